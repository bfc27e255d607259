"""`ptz-selfcal mosaic IN_BAG --out FILE.png [--projection spherical|cylindrical]` (paper section 8);
`ptz-selfcal mosaic --images DIR --out FILE.png`: a folder of stills from one fixed lens.

IN_BAG is either an output bag of `ptz-selfcal run` (it holds ptz/selfcal/camera_info and
ptz/selfcal/frame; the images come from the same bag or from --input-bag) or an input bag (images and
encoders), which is first run through the real nodes (tools/run.py) into a temporary directory.
By default (--calibration final) every tracked frame is placed through the run's final calibration
(mosaic/final.py: K and R re-derived through the frame's homography, eq. 20, from its keyframe's
latest solve, or the last solve for a keyframe no solve published), so the frames published before
the first solve are placed too; frames without a homography
(tracking lost) and frames of another tracking reference than the one whose final solve places most
are skipped and counted. --calibration published places each frame through its published K, plumb_bob
D and orientation instead, skipping the invalid zero quaternion and, unless --all-frames, the frames
published before the first solve (the prior's K misplaces them and they ghost; when no frame is
calibrated every frame is placed). The mosaic is levelled with the encoders passed through in
FrameCalibration when there are any (pan 0 at the centre, the horizon level); otherwise its frame is
the calibration's reference. The width gives one mosaic pixel per image pixel at the longest focal
length seen, capped by --max-width. The PNG is BGRA: alpha 0 where nothing was seen.

--images DIR: the folder's images in name order (a hand-held set taken in order) go through the
stills front end and the calibrator session with one focal length (online/stills_calibration.py, at
the frame_ingest node's working width), and each still is placed through the final solve's K, D and
its adjusted orientation, in the frame of the first placed still. A file that is not a readable image
is skipped and counted; a folder without two readable images is an error.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ptz_selfcal import topics
from ptz_selfcal.camera.geometry import matrix_from_quaternion
from ptz_selfcal.mosaic.blend import MosaicResult, build_mosaic
from ptz_selfcal.mosaic.final import FinalFrame, PublishedFrame, final_calibration
from ptz_selfcal.mosaic.projection import KINDS, SPHERICAL
from ptz_selfcal.mosaic.warp import FrameView
from ptz_selfcal.nodes.conversions import MSG_TO_TRACKING_STATE, STATUS_TO_MSG
from ptz_selfcal.sim import metrics
from ptz_selfcal.status import CALIBRATED, HOMOGRAPHY_STATES
from ptz_selfcal.tools.bagio import BagReader, deserialize, header_stamp_ns
from ptz_selfcal.tools.cli import CliError
from ptz_selfcal.tools.evaluate import BagData, read_image_stamps, read_output_bag, run_pipeline

IMAGE_TOPICS = (topics.bag_topic(topics.IMAGE_COMPRESSED), topics.bag_topic(topics.IMAGE_RAW))
_REDUCED = {
    2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
    4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
    8: cv2.IMREAD_REDUCED_GRAYSCALE_8,
}
# FrameCalibration.status values of a calibrated K
CALIBRATED_STATUS = frozenset(STATUS_TO_MSG[s] for s in CALIBRATED)
# Frames with more than this many images print progress lines.
PROGRESS_MIN_FRAMES = 50


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "in_bag", nargs="?", help="an output bag of `ptz-selfcal run`, or an input bag (run first)"
    )
    parser.add_argument(
        "--images",
        metavar="DIR",
        help="instead of a bag: a folder of stills from one fixed lens, in name order",
    )
    parser.add_argument("--out", required=True, metavar="FILE.png", help="mosaic image to write (PNG)")
    parser.add_argument("--projection", choices=KINDS, default=SPHERICAL, help="mosaic surface")
    parser.add_argument("--max-width", type=int, default=8192, help="mosaic width cap (pixels, full turn)")
    parser.add_argument("--input-bag", help="with an output bag without images: the bag that holds them")
    parser.add_argument(
        "--frame",
        choices=("auto", "encoders", "reference"),
        default="auto",
        help="levelled by the encoders (auto: when present) or in the calibration's reference frame",
    )
    parser.add_argument(
        "--calibration",
        choices=("final", "published"),
        default="final",
        help="final: every tracked frame through the run's last solve (also the frames published before "
        "it); published: each frame's own published K and orientation",
    )
    parser.add_argument(
        "--all-frames",
        action="store_true",
        help="with --calibration published: also the frames published before the first solve (the "
        "prior's K: they ghost)",
    )
    parser.add_argument("--no-exposure", action="store_true", help="no per-frame gain compensation")
    parser.add_argument("--params", metavar="FILE", help="parameter YAML for the nodes (input bags)")
    parser.add_argument("--deterministic", action="store_true", help="passed to run (input bags)")
    parser.add_argument("--quiet", action="store_true", help="no node output and no progress lines")


@dataclass
class Frames:
    """The frames that go into the mosaic, and why the others do not."""

    stamps: list[int] = field(default_factory=list)
    views: list[FrameView] = field(default_factory=list)
    R_reference: list[np.ndarray] = field(default_factory=list)  # reference -> camera (as published)
    encoders: list[tuple[float, float]] = field(default_factory=list)  # (pan, tilt) rad, nan if none
    skipped: Counter = field(default_factory=Counter)


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """The mosaic written to `path` (its folder made); CliError when it cannot be written."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), image):
        raise CliError(f"{out}: cannot write the image")
    return out


