"""camera_info_manager's habits of the calibrator, in a real node process over DDS: camera_info_url seeds
the prior, ~/set_camera_info anchors the zoom model, ~/reset and `ptz-selfcal reset` start afresh, and a
saved state of another camera (image size) is dropped with a warning.

The homographies are exact synthetic geometry (test_calibrator's sweep: a zooming pan/tilt with keyframe
matches at 0.2 px noise), sent in lock-step.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from sensor_msgs.msg import CameraInfo  # noqa: E402
from sensor_msgs.srv import SetCameraInfo  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_calibrator import (  # noqa: E402
    HEIGHT,
    KEYFRAME_EVERY,
    WIDTH,
    _diag_value,
    _namespaced_harness,
    sequence,
    shipped_params,
    stop,
    sweep_encoder,
)

from ptz_selfcal import topics  # noqa: E402
from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation  # noqa: E402
from ptz_selfcal.persist.state_files import STATE_FILE, ZOOM_MODEL_FILE  # noqa: E402
from ptz_selfcal.zoom import ZoomModel  # noqa: E402
from ptz_selfcal.zoom.camera_calibration import camera_calibration_yaml  # noqa: E402
from ptz_selfcal_msgs.msg import FrameCalibration, HomographyStamped  # noqa: E402

ROS_DOMAIN_ID = 144
CALIBRATED = (FrameCalibration.CALIBRATING, FrameCalibration.CONVERGED)


@pytest.fixture
def ros(ros_env):
    """rclpy in this test's domain and ROS_HOME (conftest's ros_env), for the test and its processes."""
    rclpy.init()
    yield
    rclpy.shutdown()


def _env() -> dict[str, str]:
    return dict(os.environ)  # ros_env's


def start(namespace: str, params_dir: Path, *params: str) -> subprocess.Popen:
    """The calibrator on the shipped parameters, `params` (name:=value) overriding them."""
    args = [sys.executable, "-m", "ptz_selfcal.nodes.calibrator", "--ros-args", "-r", f"__ns:={namespace}"]
    args += ["--params-file", str(shipped_params(params_dir, namespace)), "-p", "diagnostics_period:=0.2"]
    for p in params:
        args += ["-p", p]
    args += ["-r", f"{topics.DIAGNOSTICS}:={namespace}{topics.DIAGNOSTICS}"]
    return subprocess.Popen(args, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def send(harness, j: int, H, state: int, keyframe_id: int, zoom: float, size=(WIDTH, HEIGHT)) -> int:
    """One HomographyStamped of images `size`; waits for its CameraInfo and FrameCalibration."""
    return harness.send(j, H, state, keyframe_id, zoom, size=size)


def sweep(harness, offset: int, keyframes: int, n: int = 140) -> tuple[np.ndarray, list[int]]:
    """test_calibrator's zooming sweep (frames offset.., keyframes every KEYFRAME_EVERY, with matches),
    then its last views again once the worker has settled (its keyframes counter, which a reset does not
    reset, at `keyframes`): (true K of those views, their stamps)."""
    K, _, H, _ = sequence(n, pan_deg=30.0, tilt_deg=8.0)
    zoom = sweep_encoder(n)
    rng = np.random.default_rng(5)
    for j in range(n):
        keyframe = j % KEYFRAME_EVERY == 0
        state = HomographyStamped.NEW_KEYFRAME if keyframe else HomographyStamped.TRACKING
        if keyframe and j > 0:
            harness.send_matches(j, j - KEYFRAME_EVERY, H, rng)
        send(harness, offset + j, H[j], state, j - j % KEYFRAME_EVERY, zoom[j])
        time.sleep(0.01)
    harness.wait_settled(expected_keyframes=keyframes, timeout=40.0)
    late = list(range(n - 6, n))
    stamps = [
        send(harness, offset + n + 10 + k, H[j], HomographyStamped.TRACKING, n - 8, zoom[j])
        for k, j in enumerate(late)
    ]
    return K[late], stamps


def call(harness, srv_type, name: str, request, timeout: float = 10.0):
    client = harness.node.create_client(srv_type, name)
    try:
        assert client.wait_for_service(timeout_sec=timeout), f"no service {name}"
        future = client.call_async(request)
        assert harness.spin_until(future.done, timeout), f"{name} did not answer"
        return future.result()
    finally:
        harness.node.destroy_client(client)


def camera_info_request(K: np.ndarray, size=(WIDTH, HEIGHT)) -> SetCameraInfo.Request:
    request = SetCameraInfo.Request()
    info = CameraInfo()
    info.width, info.height = size
    info.distortion_model = "plumb_bob"
    info.d = [0.0] * 5
    info.k = [float(v) for v in np.asarray(K, dtype=float).ravel()]
    info.r = [float(v) for v in np.eye(3).ravel()]
    info.p = [float(v) for v in np.hstack([K, np.zeros((3, 1))]).ravel()]
    request.camera_info = info
    return request


def published_K(harness, stamp: int) -> np.ndarray:
    return np.array(harness.infos[stamp].k).reshape(3, 3)


def pan(K: np.ndarray, degrees: float) -> np.ndarray:
    """The homography of a pan by `degrees` at a constant K (from the reference view)."""
    return K @ ptz_rotation(math.radians(degrees), 0.0) @ np.linalg.inv(K)


def nominal_K(width: int, height: int) -> np.ndarray:
    """The shipped prior: 60 degrees horizontal field of view at the image centre."""
    return intrinsic_matrix(0.5 * width / math.tan(math.radians(30.0)), 0.5 * (width - 1), 0.5 * (height - 1))


def test_camera_info_url_seeds_the_prior(ros, tmp_path: Path) -> None:
    """The file's K (off centre, not the nominal 60 degrees) is what the frames get before the first
    calibration, through the reference and through the first pans; a file of another image size is
    ignored with a warning and counted; a file that cannot be read is a configuration error (exit 2)."""
    K_file = intrinsic_matrix(1450.0, 652.0, 348.5)
    path = tmp_path / "cam_s.yaml"
    path.write_text(camera_calibration_yaml(K_file, np.zeros(5), WIDTH, HEIGHT, "cam_s"))
    ns = "/cam_s"
    proc = start(ns, tmp_path / "p1", f"camera_info_url:=file://{path}")
    harness = _namespaced_harness(ns)
    output = ""
    try:
        harness.wait_connected()
        stamps = [send(harness, 0, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, 100.0)]
        stamps += [
            send(harness, j, pan(K_file, 0.2 * j), HomographyStamped.TRACKING, 0, 100.0) for j in range(1, 8)
        ]
        for s in stamps:
            assert harness.frames[s].status == FrameCalibration.INITIALISING
            np.testing.assert_allclose(published_K(harness, s), K_file, rtol=1e-6, atol=1e-4)
    finally:
        output += stop(proc)
    assert "prior K from" in output, output

    small = tmp_path / "small.yaml"
    small.write_text(camera_calibration_yaml(0.5 * K_file, np.zeros(5), 640, 360, "cam_s"))
    proc = start(ns, tmp_path / "p2", f"camera_info_url:={small}")  # a plain path
    try:
        harness.wait_connected()
        s = send(harness, 100, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, 100.0)
        np.testing.assert_allclose(published_K(harness, s), nominal_K(WIDTH, HEIGHT), rtol=1e-9)
        assert harness.spin_until(lambda: _diag_value(harness.diagnostics, "prior_size_mismatches") == 1, 5.0)
    finally:
        output = stop(proc)
        harness.close()
    assert "ignored, the nominal prior instead" in output, output

    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "ptz_selfcal.nodes.calibrator",
            "--ros-args",
            "-p",
            f"camera_info_url:=file://{tmp_path / 'missing.yaml'}",
        ],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2, (bad.returncode, bad.stdout, bad.stderr)
    assert "camera_info_url" in bad.stderr and "missing.yaml" in bad.stderr, bad.stderr


def test_set_camera_info_anchors_the_zoom_model(ros, tmp_path: Path) -> None:
    """A checkerboard K given through ~/set_camera_info at the current zoom: the frames at that zoom
    get it (from the zoom model, before any calibration), the saved zoom model predicts it there; a K
    that is not positive definite, K = 0 or another image size is refused with the reason, changing
    nothing."""
    ns = "/cam_k"
    state_dir = tmp_path / "state"
    proc = start(ns, tmp_path, f"state_dir:={state_dir}")
    harness = _namespaced_harness(ns)
    zoom = 2345.0
    K_meas = intrinsic_matrix(1620.0, 646.0, 352.0)
    service = f"{ns}/calibrator/set_camera_info"
    output = ""
    try:
        harness.wait_connected()
        first = send(harness, 0, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, zoom)
        np.testing.assert_allclose(published_K(harness, first), nominal_K(WIDTH, HEIGHT), rtol=1e-9)

        not_pd = K_meas.copy()
        not_pd[1, 1] = -not_pd[1, 1]
        for K, size, reason in (
            (not_pd, (WIDTH, HEIGHT), "positive definite"),
            (np.zeros((3, 3)), (WIDTH, HEIGHT), "uncalibrated"),
            (K_meas, (640, 480), "differs from the images"),
        ):
            answer = call(harness, SetCameraInfo, service, camera_info_request(K, size))
            assert not answer.success and reason in answer.status_message, answer.status_message
        s = send(harness, 1, np.eye(3), HomographyStamped.TRACKING, 0, zoom)
        np.testing.assert_allclose(published_K(harness, s), nominal_K(WIDTH, HEIGHT), rtol=1e-9)

        answer = call(harness, SetCameraInfo, service, camera_info_request(K_meas))
        assert answer.success and f"zoom {zoom:g}" in answer.status_message, answer.status_message
        got = {}

        def anchored() -> bool:  # the worker takes it in beside the frames: the next frames show it
            got["stamp"] = send(harness, 2 + len(got), pan(K_meas, 0.3), HomographyStamped.TRACKING, 0, zoom)
            return np.allclose(published_K(harness, got["stamp"]), K_meas, rtol=1e-6)

        assert harness.spin_until(anchored, 10.0), published_K(harness, got["stamp"])
        assert harness.frames[got["stamp"]].status == FrameCalibration.INITIALISING
        assert harness.spin_until(lambda: _diag_value(harness.diagnostics, "camera_info_anchors") == 1, 5.0)
        assert _diag_value(harness.diagnostics, "set_camera_info_refused") == 3
    finally:
        output += stop(proc)
        harness.close()
    assert "set_camera_info: K" in output, output
    prediction = ZoomModel.load(state_dir / ZOOM_MODEL_FILE).predict(zoom)
    np.testing.assert_allclose(prediction.K, K_meas, rtol=1e-6)


def test_reset_by_service_and_by_cli_starts_afresh(ros, tmp_path: Path) -> None:
    """Calibrated and saved, then ~/reset: the state files are gone, the next frame is INITIALISING on the
    nominal prior, and the same sweep calibrates again; `ptz-selfcal reset` does the same through the
    service while the calibrator runs, and deletes the files of a stopped one; each says which."""
    ns = "/cam_r"
    state_dir = tmp_path / "state"
    files = [state_dir / STATE_FILE, state_dir / ZOOM_MODEL_FILE]
    proc = start(ns, tmp_path, f"state_dir:={state_dir}", "save_period:=0.5")
    harness = _namespaced_harness(ns)
    cli = [sys.executable, "-m", "ptz_selfcal.tools.cli", "reset", "--namespace", ns]
    output = ""
    try:
        harness.wait_connected()
        K_true, stamps = sweep(harness, 0, 139 // KEYFRAME_EVERY)
        assert harness.frames[stamps[-1]].status in CALIBRATED
        assert abs(harness.infos[stamps[-1]].k[0] / K_true[-1][0, 0] - 1.0) < 0.005
        assert harness.spin_until(lambda: all(f.exists() for f in files), 10.0)

        answer = call(harness, Trigger, f"{ns}/calibrator/reset", Trigger.Request())
        assert answer.success and "removed" in answer.message, answer.message
        assert not any(f.exists() for f in files)
        s = send(harness, 1000, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, 100.0)
        assert harness.frames[s].status == FrameCalibration.INITIALISING
        np.testing.assert_allclose(published_K(harness, s), nominal_K(WIDTH, HEIGHT), rtol=1e-9)
        assert harness.spin_until(lambda: _diag_value(harness.diagnostics, "resets") == 1, 5.0)

        K_true, stamps = sweep(harness, 2000, 2 * (139 // KEYFRAME_EVERY))
        assert harness.frames[stamps[-1]].status in CALIBRATED
        assert abs(harness.infos[stamps[-1]].k[0] / K_true[-1][0, 0] - 1.0) < 0.005
        assert harness.spin_until(lambda: all(f.exists() for f in files), 10.0)

        running = subprocess.run(cli, env=_env(), capture_output=True, text=True, timeout=60)
        assert running.returncode == 0, running.stdout + running.stderr
        assert "reset the running calibrator" in running.stdout, running.stdout
        assert not any(f.exists() for f in files)
        s = send(harness, 5000, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, 100.0)
        assert harness.frames[s].status == FrameCalibration.INITIALISING
    finally:
        output += stop(proc)
        harness.close()
    assert files[0].exists(), output  # the shutdown save: the fresh session's state (no zoom model yet)
    stopped = subprocess.run(
        [*cli, "--state-dir", str(state_dir), "--wait", "1"],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert stopped.returncode == 0, stopped.stdout + stopped.stderr
    assert "no calibrator answers" in stopped.stdout and "removed" in stopped.stdout, stopped.stdout
    assert not any(f.exists() for f in files)


def test_a_saved_state_of_another_image_size_is_dropped(ros, tmp_path: Path) -> None:
    """A state saved at 1280x720 (a zoom model anchored by set_camera_info), then frames of 640x360 (a
    swapped camera): a warning, the saved files removed, the frames on the nominal prior of the new size
    (not the old camera's zoom model), counted as a reset."""
    ns = "/cam_w"
    state_dir = tmp_path / "state"
    zoom = 500.0
    K_old = intrinsic_matrix(1620.0, 646.0, 352.0)
    proc = start(ns, tmp_path, f"state_dir:={state_dir}")
    harness = _namespaced_harness(ns)
    try:
        harness.wait_connected()
        send(harness, 0, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, zoom)
        answer = call(harness, SetCameraInfo, f"{ns}/calibrator/set_camera_info", camera_info_request(K_old))
        assert answer.success, answer.status_message
        got = {}

        def anchored() -> bool:
            got["stamp"] = send(harness, 1 + len(got), np.eye(3), HomographyStamped.TRACKING, 0, zoom)
            return np.allclose(published_K(harness, got["stamp"]), K_old, rtol=1e-6)

        assert harness.spin_until(anchored, 10.0)
    finally:
        output = stop(proc)
    assert (state_dir / STATE_FILE).exists() and (state_dir / ZOOM_MODEL_FILE).exists(), output

    proc = start(ns, tmp_path, f"state_dir:={state_dir}")
    try:
        harness.wait_connected()
        s = send(harness, 100, np.eye(3), HomographyStamped.NEW_KEYFRAME, 0, zoom, size=(640, 360))
        assert harness.frames[s].status == FrameCalibration.INITIALISING
        np.testing.assert_allclose(published_K(harness, s), nominal_K(640, 360), rtol=1e-9)
        assert harness.spin_until(lambda: _diag_value(harness.diagnostics, "resets") == 1, 5.0)
        assert not (state_dir / ZOOM_MODEL_FILE).exists()
    finally:
        output = stop(proc)
        harness.close()
    assert "restored calibration state" in output and "swapped camera" in output, output
    assert "1280x720" in output and "640x360" in output, output
