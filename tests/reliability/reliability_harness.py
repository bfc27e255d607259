"""Shared helpers of the reliability tests: the real node graph in processes, an in-process feeder and
collector over DDS, rendered PTZ views with exact ground truth, process memory.

Not a conftest.py: the root tests/conftest.py is imported as `conftest` by every test module, and a
second conftest.py would shadow it. Test modules import this one by name (pytest puts this directory
on sys.path).
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import node_command

from ptz_selfcal.camera.geometry import intrinsic_matrix, ptz_rotation
from ptz_selfcal.nodes.conversions import MSG_TO_STATUS
from ptz_selfcal.status import CALIBRATED, CalibrationStatus, TrackingState

NODE_MODULES = {
    "frame_ingest": "ptz_selfcal.nodes.frame_ingest",
    "homography_tracker": "ptz_selfcal.nodes.homography_tracker",
    "calibrator": "ptz_selfcal.nodes.calibrator",
}
T0 = 1_700_000_000.0  # first stamp of every rendered sequence (s)
REPO = Path(__file__).resolve().parents[2]
SHIPPED_PARAMS = REPO / "src" / "ptz_selfcal" / "config" / "ptz_selfcal.yaml"
SOURCE_PANORAMA = REPO / "bags" / "source" / "examplepano.jpg"  # shipped with the repository
SHARED_PANORAMAS = REPO.parent / "shared" / "data" / "panoramas"  # beside the repository, optional


def status_name(code: int) -> str:
    """The name of a FrameCalibration.status value, as a plain str: results are printed and compared."""
    return MSG_TO_STATUS[code].value


# ---------------------------------------------------------------------------------------------------------
# rendered views
def panorama_path(name: str) -> Path:
    """The repository's own panorama by its name, any other from the shared data beside the repository."""
    return SOURCE_PANORAMA if name == SOURCE_PANORAMA.name else SHARED_PANORAMAS / name


@lru_cache(maxsize=2)
def panorama(name: str = "building.jpg"):
    from ptz_selfcal.sim.render import build_panorama

    path = panorama_path(name)
    if not path.exists():
        pytest.skip(f"panorama {path} not available (shared data is looked for beside the repository)")
    return build_panorama(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))


@dataclass(frozen=True)
class View:
    pan: float  # radians
    tilt: float
    f: float  # full-resolution pixels
    zoom: float  # encoder value (monotonic in f)


def principal_point(width: int, height: int) -> tuple[float, float]:
    return 0.5 * (width - 1) + 6.0, 0.5 * (height - 1) - 4.0


def true_K(view: View, width: int, height: int) -> np.ndarray:
    return intrinsic_matrix(view.f, *principal_point(width, height))


def render(view: View, width: int, height: int, pano: str = "building.jpg") -> np.ndarray:
    from ptz_selfcal.sim.render import render_view

    return render_view(
        panorama(pano), true_K(view, width, height), ptz_rotation(view.pan, view.tilt), (width, height)
    )


def zoom_of(f: float, f_wide: float) -> float:
    """A zoom encoder value that grows monotonically with f (counts)."""
    return 1000.0 * math.log(f / f_wide)


def sweep(n: int, width: int, f_wide: float, pan_deg: float = 14.0, tilt_deg: float = 4.0,
          zoom_max: float = 1.6, cycles: float = 1.0) -> list[View]:  # fmt: skip
    """A smooth pan/tilt/zoom sweep (enough rotation for the calibrator to solve)."""
    out = []
    for k in range(n):
        s = k / max(n - 1, 1)
        f = f_wide * (1.0 + (zoom_max - 1.0) * 0.5 * (1.0 - math.cos(2 * math.pi * cycles * s)))
        pan = math.radians(pan_deg * math.sin(2 * math.pi * cycles * s))
        tilt = math.radians(tilt_deg * math.sin(4 * math.pi * cycles * s + 0.4))
        out.append(View(pan, tilt, f, zoom_of(f, f_wide)))
    return out


def f_wide_for(width: int, hfov_deg: float = 50.0) -> float:
    return 0.5 * width / math.tan(math.radians(0.5 * hfov_deg))


# ---------------------------------------------------------------------------------------------------------
# the graph
def start_graph(
    start_process: Callable[..., object],
    env: dict[str, str],
    ingest: Sequence[str] = (),
    tracker: Sequence[str] = (),
    calibrator: Sequence[str] = (),
    working_width: int | None = None,
    only: Sequence[str] = ("frame_ingest", "homography_tracker", "calibrator"),
) -> dict[str, object]:
    """The three nodes as separate processes on the shipped parameter file, then -p NAME:=VALUE overrides:
    diagnostics every 0.25 s (the harness waits on the nodes' counters), a reliable image subscription
    and lossless queues (the feeder is lossless: a best-effort reader or a latest-wins queue would let
    it lose frames) and the caller's, which come last and win."""

    def params(*values: str) -> list[str]:
        return [arg for v in values for arg in ("-p", v)]

    width = () if working_width is None else (f"working_width:={working_width}",)
    # lossless queues unless the caller says otherwise (the harness counts every frame it feeds; the
    # shipped live default sheds a frame the nodes fall 50 behind on)
    lossless = "queue_policy:=lossless"
    extra = {
        "frame_ingest": params(
            "sensor_reliability:=reliable", "image_transport:=both", lossless, *width, *ingest
        ),
        "homography_tracker": params(lossless, *tracker),
        "calibrator": params(*calibrator),
    }
    return {
        name: start_process(
            node_command(
                NODE_MODULES[name], "--params-file", str(SHIPPED_PARAMS), *params("diagnostics_period:=0.25"),
                *extra[name],
            ),
            env,
            name,
        )
        for name in only
    }  # fmt: skip


