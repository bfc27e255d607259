"""The calibrator's per-frame logic and what it persists (pure: numpy + the calibration core, no rclpy).

`CalibratorSession` is everything the calibrator node does between "a HomographyStamped arrived" and
"publish this K". It wraps `online.incremental.IncrementalCalibrator` (initialisation once the motion is
well posed, section 6; bounded keyframe set; O(1) per-frame K by DIAC transfer) and plugs into its
solver seam `KeyframeBundleSolver`: LM on eq. 22 (section 3.3.1, initialised by the linear method of
3.3.2 inside lm_selfcalibration) refined by the keyframe bundle adjustment with the MAP
principal-point prior (eq. 27, section 5.2) on the tracker's keyframe point matches.

Threading model (the node runs `step` in a worker thread, never in the frame callback):
- `process(frame)` (frame thread) never solves: it queues a new keyframe and computes the frame's K
  from the latest immutable snapshot of the calibration (a read-only IncrementalCalibrator rebuilt
  with `from_dict` after every solve), so a frame never waits for a re-optimisation.
- `step(max_seconds)` (worker thread, or called inline by benchmarks/tests) adds the queued keyframes
  and matches to the calibrator, re-optimises over the keyframes, learns the zoom model and publishes
  a new snapshot.

Statuses: INITIALISING (no calibration yet; K from the zoom model if one was loaded, else nominal
parameters transferred through the frame's homography), DEGENERATE_MOTION (section 6: pan-only,
tilt-only, tiny rotations at long focal length), CALIBRATING / CONVERGED (the calibrator's state),
PREDICTED_FROM_ZOOM (no usable homography, or one the zoom gate refused: K from the zoom model),
TRACKING_LOST (no usable homography and no zoom model: the last good K).

Frame gates (issue 7, SessionConfig): a homography whose K contradicts the zoom model at a still zoom
is refused; keyframes of a fast move (a preset recall) and keyframes whose image zoomed while the zoom
encoder was still stay out of the solve (their frames keep the K of their homography).

State files (in the node's `state_dir`) are only ever replaced atomically: temporary file in the same
directory, fsync, os.replace, directory fsync. A corrupt or unreadable file is reported and ignored
(fresh start), never a crash.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray

from ptz_selfcal.camera.distortion import division_to_plumb_bob
from ptz_selfcal.camera.geometry import (
    intrinsic_matrix,
    rotation_from_homography,
)
from ptz_selfcal.camera.intrinsics import (
    SelfCalibrationError,
)
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput, FrameOutput
from ptz_selfcal.online.incremental import (
    CalibrationState,
    IncrementalCalibrator,
    focal_disagrees,
    image_motion,
    intrinsics_from_transferred_diac,
)
from ptz_selfcal.online.keyframe_solver import (
    KeyframeBundleSolver,
    KeyframeMatchSet,
)
from ptz_selfcal.persist.atomic_file import atomic_write_text, remove_stale_temporaries
from ptz_selfcal.persist.state_files import (
    STATE_FILE,
    STATE_VERSION,
    ZOOM_MODEL_FILE,
    StateFileError,
    load_yaml_file,
)
from ptz_selfcal.zoom import ZoomModel, ZoomModelError, ZoomRate

Array = NDArray[np.float64]

_LOG = logging.getLogger(__name__)


# FrameCalibration status names (the message constants have the same names).
INITIALISING = "INITIALISING"
CALIBRATING = "CALIBRATING"
CONVERGED = "CONVERGED"
DEGENERATE_MOTION = "DEGENERATE_MOTION"
TRACKING_LOST = "TRACKING_LOST"
PREDICTED_FROM_ZOOM = "PREDICTED_FROM_ZOOM"
STATUSES = (INITIALISING, CALIBRATING, CONVERGED, DEGENERATE_MOTION, TRACKING_LOST, PREDICTED_FROM_ZOOM)

# Verdicts of the zoom gate (CalibratorSession._zoom_gate).
_PASS, _HOLD, _REFUSE = "pass", "hold", "refuse"

# HomographyStamped.state names that carry a usable homography.
TRACKING_STATES_WITH_H = ("TRACKING", "NEW_KEYFRAME", "RELOCALISED")


# --------------------------------------------------------------------------------------------------
# The session
# --------------------------------------------------------------------------------------------------
@dataclass
class _PendingKeyframe:
    keyframe_id: int
    H: Array
    stamp: float
    zoom: float


@dataclass
class _Snapshot:
    """Immutable view of the calibration for the frame thread."""

    calibrator: IncrementalCalibrator
    calibrated: bool
    state: str
    message: str
    residual: float
    keyframe_count: int
    sigma_pp: tuple[float, float] = (math.nan, math.nan)
    # per keyframe of the solve: (H reference -> keyframe (unit det), K, R relative to the reference)
    keyframes: dict[int, tuple[Array, Array, Array]] = dataclasses.field(default_factory=dict)
    # the zoom model over its learned range for the frame gate: (zoom, f, sigma_f), None without a model
    zoom_table: tuple[Array, Array, Array] | None = None


class CalibratorSession:
    """One camera's self-calibration over a run (see the module docstring)."""

    def __init__(self, config: SessionConfig | None = None, state_dir: str | os.PathLike[str] | None = None):
        self.config = config or SessionConfig()
        self.state_dir = Path(state_dir) if state_dir else None
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "frames",
                "keyframes",
                "keyframe_matches",
                "invalid_homographies",
                "frames_without_homography",
                "reference_changes",
                "solves",
                "solve_failures",
                "calibrator_errors",
                "zoom_model_samples",
                "state_saves",
                "zoom_gate_rejections",
                "fast_motion_keyframes",
                "unconfirmed_keyframes",
            ),
            0,
        )
        self.status_counts: dict[str, int] = dict.fromkeys(STATUSES, 0)
        self._warnings: deque[str] = deque(maxlen=100)
        self._lock = threading.RLock()  # guards the calibrator, the matches and the zoom model
        self._pending: deque[_PendingKeyframe] = deque()
        self._pending_matches: deque[KeyframeMatchSet] = deque()
        self.matches: OrderedDict[tuple[int, int], KeyframeMatchSet] = OrderedDict()
        self.solver = KeyframeBundleSolver(self.config, self.matches)
        self.calibrator: IncrementalCalibrator | None = None
        self._snapshot: _Snapshot | None = None
        self.reference_id: str | None = None
        self.image_size: tuple[int, int] | None = None
        self.keyframe_zoom: dict[int, float] = {}
        self._sampled_keyframes: set[int] = set()
        self._neighbour: dict[int, tuple[int, Array | None]] = {}  # keyframe -> (linked keyframe, H)
        self.distortion_model: Any = None  # K -> plumb_bob D (None: distortion not estimated)
        self._keyframe_H: dict[int, Array] = {}  # keyframe -> H reference -> keyframe (as tracked)
        self._seen_keyframes: set[int] = set()
        self._refused_keyframes: set[int] = set()  # keyframes whose homography the zoom gate refused
        self._previous_frame: tuple[str | None, float, Array] | None = None  # (reference, stamp, H)
        self._previous_zoom = math.nan  # zoom encoder of the previous frame
        self._previous_focal = math.nan  # f of the previous frame from its homography (calibrated)
        self._zoom_table_cache: tuple[tuple, tuple[Array, Array, Array] | None] = ((), None)
        self.last_good: FrameOutput | None = None
        self.zoom_model = ZoomModel()
        self._zoom_ready = False
        self._zoom_rates = ZoomRate()
        self._zoom_rate = 0.0  # zoom encoder counts / s at the current frame (0 = unknown)
        self._keyframe_rate: dict[int, float] = {}  # keyframe -> zoom rate (the model learns the lag)
        self._dirty = False
        self._frame_times: deque[float] = deque(maxlen=2000)
        self._solve_times: deque[float] = deque(maxlen=200)
        self._plumb_bob_cache: tuple[tuple, Array] = ((), np.zeros(5))

    # ----------------------------------------------------------------------------------------------
    # Frame thread
    # ----------------------------------------------------------------------------------------------
    def process(self, frame: FrameInput) -> FrameOutput:
        """The calibration of one frame; O(1), never solves."""
        start = time.perf_counter()
        self.counters["frames"] += 1
        self._note_zoom_rate(frame)
        if frame.width > 0 and frame.height > 0 and self.image_size != (frame.width, frame.height):
            if self.image_size is not None:
                self._warn(f"image size changed from {self.image_size} to {(frame.width, frame.height)}")
                self._request_reset()
            self.image_size = (int(frame.width), int(frame.height))
        H = self._usable_homography(frame)
        if H is None:
            self.counters["frames_without_homography"] += 1
            self._previous_focal = math.nan
            out = self._without_homography(frame)
        else:
            out = self._with_homography(frame, H)
        self._previous_zoom = float(frame.zoom)
        out.time_s = time.perf_counter() - start
        self._frame_times.append(out.time_s)
        self.status_counts[out.status] += 1
        return out

    def _usable_homography(self, frame: FrameInput) -> Array | None:
        if frame.tracking_state not in TRACKING_STATES_WITH_H:
            return None
        if frame.H is None:
            self.counters["invalid_homographies"] += 1
            return None
        H = np.asarray(frame.H, dtype=float).reshape(3, 3)
        ok = bool(np.all(np.isfinite(H)))
        if ok:
            det = float(np.linalg.det(H))
            ok = math.isfinite(det) and det != 0.0 and abs(det) > 1e-12 * float(np.max(np.abs(H))) ** 3
        if ok:
            H = H / np.cbrt(det)
            # in coordinates centred and scaled by the image width the homography of a rotating,
            # zooming camera has singular values within the zoom ratio; wilder ones are tracker garbage
            w = float(max(frame.width, 1))
            N = np.array([[1 / w, 0, -0.5 * frame.width / w], [0, 1 / w, -0.5 * frame.height / w], [0, 0, 1]])
            s = np.linalg.svd(N @ H @ np.linalg.inv(N), compute_uv=False)
            ok = bool(np.all(np.isfinite(s))) and s[0] / max(s[2], 1e-300) < self.config.max_focal_ratio**2
        if not ok:
            self.counters["invalid_homographies"] += 1
            return None
        return H

    def _with_homography(self, frame: FrameInput, H: Array) -> FrameOutput:
        if frame.reference_id and self.reference_id is not None and frame.reference_id != self.reference_id:
            self.counters["reference_changes"] += 1
            self._warn(
                f"tracking reference changed from {self.reference_id!r} to {frame.reference_id!r}: "
                "calibration restarted on the new reference (zoom model kept)"
            )
            self._request_reset()
        if self.reference_id is None:
            self.reference_id = frame.reference_id
            self._dirty = True
        kid = int(frame.keyframe_id)
        fast = self._fast_motion(frame, H)
        snap = self._snapshot
        calibrated = None
        if snap is not None and snap.calibrated:
            try:
                K, R, sigma_f = self._frame_intrinsics(snap, H, kid)
                if np.all(np.isfinite(K)) and K[0, 0] > 0.0:
                    calibrated = (K, R, sigma_f)
            except (SelfCalibrationError, ValueError, np.linalg.LinAlgError) as exc:
                self._warn(f"frame intrinsics failed: {exc}")
        verdict = _PASS
        if calibrated is None:
            self._previous_focal = math.nan
        else:
            verdict = self._zoom_gate(snap, frame, calibrated[0])
        refused = verdict == _REFUSE
        if frame.tracking_state == "NEW_KEYFRAME" and kid not in self._seen_keyframes:
            self._seen_keyframes.add(kid)
            if len(self._seen_keyframes) > 8192:  # bounded memory: ids grow with the frame index
                self._seen_keyframes = set(sorted(self._seen_keyframes)[4096:])
            if refused:  # a wrong homography: not in the solve, and no K is carried through it
                self._refused_keyframes.add(kid)
                if len(self._refused_keyframes) > 4096:
                    self._refused_keyframes = set(sorted(self._refused_keyframes)[2048:])
            else:
                self._keyframe_H[kid] = H
                if len(self._keyframe_H) > 4096:
                    self._keyframe_H.pop(next(iter(self._keyframe_H)))
                if fast:
                    self.counters["fast_motion_keyframes"] += 1
                elif verdict == _HOLD:
                    self.counters["unconfirmed_keyframes"] += 1
                else:
                    self._pending.append(_PendingKeyframe(kid, H, float(frame.stamp), float(frame.zoom)))
        if refused:
            self.counters["zoom_gate_rejections"] += 1
            return self._without_homography(frame)
        if calibrated is not None:
            return self._calibrated_output(snap, frame, *calibrated)
        status = DEGENERATE_MOTION if snap is not None and snap.state == DEGENERATE_MOTION else INITIALISING
        out = self._prior_output(frame, status, H)
        if snap is not None and snap.message:
            out.message = snap.message
        elif status == INITIALISING:
            out.message = self._initialising_reason(snap)
        return out

    def _initialising_reason(self, snap: _Snapshot | None) -> str:
        """Why there is no calibration yet, for FrameCalibration users and logs."""
        held = self.counters["fast_motion_keyframes"]
        reason = ""
        if snap is not None:
            found = snap.keyframe_count - 1
            reason = f"{found} of min_keyframes {self.config.min_keyframes} keyframes"
        if held:
            reason += (", " if reason else "") + (
                f"{held} keyframes held out of the solve: the image moved faster than "
                f"max_keyframe_motion {self.config.max_keyframe_motion:g} image widths/s"
            )
        return reason

    def _fast_motion(self, frame: FrameInput, H: Array) -> bool:
        """Whether the image moved faster than max_keyframe_motion since the previous frame with a
        homography on the same reference (per second of stamps: frames shed upstream do not count)."""
        previous = self._previous_frame
        self._previous_frame = (self.reference_id, float(frame.stamp), H)
        if previous is None or previous[0] != self.reference_id or self.image_size is None:
            return False
        dt = float(frame.stamp) - previous[1]
        dt = dt if math.isfinite(dt) and dt > 0.0 else 1.0 / 30.0
        motion = image_motion(previous[2], H, *self.image_size)
        return motion / dt > self.config.max_keyframe_motion

    def _zoom_gate(self, snap: _Snapshot, frame: FrameInput, K: Array) -> str:
        """The zoom gate: K from the frame's homography against the zoom model at its zoom encoder.

        Judged only inside the model's learned zoom range (outside it the model extrapolates) and while
        the encoder says the zoom is still (the model at this and at the previous frame's encoder within
        zoom_gate_still): while zooming the encoder can lag the image (frame_ingest pairs an image with
        a sample up to max_hold older, and a fast zoom moves 50 % between frames). Then _HOLD when the
        image zoomed by more than half the floor since the previous frame all the same (a lagging or
        held encoder at the start of a fast zoom, or a wrong homography: the frame keeps its K, its
        keyframe stays out of the solve), _REFUSE when the focal length disagrees with the model
        (focal_disagrees: an encoder one frame behind a zoom of less than half the floor per frame
        stays within the floor), else _PASS.
        """
        previous_f, self._previous_focal = self._previous_focal, float(K[1, 1])
        table = snap.zoom_table
        zooms = np.array([frame.zoom, self._previous_zoom])
        if table is None or not np.all(np.isfinite(zooms)):
            return _PASS
        z, f, sigma = table
        if not (z[0] <= zooms.min() and zooms.max() <= z[-1]):
            return _PASS
        f_pred = np.interp(zooms, z, f)
        c = self.config
        if abs(math.log(f_pred[0] / f_pred[1])) > c.zoom_gate_still:
            return _PASS
        if not math.isfinite(previous_f) or abs(math.log(K[1, 1] / previous_f)) > 0.5 * c.zoom_gate_floor:
            return _HOLD
        relative = float(np.interp(frame.zoom, z, sigma) / f_pred[0])
        f_pred0 = float(f_pred[0])
        if focal_disagrees(float(K[1, 1]), f_pred0, f_pred0, relative, c.zoom_gate_sigmas, c.zoom_gate_floor):
            return _REFUSE
        return _PASS

    def _frame_intrinsics(self, snap: _Snapshot, H: Array, keyframe_id: int) -> tuple[Array, Array, float]:
        """K_j, R_j, sigma_f in O(1).

        When the frame was tracked against a keyframe of the solve, its K is that keyframe's refined K
        (bundle adjustment) transferred by the short keyframe -> frame homography H_j H_k^-1, and its
        orientation R_kj R_k: the error of the long reference -> keyframe chain does not enter.
        Otherwise the reference calibration is transferred by the frame's homography (eq. 20).
        """
        K_ref, R_ref, sigma_f = snap.calibrator.frame_intrinsics(H)
        model, size = snap.calibrator.model, snap.calibrator.image_size
        local = snap.keyframes.get(keyframe_id)
        if local is None:
            local = self._unsolved_keyframe(snap, keyframe_id)
        if local is None:
            return K_ref, R_ref, sigma_f
        H_k, K_k, R_k = local
        H_local = H @ np.linalg.inv(H_k)
        K = intrinsics_from_transferred_diac(H_local, K_k, model, size)
        R = rotation_from_homography(H_local, K_k, K) @ R_k
        return K, R, sigma_f * K[1, 1] / K_ref[1, 1]

    def _unsolved_keyframe(self, snap: _Snapshot, keyframe_id: int) -> tuple[Array, Array, Array] | None:
        """(H_ref_to_kf, K, R) of a keyframe the solve has not seen yet (the newest ones).

        Follows the tracker's keyframe links back to a solved keyframe and carries its refined K and R
        forward through the links' own homographies (direct keyframe-to-keyframe measurements), so the
        new keyframe's calibration does not depend on the tracker's long chain to the reference.
        """
        chain: list[Array] = []
        kid = keyframe_id
        while kid not in snap.keyframes and kid in self._neighbour and len(chain) < 16:
            kid, h = self._neighbour[kid]
            chain.append(h)
            if kid in self._refused_keyframes:
                return None
        solved = snap.keyframes.get(kid)
        if solved is None:
            return None
        H_kf = self._keyframe_H.get(keyframe_id)
        if H_kf is None or any(h is None for h in chain):  # links without their homography
            return solved
        _, K, R = solved
        model, size = snap.calibrator.model, snap.calibrator.image_size
        for h in reversed(chain):
            K_next = intrinsics_from_transferred_diac(h, K, model, size)
            R = rotation_from_homography(h, K, K_next) @ R
            K = K_next
        return H_kf, K, R

    def _calibrated_output(
        self, snap: _Snapshot, frame: FrameInput, K: Array, R: Array, sigma_f: float
    ) -> FrameOutput:
        status = snap.state if snap.state in (CALIBRATING, CONVERGED, DEGENERATE_MOTION) else CALIBRATING
        out = FrameOutput(
            status=status,
            K=np.asarray(K, dtype=float),
            D=self._distortion_of(np.asarray(K, dtype=float)),
            R=np.asarray(R, dtype=float) if np.all(np.isfinite(R)) else None,
            sigma_f=float(sigma_f),
            sigma_cx=snap.sigma_pp[0],
            sigma_cy=snap.sigma_pp[1],
            residual=snap.residual,
            keyframe_id=int(frame.keyframe_id),
            keyframe_count=snap.keyframe_count,
            source="calibration",
            message=snap.message,
        )
        if status != DEGENERATE_MOTION:
            self.last_good = out
        return out

    def _prior_output(self, frame: FrameInput, status: str, H: Array | None) -> FrameOutput:
        """Before calibration: the zoom model at this zoom, else the prior reference K through H."""
        predicted = self._predict_from_zoom(frame, status)
        if predicted is not None:
            predicted.source = "zoom_model"
            if H is not None and self._snapshot is not None:
                with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                    predicted.R = rotation_from_homography(
                        H, self._snapshot.calibrator.reference_K, predicted.K
                    )
            return predicted
        out = self._nominal_output(frame, status)
        snap = self._snapshot
        K_ref = out.K if snap is None else snap.calibrator.reference_K
        if H is not None and (snap is not None or self.image_size is not None):
            try:
                K, R, _ = (
                    snap.calibrator if snap is not None else self._prior_calibrator()
                ).frame_intrinsics(H)
                if np.all(np.isfinite(K)) and K[0, 0] > 0:
                    out.K, out.R = np.asarray(K, dtype=float), np.asarray(R, dtype=float)
                    out.sigma_f = self.config.prior_sigma_f_fraction * float(K[0, 0])
                    out.source = "prior"
            except (SelfCalibrationError, ValueError, np.linalg.LinAlgError):
                with contextlib.suppress(ValueError, np.linalg.LinAlgError):
                    out.R = rotation_from_homography(H, K_ref, out.K)
        return out

    def _without_homography(self, frame: FrameInput) -> FrameOutput:
        predicted = self._predict_from_zoom(frame, PREDICTED_FROM_ZOOM)
        if predicted is not None:
            return predicted
        if self.last_good is not None:
            last = self.last_good
            return FrameOutput(
                status=TRACKING_LOST,
                K=last.K.copy(),
                D=last.D.copy(),
                R=None,
                sigma_f=last.sigma_f,
                sigma_cx=last.sigma_cx,
                sigma_cy=last.sigma_cy,
                residual=math.nan,
                keyframe_id=last.keyframe_id,
                keyframe_count=last.keyframe_count,
                source="last_good",
            )
        return self._nominal_output(frame, TRACKING_LOST)

    def _nominal_output(self, frame: FrameInput, status: str) -> FrameOutput:
        width, height = self.image_size or (max(frame.width, 1), max(frame.height, 1))
        f = self.config.nominal_focal(width)
        return FrameOutput(
            status=status,
            K=intrinsic_matrix(f, 0.5 * (width - 1.0), 0.5 * (height - 1.0)),
            D=np.zeros(5),
            R=None,
            sigma_f=self.config.prior_sigma_f_fraction * f,
            sigma_cx=0.05 * width,
            sigma_cy=0.05 * height,
            residual=math.nan,
            keyframe_id=int(frame.keyframe_id),
            keyframe_count=self._snapshot.keyframe_count if self._snapshot else 0,
            source="nominal",
        )

    def _prior_calibrator(self) -> IncrementalCalibrator:
        assert self.image_size is not None
        return self._new_calibrator()

    # ---- zoom model ------------------------------------------------------------------------------
    def _note_zoom_rate(self, frame: FrameInput) -> None:
        """Zoom encoder rate at this frame, remembered for keyframes: with it the zoom model learns
        the encoder's lag (ZoomModel.set_live) and predicts through it."""
        rate = self._zoom_rates.update(float(frame.stamp), float(frame.zoom))
        self._zoom_rate = rate
        if frame.tracking_state == "NEW_KEYFRAME":
            self._keyframe_rate[int(frame.keyframe_id)] = rate
            if len(self._keyframe_rate) > 4096:
                self._keyframe_rate.pop(next(iter(self._keyframe_rate)))

    def _predict_from_zoom(self, frame: FrameInput, status: str) -> FrameOutput | None:
        if not math.isfinite(frame.zoom) or not self._zoom_ready:
            return None
        with self._lock:
            try:
                K, D, sigma_f, _ = self.zoom_model.predict(float(frame.zoom), self._zoom_rate)
            except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
                self._warn(f"zoom model prediction failed: {exc}")
                return None
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0.0:
            return None
        return FrameOutput(
            status=status,
            K=np.asarray(K, dtype=float),
            D=np.nan_to_num(np.asarray(D, dtype=float).reshape(5)),
            R=None,
            sigma_f=float(sigma_f),
            sigma_cx=math.nan,
            sigma_cy=math.nan,
            residual=math.nan,
            keyframe_id=int(frame.keyframe_id),
            keyframe_count=self._snapshot.keyframe_count if self._snapshot else 0,
            source="zoom_model",
        )

    def _distortion_of(self, K: Array) -> Array:
        """plumb_bob D of a calibrated frame: from `distortion_model` (e.g. lens/correction's
        SessionLensHook.distortion) when one is plugged in, else zeros (not estimated)."""
        model = self.distortion_model
        if model is None and self.solver.shared_lam is not None and self.image_size is not None:
            model = self._shared_plumb_bob  # a fixed lens's one coefficient (SessionConfig)
        if model is None:
            return np.zeros(5)
        try:
            D = np.asarray(model(K), dtype=float).ravel()
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            return np.zeros(5)
        out = np.zeros(5)
        out[: min(5, D.size)] = D[:5]
        return out if np.all(np.isfinite(out)) else np.zeros(5)

    def _shared_plumb_bob(self, K: Array) -> Array:
        """plumb_bob D of the fixed lens's division coefficient at K (one fit per estimate)."""
        lam = self.solver.shared_lam
        assert lam is not None and self.image_size is not None
        key = (lam, *np.round(np.asarray(K, dtype=float)[[0, 0, 1], [0, 2, 2]], 3))
        if self._plumb_bob_cache[0] != key:
            k1, k2 = division_to_plumb_bob(lam, K, *self.image_size)
            self._plumb_bob_cache = (key, np.array([k1, k2, 0.0, 0.0, 0.0]))
        return self._plumb_bob_cache[1]

    # ---- keyframe matches (frame thread queues, worker applies) ------------------------------------
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
        self._pending_matches.append(KeyframeMatchSet(int(keyframe_id), int(other_keyframe_id), a, b))
        # a keyframe not yet in the solve borrows the calibration of the keyframe it is linked to
        h = None
        if H is not None:
            h = np.asarray(H, dtype=float).reshape(3, 3)
            if not (np.all(np.isfinite(h)) and abs(np.linalg.det(h)) > 0.0):
                h = None
        if int(keyframe_id) not in self._neighbour and int(other_keyframe_id) != int(keyframe_id):
            self._neighbour[int(keyframe_id)] = (int(other_keyframe_id), h)
        if len(self._neighbour) > 4096:
            self._neighbour.pop(next(iter(self._neighbour)))
        self.counters["keyframe_matches"] += 1
        return True

    # ----------------------------------------------------------------------------------------------
    # Worker: add keyframes, solve, publish a snapshot
    # ----------------------------------------------------------------------------------------------
    def step(self, max_seconds: float) -> bool:
        """Apply queued keyframes and matches, re-optimise within about max_seconds; True if it solved."""
        with self._lock:
            if self.image_size is None:
                return False
            if self._reset_requested:
                self._do_reset()
            while self._pending_matches:
                m = self._pending_matches.popleft()
                if m.keyframe_id in self._refused_keyframes or m.other_keyframe_id in self._refused_keyframes:
                    continue  # a keyframe whose homography was refused stays out of the adjustment
                self.matches[(m.keyframe_id, m.other_keyframe_id)] = m
                while len(self.matches) > self.config.max_match_pairs:
                    self.matches.popitem(last=False)
            if self.calibrator is None:
                self.calibrator = self._new_calibrator()
            calibrator = self.calibrator
            added = 0
            solved = False
            start = time.perf_counter()
            while self._pending:
                kf = self._pending.popleft()
                if np.allclose(kf.H, np.eye(3), atol=1e-9):
                    self.solver.reference_keyframe_id = kf.keyframe_id  # the reference itself
                    self.keyframe_zoom[kf.keyframe_id] = kf.zoom
                    continue
                was_calibrated = calibrator.calibrated
                before = calibrator.last_solve
                try:
                    calibrator.add_keyframe(kf.keyframe_id, kf.H, kf.stamp)
                except (SelfCalibrationError, ValueError, np.linalg.LinAlgError) as exc:
                    self.counters["calibrator_errors"] += 1
                    self._warn(f"keyframe {kf.keyframe_id} rejected: {exc}")
                    continue
                self.keyframe_zoom[kf.keyframe_id] = kf.zoom
                self.counters["keyframes"] += 1
                added += 1
                if calibrator.last_solve is not before:
                    solved = True
                    self._solved(calibrator, time.perf_counter() - start, first=not was_calibrated)
                if time.perf_counter() - start > max_seconds:
                    break
            remaining = max_seconds - (time.perf_counter() - start)
            if added:
                self._needs_refinement = True
            due = time.monotonic() >= self._next_solve
            if calibrator.calibrated and self._needs_refinement and remaining > 0.0 and not solved and due:
                before = calibrator.last_solve
                t0 = time.perf_counter()
                try:
                    calibrator.reoptimise(remaining)
                except (SelfCalibrationError, ValueError, np.linalg.LinAlgError) as exc:
                    self.counters["calibrator_errors"] += 1
                    self._warn(f"re-optimisation failed: {exc}")
                if calibrator.last_solve is not before:
                    solved = True
                    self._solved(calibrator, time.perf_counter() - t0, first=False)
                else:
                    self.counters["solve_failures"] += 1
                self._needs_refinement = False
                spent = time.perf_counter() - t0
                duty = min(max(self.config.max_solve_duty, 1e-3), 1.0)
                wait = max(self.config.min_solve_period_s, spent * (1.0 - duty) / duty)
                self._next_solve = time.monotonic() + wait
            if added:  # bounded memory: forget keyframes the calibrator dropped
                live = {int(kf.keyframe_id) for kf in calibrator.keyframes}
                if self.solver.reference_keyframe_id is not None:
                    live.add(int(self.solver.reference_keyframe_id))
                self.keyframe_zoom = {k: v for k, v in self.keyframe_zoom.items() if k in live}
                self._sampled_keyframes &= live
                self.solver.rotations = {k: v for k, v in self.solver.rotations.items() if k in live}
            if added or solved or self._snapshot is None:
                self._publish_snapshot()
                self._dirty = True
            return solved

    _reset_requested = False
    _needs_refinement = False
    _next_solve = 0.0

    def _new_calibrator(self) -> IncrementalCalibrator:
        assert self.image_size is not None
        width, height = self.image_size
        f = self.config.nominal_focal(width)
        prior = intrinsic_matrix(f, 0.5 * (width - 1.0), 0.5 * (height - 1.0))
        zoom = (
            self.keyframe_zoom.get(self.solver.reference_keyframe_id, math.nan) if self.solver else math.nan
        )
        if self._zoom_ready and math.isfinite(zoom):
            with contextlib.suppress(ZoomModelError, ValueError):
                prior = self.zoom_model.predict(zoom).K
        return IncrementalCalibrator(
            self.image_size,
            self.config.intrinsics_model(),
            min_rotation_deg=self.config.min_rotation_deg,
            max_keyframes=self.config.max_keyframes,
            prior_K=prior,
            solver=self.solver,
            solve_interval=1_000_000_000,  # re-solves are the worker's, bounded in time
            min_keyframes=self.config.min_keyframes,
        )

    def _solved(self, calibrator: IncrementalCalibrator, seconds: float, first: bool) -> None:
        self.counters["solves"] += 1
        self._solve_times.append(seconds)
        if first and calibrator.calibrated:
            self._needs_refinement = True  # a second, warm-started pass (with BA) right away
        if calibrator.state is CalibrationState.CONVERGED:
            self._learn_zoom_model(calibrator)

    def keyframe_homographies_changed(self) -> None:
        """The calibrator's keyframe homographies were replaced in place (lens/correction's
        SessionLensHook after a distortion update): publish them, so that the frame thread composes a
        frame's homography and its keyframe's from the same correction (a stale keyframe homography
        against a re-corrected frame one: replayed issue-6 bag focal p90 2.6% instead of 0.7%)."""
        with self._lock:
            if self.calibrator is not None and self.image_size is not None:
                self._publish_snapshot()

    def _publish_snapshot(self) -> None:
        calibrator = self.calibrator
        assert calibrator is not None
        snapshot_calibrator = IncrementalCalibrator.from_dict(calibrator.to_dict())
        residual = calibrator.last_solve.residual if calibrator.last_solve is not None else math.nan
        message = calibrator.message or (calibrator.motion.message if calibrator.motion else "")
        keyframes: dict[int, tuple[Array, Array, Array]] = {}
        if calibrator.calibrated:
            K_ref = calibrator.reference_K
            for kf in calibrator.keyframes:
                if kf.K is None:
                    continue
                R = self.solver.rotations.get(kf.keyframe_id)
                if R is None:
                    R = rotation_from_homography(kf.H, K_ref, kf.K)
                keyframes[int(kf.keyframe_id)] = (kf.H.copy(), kf.K.copy(), np.asarray(R, dtype=float).copy())
            ref = self.solver.reference_keyframe_id
            if ref is not None:
                keyframes[int(ref)] = (np.eye(3), K_ref, np.eye(3))
        state = calibrator.state.value
        solve = calibrator.last_solve
        if self.config.fixed_lens and state == CONVERGED and solve is not None:
            # a stable solution is not yet the calibration while its focal length is this uncertain
            rel = solve.sigma_f_ref / solve.K_ref[1, 1]
            if not rel <= self.config.converged_max_sigma_f:
                state = CALIBRATING
                message = f"1-sigma of f {100 * rel:.2g}% > {100 * self.config.converged_max_sigma_f:.2g}%"
            elif not (change := self.solver.lens_model_change) <= self.config.converged_max_lens_model_change:
                state = CALIBRATING
                message = (
                    f"f moves by {100 * change:.2g}% with the radial term toggled "
                    f"(> {100 * self.config.converged_max_lens_model_change:.2g}%): not pinned by geometry"
                )
        self._snapshot = _Snapshot(
            zoom_table=self._zoom_table(),
            keyframes=keyframes,
            calibrator=snapshot_calibrator,
            calibrated=calibrator.calibrated,
            state=state,
            message=message,
            residual=float(residual),
            keyframe_count=len(calibrator.keyframes) + 1,
        )

    def _zoom_table(self, points: int = 17) -> tuple[Array, Array, Array] | None:
        """The zoom model sampled over its learned range (zoom, f, sigma_f) for the frame thread's gate
        (np.interp there: no lock, no spline evaluation per frame); None when there is no usable model.
        Recomputed only when the model can have changed (a solve, a loaded model): ~7 ms each time."""
        key = (self.counters["solves"], id(self.zoom_model), self._zoom_ready)
        if key == self._zoom_table_cache[0]:
            return self._zoom_table_cache[1]
        limits = self.zoom_model.covered_range() if self._zoom_ready else None
        table = None
        if limits is not None:
            z = np.linspace(float(limits[0]), float(limits[1]), points)
            try:
                predictions = [self.zoom_model.predict(float(zi)) for zi in z]
                f = np.array([p.K[1, 1] for p in predictions])
                sigma = np.array([p.sigma_f for p in predictions])
                table = (z, f, sigma) if np.all(np.isfinite(f)) and np.all(f > 0.0) else None
            except (ZoomModelError, ValueError, np.linalg.LinAlgError):
                table = None
        self._zoom_table_cache = (key, table)
        return table

    def _learn_zoom_model(self, calibrator: IncrementalCalibrator) -> None:
        """The converged calibration's keyframes (and reference) become the zoom model's LIVE samples,
        zoom -> (f, cx, cy, k1, k2) with their latest (bundle-adjusted) estimates, weighted by 1 / sigma^2
        of log f from the adjustment; a keyframe the calibration dropped is committed with its last one."""
        solve = calibrator.last_solve
        common = solve.sigma_f_ref / solve.K_ref[1, 1] if solve is not None else math.nan
        frames = [(int(kf.keyframe_id), kf.K) for kf in calibrator.keyframes if kf.K is not None]
        ref = self.solver.reference_keyframe_id
        if ref is not None:
            frames.append((int(ref), calibrator.reference_K))
        live: dict[int, tuple[float, ...]] = {}
        for kid, K in frames:
            zoom = self.keyframe_zoom.get(kid, math.nan)
            if not math.isfinite(zoom):
                continue
            rel = self.solver.sigma_f.get(kid, math.nan) / K[1, 1]
            rel = rel if math.isfinite(rel) and rel > 0.0 else common
            weight = 1.0 / max(rel, 1e-4) ** 2 if math.isfinite(rel) and rel > 0.0 else 1.0
            k1, k2 = self._distortion_of(K)[:2]
            rate = self._keyframe_rate.get(kid, math.nan)  # NaN: a restored keyframe keeps its own
            live[kid] = (zoom, K[1, 1], K[0, 2], K[1, 2], k1, k2, weight, rate)
        self.zoom_model.set_live(live)
        new = set(live) - self._sampled_keyframes
        self._sampled_keyframes |= new
        self.counters["zoom_model_samples"] += len(new)
        if len(self._sampled_keyframes) >= self.config.zoom_model_min_keyframes or self._zoom_ready:
            try:
                self.zoom_model.predict(float(np.nanmedian(list(self.keyframe_zoom.values()))))
                self._zoom_ready = True
            except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
                self._warn(f"zoom model not usable yet: {exc}")

    def _request_reset(self) -> None:
        self._reset_requested = True
        self._snapshot = None
        self.reference_id = None
        self._seen_keyframes.clear()
        self._refused_keyframes.clear()
        self._previous_frame = None
        self._pending.clear()

    def _do_reset(self) -> None:
        self._reset_requested = False
        self.zoom_model.new_calibration()  # its calibration is gone: live samples become history
        self.calibrator = None
        self.matches.clear()
        self.keyframe_zoom.clear()
        self._sampled_keyframes.clear()
        self.solver.reference_keyframe_id = None
        self.solver.forget_warm_start()
        self._dirty = True

    # ----------------------------------------------------------------------------------------------
    # Persistence
    # ----------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        with self._lock:
            last = self.last_good
            return _plain(
                {
                    "version": STATE_VERSION,
                    "saved_at": time.time(),
                    "image_size": list(self.image_size) if self.image_size else None,
                    "reference_id": self.reference_id,
                    "reference_keyframe_id": self.solver.reference_keyframe_id,
                    "keyframe_zoom": {int(k): float(v) for k, v in self.keyframe_zoom.items()},
                    "sampled_keyframes": sorted(int(k) for k in self._sampled_keyframes),
                    "last_good": None
                    if last is None
                    else {"K": last.K.tolist(), "D": last.D.tolist(), "sigma_f": float(last.sigma_f)},
                    "calibrator": None if self.calibrator is None else self.calibrator.to_dict(),
                    "shared_lam": self.solver.shared_lam,  # a fixed lens's distortion (None: none)
                    "focal_model": self.config.focal_model,
                    "noise_estimate": self.solver.noise_estimate,  # the eq. 27 prior's weight
                }
            )

    def load_dict(self, data: dict) -> None:
        """Restore from `to_dict` output; StateFileError when it does not fit."""
        if data.get("version") != STATE_VERSION:
            raise StateFileError(f"state version {data.get('version')!r}, expected {STATE_VERSION}")
        saved_model = data.get("focal_model", "varying")
        if saved_model != self.config.focal_model:
            # one K for every frame is not a zoom lens's calibration, nor the reverse
            raise StateFileError(
                f"state saved with focal_model {saved_model!r}, configured {self.config.focal_model!r}"
            )
        try:
            size = data.get("image_size")
            image_size = (int(size[0]), int(size[1])) if size else None
            calibrator = None
            if data.get("calibrator") is not None:
                calibrator = IncrementalCalibrator.from_dict(data["calibrator"], solver=self.solver)
            last_good = None
            last = data.get("last_good")
            if last:
                K = np.asarray(last["K"], dtype=float).reshape(3, 3)
                if not np.all(np.isfinite(K)) or K[0, 0] <= 0:
                    raise StateFileError("last K is not valid")
                last_good = FrameOutput(
                    status=CALIBRATING,
                    K=K,
                    D=np.asarray(last.get("D", [0.0] * 5), dtype=float).reshape(5),
                    R=None,
                    sigma_f=float(last.get("sigma_f", math.nan)),
                    sigma_cx=math.nan,
                    sigma_cy=math.nan,
                    residual=math.nan,
                    keyframe_id=0,
                    keyframe_count=0,
                    source="last_good",
                )
            keyframe_zoom = {
                int(k): math.nan if v is None else float(v)
                for k, v in (data.get("keyframe_zoom") or {}).items()
            }
            sampled = {int(k) for k in data.get("sampled_keyframes") or []}
            shared_lam = data.get("shared_lam")
            shared_lam = None if shared_lam is None else float(shared_lam)
            if shared_lam is not None and not math.isfinite(shared_lam):
                raise StateFileError("shared_lam is not finite")
            noise = data.get("noise_estimate")
            noise = None if noise is None or not 0.0 < float(noise) < math.inf else float(noise)
            ref_kf = data.get("reference_keyframe_id")
        except StateFileError:
            raise
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
            raise StateFileError(f"state does not load: {type(exc).__name__}: {exc}") from exc
        with self._lock:
            self.image_size = image_size
            self.reference_id = data.get("reference_id")
            self.solver.reference_keyframe_id = None if ref_kf is None else int(ref_kf)
            self.calibrator = calibrator
            self.keyframe_zoom = keyframe_zoom
            self._sampled_keyframes = sampled
            fixed_distortion = self.config.fixed_lens and self.config.estimate_distortion
            self.solver.shared_lam = shared_lam if fixed_distortion else None
            self.solver.noise_estimate = noise
            self.solver.forget_warm_start()
            self._seen_keyframes = set(keyframe_zoom)
            self.last_good = last_good
            if calibrator is not None:
                self._publish_snapshot()

    def save(self) -> list[str]:
        """Save the state and the zoom model atomically into state_dir; returns the files written."""
        if self.state_dir is None:
            return []
        with self._lock:
            text = yaml.safe_dump(self.to_dict(), sort_keys=False)
            atomic_write_text(self.state_dir / STATE_FILE, text)
            written = [str(self.state_dir / STATE_FILE)]
            if not self.zoom_model.is_empty():
                self.zoom_model.save(self.state_dir / ZOOM_MODEL_FILE)
                written.append(str(self.state_dir / ZOOM_MODEL_FILE))
            self._dirty = False
            self.counters["state_saves"] += 1
        return written

    @property
    def dirty(self) -> bool:
        return self._dirty

    def restore(self) -> list[str]:
        """Load the state and the zoom model from state_dir; returns log lines ("WARNING: ..." first).

        A corrupt file gives a warning and a fresh start for that part, never an exception.
        """
        messages: list[str] = []
        if self.state_dir is None:
            return messages
        for tmp in remove_stale_temporaries(self.state_dir):
            messages.append(f"removed {tmp}, the temporary file of a save interrupted by a kill")
        path = self.state_dir / STATE_FILE
        try:
            data = load_yaml_file(path)
            if data is not None:
                self.load_dict(data)
                state = self.calibrator.state.value if self.calibrator else "none"
                messages.append(
                    f"restored calibration state from {path}: {state}, "
                    f"{len(self.keyframe_zoom)} keyframes, reference {self.reference_id!r}"
                )
        except StateFileError as exc:
            messages.append(f"WARNING: ignoring calibration state {path} ({exc}); starting fresh")
        zpath = self.state_dir / ZOOM_MODEL_FILE
        model, problem = ZoomModel.load_or_new(zpath)
        # live samples of keyframes the restored calibration still holds stay live (its next solve
        # refreshes them); without it they become history and a new calibration (scale) begins
        if self.calibrator is not None:
            restored = {kf.keyframe_id for kf in self.calibrator.keyframes}
            model.commit_live(keep=restored | {self.solver.reference_keyframe_id})
        else:
            model.new_calibration()
        if problem is not None:
            messages.append(f"WARNING: ignoring zoom model {zpath} ({problem}); learning a new one")
        elif not model.is_empty():
            try:
                model.predict(float(np.mean(model.covered_range())))
                self._zoom_ready = True
                messages.append(f"loaded zoom model from {zpath} (zoom range {model.covered_range()})")
            except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
                messages.append(f"WARNING: zoom model {zpath} not usable ({exc})")
        self.zoom_model = model
        return messages

    # ----------------------------------------------------------------------------------------------
    # Diagnostics
    # ----------------------------------------------------------------------------------------------
    def timings_ms(self) -> dict[str, float]:
        def pct(values: deque[float], q: float) -> float:
            return float(np.percentile(np.fromiter(values, float), q)) * 1e3 if values else math.nan

        return {
            "frame_ms_median": pct(self._frame_times, 50),
            "frame_ms_p95": pct(self._frame_times, 95),
            "frame_ms_max": pct(self._frame_times, 100),
            "solve_ms_median": pct(self._solve_times, 50),
            "solve_ms_max": pct(self._solve_times, 100),
        }

    @property
    def state(self) -> str:
        snap = self._snapshot
        return "NONE" if snap is None else snap.state

    def _warn(self, text: str) -> None:
        self._warnings.append(text)

    def take_warnings(self) -> list[str]:
        out = list(self._warnings)
        self._warnings.clear()
        return out


def _plain(value: Any) -> Any:
    """YAML-safe plain Python (numpy arrays and scalars converted, tuples as lists)."""
    if isinstance(value, dict):
        return {(k if isinstance(k, str | int) else str(k)): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else value
    return value
