"""mosaic node: the live panorama of what the camera has seen (paper section 8), beside the calibrator.

Subscribes to topics.FRAME_IN (the working-resolution mono8 image), topics.FRAME_CALIBRATION (K, D,
orientation, status) and topics.HOMOGRAPHY (the tracking reference: FrameCalibration does not name it),
raw, matched by header stamp (each frame's own reference: the three topics arrive in any order). The
subscriptions are polled, not called back: their messages wait in the middleware's KEEP_LAST queues and
are taken every POLL_PERIOD, a few executor wake-ups a second where a callback costs one per message.
Only CONVERGED frames with a valid orientation enter, at most one per `frame_period` seconds of image
time (the first after it: the others are dropped by their stamp, never deserialised), into a fixed
`width` x `width`/2 spherical canvas (mosaic/live.py: memory is the canvas, about width^2 bytes; each
frame touches its own footprint only). The orientations are relative to the calibration's reference, so
a new tracking reference starts a new mosaic. Every `publish_period` seconds, when frames entered since
the last one, the canvas goes out as a sensor_msgs/CompressedImage on topics.MOSAIC (JPEG grey, or PNG
with alpha 0 where nothing was seen), its header the newest frame's. Off unless started (the suite's
launch parameter). Run:
    python -m ptz_selfcal.nodes.mosaic_node --ros-args -p width:=8192
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CompressedImage

from ptz_selfcal import topics
from ptz_selfcal.camera.geometry import matrix_from_quaternion
from ptz_selfcal.mosaic.live import FORMATS, LiveMosaic
from ptz_selfcal.mosaic.warp import FrameView
from ptz_selfcal.nodes.conversions import MSG_TO_STATUS, FrameError, declare_params, mono8_from_msg
from ptz_selfcal.nodes.params import config_kwargs, params_from
from ptz_selfcal.nodes.runtime import CountedWarnings, PolledGroup, reliable_qos, run_node, take
from ptz_selfcal.settings import setting
from ptz_selfcal.status import CalibrationStatus
from ptz_selfcal.tools.bagio import header_stamp_ns
from ptz_selfcal_msgs.msg import FrameCalibration, HomographyStamped, IngestedFrame

# Messages of each input kept while their partners are on the way (they come on three topics), and
# the middleware's queue of images between two polls.
PENDING = 16
# Seconds between two takes of the inputs, and the middleware's queue of the small ones (a few bytes
# each). No image is lost between two polls below PENDING / POLL_PERIOD frames/s (64); beyond, the
# oldest go and a later frame enters.
POLL_PERIOD = 0.25
QUEUE_DEPTH = 64


@dataclass(frozen=True)
class MosaicNodeConfig:
    """The mosaic node's parameters."""

    width: int = setting(
        4096,
        "mosaic width in pixels (the full turn; the height is half of it): the canvas is fixed, about "
        "width^2 bytes (8192: 67 MB)",
        bounds=(256, 16384),
    )
    frame_period: float = setting(
        0.5,
        "seconds of image time between two frames entering the mosaic at least (the cost: one warp of "
        "a frame's footprint each time)",
        bounds=(0.0, 3600.0),
    )
    publish_period: float = setting(
        5.0, "seconds between two published mosaics (only when frames entered)", bounds=(0.1, 86400.0)
    )
    format: str = setting("jpeg", "jpeg (grey) or png (grey + alpha where seen)", choices=FORMATS)
    jpeg_quality: int = setting(85, "JPEG quality of the published mosaic", bounds=(1, 100))


PARAMS = params_from(MosaicNodeConfig)


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _put(pending: OrderedDict, key: int, value: Any) -> None:
    pending[key] = value
    while len(pending) > PENDING:
        pending.popitem(last=False)


def _never(msg: Any) -> None:
    raise AssertionError("a polled subscription's messages are taken, never called back")


def frame_view(fc: Any, width: int, height: int) -> FrameView | None:
    """A FrameCalibration's geometry (full resolution), None without a valid orientation or K."""
    o = fc.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    if not (np.all(np.isfinite(q)) and abs(float(np.linalg.norm(q)) - 1.0) < 1e-3):
        return None
    values = (fc.fx, fc.fy, fc.cx, fc.cy, fc.skew, fc.k1, fc.k2)
    if not all(math.isfinite(v) for v in values) or fc.fx <= 0.0 or fc.fy <= 0.0:
        return None
    K = np.array([[fc.fx, fc.skew, fc.cx], [0.0, fc.fy, fc.cy], [0.0, 0.0, 1.0]])
    return FrameView(K, (float(fc.k1), float(fc.k2), 0.0), matrix_from_quaternion(q), width, height)


class MosaicNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("mosaic", **{"namespace": topics.NAMESPACE, **kwargs})
        p = declare_params(self, PARAMS)
        self._config = MosaicNodeConfig(**config_kwargs(MosaicNodeConfig, p))
        self._mosaic = LiveMosaic(self._config.width)
        self._counts: Counter[str] = Counter()
        self._warnings = CountedWarnings(self, self._counts)
        # serialised messages by header stamp: only the frames that enter are ever deserialised
        self._frames: OrderedDict[int, bytes] = OrderedDict()
        self._calibrations: OrderedDict[int, bytes] = OrderedDict()
        self._references: OrderedDict[int, bytes] = OrderedDict()
        self._reference: str | None = None  # the mosaic's
        self._last_added_ns: int | None = None
        self._header: Any = None
        self._dirty = False
        self._cpu = 0.0  # seconds in this node's callbacks
        self._pub = self.create_publisher(CompressedImage, topics.MOSAIC, reliable_qos(1))
        # polled, not called back: the inputs wait in the middleware's queues (KEEP_LAST) and are taken
        # every POLL_PERIOD, so that the node wakes a few times a second instead of thrice per frame
        polled = PolledGroup()
        self._inputs = [
            (
                self.create_subscription(
                    t, topic, _never, reliable_qos(depth), raw=True, callback_group=polled
                ),
                store,
            )
            for t, topic, store, depth in (
                # the small ones first: an image then finds its partners already here
                (HomographyStamped, topics.HOMOGRAPHY, self._references, QUEUE_DEPTH),
                (FrameCalibration, topics.FRAME_CALIBRATION, self._calibrations, QUEUE_DEPTH),
                (IngestedFrame, topics.FRAME_IN, self._frames, PENDING),
            )
        ]
        self.create_timer(POLL_PERIOD, self._poll)
        self.create_timer(self._config.publish_period, self._publish)
        p = self._mosaic.projection
        self.get_logger().info(
            f"mosaic of the CONVERGED frames of {topics.FRAME_IN} -> {self._pub.topic_name}: {p.width}x"
            f"{p.height} ({self._mosaic.nbytes / 1e6:.0f} MB), a frame every {self._config.frame_period} s, "
            f"published every {self._config.publish_period} s as {self._config.format}"
        )

    @property
    def counts(self) -> Counter[str]:
        return self._counts

    # ----------------------------------------------------------------------------------------------
    def _poll(self) -> None:
        """Take what waits on the three inputs: most frames come too soon after the last one that
        entered, and are dropped by their header stamp alone (the CDR's first field), never
        deserialised."""
        start = time.thread_time()
        for sub, store in self._inputs:
            while (raw := take(sub)) is not None:
                stamp = header_stamp_ns(raw)
                if stamp is not None and self._wanted(stamp):
                    _put(store, stamp, raw)
                    self._match(stamp)
        self._cpu += time.thread_time() - start

    def _wanted(self, stamp: int) -> bool:
        """Whether a frame of this stamp may enter now (frame_period of image time since the last)."""
        last = self._last_added_ns
        return last is None or stamp - last >= self._config.frame_period * 1e9 or stamp < last

    def _match(self, stamp: int) -> None:
        """A frame enters once its image, its calibration and its homography (which names the
        reference the orientation is relative to) are all here; they come on three topics, in any order."""
        raw = [store.get(stamp) for store in (self._frames, self._calibrations, self._references)]
        if any(r is None for r in raw):
            return
        for store in (self._frames, self._calibrations, self._references):
            del store[stamp]
        fc = deserialize_message(raw[1], FrameCalibration)
        self._counts["calibrations_taken"] += 1
        if MSG_TO_STATUS.get(fc.status) is not CalibrationStatus.CONVERGED:
            self._counts["not_converged"] += 1
            return
        frame = deserialize_message(raw[0], IngestedFrame)
        view = frame_view(fc, int(frame.full_width), int(frame.full_height))
        if view is None:
            self._counts["invalid_calibration"] += 1
            return
        try:
            image = mono8_from_msg(frame.image)
        except FrameError as exc:
            self._warnings.warn_once("bad_image", str(exc))
            return
        h = deserialize_message(raw[2], HomographyStamped)
        reference = f"{h.reference_frame_id}@{h.reference_stamp.sec}.{h.reference_stamp.nanosec:09d}"
        if reference != self._reference:
            if self._reference is not None:
                self.get_logger().info(f"new tracking reference {reference}: a new mosaic")
                self._counts["new_mosaics"] += 1
            self._mosaic.reset()
            self._reference = reference
        if self._mosaic.add(image, view) is not None:
            self._counts["frames_added"] += 1
            self._last_added_ns, self._header, self._dirty = stamp, frame.header, True

    def _publish(self) -> None:
        if not self._dirty:
            return
        start = time.thread_time()
        msg = CompressedImage()
        msg.header = self._header
        msg.format = self._config.format
        msg.data = self._mosaic.encode(self._config.format, self._config.jpeg_quality)
        self._pub.publish(msg)
        self._dirty = False
        self._counts["mosaics_out"] += 1
        self._cpu += time.thread_time() - start

    def close(self) -> None:
        c = self._counts
        self.get_logger().info(
            f"{c['frames_added']} frames added ({c['calibrations_taken']} calibrations taken, "
            f"{c['not_converged']} not converged), {c['mosaics_out']} mosaics published, "
            f"{c['new_mosaics']} new references; "
            f"{self._cpu:.2f} s CPU in callbacks"
        )


def main(args: list[str] | None = None) -> int:
    return run_node(MosaicNode, args, name="mosaic")


if __name__ == "__main__":
    sys.exit(main(sys.argv))
