"""Process plumbing shared by every node and tool: init, spin, clean shutdown on Ctrl-C/SIGTERM."""

from __future__ import annotations

import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import rclpy
from rclpy.callback_groups import CallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.subscription import Subscription

from ptz_selfcal.nodes.conversions import ConfigError


def reliable_qos(depth: int = 0) -> QoSProfile:
    """RELIABLE delivery; depth 0 means KEEP_ALL (lossless replay, ENVIRONMENT.md)."""
    if depth <= 0:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


class PolledGroup(CallbackGroup):
    """A callback group no executor waits on or runs: its subscriptions' messages stay in the
    middleware's queue (KEEP_LAST: the newest `depth`) until the node takes them itself with take(),
    e.g. from a timer, so that a message costs no executor wake-up (in rclpy the larger part of a
    small message's cost)."""

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        pass


def take(sub: Subscription) -> Any:
    """The oldest message waiting on a subscription (bytes if it is raw), None when there is none."""
    with sub.handle:
        got = sub.handle.take_message(sub.msg_type, sub.raw)
    return None if got is None else got[0]


def qos_overrides() -> QoSOverridingOptions:
    """rclpy's standard QoS overrides (history, depth, reliability): a user sets e.g.
    `qos_overrides./ptz/image_raw.subscription.depth` as a parameter, as for any ROS node."""
    return QoSOverridingOptions.with_default_policies()


def camera_name_of(node: Node, name: str) -> str:
    """The camera's name: the camera_name parameter, else the node's namespace's last component (the
    camera's namespace: /cam1 is cam1, the default /ptz is ptz)."""
    return name or node.get_namespace().rstrip("/").rsplit("/", 1)[-1] or "camera"


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, name: str = "node") -> int:
    """Create the node, spin until Ctrl-C/SIGTERM or rclpy shutdown, then tear down cleanly.

    A configuration error (absurd parameter) is one line on stderr, an ERROR status on /diagnostics under
    the node's name (what a diagnostics monitor shows of a node that is gone) and exit status 2."""
    try:
        return _spin_node(factory, args, name)
    except ConfigError as exc:
        print(f"{name}: configuration error: {exc}", file=sys.stderr)
        return 2


CONFIG_ERROR_REPORT_WAIT = 3.0  # s a node with a configuration error waits for a diagnostics subscriber


def report_config_error(name: str, message: str, wait: float = CONFIG_ERROR_REPORT_WAIT) -> None:
    """An ERROR DiagnosticStatus for node `name` (with the command line's remaps, in the camera's
    namespace unless remapped), sent to the subscribers that match within `wait` seconds."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

    from ptz_selfcal import topics

    # no rosout publisher: the failed node of the same name still holds it
    node = rclpy.create_node(name, namespace=topics.NAMESPACE, enable_rosout=False)
    try:
        try:
            hardware_id = camera_name_of(node, str(node.declare_parameter("camera_name", "").value))
        except Exception:  # the configuration error may be this parameter's own
            hardware_id = ""
        pub = node.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable_qos(10))
        deadline = time.monotonic() + wait
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        if pub.get_subscription_count() == 0:
            return
        status = DiagnosticStatus(
            level=DiagnosticStatus.ERROR,
            name=node.get_fully_qualified_name(),
            hardware_id=hardware_id,
            message=f"configuration error: {message}",
        )
        for _ in range(3):  # reliable, but a reader that has not matched this writer yet misses the first
            array = DiagnosticArray(status=[status])
            array.header.stamp = node.get_clock().now().to_msg()
            pub.publish(array)
            time.sleep(0.2)
    finally:
        node.destroy_node()


def _spin_node(factory: Callable[[], Node], args: Sequence[str] | None, name: str) -> int:
    # rclpy's default handlers turn SIGINT and SIGTERM into a context shutdown, which ends spin().
    rclpy.init(args=args)
    node = None
    executor = SingleThreadedExecutor()
    try:
        node = factory()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ConfigError as exc:
        if rclpy.ok():
            report_config_error(name, str(exc))
        raise
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if callable(close):
                close()
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


class CountedWarnings:
    """Anomaly counters for /diagnostics with one log line the first time each kind occurs."""

    def __init__(self, node: Node, counts: Counter[str]) -> None:
        self._logger = node.get_logger()
        self._counts = counts
        self._warned: set[str] = set()

    def warn_once(self, kind: str, message: str, *, key: str | None = None) -> None:
        """Count `kind` (under `key` if given) and log `message` only on its first occurrence."""
        self._counts[key or kind] += 1
        if kind not in self._warned:
            self._warned.add(kind)
            self._logger.warning(f"{message} (further ones counted in diagnostics)")


class InputWatch:
    """Whether an input still arrives, from its counter read at each diagnostics report: stale when the
    count has not grown for `timeout` seconds, or never has."""

    def __init__(self, what: str, timeout: float) -> None:
        self.what = what
        self.timeout = timeout
        self._count = 0
        self._since: float | None = None  # monotonic time of the report that saw the count grow

    def stale(self, count: int, now: float | None = None) -> str | None:
        """None while the input arrives, else why it is stale."""
        now = time.monotonic() if now is None else now
        if count > self._count:
            self._count, self._since = count, now
        if self._since is None:
            return f"no {self.what} received yet"
        age = now - self._since
        return f"no {self.what} for {age:.1f} s" if age > self.timeout else None


class FailureRun:
    """Consecutive failures of an input, from its counters (all, failed) read at each report: the run
    grows while every new input failed and ends with any good one."""

    def __init__(self) -> None:
        self._total = 0
        self._failed = 0
        self.run = 0

    def update(self, total: int, failed: int) -> int:
        new, new_failed = total - self._total, failed - self._failed
        self._total, self._failed = total, failed
        if new > 0:
            self.run = self.run + new if new_failed >= new else 0
        return self.run


def set_level(
    status: Any,
    ok: str,
    *,
    error: Iterable[str] = (),
    stale: Iterable[str] = (),
    warn: Iterable[str] = (),
) -> None:
    """A DiagnosticStatus's level and message: ERROR (cannot work) over STALE (no input) over WARN over
    OK; the message gives the reasons of the level, then `ok` (what the node has done)."""
    from diagnostic_msgs.msg import DiagnosticStatus

    for level, reasons in (
        (DiagnosticStatus.ERROR, list(error)),
        (DiagnosticStatus.STALE, list(stale)),
        (DiagnosticStatus.WARN, list(warn)),
    ):
        if reasons:
            status.level = level
            status.message = "; ".join([*reasons, ok])
            return
    status.level = DiagnosticStatus.OK
    status.message = ok
