"""Peers that cannot be matched on a node's topics, found from the ROS graph.

rclpy gives every publisher and subscription two event handlers by default (incompatible
QoS, incompatible type), whose only work is a warning when a peer cannot be matched. Each
is a waitable that rclpy's executor adds to its wait set at every wake-up, and a node on the
chair wakes for every message: with ``joy`` and ``joy_applied`` at the board's 100 Hz,
``predictor_node`` spent 12.7 / 12.8 % of a core with them and 10.5 / 11.0 % without, its
latency unchanged (two runs each, alternated; ``benchmarks/predictor_latency.py --clock
system --adapt off --joy-hz 100 --applied``).

``predictor_node`` and ``shared_control_node``, which read the joystick at that rate (now in
batches, :mod:`asgp_ros.nodes.polled`), ``vo_node`` (three image streams) and
``serial_bridge_node``, therefore create their endpoints without those handlers
(:meth:`QosWatch.subscription`, :meth:`QosWatch.publisher`) and check their peers here
instead, at their diagnostics period (:meth:`QosWatch.check`): every publisher of a topic
the node subscribes to, every subscription of a topic it publishes, from the graph
(``get_publishers_info_by_topic`` and ``get_subscriptions_info_by_topic``), against the
node's own QoS as the graph reports it (``rclpy.qos.qos_check_compatible``; the profile a
node creates an endpoint with says "default" where the graph says "infinite", which the
check would take for a mismatch) and message type. A peer that cannot be matched is logged
once, as rclpy's handlers log it, and named in the diagnostics (``qos_mismatch``, at most
:data:`MAX_SHOWN` of them by name; the status is then WARN at least, its message naming the
first, :meth:`QosWatch.escalate`) for as long as it is there; one that goes and comes back
is logged again, and one whose node the graph has not discovered yet is logged once it has.
The graph is asked with each topic's name as the node created it (the queries expand and
remap their argument, as creation did). Only a certain mismatch counts: a QoS that may or
may not match ("system default" in a peer's profile) is left to DDS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rclpy.callback_groups import CallbackGroup
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSCompatibility, QoSProfile, qos_check_compatible
from rclpy.subscription import Subscription

__all__ = ["QosWatch", "message_type_name"]


def message_type_name(msg_type: Any) -> str:
    """``sensor_msgs/msg/Joy`` for ``sensor_msgs.msg.Joy``: the name the graph reports."""
    package = str(msg_type.__module__).split(".", 1)[0]
    return f"{package}/msg/{msg_type.__name__}"


#: Peers named in ``qos_mismatch`` at most; the others are counted.
MAX_SHOWN = 5
#: What the graph reports for a peer whose node it has not yet discovered.
_UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"


@dataclass(frozen=True)
class _Endpoint:
    subscribes: bool  # a subscription (its peers publish) or a publisher
    topic: str  # fully qualified and remapped, for the messages
    type_name: str
    #: the name as the node created the endpoint with: the graph queries expand and remap
    #: their argument, so they are given this one (the remapped name would be remapped again)
    asked: str


class QosWatch:
    """A node's endpoints, made without rclpy's default event handlers, and their peers."""

    def __init__(self, node: Node) -> None:
        self._node = node
        self._endpoints: list[_Endpoint] = []
        self._warned: set[tuple[str, bytes, str]] = set()
        self._problems: list[str] = []

    def subscription(self, msg_type: Any, topic: str, callback: Any, qos: QoSProfile,
                     callback_group: CallbackGroup | None = None) -> Subscription:
        sub = self._node.create_subscription(
            msg_type, topic, callback, qos, callback_group=callback_group,
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        self._endpoints.append(_Endpoint(True, sub.topic_name, message_type_name(msg_type),
                                         topic))
        return sub

    def publisher(self, msg_type: Any, topic: str, qos: QoSProfile) -> Publisher:
        pub = self._node.create_publisher(
            msg_type, topic, qos,
            event_callbacks=PublisherEventCallbacks(use_default_callbacks=False))
        self._endpoints.append(_Endpoint(False, pub.topic_name, message_type_name(msg_type),
                                         topic))
        return pub

    @property
    def problems(self) -> list[str]:
        """The peers that could not be matched at the last :meth:`check`."""
        return list(self._problems)

    def summary(self) -> str:
        """``qos_mismatch`` of the diagnostics: "none", or the peers that cannot be matched."""
        problems = self._problems  # one snapshot: check() may replace it on another thread
        shown = problems[:MAX_SHOWN]
        more = len(problems) - len(shown)
        return "; ".join(shown + ([f"{more} more"] if more else [])) or "none"

    def escalate(self, level: str, message: str) -> tuple[str, str]:
        """A diagnostic status's level and message, given the peers found at the last
        :meth:`check`: with one that cannot be matched an OK becomes WARN (the topic's data
        do not flow to or from that peer, though the node's own work goes on) and the
        message names the first; otherwise both as given."""
        problems = self._problems  # one snapshot (the bridge calls this from its reader)
        if not problems:
            return level, message
        n = len(problems)
        more = f" (and {n - 1} more, qos_mismatch)" if n > 1 else ""
        return ("WARN" if level == "OK" else level,
                f"{message}; cannot be matched: {problems[0]}{more}")

    def check(self) -> list[str]:
        """Look at every peer of every endpoint now; log each new mismatch once."""
        node = self._node
        me = (node.get_name(), node.get_namespace())
        problems = []
        present: set[tuple[str, bytes, str]] = set()
        for ep in self._endpoints:
            pubs = node.get_publishers_info_by_topic(ep.asked)
            subs = node.get_subscriptions_info_by_topic(ep.asked)
            ours, peers = (subs, pubs) if ep.subscribes else (pubs, subs)
            own = [i.qos_profile for i in ours if (i.node_name, i.node_namespace) == me]
            for peer in peers:
                if (peer.node_name, peer.node_namespace) == me:
                    continue
                # without the graph's own report of the node's QoS, only the type is judged
                # (the profile the endpoint was made with says "default" where the graph
                # says "infinite", which the QoS check takes for a mismatch)
                why = _mismatch(ep, peer.topic_type, peer.qos_profile,
                                own[0] if own else None)
                if why is None:
                    continue
                who = peer.node_namespace.rstrip("/") + "/" + peer.node_name
                role = "publisher" if ep.subscribes else "subscription"
                problems.append(f"{ep.topic}: {role} of {who}: {why}")
                key = (ep.topic, bytes(peer.endpoint_gid), why)
                present.add(key)
                if key not in self._warned and peer.node_name != _UNKNOWN_NODE:
                    self._warned.add(key)
                    flow = ("no messages will be received from it" if ep.subscribes
                            else "it will receive no messages from this node")
                    node.get_logger().warning(
                        f"{ep.topic}: the {role} of {who} cannot be matched ({why}); {flow}")
        self._warned &= present  # a peer that went and comes back is logged again
        self._problems = problems
        return list(problems)


def _mismatch(ep: _Endpoint, peer_type: str, peer_qos: QoSProfile,
              own_qos: QoSProfile | None) -> str | None:
    """Why a peer cannot be matched with ``ep`` (its QoS ``own_qos`` as the graph reports
    it; None: the type alone is judged), or None."""
    if peer_type != ep.type_name:
        return f"type {peer_type}, not {ep.type_name}"
    if own_qos is None:
        return None
    pub, sub = (peer_qos, own_qos) if ep.subscribes else (own_qos, peer_qos)
    compatibility, reason = qos_check_compatible(pub, sub)
    if compatibility == QoSCompatibility.ERROR:
        return "incompatible QoS: " + "; ".join(
            part.strip() for part in reason.replace("ERROR:", "").split(";") if part.strip())
    return None
