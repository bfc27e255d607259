"""kill -9 of one node during `ptz-selfcal launch`: the supervisor restarts it, the calibrator resumes from
its saved state (state_dir) and zoom model, and no CameraInfo after the restart is worse than the
calibration before the kill (for longer than re-acquiring tracking takes). The state files are only ever
replaced atomically: a reader polling them throughout never sees a partial file.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import reliability_harness as rh
import yaml
from conftest import cli_command

from ptz_selfcal.status import CALIBRATED, CalibrationStatus
from ptz_selfcal.tools.launch import default_params_file, plan_suite

ROS_DOMAIN_ID = 185
VICTIMS = ("calibrator", "homography_tracker", "frame_ingest")
W, H = 640, 360


class StateWatcher(threading.Thread):
    """Reads the state files every few ms: each read must be a complete YAML mapping."""

    def __init__(self, state_dir: Path) -> None:
        super().__init__(daemon=True)
        self.state_dir = state_dir
        self.stop_event = threading.Event()
        self.reads = 0
        self.versions: set[tuple[str, int]] = set()  # (file, inode): every atomic replace is a new inode
        self.bad: list[str] = []

    def run(self) -> None:
        while not self.stop_event.is_set():
            for name in ("calibration_state.yaml", "zoom_model.yaml"):
                path = self.state_dir / name
                try:
                    with open(path) as handle:
                        inode = os.fstat(handle.fileno()).st_ino
                        text = handle.read()
                except FileNotFoundError:
                    continue
                self.reads += 1
                self.versions.add((name, inode))
                try:
                    data = yaml.safe_load(text)
                except yaml.YAMLError as exc:
                    self.bad.append(f"{name}: {exc}")
                    continue
                if not isinstance(data, dict):
                    self.bad.append(f"{name}: not a mapping ({len(text)} bytes)")
            time.sleep(0.003)


@pytest.mark.parametrize("victim", VICTIMS)
def test_kill_9_of_a_node_restarts_it_and_the_calibration_resumes(
    ros_env, start_process, tmp_path, monkeypatch, victim
):
    # A domain per case: the endpoints of the previous case's (killed) processes linger in the DDS graph
    # until their lease expires and would make the next case's connection checks pass too early.
    domain = str(ROS_DOMAIN_ID + VICTIMS.index(victim))
    monkeypatch.setenv("ROS_DOMAIN_ID", domain)
    ros_env = {**ros_env, "ROS_DOMAIN_ID": domain}
    state_dir = tmp_path / "state"
    # the shipped parameters; the test changes what it watches (state saved often, fast diagnostics), a
    # lossless image subscription for its lossless feeder and a small working image for speed
    params = tmp_path / "params.yaml"
    data = yaml.safe_load(default_params_file().read_text())
    overrides = {
        "frame_ingest": {"working_width": 320, "sensor_reliability": "reliable", "diagnostics_period": 0.25},
        "homography_tracker": {"diagnostics_period": 0.25},
        "calibrator": {"state_dir": str(state_dir), "save_period": 0.3, "diagnostics_period": 0.25},
    }
    for node, values in overrides.items():
        data[f"/**/{node}"]["ros__parameters"].update(values)
    params.write_text(yaml.safe_dump(data, sort_keys=False))
    launch = start_process(cli_command("launch", "--params", str(params)), ros_env, "launch")
    feeder = rh.Feeder("restart_feeder", homographies=False)
    watcher = StateWatcher(state_dir)
    watcher.start()
    try:
        feeder.wait_connected(60.0)
        r = rh.restart_scenario(feeder, launch.output, victim, W, H)
        worse, statuses = r["worse"], r["statuses"]
        print(
            f"{victim}: {r['lost']} frames lost in the restart, worse frames {worse}, statuses "
            f"{statuses[:8]}..., reconnected {r['reconnect_s']:.2f} s and recovered {r['recover_s']} s after "
            f"the kill, threshold {r['threshold']:.5f}"
        )
        # The dead node's endpoints leave the graph after launch's 2 s DDS lease (not Fast DDS's 20 s), the
        # restarted node's are there by then: once they are, no frame is lost. How long that takes depends
        # on the machine's load (printed; benchmarks/reliability.py measures it): not asserted here.
        assert r["lost"] == 0, r["lost"]
        out = launch.output()
        assert f"{victim} exited unexpectedly with status -9" in out, out
        if victim == "calibrator":
            assert f"restored calibration state from {state_dir}" in out, out
            assert "loaded zoom model from" in out, out
        # launch gives the tracker the calibrator's state_dir unless a zooming lens's distortion is
        # estimated (the lens correction's chains are not saved): then a restarted tracker starts a new map
        shared = "state_dir" in {n.name: n.parameters for n in plan_suite(data)}["homography_tracker"]
        if victim == "homography_tracker" and shared:  # the map it saved in the calibrator's state_dir
            assert f"restored the tracker map from {state_dir}" in out, out
        elif victim == "homography_tracker":
            assert "restored the tracker map" not in out and "state_dir (none" in out, out
        # No CameraInfo worse than before the kill, not even one frame. A restarted tracker reloads its
        # keyframe map (launch gives it the calibrator's state_dir) and relocalises with the same reference,
        # so the calibrator keeps its calibration. Where launch gives it no map (see above), the calibrator
        # restarts on a new one and publishes INITIALISING frames with K from the restored zoom model: a
        # model fitted to the keyframes, a little less exact than their calibration, so such a frame may be
        # worse only as far as its published sigma says (within 3 sigma).
        if victim == "homography_tracker" and not shared:
            worse = [i for i in worse if r["after_errors"][i] > 3.0 * r["after_sigmas"][i]]
        assert not worse, (worse, statuses, f"median focal error before {r['before']}, after {r['after']}")
        if victim == "homography_tracker":
            assert set(statuses) <= CALIBRATED | {CalibrationStatus.INITIALISING}, statuses
        elif victim == "calibrator" and "restored lens: its correction starts anew" in out:
            # saved before the lens selection had found the lens without distortion: the correction is not
            # saved, so the restored map's frames get the zoom model's K (as good: `worse` above) and say so
            assert "frames keep their homographies" not in out
            assert set(statuses) <= CALIBRATED | {CalibrationStatus.PREDICTED_FROM_ZOOM}, statuses
        else:
            assert set(statuses) <= CALIBRATED, statuses
        assert launch.alive()
    finally:
        watcher.stop_event.set()
        watcher.join(5.0)
        feeder.close()
    assert launch.stop(timeout=30.0) == 0, launch.output()
    # atomic replacement: every read was complete, files were really replaced, no temporary file is left
    assert watcher.reads > 50 and not watcher.bad, watcher.bad[:3]
    assert len({v for v in watcher.versions if v[0] == "calibration_state.yaml"}) >= 2
    # (a kill during a save leaves its temporary file: the restarted calibrator removes it at its start)
    leftovers = [p.name for p in state_dir.iterdir() if p.name.endswith(".tmp")]
    assert not leftovers, leftovers
    data = yaml.safe_load((state_dir / "calibration_state.yaml").read_text())
    assert data["calibrator"] is not None and np.isfinite(data["last_good"]["K"][0][0])
