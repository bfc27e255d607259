"""Radial distortion models, the plumb_bob conversion, the metric and estimation from image data alone."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ptz_selfcal.camera.distortion import (
    division_corner_shift,
    division_distort,
    division_lambda_for_corner_shift,
    division_to_plumb_bob,
    division_to_plumb_bob_fit,
    division_undistort,
    half_diagonal,
    max_distortion_difference,
    plumb_bob_distort,
    plumb_bob_undistort,
    radial_displacement,
)
from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.lens.curve import DistortionVsFocal
from ptz_selfcal.lens.estimation import (
    KeyframeMatch,
    estimate_keyframe_distortion,
    estimate_pair_distortion,
    rescale_lambda,
)

W, H = 1280, 720
CENTRE = np.array([639.5, 359.5])
F_WIDE = 1108.0  # 60 degrees horizontal field of view


def lam_true(f: float) -> float:
    """The issue's lens: 12% corner shift at the widest zoom, shrinking as 1/f."""
    return division_lambda_for_corner_shift(0.12 * F_WIDE / f, W, H, f)


def no_distortion(f: float) -> float:
    return 0.0


def division_error(lam_est: float, lam: float, f: float) -> float:
    K = intrinsic_matrix(f, *CENTRE)
    return max_distortion_difference(("division", (lam_est,), K), ("division", (lam,), K), W, H)


def synthetic_pair(f_i, f_j, pan_tilt_i, pan_tilt_j, lam=lam_true, n=300, noise=0.0, seed=0):
    """Distorted pixels of the same rays in two keyframes: exact K, R and division model."""
    rng = np.random.default_rng(seed)
    K_i, K_j = intrinsic_matrix(f_i, *CENTRE), intrinsic_matrix(f_j, *CENTRE)
    R_i, R_j = ptz_rotation(*pan_tilt_i), ptz_rotation(*pan_tilt_j)
    u = rng.uniform([-250.0, -250.0], [W + 250.0, H + 250.0], (20 * n, 2))
    rays = (R_i.T @ np.linalg.inv(K_i) @ np.column_stack([u, np.ones(len(u))]).T).T
    out = []
    for K, R, f in ((K_i, R_i, f_i), (K_j, R_j, f_j)):
        x = (K @ R @ rays.T).T
        pix = division_distort(x[:, :2] / x[:, 2:3], lam(f), CENTRE, f)
        out.append(
            (x[:, 2] > 0) & np.all((pix >= 0) & (pix <= [W - 1, H - 1]), axis=1) & ~np.isnan(pix[:, 0])
        )
        out.append(pix)
    keep = out[0] & out[2]
    d_i, d_j = out[1][keep][:n], out[3][keep][:n]
    return d_i + rng.normal(0.0, noise, d_i.shape), d_j + rng.normal(0.0, noise, d_j.shape)


def zoom_sequence(n_kf=8, noise=0.3, seed=1, lam=lam_true):
    """Keyframes zooming 1x -> 3x while panning by ~30% of the field of view, matched to the next two."""
    f = F_WIDE * 3.0 ** (np.arange(n_kf) / (n_kf - 1))
    pan, tilt = np.zeros(n_kf), np.zeros(n_kf)
    for k in range(1, n_kf):
        fov = 2.0 * np.arctan(640.0 / f[k])
        pan[k] = pan[k - 1] + 0.3 * fov * (1.0 if k % 2 else -0.5)
        tilt[k] = 0.1 * fov * np.sin(k)
    matches = []
    for i in range(n_kf):
        for j in (i + 1, i + 2):
            if j < n_kf:
                d_i, d_j = synthetic_pair(
                    f[i],
                    f[j],
                    (pan[i], tilt[i]),
                    (pan[j], tilt[j]),
                    lam,
                    noise=noise,
                    seed=100 * seed + 10 * i + j,
                )
                matches.append(KeyframeMatch(i, j, d_i, d_j))
    return f, matches


