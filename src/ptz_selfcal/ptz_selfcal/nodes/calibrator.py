"""calibrator node: HomographyStamped (one per frame) + KeyframeMatches in, one CameraInfo per frame out.

A thin wrapper of online/session.CalibratorSession (which drives online/incremental's
IncrementalCalibrator with LM + the keyframe bundle adjustment with the MAP principal-point prior).
For every HomographyStamped it publishes EXACTLY ONE sensor_msgs/CameraInfo on topics.CAMERA_INFO
(header copied, full-resolution size, K, P = [K|0], R = I, plumb_bob D = [k1, k2, 0, 0, 0]) and one
FrameCalibration on topics.FRAME_CALIBRATION, whatever happens: before convergence from the best
prior (saved zoom model, else nominal parameters), with lost tracking from the zoom model
(PREDICTED_FROM_ZOOM) or the last good K (TRACKING_LOST). Re-optimisation runs in a worker thread on
keyframes only, so a frame never waits for it. The encoders are not used for calibration (they are
ground truth); the zoom encoder is used to learn and query the zoom model.

State: with `state_dir` set, the calibration state and the zoom model are saved atomically every
`save_period` seconds (when changed) and on shutdown, and reloaded at start (a corrupt file gives a
warning and a fresh start; a state of another image size, or one whose zoom model the first frames
after the restart contradict, a swapped camera or lens, too).

camera_info_manager's habits: `camera_info_url` (a camera_calibration YAML) gives the prior K in place of
the nominal field of view; `~/set_camera_info` (sensor_msgs/SetCameraInfo) takes a measured K, e.g.
cameracalibrator's, as the prior and as a zoom model sample at the current zoom; `~/reset`
(std_srvs/Trigger) drops the calibration, the zoom model and the saved state, and starts fresh. Run:
    python -m ptz_selfcal.nodes.calibrator --ros-args -p state_dir:=/var/lib/ptz_selfcal/cam1
"""

from __future__ import annotations

import math
import sys
import traceback
from collections import Counter
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import Quaternion, TransformStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from sensor_msgs.srv import SetCameraInfo
from std_srvs.srv import Trigger

from ptz_selfcal import topics
from ptz_selfcal.camera.geometry import quaternion_from_matrix
from ptz_selfcal.lens.hook import SessionLensHook
from ptz_selfcal.nodes.conversions import (
    MSG_TO_TRACKING_STATE,
    STATUS_TO_MSG,
    ConfigError,
    camera_info_fields,
    declare_params,
    diagnostic_values,
    stamp_to_sec,
)
from ptz_selfcal.nodes.params import CalibratorNodeConfig, config_kwargs, params_from
from ptz_selfcal.nodes.runtime import (
    CountedWarnings,
    FailureRun,
    InputWatch,
    camera_name_of,
    qos_overrides,
    reliable_qos,
    run_node,
    set_level,
)
from ptz_selfcal.nodes.session_runner import RunnerConfig, SessionRunner
from ptz_selfcal.nodes.solve_slots import SolveSlots, default_slot_count, default_slot_dir
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.online.frames import FrameInput, FrameOutput
from ptz_selfcal.online.session import CalibratorSession
from ptz_selfcal.persist.camera_info_file import (
    CameraInfoFileError,
    camera_info_path,
    read_camera_calibration,
)
from ptz_selfcal.status import HOMOGRAPHY_STATES, WARN_STATUSES, CalibrationStatus, TrackingState
from ptz_selfcal_msgs.msg import FrameCalibration, HomographyStamped, KeyframeMatches

# The node's own settings, then the session's: names, defaults, descriptions and ranges from the dataclasses.
PARAMS = params_from(CalibratorNodeConfig) + params_from(SessionConfig)


