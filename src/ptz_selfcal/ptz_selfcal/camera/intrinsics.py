"""Intrinsics models shared by every self-calibration method (paper sections 3.3 and 5).

Each intrinsic of K (eq. 1) is KNOWN, CONSTANT (unknown but the same in every frame) or VARYING
(one unknown per frame), as in section 3.3.1. A model plus a frame count defines a parameter vector;
`parameter_index` maps every (frame, intrinsic) to its entry of that vector (or -1 when known), so
any optimiser (LM on eq. 22, bundle adjustment on eq. 26/27) packs and unpacks K the same way.

Intrinsic columns, in this order everywhere: f (= fy), aspect gamma (fx = gamma f), skew s (K[0, 1] =
s f), cx, cy — the convention of `geometry.intrinsic_matrix`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

# Column of each intrinsic in the (n, 5) value table.
F, ASPECT, SKEW, CX, CY = range(5)
INTRINSIC_NAMES = ("f", "aspect", "skew", "cx", "cy")


class ParamMode(enum.Enum):
    """How an intrinsic is treated over the sequence (section 3.3.1)."""

    KNOWN = "known"
    CONSTANT = "constant"
    VARYING = "varying"


class SelfCalibrationError(Exception):
    """The self-calibration problem is ill-posed or its solution is invalid (never a silently wrong K)."""


def image_centre(image_size: tuple[int, int]) -> tuple[float, float]:
    """Centre of a (width, height) image with pixel centres at integer coordinates."""
    width, height = image_size
    return (0.5 * (width - 1.0), 0.5 * (height - 1.0))


@dataclass(frozen=True)
class IntrinsicsModel:
    """Which intrinsics are known, constant-unknown or varying (default: square pixels, zero skew,
    constant unknown principal point, varying focal length — the paper's 'LM constant pp')."""

    focal: ParamMode = ParamMode.VARYING
    aspect: ParamMode = ParamMode.KNOWN
    skew: ParamMode = ParamMode.KNOWN
    principal_point: ParamMode = ParamMode.CONSTANT
    focal_value: float | None = None
    aspect_value: float = 1.0
    skew_value: float = 0.0
    principal_point_value: tuple[float, float] | None = None  # None = image centre

    def __post_init__(self) -> None:
        if self.focal is ParamMode.KNOWN and self.focal_value is None:
            raise ValueError("a KNOWN focal length needs focal_value")

    @property
    def modes(self) -> tuple[ParamMode, ParamMode, ParamMode, ParamMode, ParamMode]:
        """Mode of each intrinsic column (f, aspect, skew, cx, cy)."""
        pp = self.principal_point
        return (self.focal, self.aspect, self.skew, pp, pp)

    def known_values(self, image_size: tuple[int, int]) -> Array:
        """(5,) default value of each column (used for KNOWN columns; focal NaN when not known)."""
        cx, cy = self.principal_point_value or image_centre(image_size)
        f = np.nan if self.focal_value is None else float(self.focal_value)
        return np.array([f, self.aspect_value, self.skew_value, cx, cy], dtype=float)

    def normalised(self, image_size: tuple[int, int], nominal_focal: float) -> IntrinsicsModel:
        """The same model in coordinates centred at the image centre and scaled by nominal_focal."""
        cx, cy = self.principal_point_value or image_centre(image_size)
        c = image_centre(image_size)
        f = None if self.focal_value is None else self.focal_value / nominal_focal
        pp = ((cx - c[0]) / nominal_focal, (cy - c[1]) / nominal_focal)
        return replace(self, focal_value=f, principal_point_value=pp)

    # Presets (section 4.1's constraint sets).
    @classmethod
    def square_constant_pp(cls) -> IntrinsicsModel:
        return cls()

    @classmethod
    def square_varying_pp(cls) -> IntrinsicsModel:
        return cls(principal_point=ParamMode.VARYING)

    @classmethod
    def square_known_pp(cls, principal_point: tuple[float, float] | None = None) -> IntrinsicsModel:
        return cls(principal_point=ParamMode.KNOWN, principal_point_value=principal_point)

    @classmethod
    def constant_aspect(cls) -> IntrinsicsModel:
        """Zero skew, constant unknown aspect ratio and principal point, varying focal length."""
        return cls(aspect=ParamMode.CONSTANT)


SQUARE_CONSTANT_PP = IntrinsicsModel.square_constant_pp()
SQUARE_VARYING_PP = IntrinsicsModel.square_varying_pp()
SQUARE_KNOWN_PP = IntrinsicsModel.square_known_pp()


def model_to_dict(model: IntrinsicsModel) -> dict:
    """IntrinsicsModel as plain Python types."""
    return {
        "focal": model.focal.value,
        "aspect": model.aspect.value,
        "skew": model.skew.value,
        "principal_point": model.principal_point.value,
        "focal_value": model.focal_value,
        "aspect_value": model.aspect_value,
        "skew_value": model.skew_value,
        "principal_point_value": None
        if model.principal_point_value is None
        else [float(v) for v in model.principal_point_value],
    }


def model_from_dict(data: dict) -> IntrinsicsModel:
    pp = data.get("principal_point_value")
    return IntrinsicsModel(
        focal=ParamMode(data["focal"]),
        aspect=ParamMode(data["aspect"]),
        skew=ParamMode(data["skew"]),
        principal_point=ParamMode(data["principal_point"]),
        focal_value=data.get("focal_value"),
        aspect_value=data.get("aspect_value", 1.0),
        skew_value=data.get("skew_value", 0.0),
        principal_point_value=None if pp is None else (float(pp[0]), float(pp[1])),
    )


def parameter_index(model: IntrinsicsModel, n_frames: int) -> NDArray[np.intp]:
    """(n, 5) index of each (frame, intrinsic) into the parameter vector, -1 where KNOWN.

    Parameters are laid out column by column: CONSTANT gives one entry, VARYING n entries.
    """
    index = np.full((n_frames, 5), -1, dtype=np.intp)
    count = 0
    for column, mode in enumerate(model.modes):
        if mode is ParamMode.CONSTANT:
            index[:, column] = count
            count += 1
        elif mode is ParamMode.VARYING:
            index[:, column] = np.arange(count, count + n_frames)
            count += n_frames
    return index


def parameter_count(model: IntrinsicsModel, n_frames: int) -> int:
    """Number of unknowns U + V(n-1) of eq. 21."""
    index = parameter_index(model, n_frames)
    return int(index.max()) + 1 if (index >= 0).any() else 0


def values_from_parameters(
    p: ArrayLike, model: IntrinsicsModel, n_frames: int, image_size: tuple[int, int]
) -> Array:
    """(n, 5) table of (f, aspect, skew, cx, cy) per frame from a parameter vector."""
    index = parameter_index(model, n_frames)
    values = np.tile(model.known_values(image_size), (n_frames, 1))
    mask = index >= 0
    values[mask] = np.asarray(p, dtype=float)[index[mask]]
    return values


def matrices_from_values(values: ArrayLike) -> Array:
    """(n, 3, 3) K of eq. 1 from an (n, 5) table of (f, aspect, skew, cx, cy)."""
    v = np.atleast_2d(np.asarray(values, dtype=float))
    K = np.zeros((len(v), 3, 3))
    K[:, 0, 0] = v[:, ASPECT] * v[:, F]
    K[:, 0, 1] = v[:, SKEW] * v[:, F]
    K[:, 0, 2] = v[:, CX]
    K[:, 1, 1] = v[:, F]
    K[:, 1, 2] = v[:, CY]
    K[:, 2, 2] = 1.0
    return K


def values_from_matrices(K: ArrayLike) -> Array:
    """(n, 5) table of (f, aspect, skew, cx, cy) from (n, 3, 3) upper-triangular K (K[2, 2] = 1)."""
    K = np.asarray(K, dtype=float).reshape(-1, 3, 3)
    K = K / K[:, 2:3, 2:3]
    f = K[:, 1, 1]
    return np.column_stack([f, K[:, 0, 0] / f, K[:, 0, 1] / f, K[:, 0, 2], K[:, 1, 2]])


def intrinsics_from_parameters(
    p: ArrayLike, model: IntrinsicsModel, n_frames: int, image_size: tuple[int, int]
) -> Array:
    """(n, 3, 3) K per frame from a parameter vector laid out by `parameter_index`."""
    return matrices_from_values(values_from_parameters(p, model, n_frames, image_size))


def parameters_from_intrinsics(K: ArrayLike, model: IntrinsicsModel) -> Array:
    """Parameter vector from (n, 3, 3) K; CONSTANT entries take the mean over frames."""
    values = values_from_matrices(K)
    index = parameter_index(model, len(values))
    mask = index >= 0
    count = parameter_count(model, len(values))
    sums = np.bincount(index[mask], weights=values[mask], minlength=count)
    hits = np.bincount(index[mask], minlength=count)
    return sums / np.maximum(hits, 1)


def nearest_rotations(M: ArrayLike) -> Array:
    """Batched projection of (n, 3, 3) matrices onto SO(3) (SVD, Frobenius-nearest)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def rotations_from_homographies(H: ArrayLike, K: ArrayLike) -> Array:
    """(n, 3, 3) R_j = K_j^-1 H_j K_0 (section 3.3.1), scale removed and projected onto SO(3)."""
    H = np.asarray(H, dtype=float).reshape(-1, 3, 3)
    K = np.asarray(K, dtype=float).reshape(-1, 3, 3)
    M = np.linalg.solve(K, H @ K[0])
    M /= np.cbrt(np.linalg.det(M))[:, None, None]
    return nearest_rotations(M)
