"""Security of the stack: Zenoh authentication and access control (the secrets directory), its checks before a
launch, and the TLS material."""
