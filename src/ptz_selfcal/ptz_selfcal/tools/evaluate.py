"""`ptz-selfcal eval IN_BAG [--out-dir D] [--params FILE] [--no-run]`: run + comparison (DESIGN.md 7).

1. `ptz-selfcal run IN_BAG --out D/output_bag` (tools/run.py: the real nodes over DDS, lock-step),
   unless --no-run, in which case IN_BAG is an existing output bag of `run`.
2. Frames are the input images (header stamps); each gets the CameraInfo / FrameCalibration with the
   same stamp (coverage = fraction that got one).
3. Truth: the ground-truth CameraInfo (K, distortion) and JointState (pan, tilt) where the bag has
   them (synthetic bags); otherwise rotations from the encoders passed through in FrameCalibration
   (pan/tilt, the section 7 metric) and no intrinsics truth.
4. D/report.json, a printed table and D/focal.png, D/principal_point.png, D/pan_tilt.png.
5. report["figures"] (issue 15, from the ground truth; sim/metrics.py): the well-posed frame, the first
   calibrated frame (CALIBRATING or CONVERGED) and their times; focal, principal point and distortion
   errors over the frames after the warm-up and after the well-posed frame + 1 s, whichever is later;
   the share of CONVERGED frames more than 1 % off; the share of CONVERGED frames within 3 sigma_f; the
   run-level error over sigma (for coverage across seeds).
"""

from __future__ import annotations

import argparse
import io
import math
import re
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ptz_selfcal import topics
from ptz_selfcal.camera.distortion import DIVISION, PLUMB_BOB
from ptz_selfcal.camera.geometry import matrix_from_quaternion
from ptz_selfcal.nodes.conversions import STATUS_TO_MSG
from ptz_selfcal.sim import metrics
from ptz_selfcal.status import CALIBRATED, CalibrationStatus
from ptz_selfcal.tools.bagio import BagReader, deserialize, header_stamp_ns
from ptz_selfcal.tools.cli import CliError
from ptz_selfcal.tools.report import format_table, write_json, write_plots

# FrameCalibration.status values whose orientation is a calibrated estimate
_CALIBRATED = tuple(sorted(STATUS_TO_MSG[s] for s in CALIBRATED))
_CONVERGED = STATUS_TO_MSG[CalibrationStatus.CONVERGED]
CONVERGED_OFF = 0.01  # a CONVERGED frame further off than this is a broken promise (issue 15)
_IMAGE_TOPICS = tuple(topics.bag_topic(t) for t in (topics.IMAGE_COMPRESSED, topics.IMAGE_RAW))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("in_bag", help="input bag (or, with --no-run, an output bag of `ptz-selfcal run`)")
    parser.add_argument("--out-dir", default=None, help="report directory (default: eval_<bag name>)")
    parser.add_argument("--params", metavar="FILE", help="parameter YAML for the nodes (passed to run)")
    parser.add_argument("--no-run", action="store_true", help="evaluate IN_BAG as an existing output bag")
    parser.add_argument(
        "--input-bag",
        help="with --no-run: the input bag, for the image stamps (default: ground-truth stamps)",
    )
    parser.add_argument("--pair-stride", type=int, default=10, help="frame distance between rotation pairs")
    parser.add_argument("--pair-partners", type=int, default=10, help="partners per frame (stride multiples)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--quiet", action="store_true", help="no node output (the table is still printed)")
    parser.add_argument(
        "--deterministic",
        action="store_true",
        help="passed to run: each solve completes before the next frame",
    )
    parser.add_argument(
        "--with-images", action="store_true", help="passed to run: copy the input images into the output bag"
    )
    parser.add_argument("--run-arg", action="append", default=[], help=argparse.SUPPRESS)


