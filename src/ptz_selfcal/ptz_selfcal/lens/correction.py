"""The calibrator's online radial-distortion state: homographies on corrected coordinates (section 7).

Section 7 of the paper shows that self-calibration on homographies of DISTORTED points over-estimates
the focal length (and under-estimates the motion), and suggests "correct the homographies, then
self-calibrate". The tracker's homography reference -> keyframe is a CHAIN of keyframe-to-keyframe
homographies, each fitted to distorted points: every link absorbs part of the distortion into a
projective error, and the errors compound along the chain, so undistorting a grid mapped through the
chained homography (lens/estimation.undistorted_homography) does not recover the undistorted one.
Recomputing every LINK from its raw inlier correspondences after undistorting them, and chaining the
corrected links from the reference, does.

`LensCorrection` does exactly that, online and in bounded time:
- `add_match(newer, older, pts_newer, pts_older)`: the tracker's KeyframeMatches (raw, distorted,
  full-resolution inliers). They feed lens/estimator.KeyframeDistortionEstimator (one division
  coefficient per keyframe jointly with the pair homographies; the lam(f) curve) and, for each
  keyframe, its best link to an older keyframe (most points) for the chain.
- `set_keyframe(id, f, centre)`: the calibrator's current focal length / principal point of a keyframe.
  Before any calibration a prior (nominal focal length) is good enough: the images constrain the
  pixel-space coefficient kappa = lam / f^2 about the distortion centre, which does not depend on f;
  f only places a keyframe on the lam(f) curve, refined as the calibration converges.
- `update()` (worker, only when new matches arrived): every `solve_every` matches the joint
  estimation over at most `max_matches` matches, in between only the new links are chained with the
  current estimates (cheap); the corrected homography reference -> keyframe of every keyframe is its
  chain of corrected links (DLT + LM on undistorted inliers, cached per link until its coefficients
  change). Keyframes that left the estimator's window keep their last estimate; new ones take their
  ancestor's, carried over the zoom ratio. Nothing runs per frame.
- Per frame (`frame_homography`): the corrected H reference -> frame is the frame's short
  keyframe -> frame homography (tracked on distorted points, corrected by an 8x8-grid refit: its error
  is second order in the keyframe -> frame motion, without it the per-frame K's tail is several times
  worse) composed with the keyframe's corrected chain.
- `plumb_bob(K)`: D = [k1, k2, 0, 0, 0] of lam(f) at the frame's focal length for CameraInfo
  (distortion.division_to_plumb_bob, consistent with K: OpenCV undistortion with (K, D) reproduces the
  division model); cached by (lam, f, principal point) so a steady zoom costs a dictionary lookup.
- `undistort_points(id, pts)`: keyframe matches on corrected coordinates for the bundle adjustment
  (section 5).
- `view()`: the lens model a keyframe solve starts from (`LensView`, lens/interface.LensModel).

The distortion centre. In rotation-only data it is nearly interchangeable with the principal point
when the two are estimated apart (self-calibration on corrected homographies follows the assumed
centre almost one to one, and feeding its principal point back as the centre diverges). So the
keyframe bundle adjustment estimates them as ONE point, with the distortion, on the raw keyframe
matches (bundle/adjust.py distortion="curve", online/keyframe_solver.KeyframeBundleSolver given a
`LensView`): no corrected data enters it, so there is no feedback loop. Once its principal point's
1-sigma is below a gate lens/hook.SessionLensHook makes it the centre here (`set_centre`) and the
adjustment's per-keyframe coefficients and lam(f) curve replace the estimator's (`set_joint`). Until
the gate opens the centre is the image centre.

While the worker is behind, a new keyframe's first link is corrected on arrival (`provisional_link`,
on the parent's chain or its provisional one): otherwise the keyframe's frames would use a long
tracked span from the newest chained keyframe.

Pure: numpy + the core modules, no rclpy. Not thread-safe by itself: `update` builds a new immutable
`LensSnapshot` and swaps it in one assignment, so a frame thread may read `snapshot` concurrently.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import division_distort, division_to_plumb_bob, division_undistort
from ptz_selfcal.camera.geometry import normalise_homography
from ptz_selfcal.frontend.homography import estimate_homography
from ptz_selfcal.lens.curve import DistortionVsFocal
from ptz_selfcal.lens.estimation import undistorted_homography
from ptz_selfcal.lens.estimator import KeyframeDistortionEstimator

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

        The joint estimation (the expensive part) runs on the first call and then once every
        `solve_every` new matches (or when forced); in between only the new links are chained with the
        current estimates (new keyframes take lam from the curve), which is cheap, so a worker that falls
        behind never leaves new keyframes without a corrected homography.
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

    def kappa_for(self, snap: LensSnapshot, kid: int) -> tuple[float, Array]:
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
        kappa, c = self.kappa_for(snap, kid)
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
            key = (link.parent, *self.kappa_for(snap, link.parent)[0:1], *self.kappa_for(snap, child)[0:1])
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
        (re-matched, refined), so on an undistorted lens the pure chains cost accuracy. Where a
        keyframe's estimated distortion moves the image corner by less than `tracker_below_px`, the
        published homography is C_k R_k^-1 T_k: the tracked T_k brought back by the inverse raw-point
        chain R_k (near identity), then along the corrected chain C_k (= R_k without distortion: T_k
        unchanged). With real distortion R_k^-1 T_k is not a pure drift (fits of distorted points
        depend on which points) and the chain C_k is used as is.
        """
        out = dict(self._H_chain)
        if self.tracker_below_px <= 0.0:
            return out
        r = 0.5 * math.hypot(self.width, self.height)
        for kid, C in self._H_chain.items():
            R, T = self._raw_chain.get(kid), self._H_raw.get(kid)
            if R is None or T is None or abs(self.kappa_for(snap, kid)[0]) * r**3 >= self.tracker_below_px:
                continue
            with contextlib.suppress(np.linalg.LinAlgError, ValueError):
                H = normalise_homography(C @ np.linalg.solve(R, T))
                if np.all(np.isfinite(H)):
                    out[kid] = H
        return out

    # ---- frame thread ------------------------------------------------------------------------------
    def ready(self) -> bool:
        return self.snapshot is not None

    def has_keyframe(self, keyframe_id: int) -> bool:
        """Whether the keyframe's tracked homography (its NEW_KEYFRAME message) has arrived."""
        return int(keyframe_id) in self._H_raw

    def tracked_homography(self, keyframe_id: int) -> Array | None:
        """The keyframe's tracked H reference -> keyframe, on distorted points (add_keyframe)."""
        return self._H_raw.get(int(keyframe_id))

    def view(self) -> LensView:
        """The lens model at the current estimate, for the keyframe solver (lens/interface.LensModel)."""
        return LensView(self, self.snapshot)

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
                chained = self.provisional_chain(snap, k)
                if chained is not None:
                    return self._from_base(snap, H_raw, k, *chained)
                if k in snap.H:
                    base = k
                    break
        if base is None:
            return None
        H_local = np.asarray(H_raw, dtype=float) @ np.linalg.inv(self._H_raw[base])
        kappa, c = self.kappa_for(snap, base)
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

    def provisional_chain(
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
        up = self.provisional_chain(snap, parent, depth + 1)
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
        homography fit), so that the keyframe's frames use it instead of a long tracked span from the
        newest chained keyframe until `update` chains the keyframe. For the thread that calls
        `frame_homography`; True when stored."""
        snap = self.snapshot
        kid, parent = int(keyframe_id), int(parent_id)
        if snap is None or kid in snap.H or kid in self._provisional:
            return False
        up = None if parent in snap.H else self.provisional_chain(snap, parent)
        if parent not in snap.H and up is None:
            return False
        if kid not in self._H_raw or parent not in self._H_raw or kid <= parent:
            return False
        a = np.asarray(pts, dtype=float).reshape(-1, 2)
        b = np.asarray(parent_pts, dtype=float).reshape(-1, 2)
        if len(a) != len(b) or len(a) < 12:
            return False
        kappa_p, c = self.kappa_for(snap, parent) if up is None else (up[1], up[2])
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

    @property
    def plumb_bob_cached(self) -> int:
        """(k1, k2) fits held by the plumb_bob cache."""
        return len(self._plumb_bob)

    def plumb_bob(self, K: ArrayLike) -> Array:
        """CameraInfo D = [k1, k2, 0, 0, 0] of lam(f) at K's focal length, about K's principal point.

        O(1) per frame while the camera zooms: (k1, k2) are fitted (division_to_plumb_bob) at
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


