"""The keyframe solver: LM on eq. 22 (section 3.3.1), refined by the MAP keyframe bundle adjustment
(eq. 27, section 5.2), optionally with radial distortion on raw points (section 7)."""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.bundle import bundle_adjust, pair_observations
from ptz_selfcal.bundle.selection import ModelChoice, compare_models
from ptz_selfcal.camera.distortion import corner_radius, division_undistort_radius
from ptz_selfcal.camera.geometry import (
    apply_homography,
    pixel_grid,
    rotation_from_homography,
)
from ptz_selfcal.camera.intrinsics import (
    IntrinsicsModel,
    ParamMode,
    SelfCalibrationError,
    image_centre,
)
from ptz_selfcal.lens.interface import LensEstimate, LensModel
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.incremental import Keyframe
from ptz_selfcal.selfcal.degeneracy import STATUS_NEAR_AMBIGUOUS
from ptz_selfcal.selfcal.lm import lm_selfcalibration
from ptz_selfcal.selfcal.result import SelfCalibrationResult
from ptz_selfcal.selfcal.transfer import intrinsics_from_transferred_diac

Array = NDArray[np.float64]

# LM iterations of an alternative lens model probed from the adopted one's solution: near it, a few
# steps take most of the decrease in cost the criterion compares
PROBE_ITERATIONS = 6


@dataclass
class KeyframeMatchSet:
    """Inlier point pairs between two keyframes (full-resolution pixels)."""

    keyframe_id: int
    other_keyframe_id: int
    points: Array  # (N, 2) in keyframe_id
    other_points: Array  # (N, 2) in other_keyframe_id