# ------------------------------------------------------------------------------------------------
# Models
# ------------------------------------------------------------------------------------------------
def test_division_round_trip_and_barrel_sign():
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0], [W - 1, H - 1], (2000, 2))
    lam = lam_true(F_WIDE)
    assert lam < 0.0
    und = division_undistort(pts, lam, CENTRE, F_WIDE)
    np.testing.assert_allclose(division_distort(und, lam, CENTRE, F_WIDE), pts, atol=1e-9)
    # barrel: undistortion pushes every point outwards
    grow = np.linalg.norm(und - CENTRE, axis=1) - np.linalg.norm(pts - CENTRE, axis=1)
    assert np.all(grow >= -1e-12) and grow.max() > 50.0
    np.testing.assert_allclose(division_undistort(pts, 0.0, CENTRE, F_WIDE), pts)


def test_corner_shift_helper_is_exact_and_scales_with_field_of_view():
    for f, shift in ((F_WIDE, 0.12), (2.0 * F_WIDE, 0.06), (F_WIDE, -0.03)):
        lam = division_lambda_for_corner_shift(shift, W, H, f)
        corner = division_undistort([[0.0, 0.0]], lam, CENTRE, f)[0]
        assert np.linalg.norm(corner - CENTRE) == pytest.approx((1 + shift) * half_diagonal(W, H), rel=1e-12)
        assert division_corner_shift(lam, W, H, f) == pytest.approx(shift, rel=1e-12)
    # fixed (small) lam: the corner displacement scales as 1/f^2 (normalised-radius convention)
    lam = -0.01
    s1 = division_corner_shift(lam, W, H, F_WIDE)
    s2 = division_corner_shift(lam, W, H, 2 * F_WIDE)
    assert s2 / s1 == pytest.approx(0.25, rel=0.05)


def test_plumb_bob_round_trip_matches_opencv():
    K = intrinsic_matrix(900.0, 630.0, 365.0)
    k1, k2 = -0.21, 0.05
    pts = np.random.default_rng(1).uniform([0, 0], [W - 1, H - 1], (500, 2))
    dist = plumb_bob_distort(pts, k1, k2, K)
    # against OpenCV's projectPoints (the forward model)
    rays = np.column_stack([(pts - K[:2, 2]) / 900.0, np.ones(len(pts))])
    cv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.array([k1, k2, 0, 0, 0.0]))
    np.testing.assert_allclose(dist, cv.reshape(-1, 2), atol=1e-8)
    np.testing.assert_allclose(plumb_bob_undistort(dist, k1, k2, K), pts, atol=1e-8)
    np.testing.assert_allclose(plumb_bob_undistort(dist, k1, k2, K, use_opencv=True), pts, atol=1e-4)


@pytest.mark.parametrize("f, bound_px", [(F_WIDE, 0.25), (2 * F_WIDE, 0.05), (3 * F_WIDE, 0.02)])
def test_division_to_plumb_bob_consistent_with_opencv_undistortion(f, bound_px):
    lam = lam_true(f)
    K = intrinsic_matrix(f, *CENTRE)
    fit = division_to_plumb_bob_fit(lam, K, W, H)
    assert (fit.k1, fit.k2) == division_to_plumb_bob(lam, K, W, H)
    assert fit.k1 < 0.0 and fit.max_px < bound_px
    pts = np.random.default_rng(2).uniform([0, 0], [W - 1, H - 1], (3000, 2))
    pts = np.vstack([pts, [[0, 0], [W - 1, H - 1], [0, H - 1], [W - 1, 0]]])
    D = np.array([fit.k1, fit.k2, 0.0, 0.0, 0.0])
    cv = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, D, None, None, K).reshape(-1, 2)
    err = np.linalg.norm(cv - division_undistort(pts, lam, CENTRE, f), axis=1)
    assert err.max() < bound_px
    # the same with the project's own exact inversion
    err = np.linalg.norm(
        plumb_bob_undistort(pts, fit.k1, fit.k2, K) - division_undistort(pts, lam, CENTRE, f), axis=1
    )
    assert err.max() < bound_px


