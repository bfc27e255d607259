"""Optimal estimation by bundle adjustment (paper section 5).

MLE (eq. 26): minimise the sum of squared reprojection errors |x_ij - K_i R_i X_j|^2 over the
intrinsics K_i (per `IntrinsicsModel`), the rotations R_i (R_0 = I fixed: the gauge) and the rays X_j
(unit directions, two degrees of freedom each). MAP (eq. 27): the same with a Gaussian prior on the
principal point.

The solver is a sparse Levenberg-Marquardt: the 2x2 block of every ray is eliminated with the Schur
complement (all rays at once with numpy), leaving a small dense reduced camera system of the
rotations and intrinsics. Jacobians are analytic. The inverse of the reduced normal equations, scaled
by the residual variance, gives the 1-sigma uncertainty of every focal length and principal point.

Radial distortion (section 7, beyond the paper): with `distortion=True` every frame also has a
division-model coefficient lam_i about its principal point, on normalised coordinates n = K^-1 x
(camera/distortion.py's convention): the observation is the DISTORTED pixel
x_ij = K_i (s n),  n = proj(R_i X_j),  s = 2 / (1 + sqrt(1 - 4 lam_i |n|^2)),
so the principal point is also the distortion centre. In rotation-only data the two cannot be told
apart when they are estimated separately (a corrected homography's principal point follows the
assumed centre); tied together and fitted to the raw points, the distortion pattern itself pins the
centre (tests/unit/test_bundle.py, benchmarks/distortion.py). lam_i is either free per frame
(distortion="frame"), one coefficient shared by every frame (distortion="shared": a fixed lens, whose
distortion does not change between images) or on a curve of the focal length (distortion="curve",
section 7.2's second option, eq. 35 with lens/estimation.DistortionVsFocal's better-behaved
form): the corner shift s = c0 + c1 u + c2 u^2, u = f_ref / f_i, lam_i = -s / ((1 + s) (D / f_i)^2),
D the half-diagonal. Per-frame coefficients at long focal lengths trade off against the focal length
(both act at second order over a narrow field of view); the curve keeps three unknowns for the whole
zoom range.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from itertools import pairwise
from typing import Any

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import half_diagonal
from ptz_selfcal.camera.intrinsics import (
    ASPECT,
    CX,
    CY,
    SKEW,
    F,
    IntrinsicsModel,
    ParamMode,
    SelfCalibrationError,
    SelfCalibrationResult,
    image_centre,
    matrices_from_values,
    parameter_count,
    parameter_index,
    values_from_matrices,
)
from ptz_selfcal.selfcal.degeneracy import analyse_motion, single_axis_is_degenerate

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]

logger = logging.getLogger(__name__)


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


# ---------------------------------------------------------------------------------------------------
# Small vectorised helpers
# ---------------------------------------------------------------------------------------------------


def _rodrigues(omega: Array) -> Array:
    """(n, 3, 3) rotation matrices exp([omega]_x) of (n, 3) rotation vectors."""
    theta = np.linalg.norm(omega, axis=1)
    small = theta < 1e-12
    safe = np.where(small, 1.0, theta)
    k = omega / safe[:, None]
    Kx = _skew(k)
    s = np.where(small, 0.0, np.sin(theta))[:, None, None]
    c = np.where(small, 0.0, 1.0 - np.cos(theta))[:, None, None]
    return np.eye(3) + s * Kx + c * (Kx @ Kx)


def _skew(v: Array) -> Array:
    """(n, 3, 3) cross-product matrices [v]_x."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def _tangent_bases(X: Array) -> Array:
    """(m, 3, 2) orthonormal bases of the tangent planes of the unit sphere at the rays X."""
    x, y, z = X.T
    use_x = np.abs(x) < 0.9
    out = np.empty((len(X), 3, 2))
    # b1 = X x e_x = (0, z, -y) where |x| < 0.9, else X x e_y = (-z, 0, x); b2 = X x b1 (written out)
    out[:, 0, 0] = np.where(use_x, 0.0, -z)
    out[:, 1, 0] = np.where(use_x, z, 0.0)
    out[:, 2, 0] = np.where(use_x, -y, x)
    out[:, :, 0] /= np.sqrt(np.where(use_x, y * y + z * z, x * x + z * z))[:, None]
    a, b, c = out[:, 0, 0], out[:, 1, 0], out[:, 2, 0]
    out[:, 0, 1] = y * c - z * b
    out[:, 1, 1] = z * a - x * c
    out[:, 2, 1] = x * b - y * a
    return out


def initial_rays(obs: BundleObservations | _PreparedObservations, K: Array, R: Array, n_rays: int) -> Array:
    """Unit rays by back-projection X = R_i^T K_i^-1 x through each frame, averaged (section 5.1)."""
    # R_i^T K_i^-1 once per frame, then one 3x3 product per observation (a three-operand einsum over
    # the observations took 8x longer)
    M = np.swapaxes(R, 1, 2) @ np.linalg.inv(K)
    xh = np.column_stack([obs.xy, np.ones(len(obs.xy))])
    d = np.einsum("nij,nj->ni", M[obs.frame_idx], xh)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    X = np.stack([np.bincount(obs.ray_idx, weights=d[:, c], minlength=n_rays) for c in range(3)], axis=1)
    norm = np.linalg.norm(X, axis=1, keepdims=True)
    return X / np.where(norm > 0, norm, 1.0)


# ---------------------------------------------------------------------------------------------------
# The problem: parameter layout, residuals and Jacobians of eq. 26/27
# ---------------------------------------------------------------------------------------------------


@dataclass
class _Layout:
    """Where each camera unknown lives in the reduced system (index P is a dump for fixed entries)."""

    intr_index: IntArray  # (n, 5) parameter_index of the model (-1 = known)
    free_columns: IntArray  # intrinsic columns that are not KNOWN
    local: IntArray  # (n, L) global index of each frame's local unknowns: 3 rotation + free intrinsics
    n_params: int  # P
    prior_index: IntArray  # global indices of principal point unknowns under the prior
    prior_axis: IntArray  # 0 (cx) or 1 (cy) for each prior_index
    lam_index: IntArray | None = None  # (n,) global index of each frame's distortion coefficient
    curve_index: IntArray | None = None  # (degree + 1,) global indices of the lam(f) curve coefficients


