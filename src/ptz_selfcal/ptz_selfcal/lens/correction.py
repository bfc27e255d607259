"""The calibrator's online radial-distortion state: homographies on corrected coordinates (section 7).

Section 7 of the paper shows that self-calibration on homographies of DISTORTED points over-estimates
the focal length (and under-estimates the motion), and suggests "correct the homographies, then
self-calibrate". The tracker's homography reference -> keyframe is a CHAIN of keyframe-to-keyframe
homographies, each fitted to distorted points: every link absorbs part of the distortion into a
projective error, and the errors compound along the chain. Undistorting a grid mapped through that
chained homography (distortion_estimation.undistorted_homography) therefore does not recover the
undistorted homography: on the issue-6 bag (1280x720, 12% corner shift at the wide end) it leaves a
median 9 px transfer error against the truth, and self-calibration on it misses f by ~7%. Recomputing
every LINK from its raw inlier correspondences after undistorting them, and chaining the corrected
links from the reference, gives 0.7 px and f within 0.1% (benchmarks/distortion.py, first part).

`LensCorrection` does exactly that, online and in bounded time:
- `add_match(newer, older, pts_newer, pts_older)`: the tracker's KeyframeMatches (raw, distorted,
  full-resolution inliers). They feed lens/estimation.KeyframeDistortionEstimator (one
  division coefficient per keyframe jointly with the pair homographies; the lam(f) curve) and, for each
  keyframe, its best link to an older keyframe (most points) for the chain.
- `set_keyframe(id, f, centre)`: the calibrator's current focal length / principal point of a keyframe.
  Before any calibration a prior (nominal focal length) is good enough: the images constrain the
  pixel-space coefficient kappa = lam / f^2 about the distortion centre, which does not depend on f;
  f only places a keyframe on the lam(f) curve, refined as the calibration converges.
- `update()` (worker thread, only when new matches arrived): every `solve_every` matches the joint
  estimation (one solve over at most `max_matches` matches, ~0.1-0.4 s), in between only the new
  links are chained with the current estimates (milliseconds); the corrected homography reference ->
  keyframe of every keyframe is its chain of corrected links (DLT + LM on undistorted inliers, cached
  per link until its coefficients change). Keyframes that left the estimator's window keep their last
  estimate; new ones take their ancestor's, carried over the zoom ratio. Nothing runs per frame.
- Per frame (`frame_homography`): the corrected H reference -> frame is the frame's short
  keyframe -> frame homography (tracked on distorted points, corrected by an 8x8-grid refit) composed
  with the keyframe's corrected chain. Measured on the issue-6 bag (benchmarks/distortion.py): without
  the refit the focal p90 is 3.3% instead of 1.3% (median unchanged, 0.6%), so the per-frame K does
  need it; its error is second order (0.45 px for a frame 1 deg and 3% zoom from its keyframe,
  tests/unit/test_lens_correction.py) and it costs ~1 ms.
- `plumb_bob(K)`: D = [k1, k2, 0, 0, 0] of lam(f) at the frame's focal length for CameraInfo
  (distortion.division_to_plumb_bob, consistent with K: OpenCV undistortion with (K, D) reproduces the
  division model); cached by (lam, f, principal point) so a steady zoom costs a dictionary lookup.
- `undistort_points(id, pts)`: keyframe matches on corrected coordinates for the bundle adjustment
  (section 5).

The distortion centre. In rotation-only data it is nearly interchangeable with the principal point
when the two are estimated apart (self-calibration on corrected homographies follows the assumed
centre almost one to one; feeding its principal point back as the centre diverged, -210 px). So the
keyframe bundle adjustment estimates them as ONE point, with the distortion, on the raw keyframe
matches (bundle/adjust.py distortion="curve", online/session.KeyframeBundleSolver with
`SessionLensHook` as its `lens`): no corrected data enters it, so there is no feedback loop. Once its
principal point's 1-sigma is below `centre_gate_px` the hook makes it the centre here (`set_centre`)
and the adjustment's per-keyframe coefficients and lam(f) curve replace the estimator's (`set_joint`).
On the issue-6 bag (principal point 18 px off centre) the adjustment alone recovers it within ~1 px
(benchmarks/distortion.py part 1), where holding the centre at the image centre left ~20 px and a
focal error ~0.6%. Until the gate opens the centre is the image centre. `joint_bundle=False` keeps the
older path (corrected matches to the adjustment, centre at the image centre or, with
`centre_from_calibration`, the calibrated principal point).

While the worker is behind (a solve takes ~0.2-0.7 s, keyframes come every few frames at the tele
end), a new keyframe's first link is corrected on arrival (`provisional_link`, on the parent's chain or
its provisional one): without it the keyframe's frames use a long tracked span from the newest chained
keyframe, 35-70% off on the issue-6 bag.

Pure: numpy + the core modules, no rclpy. Not thread-safe by itself: `update` builds a new immutable
`LensSnapshot` and swaps it in one assignment, so a frame thread may read `snapshot` concurrently.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import division_distort, division_to_plumb_bob, division_undistort
from ptz_selfcal.camera.geometry import normalise_homography
from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.frontend.homography import estimate_homography
from ptz_selfcal.lens.estimation import (
    DistortionVsFocal,
    KeyframeDistortionEstimator,
    undistorted_homography,
)

Array = NDArray[np.float64]


def zoom_ratio(H: ArrayLike) -> float:
    """f_j / f_i of a homography K_j R K_i^-1 between nearby views: sqrt(det) of its affine part
    (exact for R about the optical axis or small; a first-order estimate otherwise)."""
    H = np.asarray(H, dtype=float)
    if H[2, 2] == 0.0:
        return math.nan
    A = H[:2, :2] / H[2, 2] - np.outer(H[:2, 2], H[2, :2]) / H[2, 2] ** 2
    det = float(np.linalg.det(A))
    return math.sqrt(det) if det > 0.0 else math.nan


@dataclass
class _Link:
    """Inliers between a keyframe and an older keyframe (raw distorted pixels)."""

    parent: int
    pts: Array  # in the keyframe
    parent_pts: Array  # in the parent


@dataclass(frozen=True)
class LensSnapshot:
    """Immutable distortion state for the frame thread (swapped atomically by `update`)."""

    kappa: dict[int, float]  # keyframe -> lam / f^2 (pixel-space division coefficient)
    centre: dict[int, Array]  # keyframe -> distortion centre used for it (principal point)
    focal: dict[int, float]  # keyframe -> focal length the estimate was made at
    H: dict[int, Array]  # keyframe -> corrected H reference -> keyframe (unit determinant)
    curve: DistortionVsFocal
    rms_px: float  # symmetric transfer error of the joint solve
    rms_uncorrected_px: float  # the same with lam = 0

    def lam_at(self, f: float) -> float:
        """lam(f) from the curve (0.0 when not fitted)."""
        if not self.curve.fitted() or not (f > 0.0):
            return 0.0
        lam = float(self.curve.predict(f))
        return lam if math.isfinite(lam) else 0.0

    def lam_of(self, keyframe_id: int, f: float) -> float:
        """The keyframe's own estimate at focal length f (lam = kappa f^2), else the curve."""
        kappa = self.kappa.get(int(keyframe_id))
        return self.lam_at(f) if kappa is None else kappa * f * f


