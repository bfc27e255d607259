"""Message <-> numpy conversions (cv_bridge does not exist here): images in, mono8 at working size out.

Works on any object with the fields of sensor_msgs/Image (height, width, encoding, is_bigendian, step,
data) or sensor_msgs/CompressedImage (format, data): rclpy messages and rosbags messages alike.
Every way an input can be unusable raises FrameError with a short `kind` (the diagnostics counter name)
and a one-line explanation; nothing here logs or crashes.

The status vocabularies of ptz_selfcal.status are mapped to the message integers here and nowhere else
(FrameCalibration.status, HomographyStamped.state), both ways.

Working resolution: an integer downscale factor k, scale s = 1/k, so that both axes scale exactly and the
pixel-centre convention x_work = (x_full + 0.5) * s - 0.5 of camera/geometry.py holds (INTER_AREA averaging
of k x k blocks; a full image whose size is not a multiple of k loses its last < k columns/rows, which
does not move any coordinate). JPEG is decoded directly at 1/2, 1/4 or 1/8 size where possible (libjpeg
DCT scaling averages the same blocks).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ptz_selfcal.status import CalibrationStatus, TrackingState
from ptz_selfcal_msgs.msg import FrameCalibration, HomographyStamped

Mono8 = NDArray[np.uint8]

# encoding -> (channels, bytes per channel, colour order or None)
RAW_ENCODINGS: dict[str, tuple[int, int, str | None]] = {
    "mono8": (1, 1, None),
    "8UC1": (1, 1, None),
    "mono16": (1, 2, None),
    "16UC1": (1, 2, None),
    "bgr8": (3, 1, "bgr"),
    "rgb8": (3, 1, "rgb"),
    "8UC3": (3, 1, "bgr"),
    "bgra8": (4, 1, "bgra"),
    "rgba8": (4, 1, "rgba"),
}

_JPEG_REDUCED = {
    2: cv2.IMREAD_REDUCED_GRAYSCALE_2,
    4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
    8: cv2.IMREAD_REDUCED_GRAYSCALE_8,
}


# ---------------------------------------------------------------------------------------------------------
# Status vocabularies <-> message constants
# ---------------------------------------------------------------------------------------------------------
STATUS_TO_MSG: Mapping[CalibrationStatus, int] = MappingProxyType(
    {
        CalibrationStatus.INITIALISING: FrameCalibration.INITIALISING,
        CalibrationStatus.CALIBRATING: FrameCalibration.CALIBRATING,
        CalibrationStatus.CONVERGED: FrameCalibration.CONVERGED,
        CalibrationStatus.DEGENERATE_MOTION: FrameCalibration.DEGENERATE_MOTION,
        CalibrationStatus.TRACKING_LOST: FrameCalibration.TRACKING_LOST,
        CalibrationStatus.PREDICTED_FROM_ZOOM: FrameCalibration.PREDICTED_FROM_ZOOM,
        CalibrationStatus.MODEL_MISMATCH: FrameCalibration.MODEL_MISMATCH,
    }
)
MSG_TO_STATUS: Mapping[int, CalibrationStatus] = MappingProxyType({v: k for k, v in STATUS_TO_MSG.items()})

TRACKING_STATE_TO_MSG: Mapping[TrackingState, int] = MappingProxyType(
    {
        TrackingState.TRACKING: HomographyStamped.TRACKING,
        TrackingState.NEW_KEYFRAME: HomographyStamped.NEW_KEYFRAME,
        TrackingState.RELOCALISED: HomographyStamped.RELOCALISED,
        TrackingState.TRACKING_LOST: HomographyStamped.TRACKING_LOST,
        TrackingState.TEXTURELESS: HomographyStamped.TEXTURELESS,
    }
)
MSG_TO_TRACKING_STATE: Mapping[int, TrackingState] = MappingProxyType(
    {v: k for k, v in TRACKING_STATE_TO_MSG.items()}
)


class FrameError(ValueError):
    """An input frame that cannot be used; `kind` names its diagnostics counter."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class WorkingImage:
    image: Mono8  # mono8, working resolution, C-contiguous
    full_width: int
    full_height: int
    factor: int  # integer downscale factor k; scale = 1 / k

    @property
    def scale(self) -> float:
        return 1.0 / self.factor


@dataclass(frozen=True)
class ImageLimits:
    max_pixels: int = 50_000_000  # larger images are refused before any decoding
    max_bytes: int = 200_000_000  # larger payloads are refused
    mono16_max: int = 65535  # mono16 value mapped to 255 (e.g. 4095 for a 12-bit sensor)


