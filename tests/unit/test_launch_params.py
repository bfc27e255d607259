"""What `ptz-selfcal launch` and the ROS launch file start: plan_suite, the one pure function both call
(names, namespace, parameters, remappings), and the tracker sharing the calibrator's state_dir."""

from __future__ import annotations

import importlib.util
import sys
import tempfile
import types
from pathlib import Path

import pytest
import yaml

from ptz_selfcal.tools.cli import CliError
from ptz_selfcal.tools.launch import (
    NODE_MODULES,
    SUITE_NODES,
    NodeSpec,
    Supervisor,
    plan_params_file,
    plan_suite,
)

LAUNCH_FILE = Path(__file__).resolve().parents[2] / "src" / "ptz_selfcal" / "launch" / "ptz_selfcal.launch.py"


def _params(data, namespace=None, **kwargs):
    """Each node's planned parameters but camera_name (every plan sets it; its own test checks it)."""
    plan = plan_suite(data, namespace, **kwargs)
    return {n.name: {k: v for k, v in n.parameters.items() if k != "camera_name"} for n in plan}


def test_tracker_without_state_dir_gets_the_calibrators():
    out = _params(
        {
            "calibrator": {"ros__parameters": {"state_dir": "/var/lib/cam1"}},
            "homography_tracker": {"ros__parameters": {"diagnostics_period": 0.25}},
        }
    )
    assert out["homography_tracker"] == {"diagnostics_period": 0.25, "state_dir": "/var/lib/cam1"}
    assert out["calibrator"] == {"state_dir": "/var/lib/cam1"}
    # no tracker section at all, a section for this namespace only
    data = {"/cam2/calibrator": {"ros__parameters": {"state_dir": "/s"}}}
    assert _params(data, "/cam2")["homography_tracker"] == {"state_dir": "/s"}
    assert "state_dir" not in _params(data, "/cam3")["homography_tracker"]


def test_tracker_state_dir_of_its_own_or_no_calibrator_state_dir_is_left_alone():
    own = {
        "calibrator": {"ros__parameters": {"state_dir": "/a"}},
        "homography_tracker": {"ros__parameters": {"state_dir": ""}},
    }
    assert _params(own)["homography_tracker"] == {"state_dir": ""}
    none = {"calibrator": {"ros__parameters": {"state_dir": ""}}}
    assert _params(none)["homography_tracker"] == {}


def test_no_shared_state_dir_when_the_calibrator_estimates_distortion():
    # the lens correction is not persisted: a tracker keeping its reference would leave the restored
    # calibration without corrected homographies, so the tracker starts a new map after a restart
    data = {"calibrator": {"ros__parameters": {"state_dir": "/a", "estimate_distortion": True}}}
    assert _params(data)["homography_tracker"] == {}


def test_a_fixed_lens_estimating_distortion_shares_its_state_dir():
    # focal_model constant keeps its one distortion coefficient in the saved calibration state and
    # needs no corrected homographies: a restarted tracker may keep its map (and the reference)
    params = {"state_dir": "/a", "estimate_distortion": True, "focal_model": "constant"}
    assert _params({"calibrator": {"ros__parameters": params}})["homography_tracker"] == {"state_dir": "/a"}


def test_plan_names_namespace_sections_camera_name_and_remaps():
    data = {
        "/**": {"ros__parameters": {"diagnostics_period": 2.0}},
        "frame_ingest": {"ros__parameters": {"joint_names": ["a_pan", "a_tilt", "a_zoom"]}},
        "homography_tracker": {"ros__parameters": {"tracker": {"max_features": 300}}},
        "/other/calibrator": {"ros__parameters": {"nominal_hfov_deg": 10.0}},
        "/*/calibrator": {"ros__parameters": {"diagnostics_period": 0.5}},
    }
    plan = plan_suite(data, "cam1/", ["image_raw:=camera/image"])
    assert [(n.name, n.module, n.namespace) for n in plan] == [
        (name, NODE_MODULES[name], "/cam1") for name in SUITE_NODES
    ]  # the live mosaic only when asked for
    assert all(n.remappings == (("image_raw", "camera/image"),) for n in plan)
    by_name = {n.name: n.parameters for n in plan}
    assert by_name["frame_ingest"] == {
        "diagnostics_period": 2.0,
        "joint_names": ["a_pan", "a_tilt", "a_zoom"],
        "camera_name": "cam1",
    }
    assert by_name["homography_tracker"] == {
        "diagnostics_period": 2.0,
        "tracker.max_features": 300,
        "camera_name": "cam1",
    }
    assert by_name["calibrator"] == {"diagnostics_period": 0.5, "camera_name": "cam1"}  # later wins
    # the default namespace is the camera's, /ptz; camera_name from the argument over the file
    default = plan_suite({"calibrator": {"ros__parameters": {"camera_name": "dome"}}}, None)
    assert {n.namespace for n in default} == {"/ptz"}
    assert {n.parameters["camera_name"] for n in default} == {"dome"}
    assert {n.parameters["camera_name"] for n in plan_suite({}, "/cam1", camera_name="axis")} == {"axis"}
    assert {n.parameters["camera_name"] for n in plan_suite({}, None)} == {"ptz"}  # the default namespace's
    # the shipped file's "" names nothing: each camera is its namespace's, so two never share a state
    shipped = {"/**": {"ros__parameters": {"camera_name": ""}}}
    assert {n.parameters["camera_name"] for n in plan_suite(shipped, "/cam2")} == {"cam2"}
    # a private namespace (run's) does not name the camera
    private = plan_suite({}, "/ptz_selfcal_run_7", name_from_namespace=False)
    assert {n.parameters["camera_name"] for n in private} == {"ptz"}
    for bad in ({"namespace": "/1cam"}, {"remaps": ["image_raw"]}):
        with pytest.raises(CliError):
            plan_suite({}, **bad)


