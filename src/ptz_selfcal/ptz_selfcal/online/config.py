"""The online calibrator's configuration: the one source of its defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.intrinsics import (
    IntrinsicsModel,
    ParamMode,
)

Array = NDArray[np.float64]


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
    # distortion="shared"). A zooming lens estimates distortion through lens/correction instead.
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
