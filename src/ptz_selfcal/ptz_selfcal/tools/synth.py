"""`ptz-selfcal synth PANORAMA OUT_BAG`: a PTZ camera rendered from an equirectangular panorama.

Writes a ROS 2 bag (mcap by default) with the topics of DESIGN.md section 3 and ptz_selfcal/topics.py
(NS = --namespace, default /ptz):
  NS/image_raw/compressed        sensor_msgs/CompressedImage (--format jpeg|png), or
  NS/image_raw                   sensor_msgs/Image (--format mono8|bgr8)
  NS/joint_states                sensor_msgs/JointState: encoders pan, tilt (rad), zoom (counts), own rate,
                                 lag and noise (sim/render.py EncoderModel: stamp t = state at t - lag,
                                 so an ingest's time_offset is -lag)
  NS/ground_truth/camera_info  sensor_msgs/CameraInfo per image, same stamp: the true K, P = [K|0],
                                 R = I; distortion_model "plumb_bob" with D = 0 when the lens has no
                                 distortion, else "division" with D = [lam] (exact: camera/distortion.py)
  NS/ground_truth/joint_states sensor_msgs/JointState per image, same stamp: true pan, tilt, zoom counts
and OUT_BAG/synth_params.yaml (every parameter, for evaluation and reproduction). The bag is written to
a temporary directory beside OUT_BAG and renamed at the end: nothing is left half-written. The same
arguments (and bag name: mcap stores it) give the same bytes, whatever --jobs.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ptz_selfcal import topics
from ptz_selfcal.camera.distortion import PLUMB_BOB
from ptz_selfcal.sim.nuisances import (
    ExposureSteps,
    LowLight,
    Nuisances,
    crossing_objects,
    followed_target,
)
from ptz_selfcal.sim.render import (
    MOTIONS,
    ZOOM_LAWS,
    CameraProfile,
    CameraState,
    EncoderModel,
    ImageModel,
    Panorama,
    ZoomEncoder,
    build_panorama,
    focal_from_hfov,
    is_equirectangular,
    render_view,
)
from ptz_selfcal.sim.synthetic import CONFIGURATIONS
from ptz_selfcal.tools.cli import CliError

FORMATS = ("jpeg", "png", "mono8", "bgr8")
DEFAULT_HFOV = 54.0
DEFAULT_START = 1_767_225_600  # 2026-01-01T00:00:00Z: a fixed epoch keeps the bytes reproducible
IMAGE_TYPE = topics.TYPES[topics.IMAGE_RAW]
COMPRESSED_TYPE = topics.TYPES[topics.IMAGE_COMPRESSED]
INFO_TYPE = topics.TYPES[topics.GT_CAMERA_INFO]
MASK_TYPE = topics.TYPES[topics.GT_MOVING_MASK]
JOINT_TYPE = topics.TYPES[topics.JOINT_STATES]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("panorama", help="equirectangular image (width = 2 x height), e.g. a 360 panorama")
    parser.add_argument("out_bag", help="new bag directory (refuses an existing path)")
    g = parser.add_argument_group("sequence")
    g.add_argument(
        "--paper-config", choices=sorted(CONFIGURATIONS),
        help="the paper's section 4.1 sequence: A = 5 deg circle, f 800 -> 1400 px; B = 3.5 deg, "
        "f 1200 -> 2000 px; both 30 frames of 640x480 mono8 at 2 fps, principal point at the centre, "
        "f linear in time (options given explicitly override these)",
    )  # fmt: skip
    g.add_argument("--frames", type=int, help="number of images (default 300)")
    g.add_argument("--width", type=int, help="image width in pixels (default 1280)")
    g.add_argument("--height", type=int, help="image height in pixels (default 720)")
    g.add_argument("--fps", type=float, help="frame rate (default 30)")
    g.add_argument("--start-time", type=float, default=DEFAULT_START, help="first image stamp, seconds")
    g = parser.add_argument_group("camera motion and lens")
    g.add_argument("--f-wide", type=float, help="focal length at the wide end, pixels (default: from --hfov)")
    # Not the calibrator's shipped prior (60 deg, centred principal point): a first bag must be solved for.
    g.add_argument(
        "--hfov", type=float, default=DEFAULT_HFOV,
        help=f"horizontal field of view at the wide end, deg (default {DEFAULT_HFOV:g})",
    )  # fmt: skip
    g.add_argument("--zoom-max", type=float, help="largest zoom ratio (default 3)")
    g.add_argument(
        "--f-tele", type=float, help="focal length at the tele end, pixels (instead of --zoom-max)"
    )
    g.add_argument(
        "--zoom-law", choices=ZOOM_LAWS,
        help="cosine: f_wide -> f_tele -> f_wide, geometric (default); linear: f_wide -> f_tele in time",
    )  # fmt: skip
    g.add_argument(
        "--motion", choices=MOTIONS,
        help="sweep: pan and tilt waves (default); circle: the principal ray on a circle (section 4.1); "
        "patrol: pan from -amplitude to +amplitude and back, tilt a small wave, --dwell at each turn",
    )  # fmt: skip
    g.add_argument("--circle-radius-deg", type=float, help="circle radius, deg (default 5)")
    g.add_argument("--circle-turns", type=float, default=1.0, help="turns of the circle over the sequence")
    g.add_argument("--dwell", type=float, default=0.0, help="patrol: seconds held at every pan turn")
    g.add_argument(
        "--slow-start", type=float, default=0.0, metavar="SECONDS",
        help="the path's speed ramps up as (t / SECONDS)^2 over the first SECONDS (default 0: none)",
    )  # fmt: skip
    g.add_argument("--pan-centre", type=float, default=0.0, help="pan added to the whole path, deg")
    g.add_argument("--pan-amplitude", type=float, default=40.0, help="pan amplitude, degrees (default 40)")
    g.add_argument("--tilt-amplitude", type=float, default=8.0, help="tilt amplitude, degrees (default 8)")
    g.add_argument(
        "--pan-cycles", type=float, default=1.0, help="pan periods (patrol: rounds) over the sequence"
    )
    g.add_argument("--tilt-cycles", type=float, default=2.0, help="tilt periods over the sequence")
    g.add_argument("--waveform", choices=("sine", "triangle"), default="sine", help="pan/tilt path shape")
    g.add_argument(
        "--pp-offset", type=float, nargs=2, metavar=("DX", "DY"),
        help="principal point offset from the image centre, pixels (default 15 -10)",
    )  # fmt: skip
    g.add_argument(
        "--pp-drift", type=float, nargs=2, default=(0.0, 0.0), metavar=("DX", "DY"),
        help="principal point displacement at --zoom-max, linear in zoom (default 0 0)",
    )  # fmt: skip
    g.add_argument(
        "--distortion", type=float, default=0.0, metavar="FRACTION",
        help="division-model corner shift at the wide end as a fraction of the half-diagonal, "
        "shrinking as 1/f (0.12 = 12%% barrel; default 0: none)",
    )  # fmt: skip
    g = parser.add_argument_group("encoders")
    g.add_argument("--encoder-rate", type=float, default=15.0, help="JointState rate, Hz (default 15)")
    g.add_argument(
        "--encoder-lag", type=float, default=0.040,
        help="seconds: a sample stamped t reports the head at t - lag (default 0.040)",
    )  # fmt: skip
    g.add_argument("--pan-tilt-noise", type=float, default=0.01, help="encoder noise sigma, degrees")
    g.add_argument("--zoom-noise", type=float, default=2.0, help="zoom encoder noise sigma, counts")
    g.add_argument(
        "--lens-ratio", type=float, default=20.0,
        help="zoom ratio of the lens over the full 0..16384 encoder range (default 20)",
    )  # fmt: skip
    g = parser.add_argument_group("images")
    g.add_argument("--format", choices=FORMATS, help="image encoding (default jpeg)")
    g.add_argument("--jpeg-quality", type=int, default=90, help="JPEG quality 1..100 (default 90)")
    g.add_argument("--image-noise", type=float, default=2.0, help="Gaussian noise sigma, grey levels")
    g.add_argument("--brightness-drift", type=float, default=0.10, help="gain amplitude (0.10 = +-10%%)")
    g.add_argument("--interpolation", choices=("linear", "cubic"), default="linear", help="panorama sampling")
    g = parser.add_argument_group("output")
    g.add_argument(
        "--namespace",
        default=topics.NAMESPACE,
        help=f"namespace of the camera's topics, e.g. /cam1 (default {topics.NAMESPACE})",
    )
    g.add_argument(
        "--frame-id", default=topics.CAMERA_FRAME_ID, help=f"image frame_id ({topics.CAMERA_FRAME_ID})"
    )
    g.add_argument("--seed", type=int, default=0, help="random seed (same seed = same bytes)")
    g.add_argument(
        "--storage", choices=("mcap", "sqlite3"), default="mcap", help="bag storage (default mcap)"
    )
    g.add_argument("--jobs", type=int, default=2, help="rendering threads (default 2)")
    g.add_argument("--quiet", action="store_true", help="no progress lines")
    add_real_video_arguments(parser)


def add_real_video_arguments(parser: argparse.ArgumentParser) -> None:
    """Issue 16's nuisances (sim/nuisances.py); all off by default (the bag is then unchanged)."""
    g = parser.add_argument_group("real video (all off by default)")
    g.add_argument(
        "--moving-objects", type=int, default=0, metavar="N",
        help="N textured objects (panorama patches, 3-6 deg wide) crossing the view at 4-10 deg/s",
    )  # fmt: skip
    g.add_argument(
        "--follow-target", type=float, nargs=2, metavar=("T0", "T1"),
        help="a large target followed by the camera from T0 to T1 s: static in the image while the "
        "background moves (a sixth of the image at T0, growing with the zoom)",
    )  # fmt: skip
    g.add_argument(
        "--exposure-steps", type=float, default=0.0, metavar="SECONDS",
        help="auto-exposure: the gain steps every SECONDS through x1, 1.25, 0.85, 1.15, 0.75",
    )  # fmt: skip
    g.add_argument(
        "--vignetting", type=float, default=0.0, metavar="STRENGTH",
        help="cos^4 vignetting about the principal point, STRENGTH = the corners' loss (0.4 = 40%%)",
    )  # fmt: skip
    g.add_argument(
        "--low-light", action="store_true",
        help="a dim scene (x0.3) with shot noise (one electron per grey level); with --jpeg-quality 60 "
        "for a night camera's compression",
    )  # fmt: skip
    g.add_argument(
        "--rolling-shutter", type=float, default=0.0, metavar="READOUT_S",
        help="rows read one after another over READOUT_S seconds, the stamp at the middle row",
    )  # fmt: skip


