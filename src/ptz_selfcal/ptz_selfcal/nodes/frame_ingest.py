"""frame_ingest node: camera images + PTZ encoders in, IngestedFrame (mono8, working size) out.

Subscribes one image transport, as image_transport does (parameter `image_transport`: topics.IMAGE_RAW
or topics.IMAGE_COMPRESSED), and topics.JOINT_STATES; publishes one IngestedFrame per usable image on
topics.FRAME_IN with the encoders interpolated to the image stamp (frontend/encoders.py), the
full-resolution size and the working scale, and relays that image, serialized bytes unchanged, on
topics.IMAGE_RELAY (or IMAGE_RELAY_COMPRESSED): with the calibrator's CameraInfo of the same header the
camera pair a CameraSubscriber (image_proc) finds. This node relays, not the calibrator, because it
holds the image already: the calibrator would need a second full-resolution subscription and a buffer
to match it to its output. The relay is published only while it has subscribers; DiagnosticArray on
topics.DIAGNOSTICS (STALE while images or encoder messages do not arrive, ERROR while every one is
unusable). Unusable images (unsupported or lying encoding, step/size mismatch, zero or huge
size, undecodable compressed data, truncated messages, duplicate stamps) are counted per kind, logged once
per kind and skipped; black or flat frames pass (the tracker decides). Images are taken serialized
(raw subscriptions) and read in place (nodes/conversions.parse_serialized_image), so a huge one is refused
from its header without a copy of its pixels. Every encoder message already received is taken at once,
so frames never wait behind a backlog of them. Run:
    python -m ptz_selfcal.nodes.frame_ingest --ros-args -p working_width:=640
"""

from __future__ import annotations

import itertools
import math
import sys
import time
from collections import Counter, deque
from dataclasses import dataclass, replace
from typing import Any

import cv2
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CompressedImage, Image, JointState
from std_msgs.msg import Float64, Header

from ptz_selfcal import topics
from ptz_selfcal.frontend.encoders import EncoderConfig, EncoderInterpolator, QueryStatus
from ptz_selfcal.nodes.conversions import (
    ConfigError,
    FrameError,
    ImageLimits,
    Param,
    SerializedImage,
    WorkingImage,
    compressed_to_working,
    declare_params,
    diagnostic_values,
    fill_mono8,
    image_to_working,
    in_range,
    one_of,
    parse_serialized_image,
    stamp_to_ns,
    stamp_to_sec,
)
from ptz_selfcal.nodes.runtime import (
    CountedWarnings,
    FailureRun,
    InputWatch,
    camera_name_of,
    qos_overrides,
    reliable_qos,
    run_node,
    set_level,
)
from ptz_selfcal.tools.bagio import header_stamp_ns
from ptz_selfcal_msgs.msg import HomographyStamped, IngestedFrame

