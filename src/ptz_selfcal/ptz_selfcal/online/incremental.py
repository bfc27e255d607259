"""Incremental self-calibration over a bounded keyframe set, with O(1) per-frame intrinsics (no rclpy).

A calibration reference frame (frame 0) anchors everything: each keyframe brings the homography
mapping reference pixels to its own pixels. The first time the keyframes' rotation is well posed
(section 6: enough rotation about two axes) the reference K_0 and every keyframe's K_j are solved by
LM on eq. 22 (initialisation); later re-solves run only when the caller asks (`reoptimise`), so the
caller bounds their time. The keyframe set is bounded (the most redundant keyframe is dropped beyond
max_keyframes), so time and memory stay bounded however long the camera runs.

Any frame's K then costs O(1): the reference DIAC transferred by its homography (eq. 20,
selfcal/transfer).

Seam for bundle adjustment (section 5): `solver` is any callable with the signature of
`lm_solver` below; it receives the keyframe records (which may carry point matches attached with
`add_keyframe(..., matches=...)`) and returns a SelfCalibrationResult whose frame 0 is the reference.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.geometry import intrinsic_matrix, normalise_homography, rotation_from_homography
from ptz_selfcal.camera.intrinsics import (
    IntrinsicsModel,
    SelfCalibrationError,
    image_centre,
    model_from_dict,
    model_to_dict,
    rotations_from_homographies,
)
from ptz_selfcal.selfcal.degeneracy import (
    STATUS_INSUFFICIENT_ROTATION,
    STATUS_NEAR_AMBIGUOUS,
    STATUS_OK,
    STATUS_SINGLE_AXIS,
    MotionReport,
    analyse_motion,
    second_axis_missing,
    single_axis_is_degenerate,
)
from ptz_selfcal.selfcal.lm import lm_selfcalibration
from ptz_selfcal.selfcal.result import SelfCalibrationResult
from ptz_selfcal.selfcal.transfer import intrinsics_from_transferred_diac
from ptz_selfcal.status import CalibrationStatus

Array = NDArray[np.float64]


@dataclass
class Keyframe:
    """A keyframe: H maps the reference frame's pixels to this keyframe's pixels (unit determinant)."""

    keyframe_id: Hashable
    H: Array
    stamp: float | None = None
    matches: object | None = None  # opaque data for a bundle-adjustment solver (not serialised)
    K: Array | None = None  # latest estimate
    tracked: bool = True  # a tracker keyframe (False: an ordinary frame chosen for its information)
    anchor: tuple[int, Array] | None = None  # an ordinary frame: (its keyframe, H keyframe -> frame)


SolverFn = Callable[
    [Array, tuple[int, int], IntrinsicsModel, "Array | None", list[Keyframe], int],
    SelfCalibrationResult,
]


def lm_solver(
    H: Array,
    image_size: tuple[int, int],
    model: IntrinsicsModel,
    K_init: Array | None,
    keyframes: list[Keyframe],
    max_nfev: int,
) -> SelfCalibrationResult:
    """Default solver: LM on eq. 22 (keyframe records unused)."""
    del keyframes
    return lm_selfcalibration(H, image_size, model, K_init, max_nfev=max_nfev)


@dataclass(frozen=True)
class AcceptedSolve:
    """Summary of the latest accepted solve (the reference K_0 and what it cost)."""

    K_ref: Array
    sigma_f_ref: float
    residual: float
    method: str
    seconds: float
    nfev: int
    motion: dict = field(default_factory=dict)


class IncrementalCalibrator:
    """Keyframe-based online self-calibration with O(1) per-frame intrinsics."""

    def __init__(
        self,
        image_size: tuple[int, int],
        model: IntrinsicsModel | None = None,
        *,
        min_rotation_deg: float = 2.0,
        max_keyframes: int = 30,
        prior_K: ArrayLike | None = None,
        solver: SolverFn | None = None,
        converge_tol: float = 5e-3,
        min_keyframes: int = 4,
        min_axis_disambiguation_px: float = 2.0,
    ) -> None:
        if max_keyframes < min_keyframes:
            raise ValueError("max_keyframes must be >= min_keyframes")
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.model = model or IntrinsicsModel()
        self.min_rotation_deg = float(min_rotation_deg)
        self.max_keyframes = int(max_keyframes)
        self.converge_tol = float(converge_tol)
        self.min_keyframes = int(min_keyframes)
        self.min_axis_disambiguation_px = float(min_axis_disambiguation_px)
        self.solver: SolverFn = solver or lm_solver
        if prior_K is None:
            cx, cy = image_centre(self.image_size)
            prior_K = intrinsic_matrix(float(self.image_size[0]), cx, cy)
        self.prior_K = np.asarray(prior_K, dtype=float)
        self.keyframes: list[Keyframe] = []
        self.state = CalibrationStatus.INITIALISING
        self.motion: MotionReport | None = None
        self.last_solve: AcceptedSolve | None = None
        self.message = ""
        self._stable_solves = 0

    # ---- public API -----------------------------------------------------------------------
    @property
    def reference_K(self) -> Array:
        """Current K_0 of the reference frame (the prior until a calibration was accepted)."""
        return self.prior_K.copy() if self.last_solve is None else self.last_solve.K_ref.copy()

    @property
    def calibrated(self) -> bool:
        return self.last_solve is not None

    def add_keyframe(
        self,
        keyframe_id: Hashable,
        H_ref_to_keyframe: ArrayLike,
        stamp: float | None = None,
        matches: object | None = None,
        tracked: bool = True,
        anchor: tuple[int, Array] | None = None,
    ) -> CalibrationStatus:
        """Store a keyframe (tracked=False: an ordinary frame chosen for its information); solve the
        first time the motion is well posed (initialisation, section 6).

        Once calibrated, adding is bounded work only: re-solves are the caller's, by `reoptimise`.
        """
        H = normalise_homography(H_ref_to_keyframe)
        self.keyframes = [kf for kf in self.keyframes if kf.keyframe_id != keyframe_id]
        stamp = None if stamp is None else float(stamp)
        self.keyframes.append(Keyframe(keyframe_id, H, stamp, matches, tracked=bool(tracked), anchor=anchor))
        if len(self.keyframes) > self.max_keyframes:
            self._drop_redundant(len(self.keyframes) - self.max_keyframes)
        if self.calibrated:
            return self.state
        self.motion = self._motion_from_current_calibration()
        missing = ""
        if single_axis_is_degenerate(self.model):
            bound = self.min_axis_disambiguation_px
            missing = second_axis_missing(self.motion, bound)
            if (
                self.motion.status == STATUS_SINGLE_AXIS
                and max(self.motion.axis_disambiguation_px) >= 4 * bound
            ):
                missing = ""  # a long motion about one axis alone: degenerate (6.1), not merely short
        if (
            self.motion.status == STATUS_INSUFFICIENT_ROTATION
            or missing
            or len(self.keyframes) < self.min_keyframes
        ):
            self.state = CalibrationStatus.INITIALISING
            self.message = missing
            return self.state
        if self.motion.status != STATUS_OK:
            self.state = CalibrationStatus.DEGENERATE_MOTION
            self.message = self.motion.message
            return self.state
        return self.reoptimise()

    def frame_intrinsics(self, H_ref_to_frame: ArrayLike) -> tuple[Array, Array, float]:
        """(K_j, R_j, sigma_f_j) of any frame in O(1) from the reference calibration (eq. 20).

        sigma_f_j = f_j sigma_f0 / f_0: the common-scale term of section 6.2 dominates. Before a
        calibration is accepted K_j comes from the prior K_0 and sigma_f_j is NaN. Raises
        SelfCalibrationError when H is inconsistent with the model (non-positive f^2 or DIAC).
        """
        H = normalise_homography(H_ref_to_frame)
        K_ref = self.reference_K
        K_j = intrinsics_from_transferred_diac(H, K_ref, self.model, self.image_size)
        R_j = rotation_from_homography(H, K_ref, K_j)
        if self.last_solve is None:
            return K_j, R_j, float("nan")
        rel = self.last_solve.sigma_f_ref / self.last_solve.K_ref[1, 1]
        return K_j, R_j, float(K_j[1, 1] * rel)

    def reoptimise(
        self, max_seconds: float | None = None, solver: SolverFn | None = None
    ) -> CalibrationStatus:
        """Re-solve over the bounded keyframe set (reference frame first) and update the state."""
        if len(self.keyframes) < self.min_keyframes:
            return self.state
        H = np.concatenate([np.eye(3)[None], np.array([kf.H for kf in self.keyframes])])
        K_init = None
        if self.calibrated:
            K_init = np.array([self.reference_K] + [kf.K for kf in self.keyframes if kf.K is not None])
            if len(K_init) != len(H):
                K_init = self._transferred_intrinsics(H)
        max_nfev = self._nfev_budget(max_seconds)
        start = time.perf_counter()
        try:
            result = (solver or self.solver)(
                H, self.image_size, self.model, K_init, list(self.keyframes), max_nfev
            )
        except SelfCalibrationError as error:
            self.message = str(error)
            if not self.calibrated:
                self.state = CalibrationStatus.DEGENERATE_MOTION
            return self.state
        seconds = time.perf_counter() - start
        self._accept(result, seconds)
        return self.state

    # ---- persistence ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        """State as plain Python types (YAML-serialisable). Keyframe matches are not saved."""
        return {
            "version": 1,
            "image_size": list(self.image_size),
            "model": model_to_dict(self.model),
            "min_rotation_deg": self.min_rotation_deg,
            "max_keyframes": self.max_keyframes,
            "converge_tol": self.converge_tol,
            "min_keyframes": self.min_keyframes,
            "min_axis_disambiguation_px": self.min_axis_disambiguation_px,
            "prior_K": self.prior_K.tolist(),
            "state": self.state.value,
            "message": self.message,
            "stable_solves": self._stable_solves,
            "keyframes": [
                {
                    "id": kf.keyframe_id,
                    "H": kf.H.tolist(),
                    "stamp": kf.stamp,
                    "K": None if kf.K is None else kf.K.tolist(),
                    "tracked": kf.tracked,
                    "anchor": None if kf.anchor is None else [int(kf.anchor[0]), kf.anchor[1].tolist()],
                }
                for kf in self.keyframes
            ],
            "last_solve": None
            if self.last_solve is None
            else {
                "K_ref": self.last_solve.K_ref.tolist(),
                "sigma_f_ref": float(self.last_solve.sigma_f_ref),
                "residual": float(self.last_solve.residual),
                "method": self.last_solve.method,
                "seconds": float(self.last_solve.seconds),
                "nfev": int(self.last_solve.nfev),
                "motion": self.last_solve.motion,
            },
        }

    @classmethod
    def from_dict(cls, data: dict, solver: SolverFn | None = None) -> IncrementalCalibrator:
        calibrator = cls(
            tuple(data["image_size"]),
            model_from_dict(data["model"]),
            min_rotation_deg=data["min_rotation_deg"],
            max_keyframes=data["max_keyframes"],
            prior_K=np.array(data["prior_K"]),
            solver=solver,
            converge_tol=data.get("converge_tol", 5e-3),
            min_keyframes=data.get("min_keyframes", 4),
            min_axis_disambiguation_px=data.get("min_axis_disambiguation_px", 2.0),
        )
        calibrator.keyframes = [
            Keyframe(
                kf["id"],
                np.array(kf["H"], dtype=float),
                kf["stamp"],
                None,
                None if kf["K"] is None else np.array(kf["K"], dtype=float),
                bool(kf.get("tracked", True)),
                None
                if kf.get("anchor") is None
                else (int(kf["anchor"][0]), np.array(kf["anchor"][1], dtype=float)),
            )
            for kf in data["keyframes"]
        ]
        calibrator.state = CalibrationStatus(data["state"])
        calibrator.message = data.get("message", "")
        calibrator._stable_solves = int(data.get("stable_solves", 0))
        solve = data.get("last_solve")
        if solve is not None:
            calibrator.last_solve = AcceptedSolve(
                np.array(solve["K_ref"], dtype=float),
                solve["sigma_f_ref"],
                solve["residual"],
                solve["method"],
                solve["seconds"],
                solve["nfev"],
                solve.get("motion", {}),
            )
        return calibrator

    # ---- internals ------------------------------------------------------------------------
    def _accept(self, result: SelfCalibrationResult, seconds: float) -> None:
        motion = result.motion
        solver_ok = result.solver_converged
        near_ambiguous = motion is not None and motion.status == STATUS_NEAR_AMBIGUOUS
        uncertain = not result.ok and solver_ok and near_ambiguous  # 6.2: best estimate, low confidence
        if not result.ok and not uncertain:
            self.message = result.message
            degenerate = motion is not None and motion.status not in (STATUS_OK, STATUS_INSUFFICIENT_ROTATION)
            if degenerate:
                self.state = CalibrationStatus.DEGENERATE_MOTION
            self._stable_solves = 0
            return  # keep the previous calibration (if any)
        previous = None if self.last_solve is None else self.last_solve.K_ref[1, 1]
        self.last_solve = AcceptedSolve(
            K_ref=result.K[0].copy(),
            sigma_f_ref=float(result.sigma_f[0]),
            residual=result.residual,
            method=result.method,
            seconds=seconds,
            nfev=result.iterations,
            motion={} if motion is None else motion.to_dict(),
        )
        for kf, K in zip(self.keyframes, result.K[1:]):
            kf.K = K.copy()
        self.message = result.message
        if uncertain:
            self._stable_solves = 0
            self.state = CalibrationStatus.DEGENERATE_MOTION
            return
        change = np.inf if previous is None else abs(result.K[0, 1, 1] / previous - 1.0)
        self._stable_solves = self._stable_solves + 1 if change < self.converge_tol else 0
        converged = self._stable_solves >= 2
        self.state = CalibrationStatus.CONVERGED if converged else CalibrationStatus.CALIBRATING

    def _nfev_budget(self, max_seconds: float | None) -> int:
        """LM evaluation budget from a time budget and the last solve's cost per evaluation."""
        if max_seconds is None or self.last_solve is None or self.last_solve.nfev == 0:
            return 200
        per_eval = self.last_solve.seconds / max(self.last_solve.nfev, 1)
        return int(np.clip(max_seconds / max(per_eval, 1e-6), 3, 200))

    def _transferred_intrinsics(self, H: Array) -> Array:
        K_ref = self.reference_K
        return intrinsics_from_transferred_diac(H, K_ref, self.model, self.image_size)

    def _motion_from_current_calibration(self) -> MotionReport:
        """Section-6 analysis of the keyframes' rotations under the current (or prior) calibration."""
        H = np.concatenate([np.eye(3)[None], np.array([kf.H for kf in self.keyframes])])
        K = self._transferred_intrinsics(H)
        R = rotations_from_homographies(H, K)
        return analyse_motion(
            R,
            K,
            self.image_size,
            min_rotation_deg=self.min_rotation_deg,
            single_axis_degenerate=single_axis_is_degenerate(self.model),
        )

    def _drop_redundant(self, count: int) -> None:
        """Drop `count` keyframes, each from the closest pair in (rotation, log zoom): the ordinary frame
        of the pair if one is (a tracker keyframe also brings the bundle adjustment real matches), else
        the older.

        The most redundant keyframe carries the least new information; O(k^2), k <= max_keyframes + 1.
        """
        H = np.array([kf.H for kf in self.keyframes])
        features = information_features(H, self.reference_K, self.model, self.image_size)
        for _ in range(count):
            d = np.linalg.norm(features[:, None] - features[None], axis=2)
            d[np.diag_indices(len(d))] = np.inf
            i, j = sorted(np.unravel_index(np.argmin(d), d.shape))
            drop = j if self.keyframes[i].tracked and not self.keyframes[j].tracked else i
            del self.keyframes[drop]
            features = np.delete(features, drop, axis=0)