# --------------------------------------------------------------------------------------------------
# Reading bags
# --------------------------------------------------------------------------------------------------
def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class BagData:
    image_stamps: list[int] = field(default_factory=list)
    camera_info: dict[int, Any] = field(default_factory=dict)
    camera_info_count: Counter = field(default_factory=Counter)
    frame_calibration: dict[int, Any] = field(default_factory=dict)
    gt_camera_info: dict[int, Any] = field(default_factory=dict)
    gt_joint_states: dict[int, Any] = field(default_factory=dict)
    reference: dict[int, int] = field(default_factory=dict)  # frame stamp -> reference stamp
    diagnostics: list[Any] = field(default_factory=list)
    topics: dict[str, int] = field(default_factory=dict)


def read_output_bag(path: str | Path, data: BagData | None = None) -> BagData:
    data = data or BagData()
    wanted = {
        topics.bag_topic(topics.CAMERA_INFO),
        topics.bag_topic(topics.FRAME_CALIBRATION),
        topics.bag_topic(topics.GT_CAMERA_INFO),
        topics.bag_topic(topics.GT_JOINT_STATES),
        topics.bag_topic(topics.HOMOGRAPHY),
        topics.bag_topic(topics.DIAGNOSTICS),
        *_IMAGE_TOPICS,
    }
    with BagReader(path) as reader:
        found = {t.name: t for t in reader.topics()}
        data.topics.update({t.name: t.count for t in found.values()})
        names = [n for n in found if n in wanted or n.endswith(topics.DIAGNOSTICS)]
        for msg in reader.messages(names):
            if msg.topic in _IMAGE_TOPICS:
                stamp = header_stamp_ns(msg.raw)
                if stamp is not None:
                    data.image_stamps.append(stamp)
                continue
            m = deserialize(msg.raw, msg.msgtype)
            if msg.topic.endswith(topics.DIAGNOSTICS):
                data.diagnostics.append(m)
                continue
            stamp = _stamp_ns(m.header.stamp)
            if msg.topic == topics.bag_topic(topics.CAMERA_INFO):
                data.camera_info[stamp] = m
                data.camera_info_count[stamp] += 1
            elif msg.topic == topics.bag_topic(topics.FRAME_CALIBRATION):
                data.frame_calibration[stamp] = m
            elif msg.topic == topics.bag_topic(topics.GT_CAMERA_INFO):
                data.gt_camera_info[stamp] = m
            elif msg.topic == topics.bag_topic(topics.GT_JOINT_STATES):
                data.gt_joint_states[stamp] = m
            elif msg.topic == topics.bag_topic(topics.HOMOGRAPHY):
                data.reference[stamp] = _stamp_ns(m.reference_stamp)
    return data


def input_damage(path: str | Path) -> dict[str, Any] | None:
    """What a damaged input bag lost ({damage, unreadable_frames (None: unknown)}); None if it is sound."""
    with BagReader(path) as reader:
        if not reader.damage:
            return None
        names = [t.name for t in reader.topics() if t.name in _IMAGE_TOPICS]
        unread = [reader.unread(n) for n in names]
        return {
            "damage": reader.damage,
            "unreadable_frames": None if None in unread else sum(n or 0 for n in unread),
        }


def read_image_stamps(path: str | Path) -> list[int]:
    with BagReader(path) as reader:
        names = [t.name for t in reader.topics() if t.name in _IMAGE_TOPICS]
        if not names:
            raise CliError(f"{path}: no image topic ({', '.join(_IMAGE_TOPICS)})")
        out = []
        for msg in reader.messages(names):
            stamp = header_stamp_ns(msg.raw)
            if stamp is not None:
                out.append(stamp)
        return out


# --------------------------------------------------------------------------------------------------
# Comparison
# --------------------------------------------------------------------------------------------------
def _joint(msg: Any, name: str) -> float:
    names = list(msg.name)
    if name in names:
        i = names.index(name)
        if i < len(msg.position):
            return float(msg.position[i])
    return math.nan


