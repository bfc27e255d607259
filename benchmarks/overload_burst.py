"""The wall-clock figures of tests/reliability/test_overload.py, which CI no longer asserts: the scenario of
the test (1920x1080 JPEG at 60 frames/s for 12 s, then a 300 frames/s burst for 3 s, latest-wins queues,
working width 640) run --repeats times, each run printing the publisher's achieved rate, the share of
frames calibrated and the latency (image sent -> its CameraInfo) p50/p95/max of both phases, and the
shed-frame estimate of frame_ingest against the frames really shed before it. Each run is repeated for
frame_ingest shed_before_decoding true and false (false: the tracker's latest-wins queue sheds decoded
frames), interleaved, and prints where frames were shed (before ingest,
by ingest undecoded, by the tracker) and the CPU time of frame_ingest and the tracker per frame sent,
with the load average.

    ros2_ws/venv/bin/python benchmarks/overload_burst.py [--repeats 5] [--seconds 12] [--only-shed|--no-shed]
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from reliability import Domain, graph, pct, rh


def phase_line(name: str, r: dict, shed: int, estimate: int) -> str:
    lat = r["latencies"]
    return (
        f"  {name:>10}: sent {r['sent']:4d} at {r['rate']:6.1f}/s, calibrated {r['calibrated']:4d} "
        f"({100 * r['calibrated'] / max(1, r['sent']):4.1f} %), latency p50 {pct(lat, 50)} ms p95 "
        f"{pct(lat, 95)} ms max {pct(lat, 100)} ms; shed before ingest {shed}, estimated {estimate}"
    )


def counters(feeder: rh.Feeder) -> tuple[int, int]:
    ingest = feeder.diagnostics["frame_ingest"]
    return int(ingest["frames_in"]), int(ingest.get("input_frames_missing_estimate", 0))


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (/proc/PID/stat), seconds."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def where_shed(feeder: rh.Feeder, pids: dict[str, int], cpu0: dict[str, float], sent: int) -> str:
    ingest, tracker = feeder.diagnostics["frame_ingest"], feeder.diagnostics["homography_tracker"]
    cpu = {
        n: 1e3 * (cpu_seconds(pids[n]) - cpu0[n]) / max(1, sent)
        for n in ("frame_ingest", "homography_tracker")
    }
    return (
        f"    shed by frame_ingest undecoded {ingest.get('skipped_tracker_behind', 0)}, by the tracker "
        f"{tracker.get('frames_dropped', 0)} (both phases); CPU ms per frame sent: frame_ingest "
        f"{cpu['frame_ingest']:.2f}, tracker {cpu['homography_tracker']:.2f}; load average "
        f"{os.getloadavg()[0]:.1f}"
    )


def run_once(domain: Domain, work: Path, seconds: float, shed: bool) -> list[str]:
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    latest = ("queue_policy:=latest", "queue_depth:=1")
    ingest = (*latest, "sensor_reliability:=best_effort", f"shed_before_decoding:={str(shed).lower()}")
    with (
        domain() as env,
        graph(env, work, ingest=ingest, tracker=latest, working_width=640) as nodes,
    ):  # fmt: skip
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT)
        feeder = rh.Feeder("bench_overload_burst", sensor_qos=qos)
        try:
            feeder.wait_connected(compressed=True)
            pids = {n: p.pid for n, p in nodes.items()}
            cpu0 = {n: cpu_seconds(pid) for n, pid in pids.items()}
            r = rh.overload_scenario(feeder, pids, seconds)
            feeder.spin(1.0)
            taken, estimate = counters(feeder)
            lines = [phase_line("60 fps", r, r["sent"] - taken, estimate)]
            burst = rh.overload_scenario(feeder, pids, 3.0, fps=300.0, t0=r["last_stamp"] + 1.0 / 60.0)
            feeder.spin(1.0)
            taken_2, estimate_2 = counters(feeder)
            shed = burst["sent"] - (taken_2 - taken)
            lines.append(phase_line("300 fps", burst, shed, estimate_2 - estimate))
            lines.append(where_shed(feeder, pids, cpu0, r["sent"] + burst["sent"]))
            return lines
        finally:
            feeder.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--only-shed", action="store_true", help="only shed_before_decoding true")
    ap.add_argument("--no-shed", action="store_true", help="only shed_before_decoding false")
    args = ap.parse_args()
    values = [True] if args.only_shed else [False] if args.no_shed else [False, True]
    domain = Domain(first=200)
    with tempfile.TemporaryDirectory(prefix="overload_burst_") as tmp:
        for i in range(args.repeats):
            for value in values:
                print(f"run {i + 1} of {args.repeats}, shed_before_decoding {str(value).lower()}", flush=True)
                for line in run_once(domain, Path(tmp), args.seconds, value):
                    print(line, flush=True)


if __name__ == "__main__":
    main()