def test_no_distortion_converts_to_zero_plumb_bob():
    k1, k2 = division_to_plumb_bob(0.0, intrinsic_matrix(F_WIDE, *CENTRE), W, H)
    assert abs(k1) < 1e-12 and abs(k2) < 1e-12


def test_metric_known_values_and_principal_point_excluded():
    f = F_WIDE
    lam = lam_true(f)
    K = intrinsic_matrix(f, *CENTRE)
    corner_shift = 0.12 * half_diagonal(W, H)
    # estimating "no distortion" misses the full corner displacement
    assert max_distortion_difference(
        ("plumb_bob", (0.0, 0.0), K), ("division", (lam,), K), W, H
    ) == pytest.approx(corner_shift, rel=1e-6)
    # a shifted principal point alone is not a distortion error
    K_off = intrinsic_matrix(f, CENTRE[0] + 7.0, CENTRE[1] - 4.0)
    assert max_distortion_difference(("division", (lam,), K_off), ("division", (lam,), K), W, H) < 1e-9
    # plumb_bob estimate against division truth (the calibrator's output against the renderer's model)
    k1, k2 = division_to_plumb_bob(lam, K, W, H)
    assert max_distortion_difference(("plumb_bob", (k1, k2), K), ("division", (lam,), K), W, H) < 0.25
    radii = np.array([0.0, 100.0, 400.0])
    disp = radial_displacement("division", (lam,), K, radii)
    assert disp[0] == 0.0 and 0.0 < disp[1] < disp[2]


# ------------------------------------------------------------------------------------------------
# Estimation from correspondences
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "f_i, f_j, pan", [(F_WIDE, F_WIDE, 0.3), (F_WIDE, 1.35 * F_WIDE, 0.3), (2.0 * F_WIDE, 2.4 * F_WIDE, 0.15)]
)
def test_pair_distortion_recovered_exactly(f_i, f_j, pan):
    d_i, d_j = synthetic_pair(f_i, f_j, (0.0, 0.0), (pan, 0.05))
    est = estimate_pair_distortion(d_i, d_j, CENTRE, f_i, f_j)
    # exact to rounding (worst of five pairs 4e-14; the bounds leave room for another machine's rounding)
    assert est.lam_i == pytest.approx(lam_true(f_i), rel=1e-12)
    assert est.lam_j == pytest.approx(lam_true(f_j), rel=1e-12)
    assert est.rms < 1e-12
    # the returned homography is the infinite homography between undistorted pixels (eq. 8)
    R_ij = ptz_rotation(pan, 0.05) @ ptz_rotation(0.0, 0.0).T
    H_true = intrinsic_matrix(f_j, *CENTRE) @ R_ij @ np.linalg.inv(intrinsic_matrix(f_i, *CENTRE))
    np.testing.assert_allclose(est.H, H_true / H_true[2, 2], rtol=1e-12, atol=1e-15)


def test_pair_distortion_with_noise_consistent_with_its_uncertainty():
    f_i, f_j = F_WIDE, 1.35 * F_WIDE
    d_i, d_j = synthetic_pair(f_i, f_j, (0.0, 0.0), (0.3, 0.05), noise=0.3, seed=3)
    est = estimate_pair_distortion(d_i, d_j, CENTRE, f_i, f_j)
    # one pair of 300 points at 0.3 px is a weak constraint (~0.6 px 1-sigma at the wide end)
    assert abs(est.lam_i - lam_true(f_i)) < 3.0 * est.sigma_lam_i
    assert abs(est.lam_j - lam_true(f_j)) < 3.0 * est.sigma_lam_j
    assert division_error(est.lam_i, lam_true(f_i), f_i) < 2.0
    assert division_error(est.lam_j, lam_true(f_j), f_j) < 2.0
    assert 0.45 < est.rms < 0.75  # symmetric transfer of 0.3 px noise in both images ~ 0.6 px
    assert 0.0 < est.sigma_lam_i < 0.005


