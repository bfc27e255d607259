"""Radial distortion through the real nodes with the shipped defaults (no parameter file): a short
distorted synth bag -> `ptz-selfcal eval` -> the lens model chosen by evidence has distortion, the
published plumb_bob D matches the true division-model lens (DESIGN.md section 7 metric) and the focal
length is not thrown off by the distortion (paper section 7); the same camera without distortion gets
D = 0 and loses no accuracy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from ptz_selfcal.camera.distortion import DIVISION, PLUMB_BOB, max_distortion_difference
from ptz_selfcal.nodes.conversions import MSG_TO_STATUS
from ptz_selfcal.status import CALIBRATED, CalibrationStatus
from ptz_selfcal.tools import evaluate

PTZ = [sys.executable, "-m", "ptz_selfcal.tools.cli"]
REPO = Path(__file__).resolve().parents[2]
PANORAMA = REPO / "bags" / "source" / "examplepano.jpg"
DOMAIN = 163


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(DOMAIN))
    return env


def _calibrated_frames(tmp_path: Path, corner_shift: float, seed: int = 0):
    """Synth bag -> eval with the shipped defaults; per calibrated frame: distortion error (px), focal
    error, whether past the first third of the frames; the CONVERGED frames' focal errors."""
    bag = tmp_path / "bag"
    # 480x270, zoom 1x -> 2x -> 1x, barrel distortion moving the corner by corner_shift of the
    # half-diagonal (12 %: 33 px) at the wide end, shrinking as 1/f. The shipped prior does not know the
    # lens: at 56 deg its f is 7.9 % short, the principal point is 11.4 px off centre, its D = 0 is
    # 37.6 px off the 12 % lens at frame 0; a 16x lens behind synth's nonlinear, lagged, noisy zoom
    # encoder.
    synth = [*PTZ, "synth", str(PANORAMA), str(bag), "--frames", "90", "--width", "480", "--height", "270"]
    synth += ["--pan-amplitude", "20", "--tilt-amplitude", "5", "--zoom-max", "2"]
    synth += ["--distortion", str(corner_shift), "--hfov", "56", "--pp-offset", "9", "-7"]
    synth += ["--lens-ratio", "16", "--seed", str(seed)]
    subprocess.run([*synth, "--quiet"], check=True, env=_env(), timeout=120)
    out = tmp_path / "report"
    cmd = [*PTZ, "eval", str(bag), "--out-dir", str(out), "--quiet", "--no-plots", "--deterministic"]
    proc = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    assert report["coverage"] == 1.0
    data = evaluate.read_output_bag(out / "output_bag")
    errors, focal, converged, settled, sigma = [], [], [], [], []
    stamps = sorted(data.frame_calibration)
    for i, stamp in enumerate(stamps):
        fc = data.frame_calibration[stamp]
        status = MSG_TO_STATUS[fc.status]
        if status not in CALIBRATED:
            continue
        info, gt = data.camera_info[stamp], data.gt_camera_info[stamp]
        K, K_true = np.reshape(info.k, (3, 3)), np.reshape(gt.k, (3, 3))
        est = (PLUMB_BOB, list(info.d), K)
        if gt.distortion_model == DIVISION:
            truth = (DIVISION, [gt.d[0]], K_true)
        else:
            truth = (PLUMB_BOB, list(gt.d) or [0.0] * 5, K_true)
        errors.append(max_distortion_difference(est, truth, 480, 270))
        focal.append(abs(K[0, 0] / K_true[0, 0] - 1.0))
        sigma.append(fc.sigma_f / fc.fx if fc.sigma_f > 0 else 0.0)  # published 1-sigma of f, relative
        settled.append(i >= len(stamps) // 3)
        if status == CalibrationStatus.CONVERGED:
            converged.append(focal[-1])
    report["calibrated_sigma"] = np.array(sigma)
    return report, np.array(errors), np.array(focal), np.array(converged), np.array(settled)


def test_published_distortion_matches_the_lens(tmp_path: Path) -> None:
    report, errors, focal, converged, settled = _calibrated_frames(tmp_path, 0.12)
    # per calibrated frame (before the calibration the nodes publish D = 0 from the prior: a 33 px
    # error at the wide end, so every calibrated frame must carry the estimated lens); the lens model
    # is the shipped default's choice: distortion
    assert report["diagnostics"].get("distortion_updates", 0) > 0
    # bounds at about 3x the worst of synth seeds 0..4 (this bag is seed 0). The p90 is over the frames
    # after the first third: the first calibrated frames come before the distortion's first estimate
    # (calibrated from all frames as soon as the motion is well posed)
    assert len(errors) >= 20, report["status_counts"]
    assert np.median(errors) < 0.5, np.round(errors, 2)
    assert np.percentile(errors[settled], 90) < 1.1, np.round(errors, 2)
    assert np.median(focal) < 0.007, np.round(focal, 4)  # ~30% and more without correction
    # The promise: no CONVERGED frame more than 1 % off, and every settled calibrated frame's error
    # within 3 of its published sigma. On this 12 % lens the sigma carries the lens model's gap (LM on
    # the corrected homographies against the raw-point adjustment), which stays above the CONVERGED
    # bound over these 90 frames: the run is CALIBRATING, with an honest sigma, not CONVERGED.
    assert max(converged, default=0.0) < 0.01, np.round(converged, 4)
    sigma = report["calibrated_sigma"]
    assert np.all(sigma[settled] > 0) and np.all(focal[settled] <= 3.0 * sigma[settled]), np.round(
        np.c_[focal[settled], sigma[settled]], 4
    )


def test_an_undistorted_lens_gets_no_distortion_and_loses_nothing(tmp_path: Path) -> None:
    """The same camera without distortion: the evidence shows none, every calibrated frame's D is
    zero (a spurious estimate would publish a small nonzero one), and f is as accurate as with
    estimate_distortion false (eval --deterministic on seeds 0..2: focal median 0.034 / 0.015 /
    0.010 % with the defaults, 0.046 / 0.018 / 0.016 % with distortion estimation off)."""
    report, errors, focal, converged, _ = _calibrated_frames(tmp_path, 0.0)
    assert len(errors) >= 20, report["status_counts"]
    assert np.median(errors) == 0.0 and np.max(errors) < 0.5, np.round(errors, 3)
    # bounds at about 3x the worst of seeds 0..2 (this bag is seed 0)
    assert np.median(focal) < 0.001, np.round(focal, 5)
    assert len(converged) >= 10 and max(converged) < 0.01, np.round(converged, 4)
