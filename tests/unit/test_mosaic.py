"""mosaic/: the projection maths on exact synthetic data, the warp, the gains and the blended mosaic."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.mosaic.blend import build_mosaic, column_runs, union_box
from ptz_selfcal.mosaic.projection import Projection, angular_distance, mosaic_width
from ptz_selfcal.mosaic.warp import (
    Box,
    FrameView,
    footprint,
    footprint_box,
    image_to_rays,
    rays_to_image,
    warp_frame,
)
from ptz_selfcal.sim.render import build_panorama, render_view

PANORAMA = Path(__file__).resolve().parents[2] / "bags" / "source" / "examplepano.jpg"
NO_DISTORTION = (0.0, 0.0, 0.0)


def _view(f: float, pan_deg: float, tilt_deg: float, w: int = 320, h: int = 240, D=NO_DISTORTION):
    K = intrinsic_matrix(f, (w - 1) / 2 + 7.0, (h - 1) / 2 - 5.0)
    return FrameView(K, D, ptz_rotation(math.radians(pan_deg), math.radians(tilt_deg)), w, h)


def test_principal_point_lands_at_pan_and_tilt() -> None:
    proj = Projection.spherical(3600)  # 10 px per degree
    for pan, tilt in [(0.0, 0.0), (30.0, 10.0), (-120.0, -25.0), (179.0, 40.0)]:
        view = _view(500.0, pan, tilt)
        ray = image_to_rays(view, [[view.K[0, 2], view.K[1, 2]]])
        x, y = proj.pixels_of_rays(ray)[0]
        assert x == pytest.approx(1800 - 0.5 + 10.0 * pan, abs=1e-9)
        assert y == pytest.approx(900 - 0.5 - 10.0 * tilt, abs=1e-9)


def test_off_axis_pixels_land_at_their_angles() -> None:
    """From a level camera a pixel f tan(a) right of the principal point is a degrees further in
    longitude; one f tan(b) above it is at latitude b (independent of the code's rotation maths)."""
    proj = Projection.spherical(7200)
    f, pan = 640.0, 25.0
    view = _view(f, pan, 0.0)
    cx, cy = view.K[0, 2], view.K[1, 2]
    a, b = math.radians(12.0), math.radians(-8.0)
    px = proj.pixels_of_rays(image_to_rays(view, [[cx + f * math.tan(a), cy], [cx, cy - f * math.tan(b)]]))
    s = 7200 / 360.0
    assert px[0, 0] == pytest.approx(3600 - 0.5 + s * (pan + 12.0), abs=1e-8)
    assert px[0, 1] == pytest.approx(1800 - 0.5, abs=1e-8)
    assert px[1, 0] == pytest.approx(3600 - 0.5 + s * pan, abs=1e-8)
    assert px[1, 1] == pytest.approx(1800 - 0.5 - s * (-8.0), abs=1e-8)


@pytest.mark.parametrize("kind", ["spherical", "cylindrical"])
def test_projection_round_trip(kind: str) -> None:
    proj = Projection.spherical(2048) if kind == "spherical" else Projection.cylindrical(2048, -1.0, 0.8)
    rng = np.random.default_rng(0)
    lat_lo, lat_hi = proj.lat_range()
    lon = rng.uniform(-math.pi, math.pi, 500)
    lat = rng.uniform(max(lat_lo, -1.5), min(lat_hi, 1.5), 500)
    rays = np.column_stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)]) * 3.0
    pixels = proj.pixels_of_rays(rays)
    assert np.all((pixels[:, 0] >= -0.5) & (pixels[:, 0] < 2048 - 0.5))
    assert np.all((pixels[:, 1] >= -0.5) & (pixels[:, 1] <= proj.height - 0.5))
    back = proj.rays_of_pixels(pixels)
    assert np.max(angular_distance(back, rays)) < 1e-12
    again = proj.pixels_of_rays(back)
    assert np.max(np.abs(again - pixels)) < 1e-9


def test_cylinder_rows_follow_tan_latitude() -> None:
    proj = Projection.cylindrical(3600, math.radians(-30.0), math.radians(45.0))
    s = 3600 / (2 * math.pi)
    assert proj.height == math.ceil(s * (1.0 + math.tan(math.radians(30.0))))
    assert float(proj.y_of_lat(math.radians(45.0))) == pytest.approx(-0.5)
    assert float(proj.y_of_lat(0.0)) == pytest.approx(s - 0.5)
    lo, hi = proj.lat_range()
    assert math.degrees(hi) == pytest.approx(45.0)
    assert math.degrees(lo) == pytest.approx(-30.0, abs=0.02)


