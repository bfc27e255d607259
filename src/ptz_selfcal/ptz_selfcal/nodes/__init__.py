"""Thin rclpy nodes: parameters, topics and conversions over ptz_selfcal.core."""