@dataclass
class LensCorrectionStats:
    updates: int = 0
    solves: int = 0
    failures: int = 0
    links: int = 0
    chained: int = 0  # live keyframes with a corrected chain after the last update
    last_update_ms: float = math.nan
    messages: list[str] = field(default_factory=list)


class LensCorrection:
    """Online distortion state of the calibrator (see the module docstring)."""

    def __init__(
        self,
        width: int,
        height: int,
        nominal_focal: float,
        max_matches: int = 24,
        max_points_per_match: int = 120,
        max_keyframes: int = 512,
        min_matches: int = 2,
        solve_every: int = 4,
        tracker_below_px: float = 1.0,
        plumb_bob_cache: int = 512,
        seed: int = 0,
    ) -> None:
        self.width, self.height = int(width), int(height)
        self.nominal_focal = float(nominal_focal)
        self.centre0 = np.array([(width - 1) / 2.0, (height - 1) / 2.0])  # default distortion centre
        self.min_matches = int(min_matches)
        self.solve_every = max(int(solve_every), 1)
        self.tracker_below_px = float(tracker_below_px)
        self.max_keyframes = int(max_keyframes)
        self.estimator = KeyframeDistortionEstimator(
            width, height, max_matches=max_matches, max_points_per_match=max_points_per_match, seed=seed
        )
        self.reference_id: int | None = None
        self._links: OrderedDict[int, _Link] = OrderedDict()
        self._focal: dict[int, float] = {}
        self._centre: dict[int, Array] = {}
        self._H_chain: OrderedDict[int, Array] = OrderedDict()  # corrected chains (kept when retired)
        self._H_raw: OrderedDict[int, Array] = OrderedDict()  # keyframe -> tracked H reference -> keyframe
        self._raw_chain: OrderedDict[int, Array] = OrderedDict()  # the chains on raw (distorted) points
        self._kappa_known: OrderedDict[int, float] = OrderedDict()  # keyframe -> last estimated kappa
        self._link_H: dict[int, tuple[tuple[float, ...], Array]] = {}  # child -> (inputs, corrected link H)
        self._new_matches = 0  # since the last joint solve
        self._unchained = 0  # since the last chaining
        self._plumb_bob: OrderedDict[tuple[int, int, int, int], tuple[float, float]] = OrderedDict()
        self._plumb_bob_size = int(plumb_bob_cache)
        self.snapshot: LensSnapshot | None = None
        self.stats = LensCorrectionStats()
        # keyframe -> (parent, corrected link H parent -> keyframe, kappa, centre): a new keyframe's
        # first link corrected at once by `provisional_link` until the worker chains it
        self._provisional: OrderedDict[int, tuple[int, Array, float, Array, float]] = OrderedDict()
        # the joint adjustment's estimate (set_joint): per-keyframe kappa and the lam(f) curve, which
        # take precedence over the estimator's own
        self._joint_kappa: dict[int, float] = {}
        self._joint_curve: DistortionVsFocal | None = None

    # ---- inputs ------------------------------------------------------------------------------------
    def set_reference(self, keyframe_id: int) -> None:
        """The keyframe whose pixels the homographies start from (H = I)."""
        if self.reference_id != int(keyframe_id):
            self.reference_id = int(keyframe_id)
            self._H_chain.clear()
            self._raw_chain.clear()
            self._raw_chain[self.reference_id] = np.eye(3)

    def add_keyframe(self, keyframe_id: int, H_raw: ArrayLike) -> None:
        """A new keyframe's tracked homography reference -> keyframe (its NEW_KEYFRAME message)."""
        H = np.asarray(H_raw, dtype=float).reshape(3, 3)
        if not np.all(np.isfinite(H)):
            return
        kid = int(keyframe_id)
        if self.reference_id is None:
            self.set_reference(kid)
        self._H_raw[kid] = H
        self._H_raw.move_to_end(kid)
        while len(self._H_raw) > self.max_keyframes:
            self._H_raw.popitem(last=False)

    def set_keyframe(self, keyframe_id: int, f: float, centre: ArrayLike | None = None) -> None:
        """Current focal length (and principal point = distortion centre) of a keyframe."""
        if not (math.isfinite(f) and f > 0.0):
            return
        kid = int(keyframe_id)
        c = self.centre0 if centre is None else np.asarray(centre, dtype=float).reshape(2)
        if not np.all(np.isfinite(c)):
            c = self.centre0
        self._focal[kid] = float(f)
        self._centre[kid] = c
        self.estimator.set_keyframe(kid, float(f), c)

    def set_joint(self, focal: dict[int, float], lam: dict[int, float]) -> bool:
        """The keyframe bundle adjustment's distortion (raw points, about its principal point, which
        `set_centre` made the centre): its per-keyframe lam at its focal lengths become the keyframes'
        coefficients, and the lam(f) curve is refitted through them (DistortionVsFocal, the same family
        as the adjustment's). The next `update` rechains with them. False when unusable."""
        f = np.array([focal[k] for k in lam if k in focal], dtype=float)
        la = np.array([lam[k] for k in lam if k in focal], dtype=float)
        ok = np.isfinite(f) & np.isfinite(la) & (f > 0.0)
        if ok.sum() < 2:
            return False
        try:
            curve = DistortionVsFocal(self.width, self.height).fit(f[ok], la[ok])
        except (ValueError, np.linalg.LinAlgError):
            return False
        self._joint_kappa = {int(k): lam[k] / focal[k] ** 2 for k in lam if k in focal and focal[k] > 0.0}
        self._joint_curve = curve
        return True

    def set_centre(self, centre: ArrayLike) -> None:
        """One distortion centre for every keyframe, known and new (the joint adjustment's principal
        point); the next `update` re-estimates the coefficients about it."""
        c = np.asarray(centre, dtype=float).reshape(2)
        if not np.all(np.isfinite(c)):
            return
        self.centre0 = c.copy()
        for kid, f in list(self._focal.items()):
            self.set_keyframe(kid, f, c)

    def add_match(
        self, keyframe_id: int, other_keyframe_id: int, pts: ArrayLike, other_pts: ArrayLike
    ) -> bool:
        """Raw inliers between a keyframe and an older one (KeyframeMatches); False if unusable."""
        a = np.asarray(pts, dtype=float).reshape(-1, 2)
        b = np.asarray(other_pts, dtype=float).reshape(-1, 2)
        i, j = int(keyframe_id), int(other_keyframe_id)
        if len(a) != len(b) or len(a) < 12 or i == j or not (np.isfinite(a).all() and np.isfinite(b).all()):
            return False
        try:
            self.estimator.add_match(i, j, a, b)
        except ValueError:
            return False
        # keyframes get their focal length from the caller; until then the nominal one
        for kid in (i, j):
            if kid not in self._focal:
                self.set_keyframe(kid, self.nominal_focal, None)
        # the chain link of the newer keyframe: the older partner with most points
        child, parent, pc, pp = (i, j, a, b) if i > j else (j, i, b, a)
        old = self._links.get(child)
        if old is None or len(pc) > len(old.pts):
            self._links[child] = _Link(parent, pc, pp)
            self._links.move_to_end(child)
            while len(self._links) > self.max_keyframes:
                self._links.popitem(last=False)
        self._new_matches += 1
        self._unchained += 1
        return True

    @property
    def pending(self) -> int:
        """Matches received since the last update."""
        return self._unchained

    # ---- worker ------------------------------------------------------------------------------------
    def update(self, force: bool = False) -> bool:
        """Re-estimate distortion and the corrected keyframe chains; True when the snapshot changed.

        The joint estimation (the expensive part, ~0.1-1 s) runs on the first call and then once every
        `solve_every` new matches (or when forced); in between only the new links are chained with the
        current estimates (new keyframes take lam from the curve), a few milliseconds, so a worker that
        falls behind never leaves new keyframes without a corrected homography.
        """
        if self._unchained == 0 and not force:
            return False
        start = time.perf_counter()
        prev = self.snapshot
        solve = force or prev is None or self._new_matches >= self.solve_every
        if solve:
            try:
                result = self.estimator.solve(min_matches=self.min_matches)
            except (ValueError, np.linalg.LinAlgError) as exc:
                self.stats.failures += 1
                self.stats.messages = [*self.stats.messages[-9:], f"distortion solve failed: {exc}"]
                return False
            if result is None:
                return False
            self._new_matches = 0
            # keyframes whose matches left the estimator's bounded window keep their last estimate
            known = self._kappa_known
            for kid, f in self._focal.items():
                lam = self.estimator.lam(kid)
                if lam is not None and math.isfinite(lam):
                    known[kid] = lam / (f * f)
                    known.move_to_end(kid)
            while len(known) > self.max_keyframes:
                known.popitem(last=False)
            kappa: dict[int, float] = dict(known)
            curve = DistortionVsFocal.from_dict(self.estimator.curve.to_dict())
            rms, rms0 = float(result.rms), float(result.rms_undistorted_model)
            self.stats.solves += 1
        else:
            assert prev is not None
            kappa, curve, rms, rms0 = dict(prev.kappa), prev.curve, prev.rms_px, prev.rms_uncorrected_px
        kappa.update(self._joint_kappa)
        if self._joint_curve is not None:
            curve = self._joint_curve
        self._unchained = 0
        snap = LensSnapshot(kappa, dict(self._centre), dict(self._focal), {}, curve, rms, rms0)
        self._rechain(snap)
        self.snapshot = LensSnapshot(
            snap.kappa, snap.centre, snap.focal, self._published(snap), curve, rms, rms0
        )
        self.stats.updates += 1
        self.stats.links = len(self._links)
        self.stats.last_update_ms = 1e3 * (time.perf_counter() - start)
        return True

    def _kappa_for(self, snap: LensSnapshot, kid: int) -> tuple[float, Array]:
        """A keyframe's pixel-space coefficient: its estimate, else its nearest estimated ancestor's
        carried over the zoom change between them (consecutive keyframes differ little in zoom; a new
        keyframe's focal length may still be the nominal one, which would misplace it on the curve),
        else the curve."""
        kappa = snap.kappa.get(kid)
        ancestor, steps = kid, 0
        while kappa is None and ancestor in self._links and steps < 16:
            ancestor, steps = self._links[ancestor].parent, steps + 1
            kappa = snap.kappa.get(ancestor)
            if kappa is not None and kid in self._H_raw and ancestor in self._H_raw:
                ratio = zoom_ratio(self._H_raw[kid] @ np.linalg.inv(self._H_raw[ancestor]))
                kappa = self._carry(snap, kappa, ancestor, ratio)
        if kappa is None:
            f = self._focal.get(kid, self.nominal_focal)
            kappa = snap.lam_at(f) / (f * f)
        return kappa, self._centre.get(kid, self.centre0)

    def _carry(
        self, snap: LensSnapshot, kappa: float, kid: int, ratio: float, f: float | None = None
    ) -> float:
        """kappa of keyframe `kid` (focal length f, default its known one) carried to a view zoomed by
        `ratio` (f_new / f_kid): the lam(f) curve's relative change when it is fitted, else distortion
        shrinking as 1/f (kappa ~ 1/f)."""
        if not (math.isfinite(ratio) and ratio > 0.0) or abs(ratio - 1.0) < 1e-4:
            return kappa
        if f is None or not (math.isfinite(f) and f > 0.0):
            f = self._focal.get(kid, self.nominal_focal)
        span = snap.curve.f_range
        if span is not None and span[1] > 1.05 * span[0]:  # a curve over focal lengths actually seen
            k0 = snap.lam_at(f) / (f * f)
            k1 = snap.lam_at(f * ratio) / (f * ratio) ** 2
            if k0 != 0.0 and math.isfinite(k1 / k0) and 0.0 < k1 / k0 < 10.0:
                return kappa * k1 / k0
        return kappa / ratio

    def undistort(self, snap: LensSnapshot, kid: int, pts: Array) -> Array:
        kappa, c = self._kappa_for(snap, kid)
        if kappa == 0.0:
            return pts
        # division_undistort with lam on radius / f: lam = kappa f^2 for any f (use f = 1)
        return division_undistort(pts, kappa, c, 1.0)

    def _rechain(self, snap: LensSnapshot) -> None:
        """Corrected H reference -> keyframe for every keyframe reachable through its links."""
        ref = self.reference_id
        if ref is None:
            return
        chain = self._H_chain
        chain[ref] = np.eye(3)
        chained = 0
        for child in sorted(self._links):
            link = self._links[child]
            if child == ref:
                continue
            parent_H = chain.get(link.parent)
            if parent_H is None:
                continue
            key = (link.parent, *self._kappa_for(snap, link.parent)[0:1], *self._kappa_for(snap, child)[0:1])
            key = (*key, *self._centre.get(child, self.centre0), *self._centre.get(link.parent, self.centre0))
            cached = self._link_H.get(child)
            try:
                if cached is not None and cached[0] == key:
                    H_link = cached[1]
                else:
                    src = self.undistort(snap, link.parent, link.parent_pts)
                    dst = self.undistort(snap, child, link.pts)
                    H_link = estimate_homography(src, dst)  # parent -> child, corrected pixels
                    self._link_H[child] = (key, H_link)
                H = normalise_homography(H_link @ parent_H)
            except (ValueError, np.linalg.LinAlgError):
                continue
            if np.all(np.isfinite(H)):
                chain[child] = H
                chain.move_to_end(child)
                chained += 1
            # the same chain on the raw points (fitted once per link): what the correction changed
            raw_parent = self._raw_chain.get(link.parent)
            if raw_parent is not None and child not in self._raw_chain:
                with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                    self._raw_chain[child] = normalise_homography(
                        estimate_homography(link.parent_pts, link.pts) @ raw_parent
                    )
        for table in (chain, self._raw_chain):
            while len(table) > self.max_keyframes:
                oldest = next(iter(table))
                if oldest == ref:
                    table.move_to_end(oldest)
                    continue
                table.popitem(last=False)
        self.stats.chained = chained
        for kid in [k for k in self._link_H if k not in self._links]:
            del self._link_H[kid]

    def _published(self, snap: LensSnapshot) -> dict[int, Array]:
        """Corrected keyframe homographies; the tracker's own where the lens barely distorts.

        One link per keyframe drifts more than the tracker's homography reference -> keyframe
        (re-matched, refined): on an undistorted lens the pure chains cost accuracy (demo bag: focal
        0.02% -> 0.3%). Where a keyframe's estimated distortion moves the image corner by less than
        `tracker_below_px`, the published homography is C_k R_k^-1 T_k: the tracked T_k brought back
        by the inverse raw-point chain R_k (near identity), then along the corrected chain C_k
        (= R_k without distortion: T_k unchanged). With real distortion R_k^-1 T_k is not a pure
        drift (fits of distorted points depend on which points) and the chain C_k is used as is.
        """
        out = dict(self._H_chain)
        if self.tracker_below_px <= 0.0:
            return out
        r = 0.5 * math.hypot(self.width, self.height)
        for kid, C in self._H_chain.items():
            R, T = self._raw_chain.get(kid), self._H_raw.get(kid)
            if R is None or T is None or abs(self._kappa_for(snap, kid)[0]) * r**3 >= self.tracker_below_px:
                continue
            with contextlib.suppress(np.linalg.LinAlgError, ValueError):
                H = normalise_homography(C @ np.linalg.solve(R, T))
                if np.all(np.isfinite(H)):
                    out[kid] = H
        return out

    # ---- frame thread ------------------------------------------------------------------------------
    def ready(self) -> bool:
        return self.snapshot is not None

    def keyframe_homography(self, keyframe_id: int) -> Array | None:
        """Corrected H reference -> keyframe (None: not chained yet)."""
        snap = self.snapshot
        if snap is None:
            return None
        return snap.H.get(int(keyframe_id))

    def frame_homography(
        self, H_raw: ArrayLike, keyframe_id: int, f_frame: float | None = None
    ) -> Array | None:
        """Corrected H reference -> frame from the tracked one (None: no correction available yet).

        The frame's short homography from its keyframe (tracked, distorted points) is corrected by a
        grid refit, the rest is the keyframe's corrected chain. A keyframe not chained yet (its own
        matches have not arrived: the NEW_KEYFRAME frame itself) is reached from the newest chained
        keyframe instead. f_frame (optional) places the frame's end on the lam(f) curve; without it
        the keyframe's coefficient is used at both ends (frames stay close to their keyframe in zoom).
        """
        snap = self.snapshot
        if snap is None:
            return None
        kid = int(keyframe_id)
        base = kid if (kid in snap.H and kid in self._H_raw) else None
        if base is None:
            # not chained yet: its own provisional chain (provisional_link), else the newest keyframe
            # with a chain or a provisional one
            for k in (kid, *(k for k in reversed(self._H_raw) if k != kid)):
                if k not in self._H_raw or not (k in snap.H or k in self._provisional):
                    continue
                chained = self._provisional_chain(snap, k)
                if chained is not None:
                    return self._from_base(snap, H_raw, k, *chained)
                if k in snap.H:
                    base = k
                    break
        if base is None:
            return None
        H_local = np.asarray(H_raw, dtype=float) @ np.linalg.inv(self._H_raw[base])
        kappa, c = self._kappa_for(snap, base)
        if kappa != 0.0:
            kappa_j = self._carry(snap, kappa, base, zoom_ratio(H_local))
            if f_frame is not None and math.isfinite(f_frame) and f_frame > 0 and snap.curve.fitted():
                kappa_j = snap.lam_at(f_frame) / (f_frame * f_frame)
            # too little overlap for the grid refit (a worker far behind): the uncorrected local part
            # (first-order error over a short span; the keyframe gets its chain at the next update)
            with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                H_local = undistorted_homography(
                    H_local, kappa, kappa_j, c, c, 1.0, 1.0, self.width, self.height, count=8
                )
        return normalise_homography(H_local @ snap.H[base])

    def _provisional_chain(
        self, snap: LensSnapshot, kid: int, depth: int = 0
    ) -> tuple[Array, float, Array, float] | None:
        """(corrected H reference -> kid, kappa, centre, focal length) through provisional links down
        to a chained keyframe; None when kid is chained itself or has no such path."""
        prov = self._provisional.get(kid)
        if prov is None or kid in snap.H or depth > 16:
            return None
        parent, H_link, kappa, c, f = prov
        if parent in snap.H:
            return H_link @ snap.H[parent], kappa, c, f
        up = self._provisional_chain(snap, parent, depth + 1)
        return None if up is None else (H_link @ up[0], kappa, c, f)

    def _from_base(
        self,
        snap: LensSnapshot,
        H_raw: ArrayLike,
        base: int,
        H_base: Array,
        kappa: float,
        c: Array,
        f: float | None = None,
    ) -> Array:
        """Corrected H reference -> frame: the tracked base -> frame part refitted, then H_base."""
        H_local = np.asarray(H_raw, dtype=float) @ np.linalg.inv(self._H_raw[base])
        if kappa != 0.0:
            kappa_j = self._carry(snap, kappa, base, zoom_ratio(H_local), f)
            with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                H_local = undistorted_homography(
                    H_local, kappa, kappa_j, c, c, 1.0, 1.0, self.width, self.height, count=8
                )
        return normalise_homography(H_local @ H_base)

    def provisional_link(
        self, keyframe_id: int, parent_id: int, pts: ArrayLike, parent_pts: ArrayLike
    ) -> bool:
        """Correct a new keyframe's link to an older, chained keyframe at once (its raw inliers
        undistorted with the parent's coefficient and the parent's carried over the link's zoom, one
        homography fit, ~ms), so that the keyframe's frames use it instead of a long tracked span from
        the newest chained keyframe until `update` chains the keyframe (a worker 15 frames behind:
        replayed issue-6 bag). For the thread that calls `frame_homography`; True when stored."""
        snap = self.snapshot
        kid, parent = int(keyframe_id), int(parent_id)
        if snap is None or kid in snap.H or kid in self._provisional:
            return False
        up = None if parent in snap.H else self._provisional_chain(snap, parent)
        if parent not in snap.H and up is None:
            return False
        if kid not in self._H_raw or parent not in self._H_raw or kid <= parent:
            return False
        a = np.asarray(pts, dtype=float).reshape(-1, 2)
        b = np.asarray(parent_pts, dtype=float).reshape(-1, 2)
        if len(a) != len(b) or len(a) < 12:
            return False
        kappa_p, c = self._kappa_for(snap, parent) if up is None else (up[1], up[2])
        f_p = self._focal.get(parent, self.nominal_focal) if up is None else up[3]
        ratio = zoom_ratio(self._H_raw[kid] @ np.linalg.inv(self._H_raw[parent]))
        kappa = self._carry(snap, kappa_p, parent, ratio, f_p)
        try:
            src = b if kappa_p == 0.0 else division_undistort(b, kappa_p, c, 1.0)
            dst = a if kappa == 0.0 else division_undistort(a, kappa, c, 1.0)
            H_link = estimate_homography(src, dst)
        except (ValueError, np.linalg.LinAlgError):
            return False
        if not np.all(np.isfinite(H_link)):
            return False
        f = f_p * ratio if math.isfinite(ratio) and ratio > 0.0 else f_p
        self._provisional[kid] = (parent, H_link, kappa, c, f)
        while len(self._provisional) > 64:
            self._provisional.popitem(last=False)
        return True

    def undistort_points(self, keyframe_id: int, pts: ArrayLike) -> Array:
        """Keyframe points on corrected coordinates (identity before the first estimate)."""
        p = np.asarray(pts, dtype=float).reshape(-1, 2)
        snap = self.snapshot
        return p if snap is None else self.undistort(snap, int(keyframe_id), p)

    def plumb_bob(self, K: ArrayLike) -> Array:
        """CameraInfo D = [k1, k2, 0, 0, 0] of lam(f) at K's focal length, about K's principal point.

        O(1) per frame while the camera zooms: (k1, k2) are fitted (division_to_plumb_bob, ~1 ms) at
        nodes 0.5% apart in log f, cached per estimate, and interpolated linearly in log f between the
        two nodes around the frame's f (k1, k2 are smooth in f: the interpolation error is far below
        the fit's own).
        """
        D = np.zeros(5)
        snap = self.snapshot
        K = np.asarray(K, dtype=float)
        f = float(K[0, 0])
        if snap is None or not (math.isfinite(f) and f > 0.0) or snap.lam_at(f) == 0.0:
            return D
        step = 0.005
        x = math.log(f) / step
        n0 = math.floor(x)
        w = x - n0
        coeffs = []
        for n in (n0, n0 + 1):
            key = (self.stats.updates, n, round(float(K[0, 2])), round(float(K[1, 2])))
            cached = self._plumb_bob.get(key)
            if cached is None:
                f_n = math.exp(n * step)
                K_n = K.copy()
                K_n[0, 0] = K_n[1, 1] = f_n
                try:
                    cached = division_to_plumb_bob(snap.lam_at(f_n), K_n, self.width, self.height)
                except ValueError:
                    return D
                self._plumb_bob[key] = cached
                while len(self._plumb_bob) > self._plumb_bob_size:
                    self._plumb_bob.popitem(last=False)
            coeffs.append(cached)
        D[0] = (1.0 - w) * coeffs[0][0] + w * coeffs[1][0]
        D[1] = (1.0 - w) * coeffs[0][1] + w * coeffs[1][1]
        return D


