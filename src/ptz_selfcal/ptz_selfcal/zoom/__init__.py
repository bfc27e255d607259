"""The zoom model: zoom encoder -> (K, D), and the camera_calibration export."""
