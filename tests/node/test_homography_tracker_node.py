"""homography_tracker in a real process: one HomographyStamped per IngestedFrame (also when lost),
homographies in full-resolution pixels, keyframe links, and the latest-wins overload policy."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import node_command

from ptz_selfcal.camera.geometry import apply_homography, intrinsic_matrix, ptz_rotation
from ptz_selfcal.nodes.conversions import MSG_TO_TRACKING_STATE
from ptz_selfcal.status import HOMOGRAPHY_STATES, LOST_STATES, TrackingState

ROS_DOMAIN_ID = 113
MODULE = "ptz_selfcal.nodes.homography_tracker"
W, H = 640, 360  # working size; full size is twice that (scale 0.5)
K_FULL = intrinsic_matrix(900.0, 639.5, 359.5)
CORNERS = np.array([[0.0, 0.0], [1279.0, 0.0], [0.0, 719.0], [1279.0, 719.0], [640.0, 360.0]])


def tracking_state(msg) -> TrackingState:
    return MSG_TO_TRACKING_STATE[msg.state]


def texture(shared_data: Path) -> np.ndarray:
    """A crop of a shared panorama: the repository's own makes no keyframe in these pans."""
    img = cv2.imread(str(shared_data / "panoramas" / "building.jpg"), cv2.IMREAD_GRAYSCALE)
    h, w = img.shape
    return np.ascontiguousarray(img[h // 2 - 900 : h // 2 + 900, w // 3 : w // 3 + 2600])


def frame(tex: np.ndarray, pan: float, tilt: float) -> tuple[np.ndarray, np.ndarray]:
    """A full-resolution view rotated by (pan, tilt) from the reference, downscaled by 2, and the true
    full-resolution homography reference -> this frame (H = K R K^-1)."""
    H_true = K_FULL @ ptz_rotation(pan, tilt) @ np.linalg.inv(K_FULL)
    offset = np.array([[1.0, 0.0, 660.0], [0.0, 1.0, 540.0], [0.0, 0.0, 1.0]])  # into the texture
    to_texture = offset @ np.linalg.inv(H_true)
    full = cv2.warpPerspective(tex, to_texture, (2 * W, 2 * H), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR)
    return cv2.resize(full, (W, H), interpolation=cv2.INTER_AREA), H_true


class Harness:
    def __init__(self) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor

        from ptz_selfcal import topics
        from ptz_selfcal.nodes.runtime import reliable_qos
        from ptz_selfcal_msgs.msg import HomographyStamped, IngestedFrame, KeyframeMatches

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("test_tracker", namespace=topics.NAMESPACE, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.homographies: list = []
        self.keyframes: list = []
        self.diagnostics: list[dict[str, str]] = []
        self.diagnostics_stamps: list[int] = []  # header stamps (ns): the tracker's clock at publishing
        self.pub = self.node.create_publisher(IngestedFrame, topics.FRAME_IN, reliable_qos())
        self.node.create_subscription(
            HomographyStamped, topics.HOMOGRAPHY, self.homographies.append, reliable_qos()
        )
        self.node.create_subscription(
            KeyframeMatches, topics.KEYFRAMES, self.keyframes.append, reliable_qos()
        )
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, reliable_qos(10))
        self.IngestedFrame = IngestedFrame

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            if status.name.endswith("homography_tracker"):
                self.diagnostics.append({kv.key: kv.value for kv in status.values})
                self.diagnostics_stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)

    def spin(self, seconds: float, until=None) -> bool:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
            if until is not None and until():
                return True
        return until is None

    def send(self, seq: int, image: np.ndarray, pan: float) -> None:
        from ptz_selfcal.nodes.conversions import fill_mono8

        msg = self.IngestedFrame()
        msg.header.stamp.sec = 1000 + seq // 30
        msg.header.stamp.nanosec = (seq % 30) * 33_333_333
        msg.header.frame_id = "ptz_camera"
        msg.image.header = msg.header
        fill_mono8(msg.image, image)
        msg.full_width, msg.full_height, msg.scale = 2 * W, 2 * H, 0.5
        msg.encoders.pan, msg.encoders.tilt, msg.encoders.zoom, msg.encoders.valid = pan, 0.0, 7.0, True
        msg.seq = seq
        self.pub.publish(msg)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def harness() -> Harness:
    h = Harness()
    yield h
    h.close()


def connect(h: Harness, proc) -> None:
    assert h.spin(
        20.0,
        lambda: h.pub.get_subscription_count() > 0 and h.node.count_publishers("/ptz/selfcal/homography") > 0,
    ), proc.output()
    h.spin(0.3)


def test_one_homography_per_frame_accurate_and_lost_frames_flagged(
    ros_env, start_process, harness: Harness, shared_data
):
    proc = start_process(node_command(MODULE, "-p", "diagnostics_period:=0.2"), ros_env, "tracker")
    tex = texture(shared_data)
    connect(harness, proc)
    pans = np.radians(np.linspace(0.0, 8.0, 25))
    truths = []
    for seq, pan in enumerate(pans):
        image, H_true = frame(tex, float(pan), float(0.2 * pan))
        truths.append(H_true)
        harness.send(seq, image, float(pan))
        harness.spin(0.01)
    black = np.zeros((H, W), np.uint8)
    for seq in range(len(pans), len(pans) + 3):
        harness.send(seq, black, 0.0)
    n = len(pans) + 3
    assert harness.spin(60.0, lambda: len(harness.homographies) >= n), proc.output()
    assert [m.seq for m in harness.homographies] == list(range(n))
    for msg, H_true in zip(harness.homographies[: len(pans)], truths):
        assert (msg.image_width, msg.image_height) == (2 * W, 2 * H)
        assert msg.encoders.valid and msg.encoders.zoom == 7.0
        assert tracking_state(msg) in HOMOGRAPHY_STATES, msg.state
        assert msg.inlier_count >= 20
        h = np.asarray(msg.h).reshape(3, 3)
        error = np.linalg.norm(apply_homography(h, CORNERS) - apply_homography(H_true, CORNERS), axis=1)
        assert error.max() < 0.6, (msg.seq, error)  # full-resolution pixels: 3x the worst frame
        assert msg.reference_stamp == harness.homographies[0].header.stamp
        assert msg.rolling_shutter_readout == 0.0  # a global shutter: estimated, never applied
    for msg in harness.homographies[len(pans) :]:
        assert tracking_state(msg) in LOST_STATES
        assert np.array_equal(np.asarray(msg.h), np.eye(3).ravel()) and msg.inlier_count == 0
    assert harness.keyframes, "an 8 degree pan must make new keyframes with links"
    for kf in harness.keyframes:
        assert len(kf.points) == len(kf.other_points) > 0 and len(kf.points) % 2 == 0
        assert np.all(np.isfinite(kf.h))
    assert harness.spin(
        5.0, lambda: harness.diagnostics and harness.diagnostics[-1].get("frames_out") == str(n)
    )
    diagnostics = harness.diagnostics[-1]
    assert diagnostics["rolling_shutter"] in ("estimating", "estimated, settled")
    assert diagnostics["rolling_shutter_readout_ms"] == "0.000" and "rolling_shutter_sigma_ms" in diagnostics
    assert proc.alive()
    assert proc.stop() == 0


def test_latest_policy_sheds_frames_and_counts_them(ros_env, start_process, harness: Harness, shared_data):
    proc = start_process(
        node_command(
            MODULE, "-p", "queue_policy:=latest", "-p", "queue_depth:=1", "-p", "diagnostics_period:=0.2"
        ),
        ros_env,
        "tracker_latest",
    )
    tex = texture(shared_data)
    connect(harness, proc)
    images = [frame(tex, float(np.radians(0.2 * k)), 0.0)[0] for k in range(8)]
    sent = 80
    for seq in range(sent):  # about 300 frames/s: far faster than the tracker
        harness.send(seq, images[seq % len(images)], 0.0)
        time.sleep(0.003)

    # Wait for the newest frame's output, not for counters to add up to `sent`: the node counts drops
    # from gaps in seq after the first frame it takes, so frames shed before that one (the tracker's
    # executor woke after seq 1 or 2 had replaced seq 0 in the depth-1 queue) are counted nowhere.
    newest = sent - 1
    arrived = harness.spin(
        30.0, lambda: bool(harness.homographies) and harness.homographies[-1].seq == newest
    )
    assert arrived, ([m.seq for m in harness.homographies], harness.diagnostics[-1:])
    # The tracker published that output after its last frame and counter update, so diagnostics stamped
    # after this moment hold the final counts (they come on their own writer: one published earlier may
    # still arrive later).
    after = harness.node.get_clock().now().nanoseconds
    assert harness.spin(5.0, lambda: max(harness.diagnostics_stamps, default=0) > after)
    harness.spin(0.5)  # and no extra (duplicate) output after them
    d = harness.diagnostics[int(np.argmax(harness.diagnostics_stamps))]  # the newest, not the last to arrive
    seqs = [m.seq for m in harness.homographies]
    assert int(d["frames_dropped"]) > 0, d
    assert len(seqs) == int(d["frames_in"]) < sent, (seqs, d)  # one output per processed frame
    assert seqs == sorted(set(seqs)) and seqs[-1] == newest, seqs  # in order; newest never dropped
    # every frame from the first the tracker took to the newest was processed or counted as dropped
    assert int(d["frames_in"]) + int(d["frames_dropped"]) == sent - seqs[0], (seqs, d)
    assert proc.stop() == 0


def test_absurd_tracker_parameter_exits_with_a_clear_error(ros_env, start_process):
    proc = start_process(node_command(MODULE, "-p", "tracker.min_inlier_ratio:=3.0"), ros_env, "bad")
    assert proc.wait(20.0) == 2
    assert "tracker.min_inlier_ratio must be in (0, 1]" in proc.output()


def endpoints(h: Harness) -> set[bytes]:
    """GIDs of the tracker's frame subscription and homography publisher as the test's graph sees them."""
    infos = [
        *h.node.get_subscriptions_info_by_topic("/ptz/selfcal/frame_in"),
        *h.node.get_publishers_info_by_topic("/ptz/selfcal/homography"),
    ]
    return {bytes(i.endpoint_gid) for i in infos if i.node_name == "homography_tracker"}


def test_restarted_tracker_reloads_its_map_and_keeps_the_reference(
    ros_env, start_process, harness, tmp_path, shared_data
):
    """kill -9 after a pan, restart on the same state_dir: the first frame relocalises against the saved
    keyframes with the same reference (stamp) and an accurate homography, new keyframe ids continue."""
    import signal

    state = tmp_path / "state"
    args = ("-p", f"state_dir:={state}", "-p", "save_period:=0.2", "-p", "diagnostics_period:=0.2")
    proc = start_process(node_command(MODULE, *args), ros_env, "tracker_first")
    tex = texture(shared_data)
    connect(harness, proc)
    pans = np.radians(np.linspace(0.0, 8.0, 25))
    for seq, pan in enumerate(pans):
        harness.send(seq, frame(tex, float(pan), float(0.2 * pan))[0], float(pan))
        harness.spin(0.01)
    assert harness.spin(60.0, lambda: len(harness.homographies) >= len(pans)), proc.output()
    reference = harness.homographies[0].header.stamp
    last_keyframe = max(
        m.keyframe_id for m in harness.homographies if tracking_state(m) == TrackingState.NEW_KEYFRAME
    )
    assert last_keyframe > 0, "an 8 degree pan must make new keyframes"

    def saved() -> bool:
        d = harness.diagnostics[-1] if harness.diagnostics else {}
        return int(d.get("map_saves", 0)) > 0 and int(d.get("frames_out", 0)) == len(pans)

    harness.spin(0.5)  # a save started with the last keyframe has finished by the next diagnostics
    assert harness.spin(10.0, saved), harness.diagnostics[-1:]
    assert (state / "tracker_map.npz").exists()
    old = endpoints(harness)
    assert proc.stop(sig=signal.SIGKILL) == -signal.SIGKILL
    harness.homographies.clear()

    proc = start_process(node_command(MODULE, *args), ros_env, "tracker_restarted")
    assert proc.wait_for_output("restored the tracker map", 20.0), proc.output()
    # the killed node's endpoints stay in the graph until their lease expires: wait for the new ones
    assert harness.spin(20.0, lambda: len(endpoints(harness) - old) >= 2), proc.output()
    harness.spin(0.3)
    for seq, k in enumerate((12, 13, 14), start=len(pans)):
        image, H_true = frame(tex, float(pans[k]), float(0.2 * pans[k]))
        harness.send(seq, image, float(pans[k]))
        harness.spin(0.01)
    assert harness.spin(30.0, lambda: len(harness.homographies) >= 3), proc.output()
    first = harness.homographies[0]
    assert tracking_state(first) == TrackingState.RELOCALISED, (first.state, proc.output())
    assert first.keyframe_id > last_keyframe
    for msg, k in zip(harness.homographies, (12, 13, 14)):
        assert msg.reference_stamp == reference and msg.reference_frame_id == "ptz_camera"
        assert tracking_state(msg) in HOMOGRAPHY_STATES, msg.state
        H_true = frame(tex, float(pans[k]), float(0.2 * pans[k]))[1]
        h = np.asarray(msg.h).reshape(3, 3)
        error = np.linalg.norm(apply_homography(h, CORNERS) - apply_homography(H_true, CORNERS), axis=1)
        assert error.max() < 0.3, (msg.seq, error)  # 3x the worst frame
    assert proc.stop() == 0
    assert not [p.name for p in state.iterdir() if p.name.endswith(".tmp")]


def test_saved_map_follows_a_revisit(ros_env, start_process, harness, tmp_path, shared_data):
    """A pan out and back: the way back tracks the keyframes of the way out (TRACKING, no new keyframe)
    and the saved map says which one it tracks last, so a restart relocalises against it first."""
    from ptz_selfcal.frontend.tracker_map import map_from_bytes

    state = tmp_path / "state"
    args = ("-p", f"state_dir:={state}", "-p", "save_period:=0.2")
    proc = start_process(node_command(MODULE, *args), ros_env, "tracker_revisit")
    tex = texture(shared_data)
    connect(harness, proc)
    out = np.radians(np.linspace(0.0, 20.0, 41))  # keyframes every few degrees
    pans = [*out, *out[-2::-1]]
    for seq, pan in enumerate(pans):
        harness.send(seq, frame(tex, float(pan), float(0.2 * pan))[0], float(pan))
        harness.spin(0.01)
    assert harness.spin(60.0, lambda: len(harness.homographies) >= len(pans)), proc.output()
    made = max(m.keyframe_id for m in harness.homographies if tracking_state(m) == TrackingState.NEW_KEYFRAME)
    last = harness.homographies[-1]
    assert tracking_state(last) == TrackingState.TRACKING and last.keyframe_id < made, (
        last.state,
        last.keyframe_id,
        made,
    )

    def saved_keyframe() -> int | None:
        try:
            return int(map_from_bytes((state / "tracker_map.npz").read_bytes())[0]["keyframe_id"])
        except (OSError, ValueError):
            return None  # not written yet

    assert harness.spin(10.0, lambda: saved_keyframe() == last.keyframe_id), (
        saved_keyframe(),
        last.keyframe_id,
    )
    assert proc.stop() == 0


def test_corrupt_saved_map_gives_a_warning_and_a_new_map(
    ros_env, start_process, harness, tmp_path, shared_data
):
    state = tmp_path / "state"
    state.mkdir()
    (state / "tracker_map.npz").write_bytes(b"PK\x03\x04 truncated")
    proc = start_process(node_command(MODULE, "-p", f"state_dir:={state}"), ros_env, "tracker_corrupt")
    tex = texture(shared_data)
    connect(harness, proc)
    harness.send(0, frame(tex, 0.0, 0.0)[0], 0.0)
    assert harness.spin(20.0, lambda: len(harness.homographies) >= 1), proc.output()
    msg = harness.homographies[0]
    assert tracking_state(msg) == TrackingState.NEW_KEYFRAME and msg.reference_stamp == msg.header.stamp
    assert "ignoring the saved tracker map" in proc.output()
    assert proc.alive()
    assert proc.stop() == 0
