"""frontend/rolling_shutter on exact synthetic data: points seen through a rolling shutter of a camera
rotating at a known rate (each row at its own time, solved exactly), corrected and estimated."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from ptz_selfcal.camera.geometry import apply_homography, intrinsic_matrix, ptz_rotation
from ptz_selfcal.frontend.homography import estimate_homography, max_deviation
from ptz_selfcal.frontend.rolling_shutter import (
    FrameMotion,
    combine,
    displacement,
    global_shutter,
    readout_step,
    rotation_motion,
    row_fraction,
    significant,
)

W, H = 960, 540
K = intrinsic_matrix(700.0, 478.0, 272.0)
DT = 0.04  # 25 frames/s


def pose(t: float, rate: tuple[float, float], start: tuple[float, float]) -> np.ndarray:
    """Head at constant pan/tilt rate (rad/s) from `start` (rad) at t = 0."""
    return ptz_rotation(start[0] + rate[0] * t, start[1] + rate[1] * t)


def observe(rays: np.ndarray, t: float, readout: float, rate, start) -> np.ndarray:
    """Rolling-shutter pixels of world rays in the frame stamped t: x = K R(t + s(y) readout) X, with y
    the row x itself is on (fixed point, converged to machine precision)."""
    x = project(K @ pose(t, rate, start), rays)
    for _ in range(30):
        s = row_fraction(x[:, 1], H)
        x = np.array([project(K @ pose(t + si * readout, rate, start), X[None])[0] for si, X in zip(s, rays)])
    return x


def project(P: np.ndarray, rays: np.ndarray) -> np.ndarray:
    x = rays @ P.T
    return x[:, :2] / x[:, 2:]


def world_rays(t: float, rate, start, count: int = 400, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    px = np.column_stack([rng.uniform(20, W - 21, count), rng.uniform(20, H - 21, count)])
    R = pose(t, rate, start)
    return (R.T @ np.linalg.inv(K) @ np.column_stack([px, np.ones(count)]).T).T


def motion_of(t: float, rate, start) -> FrameMotion:
    """The frame's global-shutter motion to the frame DT before it."""
    back = K @ pose(t - DT, rate, start) @ pose(t, rate, start).T @ np.linalg.inv(K)
    return FrameMotion(back=back, dt=DT)


def pair(readout: float, rate_kf, rate_cur, noise: float = 0.0, seed: int = 0):
    """A keyframe (stamp 0) and a frame (stamp 0.4 s) of one scene, each at its own rotation rate."""
    start_kf, t_cur = (0.0, 0.0), 0.4
    # the current frame's start chosen so that it sees about the same scene rotated by ~4 deg
    start_cur = (math.radians(4.0) - rate_cur[0] * t_cur, math.radians(1.0) - rate_cur[1] * t_cur)
    rays = world_rays(0.0, rate_kf, start_kf, seed=seed)
    x_kf = observe(rays, 0.0, readout, rate_kf, start_kf)
    x_cur = observe(rays, t_cur, readout, rate_cur, start_cur)
    rng = np.random.default_rng(seed + 1)
    x_kf = x_kf + noise * rng.standard_normal(x_kf.shape)
    x_cur = x_cur + noise * rng.standard_normal(x_cur.shape)
    H_true = K @ pose(t_cur, rate_cur, start_cur) @ pose(0.0, rate_kf, start_kf).T @ np.linalg.inv(K)
    return x_kf, x_cur, motion_of(0.0, rate_kf, start_kf), motion_of(t_cur, rate_cur, start_cur), H_true


def grid_error(H_est: np.ndarray, H_true: np.ndarray) -> float:
    g = np.stack(np.meshgrid(np.linspace(0, W - 1, 9), np.linspace(0, H - 1, 6)), -1).reshape(-1, 2)
    return float(np.max(np.linalg.norm(apply_homography(H_est, g) - apply_homography(H_true, g), axis=1)))


FAST, STILL = (math.radians(30.0), math.radians(3.0)), (0.0, 0.0)


