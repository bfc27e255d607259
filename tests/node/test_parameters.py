"""Parameter descriptors in real node processes: ranges and choices are what the parameter service
reports, and it refuses an out-of-range value, keeping the old one (issue 17)."""

from __future__ import annotations

import os
import time

import pytest
from conftest import NodeProcess, node_command

from ptz_selfcal.topics import NAMESPACE

ROS_DOMAIN_ID = 126  # (+2 for its unconnected node: 128)
NODES = {
    "frame_ingest": "ptz_selfcal.nodes.frame_ingest",
    "homography_tracker": "ptz_selfcal.nodes.homography_tracker",
    "calibrator": "ptz_selfcal.nodes.calibrator",
}


class ParamClient:
    """Service clients of one remote node's parameter services."""

    def __init__(self, node, executor, name: str) -> None:
        from rcl_interfaces.srv import DescribeParameters, GetParameters, SetParameters

        self.node = node
        self.executor = executor
        self.set = node.create_client(SetParameters, f"{NAMESPACE}/{name}/set_parameters")
        self.get = node.create_client(GetParameters, f"{NAMESPACE}/{name}/get_parameters")
        self.describe = node.create_client(DescribeParameters, f"{NAMESPACE}/{name}/describe_parameters")

    def wait(self, timeout: float) -> bool:
        return all(c.wait_for_service(timeout_sec=timeout) for c in (self.set, self.get, self.describe))

    def call(self, client, request, timeout: float = 60.0, attempt: float = 10.0):
        """The service's answer. A request whose answer does not come is sent again (the parameter
        services are idempotent): on a loaded machine a new client's reply path can match after its
        request path, and that first answer is lost. `timeout` is a safety net, not a measured bound."""
        deadline = time.monotonic() + timeout
        while True:
            future = client.call_async(request)
            wait = max(min(attempt, deadline - time.monotonic()), 0.1)
            self.executor.spin_until_future_complete(future, timeout_sec=wait)
            if future.done():
                return future.result()
            client.remove_pending_request(future)
            assert time.monotonic() < deadline, f"no answer from {client.srv_name}"

    def set_value(self, name: str, value):
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        return self.call(self.set, request).results[0]

    def value(self, name: str):
        from rcl_interfaces.srv import GetParameters
        from rclpy.parameter import parameter_value_to_python

        return parameter_value_to_python(self.call(self.get, GetParameters.Request(names=[name])).values[0])

    def descriptors(self, *names: str) -> dict:
        from rcl_interfaces.srv import DescribeParameters

        answer = self.call(self.describe, DescribeParameters.Request(names=list(names)))
        return {d.name: d for d in answer.descriptors}


