"""Optimal estimation by bundle adjustment (paper section 5).

MLE (eq. 26): minimise the sum of squared reprojection errors |x_ij - K_i R_i X_j|^2 over the
intrinsics K_i (per `IntrinsicsModel`), the rotations R_i (R_0 = I fixed: the gauge) and the rays X_j
(unit directions, two degrees of freedom each). MAP (eq. 27): the same with a Gaussian prior on the
principal point.

The solver is a sparse Levenberg-Marquardt: the 2x2 block of every ray is eliminated with the Schur
complement (all rays at once with numpy), leaving a small dense reduced camera system of the
rotations and intrinsics. Jacobians are analytic. The inverse of the reduced normal equations, scaled
by the residual variance, gives the 1-sigma uncertainty of every focal length and principal point.

The modules follow the section: observations (the measurements and the starting rays), problem (the
unknowns, residuals and Jacobians, with radial distortion), schur (ray elimination and covariance) and
this adjuster (the LM iterations and the result).
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.bundle.observations import (
    ObservationsLike,
    PreparedObservations,
    initial_rays,
    prepare_observations,
    undistorted_observations,
)
from ptz_selfcal.bundle.problem import (
    LamCurve,
    Layout,
    PrincipalPointPrior,
    State,
    apply_step,
    jacobians,
    parameter_layout,
    prior_residuals,
    residuals,
    total_cost,
)
from ptz_selfcal.bundle.schur import choose_coupling, normal_equations, reduced_covariance, schur_step
from ptz_selfcal.camera.distortion import half_diagonal
from ptz_selfcal.camera.intrinsics import (
    CX,
    CY,
    F,
    IntrinsicsModel,
    SelfCalibrationError,
    image_centre,
    matrices_from_values,
    parameter_index,
    values_from_matrices,
)
from ptz_selfcal.selfcal.degeneracy import analyse_motion, single_axis_is_degenerate
from ptz_selfcal.selfcal.result import BundleDetails, SelfCalibrationResult

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]

logger = logging.getLogger(__name__)


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
    principal point is estimated with everything else (bundle.problem): True or "frame", free per
    frame; "curve", on the lam(f) curve of degree curve_degree; "shared", ONE coefficient for every
    frame (a fixed lens: constant f, one distortion). Starting from lam_init ((n,), default 0; its mean
    for "shared"); the result's info carries "lam" (n,), "sigma_lam" (n,) and, for a curve,
    "distortion_curve" (coefficients, f_ref, half-diagonal).
    initial_damping: LM's starting damping (relative to the diagonal of the normal equations); a
    smaller one (the keyframe solver's) lets the first steps follow a pan's flat near-ambiguity
    (section 6.2) instead of creeping along it while the damping falls.
    max_focal_change: stop (message "focal length moved beyond max_focal_change") once an accepted
    step leaves a focal length further than this fraction from its start: for a caller that only
    asks whether f moves (the keyframe solver's lens-model check), not where it ends.
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
    obs, ray_ids = prepare_observations(observations, n)
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
        X = initial_rays(obs if lam is None else undistorted_observations(obs, Kmat, lam), Kmat, R, n_rays)
    else:
        X = np.asarray(rays_init, dtype=float)[ray_ids] @ R_in[0].T
        X /= np.linalg.norm(X, axis=1, keepdims=True)
    curve = None
    if distortion == "curve":
        assert lam is not None
        f0 = values[:, F]
        curve = LamCurve.fit(f0, lam, float(f0.min()), half_diagonal(*image_size), int(curve_degree))
        lam = curve.lam(f0)
    state = State(values, R, X, lam, curve)

    prior = None
    if pp_prior is not None:
        mean = np.asarray(pp_prior[0], dtype=float).reshape(2)
        sigma = np.asarray(pp_prior[1], dtype=float).reshape(2)
        prior = PrincipalPointPrior(mean, sigma, float(noise_sigma))
    layout = parameter_layout(
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


def _levenberg_marquardt(
    state: State,
    obs: PreparedObservations,
    layout: Layout,
    prior: PrincipalPointPrior | None,
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
    r, Y = residuals(state, obs)
    prior_terms = prior_residuals(state, layout, prior)
    cost = total_cost(r, prior_terms[0])
    initial_cost = cost
    exact_cost = 1e-20 * r.shape[1]  # rms below 1e-10 px: nothing left to fit
    coupling = choose_coupling(obs, layout, n_rays, schur)
    lam, nu = float(initial_damping), 2.0
    f_start = state.values[:, F].copy()
    iterations, message = 0, "maximum iterations reached"
    ne = None
    for iterations in range(1, max_iterations + 1):
        J_cam, J_ray = jacobians(state, obs, Y, layout)
        ne = normal_equations(r, J_cam, J_ray, obs, layout, n_rays, prior_terms, coupling)
        D_cam = np.maximum(np.diag(ne.U), 1e-12 * max(np.diag(ne.U).max(), 1e-300))
        D_ray = np.maximum(ne.V[[0, 2]], 1e-12)  # (2, m) diagonal of the ray blocks
        accepted = False
        while not accepted:
            d_cam, d_ray = schur_step(ne, lam, D_cam, D_ray)
            candidate = apply_step(state, d_cam, d_ray, layout, f_min)
            r_new, Y_new = residuals(candidate, obs)
            prior_new = prior_residuals(candidate, layout, prior)
            cost_new = total_cost(r_new, prior_new[0])
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
        J_cam, J_ray = jacobians(state, obs, Y, layout)
        ne = normal_equations(r, J_cam, J_ray, obs, layout, n_rays, prior_terms, coupling)
        cov = reduced_covariance(ne) * variance
    else:
        cov = np.full((layout.n_params, layout.n_params), np.nan)
    sd = np.append(np.sqrt(np.maximum(np.diag(cov), 0.0)), 0.0)
    idx = np.where(layout.intr_index >= 0, layout.intr_index, len(sd) - 1)
    sigma_f = sd[idx[:, F]]
    sigma_pp = np.column_stack([sd[idx[:, CX]], sd[idx[:, CY]]])
    lam = sigma_lam = curve = None
    if state.lam is not None and layout.lam_index is not None:
        lam, sigma_lam = state.lam.copy(), sd[layout.lam_index]
    elif state.curve is not None and layout.curve_index is not None:
        # sigma of each frame's lam through the curve: J cov J^T with J = d lam / d (c, f)
        _, dlam_dc, dlam_df = state.curve.derivatives(state.values[:, F])
        idx_f = np.where(layout.intr_index[:, F] >= 0, layout.intr_index[:, F], -1)
        var = []
        for i in range(len(dlam_dc)):
            cols = list(layout.curve_index) + ([int(idx_f[i])] if idx_f[i] >= 0 else [])
            g = np.append(dlam_dc[i], dlam_df[i]) if idx_f[i] >= 0 else dlam_dc[i]
            var.append(float(g @ cov[np.ix_(cols, cols)] @ g))
        lam, sigma_lam = state.lam.copy(), np.sqrt(np.maximum(var, 0.0))
        curve = (state.curve.coefficients.copy(), state.curve.f_ref, state.curve.half_diagonal)

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
        bundle=BundleDetails(
            rays=rays,
            covariance=cov,
            residual_variance=variance,
            initial_cost=initial_cost,
            n_observations=n_obs,
            n_rays=n_rays,
            model=model,
            lam=lam,
            sigma_lam=sigma_lam,
            distortion_curve=curve,
        ),
    )


def default_pp_prior(image_size: tuple[int, int], sigma: float = 10.0) -> tuple[Array, Array]:
    """The paper's prior of eq. 27: the principal point near the image centre, sigma pixels each way."""
    return np.array(image_centre(image_size)), np.array([sigma, sigma])
