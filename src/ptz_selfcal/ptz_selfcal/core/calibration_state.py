"""The calibrator's per-frame logic and what it persists (pure: numpy + the calibration core, no rclpy).

`CalibratorSession` is everything the calibrator node does between "a HomographyStamped arrived" and
"publish this K". It wraps `core.incremental.IncrementalCalibrator` (initialisation once the motion is
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

from ptz_selfcal.core.atomic_file import atomic_write_text, remove_stale_temporaries
from ptz_selfcal.core.bundle import bundle_adjust, pair_observations
from ptz_selfcal.core.degeneracy import STATUS_NEAR_AMBIGUOUS
from ptz_selfcal.core.distortion import division_to_plumb_bob
from ptz_selfcal.core.geometry import apply_homography, intrinsic_matrix, pixel_grid, rotation_from_homography
from ptz_selfcal.core.incremental import (
    CalibrationState,
    IncrementalCalibrator,
    Keyframe,
    focal_disagrees,
    image_motion,
    intrinsics_from_transferred_diac,
)
from ptz_selfcal.core.intrinsics import (
    IntrinsicsModel,
    ParamMode,
    SelfCalibrationError,
    SelfCalibrationResult,
    image_centre,
)
from ptz_selfcal.core.lm_selfcal import lm_selfcalibration
from ptz_selfcal.core.zoom_model import ZoomModel, ZoomModelError, ZoomRate

Array = NDArray[np.float64]

_LOG = logging.getLogger(__name__)

STATE_VERSION = 1
STATE_FILE = "calibration_state.yaml"
ZOOM_MODEL_FILE = "zoom_model.yaml"

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
# State files
# --------------------------------------------------------------------------------------------------
class StateFileError(Exception):
    """A state file that exists but cannot be used (corrupt, wrong version, wrong camera)."""


def load_yaml_file(path: str | os.PathLike[str]) -> dict | None:
    """The mapping in a YAML file; None when the file does not exist; StateFileError when unusable."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        first = (str(exc).splitlines() or [""])[0]
        raise StateFileError(f"{path}: unreadable ({type(exc).__name__}: {first})") from exc
    if not isinstance(data, dict):
        raise StateFileError(f"{path}: not a YAML mapping")
    return data


# --------------------------------------------------------------------------------------------------
# Inputs and outputs of one frame
# --------------------------------------------------------------------------------------------------
@dataclass
class FrameInput:
    """What the calibrator knows about one image (from its HomographyStamped)."""

    stamp: float  # seconds
    H: Array | None  # reference -> this frame, full-resolution pixels (None: no homography)
    tracking_state: str  # HomographyStamped state name
    width: int
    height: int
    keyframe_id: int = 0
    reference_id: str = ""
    zoom: float = math.nan  # zoom encoder (NaN when invalid)


@dataclass
class FrameOutput:
    """The calibration of one image: what goes into its CameraInfo and FrameCalibration."""

    status: str
    K: Array
    D: Array  # plumb_bob [k1, k2, 0, 0, 0]
    R: Array | None  # orientation relative to the calibration's reference frame (None: unknown)
    sigma_f: float
    sigma_cx: float
    sigma_cy: float
    residual: float
    keyframe_id: int
    keyframe_count: int
    source: str  # where K came from: calibration / prior / zoom_model / last_good / nominal
    message: str = ""
    time_s: float = 0.0


