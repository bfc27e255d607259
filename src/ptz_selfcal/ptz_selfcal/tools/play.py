"""`ptz-selfcal play BAG`: publish a bag's messages with their timing (or as fast as lossless allows)."""

from __future__ import annotations

import argparse
import sys
import time

from ptz_selfcal import topics
from ptz_selfcal.tools.bagio import BagReader, msg_class
from ptz_selfcal.tools.cli import CliError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("bag", help="bag directory (sqlite3 or mcap)")
    parser.add_argument(
        "--rate", type=float, default=1.0, help="playback speed factor; 0 = as fast as possible without loss"
    )
    parser.add_argument("--loop", action="store_true", help="start again at the end, until Ctrl-C")
    parser.add_argument("--topics", nargs="+", help="only these topics (default: all)")
    parser.add_argument(
        "--wait-subscribers",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="before publishing, wait up to this long until every topic has a subscriber",
    )
    parser.add_argument(
        "--namespace",
        metavar="NS",
        help=f"publish the bag's {topics.NAMESPACE}/... topics under NS/... (another camera's namespace)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    if not (args.rate >= 0.0) or args.rate > 1000.0:
        raise CliError(f"--rate must be in [0, 1000], got {args.rate}")
    if args.namespace is not None:
        from ptz_selfcal.tools.launch import check_namespace

        args.namespace = check_namespace(args.namespace) or "/"
    with BagReader(args.bag) as reader:
        topics = [t for t in reader.topics() if args.topics is None or t.name in args.topics]
        if not topics:
            raise CliError(f"{args.bag}: none of the requested topics is in the bag")
        classes = {t.name: msg_class(t.msgtype) for t in topics}
        if reader.damage:
            unread = [reader.unread(t.name) for t in topics]
            lost = "an unknown number" if None in unread else str(sum(n or 0 for n in unread))
            print(
                f"play: warning: {reader.damage}; playing the readable messages ({lost} lost)",
                file=sys.stderr,
            )
    return _play(args, classes)


def _play(args: argparse.Namespace, classes: dict[str, type]) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from ptz_selfcal.nodes.runtime import reliable_qos

    rclpy.init()
    node = rclpy.create_node("ptz_selfcal_play")
    publishers = {
        name: node.create_publisher(cls, in_namespace(name, args.namespace), reliable_qos())
        for name, cls in classes.items()
    }
    sent = 0
    try:
        _wait_for_subscribers(node, publishers, args.wait_subscribers)
        while True:
            sent += _play_once(node, args, publishers, sent)
            if not args.loop:
                break
        for pub in publishers.values():
            pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10.0))
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if not args.quiet:
            print(f"play: published {sent} messages", file=sys.stderr)
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


def in_namespace(name: str, namespace: str | None) -> str:
    """A bag topic of the default namespace moved into `namespace` (others stay as they are)."""
    prefix = topics.NAMESPACE + "/"
    if namespace is None or not name.startswith(prefix):
        return name
    return topics.resolve(name.removeprefix(prefix), namespace)


def _wait_for_subscribers(node, publishers: dict, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while timeout > 0 and time.monotonic() < deadline:
        if all(p.get_subscription_count() > 0 for p in publishers.values()):
            return
        time.sleep(0.05)
    if timeout > 0:
        missing = [t for t, p in publishers.items() if p.get_subscription_count() == 0]
        node.get_logger().warning(f"no subscriber after {timeout:.1f} s on: {', '.join(missing)}")


def _play_once(node, args: argparse.Namespace, publishers: dict, already_sent: int) -> int:
    import rclpy

    sent = 0
    wall_start = time.monotonic()
    bag_start: int | None = None
    last_report = wall_start
    with BagReader(args.bag) as reader:
        total = sum(t.count for t in reader.topics() if t.name in publishers)
        for msg in reader.messages(publishers):
            if not rclpy.ok():
                break
            if bag_start is None:
                bag_start = msg.timestamp_ns
            if args.rate > 0:
                due = wall_start + (msg.timestamp_ns - bag_start) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            publishers[msg.topic].publish(msg.raw)
            sent += 1
            now = time.monotonic()
            if not args.quiet and now - last_report > 2.0:
                print(f"play: {sent}/{total} messages", file=sys.stderr)
                last_report = now
    return sent
