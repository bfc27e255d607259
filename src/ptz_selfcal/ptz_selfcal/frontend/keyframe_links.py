"""The tracker's keyframes and their links (paper sections 2.2 and 4.2): a keyframe -> frame homography
measured independently of the tracked chain, so that chained error stays bounded when the camera comes
back to a view.

A link is measured photometrically (the keyframe warped by a predicted homography, the frame's corners
tracked into it by KLT), starting from the chain's prediction or from descriptor matches, and checked
against the chain. The links of a new keyframe are the bundle adjustment's input (the calibrator's
KeyframeMatches). Working-resolution pixels inside, full resolution in KeyframeLink. With a rolling
shutter (LinkFrame.readout) every fit is on global-shutter positions (frontend.rolling_shutter): a
keyframe's points corrected with its own motion, the frame's with the frame's.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import apply_homography, homography_work_to_full
from ptz_selfcal.frontend.features import (
    Descriptors,
    RobustFit,
    compute_descriptors,
    descriptor_extractor,
    detect_corners,
    gain_matched_warp,
    match_descriptors,
    robust_homography,
    track_klt,
)
from ptz_selfcal.frontend.homography import max_deviation, plausible
from ptz_selfcal.frontend.rolling_shutter import FrameMotion, global_shutter
from ptz_selfcal.frontend.tracker_config import TrackerConfig

Array = NDArray[np.float64]
Points = NDArray[np.float32]

_LOG = logging.getLogger(__name__)


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


@dataclass
class MapKeyframe:
    """A keyframe of the tracker's map (its image and corners, placed by H_ref); not the calibrator's
    keyframe record (online.incremental.Keyframe)."""

    id: int  # frame index of the keyframe
    stamp: float | None
    image: np.ndarray  # working resolution, mono8
    H_ref: Array  # reference -> keyframe, full resolution
    depth: int  # keyframe links between the reference and this keyframe
    corners: Points  # corners detected in the keyframe (working pixels)
    descriptors: Descriptors | None  # computed on first use
    motion: FrameMotion | None = None  # its image motion when made (rolling shutter; None: none known)


@dataclass
class LinkFrame:
    """The frame being linked to keyframes; its descriptors are computed on first use, once per frame."""

    image: np.ndarray  # working resolution, mono8
    index: int  # frame index (the id it gets as a keyframe)
    scale: float  # working / full resolution
    descriptors: Descriptors | None = None
    readout: float = 0.0  # rolling-shutter readout time (s) the fits correct for (0: none)
    motion: FrameMotion | None = None  # the frame's image motion, once tracked (None: none known)

    def corrected(self, points: np.ndarray, motion: FrameMotion | None) -> np.ndarray:
        """Global-shutter positions of points of this frame (or of a keyframe of the same size: its
        `motion`); the points themselves without a readout or a motion."""
        if self.readout == 0.0 or motion is None:
            return points
        return global_shutter(points, motion, self.readout, self.image.shape[0], self.scale)


@dataclass(frozen=True)
class MeasuredLink:
    """A new keyframe's link with the keyframe it starts from and the working-resolution fit behind it."""

    keyframe: MapKeyframe
    fit: RobustFit
    link: KeyframeLink


def make_link(
    kf: MapKeyframe, fit: RobustFit, src: np.ndarray, dst: np.ndarray, scale: float
) -> KeyframeLink:
    """Link keyframe -> (not yet stored) frame in full resolution; target id filled in later."""
    s = scale
    if len(src) != int(fit.inliers.sum()):  # all correspondences given: keep the inliers
        src, dst = src[fit.inliers], dst[fit.inliers]
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    return KeyframeLink(
        source_id=kf.id, target_id=-1, H=homography_work_to_full(fit.H, s),
        source_points=(src + 0.5) / s - 0.5, target_points=(dst + 0.5) / s - 0.5,
        rms_transfer_error=fit.rms / s,
    )  # fmt: skip


