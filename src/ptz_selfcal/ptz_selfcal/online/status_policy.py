"""The status policy: when a calibration is CONVERGED, and when its lens model is wrong (MODEL_MISMATCH).

CONVERGED is a promise: the frame's stated 1-sigma of f is honest and small, so the focal length is
within a fraction of a per cent. A solver that stops moving (two solves in a row within converge_tol)
promises neither: near the f / rotation ambiguity of section 6.2 the whole sequence shares one scale
error that successive solves repeat, and a lens model without its radial term (section 7) converges
firmly to the wrong f. So the policy asks, in this order:

1. lens model: do the keyframe matches fit the model in use about as well as the tracker's own noise?
   The tracker's noise is measured locally on the same matches (one homography per image cell: distortion
   and a rolling shutter bend the map only smoothly across a cell); the model's misfit is one homography
   over the whole pair (the exact map of a rotating pinhole camera, section 2.2) or, with distortion
   estimated, the bundle adjustment's residual noise. Far above: MODEL_MISMATCH, whatever the motion.
2. the solver's own verdict (INITIALISING, CALIBRATING, DEGENERATE_MOTION stand); a lens model whose
   fit is not measured yet is not CONVERGED.
3. the honest 1-sigma of f, from the bundle adjustment (LM on eq. 22 weighs algebraic residuals, not
   image noise): the adjustment's covariance is scaled by its own residuals, which its
   noise-free virtual correspondences and its fitted rays make smaller than the tracker's noise, so
   sigma is rescaled to the tracker's noise; above max_sigma_f: CALIBRATING.
4. a fixed lens: f must not move when the radial term is toggled (keyframe_solver's lens-model check).

A frame inherits its calibration's status only while its own 1-sigma of f (the calibration's, its
transfer's, its homography's: online/frame_intrinsics) is below max_sigma_f as well (`frame_status`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import apply_homography
from ptz_selfcal.frontend.homography import homography_dlt
from ptz_selfcal.status import CalibrationStatus

Array = NDArray[np.float64]

_S = CalibrationStatus


@dataclass(frozen=True)
class PairFit:
    """One keyframe match set's transfer residuals (px^2 summed, degrees of freedom): one homography over
    the whole pair (`pinhole`) and one per image cell (`local`, the tracker's noise)."""

    pinhole_ss: float
    pinhole_dof: int
    local_ss: float
    local_dof: int


def _homography_ss(src: Array, dst: Array) -> tuple[float, int]:
    H = homography_dlt(src, dst)
    r = dst - apply_homography(H, src)
    return float(np.sum(r * r)), 2 * len(src) - 8


def pair_fit(points: Array, other_points: Array, cells: int = 3, min_cell: int = 10) -> PairFit | None:
    """The fits of one match set (other_points -> points), None when too few points for the cells."""
    a = np.asarray(other_points, dtype=float).reshape(-1, 2)
    b = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(a) < 2 * min_cell or not (np.isfinite(a).all() and np.isfinite(b).all()):
        return None
    lo, hi = a.min(axis=0), a.max(axis=0)
    cell = np.minimum(((a - lo) / np.maximum(hi - lo, 1e-9) * cells).astype(int), cells - 1)
    key = cell[:, 0] * cells + cell[:, 1]
    local_ss, local_dof = 0.0, 0
    try:
        pinhole_ss, pinhole_dof = _homography_ss(a, b)
        for k in np.unique(key):
            inside = key == k
            if inside.sum() >= min_cell:
                ss, dof = _homography_ss(a[inside], b[inside])
                local_ss, local_dof = local_ss + ss, local_dof + dof
    except (ValueError, np.linalg.LinAlgError):
        return None
    if local_dof <= 0 or not (math.isfinite(pinhole_ss) and math.isfinite(local_ss)):
        return None
    return PairFit(pinhole_ss, pinhole_dof, local_ss, local_dof)


class ModelFit:
    """The fits of the recent keyframe match sets (bounded), pooled: the tracker's noise and the
    pinhole model's misfit, both as the rms transfer error of one coordinate in pixels."""

    def __init__(self, max_pairs: int = 32, min_dof: int = 150, min_pairs: int = 2) -> None:
        self.max_pairs = max_pairs
        self.min_dof = min_dof
        self.min_pairs = min_pairs
        self._fits: OrderedDict[Hashable, PairFit] = OrderedDict()

    def add(self, key: Hashable, points: Array, other_points: Array) -> None:
        fit = pair_fit(points, other_points)
        if fit is None:
            return
        self._fits[key] = fit
        self._fits.move_to_end(key)
        while len(self._fits) > self.max_pairs:
            self._fits.popitem(last=False)

    def forget(self) -> None:
        self._fits.clear()

    def _pooled(self, ss: str, dof: str) -> float:
        total = sum(getattr(f, dof) for f in self._fits.values())
        if len(self._fits) < self.min_pairs or total < self.min_dof:
            return math.nan
        return math.sqrt(sum(getattr(f, ss) for f in self._fits.values()) / total)

    @property
    def tracker_noise(self) -> float:
        """NaN until enough matches were seen."""
        return self._pooled("local_ss", "local_dof")

    @property
    def pinhole_misfit(self) -> float:
        return self._pooled("pinhole_ss", "pinhole_dof")


@dataclass(frozen=True)
class StatusPolicy:
    """The bounds of the status policy (SessionConfig's converged_max_sigma_f, model_mismatch_ratio,
    converged_max_lens_model_change)."""

    max_sigma_f: float  # CONVERGED only while the honest 1-sigma of f is below this fraction of f
    max_misfit_ratio: float  # MODEL_MISMATCH beyond this ratio of the model's misfit to the tracker's noise
    max_lens_model_change: float | None = None  # a fixed lens: f's move with the radial term toggled


@dataclass(frozen=True)
class StatusEvidence:
    """What the policy decides on."""

    solver_state: CalibrationStatus  # the incremental calibrator's verdict (motion, stability)
    solver_message: str
    sigma_f: float  # honest relative 1-sigma of the reference f (NaN: unknown)
    misfit: float  # the lens model's residual noise, px (transfer error per coordinate; NaN: unknown)
    tracker_noise: float  # the same, of the local fits: the tracker's noise (NaN: unknown)
    lens_model_change: Callable[[], float] | None = None  # measured only when it can decide
    adjusted: bool = True  # the solve ended in the bundle adjustment (sigma in image noise)


def honest_sigma(
    sigma_f: float,
    adjustment_noise: float | None,
    tracker_noise: float,
    keyframe_spread: float = 0.0,
    lens_model_gap: float = 0.0,
) -> float:
    """The adjustment's relative 1-sigma of f rescaled from its own residual noise (per observation) to the
    tracker's (per observation: a transfer error is two observations' noise, hence sqrt 2), never smaller;
    combined with the keyframes' spread: how far the adjustment's per-keyframe f departs from the reference
    K carried to the keyframe by its homography (eq. 20), which the frames inherit and the covariance of
    a weakly linked chain of keyframes leaves out; and with the lens model's gap: how far the two routes
    to f of a distorted lens disagree (section 7's corrected homographies through LM on eq. 22, and the
    adjustment of eq. 27 with the radial term on the raw matches). Both fit the matches to the tracker's
    noise, so neither covariance sees an error of the lens model (matches biased towards a pinhole map,
    a distortion curve a little off) that moves f as one scale (section 6.2); their disagreement does."""
    if adjustment_noise is not None and adjustment_noise > 0.0 and math.isfinite(tracker_noise):
        sigma_f *= max(1.0, tracker_noise / (math.sqrt(2.0) * adjustment_noise))
    terms = [t for t in (keyframe_spread, lens_model_gap) if math.isfinite(t)]
    return math.sqrt(sigma_f * sigma_f + sum(t * t for t in terms))


def decide(policy: StatusPolicy, e: StatusEvidence) -> tuple[CalibrationStatus, str]:
    """The status of the calibration and why (see the module docstring)."""
    state, message = e.solver_state, e.solver_message
    ratio = e.misfit / e.tracker_noise if e.tracker_noise > 0.0 else math.nan
    if state != _S.INITIALISING and ratio > policy.max_misfit_ratio:
        return _S.MODEL_MISMATCH, (
            f"the keyframe matches fit the lens model to {e.misfit:.2g} px, {ratio:.2g} x the tracker's "
            f"noise {e.tracker_noise:.2g} px (> {policy.max_misfit_ratio:g}): radial distortion not "
            "modelled, or a rolling shutter"
        )
    if state != _S.CONVERGED:
        return state, message
    if not ratio <= policy.max_misfit_ratio:
        return _S.CALIBRATING, "the lens model's fit to the keyframe matches is not measured yet"
    if not e.adjusted:
        return _S.CALIBRATING, "LM on eq. 22 alone: its sigma is not in image noise (no adjustment yet)"
    if not e.sigma_f <= policy.max_sigma_f:
        return _S.CALIBRATING, f"1-sigma of f {100 * e.sigma_f:.2g}% > {100 * policy.max_sigma_f:.2g}%"
    bound = policy.max_lens_model_change
    if bound is not None and e.lens_model_change is not None:
        change = e.lens_model_change()
        if not change <= bound:
            return _S.CALIBRATING, (
                f"f moves by {100 * change:.2g}% with the radial term toggled "
                f"(> {100 * bound:.2g}%): not pinned by geometry"
            )
    return state, message


def frame_status(
    state: CalibrationStatus, message: str, relative_sigma: float, max_sigma_f: float
) -> tuple[CalibrationStatus, str]:
    """A calibrated frame's status: its calibration's, but CONVERGED promises this frame's f, so a frame
    whose own relative 1-sigma is above max_sigma_f (a homography a rotating, zooming camera cannot
    produce, a long transfer) is CALIBRATING, whatever the calibration's."""
    if state != _S.CONVERGED or relative_sigma <= max_sigma_f:
        return state, message
    return _S.CALIBRATING, (
        f"this frame's 1-sigma of f {100 * relative_sigma:.2g}% > {100 * max_sigma_f:.2g}%: its homography "
        "or its transfer from the keyframe is less certain than the calibration"
    )
