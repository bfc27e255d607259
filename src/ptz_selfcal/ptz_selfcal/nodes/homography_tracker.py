"""homography_tracker node: IngestedFrame in, HomographyStamped (one per frame) and KeyframeMatches out.

A thin wrapper of frontend/tracker.HomographyTracker. Every IngestedFrame gives exactly one HomographyStamped
on topics.HOMOGRAPHY (header, full-resolution size and encoders passed through, `seq` copied), also when
tracking is lost or the frame is unusable: then the state is TRACKING_LOST or TEXTURELESS, h is the
identity and inlier_count 0. New keyframes (and relocalisations) publish their keyframe links as
KeyframeMatches on topics.KEYFRAMES. reference_frame_id/reference_stamp name the reference keyframe's
image (the map's origin: it changes when the tracker starts a new map). Tracker settings are the
parameters `tracker.<field>` of frontend/tracker_config.TrackerConfig.

State: with `state_dir` set, the keyframe map (HomographyTracker.export_map in frontend/tracker_map's file
format, with the keyframes' header stamps) is saved atomically to state_dir/tracker_map.npz by a
background thread whenever it changed (a new keyframe, a relocalisation or a revisit), at most once per
`save_period`, and on shutdown. At start the saved map is
loaded: the tracker begins lost and relocalises its first frames against the stored keyframes, so after a
restart (kill -9, crash) it keeps the same reference (reference_frame_id/reference_stamp) and keyframe
ids, and the calibrator continues its calibration. An unreadable or corrupt file: a warning, a new map.
`ptz-selfcal launch` gives the tracker the calibrator's state_dir unless it has its own. Run:
    python -m ptz_selfcal.nodes.homography_tracker --ros-args -p tracker.max_features:=300
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import re
import sys
import threading
import time
import traceback
from collections import Counter, deque
from pathlib import Path
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node

from ptz_selfcal import topics
from ptz_selfcal.frontend.tracker import HomographyTracker, TrackResult
from ptz_selfcal.frontend.tracker_config import TRACKER_CHOICES, TrackerConfig
from ptz_selfcal.frontend.tracker_map import TrackerMap, map_from_bytes, map_to_bytes
from ptz_selfcal.nodes.conversions import (
    TRACKING_STATE_TO_MSG,
    ConfigError,
    FrameError,
    Param,
    declare_params,
    diagnostic_values,
    in_range,
    mono8_from_msg,
    one_of,
    stamp_to_sec,
)
from ptz_selfcal.nodes.runtime import (
    CountedWarnings,
    FailureRun,
    camera_name_of,
    qos_overrides,
    reliable_qos,
    run_node,
    set_level,
)
from ptz_selfcal.persist.atomic_file import atomic_write_bytes, remove_stale_temporaries
from ptz_selfcal.status import KEYFRAME_STATES, LOST_STATES, TrackingState
from ptz_selfcal_msgs.msg import HomographyStamped, IngestedFrame, KeyframeMatches

PARAMS = [
    Param(
        "queue_policy",
        "latest",
        "latest: keep only the newest queue_depth frames (KEEP_LAST: bounded memory and latency live), "
        "shedding the others (counted as frames_dropped from gaps in seq); lossless: process every frame "
        "(KEEP_ALL, for replays that wait for each result)",
        one_of("lossless", "latest"),
    ),
    Param(
        "queue_depth",
        50,
        "KEEP_LAST depth of the input queue with queue_policy latest (50: bursts up to 50 frames are kept)",
        in_range(1, 1000),
    ),
    Param(
        "wait_for_subscribers",
        1,
        "hold outputs until the homography topic has this many matched subscribers, so none is published "
        "into the void while the graph connects (0: never hold)",
        in_range(0, 100),
    ),
    Param(
        "max_held",
        100,
        "outputs held at most while waiting for subscribers (the oldest are dropped)",
        in_range(1, 100000),
    ),
    Param("diagnostics_period", 1.0, "seconds between DiagnosticArray messages", in_range(0.05, 3600.0)),
    Param(
        "state_dir",
        "",
        "directory of the saved keyframe map (state_dir/tracker_map.npz), reloaded at start so that a "
        "restarted tracker keeps its reference and keyframe ids ('' = no persistence; `ptz-selfcal launch` "
        "passes the calibrator's state_dir when this is unset)",
    ),
    Param(
        "save_period",
        2.0,
        "seconds at least between two saves of the keyframe map (saved when it changed, by a background "
        "thread, and on shutdown)",
        in_range(0.05, 86400.0),
    ),
    Param(
        "camera_name",
        "",
        "name of the camera, the diagnostics' hardware_id ('': the namespace's last component, /cam1: cam1)",
        None,
    ),
    Param(
        "error_threshold",
        3,
        "consecutive frames failing with an internal error after which diagnostics report ERROR",
        in_range(1, 1_000_000),
    ),
]

_IDENTITY = np.eye(3).ravel()
MAP_FILE = "tracker_map.npz"
# TrackerConfig fields the node does not expose (frame_ingest chooses the working scale).
_NOT_PARAMETERS = {"working_scale"}
_FRACTIONS = {"ratio", "fraction", "overlap", "level", "confidence"}  # name words of (0, 1] values
# TrackerConfig fields whose negative values mean something, with their range
_SIGNED = {"rolling_shutter_readout": (-1.0, 1.0)}  # < 0: estimated from the images


def _field_comments() -> dict[str, str]:
    """The inline comments of TrackerConfig's fields, as parameter descriptions."""
    try:
        source = inspect.getsource(TrackerConfig)
    except (OSError, TypeError):
        return {}
    found = {}
    for line in source.splitlines():
        m = re.match(r"\s+(\w+):[^#]*#\s*(.+)$", line)
        if m:
            found[m.group(1)] = m.group(2).strip()
    return found