# --------------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------------
def _check(ok: bool, message: str) -> None:
    if not ok:
        raise CliError(message)


def _finite(*values: float) -> bool:
    return all(np.isfinite(v) for v in values)


# What an option left unset means, without and with --paper-config (section 4.1; sim/synthetic.py).
DEFAULTS: dict[str, Any] = {
    "frames": 300, "width": 1280, "height": 720, "fps": 30.0, "format": "jpeg", "zoom_max": 3.0,
    "pp_offset": (15.0, -10.0), "motion": "sweep", "zoom_law": "cosine", "circle_radius_deg": 5.0,
}  # fmt: skip


def paper_defaults(config: str) -> dict[str, Any]:
    radius, f_first, f_last = CONFIGURATIONS[config]
    return {
        "frames": 30, "width": 640, "height": 480, "fps": 2.0, "format": "mono8", "pp_offset": (0.0, 0.0),
        "motion": "circle", "zoom_law": "linear", "circle_radius_deg": radius, "f_wide": f_first,
        "f_tele": f_last,
    }  # fmt: skip


def resolve(args: argparse.Namespace) -> argparse.Namespace:
    """Fill the options left unset: the --paper-config preset first, then the plain defaults."""
    if getattr(args, "resolved", False):
        return args
    _check(args.f_tele is None or args.zoom_max is None, "give --f-tele or --zoom-max, not both")
    preset = paper_defaults(args.paper_config) if args.paper_config else {}
    if args.zoom_max is not None:
        preset.pop("f_tele", None)
    for name, value in {**DEFAULTS, **preset}.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    args.resolved = True
    return args


