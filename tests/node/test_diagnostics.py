"""Diagnostics in real node processes: STALE while an input does not arrive, ERROR while a node cannot
work with what it gets, and the hardware_id from camera_name (issue 17)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import pytest
from conftest import node_command

ROS_DOMAIN_ID = 127
W, H = 320, 240
INGEST = "ptz_selfcal.nodes.frame_ingest"
CALIBRATOR = "ptz_selfcal.nodes.calibrator"
# short periods, so that a test waits seconds; every wait below is for a report, not for a time
FAST = ("-p", "diagnostics_period:=0.2", "-p", "stale_timeout:=1.0")
INGEST_ARGS = (*FAST, "-p", "sensor_reliability:=reliable", "-p", "working_width:=160")


@dataclass(frozen=True)
class Report:
    node: str
    level: int
    message: str
    hardware_id: str


class Harness:
    """Publishes what frame_ingest and the calibrator take in and collects their diagnostics."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import Image, JointState

        from ptz_selfcal import topics
        from ptz_selfcal.nodes.runtime import reliable_qos
        from ptz_selfcal_msgs.msg import HomographyStamped

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("test_diagnostics", namespace=topics.NAMESPACE, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.raw = self.node.create_publisher(Image, topics.IMAGE_RAW, reliable_qos())
        self.joints = self.node.create_publisher(JointState, topics.JOINT_STATES, reliable_qos())
        self.homographies = self.node.create_publisher(HomographyStamped, topics.HOMOGRAPHY, reliable_qos())
        self.reports: list[Report] = []
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, reliable_qos(50))
        self.t = 100.0  # stamps of what is sent (s)

    def _on_diag(self, msg) -> None:
        for s in msg.status:
            level = s.level[0] if isinstance(s.level, bytes) else int(s.level)
            self.reports.append(Report(s.name.rsplit("/", 1)[-1], level, s.message, s.hardware_id))

    def spin(self, seconds: float, until=None, each=None) -> bool:
        """Spin up to `seconds`; `each()` runs every 0.1 s (a sender); True as soon as `until()` holds."""
        deadline = time.monotonic() + seconds
        next_each = time.monotonic()
        while time.monotonic() < deadline:
            if each is not None and time.monotonic() >= next_each:
                each()
                next_each += 0.1
            self.executor.spin_once(timeout_sec=0.02)
            if until is not None and until():
                return True
        return until is None

    def wait_report(self, node: str, accept, timeout: float = 60.0, each=None) -> Report:
        """The first report of `node`, from now on, that `accept` takes."""
        start = len(self.reports)

        def found() -> Report | None:
            return next((r for r in self.reports[start:] if r.node == node and accept(r)), None)

        assert self.spin(timeout, lambda: found() is not None, each), self.reports[-5:]
        report = found()
        assert report is not None
        return report

    def send_image(self, encoding: str = "mono8") -> None:
        from sensor_msgs.msg import Image

        self.t += 0.1
        msg = Image()
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(self.t), round((self.t % 1) * 1e9)
        msg.header.frame_id = "ptz_camera"
        msg.height, msg.width, msg.encoding, msg.step = H, W, encoding, W
        msg.data = np.random.default_rng(int(self.t * 10)).integers(0, 255, H * W, dtype=np.uint8).tobytes()
        self.raw.publish(msg)

    def send_joints(self, names=("pan", "tilt", "zoom")) -> None:
        from sensor_msgs.msg import JointState

        msg = JointState()
        t = self.t + 0.05
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(t), round((t % 1) * 1e9)
        msg.name = list(names)
        msg.position = [0.0, 0.0, 100.0]
        self.joints.publish(msg)

    def send_homography(self) -> None:
        from ptz_selfcal_msgs.msg import HomographyStamped

        self.t += 0.1
        msg = HomographyStamped()
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(self.t), round((self.t % 1) * 1e9)
        msg.header.frame_id = msg.reference_frame_id = "ptz_camera"
        msg.state = HomographyStamped.TRACKING
        msg.h = [float(v) for v in np.eye(3).ravel()]
        msg.image_width, msg.image_height = 640, 480
        msg.encoders.valid = False
        self.homographies.publish(msg)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def harness(ros_env):
    h = Harness()
    yield h
    h.close()


def level(name: str) -> int:
    from diagnostic_msgs.msg import DiagnosticStatus

    value = getattr(DiagnosticStatus, name)
    return value[0] if isinstance(value, bytes) else int(value)


