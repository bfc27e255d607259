"""The zoom model: zoom encoder -> (K, D), and the camera_calibration export.

model (the learned model and its file), spline (its penalised fits), rate (the encoder's rate, for
the lag), camera_calibration (per-zoom ROS calibration files).
"""

from ptz_selfcal.zoom.camera_calibration import camera_calibration_yaml, write_camera_calibrations
from ptz_selfcal.zoom.model import ZoomModel, ZoomModelError, ZoomPrediction, fit_zoom_model
from ptz_selfcal.zoom.rate import ZoomRate

__all__ = [
    "ZoomModel",
    "ZoomModelError",
    "ZoomPrediction",
    "ZoomRate",
    "camera_calibration_yaml",
    "fit_zoom_model",
    "write_camera_calibrations",
]
