"""The homography tracker's settings: one frozen dataclass, from which the tracker node generates its
parameters (`tracker.<field>`, described by each field's comment)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2

from ptz_selfcal.frontend.features import KltParams, usac_params

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
    # Rolling shutter (rows exposed one after another): fits and points corrected to the middle row.
    rolling_shutter_readout: float = -1.0  # s, first row to last (< 0: estimated from the images, 0: none)
    gain_compensation: bool = True  # match brightness before KLT: a smooth gain field (exposure, vignetting)
    seed: int = 0

    def __post_init__(self) -> None:
        for name, allowed in TRACKER_CHOICES.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, not {getattr(self, name)!r}")

    def klt(self) -> KltParams:
        """The pyramidal KLT settings of these fields."""
        return KltParams(window=self.klt_window, levels=self.klt_levels, iterations=self.klt_iterations,
                         epsilon=self.klt_epsilon, fb_threshold=self.klt_fb_threshold)  # fmt: skip

    def usac(self, scale: float, factor: float = 1.0) -> cv2.UsacParams:
        """USAC settings at working scale `scale`, the threshold `factor` times ransac_threshold."""
        threshold = factor * self.ransac_threshold * scale
        return usac_params(threshold, self.seed, self.ransac_max_iterations, self.ransac_confidence)

    def link_tolerance(self, scale: float) -> float:
        """Largest disagreement (working pixels) between a re-matched link and the tracked chain."""
        return self.link_max_deviation * scale
