"""Issue 19 "Measure": lock-step throughput and per-frame CPU of the node suite, JPEG and raw, 720p and 1080p.

For each case (1280x720 and 1920x1080, JPEG and raw bgr8) a `ptz-selfcal synth` bag of the same camera
path (seed 0, --frames frames, rendered once into --work-dir) goes through `ptz-selfcal run` (the three
real node processes over DDS, lock-step, window 4, the shipped parameters and Fast DDS profile), each run
in a process of its own. From run's own summary: frames/s over the replay and in steady state (after the
first 10% of the frames, run's STEADY_AFTER), the lock-step latency image -> CameraInfo and image ->
homography, and the CPU milliseconds per frame of each node and of run's player+recorder in steady state
(start-up excluded). The machine's 1-minute load average before and after each run is printed beside
its figures: on a machine busy with other work the rates fall and the CPU times rise.

With --old-profile the raw cases run once more under the profile launch wrote before issue 19 (its
participant lease only, so Fast DDS's default transports: a 512 KB shared-memory segment), for the
comparison the shipped profile was chosen by.

Targets (issue 19): nodes total <= 8 ms per frame at 1280x720 JPEG; lock-step >= 150 frames/s at 1280x720
JPEG and >= 80 at 1920x1080 JPEG; raw bgr8 1280x720 at least as fast as JPEG.

With --ingest-only, frame_ingest's own per-frame work instead, in this process and without DDS: the
copy rclpy makes when it takes a serialized image, the header read in place, the conversion to mono8 at
the working width, the IngestedFrame fill and its serialisation (what the publisher does), in process CPU
ms per frame (median of --repeats blocks of 100 frames) at 1280x720 and 1920x1080, JPEG and raw bgr8
(the panorama cropped, JPEG quality 90 as synth's default). Run it on two trees (PYTHONPATH) to compare.

    ros2_ws/venv/bin/python benchmarks/throughput.py [--frames 300] [--repeats 2] [--old-profile]
    ros2_ws/venv/bin/python benchmarks/throughput.py --ingest-only [--repeats 5] [--append]
Writes benchmarks/results/throughput.txt (and prints it); --append adds the run after the file's text.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pipeline import PANORAMA, cli_main

ROOT = Path(__file__).resolve().parents[1]
CASES = {  # name -> (width, height, synth --format)
    "720p-jpeg": (1280, 720, "jpeg"),
    "720p-bgr8": (1280, 720, "bgr8"),
    "1080p-jpeg": (1920, 1080, "jpeg"),
    "1080p-bgr8": (1920, 1080, "bgr8"),
}
TARGET_NODES_MS_720P_JPEG = 8.0
TARGET_FPS = {"720p-jpeg": 150.0, "1080p-jpeg": 80.0}
NODES = ("frame_ingest", "homography_tracker", "calibrator")
PLAYER = "run (player+recorder)"
# What launch gave the nodes before issue 19: a participant lease and nothing else (Fast DDS's default
# transports). Only for the comparison.
OLD_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <participant profile_name="ptz_selfcal_launch" is_default_profile="true">
    <rtps><builtin><discovery_config>
      <leaseDuration><sec>2</sec><nanosec>0</nanosec></leaseDuration>
      <leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>
    </discovery_config></builtin></rtps>
  </participant>
</profiles>
"""


@dataclass
class RunResult:
    case: str
    profile: str
    load_before: float
    load_after: float
    coverage: str = "?"
    fps: float = math.nan
    steady_fps: float = math.nan
    p50: float = math.nan
    p95: float = math.nan
    hom_p95: float = math.nan
    cpu_ms: dict[str, float] = field(default_factory=dict)  # steady state, per frame
    error: str = ""

    @property
    def nodes_ms(self) -> float:
        return sum(self.cpu_ms.get(n, math.nan) for n in NODES)


def render(work: Path, case: str, frames: int) -> Path:
    width, height, fmt = CASES[case]
    bag = work / f"{case}_{frames}"
    if not bag.exists():
        args = ["synth", str(PANORAMA), str(bag), "--quiet", "--seed", "0", "--frames", str(frames)]
        args += ["--width", str(width), "--height", str(height), "--format", fmt]
        if cli_main(args):
            raise SystemExit(f"synth failed for {case}")
    return bag


def parse(text: str, result: RunResult) -> None:
    """Fill result from run's summary lines (tools/run.py prints them even with --quiet)."""
    summary = re.search(
        r"coverage ([0-9.]+%).*?([0-9.]+) frames/s, latency in lock-step p50 ([0-9.]+) ms p95 ([0-9.]+) ms "
        r"\(to the homography: p50 [0-9.]+ ms p95 ([0-9.]+) ms",
        text,
    )
    steady = re.search(r"steady state .*?: ([0-9.]+) frames/s; CPU ms per frame: (.*), nodes total", text)
    if summary is None or steady is None:
        result.error = text.strip().splitlines()[-1] if text.strip() else "no output"
        return
    result.coverage = summary.group(1)
    result.fps, result.p50, result.p95, result.hom_p95 = (float(summary.group(k)) for k in (2, 3, 4, 5))
    result.steady_fps = float(steady.group(1))
    for item in steady.group(2).split(", "):
        name, value = item.rsplit(" ", 1)
        result.cpu_ms[name] = float(value)


