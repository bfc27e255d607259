"""The calibrator node's seam to the lens correction: `SessionLensHook` in front of a calibration
session (section 7). Typed both ways: the session is a `LensSession`, and the keyframe solver gets the
lens model as a value (LensCorrection.view(), a lens/interface.LensModel) after every worker step."""

from __future__ import annotations

import contextlib
from collections import deque
from collections.abc import Callable, Hashable, Mapping, Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import PLUMB_BOB, corner_radius, radial_displacement
from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.lens.correction import LensCorrection
from ptz_selfcal.lens.interface import LensEstimate, LensModel
from ptz_selfcal.status import TrackingState

if TYPE_CHECKING:
    from ptz_selfcal.online.frames import FrameOutput

Array = NDArray[np.float64]


class SessionKeyframe(Protocol):
    """A calibrator keyframe: its homography from the reference and its latest K."""

    keyframe_id: Hashable
    H: Array
    K: Array | None


class SessionCalibrator(Protocol):
    """What the hook reads of online/incremental.IncrementalCalibrator."""

    @property
    def calibrated(self) -> bool: ...

    @property
    def reference_K(self) -> Array: ...

    @property
    def keyframes(self) -> Sequence[SessionKeyframe]: ...

    def frame_intrinsics(self, H_ref_to_frame: ArrayLike) -> tuple[Array, Array, float]: ...


class SessionSolver(Protocol):
    """What the hook exchanges with online/keyframe_solver.KeyframeBundleSolver in joint mode."""

    @property
    def lens_estimate(self) -> LensEstimate | None: ...

    @property
    def distortion_adopted(self) -> bool | None: ...

    @property
    def noise_estimate(self) -> float | None: ...

    def set_lens_model(self, model: LensModel | None) -> None: ...


class LensSession(Protocol):
    """What the hook uses of online/session.CalibratorSession."""

    @property
    def calibrator(self) -> SessionCalibrator | None: ...

    @property
    def solver(self) -> SessionSolver: ...

    @property
    def last_good(self) -> FrameOutput | None: ...

    @property
    def image_size(self) -> tuple[int, int] | None: ...

    def add_keyframe_matches(
        self,
        keyframe_id: int,
        other_keyframe_id: int,
        points: Array,
        other_points: Array,
        H: Array | None = None,
    ) -> bool: ...

    def replace_keyframe_homographies(self, homographies: Mapping[int, Array]) -> None: ...