def test_frame_ingest_is_stale_without_images_or_encoders(harness: Harness, start_process) -> None:
    args = (*INGEST_ARGS, "-p", "camera_name:=cam7")
    proc = start_process(node_command(INGEST, *args), harness_env(), "ingest_stale")
    STALE, OK = level("STALE"), level("OK")
    first = harness.wait_report("frame_ingest", lambda r: True)
    # nothing has ever arrived: STALE, with both inputs named
    assert first.level == STALE, first
    assert "no images received yet" in first.message and "no encoder messages received yet" in first.message
    assert first.hardware_id == "cam7"
    # wait until the node's image and encoder subscriptions see this publisher, then feed both
    assert harness.spin(
        30.0, lambda: harness.raw.get_subscription_count() > 0 and harness.joints.get_subscription_count() > 0
    ), proc.output()

    def both() -> None:
        harness.send_joints()
        harness.send_image()
        harness.send_joints()

    fed = harness.wait_report("frame_ingest", lambda r: r.level != STALE, each=both)
    assert fed.level == OK, (fed, proc.output()[-2000:])
    assert "frames ingested" in fed.message
    # images stop, encoders go on: STALE for the images only
    images_gone = harness.wait_report("frame_ingest", lambda r: r.level == STALE, each=harness.send_joints)
    assert "no images for" in images_gone.message and "encoder" not in images_gone.message, images_gone
    # then the encoders stop too
    all_gone = harness.wait_report("frame_ingest", lambda r: "no encoder messages for" in r.message)
    assert all_gone.level == STALE and "no images for" in all_gone.message, all_gone
    assert {r.hardware_id for r in harness.reports if r.node == "frame_ingest"} == {"cam7"}


def test_frame_ingest_reports_error_on_inputs_it_cannot_use(harness: Harness, start_process) -> None:
    args = (*INGEST_ARGS, "-p", "error_threshold:=3")
    proc = start_process(node_command(INGEST, *args), harness_env(), "ingest_error")
    ERROR = level("ERROR")
    assert harness.spin(
        30.0, lambda: harness.raw.get_subscription_count() > 0 and harness.joints.get_subscription_count() > 0
    ), proc.output()

    # a driver whose joints are named otherwise than joint_names (a configuration the node cannot use)
    wrong = harness.wait_report(
        "frame_ingest",
        lambda r: r.level == ERROR,
        each=lambda: harness.send_joints(("cam_pan_joint", "cam_tilt_joint", "cam_zoom")),
    )
    assert "carry none of joint_names ['pan', 'tilt', 'zoom']" in wrong.message, wrong
    assert wrong.hardware_id == "ptz"  # camera_name "": the default namespace names the camera

    # images in an encoding the node cannot read, with usable encoders: ERROR for the images
    def unusable() -> None:
        harness.send_joints()
        harness.send_image("yuv422_weird")

    bad = harness.wait_report("frame_ingest", lambda r: "were all unusable" in r.message, each=unusable)
    assert bad.level == ERROR and "unsupported_encoding" in bad.message, bad
    assert "joint_names" not in bad.message, bad

    # usable input again: no longer ERROR
    def good() -> None:
        harness.send_joints()
        harness.send_image()

    healthy = harness.wait_report("frame_ingest", lambda r: r.level != ERROR, each=good)
    assert healthy.level in (level("OK"), level("WARN")), healthy


def test_calibrator_is_stale_without_homographies(harness: Harness, start_process) -> None:
    proc = start_process(node_command(CALIBRATOR, *FAST, "-p", "camera_name:=cam7"), harness_env(), "calib")
    STALE = level("STALE")
    first = harness.wait_report("calibrator", lambda r: True)
    assert first.level == STALE and "no homographies received yet" in first.message, first
    assert harness.spin(30.0, lambda: harness.homographies.get_subscription_count() > 0), proc.output()
    fed = harness.wait_report("calibrator", lambda r: r.level != STALE, each=harness.send_homography)
    assert "frames calibrated" in fed.message and "no homographies" not in fed.message, fed
    gone = harness.wait_report("calibrator", lambda r: r.level == STALE)
    assert "no homographies for" in gone.message, gone
    assert {r.hardware_id for r in harness.reports if r.node == "calibrator"} == {"cam7"}


def harness_env() -> dict[str, str]:
    import os

    return dict(os.environ)  # ros_env (through the harness fixture) has set the domain and discovery


def test_a_configuration_error_is_an_error_status_then_exit_2(harness: Harness, start_process) -> None:
    """A node that cannot start says so where a diagnostics monitor looks, under its own name, before it
    exits with its configuration-error status (which `launch` does not restart)."""
    args = (*INGEST_ARGS, "-p", "working_width:=-5", "-p", "camera_name:=cam7")
    proc = start_process(node_command(INGEST, *args), harness_env(), "bad_config")
    report = harness.wait_report("frame_ingest", lambda r: True, timeout=30.0)
    assert report.level == level("ERROR"), report
    assert "configuration error" in report.message and "working_width" in report.message, report
    assert report.hardware_id == "cam7"
    assert proc.wait(30.0) == 2, proc.output()


def test_hardware_id_defaults_to_the_camera_namespace(harness: Harness, start_process) -> None:
    """A node started by hand in a camera's namespace (no launch, no camera_name) names that camera."""
    proc = start_process(node_command(INGEST, *INGEST_ARGS, "-r", "__ns:=/cam5"), harness_env(), "ns_ingest")
    report = harness.wait_report("frame_ingest", lambda r: True, timeout=30.0)
    assert report.hardware_id == "cam5", (report, proc.output())
