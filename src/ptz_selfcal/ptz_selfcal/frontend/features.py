"""Image measurements for the homography tracker (paper sections 2.2 and 4.2).

Corner detection spread over a grid, pyramidal KLT with a forward-backward check, ORB descriptors and
robust homography estimation (USAC/MAGSAC, seeded) followed by Levenberg-Marquardt on the inliers.
All coordinates here are working-resolution pixels; the tracker converts to full resolution.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import apply_homography
from ptz_selfcal.frontend.homography import refine_homography

Array = NDArray[np.float64]
Points = NDArray[np.float32]


@dataclass(frozen=True)
class KltParams:
    window: int = 15
    levels: int = 3
    iterations: int = 10
    epsilon: float = 0.03
    fb_threshold: float = 0.5  # forward-backward disagreement allowed, working pixels
    min_eigenvalue: float = 1e-4  # OpenCV's normalised minimum eigenvalue of the KLT window


def detect_corners(
    image: np.ndarray,
    max_corners: int,
    grid: tuple[int, int],
    quality_level: float,
    min_distance: float,
    min_eigenvalue: float,
    mask: np.ndarray | None = None,
) -> Points:
    """Shi-Tomasi corners spread over a cols x rows grid, strongest first within each cell.

    `min_eigenvalue` is an absolute floor (OpenCV's normalised minimum eigenvalue, blockSize 3) so a
    flat or black image yields no corners instead of amplified noise.
    """
    eig = cv2.cornerMinEigenVal(image, 3, 3)
    peak = float(eig.max()) if eig.size else 0.0
    if peak <= min_eigenvalue:
        return np.empty((0, 2), np.float32)
    quality = max(quality_level, min_eigenvalue / peak)
    found = cv2.goodFeaturesToTrack(image, 4 * max_corners, quality, min_distance, mask=mask, blockSize=3)
    if found is None:
        return np.empty((0, 2), np.float32)
    corners = found.reshape(-1, 2).astype(np.float32)
    return _spread_over_grid(corners, image.shape[1], image.shape[0], max_corners, grid)


def _spread_over_grid(corners: Points, width: int, height: int, count: int, grid: tuple[int, int]) -> Points:
    """Keep the strongest corners of every grid cell first (corners arrive sorted by strength)."""
    cols, rows = grid
    cx = np.minimum((corners[:, 0] * cols / width).astype(int), cols - 1)
    cy = np.minimum((corners[:, 1] * rows / height).astype(int), rows - 1)
    cell = cy * cols + cx
    order = np.argsort(cell, kind="stable")
    first = np.searchsorted(cell[order], cell[order], side="left")
    rank = np.empty(len(cell), int)
    rank[order] = np.arange(len(cell)) - first
    # Round-robin over cells: rank 0 of every cell, then rank 1, ...; strength breaks ties.
    keep = np.lexsort((np.arange(len(cell)), rank))[:count]
    return corners[np.sort(keep)]


def track_klt(
    previous: np.ndarray,
    current: np.ndarray,
    points: Points,
    params: KltParams,
    initial: Points | None = None,
    levels: int | None = None,
) -> tuple[Points, NDArray[np.bool_]]:
    """Pyramidal KLT previous -> current with a forward-backward check; returns positions and validity."""
    if len(points) == 0:
        return np.empty((0, 2), np.float32), np.zeros(0, bool)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon)
    win = (params.window, params.window)
    p0 = np.ascontiguousarray(points, np.float32).reshape(-1, 1, 2)
    flags = 0
    guess = None
    if initial is not None:
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        guess = np.ascontiguousarray(initial, np.float32).reshape(-1, 1, 2).copy()
    max_level = params.levels if levels is None else levels
    p1, st, _ = cv2.calcOpticalFlowPyrLK(
        previous, current, p0, guess, winSize=win, maxLevel=max_level, criteria=criteria, flags=flags,
        minEigThreshold=params.min_eigenvalue,
    )  # fmt: skip
    # Backward pass from the forward result, seeded at the start point: a cheap consistency test.
    back, st_back, _ = cv2.calcOpticalFlowPyrLK(
        current, previous, p1, p0.copy(), winSize=win, maxLevel=0, criteria=criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW, minEigThreshold=params.min_eigenvalue,
    )  # fmt: skip
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    h, w = current.shape[:2]
    inside = (p1[:, 0] >= 0) & (p1[:, 1] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] <= h - 1)
    ok = (st.ravel() == 1) & (st_back.ravel() == 1) & (fb < params.fb_threshold) & inside
    return p1, ok


def gain_matched(previous: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Previous frame rescaled to the current mean brightness (KLT assumes constant brightness). One
    gain: the two are not aligned, so a local ratio would be texture, not light."""
    mean_prev = float(cv2.mean(previous)[0])
    mean_cur = float(cv2.mean(image)[0])
    if mean_prev < 1.0 or abs(mean_cur / mean_prev - 1.0) < _GAIN_TOLERANCE:
        return previous
    return cv2.convertScaleAbs(previous, alpha=mean_cur / mean_prev)


# Working pixels per cell of the brightness-ratio fit (the cells' means are taken on every 4th pixel of
# every 4th row: plenty for a smooth field) and the cells' usable grey range (the log ratio of dark or
# saturated cells is noise or clipped).
GAIN_CELL = 16
_GAIN_STEP = 4
_GAIN_RANGE = (6.0, 250.0)
# Brightness ratios within this of 1 everywhere are left alone (not worth a resample).
_GAIN_TOLERANCE = 0.02


def gain_matched_warp(warped: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The warped keyframe with the current frame's brightness, where it has data (not the border).

    The ratio of the two is smooth but not constant: an exposure step scales all of it, while a
    vignetting fixed in the image moves with the content, so its ratio varies across the frame. It is
    fitted as exp of a quadratic in the image coordinates to the log ratio of cell means, robustly
    (moving objects and occlusions are outlying cells), and the warped image is multiplied by it."""
    field = brightness_ratio(warped, image)
    if field is None:
        return warped
    if isinstance(field, float):
        return cv2.convertScaleAbs(warped, alpha=field)
    return cv2.multiply(warped, field, dtype=cv2.CV_8U)  # rounded and saturated


def _normalised(x: np.ndarray, size: int) -> np.ndarray:
    """Pixel coordinates to [-1, 1] over the image."""
    half = 0.5 * (size - 1)
    return ((x - half) / half).astype(np.float32)


def _quadratic_terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    gx, gy = np.meshgrid(x, y)
    return np.stack([np.ones_like(gx), gx, gy, gx * gx, gx * gy, gy * gy], axis=-1)


@lru_cache(maxsize=8)
def _gain_grids(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """The quadratic's terms at the cell centres (gh, gw, 6) and on the quarter-resolution grid that
    cv2.resize maps onto the pixels (qh, qw, 6), for a w x h image (read-only)."""
    k = GAIN_CELL // _GAIN_STEP
    centre = GAIN_CELL * np.arange(max(w, h) // GAIN_CELL) + _GAIN_STEP * (k - 1) / 2.0  # sampled pixels
    cells = _quadratic_terms(
        _normalised(centre[: w // GAIN_CELL], w), _normalised(centre[: h // GAIN_CELL], h)
    )
    qw, qh = -(-w // _GAIN_STEP), -(-h // _GAIN_STEP)
    qx = _normalised((np.arange(qw) + 0.5) * (w / qw) - 0.5, w)
    qy = _normalised((np.arange(qh) + 0.5) * (h / qh) - 0.5, h)
    quarter = _quadratic_terms(qx, qy)
    cells.flags.writeable = quarter.flags.writeable = False
    return cells, quarter


def brightness_ratio(warped: np.ndarray, image: np.ndarray) -> np.ndarray | float | None:
    """image / warped as a smooth (h, w) float32 field, a constant when too few cells support a fit,
    None when the ratio is within _GAIN_TOLERANCE of 1 (or nothing to measure it on). Within the
    outer half cell the field is held at its value there (no extrapolation)."""
    h, w = image.shape[:2]
    gw, gh = w // GAIN_CELL, h // GAIN_CELL
    if gw < 3 or gh < 3:
        return _mean_ratio(warped, image)

    def cell_means(img: np.ndarray) -> np.ndarray:
        sub = img[: gh * GAIN_CELL : _GAIN_STEP, : gw * GAIN_CELL : _GAIN_STEP].astype(np.float32)
        return cv2.resize(sub, (gw, gh), interpolation=cv2.INTER_AREA)  # exact: an integer factor

    a, b = cell_means(warped), cell_means(image)
    lo, hi = _GAIN_RANGE
    ok = cell_means((warped == 0).view(np.uint8)) == 0  # the warped keyframe covers the cell
    ok &= (a >= lo) & (a <= hi) & (b >= lo) & (b <= hi)
    if ok.sum() < 3:
        return _mean_ratio(warped, image)
    log_ratio = np.log(b[ok] / a[ok])
    cells, quarter = _gain_grids(w, h)
    A = cells[ok]
    if len(A) < 4 * A.shape[1]:  # too few cells for a field: one gain
        gain = float(np.exp(np.median(log_ratio)))
        return None if abs(gain - 1.0) < _GAIN_TOLERANCE else gain
    keep = np.ones(len(A), bool)
    for _ in range(3):  # least squares, then again without the outlying cells
        Ak = A[keep]
        coef = np.linalg.solve(Ak.T @ Ak, Ak.T @ log_ratio[keep])
        residual = np.abs(A @ coef - log_ratio)
        spread = max(1.4826 * float(np.median(residual[keep])), 0.01)
        updated = residual < 3.0 * spread
        if updated.sum() < 2 * A.shape[1] or np.array_equal(updated, keep):
            break
        keep = updated
    log_field = quarter @ coef.astype(np.float32)
    if float(np.abs(log_field).max()) < np.log1p(_GAIN_TOLERANCE):
        return None
    return cv2.resize(np.exp(log_field), (w, h), interpolation=cv2.INTER_LINEAR)


def _mean_ratio(warped: np.ndarray, image: np.ndarray) -> float | None:
    """The ratio of mean brightness where the warped keyframe has data (a 1/16 sample)."""
    sub_warp, sub_image = warped[::4, ::4], image[::4, ::4]
    valid = sub_warp > 0
    mean_warp = float(sub_warp[valid].mean()) if valid.any() else 0.0
    mean_cur = float(sub_image[valid].mean()) if valid.any() else 0.0
    if mean_warp < 1.0 or abs(mean_cur / mean_warp - 1.0) < _GAIN_TOLERANCE:
        return None
    return mean_cur / mean_warp


@dataclass(frozen=True)
class RobustFit:
    H: Array  # maps src to dst
    inliers: NDArray[np.bool_]
    rms: float  # rms transfer error of the inliers, same units as the points


def usac_params(threshold: float, seed: int, max_iterations: int, confidence: float) -> cv2.UsacParams:
    """Settings of OpenCV's USAC_MAGSAC preset with an explicit random state (deterministic)."""
    params = cv2.UsacParams()
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_MAGSAC
    params.loMethod = cv2.LOCAL_OPTIM_SIGMA
    params.loIterations = 10
    params.loSampleSize = 75
    params.final_polisher = cv2.MAGSAC
    params.final_polisher_iterations = 10
    params.threshold = threshold
    params.confidence = confidence
    params.maxIterations = max_iterations
    params.randomGeneratorState = seed
    params.isParallel = False
    return params


def robust_homography(
    src: np.ndarray,
    dst: np.ndarray,
    params: cv2.UsacParams,
    min_inliers: int,
    refine_iterations: int = 10,
    sigma_factor: float = 4.0,
) -> RobustFit | None:
    """MAGSAC homography src -> dst, then LM on the transfer error of the inliers (section 4.2),
    re-selecting the inliers at sigma_factor robust standard deviations of their residuals."""
    if len(src) < max(min_inliers, 4):
        return None
    src64 = np.asarray(src, np.float64).reshape(-1, 2)
    dst64 = np.asarray(dst, np.float64).reshape(-1, 2)
    try:
        H, mask = cv2.findHomography(src64, dst64, params)
    except cv2.error:
        return None
    if H is None or H.size == 0 or mask is None:
        return None
    inliers = mask.ravel().astype(bool)
    if inliers.sum() < min_inliers:
        return None
    return refit_homography(H, src64, dst64, inliers, params.threshold, min_inliers, refine_iterations,
                            sigma_factor)  # fmt: skip


def refit_homography(
    H: Array,
    src: np.ndarray,
    dst: np.ndarray,
    inliers: NDArray[np.bool_],
    threshold: float,
    min_inliers: int,
    refine_iterations: int = 10,
    sigma_factor: float = 4.0,
) -> RobustFit | None:
    """robust_homography after its sample consensus: from H and its inliers, LM on the transfer error of
    the inliers re-selected at sigma_factor robust standard deviations (capped by `threshold`); also the
    refit of points corrected a little (a rolling shutter's global-shutter positions)."""
    src64 = np.asarray(src, np.float64).reshape(-1, 2)
    dst64 = np.asarray(dst, np.float64).reshape(-1, 2)
    inliers = _adaptive_inliers(H, src64, dst64, inliers, threshold, sigma_factor)
    for _ in range(2):  # LM on the inliers; once more if that changed the inlier set
        if inliers.sum() < min_inliers:
            return None
        H = refine_homography(H, src64[inliers], dst64[inliers], max_nfev=refine_iterations)
        updated = _adaptive_inliers(H, src64, dst64, inliers, threshold, sigma_factor)
        if np.array_equal(updated, inliers) or updated.sum() < min_inliers:
            break
        inliers = updated
    residual = np.linalg.norm(apply_homography(H, src64) - dst64, axis=1)
    rms = float(np.sqrt(np.mean(residual[inliers] ** 2)))
    return RobustFit(H=H, inliers=inliers, rms=rms)


def _adaptive_inliers(
    H: Array, src: Array, dst: Array, inliers: NDArray[np.bool_], threshold: float, sigma_factor: float
) -> NDArray[np.bool_]:
    """Inliers at sigma_factor robust sigmas (MAD of the current inliers' residuals), capped by the
    MAGSAC threshold: tracks biased by a partly occluded window (within the threshold but far out of
    the noise) stop pulling the fit."""
    residual = np.linalg.norm(apply_homography(H, src) - dst, axis=1)
    sigma = 1.4826 * float(np.median(residual[inliers]))
    return residual < min(threshold, max(sigma_factor * sigma, 0.1 * threshold))


@dataclass(frozen=True)
class Descriptors:
    points: Points  # (N, 2) keypoint positions, working pixels
    descriptors: np.ndarray | None  # ORB (N, 32) uint8 or SIFT (N, 128) float32
    norm: int = cv2.NORM_HAMMING


def descriptor_extractor(kind: str, count: int) -> cv2.Feature2D:
    """ORB (fast, binary) or SIFT (slower, matches across larger viewpoint and scale changes)."""
    if kind == "orb":
        return cv2.ORB_create(nfeatures=count, scaleFactor=1.2, nlevels=8, fastThreshold=10)
    if kind == "sift":
        return cv2.SIFT_create(nfeatures=count)
    raise ValueError(f"unknown descriptor {kind!r} (orb or sift)")


def compute_descriptors(extractor: cv2.Feature2D, image: np.ndarray) -> Descriptors:
    keypoints, descriptors = extractor.detectAndCompute(image, None)
    points = np.array([kp.pt for kp in keypoints], np.float32).reshape(-1, 2)
    norm = cv2.NORM_L2 if descriptors is not None and descriptors.dtype == np.float32 else cv2.NORM_HAMMING
    return Descriptors(points=points, descriptors=descriptors, norm=norm)


def match_descriptors(a: Descriptors, b: Descriptors, ratio: float) -> tuple[Points, Points]:
    """Mutual nearest neighbours in descriptor distance passing Lowe's ratio test: (points in a, in b)."""
    empty = (np.empty((0, 2), np.float32), np.empty((0, 2), np.float32))
    if a.descriptors is None or b.descriptors is None or len(a.points) < 2 or len(b.points) < 2:
        return empty
    matcher = cv2.BFMatcher(a.norm)
    forward = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    backward = matcher.match(b.descriptors, a.descriptors)
    best_back = np.full(len(b.points), -1)
    for m in backward:
        best_back[m.queryIdx] = m.trainIdx
    ia, ib = [], []
    for pair in forward:
        if len(pair) < 2:
            continue
        m, n = pair
        if m.distance < ratio * n.distance and best_back[m.trainIdx] == m.queryIdx:
            ia.append(m.queryIdx)
            ib.append(m.trainIdx)
    if not ia:
        return empty
    return a.points[ia], b.points[ib]
