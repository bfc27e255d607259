"""Issue 15 "Measure": the shipped defaults, no parameter file, over bag families a user could have.

    ros2_ws/venv/bin/python benchmarks/defaults.py [--seeds N] [--jobs 2] [--quick] [--families a,b]
        [--work-dir /tmp/defaults_bench] [--deterministic] [--write] [--list]

--list prints the synth command of every bag (to make a family's bags for development); --quick runs
the first held-out seed of each family only. The full run (10 seeds, 100 runs) is sized for about 30
minutes on an idle 2-core machine with --jobs 2 when the bags are not cached yet.

Each family is a `ptz-selfcal synth` command (FAMILIES below; panorama, resolution, frame rate,
encoding, motion and lens vary between them) rendered with seeds 0 .. N-1; the seed also turns the
whole path to another pan centre, so every seed sees other scenery. Every bag is then run as a new user
would: `ptz-selfcal eval BAG --out-dir D --quiet --no-plots` (the real nodes over DDS, lock-step, the
shipped config/ptz_selfcal.yaml; --deterministic only when asked), and its report's "figures"
(tools/evaluate.figures, defined in sim/metrics.py from the ground truth) are judged.

Tune / hold-out: seeds with index % 3 == 0 are the tune set, the others are held out; families that
can use soft panoramas draw their tune and held-out seeds from different panoramas, the ones that need
sharp ones (1080p, long focal lengths: building 8192 px, examplepano 4096 px) alternate those two in
both sets (split by seed and motion). The held-out figures are the ones that count.

Per family and set: the well-posed frame (first with >= 2 deg about each of the first camera's x and y
axes), the first calibrated frame (CALIBRATING or CONVERGED) and its time, the focal error median and
p90 (over the frames after max(10 % of frames, well posed + 1 s)), principal point and distortion
errors (medians over the same frames), CONVERGED frames more than 1 % off, the 3 sigma_f coverage within
runs (the worst run) and across seeds (share of runs whose run-level error is within 3 of its stated
sigma), each beside its target with PASS / FAIL. A figure over several runs is judged on the worst run
(targets hold on every run); the median run is printed beside it. Bags are cached in --work-dir under
a name keyed by their synth arguments (synth refuses an existing path; a cached bag is reused).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import queue
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULT_FILE = ROOT / "benchmarks" / "results" / "defaults.txt"
SHARED = Path(os.environ.get("PTZ_SHARED_DATA", "/work/shared/data")) / "panoramas"
EXAMPLE = ROOT / "bags" / "source" / "examplepano.jpg"
DOMAIN_BASE = 225  # ROS_DOMAIN_ID of job slot k is DOMAIN_BASE + k (unused by the tests)
TUNE_EVERY = 3  # seed index % TUNE_EVERY == 0: the tune set

# Targets of issue 15 (fractions for the focal figures).
TARGETS = {
    "focal_median": 0.002,
    "focal_p90": 0.006,
    "pp_px": 3.0,
    "distortion_px": 1.0,
    "coverage": 0.95,
    "latency_s": 1.0,  # first calibrated within max(1 s, 3 frames) of the well-posed frame
    "latency_frames": 3,
}


def panorama(name: str) -> Path:
    """A panorama by file name: the repository's examplepano, else the shared data's."""
    return EXAMPLE if name == "examplepano.jpg" else SHARED / name


SHARP = ("examplepano.jpg", "building.jpg")  # enough pixels per degree for 1080p and long focal lengths
SOFT_TUNE = ("examplepano.jpg", "planet.jpg", "field.jpg")
SOFT_HELD = ("building.jpg", "dawn4000x2000.jpg", "leaf.jpg", "sunset.jpg", "tunnel.jpg")
MID_TUNE = ("examplepano.jpg",)
MID_HELD = ("building.jpg", "dawn4000x2000.jpg")


@dataclass(frozen=True)
class Family:
    name: str
    description: str
    synth: str  # synth options (panorama, bag path, seed and pan centre added per run)
    tune: tuple[str, ...]  # panoramas of the tune seeds
    held: tuple[str, ...]  # panoramas of the held-out seeds


FAMILIES: tuple[Family, ...] = (
    Family(
        "paperA",
        "section 4.1 configuration A: 30 frames 640x480 mono8 at 2 fps, 5 deg circle, f 800 -> 1400 px",
        "--paper-config A",
        MID_TUNE,
        MID_HELD,
    ),
    Family(
        "paperB",
        "section 4.1 configuration B: 30 frames 640x480 mono8 at 2 fps, 3.5 deg circle, f 1200 -> 2000 px",
        "--paper-config B",
        SHARP,
        SHARP,
    ),
    Family(
        "longfocal",
        "long focal, small circle (6.2): 120 frames 1280x720 bgr8 at 12 fps, 3 deg circle, "
        "f 2500 -> 4200 px, pp (15, -10)",
        "--motion circle --circle-radius-deg 3 --f-wide 2500 --f-tele 4200 --zoom-law linear "
        "--frames 120 --fps 12 --width 1280 --height 720 --format bgr8",
        SHARP,
        SHARP,
    ),
    Family(
        "barrel12",
        "12 % barrel at the wide end: 150 frames 1280x720 jpeg at 15 fps, sweep +-40/+-8 deg, zoom 3x",
        "--distortion 0.12 --frames 150 --fps 15",
        MID_TUNE,
        MID_HELD,
    ),
    Family(
        "hd30",
        "1080p at 30 fps, low light (synth --low-light, JPEG quality 60), mild barrel 3 %: 150 frames, "
        "sweep +-20/+-5 deg, zoom 2x",
        "--width 1920 --height 1080 --frames 150 --fps 30 --distortion 0.03 --low-light --jpeg-quality 60 "
        "--pan-amplitude 20 --tilt-amplitude 5 --zoom-max 2",
        SHARP,
        SHARP,
    ),
    Family(
        "slowstart",
        "clean 1280x720 png sweep at 15 fps, 150 frames, a 3 s slow start",
        "--frames 150 --fps 15 --format png --slow-start 3",
        MID_TUNE,
        MID_HELD,
    ),
    Family(
        "patrol",
        "pan-dominant patrol: 120 frames 960x540 mono8 at 5 fps, pan +-50 deg, tilt +-2.5 deg, "
        "2 s dwell at the turn, zoom 1.5x, hfov 50",
        "--motion patrol --pan-amplitude 50 --tilt-amplitude 2.5 --tilt-cycles 1 --dwell 2 --zoom-max 1.5 "
        "--hfov 50 --frames 120 --fps 5 --width 960 --height 540 --format mono8",
        SOFT_TUNE,
        SOFT_HELD,
    ),
    Family(
        "ppdrift",
        "principal point moving with zoom (12, -8) px at 4x, mild barrel 4 %: 150 frames 800x600 bgr8 "
        "at 25 fps, sweep +-30/+-6 deg",
        "--pp-drift 12 -8 --zoom-max 4 --distortion 0.04 --pan-amplitude 30 --tilt-amplitude 6 "
        "--frames 150 --fps 25 --width 800 --height 600 --format bgr8",
        MID_TUNE,
        MID_HELD,
    ),
    Family(
        "lowfps",
        "2 fps: 60 frames 640x480 jpeg, sweep +-30/+-6 deg, zoom 1.5x",
        "--frames 60 --fps 2 --width 640 --height 480 --pan-amplitude 30 --tilt-amplitude 6 --zoom-max 1.5",
        SOFT_TUNE,
        SOFT_HELD,
    ),
    Family(
        "demo",
        "synth's defaults (the clean demo): 300 frames 1280x720 jpeg at 30 fps, sweep +-40/+-8 deg, zoom 3x",
        "",
        MID_TUNE,
        MID_HELD,
    ),
)


# --------------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Run:
    family: Family
    seed: int
    role: str  # "tune" or "held"
    panorama: str

    @property
    def synth_args(self) -> tuple[str, ...]:
        pan_centre = (self.seed * 97 + 180) % 360 - 180  # other scenery per seed (seed 0: none)
        return (*self.family.synth.split(), "--seed", str(self.seed), "--pan-centre", str(pan_centre))

    @property
    def key(self) -> str:
        text = json.dumps([self.panorama, self.synth_args])
        return f"{self.family.name}_s{self.seed}_{hashlib.sha1(text.encode()).hexdigest()[:10]}"


def plan(families: Sequence[Family], seeds: int) -> list[Run]:
    runs = []
    for fam in families:
        counts = {"tune": 0, "held": 0}
        for seed in range(seeds):
            role = "tune" if seed % TUNE_EVERY == 0 else "held"
            panos = fam.tune if role == "tune" else fam.held
            runs.append(Run(fam, seed, role, panos[counts[role] % len(panos)]))
            counts[role] += 1
    return runs


def cli() -> list[str]:
    """The `ptz-selfcal` command a user has (the venv's entry point)."""
    exe = Path(sys.executable).parent / "ptz-selfcal"
    return [str(exe)] if exe.exists() else [shutil.which("ptz-selfcal") or "ptz-selfcal"]


def synth_command(run: Run, bag: Path) -> list[str]:
    return [*cli(), "synth", str(panorama(run.panorama)), str(bag), *run.synth_args, "--jobs", "1", "--quiet"]


def make_bag(run: Run, work: Path) -> tuple[Path, float]:
    """The run's bag (cached under its key); seconds spent rendering (0 when reused)."""
    bag = work / "bags" / run.key
    if (bag / "synth_params.yaml").exists():
        return bag, 0.0
    bag.parent.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    proc = subprocess.run(synth_command(run, bag), capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"synth failed for {run.key}: {proc.stderr.strip()[-500:]}")
    return bag, time.monotonic() - start


def evaluate(run: Run, bag: Path, work: Path, domain: int, deterministic: bool) -> tuple[dict, float]:
    """`ptz-selfcal eval` on the bag with the shipped defaults; its report and the wall time."""
    out = work / "eval" / run.key
    if out.exists():
        shutil.rmtree(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    cmd = [*cli(), "eval", str(bag), "--out-dir", str(out), "--quiet", "--no-plots"]
    if deterministic:
        cmd.append("--deterministic")
    start = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode:
        raise RuntimeError(f"eval failed for {run.key}: {proc.stderr.strip()[-800:]}")
    report = json.loads((out / "report.json").read_text())
    shutil.rmtree(out / "output_bag", ignore_errors=True)  # the report is what is kept
    return report, time.monotonic() - start


# --------------------------------------------------------------------------------------------------
# Judging
# --------------------------------------------------------------------------------------------------
def _finite(x: Any) -> float:
    return float(x) if x is not None and math.isfinite(float(x)) else math.nan


def run_figures(report: dict) -> dict[str, float]:
    """The numbers judged for one run (NaN where undefined)."""
    fig = report["figures"]
    wp, cal = fig.get("well_posed_time_s"), fig.get("first_calibrated_time_s")
    interval = _finite(fig.get("frame_interval_s"))
    if wp is None:
        latency = math.nan  # never well posed: nothing to be late for
    elif cal is None:
        latency = math.inf  # well posed, never calibrated
    else:
        latency = cal - wp
    run = fig.get("run_level") or {}
    conv = int(fig.get("converged_frames") or 0)
    return {
        "well_posed_frame": _finite(fig.get("well_posed_frame")),
        "well_posed_s": _finite(wp),
        "first_calibrated_frame": _finite(fig.get("first_calibrated_frame")),
        "first_calibrated_s": _finite(cal) if cal is not None else math.inf,
        "latency_s": latency,
        "latency_allowed_s": max(TARGETS["latency_s"], TARGETS["latency_frames"] * interval),
        "focal_median": _finite((fig.get("focal_error") or {}).get("median")),
        "focal_p90": _finite((fig.get("focal_error") or {}).get("p90")),
        "pp_px": _finite((fig.get("principal_point_error_px") or {}).get("median")),
        "distortion_px": _finite((fig.get("distortion_error_px") or {}).get("median")),
        "converged": conv,
        "converged_off": int(fig.get("converged_off_1pct") or 0),
        "coverage_within": _finite(fig.get("sigma3_coverage")),
        "z": _finite(run.get("z")),
        "run_error": _finite(run.get("error")),
        "calibrated_frames": int(report["frames"]["calibrated"]),
        "frames": int(report["frames"]["input"]),
    }


def _worst(values: list[float], high_is_bad: bool = True) -> float:
    v = [x for x in values if not math.isnan(x)]
    if not v:
        return math.nan
    return max(v) if high_is_bad else min(v)


def _median(values: list[float]) -> float:
    v = [x for x in values if not math.isnan(x) and not math.isinf(x)]
    return float(np.median(v)) if v else math.nan


def _verdict(ok: bool | None) -> str:
    return "n/a" if ok is None else ("PASS" if ok else "FAIL")


def _pct(x: float, digits: int = 3) -> str:
    return "n/a" if math.isnan(x) else ("inf" if math.isinf(x) else f"{100.0 * x:.{digits}f} %")


def _px(x: float) -> str:
    return "n/a" if math.isnan(x) else f"{x:.2f} px"


def _sec(x: float) -> str:
    return "n/a" if math.isnan(x) else ("never" if math.isinf(x) else f"{x:.2f} s")


def _frame(frames: list[float], seconds: list[float], pick: Any) -> str:
    i = pick(frames)
    return "never" if math.isnan(i) or math.isinf(i) else f"{i:.0f} ({_sec(pick(seconds))})"


def judge(rows: list[dict[str, float]]) -> list[tuple[str, str, str, str, str]]:
    """(figure, target, worst run, median run, verdict) lines for the runs of one family and set."""
    col = {k: [r[k] for r in rows] for k in rows[0]}
    out = [
        ("well-posed frame", "-", _frame(col["well_posed_frame"], col["well_posed_s"], _worst),
         _frame(col["well_posed_frame"], col["well_posed_s"], _median), ""),
        ("first calibrated frame", "-",
         _frame(col["first_calibrated_frame"], col["first_calibrated_s"], _worst),
         _frame(col["first_calibrated_frame"], col["first_calibrated_s"], _median), ""),
    ]  # fmt: skip
    late = [x for x in (r["latency_s"] - r["latency_allowed_s"] for r in rows) if not math.isnan(x)]
    out.append(
        (
            "calibrated after well posed",
            f"<= {_median(col['latency_allowed_s']):.2f} s",
            _sec(_worst(col["latency_s"])),
            _sec(_median(col["latency_s"])),
            _verdict(all(x <= 1e-9 for x in late) if late else None),
        )
    )
    limits = (
        ("focal_median", "focal error median", TARGETS["focal_median"], _pct, f"<= {_pct(0.002, 1)}"),
        ("focal_p90", "focal error p90", TARGETS["focal_p90"], _pct, f"<= {_pct(0.006, 1)}"),
        ("pp_px", "principal point error", TARGETS["pp_px"], _px, "<= 3 px"),
        ("distortion_px", "distortion error", TARGETS["distortion_px"], _px, "<= 1 px"),
    )
    for key, name, target, fmt, label in limits:
        worst = _worst(col[key])
        ok = None if math.isnan(worst) else worst <= target
        out.append((name, label, fmt(worst), fmt(_median(col[key])), _verdict(ok)))
    off, conv = int(sum(col["converged_off"])), int(sum(col["converged"]))
    out.append(("CONVERGED frames > 1 % off", "0", f"{off} of {conv}", "", _verdict(off == 0)))
    within = _worst(col["coverage_within"], high_is_bad=False)
    ok = None if math.isnan(within) else within >= TARGETS["coverage"]
    out.append(
        ("3 sigma coverage within runs", ">= 95 %", _pct(within, 1), _pct(_median(col["coverage_within"]), 1),
         _verdict(ok))
    )  # fmt: skip
    z = [x for x in col["z"] if not math.isnan(x)]
    across = float(np.mean(np.abs(z) <= 3.0)) if z else math.nan
    rms = f"rms z {np.sqrt(np.mean(np.square(z))):.2f}" if z else "n/a"
    ok = None if not z else across >= TARGETS["coverage"]
    out.append(
        ("3 sigma coverage across seeds", ">= 95 %", f"{_pct(across, 0)} of {len(z)} runs", rms, _verdict(ok))
    )
    return out


def family_block(fam: Family, results: dict[str, list[tuple[Run, dict[str, float]]]]) -> list[str]:
    lines = [f"{fam.name}: {fam.description}", f"  synth {fam.synth or '(defaults)'}"]
    for role, label in (("tune", "tune"), ("held", "HELD-OUT")):
        done = results.get(role, [])
        if not done:
            continue
        panos = sorted({r.panorama.rsplit(".", 1)[0] for r, _ in done})
        seeds = ",".join(str(r.seed) for r, _ in done)
        lines.append(f"  [{label}] {len(done)} runs (seeds {seeds}; {', '.join(panos)})")
        table = judge([row for _, row in done])
        w = [max(len(t[i]) for t in table) for i in range(5)]
        lines.append(f"    {'figure':<{w[0]}}  {'target':<{w[1]}}  {'worst run':<{w[2]}}  median run")
        for t in table:
            lines.append(
                f"    {t[0]:<{w[0]}}  {t[1]:<{w[1]}}  {t[2]:<{w[2]}}  {t[3]:<{w[3]}}  {t[4]}".rstrip()
            )
    return lines


def summary(families: Sequence[Family], results: dict[str, dict[str, list]]) -> list[str]:
    """One line per family: the held-out verdicts."""
    names = ("latency", "f med", "f p90", "pp", "dist", "conv>1%", "cov run", "cov seeds")
    lines = [
        "HELD-OUT summary (the figures that count)",
        f"  {'family':<10}  " + "  ".join(f"{n:>9}" for n in names),
    ]
    for fam in families:
        done = results.get(fam.name, {}).get("held", [])
        if not done:
            continue
        verdicts = [t[4] for t in judge([row for _, row in done])][2:]
        lines.append(f"  {fam.name:<10}  " + "  ".join(f"{v:>9}" for v in verdicts))
    return lines


def run_line(run: Run, row: dict[str, float], synth_s: float, eval_s: float) -> str:
    def f(x: float, scale: float = 1.0, d: int = 2) -> str:
        return "n/a" if math.isnan(x) else ("inf" if math.isinf(x) else f"{x * scale:.{d}f}")

    return (
        f"  {run.family.name} seed {run.seed} [{run.role}] {run.panorama}: "
        f"well posed {f(row['well_posed_s'])} s, "
        f"calibrated {f(row['first_calibrated_s'])} s; focal {f(row['focal_median'], 100, 3)} / "
        f"{f(row['focal_p90'], 100, 3)} %, pp {f(row['pp_px'])} px, dist {f(row['distortion_px'])} px; "
        f"CONVERGED {row['converged']} ({row['converged_off']} > 1 %), within 3 sigma "
        f"{f(row['coverage_within'], 100, 0)} %, z {f(row['z'])} (synth {synth_s:.0f} s, eval {eval_s:.0f} s)"
    )


# --------------------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--seeds", type=int, default=10, help="seeds per family (default 10: 4 tune, 6 held out)"
    )
    parser.add_argument("--quick", action="store_true", help="one held-out seed per family (development)")
    parser.add_argument("--families", help="comma-separated family names (default: all)")
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time (default 2)")
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/defaults_bench"), help="bag cache")
    parser.add_argument("--deterministic", action="store_true", help="pass --deterministic to eval")
    parser.add_argument("--write", action="store_true", help=f"write {RESULT_FILE.relative_to(ROOT)}")
    parser.add_argument("--list", action="store_true", help="print each run's synth command and exit")
    args = parser.parse_args(argv)

    families = list(FAMILIES)
    if args.families:
        wanted = args.families.split(",")
        unknown = sorted(set(wanted) - {f.name for f in FAMILIES})
        if unknown:
            parser.error(f"unknown families {unknown}; known: {[f.name for f in FAMILIES]}")
        families = [f for f in FAMILIES if f.name in wanted]
    runs = plan(families, args.seeds)
    if args.quick:  # the first held-out seed of each family
        runs = [next(r for r in runs if r.family is fam and r.role == "held") for fam in families]
    missing = sorted({r.panorama for r in runs if not panorama(r.panorama).exists()})
    if missing:
        parser.error(f"panoramas not found: {missing} (looked in {SHARED} and bags/source)")
    if args.list:
        for run in runs:
            bag = args.work_dir / "bags" / run.key
            synth = " ".join(synth_command(run, bag)[1:-3])  # without the entry point's path, --jobs, --quiet
            print(f"{run.family.name} seed {run.seed} [{run.role}]: ros2_ws/venv/bin/ptz-selfcal {synth}")
        return 0

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True, text=True
    )
    changes = " + uncommitted changes" if dirty.stdout.strip() else ""
    eval_flags = " --deterministic" if args.deterministic else ""
    header = [
        f"benchmarks/defaults.py {' '.join(argv if argv is not None else sys.argv[1:])}".rstrip(),
        f"  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, commit {commit.stdout.strip()}{changes}, "
        f"{os.cpu_count()} cores, --jobs {args.jobs}, load {os.getloadavg()[0]:.1f}",
        f"  ptz-selfcal eval BAG --out-dir D --quiet --no-plots{eval_flags} "
        "(shipped defaults, no parameter file)",
        f"  {len(runs)} runs over {len(families)} families; "
        f"tune = seed % {TUNE_EVERY} == 0, the rest held out",
    ]
    print("\n".join(header), flush=True)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    slots: queue.Queue[int] = queue.Queue()
    for k in range(args.jobs):
        slots.put(DOMAIN_BASE + k)

    def one(run: Run) -> tuple[Run, dict[str, float], float, float]:
        domain = slots.get()
        try:
            bag, synth_s = make_bag(run, args.work_dir)
            report, eval_s = evaluate(run, bag, args.work_dir, domain, args.deterministic)
        finally:
            slots.put(domain)
        return run, run_figures(report), synth_s, eval_s

    results: dict[str, dict[str, list]] = {}
    failures: list[str] = []
    start = time.monotonic()
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(one, r) for r in runs]
        for k, fut in enumerate(as_completed(futures), 1):
            try:
                run, row, synth_s, eval_s = fut.result()
            except RuntimeError as exc:
                failures.append(str(exc))
                print(f"[{k}/{len(runs)}] FAILED: {exc}", flush=True)
                continue
            results.setdefault(run.family.name, {}).setdefault(run.role, []).append((run, row))
            elapsed = time.monotonic() - start
            print(f"[{k}/{len(runs)} {elapsed:.0f} s]" + run_line(run, row, synth_s, eval_s), flush=True)
    lines = [*header, f"  {time.monotonic() - start:.0f} s in all", ""]
    for fam in families:
        got = results.get(fam.name, {})
        for role in got:
            got[role].sort(key=lambda item: item[0].seed)
        if got:
            lines += [*family_block(fam, got), ""]
    lines += summary(families, results)
    if failures:
        lines += ["", f"{len(failures)} runs failed:", *(f"  {f}" for f in failures)]
    text = "\n".join(lines)
    print("\n" + text, flush=True)
    if args.write:
        RESULT_FILE.parent.mkdir(parents=True, exist_ok=True)
        RESULT_FILE.write_text(text + "\n")
        print(f"wrote {RESULT_FILE}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