def tracker_params() -> list[Param]:
    """One parameter `tracker.<field>` per TrackerConfig field, default from the dataclass."""
    comments = _field_comments()
    defaults = TrackerConfig()
    params = []
    for f in dataclasses.fields(TrackerConfig):
        if f.name in _NOT_PARAMETERS:
            continue
        default = getattr(defaults, f.name)
        if isinstance(default, tuple):
            default = list(default)
        description = comments.get(f.name, f"TrackerConfig.{f.name} (frontend/tracker_config.py)")
        check = _tracker_check(f.name, default)
        params.append(Param(f"tracker.{f.name}", default, description, check, bounds=_tracker_bounds(f.name)))
    return params


def _tracker_bounds(name: str) -> tuple[float, float]:
    """The descriptor's range of what _tracker_check accepts (a fraction's 0 is refused by the check)."""
    if name in _SIGNED:
        return _SIGNED[name]
    return (0.0, 1.0) if _FRACTIONS & set(name.split("_")) else (0.0, sys.float_info.max)


def _tracker_check(name: str, default: Any) -> Any:
    if isinstance(default, str):
        return one_of(*TRACKER_CHOICES.get(name, (default,)))
    if name in _SIGNED:
        return in_range(*_SIGNED[name])

    def check(value: Any) -> str | None:
        if isinstance(default, bool):
            return None
        values = value if isinstance(value, list | tuple) else [value]
        for v in values:
            if not math.isfinite(v) or v < 0:
                return f"must be finite and >= 0, got {value}"
            if _FRACTIONS & set(name.split("_")) and not 0.0 < v <= 1.0:
                return f"must be in (0, 1], got {value}"
        if isinstance(default, list) and len(values) != len(default):
            return f"must have {len(default)} values, got {value}"
        return None

    return check


class HomographyTrackerNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        # in the camera's namespace unless launched into another (__ns remap, or a namespace argument)
        super().__init__("homography_tracker", **{"namespace": topics.NAMESPACE, **kwargs})
        p = declare_params(self, PARAMS)
        tracker_values = declare_params(self, tracker_params())
        config_kwargs = {}
        for name, value in tracker_values.items():
            field = name.removeprefix("tracker.")
            config_kwargs[field] = tuple(int(v) for v in value) if isinstance(value, list) else value
        try:
            self._config = TrackerConfig(**config_kwargs)
            self._tracker = HomographyTracker(self._config)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"tracker configuration: {exc}") from exc

        self._counts: Counter[str] = Counter()
        self._warnings = CountedWarnings(self, self._counts)
        self._durations: deque[float] = deque(maxlen=1000)
        self._last_seq: int | None = None
        self._last_frame_index = -1
        self._map_keyframe_id: int | None = None  # keyframe of the last result (a change: save the map)
        self._keyframe_stamps: dict[int, tuple[Time, str]] = {}
        self._reference: tuple[Time, str] | None = None
        self._state_counts: Counter[TrackingState] = Counter()

        qos = reliable_qos() if p["queue_policy"] == "lossless" else reliable_qos(p["queue_depth"])
        self._pub = self.create_publisher(HomographyStamped, topics.HOMOGRAPHY, reliable_qos())
        self._kf_pub = self.create_publisher(KeyframeMatches, topics.KEYFRAMES, reliable_qos())
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable_qos(10))
        self.create_subscription(
            IngestedFrame, topics.FRAME_IN, self._on_frame, qos, qos_overriding_options=qos_overrides()
        )
        self._p = p
        self._failing = FailureRun()
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self._held: deque[tuple[Any, Any]] = deque()  # (publisher, message) waiting for subscribers
        self._wait_subs = p["wait_for_subscribers"]
        self._max_held = p["max_held"]
        # Retries while outputs are held only: an always-on 50 Hz timer wakes the executor for nothing
        # and delays the frames queued behind it.
        self._flush_timer = self.create_timer(0.02, self._flush_held)
        self._flush_timer.cancel()
        self._map_path = Path(p["state_dir"]) / MAP_FILE if p["state_dir"] else None
        self._save_period = float(p["save_period"])
        self._save_wake = threading.Condition()
        self._save_pending: tuple[TrackerMap, dict[str, Any]] | None = None
        self._save_stop = False
        self._saver: threading.Thread | None = None
        self._png_cache: dict[Any, bytes] = {}  # keyframe images encoded by earlier saves (saver thread)
        if self._map_path is not None:
            # the saver thread only updates these (a key added during the diagnostics' iteration would raise)
            self._counts.update(map_saves=0, map_save_failures=0, map_save_ms_last=0)
            remove_stale_temporaries(self._map_path.parent)  # of a save killed half-way
            self._load_map(self._map_path)
            self._saver = threading.Thread(target=self._save_loop, name="tracker_map_saver", daemon=True)
            self._saver.start()
        self.get_logger().info(
            f"tracking {topics.FRAME_IN} -> {self._pub.topic_name} ({p['queue_policy']}); "
            f"max_features={self._config.max_features}, max_keyframes={self._config.max_keyframes}; "
            f"state_dir {p['state_dir'] or '(none: no persistence)'}"
        )

    # ------------------------------------------------------------------ keyframe map persistence
    def _load_map(self, path: Path) -> None:
        """Restore the saved map and its keyframes' stamps; any problem: a warning and a new map."""
        try:
            blob = path.read_bytes()
        except FileNotFoundError:
            self.get_logger().info(f"no saved tracker map at {path}: starting a new map")
            return
        except OSError as exc:
            self.get_logger().warning(f"cannot read the saved tracker map {path} ({exc}): starting a new map")
            return
        try:
            data, extra = map_from_bytes(blob)
            self._tracker.restore_map(data)
            stamps = {}
            for key, (sec, nanosec, frame_id) in dict(extra.get("keyframe_stamps", {})).items():
                stamps[int(key)] = (Time(sec=int(sec), nanosec=int(nanosec)), str(frame_id))
            reference = stamps[self._tracker.reference_id]
        except (ValueError, TypeError, KeyError) as exc:
            self._tracker.reset()
            self.get_logger().warning(
                f"ignoring the saved tracker map {path} ({type(exc).__name__}: {exc}): starting a new map"
            )
            return
        self._keyframe_stamps = stamps
        self._reference = reference
        self._last_frame_index = self._tracker.frame_index
        self.get_logger().info(
            f"restored the tracker map from {path}: {len(self._tracker.keyframes())} keyframes, reference "
            f"{self._tracker.reference_id}; relocalising against it"
        )

    def _queue_map_save(self) -> None:
        """Hand the current map (references, no copies) to the saver thread; O(keyframes)."""
        data = self._tracker.export_map()
        if data is None:
            return
        stamps = {}
        for kf in data["keyframes"]:
            stamp = self._keyframe_stamps.get(kf["id"])
            if stamp is not None:
                stamps[str(kf["id"])] = [int(stamp[0].sec), int(stamp[0].nanosec), stamp[1]]
        with self._save_wake:
            self._save_pending = (data, {"keyframe_stamps": stamps})
            self._save_wake.notify()

    def _save_loop(self) -> None:
        """Saver thread: the newest queued map, at most once per save_period; the last one on close()."""
        last = -math.inf
        while True:
            with self._save_wake:
                self._save_wake.wait_for(lambda: self._save_pending is not None or self._save_stop)
                if self._save_pending is None:
                    return
                delay = last + self._save_period - time.monotonic()
                if delay > 0.0 and not self._save_stop:
                    self._save_wake.wait_for(lambda: self._save_stop, timeout=delay)
                item, self._save_pending = self._save_pending, None
            start = time.monotonic()
            try:
                atomic_write_bytes(self._map_path, map_to_bytes(*item, cache=self._png_cache))
                self._counts["map_saves"] += 1
            except Exception as exc:  # a full disk must not stop the tracking
                self._counts["map_save_failures"] += 1
                if self._counts["map_save_failures"] == 1:
                    self.get_logger().warning(f"saving the tracker map {self._map_path} failed: {exc}")
            self._counts["map_save_ms_last"] = round(1e3 * (time.monotonic() - start))
            last = time.monotonic()

    def close(self) -> None:
        """Save the map one last time and stop the saver (called by run_node on shutdown)."""
        if self._saver is None:
            return
        self._queue_map_save()
        with self._save_wake:
            self._save_stop = True
            self._save_wake.notify()
        self._saver.join(timeout=30.0)

    def _warn_once(self, kind: str, message: str) -> None:
        self._warnings.warn_once(kind, f"{kind}: {message}")

    def _on_frame(self, msg: IngestedFrame) -> None:
        self._counts["frames_in"] += 1
        if self._last_seq is not None and msg.seq > self._last_seq + 1:
            self._counts["frames_dropped"] += msg.seq - self._last_seq - 1
        elif self._last_seq is not None and msg.seq <= self._last_seq:
            self._counts["seq_restarted"] += 1  # frame_ingest restarted
        self._last_seq = msg.seq
        result: TrackResult | None = None
        start = time.perf_counter()
        try:
            image = mono8_from_msg(msg.image)
            if not (msg.scale > 0.0 and math.isfinite(msg.scale)):
                raise FrameError("bad_scale", f"scale {msg.scale}")
            result = self._tracker.track(image, float(msg.scale), stamp_to_sec(msg.header.stamp))
        except FrameError as exc:
            self._warn_once(f"bad_frame_{exc.kind}", str(exc))
        except Exception as exc:  # the tracker must never take the node down
            self._warn_once("tracker_error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            self._tracker.reset()
        self._durations.append(time.perf_counter() - start)
        self._publish(msg, result)
        if result is None:
            return
        # A revisit (TRACKING on from a stored keyframe) changes the map too: the keyframe a restarted
        # tracker relocalises against first, and the least-recently-used order its store prunes by.
        moved = result.keyframe_id is not None and result.keyframe_id != self._map_keyframe_id
        self._map_keyframe_id = result.keyframe_id
        self._counts["keyframe_changes"] += int(moved)
        if self._saver is not None and (result.state in KEYFRAME_STATES or moved):
            self._queue_map_save()

    def _publish(self, frame: IngestedFrame, result: TrackResult | None) -> None:
        out = HomographyStamped()
        out.header = frame.header
        out.image_width = frame.full_width
        out.image_height = frame.full_height
        out.encoders = frame.encoders
        out.seq = frame.seq
        H = None if result is None else result.H_ref
        if result is not None:
            if result.frame_index <= self._last_frame_index:  # the tracker was reset: new ids
                self._keyframe_stamps.clear()
                self._reference = None
            self._last_frame_index = result.frame_index
            if result.keyframe_id is not None and result.keyframe_id == result.frame_index:
                self._keyframe_stamps[result.keyframe_id] = (frame.header.stamp, frame.header.frame_id)
                self._prune_keyframe_stamps()
            if result.reference_id is not None:
                self._reference = self._keyframe_stamps.get(result.reference_id, self._reference)
        state = TrackingState.TRACKING_LOST if result is None else result.state
        if H is None or not np.all(np.isfinite(H)) or state in LOST_STATES:
            if H is not None and not np.all(np.isfinite(H)):
                self._warn_once("non_finite_homography", "the tracker returned a non-finite homography")
            if state not in LOST_STATES:
                state = TrackingState.TRACKING_LOST
            out.h = _IDENTITY.copy()
            out.inlier_count = 0
            out.match_count = 0 if result is None else int(result.match_count)
            out.rms_transfer_error = 0.0
        else:
            out.h = np.asarray(H, dtype=float).ravel()
            out.inlier_count = int(result.inlier_count)
            out.match_count = int(result.match_count)
            rms = float(result.rms_transfer_error)
            out.rms_transfer_error = rms if math.isfinite(rms) else 0.0
        out.state = TRACKING_STATE_TO_MSG[state]
        out.rolling_shutter_readout = 0.0 if state in LOST_STATES else float(result.readout)
        if result is not None and result.keyframe_id is not None:
            out.keyframe_id = int(result.keyframe_id)
        if self._reference is not None:
            out.reference_stamp, out.reference_frame_id = self._reference
        self._state_counts[state] += 1
        self._send(self._pub, out)
        self._counts["frames_out"] += 1
        if result is not None:
            for link in result.links:
                self._publish_link(link)

    def _send(self, publisher: Any, msg: Any) -> None:
        self._held.append((publisher, msg))
        self._flush_held()

    def _flush_held(self) -> None:
        if self._held and self._pub.get_subscription_count() < self._wait_subs:
            while len(self._held) > self._max_held:
                self._held.popleft()
                self._warn_once("dropped_no_subscriber", "outputs dropped while nothing subscribes to them")
            if self._flush_timer.is_canceled():
                self._flush_timer.reset()
            return
        if not self._flush_timer.is_canceled():
            self._flush_timer.cancel()
        while self._held:
            publisher, msg = self._held.popleft()
            publisher.publish(msg)

    def _publish_link(self, link: Any) -> None:
        if not (np.all(np.isfinite(link.H)) and len(link.source_points) == len(link.target_points)):
            self._warn_once("bad_keyframe_link", "a keyframe link with non-finite values was not published")
            return
        msg = KeyframeMatches()
        stamp = self._keyframe_stamps.get(link.target_id)
        if stamp is not None:
            msg.header.stamp, msg.header.frame_id = stamp
        msg.keyframe_id = int(link.target_id)
        msg.other_keyframe_id = int(link.source_id)
        msg.h = np.asarray(link.H, dtype=float).ravel()
        msg.points = np.asarray(link.target_points, dtype=np.float32).ravel()
        msg.other_points = np.asarray(link.source_points, dtype=np.float32).ravel()
        self._send(self._kf_pub, msg)
        self._counts["keyframe_links_out"] += 1

    def _prune_keyframe_stamps(self) -> None:
        if len(self._keyframe_stamps) > 2 * self._config.max_keyframes + 8:
            alive = set(self._tracker.keyframes())
            for kid in [k for k in self._keyframe_stamps if k not in alive]:
                del self._keyframe_stamps[kid]

    def _readout_values(self) -> dict[str, Any]:
        """The rolling-shutter readout: in use, estimated (its 1-sigma, frames) and how it is known."""
        readout = self._tracker.readout
        if not readout.enabled:
            mode = "off (global shutter)"
        elif readout.known:
            mode = "known (tracker.rolling_shutter_readout)"
        else:
            mode = "estimated, settled" if readout.settled else "estimating"
        values: dict[str, Any] = {
            "rolling_shutter": mode,
            "rolling_shutter_readout_ms": f"{1e3 * readout.applied:.3f}",
        }
        if not readout.known:
            values["rolling_shutter_estimate_ms"] = f"{1e3 * readout.estimate:.3f}"
            values["rolling_shutter_sigma_ms"] = f"{1e3 * readout.sigma:.3f}"
            values["rolling_shutter_frames"] = readout.frames
        return values

    def _publish_diagnostics(self) -> None:
        counters: dict[str, Any] = {"frames_in": 0, "frames_out": 0, "frames_dropped": 0}
        counters.update(sorted(self._counts.items()))
        counters.update({f"state_{k}": v for k, v in sorted(self._state_counts.items())})
        if self._durations:
            d = np.asarray(self._durations) * 1e3
            counters["track_ms_mean"] = f"{d.mean():.2f}"
            counters["track_ms_p95"] = f"{np.percentile(d, 95):.2f}"
            counters["track_ms_max"] = f"{d.max():.2f}"
        counters.update(self._readout_values())
        counters["keyframes"] = len(self._keyframe_stamps)
        counters["map_keyframes"] = len(self._tracker.keyframes())  # in the tracker's store (max_keyframes)
        # matched on this side (what an output published now reaches), so a graph's readiness is observable
        counters["homography_subscribers"] = self._pub.get_subscription_count()
        counters["keyframes_subscribers"] = self._kf_pub.get_subscription_count()
        status = DiagnosticStatus()
        status.name = self.get_fully_qualified_name()
        status.hardware_id = camera_name_of(self, self._p["camera_name"])
        lost = sum(self._state_counts[state] for state in LOST_STATES)
        failing = self._failing.update(self._counts["frames_in"], self._counts["tracker_error"])
        error = []
        if failing >= self._p["error_threshold"]:
            error.append(f"the last {failing} frames failed with an internal error (tracker_error)")
        warn = []
        if self._counts.get("tracker_error") or self._counts.get("frames_dropped"):
            warn.append(
                f"{self._counts['tracker_error']} tracker errors, {self._counts['frames_dropped']} dropped"
            )
        ok = f"{counters['frames_out']} frames tracked ({lost} lost or textureless)"
        set_level(status, ok, error=error, warn=warn)
        status.values = diagnostic_values(counters)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self._diag_pub.publish(array)


def main(args: list[str] | None = None) -> int:
    return run_node(HomographyTrackerNode, args, "homography_tracker")


if __name__ == "__main__":
    sys.exit(main())
