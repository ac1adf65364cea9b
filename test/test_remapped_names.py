"""What the nodes say under a namespace and remaps: the topics as they use them (resolved,
remapped), not their parameters' relative names; and the predictor's ellipses beside its
path wherever a remap moves it."""

from __future__ import annotations

import pytest

pytest.importorskip("rclpy")

MODEL = "docs/reproduction/models/tile_asgp.npz"


def _ros_args(*rules: str) -> list[str]:
    return ["--ros-args", *[arg for rule in rules for arg in ("-r", rule)]]


@pytest.mark.ros
def test_vo_node_names_its_remapped_camera_topics(rclpy_context, capfd):
    """vo_node remapped to /cam5/info and /cam5/color said "waiting for camera_info on
    camera/color/camera_info", and its start-up line and hardware_id named the unremapped
    topics."""
    from asgp_ros.nodes.vo_node import VONode

    node = VONode(context=rclpy_context, cli_args=_ros_args(
        "__ns:=/chair5", "camera/color/camera_info:=/cam5/info",
        "camera/color/image_raw:=/cam5/color"))
    try:
        sent = []
        node._diag_pub.publish = sent.append
        node._publish_diagnostics()
        (status,) = sent[0].status
        assert status.message.startswith("waiting for camera_info on /cam5/info"), status
        assert status.hardware_id == "/cam5/color"
        err = capfd.readouterr().err
        assert "VO on /cam5/color + /chair5/camera/depth/image_raw (/cam5/info)" in err, err
        node._on_info(_camera_info())  # calibrated: waiting for pairs
        assert node.vo is not None
        sent.clear()
        node._publish_diagnostics()
        assert sent[0].status[0].message.startswith(
            "waiting for colour/depth pairs on /cam5/color (0 received), "
            "/chair5/camera/depth/image_raw (0 received)"), sent[0].status[0]
    finally:
        node.destroy_node()


def _camera_info():  # a 640 x 480 camera's
    import numpy as np

    from asgp_ros.demo import camera

    K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
    return camera.camera_info_from_matrix(0.0, K, 640, 480, "camera")


@pytest.mark.ros
def test_the_predictors_ellipses_follow_its_remapped_path(rclpy_context, repo_root, capfd):
    """With -r predicted_path:=/viz/chair7/path the path moved and the ellipses stayed on
    /chair7/predicted_path/uncertainty (derived from the parameter); the start-up line said
    "inputs joy, vo/twist" under remaps."""
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.predictor_node import PredictorNode

    model = [Parameter("model_path", value=str(repo_root / MODEL))]
    node = PredictorNode(context=rclpy_context, parameter_overrides=model, cli_args=_ros_args(
        "__ns:=/chair7", "predicted_path:=/viz/chair7/path", "joy:=pad", "vo/twist:=/vo7"))
    try:
        assert node.path_pub.topic_name == "/viz/chair7/path"
        assert node.marker_pub.topic_name == "/viz/chair7/path/uncertainty"
        err = capfd.readouterr().err
        assert ("inputs /chair7/pad, /vo7 (twist), plan /chair7/joy_plan; output "
                "/viz/chair7/path (ellipses /viz/chair7/path/uncertainty)") in err, err
    finally:
        node.destroy_node()
    # unremapped: beside the path in the namespace, as before
    node = PredictorNode(context=rclpy_context, parameter_overrides=model,
                         cli_args=_ros_args("__ns:=/chair7"))
    try:
        assert node.marker_pub.topic_name == "/chair7/predicted_path/uncertainty"
    finally:
        node.destroy_node()
    # the ellipses remapped themselves: where their own rule puts them
    node = PredictorNode(context=rclpy_context, parameter_overrides=model, cli_args=_ros_args(
        "__ns:=/chair7", "predicted_path:=/viz/path",
        "predicted_path/uncertainty:=/viz/ellipses"))
    try:
        assert node.marker_pub.topic_name == "/viz/ellipses"
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_the_layer_names_its_remapped_topics(rclpy_context, repo_root, capfd):
    """The shared-control layer's start-up line said "overrides on joy_override" under a
    remap, and its scan warnings named scan_topic's relative name."""
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.shared_control_node import SharedControlNode

    node = SharedControlNode(
        context=rclpy_context,
        parameter_overrides=[Parameter("model_path", value=str(repo_root / MODEL))],
        cli_args=_ros_args("__ns:=/chair3", "scan:=/front/scan", "joy_override:=/board3/ov"))
    try:
        err = capfd.readouterr().err
        assert ("obstacles from laser (/front/scan); inputs /chair3/joy, /chair3/vo/twist; "
                "overrides on /board3/ov") in err, err
        node._refuse_scan("a test")
        assert "ignoring /front/scan: a test" in capfd.readouterr().err
    finally:
        node.destroy_node()
