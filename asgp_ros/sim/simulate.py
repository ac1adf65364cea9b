"""Offline simulation of one recording: driver -> chair -> sensors, fast and seeded.

The closed loop (driver and chair) runs step by step at the chair's internal rate
(100 Hz, the driver updates at 50 Hz); the sensors are then sampled from the logged truth
with vectorised numpy. 20 minutes simulate in a couple of seconds.

A recording is written as a bag through the generic writer,
:func:`asgp_ros.recording.bags.write_bag` (:func:`write_recording`): the recording serialises
itself as ``/joy``, ``/vo/twist`` and ``/ground_truth/odom`` messages
(:meth:`Recording.bag_content`).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from asgp_ros.common.topics import BAG_GROUND_TRUTH, BAG_JOY, BAG_VO_TWIST
from asgp_ros.core.quaternion import yaw_to_quaternion
from asgp_ros.core.streams import RawStreams
from asgp_ros.recording.bags import CUSTOM_DATA_KEY, BagContent, serialise_batch, write_bag
from asgp_ros.sim.chair import INTERNAL_RATE_HZ, Chair, ChairParams
from asgp_ros.sim.driver import Driver
from asgp_ros.sim.sensors import SensorParams, joystick_samples, vo_samples
from asgp_ros.sim.world import RECORDING_SURFACES, Room, room_for_surface

FloatArray = NDArray[np.float64]

DEFAULT_EPOCH_NS = 1_700_000_000 * 10**9
"""Wall-clock time (ns since the Unix epoch) of a recording's t = 0 in a bag."""

TRUTH_RATE_HZ = 20.0
"""Rate of the ground truth written to bags (/ground_truth/odom); the Recording keeps 100 Hz."""

BAG_TOPIC_TYPES = {
    BAG_JOY: "sensor_msgs/msg/Joy",
    BAG_VO_TWIST: "geometry_msgs/msg/TwistStamped",
    BAG_GROUND_TRUTH: "nav_msgs/msg/Odometry",
}
"""The topics a recording is written on, and their message types."""