def _layout(
    model: IntrinsicsModel,
    n_frames: int,
    use_prior: bool,
    distortion: bool = False,
    curve_size: int = 0,
    shared: bool = False,
) -> _Layout:
    intr_index = parameter_index(model, n_frames)
    n_intr = parameter_count(model, n_frames)
    free = np.array([c for c, mode in enumerate(model.modes) if mode is not ParamMode.KNOWN], dtype=np.intp)
    n_lam = curve_size if curve_size else ((1 if shared else n_frames) if distortion else 0)
    P = n_intr + 3 * (n_frames - 1) + n_lam
    rot = np.full((n_frames, 3), P, dtype=np.intp)
    rot[1:] = n_intr + np.arange(3 * (n_frames - 1)).reshape(-1, 3)
    local = np.concatenate([rot, intr_index[:, free]], axis=1)
    lam_index = curve_index = None
    first = n_intr + 3 * (n_frames - 1)
    if curve_size:  # the curve's coefficients, shared by every frame: the last local columns
        curve_index = (first + np.arange(curve_size)).astype(np.intp)
        local = np.concatenate([local, np.repeat(curve_index[None], n_frames, axis=0)], axis=1)
    elif distortion:  # one coefficient per frame (or one for all: a fixed lens), the last local column
        lam_index = (first + (np.zeros(n_frames) if shared else np.arange(n_frames))).astype(np.intp)
        local = np.concatenate([local, lam_index[:, None]], axis=1)
    prior_index = np.zeros(0, dtype=np.intp)
    prior_axis = np.zeros(0, dtype=np.intp)
    if use_prior and model.principal_point is not ParamMode.KNOWN:
        cx_ids = np.unique(intr_index[:, CX])
        cy_ids = np.unique(intr_index[:, CY])
        prior_index = np.concatenate([cx_ids, cy_ids])
        prior_axis = np.concatenate([np.zeros(len(cx_ids), np.intp), np.ones(len(cy_ids), np.intp)])
    return _Layout(intr_index, free, local, P, prior_index, prior_axis, lam_index, curve_index)


@dataclass
class _State:
    values: Array  # (n, 5) intrinsics table (f, aspect, skew, cx, cy)
    R: Array  # (n, 3, 3) world (= frame 0) to camera rotations
    X: Array  # (m, 3) unit rays
    lam: Array | None = None  # (n,) division coefficients (None: no distortion)
    curve: _Curve | None = None  # lam(f) when the coefficients follow a curve (lam = curve.lam(f))
    _bases: Array | None = None  # _tangent_bases(X) for the Jacobian and the step, computed once

    @property
    def bases(self) -> Array:
        if self._bases is None:
            self._bases = _tangent_bases(self.X)
        return self._bases


@dataclass(frozen=True)
class _Curve:
    """lam(f) through the corner shift s(u) = sum_k c_k u^k, u = f_ref / f (module docstring)."""

    coefficients: Array
    f_ref: float
    half_diagonal: float

    def lam(self, f: Array) -> Array:
        return self.derivatives(f)[0]

    def derivatives(self, f: Array) -> tuple[Array, Array, Array]:
        """lam (n,), d lam / d c (n, k) and d lam / d f (n,) at focal lengths f."""
        u = self.f_ref / f
        powers = u[:, None] ** np.arange(len(self.coefficients))[None]
        s = powers @ self.coefficients
        rho2 = (self.half_diagonal / f) ** 2
        lam = -s / ((1.0 + s) * rho2)
        dlam_ds = -1.0 / ((1.0 + s) ** 2 * rho2)
        ds_du = (powers[:, :-1] * np.arange(1, len(self.coefficients))[None]) @ self.coefficients[1:]
        # lam = -s f^2 / ((1 + s) D^2): 2 lam / f at constant s, plus s's own change through u = f_ref / f
        dlam_df = 2.0 * lam / f + dlam_ds * ds_du * (-u / f)
        return lam, dlam_ds[:, None] * powers, dlam_df

    @classmethod
    def fit(cls, f: Array, lam: Array, f_ref: float, half_diagonal: float, degree: int) -> _Curve:
        """Least-squares coefficients through per-frame (f, lam) (the starting point)."""
        u = f_ref / f
        rho2 = (half_diagonal / f) ** 2
        s = 1.0 / (1.0 + lam * rho2) - 1.0
        A = u[:, None] ** np.arange(degree + 1)[None]
        coefficients = np.linalg.lstsq(A, s, rcond=None)[0]
        return cls(coefficients, float(f_ref), float(half_diagonal))


# Per-observation arrays are component-major, (components, N) with the N observations sorted by frame,
# so that the hot loops are contiguous vector operations and one small GEMM per frame.


def _per_frame(R: Array, vectors: Array, bounds: IntArray) -> Array:
    """R_i applied to (3, ..., N) vectors, frame by frame (one GEMM per frame)."""
    out = np.empty_like(vectors)
    for i, (lo, hi) in enumerate(pairwise(bounds)):
        out[..., lo:hi] = (R[i] @ vectors[..., lo:hi].reshape(3, -1)).reshape(out[..., lo:hi].shape)
    return out


def _distortion_scale(a: Array, b: Array, lam: Array) -> tuple[Array, Array, Array]:
    """Division model on normalised coordinates: n_d = s n with s = 2 / (1 + sqrt(1 - 4 lam q)),
    q = |n|^2 (distortion.division_distort_radius); returns s, ds/dq and ds/dlam (NaN off the model)."""
    q = a * a + b * b
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.sqrt(1.0 - 4.0 * lam * q)
        s = 2.0 / (1.0 + t)
        k = s * s / t  # ds/dt = -s^2 / 2, dt/dq = -2 lam / t, dt/dlam = -2 q / t
    return s, k * lam, k * q


def _residuals(state: _State, obs: _PreparedObservations) -> tuple[Array, Array]:
    """Reprojection residuals (2, N) of eq. 26 and the camera-frame rays Y = R_i X_j (3, N)."""
    Y = _per_frame(state.R, state.X.T[:, obs.ray_idx], obs.bounds)
    f, gamma, s, cx, cy = state.values.T[:, obs.frame_idx]
    a, b = Y[0] / Y[2], Y[1] / Y[2]
    if state.lam is not None:  # distorted projection about the principal point
        scale = _distortion_scale(a, b, state.lam[obs.frame_idx])[0]
        a, b = a * scale, b * scale
    r = np.empty((2, len(a)))
    r[0] = gamma * f * a + s * f * b + cx - obs.xy_t[0]
    r[1] = f * b + cy - obs.xy_t[1]
    return r, Y


