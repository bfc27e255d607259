"""mosaic/live.py: the fixed canvas of the live mosaic, fed views rendered from a known panorama."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from ptz_selfcal.camera.geometry import intrinsic_matrix, intrinsics_full_to_work, ptz_rotation
from ptz_selfcal.mosaic.live import WEIGHT_CAP, LiveMosaic
from ptz_selfcal.mosaic.warp import FrameView
from ptz_selfcal.sim.render import build_panorama, render_view

PANORAMA = Path(__file__).resolve().parents[2] / "bags" / "source" / "examplepano.jpg"
W = 1024


@pytest.fixture(scope="module")
def grey_panorama() -> np.ndarray:
    image = cv2.resize(
        cv2.imread(str(PANORAMA), cv2.IMREAD_GRAYSCALE), (W, W // 2), interpolation=cv2.INTER_AREA
    )
    return image


def _view(pan: float, tilt: float, f: float = W / (2 * math.pi), size=(320, 180)) -> FrameView:
    K = intrinsic_matrix(f, (size[0] - 1) / 2 + 4.0, (size[1] - 1) / 2 - 3.0)
    return FrameView(K, (0.0, 0.0, 0.0), ptz_rotation(math.radians(pan), math.radians(tilt)), *size)


def test_frames_touch_only_their_footprint_and_match_the_panorama(grey_panorama: np.ndarray) -> None:
    pano = build_panorama(grey_panorama)
    live = LiveMosaic(W)
    assert live.nbytes == 2 * W * (W // 2)
    for k, (pan, tilt) in enumerate([(-30.0, 0.0), (0.0, 4.0), (25.0, -3.0), (178.0, 0.0)]):
        view = _view(pan, tilt)
        # a working image at half the full resolution: K is scaled to it
        K_work = intrinsics_full_to_work(view.K, 0.5)
        image = render_view(pano, K_work, view.R, (160, 90), level=0)
        before_grey, before_weight = live.grey.copy(), live.weight.copy()
        box = live.add(image, view)
        assert box is not None and live.frames == k + 1
        changed = (live.grey != before_grey) | (live.weight != before_weight)
        cols = np.zeros(W, bool)
        cols[np.arange(box.x0, box.x1) % W] = True
        outside = changed.copy()
        outside[box.y0 : box.y1, cols] = False
        assert changed.any() and not outside.any()  # the frame's own box only
    covered = cv2.erode((live.weight > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    cols = covered.any(axis=0)
    deg = (np.arange(W) + 0.5) * 360 / W - 180
    assert cols[np.abs(deg) < 40].all() and cols[np.abs(deg) > 179].all()
    assert not cols[(deg > 75) & (deg < 130)].any()  # 88 deg wide views at 25 and 178 deg
    diff = np.abs(live.grey[covered].astype(float) - grey_panorama[covered].astype(float))
    assert np.median(diff) <= 3.0
    assert live.weight.max() <= WEIGHT_CAP


def test_weights_saturate_and_new_views_take_over(grey_panorama: np.ndarray) -> None:
    pano = build_panorama(grey_panorama)
    live = LiveMosaic(W)
    view = _view(10.0, 0.0)
    image = render_view(pano, view.K, view.R, (view.width, view.height), level=0)
    for _ in range(10):
        live.add(image, view)
    assert live.weight.max() == 255
    centre = (W // 2 + round(10 * W / 360), W // 4)  # (x, y) of the view's centre
    for _ in range(10):  # the scene turns black: a live mosaic follows it
        live.add(np.zeros_like(image), view)
    assert live.grey[centre[1], centre[0]] < 10


def test_reset_and_encodings(grey_panorama: np.ndarray) -> None:
    live = LiveMosaic(512)
    view = _view(0.0, 0.0, f=512 / (2 * math.pi))
    live.add(np.full((180, 320), 200, np.uint8), view)
    jpeg = cv2.imdecode(np.frombuffer(live.encode("jpeg", 90), np.uint8), cv2.IMREAD_UNCHANGED)
    png = cv2.imdecode(np.frombuffer(live.encode("png"), np.uint8), cv2.IMREAD_UNCHANGED)
    assert jpeg.shape == (256, 512) and png.shape == (256, 512, 4)
    assert np.array_equal(png[:, :, 3] > 0, live.weight > 0)
    assert abs(int(jpeg[128, 256]) - 200) <= 2 and jpeg[10, 10] == 0
    with pytest.raises(ValueError):
        live.encode("tiff")
    live.reset()
    assert live.frames == 0 and not live.weight.any() and not live.grey.any()