def downscale_factor(full_width: int, working_width: int) -> int:
    """Integer factor k >= 1 whose working width full_width / k is nearest to working_width."""
    if working_width <= 0 or full_width <= working_width:
        return 1
    return max(1, round(full_width / working_width))


def _check_size(width: int, height: int, limits: ImageLimits) -> None:
    if width <= 0 or height <= 0:
        raise FrameError("zero_size", f"image of size {width}x{height}")
    if width * height > limits.max_pixels:
        raise FrameError(
            "too_large", f"image of {width}x{height} exceeds max_image_pixels={limits.max_pixels}"
        )


def _reduce(gray: Mono8, factor: int) -> Mono8:
    if factor == 1:
        return np.ascontiguousarray(gray)
    h, w = gray.shape
    wk, hk = w // factor, h // factor
    if wk == 0 or hk == 0:
        raise FrameError("zero_size", f"image of {w}x{h} is smaller than the downscale factor {factor}")
    cropped = gray[: hk * factor, : wk * factor]
    return cv2.resize(cropped, (wk, hk), interpolation=cv2.INTER_AREA)


def _to_gray8(pixels: np.ndarray, channels: int, order: str | None, limits: ImageLimits) -> Mono8:
    if pixels.dtype == np.uint16:
        if channels != 1:
            raise FrameError("unsupported_encoding", "16-bit colour images are not supported")
        top = max(1, int(limits.mono16_max))
        # convertScaleAbs saturates at 255, so values above top need no clipped copy first
        return cv2.convertScaleAbs(pixels, alpha=255.0 / top)
    if channels == 1:
        return pixels
    code = {
        "bgr": cv2.COLOR_BGR2GRAY,
        "rgb": cv2.COLOR_RGB2GRAY,
        "bgra": cv2.COLOR_BGRA2GRAY,
        "rgba": cv2.COLOR_RGBA2GRAY,
    }[order or "bgr"]
    return cv2.cvtColor(pixels, code)


def image_to_working(msg: Any, working_width: int, limits: ImageLimits | None = None) -> WorkingImage:
    """sensor_msgs/Image -> mono8 at the working resolution; FrameError when unusable."""
    limits = limits or ImageLimits()
    width, height, step = int(msg.width), int(msg.height), int(msg.step)
    encoding = str(msg.encoding)
    _check_size(width, height, limits)
    if encoding not in RAW_ENCODINGS:
        raise FrameError("unsupported_encoding", f"unsupported encoding {encoding!r}")
    channels, depth, order = RAW_ENCODINGS[encoding]
    row_bytes = width * channels * depth
    if step < row_bytes:
        raise FrameError(
            "bad_step", f"step {step} < width*bytes per pixel = {row_bytes} ({width}x{height} {encoding})"
        )
    data = msg.data
    size = len(data)
    if size > limits.max_bytes:
        raise FrameError("too_large", f"image payload of {size} bytes exceeds {limits.max_bytes}")
    if size != step * height:
        raise FrameError(
            "size_mismatch", f"data has {size} bytes, step*height = {step * height} ({encoding})"
        )
    buf = np.frombuffer(data, np.uint8).reshape(height, step)[:, :row_bytes]
    if depth == 2:
        dtype = np.dtype(">u2" if msg.is_bigendian else "<u2")
        pixels = np.ascontiguousarray(buf).view(dtype).astype(np.uint16, copy=False)
        pixels = pixels.reshape(height, width)
    else:
        pixels = buf.reshape(height, width, channels) if channels > 1 else buf
    factor = downscale_factor(width, working_width)
    gray = _to_gray8(pixels, channels, order, limits)
    return WorkingImage(_reduce(gray, factor), width, height, factor)


# ---------------------------------------------------------------------------------------------------------
# Serialized (CDR) sensor_msgs/Image and CompressedImage read in place: frame_ingest subscribes raw, checks
# the sizes in the header and converts straight from the received buffer, so a huge image is refused
# without being copied again (rclpy's deserialisation copies the pixels twice: into the C message, then into
# a Python array) and a normal one is converted without those copies.


@dataclass(frozen=True)
class SerializedImage:
    """The fields of sensor_msgs/Image (or, with `format`, CompressedImage) over a serialized message;
    `data` is a read-only view into the received buffer."""

    sec: int
    nanosec: int
    frame_id: str
    data: memoryview
    height: int = 0
    width: int = 0
    encoding: str = ""
    is_bigendian: int = 0
    step: int = 0
    format: str = ""

    @property
    def stamp_ns(self) -> int:
        return self.sec * 1_000_000_000 + self.nanosec


