"""Homographies as a keyframe tracker reports them, for a camera of known K_j and R_j (no images).

Each frame is tracked against its keyframe: the short keyframe -> frame homography is estimated from
noisy point correspondences and chained onto the keyframe's homography from the reference, so an
ordinary frame's homography is as noisy as its keyframe's. A new keyframe starts when the frame
overlaps its keyframe less than `min_overlap` or zoomed by more than `max_scale` (frontend/tracker's
rule); its inlier points with the previous keyframe are the keyframe matches. Exact geometry with
controlled noise: what tests and benchmarks feed online/session frame by frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import apply_homography, normalise_homography, reference_homographies
from ptz_selfcal.frontend.homography import estimate_homography, local_scale, overlap_fraction
from ptz_selfcal.sim.render import CameraProfile

Array = NDArray[np.float64]


@dataclass(frozen=True)
class TrackedFrame:
    """One frame's HomographyStamped (and, for a new keyframe, its matches with the previous one)."""

    index: int
    H: Array  # reference -> frame
    keyframe_id: int  # the keyframe it was tracked against (itself for a new keyframe)
    new_keyframe: bool
    matches: tuple[int, int, Array, Array] | None = None  # (keyframe, other, its points, other's points)


def tracked_frames(
    K: Array,
    R: Array,
    image_size: tuple[int, int],
    *,
    sigma_px: float = 0.3,
    points: int = 150,
    min_overlap: float = 0.7,
    max_scale: float = 1.2,
    seed: int = 0,
) -> list[TrackedFrame]:
    """K (n, 3, 3) and world -> camera R (n, 3, 3) of every frame; the tracker's view of them."""
    width, height = image_size
    shape = (height, width)
    rng = np.random.default_rng(seed)
    H_true = reference_homographies(K, R)
    frames = [TrackedFrame(0, np.eye(3), 0, True)]
    key, H_key = 0, np.eye(3)
    for j in range(1, len(K)):
        H_kj = H_true[j] @ np.linalg.inv(H_true[key])  # keyframe -> frame
        src, dst = _correspondences(H_kj, width, height, points, sigma_px, rng)
        H_local = estimate_homography(src, dst)
        H = normalise_homography(H_local @ H_key)
        if overlap_fraction(np.linalg.inv(H_kj), shape) >= min_overlap and (
            1.0 / max_scale <= local_scale(H_kj, shape) <= max_scale
        ):
            frames.append(TrackedFrame(j, H, key, False))
            continue
        # a new keyframe: chained through the previous one, matched to it
        frames.append(TrackedFrame(j, H, j, True, (j, key, dst, src)))
        key, H_key = j, H
    return frames


def _correspondences(
    H: Array, width: int, height: int, count: int, sigma: float, rng: np.random.Generator
) -> tuple[Array, Array]:
    """`count` points of the source image visible in the destination through H, both noisy."""
    src = rng.uniform([0.0, 0.0], [width - 1.0, height - 1.0], (4 * count, 2))
    dst = apply_homography(H, src)
    inside = (dst[:, 0] >= 0) & (dst[:, 0] <= width - 1) & (dst[:, 1] >= 0) & (dst[:, 1] <= height - 1)
    src, dst = src[inside][:count], dst[inside][:count]
    if len(src) < 8:
        raise ValueError(f"only {len(src)} points shared with the keyframe")
    return src + rng.normal(0.0, sigma, src.shape), dst + rng.normal(0.0, sigma, dst.shape)


def profile_truth(profile: CameraProfile, frames: int, fps: float) -> tuple[Array, Array]:
    """True K (n, 3, 3) and world -> camera R (n, 3, 3) of a camera profile sampled at fps."""
    state = profile.state(np.arange(frames) / fps)
    return np.array([state.K(i) for i in range(frames)]), np.array([state.R(i) for i in range(frames)])