class KeyframeBundleSolver:
    """SolverFn for IncrementalCalibrator: LM on eq. 22, refined by MAP bundle adjustment (eq. 27).

    Frame 0 of the solve is the calibration reference (the tracker's reference keyframe), frames
    1.. the calibrator's keyframes. Observations are the tracker's keyframe matches between frames of
    the solve; a frame without any match gets virtual correspondences from its homography to the
    reference (grid points visible in both) so that it stays in the adjustment. When the adjustment
    fails or is not better posed, the LM result is returned.

    Radial distortion (`set_lens_model`, a lens/interface.LensModel such as LensCorrection.view(),
    handed over by lens/hook.SessionLensHook after each worker step): the matches are then RAW
    (distorted) pixels and the adjustment estimates one division coefficient per frame about the
    principal point with everything else (bundle/adjust.py, distortion=True), starting from
    lam_guess(keyframe_id, f); a frame's virtual correspondences (its homography is on corrected
    pixels) are distorted back with the lens model that corrected it, distort(keyframe_id, pts), so
    that they stand for the raw points and carry no assumption about the distortion centre. Each solve
    uses the model set when it starts. The prior of eq. 27 is weighed with the image noise of the
    previous accepted solve (its residual standard deviation, within [0.02, ba_noise_sigma_px]), with
    or without distortion: tracked matches fit far better than the nominal 1 px, and a prior weighed
    for that noise is too strong and pulls the principal point (and, near the ambiguity of a long
    focal length, f) to the image centre. `lens_estimate` keeps the last such solution for the hook.
    Keyframe id None = the reference. A fixed lens's solves after the first start the adjustment from
    the previous one (_warm_start) rather than from LM, and its lens-model check
    (`measure_lens_model_change`) runs only when the session asks for it.
    """

    def __init__(self, config: SessionConfig, matches: OrderedDict[tuple[int, int], KeyframeMatchSet]):
        self.config = config
        self.matches = matches
        self.reference_keyframe_id: int | None = None
        self.rotations: dict[Hashable, Array] = {}  # keyframe id -> R relative to the reference (last solve)
        self.last_method = ""
        self.last_message = ""
        self.sigma_f: dict[Hashable, float] = {}  # keyframe id -> 1-sigma of f in the last accepted solve
        self._lens: LensModel | None = None  # None: homographies and matches are undistorted
        self.lens_estimate: LensEstimate | None = None
        self.noise_estimate: float | None = None  # px, residual sigma of the last accepted solve
        self.distortion_mode = "curve"  # lam per frame on a lam(f) curve ("curve") or free ("frame")
        # a fixed lens with estimate_distortion: the one division coefficient and its 1-sigma
        self.shared_lam: float | None = None
        self.sigma_shared_lam = math.nan
        # a fixed lens: see measure_lens_model_change (last solve), measured when first asked for
        # (the session asks only when the solve could otherwise be CONVERGED)
        self._lens_model_change_value = math.nan
        # lens-model selection (bundle/selection.py) of the last solve: None before the first
        self.distortion_adopted: bool | None = None
        self.distortion_delta_bic = math.nan
        self.pp_varying_adopted: bool | None = None
        self.pp_delta_bic = math.nan
        # |f_LM / f_adjusted - 1| of the reference in the last accepted raw-point solve with a radial term
        # (LM on the lens correction's homographies): the lens model's error (status_policy.honest_sigma)
        self.lens_model_gap = 0.0
        self._lens_check: _LensCheck | None = None  # the solve's inputs until it is measured
        # a fixed lens: the last adjustment (reference keyframe id, K, keyframe id -> R), _warm_start
        self._warm: tuple[Hashable, Array, dict[Hashable, Array]] | None = None

    def _pp_varying(self) -> bool:
        """The principal point per keyframe in the next adjustment (auto: as adopted last, constant
        until the evidence shows it moving)."""
        mode = self.config.ba_principal_point
        return mode == "varying" or (mode == "auto" and bool(self.pp_varying_adopted))

    def set_lens_model(self, model: LensModel | None) -> None:
        """The lens model the next solves start from (None: undistorted input)."""
        self._lens = model

    @property
    def lens_model(self) -> LensModel | None:
        return self._lens

    def __call__(
        self,
        H: Array,
        image_size: tuple[int, int],
        model: IntrinsicsModel,
        K_init: Array | None,
        keyframes: list[Keyframe],
        max_nfev: int,
    ) -> SelfCalibrationResult:
        lens = self._lens  # this solve's lens model
        if lens is not None and self.distortion_adopted is not False:
            # the keyframes' homographies as the lens correction has them now (chained or provisional):
            # the ones stored at arrival may come from an older correction, and the frames are
            # corrected with the current one (a stale keyframe homography puts its frames off); a
            # lens found without distortion keeps the tracked ones, as its frames do (lens/hook.py)
            H = H.copy()
            for i, kf in enumerate(keyframes, start=1):
                H_now = lens.keyframe_homography(kf.keyframe_id)
                if H_now is not None and np.all(np.isfinite(H_now)):
                    kf.H = H[i] = H_now
        result = None
        warm = self._warm_start(H, keyframes, lens)
        if warm is not None:
            self.last_method, self.last_message = warm.method, ""
            result = self._refine(H, image_size, warm, keyframes, lens)
            if result is warm or not usable_result(result):
                result = None  # LM on eq. 22 and the adjustment from it, as for the first solve
        if result is None:
            # LM on <= max_keyframes + 1 homographies takes milliseconds: the calibrator's time-derived
            # evaluation budget (which also counts the adjustment) would stop it short of convergence
            lm = lm_selfcalibration(H, image_size, model, K_init, max_nfev=max(int(max_nfev), 100))
            self.last_method, self.last_message = lm.method, lm.message
            result = self._refine(H, image_size, lm, keyframes, lens)
        self._keep_warm_start(result, keyframes)
        if result.ok:
            self.rotations = {kf.keyframe_id: R for kf, R in zip(keyframes, result.R[1:])}
            # 1-sigma of each frame's f (the adjustment's Jacobian): the zoom model's sample weights
            ids = [self.reference_keyframe_id, *(kf.keyframe_id for kf in keyframes)]
            self.sigma_f = {k: float(s) for k, s in zip(ids, np.ravel(result.sigma_f)) if k is not None}
        return result

    def _warm_start(
        self, H: Array, keyframes: list[Keyframe], lens: LensModel | None
    ) -> SelfCalibrationResult | None:
        """A fixed lens: the adjustment's start from its previous solution instead of LM on eq. 22.

        LM on a hand-held pan's homographies is several per cent off in f, so an adjustment started
        there spends many iterations walking back to where the previous one ended, while one more
        still moves the solution by a fraction of a per cent. K is the previous adjustment's, each
        keyframe it held keeps its rotation, a new keyframe gets the rotation of its homography
        relative to the nearest held one (the direct link, not the chain from the reference). None
        (LM as for the first solve) for a zooming lens, without a previous adjustment, or when it
        holds none of these keyframes.
        """
        if not (self.config.fixed_lens and lens is None and self.config.bundle_adjustment):
            return None
        warm = self._warm
        ids = [kf.keyframe_id for kf in keyframes]
        if warm is None or warm[0] != self.reference_keyframe_id or not any(k in warm[2] for k in ids):
            return None
        K, held = warm[1], warm[2]
        R = np.empty((len(H), 3, 3))
        R[0] = np.eye(3)
        known = [0] + [j for j, k in enumerate(ids, start=1) if k in held]
        for j, k in enumerate(ids, start=1):
            if k in held:
                R[j] = held[k]
        for j in range(1, len(H)):
            if ids[j - 1] in held:
                continue
            i = min(known, key=lambda i: (abs(i - j), i))  # nearest held frame (the previous one first)
            R[j] = rotation_from_homography(H[j] @ np.linalg.inv(H[i]), K, K) @ R[i]
        n = len(H)
        return SelfCalibrationResult(
            K=np.repeat(K[None], n, axis=0),
            R=R,
            sigma_f=np.full(n, np.nan),
            sigma_pp=np.full((n, 2), np.nan),
            residual=math.nan,
            method="warm",
            solver_ok=True,
        )

    def _keep_warm_start(self, result: SelfCalibrationResult, keyframes: list[Keyframe]) -> None:
        """Remember an accepted adjustment (reference, K, keyframe id -> R) for _warm_start."""
        adjusted = result.bundle is not None and usable_result(result)
        if not (self.config.fixed_lens and adjusted and np.all(np.isfinite(result.R))):
            return
        held = {kf.keyframe_id: R.copy() for kf, R in zip(keyframes, result.R[1:])}
        self._warm = (self.reference_keyframe_id, result.K[0].copy(), held)

    def forget_warm_start(self) -> None:
        """The next solve starts from LM on eq. 22 (a new map or restored keyframes)."""
        self._warm = None

    def _refine(
        self,
        H: Array,
        image_size: tuple[int, int],
        lm: SelfCalibrationResult,
        keyframes: list[Keyframe],
        lens: LensModel | None,
    ) -> SelfCalibrationResult:
        self._lens_model_change_value, self._lens_check = math.nan, None  # this solve's, if any
        self.lens_model_gap = 0.0
        # raw-point solve: an LM start flagged only for its motion (section 6.2, LM on corrected
        # homographies) is still refined, the adjustment's own analysis decides
        # a fixed lens likewise: LM on homographies of a pan flags a near-ambiguity that the
        # adjustment on the point matches can resolve
        usable = lm.ok or (
            (lens is not None or self.config.fixed_lens)
            and bool(lm.solver_ok)
            and bool(np.all(np.isfinite(lm.K)))
        )
        if not usable or not self.config.bundle_adjustment:
            return lm
        try:
            ba = self._bundle(H, image_size, lm, keyframes, lens)
        except (SelfCalibrationError, ValueError, np.linalg.LinAlgError) as exc:
            self.last_message = f"bundle adjustment skipped: {exc}"
            return lm
        if ba is not None and self.config.fixed_lens and uncertain_motion(ba):
            # a fixed lens: the adjustment's near-ambiguity verdict (6.2) stands, with its own estimate
            # (uncertain: DEGENERATE_MOTION), rather than LM's confident one on homographies (before
            # a hand-held pan's loop closes LM is off by several times its own sigma)
            ba.solver_ok = True
            self.last_method = ba.method
            ba.method = f"{lm.method}+{ba.method}"
            return ba
        if ba is None or not ba.ok or not np.all(np.isfinite(ba.K)):
            self.last_message = "bundle adjustment failed: " + (
                "no observations" if ba is None else ba.message
            )
            return lm
        self.last_method = ba.method
        ba.method = f"{lm.method}+{ba.method}"
        if lens is not None and _distortion_visible(ba, image_size, self.noise_estimate):
            gap = abs(float(lm.K[0, 1, 1]) / float(ba.K[0, 1, 1]) - 1.0)
            self.lens_model_gap = gap if math.isfinite(gap) else 0.0
        return ba

    def _bundle(
        self,
        H: Array,
        image_size: tuple[int, int],
        lm: SelfCalibrationResult,
        keyframes: list[Keyframe],
        lens: LensModel | None,
    ) -> SelfCalibrationResult | None:
        index = {kf.keyframe_id: i + 1 for i, kf in enumerate(keyframes)}
        if self.reference_keyframe_id is not None:
            index[self.reference_keyframe_id] = 0
        ids = [self.reference_keyframe_id, *(kf.keyframe_id for kf in keyframes)]
        n_frames = len(H)
        fixed = self.config.fixed_lens
        shared = fixed and self.config.estimate_distortion and lens is None
        lam0 = None
        if lens is not None:
            lm = self._with_connectors(lm, index, ids, image_size, lens)
            lam0 = np.array([_guess(lens, k, float(K[1, 1])) for k, K in zip(ids, lm.K)])
        elif shared:  # raw matches, one coefficient for the lens (section 7), from the last estimate
            lam0 = np.full(len(lm.K), self.shared_lam or 0.0)
        rng = np.random.default_rng(0)
        limit = self.config.ba_max_points_per_pair
        if lam0 is not None:
            limit = max(limit, self.config.ba_distortion_points_per_pair)
        pairs: list[tuple[int, int, Array, Array]] = []
        for m in self.matches.values():
            a, b = index.get(m.keyframe_id), index.get(m.other_keyframe_id)
            if a is None or b is None or a == b or len(m.points) < 8:
                continue
            pa, pb = m.points, m.other_points
            if len(pa) > limit:
                keep = np.sort(rng.choice(len(pa), limit, replace=False))
                pa, pb = pa[keep], pb[keep]
            pairs.append((a, b, pa, pb))
        if not pairs:
            return None
        seen = np.zeros(len(lm.K), bool)
        for a, b, _, _ in pairs:
            seen[a] = seen[b] = True
        width, height = image_size
        absent: list[int] = []
        grid = None
        for j in np.flatnonzero(~seen[: len(H)]):
            # virtual correspondences reference <-> frame j from H_j (frame 0 <-> j when j > 0)
            if j > 0 and lam0 is not None:
                continue  # raw-point solve: left out below
            grid = pixel_grid(width, height, 8) if grid is None else grid
            if j == 0:
                k = int(np.flatnonzero(seen[: len(H)])[0])
                Hk = H[k]
                src = grid
                dst = apply_homography(Hk, src)
                pairs.append((0, k, *_visible(src, dst, width, height)))
            else:
                dst = apply_homography(H[j], grid)
                pairs.append((0, j, *_visible(grid, dst, width, height)))
            if lens is not None:  # the homographies are on corrected pixels: distort the points
                a, b, src, dst = pairs[-1]
                src, dst = lens.distort(ids[a], src), lens.distort(ids[b], dst)
                ok = np.isfinite(src).all(axis=1) & np.isfinite(dst).all(axis=1)
                pairs[-1] = (a, b, src[ok], dst[ok])
        if lam0 is not None:
            # raw-point solve: frames not linked to the reference by real matches (none of their own,
            # or a group whose links went with dropped keyframes) are left out and keep their LM
            # calibration with the adjusted principal point. Virtual correspondences from corrected
            # homographies would tie them (and through the shared principal point every frame) to the
            # centre the lens correction assumed; a detached group's scale is free (sigma_f of several %)
            linked = _linked_to_reference(pairs, len(lm.K))
            absent = [j for j in range(1, len(lm.K)) if not linked[j]]
            pairs = [p for p in pairs if linked[p[0]] and linked[p[1]]]
        # a fixed lens: one K for every image, a per-keyframe principal point would not be a fixed lens
        model = self.config.intrinsics_model() if fixed else _pp_model(self._pp_varying())
        sigma = self.config.pp_prior_sigma_px
        prior = (np.array(image_centre(image_size)), np.array([sigma, sigma]))
        noise = self.config.ba_noise_sigma_px
        if self.noise_estimate is not None:  # eq. 27 weighed with the measured image noise
            noise = min(max(self.noise_estimate, 0.02), noise)
        keep = np.array([j for j in range(len(lm.K)) if j not in set(absent)], dtype=np.intp)
        renumber = np.full(len(lm.K), -1, dtype=np.intp)
        renumber[keep] = np.arange(len(keep))
        pairs = [(int(renumber[a]), int(renumber[b]), pa, pb) for a, b, pa, pb in pairs]
        observations = pair_observations(pairs)
        f_min = 0.2 * float(np.min(lm.K[:, 1, 1]))
        radial = False if lam0 is None else ("shared" if shared else self.distortion_mode)

        def adjust(
            start: SelfCalibrationResult, distorted: bool, pp_model: IntrinsicsModel, probe: bool = False
        ) -> SelfCalibrationResult:
            """The adjustment from LM's start, or from an adjusted solution (warm). A probe only
            measures an alternative's cost: a few iterations, no covariance, no motion analysis."""
            warm = start.bundle is not None
            lam_init = None
            if distorted and lam0 is not None:
                lam_init = lam0[keep]
                if warm and start.bundle is not None and start.bundle.lam is not None:
                    lam_init = start.bundle.lam
            return bundle_adjust(
                observations,
                start.K if warm else start.K[keep],
                start.R if warm else start.R[keep],
                image_size,
                pp_model,
                rays_init=start.bundle.rays if warm and start.bundle is not None else None,
                pp_prior=prior,
                noise_sigma=noise,
                max_iterations=min(self.config.ba_max_iterations, PROBE_ITERATIONS)
                if probe
                else self.config.ba_max_iterations,
                tolerance=self.config.ba_tolerance,
                initial_damping=self.config.ba_initial_damping,
                f_min=f_min,
                distortion=radial if distorted else False,
                lam_init=lam_init,
                analyse=not probe,
                uncertainty=not probe,
            )

        def select(
            current: SelfCalibrationResult,
            distorted: bool,
            pp_model: IntrinsicsModel,
            richer: bool,
            extra: int,
        ) -> tuple[SelfCalibrationResult, ModelChoice]:
            """current against the alternative (distorted, pp_model; richer: with `extra` more unknowns)
            probed from its solution: the winner, adjusted in full from LM's start, as a first solve
            would be, when it is the alternative (a change of model is rare)."""
            probe = adjust(current, distorted, pp_model, probe=True)
            simple, rich = (current, probe) if richer else (probe, current)
            choice = compare_models(simple, rich, extra)
            if choice.richer != richer:
                return current, choice
            return adjust(lm, distorted, pp_model), choice

        distorted = lam0 is not None and self.distortion_adopted is not False
        result = adjust(lm, distorted, model)
        if lam0 is not None and self.config.distortion_selection:
            # distortion or none, by evidence on these raw matches (bundle/selection.py): the model
            # adopted last is adjusted, the other probed from its solution
            extra = _radial_unknowns(radial, len(keep))
            result, choice = select(result, not distorted, model, not distorted, extra)
            self.distortion_delta_bic = choice.delta_bic
            self.distortion_adopted = choice.richer
        if not fixed and self.config.ba_principal_point == "auto":
            # a principal point that moves with zoom (MAP, eq. 27) or a constant one (section 5.3.1)
            varying = self._pp_varying()
            radial_now = bool(result.bundle is not None and result.bundle.lam is not None)
            pp_alt = _pp_model(not varying)
            result, choice = select(result, radial_now, pp_alt, not varying, 2 * (len(keep) - 1))
            self.pp_delta_bic = choice.delta_bic
            self.pp_varying_adopted = choice.richer
            model = _pp_model(choice.richer)
        details = result.bundle
        assert details is not None  # bundle_adjust always returns its details
        if lam0 is not None and details.lam is None:  # no distortion: the evidence shows none
            zero = np.zeros(len(keep))
            details = dataclasses.replace(details, lam=zero, sigma_lam=np.full(len(keep), np.nan))
            result = dataclasses.replace(result, bundle=details)
        assert details is not None  # bundle_adjust always returns its details
        if (
            lam0 is not None
            and (result.ok or (shared and uncertain_motion(result)))
            and details.lam is not None
            and np.all(np.isfinite(details.lam))
        ):
            self.noise_estimate = math.sqrt(float(details.residual_variance))
            if shared:
                assert details.sigma_lam is not None
                self.shared_lam = float(details.lam[0])
                self.sigma_shared_lam = float(details.sigma_lam[0])
            self.lens_estimate = LensEstimate(
                principal_point=result.K[0, :2, 2].copy(),
                sigma_pp=np.asarray(result.sigma_pp[0], dtype=float).copy(),
                lam={ids[j]: float(lam) for j, lam in zip(keep, details.lam) if ids[j] is not None},
                focal={ids[j]: float(K[1, 1]) for j, K in zip(keep, result.K) if ids[j] is not None},
            )
        if lam0 is None and result.ok:
            self.noise_estimate = math.sqrt(float(details.residual_variance))
        rel_sigma = float(np.ravel(result.sigma_f)[0]) / float(result.K[0, 1, 1])
        if fixed and usable_result(result) and rel_sigma <= self.config.converged_max_sigma_f:
            # only when it can decide (above that sigma the solution is not CONVERGED anyway)
            self._lens_check = _LensCheck(pairs, result, image_size, model, prior, noise)
        if absent or len(lm.K) > n_frames:
            # the frames left out: LM's focal length and rotation, the adjusted principal point
            K, R = lm.K.copy(), lm.R.copy()
            K[keep], R[keep] = result.K, result.R
            K[absent, :2, 2] = result.K[0, :2, 2]
            near = keep[keep < n_frames]
            for j in absent:
                if j >= n_frames or len(near) == 0:
                    continue
                # from the nearest adjusted frame through the short corrected homography between them
                # (LM's own K carries the long chain's drift)
                k = int(near[np.argmin(np.abs(near - j))])
                H_kj = H[j] @ np.linalg.inv(H[k])
                with contextlib.suppress(
                    SelfCalibrationError, ValueError, ArithmeticError, np.linalg.LinAlgError
                ):
                    transfer = self.config.intrinsics_model()  # IntrinsicsModel() for a zoom lens
                    K_j = intrinsics_from_transferred_diac(H_kj, K[k], transfer, image_size)
                    R_j = rotation_from_homography(H_kj, K[k], K_j) @ R[k]
                    if np.all(np.isfinite(K_j)) and np.all(np.isfinite(R_j)):
                        K[j], R[j] = K_j, R_j
            sigma_f, sigma_pp = np.asarray(lm.sigma_f, dtype=float).copy(), np.asarray(lm.sigma_pp).copy()
            sigma_f[keep], sigma_pp[keep] = result.sigma_f, result.sigma_pp
            if lam0 is not None and details.lam is not None:
                lam = lam0.copy()
                lam[keep] = details.lam
                details = dataclasses.replace(details, lam=lam[:n_frames])
            result = dataclasses.replace(
                result,
                K=K[:n_frames],
                R=R[:n_frames],
                sigma_f=sigma_f[:n_frames],
                sigma_pp=sigma_pp[:n_frames],
                bundle=details,
            )
        return result

    def measure_lens_model_change(self) -> float:
        """A fixed lens: |f' / f - 1| of the last solve (_lens_model_change), NaN when not measured.
        Runs the second adjustment on the first call after the solve and returns that value until the
        next solve: the session asks only when the solve could otherwise be published as CONVERGED."""
        if self._lens_check is not None:
            check, self._lens_check = self._lens_check, None
            self._lens_model_change_value = self._lens_model_change(*check)
        return self._lens_model_change_value

    def _lens_model_change(
        self,
        pairs: list[tuple[int, int, Array, Array]],
        result: SelfCalibrationResult,
        image_size: tuple[int, int],
        model: IntrinsicsModel,
        prior: tuple[Array, Array],
        noise: float,
    ) -> float:
        """A fixed lens: |f' / f - 1| with f' from the same adjustment with the radial term toggled
        (one shared coefficient added when it is not estimated, removed when it is), started at the
        solution. The disambiguating information of section 6.2 sits at the image edges, where the
        lens model acts (section 7): a focal length that moves with the lens model is not pinned by
        the geometry (a hand-held pan before its loop closes, not after). At most 6 iterations, and
        it stops once f has moved by twice converged_max_lens_model_change (the verdict is made), so
        a value above the bound is how far f moved at least. NaN when the alternative does not
        solve."""
        with_distortion = not (self.config.estimate_distortion and self.distortion_adopted is not False)
        try:
            alt = bundle_adjust(
                pair_observations(pairs),
                result.K,
                result.R,
                image_size,
                model,
                rays_init=None if result.bundle is None else result.bundle.rays,
                pp_prior=prior,
                noise_sigma=noise,
                max_iterations=min(self.config.ba_max_iterations, 6),
                # bundle_adjust's default damping: the solution is far from the alternative's minimum,
                # where a tiny initial damping has most steps refused
                distortion="shared" if with_distortion else False,
                analyse=False,
                max_focal_change=2.0 * self.config.converged_max_lens_model_change,
                uncertainty=False,
            )
        except (SelfCalibrationError, ValueError, np.linalg.LinAlgError):
            return math.nan
        f, f_alt = float(result.K[0, 1, 1]), float(alt.K[0, 1, 1])
        return abs(f_alt / f - 1.0) if alt.ok and math.isfinite(f_alt) else math.nan

    def _with_connectors(
        self,
        lm: SelfCalibrationResult,
        index: dict[Hashable, int],
        ids: list[Hashable],
        image_size: tuple[int, int],
        lens: LensModel,
    ) -> SelfCalibrationResult:
        """Raw-point solve: keyframes the calibrator dropped but matched to one it kept join the
        adjustment as connectors (appended to index and ids, started from their corrected chain by
        eq. 20), so that the kept keyframes stay linked to the reference by real matches."""
        extra_K, extra_R = [], []
        for m in list(self.matches.values()):
            for inside, other in ((m.keyframe_id, m.other_keyframe_id), (m.other_keyframe_id, m.keyframe_id)):
                if inside not in index or other in index or len(m.points) < 8:
                    continue
                H_c = lens.keyframe_homography(other)
                if H_c is None:
                    continue
                try:
                    K_c = intrinsics_from_transferred_diac(H_c, lm.K[0], IntrinsicsModel(), image_size)
                    R_c = rotation_from_homography(H_c, lm.K[0], K_c)
                except (SelfCalibrationError, ValueError, ArithmeticError, np.linalg.LinAlgError):
                    continue
                if np.all(np.isfinite(K_c)) and np.all(np.isfinite(R_c)):
                    index[other] = len(ids)
                    ids.append(other)
                    extra_K.append(K_c)
                    extra_R.append(R_c)
        if not extra_K:
            return lm
        m_extra = len(extra_K)
        return dataclasses.replace(
            lm,
            K=np.concatenate([lm.K, extra_K]),
            R=np.concatenate([lm.R, extra_R]),
            sigma_f=np.concatenate([np.asarray(lm.sigma_f, dtype=float), np.full(m_extra, np.nan)]),
            sigma_pp=np.concatenate(
                [np.asarray(lm.sigma_pp, dtype=float).reshape(-1, 2), np.full((m_extra, 2), np.nan)]
            ),
        )


