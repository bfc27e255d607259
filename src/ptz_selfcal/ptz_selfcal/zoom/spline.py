"""Penalised B-splines for the zoom model: weighted, optionally monotone, Huber-robust, with one
additive offset per group (a calibration's common log f scale error, section 6.2)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import BSpline
from scipy.optimize import lsq_linear

Array = NDArray[np.float64]


class SplineFit(NamedTuple):
    spline: BSpline
    fitted: Array  # spline plus each point's group offset
    robust_weights: Array  # Huber factors in (0, 1] per point (ones without reweighting)
    covariance: Array  # of the spline coefficients, scaled by the reduced chi-square (NaN without dof)
    dof: float  # points minus the effective number of parameters
    offsets: Array  # per group (empty without groups)
    leverage: Array  # per point, of the unconstrained penalised estimate (leave-one-out residuals)


def design_matrix(x: Array, knots: Array, degree: int) -> Array:
    """B-spline basis at x (clipped into the knot range: the fit's own extension handles outside)."""
    return BSpline.design_matrix(np.clip(x, knots[0], knots[-1]), knots, degree).toarray()


def penalised_spline(
    z: Array,
    y: Array,
    w: Array,
    n_basis: int,
    smoothing: float,
    monotone: bool,
    huber: float | None = None,
    groups: Array | None = None,
    group_prior: Array | None = None,
) -> SplineFit:
    """Weighted P-spline (second-difference penalty), optionally with non-decreasing coefficients,
    Huber reweighting (threshold `huber` robust standard deviations of the weighted residuals) and one
    additive offset per group (groups[i] in 0..G-1) with a zero-mean prior of weight group_prior[g]
    (1 / sigma^2): y_i = s(z_i) + offset[groups[i]] + noise."""
    degree = min(3, n_basis - 1)
    lo, hi = float(z.min()), float(z.max())
    interior = np.linspace(lo, hi, n_basis - degree + 1)[1:-1]
    knots = np.concatenate([np.full(degree + 1, lo), interior, np.full(degree + 1, hi)])
    B = design_matrix(z, knots, degree)
    n_groups = 0 if groups is None or group_prior is None else len(group_prior)
    C = np.zeros((len(z), n_groups))
    if n_groups:
        C[np.arange(len(z)), np.asarray(groups, dtype=int)] = 1.0
    # c = L p, p = (c0, increments): increments >= 0 makes the spline monotone
    L = np.tril(np.ones((n_basis, n_basis))) if monotone else np.eye(n_basis)
    D2 = np.diff(np.eye(n_basis), n=2, axis=0) if n_basis >= 3 else np.zeros((0, n_basis))
    scale_w = float(w.mean())
    prior = np.zeros(0) if not n_groups else np.asarray(group_prior, dtype=float) / scale_w
    n_par = n_basis + n_groups
    robust = np.ones_like(w)
    for _ in range(8 if huber else 1):
        sw = np.sqrt(w * robust / scale_w)
        A = np.vstack(
            [
                np.hstack([(B * sw[:, None]) @ L, C * sw[:, None]]),
                np.hstack([np.sqrt(smoothing) * D2 @ L, np.zeros((len(D2), n_groups))]),
                np.hstack([np.zeros((n_groups, n_basis)), np.diag(np.sqrt(prior))]),
            ]
        )
        b = np.concatenate([y * sw, np.zeros(len(D2) + n_groups)])
        if monotone:
            lower = np.full(n_par, -np.inf)
            lower[1:n_basis] = 0.0
            x = lsq_linear(A, b, bounds=(lower, np.full(n_par, np.inf)), method="bvls").x
        else:
            x = np.linalg.lstsq(A, b, rcond=None)[0]
        c, offsets = L @ x[:n_basis], x[n_basis:]
        if not huber:
            break
        r = np.abs(y - B @ c - C @ offsets) * np.sqrt(w)  # residuals in sigmas of each point
        s = max(1.4826 * float(np.median(r)), 1e-12)
        new = np.minimum(1.0, huber * s / np.maximum(r, 1e-300))
        done = np.allclose(new, robust, atol=1e-3)
        robust = new
        if done:
            break
    fitted = B @ c + C @ offsets
    # covariance of the (unconstrained) penalised estimate, (X'WX + penalty + prior)^-1 in absolute
    # weights with X = [B C], scaled by the reduced chi-square (residual scatter against the weights);
    # the spline block is what a prediction needs (the offsets marginalised)
    wr = w * robust
    X = np.hstack([B, C])
    XtWX = X.T @ (X * wr[:, None])
    P = np.zeros((n_par, n_par))
    P[:n_basis, :n_basis] = smoothing * scale_w * D2.T @ D2
    P[n_basis:, n_basis:] = np.diag(prior * scale_w)
    try:
        M_inv = np.linalg.inv(XtWX + P)
        dof = len(z) - float(np.trace(M_inv @ XtWX))
    except np.linalg.LinAlgError:
        M_inv, dof = np.full((n_par, n_par), np.nan), 0.0
    leverage = np.einsum("ij,jk,ik->i", X, M_inv, X) * wr
    chi2 = float(np.sum(wr * (y - fitted) ** 2))
    cov = M_inv[:n_basis, :n_basis] * (chi2 / dof) if dof > 0.5 else np.full((n_basis, n_basis), np.nan)
    spline = BSpline(knots, c, degree, extrapolate=False)
    return SplineFit(spline, fitted, robust, cov, dof, offsets, leverage)
