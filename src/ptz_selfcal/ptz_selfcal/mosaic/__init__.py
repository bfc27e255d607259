"""Panoramic mosaics of a rotating, zooming camera (paper section 8): projection, warping, blending.

Pure numpy/OpenCV (no rclpy): `tools/mosaic.py` reads the bags and feeds frames here.
"""