PARAMS = [
    Param(
        "image_transport",
        "raw",
        "the image topic subscribed, as image_transport's: raw (image_raw) or compressed "
        "(image_raw/compressed); both: each image once from whichever copy comes first (sources that mix "
        "transports)",
        one_of("raw", "compressed", "both"),
    ),
    Param(
        "relay_image",
        True,
        "republish each ingested image on selfcal/image_raw (compressed: selfcal/image_raw/compressed), "
        "header and bytes unchanged, so that it and selfcal/camera_info are a camera pair (only while "
        "subscribed)",
        None,
    ),
    Param(
        "sensor_reliability",
        "best_effort",
        "image/encoder subscriptions: best_effort (accepts best-effort and reliable publishers) or reliable",
        one_of("best_effort", "reliable"),
    ),
    Param(
        "queue_policy",
        "latest",
        "latest: keep only the newest queue_depth frames (KEEP_LAST: bounded memory and latency live), so a "
        "slow stage sheds frames (counted downstream from gaps in seq); lossless: queue every frame "
        "(KEEP_ALL, for replays that wait for each result)",
        one_of("lossless", "latest"),
    ),
    Param(
        "shed_before_decoding",
        True,
        "queue_policy latest: while queue_depth + 1 frames published on frame_in have no homography yet "
        "(the tracker's queue of that depth is full, and it works on one), the newest image waits undecoded "
        "for the tracker's next answer and a newer one replaces it: the frames the tracker's queue would "
        "drop are shed before decoding (counted: skipped_tracker_behind); a frame unanswered for "
        "in_flight_timeout s stops counting",
        None,
    ),
    Param(
        "in_flight_timeout",
        1.0,
        "s after which a frame published on frame_in without a homography no longer counts as in flight "
        "(the tracker shed or lost it, or restarted)",
        in_range(0.01, 60.0),
    ),
    Param(
        "queue_depth",
        50,
        "KEEP_LAST depth of image queues with queue_policy latest (50: bursts up to 50 frames are kept)",
        in_range(1, 1000),
    ),
    Param(
        "working_width",
        640,
        "target width of the working image; the node downscales by the nearest integer factor (0: full size)",
        in_range(0, 100_000),
    ),
    Param(
        "joint_names",
        ["pan", "tilt", "zoom"],
        "JointState names of the pan, tilt and zoom joints (as the driver names them, e.g. axis_pan_joint); "
        "two names: joint_states has no zoom (it comes from zoom_topic, or there is none: zoom NaN)",
        None,
    ),
    Param(
        "zoom_topic",
        "",
        "topic of the zoom encoder when the driver publishes it apart from joint_states (relative to the "
        "namespace; empty: none)",
        None,
    ),
    Param(
        "zoom_topic_type",
        "joint_state",
        "zoom_topic's type: joint_state (the zoom joint, or its only position; header stamp) or float64 "
        "(std_msgs/Float64, stamped on arrival with this node's clock)",
        one_of("joint_state", "float64"),
    ),
    Param(
        "encoder_time_offset",
        0.0,
        "seconds added to encoder stamps to put them on the image clock (encoder lag: positive when the "
        "head reports a position later than the image stamps it)",
        in_range(-60.0, 60.0),
        read_only=False,
    ),
    Param(
        "encoder_max_gap",
        0.5,
        "seconds: encoder samples further apart do not bracket a stamp",
        in_range(1e-3, 60.0),
    ),
    Param(
        "encoder_extrapolate_slow",
        True,
        "encoders slower than encoder_wait (e.g. 1 Hz heads): frames do not wait for the next sample; their "
        "value is extrapolated up to 1.5 encoder periods past the newest one (counted: "
        "frames_encoders_extrapolated). encoder_max_gap grows to 2.5 periods whatever this says",
        None,
    ),
    Param(
        "encoder_max_hold",
        0.05,
        "seconds: a single encoder sample this close to a stamp is used",
        in_range(0.0, 10.0),
    ),
    Param(
        "encoder_max_future",
        10.0,
        "seconds: encoder stamps further ahead of the newest image are rejected",
        in_range(1e-3, 1e6),
    ),
    Param(
        "encoder_buffer_size", 2000, "encoder samples kept per joint (bounded memory)", in_range(2, 1_000_000)
    ),
    Param(
        "encoder_wait",
        0.2,
        "seconds (wall time) a frame may wait for an encoder sample newer than its stamp (0: never wait)",
        in_range(0.0, 10.0),
    ),
    Param(
        "max_pending_frames",
        30,
        "frames that may wait (for encoders or for the first subscriber) at once; the oldest is then "
        "published (or dropped without subscribers)",
        in_range(1, 1000),
    ),
    Param(
        "wait_for_subscribers",
        1,
        "hold frames until frame_in has this many matched subscribers, so none is published into the void "
        "while the graph connects (0: never hold)",
        in_range(0, 100),
    ),
    Param("max_image_pixels", 50_000_000, "larger images are refused before decoding", in_range(1, 1 << 40)),
    Param(
        "max_image_bytes",
        200_000_000,
        "larger image payloads are refused (read from the serialized message's header, before any copy)",
        in_range(1, 1 << 40),
    ),
    Param("mono16_max", 65535, "mono16 value shown as white (4095 for a 12-bit sensor)", in_range(1, 65535)),
    Param("diagnostics_period", 1.0, "seconds between DiagnosticArray messages", in_range(0.05, 3600.0)),
    Param(
        "camera_name",
        "",
        "name of the camera, the diagnostics' hardware_id ('': the namespace's last component, /cam1: cam1)",
        None,
    ),
    Param(
        "stale_timeout",
        5.0,
        "seconds without images or without encoder messages after which diagnostics report STALE (also "
        "before the first one)",
        in_range(0.1, 3600.0),
    ),
    Param(
        "error_threshold",
        3,
        "consecutive unusable inputs (images, or encoder messages without any of joint_names) after which "
        "diagnostics report ERROR",
        in_range(1, 1_000_000),
    ),
]


