"""StillsTracker on stills rendered from a real panorama with exact ground truth (issue 8):
a hand-held 360 degree pan in order, as the real rotation sets are."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from conftest import SOURCE_PANORAMA

from ptz_selfcal.camera.geometry import (
    intrinsic_matrix,
    ptz_rotation,
    rotation_angle,
    rotation_from_homography,
    transfer_error,
)
from ptz_selfcal.frontend.stills import (
    LinkEdge,
    StillsConfig,
    StillsTracker,
    linear_focal,
    link_rotations,
    lsh_index,
    overlap_fractions,
    path_rotations,
    points_inside,
)
from ptz_selfcal.status import TrackingState

SIZE = (320, 240)
F = 0.5 * SIZE[0] / np.tan(np.radians(30.0))  # 60 degrees of horizontal field
K = intrinsic_matrix(F, 0.5 * (SIZE[0] - 1) + 3.0, 0.5 * (SIZE[1] - 1) - 2.0)
N_STILLS = 18  # 20 degree steps: the last still overlaps the first


def hand_held(n: int = N_STILLS, seed: int = 3) -> np.ndarray:
    """World-to-camera rotations of a pan 15 degrees below the horizon (the textured ground, not the
    sky) with a hand's tilt and roll."""
    rng = np.random.default_rng(seed)
    pan = np.radians(360.0 * np.arange(n) / n + rng.uniform(-2.0, 2.0, n))
    tilt = np.radians(-15.0 + rng.uniform(-3.0, 3.0, n))
    roll = np.radians(rng.uniform(-2.0, 2.0, n))
    return np.array([ptz_rotation(p, t, r) for p, t, r in zip(pan, tilt, roll, strict=True)])


@pytest.fixture(scope="module")
def stills() -> tuple[list[np.ndarray], np.ndarray]:
    from ptz_selfcal.sim.render import build_panorama, render_view

    pano = build_panorama(cv2.imread(str(SOURCE_PANORAMA), cv2.IMREAD_GRAYSCALE))
    R = hand_held()
    return [render_view(pano, K, Ri, SIZE) for Ri in R], R


def true_h(R: np.ndarray, i: int, j: int) -> np.ndarray:
    """Still i -> still j (eq. 8, same K)."""
    return K @ R[j] @ R[i].T @ np.linalg.inv(K)


def track(images: list[np.ndarray], config: StillsConfig | None = None) -> tuple[StillsTracker, list]:
    tracker = StillsTracker(config or StillsConfig())
    return tracker, [tracker.track(image, 1.0, float(i)) for i, image in enumerate(images)]


def overlap_points(H: np.ndarray) -> np.ndarray:
    """Grid points of the source still that H maps inside the target still."""
    xs, ys = np.meshgrid(np.linspace(0, SIZE[0] - 1, 12), np.linspace(0, SIZE[1] - 1, 9))
    pts = np.column_stack([xs.ravel(), ys.ravel()])
    return pts[points_inside(H / np.cbrt(np.linalg.det(H)), pts, SIZE, 0.0)]


def test_pan_chains_every_still_and_closes_the_loop(stills):
    images, R = stills
    tracker, results = track(images)
    assert all(r.state is TrackingState.NEW_KEYFRAME for r in results)
    assert [r.keyframe_id for r in results] == list(range(N_STILLS))
    assert all(r.reference_id == 0 for r in results)
    links = [link for r in results for link in r.links]
    pairs = {(link.source_id, link.target_id) for link in links}
    assert {(i - 1, i) for i in range(1, N_STILLS)} <= pairs
    assert (0, N_STILLS - 1) in pairs  # the 360 degree loop, for the bundle adjustment
    # Every link's homography and inliers are right (rendered stills: exact ground truth; ORB corners
    # are located to about a pixel, a link of few inliers over a narrow overlap extrapolates worse).
    for link in links:
        H = true_h(R, link.source_id, link.target_id)
        err = transfer_error(link.H, H, overlap_points(H))
        assert np.median(err) < 1.0 and np.max(err) < 3.0, (link.source_id, link.target_id, err.max())
        moved = transfer_error(H, np.eye(3), link.source_points)  # |H x_s - x_s|: not the inlier error
        inlier_err = np.linalg.norm(
            cv2.perspectiveTransform(link.source_points.reshape(-1, 1, 2), H).reshape(-1, 2)
            - link.target_points,
            axis=1,
        )
        assert np.median(inlier_err) < 1.0 and np.median(moved) > 20.0  # matched across the motion
    # H_ref chains the pairwise homographies: reference -> still, the rotation it implies with the true
    # K drifts by a fraction of a degree per link (homographies chained, not adjusted).
    drift = [
        np.degrees(rotation_angle(rotation_from_homography(r.H_ref, K, K) @ R[0] @ R[r.frame_index].T))
        for r in results
    ]
    assert max(drift[:6]) < 0.75 and max(drift) < 2.5, np.round(drift, 2)
    # The choice of pairs: the previous still, the one before (60 degree field, 20 degree steps), the
    # loop, and before it closes the far stills a focal length within the range would overlap: far
    # fewer than every pair (153 for 18 stills).
    assert tracker.attempts < 3 * N_STILLS


