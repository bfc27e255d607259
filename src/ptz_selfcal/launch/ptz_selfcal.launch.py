"""ROS 2 launch file of the ptz_selfcal node suite, for users with a full ROS install:
    ros2 launch ptz_selfcal ptz_selfcal.launch.py [params_file:=FILE] [namespace:=/cam1]
Here, without launch/launch_ros, `ptz-selfcal launch` does the same (tools/launch.py).

Each node is the package's executable of the same name (setup.py installs them into lib/ptz_selfcal,
where `ros2 run ptz_selfcal <name>` finds them). The parameter file has one top-level key per node name
(config/ptz_selfcal.yaml); it is rewritten with /**/<name> keys so that the sections apply under any
namespace. Nodes that die are respawned.
"""

import os
import tempfile

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

NODES = ("frame_ingest", "homography_tracker", "calibrator")


def _nodes(context, *args, **kwargs):
    params_file = LaunchConfiguration("params_file").perform(context)
    namespace = LaunchConfiguration("namespace").perform(context)
    with open(params_file) as stream:
        sections = yaml.safe_load(stream) or {}
    rewritten = {(k if str(k).startswith("/") else f"/**/{k}"): v for k, v in sections.items()}
    handle, path = tempfile.mkstemp(prefix="ptz_selfcal_params_", suffix=".yaml")
    with os.fdopen(handle, "w") as stream:
        yaml.safe_dump(rewritten, stream)
    return [
        Node(
            package="ptz_selfcal",
            executable=name,
            name=name,
            namespace=namespace,
            parameters=[path],
            output="screen",
            respawn=True,
            respawn_delay=1.0,
        )
        for name in NODES
    ]


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("ptz_selfcal"), "config", "ptz_selfcal.yaml")
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_file", default_value=default_params, description="parameter YAML"),
            DeclareLaunchArgument("namespace", default_value="", description="namespace, e.g. /cam1"),
            OpaqueFunction(function=_nodes),
        ]
    )
