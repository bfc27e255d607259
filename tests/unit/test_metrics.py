"""sim.metrics: the DESIGN.md section 7 metrics on hand-checked and synthetic cases."""

from __future__ import annotations

import numpy as np
import pytest

from ptz_selfcal.camera.distortion import division_lambda_for_corner_shift, division_to_plumb_bob
from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation, rot_z
from ptz_selfcal.sim import metrics


def test_focal_and_principal_point_errors() -> None:
    e = metrics.focal_errors([1010.0, 990.0, np.nan], [1000.0, 1000.0, 1000.0])
    np.testing.assert_allclose(e[:2], [0.01, 0.01])
    assert np.isnan(e[2])
    d = metrics.principal_point_errors([[3.0, 4.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(d, [5.0, 0.0])


def test_summaries_ignore_nan_and_split_after_warmup() -> None:
    s = metrics.summarise([1.0, 2.0, 3.0, np.nan])
    assert s["count"] == 3 and s["median"] == 2.0 and s["max"] == 3.0
    assert s["rms"] == pytest.approx(np.sqrt(14.0 / 3.0))
    assert metrics.summarise([])["count"] == 0
    assert metrics.warmup_frames(300) == 30 and metrics.warmup_frames(7) == 1
    assert metrics.warmup_frames(0) == 0
    values = np.r_[np.full(30, 100.0), np.full(270, 1.0)]
    split = metrics.summarise_split(values, metrics.warmup_frames(len(values)))
    assert split["all"]["max"] == 100.0
    assert split["after_warmup"]["max"] == 1.0 and split["after_warmup"]["count"] == 270


def test_frame_pairs_stride_validity_and_segments() -> None:
    pairs = metrics.frame_pairs(25, stride=10, max_partners=3)
    assert {tuple(p) for p in pairs} == {(i, i + 10) for i in range(15)} | {(i, i + 20) for i in range(5)}
    valid = np.ones(25, bool)
    valid[10] = False
    pairs = metrics.frame_pairs(25, stride=10, max_partners=3, valid=valid)
    assert not np.any(pairs == 10)
    segments = np.r_[np.zeros(12), np.ones(13)]
    pairs = metrics.frame_pairs(25, stride=10, max_partners=3, segments=segments)
    assert np.all(segments[pairs[:, 0]] == segments[pairs[:, 1]])
    assert len(metrics.frame_pairs(25, stride=10, first=20)) == 0


def test_pairwise_rotation_error_is_reference_free_and_detects_scaled_motion() -> None:
    rng = np.random.default_rng(3)
    pan = np.radians(rng.uniform(-40, 40, 50))
    tilt = np.radians(rng.uniform(-8, 8, 50))
    R_true = metrics.rotations_from_encoders(pan, tilt)
    # the estimate is relative to an arbitrary reference (any fixed right factor): zero error
    A = ptz_rotation(0.3, -0.1) @ rot_z(0.05)
    R_est = np.einsum("nij,jk->nik", R_true, A.T)
    pairs = metrics.frame_pairs(50, stride=3, max_partners=5)
    err = metrics.pairwise_rotation_errors(R_est, R_true, pairs)
    assert np.max(err) < 1e-9
    # motion under-estimated by 1% (what a focal over-estimate does): the error grows with the angle
    R_scaled = metrics.rotations_from_encoders(0.99 * pan, 0.99 * tilt)
    err = metrics.pairwise_rotation_errors(R_scaled, R_true, pairs)
    true_angles = metrics.pairwise_rotation_errors(np.tile(np.eye(3), (50, 1, 1)), R_true, pairs)
    np.testing.assert_allclose(err, 0.01 * true_angles, rtol=0.05, atol=1e-6)


def test_alignment_recovers_pan_tilt_path() -> None:
    pan = np.radians(np.linspace(-40, 40, 30))
    tilt = np.radians(8 * np.sin(np.linspace(0, 3, 30)))
    R_true = metrics.rotations_from_encoders(pan, tilt)
    R_est = np.einsum("nij,kj->nik", R_true, R_true[7])  # relative to frame 7 as reference
    A = metrics.align_rotations(R_est, R_true)
    path = metrics.pan_tilt_path(np.einsum("nij,jk->nik", R_est, A))
    np.testing.assert_allclose(path[:, 0], np.degrees(pan), atol=1e-6)
    np.testing.assert_allclose(path[:, 1], np.degrees(tilt), atol=1e-6)
    assert np.all(np.isnan(metrics.pan_tilt_path(np.full((1, 3, 3), np.nan))))


def test_coverage() -> None:
    assert metrics.coverage([1, 2, 3, 4], [4, 2, 1, 3, 99]) == 1.0
    assert metrics.coverage([1, 2, 3, 4], [1, 2]) == 0.5
    assert metrics.coverage([], []) == 1.0


def test_distortion_error_zero_for_the_equivalent_plumb_bob_and_large_when_ignored() -> None:
    width, height = 1280, 720
    K = intrinsic_matrix(900.0, 650.0, 350.0)
    lam = division_lambda_for_corner_shift(0.12, width, height, 900.0)
    k1, k2 = division_to_plumb_bob(lam, K, width, height)
    true = ("division", [lam], K)
    est_good = ("plumb_bob", [k1, k2, 0, 0, 0], K)
    est_none = ("plumb_bob", [0, 0, 0, 0, 0], K)
    errors = metrics.distortion_errors([est_good, est_none, None], [true, true, true], width, height)
    assert errors[0] < 1.0
    assert errors[1] > 50.0  # 12% of the 734 px half-diagonal, ignored
    assert np.isnan(errors[2])


def test_well_posed_frame_needs_two_degrees_about_each_of_two_axes() -> None:
    """Pan alone is never well posed; the first frame with >= 2 deg of tilt and of pan from the first frame
    is; NaN frames are skipped."""
    pan = np.radians(np.linspace(0.0, 10.0, 11))  # 1 deg per frame
    assert metrics.well_posed_frame(metrics.rotations_from_encoders(pan, np.zeros(11))) is None
    tilt = np.radians(np.r_[np.zeros(5), np.linspace(0.6, 3.6, 6)])  # 0.6 deg per frame from frame 5
    R = metrics.rotations_from_encoders(pan, tilt)
    r = np.degrees(metrics.rotation_vectors_from_first(R))
    assert np.allclose(r[0], 0.0) and abs(r[3, 1]) == pytest.approx(3.0, rel=1e-3)  # pan: about y
    assert metrics.well_posed_frame(R) == 8  # tilt 2.4 deg (x), pan 8 deg (y); 1.8 deg at frame 7
    R[8] = np.nan
    assert metrics.well_posed_frame(R) == 9


def test_figure_start_is_the_later_of_warmup_and_well_posed_plus_settle() -> None:
    t = np.arange(100) / 10.0  # 10 fps
    assert metrics.figure_start(t, 10, None) == 10
    assert metrics.figure_start(t, 10, 2) == 12  # 0.2 s + 1 s = frame 12
    assert metrics.figure_start(t, 10, 0) == 10
    assert metrics.figure_start(t, 10, 95) == 100  # nothing left
    assert metrics.figure_start(np.arange(30) / 2.0, 3, 5) == 7  # 2 fps: well posed + 2 frames


def test_sigma_coverage_and_run_level_error() -> None:
    f_true = np.full(6, 1000.0)
    f_est = np.array([1001.0, 1002.0, 1010.0, 999.0, np.nan, 1500.0])
    sigma = np.full(6, 1.0)
    mask = np.array([True, True, True, True, True, False])
    assert metrics.sigma_coverage(f_est, f_true, sigma, mask) == pytest.approx(0.75)  # 10 px is > 3 sigma
    assert np.isnan(metrics.sigma_coverage(f_est, f_true, sigma, np.zeros(6, bool)))
    run = metrics.run_level_error(f_est, f_true, sigma, mask)
    assert run["frames"] == 4 and run["error"] == pytest.approx(0.0015)  # median of 1, 2, 10, -1 px
    assert run["sigma"] == pytest.approx(np.median(1.0 / f_est[:4]))
    assert run["z"] == pytest.approx(run["error"] / run["sigma"])
    np.testing.assert_allclose(metrics.signed_focal_errors([990.0], [1000.0]), [-0.01])
    assert metrics.run_level_error(f_est, f_true, sigma, np.zeros(6, bool))["frames"] == 0
