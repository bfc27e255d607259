"""Front end for a set of stills (hand-held panorama photographs taken in order) instead of video.

HomographyTracker's KLT expects small motion between frames; stills overlap by a fraction of the image.
StillsTracker detects ORB features once per still (points kept in full-resolution pixels) and chooses
which earlier stills to match instead of matching every pair:

1. the previous still (then the one before it): the homography chains the new still to the reference
   (H_ref = H_prev->new H_ref,prev, the inter-image homographies of section 2.2);
2. every other earlier still that the predicted infinite homography K R_new R_j^T K^-1 (eq. 8) maps
   over at least `min_overlap` of the new still: this closes the loop of a 360 degree set, which the
   bundle adjustment needs; only the new still's features predicted inside still j are matched;
3. when neither of the first two stills matches, every earlier still, newest first (relocalisation).

The prediction: K has square pixels, the principal point at the centre and f from every link so far
(the linear method of section 3.3.2); each link's rotation is fitted to its inlier rays (orthogonal
Procrustes) and the rotations are chained along the shortest path of links (fewest hops), so once a
loop is closed the stills near both of its ends are a few links apart. Before that the path round the
loop is long and the focal length poorly known (pan-only pairs barely separate it from the rotation
angle, the near-ambiguity of section 6.2.1), so stills `uncertain_hops` or more links away are
predicted over a range of focal lengths as well. A product of raw homographies round a 360 degree
set is useless as a prediction (their projective terms are the least constrained part of a narrow
overlap).

Each successful match (ratio test, MAGSAC + LM homography from frontend.features) is a KeyframeLink; every
still is a keyframe. Same TrackResult interface as HomographyTracker, ids are still indices. With the LSH
matcher, track() reseeds the calling thread's OpenCV RNG (lsh_index): the indices are then the same on
every run.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptz_selfcal.camera.geometry import apply_homography
from ptz_selfcal.camera.intrinsics import image_centre
from ptz_selfcal.frontend.features import Descriptors, robust_homography, usac_params
from ptz_selfcal.frontend.keyframe_links import KeyframeLink
from ptz_selfcal.frontend.tracker import TrackResult
from ptz_selfcal.selfcal.linear import normalise_homographies, normalising_transform
from ptz_selfcal.status import TrackingState

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]


@dataclass(frozen=True)
class StillsConfig:
    n_features: int = 1000  # ORB features per still
    orb_levels: int = 3  # pyramid levels: a fixed lens, stills of one scale need few
    fast_score: bool = True  # rank ORB corners by FAST score (Harris: fewer loop-closing matches)
    max_width: int | None = None  # detect at most this wide (None: as given)
    ratio: float = 0.8  # Lowe's ratio test
    matcher: str = "lsh"  # "lsh" (FLANN LSH index per still, seeded) or "bf" (brute-force Hamming)
    lsh: tuple[int, int, int] = (6, 16, 1)  # LSH hash tables, key bits, multi-probe level
    threshold: float = 2.0  # MAGSAC inlier threshold, full-resolution pixels
    max_iterations: int = 2000
    min_inliers: int = 20
    sequential: int = 2  # earlier stills tried in order for the chaining link
    min_overlap: float = 0.1  # predicted fraction of an earlier still inside the new one
    max_links: int = 4  # near stills matched besides the chaining one (most predicted overlap first)
    max_uncertain: int = 2  # far stills (a loop not closed yet) matched per new still
    margin: float = 0.1  # crop margin around the predicted overlap, fraction of the image width
    max_prediction_error: float = 0.25  # fitted vs predicted corner transfer, fraction of the width
    grid: int = 8  # overlap prediction grid (grid x grid points)
    focal_range: float = 1.4  # far stills: f from estimate / range to estimate * range
    focal_samples: int = 15  # odd: the estimate itself is one of them
    uncertain_hops: int = 5  # stills this many links away are predicted over the focal range
    rotation_points: int = 20  # inlier rays per link for its rotation
    exhaustive: bool = False  # match every earlier still instead (the reference the choice is measured by)

    def __post_init__(self) -> None:
        if self.matcher not in ("lsh", "bf"):
            raise ValueError(f"matcher must be 'lsh' or 'bf', not {self.matcher!r}")
        if self.focal_samples < 1 or self.focal_samples % 2 == 0:
            raise ValueError(f"focal_samples must be odd and >= 1, not {self.focal_samples}")
        if self.min_inliers < 4 or self.rotation_points < 2:  # a homography needs 4 points
            raise ValueError("min_inliers must be >= 4 and rotation_points >= 2")


@dataclass(eq=False)
class Still:
    id: int
    features: Descriptors  # points in full-resolution pixels
    size: tuple[float, float]  # full-resolution width, height
    H_ref: Array  # reference -> this still, full resolution, unit determinant
    index: cv2.FlannBasedMatcher | None = None


@dataclass(frozen=True)
class LinkEdge:
    """A link as the rotation prediction keeps it (link_rotations, path_rotations): a few inliers."""

    source: int  # positions in StillsTracker.stills
    target: int
    source_points: Array  # (rotation_points, 2) inliers, full-resolution pixels
    target_points: Array


@dataclass
class _Pair:
    link: KeyframeLink
    matches: int


@dataclass
class StillsTracker:
    config: StillsConfig = field(default_factory=StillsConfig)
    # process CPU seconds per stage: features, descriptor matching (with the LSH indices), robust
    # homographies, and the overlap prediction that chooses the pairs
    cpu: dict[str, float] = field(
        default_factory=lambda: {"detect": 0.0, "match": 0.0, "fit": 0.0, "predict": 0.0}
    )

    def __post_init__(self) -> None:
        score = cv2.ORB_FAST_SCORE if self.config.fast_score else cv2.ORB_HARRIS_SCORE
        self._orb = cv2.ORB_create(
            nfeatures=self.config.n_features, nlevels=self.config.orb_levels, scoreType=score
        )
        self._stills: list[Still] = []
        self._edges: list[LinkEdge] = []
        self._link_H: list[Array] = []  # every link's homography (unit determinant): the focal estimate
        self._index = -1
        self._reference: int | None = None
        self.attempts = 0  # pairs matched so far (the cost the choice of pairs saves)

    @property
    def stills(self) -> list[Still]:
        return self._stills

    def detect(self, image: np.ndarray, scale: float) -> Descriptors:
        """ORB features of a working-resolution image, points in full-resolution pixels."""
        limit = self.config.max_width
        if limit is not None and image.shape[1] > limit:
            s = limit / image.shape[1]
            image = cv2.resize(image, (limit, round(image.shape[0] * s)), interpolation=cv2.INTER_AREA)
            scale *= s
        keypoints, descriptors = self._orb.detectAndCompute(image, None)
        if not keypoints:
            return Descriptors(np.empty((0, 2), np.float32), None)
        points = cv2.KeyPoint_convert(keypoints).reshape(-1, 2).astype(np.float32)
        return Descriptors((points + 0.5) / scale - 0.5, descriptors)

    def track(self, image: np.ndarray, scale: float, stamp: float | None = None) -> TrackResult:
        """One still (working resolution, `scale` = working / full). Returns a NEW_KEYFRAME result with
        its links, TRACKING_LOST when no earlier still matches or TEXTURELESS when it has fewer than
        min_inliers features (the still is then forgotten: a blank first still is no reference)."""
        self._index += 1
        i = self._index
        c0 = time.process_time()
        features = self.detect(image, scale)
        size = (image.shape[1] / scale, image.shape[0] / scale)
        self.cpu["detect"] += time.process_time() - c0
        new = Still(i, features, size, np.eye(3))
        if len(features.points) < self.config.min_inliers:
            # a blank, dark or blurred still: nothing to match it by, and not a reference for the rest
            return TrackResult(
                TrackingState.TEXTURELESS, i, stamp, None, None, None, self._reference, 0, 0, np.nan
            )
        if not self._stills:
            self._add(new, [])
            self._reference = i
            return TrackResult(TrackingState.NEW_KEYFRAME, i, stamp, np.eye(3), np.eye(3), i, i, 0, 0, 0.0)
        tried: set[int] = set()
        if self.config.exhaustive:  # every earlier still; the newest that matches chains
            pairs = [(p, s) for s in self._stills[::-1] if (p := self._match(s, new, None)) is not None]
            chain = pairs[0] if pairs else None
        else:
            chain = self._chain(new, self._stills[-self.config.sequential :][::-1], tried)
            if chain is None:  # relocalise: every other earlier still, newest first
                chain = self._chain(new, [s for s in self._stills[::-1] if s.id not in tried], tried)
        if chain is None:
            return TrackResult(
                TrackingState.TRACKING_LOST, i, stamp, None, None, None, self._reference, 0, 0, np.nan
            )
        pair, source = chain
        new.H_ref = _unit_det(pair.link.H @ source.H_ref)
        if self.config.exhaustive:
            links = [p.link for p, _ in pairs]
        else:
            links = [pair.link, *self._loop_links(new, pair.link, tried)]
        links.sort(key=lambda link: link.source_id)
        self._add(new, links)
        n_in, rms = pair.link.inlier_count, pair.link.rms_transfer_error
        result = (TrackingState.NEW_KEYFRAME, i, stamp, new.H_ref, pair.link.H, i, self._reference)
        return TrackResult(*result, n_in, pair.matches, rms, tuple(links))

    def _add(self, still: Still, links: list[KeyframeLink]) -> None:
        if self.config.matcher == "lsh" and still.features.descriptors is not None:
            c0 = time.process_time()
            still.index = lsh_index(still.features.descriptors, *self.config.lsh)
            self.cpu["match"] += time.process_time() - c0
        self._stills.append(still)
        position = {s.id: k for k, s in enumerate(self._stills)}
        self._edges += [
            self._edge(link, position[link.source_id], position[link.target_id]) for link in links
        ]
        self._link_H += [link.H for link in links]

    def _edge(self, link: KeyframeLink, source: int, target: int) -> LinkEdge:
        """A link as the prediction keeps it: `rotation_points` of its inliers, evenly spread."""
        keep = np.linspace(0, link.inlier_count - 1, self.config.rotation_points).round().astype(np.intp)
        return LinkEdge(source, target, link.source_points[keep], link.target_points[keep])

    def _chain(self, new: Still, candidates: list[Still], tried: set[int]) -> tuple[_Pair, Still] | None:
        """The first candidate that matches the new still without a prediction."""
        for still in candidates:
            tried.add(still.id)
            pair = self._match(still, new, None)
            if pair is None and still.index is not None:  # LSH missed: exact neighbours before giving up
                pair = self._match(still, new, None, exact=True)
            if pair is not None:
                return pair, still
        return None

    def focal(self, size: tuple[float, float]) -> float:
        """Rough focal length (full-resolution pixels) from every link so far; the image width when
        the links do not determine it."""
        return linear_focal(np.array(self._link_H).reshape(-1, 3, 3), size)

    def predict(self, new: Still, chain: KeyframeLink) -> tuple[Array, Array, IntArray]:
        """Predicted homographies every earlier still -> the new one (chained by `chain`) for each
        focal length sample: (samples,), (samples, n, 3, 3) and the hops of each still's path."""
        cfg = self.config
        n = len(self._stills)
        source = next(k for k, s in enumerate(self._stills) if s.id == chain.source_id)
        edges = [*self._edges, self._edge(chain, source, n)]
        f0 = self.focal(new.size)
        half = cfg.focal_samples // 2
        focals = f0 * cfg.focal_range ** (np.arange(-half, half + 1) / max(half, 1))
        centre = np.array(image_centre(new.size))
        R_edge = link_rotations(edges, focals, centre)  # (samples, edges, 3, 3): source -> target
        R, hops = path_rotations(edges, R_edge, n)  # (samples, n + 1, 3, 3): new still -> each still
        K = np.array([[[f, 0.0, centre[0]], [0.0, f, centre[1]], [0.0, 0.0, 1.0]] for f in focals])
        Kinv = np.linalg.inv(K)[:, None]
        H = K[:, None] @ np.transpose(R[:, :n], (0, 1, 3, 2)) @ Kinv  # eq. 8: still j -> new
        return focals, H, hops[:n]

    def _loop_links(self, new: Still, chain: KeyframeLink, tried: set[int]) -> list[KeyframeLink]:
        """Links to the earlier stills predicted to overlap the new one, most overlap first."""
        cfg = self.config
        rest = np.array([k for k, s in enumerate(self._stills) if s.id not in tried], np.intp)
        if not len(rest):
            return []
        c0 = time.process_time()
        focals, H, hops = self.predict(new, chain)
        H = H[:, rest]
        sizes = np.tile([self._stills[k].size for k in rest], (len(focals), 1))
        overlap = overlap_fractions(H.reshape(-1, 3, 3), sizes, new.size, cfg.grid)
        overlap = overlap.reshape(len(focals), len(rest))
        mid = len(focals) // 2
        near = hops[rest] < cfg.uncertain_hops
        # Near stills: predicted with the estimated f (its error is small over a few links); the crop to
        # the predicted overlap and the check against the prediction apply.
        chosen = [(k, _unit_det(H[mid, k])) for k in np.flatnonzero(near & (overlap[mid] >= cfg.min_overlap))]
        chosen.sort(key=lambda kh: -overlap[mid, kh[0]])
        # Far stills: any f of the range; the f closest to the estimate first; every feature, no check.
        hit = overlap >= cfg.min_overlap  # (samples, stills)
        distance = np.where(hit, np.abs(np.arange(len(focals)) - mid)[:, None], len(focals)).min(axis=0)
        far = np.flatnonzero(~near & hit.any(axis=0))
        far = far[np.lexsort((-overlap.max(axis=0)[far], distance[far]))][: cfg.max_uncertain]
        self.cpu["predict"] += time.process_time() - c0
        links = []
        for k, H_pred in [*chosen[: cfg.max_links], *((k, None) for k in far)]:
            pair = self._match(self._stills[rest[k]], new, H_pred)
            if pair is not None:
                links.append(pair.link)
        return links

    def _match(self, old: Still, new: Still, H_pred: Array | None, exact: bool = False) -> _Pair | None:
        """Ratio-test matches old -> new (only new features predicted inside old with H_pred), robust
        homography; None when it fails or disagrees with the prediction."""
        cfg = self.config
        self.attempts += 1
        c0 = time.process_time()
        query = np.arange(len(new.features.points))
        if H_pred is not None:  # the new still's features predicted to fall inside the old one
            inside = points_inside(
                np.linalg.inv(H_pred), new.features.points, old.size, cfg.margin * old.size[0]
            )
            query = query[inside]
        ia, ib = ratio_match(old, new.features, query, cfg.ratio, exact)
        c1 = time.process_time()
        self.cpu["match"] += c1 - c0
        if len(ia) < cfg.min_inliers:
            return None
        a, b = old.features.points[ia], new.features.points[ib]
        params = usac_params(cfg.threshold, 0, cfg.max_iterations, 0.999)
        fit = robust_homography(a, b, params, cfg.min_inliers, 20)
        self.cpu["fit"] += time.process_time() - c1
        if fit is None:
            return None
        H = _unit_det(fit.H)
        if H_pred is not None:  # a loop closure on repeated texture must agree with the chain
            corners = _corners(old.size)
            err = np.linalg.norm(apply_homography(H, corners) - apply_homography(H_pred, corners), axis=1)
            if err.max() > cfg.max_prediction_error * old.size[0]:
                return None
        link = KeyframeLink(old.id, new.id, H, a[fit.inliers].astype(float), b[fit.inliers].astype(float),
                            fit.rms)  # fmt: skip
        return _Pair(link, len(ia))


