"""Bad input catalogue through the real graph and the command line.

What tests/node/test_frame_ingest.py (lying step/encoding, unsupported encoding, corrupt JPEG, a PNG that
is not one, a zero-sized raw image, NaN/duplicate/out-of-order encoder samples, absurd working_width) and
tests/node/test_run.py (a corrupt image, a NaN encoder and swapped stamps in a bag, a bag without image
topics for `run`, a directory that is no bag) already cover is not repeated. Here, with all three nodes
running: huge images (a real 16k x 16k raw image, a lying 16k header, a 16k JPEG: refused before any
decoding), compressed data that is no image, JointStates with missing joints, name/position mismatch,
no known joint, +-inf and far-future stamps, duplicate, out-of-order and far-future image stamps. Every
one is counted in /diagnostics, logged once, the graph keeps running and every good frame gets exactly
one CameraInfo. And for the command line: a truncated bag given to `run` and `eval` (decided: a clean
one-line failure, nothing started and no output bag; rosbags cannot open an mcap without its footer nor a
truncated sqlite3 file), a bag without the expected topics given to `eval`, parameter files with wrong
types or absurd values for every node (direct and through `launch`).
"""

from __future__ import annotations

import math
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import reliability_harness as rh
from conftest import REPO, cli_command, node_command

from ptz_selfcal.tools.bagio import BagReader, BagWriter

ROS_DOMAIN_ID = 170
W, H = 640, 360


