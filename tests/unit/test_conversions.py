"""nodes/conversions.py: every input encoding to mono8 at the working size, and every way to be unusable."""

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from ptz_selfcal.camera.geometry import work_from_full
from ptz_selfcal.nodes.conversions import (
    MSG_TO_STATUS,
    STATUS_TO_MSG,
    FrameError,
    ImageLimits,
    camera_info_fields,
    compressed_size,
    compressed_to_working,
    downscale_factor,
    image_to_working,
    mono8_from_msg,
)
from ptz_selfcal.status import WARN_STATUSES, CalibrationStatus

RNG = np.random.default_rng(7)
W, H = 320, 240


def scene() -> np.ndarray:
    """A smooth colour test image (smooth, so JPEG and area averaging agree closely)."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    b = 128 + 100 * np.sin(x / 23.0)
    g = 128 + 100 * np.cos(y / 17.0)
    r = 128 + 60 * np.sin((x + y) / 31.0)
    return np.clip(np.dstack([b, g, r]), 0, 255).astype(np.uint8)


def raw(pixels: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> SimpleNamespace:
    h, w = pixels.shape[:2]
    rows = pixels.reshape(h, -1).view(np.uint8) if pixels.dtype == np.uint8 else None
    if pixels.dtype == np.uint16:
        rows = pixels.astype(">u2" if bigendian else "<u2").view(np.uint8).reshape(h, -1)
    padded = np.zeros((h, rows.shape[1] + pad), np.uint8)
    padded[:, : rows.shape[1]] = rows
    return SimpleNamespace(
        width=w,
        height=h,
        encoding=encoding,
        is_bigendian=int(bigendian),
        step=padded.shape[1],
        data=padded.tobytes(),
    )


def expected_gray(bgr: np.ndarray, factor: int) -> np.ndarray:
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    return cv2.resize(gray, (W // factor, H // factor), interpolation=cv2.INTER_AREA) if factor > 1 else gray


@pytest.mark.parametrize("encoding", ["mono8", "bgr8", "rgb8", "bgra8", "8UC1"])
@pytest.mark.parametrize("pad", [0, 7])
def test_raw_8bit_encodings(encoding, pad):
    bgr = scene()
    pixels = {
        "mono8": cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY),
        "8UC1": cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY),
        "bgr8": bgr,
        "rgb8": bgr[:, :, ::-1].copy(),
        "bgra8": cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA),
    }[encoding]
    out = image_to_working(raw(pixels, encoding, pad), working_width=160)
    assert (out.full_width, out.full_height, out.factor, out.scale) == (W, H, 2, 0.5)
    assert (
        out.image.shape == (H // 2, W // 2) and out.image.dtype == np.uint8 and out.image.flags.c_contiguous
    )
    assert np.abs(out.image.astype(int) - expected_gray(bgr, 2)).max() <= 1


@pytest.mark.parametrize("bigendian", [False, True])
def test_mono16_is_scaled_to_8_bits(bigendian):
    values = (RNG.integers(0, 4096, (H, W))).astype(np.uint16)
    full = image_to_working(raw(values, "mono16", bigendian=bigendian), 0)
    np.testing.assert_allclose(full.image, np.round(values * (255 / 65535)), atol=1)
    twelve_bit = image_to_working(raw(values, "mono16", bigendian=bigendian), 0, ImageLimits(mono16_max=4095))
    np.testing.assert_allclose(twelve_bit.image, np.round(values * (255 / 4095)), atol=1)


def test_working_scale_keeps_pixel_centres():
    """A bright 2x2 block at full-resolution pixels (100..101, 60..61) has its centre at (100.5, 60.5):
    in the working image (factor 2) it must be at work_from_full(0.5) of that, i.e. (50, 30)."""
    img = np.zeros((H, W), np.uint8)
    img[60:62, 100:102] = 255
    out = image_to_working(raw(img, "mono8"), 160)
    ys, xs = np.nonzero(out.image)
    centre = np.array([xs.mean(), ys.mean(), 1.0])
    expected = work_from_full(out.scale) @ np.array([100.5, 60.5, 1.0])
    np.testing.assert_allclose(centre[:2], expected[:2])


def test_sizes_not_divisible_by_the_factor_drop_the_last_columns():
    img = RNG.integers(0, 255, (241, 323), dtype=np.uint8)
    out = image_to_working(raw(img, "mono8"), 160)
    assert (
        out.factor == 2 and out.image.shape == (120, 161) and (out.full_width, out.full_height) == (323, 241)
    )
    assert out.image[0, 0] == pytest.approx(img[:2, :2].mean(), abs=1)


def test_downscale_factor():
    assert downscale_factor(1280, 640) == 2
    assert downscale_factor(1920, 640) == 3
    assert downscale_factor(640, 640) == 1
    assert downscale_factor(320, 640) == 1  # never upscales
    assert downscale_factor(1280, 0) == 1


@pytest.mark.parametrize("fmt", ["jpeg", "bgr8; jpeg compressed bgr8", "png", "rgb8; png compressed bgr8"])
def test_compressed_formats(fmt):
    bgr = scene()
    ext = ".png" if "png" in fmt else ".jpg"
    ok, buf = cv2.imencode(ext, bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    assert compressed_size(buf.tobytes()) == (ext.strip(".").replace("jpg", "jpeg"), W, H)
    out = compressed_to_working(SimpleNamespace(format=fmt, data=buf.tobytes()), 160)
    assert out.image.shape == (H // 2, W // 2) and (out.full_width, out.full_height) == (W, H)
    tolerance = 1.5 if ext == ".png" else 4.0
    assert np.abs(out.image.astype(float) - expected_gray(bgr, 2)).mean() < tolerance


def test_sixteen_bit_png():
    values = RNG.integers(0, 65535, (H, W)).astype(np.uint16)
    _ok, buf = cv2.imencode(".png", values)
    out = compressed_to_working(SimpleNamespace(format="16UC1; png compressed", data=buf.tobytes()), 0)
    np.testing.assert_allclose(out.image, np.round(values * (255 / 65535)), atol=1)


def kind(fn, *args) -> str:
    with pytest.raises(FrameError) as info:
        fn(*args)
    assert str(info.value)  # a message for the log
    return info.value.kind


def test_unusable_raw_images_raise_with_their_kind():
    good = raw(np.zeros((H, W), np.uint8), "mono8")
    lying_step = SimpleNamespace(**{**vars(good), "step": W - 1})
    short = SimpleNamespace(**{**vars(good), "data": good.data[:-5]})
    lying_encoding = SimpleNamespace(**{**vars(good), "encoding": "bgr8"})  # mono8 data, bgr8 label
    assert kind(image_to_working, lying_step, 160) == "bad_step"
    assert kind(image_to_working, short, 160) == "size_mismatch"
    assert kind(image_to_working, lying_encoding, 160) == "bad_step"
    assert kind(image_to_working, SimpleNamespace(**{**vars(good), "encoding": "yuv422"}), 160) == (
        "unsupported_encoding"
    )
    zero = SimpleNamespace(width=0, height=0, encoding="mono8", is_bigendian=0, step=0, data=b"")
    assert kind(image_to_working, zero, 160) == "zero_size"
    # 16k x 16k is refused from the header fields alone, before any allocation
    huge = SimpleNamespace(width=16384, height=16384, encoding="mono8", is_bigendian=0, step=16384, data=b"x")
    assert kind(image_to_working, huge, 160) == "too_large"


def test_unusable_compressed_images_raise_with_their_kind():
    _ok, buf = cv2.imencode(".jpg", scene())
    data = buf.tobytes()
    corrupt = data[:200] + bytes(RNG.integers(0, 255, 300, dtype=np.uint8))
    assert kind(compressed_to_working, SimpleNamespace(format="jpeg", data=b"not an image at all"), 160) == (
        "undecodable"
    )
    assert kind(compressed_to_working, SimpleNamespace(format="jpeg", data=corrupt), 160) == "undecodable"
    assert kind(compressed_to_working, SimpleNamespace(format="jpeg", data=b""), 160) == "zero_size"
    # a PNG header claiming 16k x 16k is refused before decoding
    _ok, png = cv2.imencode(".png", np.zeros((4, 4), np.uint8))
    bomb = bytearray(png.tobytes())
    bomb[16:24] = (16384).to_bytes(4, "big") * 2
    assert kind(compressed_to_working, SimpleNamespace(format="png", data=bytes(bomb)), 160) == "too_large"


def test_mono8_from_msg_checks_consistency():
    msg = raw(np.arange(12, dtype=np.uint8).reshape(3, 4), "mono8", pad=2)
    np.testing.assert_array_equal(mono8_from_msg(msg), np.arange(12).reshape(3, 4))
    with pytest.raises(FrameError):
        mono8_from_msg(SimpleNamespace(**{**vars(msg), "step": 3}))


def test_camera_info_fields_keep_p_consistent_with_k():
    K = np.array([[1000.0, 0.0, 650.0], [0.0, 1000.0, 350.0], [0.0, 0.0, 1.0]])
    fields = camera_info_fields(K, 1280, 720, k1=-0.1)
    assert (
        fields["p"][:3] == fields["k"][:3] and fields["p"][3] == 0.0 and fields["p"][4:7] == fields["k"][3:6]
    )
    assert fields["d"] == [-0.1, 0.0, 0.0, 0.0, 0.0] and fields["distortion_model"] == "plumb_bob"
    assert fields["r"] == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize(
    ("size", "working_width"), [((1920, 1080), 640), ((1280, 720), 640), ((1000, 750), 250)]
)
def test_jpeg_reduced_decoding_keeps_pixel_centres(size, working_width):
    """Decoding at 1/2, 1/4 (libjpeg) then INTER_AREA by the rest must match full decoding + INTER_AREA:
    no sub-pixel shift (phase correlation) and close grey levels."""
    w, h = size
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.clip(128 + 60 * np.sin(x / 37.0) * np.cos(y / 29.0) + 40 * np.sin((x - y) / 53.0), 0, 255)
    img = img.astype(np.uint8)
    data = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    out = compressed_to_working(SimpleNamespace(format="jpeg", data=data), working_width)
    k = out.factor
    full = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    reference = cv2.resize(full[: h // k * k, : w // k * k], (w // k, h // k), interpolation=cv2.INTER_AREA)
    assert out.image.shape == reference.shape
    (dx, dy), _ = cv2.phaseCorrelate(out.image.astype(np.float64), reference.astype(np.float64))
    assert abs(dx) < 0.02 and abs(dy) < 0.02
    assert np.abs(out.image.astype(float) - reference).mean() < 1.5


# ---------------------------------------------------------------------------------------------------------
# serialized messages read in place (frame_ingest's raw subscriptions)
@pytest.mark.parametrize("frame_id", ["", "c", "cam", "ptz_camera", "x" * 13])  # every alignment after it
@pytest.mark.parametrize("encoding", ["mono8", "bgr8", "mono16"])
def test_serialized_image_read_in_place_equals_rclpy_deserialisation(frame_id, encoding):
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import Image

    from ptz_selfcal.nodes.conversions import parse_serialized_image

    channels, depth = {"mono8": (1, 1), "bgr8": (3, 1), "mono16": (1, 2)}[encoding]
    msg = Image(height=H, width=W, encoding=encoding, is_bigendian=1 if depth == 2 else 0)
    msg.step = W * channels * depth + 3  # padded rows
    msg.data = RNG.integers(0, 256, msg.step * H, np.uint8).tobytes()
    msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id = -5, 999_999_999, frame_id
    data = serialize_message(msg)
    parsed = parse_serialized_image(data)
    reference = deserialize_message(data, Image)
    assert (parsed.sec, parsed.nanosec, parsed.frame_id) == (-5, 999_999_999, frame_id)
    for field in ("height", "width", "encoding", "is_bigendian", "step"):
        assert getattr(parsed, field) == getattr(reference, field), field
    assert bytes(parsed.data) == bytes(reference.data)
    assert parsed.stamp_ns == -5 * 1_000_000_000 + 999_999_999
    ours, theirs = image_to_working(parsed, 160), image_to_working(reference, 160)
    assert np.array_equal(ours.image, theirs.image) and ours.factor == theirs.factor == 2


def test_serialized_compressed_image_read_in_place():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage

    from ptz_selfcal.nodes.conversions import parse_serialized_image

    jpeg = cv2.imencode(".jpg", scene())[1].tobytes()
    msg = CompressedImage(format="bgr8; jpeg compressed bgr8", data=jpeg)
    msg.header.stamp.sec, msg.header.frame_id = 12, "ptz"
    parsed = parse_serialized_image(serialize_message(msg), compressed=True)
    assert (parsed.sec, parsed.frame_id, parsed.format) == (12, "ptz", msg.format)
    assert bytes(parsed.data) == jpeg
    assert compressed_to_working(parsed, 160).image.shape == (H // 2, W // 2)


def test_serialized_image_big_endian_cdr():
    """A big-endian publisher's CDR (encapsulation 0x0000), written by hand."""
    import struct

    from ptz_selfcal.nodes.conversions import parse_serialized_image

    pixels = bytes(range(6))
    body = struct.pack(">iII", 7, 8, 4) + b"cam\0" + struct.pack(">II", 2, 3) + struct.pack(">I", 6)
    body += b"mono8\0" + b"\0" + b"\0" + struct.pack(">II", 3, 6) + pixels  # is_bigendian, pad to 4
    parsed = parse_serialized_image(b"\x00\x00\x00\x00" + body)
    assert (parsed.sec, parsed.nanosec, parsed.frame_id, parsed.height, parsed.width) == (7, 8, "cam", 2, 3)
    assert (parsed.encoding, parsed.step, bytes(parsed.data)) == ("mono8", 3, pixels)


