"""Issue 7 "Measure": reliability of the node suite, the full-size versions of tests/reliability.

For each experiment it prints frames in, frames calibrated, frames skipped and why, peak memory (RSS of
each node process), latency percentiles and the time to recover:

1. Bad input: the catalogue of tests/reliability/test_bad_input.py (16k x 16k raw image, lying 16k header,
   16k JPEG, empty/undecodable/compressedDepth data, zero-size, partial/mismatched/+-inf/far-future
   encoders, duplicate/out-of-order/far-future image stamps) between good frames, three node processes.
2. Tracking loss: black frames, heavy blur, a scene cut, a 90 deg preset move at full zoom (rendered PTZ
   views with exact ground truth): statuses and focal error while lost, error before/after, recovery.
3. Overload: 1920x1080 JPEG at 60 frames/s (best effort, like a camera driver), latest-wins policy; per
   10 s block the latency p95, each stage's p95, the CPU of each node, of the feeder and of other jobs on
   the machine, and the tracker's map counters: whether the latency is bounded and what it follows.
4. Soak: --core-frames (default 100,000) through the calibrator core's per-frame path, and --graph-frames
   (default 20,000, 320x180 images) through the three node processes.
5. Restarts: kill -9 of each node during `ptz-selfcal launch` (state_dir, zoom model).

The experiments are the same code as the CI tests (tests/reliability/reliability_harness.py), larger.
Writes benchmarks/results/reliability.txt (and prints it). Usage:
    ros2_ws/venv/bin/python benchmarks/reliability.py [--core-frames 100000] [--graph-frames 20000]
        [--overload-seconds 30] [--overload-views 24 [240]]
        [--only bad_input tracking_loss overload core_soak graph_soak restarts]
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import struct
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ptz_selfcal.status import CALIBRATED, TrackingState

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests"), str(ROOT / "tests" / "reliability")]

import reliability_harness as rh  # noqa: E402
from conftest import NodeProcess, cli_command  # noqa: E402

EXPERIMENTS = ("bad_input", "tracking_loss", "overload", "core_soak", "graph_soak", "restarts")


def pct(values, q: float, scale: float = 1e3) -> str:
    return f"{np.percentile(np.asarray(values, float), q) * scale:.0f}" if len(values) else "nan"


def latency_line(values) -> str:
    return (
        f"latency (image sent -> its CameraInfo) p50 {pct(values, 50)} ms, p95 {pct(values, 95)} ms, "
        f"p99 {pct(values, 99)} ms, max {pct(values, 100)} ms"
    )


class Domain:
    """A fresh ROS domain (and LOCALHOST discovery) for each experiment: no stale endpoints."""

    def __init__(self, first: int = 190) -> None:
        self.next = first

    @contextlib.contextmanager
    def __call__(self) -> Iterator[dict[str, str]]:
        domain = str(self.next)
        self.next += 1
        os.environ.update(ROS_DOMAIN_ID=domain, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "RCUTILS_COLORIZED_OUTPUT": "0"}
        yield env


@contextlib.contextmanager
def graph(env: dict[str, str], workdir: Path, **kwargs) -> Iterator[dict[str, NodeProcess]]:
    procs: list[NodeProcess] = []

    def start(cmd, environment, name):
        proc = NodeProcess(cmd, environment, workdir, f"{name}-{len(procs)}")
        procs.append(proc)
        return proc

    nodes = rh.start_graph(start, env, **kwargs)
    try:
        yield nodes
    finally:
        for proc in procs:
            if proc.alive():
                proc.stop(timeout=20.0)


class Sampler:
    """Peak RSS of node processes: the kernel's high-water mark (VmHWM), read while they are alive."""

    def __init__(self, pids: dict[str, int]) -> None:
        self.pids = pids
        self.peak = dict.fromkeys(pids, 0.0)
        self.now = dict.fromkeys(pids, math.nan)

    def sample(self) -> None:
        for name, pid in self.pids.items():
            value = rh.rss_mb(pid, "VmHWM")
            if math.isfinite(value):
                self.peak[name] = max(self.peak[name], value)
            self.now[name] = rh.rss_mb(pid)

    def line(self) -> str:
        return "peak RSS " + ", ".join(f"{n} {v:.0f} MB" for n, v in self.peak.items())


def skipped_line(diag: dict[str, str]) -> str:
    kinds = {
        k: v
        for k, v in diag.items()
        if k.startswith(("skipped_", "encoder_", "image_stamp", "dropped", "input_"))
    }
    kinds = {k: v for k, v in kinds.items() if k not in ("encoder_messages",) and v not in ("0", "0.0")}
    return ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())) or "none"