class _Cdr:
    """Plain CDR (XCDR1, the encoding of ROS 2 messages on every Tier-1 RMW) read from a buffer: 4-byte
    encapsulation header, then primitives aligned to their size relative to its end."""

    def __init__(self, buf: memoryview) -> None:
        self.buf = buf
        self.order = "<" if buf[1] == 1 else ">"  # CDR_LE / CDR_BE
        self.pos = 4

    def _take(self, size: int, align: int) -> memoryview:
        self.pos += -(self.pos - 4) % align
        end = self.pos + size
        if size < 0 or end > len(self.buf):
            raise FrameError("malformed", f"serialized message of {len(self.buf)} bytes is truncated")
        view, self.pos = self.buf[self.pos : end], end
        return view

    def u32(self) -> int:
        return struct.unpack(self.order + "I", self._take(4, 4))[0]

    def i32(self) -> int:
        return struct.unpack(self.order + "i", self._take(4, 4))[0]

    def u8(self) -> int:
        return self._take(1, 1)[0]

    def string(self) -> str:
        raw = self._take(self.u32(), 1)
        return bytes(raw).rstrip(b"\0").decode("utf-8", errors="replace")

    def octets(self) -> memoryview:
        return self._take(self.u32(), 1)


def parse_serialized_image(buffer: bytes | memoryview, compressed: bool = False) -> SerializedImage | None:
    """A serialized sensor_msgs/Image (or CompressedImage) read in place; None when its encapsulation is not
    plain CDR (then use rclpy.serialization.deserialize_message); FrameError("malformed") when truncated."""
    buf = memoryview(buffer).cast("B")
    if len(buf) < 4 or buf[0] != 0 or buf[1] not in (0, 1):
        return None
    cdr = _Cdr(buf)
    sec, nanosec, frame_id = cdr.i32(), cdr.u32(), cdr.string()
    if compressed:
        fmt = cdr.string()
        return SerializedImage(sec, nanosec, frame_id, cdr.octets(), format=fmt)
    height, width, encoding = cdr.u32(), cdr.u32(), cdr.string()
    is_bigendian, step = cdr.u8(), cdr.u32()
    return SerializedImage(sec, nanosec, frame_id, cdr.octets(), height, width, encoding, is_bigendian, step)


