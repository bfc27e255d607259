"""frame_ingest's relay in a real process (issue 19, copies per frame): without a subscriber on
selfcal/image_raw no image is written to the relay (the writer would copy every full-resolution image
into its history); with one, every ingested image is relayed, bytes unchanged."""

from __future__ import annotations

import numpy as np
from conftest import node_command
from test_frame_ingest import MODULE, Harness, image_msg, joint_msg, scene, true_encoders

ROS_DOMAIN_ID = 139


def _send(h: Harness, times: list[float]) -> dict[int, bytes]:
    sent = {}
    for t in times:
        h.joints.publish(joint_msg(t - 0.05, true_encoders(t - 0.05)))
        h.joints.publish(joint_msg(t + 0.05, true_encoders(t + 0.05)))
        msg = image_msg(t, scene(round(10 * t) % 7), "bgr8")
        h.raw.publish(msg)
        sent[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = bytes(msg.data)
        h.spin(0.05)
    return sent


def test_relay_writes_only_while_subscribed(ros_env, start_process):
    from sensor_msgs.msg import Image

    from ptz_selfcal import topics
    from ptz_selfcal.nodes.runtime import reliable_qos

    proc = start_process(
        node_command(
            MODULE, "-p", "working_width:=160", "-p", "diagnostics_period:=0.2", "-p", "encoder_wait:=0.3"
        ),
        ros_env,
        "frame_ingest_relay",
    )
    h = Harness()
    try:
        h.wait_connected(compressed=False)
        first = [100.0 + 0.1 * k for k in range(5)]
        _send(h, first)
        assert h.spin(10.0, lambda: len(h.frames) == len(first)), proc.output()
        assert h.spin(5.0, lambda: bool(h.diagnostics) and h.diagnostics[-1].get("frames_out") == "5")
        assert "frames_relayed" not in h.diagnostics[-1], h.diagnostics[-1]  # nobody subscribed

        relayed: dict[int, bytes] = {}
        sub = h.node.create_subscription(
            Image,
            topics.IMAGE_RELAY,
            lambda m: relayed.setdefault(
                m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, bytes(m.data)
            ),
            reliable_qos(50),
        )
        assert h.spin(10.0, lambda: sub.get_publisher_count() > 0)
        h.spin(0.5)  # the writer matched the reader too
        second = [101.0 + 0.1 * k for k in range(5)]
        sent = _send(h, second)
        assert h.spin(10.0, lambda: len(relayed) == len(second)), (len(relayed), proc.output()[-2000:])
        assert set(relayed) == set(sent)
        for stamp, data in relayed.items():
            assert np.array_equal(np.frombuffer(data, np.uint8), np.frombuffer(sent[stamp], np.uint8))

        def counted() -> bool:
            return bool(h.diagnostics) and h.diagnostics[-1].get("frames_out") == "10"

        assert h.spin(5.0, counted), h.diagnostics[-1:]
        assert h.diagnostics[-1]["frames_relayed"] == str(len(second)), h.diagnostics[-1]
    finally:
        h.close()
    assert proc.stop() == 0
