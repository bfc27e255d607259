"""Process plumbing shared by every node and tool: init, spin, clean shutdown on Ctrl-C/SIGTERM."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy


def reliable_qos(depth: int = 0) -> QoSProfile:
    """RELIABLE delivery; depth 0 means KEEP_ALL (lossless replay, ENVIRONMENT.md)."""
    if depth <= 0:
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None) -> int:
    """Create the node, spin until Ctrl-C/SIGTERM or rclpy shutdown, then tear down cleanly."""
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
