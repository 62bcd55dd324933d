"""The learner's state and its steps: what is learned, and the served model (no rclpy)."""
