"""The mosaic node in a real process, fed IngestedFrame, FrameCalibration and HomographyStamped over DDS.

The frames are views rendered from the repository's panorama with known K and pan/tilt (sim/render), at
half resolution as frame_ingest publishes them; their calibrations carry the true K and orientation. The
published mosaic must arrive, be the canvas the width parameter asks for, hold the panorama where the
converged frames look and nothing where the unconverged ones do, and start again at a new reference.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from sensor_msgs.msg import CompressedImage  # noqa: E402

from ptz_selfcal import topics  # noqa: E402
from ptz_selfcal.camera.geometry import (  # noqa: E402
    intrinsic_matrix,
    intrinsics_full_to_work,
    ptz_rotation,
    quaternion_from_matrix,
)
from ptz_selfcal.nodes.conversions import fill_mono8  # noqa: E402
from ptz_selfcal.nodes.runtime import reliable_qos  # noqa: E402
from ptz_selfcal.sim.render import build_panorama, render_view  # noqa: E402
from ptz_selfcal_msgs.msg import FrameCalibration, HomographyStamped, IngestedFrame  # noqa: E402

ROS_DOMAIN_ID = 151
NAMESPACE = "/mosaic_test"
PANORAMA = Path(__file__).resolve().parents[2] / "bags" / "source" / "examplepano.jpg"
MOSAIC_WIDTH = 2048
WIDTH, HEIGHT, SCALE = 640, 360, 0.5
T0_NS = 1_700_000_000_000_000_000
F = 560.0


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(ROS_DOMAIN_ID), PYTHONUNBUFFERED="1"
    )
    return env


@pytest.fixture(scope="module")
def ros():
    os.environ.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(ROS_DOMAIN_ID))
    rclpy.init()
    yield
    rclpy.shutdown()


@pytest.fixture(scope="module")
def panorama() -> np.ndarray:
    return cv2.imread(str(PANORAMA), cv2.IMREAD_GRAYSCALE)


def start_node(*params: str) -> subprocess.Popen:
    args = [sys.executable, "-m", "ptz_selfcal.nodes.mosaic_node", "--ros-args", "-r", f"__ns:={NAMESPACE}"]
    for p in params:
        args += ["-p", p]
    return subprocess.Popen(args, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def stop(proc: subprocess.Popen) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.stdout.read() if proc.stdout else ""


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return math.nan


class Harness:
    def __init__(self) -> None:
        self.node = rclpy.create_node("mosaic_test_harness", namespace=NAMESPACE)
        self.frame_pub = self.node.create_publisher(IngestedFrame, topics.FRAME_IN, reliable_qos())
        self.fc_pub = self.node.create_publisher(FrameCalibration, topics.FRAME_CALIBRATION, reliable_qos())
        self.h_pub = self.node.create_publisher(HomographyStamped, topics.HOMOGRAPHY, reliable_qos())
        self.mosaics: list[CompressedImage] = []
        self.node.create_subscription(CompressedImage, topics.MOSAIC, self.mosaics.append, reliable_qos())

    def spin_until(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            rclpy.spin_once(self.node, timeout_sec=0.02)
            if predicate():
                return True
        return False

    def wait_connected(self, image: np.ndarray, K: np.ndarray) -> int:
        """Matched both ways: frames of a reference of their own (-1) until a mosaic comes back (a
        publisher's first messages may go before the other side has matched it); how many were sent."""
        pubs = (self.frame_pub, self.fc_pub, self.h_pub)
        ok = self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs), 30.0)
        assert ok, "the mosaic node did not connect"
        for k in range(60):
            self.send(-1000 + k, image, K, ptz_rotation(math.pi, 0.0), FrameCalibration.CONVERGED, ref=-1)
            if self.spin_until(lambda: len(self.mosaics) > 0, 0.5):
                return k + 1
        raise AssertionError("no mosaic came back")

    def send(
        self, j: int, image: np.ndarray, K: np.ndarray, R: np.ndarray | None, status: int, ref: int
    ) -> int:
        stamp = T0_NS + j * 100_000_000  # 10 frames/s
        sec, nanosec = divmod(stamp, 10**9)
        h = HomographyStamped()
        h.header.stamp.sec, h.header.stamp.nanosec = sec, nanosec
        h.header.frame_id = topics.CAMERA_FRAME_ID
        h.reference_frame_id = topics.CAMERA_FRAME_ID
        h.reference_stamp.sec, h.reference_stamp.nanosec = divmod(T0_NS + ref, 10**9)
        h.image_width, h.image_height = WIDTH, HEIGHT
        self.h_pub.publish(h)
        frame = IngestedFrame()
        frame.header = h.header
        fill_mono8(frame.image, image)
        frame.full_width, frame.full_height, frame.scale, frame.seq = WIDTH, HEIGHT, SCALE, j % 2**32
        self.frame_pub.publish(frame)
        fc = FrameCalibration()
        fc.header = h.header
        fc.status = status
        fc.fx, fc.fy, fc.cx, fc.cy, fc.skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.0
        if R is not None:
            q = quaternion_from_matrix(R)
            fc.orientation.x, fc.orientation.y, fc.orientation.z, fc.orientation.w = (float(v) for v in q)
        else:
            fc.orientation.w = 0.0
        self.fc_pub.publish(fc)
        rclpy.spin_once(self.node, timeout_sec=0.01)
        return stamp

    def mosaic_of(self, stamp: int, timeout: float = 20.0) -> np.ndarray:
        """The first published mosaic whose header is the frame of `stamp` (the newest that entered),
        BGRA (PNG: alpha 0 where nothing was seen; a JPEG's black says nothing of coverage)."""

        def found() -> bool:
            return any(m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamp for m in self.mosaics)

        assert self.spin_until(found, timeout), f"no mosaic after the frame of {stamp}"
        msg = next(m for m in self.mosaics if m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamp)
        assert msg.format == "png"
        image = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        assert image is not None and image.shape[2] == 4
        return image


