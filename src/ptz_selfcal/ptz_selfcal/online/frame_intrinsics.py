"""Per-frame intrinsics in O(1), and the fallback chain when there is no calibration to transfer.

A calibrated frame's K is a solved keyframe's K transferred by the short keyframe -> frame homography
(eq. 20), so the error of the long reference -> keyframe chain does not enter; its 1-sigma adds the
transfer's error and the homography's own (the part of it no rotating, zooming camera produces).
Without a calibration the chain is: the zoom model at the frame's zoom encoder, the prior transferred
through the frame's homography, the last good K (tracking lost), the nominal field of view.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import intrinsic_matrix, rotation_from_homography
from ptz_selfcal.camera.intrinsics import SelfCalibrationError
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput, FrameOutput
from ptz_selfcal.online.work import CalibrationSnapshot
from ptz_selfcal.selfcal.transfer import intrinsics_from_transferred_diac, transfer_misfit
from ptz_selfcal.status import SOLVED, CalibrationStatus
from ptz_selfcal.zoom.model import ZoomModel

Array = NDArray[np.float64]

_LIMIT = 4096  # keyframe ids grow with the frame index: every per-keyframe map is bounded


class TransferError:
    """How far the K a frame gets by transfer (eq. 20) from its keyframe is off, per unit of log zoom
    between them: measured at every new keyframe, whose own frame got its K by transfer from the keyframe
    it was tracked against and which later gets the adjustment's own K. The frame's homography is tracked
    and, for a distorted lens, corrected by a refit whose error grows with the zoom between the two
    images, so neither the adjustment's covariance nor the chain's spread holds it."""

    def __init__(self, samples: int = 8) -> None:  # recent keyframes: the lens estimate improves
        self._samples: deque[tuple[float, float]] = deque(maxlen=samples)  # (log error, log zoom)
        self._slope = 0.0

    def add(self, error: float, zoom: float) -> None:
        if math.isfinite(error) and math.isfinite(zoom):
            self._samples.append((error, zoom))
            zz = sum(z * z for _, z in self._samples)
            # the rms of the error per unit of zoom, through the origin (no zoom, no transfer error)
            self._slope = math.sqrt(sum(e * e for e, _ in self._samples) / zz) if zz > 1e-10 else 0.0

    def sigma(self, zoom: float) -> float:
        """The relative 1-sigma of f transferred over log zoom `zoom`."""
        return self._slope * abs(zoom) if math.isfinite(zoom) else 0.0


def _bounded_put(mapping: dict, key: int, value: object) -> None:
    mapping[key] = value
    if len(mapping) > _LIMIT:
        mapping.pop(next(iter(mapping)))


class KeyframeLinks:
    """What the frame path knows of keyframes the solve has not seen yet: each one's homography from
    the reference as tracked, the keyframe it was matched to (with the link's homography), and the
    keyframes whose homography the zoom gate refused."""

    def __init__(self) -> None:
        self.homography: dict[int, Array] = {}  # keyframe -> H reference -> keyframe
        self.neighbour: dict[int, tuple[int, Array | None]] = {}  # keyframe -> (linked keyframe, H)
        self.refused: set[int] = set()
        # keyframe -> (the solved keyframe its own frame's K was transferred from, that frame's H), until
        # the keyframe is solved itself
        self.transferred: dict[int, tuple[int, Array]] = {}
        self.transfer_error = TransferError()

    def add_keyframe(self, keyframe_id: int, H: Array) -> None:
        _bounded_put(self.homography, keyframe_id, H)

    def refuse(self, keyframe_id: int) -> None:
        self.refused.add(keyframe_id)
        if len(self.refused) > _LIMIT:
            self.refused = set(sorted(self.refused)[_LIMIT // 2 :])

    def link(self, keyframe_id: int, other_keyframe_id: int, H: Array | None) -> None:
        """The first link of a keyframe (H maps other_keyframe_id pixels to keyframe_id pixels)."""
        if keyframe_id not in self.neighbour and other_keyframe_id != keyframe_id:
            _bounded_put(self.neighbour, keyframe_id, (other_keyframe_id, H))

    def forget_reference(self) -> None:
        """A new reference: the refusals were of the old one (links and homographies are per id)."""
        self.refused.clear()
        self.transferred.clear()

    def transfer_sample(self, snap: CalibrationSnapshot, keyframe_id: int) -> None:
        """A keyframe's own K is solved: how far its own frame's transfer is off, in the same snapshot (the
        transfer from the keyframe it was tracked against, by that frame's homography, against the
        adjustment's K: a re-solve that moves the whole calibration in between is not a transfer error)."""
        got = self.transferred.pop(keyframe_id, None)
        base = None if got is None else snap.keyframes.get(got[0])
        own = snap.keyframes.get(keyframe_id)
        if got is None or base is None or own is None:
            return
        model, size = snap.calibrator.model, snap.calibrator.image_size
        try:  # a measurement only: the frame's own K does not depend on it
            K = intrinsics_from_transferred_diac(got[1] @ np.linalg.inv(base[0]), base[1], model, size)
        except (SelfCalibrationError, ValueError, ArithmeticError, np.linalg.LinAlgError):
            return
        f, f_own, f_base = float(K[1, 1]), float(own[1][1, 1]), float(base[1][1, 1])
        if f > 0.0 and f_own > 0.0 and f_base > 0.0:
            self.transfer_error.add(math.log(f / f_own), math.log(f_own / f_base))


def frame_intrinsics(
    snap: CalibrationSnapshot,
    H: Array,
    keyframe_id: int,
    links: KeyframeLinks,
    tracked_against: int | None = None,
) -> tuple[Array, Array, float, float]:
    """K_j, R_j, sigma_f of a frame whose homography from the reference is H, and the share of sigma_f/f
    that is the homography's own (transfer_misfit: how far it is from any rotating, zooming camera's).

    Tracked against a keyframe of the solve (or one linked to it), its K is that keyframe's refined K
    (bundle adjustment) transferred by H_j H_k^-1 and its orientation R_kj R_k; otherwise the reference
    calibration is transferred by H (eq. 20). A new keyframe's own frame starts from the keyframe it
    was tracked against (`tracked_against`): its link comes on another topic, maybe after the frame,
    and its K must not depend on which came first.
    """
    K_ref, R_ref, sigma_f = snap.calibrator.frame_intrinsics(H)
    model, size = snap.calibrator.model, snap.calibrator.image_size
    local = snap.keyframes.get(keyframe_id)
    if local is not None and keyframe_id in links.transferred:
        links.transfer_sample(snap, keyframe_id)
    if local is None:
        start = keyframe_id if tracked_against is None else tracked_against
        local = snap.keyframes.get(start)
        if local is not None and tracked_against is not None and keyframe_id not in links.transferred:
            _bounded_put(links.transferred, keyframe_id, (start, np.asarray(H, dtype=float).copy()))
        if local is None:
            local = _unsolved_keyframe(snap, start, links)
    if local is None:
        misfit = _misfit(H, snap.calibrator.reference_K, size)
        return K_ref, R_ref, math.hypot(sigma_f / K_ref[1, 1], misfit) * K_ref[1, 1], misfit
    H_k, K_k, R_k = local
    H_local = H @ np.linalg.inv(H_k)
    K = intrinsics_from_transferred_diac(H_local, K_k, model, size)
    R = rotation_from_homography(H_local, K_k, K) @ R_k
    zoom = math.log(K[1, 1] / K_k[1, 1]) if K[1, 1] > 0.0 and K_k[1, 1] > 0.0 else math.nan
    # the reference's honest sigma (the common scale, section 6.2), the transfer's own error (eq. 20) and
    # the error the frame's homography shows (eq. 4)
    misfit = _misfit(H_local, K_k, size)
    terms = (sigma_f / K_ref[1, 1], links.transfer_error.sigma(zoom), misfit)
    return K, R, math.sqrt(sum(t * t for t in terms)) * K[1, 1], misfit


def _misfit(H: Array, K_from: Array, size: tuple[int, int]) -> float:
    """transfer_misfit, infinite when H has no rotating, zooming camera's map at all (the frame's f is
    then unknown however well the reference is calibrated)."""
    misfit = transfer_misfit(H, K_from, size)
    return misfit if math.isfinite(misfit) else math.inf


def _unsolved_keyframe(
    snap: CalibrationSnapshot, keyframe_id: int, links: KeyframeLinks
) -> tuple[Array, Array, Array] | None:
    """(H_ref_to_kf, K, R) of a keyframe the solve has not seen yet: a solved keyframe's refined K and R
    carried forward through the tracker's keyframe links (direct measurements), not the long chain."""
    chain: list[Array | None] = []
    kid = keyframe_id
    while kid not in snap.keyframes and kid in links.neighbour and len(chain) < 16:
        kid, h = links.neighbour[kid]
        chain.append(h)
        if kid in links.refused:
            return None
    solved = snap.keyframes.get(kid)
    if solved is None:
        return None
    H_kf = links.homography.get(keyframe_id)
    if H_kf is None or any(h is None for h in chain):  # links without their homography
        return solved
    _, K, R = solved
    model, size = snap.calibrator.model, snap.calibrator.image_size
    for h in reversed(chain):
        assert h is not None
        K_next = intrinsics_from_transferred_diac(h, K, model, size)
        R = rotation_from_homography(h, K, K_next) @ R
        K = K_next
    return H_kf, K, R


def calibrated_output(
    snap: CalibrationSnapshot, frame: FrameInput, K: Array, R: Array, sigma_f: float, D: Array
) -> FrameOutput:
    """A calibrated frame: its K transferred from the snapshot, the snapshot's status and residual."""
    return FrameOutput(
        status=snap.state if snap.state in SOLVED else CalibrationStatus.CALIBRATING,
        K=np.asarray(K, dtype=float),
        D=D,
        R=np.asarray(R, dtype=float) if np.all(np.isfinite(R)) else None,
        sigma_f=float(sigma_f),
        sigma_cx=snap.sigma_pp[0],
        sigma_cy=snap.sigma_pp[1],
        residual=snap.residual,
        keyframe_id=int(frame.keyframe_id),
        keyframe_count=snap.keyframe_count,
        source="calibration",
        message=snap.message,
    )


def nominal_output(
    config: SessionConfig, image_size: tuple[int, int], frame: FrameInput, status: str, keyframe_count: int
) -> FrameOutput:
    """The nominal field of view at the image centre: what is known before anything is measured."""
    width, height = image_size
    f = config.nominal_focal(width)
    return FrameOutput(
        status=status,
        K=intrinsic_matrix(f, 0.5 * (width - 1.0), 0.5 * (height - 1.0)),
        D=np.zeros(5),
        R=None,
        sigma_f=config.prior_sigma_f_fraction * f,
        sigma_cx=0.05 * width,
        sigma_cy=0.05 * height,
        residual=math.nan,
        keyframe_id=int(frame.keyframe_id),
        keyframe_count=keyframe_count,
        source="nominal",
    )


def last_good_output(last: FrameOutput) -> FrameOutput:
    """Tracking lost and no zoom model: the last good calibration, orientation unknown."""
    return FrameOutput(
        status=CalibrationStatus.TRACKING_LOST,
        K=last.K.copy(),
        D=last.D.copy(),
        R=None,
        sigma_f=last.sigma_f,
        sigma_cx=last.sigma_cx,
        sigma_cy=last.sigma_cy,
        residual=math.nan,
        keyframe_id=last.keyframe_id,
        keyframe_count=last.keyframe_count,
        source="last_good",
    )


def zoom_output(
    zoom_model: ZoomModel | None, frame: FrameInput, zoom_rate: float, status: str, keyframe_count: int
) -> FrameOutput | None:
    """The zoom model's calibration at the frame's zoom encoder (None without a model or an encoder);
    the model's own errors propagate."""
    if not math.isfinite(frame.zoom) or zoom_model is None:
        return None
    K, D, sigma_f, _ = zoom_model.predict(float(frame.zoom), zoom_rate)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0.0:
        return None
    return FrameOutput(
        status=status,
        K=np.asarray(K, dtype=float),
        D=np.nan_to_num(np.asarray(D, dtype=float).reshape(5)),
        R=None,
        sigma_f=float(sigma_f),
        sigma_cx=math.nan,
        sigma_cy=math.nan,
        residual=math.nan,
        keyframe_id=int(frame.keyframe_id),
        keyframe_count=keyframe_count,
        source="zoom_model",
    )


def initialising_reason(snap: CalibrationSnapshot | None, held: int, config: SessionConfig) -> str:
    """Why there is no calibration yet, for FrameCalibration users and logs."""
    reason = "no frame solved yet: waiting for rotation about two axes (section 6)"
    if snap is not None:
        reason = f"{snap.keyframe_count - 1} of min_keyframes {config.min_keyframes} keyframes"
    if held:
        reason += (", " if reason else "") + (
            f"{held} keyframes held out of the solve: the image moved faster than "
            f"max_keyframe_motion {config.max_keyframe_motion:g} image widths/s"
        )
    return reason