def stamp_of(t: float):
    from builtin_interfaces.msg import Time

    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=min(round((t - sec) * 1e9), 999_999_999))


def ns_of(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def t_ns(t: float) -> int:
    return ns_of(stamp_of(t))


class Feeder:
    """An in-process rclpy node: publishes images and encoders, collects every output of the graph."""

    def __init__(self, name: str = "reliability_feeder", sensor_qos=None, homographies: bool = True) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState

        from ptz_selfcal import topics
        from ptz_selfcal.nodes.runtime import reliable_qos
        from ptz_selfcal_msgs.msg import FrameCalibration, HomographyStamped

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, namespace=topics.NAMESPACE, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = sensor_qos or reliable_qos()
        self.raw = self.node.create_publisher(Image, topics.IMAGE_RAW, qos)
        self.compressed = self.node.create_publisher(CompressedImage, topics.IMAGE_COMPRESSED, qos)
        self.joints = self.node.create_publisher(JointState, topics.JOINT_STATES, reliable_qos())
        self.infos: dict[int, list] = defaultdict(list)  # stamp ns -> CameraInfo messages
        self.info_arrival: dict[int, float] = {}  # stamp ns -> monotonic arrival of its (first) CameraInfo
        self.info_order: list[int] = []
        self.frames: dict[int, object] = {}  # stamp ns -> FrameCalibration
        self.homographies: dict[int, object] = {}
        self.diagnostics: dict[str, dict[str, str]] = {}  # node name -> last counters
        self.diagnostics_arrival: dict[str, float] = {}  # node name -> monotonic arrival of the last ones
        self.sent: dict[int, float] = {}  # stamp ns -> monotonic send time
        self.info_sub = self.node.create_subscription(
            CameraInfo, topics.CAMERA_INFO, self._on_info, reliable_qos()
        )
        self.frame_sub = self.node.create_subscription(
            FrameCalibration, topics.FRAME_CALIBRATION, self._on_frame, reliable_qos()
        )
        self.listens_to_homographies = homographies
        if homographies:  # (a subscriber here keeps the tracker from holding outputs for the calibrator)
            self.node.create_subscription(HomographyStamped, topics.HOMOGRAPHY, self._on_h, reliable_qos())
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, reliable_qos(50))

    # -- callbacks
    def _on_info(self, msg) -> None:
        ns = ns_of(msg.header.stamp)
        self.infos[ns].append(msg)
        self.info_arrival.setdefault(ns, time.monotonic())
        self.info_order.append(ns)

    def _on_frame(self, msg) -> None:
        self.frames[ns_of(msg.header.stamp)] = msg

    def _on_h(self, msg) -> None:
        self.homographies[ns_of(msg.header.stamp)] = msg

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            name = status.name.rsplit("/", 1)[-1]
            self.diagnostics[name] = {kv.key: kv.value for kv in status.values}
            self.diagnostics[name]["_message"] = status.message
            level = status.level
            self.diagnostics[name]["_level"] = str(level[0] if isinstance(level, bytes) else level)
            self.diagnostics_arrival[name] = time.monotonic()

    # -- spinning
    def spin(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)
            if until is not None and until():
                return True
        return until is None

    def wait_connected(self, timeout: float = 30.0, compressed: bool = False) -> None:
        """Wait until every hop of ingest -> tracker -> calibrator -> this feeder is matched on the side
        that publishes. A subscription matched here, or one this node's graph shows, says nothing about
        whether the remote writer has matched it yet (each participant discovers the other's endpoints
        separately; under load seconds apart), and a reliable volatile writer drops what it publishes
        before that for the late reader: frame 0 lost to the calibrator, or its CameraInfo to us. So the
        nodes' own matched counts, from diagnostics sent after this call started, are waited for."""
        image_pub = self.compressed if compressed else self.raw
        since = time.monotonic()
        needed = {
            "frame_ingest": {"frame_in_subscribers": 1},
            # the calibrator's, and ours (which alone would release the tracker's held outputs)
            "homography_tracker": {
                "homography_subscribers": 1 + int(self.listens_to_homographies),
                "keyframes_subscribers": 1,
            },
            "calibrator": {"camera_info_subscribers": 1, "frame_calibration_subscribers": 1},
        }

        def matched_remotely() -> bool:
            return all(
                self.diagnostics_arrival.get(node, -math.inf) > since
                and all(self.counter(node, key, -1) >= n for key, n in counts.items())
                for node, counts in needed.items()
            )

        ok = self.spin(
            timeout,
            lambda: (
                image_pub.get_subscription_count() > 0
                and self.joints.get_subscription_count() > 0
                and self.info_sub.get_publisher_count() > 0
                and self.frame_sub.get_publisher_count() > 0
                and matched_remotely()
            ),
        )
        state = {node: {k: self.diagnostics.get(node, {}).get(k) for k in c} for node, c in needed.items()}
        assert ok, f"the graph did not connect: {state}"

    # -- sending
    def send_encoders(
        self, t: float, values: Sequence[float], names: Sequence[str] = ("pan", "tilt", "zoom")
    ) -> None:
        from sensor_msgs.msg import JointState

        msg = JointState()
        msg.header.stamp = stamp_of(t)
        msg.name = list(names)
        msg.position = [float(v) for v in values]
        self.joints.publish(msg)

    def send_image(self, t: float, pixels: np.ndarray, encoding: str = "mono8", step: int | None = None,
                   data: bytes | None = None, width: int | None = None,
                   height: int | None = None) -> int:  # fmt: skip
        msg = image_msg(t, pixels, encoding, step, data, width, height)
        self.raw.publish(msg)
        ns = ns_of(msg.header.stamp)
        self.sent[ns] = time.monotonic()
        return ns

    def send_compressed(self, t: float, data: bytes, fmt: str = "jpeg") -> int:
        from sensor_msgs.msg import CompressedImage

        msg = CompressedImage()
        msg.header.stamp = stamp_of(t)
        msg.header.frame_id = "ptz_camera"
        msg.format = fmt
        msg.data = data
        self.compressed.publish(msg)
        ns = ns_of(msg.header.stamp)
        self.sent[ns] = time.monotonic()
        return ns

    def send_view(self, t: float, view: View, image: np.ndarray) -> int:
        self.send_encoders(t, (view.pan, view.tilt, view.zoom))
        return self.send_image(t, image)

    def wait_info(self, stamp_ns: int, timeout: float = 15.0) -> bool:
        return self.spin(timeout, lambda: stamp_ns in self.infos and stamp_ns in self.frames)

    def counter(self, node: str, key: str, default: int = 0) -> int:
        value = self.diagnostics.get(node, {}).get(key)
        return default if value is None else int(float(value))

    def wait_counter(
        self, node: str, key: str, predicate: Callable[[int], bool], timeout: float = 10.0
    ) -> bool:
        return self.spin(timeout, lambda: predicate(self.counter(node, key, -1)))

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def image_msg(t: float, pixels: np.ndarray, encoding: str = "mono8", step: int | None = None,
              data: bytes | None = None, width: int | None = None, height: int | None = None):  # fmt: skip
    import array

    from sensor_msgs.msg import Image

    msg = Image()
    msg.header.stamp = stamp_of(t)
    msg.header.frame_id = "ptz_camera"
    msg.height = int(pixels.shape[0] if height is None else height)
    msg.width = int(pixels.shape[1] if width is None else width)
    msg.encoding = encoding
    channels = pixels.shape[2] if pixels.ndim == 3 else 1
    msg.step = int(step if step is not None else pixels.shape[1] * pixels.itemsize * channels)
    payload = data if data is not None else np.ascontiguousarray(pixels).tobytes()
    buf = array.array("B")
    buf.frombytes(payload)
    msg.data = buf
    return msg