def test_row_fraction_is_the_middle_row_at_zero_and_half_a_readout_at_the_ends():
    assert row_fraction([0.0, (H - 1) / 2, H - 1], H) == pytest.approx([-0.5, 0.0, 0.5])
    # working resolution at scale 0.5: the full-resolution rows' fractions
    y_work = (np.array([0.0, H - 1.0]) + 0.5) * 0.5 - 0.5
    assert row_fraction(y_work, H // 2, 0.5) == pytest.approx([-0.5, 0.5])


def test_correction_recovers_the_global_shutter_homography():
    readout = 0.03
    x_kf, x_cur, m_kf, m_cur, H_true = pair(readout, STILL, FAST)
    raw = grid_error(estimate_homography(x_kf, x_cur), H_true)
    gs_kf = global_shutter(x_kf, m_kf, readout, H)
    gs_cur = global_shutter(x_cur, m_cur, readout, H)
    corrected = grid_error(estimate_homography(gs_kf, gs_cur), H_true)
    assert raw > 5.0  # 30 deg/s over a 30 ms readout: a frame sheared by ~10 px
    assert corrected < 0.02 * raw and corrected < 0.15


@pytest.mark.parametrize("rates", [(STILL, FAST), (FAST, FAST), ((-0.5, 0.1), FAST)])
def test_estimation_recovers_the_readout(rates):
    readout = 0.03
    x_kf, x_cur, m_kf, m_cur, H_true = pair(readout, *rates, noise=0.05)
    d_kf, d_cur = displacement(x_kf, m_kf, H), displacement(x_cur, m_cur, H)
    tau, sigma, H_fit = readout_step(estimate_homography(x_kf, x_cur), x_kf, x_cur, d_kf, d_cur)
    assert tau == pytest.approx(readout, rel=0.05)
    assert sigma < 0.1 * readout and abs(tau - readout) < 4.0 * sigma
    assert grid_error(H_fit, H_true) < 0.3


def test_global_shutter_data_estimates_zero_and_nothing_is_applied():
    x_kf, x_cur, m_kf, m_cur, _ = pair(0.0, STILL, FAST, noise=0.05)
    d_kf, d_cur = displacement(x_kf, m_kf, H), displacement(x_cur, m_cur, H)
    tau, sigma, _ = readout_step(estimate_homography(x_kf, x_cur), x_kf, x_cur, d_kf, d_cur)
    assert abs(tau) < 4.0 * sigma
    assert not significant(tau, sigma, 0.002)


def test_no_motion_no_displacement_and_no_estimate():
    x = np.array([[10.0, 20.0], [500.0, 300.0]])
    assert np.all(displacement(x, None, H) == 0.0)
    assert np.all(global_shutter(x, None, 0.03, H) == x)
    x_kf, x_cur, *_ = pair(0.0, STILL, STILL)
    zero = np.zeros_like(x_kf)
    tau, sigma, _ = readout_step(estimate_homography(x_kf, x_cur), x_kf, x_cur, zero, zero, readout=0.01)
    assert tau == 0.01 and sigma == math.inf


def test_combine_is_a_weighted_median_robust_to_outliers():
    rng = np.random.default_rng(3)
    sig = rng.uniform(0.001, 0.004, 60)
    x = 0.03 + sig * rng.standard_normal(60)
    x[:8] = 0.2  # a few frames of another motion (a moving object, a cut)
    tau, sigma = combine(x, sig)
    assert tau == pytest.approx(0.03, abs=0.002)
    assert 0.0 < sigma < 0.002
    assert combine([], [])[0] != combine([], [])[0]  # NaN: nothing to combine
    assert significant(0.03, 0.001, 0.002) and significant(-0.03, 0.001, 0.002)
    assert not significant(0.03, 0.011, 0.002) and not significant(0.001, 0.0001, 0.002)


def test_the_motion_without_zoom_and_the_velocity_at_the_stamp():
    zoom = np.array([[1.02, 0.0, -0.02 * (W - 1) / 2], [0.0, 1.02, -0.02 * (H - 1) / 2], [0.0, 0.0, 1.0]])
    assert rotation_motion(zoom, (H, W)) == pytest.approx(np.eye(3), abs=1e-12)
    pan = motion_of(0.0, FAST, (0.0, 0.0))
    # a pan has (almost) no scale at the centre: left as it is, to 1 % of its 21 px
    assert max_deviation(rotation_motion(pan.back, (H, W)), pan.back, (H, W)) < 0.25
    # constant rate: the previous interval's generator is the same, the stamp's velocity is the interval's
    steady = FrameMotion(pan.back, DT, previous=(pan.interval_generator, DT))
    assert steady.generator == pytest.approx(pan.interval_generator, abs=1e-12)
    # a rate growing over the intervals is extrapolated half an interval on, to the stamp
    slower = FrameMotion(motion_of(0.0, (FAST[0] / 2, 0.0), (0.0, 0.0)).back, DT)
    faster = FrameMotion(pan.back, DT, previous=(slower.interval_generator, DT))
    expected = pan.interval_generator + 0.5 * (pan.interval_generator - slower.interval_generator)
    assert faster.generator == pytest.approx(expected)


def test_the_generator_is_the_motions_logarithm():
    pan = motion_of(0.0, FAST, (0.0, 0.0))
    back = expm(-DT * pan.generator)  # the series' logarithm, inverted
    assert back / back[2, 2] == pytest.approx(pan.back / pan.back[2, 2], abs=1e-9)
