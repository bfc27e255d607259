"""The learned zoom model: zoom encoder -> (f, principal point, k1, k2) with its uncertainty.

What the calibrator learns while the camera zooms is summarised here so that a restarted calibrator,
or a frame without a homography (tracking lost, status PREDICTED_FROM_ZOOM), gets a good K and D from
the zoom encoder alone.

- Bounded memory: samples are accumulated into zoom bins holding weighted running sums (count, sum w,
  sum w z, sum w q, sum w q^2 for q in log f, cx, cy, k1, k2). When more than `max_bins` bins are
  occupied the bin width doubles and neighbours merge (running sums merge exactly), so any encoder
  range fits in O(max_bins) memory however long the camera runs.
- Live samples: the keyframes of the running calibration are re-estimated at every solve (bundle
  adjustment refines them long after they were added), so they enter as LIVE samples keyed by keyframe
  (`set_live`): each solve replaces them with the latest estimates, and a keyframe that leaves the
  calibration is committed to the bins with its last (best) estimate. At most `max_live` are kept.
  The bins are the history (reloaded from the file at start and never refitted away); the fit uses
  bins and live samples together.
- Calibrations: the f / rotation near-ambiguity (section 6.2) gives all focal lengths of one
  calibration one common scale error, which differs between calibrations (sessions, resets). Samples
  carry their calibration's id (`new_calibration` starts the next); the log f fit has one offset per
  calibration with a zero-mean prior of that calibration's per-sample sigma, so calibrations are
  levelled against each other where they overlap in zoom and a biased one cannot bend the curve where
  it alone has data. Beyond `max_calibrations` the oldest merges into the next (shifted by the
  difference of their offsets; bounded memory).
- Encoder lag: a zoom encoder that reports late (or a wrong encoder_time_offset) reads the zoom of
  `lag` seconds earlier, so zooming in and zooming out trace two curves (at 35 %/s a 40 ms lag is 1.4 %
  in f). Keyframes carry their zoom rate (ZoomRate); the lag that joins both branches into one
  monotone curve of zoom + lag * rate is adopted when it explains the live samples significantly
  better (`estimate_lag`), and predictions take the frame's rate too.
- Weights: a sample's weight is 1 / sigma^2 of its log f (relative focal sigma from the bundle
  adjustment's Jacobian); keyframes the adjustment pins down poorly count little.
- zoom -> log f: a MONOTONE penalised cubic B-spline (non-decreasing coefficients give a non-decreasing
  spline; all that is known of a lens is that f grows with zoom), weighted, made robust by
  Huber reweighting of the bins (a keyframe whose focal length is several sigma off its neighbours,
  e.g. one the adjustment has not converged on yet, is down-weighted). log f because zoom lenses are
  close to exponential in their drive position. Outside the covered range log f is extended linearly
  with the end slope and the uncertainty grows with the extrapolated change.
- zoom -> cx, cy, k1, k2: the same penalised spline without the monotone constraint; constant outside
  the covered range. k1, k2 enter the plumb_bob model linearly, so averaging them averages the curves.
- Uncertainty of log f: the weighted spline's own covariance at the zoom, scaled by the reduced
  chi-square when the samples scatter more than their sigmas say, plus the typical per-sample sigma
  near that zoom: the f / rotation near-ambiguity (section 6.2) makes one calibration's focal errors a
  common scale factor that averaging its keyframes does not remove; plus the samples' scatter about
  the curve beyond their own sigmas (the zoom encoder's noise and lag: a predicted frame reads the
  same encoder). Other quantities: per bin, the
  standard error of the bin mean combined with the spline's misfit.
- Visited range: [lowest, highest] zoom of the samples (committed and live); `in_range` says so.
- Persistence: YAML with a format name and version, written atomically (persist.atomic_file); any
  unreadable or invalid file raises ZoomModelError so the caller starts fresh. The camera_calibration
  export (zoom.camera_calibration) writes K and D at chosen zooms for ROS tools.
"""

from __future__ import annotations

import math
import os
from collections.abc import Hashable, Iterable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import BSpline

from ptz_selfcal.camera.geometry import intrinsic_matrix
from ptz_selfcal.persist.atomic_file import atomic_write_text, remove_stale_temporaries
from ptz_selfcal.zoom.camera_calibration import write_camera_calibrations
from ptz_selfcal.zoom.spline import design_matrix, penalised_spline