# --------------------------------------------------------------------------------------------------
# The calibrator node's seam
# --------------------------------------------------------------------------------------------------
class SessionLensHook:
    """LensCorrection in front of a calibration session (online/session.CalibratorSession).

    The node calls, in its three threads of control:
    - `frame(H, state, keyframe_id, reference, width, height)` (frame callback): the tracked homography
      replaced by the corrected one. Keyframes arriving before the first distortion estimate (the first
      two or three) pass uncorrected and get their corrected chains at the first `work`; with
      `hold_keyframes` they are passed on as plain TRACKING frames instead, never entering the
      calibration (measured worse: 12% barrel bag focal median 0.79% vs 0.62%, undistorted demo bag
      0.26% vs 0.11%).
    - `matches(...)` (KeyframeMatches callback): queued, O(1).
    - `work(session)` (the node's worker, after `session.step`): drains the queue into LensCorrection,
      gives it the session's keyframe focal lengths and principal point (nominal before the first
      calibration), re-estimates distortion when matches arrived, and re-sends the latest keyframe
      matches to the session on corrected coordinates (the bundle adjustment's observations) with the
      corrected link homographies.
    - `distortion(K)` (frame callback): plumb_bob D for the frame's K.
    The session gets D through its `distortion_model` seam (the node plugs `distortion` into it).
    """

    def __init__(
        self,
        nominal_focal_of_width: Any,
        resend: int = 64,
        centre_from_calibration: bool = False,
        hold_keyframes: bool = False,
        joint_bundle: bool = True,
        centre_gate_px: float = 2.0,
    ) -> None:
        self._nominal = nominal_focal_of_width
        self.hold_keyframes = hold_keyframes
        self.centre_from_calibration = centre_from_calibration
        self.joint_bundle = joint_bundle
        self.centre_gate_px = float(centre_gate_px)
        self.centre: Array | None = None  # distortion centre from the joint adjustment (None: image centre)
        self._estimate: Any = None  # the session solver's last LensEstimate taken
        self.centre_updates = 0
        self.lens: LensCorrection | None = None
        self._reference: str | None = None
        self._queue: deque[tuple[int, int, Array, Array, bool]] = deque(maxlen=4 * resend)
        self._session: Any = None  # the session of the last `work` (joint mode: raw matches go to it)
        self._early_links: dict[int, tuple[int, Array, Array]] = {}  # matches before their keyframe
        self._raw_matches: deque[tuple[int, int, Array, Array]] = deque(maxlen=resend)
        self._size: tuple[int, int] | None = None
        self.held_keyframes = 0
        self.uncorrectable_frames = 0  # calibrated session, frame the lens correction cannot correct

    def _ensure(self, reference: str, width: int, height: int) -> LensCorrection | None:
        if width <= 0 or height <= 0:
            return self.lens
        if self.lens is None or self._size != (width, height) or reference != self._reference:
            # new map or new image size: the tracker's keyframe ids and homographies start afresh
            self.lens = LensCorrection(width, height, float(self._nominal(width)))
            self._size, self._reference = (width, height), reference
            self._queue.clear()
            self._raw_matches.clear()
            self._early_links.clear()
            self.centre = None
        return self.lens

    def frame(
        self,
        H: Array | None,
        state: str,
        keyframe_id: int,
        reference: str,
        width: int,
        height: int,
        calibrated: bool = False,
    ) -> tuple[Array | None, str]:
        """The frame's homography on corrected coordinates, and its tracking state.

        `calibrated`: the session already holds a calibration (on corrected coordinates) for this
        reference. A raw homography must then never reach it (on the issue-6 lens that is a 40-60 %
        focal error): a frame the correction cannot reach (its state is not persisted, so after a
        restart on a restored tracker map it starts empty) goes out without a homography, K from the
        zoom model.
        """
        lens = self._ensure(reference, width, height)
        if lens is None or H is None or not np.all(np.isfinite(H)):
            return H, state
        kid = int(keyframe_id)
        if state == "NEW_KEYFRAME":
            lens.add_keyframe(kid, H)
            waiting = self._early_links.pop(kid, None)
            if waiting is not None:  # its matches came first
                self._link_now(lens, kid, *waiting)
        corrected = lens.frame_homography(H, kid)
        if corrected is not None:
            return corrected, state
        if calibrated:
            self.uncorrectable_frames += 1
            return None, "TRACKING_LOST"
        if self.hold_keyframes and state == "NEW_KEYFRAME" and kid != lens.reference_id:
            self.held_keyframes += 1
            return H, "TRACKING"
        return H, state

    def matches(self, keyframe_id: int, other_keyframe_id: int, pts: Array, other_pts: Array) -> None:
        m = (int(keyframe_id), int(other_keyframe_id), pts, other_pts)
        lens = self.lens
        if lens is not None and self.joint_bundle:
            child, parent, pc, pp = m if m[0] > m[1] else (m[1], m[0], m[3], m[2])
            self._link_now(lens, child, parent, pc, pp)
        session, forwarded = self._session, False
        if self.joint_bundle and session is not None:
            # raw points are what the adjustment takes: on to the session at once, so that a new
            # keyframe's frames reach a solved keyframe through this link before the worker runs
            forwarded = bool(session.add_keyframe_matches(*m, None))
        self._queue.append((*m, forwarded))

    def work(self, session: Any) -> bool:
        """Worker step; True when the distortion estimate changed."""
        lens = self.lens
        if lens is None:
            return False
        self._session = session
        while self._queue:
            *m, forwarded = self._queue.popleft()
            if lens.add_match(*m):
                self._raw_matches.append(tuple(m))
            if self.joint_bundle and not forwarded:
                session.add_keyframe_matches(*m, None)
        moved = self._take_joint_estimate(session, lens)
        if lens.pending == 0 and not moved:
            return False
        calibrator = getattr(session, "calibrator", None)
        if calibrator is not None:
            if getattr(calibrator, "calibrated", False) and lens.reference_id is not None:
                K = calibrator.reference_K
                lens.set_keyframe(lens.reference_id, K[0, 0], self._centre(K))
            solved = set()
            for kf in list(getattr(calibrator, "keyframes", [])):
                if kf.K is not None:
                    lens.set_keyframe(int(kf.keyframe_id), kf.K[0, 0], self._centre(kf.K))
                    solved.add(int(kf.keyframe_id))
            # the other keyframes (held, dropped, not solved yet): the reference calibration (or the
            # prior) transferred through their corrected chain, eq. 20
            snap = lens.snapshot
            for kid, H in ({} if snap is None else snap.H).items():
                if kid in solved or kid == lens.reference_id:
                    continue
                try:
                    K = calibrator.frame_intrinsics(H)[0]
                except (SelfCalibrationError, ValueError, ArithmeticError, np.linalg.LinAlgError):
                    continue
                if np.all(np.isfinite(K)):
                    lens.set_keyframe(kid, K[0, 0], self._centre(K))
        if not lens.update(force=moved):
            return False
        snap = lens.snapshot
        assert snap is not None
        # the session's keyframes were stored with the correction known when they arrived: give them
        # their chains recomputed with the new estimate (the worker owns the calibrator here)
        if calibrator is not None:
            for kf in list(getattr(calibrator, "keyframes", [])):
                H = snap.H.get(int(kf.keyframe_id))
                if H is not None:
                    kf.H = H
            changed = getattr(session, "keyframe_homographies_changed", None)
            if changed is not None:
                changed()
        if self.joint_bundle:  # the adjustment fits the distortion itself: the raw points went already
            return True
        for i, j, a, b in self._raw_matches:
            H_i, H_j = snap.H.get(i), snap.H.get(j)
            link = None if H_i is None or H_j is None else H_i @ np.linalg.inv(H_j)
            session.add_keyframe_matches(i, j, lens.undistort_points(i, a), lens.undistort_points(j, b), link)
        return True

    def _link_now(self, lens: LensCorrection, child: int, parent: int, pc: Array, pp: Array) -> None:
        """provisional_link, or kept for the keyframe's NEW_KEYFRAME homography when the matches
        arrive before it (the two topics are not ordered)."""
        if child not in lens._H_raw:
            self._early_links[child] = (parent, pc, pp)
            while len(self._early_links) > 16:
                self._early_links.pop(next(iter(self._early_links)))
            return
        with contextlib.suppress(ValueError, ArithmeticError, np.linalg.LinAlgError):
            lens.provisional_link(child, parent, pc, pp)

    def _take_joint_estimate(self, session: Any, lens: LensCorrection) -> bool:
        """With joint_bundle: plug the distortion guess into the session's solver (its adjustment then
        runs on raw points, bundle/adjust.py distortion=True) and take its principal point as the
        distortion centre, and its coefficients, once its 1-sigma is below centre_gate_px; True when
        they changed."""
        solver = getattr(session, "solver", None)
        if not self.joint_bundle or solver is None:
            return False
        solver.lens = self
        estimate = getattr(solver, "lens_estimate", None)
        if estimate is None or estimate is self._estimate:
            return False
        self._estimate = estimate
        pp = np.asarray(estimate.principal_point, dtype=float)
        sigma = np.asarray(estimate.sigma_pp, dtype=float)
        if not (np.all(np.isfinite(pp)) and np.all(np.isfinite(sigma)) and sigma.max() < self.centre_gate_px):
            return False
        moved = self.centre is None or float(np.hypot(*(pp - self.centre))) > 0.1
        self.centre = pp
        if moved:
            self.centre_updates += 1
            lens.set_centre(pp)
        # its coefficients too (about that centre): they come from the raw points of every keyframe
        # of the solve (issue-6 bag offline: distortion error 0.04 px)
        return lens.set_joint(dict(estimate.focal), dict(estimate.lam)) or moved

    def lam_guess(self, keyframe_id: int | None, f: float) -> float:
        """The division coefficient of a keyframe (None: the reference) at focal length f from the
        current estimate (its pixel-space kappa, else the lam(f) curve); 0.0 before any."""
        lens = self.lens
        snap = None if lens is None else lens.snapshot
        if lens is None or snap is None:
            return 0.0
        kid = lens.reference_id if keyframe_id is None else int(keyframe_id)
        if kid is None:
            return snap.lam_at(f)
        return float(lens._kappa_for(snap, kid)[0]) * f * f

    def keyframe_homography(self, keyframe_id: int) -> Array | None:
        """The corrected H reference -> keyframe, chained or provisional (None: neither yet)."""
        lens = self.lens
        snap = None if lens is None else lens.snapshot
        if lens is None or snap is None:
            return None
        H = snap.H.get(int(keyframe_id))
        if H is None:
            chained = lens._provisional_chain(snap, int(keyframe_id))
            H = None if chained is None else normalise_homography(chained[0])
        return H

    def distort(self, keyframe_id: int | None, pts: ArrayLike) -> Array:
        """Corrected pixels of a keyframe (None: the reference) back to raw ones with the model that
        corrected them (identity before the first estimate)."""
        lens = self.lens
        p = np.asarray(pts, dtype=float).reshape(-1, 2)
        snap = None if lens is None else lens.snapshot
        if lens is None or snap is None:
            return p
        kid = lens.reference_id if keyframe_id is None else int(keyframe_id)
        if kid is None:
            return p
        kappa, c = lens._kappa_for(snap, kid)
        return p if kappa == 0.0 else division_distort(p, kappa, c, 1.0)

    def _centre(self, K: Array) -> Array | None:
        # the distortion centre and the principal point are nearly interchangeable in rotation-only
        # data when estimated apart (the estimate follows the assumed centre), so feeding the
        # calibrated principal point back drifts; the joint adjustment's centre (gated) is used when
        # there is one, else the image centre (None)
        if self.joint_bundle:
            return self.centre
        return K[:2, 2] if self.centre_from_calibration else None

    def distortion(self, K: Array) -> Array:
        return np.zeros(5) if self.lens is None else self.lens.plumb_bob(K)
