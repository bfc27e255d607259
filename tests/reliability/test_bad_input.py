"""Bad input catalogue through the real graph and the command line.

What tests/node/test_frame_ingest.py (lying step/encoding, unsupported encoding, corrupt JPEG, a PNG that
is not one, a zero-sized raw image, NaN/duplicate/out-of-order encoder samples, absurd working_width) and
tests/node/test_run.py (a corrupt image, a NaN encoder and swapped stamps in a bag, a bag without image
topics for `run`, a directory that is no bag) already cover is not repeated. Here, with all three nodes
running: huge images (a real 16k x 16k raw image, refused from the header of the serialized message
without a copy of its pixels, a lying 16k header, a 16k JPEG: refused before any decoding), compressed
data that is no image, JointStates with missing joints, name/position mismatch,
no known joint, +-inf and far-future stamps, duplicate, out-of-order and far-future image stamps. Every
one is counted in /diagnostics, logged once, the graph keeps running and every good frame gets exactly
one CameraInfo. And for the command line: a bag file with nothing readable given to `run` and `eval` (a
clean one-line failure, nothing started and no output bag; a truncated bag is read up to its last
complete record instead, tests/bag/test_bag_recovery.py), a bag without the expected topics given to
`eval`, parameter files with wrong types or absurd values for every node (direct and through `launch`).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import reliability_harness as rh
from conftest import REPO, cli_command, node_command

from ptz_selfcal.status import CALIBRATED
from ptz_selfcal.tools.bagio import BagReader, BagWriter

ROS_DOMAIN_ID = 170
W, H = 640, 360


def test_graph_survives_the_catalogue_and_calibrates_every_good_frame(ros_env, start_process):
    procs = rh.start_graph(start_process, ros_env)
    feeder = rh.Feeder("bad_input_feeder")
    try:
        feeder.wait_connected()
        peak_before = rh.rss_mb(procs["frame_ingest"].pid, "VmHWM")
        views, good, refused = rh.bad_input_catalogue(feeder, W, H)

        def t_of(i: int) -> float:
            return rh.T0 + i / 30.0

        feeder.spin(3.0, lambda: all(ns in feeder.infos for ns in good))
        # exactly one CameraInfo per good image, none for a refused one
        assert sorted(feeder.infos) == sorted(good), (len(feeder.infos), len(good))
        twice = [(good.index(ns), ns, len(feeder.infos[ns])) for ns in good if len(feeder.infos[ns]) != 1]
        assert not twice, twice
        assert not set(refused) & set(feeder.infos)
        # the good frame with encoders in two partial messages and those after the wild stamps: valid
        for i in (21, 36, 40, 59):
            assert feeder.frames[rh.t_ns(t_of(i))].encoders.valid, i
        far = feeder.frames[rh.t_ns(t_of(35) + 3.15e8)]
        assert not far.encoders.valid
        # calibration goes on: the last frames are calibrated and accurate
        last = [rh.t_ns(t_of(i)) for i in range(50, 60)]
        statuses = {rh.status_name(feeder.frames[ns].status) for ns in last}
        assert statuses <= CALIBRATED, statuses
        errors = [rh.focal_error(feeder.infos[ns][0], views[50 + j]) for j, ns in enumerate(last)]
        assert max(errors) < 0.01, errors

        def counted() -> bool:
            return all(
                feeder.counter(node, key) == len(good)
                for node, key in (
                    ("calibrator", "camera_info_out"),
                    ("frame_ingest", "frames_out"),
                    ("homography_tracker", "frames_out"),
                )
            )

        assert feeder.spin(5.0, counted), feeder.diagnostics
        d = feeder.diagnostics["frame_ingest"]
        expected = {
            "skipped_too_large": 3,
            "skipped_zero_size": 2,
            "skipped_undecodable": 2,
            "skipped_unsupported_format": 1,
            "skipped_duplicate_stamp": 1,
            "image_stamp_out_of_order": 2,  # the older image, and the good frame after the future one
            "encoder_missing_joints": 2,
            "encoder_bad_message": 1,
            "encoder_no_known_joint": 1,
            "encoder_rejected_not_finite": 3,
            "encoder_rejected_future_stamp": 3,
        }
        found = {key: int(d.get(key, 0)) for key in expected}
        assert found == expected, d
        assert int(d["skipped_total"]) == len(refused) + 1
        assert int(d["frames_in"]) == len(good) + len(refused) + 1
        # nothing was lost on the way in: the estimate of missing input frames (from stamp gaps) must stay
        # small, also after one image with a stamp 10 years ahead (a jump, not 9.5e9 missing frames)
        assert int(d.get("input_frames_missing_estimate", 0)) < len(good), d
        assert int(feeder.diagnostics["homography_tracker"]["frames_out"]) == len(good)
        for name, proc in procs.items():
            assert proc.alive(), f"{name} died:\n{proc.output()[-3000:]}"
        # The 256 MiB image costs frame_ingest only the transport's copies (DDS reassembly, rmw's serialized
        # message, rclpy's bytes): it is refused from its header, read in place. Deserialised first, it
        # cost a fourth (measured +1022 MB; now +768 MB, benchmarks/reliability.py section 1).
        growth = rh.rss_mb(procs["frame_ingest"].pid, "VmHWM") - peak_before
        assert growth < 3.5 * 256, f"frame_ingest peak RSS grew by {growth:.0f} MB"
        log = procs["frame_ingest"].output()
        for kind in ("too_large", "zero_size", "undecodable", "unsupported_format", "duplicate_stamp"):
            assert log.count(f"frame skipped ({kind})") == 1, kind  # once per kind, then counted
        assert "exceeds max_image_pixels" in log
        assert "encoder_missing_joints: JointState without" in log
    finally:
        feeder.close()
    for name, proc in procs.items():
        assert proc.stop() == 0, name


# ---------------------------------------------------------------------------------------------------------
# command line: damaged bags
def unreadable_copy(source: Path, out: Path, storage: str) -> Path:
    """A copy of the bag (in the given storage) whose file holds no readable record: its metadata says
    it is a bag, its bytes are not one."""
    whole = out.with_name(out.name + "_whole")
    with BagReader(source) as reader, BagWriter(whole, storage=storage) as writer:
        for msg in reader.messages():
            writer.add_topic(msg.topic, msg.msgtype)
            writer.write_raw(msg.topic, msg.timestamp_ns, msg.raw)
    out.mkdir()
    shutil.copy(whole / "metadata.yaml", out / "metadata.yaml")
    (data,) = [p for p in whole.iterdir() if p.suffix in (".mcap", ".db3")]
    (out / data.name).write_bytes(bytes(range(256)) * 64)
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_unreadable_bag_is_a_clean_one_line_failure_for_run_and_eval(ros_env, tmp_path, storage):
    bag = unreadable_copy(REPO / "bags/ci_short", tmp_path / "unreadable", storage)
    for command, out_args in (
        ("run", ["--out", str(tmp_path / "out")]),
        ("eval", ["--out-dir", str(tmp_path / "eval"), "--no-plots"]),
    ):
        result = subprocess.run(
            cli_command(command, str(bag), *out_args), env=ros_env, capture_output=True, text=True, timeout=60
        )
        assert result.returncode == 2, (command, result.stderr)
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1, (command, result.stderr)
        assert lines[0].startswith(f"ptz-selfcal {command}: error: {bag}: cannot open bag"), lines[0]
        assert "Traceback" not in result.stderr and "[launch] started" not in result.stderr
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "eval" / "output_bag").exists()


def test_bag_without_the_expected_topics_is_a_clear_error_for_eval(ros_env, tmp_path):
    bag = tmp_path / "joints_only"
    with BagReader(REPO / "bags/ci_short") as reader, BagWriter(bag) as writer:
        for msg in reader.messages(["/ptz/joint_states"]):
            writer.add_topic(msg.topic, msg.msgtype)
            writer.write_raw(msg.topic, msg.timestamp_ns, msg.raw)
    result = subprocess.run(
        cli_command("eval", str(bag), "--out-dir", str(tmp_path / "eval"), "--no-plots"),
        env=ros_env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "no /ptz/image_raw or /ptz/image_raw/compressed topic" in lines[0], lines


# ---------------------------------------------------------------------------------------------------------
# parameter files with wrong types or absurd values: nodes and launch
BAD_PARAMS = [
    ("frame_ingest", "queue_policy", "fastest", "queue_policy must be one of"),
    ("frame_ingest", "max_image_pixels", -1, "max_image_pixels must be in"),
    ("frame_ingest", "encoder_max_gap", ".nan", "encoder_max_gap must be in"),
    ("homography_tracker", "queue_depth", 0, "queue_depth must be in"),
    ("homography_tracker", "tracker.max_features", -300, "tracker.max_features"),
    ("homography_tracker", "diagnostics_period", "often", "diagnostics_period"),
    ("calibrator", "nominal_hfov_deg", 500.0, "nominal_hfov_deg must be in"),
    ("calibrator", "max_keyframes", 2.5, "max_keyframes"),
    ("calibrator", "ba_principal_point", "wobbly", "ba_principal_point must be one of"),
    ("calibrator", "focal_model", "zoomy", "focal_model must be one of"),
    ("calibrator", "converged_max_sigma_f", 0.0, "converged_max_sigma_f must be in"),
]


def params_file(tmp_path: Path, node: str, name: str, value: object) -> Path:
    path = tmp_path / f"{node}_{name.replace('.', '_')}.yaml"
    text = value if isinstance(value, str) else repr(value)
    # the nodes run in the camera's namespace (/ptz by default): a file for one of them, wherever it runs
    path.write_text(f"/**/{node}:\n  ros__parameters:\n    {name}: {text}\n")
    return path


@pytest.mark.parametrize(("node", "name", "value", "message"), BAD_PARAMS)
def test_bad_parameter_value_stops_the_node_at_start_with_a_clear_error(
    ros_env, start_process, tmp_path, node, name, value, message
):
    path = params_file(tmp_path, node, name, value)
    proc = start_process(node_command(rh.NODE_MODULES[node], "--params-file", str(path)), ros_env, node)
    assert proc.wait(30.0) == 2, proc.output()
    out = proc.output()
    assert f"{node}: configuration error: parameter {name}" in out and message in out, out
    assert "Traceback" not in out


def test_contradicting_calibrator_parameters_stop_it_with_a_clear_error(ros_env, start_process, tmp_path):
    path = tmp_path / "fixed_lens_varying_pp.yaml"
    path.write_text(
        "/**/calibrator:\n  ros__parameters:\n    focal_model: constant\n    ba_principal_point: varying\n"
    )
    proc = start_process(
        node_command(rh.NODE_MODULES["calibrator"], "--params-file", str(path)), ros_env, "cal"
    )
    assert proc.wait(30.0) == 2, proc.output()
    out = proc.output()
    assert "calibrator: configuration error: parameter ba_principal_point varying contradicts" in out, out
    assert "Traceback" not in out


@pytest.mark.parametrize("case", [BAD_PARAMS[0], BAD_PARAMS[4], BAD_PARAMS[6]], ids=lambda c: c[0])
def test_bad_parameter_value_stops_launch_with_the_node_message(ros_env, start_process, tmp_path, case):
    node, name, value, message = case
    path = params_file(tmp_path, node, name, value)
    proc = start_process(cli_command("launch", "--params", str(path)), ros_env, "launch")
    assert proc.wait(60.0) == 2, proc.output()
    out = proc.output()
    assert f"{node} exited with status 2 at start-up" in out and message in out, out
    assert out.strip().splitlines()[-1].startswith("ptz-selfcal launch: error:"), out