def evaluate(
    data: BagData,
    pair_stride: int = 10,
    pair_partners: int = 10,
) -> tuple[dict, dict[str, np.ndarray]]:
    """The report dict and the per-frame series for the plots."""
    if data.image_stamps:
        frames = sorted(set(data.image_stamps))
        basis = "input images"
    elif data.gt_camera_info:
        frames = sorted(data.gt_camera_info)
        basis = "ground-truth camera_info (one per input image)"
    elif data.gt_joint_states:
        frames = sorted(data.gt_joint_states)
        basis = "ground-truth joint_states (one per input image)"
    else:
        frames = sorted(data.camera_info)
        basis = "output camera_info only (input frames unknown: coverage not meaningful)"
    n = len(frames)
    if n == 0:
        raise CliError("no frames to evaluate (no images, no ground truth, no CameraInfo)")
    warmup = metrics.warmup_frames(n)

    K_est = np.full((n, 3, 3), np.nan)
    D_est = np.full((n, 5), np.nan)
    status = np.full(n, -1)
    sigma_f = np.full(n, np.nan)
    R_est = np.full((n, 3, 3), np.nan)
    enc = np.full((n, 2), np.nan)
    K_true = np.full((n, 3, 3), np.nan)
    dist_true: list[tuple[str, Any, Any] | None] = [None] * n
    dist_est: list[tuple[str, Any, Any] | None] = [None] * n
    pt_true = np.full((n, 2), np.nan)
    segment = np.full(n, -1, dtype=np.int64)
    width = height = 0
    for i, stamp in enumerate(frames):
        info = data.camera_info.get(stamp)
        if info is not None:
            K_est[i] = np.asarray(info.k, dtype=float).reshape(3, 3)
            d = np.zeros(5)
            d[: min(5, len(info.d))] = np.asarray(info.d, dtype=float)[:5]
            D_est[i] = d
            width, height = int(info.width) or width, int(info.height) or height
        fc = data.frame_calibration.get(stamp)
        if fc is not None:
            status[i] = int(fc.status)
            sigma_f[i] = float(fc.sigma_f)
            q = np.array([fc.orientation.x, fc.orientation.y, fc.orientation.z, fc.orientation.w])
            if status[i] in _CALIBRATED and abs(np.linalg.norm(q) - 1.0) < 1e-3:
                R_est[i] = matrix_from_quaternion(q)
            if fc.encoders.valid:
                enc[i] = (fc.encoders.pan, fc.encoders.tilt)
        gt = data.gt_camera_info.get(stamp)
        if gt is not None:
            K_true[i] = np.asarray(gt.k, dtype=float).reshape(3, 3)
            width, height = int(gt.width) or width, int(gt.height) or height
            if gt.distortion_model == DIVISION:
                dist_true[i] = (DIVISION, [float(gt.d[0])], K_true[i])
            else:
                dist_true[i] = (PLUMB_BOB, list(gt.d) or [0.0] * 5, K_true[i])
        if info is not None:
            dist_est[i] = (PLUMB_BOB, D_est[i], K_est[i])
        js = data.gt_joint_states.get(stamp)
        if js is not None:
            pt_true[i] = (_joint(js, "pan"), _joint(js, "tilt"))
        segment[i] = data.reference.get(stamp, 0)

    have_k_truth = bool(np.isfinite(K_true).all(axis=(1, 2)).any())
    if np.isfinite(pt_true).all(axis=1).any():
        rot_source, pan_tilt_ref = "ground truth", pt_true
    elif np.isfinite(enc).all(axis=1).any():
        rot_source, pan_tilt_ref = "encoders", enc
    else:
        rot_source, pan_tilt_ref = "none", pt_true
    R_ref = np.full((n, 3, 3), np.nan)
    ok_ref = np.isfinite(pan_tilt_ref).all(axis=1)
    if ok_ref.any():
        R_ref[ok_ref] = metrics.rotations_from_encoders(pan_tilt_ref[ok_ref, 0], pan_tilt_ref[ok_ref, 1])

    report: dict[str, Any] = {
        "frames": {
            "input": n,
            "basis": basis,
            "calibrated": int(np.isin(status, _CALIBRATED).sum()),
            "with_camera_info": int(np.isfinite(K_est).all(axis=(1, 2)).sum()),
            "duplicate_camera_info": int(sum(c - 1 for c in data.camera_info_count.values() if c > 1)),
            "warmup": warmup,
        },
        "coverage": metrics.coverage(frames, list(data.camera_info)),
        "truth": {"intrinsics": "ground truth" if have_k_truth else "none", "rotations": rot_source},
        "image_size": [width, height],
        "metrics": {},
        "status_counts": {str(s): int((status == STATUS_TO_MSG[s]).sum()) for s in CalibrationStatus},
    }
    report["status_counts"]["NO_OUTPUT"] = int((status < 0).sum())
    m = report["metrics"]
    focal = principal_point = distortion = np.full(n, np.nan)
    if have_k_truth:
        focal = metrics.focal_errors(K_est[:, 0, 0], K_true[:, 0, 0])
        principal_point = metrics.principal_point_errors(K_est[:, :2, 2], K_true[:, :2, 2])
        m["focal_error"] = metrics.summarise_split(focal, warmup)
        m["principal_point_error_px"] = metrics.summarise_split(principal_point, warmup)
        if width > 0 and height > 0:
            distortion = metrics.distortion_errors(dist_est, dist_true, width, height)
            m["distortion_error_px"] = metrics.summarise_split(distortion, warmup)
    valid_rot = np.isfinite(R_est).all(axis=(1, 2)) & np.isfinite(R_ref).all(axis=(1, 2))
    pairs = metrics.frame_pairs(n, pair_stride, pair_partners, valid=valid_rot, segments=segment)
    if len(pairs):
        errors = np.degrees(metrics.pairwise_rotation_errors(R_est, R_ref, pairs))
        m["rotation_error_deg"] = metrics.summarise_pairs(errors, pairs, warmup)
        m["rotation_error_deg"]["pairs"] = {
            "stride": pair_stride,
            "partners": pair_partners,
            "count": len(pairs),
        }
    report["frames"]["with_orientation"] = int(valid_rot.sum())
    times = (np.asarray(frames, dtype=np.int64) - frames[0]) * 1e-9
    report["figures"] = figures(
        times, status, sigma_f, K_est[:, 0, 0], K_true[:, 0, 0], R_ref, warmup,
        {
            "focal_error": focal,
            "principal_point_error_px": principal_point,
            "distortion_error_px": distortion,
        },
    )  # fmt: skip
    report["figures"]["rotation_truth"] = rot_source

    # pan/tilt path: estimated orientation aligned (per tracking reference) to the truth
    pan_tilt_est = np.full((n, 2), np.nan)
    for seg in np.unique(segment[valid_rot]) if valid_rot.any() else []:
        sel = valid_rot & (segment == seg)
        A = metrics.align_rotations(R_est[sel], R_ref[sel])
        pan_tilt_est[sel] = metrics.pan_tilt_path(np.einsum("nij,jk->nik", R_est[sel], A))
    series = {
        "frame": np.arange(n),
        "f_est": K_est[:, 0, 0],
        "f_true": K_true[:, 0, 0],
        "cx_est": K_est[:, 0, 2],
        "cy_est": K_est[:, 1, 2],
        "cx_true": K_true[:, 0, 2],
        "cy_true": K_true[:, 1, 2],
        "pan_est": pan_tilt_est[:, 0],
        "tilt_est": pan_tilt_est[:, 1],
        "pan_ref": np.degrees(pan_tilt_ref[:, 0]),
        "tilt_ref": np.degrees(pan_tilt_ref[:, 1]),
        "ref_label": rot_source,
        "warmup": warmup,
    }
    report["diagnostics"] = _last_calibrator_diagnostics(data.diagnostics)
    timing = report["diagnostics"].get("frame_ms_p95")
    report["performance"] = {
        "calibrator_frame_ms_p95": float(timing) if timing is not None else None,
    }
    return report, series


