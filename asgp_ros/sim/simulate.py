"""Offline simulation of one recording: driver -> chair -> sensors, fast and seeded.

The closed loop (driver and chair) runs step by step at the chair's internal rate
(100 Hz, the driver updates at 50 Hz); the sensors are then sampled from the logged truth
with vectorised numpy. 20 minutes simulate in a couple of seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core.streams import RawStreams
from asgp_ros.sim.chair import INTERNAL_RATE_HZ, Chair, ChairParams
from asgp_ros.sim.driver import Driver
from asgp_ros.sim.sensors import SensorParams, joystick_samples, vo_samples
from asgp_ros.sim.world import RECORDING_SURFACES, Room, room_for_surface

FloatArray = NDArray[np.float64]

DEFAULT_EPOCH_NS = 1_700_000_000 * 10**9
"""Wall-clock time (ns since the Unix epoch) of a recording's t = 0 in a bag."""

TRUTH_RATE_HZ = 20.0
"""Rate of the ground truth written to bags (/ground_truth/odom); the Recording keeps 100 Hz."""


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

    chair = Chair.for_room(room, s_chair, chair_params)
    driver = Driver(s_driver, room, duration=duration)
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
    wheels = np.stack([log[:, 8], 2.0 * log[:, 4] - log[:, 8]], axis=1)
    truth_t = log[:, 0].copy()
    truth = log[:, 1:6].copy()
    command = log[:, 6:8].copy()
    moving = (np.abs(truth[:, 3]) > 0.02) | (np.abs(truth[:, 4]) > 0.02)

    joy_t, joy_r, joy_bag = joystick_samples(
        duration, truth_t, command, np.random.default_rng(s_joy), sp)
    vo = vo_samples(duration, truth_t, truth[:, :3], moving, surface,
                    np.random.default_rng(s_vo), sp)
    exposed = float(np.sum(moving[:-1] * dt))
    meta = {
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
        "vo_failures": vo.failures.round(6).tolist(),
        "moving_s": round(exposed, 3),
        "carpet_fraction": round(float(np.mean(log[:, 9])), 4),
    }
    return Recording(
        surface=surface, seed=int(seed), duration=duration,
        joy_t=joy_t, joy=joy_r, joy_bag_t=joy_bag,
        vo_t=vo.stamp, vo=vo.vel, vo_bag_t=vo.bag_time, vo_stale=vo.stale,
        failures=vo.failures, truth_t=truth_t, truth=truth, command=command,
        wheels=wheels, floor=log[:, 9].astype(np.int8), epoch_ns=int(epoch_ns), meta=meta,
    )