def _jacobians(state: _State, obs: _PreparedObservations, Y: Array, layout: _Layout) -> tuple[Array, Array]:
    """Analytic Jacobians of the residuals: camera part (2, L, N) and ray part (2, 2, N)."""
    f, gamma, s = state.values.T[: SKEW + 1, obs.frame_idx]
    Y0, Y1, Y2 = Y
    inv_z = 1.0 / Y2
    a, b = Y0 * inv_z, Y1 * inv_z
    J_cam = np.zeros((2, layout.local.shape[1], len(a)))
    if state.lam is None:
        # d(u, v)/dY of the pinhole projection with K of eq. 1 (row 1 has no Y0 term).
        A00, A01 = gamma * f * inv_z, s * f * inv_z
        A10, A11 = 0.0 * A00, f * inv_z
        ad, bd = a, b
    else:
        # distorted normalised point n_d = scale n: d(n_d)/dn = scale I + 2 ds/dq n n^T
        scale, ds_dq, ds_dlam = _distortion_scale(a, b, state.lam[obs.frame_idx])
        ad, bd = a * scale, b * scale
        D00, D01, D11 = scale + 2.0 * ds_dq * a * a, 2.0 * ds_dq * a * b, scale + 2.0 * ds_dq * b * b
        # d(u, v)/dn = [[gamma f, s f], [0, f]] D, then dn/dY = [[1, 0, -a], [0, 1, -b]] / Y2
        A00, A01 = f * inv_z * (gamma * D00 + s * D01), f * inv_z * (gamma * D01 + s * D11)
        A10, A11 = f * inv_z * D01, f * inv_z * D11
        du_dlam = np.stack([f * (gamma * a + s * b) * ds_dlam, f * b * ds_dlam])  # (2, N)
        if state.curve is None:
            J_cam[:, -1] = du_dlam
        else:
            _, dlam_dc, dlam_df = state.curve.derivatives(state.values[:, F])
            k = len(state.curve.coefficients)
            J_cam[:, -k:] = du_dlam[:, None, :] * dlam_dc[obs.frame_idx].T[None]
            df_extra = du_dlam * dlam_df[obs.frame_idx]  # f moves lam along the curve
    A02 = -(A00 * a + A01 * b)
    A12 = -(A10 * a + A11 * b)
    # Left update R <- exp([w]_x) R: dY/dw = -[Y]_x, so each row of dr/dw is Y x (row of A).
    J_cam[0, 0] = Y1 * A02 - Y2 * A01
    J_cam[0, 1] = Y2 * A00 - Y0 * A02
    J_cam[0, 2] = Y0 * A01 - Y1 * A00
    J_cam[1, 0] = Y1 * A12 - Y2 * A11
    J_cam[1, 1] = Y2 * A10 - Y0 * A12
    J_cam[1, 2] = Y0 * A11 - Y1 * A10
    for k, column in enumerate(layout.free_columns, start=3):
        if column == F:
            J_cam[0, k] = gamma * ad + s * bd
            J_cam[1, k] = bd
            if state.curve is not None:
                J_cam[:, k] += df_extra
        elif column == ASPECT:
            J_cam[0, k] = f * ad
        elif column == SKEW:
            J_cam[0, k] = f * bd
        elif column == CX:
            J_cam[0, k] = 1.0
        else:
            J_cam[1, k] = 1.0
    # Ray update X <- normalise(X + B d): dY/dd = R_i B_j (tangent basis B of the ray X_j).
    G = _per_frame(state.R, state.bases.transpose(1, 2, 0)[:, :, obs.ray_idx], obs.bounds)
    J_ray = np.empty((2, 2, len(a)))
    J_ray[0] = A00 * G[0] + A01 * G[1] + A02 * G[2]
    J_ray[1] = A10 * G[0] + A11 * G[1] + A12 * G[2]
    return J_cam, J_ray


def _prior_terms(
    state: _State, layout: _Layout, prior: tuple[Array, Array, float] | None
) -> tuple[Array, Array]:
    """Residuals of the principal point prior of eq. 27 and their (constant) derivatives."""
    if prior is None or len(layout.prior_index) == 0:
        return np.zeros(0), np.zeros(0)
    mean, sigma, noise = prior
    # Value of each prior unknown: the first frame holding it.
    frame = np.array(
        [
            np.flatnonzero(layout.intr_index[:, CX + ax] == p)[0]
            for p, ax in zip(layout.prior_index, layout.prior_axis)
        ]
    )
    value = state.values[frame, CX + layout.prior_axis]
    weight = noise / sigma[layout.prior_axis]
    return weight * (value - mean[layout.prior_axis]), weight


class _DenseCoupling:
    """W (P, 2, m) stored densely over rays: best when every ray is seen in many frames."""

    def __init__(self, W: Array) -> None:
        self.W = W

    def schur(self, V_inv: Array) -> Array:
        """W V^-1 W^T (P, P)."""
        P = len(self.W)
        return _times_blocks(self.W, V_inv).reshape(P, -1) @ self.W.reshape(P, -1).T

    def times_rays(self, V_inv: Array, g_ray: Array) -> Array:
        """W V^-1 g (P,) for a (2, m) ray vector g."""
        return self.W.reshape(len(self.W), -1) @ _blocks_times(V_inv, g_ray).ravel()

    def transpose_times(self, d_cam: Array) -> Array:
        """W^T d (2, m)."""
        return (self.W.reshape(len(self.W), -1).T @ d_cam).reshape(2, -1)


class _SparseCoupling:
    """W kept per observation (L, 2, N): best when rays are seen in few frames (keyframe pairs).

    W V^-1 W^T is accumulated over every ordered pair of observations of the same ray, one GEMM per
    pair of frames (pairs are pre-sorted by frame pair).
    """

    def __init__(self, W_obs: Array, structure: _SparseStructure, n_params: int, n_rays: int) -> None:
        self.W_obs = W_obs
        self.st = structure
        self.P = n_params
        self.m = n_rays

    def schur(self, V_inv: Array) -> Array:
        v = V_inv[:, self.st.ray]
        W0, W1 = self.W_obs[:, 0], self.W_obs[:, 1]
        WV = np.stack([W0 * v[0] + W1 * v[1], W0 * v[1] + W1 * v[2]], axis=2)  # (L, N, 2)
        W = np.stack([W0, W1], axis=2)
        A, B = WV[:, self.st.pair_first], W[:, self.st.pair_second]  # (L, Np, 2)
        L = len(W)
        blocks = np.empty((len(self.st.group_bounds) - 1, L, L))
        for g, (lo, hi) in enumerate(pairwise(self.st.group_bounds)):
            blocks[g] = A[:, lo:hi].reshape(L, -1) @ B[:, lo:hi].reshape(L, -1).T
        P1 = self.P + 1
        S = np.bincount(self.st.group_index.ravel(), weights=blocks.ravel(), minlength=P1 * P1)
        return S.reshape(P1, P1)[:-1, :-1]

    def times_rays(self, V_inv: Array, g_ray: Array) -> Array:
        Vg = _blocks_times(V_inv, g_ray)[:, self.st.ray]  # (2, N)
        contrib = self.W_obs[:, 0] * Vg[0] + self.W_obs[:, 1] * Vg[1]  # (L, N)
        return np.bincount(self.st.local.ravel(), weights=contrib.ravel(), minlength=self.P + 1)[:-1]

    def transpose_times(self, d_cam: Array) -> Array:
        d = np.append(d_cam, 0.0)[self.st.local]  # (L, N)
        q0 = np.einsum("ln,ln->n", self.W_obs[:, 0], d)
        q1 = np.einsum("ln,ln->n", self.W_obs[:, 1], d)
        return np.stack([np.bincount(self.st.ray, weights=q, minlength=self.m) for q in (q0, q1)])


