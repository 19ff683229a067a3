"""The processes: thin shells over `gpmppi` that decode messages, call the core and encode. Each service is one
module here (`services/<name>.py`, run by `services.run`); the code they share is in packages by role: runtime,
codec, recording, view, security, launch (docs/development.md)."""
