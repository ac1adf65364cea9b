"""Each node's parameters are defined once, in its table (name, default, range): the YAML
files in config/ and the README are checked against those tables."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from asgp_ros.common.paramspec import ParamSpec, check_value

REPO = Path(__file__).resolve().parents[1]
ROS_BUILTINS = {"use_sim_time"}


def _tables() -> dict[str, tuple[str, tuple[ParamSpec, ...]]]:
    pytest.importorskip("rclpy")
    from asgp_ros.nodes import predictor_node, shared_control_node
    from asgp_ros.serial import params as bridge
    from asgp_ros.vo import params as vo

    return {"predictor_node": ("predictor.yaml", predictor_node.PARAMS),
            "serial_bridge_node": ("bridge.yaml", bridge.PARAMS),
            "vo_node": ("vo.yaml", vo.PARAMS),
            "shared_control_node": ("shared_control.yaml", shared_control_node.PARAMS)}


def _flatten(tree: dict, prefix: str = "") -> dict:
    """Nested YAML maps are ROS's dotted parameter names (calibration.forward.neutral)."""
    out: dict = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


@pytest.mark.parametrize("node", ["predictor_node", "serial_bridge_node", "vo_node",
                                  "shared_control_node"])
def test_yaml_values_are_declared_typed_and_in_range(node):
    yaml_name, specs = _tables()[node]
    doc = yaml.safe_load((REPO / "config" / yaml_name).read_text())
    # /**/: the node in any namespace (a bare name is the node in / only)
    assert list(doc) == [f"/**/{node}"], f"{yaml_name}: top level must be /**/{node}"
    values = _flatten(doc[f"/**/{node}"]["ros__parameters"])
    by_name = {s.name: s for s in specs}
    unknown = sorted(set(values) - set(by_name) - ROS_BUILTINS)
    assert not unknown, f"{yaml_name} sets parameters {node} does not declare: {unknown}"
    for name, value in values.items():
        if name in ROS_BUILTINS:
            continue
        spec = by_name[name]
        # ROS parameters keep their YAML type: 2 is an integer, not a double.
        assert type(value) is type(spec.default), (yaml_name, name, value, spec.default)
        check_value(spec, value)  # inside the declared range


def test_readme_names_only_declared_parameters():
    """Every `name_s`-style predictor parameter the README mentions is declared, and the
    README states no default that disagrees with the table."""
    specs = {s.name: s for s in _tables()["predictor_node"][1]}
    readme = (REPO / "README.md").read_text()
    for name, value in re.findall(r"`([a-z_]+_(?:s|hz|steps))`\s*\(default ([0-9.]+)", readme):
        assert name in specs, name
        assert float(value) == float(specs[name].default), (name, value)
    for name in re.findall(r"`((?:joy|vo|plan)_timeout_s|buffer_s|reset_jump_s)`", readme):
        assert name in specs, name


@pytest.mark.parametrize("node", ["predictor_node", "serial_bridge_node", "vo_node",
                                  "shared_control_node"])
@pytest.mark.parametrize("namespace", ["/", "/chair1", "/lab/chair2"])
def test_yaml_values_reach_the_node_in_any_namespace(node, namespace):
    """launch/asgp.launch.py hands each node its config/*.yaml as it is, and namespace:=
    as a remap of __ns. Keyed by the bare node name, rcl applied the file in / only: under
    namespace:=chair1 the bridge drove the board with the default calibration and the
    layer checked collisions with the default footprint, without a word. rcl's own
    reading of the shipped file, as the launch file passes it, must give the node every
    value in it."""
    import rclpy
    from rclpy.context import Context

    yaml_name, _ = _tables()[node]
    path = REPO / "config" / yaml_name
    doc = yaml.safe_load(path.read_text())
    (section,) = doc.values()
    want = _flatten(section["ros__parameters"])
    context = Context()
    rclpy.init(context=context, args=["--ros-args", "-r", f"__ns:={namespace}",
                                      "--params-file", str(path)])
    try:
        probe = rclpy.create_node(node, context=context, start_parameter_services=False,
                                  automatically_declare_parameters_from_overrides=True)
        try:
            assert probe.get_fully_qualified_name() == f"{namespace.rstrip('/')}/{node}"
            got = {name: probe.get_parameter(name).value for name in want
                   if probe.has_parameter(name)}
        finally:
            probe.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert got == want