@dataclass
class _SparseStructure:
    """Fixed index structure of the sparse Schur complement for one solve."""

    ray: IntArray  # (N,) ray of each observation
    local: IntArray  # (L, N) global unknown index of each observation's camera entries (P = fixed)
    pair_first: IntArray  # (Np,) first observation of every ordered pair sharing a ray, by frame pair
    pair_second: IntArray  # (Np,) second observation
    group_bounds: IntArray  # (G + 1,) pairs of one frame pair are pair_*[bounds[g]:bounds[g + 1]]
    group_index: IntArray  # (G, L, L) flat index of each frame pair's block in the (P+1, P+1) matrix


def _sparse_structure(obs: _PreparedObservations, layout: _Layout, n_rays: int) -> _SparseStructure:
    by_ray = np.argsort(obs.ray_idx, kind="stable")
    counts = np.bincount(obs.ray_idx, minlength=n_rays)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_of_obs = counts[obs.ray_idx[by_ray]]  # for each observation (in ray order): its ray's count
    first = np.repeat(by_ray, n_of_obs)
    group_start = np.repeat(starts[obs.ray_idx[by_ray]], n_of_obs)
    within = np.arange(len(first)) - np.repeat(np.cumsum(n_of_obs) - n_of_obs, n_of_obs)
    second = by_ray[group_start + within]
    # Sort the pairs by (frame of first, frame of second): one GEMM per frame pair.
    n_frames = len(layout.local)
    key = obs.frame_idx[first] * n_frames + obs.frame_idx[second]
    order = np.argsort(key, kind="stable")
    first, second, key = first[order], second[order], key[order]
    cut = np.flatnonzero(np.diff(key)) + 1
    bounds = np.concatenate([[0], cut, [len(key)]]).astype(np.intp)
    f1, f2 = np.divmod(key[bounds[:-1]], n_frames)
    P1 = layout.n_params + 1
    index = layout.local[f1][:, :, None] * P1 + layout.local[f2][:, None, :]
    local = np.ascontiguousarray(layout.local[obs.frame_idx].T)
    return _SparseStructure(obs.ray_idx, local, first, second, bounds, index)


class _PairCoupling:
    """W for rays seen in exactly two frames (every keyframe match is one): each ray's column of W
    lives on the union of its two frames' local unknowns (U <= 2L rows instead of P), rays grouped by
    frame pair, so W V^-1 W^T is one small GEMM per frame pair (section 5's sparse structure; the
    keyframe adjustment's reduced system is dominated by the shared intrinsics and two rotations per
    ray, and the dense (P, 2, m) W spent half an iteration on zeros)."""

    def __init__(self, W_obs: Array, structure: _PairStructure, n_params: int) -> None:
        st = structure
        U, m = st.union.shape
        W = np.bincount(st.scatter.ravel(), weights=W_obs.ravel(), minlength=U * m * 2)
        self.W = W.reshape(U, m, 2)  # rows of each ray's union, rays in frame-pair order
        self.st = structure
        self.P = n_params

    def schur(self, V_inv: Array) -> Array:
        v = V_inv[:, self.st.order]
        W0, W1 = self.W[..., 0], self.W[..., 1]
        WV = np.stack([W0 * v[0] + W1 * v[1], W0 * v[1] + W1 * v[2]], axis=2)  # (U, m, 2)
        U = len(self.W)
        bounds = self.st.group_bounds
        blocks = np.empty((len(bounds) - 1, U, U))
        for g, (lo, hi) in enumerate(pairwise(bounds)):
            blocks[g] = WV[:, lo:hi].reshape(U, -1) @ self.W[:, lo:hi].reshape(U, -1).T
        P1 = self.P + 1
        S = np.bincount(self.st.group_index.ravel(), weights=blocks.ravel(), minlength=P1 * P1)
        return S.reshape(P1, P1)[:-1, :-1]

    def times_rays(self, V_inv: Array, g_ray: Array) -> Array:
        Vg = _blocks_times(V_inv, g_ray)[:, self.st.order]  # (2, m)
        contrib = self.W[..., 0] * Vg[0] + self.W[..., 1] * Vg[1]  # (U, m)
        return np.bincount(self.st.union.ravel(), weights=contrib.ravel(), minlength=self.P + 1)[:-1]

    def transpose_times(self, d_cam: Array) -> Array:
        d = np.append(d_cam, 0.0)[self.st.union]  # (U, m)
        out = np.empty((2, d.shape[1]))
        out[:, self.st.order] = np.einsum("umc,um->cm", self.W, d)
        return out


@dataclass
class _PairStructure:
    """Fixed index structure of _PairCoupling for one solve (every ray seen in exactly two frames)."""

    order: IntArray  # (m,) rays sorted by frame pair (position r holds ray order[r])
    union: IntArray  # (U, m) global unknown index of each union row of each sorted ray (P = none)
    scatter: IntArray  # (L, 2, N) flat index of each observation's W entry in the (U, m, 2) array
    group_bounds: IntArray  # (G + 1,) sorted rays of frame pair g are [bounds[g], bounds[g + 1])
    group_index: IntArray  # (G, U, U) flat index of each frame pair's block in the (P+1, P+1) matrix


