"""The runtime every service shares: the node (Zenoh session, typed pub/sub, heartbeat, logs), the settings
every service shares, opening a session, and scheduling (inboxes, CPU priority, numba threads)."""
