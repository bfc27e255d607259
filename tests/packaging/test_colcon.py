"""Both packages build with colcon, as on a full ROS 2 Jazzy install, and their install space works."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
VENV_BIN = Path(sys.executable).parent


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
    for exe in ("ptz-selfcal", "frame_ingest", "homography_tracker", "calibrator"):
        assert (lib / exe).exists(), f"{exe} missing from {lib}"
    share = colcon_install / "ptz_selfcal" / "share" / "ptz_selfcal"
    assert (share / "package.xml").exists()
    assert (share / "launch" / "ptz_selfcal.launch.py").exists()
    assert (share / "config" / "ptz_selfcal.yaml").exists()
    assert (
        colcon_install / "ptz_selfcal_msgs" / "share" / "ptz_selfcal_msgs" / "msg" / "FrameCalibration.msg"
    ).exists()
