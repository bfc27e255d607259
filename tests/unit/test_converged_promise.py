"""CONVERGED is a promise (DESIGN.md section 3): within every run >= 95 % of the CONVERGED frames have
|f - f_true| <= 3 sigma_f and none is more than 1 % off; a lens model that does not fit is reported as
MODEL_MISMATCH, never CONVERGED and never DEGENERATE_MOTION. Sessions over several motions and seeds
(the status policy, online/status_policy.py, was developed on seeds 0 and 1; 2 and 5 are held out)."""

from __future__ import annotations

import numpy as np
import pytest
from test_calibration_state import (
    HEIGHT,
    PP,
    WIDTH,
    encoded_sweep,
    feed,
    long_focal_sweep,
)

from ptz_selfcal.camera.distortion import (
    division_distort,
    division_lambda_for_corner_shift,
    division_undistort,
)
from ptz_selfcal.camera.geometry import apply_homography
from ptz_selfcal.camera.intrinsics import IntrinsicsModel
from ptz_selfcal.frontend.homography import homography_dlt
from ptz_selfcal.lens.hook import SessionLensHook
from ptz_selfcal.nodes.session_runner import RunnerConfig, SessionRunner
from ptz_selfcal.online import session as cs
from ptz_selfcal.selfcal.transfer import intrinsics_from_transferred_diac
from ptz_selfcal.status import CalibrationStatus as S

MOTIONS = {
    # name: (sweep, nominal field of view of the prior, whether CONVERGED must be reached)
    "sweep": (lambda: encoded_sweep(120), 50.0, True),
    "small_rotations": (lambda: encoded_sweep(120, pan_deg=15.0, tilt_deg=5.0), 50.0, True),
    "wide_pan_few_frames": (lambda: encoded_sweep(90, pan_deg=40.0, tilt_deg=10.0), 50.0, True),
    # the near-ambiguity of section 6.2: sigma_f stays near 0.4 %, CALIBRATING is the honest status
    "long_focal": (lambda: long_focal_sweep(160), 30.0, False),
}


def session_config(**kwargs) -> cs.SessionConfig:
    return cs.SessionConfig(**kwargs)


def converged_honesty(outs: list, K_true) -> tuple[int, float, float]:
    """(CONVERGED frames, share of them within 3 sigma_f, share of them more than 1 % off)."""
    rows = [
        (abs(o.K[1, 1] - K_true[j][1, 1]) / K_true[j][1, 1], o.sigma_f / o.K[1, 1])
        for j, o in enumerate(outs)
        if o.status == S.CONVERGED
    ]
    if not rows:
        return 0, 1.0, 0.0
    err, sigma = np.array(rows).T
    return len(rows), float(np.mean(err <= 3.0 * sigma)), float(np.mean(err > 0.01))


@pytest.mark.parametrize("seed", [0, 2, 5])
@pytest.mark.parametrize("motion", sorted(MOTIONS))
def test_converged_frames_are_within_three_sigma_and_one_percent(motion: str, seed: int) -> None:
    make, hfov, must_converge = MOTIONS[motion]
    K, H, zoom = make()
    outs = feed(cs.CalibratorSession(session_config(nominal_hfov_deg=hfov)), H, zoom, seed=seed)
    count, covered, off = converged_honesty(outs, K)
    assert off == 0.0, (motion, seed, count, off)
    assert covered >= 0.95, (motion, seed, count, covered)
    if must_converge:
        assert count >= 0.25 * len(outs), (motion, seed, count)
    else:
        assert outs[-1].status == S.CALIBRATING and "1-sigma of f" in outs[-1].message


def distorted_zoom_sweep(n: int = 120, corner_shift: float = 0.12):
    """encoded_sweep's zooming lens with barrel distortion (division model about the principal point,
    corner shift `corner_shift` of the half-diagonal at f = 1000 px, shrinking as 1/f)."""
    K, H, zoom = encoded_sweep(n)
    f = K[:, 1, 1]
    lam = np.array(
        [division_lambda_for_corner_shift(corner_shift * 1000.0 / fi, WIDTH, HEIGHT, fi) for fi in f]
    )
    return K, H, zoom, lam