@dataclass
class SessionConfig:
    nominal_focal_px: float = 0.0  # > 0 overrides nominal_hfov_deg
    nominal_hfov_deg: float = 60.0
    min_rotation_deg: float = 2.0  # keyframe rotation needed before the first solve (section 6)
    min_keyframes: int = 4
    max_keyframes: int = 30
    bundle_adjustment: bool = True
    ba_principal_point: str = "constant"  # "constant" or "varying" (per keyframe), both with the prior
    pp_prior_sigma_px: float = 20.0  # MAP principal point prior (eq. 27), 1-sigma each axis
    ba_noise_sigma_px: float = 1.0  # image noise that weighs the prior (eq. 27)
    ba_max_points_per_pair: int = 50
    # with distortion estimated in the adjustment (raw points): more per pair, the distortion centre
    # needs them (issue-6 bag replayed: focal median 0.32% with 50, 0.22% with 200)
    ba_distortion_points_per_pair: int = 200
    ba_max_iterations: int = 30
    # the adjustment stops when an iteration lowers its cost by less than this fraction: a step worth
    # < 1e-6 of the cost moved the unknowns by ~sqrt(1e-6 dof) ~ 0.1 of their 1-sigma at most (dof ~
    # 1e4 residuals); the former 1e-10 spent a third of a warm-started adjustment's iterations
    # creeping along the near-ambiguity of a pan before its loop closes (real sets: same final f)
    ba_tolerance: float = 1e-6
    # LM's starting damping in the adjustment (bundle_adjust initial_damping): 1e-6 crept along a
    # pan's near-ambiguity (real sets: 66-91 iterations over a set instead of 42-77, same solutions)
    ba_initial_damping: float = 1e-9
    max_match_pairs: int = 256
    max_focal_ratio: float = 20.0  # homographies scaling more than this are tracker failures
    prior_sigma_f_fraction: float = 0.3  # 1-sigma reported for f from nominal parameters
    zoom_model_min_keyframes: int = 4  # converged keyframes before the zoom model is used
    # CPU share of the re-optimisation (the node runs it beside the tracker on the same cores): after a
    # solve of t seconds the next waits max(min_solve_period_s, t (1 - duty) / duty); 0 = no limit
    min_solve_period_s: float = 0.0
    max_solve_duty: float = 1.0
    # Frame gates (issue 7). A homography whose K (DIAC transfer, eq. 20) contradicts the zoom model at
    # the frame's zoom encoder by more than max(zoom_gate_floor, zoom_gate_sigmas sigma) in log f, inside
    # the model's learned zoom range, is refused: PREDICTED_FROM_ZOOM, never a keyframe of the solve.
    zoom_gate_sigmas: float = 4.0
    zoom_gate_floor: float = 0.1
    zoom_gate_still: float = 0.01  # judged only while the zoom encoder changes less per frame
    # Keyframes of a fast move (image corners moving more than this many image widths per second, i.e.
    # 20 % of the width per frame at 30 fps: a preset recall, not tracking) stay out of the solve: their
    # homographies chain over small overlaps and drift, and real cameras blur them. Their frames are
    # still calibrated. (The CI synth bag's sweep moves up to ~11 % per frame.)
    max_keyframe_motion: float = 6.0
    # "varying": a zooming camera, f per keyframe (pan-only motion is DEGENERATE_MOTION, section 6.1).
    # "constant": a fixed lens, one f and one principal point for every image (square pixels, zero
    # skew): a pan alone calibrates it (degeneracy.single_axis_is_degenerate); every frame has that K.
    focal_model: str = "varying"
    # Fixed lens only: ONE radial (division) coefficient about the principal point for every image,
    # estimated with K in the keyframe bundle adjustment on the raw keyframe matches (bundle.py
    # distortion="shared"). A zooming lens estimates distortion through core/lens_correction instead.
    estimate_distortion: bool = False
    # Fixed lens: CONVERGED (what a user may take as the calibration) also needs the focal length's
    # 1-sigma below this fraction; above it a stable solution is still CALIBRATING (DESIGN.md 5.5:
    # uncertainty reported instead of confident nonsense). A hand-held pan's sigma_f is 2-5% before
    # its loop closes, 0.02-0.04% after (the real sets, benchmarks/peers.py).
    converged_max_sigma_f: float = 0.01
    # Fixed lens: CONVERGED also needs f to move by less than this fraction when the adjustment's
    # radial term is toggled (KeyframeBundleSolver._lens_model_change): sigma_f measures the noise, not
    # the lens model's bias (grail before its loop closes: sigma_f 0.7%, 5-7% off AutoStitch, 18% apart
    # with and without the radial term; after: 0.9%). Conservative: a strongly distorted lens whose
    # pan never closes a loop stays CALIBRATING.
    converged_max_lens_model_change: float = 0.02

    def __post_init__(self) -> None:
        if self.focal_model not in ("varying", "constant"):
            raise ValueError(f"focal_model must be 'varying' or 'constant', not {self.focal_model!r}")

    @property
    def fixed_lens(self) -> bool:
        return self.focal_model == "constant"

    def intrinsics_model(self) -> IntrinsicsModel:
        """The self-calibration model (section 3.3.1): square pixels, zero skew, a constant principal
        point, and f varying per frame or (a fixed lens) constant."""
        if self.fixed_lens:
            return IntrinsicsModel(focal=ParamMode.CONSTANT)
        return IntrinsicsModel()

    def nominal_focal(self, width: int) -> float:
        if self.nominal_focal_px > 0.0:
            return float(self.nominal_focal_px)
        return 0.5 * width / math.tan(math.radians(0.5 * self.nominal_hfov_deg))