def _pair_structure(obs: _PreparedObservations, layout: _Layout, n_rays: int) -> _PairStructure:
    by_ray = np.argsort(obs.ray_idx, kind="stable").reshape(n_rays, 2)  # the two observations of each
    frames = obs.frame_idx[by_ray]
    swap = frames[:, 0] > frames[:, 1]
    by_ray[swap] = by_ray[swap, ::-1]
    frames[swap] = frames[swap, ::-1]
    n_frames, L = layout.local.shape
    key = frames[:, 0] * n_frames + frames[:, 1]
    order = np.argsort(key, kind="stable")
    key = key[order]
    cut = np.flatnonzero(np.diff(key)) + 1
    bounds = np.concatenate([[0], cut, [len(key)]]).astype(np.intp)
    P = layout.n_params
    U = 2 * L
    G = len(bounds) - 1
    unions = np.full((G, U), P, dtype=np.intp)
    second_pos = np.empty((G, L), dtype=np.intp)
    for g, k in enumerate(key[bounds[:-1]]):
        a, b = divmod(int(k), n_frames)
        unions[g, :L] = layout.local[a]
        row = {int(v): i for i, v in enumerate(layout.local[a]) if v != P}  # shared unknowns merge
        nxt = L
        for i, v in enumerate(layout.local[b]):
            if int(v) != P and int(v) in row:
                second_pos[g, i] = row[int(v)]
            else:
                unions[g, nxt], second_pos[g, i] = v, nxt
                nxt += 1
    group_of = np.repeat(np.arange(G), np.diff(bounds))  # (m,) group of each sorted ray
    rank = np.empty(n_rays, dtype=np.intp)
    rank[order] = np.arange(n_rays)
    first, second = by_ray[:, 0], by_ray[:, 1]
    pos = np.empty((L, len(obs.frame_idx)), dtype=np.intp)
    pos[:, first] = np.arange(L)[:, None]
    pos[:, second] = second_pos[group_of[rank]].T
    r = rank[obs.ray_idx]  # sorted position of each observation's ray
    scatter = (pos[:, None, :] * n_rays + r[None, None, :]) * 2 + np.arange(2)[None, :, None]
    P1 = P + 1
    group_index = unions[:, :, None] * P1 + unions[:, None, :]
    return _PairStructure(order, np.ascontiguousarray(unions[group_of].T), scatter, bounds, group_index)


@dataclass
class _Normal:
    """Normal equations in block form: U (P, P), the camera-ray coupling W, V (3, m) as
    (v00, v01, v11) per ray, gradients g_cam (P,) and g_ray (2, m)."""

    U: Array
    W: _DenseCoupling | _SparseCoupling | _PairCoupling
    V: Array
    g_cam: Array
    g_ray: Array


def _choose_coupling(
    obs: _PreparedObservations, layout: _Layout, n_rays: int, schur: str
) -> IntArray | _SparseStructure | _PairStructure:
    """Dense W for long tracks, per-observation-pair accumulation for short ones; rays seen in exactly
    two frames (keyframe pairs) by frame pair (_PairCoupling) when that is narrower than P.

    Cost model: the dense product is P^2 2m flops in BLAS; the sparse one ~50x more per entry of its
    L^2 sum_j n_j^2 pair blocks (gather, multiply, scatter).
    """
    if schur not in ("auto", "dense", "sparse", "pair"):
        raise ValueError(f"schur must be 'auto', 'dense', 'sparse' or 'pair', not {schur!r}")
    P, L = layout.n_params, layout.local.shape[1]
    counts = np.bincount(obs.ray_idx, minlength=n_rays)
    two_views = bool(np.all(counts == 2))
    if schur == "pair" and not two_views:
        raise ValueError("schur 'pair' needs every ray seen in exactly two frames")
    if schur == "pair" or (schur == "auto" and two_views and 2 * L < P):
        return _pair_structure(obs, layout, n_rays)
    pairs = float(np.sum(counts.astype(float) ** 2))
    sparse = schur == "sparse" or (schur == "auto" and 50.0 * pairs * L * L < 2.0 * P * P * n_rays)
    return _sparse_structure(obs, layout, n_rays) if sparse else _coupling_index(obs, layout, n_rays)


def _coupling_index(obs: _PreparedObservations, layout: _Layout, n_rays: int) -> IntArray:
    """(L, 2, N) flat index of each observation's entries in W (P+1, 2, m); fixed for a solve."""
    rows = layout.local[obs.frame_idx].T[:, None, :] * 2 + np.arange(2)[None, :, None]
    return rows * n_rays + obs.ray_idx[None, None, :]


def _normal_equations(
    r: Array,
    J_cam: Array,
    J_ray: Array,
    obs: _PreparedObservations,
    layout: _Layout,
    n_rays: int,
    prior_grad: tuple[Array, Array],
    coupling: IntArray | _SparseStructure | _PairStructure,
) -> _Normal:
    """Gauss-Newton normal equations J^T J, J^T r in block form; coupling is the dense W index of
    `_coupling_index` or the structure of `_sparse_structure`."""
    L = layout.local.shape[1]
    P1 = layout.n_params + 1
    # Camera blocks: every observation of frame i shares the frame's local index list (GEMMs per frame).
    U_frame = np.empty((len(obs.bounds) - 1, L, L))
    g_frame = np.empty((len(obs.bounds) - 1, L))
    for i, (lo, hi) in enumerate(pairwise(obs.bounds)):
        J0, J1 = J_cam[0, :, lo:hi], J_cam[1, :, lo:hi]
        U_frame[i] = J0 @ J0.T + J1 @ J1.T
        g_frame[i] = J0 @ r[0, lo:hi] + J1 @ r[1, lo:hi]
    loc = layout.local
    rows = np.repeat(loc[:, :, None], L, axis=2)
    cols = np.repeat(loc[:, None, :], L, axis=1)
    U = np.bincount((rows * P1 + cols).ravel(), weights=U_frame.ravel(), minlength=P1 * P1).reshape(P1, P1)
    g_cam = np.bincount(loc.ravel(), weights=g_frame.ravel(), minlength=P1)
    # Ray blocks (2x2 each, stored as v00, v01, v11) and the camera-ray coupling W (P+1, 2, m).
    ray = obs.ray_idx
    (t00, t01), (t10, t11) = J_ray  # J_ray[row, tangent direction]
    V = np.stack(
        [
            np.bincount(ray, weights=t00 * t00 + t10 * t10, minlength=n_rays),
            np.bincount(ray, weights=t00 * t01 + t10 * t11, minlength=n_rays),
            np.bincount(ray, weights=t01 * t01 + t11 * t11, minlength=n_rays),
        ]
    )
    g_ray = np.stack(
        [
            np.bincount(ray, weights=t00 * r[0] + t10 * r[1], minlength=n_rays),
            np.bincount(ray, weights=t01 * r[0] + t11 * r[1], minlength=n_rays),
        ]
    )
    W_obs = J_cam[0][:, None, :] * J_ray[0][None] + J_cam[1][:, None, :] * J_ray[1][None]
    if isinstance(coupling, _PairStructure):
        W: _DenseCoupling | _SparseCoupling | _PairCoupling = _PairCoupling(W_obs, coupling, P1 - 1)
    elif isinstance(coupling, _SparseStructure):
        W = _SparseCoupling(W_obs, coupling, P1 - 1, n_rays)
    else:
        dense = np.bincount(coupling.ravel(), weights=W_obs.ravel(), minlength=P1 * 2 * n_rays)
        W = _DenseCoupling(dense.reshape(P1, 2, n_rays)[:-1])
    # MAP prior of eq. 27: diagonal Gauss-Newton terms on the principal point unknowns.
    prior_r, prior_J = prior_grad
    if len(prior_r):
        U[layout.prior_index, layout.prior_index] += prior_J**2
        g_cam[layout.prior_index] += prior_J * prior_r
    return _Normal(U[:-1, :-1], W, V, g_cam[:-1], g_ray)


