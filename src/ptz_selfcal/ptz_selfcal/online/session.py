"""One camera's online self-calibration: the frame path, and a session over it (pure, single-threaded).

`CalibratorSession.process(frame)` is everything between "a HomographyStamped arrived" and "publish
this K", in O(1): it never solves. It gates the frame's homography (online/gates.py), transfers the
latest calibration to the frame (eq. 20, online/frame_intrinsics.py) or falls back (zoom model, prior,
last good K, nominal), and collects new keyframes and keyframe matches. The solving half,
online/keyframe_calibration.KeyframeCalibration, takes them as a `WorkBatch` and answers with an
immutable snapshot (online/work.py).

The session is a small state machine over events: a frame, a keyframe added, a solve accepted or
not (a result), the reference changed (a new epoch: results of the old one are dropped), tracking
lost (no usable homography). `step` runs the solving half inline, for benchmarks and tests; the
calibrator node instead runs `take_work` / `calibration.apply` / `accept` with the solve in a worker
thread of its own, so that a frame never waits for a solve.

Statuses: INITIALISING (no calibration yet: zoom model, else the prior through the frame's homography),
DEGENERATE_MOTION (section 6), CALIBRATING / CONVERGED (the calibration's state), PREDICTED_FROM_ZOOM
(no usable homography, or one the zoom gate refused: K from the zoom model), TRACKING_LOST (no usable
homography and no zoom model: the last good K).
"""

from __future__ import annotations

import contextlib
import enum
import math
import os
import time
from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import image_motion, rotation_from_homography
from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frame_intrinsics import (
    KeyframeLinks,
    calibrated_output,
    frame_intrinsics,
    initialising_reason,
    last_good_output,
    nominal_output,
    zoom_output,
)
from ptz_selfcal.online.frames import FrameInput, FrameOutput
from ptz_selfcal.online.gates import (
    MotionGate,
    RestoredStateCheck,
    ZoomGate,
    ZoomVerdict,
    usable_homography,
)
from ptz_selfcal.online.incremental import IncrementalCalibrator
from ptz_selfcal.online.keyframe_calibration import KeyframeCalibration, new_calibrator
from ptz_selfcal.online.keyframe_solver import KeyframeBundleSolver, KeyframeMatchSet
from ptz_selfcal.online.lens_output import DistortionFn, PlumbBob
from ptz_selfcal.online.selection import CalibrationFrameSelector
from ptz_selfcal.online.status_policy import frame_status
from ptz_selfcal.online.work import CalibrationSnapshot, PendingKeyframe, WorkBatch, WorkResult
from ptz_selfcal.persist.atomic_file import remove_stale_temporaries
from ptz_selfcal.persist.camera_info_file import intrinsics_problem
from ptz_selfcal.persist.session_state import state_from_dict, write_state
from ptz_selfcal.persist.state_files import (
    STATE_FILE,
    ZOOM_MODEL_FILE,
    StateFileError,
    load_yaml_file,
    remove_state_files,
)
from ptz_selfcal.status import HOMOGRAPHY_STATES, CalibrationStatus, TrackingState
from ptz_selfcal.zoom import ZoomModel, ZoomModelError, ZoomRate

Array = NDArray[np.float64]

_S = CalibrationStatus
_TRANSFER_ERRORS = (SelfCalibrationError, ValueError, np.linalg.LinAlgError)
_FLAGGED = (_S.DEGENERATE_MOTION, _S.MODEL_MISMATCH)  # a solve's best estimate, not a calibration
_USABLE = (ZoomVerdict.PASS, ZoomVerdict.AGREE)  # verdicts that let an ordinary frame join the solve
_SAME_KEYFRAME = 0.01  # image widths: a saved keyframe re-sent differs by tracking noise, far less


_MATCH_WAIT_FRAMES = 8  # more than the frames a lock-step replay keeps in flight

_FRAME_COUNTERS = (
    *("frames", "keyframe_matches", "invalid_homographies", "frames_without_homography"),
    *("reference_changes", "state_saves", "zoom_gate_rejections", "fast_motion_keyframes"),
    "unconfirmed_keyframes",
    "off_model_frames",
    "prior_size_mismatches",
    "resets",
)

# A measured K (set_camera_info: a checkerboard calibration) as a zoom model sample: its relative
# 1-sigma of f, far tighter than a self-calibrated keyframe's, so that it anchors the model at its zoom.
MEASURED_SIGMA_F = 1e-3

