"""Radial distortion models (paper section 7) and their conversion to OpenCV's plumb_bob.

Division model (the eq. 32 family, in Fitzgibbon's "undistort = divide" form):

    x_u = c + (x_d - c) / (1 + lam * rho_d^2),    rho_d = |x_d - c| / f

- lam is DIMENSIONLESS: it acts on the radius normalised by the focal length f (pixels), so one lam
  describes the same angular distortion of the lens at any image size. The paper's pixel-unit kappa
  (eq. 32, r_d = r_u / (1 - kappa r_u^2)) is kappa = lam / f^2 to first order, with the same sign
  convention (negative = barrel); eq. 32 is the same quadratic with x_u and x_d exchanged.
- lam < 0 is barrel distortion (the distorted image is compressed towards c), lam > 0 pin-cushion.
- Undistortion is closed form (used per pixel by the renderer); distortion solves the quadratic
  lam * rho_u * rho_d^2 - rho_d + rho_u = 0 for the root that tends to rho_u as lam -> 0.

plumb_bob (OpenCV, ROS CameraInfo): on normalised coordinates x_n = K^-1 x,
    x_d = x_u * (1 + k1 r^2 + k2 r^4 + k3 r^6),  r = |x_u|  (tangential p1 = p2 = 0 here).

`radial_displacement` and `max_distortion_difference` implement the metric of DESIGN.md section 7.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

DIVISION = "division"
PLUMB_BOB = "plumb_bob"


def _as_points(points: ArrayLike) -> Array:
    return np.asarray(points, dtype=float).reshape(-1, 2)


# --------------------------------------------------------------------------------------------------
# Division model
# --------------------------------------------------------------------------------------------------
def division_undistort_radius(rho_d: ArrayLike, lam: float) -> Array:
    """Normalised undistorted radius from the distorted one: rho_u = rho_d / (1 + lam rho_d^2)."""
    rho_d = np.asarray(rho_d, dtype=float)
    return rho_d / (1.0 + lam * rho_d * rho_d)


def division_distort_radius(rho_u: ArrayLike, lam: float) -> Array:
    """Normalised distorted radius from the undistorted one (closed-form root of the quadratic).

    rho_d = 2 rho_u / (1 + sqrt(1 - 4 lam rho_u^2)); NaN where no real root exists (pin-cushion far out).
    """
    rho_u = np.asarray(rho_u, dtype=float)
    disc = 1.0 - 4.0 * lam * rho_u * rho_u
    with np.errstate(invalid="ignore"):
        return np.where(disc >= 0.0, 2.0 * rho_u / (1.0 + np.sqrt(np.maximum(disc, 0.0))), np.nan)


def division_undistort(points_d: ArrayLike, lam: float, centre: ArrayLike, f: float) -> Array:
    """Undistort (N, 2) distorted pixels with the division model (lam on radius / f, see module doc)."""
    c = np.asarray(centre, dtype=float).reshape(2)
    d = _as_points(points_d) - c
    scale = 1.0 / (1.0 + (lam / (f * f)) * np.einsum("ij,ij->i", d, d))
    return c + d * scale[:, None]


def division_distort(points_u: ArrayLike, lam: float, centre: ArrayLike, f: float) -> Array:
    """Distort (N, 2) undistorted pixels with the division model (exact inverse of division_undistort)."""
    c = np.asarray(centre, dtype=float).reshape(2)
    u = _as_points(points_u) - c
    disc = 1.0 - 4.0 * (lam / (f * f)) * np.einsum("ij,ij->i", u, u)
    with np.errstate(invalid="ignore"):
        scale = np.where(disc >= 0.0, 2.0 / (1.0 + np.sqrt(np.maximum(disc, 0.0))), np.nan)
    return c + u * scale[:, None]


def distort_points(points_u: ArrayLike, K: ArrayLike, lam: float) -> Array:
    """Distort (N, 2) undistorted pixels with the division model on normalised coordinates K^-1 x
    about K's principal point (= division_distort with f = fx for square pixels and zero skew; the
    projection of bundle/adjust.py's distortion=True adjustment)."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    pts = _as_points(points_u)
    n = np.linalg.solve(K, np.column_stack([pts, np.ones(len(pts))]).T)[:2].T
    disc = 1.0 - 4.0 * lam * np.einsum("ij,ij->i", n, n)
    with np.errstate(invalid="ignore"):
        scale = np.where(disc >= 0.0, 2.0 / (1.0 + np.sqrt(np.maximum(disc, 0.0))), np.nan)
    return (n * scale[:, None]) @ K[:2, :2].T + K[:2, 2]