# --------------------------------------------------------------------------------------------------
# Helpers (vectorised over stills / points)
# --------------------------------------------------------------------------------------------------
def lsh_index(
    descriptors: np.ndarray, tables: int = 6, key_bits: int = 12, probe: int = 1, seed: int = 0
) -> cv2.FlannBasedMatcher:
    """A FLANN LSH index over one still's binary descriptors (built once per still), the same on every
    run. FLANN draws the hash tables' bits from OpenCV's RNG of the calling thread (cv::theRNG), which
    has no seed parameter and whose state cannot be read back: that RNG is seeded with `seed` here, so a
    caller that draws from OpenCV's RNG itself builds the index on a thread of its own."""
    params = {"algorithm": 6, "table_number": tables, "key_size": key_bits, "multi_probe_level": probe}
    cv2.setRNGSeed(seed)
    index = cv2.FlannBasedMatcher(params, {"checks": 32})
    index.add([descriptors])
    index.train()  # the tables are drawn here; queries draw nothing
    return index


def ratio_match(
    old: Still, new: Descriptors, query: IntArray, ratio: float, exact: bool = False
) -> tuple[IntArray, IntArray]:
    """Indices (in old, in new) of the new still's `query` features whose nearest neighbour among the
    old still's descriptors passes Lowe's ratio test: through the old still's LSH index when it has
    one (approximate neighbours) unless `exact` (brute force)."""
    empty = np.empty(0, np.intp), np.empty(0, np.intp)
    train = old.features.descriptors
    if train is None or new.descriptors is None or len(train) < 2 or len(query) < 2:
        return empty
    desc = new.descriptors[query]
    if old.index is not None and not exact:
        pairs = old.index.knnMatch(desc, k=2)
    else:
        pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(desc, train, k=2)
    rows = np.array(
        [(p[0].queryIdx, p[0].trainIdx, p[0].distance, p[1].distance) for p in pairs if len(p) == 2],
        dtype=float,
    ).reshape(-1, 4)
    good = rows[rows[:, 2] < ratio * rows[:, 3]]
    return good[:, 1].astype(np.intp), query[good[:, 0].astype(np.intp)]


