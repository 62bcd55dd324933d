"""The message path: runs in the node's thread and never waits (no rclpy)."""
