"""Per-frame intrinsics by transfer of the reference DIAC (paper eq. 20: omega*_j = H_j omega*_0 H_j^T).

Once the reference K_0 is calibrated, any frame's K_j costs O(1) from its homography: the transferred
DIAC is fitted to the intrinsics model (least-squares f with a constant principal point, a Cholesky
factor with a per-frame one). A frame whose transferred f contradicts an independent prediction
(`focal_disagrees`) has a wrong homography; one that a rotating, zooming camera cannot produce
(`transfer_misfit`) carries its own error into the transferred f.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.geometry import (
    apply_homography,
    nearest_rotation,
    pixel_grid,
    rotation_from_homography,
)
from ptz_selfcal.camera.intrinsics import IntrinsicsModel, ParamMode, SelfCalibrationError, image_centre

Array = NDArray[np.float64]


def intrinsics_from_transferred_diac(
    H: ArrayLike, K_ref: ArrayLike, model: IntrinsicsModel, image_size: tuple[int, int]
) -> Array:
    """K_j from the reference DIAC transferred by H_j: omega*_j = H omega*_0 H^T (eq. 20).

    H is (3, 3) or (n, 3, 3); returns K of the same leading shape. With a constant or known
    principal point (aspect and skew taken from K_ref) only f is free: lambda omega*_j = f^2 P + Q
    is linear in (lambda, f^2), solved by least squares in coordinates centred and scaled by
    K_ref's focal length. Otherwise (per-frame principal point) K_j is the Cholesky factor. A fixed
    lens (focal length and principal point not varying) has K_j = K_ref.
    """
    H = np.asarray(H, dtype=float)
    single = H.ndim == 2
    H = H.reshape(-1, 3, 3)
    K_ref = np.asarray(K_ref, dtype=float)
    if model.focal is not ParamMode.VARYING and model.principal_point is not ParamMode.VARYING:
        # a fixed lens: every frame has the reference's K (H only carries the rotation)
        K = np.repeat((K_ref / K_ref[2, 2])[None], len(H), axis=0)
        return K[0] if single else K
    s = K_ref[1, 1]
    c = image_centre(image_size)
    N = np.array([[1.0 / s, 0.0, -c[0] / s], [0.0, 1.0 / s, -c[1] / s], [0.0, 0.0, 1.0]])
    Hn = N @ H @ np.linalg.inv(N)
    Kn_ref = N @ K_ref
    diac = Hn @ (Kn_ref @ Kn_ref.T) @ np.swapaxes(Hn, 1, 2)
    if model.principal_point is ParamMode.VARYING or model.focal is not ParamMode.VARYING:
        K_n = _upper_cholesky(diac)
    else:
        K_n = _fit_focal(diac, Kn_ref)
    K = np.linalg.inv(N) @ K_n
    K = K / K[:, 2:3, 2:3]
    return K[0] if single else K


def transfer_misfit(
    H: ArrayLike, K_from: ArrayLike, image_size: tuple[int, int], iterations: int = 3
) -> float:
    """The relative 1-sigma of f that a transfer (eq. 20) through H inherits from H's own error, read off
    the part of H that no rotating, zooming camera produces.

    Eq. 4: H = K_j R K_i^-1, K_j with K_i's principal point, aspect and skew and its own f. The nearest
    such map over a grid of the image (Gauss-Newton on R and log f from eq. 20's f and the rotation nearest
    K_j^-1 H K_i) leaves an rms distance, taken per unit of the grid's rms radius about the principal
    point (the distance a zoom by 1 moves it). A tracked homography that fits its inliers closely can
    still be far off over the frame (tracks on weak corners held at their prediction, inliers on a small
    part of the image), and the frame's f with it. An error with no preferred direction would be as large
    in the zoom as in each of the 4 degrees of freedom outside the model (8 of H, 3 of R, 1 of f), half
    their rms; a fit to a few tracks in one part of the image pins the map's shape better than its scale,
    its zoom error is 1.5-2 times that (exact synthetic fits), so the whole rms is taken. NaN when H has
    no such map.
    """
    H = np.asarray(H, dtype=float)
    K_from = np.asarray(K_from, dtype=float)
    try:
        K = intrinsics_from_transferred_diac(H, K_from, IntrinsicsModel(), image_size)
        R = rotation_from_homography(H, K_from, K)
        K_from_inv = np.linalg.inv(K_from)
    except (SelfCalibrationError, ValueError, ArithmeticError, np.linalg.LinAlgError):
        return math.nan
    grid = pixel_grid(*image_size, count=8)
    x = np.column_stack([grid, np.ones(len(grid))])
    target = apply_homography(H, grid)
    zoom = np.diag([1.0, 1.0, 0.0])  # d K / d log f = K diag(1, 1, 0)
    generators = [np.cross(np.eye(3), axis) for axis in np.eye(3)]  # [e_i]x: d R = [e_i]x R
    residual = np.full(2 * len(grid), np.inf)
    for step in range(iterations + 1):
        y = x @ (K @ R @ K_from_inv).T
        if not np.all(y[:, 2] > 0.0):
            return math.nan  # part of the image behind the camera: no such map
        p = y[:, :2] / y[:, 2:3]
        residual = (p - target).ravel()
        if step == iterations:
            break
        dM = [K @ G @ R @ K_from_inv for G in generators] + [K @ zoom @ R @ K_from_inv]
        dy = [x @ D.T for D in dM]
        J = np.column_stack([((d[:, :2] - p * d[:, 2:3]) / y[:, 2:3]).ravel() for d in dy])
        delta = np.linalg.lstsq(J, -residual, rcond=None)[0]
        R = nearest_rotation((np.eye(3) + np.cross(np.eye(3), delta[:3])) @ R)
        K = K.copy()
        K[:2, :2] *= math.exp(delta[3])
    radius = np.sqrt(np.mean(np.sum((grid - K_from[:2, 2] / K_from[2, 2]) ** 2, axis=1)))
    misfit = math.sqrt(2.0 * float(np.mean(residual * residual))) / max(float(radius), 1e-9)
    return misfit if math.isfinite(misfit) else math.nan


def focal_disagrees(
    f: float, f_low: float, f_high: float, relative_sigma: float, n_sigma: float, floor: float
) -> bool:
    """Whether a frame's focal length contradicts a prediction (the zoom model at its zoom encoder).

    The prediction is the interval [f_low, f_high] (the zoom encoder may lag the image: the zoom model
    at the previous and at this frame's zoom). Compared in log f (zoom acts multiplicatively): the
    distance of log f from the interval beyond n_sigma times the prediction's relative 1-sigma, and
    never below `floor` (a fraction). A frame's K comes from its homography by DIAC transfer (eq. 20),
    so a gross disagreement means a wrong homography.
    """
    values = (f, f_low, f_high)
    if not all(math.isfinite(v) and v > 0.0 for v in values):
        return True
    lo, hi = min(f_low, f_high), max(f_low, f_high)
    distance = max(math.log(lo / f), math.log(f / hi), 0.0)
    relative = relative_sigma if math.isfinite(relative_sigma) and relative_sigma > 0.0 else 0.0
    return distance > max(floor, n_sigma * relative)


def _fit_focal(diac: Array, K_ref: Array) -> Array:
    """(n, 3, 3) K with K_ref's aspect, skew and principal point, f^2 by least squares on the DIAC."""
    gamma, skew = K_ref[0, 0] / K_ref[1, 1], K_ref[0, 1] / K_ref[1, 1]
    pp = K_ref[:2, 2]
    P = np.array([[gamma**2 + skew**2, skew, 0.0], [skew, 1.0, 0.0], [0.0, 0.0, 0.0]]).ravel()
    p3 = np.append(pp, 1.0)
    Q = np.outer(p3, p3).ravel()
    d = diac.reshape(-1, 9)
    # Normal equations of [d, -P] [lambda, f^2]^T = Q, one 2x2 system per frame.
    a11, a12, a22 = np.einsum("ni,ni->n", d, d), -(d @ P), P @ P
    b1, b2 = d @ Q, -(P @ Q)
    f2 = (a11 * b2 - a12 * b1) / (a11 * a22 - a12**2)
    if not np.all(f2 > 0.0):
        raise SelfCalibrationError("transferred DIAC gives a non-positive focal length")
    f = np.sqrt(f2)
    K = np.zeros((len(d), 3, 3))
    K[:, 0, 0], K[:, 0, 1], K[:, 1, 1] = gamma * f, skew * f, f
    K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = pp[0], pp[1], 1.0
    return K


def _upper_cholesky(diac: Array) -> Array:
    """(n, 3, 3) upper-triangular K with K K^T = diac (K[2, 2] = 1)."""
    diac = 0.5 * (diac + np.swapaxes(diac, 1, 2))
    if np.any(np.linalg.eigvalsh(diac)[:, 0] <= 0.0):
        raise SelfCalibrationError("transferred DIAC is not positive definite")
    flip = np.eye(3)[::-1]
    L = np.linalg.cholesky(flip @ diac @ flip)  # reverse-order Cholesky gives an upper factor
    K = flip @ L @ flip
    return K / K[:, 2:3, 2:3]
