"""lens/correction and lens/hook: the calibrator's online distortion state on exact synthetic correspondences.

Keyframes of a camera that pans, tilts and zooms (known K_i, R_i) see the same random rays through the
issue's lens (division model, 12% corner shift at the wide end shrinking as 1/f). The module must
recover each keyframe's coefficient, chain corrected keyframe homographies that match the true
undistorted ones, correct frames tracked against a keyframe, and publish plumb_bob D consistent with K.
"""

from __future__ import annotations

import numpy as np
import pytest

from ptz_selfcal.camera.distortion import (
    PLUMB_BOB,
    corner_radius,
    division_distort,
    division_lambda_for_corner_shift,
    max_distortion_difference,
    radial_displacement,
)
from ptz_selfcal.camera.geometry import (
    apply_homography,
    intrinsic_matrix,
    normalise_homography,
    pixel_grid,
    ptz_rotation,
)
from ptz_selfcal.frontend.homography import estimate_homography
from ptz_selfcal.lens.correction import LensCorrection, LensView
from ptz_selfcal.lens.hook import SessionLensHook
from ptz_selfcal.lens.interface import LensEstimate, LensModel
from ptz_selfcal.online.frames import FrameOutput

W, H = 1280, 720
H_IMG = H
PP = np.array([654.5, 349.5])  # principal point = distortion centre, off the image centre
F_WIDE = 1108.0
# keyframes: (pan deg, tilt deg, zoom)
POSES = [(0, 0, 1.0), (4, 1, 1.1), (8, 2, 1.25), (11, 0, 1.4), (14, -2, 1.6), (16, -1, 1.8), (18, 1, 2.0)]


def lam_issue(f: float) -> float:
    return division_lambda_for_corner_shift(0.12 * F_WIDE / f, W, H, f)


def camera(k: int) -> tuple[np.ndarray, np.ndarray]:
    pan, tilt, zoom = POSES[k]
    return intrinsic_matrix(F_WIDE * zoom, *PP), ptz_rotation(np.radians(pan), np.radians(tilt))


def true_H(k: int, j: int = 0) -> np.ndarray:
    """Undistorted pixels of keyframe j -> keyframe k."""
    (K_k, R_k), (K_j, R_j) = camera(k), camera(j)
    return normalise_homography(K_k @ R_k @ R_j.T @ np.linalg.inv(K_j))