Array = NDArray[np.float64]

FORMAT_NAME = "ptz_selfcal_zoom_model"
FORMAT_VERSION = 1
QUANTITIES = ("log_f", "cx", "cy", "k1", "k2")
_GAP_FRACTION = 0.1  # of the change of log f across a gap between samples: the curve's 1-sigma there
_SUM_FIELDS = ("n", "w", "wz", *(f"w_{q}" for q in QUANTITIES), *(f"w2_{q}" for q in QUANTITIES))


class ZoomModelError(Exception):
    """The zoom model file is missing, corrupt or invalid, or the model has no data yet."""


class ZoomPrediction(NamedTuple):
    K: Array  # 3x3, full-resolution pixels
    D: Array  # plumb_bob [k1, k2, 0, 0, 0]
    sigma_f: float  # 1-sigma of f in pixels
    in_range: bool  # zoom inside the visited range [lowest, highest zoom added]


class _Fit(NamedTuple):
    z_lo: float
    z_hi: float
    splines: dict[str, BSpline | None]  # None = constant
    constants: dict[str, float]
    end_slopes: tuple[float, float]  # d log f / dz at z_lo and z_hi
    bin_z: Array
    bin_sigma: dict[str, Array]  # per-bin 1-sigma of each quantity (fit + mean)
    log_f_cov: tuple[Array, Array, int, Array] | None  # knots, degree, coefficient covariance (scaled)
    offsets: dict[int, float]  # per calibration: its estimated log f scale offset (section 6.2)


