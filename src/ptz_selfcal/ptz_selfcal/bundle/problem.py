"""The problem of eq. 26/27: parameter layout, state, the lam(f) curve, residuals and analytic Jacobians.

Radial distortion (section 7, beyond the paper): with bundle_adjust's `distortion` every frame also
has a division-model coefficient lam_i about its principal point, on normalised coordinates n = K^-1 x
(camera/distortion.py's convention): the observation is the DISTORTED pixel
x_ij = K_i (s n),  n = proj(R_i X_j),  s = 2 / (1 + sqrt(1 - 4 lam_i |n|^2)),
so the principal point is also the distortion centre. In rotation-only data the two cannot be told
apart when they are estimated separately (a corrected homography's principal point follows the
assumed centre); tied together and fitted to the raw points, the distortion pattern itself pins the
centre (tests/unit/test_bundle.py, benchmarks/distortion.py). lam_i is either free per frame
(distortion="frame"), one coefficient shared by every frame (distortion="shared": a fixed lens, whose
distortion does not change between images) or on a curve of the focal length (distortion="curve",
section 7.2's second option, eq. 35 with lens/curve.DistortionVsFocal's better-behaved
form): the corner shift s = c0 + c1 u + c2 u^2, u = f_ref / f_i, lam_i = -s / ((1 + s) (D / f_i)^2),
D the half-diagonal. Per-frame coefficients at long focal lengths trade off against the focal length
(both act at second order over a narrow field of view); the curve keeps three unknowns for the whole
zoom range.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.bundle.observations import PreparedObservations
from ptz_selfcal.camera.distortion import (
    corner_shift_of_lambda,
    lambda_of_corner_shift,
    lambda_of_corner_shift_derivative,
)
from ptz_selfcal.camera.intrinsics import (
    ASPECT,
    CX,
    CY,
    SKEW,
    F,
    IntrinsicsModel,
    ParamMode,
    parameter_count,
    parameter_index,
)

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class PrincipalPointPrior:
    """The Gaussian prior of eq. 27: principal point mean (2,) and sigma (2,) in pixels, weighed
    against the reprojection errors by the image noise level noise_sigma (1 px as eq. 27 is printed)."""

    mean: Array
    sigma: Array
    noise_sigma: float


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


@dataclass
class Layout:
    """Where each camera unknown lives in the reduced system (index P is a dump for fixed entries)."""

    intr_index: IntArray  # (n, 5) parameter_index of the model (-1 = known)
    free_columns: IntArray  # intrinsic columns that are not KNOWN
    local: IntArray  # (n, L) global index of each frame's local unknowns: 3 rotation + free intrinsics
    n_params: int  # P
    prior_index: IntArray  # global indices of principal point unknowns under the prior
    prior_axis: IntArray  # 0 (cx) or 1 (cy) for each prior_index
    lam_index: IntArray | None = None  # (n,) global index of each frame's distortion coefficient
    curve_index: IntArray | None = None  # (degree + 1,) global indices of the lam(f) curve coefficients


def parameter_layout(
    model: IntrinsicsModel,
    n_frames: int,
    use_prior: bool,
    distortion: bool = False,
    curve_size: int = 0,
    shared: bool = False,
) -> Layout:
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
    return Layout(intr_index, free, local, P, prior_index, prior_axis, lam_index, curve_index)


@dataclass
class State:
    values: Array  # (n, 5) intrinsics table (f, aspect, skew, cx, cy)
    R: Array  # (n, 3, 3) world (= frame 0) to camera rotations
    X: Array  # (m, 3) unit rays
    lam: Array | None = None  # (n,) division coefficients (None: no distortion)
    curve: LamCurve | None = None  # lam(f) when the coefficients follow a curve (lam = curve.lam(f))
    _bases: Array | None = None  # _tangent_bases(X) for the Jacobian and the step, computed once

    @property
    def bases(self) -> Array:
        if self._bases is None:
            self._bases = _tangent_bases(self.X)
        return self._bases


@dataclass(frozen=True)
class LamCurve:
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
        rho = self.half_diagonal / f
        lam = lambda_of_corner_shift(s, rho)
        dlam_ds = lambda_of_corner_shift_derivative(s, rho)
        ds_du = (powers[:, :-1] * np.arange(1, len(self.coefficients))[None]) @ self.coefficients[1:]
        # lam = -s f^2 / ((1 + s) D^2): 2 lam / f at constant s, plus s's own change through u = f_ref / f
        dlam_df = 2.0 * lam / f + dlam_ds * ds_du * (-u / f)
        return lam, dlam_ds[:, None] * powers, dlam_df

    @classmethod
    def fit(cls, f: Array, lam: Array, f_ref: float, half_diagonal: float, degree: int) -> LamCurve:
        """Least-squares coefficients through per-frame (f, lam) (the starting point)."""
        u = f_ref / f
        s = corner_shift_of_lambda(lam, half_diagonal / f)
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


def residuals(state: State, obs: PreparedObservations) -> tuple[Array, Array]:
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


def jacobians(state: State, obs: PreparedObservations, Y: Array, layout: Layout) -> tuple[Array, Array]:
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


def prior_residuals(state: State, layout: Layout, prior: PrincipalPointPrior | None) -> tuple[Array, Array]:
    """Residuals of the principal point prior of eq. 27 and their (constant) derivatives."""
    if prior is None or len(layout.prior_index) == 0:
        return np.zeros(0), np.zeros(0)
    mean, sigma, noise = prior.mean, prior.sigma, prior.noise_sigma
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


def apply_step(state: State, d_cam: Array, d_ray: Array, layout: Layout, f_min: float) -> State:
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
    return State(values, R, X, lam, curve)


def total_cost(r: Array, prior_r: Array) -> float:
    return float(np.sum(r * r) + np.sum(prior_r * prior_r))
