"""Issue 16 "Measure": the real-video nuisances, each alone and all together, with the shipped defaults.

    ros2_ws/venv/bin/python benchmarks/real_video.py [--panoramas examplepano,building] [--seeds 0,1]
        [--cases moving_objects,...] [--frames 150] [--size 960x540] [--work-dir /tmp/real_video]
        [--opencv-cases none,all] [--quick] [--out FILE]

Every case is a `ptz-selfcal synth` bag (a sweep with zoom 1x -> 2.5x, pan +-30 deg peaking at 30 deg/s,
25 frames/s) with one nuisance of sim/nuisances.py switched on by its synth option (CASES below), or all
of them but the rolling shutter, beside the same bag without it ("none": same panorama, seed and motion).
Each bag is run as a new user would: `ptz-selfcal eval BAG --out-dir D --quiet --no-plots` (the real
nodes, the shipped config, no parameter file), and its report gives, after the first 10 % of frames:
focal error median and p90, principal point error median, pairwise rotation error median, the share of
CONVERGED frames more than 1 % off, the statuses, the pipeline's frames/s; the tracker's diagnostics give
its own frames/s. Where the ground-truth moving mask exists, the keyframe links the tracker published
(what reaches the keyframe bundle adjustment) are looked up in it: the share of their inliers with an end
on a moving object, beside the share of the keyframes' area the objects cover. A figure that cannot be
formed is printed "n/a" with the reason.

OpenCV's stitching calibration (benchmarks/opencv_peer.py, SIFT) sees every 5th frame of the
--opencv-cases bags and is evaluated on all of them (a batch method has no warm-up); its results are cached
for byte-identical frames under --work-dir as benchmarks/peers.py does. Bags, reports and the load
average around each eval are cached in --work-dir under their case name (a cached report is reused:
delete it after a code change).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import peers

import ptz_selfcal
from ptz_selfcal import topics
from ptz_selfcal.nodes.conversions import stamp_to_ns
from ptz_selfcal.tools.bagio import BagReader, deserialize

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).with_name("ptz-selfcal")
SHARED = Path(os.environ.get("PTZ_SHARED_DATA", "/work/shared/data")) / "panoramas"
PANORAMAS = {"examplepano": ROOT / "bags" / "source" / "examplepano.jpg", "building": SHARED / "building.jpg"}
FPS = 25.0
PAN_AMPLITUDE_DEG = 30.0
PAN_SPEED_DEG_S = 30.0  # the sweep's peak pan speed (the rolling-shutter target's 30 deg/s)
CASES: dict[str, list[str]] = {
    "none": [],
    "moving_objects": ["--moving-objects", "4"],
    "followed_target": ["--follow-target", "1.5", "4.5"],
    "exposure_steps": ["--exposure-steps", "2"],
    "vignetting": ["--vignetting", "0.4"],
    "low_light": ["--low-light", "--jpeg-quality", "60"],
    "rolling_shutter": ["--rolling-shutter", "0.03"],
}
CASES["all"] = [a for name in ("moving_objects", "followed_target", "exposure_steps", "vignetting",
                               "low_light") for a in CASES[name]]  # fmt: skip
READOUT_S = 0.03
# Issue 16's targets (focal in %, principal point in px at 1280x720 (3 px at 1920x1080), rotation in deg,
# CONVERGED frames more than 1 % off in %) for every case but the rolling shutter, which has its own.
TARGETS = {"focal_median": 0.2, "focal_p90": 0.6, "pp": 2.0, "rotation": 0.03, "off_1pct": 0.0}
RS_TARGETS = {"focal_median": 0.3, "focal_p90": 1.0, "pp": 3.0}
TRACKER_FPS_TARGET = 150.0  # at 1280x720
OPENCV_STRIDE = peers.STRIDE


def pan_cycles(frames: int) -> float:
    """Pan periods over the sequence for a sine sweep of PAN_AMPLITUDE_DEG peaking at PAN_SPEED_DEG_S."""
    period = (frames - 1) / FPS  # synth: first to last frame
    return PAN_SPEED_DEG_S * period / (2.0 * math.pi * PAN_AMPLITUDE_DEG)


def motion(frames: int) -> list[str]:
    return ["--fps", f"{FPS:g}", "--zoom-max", "2.5", "--pan-amplitude", f"{PAN_AMPLITUDE_DEG:g}",
            "--tilt-amplitude", "6", "--pan-cycles", f"{pan_cycles(frames):.4f}"]  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------------
def make_bag(work: Path, panorama: str, seed: int, case: str, frames: int, size: tuple[int, int]) -> Path:
    """The case's synth bag, named by its options' digest too (a changed motion is a new bag)."""
    options = ["--frames", str(frames), "--width", str(size[0]), "--height", str(size[1]), *motion(frames),
               "--seed", str(seed), *CASES[case]]  # fmt: skip
    digest = hashlib.sha256(repr(options).encode()).hexdigest()[:8]
    bag = work / f"{panorama}_{size[0]}x{size[1]}_{frames}_s{seed}_{case}_{digest}"
    if not bag.exists():
        cmd = [str(BIN), "synth", str(PANORAMAS[panorama]), str(bag), *options, "--quiet"]
        subprocess.run(cmd, check=True)
    return bag


def load_text() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def evaluate(bag: Path) -> tuple[dict[str, Any], dict[str, str]]:
    """The eval report of `bag` and the load averages at its start and end (cached beside it)."""
    out = bag.with_name(f"eval_{bag.name}")
    if not (out / "report.json").exists():
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        cmd = [str(BIN), "eval", str(bag), "--out-dir", str(out), "--no-plots", "--quiet"]
        start = load_text()
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode:
            sys.exit(f"eval {bag} failed:\n{proc.stderr[-2000:]}")
        (out / "load.json").write_text(json.dumps({"start": start, "end": load_text()}))
    load_file = out / "load.json"
    load = json.loads(load_file.read_text()) if load_file.exists() else {"start": "?", "end": "?"}
    return json.loads((out / "report.json").read_text()), load


# --------------------------------------------------------------------------------------------------
# Figures of one run
# --------------------------------------------------------------------------------------------------
@dataclass
class Row:
    """One case's figures; None where undefined, with the reason in `why`."""

    label: str
    values: dict[str, float | None]
    statuses: dict[str, int]
    load: str
    why: list[str] = field(default_factory=list)

    def get(self, key: str) -> float | None:
        return self.values.get(key)


