"""rclpy side of :mod:`asgp_ros.common.paramspec`: descriptors and declarations from a table."""

from __future__ import annotations

from collections.abc import Callable, Container, Iterable

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

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
    """Declare every parameter of ``specs`` on ``node``; return the values it received.

    Raises:
        ValueError: rclpy refused a value given for one (out of its range, not finite, of
            another type), naming the parameter; a node refuses to start with it.
    """
    values: dict[str, object] = {}
    for spec in specs:
        try:
            node.declare_parameter(spec.name, spec.default, descriptor(spec))
        except ParameterException as exc:
            raise ValueError(f"parameter {spec.name}: {' '.join(str(exc).split())}") from None
        values[spec.name] = node.get_parameter(spec.name).value
        value = values[spec.name]
        if spec.name.endswith("_topic") and isinstance(value, str) and value.strip():
            # an invalid name reached rclpy's endpoint creation later, with a traceback
            problem = topic_name_problem(node.resolve_topic_name, value)
            if problem is not None:
                raise ValueError(f"parameter {spec.name}: {value!r} is not a valid topic "
                                 f"name ({problem})")
    unknown = unknown_overrides(node)
    if unknown:
        # a misspelt key left its setting at the default with one warning: a footprint
        # checked 0.7 m wide for footprint_widht 0.9, an axis not inverted for inverted
        raise ValueError(f"parameters this node does not have (misspelt?): "
                         f"{', '.join(unknown)}; it does not start with them")
    return values


def topic_name_problem(resolve: Callable[[str], str], name: str) -> str | None:
    """Why ``name`` is no valid topic name for a node (``resolve``: its
    ``resolve_topic_name``, expansion and remapping), in rcl's words; None if valid."""
    try:
        resolve(name)
    except RuntimeError as exc:  # rclpy's RCLError
        text = " ".join(str(exc).split())
        text = text.removeprefix("failed to resolve name: ")
        return text.split(", at /")[0]  # less rcl's source file and line
    return None


def topic_beside(resolve: Callable[..., str], topic: str, suffix: str) -> str:
    """The topic ``<topic>/<suffix>`` (a publisher's second topic: the path's ellipses) as
    a node is to use it: beside the name ``topic`` resolves to, namespace and remaps
    applied (a path remapped to ``/viz/path`` has its ellipses on
    ``/viz/path/uncertainty``: they stayed on the parameter's ``<ns>/predicted_path/...``),
    unless ``<topic>/<suffix>`` is remapped itself. ``resolve``: the node's
    ``resolve_topic_name``; ``topic`` must resolve."""
    own = f"{topic}/{suffix}"
    try:
        remapped = resolve(own)
        if remapped != resolve(own, only_expand=True):
            return remapped
    except RuntimeError:  # (rclpy's RCLError: a name too long, said by the caller's check)
        pass
    return f"{resolve(topic).rstrip('/')}/{suffix}"


def unknown_overrides(node: Node) -> list[str]:
    """Parameters given to ``node`` (a params file, ``-p``, ``parameter_overrides``) that it
    has not declared: rclpy ignores them silently, and a misspelt one (``adapt.enable``)
    would leave its setting at the default."""
    given = getattr(node, "_parameter_overrides", None) or {}  # rclpy keeps no public copy
    return sorted(name for name in given if not node.has_parameter(name))


#: Why a node refuses to switch ``use_sim_time`` while it runs.
SIM_TIME_AT_START = ("use_sim_time is read at start-up (the node's timers run on the clock it "
                     "chose then): restart the node to change it")


def sim_time_change(node: Node, params: Iterable[Parameter]) -> str | None:
    """Why ``params`` may not be applied to ``node``, if they switch its ``use_sim_time``
    (a change to the value it has is no switch); else None."""
    for prm in params:
        if prm.name == "use_sim_time" and prm.value != node.get_parameter(prm.name).value:
            return SIM_TIME_AT_START
    return None


def is_change(node: Node, prm: Parameter) -> bool:
    """Whether setting ``prm`` changes the node's value (a set to the value it has, a
    ``ros2 param load`` of the node's own dump, changes nothing and is not refused)."""
    return not node.has_parameter(prm.name) or prm.value != node.get_parameter(prm.name).value


def refuse_at_runtime(node: Node, names: Container[str], who: str
                      ) -> Callable[[list[Parameter]], SetParametersResult]:
    """An on-set-parameters callback for a node whose parameters ``names`` are all read at
    start-up: a change of one of them, or of ``use_sim_time``, is refused with the reason
    (without a callback rclpy would accept it and nothing would change)."""
    def callback(params: list[Parameter]) -> SetParametersResult:
        why = sim_time_change(node, params)
        for prm in params:
            if why is None and prm.name in names and is_change(node, prm):
                why = f"{prm.name} is read at start-up: restart {who} to change it"
        return SetParametersResult(successful=why is None, reason=why or "")
    return callback