# --------------------------------------------------------------------------------------------------------
def bad_input(domain: Domain, work: Path, lines: list[str]) -> None:
    with domain() as env, graph(env, work) as nodes:
        feeder = rh.Feeder("bench_bad_input")
        sampler = Sampler({n: p.pid for n, p in nodes.items()})
        try:
            feeder.wait_connected()
            sampler.sample()
            peak_before = dict(sampler.peak)
            start = time.monotonic()
            _views, good, refused = rh.bad_input_catalogue(feeder, 640, 360, n=120)
            feeder.spin(3.0, lambda: all(ns in feeder.infos for ns in good))
            sampler.sample()
            feeder.spin(1.0)
            wall = time.monotonic() - start
            d = feeder.diagnostics
            once = sum(1 for ns in good if len(feeder.infos.get(ns, [])) == 1)
            lat = [feeder.info_arrival[ns] - feeder.sent[ns] for ns in good if ns in feeder.info_arrival]
            lines += [
                "",
                "1. Bad input catalogue (three node processes, 640x360 good frames in lock-step)",
                f"   frames in {d['frame_ingest']['frames_in']} ({len(good)} good, {len(refused)} refused, "
                f"1 duplicate stamp), frames calibrated {len(feeder.infos)} (good frames with exactly one "
                f"CameraInfo: {once}/{len(good)}; CameraInfo for a refused frame: "
                f"{len(set(refused) & set(feeder.infos))}); {wall:.0f} s",
                f"   skipped and why (frame_ingest /diagnostics): {skipped_line(d['frame_ingest'])}",
                f"   {sampler.line()} (kernel high-water mark over the catalogue, which holds a real 256 MB "
                f"16k x 16k image; frame_ingest peak {sampler.peak['frame_ingest']:.0f} MB = "
                f"{peak_before['frame_ingest']:.0f} MB before the catalogue + "
                f"{(sampler.peak['frame_ingest'] - peak_before['frame_ingest']) / 256:.2f} x 256 MB; RSS at "
                f"the end {sampler.now['frame_ingest']:.0f} MB)",
                f"   {huge_image_copies()}",
                f"   {ingest_cost()}",
                f"   {latency_line(lat)}",
                "   nodes alive at the end: " + ", ".join(f"{n} {p.alive()}" for n, p in nodes.items()),
            ]
        finally:
            feeder.close()


def ingest_cost(repeats: int = 40) -> str:
    """Per-frame time of frame_ingest's conversion of a received serialized image to the working mono8:
    rclpy's deserialisation + conversion (the node's path before it subscribed raw) against the raw path
    (the take's copy of the serialized message, its header read in place, conversion). Median over
    `repeats` of the thread's CPU time (waiting for a CPU not counted), both paths interleaved so that load
    from other processes hits both alike."""
    import cv2
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CompressedImage, Image

    from ptz_selfcal.nodes.conversions import (
        compressed_to_working,
        image_to_working,
        parse_serialized_image,
    )

    rng = np.random.default_rng(7)
    cases = []
    for width, height, encoding in ((1920, 1080, "bgr8"), (640, 360, "mono8")):
        channels = 3 if encoding == "bgr8" else 1
        pixels = rng.integers(0, 256, (height, width, channels), np.uint8)
        msg = Image(height=height, width=width, encoding=encoding, step=width * channels)
        msg.data = pixels.tobytes()
        cases.append((f"{width}x{height} {encoding}", Image, msg, image_to_working))
    jpeg = cv2.imencode(".jpg", rh.render(rh.View(0.0, 0.0, 1600.0, 0.0), 1920, 1080))[1].tobytes()
    cases.append(("1920x1080 JPEG", CompressedImage, CompressedImage(format="jpeg", data=jpeg),
                  compressed_to_working))  # fmt: skip
    parts = []
    for label, msg_type, msg, convert in cases:
        data = serialize_message(msg)
        compressed = msg_type is CompressedImage
        before, after = [], []
        for _ in range(repeats):
            t0 = time.thread_time()
            convert(deserialize_message(data, msg_type), 640)
            t1 = time.thread_time()
            convert(parse_serialized_image(bytes(bytearray(data)), compressed), 640)
            t2 = time.thread_time()
            before.append(t1 - t0)
            after.append(t2 - t1)
        parts.append(f"{label} {np.median(before) * 1e3:.2f} -> {np.median(after) * 1e3:.2f} ms")
    return (
        "ingest CPU per frame, serialized image -> working mono8, deserialised -> raw subscription read in "
        + ("place: " + ", ".join(parts))
    )


