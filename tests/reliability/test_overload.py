"""Overload: 60 frames/s of 1920x1080 JPEG (what an IP camera sends) into the real graph on this 2-core
machine with the latest-wins policy (`queue_policy: latest` in frame_ingest and homography_tracker).

The graph sheds frames by policy instead of queueing them: every frame sent is calibrated once or
reported as dropped (tracker frames_dropped from sequence gaps; ingest frames_in below sent), nothing is
left queued once the input stops, CameraInfos come in the order of their images, every CameraInfo
belongs to a published image and comes once, and the resident memory of every node process stays
bounded. A second, short burst at a rate no 2-core machine decodes and tracks (1080p at 300 frames/s)
proves the shedding itself.

Only counts, orderings and bounds are asserted: the rates and latencies depend on what else the machine
runs; the test prints them, benchmarks/reliability.py measures them.
"""

from __future__ import annotations

import numpy as np
import reliability_harness as rh
from rclpy.qos import QoSProfile, ReliabilityPolicy

ROS_DOMAIN_ID = 178
SECONDS = 12.0


def _counters(feeder: rh.Feeder) -> dict[str, int]:
    d = feeder.diagnostics
    ingest, tracker = d["frame_ingest"], d["homography_tracker"]
    return {
        "ingest_in": int(ingest["frames_in"]),
        "ingest_out": int(ingest["frames_out"]),
        "tracker_in": int(tracker["frames_in"]),
        "tracker_dropped": int(tracker["frames_dropped"]),
        "missing_estimate": int(ingest.get("input_frames_missing_estimate", 0)),
        "camera_info_out": int(d["calibrator"]["camera_info_out"]),
    }


def _assert_accounted(r: dict, before: dict[str, int], after: dict[str, int]) -> dict[str, int]:
    """Every frame sent is calibrated once or reported as dropped (before ingest, by ingest, by tracker)."""
    delta = {key: after[key] - before.get(key, 0) for key in after}
    assert r["duplicates"] == 0 and r["unknown"] == 0
    assert delta["camera_info_out"] == r["calibrated"], (delta, r["calibrated"])
    dropped_before_ingest = r["sent"] - delta["ingest_in"]
    skipped_by_ingest = delta["ingest_in"] - delta["ingest_out"]
    assert dropped_before_ingest >= 0 and skipped_by_ingest >= 0, delta
    assert delta["tracker_in"] + delta["tracker_dropped"] <= delta["ingest_out"], delta
    reported = dropped_before_ingest + skipped_by_ingest + delta["tracker_dropped"]
    assert r["sent"] - r["calibrated"] == reported, (r["sent"], r["calibrated"], delta)
    return {"before_ingest": dropped_before_ingest, "tracker": delta["tracker_dropped"], **delta}


def _assert_in_order(feeder: rh.Feeder, r: dict, t0: float) -> None:
    """The CameraInfos of a scenario stamped from t0 arrived in the order their images were sent (a shed
    frame leaves a gap, never a reordering)."""
    first, last = rh.ns_of(rh.stamp_of(t0)), rh.ns_of(rh.stamp_of(r["last_stamp"]))
    arrived = sorted((t, ns) for ns, t in feeder.info_arrival.items() if first <= ns <= last)
    stamps = [ns for _, ns in arrived]
    assert len(stamps) == r["calibrated"] and stamps == sorted(stamps), "CameraInfos out of order"


def _latency_line(name: str, r: dict, dropped: dict[str, int]) -> str:
    lat = np.asarray(r["latencies"]) * 1e3
    return (
        f"{name}: sent {r['sent']} at {r['rate']:.1f}/s, calibrated {r['calibrated']}, latency p50 "
        f"{np.percentile(lat, 50):.0f} ms p95 {np.percentile(lat, 95):.0f} ms max {lat.max():.0f} ms; "
        f"shed before ingest {dropped['before_ingest']} (estimated {dropped['missing_estimate']}), "
        f"by the tracker {dropped['tracker']}; peak RSS "
        + ", ".join(f"{n} {max(v for _, v in s):.0f} MB" for n, s in r["rss"].items())
    )


def test_60fps_1080p_is_shed_by_policy_with_bounded_latency_and_memory(ros_env, start_process):
    latest = ("queue_policy:=latest", "queue_depth:=1")
    procs = rh.start_graph(
        start_process, ros_env, ingest=(*latest, "sensor_reliability:=best_effort"), tracker=latest,
        working_width=640,
    )  # fmt: skip
    camera_qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
    feeder = rh.Feeder("overload_feeder", sensor_qos=camera_qos)
    pids = {n: p.pid for n, p in procs.items()}
    try:
        feeder.wait_connected(compressed=True)
        r = rh.overload_scenario(feeder, pids, SECONDS)
        feeder.spin(1.0)
        counts = _counters(feeder)
        dropped = _assert_accounted(r, {}, counts)
        print(_latency_line("60 fps", r, dropped))  # for the log; benchmarks/reliability.py measures it
        assert r["calibrated"] > 0, r
        _assert_in_order(feeder, r, rh.T0)
        # memory bounded: no growth over the second half of the run
        for name, samples in r["rss"].items():
            half = [v for t, v in samples if t >= SECONDS / 2]
            first = [v for t, v in samples if t < SECONDS / 2]
            assert max(half) < max(first) * 1.1 + 20.0, (name, first, half)
        # the tracker's keyframe store is capped (max_keyframes, default 64) and reported
        tracker = feeder.diagnostics["homography_tracker"]
        assert 1 <= int(tracker["map_keyframes"]) <= 64, tracker
        # frame_ingest estimates the images shed before it from the gaps in their stamps, relative to the
        # median interval, which itself grows with the shedding: how far it undercounts depends on the load
        # (33 % of 469 shed with other jobs running, 69 % of 111 without), so only its bounds are asserted
        shed = dropped["before_ingest"]
        estimate = dropped["missing_estimate"]
        assert (shed <= 10 or estimate > 0) and estimate <= 1.5 * shed + 5, dropped

        # the burst: more than any 2-core machine decodes and tracks, so frames must be shed, and reported
        t_burst = r["last_stamp"] + 1.0 / 60.0
        burst = rh.overload_scenario(feeder, pids, 3.0, fps=300.0, t0=t_burst)
        feeder.spin(1.0)
        dropped = _assert_accounted(burst, counts, _counters(feeder))
        print(_latency_line("300 fps burst", burst, dropped))
        assert dropped["before_ingest"] + dropped["tracker"] > 0, dropped
        assert 0 < burst["calibrated"] < burst["sent"], burst["calibrated"]
        _assert_in_order(feeder, burst, t_burst)
        for name, proc in procs.items():
            assert proc.alive(), f"{name} died:\n{proc.output()[-3000:]}"
    finally:
        feeder.close()
