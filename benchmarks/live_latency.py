"""Issue 5 "Measure", live: image -> CameraInfo latency at 30 frames/s (play --rate 1), both queue policies.

A 300-frame 1280x720 JPEG `ptz-selfcal synth` bag (rendered once, or --bag) is played LIVE at its own
frame rate by a small player inside this process (the same publishing as `ptz-selfcal play --rate 1`:
raw CDR bytes, RELIABLE, images and encoders interleaved in bag order, each message sent at its bag time
mapped to wall time at the start). The three node processes are started by the same machinery as
`ptz-selfcal launch`/`run` (tools/launch.Supervisor, the default parameter file with the queue policy
overridden). This process subscribes to topics.CAMERA_INFO (and topics.HOMOGRAPHY, to split the latency
into ingest + tracking and calibration) and measures per image the wall time from the moment the player
published it to the arrival of the CameraInfo with its stamp.

Printed per policy: p50/p95/p99/max latency, frames published / calibrated / dropped (and where:
shed before frame_ingest, by the tracker's latest-wins queue), whether the latency grows over the run
(first vs last third, and the slope), the peak RSS (VmHWM) of each node process, the nodes' own per-stage
times from /diagnostics, and the machine load average. Writes benchmarks/results/live_latency.txt.

    ros2_ws/venv/bin/python benchmarks/live_latency.py [--bag SYNTH_BAG] [--policies lossless latest]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PANORAMA = Path("/work/shared/data/panoramas/building.jpg")
TARGET_P95_MS = 40.0
NODES = ("frame_ingest", "homography_tracker", "calibrator")


def peak_rss_mb(pid: int) -> float:
    """VmHWM (peak resident set size) of a process, MB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def _autogroup_nice(pid: int) -> int | None:
    try:  # "/autogroup-570 nice 0"
        return int(Path(f"/proc/{pid}/autogroup").read_text().split()[-1])
    except (OSError, ValueError, IndexError):
        return None


def _set_autogroup_nice(pid: int, nice: int) -> None:
    try:
        Path(f"/proc/{pid}/autogroup").write_text(str(nice))
    except OSError as exc:
        print(f"live_latency: cannot set the autogroup nice of {pid}: {exc}", file=sys.stderr)


def render_bag(work: Path) -> Path:
    from ptz_selfcal.tools import synth

    bag = work / "synth300"
    parser = argparse.ArgumentParser()
    synth.add_arguments(parser)
    status = synth.run(parser.parse_args([str(PANORAMA), str(bag), "--quiet", "--seed", "0"]))
    if status:
        raise SystemExit(f"synth failed ({status})")
    return bag


@dataclass
class Result:
    policy: str
    depth: int
    published: int = 0
    sent: dict[int, float] = field(default_factory=dict)  # image stamp -> wall time published
    info: dict[int, float] = field(default_factory=dict)  # image stamp -> CameraInfo arrival
    homography: dict[int, float] = field(default_factory=dict)  # image stamp -> HomographyStamped arrival
    unmatched: int = 0
    play_late_ms: list[float] = field(default_factory=list)  # player behind its schedule
    diagnostics: dict[str, dict[str, str]] = field(default_factory=dict)
    peak_rss: dict[str, float] = field(default_factory=dict)
    cpu: dict[str, float] = field(default_factory=dict)
    load: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    wall: float = 0.0
    nice: int | None = None

    def latencies(self) -> tuple[np.ndarray, np.ndarray]:
        """(publish order index, latency s) of every calibrated image."""
        order = sorted(self.sent)
        idx = [i for i, s in enumerate(order) if s in self.info]
        lat = [self.info[order[i]] - self.sent[order[i]] for i in idx]
        return np.asarray(idx, dtype=float), np.asarray(lat, dtype=float)

    def stage(self) -> np.ndarray:
        return np.asarray([self.homography[s] - self.sent[s] for s in self.sent if s in self.homography])


