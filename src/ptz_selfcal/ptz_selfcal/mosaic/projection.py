"""Mosaic surfaces: spherical (equirectangular) and cylindrical, longitude across the full width.

World conventions are those of camera/geometry.py (x right, y DOWN, z forward; R maps world rays to
camera rays) and of the synthetic panoramas (sim/render.py's module doc): longitude lon = atan2(X, Z)
runs left to right with lon = 0 at the horizontal centre, latitude lat = atan2(-Y, hypot(X, Z)) is
+pi/2 at the top. Pixel j covers [j, j + 1) and its centre is the integer coordinate j, so with
s = W / 2pi pixels per radian:
    x = s lon + W / 2 - 1/2
    spherical:   y = s (pi/2 - lat) - 1/2                 (H = W / 2 rows, pole to pole)
    cylindrical: y = s (t_top - tan lat) - 1/2            (rows cover tan lat in [t_top - H / s, t_top])
Columns outside [0, W) are the same longitudes one turn away (callers wrap them modulo W).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

SPHERICAL = "spherical"
CYLINDRICAL = "cylindrical"
KINDS = (SPHERICAL, CYLINDRICAL)
# A cylinder cannot reach the poles: latitudes beyond this are left out of a cylindrical mosaic.
CYLINDER_MAX_LATITUDE = math.radians(75.0)


def mosaic_width(f_max: float, max_width: int, min_width: int = 64) -> int:
    """Full-turn width with one mosaic pixel per image pixel at focal length f_max (2 pi f_max), even
    (so that a spherical mosaic is exactly 2:1), capped at max_width."""
    if not math.isfinite(f_max) or f_max <= 0.0:
        raise ValueError(f"focal length {f_max} is not positive")
    width = min(math.ceil(2.0 * math.pi * f_max), int(max_width))
    width = max(width, min_width)
    return width + (width % 2)


@dataclass(frozen=True)
class Projection:
    """A W x H mosaic surface; t_top is the tan(latitude) of the top edge (cylindrical only)."""

    kind: str
    width: int
    height: int
    t_top: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown projection {self.kind!r} (expected one of {', '.join(KINDS)})")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"mosaic size {self.width}x{self.height} is not positive")

    @property
    def scale(self) -> float:
        """Pixels per radian of longitude."""
        return self.width / (2.0 * math.pi)

    @classmethod
    def spherical(cls, width: int) -> Projection:
        return cls(SPHERICAL, int(width), int(width) // 2)

    @classmethod
    def cylindrical(cls, width: int, lat_min: float, lat_max: float) -> Projection:
        """A cylinder over the latitudes [lat_min, lat_max], clipped to +-CYLINDER_MAX_LATITUDE."""
        lo = max(lat_min, -CYLINDER_MAX_LATITUDE)
        hi = min(lat_max, CYLINDER_MAX_LATITUDE)
        if not hi > lo:
            raise ValueError("empty latitude range for a cylindrical mosaic")
        s = width / (2.0 * math.pi)
        t_top = math.tan(hi)
        height = max(1, math.ceil(s * (t_top - math.tan(lo))))
        return cls(CYLINDRICAL, int(width), height, t_top)

    # columns <-> longitude (the same for both surfaces)
    def x_of_lon(self, lon: ArrayLike) -> Array:
        return np.asarray(lon, dtype=float) * self.scale + 0.5 * self.width - 0.5

    def lon_of_x(self, x: ArrayLike) -> Array:
        return (np.asarray(x, dtype=float) + 0.5 - 0.5 * self.width) / self.scale

    # rows <-> latitude
    def y_of_lat(self, lat: ArrayLike) -> Array:
        lat = np.asarray(lat, dtype=float)
        if self.kind == SPHERICAL:
            return self.scale * (0.5 * math.pi - lat) - 0.5
        return self.scale * (self.t_top - np.tan(lat)) - 0.5

    def lat_of_y(self, y: ArrayLike) -> Array:
        edge = (np.asarray(y, dtype=float) + 0.5) / self.scale
        if self.kind == SPHERICAL:
            return 0.5 * math.pi - edge
        return np.arctan(self.t_top - edge)

    def lat_range(self) -> tuple[float, float]:
        """Latitudes of the bottom and top edges."""
        return float(self.lat_of_y(self.height - 0.5)), float(self.lat_of_y(-0.5))

    # world rays <-> pixels
    def pixels_of_rays(self, rays: ArrayLike) -> Array:
        """(N, 2) mosaic pixels (x in [-1/2, W - 1/2)) of (N, 3) world directions (any length)."""
        lon, lat = lonlat_of_rays(rays)
        return np.column_stack([self.x_of_lon(lon), self.y_of_lat(lat)])

    def rays_of_pixels(self, pixels: ArrayLike) -> Array:
        """(N, 3) unit world directions of (N, 2) mosaic pixels."""
        p = np.asarray(pixels, dtype=float).reshape(-1, 2)
        return rays_of_lonlat(self.lon_of_x(p[:, 0]), self.lat_of_y(p[:, 1]))


def lonlat_of_rays(rays: ArrayLike) -> tuple[Array, Array]:
    d = np.asarray(rays, dtype=float).reshape(-1, 3)
    return np.arctan2(d[:, 0], d[:, 2]), np.arctan2(-d[:, 1], np.hypot(d[:, 0], d[:, 2]))


def rays_of_lonlat(lon: ArrayLike, lat: ArrayLike) -> Array:
    lon, lat = np.asarray(lon, dtype=float), np.asarray(lat, dtype=float)
    c = np.cos(lat)
    return np.column_stack([c * np.sin(lon), -np.sin(lat), c * np.cos(lon)])


def angular_distance(rays_a: ArrayLike, rays_b: ArrayLike) -> Array:
    """Angle (radians) between corresponding rows of two (N, 3) direction arrays (stable near 0)."""
    a = np.asarray(rays_a, dtype=float).reshape(-1, 3)
    b = np.asarray(rays_b, dtype=float).reshape(-1, 3)
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