def half_diagonal(width: int, height: int) -> float:
    """Distance in pixels from the image centre ((w-1)/2, (h-1)/2) to a corner pixel centre."""
    return 0.5 * float(np.hypot(width - 1.0, height - 1.0))


def lambda_of_corner_shift(shift: ArrayLike, rho: ArrayLike) -> Array:
    """lam such that undistortion moves a distorted point at normalised radius rho by the fraction
    `shift` of its radius: 1 / (1 + lam rho^2) = 1 + shift (the corner shift, as data sheets quote
    distortion, with rho = half-diagonal / f). The one definition of this conversion."""
    s, r = np.asarray(shift, dtype=float), np.asarray(rho, dtype=float)
    return -s / ((1.0 + s) * r * r)


def corner_shift_of_lambda(lam: ArrayLike, rho: ArrayLike) -> Array:
    """Inverse of lambda_of_corner_shift: the shift fraction of a point at normalised radius rho."""
    la, r = np.asarray(lam, dtype=float), np.asarray(rho, dtype=float)
    return 1.0 / (1.0 + la * r * r) - 1.0


def lambda_of_corner_shift_derivative(shift: ArrayLike, rho: ArrayLike) -> Array:
    """d lam / d shift of lambda_of_corner_shift at constant rho."""
    s, r = np.asarray(shift, dtype=float), np.asarray(rho, dtype=float)
    return -1.0 / ((1.0 + s) ** 2 * r * r)


def corner_shift_of_lambda_derivative(lam: ArrayLike, rho: ArrayLike) -> Array:
    """d shift / d lam of corner_shift_of_lambda at constant rho."""
    la, r = np.asarray(lam, dtype=float), np.asarray(rho, dtype=float)
    return -(r * r) / (1.0 + la * r * r) ** 2


def division_lambda_for_corner_shift(shift_fraction: float, width: int, height: int, f: float) -> float:
    """lam such that undistortion moves the image corner by shift_fraction of the half-diagonal.

    The distorted corner (rho_d = D / f, D the half-diagonal, centre at the image centre) undistorts to
    D * (1 + shift_fraction): positive shift_fraction = barrel (lam < 0), negative = pin-cushion.
    """
    if shift_fraction <= -1.0:
        raise ValueError("shift_fraction must be > -1")
    return float(lambda_of_corner_shift(shift_fraction, half_diagonal(width, height) / f))


def division_corner_shift(lam: float, width: int, height: int, f: float) -> float:
    """Inverse of division_lambda_for_corner_shift: corner shift as a fraction of the half-diagonal."""
    return float(corner_shift_of_lambda(lam, half_diagonal(width, height) / f))


# --------------------------------------------------------------------------------------------------
# plumb_bob (OpenCV radial k1, k2[, k3])
# --------------------------------------------------------------------------------------------------
def _radial_coefficients(coeffs: ArrayLike) -> tuple[float, float, float]:
    """(k1, k2, k3) from (k1,), (k1, k2), (k1, k2, k3) or a full OpenCV (k1, k2, p1, p2, k3)."""
    c = np.asarray(coeffs, dtype=float).ravel()
    if len(c) >= 5:
        if abs(c[2]) > 0.0 or abs(c[3]) > 0.0:
            raise ValueError("tangential distortion is not supported")
        return float(c[0]), float(c[1]), float(c[4])
    c = np.concatenate([c, np.zeros(3 - len(c))])
    return float(c[0]), float(c[1]), float(c[2])


