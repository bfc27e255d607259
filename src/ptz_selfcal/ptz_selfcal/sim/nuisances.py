"""Nuisances of real video on rendered frames, with exact ground truth (issue 16).

Geometry (what the lens sees): textured objects moving through the scene, a target the camera follows
(static in the image while the background moves) and a rolling shutter; photometry (what the sensor
makes of it): auto-exposure steps, vignetting and low light. Pure numpy/OpenCV, evaluation only.

Objects are rectangles on tangent planes of the view sphere: a pose (unit centre direction c, east and
down axes e, d in world coordinates) and tan-of-half-angle sizes (a, b); a world ray r hits the object
where r.c > 0, |r.e / r.c| <= a and |r.d / r.c| <= b, so a rotating, zooming camera sees it through an
exact homography and its mask is exactly the pixels the object's texture replaces (no antialiasing).

Rolling shutter (Forssen and Ringaby's model for a rotating camera): row y of an h-row frame stamped t
is read at t_y = t + (y / (h - 1) - 1/2) readout (the stamp is the middle row's time); its pan and tilt
are interpolated linearly between the head's pose at t - readout/2 and t + readout/2, K and the lens are
the stamp's. Objects are posed at their row's time. With readout 0 the rows share the stamp's rotation
and the frame is render_view's, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.distortion import division_undistort
from ptz_selfcal.camera.geometry import ptz_rotation
from ptz_selfcal.sim.render import (
    _PAD,
    CameraProfile,
    Panorama,
    gaussian_noise,
    panorama_coordinates,
    pyramid_blend,
)

Array = NDArray[np.float64]
Rotation = Callable[[float], Array]  # time -> world-to-camera rotation of the head

# Gains of the auto-exposure cycle, one per step (first = the sequence's start).
EXPOSURE_GAINS = (1.0, 1.25, 0.85, 1.15, 0.75)
_DOWN = np.array([0.0, 1.0, 0.0])  # world y points down (sim/render.py)


# --------------------------------------------------------------------------------------------------
# Moving objects
# --------------------------------------------------------------------------------------------------
def tangent_basis(centre: Array) -> tuple[Array, Array]:
    """(east, down) unit axes of the tangent plane at unit directions centre (..., 3): east is
    horizontal (perpendicular to world down), down completes the right-handed frame (c = east x down)."""
    east = np.cross(_DOWN, centre)
    east /= np.linalg.norm(east, axis=-1, keepdims=True)
    return east, np.cross(centre, east)


def direction(lon: Array, lat: Array) -> Array:
    """(..., 3) unit world direction of longitude/latitude (the panorama's angles, sim/render.py)."""
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    return np.stack([np.sin(lon) * np.cos(lat), -np.sin(lat), np.cos(lon) * np.cos(lat)], axis=-1)


@dataclass(frozen=True)
class Pose:
    """Per-row object poses (n rows): centre, east, down (n, 3) world unit vectors; moving (n,)."""

    centre: Array
    east: Array
    down: Array
    moving: NDArray[np.bool_]


@dataclass(frozen=True)
class CrossingObject:
    """A vehicle-like rectangle driving horizontally (in longitude) through the scene.

    Centre at longitude lon0 + speed (t - t_mid), latitude lat; always moving."""

    texture: np.ndarray  # uint8, the panorama's channels
    half_width: float  # tan of the half angle
    half_height: float
    lon0: float  # radians, at t_mid
    lat: float
    speed: float  # radians per second
    t_mid: float

    def pose(self, times: Array, rotations: Array, rotation_at: Rotation) -> Pose:
        centre = direction(
            self.lon0 + self.speed * (np.asarray(times) - self.t_mid), np.full(len(times), self.lat)
        )
        east, down = tangent_basis(centre)
        return Pose(centre, east, down, np.ones(len(times), bool))


@dataclass(frozen=True)
class FollowedTarget:
    """A target the camera follows from t0 to t1: it moves exactly as the head does, so it stays at the
    same camera direction (static in the image up to the zoom) while the background moves. Before t0 it
    stands where the camera then saw it, after t1 where it was left; moving only inside [t0, t1]."""

    texture: np.ndarray
    half_width: float
    half_height: float
    centre_cam: tuple[float, float, float]  # unit direction in camera coordinates
    t0: float
    t1: float

    def pose(self, times: Array, rotations: Array, rotation_at: Rotation) -> Pose:
        times = np.asarray(times, float)
        c = np.asarray(self.centre_cam, float)
        east_cam, down_cam = tangent_basis(c)
        # camera -> world of each row: the row's own rotation while followed, else the window's end
        to_world = np.array(
            [
                rotations[k].T if self.t0 <= t <= self.t1 else rotation_at(min(max(t, self.t0), self.t1)).T
                for k, t in enumerate(times)
            ]
        )
        moving = (times >= self.t0) & (times <= self.t1)
        return Pose(to_world @ c, to_world @ east_cam, to_world @ down_cam, moving)


MovingObject = CrossingObject | FollowedTarget


def panorama_patch(panorama: Panorama, size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A (w, h) = size patch of the panorama's full-resolution texture from a random place in its middle
    latitudes, mirrored left-right (an object is not a copy of the scene behind it)."""
    w, h = size
    image = panorama.levels[0][_PAD : _PAD + panorama.height, _PAD : _PAD + panorama.width]
    w, h = min(w, panorama.width), min(h, panorama.height // 2)
    x = int(rng.integers(0, panorama.width - w + 1))
    y = int(rng.integers(panorama.height // 4, panorama.height * 3 // 4 - h + 1))
    return np.ascontiguousarray(image[y : y + h, x : x + w][:, ::-1])


def crossing_objects(
    count: int, panorama: Panorama, profile: CameraProfile, rng: np.random.Generator
) -> tuple[CrossingObject, ...]:
    """`count` objects, each crossing the camera's view: at a random time it is at a random point of the
    central 60 % of the image, 3-6 deg wide (aspect 0.4-0.6), driving left or right at 4-10 deg/s."""
    objects = []
    for _ in range(count):
        t_mid = float(rng.uniform(0.1, 0.9) * profile.period)
        state = profile.state(np.array([t_mid]))
        x = np.array(
            [
                (0.5 + rng.uniform(-0.3, 0.3)) * profile.width,
                (0.5 + rng.uniform(-0.3, 0.3)) * profile.height,
                1.0,
            ]
        )
        ray = state.R(0).T @ np.linalg.solve(state.K(0), x)
        lon, lat = float(np.arctan2(ray[0], ray[2])), float(np.arctan2(-ray[1], np.hypot(ray[0], ray[2])))
        half = float(np.tan(np.radians(rng.uniform(1.5, 3.0))))
        aspect = float(rng.uniform(0.4, 0.6))
        speed = float(np.radians(rng.uniform(4.0, 10.0)) * rng.choice([-1.0, 1.0]))
        texture = panorama_patch(panorama, (256, round(256 * aspect)), rng)
        objects.append(CrossingObject(texture, half, half * aspect, lon, lat, speed, t_mid))
    return tuple(objects)


def followed_target(
    panorama: Panorama,
    profile: CameraProfile,
    t0: float,
    t1: float,
    rng: np.random.Generator,
    cover: tuple[float, float] = (0.35, 0.45),
) -> FollowedTarget:
    """A target followed from t0 to t1, near the image centre, covering `cover` of the image's width and
    height at t0 (a sixth of the image; more as the camera zooms in)."""
    state = profile.state(np.array([t0]))
    K = state.K(0)
    x = np.array(
        [
            (0.5 + rng.uniform(-0.05, 0.05)) * profile.width,
            (0.5 + rng.uniform(-0.05, 0.05)) * profile.height,
            1.0,
        ]
    )
    c = np.linalg.solve(K, x)
    c /= np.linalg.norm(c)
    f = float(K[0, 0])
    half_w, half_h = 0.5 * cover[0] * profile.width / f, 0.5 * cover[1] * profile.height / f
    texture = panorama_patch(panorama, (512, round(512 * half_h / half_w)), rng)
    return FollowedTarget(texture, half_w, half_h, (float(c[0]), float(c[1]), float(c[2])), t0, t1)


# --------------------------------------------------------------------------------------------------
# Photometry
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExposureSteps:
    """Auto-exposure: a gain constant for `period` seconds, then the next of `gains` (cycling)."""

    period: float
    gains: tuple[float, ...] = EXPOSURE_GAINS

    def gain(self, t: float) -> float:
        return float(self.gains[int(np.floor(t / self.period)) % len(self.gains)])


@dataclass(frozen=True)
class LowLight:
    """A dim scene: the signal scaled by `dim`, then shot noise of variance signal / electrons_per_level
    (Poisson, in the Gaussian limit) in grey levels."""

    dim: float = 0.3
    electrons_per_level: float = 1.0


def vignetting_gain(
    size: tuple[int, int], centre: Array, strength: float, corner_angle: float = 30.0
) -> np.ndarray:
    """(h, w) float32 cos^4 falloff about `centre` (the principal point): 1 there, 1 - strength at the
    image corner's radius. The cos^4 law is taken at a field angle growing to corner_angle (deg) at the
    half-diagonal and rescaled, so `strength` is the corner's loss whatever the zoom."""
    w, h = size
    gx = np.arange(w, dtype=np.float32)[None, :] - np.float32(centre[0])
    gy = np.arange(h, dtype=np.float32)[:, None] - np.float32(centre[1])
    r = np.sqrt(gx * gx + gy * gy) / np.float32(0.5 * np.hypot(w, h))
    t = np.float32(np.tan(np.radians(corner_angle)))
    cos4 = 1.0 / (1.0 + (r * t) ** 2) ** 2  # cos^4(atan(r t))
    corner = float(1.0 / (1.0 + t * t) ** 2)
    return (1.0 - np.float32(strength / (1.0 - corner)) * (1.0 - cos4)).astype(np.float32)


# --------------------------------------------------------------------------------------------------
# A frame
# --------------------------------------------------------------------------------------------------
def row_times(t: float, height: int, readout: float) -> Array:
    """Read-out time of every row of a frame stamped t (the middle row's time)."""
    return t + (np.arange(height) / max(height - 1, 1) - 0.5) * readout


def row_rays(
    K: Array, rotations: Array, size: tuple[int, int], distortion: float | None = None
) -> np.ndarray:
    """(3, h, w) float32 world rays with row y seen through rotations[y] (h, 3, 3).

    The arithmetic of sim/render.view_rays, row by row: equal rotations give its rays bit for bit."""
    K = np.asarray(K, dtype=float)
    w, h = size
    K_inv = np.linalg.inv(K)
    first = rotations[0]
    if all(np.array_equal(R, first) for R in rotations):
        M = np.broadcast_to(np.asarray(first, dtype=float).T @ K_inv, (h, 3, 3))
    else:
        M = np.array([np.asarray(R, dtype=float).T @ K_inv for R in rotations])
    if distortion:
        gx, gy = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        und = division_undistort(np.column_stack([gx.ravel(), gy.ravel()]), distortion, K[:2, 2], K[0, 0])
        u = und[:, 0].reshape(h, w).astype(np.float32)
        v = und[:, 1].reshape(h, w).astype(np.float32)
    else:
        u = np.arange(w, dtype=np.float32)[None, :]
        v = np.arange(h, dtype=np.float32)[:, None]
    M32 = M.astype(np.float32)
    return np.stack([M32[:, i, 0, None] * u + M32[:, i, 1, None] * v + M32[:, i, 2, None] for i in range(3)])


def render_rays(
    panorama: Panorama, f: float, rays: np.ndarray, interpolation: int = cv2.INTER_LINEAR
) -> np.ndarray:
    """The panorama seen along `rays` (3, h, w), mip-mapped for focal length f as render_view does."""
    level, weight = pyramid_blend(panorama, f)
    x, y = panorama_coordinates(rays, panorama.width, panorama.height)
    w_l, _ = panorama.level_size(level)
    scale = np.float32(0.5**level)
    pad = np.float32(_PAD)
    map_x = (np.mod(x * scale, np.float32(w_l)) + pad).astype(np.float32)
    map_y = (y * scale + pad).astype(np.float32)
    view = cv2.remap(panorama.levels[level], map_x, map_y, interpolation, borderMode=cv2.BORDER_REPLICATE)
    if weight < 1e-3:
        return view
    coarse = cv2.remap(
        panorama.levels[level + 1], (map_x - pad) * 0.5 + pad, (map_y - pad) * 0.5 + pad, interpolation,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
    return cv2.addWeighted(view, 1.0 - weight, coarse, weight, 0.0)


def draw_object(
    image: np.ndarray, mask: np.ndarray, rays: np.ndarray, obj: MovingObject, pose: Pose, interpolation: int
) -> None:
    """Paint obj's texture over image (in place) where the rays hit it; mark mask 255 on the rows
    where it is moving."""
    c, e, d = (p.astype(np.float32) for p in (pose.centre, pose.east, pose.down))

    def dot(axis: np.ndarray) -> np.ndarray:
        return rays[0] * axis[:, 0, None] + rays[1] * axis[:, 1, None] + rays[2] * axis[:, 2, None]

    depth = dot(c)
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = dot(e) / depth, dot(d) / depth
    hit = (depth > 0) & (np.abs(u) <= obj.half_width) & (np.abs(v) <= obj.half_height)
    if not hit.any():
        return
    th, tw = obj.texture.shape[:2]
    tx = np.where(hit, (u / np.float32(obj.half_width) + 1.0) * np.float32(0.5 * tw) - 0.5, 0).astype(
        np.float32
    )
    ty = np.where(hit, (v / np.float32(obj.half_height) + 1.0) * np.float32(0.5 * th) - 0.5, 0).astype(
        np.float32
    )
    texture = cv2.remap(obj.texture, tx, ty, interpolation, borderMode=cv2.BORDER_REPLICATE)
    image[hit] = texture[hit]
    mask[hit & pose.moving[:, None]] = 255


@dataclass(frozen=True)
class Nuisances:
    """Everything issue 16 adds to a synthetic frame; the default adds nothing."""

    objects: tuple[MovingObject, ...] = ()
    readout: float = 0.0  # rolling shutter readout time, seconds (0 = global shutter)
    exposure: ExposureSteps | None = None
    vignetting: float = 0.0  # the corner's brightness loss (0.4 = 40 %)
    low_light: LowLight | None = None

    @property
    def geometric(self) -> bool:
        return bool(self.objects) or self.readout > 0.0

    @property
    def photometric(self) -> bool:
        return self.exposure is not None or self.vignetting > 0.0 or self.low_light is not None

    def render(
        self, panorama: Panorama, profile: CameraProfile, t: float, interpolation: int = cv2.INTER_LINEAR
    ) -> tuple[np.ndarray, np.ndarray]:
        """(view, moving mask) of the frame stamped t: the panorama through the rolling shutter, the
        objects painted over it; mask uint8, 255 on moving objects."""
        size = (profile.width, profile.height)
        state = profile.state(np.array([t]))
        K, lam = state.K(0), float(state.lam[0])
        times = row_times(t, profile.height, self.readout)
        if self.readout > 0.0:
            ends = profile.state(np.array([times[0], times[-1]]))
            s = np.linspace(0.0, 1.0, profile.height)
            pans = ends.pan[0] + s * (ends.pan[1] - ends.pan[0])
            tilts = ends.tilt[0] + s * (ends.tilt[1] - ends.tilt[0])
            rotations = np.array([ptz_rotation(float(p), float(q)) for p, q in zip(pans, tilts)])
        else:
            rotations = np.broadcast_to(state.R(0), (profile.height, 3, 3))
        rays = row_rays(K, rotations, size, lam or None)
        view = render_rays(panorama, float(K[0, 0]), rays, interpolation)
        mask = np.zeros((profile.height, profile.width), np.uint8)

        def rotation_at(time: float) -> Array:
            pan, tilt = profile.pan_tilt(np.array([time]))
            return ptz_rotation(float(pan[0]), float(tilt[0]))

        for obj in self.objects:
            draw_object(view, mask, rays, obj, obj.pose(times, rotations, rotation_at), interpolation)
        return view, mask

    def gain(self, t: float) -> float:
        """The global gain at time t: exposure step times the low light's dimming."""
        exposure = self.exposure.gain(t) if self.exposure is not None else 1.0
        return exposure * (self.low_light.dim if self.low_light is not None else 1.0)

    def expose(self, image: np.ndarray, t: float, centre: Array, rng: np.random.Generator) -> np.ndarray:
        """The sensor's uint8 image of scene `image` at time t: vignetting about `centre`, the gain, shot
        noise (low light), rounded and saturated. Without photometric nuisances: image itself."""
        if not self.photometric:
            return image
        x = image.astype(np.float32)
        if self.vignetting > 0.0:
            falloff = vignetting_gain((image.shape[1], image.shape[0]), centre, self.vignetting)
            x *= falloff if x.ndim == 2 else falloff[..., None]
        x *= np.float32(self.gain(t))
        if self.low_light is not None:
            x += np.sqrt(x / np.float32(self.low_light.electrons_per_level)) * gaussian_noise(
                x.shape, 1.0, rng
            )
        return np.clip(np.rint(x), 0, 255).astype(np.uint8)