def _unit_det(H: Array) -> Array:
    """Scale a homography to determinant 1 (sign kept): a rotation's K R K^-1 then maps points in front
    of the camera to a positive third coordinate."""
    return H / np.cbrt(np.linalg.det(H))


def _corners(size: tuple[float, float]) -> Array:
    w, h = size
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])


def linear_focal(H: Array, size: tuple[float, float], bounds: tuple[float, float] = (0.2, 20.0)) -> float:
    """Constant focal length of a rotating camera with square pixels and the principal point at the
    centre from (n, 3, 3) inter-image homographies (section 3.3.2, linear): with the DIAC
    w* = K K^T = diag(f^2, f^2, 1) in centred coordinates, H w* H^T = w* for a unit-determinant H,
    linear in a = f^2: a (h1 h1^T + h2 h2^T - diag(1, 1, 0)) = diag(0, 0, 1) - h3 h3^T (h_k: columns),
    solved by least squares over every H. Width-normalised; falls back to the width (about 53 degrees
    of horizontal field) outside bounds (fractions of the width) or without homographies."""
    w = size[0]
    if not len(H):
        return w
    Hn = normalise_homographies(H, normalising_transform(image_centre(size), w))
    h1, h2, h3 = Hn[:, :, 0], Hn[:, :, 1], Hn[:, :, 2]
    outer = np.einsum("ni,nj->nij", h1, h1) + np.einsum("ni,nj->nij", h2, h2)
    A = outer - np.diag([1.0, 1.0, 0.0])
    B = np.diag([0.0, 0.0, 1.0]) - np.einsum("ni,nj->nij", h3, h3)
    den = float(np.sum(A * A))
    a = float(np.sum(A * B)) / den if den > 0 else -1.0
    if not bounds[0] ** 2 <= a <= bounds[1] ** 2:
        return w
    return float(np.sqrt(a)) * w


