"""OpenCV's stitching calibration as a peer for benchmarks/peers.py (issue 8). Benchmark code, not product.

The pipeline is the one of OpenCV's `stitching_detailed` sample: a feature finder (SIFT or ORB) ->
BestOf2NearestMatcher over all pairs -> leaveBiggestComponent -> HomographyBasedEstimator ->
BundleAdjusterRay (per-image focal length and rotation) -> BundleAdjusterReproj with a refinement mask
that frees every image's focal length, principal point and aspect ratio.

Two helpers of cv2.detail are unusable from Python, so they are ported / corrected here:
- `focalsFromHomography(H, f0, f1, f0_ok, f1_ok)` writes into C++ reference arguments; the binding
  passes Python floats by value and returns None. Ported: `focals_from_homography` (Shum and Szeliski's
  formula, OpenCV autocalib.cpp, the current version that swaps the denominators with the candidates).
- `calibrateRotatingCamera(Hs)` solves H W H^T = W for the dual image of the absolute conic W = K K^T but
  returns the transpose of W's lower Cholesky factor, L^T with L L^T = W, unscaled. L^T equals K only
  when the principal point is at the origin (and skew is zero): L^T L != W otherwise. Corrected:
  `correct_rotating_camera_k` turns the binding's output into the upper-triangular K with K K^T = W,
  K[2, 2] = 1; `calibrate_rotating_camera` is a numpy port that returns that K directly.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

PORT_NOTE = (
    "OpenCV notes: cv2.detail.focalsFromHomography returns None in Python (C++ reference outputs) -> "
    "ported (Shum-Szeliski formula of autocalib.cpp); cv2.detail.calibrateRotatingCamera returns the "
    "transpose of the Cholesky factor of W = K K^T (wrong unless the principal point is at the origin) "
    "-> corrected to the upper-triangular factor, K[2,2] = 1."
)

# Index map of the six unknowns of the symmetric W (autocalib.cpp idx_map).
_IDX = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _focal_candidate(d1: float, d2: float, v1: float, v2: float) -> float | None:
    """The branch logic of autocalib.cpp for one focal: candidates v (f^2) with denominators d."""
    if v1 < v2:
        v1, v2, d1, d2 = v2, v1, d2, d1
    if v1 > 0 and v2 > 0:
        return float(np.sqrt(v1 if abs(d1) > abs(d2) else v2))
    if v1 > 0:
        return float(np.sqrt(v1))
    return None


def focals_from_homography(H: ArrayLike) -> tuple[float, float, bool, bool]:
    """Port of cv::detail::focalsFromHomography: (f0, f1, f0_ok, f1_ok) for H mapping image 0 to 1.

    Valid for a camera rotating about its centre with square pixels, zero skew and the principal point
    at the origin (OpenCV's matcher centres keypoints on the image before estimating H). f0 is the
    focal length of the source image, f1 that of the destination image.
    """
    h = np.asarray(H, dtype=float).ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        d1 = h[6] * h[7]
        d2 = (h[7] - h[6]) * (h[7] + h[6])
        v1 = -(h[0] * h[1] + h[3] * h[4]) / d1
        v2 = (h[0] ** 2 + h[3] ** 2 - h[1] ** 2 - h[4] ** 2) / d2
        f1 = _focal_candidate(d1, d2, v1, v2)
        d1 = h[0] * h[3] + h[1] * h[4]
        d2 = h[0] ** 2 + h[1] ** 2 - h[3] ** 2 - h[4] ** 2
        v1 = -h[2] * h[5] / d1
        v2 = (h[5] ** 2 - h[2] ** 2) / d2
        f0 = _focal_candidate(d1, d2, v1, v2)
    return (f0 or 0.0, f1 or 0.0, f0 is not None, f1 is not None)


def estimate_focal(Hs: Sequence[ArrayLike]) -> float | None:
    """Port of cv::detail::estimateFocal's core: median of sqrt(f0 f1) over the homographies."""
    focals = []
    for H in Hs:
        f0, f1, ok0, ok1 = focals_from_homography(H)
        if ok0 and ok1:
            focals.append(np.sqrt(f0 * f1))
    return float(np.median(focals)) if focals else None


def upper_cholesky(W: ArrayLike) -> Array:
    """Upper-triangular U with U U^T = W (W symmetric positive definite), U[2, 2] = 1."""
    J = np.eye(3)[::-1]
    L = np.linalg.cholesky(J @ np.asarray(W, dtype=float) @ J)
    U = J @ L @ J
    return U / U[2, 2]


def rotating_camera_conic(Hs: Sequence[ArrayLike]) -> Array:
    """W = K K^T solving H W H^T = W (least squares, SVD) as calibrateRotatingCamera sets it up."""
    rows = []
    for H in Hs:
        H = np.asarray(H, dtype=float)
        H = H / np.cbrt(np.linalg.det(H))
        A = np.zeros((6, 6))
        for k, (a, b) in enumerate(_UPPER):
            np.add.at(A[k], _IDX.ravel(), np.outer(H[a], H[b]).ravel())
            A[k, _IDX[a, b]] -= 1.0
        rows.append(A)
    w = np.linalg.svd(np.vstack(rows))[2][-1]
    return w[_IDX] / w[5]


def calibrate_rotating_camera(Hs: Sequence[ArrayLike]) -> Array:
    """Corrected port of cv::detail::calibrateRotatingCamera: constant K from H_i = K R_i K^-1."""
    return upper_cholesky(rotating_camera_conic(Hs))


def correct_rotating_camera_k(K_binding: ArrayLike) -> Array:
    """The true K from the binding's output L^T (L lower Cholesky factor of W = K K^T)."""
    Lt = np.asarray(K_binding, dtype=float)
    return upper_cholesky(Lt.T @ Lt)


def calibrate_rotating_camera_binding(Hs: Sequence[ArrayLike]) -> Array | None:
    """cv2.detail.calibrateRotatingCamera followed by the correction (None when OpenCV fails)."""
    ok, K = cv2.detail.calibrateRotatingCamera([np.asarray(H, dtype=np.float64) for H in Hs])
    return correct_rotating_camera_k(K) if ok else None


@dataclass
class OpenCVConfig:
    features: str = "sift"  # "sift" or "orb"
    n_features: int = 0  # 0 = detector default (SIFT: all, ORB: 1500)
    match_conf: float | None = None  # None = stitching_detailed default (0.65 ORB, 0.3 otherwise)
    conf_thresh: float = 1.0
    refine_mask: str = "xxxxx"  # stitching_detailed order: fx, skew, ppx, aspect, ppy ('_' = fixed)
    reproj_mask: str = "x_x_x"  # the second stage: focal length and principal point per image
    max_iterations: int = 1000


@dataclass
class OpenCVResult:
    """Per-image K and world-to-camera R (ptz_selfcal convention), for the images kept by OpenCV."""

    indices: NDArray[np.intp]  # positions in the input list that OpenCV calibrated
    K: Array  # (m, 3, 3)
    R: Array  # (m, 3, 3) world-to-camera (OpenCV's CameraParams.R is camera-to-world)
    wall_time: float  # seconds, whole pipeline
    cpu_time: float  # process CPU seconds (all threads), whole pipeline
    ok: bool = True
    message: str = ""
    stage_times: dict[str, float] = field(default_factory=dict)


def _finder(config: OpenCVConfig) -> cv2.Feature2D:
    if config.features == "orb":
        return cv2.ORB_create(config.n_features or 1500)
    if config.features == "sift":
        return cv2.SIFT_create(config.n_features)
    raise ValueError(f"unknown feature finder {config.features!r}")


def refinement_mask(flags: str) -> NDArray[np.uint8]:
    """stitching_detailed's --ba_refine_mask: 'x' refines fx, skew, ppx, aspect, ppy in that order."""
    mask = np.zeros((3, 3), np.uint8)
    for flag, (r, c) in zip(flags, ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2))):
        mask[r, c] = flag == "x"
    return mask


