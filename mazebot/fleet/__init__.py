"""A fleet of robots over Zenoh: the robot\x27s publisher, the laptop\x27s watcher (docs/fleet.md)."""