def feed_distorted_zoom(
    session: cs.CalibratorSession, K, H, zoom, lam, every: int = 8, seed: int = 0
) -> list:
    """feed() with the keyframe matches on distorted pixels (each keyframe its own coefficient); the
    frames' homographies are the undistorted truth."""
    rng = np.random.default_rng(seed)
    pp = np.array(PP)
    outs = []
    for j in range(len(H)):
        kf = j % every == 0
        state = "NEW_KEYFRAME" if kf else "TRACKING"
        frame = cs.FrameInput(j / 30.0, H[j], state, WIDTH, HEIGHT, j - j % every, "ref", float(zoom[j]))
        outs.append(session.process(frame))
        if kf and j >= every:
            b = j - every
            xa = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], (300, 2))
            xu = division_undistort(xa, lam[j], pp, K[j][1, 1])
            xb = division_distort(apply_homography(H[b] @ np.linalg.inv(H[j]), xu), lam[b], pp, K[b][1, 1])
            ok = np.isfinite(xb).all(axis=1) & (xb >= 0).all(axis=1) & (xb < (WIDTH, HEIGHT)).all(axis=1)
            session.add_keyframe_matches(j, b, xa[ok] + rng.normal(0, 0.2, (ok.sum(), 2)), xb[ok])
        if kf:
            session.step(0.5, paced=False)
    return outs


@pytest.mark.parametrize("corner_shift", [0.12, 0.04])
def test_a_distorted_lens_without_distortion_estimation_is_a_model_mismatch(corner_shift: float) -> None:
    """Barrel distortion not modelled (estimate_distortion off): the matches fit one homography per pair
    far worse than the tracker's noise. The status says MODEL_MISMATCH with the reason, never CONVERGED
    and never DEGENERATE_MOTION (the motion is fine: the same sweep undistorted converges)."""
    K, H, zoom, lam = distorted_zoom_sweep(corner_shift=corner_shift)
    session = cs.CalibratorSession(session_config(nominal_hfov_deg=50.0))
    outs = feed_distorted_zoom(session, K, H, zoom, lam)
    statuses = {o.status for o in outs}
    assert S.CONVERGED not in statuses and S.DEGENERATE_MOTION not in statuses, statuses
    assert outs[-1].status == S.MODEL_MISMATCH and "tracker's noise" in outs[-1].message
    # the same sweep without distortion: the check lets it converge
    plain = feed_distorted_zoom(
        cs.CalibratorSession(session_config(nominal_hfov_deg=50.0)), K, H, zoom, 0 * lam
    )
    assert plain[-1].status == S.CONVERGED


def _raw_homography(H_true_ab, lam_a, lam_b, f_a, f_b, pp, rng, count: int = 400):
    """What a tracker fits between two distorted images: one homography (DLT) to distorted points of
    image a and their images in b (undistorted with a's coefficient, mapped, distorted with b's)."""
    xa = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], (count, 2))
    xb = division_distort(apply_homography(H_true_ab, division_undistort(xa, lam_a, pp, f_a)), lam_b, pp, f_b)
    ok = np.isfinite(xb).all(axis=1) & (xb >= 0).all(axis=1) & (xb < (WIDTH, HEIGHT)).all(axis=1)
    return homography_dlt(xa[ok], xb[ok])


def feed_distorted_pipeline(K, H, zoom, lam, every: int = 8, noise: float = 0.1, seed: int = 0) -> list:
    """A distorted zoom lens through the calibrator's own path with distortion estimation (the node's:
    lens/hook.SessionLensHook in front of the session, nodes/session_runner's inline solves): every frame's
    homography is fitted on DISTORTED points (chained through the keyframes, as the tracker's), the
    keyframe matches are distorted pixels with noise."""
    rng = np.random.default_rng(seed)
    pp = np.array(PP)
    f = K[:, 1, 1]
    session = cs.CalibratorSession(session_config(nominal_hfov_deg=50.0))
    hook = SessionLensHook(session.config.nominal_focal)
    session.set_distortion(hook.distortion)
    runner = SessionRunner(session, RunnerConfig(0.5, 1.0, 60.0), lens=hook)
    runner.start(inline=True)
    H_raw_kf: dict[int, np.ndarray] = {0: np.eye(3)}
    outs, last_kf = [], 0
    for j in range(len(H)):
        runner.solve_inline()
        kf = j % every == 0
        local = H[j] @ np.linalg.inv(H[last_kf])
        H_raw = _raw_homography(local, lam[last_kf], lam[j], f[last_kf], f[j], pp, rng) @ H_raw_kf[last_kf]
        H_raw = np.eye(3) if j == 0 else H_raw / H_raw[2, 2]
        state = "NEW_KEYFRAME" if kf else "TRACKING"
        H_c, state = hook.frame(H_raw, state, j - j % every, "ref", WIDTH, HEIGHT, runner.view.calibrated)
        frame = cs.FrameInput(j / 30.0, H_c, state, WIDTH, HEIGHT, j - j % every, "ref", float(zoom[j]))
        outs.append(runner.process(frame)[0])
        if kf and j > 0:
            b = last_kf
            xa = rng.uniform([0, 0], [WIDTH - 1, HEIGHT - 1], (300, 2))
            xu = division_undistort(xa, lam[j], pp, f[j])
            xb = division_distort(apply_homography(H[b] @ np.linalg.inv(H[j]), xu), lam[b], pp, f[b])
            ok = np.isfinite(xb).all(axis=1) & (xb >= 0).all(axis=1) & (xb < (WIDTH, HEIGHT)).all(axis=1)
            hook.matches(
                j,
                b,
                xa[ok] + rng.normal(0, noise, (ok.sum(), 2)),
                xb[ok] + rng.normal(0, noise, (ok.sum(), 2)),
            )
        if kf:
            H_raw_kf[j], last_kf = H_raw, j
    runner.solve_inline()
    return outs


