"""The launcher: the launch file (and the shipped default, `default.yaml`), the supervision of the router and the
services as child processes, and the monitor that summarises a run."""