def _inverse_blocks(V: Array) -> Array:
    """Inverses of the symmetric 2x2 ray blocks, (3, m) components (v00, v01, v11) in and out."""
    det = V[0] * V[2] - V[1] * V[1]
    return np.stack([V[2], -V[1], V[0]]) / det


def _times_blocks(W: Array, V_inv: Array) -> Array:
    """(P, 2, m) W times the symmetric 2x2 blocks of every ray."""
    out = np.empty_like(W)
    out[:, 0] = W[:, 0] * V_inv[0] + W[:, 1] * V_inv[1]
    out[:, 1] = W[:, 0] * V_inv[1] + W[:, 1] * V_inv[2]
    return out


def _blocks_times(V_inv: Array, g: Array) -> Array:
    """The symmetric 2x2 block of every ray times a (2, m) ray vector."""
    return np.stack([V_inv[0] * g[0] + V_inv[1] * g[1], V_inv[1] * g[0] + V_inv[2] * g[1]])


def _solve_reduced(S: Array, rhs: Array) -> Array:
    """Solve the symmetric reduced camera system with Jacobi scaling (Cholesky, lstsq fallback)."""
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    Ss = S / d[:, None] / d[None, :]
    try:
        x = scipy.linalg.cho_solve(
            scipy.linalg.cho_factor(Ss, check_finite=False), rhs / d, check_finite=False
        )
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(Ss, rhs / d, rcond=None)[0]
    return x / d


def _schur_step(ne: _Normal, lam: float, D_cam: Array, D_ray: Array) -> tuple[Array, Array]:
    """Damped Gauss-Newton step (U + lam D) dc + W dp = -g_c, W^T dc + (V + lam D) dp = -g_p.

    Returns d_cam (P,) and d_ray (m, 2).
    """
    V = ne.V.copy()
    V[0] += lam * D_ray[0]
    V[2] += lam * D_ray[1]
    V_inv = _inverse_blocks(V)
    S = ne.U - ne.W.schur(V_inv)
    S[np.diag_indices_from(S)] += lam * D_cam
    d_cam = _solve_reduced(S, -ne.g_cam + ne.W.times_rays(V_inv, ne.g_ray))
    d_ray = -_blocks_times(V_inv, ne.g_ray + ne.W.transpose_times(d_cam))
    return d_cam, d_ray.T


def _reduced_covariance(ne: _Normal) -> Array:
    """Inverse of the undamped reduced camera system (rays marginalised), unit residual variance."""
    S = ne.U - ne.W.schur(_inverse_blocks(ne.V))
    P = len(S)
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    Ss = S / d[:, None] / d[None, :]
    try:
        inv = scipy.linalg.cho_solve(
            scipy.linalg.cho_factor(Ss, check_finite=False), np.eye(P), check_finite=False
        )
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(Ss)
    return inv / d[:, None] / d[None, :]


def _apply_step(state: _State, d_cam: Array, d_ray: Array, layout: _Layout, f_min: float) -> _State:
    """New state after a step: intrinsics additive, rotations on the left, rays on the sphere."""
    d = np.append(d_cam, 0.0)
    values = state.values.copy()
    free = layout.free_columns
    idx = layout.intr_index[:, free]
    values[:, free] += d[np.where(idx >= 0, idx, len(d) - 1)]
    values[:, F] = np.maximum(values[:, F], f_min)
    omega = d[layout.local[:, :3]]
    R = _rodrigues(omega) @ state.R
    B = state.bases
    X = state.X + B[:, :, 0] * d_ray[:, :1] + B[:, :, 1] * d_ray[:, 1:]
    X /= np.linalg.norm(X, axis=1, keepdims=True)
    lam, curve = state.lam, state.curve
    if curve is not None and layout.curve_index is not None:
        curve = replace(curve, coefficients=curve.coefficients + d[layout.curve_index])
        lam = curve.lam(values[:, F])
    elif lam is not None and layout.lam_index is not None:
        lam = lam + d[layout.lam_index]
    return _State(values, R, X, lam, curve)


# ---------------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------------


@dataclass
class _PreparedObservations:
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


def _prepare(observations: ObservationsLike, n_frames: int) -> tuple[_PreparedObservations, IntArray]:
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
    prepared = _PreparedObservations(frame_idx, compact[order], xy, starts, np.ascontiguousarray(xy.T))
    return prepared, kept_ids