@pytest.mark.parametrize("seed", [0, 3])
def test_a_distorted_zoom_lens_estimated_on_the_way_keeps_the_converged_promise(seed: int) -> None:
    """12 % barrel at the wide end, estimated by the default path (raw tracked homographies corrected by
    the lens correction, the adjustment's radial term on the raw matches): the frames published CONVERGED
    are within 3 of their sigma_f and within 1 %; the exact data let the calibration converge (an honest
    sigma of a lens model that fits is small, and its two routes to f agree by the end). The frames near
    a keyframe are CONVERGED to the end; the others, a transfer of several per cent of zoom away through a
    corrected homography, are CALIBRATING by their own sigma_f (the transfer's error and the homography's)
    and say so."""
    K, H, zoom, lam = distorted_zoom_sweep()
    outs = feed_distorted_pipeline(K, H, zoom, lam, seed=seed)
    count, covered, off = converged_honesty(outs, K)
    last = outs[-20:]
    assert any(o.status == S.CONVERGED for o in last), (seed, count, [o.message for o in last])
    assert all(o.status == S.CONVERGED or "this frame's 1-sigma" in o.message for o in last), (
        seed,
        [(o.status, o.message) for o in last],
    )
    assert off == 0.0, (seed, count, off)
    assert covered >= 0.95, (seed, count, covered)


def patch_fitted(H, corrupt, every: int = 8, seed: int = 0, points: int = 30, patch=(200.0, 110.0)):
    """H with the frames in `corrupt` replaced by what a tracker fits when its surviving tracks are a small
    patch of the image (a soft scene's last corners): the keyframe -> frame homography by DLT on `points`
    tracks with 0.2 px noise inside one patch-sized part of the keyframe, exact there, extrapolated
    over the rest of the frame. Keyframes keep their exact homographies."""
    rng = np.random.default_rng(seed)
    out = np.array(H, dtype=float)
    for j in corrupt:
        k = j - j % every
        assert j != k
        local = H[j] @ np.linalg.inv(H[k])
        corner = rng.uniform([100.0, 100.0], [WIDTH - 100.0 - patch[0], HEIGHT - 100.0 - patch[1]])
        xk = corner + rng.uniform([0.0, 0.0], patch, (points, 2))
        xj = apply_homography(local, xk) + rng.normal(0.0, 0.2, (points, 2))
        out[j] = homography_dlt(xk, xj) @ H[k]
    return out


@pytest.mark.parametrize("seed", [0, 2])
def test_a_frame_whose_homography_is_fitted_on_a_small_patch_is_not_converged_off_target(seed: int) -> None:
    """The soft-panorama failure: tracks on a few weak corners of one part of the image fit the frame's
    homography to their noise, but it is far off over the rest of the frame, and the frame's K transferred
    through it (eq. 20) with it. Its sigma_f must say so (the part of H no rotating, zooming camera
    produces), so it is never published CONVERGED more than 1 % off, and the CONVERGED frames keep their
    3 sigma coverage; the exactly tracked frames around it still converge."""
    K, H, zoom = encoded_sweep(120)
    corrupt = [j for j in range(60, 120) if j % 8 in (3, 6)]
    H_bad = patch_fitted(H, corrupt, seed=seed)
    # the data are a test of it: some of these frames' transferred f is more than 1 % off
    model, size = IntrinsicsModel(), (WIDTH, HEIGHT)
    local = [(H_bad[j] @ np.linalg.inv(H[j - j % 8]), K[j - j % 8], K[j]) for j in corrupt]
    f_bad = [
        intrinsics_from_transferred_diac(h, Kk, model, size)[1, 1] / Kj[1, 1] - 1.0 for h, Kk, Kj in local
    ]
    assert max(abs(e) for e in f_bad) > 0.01, f_bad
    outs = feed(cs.CalibratorSession(session_config(nominal_hfov_deg=50.0)), H_bad, zoom, seed=seed)
    count, covered, off = converged_honesty(outs, K)
    assert off == 0.0, (seed, count, off)
    assert covered >= 0.95, (seed, count, covered)
    clean = [o for j, o in enumerate(outs) if j >= 60 and j not in corrupt]
    assert sum(o.status == S.CONVERGED for o in clean) >= 0.5 * len(clean), [o.status for o in clean]
