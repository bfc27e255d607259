"""Frame gates: which homographies the calibration may use, and which keyframes enter the solve.

- `usable_homography`: finite, invertible, and with singular values a rotating, zooming camera can
  produce (eq. 4: H = K_j R K_0^-1 scales by at most the zoom ratio).
- `MotionGate`: keyframes of a fast move (a preset recall, not tracking) stay out of the solve: their
  homographies chain over small overlaps and drift.
- `zoom_gate`: a homography whose K (eq. 20) contradicts the zoom model at a still zoom encoder is
  refused; one whose image zoomed while the encoder was still is held out of the solve.
- `RestoredStateCheck`: whether a restored state is of this lens at all (a swap at the same image size):
  the same comparison, over the first judged frames after a restart.
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

    PASS = "pass"  # not judged
    AGREE = "agree"  # judged, and consistent
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

    @property
    def previous_zoom(self) -> float:
        return self._previous_zoom


def still_zoom_prediction(
    table: ZoomTable | None, zoom: float, previous_zoom: float, config: SessionConfig
) -> tuple[float, float] | None:
    """The zoom model's f and relative 1-sigma at this zoom encoder, or None where a frame's f cannot
    be judged against it: outside the model's learned zoom range (it extrapolates there), or while the
    encoder says the zoom moves (the encoder can lag the image)."""
    zooms = np.array([zoom, previous_zoom])
    if table is None or not np.all(np.isfinite(zooms)):
        return None
    z = table.zoom
    if not (z[0] <= zooms.min() and zooms.max() <= z[-1]):
        return None
    f_pred = np.interp(zooms, z, table.f)
    if abs(math.log(f_pred[0] / f_pred[1])) > config.zoom_gate_still:
        return None
    return float(f_pred[0]), float(np.interp(zoom, z, table.sigma_f) / f_pred[0])


def zoom_gate(
    table: ZoomTable | None,
    zoom: float,
    previous_zoom: float,
    f: float,
    previous_f: float,
    config: SessionConfig,
) -> ZoomVerdict:
    """A frame's f from its homography against the zoom model at its zoom encoder (judged where
    `still_zoom_prediction` can). HOLD when the image zoomed by more than half the floor since the
    previous frame all the same (a lagging or held encoder at the start of a fast zoom, or a wrong
    homography), REFUSE when f disagrees with the model.
    """
    predicted = still_zoom_prediction(table, zoom, previous_zoom, config)
    if predicted is None:
        return ZoomVerdict.PASS
    c = config
    if not math.isfinite(previous_f) or abs(math.log(f / previous_f)) > 0.5 * c.zoom_gate_floor:
        return ZoomVerdict.HOLD
    f_pred, relative = predicted
    if focal_disagrees(float(f), f_pred, f_pred, relative, c.zoom_gate_sigmas, c.zoom_gate_floor):
        return ZoomVerdict.REFUSE
    return ZoomVerdict.AGREE


class RestoredStateCheck:
    """Whether a restored state is of this camera and lens: a lens swapped at the same image size.

    The first `FRAMES` frames judged after a restart (a calibrated f from the homography, eq. 20, at a
    still zoom inside the saved zoom model's range) are compared with the model as the zoom gate does,
    with a smaller floor: one frame may have a wrong homography, most of several cannot, so a
    majority that disagrees means the saved model is of another lens. The verdict is given once."""

    FRAMES = 10
    SHARE = 0.7  # of the judged frames that disagree: the state is not this lens's
    FLOOR = 0.03  # in log f: well above a calibrated frame's error, below any real change of lens

    def __init__(self, config: SessionConfig) -> None:
        self.config = config
        self._ratios: list[float] = []  # f / predicted f of the judged frames
        self._disagree = 0
        self.done = False

    def judge(self, table: ZoomTable | None, zoom: float, previous_zoom: float, f: float) -> str | None:
        """Why the restored state does not fit (a sentence), once the verdict is in; else None."""
        predicted = None if self.done else still_zoom_prediction(table, zoom, previous_zoom, self.config)
        if predicted is None or not (math.isfinite(f) and f > 0.0):
            return None
        f_pred, relative = predicted
        self._ratios.append(f / f_pred)
        self._disagree += focal_disagrees(
            f, f_pred, f_pred, relative, self.config.zoom_gate_sigmas, self.FLOOR
        )
        if len(self._ratios) < self.FRAMES:
            return None
        self.done = True
        if self._disagree < self.SHARE * len(self._ratios):
            return None
        ratio = float(np.median(self._ratios))
        return (
            f"{self._disagree} of the first {len(self._ratios)} frames judged disagree with the saved "
            f"zoom model, their focal lengths {100 * (ratio - 1):+.1f} % from its f at their zoom (median)"
        )
