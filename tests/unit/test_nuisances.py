"""sim/nuisances.py on exact data: rolling shutter rows, object masks, a followed target, photometry."""

from __future__ import annotations

import numpy as np
import pytest

from ptz_selfcal.camera.geometry import ptz_rotation
from ptz_selfcal.sim import nuisances as nz
from ptz_selfcal.sim.render import CameraProfile, build_panorama, render_view

SIZE = (320, 180)


@pytest.fixture(scope="module")
def panorama():
    rng = np.random.default_rng(5)
    texture = rng.integers(0, 256, (256, 512), dtype=np.uint8)
    return build_panorama(np.repeat(np.repeat(texture, 2, axis=0), 2, axis=1))


def _profile(**kw) -> CameraProfile:
    args = {"width": SIZE[0], "height": SIZE[1], "period": 4.0, "f_wide": 300.0, "zoom_max": 2.0}
    return CameraProfile(**{**args, **kw})


@pytest.mark.parametrize("corner_shift", [0.0, 0.08])
def test_zero_readout_is_the_global_shutter_frame_bit_for_bit(panorama, corner_shift):
    profile = _profile(corner_shift=corner_shift)
    for t in (0.0, 0.7, 2.0):
        state = profile.state(np.array([t]))
        ref = render_view(panorama, state.K(0), state.R(0), SIZE, float(state.lam[0]) or None)
        view, mask = nz.Nuisances(readout=0.0).render(panorama, profile, t)
        assert np.array_equal(view, ref)
        assert not mask.any()


def test_rolling_shutter_rows_are_seen_from_their_own_pose(panorama):
    """Row y is the global-shutter frame of the pose interpolated at y / (h - 1), bit for bit."""
    profile, t, readout = _profile(), 1.1, 0.05
    view, _ = nz.Nuisances(readout=readout).render(panorama, profile, t)
    times = nz.row_times(t, SIZE[1], readout)
    assert times[0] == pytest.approx(t - readout / 2) and times[-1] == pytest.approx(t + readout / 2)
    ends = profile.state(times[[0, -1]])
    state = profile.state(np.array([t]))
    global_view = render_view(panorama, state.K(0), state.R(0), SIZE)
    for y in (0, 67, SIZE[1] - 1):
        s = y / (SIZE[1] - 1)
        pan = ends.pan[0] + s * (ends.pan[1] - ends.pan[0])
        tilt = ends.tilt[0] + s * (ends.tilt[1] - ends.tilt[0])
        row = render_view(panorama, state.K(0), ptz_rotation(float(pan), float(tilt)), SIZE)[y]
        assert np.array_equal(view[y], row)
    # the first and last rows really moved (the test would pass on a global shutter otherwise)
    assert not np.array_equal(view[0], global_view[0]) and not np.array_equal(view[-1], global_view[-1])


def _white(obj):
    return type(obj)(**{**obj.__dict__, "texture": np.full_like(obj.texture, 255)})


def test_the_mask_covers_the_objects_exactly():
    """Objects of a white texture on a black scene: the moving mask is exactly the white pixels."""
    black = build_panorama(np.zeros((256, 512), np.uint8))
    profile = _profile()
    objects = nz.crossing_objects(3, black, profile, np.random.default_rng(1))
    white = nz.Nuisances(objects=tuple(_white(o) for o in objects), readout=0.02)
    for obj in objects:  # each object is in view at its own time
        view, mask = white.render(black, profile, obj.t_mid)
        assert mask.sum() > 0
        assert np.array_equal(mask, view)  # 255 on the objects, 0 elsewhere, in both
    covered = [white.render(black, profile, t)[1].mean() / 255 for t in np.linspace(0, profile.period, 9)]
    assert 0.0 < max(covered) < 0.2


def test_a_followed_target_is_static_in_the_image_only_while_followed(panorama):
    profile = _profile(zoom_max=1.0)  # no zoom: a followed target keeps its pixels exactly
    target = nz.followed_target(panorama, profile, 1.0, 2.5, np.random.default_rng(2))
    scene = nz.Nuisances(objects=(target,))
    frames = {t: scene.render(panorama, profile, t) for t in (0.5, 1.2, 2.0, 3.0)}
    _, mask_a = frames[1.2]
    _, mask_b = frames[2.0]
    assert 0.1 < mask_a.mean() / 255 < 0.25
    assert np.array_equal(mask_a, mask_b)
    hit = mask_a > 0
    # the target's pixels: the same (up to the rounding of rays through two rotations)
    change = frames[1.2][0][hit].astype(int) - frames[2.0][0][hit]
    assert np.abs(change).max() <= 1
    assert not np.array_equal(frames[1.2][0][~hit], frames[2.0][0][~hit])  # the background moved
    # before and after the window it stands still in the world: painted, but not masked as moving
    for t in (0.5, 3.0):
        view, mask = frames[t]
        assert not mask.any()
        plain = render_view(
            panorama, profile.state(np.array([t])).K(0), profile.state(np.array([t])).R(0), SIZE
        )
        assert not np.array_equal(view, plain)


def test_exposure_steps_change_the_mean_by_the_stated_gain():
    steps = nz.ExposureSteps(period=2.0)
    scene = nz.Nuisances(exposure=steps)
    grey = np.full(SIZE[::-1], 100, np.uint8)
    rng = np.random.default_rng(0)
    for t, gain in (
        (0.5, steps.gains[0]),
        (2.5, steps.gains[1]),
        (4.1, steps.gains[2]),
        (10.0, steps.gains[0]),
    ):
        assert steps.gain(t) == gain
        assert scene.expose(grey, t, np.zeros(2), rng).mean() == pytest.approx(100 * gain, abs=0.5)
    assert len(set(steps.gains)) > 1


def test_vignetting_is_one_at_the_centre_and_loses_the_strength_at_the_corner():
    w, h = SIZE
    gain = nz.vignetting_gain(SIZE, np.array([(w - 1) / 2, (h - 1) / 2]), 0.4)
    assert gain.max() == pytest.approx(1.0, abs=2e-3)
    assert gain[0, 0] == pytest.approx(0.6, abs=5e-3) and gain[-1, -1] == pytest.approx(0.6, abs=5e-3)
    assert np.all(np.diff(gain[h // 2, w // 2 :]) <= 0)  # falls off monotonically


def test_low_light_dims_and_adds_shot_noise():
    low = nz.LowLight(dim=0.25, electrons_per_level=2.0)
    scene = nz.Nuisances(low_light=low)
    bright = np.full((400, 400), 200, np.uint8)
    out = scene.expose(bright, 0.0, np.zeros(2), np.random.default_rng(3)).astype(float)
    assert out.mean() == pytest.approx(50.0, abs=0.2)
    assert out.var() == pytest.approx(50.0 / 2.0 + 1 / 12, rel=0.1)  # shot noise + rounding


def test_no_nuisance_changes_nothing(panorama):
    scene = nz.Nuisances()
    assert not scene.geometric and not scene.photometric
    image = np.arange(SIZE[0] * SIZE[1], dtype=np.uint8).reshape(SIZE[::-1])
    assert scene.expose(image, 1.0, np.zeros(2), np.random.default_rng(0)) is image