class _LensCheck(NamedTuple):
    """A fixed lens's solve, kept for measure_lens_model_change (its adjustment's inputs and result)."""

    pairs: list[tuple[int, int, Array, Array]]
    result: SelfCalibrationResult
    image_size: tuple[int, int]
    model: IntrinsicsModel
    prior: tuple[Array, Array]
    noise: float


def _linked_to_reference(pairs: list[tuple[int, int, Array, Array]], n: int) -> NDArray[np.bool_]:
    """(n,) whether each frame is connected to frame 0 through the pairs."""
    neighbours: dict[int, set[int]] = {}
    for a, b, pa, _ in pairs:
        if len(pa):
            neighbours.setdefault(a, set()).add(b)
            neighbours.setdefault(b, set()).add(a)
    linked = np.zeros(n, dtype=bool)
    stack = [0]
    linked[0] = True
    while stack:
        for k in neighbours.get(stack.pop(), ()):
            if not linked[k]:
                linked[k] = True
                stack.append(k)
    return linked


def usable_result(result: SelfCalibrationResult) -> bool:
    """Accepted, or finite and flagged only for the near-ambiguity: a solution kept with its sigma."""
    return result.ok or uncertain_motion(result)


def uncertain_motion(result: SelfCalibrationResult) -> bool:
    """A finite solution flagged only for the focal/rotation near-ambiguity (section 6.2)."""
    motion = result.motion
    return (
        not result.ok
        and motion is not None
        and motion.status == STATUS_NEAR_AMBIGUOUS
        and bool(np.all(np.isfinite(result.K)))
        and bool(np.all(result.K[:, 1, 1] > 0.0))
    )