def figures(
    times: np.ndarray,
    status: np.ndarray,
    sigma_f: np.ndarray,
    f_est: np.ndarray,
    f_true: np.ndarray,
    R_true: np.ndarray,
    warmup: int,
    errors: dict[str, np.ndarray],
) -> dict[str, Any]:
    """Issue 15's figures of one run (sim/metrics.py defines each; None / NaN where undefined)."""
    well_posed = metrics.well_posed_frame(R_true)
    calibrated = metrics.first_frame(np.isin(status, _CALIBRATED))
    start = metrics.figure_start(times, warmup, well_posed)
    converged = status == _CONVERGED
    off = metrics.focal_errors(f_est, f_true) > CONVERGED_OFF
    n_conv = int(converged.sum())

    def at(i: int | None) -> float | None:
        return None if i is None else float(times[i])

    out: dict[str, Any] = {
        "well_posed_frame": well_posed,
        "well_posed_time_s": at(well_posed),
        "first_calibrated_frame": calibrated,
        "first_calibrated_time_s": at(calibrated),
        "frame_interval_s": float(np.median(np.diff(times))) if len(times) > 1 else None,
        "from_frame": start,
        "from_time_s": at(start) if start < len(times) else None,
        **{key: metrics.summarise(v[start:]) for key, v in errors.items()},
        "converged_frames": n_conv,
        "converged_off_1pct": int((converged & off).sum()),
        "converged_off_1pct_share": float((converged & off).sum() / n_conv) if n_conv else None,
        "sigma3_coverage": metrics.sigma_coverage(f_est, f_true, sigma_f, converged),
        "run_level": metrics.run_level_error(
            f_est, f_true, sigma_f, converged & (np.arange(len(times)) >= start)
        ),
    }
    return out


