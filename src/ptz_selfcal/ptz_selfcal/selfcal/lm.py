"""Non-linear self-calibration by Levenberg-Marquardt on eq. 22 (paper section 3.3.1).

Cost: D = sum_j || K_j K_j^T / |.|_F - H_j K_0 K_0^T H_j^T / |.|_F ||_F^2 over the unknown intrinsics
of every frame, each intrinsic KNOWN, CONSTANT or VARYING (camera.intrinsics). Solved in coordinates
centred at the image centre and scaled by a nominal focal length, with an analytic Jacobian.

Pitfall: with a per-frame principal point eq. 22 has an exact zero-cost solution as
f -> 0, so f is bounded below and a collapse onto that bound is reported as a failure.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import OptimizeResult, least_squares

from ptz_selfcal.camera.intrinsics import (
    ASPECT,
    CX,
    CY,
    SKEW,
    F,
    IntrinsicsModel,
    ParamMode,
    SelfCalibrationError,
    image_centre,
    matrices_from_values,
    parameter_count,
    parameter_index,
    parameters_from_intrinsics,
    rotations_from_homographies,
    values_from_parameters,
)
from ptz_selfcal.selfcal.degeneracy import analyse_motion, single_axis_is_degenerate
from ptz_selfcal.selfcal.linear import (
    linear_selfcalibration,
    normalise_homographies,
    normalising_transform,
)
from ptz_selfcal.selfcal.result import SelfCalibrationResult

Array = NDArray[np.float64]

# Upper-triangle entries of a symmetric 3x3 matrix and their weights in the Frobenius norm.
_ROWS = np.array([0, 0, 0, 1, 1, 2])
_COLS = np.array([0, 1, 2, 1, 2, 2])
_WEIGHTS = np.sqrt(np.array([1.0, 2.0, 2.0, 1.0, 2.0, 1.0]))


class Eq22Problem:
    """Residuals and analytic Jacobian of eq. 22 for fixed normalised homographies and model."""

    def __init__(self, Hn: Array, model: IntrinsicsModel) -> None:
        self.H = Hn
        self.Ht = np.swapaxes(Hn, 1, 2)
        self.model = model
        self.n = len(Hn)
        self.index = parameter_index(model, self.n)
        self.size = parameter_count(model, self.n)
        self.varying = [c for c in range(5) if model.modes[c] is not ParamMode.KNOWN]

    def intrinsics(self, p: Array) -> tuple[Array, Array]:
        values = values_from_parameters(p, self.model, self.n, (1, 1))
        return values, matrices_from_values(values)

    @staticmethod
    def _normalised(A: Array) -> tuple[Array, Array]:
        norm = np.sqrt(np.einsum("nij,nij->n", A, A))
        return A / norm[:, None, None], norm

    def residuals(self, p: Array) -> Array:
        _, K = self.intrinsics(p)
        A = K @ np.swapaxes(K, 1, 2)  # DIAC K_j K_j^T
        B = self.H[1:] @ A[0] @ self.Ht[1:]  # H_j K_0 K_0^T H_j^T (eq. 20)
        a, _ = self._normalised(A[1:])
        b, _ = self._normalised(B)
        return ((a - b)[:, _ROWS, _COLS] * _WEIGHTS).ravel()

    def _dK(self, values: Array) -> Array:
        """(n, 5, 3, 3) derivative of K_j with respect to each of its intrinsic columns."""
        dK = np.zeros((self.n, 5, 3, 3))
        dK[:, F, 0, 0] = values[:, ASPECT]
        dK[:, F, 0, 1] = values[:, SKEW]
        dK[:, F, 1, 1] = 1.0
        dK[:, ASPECT, 0, 0] = values[:, F]
        dK[:, SKEW, 0, 1] = values[:, F]
        dK[:, CX, 0, 2] = 1.0
        dK[:, CY, 1, 2] = 1.0
        return dK

    @staticmethod
    def _d_normalised(A: Array, norm: Array, dA: Array) -> Array:
        """Derivative of A/|A|_F given dA (n, c, 3, 3): dA/|A| - A (A:dA)/|A|^3."""
        inner = np.einsum("nij,ncij->nc", A, dA)
        return dA / norm[:, None, None, None] - A[:, None] * (inner / norm[:, None] ** 3)[:, :, None, None]

    def jacobian(self, p: Array) -> Array:
        values, K = self.intrinsics(p)
        Kt = np.swapaxes(K, 1, 2)
        A = K @ Kt
        dK = self._dK(values)
        dKKt = dK @ Kt[:, None]
        dA = dKKt + np.swapaxes(dKKt, 2, 3)  # d(K K^T) = dK K^T + K dK^T
        B = self.H[1:] @ A[0] @ self.Ht[1:]
        dB = self.H[1:, None] @ dA[0][None] @ self.Ht[1:, None]
        _, norm_a = self._normalised(A[1:])
        _, norm_b = self._normalised(B)
        da = self._d_normalised(A[1:], norm_a, dA[1:])[:, :, _ROWS, _COLS] * _WEIGHTS
        db = self._d_normalised(B, norm_b, dB)[:, :, _ROWS, _COLS] * _WEIGHTS
        J = np.zeros((self.n - 1, 6, self.size))
        rows = np.arange(self.n - 1)
        for c in self.varying:
            J[rows, :, self.index[1:, c]] += da[:, c]
            J[:, :, self.index[0, c]] -= db[:, c]
        return J.reshape(-1, self.size)


def _initial_intrinsics(H: Array, image_size: tuple[int, int], model: IntrinsicsModel) -> Array:
    """Linear estimate (3.3.2) under the model's linear constraints, with a zoom-ratio fallback."""
    square = (
        model.aspect is ParamMode.KNOWN
        and model.aspect_value == 1.0
        and model.skew is ParamMode.KNOWN
        and model.skew_value == 0.0
    )
    known_pp = None
    if model.principal_point is ParamMode.KNOWN:
        known_pp = model.principal_point_value or image_centre(image_size)
    try:
        return linear_selfcalibration(
            H, image_size, square_pixels=square, known_principal_point=known_pp, analyse=False
        ).K
    except SelfCalibrationError:
        # Fallback: f_0 = image width, f_j from the area scale of H_j (zoom ratio), pp at the centre.
        N = normalising_transform(image_centre(image_size), float(image_size[0]))
        Hn = N @ H @ np.linalg.inv(N)
        Hn /= Hn[:, 2:3, 2:3]
        ratio = np.sqrt(np.abs(np.linalg.det(Hn[:, :2, :2])))
        cx, cy = image_centre(image_size)
        K = np.zeros((len(H), 3, 3))
        K[:, 0, 0] = K[:, 1, 1] = image_size[0] * ratio
        K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = cx, cy, 1.0
        return K