def test_image_round_trip_with_plumb_bob() -> None:
    view = _view(420.0, -40.0, 15.0, D=(-0.18, 0.03, 0.0))
    g = np.stack(np.meshgrid(np.linspace(-0.5, 319.5, 17), np.linspace(-0.5, 239.5, 13)), -1).reshape(-1, 2)
    px, front = rays_to_image(view, image_to_rays(view, g))
    assert front.all()
    assert np.max(np.abs(px - g)) < 1e-8


def test_mosaic_width_is_one_pixel_per_pixel_at_the_longest_focal_length() -> None:
    assert mosaic_width(1000.0, 100000) == 6284  # ceil(2 pi 1000) = 6284, even
    assert mosaic_width(1000.3, 100000) % 2 == 0
    assert mosaic_width(5000.0, 8192) == 8192
    assert mosaic_width(5000.0, 8191) == 8192 - 0  # even: a spherical mosaic is exactly 2:1
    with pytest.raises(ValueError):
        mosaic_width(0.0, 8192)


def test_warp_samples_the_image_where_the_ray_lands() -> None:
    """A frame whose grey level is its own column coordinate: every warped pixel holds the column
    that rays_to_image gives for that mosaic pixel (bilinear sampling of a ramp is exact)."""
    view = _view(300.0, 170.0, -20.0, D=(-0.12, 0.01, 0.0))  # straddles the 180 deg seam
    ramp = np.tile(np.arange(view.width, dtype=np.float32), (view.height, 1))
    proj = Projection.spherical(2000)
    box = footprint_box(footprint(view), proj)
    assert box.x1 > proj.width  # unwrapped past the seam
    warped = warp_frame(ramp, view, proj, box)
    ys, xs = np.nonzero(warped.weight > 0.05)
    assert len(xs) > 1000
    rays = proj.rays_of_pixels(np.column_stack([xs + box.x0, ys + box.y0]))
    expected, front = rays_to_image(view, rays)
    assert front.all()
    assert np.max(np.abs(warped.pixels[ys, xs, 0] - expected[:, 0])) < 0.02  # cv2 bilinear: 1/32 px steps
    assert np.all((expected >= -0.5) & (expected <= [view.width - 0.5, view.height - 0.5]))


def test_a_pole_in_view_covers_every_longitude() -> None:
    fp = footprint(_view(200.0, 30.0, 85.0))
    assert fp.full_turn and fp.lat_max == pytest.approx(math.pi / 2)
    fp = footprint(_view(200.0, 30.0, 60.0))
    assert not fp.full_turn and fp.lat_max < math.pi / 2


def test_column_runs_and_union_wrap_round() -> None:
    assert column_runs(95, 105, 90, 100, 20) == [(0, 5, 10)]  # an unwrapped crop holds 90..109
    assert column_runs(95, 105, 0, 100, 100) == [(0, 95, 5), (5, 0, 5)]  # split at the seam
    assert column_runs(95, 105, 0, 100, 98) == [(0, 95, 3), (5, 0, 5)]  # clipped to the crop
    assert column_runs(0, 10, 0, 100, 100) == [(0, 0, 10)]
    box = union_box([Box(90, 110, 5, 9), Box(0, 20, 3, 8)], 100)
    assert (box.x0, box.x1, box.y0, box.y1) == (90, 120, 3, 9)
    assert union_box([Box(0, 60, 0, 1), Box(50, 110, 0, 1)], 100).x1 - union_box([], 100).x1 == 100


