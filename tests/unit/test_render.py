"""sim/render.py: the rendered views obey the ground-truth projection exactly, profiles and encoders."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ptz_selfcal.camera.distortion import division_corner_shift, division_distort, division_undistort
from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.sim.render import (
    CameraProfile,
    EncoderModel,
    ImageModel,
    ZoomEncoder,
    build_panorama,
    focal_from_hfov,
    gaussian_noise,
    is_equirectangular,
    pyramid_blend,
    render_view,
)
from ptz_selfcal.sim.synthetic import circle_rotations

PANO_W, PANO_H = 2048, 1024
BLOB_SIGMA = 2.0  # panorama pixels


def _lon_lat(world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent of render.py: longitude right of +z, latitude up (world y points down)."""
    X, Y, Z = world.T
    return np.arctan2(X, Z), np.arcsin(-Y / np.linalg.norm(world, axis=1))


def _blob_panorama(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Black equirectangular image with a Gaussian blob at each (lon, lat), pixel centres at integers."""
    xs = (lon + np.pi) / (2.0 * np.pi) * PANO_W - 0.5
    ys = (np.pi / 2.0 - lat) / np.pi * PANO_H - 0.5
    gx = np.arange(PANO_W, dtype=float)
    gy = np.arange(PANO_H, dtype=float)
    image = np.zeros((PANO_H, PANO_W), dtype=float)
    for x, y in zip(xs, ys):
        dx = np.minimum(np.abs(gx - x), PANO_W - np.abs(gx - x))  # wraps in longitude
        image += np.outer(np.exp(-0.5 * ((gy - y) / BLOB_SIGMA) ** 2), np.exp(-0.5 * (dx / BLOB_SIGMA) ** 2))
    return np.clip(np.rint(240.0 * image), 0, 255).astype(np.uint8)


def _centroid(image: np.ndarray, near: np.ndarray, half: int = 9) -> np.ndarray:
    x0, y0 = np.rint(near).astype(int)
    patch = image[y0 - half : y0 + half + 1, x0 - half : x0 + half + 1].astype(float)
    patch = np.maximum(patch - 2.0, 0.0)
    gy, gx = np.mgrid[-half : half + 1, -half : half + 1]
    return np.array([x0 + (gx * patch).sum() / patch.sum(), y0 + (gy * patch).sum() / patch.sum()])


@pytest.mark.parametrize(
    ("pan_deg", "tilt_deg", "lam"),
    [(20.0, 5.0, 0.0), (-35.0, -8.0, -0.12), (180.0, 3.0, 0.0), (179.5, -4.0, -0.2)],
)
def test_world_direction_lands_on_predicted_pixel(pan_deg: float, tilt_deg: float, lam: float) -> None:
    """Blobs painted at the world directions of chosen pixels are rendered on those pixels (incl.
    the division-model distortion and the longitude seam at pan 180 deg)."""
    w, h, f = 320, 240, 360.0
    K = intrinsic_matrix(f, 0.5 * (w - 1) + 13.0, 0.5 * (h - 1) - 9.0)
    R = ptz_rotation(np.radians(pan_deg), np.radians(tilt_deg))
    targets = np.array(
        [[160.0, 120.0], [30.3, 25.7], [290.6, 30.2], [25.2, 212.9], [296.8, 214.4], [100.5, 150.5]]
    )
    und = division_undistort(targets, lam, K[:2, 2], f) if lam else targets
    rays = (R.T @ np.linalg.inv(K) @ np.column_stack([und, np.ones(len(und))]).T).T
    lon, lat = _lon_lat(rays)
    view = render_view(build_panorama(_blob_panorama(lon, lat)), K, R, (w, h), lam or None)
    found = np.array([_centroid(view, t) for t in targets])
    assert np.max(np.linalg.norm(found - targets, axis=1)) < 0.06
    if lam:  # the same check through the forward model: distort(project(X)) = target
        proj = (K @ R @ rays.T).T
        predicted = division_distort(proj[:, :2] / proj[:, 2:], lam, K[:2, 2], f)
        np.testing.assert_allclose(predicted, targets, atol=1e-9)


def _smooth_panorama(seed: int = 3, sigma: float = 6.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, (512, 1024)).astype(np.float32)
    tiled = cv2.GaussianBlur(np.hstack([noise] * 3), (0, 0), sigma)  # periodic in longitude: no seam
    smooth = tiled[:, 1024:2048]
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min()) * 255.0
    return smooth.astype(np.uint8)


def test_pyramid_levels_are_aligned() -> None:
    """A view sampled from pyrDown levels 1 and 2 is not shifted against level 0 (x_L = x_0 / 2^L)."""
    pano = build_panorama(_smooth_panorama())
    K = intrinsic_matrix(120.0, 127.5, 95.5)
    R = ptz_rotation(0.4, 0.1)
    ref = render_view(pano, K, R, (256, 192), level=0).astype(np.float32)
    for level in (1, 2):
        view = render_view(pano, K, R, (256, 192), level=level).astype(np.float32)
        (dx, dy), _ = cv2.phaseCorrelate(ref, view)
        assert abs(dx) < 0.03 and abs(dy) < 0.03, (level, dx, dy)


def test_pyramid_blend_follows_focal_length() -> None:
    pano = build_panorama(_smooth_panorama())
    f_match = 1024 / (2.0 * np.pi)  # 1024-wide panorama: one level-0 pixel per output pixel
    assert pyramid_blend(pano, f_match * 3.0) == (0, 0.0)  # finer than the panorama: level 0 only
    assert pyramid_blend(pano, f_match) == (0, 0.0)
    level, w = pyramid_blend(pano, f_match / 2.0**0.25)
    assert level == 0 and w == pytest.approx(0.25)
    level, w = pyramid_blend(pano, f_match / 2.0**2.5)
    assert level == 2 and w == pytest.approx(0.5)


def test_blended_views_change_continuously_with_zoom() -> None:
    """Rendered at f(1 -+ 1e-6) across a level boundary, a view barely changes: no level jump."""
    pano = build_panorama(_smooth_panorama(sigma=1.0))
    R = ptz_rotation(0.2, 0.0)
    for s in (0.5, 1.0, 1.5, 2.0):  # ratio 2^s panorama pixels per output pixel
        f = 1024 / (2.0 * np.pi) / 2.0**s
        a = render_view(pano, intrinsic_matrix(f * (1 - 1e-6), 63.5, 47.5), R, (128, 96)).astype(int)
        b = render_view(pano, intrinsic_matrix(f * (1 + 1e-6), 63.5, 47.5), R, (128, 96)).astype(int)
        assert np.abs(a - b).mean() < 1.0 and np.abs(a - b).max() <= 2, s  # rounding; a level jump is ~10


def test_rendering_is_deterministic_and_wraps() -> None:
    pano = build_panorama(cv2.cvtColor(_smooth_panorama(), cv2.COLOR_GRAY2BGR))
    K = intrinsic_matrix(200.0, 100.0, 60.0)
    a = render_view(pano, K, ptz_rotation(np.pi, 0.0), (200, 120))
    b = render_view(pano, K, ptz_rotation(np.pi, 0.0), (200, 120))
    c = render_view(pano, K, ptz_rotation(-np.pi, 0.0), (200, 120))
    assert a.shape == (120, 200, 3) and a.dtype == np.uint8
    assert np.array_equal(a, b)
    assert np.abs(a.astype(int) - c.astype(int)).max() <= 1  # same view across the seam
    # no seam: the column where longitude wraps is as smooth as any other
    gray = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY).astype(float)
    steps = np.abs(np.diff(gray, axis=1)).mean(axis=0)
    assert steps.max() < 4.0 * np.median(steps) + 2.0


def test_non_equirectangular_rejected() -> None:
    assert is_equirectangular(4096, 2048) and not is_equirectangular(3000, 2000)
    with pytest.raises(ValueError, match="equirectangular"):
        build_panorama(np.zeros((200, 300), np.uint8))


def _profile(**kw: object) -> CameraProfile:
    base = dict(width=1280, height=720, period=10.0, f_wide=focal_from_hfov(1280, 60.0), corner_shift=0.12)
    base.update(kw)
    return CameraProfile(**base)  # type: ignore[arg-type]


def test_zoom_profile_monotone_and_bounded() -> None:
    p = _profile(zoom_max=3.0)
    t = np.linspace(0.0, 10.0, 301)
    f = p.focal(t)
    half = len(t) // 2
    assert np.all(np.diff(f[: half + 1]) > 0) and np.all(np.diff(f[half:]) < 0)
    assert f[0] == pytest.approx(p.f_wide) and f[-1] == pytest.approx(p.f_wide)
    assert f[half] == pytest.approx(3.0 * p.f_wide)
    pan, tilt = p.pan_tilt(t)
    assert np.max(np.abs(pan)) == pytest.approx(np.radians(40.0), rel=1e-3)
    assert np.max(np.abs(tilt)) == pytest.approx(np.radians(8.0), rel=1e-3)
    tri_pan, _ = _profile(waveform="triangle").pan_tilt(t)
    assert np.allclose(np.abs(np.diff(tri_pan[:60])), np.abs(np.diff(tri_pan[:60]))[0])  # constant speed


def test_lens_principal_point_and_distortion() -> None:
    p = _profile(pp_offset=(15.0, -10.0), pp_drift=(6.0, 4.0))
    np.testing.assert_allclose(p.principal_point(p.f_wide), [639.5 + 15.0, 359.5 - 10.0])
    np.testing.assert_allclose(p.principal_point(3.0 * p.f_wide), [639.5 + 21.0, 359.5 - 6.0])
    f = np.array([1.0, 1.5, 2.0, 3.0]) * p.f_wide
    lam = p.distortion_lambda(f)
    assert np.all(lam < 0)  # barrel
    shifts = [division_corner_shift(lm, 1280, 720, fi) for lm, fi in zip(lam, f)]
    np.testing.assert_allclose(shifts, 0.12 * p.f_wide / f, rtol=1e-12)  # shrinks as 1/f
    assert np.all(_profile(corner_shift=0.0).distortion_lambda(f) == 0.0)


def test_zoom_encoder_monotone_nonlinear_invertible() -> None:
    enc = ZoomEncoder(f_wide=1000.0, lens_ratio=20.0)
    f = np.linspace(1000.0, 3000.0, 200)
    c = enc.counts(f)
    assert c[0] == 0.0 and np.all(np.diff(c) > 0) and c[-1] < 16384.0
    np.testing.assert_allclose(enc.focal(c), f, rtol=1e-12)
    linear = c[0] + (c[-1] - c[0]) * (f - f[0]) / (f[-1] - f[0])
    assert np.max(np.abs(c - linear)) > 500.0  # clearly not linear in f


def test_encoder_lag_rate_and_noise() -> None:
    p = _profile()
    zoom = ZoomEncoder(p.f_wide)
    model = EncoderModel(rate=15.0, lag=0.04, pan_tilt_sigma=0.0, zoom_sigma=0.0)
    stamps = model.sample_times(0.0, 10.0)
    np.testing.assert_allclose(np.diff(stamps), 1.0 / 15.0)
    assert stamps[0] < 0.0 and stamps[-1] > 10.04  # every image stamp + lag is bracketed
    pan, tilt, counts = model.readings(p, zoom, stamps, np.random.default_rng(0))
    true_pan, true_tilt = p.pan_tilt(stamps - 0.04)  # stamped t = state at t - lag
    np.testing.assert_allclose(pan, true_pan, atol=1e-15)
    np.testing.assert_allclose(tilt, true_tilt, atol=1e-15)
    np.testing.assert_array_equal(counts, np.round(zoom.counts(p.focal(stamps - 0.04))))
    noisy = EncoderModel(rate=15.0, lag=0.04, pan_tilt_sigma=np.radians(0.01), zoom_sigma=2.0)
    pan_n, _, counts_n = noisy.readings(p, zoom, stamps, np.random.default_rng(0))
    assert np.degrees(np.std(pan_n - true_pan)) == pytest.approx(0.01, rel=0.3)
    assert np.all(counts_n == np.round(counts_n)) and 0.5 < np.std(counts_n - counts) < 4.0


def test_image_model_noise_and_gain() -> None:
    noise = gaussian_noise((400, 500), 2.0, np.random.default_rng(1))
    assert abs(noise.mean()) < 0.02 and noise.std() == pytest.approx(2.0, rel=0.02)
    model = ImageModel(noise_sigma=2.0, brightness_drift=0.1, period=10.0)
    assert model.gain(2.5) == pytest.approx(1.1) and model.gain(7.5) == pytest.approx(0.9)
    image = np.full((100, 120, 3), 100, np.uint8)
    a = model.apply(image, 2.5, np.random.default_rng([7, 2, 0]))
    b = model.apply(image, 2.5, np.random.default_rng([7, 2, 0]))
    assert np.array_equal(a, b)
    assert a.mean() == pytest.approx(110.0, abs=0.2) and a.std() == pytest.approx(2.0, rel=0.1)
    clean = ImageModel(noise_sigma=0.0, brightness_drift=0.0).apply(image, 1.0, np.random.default_rng(0))
    assert np.array_equal(clean, image)


def _optical_axes(pan: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """(n, 3) world directions of the principal ray: the third row of R (R maps world to camera)."""
    return np.array([ptz_rotation(p, t)[2] for p, t in zip(pan, tilt)])


def test_circle_motion_is_the_papers_circle() -> None:
    """The principal ray stays on a cone of the given half angle about world +z, equally spaced over one
    turn, and frame for frame the rotations of sim/synthetic.py (section 4.1)."""
    n, fps = 30, 2.0
    p = _profile(
        period=(n - 1) / fps, motion="circle", circle_radius=np.radians(3.5), circle_period=n / fps,
        corner_shift=0.0,
    )  # fmt: skip
    pan, tilt = p.pan_tilt(np.arange(n) / fps)
    axes = _optical_axes(pan, tilt)
    np.testing.assert_allclose(np.degrees(np.arccos(axes[:, 2])), 3.5, atol=1e-9)
    phase = np.unwrap(np.arctan2(-axes[:, 1], axes[:, 0]))
    np.testing.assert_allclose(np.diff(phase), 2.0 * np.pi / n, atol=1e-9)
    R = np.array([ptz_rotation(a, b) for a, b in zip(pan, tilt)])
    np.testing.assert_allclose(R, circle_rotations(n, 3.5), atol=1e-12)
    assert pan[0] == pytest.approx(np.radians(3.5)) and tilt[0] == pytest.approx(0.0, abs=1e-15)


def test_linear_zoom_law_and_drift() -> None:
    """zoom_law linear: f from f_wide to f_wide * zoom_max linearly in time (held outside the sequence);
    a principal point drift is then linear in time too."""
    p = _profile(f_wide=800.0, zoom_max=1400.0 / 800.0, zoom_law="linear", pp_drift=(6.0, -4.0), period=14.5)
    t = np.linspace(0.0, 14.5, 30)
    f = p.focal(t)
    np.testing.assert_allclose(f, np.linspace(800.0, 1400.0, 30), rtol=1e-12)
    np.testing.assert_allclose(p.focal([-1.0, 20.0]), [800.0, 1400.0], rtol=1e-12)
    pp = p.principal_point(f)
    np.testing.assert_allclose(pp[-1] - pp[0], [6.0, -4.0], atol=1e-9)
    np.testing.assert_allclose(np.diff(pp, axis=0), np.diff(pp, axis=0)[:1].repeat(29, 0), atol=1e-9)


def test_slow_start_ramps_the_speed_and_keeps_the_path() -> None:
    """slow_start S: the head barely moves at first (speed ~ (t/S)^2), reaches full speed by S, and the
    path still runs from where it starts to where it ends (pan, tilt and zoom alike)."""
    plain, slow = _profile(corner_shift=0.0), _profile(corner_shift=0.0, slow_start=3.0)
    t = np.linspace(0.0, 10.0, 1001)
    for a, b in zip(plain.pan_tilt(t), slow.pan_tilt(t)):
        assert a[0] == b[0] and a[-1] == pytest.approx(b[-1], abs=1e-12)
    pan, _ = slow.pan_tilt(t)
    speed = np.abs(np.diff(pan)) / np.diff(t)
    full = np.abs(np.diff(plain.pan_tilt(t)[0]) / np.diff(t))
    assert speed[:50].max() < 0.05 * full[:50].max()  # the first 0.5 s: under 5% of the plain speed
    assert slow.clock(np.array([3.0, 6.0, 10.0]))[-1] == pytest.approx(10.0)
    assert np.all(np.diff(slow.clock(t)) > 0)  # time never runs back
    assert slow.focal(10.0) == pytest.approx(plain.focal(10.0))


def test_patrol_pans_far_tilts_little_and_dwells() -> None:
    """patrol: pan from -A to +A and back, the tilt's small wave beside it, the head still for `dwell`
    seconds at each turn."""
    p = _profile(
        corner_shift=0.0, motion="patrol", pan_amplitude=np.radians(30.0), tilt_amplitude=np.radians(1.5),
        pan_cycles=2.0, tilt_cycles=1.0, dwell=1.0, period=20.0,
    )  # fmt: skip
    t = np.linspace(0.0, 20.0, 2001)
    pan, tilt = p.pan_tilt(t)
    assert np.degrees(pan[0]) == pytest.approx(-30.0) and np.degrees(pan.max()) == pytest.approx(30.0)
    assert np.degrees(np.abs(tilt).max()) == pytest.approx(1.5, rel=1e-3)
    moving = np.hypot(np.diff(pan), np.diff(tilt)) > 1e-12
    assert (~moving).sum() == pytest.approx(3 * 100, abs=3)  # three turns (not at the ends), 1 s each
    still = np.flatnonzero(~moving)
    assert np.allclose(np.degrees(np.abs(pan[still])), 30.0)  # it holds at the turns
    with pytest.raises(ValueError, match="dwell"):
        _profile(motion="patrol", pan_cycles=2.0, dwell=4.0, period=10.0)