def run_once(bag: Path, case: str, profile: str, work: Path, domain: int) -> RunResult:
    out = Path(tempfile.mkdtemp(prefix="throughput_", dir=work)) / "out"
    env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    env.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    env.pop("FASTDDS_DEFAULT_PROFILES_FILE", None)
    if profile == "old":
        old = work / "old_profile.xml"
        old.write_text(OLD_PROFILE)
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(old)
    cmd = [sys.executable, "-c", "import sys; from ptz_selfcal.tools.cli import main; sys.exit(main())"]
    cmd += ["run", str(bag), "--out", str(out), "--quiet"]
    result = RunResult(case, profile, os.getloadavg()[0], math.nan)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    result.load_after = os.getloadavg()[0]
    parse(proc.stdout + proc.stderr, result)
    subprocess.run(["rm", "-rf", str(out.parent)], check=False)
    return result


def row(r: RunResult) -> str:
    if r.error:
        return (
            f"  {r.case:<11} {r.profile:<8} load {r.load_before:4.1f}/{r.load_after:4.1f}  FAILED: {r.error}"
        )
    cpu = "  ".join(f"{r.cpu_ms.get(n, math.nan):6.2f}" for n in (*NODES, PLAYER))
    return (
        f"  {r.case:<11} {r.profile:<8} load {r.load_before:4.1f}/{r.load_after:4.1f}  {r.coverage:>6} "
        f"{r.fps:6.1f} {r.steady_fps:6.1f}  {r.p50:6.1f} {r.p95:7.1f} {r.hom_p95:7.1f}   {cpu}  "
        f"{r.nodes_ms:6.2f}"
    )


HEADER = (
    "  case        profile  load 1m        cover.    fps steady   p50 ms  p95 ms hom p95   "
    "ingest tracker  calib. player   nodes\n"
    "  (CPU ms per frame in steady state; load = 1-minute load average before/after the run, 2 CPUs)"
)


def median(results: list[RunResult], get) -> float:
    values = [get(r) for r in results if not r.error]
    return float(np.median(values)) if values else math.nan


def verdicts(results: list[RunResult]) -> list[str]:
    def of(case: str) -> list[RunResult]:
        return [r for r in results if r.case == case and r.profile == "shipped"]

    lines = ["", "Targets (medians of the shipped-profile runs; load average beside each):"]
    jpeg = of("720p-jpeg")
    if jpeg:
        ms = median(jpeg, lambda r: r.nodes_ms)
        load = median(jpeg, lambda r: r.load_before)
        ok = "yes" if ms <= TARGET_NODES_MS_720P_JPEG else "NO"
        lines.append(
            f"  nodes CPU per frame, 1280x720 JPEG: {ms:.2f} ms "
            f"(target <= {TARGET_NODES_MS_720P_JPEG:g}: {ok}; load {load:.1f})"
        )
    for case, target in TARGET_FPS.items():
        if of(case):
            fps = median(of(case), lambda r: r.fps)
            load = median(of(case), lambda r: r.load_before)
            ok = "yes" if fps >= target else "NO"
            lines.append(
                f"  lock-step {case}: {fps:.1f} frames/s (target >= {target:g}: {ok}; load {load:.1f})"
            )
    raw, jpeg = of("720p-bgr8"), of("720p-jpeg")
    if raw and jpeg:
        a, b = median(raw, lambda r: r.fps), median(jpeg, lambda r: r.fps)
        ok = "yes" if a >= b else "NO"
        lines.append(
            f"  raw bgr8 1280x720 vs JPEG: {a:.1f} vs {b:.1f} frames/s (target raw >= JPEG: {ok}; load "
            f"{median(raw, lambda r: r.load_before):.1f} / {median(jpeg, lambda r: r.load_before):.1f})"
        )
    return lines


