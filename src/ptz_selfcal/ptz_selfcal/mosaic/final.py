"""Every frame of a run through the run's last solves, also the frames published before the first.

A frame's published K and R are those of the solve that was current when it went out: the prior's
before the first solve. Offline the solves are known, so each frame's K and R are re-derived through
its tracked homography from an anchor, a frame a solve published: for a frame j and an anchor a, both
tracked from the same reference, H_aj = H_j H_a^-1 maps a's pixels to j's, K_j is a's DIAC transferred
by H_aj (eq. 20) and R_j = (K_j^-1 H_aj K_a) R_a (section 3.3.1). The anchor is a frame tracked
against the same keyframe, of the latest solve that published one (H_aj is then two short tracked
links and R_a rests on that keyframe's refined pose; a chain of raw keyframe homographies would carry
the tracker's drift), the closest-pointing of them; a frame whose keyframe no solve published (the
frames before the first solve, mostly) is anchored on the closest-pointing frame of the final solve.
An anchor is its own anchor and keeps what it published.
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.camera.geometry import rotation_from_homography
from ptz_selfcal.camera.intrinsics import IntrinsicsModel, ParamMode
from ptz_selfcal.selfcal.transfer import intrinsics_from_transferred_diac

Array = NDArray[np.float64]


@dataclass(frozen=True)
class PublishedFrame:
    """What the calibrator published for one frame, and the tracker's homography behind it."""

    H: Array | None  # tracker reference -> frame, full-resolution pixels (None: not tracked)
    keyframe_id: int  # the keyframe the frame was tracked against
    K: Array
    R: Array | None  # relative to the calibration's reference (None: unknown)
    calibrated: bool  # published with a self-calibration (not the prior, not the zoom model)
    solve: Hashable  # what tells the solves apart (every frame of one solve shares it)


@dataclass(frozen=True)
class FinalFrame:
    """A frame's K and R under the final solve, and the anchor frame they were transferred from."""

    K: Array
    R: Array
    anchor: int


def final_solve(frames: Sequence[PublishedFrame]) -> Hashable | None:
    """The solve of the last calibrated, tracked frame with an orientation (None: no solve)."""
    for f in reversed(frames):
        if f.calibrated and f.H is not None and f.R is not None:
            return f.solve
    return None


def _model(anchors: Sequence[PublishedFrame], model: IntrinsicsModel) -> IntrinsicsModel:
    """A fixed lens publishes one K for every frame: transferring it would only add noise."""
    K0 = anchors[0].K
    if len(anchors) > 1 and all(np.allclose(a.K, K0, rtol=1e-12, atol=0.0) for a in anchors):
        return IntrinsicsModel(focal=ParamMode.CONSTANT)
    return model


def final_calibration(
    frames: Sequence[PublishedFrame],
    image_size: tuple[int, int],
    model: IntrinsicsModel | None = None,
) -> list[FinalFrame | None]:
    """Each frame's K and R from the run's solves (module doc); None for a frame without a homography
    or for every frame when no solve was published. `frames` in publication order, one reference."""
    out: list[FinalFrame | None] = [None] * len(frames)
    solve = final_solve(frames)
    if solve is None:
        return out
    usable = [i for i, f in enumerate(frames) if f.calibrated and f.H is not None and f.R is not None]
    latest = {frames[i].keyframe_id: frames[i].solve for i in usable}  # publication order: the last wins
    final = [i for i in usable if frames[i].solve == solve]
    model = _model([frames[i] for i in final], model or IntrinsicsModel())
    H_c = np.array([frames[i].H for i in usable], dtype=float)
    R_c = np.array([frames[i].R for i in usable], dtype=float)
    keyframes = np.array([frames[i].keyframe_id for i in usable])
    ids = {key: n for n, key in enumerate(dict.fromkeys(frames[i].solve for i in usable))}
    solve_id = np.array([ids[frames[i].solve] for i in usable])
    is_final = solve_id == ids[solve]
    # the final frame nearest the reference view gives the reference K that only ranks them by pointing
    nearest = int(np.argmax(np.where(is_final, np.trace(R_c, axis1=1, axis2=2), -np.inf)))
    K_near = frames[usable[nearest]].K
    K_ref = intrinsics_from_transferred_diac(np.linalg.inv(H_c[nearest]), K_near, model, image_size)
    tracked = [i for i, f in enumerate(frames) if f.H is not None]
    if not tracked:
        return out
    H = np.array([frames[i].H for i in tracked], dtype=float)
    K_rough = intrinsics_from_transferred_diac(H, K_ref, model, image_size)
    for row, i in enumerate(tracked):
        f = frames[i]
        if f.keyframe_id in latest:  # its keyframe's latest solve: a short link, a refined pose
            same = (keyframes == f.keyframe_id) & (solve_id == ids[latest[f.keyframe_id]])
        else:
            same = is_final
        candidates = np.nonzero(same)[0]
        R_rough = rotation_from_homography(H[row], K_ref, K_rough[row])
        # cos of the angle between the two orientations grows with trace(R_a R_rough^T)
        closeness = np.einsum("nij,ij->n", R_c[candidates], R_rough)
        a = int(candidates[int(np.argmax(closeness))])
        anchor = frames[usable[a]]
        if usable[a] == i:
            out[i] = FinalFrame(np.asarray(f.K, dtype=float), np.asarray(f.R, dtype=float), i)
            continue
        H_aj = H[row] @ np.linalg.inv(H_c[a])
        K = intrinsics_from_transferred_diac(H_aj, anchor.K, model, image_size)
        R = rotation_from_homography(H_aj, anchor.K, K) @ R_c[a]
        out[i] = FinalFrame(K, R, usable[a])
    return out