class _Frames:
    def __init__(self, views: list[FrameView], images: list[np.ndarray]) -> None:
        self.views, self._images = views, images

    def images(self, reduction: int) -> Iterator[tuple[int, np.ndarray]]:
        for i, image in enumerate(self._images):
            if reduction > 1:
                h, w = image.shape[:2]
                image = cv2.resize(image, (w // reduction, h // reduction), interpolation=cv2.INTER_AREA)
            yield i, image


@pytest.fixture(scope="module")
def small_panorama() -> np.ndarray:
    return cv2.resize(cv2.imread(str(PANORAMA)), (1024, 512), interpolation=cv2.INTER_AREA)


def test_mosaic_of_rendered_views_is_the_panorama(small_panorama: np.ndarray) -> None:
    """Views rendered at the panorama's own resolution (f = W / 2 pi), two of them 13 % darker
    (no clipping), two across the seam: the mosaic is the panorama where it is covered, exposure
    steps removed."""
    pano = build_panorama(small_panorama)
    f = 1024 / (2 * math.pi)
    poses = [(-40, 5), (-15, 0), (10, -5), (35, 3), (60, 8), (175, 0), (-165, 2)]
    views, images = [], []
    for k, (pan, tilt) in enumerate(poses):
        view = _view(f, pan, tilt, 160, 120)
        image = render_view(pano, view.K, view.R, (160, 120), level=0)
        if k in (1, 3):
            image = np.rint(image.astype(float) * 0.87).astype(np.uint8)
        views.append(view)
        images.append(image)
    result = build_mosaic(_Frames(views, images), max_width=1024)
    assert result.projection.width == 1024 and result.image.shape == (512, 1024, 4)
    assert result.frames == len(poses)
    assert result.gains[1] / result.gains[0] == pytest.approx(1 / 0.87, abs=0.02)
    assert result.gains[3] / result.gains[2] == pytest.approx(1 / 0.87, abs=0.02)
    covered = result.image[:, :, 3] > 0
    # covered where the views look, nowhere else: the columns of pan -67..87 deg and both seam ends
    cols = covered.any(axis=0)
    deg = (np.arange(1024) + 0.5) * 360 / 1024 - 180
    assert cols[np.abs(deg) < 60].all() and cols[np.abs(deg) > 178].all()
    assert not cols[(deg > 110) & (deg < 140)].any()
    inner = cv2.erode(covered.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    # the two groups of overlapping views have a gain each (nothing relates their exposures)
    for group in (np.abs(deg) < 100, np.abs(deg) > 100):
        sel = inner & group[None, :]
        mosaic, truth = result.image[:, :, :3][sel].astype(float), small_panorama[sel].astype(float)
        gain = float((mosaic * truth).sum() / (mosaic * mosaic).sum())
        assert abs(gain - 1.0) < 0.1
        assert np.median(np.abs(gain * mosaic - truth)) <= 3.0  # 5.7 without the exposure gains


def test_the_command_decodes_every_image_encoding_in_bgr() -> None:
    """tools/mosaic.decode_image: raw mono8/bgr8/rgb8/mono16 and compressed images, full and reduced."""
    from ptz_selfcal.tools import synth
    from ptz_selfcal.tools.bagio import serialize, typestore
    from ptz_selfcal.tools.mosaic import decode_image

    types = typestore().types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="c"
    )
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (32, 40, 3), dtype=np.uint8)
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)

    def decoded(fmt: str, payload: np.ndarray | bytes, reduction: int = 1) -> np.ndarray:
        msg = synth.image_msg(types, header, fmt, payload, (40, 32))
        msgtype = "sensor_msgs/msg/CompressedImage" if fmt in ("jpeg", "png") else "sensor_msgs/msg/Image"
        out = decode_image(msgtype, serialize(msg, msgtype), reduction)
        assert out is not None
        return out

    assert np.array_equal(decoded("bgr8", bgr), bgr)
    assert np.array_equal(decoded("rgb8", np.ascontiguousarray(bgr[:, :, ::-1])), bgr)
    assert np.array_equal(decoded("mono8", grey), np.repeat(grey[:, :, None], 3, axis=2))
    assert np.array_equal(decoded("png", cv2.imencode(".png", bgr)[1].tobytes()), bgr)
    ramp = np.repeat(np.tile(np.arange(0, 240, 6, dtype=np.uint8), (32, 1))[:, :, None], 3, axis=2)
    small = decoded("png", cv2.imencode(".png", ramp)[1].tobytes(), reduction=4)  # grey, 1/4 size
    assert small.shape == (8, 10) and np.abs(small.astype(float) - (np.arange(10) * 24 + 9)).max() <= 12
    assert decoded("bgr8", bgr, reduction=2).shape == (16, 20)
    deep = grey.astype("<u2") * 256 + 77  # mono16: the high byte is the grey level
    msg = types["sensor_msgs/msg/Image"](
        header=header, height=32, width=40, encoding="mono16", is_bigendian=0, step=80,
        data=np.frombuffer(deep.tobytes(), np.uint8),
    )  # fmt: skip
    out = decode_image("sensor_msgs/msg/Image", serialize(msg, "sensor_msgs/msg/Image"), 1)
    assert out is not None and np.array_equal(out, np.repeat(grey[:, :, None], 3, axis=2))