# --------------------------------------------------------------------------------------------------
# The solver plugged into IncrementalCalibrator's seam: LM (eq. 22), then keyframe BA (eq. 27)
# --------------------------------------------------------------------------------------------------
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

    Radial distortion (core/lens_correction.SessionLensHook sets `lens`): the matches are then RAW
    (distorted) pixels and the adjustment estimates one division coefficient per frame about the
    principal point with everything else (core/bundle.py, distortion=True), starting from
    lens.lam_guess(keyframe_id, f); a frame's virtual correspondences (its homography is on corrected
    pixels) are distorted back with the lens model that corrected it, lens.distort(keyframe_id, pts),
    so that they stand for the raw points and carry no assumption about the distortion centre.
    The prior of eq. 27 is weighed with the image noise of the previous accepted solve (its residual
    standard deviation, within [0.02, ba_noise_sigma_px]), with or without distortion: tracked matches
    fit to ~0.05-0.15 px, and a prior weighed for the printed 1 px noise acts as a ~10x too strong
    prior that pulls the principal point (and, near the ambiguity of a long focal length, f) to the
    image centre. `lens_estimate` keeps the last such solution for the hook. Keyframe id None = the reference.
    A fixed lens's solves after the first start the adjustment from the previous one (_warm_start)
    rather than from LM, and its lens-model check runs only when the session asks for it.
    """

    def __init__(self, config: SessionConfig, matches: OrderedDict[tuple[int, int], KeyframeMatchSet]):
        self.config = config
        self.matches = matches
        self.reference_keyframe_id: int | None = None
        self.rotations: dict[Any, Array] = {}  # keyframe id -> R relative to the reference (last solve)
        self.last_method = ""
        self.last_message = ""
        self.sigma_f: dict[Any, float] = {}  # keyframe id -> 1-sigma of f in the last accepted solve
        self.lens: Any = None  # lam_guess(keyframe_id, f), distort(keyframe_id, pts); None: undistorted
        self.lens_estimate: LensEstimate | None = None
        self.noise_estimate: float | None = None  # px, residual sigma of the last accepted solve
        self.distortion_mode = "curve"  # lam per frame on a lam(f) curve ("curve") or free ("frame")
        # a fixed lens with estimate_distortion: the one division coefficient and its 1-sigma
        self.shared_lam: float | None = None
        self.sigma_shared_lam = math.nan
        # a fixed lens: see _lens_model_change (last solve), measured when first asked for (the
        # session asks only when the solve could otherwise be CONVERGED)
        self._lens_model_change_value = math.nan
        self._lens_check: tuple | None = None  # the solve's inputs until it is measured
        # a fixed lens: the last adjustment (reference keyframe id, K, keyframe id -> R), _warm_start
        self._warm: tuple[Any, Array, dict[Any, Array]] | None = None

    def __call__(
        self,
        H: Array,
        image_size: tuple[int, int],
        model: IntrinsicsModel,
        K_init: Array | None,
        keyframes: list[Keyframe],
        max_nfev: int,
    ) -> SelfCalibrationResult:
        if self.lens is not None:
            # the keyframes' homographies as the lens correction has them now (chained or provisional):
            # the ones stored at arrival may come from an older correction, and the frames are
            # corrected with the current one (a stale keyframe homography put its frames 1% off)
            H = H.copy()
            for i, kf in enumerate(keyframes, start=1):
                H_now = self.lens.keyframe_homography(kf.keyframe_id)
                if H_now is not None and np.all(np.isfinite(H_now)):
                    kf.H = H[i] = H_now
        result = None
        warm = self._warm_start(H, keyframes)
        if warm is not None:
            self.last_method, self.last_message = warm.method, ""
            result = self._refine(H, image_size, warm, keyframes)
            if result is warm or not _usable(result):
                result = None  # LM on eq. 22 and the adjustment from it, as for the first solve
        if result is None:
            # LM on <= max_keyframes + 1 homographies takes milliseconds: the calibrator's time-derived
            # evaluation budget (which also counts the adjustment) would stop it short of convergence
            lm = lm_selfcalibration(H, image_size, model, K_init, max_nfev=max(int(max_nfev), 100))
            self.last_method, self.last_message = lm.method, lm.message
            result = self._refine(H, image_size, lm, keyframes)
        self._keep_warm_start(result, keyframes)
        if result.ok:
            self.rotations = {kf.keyframe_id: R for kf, R in zip(keyframes, result.R[1:])}
            # 1-sigma of each frame's f (the adjustment's Jacobian): the zoom model's sample weights
            ids = [self.reference_keyframe_id, *(kf.keyframe_id for kf in keyframes)]
            self.sigma_f = {k: float(s) for k, s in zip(ids, np.ravel(result.sigma_f)) if k is not None}
        return result

    def _warm_start(self, H: Array, keyframes: list[Keyframe]) -> SelfCalibrationResult | None:
        """A fixed lens: the adjustment's start from its previous solution instead of LM on eq. 22.

        LM on a hand-held pan's homographies is 8-18% off in f (the real sets), so an adjustment
        started there spends 10-30 iterations walking back to where the previous one ended; one more
        still moves the solution by a fraction of a per cent. K is the previous adjustment's, each
        keyframe it held keeps its rotation, a new keyframe gets the rotation of its homography
        relative to the nearest held one (the direct link, not the chain from the reference). None
        (LM as for the first solve) for a zooming lens, without a previous adjustment, or when it
        holds none of these keyframes.
        """
        if not (self.config.fixed_lens and self.lens is None and self.config.bundle_adjustment):
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
            info={"solver_ok": True},
        )

    def _keep_warm_start(self, result: SelfCalibrationResult, keyframes: list[Keyframe]) -> None:
        """Remember an accepted adjustment (reference, K, keyframe id -> R) for _warm_start."""
        adjusted = "rays" in result.info and _usable(result)
        if not (self.config.fixed_lens and adjusted and np.all(np.isfinite(result.R))):
            return
        held = {kf.keyframe_id: R.copy() for kf, R in zip(keyframes, result.R[1:])}
        self._warm = (self.reference_keyframe_id, result.K[0].copy(), held)

    def forget_warm_start(self) -> None:
        """The next solve starts from LM on eq. 22 (a new map or restored keyframes)."""
        self._warm = None

    def _refine(
        self, H: Array, image_size: tuple[int, int], lm: SelfCalibrationResult, keyframes: list[Keyframe]
    ) -> SelfCalibrationResult:
        self._lens_model_change_value, self._lens_check = math.nan, None  # this solve's, if any
        # raw-point solve: an LM start flagged only for its motion (section 6.2, LM on corrected
        # homographies) is still refined, the adjustment's own analysis decides
        # a fixed lens likewise: LM on homographies of a pan flags a near-ambiguity that the
        # adjustment on the point matches resolves (measured on the real hand-held sets)
        usable = lm.ok or (
            (self.lens is not None or self.config.fixed_lens)
            and bool(lm.info.get("solver_ok", False))
            and bool(np.all(np.isfinite(lm.K)))
        )
        if not usable or not self.config.bundle_adjustment:
            return lm
        try:
            ba = self._bundle(H, image_size, lm, keyframes)
        except (SelfCalibrationError, ValueError, np.linalg.LinAlgError) as exc:
            self.last_message = f"bundle adjustment skipped: {exc}"
            return lm
        if ba is not None and self.config.fixed_lens and _uncertain_motion(ba):
            # a fixed lens: the adjustment's near-ambiguity verdict (6.2) stands, with its own estimate
            # (uncertain: DEGENERATE_MOTION), rather than LM's confident one on homographies
            # (the real sets before their loop closes: LM 8-18% off with a 1-2% sigma)
            ba.info["solver_ok"] = True
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
        return ba

    def _bundle(
        self, H: Array, image_size: tuple[int, int], lm: SelfCalibrationResult, keyframes: list[Keyframe]
    ) -> SelfCalibrationResult | None:
        index = {kf.keyframe_id: i + 1 for i, kf in enumerate(keyframes)}
        if self.reference_keyframe_id is not None:
            index[self.reference_keyframe_id] = 0
        ids = [self.reference_keyframe_id, *(kf.keyframe_id for kf in keyframes)]
        n_frames = len(H)
        fixed = self.config.fixed_lens
        shared = fixed and self.config.estimate_distortion and self.lens is None
        lam0 = None
        if self.lens is not None:
            lm = self._with_connectors(lm, index, ids, image_size)
            lam0 = np.array([_guess(self.lens.lam_guess, k, float(K[1, 1])) for k, K in zip(ids, lm.K)])
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
            if self.lens is not None:  # the homographies are on corrected pixels: distort the points
                a, b, src, dst = pairs[-1]
                src, dst = self.lens.distort(ids[a], src), self.lens.distort(ids[b], dst)
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
        if fixed:  # one K for every image: a per-keyframe principal point would not be a fixed lens
            model = self.config.intrinsics_model()
        else:
            model = IntrinsicsModel(
                principal_point=ParamMode.VARYING
                if self.config.ba_principal_point == "varying"
                else ParamMode.CONSTANT
            )
        sigma = self.config.pp_prior_sigma_px
        prior = (np.array(image_centre(image_size)), np.array([sigma, sigma]))
        noise = self.config.ba_noise_sigma_px
        if self.noise_estimate is not None:  # eq. 27 weighed with the measured image noise
            noise = min(max(self.noise_estimate, 0.02), noise)
        keep = np.array([j for j in range(len(lm.K)) if j not in set(absent)], dtype=np.intp)
        renumber = np.full(len(lm.K), -1, dtype=np.intp)
        renumber[keep] = np.arange(len(keep))
        pairs = [(int(renumber[a]), int(renumber[b]), pa, pb) for a, b, pa, pb in pairs]
        result = bundle_adjust(
            pair_observations(pairs),
            lm.K[keep],
            lm.R[keep],
            image_size,
            model,
            pp_prior=prior,
            noise_sigma=noise,
            max_iterations=self.config.ba_max_iterations,
            tolerance=self.config.ba_tolerance,
            initial_damping=self.config.ba_initial_damping,
            f_min=0.2 * float(np.min(lm.K[:, 1, 1])),
            distortion=False if lam0 is None else ("shared" if shared else self.distortion_mode),
            lam_init=None if lam0 is None else lam0[keep],
        )
        if (
            lam0 is not None
            and (result.ok or (shared and _uncertain_motion(result)))
            and np.all(np.isfinite(result.info["lam"]))
        ):
            self.noise_estimate = math.sqrt(float(result.info["residual_variance"]))
            if shared:
                self.shared_lam = float(result.info["lam"][0])
                self.sigma_shared_lam = float(result.info["sigma_lam"][0])
            self.lens_estimate = LensEstimate(
                principal_point=result.K[0, :2, 2].copy(),
                sigma_pp=np.asarray(result.sigma_pp[0], dtype=float).copy(),
                lam={ids[j]: float(lam) for j, lam in zip(keep, result.info["lam"]) if ids[j] is not None},
                focal={ids[j]: float(K[1, 1]) for j, K in zip(keep, result.K) if ids[j] is not None},
            )
        if lam0 is None and result.ok:
            self.noise_estimate = math.sqrt(float(result.info["residual_variance"]))
        rel_sigma = float(np.ravel(result.sigma_f)[0]) / float(result.K[0, 1, 1])
        if fixed and _usable(result) and rel_sigma <= self.config.converged_max_sigma_f:
            # only when it can decide (above that sigma the solution is not CONVERGED anyway)
            self._lens_check = (pairs, result, image_size, model, prior, noise)
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
                # (LM's own K carries the long chain's drift: 1.5% on the issue-6 bag)
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
            info = dict(result.info)
            if lam0 is not None and "lam" in info:
                lam = lam0.copy()
                lam[keep] = info["lam"]
                info["lam"] = lam[:n_frames]
            result = dataclasses.replace(
                result,
                K=K[:n_frames],
                R=R[:n_frames],
                sigma_f=sigma_f[:n_frames],
                sigma_pp=sigma_pp[:n_frames],
                info=info,
            )
        return result

    @property
    def lens_model_change(self) -> float:
        """A fixed lens: |f' / f - 1| of the last solve (_lens_model_change), NaN when not measured.
        The second adjustment runs on the first request after the solve: the session asks for it only
        when the solve could otherwise be published as CONVERGED."""
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
        the geometry (the real hand-held sets before their loop closes: 13-20 %; after: < 1 %). At
        most 6 iterations, and it stops once f has moved by twice converged_max_lens_model_change
        (the verdict is made: 3-6 % after one or two iterations there), so a value above the bound
        is how far f moved at least. NaN when the alternative does not solve."""
        with_distortion = not self.config.estimate_distortion
        try:
            alt = bundle_adjust(
                pair_observations(pairs),
                result.K,
                result.R,
                image_size,
                model,
                rays_init=result.info.get("rays"),
                pp_prior=prior,
                noise_sigma=noise,
                max_iterations=min(self.config.ba_max_iterations, 6),
                # bundle_adjust's default damping: the solution is far from the alternative's minimum
                # (from 1e-9 two of every three steps were refused: 3x the Schur solves, real sets)
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
        self, lm: SelfCalibrationResult, index: dict[Any, int], ids: list[Any], image_size: tuple[int, int]
    ) -> SelfCalibrationResult:
        """Raw-point solve: keyframes the calibrator dropped but matched to one it kept join the
        adjustment as connectors (appended to index and ids, started from their corrected chain by
        eq. 20), so that the kept keyframes stay linked to the reference by real matches."""
        extra_K, extra_R = [], []
        for m in list(self.matches.values()):
            for inside, other in ((m.keyframe_id, m.other_keyframe_id), (m.other_keyframe_id, m.keyframe_id)):
                if inside not in index or other in index or len(m.points) < 8:
                    continue
                H_c = self.lens.keyframe_homography(other)
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