def test_launch_persists_each_camera_under_ros_home_unless_told_otherwise():
    from ptz_selfcal.tools.launch import state_root

    assert state_root({"ROS_HOME": "/rh", "HOME": "/h"}) == "/rh/ptz_selfcal"
    assert state_root({"HOME": "/h"}) == "/h/.ros/ptz_selfcal"
    by_name = _params({}, "/cam1", state_root="/rh/ptz_selfcal")
    assert by_name["calibrator"]["state_dir"] == "/rh/ptz_selfcal/cam1"
    assert by_name["homography_tracker"]["state_dir"] == "/rh/ptz_selfcal/cam1"  # the map beside it
    assert _params({}, None, state_root="/rh")["calibrator"]["state_dir"] == "/rh/ptz"  # the default camera
    named = _params({}, "/cam1", camera_name="dome", state_root="/rh")
    assert named["calibrator"]["state_dir"] == "/rh/dome"
    own = {"calibrator": {"ros__parameters": {"state_dir": "/var/lib/cam1"}}}
    assert _params(own, "/cam1", state_root="/rh")["calibrator"]["state_dir"] == "/var/lib/cam1"
    assert "state_dir" not in _params({}, "/cam1")["calibrator"]  # run, eval, --no-persist: none


def test_cli_launch_gives_each_node_its_planned_place_and_parameters(tmp_path):
    """`ptz-selfcal launch`'s node commands carry the plan: name, namespace, remaps and a parameter file
    whose section for each node's fully qualified name holds exactly its planned parameters."""
    data = {"calibrator": {"ros__parameters": {"state_dir": "/s"}}}
    plan = plan_suite(data, "/cam1", ["joint_states:=/head/joints"])
    path = plan_params_file(plan, str(tmp_path))
    sections = yaml.safe_load(path.read_text())
    assert {k: v["ros__parameters"] for k, v in sections.items()} == {
        f"/cam1/{n.name}": n.parameters for n in plan
    }
    remaps = [f"{a}:={b}" for a, b in plan[0].remappings]
    supervisor = Supervisor([NodeSpec(n.name, n.module) for n in plan], path, "/cam1", remaps)
    cmd = supervisor.command(supervisor.children[1].spec)
    assert cmd[1:3] == ["-m", NODE_MODULES["homography_tracker"]]
    assert cmd[3:] == [
        "--ros-args", "-r", "__node:=homography_tracker", "-r", "__ns:=/cam1", "--params-file", str(path),
        "-r", "joint_states:=/head/joints",
    ]  # fmt: skip


