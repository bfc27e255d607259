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
from ptz_selfcal.settings import setting

Array = NDArray[np.float64]


@dataclass
class SessionConfig:
    """The online calibrator's settings: each field is also the calibrator node's parameter of that name
    (or of its Setting.param), with this description and range (nodes/params.py)."""

    nominal_focal_px: float = setting(
        0.0,
        "nominal focal length in full-resolution pixels (> 0 overrides nominal_hfov_deg)",
        bounds=(0.0, 1e6),
    )
    nominal_hfov_deg: float = setting(
        60.0,
        "horizontal field of view (deg) of the nominal prior used before the first calibration",
        bounds=(1.0, 170.0),
    )
    min_rotation_deg: float = setting(
        2.0,
        "keyframe rotation off the reference's optical axis needed before the first solve (section 6)",
        bounds=(0.0, 90.0),
    )
    # the first solve waits for the motion (min_axis_disambiguation_px), not for a count: eq. 22 with
    # f per frame has more equations than unknowns from two frames besides the reference on
    min_keyframes: int = setting(
        2,
        "keyframes (tracker keyframes and calibration frames) needed before the first solve",
        bounds=(2, 1000),
    )
    min_axis_disambiguation_px: float = setting(
        2.0,
        "first solve once eq. 30's disambiguating term from the rotation about each camera axis (tilt and "
        "pan, at the reference's image corner) reaches this many pixels: well above the homographies' "
        "noise (sections 6.1 and 6.2)",
        bounds=(0.0, 1e4),
    )
    calibration_frames: bool = setting(
        True,
        "ordinary frames join the solve when they add rotation or zoom the set does not have (every "
        "frame's homography carries the information, not only the tracker's keyframes)",
    )
    calibration_frame_spacing: float = setting(
        0.03,
        "an ordinary frame joins the solve when it is this far from every frame of the set, in fields of "
        "view of rotation and log f (and, once the set is full, farther than its members' median gap)",
        bounds=(1e-4, 10.0),
    )
    # each one costs a re-optimisation; before the first solve they come as fast as the motion allows
    calibration_frame_period_s: float = setting(
        0.5,
        "once calibrated, an ordinary frame joins the solve at most once per this many seconds of image time",
        bounds=(0.0, 3600.0),
    )
    max_keyframes: int = setting(
        30, "keyframes kept in the re-optimisation (bounds time and memory)", bounds=(4, 1000)
    )
    bundle_adjustment: bool = setting(True, "refine LM with the keyframe bundle adjustment (section 5)")
    ba_principal_point: str = setting(
        "auto",
        "principal point in the bundle adjustment, with the MAP prior: constant, varying (per keyframe: a "
        "zoom lens moving it, section 5.3.1), or auto: varying only while it wins the information "
        "criterion (BIC) against constant on the keyframe matches, re-decided at every solve",
        choices=("auto", "constant", "varying"),
    )
    pp_prior_sigma_px: float = setting(
        20.0,
        "1-sigma (px) of the MAP principal-point prior at the image centre, each axis (eq. 27)",
        bounds=(0.1, 1e5),
    )
    ba_noise_sigma_px: float = setting(
        1.0, "image noise (px, 1-sigma) that weighs the principal-point prior (eq. 27)", bounds=(0.01, 100.0)
    )
    ba_max_points_per_pair: int = setting(
        50, "matches per keyframe pair used by the adjustment", bounds=(8, 10000)
    )
    ba_distortion_points_per_pair: int = setting(
        200,
        "matches per keyframe pair when the adjustment estimates distortion on raw points (more than "
        "ba_max_points_per_pair: the distortion centre needs them)",
        bounds=(8, 10000),
    )
    ba_max_iterations: int = setting(
        30, "iterations of one keyframe bundle adjustment at most", bounds=(1, 10000)
    )
    # a step lowering the cost by < 1e-6 of it moves the unknowns by ~sqrt(1e-6 dof) ~ 0.1 sigma at most
    # (dof ~ 1e4 residuals): smaller tolerances only creep along a pan's near-ambiguity, same final f
    ba_tolerance: float = setting(
        1e-6,
        "the adjustment stops when an iteration lowers its cost by less than this fraction",
        bounds=(0.0, 1.0),
    )
    # a larger start creeps along a pan's near-ambiguity for more iterations to the same solution
    ba_initial_damping: float = setting(
        1e-9, "LM's starting damping in the keyframe bundle adjustment", bounds=(0.0, 1e6)
    )
    max_match_pairs: int = setting(
        256, "keyframe match sets kept at most (the oldest are dropped)", bounds=(1, 100000)
    )
    max_focal_ratio: float = setting(
        20.0, "homographies scaling more than this are tracker failures and are ignored", bounds=(1.0, 1e4)
    )
    prior_sigma_f_fraction: float = setting(
        0.3,
        "1-sigma reported for f, as a fraction of f, while K comes from the nominal parameters",
        bounds=(0.0, 100.0),
    )
    zoom_model_min_keyframes: int = setting(
        4, "converged keyframes sampled before the zoom model is used", bounds=(1, 100000)
    )
    # The node runs the re-optimisation beside the tracker on the same cores: after a solve of t seconds
    # the next waits max(min_solve_period_s, t (1 - duty) / duty).
    min_solve_period_s: float = setting(
        0.1,
        "seconds at least between two re-optimisations (keyframes arriving meanwhile are batched)",
        bounds=(0.0, 3600.0),
        param="reoptimise_min_interval",
    )
    max_solve_duty: float = setting(
        0.5,
        "largest fraction of one core the re-optimisation may use (it shares the cores with the tracker)",
        bounds=(0.01, 1.0),
        param="reoptimise_max_duty",
    )
    # Frame gates (issue 7): a homography whose K (DIAC transfer, eq. 20) contradicts the zoom model is
    # refused: PREDICTED_FROM_ZOOM, never a keyframe of the solve.
    zoom_gate_sigmas: float = setting(
        4.0,
        "zoom gate: a frame's K further than max(zoom_gate_floor, this many sigma) in log f from the zoom "
        "model at its zoom encoder, inside the model's learned zoom range, is refused",
        bounds=(0.0, 1000.0),
    )
    zoom_gate_floor: float = setting(
        0.1, "zoom gate: the smallest disagreement in log f that refuses a frame", bounds=(0.0, 10.0)
    )
    zoom_gate_still: float = setting(
        0.01,
        "zoom gate: judged only while the zoom model's f changes by less than this (log f) from the "
        "previous frame's zoom encoder (a moving zoom's encoder can lag the image)",
        bounds=(0.0, 10.0),
    )
    # 6 widths/s = 20 % of the width per frame at 30 fps: a preset recall, not tracking; such
    # homographies chain over small overlaps and drift, and real cameras blur them
    max_keyframe_motion: float = setting(
        6.0,
        "keyframes of a faster move (image corners moving more than this many image widths per second) "
        "stay out of the solve; their frames are still calibrated",
        bounds=(1e-3, 1e6),
    )
    focal_model: str = setting(
        "varying",
        "varying: a zooming camera, f per keyframe (pan-only or tilt-only motion is DEGENERATE_MOTION); "
        "constant: a fixed lens, one f and principal point for every image, calibrated by a pan alone "
        "(section 6.1: constant K with square pixels and zero skew)",
        choices=("varying", "constant"),
    )
    # In the session this is the fixed lens's one coefficient (bundle/adjust distortion="shared"); the
    # node gives a zooming lens's estimate_distortion to lens/hook.SessionLensHook instead.
    estimate_distortion: bool = setting(
        True,
        "radial distortion (section 7). focal_model varying: through lens/hook.SessionLensHook, "
        "division model about the principal point estimated in the keyframe bundle adjustment on the raw "
        "keyframe matches (lam(f) curve), homographies corrected with it before self-calibration. "
        "focal_model constant: ONE division coefficient for the lens, estimated with K in that "
        "adjustment. D = its plumb_bob fit at each frame's K. With distortion_selection, adopted only "
        "while the data shows it; false: a pinhole lens, D = 0",
    )
    distortion_selection: bool = setting(
        True,
        "with estimate_distortion: every solve fits the adjustment with and without distortion on the "
        "same raw keyframe matches and keeps distortion only while it wins the information criterion "
        "(BIC), so a lens without distortion gets none; false: distortion always estimated",
    )
    # sigma_f is honest (online/status_policy.py): below this bound 1 % is several sigma away
    converged_max_sigma_f: float = setting(
        0.002,
        "CONVERGED only while the focal length's honest 1-sigma (common scale included, section 6.2) is "
        "below this fraction (else CALIBRATING)",
        bounds=(1e-6, 1.0),
    )
    model_mismatch_ratio: float = setting(
        1.5,
        "MODEL_MISMATCH when the keyframe matches fit the lens model (one homography per pair, or the "
        "adjustment with distortion) worse than this many times the tracker's noise (local fits)",
        bounds=(1.0, 1e6),
    )
    # sigma_f does not measure the lens model's bias: toggling the radial term does (conservative: a
    # strongly distorted lens whose pan never closes a loop stays CALIBRATING)
    converged_max_lens_model_change: float = setting(
        0.02,
        "focal_model constant: CONVERGED only while f moves by less than this fraction when the "
        "adjustment's radial term is toggled (a focal length the lens model moves is not pinned by the "
        "geometry: a hand-held pan before its loop closes)",
        bounds=(1e-6, 10.0),
    )

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
