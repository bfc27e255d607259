"""Typed values between the node and the session: one frame in, its calibration out."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass
class FrameInput:
    """What the calibrator knows about one image (from its HomographyStamped)."""

    stamp: float  # seconds
    H: Array | None  # reference -> this frame, full-resolution pixels (None: no homography)
    tracking_state: str  # HomographyStamped state name
    width: int
    height: int
    keyframe_id: int = 0
    reference_id: str = ""
    zoom: float = math.nan  # zoom encoder (NaN when invalid)


@dataclass
class FrameOutput:
    """The calibration of one image: what goes into its CameraInfo and FrameCalibration."""

    status: str
    K: Array
    D: Array  # plumb_bob [k1, k2, 0, 0, 0]
    R: Array | None  # orientation relative to the calibration's reference frame (None: unknown)
    sigma_f: float
    sigma_cx: float
    sigma_cy: float
    residual: float
    keyframe_id: int
    keyframe_count: int
    source: str  # where K came from: calibration / prior / zoom_model / last_good / nominal
    message: str = ""
    time_s: float = 0.0