def ingest_messages(case: str, count: int) -> list[bytes]:
    """Serialized images of a case as frame_ingest receives them: crops of the panorama along a pan."""
    import cv2
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage, Image

    width, height, fmt = CASES[case]
    pano = cv2.imread(str(PANORAMA), cv2.IMREAD_COLOR)
    scale = max(1.0, 1.1 * height / pano.shape[0], 1.1 * width / pano.shape[1])
    if scale > 1.0:
        pano = cv2.resize(pano, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    span = pano.shape[1] - width
    out = []
    for k in range(count):
        x0 = (7 * k) % max(1, span)
        crop = np.ascontiguousarray(pano[:height, x0 : x0 + width])
        if fmt == "jpeg":
            msg = CompressedImage(format="jpeg")
            msg.data = cv2.imencode(".jpg", crop, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
        else:
            msg = Image(height=height, width=width, encoding="bgr8", step=3 * width)
            msg.data = crop.tobytes()
        msg.header.stamp.sec, msg.header.frame_id = k, "ptz_camera"
        out.append(serialize_message(msg))
    return out


def ingest_cpu_ms(case: str, repeats: int, working_width: int = 640) -> tuple[float, float]:
    """(median, spread) of frame_ingest's process CPU ms per frame for one case, without DDS."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Header

    from ptz_selfcal.nodes import frame_ingest as fi
    from ptz_selfcal.nodes.conversions import (
        ImageLimits,
        compressed_to_working,
        fill_mono8,
        image_to_working,
        parse_serialized_image,
    )
    from ptz_selfcal_msgs.msg import IngestedFrame

    compressed = CASES[case][2] == "jpeg"
    convert = compressed_to_working if compressed else image_to_working
    limits = ImageLimits()
    messages = ingest_messages(case, 100)

    def one(data: bytes) -> bytes:
        taken = bytes(memoryview(data))  # rclpy's take of a serialized message: one copy into a bytes object
        view = parse_serialized_image(taken, compressed=compressed)
        frame = convert(view, working_width, limits)
        header = Header(stamp=Time(sec=view.sec, nanosec=view.nanosec), frame_id=view.frame_id)
        msg = IngestedFrame()
        msg.header = header
        if hasattr(fi, "working_image_msg"):
            msg.image = fi.working_image_msg(header, frame.image)
        else:  # a tree from before it
            msg.image.header = header
            fill_mono8(msg.image, frame.image)
        msg.full_width, msg.full_height, msg.scale = frame.full_width, frame.full_height, frame.scale
        return serialize_message(msg)  # the publisher's conversion to C and serialisation

    for data in messages[:10]:  # warm-up: imports, OpenCV's buffers
        one(data)
    blocks = []
    for _ in range(repeats):
        start = time.process_time()
        for data in messages:
            one(data)
        blocks.append(1e3 * (time.process_time() - start) / len(messages))
    return float(np.median(blocks)), float(np.max(blocks) - np.min(blocks))


def ingest_only(args: argparse.Namespace, given: str) -> int:
    import ptz_selfcal

    lines = [
        f"# ros2_ws/venv/bin/python benchmarks/throughput.py {given}".rstrip(),
        f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, {os.cpu_count()} CPUs, ptz_selfcal "
        f"from {Path(ptz_selfcal.__file__).parent}",
        "# frame_ingest's per-frame work without DDS (take copy, header in place, mono8 at width 640, "
        "IngestedFrame fill and serialisation), process CPU ms per frame, median of blocks of 100 frames",
        "",
        "  case        ingest ms/frame  (spread)  load 1m",
    ]
    for case in args.cases:
        load = os.getloadavg()[0]
        ms, spread = ingest_cpu_ms(case, args.repeats)
        lines.append(f"  {case:<11} {ms:10.2f}      ({spread:4.2f})    {load:4.1f}")
        print(lines[-1], flush=True)
    write(args, lines)
    return 0


def write(args: argparse.Namespace, lines: list[str]) -> None:
    text = "\n".join(lines) + "\n"
    print(text)
    if args.no_write:
        return
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.append and args.out.exists():
        text = args.out.read_text().rstrip("\n") + "\n\n" + text
    args.out.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=300, help="frames per bag (default 300)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per case (default 2)")
    parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
    parser.add_argument(
        "--old-profile", action="store_true", help="also run the raw cases on the old profile"
    )
    parser.add_argument("--work-dir", type=Path, help="keep the bags here (default: a temporary directory)")
    parser.add_argument("--domain", type=int, default=212, help="ROS_DOMAIN_ID of the runs (default 212)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "throughput.txt")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument("--append", action="store_true", help="add the run after the text of --out")
    parser.add_argument(
        "--ingest-only", action="store_true", help="frame_ingest's per-frame work in this process, no DDS"
    )
    args = parser.parse_args(argv)
    given = " ".join(argv if argv is not None else sys.argv[1:])
    if args.ingest_only:
        return ingest_only(args, given)
    lines = [
        f"# ros2_ws/venv/bin/python benchmarks/throughput.py {given}".rstrip(),
        f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, {os.cpu_count()} CPUs, load average "
        f"{' '.join(f'{v:.2f}' for v in os.getloadavg())} at start",
        f"# {args.frames}-frame synth bags of {PANORAMA.name} (seed 0), ptz-selfcal run lock-step "
        "(window 4), shipped parameters; profile 'shipped' = config/fastdds.xml, 'old' = the lease-only "
        "profile of before",
    ]
    with tempfile.TemporaryDirectory(prefix="throughput_") as tmp:
        work = args.work_dir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        bags = {case: render(work, case, args.frames) for case in args.cases}
        plan = [(case, "shipped") for case in args.cases]
        if args.old_profile:
            plan += [(case, "old") for case in args.cases if CASES[case][2] != "jpeg"]
        results: list[RunResult] = []
        lines += ["", HEADER]
        for _ in range(args.repeats):  # interleaved: slow drifts of the machine's load hit every case alike
            for case, profile in plan:
                results.append(run_once(bags[case], case, profile, work, args.domain))
                lines.append(row(results[-1]))
                print(lines[-1], flush=True)
    lines += verdicts(results)
    lines.append(f"# load average at the end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    write(args, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
