"""Running a checked pipeline: event-time scheduling, operator tasks, hosts over Zenoh."""