def _f_wide(args: argparse.Namespace) -> float:
    return float(args.f_wide if args.f_wide is not None else focal_from_hfov(args.width, args.hfov))


def _zoom_max(args: argparse.Namespace) -> float:
    return float(args.zoom_max if args.f_tele is None else args.f_tele / _f_wide(args))


def validate(args: argparse.Namespace) -> None:
    """One-line CliError for every absurd option (before any work is done)."""
    resolve(args)
    _check(args.frames >= 2, f"--frames must be at least 2, got {args.frames}")
    _check(args.frames <= 1_000_000, f"--frames must be at most 1000000, got {args.frames}")
    _check(16 <= args.width <= 16384 and 16 <= args.height <= 16384, "--width/--height must be in 16..16384")
    _check(_finite(args.fps) and 0.0 < args.fps <= 1000.0, f"--fps must be in (0, 1000], got {args.fps}")
    _check(_finite(args.start_time) and 0.0 <= args.start_time < 4e9, "--start-time must be in [0, 4e9) s")
    _check(_finite(args.hfov) and 1.0 <= args.hfov <= 170.0, f"--hfov must be in [1, 170], got {args.hfov}")
    if args.f_wide is not None:
        _check(_finite(args.f_wide) and args.f_wide > 1.0, f"--f-wide must be > 1 pixel, got {args.f_wide}")
    if args.f_tele is not None:
        _check(
            _finite(args.f_tele) and args.f_tele >= _f_wide(args),
            f"--f-tele must be >= the wide end's focal length {_f_wide(args):g}, got {args.f_tele}",
        )
    zoom_max = _zoom_max(args)
    _check(_finite(args.zoom_max) and args.zoom_max >= 1.0, f"--zoom-max must be >= 1, got {args.zoom_max}")
    _check(
        _finite(args.lens_ratio) and args.lens_ratio >= max(zoom_max, 1.0 + 1e-6) and args.lens_ratio > 1.0,
        f"--lens-ratio must be > 1 and >= --zoom-max, got {args.lens_ratio}",
    )
    _check(
        _finite(args.pan_amplitude) and 0.0 <= args.pan_amplitude <= 170.0,
        f"--pan-amplitude must be in [0, 170] deg, got {args.pan_amplitude}",
    )
    _check(
        _finite(args.tilt_amplitude) and 0.0 <= args.tilt_amplitude <= 60.0,
        f"--tilt-amplitude must be in [0, 60] deg, got {args.tilt_amplitude}",
    )
    _check(_finite(args.pan_cycles, args.tilt_cycles), "--pan-cycles/--tilt-cycles must be finite")
    _check(
        _finite(args.circle_radius_deg) and 0.0 < args.circle_radius_deg <= 60.0,
        f"--circle-radius-deg must be in (0, 60], got {args.circle_radius_deg}",
    )
    _check(_finite(args.circle_turns) and args.circle_turns > 0.0, "--circle-turns must be > 0")
    _check(_finite(args.pan_centre) and abs(args.pan_centre) <= 180.0, "--pan-centre must be in [-180, 180]")
    period = (args.frames - 1) / args.fps
    _check(
        _finite(args.slow_start) and 0.0 <= args.slow_start <= period,
        f"--slow-start must be in [0, {period:g}] s (the sequence's length), got {args.slow_start}",
    )
    _check(_finite(args.dwell) and args.dwell >= 0.0, f"--dwell must be >= 0 s, got {args.dwell}")
    _check(_finite(*args.pp_offset, *args.pp_drift), "--pp-offset/--pp-drift must be finite")
    _check(
        max(map(abs, (*args.pp_offset, *args.pp_drift))) <= 0.25 * min(args.width, args.height),
        "--pp-offset/--pp-drift must stay within a quarter of the image size",
    )
    _check(
        _finite(args.distortion) and -0.3 <= args.distortion <= 0.5,
        f"--distortion must be in [-0.3, 0.5], got {args.distortion}",
    )
    _check(
        _finite(args.encoder_rate) and 0.0 < args.encoder_rate <= 10000.0,
        f"--encoder-rate must be in (0, 10000] Hz, got {args.encoder_rate}",
    )
    _check(_finite(args.encoder_lag) and abs(args.encoder_lag) <= 10.0, "--encoder-lag must be within +-10 s")
    _check(_finite(args.pan_tilt_noise) and args.pan_tilt_noise >= 0.0, "--pan-tilt-noise must be >= 0")
    _check(_finite(args.zoom_noise) and args.zoom_noise >= 0.0, "--zoom-noise must be >= 0")
    _check(1 <= args.jpeg_quality <= 100, f"--jpeg-quality must be in 1..100, got {args.jpeg_quality}")
    _check(
        _finite(args.image_noise) and 0.0 <= args.image_noise <= 100.0, "--image-noise must be in [0, 100]"
    )
    _check(
        _finite(args.brightness_drift) and 0.0 <= args.brightness_drift < 1.0,
        "--brightness-drift must be in [0, 1)",
    )
    _check(args.namespace.startswith("/") and " " not in args.namespace, "--namespace must start with /")
    _check(1 <= args.jobs <= 64, f"--jobs must be in 1..64, got {args.jobs}")
    validate_real_video(args)
    try:
        make_setup(args)
    except ValueError as exc:  # e.g. a patrol whose dwells fill the sequence
        raise CliError(str(exc)) from None