def compressed_size(data: bytes | memoryview | np.ndarray) -> tuple[str, int, int] | None:
    """(kind, width, height) read from a PNG or JPEG header without decoding; None if not recognised.
    (0, 0) as the size when the header cannot be parsed."""
    view = memoryview(np.ascontiguousarray(np.frombuffer(data, np.uint8)))
    b = bytes(view[:24])
    if b.startswith(b"\x89PNG\r\n\x1a\n"):
        if len(b) >= 24 and b[12:16] == b"IHDR":
            w, h = struct.unpack(">II", b[16:24])
            return "png", int(w), int(h)
        return "png", 0, 0
    if not b.startswith(b"\xff\xd8"):
        return None
    i, n = 2, len(view)
    while i + 9 < n:
        if view[i] != 0xFF:
            break
        marker = view[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length
            i += 2
            continue
        length = (view[i + 2] << 8) | view[i + 3]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame
            h = (view[i + 5] << 8) | view[i + 6]
            w = (view[i + 7] << 8) | view[i + 8]
            return "jpeg", int(w), int(h)
        if length < 2:
            break
        i += 2 + length
    return "jpeg", 0, 0


def _jpeg_reduction(factor: int, wk: int, hk: int) -> int:
    """The largest libjpeg DCT reduction (8, 4, 2) not above the downscale factor that divides the
    working block exactly (1: decode at full size)."""
    for r in (8, 4, 2):
        if r <= factor and (wk * factor) % r == 0 and (hk * factor) % r == 0:
            return r
    return 1


def compressed_to_working(msg: Any, working_width: int, limits: ImageLimits | None = None) -> WorkingImage:
    """sensor_msgs/CompressedImage (jpeg, png, "bgr8; jpeg compressed bgr8", 16-bit png) -> mono8."""
    limits = limits or ImageLimits()
    fmt = str(msg.format).lower()
    if "compresseddepth" in fmt:
        raise FrameError("unsupported_format", f"unsupported compressed format {msg.format!r}")
    data = np.frombuffer(msg.data, np.uint8)
    if data.size == 0:
        raise FrameError("zero_size", "empty compressed image")
    if data.size > limits.max_bytes:
        raise FrameError("too_large", f"compressed payload of {data.size} bytes exceeds {limits.max_bytes}")
    header = compressed_size(data)
    if header is None:
        raise FrameError("undecodable", f"compressed data ({msg.format!r}) is neither JPEG nor PNG")
    kind, w, h = header
    if w == 0 or h == 0:
        raise FrameError("undecodable", f"{kind} data without a readable size header")
    _check_size(w, h, limits)
    factor = downscale_factor(w, working_width)
    hk, wk = h // factor, w // factor
    if hk == 0 or wk == 0:
        raise FrameError("zero_size", f"image of {w}x{h} is smaller than the downscale factor {factor}")
    reduced = _jpeg_reduction(factor, wk, hk) if kind == "jpeg" else 1
    if reduced > 1:
        decoded = cv2.imdecode(data, _JPEG_REDUCED[reduced])
        if decoded is None:
            raise FrameError("undecodable", f"corrupt {kind} data ({data.size} bytes)")
        # The block of full-resolution pixels that makes whole working pixels, at 1/reduced size; then
        # INTER_AREA by the remaining (possibly fractional) factor keeps the pixel-centre convention.
        gray = decoded[: hk * factor // reduced, : wk * factor // reduced]
        if reduced != factor:
            gray = cv2.resize(gray, (wk, hk), interpolation=cv2.INTER_AREA)
        return WorkingImage(np.ascontiguousarray(gray), w, h, factor)
    decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise FrameError("undecodable", f"corrupt {kind} data ({data.size} bytes)")
    if decoded.shape[0] != h or decoded.shape[1] != w:
        raise FrameError(
            "undecodable", f"{kind} decoded to {decoded.shape[1]}x{decoded.shape[0]}, header {w}x{h}"
        )
    channels = 1 if decoded.ndim == 2 else decoded.shape[2]
    order = {1: None, 3: "bgr", 4: "bgra"}.get(channels)
    if channels not in (1, 3, 4):
        raise FrameError("unsupported_format", f"{kind} with {channels} channels")
    gray = _to_gray8(decoded, channels, order, limits)
    return WorkingImage(_reduce(gray, factor), w, h, factor)


def fill_mono8(msg: Any, image: Mono8) -> None:
    """Fill a sensor_msgs/Image (rclpy) with a mono8 numpy image (fast path for array.array data)."""
    import array

    image = np.ascontiguousarray(image, np.uint8)
    msg.height, msg.width = int(image.shape[0]), int(image.shape[1])
    msg.encoding = "mono8"
    msg.is_bigendian = 0
    msg.step = int(image.shape[1])
    data = array.array("B")
    data.frombytes(memoryview(image))  # one copy: tobytes() would make a second
    msg.data = data


def mono8_from_msg(msg: Any) -> Mono8:
    """A mono8 sensor_msgs/Image as a (read-only view) numpy array; FrameError when inconsistent."""
    if msg.encoding not in ("mono8", "8UC1"):
        raise FrameError("unsupported_encoding", f"expected mono8, got {msg.encoding!r}")
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    if w <= 0 or h <= 0:
        raise FrameError("zero_size", f"image of size {w}x{h}")
    if step < w or len(msg.data) != step * h:
        raise FrameError("size_mismatch", f"step {step}, {len(msg.data)} bytes for {w}x{h} mono8")
    return np.frombuffer(msg.data, np.uint8).reshape(h, step)[:, :w]


def camera_info_fields(
    K: NDArray[np.float64], width: int, height: int, k1: float = 0.0, k2: float = 0.0
) -> dict:
    """The CameraInfo fields of DESIGN.md section 3 for a full-resolution K: K, P = [K|0], R = I,
    plumb_bob D = [k1, k2, 0, 0, 0]. Assign them with `for k, v in fields.items(): setattr(msg, k, v)`."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "width": int(width),
        "height": int(height),
        "distortion_model": "plumb_bob",
        "d": [float(k1), float(k2), 0.0, 0.0, 0.0],
        "k": [float(v) for v in K.ravel()],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [float(v) for v in P.ravel()],
    }


def stamp_to_sec(stamp: Any) -> float:
    return float(stamp.sec) + 1e-9 * float(stamp.nanosec)


def stamp_to_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


# ---------------------------------------------------------------------------------------------------------
# Parameter helpers shared by the nodes of this package: declared with descriptions, validated at start-up.


class ConfigError(ValueError):
    """A parameter with a wrong type or an absurd value: the node exits with status 2 and this message."""


@dataclass(frozen=True)
class Param:
    name: str
    default: Any
    description: str
    check: Any = None  # callable(value) -> error text or None; an InRange/OneOf also gives the descriptor
    read_only: bool = True
    bounds: tuple[float, float] | None = None  # the descriptor's range when `check` does not carry it


@dataclass(frozen=True)
class InRange:
    """Check of an inclusive range; its bounds also become the parameter descriptor's range."""

    lo: float
    hi: float

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.lo, self.hi)

    def __call__(self, value: Any) -> str | None:
        if not (self.lo <= value <= self.hi):  # also rejects NaN
            return f"must be in [{self.lo}, {self.hi}], got {value}"
        return None


@dataclass(frozen=True)
class OneOf:
    """Check of a string's choices; they also go into the parameter's description."""

    choices: tuple[str, ...]

    def __call__(self, value: Any) -> str | None:
        if value in self.choices:
            return None
        return f"must be one of {', '.join(self.choices)}, got {value!r}"


def in_range(lo: float, hi: float) -> InRange:
    return InRange(lo, hi)


def one_of(*choices: str) -> OneOf:
    return OneOf(tuple(choices))


_INT64 = (-(1 << 63), (1 << 63) - 1)


def parameter_descriptor(spec: Param, *, read_only: bool | None = None) -> Any:
    """The ParameterDescriptor of `spec`: description, read_only, its range (FloatingPointRange for a
    float, IntegerRange for an int, of each element for an array) and its choices."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

    description = spec.description
    descriptor = ParameterDescriptor(read_only=spec.read_only if read_only is None else read_only)
    choices = getattr(spec.check, "choices", None)
    if choices:
        descriptor.additional_constraints = f"one of: {', '.join(choices)}"
        description = f"{description} (one of: {', '.join(choices)})"
    bounds = spec.bounds or getattr(spec.check, "bounds", None)
    sample = spec.default[0] if isinstance(spec.default, list | tuple) and spec.default else spec.default
    if bounds is not None and not isinstance(sample, bool):
        lo, hi = bounds
        if isinstance(sample, int):
            # an integer parameter's range is in integers: the whole numbers inside the real bounds
            lo_i = _INT64[0] if lo == -math.inf else max(_INT64[0], math.ceil(lo))
            hi_i = _INT64[1] if hi == math.inf else min(_INT64[1], math.floor(hi))
            descriptor.integer_range = [IntegerRange(from_value=lo_i, to_value=hi_i, step=0)]
        elif isinstance(sample, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
    descriptor.description = description
    return descriptor


def declare_params(node: Any, specs: list[Param]) -> dict[str, Any]:
    """Declare every parameter with its descriptor (description, range, choices), check types and
    ranges; ConfigError otherwise.

    Declared first without its range, so that a bad start-up value gets this package's message (rclpy's
    range check would refuse it with its own), then given the full descriptor: from then on rclpy's
    parameter service refuses an out-of-range SetParameters with the old value kept."""
    values: dict[str, Any] = {}
    for spec in specs:
        loose = parameter_descriptor(spec, read_only=False)
        loose.integer_range, loose.floating_point_range = [], []
        try:
            value = node.declare_parameter(spec.name, spec.default, loose).value
        except Exception as exc:  # rclpy raises several exception types for wrongly typed overrides
            raise ConfigError(f"parameter {spec.name}: {_first_line(exc)}") from exc
        if isinstance(spec.default, float) and isinstance(value, int):
            value = float(value)
        if spec.default is not None and not isinstance(value, type(spec.default)):
            raise ConfigError(f"parameter {spec.name}: expected {type(spec.default).__name__}, got {value!r}")
        if spec.check is not None:
            error = spec.check(value)
            if error:
                raise ConfigError(f"parameter {spec.name} {error}")
        descriptor = parameter_descriptor(spec)
        descriptor.type = node.describe_parameter(spec.name).type  # the declared type (static typing)
        try:
            node.set_descriptor(spec.name, descriptor)
        except Exception as exc:  # a value the check let through but the descriptor's range refuses
            raise ConfigError(f"parameter {spec.name}: {_first_line(exc)}") from exc
        values[spec.name] = value
    return values


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def diagnostic_values(counters: dict[str, Any]) -> list:
    from diagnostic_msgs.msg import KeyValue

    return [KeyValue(key=str(k), value=str(v)) for k, v in counters.items()]