class CalibratorNode(Node):
    def __init__(self, **kwargs: Any) -> None:
        # in the camera's namespace unless launched into another (__ns remap, or a namespace argument)
        super().__init__("calibrator", **{"namespace": topics.NAMESPACE, **kwargs})
        p = declare_params(self, PARAMS)
        if p["focal_model"] == "constant" and p["ba_principal_point"] == "varying":
            # a fixed lens has one K for every image: the session would silently ignore it
            raise ConfigError(
                "parameter ba_principal_point varying contradicts focal_model constant (a fixed lens: one "
                "principal point for every image)"
            )
        self._p = p
        kwargs = config_kwargs(SessionConfig, p)
        kwargs["max_keyframes"] = max(p["max_keyframes"], p["min_keyframes"])
        config = SessionConfig(**kwargs)
        # a fixed lens estimates its one distortion coefficient inside the session's adjustment
        config.estimate_distortion = bool(p["estimate_distortion"]) and config.fixed_lens
        session = CalibratorSession(config, state_dir=p["state_dir"] or None)
        self._camera_name = camera_name_of(self, p["camera_name"])
        self._seed_prior(session, p["camera_info_url"])
        self._lens: SessionLensHook | None = None
        if p["estimate_distortion"] and not config.fixed_lens:
            self._lens = SessionLensHook(config.nominal_focal)
            session.set_distortion(self._lens.distortion)
        restored = False
        for line in session.restore():
            (self.get_logger().warning if line.startswith("WARNING") else self.get_logger().info)(line)
            restored |= line.startswith("restored calibration state")
        if self._lens is not None:
            self._lens.restored(session)
            if restored:  # the lens correction's own state is not saved: say what the frames get
                self.get_logger().info(
                    "restored lens: no correction needed (no distortion, or one below the noise), frames "
                    "keep their homographies"
                    if self._lens.pinhole
                    else "restored lens: its correction starts anew, frames of the restored map get K "
                    "from the zoom model (PREDICTED_FROM_ZOOM) until new keyframes are corrected"
                )

        self._counts: Counter[str] = Counter()
        self._warnings = CountedWarnings(self, self._counts)
        self._last_status: str | None = None
        self._last_frame_stamp_ns = 0
        slots = None
        if p["solve_slots"] >= 0:
            count = p["solve_slots"] or default_slot_count()
            slots = SolveSlots(p["solve_slots_dir"] or default_slot_dir(), count)
        self._runner = SessionRunner(
            session,
            RunnerConfig(p["reoptimise_budget"], p["reoptimise_period"], p["save_period"], slots),
            lens=self._lens,
            log=self._log,
        )

        self._info_pub = self.create_publisher(CameraInfo, topics.CAMERA_INFO, reliable_qos())
        self._frame_pub = self.create_publisher(FrameCalibration, topics.FRAME_CALIBRATION, reliable_qos())
        self._orientation_pub = self.create_publisher(TransformStamped, topics.ORIENTATION, reliable_qos(10))
        self._reference_frame = p["reference_frame"] or f"{self._camera_name}_selfcal_reference"
        self._child_frame = p["child_frame"] or f"{self._camera_name}_selfcal_optical"
        self._diag_pub = self.create_publisher(DiagnosticArray, topics.DIAGNOSTICS, reliable_qos(10))
        # matches first: when both are waiting, the executor takes a keyframe's matches before the next
        # frame's homography (inline_solves then solves with them, whatever the arrival order)
        self.create_subscription(KeyframeMatches, topics.KEYFRAMES, self._on_keyframe_matches, reliable_qos())
        # KEEP_ALL: every homography gets its CameraInfo (small messages; the tracker's queue is the bounded
        # one); the standard overrides let a deployment bound it
        self.create_subscription(
            HomographyStamped,
            topics.HOMOGRAPHY,
            self._on_homography,
            reliable_qos(),
            qos_overriding_options=qos_overrides(),
        )
        self.create_timer(p["diagnostics_period"], self._publish_diagnostics)
        self.create_service(SetCameraInfo, "~/set_camera_info", self._on_set_camera_info)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self._runner.start(inline=p["inline_solves"])
        self.get_logger().info(
            f"calibrating {topics.HOMOGRAPHY} -> {self._info_pub.topic_name}; state_dir "
            f"{p['state_dir'] or '(none: no persistence)'}; bundle adjustment "
            f"{'on' if p['bundle_adjustment'] else 'off'} (pp {p['ba_principal_point']}, "
            f"prior sigma {p['pp_prior_sigma_px']} px); focal length {p['focal_model']}"
        )

    def _seed_prior(self, session: CalibratorSession, url: str) -> None:
        """camera_info_url's K as the prior; a file that cannot be read is a configuration error."""
        try:
            path = camera_info_path(url, self._camera_name)
            if path is None:
                return
            calibration = read_camera_calibration(path)
        except CameraInfoFileError as exc:
            raise ConfigError(f"parameter camera_info_url: {exc}") from exc
        session.seed_prior(calibration.K, (calibration.width, calibration.height))
        K = calibration.K
        self.get_logger().info(
            f"prior K from {path} ({calibration.width}x{calibration.height} images): f = {K[1, 1]:.1f} px, "
            f"pp = ({K[0, 2]:.1f}, {K[1, 2]:.1f})"
        )

    def _on_set_camera_info(
        self, request: SetCameraInfo.Request, response: SetCameraInfo.Response
    ) -> SetCameraInfo.Response:
        info = request.camera_info
        K = np.asarray(info.k, dtype=float).reshape(3, 3)
        ok, text = self._runner.set_camera_info(K, np.asarray(info.d, dtype=float), (info.width, info.height))
        response.success, response.status_message = ok, text
        self._counts["set_camera_info_accepted" if ok else "set_camera_info_refused"] += 1
        self._log("info" if ok else "warning", f"set_camera_info: {text}")
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        removed = self._runner.reset("reset requested (~/reset): starting fresh")
        state_dir = self._runner.session.state_dir
        if state_dir is None:
            saved = "no state_dir: nothing saved"
        else:
            saved = f"removed {', '.join(map(str, removed))}" if removed else f"no saved state in {state_dir}"
        response.success = True
        response.message = f"calibration and zoom model dropped, a new epoch; {saved}"
        self._log("warning", f"reset: {response.message}")
        return response

    # ----------------------------------------------------------------------------------------------
    def _log(self, level: str, text: str) -> None:
        if text.startswith("worker_error"):
            self._warn_once("worker_error", text.removeprefix("worker_error: "))
            return
        # one call site per severity: rclpy refuses a call site whose severity changes between calls
        logger = self.get_logger()
        if level == "warning":
            logger.warning(text)
        elif level == "debug":
            logger.debug(text)
        else:
            logger.info(text)

    def _warn_once(self, kind: str, message: str) -> None:
        self._warnings.warn_once(kind, f"{kind}: {message}")

    def _on_homography(self, msg: HomographyStamped) -> None:
        self._counts["homographies_in"] += 1
        self._last_frame_stamp_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        width, height = int(msg.image_width), int(msg.image_height)
        runner = self._runner
        runner.solve_inline()  # inline_solves: what the previous frames brought is solved first
        try:
            h = np.asarray(msg.h, dtype=float)
            enc = msg.encoders
            zoom = float(enc.zoom) if enc.valid and math.isfinite(enc.zoom) else math.nan
            ref = msg.reference_stamp
            reference = f"{msg.reference_frame_id}@{ref.sec}.{ref.nanosec:09d}"
            H = h.reshape(3, 3) if h.size == 9 else None
            state = MSG_TO_TRACKING_STATE.get(msg.state, TrackingState.TRACKING_LOST)
            if self._lens is not None and state in HOMOGRAPHY_STATES:
                # distortion-corrected homography (keyframes held back until the first estimate)
                H, state = self._lens.frame(
                    H,
                    state,
                    int(msg.keyframe_id),
                    reference,
                    width,
                    height,
                    calibrated=runner.view.calibrated,
                )
            frame = FrameInput(
                stamp=stamp_to_sec(msg.header.stamp),
                H=H,
                tracking_state=state,
                width=width,
                height=height,
                keyframe_id=int(msg.keyframe_id),
                reference_id=reference,
                zoom=zoom,
            )
            if width <= 0 or height <= 0:
                self._warn_once("bad_image_size", f"image size {width}x{height} in a HomographyStamped")
            out, invalid = runner.process(frame)
            if invalid:
                self._warn_once("invalid_homography", "a non-finite or implausible homography was ignored")
        except Exception as exc:  # never lose a frame's CameraInfo to a bug
            self._warn_once("calibrator_error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            lost = FrameInput(0.0, None, TrackingState.TRACKING_LOST, max(width, 1), max(height, 1))
            out = runner.nominal_output(lost, CalibrationStatus.TRACKING_LOST)
        if MSG_TO_TRACKING_STATE.get(msg.state) == TrackingState.NEW_KEYFRAME:
            runner.wake()  # the worker adds the keyframe and re-optimises
        self._publish(msg, out)
        if out.status != self._last_status:
            self.get_logger().info(
                f"status {self._last_status or '-'} -> {out.status}: f={out.K[0, 0]:.1f} px, "
                f"pp=({out.K[0, 2]:.1f}, {out.K[1, 2]:.1f}), K from {out.source}"
                + (f" ({out.message})" if out.message else "")
            )
            self._last_status = out.status

    def _publish(self, msg: HomographyStamped, out: FrameOutput) -> None:
        width, height = int(msg.image_width), int(msg.image_height)
        info = CameraInfo()
        info.header = msg.header
        K, D = out.K, out.D
        if out.source in _PRIOR_SOURCES and self._p["camera_info_before_calibration"] == "uncalibrated":
            K, D = np.zeros((3, 3)), np.zeros(5)  # ROS's "uncalibrated": no K until a calibration
        for key, value in camera_info_fields(K, width, height, D[0], D[1]).items():
            setattr(info, key, value)
        self._info_pub.publish(info)

        fc = FrameCalibration()
        fc.header = msg.header
        fc.status = STATUS_TO_MSG[CalibrationStatus(out.status)]
        K = out.K
        fc.fx, fc.fy, fc.cx, fc.cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        fc.skew = float(K[0, 1])
        fc.k1, fc.k2 = float(out.D[0]), float(out.D[1])
        if out.R is not None:
            q = quaternion_from_matrix(out.R)
            fc.orientation = Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))
            # R maps reference coordinates to camera ones (section 3.3.1); a transform gives the child's
            # pose in the parent: the inverse rotation
            transform = TransformStamped()
            transform.header.stamp = msg.header.stamp
            transform.header.frame_id = self._reference_frame
            transform.child_frame_id = self._child_frame
            x, y, z, w = quaternion_from_matrix(out.R.T)
            transform.transform.rotation = Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))
            self._orientation_pub.publish(transform)
        else:  # unknown orientation: the (invalid) zero quaternion says so
            fc.orientation = Quaternion(x=0.0, y=0.0, z=0.0, w=0.0)
        fc.encoders = msg.encoders
        fc.sigma_f = _finite_or(out.sigma_f, -1.0)
        fc.sigma_cx = _finite_or(out.sigma_cx, -1.0)
        fc.sigma_cy = _finite_or(out.sigma_cy, -1.0)
        fc.residual = _finite_or(out.residual, -1.0)
        fc.keyframe_id = int(out.keyframe_id) & 0xFFFFFFFF
        fc.keyframe_count = int(out.keyframe_count)
        readout = float(msg.rolling_shutter_readout)  # what the tracker corrected the homography for
        fc.rolling_shutter_readout = readout if math.isfinite(readout) else 0.0
        self._frame_pub.publish(fc)
        self._counts["camera_info_out"] += 1

    def _on_keyframe_matches(self, msg: KeyframeMatches) -> None:
        self._counts["keyframe_matches_in"] += 1
        try:
            a = np.asarray(msg.points, dtype=float).reshape(-1, 2)
            b = np.asarray(msg.other_points, dtype=float).reshape(-1, 2)
        except ValueError:
            self._warn_once("bad_keyframe_matches", "point arrays of odd length")
            return
        if self._lens is not None:  # the hook re-sends them on corrected coordinates after each update
            self._lens.matches(int(msg.keyframe_id), int(msg.other_keyframe_id), a, b)
            self._runner.wake()
            return
        h = np.asarray(msg.h, dtype=float)
        h = h.reshape(3, 3) if h.size == 9 else None
        if not self._runner.add_keyframe_matches(int(msg.keyframe_id), int(msg.other_keyframe_id), a, b, h):
            self._warn_once(
                "bad_keyframe_matches", "unusable keyframe matches (too few or non-finite points)"
            )
            return
        self._runner.wake()

    # diagnostics' own state, made at the first report (from the node's parameters)
    _homography_watch: InputWatch | None = None
    _failing: FailureRun | None = None

    def _publish_diagnostics(self) -> None:
        watch, failing_run = self._homography_watch, self._failing
        if watch is None or failing_run is None:
            watch = self._homography_watch = InputWatch("homographies", self._p["stale_timeout"])
            failing_run = self._failing = FailureRun()
        counters: dict[str, Any] = {"homographies_in": 0, "camera_info_out": 0}
        counters.update(sorted(self._counts.items()))
        counters.update(self._runner.read(_session_counters))  # type: ignore[arg-type]
        if self._lens is not None:
            counters["distortion_updates"] = self._runner.distortion_updates
            counters["distortion_held_keyframes"] = self._lens.held_keyframes
            counters["distortion_uncorrectable_frames"] = self._lens.uncorrectable_frames
            lens = self._lens.lens
            if lens is not None and lens.snapshot is not None:
                counters["distortion_lam_at_reference"] = f"{lens.snapshot.lam_at(lens.nominal_focal):.5f}"
        # matched on this side (what a CameraInfo published now reaches), so a graph's readiness is observable
        counters["camera_info_subscribers"] = self._info_pub.get_subscription_count()
        counters["frame_calibration_subscribers"] = self._frame_pub.get_subscription_count()
        # whether the re-optimisation has taken in everything received up to the frame last_frame_stamp_ns
        # (0: idle; under load it lags the frames, and a test can wait for it instead of guessing a time)
        counters["last_frame_stamp_ns"] = self._last_frame_stamp_ns
        counters["reoptimise_pending"] = self._runner.pending
        counters["reoptimise_deferred_no_slot"] = self._runner.deferred_steps
        status = DiagnosticStatus()
        status.name = self.get_fully_qualified_name()
        status.hardware_id = self._camera_name
        error, warn = [], []
        failing = failing_run.update(self._counts["homographies_in"], self._counts["calibrator_error"])
        if failing >= self._p["error_threshold"]:
            error.append(f"the last {failing} frames failed with an internal error (calibrator_error)")
        if self._last_status in WARN_STATUSES:
            warn.append(f"status {self._last_status}")
        if self._counts.get("calibrator_error") or self._counts.get("worker_error"):
            errors = self._counts["calibrator_error"] + self._counts["worker_error"]
            warn.append(f"{errors} internal errors")
        stale = watch.stale(self._counts["homographies_in"])
        ok = f"{counters['camera_info_out']} frames calibrated; last status {self._last_status}"
        set_level(status, ok, error=error, stale=[stale] if stale else [], warn=warn)
        status.values = diagnostic_values(counters)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self._diag_pub.publish(array)

    def close(self) -> None:
        """Stop the worker and save the state (called by run_node on shutdown)."""
        try:
            self._runner.stop()
        except Exception as exc:
            self.get_logger().warning(f"final save failed: {exc}")
            return
        if self._runner.session.state_dir is not None:
            self.get_logger().info(f"saved the calibration state to {self._runner.session.state_dir}")


def _session_counters(s: CalibratorSession) -> dict[str, Any]:
    counters: dict[str, Any] = dict(s.counters)
    counters.update({f"status_{k}": v for k, v in s.status_counts.items()})
    counters.update({k: f"{v:.3f}" for k, v in s.timings_ms().items() if math.isfinite(v)})
    counters["calibration_state"] = s.state
    return counters


# the outputs that are a prior, not a calibration (a learned zoom model's K is one)
_PRIOR_SOURCES = frozenset({"prior", "nominal"})


def _finite_or(value: float, default: float) -> float:
    return float(value) if value is not None and math.isfinite(value) else default


def main(args: list[str] | None = None) -> int:
    # The re-optimisation worker holds the GIL in Python-level stretches of its solves; a frame's
    # callback waits up to the switch interval at every hand-over (5 ms by default, several per frame).
    # 1 ms bounds what the worker adds to a frame's latency at a small cost in the worker's throughput.
    sys.setswitchinterval(0.001)
    return run_node(CalibratorNode, args, "calibrator")


if __name__ == "__main__":
    sys.exit(main())
