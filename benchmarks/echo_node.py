"""The floor of ``benchmarks/predictor_latency.py``: an rclpy node that answers each VO
message with a path at once, doing nothing else.

    .venv/bin/python benchmarks/echo_node.py --horizon 10 --lag 1 [--sim]

It has the predictor node's endpoints for the inputs the benchmark sends (the joystick and
VO with the sensor-data QoS, /clock with ``--sim``), publishes ``predicted_path`` (reliable,
depth 10) with ``--horizon`` poses, stamped with the grid step the predictor would predict
at (the VO message's step less ``--lag``), and spins rclpy's SingleThreadedExecutor as the
node does. What the predictor node's latency has beyond this node's is its own work (the
prediction, its buffers, its checks); what both have is rclpy's executor and DDS delivery
both ways on this machine.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DT = 0.2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--lag", type=int, default=0)
    parser.add_argument("--sim", action="store_true", help="use_sim_time (/clock)")
    args = parser.parse_args(argv)

    import numpy as np
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Path as PathMsg
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import Joy

    from asgp_ros.nodes import conversions as conv

    rclpy.init()
    node = rclpy.create_node("predictor_echo", parameter_overrides=[
        Parameter("use_sim_time", Parameter.Type.BOOL, args.sim)])
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(PathMsg, "predicted_path", reliable)
    k = args.horizon

    def on_vo(msg: TwistStamped) -> None:
        t0 = (round(conv.stamp_to_seconds(msg.header.stamp) / DT) - args.lag) * DT
        poses = np.zeros((k, 3))
        pub.publish(conv.path_from_poses(poses, t0 + DT * np.arange(1, k + 1), "base_link",
                                         t0))

    node.create_subscription(Joy, "joy", lambda _msg: None, qos_profile_sensor_data)
    node.create_subscription(Joy, "joy_applied", lambda _msg: None, qos_profile_sensor_data)
    node.create_subscription(TwistStamped, "vo/twist", on_vo, qos_profile_sensor_data)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