def test_no_distortion_gives_zero_lambda_and_zero_k1():
    d_i, d_j = synthetic_pair(
        F_WIDE, 1.3 * F_WIDE, (0.0, 0.0), (0.3, 0.05), lam=no_distortion, noise=0.2, seed=4
    )
    est = estimate_pair_distortion(d_i, d_j, CENTRE, F_WIDE, 1.3 * F_WIDE)
    K = intrinsic_matrix(F_WIDE, *CENTRE)
    k1, _ = division_to_plumb_bob(est.lam_i, K, W, H)
    assert abs(est.lam_i) < 0.01 and abs(est.lam_j) < 0.01
    assert abs(k1) < 0.01  # the lens has k1 ~ -0.24 here
    assert division_error(est.lam_i, 0.0, F_WIDE) < 1.0


def test_keyframe_distortion_while_zooming_per_keyframe_and_curve():
    f, matches = zoom_sequence(noise=0.3)
    per_kf = estimate_keyframe_distortion(matches, f, CENTRE)
    errors = [division_error(lam, lam_true(fk), fk) for lam, fk in zip(per_kf.lam, f)]
    assert np.median(errors) < 0.5 and max(errors) < 1.0
    assert per_kf.rms < 0.7 < 2.0 < per_kf.rms_undistorted_model  # correction removes the model error
    assert np.all(np.isfinite(per_kf.sigma_lam)) and np.all(per_kf.sigma_lam > 0)
    # the curve-constrained estimate (lam tied through DistortionVsFocal) is as good or better
    curve = DistortionVsFocal(W, H)
    tied = estimate_keyframe_distortion(matches, f, CENTRE, curve=curve)
    np.testing.assert_allclose(curve.predict(f), tied.lam, rtol=1e-12)  # the curve is left fitted
    errors_tied = [division_error(lam, lam_true(fk), fk) for lam, fk in zip(tied.lam, f)]
    assert max(errors_tied) < 0.5
    assert tied.curve_coefficients is not None


def test_wrong_nominal_focal_is_absorbed_by_rescaling():
    f, matches = zoom_sequence(n_kf=4, noise=0.0)
    est = estimate_keyframe_distortion(matches, 1.15 * f, CENTRE)
    for lam, fk in zip(est.lam, f):
        assert rescale_lambda(lam, 1.15 * fk, fk) == pytest.approx(lam_true(fk), rel=1e-6)


# ------------------------------------------------------------------------------------------------
# Distortion versus focal length
# ------------------------------------------------------------------------------------------------
def test_distortion_vs_focal_robust_fit_and_extrapolation():
    rng = np.random.default_rng(5)
    f = F_WIDE * rng.uniform(1.0, 3.0, 60)
    curve = DistortionVsFocal(W, H)
    true_shift = curve.shift_from_lambda(f, [lam_true(x) for x in f])
    shift = true_shift + rng.normal(0.0, 0.3 / half_diagonal(W, H), len(f))  # 0.3 px corner noise
    shift[:5] += 0.02  # five bad keyframes (15 px)
    curve.fit(f, curve.lambda_from_shift(f, shift))
    grid = np.linspace(F_WIDE, 3 * F_WIDE, 50)
    errors = [division_error(curve.predict(x), lam_true(x), x) for x in grid]
    assert max(errors) < 0.3
    assert curve.in_range(2 * F_WIDE) and not curve.in_range(4 * F_WIDE)
    # beyond the fitted range the corner shift fades as 1/f, never the polynomial
    assert curve.predict_shift(6 * F_WIDE) == pytest.approx(curve.predict_shift(3 * F_WIDE) / 2.0, rel=0.02)
    assert division_error(float(curve.predict(6 * F_WIDE)), lam_true(6 * F_WIDE), 6 * F_WIDE) < 0.3


