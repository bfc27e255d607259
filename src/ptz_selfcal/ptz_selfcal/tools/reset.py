"""`ptz-selfcal reset [--namespace NS] [--state-dir DIR]`: start a camera's calibration afresh.

A calibrator running in the namespace is asked through its `~/reset` service (std_srvs/Trigger): it drops
its calibration, its zoom model and its saved state, and starts a new epoch. When none answers, the
saved state of the stopped calibrator is deleted: --state-dir, else the directory `ptz-selfcal launch`
keeps the camera's state in ($ROS_HOME/ptz_selfcal/<camera name>). It says which of the two it did.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ptz_selfcal.persist.state_files import remove_state_files
from ptz_selfcal.tools.cli import CliError
from ptz_selfcal.tools.launch import check_namespace, state_root


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--namespace", help="the camera's namespace (default /ptz)")
    parser.add_argument(
        "--state-dir",
        type=Path,
        help="a stopped calibrator's state_dir (default: launch's, $ROS_HOME/ptz_selfcal/<camera name>)",
    )
    parser.add_argument("--camera-name", help="the camera's name (default: the namespace's last component)")
    parser.add_argument(
        "--wait", type=float, default=3.0, help="seconds to wait for a running calibrator's reset service"
    )


def run(args: argparse.Namespace) -> int:
    from ptz_selfcal import topics

    ns = check_namespace(args.namespace) or topics.NAMESPACE
    if not 0.0 <= args.wait <= 600.0:
        raise CliError(f"--wait must be in [0, 600] s, got {args.wait}")
    service = f"{ns}/calibrator/reset"
    answer = _call_reset(service, args.wait)
    if answer is not None:
        ok, message = answer
        print(f"reset the running calibrator ({service}): {message}")
        return 0 if ok else 1
    camera = args.camera_name or ns.rsplit("/", 1)[-1]
    state_dir = args.state_dir or Path(state_root()) / camera
    removed = remove_state_files(state_dir)
    if removed:
        print(f"no calibrator answers {service}: removed its saved state {', '.join(map(str, removed))}")
    else:
        print(f"no calibrator answers {service}, and {state_dir} holds no saved state: nothing to reset")
    return 0


def _call_reset(service: str, wait: float) -> tuple[bool, str] | None:
    """(success, message) of the service, or None when no calibrator offers it within `wait` seconds."""
    import rclpy
    from std_srvs.srv import Trigger

    rclpy.init(args=[])
    node = rclpy.create_node("ptz_selfcal_reset", enable_rosout=False)
    try:
        client = node.create_client(Trigger, service)
        if not client.wait_for_service(timeout_sec=wait):
            return None
        future = client.call_async(Trigger.Request())
        rclpy.spin_until_future_complete(node, future, timeout_sec=max(wait, 10.0))
        if not future.done() or future.result() is None:
            raise CliError(f"{service} did not answer")
        result = future.result()
        return bool(result.success), str(result.message)
    finally:
        node.destroy_node()
        rclpy.shutdown()