def test_same_links_every_run(stills):
    images, _ = stills
    runs = [track(images[:8])[1] for _ in range(2)]
    summary = [[(k.source_id, k.target_id, k.inlier_count) for r in rs for k in r.links] for rs in runs]
    assert summary[0] == summary[1]
    np.testing.assert_array_equal(runs[0][-1].H_ref, runs[1][-1].H_ref)


def test_brute_force_matcher_closes_the_loop_too(stills):
    images, _ = stills
    _, results = track(images, StillsConfig(matcher="bf"))
    assert (0, N_STILLS - 1) in {(k.source_id, k.target_id) for r in results for k in r.links}


def test_without_loop_candidates_only_consecutive_links(stills):
    images, _ = stills
    _, results = track(images, replace(StillsConfig(), max_links=0, max_uncertain=0))
    pairs = {(k.source_id, k.target_id) for r in results for k in r.links}
    assert pairs == {(i - 1, i) for i in range(1, N_STILLS)}


def test_lost_still_is_skipped_and_the_next_chains_to_the_one_before(stills):
    images, R = stills
    blank = np.full_like(images[0], 128)  # no feature at all
    noise = np.random.default_rng(1).integers(0, 256, images[0].shape, np.uint8)  # features, no match
    sequence = [*images[:5], blank, noise, *images[5:8]]  # still 5 of the pan is frame 7
    tracker, results = track(sequence)
    assert results[5].state is TrackingState.TEXTURELESS and results[5].H_ref is None
    assert results[6].state is TrackingState.TRACKING_LOST and results[6].H_ref is None
    assert results[5].reference_id == results[6].reference_id == 0
    assert results[7].state is TrackingState.NEW_KEYFRAME
    chain = next(k for k in results[7].links if k.source_id == 4)  # the stored still before the blank
    np.testing.assert_array_equal(results[7].H_keyframe, chain.H)
    H = true_h(R, 4, 5)  # frame 4 -> frame 7 (stills 4 and 5 of the pan)
    assert np.max(transfer_error(chain.H, H, overlap_points(H))) < 3.0
    assert [s.id for s in tracker.stills] == [0, 1, 2, 3, 4, 7, 8, 9]


def test_a_blank_first_still_is_not_the_reference(stills):
    """A lens cap or a dark first shot: TEXTURELESS and forgotten; the first still with features is the
    reference the others chain to (a featureless reference would leave every later still lost)."""
    images, _ = stills
    tracker, results = track([np.zeros_like(images[0]), *images[:3]])
    assert results[0].state is TrackingState.TEXTURELESS and results[0].reference_id is None
    assert [r.state for r in results[1:]] == [TrackingState.NEW_KEYFRAME] * 3
    assert all(r.reference_id == 1 for r in results[1:])
    assert [s.id for s in tracker.stills] == [1, 2, 3]


def test_exhaustive_matches_every_pair(stills):
    images, _ = stills
    tracker, results = track(images[:5], StillsConfig(exhaustive=True))
    assert tracker.attempts == 4 * 5 // 2
    assert {(k.source_id, k.target_id) for k in results[-1].links} >= {(3, 4), (2, 4)}


def test_first_still_is_the_reference():
    tracker = StillsTracker()
    image = np.random.default_rng(0).integers(0, 255, (120, 160), np.uint8)
    r = tracker.track(image, 0.5, 1.0)
    assert r.state is TrackingState.NEW_KEYFRAME and r.reference_id == 0 and r.links == ()
    np.testing.assert_array_equal(r.H_ref, np.eye(3))
    # Points are full-resolution pixels: working pixel (x + 0.5) / scale - 0.5.
    points = tracker.stills[0].features.points
    assert points.max(axis=0)[0] > 160 and tracker.stills[0].size == (320.0, 240.0)


