"""Frame gates: which homographies the calibration may use, and which keyframes enter the solve.

- `usable_homography`: finite, invertible, and with singular values a rotating, zooming camera can
  produce (eq. 4: H = K_j R K_0^-1 scales by at most the zoom ratio).
- `MotionGate`: keyframes of a fast move (a preset recall, not tracking) stay out of the solve: their
  homographies chain over small overlaps and drift.
- `zoom_gate`: a homography whose K (eq. 20) contradicts the zoom model at a still zoom encoder is
  refused; one whose image zoomed while the encoder was still is held out of the solve.
"""

from __future__ import annotations

import enum
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.geometry import image_motion
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.work import ZoomTable
from ptz_selfcal.selfcal.transfer import focal_disagrees

Array = NDArray[np.float64]


class ZoomVerdict(enum.Enum):
    """The zoom gate's verdict on a frame's homography."""

    PASS = "pass"  # consistent, or not judged
    HOLD = "hold"  # the frame keeps its K, its keyframe stays out of the solve
    REFUSE = "refuse"  # a wrong homography: no K through it, never a keyframe of the solve


def usable_homography(H: ArrayLike | None, width: int, height: int, max_focal_ratio: float) -> Array | None:
    """H scaled to unit determinant, or None when it cannot come from a rotating, zooming camera."""
    if H is None:
        return None
    H = np.asarray(H, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(H)):
        return None
    det = float(np.linalg.det(H))
    if not (math.isfinite(det) and det != 0.0 and abs(det) > 1e-12 * float(np.max(np.abs(H))) ** 3):
        return None
    H = H / np.cbrt(det)
    # centred and scaled by the width, such a homography has singular values within the zoom ratio
    w = float(max(width, 1))
    N = np.array([[1 / w, 0, -0.5 * width / w], [0, 1 / w, -0.5 * height / w], [0, 0, 1]])
    s = np.linalg.svd(N @ H @ np.linalg.inv(N), compute_uv=False)
    if not (np.all(np.isfinite(s)) and s[0] / max(s[2], 1e-300) < max_focal_ratio**2):
        return None
    return H


class MotionGate:
    """Whether the image moved faster than max_keyframe_motion image widths per second since the
    previous frame with a homography on the same reference (per second of stamps: frames shed
    upstream do not count)."""

    def __init__(self, max_motion: float) -> None:
        self.max_motion = max_motion
        self._previous: tuple[str | None, float, Array] | None = None  # (reference, stamp, H)

    def fast(self, reference: str | None, stamp: float, H: Array, image_size: tuple[int, int] | None) -> bool:
        previous, self._previous = self._previous, (reference, float(stamp), H)
        if previous is None or previous[0] != reference or image_size is None:
            return False
        dt = float(stamp) - previous[1]
        dt = dt if math.isfinite(dt) and dt > 0.0 else 1.0 / 30.0
        return image_motion(previous[2], H, *image_size) / dt > self.max_motion

    def forget(self) -> None:
        self._previous = None


class ZoomGate:
    """zoom_gate with the previous frame's zoom encoder and f (from its homography) remembered."""

    def __init__(self, config: SessionConfig) -> None:
        self.config = config
        self._previous_zoom = math.nan
        self._previous_f = math.nan  # NaN: the previous frame had no calibrated f

    def judge(self, table: ZoomTable | None, zoom: float, f: float) -> ZoomVerdict:
        previous_f, self._previous_f = self._previous_f, float(f)
        return zoom_gate(table, zoom, self._previous_zoom, float(f), previous_f, self.config)

    def no_focal(self) -> None:
        """This frame has no calibrated f: the next one is not compared with it."""
        self._previous_f = math.nan

    def frame_done(self, zoom: float) -> None:
        self._previous_zoom = float(zoom)


def zoom_gate(
    table: ZoomTable | None,
    zoom: float,
    previous_zoom: float,
    f: float,
    previous_f: float,
    config: SessionConfig,
) -> ZoomVerdict:
    """A frame's f from its homography against the zoom model at its zoom encoder.

    Judged only inside the model's learned zoom range (outside it the model extrapolates) and while
    the encoder says the zoom is still: while zooming the encoder can lag the image. HOLD when the
    image zoomed by more than half the floor since the previous frame all the same (a lagging or held
    encoder at the start of a fast zoom, or a wrong homography), REFUSE when f disagrees with the model.
    """
    zooms = np.array([zoom, previous_zoom])
    if table is None or not np.all(np.isfinite(zooms)):
        return ZoomVerdict.PASS
    z = table.zoom
    if not (z[0] <= zooms.min() and zooms.max() <= z[-1]):
        return ZoomVerdict.PASS
    f_pred = np.interp(zooms, z, table.f)
    c = config
    if abs(math.log(f_pred[0] / f_pred[1])) > c.zoom_gate_still:
        return ZoomVerdict.PASS
    if not math.isfinite(previous_f) or abs(math.log(f / previous_f)) > 0.5 * c.zoom_gate_floor:
        return ZoomVerdict.HOLD
    relative = float(np.interp(zoom, z, table.sigma_f) / f_pred[0])
    f_pred0 = float(f_pred[0])
    if focal_disagrees(float(f), f_pred0, f_pred0, relative, c.zoom_gate_sigmas, c.zoom_gate_floor):
        return ZoomVerdict.REFUSE
    return ZoomVerdict.PASS