def validate_real_video(args: argparse.Namespace) -> None:
    period = (args.frames - 1) / args.fps
    _check(0 <= args.moving_objects <= 50, f"--moving-objects must be in 0..50, got {args.moving_objects}")
    if args.follow_target is not None:
        t0, t1 = args.follow_target
        _check(
            _finite(t0, t1) and 0.0 <= t0 < t1 <= period,
            f"--follow-target T0 T1 must satisfy 0 <= T0 < T1 <= {period:g} s (the sequence)",
        )
    _check(_finite(args.exposure_steps) and args.exposure_steps >= 0.0, "--exposure-steps must be >= 0 s")
    _check(_finite(args.vignetting) and 0.0 <= args.vignetting <= 0.9, "--vignetting must be in [0, 0.9]")
    _check(
        _finite(args.rolling_shutter) and 0.0 <= args.rolling_shutter <= 1.0 / args.fps,
        f"--rolling-shutter must be in [0, 1 / fps = {1.0 / args.fps:g}] s",
    )


def real_video_scene(args: argparse.Namespace, panorama: Panorama, profile: CameraProfile) -> Nuisances:
    """The nuisances the options ask for (objects drawn from their own random stream)."""
    rng = np.random.default_rng([args.seed, 4])
    objects = crossing_objects(args.moving_objects, panorama, profile, rng)
    if args.follow_target is not None:
        objects += (followed_target(panorama, profile, *args.follow_target, rng),)
    return Nuisances(
        objects=objects,
        readout=args.rolling_shutter,
        exposure=ExposureSteps(args.exposure_steps) if args.exposure_steps > 0.0 else None,
        vignetting=args.vignetting,
        low_light=LowLight() if args.low_light else None,
    )


