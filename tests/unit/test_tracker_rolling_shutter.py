"""HomographyTracker on frames the project's renderer exposes through a rolling shutter (sim/nuisances:
row y at t + (y / (h - 1) - 1/2) readout, pan and tilt linear across the rows): the readout is estimated,
and the homographies it publishes are the global-shutter camera's at the stamps."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from conftest import SOURCE_PANORAMA

from ptz_selfcal.camera.geometry import apply_homography
from ptz_selfcal.frontend.rolling_shutter import MIN_READOUT
from ptz_selfcal.frontend.tracker import HomographyTracker
from ptz_selfcal.frontend.tracker_config import TrackerConfig
from ptz_selfcal.sim.nuisances import Nuisances
from ptz_selfcal.sim.render import CameraProfile, build_panorama

W, H, FPS, FRAMES = 640, 360, 25.0, 60
READOUT = 0.03
SCALE = 0.5


@pytest.fixture(scope="module")
def sequence() -> dict[float, tuple[list[np.ndarray], list[np.ndarray]]]:
    """readout -> (working images, ground-truth reference -> frame homographies, full resolution) of a
    pan at ~30 deg/s slowing to ~25 (a sine sweep's first part), no zoom."""
    panorama = build_panorama(cv2.imread(str(SOURCE_PANORAMA), cv2.IMREAD_GRAYSCALE))
    period = (FRAMES - 1) / FPS
    profile = CameraProfile(width=W, height=H, period=period, f_wide=480.0, zoom_max=1.0, tilt_cycles=0.2,
                            pan_amplitude=math.radians(120.0), pan_cycles=0.1,
                            tilt_amplitude=math.radians(4.0), pp_offset=(6.0, -4.0))  # fmt: skip
    times = np.arange(FRAMES) / FPS
    state = profile.state(times)
    Hs = [state.K(i) @ state.R(i) @ state.R(0).T @ np.linalg.inv(state.K(0)) for i in range(FRAMES)]
    out = {}
    for readout in (0.0, READOUT):
        scene = Nuisances(readout=readout)
        images = []
        for t in times:
            view, _ = scene.render(panorama, profile, float(t))
            images.append(cv2.resize(view, (int(W * SCALE), int(H * SCALE)), interpolation=cv2.INTER_AREA))
        out[readout] = (images, Hs)
    return out


def run(images: list[np.ndarray], readout: float) -> tuple[HomographyTracker, list]:
    tracker = HomographyTracker(TrackerConfig(rolling_shutter_readout=readout))
    results = [tracker.track(image, SCALE, stamp=i / FPS) for i, image in enumerate(images)]
    return tracker, results


def errors(results, Hs) -> np.ndarray:
    """Per frame: largest transfer error (full-resolution px) over a grid of the reference image."""
    grid = np.stack(np.meshgrid(np.linspace(40, W - 41, 8), np.linspace(30, H - 31, 5)), -1).reshape(-1, 2)
    out = []
    for r, H_true in zip(results, Hs):
        if r.H_ref is None:
            out.append(np.inf)
            continue
        seen = apply_homography(H_true, grid)
        inside = np.all((seen > 0) & (seen < [W - 1, H - 1]), axis=1)
        if inside.sum() < 6:
            continue
        out.append(np.max(np.linalg.norm(apply_homography(r.H_ref, grid[inside]) - seen[inside], axis=1)))
    return np.asarray(out)


def keyframe_errors(results, Hs) -> np.ndarray:
    """Per frame: largest transfer error (full-resolution px) of H_keyframe over a grid of the frame."""
    grid = np.stack(np.meshgrid(np.linspace(40, W - 41, 8), np.linspace(30, H - 31, 5)), -1).reshape(-1, 2)
    out = []
    for r in results:
        H_true = Hs[r.frame_index] @ np.linalg.inv(Hs[r.keyframe_id])
        if r.keyframe_id == r.frame_index:
            continue
        in_keyframe = apply_homography(np.linalg.inv(H_true), grid)
        error = apply_homography(r.H_keyframe, in_keyframe) - grid
        out.append(np.max(np.linalg.norm(error, axis=1)))
    return np.asarray(out)


def test_the_readout_is_estimated_and_the_homographies_are_global_shutter(sequence):
    images, Hs = sequence[READOUT]
    tracker, results = run(images, -1.0)
    estimator = tracker.readout
    assert estimator.estimate == pytest.approx(READOUT, rel=0.1)
    assert estimator.sigma < 0.1 * READOUT and estimator.applied == estimator.estimate
    late = results[FRAMES // 2 :]
    assert all(r.readout == pytest.approx(READOUT, rel=0.1) for r in late)
    _, plain = run(images, 0.0)  # the model off: what the tracker did before it
    assert all(r.readout == 0.0 for r in plain)
    # keyframe -> frame homographies once the readout is applied: a global shutter's
    corrected, uncorrected = keyframe_errors(late, Hs), keyframe_errors(plain[FRAMES // 2 :], Hs)
    assert np.median(uncorrected) > 0.25  # a 30 ms readout at ~30 deg/s: no homography between frames
    assert np.median(corrected) < 0.25 * np.median(uncorrected)
    # chained to the reference: keyframes made before the estimate was significant keep their error
    assert np.median(errors(results[10:], Hs[10:])) < 0.6 * np.median(errors(plain[10:], Hs[10:]))
    # the published links are global-shutter points too: they fit their homography
    links = [link for r in late for link in r.links]
    assert links
    for link in links:
        residual = apply_homography(link.H, link.source_points) - link.target_points
        assert np.sqrt(np.mean(np.sum(residual**2, axis=1))) < 1.0


def test_a_known_readout_is_used_as_given(sequence):
    images, Hs = sequence[READOUT]
    tracker, results = run(images, READOUT)
    assert tracker.readout.applied == READOUT and tracker.readout.settled
    assert all(r.readout == READOUT for r in results if r.H_ref is not None and r.frame_index > 0)
    assert np.median(errors(results[10:], Hs[10:])) < 0.2


def test_a_global_shutter_camera_is_tracked_exactly_as_without_the_model(sequence):
    images, _ = sequence[0.0]
    tracker, estimated = run(images, -1.0)
    _, off = run(images, 0.0)
    assert abs(tracker.readout.estimate) < max(3.0 * tracker.readout.sigma, MIN_READOUT)
    assert tracker.readout.applied == 0.0
    for a, b in zip(estimated, off):
        assert a.state == b.state and a.readout == 0.0
        assert (a.H_ref is None and b.H_ref is None) or np.array_equal(a.H_ref, b.H_ref)
