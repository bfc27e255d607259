"""A saved state of another lens at the same image size, end to end: `ptz-selfcal eval` of a bag with a
state_dir (real nodes over DDS), then of a bag of the same camera, then of one whose lens is longer at
every zoom encoder reading (a swapped lens, same 640x360 images). The same lens keeps its state; the
swapped one is detected from its frames' focal lengths against the saved zoom model, the calibrator
starts fresh with a warning, and the run calibrates the new lens as if it had started fresh."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
import yaml
from conftest import cli_command, make_synth_bag

from ptz_selfcal.nodes.conversions import MSG_TO_STATUS
from ptz_selfcal.persist.state_files import STATE_FILE, ZOOM_MODEL_FILE
from ptz_selfcal.status import CalibrationStatus
from ptz_selfcal.tools import evaluate
from ptz_selfcal.tools.launch import default_params_file

DOMAIN = 166
FRAMES, WIDTH, HEIGHT = 120, 640, 360
START_A, START_SAME, START_SWAPPED = "1767225600", "1767229200", "1767232800"  # three sessions, hours apart


def _eval(bag: Path, out: Path, params: Path) -> tuple[dict, str]:
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(DOMAIN))
    cmd = cli_command("eval", str(bag), "--out-dir", str(out), "--params", str(params), "--deterministic")
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads((out / "report.json").read_text()), proc.stdout + proc.stderr


def _converged_within(out: Path, tolerance: float) -> int:
    """The CONVERGED frames of a run, each within `tolerance` (relative) of the true focal length."""
    data = evaluate.read_output_bag(out / "output_bag")
    count = 0
    for stamp, fc in data.frame_calibration.items():
        if MSG_TO_STATUS[fc.status] != CalibrationStatus.CONVERGED:
            continue
        f, f_true = data.camera_info[stamp].k[0], data.gt_camera_info[stamp].k[0]
        assert abs(f / f_true - 1.0) < tolerance, (stamp, f, f_true)
        count += 1
    return count


@pytest.fixture
def params(tmp_path: Path) -> Path:
    """The shipped parameter file with a state_dir for the calibrator (as `launch` gives one)."""
    data = yaml.safe_load(default_params_file().read_text())
    data["/**/calibrator"]["ros__parameters"]["state_dir"] = str(tmp_path / "state")
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_swapped_lens_of_the_same_image_size_starts_fresh(tmp_path: Path, params: Path) -> None:
    state = tmp_path / "state"
    lens_a = make_synth_bag(tmp_path / "a", FRAMES, WIDTH, HEIGHT, "--seed", "1", "--start-time", START_A)
    report, log = _eval(lens_a, tmp_path / "eval_a", params)
    assert (state / STATE_FILE).exists() and (state / ZOOM_MODEL_FILE).exists(), log[-3000:]
    assert report["status_counts"].get("CONVERGED", 0) > 0, report["status_counts"]

    # the same lens, another session: restored, kept
    same = make_synth_bag(tmp_path / "same", FRAMES, WIDTH, HEIGHT, "--seed", "2", "--start-time", START_SAME)
    report, log = _eval(same, tmp_path / "eval_same", params)
    assert "restored calibration state" in log and "does not fit" not in log, log[-3000:]
    assert _converged_within(tmp_path / "eval_same", 0.01) > 0

    old_model = (state / ZOOM_MODEL_FILE).read_text()
    # a lens 28 % longer at every zoom (42 deg instead of synth's 54 deg at the wide end): starts fresh
    swapped = make_synth_bag(
        tmp_path / "swapped",
        FRAMES,
        WIDTH,
        HEIGHT,
        "--seed",
        "3",
        "--start-time",
        START_SWAPPED,
        "--hfov",
        "42",
    )
    report, log = _eval(swapped, tmp_path / "eval_swapped", params)
    assert "restored calibration state" in log, log[-3000:]
    assert "does not fit these images" in log and "swapped camera or lens" in log, log[-3000:]
    assert "removed the saved state" in log, log[-3000:]
    # from then on a fresh calibration of the new lens: what a run without any saved state gives
    late = report["metrics"]["focal_error"]["after_warmup"]
    assert late["count"] > 0 and late["median"] < 0.005, late
    assert _converged_within(tmp_path / "eval_swapped", 0.01) > 0
    # what is saved now is the new lens's: the old lens's zoom model is gone (the new one is written once
    # the fresh calibration has learned one, which depends on how late in the bag the swap was found)
    assert (state / STATE_FILE).exists()
    model = state / ZOOM_MODEL_FILE
    assert not model.exists() or model.read_text() != old_model