def link_rotations(edges: list[LinkEdge], focals: Array, centre: Array) -> Array:
    """(samples, edges, 3, 3) rotation of each link (source camera -> target camera) for each focal
    length: the orthogonal Procrustes fit of its inlier rays K^-1 x (x_t ~ K R x_s, eq. 3)."""
    a = np.array([e.source_points for e in edges]) - centre  # (edges, m, 2)
    b = np.array([e.target_points for e in edges]) - centre
    f = focals[:, None, None, None]
    ra = np.concatenate([a[None] / f, np.ones((len(focals), *a.shape[:2], 1))], axis=-1)
    rb = np.concatenate([b[None] / f, np.ones((len(focals), *b.shape[:2], 1))], axis=-1)
    ra /= np.linalg.norm(ra, axis=-1, keepdims=True)
    rb /= np.linalg.norm(rb, axis=-1, keepdims=True)
    U, _, Vt = np.linalg.svd(np.einsum("semi,semj->seij", rb, ra))  # R = argmax tr(R^T rb ra^T)
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def path_rotations(edges: list[LinkEdge], R_edge: Array, n: int) -> tuple[Array, IntArray]:
    """Rotations from still `n` (the newest) to every still along the fewest links (breadth-first),
    for every focal sample: (samples, n + 1, 3, 3) R_n->k, with the hop count of each path (n + 1,)."""
    adjacent: list[list[tuple[int, int, bool]]] = [[] for _ in range(n + 1)]
    for e, edge in enumerate(edges):
        adjacent[edge.source].append((edge.target, e, True))
        adjacent[edge.target].append((edge.source, e, False))
    R = np.broadcast_to(np.eye(3), (len(R_edge), n + 1, 3, 3)).copy()
    hops = np.full(n + 1, -1, np.intp)
    hops[n] = 0
    queue = deque([n])
    while queue:
        k = queue.popleft()
        for other, e, forward in adjacent[k]:
            if hops[other] >= 0:
                continue
            hops[other] = hops[k] + 1
            # edge e maps its source camera to its target camera; going backwards inverts it
            step = R_edge[:, e] if forward else np.transpose(R_edge[:, e], (0, 2, 1))
            R[:, other] = step @ R[:, k]
            queue.append(other)
    return R, hops


