"""The live mosaic: a fixed spherical canvas that each frame updates on its own footprint only.

Memory is the canvas, fixed at construction (one grey byte and one weight byte per mosaic pixel), not
the frames seen. A frame is warped onto its footprint box (mosaic/warp.py) and blended into a running
weighted mean there: c <- (c w + p v) / (w + v), with v the frame's feather weight. The stored weight
saturates at WEIGHT_CAP, so that a pixel seen by many frames still follows the newest views (the scene
changes; a live background should too).
"""

from __future__ import annotations

import cv2
import numpy as np

from ptz_selfcal.mosaic.blend import column_runs
from ptz_selfcal.mosaic.projection import Projection
from ptz_selfcal.mosaic.warp import Box, FrameView, footprint, footprint_box, warp_frame

# Stored weight of a frame's centre pixel (uint8 units), and the most a pixel accumulates (about four
# frames: the fifth view of a pixel still moves it by a fifth).
WEIGHT_UNIT = 64.0
WEIGHT_CAP = 255.0
FORMATS = ("jpeg", "png")
# A frame is warped in strips of this many mosaic rows: the warp's float arrays stay a few MB whatever
# the canvas, where a whole footprint at 8192 columns would need tens.
STRIP_ROWS = 128


class LiveMosaic:
    """An equirectangular (spherical) canvas of `width` x `width` / 2 pixels, grey, in the frame of the
    orientations it is given."""

    def __init__(self, width: int) -> None:
        self.projection = Projection.spherical(width)
        shape = (self.projection.height, self.projection.width)
        self.grey = np.zeros(shape, np.uint8)
        self.weight = np.zeros(shape, np.uint8)
        self.frames = 0

    @property
    def nbytes(self) -> int:
        return self.grey.nbytes + self.weight.nbytes

    def reset(self) -> None:
        """A new mosaic (a new calibration reference: the old orientations mean nothing in it)."""
        self.grey.fill(0)
        self.weight.fill(0)
        self.frames = 0

    def add(self, image: np.ndarray, view: FrameView) -> Box | None:
        """Blend a grey uint8 image (full size or reduced: K is scaled to it) into its footprint;
        returns the box it touched (columns unwrapped), None when it faces nothing of the canvas."""
        box = footprint_box(footprint(view), self.projection)
        if box.empty:
            return None
        for y0 in range(box.y0, box.y1, STRIP_ROWS):
            self._blend(image, view, Box(box.x0, box.x1, y0, min(y0 + STRIP_ROWS, box.y1)))
        self.frames += 1
        return box

    def _blend(self, image: np.ndarray, view: FrameView, box: Box) -> None:
        warped = warp_frame(image, view, self.projection, box)
        rows = slice(box.y0, box.y1)
        W = self.projection.width
        for src, dst, n in column_runs(box.x0, box.x1, 0, W, W):
            v = warped.weight[:, src : src + n] * np.float32(WEIGHT_UNIT)
            if not v.any():
                continue
            c = self.grey[rows, dst : dst + n]
            w = self.weight[rows, dst : dst + n]
            total = w + v
            # c + (p - c) v / (w + v), in place and unmasked: exactly c (and the weight w) where v is 0
            mean = warped.pixels[:, src : src + n, 0].astype(np.float32)
            mean -= c
            mean *= v
            mean /= np.maximum(total, np.float32(1e-6))
            mean += c
            c[...] = np.rint(mean, out=mean)
            w[...] = np.minimum(total, np.float32(WEIGHT_CAP), out=total)

    def encode(self, fmt: str = "jpeg", jpeg_quality: int = 85) -> bytes:
        """The canvas as JPEG (grey, black where nothing was seen) or PNG (BGRA, alpha 0 there)."""
        if fmt == "jpeg":
            ok, data = cv2.imencode(".jpg", self.grey, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
        elif fmt == "png":
            alpha = np.where(self.weight > 0, 255, 0).astype(np.uint8)
            bgra = np.dstack([self.grey, self.grey, self.grey, alpha])
            ok, data = cv2.imencode(".png", bgra, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        else:
            raise ValueError(f"unknown mosaic format {fmt!r} (expected one of {', '.join(FORMATS)})")
        if not ok:
            raise ValueError("the mosaic could not be encoded")
        return data.tobytes()
