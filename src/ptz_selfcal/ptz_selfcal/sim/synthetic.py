"""The paper's synthetic experiment (section 4.1), reusable by tests and benchmarks.

1000 points in a 3 m cube centred 5 m in front of a rotating camera; 30 frames of 640x480 with square
pixels and zero skew; the principal ray describes a circle (a cone of constant half angle about the
cube's centre direction) while the focal length grows linearly. Configuration A: 5 deg, f 800 -> 1400
px; configuration B: 3.5 deg, f 1200 -> 2000 px (the worse conditioned one). The principal point is the
image centre or, for the MAP experiment of section 5.3.1, drifts linearly over the sequence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation, reference_homographies
from ptz_selfcal.camera.intrinsics import image_centre
from ptz_selfcal.frontend.homography import estimate_homography
from ptz_selfcal.sim.render import cone_pan_tilt

Array = NDArray[np.float64]

# (cone half angle in degrees, first focal length, last focal length) of section 4.1 / figure 6.
CONFIGURATIONS: dict[str, tuple[float, float, float]] = {
    "A": (5.0, 800.0, 1400.0),
    "B": (3.5, 1200.0, 2000.0),
}
# Direction of the principal point drift (unit vector, mostly along x as zoom lenses tend to do).
DRIFT_DIRECTION = np.array([0.8, 0.6])


@dataclass
class SyntheticSequence:
    """A synthetic sequence with exact ground truth and noisy observations.

    R[i] maps world rays to camera-i rays (x_i ~ K_i R_i X); H[j] maps frame-0 pixels to frame-j pixels,
    estimated from the noisy correspondences (H[0] = I).
    """

    config: str
    sigma: float
    seed: int
    image_size: tuple[int, int]
    K: Array  # (n, 3, 3) true intrinsics
    R: Array  # (n, 3, 3) true world-to-camera rotations
    points: Array  # (m, 3) world points
    point_ids: list[NDArray[np.intp]]  # per frame: ids of the points visible in the image
    pixels: list[Array]  # per frame: (k, 2) noisy pixel coordinates of those points
    H: Array  # (n, 3, 3) estimated homographies frame 0 -> frame j

    @property
    def n_frames(self) -> int:
        return len(self.K)

    @property
    def R_relative(self) -> Array:
        """(n, 3, 3) true rotations relative to frame 0 (R_j R_0^T), the calibration's convention."""
        return np.einsum("nij,kj->nik", self.R, self.R[0])

    def H_true(self) -> Array:
        """(n, 3, 3) exact infinite homographies frame 0 -> frame j (eq. 8), unit H[2, 2]."""
        H = reference_homographies(self.K, self.R)
        return H / H[:, 2:3, 2:3]

    def observations(self) -> tuple[NDArray[np.intp], NDArray[np.intp], Array]:
        """(frame_idx (N,), ray_idx (N,), xy (N, 2)) for bundle adjustment (eq. 26)."""
        frames = np.concatenate([np.full(len(ids), i, dtype=np.intp) for i, ids in enumerate(self.point_ids)])
        return frames, np.concatenate(self.point_ids).astype(np.intp), np.concatenate(self.pixels)


def circle_rotations(n_frames: int, radius_deg: float) -> Array:
    """(n, 3, 3) world-to-camera rotations whose principal ray runs once round a cone about world +z."""
    phi = 2.0 * np.pi * np.arange(n_frames) / n_frames
    pan, tilt = cone_pan_tilt(phi, np.radians(radius_deg))  # the renderer's circle (synth --motion circle)
    return np.array([ptz_rotation(p, t) for p, t in zip(pan, tilt)])


def project(K: Array, R: Array, points: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Pixels of world points through x ~ K R X (eq. 3) and whether each is in front of the camera."""
    cam = points @ (K @ R).T
    return cam[:, :2] / cam[:, 2:3], cam[:, 2] > 0.0


def paper_sequence(
    config: str,
    sigma: float,
    seed: int,
    *,
    n_frames: int = 30,
    n_points: int = 1000,
    width: int = 640,
    height: int = 480,
    principal_point_drift: float = 0.0,
) -> SyntheticSequence:
    """Generate the synthetic sequence of section 4.1 ('A' or 'B') with Gaussian pixel noise sigma.

    principal_point_drift: total motion in pixels of the principal point over the sequence, centred on
    the image centre (section 5.3.1); 0 keeps it at the centre.
    """
    if config not in CONFIGURATIONS:
        raise ValueError(f"unknown configuration {config!r}; expected one of {sorted(CONFIGURATIONS)}")
    radius, f_first, f_last = CONFIGURATIONS[config]
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1.5, 1.5, size=(n_points, 3)) + np.array([0.0, 0.0, 5.0])
    t = np.linspace(0.0, 1.0, n_frames)
    focal = f_first + (f_last - f_first) * t
    centre = np.array(image_centre((width, height)))
    pp = centre + principal_point_drift * (t - 0.5)[:, None] * DRIFT_DIRECTION
    K = np.array([intrinsic_matrix(f, cx, cy) for f, (cx, cy) in zip(focal, pp)])
    R = circle_rotations(n_frames, radius)

    point_ids: list[NDArray[np.intp]] = []
    pixels: list[Array] = []
    for Ki, Ri in zip(K, R):
        xy, front = project(Ki, Ri, points)
        inside = (
            front & (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= height - 1)
        )
        ids = np.flatnonzero(inside)
        point_ids.append(ids)
        pixels.append(xy[ids] + sigma * rng.standard_normal((len(ids), 2)))

    H = np.empty((n_frames, 3, 3))
    H[0] = np.eye(3)
    for j in range(1, n_frames):
        common, i0, ij = np.intersect1d(point_ids[0], point_ids[j], return_indices=True)
        if len(common) < 4:
            raise ValueError(f"frame {j} shares only {len(common)} points with frame 0")
        H[j] = estimate_homography(pixels[0][i0], pixels[j][ij])
    return SyntheticSequence(
        config=config,
        sigma=float(sigma),
        seed=int(seed),
        image_size=(width, height),
        K=K,
        R=R,
        points=points,
        point_ids=point_ids,
        pixels=pixels,
        H=H,
    )
