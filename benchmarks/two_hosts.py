"""Issue 19 "Measure", across hosts: image -> CameraInfo latency and throughput with frame_ingest on a
camera-side host and homography_tracker + calibrator on a server, against the same graph on one host.

The two hosts are two network namespaces of this benchmark's own joined by a veth pair
(tests/node/two_hosts_harness.py; removed at the end): discovery by static peers only
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, ROS_STATIC_PEERS naming both), shared memory within a host
only, the shipped Fast DDS profile as launch gives it to the nodes (with static peers: its copy with
the peers as discovery, dds_profile_environment) and parameter defaults (queue policy and depth). This
process is the camera driver: it plays the bag live on the camera-side host and takes the CameraInfo
back there, so the latency over the link includes both crossings (the frame to the server, its
CameraInfo back). "One host": the same nodes, frames and rate, all on the camera-side host.

The player and the measurement are benchmarks/live_latency.py's (measure, report). Printed per run:
its report, and the frames per second delivered (calibrated images over the time from the first image
published to the last CameraInfo), the bytes on the link per image and the datagrams the server's kernel
dropped for a full socket receive buffer (each one a fragment the reliable protocol re-sends). Writes
benchmarks/results/two_hosts.txt.

    ros2_ws/venv/bin/python benchmarks/two_hosts.py [--bag SYNTH_BAG] [--repeats N] [--rate 1]
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "benchmarks"), str(ROOT / "tests" / "node")]

from live_latency import finish, load_bag, measure, pct, render_bag, report  # noqa: E402
from two_hosts_harness import NetnsSupervisor, TwoHosts, enter, unavailable  # noqa: E402

TARGET_P95_GAP_MS = 5.0  # issue 19: p95 over the link within 5 ms of the same graph on one host
SERVER_NODES = ("homography_tracker", "calibrator")


def delivered_fps(res) -> float:
    if not res.info:
        return float("nan")
    return len(res.info) / (max(res.info.values()) - min(res.sent.values()))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--bag", type=Path, help="an existing synth bag (default: live_latency's, rendered)")
    parser.add_argument("--rate", type=float, default=1.0, help="playback speed factor (default 1: live)")
    parser.add_argument("--repeats", type=int, default=2, help="runs per setting (alternating)")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "two_hosts.txt")
    parser.add_argument("--no-write", action="store_true", help="print only")
    parser.add_argument(
        "--nice",
        type=int,
        help="run the nodes and the player at this niceness in both settings (live_latency's --nice: "
        "e.g. -10, the camera pipeline ahead of the machine's other work)",
    )
    args = parser.parse_args(argv)
    reason = unavailable()
    if reason:
        print(f"two_hosts: {reason}", file=sys.stderr)
        return 1

    from ptz_selfcal import topics
    from ptz_selfcal.nodes.frame_ingest import PARAMS
    from ptz_selfcal.tools.launch import PROFILE_VARIABLES, dds_profile_environment

    defaults = {p.name: p.default for p in PARAMS}
    policy, depth = defaults["queue_policy"], defaults["queue_depth"]
    given = " ".join(argv if argv is not None else sys.argv[1:])
    lines = [
        f"# ros2_ws/venv/bin/python benchmarks/two_hosts.py {given}".rstrip(),
        f"# {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}, {os.cpu_count()} CPUs, "
        f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())} at start",
    ]
    summary: dict[str, list[tuple[float, float, float]]] = {"one host": [], "two hosts": []}
    with tempfile.TemporaryDirectory(prefix="two_hosts_") as tmp, TwoHosts() as hosts:
        bag = args.bag
        if bag is None:
            bag = render_bag(Path(tmp))
            lines.append("# live_latency's synth bag: 300 frames 1280x720 JPEG at 30 frames/s, seed 0")
        image_topic = topics.bag_topic(topics.IMAGE_COMPRESSED)
        image_type, messages = load_bag(bag, image_topic, topics.bag_topic(topics.JOINT_STATES))
        images = sum(1 for m in messages if m[0] == image_topic)
        lines.append(
            f"# bag {bag}: {images} images ({image_type}), rate {args.rate}; shipped queue {policy} "
            f"(depth {depth}), Fast DDS profile and parameters; link {hosts.a.address} <-> {hosts.b.address}"
        )
        # This process (player and measurement) and every node it starts live on the camera-side host.
        enter(hosts.a.netns)
        base = {k: v for k, v in os.environ.items() if k not in PROFILE_VARIABLES}
        base.setdefault("ROS_DOMAIN_ID", "61")
        settings = {
            "one host": ({}, {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}),
            "two hosts": ({name: hosts.b.netns for name in SERVER_NODES}, hosts.environment()),
        }
        for k in range(args.repeats):
            for name, (netns, env) in settings.items():
                sub = Path(tmp) / f"{name.replace(' ', '_')}_{k}"
                sub.mkdir()
                # what launch gives its nodes, for this process (the camera driver) and the nodes alike
                os.environ.clear()
                os.environ.update({**base, **env})
                os.environ.update(dds_profile_environment(str(sub)))
                before = hosts.counters(hosts.b), hosts.udp_receive_errors(hosts.b)
                res = measure(
                    messages, image_type, image_topic, policy, depth, sub, args.rate, [], args.nice,
                    supervisor_class=functools.partial(NetnsSupervisor, netns=netns),
                )  # fmt: skip
                link = hosts.counters(hosts.b)["rx_bytes"] - before[0]["rx_bytes"]
                dropped = hosts.udp_receive_errors(hosts.b) - before[1]
                lines.append(f"## {name}" + (" (the server's nodes across the veth link)" if netns else ""))
                report(res, lines)
                fps = delivered_fps(res)
                lines.append(
                    f"  delivered {fps:.1f} frames/s; server's link end received {link / 1e6:.1f} MB "
                    f"({link / max(res.published, 1) / 1e3:.0f} kB per image, discovery included), "
                    f"datagrams dropped for a full receive buffer on the server: {dropped}"
                )
                _, lat = res.latencies()
                summary[name].append((pct(lat, 50), pct(lat, 95), fps))
                print("\n".join(lines[-12:]), flush=True)
    lines.append("# summary (p50 / p95 ms, delivered frames/s, per run):")
    for name, runs in summary.items():
        shown = "; ".join(f"{p50:.1f} / {p95:.1f} ms, {fps:.1f} fps" for p50, p95, fps in runs)
        lines.append(f"#   {name}: {shown}")
    one = float(np.median([r[1] for r in summary["one host"]]))
    two = float(np.median([r[1] for r in summary["two hosts"]]))
    ok = "yes" if two - one <= TARGET_P95_GAP_MS else "NO"
    lines.append(
        f"# median p95: one host {one:.1f} ms, two hosts {two:.1f} ms, gap {two - one:+.1f} ms "
        f"(target <= {TARGET_P95_GAP_MS:.0f} ms: {ok})"
    )
    finish(lines, None if args.no_write else args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
