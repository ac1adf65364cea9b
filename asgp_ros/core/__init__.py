"""ROS-free numerics of the ASGP predictor (numpy and scipy only)."""

from asgp_ros.core.sparse_gp import SparseGP

__all__ = ["SparseGP"]
