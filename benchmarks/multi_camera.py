"""Issue 19 "Several cameras per machine": N suites in their own namespaces on this machine, each fed live
by its own player process, with the shipped parameters (queue_policy latest, depth 50; the machine-wide
solve slots). Each camera is one `benchmarks/live_latency.py --sync` process: it starts its suite
(/camK, the same launch machinery as `ptz-selfcal launch`), plays a synth bag at its frame rate once all
N are up, and measures image -> CameraInfo per image. A camera passes when every image it sent got its
CameraInfo, none was shed anywhere, and its p95 latency is at most 80 ms; N passes when every camera does.
Printed per N: each camera's calibrated share, shed counts and p50/p95, the CPU of the nodes and of the
players per frame, and the load average at the start. The largest N that passes is reported per size,
trying N = 1, 2, ... until one fails (or --max-n).

    ros2_ws/venv/bin/python benchmarks/multi_camera.py [--sizes 1280x720,1920x1080] [--fps 25] [--max-n 6]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PANORAMA = ROOT / "bags" / "source" / "examplepano.jpg"
P95_TARGET_MS = 80.0
TARGETS = {(1280, 720): 4, (1920, 1080): 2}  # the N targets


def render(work: Path, size: tuple[int, int], fps: float, frames: int, seed: int) -> Path:
    bag = work / f"synth_{size[0]}x{size[1]}_{seed}"
    cmd = [
        sys.executable, "-m", "ptz_selfcal.tools.cli", "synth", str(PANORAMA), str(bag), "--quiet",
        "--width", str(size[0]), "--height", str(size[1]), "--fps", str(fps), "--frames", str(frames),
        "--seed", str(seed),
    ]  # fmt: skip
    subprocess.run(cmd, check=True)
    return bag


def run_n(bags: list[Path], work: Path, domain: int) -> list[dict]:
    """N cameras at once (one bag each); their live_latency summaries."""
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain)}
    procs = []
    for k, bag in enumerate(bags):
        out = work / f"cam{k}.json"
        cmd = [
            sys.executable, str(ROOT / "benchmarks" / "live_latency.py"), "--bag", str(bag), "--policies",
            "latest", "--depth", "50", "--no-write", "--namespace", f"/cam{k}", "--sync", "--json", str(out),
        ]  # fmt: skip
        procs.append(
            (subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True), out)
        )
    try:
        for proc, _ in procs:  # every suite up before any camera plays
            for line in proc.stdout:
                if line.strip() == "READY":
                    break
            else:
                raise SystemExit(f"a camera's suite did not come up (exit {proc.wait()})")
        for proc, _ in procs:
            proc.stdin.write("go\n")
            proc.stdin.flush()
        for proc, _ in procs:
            proc.stdout.read()
            if proc.wait(timeout=600) != 0:
                raise SystemExit(f"a camera's run failed (exit {proc.returncode})")
        return [json.loads(out.read_text()) for _, out in procs]
    finally:
        for proc, _ in procs:
            if proc.poll() is None:
                proc.kill()


def passes(camera: dict) -> bool:
    shed = camera["shed_before_ingest"] + camera["shed_by_ingest"] + camera["shed_by_tracker"]
    complete = camera["calibrated"] == camera["published"] and shed == 0
    return complete and camera["p95_ms"] <= P95_TARGET_MS


def describe(n: int, cameras: list[dict], load: float) -> list[str]:
    frames = sum(c["published"] for c in cameras)
    nodes = 1e3 * sum(c["node_cpu_s"] for c in cameras) / max(1, frames)
    players = 1e3 * sum(c["player_cpu_s"] for c in cameras) / max(1, frames)
    verdict = "PASS" if all(passes(c) for c in cameras) else "fail"
    lines = [
        f"  N = {n}: {verdict}; load average {load:.2f} at start; CPU per frame: nodes {nodes:.1f} ms, "
        f"players {players:.1f} ms (their whole process, loading the bag included)"
    ]
    for k, c in enumerate(cameras):
        shed = (c["shed_before_ingest"], c["shed_by_ingest"], c["shed_by_tracker"])
        lines.append(
            f"    /cam{k}: calibrated {c['calibrated']}/{c['published']}, shed before ingest / by ingest / "
            f"by the tracker {shed[0]} / {shed[1]} / {shed[2]}, latency p50 {c['p50_ms']:.1f} ms p95 "
            f"{c['p95_ms']:.1f} ms"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="1280x720,1920x1080")
    parser.add_argument("--fps", type=float, default=25.0)
    parser.add_argument("--frames", type=int, default=250)
    parser.add_argument("--max-n", type=int, default=6)
    parser.add_argument("--domain", type=int, default=212)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "multi_camera.txt")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    given = " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        f"# ros2_ws/venv/bin/python benchmarks/multi_camera.py {given}",
        f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} CPUs; JPEG synth bags of "
        f"{args.frames} frames at {args.fps:g} frames/s, one seed per camera; pass: every image calibrated, "
        f"none shed, p95 <= {P95_TARGET_MS:g} ms on every camera",
    ]
    print("\n".join(lines), flush=True)
    with tempfile.TemporaryDirectory(prefix="multi_camera_") as tmp:
        work = Path(tmp)
        for text in args.sizes.split(","):
            size = tuple(int(v) for v in text.split("x"))
            bags: list[Path] = []
            largest = 0
            lines.append(f"{size[0]}x{size[1]} JPEG at {args.fps:g} frames/s")
            for n in range(1, args.max_n + 1):
                while len(bags) < n:
                    bags.append(render(work, size, args.fps, args.frames, seed=len(bags)))
                trial = work / f"{size[0]}_{n}"
                trial.mkdir()
                load = os.getloadavg()[0]
                cameras = run_n(bags[:n], trial, args.domain)
                lines += describe(n, cameras, load)
                print("\n".join(lines[-(n + 1) :]), flush=True)
                if not all(passes(c) for c in cameras):
                    break
                largest = n
            target = TARGETS.get(size)
            verdict = (
                ""
                if target is None
                else f" (target >= {target}: {'met' if largest >= target else 'not met'})"
            )
            lines.append(f"  largest N: {largest}{verdict}")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    if not args.no_write:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
