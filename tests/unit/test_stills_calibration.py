"""online/stills_calibration on exact synthetic data: the pose of each still under the final solve.

The stills of a hand-held 360 degree set overlap by a third of the image (as the real rotation sets
do): a chain of free homographies fitted to such narrow overlaps does not give the rotations (K^-1 H K
of it is not a rotation), the bundle adjustment's rotations do, and they close the loop."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from conftest import SOURCE_PANORAMA

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation, rotation_angle
from ptz_selfcal.frontend.keyframe_links import KeyframeLink
from ptz_selfcal.online.stills_calibration import calibrate_stills, still_poses
from ptz_selfcal.sim import metrics

SIZE = (320, 400)  # portrait, as a hand-held set
F = 0.5 * SIZE[0] / math.tan(math.radians(16.0))  # 32 degrees across: 20 degree steps overlap by a third
K = intrinsic_matrix(F, 0.5 * (SIZE[0] - 1), 0.5 * (SIZE[1] - 1))
N_STILLS = 18


def hand_held(n: int = N_STILLS, seed: int = 4) -> np.ndarray:
    """World-to-camera rotations of a 360 degree pan in 20 degree steps 15 degrees below the horizon (the
    textured ground, not the sky) with a hand's tilt and roll."""
    rng = np.random.default_rng(seed)
    pan = np.radians(360.0 * np.arange(n) / n + rng.uniform(-1.0, 1.0, n))
    tilt = np.radians(-15.0 + rng.uniform(-2.0, 2.0, n))
    roll = np.radians(rng.uniform(-1.0, 1.0, n))
    return np.array([ptz_rotation(p, t, r) for p, t, r in zip(pan, tilt, roll, strict=True)])


def angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return math.degrees(rotation_angle(A @ B.T))


def link(R: np.ndarray, i: int, j: int) -> KeyframeLink:
    """An exact link still i -> still j (eq. 8): H = K R_j R_i^T K^-1, a few inliers."""
    H = K @ R[j] @ R[i].T @ np.linalg.inv(K)
    pts = np.array([[50.0, 60.0], [200.0, 80.0], [120.0, 300.0], [260.0, 350.0]])
    proj = np.c_[pts, np.ones(4)] @ H.T
    return KeyframeLink(i, j, H, pts, proj[:, :2] / proj[:, 2:], 0.0)


def test_held_stills_keep_their_adjusted_pose_and_the_others_follow_their_links() -> None:
    R = hand_held(6)
    R_rel = np.array([Ri @ R[0].T for Ri in R])  # reference (still 0) -> still
    held = {0: (K, R_rel[0]), 1: (K, R_rel[1]), 2: (K, R_rel[2])}
    # still 3 through its link from 2, still 4 (linked only to 3) through 3, still 5 linked to nothing;
    # the link 0 -> 2 disagrees with the adjusted poses (a drifting chain): held poses are kept
    wrong = link(R, 0, 2)
    wrong = KeyframeLink(
        0, 2, wrong.H @ np.diag([1.03, 0.97, 1.0]), wrong.source_points, wrong.target_points, 0
    )
    links = [link(R, 0, 1), wrong, link(R, 2, 3), link(R, 4, 3)]  # 4 -> 3: walked backwards
    poses = still_poses(held, links, range(6))
    assert sorted(poses) == [0, 1, 2, 3, 4]
    for i in range(3):
        assert poses[i][1] is not None and np.allclose(poses[i][1], R_rel[i], atol=1e-12)
    for i in (3, 4):
        assert angle_deg(poses[i][1], R_rel[i]) < 1e-6
        assert np.allclose(poses[i][0], K)
    assert sorted(still_poses(held, links, [0, 3])) == [0, 3]  # only the stills asked for


@pytest.fixture(scope="module")
def rendered() -> tuple[list[np.ndarray], np.ndarray]:
    from ptz_selfcal.sim.render import build_panorama, render_view

    pano = build_panorama(cv2.imread(str(SOURCE_PANORAMA), cv2.IMREAD_GRAYSCALE))
    R = hand_held()
    return [render_view(pano, K, Ri, SIZE) for Ri in R], R


def test_a_360_degree_set_is_placed_by_the_adjustment_and_closes(rendered) -> None:
    images, R = rendered
    cal = calibrate_stills(((image, 1.0) for image in images), 0.5)
    assert cal.indices == list(range(N_STILLS)) and not cal.skipped
    assert cal.size == SIZE
    assert abs(cal.K[0][0, 0] / F - 1.0) < 0.005
    # every still's orientation after one global rotation (the gauge), and each step: within two pixels'
    # angle (0.1 degree per pixel here) where K^-1 H K of the tracker's chain is degrees off
    A = metrics.align_rotations(np.array(cal.R), R)  # world -> the calibration's reference
    rel_err = [angle_deg(cal.R[i] @ A, R[i]) for i in range(N_STILLS)]
    step_err = [
        angle_deg(cal.R[(i + 1) % N_STILLS] @ cal.R[i].T, R[(i + 1) % N_STILLS] @ R[i].T)
        for i in range(N_STILLS)
    ]
    assert max(rel_err) < 0.2, np.round(rel_err, 3)
    assert max(step_err) < 0.2, np.round(step_err, 3)  # the last -> first step: the loop closes
