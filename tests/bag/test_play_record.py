"""`ptz-selfcal play` and `record` in separate real processes over DDS: nothing lost, nothing changed."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ptz_selfcal.tools.bagio import BagReader, BagWriter, typestore

PTZ = [sys.executable, "-m", "ptz_selfcal.tools.cli"]
IMAGE_TOPIC = "/ptz/image_raw"
JOINT_TOPIC = "/ptz/joint_states"


def ros_env(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain))
    return env


def make_input_bag(path: Path, n_images: int = 300, encoders_per_image: int = 3) -> None:
    T = typestore().types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    rng = np.random.default_rng(7)
    with BagWriter(path) as writer:
        for i in range(n_images):
            t_ns = 1_700_000_000_000_000_000 + i * 33_333_333
            for k in range(encoders_per_image):
                te = t_ns + k * 11_111_111
                js = T["sensor_msgs/msg/JointState"](
                    header=Header(stamp=Time(sec=te // 10**9, nanosec=te % 10**9), frame_id=""),
                    name=["pan", "tilt", "zoom"],
                    position=rng.normal(size=3),
                    velocity=np.zeros(0),
                    effort=np.zeros(0),
                )
                writer.write(JOINT_TOPIC, "sensor_msgs/msg/JointState", te, js)
            img = T["sensor_msgs/msg/Image"](
                header=Header(stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9), frame_id="ptz_camera"),
                height=240,
                width=320,
                encoding="mono8",
                is_bigendian=0,
                step=320,
                data=rng.integers(0, 256, 240 * 320, dtype=np.uint8),
            )
            writer.write(IMAGE_TOPIC, "sensor_msgs/msg/Image", t_ns, img)


def payloads(path: Path) -> dict[str, list[bytes]]:
    out: dict[str, list[bytes]] = {IMAGE_TOPIC: [], JOINT_TOPIC: []}
    with BagReader(path) as reader:
        for msg in reader.messages():
            out[msg.topic].append(msg.raw)
    return out


def test_play_record_round_trip_is_lossless_and_exact(tmp_path: Path) -> None:
    src, out = tmp_path / "in", tmp_path / "out"
    make_input_bag(src)
    env = ros_env(101)
    recorder = subprocess.Popen(
        [
            *PTZ, "record", str(out), "--topics", IMAGE_TOPIC, JOINT_TOPIC,
            "--type", f"{IMAGE_TOPIC}=sensor_msgs/msg/Image",
            "--type", f"{JOINT_TOPIC}=sensor_msgs/msg/JointState",
            "--max-messages", "1200", "--idle-timeout", "20",
        ],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert "record: recording" in recorder.stdout.readline()
        play = subprocess.run(
            [*PTZ, "play", str(src), "--rate", "0", "--wait-subscribers", "15", "--quiet"],
            env=env, capture_output=True, text=True, timeout=180,
        )  # fmt: skip
        assert play.returncode == 0, play.stderr
        recorder.wait(timeout=120)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == 0, recorder.stderr.read()
    sent, got = payloads(src), payloads(out)
    assert len(got[IMAGE_TOPIC]) == 300 and len(got[JOINT_TOPIC]) == 900
    # Identical CDR payloads (header stamps included), in the order they were sent on each topic.
    assert got[IMAGE_TOPIC] == sent[IMAGE_TOPIC]
    assert got[JOINT_TOPIC] == sent[JOINT_TOPIC]


def test_play_honours_bag_timing_scaled_by_rate(tmp_path: Path) -> None:
    src = tmp_path / "in"
    make_input_bag(src, n_images=30, encoders_per_image=1)  # spans 29 * 33.3 ms = 0.97 s
    start = time.monotonic()
    play = subprocess.run(
        [*PTZ, "play", str(src), "--rate", "0.5", "--quiet"],
        env=ros_env(102), capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    elapsed = time.monotonic() - start
    assert play.returncode == 0, play.stderr
    assert elapsed >= 0.97 / 0.5, f"played a 0.97 s bag at rate 0.5 in {elapsed:.2f} s"


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (lambda p: None, "no such bag"),
        (lambda p: p.write_text("not a bag"), "not a ROS 2 bag"),
        (
            lambda p: (p.mkdir(), (p / "metadata.yaml").write_text("rosbag2_bagfile_information: {")),
            "cannot open",
        ),
    ],
    ids=["missing", "plain-file", "corrupt-metadata"],
)
def test_play_rejects_bad_bags_with_one_line(tmp_path: Path, make, expected: str) -> None:
    bag = tmp_path / "bag"
    make(bag)
    result = subprocess.run(
        [*PTZ, "play", str(bag)], env=ros_env(103), capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2
    assert expected in result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_play_rejects_a_file_with_nothing_readable(tmp_path: Path) -> None:
    """A truncated bag is played up to its last complete record (tests/bag/test_bag_recovery.py); a
    file with no readable record at all is a clean one-line failure."""
    src = tmp_path / "in"
    make_input_bag(src, n_images=40, encoders_per_image=1)
    storage = next(src.glob("*.mcap"))
    storage.write_bytes(bytes(range(256)) * 20)
    result = subprocess.run(
        [*PTZ, "play", str(src), "--rate", "0", "--quiet"], env=ros_env(104), capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    assert "cannot open bag" in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_record_refuses_existing_path(tmp_path: Path) -> None:
    existing = tmp_path / "out"
    existing.mkdir()
    (existing / "keep.txt").write_text("precious")
    result = subprocess.run(
        [*PTZ, "record", str(existing), "--topics", IMAGE_TOPIC], env=ros_env(105), capture_output=True,
        text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 2
    assert "already exists" in result.stderr and "Traceback" not in result.stderr
    assert (existing / "keep.txt").read_text() == "precious"
