"""The zoom encoder's rate of change at each frame: with it the zoom model learns and undoes the
encoder's lag (zooming in and out trace one curve of zoom + lag * rate)."""

from __future__ import annotations

import math

import numpy as np


class ZoomRate:
    """Zoom encoder rate (counts / s) at each frame: the least-squares slope of the frame zoom values
    of the last `window` seconds (at least 3; else the backward difference to the previous one within
    `max_gap`), so a held or repeated encoder value does not spike it. 0 when unknown."""

    def __init__(self, window: float = 0.15, max_gap: float = 0.5) -> None:
        self.window = window
        self.max_gap = max_gap
        self._recent: list[tuple[float, float]] = []

    def update(self, stamp: float, zoom: float) -> float:
        """Add this frame's (stamp s, zoom) and return the rate at it (NaN zoom: 0, history kept)."""
        if not (math.isfinite(stamp) and math.isfinite(zoom)):
            return 0.0
        recent = [p for p in self._recent if 0.0 < stamp - p[0] <= self.max_gap]
        recent.append((float(stamp), float(zoom)))
        self._recent = recent
        if len(recent) < 2:
            return 0.0
        window = np.array([p for p in recent if stamp - p[0] <= self.window])
        if len(window) < 3:
            (t0, z0), (t1, z1) = recent[-2], recent[-1]
            return (z1 - z0) / (t1 - t0)
        t = window[:, 0] - window[:, 0].mean()
        return float(np.dot(t, window[:, 1] - window[:, 1].mean()) / max(float(np.dot(t, t)), 1e-12))