@dataclass(frozen=True)
class Recording:
    """One simulated drive: what the sensors reported and what really happened.

    Times are seconds from the start of the recording (add ``epoch_ns`` for bag time).

    Attributes:
        surface: "tile", "carpet" or "hybrid". seed: the seed. duration: length (s).
        joy_t: [Nj] joystick stamps; joy: [Nj, 2] readings; joy_bag_t: [Nj] bag times.
        vo_t: [Nv] VO frame stamps; vo: [Nv, 2] reported (v, omega); vo_bag_t: [Nv];
        vo_stale: [Nv] reports repeated during a tracking failure.
        failures: [F, 2] (start, end) of each tracking failure.
        truth_t: [Nt] at the chair's internal rate (100 Hz); truth: [Nt, 5]
            (x, y, theta, v, omega); command: [Nt, 2] the true stick position;
            wheels: [Nt, 2] rim speeds; floor: [Nt] 0 = tile, 1 = carpet.
        epoch_ns: bag time of t = 0.
        meta: parameters and summary (JSON-serialisable).
    """

    surface: str
    seed: int
    duration: float
    joy_t: FloatArray
    joy: FloatArray
    joy_bag_t: FloatArray
    vo_t: FloatArray
    vo: FloatArray
    vo_bag_t: FloatArray
    vo_stale: NDArray[np.bool_]
    failures: FloatArray
    truth_t: FloatArray
    truth: FloatArray
    command: FloatArray
    wheels: FloatArray
    floor: NDArray[np.int8]
    epoch_ns: int = DEFAULT_EPOCH_NS
    meta: dict[str, Any] = field(default_factory=dict)

    def to_streams(self, absolute: bool = True, truth_rate_hz: float | None = None,
                   flag_failures: bool = False) -> RawStreams:
        """The recording as the resampler sees it (what a bag of it reads to).

        Args:
            absolute: add ``epoch_ns`` to the times (as in a bag).
            truth_rate_hz: decimate the ground truth to this rate (None: 100 Hz).
            flag_failures: mark the stale VO reports as tracking failures (``vel_ok``
                False), as a VO that reports its tracking state would; by default they are
                hidden, as with Fovis and in a bag.
        """
        off = self.epoch_ns * 1e-9 if absolute else 0.0
        ti, tr = self.truth_t, self.truth
        if truth_rate_hz is not None:
            step = max(1, round(INTERNAL_RATE_HZ / truth_rate_hz))
            ti, tr = ti[::step], tr[::step]
        return RawStreams(
            joy_t=self.joy_t + off, joy=self.joy, vel_t=self.vo_t + off, vel=self.vo,
            vel_ok=~self.vo_stale if flag_failures else np.ones(self.vo_t.size, dtype=bool),
            truth_t=ti + off, truth=tr, source=f"simulated {self.surface} seed {self.seed}",
        )

    def bag_content(self, typestore: Any, ros1: bool, truth: bool = True) -> BagContent:
        """The recording as bag messages for :func:`asgp_ros.recording.bags.write_bag`.

        ``/joy`` (sensor_msgs/Joy, axes = the two deflections) and ``/vo/twist``
        (TwistStamped in base_link) at their recorded stamps and bag times, and with
        ``truth`` ``/ground_truth/odom`` (Odometry, odom -> base_link) decimated to
        ``TRUTH_RATE_HZ``; the description ``meta`` goes into the custom data.

        Args:
            typestore: the rosbags typestore of the bag's format.
            ros1: serialise for a ROS 1 bag (headers carry a sequence number) instead of CDR.
            truth: include the ground truth.
        """
        msg = _Messages(typestore, ros1)
        stamp_fields = {"sec": "i4", "nanosec": "u4"} | ({"seq": "u4"} if ros1 else {})
        topics = [t for t in BAG_TOPIC_TYPES if truth or t != BAG_GROUND_TRUTH]
        out: list[tuple[int, int, bytes]] = []

        def to_ns(t: FloatArray) -> NDArray[np.int64]:
            return np.rint(np.asarray(t) * 1e9).astype(np.int64) + np.int64(self.epoch_ns)

        def add(topic: str, make: Callable[..., Any], fields: dict[str, str],
                t: FloatArray, bag_t: FloatArray, values: dict[str, Any]) -> None:
            n = t.shape[0]
            if n == 0:
                return
            t_ns = to_ns(t)
            values = dict(values, sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000,
                          seq=np.arange(1, n + 1))
            data = serialise_batch(typestore, ros1, BAG_TOPIC_TYPES[topic], make,
                                   stamp_fields | fields, values, n)
            out.extend(zip(to_ns(bag_t).tolist(), [topics.index(topic)] * n, data,
                           strict=True))

        add(BAG_JOY, msg.joy, {"a0": "f4", "a1": "f4"}, self.joy_t, self.joy_bag_t,
            {"a0": self.joy[:, 0], "a1": self.joy[:, 1]})
        add(BAG_VO_TWIST, msg.twist_stamped, {"v": "f8", "w": "f8"}, self.vo_t,
            self.vo_bag_t, {"v": self.vo[:, 0], "w": self.vo[:, 1]})
        if truth:
            period = float(self.truth_t[1] - self.truth_t[0]) if self.truth_t.size > 1 else 1.0
            step = max(1, round(1.0 / (TRUTH_RATE_HZ * period)))
            tt, st = self.truth_t[::step], self.truth[::step]
            _qx, _qy, qz, qw = yaw_to_quaternion(st[:, 2])
            add(BAG_GROUND_TRUTH, msg.odometry,
                {k: "f8" for k in ("x", "y", "qz", "qw", "v", "w")}, tt, tt,
                {"x": st[:, 0], "y": st[:, 1], "qz": qz, "qw": qw, "v": st[:, 3],
                 "w": st[:, 4]})
        return BagContent(connections=[(t, BAG_TOPIC_TYPES[t]) for t in topics],
                          messages=out,
                          custom_data={CUSTOM_DATA_KEY: json.dumps(self.meta, sort_keys=True)})