# A K given for one image size (camera_info_url, set_camera_info): (K, (width, height)).
SizedK = tuple[Array, tuple[int, int]]


class Phase(enum.Enum):
    """Where the session is with the current reference. Events move it: the first homography of a
    reference (NO_REFERENCE -> REFERENCED), a result whose snapshot is calibrated (-> CALIBRATED), the
    reference changing (-> NO_REFERENCE, a new epoch). A frame's status follows from the phase and
    the fallback that served it; tracking lost changes no phase."""

    NO_REFERENCE = "no_reference"
    REFERENCED = "referenced"
    CALIBRATED = "calibrated"


class PriorCalibration(KeyframeCalibration):
    """The solving half with a measured prior: a K given by camera_info_url or set_camera_info is the
    prior of a new calibration where the zoom model gives none, in place of the nominal field of view;
    set_camera_info's K is also a zoom model sample. Its owner (the worker) calls these methods."""

    prior: SizedK | None = None

    def given_K(self) -> Array | None:
        prior = self.prior
        return prior[0].copy() if prior is not None and prior[1] == self.image_size else None

    def anchor(self, zoom: float, K: Array, D: Array, size: tuple[int, int]) -> None:
        """A measured K at this zoom (NaN: no zoom reading): the prior, and a zoom model sample."""
        self.prior = (K.copy(), size)
        calibrator = self.calibrator
        if calibrator is not None and calibrator.last_solve is None and calibrator.image_size == size:
            calibrator.prior_K = K.copy()  # not calibrated yet: it starts from the measured K
            self._published = False  # the frame path gets the new prior with the next result
        if not math.isfinite(zoom):
            return
        k1, k2 = float(D[0]), float(D[1])
        weight = 1.0 / MEASURED_SIGMA_F**2
        if not self.zoom_model.add_sample(zoom, K[1, 1], K[0, 2], K[1, 2], k1, k2, weight):
            self._warn(f"set_camera_info: K not usable as a zoom model sample at zoom {zoom:g}")
            return
        self.counters["camera_info_anchors"] = self.counters.get("camera_info_anchors", 0) + 1
        try:
            self.zoom_model.predict(zoom)
            self.zoom_ready = True
        except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
            self._warn(f"zoom model not usable yet: {exc}")
        self._zoom_changed = True
        self.dirty = True

    def forget(self, prior: SizedK | None) -> None:
        """A reset: no calibration and no zoom model; `prior` is the prior again (camera_info_url's)."""
        self.reset()
        self.zoom_model = ZoomModel()
        self.zoom_ready = False
        self.prior = prior
        self.dirty = False  # nothing to save until something is learned again


