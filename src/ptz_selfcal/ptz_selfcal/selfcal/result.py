"""The result every self-calibration method returns: linear (3.3.2), LM (3.3.1), bundle adjustment (5)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import quaternion_from_matrix
from ptz_selfcal.selfcal.degeneracy import MotionReport

Array = NDArray[np.float64]


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
    info: dict = field(default_factory=dict)

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
