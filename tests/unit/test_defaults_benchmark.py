"""benchmarks/defaults.py: the tune / hold-out plan and the verdicts beside issue 15's targets."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "defaults.py"
_SPEC = importlib.util.spec_from_file_location("defaults_benchmark", _PATH)
assert _SPEC is not None and _SPEC.loader is not None
defaults = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = defaults  # dataclasses look their module up
_SPEC.loader.exec_module(defaults)


def _row(**kw: float) -> dict[str, float]:
    row = {
        "well_posed_frame": 5.0, "well_posed_s": 2.5, "first_calibrated_frame": 6.0,
        "first_calibrated_s": 3.0,
        "latency_s": 0.5, "latency_allowed_s": 1.5, "focal_median": 0.001, "focal_p90": 0.004, "pp_px": 1.0,
        "distortion_px": 0.2, "converged": 20, "converged_off": 0, "coverage_within": 1.0, "z": 0.5,
        "run_error": 0.0005, "calibrated_frames": 25, "frames": 30,
    }  # fmt: skip
    row.update(kw)
    return row


def _verdicts(rows: list[dict[str, float]]) -> dict[str, str]:
    return {t[0]: t[4] for t in defaults.judge(rows)}


def test_plan_splits_seeds_and_panoramas() -> None:
    runs = defaults.plan(defaults.FAMILIES, 10)
    assert len(runs) == 10 * len(defaults.FAMILIES) >= 80  # at least 8 families
    paper = [r for r in runs if r.family.name == "paperA"]
    assert [r.seed for r in paper if r.role == "tune"] == [0, 3, 6, 9]
    assert {r.panorama for r in paper if r.role == "tune"}.isdisjoint(
        {r.panorama for r in paper if r.role == "held"}
    )
    assert len({r.key for r in runs}) == len(runs)  # one cached bag per run
    assert "--seed" in paper[1].synth_args and paper[1].synth_args[-2:] == ("--pan-centre", "97")


def test_every_target_is_judged_on_the_worst_run() -> None:
    assert set(_verdicts([_row(), _row()]).values()) == {"", "PASS"}
    bad = _verdicts([_row(), _row(focal_p90=0.007, converged_off=1, coverage_within=0.9, z=4.0)])
    assert bad["focal error p90"] == "FAIL" and bad["focal error median"] == "PASS"
    assert bad["CONVERGED frames > 1 % off"] == "FAIL"
    assert bad["3 sigma coverage within runs"] == "FAIL"
    assert bad["3 sigma coverage across seeds"] == "FAIL"  # 1 of 2 runs beyond 3 sigma
    late = _verdicts([_row(latency_s=1.6)])
    assert late["calibrated after well posed"] == "FAIL"
    never = _verdicts(
        [_row(latency_s=math.inf, first_calibrated_s=math.inf, z=math.nan, coverage_within=math.nan)]
    )
    assert never["calibrated after well posed"] == "FAIL" and never["3 sigma coverage within runs"] == "n/a"
    unposed = _verdicts([_row(well_posed_frame=math.nan, well_posed_s=math.nan, latency_s=math.nan)])
    assert unposed["calibrated after well posed"] == "n/a"