def test_distortion_vs_focal_reduces_degree_on_a_narrow_range():
    f = np.array([F_WIDE, F_WIDE * 1.02, F_WIDE * 1.04])
    curve = DistortionVsFocal(W, H).fit(f, [lam_true(x) for x in f])
    assert curve.coefficients is not None and curve.coefficients[2] == 0.0
    assert division_error(float(curve.predict(F_WIDE * 1.02)), lam_true(F_WIDE * 1.02), F_WIDE * 1.02) < 0.2


def test_analytic_jacobian_matches_finite_differences():
    from ptz_selfcal.lens.estimation import _homography_from_update, _pair_jacobian, _pair_residuals

    rng = np.random.default_rng(6)
    a, b = rng.uniform(-0.5, 0.5, (40, 2)), rng.uniform(-0.4, 0.4, (40, 2))
    H0 = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    p0 = np.concatenate([[-0.2, -0.3], 0.01 * rng.normal(size=8)])

    def residuals(p):
        return _pair_residuals(a, b, p[0], p[1], _homography_from_update(p[2:], H0), 1100.0, 1500.0)

    r, J_lam, J_D = _pair_jacobian(
        a, b, p0[0], p0[1], H0, _homography_from_update(p0[2:], H0), 1100.0, 1500.0
    )
    J = np.hstack([J_lam, J_D])
    numeric = np.column_stack([(residuals(p0 + d) - residuals(p0 - d)) / 2e-7 for d in 1e-7 * np.eye(10)])
    np.testing.assert_allclose(r, residuals(p0))
    assert np.abs(J - numeric).max() < 1e-6 * np.abs(numeric).max()


def test_homographies_on_corrected_coordinates():
    from ptz_selfcal.camera.geometry import transfer_error
    from ptz_selfcal.frontend.homography import estimate_homography
    from ptz_selfcal.lens.estimation import (
        undistorted_homography,
        undistorted_homography_from_points,
    )

    f_i, f_j = F_WIDE, 1.1 * F_WIDE
    d_i, d_j = synthetic_pair(f_i, f_j, (0.0, 0.0), (0.15, 0.05), n=400)
    K_i, K_j = intrinsic_matrix(f_i, *CENTRE), intrinsic_matrix(f_j, *CENTRE)
    H_true = K_j @ ptz_rotation(0.15, 0.05) @ np.linalg.inv(K_i)  # eq. 8 between undistorted images
    u_i = division_undistort(d_i, lam_true(f_i), CENTRE, f_i)
    exact = undistorted_homography_from_points(
        d_i, d_j, lam_true(f_i), lam_true(f_j), CENTRE, CENTRE, f_i, f_j
    )
    assert transfer_error(exact, H_true, u_i).max() < 1e-6
    H_raw = estimate_homography(d_i, d_j)  # what a tracker fits to distorted points
    raw_error = np.median(transfer_error(H_raw, H_true, u_i))
    corrected = undistorted_homography(H_raw, lam_true(f_i), lam_true(f_j), CENTRE, CENTRE, f_i, f_j, W, H)
    corrected_error = np.median(transfer_error(corrected, H_true, u_i))
    assert raw_error > 8.0 and corrected_error < 1.0


