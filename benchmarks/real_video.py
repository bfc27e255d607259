"""Issue 16 "Measure": the real-video nuisances, each alone and all together, with the shipped defaults.

    ros2_ws/venv/bin/python benchmarks/real_video.py [--panoramas examplepano,building] [--seeds 0,1]
        [--cases none,exposure,...] [--frames 150] [--size 960x540] [--work-dir /tmp/real_video]
        [--quick]

Every case is a `ptz-selfcal synth` bag (a sweep with zoom 1x -> 2.5x, pan +-30 deg at 25 frames/s)
with one nuisance of sim/nuisances.py switched on by its synth option (CASES below), or all of them,
beside the same bag without it ("none": same panorama, seed and motion). Each bag is run as a new user
would: `ptz-selfcal eval BAG --out-dir D --quiet --no-plots` (the real nodes, the shipped config), and
its report gives, after the first 10 % of frames: focal error median and p90, principal point error
median, pairwise rotation error median, the share of CONVERGED frames more than 1 % off, frames/s.
Bags and reports are cached in --work-dir under their case name (a cached report is reused: delete
it after a code change). Not yet here: the rolling-shutter targets' motion (30 deg/s pans, readout
estimation) and the OpenCV stitching reference row.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).with_name("ptz-selfcal")
SHARED = Path(os.environ.get("PTZ_SHARED_DATA", "/work/shared/data")) / "panoramas"
PANORAMAS = {"examplepano": ROOT / "bags" / "source" / "examplepano.jpg", "building": SHARED / "building.jpg"}
MOTION = ["--fps", "25", "--zoom-max", "2.5", "--pan-amplitude", "30", "--tilt-amplitude", "6"]
CASES: dict[str, list[str]] = {
    "none": [],
    "moving_objects": ["--moving-objects", "4"],
    "followed_target": ["--follow-target", "1.5", "4.5"],
    "exposure_steps": ["--exposure-steps", "2"],
    "vignetting": ["--vignetting", "0.4"],
    "low_light": ["--low-light", "--jpeg-quality", "60"],
    "rolling_shutter": ["--rolling-shutter", "0.03"],
}
CASES["all"] = [a for name in ("moving_objects", "followed_target", "exposure_steps", "vignetting",
                               "low_light") for a in CASES[name]]  # fmt: skip
# Issue 16's targets (focal in %, principal point in px at 1280x720, rotation in deg).
TARGETS = {"focal_median": 0.2, "focal_p90": 0.6, "pp": 2.0, "rotation": 0.03, "off_1pct": 0.0}


def make_bag(work: Path, panorama: str, seed: int, case: str, frames: int, size: tuple[int, int]) -> Path:
    bag = work / f"{panorama}_{size[0]}x{size[1]}_{frames}_s{seed}_{case}"
    if not bag.exists():
        cmd = [str(BIN), "synth", str(PANORAMAS[panorama]), str(bag), "--frames", str(frames),
               "--width", str(size[0]), "--height", str(size[1]), *MOTION, "--seed", str(seed),
               *CASES[case], "--quiet"]  # fmt: skip
        subprocess.run(cmd, check=True)
    return bag


def evaluate(bag: Path) -> dict[str, Any]:
    out = bag.with_name(f"eval_{bag.name}")
    if not (out / "report.json").exists():
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        cmd = [str(BIN), "eval", str(bag), "--out-dir", str(out), "--no-plots", "--quiet"]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode:
            sys.exit(f"eval {bag} failed:\n{proc.stderr[-2000:]}")
    return json.loads((out / "report.json").read_text())


def row(report: dict[str, Any]) -> dict[str, float]:
    m, f = report["metrics"], report["figures"]
    return {
        "focal_median": 100.0 * m["focal_error"]["after_warmup"]["median"],
        "focal_p90": 100.0 * m["focal_error"]["after_warmup"]["p90"],
        "pp": m["principal_point_error_px"]["after_warmup"]["median"],
        "rotation": m["rotation_error_deg"]["after_warmup"]["median"],
        "off_1pct": 100.0 * f["converged_off_1pct_share"],
        "degenerate": float(report["status_counts"].get("DEGENERATE_MOTION", 0)),
        "fps": report["performance"]["run_throughput_fps"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--panoramas", default="examplepano,building")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--size", default="960x540")
    parser.add_argument("--work-dir", default="/tmp/real_video")
    parser.add_argument("--quick", action="store_true", help="examplepano, seed 0, 150 frames of 640x360")
    args = parser.parse_args()
    if args.quick:
        # 150 frames at 25 fps: the followed target's window (1.5 s to 4.5 s) fits in the sequence
        args.panoramas, args.seeds, args.frames, args.size = "examplepano", "0", 150, "640x360"
    size = tuple(int(v) for v in args.size.split("x"))
    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    cases = [c for c in args.cases.split(",") if c != "none"]
    columns = ("focal_median", "focal_p90", "pp", "rotation", "off_1pct", "degenerate", "fps")
    print(f"{'case':34s}" + "".join(f"{c:>13s}" for c in columns))
    print(f"{'targets (with the nuisance)':34s}" + "".join(f"{TARGETS.get(c, ''):>13}" for c in columns))
    for panorama in args.panoramas.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            plain = row(evaluate(make_bag(work, panorama, seed, "none", args.frames, size)))
            for case in cases:
                with_it = row(evaluate(make_bag(work, panorama, seed, case, args.frames, size)))
                for label, values in ((f"{panorama} s{seed} {case}", with_it), ("  without it", plain)):
                    print(f"{label:34s}" + "".join(f"{values[c]:13.3f}" for c in columns), flush=True)


if __name__ == "__main__":
    main()
