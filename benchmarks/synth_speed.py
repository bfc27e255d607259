"""Speed of `ptz-selfcal synth`: 300 frames of 1280x720 JPEG, rendered and written to an mcap bag.

Issue 2 asks for under 60 s on this machine. Times the whole command (panorama decode and pyramid,
rendering, image noise, JPEG encoding, bag writing, final rename) in-process, plus a per-stage split of
one frame, and prints frames/s and total seconds.

    ros2_ws/venv/bin/python benchmarks/synth_speed.py [--frames 300] [--width 1280] [--height 720]
        [--jobs 2] [--panorama bags/source/examplepano.jpg]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ptz_selfcal.sim.render import ImageModel, build_panorama, view_maps
from ptz_selfcal.tools import cli

ROOT = Path(__file__).resolve().parents[1]


def stage_times(panorama: Path, width: int, height: int, repeats: int = 20) -> dict[str, float]:
    """Milliseconds per frame of each stage, single-threaded, on a mid-sequence view."""
    from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation

    pano = build_panorama(cv2.imread(str(panorama)))
    K = intrinsic_matrix(1.5 * 0.5 * width / np.tan(np.radians(30.0)), 0.5 * width + 15, 0.5 * height - 10)
    R = ptz_rotation(0.3, 0.05)
    out: dict[str, float] = {}
    t = time.perf_counter()
    for _ in range(repeats):
        mx, my, level = view_maps(pano, K, R, (width, height))
    out["maps"] = (time.perf_counter() - t) / repeats * 1e3
    t = time.perf_counter()
    for _ in range(repeats):
        view = cv2.remap(pano.levels[level], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    out["remap"] = (time.perf_counter() - t) / repeats * 1e3
    model = ImageModel()
    t = time.perf_counter()
    for i in range(repeats):
        image = model.apply(view, 1.0, np.random.default_rng(i))
    out["noise+gain"] = (time.perf_counter() - t) / repeats * 1e3
    t = time.perf_counter()
    for _ in range(repeats):
        cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    out["jpeg"] = (time.perf_counter() - t) / repeats * 1e3
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--panorama", type=Path, default=ROOT / "bags" / "source" / "examplepano.jpg")
    args = parser.parse_args()
    for name, ms in stage_times(args.panorama, args.width, args.height).items():
        print(f"  {name:<11s} {ms:6.1f} ms/frame (1 thread)")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench"
        argv = [
            "synth",
            str(args.panorama),
            str(out),
            "--frames",
            str(args.frames),
            "--width",
            str(args.width),
        ]
        argv += ["--height", str(args.height), "--jobs", str(args.jobs), "--quiet"]
        sys.argv = ["ptz-selfcal", *argv]  # the CLI adds a command's options from sys.argv
        start = time.perf_counter()
        status = cli.main(argv)
        seconds = time.perf_counter() - start
        if status != 0:
            return status
        size = sum(f.stat().st_size for f in out.iterdir()) / 1e6
    print(
        f"synth {args.frames} frames {args.width}x{args.height} jpeg, {args.jobs} threads: "
        f"{seconds:.1f} s total, {args.frames / seconds:.1f} frames/s, bag {size:.1f} MB"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
