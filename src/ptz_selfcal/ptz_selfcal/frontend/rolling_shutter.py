"""Rolling shutter of a rotating camera, to first order in the readout time.

Forssen and Ringaby's rolling-shutter model for a rotating camera (rows exposed one after another, the
rotation interpolated at constant angular velocity across the frame): row y of an h-row frame stamped t
(the middle row's time) is exposed at t + s(y) readout, s(y) = y / (h - 1) - 1/2. A point seen at x
has moved by s(y) readout v(x) since the stamp, v the image velocity of the rotating camera (pixels/s).
The image motion of a rotation at constant rate is a one-parameter group of homographies exp(t A); A is
the logarithm of the frame's motion from the previous frame (two consecutive global-shutter
homographies), v(x) the flow of A at x. The global-shutter position at the stamp is exp(-s(y) readout A)
applied to x (global_shutter; to second order in the readout), x - readout d(x) to first order with
d(x) = s(y) v(x): one more linear unknown beside a homography's parameters (readout_step). The x^2 y and
y^3 terms of d (the perspective of a rotation's image velocity) are no homography: they make the readout
observable from two frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.geometry import apply_homography
from ptz_selfcal.frontend.homography import local_scale

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FrameMotion:
    """A frame's image motion: `back` maps its pixels to the previous frame's, taken dt seconds before."""

    back: Array  # 3x3, this frame -> the previous one (global shutter)
    dt: float  # seconds between the two stamps (> 0)
    # the previous frame's interval_generator and dt (the velocity extrapolated to the stamp)
    previous: tuple[Array, float] | None = None

    @cached_property
    def interval_generator(self) -> Array:
        """A with exp(-dt A) = back (up to scale): the mean image motion per second over the interval."""
        back = np.asarray(self.back, dtype=float)
        det = np.linalg.det(back)
        if not (self.dt > 0.0 and det > 0.0):
            return np.zeros((3, 3))
        return -_log_near_identity(back / np.cbrt(det)) / self.dt

    @cached_property
    def generator(self) -> Array:
        """The image motion per second at this frame's stamp: the interval's (its middle's) extrapolated
        linearly to the stamp with the previous interval's, when known."""
        A = self.interval_generator
        if self.previous is None or not self.previous[1] > 0.0:
            return A
        A_earlier, dt_earlier = self.previous
        return A + (A - A_earlier) * self.dt / (self.dt + dt_earlier)


def _log_near_identity(M: Array) -> Array:
    """Matrix logarithm: the Mercator series for a frame's motion (close to I: 10 terms, far below the
    noise), scipy's logm otherwise (about 30x slower)."""
    E = M - np.eye(3)
    if np.linalg.norm(E, 2) > 0.2:
        return np.real(scipy.linalg.logm(M))
    log, power = np.zeros((3, 3)), np.eye(3)
    for k in range(1, 11):
        power = power @ E
        log += power * ((-1.0) ** (k + 1) / k)
    return log


def rotation_motion(back: Array, shape: tuple[int, ...]) -> Array:
    """A frame's motion without its zoom (the scale at the image centre, taken about it): the rows are
    read under the stamp's focal length, only the rotation moves across the readout (the model)."""
    h, w = shape[:2]
    z = local_scale(back, shape)
    centre = np.array([[1.0, 0.0, (w - 1) / 2.0], [0.0, 1.0, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    return centre @ np.diag([1.0 / z, 1.0 / z, 1.0]) @ np.linalg.inv(centre) @ back


def row_fraction(y: ArrayLike, height: int, scale: float = 1.0) -> Array:
    """s(y) = y / (h - 1) - 1/2 of the full-resolution frame (h rows) for rows y of an image at `scale`
    (working / full resolution; x_work = (x_full + 0.5) scale - 0.5)."""
    y_full = (np.asarray(y, dtype=float) + 0.5) / scale - 0.5
    rows = height / scale
    return y_full / max(rows - 1.0, 1.0) - 0.5


def _flow(A: Array, pts: Array) -> Array:
    """Image velocity of the homography flow exp(t A) at pts (N, 2): d/dt of the projected point."""
    p = pts @ A[:, :2].T + A[:, 2]
    return p[:, :2] - pts * p[:, 2:]


def displacement(
    points: ArrayLike, motion: FrameMotion | None, height: int, scale: float = 1.0, at_stamp: bool = True
) -> Array:
    """d(x) = s(y) v(x) (pixels per second of readout) at `points` (N, 2) of a frame `height` rows high,
    v the image velocity of the frame's motion (its generator's flow) at the stamp, or (at_stamp False)
    the interval's mean, less noisy (no extrapolation). No motion: zeros."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if motion is None or not motion.dt > 0.0:
        return np.zeros_like(pts)
    A = motion.generator if at_stamp else motion.interval_generator
    return row_fraction(pts[:, 1], height, scale)[:, None] * _flow(A, pts)


def global_shutter(
    points: ArrayLike, motion: FrameMotion | None, readout: float, height: int, scale: float = 1.0
) -> Array:
    """Positions at the stamp of a global-shutter camera: exp(-u A) x with u = s(y) readout, to second
    order in u (first order: x - readout d(x)). No motion or readout: the points."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if motion is None or readout == 0.0 or not motion.dt > 0.0:
        return pts
    A = motion.generator
    u = readout * row_fraction(pts[:, 1], height, scale)[:, None]
    x = np.column_stack([pts, np.ones(len(pts))])
    Ax = x @ A.T
    q = x - u * Ax + 0.5 * u**2 * (Ax @ A.T)
    return q[:, :2] / q[:, 2:]


def _normaliser(points: Array) -> tuple[float, Array]:
    """(scale, centre) of the similarity moving the centroid to 0 and the mean distance to sqrt(2)."""
    centre = points.mean(axis=0)
    return math.sqrt(2.0) / max(float(np.mean(np.linalg.norm(points - centre, axis=1))), 1e-12), centre


def readout_step(
    H: ArrayLike,
    src: ArrayLike,
    dst: ArrayLike,
    d_src: ArrayLike,
    d_dst: ArrayLike,
    readout: float = 0.0,
    iterations: int = 2,
) -> tuple[float, float, Array]:
    """Joint least squares over (H, r) of |H (src - (r - readout) d_src) - (dst - (r - readout) d_dst)|^2
    on inliers, by Gauss-Newton from (H, readout): (r, its 1-sigma from the residual, H). src, dst: the
    points corrected for `readout` (global_shutter; the observed ones for 0); d_src, d_dst: their
    displacement() in their own frames (the derivative of the correction)."""
    src, dst = np.asarray(src, float).reshape(-1, 2), np.asarray(dst, float).reshape(-1, 2)
    d_src, d_dst = np.asarray(d_src, float).reshape(-1, 2), np.asarray(d_dst, float).reshape(-1, 2)
    n = len(src)
    if n < 6:
        return readout, math.inf, np.asarray(H, float)
    # normalised coordinates for conditioning (displacements scale with the points)
    ks, cs = _normaliser(src)
    kd, cd = _normaliser(dst)
    Ts = np.array([[ks, 0.0, -ks * cs[0]], [0.0, ks, -ks * cs[1]], [0.0, 0.0, 1.0]])
    Td = np.array([[kd, 0.0, -kd * cd[0]], [0.0, kd, -kd * cd[1]], [0.0, 0.0, 1.0]])
    s, t, ds, dd = (src - cs) * ks, (dst - cd) * kd, d_src * ks, d_dst * kd
    Hn = Td @ np.asarray(H, float) @ np.linalg.inv(Ts)
    Hn = Hn / Hn[2, 2]
    r = float(readout)
    sigma = math.inf
    for _ in range(max(iterations, 1)):
        a = s - (r - readout) * ds
        w = a @ Hn[2, :2] + Hn[2, 2]
        proj = apply_homography(Hn, a)
        res = (proj - (t - (r - readout) * dd)).ravel()
        A = np.zeros((2 * n, 9))
        A[0::2, 0:2] = a / w[:, None]
        A[0::2, 2] = 1.0 / w
        A[1::2, 3:5] = a / w[:, None]
        A[1::2, 5] = 1.0 / w
        A[0::2, 6:8] = -proj[:, :1] * a / w[:, None]
        A[1::2, 6:8] = -proj[:, 1:2] * a / w[:, None]
        # d proj / d a (2x2 per point) applied to -d_src, plus d_dst: the readout's column
        Ja = (Hn[None, :2, :2] - proj[:, :, None] * Hn[None, 2, :2][:, None, :]) / w[:, None, None]
        A[:, 8] = (-np.einsum("nij,nj->ni", Ja, ds) + dd).ravel()
        norms = np.linalg.norm(A, axis=0)
        if not norms[8] > 0.0:
            return readout, math.inf, np.asarray(H, float)
        norms[norms == 0.0] = 1.0
        An = A / norms
        step, *_ = np.linalg.lstsq(An, -res, rcond=None)
        step /= norms
        Hn = Hn + np.append(step[:8], 0.0).reshape(3, 3)
        r += float(step[8])
        dof = max(2 * n - 9, 1)
        after = res + A @ step  # the linearised residual at the new estimate
        var = float(after @ after) / dof
        # the readout's information: its column's part no change of H explains (a zoom's or a shear's
        # displacements are homographies: no information, infinite sigma)
        Q, _ = np.linalg.qr(An[:, :8])
        g = An[:, 8]
        unexplained = float(np.sum((g - Q @ (Q.T @ g)) ** 2))
        sigma = math.sqrt(var / unexplained) / norms[8] if unexplained > 1e-9 else math.inf
    H_out = np.linalg.inv(Td) @ Hn @ Ts
    return r, sigma, H_out / H_out[2, 2]


def combine(estimates: ArrayLike, sigmas: ArrayLike) -> tuple[float, float]:
    """Per-frame estimates with their sigmas -> (weighted median, sigma): inverse-variance weights (the
    sigmas floored at half their median), the sigma inflated by the estimates' robust scatter about the
    median (outliers, model error)."""
    x, s = np.asarray(estimates, float), np.asarray(sigmas, float)
    keep = np.isfinite(x) & np.isfinite(s) & (s > 0.0)
    x, s = x[keep], s[keep]
    if len(x) == 0:
        return math.nan, math.inf
    # no frame weighs more than 4 typical ones: a frame's sigma can be overconfident (its residual
    # misses a systematic error), and one such frame would be the weighted median alone
    s = np.maximum(s, 0.5 * float(np.median(s)))
    w = 1.0 / s**2
    order = np.argsort(x)
    cumulative = np.cumsum(w[order])
    median = float(x[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])
    spread = 1.4826 * float(np.median(np.abs(x - median) / s)) if len(x) >= 3 else 1.0
    return median, max(spread, 1.0) / math.sqrt(float(w.sum()))


def significant(readout: float, sigma: float, floor: float) -> bool:
    """Whether an estimated readout is a rolling shutter: above 3 sigma and above `floor` (seconds);
    negative readouts are rows read bottom to top (a flipped image)."""
    return math.isfinite(readout) and abs(readout) > max(3.0 * sigma, floor)


# ----------------------------------------------------------------------------- the tracker's estimate
MIN_READOUT = 0.004  # seconds: an estimate below this is not applied (a global shutter, or negligible)
MIN_FRAMES = 5  # frames combined at least before an estimate is applied
MIN_GROUPS = 2  # ... from this many keyframes at least (frames of one keyframe share its errors)
MAX_FRAME_ZOOM = 0.03  # frames zooming more than this from the previous one do not estimate (first order)
# Frames this close to their keyframe do not estimate: the two velocities are one interval apart, the
# readout's signal (their difference's) is below their errors (such frames estimate far too low).
MIN_KEYFRAME_GAP = 2
MAX_FRAME_SIGMA = 0.01  # seconds: a frame estimating worse than this has too little motion to count
SETTLE_FRAMES = 40  # frames combined at least before the estimate settles
SETTLE_RELATIVE = 0.03  # settled when sigma is below this share of the estimate (of MIN_READOUT: none)
MAX_ESTIMATES = 400  # settled after this many frames in any case (bounded memory and time)


class ReadoutEstimator:
    """The readout time in use: a known one (>= 0; 0 = global shutter), or estimated from the tracked
    frames' readout_step results, combined (combine) until settled, then no longer estimated. An
    estimate is applied once significant(), else 0: a global-shutter camera is tracked as without it.
    Frames tracked against one keyframe share its errors: the sigma counts keyframes (groups), not
    frames, as independent (inflated by sqrt(frames / groups))."""

    def __init__(self, readout: float) -> None:
        self.known = readout >= 0.0
        self.estimate = float(readout) if self.known else math.nan
        self.sigma = 0.0 if self.known else math.inf
        self.settled = self.known
        self.frames = 0
        self._estimates: list[float] = []
        self._sigmas: list[float] = []
        self._groups: set[int] = set()

    @property
    def enabled(self) -> bool:
        """Whether rolling-shutter geometry is used at all (not a known global shutter)."""
        return not (self.known and self.estimate == 0.0)

    @property
    def applied(self) -> float:
        """The readout (s) points are corrected with now (0: none)."""
        if self.known:
            return self.estimate
        applies = (self.frames >= MIN_FRAMES and len(self._groups) >= MIN_GROUPS) or self.settled
        applies = applies and significant(self.estimate, self.sigma, MIN_READOUT)
        return self.estimate if applies else 0.0

    def add(self, readout: float, sigma: float, group: int = 0) -> None:
        """One frame's readout_step result, tracked against keyframe `group` (ignored once settled or
        when it carries no information)."""
        if self.settled or not (math.isfinite(readout) and 0.0 < sigma <= MAX_FRAME_SIGMA):
            return
        self._estimates.append(readout)
        self._sigmas.append(sigma)
        self._groups.add(group)
        self.frames = len(self._estimates)
        self.estimate, sigma = combine(self._estimates, self._sigmas)
        self.sigma = sigma * math.sqrt(self.frames / len(self._groups))
        scale = abs(self.estimate) if significant(self.estimate, self.sigma, MIN_READOUT) else MIN_READOUT
        if self.frames >= MAX_ESTIMATES or (
            self.frames >= SETTLE_FRAMES and self.sigma < SETTLE_RELATIVE * scale
        ):
            self.settled = True
            self._estimates, self._sigmas, self._groups = [], [], set()