def bundle_adjust(
    observations: ObservationsLike,
    K_init: ArrayLike,
    R_init: ArrayLike,
    image_size: tuple[int, int],
    model: IntrinsicsModel,
    *,
    rays_init: ArrayLike | None = None,
    pp_prior: tuple[ArrayLike, ArrayLike] | None = None,
    noise_sigma: float = 1.0,
    max_iterations: int = 50,
    f_min: float | None = None,
    tolerance: float = 1e-10,
    analyse: bool = True,
    schur: str = "auto",
    distortion: bool | str = False,
    lam_init: ArrayLike | None = None,
    curve_degree: int = 2,
    initial_damping: float = 1e-6,
    max_focal_change: float | None = None,
    uncertainty: bool = True,
) -> SelfCalibrationResult:
    """MLE (eq. 26) or, with pp_prior = (mean (2,), sigma (2,)) in pixels, MAP (eq. 27) calibration.

    observations: BundleObservations or (frame_idx (N,), ray_idx (N,), xy (N, 2)); rays seen in fewer
    than two frames are ignored. K_init, R_init: (n, 3, 3) starting intrinsics and world-to-camera
    rotations (e.g. from `lm_selfcalibration`); the result's R are relative to frame 0 (R[0] = I, the
    gauge). rays_init: (max ray id + 1, 3) starting rays in the frame of R_init, default back-projected.
    noise_sigma: the image noise level, which weighs the prior against the reprojection errors
    (eq. 27 as printed is noise_sigma = 1 px). f_min: lower bound on the focal length (default a tenth
    of the image width). Uncertainties are 1-sigma from the reduced normal equations scaled by the
    residual variance; `residual` is the rms reprojection error in pixels. With analyse, the result
    carries a MotionReport (section 6) and ok is False when the motion is not well posed.
    schur: how the rays are eliminated, 'dense' (rays seen in many frames), 'sparse' (rays seen in
    few frames), 'pair' (every ray seen in exactly two frames: keyframe pairs) or 'auto' ('pair'
    where it applies and is narrower than P, else by a cost estimate); the result is the same.
    distortion: the observations are DISTORTED pixels; a division coefficient per frame about its
    principal point is estimated with everything else (module docstring): True or "frame", free per
    frame; "curve", on the lam(f) curve of degree curve_degree; "shared", ONE coefficient for every
    frame (a fixed lens: constant f, one distortion). Starting from lam_init ((n,), default 0; its mean
    for "shared"); the result's info carries "lam" (n,), "sigma_lam" (n,) and, for a curve,
    "distortion_curve" (coefficients, f_ref, half-diagonal).
    initial_damping: LM's starting damping (relative to the diagonal of the normal equations). The
    keyframe adjustment (online/session) starts at 1e-9: from 1e-6 it crept along a pan's
    near-ambiguity (section 6.2), the damping falling tenfold per accepted iteration before the step
    could follow the flat direction (real sets: 1.5x the iterations, same solution).
    max_focal_change: stop (message "focal length moved beyond max_focal_change") once an accepted
    step leaves a focal length further than this fraction from its start: for a caller that only
    asks whether f moves (calibration_state's lens-model check), not where it ends.
    uncertainty: False skips the covariance (an undamped Jacobian and reduced system at the
    solution, about one more iteration): sigma_f, sigma_pp, sigma_lam and "covariance" are NaN.
    """
    if distortion not in (False, True, "frame", "curve", "shared"):
        raise ValueError(f"distortion must be False, True, 'frame', 'curve' or 'shared', not {distortion!r}")
    K0 = np.asarray(K_init, dtype=float).reshape(-1, 3, 3)
    R_in = np.asarray(R_init, dtype=float).reshape(-1, 3, 3)
    n = len(K0)
    if len(R_in) != n:
        raise ValueError("K_init and R_init differ in frame count")
    obs, ray_ids = _prepare(observations, n)
    n_rays = len(ray_ids)
    if n_rays == 0:
        raise SelfCalibrationError("no ray is seen in two frames")
    f_min = 0.1 * image_size[0] if f_min is None else float(f_min)

    # Gauge: express everything in frame 0's camera frame so that R_0 = I stays fixed.
    R = np.einsum("nij,kj->nik", R_in, R_in[0])
    values = values_from_matrices(K0)
    index = parameter_index(model, n)
    known = model.known_values(image_size)
    for c in range(5):
        if (index[:, c] < 0).all():
            values[:, c] = known[c]
        else:  # constant unknowns start at their mean over frames
            for p in np.unique(index[:, c]):
                values[index[:, c] == p, c] = values[index[:, c] == p, c].mean()
    lam = None
    if distortion:
        lam = np.zeros(n) if lam_init is None else np.asarray(lam_init, dtype=float).reshape(n).copy()
        if not np.all(np.isfinite(lam)):
            raise ValueError("lam_init must be finite")
        if distortion == "shared":  # one lens for every frame: one coefficient, started at the mean
            lam[:] = lam.mean()
    if rays_init is None:
        Kmat = matrices_from_values(values)
        X = initial_rays(obs if lam is None else _undistorted(obs, Kmat, lam), Kmat, R, n_rays)
    else:
        X = np.asarray(rays_init, dtype=float)[ray_ids] @ R_in[0].T
        X /= np.linalg.norm(X, axis=1, keepdims=True)
    curve = None
    if distortion == "curve":
        assert lam is not None
        f0 = values[:, F]
        curve = _Curve.fit(f0, lam, float(f0.min()), half_diagonal(*image_size), int(curve_degree))
        lam = curve.lam(f0)
    state = _State(values, R, X, lam, curve)

    prior = None
    if pp_prior is not None:
        mean = np.asarray(pp_prior[0], dtype=float).reshape(2)
        sigma = np.asarray(pp_prior[1], dtype=float).reshape(2)
        prior = (mean, sigma, float(noise_sigma))
    layout = _layout(
        model,
        n,
        prior is not None,
        bool(distortion),
        0 if curve is None else curve_degree + 1,
        shared=distortion == "shared",
    )
    result = _levenberg_marquardt(
        state,
        obs,
        layout,
        prior,
        n_rays,
        ray_ids,
        max_iterations,
        f_min,
        tolerance,
        model,
        schur,
        initial_damping,
        max_focal_change,
        uncertainty,
    )
    if analyse:
        result.motion = analyse_motion(
            result.R,
            result.K,
            image_size,
            sigma_f=result.sigma_f,
            single_axis_degenerate=single_axis_is_degenerate(model),
        )
        if result.ok and not result.motion.well_posed:
            result.ok = False
            result.message = f"motion not well posed: {result.motion.status} ({result.motion.message})"
    return result


def _undistorted(obs: _PreparedObservations, K: Array, lam: Array) -> _PreparedObservations:
    """The observations undistorted with the frames' coefficients (division model, closed form)."""
    xh = np.column_stack([obs.xy, np.ones(len(obs.xy))])
    n = np.einsum("nij,nj->ni", np.linalg.inv(K)[obs.frame_idx], xh)[:, :2]
    n /= (1.0 + lam[obs.frame_idx] * np.sum(n * n, axis=1))[:, None]
    xy = np.einsum("nij,nj->ni", K[obs.frame_idx], np.column_stack([n, np.ones(len(n))]))[:, :2]
    return replace(obs, xy=xy, xy_t=np.ascontiguousarray(xy.T))


def _cost(r: Array, prior_r: Array) -> float:
    return float(np.sum(r * r) + np.sum(prior_r * prior_r))


