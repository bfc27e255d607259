"""One suite across two hosts (issue 19): frame_ingest on a camera-side host, homography_tracker and
calibrator on a server, simulated by two network namespaces of the test's own joined by a veth pair
(two_hosts_harness). Discovery by static peers only; every image gets its CameraInfo on the server;
the images crossed the link once (its byte counters) and not by shared memory (no server process maps
a camera-side segment), and no multicast went over it.
"""

from __future__ import annotations

import re
import time

import pytest
from conftest import PYTHON, cli_command
from test_fastdds_shared_memory import mapped_segments, shipped_segment_size
from two_hosts_harness import TwoHosts, in_netns, shm_segments, unavailable

from ptz_selfcal import topics
from ptz_selfcal.nodes.conversions import downscale_factor
from ptz_selfcal.nodes.frame_ingest import PARAMS as INGEST_PARAMS
from ptz_selfcal.tools.bagio import BagReader, deserialize

ROS_DOMAIN_ID = 190
IMAGE = topics.bag_topic(topics.IMAGE_COMPRESSED)
JOINTS = topics.bag_topic(topics.JOINT_STATES)
CAMERA_INFO = topics.bag_topic(topics.CAMERA_INFO)

# Waits on the camera side until the server's tracker reads frame_in and the server's recorder reads
# the calibrator's camera_info: discovery has crossed the link both ways.
DISCOVERED = f"""
import sys, time, rclpy
rclpy.init()
node = rclpy.create_node("two_hosts_probe")
deadline = time.monotonic() + 30.0
while time.monotonic() < deadline:
    if (node.count_subscribers("{topics.resolve(topics.FRAME_IN, topics.NAMESPACE)}") > 0
            and node.count_publishers("{CAMERA_INFO}") > 0 and node.count_subscribers("{CAMERA_INFO}") > 0):
        sys.exit(0)
    time.sleep(0.1)
sys.exit(1)
"""


@pytest.fixture
def hosts():
    reason = unavailable()
    if reason:
        pytest.skip(reason)
    with TwoHosts() as two:
        yield two


def stamps(bag, topic: str) -> list[int]:
    with BagReader(bag) as reader:
        return [
            (m := deserialize(msg.raw, msg.msgtype)).header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
            for msg in reader.messages([topic])
        ]


def node_pids(output: str) -> dict[str, int]:
    return {name: int(pid) for name, pid in re.findall(r"started (\w+) \(pid (\d+)\)", output)}


def wait_for_pids(proc, names: set[str], timeout: float = 20.0) -> dict[str, int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.alive() and not names <= set(node_pids(proc.output())):
        time.sleep(0.05)
    pids = node_pids(proc.output())
    assert names <= set(pids), proc.output()
    return pids


def test_frame_ingest_on_one_host_tracker_and_calibrator_on_another(
    hosts, ros_env, start_process, short_synth_bag, tmp_path
):
    env = {**ros_env, **hosts.environment()}
    params = tmp_path / "camera.yaml"  # the camera box ingests the bag's JPEG stream
    params.write_text("/**/frame_ingest:\n  ros__parameters:\n    image_transport: compressed\n")
    out = tmp_path / "server_out"
    image_stamps = stamps(short_synth_bag, IMAGE)

    def cli(host, *args: str) -> list[str]:
        return in_netns(host.netns, cli_command(*args))

    server = start_process(
        cli(hosts.b, "launch", "--nodes", "homography_tracker", "calibrator", "--no-persist"), env, "server"
    )
    info_type = f"{CAMERA_INFO}={topics.TYPES[topics.CAMERA_INFO]}"
    record = start_process(
        cli(hosts.b, "record", str(out), "--topics", CAMERA_INFO, "--type", info_type,
            "--max-messages", str(len(image_stamps)), "--duration", "45"),
        env, "record",
    )  # fmt: skip
    camera = start_process(
        cli(hosts.a, "launch", "--nodes", "frame_ingest", "--no-persist", "--params", str(params)),
        env,
        "camera",
    )
    server_pids = wait_for_pids(server, {"homography_tracker", "calibrator"})
    camera_pids = wait_for_pids(camera, {"frame_ingest"})
    probe = start_process(in_netns(hosts.a.netns, [PYTHON, "-c", DISCOVERED]), env, "probe")
    assert probe.wait(40.0) == 0, (probe.output(), server.output(), camera.output())
    time.sleep(1.0)  # the far ends' matching settles too

    before = {h: hosts.counters(h) for h in (hosts.a, hosts.b)}
    play_args = ("--topics", IMAGE, JOINTS, "--wait-subscribers", "20", "--quiet")
    play = start_process(cli(hosts.a, "play", str(short_synth_bag), *play_args), env, "play")
    assert play.wait(30.0) == 0, play.output()
    assert record.wait(30.0) == 0, (record.output(), server.output(), camera.output())
    after = {h: hosts.counters(h) for h in (hosts.a, hosts.b)}
    pids = {**server_pids, **camera_pids}
    segments = {name: shm_segments(pid) for name, pid in pids.items()}
    # launch's copy of the profile was taken (Fast DDS falls back to its defaults on a profile it rejects)
    assert all(max(mapped_segments(pid), default=0) >= shipped_segment_size() for pid in pids.values()), (
        {name: mapped_segments(pid) for name, pid in pids.items()},
        camera.output(),
        server.output(),
    )

    # every image calibrated on the server, exactly once
    assert sorted(stamps(out, CAMERA_INFO)) == sorted(image_stamps)
    # what crossed the link: at least the working-resolution frames (mono8) frame_ingest sent the tracker
    with BagReader(short_synth_bag) as reader:
        first = deserialize(next(reader.messages([topics.bag_topic(topics.GT_CAMERA_INFO)])).raw,
                            "sensor_msgs/msg/CameraInfo")  # fmt: skip
    working_width = next(p.default for p in INGEST_PARAMS if p.name == "working_width")
    k = downscale_factor(first.width, working_width)
    frame_bytes = len(image_stamps) * (first.width // k) * (first.height // k)
    sent = after[hosts.a]["tx_bytes"] - before[hosts.a]["tx_bytes"]
    received = after[hosts.b]["rx_bytes"] - before[hosts.b]["rx_bytes"]
    assert sent >= frame_bytes and received >= frame_bytes, (sent, received, frame_bytes)
    # ... once: launch's static-peer profile leaves rmw_fastrtps no second UDPv4 transport sending each
    # datagram again, and the receive buffer drops none for the reliable protocol to re-send
    assert received < 1.6 * frame_bytes, (received, frame_bytes)
    # static peers only: nothing was multicast on the link, in either direction
    assert after[hosts.a]["rx_multicast"] == after[hosts.b]["rx_multicast"] == 0, after
    # shared memory within a host, never between them: the server's reader of camera-side frames maps no
    # camera-side segment, while the calibrator maps the tracker's (the check sees shared memory in use)
    assert segments["homography_tracker"] & segments["calibrator"], segments
    assert not segments["frame_ingest"] & (segments["homography_tracker"] | segments["calibrator"]), segments
    for proc in (camera, server):
        assert proc.stop(timeout=20.0) == 0, proc.output()
