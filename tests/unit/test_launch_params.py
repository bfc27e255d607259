"""`ptz-selfcal launch` parameter preparation: the tracker shares the calibrator's state_dir."""

from __future__ import annotations

import pytest
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


def test_default_yaml_lists_every_node_parameter_with_its_default_and_a_description():
    """config/ptz_selfcal.yaml is the user's reference: every parameter a node declares is there (the
    tracker's state_dir only as a comment: `launch` fills it in) with the node's default, and each has
    a description and, for a number, a check that refuses absurd values."""
    from ptz_selfcal.nodes import calibrator, frame_ingest, homography_tracker
    from ptz_selfcal.tools.launch import default_params_file

    path = default_params_file()
    data = yaml.safe_load(path.read_text())
    commented = {("homography_tracker", "state_dir")}
    for key, params in (
        ("frame_ingest", frame_ingest.PARAMS),
        ("homography_tracker", homography_tracker.PARAMS),
        ("calibrator", calibrator.PARAMS),
    ):
        listed = data[key]["ros__parameters"]
        for p in params:
            assert p.description.strip(), (key, p.name)
            if isinstance(p.default, int | float) and not isinstance(p.default, bool):
                assert p.check is not None, (key, p.name)
            if (key, p.name) in commented:
                assert p.name not in listed and f"# {p.name}:" in path.read_text()
                continue
            assert listed.get(p.name) == p.default, (key, p.name, listed.get(p.name), p.default)
        assert set(listed) <= {p.name for p in params}, (key, set(listed) - {p.name for p in params})
    for p in homography_tracker.tracker_params():  # every TrackerConfig field, revisit_* included
        assert p.description.strip() and p.check is not None, p.name


def test_tracker_string_parameters_accept_only_their_choices():
    """An unknown klt_source ran silently as "warped"; now the node refuses it (and the core too)."""
    from ptz_selfcal.frontend.tracker_config import TRACKER_CHOICES, TrackerConfig
    from ptz_selfcal.nodes import homography_tracker

    checks = {p.name: p.check for p in homography_tracker.tracker_params()}
    for field, allowed in TRACKER_CHOICES.items():
        assert all(checks[f"tracker.{field}"](v) is None for v in allowed)
        assert "must be one of" in checks[f"tracker.{field}"]("bogus")
        with pytest.raises(ValueError, match=field):
            TrackerConfig(**{field: "bogus"})