def _levenberg_marquardt(
    state: _State,
    obs: _PreparedObservations,
    layout: _Layout,
    prior: tuple[Array, Array, float] | None,
    n_rays: int,
    ray_ids: IntArray,
    max_iterations: int,
    f_min: float,
    tolerance: float,
    model: IntrinsicsModel,
    schur: str,
    initial_damping: float,
    max_focal_change: float | None,
    uncertainty: bool,
) -> SelfCalibrationResult:
    """Sparse LM with Marquardt's diagonal damping and Nielsen's damping update."""
    r, Y = _residuals(state, obs)
    prior_terms = _prior_terms(state, layout, prior)
    cost = _cost(r, prior_terms[0])
    initial_cost = cost
    exact_cost = 1e-20 * r.shape[1]  # rms below 1e-10 px: nothing left to fit
    coupling = _choose_coupling(obs, layout, n_rays, schur)
    lam, nu = float(initial_damping), 2.0
    f_start = state.values[:, F].copy()
    iterations, message = 0, "maximum iterations reached"
    ne = None
    for iterations in range(1, max_iterations + 1):
        J_cam, J_ray = _jacobians(state, obs, Y, layout)
        ne = _normal_equations(r, J_cam, J_ray, obs, layout, n_rays, prior_terms, coupling)
        D_cam = np.maximum(np.diag(ne.U), 1e-12 * max(np.diag(ne.U).max(), 1e-300))
        D_ray = np.maximum(ne.V[[0, 2]], 1e-12)  # (2, m) diagonal of the ray blocks
        accepted = False
        while not accepted:
            d_cam, d_ray = _schur_step(ne, lam, D_cam, D_ray)
            candidate = _apply_step(state, d_cam, d_ray, layout, f_min)
            r_new, Y_new = _residuals(candidate, obs)
            prior_new = _prior_terms(candidate, layout, prior)
            cost_new = _cost(r_new, prior_new[0])
            # Predicted decrease of the quadratic model (cost = |r|^2).
            predicted = float(
                d_cam @ (lam * D_cam * d_cam - ne.g_cam)
                + np.sum(d_ray.T * (lam * D_ray * d_ray.T - ne.g_ray))
            )
            rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
            if predicted <= 0.1 * tolerance * cost:  # the model promises nothing more: converged
                break
            if np.isfinite(cost_new) and rho > 0:
                accepted = True
                lam *= max(0.1, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
            else:
                lam *= nu
                nu *= 2.0
                if lam > 1e16:
                    break
        if not accepted:
            message = "converged" if cost <= exact_cost or lam <= 1e16 else "no further decrease"
            break
        decrease = cost - cost_new
        logger.debug("BA iteration %d: cost %.12g -> %.12g, lambda %.3g", iterations, cost, cost_new, lam)
        state, r, Y, prior_terms, cost = candidate, r_new, Y_new, prior_new, cost_new
        if decrease <= tolerance * cost or cost <= exact_cost:
            message = "converged"
            break
        if (
            max_focal_change is not None
            and np.max(np.abs(state.values[:, F] / f_start - 1.0)) > max_focal_change
        ):
            message = "focal length moved beyond max_focal_change"
            break

    # Uncertainty from the undamped reduced system at the solution (rays marginalised).
    n_obs = r.shape[1]
    dof = max(2 * n_obs + len(prior_terms[0]) - layout.n_params - 2 * n_rays, 1)
    variance = cost / dof
    if uncertainty:
        J_cam, J_ray = _jacobians(state, obs, Y, layout)
        ne = _normal_equations(r, J_cam, J_ray, obs, layout, n_rays, prior_terms, coupling)
        cov = _reduced_covariance(ne) * variance
    else:
        cov = np.full((layout.n_params, layout.n_params), np.nan)
    sd = np.append(np.sqrt(np.maximum(np.diag(cov), 0.0)), 0.0)
    idx = np.where(layout.intr_index >= 0, layout.intr_index, len(sd) - 1)
    sigma_f = sd[idx[:, F]]
    sigma_pp = np.column_stack([sd[idx[:, CX]], sd[idx[:, CY]]])
    extra: dict[str, Any] = {}
    if state.lam is not None and layout.lam_index is not None:
        extra = {"lam": state.lam.copy(), "sigma_lam": sd[layout.lam_index]}
    elif state.curve is not None and layout.curve_index is not None:
        # sigma of each frame's lam through the curve: J cov J^T with J = d lam / d (c, f)
        _, dlam_dc, dlam_df = state.curve.derivatives(state.values[:, F])
        idx_f = np.where(layout.intr_index[:, F] >= 0, layout.intr_index[:, F], -1)
        var = []
        for i in range(len(dlam_dc)):
            cols = list(layout.curve_index) + ([int(idx_f[i])] if idx_f[i] >= 0 else [])
            g = np.append(dlam_dc[i], dlam_df[i]) if idx_f[i] >= 0 else dlam_dc[i]
            var.append(float(g @ cov[np.ix_(cols, cols)] @ g))
        extra = {
            "lam": state.lam.copy(),
            "sigma_lam": np.sqrt(np.maximum(var, 0.0)),
            "distortion_curve": (
                state.curve.coefficients.copy(),
                state.curve.f_ref,
                state.curve.half_diagonal,
            ),
        }

    rays = np.full((int(ray_ids.max()) + 1, 3), np.nan)
    rays[ray_ids] = state.X
    residual = float(np.sqrt(np.mean(r[0] ** 2 + r[1] ** 2)))
    ok = bool(np.isfinite(cost) and (state.values[:, F] > f_min).all())
    if not ok:
        message = "focal length at its lower bound" if np.isfinite(cost) else "non-finite cost"
    method = "map" if prior is not None else "mle"
    return SelfCalibrationResult(
        K=matrices_from_values(state.values),
        R=state.R,
        sigma_f=sigma_f,
        sigma_pp=sigma_pp,
        residual=residual,
        method=method,
        iterations=iterations,
        ok=ok,
        message=message,
        cost=cost,
        info={
            "rays": rays,
            "covariance": cov,
            "residual_variance": variance,
            "initial_cost": initial_cost,
            "n_observations": n_obs,
            "n_rays": n_rays,
            "model": model,
            **extra,
        },
    )


def default_pp_prior(image_size: tuple[int, int], sigma: float = 10.0) -> tuple[Array, Array]:
    """The paper's prior of eq. 27: the principal point near the image centre, sigma pixels each way."""
    return np.array(image_centre(image_size)), np.array([sigma, sigma])