class _Messages:
    """Builders of the recording's messages in a bag's type store, from scalar fields (the
    form :func:`asgp_ros.recording.bags.serialise_batch` fills in); a ROS 1 header carries
    a sequence number."""

    def __init__(self, typestore: Any, ros1: bool) -> None:
        self.T = typestore.types
        self.ros1 = ros1

    def header(self, frame: str, sec: int, nanosec: int, seq: int) -> Any:
        T = self.T
        stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        if self.ros1:
            return T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def vec(self, x: float = 0.0, z: float = 0.0) -> Any:
        return self.T["geometry_msgs/msg/Vector3"](x=x, y=0.0, z=z)

    def twist(self, v: float, w: float) -> Any:
        return self.T["geometry_msgs/msg/Twist"](linear=self.vec(x=v), angular=self.vec(z=w))

    def joy(self, sec: int, nanosec: int, a0: float, a1: float, seq: int = 0) -> Any:
        """sensor_msgs/Joy, axes = (forward, turn) deflection."""
        return self.T["sensor_msgs/msg/Joy"](
            header=self.header("", sec, nanosec, seq),
            axes=np.array([a0, a1], dtype=np.float32), buttons=np.zeros(0, dtype=np.int32))

    def twist_stamped(self, sec: int, nanosec: int, v: float, w: float, seq: int = 0) -> Any:
        """geometry_msgs/TwistStamped in base_link."""
        return self.T["geometry_msgs/msg/TwistStamped"](
            header=self.header("base_link", sec, nanosec, seq), twist=self.twist(v, w))

    def odometry(self, sec: int, nanosec: int, x: float, y: float, qz: float, qw: float,
                 v: float, w: float, seq: int = 0) -> Any:
        """nav_msgs/Odometry, odom -> base_link, zero covariances."""
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=qz, w=qw))
        return T["nav_msgs/msg/Odometry"](
            header=self.header("odom", sec, nanosec, seq), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=self.twist(v, w),
                                                             covariance=np.zeros(36)))


def write_recording(path: str | os.PathLike[str], recording: Recording,
                    storage: str = "mcap", truth: bool = True) -> Path:
    """Write a recording as a bag (atomically, byte-for-byte reproducibly: message times
    come from the recording, never from the wall clock).

    Args:
        path: a ROS 2 bag directory, or a ``.bag`` file for ROS 1.
        recording: the simulator's output.
        storage: "mcap" (default), "sqlite3" or "ros1" (automatic for a ``.bag`` path).
        truth: include ``/ground_truth/odom`` (at ``TRUTH_RATE_HZ``).

    Raises:
        asgp_ros.recording.bags.BagError: the bag cannot be written.
    """
    class _Source:
        def bag_content(self, typestore: Any, ros1: bool) -> BagContent:
            return recording.bag_content(typestore, ros1, truth=truth)

    return write_bag(path, _Source(), storage=storage)