def lm_selfcalibration(
    H: ArrayLike,
    image_size: tuple[int, int],
    model: IntrinsicsModel | None = None,
    K_init: ArrayLike | None = None,
    *,
    f_min: float | None = None,
    nominal_focal: float | None = None,
    max_nfev: int = 200,
    analyse: bool = True,
    max_relative_sigma_f: float = 0.02,
) -> SelfCalibrationResult:
    """Self-calibration by LM on eq. 22 from H[j] mapping frame-0 pixels to frame-j pixels (H[0] = I).

    nominal_focal: coordinate scale in pixels (default half the image width).
    f_min (pixels) bounds every focal length from below; default 0.1 x the smallest initial focal.
    MINPACK LM runs first; only if it leaves the admissible range is the solve repeated with the
    bound enforced (trust-region reflective), and ending on the bound is reported as a failure.
    The result carries 1-sigma uncertainties from the final Jacobian and a MotionReport (section 6);
    ok is False when f collapsed onto f_min (eq. 22's f -> 0 solution) or the motion is not well
    posed, e.g. near-ambiguous (6.2) when the median relative sigma_f exceeds max_relative_sigma_f.
    Raises SelfCalibrationError on invalid input.
    """
    model = model or IntrinsicsModel()
    H = np.asarray(H, dtype=float).reshape(-1, 3, 3)
    n = len(H)
    if n < 2:
        raise SelfCalibrationError("need at least two frames")
    # Scale: half the image width (coordinates in [-1, 1]): smaller eq. 22 focal errors than the width or f.
    nominal = float(nominal_focal or 0.5 * image_size[0])
    N = normalising_transform(image_centre(image_size), nominal)
    Hn = normalise_homographies(H, N)
    nmodel = model.normalised(image_size, nominal)
    problem = Eq22Problem(Hn, nmodel)
    if problem.size > 6 * (n - 1):
        raise SelfCalibrationError(f"{problem.size} unknowns but only {6 * (n - 1)} equations (eq. 21)")
    K0 = _initial_intrinsics(H, image_size, model) if K_init is None else np.asarray(K_init, dtype=float)
    K0 = np.broadcast_to(K0, (n, 3, 3))
    p0 = parameters_from_intrinsics(N @ K0, nmodel)
    f_floor = (f_min if f_min is not None else 0.1 * float(np.min(K0[:, 1, 1]))) / nominal
    lower = np.full(problem.size, -np.inf)
    f_index = np.unique(problem.index[:, F][problem.index[:, F] >= 0])
    lower[f_index] = f_floor
    p0[f_index] = np.maximum(p0[f_index], 1.001 * f_floor)
    sol = least_squares(problem.residuals, p0, jac=problem.jacobian, method="lm", max_nfev=max_nfev)
    if np.any(sol.x[f_index] <= f_floor):
        # f left its admissible range (eq. 22's f -> 0 valley): re-solve with f bounded below.
        sol = least_squares(
            problem.residuals,
            p0,
            jac=problem.jacobian,
            bounds=(lower, np.inf),
            method="trf",
            max_nfev=max_nfev,
        )
    values, K_n = problem.intrinsics(sol.x)
    K = np.linalg.inv(N) @ K_n
    K /= K[:, 2:3, 2:3]
    sigma_f, sigma_pp = _uncertainty(sol.jac, sol.fun, problem, nominal)
    R = rotations_from_homographies(H, K)
    ok, message = _check_solution(sol, values, f_floor, K0, nominal)
    result = SelfCalibrationResult(
        K=K,
        R=R,
        sigma_f=sigma_f,
        sigma_pp=sigma_pp,
        residual=float(np.sqrt(np.mean(sol.fun**2))),
        method=f"lm_{_model_name(model)}",
        iterations=int(sol.nfev),
        ok=ok,
        message=message,
        cost=float(sol.cost),
        solver_ok=ok,
    )
    if analyse:
        result.motion = analyse_motion(
            R,
            K,
            image_size,
            sigma_f=sigma_f,
            max_relative_sigma_f=max_relative_sigma_f,
            single_axis_degenerate=single_axis_is_degenerate(model),
        )
        if result.ok and not result.motion.well_posed:
            result.ok = False
            result.message = f"motion not well posed: {result.motion.status} ({result.motion.message})"
    return result


