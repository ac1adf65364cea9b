"""ROS-free numerics of the ASGP predictor (numpy and scipy only, with threadpoolctl for the
BLAS threads; OpenCV is used where it is installed, not needed: see ``collision._opencv``).

The functions ``resample`` and ``rollout`` are not re-exported here, so that
``asgp_ros.core.resample`` and ``asgp_ros.core.rollout`` always name the modules:
``from asgp_ros.core.rollout import rollout``.
"""

from asgp_ros.core.features import FeatureConfig, build_inputs, design_matrix, input_layout
from asgp_ros.core.modelfile import ModelFileError, load_model, save_model
from asgp_ros.core.models import (
    ChannelModel,
    ModelKind,
    MotionModel,
    get_kind,
    register_kind,
    registered_kinds,
)
from asgp_ros.core.resample import ResampleConfig, Resampled
from asgp_ros.core.rollout import Rollout
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.core.streams import RawStreams
from asgp_ros.core.unicycle import integrate_path, integrate_path_cov, path_sensitivity

__all__ = [
    "ChannelModel",
    "FeatureConfig",
    "ModelFileError",
    "ModelKind",
    "MotionModel",
    "RawStreams",
    "ResampleConfig",
    "Resampled",
    "Rollout",
    "SparseGP",
    "build_inputs",
    "design_matrix",
    "get_kind",
    "input_layout",
    "integrate_path",
    "integrate_path_cov",
    "load_model",
    "path_sensitivity",
    "register_kind",
    "registered_kinds",
    "save_model",
]
