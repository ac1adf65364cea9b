"""rclpy side of :mod:`asgp_ros.common.paramspec`: descriptors and declarations from a table."""

from __future__ import annotations

from collections.abc import Iterable

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node

from asgp_ros.common.paramspec import ParamSpec


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """Description and range of one parameter, for ``ros2 param describe``.

    Parameters read only at start-up say so in their description; the node's on-set callback
    refuses to change them with a reason (rclpy's ``read_only`` would refuse without one).
    """
    text = spec.description if spec.runtime else f"{spec.description} (read at start-up)"
    d = ParameterDescriptor(description=text)
    if spec.low is not None and spec.high is not None and not isinstance(spec.default, bool):
        if isinstance(spec.default, int):
            d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high),
                                            step=0)]
        elif isinstance(spec.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(spec.low),
                                                         to_value=float(spec.high), step=0.0)]
    return d


def declare(node: Node, specs: Iterable[ParamSpec]) -> dict[str, object]:
    """Declare every parameter of ``specs`` on ``node``; return the values it received."""
    values: dict[str, object] = {}
    for spec in specs:
        node.declare_parameter(spec.name, spec.default, descriptor(spec))
        values[spec.name] = node.get_parameter(spec.name).value
    return values
