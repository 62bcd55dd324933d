"""The learner in a child process: the node's proxy, the child's loop, the ring (no rclpy)."""