# ---------------------------------------------------------------------------------------------------------
# measurements
def rss_mb(pid: int, field: str = "VmRSS") -> float:
    """Resident memory of a process (MB), NaN when it is gone; field VmHWM: its peak so far (the kernel's
    high-water mark, exact where sampling would miss a short-lived copy)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def focal_error(info, view: View) -> float:
    return abs(info.k[0] / view.f - 1.0)


def percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values, float), q)) if len(values) else math.nan


# ---------------------------------------------------------------------------------------------------------
# scenarios shared by the tests (CI size) and benchmarks/reliability.py (full size)


@dataclass
class Sent:
    stamp_ns: int
    view: View
    segment: str


class LockStep:
    """Sends rendered views one at a time and waits for each one's CameraInfo (lossless graph)."""

    def __init__(self, feeder: Feeder, width: int, height: int, fps: float = 30.0, timeout: float = 20.0,
                 pano: str = "building.jpg") -> None:  # fmt: skip
        self.feeder, self.width, self.height, self.pano = feeder, width, height, pano
        self.fps, self.timeout = fps, timeout
        self.k = 0
        self.log: list[Sent] = []
        self.lost: list[int] = []

    def send(self, view: View, image: np.ndarray | None, segment: str) -> Sent:
        sent = self.try_send(view, image, segment, self.timeout)
        assert sent is not None, f"no CameraInfo for frame {self.k - 1} ({segment})"
        return sent

    def try_send(self, view: View, image: np.ndarray | None, segment: str, timeout: float) -> Sent | None:
        """Send one frame; None when its CameraInfo did not come within timeout (the frame is lost)."""
        t = T0 + self.k / self.fps
        self.k += 1
        image = render(view, self.width, self.height, self.pano) if image is None else image
        ns = self.feeder.send_view(t, view, image)
        if not self.feeder.wait_info(ns, timeout):
            self.lost.append(ns)
            return None
        sent = Sent(ns, view, segment)
        self.log.append(sent)
        return sent

    def until_calibrated(self, views: Sequence[View], images: Sequence[np.ndarray], rounds: int = 4) -> bool:
        """Repeat the views until a whole pass is calibrated (the re-optimisation runs beside the frames:
        on a loaded machine convergence may come a little later than the warm-up)."""
        for _ in range(rounds):
            sent = [self.send(v, im, "settle") for v, im in zip(views, images)]
            if all(self.status(s) in CALIBRATED for s in sent):
                return True
            # Under load the re-optimisation lags the frames by an amount that depends on the machine:
            # before the next pass, wait until it has taken in everything up to this pass's last frame.
            self.feeder.spin(60.0, lambda last=sent[-1].stamp_ns: self.calibrator_caught_up(last))
        return False

    def calibrator_caught_up(self, stamp_ns: int) -> bool:
        d = self.feeder.diagnostics.get("calibrator", {})
        return int(d.get("last_frame_stamp_ns", -1)) >= stamp_ns and d.get("reoptimise_pending") == "0"

    def status(self, sent: Sent) -> str:
        return status_name(self.feeder.frames[sent.stamp_ns].status)

    def error(self, sent: Sent) -> float:
        return focal_error(self.feeder.infos[sent.stamp_ns][0], sent.view)

    def sigma(self, sent: Sent) -> float:
        """The frame's published 1-sigma of f relative to f (0 when it publishes none: no promise)."""
        frame = self.feeder.frames[sent.stamp_ns]
        return frame.sigma_f / frame.fx if frame.sigma_f > 0 and frame.fx > 0 else 0.0


