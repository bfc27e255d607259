"""Typed values between the frame path and the keyframe calibration (the two halves of a session).

The frame path (online/session.CalibratorSession.process) hands a `WorkBatch` to the keyframe
calibration (online/keyframe_calibration.KeyframeCalibration.apply), which answers with a
`WorkResult` carrying an immutable `CalibrationSnapshot`. Each value belongs to one epoch (one
calibration reference): a result of an older epoch than the frame path's is dropped, so a solve that
was running when the reference changed can never publish the old reference's calibration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.online.incremental import IncrementalCalibrator
from ptz_selfcal.online.keyframe_solver import KeyframeMatchSet
from ptz_selfcal.status import CalibrationStatus
from ptz_selfcal.zoom.model import ZoomModel

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PendingKeyframe:
    """A keyframe the frame path accepted for the solve, or an ordinary frame it chose for the
    information it adds (online/selection.py: negative ids)."""

    keyframe_id: int
    H: Array  # reference -> keyframe, unit determinant
    stamp: float
    zoom: float  # zoom encoder at the keyframe (NaN when invalid)
    zoom_rate: float  # zoom encoder counts / s at the keyframe: the zoom model learns the encoder's lag
    tracked: bool = True  # a tracker keyframe; False: an ordinary frame chosen for its information
    # an ordinary frame: (its keyframe, H keyframe -> frame), so that its homography follows the
    # keyframe's when the lens correction re-corrects the keyframes
    anchor: tuple[int, Array] | None = None


@dataclass(frozen=True)
class WorkBatch:
    """What the frame path collected since the last batch."""

    epoch: int  # the frame path's reference epoch: a new epoch resets the keyframe calibration
    image_size: tuple[int, int] | None
    keyframes: tuple[PendingKeyframe, ...] = ()
    matches: tuple[KeyframeMatchSet, ...] = ()
    paced: bool = True  # re-optimisations keep to max_solve_duty; False: whenever due (replays)


@dataclass(frozen=True)
class ZoomTable:
    """The zoom model sampled over its learned range, for the frame path's zoom gate (np.interp)."""

    zoom: Array
    f: Array
    sigma_f: Array


@dataclass(frozen=True)
class CalibrationSnapshot:
    """The keyframe calibration as the frame path reads it; never mutated after publication."""

    epoch: int
    calibrator: IncrementalCalibrator  # a read-only copy: frame_intrinsics (eq. 20) of any frame
    calibrated: bool
    state: CalibrationStatus
    message: str
    residual: float
    keyframe_count: int
    sigma_pp: tuple[float, float] = (math.nan, math.nan)
    # per keyframe of the solve: (H reference -> keyframe (unit det), K, R relative to the reference)
    keyframes: dict[int, tuple[Array, Array, Array]] = field(default_factory=dict)
    zoom_table: ZoomTable | None = None
    shared_lam: float | None = None  # a fixed lens's one division coefficient (None: not estimated)


@dataclass(frozen=True)
class WorkResult:
    """The keyframe calibration's answer to one batch."""

    epoch: int
    solved: bool
    snapshot: CalibrationSnapshot | None  # None: nothing new for the frame path
    zoom_model: ZoomModel | None  # a read-only copy when the model changed (None: unchanged)
    zoom_ready: bool
    counters: dict[str, int]
    warnings: tuple[str, ...]
    solve_ms: tuple[float, float]  # median, max of the recent solves (NaN when none)
    backlog: int = 0  # keyframes a spent budget left for the next batch
    needs_refinement: bool = False  # a re-optimisation is due
