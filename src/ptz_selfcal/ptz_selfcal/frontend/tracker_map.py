"""The tracker's keyframe map as one file (no pickle), so that a restarted tracker keeps its reference.

HomographyTracker.export_map() gives the map as plain data (ids, reference, homographies, working
images and corners, least recently used first; descriptors are recomputed from the images),
map_to_bytes()/map_from_bytes() turn it into one .npz blob and back and HomographyTracker.restore_map()
loads it: the tracker then starts lost and its first frame relocalises against the stored keyframes (the
last tracked one first), so a restarted tracker keeps the same reference and keyframe ids (new ids
continue after the stored ones). A revisit changes the map (the keyframe tracked, the pruning order) on a
TRACKING frame: a caller saving the map saves it when a result's keyframe_id changes, not only on
NEW_KEYFRAME / RELOCALISED.
"""

from __future__ import annotations

import io
import json
import zlib
from typing import Any, TypedDict

import cv2
import numpy as np
from numpy.typing import NDArray

MAP_FORMAT = "ptz_selfcal.tracker_map"
MAP_VERSION = 2


class StoredKeyframe(TypedDict):
    """One keyframe of an exported map (a MapKeyframe without its descriptors, recomputed on use)."""

    id: int
    stamp: float | None
    H_ref: NDArray[np.float64]  # reference -> keyframe, full resolution
    depth: int  # keyframe links between the reference and this keyframe
    image: NDArray[np.uint8]  # working resolution, mono8
    corners: NDArray[np.float32]  # working pixels


class TrackerMap(TypedDict):
    """The keyframe map as plain data: HomographyTracker.export_map gives it, restore_map and
    map_to_bytes take it, map_from_bytes gives it back (to be checked by restore_map)."""

    reference_id: int
    keyframe_id: int
    frame_index: int
    scale: float  # working / full resolution
    keyframes: list[StoredKeyframe]  # least recently used first


def map_to_bytes(
    data: TrackerMap,
    extra: dict[str, Any] | None = None,
    cache: dict[tuple[int, int, tuple[int, ...]], bytes] | None = None,
) -> bytes:
    """An exported map (HomographyTracker.export_map) as one .npz blob: the metadata (and the caller's
    JSON-serialisable `extra`) as JSON, the keyframe images as lossless PNG, the other arrays stacked.
    Loadable without pickle. `cache` (kept by the caller between saves) holds the PNG of each keyframe
    image (keyed by id and checksum): a keyframe is encoded once, not at every save; it is left holding
    only the keyframes of this map (bounded)."""
    keyframes = data["keyframes"]
    meta = {key: data[key] for key in ("reference_id", "keyframe_id", "frame_index", "scale")}
    encoded: dict[tuple[int, int, tuple[int, ...]], bytes] = {}
    for kf in keyframes:
        image = np.ascontiguousarray(kf["image"], np.uint8)
        key = (int(kf["id"]), zlib.crc32(image), image.shape)
        png = None if cache is None else cache.get(key)
        if png is None:
            ok, buffer = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if not ok:
                raise ValueError(f"keyframe {kf['id']}: the image cannot be encoded")
            png = buffer.tobytes()
        encoded[key] = png
    if cache is not None:
        cache.clear()
        cache.update(encoded)
    pngs = list(encoded.values())
    meta.update(
        format=MAP_FORMAT, version=MAP_VERSION, extra=extra or {},
        ids=[int(kf["id"]) for kf in keyframes], depths=[int(kf["depth"]) for kf in keyframes],
        stamps=[None if kf["stamp"] is None else float(kf["stamp"]) for kf in keyframes],
        corner_counts=[len(kf["corners"]) for kf in keyframes], png_sizes=[len(png) for png in pngs],
    )  # fmt: skip
    out = io.BytesIO()
    np.savez(
        out,
        meta=np.frombuffer(json.dumps(meta).encode(), np.uint8),
        images_png=np.frombuffer(b"".join(pngs), np.uint8),
        H_ref=np.stack([kf["H_ref"] for kf in keyframes]).astype(np.float64),
        corners=np.concatenate([np.asarray(kf["corners"], np.float32).reshape(-1, 2) for kf in keyframes]),
    )
    return out.getvalue()


def _decode_images(blob: NDArray[np.uint8], sizes: list[int]) -> NDArray[np.uint8]:
    if blob.ndim != 1 or sum(sizes) != len(blob) or not sizes:
        raise ValueError("image sizes do not match the image data")
    images = []
    for chunk in np.split(blob, np.cumsum(sizes)[:-1]):
        image = cv2.imdecode(chunk, cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim != 2 or image.dtype != np.uint8:
            raise ValueError("a keyframe image is not a mono8 PNG")
        images.append(image)
    if len({image.shape for image in images}) != 1:
        raise ValueError("keyframe images of different sizes")
    return np.stack(images)


def map_from_bytes(blob: bytes) -> tuple[TrackerMap, dict[str, Any]]:
    """(map for HomographyTracker.restore_map, extra) from map_to_bytes' blob; ValueError when it is not
    one (truncated, corrupt, another format or version, inconsistent sizes)."""
    try:
        with np.load(io.BytesIO(blob), allow_pickle=False) as npz:
            meta = json.loads(npz["meta"].tobytes().decode())
            images_png, H_ref, corners = npz["images_png"], npz["H_ref"], npz["corners"]
    except ValueError:
        raise
    except Exception as exc:  # zipfile.BadZipFile, EOFError, KeyError, UnicodeDecodeError, OSError
        raise ValueError(f"not a tracker map file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != MAP_FORMAT or meta.get("version") != MAP_VERSION:
        raise ValueError("not a tracker map file of this version")
    try:
        ids, counts = meta["ids"], meta["corner_counts"]
        n = len(ids)
        images = _decode_images(images_png, meta["png_sizes"])
        if not (images.ndim == 3 and len(images) == n and H_ref.shape == (n, 3, 3)):
            raise ValueError("keyframe arrays do not match the keyframe list")
        if len(counts) != n or len(meta["depths"]) != n or len(meta["stamps"]) != n:
            raise ValueError("keyframe lists of different lengths")
        if corners.ndim != 2 or corners.shape[1] != 2 or sum(counts) != len(corners):
            raise ValueError("corner counts do not match the corners")
        splits = np.split(corners, np.cumsum(counts)[:-1]) if n else []
        keyframes = [
            StoredKeyframe(
                id=ids[i],
                stamp=meta["stamps"][i],
                H_ref=H_ref[i],
                depth=meta["depths"][i],
                image=images[i],
                corners=splits[i],
            )
            for i in range(n)
        ]
        data = TrackerMap(
            reference_id=meta["reference_id"],
            keyframe_id=meta["keyframe_id"],
            frame_index=meta["frame_index"],
            scale=meta["scale"],
            keyframes=keyframes,
        )
    except (KeyError, TypeError) as exc:
        raise ValueError(f"malformed tracker map metadata: {type(exc).__name__}: {exc}") from exc
    extra = meta.get("extra") or {}
    return data, extra if isinstance(extra, dict) else {}
