"""Linear self-calibration of a rotating and zooming camera (paper section 3.3.2, eq. 23).

Every frame's linear constraints on its image of the absolute conic (IAC) omega_j — zero skew,
square pixels, known principal point — are transferred to the reference frame with
omega_j = H_j^-T omega_0 H_j^-1 (eq. 23) and solved by least squares (SVD) for the six entries of
omega_0. Each K_j then follows from the Cholesky factorisation of omega_j.

Conditioning: pixel coordinates are centred at the image centre (or at the
known principal point) and scaled by a nominal focal length; homographies are scaled to unit
determinant in those coordinates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.intrinsics import (
    SelfCalibrationError,
    image_centre,
    rotations_from_homographies,
)
from ptz_selfcal.selfcal.degeneracy import analyse_motion
from ptz_selfcal.selfcal.result import SelfCalibrationResult

Array = NDArray[np.float64]

# Symmetric 3x3 entries (row, column) in the order of the unknown vector w of omega_0.
_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def normalising_transform(centre: tuple[float, float], nominal_focal: float) -> Array:
    """N mapping pixels to coordinates centred at `centre` and scaled by 1/nominal_focal."""
    s = 1.0 / nominal_focal
    return np.array([[s, 0.0, -s * centre[0]], [0.0, s, -s * centre[1]], [0.0, 0.0, 1.0]])


def normalise_homographies(H: ArrayLike, N: Array) -> Array:
    """(n, 3, 3) N H_j N^-1 scaled to unit determinant (eq. 10's scale), validated."""
    H = np.asarray(H, dtype=float).reshape(-1, 3, 3)
    Hn = N @ H @ np.linalg.inv(N)
    det = np.linalg.det(Hn)
    if not np.all(np.isfinite(det)) or np.any(np.abs(det) < 1e-300):
        raise SelfCalibrationError("a homography is singular or not finite")
    return Hn / np.cbrt(det)[:, None, None]


def conic_transfer_rows(G: Array, a: int, b: int) -> Array:
    """(n, 6) coefficients of omega_j[a, b] = (G_j^T omega_0 G_j)[a, b] in the entries w of omega_0."""
    rows = np.empty((len(G), 6))
    for k, (r, c) in enumerate(_SYM):
        term = G[:, r, a] * G[:, c, b]
        if r != c:
            term = term + G[:, c, a] * G[:, r, b]
        rows[:, k] = term
    return rows


def symmetric_from_vector(w: Array) -> Array:
    """3x3 symmetric matrix from its six independent entries (order of _SYM)."""
    M = np.empty((3, 3))
    for k, (r, c) in enumerate(_SYM):
        M[r, c] = M[c, r] = w[k]
    return M


def intrinsics_from_iac(omega: Array) -> Array:
    """(n, 3, 3) upper-triangular K with omega = K^-T K^-1 (Cholesky), K[2, 2] = 1.

    Raises SelfCalibrationError naming the frames whose omega is not positive definite.
    """
    omega = 0.5 * (omega + np.swapaxes(omega, 1, 2))
    eig_min = np.linalg.eigvalsh(omega)[:, 0]
    bad = np.flatnonzero(~(eig_min > 0.0))
    if bad.size:
        raise SelfCalibrationError(
            f"IAC not positive definite in {bad.size} frame(s) (first: {int(bad[0])}); "
            "the constraints do not fit a real camera (noise, wrong model or degenerate motion)"
        )
    L = np.linalg.cholesky(omega)  # omega = L L^T, so K^-1 = L^T
    K = np.linalg.inv(np.swapaxes(L, 1, 2))
    return K / K[:, 2:3, 2:3]


def _solve_null_vector(A: Array, rank_tolerance: float, min_gap: float) -> tuple[Array, Array]:
    """Unit w minimising |A w| by SVD, refusing a null space of dimension > 1."""
    if A.shape[0] < 5:
        raise SelfCalibrationError(f"only {A.shape[0]} linear constraints for the 5 dof of omega_0")
    A = A / np.linalg.norm(A, axis=1, keepdims=True).clip(1e-300)  # equal weight per constraint
    _, s, Vt = np.linalg.svd(A, full_matrices=False)
    if s[4] < rank_tolerance * s[0] or s[4] < min_gap * s[5]:
        raise SelfCalibrationError(
            "insufficient constraints: the linear system for omega_0 has a null space of dimension > 1 "
            f"(singular values {s[4]:.3g}, {s[5]:.3g} of {s[0]:.3g}); the motion is degenerate for "
            "this constraint set (e.g. pan-only or tilt-only with zero skew only)"
        )
    return Vt[5], s


def linear_selfcalibration(
    H: ArrayLike,
    image_size: tuple[int, int],
    *,
    zero_skew: bool = True,
    square_pixels: bool = True,
    known_principal_point: tuple[float, float] | None = None,
    nominal_focal: float | str | None = None,
    rank_tolerance: float = 1e-9,
    min_gap: float = 1.5,
    analyse: bool = True,
) -> SelfCalibrationResult:
    """Linear self-calibration (section 3.3.2) from H[j] mapping frame-0 pixels to frame-j pixels.

    Constraints per frame on omega_j: zero skew (omega_12 = 0), square pixels (omega_11 = omega_22),
    known principal point (omega_13 = omega_23 = 0 in coordinates centred on it). Square pixels and a
    known principal point imply zero skew, as in the paper. Raises SelfCalibrationError when the
    constraints are insufficient (rank-deficient system) or omega is not positive definite.
    nominal_focal: the coordinate scale (default the image width); "auto" re-solves with the first
    estimate's median focal length, which removes most of the varying-pp bias.
    With `analyse`, the result carries the geometric section-6 MotionReport (no sigma_f: the
    linear method has none) and ok is False when the motion is not well posed.
    """
    H = np.asarray(H, dtype=float).reshape(-1, 3, 3)
    if not (zero_skew or square_pixels or known_principal_point is not None):
        raise SelfCalibrationError("no constraint selected")
    if nominal_focal == "auto":
        # Two passes: the bias with a varying principal point shrinks as the scale nears the true
        # focal length, so re-normalise by the first pass's median focal.
        first = linear_selfcalibration(
            H,
            image_size,
            zero_skew=zero_skew,
            square_pixels=square_pixels,
            known_principal_point=known_principal_point,
            analyse=False,
        )
        nominal_focal = float(np.median(first.K[:, 1, 1]))
    nominal = float(nominal_focal or image_size[0])
    centre = known_principal_point if known_principal_point is not None else image_centre(image_size)
    N = normalising_transform(centre, nominal)
    G = np.linalg.inv(normalise_homographies(H, N))  # omega_j = G_j^T omega_0 G_j (eq. 23)
    blocks = [conic_transfer_rows(G, 0, 1)]  # zero skew: omega_12 = 0
    if square_pixels:
        blocks.append(conic_transfer_rows(G, 0, 0) - conic_transfer_rows(G, 1, 1))
    if known_principal_point is not None:
        blocks += [conic_transfer_rows(G, 0, 2), conic_transfer_rows(G, 1, 2)]
    A = np.vstack(blocks)
    w, s = _solve_null_vector(A, rank_tolerance, min_gap)
    omega_0 = symmetric_from_vector(w)
    if np.trace(omega_0) < 0.0:
        omega_0 = -omega_0
    omega = np.swapaxes(G, 1, 2) @ omega_0 @ G
    K_n = intrinsics_from_iac(omega)
    K_n = _impose_constraints(K_n, square_pixels, known_principal_point is not None)
    K = np.linalg.inv(N) @ K_n
    K /= K[:, 2:3, 2:3]
    R = rotations_from_homographies(H, K)
    n = len(H)
    result = SelfCalibrationResult(
        K=K,
        R=R,
        sigma_f=np.full(n, np.nan),
        sigma_pp=np.full((n, 2), np.nan),
        residual=float(s[5] / np.sqrt(A.shape[0])),
        method="linear",
        iterations=0,
        ok=True,
        message="",
    )
    if analyse:
        result.motion = analyse_motion(R, K, image_size)
        if not result.motion.well_posed:
            result.ok = False
            result.message = f"motion not well posed: {result.motion.status} ({result.motion.message})"
    return result


def _impose_constraints(K: Array, square_pixels: bool, known_pp: bool) -> Array:
    """Make the Cholesky factors satisfy the imposed constraints exactly (zero skew always)."""
    K = K.copy()
    K[:, 0, 1] = 0.0
    if square_pixels:
        f = np.sqrt(K[:, 0, 0] * K[:, 1, 1])
        K[:, 0, 0] = K[:, 1, 1] = f
    if known_pp:
        K[:, :2, 2] = 0.0
    return K
