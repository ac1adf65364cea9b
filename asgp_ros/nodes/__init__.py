"""Thin rclpy nodes; message <-> numpy conversions live in :mod:`asgp_ros.nodes.conversions`."""
