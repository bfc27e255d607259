"""The paper's synthetic experiment generator (section 4.1): exact ground truth, noise and homographies."""

from __future__ import annotations

import numpy as np
import pytest

from ptz_selfcal.camera.geometry import normalise_homography, rotation_angle, transfer_error
from ptz_selfcal.sim.synthetic import CONFIGURATIONS, paper_sequence, project


@pytest.mark.parametrize("config", ["A", "B"])
def test_exact_sequence_has_exact_homographies(config: str) -> None:
    seq = paper_sequence(config, 0.0, seed=11)
    H_true = seq.H_true()
    grid = np.array([[0.0, 0.0], [639.0, 0.0], [0.0, 479.0], [639.0, 479.0], [319.5, 239.5]])
    for j in range(seq.n_frames):
        assert transfer_error(seq.H[j], H_true[j], grid).max() < 1e-6
        # Unit-determinant forms agree entrywise too (no hidden scale).
        np.testing.assert_allclose(normalise_homography(seq.H[j]), normalise_homography(H_true[j]), atol=1e-9)
    np.testing.assert_array_equal(seq.H[0], np.eye(3))


@pytest.mark.parametrize("config", ["A", "B"])
def test_sequence_geometry_matches_the_paper(config: str) -> None:
    radius, f_first, f_last = CONFIGURATIONS[config]
    seq = paper_sequence(config, 0.0, seed=3)
    assert seq.n_frames == 30 and seq.points.shape == (1000, 3)
    # Focal length linear from f_first to f_last, square pixels, zero skew, pp at the centre.
    np.testing.assert_allclose(seq.K[:, 1, 1], np.linspace(f_first, f_last, 30))
    np.testing.assert_allclose(seq.K[:, 0, 0], seq.K[:, 1, 1])
    np.testing.assert_array_equal(seq.K[:, 0, 1], 0.0)
    np.testing.assert_allclose(seq.K[:, :2, 2], np.tile([319.5, 239.5], (30, 1)))
    # Points in a 3 m cube centred 5 m in front (world +z).
    assert np.all(np.abs(seq.points - [0.0, 0.0, 5.0]) <= 1.5)
    # The principal ray runs on a cone of the configuration's half angle about +z, once round.
    axes = seq.R[:, 2, :]  # camera z axis in world coordinates (row 2 of world-to-camera R)
    cone = np.degrees(np.arccos(axes[:, 2]))
    np.testing.assert_allclose(cone, radius, atol=1e-9)
    azimuth = np.unwrap(np.arctan2(axes[:, 1], axes[:, 0]))
    assert abs(abs(azimuth[-1] - azimuth[0]) - 2 * np.pi * 29 / 30) < 1e-9
    # Rotations are proper and relative rotations reach twice the cone radius at most.
    assert np.allclose(np.linalg.det(seq.R), 1.0)
    max_relative = max(np.degrees(rotation_angle(R)) for R in seq.R_relative)
    assert 2 * radius * 0.95 < max_relative <= 2 * radius + 1e-9


def test_noise_is_gaussian_with_the_requested_sigma_and_visibility_is_honoured() -> None:
    sigma = 0.8
    seq = paper_sequence("A", sigma, seed=5)
    residuals = []
    for K, R, ids, xy in zip(seq.K, seq.R, seq.point_ids, seq.pixels):
        exact, front = project(K, R, seq.points[ids])
        assert front.all()
        assert np.all((exact >= 0) & (exact <= [639, 479]))
        residuals.append(xy - exact)
    res = np.concatenate(residuals)
    assert len(res) > 10000
    # Per-axis standard deviation within 3% (N > 10000 gives ~0.7% standard error) and zero mean.
    np.testing.assert_allclose(res.std(axis=0), sigma, rtol=0.03)
    assert np.all(np.abs(res.mean(axis=0)) < 0.03)


def test_same_seed_same_sequence_and_different_seed_differs() -> None:
    a = paper_sequence("B", 0.5, seed=7)
    b = paper_sequence("B", 0.5, seed=7)
    c = paper_sequence("B", 0.5, seed=8)
    np.testing.assert_array_equal(a.observations()[2], b.observations()[2])
    np.testing.assert_array_equal(a.H, b.H)
    assert not np.array_equal(a.points, c.points)


def test_noisy_homographies_stay_close_to_the_truth() -> None:
    seq = paper_sequence("A", 0.5, seed=2)
    H_true = seq.H_true()
    errors = []
    for j in range(1, 30):
        common = np.intersect1d(seq.point_ids[0], seq.point_ids[j])
        exact0, _ = project(seq.K[0], seq.R[0], seq.points[common])
        errors.append(np.sqrt(np.mean(transfer_error(seq.H[j], H_true[j], exact0) ** 2)))
    errors = np.array(errors)
    # Hundreds of correspondences at sigma 0.5 px: well sub-pixel transfer error where the points are,
    # but not exact.
    assert errors.max() < 0.3
    assert errors.min() > 1e-3


def test_principal_point_drift_is_linear_and_centred() -> None:
    seq = paper_sequence("A", 0.0, seed=1, principal_point_drift=20.0)
    pp = seq.K[:, :2, 2]
    np.testing.assert_allclose(np.linalg.norm(pp[-1] - pp[0]), 20.0)
    np.testing.assert_allclose(pp.mean(axis=0), [319.5, 239.5], atol=1e-9)
    steps = np.diff(pp, axis=0)
    np.testing.assert_allclose(steps, np.tile(steps[0], (29, 1)), atol=1e-12)
    # Homographies are still exact for the drifting principal point.
    H_true = seq.H_true()
    assert max(transfer_error(seq.H[j], H_true[j], pp[:1]).max() for j in range(30)) < 1e-6


def test_observations_are_consistent_with_per_frame_lists() -> None:
    seq = paper_sequence("B", 0.25, seed=4)
    frames, rays, xy = seq.observations()
    assert len(frames) == len(rays) == len(xy) == sum(len(ids) for ids in seq.point_ids)
    for i in (0, 17, 29):
        np.testing.assert_array_equal(rays[frames == i], seq.point_ids[i])
        np.testing.assert_array_equal(xy[frames == i], seq.pixels[i])


def test_unknown_configuration_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown configuration"):
        paper_sequence("C", 0.5, seed=0)
