"""Tracking loss through the real graph (three node processes over DDS, rendered PTZ views with exact
ground truth): black frames, heavy blur, a scene cut and a fast 90 degree preset move at full zoom, and
a sharp preset recall panning 9 deg/frame while zooming 1x -> 2.5x over a repetitive facade and back.

CameraInfo keeps coming for every frame (from the zoom model while lost), tracking relocalises when the
view comes back, and the calibration after recovery is as good as before (median focal error on the same
views within 10 % of its value before: the tracker tracks views it has seen against the keyframes it made
then, so the calibration does not drift pass after pass).
"""

from __future__ import annotations

import pytest
import reliability_harness as rh

from ptz_selfcal.status import CALIBRATED, LOSS_STATUSES, CalibrationStatus

ROS_DOMAIN_ID = 175
W, H = 640, 360


# First in the module: its graph runs before the shared one of loss_results starts (6 node processes
# at once on 2 cores under load delayed a first CameraInfo past the lock-step timeout).
def test_fast_zooming_preset_recall_does_not_corrupt_the_calibration(ros_env, start_process, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "176")
    env = {**ros_env, "ROS_DOMAIN_ID": "176"}
    procs = rh.start_graph(start_process, env)
    feeder = rh.Feeder("zoom_preset_feeder")
    try:
        feeder.wait_connected()
        r = rh.zoom_preset_scenario(feeder, W, H)
        assert all(p.alive() for p in procs.values())
        # while moving: K from the zoom model or a good homography, never a wildly wrong one
        assert max(r["moving_errors"]) < 0.05, [round(e, 3) for e in r["moving_errors"]]
        assert set(r["after_statuses"][-16:]) <= CALIBRATED, r["after_statuses"]
        assert r["after"] <= 1.1 * r["before"], (r["before"], r["after"])
    finally:
        feeder.close()


@pytest.fixture(scope="module")
def loss_results(request):
    """One run of the whole scenario, shared by the assertions below (about 40 s)."""
    import os
    import tempfile
    from pathlib import Path

    from conftest import NodeProcess

    env = dict(os.environ)
    env.update(
        ROS_DOMAIN_ID=str(ROS_DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1"
    )
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE")}
    os.environ.update(ROS_DOMAIN_ID=env["ROS_DOMAIN_ID"], ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    tmp = Path(tempfile.mkdtemp(prefix="ptz_reliability_loss_"))
    procs: list[NodeProcess] = []

    def start(cmd, environment, name):
        proc = NodeProcess(cmd, environment, tmp, name)
        procs.append(proc)
        return proc

    graph = rh.start_graph(start, env)
    feeder = rh.Feeder("loss_feeder")
    try:
        feeder.wait_connected()
        disturbances = ("black", "blur", "scene_cut", "preset_90deg", "none")  # none: the control
        results = rh.tracking_loss_scenario(feeder, W, H, disturbances=disturbances)
        feeder.spin(0.6)
        results["_diagnostics"] = dict(feeder.diagnostics)
        results["_infos"] = {ns: len(v) for ns, v in feeder.infos.items()}
        results["_alive"] = {name: p.alive() for name, p in graph.items()}
        yield results
    finally:
        feeder.close()
        for proc in procs:
            proc.stop()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def test_camera_info_for_every_frame_and_nodes_alive(loss_results):
    stamps = loss_results["_log"]["stamps"]
    infos = loss_results["_infos"]
    assert sorted(infos) == sorted(stamps)
    assert all(count == 1 for count in infos.values())
    assert all(loss_results["_alive"].values()), loss_results["_alive"]
    calibrator = loss_results["_diagnostics"]["calibrator"]
    assert int(calibrator["camera_info_out"]) == len(stamps)
    assert int(calibrator[f"status_{CalibrationStatus.PREDICTED_FROM_ZOOM}"]) > 0


@pytest.mark.parametrize("disturbance", ["black", "blur", "scene_cut"])
def test_lost_view_predicted_from_zoom_then_relocalised_uncorrupted(loss_results, disturbance):
    r = loss_results[disturbance]
    # while the view is gone the K comes from the zoom model (learned over the warm-up's zoom range)
    assert set(r["statuses"]) <= LOSS_STATUSES, r["statuses"]
    assert CalibrationStatus.PREDICTED_FROM_ZOOM in r["statuses"]
    assert max(r["errors"]) < 0.05, r["errors"]
    # relocalised within the first frames of the returning view, and the calibration is not corrupted
    assert r["recovery_frames"] is not None and r["recovery_frames"] <= 3, r["after_statuses"]
    assert r["after"] <= 1.1 * r["before"], (r["before"], r["after"])


def test_preset_move_predicted_from_zoom_then_relocalised_uncorrupted(loss_results):
    r = loss_results["preset_90deg"]
    # motion-blurred moves and the unseen preset view: no homography, K from the zoom model
    assert set(r["statuses"]) <= LOSS_STATUSES | CALIBRATED, r["statuses"]
    assert CalibrationStatus.PREDICTED_FROM_ZOOM in r["statuses"]
    assert max(r["errors"]) < 0.05, r["errors"]
    assert r["recovery_frames"] is not None and r["recovery_frames"] <= 3, r["after_statuses"]
    assert r["after"] <= 1.1 * r["before"], (r["before"], r["after"])


def test_undisturbed_pass_over_the_same_views_does_not_drift(loss_results):
    """The control: the same views once more with nothing in between. The tracker tracks them against
    the keyframes it made on the first pass (revisits), so the calibrator's keyframe set and the
    frames' calibration stay as they were (issue 7: they drifted pass after pass before)."""
    r = loss_results["none"]
    assert r["frames"] == 0 and r["recovery_frames"] == 0, r["after_statuses"]
    assert set(r["after_statuses"]) <= CALIBRATED, r["after_statuses"]
    assert r["after"] <= 1.1 * r["before"], (r["before"], r["after"])