def window_views(width: int, f: float, n: int = 16) -> list[View]:
    """A small back-and-forth around pan = tilt = 0 at focal length f (repeatable views)."""
    fw = f_wide_for(width)
    out = []
    for i in range(n):
        s = 2 * math.pi * i / n
        out.append(
            View(math.radians(3.0 * math.sin(s)), math.radians(0.8 * math.sin(2 * s)), f, zoom_of(f, fw))
        )
    return out


def motion_blur(image: np.ndarray, length: int) -> np.ndarray:
    return cv2.blur(image, (max(1, length), 1))


def tracking_loss_scenario(feeder: Feeder, width: int, height: int, warmup: int = 100, window: int = 16,
                           bad: int = 8, zoom_max: float = 2.0,
                           disturbances: Sequence[str] = ("black", "blur", "scene_cut", "preset_90deg"),
                           pano: str = SOURCE_PANORAMA.name) -> dict[str, dict]:  # fmt: skip
    """Warm-up sweep (1x..zoom_max, the zoom model learns that range), zoom in to full zoom, then for each
    disturbance: a window of views at full zoom, the disturbance, the same window again. Returns per
    disturbance: frames, statuses and focal errors during it, errors on the window before and after
    (median; and the largest after),
    frames until the calibration came back (recovery) and its wall time. "none" is the undisturbed
    control (the window again, nothing in between: any change is drift over repeated passes); repeated
    names get keys name, name_2, ..."""
    fw = f_wide_for(width)
    fmax = zoom_max * fw
    ls = LockStep(feeder, width, height, pano=pano)
    for v in sweep(warmup, width, fw, zoom_max=zoom_max):
        ls.send(v, None, "warmup")
    for i in range(1, 21):
        f = fw + (fmax - fw) * i / 20
        ls.send(View(0.0, 0.0, f, zoom_of(f, fw)), None, "zoom_in")
    views = window_views(width, fmax, window)
    images = [render(v, width, height, pano) for v in views]
    last, last_image = views[-1], images[-1]
    results: dict[str, dict] = {}

    def run_window(tag: str) -> list[Sent]:
        return [ls.send(v, im, tag) for v, im in zip(views, images)]

    assert ls.until_calibrated(views, images), "the calibration did not converge during the warm-up"
    before = run_window("window")
    for name in disturbances:
        lost: list[Sent] = []
        if name == "none":
            pass
        elif name == "black":
            lost = [ls.send(last, np.zeros_like(last_image), name) for _ in range(bad)]
        elif name == "blur":
            blurred = cv2.GaussianBlur(last_image, (0, 0), 12)
            lost = [ls.send(last, blurred, name) for _ in range(bad)]
        elif name == "scene_cut":  # the scene half a turn away, which the tracker has never seen
            other = render(View(last.pan + math.pi, last.tilt, last.f, last.zoom), width, height, pano)
            lost = [ls.send(last, other, name) for _ in range(bad)]
        elif name == "preset_90deg":  # 90 degrees of pan in `bad` frames at full zoom, hold, and back
            step = 90.0 / bad
            blur_px = int(math.radians(step) * fmax)
            path = [
                View(last.pan + math.radians(step * i), last.tilt, fmax, last.zoom) for i in range(1, bad + 1)
            ]
            for v in path:
                lost.append(ls.send(v, motion_blur(render(v, width, height, pano), blur_px), name))
            for _ in range(bad):
                lost.append(ls.send(path[-1], None, name + "_hold"))
            for v in reversed([last, *path[:-1]]):
                lost.append(ls.send(v, motion_blur(render(v, width, height, pano), blur_px), name))
        else:
            raise ValueError(f"unknown disturbance {name!r}")
        t_back = time.monotonic()
        after = run_window("window")
        recovered = next((i for i, s in enumerate(after) if ls.status(s) in CALIBRATED), None)
        recover_s = math.nan
        if recovered is not None:
            recover_s = feeder.info_arrival[after[recovered].stamp_ns] - t_back
        good_after = after[recovered:] if recovered is not None else []
        key, repeat = name, 1
        while key in results:
            repeat += 1
            key = f"{name}_{repeat}"
        results[key] = {
            "frames": len(lost),
            "statuses": [ls.status(s) for s in lost],
            "errors": [ls.error(s) for s in lost],
            "before": float(np.median([ls.error(s) for s in before])),
            "after": float(np.median([ls.error(s) for s in good_after])) if good_after else math.nan,
            "after_max": max((ls.error(s) for s in good_after), default=math.nan),
            "after_statuses": [ls.status(s) for s in after],
            "recovery_frames": recovered,
            "recovery_s": recover_s,
        }
        before = after
    results["_log"] = {"frames": len(ls.log), "stamps": [s.stamp_ns for s in ls.log]}
    return results


