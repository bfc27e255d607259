"""Keyframe-based homography tracker for a rotating and zooming camera (paper sections 2.2 and 4.2).

Per frame (working resolution): the current keyframe is warped by the constant-velocity prediction of
its keyframe -> frame homography and pyramidal KLT (forward-backward checked) measures the residual
motion of the keyframe's corners. Every track is thus a measured keyframe position paired with a
current position, without the drift of frame-to-frame chaining and without the bias translational
KLT has under zoom (klt_source="frame" gives classic frame-to-frame KLT). The keyframe -> frame
infinite homography comes from seeded USAC/MAGSAC, then LM on the inliers (frontend.homography).
A new keyframe is made when the overlap, the scale or the surviving tracks drop. It is linked to its
parent (the tracked fit) and to older overlapping keyframes, fewest hops to the reference first, each
re-measured independently of the chain (photometric KLT against the warped older keyframe, with
descriptor re-matching as fallback); its reference -> keyframe homography goes through the link with
the fewest hops, so chained error stays bounded when the camera comes back. A frame that needs a new
keyframe while a stored one covers it well (a camera back at a view it has seen) is re-measured against
that keyframe and tracked on from it instead: repeated passes over the same views add no keyframes.
After a loss (black frame, cut, fast move) descriptor matching against the stored keyframes relocalises
the camera.
Homographies in results are in full-resolution pixels (x_work = (x_full + 0.5) * s - 0.5).

Rolling shutter (frontend.rolling_shutter; TrackerConfig.rolling_shutter_readout: known, or estimated
from the tracked frames): KLT measures the observed (rolling-shutter) positions; every fit, link and
published point is on the global-shutter positions at the frames' stamps, each frame's points corrected
with its own image motion (a keyframe's as it was when made; the rotation's, without the zoom). A
frame's motion is its fit against the previous frame's: fitted first with the previous motion, refitted
once with its own. While the estimate
is not significant nothing is corrected (a global shutter is tracked exactly as without the model).

The map persists through export_map()/restore_map() and frontend.tracker_map (a restarted tracker
relocalises against it and keeps its reference and keyframe ids). Links are measured by
frontend.keyframe_links, the settings are frontend.tracker_config.TrackerConfig.
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import apply_homography, homography_work_to_full, work_from_full
from ptz_selfcal.frontend.features import (
    Descriptors,
    RobustFit,
    detect_corners,
    gain_matched,
    gain_matched_warp,
    refit_homography,
    robust_homography,
    track_klt,
)
from ptz_selfcal.frontend.homography import local_scale, max_deviation, overlap_fraction
from ptz_selfcal.frontend.keyframe_links import (
    KeyframeLink,
    KeyframeLinker,
    LinkFrame,
    MapKeyframe,
    MeasuredLink,
    make_link,
)
from ptz_selfcal.frontend.rolling_shutter import (
    MAX_FRAME_ZOOM,
    MIN_KEYFRAME_GAP,
    FrameMotion,
    ReadoutEstimator,
    displacement,
    readout_step,
    rotation_motion,
)
from ptz_selfcal.frontend.tracker_config import TrackerConfig
from ptz_selfcal.frontend.tracker_map import StoredKeyframe, TrackerMap
from ptz_selfcal.status import TrackingState

Array = NDArray[np.float64]
Points = NDArray[np.float32]

_LOG = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrackResult:
    """One frame's output. Ids are frame indices (0-based count of track() calls since reset).

    H_ref maps the reference (first keyframe of the current map) to this frame; H_keyframe maps the
    keyframe `keyframe_id` to this frame. On NEW_KEYFRAME / RELOCALISED the frame itself is the new
    keyframe (keyframe_id = its index, H_keyframe = I) and `links` holds its measured links to older
    keyframes (the calibrator's bundle adjustment input). TRACKING_LOST / TEXTURELESS: no H at all.
    """

    state: TrackingState
    frame_index: int
    stamp: float | None
    H_ref: Array | None  # reference keyframe -> current frame, full resolution (None when lost)
    H_keyframe: Array | None  # keyframe -> current frame, full resolution
    keyframe_id: int | None
    reference_id: int | None
    inlier_count: int
    match_count: int
    rms_transfer_error: float  # full-resolution pixels
    links: tuple[KeyframeLink, ...] = ()  # for NEW_KEYFRAME / RELOCALISED: links of the new keyframe
    readout: float = 0.0  # rolling-shutter readout (s) H and links are corrected for (0: none)


@dataclass
class _Tracks:
    current: Points = field(default_factory=lambda: np.empty((0, 2), np.float32))
    in_keyframe: Points = field(default_factory=lambda: np.empty((0, 2), np.float32))
    initial_count: int = 0
    H_last: Array = field(default_factory=lambda: np.eye(3))  # keyframe -> last frame (working pixels)
    H_previous: Array = field(default_factory=lambda: np.eye(3))  # keyframe -> the frame before


class HomographyTracker:
    """Frame-by-frame infinite-homography tracker; see the module docstring."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self._klt = self.config.klt()
        self._linker = KeyframeLinker(self.config)
        # the camera's, not the map's: kept through reset()
        self._readout = ReadoutEstimator(self.config.rolling_shutter_readout)
        self.reset()

    # ------------------------------------------------------------------ public API
    def reset(self) -> None:
        """Forget every keyframe and track: the next frame starts a new map (frame ids restart at 0)."""
        self._keyframes: OrderedDict[int, MapKeyframe] = OrderedDict()
        self._reference_id: int | None = None
        self._keyframe_id: int | None = None
        self._tracks = _Tracks()
        self._previous: np.ndarray | None = None
        self._scale: float | None = None
        self._frame_index = -1
        self._lost_frames = 0
        self._lost = False
        self._frame: LinkFrame | None = None  # the frame being tracked, as links see it
        self._last_H_ref: Array | None = None  # reference -> previous frame (full res; None: no H)
        self._last_stamp: float | None = None  # the previous frame's stamp
        self._last_motion: FrameMotion | None = None  # the previous frame's image motion

    @property
    def readout(self) -> ReadoutEstimator:
        """The rolling-shutter readout time: known or estimated, its sigma, and the one applied."""
        return self._readout

    def keyframes(self) -> dict[int, Array]:
        """Stored keyframes of the current map: id -> H (reference -> keyframe, full resolution)."""
        return {k: kf.H_ref.copy() for k, kf in self._keyframes.items()}

    @property
    def reference_id(self) -> int | None:
        return self._reference_id

    @property
    def frame_index(self) -> int:
        """Index of the last frame tracked (-1 before the first); the next frame gets this + 1."""
        return self._frame_index

    def export_map(self) -> TrackerMap | None:
        """The keyframe map as plain data for restore_map (None while there is no map).

        Cheap (no copies: a keyframe's arrays are never modified once stored), so it can be taken on the
        frame path and serialised (map_to_bytes) elsewhere."""
        if self._reference_id is None or self._scale is None or self._keyframe_id not in self._keyframes:
            return None
        return TrackerMap(
            reference_id=self._reference_id,
            keyframe_id=self._keyframe_id,
            frame_index=self._frame_index,
            scale=self._scale,
            keyframes=[
                StoredKeyframe(
                    id=kf.id,
                    stamp=kf.stamp,
                    H_ref=kf.H_ref,
                    depth=kf.depth,
                    image=kf.image,
                    corners=kf.corners,
                )
                for kf in self._keyframes.values()
            ],
        )

    def restore_map(self, data: TrackerMap) -> None:
        """Replace the map by an exported one (ValueError when it is inconsistent; the tracker is then
        reset). The next frame is relocalised against the stored keyframes (same reference and keyframe
        ids); frame ids continue after the stored frame index. Keyframes beyond max_keyframes are dropped
        (the least recently used, the map's order; never the reference or the last tracked one)."""
        self.reset()
        try:
            keyframes = OrderedDict()
            shape = None
            for item in data["keyframes"]:
                image = np.ascontiguousarray(item["image"], np.uint8)
                H_ref = np.asarray(item["H_ref"], np.float64).reshape(3, 3)
                corners = np.asarray(item["corners"], np.float32).reshape(-1, 2)
                shape = image.shape if shape is None else shape
                if image.ndim != 2 or image.shape != shape or not np.all(np.isfinite(H_ref)):
                    raise ValueError(f"keyframe {item['id']}: bad image or homography")
                stamp = None if item["stamp"] is None else float(item["stamp"])
                kid = int(item["id"])
                keyframes[kid] = MapKeyframe(kid, stamp, image, H_ref, int(item["depth"]), corners, None)
            reference_id, keyframe_id = int(data["reference_id"]), int(data["keyframe_id"])
            frame_index, scale = int(data["frame_index"]), float(data["scale"])
            if reference_id not in keyframes or keyframe_id not in keyframes:
                raise ValueError("the reference or the last keyframe is not among the stored keyframes")
            if not (0.0 < scale <= 1.0) or frame_index < max(keyframes):
                raise ValueError(f"bad working scale {scale} or frame index {frame_index}")
        except (KeyError, TypeError, IndexError) as exc:
            raise ValueError(f"malformed tracker map: {type(exc).__name__}: {exc}") from exc
        self._keyframes = keyframes
        self._reference_id, self._keyframe_id = reference_id, keyframe_id
        self._frame_index, self._scale = frame_index, scale
        self._lost = True
        self._prune()

    def _map_shape(self) -> tuple[int, ...] | None:
        kf = self._keyframes.get(self._reference_id) if self._reference_id is not None else None
        return None if kf is None else kf.image.shape

    def track(self, image_work: np.ndarray, scale: float, stamp: float | None = None) -> TrackResult:
        """Process one mono8 working-resolution frame; `scale` = working / full resolution."""
        image = np.ascontiguousarray(image_work, np.uint8)
        if image.ndim != 2:
            raise ValueError("the tracker expects a single-channel (mono8) image")
        shape = self._previous.shape if self._previous is not None else self._map_shape()
        shape_changed = shape is not None and shape != image.shape
        if shape_changed or (self._scale is not None and abs(scale - self._scale) > 1e-12):
            _LOG.info("image size or working scale changed: new map")
            frame_index = self._frame_index
            self.reset()
            self._frame_index = frame_index  # ids stay unique over the tracker's life
        self._scale = scale
        self._frame_index += 1
        readout = self._readout.applied if stamp is not None else 0.0
        self._frame = LinkFrame(image, self._frame_index, scale, readout=readout)
        if self._reference_id is None:
            result = self._start_map(image, stamp)
        elif self._lost:
            result = self._relocalise(image, stamp)
        else:
            result = self._track_frame(image, stamp)
        self._previous = image
        self._last_H_ref = result.H_ref
        self._last_stamp, self._last_motion = stamp, self._frame.motion
        return replace(result, readout=readout) if readout != 0.0 and result.H_ref is not None else result

    # ------------------------------------------------------------------ per-frame tracking
    def _track_frame(self, image: np.ndarray, stamp: float | None) -> TrackResult:
        c = self.config
        keyframe = self._keyframes[self._keyframe_id]
        current, ok, H_pred = self._klt_tracks(keyframe, image)
        fit = self._fit_tracks(current, ok)
        # Second warp + KLT pass when the prediction was poor: the residual then has (almost) no
        # scale/rotation left for translational KLT to be biased by (Gauss-Newton on the warp).
        repeat = fit is not None and c.klt_source == "warped" and c.repeat_threshold > 0.0
        if repeat and max_deviation(fit.H, H_pred, image.shape) > c.repeat_threshold * self._scale:
            current2, ok2 = self._warped_klt(keyframe, image, fit.H, levels=1)
            fit2 = self._fit_tracks(current2, ok2)
            if fit2 is not None and fit2.inliers.sum() >= 0.8 * fit.inliers.sum():
                current, ok, fit = current2, ok2, fit2
        verify = fit is not None and c.klt_source == "warped" and c.verify_threshold > 0.0
        if verify and max_deviation(fit.H, H_pred, image.shape) > c.verify_threshold * self._scale:
            current, ok, fit = self._verified(keyframe, image, current, ok, fit)
        match_count = int(ok.sum())
        if fit is None or fit.inliers.sum() < c.min_inlier_ratio * max(match_count, 1):
            return self._lose(image, stamp, match_count)
        fit = self._rolling_shutter(keyframe, current, ok, fit, stamp)
        keep = np.flatnonzero(ok)[fit.inliers]
        self._tracks.current = current[keep]
        self._tracks.in_keyframe = self._tracks.in_keyframe[keep]
        self._tracks.H_previous, self._tracks.H_last = self._tracks.H_last, fit.H
        H_keyframe = homography_work_to_full(fit.H, self._scale)
        H_ref = H_keyframe @ keyframe.H_ref
        inlier_count = int(fit.inliers.sum())
        if self._needs_keyframe(fit.H, inlier_count, image.shape):
            corners = self._detect(image)
            revisited = self._revisit(image, stamp, keyframe, H_ref, match_count, corners)
            if revisited is not None:
                return revisited
            return self._new_keyframe(image, stamp, keyframe, fit, match_count, corners)
        return TrackResult(
            state=TrackingState.TRACKING, frame_index=self._frame_index, stamp=stamp,
            H_ref=H_ref, H_keyframe=H_keyframe, keyframe_id=keyframe.id, reference_id=self._reference_id,
            inlier_count=inlier_count, match_count=match_count, rms_transfer_error=fit.rms / self._scale,
        )  # fmt: skip

    def _verified(
        self, keyframe: MapKeyframe, image: np.ndarray, current: Points, ok: NDArray[np.bool_], fit: RobustFit
    ) -> tuple[Points, NDArray[np.bool_], RobustFit | None]:
        """Check a fit the prediction did not foresee against descriptor matches (a global measurement).

        Under a fast move (or the first frames after a relocalisation, whose velocity is unknown) KLT
        starts far from the truth and, on repetitive texture (facades, tiles), locks many tracks onto the
        same wrong period: a consistent fit with high inlier ratio and low rms that is hundreds of pixels
        off (an image scale or shift of the wrong alias). When the descriptor homography contradicts the
        fit, the tracks are re-measured from it; when that does not confirm it either, the frame is lost
        (relocalisation then registers it). No descriptor homography: the fit stands (nothing against it).
        """
        H_desc = self._linker.descriptor_homography(keyframe, self._frame)
        # looser than a link: the descriptor fit is unrefined (3x the USAC threshold), while a wrong alias
        # is off by a whole texture period (a window, a brick row)
        tolerance = 4.0 * self.config.link_tolerance(self._scale)
        if H_desc is None or max_deviation(fit.H, H_desc, image.shape) <= tolerance:
            return current, ok, fit
        current2, ok2 = self._warped_klt(keyframe, image, H_desc)
        fit2 = self._fit_tracks(current2, ok2)
        if fit2 is not None and max_deviation(fit2.H, H_desc, image.shape) <= tolerance:
            _LOG.debug("frame %d: tracked fit contradicted by descriptors, re-tracked", self._frame_index)
            return current2, ok2, fit2
        _LOG.debug("frame %d: tracked fit contradicted by descriptors: lost", self._frame_index)
        return current, ok, None

    def _fit_tracks(self, current: Points, ok: NDArray[np.bool_]) -> RobustFit | None:
        """Keyframe -> frame homography (working pixels) from the tracks that survived KLT (global-shutter
        positions: the frame's with the previous frame's motion until _rolling_shutter refits)."""
        c = self.config
        if ok.sum() < c.min_inliers:
            return None
        usac = c.usac(self._scale)
        keyframe = self._keyframes[self._keyframe_id]
        src = self._frame.corrected(self._tracks.in_keyframe[ok], keyframe.motion)
        dst = self._frame.corrected(current[ok], self._last_motion)
        return robust_homography(src, dst, usac, c.min_inliers, c.refine_iterations)

    def _rolling_shutter(
        self,
        keyframe: MapKeyframe,
        current: Points,
        ok: NDArray[np.bool_],
        fit: RobustFit,
        stamp: float | None,
    ) -> RobustFit:
        """The frame's motion from its fit; with a readout the fit redone on the frame's points corrected
        with it; while estimating, this frame's readout estimate added (rolling_shutter.readout_step)."""
        tracks, frame, c = self._tracks, self._frame, self.config
        if (
            not self._readout.enabled
            or stamp is None
            or self._last_stamp is None
            or stamp <= self._last_stamp
        ):
            return fit
        # this frame -> keyframe -> the previous frame (tracked against the same keyframe)
        back = tracks.H_last @ np.linalg.inv(fit.H)
        last = self._last_motion
        previous = None if last is None else (last.interval_generator, last.dt)
        frame.motion = FrameMotion(back=rotation_motion(back, frame.image.shape), dt=stamp - self._last_stamp,
                                   previous=previous)  # fmt: skip
        if keyframe.motion is None and keyframe.id == frame.index - 1:
            # a keyframe made without a motion (the first, a relocalised one): the same interval's
            keyframe.motion = frame.motion
        src_raw, dst_raw = tracks.in_keyframe[ok], current[ok]
        if frame.readout != 0.0:
            src = frame.corrected(src_raw, keyframe.motion)
            dst = frame.corrected(dst_raw, frame.motion)
            threshold = c.usac(self._scale).threshold
            refit = refit_homography(
                fit.H, src, dst, fit.inliers, threshold, c.min_inliers, c.refine_iterations
            )
            fit = refit if refit is not None else fit
        zoom = local_scale(back, frame.image.shape)
        estimating = not self._readout.settled and keyframe.motion is not None
        if estimating and abs(zoom - 1.0) <= MAX_FRAME_ZOOM and frame.index - keyframe.id >= MIN_KEYFRAME_GAP:
            height = frame.image.shape[0]
            # linearised about no readout (the observed points), not about the one in use: an estimate
            # fed back through the correction (and its inliers) drifted off in one of two bags
            src_in, dst_in = src_raw[fit.inliers], dst_raw[fit.inliers]
            # the intervals' velocities: the stamps' (extrapolated) are noisier, attenuating the estimate
            d_src = displacement(src_in, keyframe.motion, height, frame.scale, at_stamp=False)
            d_dst = displacement(dst_in, frame.motion, height, frame.scale, at_stamp=False)
            estimate, sigma, _ = readout_step(fit.H, src_in, dst_in, d_src, d_dst, 0.0, iterations=3)
            self._readout.add(estimate, sigma, keyframe.id)
        return fit

    def _klt_tracks(
        self, keyframe: MapKeyframe, image: np.ndarray
    ) -> tuple[Points, NDArray[np.bool_], Array]:
        """Track positions in the current frame and the predicted keyframe -> frame H (working px):
        frame to frame, or straight from the keyframe seeded by a constant-velocity prediction."""
        tracks, source, gain = self._tracks, self.config.klt_source, self.config.gain_compensation
        H_pred = tracks.H_last @ np.linalg.inv(tracks.H_previous) @ tracks.H_last
        if source == "frame":
            previous = gain_matched(self._previous, image) if gain else self._previous
            return (*track_klt(previous, image, tracks.current, self._klt), H_pred)
        if source == "keyframe":
            guess = self._predicted_positions(H_pred)
            reference = gain_matched(keyframe.image, image) if gain else keyframe.image
            return (*track_klt(reference, image, tracks.in_keyframe, self._klt, initial=guess), H_pred)
        return (*self._warped_klt(keyframe, image, H_pred), H_pred)

    def _predicted_positions(self, H_pred: Array) -> Points:
        guess = apply_homography(H_pred, self._tracks.in_keyframe).astype(np.float32)
        bad = ~np.all(np.isfinite(guess), axis=1)
        guess[bad] = self._tracks.current[bad]
        return guess

    def _warped_klt(
        self, keyframe: MapKeyframe, image: np.ndarray, H_pred: Array, levels: int | None = None
    ) -> tuple[Points, NDArray[np.bool_]]:
        """Inverse-compositional flavour of KLT: the keyframe resampled into the predicted current
        geometry, so KLT only measures the small residual motion between images of equal scale."""
        h, w = image.shape
        guess = self._predicted_positions(H_pred)
        warped = cv2.warpPerspective(keyframe.image, H_pred, (w, h))
        if self.config.gain_compensation:
            warped = gain_matched_warp(warped, image)
        found, ok = track_klt(warped, image, guess, self._klt, initial=guess, levels=levels)
        margin = self.config.klt_window // 2 + 1
        kh, kw = keyframe.image.shape
        pts = self._tracks.in_keyframe
        ok &= np.all(pts >= margin, axis=1) & (pts[:, 0] <= kw - 1 - margin) & (pts[:, 1] <= kh - 1 - margin)
        return found, ok

    def _needs_keyframe(self, H_work: Array, inlier_count: int, shape: tuple[int, ...]) -> bool:
        c = self.config
        if inlier_count < c.keyframe_min_track_fraction * self._tracks.initial_count:
            return True
        return self._needs_keyframe_after(H_work, shape)

    # ------------------------------------------------------------------ keyframes
    def _start_map(self, image: np.ndarray, stamp: float | None) -> TrackResult:
        corners = self._detect(image)
        if len(corners) < self.config.textured_min_corners:
            return self._result(TrackingState.TEXTURELESS, stamp, 0)
        self._keyframes.clear()
        keyframe = self._add_keyframe(image, stamp, np.eye(3), 0, corners)
        self._reference_id = keyframe.id
        self._lost, self._lost_frames = False, 0
        return TrackResult(
            state=TrackingState.NEW_KEYFRAME, frame_index=self._frame_index, stamp=stamp, H_ref=np.eye(3),
            H_keyframe=np.eye(3), keyframe_id=keyframe.id, reference_id=keyframe.id,
            inlier_count=len(corners), match_count=len(corners), rms_transfer_error=0.0,
        )  # fmt: skip

    def _new_keyframe(
        self,
        image: np.ndarray,
        stamp: float | None,
        parent: MapKeyframe,
        fit: RobustFit,
        match_count: int,
        corners: Points | None = None,
    ) -> TrackResult:
        """Make the current frame a keyframe linked to its parent and to older overlapping keyframes."""
        corners = self._detect(image) if corners is None else corners
        if len(corners) < self.config.textured_min_corners:
            # Too little texture left to start new tracks: keep the old keyframe while tracks last.
            H_keyframe = homography_work_to_full(fit.H, self._scale)
            return TrackResult(
                state=TrackingState.TRACKING, frame_index=self._frame_index, stamp=stamp,
                H_ref=H_keyframe @ parent.H_ref, H_keyframe=H_keyframe, keyframe_id=parent.id,
                reference_id=self._reference_id, inlier_count=int(fit.inliers.sum()),
                match_count=match_count, rms_transfer_error=fit.rms / self._scale,
            )  # fmt: skip
        # The tracked fit is the parent link: its inliers were measured against the (warped) parent.
        tracks = self._tracks
        frame = self._frame
        src, dst = (
            frame.corrected(tracks.in_keyframe, parent.motion),
            frame.corrected(tracks.current, frame.motion),
        )
        parent_link = make_link(parent, fit, src, dst, self._scale)
        links = [MeasuredLink(parent, fit, parent_link)]
        H_ref_guess = homography_work_to_full(fit.H, self._scale) @ parent.H_ref
        for kf, H_chain in self._older_candidates(image, H_ref_guess, parent.id):
            # Descriptor re-matching only while no link as close to the reference exists (bounded cost).
            shortest = min(measured.keyframe.depth for measured in links)
            linked = self._linker.link(
                kf, self._frame, corners, H_chain, kf.depth < shortest, parent.depth + 1 + kf.depth
            )
            if linked is not None:
                links.append(linked)
        return self._commit_keyframe(image, stamp, corners, links, TrackingState.NEW_KEYFRAME, match_count)

    def _revisit(
        self,
        image: np.ndarray,
        stamp: float | None,
        current: MapKeyframe,
        H_ref: Array,
        match_count: int,
        corners: Points,
    ) -> TrackResult | None:
        """Go on tracking against a stored keyframe that covers at least revisit_min_overlap of the frame
        (predicted through the chain; the fewest hops to the reference, then the largest overlap),
        re-measured photometrically and checked against the chain like a link, instead of making a new
        keyframe; None: no such keyframe.

        A camera going back and forth over the same views would otherwise add keyframes on every pass,
        and the calibrator's bounded keyframe set would trade older, better-linked keyframes of a view for
        newer ones: its frames' calibration then drifts pass after pass (issue 7)."""
        c = self.config
        if not c.revisit_keyframes:
            return None
        S = work_from_full(self._scale)
        best: tuple[tuple[int, float], MapKeyframe, Array] | None = None
        for kf in self._keyframes.values():
            if kf.id == current.id:
                continue
            H_work = S @ H_ref @ np.linalg.inv(kf.H_ref) @ np.linalg.inv(S)  # keyframe -> frame
            scale = local_scale(H_work, image.shape)
            if max(scale, 1.0 / scale) > math.sqrt(c.keyframe_max_scale_change):
                continue
            overlap = overlap_fraction(np.linalg.inv(H_work), image.shape)
            rank = (kf.depth, -overlap)  # fewest hops to the reference first, as links
            if overlap >= c.revisit_min_overlap and (best is None or rank < best[0]):
                best = (rank, kf, H_work)
        if best is None:
            return None
        _, kf, H_chain = best
        linked = self._linker.link(
            kf, self._frame, corners, H_chain, rematch=False, hops=current.depth + 1 + kf.depth
        )
        if linked is None:
            return None
        fit = linked.fit
        # the keyframe's own corners seen in the frame become the tracks (as after a new keyframe)
        h, w = image.shape
        margin = c.klt_window // 2 + 1
        seen = apply_homography(fit.H, kf.corners)
        inside = np.all(np.isfinite(seen), axis=1) & np.all(seen >= margin, axis=1)
        inside &= (seen[:, 0] <= w - 1 - margin) & (seen[:, 1] <= h - 1 - margin)
        inlier_count = int(fit.inliers.sum())
        if inside.sum() < c.min_inliers or self._needs_keyframe_after(fit.H, image.shape):
            return None
        velocity = self._tracks.H_last @ np.linalg.inv(self._tracks.H_previous)
        self._tracks = _Tracks(
            current=seen[inside].astype(np.float32), in_keyframe=kf.corners[inside].copy(),
            initial_count=int(inside.sum()), H_last=fit.H, H_previous=np.linalg.inv(velocity) @ fit.H,
        )  # fmt: skip
        self._keyframe_id = kf.id
        self._keyframes.move_to_end(kf.id)  # in use: the last the store prunes
        H_keyframe = homography_work_to_full(fit.H, self._scale)
        return TrackResult(
            state=TrackingState.TRACKING, frame_index=self._frame_index, stamp=stamp,
            H_ref=H_keyframe @ kf.H_ref, H_keyframe=H_keyframe, keyframe_id=kf.id,
            reference_id=self._reference_id, inlier_count=inlier_count, match_count=match_count,
            rms_transfer_error=fit.rms / self._scale,
        )  # fmt: skip

    def _needs_keyframe_after(self, H_work: Array, shape: tuple[int, ...]) -> bool:
        """The scale and overlap tests of _needs_keyframe (alone: a freshly measured keyframe -> frame H,
        all tracks new)."""
        c = self.config
        scale_change = local_scale(H_work, shape)
        if max(scale_change, 1.0 / scale_change) > c.keyframe_max_scale_change:
            return True
        return overlap_fraction(np.linalg.inv(H_work), shape) < c.keyframe_min_overlap

    def _older_candidates(
        self, image: np.ndarray, H_ref_guess: Array, exclude: int
    ) -> list[tuple[MapKeyframe, Array]]:
        """Older keyframes overlapping the new frame, fewest hops to the reference first, each with the
        keyframe -> frame homography predicted through the chain (working pixels)."""
        c = self.config
        S = work_from_full(self._scale)
        scored = []
        for kf in self._keyframes.values():
            if kf.id == exclude:
                continue
            H_work = S @ H_ref_guess @ np.linalg.inv(kf.H_ref) @ np.linalg.inv(S)
            overlap = overlap_fraction(np.linalg.inv(H_work), image.shape)
            if overlap >= c.link_min_overlap:
                scored.append((kf.depth, -overlap, kf.id, kf, H_work))
        scored.sort(key=lambda item: item[:3])
        return [(kf, H_work) for *_, kf, H_work in scored[: c.link_candidates]]

    def _commit_keyframe(
        self,
        image: np.ndarray,
        stamp: float | None,
        corners: Points,
        links: list[MeasuredLink],
        state: TrackingState,
        match_count: int,
    ) -> TrackResult:
        """Store the frame as a keyframe, chained through the link with the fewest hops to the reference."""
        chosen = min(links, key=lambda measured: (measured.keyframe.depth, -measured.link.inlier_count))
        source, best = chosen.keyframe, chosen.link
        H_ref = best.H @ source.H_ref
        # the frame's descriptors, if relocalisation or re-matching computed them, are the keyframe's
        keyframe = self._add_keyframe(image, stamp, H_ref, source.depth + 1, corners, self._frame.descriptors)
        self._lost, self._lost_frames = False, 0
        return TrackResult(
            state=state, frame_index=self._frame_index, stamp=stamp, H_ref=H_ref, H_keyframe=np.eye(3),
            keyframe_id=keyframe.id, reference_id=self._reference_id, inlier_count=best.inlier_count,
            match_count=match_count, rms_transfer_error=best.rms_transfer_error,
            links=tuple(replace(measured.link, target_id=keyframe.id) for measured in links),
        )  # fmt: skip

    def _add_keyframe(
        self,
        image: np.ndarray,
        stamp: float | None,
        H_ref: Array,
        depth: int,
        corners: Points,
        descriptors: Descriptors | None = None,
    ) -> MapKeyframe:
        keyframe = MapKeyframe(
            self._frame_index, stamp, image, H_ref, depth, corners, descriptors, motion=self._frame.motion
        )
        self._keyframes[keyframe.id] = keyframe
        self._keyframe_id = keyframe.id
        # Keep the frame-to-frame motion for the constant-velocity prediction: the tracked one, or after a
        # relocalisation the motion from the previous frame when that one had a homography (a fast move
        # lost only for the frame relocalised goes on fast), else identity.
        if not self._lost:
            velocity = self._tracks.H_last @ np.linalg.inv(self._tracks.H_previous)
        elif self._last_H_ref is not None:
            S = work_from_full(self._scale)
            velocity = S @ H_ref @ np.linalg.inv(self._last_H_ref) @ np.linalg.inv(S)
        else:
            velocity = np.eye(3)
        self._tracks = _Tracks(current=corners.copy(), in_keyframe=corners.copy(), initial_count=len(corners),
                               H_previous=np.linalg.inv(velocity))  # fmt: skip
        self._prune()
        return keyframe

    def _prune(self) -> None:
        """Bounded memory: drop the least recently used keyframes beyond the cap (the store's order: made
        or revisited last at the end), never the reference or the current one."""
        while len(self._keyframes) > self.config.max_keyframes:
            victim = next(k for k in self._keyframes if k not in (self._reference_id, self._keyframe_id))
            del self._keyframes[victim]

    # ------------------------------------------------------------------ loss and relocalisation
    def _lose(self, image: np.ndarray, stamp: float | None, match_count: int) -> TrackResult:
        self._lost = True
        return self._relocalise(image, stamp, match_count=match_count)

    def _relocalise(self, image: np.ndarray, stamp: float | None, match_count: int = 0) -> TrackResult:
        c = self.config
        corners = self._detect(image)
        if len(corners) < c.textured_min_corners:
            return self._result(TrackingState.TEXTURELESS, stamp, match_count)
        self._lost_frames += 1
        frame, linker = self._frame, self._linker
        for kf in self._relocalisation_order():
            H_desc = linker.descriptor_homography(kf, frame)
            refined = None if H_desc is None else linker.photometric_link(kf, frame, corners, H_desc)
            if refined is not None:
                fit, src, dst = refined
                links = [MeasuredLink(kf, fit, make_link(kf, fit, src, dst, self._scale))]
                # Also link older overlapping keyframes (fewer hops to the reference, loop closure).
                H_ref_guess = links[0].link.H @ kf.H_ref
                for other, H_chain in self._older_candidates(image, H_ref_guess, kf.id):
                    hops = kf.depth + 1 + other.depth
                    linked = linker.link(other, frame, corners, H_chain, other.depth < kf.depth, hops)
                    if linked is not None:
                        links.append(linked)
                return self._commit_keyframe(
                    image, stamp, corners, links, TrackingState.RELOCALISED, len(fit.inliers)
                )
        if self._lost_frames > c.new_map_after_lost:
            _LOG.info("relocalisation failed for %d frames: starting a new map", self._lost_frames)
            self._reference_id = None
            return self._start_map(image, stamp)
        return self._result(TrackingState.TRACKING_LOST, stamp, match_count)

    def _relocalisation_order(self) -> list[MapKeyframe]:
        """The last tracked keyframe, then the others most recently used first in a window that moves on
        every lost frame: relocalise_candidates per frame bound the cost, and all keyframes get tried in
        turn."""
        last = [self._keyframes[self._keyframe_id]] if self._keyframe_id in self._keyframes else []
        others = [kf for k, kf in reversed(self._keyframes.items()) if k != self._keyframe_id]
        count = max(self.config.relocalise_candidates - len(last), 0)
        if not others or count == 0:
            return last
        start = (self._lost_frames - 1) * count % len(others)
        window = (others[start:] + others[:start])[: min(count, len(others))]
        return last + window

    # ------------------------------------------------------------------ helpers
    def _detect(self, image: np.ndarray) -> Points:
        c = self.config
        return detect_corners(image, c.max_features, c.grid, c.quality_level, c.min_distance,
                              c.min_corner_eigenvalue)  # fmt: skip

    def _result(self, state: TrackingState, stamp: float | None, match_count: int) -> TrackResult:
        return TrackResult(
            state=state, frame_index=self._frame_index, stamp=stamp, H_ref=None, H_keyframe=None,
            keyframe_id=self._keyframe_id, reference_id=self._reference_id, inlier_count=0,
            match_count=match_count, rms_transfer_error=float("nan"),
        )  # fmt: skip