def valid_quaternion(q: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(q)) and abs(float(np.linalg.norm(q)) - 1.0) < 1e-3)


@dataclass(frozen=True)
class Tracked:
    """A frame's HomographyStamped: tracker reference -> frame (None when not tracked), its keyframe."""

    H: np.ndarray | None
    keyframe_id: int


def read_homographies(path: Path) -> dict[int, Tracked]:
    """The tracker's homographies of an output bag, by frame stamp."""
    out: dict[int, Tracked] = {}
    with BagReader(path) as reader:
        names = [t.name for t in reader.topics() if t.name == topics.bag_topic(topics.HOMOGRAPHY)]
        for msg in reader.messages(names):
            m = deserialize(msg.raw, msg.msgtype)
            h = np.asarray(m.h, dtype=float)
            ok = MSG_TO_TRACKING_STATE.get(m.state) in HOMOGRAPHY_STATES and h.size == 9
            ok = ok and bool(np.all(np.isfinite(h)))
            stamp = int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec)
            out[stamp] = Tracked(h.reshape(3, 3) if ok else None, int(m.keyframe_id))
    return out


def _orientation(fc: Any) -> np.ndarray | None:
    o = fc.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    return matrix_from_quaternion(q) if valid_quaternion(q) else None


def _intrinsics(info: Any) -> np.ndarray | None:
    K = np.asarray(info.k, dtype=float).reshape(3, 3)
    return K if np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 else None


def _distortion(info: Any) -> tuple[float, float, float]:
    d = [float(x) for x in info.d] + [0.0] * 5
    return (d[0], d[1], d[4])


def collect_frames(data: BagData, calibrated_only: bool = False) -> Frames:
    """Frames placed as published: a CameraInfo and a valid orientation, of the tracking reference with
    most frames (calibrated_only: and a calibrated status, not the prior's K of the frames before the
    first solve)."""
    frames = Frames()
    stamps = sorted(set(data.image_stamps) | set(data.camera_info) | set(data.frame_calibration))
    candidates = []
    for stamp in stamps:
        info, fc = data.camera_info.get(stamp), data.frame_calibration.get(stamp)
        if info is None or fc is None:
            frames.skipped["no calibration"] += 1
            continue
        R = _orientation(fc)
        if R is None:
            frames.skipped["invalid orientation"] += 1
            continue
        if calibrated_only and int(fc.status) not in CALIBRATED_STATUS:
            frames.skipped["not calibrated"] += 1
            continue
        candidates.append((stamp, info, fc, R))
    references = Counter(data.reference.get(s, 0) for s, *_ in candidates)
    main_reference = references.most_common(1)[0][0] if references else 0
    for stamp, info, fc, R in candidates:
        if data.reference.get(stamp, 0) != main_reference:
            frames.skipped["other reference"] += 1
            continue
        K = _intrinsics(info)
        if K is None:
            frames.skipped["no calibration"] += 1
            continue
        _append(frames, stamp, FrameView(K, _distortion(info), R, int(info.width), int(info.height)), fc)
    return frames