def huge_image_copies() -> str:
    """Peak memory (this process's high-water mark, reset before each) of taking a serialized 256 MB
    16k x 16k Image to frame_ingest's size check: rclpy's deserialisation (the node's path before it
    subscribed raw) against reading it in place."""
    import array

    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image

    from ptz_selfcal.nodes.conversions import FrameError, image_to_working, parse_serialized_image

    side = 16384
    msg = Image(height=side, width=side, encoding="mono8", step=side)
    pixels = array.array("B")
    pixels.frombytes(bytes(side * side))
    msg.data = pixels
    data = serialize_message(msg)
    del msg, pixels
    growth = {}
    for name, read in (
        ("deserialised", lambda: deserialize_message(data, Image)),
        ("read in place", lambda: parse_serialized_image(data)),
    ):
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
        base = rh.rss_mb(os.getpid())
        image = read()
        with contextlib.suppress(FrameError):  # refused as too large: the point of the check
            image_to_working(image, 640)
        del image
        growth[name] = rh.rss_mb(os.getpid(), "VmHWM") - base
    return (
        f"the serialized 256 MB image taken to the size check (in this process): deserialised +"
        f"{growth['deserialised']:.0f} MB peak, read in place +{growth['read in place']:.0f} MB"
    )


def tracking_loss(domain: Domain, work: Path, lines: list[str]) -> None:
    with domain() as env, graph(env, work) as nodes:
        feeder = rh.Feeder("bench_loss")
        sampler = Sampler({n: p.pid for n, p in nodes.items()})
        try:
            feeder.wait_connected()
            disturbances = ("black", "blur", "scene_cut", "preset_90deg", "none", "none", "none")
            r = rh.tracking_loss_scenario(feeder, 640, 360, warmup=150, window=20, bad=15,
                                          disturbances=disturbances)  # fmt: skip
            sampler.sample()
            stamps = r["_log"]["stamps"]
            lat = [feeder.info_arrival[ns] - feeder.sent[ns] for ns in stamps if ns in feeder.info_arrival]
            lines += [
                "",
                "2. Tracking loss (three node processes, 640x360 rendered views, zoom 1x-2x, disturbances at "
                "full zoom 2x; each between two passes of the same 20 views; then 3 undisturbed passes: the "
                "control)",
                f"   frames in {len(stamps)}, frames calibrated (one CameraInfo each) "
                f"{sum(1 for ns in stamps if len(feeder.infos.get(ns, [])) == 1)}; {sampler.line()}",
                f"   {latency_line(lat)}",
                f"   {'disturbance':<14} {'frames':>6}  {'statuses while lost':<34} {'f err lost %':>12} "
                f"{'before %':>9} {'after %':>8} {'ok<=1.1x':>8} {'recover':>8}",
            ]
            for name in ("black", "blur", "scene_cut", "preset_90deg", "none", "none_2", "none_3"):
                x = r[name]
                counts: dict[str, int] = {}
                for s in x["statuses"]:
                    counts[s] = counts.get(s, 0) + 1
                text = ", ".join(f"{k} {v}" for k, v in counts.items()) or "-"
                ok = x["after"] <= 1.1 * x["before"]
                lost_max = f"{100 * max(x['errors']):>12.3f}" if x["errors"] else f"{'-':>12}"
                rec = (
                    f"{x['recovery_frames']} fr/{x['recovery_s'] * 1e3:.0f} ms"
                    if x["recovery_frames"] is not None
                    else "never"
                )
                lines.append(
                    f"   {name:<14} {x['frames']:>6}  {text:<34} {lost_max} "
                    f"{100 * x['before']:>9.4f} {100 * x['after']:>8.4f} {'yes' if ok else 'NO':>8} {rec:>8}"
                )
            lines.append(
                "   (ok: median focal error on the views after recovery <= 1.1 x before, strictly; none: the "
                "same views again without a disturbance (drift over passes); recover: frames of the returning"
                " view until calibrated again, and time from its first frame)"
            )
        finally:
            feeder.close()
    with domain() as env, graph(env, work):
        feeder = rh.Feeder("bench_zoom_preset")
        try:
            feeder.wait_connected()
            z = rh.zoom_preset_scenario(feeder, 640, 360)
            counts: dict[str, int] = {}
            for s in z["moving_statuses"]:
                counts[s] = counts.get(s, 0) + 1
            after: dict[str, int] = {}
            for s in z["after_statuses"]:
                after[s] = after.get(s, 0) + 1
            ok = z["after"] <= 1.1 * z["before"]
            lines += [
                "   sharp preset recall panning 9 deg/frame while zooming 1x -> 2.5x (past the learned zoom "
                f"range), hold, back: {len(z['moving_statuses'])} frames moving {counts}, focal error while "
                f"moving max {100 * max(z['moving_errors']):.1f} %;",
                f"   window before {100 * z['before']:.4f} %, after {100 * z['after']:.4f} % "
                f"({'ok' if ok else 'NOT ok: calibration corrupted'}); statuses after {after}",
            ]
        finally:
            feeder.close()


