"""Both packages build with colcon, as on a full ROS 2 Jazzy install, and their install space works."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import NodeProcess

ROOT = Path(__file__).resolve().parents[2]
VENV_BIN = Path(sys.executable).parent
NODES = ("frame_ingest", "homography_tracker", "calibrator")


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    colcon = VENV_BIN / "colcon"
    if not colcon.exists():
        pytest.fail("colcon is not installed in the environment (ros2_ws/requirements.txt)")
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(ROOT / "src", ws / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    prefix = str(Path(sys.prefix))
    env = {
        "PATH": f"{VENV_BIN}:/usr/bin:/bin",
        "HOME": os.environ.get("HOME", "/tmp"),
        "AMENT_PREFIX_PATH": prefix,
        "CMAKE_PREFIX_PATH": prefix,
    }
    result = subprocess.run(
        [
            str(colcon),
            "build",
            "--cmake-args",
            f"-DPython3_EXECUTABLE={sys.executable}",
            "-DBUILD_TESTING=OFF",
        ],
        cwd=ws,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "2 packages finished" in result.stdout
    return ws / "install"


def test_messages_import_from_install_space(colcon_install: Path) -> None:
    script = (
        "import ptz_selfcal_msgs.msg as m, ptz_selfcal;"
        "print(m.__file__); print(ptz_selfcal.__file__);"
        "f = m.FrameCalibration(status=m.FrameCalibration.CONVERGED, fx=1000.0);"
        "h = m.HomographyStamped(); print(f.status, f.fx, len(h.h))"
    )
    cmd = f"source {colcon_install}/setup.bash && {sys.executable} -c '{script}'"
    result = subprocess.run(
        ["bash", "-c", cmd], env={"PATH": "/usr/bin:/bin"}, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    msg_file, pkg_file, values = result.stdout.strip().splitlines()
    # Imported from the colcon install space, not from the environment the tests run in.
    assert msg_file.startswith(str(colcon_install / "ptz_selfcal_msgs"))
    assert pkg_file.startswith(str(colcon_install / "ptz_selfcal"))
    assert values == "2 1000.0 9"


def test_install_space_has_node_executables_launch_and_config(colcon_install: Path) -> None:
    lib = colcon_install / "ptz_selfcal" / "lib" / "ptz_selfcal"
    for exe in ("ptz-selfcal", "frame_ingest", "homography_tracker", "calibrator", "mosaic"):
        assert (lib / exe).exists(), f"{exe} missing from {lib}"
    share = colcon_install / "ptz_selfcal" / "share" / "ptz_selfcal"
    assert (share / "package.xml").exists()
    assert (share / "launch" / "ptz_selfcal.launch.py").exists()
    assert (share / "config" / "ptz_selfcal.yaml").exists()
    assert (share / "config" / "fastdds.xml").exists()
    assert (
        colcon_install / "ptz_selfcal_msgs" / "share" / "ptz_selfcal_msgs" / "msg" / "FrameCalibration.msg"
    ).exists()


# The install space's own programs run from a shell that sourced only its setup.bash.
ROS_DOMAIN_ID = 124


def install_env(tmp_path: Path) -> dict[str, str]:
    return {
        "PATH": "/usr/bin:/bin",
        "HOME": os.environ.get("HOME", "/tmp"),
        "ROS_HOME": str(tmp_path / "ros_home"),  # where launch keeps per-camera state
        "ROS_DOMAIN_ID": str(ROS_DOMAIN_ID),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
    }


def start_installed(colcon_install: Path, tmp_path: Path, name: str, *args: str) -> NodeProcess:
    """An executable of the install space (lib/ptz_selfcal/<name>) after `source setup.bash`; exec, so
    that Ctrl-C (SIGINT) reaches it and not the shell."""
    exe = colcon_install / "ptz_selfcal" / "lib" / "ptz_selfcal" / name
    cmd = f"source {colcon_install}/setup.bash && exec {exe} {' '.join(args)}"
    return NodeProcess(["bash", "-c", cmd], install_env(tmp_path), tmp_path, name)


def wait_for(proc: NodeProcess, texts: list[str], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.alive():
        if all(t in proc.output() for t in texts):
            return True
        time.sleep(0.1)
    return all(t in proc.output() for t in texts)


def test_launch_runs_from_the_install_space_and_stops_on_ctrl_c(colcon_install: Path, tmp_path: Path) -> None:
    proc = start_installed(colcon_install, tmp_path, "ptz-selfcal", "launch")
    try:
        # each node logs its start-up line (after its parameters were read from the installed config), as
        # logger <namespace>.<node>
        started = [f"[launch] started {n}" for n in NODES] + [f".{n}]: " for n in NODES]
        ok = wait_for(proc, started, 180.0)
        out = proc.output()
        assert ok and proc.alive(), out
    finally:
        code = proc.stop(timeout=30.0)
    out = proc.output()
    assert "cannot read parameter file" not in out and "configuration error" not in out, out
    assert code == 0, out
    assert "[launch] stopped (frame_ingest: 0, homography_tracker: 0, calibrator: 0)" in out, out


def test_the_installed_config_is_found_through_the_ament_index(colcon_install: Path, tmp_path: Path) -> None:
    script = "from ptz_selfcal.tools.launch import default_params_file; print(default_params_file())"
    cmd = f"source {colcon_install}/setup.bash && {sys.executable} -c '{script}'"
    result = subprocess.run(
        ["bash", "-c", cmd], env=install_env(tmp_path), capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    share = colcon_install / "ptz_selfcal" / "share" / "ptz_selfcal"
    assert result.stdout.strip() == str(share / "config" / "ptz_selfcal.yaml")


def test_a_node_runs_from_the_install_space(colcon_install: Path, tmp_path: Path) -> None:
    proc = start_installed(colcon_install, tmp_path, "frame_ingest", "--ros-args", "-p", "camera_name:=cam9")
    try:
        assert wait_for(proc, ["ptz.frame_ingest]: "], 120.0) and proc.alive(), proc.output()
        # it is a node of the graph: its diagnostics come with the camera_name it was given
        assert diagnostics_hardware_ids(20.0) == {"cam9"}, proc.output()
    finally:
        code = proc.stop(timeout=20.0)
    assert code == 0, proc.output()


def diagnostics_hardware_ids(timeout: float) -> set[str]:
    """The hardware_ids of the first DiagnosticArray on this test's domain."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ROS_DOMAIN_ID)
    node = rclpy.create_node("test_colcon_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    found: list[set[str]] = []
    node.create_subscription(
        DiagnosticArray, "/diagnostics", lambda m: found.append({s.hardware_id for s in m.status}), 10
    )
    try:
        deadline = time.monotonic() + timeout
        while not found and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        return found[0] if found else set()
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()


def test_package_xml_declares_what_the_package_imports() -> None:
    """Every module the package (and its launch file) imports that is not the standard library is an
    exec_depend, under its rosdep key."""
    import ast
    import xml.etree.ElementTree as ET

    keys = {  # module -> rosdep key, where they differ
        "numpy": "python3-numpy",
        "scipy": "python3-scipy",
        "cv2": "python3-opencv",
        "yaml": "python3-yaml",
        "matplotlib": "python3-matplotlib",
        "rosbags": "python3-rosbags-pip",
    }
    package = ROOT / "src" / "ptz_selfcal"
    declared = {e.text for e in ET.parse(package / "package.xml").getroot().iter("exec_depend")}
    imported: set[str] = set()
    for path in [*(package / "ptz_selfcal").rglob("*.py"), *(package / "launch").glob("*.py")]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split(".")[0])
    external = imported - set(sys.stdlib_module_names) - {"ptz_selfcal", "__future__"}
    missing = {keys.get(m, m) for m in external} - declared
    assert not missing, f"imported but not in package.xml: {sorted(missing)}"
    assert {"rcl_interfaces", "launch", "launch_ros", "ament_index_python"} <= declared


def test_package_xml_declares_the_bag_readers_the_tests_use() -> None:
    """The libraries the tests read bags with (rosbags, and MCAP's own readers) are test_depends (or
    exec_depends), under their rosdep keys."""
    import ast
    import xml.etree.ElementTree as ET

    keys = {
        "pytest": "python3-pytest",
        "mcap": "python3-mcap-pip",
        "mcap_ros2": "python3-mcap-ros2-support-pip",
        "rosbags": "python3-rosbags-pip",
    }
    root = ET.parse(ROOT / "src" / "ptz_selfcal" / "package.xml").getroot()
    declared = {e.text for tag in ("test_depend", "exec_depend") for e in root.iter(tag)}
    imported: set[str] = set()
    for path in (ROOT / "tests").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split(".")[0])
    assert {"mcap", "mcap_ros2"} <= imported  # what this test is about is still used (rosbags: via bagio)
    missing = {keys[m] for m in imported & set(keys)} - declared
    assert not missing, f"imported by the tests but not in package.xml: {sorted(missing)}"