def _camera_matrices(cameras: Sequence[cv2.detail.CameraParams]) -> tuple[Array, Array]:
    K = np.array([np.asarray(c.K(), dtype=float) for c in cameras])
    R = np.array([np.asarray(c.R, dtype=float).T for c in cameras])
    return K, R


def _adjust(
    adjuster: cv2.detail.BundleAdjusterBase,
    features: list,
    matches: list,
    cameras: list,
    mask: str,
    config: OpenCVConfig,
) -> tuple[bool, list]:
    adjuster.setConfThresh(config.conf_thresh)
    adjuster.setRefinementMask(refinement_mask(mask))
    adjuster.setTermCriteria((cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, config.max_iterations, 1e-12))
    for cam in cameras:
        cam.R = np.asarray(cam.R, dtype=np.float32)
    return adjuster.apply(features, matches, cameras)


def run_stitching_calibration(
    images: Sequence[np.ndarray], config: OpenCVConfig | None = None
) -> OpenCVResult:
    """Feature finder -> matcher -> HomographyBasedEstimator -> BundleAdjusterRay -> BundleAdjusterReproj."""
    config = config or OpenCVConfig()
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    c0 = time.process_time()
    finder = _finder(config)
    features = [cv2.detail.computeImageFeatures2(finder, img) for img in images]
    for i, feat in enumerate(features):
        feat.img_idx = i
    t1 = time.perf_counter()
    conf = config.match_conf if config.match_conf is not None else (0.65 if config.features == "orb" else 0.3)
    matcher = cv2.detail.BestOf2NearestMatcher(False, conf)
    matches = matcher.apply2(features)
    matcher.collectGarbage()
    keep = np.asarray(cv2.detail.leaveBiggestComponent(features, matches, config.conf_thresh), dtype=np.intp)
    keep = keep.ravel()
    if len(keep) < len(images):  # re-match the kept images so the indices of `matches` agree
        features = [features[i] for i in keep]
        for i, feat in enumerate(features):
            feat.img_idx = i
        matches = matcher.apply2(features)
    t2 = time.perf_counter()
    ok, cameras = cv2.detail.HomographyBasedEstimator().apply(features, matches, None)
    message = "" if ok else "HomographyBasedEstimator failed"
    t3 = time.perf_counter()
    if ok:
        adjuster = cv2.detail.BundleAdjusterRay()
        ok, cameras = _adjust(adjuster, features, matches, cameras, config.refine_mask, config)
        message = "" if ok else "BundleAdjusterRay failed"
    t4 = time.perf_counter()
    if ok:
        adjuster = cv2.detail.BundleAdjusterReproj()
        ok, cameras = _adjust(adjuster, features, matches, cameras, config.reproj_mask, config)
        message = "" if ok else "BundleAdjusterReproj failed"
    t5 = time.perf_counter()
    cpu = time.process_time() - c0
    times.update(features=t1 - t0, matching=t2 - t1, estimator=t3 - t2, ray=t4 - t3, reproj=t5 - t4)
    if not ok:
        empty = np.empty((0, 3, 3))
        return OpenCVResult(keep[:0], empty, empty, t5 - t0, cpu, False, message, times)
    K, R = _camera_matrices(cameras)
    return OpenCVResult(keep, K, R, t5 - t0, cpu, True, "", times)
