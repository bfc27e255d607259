"""Presentation of an evaluation (`ptz-selfcal eval`): report.json, the printed table, PNG plots.

The report is a plain dict built by tools/evaluate.py; this module only writes and draws it.
Plots follow the paper's figures 6 and 7: focal length against frame (estimate, truth), principal
point against frame, and the pan/tilt path (estimated orientation aligned to the truth's reference,
against the encoders or the ground truth).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from ptz_selfcal.persist.atomic_file import atomic_write_text


def _clean(value: Any) -> Any:
    """JSON-safe: numpy scalars/arrays to Python, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(report: dict, path: str | os.PathLike[str]) -> Path:
    """Write the report atomically (persist.atomic_file: temp file, fsync, rename)."""
    path = Path(path)
    atomic_write_text(path, json.dumps(_clean(report), indent=2, sort_keys=False) + "\n")
    return path


# --------------------------------------------------------------------------------------------------
# Table
# --------------------------------------------------------------------------------------------------
def _fmt(value: Any, scale: float = 1.0, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value * scale:.{digits}f}"


def format_table(report: dict) -> str:
    """The human-readable summary: one row per metric, columns all frames / after warm-up."""
    m = report.get("metrics", {})
    rows: list[tuple[str, str, str]] = []

    def stat_row(label: str, key: str, stat: str, scale: float = 1.0, digits: int = 3) -> None:
        entry = m.get(key)
        if not entry:
            rows.append((label, "n/a", "n/a"))
            return
        rows.append(
            (
                label,
                _fmt(entry["all"].get(stat), scale, digits),
                _fmt(entry["after_warmup"].get(stat), scale, digits),
            )
        )

    stat_row("focal error median (%)", "focal_error", "median", 100.0, 3)
    stat_row("focal error p90 (%)", "focal_error", "p90", 100.0, 3)
    stat_row("focal error rms (%)", "focal_error", "rms", 100.0, 3)
    stat_row("principal point error median (px)", "principal_point_error_px", "median", 1.0, 2)
    stat_row("principal point error p90 (px)", "principal_point_error_px", "p90", 1.0, 2)
    stat_row("pairwise rotation error median (deg)", "rotation_error_deg", "median", 1.0, 4)
    stat_row("pairwise rotation error p90 (deg)", "rotation_error_deg", "p90", 1.0, 4)
    stat_row("distortion error median (px)", "distortion_error_px", "median", 1.0, 2)
    stat_row("distortion error max (px)", "distortion_error_px", "max", 1.0, 2)
    frames = report.get("frames", {})
    lines = [
        f"ptz-selfcal eval: {report.get('output_bag', '')}",
        f"frames in {frames.get('input', 'n/a')}, calibrated {frames.get('calibrated', 'n/a')}, "
        f"warm-up {frames.get('warmup', 'n/a')}; coverage {_fmt(report.get('coverage'), 100.0, 1)}%",
        f"truth: intrinsics from {report.get('truth', {}).get('intrinsics', 'n/a')}, "
        f"rotations from {report.get('truth', {}).get('rotations', 'n/a')}",
    ]
    width = max(len(r[0]) for r in rows)
    lines.append(f"{'metric':<{width}}  {'all frames':>12}  {'after 10%':>12}")
    lines.append("-" * (width + 28))
    lines += [f"{label:<{width}}  {a:>12}  {b:>12}" for label, a, b in rows]
    counts = report.get("status_counts", {})
    if counts:
        lines.append("status: " + ", ".join(f"{k} {v}" for k, v in counts.items() if v))
    perf = report.get("performance", {})
    if perf:
        parts = []
        if perf.get("run_throughput_fps") is not None:
            parts.append(f"run throughput {_fmt(perf['run_throughput_fps'], 1.0, 1)} frames/s")
        if perf.get("calibrator_frame_ms_p95") is not None:
            parts.append(f"calibrator per-frame p95 {_fmt(perf['calibrator_frame_ms_p95'], 1.0, 2)} ms")
        if parts:
            lines.append("performance: " + ", ".join(parts))
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------------
def write_plots(series: dict[str, np.ndarray], out_dir: str | os.PathLike[str]) -> list[Path]:
    """focal.png, principal_point.png, pan_tilt.png from per-frame series (NaN = missing).

    series keys: frame, f_est, f_true, cx_est, cy_est, cx_true, cy_true, pan_est, tilt_est, pan_ref,
    tilt_ref (degrees), ref_label (str: "ground truth" or "encoders"), warmup (int).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    frame = np.asarray(series["frame"])
    warmup = int(series.get("warmup", 0))
    ref_label = str(series.get("ref_label", "truth"))
    written: list[Path] = []

    def finish(fig, name: str) -> None:
        path = out / name
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)

    def mark_warmup(ax) -> None:
        if warmup > 0:
            ax.axvspan(frame[0] if len(frame) else 0, warmup, color="0.9", zorder=0, label="warm-up (10%)")

    fig, ax = plt.subplots(figsize=(8, 4))
    mark_warmup(ax)
    if np.isfinite(series.get("f_true", np.array([np.nan]))).any():
        ax.plot(frame, series["f_true"], "k-", lw=2, label="truth")
    ax.plot(frame, series["f_est"], "r.", ms=3, label="estimate")
    ax.set_xlabel("frame")
    ax.set_ylabel("focal length (px)")
    ax.set_title("Focal length")
    ax.legend(loc="best")
    finish(fig, "focal.png")

    fig, axes = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for ax, key, name in ((axes[0], "cx", "u0"), (axes[1], "cy", "v0")):
        mark_warmup(ax)
        if np.isfinite(series.get(f"{key}_true", np.array([np.nan]))).any():
            ax.plot(frame, series[f"{key}_true"], "k-", lw=2, label="truth")
        ax.plot(frame, series[f"{key}_est"], "b.", ms=3, label="estimate")
        ax.set_ylabel(f"{name} (px)")
        ax.legend(loc="best")
    axes[0].set_title("Principal point")
    axes[1].set_xlabel("frame")
    finish(fig, "principal_point.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    ax = axes[0]
    mark_warmup(ax)
    ax.plot(frame, series["pan_ref"], "k-", lw=2, label=f"pan ({ref_label})")
    ax.plot(frame, series["tilt_ref"], "-", color="0.5", lw=2, label=f"tilt ({ref_label})")
    ax.plot(frame, series["pan_est"], "r.", ms=3, label="pan (estimate)")
    ax.plot(frame, series["tilt_est"], "b.", ms=3, label="tilt (estimate)")
    ax.set_xlabel("frame")
    ax.set_ylabel("angle (deg)")
    ax.set_title("Pan and tilt against frame")
    ax.legend(loc="best", fontsize=8)
    ax = axes[1]
    ax.plot(series["pan_ref"], series["tilt_ref"], "k-", lw=2, label=ref_label)
    ax.plot(series["pan_est"], series["tilt_est"], "r.", ms=3, label="estimate (aligned)")
    ax.set_xlabel("pan (deg)")
    ax.set_ylabel("tilt (deg)")
    ax.set_title("Pan/tilt path")
    ax.legend(loc="best", fontsize=8)
    finish(fig, "pan_tilt.png")
    return written