_MAX_HEADER_BYTES = 65536  # serialized header, frame_id, encoding/format: more than any sane message has


_MAX_DRAIN = 1000  # encoder messages taken at once (bounds one callback's time)
_NO_ZOOM = "(no zoom encoder)"


class InFlight:
    """Frames published on frame_in that the tracker has not answered yet (a homography of their stamp or
    a later one: stamps rise, and the tracker answers in order): how far behind it is. A frame unanswered
    for `timeout` s stops counting: the tracker shed or lost it, or restarted."""

    def __init__(self, timeout: float) -> None:
        self.timeout = timeout
        self._sent: deque[tuple[int, float]] = deque()  # (stamp ns, monotonic time published)

    def sent(self, stamp_ns: int, now: float) -> None:
        self._sent.append((stamp_ns, now))

    def answered(self, stamp_ns: int) -> None:
        while self._sent and self._sent[0][0] <= stamp_ns:
            self._sent.popleft()

    def count(self, now: float) -> int:
        while self._sent and now - self._sent[0][1] > self.timeout:
            self._sent.popleft()
        return len(self._sent)


def _take(subscription: Any) -> Any:
    """The next message already received by a subscription, None if there is none (what rclpy's executor
    does for one message per wake-up)."""
    with subscription.handle:
        taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
    return None if taken is None else taken[0]


def _header_of(msg: Any) -> Header:
    """std_msgs/Header of a deserialized message or of a SerializedImage (read in place)."""
    if isinstance(msg, SerializedImage):
        return Header(stamp=Time(sec=msg.sec, nanosec=msg.nanosec), frame_id=msg.frame_id)
    return msg.header


def working_image_msg(header: Any, image: Any) -> Image:
    """IngestedFrame's sensor_msgs/Image: the mono8 working image, copied once."""
    # check_fields: its data setter keeps the filled array; unchecked, it copies the pixels once more
    msg = Image(check_fields=True)
    msg.header = header
    fill_mono8(msg, image)
    return msg


@dataclass
class _Pending:
    frame: WorkingImage
    header: Any
    arrived: float  # monotonic
    raw: bytes | None = None  # the serialized input image, for the relay
    compressed: bool = False