def _finite(value: Any) -> float | None:
    return float(value) if value is not None and math.isfinite(float(value)) else None


def status_text(counts: dict[str, int]) -> str:
    short = {"INITIALISING": "INIT", "CALIBRATING": "CAL", "CONVERGED": "CONV", "DEGENERATE_MOTION": "DEGEN",
             "TRACKING_LOST": "LOST", "PREDICTED_FROM_ZOOM": "ZOOM", "MODEL_MISMATCH": "MISM",
             "NO_OUTPUT": "NONE"}  # fmt: skip
    return " ".join(f"{short.get(k, k)} {v}" for k, v in counts.items() if v)


def report_row(label: str, report: dict[str, Any], load: dict[str, str]) -> Row:
    m, f = report["metrics"], report["figures"]
    counts = {k: int(v) for k, v in report["status_counts"].items()}
    # a metric eval could not form (no truth, no frame pair with an orientation) is absent
    late = {
        key: m.get(key, {}).get("after_warmup", {}) for key in ("focal_error", "principal_point_error_px")
    }
    rot = m.get("rotation_error_deg", {}).get("after_warmup", {})
    share = f.get("converged_off_1pct_share")
    values = {
        "focal_median": _scaled(late["focal_error"].get("median"), 100.0),
        "focal_p90": _scaled(late["focal_error"].get("p90"), 100.0),
        "pp": _finite(late["principal_point_error_px"].get("median")),
        "rotation": _finite(rot.get("median")),
        "converged": float(f.get("converged_frames", counts.get("CONVERGED", 0))),
        "off_1pct": _scaled(share, 100.0),
        "run_fps": _finite(report["performance"].get("run_throughput_fps")),
    }
    row = Row(label, values, counts, load["end"])
    n_late = report["frames"]["input"] - report["frames"]["warmup"]
    if values["focal_median"] is None:
        row.why.append(f"focal: no CameraInfo after the first 10 % ({n_late} frames)")
    if values["rotation"] is None:
        row.why.append(
            "rot: no frame pair after the first 10 % with an orientation "
            f"({report['frames']['with_orientation']} of {report['frames']['input']} frames have one: "
            f"the rest are {_uncalibrated(counts)})"
        )
    if values["off_1pct"] is None:
        row.why.append("CONV >1 %: no CONVERGED frame")
    return row


def _scaled(value: Any, scale: float) -> float | None:
    v = _finite(value)
    return None if v is None else scale * v


