"""tools/evaluate.figures: issue 15's per-run figures from statuses, sigmas and the ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from ptz_selfcal.nodes.conversions import STATUS_TO_MSG
from ptz_selfcal.sim import metrics
from ptz_selfcal.status import CalibrationStatus
from ptz_selfcal.tools.evaluate import figures, format_figures

INIT, CAL, CONV = (STATUS_TO_MSG[s] for s in ("INITIALISING", "CALIBRATING", "CONVERGED"))


def test_figures_of_a_run() -> None:
    n, fps = 40, 4.0
    t = np.arange(n) / fps
    # a 1 deg/frame pan with a 0.6 deg/frame tilt: well posed at frame 4 (tilt 2.4 deg, pan 4 deg)
    R = metrics.rotations_from_encoders(np.radians(np.arange(n)), np.radians(0.6 * np.arange(n)))
    status = np.array([INIT] * 6 + [CAL] * 4 + [CONV] * 30)
    f_true = np.linspace(1000.0, 2000.0, n)
    f_est = f_true * np.r_[np.full(6, 1.3), np.full(4, 1.02), np.full(29, 1.001), 1.02]
    sigma_f = 0.0005 * f_est  # 0.05 %: frames 0.1 % off are outside 3 sigma
    err = metrics.focal_errors(f_est, f_true)
    fig = figures(t, status, sigma_f, f_est, f_true, R, metrics.warmup_frames(n), {"focal_error": err})
    assert (fig["well_posed_frame"], fig["first_calibrated_frame"]) == (4, 6)
    assert fig["first_calibrated_time_s"] == pytest.approx(1.5)
    assert fig["from_frame"] == 8  # well posed 1.0 s + 1 s = 2.0 s (frame 8) > the 4-frame warm-up
    assert fig["focal_error"]["count"] == n - 8 and fig["focal_error"]["median"] == pytest.approx(0.001)
    assert (fig["converged_frames"], fig["converged_off_1pct"]) == (30, 1)
    assert fig["converged_off_1pct_share"] == pytest.approx(1 / 30)
    assert fig["sigma3_coverage"] == pytest.approx(29 / 30)  # 0.1 % <= 3 x 0.05 %
    assert fig["run_level"]["z"] == pytest.approx(0.001 / 0.0005, rel=1e-3)
    text = format_figures({"figures": fig})
    assert "well posed: frame 4 (1.00 s); first calibrated: frame 6 (1.50 s)" in text
    assert "of them > 1 % off 1 (3.3 %)" in text


def test_figures_without_calibration_or_motion() -> None:
    n = 10
    R = metrics.rotations_from_encoders(np.zeros(n), np.zeros(n))
    status = np.full(n, STATUS_TO_MSG[CalibrationStatus.INITIALISING])
    f = np.full(n, 1000.0)
    fig = figures(np.arange(n) / 2.0, status, np.full(n, np.nan), f, f, R, 1, {})
    assert fig["well_posed_frame"] is None and fig["first_calibrated_frame"] is None
    assert fig["from_frame"] == 1 and fig["converged_frames"] == 0
    assert fig["converged_off_1pct_share"] is None and np.isnan(fig["sigma3_coverage"])
    assert "never" in format_figures({"figures": fig})
