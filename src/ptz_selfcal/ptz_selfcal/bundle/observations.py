"""Image measurements of the bundle adjustment (section 5): observations, their preparation for a
solve (sorted by frame, rays renumbered) and the starting rays."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.intrinsics import SelfCalibrationError

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass
class BundleObservations:
    """Image measurements for eq. 26: observation k is ray ray_idx[k] seen in frame frame_idx[k] at xy[k]."""

    frame_idx: IntArray
    ray_idx: IntArray
    xy: Array

    def __post_init__(self) -> None:
        self.frame_idx = np.asarray(self.frame_idx, dtype=np.intp).ravel()
        self.ray_idx = np.asarray(self.ray_idx, dtype=np.intp).ravel()
        self.xy = np.asarray(self.xy, dtype=float).reshape(-1, 2)
        if not len(self.frame_idx) == len(self.ray_idx) == len(self.xy):
            raise ValueError("frame_idx, ray_idx and xy must have the same length")


ObservationsLike = BundleObservations | tuple[ArrayLike, ArrayLike, ArrayLike]


def pair_observations(matches: Sequence[tuple[int, int, ArrayLike, ArrayLike]]) -> BundleObservations:
    """Observations from keyframe-to-keyframe matches (frame_a, frame_b, xy_a (k, 2), xy_b (k, 2)).

    Every match becomes its own ray seen in exactly two frames.
    """
    frames, rays, xys = [], [], []
    next_ray = 0
    for frame_a, frame_b, xy_a, xy_b in matches:
        a = np.asarray(xy_a, dtype=float).reshape(-1, 2)
        b = np.asarray(xy_b, dtype=float).reshape(-1, 2)
        if len(a) != len(b):
            raise ValueError("matched point lists differ in length")
        ids = np.arange(next_ray, next_ray + len(a))
        next_ray += len(a)
        frames += [np.full(len(a), frame_a), np.full(len(b), frame_b)]
        rays += [ids, ids]
        xys += [a, b]
    if not frames:
        return BundleObservations(np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros((0, 2)))
    return BundleObservations(np.concatenate(frames), np.concatenate(rays), np.concatenate(xys))


@dataclass
class PreparedObservations:
    """Observations sorted by frame, rays renumbered 0..m-1; frame_starts[i] = first row of frame i."""

    frame_idx: IntArray
    ray_idx: IntArray
    xy: Array
    frame_starts: IntArray
    xy_t: Array  # (2, N) the same pixels, component-major

    @property
    def bounds(self) -> IntArray:
        """(n + 1,) row ranges of the frames: frame i is rows bounds[i]:bounds[i + 1]."""
        return np.append(self.frame_starts, len(self.frame_idx))


def prepare_observations(
    observations: ObservationsLike, n_frames: int
) -> tuple[PreparedObservations, IntArray]:
    """Sort by frame, keep rays seen at least twice, renumber rays densely. Returns the original ids."""
    obs = observations if isinstance(observations, BundleObservations) else BundleObservations(*observations)
    if len(obs.frame_idx) and (obs.frame_idx.min() < 0 or obs.frame_idx.max() >= n_frames):
        raise ValueError("frame_idx out of range")
    _, compact, counts = np.unique(obs.ray_idx, return_inverse=True, return_counts=True)
    keep = counts[compact] >= 2
    kept_ids, compact = np.unique(obs.ray_idx[keep], return_inverse=True)
    order = np.argsort(obs.frame_idx[keep], kind="stable")
    frame_idx = obs.frame_idx[keep][order]
    seen = np.bincount(frame_idx, minlength=n_frames)
    if (seen == 0).any():
        raise SelfCalibrationError(
            f"frames {np.flatnonzero(seen == 0).tolist()} share no ray with another frame"
        )
    starts = np.concatenate([[0], np.cumsum(seen)[:-1]]).astype(np.intp)
    xy = obs.xy[keep][order]
    prepared = PreparedObservations(frame_idx, compact[order], xy, starts, np.ascontiguousarray(xy.T))
    return prepared, kept_ids


def initial_rays(obs: BundleObservations | PreparedObservations, K: Array, R: Array, n_rays: int) -> Array:
    """Unit rays by back-projection X = R_i^T K_i^-1 x through each frame, averaged (section 5.1)."""
    # R_i^T K_i^-1 once per frame, then one 3x3 product per observation: far cheaper than a
    # three-operand einsum over the observations
    M = np.swapaxes(R, 1, 2) @ np.linalg.inv(K)
    xh = np.column_stack([obs.xy, np.ones(len(obs.xy))])
    d = np.einsum("nij,nj->ni", M[obs.frame_idx], xh)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    X = np.stack([np.bincount(obs.ray_idx, weights=d[:, c], minlength=n_rays) for c in range(3)], axis=1)
    norm = np.linalg.norm(X, axis=1, keepdims=True)
    return X / np.where(norm > 0, norm, 1.0)


def undistorted_observations(obs: PreparedObservations, K: Array, lam: Array) -> PreparedObservations:
    """The observations undistorted with the frames' coefficients (division model, closed form)."""
    xh = np.column_stack([obs.xy, np.ones(len(obs.xy))])
    n = np.einsum("nij,nj->ni", np.linalg.inv(K)[obs.frame_idx], xh)[:, :2]
    n /= (1.0 + lam[obs.frame_idx] * np.sum(n * n, axis=1))[:, None]
    xy = np.einsum("nij,nj->ni", K[obs.frame_idx], np.column_stack([n, np.ones(len(n))]))[:, :2]
    return replace(obs, xy=xy, xy_t=np.ascontiguousarray(xy.T))
