"""Process plumbing shared by every node and tool: init, spin, clean shutdown on Ctrl-C/SIGTERM."""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from ptz_selfcal.nodes.conversions import ConfigError


def reliable_qos(depth: int = 0) -> QoSProfile:
    """RELIABLE delivery; depth 0 means KEEP_ALL (lossless replay, ENVIRONMENT.md)."""
    if depth <= 0:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, name: str = "node") -> int:
    """Create the node, spin until Ctrl-C/SIGTERM or rclpy shutdown, then tear down cleanly.

    A configuration error (absurd parameter) is one line on stderr and exit status 2."""
    try:
        return _spin_node(factory, args)
    except ConfigError as exc:
        print(f"{name}: configuration error: {exc}", file=sys.stderr)
        return 2


def _spin_node(factory: Callable[[], Node], args: Sequence[str] | None) -> int:
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
