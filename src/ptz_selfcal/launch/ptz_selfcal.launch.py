"""ROS 2 launch file of the ptz_selfcal node suite, for users with a full ROS install:
    ros2 launch ptz_selfcal ptz_selfcal.launch.py [namespace:=/cam1] [camera_name:=cam1]
        [params_file:=FILE] [remappings:="image_raw:=camera/image joint_states:=/head/joints"]
        [persist:=false] [mosaic:=true]
Here, without launch/launch_ros, `ptz-selfcal launch` does the same: both take their node list (names,
namespace, parameters, remappings) from ptz_selfcal.tools.launch.plan_suite, so they start the same graph
(tests/unit/test_launch_params.py checks this file's actions against it with stand-ins for launch).

Each node is the package's executable of the same name (setup.py installs them into lib/ptz_selfcal).
The parameters go to each node as the dictionary plan_suite resolved for its fully qualified name (no
rewritten copy of the parameter file). Nodes that die are respawned, except after a configuration error
(exit status 2), which ends the launch: restarting cannot help. The nodes load the package's Fast DDS
profile (config/fastdds.xml: shared memory for raw images, a 2 s participant lease), as with
`ptz-selfcal launch`, unless the environment names a profile file of its own.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, RegisterEventHandler, Shutdown
from launch.event_handlers import OnProcessExit
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from ptz_selfcal.tools.launch import (
    CONFIG_ERROR_STATUS,
    NODE_MODULES,
    SUITE_NODES,
    dds_profile_environment,
    load_params_file,
    plan_suite,
    state_root,
)


def _true(text):
    return text.lower() in ("true", "1", "yes")


def _on_exit(event, context):
    if event.returncode == CONFIG_ERROR_STATUS:
        return [Shutdown(reason=f"{event.action.name}: configuration error (exit status 2)")]
    return []


def _nodes(context, *args, **kwargs):
    def value(name):
        return LaunchConfiguration(name).perform(context)

    data = load_params_file(value("params_file"), list(NODE_MODULES))
    plan = plan_suite(
        data,
        value("namespace") or None,
        value("remappings").split(),
        value("camera_name") or None,
        nodes=SUITE_NODES + (("mosaic",) if _true(value("mosaic")) else ()),
        state_root=state_root() if _true(value("persist")) else None,
    )
    profile = dds_profile_environment()  # the shipped file as it is: nothing is written here
    actions = []
    for planned in plan:
        node = Node(
            package="ptz_selfcal",
            executable=planned.name,
            name=planned.name,
            namespace=planned.namespace,
            parameters=[planned.parameters],
            remappings=list(planned.remappings),
            output="screen",
            respawn=True,
            respawn_delay=1.0,
            additional_env=profile,
        )
        actions += [node, RegisterEventHandler(OnProcessExit(target_action=node, on_exit=_on_exit))]
    return actions


def generate_launch_description():
    default_params = os.path.join(get_package_share_directory("ptz_selfcal"), "config", "ptz_selfcal.yaml")
    return LaunchDescription(
        [
            DeclareLaunchArgument("params_file", default_value=default_params, description="parameter YAML"),
            DeclareLaunchArgument(
                "namespace", default_value="", description="the camera's namespace (default /ptz)"
            ),
            DeclareLaunchArgument(
                "camera_name",
                default_value="",
                description="diagnostics hardware_id (default: the file's, else the namespace's last part)",
            ),
            DeclareLaunchArgument(
                "remappings", default_value="", description="space-separated FROM:=TO topic remappings"
            ),
            DeclareLaunchArgument(
                "persist",
                default_value="true",
                description="calibrator state in $ROS_HOME/ptz_selfcal/<camera_name> unless state_dir is set",
            ),
            DeclareLaunchArgument(
                "mosaic", default_value="false", description="also start the live mosaic (selfcal/mosaic)"
            ),
            OpaqueFunction(function=_nodes),
        ]
    )