def _out_path(path: str) -> Path:
    out = Path(path)
    _check(not out.exists() and not out.is_symlink(), f"{out}: already exists (refusing to overwrite)")
    _check(out.parent.is_dir(), f"{out.parent}: no such directory")
    _check(out.name not in ("", ".", ".."), f"{path}: not a valid bag path")
    return out


def load_panorama(path: str) -> np.ndarray:
    p = Path(path)
    _check(p.exists(), f"{p}: no such file")
    _check(p.is_file(), f"{p}: not a file")
    image = cv2.imread(str(p), cv2.IMREAD_COLOR)
    _check(image is not None and image.size > 0, f"{p}: cannot read the image (not an image file?)")
    h, w = image.shape[:2]
    _check(
        is_equirectangular(w, h),
        f"{p}: {w}x{h} is not an equirectangular panorama (width must be twice the height)",
    )
    return image


# --------------------------------------------------------------------------------------------------
# The scene
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Setup:
    profile: CameraProfile
    zoom: ZoomEncoder
    encoders: EncoderModel
    image_model: ImageModel
    frame_times: np.ndarray  # seconds from the first frame
    start_ns: int


def make_setup(args: argparse.Namespace) -> Setup:
    resolve(args)
    f_wide = _f_wide(args)
    period = (args.frames - 1) / args.fps
    profile = CameraProfile(
        width=args.width,
        height=args.height,
        period=period,
        f_wide=f_wide,
        zoom_max=_zoom_max(args),
        pan_amplitude=float(np.radians(args.pan_amplitude)),
        tilt_amplitude=float(np.radians(args.tilt_amplitude)),
        pan_cycles=args.pan_cycles,
        tilt_cycles=args.tilt_cycles,
        waveform=args.waveform,
        pp_offset=tuple(args.pp_offset),
        pp_drift=tuple(args.pp_drift),
        corner_shift=args.distortion,
        motion=args.motion,
        circle_radius=float(np.radians(args.circle_radius_deg)),
        circle_period=args.frames / args.fps / args.circle_turns,  # frames evenly spaced round a turn
        dwell=args.dwell,
        pan_centre=float(np.radians(args.pan_centre)),
        zoom_law=args.zoom_law,
        slow_start=args.slow_start,
    )
    return Setup(
        profile=profile,
        zoom=ZoomEncoder(f_wide, lens_ratio=args.lens_ratio),
        encoders=EncoderModel(
            args.encoder_rate, args.encoder_lag, float(np.radians(args.pan_tilt_noise)), args.zoom_noise
        ),
        image_model=ImageModel(args.image_noise, args.brightness_drift, period),
        frame_times=np.arange(args.frames) / args.fps,
        start_ns=round(args.start_time * 1e9),
    )


# --------------------------------------------------------------------------------------------------
# Messages (rosbags dataclasses)
# --------------------------------------------------------------------------------------------------
def _header(types: Any, stamp_ns: int, frame_id: str) -> Any:
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
    )


def camera_info_msg(types: Any, header: Any, state: CameraState, i: int, width: int, height: int) -> Any:
    K = state.K(i)
    lam = float(state.lam[i])
    model, d = (topics.GT_DIVISION_MODEL, [lam]) if lam != 0.0 else (PLUMB_BOB, [0.0] * 5)
    P = np.hstack([K, np.zeros((3, 1))])
    roi = types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return types[INFO_TYPE](
        header=header, height=height, width=width, distortion_model=model, d=np.array(d, dtype=np.float64),
        k=K.ravel().astype(np.float64), r=np.eye(3).ravel(), p=P.ravel().astype(np.float64),
        binning_x=0, binning_y=0, roi=roi,
    )  # fmt: skip


