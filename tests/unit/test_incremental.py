"""Incremental calibrator API: O(1) per-frame K (eq. 20), bounded keyframes, state, persistence."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from ptz_selfcal.camera.geometry import (
    image_motion,
    infinite_homography,
    intrinsic_matrix,
    ptz_rotation,
    relative_rotation,
    rotation_angle,
)
from ptz_selfcal.camera.intrinsics import SQUARE_CONSTANT_PP, SQUARE_VARYING_PP
from ptz_selfcal.online.incremental import IncrementalCalibrator, Keyframe, lm_solver
from ptz_selfcal.selfcal.lm import lm_selfcalibration
from ptz_selfcal.selfcal.transfer import focal_disagrees, intrinsics_from_transferred_diac
from ptz_selfcal.status import CalibrationStatus

SIZE = (640, 480)
CENTRE = (319.5, 239.5)


def sequence(n: int, radius_deg: float = 5.0, f0: float = 800.0, f1: float = 1400.0):
    """Paper 4.1 style: principal ray on a circle, linear zoom; returns K, world R and exact H."""
    phi = 2.0 * np.pi * np.arange(n) / n
    r = np.radians(radius_deg)
    R = np.array([ptz_rotation(r * np.cos(a), r * np.sin(a)) for a in phi])
    K = np.array([intrinsic_matrix(f, *CENTRE) for f in np.linspace(f0, f1, n)])
    H = np.array([infinite_homography(K[0], K[j], relative_rotation(R[0], R[j])) for j in range(n)])
    return K, R, H


def rel_err(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.max(np.abs(A - B)) / B[1, 1])


def test_per_frame_intrinsics_equal_batch_answer_on_exact_data() -> None:
    K, R, H = sequence(30)
    keyframes = list(range(1, 30, 2))
    calibrator = IncrementalCalibrator(SIZE, max_keyframes=20)
    for j in keyframes:
        calibrator.add_keyframe(j, H[j], stamp=0.1 * j)
    calibrator.reoptimise()  # over every keyframe, as the batch solve below
    assert calibrator.state in (CalibrationStatus.CALIBRATING, CalibrationStatus.CONVERGED)
    batch = lm_selfcalibration(np.concatenate([H[:1], H[keyframes]]), SIZE)
    assert rel_err(calibrator.reference_K, batch.K[0]) < 1e-6
    for j in range(30):  # keyframes and frames that never were keyframes
        K_j, R_j, sigma_f = calibrator.frame_intrinsics(H[j])
        assert rel_err(K_j, K[j]) < 1e-6
        assert rotation_angle(R_j @ relative_rotation(R[0], R[j]).T) < 1e-7
        assert np.isfinite(sigma_f) and sigma_f >= 0.0
    for n, j in enumerate(keyframes):
        assert rel_err(calibrator.frame_intrinsics(H[j])[0], batch.K[n + 1]) < 1e-6


def test_varying_pp_model_per_frame_intrinsics() -> None:
    K, _, H = sequence(20)
    calibrator = IncrementalCalibrator(SIZE, SQUARE_VARYING_PP)
    for j in range(1, 20):
        calibrator.add_keyframe(j, H[j])
    for j in (0, 7, 19):
        assert rel_err(calibrator.frame_intrinsics(H[j])[0], K[j]) < 1e-6


def test_states_initialising_then_calibrating_then_converged() -> None:
    _, _, H = sequence(30)
    calibrator = IncrementalCalibrator(SIZE, min_rotation_deg=2.0)
    assert calibrator.state is CalibrationStatus.INITIALISING
    assert np.allclose(calibrator.frame_intrinsics(H[1])[0][:2, 2], CENTRE, atol=30.0)  # prior still answers
    states = []
    for j in range(1, 30):  # as the session drives it: re-solve after each keyframe once initialised
        initialised = calibrator.calibrated
        state = calibrator.add_keyframe(j, H[j])
        states.append(calibrator.reoptimise() if initialised else state)
    assert states[0] is CalibrationStatus.INITIALISING  # 0.5 deg of rotation only
    assert CalibrationStatus.CALIBRATING in states
    assert states[-1] is CalibrationStatus.CONVERGED


def test_keyframes_after_initialisation_are_stored_without_a_solve() -> None:
    """add_keyframe solves once, when the motion first is well posed; re-solves are reoptimise's."""
    _, _, H = sequence(30)
    calibrator = IncrementalCalibrator(SIZE)
    j = 1
    while not calibrator.calibrated:
        calibrator.add_keyframe(j, H[j])
        j += 1
    first, state = calibrator.last_solve, calibrator.state
    for k in range(j, 30):
        assert calibrator.add_keyframe(k, H[k]) is state
        assert calibrator.last_solve is first
    assert len(calibrator.keyframes) == 29
    calibrator.reoptimise()
    assert calibrator.last_solve is not first