def test_incremental_estimator_for_the_calibrator():
    from ptz_selfcal.lens.estimator import KeyframeDistortionEstimator

    # 0.15 px: the KLT matches of the image benchmark have 0.06-0.13 px transfer rms after correction
    f, matches = zoom_sequence(n_kf=8, noise=0.15, seed=2)
    est = KeyframeDistortionEstimator(W, H, max_matches=6, max_points_per_match=200)
    assert est.solve() is None and est.lam_at_focal(F_WIDE) == 0.0
    ids = [10 * (k + 1) for k in range(len(f))]  # the calibrator's keyframe ids
    for m in matches:
        est.set_keyframe(ids[m.i], f[m.i], CENTRE)  # older keyframe: calibrated by now
        est.set_keyframe(ids[m.j], 1.08 * f[m.j], CENTRE)  # newest keyframe: focal length still nominal
        est.add_match(ids[m.i], ids[m.j], m.pts_i, m.pts_j)
        est.solve()
    assert est.match_count == 6  # bounded
    # calibration refines the focal lengths of the live keyframes: lam follows (lam / f^2 invariant)
    live = est.live_keyframes()
    for kid in live:
        k = ids.index(kid)
        est.set_keyframe(kid, f[k], CENTRE)
        assert division_error(est.lam(kid), lam_true(f[k]), f[k]) < 1.0
    est.solve()
    # the curve learned from live and retired keyframes covers the whole zoom range
    for fk in (f[0], f[3], f[-1]):
        assert division_error(est.lam_at_focal(fk), lam_true(fk), fk) < 1.5
    # its state round-trips for the calibrator's state file
    restored = DistortionVsFocal.from_dict(est.curve.to_dict())
    assert restored.predict(f[2]) == pytest.approx(est.curve.predict(f[2]), rel=1e-12)
    with pytest.raises(ValueError):
        DistortionVsFocal.from_dict({"degree": 2})


def test_invalid_matches_are_rejected():
    few = KeyframeMatch(0, 1, np.zeros((5, 2)), np.zeros((5, 2)))
    with pytest.raises(ValueError):
        estimate_keyframe_distortion([few], [F_WIDE, F_WIDE], CENTRE)
    with pytest.raises(ValueError):
        estimate_keyframe_distortion([], [F_WIDE], CENTRE)


def test_frame_distortion_with_known_keyframe_and_prior():
    from ptz_selfcal.lens.estimation import estimate_frame_distortion

    f_kf, f_fr = 1.2 * F_WIDE, 1.3 * F_WIDE
    d_kf, d_fr = synthetic_pair(f_kf, f_fr, (0.0, 0.0), (0.2, 0.04), n=250)
    exact = estimate_frame_distortion(d_kf, d_fr, lam_true(f_kf), CENTRE, f_kf, f_fr)
    assert exact.lam_i == lam_true(f_kf) and exact.sigma_lam_i == 0.0
    assert exact.lam_j == pytest.approx(lam_true(f_fr), rel=1e-6) and exact.rms < 1e-6
    H_true = (
        intrinsic_matrix(f_fr, *CENTRE)
        @ ptz_rotation(0.2, 0.04)
        @ np.linalg.inv(intrinsic_matrix(f_kf, *CENTRE))
    )
    np.testing.assert_allclose(exact.H, H_true / H_true[2, 2], rtol=1e-6, atol=1e-9)
    # few points near the centre barely see distortion: the prior (e.g. the curve) holds the estimate
    rng = np.random.default_rng(8)
    d_kf, d_fr = synthetic_pair(f_kf, f_fr, (0.0, 0.0), (0.02, 0.01), n=2000, noise=0.3, seed=9)
    central = np.linalg.norm(d_fr - CENTRE, axis=1) < 150.0
    d_kf, d_fr = d_kf[central][:30], d_fr[central][:30]
    free = estimate_frame_distortion(d_kf, d_fr, lam_true(f_kf), CENTRE, f_kf, f_fr)
    prior_lam = lam_true(f_fr) * (1.0 + 0.02 * rng.normal())
    held = estimate_frame_distortion(d_kf, d_fr, lam_true(f_kf), CENTRE, f_kf, f_fr, prior_lam, 0.01)
    assert free.sigma_lam_j > 5.0 * held.sigma_lam_j and held.sigma_lam_j <= 0.01
    assert abs(held.lam_j - prior_lam) < 0.01  # the few central points barely move it off the prior
    assert division_error(held.lam_j, lam_true(f_fr), f_fr) < division_error(free.lam_j, lam_true(f_fr), f_fr)
