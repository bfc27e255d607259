"""`ptz-selfcal run IN_BAG --out OUT_BAG`: replay a bag through the real node suite, lose no frame.

The three nodes run as separate processes (the `launch` supervisor) in a private namespace; a player
node in this process publishes the bag's image topic and encoders over DDS in LOCK-STEP: at most
`--window` images are in flight, and the next one goes out when the calibrator's CameraInfo for an
earlier one arrived (matched by header stamp, in order: an image overtaken by a later image's CameraInfo
got no output and is counted as skipped; one without any answer within `--timeout` counts as lost).
Encoder messages are sent up to `--encoder-lookahead` seconds (bag time) ahead of the next image so that
frame_ingest can interpolate without waiting. Every output topic (camera_info, frame calibration,
homography, keyframes, diagnostics) is recorded to OUT_BAG (mcap) together with the input bag's
non-image topics (encoders, ground truth) copied unchanged (with --with-images the image topic too);
output messages get the bag time of the input image with the same header stamp, and those without one
(diagnostics) the newest image's, so the output bag spans the input's time. Each topic carries the QoS
profiles its publishers offer (the input's for copies). A truncated or damaged input bag is replayed up
to its last complete record and the summary says how many images were unreadable. With --deterministic the
calibrator runs with inline_solves (each solve completes before the next frame) and frame_ingest only
interpolates encoders between bracketing samples (encoder_max_hold 0, no extrapolation whose use depends
on delivery order) and waits up to half of --timeout for them, so what each frame gets does not depend
on delivery order or load. The nodes and the player load the shipped Fast DDS profile (config/fastdds.xml,
as `launch` gives it) unless the environment names another.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import sys
import tempfile
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ptz_selfcal import topics
from ptz_selfcal.tools.bagio import (
    BagError,
    BagMessage,
    BagReader,
    BagWriter,
    header_stamp_ns,
    msg_class,
    qos_from_rclpy,
)
from ptz_selfcal.tools.cli import CliError
from ptz_selfcal.tools.launch import NODE_MODULES, NodeSpec, Supervisor, dds_profile_environment, prepare

_IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
OUTPUT_TOPICS = (
    topics.CAMERA_INFO,
    topics.FRAME_CALIBRATION,
    topics.HOMOGRAPHY,
    topics.KEYFRAMES,
    topics.DIAGNOSTICS,
)
STEADY_AFTER = 0.1  # fraction of the frames counted as start-up in the steady-state figures
PLAYER = "run (player+recorder)"  # this process, in the CPU figures


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("in_bag", help="input bag directory (images, encoders, optional ground truth)")
    parser.add_argument(
        "--out", required=True, metavar="OUT_BAG", help="output bag directory to create (mcap)"
    )
    parser.add_argument("--params", metavar="FILE", help="parameter YAML (default: config/ptz_selfcal.yaml)")
    parser.add_argument("--window", type=int, default=4, help="images in flight at most (lock-step window)")
    parser.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        help="seconds without a CameraInfo after which an image is lost",
    )
    parser.add_argument(
        "--startup-timeout", type=float, default=60.0, help="seconds for the nodes to start and connect"
    )
    parser.add_argument(
        "--encoder-lookahead",
        type=float,
        default=1.0,
        help="seconds (bag time) of non-image messages sent ahead of the next image",
    )
    parser.add_argument(
        "--drain",
        type=float,
        default=2.0,
        help="seconds to wait after the last frame for trailing outputs and final diagnostics",
    )
    parser.add_argument(
        "--image-topic", help="bag topic of the images (default: /ptz/image_raw[/compressed])"
    )
    parser.add_argument("--joints-topic", help="bag topic of the encoders (default: /ptz/joint_states)")
    parser.add_argument("--namespace", help="namespace of the nodes (default: a private one per run)")
    parser.add_argument("--record-frames", action="store_true", help="also record frame_in (working images)")
    parser.add_argument(
        "--with-images", action="store_true", help="copy the input image topic into the output bag"
    )
    parser.add_argument("--max-frames", type=int, default=0, help="stop after this many images (0: all)")
    parser.add_argument(
        "--deterministic",
        action="store_true",
        help="each solve completes before the next frame, encoders only interpolated (repeatable replays)",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no node output, no progress lines (summary only)"
    )
    parser.add_argument("--calibrator-module", default=NODE_MODULES["calibrator"], help=argparse.SUPPRESS)


@dataclass
class _InFlight:
    stamp_ns: int
    bag_time_ns: int
    sent: float
    index: int


@dataclass
class RunStats:
    total: int = 0
    sent: int = 0
    calibrated: int = 0
    skipped: int = 0  # overtaken by a later image's CameraInfo: the pipeline dropped it (bad frame)
    lost: int = 0  # no CameraInfo within the timeout
    unmatched: int = 0  # CameraInfo for no image in flight (late, or a stamp the player never sent)
    recorded: dict[str, int] = field(default_factory=dict)
    latencies: list[float] = field(default_factory=list)  # image sent -> its CameraInfo received
    tracker_latencies: list[float] = field(default_factory=list)  # image sent -> its homography received
    started: float = 0.0
    finished: float = 0.0
    cpu_seconds: dict[str, float] = field(default_factory=dict)
    # steady state: CPU seconds of each node and of this process, and the time, when the first
    # STEADY_AFTER of the frames had their answer, and again when the last one had
    steady_start: tuple[float, int, dict[str, float]] | None = None  # (time, frames answered, cpu)
    steady_end: tuple[float, int, dict[str, float]] | None = None

    @property
    def answered(self) -> int:
        return self.calibrated + self.skipped + self.lost

    @property
    def rate(self) -> float:
        elapsed = (self.finished or time.monotonic()) - self.started
        return self.calibrated / elapsed if elapsed > 0 else 0.0


def _pick_topic(
    reader: BagReader, wanted: str | None, defaults: tuple[str, ...], types: tuple[str, ...], what: str
) -> tuple[str, str, int] | None:
    """The bag topic to play as `what`: the one named on the command line, else a default name, else the
    only non-ground-truth topic of a fitting type; None when there is none."""
    found = {t.name: t for t in reader.topics()}
    if wanted:
        name = wanted if wanted.startswith("/") else "/" + wanted  # a bag's names are absolute
        if name not in found:
            raise CliError(f"{reader.path}: no topic {name} (topics: {', '.join(found) or 'none'})")
        if found[name].msgtype not in types:
            raise CliError(f"{reader.path}: {name} is a {found[name].msgtype}, not a {' or '.join(types)}")
        candidates = [found[name]]
    else:
        candidates = [found[n] for n in map(topics.bag_topic, defaults) if n in found]
        if not candidates:
            candidates = [t for t in found.values() if t.msgtype in types and "ground_truth" not in t.name]
            if len(candidates) > 1:
                names = ", ".join(t.name for t in candidates)
                raise CliError(
                    f"{reader.path}: several {what} topics ({names}): choose one with --{what}-topic"
                )
    candidates = [t for t in candidates if t.count > 0] or candidates
    if not candidates:
        return None
    best = max(candidates, key=lambda t: t.count)
    return best.name, best.msgtype, best.count


def _image_topic(reader: BagReader, wanted: str | None = None) -> tuple[str, str, int]:
    picked = _pick_topic(reader, wanted, (topics.IMAGE_COMPRESSED, topics.IMAGE_RAW), _IMAGE_TYPES, "image")
    if picked is None:
        names = ", ".join(t.name for t in reader.topics()) or "none"
        raise CliError(
            f"{reader.path}: no {topics.bag_topic(topics.IMAGE_RAW)} or "
            f"{topics.bag_topic(topics.IMAGE_COMPRESSED)} topic (topics: {names})"
        )
    return picked


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.window <= 1000:
        raise CliError(f"--window must be in [1, 1000], got {args.window}")
    for name in ("timeout", "startup_timeout"):
        if not getattr(args, name) > 0:
            raise CliError(f"--{name.replace('_', '-')} must be > 0")
    if not 0 <= args.drain <= 600:
        raise CliError("--drain must be in [0, 600] s")
    if not 0 <= args.encoder_lookahead <= 3600:
        raise CliError("--encoder-lookahead must be in [0, 3600] s")
    with BagReader(args.in_bag) as reader:
        image_topic, image_type, total = _image_topic(reader, args.image_topic)
        joints = _pick_topic(
            reader, args.joints_topic, (topics.JOINT_STATES,), ("sensor_msgs/msg/JointState",), "joints"
        )
        bag_topics = {t.name: t.msgtype for t in reader.topics()}
        bag_qos = {t.name: t.qos for t in reader.topics()}
        bag_start = reader.start_ns
        unread = reader.unread(image_topic)
        if reader.damage:
            lost = "an unknown number of" if unread is None else str(unread)
            print(
                f"run: warning: {reader.damage}; replaying the {total} readable images ({lost} lost)",
                file=sys.stderr,
            )
    if args.max_frames > 0:
        total = min(total, args.max_frames)
    out = Path(args.out)
    if out.exists():
        raise CliError(f"{out}: already exists (refusing to overwrite)")
    namespace = args.namespace or f"/ptz_selfcal_run_{os.getpid()}"
    with tempfile.TemporaryDirectory(prefix="ptz_selfcal_run_") as tmp:
        params_file, namespace, _ = prepare(args.params, namespace, [], tmp)
        assert namespace is not None
        input_kind = "compressed" if image_type == "sensor_msgs/msg/CompressedImage" else "raw"
        diag_remap = ["-r", f"{topics.DIAGNOSTICS}:={namespace}{topics.DIAGNOSTICS}"]
        # Run-mode overrides (after the params file, so they win): lossless, reliable, the bag's image
        # topic, and outputs held until the next stage (and the recorder where it listens) is matched.
        # Lock-step replay has no latency budget, so a frame may wait longer for its bracketing encoder
        # sample than live (on a loaded machine the 0.2 s default expired and left encoders invalid).
        ingest_args = {
            "sensor_reliability": "reliable",
            "queue_policy": "lossless",
            "image_transport": input_kind,
            "wait_for_subscribers": 2 if args.record_frames else 1,
            "encoder_wait": 1.0,
        }
        if args.deterministic:
            # A stamp just past the newest sample is otherwise extrapolated or interpolated depending on
            # whether the next sample (sent before the image, on another topic) was delivered first; and
            # a sample DDS re-sends late on a loaded machine must not expire the frame's wait.
            ingest_args["encoder_max_hold"] = 0.0
            ingest_args["encoder_extrapolate_slow"] = "false"
            ingest_args["encoder_wait"] = max(1.0, 0.5 * args.timeout)
        tracker_args = {"queue_policy": "lossless", "wait_for_subscribers": 2}
        # Lock-step results otherwise depend on when the worker's solves land relative to the frames.
        calibrator_args = {"inline_solves": "true"} if args.deterministic else {}
        # an evaluation is one camera alone: its solves do not wait for other runs' (the machine's slots
        # are for live suites)
        calibrator_args["solve_slots_dir"] = str(Path(tmp) / "solve_slots")
        specs = [
            NodeSpec("frame_ingest", NODE_MODULES["frame_ingest"], diag_remap + _overrides(ingest_args)),
            NodeSpec(
                "homography_tracker",
                NODE_MODULES["homography_tracker"],
                diag_remap + _overrides(tracker_args),
            ),
            NodeSpec("calibrator", args.calibrator_module, diag_remap + _overrides(calibrator_args)),
        ]
        # The nodes and this process's player load the shipped Fast DDS profile: the player publishes the
        # images, and its shared-memory segment is the one a raw image must fit in.
        profile = dds_profile_environment()
        supervisor = Supervisor(
            specs, params_file, namespace, echo=not args.quiet, output=sys.stderr, env=profile
        )
        writer = BagWriter(out)
        try:
            replay = _Replay(args, supervisor, writer, namespace, image_topic, image_type, total, bag_topics)
            replay.profile = profile
            replay.encoder_topic = joints[0] if joints else None
            replay.bag_qos = bag_qos
            replay.last_bag_time = bag_start
            stats = replay.run()
            if replay.unread_late and unread is not None:
                unread += replay.unread_late
        finally:
            writer.close()
    # The summary is printed even with --quiet (eval and benchmarks read it).
    p50, p95 = _percentiles_ms(stats.latencies)
    t50, t95 = _percentiles_ms(stats.tracker_latencies)
    coverage = 100.0 * stats.calibrated / stats.total if stats.total else 0.0
    print(
        f"run: {stats.calibrated}/{stats.total} images got a CameraInfo (coverage {coverage:.1f}%), "
        f"{stats.skipped} skipped by the nodes, {stats.lost} lost (timeout), "
        f"{stats.unmatched} unmatched; "
        f"{_unread_text(unread)}"
        f"{stats.rate:.1f} frames/s, latency in lock-step p50 {p50:.1f} ms p95 {p95:.1f} ms "
        f"(to the homography: p50 {t50:.1f} ms p95 {t95:.1f} ms); "
        f"wrote {out}",
        file=sys.stderr,
    )
    cpu = {**stats.cpu_seconds, PLAYER: _own_cpu_seconds()}
    print(f"run: CPU seconds: {', '.join(f'{k} {v:.1f}' for k, v in cpu.items())}", file=sys.stderr)
    steady = _steady_state(stats)
    if steady is not None:
        frames, rate, per_frame = steady
        nodes = sum(v for k, v in per_frame.items() if k != PLAYER)
        print(
            f"run: steady state (after the first {STEADY_AFTER:.0%} of the frames, {frames} frames): "
            f"{rate:.1f} frames/s; CPU ms per frame: "
            + ", ".join(f"{k} {v:.2f}" for k, v in per_frame.items())
            + f", nodes total {nodes:.2f}",
            file=sys.stderr,
        )
    return 0


def _cpu_now(supervisor: Supervisor) -> dict[str, float]:
    return {**supervisor.cpu_seconds(), PLAYER: _own_cpu_seconds()}


def _steady_state(stats: RunStats) -> tuple[int, float, dict[str, float]] | None:
    """(frames, frames/s, CPU ms per frame of each process) between the two steady-state samples."""
    if stats.steady_start is None or stats.steady_end is None:
        return None
    (t0, n0, cpu0), (t1, n1, cpu1) = stats.steady_start, stats.steady_end
    frames = n1 - n0
    if frames <= 0 or t1 <= t0:
        return None
    per_frame = {k: 1e3 * (cpu1[k] - cpu0[k]) / frames for k in cpu1 if k in cpu0}
    return frames, frames / (t1 - t0), per_frame


def _unread_text(unread: int | None) -> str:
    if unread == 0:
        return ""
    count = "an unknown number of" if unread is None else str(unread)
    return f"{count} images unreadable in the damaged input bag; "


def _percentiles_ms(values: list[float]) -> tuple[float, float]:
    if not values:
        return float("nan"), float("nan")
    ordered = sorted(values)
    return ordered[len(ordered) // 2] * 1e3, ordered[int(0.95 * (len(ordered) - 1))] * 1e3


def _own_cpu_seconds() -> float:
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


@contextlib.contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """os.environ with `values` set, restored afterwards."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _overrides(values: dict[str, Any]) -> list[str]:
    return [arg for name, value in values.items() for arg in ("-p", f"{name}:={value}")]


