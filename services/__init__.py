"""The processes: thin shells over `gpmppi` that decode messages, call the core and encode."""
