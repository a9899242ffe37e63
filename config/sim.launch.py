"""Launch the soft_tissue_sim node with its parameters file, and optionally RViz 2.

    ros2 launch soft_tissue_sim sim.launch.py                      # the node, parameters from config/sim_node.yaml
    ros2 launch soft_tissue_sim sim.launch.py rviz:=true           # and RViz 2 with config/soft_tissue_sim.rviz
    ros2 launch soft_tissue_sim sim.launch.py scene:=beam_1200.yaml device:=cpu
    ros2 launch soft_tissue_sim sim.launch.py rate_hz:=100 realtime:=false

Arguments: rviz (false: with true, also a static transform so that the frame 'world' exists
in TF for RViz), params_file (the installed config/sim_node.yaml), scene, device, rate_hz and
realtime (empty: the parameters file's value), namespace (empty). A bad scene or value ends
the node with a FATAL line and exit code 1. RViz's fixed frame is 'world', the
node's default frame_id; with a namespace, point RViz's displays at the namespaced topics.
"""

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "soft_tissue_sim"


def _sim_node(context, *args, **kwargs):
    overrides = {}
    for key in ("scene", "device", "rate_hz", "realtime"):  # only what was given overrides the file
        value = LaunchConfiguration(key).perform(context).strip()
        if value:
            overrides[key] = value if key in ("scene", "device") else yaml.safe_load(value)  # 100 -> int, true -> bool
    return [Node(
        package=PACKAGE,
        executable="sim_node",
        name="soft_tissue_sim",
        namespace=LaunchConfiguration("namespace"),
        parameters=[LaunchConfiguration("params_file")] + ([overrides] if overrides else []),
        output="screen",
        emulate_tty=True,
    )]


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    return LaunchDescription([
        DeclareLaunchArgument("rviz", default_value="false", description="also start RViz 2"),
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "sim_node.yaml"),
                              description="parameters file of the simulation node"),
        DeclareLaunchArgument("scene", default_value="", description="scene YAML (empty: the parameters file's)"),
        DeclareLaunchArgument("device", default_value="", description="auto | cpu | cuda | cuda:N (empty: the file's)"),
        DeclareLaunchArgument("rate_hz", default_value="", description="physics steps per second (empty: the file's)"),
        DeclareLaunchArgument("realtime", default_value="", description="true | false (empty: the file's)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the simulation node"),
        OpaqueFunction(function=_sim_node),
        # RViz needs its fixed frame in TF; nothing else may publish 'world' here (identity, harmless otherwise)
        Node(
            package="tf2_ros",
            executable="static_transform_publisher",
            name="world_frame",
            arguments=["--frame-id", "world", "--child-frame-id", "soft_tissue_sim_world"],
            condition=IfCondition(LaunchConfiguration("rviz")),
        ),
        Node(
            package="rviz2",
            executable="rviz2",
            name="rviz2",
            arguments=["-d", os.path.join(share, "config", "soft_tissue_sim.rviz")],
            condition=IfCondition(LaunchConfiguration("rviz")),
            output="screen",
        ),
    ])