def information_features(
    H: Array, K_ref: Array, model: IntrinsicsModel, image_size: tuple[int, int], fov: float | None = None
) -> Array:
    """(n, 4) [rotation vector in fields of view, log f] of the frames whose homographies from the
    reference are H, under the reference calibration K_ref (eq. 20): the metric in which a frame is
    redundant with the set's or adds to it (log zoom ~ change of the field of view). fov: the field of
    view in radians that scales the rotations (default the frames' median)."""
    H = np.asarray(H, dtype=float).reshape(-1, 3, 3)
    K = intrinsics_from_transferred_diac(H, K_ref, model, image_size)
    R = rotations_from_homographies(np.concatenate([np.eye(3)[None], H]), np.concatenate([K_ref[None], K]))
    return features_of(K, R[1:], image_size, fov)


def features_of(K: Array, R: Array, image_size: tuple[int, int], fov: float | None = None) -> Array:
    """information_features of frames whose K (n, 3, 3) and R relative to the reference are known."""
    K, R = np.asarray(K, dtype=float).reshape(-1, 3, 3), np.asarray(R, dtype=float).reshape(-1, 3, 3)
    if fov is None:
        fov = float(np.median(2.0 * np.arctan(0.5 * image_size[0] / K[:, 1, 1])))
    # the rotation vectors in closed form (angles below 180 deg): this runs on every frame
    w = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    sin = np.linalg.norm(w, axis=1)
    angle = np.arctan2(sin, 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0))
    rotvec = w * np.where(sin > 1e-12, angle / np.maximum(sin, 1e-300), 1.0)[:, None]
    return np.column_stack([rotvec / fov, np.log(K[:, 1, 1])])
