"""The lens model chosen by evidence (bundle/selection.py through online/keyframe_solver.py): radial
distortion adopted on a distorted lens and not on an exact one, a principal point per keyframe when it
moves with zoom and a constant one when it does not, on exact keyframe matches with tracker-like noise."""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np
import pytest

from ptz_selfcal.bundle import bundle_adjust, pair_observations
from ptz_selfcal.bundle.selection import SELECTION_MARGIN, compare_models
from ptz_selfcal.camera.distortion import division_distort, division_undistort
from ptz_selfcal.camera.geometry import normalise_homography
from ptz_selfcal.camera.intrinsics import IntrinsicsModel, ParamMode
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.incremental import Keyframe
from ptz_selfcal.online.keyframe_solver import KeyframeBundleSolver, KeyframeMatchSet
from ptz_selfcal.sim.render import CameraProfile

SIZE = (960, 540)
NOISE_PX = 0.1  # px, about the tracker's keyframe-match noise


class _UncorrectedLens:
    """A lens model (lens/interface.LensModel) before any estimate: no distortion assumed."""

    def lam_guess(self, keyframe_id, f):
        return 0.0

    def distort(self, keyframe_id, pts):
        return np.asarray(pts, dtype=float)

    def keyframe_homography(self, keyframe_id):
        return None


def _sequence(corner_shift: float, pp_drift=(0.0, 0.0), n: int = 14, seed: int = 0):
    """A zooming camera (1x -> 3x) on a pan/tilt sweep: its keyframes' true homographies from keyframe
    0 (what a lens correction would give), and matches of pairs (i, i+1), (i, i+2) on DISTORTED
    pixels with Gaussian noise."""
    width, height = SIZE
    f_wide = 0.5 * width / math.tan(math.radians(27.0))
    profile = CameraProfile(
        width, height, 10.0, f_wide, corner_shift=corner_shift, pp_offset=(12.0, -8.0), pp_drift=pp_drift
    )
    state = profile.state(np.linspace(0.0, 5.0, n))
    K = np.array([state.K(i) for i in range(n)])
    R = np.array([state.R(i) for i in range(n)])
    rng = np.random.default_rng(seed)
    matches: OrderedDict[tuple[int, int], KeyframeMatchSet] = OrderedDict()
    for i in range(n):
        for j in (i + 1, i + 2):
            if j >= n:
                continue
            xd = rng.uniform((0, 0), (width - 1, height - 1), (400, 2))
            xu = division_undistort(xd, state.lam[i], state.pp[i], state.f[i])
            X = (np.linalg.inv(K[i]) @ np.column_stack([xu, np.ones(len(xu))]).T).T @ R[i]
            y = X @ (K[j] @ R[j]).T
            xj = division_distort(y[:, :2] / y[:, 2:], state.lam[j], state.pp[j], state.f[j])
            ok = (
                np.isfinite(xj).all(axis=1)
                & (xj >= 0).all(axis=1)
                & (xj <= (width - 1, height - 1)).all(axis=1)
            )
            k = np.flatnonzero(ok & (y[:, 2] > 0))[:150]
            noisy = NOISE_PX * rng.standard_normal((2, len(k), 2))
            matches[(j, i)] = KeyframeMatchSet(j, i, xj[k] + noisy[1], xd[k] + noisy[0])
    H = np.array([normalise_homography(K[j] @ R[j] @ R[0].T @ np.linalg.inv(K[0])) for j in range(n)])
    return H, K, np.einsum("nij,kj->nik", R, R[0]), matches, np.asarray(state.lam, dtype=float)


def _solve(corner_shift: float, pp_drift=(0.0, 0.0), seed: int = 0, hook: bool = True, **config):
    """One keyframe solve as the calibrator runs it: with the lens hook (raw points, the lens model
    chosen by the solve) or, hook False, as with estimate_distortion false (no lens model)."""
    H, K, _, matches, lam = _sequence(corner_shift, pp_drift, seed=seed)
    solver = KeyframeBundleSolver(SessionConfig(**config), matches)
    solver.reference_keyframe_id = 0
    solver.set_lens_model(_UncorrectedLens() if hook else None)
    keyframes = [Keyframe(j, H[j].copy()) for j in range(1, len(H))]
    result = solver(H, SIZE, IntrinsicsModel(), None, keyframes, 200)
    focal_error = float(np.max(np.abs(result.K[:, 0, 0] / K[:, 0, 0] - 1.0)))
    solver.true_lam = lam  # the test's truth beside the solver
    return solver, result, focal_error


