"""Blending: one gain per frame (exposure compensation), feathered accumulation, the mosaic builder.

Two passes over the frames. Pass 1 warps every frame at low resolution (a reduced decode) and solves
one gain per frame from the mean intensities of every overlapping pair, OpenCV's GainCompensator
least squares (cv2.detail: sum over pairs N_ij ((g_i I_ij - g_j I_ji)^2 / sigma_n^2 + (1 - g_i)^2 /
sigma_g^2)) with a weaker prior, written out here because the cv2.detail binding needs every warped
image in memory at once and knows nothing of longitude wrapping. Pass 2 warps at full resolution and
accumulates gain * weight * pixels and weight in the bounding box of everything seen, so memory is
bounded by the covered region, not by the number of frames.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np

from ptz_selfcal.mosaic.projection import SPHERICAL, Projection, mosaic_width
from ptz_selfcal.mosaic.warp import Box, Footprint, FrameView, Warped, footprint, footprint_box, warp_frame

# Intensity noise (grey levels, GainCompensator's) and a gain prior (1 sigma around 1) weaker than its 0.1,
# which pulls a 10 % exposure step to 7 %: the prior only has to fix the overall scale.
GAIN_SIGMA_N = 10.0
GAIN_SIGMA_G = 1.0
# Partners per frame in the gain solve at most (long bags: every k-th pair, all frames still linked).
GAIN_MAX_PARTNERS = 120
# Exposure pass: a typical frame's width on the coarse surface (pixels).
GAIN_FRAME_WIDTH = 48


class FrameSource(Protocol):
    """The frames of a mosaic: their geometry up front, their images on demand (twice)."""

    views: Sequence[FrameView]

    def images(self, reduction: int) -> Iterator[tuple[int, np.ndarray]]:
        """(index into views, image) for every frame, decoded at 1/reduction size (1, 2, 4 or 8);
        grey for reduction > 1 is enough, BGR (uint8) at reduction 1."""
        ...


@dataclass(frozen=True)
class MosaicResult:
    image: np.ndarray  # (H, W, 4) uint8 BGRA, alpha 255 where a frame covers the pixel
    projection: Projection
    gains: np.ndarray
    frames: int
    crop: Box  # the accumulated region (columns unwrapped)


def column_runs(x0: int, x1: int, origin: int, period: int, limit: int) -> list[tuple[int, int, int]]:
    """(source offset, destination start, length) runs that place unwrapped columns [x0, x1) into an
    array of `limit` columns starting at unwrapped column `origin` (columns modulo `period`)."""
    runs = []
    x = x0
    while x < x1:
        dst = (x - origin) % period
        n = min(x1 - x, period - dst)  # up to the wrap point
        if dst < limit:
            runs.append((x - x0, dst, min(n, limit - dst)))
        x += n
    return runs


def overlap_columns(a: Box, b: Box, period: int) -> list[tuple[int, int]]:
    """Unwrapped column intervals (in a's numbering) where boxes a and b overlap."""
    out = []
    for k in (-period, 0, period):
        lo, hi = max(a.x0, b.x0 + k), min(a.x1, b.x1 + k)
        if hi > lo:
            out.append((lo, hi))
    return out


def solve_gains(warps: Sequence[Warped], period: int, max_partners: int = GAIN_MAX_PARTNERS) -> np.ndarray:
    """One gain per frame from the pairwise overlaps of low-resolution grey warps (module doc)."""
    n = len(warps)
    A = np.zeros((n, n))
    b = np.zeros(n)
    alpha, beta = 1.0 / GAIN_SIGMA_N**2, 1.0 / GAIN_SIGMA_G**2
    stride = max(1, math.ceil(n / max_partners))
    for i in range(n):
        wi = warps[i]
        for j in range(i + 1, n, stride if n > max_partners else 1):
            wj = warps[j]
            r0, r1 = max(wi.box.y0, wj.box.y0), min(wi.box.y1, wj.box.y1)
            if r1 <= r0:
                continue
            for lo, hi in overlap_columns(wi.box, wj.box, period):
                ia = (slice(r0 - wi.box.y0, r1 - wi.box.y0), slice(lo - wi.box.x0, hi - wi.box.x0))
                shift = lo - ((lo - wj.box.x0) % period + wj.box.x0)  # a's numbering minus b's
                jb = (
                    slice(r0 - wj.box.y0, r1 - wj.box.y0),
                    slice(lo - shift - wj.box.x0, hi - shift - wj.box.x0),
                )
                both = (wi.weight[ia] > 0) & (wj.weight[jb] > 0)
                count = int(both.sum())
                if count == 0:
                    continue
                Ii = float(wi.pixels[ia][..., 0][both].mean())
                Ij = float(wj.pixels[jb][..., 0][both].mean())
                for p, q, Ip, Iq in ((i, j, Ii, Ij), (j, i, Ij, Ii)):
                    b[p] += beta * count
                    A[p, p] += beta * count + 2.0 * alpha * Ip * Ip * count
                    A[p, q] -= 2.0 * alpha * Ip * Iq * count
    alone = np.diag(A) == 0.0  # frames that overlap nothing keep gain 1
    A[alone, alone] = 1.0
    b[alone] = 1.0
    return np.linalg.solve(A, b)


class Accumulator:
    """Sum of weight * gain * pixels and of weights over a crop of the mosaic (columns wrap)."""

    def __init__(self, projection: Projection, crop: Box, channels: int) -> None:
        self.projection, self.crop = projection, crop
        h, w = crop.y1 - crop.y0, crop.x1 - crop.x0
        self.sum = np.zeros((h, w, channels), np.float32)
        self.weight = np.zeros((h, w), np.float32)

    def add(self, warped: Warped, gain: float = 1.0, scale: float = 1.0) -> None:
        box = warped.box
        r0, r1 = max(box.y0, self.crop.y0), min(box.y1, self.crop.y1)
        if r1 <= r0:
            return
        src_rows = slice(r0 - box.y0, r1 - box.y0)
        dst_rows = slice(r0 - self.crop.y0, r1 - self.crop.y0)
        w = warped.weight[src_rows] * np.float32(scale)
        p = warped.pixels[src_rows] * (w * np.float32(gain))[:, :, None]
        runs = column_runs(box.x0, box.x1, self.crop.x0, self.projection.width, self.sum.shape[1])
        for src, dst, n in runs:
            self.sum[dst_rows, dst : dst + n] += p[:, src : src + n]
            self.weight[dst_rows, dst : dst + n] += w[:, src : src + n]

    def image(self) -> np.ndarray:
        """The full mosaic, BGRA uint8 (alpha 0 where nothing was seen)."""
        W, H = self.projection.width, self.projection.height
        channels = self.sum.shape[2]
        out = np.zeros((H, W, 4), np.uint8)
        covered = self.weight > 0
        mean = self.sum / np.where(covered, self.weight, 1.0)[:, :, None]
        mean = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
        if channels == 1:
            mean = np.repeat(mean, 3, axis=2)
        tile = np.concatenate([mean, np.where(covered, 255, 0).astype(np.uint8)[:, :, None]], axis=2)
        rows = slice(self.crop.y0, self.crop.y1)
        for src, dst, n in column_runs(0, tile.shape[1], -self.crop.x0, W, W):
            out[rows, dst : dst + n] = tile[:, src : src + n]
        return out


def union_box(boxes: Sequence[Box], width: int) -> Box:
    """The smallest box (columns unwrapped, starting in [0, W)) that holds every box modulo W."""
    boxes = [b for b in boxes if not b.empty]
    if not boxes:
        return Box(0, 0, 0, 0)
    seen = np.zeros(width, bool)
    for box in boxes:
        for _, dst, n in column_runs(box.x0, box.x1, 0, width, width):
            seen[dst : dst + n] = True
    y0, y1 = min(b.y0 for b in boxes), max(b.y1 for b in boxes)
    if seen.all():
        return Box(0, width, y0, y1)
    # the crop starts right after the longest circular run of unseen columns
    start = int(np.argmin(seen))  # an unseen column
    rolled = np.roll(seen, -start)
    best_len, best_end, run = 0, 0, 0
    for k, s in enumerate(rolled):
        run = 0 if s else run + 1
        if run > best_len:
            best_len, best_end = run, k + 1
    x0 = (start + best_end) % width
    return Box(x0, x0 + width - best_len, y0, y1)


def _reduction(width: int, target: float) -> int:
    """The largest reduced decode (8, 4, 2) that keeps the image at least `target` pixels wide."""
    for r in (8, 4, 2):
        if width / r >= target:
            return r
    return 1


def _exposure_gains(
    source: FrameSource,
    views: Sequence[FrameView],
    footprints: Sequence[Footprint],
    boxes: Sequence[Box],
    kind: str,
    width: int,
    progress: Callable[[str, int, int], None] | None,
) -> np.ndarray:
    """Pass 1: every frame warped onto a coarse surface (a typical frame GAIN_FRAME_WIDTH pixels wide;
    overlap means need no detail), one gain per frame (solve_gains)."""
    n = len(views)
    typical = float(np.median([b.x1 - b.x0 for b in boxes if not b.empty] or [width]))
    low = make_projection(
        kind, min(width, max(64, 2 * round(width * GAIN_FRAME_WIDTH / (2 * typical)))), footprints
    )
    low_boxes = [footprint_box(fp, low) for fp in footprints]
    widths = [b.x1 - b.x0 for b in low_boxes]
    r = _reduction(min(v.width for v in views), 2.0 * float(np.median(widths)))
    warps: list[Warped | None] = [None] * n
    for done, (i, image) in enumerate(source.images(r), start=1):
        grey = image if image.ndim == 2 else image.mean(axis=2).astype(np.float32)
        target = max(8, widths[i])
        if grey.shape[1] > 2 * target:  # area-average first: bilinear sampling would alias
            size = (target, max(4, round(grey.shape[0] * target / grey.shape[1])))
            grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
        warps[i] = warp_frame(grey, views[i], low, low_boxes[i])
        if progress:
            progress("exposure", done, n)
    gains = np.ones(n)
    present = [i for i in range(n) if warps[i] is not None]
    gains[present] = solve_gains([warps[i] for i in present], low.width)
    return gains


def make_projection(kind: str, width: int, footprints: Sequence[Footprint]) -> Projection:
    if kind == SPHERICAL:
        return Projection.spherical(width)
    lat_min, lat_max = min(f.lat_min for f in footprints), max(f.lat_max for f in footprints)
    return Projection.cylindrical(width, lat_min, lat_max)


def resolution_weight(view: FrameView, f_max: float) -> float:
    """Sharper (longer focal length) frames count more where frames overlap."""
    return float(view.K[0, 0]) / f_max


def build_mosaic(
    source: FrameSource,
    kind: str = SPHERICAL,
    max_width: int = 8192,
    progress: Callable[[str, int, int], None] | None = None,
    compensate: bool = True,
) -> MosaicResult:
    """The blended mosaic of every frame of source (module doc). progress(pass name, done, total)."""
    views = list(source.views)
    if not views:
        raise ValueError("no frames to place")
    f_max = max(float(v.K[0, 0]) for v in views)
    footprints = [footprint(v) for v in views]
    projection = make_projection(kind, mosaic_width(f_max, max_width), footprints)
    boxes = [footprint_box(fp, projection) for fp in footprints]
    crop = union_box(boxes, projection.width)
    n = len(views)

    gains = np.ones(n)
    if compensate and n > 1:
        gains = _exposure_gains(source, views, footprints, boxes, kind, projection.width, progress)

    acc: Accumulator | None = None
    used = 0
    for done, (i, image) in enumerate(source.images(1), start=1):
        if boxes[i].empty:
            continue
        warped = warp_frame(image, views[i], projection, boxes[i])
        if acc is None:
            acc = Accumulator(projection, crop, warped.pixels.shape[2])
        acc.add(warped, float(gains[i]), resolution_weight(views[i], f_max))
        used += 1
        if progress:
            progress("blend", done, n)
    if acc is None:
        raise ValueError("no frame could be read")
    return MosaicResult(acc.image(), projection, gains, used, crop)
