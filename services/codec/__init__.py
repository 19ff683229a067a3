"""Translations at the edges of the services: messages <-> the core's arrays and tasks, and ROS 2 CDR over Zenoh
(rmw_zenoh keys and attachments)."""