def _check_solution(
    sol: OptimizeResult, values: Array, f_floor: float, K0: Array, nominal: float
) -> tuple[bool, str]:
    """Detect a failed solve and eq. 22's degenerate f -> 0 solution."""
    f = values[:, F]
    if not np.all(np.isfinite(sol.x)):
        return False, "solver diverged (non-finite parameters)"
    if np.any(f <= 1.01 * f_floor):
        return False, "focal length collapsed onto its lower bound (eq. 22's f -> 0 solution)"
    if sol.cost < 1e-18 and np.median(f) < 0.3 * np.median(K0[:, 1, 1]) / nominal:
        return False, "near-zero cost with tiny focal lengths (eq. 22's f -> 0 solution)"
    if sol.status < 0:
        return False, f"solver failed: {sol.message}"
    if sol.status == 0:
        return True, "evaluation budget reached before convergence (estimate improved, not final)"
    return True, ""


def _uncertainty(J: Array, residuals: Array, problem: Eq22Problem, nominal: float) -> tuple[Array, Array]:
    """1-sigma of f and pp per frame, pixels: (J^T J)^-1 scaled by the residual variance."""
    m, p = J.shape
    dof = max(m - p, 1)
    variance = float(residuals @ residuals) / dof
    JtJ = J.T @ J
    try:
        cov = np.linalg.inv(JtJ) * variance
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(JtJ) * variance
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * nominal
    sd = np.append(sd, 0.0)  # index -1 (KNOWN) reads 0
    index = problem.index
    return sd[index[:, F]], np.column_stack([sd[index[:, CX]], sd[index[:, CY]]])


def _model_name(model: IntrinsicsModel) -> str:
    return f"{model.principal_point.value}_pp"
