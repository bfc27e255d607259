"""Issue 8: the stills front end on the real hand-held sets, configuration by configuration.

    ros2_ws/venv/bin/python benchmarks/stills_frontend.py [--sets parrington,...] [--configs A,B] [--out FILE]

Per configuration and set: CPU ms per still of the front end by stage (detect, match, fit, predict), the
pairs it matched, its links (those between non-consecutive stills close the loop), stills lost, its own
rough focal length (the linear estimate the overlap prediction uses) against AutoStitch's, then the CPU
and wall ms per still of the whole fixed-lens pass (front end + the calibrator session with focal_model
constant, benchmarks/peers.run_session) and the focal length of its final state against AutoStitch's.
"all pairs" is the former front end (every new still matched against every earlier one, 2000 ORB
features over 8 levels, brute force), kept as StillsConfig(exhaustive=True).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import peers

from ptz_selfcal.frontend.stills import StillsConfig, StillsTracker

DEFAULT = StillsConfig()
CONFIGS: dict[str, StillsConfig] = {
    "all pairs, ORB 2000 x8 (before)": StillsConfig(
        exhaustive=True, n_features=2000, orb_levels=8, fast_score=False, matcher="bf"
    ),
    "chosen pairs, ORB 2000 x8, BF": replace(
        DEFAULT, n_features=2000, orb_levels=8, fast_score=False, matcher="bf"
    ),
    "chosen pairs, ORB 1000 x3 Harris, BF": replace(DEFAULT, fast_score=False, matcher="bf"),
    "chosen pairs, ORB 1000 x3, BF": replace(DEFAULT, matcher="bf"),
    "chosen pairs, ORB 1000 x3, LSH 6x12 bits": replace(DEFAULT, lsh=(6, 12, 1)),
    "chosen pairs, ORB 1000 x3, LSH 4x12 bits": replace(DEFAULT, lsh=(4, 12, 1)),
    "chosen, ORB 1000 x3, LSH 6x16 (default)": DEFAULT,
    "chosen pairs, ORB 1000 x2, LSH 6x16": replace(DEFAULT, orb_levels=2),
    "chosen pairs, ORB 1000 x1, LSH 6x16": replace(DEFAULT, orb_levels=1),
    "chosen pairs, ORB 800 x1, LSH 6x16": replace(DEFAULT, orb_levels=1, n_features=800),
    "chosen pairs, ORB 600 x1, LSH 6x16": replace(DEFAULT, orb_levels=1, n_features=600),
    "chosen pairs, ORB 600 x1, BF": replace(DEFAULT, orb_levels=1, n_features=600, matcher="bf"),
    "chosen pairs, ORB 1500 x3, LSH 6x16": replace(DEFAULT, n_features=1500),
    "chosen pairs, ORB 700 x3, LSH 6x16": replace(DEFAULT, n_features=700),
    "chosen pairs, ORB 1000 x3, LSH, 320 px": replace(DEFAULT, max_width=320),
    "previous still only (no loop closure)": replace(DEFAULT, max_links=0, max_uncertain=0),
}


def front_end(seq: peers.Sequence, config: StillsConfig) -> tuple[StillsTracker, list, float]:
    """The tracker alone over the set: (tracker with its stage CPU and pair count, results, CPU s)."""
    tracker = StillsTracker(config)
    scale = peers.working_scale(seq.size)
    c0 = time.process_time()
    results = [
        tracker.track(peers.to_working(f, scale), scale, i / peers.FPS) for i, f in enumerate(seq.frames)
    ]
    return tracker, results, time.process_time() - c0


def row(name: str, seq: peers.Sequence, config: StillsConfig) -> str:
    n = len(seq.frames)
    tracker, results, cpu = front_end(seq, config)
    stages = " ".join(f"{1000.0 * v / n:5.1f}" for v in tracker.cpu.values())
    links = [link for r in results for link in r.links]
    loops = sorted({(k.source_id, k.target_id) for k in links if k.target_id - k.source_id > 1})
    lost = sum(r.H_ref is None for r in results)
    f_est = tracker.focal(tracker.stills[0].size)
    f_est = f"{100.0 * (f_est - seq.f_reference) / seq.f_reference:+.0f}" if seq.f_reference else "-"
    rows, tracking = peers.run_session(seq, "constant", stills=config)  # the node, focal_model:=constant
    final = peers.evaluate(seq, rows[-1], None)
    f_as = "-" if np.isnan(final.f_vs_autostitch) else f"{final.f_vs_autostitch:.2f}"
    total_cpu = 1000.0 * tracking.cpu_seconds / n
    wall = 1000.0 * tracking.seconds / n
    return (
        f"{seq.name:<11} {name:<42} {1000.0 * cpu / n:6.1f}  {stages}  {tracker.attempts:5d} {len(links):5d} "
        f"{lost:4d} {f_est:>5}  {total_cpu:7.1f} {wall:7.1f}  {f_as:>6}  loop links {loops}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", default="parrington,grail,denny,weir")
    parser.add_argument("--configs", default="", help="substrings of configuration names (default: all)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    wanted = [c for c in args.configs.split(",") if c]
    configs = {k: v for k, v in CONFIGS.items() if not wanted or any(w in k for w in wanted)}
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    lines = [
        "$ ros2_ws/venv/bin/python benchmarks/stills_frontend.py " + " ".join(argv or sys.argv[1:]),
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {peers.code_revision()}; "
        f"load average at the start {load} (2 CPUs shared: wall times inflated, CPU times less so)",
        "Per still: front end CPU ms (total, detect, match, fit, predict); pairs matched, links, stills lost;"
        " the front end's rough f vs AutoStitch %; CPU and wall ms of the fixed-lens pass (front end +"
        " calibrator session, focal_model constant); its final-state f vs AutoStitch %.",
        "",
        f"{'set':<11} {'front end':<42} {'fe cpu':>6}  {'det':>5} {'match':>5} {'fit':>5} {'pred':>5}  "
        f"{'pairs':>5} {'links':>5} {'lost':>4} {'f0 %':>5}  {'all cpu':>7} {'wall':>7}  {'f-AS %':>6}",
    ]
    print("\n".join(lines), flush=True)
    for name in [s for s in args.sets.split(",") if s]:
        seq = peers.load_real_set(name)
        for label, config in configs.items():
            lines.append(row(label, seq, config))
            print(lines[-1], flush=True)
    if args.out is not None:
        args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
