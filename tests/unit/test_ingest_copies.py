"""Copies of an image in frame_ingest's conversions (issue 19, "count the copies"): a mono8 input at the
working size is used in place, the IngestedFrame fill copies the working image once, mono16 is scaled
without a clipped copy. Copies are counted as the bytes Python allocates (tracemalloc sees numpy's and
OpenCV's arrays and bytes objects)."""

import tracemalloc

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image

from ptz_selfcal.nodes.conversions import (
    ImageLimits,
    fill_mono8,
    image_to_working,
    parse_serialized_image,
)

RNG = np.random.default_rng(19)
W, H = 640, 360


def serialized(pixels: np.ndarray, encoding: str, step: int | None = None) -> bytes:
    """A sensor_msgs/Image as frame_ingest receives it (raw subscription: serialized CDR bytes)."""
    msg = Image()
    msg.height, msg.width = pixels.shape[:2]
    msg.encoding = encoding
    rows = pixels.reshape(pixels.shape[0], -1).view(np.uint8)
    msg.step = step if step is not None else rows.shape[1]
    if msg.step > rows.shape[1]:
        rows = np.hstack([rows, np.zeros((rows.shape[0], msg.step - rows.shape[1]), np.uint8)])
    msg.data = rows.tobytes()
    return serialize_message(msg)


def peak_bytes(fn) -> tuple[object, int]:
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        result = fn()
        return result, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_mono8_at_working_size_is_used_in_place():
    gray = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    data = serialized(gray, "mono8")
    msg = parse_serialized_image(data)
    working = image_to_working(msg, W)
    assert working.factor == 1 and working.image.flags.c_contiguous
    assert np.shares_memory(working.image, np.frombuffer(data, np.uint8))  # no conversion copy
    np.testing.assert_array_equal(working.image, gray)


def test_padded_mono8_is_copied_once_to_be_contiguous():
    gray = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    data = serialized(gray, "mono8", step=W + 16)
    working = image_to_working(parse_serialized_image(data), W)
    assert working.image.flags.c_contiguous and not np.shares_memory(
        working.image, np.frombuffer(data, np.uint8)
    )
    np.testing.assert_array_equal(working.image, gray)


def test_ingested_frame_fill_copies_the_working_image_once():
    image = RNG.integers(0, 256, (H, W), dtype=np.uint8)
    msg = Image(check_fields=True)  # as frame_ingest fills it: the data setter keeps the array given
    _, peak = peak_bytes(lambda: fill_mono8(msg, image))
    assert peak < 1.5 * image.nbytes, peak  # one copy (tobytes() and then the array: two)
    assert (msg.height, msg.width, msg.step, msg.encoding) == (H, W, W, "mono8")
    np.testing.assert_array_equal(np.frombuffer(msg.data, np.uint8).reshape(H, W), image)


@pytest.mark.parametrize("top", [65535, 4095])
def test_mono16_is_scaled_without_a_clipped_copy(top):
    values = RNG.integers(0, 65536, (H, W)).astype(np.uint16)  # above top too: they saturate at 255
    msg = parse_serialized_image(serialized(values, "mono16"))
    working, peak = peak_bytes(lambda: image_to_working(msg, W, ImageLimits(mono16_max=top)))
    assert peak < 1.5 * values.size, peak  # the mono8 result only (np.minimum first: 2 bytes more a pixel)
    expected = np.round(np.minimum(values, top) * (255.0 / top)).astype(np.uint8)
    np.testing.assert_array_equal(working.image, expected)
