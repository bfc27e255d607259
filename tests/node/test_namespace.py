"""A second camera by namespace alone: `ptz-selfcal launch --namespace /cam1` beside a driver that publishes
as real ones do (raw and compressed copies of each image, best effort; axis-style pan/tilt joint names at
1 Hz, the zoom on a state topic of its own) in /cam1, with no remaps. A CameraSubscriber-style consumer
pairs every selfcal/image_raw with its selfcal/camera_info by stamp, as image_transport's exact-time
synchroniser does; every frame has encoders, extrapolated past the newest 1 Hz sample and counted so."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
import yaml
from conftest import cli_command

ROS_DOMAIN_ID = 131
NAMESPACE = "/cam1"
WIDTH, HEIGHT = 320, 240
FRAMES = 30
JOINTS = ["axis_pan_joint", "axis_tilt_joint"]
ZOOM_JOINT = "axis_zoom_joint"


def stamp_of(t: float):
    from builtin_interfaces.msg import Time

    return Time(sec=int(t), nanosec=round((t - int(t)) * 1e9))


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class Driver:
    """The camera driver and the consumer, in one rclpy node of the camera's namespace."""

    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState

        from ptz_selfcal import topics
        from ptz_selfcal.nodes.runtime import reliable_qos
        from ptz_selfcal_msgs.msg import FrameCalibration

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("axis_driver", namespace=NAMESPACE, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        sensor = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.raw = self.node.create_publisher(Image, "image_raw", sensor)
        self.compressed = self.node.create_publisher(CompressedImage, "image_raw/compressed", sensor)
        self.joints = self.node.create_publisher(JointState, "joint_states", reliable_qos(10))
        self.zoom = self.node.create_publisher(JointState, "zoom_state", reliable_qos(10))
        self.relayed: dict[int, object] = {}
        self.infos: dict[int, object] = {}
        self.relay_sub = self.node.create_subscription(
            Image, topics.IMAGE_RELAY, lambda m: self.relayed.setdefault(stamp_ns(m.header.stamp), m), 50
        )
        self.info_sub = self.node.create_subscription(
            CameraInfo, topics.CAMERA_INFO, lambda m: self.infos.setdefault(stamp_ns(m.header.stamp), m), 50
        )
        self.frames: dict[int, object] = {}
        self.node.create_subscription(
            FrameCalibration,
            topics.FRAME_CALIBRATION,
            lambda m: self.frames.setdefault(stamp_ns(m.header.stamp), m),
            50,
        )
        self.ingest_diagnostics: dict[str, str] = {}
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diagnostics, 50)

    def _on_diagnostics(self, array) -> None:
        for status in array.status:
            if status.name == f"{NAMESPACE}/frame_ingest":
                assert status.hardware_id == "cam1"
                self.ingest_diagnostics = {kv.key: kv.value for kv in status.values}

    def spin(self, seconds: float, until=None) -> bool:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
            if until is not None and until():
                return True
        return until is None

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def textured(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    small = rng.integers(0, 255, (HEIGHT // 8, WIDTH // 8, 3), dtype=np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (WIDTH, HEIGHT), interpolation=cv2.INTER_NEAREST), (5, 5), 0)


@pytest.fixture
def params_file(tmp_path):
    path = tmp_path / "cam1.yaml"
    sections = {
        "frame_ingest": {"joint_names": JOINTS, "zoom_topic": "zoom_state", "diagnostics_period": 0.25},
        "homography_tracker": {"diagnostics_period": 0.25},
        "calibrator": {"diagnostics_period": 0.25},
    }
    path.write_text(yaml.safe_dump({k: {"ros__parameters": v} for k, v in sections.items()}))
    return path


def test_second_camera_by_namespace_alone_pairs_relay_and_camera_info(ros_env, start_process, params_file):
    from sensor_msgs.msg import CompressedImage, Image, JointState

    proc = start_process(
        cli_command("launch", "--namespace", NAMESPACE, "--params", str(params_file)),
        {**ros_env, "ROS_HOME": str(params_file.parent / "ros_home")},  # where launch keeps the state
        "launch_cam1",
    )
    d = Driver()
    try:
        connected = d.spin(
            90.0,
            lambda: (
                d.raw.get_subscription_count() > 0
                and d.joints.get_subscription_count() > 0
                and d.relay_sub.get_publisher_count() > 0
                and d.info_sub.get_publisher_count() > 0
            ),
        )
        assert connected, proc.output()
        d.spin(1.5)  # the remote writers match the consumer too
        names = {n for n, _ in d.node.get_topic_names_and_types()}
        assert not any(n.startswith("/ptz/") for n in names), sorted(names)
        # one transport, as image_transport subscribes: the default is raw
        assert d.compressed.get_subscription_count() == 0

        sent: dict[int, bytes] = {}
        t0 = 1000.0

        def encoders(t: float) -> None:  # 1 Hz, axis-style: pan and tilt, and the zoom apart
            pan_tilt = [0.01 * t, 0.0]
            d.joints.publish(JointState(header=_header(t, "axis_base"), name=JOINTS, position=pan_tilt))
            d.zoom.publish(JointState(header=_header(t, ""), name=[ZOOM_JOINT], position=[2 * t]))

        for t in (t0 - 4, t0 - 3, t0 - 2, t0 - 1):  # the head has been reporting for a while
            encoders(t)
        for k in range(FRAMES):
            t = t0 + 0.1 * k
            if k % 10 == 0:
                encoders(t)
            bgr = textured(k)
            header = _header(t, "cam1_optical")
            image = Image(header=header, height=HEIGHT, width=WIDTH, encoding="bgr8", step=3 * WIDTH)
            image.data = bgr.tobytes()
            d.raw.publish(image)
            jpeg = cv2.imencode(".jpg", bgr)[1].tobytes()
            d.compressed.publish(CompressedImage(header=header, format="jpeg", data=jpeg))
            sent[stamp_ns(header.stamp)] = image.data.tobytes()
            d.spin(0.1)
        settled = d.spin(
            30.0,
            lambda: (
                len(d.relayed) >= FRAMES - 5
                and set(d.relayed) <= set(d.infos)
                and set(d.relayed) <= set(d.frames)
                and int(d.ingest_diagnostics.get("frames_out", 0)) >= len(d.relayed)
            ),
        )
        assert settled, (len(d.relayed), len(d.infos), proc.output()[-3000:])
        d.spin(1.0)
    finally:
        d.close()
    assert proc.stop(timeout=20.0) == 0, proc.output()
    # best effort may lose a few images on the way in; every image that got through is relayed unchanged,
    # and pairs with a CameraInfo of the same header and full-resolution size
    assert len(d.relayed) >= FRAMES - 5, len(d.relayed)
    assert set(d.relayed) == set(d.infos)
    for stamp, image in d.relayed.items():
        info = d.infos[stamp]
        assert image.header.frame_id == info.header.frame_id == "cam1_optical"
        assert (image.width, image.height) == (info.width, info.height) == (WIDTH, HEIGHT)
        assert image.data.tobytes() == sent[stamp]
        assert info.k[0] > 0
        # encoders at the stamp: interpolated or extrapolated along the 1 Hz samples, zoom from its topic
        t = stamp * 1e-9
        encoders = d.frames[stamp].encoders
        assert encoders.valid, (t, encoders)
        assert abs(encoders.pan - 0.01 * t) < 1e-6 and abs(encoders.zoom - 2 * t) < 1e-6, (t, encoders)
    # the frames after the newest sample did not wait for the next one: extrapolated, and counted
    diagnostics = d.ingest_diagnostics
    assert float(diagnostics["encoder_period_s"]) == pytest.approx(1.0)
    extrapolated = int(diagnostics["frames_encoders_extrapolated"])
    assert len(d.relayed) - 3 <= extrapolated <= int(diagnostics["frames_out"]) - 1, diagnostics
    assert int(diagnostics.get("encoder_wait_expired", 0)) == 0, diagnostics
    out = proc.output()
    assert "/cam1/selfcal/frame_in" in out, out  # the nodes said where they publish


def _header(t: float, frame_id: str):
    from std_msgs.msg import Header

    return Header(stamp=stamp_of(t), frame_id=frame_id)


def test_a_bag_played_into_another_namespace_is_calibrated_there(
    ros_env, start_process, short_synth_bag, tmp_path
):
    """An existing bag (its topics under /ptz) played into /cam1 (`play --namespace`) beside a suite
    launched there, on its compressed transport: every image gets its CameraInfo in /cam1, and nothing is
    published under /ptz."""
    from sensor_msgs.msg import CameraInfo

    from ptz_selfcal import topics
    from ptz_selfcal.tools.bagio import BagReader, header_stamp_ns

    with BagReader(short_synth_bag) as reader:
        compressed = topics.bag_topic(topics.IMAGE_COMPRESSED)
        images = {header_stamp_ns(m.raw) for m in reader.messages([compressed])}
    params = tmp_path / "compressed.yaml"
    # reliable: a best-effort reader may miss the first image while it matches the player, and this test
    # counts every image
    ingest = {"image_transport": "compressed", "sensor_reliability": "reliable"}
    params.write_text(yaml.safe_dump({"frame_ingest": {"ros__parameters": ingest}}))
    suite = start_process(
        cli_command("launch", "--namespace", NAMESPACE, "--params", str(params)),
        {**ros_env, "ROS_HOME": str(tmp_path / "ros_home")},
        "launch_play",
    )
    d = Driver()
    try:
        assert d.spin(90.0, lambda: d.info_sub.get_publisher_count() > 0), suite.output()
        infos: dict[int, object] = {}
        d.node.create_subscription(
            CameraInfo, topics.CAMERA_INFO, lambda m: infos.setdefault(stamp_ns(m.header.stamp), m), 100
        )
        played = [compressed, topics.bag_topic(topics.JOINT_STATES)]
        command = cli_command("play", str(short_synth_bag), "--namespace", NAMESPACE, "--topics", *played)
        play = start_process([*command, "--wait-subscribers", "60"], ros_env, "play_cam1")
        assert d.spin(60.0, lambda: set(infos) >= images), (len(infos), len(images), suite.output()[-3000:])
        assert play.wait(30.0) == 0, play.output()
        names = {n for n, _ in d.node.get_topic_names_and_types()}
    finally:
        d.close()
    assert suite.stop(timeout=20.0) == 0, suite.output()
    assert set(infos) == images
    assert f"{NAMESPACE}/image_raw/compressed" in names and not any(n.startswith("/ptz/") for n in names)