@dataclass(frozen=True)
class LensEstimate:
    """Distortion from the keyframe adjustment on raw points: the principal point (= distortion centre)
    with its 1-sigma, and each frame's division coefficient lam at its focal length."""

    principal_point: Array
    sigma_pp: Array
    lam: dict[int, float]
    focal: dict[int, float]


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


def _usable(result: SelfCalibrationResult) -> bool:
    """Accepted, or finite and flagged only for the near-ambiguity: a solution kept with its sigma."""
    return result.ok or _uncertain_motion(result)


def _uncertain_motion(result: SelfCalibrationResult) -> bool:
    """A finite solution flagged only for the focal/rotation near-ambiguity (section 6.2)."""
    motion = result.motion
    return (
        not result.ok
        and motion is not None
        and motion.status == STATUS_NEAR_AMBIGUOUS
        and bool(np.all(np.isfinite(result.K)))
        and bool(np.all(result.K[:, 1, 1] > 0.0))
    )


def _guess(guess: Any, keyframe_id: int | None, f: float) -> float:
    try:
        lam = float(guess(keyframe_id, f))
    except (ValueError, ArithmeticError, KeyError):
        return 0.0
    return lam if math.isfinite(lam) else 0.0


def _visible(src: Array, dst: Array, width: int, height: int) -> tuple[Array, Array]:
    ok = np.isfinite(dst).all(axis=1)
    ok &= (dst[:, 0] >= 0) & (dst[:, 0] <= width - 1) & (dst[:, 1] >= 0) & (dst[:, 1] <= height - 1)
    return src[ok], dst[ok]


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
        """plumb_bob D of a calibrated frame: from `distortion_model` (e.g. core/lens_correction's
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
        """The calibrator's keyframe homographies were replaced in place (core/lens_correction's
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