def overload(
    domain: Domain, work: Path, lines: list[str], seconds: float, views: int = 24, block_s: float = 10.0
) -> None:
    """`views` distinct views cycled at 60 frames/s: the sweep's pan (+-3 deg), tilt (+-1 deg, twice as
    fast) and zoom (1-1.1x) oscillate at 60 / views Hz (24, the CI test's: 2.5 Hz, peak pan speed 47 deg/s,
    far from a constant-velocity motion; 240: 0.25 Hz, 4.7 deg/s, a realistic patrol)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    latest = ("queue_policy:=latest", "queue_depth:=1")
    with (
        domain() as env,
        graph(env, work, ingest=(*latest, "sensor_reliability:=best_effort"), tracker=latest,
              working_width=640) as nodes,
    ):  # fmt: skip
        feeder = rh.Feeder(
            "bench_overload", sensor_qos=QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        )
        stages = StageTimes(feeder)
        try:
            feeder.wait_connected(compressed=True)
            pids = {n: p.pid for n, p in nodes.items()}
            blocks = Blocks(feeder, {**pids, "feeder": os.getpid()}, block_s)
            r = rh.overload_scenario(feeder, pids, seconds, distinct=views, on_sample=blocks.sample)
            blocks.threads_end()  # (the run and the scenario's 3 s for the last frames in flight)
            feeder.spin(1.0)
            d = feeder.diagnostics
            ingest, tracker = d["frame_ingest"], d["homography_tracker"]
            shed_dds = r["sent"] - int(ingest["frames_in"])
            taken = {
                "frame_ingest": int(ingest["frames_in"]),
                "homography_tracker": int(tracker["frames_in"]),
                "calibrator": r["calibrated"],
                "feeder": r["sent"],
            }
            lines += [
                "",
                f"3. Overload: 1920x1080 JPEG at 60 frames/s for {seconds:.0f} s (best effort), "
                "queue_policy latest (depth 1) in frame_ingest and homography_tracker, working width 640; "
                f"{views} views cycled (pan +-3 deg at {60 / views:.2f} Hz, peak "
                f"{3 * 2 * math.pi * 60 / views:.1f} deg/s)",
                f"   frames in {r['sent']} ({r['rate']:.1f}/s), frames calibrated {r['calibrated']} "
                f"({r['calibrated'] / r['elapsed']:.1f}/s), duplicates {r['duplicates']}",
                f"   skipped and why: {shed_dds} shed by the latest-wins image queue before frame_ingest "
                f"(frames_in {ingest['frames_in']}; frame_ingest's estimate from stamp gaps in /diagnostics: "
                f"{ingest.get('input_frames_missing_estimate', 0)}), {tracker.get('frames_dropped')} shed by "
                f"the tracker's "
                f"latest-wins queue (homography_tracker frames_dropped in /diagnostics), "
                f"{int(ingest['frames_out']) - int(tracker['frames_in']) - int(tracker['frames_dropped'])} "
                "in flight/unaccounted",
                f"   {latency_line(r['latencies'])}; first third p95 {pct(r['early_latencies'], 95)} ms, "
                f"last third p95 {pct(r['late_latencies'], 95)} ms",
                "   peak RSS "
                + ", ".join(f"{n} {max(v for _, v in s):.0f} MB" for n, s in r["rss"].items())
                + "; RSS at the end "
                + ", ".join(f"{n} {s[-1][1]:.0f} MB" for n, s in r["rss"].items()),
                f"   tracker per-frame time in /diagnostics: mean {tracker.get('track_ms_mean')} ms, p95 "
                f"{tracker.get('track_ms_p95')} ms; calibrator solves {d['calibrator'].get('solves')}, "
                "frame_ingest encoder messages taken from a backlog "
                f"{ingest.get('encoder_messages_drained', 0)}, frames whose encoder wait expired "
                f"{ingest.get('encoder_wait_expired', 0)}",
                *stages.lines(feeder),
                *blocks.lines(r, stages),
                blocks.thread_line(taken),
            ]
        finally:
            feeder.close()


def _machine_busy_s() -> float:
    """CPU seconds the whole machine was busy (all CPUs: /proc/stat minus idle and iowait)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
    return (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")


def _thread_cpu_s(pid: int) -> tuple[float, float]:
    """(main thread, all other threads) CPU seconds of a process: Python's executor runs on the main thread
    of a node, DDS's receive/event threads (and worker threads) are the others."""
    main = other = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # a thread that ended meanwhile
            continue
        cpu = (int(fields[11]) + int(fields[12])) / tick
        main, other = (main + cpu, other) if int(task.name) == pid else (main, other + cpu)
    return main, other


class Blocks:
    """The overload run cut into blocks of `block_s` seconds (by send time): what shows whether the latency
    is bounded or keeps rising, and what else changes with it. At each block boundary: CPU seconds of each
    node process, of this process (the feeder: encoding-free publishing, receiving every output) and of
    the whole machine (the rest is other jobs on the same CPUs), and the nodes' /diagnostics counters."""

    def __init__(self, feeder: rh.Feeder, pids: dict[str, int], block_s: float) -> None:
        self.feeder, self.pids, self.block_s = feeder, pids, block_s
        self.marks: list[tuple[float, dict[str, float], float, dict[str, dict[str, str]]]] = []
        self._mark(0.0)
        self.last = self.marks[0]
        self.threads = [{name: _thread_cpu_s(pid) for name, pid in pids.items()}]
        self.threads_at = [time.monotonic()]

    def _mark(self, t: float) -> None:
        cpu = {name: rh.cpu_seconds(pid) for name, pid in self.pids.items()}
        diag = {name: dict(values) for name, values in self.feeder.diagnostics.items()}
        self.marks.append((t, cpu, _machine_busy_s(), diag))

    def sample(self, t: float) -> None:
        self._mark(t)
        if t < (len(self.marks) - 1) * self.block_s:  # not a block boundary: only the latest sample
            self.last = self.marks.pop()

    def threads_end(self) -> None:
        """Per-thread CPU at the end of the run (call before the feeder's drain)."""
        self.threads.append({name: _thread_cpu_s(pid) for name, pid in self.pids.items()})
        self.threads_at.append(time.monotonic())

    def thread_line(self, frames: dict[str, int]) -> str:
        dt = self.threads_at[1] - self.threads_at[0]
        parts = []
        for name in self.pids:
            (m0, o0), (m1, o1) = self.threads[0][name], self.threads[1][name]
            n = frames.get(name)
            per = f", {1e3 * (m1 - m0) / n:.1f} + {1e3 * (o1 - o0) / n:.1f} ms per frame taken" if n else ""
            parts.append(f"{name} {100 * (m1 - m0) / dt:.0f} + {100 * (o1 - o0) / dt:.0f} %{per}")
        head = (
            "   CPU over the run and 3 s after, main (Python executor) + other threads (DDS, workers), % of "
            "a core: "
        )
        return head + "; ".join(parts)

    def lines(self, r: dict, stages: StageTimes) -> list[str]:
        if self.last[0] > self.marks[-1][0]:  # the partial block at the end (its last sample in the run)
            self.marks.append(self.last)
        feeder, p = self.feeder, stages.published
        sent = sorted(feeder.sent.items(), key=lambda item: item[1])
        names = [n for n in self.pids if n != "feeder"]
        out = [
            f"   per {self.block_s:.0f} s block (frames by send time): latency image sent -> CameraInfo, per "
            "stage p95 (publish times), CPU % of one core per process over the block, machine busy % of "
            f"{os.cpu_count()} cores (others: not the graph nor the feeder), tracker counters in the block",
            f"   {'block s':>8} {'sent':>5} {'calib':>5} {'p50':>4} {'p95':>4} {'max':>4} | {'ingest':>6} "
            f"{'track':>5} {'calib':>5} | {'cpu in':>6} {'track':>5} {'calib':>5} {'feed':>5} "
            f"{'others':>6} {'busy':>5} | {'newkf':>5} {'reloc':>5} {'lost':>4} {'shed':>5} {'kf':>3} "
            f"{'trk ms':>6}",
        ]
        rows: list[tuple[float, float, float]] = []  # (block middle s, p95 ms, others % of a core)
        for (t0, cpu0, busy0, diag0), (t1, cpu1, busy1, diag1) in zip(self.marks, self.marks[1:]):
            if t1 - t0 < 0.5 * self.block_s:
                continue
            frames = [ns for ns, when in sent if t0 <= when - r["start"] < t1]
            lat = [feeder.info_arrival[ns] - feeder.sent[ns] for ns in frames if ns in feeder.info_arrival]
            seen = [ns for ns in frames if all(ns in p[k] for k in p)]
            ingest = [p["ingest"][ns] - feeder.sent[ns] for ns in seen]
            track = [p["tracker"][ns] - p["ingest"][ns] for ns in seen]
            calib = [p["calibrator"][ns] - p["tracker"][ns] for ns in seen]
            dt = t1 - t0
            use = {n: 100.0 * (cpu1[n] - cpu0[n]) / dt for n in self.pids}
            busy = 100.0 * (busy1 - busy0) / dt
            others = busy - sum(use.values())
            t_new, t_old = diag1.get("homography_tracker", {}), diag0.get("homography_tracker", {})

            def delta(key: str, new=t_new, old=t_old) -> int:
                return int(float(new.get(key, 0))) - int(float(old.get(key, 0)))

            out.append(
                f"   {t0:>3.0f}-{t1:<4.0f} {len(frames):>5} {len(lat):>5} {pct(lat, 50):>4} "
                f"{pct(lat, 95):>4} {pct(lat, 100):>4} | {pct(ingest, 95):>6} {pct(track, 95):>5} "
                f"{pct(calib, 95):>5} | "
                + " ".join(f"{use[n]:>{w}.0f}" for n, w in zip([*names, "feeder"], (6, 5, 5, 5)))
                + f" {others:>6.0f} {busy / os.cpu_count():>5.0f} | "
                f"{delta(f'state_{TrackingState.NEW_KEYFRAME}'):>5} "
                f"{delta(f'state_{TrackingState.RELOCALISED}'):>5} "
                f"{delta(f'state_{TrackingState.TRACKING_LOST}'):>4} "
                f"{delta('keyframe_changes'):>5} "
                f"{delta('frames_dropped'):>5} {t_new.get('map_keyframes', '-'):>3} "
                f"{t_new.get('track_ms_mean', '-'):>6}"
            )
            if lat:
                rows.append((0.5 * (t0 + t1), float(np.percentile(lat, 95)) * 1e3, others))
        return out + self.summary(rows)

    @staticmethod
    def summary(rows: list[tuple[float, float, float]], quiet: float = 10.0) -> list[str]:
        """Bounded or rising: the p95 trend over the blocks in which other jobs took less than `quiet` % of
        a core (least squares, ms per minute), and how the p95 goes with the other jobs' CPU."""
        if len(rows) < 3:
            return []
        t, p95, others = (np.asarray(v, float) for v in zip(*rows))
        calm = others < quiet
        out = []
        if calm.sum() >= 2:
            slope = np.polyfit(t[calm] / 60.0, p95[calm], 1)[0]
            out.append(
                f"   blocks with other jobs < {quiet:.0f} % of a core: {calm.sum()} of {len(rows)}, p95 "
                f"{p95[calm].min():.0f}-{p95[calm].max():.0f} ms (median {np.median(p95[calm]):.0f}), trend "
                f"{slope:+.1f} ms per minute (first {t[calm][0]:.0f} s: {p95[calm][0]:.0f} ms, last "
                f"{t[calm][-1]:.0f} s: {p95[calm][-1]:.0f} ms)"
            )
        if (~calm).any():
            out.append(
                f"   blocks with other jobs >= {quiet:.0f} %: {(~calm).sum()}, p95 {p95[~calm].min():.0f}-"
                f"{p95[~calm].max():.0f} ms at {others[~calm].min():.0f}-{others[~calm].max():.0f} % of a "
                "core; correlation of block p95 with the other jobs' CPU over all blocks "
                f"{np.corrcoef(p95, others)[0, 1]:+.2f}"
            )
        return out


class StageTimes:
    """Where the latency goes: the publish time (DDS source timestamp) of each frame's IngestedFrame,
    HomographyStamped and CameraInfo, seen by the feeder (best effort, depth 1: no back-pressure). Taken
    serialized, the header stamp read in place: deserialising every 640x360 IngestedFrame cost this
    process (on the same 2 CPUs as the graph) CPU the measurement should not take."""

    def __init__(self, feeder: rh.Feeder) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo

        from ptz_selfcal import topics
        from ptz_selfcal_msgs.msg import HomographyStamped, IngestedFrame

        self.wall_minus_mono = time.time() - time.monotonic()
        self.published: dict[str, dict[int, float]] = {"ingest": {}, "tracker": {}, "calibrator": {}}
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
        for key, msg_type, topic in (
            ("ingest", IngestedFrame, topics.FRAME_IN),
            ("tracker", HomographyStamped, topics.HOMOGRAPHY),
            ("calibrator", CameraInfo, topics.CAMERA_INFO),
        ):
            feeder.node.create_subscription(msg_type, topic, self._callback(key), qos, raw=True)

    def _callback(self, key: str):
        def on_message(data: bytes, info) -> None:
            # CDR: 4 bytes of encapsulation (byte 1: 1 = little endian), then header.stamp (int32, uint32)
            sec, nanosec = struct.unpack("<iI" if data[1] & 1 else ">iI", data[4:12])
            mono = info["source_timestamp"] * 1e-9 - self.wall_minus_mono
            self.published[key][sec * 1_000_000_000 + nanosec] = mono

        return on_message

    def lines(self, feeder: rh.Feeder) -> list[str]:
        p = self.published
        stamps = [ns for ns in sorted(feeder.sent) if all(ns in p[k] for k in p)]
        third = max(1, len(stamps) // 3)
        out = []
        for name, part in (("first third", stamps[:third]), ("last third", stamps[-third:])):
            ingest = [p["ingest"][ns] - feeder.sent[ns] for ns in part]
            tracker = [p["tracker"][ns] - p["ingest"][ns] for ns in part]
            calibrator = [p["calibrator"][ns] - p["tracker"][ns] for ns in part]
            out.append(
                f"   {name} p50/p95 ms per stage (publish times): sent -> frame_ingest {pct(ingest, 50)}/"
                f"{pct(ingest, 95)}, -> homography_tracker {pct(tracker, 50)}/{pct(tracker, 95)}, -> "
                f"calibrator {pct(calibrator, 50)}/{pct(calibrator, 95)} ({len(part)} frames seen at "
                "every stage)"
            )
        return out


def core_soak(lines: list[str], core_frames: int) -> None:
    r = rh.core_soak(core_frames, warmup=(2_000, 12_000))
    lines += [
        "",
        f"4a. Soak, calibrator core (CalibratorSession.process + worker steps inline, exact homographies "
        f"of a patrolling camera, period 600 frames): {r['frames']} frames in {r['wall_s']:.0f} s",
        f"   frames calibrated {sum(r['statuses'].get(s, 0) for s in CALIBRATED)} "
        f"({r['statuses']}), median focal error {100 * r['median_error']:.4f} %, {r['solves']} solves",
        f"   CPU ms/frame after warm-up (frames 2k-12k) {r['warm_cpu_ms']:.3f}, at the end (last 10k) "
        f"{r['end_cpu_ms']:.3f}: ratio {r['end_cpu_ms'] / r['warm_cpu_ms']:.3f} (target <= 1.1); best "
        f"1000-frame block {r['warm_cpu_min']:.3f} vs {r['end_cpu_min']:.3f}: ratio "
        f"{r['end_cpu_min'] / r['warm_cpu_min']:.3f}; p95 {r['p95_cpu_ms']:.3f} ms",
        f"   RSS after warm-up {r['warm_rss']:.1f} MB, at the end {r['end_rss']:.1f} MB: ratio "
        f"{r['end_rss'] / r['warm_rss']:.3f} (target <= 1.1); growth "
        f"{(r['rss_blocks'][-1] - r['rss_blocks'][1]) / max(1, len(r['rss_blocks']) - 2) * 100:.2f} MB per "
        "100k frames",
    ]


def graph_soak(domain: Domain, work: Path, lines: list[str], graph_frames: int) -> None:
    with domain() as env, graph(env, work, working_width=160) as nodes:
        feeder = rh.Feeder("bench_soak", homographies=False)
        try:
            feeder.wait_connected()
            g = rh.graph_soak(
                feeder, {n: p.pid for n, p in nodes.items()}, graph_frames, 320, 180, block=1000
            )
            lat_first = g["latency_blocks"][1] if len(g["latency_blocks"]) > 1 else []
            lat_last = g["latency_blocks"][-1] if g["latency_blocks"] else []
            lines += [
                "",
                f"4b. Soak, full graph (three node processes, 320x180 rendered patrol, lossless, 3 in "
                f"flight): {g['frames']} frames in {g['wall_s']:.0f} s "
                f"({g['frames'] / g['wall_s']:.1f} frames/s)",
                f"   frames calibrated {g['calibrated']} (duplicates {g['duplicates']}, lost {g['lost']}); "
                f"statuses {g['statuses']}",
                f"   latency block 2 (frames 1k-2k): p50 {pct(lat_first, 50)} ms p95 {pct(lat_first, 95)} "
                f"ms; "
                f"last block: p50 {pct(lat_last, 50)} ms p95 {pct(lat_last, 95)} ms",
                f"   {'node':<20} {'RSS 1k-2k MB':>12} {'RSS end MB':>10} {'ratio':>6} "
                f"{'CPU ms/fr 1k-2k':>15} {'CPU end':>8} {'ratio':>6}",
            ]
            for name in nodes:
                rss, cpu = g["rss"][name], g["cpu_ms_per_frame"][name]
                a_cpu = float(np.mean(cpu[1:3]))
                lines.append(
                    f"   {name:<20} {rss[1]:>12.1f} {rss[-1]:>10.1f} {rss[-1] / rss[1]:>6.3f} {a_cpu:>15.2f} "
                    f"{cpu[-1]:>8.2f} {cpu[-1] / a_cpu:>6.3f}"
                )
        finally:
            feeder.close()


def restarts(domain: Domain, work: Path, lines: list[str]) -> None:
    lines += [
        "",
        "5. Restarts: kill -9 of one node during `ptz-selfcal launch` (state_dir, save_period 0.3 s), "
        "640x360 views, calibrated, then the same 16 views 3 times after the restart",
        f"   {'killed node':<20} {'frames in':>9} {'calibrated':>10} {'lost':>5} {'worse':>6} "
        f"{'f err before %':>14} {'after %':>8} {'reconnect s':>11} {'recover s':>9}  statuses after",
    ]
    for victim in ("calibrator", "homography_tracker", "frame_ingest"):
        with domain() as env:
            state_dir = work / f"state_{victim}"
            params = work / f"params_{victim}.yaml"
            params.write_text(
                "frame_ingest:\n  ros__parameters:\n    working_width: 320\n"
                "    sensor_reliability: reliable\n    diagnostics_period: 0.25\n"
                "homography_tracker:\n  ros__parameters:\n    diagnostics_period: 0.25\n"
                f"calibrator:\n  ros__parameters:\n    state_dir: {state_dir}\n    save_period: 0.3\n"
                "    nominal_hfov_deg: 55.0\n    diagnostics_period: 0.25\n"
            )
            launch = NodeProcess(
                cli_command("launch", "--params", str(params)), env, work, f"launch_{victim}"
            )
            feeder = rh.Feeder("bench_restart", homographies=False)
            try:
                feeder.wait_connected(60.0)
                r = rh.restart_scenario(feeder, launch.output, victim, 640, 360)
                counts: dict[str, int] = {}
                for s in r["statuses"]:
                    counts[s] = counts.get(s, 0) + 1
                recover = "never" if r["recover_s"] is None else f"{r['recover_s']:.2f}"
                lines.append(
                    f"   {victim:<20} {r['frames']:>9} {r['calibrated']:>10} {r['lost']:>5} "
                    f"{len(r['worse']):>6} "
                    f"{100 * r['before']:>14.4f} {100 * r['after']:>8.4f} {r['reconnect_s']:>11.2f} "
                    f"{recover:>9}  {counts}"
                )
            except Exception as exc:  # one victim's failure must not hide the others'
                lines.append(
                    f"   {victim:<20} FAILED: {type(exc).__name__}: {str(exc).splitlines()[0][:200]}"
                )
            finally:
                feeder.close()
                launch.stop(timeout=30.0)
    lines.append(
        "   (reconnect: kill -> the graph has the restarted node's DDS endpoints and none of the killed "
        "one's (launch's 2 s participant lease; Fast DDS's default 20 s kept them ~20 s); frames are sent "
        "from then on; lost: frames without CameraInfo after that; worse: frames with focal error > 1.1 x "
        "the worst before the kill + 0.05 %; recover: kill -> first CameraInfo not worse)"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--core-frames", type=int, default=100_000)
    parser.add_argument("--graph-frames", type=int, default=20_000)
    parser.add_argument("--overload-seconds", type=float, default=30.0)
    parser.add_argument(
        "--overload-views", type=int, nargs="+", default=[24], help="one overload run per number of views"
    )
    parser.add_argument("--only", nargs="+", choices=EXPERIMENTS, default=list(EXPERIMENTS))
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "reliability.txt")
    args = parser.parse_args(argv)
    lines = [
        f"benchmarks/reliability.py  {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}  "
        f"({os.cpu_count()} CPUs, python {sys.version.split()[0]})"
    ]
    domain = Domain()
    with tempfile.TemporaryDirectory(prefix="ptz_reliability_") as tmp:
        work = Path(tmp)
        for name in args.only:
            try:
                if name == "bad_input":
                    bad_input(domain, work, lines)
                elif name == "tracking_loss":
                    tracking_loss(domain, work, lines)
                elif name == "overload":
                    for views in args.overload_views:
                        overload(domain, work, lines, args.overload_seconds, views)
                elif name == "core_soak":
                    core_soak(lines, args.core_frames)
                elif name == "graph_soak":
                    graph_soak(domain, work, lines, args.graph_frames)
                else:
                    restarts(domain, work, lines)
            except Exception as exc:  # report and go on with the next experiment
                lines.append(f"   {name}: FAILED: {type(exc).__name__}: {str(exc).splitlines()[0][:300]}")
            print("\n".join(lines), flush=True)
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
