"""The ports / corrections of cv2.detail's self-calibration helpers (benchmarks/opencv_peer.py, issue 8)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import opencv_peer

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation, rot_z

cv2 = pytest.importorskip("cv2")


def _rotations() -> list[np.ndarray]:
    angles = [(0.12, 0.05, 0.02), (-0.08, 0.11, -0.03), (0.03, -0.09, 0.08), (0.2, 0.15, 0.0)]
    return [rot_z(roll) @ ptz_rotation(pan, tilt) for pan, tilt, roll in angles]


def test_focals_from_homography_exact_different_focals() -> None:
    K0, K1 = intrinsic_matrix(900.0, 0.0, 0.0), intrinsic_matrix(1150.0, 0.0, 0.0)
    for R in _rotations():
        H = K1 @ R @ np.linalg.inv(K0)
        f0, f1, ok0, ok1 = opencv_peer.focals_from_homography(H / H[2, 2] * 3.7)
        assert ok0 and ok1
        assert f0 == pytest.approx(900.0, rel=1e-6)
        assert f1 == pytest.approx(1150.0, rel=1e-6)


def test_focals_from_homography_degenerate_is_not_ok() -> None:
    assert opencv_peer.focals_from_homography(np.eye(3))[2:] == (False, False)


def test_binding_focals_from_homography_returns_nothing() -> None:
    """Why the port exists: the binding cannot return the reference outputs."""
    assert cv2.detail.focalsFromHomography(np.eye(3), 0.0, 0.0, False, False) is None


def test_estimate_focal_median() -> None:
    K = intrinsic_matrix(1000.0, 0.0, 0.0)
    Hs = [K @ R @ np.linalg.inv(K) for R in _rotations()]
    assert opencv_peer.estimate_focal(Hs) == pytest.approx(1000.0, rel=1e-6)


@pytest.mark.parametrize("pp", [(0.0, 0.0), (655.3, 344.8), (-40.0, 25.0)])
def test_calibrate_rotating_camera_port_exact(pp: tuple[float, float]) -> None:
    K = intrinsic_matrix(1234.0, *pp, aspect=1.02, skew=0.01)
    Hs = [2.5 * K @ R @ np.linalg.inv(K) for R in _rotations()]
    np.testing.assert_allclose(opencv_peer.calibrate_rotating_camera(Hs), K, rtol=0, atol=1e-6 * 1234.0)


def test_binding_calibrate_rotating_camera_corrected() -> None:
    K = intrinsic_matrix(1234.0, 655.3, 344.8)
    Hs = [K @ R @ np.linalg.inv(K) for R in _rotations()]
    ok, K_raw = cv2.detail.calibrateRotatingCamera(Hs)
    assert ok
    # The binding's output is the transpose of the lower Cholesky factor of W = K K^T, not K.
    np.testing.assert_allclose(K_raw.T @ K_raw, K @ K.T * (K_raw.T @ K_raw)[2, 2], rtol=1e-6)
    assert not np.allclose(K_raw / K_raw[2, 2], K, rtol=1e-3)
    np.testing.assert_allclose(opencv_peer.correct_rotating_camera_k(K_raw), K, atol=1e-6 * 1234.0)
    np.testing.assert_allclose(opencv_peer.calibrate_rotating_camera_binding(Hs), K, atol=1e-6 * 1234.0)


def test_binding_correct_when_pp_at_origin() -> None:
    K = intrinsic_matrix(800.0, 0.0, 0.0)
    Hs = [K @ R @ np.linalg.inv(K) for R in _rotations()]
    _, K_raw = cv2.detail.calibrateRotatingCamera(Hs)
    np.testing.assert_allclose(K_raw / K_raw[2, 2], K, atol=1e-6 * 800.0)


def test_refinement_mask_order() -> None:
    mask = opencv_peer.refinement_mask("x_x_x")
    assert mask.tolist() == [[1, 0, 1], [0, 0, 1], [0, 0, 0]]


def test_upper_cholesky_is_the_upper_factor() -> None:
    K = intrinsic_matrix(950.0, 612.0, 371.0, aspect=0.98, skew=0.003)
    U = opencv_peer.upper_cholesky(7.0 * K @ K.T)
    assert np.allclose(np.tril(U, -1), 0.0)
    np.testing.assert_allclose(U, K, atol=1e-9 * 950.0)


def test_autostitch_focal_parses_scaled_blocks(tmp_path: Path) -> None:
    import peers

    block = "C:\\x\\img{0}.jpg\n384 512\n\n{1} 0 255.5\n0 {1} 191.5\n0 0 1\n\n1 0 0\n0 1 0\n0 0 1\n\n{2}\n\n"
    (tmp_path / "autostitch_pano.txt").write_text(block.format(0, 1, 700.0) + block.format(1, 2, 351.0))
    assert peers.autostitch_focal(tmp_path) == pytest.approx(701.0)
    assert peers.autostitch_focal(tmp_path / "missing") is None


def test_opencv_cache_key_follows_pixels_and_config() -> None:
    import peers

    images = [np.full((8, 10), k, np.uint8) for k in range(3)]
    config = opencv_peer.OpenCVConfig()
    key = peers.opencv_cache_key(images, config)
    assert key == peers.opencv_cache_key([im.copy() for im in images], config)
    changed = [im.copy() for im in images]
    changed[1][4, 5] += 1
    assert peers.opencv_cache_key(changed, config) != key
    assert peers.opencv_cache_key(images, opencv_peer.OpenCVConfig(features="orb")) != key


def test_opencv_cache_round_trip(tmp_path: Path) -> None:
    import peers

    K = np.array([intrinsic_matrix(900.0 + k, 320.0, 240.0) for k in range(2)])
    R = np.array([np.eye(3), ptz_rotation(0.1, 0.02)])
    res = opencv_peer.OpenCVResult(np.array([0, 2]), K, R, 12.5, 3.25, True, "", {"features": 1.0})
    path = tmp_path / "c" / "clean_key.npz"
    peers.save_opencv_result(path, res, 4.2)
    back, note = peers.load_opencv_result(path)
    np.testing.assert_array_equal(back.indices, [0, 2])
    np.testing.assert_allclose(back.K, K)
    np.testing.assert_allclose(back.R, R)
    assert (back.wall_time, back.cpu_time, back.ok, back.stage_times) == (12.5, 3.25, True, {"features": 1.0})
    assert "load at start 4.2" in note and "reused" in note