def simulate(
    surface: str,
    minutes: float,
    seed: int,
    *,
    room: Room | None = None,
    chair_params: dict[str, ChairParams] | None = None,
    sensor_params: SensorParams | None = None,
    epoch_ns: int = DEFAULT_EPOCH_NS,
) -> Recording:
    """Simulate one recording.

    Args:
        surface: "tile", "carpet" or "hybrid" (sets the floor and the VO failure rate).
        minutes: length (> 0.1 min, so that the motionless lead-in and tail fit).
        seed: seed; the same arguments give an identical recording.
        room: the room (default ``room_for_surface(surface)``).
        chair_params: per-floor chair parameters overriding the presets.
        sensor_params: sensor model parameters.
        epoch_ns: bag time of the start.
    """
    if surface not in RECORDING_SURFACES:
        raise ValueError(f"unknown surface {surface!r}; expected one of {RECORDING_SURFACES}")
    if not (math.isfinite(minutes) and minutes >= 0.1):
        raise ValueError(f"minutes must be >= 0.1, got {minutes}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    room = room if room is not None else room_for_surface(surface)
    sp = sensor_params if sensor_params is not None else SensorParams()
    duration = float(minutes) * 60.0
    ss = np.random.SeedSequence([seed, RECORDING_SURFACES.index(surface)])
    s_chair, s_driver, s_joy, s_vo = (int(s.generate_state(1)[0]) for s in ss.spawn(4))

    dt = 1.0 / INTERNAL_RATE_HZ
    log = _drive(Chair.for_room(room, s_chair, chair_params),
                 Driver(s_driver, room, duration=duration), duration)
    wheels = np.stack([log[:, 8], 2.0 * log[:, 4] - log[:, 8]], axis=1)
    truth_t = log[:, 0].copy()
    truth = log[:, 1:6].copy()
    command = log[:, 6:8].copy()
    moving = (np.abs(truth[:, 3]) > 0.02) | (np.abs(truth[:, 4]) > 0.02)

    joy_t, joy_r, joy_bag = joystick_samples(
        duration, truth_t, command, np.random.default_rng(s_joy), sp)
    vo = vo_samples(duration, truth_t, truth[:, :3], moving, surface,
                    np.random.default_rng(s_vo), sp)
    meta = _recording_meta(surface, seed, duration, room, sp, vo.failures,
                           moving_s=float(np.sum(moving[:-1] * dt)),
                           carpet_fraction=float(np.mean(log[:, 9])))
    return Recording(
        surface=surface, seed=int(seed), duration=duration,
        joy_t=joy_t, joy=joy_r, joy_bag_t=joy_bag,
        vo_t=vo.stamp, vo=vo.vel, vo_bag_t=vo.bag_time, vo_stale=vo.stale,
        failures=vo.failures, truth_t=truth_t, truth=truth, command=command,
        wheels=wheels, floor=log[:, 9].astype(np.int8), epoch_ns=int(epoch_ns), meta=meta,
    )


def _drive(chair: Chair, driver: Driver, duration: float) -> FloatArray:
    """The closed loop at the chair's rate (the driver's hand at half of it), from rest at
    the origin; the log [n, 10]: t, x, y, theta, v, omega, the two joystick deflections,
    the left wheel's speed, and 1 on carpet (0 on tile)."""
    state = chair.reset((0.0, 0.0, 0.0))
    dt = 1.0 / INTERNAL_RATE_HZ
    n = round(duration * INTERNAL_RATE_HZ) + 1
    log = np.empty((n, 10))
    joy = np.zeros(2)
    carpet = {"tile": 0.0, "carpet": 1.0}
    for i in range(n):
        t = i * dt
        if i % 2 == 0:  # the hand at 50 Hz
            joy = driver.command(t, state)
        log[i] = (t, state.x, state.y, state.theta, state.v, state.omega,
                  joy[0], joy[1], state.wheel_left, carpet[state.surface])
        if i + 1 < n:
            state = chair.step(joy, dt)
    return log


def _recording_meta(surface: str, seed: int, duration: float, room: Room, sp: SensorParams,
                    failures: FloatArray, *, moving_s: float, carpet_fraction: float
                    ) -> dict[str, Any]:
    """The description of a recording stored with its bag (room, rates, VO failures, time
    moving, share of carpet)."""
    return {
        "surface": surface,
        "seed": int(seed),
        "duration_s": duration,
        "room": {"x": [room.x_min, room.x_max], "y": [room.y_min, room.y_max],
                 "furniture_band": room.furniture_band, "base_surface": room.base_surface,
                 "patches": [[p.x_min, p.y_min, p.x_max, p.y_max, p.surface]
                             for p in room.patches]},
        "chair_rate_hz": INTERNAL_RATE_HZ,
        "joy_rate_hz": sp.joy_rate_hz,
        "vo_rate_hz": list(sp.vo_rate_hz),
        "vo_failure_rate_per_min": sp.failure_rate(surface),
        "vo_failures": failures.round(6).tolist(),
        "moving_s": round(moving_s, 3),
        "carpet_fraction": round(carpet_fraction, 4),
    }
