"""Linear self-calibration (paper section 3.3.2, eq. 23) on synthetic data with exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from ptz_selfcal.camera.geometry import (
    intrinsic_matrix,
    ptz_rotation,
    reference_homographies,
    relative_rotation,
    rotation_angle,
)
from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.frontend.homography import estimate_homography
from ptz_selfcal.selfcal.linear import intrinsics_from_iac, linear_selfcalibration
from ptz_selfcal.sim.synthetic import circle_rotations

SIZE = (640, 480)
CENTRE = (319.5, 239.5)


def paper_sequence(config: str, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    radius, f0, f1 = {"A": (5.0, 800.0, 1400.0), "B": (3.5, 1200.0, 2000.0)}[config]
    K = np.array([intrinsic_matrix(f, *CENTRE) for f in np.linspace(f0, f1, n)])
    return K, circle_rotations(n, radius)


def noisy_homographies(K: np.ndarray, R: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """H from 1000 noisy points of a 3 m cube 5 m away (paper 4.1): normalised DLT + refinement."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.5, 1.5, (1000, 3)) + np.array([0.0, 0.0, 5.0])
    pts, vis = [], []
    for Kj, Rj in zip(K, R):
        p = X @ (Kj @ Rj).T
        p = p[:, :2] / p[:, 2:]
        vis.append(np.all((p >= 0.0) & (p <= [SIZE[0] - 1.0, SIZE[1] - 1.0]), axis=1))
        pts.append(p + rng.normal(0.0, sigma, p.shape))
    H = [np.eye(3)]
    for j in range(1, len(K)):
        m = vis[0] & vis[j]
        H.append(estimate_homography(pts[0][m], pts[j][m]))
    return np.array(H)


def assert_intrinsics_close(K_est: np.ndarray, K_true: np.ndarray, rel: float = 1e-6) -> None:
    f = K_true[:, 1, 1]
    assert np.max(np.abs(K_est[:, 1, 1] / f - 1.0)) < rel
    assert np.max(np.abs(K_est[:, 0, 0] / K_true[:, 0, 0] - 1.0)) < rel
    # principal point and skew relative to f (they may be zero)
    assert np.max(np.abs(K_est[:, :2, 2] - K_true[:, :2, 2]) / f[:, None]) < rel
    assert np.max(np.abs(K_est[:, 0, 1] - K_true[:, 0, 1]) / f) < rel


def test_square_pixels_exact_recovers_varying_principal_point() -> None:
    rng = np.random.default_rng(3)
    n = 12
    f = np.linspace(700.0, 1500.0, n)
    pp = np.array(CENTRE) + rng.uniform(-25.0, 25.0, (n, 2))
    K = np.array([intrinsic_matrix(f[j], *pp[j]) for j in range(n)])
    R = circle_rotations(n, 6.0)
    result = linear_selfcalibration(reference_homographies(K, R), SIZE, square_pixels=True)
    assert_intrinsics_close(result.K, K)
    for j in range(n):
        assert rotation_angle(result.R[j] @ relative_rotation(R[0], R[j]).T) < 1e-8
    assert np.allclose(result.R[0], np.eye(3), atol=1e-12)


def test_zero_skew_only_exact_with_general_rotation() -> None:
    """Zero skew alone suffices when the rotations include roll (not a pan-tilt platform)."""
    rng = np.random.default_rng(7)
    n = 15
    K = np.array(
        [
            intrinsic_matrix(
                rng.uniform(700, 1500), *(np.array(CENTRE) + rng.uniform(-20, 20, 2)), rng.uniform(0.9, 1.1)
            )
            for _ in range(n)
        ]
    )
    R = np.array([ptz_rotation(*rng.uniform(-0.2, 0.2, 3)) for _ in range(n)])
    result = linear_selfcalibration(reference_homographies(K, R), SIZE, zero_skew=True, square_pixels=False)
    assert_intrinsics_close(result.K, K)


@pytest.mark.parametrize("square", [True, False])
def test_known_principal_point_exact_off_centre(square: bool) -> None:
    pp = (301.0, 255.0)
    n = 10
    aspect = 1.0 if square else 1.07
    K = np.array([intrinsic_matrix(f, *pp, aspect=aspect) for f in np.linspace(900.0, 1300.0, n)])
    R = circle_rotations(n, 5.0)
    result = linear_selfcalibration(
        reference_homographies(K, R), SIZE, square_pixels=square, known_principal_point=pp
    )
    assert_intrinsics_close(result.K, K)


def test_paper_configurations_exact() -> None:
    for config in "AB":
        K, R = paper_sequence(config)
        H = reference_homographies(K, R)
        assert_intrinsics_close(linear_selfcalibration(H, SIZE).K, K)
        assert_intrinsics_close(linear_selfcalibration(H, SIZE, known_principal_point=CENTRE).K, K)


