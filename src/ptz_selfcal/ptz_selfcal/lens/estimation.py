"""Radial distortion from image data alone while the camera zooms (paper section 7.2, beyond the paper).

A rotating camera maps UNDISTORTED points of keyframe i to those of keyframe j by a homography
(eq. 8); distorted points are not related by any homography, so the transfer error of the best
homography measures the distortion left uncorrected (section 7.2, Fig. 15). We minimise the symmetric
transfer error over one division-model coefficient per keyframe and one homography per keyframe pair:

    min  sum_pairs sum_points |d_j(H u_i(x_i)) - x_j|^2 + |d_i(H^-1 u_j(x_j)) - x_i|^2

(u_k / d_k = undistortion / distortion with lam_k, see camera/distortion.py). This is the paper's first
option (one kappa per image) but on homographies instead of the full bundle adjustment: the homography
absorbs K and R, so the problem is small and well conditioned. Optionally the coefficients are tied by
the distortion-versus-focal curve (the paper's second option, eq. 35, with a better-behaved curve):
see lens/curve.DistortionVsFocal; lens/estimator.py is the incremental seam for the calibrator.

Seams for the calibrator: everything is expressed with dimensionless lam on radius / f; the image data
constrain the pixel-unit coefficient lam / f^2, so if f is refined later, `rescale_lambda` converts.
Pure rotation is required: a pure zoom about the distortion centre leaves lam_j (f_i/f_j)^2 - lam_i
unobservable to first order, so pairs should differ by a rotation of a good part of the field of view.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import division_undistort, lambda_of_corner_shift_derivative
from ptz_selfcal.camera.geometry import apply_homography, pixel_grid
from ptz_selfcal.frontend.homography import estimate_homography, homography_dlt
from ptz_selfcal.lens.curve import DistortionVsFocal

Array = NDArray[np.float64]


# --------------------------------------------------------------------------------------------------
# Helpers on normalised coordinates (x - c) / f
# --------------------------------------------------------------------------------------------------
def rescale_lambda(lam: float, f_old: float, f_new: float) -> float:
    """The same pixel-space distortion expressed for a new focal length (lam / f^2 is invariant)."""
    return float(lam * (f_new / f_old) ** 2)


def _undistort_normalised(a: Array, lam: float) -> Array:
    return a / (1.0 + lam * np.einsum("ij,ij->i", a, a))[:, None]


def _distort_normalised(a: Array, lam: float) -> Array:
    # closed-form root of the division quadratic; clamped so residuals stay finite for pin-cushion
    disc = np.maximum(1.0 - 4.0 * lam * np.einsum("ij,ij->i", a, a), 1e-6)
    return a * (2.0 / (1.0 + np.sqrt(disc)))[:, None]


def _homography_from_update(delta: Array, H0: Array) -> Array:
    """H = (I + D) H0 with D[2, 2] = 0: a local 8-parameter chart around H0."""
    D = np.append(delta, 0.0).reshape(3, 3)
    return (np.eye(3) + D) @ H0


def _centre_pair(centre: ArrayLike) -> tuple[Array, Array]:
    c = np.asarray(centre, dtype=float)
    if c.shape == (2,):
        return c, c
    if c.shape == (2, 2):
        return c[0], c[1]
    raise ValueError("centre must be (2,) or (2, 2)")


# --------------------------------------------------------------------------------------------------
# Homographies on corrected coordinates (what self-calibration needs, section 7.2's third option)
# --------------------------------------------------------------------------------------------------
def undistorted_homography_from_points(
    pts_i: ArrayLike,
    pts_j: ArrayLike,
    lam_i: float,
    lam_j: float,
    centre_i: ArrayLike,
    centre_j: ArrayLike,
    f_i: float,
    f_j: float,
) -> Array:
    """Exact route: undistort the inlier correspondences of each image, then DLT + LM (eq. 8 holds)."""
    src = division_undistort(pts_i, lam_i, centre_i, f_i)
    dst = division_undistort(pts_j, lam_j, centre_j, f_j)
    return estimate_homography(src, dst)


def undistorted_homography(
    H_distorted: ArrayLike,
    lam_i: float,
    lam_j: float,
    centre_i: ArrayLike,
    centre_j: ArrayLike,
    f_i: float,
    f_j: float,
    width: int,
    height: int,
    count: int = 16,
) -> Array:
    """Approximate route when only a homography fitted to DISTORTED points is available.

    A grid of image-i pixels is mapped through H_distorted, both ends are undistorted and a homography
    refitted. The result inherits H_distorted's misfit to the true (non-projective) distorted mapping,
    far smaller than the distortion it removes but not zero. Prefer `undistorted_homography_from_points`
    whenever the inliers are at hand.
    """
    grid = pixel_grid(width, height, count)
    mapped = apply_homography(H_distorted, grid)
    margin = 0.05 * max(width, height)
    keep = np.all((mapped >= -margin) & (mapped <= [width - 1 + margin, height - 1 + margin]), axis=1)
    keep &= np.all(np.isfinite(mapped), axis=1)
    if keep.sum() < 8:
        raise ValueError("the homography maps too little of image i into image j")
    src = division_undistort(grid[keep], lam_i, centre_i, f_i)
    dst = division_undistort(mapped[keep], lam_j, centre_j, f_j)
    return estimate_homography(src, dst)


# --------------------------------------------------------------------------------------------------
# Joint estimation over keyframe pairs
# --------------------------------------------------------------------------------------------------
@dataclass
class KeyframeMatch:
    """Corresponding distorted pixels between keyframes i and j (inliers, full-resolution pixels)."""

    i: int
    j: int
    pts_i: Array
    pts_j: Array


@dataclass
class KeyframeDistortion:
    lam: Array  # per keyframe, dimensionless (radius / f)
    sigma_lam: Array  # 1-sigma from the Gauss-Newton covariance (inf where unobserved)
    homographies: list[Array]  # per match: undistorted pixels of i -> undistorted pixels of j
    rms: float  # symmetric transfer error, pixels, all matches
    pair_rms: Array
    rms_undistorted_model: float = float("nan")  # the same with lam = 0 (what correction gained)
    curve_coefficients: Array | None = None
    converged: bool = True
    message: str = field(default="")


@dataclass
class PairDistortion:
    lam_i: float
    lam_j: float
    H: Array  # undistorted pixels of i -> undistorted pixels of j
    rms: float
    sigma_lam_i: float = float("nan")
    sigma_lam_j: float = float("nan")


def _normalise(pts: ArrayLike, centre: Array, f: float) -> Array:
    return (np.asarray(pts, dtype=float).reshape(-1, 2) - centre) / f


def _initial_homography(a: Array, b: Array, lam_i: float, lam_j: float) -> Array:
    H = homography_dlt(_undistort_normalised(a, lam_i), _undistort_normalised(b, lam_j))
    return H / np.cbrt(np.linalg.det(H))


def _pair_residuals(
    a: Array, b: Array, lam_i: float, lam_j: float, H: Array, f_i: float, f_j: float
) -> Array:
    """Symmetric transfer residuals in pixels, (4N,)."""
    res_j = (_distort_normalised(apply_homography(H, _undistort_normalised(a, lam_i)), lam_j) - b) * f_j
    res_i = (
        _distort_normalised(apply_homography(np.linalg.inv(H), _undistort_normalised(b, lam_j)), lam_i) - a
    ) * f_i
    return np.concatenate([res_j.ravel(), res_i.ravel()])


def _projection_derivative(p: Array) -> tuple[Array, Array]:
    """v = p[:2] / p[2] and dv/dp, (N, 2) and (N, 2, 3)."""
    v = p[:, :2] / p[:, 2:3]
    dv = np.zeros((len(p), 2, 3))
    inv = 1.0 / p[:, 2]
    dv[:, 0, 0] = inv
    dv[:, 1, 1] = inv
    dv[:, :, 2] = -v * inv[:, None]
    return v, dv


def _distort_derivative(v: Array, lam: float) -> tuple[Array, Array, Array]:
    """w = v g(lam |v|^2) (closed-form division distortion), dw/dv (N, 2, 2) and dw/dlam (N, 2)."""
    s = np.einsum("ij,ij->i", v, v)
    disc = np.maximum(1.0 - 4.0 * lam * s, 1e-6)
    sq = np.sqrt(disc)
    g = 2.0 / (1.0 + sq)
    dg = 4.0 / ((1.0 + sq) ** 2 * sq)  # dg/dt, t = lam |v|^2
    w = v * g[:, None]
    dw_dv = g[:, None, None] * np.eye(2) + (2.0 * lam * dg)[:, None, None] * v[:, :, None] * v[:, None, :]
    return w, dw_dv, v * (dg * s)[:, None]


def _one_way(
    a: Array, b: Array, lam_src: float, lam_dst: float, M: Array, f_dst: float
) -> tuple[Array, Array, Array, Array, Array, Array]:
    """Residual f_dst (d(M u(a)) - b) and its derivatives w.r.t. lam_src, lam_dst and M's input p.

    Returns r (N, 2), dr/dlam_src (N, 2), dr/dlam_dst (N, 2), dr/dp (N, 2, 3) with p = M [u, 1],
    the homogeneous source point [u, 1] (N, 3) and p (N, 3).
    """
    s_a = np.einsum("ij,ij->i", a, a)
    den = 1.0 + lam_src * s_a
    u = a / den[:, None]
    du_dlam = -a * (s_a / den**2)[:, None]
    x = np.column_stack([u, np.ones(len(u))])
    p = x @ M.T
    v, dv_dp = _projection_derivative(p)
    w, dw_dv, dw_dlam = _distort_derivative(v, lam_dst)
    dr_dp = f_dst * np.einsum("nij,njk->nik", dw_dv, dv_dp)
    dr_dlam_src = np.einsum("nik,kl,nl->ni", dr_dp, M[:, :2], du_dlam)
    return f_dst * (w - b), dr_dlam_src, f_dst * dw_dlam, dr_dp, x, p


_CHART = [(r, c) for r in range(3) for c in range(3)][:8]  # the 8 free entries of D in H = (I + D) H0


def _pair_jacobian(
    a: Array, b: Array, lam_i: float, lam_j: float, H0: Array, H: Array, f_i: float, f_j: float
) -> tuple[Array, Array, Array]:
    """Residuals (4N,), d/d(lam_i, lam_j) (4N, 2) and d/dD (4N, 8) of the symmetric transfer error."""
    Hinv = np.linalg.inv(H)
    r_j, dj_dli, dj_dlj, dj_dp, x_i, _ = _one_way(a, b, lam_i, lam_j, H, f_j)
    r_i, di_dlj, di_dli, di_dp, _, p_back = _one_way(b, a, lam_j, lam_i, Hinv, f_i)
    # forward: dp/dD[r, c] = e_r (H0 x)_c ; backward: d(H^-1 x')/dD[r, c] = -H^-1 e_r (H0 H^-1 x')_c
    q = x_i @ H0.T
    m = p_back @ H0.T
    back = np.einsum("nik,kr->nir", di_dp, -Hinv)
    J_D = np.empty((2, len(a), 2, 8))
    for col, (r, c) in enumerate(_CHART):
        J_D[0, :, :, col] = dj_dp[:, :, r] * q[:, c : c + 1]
        J_D[1, :, :, col] = back[:, :, r] * m[:, c : c + 1]
    J_lam = np.concatenate(
        [
            np.stack([dj_dli, dj_dlj], axis=-1).reshape(-1, 2),
            np.stack([di_dli, di_dlj], axis=-1).reshape(-1, 2),
        ]
    )
    return np.concatenate([r_j.ravel(), r_i.ravel()]), J_lam, J_D.reshape(-1, 8)


def _to_pixels(H_norm: Array, centre_i: Array, centre_j: Array, f_i: float, f_j: float) -> Array:
    """Homography on normalised coordinates -> on pixels."""
    Ni = np.array([[1.0 / f_i, 0.0, -centre_i[0] / f_i], [0.0, 1.0 / f_i, -centre_i[1] / f_i], [0, 0, 1.0]])
    Mj = np.array([[f_j, 0.0, centre_j[0]], [0.0, f_j, centre_j[1]], [0, 0, 1.0]])
    H = Mj @ H_norm @ Ni
    return H / H[2, 2]


def estimate_keyframe_distortion(
    matches: Sequence[KeyframeMatch],
    focals: ArrayLike,
    centres: ArrayLike,
    lam0: ArrayLike | None = None,
    curve: DistortionVsFocal | None = None,
    loss: str = "soft_l1",
    f_scale_px: float = 2.0,
    max_iterations: int = 100,
    fixed: ArrayLike | None = None,
    prior: tuple[ArrayLike, ArrayLike] | None = None,
    noise_px: float = 0.3,
) -> KeyframeDistortion:
    """One lam per keyframe (or the curve's coefficients if `curve` is given) and one H per match.

    focals: (K,) current focal estimates (a nominal value is fine: only lam / f^2 is observed);
    centres: (2,) or (K, 2) distortion centres (principal points); lam0: (K,) starting values.
    Robust loss (soft_l1, f_scale_px pixels) against residual outliers in the matches. With `curve`,
    lam_k = curve(f_k) and the curve object is left fitted. Without a curve: `fixed` (K,) bool keeps
    those keyframes at lam0; `prior` = (mean (K,), sigma (K,), inf = none) adds the Gaussian prior
    (lam - mean) / sigma, weighted against the matches as if they had noise_px pixels of noise.
    Levenberg-Marquardt with the analytic Jacobian on block-sparse normal equations: O(points) per
    iteration, (8 pairs + K)^2 memory.
    """
    focals = np.asarray(focals, dtype=float).ravel()
    n_kf = len(focals)
    centres = np.asarray(centres, dtype=float)
    centres = np.tile(centres, (n_kf, 1)) if centres.shape == (2,) else centres.reshape(n_kf, 2)
    lam_init = np.zeros(n_kf) if lam0 is None else np.asarray(lam0, dtype=float).ravel().copy()
    norm = [
        (_normalise(m.pts_i, centres[m.i], focals[m.i]), _normalise(m.pts_j, centres[m.j], focals[m.j]))
        for m in matches
    ]
    if not matches:
        raise ValueError("no keyframe matches")
    if any(len(a) < 8 or len(a) != len(b) for a, b in norm):
        raise ValueError("every match needs at least 8 correspondences of equal count")

    # distortion parameters: per-keyframe lam, or curve coefficients (in corner-shift units)
    if curve is not None:
        if curve.f_ref is None:
            curve.f_ref = float(focals.min())
        u = curve.f_ref / focals
        V = np.vander(u, curve.degree + 1, increasing=True)
        s0 = curve.shift_from_lambda(focals, lam_init)
        c0 = np.linalg.lstsq(V, s0, rcond=None)[0]
        n_dist = curve.degree + 1

        def lams_of(p: Array) -> Array:
            return curve.lambda_from_shift(focals, V @ p)

        p_init = c0
    else:
        free = np.ones(n_kf, dtype=bool) if fixed is None else ~np.asarray(fixed, dtype=bool).ravel()
        n_dist = int(free.sum())
        selection = np.eye(n_kf)[:, free]

        def lams_of(p: Array) -> Array:
            lams = lam_init.copy()
            lams[free] = p
            return lams

        p_init = lam_init[free]
    prior_rows = np.zeros(0, dtype=int)
    if prior is not None:
        if curve is not None:
            raise ValueError("a prior on lam needs per-keyframe coefficients (no curve)")
        prior_mean = np.asarray(prior[0], dtype=float).ravel()
        prior_weight = noise_px / np.asarray(prior[1], dtype=float).ravel()
        prior_rows = np.flatnonzero(free & np.isfinite(prior_mean) & (prior_weight > 0))
    H0 = [_initial_homography(a, b, lam_init[m.i], lam_init[m.j]) for m, (a, b) in zip(matches, norm)]
    sizes = [4 * len(a) for a, _ in norm] + ([len(prior_rows)] if len(prior_rows) else [])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    n_match_rows = int(offsets[len(matches)])
    n_par = n_dist + 8 * len(matches)

    def dlam_dp(p: Array) -> Array:
        """(n_kf, n_dist) derivative of the keyframe coefficients w.r.t. the distortion parameters."""
        if curve is None:
            return selection
        return lambda_of_corner_shift_derivative(V @ p, curve.half_diagonal / focals)[:, None] * V

    def evaluate(x: Array, with_jacobian: bool) -> tuple[Array, list[tuple[Array, Array]]]:
        """Residuals and, per match, (column indices, Jacobian block) of the block-sparse Jacobian."""
        lams = lams_of(x[:n_dist])
        G = dlam_dp(x[:n_dist]) if with_jacobian else None
        res = np.empty(offsets[-1])
        blocks = []
        for k, (m, (a, b)) in enumerate(zip(matches, norm)):
            rows = slice(offsets[k], offsets[k + 1])
            h_cols = np.arange(n_dist + 8 * k, n_dist + 8 * k + 8)
            H = _homography_from_update(x[h_cols], H0[k])
            if G is None:
                res[rows] = _pair_residuals(a, b, lams[m.i], lams[m.j], H, focals[m.i], focals[m.j])
                continue
            res[rows], J_lam, J_D = _pair_jacobian(
                a, b, lams[m.i], lams[m.j], H0[k], H, focals[m.i], focals[m.j]
            )
            # chain rule through lam_k(parameters): selection of free keyframes, or the curve
            d_cols = np.flatnonzero((G[m.i] != 0.0) | (G[m.j] != 0.0))
            J_dist = (J_lam[:, :1] * G[m.i] + J_lam[:, 1:] * G[m.j])[:, d_cols]
            blocks.append((np.concatenate([d_cols, h_cols]), np.hstack([J_dist, J_D])))
        if len(prior_rows):
            res[n_match_rows:] = prior_weight[prior_rows] * (lams[prior_rows] - prior_mean[prior_rows])
            if G is not None:
                J_prior = prior_weight[prior_rows, None] * G[prior_rows]
                p_cols = np.flatnonzero(np.any(J_prior != 0.0, axis=0))
                blocks.append((p_cols, J_prior[:, p_cols]))
        return res, blocks

    x0 = np.concatenate([p_init, np.zeros(8 * len(matches))])
    solution = _robust_levenberg_marquardt(evaluate, x0, offsets, n_par, loss, f_scale_px, max_iterations)
    x = solution.x
    lams = lams_of(x[:n_dist])
    res, blocks = evaluate(x, True)
    # per-pair rms of point transfer distances, and the covariance of lam (Gauss-Newton, robust-free)
    pair_rms = np.array(
        [np.sqrt(np.mean(res[offsets[k] : offsets[k + 1]] ** 2) * 2.0) for k in range(len(matches))]
    )
    # posterior covariance: data term scaled by the residual variance of the matches, prior exact
    JtJ, _ = _normal_equations(blocks[: len(matches)], offsets, res, np.ones_like(res), n_par)
    dof = max(n_match_rows - n_par, 1)
    information = JtJ * (dof / max(float(res[:n_match_rows] @ res[:n_match_rows]), 1e-300))
    if len(blocks) > len(matches):  # the prior block: rows noise_px / sigma_prior * dlam/dp
        p_cols, J_prior = blocks[-1]
        information[np.ix_(p_cols, p_cols)] += J_prior.T @ J_prior / noise_px**2
    cov = np.linalg.pinv(information)
    if curve is None:
        seen = np.zeros(n_kf, dtype=bool)
        for m in matches:
            seen[[m.i, m.j]] = True
        seen[prior_rows] = True
        sigma = np.zeros(n_kf)
        sigma[free] = np.sqrt(np.maximum(np.diag(cov)[:n_dist], 0.0))
        sigma = np.where(seen | ~free, sigma, np.inf)
    else:
        sigma = _curve_lambda_sigmas(cov[:n_dist, :n_dist], focals, curve, x[:n_dist])
        curve.coefficients = x[:n_dist].copy()  # the curve passed in is now fitted
        curve.f_range = (float(focals.min()), float(focals.max()))
    homographies = [
        _to_pixels(
            _homography_from_update(x[n_dist + 8 * k : n_dist + 8 * k + 8], H0[k]),
            centres[m.i],
            centres[m.j],
            focals[m.i],
            focals[m.j],
        )
        for k, m in enumerate(matches)
    ]
    zero = np.concatenate(
        [
            _pair_residuals(a, b, 0.0, 0.0, _initial_homography(a, b, 0.0, 0.0), focals[m.i], focals[m.j])
            for m, (a, b) in zip(matches, norm)
        ]
    )
    return KeyframeDistortion(
        lam=np.asarray(lams, dtype=float),
        sigma_lam=sigma,
        homographies=homographies,
        rms=float(np.sqrt(np.mean(res[:n_match_rows] ** 2) * 2.0)),
        pair_rms=pair_rms,
        rms_undistorted_model=float(np.sqrt(np.mean(zero**2) * 2.0)),
        curve_coefficients=None if curve is None else x[:n_dist].copy(),
        converged=solution.converged,
        message=solution.message,
    )


class _Solution(NamedTuple):
    x: Array
    converged: bool
    message: str


def _normal_equations(
    blocks: list[tuple[Array, Array]], offsets: Array, res: Array, weights: Array, n_par: int
) -> tuple[Array, Array]:
    """J^T W J and J^T W r accumulated block by block (J is never formed densely)."""
    A = np.zeros((n_par, n_par))
    g = np.zeros(n_par)
    for k, (cols, Jb) in enumerate(blocks):
        rows = slice(offsets[k], offsets[k + 1])
        WJ = Jb * weights[rows, None]
        A[np.ix_(cols, cols)] += Jb.T @ WJ
        g[cols] += WJ.T @ res[rows]
    return A, g


def _robust_cost(res: Array, loss: str, scale: float) -> tuple[float, Array]:
    """Total robust cost and the IRLS weights rho'(r^2) (scipy's soft_l1 / huber / linear losses)."""
    z = (res / scale) ** 2
    if loss == "soft_l1":
        return float(scale**2 * np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0))), 1.0 / np.sqrt(1.0 + z)
    if loss == "huber":
        big = z > 1.0
        rho = np.where(big, 2.0 * np.sqrt(np.maximum(z, 1.0)) - 1.0, z)
        return float(scale**2 * np.sum(rho)), np.where(big, 1.0 / np.sqrt(np.maximum(z, 1.0)), 1.0)
    if loss == "linear":
        return float(np.sum(res**2)), np.ones_like(res)
    raise ValueError(f"unknown loss {loss!r}")


def _robust_levenberg_marquardt(
    evaluate, x0: Array, offsets: Array, n_par: int, loss: str, scale: float, max_iterations: int
) -> _Solution:
    """Levenberg-Marquardt with iteratively reweighted robust loss on block-sparse normal equations."""
    x = x0.copy()
    res, blocks = evaluate(x, True)
    cost, weights = _robust_cost(res, loss, scale)
    mu = 1e-4
    for _ in range(max_iterations):
        A, g = _normal_equations(blocks, offsets, res, weights, n_par)
        diag = np.maximum(np.diag(A), 1e-12 * max(float(np.max(np.diag(A))), 1e-300))
        improved = False
        for _ in range(20):
            try:
                step = np.linalg.solve(A + mu * np.diag(diag), -g)
            except np.linalg.LinAlgError:
                mu *= 10.0
                continue
            new_res = evaluate(x + step, False)[0]
            new_cost = _robust_cost(new_res, loss, scale)[0]
            if np.isfinite(new_cost) and new_cost <= cost:
                improved = True
                break
            mu *= 10.0
        if not improved:
            return _Solution(x, True, "no further decrease of the cost")
        x = x + step
        decrease = cost - new_cost
        cost = new_cost
        mu = max(mu / 10.0, 1e-12)
        if decrease <= 1e-12 * max(cost, 1e-300) or np.max(np.abs(step)) < 1e-14:
            return _Solution(x, True, "converged")
        res, blocks = evaluate(x, True)
        weights = _robust_cost(res, loss, scale)[1]
    return _Solution(x, False, "iteration limit")


def _curve_lambda_sigmas(cov: Array, focals: Array, curve: DistortionVsFocal, coeffs: Array) -> Array:
    assert curve.f_ref is not None
    V = np.vander(curve.f_ref / focals, len(coeffs), increasing=True)
    sigma_s = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", V, cov, V), 0.0))
    return -sigma_s * lambda_of_corner_shift_derivative(V @ coeffs, curve.half_diagonal / focals)


def estimate_pair_distortion(
    pts_i: ArrayLike,
    pts_j: ArrayLike,
    centre: ArrayLike,
    f_i: float,
    f_j: float,
    lam0: tuple[float, float] = (0.0, 0.0),
    loss: str = "soft_l1",
    f_scale_px: float = 2.0,
) -> PairDistortion:
    """Division coefficients of two keyframes jointly with their homography (symmetric transfer error).

    centre: (2,) shared or (2, 2) per-keyframe distortion centre. Returns lam_i, lam_j, H (undistorted
    pixels of i -> undistorted pixels of j) and the rms transfer distance in pixels.
    """
    c_i, c_j = _centre_pair(centre)
    match = KeyframeMatch(0, 1, np.asarray(pts_i, dtype=float), np.asarray(pts_j, dtype=float))
    out = estimate_keyframe_distortion(
        [match],
        [f_i, f_j],
        np.stack([c_i, c_j]),
        lam0=np.asarray(lam0, dtype=float),
        loss=loss,
        f_scale_px=f_scale_px,
    )
    return PairDistortion(
        float(out.lam[0]), float(out.lam[1]), out.homographies[0], out.rms, *map(float, out.sigma_lam)
    )


def estimate_frame_distortion(
    pts_keyframe: ArrayLike,
    pts_frame: ArrayLike,
    lam_keyframe: float,
    centre: ArrayLike,
    f_keyframe: float,
    f_frame: float,
    lam_prior: float | None = None,
    sigma_prior: float = float("inf"),
    noise_px: float = 0.3,
) -> PairDistortion:
    """Per-frame route: the frame's own lam jointly with its homography to a keyframe whose lam is known.

    For the node that holds the frame's inliers (distorted pixels): returns lam_i = lam_keyframe
    (fixed), lam_j = the frame's lam and H between UNDISTORTED pixels (what eq. 8 and the per-frame K
    need; a homography fitted to distorted points and corrected afterwards is biased, see
    `undistorted_homography`). lam_prior / sigma_prior (e.g. DistortionVsFocal at the frame's predicted
    f) regularise frames with few or poorly spread points. centre: (2,) or (2, 2).
    """
    c_i, c_j = _centre_pair(centre)
    match = KeyframeMatch(0, 1, np.asarray(pts_keyframe, dtype=float), np.asarray(pts_frame, dtype=float))
    start = lam_keyframe * (f_frame / f_keyframe) ** 2 if lam_prior is None else lam_prior
    prior = None
    if lam_prior is not None and np.isfinite(sigma_prior):
        prior = (np.array([np.nan, lam_prior]), np.array([np.inf, sigma_prior]))
    out = estimate_keyframe_distortion(
        [match],
        [f_keyframe, f_frame],
        np.stack([c_i, c_j]),
        lam0=np.array([lam_keyframe, start]),
        fixed=np.array([True, False]),
        prior=prior,
        noise_px=noise_px,
    )
    return PairDistortion(
        float(out.lam[0]), float(out.lam[1]), out.homographies[0], out.rms, 0.0, float(out.sigma_lam[1])
    )
