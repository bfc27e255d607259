"""Incremental per-keyframe distortion for the calibrator (paper section 7.2): keyframe matches in,
each keyframe's division coefficient and the lam(f) curve out, in bounded memory and time."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.lens.curve import DistortionVsFocal
from ptz_selfcal.lens.estimation import KeyframeDistortion, KeyframeMatch, estimate_keyframe_distortion

Array = NDArray[np.float64]


class KeyframeDistortionEstimator:
    """Stateful seam for the calibrator: keyframe matches in, per-keyframe lam and lam(f) out.

    - add_match(id_i, id_j, pts_i, pts_j): inlier correspondences between two keyframes (distorted
      full-resolution pixels, e.g. from the tracker's KeyframeMatches); subsampled to
      max_points_per_match, at most max_matches kept (oldest dropped: bounded memory and solve time).
    - set_keyframe(id, f, centre): the calibrator's current focal length and principal point of a
      keyframe (the distortion centre). Estimates are kept as pixel-space kappa = lam / f^2, the
      quantity the images constrain, so refining f later changes lam consistently (rescale_lambda).
    - solve(): joint estimation (estimate_keyframe_distortion), then the DistortionVsFocal curve fitted
      robustly to the per-keyframe estimates (and to a bounded history of keyframes already dropped).
    - lam(id), lam_at_focal(f): for correcting keyframe points and, through the curve, any frame.
    The curve is a function of f, so a keyframe's estimate joins it at the focal length last set for
    it: keep set_keyframe up to date (a dropped keyframe keeps the focal length it had).
    """

    def __init__(
        self,
        width: int,
        height: int,
        max_matches: int = 40,
        max_points_per_match: int = 300,
        history: int = 200,
        seed: int = 0,
    ) -> None:
        self.width, self.height = width, height
        self.max_matches = max_matches
        self.max_points_per_match = max_points_per_match
        self.history = history
        self._rng = np.random.default_rng(seed)
        self._matches: list[KeyframeMatch] = []  # i, j are keyframe ids here
        self._focal: dict[int, float] = {}
        self._centre: dict[int, Array] = {}
        self._kappa: dict[int, float] = {}  # lam / f^2
        self._sigma_kappa: dict[int, float] = {}
        self._retired: list[tuple[float, float, float]] = []  # (f, lam, sigma_lam) of dropped keyframes
        self.curve = DistortionVsFocal(width, height)
        self.last: KeyframeDistortion | None = None

    @property
    def match_count(self) -> int:
        return len(self._matches)

    def live_keyframes(self) -> list[int]:
        """The keyframes a kept match refers to, in id order."""
        return sorted({m.i for m in self._matches} | {m.j for m in self._matches})

    def set_keyframe(self, keyframe_id: int, f: float, centre: ArrayLike) -> None:
        self._focal[int(keyframe_id)] = float(f)
        self._centre[int(keyframe_id)] = np.asarray(centre, dtype=float).reshape(2)

    def add_match(self, id_i: int, id_j: int, pts_i: ArrayLike, pts_j: ArrayLike) -> None:
        pts_i = np.asarray(pts_i, dtype=float).reshape(-1, 2)
        pts_j = np.asarray(pts_j, dtype=float).reshape(-1, 2)
        if len(pts_i) != len(pts_j) or int(id_i) == int(id_j):
            raise ValueError("a match needs two different keyframes and equal point counts")
        if len(pts_i) > self.max_points_per_match:
            keep = np.sort(self._rng.choice(len(pts_i), self.max_points_per_match, replace=False))
            pts_i, pts_j = pts_i[keep], pts_j[keep]
        self._matches.append(KeyframeMatch(int(id_i), int(id_j), pts_i, pts_j))
        dropped: set[int] = set()
        while len(self._matches) > self.max_matches:
            old = self._matches.pop(0)
            dropped |= {old.i, old.j}
        used = {m.i for m in self._matches} | {m.j for m in self._matches}
        for kid in dropped - used:
            self._retire(kid)

    def _retire(self, kid: int) -> None:
        """A keyframe no match refers to any more: keep its estimate for the curve, forget the rest."""
        f = self._focal.pop(kid, None)
        self._centre.pop(kid, None)
        kappa, sigma = self._kappa.pop(kid, None), self._sigma_kappa.pop(kid, np.inf)
        if f is not None and kappa is not None and np.isfinite(sigma):
            self._retired.append((f, kappa * f * f, sigma * f * f))
            self._retired = self._retired[-self.history :]

    def solve(self, min_matches: int = 1) -> KeyframeDistortion | None:
        """Re-estimate every keyframe's lam and the curve; None if too little data (or no focals yet)."""
        usable = [
            m for m in self._matches if m.i in self._focal and m.j in self._focal and len(m.pts_i) >= 12
        ]
        if len(usable) < min_matches:
            return None
        ids = sorted({m.i for m in usable} | {m.j for m in usable})
        index = {kid: n for n, kid in enumerate(ids)}
        focals = np.array([self._focal[k] for k in ids])
        centres = np.array([self._centre[k] for k in ids])
        lam0 = np.array([self._initial_lambda(k) for k in ids])
        matches = [KeyframeMatch(index[m.i], index[m.j], m.pts_i, m.pts_j) for m in usable]
        result = estimate_keyframe_distortion(matches, focals, centres, lam0=lam0)
        for n, kid in enumerate(ids):
            f2 = focals[n] ** 2
            self._kappa[kid] = float(result.lam[n] / f2)
            self._sigma_kappa[kid] = float(result.sigma_lam[n] / f2)
        f_all = np.concatenate([focals, [r[0] for r in self._retired]])
        lam_all = np.concatenate([result.lam, [r[1] for r in self._retired]])
        sigma_all = np.concatenate([result.sigma_lam, [r[2] for r in self._retired]])
        ok = np.isfinite(sigma_all) & (sigma_all > 0)
        if ok.any():
            self.curve.fit(f_all[ok], lam_all[ok], 1.0 / sigma_all[ok] ** 2)
        self.last = result
        return result

    def _initial_lambda(self, kid: int) -> float:
        f = self._focal[kid]
        if kid in self._kappa:
            return self._kappa[kid] * f * f
        return float(self.curve.predict(f)) if self.curve.fitted() else 0.0

    def lam(self, keyframe_id: int) -> float | None:
        """The keyframe's lam at its current focal length (None before its first solve)."""
        kid = int(keyframe_id)
        if kid not in self._kappa or kid not in self._focal:
            return None
        return self._kappa[kid] * self._focal[kid] ** 2

    def lam_at_focal(self, f: float) -> float:
        """lam of any frame from the curve (0.0 before the first solve)."""
        return float(self.curve.predict(f)) if self.curve.fitted() else 0.0