def overload_scenario(feeder: Feeder, pids: dict[str, int], seconds: float, fps: float = 60.0,
                      width: int = 1920, height: int = 1080, distinct: int = 24,
                      t0: float = T0, on_sample: Callable[[float], None] | None = None) -> dict:  # fmt: skip
    """Publish JPEG frames of width x height at `fps` (best effort, like a camera driver) with encoders for
    `seconds`, stamped from `t0`; returns what came out: counts, latencies (send -> CameraInfo), RSS samples
    per node, the monotonic start and the last stamp sent (s). `on_sample(seconds since the start)` is
    called with every RSS sample (every 0.25 s)."""
    from sensor_msgs.msg import CompressedImage

    fw = f_wide_for(width)
    views = sweep(distinct, width, fw, pan_deg=3.0, tilt_deg=1.0, zoom_max=1.1)
    msgs = []
    for v in views:
        msg = CompressedImage()
        msg.header.frame_id = "ptz_camera"
        msg.format = "jpeg"
        msg.data = cv2.imencode(".jpg", render(v, width, height), [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
        msgs.append(msg)
    rss: dict[str, list[tuple[float, float]]] = {name: [] for name in pids}
    sent: list[int] = []
    start = time.monotonic()
    next_rss = start
    k = 0
    while True:
        now = time.monotonic()
        if now - start >= seconds:
            break
        due = start + k / fps
        if now >= due:
            t = t0 + k / fps
            v = views[k % distinct]
            msg = msgs[k % distinct]
            msg.header.stamp = stamp_of(t)
            feeder.send_encoders(t, (v.pan, v.tilt, v.zoom))
            feeder.compressed.publish(msg)
            ns = ns_of(msg.header.stamp)
            feeder.sent[ns] = time.monotonic()
            sent.append(ns)
            k += 1
            if time.monotonic() - due > 1.0:  # the publisher itself fell behind: say so, do not burst
                start += time.monotonic() - due
        if now >= next_rss:
            for name, pid in pids.items():
                rss[name].append((now - start, rss_mb(pid)))
            if on_sample is not None:
                on_sample(now - start)
            next_rss = now + 0.25
        feeder.executor.spin_once(timeout_sec=max(0.0, min(0.002, due - time.monotonic())))
    elapsed = time.monotonic() - start
    feeder.spin(3.0)  # the last frames in flight
    latencies = [feeder.info_arrival[ns] - feeder.sent[ns] for ns in sent if ns in feeder.info_arrival]
    third = max(1, len(sent) // 3)
    early = [feeder.info_arrival[ns] - feeder.sent[ns] for ns in sent[:third] if ns in feeder.info_arrival]
    late = [feeder.info_arrival[ns] - feeder.sent[ns] for ns in sent[-third:] if ns in feeder.info_arrival]
    return {
        "sent": len(sent),
        "elapsed": elapsed,
        "rate": len(sent) / elapsed,
        "calibrated": sum(1 for ns in sent if ns in feeder.infos),
        "duplicates": sum(1 for ns in sent if len(feeder.infos.get(ns, [])) > 1),
        "unknown": sum(1 for ns in feeder.infos if ns not in feeder.sent),
        "latencies": latencies,
        "early_latencies": early,
        "late_latencies": late,
        "rss": rss,
        "start": start,
        "last_stamp": t0 + (k - 1) / fps,
    }


def cpu_seconds(pid: int) -> float:
    """user + system CPU seconds of a process (Linux /proc), NaN when it is gone."""
    import os

    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return math.nan


def own_rss_mb() -> float:
    import os

    return rss_mb(os.getpid())


def core_soak(n: int, warmup: tuple[int, int], width: int = 1280, height: int = 720, period: int = 600,
              keyframe_every: int = 30) -> dict:  # fmt: skip
    """n frames through core CalibratorSession.process (the calibrator node's per-frame path) fed exact
    synthetic homographies of a camera sweeping periodically over pan/tilt/zoom, like a patrolling PTZ
    camera: keyframes (and their matches, and a worker step) are made during the first period; later
    periods revisit the same views, tracked against the existing keyframes, with a worker step every
    keyframe_every frames. Returns CPU ms per frame and RSS (MB) of this process per 1000-frame block."""
    from ptz_selfcal.camera.geometry import apply_homography
    from ptz_selfcal.online.session import CalibratorSession, FrameInput, SessionConfig

    session = CalibratorSession(
        SessionConfig(nominal_hfov_deg=55.0, min_solve_period_s=0.0, max_solve_duty=1.0)
    )
    rng = np.random.default_rng(0)
    t = np.arange(period) / period
    f = 1100.0 * (2.0 - np.cos(2 * np.pi * t))
    pan = np.radians(30.0 * np.sin(2 * np.pi * t))
    tilt = np.radians(6.0 * np.sin(4 * np.pi * t + 0.3))
    pp = (0.5 * (width - 1) + 12.0, 0.5 * (height - 1) - 8.0)
    K = [intrinsic_matrix(fi, *pp) for fi in f]
    R = [ptz_rotation(p, q) for p, q in zip(pan, tilt)]
    Hs = [K[j] @ R[j] @ R[0].T @ np.linalg.inv(K[0]) for j in range(period)]
    block = 1000
    cpu = np.zeros(n)
    cpu_frame = np.zeros(n)  # the frame path alone (process()); the node runs the steps on a worker thread
    rss: list[float] = []
    errors = np.full(n, np.nan)  # preallocated: the soak's own bookkeeping must not grow per frame
    statuses: dict[str, int] = {}
    wall = time.perf_counter()
    for j in range(n):
        c = j % period
        first = j < period
        new_kf = first and c % keyframe_every == 0
        kid = c - c % keyframe_every
        state = TrackingState.NEW_KEYFRAME if new_kf else TrackingState.TRACKING
        frame = FrameInput(
            stamp=j / 30.0, H=Hs[c], tracking_state=state, width=width,
            height=height, keyframe_id=kid, reference_id="ref", zoom=float(f[c]),
        )  # fmt: skip
        t0 = time.thread_time()
        out = session.process(frame)
        cpu_frame[j] = time.thread_time() - t0
        if new_kf and c >= keyframe_every:
            a, b = c, c - keyframe_every
            xa = rng.uniform([0, 0], [width - 1, height - 1], (200, 2))
            xb = apply_homography(Hs[b] @ np.linalg.inv(Hs[a]), xa)
            ok = (xb[:, 0] >= 0) & (xb[:, 0] <= width - 1) & (xb[:, 1] >= 0) & (xb[:, 1] <= height - 1)
            session.add_keyframe_matches(a, b, xa[ok] + rng.normal(0, 0.3, (ok.sum(), 2)), xb[ok])
        if c % keyframe_every == 0:
            session.step(0.5 if first else 0.05)
        cpu[j] = time.thread_time() - t0
        name = str(out.status)  # a plain name: the benchmark prints this dict
        statuses[name] = statuses.get(name, 0) + 1
        if out.status in CALIBRATED:
            errors[j] = abs(out.K[0, 0] / f[c] - 1.0)
        if (j + 1) % block == 0:
            rss.append(own_rss_mb())
    blocks = cpu[: n - n % block].reshape(-1, block).mean(axis=1) * 1e3
    frame_blocks = cpu_frame[: n - n % block].reshape(-1, block).mean(axis=1) * 1e3
    a, b = warmup
    return {
        "frames": n,
        "wall_s": time.perf_counter() - wall,
        "cpu_ms_blocks": blocks.tolist(),
        "rss_blocks": rss,
        "warm_cpu_ms": float(np.mean(blocks[a // block : b // block])),
        "end_cpu_ms": float(np.mean(blocks[-((b - a) // block) :])),
        # the least disturbed 1000-frame block of each window: the per-frame cost itself, robust to other
        # processes on the (shared, 2-core) machine, which inflate thread CPU time through the caches
        "warm_cpu_min": float(np.min(blocks[a // block : b // block])),
        "end_cpu_min": float(np.min(blocks[-((b - a) // block) :])),
        "frame_cpu_ms_blocks": frame_blocks.tolist(),
        "warm_frame_cpu_min": float(np.min(frame_blocks[a // block : b // block])),
        "end_frame_cpu_min": float(np.min(frame_blocks[-((b - a) // block) :])),
        "warm_rss": float(np.mean(rss[a // block : b // block])),
        "end_rss": float(np.mean(rss[-((b - a) // block) :])),
        "p95_cpu_ms": float(np.percentile(cpu, 95) * 1e3),
        "statuses": statuses,
        "median_error": float(np.nanmedian(errors)) if np.isfinite(errors).any() else math.nan,
        "solves": session.counters["solves"],
    }


def graph_soak(feeder: Feeder, pids: dict[str, int], n: int, width: int, height: int,
               in_flight: int = 3, block: int = 250) -> dict:  # fmt: skip
    """n frames through the real graph, lossless and pipelined (at most `in_flight` images without their
    CameraInfo), views of a periodic patrol; per block of frames: RSS and CPU seconds per frame of each
    node, and latencies (send -> CameraInfo)."""
    fw = f_wide_for(width)
    period = 240
    views = sweep(period, width, fw, pan_deg=12.0, tilt_deg=3.0, zoom_max=1.5)
    images = [render(v, width, height) for v in views]
    stamps: list[int] = []
    pending: list[int] = []
    rss = {name: [] for name in pids}
    cpu = {name: [] for name in pids}
    cpu_last = {name: cpu_seconds(pid) for name, pid in pids.items()}
    lat_blocks: list[list[float]] = []
    lost = 0
    start = time.monotonic()
    for j in range(n):
        while len(pending) >= in_flight:
            feeder.executor.spin_once(timeout_sec=0.01)
            now = time.monotonic()
            pending = [ns for ns in pending if ns not in feeder.infos and now - feeder.sent[ns] < 20.0]
        c = j % period
        t = T0 + j / 30.0
        ns = feeder.send_view(t, views[c], images[c])
        stamps.append(ns)
        pending.append(ns)
        if (j + 1) % block == 0:
            for name, pid in pids.items():
                rss[name].append(rss_mb(pid))
                now_cpu = cpu_seconds(pid)
                cpu[name].append((now_cpu - cpu_last[name]) / block * 1e3)
                cpu_last[name] = now_cpu
            lat_blocks.append([feeder.info_arrival[s] - feeder.sent[s] for s in stamps[-block:]
                               if s in feeder.info_arrival])  # fmt: skip
    feeder.spin(10.0, lambda: all(s in feeder.infos for s in stamps[-in_flight:]))
    lost = sum(1 for s in stamps if s not in feeder.infos)
    return {
        "frames": n,
        "wall_s": time.monotonic() - start,
        # where frames went missing, for the failure message: their indices and the nodes' counters
        "lost_frames": [j for j, s in enumerate(stamps) if s not in feeder.infos],
        "counters": {name: dict(values) for name, values in feeder.diagnostics.items()},
        "calibrated": sum(1 for s in stamps if s in feeder.infos),
        "duplicates": sum(1 for s in stamps if len(feeder.infos.get(s, [])) > 1),
        "lost": lost,
        "rss": rss,
        "cpu_ms_per_frame": cpu,
        "latency_blocks": lat_blocks,
        "statuses": {
            name: sum(
                1 for s in stamps if s in feeder.frames and status_name(feeder.frames[s].status) == name
            )
            for name in map(str, CalibrationStatus)
        },
    }


def bad_input_catalogue(feeder: Feeder, width: int, height: int, n: int = 60):
    """Good rendered frames (lock-step) interleaved with the bad input catalogue of test_bad_input.py;
    returns (views, stamps that must get exactly one CameraInfo, stamps that must get none)."""
    W, H = width, height
    fw = f_wide_for(W)
    views = sweep(n, W, fw)
    images = [render(v, W, H) for v in views]
    good: list[int] = []  # stamps that must get exactly one CameraInfo
    refused: list[int] = []  # stamps that must get none
    k = 0

    def t_of(i: int) -> float:
        return T0 + i / 30.0

    def send_good(i: int, encoders: bool = True) -> int:
        if encoders:
            feeder.send_encoders(t_of(i), (views[i].pan, views[i].tilt, views[i].zoom))
        ns = feeder.send_image(t_of(i), images[i])
        good.append(ns)
        assert feeder.wait_info(ns), f"good frame {i} got no CameraInfo"
        return ns

    jpeg16k = cv2.imencode(".jpg", np.zeros((16384, 16384), np.uint8))[1].tobytes()
    png = cv2.imencode(".png", images[0])[1].tobytes()
    for k in range(n):
        t_bad = t_of(k) + 0.011  # bad inputs get stamps of their own between the good frames
        if k == 5:
            refused.append(feeder.send_image(t_bad, np.zeros((16384, 16384), np.uint8)))  # 256 MB
        elif k == 7:  # a lying header: 16k x 16k claimed, 1 kB of data
            refused.append(feeder.send_image(t_bad, images[0], data=bytes(1024), width=16384, height=16384))
        elif k == 9:
            refused.append(feeder.send_compressed(t_bad, jpeg16k, "jpeg"))  # decompression bomb
        elif k == 11:
            refused.append(feeder.send_compressed(t_bad, b"", "jpeg"))
        elif k == 13:
            refused.append(feeder.send_compressed(t_bad, bytes(range(256)) * 8, "jpeg"))
        elif k == 15:
            refused.append(feeder.send_compressed(t_bad, png[:40], "png"))  # header only
        elif k == 17:
            refused.append(feeder.send_compressed(t_bad, png, "16UC1; compressedDepth"))
        elif k == 19:
            refused.append(feeder.send_image(t_bad, images[0], width=0, height=H, step=0, data=b""))
        elif k == 21:
            feeder.send_encoders(t_of(k), (views[k].pan, views[k].tilt), names=("pan", "tilt"))
            feeder.send_encoders(t_of(k) + 0.002, (views[k].zoom,), names=("zoom",))
        elif k == 23:
            feeder.send_encoders(t_of(k) - 0.002, (1.0, 2.0), names=("pan", "tilt", "zoom"))  # mismatch
            feeder.send_encoders(t_of(k) - 0.001, (1.0, 2.0), names=("a", "b"))  # no known joint
        elif k == 25:
            feeder.send_encoders(t_of(k) - 0.003, (math.inf, -math.inf, math.nan))
        elif k == 27:
            feeder.send_encoders(t_of(k) + 1e6, (0.0, 0.0, 0.0))  # 11 days ahead: rejected
        if k == 21:
            send_good(k, encoders=False)  # its encoders came in two partial messages
        else:
            send_good(k)
        if k == 31:  # the same stamp again: refused as a duplicate, the first one keeps its CameraInfo
            feeder.send_image(t_of(k), images[k])
        elif k == 33:  # an image older than the previous one (not a duplicate): calibrated anyway
            feeder.send_encoders(t_of(k) - 0.005, (views[k].pan, views[k].tilt, views[k].zoom))
            ns = feeder.send_image(t_of(k) - 0.005, images[k])
            good.append(ns)
            assert feeder.wait_info(ns), "the out-of-order image got no CameraInfo"
        elif k == 35:  # an image 10 years in the future: calibrated (encoders invalid), no lasting harm
            ns = feeder.send_image(t_of(k) + 3.15e8, images[k])
            good.append(ns)
            assert feeder.wait_info(ns, 20.0), "the far-future image got no CameraInfo"
    return views, good, refused


# The restart comparison, relative to the worst frame before the kill: 3x the worst rise of the worst
# frame after over repeated runs of every victim (a calibration lost in the restart is off by 0.1 % (zoom
# model) to 10 % (nominal), several times the frames' 0.07 %)
RESTART_FACTOR = 1.03


def started(output: str) -> dict[str, list[int]]:
    """Node name -> pids the `launch` supervisor started (in order), from its output."""
    import re

    pids: dict[str, list[int]] = {}
    for name, pid in re.findall(r"\[launch\] started (\w+) \(pid (\d+)\)", output):
        pids.setdefault(name, []).append(int(pid))
    return pids


def restart_scenario(feeder: Feeder, launch_output: Callable[[], str], victim: str, width: int, height: int,
                     warmup: int = 90, after_passes: int = 3) -> dict:  # fmt: skip
    """Calibrate (warm-up sweep, then a window of views until calibrated), wait for two state saves, kill -9
    the victim node of a running `launch`, wait for its restart, probe until frames come through again,
    then the window `after_passes` times. Returns frames lost, the frames whose focal error is worse than
    RESTART_FACTOR x the worst of the window before, statuses after, time from the kill to recovery."""
    import os
    import signal

    fw = f_wide_for(width)
    ls = LockStep(feeder, width, height, timeout=30.0)
    for v in sweep(warmup, width, fw, zoom_max=1.6):
        ls.send(v, None, "warmup")
    window = window_views(width, fw)
    images = [render(v, width, height) for v in window]
    assert ls.until_calibrated(window, images), "the calibration did not converge during the warm-up"
    before = [ls.send(v, im, "before") for v, im in zip(window, images)]
    assert {ls.status(s) for s in before} <= CALIBRATED, [ls.status(s) for s in before]
    # the saved state holds this calibration before the kill
    assert feeder.spin(10.0, lambda: feeder.counter("calibrator", "state_saves") >= 2)
    time.sleep(0.8)
    threshold = RESTART_FACTOR * max(ls.error(s) for s in before)
    old = endpoints_of(feeder, victim)
    pid = started(launch_output())[victim][-1]
    os.kill(pid, signal.SIGKILL)
    killed = time.monotonic()
    assert feeder.spin(30.0, lambda: len(started(launch_output()).get(victim, [])) == 2), launch_output()
    # A killed process's DDS endpoints stay in the graph until its participant's lease expires (`launch`
    # sets 2 s; Fast DDS's default is 20 s), and frames sent meanwhile may go to the dead node: send none
    # until the graph has the restarted node's endpoints and none of the dead one's.
    reconnected = feeder.spin(
        60.0,
        lambda: not (endpoints_of(feeder, victim) & old) and len(endpoints_of(feeder, victim)) >= len(old),
    )
    assert reconnected, (len(old), len(endpoints_of(feeder, victim) & old), launch_output()[-3000:])
    reconnect_s = time.monotonic() - killed
    feeder.wait_connected(30.0)
    # and should a frame still not come through, probe until one does (counted as lost)
    probe = None
    while probe is None and time.monotonic() - killed < 60.0:
        probe = ls.try_send(window[0], images[0], "probe", 2.0)
    assert probe is not None, launch_output()
    after: list[Sent] = []
    for _ in range(after_passes):
        after += [ls.send(v, im, "after") for v, im in zip(window, images)]
    worse = [i for i, s in enumerate(after) if ls.error(s) > threshold]
    first_good = next((i for i, _ in enumerate(after) if i not in worse), None)
    recover_s = feeder.info_arrival[after[first_good].stamp_ns] - killed if first_good is not None else None
    return {
        "frames": len(ls.log) + len(ls.lost),
        "calibrated": len(ls.log),
        "lost": len(ls.lost),
        "worse": worse,
        "statuses": [ls.status(s) for s in after],
        "threshold": threshold,
        "before_max": max(ls.error(s) for s in before),
        "after_errors": [ls.error(s) for s in after],
        "after_sigmas": [ls.sigma(s) for s in after],  # published 1-sigma of f, relative
        "before": float(np.median([ls.error(s) for s in before])),
        "after": float(np.median([ls.error(s) for s in after])),
        "recover_s": recover_s,
        "reconnect_s": reconnect_s,
    }


def endpoints_of(feeder: Feeder, node_name: str) -> set[bytes]:
    """GIDs of the DDS endpoints (publishers and subscriptions, every topic) of the nodes named node_name,
    as the feeder's graph sees them (a killed node's stay until its lease expires)."""
    node = feeder.node
    gids = set()
    for topic, _types in node.get_topic_names_and_types():
        for info in (*node.get_publishers_info_by_topic(topic), *node.get_subscriptions_info_by_topic(topic)):
            if info.node_name == node_name:
                gids.add(bytes(info.endpoint_gid))
    return gids


def zoom_preset_scenario(feeder: Feeder, width: int, height: int, warmup: int = 100,
                         pano: str = SOURCE_PANORAMA.name) -> dict:  # fmt: skip
    """A preset recall that zooms past the learned range while panning: warm-up sweep (1x..1.6x), the
    window of views at the sweep's end (wide), then 10 sharp frames panning 9 deg/frame while zooming to
    2.5x, 5 frames held there, 10 frames back (pan and zoom) to the window, and the window again."""
    fw = f_wide_for(width)
    ls = LockStep(feeder, width, height, pano=pano)
    for v in sweep(warmup, width, fw, zoom_max=1.6):
        ls.send(v, None, "warmup")
    views = window_views(width, fw)
    images = [render(v, width, height, pano) for v in views]
    assert ls.until_calibrated(views, images), "the calibration did not converge during the warm-up"
    before = [ls.send(v, im, "window") for v, im in zip(views, images)]
    last, fmax = views[-1], 2.5 * fw
    moving: list[Sent] = []
    for i in range(1, 11):
        f = fw + (fmax - fw) * min(1.0, i / 3)
        moving.append(
            ls.send(View(last.pan + math.radians(9 * i), last.tilt, f, zoom_of(f, fw)), None, "move")
        )
    for _ in range(5):
        moving.append(ls.send(moving[-1].view, None, "hold"))
    for i in range(9, -1, -1):
        f = last.f + (fmax - last.f) * i / 10
        moving.append(
            ls.send(View(last.pan + math.radians(9 * i), last.tilt, f, zoom_of(f, fw)), None, "back")
        )
    after = [ls.send(v, im, "window") for v, im in zip(views, images)]
    after += [ls.send(v, im, "window") for v, im in zip(views, images)]
    return {
        "before": float(np.median([ls.error(s) for s in before])),
        "after": float(np.median([ls.error(s) for s in after[len(views) :]])),
        "after_max": max(ls.error(s) for s in after[len(views) :]),
        "after_statuses": [ls.status(s) for s in after],
        "moving_statuses": [ls.status(s) for s in moving],
        "moving_errors": [ls.error(s) for s in moving],
        "frames": len(ls.log),
    }
