"""The output bag of `run --with-images` as MCAP tooling reads it (the `mcap` and `mcap-ros2-support`
libraries) and as rosbags reads it: every message decodes, every message has the bag time of its data,
the bag spans the input's time, QoS profiles are recorded, the input images are in it unchanged."""

from __future__ import annotations

import os
import subprocess
import time
from collections import Counter
from pathlib import Path

import pytest
import yaml
from conftest import cli_command, make_synth_bag
from mcap.reader import NonSeekingReader, make_reader
from mcap_ros2.decoder import DecoderFactory

from ptz_selfcal import topics
from ptz_selfcal.tools.bagio import BagReader, header_stamp_ns

ROS_DOMAIN_ID = 121
FRAMES = 24
FPS = 30.0
FRAME_NS = int(1e9 / FPS)
IMAGES = topics.bag_topic(topics.IMAGE_COMPRESSED)
PER_IMAGE = [topics.bag_topic(t) for t in (topics.CAMERA_INFO, topics.FRAME_CALIBRATION, topics.HOMOGRAPHY)]


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(input bag, output bag of `run --with-images`), made once for the module."""
    root = tmp_path_factory.mktemp("output_bags")
    src = make_synth_bag(root / "in", FRAMES, 320, 180, "--fps", str(FPS))
    return src, root / "out"


@pytest.fixture(scope="module")
def output_bag(bags: tuple[Path, Path]) -> Path:
    src, out = bags
    # ros_env's values (that fixture is per test; this run is made once per module)
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(ROS_DOMAIN_ID),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
    }
    proc = subprocess.run(
        cli_command("run", str(src), "--out", str(out), "--with-images", "--quiet"),
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"{FRAMES}/{FRAMES} images got a CameraInfo" in proc.stderr
    return out


def _mcap_file(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def test_mcap_libraries_decode_every_message(output_bag: Path) -> None:
    with BagReader(output_bag) as reader:
        assert reader.damage is None
        rosbags_counts = {t.name: t.count for t in reader.topics()}
    assert rosbags_counts[IMAGES] == FRAMES and all(rosbags_counts[t] == FRAMES for t in PER_IMAGE)
    with _mcap_file(output_bag).open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        decoded = Counter()
        for _schema, channel, message, ros_msg in reader.iter_decoded_messages():
            decoded[channel.topic] += 1
            if hasattr(ros_msg, "header"):
                assert ros_msg.header.stamp.sec > 0
            assert message.log_time == message.publish_time
    assert dict(decoded) == rosbags_counts
    assert summary.statistics.message_count == sum(rosbags_counts.values())
    # a reader that ignores the summary and streams the records in order sees the same messages
    with _mcap_file(output_bag).open("rb") as f:
        streamed = Counter(ch.topic for _s, ch, _m in NonSeekingReader(f).iter_messages())
    assert streamed == decoded


def test_timeline_is_the_inputs(bags: tuple[Path, Path], output_bag: Path) -> None:
    src, _ = bags
    with BagReader(src) as reader:
        in_start, in_duration = reader.start_ns, reader.duration_ns
        image_times = {header_stamp_ns(m.raw): (m.timestamp_ns, m.raw) for m in reader.messages([IMAGES])}
    with BagReader(output_bag) as reader:
        assert abs(reader.start_ns - in_start) <= FRAME_NS
        assert abs(reader.duration_ns - in_duration) <= FRAME_NS
        seen: Counter[str] = Counter()
        for msg in reader.messages():
            assert in_start <= msg.timestamp_ns < in_start + in_duration, msg.topic
            stamp = header_stamp_ns(msg.raw)
            if msg.topic == IMAGES:
                assert image_times[stamp] == (msg.timestamp_ns, msg.raw)  # copied unchanged
            elif msg.topic in PER_IMAGE:
                assert msg.timestamp_ns == image_times[stamp][0]  # the bag time of its image
            seen[msg.topic] += 1
    assert seen[topics.bag_topic(topics.DIAGNOSTICS)] > 0


def test_qos_profiles_are_recorded(output_bag: Path) -> None:
    info = yaml.safe_load((output_bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    profiles = {
        t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
        for t in info["topics_with_message_count"]
    }
    assert set(profiles) >= {IMAGES, *PER_IMAGE}
    for name, offered in profiles.items():
        assert offered, f"{name}: no offered_qos_profiles"
        assert all(p["reliability"] in ("reliable", "best_effort") for p in offered), (name, offered)
    for name in PER_IMAGE:  # what the nodes offer in run mode
        assert [p["reliability"] for p in profiles[name]] == ["reliable"], profiles[name]
    # Outputs carry their publishers' profiles as discovered (DDS discovery carries no history), not
    # the fallback a topic without known publishers gets: diagnostics arrive while the nodes come up.
    for name in [*PER_IMAGE, topics.bag_topic(topics.DIAGNOSTICS)]:
        assert profiles[name] and all(p["history"] == "unknown" for p in profiles[name]), profiles[name]
    with BagReader(output_bag) as reader:
        assert all(t.qos for t in reader.topics())


def test_record_writes_the_offered_qos(tmp_path: Path, ros_env: dict[str, str]) -> None:
    """A best-effort, transient-local publisher: `record` writes those profiles, not a default."""
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    topic = "/qos_probe/joint_states"
    out = tmp_path / "recorded"
    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        node = rclpy.create_node("qos_probe", context=context)
        qos = QoSProfile(
            depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.TRANSIENT_LOCAL
        )
        pub = node.create_publisher(JointState, topic, qos)
        recorder = subprocess.Popen(
            cli_command("record", str(out), "--topics", topic, "--max-messages", "5", "--idle-timeout", "30"),
            env=ros_env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            deadline = time.monotonic() + 120
            while recorder.poll() is None and time.monotonic() < deadline:
                pub.publish(JointState(name=["pan"], position=[0.1]))
                time.sleep(0.05)
        finally:
            if recorder.poll() is None:
                recorder.kill()
        assert recorder.wait(timeout=30) == 0, recorder.stderr.read()
    finally:
        context.try_shutdown()
    info = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    (entry,) = info["topics_with_message_count"]
    assert entry["message_count"] >= 5
    offered = entry["topic_metadata"]["offered_qos_profiles"]
    assert [(p["reliability"], p["durability"]) for p in offered] == [("best_effort", "transient_local")]
