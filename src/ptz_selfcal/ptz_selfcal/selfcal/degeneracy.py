"""Degenerate motions and near-ambiguities of rotating-camera self-calibration (paper section 6).

- 6.1: rotation about a single axis (pan only, tilt only, roll only) leaves intrinsics unconstrained
  for the usual constraint sets (the aspect ratio at least; with zero skew only, more).
- 6.2: the focal length / rotation near-ambiguity. In eq. 30 only the term (x/f)(x theta_Y - y theta_X)
  separates f from the rotation angle; when it falls below the noise (small rotation relative to
  the field of view, long focal length) the whole sequence's focal lengths share one unobservable
  scale factor. Measured both geometrically (size of that term at the image corners, pixels) and,
  when a solver supplies it, as the relative 1-sigma focal uncertainty from its Jacobian.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from ptz_selfcal.camera.intrinsics import IntrinsicsModel, ParamMode, image_centre

Array = NDArray[np.float64]

STATUS_OK = "ok"
STATUS_SINGLE_AXIS = "degenerate_single_axis"
STATUS_NEAR_AMBIGUOUS = "near_ambiguous"
STATUS_INSUFFICIENT_ROTATION = "insufficient_rotation"


@dataclass
class MotionReport:
    """How well a rotation sequence constrains self-calibration (section 6). Angles in degrees."""

    status: str
    well_posed: bool
    message: str
    rotation_extent_deg: tuple[float, float, float]  # range about camera-0 x (tilt), y (pan), z (roll)
    perpendicular_extent_deg: tuple[float, float]  # major/minor extent perpendicular to the optical axis
    max_perpendicular_rotation_deg: float  # largest rotation of a frame away from frame 0's axis
    single_axis: bool
    axis_ratio: float  # second / first principal extent of the rotation vectors (0 = single axis)
    disambiguation_px: float  # largest |(x/f)(x theta_Y - y theta_X)| at the image corners (eq. 30)
    relative_sigma_f: float  # median sigma_f / f over frames (NaN when not supplied)
    # eq. 30's term from each camera axis alone at frame 0's corner: (|x y| / f) theta_X (tilt) and
    # (x^2 / f) theta_Y (pan), largest over the frames
    axis_disambiguation_px: tuple[float, float] = (0.0, 0.0)

    def to_dict(self) -> dict:
        """Plain Python types (YAML/JSON serialisable)."""
        d = asdict(self)
        for key, value in d.items():
            if isinstance(value, tuple):
                d[key] = [float(v) for v in value]
            elif isinstance(value, np.floating | np.bool_):
                d[key] = value.item()
        return d


def single_axis_is_degenerate(model: IntrinsicsModel) -> bool:
    """Whether rotation about a single axis leaves the model's intrinsics undetermined (6.1).

    Constant K (Hartley 1997): a rotation R about axis a keeps every DIAC K (alpha I + beta a a^T) K^T
    fixed, a one-parameter family; in the image it changes the aspect ratio (and skew / principal point
    unless a is a camera axis), so with the aspect ratio KNOWN and the skew known the family is gone -
    section 6.1 (Hayman 2000): for pure pan or tilt the aspect ratio must be known and the skew or the
    principal point constrained. A fixed lens (constant f and principal point, square pixels, zero skew)
    is therefore calibrated by a pan alone. With a focal length varying per frame the session keeps
    reporting pan-only/tilt-only motion as degenerate.
    """
    if model.focal is ParamMode.VARYING or model.principal_point is ParamMode.VARYING:
        return True
    return model.aspect is not ParamMode.KNOWN or model.skew is not ParamMode.KNOWN


def rotation_vectors(R: ArrayLike) -> Array:
    """(n, 3) axis-angle vectors (radians) of rotations relative to the reference frame."""
    return Rotation.from_matrix(np.asarray(R, dtype=float).reshape(-1, 3, 3)).as_rotvec()


def disambiguation_magnitude(rotvec: Array, focal: Array, image_size: tuple[int, int]) -> Array:
    """Per-frame size in pixels of eq. 30's disambiguating term (x/f)(x theta_Y - y theta_X).

    Evaluated at the four image corners (where it is largest), x and y relative to the centre.
    """
    cx, cy = image_centre(image_size)
    corners = np.array([[-cx, -cy], [cx, -cy], [-cx, cy], [cx, cy]])
    cross = corners[:, 0][None] * rotvec[:, 1:2] - corners[:, 1][None] * rotvec[:, 0:1]  # (n, 4)
    radius = np.linalg.norm(corners, axis=1)[None]
    return np.max(np.abs(cross) * radius, axis=1) / focal


def axis_disambiguation(rotvec: Array, focal: float, image_size: tuple[int, int]) -> tuple[float, float]:
    """(tilt, pan): the largest size in pixels of eq. 30's disambiguating term that the rotations about
    frame 0's x (tilt) and y (pan) axes give alone, at its image corner, f = frame 0's focal length.

    With square pixels and zero skew the single-axis degeneracies are those of a camera axis (6.1:
    pan-only, tilt-only), and f separates from the rotation only through this term (6.2): a sequence
    determines its calibration once both components stand above the homographies' noise.
    """
    cx, cy = image_centre(image_size)
    tilt = float(np.max(np.abs(rotvec[:, 0]))) * cx * cy / focal
    pan = float(np.max(np.abs(rotvec[:, 1]))) * cx * cx / focal
    return tilt, pan


def analyse_motion(
    R: ArrayLike,
    K: ArrayLike,
    image_size: tuple[int, int],
    sigma_f: ArrayLike | None = None,
    *,
    min_rotation_deg: float = 0.5,
    single_axis_ratio: float = 0.05,
    min_disambiguation_px: float = 1.0,
    max_relative_sigma_f: float = 0.02,
    single_axis_degenerate: bool = True,
    min_axis_disambiguation_px: float = 2.0,
) -> MotionReport:
    """Classify a sequence's motion for self-calibration (section 6).

    R: (n, 3, 3) rotations of each frame relative to frame 0; K: (n, 3, 3) per-frame intrinsics;
    sigma_f: optional (n,) 1-sigma focal uncertainties (pixels) from a solver's Jacobian.
    Status, in order of precedence: insufficient_rotation, degenerate_single_axis, near_ambiguous, ok.
    single_axis_degenerate=False (a model for which one rotation axis is enough, see
    `single_axis_is_degenerate`): rotation about one axis is reported in the fields but not a status.
    Rotations about one oblique axis (a sweep's first frames, pan and tilt in proportion) are not
    degenerate with square pixels and zero skew: single_axis is not reported once both camera axes'
    disambiguating terms (`axis_disambiguation`) reach min_axis_disambiguation_px.
    """
    rotvec = rotation_vectors(R)
    K = np.asarray(K, dtype=float).reshape(-1, 3, 3)
    focal = K[:, 1, 1]
    extent = np.degrees(np.ptp(rotvec, axis=0))
    perp = rotvec[:, :2]
    perp_dirs = np.linalg.svd(perp - perp.mean(axis=0), full_matrices=False)[2]
    projected = (perp - perp.mean(axis=0)) @ perp_dirs.T
    perp_extent = np.degrees(np.ptp(projected, axis=0)) if len(perp) > 1 else np.zeros(2)
    max_perp = float(np.degrees(np.max(np.linalg.norm(perp, axis=1))))
    sv = np.linalg.svd(rotvec, compute_uv=False)  # uncentred: single axis <=> rank 1
    axis_ratio = float(sv[1] / sv[0]) if sv[0] > 0 else 0.0
    axis_px = axis_disambiguation(rotvec, float(focal[0]), image_size)
    single_axis = axis_ratio < single_axis_ratio and min(axis_px) < min_axis_disambiguation_px
    disambiguation = float(np.max(disambiguation_magnitude(rotvec, focal, image_size)))
    rel_sigma = float("nan")
    if sigma_f is not None:
        rel_sigma = float(np.median(np.asarray(sigma_f, dtype=float) / focal))
    if max_perp < min_rotation_deg:
        status = STATUS_INSUFFICIENT_ROTATION
        message = f"largest rotation off the optical axis {max_perp:.3g} deg < {min_rotation_deg:.3g} deg"
    elif single_axis and single_axis_degenerate:
        status = STATUS_SINGLE_AXIS
        message = f"rotation about a single axis (axis ratio {axis_ratio:.3g}): pan-only/tilt-only (6.1)"
    elif disambiguation < min_disambiguation_px or rel_sigma > max_relative_sigma_f:
        status = STATUS_NEAR_AMBIGUOUS
        message = (
            f"focal/rotation near-ambiguity (6.2): disambiguating term {disambiguation:.3g} px, "
            f"relative sigma_f {rel_sigma:.3g}"
        )
    else:
        status, message = STATUS_OK, ""
    return MotionReport(
        status=status,
        well_posed=status == STATUS_OK,
        message=message,
        rotation_extent_deg=(float(extent[0]), float(extent[1]), float(extent[2])),
        perpendicular_extent_deg=(float(perp_extent[0]), float(perp_extent[1])),
        max_perpendicular_rotation_deg=max_perp,
        single_axis=bool(single_axis),
        axis_ratio=axis_ratio,
        disambiguation_px=disambiguation,
        relative_sigma_f=rel_sigma,
        axis_disambiguation_px=axis_px,
    )


def second_axis_missing(report: MotionReport, min_px: float) -> str:
    """Why a sequence is not yet well posed for a first solve (section 6), "" when it is: the
    disambiguating term of eq. 30 about each camera axis must reach min_px (`axis_disambiguation`)."""
    tilt, pan = report.axis_disambiguation_px
    missing = [(name, px) for name, px in (("tilt (x)", tilt), ("pan (y)", pan)) if not px >= min_px]
    if not missing:
        return ""
    return "waiting for rotation about the " + " and ".join(
        f"{name} axis (disambiguating term {px:.2g} px < {min_px:.2g} px, 6.2)" for name, px in missing
    )
