"""Lens-model selection between two keyframe bundle adjustments on the same observations (sections 5
and 7): radial distortion or none, a principal point constant or moving with zoom, chosen by the data
rather than by a per-camera parameter (a default must suit lenses it has never seen).

The Bayesian information criterion with the noise variance unknown: n ln(RSS / n) + k ln n for n
image residuals and k unknowns (with eq. 27's prior: the image term of the MAP solution). Both
adjustments see the same points and rays, so only the unknowns that differ count. The richer model is
adopted only when it lowers the criterion by more than a margin, so that an exact lens is not given
terms it does not have (each costs accuracy) and a choice does not flip on noise from one solve to the
next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptz_selfcal.selfcal.result import SelfCalibrationResult

# ln(Bayes factor) > 5 (BIC difference > 10) is "very strong" evidence on Kass and Raftery's scale
SELECTION_MARGIN = 10.0


@dataclass(frozen=True)
class ModelChoice:
    """Which of two adjustments wins, and by how much (BIC of the richer minus the simpler: negative
    when the richer fits better than its extra unknowns explain)."""

    richer: bool
    delta_bic: float


def compare_models(
    simple: SelfCalibrationResult,
    rich: SelfCalibrationResult,
    extra_unknowns: int,
    margin: float = SELECTION_MARGIN,
) -> ModelChoice:
    """BIC of `rich` (with extra_unknowns more) against `simple`, both bundle_adjust results on the same
    observations, on their image residuals. A result that did not solve (non-finite cost) loses; so
    does a richer one that does not lower the criterion by more than margin."""
    n = 0 if simple.bundle is None else 2 * simple.bundle.n_observations
    c_simple, c_rich = _image_cost(simple), _image_cost(rich)
    if n <= 0 or not _solved(rich, c_rich):
        return ModelChoice(False, math.inf)
    if not _solved(simple, c_simple):
        return ModelChoice(True, -math.inf)
    delta = n * math.log(c_rich / c_simple) + extra_unknowns * math.log(n)
    return ModelChoice(delta < -margin, delta)


def _image_cost(result: SelfCalibrationResult) -> float:
    """The sum of squared image residuals (px^2), without the principal-point prior: the likelihood
    the criterion weighs (the prior's weight depends on a noise estimate, not on the data)."""
    n_obs = 0 if result.bundle is None else result.bundle.n_observations
    return float(result.residual) ** 2 * n_obs if math.isfinite(result.cost) else math.nan


def _solved(result: SelfCalibrationResult, cost: float) -> bool:
    # a positive finite cost and finite intrinsics (the motion's verdict is not the lens model's)
    return math.isfinite(cost) and cost > 0.0 and bool(np.all(np.isfinite(result.K)))