def _load_launch_file(monkeypatch):
    """The ROS launch file, imported with stand-ins for launch and launch_ros (not installed here) that
    record what it builds."""

    class Recorded:
        def __init__(self, *args, **kwargs):
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Recorded):
        def perform(self, context):
            return context.launch_configurations[self.args[0]]

    fakes = {
        "launch": {"LaunchDescription": Recorded},
        "launch.actions": {
            "DeclareLaunchArgument": Recorded,
            "OpaqueFunction": Recorded,
            "RegisterEventHandler": Recorded,
            "Shutdown": Recorded,
        },
        "launch.event_handlers": {"OnProcessExit": Recorded},
        "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration},
        "launch_ros": {},
        "launch_ros.actions": {"Node": Recorded},
        "ament_index_python.packages": {"get_package_share_directory": lambda name: f"/share/{name}"},
    }
    for name, attrs in fakes.items():
        module = types.ModuleType(name)
        module.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, name, module)
    spec = importlib.util.spec_from_file_location("ptz_selfcal_launch_file", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ros_launch_file_starts_the_plan(monkeypatch, tmp_path):
    """Launch-file parity: the Node actions of ptz_selfcal.launch.py are plan_suite's nodes (executable,
    name, namespace, parameters, remappings), a configuration error ends the launch instead of a
    respawn, and no parameter file is rewritten."""
    params = tmp_path / "p.yaml"
    params.write_text(yaml.safe_dump({"frame_ingest": {"ros__parameters": {"working_width": 320}}}))
    module = _load_launch_file(monkeypatch)
    description = module.generate_launch_description()
    declared = {a.args[0]: a.kwargs.get("default_value") for a in description.args[0] if a.args}
    assert set(declared) == {"params_file", "namespace", "camera_name", "remappings", "persist", "mosaic"}
    assert declared["mosaic"] == "false"  # the live mosaic is off by default
    assert declared["persist"] == "true"
    assert declared["params_file"] == "/share/ptz_selfcal/config/ptz_selfcal.yaml"
    (opaque,) = [a for a in description.args[0] if "function" in a.kwargs]
    context = types.SimpleNamespace(
        launch_configurations={
            "params_file": str(params),
            "namespace": "/cam1",
            "camera_name": "",
            "remappings": "image_raw:=camera/image joint_states:=/head/joints",
            "persist": "true",
            "mosaic": "false",
        }
    )
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros_home"))

    def no_temporary_file(*args, **kwargs):
        raise AssertionError("the launch file wrote a temporary parameter file")

    monkeypatch.setattr(tempfile, "mkstemp", no_temporary_file)
    monkeypatch.setattr(tempfile, "NamedTemporaryFile", no_temporary_file)
    actions = opaque.kwargs["function"](context)
    nodes = [a.kwargs for a in actions if "executable" in a.kwargs]
    plan = plan_suite(
        {"frame_ingest": {"ros__parameters": {"working_width": 320}}},
        "/cam1",
        ["image_raw:=camera/image", "joint_states:=/head/joints"],
        state_root=str(tmp_path / "ros_home" / "ptz_selfcal"),
    )
    assert plan[2].parameters["state_dir"] == str(tmp_path / "ros_home" / "ptz_selfcal" / "cam1")
    assert [
        (n["executable"], n["name"], n["namespace"], n["parameters"], n["remappings"]) for n in nodes
    ] == [(p.name, p.name, p.namespace, [p.parameters], list(p.remappings)) for p in plan]
    assert all(n["package"] == "ptz_selfcal" for n in nodes)
    from ptz_selfcal.tools.launch import dds_profile_environment

    assert all(n["additional_env"] == dds_profile_environment() for n in nodes)  # the one Fast DDS profile
    context.launch_configurations["mosaic"] = "true"  # the optional live mosaic, after the suite
    with_mosaic = [a.kwargs for a in opaque.kwargs["function"](context) if "executable" in a.kwargs]
    assert [n["executable"] for n in with_mosaic] == [*(p.name for p in plan), "mosaic"]
    handlers = [a for a in actions if a.args and type(a.args[0]).__name__ == "Recorded"]
    assert len(handlers) == len(nodes)  # one exit handler per node: status 2 shuts the launch down
    on_exit = handlers[0].args[0].kwargs["on_exit"]
    node = types.SimpleNamespace(name="frame_ingest")
    (shutdown,) = on_exit(types.SimpleNamespace(returncode=2, action=node), context)
    assert "configuration error" in shutdown.kwargs["reason"]
    assert on_exit(types.SimpleNamespace(returncode=-9, action=node), context) == []  # respawned


def test_default_yaml_lists_every_node_parameter_with_its_default_and_a_description():
    """config/ptz_selfcal.yaml is the user's reference: every parameter a node declares is there (the
    tracker's state_dir only as a comment: `launch` fills it in) with the node's default, and each has
    a description and, for a number, a check that refuses absurd values."""
    from ptz_selfcal.nodes import calibrator, frame_ingest, homography_tracker, mosaic_node
    from ptz_selfcal.tools.launch import default_params_file

    path = default_params_file()
    data = yaml.safe_load(path.read_text())
    commented = {("homography_tracker", "state_dir")}
    for key, params in (
        ("frame_ingest", frame_ingest.PARAMS),
        ("homography_tracker", homography_tracker.PARAMS),
        ("calibrator", calibrator.PARAMS),
        ("mosaic", mosaic_node.PARAMS),
    ):
        listed = data[f"/**/{key}"]["ros__parameters"]
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
