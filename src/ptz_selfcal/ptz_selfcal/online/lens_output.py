"""plumb_bob D of a calibrated frame: [k1, k2, 0, 0, 0], zeros where distortion is not estimated."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import division_to_plumb_bob

Array = NDArray[np.float64]

DistortionFn = Callable[[Array], ArrayLike]  # K -> plumb_bob D (a zoom lens's correction)


class PlumbBob:
    """D of a frame's K: from the lens correction of a zooming lens when one is given, else from a fixed
    lens's one division coefficient (section 7), else zeros. One instance per thread (it caches)."""

    def __init__(self, distortion: DistortionFn | None = None) -> None:
        self.distortion = distortion
        self._cache: tuple[tuple, Array] = ((), np.zeros(5))

    def __call__(self, K: Array, shared_lam: float | None, image_size: tuple[int, int] | None) -> Array:
        if self.distortion is not None:
            model: DistortionFn = self.distortion
        elif shared_lam is not None and image_size is not None:
            model = lambda K: self._shared(K, shared_lam, image_size)  # noqa: E731
        else:
            return np.zeros(5)
        try:
            D = np.asarray(model(K), dtype=float).ravel()
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            return np.zeros(5)
        out = np.zeros(5)
        out[: min(5, D.size)] = D[:5]
        return out if np.all(np.isfinite(out)) else np.zeros(5)

    def _shared(self, K: Array, lam: float, image_size: tuple[int, int]) -> Array:
        """The division coefficient as plumb_bob at K: one least-squares fit per (lam, f, centre)."""
        key = (lam, *np.round(np.asarray(K, dtype=float)[[0, 0, 1], [0, 2, 2]], 3))
        if self._cache[0] != key:
            k1, k2 = division_to_plumb_bob(lam, K, *image_size)
            self._cache = (key, np.array([k1, k2, 0.0, 0.0, 0.0]))
        return self._cache[1]
