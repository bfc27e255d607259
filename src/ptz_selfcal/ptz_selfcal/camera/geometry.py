"""Camera geometry shared by every part of ptz_selfcal (paper sections 2.1-2.3).

Conventions (used everywhere in the project):
- Camera frame: x right, y down, z forward (OpenCV). Pixel centres are at integer coordinates.
- K = [[gamma*f, s*f, u0], [0, f, v0], [0, 0, 1]] (eq. 1); fx = gamma*f, fy = f.
- R_i maps world rays to camera-i rays, x_i ~ K_i R_i X (eq. 3); H_ij = K_j R_j R_i^T K_i^-1 (eq. 8).
- A pan-tilt head: pan positive turns the optical axis to the right (+x), tilt positive turns it up.
- Working resolution: x_work = (x_full + 0.5) * s - 0.5 (pixel centres preserved).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def intrinsic_matrix(f: float, cx: float, cy: float, aspect: float = 1.0, skew: float = 0.0) -> Array:
    """K of eq. 1 with focal f (= fy), aspect ratio gamma, skew s and principal point (cx, cy)."""
    return np.array([[aspect * f, skew * f, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def rot_x(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ptz_rotation(pan: float, tilt: float, roll: float = 0.0) -> Array:
    """World-to-camera rotation R of a pan-tilt head (pan about world vertical, then tilt)."""
    camera_to_world = rot_y(pan) @ rot_x(tilt) @ rot_z(roll)
    return camera_to_world.T


def pan_tilt_from_rotation(R: ArrayLike) -> tuple[float, float]:
    """Inverse of ptz_rotation for roll = 0: (pan, tilt) of the optical axis in radians."""
    axis = np.asarray(R, dtype=float).T @ np.array([0.0, 0.0, 1.0])
    return float(np.arctan2(axis[0], axis[2])), float(np.arctan2(-axis[1], np.hypot(axis[0], axis[2])))


def infinite_homography(K_i: ArrayLike, K_j: ArrayLike, R_ij: ArrayLike) -> Array:
    """H_ij = K_j R_ij K_i^-1 (eq. 8): maps pixels of image i to pixels of image j."""
    return np.asarray(K_j) @ np.asarray(R_ij) @ np.linalg.inv(np.asarray(K_i))


def reference_homographies(K: ArrayLike, R: ArrayLike) -> Array:
    """(n, 3, 3) infinite homographies H_j = K_j R_j R_0^T K_0^-1 from frame 0 to every frame j (eq. 8)."""
    K, R = np.asarray(K, dtype=float), np.asarray(R, dtype=float)
    return np.array([infinite_homography(K[0], K[j], relative_rotation(R[0], R[j])) for j in range(len(K))])


def relative_rotation(R_i: ArrayLike, R_j: ArrayLike) -> Array:
    """R_ij = R_j R_i^T: rotation from camera i to camera j."""
    return np.asarray(R_j) @ np.asarray(R_i).T


def normalise_homography(H: ArrayLike) -> Array:
    """Scale H to unit determinant (the scale the infinite homography constraint assumes, eq. 10)."""
    H = np.asarray(H, dtype=float)
    det = np.linalg.det(H)
    if not np.isfinite(det) or det == 0.0:
        raise ValueError("homography is singular")
    return H / np.cbrt(det)


def rotation_angle(R: ArrayLike) -> float:
    """Rotation angle of R in radians, accurate for small and large angles."""
    R = np.asarray(R, dtype=float)
    axis_sin = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    cos = 0.5 * (np.trace(R) - 1.0)
    return float(np.arctan2(axis_sin, cos))


def nearest_rotation(M: ArrayLike) -> Array:
    """The rotation closest to M in the Frobenius norm (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def quaternion_from_matrix(R: ArrayLike) -> Array:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (geometry_msgs order)."""
    R = np.asarray(R, dtype=float)
    trace = np.trace(R)
    if trace > 0.0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 1e-300))
        q = np.empty(4)
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def matrix_from_quaternion(q: ArrayLike) -> Array:
    """Rotation matrix of a quaternion (x, y, z, w)."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_from_homography(H: ArrayLike, K_ref: ArrayLike, K_j: ArrayLike) -> Array:
    """R_j = K_j^-1 H_j K_0 (section 3.3.1), projected onto SO(3) after scale removal."""
    M = np.linalg.inv(np.asarray(K_j)) @ np.asarray(H, dtype=float) @ np.asarray(K_ref)
    M /= np.cbrt(np.linalg.det(M))
    return nearest_rotation(M)


def work_from_full(s: float) -> Array:
    """3x3 map of full-resolution pixels to working-resolution pixels (pixel centres kept)."""
    t = 0.5 * s - 0.5
    return np.array([[s, 0.0, t], [0.0, s, t], [0.0, 0.0, 1.0]])


def homography_work_to_full(H_work: ArrayLike, s: float) -> Array:
    """A homography between working-resolution images expressed in full-resolution pixels."""
    S = work_from_full(s)
    return np.linalg.inv(S) @ np.asarray(H_work, dtype=float) @ S


def intrinsics_work_to_full(K_work: ArrayLike, s: float) -> Array:
    """K at working resolution to K at full resolution: cx_full = (cx_work + 0.5)/s - 0.5."""
    return np.linalg.inv(work_from_full(s)) @ np.asarray(K_work, dtype=float)


def intrinsics_full_to_work(K_full: ArrayLike, s: float) -> Array:
    return work_from_full(s) @ np.asarray(K_full, dtype=float)


def apply_homography(H: ArrayLike, points: ArrayLike) -> Array:
    """Map (N, 2) pixel coordinates through H."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    H = np.asarray(H, dtype=float)
    proj = pts @ H[:, :2].T + H[:, 2]
    return proj[:, :2] / proj[:, 2:3]


def image_motion(H_a: ArrayLike, H_b: ArrayLike, width: int, height: int) -> float:
    """Largest displacement, in image widths, of the image corners and centre from frame a to frame b.

    H_a, H_b map a common reference to each frame, so H_b H_a^-1 is the frame-to-frame motion; a
    preset recall moves a whole field of view in a few frames, normal tracking a few per cent.
    """
    M = np.asarray(H_b, dtype=float) @ np.linalg.inv(np.asarray(H_a, dtype=float))
    x = np.array([[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0]])
    x = np.vstack([x, [[0.5 * (width - 1.0), 0.5 * (height - 1.0)]]])
    p = np.column_stack([x, np.ones(len(x))]) @ M.T
    with np.errstate(divide="ignore", invalid="ignore"):
        moved = np.linalg.norm(p[:, :2] / p[:, 2:3] - x, axis=1)
    if not np.all(np.isfinite(moved)) or np.any(p[:, 2] <= 0.0):
        return math.inf  # a corner went behind the camera: a huge motion, or a broken homography
    return float(np.max(moved) / max(width, 1))


def pixel_grid(width: int, height: int, count: int = 16) -> Array:
    """A regular (count*count', 2) grid of pixel positions spanning the image, corners included."""
    xs = np.linspace(0.0, width - 1.0, count)
    ys = np.linspace(0.0, height - 1.0, max(2, round(count * height / width)))
    gx, gy = np.meshgrid(xs, ys)
    return np.column_stack([gx.ravel(), gy.ravel()])


def transfer_error(H_est: ArrayLike, H_true: ArrayLike, points: ArrayLike) -> Array:
    """Per-point distance in pixels between points mapped through H_est and through H_true."""
    return np.linalg.norm(apply_homography(H_est, points) - apply_homography(H_true, points), axis=1)


def pairwise_rotation_errors(R_est: ArrayLike, R_true: ArrayLike, pairs: ArrayLike) -> Array:
    """|angle(R_est_i R_est_j^T) - angle(R_true_i R_true_j^T)| in radians (free of axis conventions)."""
    R_est = np.asarray(R_est, dtype=float)
    R_true = np.asarray(R_true, dtype=float)
    out = np.empty(len(pairs))
    for n, (i, j) in enumerate(np.asarray(pairs, dtype=int)):
        a = rotation_angle(R_est[i] @ R_est[j].T)
        b = rotation_angle(R_true[i] @ R_true[j].T)
        out[n] = abs(a - b)
    return out
