"""A fixed lens's stills (a hand-held panorama set, in order) through the stills front end and the
calibrator session, and each still's K, D and orientation under the final solve.

The tracker's homography of a still (reference -> still) is a chain of free 8-parameter homographies,
each fitted to the narrow overlap of two stills, where its projective terms are the least constrained
part (frontend/stills.py). K^-1 H K of such a homography is not a rotation, and its nearest rotation
misses the angle between the stills (on a hand-held set by degrees per still, so a 360 degree set does
not close). The bundle adjustment (eq. 27) holds every still as a keyframe with its own rotation fitted
to the point matches with the loop-closing links: that is a still's orientation. A still the bounded
keyframe set no longer holds is placed through its direct link to a placed one (x_i ~ K R_ji x_j, eq.
3), never through the long chain.
"""

from __future__ import annotations

import dataclasses
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import rotation_from_homography
from ptz_selfcal.frontend.keyframe_links import KeyframeLink
from ptz_selfcal.frontend.stills import StillsConfig, StillsTracker
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput
from ptz_selfcal.online.lens_output import PlumbBob
from ptz_selfcal.online.session import CalibratorSession
from ptz_selfcal.status import HOMOGRAPHY_STATES, TrackingState

Array = NDArray[np.float64]

# image time between stills: a photographer's pace (the session's periods are in image seconds)
STILL_INTERVAL_S = 1.0
# solving steps after the last still for work still queued (each step empties the queue it finds)
FINAL_STEPS = 4


@dataclass
class StillsCalibration:
    """The placed stills (input order) with their K, plumb_bob D and reference -> still rotation."""

    indices: list[int] = field(default_factory=list)
    K: list[Array] = field(default_factory=list)
    D: Array = field(default_factory=lambda: np.zeros(5))
    R: list[Array] = field(default_factory=list)
    size: tuple[int, int] = (0, 0)  # full-resolution width, height
    status: str = "NONE"  # the final calibration's status
    message: str = ""
    skipped: Counter = field(default_factory=Counter)  # why the other stills are not placed


def fixed_lens_config(config: SessionConfig | None = None) -> SessionConfig:
    """The session's configuration for stills of one lens: its defaults with focal_model constant."""
    return dataclasses.replace(config or SessionConfig(), focal_model="constant")


def still_poses(
    held: Mapping[int, tuple[Array, Array]], links: Sequence[KeyframeLink], ids: Iterable[int]
) -> dict[int, tuple[Array, Array]]:
    """(K, R) of each still id of `ids` that can be placed: a still the solve holds (`held`: id ->
    (K, R), the adjusted poses) keeps its pose; another is placed through its direct link to a placed
    still, R_i = (K^-1 H_ji K) R_j with the placed still's K (one lens), breadth-first from the held
    stills, the link with most inliers first. Stills no link reaches are left out."""
    placed = {int(k): (np.asarray(K, float), np.asarray(R, float)) for k, (K, R) in held.items()}
    wanted = set(ids)
    adjacent: dict[int, list[tuple[int, Array, int]]] = {}
    for link in links:  # link.H maps source pixels to target pixels
        H = np.asarray(link.H, dtype=float)
        adjacent.setdefault(link.source_id, []).append((link.target_id, H, link.inlier_count))
        adjacent.setdefault(link.target_id, []).append((link.source_id, np.linalg.inv(H), link.inlier_count))
    queue = deque(sorted(placed))
    while queue:
        j = queue.popleft()
        K, R = placed[j]
        for i, H_ji, _ in sorted(adjacent.get(j, []), key=lambda a: -a[2]):
            if i in placed or i not in wanted:
                continue
            placed[i] = (K, rotation_from_homography(H_ji, K, K) @ R)
            queue.append(i)
    return {i: placed[i] for i in sorted(wanted) if i in placed}


def calibrate_stills(
    stills: Iterable[tuple[np.ndarray, float]],
    budget_s: float,
    tracker: StillsConfig | None = None,
    session: SessionConfig | None = None,
    progress: Callable[[int], None] | None = None,
) -> StillsCalibration:
    """Stills (grey working image, scale = working / full) through StillsTracker and CalibratorSession
    (fixed_lens_config), the solving half inline after each still with `budget_s` (the calibrator node's
    re-optimisation budget) on the schedule of `ptz-selfcal run --deterministic` (no clock in what is
    solved); then every still of the reference placed by still_poses. progress(i) after still i."""
    front = StillsTracker(tracker or StillsConfig())
    calibration = CalibratorSession(fixed_lens_config(session))
    out = StillsCalibration()
    links: list[KeyframeLink] = []
    tracked: dict[int, str] = {}  # tracker still id -> its tracking reference
    order: list[int] = []  # tracker still id -> input index
    for i, (image, scale) in enumerate(stills):
        w, h = round(image.shape[1] / scale), round(image.shape[0] / scale)
        if out.size == (0, 0):
            out.size = (w, h)
        elif out.size != (w, h):  # not the lens of the others (or turned): one K cannot hold both
            out.skipped["other image size"] += 1
            continue
        result = front.track(image, scale, i * STILL_INTERVAL_S)
        order.append(i)
        for link in result.links:  # what the tracker node publishes as KeyframeMatches
            calibration.add_keyframe_matches(
                link.target_id, link.source_id, link.target_points, link.source_points, link.H
            )
        links += result.links
        kid = -1 if result.keyframe_id is None else int(result.keyframe_id)
        ref = "" if result.reference_id is None else str(result.reference_id)
        frame = FrameInput(i * STILL_INTERVAL_S, result.H_ref, result.state.value, w, h, kid, ref)
        calibration.process(frame)
        calibration.step(budget_s, paced=False)
        if result.state in HOMOGRAPHY_STATES and result.H_ref is not None:
            tracked[len(order) - 1] = ref
        else:
            out.skipped["textureless" if result.state is TrackingState.TEXTURELESS else "not matched"] += 1
        if progress is not None:
            progress(i)
    for _ in range(FINAL_STEPS):
        if not calibration.pending_work:
            break
        calibration.step(budget_s, paced=False)
    snap = calibration.snapshot
    if snap is None or not snap.calibrated:
        out.skipped["no calibration"] += len(tracked)
        out.message = snap.message if snap is not None else "no still matched another"
        return out
    reference = calibration.reference_id or ""
    ids = [i for i, ref in tracked.items() if ref == reference]
    out.skipped["other reference"] += len(tracked) - len(ids)
    poses = still_poses({k: (K, R) for k, (_, K, R) in snap.keyframes.items()}, links, ids)
    out.skipped["not linked to the solve"] += len(ids) - len(poses)
    out.indices = [order[k] for k in poses]
    out.K = [K for K, _ in poses.values()]
    out.R = [R for _, R in poses.values()]
    if out.K:
        out.D = PlumbBob()(out.K[0], snap.shared_lam, out.size)
    out.status, out.message = str(snap.state), snap.message
    out.skipped = Counter({k: v for k, v in out.skipped.items() if v})
    return out