class FrameIngest(Node):
    def __init__(self, **kwargs: Any) -> None:
        # in the camera's namespace unless launched into another (__ns remap, or a namespace argument)
        super().__init__("frame_ingest", **{"namespace": topics.NAMESPACE, **kwargs})
        p = declare_params(self, PARAMS)
        names = list(p["joint_names"])
        if len(names) not in (2, 3) or len(set(names)) != len(names) or not all(names):
            raise ConfigError(f"parameter joint_names must be two or three distinct names, got {names}")
        self._p = p
        # joint_states carries pan, tilt and (with three names and no zoom_topic) zoom; a zoom of its own
        # topic goes into the interpolator under the third name (or "zoom"); no zoom at all: a stand-in
        # joint held at 0 beside every pan/tilt sample, published as NaN
        self._zoom_joint = names[2] if len(names) == 3 else "zoom" if p["zoom_topic"] else _NO_ZOOM
        self._state_joints = tuple(names) if len(names) == 3 and not p["zoom_topic"] else tuple(names[:2])
        self._encoder_config = EncoderConfig(
            joints=(names[0], names[1], self._zoom_joint),
            time_offset=p["encoder_time_offset"],
            max_gap=p["encoder_max_gap"],
            max_hold=p["encoder_max_hold"],
            max_future=p["encoder_max_future"],
            max_samples=p["encoder_buffer_size"],
        )
        try:
            self._encoders = EncoderInterpolator(self._encoder_config)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        self._encoder_stamps: deque[float] = deque(maxlen=9)  # recent joint_states stamps
        self._encoder_period: float | None = None
        self._limits = ImageLimits(p["max_image_pixels"], p["max_image_bytes"], p["mono16_max"])
        self._working_width = p["working_width"]
        self._wait = p["encoder_wait"]

        self._counts: Counter[str] = Counter()  # frames_in, frames_out, skipped_<kind>, ...
        self._warnings = CountedWarnings(self, self._counts)
        self._seq = 0
        self._recent_stamps: deque[int] = deque(maxlen=8)
        self._newest_image_time: float | None = None
        self._pending: deque[_Pending] = deque()
        self._last_skipped_total = 0
        self._decode_times: deque[float] = deque(maxlen=1000)  # seconds per conversion to mono8
        self._last_received: float | None = None  # stamp of the previous image received (s)
        self._intervals: deque[float] = deque(maxlen=51)  # recent image stamp intervals (s)

        sensor = QoSProfile(
            history=HistoryPolicy.KEEP_ALL if p["queue_policy"] == "lossless" else HistoryPolicy.KEEP_LAST,
            depth=p["queue_depth"] if p["queue_policy"] == "latest" else 0,
            reliability=ReliabilityPolicy.BEST_EFFORT
            if p["sensor_reliability"] == "best_effort"
            else ReliabilityPolicy.RELIABLE,
        )
        encoder_qos = QoSProfile(depth=100, reliability=sensor.reliability)  # KEEP_LAST: bounded
        # latest: the writer keeps only the newest frames too, so a slow tracker never backs frames up here
        out_qos = reliable_qos() if p["queue_policy"] == "lossless" else reliable_qos(p["queue_depth"])
        self._pub = self.create_publisher(IngestedFrame, topics.FRAME_IN, out_qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable_qos(10))
        # KEEP_LAST: a slow consumer of the relay never backs full-resolution images up in this process
        relay_qos = reliable_qos(p["queue_depth"])
        self._relays: dict[bool, Any] = {}  # compressed? -> its relay publisher
        for compressed, msg_type, name in (
            (False, Image, topics.IMAGE_RELAY),
            (True, CompressedImage, topics.IMAGE_RELAY_COMPRESSED),
        ):
            if p["relay_image"] and p["image_transport"] in ("compressed" if compressed else "raw", "both"):
                self._relays[compressed] = self.create_publisher(
                    msg_type, name, relay_qos, qos_overriding_options=qos_overrides()
                )
        # raw=True: the callback gets the serialized message, whose header is read in place, so a huge image
        # is refused before any copy of its pixels and a good one is converted without rclpy's two copies
        if p["image_transport"] in ("raw", "both"):
            self.create_subscription(
                Image,
                topics.IMAGE_RAW,
                self._on_raw,
                sensor,
                raw=True,
                qos_overriding_options=qos_overrides(),
            )
        if p["image_transport"] in ("compressed", "both"):
            self.create_subscription(
                CompressedImage,
                topics.IMAGE_COMPRESSED,
                self._on_compressed,
                sensor,
                raw=True,
                qos_overriding_options=qos_overrides(),
            )
        if p["zoom_topic"]:
            self.create_subscription(
                Float64 if p["zoom_topic_type"] == "float64" else JointState,
                p["zoom_topic"],
                self._on_zoom,
                encoder_qos,
                qos_overriding_options=qos_overrides(),
            )
        self._joint_sub = self.create_subscription(
            JointState,
            topics.JOINT_STATES,
            self._on_joints,
            encoder_qos,
            qos_overriding_options=qos_overrides(),
        )
        # latest: the tracker's answers tell how far behind it is, so that an image it could not take in
        # time is shed here, before decoding, rather than decoded and then dropped from its queue
        self._in_flight: InFlight | None = None
        self._held: tuple[Any, Any, bytes, bool] | None = None  # the newest image, waiting for the tracker
        self._answers = None
        self._max_in_flight = p["queue_depth"] + 1
        if p["queue_policy"] == "latest" and p["shed_before_decoding"]:
            self._in_flight = InFlight(p["in_flight_timeout"])
            self._answers = self.create_subscription(
                HomographyStamped,
                topics.HOMOGRAPHY,
                self._on_answer,
                QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT),
                raw=True,
            )
        self._image_watch = InputWatch("images", p["stale_timeout"])
        self._encoder_watch = InputWatch("encoder messages", p["stale_timeout"])
        self._bad_images = FailureRun()
        self._bad_encoders = FailureRun()
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        # Retries only while frames wait (for encoders or a subscriber): an always-on 50 Hz timer costs
        # every frame's executor (each rclpy wake-up ~0.6 ms of CPU) and delays the frames behind it.
        self._flush_timer = self.create_timer(0.02, self._flush_pending)
        self._flush_timer.cancel()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        # OpenCV's own warnings about corrupt data would repeat per frame: we count and log them ourselves.
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        self.get_logger().info(
            f"image_transport={p['image_transport']} ({p['sensor_reliability']}, {p['queue_policy']}), "
            f"working_width={self._working_width}, joints={names}"
            f"{f' + {self._zoom_joint} on ' + p['zoom_topic'] if p['zoom_topic'] else ''}, encoder offset "
            f"{p['encoder_time_offset']:+.3f} s -> {self._pub.topic_name}"
        )

    # ------------------------------------------------------------------ parameters
    def _on_set_parameters(self, params: list) -> Any:
        from rcl_interfaces.msg import SetParametersResult

        for param in params:
            if param.name == "encoder_time_offset":
                value = param.value
                if not isinstance(value, float | int) or not -60.0 <= value <= 60.0:
                    return SetParametersResult(
                        successful=False, reason="encoder_time_offset must be in [-60, 60] s"
                    )
                self._encoder_config = replace(self._encoder_config, time_offset=float(value))
                self._encoders = EncoderInterpolator(self._encoder_config)  # stamps shift: start afresh
                self.get_logger().info(f"encoder_time_offset set to {value:+.3f} s (encoder buffer cleared)")
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ input
    def _skip(self, kind: str, message: str) -> None:
        self._warnings.warn_once(kind, f"frame skipped ({kind}): {message}", key=f"skipped_{kind}")

    def _note(self, kind: str, message: str) -> None:
        """A counted anomaly that does not stop the frame (logged once per kind)."""
        self._warnings.warn_once(kind, f"{kind}: {message}")

    def _on_raw(self, data: bytes) -> None:
        self._counts["frames_in_raw"] += 1
        msg = self._read(data, Image)
        if msg is not None:
            self._ingest(msg, lambda: image_to_working(msg, self._working_width, self._limits), data, False)

    def _on_compressed(self, data: bytes) -> None:
        self._counts["frames_in_compressed"] += 1
        msg = self._read(data, CompressedImage)
        if msg is not None:
            self._ingest(
                msg, lambda: compressed_to_working(msg, self._working_width, self._limits), data, True
            )

    def _read(self, data: bytes, msg_type: Any) -> Any:
        """A received serialized image with its header fields readable (pixels not copied); None (counted
        and logged) when it is refused before conversion."""
        try:
            msg = parse_serialized_image(data, compressed=msg_type is CompressedImage)
        except FrameError as exc:  # truncated: no stamp to go by
            self._counts["frames_in"] += 1
            self._skip(exc.kind, f"{msg_type.__name__}: {exc}")
            return None
        if msg is not None:
            return msg
        # Another encapsulation than plain CDR: deserialise the usual way, but never a payload that is too
        # large anyway (the serialized size bounds the pixel data from above by a few hundred bytes).
        if len(data) > self._limits.max_bytes + _MAX_HEADER_BYTES:
            self._counts["frames_in"] += 1
            self._skip(
                "too_large",
                f"serialized {msg_type.__name__} of {len(data)} bytes exceeds max_image_bytes="
                f"{self._limits.max_bytes}",
            )
            return None
        try:
            return deserialize_message(data, msg_type)
        except Exception as exc:  # rclpy raises several types for data it cannot read
            self._counts["frames_in"] += 1
            self._skip("malformed", f"{msg_type.__name__}: {type(exc).__name__}: {exc}")
            return None

    def _ingest(self, msg: Any, convert: Any, data: bytes, compressed: bool) -> None:
        self._counts["frames_in"] += 1
        header = _header_of(msg)
        stamp_ns = stamp_to_ns(header.stamp)
        if stamp_ns in self._recent_stamps:
            self._skip("duplicate_stamp", f"a frame with stamp {stamp_ns * 1e-9:.6f} was already ingested")
            return
        held = self._held
        if held is not None and stamp_to_ns(_header_of(held[0]).stamp) == stamp_ns:
            self._skip("duplicate_stamp", f"a frame with stamp {stamp_ns * 1e-9:.6f} is already waiting")
            return
        self._note_interval(stamp_ns * 1e-9)
        if self._tracker_behind():  # latest wins: the newest waits undecoded, an older waiting one is shed
            if held is not None:
                self._shed_held()
            self._held = (msg, convert, data, compressed)
            return
        if held is not None:  # the tracker caught up (or stopped answering): the waiting one goes first
            self._held = None
            self._convert(*held)
        self._convert(msg, convert, data, compressed)

    def _shed_held(self) -> None:
        self._held = None
        self._skip(
            "tracker_behind",
            f"{self._max_in_flight} frames on frame_in had no homography yet and a newer image "
            "came: shed before decoding (the tracker is slower than the images; logged once, counted)",
        )

    def _convert(self, msg: Any, convert: Any, data: bytes, compressed: bool) -> None:
        header = _header_of(msg)
        stamp_ns = stamp_to_ns(header.stamp)
        start = time.perf_counter()
        try:
            frame = convert()
            self._decode_times.append(time.perf_counter() - start)
        except FrameError as exc:
            self._skip(exc.kind, str(exc))
            return
        except Exception as exc:  # never let one frame take the node down
            self._skip("internal_error", f"{type(exc).__name__}: {exc}")
            return
        self._recent_stamps.append(stamp_ns)
        t = stamp_to_sec(header.stamp)
        if self._newest_image_time is not None and t < self._newest_image_time:
            self._note(
                "image_stamp_out_of_order", f"image stamp {t:.6f} older than {self._newest_image_time:.6f}"
            )
        # The latest image (not the largest stamp) is the reference of the encoders' far-future check, so
        # one image with a wild stamp does not disable the check for good.
        self._newest_image_time = t
        self._pending.append(_Pending(frame, header, time.monotonic(), data, compressed))
        self._flush_pending()

    def _tracker_behind(self) -> bool:
        """Whether queue_depth + 1 frames wait for the tracker (only while one answers at all: with no
        homography publisher every frame goes out, as without this check)."""
        flight = self._in_flight
        if flight is None or flight.count(time.monotonic()) < self._max_in_flight:
            return False
        return self._answers is not None and self._answers.get_publisher_count() > 0

    def _on_answer(self, raw: bytes) -> None:
        stamp = header_stamp_ns(raw)
        if stamp is not None and self._in_flight is not None:
            self._in_flight.answered(stamp)
        if self._held is not None and not self._tracker_behind():
            held, self._held = self._held, None
            self._convert(*held)

    def _note_interval(self, t: float) -> None:
        """Estimate images that never reached this node (shed by a latest-wins queue, lost by a best-effort
        link) from gaps in the stamps: a gap of n nominal frame intervals means n - 1 missing images."""
        previous, self._last_received = self._last_received, t
        if previous is None or t <= previous:
            return
        interval = t - previous
        self._intervals.append(interval)
        nominal = sorted(self._intervals)[len(self._intervals) // 2]
        if len(self._intervals) >= 10 and interval > 1.5 * nominal:
            if interval > 10.0:  # a stream pause or a stamp jump (wild stamp, clock reset), not lost images
                self._counts["image_stamp_gaps_over_10s"] += 1
            else:
                self._counts["input_frames_missing_estimate"] += round(interval / nominal) - 1

    def _on_joints(self, msg: JointState) -> None:
        # The executor hands over one message per subscription and wake-up: with frames (latest-wins)
        # arriving as often as encoder messages, a backlog of encoder messages built up while this process
        # had no CPU never shrank, and every later frame waited (up to encoder_wait) for its encoders
        # behind it. So every encoder message already received is taken now.
        self._add_joints(msg)
        self._drain_joints()
        self._flush_pending()

    def _drain_joints(self) -> None:
        """Every encoder message already received, into the interpolator."""
        for _ in range(_MAX_DRAIN):
            more = _take(self._joint_sub)
            if more is None:
                break
            self._counts["encoder_messages_drained"] += 1
            self._add_joints(more)

    def _add_joints(self, msg: JointState) -> None:
        self._counts["encoder_messages"] += 1
        names = list(msg.name)
        positions = list(msg.position)
        if len(positions) != len(names):
            self._note(
                "encoder_bad_message", f"JointState with {len(names)} names and {len(positions)} positions"
            )
            return
        missing = [j for j in self._state_joints if j not in names]
        if len(missing) == len(self._state_joints):
            self._note("encoder_no_known_joint", f"JointState without any of {list(self._state_joints)}")
            return
        if missing:
            self._note("encoder_missing_joints", f"JointState without {missing} (the others are used)")
        stamp = stamp_to_sec(msg.header.stamp)
        values = {n: v for n, v in zip(names, positions) if n in self._state_joints}
        if self._zoom_joint == _NO_ZOOM:
            values[_NO_ZOOM] = 0.0
        self._store(stamp, values)
        self._note_encoder_period(stamp)

    def _store(self, stamp: float, values: dict[str, float]) -> None:
        for joint, reason in self._encoders.add(stamp, values, self._newest_image_time):
            self._note(f"encoder_rejected_{reason.value}", f"{joint} sample rejected ({reason.value})")

    def _on_zoom(self, msg: Any) -> None:
        """The zoom encoder of its own topic (a driver such as axis_camera publishes it apart)."""
        self._counts["zoom_messages"] += 1
        if isinstance(msg, Float64):
            stamp, value = self.get_clock().now().nanoseconds * 1e-9, msg.data
        else:
            names, positions = list(msg.name), list(msg.position)
            if self._zoom_joint in names and len(positions) == len(names):
                value = positions[names.index(self._zoom_joint)]
            elif len(positions) == 1:
                value = positions[0]
            else:
                self._note("zoom_no_value", f"zoom JointState without {self._zoom_joint} or one position")
                return
            stamp = stamp_to_sec(msg.header.stamp)
        self._store(stamp, {self._zoom_joint: float(value)})
        self._flush_pending()

    def _note_encoder_period(self, stamp: float) -> None:
        """The encoders' own period (median of recent joint_states intervals) sets how far apart samples
        may bracket a stamp and, for heads slower than encoder_wait, how far a frame's value is
        extrapolated instead of waiting a period for the next sample."""
        if self._encoder_stamps and stamp <= self._encoder_stamps[-1]:
            return
        self._encoder_stamps.append(stamp)
        if len(self._encoder_stamps) < 4:
            return
        ordered = list(self._encoder_stamps)
        intervals = sorted(b - a for a, b in itertools.pairwise(ordered))
        period = intervals[len(intervals) // 2]
        self._encoder_period = period
        gap = max(self._p["encoder_max_gap"], min(60.0, 2.5 * period))
        hold = self._p["encoder_max_hold"]
        if self._p["encoder_extrapolate_slow"] and period > self._wait:
            hold = max(hold, min(10.0, 1.5 * period))
        config = self._encoders.config
        if (config.max_gap, config.max_hold) != (gap, hold):
            self._encoders.config = replace(config, max_gap=gap, max_hold=hold)

    # ------------------------------------------------------------------ output
    def _flush_pending(self) -> None:
        self._flush_pending_once()
        if self._pending and self._flush_timer.is_canceled():
            self._flush_timer.reset()
        elif not self._pending and not self._flush_timer.is_canceled():
            self._flush_timer.cancel()

    def _flush_pending_once(self) -> None:
        now = time.monotonic()
        while self._pending and self._pub.get_subscription_count() < self._p["wait_for_subscribers"]:
            if len(self._pending) <= self._p["max_pending_frames"]:
                return
            self._pending.popleft()
            self._note("dropped_no_subscriber", "frames dropped while nothing subscribes to frame_in")
        drained = False
        while self._pending:
            item = self._pending[0]
            query = self._encoders.query(stamp_to_sec(item.header.stamp))
            if query.status is QueryStatus.NOT_YET and self._wait > 0 and not drained:
                # The executor runs a due timer before the subscriptions: after this process had no CPU
                # for encoder_wait, the retry timer came first and gave up on frames whose encoder
                # samples had arrived meanwhile (likely how a lock-step replay at load 11 left 13 of 48
                # frames without encoders). A frame waits for its encoders to come, not for their
                # callback to run.
                self._drain_joints()
                drained = True
                query = self._encoders.query(stamp_to_sec(item.header.stamp))
            waiting = (
                query.status is QueryStatus.NOT_YET
                and self._wait > 0
                and now - item.arrived < self._wait
                and len(self._pending) <= self._p["max_pending_frames"]
            )
            if waiting:
                return
            self._pending.popleft()
            if query.status is QueryStatus.NOT_YET and self._wait > 0:
                self._counts["encoder_wait_expired"] += 1
            self._publish(item, query)

    def _publish(self, item: _Pending, query: Any) -> None:
        frame = item.frame
        msg = IngestedFrame()
        msg.header = item.header
        msg.image = working_image_msg(item.header, frame.image)
        msg.full_width = frame.full_width
        msg.full_height = frame.full_height
        msg.scale = frame.scale
        msg.encoders.pan = query.pan
        msg.encoders.tilt = query.tilt
        msg.encoders.zoom = math.nan if self._zoom_joint == _NO_ZOOM else query.zoom
        msg.encoders.valid = query.valid
        newest = self._encoders.newest_stamp()
        if query.valid and newest is not None and stamp_to_sec(item.header.stamp) > newest:
            self._counts["frames_encoders_extrapolated"] += 1  # past the newest sample: a prediction
        if not query.valid:
            self._counts[f"encoders_invalid_{query.status.value.lower()}"] += 1
        msg.seq = self._seq
        self._seq += 1
        self._pub.publish(msg)
        self._counts["frames_out"] += 1
        if self._in_flight is not None:
            self._in_flight.sent(stamp_to_ns(item.header.stamp), time.monotonic())
        relay = self._relays.get(item.compressed)
        # only while subscribed: without readers the writer would still copy every full-resolution image
        if relay is not None and item.raw is not None and relay.get_subscription_count() > 0:
            relay.publish(item.raw)
            self._counts["frames_relayed"] += 1

    def _publish_diagnostics(self) -> None:
        counters: dict[str, Any] = {"frames_in": 0, "frames_out": 0}
        counters.update(sorted(self._counts.items()))
        counters["encoder_samples_accepted"] = self._encoders.samples_accepted
        if self._encoder_period is not None:
            counters["encoder_period_s"] = f"{self._encoder_period:.3f}"
        counters["encoder_max_gap_s"] = f"{self._encoders.config.max_gap:.3f}"
        counters["encoder_max_hold_s"] = f"{self._encoders.config.max_hold:.3f}"
        counters["encoder_samples_rejected"] = sum(self._encoders.rejections.values())
        counters["pending_frames"] = len(self._pending)
        # matched on this side (what a frame published now reaches), so a graph's readiness is observable
        counters["frame_in_subscribers"] = self._pub.get_subscription_count()
        if self._decode_times:
            d = sorted(self._decode_times)
            counters["decode_ms_median"] = f"{1e3 * d[len(d) // 2]:.2f}"
            counters["decode_ms_p95"] = f"{1e3 * d[int(0.95 * (len(d) - 1))]:.2f}"
        skipped = sum(v for k, v in self._counts.items() if k.startswith("skipped_"))
        counters["skipped_total"] = skipped
        status = DiagnosticStatus()
        status.name = self.get_fully_qualified_name()
        status.hardware_id = camera_name_of(self, self._p["camera_name"])
        error, warn = [], []
        # a duplicate (the raw and the compressed copy of one image) is no failure of the input
        duplicates = self._counts["skipped_duplicate_stamp"]
        bad_run = self._bad_images.update(self._counts["frames_in"] - duplicates, skipped - duplicates)
        if bad_run >= self._p["error_threshold"]:
            unusable = sorted(
                k.removeprefix("skipped_")
                for k in self._counts
                if k.startswith("skipped_") and k != "skipped_duplicate_stamp"
            )
            error.append(f"the last {bad_run} images were all unusable ({', '.join(unusable)})")
        joints = list(self._state_joints)
        encoder_run = self._bad_encoders.update(
            self._counts["encoder_messages"], self._counts["encoder_no_known_joint"]
        )
        if encoder_run >= self._p["error_threshold"]:
            error.append(f"the last {encoder_run} joint_states carry none of joint_names {joints}")
        stale = [
            reason
            for reason in (
                self._image_watch.stale(self._counts["frames_in"]),
                self._encoder_watch.stale(self._counts["encoder_messages"]),
            )
            if reason
        ]
        if skipped > self._last_skipped_total:
            warn.append(f"{skipped - self._last_skipped_total} frames skipped since the last report")
        self._last_skipped_total = skipped
        set_level(status, f"{counters['frames_out']} frames ingested", error=error, stale=stale, warn=warn)
        status.values = diagnostic_values(counters)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self._diag_pub.publish(array)

    def close(self) -> None:
        """Publish what is still waiting for encoders (called by run_node before shutdown)."""
        while self._pending:
            item = self._pending.popleft()
            try:
                self._publish(item, self._encoders.query(stamp_to_sec(item.header.stamp)))
            except Exception:  # the context may already be shut down (SIGINT): nothing left to do
                self._pending.clear()


def main(args: list[str] | None = None) -> int:
    return run_node(FrameIngest, args, "frame_ingest")


if __name__ == "__main__":
    sys.exit(main())