def test_pan_only_motion_is_degenerate() -> None:
    n = 20
    K = np.array([intrinsic_matrix(f, *CENTRE) for f in np.linspace(800.0, 1000.0, n)])
    R = np.array([ptz_rotation(a, 0.0) for a in np.radians(np.linspace(0.0, 15.0, n))])
    calibrator = IncrementalCalibrator(SIZE)
    for j in range(1, n):
        state = calibrator.add_keyframe(j, infinite_homography(K[0], K[j], relative_rotation(R[0], R[j])))
    assert state is CalibrationStatus.DEGENERATE_MOTION
    assert not calibrator.calibrated


def test_state_round_trip_through_yaml() -> None:
    K, _, H = sequence(30)
    calibrator = IncrementalCalibrator(SIZE, max_keyframes=12)
    for j in range(1, 30):
        calibrator.add_keyframe(f"kf{j}", H[j], stamp=float(j))
    restored = IncrementalCalibrator.from_dict(yaml.safe_load(yaml.safe_dump(calibrator.to_dict())))
    assert restored.state is calibrator.state
    assert len(restored.keyframes) == len(calibrator.keyframes) <= 12
    assert np.array_equal(restored.reference_K, calibrator.reference_K)
    assert rel_err(restored.frame_intrinsics(H[11])[0], K[11]) < 1e-6
    restored.reoptimise()
    assert rel_err(restored.reference_K, K[0]) < 1e-6
    # a state saved while the calibrator had a solve_interval still loads (the key is ignored)
    legacy = {**calibrator.to_dict(), "solve_interval": 1_000_000_000}
    assert IncrementalCalibrator.from_dict(legacy).to_dict() == calibrator.to_dict()


def test_solver_seam_receives_keyframe_records() -> None:
    _, _, H = sequence(16)
    seen: list[int] = []

    def solver(H_set, image_size, model, K_init, keyframes: list[Keyframe], max_nfev: int):
        seen.append(sum(kf.matches is not None for kf in keyframes))
        return lm_solver(H_set, image_size, model, K_init, keyframes, max_nfev)

    calibrator = IncrementalCalibrator(SIZE, solver=solver)
    for j in range(1, 16):
        calibrator.add_keyframe(j, H[j], matches={"points": np.zeros((4, 2))})
    assert calibrator.calibrated
    assert calibrator.reoptimise(max_seconds=0.05) is calibrator.state
    assert seen and seen[-1] == 15


def test_unbounded_run_keeps_keyframes_and_cost_bounded() -> None:
    """5000 frames, each offered as a keyframe: what each call works on stays bounded (the keyframe set
    and the saved state do not grow), so its cost does too; the per-call time itself is measured by the
    core soak in benchmarks/reliability.py, not asserted on a shared CI machine."""
    n, max_keyframes = 5000, 25
    t = np.arange(n) / 50.0
    pan = np.radians(20.0) * np.sin(0.31 * t)
    tilt = np.radians(8.0) * np.sin(0.53 * t + 0.4)
    f = 1100.0 + 500.0 * np.sin(0.17 * t)
    K0 = intrinsic_matrix(f[0], *CENTRE)
    R0 = ptz_rotation(pan[0], tilt[0])
    calibrator = IncrementalCalibrator(SIZE, max_keyframes=max_keyframes)
    state_size: dict[int, int] = {}
    worst = 0.0
    for i in range(1, n):
        K_i = intrinsic_matrix(f[i], *CENTRE)
        H = infinite_homography(K0, K_i, relative_rotation(R0, ptz_rotation(pan[i], tilt[i])))
        calibrator.add_keyframe(i, H, stamp=float(t[i]))
        if calibrator.calibrated and i % 500 == 0:
            calibrator.reoptimise()  # a periodic re-solve over the bounded set
            state_size[i] = len(json.dumps(calibrator.to_dict()))
        K_est, _, _ = calibrator.frame_intrinsics(H)
        assert len(calibrator.keyframes) <= max_keyframes
        if calibrator.calibrated and i % 250 == 0:
            worst = max(worst, rel_err(K_est, K_i))
    assert calibrator.state is CalibrationStatus.CONVERGED
    assert worst < 1e-6
    assert len(calibrator.keyframes) == max_keyframes
    early, late = state_size[1000], state_size[4500]
    assert late <= 1.1 * early, state_size  # the same bounded set, not a growing history


def test_near_ambiguous_solution_is_kept_but_reported() -> None:
    """Config B, varying pp, sigma = 2 px (section 6.2): the estimate is kept as the best available,
    with state DEGENERATE_MOTION and a large sigma_f, never as CONVERGED."""
    from ptz_selfcal.frontend.homography import estimate_homography

    K, R, _ = sequence(30, radius_deg=3.5, f0=1200.0, f1=2000.0)
    rng = np.random.default_rng(0)
    X = rng.uniform(-1.5, 1.5, (1000, 3)) + np.array([0.0, 0.0, 5.0])
    pts, vis = [], []
    for Kj, Rj in zip(K, R):
        p = X @ (Kj @ Rj).T
        p = p[:, :2] / p[:, 2:]
        vis.append(np.all((p >= 0.0) & (p <= [SIZE[0] - 1.0, SIZE[1] - 1.0]), axis=1))
        pts.append(p + rng.normal(0.0, 2.0, p.shape))
    calibrator = IncrementalCalibrator(SIZE, SQUARE_VARYING_PP)
    for j in range(1, 30):
        m = vis[0] & vis[j]
        state = calibrator.add_keyframe(j, estimate_homography(pts[0][m], pts[j][m]))
    assert state is CalibrationStatus.DEGENERATE_MOTION
    assert calibrator.calibrated
    K_j, _, sigma_f = calibrator.frame_intrinsics(np.eye(3))
    assert sigma_f / K_j[1, 1] > 0.02
    assert "near_ambiguous" in calibrator.message