def joint_state_msg(types: Any, header: Any, values: tuple[float, float, float]) -> Any:
    empty = np.zeros(0, dtype=np.float64)
    return types[JOINT_TYPE](
        header=header,
        name=list(topics.JOINT_NAMES),
        position=np.array(values, dtype=np.float64),
        velocity=empty,
        effort=empty,
    )


def image_msg(types: Any, header: Any, fmt: str, payload: np.ndarray | bytes, size: tuple[int, int]) -> Any:
    data = np.frombuffer(payload, dtype=np.uint8) if isinstance(payload, bytes) else payload.reshape(-1)
    if fmt in ("jpeg", "png"):
        return types[COMPRESSED_TYPE](header=header, format=fmt, data=data)
    w, h = size
    channels = 1 if fmt == "mono8" else 3
    return types[IMAGE_TYPE](
        header=header, height=h, width=w, encoding=fmt, is_bigendian=0, step=w * channels, data=data
    )


# --------------------------------------------------------------------------------------------------
# Rendering pipeline
# --------------------------------------------------------------------------------------------------
def frame_renderer(
    args: argparse.Namespace,
    panorama: Panorama,
    setup: Setup,
    truth: CameraState,
    scene: Nuisances | None = None,
) -> Callable[[int], tuple[np.ndarray | bytes, np.ndarray | None]]:
    """frame index -> (encoded image (bytes for jpeg/png, a uint8 array for raw formats), the moving
    objects' mask when the scene has objects)."""
    interpolation = cv2.INTER_CUBIC if args.interpolation == "cubic" else cv2.INTER_LINEAR
    size = (args.width, args.height)
    scene = scene or Nuisances()

    def render(i: int) -> tuple[np.ndarray | bytes, np.ndarray | None]:
        mask = None
        if scene.geometric:
            view, mask = scene.render(panorama, setup.profile, float(truth.t[i]), interpolation)
        else:
            view = render_view(
                panorama, truth.K(i), truth.R(i), size, float(truth.lam[i]) or None, interpolation
            )
        if scene.photometric:
            noise = np.random.default_rng([args.seed, 3, i])
            view = scene.expose(view, float(truth.t[i]), truth.pp[i], noise)
        payload = encoded(view, i)
        return payload, (mask if scene.objects else None)

    def encoded(view: np.ndarray, i: int) -> np.ndarray | bytes:
        rng = np.random.default_rng([args.seed, 2, i])  # one stream per frame: order-independent
        image = setup.image_model.apply(view, float(truth.t[i]), rng)
        if args.format == "jpeg":
            return _encode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, args.jpeg_quality])
        if args.format == "png":
            return _encode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        return image

    return render


def _encode(ext: str, image: np.ndarray, params: list[int]) -> bytes:
    ok, buf = cv2.imencode(ext, image, params)
    if not ok:
        raise CliError(f"cannot encode a {ext} image")
    return buf.tobytes()


def ordered_map(fn: Callable[[int], Any], count: int, jobs: int, ahead: int = 4) -> Iterator[Any]:
    """fn(0), fn(1), ... in order, computed by `jobs` threads at most `ahead` items ahead."""
    if jobs <= 1:
        yield from (fn(i) for i in range(count))
        return
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        pending: deque[Future] = deque()
        for i in range(count):
            pending.append(pool.submit(fn, i))
            if len(pending) >= ahead:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


class Progress:
    """A line on stderr every `every` seconds: frames done, frames/s, time left."""

    def __init__(self, total: int, quiet: bool, every: float = 2.0) -> None:
        self.total, self.quiet, self.every = total, quiet, every
        self.start = self.last = time.monotonic()

    def update(self, done: int) -> None:
        now = time.monotonic()
        if self.quiet or (now - self.last < self.every and done < self.total):
            return
        self.last = now
        rate = done / max(now - self.start, 1e-9)
        eta = (self.total - done) / max(rate, 1e-9)
        print(f"synth: {done}/{self.total} frames, {rate:.1f} frames/s, {eta:.0f} s left", file=sys.stderr)


@dataclass(frozen=True)
class Topics:
    image: str
    image_type: str
    encoders: str
    camera_info: str
    truth: str

    @classmethod
    def for_args(cls, args: argparse.Namespace) -> Topics:
        ns = args.namespace.rstrip("/")

        def name(topic: str) -> str:  # the default namespace: the bag contract's absolute names
            return f"{ns}/{topic}" if ns else topics.bag_topic(topic)

        names = (topics.JOINT_STATES, topics.GT_CAMERA_INFO, topics.GT_JOINT_STATES)
        if args.format in ("jpeg", "png"):
            return cls(name(topics.IMAGE_COMPRESSED), COMPRESSED_TYPE, *map(name, names))
        return cls(name(topics.IMAGE_RAW), IMAGE_TYPE, *map(name, names))

    def types(self) -> list[tuple[str, str]]:
        return [
            (self.image, self.image_type),
            (self.encoders, JOINT_TYPE),
            (self.camera_info, INFO_TYPE),
            (self.truth, JOINT_TYPE),
        ]


