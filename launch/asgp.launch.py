"""The smart-wheelchair stack on a full ROS 2 install: serial bridge, VO, predictor and,
optionally, the shared-control layer.

    ros2 launch asgp_ros asgp.launch.py model_path:=/path/to/chair.npz
    ros2 launch asgp_ros asgp.launch.py model_path:=chair.npz use_bridge:=false \
        use_vo:=false use_sim_time:=true        # predictor only, following `asgp replay`

Each node reads its YAML from the package's share/asgp_ros/config (``serial_bridge_node``
-> bridge.yaml, ``vo_node`` -> vo.yaml, ``predictor_node`` -> predictor.yaml,
``shared_control_node`` -> shared_control.yaml, with ``use_shared_control:=true``); the
arguments below override single parameters. Topics are relative, so ``namespace:=chair1``
runs a second chair side by side.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

PACKAGE = "asgp_ros"


def _config(name: str) -> PathJoinSubstitution:
    return PathJoinSubstitution([FindPackageShare(PACKAGE), "config", name])


def _text(name: str) -> ParameterValue:
    """A launch argument given to a node as a string, never read as YAML (a model path
    ``chair #2.npz`` was cut at the '#', one named ``run: 2.npz`` aborted the launch)."""
    return ParameterValue(LaunchConfiguration(name), value_type=str)


def generate_launch_description() -> LaunchDescription:
    namespace = LaunchConfiguration("namespace")
    use_sim_time = LaunchConfiguration("use_sim_time")
    common = {"use_sim_time": use_sim_time}
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of all nodes and topics"),
        DeclareLaunchArgument("use_sim_time", default_value="false",
                              description="follow /clock (bag replay, simulation)"),
        DeclareLaunchArgument("model_path", description="model file from `asgp train`"),
        DeclareLaunchArgument("port", default_value="/dev/asgp_joystick",
                              description="serial device of the joystick interface board"),
        DeclareLaunchArgument("use_bridge", default_value="true",
                              description="start the serial bridge to the joystick board"),
        DeclareLaunchArgument("use_vo", default_value="true",
                              description="start the RGB-D visual odometry"),
        DeclareLaunchArgument("use_shared_control", default_value="false",
                              description="start the shared-control layer (needs `scan`)"),
        Node(
            package=PACKAGE,
            executable="serial_bridge_node",
            name="serial_bridge_node",
            namespace=namespace,
            # never use_sim_time: the bridge drives a real board in real time (it refuses it)
            parameters=[_config("bridge.yaml"), {"port": _text("port")}],
            condition=IfCondition(LaunchConfiguration("use_bridge")),
            output="screen",
        ),
        Node(
            package=PACKAGE,
            executable="vo_node",
            name="vo_node",
            namespace=namespace,
            parameters=[_config("vo.yaml"), common],
            condition=IfCondition(LaunchConfiguration("use_vo")),
            output="screen",
        ),
        Node(
            package=PACKAGE,
            executable="predictor_node",
            name="predictor_node",
            namespace=namespace,
            parameters=[_config("predictor.yaml"), common,
                        {"model_path": _text("model_path")}],
            output="screen",
        ),
        Node(
            package=PACKAGE,
            executable="shared_control_node",
            name="shared_control_node",
            namespace=namespace,
            parameters=[_config("shared_control.yaml"), common,
                        {"model_path": _text("model_path")}],
            condition=IfCondition(LaunchConfiguration("use_shared_control")),
            output="screen",
        ),
    ])