class CalibratorSession:
    """One camera's self-calibration over a run (see the module docstring)."""

    def __init__(self, config: SessionConfig | None = None, state_dir: str | os.PathLike[str] | None = None):
        self.config = config or SessionConfig()
        self.state_dir = Path(state_dir) if state_dir else None
        self.calibration = PriorCalibration(self.config)  # the solving half (owned by its caller)
        self._counters: dict[str, int] = dict.fromkeys(_FRAME_COUNTERS, 0)
        self.status_counts: dict[str, int] = dict.fromkeys(CalibrationStatus, 0)
        self._result: WorkResult = self.calibration.result()
        self._warnings: deque[str] = deque(maxlen=100)
        self._epoch = 0
        self._snapshot: CalibrationSnapshot | None = None
        self._zoom: ZoomModel | None = None  # read-only copy of the learned zoom model, when usable
        self._pending: list[PendingKeyframe] = []
        self._pending_matches: list[tuple[int, KeyframeMatchSet]] = []  # (frame count at arrival, set)
        self.reference_id: str | None = None
        self.phase = Phase.NO_REFERENCE
        self.image_size: tuple[int, int] | None = None
        self.last_good: FrameOutput | None = None
        self._links = KeyframeLinks()
        self._seen_keyframes: set[int] = set()
        self._motion = MotionGate(self.config.max_keyframe_motion)
        self._tracked_against: int | None = None  # the keyframe of the last frame with a homography
        self._zoom_gate = ZoomGate(self.config)
        self._zoom_rates = ZoomRate()
        self._zoom_rate = 0.0  # zoom encoder counts / s at the current frame (0 = unknown)
        self._plumb_bob = PlumbBob()
        self._frame_dirty = False
        self._frame_times: deque[float] = deque(maxlen=2000)
        # ordinary frames chosen for the solve (online/selection.py), and the prior they are chosen
        # under before the first calibration
        self._selector = CalibrationFrameSelector(
            self.config.max_keyframes + 1, self.config.calibration_frame_spacing
        )
        self._prior: tuple[tuple, IncrementalCalibrator] | None = None
        self._last_proposal = -math.inf  # stamp of the last ordinary frame proposed
        self._given_prior: SizedK | None = None  # camera_info_url's or set_camera_info's K
        self._startup_prior: SizedK | None = None  # camera_info_url's: the prior again after a reset
        self._restored_size: tuple[int, int] | None = None  # a saved state's images, until a frame comes
        self._stale_state: str | None = None  # why the saved state did not fit the images
        self._restored_check: RestoredStateCheck | None = None  # a restored lens, until judged
        self._restored_keyframes: dict[int, Array] = {}  # the saved reference's keyframes, by id
        self._forget_due = False  # a reset whose solving half's part is still to be done
        self._fresh = False  # reset, and no reference since: nothing to save (see `fresh`)
        self.last_zoom = math.nan  # the latest frame's zoom encoder reading

    # ---- the frame path --------------------------------------------------------------------------
    def process(self, frame: FrameInput) -> FrameOutput:
        """The calibration of one frame; O(1), never solves."""
        start = time.perf_counter()
        self._counters["frames"] += 1
        self._zoom_rate = self._zoom_rates.update(float(frame.stamp), float(frame.zoom))
        self.last_zoom = float(frame.zoom)
        size = (int(frame.width), int(frame.height))
        if frame.width > 0 and frame.height > 0 and self.image_size != size:
            if self._restored_size is not None:  # another camera or lens than the saved state's
                self._stale_state = (
                    f"the saved calibration state is of {self._restored_size[0]}x{self._restored_size[1]} "
                    f"images, these are {size[0]}x{size[1]} (a swapped camera or lens?): starting fresh"
                )
                self.reset(self._stale_state)
            elif self.image_size is not None:
                self._new_reference(f"image size changed from {self.image_size} to {size}")
            self.image_size = size
            self._check_prior_size()
        if frame.width > 0 and frame.height > 0:
            self._restored_size = None
        H = None
        if frame.tracking_state in HOMOGRAPHY_STATES:
            H = usable_homography(frame.H, frame.width, frame.height, self.config.max_focal_ratio)
            if H is None:
                self._counters["invalid_homographies"] += 1
        if H is None:
            self._counters["frames_without_homography"] += 1
            self._zoom_gate.no_focal()
            out = self._without_homography(frame)
        else:
            out = self._with_homography(frame, H)
        self._zoom_gate.frame_done(frame.zoom)
        out.time_s = time.perf_counter() - start
        self._frame_times.append(out.time_s)
        self.status_counts[out.status] += 1
        return out

    def _with_homography(self, frame: FrameInput, H: Array) -> FrameOutput:
        if frame.reference_id and self.reference_id is not None and frame.reference_id != self.reference_id:
            self._counters["reference_changes"] += 1
            self._new_reference(
                f"tracking reference changed from {self.reference_id!r} to {frame.reference_id!r}: "
                "calibration restarted on the new reference (zoom model kept)"
            )
        if self.reference_id is None:
            self.reference_id = frame.reference_id
            if self.phase is Phase.NO_REFERENCE:
                self.phase = Phase.REFERENCED
            self._frame_dirty = True
            self._fresh = False
        kid = int(frame.keyframe_id)
        if frame.tracking_state == TrackingState.NEW_KEYFRAME and self._not_saved_keyframe(kid, H):
            self._counters["reference_changes"] += 1
            self._new_reference(
                f"keyframe {kid} of reference {self.reference_id!r} is not the saved one (another "
                "homography): a tracker that started afresh; calibration restarted (zoom model kept)"
            )
            if self._zoom is not None:  # frames judged so far went through the saved reference's K
                self._restored_check = RestoredStateCheck(self.config)
            return self._with_homography(frame, H)
        fast = self._motion.fast(self.reference_id, frame.stamp, H, self.image_size)
        snap = self._snapshot
        calibrated = None
        off_model = False  # the homography is further from a rotating, zooming camera's than CONVERGED allows
        if self.phase is Phase.CALIBRATED:
            assert snap is not None
            try:
                new = frame.tracking_state == TrackingState.NEW_KEYFRAME
                against = self._tracked_against if new else None
                K, R, sigma_f, misfit = frame_intrinsics(snap, H, kid, self._links, against)
                off_model = not misfit <= self.config.converged_max_sigma_f
                if np.all(np.isfinite(K)) and K[0, 0] > 0.0:
                    calibrated = (K, R, sigma_f)
            except _TRANSFER_ERRORS as exc:
                self._warn(f"frame intrinsics failed: {exc}")
        if calibrated is not None and self._restored_lens_differs(snap, frame, calibrated[0][1, 1]):
            return self._with_homography(frame, H)  # reset: the frame begins the fresh start
        verdict = ZoomVerdict.PASS
        if calibrated is None:
            self._zoom_gate.no_focal()
        else:
            assert snap is not None
            verdict = self._zoom_gate.judge(snap.zoom_table, frame.zoom, calibrated[0][1, 1])
        self._tracked_against = kid
        if frame.tracking_state == TrackingState.NEW_KEYFRAME and kid not in self._seen_keyframes:
            self._keyframe_added(frame, kid, H, fast, verdict)
        elif frame.tracking_state == TrackingState.TRACKING and verdict in _USABLE and not fast:
            if off_model:  # its error would steer the solve (LM on eq. 22 takes the homography as it is)
                self._counters["off_model_frames"] += 1
            else:
                self._propose(frame, H, None if calibrated is None else calibrated[:2])
        if verdict is ZoomVerdict.REFUSE:
            self._counters["zoom_gate_rejections"] += 1
            return self._without_homography(frame)
        if calibrated is not None:
            assert snap is not None
            K, R, sigma_f = calibrated
            out = calibrated_output(
                snap, frame, K, R, sigma_f, self._plumb_bob(K, snap.shared_lam, self.image_size)
            )
            out.status, out.message = frame_status(
                out.status, out.message, out.sigma_f / out.K[1, 1], self.config.converged_max_sigma_f
            )
            if out.status not in _FLAGGED:
                self.last_good = out
            return out
        status = snap.state if snap is not None and snap.state in _FLAGGED else _S.INITIALISING
        out = self._prior_output(frame, status, H)
        if snap is not None and snap.message:
            out.message = snap.message
        elif status == _S.INITIALISING:
            out.message = initialising_reason(snap, self._counters["fast_motion_keyframes"], self.config)
        return out

    def _not_saved_keyframe(self, kid: int, H: Array) -> bool:
        """Whether a keyframe the tracker announces under the saved reference's name and a saved id is
        another image: a tracker without the saved map names its reference and keyframes as the saved
        ones only by chance (the same first stamp), and its homographies are not of the saved images."""
        saved = self._restored_keyframes.get(kid)
        if saved is None or self.image_size is None:
            return False
        return image_motion(saved, H, *self.image_size) > _SAME_KEYFRAME

    def _restored_lens_differs(self, snap: CalibrationSnapshot | None, frame: FrameInput, f: float) -> bool:
        """Whether the restored state proved to be of another lens (a swap at the same image size):
        then the session has started fresh, with a warning."""
        check = self._restored_check
        if check is None or snap is None:
            return False
        why = check.judge(snap.zoom_table, float(frame.zoom), self._zoom_gate.previous_zoom, float(f))
        if check.done:
            self._restored_check = None
        if why is None:
            return False
        self._stale_state = (
            f"the saved calibration state does not fit these images: {why} "
            "(a swapped camera or lens?): starting fresh"
        )
        self.reset(self._stale_state)
        return True

    def _keyframe_added(
        self, frame: FrameInput, kid: int, H: Array, fast: bool, verdict: ZoomVerdict
    ) -> None:
        """A new keyframe enters the solve unless a gate keeps it out (online/gates.py)."""
        self._seen_keyframes.add(kid)
        if len(self._seen_keyframes) > 8192:  # bounded memory: ids grow with the frame index
            self._seen_keyframes = set(sorted(self._seen_keyframes)[4096:])
        if verdict is ZoomVerdict.REFUSE:  # a wrong homography: not in the solve, no K carried through it
            self._links.refuse(kid)
            return
        self._links.add_keyframe(kid, H)
        if fast:
            self._counters["fast_motion_keyframes"] += 1
        elif verdict is ZoomVerdict.HOLD:
            self._counters["unconfirmed_keyframes"] += 1
        else:
            self._pending.append(
                PendingKeyframe(kid, H, float(frame.stamp), float(frame.zoom), self._zoom_rate)
            )
            calibrator = self._set_calibrator()
            if calibrator is not None:
                self._selector.member(kid, H, calibrator)

    def _propose(self, frame: FrameInput, H: Array, KR: tuple[Array, Array] | None) -> None:
        """An ordinary frame joins the solve when it adds rotation or zoom to the set (online/selection)."""
        calibrator = self._set_calibrator() if self.config.calibration_frames else None
        stamp = float(frame.stamp)
        if (
            self.phase is Phase.CALIBRATED
            and 0.0 <= stamp - self._last_proposal < self.config.calibration_frame_period_s
        ):
            return
        if calibrator is None:
            return
        frame_id = self._selector.propose(H, calibrator, KR)
        if frame_id is None:
            return
        kid = int(frame.keyframe_id)
        solved = self._snapshot.keyframes.get(kid) if self._snapshot is not None else None
        H_key = solved[0] if solved is not None else self._links.homography.get(kid)
        anchor = None if H_key is None else (kid, H @ np.linalg.inv(H_key))
        zoom, self._last_proposal = float(frame.zoom), stamp
        self._pending.append(
            PendingKeyframe(frame_id, H, stamp, zoom, self._zoom_rate, tracked=False, anchor=anchor)
        )

    def _set_calibrator(self) -> IncrementalCalibrator | None:
        """The calibration the set's frames are compared under: the latest, else the prior."""
        if self._snapshot is not None:
            return self._snapshot.calibrator
        if self.image_size is None:
            return None
        key = (self.image_size, id(self._zoom))
        if self._prior is None or self._prior[0] != key:
            self._prior = (key, self._prior_calibrator())
        return self._prior[1]

    def _prior_output(self, frame: FrameInput, status: str, H: Array) -> FrameOutput:
        """Before calibration: the zoom model at this zoom, else the prior reference K through H."""
        snap = self._snapshot
        predicted = self._predict_from_zoom(frame, status)
        if predicted is not None:
            if snap is not None:
                with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                    predicted.R = rotation_from_homography(H, snap.calibrator.reference_K, predicted.K)
            return predicted
        out = self.nominal_output(frame, status)
        if snap is None and self.image_size is None:
            return out
        try:
            prior = snap.calibrator if snap is not None else self._prior_calibrator()
            K, R, _ = prior.frame_intrinsics(H)
            if np.all(np.isfinite(K)) and K[0, 0] > 0:
                out.K, out.R = np.asarray(K, dtype=float), np.asarray(R, dtype=float)
                out.sigma_f = self.config.prior_sigma_f_fraction * float(K[0, 0])
                out.source = "prior"
        except _TRANSFER_ERRORS:
            K_ref = out.K if snap is None else snap.calibrator.reference_K
            with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                out.R = rotation_from_homography(H, K_ref, out.K)
        return out

    def _prior_calibrator(self) -> IncrementalCalibrator:
        assert self.image_size is not None
        return new_calibrator(self.config, self.image_size, self._zoom, math.nan, given_K=self._given_K())

    def _given_K(self) -> Array | None:
        """The given prior K (camera_info_url, set_camera_info) when it is of these images."""
        given = self._given_prior
        if given is None or given[1] != self.image_size:
            return None
        return given[0].copy()

    def _check_prior_size(self) -> None:
        given = self._given_prior
        if given is not None and given[1] != self.image_size:
            self._counters["prior_size_mismatches"] += 1
            self._warn(
                f"the given prior K is of {given[1][0]}x{given[1][1]} images, these are "
                f"{self.image_size[0]}x{self.image_size[1]}: ignored, the nominal prior instead"
            )
            self._given_prior = None

    def _without_homography(self, frame: FrameInput) -> FrameOutput:
        predicted = self._predict_from_zoom(frame, _S.PREDICTED_FROM_ZOOM)
        if predicted is not None:
            return predicted
        if self.last_good is not None:
            return last_good_output(self.last_good)
        return self.nominal_output(frame, _S.TRACKING_LOST)

    def nominal_output(self, frame: FrameInput, status: str) -> FrameOutput:
        """The nominal calibration of a frame: what the node publishes when nothing else is known."""
        size = self.image_size or (max(frame.width, 1), max(frame.height, 1))
        count = self._snapshot.keyframe_count if self._snapshot else 0
        out = nominal_output(self.config, size, frame, status, count)
        given = self._given_K()
        if given is not None:
            out.K = given
            out.sigma_f = self.config.prior_sigma_f_fraction * float(given[1, 1])
        return out

    def _predict_from_zoom(self, frame: FrameInput, status: str) -> FrameOutput | None:
        count = self._snapshot.keyframe_count if self._snapshot else 0
        try:
            return zoom_output(self._zoom, frame, self._zoom_rate, status, count)
        except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
            self._warn(f"zoom model prediction failed: {exc}")
            return None

    def add_keyframe_matches(
        self,
        keyframe_id: int,
        other_keyframe_id: int,
        points: Array,
        other_points: Array,
        H: Array | None = None,
    ) -> bool:
        """Inlier matches between two keyframes (points in keyframe_id, other_points in the other);
        H maps other_keyframe_id pixels to keyframe_id pixels (KeyframeMatches.h)."""
        a = np.asarray(points, dtype=float).reshape(-1, 2)
        b = np.asarray(other_points, dtype=float).reshape(-1, 2)
        if len(a) != len(b) or len(a) < 8 or not (np.isfinite(a).all() and np.isfinite(b).all()):
            self._warn(
                f"keyframe matches {keyframe_id}<->{other_keyframe_id} unusable ({len(a)}/{len(b)} points)"
            )
            return False
        matches = KeyframeMatchSet(int(keyframe_id), int(other_keyframe_id), a, b)
        self._pending_matches.append((self._counters["frames"], matches))
        h = None  # a keyframe not yet in the solve borrows the calibration of the keyframe it is linked to
        if H is not None:
            h = np.asarray(H, dtype=float).reshape(3, 3)
            if not (np.all(np.isfinite(h)) and abs(np.linalg.det(h)) > 0.0):
                h = None
        self._links.link(int(keyframe_id), int(other_keyframe_id), h)
        self._counters["keyframe_matches"] += 1
        return True

    def set_distortion(self, distortion: DistortionFn | None) -> None:
        """A zoom lens's distortion (K -> plumb_bob D) from the lens correction; None: not estimated."""
        self._plumb_bob = PlumbBob(distortion)
        self.calibration.set_distortion(distortion)

    # ---- events between the halves ---------------------------------------------------------------
    def take_work(self, paced: bool = True) -> WorkBatch:
        """The keyframes and matches collected since the last batch, for the solving half (paced: its
        re-optimisations keep to max_solve_duty of a core; False: they run whenever due)."""
        refused = self._links.refused
        ready, waiting = [], []
        for arrival, m in self._pending_matches:
            (ready if self._ready(arrival, m) else waiting).append((arrival, m))
        self._pending_matches = waiting
        matches = tuple(m for _, m in ready if not {m.keyframe_id, m.other_keyframe_id} & refused)
        work = WorkBatch(self._epoch, self.image_size, tuple(self._pending), matches, paced)
        self._pending = []
        return work

    def _ready(self, arrival: int, matches: KeyframeMatchSet) -> bool:
        """A keyframe's matches wait for its own frame (they come on another topic, maybe first), so that
        the solve sees them at the same point whatever the arrival order; a keyframe whose frame never
        comes (shed upstream) lets them go after a few frames."""
        waited = self._counters["frames"] - arrival
        return matches.keyframe_id in self._seen_keyframes or waited >= _MATCH_WAIT_FRAMES

    def accept(self, result: WorkResult) -> bool:
        """A result of the solving half; False (dropped) when it belongs to an older reference."""
        if result.epoch != self._epoch:
            return False
        self._result = result
        self._warnings.extend(result.warnings)
        if result.zoom_model is not None:
            self._zoom = result.zoom_model if result.zoom_ready else None
        if result.snapshot is not None:
            self._snapshot = result.snapshot
            if not result.backlog:  # every frame handed over is in the solve, or was dropped by it
                held = {int(kf.keyframe_id) for kf in result.snapshot.calibrator.keyframes}
                self._selector.keep_only(held | {int(p.keyframe_id) for p in self._pending})
            if result.snapshot.calibrated:
                self.phase = Phase.CALIBRATED
            elif self.phase is Phase.CALIBRATED:
                self.phase = Phase.REFERENCED
        return True

    def step(self, max_seconds: float, paced: bool = True) -> bool:
        """Run the solving half inline on what was collected; True if it solved (paced: as take_work;
        False: the schedule of `ptz-selfcal run --deterministic`, no clock in what is solved)."""
        if self.take_forget():
            self.reset_solving_half()
        result = self.calibration.apply(self.take_work(paced), max_seconds)
        self.accept(result)
        return result.solved

    def replace_keyframe_homographies(self, homographies: Mapping[int, Array]) -> None:
        """The lens correction re-corrected the keyframes' homographies (KeyframeCalibration's)."""
        self.accept(self.calibration.replace_keyframe_homographies(homographies))

    def _new_reference(self, why: str) -> None:
        """The reference changed: a new epoch; the calibration restarts, the zoom model is kept."""
        self._warn(why)
        self._epoch += 1
        self._snapshot = None
        self.reference_id = None
        self.phase = Phase.NO_REFERENCE
        self._seen_keyframes.clear()
        self._links.forget_reference()
        self._motion.forget()
        self._last_proposal = -math.inf
        self._tracked_against = None
        self._restored_keyframes = {}
        self._pending.clear()
        self._selector.forget()

    # ---- a given prior, a reset ------------------------------------------------------------------
    def seed_prior(self, K: Array, size: tuple[int, int]) -> None:
        """camera_info_url's K as the prior of both halves, before any frame (and again after a reset)."""
        self._startup_prior = (np.asarray(K, dtype=float).copy(), (int(size[0]), int(size[1])))
        self.set_prior(*self._startup_prior)
        self.calibration.prior = self._startup_prior

    def camera_info_problem(self, K: Array, size: tuple[int, int]) -> str | None:
        """Why K of images `size` cannot be this camera's calibration (set_camera_info), or None."""
        return intrinsics_problem(K, size, self.image_size)

    def set_prior(self, K: Array, size: tuple[int, int]) -> None:
        """The frame path's prior from now on (the solving half's: PriorCalibration.anchor)."""
        K = np.asarray(K, dtype=float)
        self._given_prior = (K / K[2, 2], (int(size[0]), int(size[1])))
        self._prior = None
        if self.image_size is not None:
            self._check_prior_size()

    def reset(self, why: str) -> None:
        """Start fresh, the frame path's part: a new epoch, no calibration, no zoom model, the startup
        prior; the solving half's part is `reset_solving_half`, on its owner's thread."""
        self._counters["resets"] += 1
        self._new_reference(why)
        self._zoom = None
        self.last_good = None
        self._given_prior = self._startup_prior
        self._prior = None
        self._restored_size = None
        self._restored_check = None
        self._frame_dirty = False
        self._forget_due = True
        self._fresh = True

    def take_forget(self) -> bool:
        """Whether a reset's solving half's part is due (once): then its owner calls reset_solving_half."""
        due, self._forget_due = self._forget_due, False
        return due

    def reset_solving_half(self) -> None:
        self.calibration.forget(self._startup_prior)

    def take_stale_state(self) -> str | None:
        """Why a saved state was dropped for not fitting the images (once), else None."""
        stale, self._stale_state = self._stale_state, None
        return stale

    def remove_state_files(self) -> list[Path]:
        """Delete the saved state in state_dir (a reset); the files removed."""
        return [] if self.state_dir is None else remove_state_files(self.state_dir)

    # ---- persistence -----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """What a restart needs (persist/session_state.py); reads both halves."""
        return self.calibration.to_dict(self.image_size, self.reference_id, self.last_good)

    def load_dict(self, data: dict) -> None:
        """Restore from `to_dict` output; StateFileError when it does not fit."""
        saved = state_from_dict(data, self.config.focal_model, self.solver)
        self.calibration.restore(saved)
        self.image_size, self.reference_id, self.last_good = (
            saved.image_size,
            saved.reference_id,
            saved.last_good,
        )
        self._seen_keyframes = set(saved.keyframe_zoom)
        self._selector.forget()
        if saved.calibrator is not None:
            self._selector.restored([int(kf.keyframe_id) for kf in saved.calibrator.keyframes])
        self.phase = Phase.NO_REFERENCE if saved.reference_id is None else Phase.REFERENCED
        if saved.calibrator is not None:
            self.accept(self.calibration.result())

    def save(self) -> list[str]:
        """Save the state and the zoom model atomically into state_dir; returns the files written."""
        if self.state_dir is None or self._fresh:
            return []
        written = self.write_state(self.to_dict())
        self.mark_saved()
        return written

    def write_state(self, data: dict) -> list[str]:
        """Write a `to_dict` and the zoom model (the node takes the dict under its lock, writes outside)."""
        assert self.state_dir is not None
        return write_state(self.state_dir, data, self.calibration.zoom_model)

    def mark_saved(self) -> None:
        self._frame_dirty = self.calibration.dirty = False
        self._counters["state_saves"] += 1

    @property
    def dirty(self) -> bool:
        return not self._fresh and (self._frame_dirty or self.calibration.dirty)

    @property
    def fresh(self) -> bool:
        """Reset, and no reference since: nothing to save (the deleted files are the state)."""
        return self._fresh

    def restore(self) -> list[str]:
        """Load the state and the zoom model from state_dir; returns log lines ("WARNING: ..." first).
        A corrupt file gives a warning and a fresh start for that part, never an exception."""
        messages: list[str] = []
        if self.state_dir is None:
            return messages
        for tmp in remove_stale_temporaries(self.state_dir):
            messages.append(f"removed {tmp}, the temporary file of a save interrupted by a kill")
        path = self.state_dir / STATE_FILE
        c = self.calibration
        try:
            data = load_yaml_file(path)
            if data is not None:
                self.load_dict(data)
                self._restored_size = self.image_size
                state = c.calibrator.state.value if c.calibrator else "none"
                messages.append(
                    f"restored calibration state from {path}: {state}, "
                    f"{len(c.keyframe_zoom)} keyframes, reference {self.reference_id!r}"
                )
        except StateFileError as exc:
            messages.append(f"WARNING: ignoring calibration state {path} ({exc}); starting fresh")
        messages += c.restore_zoom_model(self.state_dir / ZOOM_MODEL_FILE)
        self.accept(c.result())
        if c.zoom_ready:  # the first frames judged against its zoom model tell whether it is this lens
            self._restored_check = RestoredStateCheck(self.config)
        if self._snapshot is not None:
            self._restored_keyframes = {k: v[0].copy() for k, v in self._snapshot.keyframes.items()}
        return messages

    # ---- diagnostics -----------------------------------------------------------------------------
    @property
    def counters(self) -> dict[str, int]:
        """The frame path's counters and those of the solving half's last result."""
        return {**self._counters, **self._result.counters}

    def timings_ms(self) -> dict[str, float]:
        frames = np.fromiter(self._frame_times, float)

        def pct(q: float) -> float:
            return float(np.percentile(frames, q)) * 1e3 if frames.size else math.nan

        median, most = self._result.solve_ms
        return {
            "frame_ms_median": pct(50),
            "frame_ms_p95": pct(95),
            "frame_ms_max": pct(100),
            "solve_ms_median": median,
            "solve_ms_max": most,
        }

    @property
    def calibrator(self) -> IncrementalCalibrator | None:
        """The solving half's calibrator (what the lens correction reads between solves)."""
        return self.calibration.calibrator

    @property
    def solver(self) -> KeyframeBundleSolver:
        """The solving half's keyframe solver (the lens correction hands it the lens model)."""
        return self.calibration.solver

    @property
    def selector(self) -> CalibrationFrameSelector:
        """The frame path's choice of ordinary frames for the solve (online/selection.py)."""
        return self._selector

    @property
    def invalid_homographies(self) -> int:
        """Frames whose homography was non-finite or implausible (online/gates.usable_homography)."""
        return self._counters["invalid_homographies"]

    @property
    def snapshot(self) -> CalibrationSnapshot | None:
        """The calibration the frames are served from (None before the first, and after a reset)."""
        return self._snapshot

    @property
    def state(self) -> str:
        snap = self._snapshot
        return "NONE" if snap is None else snap.state

    @property
    def pending_work(self) -> int:
        """Keyframes, match sets and refinements not yet done by the solving half (0: it is idle)."""
        r = self._result
        ready = sum(self._ready(arrival, m) for arrival, m in self._pending_matches)
        return len(self._pending) + ready + r.backlog + int(r.needs_refinement)

    def _warn(self, text: str) -> None:
        self._warnings.append(text)

    def take_warnings(self) -> list[str]:
        out = list(self._warnings)
        self._warnings.clear()
        return out
