"""A simulated wheelchair user driving "roughly randomly but safely" (the paper's data
collection), closed loop on the chair's true state.

Behaviour: bouts of straight cruising at a chosen speed (with speed changes), arcs, turns
on the spot, stops and short reversals, drawn at random. The hand moves the stick towards
each bout's target through a second-order response (a 0.15-0.4 s reach, sometimes with a
little overshoot) plus a slow tremor, and lets the stick spring back to exactly zero when
it releases it.

Safety: like a person, the driver looks ahead along the direction of travel. When the
chair would get close to the furniture band along the walls it slows down and turns
towards open space (towards a point it picks in the free area), stopping and turning on
the spot if already close; a reversal is abandoned when the space behind runs out. The
chair's footprint stays out of the furniture band (``Room.furniture_band``) with a margin.

Inattention (``DriverParams.inattention`` > 0, off by default): now and then a bout is an
inattentive one. The driver heads for a point on the furniture front, at a cruising
speed, without looking ahead; only once the chair is within ``notice`` of the furniture
(or touching it) and a reaction time ``lateness`` has passed does the usual avoidance take
over, the driver backing off first. This is the user a shared-control layer exists for:
with it, drives end in contacts with the furniture (``Chair(blocked=Room.contact)``
counts them). An attentive driver
draws exactly the random numbers it always did, so existing drives are unchanged.

Every drive starts and (with a ``duration``) ends with the stick released for several
seconds and the chair still.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from asgp_ros.sim.chair import ChairState
from asgp_ros.sim.world import FOOTPRINT_RADIUS, Room

_MODES = ("cruise", "arc", "spin", "stop", "reverse")
_MODE_P = np.array([0.36, 0.25, 0.12, 0.15, 0.12])


@dataclass(frozen=True)
class DriverParams:
    """Tunables of the simulated user.

    Attributes:
        start_rest: range of the motionless lead-in (s).
        end_rest: range of the motionless tail, stick released (s).
        margin: extra clearance (m) the driver keeps beyond the furniture band and the
            footprint; the centre stays >= furniture_band + footprint radius + margin
            from the walls.
        caution: distance (m) beyond that limit where the driver starts steering away.
        reaction: look-ahead time (s) of the driver.
        tremor: standard deviation of the hand's slow tremor (deflection units).
        inattention: probability that a bout is an inattentive one (0 = never).
        notice: how close (m, footprint to furniture) an inattentive driver lets the chair
            come before noticing.
        lateness: range of the reaction time (s) after noticing.
    """

    start_rest: tuple[float, float] = (3.0, 6.0)
    end_rest: tuple[float, float] = (3.0, 6.0)
    margin: float = 0.1
    caution: float = 0.6
    reaction: float = 0.5
    tremor: float = 0.025
    inattention: float = 0.0
    notice: float = 0.05
    lateness: tuple[float, float] = (0.3, 0.9)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.inattention) and 0.0 <= self.inattention <= 1.0):
            raise ValueError(f"inattention must be in [0, 1], got {self.inattention}")
        lo, hi = self.lateness
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi <= 10.0):
            raise ValueError(f"lateness must be 0 <= lo <= hi <= 10 s, got {self.lateness}")


class Driver:
    """The user's hand on the joystick.

    Args:
        seed: seed of the driver's random choices.
        room: the room to stay in.
        duration: length of the drive (s); the driver stops and releases the stick for
            the last few seconds. ``None`` for an open-ended live drive.
        params: tunables.

    ``command(t, state) -> [2]`` (forward, turn) deflection in the unit disc; call it with
    non-decreasing ``t`` (s, any clock: the drive starts at the first call, ``duration``
    counts from there) at any rate (10-100 Hz).
    """

    def __init__(
        self,
        seed: int,
        room: Room | None = None,
        duration: float | None = None,
        params: DriverParams | None = None,
    ) -> None:
        self.room = room if room is not None else Room()
        self.params = params if params is not None else DriverParams()
        self._rng = np.random.default_rng(seed)
        if duration is not None and not (math.isfinite(duration) and duration > 0.0):
            raise ValueError(f"duration must be > 0 s, got {duration}")
        self.duration = duration
        p = self.params
        self._t_start = float(self._rng.uniform(*p.start_rest))
        self._t_end_rest = float(self._rng.uniform(*p.end_rest))
        self._hard = self.room.furniture_band + FOOTPRINT_RADIUS + p.margin
        self._t_last: float | None = None
        self._t0 = 0.0
        self._pos = np.zeros(2)  # hand position (forward, turn)
        self._vel = np.zeros(2)
        self._tremor = np.zeros(2)
        self._mode = "rest"
        self._mode_end = self._t_start
        self._target = np.zeros(2)
        self._wn = 8.0
        self._zeta = 0.9
        self._avoiding = False
        self._goal = np.zeros(2)
        self._noticed: float | None = None  # when an inattentive driver noticed (drive s)
        self._react = 0.0
        self._back_from = 0.0
        self._stuck_s = 0.0
        self._wall_goal = np.zeros(2)
        self.inattentive_bouts = 0

    # ---------------------------------------------------------------- behaviour
    @property
    def mode(self) -> str:
        return "avoid" if self._avoiding else self._mode

    def _new_bout(self, t: float) -> None:
        rng = self._rng
        p = self.params
        if p.inattention > 0.0 and rng.random() < p.inattention:
            self._inattentive_bout(t)
            return
        mode = str(rng.choice(_MODES, p=_MODE_P))
        f = t_ = 0.0
        if mode == "cruise":
            f, t_, dur = rng.uniform(0.35, 1.0), rng.normal(0.0, 0.05), rng.uniform(2.0, 7.0)
        elif mode == "arc":
            f = rng.uniform(0.25, 0.85)
            t_ = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.0)
            dur = rng.uniform(1.0, 4.0)
        elif mode == "spin":
            f = rng.uniform(-0.05, 0.15)
            t_ = rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 1.0)
            dur = rng.uniform(0.8, 3.0)
        elif mode == "stop":
            dur = rng.uniform(0.5, 3.0)
        else:  # reverse
            f, t_, dur = -rng.uniform(0.3, 0.9), rng.normal(0.0, 0.2), rng.uniform(1.0, 3.0)
        self._mode = mode
        self._mode_end = t + float(dur)
        self._target = np.array([f, t_], dtype=float)
        # A new reach: its own speed and damping (0.7 = slight overshoot).
        self._wn = float(rng.uniform(6.0, 14.0))
        self._zeta = float(rng.uniform(0.7, 1.1))

    def _inattentive_bout(self, t: float) -> None:
        """Head for a point on the furniture front, at a cruising speed, not looking."""
        rng = self._rng
        x_lo, x_hi, y_lo, y_hi = self.room.free_box
        side = int(rng.integers(4))
        u = float(rng.uniform(0.15, 0.85))
        self._wall_goal = np.array([
            (x_lo, x_hi, x_lo + u * (x_hi - x_lo), x_lo + u * (x_hi - x_lo))[side],
            (y_lo + u * (y_hi - y_lo), y_lo + u * (y_hi - y_lo), y_lo, y_hi)[side],
        ])
        self._avoiding = False
        self._mode = "inattentive"
        self._mode_end = t + float(rng.uniform(6.0, 12.0))
        self._target = np.array([float(rng.uniform(0.5, 0.9)), 0.0])
        self._wn = float(rng.uniform(6.0, 14.0))
        self._zeta = float(rng.uniform(0.7, 1.1))
        self._noticed = None
        self._react = float(rng.uniform(*self.params.lateness))
        self.inattentive_bouts += 1

    def _inattentive(self, t: float, state: ChairState) -> np.ndarray | None:
        """The stick of an inattentive bout, or None once the driver has reacted."""
        clear = self.room.footprint_clearance(state.x, state.y, state.theta) \
            - self.room.furniture_band
        if self._noticed is None and clear < self.params.notice:
            self._noticed = t
        if self._noticed is not None and t - self._noticed >= self._react:
            return None
        if t >= self._mode_end:  # the bout is over before anything happened
            return None
        gx, gy = self._wall_goal[0] - state.x, self._wall_goal[1] - state.y
        err = math.atan2(math.sin(math.atan2(gy, gx) - state.theta),
                         math.cos(math.atan2(gy, gx) - state.theta))
        turn = max(-1.0, min(1.0, 1.2 * err))
        fwd = float(self._target[0]) * (1.0 if abs(err) < 0.6 else 0.3)
        return np.array([fwd, turn])

    def _back_off(self, state: ChairState) -> np.ndarray:
        """Get away from the furniture by the end of the chair that faces the room: reverse,
        turning the back towards the room, or, when the front already faces it (reversing
        would push into the furniture behind), ease forward, turning the front towards it.
        "The room" is away from the nearest wall, and from both walls in a corner."""
        r = self.room
        gaps = np.array([state.x - r.x_min, r.x_max - state.x,
                         state.y - r.y_min, r.y_max - state.y])
        normals = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
        ix, iy = normals[gaps <= gaps.min() + 0.3].sum(axis=0)
        inward = math.atan2(iy, ix)
        front = math.atan2(math.sin(inward - state.theta), math.cos(inward - state.theta))
        if abs(front) < 0.5 * math.pi:
            return np.array([0.4, max(-0.6, min(0.6, 1.5 * front))])
        err = inward - (state.theta + math.pi)  # the back should point inward
        err = math.atan2(math.sin(err), math.cos(err))
        return np.array([-0.5, max(-0.6, min(0.6, 1.5 * err))])

    def _clearance_ahead(self, state: ChairState, direction: float, dist: float) -> float:
        """Wall distance of the chair centre ``dist`` m ahead (direction +1) or behind."""
        c, s = math.cos(state.theta), math.sin(state.theta)
        return self.room.wall_distance(
            state.x + direction * dist * c, state.y + direction * dist * s
        )

    def _pick_goal(self) -> None:
        r = self.room
        m = self._hard + 0.8
        self._goal = np.array([
            self._rng.uniform(r.x_min + m, r.x_max - m),
            self._rng.uniform(r.y_min + m, r.y_max - m),
        ])

    def _safety(self, t: float, state: ChairState, target: np.ndarray) -> np.ndarray:
        """Override the bout's target when the chair heads for the furniture."""
        p = self.params
        v = state.v
        hard = self._hard
        soft = hard + p.caution
        here = self.room.wall_distance(state.x, state.y)
        # Forward look-ahead: reaction distance + braking (about 1.2 m/s^2) + body.
        fwd_speed = max(v, 0.3 * max(target[0], 0.0))
        look = p.reaction * fwd_speed + fwd_speed**2 / 2.4 + 0.1
        ahead = self._clearance_ahead(state, 1.0, look)
        if target[0] < 0.0:
            back_speed = max(-v, 0.3)
            back = self._clearance_ahead(state, -1.0, p.reaction * back_speed + 0.5)
            if back < hard + 0.3 or here < hard + 0.2:
                self._mode_end = t  # abandon the reversal
                target = np.array([0.0, target[1]])
        if not self._avoiding and (ahead < soft or here < hard + 0.3) and target[0] >= 0.0:
            self._avoiding = True
            self._pick_goal()
        if self._avoiding:
            gx, gy = self._goal[0] - state.x, self._goal[1] - state.y
            err = math.atan2(gy, gx) - state.theta
            err = math.atan2(math.sin(err), math.cos(err))
            turn = max(-1.0, min(1.0, 1.6 * err))
            if abs(turn) < 0.35 and abs(err) > 0.15:
                turn = math.copysign(0.35, err)
            aligned = abs(err) < 0.35
            room_ahead = (ahead - hard) / max(p.caution, 1e-6)
            if aligned and ahead > soft:
                self._avoiding = False
                self._mode_end = t  # new bout
                return np.array([0.4, 0.0])
            leaving = aligned and ahead > here + 0.05  # facing away from the furniture
            if not leaving and (ahead < hard + 0.15 or here < hard + 0.1):
                fwd = 0.0  # stop and turn on the spot
            else:
                fwd = min(0.6, max(0.1 if leaving else 0.0, room_ahead)) \
                    * (1.0 if aligned else 0.5)
            return np.array([fwd, turn])
        return target

    # ---------------------------------------------------------------- the hand
    def command(self, t: float, state: ChairState) -> np.ndarray:
        """The joystick deflection [forward, turn] at time ``t`` (s) given the chair state."""
        if not math.isfinite(t):
            raise ValueError("t must be finite")
        dt = 0.0 if self._t_last is None else t - self._t_last
        if dt < 0.0:
            raise ValueError(f"time went backwards: {t} < {self._t_last}")
        if self._t_last is None:
            self._t0 = t
        self._t_last = t
        t = t - self._t0  # the drive's own clock: 0 at the first call
        ending = self.duration is not None and t >= self.duration - self._t_end_rest - 2.5
        if t < self._t_start or ending:
            self._mode = "rest"
            self._avoiding = False
            target = np.zeros(2)
        else:
            if self._mode == "rest" or (t >= self._mode_end and not self._avoiding):
                self._new_bout(t)
            stick = None
            if self.params.inattention > 0.0 and self._mode != "back_off":
                # pinned against the furniture (a bump the attentive rules never meet):
                # asking to move, or steering away from the furniture, and not moving for a
                # second -> back off. (The avoidance alone can stand still for good after an
                # inattentive bout: a creep of 0.1 inside the chair's dead zone, or lined up
                # with its goal along a wall, where going ahead gains no clearance.)
                asking = self._avoiding or float(np.max(np.abs(self._pos))) > 0.3
                moving = abs(state.v) > 0.02 or abs(state.omega) > 0.02
                self._stuck_s = self._stuck_s + dt if asking and not moving else 0.0
                if self._stuck_s > 1.0:
                    self._stuck_s = 0.0
                    self._avoiding = False
                    self._mode, self._mode_end, self._back_from = "back_off", t + 3.0, t
            if self._mode == "inattentive":
                stick = self._inattentive(t, state)
                if stick is None:  # reacted: back off the way it came, then drive on
                    self._mode, self._mode_end = "back_off", t + 8.0
                    self._back_from = t
            if self._mode == "back_off":
                stick = self._back_off(state)
                clear = self.room.wall_distance(state.x, state.y) >= self._hard + 0.3
                if t >= self._mode_end or (clear and t - self._back_from >= 1.0):
                    self._new_bout(t)
                    stick = None
            target = stick if stick is not None else \
                self._safety(t, state, self._target.copy())
        released = not target.any()
        # Speed changes within a cruise: now and then the user picks another speed.
        if self._mode == "cruise" and not self._avoiding and self._rng.random() < 0.15 * dt:
            self._target[0] = float(self._rng.uniform(0.35, 1.0))
        self._integrate(dt, target, released)
        return self._pos.copy()

    def _integrate(self, dt: float, target: np.ndarray, released: bool) -> None:
        if dt <= 0.0:
            return
        if released and np.max(np.abs(self._pos)) < 0.02:
            # The stick springs back to the centre when released.
            self._pos[:] = 0.0
            self._vel[:] = 0.0
            self._tremor[:] = 0.0
            return
        # Slow tremor: Ornstein-Uhlenbeck with a 0.5 s time constant (exact update).
        a = math.exp(-dt / 0.5)
        sd = self.params.tremor * math.sqrt(1.0 - a * a)
        self._tremor = a * self._tremor + sd * self._rng.standard_normal(2)
        goal = target + (0.0 if released else 1.0) * self._tremor
        wn, zeta = (14.0, 1.0) if released else (self._wn, self._zeta)
        # Second-order reach, semi-implicit Euler in sub-steps of <= 5 ms (scalar floats:
        # this runs 200 times a second in the offline simulation).
        n = max(1, math.ceil(dt / 0.005))
        h = dt / n
        k2, k1 = wn * wn, 2.0 * zeta * wn
        g0, g1 = float(goal[0]), float(goal[1])
        p0, p1 = float(self._pos[0]), float(self._pos[1])
        v0, v1 = float(self._vel[0]), float(self._vel[1])
        for _ in range(n):
            v0 += h * (k2 * (g0 - p0) - k1 * v0)
            v1 += h * (k2 * (g1 - p1) - k1 * v1)
            p0 += h * v0
            p1 += h * v1
        self._pos = np.array([p0, p1])
        self._vel = np.array([v0, v1])
        r = math.hypot(self._pos[0], self._pos[1])
        if r > 1.0:  # the circular gate of the joystick
            self._pos /= r
            self._vel[:] = 0.0