def overlap_fractions(H: Array, size_old: ArrayLike, size_new: tuple[float, float], grid: int) -> Array:
    """(n,) fraction of a grid over each old still (size_old: one (w, h) or one per still) that H
    (old -> new, unit determinant) maps in front of the new camera and inside its image."""
    size = np.broadcast_to(np.asarray(size_old, float), (len(H), 2))
    centres = (np.arange(grid) + 0.5) / grid  # cell centres: no point on the image border
    gx, gy = (g.ravel() for g in np.meshgrid(centres, centres))
    pts = np.stack([gx * size[:, :1] - 0.5, gy * size[:, 1:] - 0.5, np.ones((len(H), gx.size))], axis=1)
    proj = H @ pts  # (n, 3, m)
    z = proj[:, 2]
    front = z > 1e-9
    x = proj[:, 0] / np.where(front, z, 1.0)
    y = proj[:, 1] / np.where(front, z, 1.0)
    W, Hh = size_new
    inside = front & (x >= -0.5) & (x <= W - 0.5) & (y >= -0.5) & (y <= Hh - 0.5)
    return inside.mean(axis=1)


def points_inside(H: Array, points: NDArray, size: tuple[float, float], margin: float) -> NDArray[np.bool_]:
    """Which points map through H (unit determinant) in front of the camera and inside an image of
    `size` widened by `margin` pixels on every side."""
    pts = np.asarray(points, float).reshape(-1, 2)
    proj = pts @ H[:, :2].T + H[:, 2]
    z = proj[:, 2]
    front = z > 1e-9
    x = proj[:, 0] / np.where(front, z, 1.0)
    y = proj[:, 1] / np.where(front, z, 1.0)
    w, h = size
    lo = -0.5 - margin
    return front & (x >= lo) & (x <= w - 0.5 + margin) & (y >= lo) & (y <= h - 0.5 + margin)
