"""`ptz-selfcal launch` parameter preparation: the tracker shares the calibrator's state_dir."""

from __future__ import annotations

import yaml

from ptz_selfcal.tools.launch import namespaced_params_file


def _prepared(tmp_path, data):
    return yaml.safe_load(namespaced_params_file(data, str(tmp_path)).read_text())


def test_tracker_without_state_dir_gets_the_calibrators(tmp_path):
    out = _prepared(
        tmp_path,
        {
            "calibrator": {"ros__parameters": {"state_dir": "/var/lib/cam1"}},
            "homography_tracker": {"ros__parameters": {"diagnostics_period": 0.25}},
        },
    )
    assert out["/**/homography_tracker"]["ros__parameters"] == {
        "diagnostics_period": 0.25,
        "state_dir": "/var/lib/cam1",
    }
    assert out["/**/calibrator"]["ros__parameters"] == {"state_dir": "/var/lib/cam1"}
    # no tracker section at all, under a namespace
    out = _prepared(tmp_path, {"/cam2/calibrator": {"ros__parameters": {"state_dir": "/s"}}})
    assert out["/cam2/homography_tracker"]["ros__parameters"] == {"state_dir": "/s"}


def test_tracker_state_dir_of_its_own_or_no_calibrator_state_dir_is_left_alone(tmp_path):
    own = {
        "calibrator": {"ros__parameters": {"state_dir": "/a"}},
        "homography_tracker": {"ros__parameters": {"state_dir": ""}},
    }
    assert _prepared(tmp_path, own)["/**/homography_tracker"]["ros__parameters"] == {"state_dir": ""}
    none = {"calibrator": {"ros__parameters": {"state_dir": ""}}}
    assert set(_prepared(tmp_path, none)) == {"/**/calibrator"}


def test_no_shared_state_dir_when_the_calibrator_estimates_distortion(tmp_path):
    # the lens correction is not persisted: a tracker keeping its reference would leave the restored
    # calibration without corrected homographies, so the tracker starts a new map after a restart
    data = {"calibrator": {"ros__parameters": {"state_dir": "/a", "estimate_distortion": True}}}
    assert set(_prepared(tmp_path, data)) == {"/**/calibrator"}


def test_a_fixed_lens_estimating_distortion_shares_its_state_dir(tmp_path):
    # focal_model constant keeps its one distortion coefficient in the saved calibration state and
    # needs no corrected homographies: a restarted tracker may keep its map (and the reference)
    params = {"state_dir": "/a", "estimate_distortion": True, "focal_model": "constant"}
    out = _prepared(tmp_path, {"calibrator": {"ros__parameters": params}})
    assert out["/**/homography_tracker"]["ros__parameters"] == {"state_dir": "/a"}
