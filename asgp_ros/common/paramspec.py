"""Parameter tables shared by a node's declarations, its YAML file and its validation.

A node's parameters are one tuple of :class:`ParamSpec` (name, default, description, range).
:func:`check_values` turns the values a node received into a plain dict, checked against the
table: the type follows the default (bool, int, float or str), numbers must be finite and
inside ``[low, high]``. Cross-field rules stay with each node's own validation. ROS-free:
the rclpy side (descriptors, declarations) is :mod:`asgp_ros.nodes.parameters`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

#: the value types a parameter can have (its default's type is the parameter's type)
ParamValue = bool | int | float | str


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: ParamValue
    description: str
    low: float | None = None   # inclusive range for numbers
    high: float | None = None
    runtime: bool = False      # may change while the node runs (else read-only)


def check_value(spec: ParamSpec, value: object) -> Any:
    """``value`` converted to the type of ``spec.default``; ValueError naming the parameter.

    Typed ``Any``: the type follows ``spec.default``, and the checked values are passed on
    as keyword arguments of the nodes' parameter dataclasses.
    """
    if isinstance(spec.default, bool):
        if not isinstance(value, bool):
            raise ValueError(f"parameter {spec.name} must be a boolean, got {value!r}")
        return value
    if isinstance(spec.default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"parameter {spec.name} must be an integer, got {value!r}")
    elif isinstance(spec.default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"parameter {spec.name} must be a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"parameter {spec.name} must be finite, got {value!r}")
    elif isinstance(spec.default, str):
        if not isinstance(value, str):
            raise ValueError(f"parameter {spec.name} must be a string, got {value!r}")
        return value
    if spec.low is not None and spec.high is not None and not spec.low <= value <= spec.high:
        raise ValueError(
            f"parameter {spec.name} = {value} is outside [{spec.low}, {spec.high}]")
    return value


def check_values(specs: Iterable[ParamSpec], values: Mapping[str, object]) -> dict[str, Any]:
    """Every parameter of ``specs`` (missing ones take their defaults), checked."""
    return {spec.name: check_value(spec, values.get(spec.name, spec.default))
            for spec in specs}
