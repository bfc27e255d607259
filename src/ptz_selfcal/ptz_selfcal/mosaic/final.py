"""Every frame of a run through the run's final calibration, also the frames published before it.

A frame's published K and R are those of the solve that was current when it went out: the prior's
before the first solve, an early solve's while calibrating. Offline the last accepted solve is known,
so each frame's K and R are re-derived from it through the frame's tracked homography. The solve is
read off the frames it published ("anchors"): for a frame j and an anchor a, both tracked from the
same reference, H_aj = H_j H_a^-1 maps a's pixels to j's, K_j is a's DIAC transferred by H_aj (eq. 20)
and R_j = (K_j^-1 H_aj K_a) R_a (section 3.3.1). The anchor is one tracked against the same keyframe
when there is one (H_aj is then two short tracked links, no chain of keyframes between them),
otherwise the one pointing closest; an anchor is its own anchor and keeps what it published.
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
    """Each frame's K and R under the final solve (module doc); None for a frame without a homography
    or for every frame when no solve was published. `frames` in publication order, one reference."""
    out: list[FinalFrame | None] = [None] * len(frames)
    solve = final_solve(frames)
    if solve is None:
        return out
    index = [
        i
        for i, f in enumerate(frames)
        if f.calibrated and f.solve == solve and f.H is not None and f.R is not None
    ]
    anchors = [frames[i] for i in index]
    model = _model(anchors, model or IntrinsicsModel())
    H_a = np.array([a.H for a in anchors], dtype=float)
    R_a = np.array([a.R for a in anchors], dtype=float)
    keyframes = np.array([a.keyframe_id for a in anchors])
    # the anchor nearest the reference view gives the reference K that only ranks anchors by pointing
    nearest = int(np.argmax(np.trace(R_a, axis1=1, axis2=2)))
    K_near = anchors[nearest].K
    K_ref = intrinsics_from_transferred_diac(np.linalg.inv(H_a[nearest]), K_near, model, image_size)
    tracked = [i for i, f in enumerate(frames) if f.H is not None]
    if not tracked:
        return out
    H = np.array([frames[i].H for i in tracked], dtype=float)
    K_rough = intrinsics_from_transferred_diac(H, K_ref, model, image_size)
    for row, i in enumerate(tracked):
        f = frames[i]
        R_rough = rotation_from_homography(H[row], K_ref, K_rough[row])
        same = keyframes == f.keyframe_id
        candidates = np.nonzero(same)[0] if same.any() else np.arange(len(anchors))
        # cos of the angle between the two orientations grows with trace(R_a R_rough^T)
        closeness = np.einsum("nij,ij->n", R_a[candidates], R_rough)
        a = int(candidates[int(np.argmax(closeness))])
        if index[a] == i:
            out[i] = FinalFrame(np.asarray(f.K, dtype=float), np.asarray(f.R, dtype=float), i)
            continue
        H_aj = H[row] @ np.linalg.inv(H_a[a])
        K = intrinsics_from_transferred_diac(H_aj, anchors[a].K, model, image_size)
        R = rotation_from_homography(H_aj, anchors[a].K, K) @ R_a[a]
        out[i] = FinalFrame(K, R, index[a])
    return out
