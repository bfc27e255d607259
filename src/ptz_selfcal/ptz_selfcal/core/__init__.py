"""Pure algorithms: numpy, scipy and OpenCV only; no rclpy and no message types."""