def format_figures(report: dict) -> str:
    """Issue 15's figures as lines under the metrics table."""
    fig = report.get("figures") or {}
    if not fig:
        return ""

    def frame(key: str) -> str:
        i, t = fig.get(f"{key}_frame"), fig.get(f"{key}_time_s")
        return "never" if i is None else f"frame {i} ({t:.2f} s)"

    def stat(key: str, name: str, scale: float = 1.0, digits: int = 2) -> str:
        entry = fig.get(key) or {}
        return f"{name} {_num(entry.get('median'), scale, digits)} / {_num(entry.get('p90'), scale, digits)}"

    run = fig.get("run_level") or {}
    share = fig.get("converged_off_1pct_share")
    return "\n".join(
        [
            f"well posed: {frame('well_posed')}; first calibrated: {frame('first_calibrated')}",
            f"from frame {fig.get('from_frame')} (median / p90): "
            + ", ".join(
                [
                    stat("focal_error", "focal %", 100.0, 3),
                    stat("principal_point_error_px", "pp px"),
                    stat("distortion_error_px", "distortion px"),
                ]
            ),
            f"CONVERGED {fig.get('converged_frames', 0)}, "
            f"of them > 1 % off {fig.get('converged_off_1pct', 0)}"
            + ("" if share is None else f" ({100.0 * share:.1f} %)")
            + f"; within 3 sigma_f {_num(fig.get('sigma3_coverage'), 100.0, 1)} %; run-level error "
            f"{_num(run.get('error'), 100.0, 3)} % = {_num(run.get('z'), 1.0, 2)} sigma",
        ]
    )


def _num(value: Any, scale: float, digits: int) -> str:
    if value is None or not np.isfinite(value):
        return "n/a"
    return f"{value * scale:.{digits}f}"


def _last_calibrator_diagnostics(arrays: list[Any]) -> dict[str, Any]:
    for array in reversed(arrays):
        for status in array.status:
            if status.name.endswith("calibrator"):
                out: dict[str, Any] = {}
                for kv in status.values:
                    try:
                        out[kv.key] = float(kv.value)
                    except ValueError:
                        out[kv.key] = kv.value
                return out
    return {}