# --------------------------------------------------------------------------------------------------
# The prediction's pieces
# --------------------------------------------------------------------------------------------------
def test_linear_focal_recovers_f_from_rotation_homographies():
    size = (640.0, 480.0)
    Kc = intrinsic_matrix(700.0, 319.5, 239.5)
    R = [ptz_rotation(np.radians(p), np.radians(t)) for p, t in ((20, 1), (-15, 4), (8, -6))]
    H = np.array([Kc @ Ri @ np.linalg.inv(Kc) for Ri in R]) * np.array([2.0, -1.0, 0.5])[:, None, None]
    assert linear_focal(H, size) == pytest.approx(700.0, rel=1e-9)
    pan_only = np.array([Kc @ ptz_rotation(np.radians(20), 0) @ np.linalg.inv(Kc)])
    assert linear_focal(pan_only, size) == pytest.approx(700.0, rel=1e-9)
    assert linear_focal(np.empty((0, 3, 3)), size) == 640.0  # nothing to go on: the width
    assert linear_focal(np.eye(3)[None], size) == 640.0  # no rotation: undetermined


def test_overlap_fractions():
    size = (320.0, 240.0)
    half = np.array([[1.0, 0.0, 160.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    R180 = K @ ptz_rotation(np.pi, 0.0) @ np.linalg.inv(K)  # behind the camera
    R180 /= np.cbrt(np.linalg.det(R180))
    got = overlap_fractions(np.array([np.eye(3), half, R180]), size, size, 8)
    np.testing.assert_allclose(got, [1.0, 0.5, 0.0])
    # One size per old still: a still twice as wide overlaps the new one by half under the identity.
    sizes = np.array([[320.0, 240.0], [640.0, 240.0], [160.0, 120.0]])
    got = overlap_fractions(np.repeat(np.eye(3)[None], 3, axis=0), sizes, size, 8)
    np.testing.assert_allclose(got, [1.0, 0.5, 1.0])


def test_link_and_path_rotations_compose_along_the_fewest_links():
    Kc = intrinsic_matrix(F, *(0.5 * (np.array(SIZE) - 1)))
    R = hand_held(6, seed=1)  # world -> camera k
    rng = np.random.default_rng(2)
    rays = np.column_stack([rng.uniform(-0.3, 0.3, (20, 2)), np.ones(20)])

    def edge(a: int, b: int) -> LinkEdge:  # rays seen by camera a, projected into both cameras
        world = (R[a].T @ rays.T).T
        pa = (Kc @ R[a] @ world.T).T
        pb = (Kc @ R[b] @ world.T).T
        return LinkEdge(a, b, pa[:, :2] / pa[:, 2:], pb[:, :2] / pb[:, 2:])

    edges = [edge(0, 1), edge(1, 2), edge(2, 3), edge(3, 4), edge(4, 5), edge(0, 5)]  # a ring
    focals = np.array([0.9 * F, F])
    R_edge = link_rotations(edges, focals, Kc[:2, 2])
    for e, ed in enumerate(edges):
        np.testing.assert_allclose(R_edge[1, e], R[ed.target] @ R[ed.source].T, atol=1e-9)
    R_path, hops = path_rotations(edges, R_edge, 5)  # from still 5
    np.testing.assert_array_equal(hops, [1, 2, 3, 2, 1, 0])  # still 2 is 3 links away either way
    for k in range(6):
        np.testing.assert_allclose(R_path[1, k], R[k] @ R[5].T, atol=1e-9)


def test_lsh_index_is_deterministic_whatever_the_callers_opencv_rng_state():
    """The index's hash tables come from OpenCV's RNG: the same whatever state the caller's RNG is in.
    Core starts no thread, so building reseeds the calling thread's RNG (as lsh_index documents): the
    caller's draws after it are the same whatever they were before."""
    rng = np.random.default_rng(4)
    train = rng.integers(0, 256, (400, 32), np.uint8)
    query = np.clip(train[:200].astype(int) ^ (rng.random((200, 32)) < 0.02) * 255, 0, 255)
    query = query.astype(np.uint8)

    def draws() -> np.ndarray:
        out = np.zeros(8, np.float32)
        cv2.randu(out, 0.0, 1.0)
        return out

    matches, after = [], []
    for caller_seed in (1234, 99):
        cv2.setRNGSeed(caller_seed)
        index = lsh_index(train, 6, 16, 1, seed=0)
        after.append(draws())
        matches.append([(m.queryIdx, m.trainIdx) for p in index.knnMatch(query, k=2) for m in p])
    assert matches[0] == matches[1] and len(matches[0]) > 100
    np.testing.assert_array_equal(after[0], after[1])


def test_config_is_validated():
    for bad in ({"matcher": "flann"}, {"focal_samples": 4}, {"min_inliers": 3}):
        with pytest.raises(ValueError):
            StillsConfig(**bad)


def test_exact_neighbours_when_the_lsh_index_misses(stills):
    images, _ = stills
    coarse = replace(StillsConfig(), lsh=(1, 30, 0))  # one table of 30-bit keys: almost no collisions
    tracker, results = track(images[:6], coarse)
    assert all(r.state is TrackingState.NEW_KEYFRAME for r in results)
    assert tracker.attempts >= 2 * 5  # every chaining pair went to brute force after the index