def test_pan_only_with_zero_skew_only_is_rejected() -> None:
    n = 10
    K = np.array([intrinsic_matrix(f, *CENTRE) for f in np.linspace(800.0, 1200.0, n)])
    R = np.array([ptz_rotation(p, 0.0) for p in np.radians(np.linspace(0.0, 12.0, n))])
    with pytest.raises(SelfCalibrationError, match="insufficient"):
        linear_selfcalibration(reference_homographies(K, R), SIZE, square_pixels=False)


def test_pan_tilt_with_zero_skew_only_is_rejected() -> None:
    """Agapito et al. 1999 (section 6.1): zero skew is insufficient for a pan-tilt platform."""
    K, R = paper_sequence("A")
    with pytest.raises(SelfCalibrationError, match="insufficient"):
        linear_selfcalibration(reference_homographies(K, R), SIZE, square_pixels=False)


def test_too_few_equations_is_rejected() -> None:
    K, R = paper_sequence("A", n=2)
    with pytest.raises(SelfCalibrationError, match="constraints"):
        linear_selfcalibration(reference_homographies(K, R), SIZE, square_pixels=False)


def test_non_positive_definite_iac_is_detected() -> None:
    omega = np.array([np.eye(3), np.diag([1.0, -1.0, 1.0])])
    with pytest.raises(SelfCalibrationError, match="positive definite"):
        intrinsics_from_iac(omega)
    K = intrinsics_from_iac(np.array([np.diag([1.0 / 4.0, 1.0 / 4.0, 1.0])]))
    assert np.allclose(K[0], np.diag([2.0, 2.0, 1.0]))


def test_noisy_homographies_within_statistical_bounds() -> None:
    """Config A, sigma = 0.5 px, 5 fixed seeds: rms focal error of known pp < 1%, varying pp < 2.5%."""
    K, R = paper_sequence("A")
    err_known, err_square = [], []
    for seed in range(5):
        H = noisy_homographies(K, R, 0.5, seed)
        err_known.append(
            linear_selfcalibration(H, SIZE, known_principal_point=CENTRE).K[:, 1, 1] / K[:, 1, 1] - 1
        )
        err_square.append(linear_selfcalibration(H, SIZE).K[:, 1, 1] / K[:, 1, 1] - 1)
    rms_known = np.sqrt(np.mean(np.square(err_known)))
    rms_square = np.sqrt(np.mean(np.square(err_square)))
    assert 1e-4 < rms_known < 0.01
    assert 1e-4 < rms_square < 0.025


def test_varying_pp_bias_grows_with_noise_in_configuration_b() -> None:
    """The paper's bias of the linear method with varying principal point (config B): f overestimated."""
    K, R = paper_sequence("B")
    bias = []
    for sigma in (0.5, 2.0):
        errs = [
            linear_selfcalibration(noisy_homographies(K, R, sigma, s), SIZE).K[:, 1, 1] / K[:, 1, 1] - 1
            for s in range(3)
        ]
        bias.append(float(np.mean(errs)))
    assert bias[1] > 0.1 and bias[1] > 3.0 * abs(bias[0])


def test_pan_only_with_square_pixels_solves_but_is_flagged() -> None:
    """Known aspect removes the pan-only ambiguity of zero skew alone, but the motion report still says
    single-axis (section 6.1: nothing beyond the imposed constraints can be checked), so ok is False."""
    n = 10
    K = np.array([intrinsic_matrix(f, *CENTRE) for f in np.linspace(800.0, 1200.0, n)])
    R = np.array([ptz_rotation(p, np.radians(5.0)) for p in np.radians(np.linspace(0.0, 12.0, n))])
    result = linear_selfcalibration(reference_homographies(K, R), SIZE, square_pixels=True)
    assert_intrinsics_close(result.K, K)
    assert not result.ok
    assert result.motion is not None and result.motion.status == "degenerate_single_axis"
    ok = linear_selfcalibration(reference_homographies(*paper_sequence("A")), SIZE)
    assert ok.ok and ok.motion.status == "ok"


def test_auto_nominal_focal_removes_most_of_the_varying_pp_bias() -> None:
    """Pitfall: the varying-pp bias depends on the coordinate scale; re-normalising by the
    first estimate's focal length ('auto') shrinks it (config B, sigma = 1.5 px, 3 seeds)."""
    K, R = paper_sequence("B")
    default, auto = [], []
    for seed in range(3):
        H = noisy_homographies(K, R, 1.5, seed)
        default.append(linear_selfcalibration(H, SIZE).K[:, 1, 1] / K[:, 1, 1] - 1)
        auto.append(linear_selfcalibration(H, SIZE, nominal_focal="auto").K[:, 1, 1] / K[:, 1, 1] - 1)
    assert float(np.mean(default)) > 0.08
    assert abs(float(np.mean(auto))) < 0.3 * float(np.mean(default))
