"""`ptz-selfcal launch`: three node processes, clean Ctrl-C, restarts, bad parameter files, no orphans."""

from __future__ import annotations

import os
import re
import signal
import time
from collections.abc import Iterable
from pathlib import Path

import pytest
from conftest import cli_command

ROS_DOMAIN_ID = 111
NODES = ("frame_ingest", "homography_tracker", "calibrator")


@pytest.fixture
def launch_env(ros_env, tmp_path) -> tuple[dict[str, str], list[str]]:
    """Environment and extra arguments for the real node suite: a ROS_HOME of the test's own, where
    launch keeps the calibration state by default."""
    return {**ros_env, "ROS_HOME": str(tmp_path / "ros_home")}, []


def started_pids(output: str) -> dict[str, list[int]]:
    pids: dict[str, list[int]] = {}
    for name, pid in re.findall(r"\[launch\] started (\w+) \(pid (\d+)\)", output):
        pids.setdefault(name, []).append(int(pid))
    return pids


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    # reaped children cannot linger; a zombie would still answer kill(0): check its state
    status = Path(f"/proc/{pid}/status")
    return not status.exists() or "zombie" in status.read_text()


def graph_nodes(namespace: str, timeout: float, topics: Iterable[str] = ()) -> tuple[set[str], set[str]]:
    """Node names visible in the ROS graph under a namespace, and the topic names of the graph; polls
    until all three nodes and the given topics are there (a node is visible before its publishers), or
    timeout (a safety net for a loaded machine, not a measured bound)."""
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("test_launch_probe", context=context)
    try:
        deadline = time.monotonic() + timeout
        found: set[str] = set()
        names: set[str] = set()
        while time.monotonic() < deadline:
            found = {n for n, ns in node.get_node_names_and_namespaces() if ns == namespace}
            names = {name for name, _types in node.get_topic_names_and_types()}
            if set(NODES) <= found and set(topics) <= names:
                break
            time.sleep(0.1)
        return found, names
    finally:
        node.destroy_node()
        context.try_shutdown()


def wait_started(proc, count: int, timeout: float = 20.0) -> dict[str, list[int]]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.alive():
        pids = started_pids(proc.output())
        if sum(len(v) for v in pids.values()) >= count:
            return pids
        time.sleep(0.05)
    raise AssertionError(f"launch did not start {count} processes:\n{proc.output()}")


def test_three_processes_ctrl_c_stops_all_with_exit_0(launch_env, start_process):
    env, extra = launch_env
    proc = start_process(
        cli_command("launch", "--namespace", "/cam7", "--remap", "image_raw:=camera/image", *extra),
        env,
        "launch",
    )
    pids = wait_started(proc, 3)
    assert set(pids) == set(NODES) and len({p[0] for p in pids.values()}) == 3
    nodes, topic_names = graph_nodes("/cam7", 60.0, ["/cam7/selfcal/camera_info", "/cam7/camera/image"])
    assert set(NODES) <= nodes, proc.output()
    assert "/cam7/camera/image" in topic_names and "/cam7/image_raw" not in topic_names  # remapped
    assert "/cam7/selfcal/camera_info" in topic_names
    assert proc.alive()
    assert proc.stop(timeout=20.0) == 0, proc.output()
    for name, (pid,) in pids.items():
        assert gone(pid), f"{name} (pid {pid}) survived the launch"
    out = proc.output()
    assert "[launch] stopped (frame_ingest: 0, homography_tracker: 0, calibrator: 0); 0 restarts" in out, out
    assert "[frame_ingest] " in out  # output prefixed with the node name
    # persistence by default, per camera (the namespace names it), under ROS_HOME
    state_dir = Path(env["ROS_HOME"]) / "ptz_selfcal" / "cam7"
    (started,) = [line for line in out.splitlines() if "[cam7.calibrator]: calibrating" in line]
    assert f"state_dir {state_dir};" in started, out
    assert f"saved the calibration state to {state_dir}" in out, out


def test_killed_node_is_restarted_and_supervisor_kill_leaves_no_orphan(launch_env, start_process):
    env, extra = launch_env
    proc = start_process(cli_command("launch", *extra), env, "launch_restart")
    pids = wait_started(proc, 3)
    assert proc.wait_for_output("[frame_ingest] [INFO]", 20.0), proc.output()
    os.kill(pids["frame_ingest"][0], signal.SIGKILL)
    pids = wait_started(proc, 4, timeout=15.0)
    assert len(pids["frame_ingest"]) == 2, proc.output()
    assert "frame_ingest exited unexpectedly with status -9" in proc.output()
    assert proc.wait_for_output("restart #1", 1.0)
    # kill -9 of the supervisor itself: the kernel sends SIGTERM to its children (PR_SET_PDEATHSIG)
    children = [p[-1] for p in pids.values()]
    proc.proc.kill()
    proc.wait(5.0)
    deadline = time.monotonic() + 15.0
    while time.monotonic() < deadline and not all(gone(p) for p in children):
        time.sleep(0.1)
    assert all(gone(p) for p in children), "orphaned node processes after kill -9 of launch"


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("frame_ingest: [\n", "not valid YAML at line"),
        ("camera_driver:\n  ros__parameters: {}\n", "unknown node 'camera_driver'"),
        ("frame_ingest:\n  working_width: 3\n", "must contain ros__parameters"),
        ("- a\n- b\n", "expected a mapping"),
    ],
)
def test_bad_parameter_file_is_refused_before_anything_starts(
    ros_env, start_process, tmp_path, content, message
):
    params = tmp_path / "params.yaml"
    params.write_text(content)
    proc = start_process(cli_command("launch", "--params", str(params)), ros_env, "launch_bad")
    assert proc.wait(30.0) == 2
    out = proc.output()
    assert message in out and "started" not in out, out
    assert len(out.strip().splitlines()) == 1


def test_wrong_parameter_type_stops_the_suite_with_the_node_message(launch_env, start_process, tmp_path):
    env, extra = launch_env
    params = tmp_path / "params.yaml"
    params.write_text("frame_ingest:\n  ros__parameters:\n    working_width: wide\n")
    proc = start_process(cli_command("launch", "--params", str(params), *extra), env, "launch_type")
    assert proc.wait(40.0) == 2, proc.output()
    out = proc.output()
    assert "frame_ingest exited with status 2 at start-up" in out and "working_width" in out, out
    for pid in (p for v in started_pids(out).values() for p in v):
        assert gone(pid)


def test_nice_applies_to_every_node_thread_and_session(launch_env, start_process):
    env, extra = launch_env
    proc = start_process(cli_command("launch", "--namespace", "/cam8", "--nice", "7", *extra), env, "launch")
    pids = wait_started(proc, 3)
    nodes, _ = graph_nodes("/cam8", 60.0)  # up and running: their DDS and executor threads exist now
    assert set(NODES) <= nodes, proc.output()
    for name, (pid,) in pids.items():
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
        assert len(tasks) > 1
        for task in tasks:  # field 19 of stat is the nice value (after the parenthesised command name)
            assert int((task / "stat").read_text().rsplit(")", 1)[1].split()[16]) == 7, (name, task.name)
        autogroup = Path(f"/proc/{pid}/autogroup")
        if autogroup.exists():
            assert autogroup.read_text().split()[-1] == "7", (name, autogroup.read_text())
    assert proc.stop(timeout=20.0) == 0, proc.output()
