"""The shipped Fast DDS profile is what the processes really run with: Fast DDS falls back to its
defaults (a 512 KB shared-memory segment) when it rejects a profile, with only a log line to say so,
so these tests read the segment each participant mapped."""

from __future__ import annotations

import re
import time
import xml.etree.ElementTree as ET
from pathlib import Path

from conftest import PYTHON, cli_command

from ptz_selfcal.tools.launch import PROFILE_VARIABLES, default_profile_file

ROS_DOMAIN_ID = 174
SEGMENT = re.compile(r"([0-9a-f]+)-([0-9a-f]+) .*/dev/shm/fastrtps_[0-9a-f]{16}$")


def shipped_segment_size() -> int:
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.parse(default_profile_file()).getroot()
    (size,) = [
        int(d.find("f:segment_size", ns).text)
        for d in root.findall("f:transport_descriptors/f:transport_descriptor", ns)
        if d.find("f:type", ns).text == "SHM"
    ]
    return size


def mapped_segments(pid: int) -> list[int]:
    """Sizes of the Fast DDS shared-memory segments a process has mapped (its own and its peers')."""
    try:
        lines = Path(f"/proc/{pid}/maps").read_text().splitlines()
    except OSError:
        return []
    return [int(m.group(2), 16) - int(m.group(1), 16) for m in map(SEGMENT.match, lines) if m]


def wait_for_segment(proc, pid: int, size: int, timeout: float = 30.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.alive():
        segments = mapped_segments(pid)
        if any(s >= size for s in segments):
            return segments
        time.sleep(0.1)
    return mapped_segments(pid)


def test_a_test_process_participant_uses_the_shipped_segment(ros_env, start_process):
    """ros_env (every node, run and launch test) names the shipped profile, and Fast DDS accepts it."""
    assert ros_env[PROFILE_VARIABLES[0]] == str(default_profile_file())
    size = shipped_segment_size()
    script = "import rclpy, time; rclpy.init(); n = rclpy.create_node('profile_probe'); time.sleep(60)"
    proc = start_process([PYTHON, "-c", script], ros_env, "probe")
    segments = wait_for_segment(proc, proc.pid, size)
    assert any(s >= size for s in segments), (segments, proc.output())


def test_launched_nodes_use_the_shipped_segment_even_from_a_bare_environment(ros_env, start_process):
    """`launch` gives its nodes the profile itself: a user's shell names none."""
    env = {k: v for k, v in ros_env.items() if k not in PROFILE_VARIABLES}
    proc = start_process(cli_command("launch", "--nodes", "frame_ingest", "--no-persist"), env, "launch")
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and "started frame_ingest (pid" not in proc.output():
        time.sleep(0.05)
    match = re.search(r"started frame_ingest \(pid (\d+)\)", proc.output())
    assert match, proc.output()
    assert f"Fast DDS profile {default_profile_file()}" in proc.output()
    size = shipped_segment_size()
    segments = wait_for_segment(proc, int(match.group(1)), size)
    assert any(s >= size for s in segments), (segments, proc.output())
    assert proc.stop(timeout=20.0) == 0, proc.output()
