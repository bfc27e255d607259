"""One frame onto the mosaic surface: its footprint and its inverse warp (mosaic pixel -> image pixel).

A frame is its full-resolution K, plumb_bob D (k1, k2, k3 on normalised coordinates, as CameraInfo
publishes it) and R, the world-to-camera rotation (x_cam ~ K R X, camera/geometry.py). Every mosaic
pixel of the footprint gets the world ray of its (lon, lat), then x = distort(K R ray), then a bilinear
sample of the image; the weight falls linearly from the image centre to zero at its border
(feathering), so that seams between frames fade instead of stepping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import plumb_bob_distort, plumb_bob_undistort
from ptz_selfcal.camera.geometry import intrinsics_full_to_work
from ptz_selfcal.mosaic.projection import Projection, lonlat_of_rays

Array = NDArray[np.float64]

# Border samples per image side for the footprint (the border's image is a smooth curve).
_BORDER_SAMPLES = 32
# Undistorted radius (squared, normalised) beyond which a plumb_bob polynomial is not trusted: this
# many times the corners' own, so that a fold of the polynomial far outside the image maps nothing.
_RADIUS2_MARGIN = 2.0


@dataclass(frozen=True)
class FrameView:
    """Geometry of one frame: full-resolution K, plumb_bob (k1, k2, k3), world-to-camera R, size."""

    K: Array
    D: tuple[float, float, float]
    R: Array
    width: int
    height: int

    @property
    def distorted(self) -> bool:
        return any(abs(k) > 0.0 for k in self.D)


@dataclass(frozen=True)
class Footprint:
    """The directions a frame sees: longitudes [lon_min, lon_max] unwrapped round the frame's centre
    (lon_max - lon_min may exceed pi near a pole; full turn when a pole is in view), latitudes."""

    lon_min: float
    lon_max: float
    lat_min: float
    lat_max: float

    @property
    def full_turn(self) -> bool:
        return self.lon_max - self.lon_min >= 2.0 * math.pi


@dataclass(frozen=True)
class Box:
    """Mosaic pixel box [x0, x1) x [y0, y1); columns unwrapped (taken modulo the width)."""

    x0: int
    x1: int
    y0: int
    y1: int

    @property
    def empty(self) -> bool:
        return self.x1 <= self.x0 or self.y1 <= self.y0


@dataclass(frozen=True)
class Warped:
    """A frame resampled on its box: (h, w, C) pixels (the image's dtype) and (h, w) float32 weights."""

    box: Box
    pixels: np.ndarray
    weight: np.ndarray


def image_to_rays(view: FrameView, pixels: ArrayLike) -> Array:
    """(N, 3) world directions of (N, 2) full-resolution image pixels (undistorted first)."""
    p = np.asarray(pixels, dtype=float).reshape(-1, 2)
    if view.distorted:
        p = plumb_bob_undistort(p, view.D[0], view.D[1], view.K, view.D[2])
    homog = np.column_stack([p, np.ones(len(p))])
    return homog @ np.linalg.inv(view.K).T @ view.R  # R^T K^-1 x, row-wise


def rays_to_image(view: FrameView, rays: ArrayLike) -> tuple[Array, NDArray[np.bool_]]:
    """(N, 2) full-resolution pixels of (N, 3) world directions, and which are in front of the camera."""
    c = np.asarray(rays, dtype=float).reshape(-1, 3) @ view.R.T
    front = c[:, 2] > 1e-9
    z = np.where(front, c[:, 2], 1.0)
    x = (c @ view.K.T)[:, :2] / z[:, None]
    if view.distorted:
        x = plumb_bob_distort(x, view.D[0], view.D[1], view.K, view.D[2])
    return x, front


def _border(width: int, height: int, n: int = _BORDER_SAMPLES) -> Array:
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    x1, y1 = width - 0.5, height - 0.5
    top = np.column_stack([-0.5 + t * width, np.full(n, -0.5)])
    right = np.column_stack([np.full(n, x1), -0.5 + t * height])
    bottom = np.column_stack([x1 - t * width, np.full(n, y1)])
    left = np.column_stack([np.full(n, -0.5), y1 - t * height])
    return np.vstack([top, right, bottom, left])


def footprint(view: FrameView) -> Footprint:
    """Longitude and latitude range of a frame (extremes lie on the border unless a pole is in view)."""
    lon, lat = lonlat_of_rays(image_to_rays(view, _border(view.width, view.height)))
    lon_c = float(lonlat_of_rays(image_to_rays(view, [[view.K[0, 2], view.K[1, 2]]]))[0][0])
    lon = lon_c + np.mod(lon - lon_c + math.pi, 2.0 * math.pi) - math.pi
    lon_min, lon_max = float(lon.min()), float(lon.max())
    lat_min, lat_max = float(lat.min()), float(lat.max())
    for sign in (1.0, -1.0):  # the north (world -y) and south poles
        px, front = rays_to_image(view, [[0.0, -sign, 0.0]])
        inside = -0.5 <= px[0, 0] <= view.width - 0.5 and -0.5 <= px[0, 1] <= view.height - 0.5
        if front[0] and inside:
            lon_min, lon_max = -math.pi, math.pi
            lat_max, lat_min = (0.5 * math.pi, lat_min) if sign > 0 else (lat_max, -0.5 * math.pi)
    return Footprint(lon_min, lon_max, lat_min, lat_max)


def footprint_box(fp: Footprint, projection: Projection, margin: int = 1) -> Box:
    """The mosaic pixels a footprint touches (a margin for bilinear sampling), rows clipped."""
    W, H = projection.width, projection.height
    if fp.full_turn:
        x0, x1 = 0, W
    else:
        x0 = math.floor(float(projection.x_of_lon(fp.lon_min))) - margin
        x1 = math.ceil(float(projection.x_of_lon(fp.lon_max))) + 1 + margin
        if x1 - x0 >= W:
            x0, x1 = 0, W
        elif x0 < 0 or x0 >= W:  # the box's first column in [0, W)
            shift = (x0 // W) * W
            x0, x1 = x0 - shift, x1 - shift
    lo, hi = projection.lat_range()
    lat_max, lat_min = min(fp.lat_max, hi), max(fp.lat_min, lo)
    if lat_max < lat_min:
        return Box(x0, x1, 0, 0)
    y0 = max(0, math.floor(float(projection.y_of_lat(lat_max))) - margin)
    y1 = min(H, math.ceil(float(projection.y_of_lat(lat_min))) + 1 + margin)
    return Box(x0, x1, y0, y1)


def warp_frame(image: np.ndarray, view: FrameView, projection: Projection, box: Box) -> Warped:
    """Resample an image (full size, or decoded smaller: K is scaled to it) onto a mosaic box."""
    h_img, w_img = image.shape[:2]
    s = w_img / view.width
    K = view.K if s == 1.0 else intrinsics_full_to_work(view.K, s)
    lon = projection.lon_of_x(np.arange(box.x0, box.x1))
    lat = projection.lat_of_y(np.arange(box.y0, box.y1))
    sin_lon, cos_lon = np.sin(lon).astype(np.float32), np.cos(lon).astype(np.float32)
    sin_lat, cos_lat = np.sin(lat).astype(np.float32), np.cos(lat).astype(np.float32)
    # without distortion K R d is projected directly (u = p0 / p2), with it R d is distorted first
    M = np.asarray(view.R, dtype=float) if view.distorted else K @ np.asarray(view.R, dtype=float)
    # M d with d = (cos lat sin lon, -sin lat, cos lat cos lon): separable in (lat, lon)
    c = [
        cos_lat[:, None] * (np.float32(M[i, 0]) * sin_lon + np.float32(M[i, 2]) * cos_lon)[None, :]
        - (np.float32(M[i, 1]) * sin_lat)[:, None]
        for i in range(3)
    ]
    front = c[2] > np.float32(1e-6 * abs(M[2]).max())
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        inv_z = np.float32(1.0) / c[2]
        if view.distorted:
            xn, yn = c[0] * inv_z, c[1] * inv_z
            r2 = xn * xn + yn * yn
            x1, y1 = w_img - 0.5, h_img - 0.5
            corners = np.array([[-0.5, -0.5], [x1, y1], [-0.5, y1], [x1, -0.5]])
            cn = (corners - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
            front &= r2 <= np.float32(_RADIUS2_MARGIN * float((cn**2).sum(axis=1).max()))
            xn[~front], yn[~front] = 0.0, 0.0
            ux = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
            und = np.column_stack([ux.ravel(), (K[1, 1] * yn + K[1, 2]).ravel()])
            dist = plumb_bob_distort(und, view.D[0], view.D[1], K, view.D[2])
            u = dist[:, 0].reshape(xn.shape).astype(np.float32)
            v = dist[:, 1].reshape(xn.shape).astype(np.float32)
        else:
            u, v = c[0] * inv_z, c[1] * inv_z
    far = ~front
    u[far], v[far] = -1e4, -1e4
    # distance to the image border, in pixels: the feather weight's ramp
    weight = np.minimum(u, np.float32(w_img - 1.0) - u)
    np.minimum(weight, v, out=weight)
    np.minimum(weight, np.float32(h_img - 1.0) - v, out=weight)
    weight += np.float32(0.5)
    weight *= np.float32(1.0 / max(1.0, 0.5 * min(w_img, h_img)))
    np.clip(weight, 0.0, 1.0, out=weight)
    pixels = cv2.remap(image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return Warped(box, pixels[:, :, None] if pixels.ndim == 2 else pixels, weight)
