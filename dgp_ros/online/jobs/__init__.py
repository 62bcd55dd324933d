"""The jobs that replace the served model: refits, rebases, proofs, the freeze (no rclpy)."""
