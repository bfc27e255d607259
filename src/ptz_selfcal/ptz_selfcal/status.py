"""The two status vocabularies, defined once: the calibrator's status and the tracker's state.

Each member's value is its name, so a status compares equal to the plain string that logs, reports and
diagnostics print. The message integers (FrameCalibration.status, HomographyStamped.state) are mapped to
these in one place, nodes/conversions.py; this module stays pure so that core imports it without rclpy.
"""

from __future__ import annotations

from enum import StrEnum


class CalibrationStatus(StrEnum):
    """The calibrator's status of a frame (FrameCalibration.status)."""

    INITIALISING = "INITIALISING"
    CALIBRATING = "CALIBRATING"
    CONVERGED = "CONVERGED"
    DEGENERATE_MOTION = "DEGENERATE_MOTION"
    TRACKING_LOST = "TRACKING_LOST"
    PREDICTED_FROM_ZOOM = "PREDICTED_FROM_ZOOM"
    # the keyframe matches fit the lens model far worse than the tracker's own noise: the model is wrong
    # (radial distortion not modelled, a rolling shutter), not the motion
    MODEL_MISMATCH = "MODEL_MISMATCH"


class TrackingState(StrEnum):
    """The tracker's state of a frame (HomographyStamped.state)."""

    TRACKING = "TRACKING"
    NEW_KEYFRAME = "NEW_KEYFRAME"
    RELOCALISED = "RELOCALISED"
    TRACKING_LOST = "TRACKING_LOST"
    TEXTURELESS = "TEXTURELESS"


# Statuses whose intrinsics come from a self-calibration of the current reference (section 3.3).
CALIBRATED: frozenset[CalibrationStatus] = frozenset(
    {CalibrationStatus.CALIBRATING, CalibrationStatus.CONVERGED}
)
# Statuses a solve can leave: a calibration, or its best estimate flagged for the motion or the lens model.
SOLVED: frozenset[CalibrationStatus] = CALIBRATED | {
    CalibrationStatus.DEGENERATE_MOTION,
    CalibrationStatus.MODEL_MISMATCH,
}
# Statuses of a frame without a usable homography: intrinsics, if any, come from the zoom model.
LOSS_STATUSES: frozenset[CalibrationStatus] = frozenset(
    {CalibrationStatus.PREDICTED_FROM_ZOOM, CalibrationStatus.TRACKING_LOST}
)
# Statuses that deserve a diagnostics warning: the output is not a fresh self-calibration.
WARN_STATUSES: frozenset[CalibrationStatus] = LOSS_STATUSES | {
    CalibrationStatus.DEGENERATE_MOTION,
    CalibrationStatus.MODEL_MISMATCH,
}

# Tracking states whose result carries a usable reference -> frame homography (section 2.2).
HOMOGRAPHY_STATES: frozenset[TrackingState] = frozenset(
    {TrackingState.TRACKING, TrackingState.NEW_KEYFRAME, TrackingState.RELOCALISED}
)
# Tracking states that add a keyframe to the tracker's map.
KEYFRAME_STATES: frozenset[TrackingState] = frozenset({TrackingState.NEW_KEYFRAME, TrackingState.RELOCALISED})
# Tracking states without a homography.
LOST_STATES: frozenset[TrackingState] = frozenset({TrackingState.TRACKING_LOST, TrackingState.TEXTURELESS})