def _append(frames: Frames, stamp: int, view: FrameView, fc: Any) -> None:
    frames.stamps.append(stamp)
    frames.views.append(view)
    frames.R_reference.append(view.R)
    enc = fc.encoders
    frames.encoders.append((float(enc.pan), float(enc.tilt)) if enc.valid else (np.nan, np.nan))


def collect_final_frames(data: BagData, tracked: dict[int, Tracked]) -> Frames:
    """Every tracked frame placed with the run's final calibration (mosaic/final.py), frames published
    before it included; of the tracking reference whose final solve places most frames."""
    frames = Frames()
    groups: dict[int, list[tuple[int, Any, Any, PublishedFrame]]] = {}
    for stamp in sorted(set(data.image_stamps) | set(data.camera_info) | set(data.frame_calibration)):
        info, fc, t = data.camera_info.get(stamp), data.frame_calibration.get(stamp), tracked.get(stamp)
        K = _intrinsics(info) if info is not None else None
        if K is None or fc is None or t is None:
            frames.skipped["no calibration"] += 1
            continue
        if t.H is None:
            frames.skipped["not tracked"] += 1
            continue
        R = _orientation(fc)
        calibrated = int(fc.status) in CALIBRATED_STATUS
        solve = (int(fc.keyframe_count), float(fc.residual))  # one solve's frames share both
        published = PublishedFrame(t.H, t.keyframe_id, K, R, calibrated, solve)
        groups.setdefault(data.reference.get(stamp, 0), []).append((stamp, info, fc, published))
    placed: dict[int, list[FinalFrame | None]] = {}
    for reference, group in groups.items():
        size = (int(group[0][1].width), int(group[0][1].height))
        placed[reference] = final_calibration([g[3] for g in group], size)
    best = max(placed, key=lambda r: sum(p is not None for p in placed[r]), default=None)
    for reference, group in groups.items():
        if reference != best:
            frames.skipped["other reference"] += len(group)
            continue
        for (stamp, info, fc, _), final in zip(group, placed[reference]):
            if final is None:
                frames.skipped["no final solve"] += 1
                continue
            D = _distortion(group[final.anchor][1])  # the final solve's distortion
            _append(frames, stamp, FrameView(final.K, D, final.R, int(info.width), int(info.height)), fc)
    return frames


def with_alignment(frames: Frames, A: np.ndarray) -> Frames:
    """The same frames with world-to-camera rotations R_j A (A: world -> calibration reference)."""
    views = [FrameView(v.K, v.D, R @ A, v.width, v.height) for v, R in zip(frames.views, frames.R_reference)]
    return Frames(frames.stamps, views, frames.R_reference, frames.encoders, frames.skipped)


def encoder_alignment(frames: Frames) -> np.ndarray | None:
    """The rotation that levels the mosaic with the encoders' pan/tilt (None without 3 readings)."""
    enc = np.asarray(frames.encoders, dtype=float).reshape(-1, 2)
    ok = np.isfinite(enc).all(axis=1)
    if ok.sum() < 3:
        return None
    R_enc = np.full((len(enc), 3, 3), np.nan)
    R_enc[ok] = metrics.rotations_from_encoders(enc[ok, 0], enc[ok, 1])
    return metrics.align_rotations(np.asarray(frames.R_reference), R_enc, ok)