# --------------------------------------------------------------------------------------------------
# The command
# --------------------------------------------------------------------------------------------------
class _Tee(io.TextIOBase):
    """Pass text through to a stream and keep a copy (to read `run`'s summary line)."""

    def __init__(self, stream: Any) -> None:
        self.stream, self.parts = stream, []

    def write(self, text: str) -> int:
        self.parts.append(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()

    def fileno(self) -> int:
        return self.stream.fileno()


def run_pipeline(in_bag: Path, out_bag: Path, params: str | None, quiet: bool, extra: list[str]) -> dict:
    """`ptz-selfcal run` through its own parser and function; returns wall time and its summary."""
    from ptz_selfcal.tools import run as run_tool

    parser = argparse.ArgumentParser(prog="ptz-selfcal run")
    run_tool.add_arguments(parser)
    argv = [str(in_bag), "--out", str(out_bag), *extra]
    if params:
        argv += ["--params", params]
    if quiet:
        argv.append("--quiet")
    args = parser.parse_args(argv)
    tee = _Tee(sys.stderr)
    old, sys.stderr = sys.stderr, tee
    start = time.monotonic()
    try:
        status = run_tool.run(args)
    finally:
        sys.stderr = old
    wall = time.monotonic() - start
    if status:
        raise CliError(f"run failed with status {status}")
    text = "".join(tee.parts)
    # the summary line ("run: N/M images got a CameraInfo ... X frames/s ...") is the last rate printed
    rates = re.findall(r"got a CameraInfo.*?([\d.]+) frames/s", text)
    return {"wall_s": wall, "throughput_fps": float(rates[-1]) if rates else None}


def run(args: argparse.Namespace, mosaic: Callable[..., dict] | None = None) -> int:
    in_bag = Path(args.in_bag)
    out_dir = Path(args.out_dir or f"eval_{in_bag.resolve().name}")
    out_dir.mkdir(parents=True, exist_ok=True)
    run_info: dict[str, Any] = {}
    if args.no_run:
        output_bag = in_bag
        data = BagData()
        if args.input_bag:
            data.image_stamps = read_image_stamps(args.input_bag)
        data = read_output_bag(output_bag, data)
    else:
        output_bag = out_dir / "output_bag"
        if output_bag.exists():
            raise CliError(f"{output_bag}: already exists (remove it or choose another --out-dir)")
        run_args = [
            *args.run_arg,
            *(["--deterministic"] if args.deterministic else []),
            *(["--with-images"] if args.with_images else []),
        ]
        run_info = run_pipeline(in_bag, output_bag, args.params, args.quiet, run_args)
        data = BagData(image_stamps=read_image_stamps(in_bag))
        data = read_output_bag(output_bag, data)
    report, series = evaluate(data, args.pair_stride, args.pair_partners)
    report["input_bag"] = str(in_bag if not args.no_run else (args.input_bag or ""))
    report["output_bag"] = str(output_bag)
    source = args.input_bag if args.no_run else in_bag
    damage = input_damage(source) if source else None
    if damage:
        report["frames"]["unreadable_in_input"] = damage["unreadable_frames"]
        report["input_damage"] = damage["damage"]
    if run_info:
        frames = report["frames"]["input"]
        report["performance"]["run_wall_s"] = run_info["wall_s"]
        # run's own figure (frames over the replay, start-up excluded) when it printed one
        report["performance"]["run_throughput_fps"] = (
            run_info["throughput_fps"] or frames / run_info["wall_s"]
        )
        report["performance"]["run_frames_per_wall_s"] = frames / run_info["wall_s"]
    plots = [] if args.no_plots else [str(p) for p in write_plots(series, out_dir)]
    report["plots"] = plots
    if mosaic is not None and not args.no_plots:  # a picture of the run too (tools/eval_command.py)
        report["mosaic"] = mosaic(data, output_bag, Path(source) if source else output_bag, out_dir)
    path = write_json(report, out_dir / "report.json")
    print(format_table(report))
    if report.get("figures"):
        print(format_figures(report))
    if damage:
        lost = damage["unreadable_frames"]
        count = "an unknown number of" if lost is None else str(lost)
        print(f"input bag damaged: {count} frames unreadable, the rest evaluated ({damage['damage']})")
    print(f"wrote {path}" + (f" and {len(plots)} plots in {out_dir}" if plots else ""))
    return 0