@pytest.fixture(scope="module")
def clients(tmp_path_factory: pytest.TempPathFactory):
    """The three nodes, started once for the module (every test here only reads them, or sets a value
    and checks it)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(ROS_DOMAIN_ID),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "PYTHONUNBUFFERED": "1",
    }
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update(ROS_DOMAIN_ID=env["ROS_DOMAIN_ID"], ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    logs = tmp_path_factory.mktemp("parameters")
    procs = {name: NodeProcess(node_command(module), env, logs, name) for name, module in NODES.items()}
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("test_parameters", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        found = {name: ParamClient(node, executor, name) for name in NODES}
        for name, client in found.items():
            assert client.wait(60.0), procs[name].output()
        yield found
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)
        for proc in procs.values():
            proc.stop(timeout=10.0)
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def test_out_of_range_set_is_refused_and_the_old_value_stays(clients) -> None:
    ingest = clients["frame_ingest"]
    before = ingest.value("encoder_time_offset")
    assert isinstance(before, float) and -60.0 <= before <= 60.0
    refused = ingest.set_value("encoder_time_offset", 100.0)  # the range is [-60, 60] s
    assert not refused.successful
    assert "out of range" in refused.reason, refused.reason
    assert ingest.value("encoder_time_offset") == before
    # the same parameter in range is taken: the range, not a read-only flag, refused 100
    accepted = ingest.set_value("encoder_time_offset", 0.25 if before != 0.25 else 0.5)
    assert accepted.successful, accepted.reason
    now = ingest.value("encoder_time_offset")
    assert now in (0.25, 0.5) and now != before
    nan = ingest.set_value("encoder_time_offset", float("nan"))
    assert not nan.successful
    assert ingest.value("encoder_time_offset") == now


def test_describe_parameters_returns_ranges_and_choices(clients) -> None:
    ingest = clients["frame_ingest"].descriptors(
        "encoder_time_offset", "queue_depth", "image_transport", "camera_name"
    )
    (offset,) = ingest["encoder_time_offset"].floating_point_range
    assert (offset.from_value, offset.to_value) == (-60.0, 60.0)
    (depth,) = ingest["queue_depth"].integer_range
    assert (depth.from_value, depth.to_value) == (1, 1000)
    assert "one of: raw, compressed, both" in ingest["image_transport"].description
    assert ingest["image_transport"].additional_constraints == "one of: raw, compressed, both"
    assert not ingest["camera_name"].floating_point_range and not ingest["camera_name"].integer_range

    tracker = clients["homography_tracker"].descriptors("tracker.min_inlier_ratio", "tracker.max_features")
    (ratio,) = tracker["tracker.min_inlier_ratio"].floating_point_range
    assert (ratio.from_value, ratio.to_value) == (0.0, 1.0)
    (features,) = tracker["tracker.max_features"].integer_range
    assert features.from_value == 0 and features.to_value > 1_000_000

    calibrator = clients["calibrator"].descriptors("nominal_hfov_deg", "max_keyframes", "stale_timeout")
    for name in ("nominal_hfov_deg", "stale_timeout"):
        (r,) = calibrator[name].floating_point_range
        assert r.from_value < r.to_value, name
    (keyframes,) = calibrator["max_keyframes"].integer_range
    assert 0 < keyframes.from_value < keyframes.to_value


def test_every_numeric_parameter_of_the_three_nodes_has_its_range(clients) -> None:
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import ListParameters

    numeric = {
        ParameterType.PARAMETER_DOUBLE: "floating_point_range",
        ParameterType.PARAMETER_INTEGER: "integer_range",
        ParameterType.PARAMETER_DOUBLE_ARRAY: "floating_point_range",
        ParameterType.PARAMETER_INTEGER_ARRAY: "integer_range",
    }
    checked = 0
    for name, client in clients.items():
        lister = client.node.create_client(ListParameters, f"{NAMESPACE}/{name}/list_parameters")
        assert lister.wait_for_service(timeout_sec=30.0)
        names = [
            n
            for n in client.call(lister, ListParameters.Request()).result.names
            if not n.startswith("qos_overrides.") and n != "use_sim_time"  # rclpy's own
        ]
        for descriptor in client.descriptors(*names).values():
            if descriptor.type in numeric:
                assert getattr(descriptor, numeric[descriptor.type]), (name, descriptor.name)
                checked += 1
    assert checked >= 60


def test_read_only_parameter_is_refused_and_kept(clients) -> None:
    ingest = clients["frame_ingest"]
    before = ingest.value("working_width")
    refused = ingest.set_value("working_width", 320)
    assert not refused.successful and "read-only" in refused.reason
    assert ingest.value("working_width") == before


@pytest.mark.parametrize(
    ("module", "cls", "topic"),
    [
        ("ptz_selfcal.nodes.frame_ingest", "FrameIngest", "image_raw"),
        ("ptz_selfcal.nodes.homography_tracker", "HomographyTrackerNode", "frame_in"),
    ],
)
def test_the_live_queue_is_bounded_keep_last_by_default(module: str, cls: str, topic: str) -> None:
    """The image queue by default, lossless (replays) and an rclpy QoS override, as created by the node
    (history and depth are not in the graph's endpoint information, so the node is built here)."""
    import importlib

    import rclpy
    from rclpy.parameter import Parameter
    from rclpy.qos import HistoryPolicy

    node_class = getattr(importlib.import_module(module), cls)

    def queue(*overrides: Parameter):
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=ROS_DOMAIN_ID + 2)  # its own domain: nothing connects to it
        try:
            node = node_class(context=context, parameter_overrides=list(overrides))
            try:
                (sub,) = [s for s in node.subscriptions if s.topic_name.endswith(f"/{topic}")]
                return sub.topic_name, sub.qos_profile.history, sub.qos_profile.depth
            finally:
                node.destroy_node()
        finally:
            rclpy.shutdown(context=context)

    name, history, depth = queue()
    assert (history, depth) == (HistoryPolicy.KEEP_LAST, 50)
    _, history, _ = queue(Parameter("queue_policy", value="lossless"))
    assert history == HistoryPolicy.KEEP_ALL
    _, history, depth = queue(Parameter("queue_depth", value=3))
    assert (history, depth) == (HistoryPolicy.KEEP_LAST, 3)
    # rclpy's standard override of the same queue
    _, history, depth = queue(Parameter(f"qos_overrides.{name}.subscription.depth", value=7))
    assert (history, depth) == (HistoryPolicy.KEEP_LAST, 7)