def test_image_motion_of_a_pan_and_a_zoom_in_image_widths() -> None:
    K = intrinsic_matrix(800.0, *CENTRE)
    H0 = np.eye(3)
    # pan by atan(64 / 800): the centre moves 64 px = 0.1 widths, the corners a little more
    H_pan = infinite_homography(K, K, ptz_rotation(math.atan(64.0 / 800.0), 0.0))
    moved = image_motion(H0, H_pan, *SIZE)
    assert 0.1 <= moved < 0.13
    # zoom 1.1x about the centre: the corners move 10 % of their distance to it
    H_zoom = infinite_homography(K, intrinsic_matrix(880.0, *CENTRE), np.eye(3))
    assert abs(image_motion(H0, H_zoom, *SIZE) - 0.1 * math.hypot(*CENTRE) / SIZE[0]) < 1e-9
    # the motion between two frames does not depend on the common reference
    G = infinite_homography(K, K, ptz_rotation(0.3, -0.1))
    assert abs(image_motion(H_pan @ G, H_zoom @ G, *SIZE) - image_motion(H_pan, H_zoom, *SIZE)) < 1e-9
    assert image_motion(H0, H0, *SIZE) == 0.0
    # a corner behind the camera (90 deg pan at this focal length) is an unbounded motion
    assert (
        image_motion(H0, infinite_homography(K, K, ptz_rotation(math.radians(89.0), 0.0)), *SIZE) == math.inf
    )


def test_focal_disagrees_in_log_f_beyond_the_floor_or_the_sigmas() -> None:
    # the DIAC transfer of a homography with a wrong image scale implies a wrong f (eq. 20)
    K_ref, K = intrinsic_matrix(800.0, *CENTRE), intrinsic_matrix(1200.0, *CENTRE)
    R = ptz_rotation(0.05, 0.02)
    good = infinite_homography(K_ref, K, R)
    scale = np.array([[1.25, 0, -0.25 * CENTRE[0]], [0, 1.25, -0.25 * CENTRE[1]], [0, 0, 1]])
    f_good = intrinsics_from_transferred_diac(good, K_ref, SQUARE_CONSTANT_PP, SIZE)[1, 1]
    f_wrong = intrinsics_from_transferred_diac(scale @ good, K_ref, SQUARE_CONSTANT_PP, SIZE)[1, 1]
    assert abs(f_good / 1200.0 - 1) < 1e-9 and abs(f_wrong / 1500.0 - 1) < 1e-6
    assert not focal_disagrees(f_good, 1200.0, 1200.0, 0.01, 4.0, 0.1)
    assert focal_disagrees(f_wrong, 1200.0, 1200.0, 0.01, 4.0, 0.1)
    # symmetric in log f, floor and sigmas
    assert focal_disagrees(1200.0 / 1.12, 1200.0, 1200.0, 0.0, 4.0, 0.1)
    assert not focal_disagrees(1200.0 / 1.09, 1200.0, 1200.0, 0.0, 4.0, 0.1)
    assert not focal_disagrees(f_wrong, 1200.0, 1200.0, 0.06, 4.0, 0.1)  # 4 sigma = 24 % > 22 %
    # an interval prediction: inside it nothing disagrees
    assert not focal_disagrees(1500.0, 1000.0, 1600.0, 0.0, 4.0, 0.1)
    assert focal_disagrees(1800.0, 1000.0, 1600.0, 0.0, 4.0, 0.1)
    # no usable value: disagrees (never trust it)
    assert focal_disagrees(math.nan, 1200.0, 1200.0, 0.01, 4.0, 0.1)
    assert focal_disagrees(-1.0, 1200.0, 1200.0, 0.01, 4.0, 0.1)


@pytest.mark.parametrize("min_keyframes", [2, 3, 4])
def test_the_first_solve_comes_with_the_min_keyframes_th_keyframe(min_keyframes: int) -> None:
    """Keyframes 8 degrees off the reference about both axes, zooming: the motion is well posed from the
    first keyframe on, so the first solve comes with keyframe number min_keyframes, not one later."""
    _, _, H = sequence(32, radius_deg=8.0)
    calibrator = IncrementalCalibrator(SIZE, min_keyframes=min_keyframes)
    states = [calibrator.add_keyframe(j, H[j]) for j in (8, 16, 24, 31)]
    initialising = [s is CalibrationStatus.INITIALISING for s in states]
    assert initialising == [k < min_keyframes - 1 for k in range(4)], states
