"""`ptz-selfcal run`: a bag through the real node processes in lock-step; every image gets its CameraInfo.

The bag (conftest short_synth_bag) starts where the shipped prior does not: the prior's f 25 % short,
the principal point 20 px off centre, zoom encoders through synth's nonlinear, lagged, noisy law. These
tests count and match outputs; the accuracy of a replay is tests/bag/test_eval.py's.
"""

from __future__ import annotations

import math
import re
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import cli_command

from ptz_selfcal import topics
from ptz_selfcal.tools.bagio import BagReader, BagWriter, deserialize, serialize

ROS_DOMAIN_ID = 112
IMAGE = topics.bag_topic(topics.IMAGE_COMPRESSED)
JOINTS = topics.bag_topic(topics.JOINT_STATES)


@pytest.fixture
def run_env(ros_env) -> tuple[dict[str, str], list[str]]:
    """The real node suite's environment, and no extra arguments for `run`."""
    return ros_env, []


def run_cli(env: dict[str, str], *args: str, timeout: float = 90.0) -> subprocess.CompletedProcess:
    return subprocess.run(cli_command("run", *args), env=env, capture_output=True, text=True, timeout=timeout)


def stamps(bag: Path, topic: str) -> list[int]:
    with BagReader(bag) as reader:
        out = []
        for msg in reader.messages([topic]):
            m = deserialize(msg.raw, msg.msgtype)
            out.append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
        return out


def final_counters(bag: Path, node: str) -> dict[str, str]:
    last: dict[str, str] = {}
    with BagReader(bag) as reader:
        for msg in reader.messages(["/diagnostics"]):
            for status in deserialize(msg.raw, msg.msgtype).status:
                if status.name.endswith(node):
                    last = {kv.key: kv.value for kv in status.values}
    return last


def test_every_image_gets_one_camera_info_and_everything_is_recorded(run_env, short_synth_bag, tmp_path):
    env, extra = run_env
    out = tmp_path / "out"
    result = run_cli(env, str(short_synth_bag), "--out", str(out), "--window", "3", *extra)
    assert result.returncode == 0, result.stderr
    image_stamps = stamps(short_synth_bag, IMAGE)
    info_stamps = stamps(out, topics.bag_topic(topics.CAMERA_INFO))
    assert len(image_stamps) == 40
    assert sorted(info_stamps) == sorted(image_stamps)  # coverage 100 %, exactly one per image
    with BagReader(out) as reader, BagReader(short_synth_bag) as source:
        counts = {t.name: t.count for t in reader.topics()}
        source_counts = {t.name: t.count for t in source.topics()}
    assert counts[topics.bag_topic(topics.FRAME_CALIBRATION)] == 40
    assert counts[topics.bag_topic(topics.HOMOGRAPHY)] == 40
    assert counts["/diagnostics"] > 0
    assert topics.bag_topic(topics.KEYFRAMES) in counts
    for copied in (topics.GT_CAMERA_INFO, topics.GT_JOINT_STATES, topics.JOINT_STATES):
        assert counts[topics.bag_topic(copied)] == source_counts[topics.bag_topic(copied)]
    assert IMAGE not in counts  # images are not copied
    with BagReader(out) as reader:
        info = next(
            deserialize(m.raw, m.msgtype) for m in reader.messages([topics.bag_topic(topics.CAMERA_INFO)])
        )
    assert (info.width, info.height) == (640, 360) and all(math.isfinite(v) for v in info.k)
    m = re.search(
        r"run: 40/40 images got a CameraInfo \(coverage 100.0%\).* ([\d.]+) frames/s", result.stderr
    )
    assert m, result.stderr
    ingest = final_counters(out, "frame_ingest")
    assert ingest.get("frames_out") == "40", ingest


def damaged_copy(source: Path, out: Path) -> None:
    """The bag with a corrupt image (index 10), a NaN encoder value and two images in swapped order."""
    with BagReader(source) as reader:
        messages = list(reader.messages())
    images = [i for i, m in enumerate(messages) if m.topic == IMAGE]
    joints = [i for i, m in enumerate(messages) if m.topic == JOINTS]
    a, b = images[20], images[21]
    # bag (arrival) order kept, header stamps swapped: image 21's stamp arrives before image 20's
    ta, tb = messages[a].timestamp_ns, messages[b].timestamp_ns
    messages[a], messages[b] = replace(messages[b], timestamp_ns=ta), replace(messages[a], timestamp_ns=tb)
    with BagWriter(out) as writer:
        for i, msg in enumerate(messages):
            raw = msg.raw
            if i == images[10]:
                m = deserialize(raw, msg.msgtype)
                m.data = np.frombuffer(b"\xff\xd8\xff\xe0 this is not a jpeg any more" * 20, np.uint8)
                raw = serialize(m, msg.msgtype)
            elif i == joints[5]:
                m = deserialize(raw, msg.msgtype)
                m.position = np.array([math.nan, *m.position[1:]])
                raw = serialize(m, msg.msgtype)
            writer.add_topic(msg.topic, msg.msgtype)
            writer.write_raw(msg.topic, msg.timestamp_ns, raw)


def test_bad_frames_are_counted_and_every_good_frame_is_calibrated(run_env, short_synth_bag, tmp_path):
    env, extra = run_env
    bad = tmp_path / "bad"
    damaged_copy(short_synth_bag, bad)
    out = tmp_path / "out"
    result = run_cli(env, str(bad), "--out", str(out), "--timeout", "5", *extra)
    assert result.returncode == 0, result.stderr
    assert (
        "39/40 images got a CameraInfo" in result.stderr and "1 skipped by the nodes, 0 lost" in result.stderr
    )
    image_stamps = stamps(bad, IMAGE)
    corrupt = image_stamps[10]
    info_stamps = stamps(out, topics.bag_topic(topics.CAMERA_INFO))
    assert sorted(info_stamps) == sorted(s for s in image_stamps if s != corrupt)
    ingest = final_counters(out, "frame_ingest")
    assert ingest.get("skipped_undecodable") == "1", ingest
    assert ingest.get("encoder_rejected_not_finite") == "1", ingest
    assert ingest.get("image_stamp_out_of_order") == "1", ingest


def test_nodes_that_cannot_start_give_a_clear_error(ros_env, short_synth_bag, tmp_path):
    result = run_cli(
        ros_env,
        str(short_synth_bag),
        "--out",
        str(tmp_path / "out"),
        "--calibrator-module",
        "no_such_module_xyz",
    )
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    assert "ptz-selfcal run: error: the nodes failed: calibrator exited with status 1 at start-up" in last


def test_input_errors(ros_env, short_synth_bag, tmp_path):
    result = run_cli(ros_env, str(tmp_path), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "not a ROS 2 bag" in result.stderr
    empty = tmp_path / "noimages"
    with BagWriter(empty) as writer:
        writer.add_topic("/other", "sensor_msgs/msg/JointState")
    result = run_cli(ros_env, str(empty), "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "no /ptz/image_raw or /ptz/image_raw/compressed topic" in result.stderr
    result = run_cli(ros_env, str(short_synth_bag), "--out", str(short_synth_bag))
    assert result.returncode == 2 and "already exists" in result.stderr