def decode_image(msgtype: str, raw: bytes, reduction: int) -> np.ndarray | None:
    """BGR uint8 at full size (reduction 1) or grey at about 1/reduction size; None if undecodable."""
    msg = deserialize(raw, msgtype)
    if msgtype.endswith("CompressedImage"):
        data = np.frombuffer(msg.data, np.uint8)
        flag = _REDUCED.get(reduction, cv2.IMREAD_GRAYSCALE) if reduction > 1 else cv2.IMREAD_COLOR
        image = cv2.imdecode(data, flag)
        if image is not None and reduction > 1 and flag == cv2.IMREAD_GRAYSCALE:
            image = cv2.resize(
                image, None, fx=1.0 / reduction, fy=1.0 / reduction, interpolation=cv2.INTER_AREA
            )
        return image
    h, w, enc = int(msg.height), int(msg.width), str(msg.encoding)
    data = np.frombuffer(msg.data, np.uint8)
    if enc in ("mono16", "16UC1"):
        image = (data.view("<u2" if not msg.is_bigendian else ">u2").reshape(h, -1)[:, :w] >> 8).astype(
            np.uint8
        )
    else:
        channels = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3}.get(enc)
        if channels is None:
            return None
        image = data.reshape(h, int(msg.step))[:, : w * channels].reshape(h, w, channels)
        if enc == "rgb8":
            image = image[:, :, ::-1]
    image = np.ascontiguousarray(image.squeeze())
    if reduction > 1:
        grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return cv2.resize(grey, (w // reduction, h // reduction), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image


class BagFrameSource:
    """mosaic.blend.FrameSource over the images of a bag, matched to the frames by header stamp."""

    def __init__(self, image_bag: Path, frames: Frames) -> None:
        self.image_bag, self.views = image_bag, frames.views
        self._index = {stamp: i for i, stamp in enumerate(frames.stamps)}
        self.decode_seconds = 0.0

    def images(self, reduction: int) -> Iterator[tuple[int, np.ndarray]]:
        with BagReader(self.image_bag) as reader:
            names = [t.name for t in reader.topics() if t.name in IMAGE_TOPICS][:1]
            seen = set()
            for msg in reader.messages(names):
                i = self._index.get(header_stamp_ns(msg.raw))
                if i is None or i in seen:
                    continue
                start = time.perf_counter()
                image = decode_image(msg.msgtype, msg.raw, reduction)
                self.decode_seconds += time.perf_counter() - start
                if image is not None:
                    seen.add(i)
                    yield i, image


def image_topics(path: Path) -> list[str]:
    with BagReader(path) as reader:
        return [t.name for t in reader.topics() if t.name in IMAGE_TOPICS and t.count > 0]


def is_output_bag(path: Path) -> bool:
    with BagReader(path) as reader:
        names = {t.name for t in reader.topics()}
    return (
        topics.bag_topic(topics.CAMERA_INFO) in names and topics.bag_topic(topics.FRAME_CALIBRATION) in names
    )


def progress_printer(total: int, quiet: bool) -> Any:
    if quiet or total < PROGRESS_MIN_FRAMES:
        return None
    step = max(1, total // 10)

    def report(stage: str, done: int, n: int) -> None:
        if done % step == 0 or done == n:
            print(f"mosaic: {stage} {done}/{n} frames", file=sys.stderr, flush=True)

    return report


def make_mosaic(
    image_bag: Path,
    frames: Frames,
    kind: str = SPHERICAL,
    max_width: int = 8192,
    quiet: bool = True,
    compensate: bool = True,
) -> MosaicResult:
    if not frames.views:
        raise CliError("no frame has a calibration and a valid orientation: nothing to place")
    source = BagFrameSource(image_bag, frames)
    return build_mosaic(source, kind, max_width, progress_printer(len(frames.views), quiet), compensate)


def _mosaic_from(output_bag: Path, image_bag: Path, args: argparse.Namespace) -> int:
    if not image_topics(image_bag):
        raise CliError(
            f"{image_bag}: no images ({', '.join(IMAGE_TOPICS)}); pass the input bag with --input-bag"
        )
    data = BagData(image_stamps=read_image_stamps(image_bag)) if image_bag != output_bag else None
    data = read_output_bag(output_bag, data)
    if args.calibration == "final":
        frames = collect_final_frames(data, read_homographies(output_bag))
        if not frames.views:
            print("mosaic: no final solve to place the frames with: as published", file=sys.stderr)
    if args.calibration == "published" or not frames.views:
        frames = collect_frames(data, calibrated_only=not args.all_frames)
    if not frames.views and not args.all_frames:
        print("mosaic: no frame is calibrated, placing every frame with its published K", file=sys.stderr)
        frames = collect_frames(data)
    A = encoder_alignment(frames) if args.frame != "reference" else None
    if args.frame == "encoders" and A is None:
        raise CliError("--frame encoders: fewer than 3 frames carry encoder readings")
    if A is not None:
        frames = with_alignment(frames, A)
    start = time.monotonic()
    result = make_mosaic(image_bag, frames, args.projection, args.max_width, args.quiet, not args.no_exposure)
    wall = time.monotonic() - start
    out = write_image(args.out, result.image)
    p = result.projection
    skipped = ", ".join(f"{k} {v}" for k, v in sorted(frames.skipped.items())) or "none"
    covered = float((result.image[:, :, 3] > 0).mean())
    print(
        f"mosaic: {result.frames} frames placed in {wall:.1f} s, skipped: {skipped}; "
        f"{p.kind} {p.width}x{p.height}, {100 * covered:.1f} % covered, frame "
        f"{'encoders' if A is not None else 'calibration reference'}; wrote {out}"
    )
    return 0


def run(args: argparse.Namespace) -> int:
    if Path(args.out).suffix.lower() != ".png":
        raise CliError(f"{args.out}: the mosaic is written as PNG (name it .png)")
    if args.max_width < 64:
        raise CliError("--max-width must be at least 64")
    if (args.in_bag is None) == (args.images is None):
        raise CliError("give either IN_BAG or --images DIR")
    if args.images is not None:
        return _mosaic_from_images(Path(args.images), args)
    in_bag = Path(args.in_bag)
    if is_output_bag(in_bag):
        image_bag = Path(args.input_bag) if args.input_bag else in_bag
        return _mosaic_from(in_bag, image_bag, args)
    with tempfile.TemporaryDirectory(prefix="ptz_selfcal_mosaic_") as tmp:
        output_bag = Path(tmp) / "output_bag"
        extra = ["--deterministic"] if args.deterministic else []
        run_pipeline(in_bag, output_bag, args.params, args.quiet, extra)
        return _mosaic_from(output_bag, in_bag, args)


# --------------------------------------------------------------------------------------------------
# A folder of stills (--images)
# --------------------------------------------------------------------------------------------------
# what cv2.imread reads (the name decides which files are tried; the content whether they are images)
STILL_SUFFIXES = frozenset(
    (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".pgm", ".ppm", ".pnm")
)


class StillsFrameSource:
    """mosaic.blend.FrameSource over still image files (views[k] is the view of paths[k])."""

    def __init__(self, paths: Sequence[Path], views: Sequence[FrameView]) -> None:
        self.paths, self.views = list(paths), list(views)

    def images(self, reduction: int) -> Iterator[tuple[int, np.ndarray]]:
        for i, path in enumerate(self.paths):
            flag = _REDUCED.get(reduction, cv2.IMREAD_COLOR) if reduction > 1 else cv2.IMREAD_COLOR
            image = cv2.imread(str(path), flag)
            if image is not None:
                yield i, image


def still_paths(folder: Path) -> list[Path]:
    """The image files of a folder in name order; CliError when it is missing or holds none."""
    if not folder.is_dir():
        raise CliError(f"{folder}: no such folder")
    paths = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in STILL_SUFFIXES)
    if not paths:
        raise CliError(f"{folder}: no image files ({', '.join(sorted(STILL_SUFFIXES))})")
    return paths


def working_stills(
    paths: Sequence[Path], working_width: int, good: list[Path], skipped: Counter, quiet: bool
) -> Iterator[tuple[np.ndarray, float]]:
    """(grey working image, working / full scale) of each readable file, decoded and reduced as
    frame_ingest does a CompressedImage of the same bytes; the readable files are appended to `good`,
    the others counted in `skipped` and named on stderr."""
    from types import SimpleNamespace

    from ptz_selfcal.nodes.conversions import FrameError, compressed_to_working

    for path in paths:
        fmt = "png" if path.suffix.lower() == ".png" else "jpeg"
        try:
            work = compressed_to_working(SimpleNamespace(data=path.read_bytes(), format=fmt), working_width)
        except (FrameError, OSError) as exc:
            skipped["unreadable"] += 1
            if not quiet:
                print(
                    f"mosaic: {path.name}: not a readable image ({exc}), skipped", file=sys.stderr, flush=True
                )
            continue
        good.append(path)
        yield work.image, work.scale


def _mosaic_from_images(folder: Path, args: argparse.Namespace) -> int:
    from ptz_selfcal.nodes.frame_ingest import PARAMS
    from ptz_selfcal.nodes.params import CalibratorNodeConfig
    from ptz_selfcal.online.stills_calibration import calibrate_stills

    paths = still_paths(folder)
    working_width = next(int(p.default) for p in PARAMS if p.name == "working_width")
    good: list[Path] = []
    skipped: Counter = Counter()
    report = progress_printer(len(paths), args.quiet)
    progress = None if report is None else (lambda i: report("calibrating", i + 1, len(paths)))
    start = time.monotonic()
    stills = working_stills(paths, working_width, good, skipped, args.quiet)
    calibration = calibrate_stills(stills, CalibratorNodeConfig().reoptimise_budget, progress=progress)
    if len(good) < 2:
        raise CliError(f"{folder}: {len(good)} readable image(s) of {len(paths)}: a mosaic needs two or more")
    skipped.update(calibration.skipped)
    if not calibration.indices:
        raise CliError(
            f"{folder}: the stills gave no calibration ({calibration.message or calibration.status})"
        )
    w, h = calibration.size
    D = (float(calibration.D[0]), float(calibration.D[1]), float(calibration.D[4]))
    views = [FrameView(K, D, R, w, h) for K, R in zip(calibration.K, calibration.R)]
    source = StillsFrameSource([good[i] for i in calibration.indices], views)
    result = build_mosaic(source, args.projection, args.max_width, report, not args.no_exposure)
    wall = time.monotonic() - start
    out = write_image(args.out, result.image)
    p = result.projection
    covered = float((result.image[:, :, 3] > 0).mean())
    text = ", ".join(f"{k} {v}" for k, v in sorted(skipped.items())) or "none"
    print(
        f"mosaic: {result.frames} of {len(paths)} stills placed in {wall:.1f} s, skipped: {text}; "
        f"f {float(calibration.K[0][0, 0]):.1f} px ({calibration.status}); {p.kind} {p.width}x{p.height}, "
        f"{100 * covered:.1f} % covered, frame of still {paths.index(good[calibration.indices[0]])}; "
        f"wrote {out}"
    )
    return 0


# --------------------------------------------------------------------------------------------------
# The mosaic in `ptz-selfcal eval`
# --------------------------------------------------------------------------------------------------
SYNTH_PARAMS = "synth_params.yaml"  # tools/synth.py writes it into the bag directory
EVAL_MAX_WIDTH = 4096


def repository_panoramas() -> Path:
    """The repository's panoramas (bags/source), where a checkout has them."""
    return Path(__file__).resolve().parents[4] / "bags" / "source"


def source_panorama(in_bag: Path, search: Sequence[Path] = ()) -> Path | None:
    """The panorama a synthetic bag was rendered from: named with its sha256 in the bag's
    synth_params.yaml, looked for beside the bag, in `search` and in the repository's bags/source."""
    import hashlib

    import yaml

    params = in_bag / SYNTH_PARAMS
    if not params.is_file():
        return None
    info = (yaml.safe_load(params.read_text()) or {}).get("panorama") or {}
    name, sha = info.get("file"), info.get("sha256")
    if not name:
        return None
    for folder in (in_bag.parent, in_bag.parent.parent, *search, repository_panoramas()):
        path = Path(folder) / str(name)
        if path.is_file() and (not sha or hashlib.sha256(path.read_bytes()).hexdigest() == sha):
            return path
    return None


def truth_alignment(data: BagData, frames: Frames) -> np.ndarray | None:
    """The rotation that puts a synthetic bag's mosaic in its panorama's frame (ground-truth pan/tilt);
    None without ground truth for at least 3 placed frames."""
    R_true = np.full((len(frames.stamps), 3, 3), np.nan)
    for k, stamp in enumerate(frames.stamps):
        js = data.gt_joint_states.get(stamp)
        if js is None or "pan" not in js.name or "tilt" not in js.name:
            continue
        names = list(js.name)
        pan, tilt = js.position[names.index("pan")], js.position[names.index("tilt")]
        R_true[k] = metrics.rotations_from_encoders([pan], [tilt])[0]
    ok = np.isfinite(R_true).all(axis=(1, 2))
    if ok.sum() < 3:
        return None
    return metrics.align_rotations(np.asarray(frames.R_reference), R_true, ok)


def eval_mosaic(
    data: BagData, output_bag: Path, image_bag: Path, out_dir: Path, max_width: int = EVAL_MAX_WIDTH
) -> dict[str, Any]:
    """`eval`'s mosaic: out_dir/mosaic.png (final calibration, levelled by the encoders or, for a
    synthetic bag, in its panorama's frame by the ground truth) and, when the source panorama is found,
    out_dir/mosaic_vs_source.png: the covered region over the same region of the panorama. The
    report's entry (never raises for a bag it cannot place: the entry says why)."""
    try:
        frames = collect_final_frames(data, read_homographies(output_bag))
        if not frames.views:
            frames = collect_frames(data, calibrated_only=True)
        if not frames.views:
            return {"file": None, "note": "no frame to place"}
        A = truth_alignment(data, frames)
        frame = "ground truth" if A is not None else "encoders"
        if A is None:
            A = encoder_alignment(frames)
            frame = "encoders" if A is not None else "calibration reference"
        if A is not None:
            frames = with_alignment(frames, A)
        result = make_mosaic(image_bag, frames, SPHERICAL, max_width)
    except (CliError, ValueError, np.linalg.LinAlgError) as exc:
        return {"file": None, "note": f"no mosaic: {exc}"}
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "mosaic.png"
    cv2.imwrite(str(path), result.image)
    covered = result.image[:, :, 3] > 0
    entry: dict[str, Any] = {
        "file": str(path),
        "frames_placed": result.frames,
        "skipped": dict(frames.skipped),
        "size": [result.projection.width, result.projection.height],
        "covered_pct": 100.0 * float(covered.mean()),
        "frame": frame,
    }
    panorama = source_panorama(image_bag)
    if panorama is not None and frame == "ground truth":
        entry.update(_beside_source(result.image, panorama, out_dir / "mosaic_vs_source.png"))
    return entry


def _beside_source(mosaic: np.ndarray, panorama: Path, out: Path) -> dict[str, Any]:
    """The mosaic's covered bounding box above the same region of the source panorama (at the mosaic's
    resolution), and the median grey-level difference there after one global gain."""
    source = cv2.imread(str(panorama), cv2.IMREAD_COLOR)
    H, W = mosaic.shape[:2]
    source = cv2.resize(source, (W, H), interpolation=cv2.INTER_AREA)
    covered = mosaic[:, :, 3] > 0
    rows = np.nonzero(covered.any(axis=1))[0]
    y0, y1 = int(rows.min()), int(rows.max()) + 1
    cols = np.nonzero(covered.any(axis=0))[0]
    x0, x1 = int(cols.min()), int(cols.max()) + 1  # a crop across the wrap keeps the whole width
    crop, truth = mosaic[y0:y1, x0:x1, :3], source[y0:y1, x0:x1]
    mask = covered[y0:y1, x0:x1]
    a = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)[mask].astype(float)
    b = cv2.cvtColor(truth, cv2.COLOR_BGR2GRAY)[mask].astype(float)
    gain = float((a * b).sum() / max((a * a).sum(), 1e-9))
    shown = np.where(mask[:, :, None], crop, crop // 4)
    cv2.imwrite(str(out), np.vstack([shown, truth]))
    return {
        "source_panorama": panorama.name,
        "comparison_file": str(out),
        "photometric_median_abs_diff": float(np.median(np.abs(gain * a - b))),
    }
