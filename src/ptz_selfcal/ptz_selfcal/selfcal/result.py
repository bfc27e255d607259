"""The result every self-calibration method returns: linear (3.3.2), LM (3.3.1), bundle adjustment (5)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import quaternion_from_matrix
from ptz_selfcal.camera.intrinsics import IntrinsicsModel
from ptz_selfcal.selfcal.degeneracy import MotionReport

Array = NDArray[np.float64]


@dataclass(frozen=True)
class BundleDetails:
    """What a bundle adjustment (section 5) knows besides K and R."""

    rays: Array  # (n_rays, 3) unit rays in the reference frame (NaN: not observed)
    covariance: Array  # of the adjustment's unknowns (NaN without the uncertainty)
    residual_variance: float  # of the image residuals, px^2: the measured image noise
    initial_cost: float
    n_observations: int
    n_rays: int
    model: IntrinsicsModel
    lam: Array | None = None  # each frame's division coefficient when distortion is estimated (7)
    sigma_lam: Array | None = None
    distortion_curve: tuple[Array, float, float] | None = None  # lam(f) curve: coefficients, f_ref, D


@dataclass
class SelfCalibrationResult:
    """Per-frame intrinsics and rotations from a self-calibration solve.

    R[j] is the rotation of frame j relative to the reference frame 0 (R[0] = I), so that
    x_j ~ K_j R_j K_0^-1 x_0 (section 3.3.1). Uncertainties are 1-sigma in pixels.
    """

    K: Array
    R: Array
    sigma_f: Array
    sigma_pp: Array
    residual: float
    method: str
    iterations: int = 0
    ok: bool = True
    message: str = ""
    motion: MotionReport | None = None
    cost: float = float("nan")
    # whether the solver itself converged, apart from the motion's verdict (None: as `ok`)
    solver_ok: bool | None = None
    bundle: BundleDetails | None = None  # a bundle adjustment's rays, noise and distortion

    @property
    def solver_converged(self) -> bool:
        return self.ok if self.solver_ok is None else self.solver_ok

    @property
    def n_frames(self) -> int:
        return len(self.K)

    @property
    def focal(self) -> Array:
        """fy of every frame."""
        return self.K[:, 1, 1].copy()

    @property
    def principal_point(self) -> Array:
        """(n, 2) principal point of every frame."""
        return self.K[:, :2, 2].copy()

    def quaternions(self) -> Array:
        """(n, 4) orientation of each frame relative to frame 0 as (x, y, z, w)."""
        return np.array([quaternion_from_matrix(R) for R in self.R])