def encoder_messages(types: Any, setup: Setup, seed: int) -> deque[tuple[int, Any]]:
    """(stamp ns, JointState) of every encoder sample, in time order (sim/render.py EncoderModel)."""
    times = setup.encoders.sample_times(float(setup.frame_times[0]), float(setup.frame_times[-1]))
    pan, tilt, zoom = setup.encoders.readings(
        setup.profile, setup.zoom, times, np.random.default_rng([seed, 1])
    )
    out: deque[tuple[int, Any]] = deque()
    for k, t in enumerate(times):
        t_ns = setup.start_ns + round(float(t) * 1e9)
        values = (float(pan[k]), float(tilt[k]), float(zoom[k]))
        out.append((t_ns, joint_state_msg(types, _header(types, t_ns, ""), values)))
    return out


def frame_messages(
    types: Any,
    args: argparse.Namespace,
    names: Topics,
    truth: CameraState,
    counts: np.ndarray,
    i: int,
    t_ns: int,
    payload: Any,
) -> list[tuple[str, str, Any]]:
    """The image of frame i and its ground truth (CameraInfo, JointState), all with the same header."""
    header = _header(types, t_ns, args.frame_id)
    gt = (float(truth.pan[i]), float(truth.tilt[i]), float(counts[i]))
    return [
        (
            names.image,
            names.image_type,
            image_msg(types, header, args.format, payload, (args.width, args.height)),
        ),
        (names.camera_info, INFO_TYPE, camera_info_msg(types, header, truth, i, args.width, args.height)),
        (names.truth, JOINT_TYPE, joint_state_msg(types, header, gt)),
    ]


def write_bag(args: argparse.Namespace, bag_path: Path, panorama: Panorama, setup: Setup) -> None:
    """Render every frame and write all topics, in time order, to a new bag at bag_path."""
    from ptz_selfcal.tools.bagio import BagWriter, typestore

    types = typestore().types
    names = Topics.for_args(args)
    truth = setup.profile.state(setup.frame_times)
    counts = setup.zoom.counts(truth.f)  # exact zoom counts of the ground truth
    encoders = encoder_messages(types, setup, args.seed)
    progress = Progress(args.frames, args.quiet)
    scene = real_video_scene(args, panorama, setup.profile)
    mask_topic = f"{args.namespace.rstrip('/')}/{topics.GT_MOVING_MASK}"
    with BagWriter(bag_path, storage=args.storage) as writer:
        for topic, msgtype in names.types():
            writer.add_topic(topic, msgtype)
        if scene.objects:
            writer.add_topic(mask_topic, MASK_TYPE)
        render = frame_renderer(args, panorama, setup, truth, scene)
        for i, (payload, mask) in enumerate(ordered_map(render, args.frames, args.jobs)):
            t_ns = setup.start_ns + round(float(truth.t[i]) * 1e9)
            while encoders and encoders[0][0] <= t_ns:
                writer.write(names.encoders, JOINT_TYPE, *encoders.popleft())
            for topic, msgtype, msg in frame_messages(types, args, names, truth, counts, i, t_ns, payload):
                writer.write(topic, msgtype, t_ns, msg)
            if mask is not None:  # the moving objects' ground truth, the image's header
                header = _header(types, t_ns, args.frame_id)
                writer.write(
                    mask_topic, MASK_TYPE, t_ns, image_msg(types, header, "mono8", mask, mask.shape[::-1])
                )
            progress.update(i + 1)
        for t_ns, msg in encoders:
            writer.write(names.encoders, JOINT_TYPE, t_ns, msg)


