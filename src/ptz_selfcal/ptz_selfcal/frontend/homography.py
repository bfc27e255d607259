"""Homography estimation from point correspondences (paper sections 2.2 and 4.2).

Normalised DLT (Hartley) for a linear estimate, then Gold-Standard refinement: the homography and
the corrected reference points are adjusted to minimise the reprojection error in both images.
For speed on long point lists `refine_homography` minimises the one-image transfer error by default.
Then measures of what a homography does to an image (overlap, local scale, deviation, plausibility),
by which the tracker chooses keyframes and checks links.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from ptz_selfcal.camera.geometry import apply_homography

Array = NDArray[np.float64]


def _normalising_transform(points: Array) -> Array:
    """Similarity moving the centroid to the origin and the mean distance to sqrt(2)."""
    centre = points.mean(axis=0)
    scale = np.sqrt(2.0) / max(np.mean(np.linalg.norm(points - centre, axis=1)), 1e-12)
    return np.array([[scale, 0.0, -scale * centre[0]], [0.0, scale, -scale * centre[1]], [0.0, 0.0, 1.0]])


def homography_dlt(src: ArrayLike, dst: ArrayLike) -> Array:
    """Normalised DLT: H with dst ~ H src from N >= 4 correspondences, scaled so H[2, 2] = 1."""
    src = np.asarray(src, dtype=float).reshape(-1, 2)
    dst = np.asarray(dst, dtype=float).reshape(-1, 2)
    if len(src) < 4 or len(src) != len(dst):
        raise ValueError("need at least 4 correspondences of equal count")
    Ts, Td = _normalising_transform(src), _normalising_transform(dst)
    s = src @ Ts[:2, :2].T + Ts[:2, 2]
    d = dst @ Td[:2, :2].T + Td[:2, 2]
    n = len(s)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:2] = s
    A[0::2, 2] = 1.0
    A[0::2, 6:8] = -d[:, :1] * s
    A[0::2, 8] = -d[:, 0]
    A[1::2, 3:5] = s
    A[1::2, 5] = 1.0
    A[1::2, 6:8] = -d[:, 1:2] * s
    A[1::2, 8] = -d[:, 1]
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    H = np.linalg.inv(Td) @ Vt[-1].reshape(3, 3) @ Ts
    return H / H[2, 2]


def refine_homography(H0: ArrayLike, src: ArrayLike, dst: ArrayLike, max_nfev: int = 50) -> Array:
    """Levenberg-Marquardt on the transfer error |dst - H src|^2 (8 parameters, H[2, 2] = 1).

    Coordinates are normalised internally for conditioning.
    """
    src = np.asarray(src, dtype=float).reshape(-1, 2)
    dst = np.asarray(dst, dtype=float).reshape(-1, 2)
    Ts, Td = _normalising_transform(src), _normalising_transform(dst)
    s = src @ Ts[:2, :2].T + Ts[:2, 2]
    d = dst @ Td[:2, :2].T + Td[:2, 2]
    Hn = Td @ np.asarray(H0, dtype=float) @ np.linalg.inv(Ts)
    Hn /= Hn[2, 2]

    def residuals(h: Array) -> Array:
        return (apply_homography(np.append(h, 1.0).reshape(3, 3), s) - d).ravel()

    def jacobian(h: Array) -> Array:
        H = np.append(h, 1.0).reshape(3, 3)
        w = s @ H[2, :2] + H[2, 2]
        proj = apply_homography(H, s)
        J = np.zeros((2 * len(s), 8))
        J[0::2, 0:2] = s / w[:, None]
        J[0::2, 2] = 1.0 / w
        J[1::2, 3:5] = s / w[:, None]
        J[1::2, 5] = 1.0 / w
        J[0::2, 6:8] = -proj[:, :1] * s / w[:, None]
        J[1::2, 6:8] = -proj[:, 1:2] * s / w[:, None]
        return J

    result = least_squares(residuals, Hn.ravel()[:8], jac=jacobian, method="lm", max_nfev=max_nfev)
    H = np.linalg.inv(Td) @ np.append(result.x, 1.0).reshape(3, 3) @ Ts
    return H / H[2, 2]


def estimate_homography(src: ArrayLike, dst: ArrayLike) -> Array:
    """Normalised DLT followed by non-linear refinement (all points taken as inliers)."""
    return refine_homography(homography_dlt(src, dst), src, dst)


# ----------------------------------------------------------------------------- a homography over an image
def _corners(shape: tuple[int, ...]) -> Array:
    h, w = shape[:2]
    return np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]])


def overlap_fraction(H_frame_to_keyframe: Array, shape: tuple[int, ...]) -> float:
    """Fraction of the frame's area that lies inside the keyframe (both the same image size)."""
    quad = apply_homography(H_frame_to_keyframe, _corners(shape)).astype(np.float32)
    area = abs(cv2.contourArea(quad))
    if not np.all(np.isfinite(quad)) or area <= 0.0 or not cv2.isContourConvex(quad):
        return 0.0
    inter, _ = cv2.intersectConvexConvex(quad, _corners(shape).astype(np.float32))
    return float(inter / area)


def local_scale(H: Array, shape: tuple[int, ...]) -> float:
    """sqrt|det J| of x -> Hx at the image centre: the zoom factor between the two images there."""
    h, w = shape[:2]
    x = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    p = H @ x
    J = (H[:2, :2] * p[2] - np.outer(p[:2], H[2, :2])) / p[2] ** 2
    return float(np.sqrt(abs(np.linalg.det(J))))


def max_deviation(H_a: Array, H_b: Array, shape: tuple[int, ...]) -> float:
    """Largest distance between two homographies' images of a grid over the source image."""
    h, w = shape[:2]
    grid = np.stack(np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 4)), -1).reshape(-1, 2)
    return float(np.max(np.linalg.norm(apply_homography(H_a, grid) - apply_homography(H_b, grid), axis=1)))


def plausible(H: Array, shape: tuple[int, ...]) -> bool:
    """Reject degenerate fits: the frame must map to a convex quadrilateral of sane size."""
    quad = apply_homography(H, _corners(shape)).astype(np.float32)
    if not np.all(np.isfinite(quad)) or not cv2.isContourConvex(quad):
        return False
    ratio = abs(cv2.contourArea(quad)) / float(shape[0] * shape[1])
    return 0.05 < ratio < 20.0