class KeyframeLinker:
    """Measures keyframe -> frame homographies (working pixels) for links, revisits and relocalisation."""

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self._klt = config.klt()
        self._extractor = descriptor_extractor(config.descriptor, config.descriptor_features)

    def link(
        self,
        kf: MapKeyframe,
        frame: LinkFrame,
        corners: Points,
        H_chain: Array,
        rematch: bool = True,
        hops: int = 1,
    ) -> MeasuredLink | None:
        """Re-measure keyframe -> frame independently of the chain: photometrically from the chain's
        prediction, else (rematch) from descriptor matches; reject a link that contradicts the chain.

        The chain between the keyframe and the frame is up to `hops` links long and drifts (each link is
        measured on the overlap only, mostly small at high zoom, and extrapolated to the whole image):
        a link further than link_max_deviation from it is kept up to link_max_deviation sqrt(hops) when
        the descriptor homography, a global measurement independent of both, confirms it (loop closure
        after a long excursion; a wrong alias on repetitive texture is not confirmed)."""
        c = self.config
        shape = frame.image.shape
        tolerance = c.link_tolerance(frame.scale)
        loose = tolerance * math.sqrt(max(hops, 1))
        starts = [] if c.link_with_descriptors else [H_chain]
        H_desc = self.descriptor_homography(kf, frame) if c.link_with_descriptors else None
        starts += [H_desc] if H_desc is not None else []
        for attempt in range(2):
            for H0 in starts:
                if max_deviation(H0, H_chain, shape) > loose:
                    continue
                refined = self.photometric_link(kf, frame, corners, H0)
                if refined is None:
                    continue
                fit, src, dst = refined
                off = max_deviation(fit.H, H_chain, shape)
                if off > tolerance and not (off <= loose and self.confirmed(kf, frame, fit.H)):
                    _LOG.debug("link %d -> frame %d contradicts the chain: dropped", kf.id, frame.index)
                    continue
                return MeasuredLink(kf, fit, make_link(kf, fit, src, dst, frame.scale))
            if attempt == 0 and rematch and not c.link_with_descriptors:
                H_desc = self.descriptor_homography(kf, frame)  # photometric start failed: re-match
                starts = [H_desc] if H_desc is not None else []
        return None

    def confirmed(self, kf: MapKeyframe, frame: LinkFrame, H: Array) -> bool:
        """Whether the descriptor homography keyframe -> frame agrees with H (working pixels)."""
        H_desc = self.descriptor_homography(kf, frame)
        tolerance = self.config.link_tolerance(frame.scale)
        return H_desc is not None and max_deviation(H, H_desc, frame.image.shape) <= tolerance

    def descriptor_homography(self, kf: MapKeyframe, frame: LinkFrame) -> Array | None:
        """Keyframe -> frame homography (working pixels) from descriptor matches, or None."""
        c = self.config
        src, dst = match_descriptors(
            self._descriptors_of(kf), self._frame_descriptors(frame), c.descriptor_ratio
        )
        src, dst = frame.corrected(src, kf.motion), frame.corrected(dst, frame.motion)
        fit = robust_homography(src, dst, c.usac(frame.scale, 3.0), c.min_inliers, c.refine_iterations)
        if fit is None or not plausible(fit.H, frame.image.shape):
            return None
        return fit.H

    def photometric_link(
        self, kf: MapKeyframe, frame: LinkFrame, corners: Points, H0: Array
    ) -> tuple[RobustFit, Array, Array] | None:
        """Refine keyframe -> frame H (working pixels): warp the keyframe by the guess H0, KLT the frame's
        corners into the warped keyframe (small residual motion, no scale change) and map them back."""
        c = self.config
        image = frame.image
        h, w = image.shape
        in_kf = apply_homography(np.linalg.inv(H0), corners)
        margin = c.klt_window
        kh, kw = kf.image.shape
        visible = (
            np.all(in_kf >= margin, axis=1)
            & (in_kf[:, 0] <= kw - 1 - margin)
            & (in_kf[:, 1] <= kh - 1 - margin)
        )
        warped = cv2.warpPerspective(kf.image, H0, (w, h))
        if c.gain_compensation:
            warped = gain_matched_warp(warped, image)
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
        src = frame.corrected(apply_homography(np.linalg.inv(H0), found[ok]), kf.motion)
        dst = frame.corrected(pts[ok].astype(np.float64), frame.motion)
        fit = robust_homography(src, dst, c.usac(frame.scale), c.min_inliers, c.refine_iterations)
        return None if fit is None else (fit, src[fit.inliers], dst[fit.inliers])

    def _descriptors_of(self, kf: MapKeyframe) -> Descriptors:
        """Descriptors of a keyframe, computed once on first use (relocalisation, re-matching)."""
        if kf.descriptors is None:
            kf.descriptors = compute_descriptors(self._extractor, kf.image)
        return kf.descriptors

    def _frame_descriptors(self, frame: LinkFrame) -> Descriptors:
        """Descriptors of the frame, computed once (several keyframes are matched against it)."""
        if frame.descriptors is None:
            frame.descriptors = compute_descriptors(self._extractor, frame.image)
        return frame.descriptors