def params_yaml(args: argparse.Namespace, setup: Setup, panorama_sha256: str) -> str:
    """Every parameter of the bag (deterministic text: no wall-clock time, no absolute paths)."""
    import yaml

    p, z, e, im = setup.profile, setup.zoom, setup.encoders, setup.image_model
    # the motion's keys only when it is not the plain sweep: older bags' files stay byte-identical
    motion = {
        "motion": p.motion, "paper_config": args.paper_config,
        "circle_radius_deg": args.circle_radius_deg, "circle_period_s": p.circle_period,
        "circle_law": "principal ray on a cone of circle_radius about world +z, phase 2 pi t / circle_period",
        "dwell_s": p.dwell, "pan_centre_deg": args.pan_centre, "slow_start_s": p.slow_start,
        "slow_start_law": "path time r(t) period / r(period), r = t^3 / (3 S^2) for t < S, t - 2 S / 3 after",
        "f_tele_px": p.f_wide * p.zoom_max,
    }  # fmt: skip
    plain = p.motion == "sweep" and p.zoom_law == "cosine" and not (p.slow_start or p.pan_centre)
    zoom_law = (
        "z(t) = zoom_max ** ((1 - cos(2 pi t / period)) / 2), f = f_wide z"
        if p.zoom_law == "cosine"
        else "z(t) = 1 + (zoom_max - 1) t / period, f = f_wide z"
    )
    doc = {
        "generator": "ptz-selfcal synth",
        "panorama": {"file": Path(args.panorama).name, "sha256": panorama_sha256},
        "frames": args.frames, "fps": args.fps, "width": args.width, "height": args.height,
        "start_time_ns": setup.start_ns, "seed": args.seed, "format": args.format,
        "jpeg_quality": args.jpeg_quality, "interpolation": args.interpolation,
        "profile": {
            "period_s": p.period, "f_wide_px": p.f_wide, "zoom_max": p.zoom_max,
            "zoom_law": zoom_law,
            "pan_amplitude_deg": args.pan_amplitude, "tilt_amplitude_deg": args.tilt_amplitude,
            "pan_cycles": p.pan_cycles, "tilt_cycles": p.tilt_cycles, "waveform": p.waveform,
            "pp_offset_px": list(p.pp_offset), "pp_drift_px": list(p.pp_drift),
            "distortion_corner_shift_at_wide": p.corner_shift,
            "distortion_model": "division, lam on radius / fx about the principal point",
            **({} if plain else motion),
        },
        "zoom_encoder": {
            "law": "counts = 16384 * (ln(f / f_wide) / ln(lens_ratio)) ** exponent",
            "lens_ratio": z.lens_ratio, "exponent": z.exponent, "counts_max": z.counts_max,
        },
        "encoders": {
            "rate_hz": e.rate, "lag_s": e.lag,
            "lag_meaning": "a sample stamped t reports the head at t - lag (ingest time_offset = -lag)",
            "pan_tilt_sigma_deg": float(np.degrees(e.pan_tilt_sigma)), "zoom_sigma_counts": e.zoom_sigma,
        },
        "image_model": {"noise_sigma": im.noise_sigma, "brightness_drift": im.brightness_drift},
        **real_video_params(args),
    }  # fmt: skip
    return yaml.safe_dump(_plain(doc), sort_keys=False)


def real_video_params(args: argparse.Namespace) -> dict[str, Any]:
    """The real-video nuisances' parameters, only when one is on (other bags' files are unchanged)."""
    on = (
        args.moving_objects or args.follow_target or args.exposure_steps or args.vignetting
        or args.low_light or args.rolling_shutter
    )  # fmt: skip
    if not on:
        return {}
    low = LowLight()
    return {
        "real_video": {
            "moving_objects": args.moving_objects,
            "follow_target_s": list(args.follow_target) if args.follow_target else None,
            "moving_mask": f"{topics.GT_MOVING_MASK}: mono8, 255 on objects moving at the frame's time",
            "exposure_step_s": args.exposure_steps, "exposure_gains": list(ExposureSteps(1.0).gains),
            "vignetting_corner_loss": args.vignetting,
            "low_light_dim": low.dim if args.low_light else None,
            "low_light_electrons_per_level": low.electrons_per_level if args.low_light else None,
            "rolling_shutter_readout_s": args.rolling_shutter,
            "rolling_shutter_law": "row y at t + (y / (h - 1) - 1/2) readout; pan, tilt linear across it",
        }
    }  # fmt: skip


def _plain(value: Any) -> Any:
    """numpy scalars and tuples to plain Python (safe_dump's types)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value


def _sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def run(args: argparse.Namespace) -> int:
    validate(args)
    out = _out_path(args.out_bag)
    image = load_panorama(args.panorama)
    if args.format == "mono8":
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    panorama = build_panorama(image)
    setup = make_setup(args)
    start = time.monotonic()
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        bag = staging / out.name
        write_bag(args, bag, panorama, setup)
        (bag / "synth_params.yaml").write_text(params_yaml(args, setup, _sha256(args.panorama)))
        _check(not out.exists(), f"{out}: appeared while rendering (refusing to overwrite)")
        os.rename(bag, out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    if not args.quiet:
        seconds = time.monotonic() - start
        size = sum(f.stat().st_size for f in out.iterdir()) / 1e6
        print(
            f"synth: wrote {out} ({args.frames} frames in {seconds:.1f} s, "
            f"{args.frames / seconds:.1f} frames/s, {size:.1f} MB)",
            file=sys.stderr,
        )
    return 0