def _uncalibrated(counts: dict[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in counts.items() if v and k not in ("CALIBRATING", "CONVERGED"))


def tracker_fps(out_bag: Path) -> float | None:
    """1000 / the tracker node's mean track time in its last diagnostics (its own frames/s, one core)."""
    mean_ms = None
    with BagReader(out_bag) as reader:
        for m in reader.messages([topics.DIAGNOSTICS]):
            for status in deserialize(m.raw, m.msgtype).status:
                if status.name.endswith("tracker"):
                    values = {kv.key: kv.value for kv in status.values}
                    mean_ms = float(values["track_ms_mean"]) if "track_ms_mean" in values else mean_ms
    return 1000.0 / mean_ms if mean_ms else None


def published_readout(out_bag: Path) -> tuple[float | None, str]:
    """(the rolling-shutter readout in s the last FrameCalibration carries, the tracker's last
    diagnostics on it: mode, estimate +- sigma over frames) of an eval's output bag."""
    readout, diagnostics = None, "no tracker diagnostics"
    with BagReader(out_bag) as reader:
        frame_topic = topics.bag_topic(topics.FRAME_CALIBRATION)
        for m in reader.messages([frame_topic, topics.DIAGNOSTICS]):
            msg = deserialize(m.raw, m.msgtype)
            if m.topic == frame_topic:
                readout = float(getattr(msg, "rolling_shutter_readout", math.nan))
                continue
            for status in msg.status:
                values = {kv.key: kv.value for kv in status.values}
                if status.name.endswith("tracker") and "rolling_shutter" in values:
                    in_use = values["rolling_shutter_readout_ms"]
                    diagnostics = f"tracker: {values['rolling_shutter']}, in use {in_use} ms"
                    if "rolling_shutter_estimate_ms" in values:
                        diagnostics += (f", estimate {values['rolling_shutter_estimate_ms']} +- "
                                        f"{values['rolling_shutter_sigma_ms']} ms over "
                                        f"{values['rolling_shutter_frames']} frames")  # fmt: skip
    return _finite(readout), diagnostics


@dataclass(frozen=True)
class MovingShare:
    """Keyframe-link inliers with an end on a moving object, and the moving share of the keyframes."""

    on_moving: int
    inliers: int
    links: int
    area: float  # mean share of a linked keyframe's pixels on moving objects

    @property
    def share(self) -> float:
        return self.on_moving / self.inliers if self.inliers else float("nan")


def moving_share(bag: Path, out_bag: Path) -> MovingShare | None:
    """The tracker's published keyframe links (full-resolution inlier pairs) looked up in the input's
    ground-truth moving masks at their keyframes' stamps; None when the bag has no mask topic."""
    mask_topic = topics.bag_topic(topics.GT_MOVING_MASK)
    links: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # (keyframe, other keyframe, points, other)
    keyframe_stamp: dict[int, int] = {}
    with BagReader(out_bag) as reader:
        wanted = [topics.bag_topic(topics.KEYFRAMES), topics.bag_topic(topics.HOMOGRAPHY)]
        for m in reader.messages(wanted):
            msg = deserialize(m.raw, m.msgtype)
            if m.topic == wanted[0]:
                keyframe_stamp[int(msg.keyframe_id)] = stamp_to_ns(msg.header.stamp)
                pts = np.asarray(msg.points, np.float32).reshape(-1, 2)
                other = np.asarray(msg.other_points, np.float32).reshape(-1, 2)
                links.append((int(msg.keyframe_id), int(msg.other_keyframe_id), pts, other))
            elif msg.state in (msg.NEW_KEYFRAME, msg.RELOCALISED):  # the frame is the new keyframe
                keyframe_stamp[int(msg.keyframe_id)] = stamp_to_ns(msg.header.stamp)
    with BagReader(bag) as reader:
        if mask_topic not in {t.name for t in reader.topics()}:
            return None
        needed = set(keyframe_stamp.values())
        masks = {}
        for m in reader.messages([mask_topic]):
            msg = deserialize(m.raw, m.msgtype)
            stamp = stamp_to_ns(msg.header.stamp)
            if stamp in needed:
                data = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)[:, : msg.width]
                masks[stamp] = data > 0

    def on_mask(keyframe: int, pts: np.ndarray) -> np.ndarray:
        mask = masks.get(keyframe_stamp.get(keyframe, -1))
        if mask is None:
            return np.zeros(len(pts), bool)
        h, w = mask.shape
        x = np.clip(np.rint(pts[:, 0]).astype(int), 0, w - 1)
        y = np.clip(np.rint(pts[:, 1]).astype(int), 0, h - 1)
        return mask[y, x]

    on_moving = inliers = 0
    areas = []
    for kf, other, pts, other_pts in links:
        on_moving += int((on_mask(kf, pts) | on_mask(other, other_pts)).sum())
        inliers += len(pts)
        areas += [float(masks[s].mean()) for s in (keyframe_stamp.get(k) for k in (kf, other)) if s in masks]
    return MovingShare(on_moving, inliers, len(links), float(np.mean(areas)) if areas else float("nan"))


