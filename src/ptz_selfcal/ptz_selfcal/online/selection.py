"""Calibration frames chosen from every frame's homography, not only the tracker's keyframes.

A camera that moves little (a long focal length, the paper's 5 deg circle of section 4.1, a slow
start) makes few tracker keyframes, but every frame's homography to the reference carries the
rotation and zoom information that self-calibration needs (section 3: the paper uses every frame).
The frame path proposes an ordinary frame for the solve when it is far from every member of the
bounded set in the metric the set is pruned in (online/incremental.information_features: rotation
in fields of view, log f, under the current or prior calibration): it adds rotation axes, angles or
zoom the set does not have. Once the set is full, only a frame farther from it than its members are
from their nearest neighbours (median) is proposed: it fills a gap, and the solve drops the redundant
member of the closest pair for it, so the proposals stop once the set spans what the camera has
seen. O(k) per frame, k <= max_keyframes + 1.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.online.incremental import IncrementalCalibrator, features_of, information_features

Array = NDArray[np.float64]

_TRANSFER_ERRORS = (SelfCalibrationError, ValueError, ArithmeticError, np.linalg.LinAlgError)


class CalibrationFrameSelector:
    """The frame path's view of the solve's set (reference, keyframes, proposed frames), and which
    ordinary frames join it. Ordinary frames get ids below every tracker keyframe id (those are frame
    indices, >= 0): -1, -2, ..."""

    def __init__(self, capacity: int, spacing: float) -> None:
        self.capacity = int(capacity)  # the solve's set: max_keyframes and the reference
        self.spacing = float(spacing)  # the smallest distance of a proposal from every member
        self._members: dict[int, tuple[Array, Array]] = {}  # id -> (H reference -> frame, feature)
        self._basis: tuple[int, float] | None = None  # (calibrator id, f_ref) the features are under
        self._gap = math.inf  # the members' median distance to their nearest neighbour (when full)
        self.next_id = -1

    def member(self, frame_id: int, H: Array, calibrator: IncrementalCalibrator) -> None:
        """A frame that entered the solve another way (the reference, a tracker keyframe)."""
        feature = self._feature(H, calibrator)
        if feature is not None:
            self._add(frame_id, H, feature)

    def propose(
        self, H: Array, calibrator: IncrementalCalibrator, KR: tuple[Array, Array] | None = None
    ) -> int | None:
        """The id under which this ordinary frame joins the solve, None when it adds too little. KR: the
        frame's K and R relative to the reference when the frame path has them already (eq. 20 from its
        keyframe), which spares a transfer per frame."""
        feature = self._feature(H, calibrator, KR)
        if feature is None:
            return None
        if self._members:
            features = np.array([f for _, f in self._members.values()])
            nearest = float(np.min(np.linalg.norm(features - feature, axis=1)))
            full = len(self._members) >= self.capacity
            if not nearest > max(self.spacing, self._gap if full else 0.0):
                return None
        frame_id = self.next_id
        self.next_id -= 1
        self._add(frame_id, H, feature)
        return frame_id

    def forget(self) -> None:
        """A new reference: the set starts again (ids keep counting down)."""
        self._members.clear()
        self._basis = None
        self._gap = math.inf

    def keep_only(self, frame_ids: set[int]) -> None:
        """The solve's set as its latest snapshot holds it (with the frames not handed to it yet):
        members it dropped are forgotten, so that the view follows the solve's own pruning."""
        kept = {k: m for k, m in self._members.items() if k in frame_ids or _is_reference(m[0])}
        if len(kept) != len(self._members):
            self._members = kept
            self._update_closest()

    def restored(self, frame_ids: list[int]) -> None:
        """Ids of a restored set: new ordinary frames are numbered below them."""
        self.next_id = min([self.next_id, *(int(k) - 1 for k in frame_ids if int(k) < 0)])

    def __len__(self) -> int:
        return len(self._members)

    # ----------------------------------------------------------------------------------------------
    def _feature(
        self, H: Array, calibrator: IncrementalCalibrator, KR: tuple[Array, Array] | None = None
    ) -> Array | None:
        K_ref = calibrator.reference_K
        fov = 2.0 * math.atan(0.5 * calibrator.image_size[0] / K_ref[1, 1])
        basis = (id(calibrator), float(K_ref[1, 1]))
        if basis != self._basis:  # a new calibration: the members' features under it (O(k))
            self._basis = basis
            self._recompute(calibrator, fov)
        if KR is not None:
            feature = features_of(KR[0], KR[1], calibrator.image_size, fov)[0]
            return feature if np.all(np.isfinite(feature)) else None
        return self._transfer(H, calibrator, fov)

    def _recompute(self, calibrator: IncrementalCalibrator, fov: float) -> None:
        """The members' features under a new calibration: one vectorised transfer, one by one when a
        member's fails."""
        if not self._members:
            return
        ids, H = list(self._members), np.array([H for H, _ in self._members.values()])
        try:
            K_ref, model, size = calibrator.reference_K, calibrator.model, calibrator.image_size
            features = information_features(H, K_ref, model, size, fov)
        except _TRANSFER_ERRORS:
            features = [self._transfer(H_k, calibrator, fov) for H_k in H]
        self._members = {
            k: (H_k, f) for k, H_k, f in zip(ids, H, features) if f is not None and np.all(np.isfinite(f))
        }
        self._update_closest()

    @staticmethod
    def _transfer(H: Array, calibrator: IncrementalCalibrator, fov: float) -> Array | None:
        try:
            K_ref, model, size = calibrator.reference_K, calibrator.model, calibrator.image_size
            feature = information_features(H, K_ref, model, size, fov)[0]
        except _TRANSFER_ERRORS:
            return None
        return feature if np.all(np.isfinite(feature)) else None

    def _add(self, frame_id: int, H: Array, feature: Array) -> None:
        self._members.pop(frame_id, None)
        self._members[frame_id] = (H, feature)
        while len(self._members) > self.capacity:  # the solve drops the most redundant: so does its view
            ids = list(self._members)
            i, j = sorted(np.unravel_index(np.argmin(self._distances()), (len(ids), len(ids))))
            drop = j if ids[i] >= 0 > ids[j] else i
            del self._members[ids[drop]]
        self._update_closest()

    def _distances(self) -> Array:
        features = np.array([f for _, f in self._members.values()])
        d = np.linalg.norm(features[:, None] - features[None], axis=2)
        d[np.diag_indices(len(d))] = np.inf
        return d

    def _update_closest(self) -> None:
        full = len(self._members) >= self.capacity
        self._gap = (
            float(np.median(np.min(self._distances(), axis=1))) if full and len(self) > 1 else math.inf
        )


def _is_reference(H: Array) -> bool:
    return bool(np.allclose(H, np.eye(3), atol=1e-9))
