"""mosaic/final.py: every frame through the run's solves, on exact homographies of known cameras.

The frames before the first solve carry the prior's K and an orientation computed with it, an earlier
solve a 3 % long K: after the re-derivation the frames of keyframes the final solve published, and those
of keyframes no solve published, have their true K and R (the homographies are exact, so the only error
left is arithmetic); a keyframe only the earlier solve published keeps that solve's calibration.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation, rotation_angle
from ptz_selfcal.mosaic.final import PublishedFrame, final_calibration, final_solve

SIZE = (640, 360)
CX, CY = 330.0, 172.0


def _truth(n: int, fixed_lens: bool = False) -> tuple[list[np.ndarray], list[np.ndarray]]:
    t = np.linspace(0.0, 1.0, n)
    pans, tilts = np.radians(35.0 * np.sin(2 * math.pi * t)), np.radians(6.0 * np.sin(3 * math.pi * t))
    f = np.full(n, 600.0) if fixed_lens else 600.0 * (1.0 + 1.5 * np.sin(math.pi * t) ** 2)
    K = [intrinsic_matrix(fj, CX, CY) for fj in f]
    R = [ptz_rotation(p, q) for p, q in zip(pans, tilts)]
    return K, R


def _published(K: list, R: list, first_solve: int, last_solve: int, keyframe_every: int = 6) -> list:
    """Frames before first_solve: the prior (f 520, centred pp, R from it, not calibrated); until
    last_solve an early solve (f 3 % long); then the final solve's exact K and R. H_j = K_j R_j K_0^-1."""
    prior = intrinsic_matrix(520.0, 319.5, 179.5)
    frames = []
    for j, (Kj, Rj) in enumerate(zip(K, R)):
        H, kf = Kj @ Rj @ np.linalg.inv(K[0]), j // keyframe_every
        if j < first_solve:
            pub = PublishedFrame(H, kf, prior, Rj @ ptz_rotation(0.01, 0.0), False, (0, -1.0))
        elif j < last_solve:
            K_early = Kj.copy()
            K_early[:2, :2] *= 1.03
            pub = PublishedFrame(H, kf, K_early, Rj @ ptz_rotation(0.002, 0.0), True, (3, 0.4))
        else:
            pub = PublishedFrame(H, kf, Kj, Rj, True, (5, 0.3))
        frames.append(pub)
    return frames


def _errors(out: list, K: list, R: list) -> tuple[float, float]:
    f_err = max(abs(o.K[0, 0] / k[0, 0] - 1.0) for o, k in zip(out, K))
    r_err = max(rotation_angle(o.R @ r.T) for o, r in zip(out, R))
    return f_err, r_err


def test_frames_before_the_first_solve_get_the_final_solves_calibration() -> None:
    K, R = _truth(60)
    frames = _published(K, R, 15, 40, keyframe_every=5)  # keyframes 0-2: no solve published them
    assert final_solve(frames) == (5, 0.3)
    out = final_calibration(frames, SIZE)
    assert all(o is not None for o in out)
    exact = [*range(15), *range(40, 60)]
    f_err, r_err = _errors([out[j] for j in exact], [K[j] for j in exact], [R[j] for j in exact])
    assert f_err < 1e-9 and r_err < 1e-9
    # principal point of the final solve (constant principal point model)
    assert max(abs(out[j].K[0, 2] - CX) + abs(out[j].K[1, 2] - CY) for j in exact) < 1e-6
    # the published values were off: the prior's 13 % in f
    assert _errors(frames[:15], K[:15], R[:15])[0] > 0.1
    # keyframes 3-7 only the earlier solve published: its calibration, transferred within the keyframe
    for j in range(15, 40):
        assert frames[out[j].anchor].solve == (3, 0.4)
        assert frames[out[j].anchor].keyframe_id == frames[j].keyframe_id
        assert abs(out[j].K[0, 0] / K[j][0, 0] - 1.03) < 1e-9


def test_anchors_keep_what_they_published_and_share_keyframes() -> None:
    K, R = _truth(60)
    frames = _published(K, R, 15, 40)
    out = final_calibration(frames, SIZE)
    for j in range(40, 60):
        assert out[j].anchor == j and out[j].K is not None
        assert np.array_equal(out[j].K, frames[j].K)
    # a frame whose keyframe the final solve also tracked against is anchored on that keyframe's frame
    for j in range(36, 40):  # keyframe 6 = frames 36..41: anchors 40 and 41
        assert frames[out[j].anchor].keyframe_id == frames[j].keyframe_id
    # no anchor shares keyframe 0: the closest-pointing anchor is used
    assert frames[out[0].anchor].solve == (5, 0.3)


def test_untracked_frames_and_runs_without_a_solve() -> None:
    K, R = _truth(30)
    frames = _published(K, R, 10, 10)
    frames[12] = PublishedFrame(None, 2, K[12], None, True, (5, 0.3))  # tracking lost
    out = final_calibration(frames, SIZE)
    assert out[12] is None and all(o is not None for i, o in enumerate(out) if i != 12)
    only_prior = _published(K, R, 30, 30)
    assert final_solve(only_prior) is None
    assert final_calibration(only_prior, SIZE) == [None] * 30


@pytest.mark.parametrize("fixed_lens", [True, False])
def test_a_fixed_lens_keeps_one_k(fixed_lens: bool) -> None:
    K, R = _truth(40, fixed_lens=fixed_lens)
    out = final_calibration(_published(K, R, 10, 10), SIZE)
    f = np.array([o.K[0, 0] for o in out])
    if fixed_lens:
        assert np.all(f == 600.0)  # the published K itself, not a transfer of it
    else:
        assert np.ptp(f) > 100.0
    f_err, r_err = _errors(out, K, R)
    assert f_err < 1e-9 and r_err < 1e-9
