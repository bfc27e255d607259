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

Persistence: export_map() gives the keyframe map as plain data (ids, reference, homographies, working
images and corners, least recently used first; descriptors are recomputed from the images),
map_to_bytes()/map_from_bytes() turn it into one .npz blob and back (no pickle) and restore_map() loads
it: the tracker then starts lost and its first frame relocalises against the stored keyframes (the last
tracked one first), so a restarted tracker keeps the same reference and keyframe ids (new ids continue
after the stored ones). A revisit changes the map (the keyframe tracked, the pruning order) on a
TRACKING frame: a caller saving the map saves it when a result's keyframe_id changes, not only on
NEW_KEYFRAME / RELOCALISED.
"""

from __future__ import annotations

import io
import json
import logging
import math
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import apply_homography, homography_work_to_full, work_from_full
from ptz_selfcal.frontend.features import (
    Descriptors,
    KltParams,
    RobustFit,
    compute_descriptors,
    descriptor_extractor,
    detect_corners,
    match_descriptors,
    robust_homography,
    track_klt,
    usac_params,
)
from ptz_selfcal.status import TrackingState

Array = NDArray[np.float64]
Points = NDArray[np.float32]

_LOG = logging.getLogger(__name__)

MAP_FORMAT = "ptz_selfcal.tracker_map"
MAP_VERSION = 2


# The string fields of TrackerConfig and the values each accepts.
TRACKER_CHOICES: dict[str, tuple[str, ...]] = {
    "klt_source": ("warped", "keyframe", "frame"),
    "descriptor": ("orb", "sift"),
}


@dataclass(frozen=True)
class TrackerConfig:
    working_scale: float = 0.5  # working / full resolution the node should downscale to
    max_features: int = 300
    grid: tuple[int, int] = (8, 5)  # (cols, rows) cells that spread the corners over the image
    quality_level: float = 0.01
    min_distance: float = 8.0  # working pixels between corners
    min_corner_eigenvalue: float = 2e-4  # absolute texture floor (OpenCV normalised eigenvalue)
    klt_window: int = 15
    klt_levels: int = 3
    klt_iterations: int = 10
    klt_epsilon: float = 0.01  # KLT stops when the update is below this (working pixels)
    klt_fb_threshold: float = 0.5  # working pixels
    # KLT source: "warped" = keyframe warped by the predicted homography (no drift, no zoom bias),
    # "keyframe" = keyframe image seeded by the prediction, "frame" = previous frame (classic KLT).
    klt_source: str = "warped"
    ransac_threshold: float = 1.0  # full-resolution pixels
    ransac_max_iterations: int = 1000
    ransac_confidence: float = 0.999
    refine_iterations: int = 10
    min_inliers: int = 20
    min_inlier_ratio: float = 0.25
    textured_min_corners: int = 30  # fewer detectable corners than this -> TEXTURELESS
    keyframe_min_overlap: float = 0.7  # fraction of the frame still covered by the keyframe
    keyframe_max_scale_change: float = 1.2
    keyframe_min_track_fraction: float = 0.5
    link_min_overlap: float = 0.5  # older keyframes overlapping this much are link candidates
    link_max_deviation: float = 8.0  # full-res px a link may differ from the tracked chain
    link_candidates: int = 2  # older keyframes re-matched per new keyframe (besides the previous one)
    link_with_descriptors: bool = False  # always start links from ORB matches (else only as fallback)
    # A camera back at a view it has seen: repeated passes leave the map and the calibration alone.
    revisit_keyframes: bool = True  # a frame needing a new keyframe tracks a stored one covering it instead
    revisit_min_overlap: float = 0.85  # fraction of the frame a stored keyframe must cover to be revisited
    max_keyframes: int = 64  # keyframe store cap (least recently used pruned; the reference is kept)
    descriptor: str = "orb"  # re-matching/relocalisation descriptor: "orb" or "sift"
    descriptor_features: int = 500
    descriptor_ratio: float = 0.8
    relocalise_candidates: int = 3  # keyframes tried per lost frame (others on the next frames)
    new_map_after_lost: int = 30  # frames lost (with texture) before a new map is started
    repeat_threshold: float = 5.0  # re-warp and re-track when the prediction was off by more (full px)
    verify_threshold: float = 16.0  # fits further than this from the prediction are checked by descriptors
    gain_compensation: bool = True  # match mean brightness before KLT (+-20% exposure changes)
    seed: int = 0

    def __post_init__(self) -> None:
        for name, allowed in TRACKER_CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, not {getattr(self, name)!r}")


@dataclass(frozen=True)
class KeyframeLink:
    """Keyframe -> keyframe homography and its inlier correspondences, full-resolution pixels."""

    source_id: int
    target_id: int
    H: Array  # maps source keyframe pixels to target keyframe pixels
    source_points: Array  # (N, 2)
    target_points: Array  # (N, 2)
    rms_transfer_error: float

    @property
    def inlier_count(self) -> int:
        return len(self.source_points)


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


@dataclass
class Keyframe:
    id: int  # frame index of the keyframe
    stamp: float | None
    image: np.ndarray  # working resolution, mono8
    H_ref: Array  # reference -> keyframe, full resolution
    depth: int  # keyframe links between the reference and this keyframe
    corners: Points  # corners detected in the keyframe (working pixels)
    descriptors: Descriptors | None  # computed on first use


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
        c = self.config
        self._klt = KltParams(window=c.klt_window, levels=c.klt_levels, iterations=c.klt_iterations,
                              epsilon=c.klt_epsilon, fb_threshold=c.klt_fb_threshold)  # fmt: skip
        self._extractor = descriptor_extractor(c.descriptor, c.descriptor_features)
        self.reset()

    # ------------------------------------------------------------------ public API
    def reset(self) -> None:
        """Forget every keyframe and track: the next frame starts a new map (frame ids restart at 0)."""
        self._keyframes: OrderedDict[int, Keyframe] = OrderedDict()
        self._reference_id: int | None = None
        self._keyframe_id: int | None = None
        self._tracks = _Tracks()
        self._previous: np.ndarray | None = None
        self._scale: float | None = None
        self._frame_index = -1
        self._lost_frames = 0
        self._lost = False
        self._frame_orb: tuple[int, Descriptors] | None = None
        self._last_H_ref: Array | None = None  # reference -> previous frame (full res; None: no H)

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

    def export_map(self) -> dict[str, Any] | None:
        """The keyframe map as plain data for restore_map (None while there is no map).

        Cheap (no copies: a keyframe's arrays are never modified once stored), so it can be taken on the
        frame path and serialised (map_to_bytes) elsewhere."""
        if self._reference_id is None or self._scale is None or self._keyframe_id not in self._keyframes:
            return None
        return {
            "reference_id": self._reference_id,
            "keyframe_id": self._keyframe_id,
            "frame_index": self._frame_index,
            "scale": self._scale,
            "keyframes": [
                {
                    "id": kf.id,
                    "stamp": kf.stamp,
                    "H_ref": kf.H_ref,
                    "depth": kf.depth,
                    "image": kf.image,
                    "corners": kf.corners,
                }
                for kf in self._keyframes.values()
            ],
        }

    def restore_map(self, data: dict[str, Any]) -> None:
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
                keyframes[kid] = Keyframe(kid, stamp, image, H_ref, int(item["depth"]), corners, None)
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
        if self._reference_id is None:
            result = self._start_map(image, stamp)
        elif self._lost:
            result = self._relocalise(image, stamp)
        else:
            result = self._track_frame(image, stamp)
        self._previous = image
        self._last_H_ref = result.H_ref
        return result

    # ------------------------------------------------------------------ per-frame tracking
    def _track_frame(self, image: np.ndarray, stamp: float | None) -> TrackResult:
        c = self.config
        keyframe = self._keyframes[self._keyframe_id]
        current, ok, H_pred = self._klt_tracks(keyframe, image)
        fit = self._fit_tracks(current, ok)
        # Second warp + KLT pass when the prediction was poor: the residual then has (almost) no
        # scale/rotation left for translational KLT to be biased by (Gauss-Newton on the warp).
        repeat = fit is not None and c.klt_source == "warped" and c.repeat_threshold > 0.0
        if repeat and _deviation(fit.H, H_pred, image.shape) > c.repeat_threshold * self._scale:
            current2, ok2 = self._warped_klt(keyframe, image, fit.H, levels=1)
            fit2 = self._fit_tracks(current2, ok2)
            if fit2 is not None and fit2.inliers.sum() >= 0.8 * fit.inliers.sum():
                current, ok, fit = current2, ok2, fit2
        verify = fit is not None and c.klt_source == "warped" and c.verify_threshold > 0.0
        if verify and _deviation(fit.H, H_pred, image.shape) > c.verify_threshold * self._scale:
            current, ok, fit = self._verified(keyframe, image, current, ok, fit)
        match_count = int(ok.sum())
        if fit is None or fit.inliers.sum() < c.min_inlier_ratio * max(match_count, 1):
            return self._lose(image, stamp, match_count)
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
        self, keyframe: Keyframe, image: np.ndarray, current: Points, ok: NDArray[np.bool_], fit: RobustFit
    ) -> tuple[Points, NDArray[np.bool_], RobustFit | None]:
        """Check a fit the prediction did not foresee against descriptor matches (a global measurement).

        Under a fast move (or the first frames after a relocalisation, whose velocity is unknown) KLT
        starts far from the truth and, on repetitive texture (facades, tiles), locks many tracks onto the
        same wrong period: a consistent fit with high inlier ratio and low rms that is hundreds of pixels
        off (an image scale or shift of the wrong alias). When the descriptor homography contradicts the
        fit, the tracks are re-measured from it; when that does not confirm it either, the frame is lost
        (relocalisation then registers it). No descriptor homography: the fit stands (nothing against it).
        """
        H_desc = self._descriptor_homography(keyframe, image)
        # the descriptor fit is not refined (ORB, 3 px USAC): ~10 px off at the image corners is normal,
        # a wrong alias is a texture period (a window, a brick row: tens to hundreds of pixels)
        tolerance = 4.0 * self._link_tolerance()
        if H_desc is None or _deviation(fit.H, H_desc, image.shape) <= tolerance:
            return current, ok, fit
        current2, ok2 = self._warped_klt(keyframe, image, H_desc)
        fit2 = self._fit_tracks(current2, ok2)
        if fit2 is not None and _deviation(fit2.H, H_desc, image.shape) <= tolerance:
            _LOG.debug("frame %d: tracked fit contradicted by descriptors, re-tracked", self._frame_index)
            return current2, ok2, fit2
        _LOG.debug("frame %d: tracked fit contradicted by descriptors: lost", self._frame_index)
        return current, ok, None

    def _fit_tracks(self, current: Points, ok: NDArray[np.bool_]) -> RobustFit | None:
        """Keyframe -> frame homography (working pixels) from the tracks that survived KLT."""
        c = self.config
        if ok.sum() < c.min_inliers:
            return None
        return robust_homography(self._tracks.in_keyframe[ok], current[ok], self._usac(), c.min_inliers,
                                 c.refine_iterations)  # fmt: skip

    def _klt_tracks(self, keyframe: Keyframe, image: np.ndarray) -> tuple[Points, NDArray[np.bool_], Array]:
        """Track positions in the current frame and the predicted keyframe -> frame H (working px):
        frame to frame, or straight from the keyframe seeded by a constant-velocity prediction."""
        tracks, source = self._tracks, self.config.klt_source
        H_pred = tracks.H_last @ np.linalg.inv(tracks.H_previous) @ tracks.H_last
        if source == "frame":
            previous = self._gain_matched(self._previous, image)
            return (*track_klt(previous, image, tracks.current, self._klt), H_pred)
        if source == "keyframe":
            guess = self._predicted_positions(H_pred)
            reference = self._gain_matched(keyframe.image, image)
            return (*track_klt(reference, image, tracks.in_keyframe, self._klt, initial=guess), H_pred)
        return (*self._warped_klt(keyframe, image, H_pred), H_pred)

    def _predicted_positions(self, H_pred: Array) -> Points:
        guess = apply_homography(H_pred, self._tracks.in_keyframe).astype(np.float32)
        bad = ~np.all(np.isfinite(guess), axis=1)
        guess[bad] = self._tracks.current[bad]
        return guess

    def _warped_klt(
        self, keyframe: Keyframe, image: np.ndarray, H_pred: Array, levels: int | None = None
    ) -> tuple[Points, NDArray[np.bool_]]:
        """Inverse-compositional flavour of KLT: the keyframe resampled into the predicted current
        geometry, so KLT only measures the small residual motion between images of equal scale."""
        h, w = image.shape
        guess = self._predicted_positions(H_pred)
        warped = self._gain_matched_warp(cv2.warpPerspective(keyframe.image, H_pred, (w, h)), image)
        found, ok = track_klt(warped, image, guess, self._klt, initial=guess, levels=levels)
        margin = self.config.klt_window // 2 + 1
        kh, kw = keyframe.image.shape
        pts = self._tracks.in_keyframe
        ok &= np.all(pts >= margin, axis=1) & (pts[:, 0] <= kw - 1 - margin) & (pts[:, 1] <= kh - 1 - margin)
        return found, ok

    def _gain_matched(self, previous: np.ndarray, image: np.ndarray) -> np.ndarray:
        """Previous frame rescaled to the current mean brightness (KLT assumes constant brightness)."""
        if not self.config.gain_compensation:
            return previous
        mean_prev = float(cv2.mean(previous)[0])
        mean_cur = float(cv2.mean(image)[0])
        if mean_prev < 1.0 or abs(mean_cur / mean_prev - 1.0) < 0.02:
            return previous
        return cv2.convertScaleAbs(previous, alpha=mean_cur / mean_prev)

    def _gain_matched_warp(self, warped: np.ndarray, image: np.ndarray) -> np.ndarray:
        """As _gain_matched, with the means taken where the warped keyframe has data (not the border)."""
        if not self.config.gain_compensation:
            return warped
        sub_warp, sub_image = warped[::4, ::4], image[::4, ::4]  # a 1/16 sample is plenty for a gain
        valid = sub_warp > 0
        mean_warp = float(sub_warp[valid].mean()) if valid.any() else 0.0
        mean_cur = float(sub_image[valid].mean()) if valid.any() else 0.0
        if mean_warp < 1.0 or abs(mean_cur / mean_warp - 1.0) < 0.02:
            return warped
        return cv2.convertScaleAbs(warped, alpha=mean_cur / mean_warp)

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
        parent: Keyframe,
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
        links = [(parent, fit, self._make_link(parent, fit, tracks.in_keyframe, tracks.current))]
        H_ref_guess = homography_work_to_full(fit.H, self._scale) @ parent.H_ref
        for kf, H_chain in self._older_candidates(image, H_ref_guess, parent.id):
            # Descriptor re-matching only while no link as close to the reference exists (bounded cost).
            shortest = min(link_kf.depth for link_kf, _, _ in links)
            linked = self._link(kf, image, corners, H_chain, kf.depth < shortest, parent.depth + 1 + kf.depth)
            if linked is not None:
                links.append(linked)
        return self._commit_keyframe(image, stamp, corners, links, TrackingState.NEW_KEYFRAME, match_count)

    def _revisit(
        self,
        image: np.ndarray,
        stamp: float | None,
        current: Keyframe,
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
        best: tuple[tuple[int, float], Keyframe, Array] | None = None
        for kf in self._keyframes.values():
            if kf.id == current.id:
                continue
            H_work = S @ H_ref @ np.linalg.inv(kf.H_ref) @ np.linalg.inv(S)  # keyframe -> frame
            scale = _local_scale(H_work, image.shape)
            if max(scale, 1.0 / scale) > math.sqrt(c.keyframe_max_scale_change):
                continue
            overlap = _overlap(np.linalg.inv(H_work), image.shape)
            rank = (kf.depth, -overlap)  # fewest hops to the reference first, as links
            if overlap >= c.revisit_min_overlap and (best is None or rank < best[0]):
                best = (rank, kf, H_work)
        if best is None:
            return None
        _, kf, H_chain = best
        linked = self._link(kf, image, corners, H_chain, rematch=False, hops=current.depth + 1 + kf.depth)
        if linked is None:
            return None
        fit = linked[1]
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
        scale_change = _local_scale(H_work, shape)
        if max(scale_change, 1.0 / scale_change) > c.keyframe_max_scale_change:
            return True
        return _overlap(np.linalg.inv(H_work), shape) < c.keyframe_min_overlap

    def _older_candidates(
        self, image: np.ndarray, H_ref_guess: Array, exclude: int
    ) -> list[tuple[Keyframe, Array]]:
        """Older keyframes overlapping the new frame, fewest hops to the reference first, each with the
        keyframe -> frame homography predicted through the chain (working pixels)."""
        c = self.config
        S = work_from_full(self._scale)
        scored = []
        for kf in self._keyframes.values():
            if kf.id == exclude:
                continue
            H_work = S @ H_ref_guess @ np.linalg.inv(kf.H_ref) @ np.linalg.inv(S)
            overlap = _overlap(np.linalg.inv(H_work), image.shape)
            if overlap >= c.link_min_overlap:
                scored.append((kf.depth, -overlap, kf.id, kf, H_work))
        scored.sort(key=lambda item: item[:3])
        return [(kf, H_work) for *_, kf, H_work in scored[: c.link_candidates]]

    def _link(
        self,
        kf: Keyframe,
        image: np.ndarray,
        corners: Points,
        H_chain: Array,
        rematch: bool = True,
        hops: int = 1,
    ) -> tuple[Keyframe, RobustFit, KeyframeLink] | None:
        """Re-measure keyframe -> frame independently of the chain: photometrically from the chain's
        prediction, else (rematch) from descriptor matches; reject a link that contradicts the chain.

        The chain between the keyframe and the frame is up to `hops` links long and drifts (each link is
        measured on the overlap only, mostly small at high zoom, and extrapolated to the whole image):
        a link further than link_max_deviation from it is kept up to link_max_deviation sqrt(hops) when
        the descriptor homography, a global measurement independent of both, confirms it (loop closure
        after a long excursion; a wrong alias on repetitive texture is not confirmed)."""
        c = self.config
        tolerance = self._link_tolerance()
        loose = tolerance * math.sqrt(max(hops, 1))
        starts = [] if c.link_with_descriptors else [H_chain]
        H_desc = self._descriptor_homography(kf, image) if c.link_with_descriptors else None
        starts += [H_desc] if H_desc is not None else []
        for attempt in range(2):
            for H0 in starts:
                if _deviation(H0, H_chain, image.shape) > loose:
                    continue
                refined = self._photometric_link(kf, image, corners, H0)
                if refined is None:
                    continue
                fit, src, dst = refined
                off = _deviation(fit.H, H_chain, image.shape)
                if off > tolerance and not (off <= loose and self._confirmed(kf, image, fit.H)):
                    _LOG.debug("link %d -> frame %d contradicts the chain: dropped", kf.id, self._frame_index)
                    continue
                return kf, fit, self._make_link(kf, fit, src, dst)
            if attempt == 0 and rematch and not c.link_with_descriptors:
                H_desc = self._descriptor_homography(kf, image)  # photometric start failed: re-match
                starts = [H_desc] if H_desc is not None else []
        return None

    def _confirmed(self, kf: Keyframe, image: np.ndarray, H: Array) -> bool:
        """Whether the descriptor homography keyframe -> frame agrees with H (working pixels)."""
        H_desc = self._descriptor_homography(kf, image)
        return H_desc is not None and _deviation(H, H_desc, image.shape) <= self._link_tolerance()

    def _descriptor_homography(self, kf: Keyframe, image: np.ndarray) -> Array | None:
        """Keyframe -> frame homography (working pixels) from ORB matches, or None."""
        c = self.config
        src, dst = match_descriptors(
            self._descriptors_of(kf), self._frame_descriptors(image), c.descriptor_ratio
        )
        fit = robust_homography(src, dst, self._usac(3.0), c.min_inliers, c.refine_iterations)
        if fit is None or not _plausible(fit.H, image.shape):
            return None
        return fit.H

    def _descriptors_of(self, kf: Keyframe) -> Descriptors:
        """Descriptors of a keyframe, computed once on first use (relocalisation, re-matching)."""
        if kf.descriptors is None:
            kf.descriptors = compute_descriptors(self._extractor, kf.image)
        return kf.descriptors

    def _frame_descriptors(self, image: np.ndarray) -> Descriptors:
        """Descriptors of the current frame (cached for the frame being processed)."""
        if self._frame_orb is None or self._frame_orb[0] != self._frame_index:
            self._frame_orb = (self._frame_index, compute_descriptors(self._extractor, image))
        return self._frame_orb[1]

    def _commit_keyframe(
        self,
        image: np.ndarray,
        stamp: float | None,
        corners: Points,
        links: list[tuple[Keyframe, RobustFit, KeyframeLink]],
        state: TrackingState,
        match_count: int,
    ) -> TrackResult:
        """Store the frame as a keyframe, chained through the link with the fewest hops to the reference."""
        source, _, best = min(links, key=lambda item: (item[0].depth, -item[2].inlier_count))
        H_ref = best.H @ source.H_ref
        descriptors = (
            self._frame_orb[1] if self._frame_orb and self._frame_orb[0] == self._frame_index else None
        )
        keyframe = self._add_keyframe(image, stamp, H_ref, source.depth + 1, corners, descriptors)
        self._lost, self._lost_frames = False, 0
        return TrackResult(
            state=state, frame_index=self._frame_index, stamp=stamp, H_ref=H_ref, H_keyframe=np.eye(3),
            keyframe_id=keyframe.id, reference_id=self._reference_id, inlier_count=best.inlier_count,
            match_count=match_count, rms_transfer_error=best.rms_transfer_error,
            links=tuple(replace(link, target_id=keyframe.id) for _, _, link in links),
        )  # fmt: skip

    def _photometric_link(
        self, kf: Keyframe, image: np.ndarray, corners: Points, H0: Array
    ) -> tuple[RobustFit, Array, Array] | None:
        """Refine keyframe -> frame H (working pixels): warp the keyframe by the guess H0, KLT the frame's
        corners into the warped keyframe (small residual motion, no scale change) and map them back."""
        c = self.config
        h, w = image.shape
        in_kf = apply_homography(np.linalg.inv(H0), corners)
        margin = c.klt_window
        kh, kw = kf.image.shape
        visible = (
            np.all(in_kf >= margin, axis=1)
            & (in_kf[:, 0] <= kw - 1 - margin)
            & (in_kf[:, 1] <= kh - 1 - margin)
        )
        warped = self._gain_matched_warp(cv2.warpPerspective(kf.image, H0, (w, h)), image)
        pts = corners[visible]
        if len(pts) < c.max_features // 3:
            # Small overlap: detect corners inside it, so the link does not hang on a handful.
            ones = np.full(kf.image.shape, 255, np.uint8)
            overlap = cv2.erode(
                cv2.warpPerspective(ones, H0, (w, h)), np.ones((2 * margin + 1,) * 2, np.uint8)
            )
            found = detect_corners(image, c.max_features, c.grid, c.quality_level, c.min_distance,
                                   c.min_corner_eigenvalue, mask=overlap)  # fmt: skip
            pts = found if len(found) > len(pts) else pts
        if len(pts) < c.min_inliers:
            return None
        found, ok = track_klt(image, warped, pts, self._klt, initial=pts, levels=2)
        if ok.sum() < c.min_inliers:
            return None
        src = apply_homography(np.linalg.inv(H0), found[ok])
        dst = pts[ok].astype(np.float64)
        fit = robust_homography(src, dst, self._usac(), c.min_inliers, c.refine_iterations)
        return None if fit is None else (fit, src[fit.inliers], dst[fit.inliers])

    def _make_link(self, kf: Keyframe, fit: RobustFit, src: np.ndarray, dst: np.ndarray) -> KeyframeLink:
        """Link keyframe -> (not yet stored) frame in full resolution; target id filled in later."""
        s = self._scale
        if len(src) != int(fit.inliers.sum()):  # all correspondences given: keep the inliers
            src, dst = src[fit.inliers], dst[fit.inliers]
        src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
        return KeyframeLink(
            source_id=kf.id, target_id=-1, H=homography_work_to_full(fit.H, s),
            source_points=(src + 0.5) / s - 0.5, target_points=(dst + 0.5) / s - 0.5,
            rms_transfer_error=fit.rms / s,
        )  # fmt: skip

    def _add_keyframe(
        self,
        image: np.ndarray,
        stamp: float | None,
        H_ref: Array,
        depth: int,
        corners: Points,
        descriptors: Descriptors | None = None,
    ) -> Keyframe:
        keyframe = Keyframe(self._frame_index, stamp, image, H_ref, depth, corners, descriptors)
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
        for kf in self._relocalisation_order():
            H_desc = self._descriptor_homography(kf, image)
            refined = None if H_desc is None else self._photometric_link(kf, image, corners, H_desc)
            if refined is not None:
                fit, src, dst = refined
                links = [(kf, fit, self._make_link(kf, fit, src, dst))]
                # Also link older overlapping keyframes (fewer hops to the reference, loop closure).
                H_ref_guess = links[0][2].H @ kf.H_ref
                for other, H_chain in self._older_candidates(image, H_ref_guess, kf.id):
                    linked = self._link(
                        other, image, corners, H_chain, other.depth < kf.depth, kf.depth + 1 + other.depth
                    )
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

    def _relocalisation_order(self) -> list[Keyframe]:
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

    def _usac(self, factor: float = 1.0) -> cv2.UsacParams:
        c = self.config
        threshold = factor * c.ransac_threshold * self._scale
        return usac_params(threshold, c.seed, c.ransac_max_iterations, c.ransac_confidence)

    def _link_tolerance(self) -> float:
        """Largest disagreement (working pixels) between a re-matched link and the tracked chain."""
        return self.config.link_max_deviation * self._scale

    def _result(self, state: TrackingState, stamp: float | None, match_count: int) -> TrackResult:
        return TrackResult(
            state=state, frame_index=self._frame_index, stamp=stamp, H_ref=None, H_keyframe=None,
            keyframe_id=self._keyframe_id, reference_id=self._reference_id, inlier_count=0,
            match_count=match_count, rms_transfer_error=float("nan"),
        )  # fmt: skip


def map_to_bytes(
    data: dict[str, Any],
    extra: dict[str, Any] | None = None,
    cache: dict[tuple[int, int, tuple[int, ...]], bytes] | None = None,
) -> bytes:
    """An exported map (HomographyTracker.export_map) as one .npz blob: the metadata (and the caller's
    JSON-serialisable `extra`) as JSON, the keyframe images as lossless PNG, the other arrays stacked.
    Loadable without pickle. `cache` (kept by the caller between saves) holds the PNG of each keyframe
    image (keyed by id and checksum): a keyframe is encoded once, not at every save; it is left holding
    only the keyframes of this map (bounded)."""
    keyframes = data["keyframes"]
    meta = {key: data[key] for key in ("reference_id", "keyframe_id", "frame_index", "scale")}
    encoded: dict[tuple[int, int, tuple[int, ...]], bytes] = {}
    for kf in keyframes:
        image = np.ascontiguousarray(kf["image"], np.uint8)
        key = (int(kf["id"]), zlib.crc32(image), image.shape)
        png = None if cache is None else cache.get(key)
        if png is None:
            ok, buffer = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise ValueError(f"keyframe {kf['id']}: the image cannot be encoded")
            png = buffer.tobytes()
        encoded[key] = png
    if cache is not None:
        cache.clear()
        cache.update(encoded)
    pngs = list(encoded.values())
    meta.update(
        format=MAP_FORMAT, version=MAP_VERSION, extra=extra or {},
        ids=[int(kf["id"]) for kf in keyframes], depths=[int(kf["depth"]) for kf in keyframes],
        stamps=[None if kf["stamp"] is None else float(kf["stamp"]) for kf in keyframes],
        corner_counts=[len(kf["corners"]) for kf in keyframes], png_sizes=[len(png) for png in pngs],
    )  # fmt: skip
    out = io.BytesIO()
    np.savez(
        out,
        meta=np.frombuffer(json.dumps(meta).encode(), np.uint8),
        images_png=np.frombuffer(b"".join(pngs), np.uint8),
        H_ref=np.stack([kf["H_ref"] for kf in keyframes]).astype(np.float64),
        corners=np.concatenate([np.asarray(kf["corners"], np.float32).reshape(-1, 2) for kf in keyframes]),
    )
    return out.getvalue()


def _decode_images(blob: NDArray[np.uint8], sizes: list[int]) -> NDArray[np.uint8]:
    if blob.ndim != 1 or sum(sizes) != len(blob) or not sizes:
        raise ValueError("image sizes do not match the image data")
    images = []
    for chunk in np.split(blob, np.cumsum(sizes)[:-1]):
        image = cv2.imdecode(chunk, cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError("a keyframe image is not a mono8 PNG")
        images.append(image)
    if len({image.shape for image in images}) != 1:
        raise ValueError("keyframe images of different sizes")
    return np.stack(images)


def map_from_bytes(blob: bytes) -> tuple[dict[str, Any], dict[str, Any]]:
    """(map for HomographyTracker.restore_map, extra) from map_to_bytes' blob; ValueError when it is not
    one (truncated, corrupt, another format or version, inconsistent sizes)."""
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as npz:
            meta = json.loads(npz["meta"].tobytes().decode())
            images_png, H_ref, corners = npz["images_png"], npz["H_ref"], npz["corners"]
    except ValueError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, EOFError, KeyError, UnicodeDecodeError, OSError
        raise ValueError(f"not a tracker map file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != MAP_FORMAT or meta.get("version") != MAP_VERSION:
        raise ValueError("not a tracker map file of this version")
    try:
        ids, counts = meta["ids"], meta["corner_counts"]
        n = len(ids)
        images = _decode_images(images_png, meta["png_sizes"])
        if not (images.ndim == 3 and len(images) == n and H_ref.shape == (n, 3, 3)):
            raise ValueError("keyframe arrays do not match the keyframe list")
        if len(counts) != n or len(meta["depths"]) != n or len(meta["stamps"]) != n:
            raise ValueError("keyframe lists of different lengths")
        if corners.ndim != 2 or corners.shape[1] != 2 or sum(counts) != len(corners):
            raise ValueError("corner counts do not match the corners")
        splits = np.split(corners, np.cumsum(counts)[:-1]) if n else []
        keyframes = [
            {
                "id": ids[i],
                "stamp": meta["stamps"][i],
                "H_ref": H_ref[i],
                "depth": meta["depths"][i],
                "image": images[i],
                "corners": splits[i],
            }
            for i in range(n)
        ]
        data = {key: meta[key] for key in ("reference_id", "keyframe_id", "frame_index", "scale")}
    except (KeyError, TypeError) as exc:
        raise ValueError(f"malformed tracker map metadata: {type(exc).__name__}: {exc}") from exc
    data["keyframes"] = keyframes
    extra = meta.get("extra") or {}
    return data, extra if isinstance(extra, dict) else {}


def _corners(shape: tuple[int, ...]) -> Array:
    h, w = shape[:2]
    return np.array([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]])


def _overlap(H_frame_to_keyframe: Array, shape: tuple[int, ...]) -> float:
    """Fraction of the frame's area that lies inside the keyframe (both the same image size)."""
    quad = apply_homography(H_frame_to_keyframe, _corners(shape)).astype(np.float32)
    area = abs(cv2.contourArea(quad))
    if not np.all(np.isfinite(quad)) or area <= 0.0 or not cv2.isContourConvex(quad):
        return 0.0
    inter, _ = cv2.intersectConvexConvex(quad, _corners(shape).astype(np.float32))
    return float(inter / area)


def _local_scale(H: Array, shape: tuple[int, ...]) -> float:
    """sqrt|det J| of x -> Hx at the image centre: the zoom factor between the two images there."""
    h, w = shape[:2]
    x = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    p = H @ x
    J = (H[:2, :2] * p[2] - np.outer(p[:2], H[2, :2])) / p[2] ** 2
    return float(np.sqrt(abs(np.linalg.det(J))))


def _deviation(H_a: Array, H_b: Array, shape: tuple[int, ...]) -> float:
    """Largest distance between two homographies' images of a grid over the source image."""
    h, w = shape[:2]
    grid = np.stack(np.meshgrid(np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 4)), -1).reshape(-1, 2)
    return float(np.max(np.linalg.norm(apply_homography(H_a, grid) - apply_homography(H_b, grid), axis=1)))


def _plausible(H: Array, shape: tuple[int, ...]) -> bool:
    """Reject degenerate fits: the frame must map to a convex quadrilateral of sane size."""
    quad = apply_homography(H, _corners(shape)).astype(np.float32)
    if not np.all(np.isfinite(quad)) or not cv2.isContourConvex(quad):
        return False
    ratio = abs(cv2.contourArea(quad)) / float(shape[0] * shape[1])
    return 0.05 < ratio < 20.0