def plumb_bob_distort_radius(r_u: ArrayLike, k1: float, k2: float, k3: float = 0.0) -> Array:
    r_u = np.asarray(r_u, dtype=float)
    r2 = r_u * r_u
    return r_u * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))


def plumb_bob_undistort_radius(
    r_d: ArrayLike, k1: float, k2: float, k3: float = 0.0, iterations: int = 30
) -> Array:
    """Invert r_d = r_u (1 + k1 r_u^2 + k2 r_u^4 + k3 r_u^6) by Newton's method (vectorised)."""
    r_d = np.asarray(r_d, dtype=float)
    r_u = r_d.copy()
    for _ in range(iterations):
        r2 = r_u * r_u
        g = r_u * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))) - r_d
        dg = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + 7.0 * k3 * r2))
        step = g / np.where(np.abs(dg) > 1e-12, dg, 1e-12)
        r_u = r_u - step
        if np.all(np.abs(step) < 1e-14):
            break
    return r_u


def plumb_bob_distort(points_u: ArrayLike, k1: float, k2: float, K: ArrayLike, k3: float = 0.0) -> Array:
    """Distort (N, 2) undistorted pixels with OpenCV's radial model on normalised coordinates."""
    K = np.asarray(K, dtype=float)
    u = _as_points(points_u)
    y = (u[:, 1] - K[1, 2]) / K[1, 1]
    x = (u[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    r2 = x * x + y * y
    g = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd, yd = x * g, y * g
    return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])


