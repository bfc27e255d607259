"""Schur elimination of the rays and the covariance of the camera unknowns (section 5).

The 2x2 block of every ray is eliminated with the Schur complement (all rays at once with numpy),
leaving a small dense reduced camera system of the rotations and intrinsics; its inverse at the
solution, scaled by the residual variance, is the covariance of every focal length and principal
point. The camera-ray coupling W is kept dense, per observation or per frame pair, whichever the
structure of the observations makes cheapest (choose_coupling).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise
from typing import Protocol

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from ptz_selfcal.bundle.observations import PreparedObservations
from ptz_selfcal.bundle.problem import Layout

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]


class Coupling(Protocol):
    """The camera-ray block W of the normal equations, in whichever storage suits the observations."""

    def schur(self, V_inv: Array) -> Array:
        """W V^-1 W^T (P, P)."""
        ...

    def times_rays(self, V_inv: Array, g_ray: Array) -> Array:
        """W V^-1 g (P,) for a (2, m) ray vector g."""
        ...

    def transpose_times(self, d_cam: Array) -> Array:
        """W^T d (2, m)."""
        ...


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


def _sparse_structure(obs: PreparedObservations, layout: Layout, n_rays: int) -> _SparseStructure:
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
    frame pair, so W V^-1 W^T is one small GEMM per frame pair (section 5's sparse structure: a ray of
    a keyframe pair touches only the shared intrinsics and two rotations, so a dense (P, 2, m) W is
    mostly zeros)."""

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


def _pair_structure(obs: PreparedObservations, layout: Layout, n_rays: int) -> _PairStructure:
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


# The fixed index structure of W for one solve: dense index, per-observation pairs or frame pairs.
CouplingStructure = IntArray | _SparseStructure | _PairStructure


@dataclass
class NormalEquations:
    """Normal equations in block form: U (P, P), the camera-ray coupling W, V (3, m) as
    (v00, v01, v11) per ray, gradients g_cam (P,) and g_ray (2, m)."""

    U: Array
    W: Coupling
    V: Array
    g_cam: Array
    g_ray: Array


def choose_coupling(obs: PreparedObservations, layout: Layout, n_rays: int, schur: str) -> CouplingStructure:
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


def _coupling_index(obs: PreparedObservations, layout: Layout, n_rays: int) -> IntArray:
    """(L, 2, N) flat index of each observation's entries in W (P+1, 2, m); fixed for a solve."""
    rows = layout.local[obs.frame_idx].T[:, None, :] * 2 + np.arange(2)[None, :, None]
    return rows * n_rays + obs.ray_idx[None, None, :]


def normal_equations(
    r: Array,
    J_cam: Array,
    J_ray: Array,
    obs: PreparedObservations,
    layout: Layout,
    n_rays: int,
    prior_grad: tuple[Array, Array],
    coupling: CouplingStructure,
) -> NormalEquations:
    """Gauss-Newton normal equations J^T J, J^T r in block form, W stored as `coupling` (the
    structure choose_coupling returned) says."""
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
        W: Coupling = _PairCoupling(W_obs, coupling, P1 - 1)
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
    return NormalEquations(U[:-1, :-1], W, V, g_cam[:-1], g_ray)


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


def schur_step(ne: NormalEquations, lam: float, D_cam: Array, D_ray: Array) -> tuple[Array, Array]:
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


def reduced_covariance(ne: NormalEquations) -> Array:
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
