"""The keyframe calibration: the bounded keyframe set of one reference, its solves and the zoom model.

It takes `WorkBatch`es from the frame path, adds their keyframes and matches to the incremental
calibrator (online/incremental.py: initialisation once the motion is well posed, section 6), re-solves
with the keyframe solver (LM on eq. 22, then the MAP bundle adjustment of eq. 27), learns the zoom
model from converged keyframes, and answers with a `WorkResult` holding an immutable snapshot for the
frame path. Single-threaded and pure: whoever calls `apply` owns this object; the frame path reads
only the snapshots (the node runs `apply` in its worker thread, outside its frame lock).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import time
from collections import OrderedDict, deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import intrinsic_matrix, normalise_homography, rotation_from_homography
from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameOutput
from ptz_selfcal.online.incremental import IncrementalCalibrator
from ptz_selfcal.online.keyframe_solver import KeyframeBundleSolver, KeyframeMatchSet
from ptz_selfcal.online.lens_output import DistortionFn, PlumbBob
from ptz_selfcal.online.status_policy import ModelFit, StatusEvidence, StatusPolicy, decide, honest_sigma
from ptz_selfcal.online.work import CalibrationSnapshot, PendingKeyframe, WorkBatch, WorkResult, ZoomTable
from ptz_selfcal.persist.session_state import SavedState, load_zoom_model, state_to_dict
from ptz_selfcal.selfcal.transfer import intrinsics_from_transferred_diac
from ptz_selfcal.status import CalibrationStatus
from ptz_selfcal.zoom.model import ZoomModel, ZoomModelError

Array = NDArray[np.float64]

_SOLVE_ERRORS = (SelfCalibrationError, ValueError, np.linalg.LinAlgError)


class KeyframeCalibration:
    """One reference's keyframe calibration (see the module docstring)."""

    def __init__(self, config: SessionConfig, distortion: DistortionFn | None = None) -> None:
        self.config = config
        self.counters: dict[str, int] = dict.fromkeys(
            ("keyframes", "solves", "solve_failures", "calibrator_errors", "zoom_model_samples"), 0
        )
        self._warnings: list[str] = []
        self.matches: OrderedDict[tuple[int, int], KeyframeMatchSet] = OrderedDict()
        self.solver = KeyframeBundleSolver(config, self.matches)
        self.model_fit = ModelFit()  # the keyframe matches' fits: the tracker's noise, the pinhole misfit
        self.policy = StatusPolicy(
            max_sigma_f=config.converged_max_sigma_f,
            max_misfit_ratio=config.model_mismatch_ratio,
            max_lens_model_change=config.converged_max_lens_model_change if config.fixed_lens else None,
        )
        self.calibrator: IncrementalCalibrator | None = None
        self.image_size: tuple[int, int] | None = None
        self.epoch = 0
        self.keyframe_zoom: dict[int, float] = {}
        self.keyframe_rate: dict[int, float] = {}  # keyframe -> zoom rate (the model learns the lag)
        self.sampled_keyframes: set[int] = set()
        self.zoom_model = ZoomModel()
        self.zoom_ready = False
        self.dirty = False
        self._plumb_bob = PlumbBob(distortion)
        self._published = False  # a snapshot of this epoch went out
        self._zoom_changed = False  # the zoom model changed since the last result
        self._needs_refinement = False
        self._next_solve = 0.0
        self._backlog: deque[PendingKeyframe] = deque()  # keyframes a spent budget left for later
        self._awaiting_matches = False  # a restored calibration: no re-solve until match sets arrive
        self._solve_times: deque[float] = deque(maxlen=200)
        self._zoom_table_cache: tuple[tuple, ZoomTable | None] = ((), None)

    # ----------------------------------------------------------------------------------------------
    def apply(self, work: WorkBatch, max_seconds: float) -> WorkResult:
        """Add the batch's keyframes and matches, re-optimise within about max_seconds."""
        solved, snapshot = False, None
        if work.epoch != self.epoch:
            self.reset()
            self.epoch = work.epoch
        if work.image_size is not None:
            self.image_size = work.image_size
            for m in work.matches:
                self.matches[(m.keyframe_id, m.other_keyframe_id)] = m
                self.model_fit.add((m.keyframe_id, m.other_keyframe_id), m.points, m.other_points)
                while len(self.matches) > self.config.max_match_pairs:
                    self.matches.popitem(last=False)
            solved, added = self._solve(work, max_seconds)
            if added or solved or not self._published:
                snapshot = self.snapshot()
                self.dirty = True
        return self._result(solved, snapshot)

    def _solve(self, work: WorkBatch, max_seconds: float) -> tuple[bool, int]:
        if self.calibrator is None:
            self.calibrator = self.new_calibrator()
        calibrator = self.calibrator
        added = 0
        solved = False
        start = time.perf_counter()
        backlog = self._backlog
        backlog.extend(work.keyframes)
        while backlog:
            kf = backlog.popleft()
            if np.allclose(kf.H, np.eye(3), atol=1e-9):
                self.solver.reference_keyframe_id = kf.keyframe_id  # the reference itself
                self.keyframe_zoom[kf.keyframe_id] = kf.zoom
                self._note_rate(kf.keyframe_id, kf.zoom_rate)
                continue
            was_calibrated = calibrator.calibrated
            before = calibrator.last_solve
            try:
                calibrator.add_keyframe(kf.keyframe_id, kf.H, kf.stamp, tracked=kf.tracked, anchor=kf.anchor)
            except _SOLVE_ERRORS as exc:
                self.counters["calibrator_errors"] += 1
                self._warn(f"keyframe {kf.keyframe_id} rejected: {exc}")
                continue
            self.keyframe_zoom[kf.keyframe_id] = kf.zoom
            self._note_rate(kf.keyframe_id, kf.zoom_rate)
            self.counters["keyframes"] += 1
            added += 1
            if calibrator.last_solve is not before:
                solved = True
                self._solved(time.perf_counter() - start, first=not was_calibrated)
            if work.paced and time.perf_counter() - start > max_seconds:
                break  # the rest waits for the next batch
        remaining = max_seconds - (time.perf_counter() - start)
        if added:
            self._needs_refinement = True
        # unpaced (replays): no clock in what is solved, so the same inputs give the same calibration
        due = not work.paced or (time.monotonic() >= self._next_solve and remaining > 0.0)
        if self._awaiting_matches and work.matches:
            self._awaiting_matches = False
            self._needs_refinement = True
        if self._awaiting_matches:
            # a restored calibration comes without its match sets (they are not saved): until new ones
            # arrive a re-solve could only be LM on the homographies, which must not replace the
            # adjustment it was made by; the refinement waits for them
            self._needs_refinement = False
        if calibrator.calibrated and self._needs_refinement and not solved and due:
            solved = self._reoptimise(remaining if work.paced else None)
        if added:  # bounded memory: forget keyframes the calibrator dropped
            live = {int(kf.keyframe_id) for kf in calibrator.keyframes}
            if self.solver.reference_keyframe_id is not None:
                live.add(int(self.solver.reference_keyframe_id))
            self.keyframe_zoom = {k: v for k, v in self.keyframe_zoom.items() if k in live}
            self.keyframe_rate = {k: v for k, v in self.keyframe_rate.items() if k in live}
            self.sampled_keyframes &= live
            self.solver.rotations = {k: v for k, v in self.solver.rotations.items() if k in live}
        return solved, added

    def _reoptimise(self, budget: float | None) -> bool:
        """One re-optimisation within budget seconds (None: the evaluation count alone bounds it); then
        the next waits so that solves take at most max_solve_duty of a core (they share the cores with
        the tracker)."""
        calibrator = self.calibrator
        assert calibrator is not None
        before = calibrator.last_solve
        t0 = time.perf_counter()
        try:
            calibrator.reoptimise(budget)
        except _SOLVE_ERRORS as exc:
            self.counters["calibrator_errors"] += 1
            self._warn(f"re-optimisation failed: {exc}")
        solved = calibrator.last_solve is not before
        if solved:
            self._solved(time.perf_counter() - t0, first=False)
        else:
            self.counters["solve_failures"] += 1
        self._needs_refinement = False
        spent = time.perf_counter() - t0
        duty = min(max(self.config.max_solve_duty, 1e-3), 1.0)
        self._next_solve = time.monotonic() + max(self.config.min_solve_period_s, spent * (1.0 - duty) / duty)
        return solved

    def _note_rate(self, keyframe_id: int, rate: float) -> None:
        self.keyframe_rate[keyframe_id] = rate
        if len(self.keyframe_rate) > 4096:
            self.keyframe_rate.pop(next(iter(self.keyframe_rate)))

    def new_calibrator(self) -> IncrementalCalibrator:
        """An empty calibrator whose prior is the zoom model at the reference's zoom, else the given K
        (given_K), else nominal."""
        assert self.image_size is not None
        return new_calibrator(
            self.config,
            self.image_size,
            self.zoom_model if self.zoom_ready else None,
            self.keyframe_zoom.get(self.solver.reference_keyframe_id, math.nan),  # type: ignore[arg-type]
            self.solver,
            given_K=self.given_K(),
        )

    def given_K(self) -> Array | None:
        """A K given for these images in place of the nominal prior (none here)."""
        return None

    def _solved(self, seconds: float, first: bool) -> None:
        calibrator = self.calibrator
        assert calibrator is not None
        self.counters["solves"] += 1
        self._solve_times.append(seconds)
        if first and calibrator.calibrated:
            self._needs_refinement = True  # a second, warm-started pass (with BA) right away
        if self._status(calibrator, "")[0] is CalibrationStatus.CONVERGED:  # the policy's, not the solver's
            self._learn_zoom_model(calibrator)

    # ----------------------------------------------------------------------------------------------
    def snapshot(self) -> CalibrationSnapshot | None:
        """The calibration as the frame path reads it (None before the first batch)."""
        calibrator = self.calibrator
        if calibrator is None:
            return None
        self._published = True
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
        state, message = self._status(calibrator, message)
        copied = IncrementalCalibrator.from_dict(calibrator.to_dict())
        if copied.last_solve is not None:  # the frames' sigma_f: the honest common scale (section 6.2)
            sigma = self.sigma_f(calibrator) * float(copied.last_solve.K_ref[1, 1])
            copied.last_solve = dataclasses.replace(copied.last_solve, sigma_f_ref=sigma)
        return CalibrationSnapshot(
            epoch=self.epoch,
            zoom_table=self._zoom_table(),
            keyframes=keyframes,
            calibrator=copied,
            calibrated=calibrator.calibrated,
            state=state,
            message=message,
            residual=float(residual),
            keyframe_count=len(calibrator.keyframes) + 1,
            shared_lam=self.solver.shared_lam,
        )

    def sigma_f(self, calibrator: IncrementalCalibrator) -> float:
        """The honest relative 1-sigma of the reference f (online/status_policy.honest_sigma): the
        adjustment's, rescaled to the tracker's noise measured on the keyframe matches."""
        solve = calibrator.last_solve
        if solve is None:
            return math.nan
        rel = solve.sigma_f_ref / solve.K_ref[1, 1]
        adjusted = "+" in solve.method  # LM on eq. 22, then the bundle adjustment
        noise = self.solver.noise_estimate if adjusted else None
        spread = self._keyframe_spread(calibrator)
        gap = self.solver.lens_model_gap if adjusted else 0.0
        return honest_sigma(float(rel), noise, self.model_fit.tracker_noise, spread, gap)

    @staticmethod
    def _keyframe_spread(calibrator: IncrementalCalibrator) -> float:
        """The largest |f_k / f_k' - 1| over the keyframes: f_k the solve's, f_k' the reference K carried
        to keyframe k by its homography (eq. 20)."""
        K_ref, worst = calibrator.reference_K, 0.0
        for kf in calibrator.keyframes:
            if kf.K is None:
                continue
            with contextlib.suppress(*_SOLVE_ERRORS):
                K_t = intrinsics_from_transferred_diac(kf.H, K_ref, calibrator.model, calibrator.image_size)
                change = abs(float(kf.K[1, 1]) / float(K_t[1, 1]) - 1.0)
                worst = max(worst, change) if math.isfinite(change) else worst
        return worst

    def _misfit(self) -> float:
        """The lens model's residual noise as a transfer error per coordinate (px): with distortion
        estimated, the adjustment's on the raw matches; without, one homography per match set."""
        c = self.config
        distorted = self.solver.lens_model is not None or (c.fixed_lens and c.estimate_distortion)
        if not distorted:
            return self.model_fit.pinhole_misfit
        solve = self.calibrator.last_solve if self.calibrator is not None else None
        noise = self.solver.noise_estimate
        if solve is None or "+" not in solve.method or noise is None:
            return math.nan
        return math.sqrt(2.0) * noise

    def _status(self, calibrator: IncrementalCalibrator, message: str) -> tuple[CalibrationStatus, str]:
        """The status policy (online/status_policy.py) on this calibration's evidence."""
        evidence = StatusEvidence(
            solver_state=calibrator.state,
            solver_message=message,
            sigma_f=self.sigma_f(calibrator),
            misfit=self._misfit(),
            tracker_noise=self.model_fit.tracker_noise,
            lens_model_change=self.solver.measure_lens_model_change if self.config.fixed_lens else None,
            adjusted=calibrator.last_solve is not None and "+" in calibrator.last_solve.method,
        )
        return decide(self.policy, evidence)

    def _zoom_table(self, points: int = 17) -> ZoomTable | None:
        """The zoom model over its learned range for the frame path's gate (np.interp there: no spline
        evaluation per frame); recomputed only when the model can have changed."""
        key = (self.counters["solves"], id(self.zoom_model), self.zoom_ready)
        if key == self._zoom_table_cache[0]:
            return self._zoom_table_cache[1]
        limits = self.zoom_model.covered_range() if self.zoom_ready else None
        table = None
        if limits is not None:
            z = np.linspace(float(limits[0]), float(limits[1]), points)
            try:
                predictions = [self.zoom_model.predict(float(zi)) for zi in z]
                f = np.array([p.K[1, 1] for p in predictions])
                sigma = np.array([p.sigma_f for p in predictions])
                table = ZoomTable(z, f, sigma) if np.all(np.isfinite(f)) and np.all(f > 0.0) else None
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
            k1, k2 = self._plumb_bob(K, self.solver.shared_lam, self.image_size)[:2]
            rate = self.keyframe_rate.get(kid, math.nan)  # NaN: a restored keyframe keeps its own
            live[kid] = (zoom, K[1, 1], K[0, 2], K[1, 2], k1, k2, weight, rate)
        self.zoom_model.set_live(live)
        self._zoom_changed = True
        new = set(live) - self.sampled_keyframes
        self.sampled_keyframes |= new
        self.counters["zoom_model_samples"] += len(new)
        if len(self.sampled_keyframes) >= self.config.zoom_model_min_keyframes or self.zoom_ready:
            try:
                self.zoom_model.predict(float(np.nanmedian(list(self.keyframe_zoom.values()))))
                self.zoom_ready = True
            except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
                self._warn(f"zoom model not usable yet: {exc}")

    def reset(self) -> None:
        """A new reference: the calibration starts again, the zoom model keeps what it learned."""
        self.zoom_model.new_calibration()  # its calibration is gone: live samples become history
        self._zoom_changed = True
        self.calibrator = None
        self._awaiting_matches = False
        self._backlog.clear()
        self.matches.clear()
        self.model_fit.forget()
        self.keyframe_zoom.clear()
        self.keyframe_rate.clear()
        self.sampled_keyframes.clear()
        self.solver.reference_keyframe_id = None
        self.solver.forget_warm_start()
        self._published = False
        self.dirty = True

    def set_distortion(self, distortion: DistortionFn | None) -> None:
        """A zoom lens's distortion (K -> plumb_bob D) for the zoom model's samples."""
        self._plumb_bob = PlumbBob(distortion)

    # ---- persistence (persist/session_state.py) --------------------------------------------------
    def to_dict(
        self, image_size: tuple[int, int] | None, reference_id: str | None, last_good: FrameOutput | None
    ) -> dict:
        """The state file's mapping, with the frame path's part given."""
        return state_to_dict(
            image_size,
            reference_id,
            last_good,
            self.calibrator,
            self.solver,
            self.keyframe_zoom,
            self.sampled_keyframes,
            self.config.focal_model,
        )

    def restore(self, saved: SavedState) -> None:
        self.image_size = saved.image_size
        self.solver.reference_keyframe_id = saved.reference_keyframe_id
        self.calibrator = saved.calibrator
        self.keyframe_zoom = saved.keyframe_zoom
        self.sampled_keyframes = saved.sampled_keyframes
        fixed_distortion = self.config.fixed_lens and self.config.estimate_distortion
        self.solver.shared_lam = saved.shared_lam if fixed_distortion else None
        self.solver.noise_estimate = saved.noise_estimate
        self._awaiting_matches = saved.calibrator is not None and self.config.bundle_adjustment
        self.solver.distortion_adopted = saved.distortion_adopted
        self.solver.pp_varying_adopted = saved.pp_varying_adopted
        self.solver.forget_warm_start()

    def restore_zoom_model(self, path: Path) -> list[str]:
        """Load the saved zoom model; log lines ("WARNING: ..." first). Live samples of keyframes the
        restored calibration still holds stay live (its next solve refreshes them); without one they
        become history and a new calibration (scale) begins."""
        keep = None
        if self.calibrator is not None:
            keep = {kf.keyframe_id for kf in self.calibrator.keyframes} | {self.solver.reference_keyframe_id}
        model, ready, messages = load_zoom_model(path, keep)
        self.zoom_model, self.zoom_ready, self._zoom_changed = model, ready, True
        return messages

    # ----------------------------------------------------------------------------------------------
    def replace_keyframe_homographies(self, homographies: Mapping[int, Array]) -> WorkResult:
        """The keyframes' homographies from the reference re-corrected (the lens correction's new
        estimate); the result publishes them, so that a frame's homography and its keyframe's come
        from the same correction."""
        if self.calibrator is not None:
            for kf in self.calibrator.keyframes:
                H = homographies.get(int(kf.keyframe_id))
                if H is None and kf.anchor is not None and kf.anchor[0] in homographies:
                    H = normalise_homography(kf.anchor[1] @ homographies[kf.anchor[0]])  # an ordinary frame
                if H is not None:
                    kf.H = H
        return self.result()

    def result(self) -> WorkResult:
        """The current snapshot as a result, for a change made outside `apply` (a restore, or the lens
        correction replacing the keyframes' homographies)."""
        return self._result(False, self.snapshot())

    def _result(self, solved: bool, snapshot: CalibrationSnapshot | None) -> WorkResult:
        zoom = None
        if self._zoom_changed:
            self._zoom_changed = False
            limits = self.zoom_model.covered_range() if self.zoom_ready else None
            if limits is not None:  # fitted here, so that the frame path's copy only evaluates
                with contextlib.suppress(ZoomModelError, ValueError, np.linalg.LinAlgError):
                    self.zoom_model.predict(float(np.mean(limits)))
            zoom = copy.deepcopy(self.zoom_model)
        warnings, self._warnings = tuple(self._warnings), []
        times = np.fromiter(self._solve_times, float)
        solve_ms = (
            (float(np.median(times)) * 1e3, float(times.max()) * 1e3) if times.size else (math.nan,) * 2
        )
        return WorkResult(
            epoch=self.epoch,
            solved=solved,
            snapshot=snapshot,
            zoom_model=zoom,
            zoom_ready=self.zoom_ready,
            counters={**self.counters, "zoom_model_samples_total": self.zoom_model.sample_count},
            warnings=warnings,
            solve_ms=solve_ms,  # type: ignore[arg-type]
            backlog=len(self._backlog),
            # a refinement can run only once there is a calibration to refine
            needs_refinement=self._needs_refinement
            and self.calibrator is not None
            and self.calibrator.calibrated,
        )

    def _warn(self, text: str) -> None:
        self._warnings.append(text)
        del self._warnings[:-100]


def new_calibrator(
    config: SessionConfig,
    image_size: tuple[int, int],
    zoom_model: ZoomModel | None,
    reference_zoom: float,
    solver: KeyframeBundleSolver | None = None,
    given_K: Array | None = None,
) -> IncrementalCalibrator:
    """An empty incremental calibrator; its prior K is the zoom model's at the reference zoom when there
    is one, else given_K (a measured K: camera_info_url, set_camera_info), else the nominal field of
    view at the image centre."""
    width, height = image_size
    if given_K is not None:
        prior = np.array(given_K, dtype=float)
    else:
        prior = intrinsic_matrix(config.nominal_focal(width), 0.5 * (width - 1.0), 0.5 * (height - 1.0))
    if zoom_model is not None and math.isfinite(reference_zoom):
        with contextlib.suppress(ZoomModelError, ValueError):
            prior = zoom_model.predict(reference_zoom).K
    return IncrementalCalibrator(
        image_size,
        config.intrinsics_model(),
        min_rotation_deg=config.min_rotation_deg,
        max_keyframes=config.max_keyframes,
        prior_K=prior,
        solver=solver,
        min_keyframes=config.min_keyframes,
        min_axis_disambiguation_px=config.min_axis_disambiguation_px,
    )
