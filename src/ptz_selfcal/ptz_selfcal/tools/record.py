"""`ptz-selfcal record OUT_BAG --topics ...`: write the raw messages of topics to a new mcap bag."""

from __future__ import annotations

import argparse
import sys
import time

from ptz_selfcal.tools.bagio import BagError, BagWriter, msg_class, qos_from_rclpy
from ptz_selfcal.tools.cli import CliError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("out_bag", help="new bag directory to create (refuses an existing path)")
    parser.add_argument("--topics", nargs="+", required=True, help="topics to record")
    parser.add_argument(
        "--type",
        action="append",
        default=[],
        metavar="TOPIC=TYPE",
        help="message type of a topic (e.g. /ptz/image_raw=sensor_msgs/msg/Image); otherwise discovered",
    )
    parser.add_argument("--discovery-timeout", type=float, default=10.0, help="seconds to discover types")
    parser.add_argument(
        "--max-messages", type=int, default=0, help="stop after this many messages (0: never)"
    )
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: never)")
    parser.add_argument(
        "--idle-timeout",
        type=float,
        default=0.0,
        help="stop when nothing arrived for this many seconds after the first message (0: never)",
    )


def run(args: argparse.Namespace) -> int:
    types = _explicit_types(args)
    try:
        writer = BagWriter(args.out_bag)
    except BagError:
        raise
    except Exception as exc:
        raise CliError(f"{args.out_bag}: cannot create bag ({exc})") from exc
    try:
        return _record(args, writer, types)
    finally:
        writer.close()


def _explicit_types(args: argparse.Namespace) -> dict[str, str]:
    types = {}
    for item in args.type:
        topic, sep, msgtype = item.partition("=")
        if not sep or msgtype.count("/") != 2:
            raise CliError(f"--type wants TOPIC=pkg/msg/Name, got {item!r}")
        types[topic] = msgtype
    return types


def _record(args: argparse.Namespace, writer: BagWriter, types: dict[str, str]) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.qos import QoSProfile

    rclpy.init()
    node = rclpy.create_node("ptz_selfcal_record")
    counts = dict.fromkeys(args.topics, 0)
    last_message = [0.0]
    try:
        types.update(
            _discover_types(node, [t for t in args.topics if t not in types], args.discovery_timeout)
        )
        for topic in args.topics:
            if topic not in types:
                node.get_logger().warning(f"{topic}: no publisher discovered, not recorded")
                continue
            writer.add_topic(topic, types[topic], _offered(node, topic))
            qos = QoSProfile(depth=1000, reliability=_reliability(node, topic))

            def on_message(raw: bytes, topic: str = topic) -> None:
                if not counts[topic]:  # publishers that appeared after the subscription count too
                    writer.set_qos(topic, _offered(node, topic))
                writer.write_raw(topic, node.get_clock().now().nanoseconds, raw)
                counts[topic] += 1
                last_message[0] = time.monotonic()

            node.create_subscription(msg_class(types[topic]), topic, on_message, qos, raw=True)
        if not any(t in types for t in args.topics):
            raise CliError("none of the topics could be recorded (no types)")
        print(f"record: recording {', '.join(t for t in args.topics if t in types)}", flush=True)
        start = time.monotonic()
        while rclpy.ok():
            rclpy.spin_once(node, timeout_sec=0.1)
            total = sum(counts.values())
            now = time.monotonic()
            if args.max_messages and total >= args.max_messages:
                break
            if args.duration and now - start >= args.duration:
                break
            if args.idle_timeout and total and now - last_message[0] >= args.idle_timeout:
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        summary = ", ".join(f"{t}: {n}" for t, n in counts.items())
        print(f"record: wrote {sum(counts.values())} messages to {args.out_bag} ({summary})", file=sys.stderr)
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


def _discover_types(node, topics: list[str], timeout: float) -> dict[str, str]:
    import rclpy

    found: dict[str, str] = {}
    deadline = time.monotonic() + timeout
    while topics and time.monotonic() < deadline and rclpy.ok():
        for name, type_names in node.get_topic_names_and_types():
            if name in topics and type_names:
                found[name] = type_names[0]
        if len(found) == len(topics):
            break
        rclpy.spin_once(node, timeout_sec=0.1)
    return found


def _offered(node, topic: str) -> list:
    """Like rosbag2: the QoS profiles the topic's publishers offer, as discovered."""
    return [qos_from_rclpy(i.qos_profile) for i in node.get_publishers_info_by_topic(topic)]


def _reliability(node, topic: str):
    """RELIABLE when every known publisher offers it (lossless), otherwise BEST_EFFORT (compatible)."""
    from rclpy.qos import ReliabilityPolicy

    infos = node.get_publishers_info_by_topic(topic)
    if infos and any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos):
        return ReliabilityPolicy.BEST_EFFORT
    return ReliabilityPolicy.RELIABLE