@pytest.mark.parametrize("corner_shift", [0.12, 0.03])
@pytest.mark.parametrize("seed", [0, 1])
def test_a_distorted_lens_is_given_distortion(corner_shift, seed) -> None:
    solver, result, focal_error = _solve(corner_shift, seed=seed)
    assert solver.distortion_adopted is True, solver.distortion_delta_bic
    assert solver.distortion_delta_bic < -SELECTION_MARGIN
    assert result.bundle is not None
    assert np.all(np.abs(result.bundle.lam / solver.true_lam - 1.0) < 0.1)
    assert focal_error < 0.01


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_exact_lens_is_given_none_and_loses_nothing(seed) -> None:
    solver, result, focal_error = _solve(0.0, seed=seed)
    assert solver.distortion_adopted is False, solver.distortion_delta_bic
    assert result.bundle is not None and np.all(result.bundle.lam == 0.0)  # what the hook takes
    assert solver.lens_estimate is not None and all(v == 0.0 for v in solver.lens_estimate.lam.values())
    # the pinhole solution itself: as good as with distortion estimation off (which adjusts fewer
    # points per pair), within a tenth of its own 1-sigma
    _, reference, reference_error = _solve(0.0, seed=seed, hook=False)
    sigma = float(np.max(reference.sigma_f / reference.K[:, 0, 0]))
    assert focal_error <= reference_error + 0.1 * sigma


def test_forced_distortion_is_estimated_on_an_exact_lens_too() -> None:
    # distortion_selection false: the distortion term is always in the adjustment (the earlier behaviour)
    solver, result, _ = _solve(0.0, distortion_selection=False)
    assert solver.distortion_adopted is None
    assert result.bundle is not None and np.all(result.bundle.lam != 0.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_principal_point_moving_with_zoom_is_estimated_per_keyframe(seed) -> None:
    solver, _, focal_error = _solve(0.0, pp_drift=(24.0, -16.0), seed=seed)
    assert solver.pp_varying_adopted is True, solver.pp_delta_bic
    _, _, constant_error = _solve(0.0, pp_drift=(24.0, -16.0), seed=seed, ba_principal_point="constant")
    assert focal_error < constant_error


@pytest.mark.parametrize("seed", [0, 1])
def test_a_constant_principal_point_stays_constant(seed) -> None:
    solver, result, _ = _solve(0.0, seed=seed)
    assert solver.pp_varying_adopted is False, solver.pp_delta_bic
    assert np.ptp(result.K[:, 0, 2]) == 0.0 and np.ptp(result.K[:, 1, 2]) == 0.0


def test_compare_models_counts_the_extra_unknowns() -> None:
    # the same observations fitted by a model and by itself with k more unknowns that change nothing:
    # the criterion prefers the simpler by k ln n, and a failed richer fit never wins
    _, K, R, matches, _ = _sequence(0.0)
    pairs = [(m.other_keyframe_id, m.keyframe_id, m.other_points, m.points) for m in matches.values()]
    obs = pair_observations(pairs)
    model = IntrinsicsModel(principal_point=ParamMode.CONSTANT)
    fit = bundle_adjust(obs, K * [[[1.02, 1, 1], [1, 1.02, 1], [1, 1, 1]]], R, SIZE, model, analyse=False)
    n = 2 * fit.bundle.n_observations
    choice = compare_models(fit, fit, 3)
    assert not choice.richer and choice.delta_bic == pytest.approx(3 * math.log(n))
    failed = bundle_adjust(obs, K, R, SIZE, model, analyse=False)
    failed.cost = math.nan
    assert not compare_models(fit, failed, 1).richer
    assert compare_models(failed, fit, 1).richer