def _columns(pans_deg) -> np.ndarray:
    """Mosaic columns within 10 degrees of the given pans (well inside those views' footprints)."""
    deg = (np.arange(MOSAIC_WIDTH) + 0.5) * 360.0 / MOSAIC_WIDTH - 180.0
    return np.any([np.abs((deg - p + 180.0) % 360.0 - 180.0) < 10.0 for p in pans_deg], axis=0)


def test_the_mosaic_of_converged_frames_is_the_panorama(ros, panorama: np.ndarray) -> None:
    proc = start_node(f"width:={MOSAIC_WIDTH}", "frame_period:=0.0", "publish_period:=0.3", "format:=png")
    harness = Harness()
    output = ""
    try:
        pano = build_panorama(panorama)
        K = intrinsic_matrix(F, (WIDTH - 1) / 2 + 9.0, (HEIGHT - 1) / 2 - 6.0)
        K_work = intrinsics_full_to_work(K, SCALE)
        size = (round(WIDTH * SCALE), round(HEIGHT * SCALE))

        def view(pan: float, tilt: float) -> tuple[np.ndarray, np.ndarray]:
            R = ptz_rotation(math.radians(pan), math.radians(tilt))
            return render_view(pano, K_work, R, size), R

        primers = harness.wait_connected(view(180.0, 0.0)[0], K)

        converged = [(-40.0, 0.0), (-20.0, 5.0), (0.0, -4.0), (20.0, 3.0), (40.0, 0.0)]
        j = 0
        for pan, tilt in converged:
            image, R = view(pan, tilt)
            last = harness.send(j, image, K, R, FrameCalibration.CONVERGED, ref=0)
            j += 1
            # never entered: not converged (at 120 deg), an invalid orientation
            image, R = view(120.0, 0.0)
            harness.send(j, image, K * 0.8, R, FrameCalibration.CALIBRATING, ref=0)
            harness.send(j + 1, image, K, None, FrameCalibration.CONVERGED, ref=0)
            j += 2
        mosaic = harness.mosaic_of(last)
        assert mosaic.shape == (MOSAIC_WIDTH // 2, MOSAIC_WIDTH, 4)  # the canvas of the width parameter
        covered = cv2.erode((mosaic[:, :, 3] > 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        seen = _columns([p for p, _ in converged])
        assert covered[MOSAIC_WIDTH // 4, seen].all()  # the horizon in front of every converged view
        # compared at half the canvas (the views are rendered at 0.9 canvas pixels per image pixel)
        half = (MOSAIC_WIDTH // 2, MOSAIC_WIDTH // 4)
        truth = cv2.resize(panorama, half, interpolation=cv2.INTER_AREA).astype(float)
        inside = cv2.resize((covered & seen[None, :]).astype(np.uint8), half, interpolation=cv2.INTER_NEAREST)
        small = cv2.resize(mosaic[:, :, 0], half, interpolation=cv2.INTER_AREA).astype(float)
        diff = np.abs(small[inside > 0] - truth[inside > 0])
        assert np.median(diff) < 6.0, np.median(diff)
        assert not (mosaic[:, _columns([120.0]), 3] > 0).any()  # the unconverged frames stayed out

        # a new tracking reference: a new mosaic, the old views gone
        image, R = view(160.0, 0.0)
        last = harness.send(j, image, K, R, FrameCalibration.CONVERGED, ref=1)
        mosaic = harness.mosaic_of(last)
        assert (mosaic[:, _columns([160.0]), 3] > 0).any()
        assert not (mosaic[:, seen, 3] > 0).any()
        assert peak_rss_mb(proc.pid) < 200.0  # the canvas is 4 MB; the process bounded with it
    finally:
        output = stop(proc)
        harness.node.destroy_node()
    assert f"{primers + 6} frames added" in output and "2 new references" in output, output[-3000:]