def test_graph_survives_the_catalogue_and_calibrates_every_good_frame(ros_env, start_process):
    procs = rh.start_graph(start_process, ros_env)
    feeder = rh.Feeder("bad_input_feeder")
    try:
        feeder.wait_connected()
        fw = rh.f_wide_for(W)
        views = rh.sweep(60, W, fw)
        images = [rh.render(v, W, H) for v in views]
        good: list[int] = []  # stamps that must get exactly one CameraInfo
        refused: list[int] = []  # stamps that must get none
        k = 0

        def t_of(i: int) -> float:
            return rh.T0 + i / 30.0

        def send_good(i: int, encoders: bool = True) -> int:
            if encoders:
                feeder.send_encoders(t_of(i), (views[i].pan, views[i].tilt, views[i].zoom))
            ns = feeder.send_image(t_of(i), images[i])
            good.append(ns)
            assert feeder.wait_info(ns), f"good frame {i} got no CameraInfo"
            return ns

        jpeg16k = cv2.imencode(".jpg", np.zeros((16384, 16384), np.uint8))[1].tobytes()
        png = cv2.imencode(".png", images[0])[1].tobytes()
        for k in range(60):
            t_bad = t_of(k) + 0.011  # bad inputs get stamps of their own between the good frames
            if k == 5:
                refused.append(feeder.send_image(t_bad, np.zeros((16384, 16384), np.uint8)))  # 256 MB
            elif k == 7:  # a lying header: 16k x 16k claimed, 1 kB of data
                refused.append(
                    feeder.send_image(t_bad, images[0], data=bytes(1024), width=16384, height=16384)
                )
            elif k == 9:
                refused.append(feeder.send_compressed(t_bad, jpeg16k, "jpeg"))  # decompression bomb
            elif k == 11:
                refused.append(feeder.send_compressed(t_bad, b"", "jpeg"))
            elif k == 13:
                refused.append(feeder.send_compressed(t_bad, bytes(range(256)) * 8, "jpeg"))
            elif k == 15:
                refused.append(feeder.send_compressed(t_bad, png[:40], "png"))  # header only
            elif k == 17:
                refused.append(feeder.send_compressed(t_bad, png, "16UC1; compressedDepth"))
            elif k == 19:
                refused.append(feeder.send_image(t_bad, images[0], width=0, height=H, step=0, data=b""))
            elif k == 21:
                feeder.send_encoders(t_of(k), (views[k].pan, views[k].tilt), names=("pan", "tilt"))
                feeder.send_encoders(t_of(k) + 0.002, (views[k].zoom,), names=("zoom",))
            elif k == 23:
                feeder.send_encoders(t_of(k) - 0.002, (1.0, 2.0), names=("pan", "tilt", "zoom"))  # mismatch
                feeder.send_encoders(t_of(k) - 0.001, (1.0, 2.0), names=("a", "b"))  # no known joint
            elif k == 25:
                feeder.send_encoders(t_of(k) - 0.003, (math.inf, -math.inf, math.nan))
            elif k == 27:
                feeder.send_encoders(t_of(k) + 1e6, (0.0, 0.0, 0.0))  # 11 days ahead: rejected
            if k == 21:
                send_good(k, encoders=False)  # its encoders came in two partial messages
            else:
                send_good(k)
            if k == 31:  # the same stamp again: refused as a duplicate, the first one keeps its CameraInfo
                feeder.send_image(t_of(k), images[k])
            elif k == 33:  # an image older than the previous one (not a duplicate): calibrated anyway
                feeder.send_encoders(t_of(k) - 0.005, (views[k].pan, views[k].tilt, views[k].zoom))
                ns = feeder.send_image(t_of(k) - 0.005, images[k])
                good.append(ns)
                assert feeder.wait_info(ns), "the out-of-order image got no CameraInfo"
            elif k == 35:  # an image 10 years in the future: calibrated (encoders invalid), no lasting harm
                ns = feeder.send_image(t_of(k) + 3.15e8, images[k])
                good.append(ns)
                assert feeder.wait_info(ns, 20.0), "the far-future image got no CameraInfo"
        feeder.spin(3.0, lambda: all(ns in feeder.infos for ns in good))
        # exactly one CameraInfo per good image, none for a refused one
        assert sorted(feeder.infos) == sorted(good), (len(feeder.infos), len(good))
        assert all(len(feeder.infos[ns]) == 1 for ns in good)
        assert not set(refused) & set(feeder.infos)
        # the good frame with encoders in two partial messages and those after the wild stamps: valid
        for i in (21, 36, 40, 59):
            assert feeder.frames[rh.t_ns(t_of(i))].encoders.valid, i
        far = feeder.frames[rh.t_ns(t_of(35) + 3.15e8)]
        assert not far.encoders.valid
        # calibration goes on: the last frames are calibrated and accurate
        last = [rh.t_ns(t_of(i)) for i in range(50, 60)]
        statuses = {rh.STATUS_NAMES[feeder.frames[ns].status] for ns in last}
        assert statuses <= rh.CALIBRATED, statuses
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
        assert int(feeder.diagnostics["homography_tracker"]["frames_out"]) == len(good)
        for name, proc in procs.items():
            assert proc.alive(), f"{name} died:\n{proc.output()[-3000:]}"
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
def truncated_copy(source: Path, out: Path, storage: str) -> Path:
    """A copy of the bag (in the given storage) with its file cut in the middle."""
    whole = out.with_name(out.name + "_whole")
    with BagReader(source) as reader, BagWriter(whole, storage=storage) as writer:
        for msg in reader.messages():
            writer.add_topic(msg.topic, msg.msgtype)
            writer.write_raw(msg.topic, msg.timestamp_ns, msg.raw)
    out.mkdir()
    shutil.copy(whole / "metadata.yaml", out / "metadata.yaml")
    (data,) = [p for p in whole.iterdir() if p.suffix in (".mcap", ".db3")]
    raw = data.read_bytes()
    (out / data.name).write_bytes(raw[: len(raw) // 2])
    return out


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_truncated_bag_is_a_clean_one_line_failure_for_run_and_eval(ros_env, tmp_path, storage):
    bag = truncated_copy(REPO / "bags/ci_short", tmp_path / "truncated", storage)
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
]


def params_file(tmp_path: Path, node: str, name: str, value: object) -> Path:
    path = tmp_path / f"{node}_{name.replace('.', '_')}.yaml"
    text = value if isinstance(value, str) else repr(value)
    path.write_text(f"{node}:\n  ros__parameters:\n    {name}: {text}\n")
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


@pytest.mark.parametrize("case", [BAD_PARAMS[0], BAD_PARAMS[4], BAD_PARAMS[6]], ids=lambda c: c[0])
def test_bad_parameter_value_stops_launch_with_the_node_message(ros_env, start_process, tmp_path, case):
    node, name, value, message = case
    path = params_file(tmp_path, node, name, value)
    proc = start_process(cli_command("launch", "--params", str(path)), ros_env, "launch")
    assert proc.wait(60.0) == 2, proc.output()
    out = proc.output()
    assert f"{node} exited with status 2 at start-up" in out and message in out, out
    assert out.strip().splitlines()[-1].startswith("ptz-selfcal launch: error:"), out