def test_serialized_image_truncated_is_malformed_and_sizes_checked_on_the_view():
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    from ptz_selfcal.nodes.conversions import parse_serialized_image

    msg = Image(height=H, width=W, encoding="mono8", step=W)
    msg.data = bytes(W * H)
    data = serialize_message(msg)
    # a data length beyond the end of the buffer (a truncated message) is refused without reading on
    lying = data[: len(data) - W * H]  # the data field claims W * H bytes, none follow
    with pytest.raises(FrameError) as exc:
        parse_serialized_image(lying)
    assert exc.value.kind == "malformed"
    for cut in (0, 3):
        assert parse_serialized_image(data[:cut]) is None  # no encapsulation header: not plain CDR
    with pytest.raises(FrameError) as exc:
        parse_serialized_image(data[:10])
    assert exc.value.kind == "malformed"
    assert parse_serialized_image(b"\x00\x07\x00\x00" + data[4:]) is None  # XCDR2: rclpy deserialises it
    parsed = parse_serialized_image(data)
    with pytest.raises(FrameError) as exc:
        image_to_working(parsed, 160, ImageLimits(max_bytes=W * H - 1))
    assert exc.value.kind == "too_large"


def test_status_constants_keep_their_values_and_model_mismatch_is_added():
    """Evaluators read FrameCalibration.status by number: the six first values never move, and
    MODEL_MISMATCH (a lens model that does not fit) is a seventh, mapped both ways, a diagnostics WARN."""
    from ptz_selfcal_msgs.msg import FrameCalibration

    before = ("INITIALISING", "CALIBRATING", "CONVERGED", "DEGENERATE_MOTION", "TRACKING_LOST")
    assert [getattr(FrameCalibration, name) for name in (*before, "PREDICTED_FROM_ZOOM")] == list(range(6))
    mismatch = CalibrationStatus.MODEL_MISMATCH
    assert STATUS_TO_MSG[mismatch] == FrameCalibration.MODEL_MISMATCH == 6
    assert MSG_TO_STATUS[6] is mismatch and mismatch in WARN_STATUSES
    assert CalibrationStatus.CONVERGED not in WARN_STATUSES
