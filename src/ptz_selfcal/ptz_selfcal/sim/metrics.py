"""Evaluation metrics of DESIGN.md section 7 (pure numpy: no rclpy, no message types).

- focal: |f_est - f| / f per frame (f_est is fx).
- principal point: Euclidean distance in pixels.
- rotation, free of axis conventions: for frame pairs (i, j), |angle(R_est_i R_est_j^T) -
  angle(R_i R_j^T)| with R from ground truth or from the pan/tilt encoders. Pairs come from
  `frame_pairs`: every frame with partners at a fixed stride ahead of it.
- coverage: fraction of input images that got a CameraInfo with the same stamp.
- distortion: `camera.distortion.max_distortion_difference` (principal point error excluded).
- summaries over all frames and over the frames after the first 10% (warm-up).
- issue 15's figures: the well-posed frame (the first whose true rotation from the first frame has
  >= 2 deg about each of the first camera's x (tilt) and y (pan) axes: the rotation vector's components),
  the frames the accuracy figures are taken over (after the warm-up and after the well-posed frame + 1 s,
  whichever is later), the 3-sigma coverage of a run and its run-level error in units of its sigma.

Arrays are indexed by input frame; NaN marks "no estimate for this frame" and is left out of the
statistics (coverage says how many frames had one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.distortion import max_distortion_difference
from ptz_selfcal.camera.geometry import nearest_rotation, pan_tilt_from_rotation, ptz_rotation

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]

WARMUP_FRACTION = 0.1
WELL_POSED_DEG = 2.0  # rotation about each of two orthogonal axes (issue 15's definition)
SETTLE_S = 1.0  # figures start this long after the well-posed frame
COVERAGE_SIGMAS = 3.0


# --------------------------------------------------------------------------------------------------
# Per-frame errors
# --------------------------------------------------------------------------------------------------
def signed_focal_errors(f_est: ArrayLike, f_true: ArrayLike) -> Array:
    """(f_est - f_true) / f_true per frame (a fraction, not a percentage)."""
    f_est = np.asarray(f_est, dtype=float)
    f_true = np.asarray(f_true, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (f_est - f_true) / f_true


def focal_errors(f_est: ArrayLike, f_true: ArrayLike) -> Array:
    """|f_est - f_true| / f_true per frame (a fraction, not a percentage)."""
    return np.abs(signed_focal_errors(f_est, f_true))


def principal_point_errors(pp_est: ArrayLike, pp_true: ArrayLike) -> Array:
    """Euclidean distance in pixels between (n, 2) estimated and true principal points."""
    d = np.asarray(pp_est, dtype=float).reshape(-1, 2) - np.asarray(pp_true, dtype=float).reshape(-1, 2)
    return np.hypot(d[:, 0], d[:, 1])


def distortion_errors(
    est: Sequence[tuple[str, ArrayLike, ArrayLike] | None],
    true: Sequence[tuple[str, ArrayLike, ArrayLike] | None],
    width: int,
    height: int,
) -> Array:
    """Per-frame DESIGN.md section 7 distortion error in pixels; NaN where either side is missing.

    est[i], true[i]: (model, params, K) as `max_distortion_difference` takes them.
    """
    out = np.full(len(est), np.nan)
    for i, (e, t) in enumerate(zip(est, true, strict=True)):
        if e is None or t is None:
            continue
        try:
            out[i] = max_distortion_difference(e, t, width, height, samples=128)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            continue
    return out


def frame_pairs(
    n_frames: int,
    stride: int = 10,
    max_partners: int = 10,
    valid: ArrayLike | None = None,
    segments: ArrayLike | None = None,
    first: int = 0,
) -> IntArray:
    """(m, 2) frame pairs (i, j), i < j: every frame i >= first with partners j = i + k*stride.

    k = 1 .. max_partners. Frames where `valid` is False are skipped; with `segments` (one label per
    frame, e.g. the calibration reference a frame's orientation is relative to) both frames of a pair
    must share a label.
    """
    stride = max(1, int(stride))
    ok = np.ones(n_frames, bool) if valid is None else np.asarray(valid, bool).copy()
    ok[: max(0, first)] = False
    seg = None if segments is None else np.asarray(segments)
    pairs = []
    idx = np.flatnonzero(ok)
    for k in range(1, max(1, int(max_partners)) + 1):
        j = idx + k * stride
        keep = j < n_frames
        i_k, j_k = idx[keep], j[keep]
        keep = ok[j_k]
        if seg is not None:
            keep &= seg[i_k] == seg[j_k]
        pairs.append(np.column_stack([i_k[keep], j_k[keep]]))
    if not pairs:
        return np.zeros((0, 2), np.intp)
    out = np.concatenate(pairs).astype(np.intp)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def pairwise_rotation_errors(R_est: ArrayLike, R_true: ArrayLike, pairs: ArrayLike) -> Array:
    """|angle(R_est_i R_est_j^T) - angle(R_true_i R_true_j^T)| in radians for each pair (vectorised)."""
    R_est = np.asarray(R_est, dtype=float).reshape(-1, 3, 3)
    R_true = np.asarray(R_true, dtype=float).reshape(-1, 3, 3)
    pairs = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    if len(pairs) == 0:
        return np.zeros(0)
    a = _angles(np.einsum("nij,nkj->nik", R_est[pairs[:, 0]], R_est[pairs[:, 1]]))
    b = _angles(np.einsum("nij,nkj->nik", R_true[pairs[:, 0]], R_true[pairs[:, 1]]))
    return np.abs(a - b)


def _angles(R: Array) -> Array:
    """Rotation angles of (n, 3, 3) matrices (the atan2 form of `geometry.rotation_angle`)."""
    s = 0.5 * np.linalg.norm(
        np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1), axis=1
    )
    c = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    return np.arctan2(s, c)


def rotations_from_encoders(pan: ArrayLike, tilt: ArrayLike) -> Array:
    """(n, 3, 3) world-to-camera rotations of a pan-tilt head from encoder angles (radians)."""
    return np.array([ptz_rotation(float(p), float(t)) for p, t in zip(pan, tilt, strict=True)])


def coverage(input_stamps: ArrayLike, output_stamps: ArrayLike) -> float:
    """Fraction of input stamps (ns) that appear among the output stamps (1.0 for no input)."""
    inputs = np.asarray(input_stamps, dtype=np.int64).ravel()
    if len(inputs) == 0:
        return 1.0
    return float(np.isin(inputs, np.asarray(output_stamps, dtype=np.int64).ravel()).mean())


# --------------------------------------------------------------------------------------------------
# Aligning estimated orientations (relative to the calibration's reference) with the truth
# --------------------------------------------------------------------------------------------------
def align_rotations(R_est: ArrayLike, R_true: ArrayLike, mask: ArrayLike | None = None) -> Array:
    """The rotation A (truth world -> estimate reference) minimising sum |R_est_j A - R_true_j|_F.

    R_est_j maps the reference camera's rays to camera j; R_est_j A then maps world rays to camera j
    and is comparable with R_true_j. Closed form: A = nearest_rotation(sum R_est_j^T R_true_j).
    """
    R_est = np.asarray(R_est, dtype=float).reshape(-1, 3, 3)
    R_true = np.asarray(R_true, dtype=float).reshape(-1, 3, 3)
    use = np.ones(len(R_est), bool) if mask is None else np.asarray(mask, bool)
    use &= np.isfinite(R_est).all(axis=(1, 2)) & np.isfinite(R_true).all(axis=(1, 2))
    if not use.any():
        return np.eye(3)
    return nearest_rotation(np.einsum("nji,njk->ik", R_est[use], R_true[use]))


def pan_tilt_path(R: ArrayLike) -> Array:
    """(n, 2) pan and tilt in degrees of the optical axis of each world-to-camera rotation (NaN kept)."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    out = np.full((len(R), 2), np.nan)
    for i, Ri in enumerate(R):
        if np.isfinite(Ri).all():
            out[i] = np.degrees(pan_tilt_from_rotation(Ri))
    return out


# --------------------------------------------------------------------------------------------------
# When the problem is well posed, and how honest a run's stated uncertainty is (issue 15)
# --------------------------------------------------------------------------------------------------
def rotation_vectors_from_first(R: ArrayLike) -> Array:
    """(n, 3) rotation vectors (radians) of R_j R_0^T, in the first camera's axes (x = tilt, y = pan).

    R are world-to-camera rotations; NaN rows stay NaN (the first finite frame is the reference).
    """
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    out = np.full((len(R), 3), np.nan)
    ok = np.isfinite(R).all(axis=(1, 2))
    if ok.any():
        rel = np.einsum("nij,kj->nik", R[ok], R[np.flatnonzero(ok)[0]])
        out[ok] = Rotation.from_matrix(rel).as_rotvec()
    return out


def well_posed_frame(R: ArrayLike, min_angle_deg: float = WELL_POSED_DEG) -> int | None:
    """The first frame whose rotation from the first frame has >= min_angle about each of the first
    camera's x and y axes (rotation-vector components); None when no frame has."""
    r = np.abs(rotation_vectors_from_first(R))
    with np.errstate(invalid="ignore"):
        hit = np.flatnonzero((r[:, :2] >= np.radians(min_angle_deg)).all(axis=1))
    return int(hit[0]) if len(hit) else None


def first_frame(mask: ArrayLike) -> int | None:
    """Index of the first True, None when there is none."""
    hit = np.flatnonzero(np.asarray(mask, bool))
    return int(hit[0]) if len(hit) else None


def figure_start(
    times_s: ArrayLike, n_warmup: int, well_posed: int | None, settle_s: float = SETTLE_S
) -> int:
    """First frame of the accuracy figures: after the warm-up and after the well-posed frame + settle_s,
    whichever is later (the warm-up alone when the motion is never well posed)."""
    t = np.asarray(times_s, dtype=float)
    if well_posed is None:
        return int(n_warmup)
    late = np.flatnonzero(t >= t[well_posed] + settle_s - 1e-9)
    return max(int(n_warmup), int(late[0]) if len(late) else len(t))


def sigma_coverage(
    f_est: ArrayLike, f_true: ArrayLike, sigma_f: ArrayLike, mask: ArrayLike, k: float = COVERAGE_SIGMAS
) -> float:
    """Share of the masked frames with |f_est - f| <= k sigma_f (NaN when none is masked)."""
    e = np.abs(np.asarray(f_est, float) - np.asarray(f_true, float))
    sel = np.asarray(mask, bool) & np.isfinite(e)
    if not sel.any():
        return float("nan")
    with np.errstate(invalid="ignore"):
        return float(np.mean(e[sel] <= k * np.asarray(sigma_f, float)[sel]))


def run_level_error(
    f_est: ArrayLike, f_true: ArrayLike, sigma_f: ArrayLike, mask: ArrayLike
) -> dict[str, float]:
    """A run's focal error as one number and its stated 1-sigma, both relative (section 6.2: the error
    of a sequence is largely one common scale): the medians of (f_est - f) / f and of sigma_f / f_est
    over the masked frames, and z = error / sigma (across seeds, |z| <= 3 should hold 99.7% of the
    time when sigma is honest)."""
    f_est = np.asarray(f_est, float)
    rel = signed_focal_errors(f_est, f_true)
    with np.errstate(invalid="ignore", divide="ignore"):
        rel_sigma = np.asarray(sigma_f, float) / f_est
    sel = np.asarray(mask, bool) & np.isfinite(rel) & np.isfinite(rel_sigma)
    if not sel.any():
        nan = float("nan")
        return {"error": nan, "sigma": nan, "z": nan, "frames": 0}
    error, sigma = float(np.median(rel[sel])), float(np.median(rel_sigma[sel]))
    return {
        "error": error,
        "sigma": sigma,
        "z": error / sigma if sigma > 0 else float("nan"),
        "frames": int(sel.sum()),
    }


# --------------------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------------------
def summarise(values: ArrayLike) -> dict[str, float | int]:
    """count, median, p90, rms, mean, max of the finite values (NaN statistics when there are none)."""
    v = np.asarray(values, dtype=float).ravel()
    v = v[np.isfinite(v)]
    if len(v) == 0:
        nan = float("nan")
        return {"count": 0, "median": nan, "p90": nan, "rms": nan, "mean": nan, "max": nan}
    return {
        "count": len(v),
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "rms": float(np.sqrt(np.mean(v * v))),
        "mean": float(np.mean(v)),
        "max": float(np.max(v)),
    }


def warmup_frames(n_frames: int, fraction: float = WARMUP_FRACTION) -> int:
    """Number of frames in the warm-up (the first 10%, rounded up)."""
    return math.ceil(fraction * n_frames - 1e-9)


def summarise_split(values: ArrayLike, n_warmup: int) -> dict[str, dict[str, float | int]]:
    """Summaries over all frames and over frames after the warm-up (per-frame arrays)."""
    v = np.asarray(values, dtype=float)
    return {"all": summarise(v), "after_warmup": summarise(v[n_warmup:])}


def summarise_pairs(errors: ArrayLike, pairs: ArrayLike, n_warmup: int) -> dict[str, dict[str, float | int]]:
    """Summaries of pairwise errors over all pairs and over pairs with both frames after the warm-up."""
    e = np.asarray(errors, dtype=float)
    p = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    late = (p >= n_warmup).all(axis=1) if len(p) else np.zeros(0, bool)
    return {"all": summarise(e), "after_warmup": summarise(e[late])}