class _Replay:
    def __init__(
        self,
        args: argparse.Namespace,
        supervisor: Supervisor,
        writer: BagWriter,
        namespace: str,
        image_topic: str,
        image_type: str,
        total: int,
        bag_topics: dict[str, str],
    ) -> None:
        self.args = args
        self.supervisor = supervisor
        self.writer = writer
        self.namespace = namespace
        self.image_topic = image_topic
        self.image_type = image_type
        self.bag_topics = bag_topics
        self.stats = RunStats(total=total)
        self.in_flight: deque[_InFlight] = deque()
        self.stamp_times: OrderedDict[int, int] = OrderedDict()  # image stamp -> input bag time
        self.sent_times: OrderedDict[int, float] = OrderedDict()  # image stamp -> when it was sent
        # Bag time of the newest image sent: outputs with no image stamp (diagnostics) get it, so the
        # output bag's timeline is the input's (run() sets the input's start before the first image).
        self.last_bag_time = 0
        self.bag_qos: dict[str, tuple] = {}  # input topic -> its recorded QoS profiles
        self.unread_late = 0  # images the index promised that could not be read
        self.qos_recorded: set[str] = set()  # output topics whose publishers' QoS is set
        self.node: Any = None
        self.output_topics = [*OUTPUT_TOPICS, *([topics.FRAME_IN] if args.record_frames else [])]
        self.encoder_topic: str | None = topics.bag_topic(topics.JOINT_STATES)
        self._lost_logged = 0
        self.profile: dict[str, str] = {}  # environment of this process's DDS participant (the profile)
        self.diagnostics_seen: dict[str, float] = {}  # node name -> when its last diagnostics arrived
        self.diagnostics_values: dict[str, dict[str, str]] = {}  # node name -> its last counters

    # ---------------------------------------------------------------- bag side
    def _messages(self) -> Iterator[BagMessage]:
        with BagReader(self.args.in_bag) as reader:
            try:
                yield from reader.messages()
            except BagError as exc:
                print(f"run: warning: {exc}; replaying what could be read", file=sys.stderr)

    def _copy(self, msg: BagMessage) -> None:
        self.writer.add_topic(msg.topic, msg.msgtype, self.bag_qos.get(msg.topic, ()))
        self.writer.write_raw(msg.topic, msg.timestamp_ns, msg.raw)

    # ---------------------------------------------------------------- ROS side
    def _on_output(self, topic: str, raw: bytes) -> None:
        stamp = header_stamp_ns(raw)
        bag_time = (
            self.stamp_times.get(stamp, self.last_bag_time) if stamp is not None else self.last_bag_time
        )
        name = topics.bag_topic(topic)
        self._record_qos(topic)
        self.writer.write_raw(name, bag_time, raw)
        self.stats.recorded[name] = self.stats.recorded.get(name, 0) + 1
        if topic == topics.HOMOGRAPHY and stamp is not None:
            sent = self.sent_times.get(stamp)
            if sent is not None:
                self.stats.tracker_latencies.append(time.monotonic() - sent)
        if topic == topics.CAMERA_INFO and stamp is not None:
            self._resolve(stamp)
        elif topic == topics.DIAGNOSTICS:
            self._note_diagnostics(raw)

    def _note_diagnostics(self, raw: bytes) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.serialization import deserialize_message

        try:
            array = deserialize_message(raw, DiagnosticArray)
        except Exception:
            return
        now = time.monotonic()
        for status in array.status:
            self.diagnostics_seen[status.name.rsplit("/", 1)[-1]] = now
            self.diagnostics_values[status.name.rsplit("/", 1)[-1]] = {
                kv.key: kv.value for kv in status.values
            }

    def _resolve(self, stamp: int) -> None:
        for k, item in enumerate(self.in_flight):
            if item.stamp_ns == stamp:
                for _ in range(k):  # earlier images got no output: the nodes dropped them
                    self.in_flight.popleft()
                    self.stats.skipped += 1
                self.in_flight.popleft()
                self.stats.calibrated += 1
                self.stats.latencies.append(time.monotonic() - item.sent)
                return
        self.stats.unmatched += 1

    def run(self) -> RunStats:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        from ptz_selfcal.nodes.runtime import reliable_qos

        context = rclpy.Context()
        with _environment(self.profile):  # Fast DDS reads it when the process's first participant starts
            rclpy.init(context=context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO)
            node = rclpy.create_node("ptz_selfcal_run_player", namespace=self.namespace, context=context)
        self.node = node
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        interrupted = threading.Event()

        def on_term(signum: int, _frame: Any) -> None:
            raise KeyboardInterrupt

        previous_term = signal.signal(signal.SIGTERM, on_term)
        try:
            image_pub = node.create_publisher(
                msg_class(self.image_type),
                topics.IMAGE_COMPRESSED
                if self.image_type == "sensor_msgs/msg/CompressedImage"
                else topics.IMAGE_RAW,
                reliable_qos(),
            )
            encoder_pub = None
            if self.encoder_topic is not None and self.encoder_topic in self.bag_topics:
                encoder_pub = node.create_publisher(
                    msg_class(self.bag_topics[self.encoder_topic]), topics.JOINT_STATES, reliable_qos()
                )
            self.subs: dict[str, Any] = {}
            for topic in self.output_topics:
                name = f"{self.namespace}{topic}" if topic.startswith("/") else topic
                self.writer.add_topic(topics.bag_topic(topic), topics.TYPES[topic])
                self.subs[topic] = node.create_subscription(
                    msg_class(topics.TYPES[topic]),
                    name,
                    lambda raw, topic=topic: self._on_output(topic, raw),
                    reliable_qos(),
                    raw=True,
                )
            self.supervisor.start()
            self._wait_ready(node, executor, image_pub, encoder_pub)
            self.stats.started = time.monotonic()
            self._lockstep(executor, image_pub, encoder_pub)
            self._drain(executor)
        except KeyboardInterrupt:
            interrupted.set()
        finally:
            self.stats.finished = self.stats.finished or time.monotonic()
            self.supervisor.stop()
            self.stats.cpu_seconds = self.supervisor.final_cpu_seconds
            signal.signal(signal.SIGTERM, previous_term)
            executor.shutdown()
            node.destroy_node()
            context.try_shutdown()
        if interrupted.is_set():
            raise KeyboardInterrupt
        return self.stats

    def _record_qos(self, topic: str) -> None:
        """An output topic's QoS as its publishers offer it, recorded like rosbag2 does (before its first
        message: diagnostics arrive while the nodes come up)."""
        if topic in self.qos_recorded or self.node is None:
            return
        self.qos_recorded.add(topic)
        name = f"{self.namespace}{topic}" if topic.startswith("/") else f"{self.namespace}/{topic}"
        infos = self.node.get_publishers_info_by_topic(name)
        self.writer.set_qos(topics.bag_topic(topic), [qos_from_rclpy(i.qos_profile) for i in infos])

    def _check_supervisor(self) -> None:
        self.supervisor.poll()
        if self.supervisor.fatal:
            raise CliError(f"the nodes failed: {self.supervisor.fatal}")

    def _wait_ready(self, node: Any, executor: Any, image_pub: Any, encoder_pub: Any) -> None:
        """Until every node is up and connected (the player sees its subscribers and publishers)."""
        ns = self.namespace
        deadline = time.monotonic() + self.args.startup_timeout
        checks = {
            "frame_ingest subscribed to images": lambda: image_pub.get_subscription_count() > 0,
            "frame_ingest subscribed to encoders": lambda: (
                encoder_pub is None or encoder_pub.get_subscription_count() > 0
            ),
            "homography_tracker subscribed to frames": lambda: (
                node.count_subscribers(f"{ns}/{topics.FRAME_IN}") > 0
            ),
            "calibrator subscribed to homographies": lambda: (
                node.count_subscribers(f"{ns}/{topics.HOMOGRAPHY}") > 1
            ),
            "calibrator publishes camera_info": lambda: (
                node.count_publishers(f"{ns}/{topics.CAMERA_INFO}") > 0
            ),
            "frame_ingest publishes frames": lambda: node.count_publishers(f"{ns}/{topics.FRAME_IN}") > 0,
            "homography_tracker publishes": lambda: node.count_publishers(f"{ns}/{topics.HOMOGRAPHY}") > 0,
            "outputs matched to the recorder": lambda: all(
                self.subs[t].get_publisher_count() > 0
                for t in (topics.CAMERA_INFO, topics.FRAME_CALIBRATION, topics.HOMOGRAPHY)
            ),
        }
        if self.args.calibrator_module == NODE_MODULES["calibrator"]:
            # A subscription seen here says nothing about whether the remote writer has matched it yet
            # (each side discovers the other separately), and a volatile writer drops for a reader it
            # has not matched: the nodes' own matched counts (diagnostics) say when the first frame's
            # outputs reach the next stage and the recorder.
            needed = {
                "frame_ingest": {"frame_in_subscribers": 2 if self.args.record_frames else 1},
                "homography_tracker": {"homography_subscribers": 2, "keyframes_subscribers": 2},
                "calibrator": {"camera_info_subscribers": 1, "frame_calibration_subscribers": 1},
            }

            def matched_by_the_nodes() -> bool:
                return all(
                    int(float(self.diagnostics_values.get(node, {}).get(key, -1))) >= n
                    for node, counts in needed.items()
                    for key, n in counts.items()
                )

            checks["outputs matched by the nodes (their diagnostics)"] = matched_by_the_nodes
        while True:
            self._check_supervisor()
            missing = [name for name, ok in checks.items() if not ok()]
            if not missing:
                break
            if time.monotonic() > deadline:
                raise CliError(
                    f"the nodes did not come up within {self.args.startup_timeout:.0f} s: not yet {missing}"
                )
            executor.spin_once(timeout_sec=0.05)
        # Discovery is symmetric but not simultaneous: give the remote ends a moment to match us.
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)

    def _lockstep(self, executor: Any, image_pub: Any, encoder_pub: Any) -> None:
        args = self.args
        stats = self.stats
        lookahead = int(args.encoder_lookahead * 1e9)
        queued: deque[BagMessage] = deque()  # images read ahead (their encoders already sent)
        messages = self._messages()
        exhausted = False
        last_read = 0
        last_report = time.monotonic()
        images_read = 0
        recorded_names = {topics.bag_topic(t) for t in self.output_topics}

        def pump() -> None:
            nonlocal exhausted, last_read, images_read
            while not exhausted and (not queued or last_read <= queued[0].timestamp_ns + lookahead):
                msg = next(messages, None)
                if msg is None:
                    exhausted = True
                    if images_read < stats.total:  # damage the bag's index did not show
                        self.unread_late = stats.total - images_read
                        stats.total = images_read
                    return
                last_read = msg.timestamp_ns
                if msg.topic == self.image_topic:
                    if images_read < stats.total:
                        queued.append(msg)
                        images_read += 1
                    elif args.max_frames:
                        exhausted = True
                    continue
                if msg.topic == self.encoder_topic and encoder_pub is not None:
                    encoder_pub.publish(msg.raw)
                if msg.msgtype not in _IMAGE_TYPES and msg.topic not in recorded_names:
                    self._copy(msg)

        pump()
        while queued or self.in_flight:
            while queued and len(self.in_flight) < args.window:
                msg = queued.popleft()
                stamp = header_stamp_ns(msg.raw)
                stamp = stamp if stamp is not None else msg.timestamp_ns
                self.stamp_times[stamp] = msg.timestamp_ns
                self.sent_times[stamp] = time.monotonic()
                while len(self.stamp_times) > 4096:
                    self.stamp_times.popitem(last=False)
                while len(self.sent_times) > 4096:
                    self.sent_times.popitem(last=False)
                self.last_bag_time = msg.timestamp_ns
                self.in_flight.append(_InFlight(stamp, msg.timestamp_ns, time.monotonic(), stats.sent))
                image_pub.publish(msg.raw)
                if args.with_images:
                    self._copy(msg)
                stats.sent += 1
                pump()
            executor.spin_once(timeout_sec=0.02)
            now = time.monotonic()
            if stats.steady_start is None and stats.answered >= max(1, round(STEADY_AFTER * stats.total)):
                stats.steady_start = (now, stats.answered, _cpu_now(self.supervisor))
            while self.in_flight and now - self.in_flight[0].sent > args.timeout:
                item = self.in_flight.popleft()
                stats.lost += 1
                if self._lost_logged < 5:
                    self._lost_logged += 1
                    print(
                        f"run: image {item.index} (stamp {item.stamp_ns * 1e-9:.6f}) got no CameraInfo "
                        f"within {args.timeout:.1f} s: counted as lost",
                        file=sys.stderr,
                    )
            if now - last_report > 1.0:
                last_report = now
                self._check_supervisor()
                if not args.quiet:
                    print(
                        f"run: {stats.calibrated + stats.skipped + stats.lost}/{stats.total} frames, "
                        f"{stats.rate:.1f} frames/s",
                        file=sys.stderr,
                    )
        stats.finished = time.monotonic()
        stats.steady_end = (stats.finished, stats.answered, _cpu_now(self.supervisor))
        while not exhausted:  # copy the non-image topics after the last image
            pump()
            if queued:
                queued.clear()

    def _drain(self, executor: Any) -> None:
        """Collect what the nodes still publish after the last frame: FrameCalibration after CameraInfo,
        and one more DiagnosticArray from every node that publishes them (final counters in the bag)."""
        recorded = self.stats.recorded
        info = topics.bag_topic(topics.CAMERA_INFO)
        frame = topics.bag_topic(topics.FRAME_CALIBRATION)
        done = time.monotonic()
        end = done + self.args.drain
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)
            fresh = all(t > done for t in self.diagnostics_seen.values()) and len(self.diagnostics_seen) >= 3
            if recorded.get(frame, 0) >= recorded.get(info, 0) and fresh:
                break