def _distortion_visible(
    result: SelfCalibrationResult, image_size: tuple[int, int], noise: float | None
) -> bool:
    """The adjustment's radial term moves some keyframe's image corner by more than its residual noise:
    a lens model that differs from a pinhole by something measurable (lens/hook.py keeps a lens whose
    distortion moves no corner by that much on its tracked homographies, as a pinhole)."""
    details = result.bundle
    if details is None or details.lam is None or noise is None:
        return False
    for K, lam in zip(result.K, details.lam):
        f = float(K[1, 1])
        rho = corner_radius(K, *image_size) / f
        if lam != 0.0 and f * abs(float(division_undistort_radius(rho, float(lam))) - rho) > noise:
            return True
    return False


def _pp_model(varying: bool) -> IntrinsicsModel:
    return IntrinsicsModel(principal_point=ParamMode.VARYING if varying else ParamMode.CONSTANT)


def _radial_unknowns(radial: bool | str, n_frames: int) -> int:
    """The distortion unknowns bundle_adjust adds: one coefficient per frame, one for the lens, or the
    lam(f) curve's (its default degree 2: three)."""
    return {"shared": 1, "curve": 3}.get(str(radial), n_frames)


def _guess(lens: LensModel, keyframe_id: int | None, f: float) -> float:
    """The lens model's starting lam of a frame (0.0 where it has none that is finite)."""
    try:
        lam = float(lens.lam_guess(keyframe_id, f))
    except (ValueError, ArithmeticError, KeyError):
        return 0.0
    return lam if math.isfinite(lam) else 0.0


def _visible(src: Array, dst: Array, width: int, height: int) -> tuple[Array, Array]:
    ok = np.isfinite(dst).all(axis=1)
    ok &= (dst[:, 0] >= 0) & (dst[:, 0] <= width - 1) & (dst[:, 1] >= 0) & (dst[:, 1] <= height - 1)
    return src[ok], dst[ok]