def plumb_bob_undistort(
    points_d: ArrayLike, k1: float, k2: float, K: ArrayLike, k3: float = 0.0, use_opencv: bool = False
) -> Array:
    """Undistort (N, 2) distorted pixels (pixels out, P = K).

    Default: exact radial Newton inversion. use_opencv=True calls cv2.undistortPointsIter with a tight
    criterion (what a careful OpenCV consumer gets).
    """
    K = np.asarray(K, dtype=float)
    d = _as_points(points_d)
    if use_opencv:
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        D = np.array([k1, k2, 0.0, 0.0, k3])
        src = d.reshape(-1, 1, 2)
        if hasattr(cv2, "undistortPointsIter"):
            out = cv2.undistortPointsIter(src, K, D, None, K, criteria)
        else:
            out = cv2.undistortPoints(src, K, D, None, None, K, criteria)
        return out.reshape(-1, 2).astype(float)
    y = (d[:, 1] - K[1, 2]) / K[1, 1]
    x = (d[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    r_d = np.hypot(x, y)
    r_u = plumb_bob_undistort_radius(r_d, k1, k2, k3)
    scale = np.divide(r_u, r_d, out=np.ones_like(r_d), where=r_d > 0.0)
    xu, yu = x * scale, y * scale
    return np.column_stack([K[0, 0] * xu + K[0, 1] * yu + K[0, 2], K[1, 1] * yu + K[1, 2]])


# --------------------------------------------------------------------------------------------------
# Radial displacement curves and the distortion metric (DESIGN.md section 7)
# --------------------------------------------------------------------------------------------------
def radial_displacement(model: str, params: ArrayLike, K: ArrayLike, radii: ArrayLike) -> Array:
    """Undistortion displacement r_u - r_d in pixels at distorted radii (pixels from K's principal point).

    model "division": params = (lam,) normalised by fx; "plumb_bob": params = (k1[, k2[, k3]]) or the
    5-vector D. Positive values = barrel (undistortion pushes points outwards).
    """
    K = np.asarray(K, dtype=float)
    f = float(K[0, 0])
    rho_d = np.asarray(radii, dtype=float) / f
    p = np.asarray(params, dtype=float).ravel()
    if model == DIVISION:
        rho_u = division_undistort_radius(rho_d, float(p[0]))
    elif model == PLUMB_BOB:
        rho_u = plumb_bob_undistort_radius(rho_d, *_radial_coefficients(p))
    else:
        raise ValueError(f"unknown distortion model {model!r}")
    return f * (rho_u - rho_d)


def corner_radius(K: ArrayLike, width: int, height: int) -> float:
    """Largest distance in pixels from K's principal point to an image corner pixel centre."""
    K = np.asarray(K, dtype=float)
    corners = np.array([[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]])
    return float(np.max(np.linalg.norm(corners - K[:2, 2], axis=1)))


def max_distortion_difference(
    est: tuple[str, ArrayLike, ArrayLike],
    true: tuple[str, ArrayLike, ArrayLike],
    width: int,
    height: int,
    samples: int = 512,
) -> float:
    """DESIGN.md section 7 distortion error in pixels.

    est and true are (model, params, K). Both displacement curves are evaluated about their own
    principal point (principal point error excluded) at the same radii, from 0 to the true K's farthest
    image corner; returns the largest absolute difference.
    """
    model_e, params_e, K_e = est
    model_t, params_t, K_t = true
    radii = np.linspace(0.0, corner_radius(K_t, width, height), samples)
    diff = radial_displacement(model_e, params_e, K_e, radii) - radial_displacement(
        model_t, params_t, K_t, radii
    )
    return float(np.max(np.abs(diff)))


# --------------------------------------------------------------------------------------------------
# Division model -> plumb_bob (what the CameraInfo carries)
# --------------------------------------------------------------------------------------------------
class PlumbBobFit(NamedTuple):
    k1: float
    k2: float
    rms_px: float  # fit residual over the image, pixels (distorted positions)
    max_px: float


def division_to_plumb_bob_fit(
    lam: float, K: ArrayLike, width: int, height: int, samples: int = 256, minimax_iterations: int = 20
) -> PlumbBobFit:
    """Fit plumb_bob (k1, k2) to the division model lam over the image, radii 0 .. farthest corner.

    Residual = distorted-position difference in pixels at undistorted radii reaching the distorted
    corner (what cv2.initUndistortRectifyMap evaluates), scaled to the undistorted-position error.
    Linear least squares, then Lawson's iterative reweighting towards the minimax fit (the metric of
    DESIGN.md section 7 is a maximum).
    """
    K = np.asarray(K, dtype=float)
    f = float(K[0, 0])
    rho_d_max = corner_radius(K, width, height) / f
    rho_u_max = float(division_undistort_radius(rho_d_max, lam))
    if not np.isfinite(rho_u_max) or rho_u_max <= 0.0:
        raise ValueError("division model is not invertible over the image")
    rho_u = np.linspace(0.0, rho_u_max, samples)[1:]
    rho_d = division_distort_radius(rho_u, lam)
    # r_d - r_u = k1 r_u^3 + k2 r_u^5 in pixels, each row scaled by d rho_u / d rho_d so the residual is
    # the (linearised) undistortion error, the quantity the metric compares
    lam_r2 = lam * rho_d * rho_d
    gain = (1.0 - lam_r2) / (1.0 + lam_r2) ** 2
    A = (f * gain)[:, None] * np.column_stack([rho_u**3, rho_u**5])
    b = f * gain * (rho_d - rho_u)
    weights = np.full(len(b), 1.0 / len(b))
    best: tuple[float, Array] | None = None
    for _ in range(max(1, minimax_iterations)):
        sw = np.sqrt(weights)
        k = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)[0]
        res = np.abs(A @ k - b)
        if best is None or res.max() < best[0]:
            best = (float(res.max()), k)
        weights = weights * np.maximum(res, 1e-15)
        weights /= weights.sum()
    assert best is not None
    k = best[1]
    res = A @ k - b
    return PlumbBobFit(float(k[0]), float(k[1]), float(np.sqrt(np.mean(res**2))), float(np.max(np.abs(res))))


def division_to_plumb_bob(lam: float, K: ArrayLike, width: int, height: int) -> tuple[float, float]:
    """(k1, k2) such that OpenCV with (K, D = [k1, k2, 0, 0, 0]) reproduces the division model lam."""
    fit = division_to_plumb_bob_fit(lam, K, width, height)
    return fit.k1, fit.k2