def project(K: np.ndarray, R: np.ndarray, rays: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    x = (K @ R @ rays.T).T
    ok = x[:, 2] > 0
    u = x[:, :2] / x[:, 2:3]
    d = division_distort(u, lam, K[:2, 2], K[0, 0])
    ok &= np.all((d >= 0) & (d <= [W - 1, H - 1]), axis=1)
    return d, ok


def matches(k: int, j: int, lam, n: int = 200, noise: float = 0.0, seed: int = 0):
    """Distorted inliers of the same rays in keyframes k (newer) and j (older)."""
    rng = np.random.default_rng(seed + 31 * k + j)
    K_j, R_j = camera(j)
    u = rng.uniform([0, 0], [W - 1, H - 1], (30 * n, 2))
    rays = (R_j.T @ np.linalg.inv(K_j) @ np.column_stack([u, np.ones(len(u))]).T).T
    K_k, R_k = camera(k)
    a, ok_a = project(K_k, R_k, rays, lam(K_k[0, 0]))
    b, ok_b = project(K_j, R_j, rays, lam(K_j[0, 0]))
    ok = np.flatnonzero(ok_a & ok_b)[:n]
    return a[ok] + rng.normal(0, noise, (len(ok), 2)), b[ok] + rng.normal(0, noise, (len(ok), 2))


def tracked_H(k: int, j: int, lam) -> np.ndarray:
    """What the tracker reports: a homography fitted to DISTORTED points (keyframe j -> k)."""
    a, b = matches(k, j, lam, n=300, seed=99)
    return estimate_homography(b, a)


def feed(lam, noise: float = 0.0, with_focals: bool = True) -> LensCorrection:
    lens = LensCorrection(W, H, nominal_focal=F_WIDE)
    H_raw = np.eye(3)
    lens.add_keyframe(0, H_raw)
    for k in range(1, len(POSES)):
        H_raw = tracked_H(k, k - 1, lam) @ H_raw  # the tracker's chain on distorted points
        lens.add_keyframe(k, H_raw)
        for j in {k - 1, max(k - 2, 0)}:
            a, b = matches(k, j, lam, noise=noise)
            assert lens.add_match(k, j, a, b)
    for k in range(len(POSES)):
        K, _ = camera(k)
        if with_focals:
            lens.set_keyframe(k, K[0, 0], K[:2, 2])
        else:  # before calibration: nominal focal length, true centre
            lens.set_keyframe(k, F_WIDE, K[:2, 2])
    assert lens.update()
    return lens


def transfer_rms(H_est: np.ndarray, H_true: np.ndarray) -> float:
    grid = pixel_grid(W, H, 10)
    d = apply_homography(H_est, grid) - apply_homography(H_true, grid)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


@pytest.mark.parametrize("with_focals", [True, False])
def test_per_keyframe_distortion_recovered(with_focals: bool) -> None:
    lens = feed(lam_issue, with_focals=with_focals)
    snap = lens.snapshot
    assert snap is not None and snap.rms_px < 0.05 < snap.rms_uncorrected_px
    for k in range(len(POSES)):
        K, _ = camera(k)
        f = K[0, 0]
        lam_est = snap.kappa[k] * f * f  # pixel-space coefficient: independent of the focal used
        err = max_distortion_difference(("division", [lam_est], K), ("division", [lam_issue(f)], K), W, H)
        assert err < 0.05, (k, err)


def test_corrected_keyframe_homographies_match_the_truth() -> None:
    lens = feed(lam_issue)
    for k in range(1, len(POSES)):
        H_c = lens.keyframe_homography(k)
        assert H_c is not None
        assert transfer_rms(H_c, true_H(k)) < 0.05, k
    # the tracked chain on distorted points is far off: the correction is what self-calibration needs
    H_raw = np.eye(3)
    for k in range(1, len(POSES)):
        H_raw = tracked_H(k, k - 1, lam_issue) @ H_raw
    assert transfer_rms(H_raw, true_H(len(POSES) - 1)) > 5.0


def test_frames_near_a_keyframe_are_corrected_to_second_order() -> None:
    lens = feed(lam_issue)
    k = 3
    H_raw_k = lens.tracked_homography(k)
    # a frame 1 degree of pan and 3% zoom away from keyframe 3, tracked against it on distorted points
    pan, tilt, zoom = POSES[k]
    K_f = intrinsic_matrix(F_WIDE * zoom * 1.03, *PP)
    R_f = ptz_rotation(np.radians(pan + 1.0), np.radians(tilt))
    K_k, R_k = camera(k)
    rng = np.random.default_rng(5)
    u = rng.uniform([0, 0], [W - 1, H - 1], (400, 2))
    rays = (R_k.T @ np.linalg.inv(K_k) @ np.column_stack([u, np.ones(len(u))]).T).T
    a, ok_a = project(K_f, R_f, rays, lam_issue(K_f[0, 0]))
    b, ok_b = project(K_k, R_k, rays, lam_issue(K_k[0, 0]))
    ok = ok_a & ok_b
    H_raw_frame = estimate_homography(b[ok], a[ok]) @ H_raw_k
    H_true_frame = normalise_homography(K_f @ R_f @ camera(0)[1].T @ np.linalg.inv(camera(0)[0]))
    H_c = lens.frame_homography(H_raw_frame, k, f_frame=K_f[0, 0])
    assert H_c is not None
    assert transfer_rms(H_c, H_true_frame) < 1.0  # measured 0.45 px: the short refit's second-order error
    assert transfer_rms(H_raw_frame, H_true_frame) > 5.0
    # the NEW_KEYFRAME frame itself (not chained yet) is reached from the newest chained keyframe
    assert lens.frame_homography(H_raw_frame, 999) is not None


def test_plumb_bob_consistent_with_the_division_model_and_cached() -> None:
    lens = feed(lam_issue)
    for zoom in (1.0, 1.5, 2.0):
        K = intrinsic_matrix(F_WIDE * zoom, *PP)
        D = lens.plumb_bob(K)
        assert D[0] < 0.0 and np.all(D[2:] == 0.0)  # barrel
        err = max_distortion_difference(("plumb_bob", D, K), ("division", [lam_issue(K[0, 0])], K), W, H)
        assert err < 1.0, (zoom, err)
    cached = lens.plumb_bob_cached
    lens.plumb_bob(intrinsic_matrix(F_WIDE * 1.5, *PP))
    assert lens.plumb_bob_cached == cached


def test_no_distortion_gives_zero_coefficients_and_unchanged_homographies() -> None:
    lens = feed(lambda f: 0.0, noise=0.2)
    snap = lens.snapshot
    assert snap is not None
    for k in range(len(POSES)):
        K, _ = camera(k)
        err = max_distortion_difference(
            ("division", [snap.kappa[k] * K[0, 0] ** 2], K), ("division", [0.0], K), W, H
        )
        assert err < 0.5, (k, err)
    D = lens.plumb_bob(camera(0)[0])
    assert abs(D[0]) < 5e-3 and abs(D[1]) < 5e-3
    assert transfer_rms(lens.keyframe_homography(len(POSES) - 1), true_H(len(POSES) - 1)) < 1.0


def test_nothing_before_the_first_estimate_and_bad_matches_refused() -> None:
    lens = LensCorrection(W, H, nominal_focal=F_WIDE)
    assert not lens.ready() and lens.frame_homography(np.eye(3), 0) is None
    assert np.all(lens.plumb_bob(intrinsic_matrix(F_WIDE, *PP)) == 0.0)
    assert not lens.add_match(1, 1, np.zeros((20, 2)), np.zeros((20, 2)))
    assert not lens.add_match(1, 0, np.zeros((5, 2)), np.zeros((5, 2)))
    assert not lens.add_match(1, 0, np.full((20, 2), np.nan), np.zeros((20, 2)))
    assert not lens.update()  # nothing pending


class _StubKeyframe:
    def __init__(self, k: int) -> None:
        self.keyframe_id, self.K, self.H = k, camera(k)[0], None


class _StubCalibrator:
    """The calibrated keyframes (true K) a session would hold."""

    calibrated = True

    def __init__(self) -> None:
        self.reference_K = camera(0)[0]
        self.keyframes: list[_StubKeyframe] = []

    def frame_intrinsics(self, H):
        raise ValueError("not needed: every keyframe is solved")


class _StubSolver:
    """What SessionLensHook exchanges with online/keyframe_solver.KeyframeBundleSolver in joint mode."""

    def __init__(self) -> None:
        self.model: LensModel | None = None
        self.lens_estimate: LensEstimate | None = None

    def set_lens_model(self, model: LensModel | None) -> None:
        self.model = model


class _StubSession:
    """What SessionLensHook uses of online/session.CalibratorSession (lens/hook.LensSession)."""

    def __init__(self) -> None:
        self.calibrator = _StubCalibrator()
        self.solver = _StubSolver()
        self.matches: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self.homography_updates = 0

    def add_keyframe_matches(self, i, j, a, b, H=None) -> bool:
        self.matches.append((i, j, a, b, H))
        return True

    def replace_keyframe_homographies(self, homographies) -> None:
        for kf in self.calibrator.keyframes:
            if kf.keyframe_id in homographies:
                kf.H = homographies[kf.keyframe_id]
        self.homography_updates += 1


@pytest.mark.parametrize("hold", [True, False])
def test_session_hook_corrects_keyframes_frames_and_matches(hold: bool) -> None:
    # the calibration's principal point as the distortion centre (here exact)
    hook = SessionLensHook(
        lambda width: F_WIDE, centre_from_calibration=True, hold_keyframes=hold, joint_bundle=False
    )
    session = _StubSession()
    _, state = hook.frame(np.eye(3), "NEW_KEYFRAME", 0, "ref", W, H_IMG)
    assert state == "NEW_KEYFRAME"  # the reference keyframe passes
    H_raw = np.eye(3)
    errs = []
    for k in range(1, len(POSES)):
        H_raw = tracked_H(k, k - 1, lam_issue) @ H_raw
        session.calibrator.keyframes.append(_StubKeyframe(k))
        if k < 3:  # before the first estimate: uncorrected (held back as a plain frame if asked)
            out, state = hook.frame(H_raw, "NEW_KEYFRAME", k, "ref", W, H_IMG)
            assert state == ("TRACKING" if hold else "NEW_KEYFRAME") and np.allclose(out, H_raw)
        else:
            out, state = hook.frame(H_raw, "NEW_KEYFRAME", k, "ref", W, H_IMG)
            assert state == "NEW_KEYFRAME"
            errs.append((transfer_rms(out, true_H(k)), transfer_rms(H_raw, true_H(k))))
        for j in {k - 1, max(k - 2, 0)}:
            hook.matches(k, j, *matches(k, j, lam_issue))
        assert hook.work(session) == (k >= 2)  # the first estimate needs two keyframe matches
        assert not hook.work(session)  # nothing new: no work
    assert hook.held_keyframes == (2 if hold else 0)
    # NEW_KEYFRAME frames: the previous keyframe's chain and a refit over one keyframe step (large
    # here: 10-15% zoom per keyframe), then replaced by their own chains in the session
    for corrected, raw in errs:
        assert corrected < 0.1 * raw, errs
    for kf in session.calibrator.keyframes:
        assert transfer_rms(kf.H, true_H(kf.keyframe_id)) < 0.1
    # the bundle adjustment's matches arrive on corrected coordinates
    i, j, a, _, link = session.matches[-1]
    assert link is not None and transfer_rms(link, true_H(i, j)) < 0.1
    assert not np.allclose(a, matches(i, j, lam_issue)[0])
    D = hook.distortion(intrinsic_matrix(F_WIDE, *PP))
    assert D[0] < -0.1


def test_a_calibrated_session_never_gets_a_raw_homography_the_correction_cannot_reach() -> None:
    # after a restart on a restored tracker map the calibration (corrected coordinates) is restored but
    # the lens correction starts empty: the frame goes out without a homography (K from the zoom model)
    hook = SessionLensHook(lambda width: F_WIDE, joint_bundle=False)
    H_raw = tracked_H(3, 0, lam_issue)
    out, state = hook.frame(H_raw, "TRACKING", 3, "ref", W, H_IMG, calibrated=True)
    assert out is None and state == "TRACKING_LOST" and hook.uncorrectable_frames == 1
    # before any calibration the raw homography still passes (the session initialises on it)
    out, state = hook.frame(H_raw, "TRACKING", 3, "ref", W, H_IMG, calibrated=False)
    assert np.allclose(out, H_raw) and state == "TRACKING" and hook.uncorrectable_frames == 1


@pytest.mark.parametrize(
    ("adopted", "k1", "pinhole"),
    [
        (False, 0.0, True),  # found without distortion
        (None, 0.0, True),  # not decided and none published: calibrated on the raw chains
        (None, -0.1, False),  # not decided, but calibrated on corrected coordinates
        (True, -0.1, False),  # a real distortion: raw homographies would move f
        (True, -0.0003, True),  # adopted, but moves the corner by less than the tracker's noise
    ],
)
def test_a_restored_lens_keeps_raw_homographies_only_when_correcting_them_changes_nothing(
    adopted: bool | None, k1: float, pinhole: bool
) -> None:
    session = _StubSession()
    session.solver.distortion_adopted = adopted
    session.solver.noise_estimate = 0.12
    session.image_size = (W, H_IMG)
    K = intrinsic_matrix(F_WIDE, *PP)
    D = np.array([k1, 0.0, 0.0, 0.0, 0.0])
    session.last_good = FrameOutput("CONVERGED", K, D, None, 1.0, 1.0, 1.0, 0.1, 0, 3, "calibration")
    shift = radial_displacement(PLUMB_BOB, session.last_good.D, K, [corner_radius(K, W, H_IMG)])[0]
    assert (abs(shift) < 0.12) == (abs(k1) < 0.01)  # the cases are what they say
    hook = SessionLensHook(lambda width: F_WIDE, joint_bundle=False)
    hook.restored(session)
    assert hook.pinhole is pinhole
    out, state = hook.frame(tracked_H(3, 0, lam_issue), "TRACKING", 3, "ref", W, H_IMG, calibrated=True)
    assert (out is not None and state == "TRACKING") is pinhole


def test_joint_hook_sends_raw_matches_and_takes_the_adjusted_centre_once_it_is_certain() -> None:
    hook = SessionLensHook(lambda width: F_WIDE, centre_gate_px=2.0)
    session = _StubSession()
    hook.frame(np.eye(3), "NEW_KEYFRAME", 0, "ref", W, H_IMG)
    H_raw = np.eye(3)
    for k in range(1, 4):
        H_raw = tracked_H(k, k - 1, lam_issue) @ H_raw
        session.calibrator.keyframes.append(_StubKeyframe(k))
        hook.frame(H_raw, "NEW_KEYFRAME", k, "ref", W, H_IMG)
        hook.matches(k, k - 1, *matches(k, k - 1, lam_issue))
        hook.work(session)
    # the adjustment gets the lens model as a value: the correction at its current estimate
    view = session.solver.model
    assert isinstance(view, LensView) and view.correction is hook.lens
    assert view.snapshot is hook.lens.snapshot is not None
    i, j, a, _, _ = session.matches[-1]
    np.testing.assert_array_equal(a, matches(i, j, lam_issue)[0])  # raw points: the adjustment fits lam
    assert hook.centre is None and np.allclose(hook.lens.centre0, [(W - 1) / 2, (H_IMG - 1) / 2])
    # lam_guess and distort are the lens model: distort inverts the correction of the keyframe's points
    lam = view.lam_guess(2, F_WIDE)
    assert lam < 0.0 and abs(lam / lam_issue(F_WIDE) - 1.0) < 0.2
    pts = matches(2, 1, lam_issue)[0]
    np.testing.assert_allclose(view.distort(2, hook.lens.undistort_points(2, pts)), pts, atol=1e-6)
    # an uncertain estimate is not taken, a certain one is (and the coefficients are re-estimated)
    centre = np.array(PP)
    session.solver.lens_estimate = LensEstimate(centre + 5.0, np.array([3.0, 3.0]), {}, {})
    hook.matches(3, 2, *matches(3, 2, lam_issue))
    hook.work(session)
    assert hook.centre is None
    session.solver.lens_estimate = LensEstimate(centre, np.array([0.5, 0.5]), {}, {})
    updates = hook.lens.stats.updates
    assert hook.work(session)  # the centre moved: re-estimated without new matches
    assert hook.lens.stats.updates == updates + 1
    np.testing.assert_allclose(hook.centre, centre)
    np.testing.assert_allclose(hook.lens.centre0, centre)
    assert session.solver.model.snapshot is hook.lens.snapshot  # the next solves start from it
    assert not hook.work(session)  # the same estimate again: nothing to do
    # a new map: the old map's model is void at once (the next solve must not use it)
    hook.frame(np.eye(3), "NEW_KEYFRAME", 0, "new map", W, H_IMG)
    void = session.solver.model
    assert void.correction is hook.lens and void.snapshot is None
    assert void.lam_guess(2, F_WIDE) == 0.0 and void.keyframe_homography(2) is None
    np.testing.assert_array_equal(void.distort(2, pts), pts)


def test_new_keyframes_corrected_on_arrival_before_the_worker_chains_them() -> None:
    """Keyframes 4-6 arrive while the worker is behind (no update after keyframe 3): with their first
    links corrected on arrival (provisional_link, each on the previous one's provisional chain) their
    homographies are far better than from a long tracked span."""
    lens = LensCorrection(W, H, nominal_focal=F_WIDE)
    H_raw = {0: np.eye(3)}
    lens.add_keyframe(0, H_raw[0])
    for k in range(1, len(POSES)):
        H_raw[k] = tracked_H(k, k - 1, lam_issue) @ H_raw[k - 1]
    for k in range(1, 4):
        lens.add_keyframe(k, H_raw[k])
        for j in {k - 1, max(k - 2, 0)}:
            assert lens.add_match(k, j, *matches(k, j, lam_issue))
    for k in range(4):
        lens.set_keyframe(k, camera(k)[0][0, 0], PP)
    assert lens.update()
    late = range(4, len(POSES))
    for k in late:
        lens.add_keyframe(k, H_raw[k])
    stale = {k: transfer_rms(lens.frame_homography(H_raw[k], k), true_H(k)) for k in late}
    for k in late:
        assert lens.provisional_link(k, k - 1, *matches(k, k - 1, lam_issue))
    assert not lens.provisional_link(2, 1, *matches(2, 1, lam_issue))  # chained already
    fresh = {k: transfer_rms(lens.frame_homography(H_raw[k], k), true_H(k)) for k in late}
    # one provisional link is as good as a chained one; each further one carries its coefficient
    # over the zoom change (kappa ~ 1/f before the curve spans it) and adds error, still far below
    assert fresh[4] < 0.3, fresh
    for k in late:
        assert fresh[k] < 0.2 * stale[k], (fresh, stale)


def test_joint_estimate_replaces_the_coefficients_and_curve() -> None:
    lens = feed(lambda f: 0.9 * lam_issue(f))  # the estimator sees a lens 10% weaker ...
    focal = {k: camera(k)[0][0, 0] for k in range(len(POSES))}
    assert lens.set_joint(focal, {k: lam_issue(f) for k, f in focal.items()})  # ... the adjustment the truth
    assert not lens.set_joint({0: 1000.0}, {0: -0.2})  # one sample: no curve
    lens.update(force=True)
    snap = lens.snapshot
    for k, f in focal.items():
        np.testing.assert_allclose(snap.kappa[k] * f * f, lam_issue(f), rtol=1e-12)
        np.testing.assert_allclose(snap.lam_at(f), lam_issue(f), rtol=1e-3)
