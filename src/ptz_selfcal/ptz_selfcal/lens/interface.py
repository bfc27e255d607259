"""What the keyframe solver and the lens layer hand each other (section 7): the lens model a raw-point
solve starts from, and the distortion that solve estimated. Values and a Protocol, no behaviour."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


class LensModel(Protocol):
    """The lens correction as one keyframe solve sees it (keyframe id None = the reference).

    The solver's adjustment runs on raw (distorted) points: it starts each frame's division coefficient
    from lam_guess, distorts the virtual correspondences of corrected homographies back with distort,
    and takes each keyframe's corrected homography as the correction has it now."""

    def lam_guess(self, keyframe_id: int | None, f: float) -> float: ...

    def distort(self, keyframe_id: int | None, pts: ArrayLike) -> Array: ...

    def keyframe_homography(self, keyframe_id: int) -> Array | None: ...


@dataclass(frozen=True)
class LensEstimate:
    """Distortion from the keyframe adjustment on raw points: the principal point (= distortion centre)
    with its 1-sigma, and each frame's division coefficient lam at its focal length."""

    principal_point: Array
    sigma_pp: Array
    lam: dict[int, float]
    focal: dict[int, float]