def load_bag(bag: Path, image_topic: str, joint_topic: str) -> tuple[str, list[tuple[str, int, bytes]]]:
    from ptz_selfcal.tools.bagio import BagReader

    with BagReader(bag) as reader:
        types = {t.name: t.msgtype for t in reader.topics()}
        msgs = [(m.topic, m.timestamp_ns, m.raw) for m in reader.messages([image_topic, joint_topic])]
    return types[image_topic], msgs


def measure(
    bag_messages: list[tuple[str, int, bytes]],
    image_type: str,
    image_topic: str,
    policy: str,
    depth: int,
    domain_tmp: Path,
    rate: float,
    extra: list[str],
    nice: int | None = None,
    supervisor_class: Any = None,
    namespace: str | None = None,
    ready: Any = None,
) -> Result:
    """One live run; `supervisor_class` (launch's Supervisor by default) starts the nodes, e.g. some of
    them in another network namespace (benchmarks/two_hosts.py)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from ptz_selfcal import topics
    from ptz_selfcal.nodes.runtime import reliable_qos
    from ptz_selfcal.tools.bagio import header_stamp_ns, msg_class
    from ptz_selfcal.tools.launch import NODE_MODULES, NodeSpec, Supervisor, prepare

    res = Result(policy, depth, nice=nice)
    own_group: int | None = None
    namespace = namespace or f"/live_latency_{os.getpid()}_{policy}"
    params_file, namespace, _ = prepare(None, namespace, [], str(domain_tmp))
    compressed = image_type == "sensor_msgs/msg/CompressedImage"
    diag = ["-r", f"{topics.DIAGNOSTICS}:={namespace}{topics.DIAGNOSTICS}"]
    queue = ["-p", f"queue_policy:={policy}", "-p", f"queue_depth:={depth}"]
    ingest = ["-p", f"image_transport:={'compressed' if compressed else 'raw'}"]
    specs = [
        NodeSpec("frame_ingest", NODE_MODULES["frame_ingest"], [*diag, *queue, *ingest, *extra]),
        NodeSpec("homography_tracker", NODE_MODULES["homography_tracker"], [*diag, *queue]),
        NodeSpec("calibrator", NODE_MODULES["calibrator"], [*diag]),
    ]
    supervisor = (supervisor_class or Supervisor)(
        specs, params_file, namespace, echo=False, output=sys.stderr
    )

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
    node = rclpy.create_node("live_latency", namespace=namespace, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    lock = threading.Lock()

    def on_info(raw: bytes) -> None:
        now = time.monotonic()
        stamp = header_stamp_ns(raw)
        with lock:
            if stamp in res.sent and stamp not in res.info:
                res.info[stamp] = now
            else:
                res.unmatched += 1

    def on_homography(raw: bytes) -> None:
        now = time.monotonic()
        stamp = header_stamp_ns(raw)
        with lock:
            if stamp in res.sent:
                res.homography.setdefault(stamp, now)

    def on_diagnostics(msg: Any) -> None:
        for status in msg.status:
            name = status.name.rsplit("/", 1)[-1]
            res.diagnostics[name] = {kv.key: kv.value for kv in status.values}

    from diagnostic_msgs.msg import DiagnosticArray

    image_pub = node.create_publisher(
        msg_class(image_type), topics.IMAGE_COMPRESSED if compressed else topics.IMAGE_RAW, reliable_qos()
    )
    joint_pub = node.create_publisher(
        msg_class("sensor_msgs/msg/JointState"), topics.JOINT_STATES, reliable_qos()
    )
    info_cls = msg_class(topics.TYPES[topics.CAMERA_INFO])
    hom_cls = msg_class(topics.TYPES[topics.HOMOGRAPHY])
    info_sub = node.create_subscription(info_cls, topics.CAMERA_INFO, on_info, reliable_qos(), raw=True)
    node.create_subscription(hom_cls, topics.HOMOGRAPHY, on_homography, reliable_qos(), raw=True)
    node.create_subscription(
        DiagnosticArray, f"{namespace}{topics.DIAGNOSTICS}", on_diagnostics, reliable_qos(10)
    )
    ns = namespace
    try:
        supervisor.start()
        deadline = time.monotonic() + 60.0
        checks = [
            lambda: image_pub.get_subscription_count() > 0,
            lambda: joint_pub.get_subscription_count() > 0,
            lambda: node.count_subscribers(f"{ns}/{topics.FRAME_IN}") > 0,
            lambda: node.count_subscribers(f"{ns}/{topics.HOMOGRAPHY}") > 1,
            lambda: node.count_subscribers(f"{ns}/{topics.KEYFRAMES}") > 0,
            lambda: info_sub.get_publisher_count() > 0,
        ]
        while not all(c() for c in checks):
            supervisor.poll()
            if supervisor.fatal or time.monotonic() > deadline:
                raise SystemExit(f"nodes did not come up: {supervisor.fatal or 'timeout'}")
            executor.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 2.0  # let discovery settle on the far ends too
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        if ready is not None:  # several cameras (benchmarks/multi_camera.py): start together
            ready()

        done = threading.Event()

        def play() -> None:
            start = time.monotonic() + 0.1
            first = bag_messages[0][1]
            for topic, t_ns, raw in bag_messages:
                due = start + (t_ns - first) * 1e-9 / rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                if topic == image_topic:
                    stamp = header_stamp_ns(raw)
                    now = time.monotonic()
                    with lock:
                        res.sent[stamp] = now
                    image_pub.publish(raw)
                    res.published += 1
                    res.play_late_ms.append(1e3 * (now - due))
                else:
                    joint_pub.publish(raw)
            done.set()

        if nice is not None:
            # Every thread of the nodes and of this process ahead of the machine's other work. With the
            # kernel's autogroups (each session, e.g. each node started with start_new_session, shares
            # CPU equally with every other session) a thread's nice only ranks it inside its session:
            # the session's /proc/PID/autogroup nice ranks it against the others.
            own_group = _autogroup_nice(os.getpid())
            for pid in [os.getpid(), *supervisor.pids().values()]:
                _set_autogroup_nice(pid, nice)
                for task in Path(f"/proc/{pid}/task").iterdir():
                    os.setpriority(os.PRIO_PROCESS, int(task.name), nice)
        start_cpu = supervisor.cpu_seconds()
        res.load = os.getloadavg()
        t0 = time.monotonic()
        player = threading.Thread(target=play, daemon=True)
        player.start()
        while not done.is_set():
            executor.spin_once(timeout_sec=0.01)
        # drain: until every image has its CameraInfo or nothing arrived for 3 s
        quiet_since = time.monotonic()
        count = len(res.info)
        while time.monotonic() - quiet_since < 3.0 and len(res.info) < res.published:
            executor.spin_once(timeout_sec=0.05)
            if len(res.info) != count:
                count, quiet_since = len(res.info), time.monotonic()
        res.wall = time.monotonic() - t0
        end = time.monotonic() + 1.2  # one more diagnostics period
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        cpu = supervisor.cpu_seconds()
        res.cpu = {k: v - start_cpu.get(k, 0.0) for k, v in cpu.items()}
        res.peak_rss = {name: peak_rss_mb(pid) for name, pid in supervisor.pids().items()}
    finally:
        if nice is not None and own_group is not None:
            _set_autogroup_nice(os.getpid(), own_group)
            os.setpriority(os.PRIO_PROCESS, 0, 0)
        supervisor.stop()
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
    return res


def _sync_start() -> None:
    print("READY", flush=True)
    sys.stdin.readline()


def summary(res: Result) -> dict[str, Any]:
    """The figures benchmarks/multi_camera.py compares across cameras."""
    import resource

    _, lat = res.latencies()
    ingest = res.diagnostics.get("frame_ingest", {})
    tracker = res.diagnostics.get("homography_tracker", {})
    own = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "published": res.published,
        "calibrated": len(res.info),
        "p50_ms": pct(lat, 50),
        "p95_ms": pct(lat, 95),
        "shed_before_ingest": res.published - int(ingest.get("frames_in", 0) or 0),
        "shed_by_ingest": int(ingest.get("frames_in", 0) or 0) - int(ingest.get("frames_out", 0) or 0),
        "shed_by_tracker": int(tracker.get("frames_dropped", 0) or 0),
        "node_cpu_s": sum(res.cpu.values()),
        "player_cpu_s": own.ru_utime + own.ru_stime,
        "wall_s": res.wall,
    }


def pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) * 1e3 if len(values) else math.nan


def report(res: Result, lines: list[str]) -> None:
    idx, lat = res.latencies()
    n = res.published
    calibrated = len(res.info)
    lines.append(
        f"queue_policy {res.policy}"
        + (f" (queue_depth {res.depth})" if res.policy == "latest" else " (KEEP_ALL)")
        + (f", nice {res.nice}" if res.nice is not None else "")
        + f"; load average {res.load[0]:.2f} {res.load[1]:.2f} {res.load[2]:.2f} at start"
    )
    ok = "yes" if pct(lat, 95) <= TARGET_P95_MS else "NO"
    lines.append(
        f"  latency image published -> CameraInfo: p50 {pct(lat, 50):.1f} ms, p95 {pct(lat, 95):.1f} ms, "
        f"p99 {pct(lat, 99):.1f} ms, max {pct(lat, 100):.1f} ms  (target p95 <= {TARGET_P95_MS:.0f} ms: {ok})"
    )
    st = res.stage()
    lines.append(
        f"  of which image -> HomographyStamped (ingest + tracker): p50 {pct(st, 50):.1f} ms, "
        f"p95 {pct(st, 95):.1f} ms, max {pct(st, 100):.1f} ms"
    )
    ingest = res.diagnostics.get("frame_ingest", {})
    tracker = res.diagnostics.get("homography_tracker", {})
    shed_dds = n - int(ingest.get("frames_in", 0) or 0)
    shed_tracker = int(tracker.get("frames_dropped", 0) or 0)
    calib = res.diagnostics.get("calibrator", {})
    lines.append(
        f"  frames published {n}, calibrated {calibrated} ({100.0 * calibrated / max(n, 1):.1f}%), dropped "
        f"{n - calibrated} (not received by frame_ingest {shed_dds}, shed by the tracker's queue "
        f"{shed_tracker}); unmatched CameraInfo {res.unmatched}"
    )
    lines.append(
        f"  per stage (last /diagnostics): frame_ingest in {ingest.get('frames_in', '?')} out "
        f"{ingest.get('frames_out', '?')}, homography_tracker in {tracker.get('frames_in', '?')} out "
        f"{tracker.get('frames_out', '?')}, calibrator in {calib.get('homographies_in', '?')} out "
        f"{calib.get('camera_info_out', '?')}"
    )
    if len(lat) >= 6:
        third = max(1, len(lat) // 3)
        first, last = lat[:third], lat[-third:]
        slope = np.polyfit(idx / 30.0, lat, 1)[0] * 1e3  # ms of latency per s of run
        grows = pct(last, 50) > 1.5 * pct(first, 50) + 5.0 or slope > 5.0
        lines.append(
            f"  growth: first third p50 {pct(first, 50):.1f} / p95 {pct(first, 95):.1f} ms, last third p50 "
            f"{pct(last, 50):.1f} / p95 {pct(last, 95):.1f} ms, slope {slope:+.1f} ms per s -> "
            f"{'latency GROWS' if grows else 'flat'}"
            + (
                f" (queue depth {res.depth}: none can grow; latency follows the CPU left to the nodes)"
                if res.policy == "latest" and grows
                else " (a lossless queue builds up)"
                if grows
                else ""
            )
        )
    late = np.asarray(res.play_late_ms)
    lines.append(
        f"  player behind schedule: p95 {np.percentile(late, 95):.1f} ms, max {late.max():.1f} ms; "
        f"wall {res.wall:.1f} s"
    )
    lines.append(
        "  peak RSS (VmHWM): "
        + ", ".join(f"{k} {v:.0f} MB" for k, v in res.peak_rss.items())
        + "; CPU s during the run: "
        + ", ".join(f"{k} {v:.1f}" for k, v in res.cpu.items())
    )
    keys = {
        "frame_ingest": ("decode_ms_median", "decode_ms_p95"),
        "homography_tracker": (
            "track_ms_mean",
            "track_ms_p95",
            "track_ms_max",
            "keyframe_ms_p95",
            "keyframes",
        ),
        "calibrator": ("frame_ms_median", "frame_ms_p95", "frame_ms_max", "solve_ms_median", "solve_ms_max"),
    }
    for name, wanted in keys.items():
        values = res.diagnostics.get(name, {})
        shown = [f"{k} {values[k]}" for k in wanted if k in values]
        lines.append(f"  {name} diagnostics: {', '.join(shown) or '-'}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--bag", type=Path, help="an existing synth bag (default: render one)")
    parser.add_argument(
        "--policies", nargs="+", default=["lossless", "latest"], choices=["lossless", "latest"]
    )
    parser.add_argument("--depth", type=int, default=1, help="queue_depth with the latest policy (default 1)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1: live)")
    parser.add_argument("--repeats", type=int, default=1, help="runs per policy")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "live_latency.txt")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument(
        "--nice",
        type=int,
        help="run the nodes and the player at this niceness (e.g. -10: a camera pipeline prioritised over "
        "the machine's batch work; needs the privilege)",
    )
    parser.add_argument(
        "--ingest-param", nargs="*", default=[], metavar="NAME:=VALUE", help="extra frame_ingest parameters"
    )
    parser.add_argument("--namespace", help="the suite's namespace (default: a private one)")
    parser.add_argument(
        "--sync", action="store_true", help="print READY when the nodes are up, play after a line on stdin"
    )
    parser.add_argument("--json", type=Path, help="also write the last run's figures as JSON")
    args = parser.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", "211")

    from ptz_selfcal import topics

    given = " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        f"# ros2_ws/venv/bin/python benchmarks/live_latency.py {given}",
        f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, {os.cpu_count()} CPUs, "
        f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} at start",
    ]
    with tempfile.TemporaryDirectory(prefix="live_latency_") as tmp:
        bag = args.bag
        if bag is None:
            t = time.monotonic()
            bag = render_bag(Path(tmp))
            lines.append(
                f"# synth bag rendered in {time.monotonic() - t:.1f} s (300 frames 1280x720 JPEG, seed 0)"
            )
        image_topic = topics.bag_topic(topics.IMAGE_COMPRESSED)
        image_type, messages = load_bag(bag, image_topic, topics.bag_topic(topics.JOINT_STATES))
        images = sum(1 for m in messages if m[0] == image_topic)
        lines.append(f"# bag {bag}: {images} images ({image_type}), played at rate {args.rate}")
        extra = [a for item in args.ingest_param for a in ("-p", item)]
        for policy in args.policies:
            for k in range(args.repeats):
                sub = Path(tmp) / f"{policy}_{k}"
                sub.mkdir()
                res = measure(
                    messages, image_type, image_topic, policy, args.depth, sub, args.rate, extra, args.nice,
                    namespace=args.namespace, ready=_sync_start if args.sync else None,
                )  # fmt: skip
                report(res, lines)
                if args.json:
                    args.json.write_text(json.dumps(summary(res)))
                print("\n".join(lines[-10:]), flush=True)
    finish(lines, None if args.no_write else args.out)
    return 0


def finish(lines: list[str], out: Path | None) -> None:
    """The load average at the end, then print the results and write them to `out` (None: print only)."""
    lines.append(f"# load average at the end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    text = "\n".join(lines) + "\n"
    print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)


if __name__ == "__main__":
    sys.exit(main())