@dataclass(frozen=True)
class LensView:
    """lens/interface.LensModel of a LensCorrection at one estimate (`snapshot`; None: none yet, then
    lam 0, no distortion and no corrected homography). Keyframe id None = the reference.

    The estimate is fixed (the worker that solves is the one that updates it); the links and
    provisional chains it reads are the correction's current ones, as the frame thread adds them."""

    correction: LensCorrection
    snapshot: LensSnapshot | None

    def lam_guess(self, keyframe_id: int | None, f: float) -> float:
        """The keyframe's division coefficient at focal length f: its pixel-space kappa (or an
        ancestor's, carried over the zoom), else the lam(f) curve; 0.0 before any estimate."""
        snap = self.snapshot
        if snap is None:
            return 0.0
        kid = self.correction.reference_id if keyframe_id is None else int(keyframe_id)
        if kid is None:
            return snap.lam_at(f)
        return float(self.correction.kappa_for(snap, kid)[0]) * f * f

    def keyframe_homography(self, keyframe_id: int) -> Array | None:
        """The corrected H reference -> keyframe, chained or provisional (None: neither yet)."""
        snap = self.snapshot
        if snap is None:
            return None
        H = snap.H.get(int(keyframe_id))
        if H is None:
            chained = self.correction.provisional_chain(snap, int(keyframe_id))
            H = None if chained is None else normalise_homography(chained[0])
        return H

    def distort(self, keyframe_id: int | None, pts: ArrayLike) -> Array:
        """Corrected pixels of a keyframe back to raw ones with the model that corrected them
        (identity before the first estimate)."""
        p = np.asarray(pts, dtype=float).reshape(-1, 2)
        snap = self.snapshot
        if snap is None:
            return p
        kid = self.correction.reference_id if keyframe_id is None else int(keyframe_id)
        if kid is None:
            return p
        kappa, c = self.correction.kappa_for(snap, kid)
        return p if kappa == 0.0 else division_distort(p, kappa, c, 1.0)