def opencv_row(label: str, bag: Path, cache: Path) -> Row:
    """OpenCV's stitching calibration on every 5th frame of `bag` (benchmarks/peers.py's run and errors)."""
    frames, K, R = peers.read_synth_bag(bag)
    seq = peers.Sequence(bag.name, frames, np.arange(0, len(frames), OPENCV_STRIDE), K, R)
    result = peers.run_opencv(seq, "sift", cache)
    r = peers.evaluate(seq, result, None)
    values = {"focal_median": r.f_med, "focal_p90": r.f_p90, "pp": r.pp_med, "rotation": r.rot_med}
    row = Row(label, {k: _finite(v) for k, v in values.items()}, {}, load_text())
    row.values["opencv_ms"] = _finite(r.ms)
    row.why.append(f"OpenCV SIFT, every {OPENCV_STRIDE}th frame: {r.frames} calibrated, {r.ms:.0f} ms/frame "
                   f"wall{'; ' + r.note if r.note else ''}")  # fmt: skip
    return row


# --------------------------------------------------------------------------------------------------
# Printing
# --------------------------------------------------------------------------------------------------
COLUMNS = (  # key, header, format
    ("focal_median", "f med %", ".3f"),
    ("focal_p90", "f p90 %", ".3f"),
    ("pp", "pp px", ".2f"),
    ("rotation", "rot deg", ".4f"),
    ("converged", "CONV", ".0f"),
    ("off_1pct", ">1%CONV%", ".1f"),
    ("run_fps", "run fps", ".1f"),
    ("tracker_fps", "trk fps", ".0f"),
    ("moving_share", "mov in%", ".2f"),
    ("moving_area", "mov ar%", ".2f"),
)
LABEL = 36