class ZoomModel:
    """Learned zoom -> (K, D) model with bounded memory (see module docstring)."""

    def __init__(
        self,
        max_bins: int = 64,
        bin_width: float | None = None,
        max_basis: int = 10,
        smoothing: float = 1e-3,
        max_live: int = 256,
        huber: float = 2.5,
        max_calibrations: int = 8,
        estimate_lag: bool = True,
        max_lag: float = 0.25,
    ) -> None:
        if max_bins < 4:
            raise ValueError("max_bins must be >= 4")
        if max_live < 0:
            raise ValueError("max_live must be >= 0")
        if max_calibrations < 1:
            raise ValueError("max_calibrations must be >= 1")
        self.max_bins = max_bins
        self.bin_width = bin_width
        self.max_basis = max_basis
        self.smoothing = smoothing
        self.max_live = max_live
        self.huber = huber
        self.max_calibrations = max_calibrations
        self.calibration = 0  # id of the running calibration: its samples share one scale error
        self.estimate_lag = estimate_lag
        self.max_lag = max_lag
        self.lag = 0.0  # s: the lens is at zoom + lag * zoom_rate when the encoder reads zoom
        self._live_rate: dict[Hashable, float] = {}  # keyframe -> zoom rate (encoder counts / s)
        self._bins: dict[tuple[int, int], Array] = {}  # (calibration, zoom bin) -> running sums
        self._live: dict[Hashable, Array] = {}  # keyframe -> one sample's row (see _row)
        self._zoom_limits: tuple[float, float] | None = None  # lowest and highest committed zoom
        self._fit: _Fit | None = None

    # ------------------------------------------------------------------------------------------ data
    @property
    def sample_count(self) -> int:
        """Committed samples plus live ones."""
        return int(sum(b[0] for b in self._bins.values())) + len(self._live)

    @property
    def bin_count(self) -> int:
        return len(self._bins)

    @property
    def live_count(self) -> int:
        return len(self._live)

    def live_keys(self) -> list[Hashable]:
        return list(self._live)

    def is_empty(self) -> bool:
        return not self._bins and not self._live

    def covered_range(self) -> tuple[float, float] | None:
        """(lowest, highest) zoom of the samples (committed and live): the visited range, or None."""
        zooms = [row[2] / row[1] for row in self._live.values()]
        if self._zoom_limits is not None:
            zooms += list(self._zoom_limits)
        return (float(min(zooms)), float(max(zooms))) if zooms else None

    @staticmethod
    def _row(
        zoom: float, f: float, cx: float, cy: float, k1: float, k2: float, weight: float
    ) -> Array | None:
        """Running-sum row of one sample (n, w, w z, w q, w q^2), or None if it is not usable."""
        values = (zoom, f, cx, cy, k1, k2, weight)
        if not all(math.isfinite(v) for v in values) or f <= 0.0 or weight <= 0.0:
            return None
        q = np.array([math.log(f), cx, cy, k1, k2])
        return np.concatenate([[1.0, weight, weight * zoom], weight * q, weight * q * q])

    def _commit_row(self, row: Array, calibration: int | None = None) -> None:
        zoom = float(row[2] / row[1])
        if self.bin_width is None:
            self.bin_width = max(abs(zoom), 1.0) * 1e-6  # grows by doubling as the range is explored
        cal = self.calibration if calibration is None else calibration
        key = (cal, math.floor(zoom / self.bin_width))
        lo, hi = self._zoom_limits or (zoom, zoom)
        self._zoom_limits = (min(lo, zoom), max(hi, zoom))
        if key in self._bins:
            self._bins[key] = self._bins[key] + row
        else:
            self._bins[key] = row.copy()
        while len(self._bins) > self.max_bins:
            self._coarsen()
        self._fit = None

    def add_sample(
        self,
        zoom: float,
        f: float,
        cx: float,
        cy: float,
        k1: float = 0.0,
        k2: float = 0.0,
        weight: float = 1.0,
    ) -> bool:
        """Commit one calibrated frame; weight = 1 / sigma^2 of log f (or relative). False if rejected."""
        row = self._row(*(float(v) for v in (zoom, f, cx, cy, k1, k2, weight)))
        if row is None:
            return False
        self._commit_row(row)
        return True

    def set_live(self, samples: Mapping[Hashable, tuple[float, ...]]) -> int:
        """Replace the live samples by `samples` (keyframe -> (zoom, f, cx, cy, k1, k2, weight[,
        zoom_rate])), the latest estimates of the running calibration's keyframes; zoom_rate (encoder
        counts per second at the keyframe; NaN or absent: the rate the key already has, else 0) lets the
        model learn the encoder's lag. A live
        keyframe absent from `samples` has left the calibration: its last estimate is committed.
        Returns how many are live."""
        live: dict[Hashable, Array] = {}
        rates: dict[Hashable, float] = {}
        for key, sample in samples.items():
            values = [float(v) for v in sample]
            # no rate (NaN or absent): the one this keyframe came with (e.g. restored from the file)
            rate = (
                values[7] if len(values) > 7 and math.isfinite(values[7]) else self._live_rate.get(key, 0.0)
            )
            values[0] += self.lag * rate
            row = self._row(*values[:7])
            if row is not None:
                live[key], rates[key] = row, rate
        for key in [k for k in self._live if k not in live]:
            self._commit_row(self._live.pop(key))
            self._live_rate.pop(key, None)
        while len(live) > self.max_live:  # bounded: the oldest entries are committed
            key = next(iter(live))
            self._commit_row(live.pop(key))
            rates.pop(key)
        self._live, self._live_rate = live, rates
        self._fit = None
        if self.estimate_lag:
            self._estimate_lag()
        return len(live)

    def _estimate_lag(self) -> None:
        """Encoder lag from the live samples: a lens zoomed in and out reads f(zoom + lag * rate), two
        branches that one curve of zoom + lag * rate joins. The lag minimising the weighted misfit of
        the monotone spline is adopted when it explains the data significantly better than the current
        one (F statistic > 10 for one extra parameter); committed samples keep the lag of their day."""
        keys = list(self._live)
        if len(keys) < 10:
            return
        rows = np.array([self._live[k] for k in keys])
        rate = np.array([self._live_rate.get(k, 0.0) for k in keys])
        moving = np.abs(rate) > 0.05 * max(float(np.abs(rate).max()), 1e-12)
        if np.sum(moving & (rate > 0)) < 3 or np.sum(moving & (rate < 0)) < 3:
            return  # the zoom went one way only: lag and curve are not separable
        w = rows[:, 1]
        z_raw = rows[:, 2] / w - self.lag * rate
        y = rows[:, 3] / w
        n_basis = min(self.max_basis, len(keys) - 3)

        def misfit(tau: float) -> float:
            z = z_raw + tau * rate
            if z.max() - z.min() <= 0.0:
                return math.inf
            fit = penalised_spline(z, y, w, n_basis, self.smoothing, monotone=True, huber=self.huber)
            return float(np.sum(fit.robust_weights * w * (y - fit.fitted) ** 2))

        grid = np.linspace(-self.max_lag, self.max_lag, 21)
        costs = np.array([misfit(float(t)) for t in grid])
        i = int(np.argmin(costs))
        tau = float(grid[i])
        if 0 < i < len(grid) - 1:  # parabola through the minimum and its neighbours
            c0, c1, c2 = costs[i - 1 : i + 2]
            denom = c0 - 2.0 * c1 + c2
            if denom > 0.0:
                tau += 0.5 * (c0 - c2) / denom * float(grid[1] - grid[0])
        best, current = misfit(tau), misfit(self.lag)
        dof = len(keys) - n_basis - 1
        if dof > 0 and best > 0.0 and (current - best) / (best / dof) > 10.0:
            self._set_lag(tau)

    def _set_lag(self, lag: float) -> None:
        for key, row in self._live.items():
            row[2] += row[1] * (lag - self.lag) * self._live_rate.get(key, 0.0)
        self.lag = float(lag)
        self._fit = None

    def commit_live(self, keep: Iterable[Hashable] = ()) -> int:
        """Commit the live samples except those in `keep` (e.g. the calibration was reset or not
        restored); returns how many were committed."""
        keep = set(keep)
        gone = [k for k in self._live if k not in keep]
        for key in gone:
            self._commit_row(self._live.pop(key))
            self._live_rate.pop(key, None)
        self._fit = None
        return len(gone)

    def new_calibration(self) -> int:
        """The running calibration ended (reset, new reference, restart without its state): its live
        samples are committed and later samples belong to a new calibration with its own scale error
        (section 6.2). Beyond `max_calibrations` the oldest is merged into the next, shifted by the
        difference of their estimated scale offsets. Returns the new calibration id."""
        if not self._live and not any(c == self.calibration for c, _ in self._bins):
            return self.calibration  # nothing learned from the running one: it stays the current id
        self.commit_live()
        self.calibration += 1
        self._fit = None
        cals = sorted({c for c, _ in self._bins})
        while len(cals) > self.max_calibrations:
            oldest, nxt = cals[0], cals[1]
            offsets = self._fitted().offsets
            shift = offsets.get(nxt, 0.0) - offsets.get(oldest, 0.0)
            for key in [k for k in self._bins if k[0] == oldest]:
                row = self._bins.pop(key).copy()
                w, wq = row[1], row[3]
                row[3] = wq + w * shift  # log f -> log f + shift: sum w q and sum w q^2 exactly
                row[8] = row[8] + 2.0 * shift * wq + w * shift * shift
                target = (nxt, key[1])
                self._bins[target] = self._bins[target] + row if target in self._bins else row
            self._fit = None
            cals = cals[1:]
        return self.calibration

    def add_samples(self, samples: Iterable[tuple[float, ...]]) -> int:
        """Add (zoom, f, cx, cy[, k1, k2[, weight]]) tuples; returns how many were accepted."""
        return sum(self.add_sample(*s) for s in samples)

    def add_calibrations(
        self, zooms: ArrayLike, Ks: ArrayLike, Ds: ArrayLike | None = None, weights: ArrayLike | None = None
    ) -> int:
        """Accumulate arrays of calibrations: zooms (N,), Ks (N, 3, 3) full-resolution, Ds (N, >=2)
        plumb_bob or None, weights (N,) or None. f = fx. Adds to what the model already holds (a
        reloaded model keeps its history). Returns how many were accepted."""
        zooms = np.asarray(zooms, dtype=float).ravel()
        Ks = np.asarray(Ks, dtype=float).reshape(-1, 3, 3)
        Ds = np.zeros((len(zooms), 2)) if Ds is None else np.asarray(Ds, dtype=float).reshape(len(zooms), -1)
        w = np.ones(len(zooms)) if weights is None else np.asarray(weights, dtype=float).ravel()
        if not (len(Ks) == len(Ds) == len(w) == len(zooms)) or Ds.shape[1] < 2:
            raise ValueError("zooms, Ks, Ds and weights must have the same length (Ds >= 2 columns)")
        return sum(
            self.add_sample(z, K[0, 0], K[0, 2], K[1, 2], D[0], D[1], wk)
            for z, K, D, wk in zip(zooms, Ks, Ds, w)
        )

    @classmethod
    def fit(
        cls,
        zooms: ArrayLike,
        Ks: ArrayLike,
        Ds: ArrayLike | None = None,
        weights: ArrayLike | None = None,
        **kwargs: Any,
    ) -> ZoomModel:
        """A new model from arrays of calibrations (see add_calibrations). To keep what a reloaded
        model already learned, call add_calibrations on it instead."""
        model = cls(**kwargs)
        model.add_calibrations(zooms, Ks, Ds, weights)
        return model

    def ready(self) -> bool:
        """True once predict() can answer (at least one sample)."""
        return not self.is_empty()

    def sigma_f(self, zoom: float) -> float:
        """1-sigma of the predicted focal length in pixels at this zoom."""
        return float(self.predict_parameters(zoom)["sigma_f"])

    def _coarsen(self) -> None:
        """Double the bin width; running sums of merged bins simply add."""
        assert self.bin_width is not None
        merged: dict[tuple[int, int], Array] = {}
        for (cal, key), row in self._bins.items():
            new = (cal, key // 2)
            merged[new] = merged[new] + row if new in merged else row.copy()
        self._bins = merged
        self.bin_width *= 2.0

    def _bin_table(self) -> tuple[Array, Array, Array, Array, Array, Array]:
        """Per bin of committed AND live samples (sorted by zoom): mean zoom, count, total weight,
        means (B, 5), variances (B, 5), calibration id."""
        bins = dict(self._bins)
        width = self.bin_width
        for row in self._live.values():
            zoom = float(row[2] / row[1])
            if width is None:
                width = max(abs(zoom), 1.0) * 1e-6
            key = (self.calibration, math.floor(zoom / width))
            bins[key] = bins[key] + row if key in bins else row
        keys = sorted(bins, key=lambda k: (k[1], k[0]))
        rows = np.array([bins[k] for k in keys])
        n, w = rows[:, 0], rows[:, 1]
        z = rows[:, 2] / w
        mean = rows[:, 3:8] / w[:, None]
        var = np.maximum(rows[:, 8:13] / w[:, None] - mean**2, 0.0)
        return z, n, w, mean, var, np.array([k[0] for k in keys])

    # ------------------------------------------------------------------------------------------- fit
    def _refit(self) -> _Fit:
        if self.is_empty():
            raise ZoomModelError("the zoom model has no samples")
        z, n, w, mean, var, cal = self._bin_table()
        n_bins = len(z)
        # one log f offset per calibration (its common scale error, section 6.2) with a zero-mean
        # prior of its typical per-sample sigma: calibrations that overlap in zoom are levelled against
        # each other, the model sits at their precision-weighted mean
        cal_ids, groups = np.unique(cal, return_inverse=True)
        group_prior = None
        if len(cal_ids) > 1:
            group_prior = np.array(
                [1.0 / float(np.median(n[groups == g] / w[groups == g])) for g in range(len(cal_ids))]
            )
        # standard error of each bin mean: its own spread, or the pooled spread for single samples
        pooled = np.sum(var * n[:, None], axis=0) / max(np.sum(np.maximum(n - 1, 0)), 1)
        spread = np.where((n > 1)[:, None], var * n[:, None] / np.maximum(n - 1, 1)[:, None], pooled)
        se = np.sqrt(spread / n[:, None])
        splines: dict[str, BSpline | None] = {}
        constants: dict[str, float] = {}
        sigma: dict[str, Array] = {}
        slopes = (0.0, 0.0)
        log_f_cov = None
        offsets: dict[int, float] = {}
        leverage = np.zeros(n_bins)
        # keep one degree of freedom for the misfit once there are 3 bins (an interpolating spline
        # would claim zero uncertainty)
        n_basis = min(n_bins if n_bins < 3 else n_bins - 1, self.max_basis)
        robust = np.ones(n_bins)
        for col, name in enumerate(QUANTITIES):
            y = mean[:, col]
            wq = w * robust  # the focal fit's outliers are the same frames' other parameters too
            if n_bins == 1 or z.max() - z.min() <= 0.0:
                splines[name] = None
                constants[name] = float(np.average(y, weights=wq))
                fitted = np.full_like(y, constants[name])
            else:
                log_f = name == "log_f"
                fit = penalised_spline(
                    z,
                    y,
                    wq,
                    n_basis,
                    self.smoothing,
                    monotone=log_f,
                    huber=self.huber if log_f else None,
                    groups=groups if log_f else None,
                    group_prior=group_prior if log_f else None,
                )
                fitted = fit.fitted
                splines[name] = fit.spline
                constants[name] = float(np.average(y, weights=wq))
                if log_f:
                    robust = fit.robust_weights
                    d = fit.spline.derivative()
                    slopes = (max(float(d(z.min())), 0.0), max(float(d(z.max())), 0.0))
                    log_f_cov = (fit.spline.t, fit.covariance, fit.spline.k, fitted)
                    leverage = fit.leverage
                    offsets = {int(c): float(o) for c, o in zip(cal_ids, fit.offsets)}
            dof = n_bins - min(n_basis, n_bins)
            keep = robust > 0.5  # misfit of the points the fit trusts
            misfit = np.sum((n * (y - fitted) ** 2)[keep]) / np.sum(n[keep])
            misfit2 = float(misfit) * n_bins / dof if dof > 0 else 0.0
            sigma[name] = np.sqrt(se[:, col] ** 2 + misfit2)
            if dof == 0 and not np.any(n > 1):
                sigma[name] = np.full(n_bins, np.nan)  # no replicate and no redundancy: unknown
        if log_f_cov is not None:
            # log f: the spline's own covariance at each bin, plus the per-sample sigma there when the
            # weights are 1 / sigma^2 (the calibrator's): one calibration's focal errors share a common
            # scale (section 6.2) that averaging its keyframes does not remove, only averaging over
            # calibrations. Unit weights (sigma unknown, 1/w = 100%) add nothing.
            knots, cov, degree, fitted = log_f_cov
            B = design_matrix(z, knots, degree)
            fit_var = np.einsum("ij,jk,ik->i", B, cov, B)
            own2 = n / w
            known = own2 < 0.25
            per_sample2 = np.where(known, own2, 0.0) / len(cal_ids)
            # plus the samples' scatter about the curve beyond their own sigmas, each left out of the fit
            # (its leave-one-out residual): the zoom encoder's noise and an unlearned lag, which a frame
            # predicted from its own reading has as well, and the curve's error between samples
            # (pooled, and at least each bin's own where the samples are sparse)
            trusted = known & (robust > 0.5) & (leverage < 0.99)
            excess2 = np.zeros(n_bins)
            if np.sum(trusted) > 2:
                loo = (mean[:, 0] - fitted) / (1.0 - np.where(trusted, leverage, 0.0))
                own_excess = np.where(trusted, np.maximum(var[:, 0] + loo**2 - own2, 0.0), 0.0)
                pooled = np.sum((n * own_excess)[trusted]) / np.sum(n[trusted])
                excess2 = np.maximum(own_excess, pooled)
            if np.all(np.isfinite(fit_var)):
                sigma["log_f"] = np.sqrt(fit_var + per_sample2 + excess2)
        return _Fit(float(z.min()), float(z.max()), splines, constants, slopes, z, sigma, log_f_cov, offsets)

    def _fitted(self) -> _Fit:
        if self._fit is None:
            self._fit = self._refit()
        return self._fit

    def _evaluate(self, fit: _Fit, name: str, zoom: float) -> float:
        spline = fit.splines[name]
        if spline is None:
            return fit.constants[name]
        zc = min(max(zoom, fit.z_lo), fit.z_hi)
        value = float(spline(zc))
        if name == "log_f":  # linear extension of log f with the end slope
            value += fit.end_slopes[0] * (zoom - zc) if zoom < zc else fit.end_slopes[1] * (zoom - zc)
        return value

    def _between_samples(self, fit: _Fit, zoom: float) -> float:
        """1-sigma of log f for the curve between the two samples (bins) around zoom: a tenth of the change
        of log f across the gap at its middle, zero at the samples (the curve is known only where it was
        measured; a long gap, e.g. between the reference and the first keyframes of a fast zoom, can sag)."""
        z = fit.bin_z
        i = int(np.searchsorted(z, zoom))
        if i <= 0 or i >= len(z) or not z[i] > z[i - 1]:
            return 0.0
        a, b = float(z[i - 1]), float(z[i])
        change = abs(self._evaluate(fit, "log_f", b) - self._evaluate(fit, "log_f", a))
        return _GAP_FRACTION * change * 4.0 * (zoom - a) * (b - zoom) / (b - a) ** 2

    def predict_parameters(self, zoom: float, zoom_rate: float = 0.0) -> dict[str, float]:
        """f, cx, cy, k1, k2 and their 1-sigma (sigma_f in pixels), plus in_range, at an encoder value
        (and its rate of change in counts / s, which the learned encoder lag turns into a zoom shift)."""
        fit = self._fitted()
        if math.isfinite(zoom_rate):
            zoom = zoom + self.lag * zoom_rate
        out = {name: self._evaluate(fit, name, zoom) for name in QUANTITIES}
        out["f"] = math.exp(out.pop("log_f"))
        zc = min(max(zoom, fit.z_lo), fit.z_hi)
        sig = {name: float(np.interp(zc, fit.bin_z, s)) for name, s in fit.bin_sigma.items()}
        extrapolated = abs(self._evaluate(fit, "log_f", zoom) - self._evaluate(fit, "log_f", zc))
        sigma_log_f = math.hypot(sig["log_f"], self._between_samples(fit, zc))
        out["sigma_f"] = out["f"] * (sigma_log_f + 0.5 * extrapolated)
        out["sigma_cx"], out["sigma_cy"] = sig["cx"], sig["cy"]
        out["sigma_k1"], out["sigma_k2"] = sig["k1"], sig["k2"]
        lo, hi = self.covered_range() or (fit.z_lo, fit.z_hi)
        out["in_range"] = bool(lo <= zoom <= hi)
        return out

    def predict(self, zoom: float, zoom_rate: float = 0.0) -> ZoomPrediction:
        """K (square pixels, zero skew) and plumb_bob D at a zoom encoder value (and its rate, counts / s,
        see predict_parameters); ZoomModelError if empty."""
        p = self.predict_parameters(zoom, zoom_rate)
        K = intrinsic_matrix(p["f"], p["cx"], p["cy"])
        D = np.array([p["k1"], p["k2"], 0.0, 0.0, 0.0])
        return ZoomPrediction(K, D, float(p["sigma_f"]), bool(p["in_range"]))

    # ----------------------------------------------------------------------------------- persistence
    def to_dict(self) -> dict[str, Any]:
        bins = [
            {"calibration": int(c), "key": int(k), **dict(zip(_SUM_FIELDS, map(float, self._bins[(c, k)])))}
            for c, k in sorted(self._bins)
        ]
        live = [
            {
                "key": k if isinstance(k, int | str) else str(k),
                "rate": float(self._live_rate.get(k, 0.0)),
                **dict(zip(_SUM_FIELDS, map(float, row))),
            }
            for k, row in self._live.items()
        ]
        summary = []
        if not self.is_empty():
            for z in self._bin_table()[0]:
                p = self.predict_parameters(float(z))
                summary.append({"zoom": float(z), "f": p["f"], "cx": p["cx"], "cy": p["cy"], "k1": p["k1"]})
        return {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "settings": {
                "max_bins": self.max_bins,
                "bin_width": self.bin_width,
                "max_basis": self.max_basis,
                "smoothing": self.smoothing,
                "max_live": self.max_live,
                "huber": self.huber,
                "max_calibrations": self.max_calibrations,
                "calibration": self.calibration,  # the running calibration (its samples are the live ones)
                "estimate_lag": self.estimate_lag,
                "max_lag": self.max_lag,
                "lag": self.lag,  # s, learned encoder lag (live samples' zoom includes lag * rate)
            },
            "zoom_limits": None if self._zoom_limits is None else [float(v) for v in self._zoom_limits],
            "bins": bins,
            "live": live,  # the running calibration's keyframes (latest estimates), not yet committed
            "summary": summary,  # for humans; ignored on load (the model is refitted from the bins)
        }

    @classmethod
    def from_dict(cls, data: Any) -> ZoomModel:
        """Rebuild from to_dict() output; ZoomModelError on anything invalid."""
        if not isinstance(data, dict):
            raise ZoomModelError("zoom model file is not a mapping")
        if data.get("format") != FORMAT_NAME:
            raise ZoomModelError(f"not a zoom model file (format {data.get('format')!r})")
        if data.get("version") != FORMAT_VERSION:
            raise ZoomModelError(f"unsupported zoom model version {data.get('version')!r}")
        settings, bins = data.get("settings"), data.get("bins")
        if not isinstance(settings, dict) or not isinstance(bins, list):
            raise ZoomModelError("zoom model file lacks settings or bins")
        try:
            width = settings.get("bin_width")
            model = cls(
                max_bins=int(settings["max_bins"]),
                bin_width=None if width is None else float(width),
                max_basis=int(settings["max_basis"]),
                smoothing=float(settings["smoothing"]),
                max_live=int(settings.get("max_live", 256)),
                huber=float(settings.get("huber", 2.5)),
                max_calibrations=int(settings.get("max_calibrations", 8)),
                estimate_lag=bool(settings.get("estimate_lag", True)),
                max_lag=float(settings.get("max_lag", 0.25)),
            )
            model.calibration = int(settings.get("calibration", 0))
            model.lag = float(settings.get("lag", 0.0))
            if not (math.isfinite(model.lag) and abs(model.lag) <= max(model.max_lag, 0.0)):
                raise ZoomModelError(f"invalid lag {model.lag}")
            for entry in bins:
                row = np.array([float(entry[name]) for name in _SUM_FIELDS])
                key = (int(entry.get("calibration", 0)), int(entry["key"]))
                if not np.all(np.isfinite(row)) or row[0] < 1 or row[1] <= 0.0 or key in model._bins:
                    raise ZoomModelError(f"invalid zoom model bin {key}")
                model._bins[key] = row
            live = data.get("live") or []
            if not isinstance(live, list) or len(live) > max(model.max_live, 0):
                raise ZoomModelError("invalid live samples")
            for entry in live:
                row = np.array([float(entry[name]) for name in _SUM_FIELDS])
                key = entry["key"]
                if (
                    not np.all(np.isfinite(row))
                    or row[0] != 1.0
                    or row[1] <= 0.0
                    or not isinstance(key, int | str)
                    or key in model._live
                ):
                    raise ZoomModelError(f"invalid live sample {key!r}")
                rate = float(entry.get("rate", 0.0))
                if not math.isfinite(rate):
                    raise ZoomModelError(f"invalid live sample {key!r}")
                model._live[key], model._live_rate[key] = row, rate
        except (KeyError, TypeError, ValueError) as exc:
            raise ZoomModelError(f"invalid zoom model file: {exc}") from exc
        limits = data.get("zoom_limits")
        if model._bins:
            try:
                lo, hi = (float(v) for v in limits)
            except (TypeError, ValueError) as exc:
                raise ZoomModelError("invalid zoom_limits") from exc
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ZoomModelError("invalid zoom_limits")
            model._zoom_limits = (lo, hi)
        if model._bins and (model.bin_width is None or not model.bin_width > 0.0):
            raise ZoomModelError("invalid bin width")
        if len(model._bins) > model.max_bins:
            raise ZoomModelError("more bins than max_bins")
        if not model.is_empty():
            try:
                model._fitted()
            except (ValueError, np.linalg.LinAlgError) as exc:
                raise ZoomModelError(f"zoom model cannot be fitted: {exc}") from exc
        return model

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the model atomically (persist.atomic_file), after removing the temporary files of
        writers no longer running (a save killed half-way); a live writer's file is left alone."""
        path = Path(path)
        remove_stale_temporaries(path.parent)
        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ZoomModel:
        """Load a saved model; ZoomModelError (never another exception) if missing, corrupt or invalid."""
        try:
            text = Path(path).read_text(encoding="utf-8")
            data = yaml.safe_load(text)
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
            raise ZoomModelError(f"cannot read zoom model {path}: {exc}") from exc
        return cls.from_dict(data)

    @classmethod
    def load_or_new(cls, path: str | os.PathLike[str], **kwargs: Any) -> tuple[ZoomModel, str | None]:
        """The saved model, or a fresh one and the reason the saved one was not usable."""
        if not Path(path).exists():
            return cls(**kwargs), None
        try:
            return cls.load(path), None
        except ZoomModelError as exc:
            return cls(**kwargs), str(exc)

    # ----------------------------------------------------------------------------- ROS calibrations
    def export_camera_calibration_yaml(
        self,
        directory: str | os.PathLike[str],
        zoom_values: Iterable[float],
        width: int,
        height: int,
        camera_name: str,
    ) -> list[Path]:
        """Per-zoom calibration files in the camera_calibration_parsers YAML format (one per zoom)."""
        predictions = ((zoom, *self.predict(float(zoom))[:2]) for zoom in zoom_values)
        return write_camera_calibrations(directory, predictions, width, height, camera_name)


def fit_zoom_model(
    zooms: ArrayLike,
    Ks: ArrayLike,
    Ds: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    **kwargs: Any,
) -> ZoomModel:
    """Module-level ZoomModel.fit."""
    return ZoomModel.fit(zooms, Ks, Ds, weights, **kwargs)
