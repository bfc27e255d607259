"""ROS 2 launch file of the ptz_selfcal node suite, for users with a full ROS install:
    ros2 launch ptz_selfcal ptz_selfcal.launch.py [params_file:=FILE] [namespace:=/cam1]
Here, without launch/launch_ros, `ptz-selfcal launch` does the same (tools/launch.py).

The nodes are Python modules (`python3 -m ptz_selfcal.nodes.<name>`; the package installs no per-node
executables), so each one is an ExecuteProcess with the usual --ros-args. The parameter file has one
top-level key per node name (config/ptz_selfcal.yaml); it is rewritten with /**/<name> keys so that the
sections apply under any namespace. Nodes that die are respawned.
"""

import os
import sys
import tempfile

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.substitutions import LaunchConfiguration

NODES = (
    ("frame_ingest", "ptz_selfcal.nodes.frame_ingest"),
    ("homography_tracker", "ptz_selfcal.nodes.homography_tracker"),
    ("calibrator", "ptz_selfcal.nodes.calibrator"),
)


def _nodes(context, *args, **kwargs):
    params_file = LaunchConfiguration("params_file").perform(context)
    namespace = LaunchConfiguration("namespace").perform(context)
    with open(params_file) as stream:
        sections = yaml.safe_load(stream) or {}
    rewritten = {(k if str(k).startswith("/") else f"/**/{k}"): v for k, v in sections.items()}
    handle, path = tempfile.mkstemp(prefix="ptz_selfcal_params_", suffix=".yaml")
    with os.fdopen(handle, "w") as stream:
        yaml.safe_dump(rewritten, stream)
    actions = []
    for name, module in NODES:
        cmd = [sys.executable, "-m", module, "--ros-args", "-r", f"__node:={name}", "--params-file", path]
        if namespace:
            cmd += ["-r", f"__ns:={namespace}"]
        actions.append(ExecuteProcess(cmd=cmd, name=name, output="screen", respawn=True, respawn_delay=1.0))
    return actions


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("ptz_selfcal"), "config", "ptz_selfcal.yaml")
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_file", default_value=default_params, description="parameter YAML"),
            DeclareLaunchArgument("namespace", default_value="", description="namespace, e.g. /cam1"),
            OpaqueFunction(function=_nodes),
        ]
    )