def fmt(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def header() -> str:
    return f"{'case':<{LABEL}}" + "".join(f"{h:>9}" for _, h, _ in COLUMNS) + f"{'load':>15}  statuses"


def format_row(row: Row) -> str:
    cells = "".join(f"{fmt(row.get(k), spec):>9}" for k, _, spec in COLUMNS)
    line = f"{row.label:<{LABEL}}{cells}{row.load:>15}  {status_text(row.statuses)}".rstrip()
    return "\n".join([line, *(f"{'':<{LABEL}}n/a or note: {w}" for w in row.why)])


def median_of(rows: Iterable[Row], key: str) -> tuple[float | None, int]:
    values = [v for r in rows if (v := r.get(key)) is not None]
    return (float(np.median(values)) if values else None), len(values)


def target_lines(case: str, rows: list[Row], targets: dict[str, float]) -> list[str]:
    """Per target: the runs meeting it, and their median, for the case's rows with the nuisance."""
    parts = []
    for key, limit in targets.items():
        values = [r.get(key) for r in rows]
        met = sum(1 for v in values if v is not None and v <= limit)
        med, n = median_of(rows, key)
        na = len(values) - n
        parts.append(f"{key} <= {limit:g}: {met} of {len(values)} runs (median {fmt(med, '.3f')}"
                     + (f", n/a in {na}" if na else "") + ")")  # fmt: skip
    return [f"  {case}: " + "; ".join(parts)]


# --------------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------------
def run_case(work: Path, panorama: str, seed: int, case: str, frames: int, size: tuple[int, int]) -> Row:
    bag = make_bag(work, panorama, seed, case, frames, size)
    report, load = evaluate(bag)
    row = report_row(f"{panorama} s{seed} {case}", report, load)
    out_bag = Path(report["output_bag"])
    row.values["tracker_fps"] = tracker_fps(out_bag)
    if row.values["tracker_fps"] is None:
        row.why.append("trk fps: no tracker diagnostics with track_ms_mean in the output bag")
    readout, diagnostics = published_readout(out_bag)
    row.values["readout"] = readout
    published = fmt(_scaled(readout, 1e3), ".2f")
    row.why.append(f"rolling shutter: the last FrameCalibration's readout {published} ms; {diagnostics}")
    share = moving_share(bag, out_bag)
    if share is None:
        row.values["moving_share"] = row.values["moving_area"] = None
    else:
        row.values["moving_share"] = _finite(100.0 * share.share)
        row.values["moving_area"] = _finite(100.0 * share.area)
        row.why.append(
            f"moving objects: {share.on_moving} of {share.inliers} inliers of {share.links} keyframe links "
            "have an end on a moving object"
        )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--panoramas", default="examplepano,building")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--cases", default=",".join(c for c in CASES if c != "none"))
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--size", default="960x540")
    parser.add_argument("--work-dir", default="/tmp/real_video")
    parser.add_argument("--opencv-cases", default="none,all", help="cases with an OpenCV row ('' for none)")
    parser.add_argument("--opencv-seeds", default=None, help="seeds with OpenCV rows (default: the first)")
    parser.add_argument("--out", type=Path, default=None, help="also write the text here")
    parser.add_argument("--quick", action="store_true", help="examplepano, seed 0, 150 frames of 640x360")
    args = parser.parse_args()
    if args.quick:
        # 150 frames at 25 fps: the followed target's window (1.5 s to 4.5 s) fits in the sequence
        args.panoramas, args.seeds, args.frames, args.size = "examplepano", "0", 150, "640x360"
    size = (int(args.size.split("x")[0]), int(args.size.split("x")[1]))
    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    cases = [c for c in args.cases.split(",") if c and c != "none"]
    seeds = [int(s) for s in args.seeds.split(",")]
    opencv_seeds = {int(s) for s in (args.opencv_seeds or str(seeds[0])).split(",") if s}
    opencv_cases = {c for c in args.opencv_cases.split(",") if c}
    lines: list[str] = []

    def emit(text: str = "") -> None:
        lines.append(text)
        print(text, flush=True)

    cmd = " ".join(["ros2_ws/venv/bin/python benchmarks/real_video.py", *sys.argv[1:]])
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    emit(f"$ {cmd}")
    emit(f"{stamp}, {code_source()}; load average (1/5/15 min) at the start {load_text()} "
         f"(2 CPUs shared: frames/s depend on it; 'load' = at the end of each case's eval)")  # fmt: skip
    emit(f"bags: ptz-selfcal synth {' '.join(motion(args.frames))} --frames {args.frames} "
         f"--width {size[0]} --height {size[1]} (peak pan {PAN_SPEED_DEG_S:g} deg/s); shipped defaults, "
         f"no parameter file")  # fmt: skip
    emit(
        "figures after the first 10 % of frames: focal error median / p90 (%), principal point median (px), "
        "pairwise rotation median (deg); CONV = CONVERGED frames, >1%CONV% = their share > 1 % off; run fps ="
        " the pipeline's throughput; trk fps = 1000 / the tracker's mean track ms; mov in% = share of "
        "keyframe-link inliers with an end on a moving object (ground-truth mask), mov ar% = the moving "
        "objects' share of those keyframes' pixels; OpenCV rows: every 5th frame, all of them"
    )
    emit()
    emit(header())
    with_rows: dict[str, list[Row]] = {c: [] for c in cases}
    without_rows: list[Row] = []
    ocv_rows: dict[str, list[Row]] = {}
    for panorama in args.panoramas.split(","):
        for seed in seeds:
            ocv = opencv_cases if seed in opencv_seeds else set()
            plain = run_case(work, panorama, seed, "none", args.frames, size)
            plain.label += " (without)"
            without_rows.append(plain)
            emit(format_row(plain))
            if "none" in ocv:
                ocv_rows.setdefault("none", []).append(
                    _opencv(work, panorama, seed, "none", args, size, emit)
                )
            for case in cases:
                row = run_case(work, panorama, seed, case, args.frames, size)
                with_rows[case].append(row)
                emit(format_row(row))
                if case in ocv:
                    ocv_rows.setdefault(case, []).append(
                        _opencv(work, panorama, seed, case, args, size, emit)
                    )
    runs = len(without_rows)
    emit()
    emit(f"Median over the {runs} runs (panorama x seed), with the nuisance and without it:")
    emit(header())
    plain = summary_row("without any nuisance", without_rows)
    emit(format_row(plain))
    for case in cases:
        emit(format_row(summary_row(case, with_rows[case])))
    for case, rows in ocv_rows.items():
        emit(format_row(summary_row(f"OpenCV {case}", rows)))
    emit()
    emit("Targets (issue 16), with the nuisance:")
    for case in cases:
        if case != "rolling_shutter":
            for line in target_lines(case, with_rows[case], TARGETS):
                emit(line)
    if size != (1280, 720):
        emit(f"  principal point targets are at 1280x720 (2 px) and 1920x1080 (3 px): this run is "
             f"{size[0]}x{size[1]}")  # fmt: skip
    emit(tracker_line(size, [r for rs in with_rows.values() for r in rs] + without_rows))
    if "rolling_shutter" in cases:
        for line in rolling_shutter_lines(with_rows["rolling_shutter"]):
            emit(line)
    emit(
        "  moving objects' tracks reaching the calibration: the keyframe links' share above (mov in%); "
        "frame-to-keyframe homographies carry no points, their effect is in the rotation and focal figures"
    )
    emit(f"load average at the end {load_text()}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


def code_source() -> str:
    """The code the run measured: the work tree's commit, or the snapshot PYTHONPATH put first."""
    package = Path(ptz_selfcal.__file__).resolve().parents[2]
    if package.is_relative_to(ROOT):
        return peers.code_revision()
    revision = next((p / "REVISION" for p in package.parents if (p / "REVISION").exists()), None)
    commit = revision.read_text().strip() if revision is not None else "unknown commit"
    return f"code: ptz_selfcal from {package} (a snapshot of {commit}), benchmarks/ of the work tree"


def _opencv(
    work: Path, panorama: str, seed: int, case: str, args: argparse.Namespace, size: tuple[int, int],
    emit: Callable[[str], None],
) -> Row:  # fmt: skip
    bag = make_bag(work, panorama, seed, case, args.frames, size)
    row = opencv_row(f"  OpenCV {panorama} s{seed} {case}", bag, work / "opencv_cache")
    emit(format_row(row))
    return row


def summary_row(label: str, rows: list[Row]) -> Row:
    keys = {k for r in rows for k in r.values}
    values = {k: median_of(rows, k)[0] for k in keys}
    counts: dict[str, int] = {}
    for r in rows:
        for k, v in r.statuses.items():
            counts[k] = counts.get(k, 0) + v
    row = Row(label, values, counts, "")
    na = sorted(
        {w.split(":")[0] for r in rows for w in r.why if w.split(":")[0] in ("focal", "rot", "CONV >1 %")}
    )
    if na:
        row.why.append(f"n/a in some runs: {', '.join(na)} (see the runs above); statuses summed over runs")
    return row


def tracker_line(size: tuple[int, int], rows: list[Row]) -> str:
    med, n = median_of(rows, "tracker_fps")
    low = min((v for r in rows if (v := r.get("tracker_fps")) is not None), default=None)
    where = (
        "at 1280x720: the target's size"
        if size == (1280, 720)
        else f"at {size[0]}x{size[1]}, not the target's 1280x720 (run --size 1280x720)"
    )
    verdict = (
        "" if size != (1280, 720) or med is None else f": {'met' if low >= TRACKER_FPS_TARGET else 'not met'}"
    )
    return (
        f"  tracker throughput >= {TRACKER_FPS_TARGET:g} frames/s {where}: median {fmt(med, '.0f')}, "
        f"lowest {fmt(low, '.0f')} over {n} runs{verdict} (the node's wall time per track call beside the "
        "eval's other nodes; benchmarks/tracker.py measures the tracker alone)"
    )


def rolling_shutter_lines(rows: list[Row]) -> list[str]:
    lines = target_lines(f"rolling_shutter ({1000 * READOUT_S:g} ms readout, peak pan {PAN_SPEED_DEG_S:g} "
                         f"deg/s)", rows, RS_TARGETS)  # fmt: skip
    counts: dict[str, int] = {}
    for r in rows:
        for k, v in r.statuses.items():
            counts[k] = counts.get(k, 0) + v
    lines.append(f"  rolling_shutter statuses published (summed over runs): {status_text(counts)}")
    published = [r.get("readout") for r in rows]
    within = sum(1 for v in published if v is not None and abs(v - READOUT_S) <= 0.1 * READOUT_S)
    text = ", ".join(fmt(_scaled(v, 1e3), ".2f") for v in published)
    lines.append(
        f"  rolling_shutter readout time estimated within 10 %: {within} of {len(rows)} runs (the readout "
        f"the last FrameCalibration carries, ms: {text}; true {1e3 * READOUT_S:g} ms)"
    )
    return lines


if __name__ == "__main__":
    main()
