"""Pan-tilt-zoom encoder samples interpolated to image stamps (pure: no rclpy, no messages).

A PTZ head reports its joints at its own rate (often well below the frame rate), with its own clock
offset, sometimes one joint per message, sometimes with garbage (NaN/inf, repeated or out-of-order
stamps, a stamp far in the future). `EncoderInterpolator` keeps a bounded, time-sorted buffer per joint
and answers "what were pan, tilt and zoom at this image stamp?":

- encoder time offset: a sample stamped t_e describes the head at image-clock time t_e + time_offset;
- a query is VALID when, for every joint, samples bracket the stamp no more than `max_gap` apart (linear
  interpolation; pan and tilt along the shorter arc), or a sample lies within `max_hold` of it (a stamp
  just past the newest sample is extrapolated along the last two samples when they are no more than
  `max_gap` apart: holding the newest value would give a zooming head's frames a zoom up to max_hold
  stale, while waiting for the next sample would add an encoder period of latency to every frame);
- otherwise the state says why (NO_DATA, NOT_YET = the stamp is newer than the newest sample, so waiting
  may help, GAP = the bracketing samples are too far apart, TOO_OLD = older than anything retained) and
  the values are NaN.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum


class QueryStatus(StrEnum):
    VALID = "VALID"
    NO_DATA = "NO_DATA"  # no sample of some joint yet
    NOT_YET = "NOT_YET"  # stamp newer than the newest sample (+ max_hold): newer samples may come
    GAP = "GAP"  # bracketed, but by samples further apart than max_gap
    TOO_OLD = "TOO_OLD"  # older than every retained sample (- max_hold)


class Rejection(StrEnum):
    """Why a sample (or one joint of a sample) was not stored."""

    NOT_FINITE = "not_finite"  # NaN/inf value or stamp
    DUPLICATE = "duplicate_stamp"  # same stamp as a stored sample of that joint
    TOO_OLD = "too_old"  # older than everything retained while the buffer is full
    FUTURE = "future_stamp"  # further ahead of the reference time than max_future


@dataclass(frozen=True)
class EncoderConfig:
    joints: tuple[str, str, str] = ("pan", "tilt", "zoom")
    angular: tuple[bool, bool, bool] = (True, True, False)  # interpolate along the shorter arc
    time_offset: float = 0.0  # seconds added to encoder stamps to put them on the image clock
    max_gap: float = 0.5  # seconds: bracketing samples further apart than this are not trusted
    max_hold: float = 0.05  # seconds: a sample this close to the stamp is used (see the module doc)
    max_future: float = 10.0  # seconds ahead of the reference time beyond which a sample is rejected
    max_samples: int = 2000  # per joint (bounded memory)

    def validate(self) -> None:
        if len(self.joints) != 3 or len(set(self.joints)) != 3 or not all(self.joints):
            raise ValueError(f"joints must be three distinct non-empty names, got {list(self.joints)}")
        for name in ("time_offset", "max_gap", "max_hold", "max_future"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        if abs(self.time_offset) > 60.0:
            raise ValueError(f"time_offset must be within +-60 s, got {self.time_offset}")
        if not 0.0 < self.max_gap <= 60.0:
            raise ValueError(f"max_gap must be in (0, 60] s, got {self.max_gap}")
        if not 0.0 <= self.max_hold <= 10.0:
            raise ValueError(f"max_hold must be in [0, 10] s, got {self.max_hold}")
        if not self.max_future > 0.0:
            raise ValueError(f"max_future must be > 0 s, got {self.max_future}")
        if not 2 <= self.max_samples <= 1_000_000:
            raise ValueError(f"max_samples must be in [2, 1000000], got {self.max_samples}")


@dataclass(frozen=True)
class EncoderQuery:
    status: QueryStatus
    pan: float
    tilt: float
    zoom: float

    @property
    def valid(self) -> bool:
        return self.status is QueryStatus.VALID


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class _JointBuffer:
    """Time-sorted samples of one joint, at most `capacity` (the oldest are dropped)."""

    def __init__(self, capacity: int, angular: bool) -> None:
        self.capacity = capacity
        self.angular = angular
        self.times: list[float] = []
        self.values: list[float] = []

    def add(self, t: float, value: float) -> Rejection | None:
        i = bisect.bisect_left(self.times, t)
        if i < len(self.times) and self.times[i] == t:
            return Rejection.DUPLICATE
        if len(self.times) >= self.capacity:
            if i == 0:
                return Rejection.TOO_OLD
            del self.times[0], self.values[0]
            i -= 1
        self.times.insert(i, t)
        self.values.insert(i, value)
        return None

    def query(self, t: float, max_gap: float, max_hold: float) -> tuple[QueryStatus, float]:
        times = self.times
        if not times:
            return QueryStatus.NO_DATA, math.nan
        i = bisect.bisect_left(times, t)
        if i < len(times) and times[i] == t:
            return QueryStatus.VALID, self.values[i]
        if i == len(times):  # newer than every sample
            if t - times[-1] <= max_hold:
                return QueryStatus.VALID, self._extrapolate(t, max_gap)
            return QueryStatus.NOT_YET, math.nan
        if i == 0:  # older than every sample
            if times[0] - t <= max_hold:
                return QueryStatus.VALID, self.values[0]
            return QueryStatus.TOO_OLD, math.nan
        t0, t1 = times[i - 1], times[i]
        v0, v1 = self.values[i - 1], self.values[i]
        if t1 - t0 > max_gap:
            if t - t0 <= max_hold:
                return QueryStatus.VALID, v0
            if t1 - t <= max_hold:
                return QueryStatus.VALID, v1
            return QueryStatus.GAP, math.nan
        return QueryStatus.VALID, self._along(t, i - 1)

    def _along(self, t: float, i: int) -> float:
        """The value at t on the line through samples i and i + 1 (pan/tilt along the shorter arc)."""
        t0, t1 = self.times[i], self.times[i + 1]
        v0, v1 = self.values[i], self.values[i + 1]
        delta = _wrap(v1 - v0) if self.angular else v1 - v0
        return v0 + (t - t0) / (t1 - t0) * delta

    def _extrapolate(self, t: float, max_gap: float) -> float:
        """Past the newest sample: along the last two samples if they are close enough, else held."""
        if len(self.times) >= 2 and self.times[-1] - self.times[-2] <= max_gap:
            return self._along(t, len(self.times) - 2)
        return self.values[-1]


# Worst status first: the query reports the worst joint's status.
_SEVERITY = {
    QueryStatus.NO_DATA: 0,
    QueryStatus.GAP: 1,
    QueryStatus.TOO_OLD: 2,
    QueryStatus.NOT_YET: 3,
    QueryStatus.VALID: 4,
}


class EncoderInterpolator:
    """Bounded per-joint encoder buffers and interpolation to image stamps; see the module docstring."""

    def __init__(self, config: EncoderConfig | None = None) -> None:
        self.config = config or EncoderConfig()
        self.config.validate()
        self._buffers = {
            name: _JointBuffer(self.config.max_samples, angular)
            for name, angular in zip(self.config.joints, self.config.angular)
        }
        self.samples_accepted = 0  # joint values stored
        self.rejections: dict[str, int] = {r.value: 0 for r in Rejection}

    @property
    def joints(self) -> tuple[str, ...]:
        return self.config.joints

    def sample_count(self, joint: str) -> int:
        return len(self._buffers[joint].times)

    def newest_stamp(self) -> float | None:
        """Image-clock time of the newest sample common to all joints (the oldest 'newest')."""
        newest = [b.times[-1] for b in self._buffers.values() if b.times]
        return min(newest) if len(newest) == len(self._buffers) else None

    def add(
        self, stamp: float, values: Mapping[str, float], reference_time: float | None = None
    ) -> list[tuple[str, Rejection]]:
        """Store the values of the known joints in `values` (others are ignored) taken at encoder
        time `stamp`. `reference_time` (image clock, e.g. the newest image stamp) enables the
        far-future check. Returns the rejected (joint, reason) pairs, empty when all were stored."""
        rejected: list[tuple[str, Rejection]] = []
        present = [name for name in self.config.joints if name in values]
        t = stamp + self.config.time_offset
        whole: Rejection | None = None
        if not math.isfinite(t):
            whole = Rejection.NOT_FINITE
        elif reference_time is not None and t - reference_time > self.config.max_future:
            whole = Rejection.FUTURE
        if whole is not None:
            self.rejections[whole.value] += len(present)
            return [(name, whole) for name in present]
        for name in present:
            value = float(values[name])
            reason = Rejection.NOT_FINITE if not math.isfinite(value) else self._buffers[name].add(t, value)
            if reason is None:
                self.samples_accepted += 1
            else:
                rejected.append((name, reason))
                self.rejections[reason.value] += 1
        return rejected

    def add_arrays(
        self,
        stamp: float,
        names: Sequence[str],
        positions: Sequence[float],
        reference_time: float | None = None,
    ) -> list[tuple[str, Rejection]]:
        """add() for a JointState-like pair of name and position lists (extra names are ignored)."""
        values = {n: p for n, p in zip(names, positions) if n in self._buffers}
        return self.add(stamp, values, reference_time)

    def query(self, t: float) -> EncoderQuery:
        """Encoder values at image-clock time t."""
        c = self.config
        status = QueryStatus.VALID
        out: list[float] = []
        for name in c.joints:
            s, v = self._buffers[name].query(t, c.max_gap, c.max_hold)
            if _SEVERITY[s] < _SEVERITY[status]:
                status = s
            out.append(v)
        if status is not QueryStatus.VALID:
            return EncoderQuery(status, math.nan, math.nan, math.nan)
        return EncoderQuery(status, out[0], out[1], out[2])
