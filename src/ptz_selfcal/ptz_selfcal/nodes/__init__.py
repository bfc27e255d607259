"""Thin rclpy nodes: parameters, topics and conversions over the pure packages."""