class SessionLensHook:
    """LensCorrection in front of a calibration session (online/session.CalibratorSession).

    The node calls, in its three threads of control:
    - `frame(H, state, keyframe_id, reference, width, height)` (frame callback): the tracked homography
      replaced by the corrected one. Keyframes arriving before the first distortion estimate (the first
      two or three) pass uncorrected and get their corrected chains at the first `work`; with
      `hold_keyframes` they are passed on as plain TRACKING frames instead, never entering the
      calibration (off by default: the calibration is worse without those keyframes).
    - `matches(...)` (KeyframeMatches callback): queued, O(1).
    - `work(session)` (the node's worker, after `session.step`): drains the queue into LensCorrection,
      gives it the session's keyframe focal lengths and principal point (nominal before the first
      calibration), re-estimates distortion when matches arrived, and re-sends the latest keyframe
      matches to the session on corrected coordinates (the bundle adjustment's observations) with the
      corrected link homographies; in joint mode hands the session's solver the lens model
      (LensCorrection.view()) and takes the solver's LensEstimate.
    - `distortion(K)` (frame callback): plumb_bob D for the frame's K.
    The session gets D through its `distortion_model` seam (the node plugs `distortion` into it).
    """

    def __init__(
        self,
        nominal_focal_of_width: Callable[[int], float],
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
        self._estimate: LensEstimate | None = None  # the session solver's last one taken
        self.centre_updates = 0
        self.lens: LensCorrection | None = None
        self._reference: str | None = None
        self._queue: deque[tuple[int, int, Array, Array, bool]] = deque(maxlen=4 * resend)
        self._session: LensSession | None = None  # of the last `work` (joint mode: raw matches go to it)
        self._early_links: dict[int, tuple[int, Array, Array]] = {}  # matches before their keyframe
        self._raw_matches: deque[tuple[int, int, Array, Array]] = deque(maxlen=resend)
        self._size: tuple[int, int] | None = None
        self.held_keyframes = 0
        self.uncorrectable_frames = 0  # calibrated session, frame the lens correction cannot correct
        # the solver's adjustment found no distortion (its estimate's lam all zero, bundle/selection.py):
        # the tracked homographies go on as they are, as with estimate_distortion false
        self.pinhole = False

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
            if self.joint_bundle and self._session is not None:  # the old map's model is void
                self._session.solver.set_lens_model(self.lens.view())
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

        `calibrated`: the session already holds a calibration for this reference, on corrected
        coordinates once the correction has an estimate. A raw homography must then never reach it
        (a distorted lens's raw homography puts the focal length far off): a frame the correction
        cannot reach (its state is not persisted, so after a restart on a restored tracker map it
        starts empty) goes out without a homography, K from the zoom model. A lens found without
        distortion (`pinhole`) gets its tracked homographies.
        """
        lens = self._ensure(reference, width, height)
        if lens is None or H is None or not np.all(np.isfinite(H)):
            return H, state
        kid = int(keyframe_id)
        waiting = None
        if state == TrackingState.NEW_KEYFRAME:
            lens.add_keyframe(kid, H)
            waiting = self._early_links.pop(kid, None)
        corrected = None if self.pinhole else lens.frame_homography(H, kid)
        if waiting is not None:
            # its matches came first; linked after its own frame is corrected, as when they come after
            # (the two topics are not ordered: a frame's correction must not depend on which came first)
            self._link_now(lens, kid, *waiting)
        if self.pinhole:  # nothing to correct; the correction keeps its chains for a change of model
            return H, state
        if corrected is not None:
            return corrected, state
        if calibrated and (lens.snapshot is not None or not lens.has_keyframe(kid)):
            # (before the first estimate the session's calibration was made on the same uncorrected
            # chains as this frame's: it goes on)
            self.uncorrectable_frames += 1
            return None, TrackingState.TRACKING_LOST
        if self.hold_keyframes and state == TrackingState.NEW_KEYFRAME and kid != lens.reference_id:
            self.held_keyframes += 1
            return H, TrackingState.TRACKING
        return H, state

    def restored(self, session: LensSession) -> None:
        """A session restored from its saved state: the correction's own state is not saved, but a lens
        the evidence had found without distortion needs none, nor one whose distortion moves no point of
        the image by the tracker's noise (the correction would change nothing measurable), so its frames
        go on calibrated."""
        self.pinhole = session.solver.distortion_adopted is False or _below_noise(session)

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

    def work(self, session: LensSession) -> bool:
        """Worker step; True when the distortion estimate changed. In joint mode the session's solver
        gets the lens model at the estimate this step leaves (its next solves start from it)."""
        lens = self.lens
        if lens is None:
            return False
        self._session = session
        try:
            return self._work(session, lens)
        finally:
            current = self.lens  # the frame thread may have started a new map's correction meanwhile
            if self.joint_bundle and current is not None:
                session.solver.set_lens_model(current.view())

    def _work(self, session: LensSession, lens: LensCorrection) -> bool:
        while self._queue:
            *m, forwarded = self._queue.popleft()
            if lens.add_match(*m):
                self._raw_matches.append(tuple(m))
            if self.joint_bundle and not forwarded:
                session.add_keyframe_matches(*m, None)
        moved = self._take_joint_estimate(session, lens)
        if lens.pending == 0 and not moved:
            return False
        calibrator = session.calibrator
        if calibrator is not None:
            if calibrator.calibrated and lens.reference_id is not None:
                K = calibrator.reference_K
                lens.set_keyframe(lens.reference_id, K[0, 0], self._centre(K))
            solved = set()
            for kf in list(calibrator.keyframes):
                if kf.K is not None and lens.has_keyframe(int(kf.keyframe_id)):  # not an ordinary frame
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
        # their chains recomputed with the new estimate
        if calibrator is not None and not self.pinhole:
            session.replace_keyframe_homographies(snap.H)
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
        if not lens.has_keyframe(child):
            self._early_links[child] = (parent, pc, pp)
            while len(self._early_links) > 16:
                self._early_links.pop(next(iter(self._early_links)))
            return
        with contextlib.suppress(ValueError, ArithmeticError, np.linalg.LinAlgError):
            lens.provisional_link(child, parent, pc, pp)

    def _take_joint_estimate(self, session: LensSession, lens: LensCorrection) -> bool:
        """With joint_bundle (the solver's adjustment runs on raw points, bundle/adjust.py
        distortion=True): take its principal point as the distortion centre, and its coefficients,
        once its 1-sigma is below centre_gate_px; True when they changed."""
        if not self.joint_bundle:
            return False
        estimate = session.solver.lens_estimate
        if estimate is None or estimate is self._estimate:
            return False
        self._estimate = estimate
        pinhole = bool(estimate.lam) and all(v == 0.0 for v in estimate.lam.values())
        # back to distortion: the corrected chains go to the session at this update
        rechain = self.pinhole and not pinhole
        if pinhole and not self.pinhole:  # the session's keyframes back on their tracked homographies
            ids = {} if lens.snapshot is None else lens.snapshot.H
            tracked = {k: lens.tracked_homography(k) for k in ids}
            session.replace_keyframe_homographies({k: H for k, H in tracked.items() if H is not None})
        self.pinhole = pinhole
        pp = np.asarray(estimate.principal_point, dtype=float)
        sigma = np.asarray(estimate.sigma_pp, dtype=float)
        if not (np.all(np.isfinite(pp)) and np.all(np.isfinite(sigma)) and sigma.max() < self.centre_gate_px):
            return rechain
        moved = self.centre is None or float(np.hypot(*(pp - self.centre))) > 0.1
        self.centre = pp
        if moved:
            self.centre_updates += 1
            lens.set_centre(pp)
        # its coefficients too (about that centre): they come from the raw points of every keyframe
        # of the solve
        return lens.set_joint(dict(estimate.focal), dict(estimate.lam)) or moved or rechain

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


def _below_noise(session: LensSession) -> bool:
    """The last published distortion moves the image corner by less than the solver's measured noise."""
    last, noise, size = session.last_good, session.solver.noise_estimate, session.image_size
    if last is None or noise is None or size is None:
        return False
    radius = corner_radius(last.K, *size)
    return bool(abs(radial_displacement(PLUMB_BOB, last.D, last.K, [radius])[0]) < noise)
