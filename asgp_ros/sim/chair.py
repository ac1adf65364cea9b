"""A commercial powered wheelchair (PWC) as its user experiences it: a black box from joystick
deflection to motion.

The model is that of a mid-wheel-drive chair (Permobil M-series class) with a programmable
controller, two speed-controlled hub motors and free-swivelling casters:

1. **Controller profile** (what the dealer programs): dead zone, expo speed/turn curves,
   reduced forward speed while turning, reduced turn rate at speed, separate acceleration
   and deceleration ramps for speed and turn, a short pause when the commanded direction
   of travel reverses.
2. **Drive**: the ramped body set-point becomes left/right wheel set-points (scaled down
   together when a wheel would exceed its top speed: motor saturation); each wheel's speed
   loop (proportional, with load compensation tuned on a hard floor) asks for a torque that
   is clamped (current limit) and delivered through a first-order motor lag; the body then
   obeys ``dv/dt = mean wheel force - rolling resistance``, ``domega/dt = differential
   force * rho - turning resistance``. Speed loop + motor lag make the response second
   order; rolling / scrub resistance not cancelled by the load compensation gives a
   surface-dependent speed droop.
3. **Casters**: one effective trailing caster ahead of the axle. It swivels according to the
   no-slip kinematics of a trailing wheel, slowed by swivel friction; the slip that remains
   while it swings scrubs sideways and produces a transient yaw torque and drag. When the
   direction of travel reverses the caster has to flip by pi, which gives the familiar
   lurch to one side (which side depends on the caster's history) and a delay.
4. **Brake**: the electromagnetic parking brake engages when the set-point has been zero
   and the chair nearly still for 0.15 s, so a chair at rest is exactly at rest.
5. **Surface noise**: small random accelerations from floor unevenness, stronger on carpet.

Carpet has more rolling resistance, much more turning scrub and caster drag and a
stickier caster swivel: slower, more droop, especially in rotation, more caster lurch and
more noise, so it is both slower and harder to predict than tile. The response is
nonlinear (dead zone, expo, saturations, Coulomb friction) and history dependent (ramps,
lags, caster angle, reversal pause), which is what the ASGP has to learn.

Units: SI (m, s, rad); "per mass" accelerations (m/s^2, rad/s^2) instead of forces so that
the parameters can be read off a chair's specification and a step response.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from asgp_ros.sim.world import SURFACES, Room

INTERNAL_RATE_HZ = 100.0
"""The chair integrates its dynamics at this fixed rate (explicit Euler, 10 ms steps)."""

_EPS_V = 0.03  # m/s: smoothing of Coulomb friction sign (tanh(v / eps))
_EPS_SLIP = 0.05  # m/s: smoothing of caster scrub sign


@dataclass(frozen=True)
class ChairParams:
    """Parameters of the chair model. Ranges are plausible for a Permobil-class chair.

    Controller profile (chair-intrinsic, does not change with the floor):

    Attributes:
        v_max: forward top speed at full deflection (m/s), 1.5-3.0.
        v_max_reverse: reverse top speed (m/s), 0.4-1.0.
        omega_max: turn rate at full turn deflection while still (rad/s), 1.0-2.0.
        dead_zone: joystick dead zone, fraction of full deflection, 0.05-0.15.
        speed_expo: exponent of the speed curve (1 = linear), 1.0-2.5.
        turn_expo: exponent of the turn curve, 1.0-2.5.
        turn_slowdown: forward speed reduction at full turn deflection (fraction), 0.3-0.7.
        turn_at_speed: turn rate available at top speed (fraction of omega_max), 0.3-0.8.
        accel: forward/reverse speed-up ramp (m/s^2), 0.5-1.5.
        decel: slow-down ramp (m/s^2), 1.0-2.5.
        ang_accel: turn-rate build-up ramp (rad/s^2), 1.5-4.0.
        ang_decel: turn-rate release ramp (rad/s^2), 2.0-6.0.
        reversal_pause: set-point held at zero when the direction of travel reverses (s),
            0.0-0.5.

    Drive (chair-intrinsic):

    Attributes:
        track_width: distance between the drive wheels (m), 0.5-0.6.
        wheel_speed_max: top rim speed of a drive wheel (m/s), >= v_max; 1.05-1.3 v_max.
        tau_speed: time constant of the wheel speed loop (s), 0.1-0.4.
        tau_motor: torque (current) lag of the motors (s), 0.03-0.15.
        yaw_ratio: tau_speed / yaw time constant (m^2 ratio of mass to yaw inertia about
            the axle, m b^2 / 4 I), 0.4-1.0; below 1 rotation responds slower than speed.
        accel_sat: torque (current) limit per wheel as an acceleration (m/s^2), 1.5-4.0.
        load_comp: fraction of the nominal resistances (comp_*) the controller's IR
            compensation feeds forward, 0-1.
        comp_rolling: nominal rolling resistance the controller was tuned for (m/s^2).
        comp_turn: nominal turning resistance the controller was tuned for (rad/s^2).
        caster_offset: caster pivot ahead of the drive axle (m), 0.3-0.5.
        caster_trail: caster trail (m), 0.03-0.08.
        caster_yaw_gain: yaw acceleration per lateral caster force per mass, m x_c / I
            (1/m), 2-5.

    Surface (depends on the floor under the chair):

    Attributes:
        rolling_resistance: Coulomb rolling resistance (m/s^2): tile 0.1-0.2, carpet
            0.3-0.6.
        viscous_drag: speed-proportional drag (1/s): tile ~0.05, carpet ~0.2.
        turn_resistance: Coulomb scrub of the tyres when rotating (rad/s^2): tile 0.2-0.5,
            carpet 0.8-1.5.
        turn_damping: rate-proportional scrub (1/s): tile ~0.1, carpet ~0.5.
        caster_swivel: fraction of the kinematic swivel rate the caster achieves against
            its swivel friction, tile 0.8-0.95, carpet 0.4-0.7.
        caster_scrub: sideways scrub of a misaligned caster (m/s^2): tile ~0.5, carpet
            ~1.5.
        accel_noise_v: random acceleration from floor unevenness (m/s per sqrt(s)).
        accel_noise_w: random angular acceleration (rad/s per sqrt(s)).
        caster_noise: random caster swivel from floor unevenness while rolling
            (rad per sqrt(s) at 0.2 m/s and above); it decides which way a caster flips.
        surface: the name of the floor these values describe.
    """

    v_max: float = 1.8
    v_max_reverse: float = 0.65
    omega_max: float = 1.4
    dead_zone: float = 0.08
    speed_expo: float = 1.6
    turn_expo: float = 1.4
    turn_slowdown: float = 0.5
    turn_at_speed: float = 0.5
    accel: float = 0.9
    decel: float = 1.6
    ang_accel: float = 2.5
    ang_decel: float = 4.0
    reversal_pause: float = 0.25
    track_width: float = 0.56
    wheel_speed_max: float = 2.1
    tau_speed: float = 0.22
    tau_motor: float = 0.08
    yaw_ratio: float = 0.6
    accel_sat: float = 2.5
    load_comp: float = 0.7
    comp_rolling: float = 0.15
    comp_turn: float = 0.3
    caster_offset: float = 0.4
    caster_trail: float = 0.05
    caster_yaw_gain: float = 3.0
    rolling_resistance: float = 0.15
    viscous_drag: float = 0.05
    turn_resistance: float = 0.3
    turn_damping: float = 0.1
    caster_swivel: float = 0.9
    caster_scrub: float = 0.5
    accel_noise_v: float = 0.03
    accel_noise_w: float = 0.05
    caster_noise: float = 0.1
    surface: str = "tile"

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if name == "surface":
                continue
            if not math.isfinite(value) or value < 0.0:
                raise ValueError(f"ChairParams.{name} must be finite and >= 0, got {value}")
        positive = ("v_max", "v_max_reverse", "omega_max", "accel", "decel", "ang_accel",
                    "ang_decel", "track_width", "wheel_speed_max", "tau_speed", "tau_motor",
                    "yaw_ratio", "accel_sat", "caster_trail")
        for name in positive:
            if getattr(self, name) <= 0.0:
                raise ValueError(f"ChairParams.{name} must be > 0")
        if not self.dead_zone < 0.5:
            raise ValueError("ChairParams.dead_zone must be < 0.5")
        for name in ("turn_slowdown", "turn_at_speed", "load_comp", "caster_swivel"):
            if getattr(self, name) > 1.0:
                raise ValueError(f"ChairParams.{name} must be in [0, 1]")
        if self.wheel_speed_max < self.v_max:
            raise ValueError("ChairParams.wheel_speed_max must be >= v_max")
        if self.tau_motor < 2.0 / INTERNAL_RATE_HZ or self.tau_speed < 2.0 / INTERNAL_RATE_HZ:
            raise ValueError("tau_motor and tau_speed must be >= 2 internal steps (20 ms)")
        if self.surface not in SURFACES:
            raise ValueError(f"unknown surface {self.surface!r}; expected one of {SURFACES}")

    @classmethod
    def preset(cls, surface: str, **overrides: Any) -> ChairParams:
        """The default chair on ``"tile"`` or ``"carpet"`` (keyword overrides allowed)."""
        if surface == "tile":
            base = cls()
        elif surface == "carpet":
            base = cls(
                rolling_resistance=0.45,
                viscous_drag=0.2,
                turn_resistance=0.5,
                turn_damping=0.35,
                caster_swivel=0.65,
                caster_scrub=0.9,
                caster_noise=0.15,
                accel_noise_v=0.07,
                accel_noise_w=0.1,
                surface="carpet",
            )
        else:
            raise ValueError(
                f"no chair preset for surface {surface!r}; expected one of {SURFACES} "
                "(a 'hybrid' floor is a Room with patches of both)"
            )
        return replace(base, **overrides) if overrides else base


@dataclass(frozen=True)
class ChairState:
    """The chair's true state after a step.

    Attributes:
        t: simulation time (s).
        x, y, theta: pose of the drive-axle centre in the world frame (m, m, rad, theta
            wrapped to (-pi, pi]).
        v, omega: body twist (m/s forward, rad/s CCW).
        wheel_left, wheel_right: rim speeds of the drive wheels (m/s).
        caster: caster swivel angle relative to the chair's x axis (rad).
        surface: floor under the chair.
        braked: the parking brake is engaged.
    """

    t: float
    x: float
    y: float
    theta: float
    v: float
    omega: float
    wheel_left: float
    wheel_right: float
    caster: float
    surface: str
    braked: bool

    @property
    def pose(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.theta)


CONTACT_GAP_S = 1.0
"""Blocked steps less than this apart are one contact (s)."""


def _profile(u: float, dead_zone: float, expo: float) -> float:
    """Dead zone + expo curve: [-1, 1] deflection -> [-1, 1] demand."""
    a = abs(u)
    if a <= dead_zone:
        return 0.0
    s: float = min(1.0, (a - dead_zone) / (1.0 - dead_zone)) ** expo
    return s if u > 0.0 else -s


def _ramp(current: float, target: float, up: float, down: float, dt: float) -> float:
    """Move ``current`` towards ``target``; ``up`` when |.| grows in the same direction."""
    growing = current * target >= 0.0 and abs(target) > abs(current)
    step = (up if growing else down) * dt
    if target > current:
        return min(target, current + step)
    return max(target, current - step)


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


@dataclass
class _Internal:
    v_set: float = 0.0  # ramped set-points
    w_set: float = 0.0
    pause: float = 0.0  # remaining reversal pause (s)
    last_dir: float = 0.0  # direction of travel of the last non-zero speed set-point
    a_left: float = 0.0  # delivered motor accelerations
    a_right: float = 0.0
    still: float = 0.0  # time with zero set-point and near-zero motion (s)
    noise: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    noise_i: int = 0


class Chair:
    """The simulated chair, advanced step by step (live) or in a fast loop (offline).

    Args:
        params: one ``ChairParams`` for a uniform floor, or a mapping surface name ->
            ``ChairParams`` (e.g. ``{"tile": ..., "carpet": ...}``) used with ``surface_at``.
        seed: seed of the chair's own random numbers (floor noise, caster start angle).
        surface_at: ``(x, y) -> surface name`` (e.g. ``Room.surface_at``); required when
            ``params`` is a mapping, ignored otherwise.
        blocked: ``(x, y, theta) -> overlap``, how far (m) the chair at that pose would
            reach into an obstacle, 0 where it is free (e.g. ``Room.overlap``); None:
            nothing stops the chair. No internal step moves the chair deeper into an
            obstacle: a step that would is undone in translation (the chair stops against
            the obstacle, with no forward speed, as a bump into furniture does; it may still
            turn, scraping along, so a corner can swing a little into it); :attr:`contacts`
            counts the contacts (a step in overlap after at
            least ``CONTACT_GAP_S`` without one; pushing on against the furniture is the
            same contact).
    """

    def __init__(
        self,
        params: ChairParams | Mapping[str, ChairParams],
        seed: int = 0,
        surface_at: Callable[[float, float], str] | None = None,
        blocked: Callable[[float, float, float], float] | None = None,
    ) -> None:
        self._blocked = blocked
        self.contacts = 0
        self._free_s = math.inf  # time since the last blocked step
        if isinstance(params, ChairParams):
            self._by_surface = {params.surface: params}
            self._surface_at: Callable[[float, float], str] | None = None
            self._default = params
        else:
            if not params:
                raise ValueError("Chair needs at least one ChairParams")
            if surface_at is None:
                raise ValueError("Chair with per-surface params needs surface_at(x, y)")
            self._by_surface = dict(params)
            self._surface_at = surface_at
            self._default = next(iter(self._by_surface.values()))
        self._rng = np.random.default_rng(seed)
        self._dt = 1.0 / INTERNAL_RATE_HZ
        self._carry = 0.0
        self.reset()

    @classmethod
    def for_room(cls, room: Room, seed: int = 0,
                 params: Mapping[str, ChairParams] | None = None,
                 blocked: Callable[[float, float, float], float] | None = None) -> Chair:
        """The preset chair on the room's floor (per-surface ``params`` override presets).

        A room with patches (the hybrid atrium) gets a chair that looks up the floor under
        it at every internal step.
        """
        presets = {s: ChairParams.preset(s) for s in SURFACES}
        if params:
            presets.update(params)
        if room.patches:
            return cls(presets, seed=seed, surface_at=room.surface_at, blocked=blocked)
        return cls(presets[room.base_surface], seed=seed, blocked=blocked)

    # ------------------------------------------------------------------ state
    def reset(self, pose: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> ChairState:
        """Put the chair at rest (brake on) at ``pose`` = (x, y, theta)."""
        x, y, theta = (float(p) for p in pose)
        if not all(math.isfinite(p) for p in (x, y, theta)):
            raise ValueError(f"pose must be finite, got {pose}")
        self._t = 0.0
        self._x, self._y, self._theta = x, y, _wrap(theta)
        self._v = self._w = 0.0
        # Casters are left roughly trailing the last forward drive, a little askew.
        self._psi = float(self._rng.normal(0.0, 0.15))
        self._in = _Internal(still=1.0)
        self._carry = 0.0
        self._state = self._make_state()
        return self._state

    @property
    def state(self) -> ChairState:
        return self._state

    def params_at(self, x: float, y: float) -> ChairParams:
        """The parameters in force at (x, y)."""
        if self._surface_at is None:
            return self._default
        name = self._surface_at(x, y)
        try:
            return self._by_surface[name]
        except KeyError:
            raise ValueError(
                f"no ChairParams for surface {name!r} at ({x:.2f}, {y:.2f}); have "
                f"{sorted(self._by_surface)}"
            ) from None

    def _make_state(self) -> ChairState:
        half = 0.5 * self._default.track_width
        p = self.params_at(self._x, self._y)
        return ChairState(
            t=self._t, x=self._x, y=self._y, theta=self._theta, v=self._v, omega=self._w,
            wheel_left=self._v - self._w * half, wheel_right=self._v + self._w * half,
            caster=self._psi, surface=p.surface, braked=self._in.still >= 0.15,
        )

    def _noise(self) -> tuple[float, float, float]:
        n = self._in
        if n.noise_i >= n.noise.shape[0]:
            n.noise = self._rng.standard_normal((4096, 3))
            n.noise_i = 0
        a, b, c = n.noise[n.noise_i]
        n.noise_i += 1
        return float(a), float(b), float(c)

    # ------------------------------------------------------------------ dynamics
    def step(self, joy: Sequence[float] | np.ndarray, dt: float) -> ChairState:
        """Advance by ``dt`` seconds with the joystick held at ``joy`` = [forward, turn].

        ``joy`` is clipped to [-1, 1] per axis (the chair's input port does the same).
        Returns the state at the end of the step.
        """
        try:
            f, t = joy
            f, t = float(f), float(t)
        except (TypeError, ValueError):
            raise ValueError(
                f"joy must be 2 finite numbers [forward, turn], got {joy!r}") from None
        if not (math.isfinite(f) and math.isfinite(t)):
            raise ValueError(f"joy must be 2 finite numbers [forward, turn], got {joy!r}")
        if not (math.isfinite(dt) and dt >= 0.0):
            raise ValueError(f"dt must be finite and >= 0, got {dt}")
        u_f = min(1.0, max(-1.0, f))
        u_t = min(1.0, max(-1.0, t))
        total = self._carry + dt
        n = int(total / self._dt + 1e-9)
        self._carry = total - n * self._dt
        for _ in range(n):
            if self._blocked is None:
                self._substep(u_f, u_t)
            else:
                self._guarded_substep(u_f, u_t)
        if n:
            self._state = self._make_state()
        return self._state

    def _guarded_substep(self, u_f: float, u_t: float) -> None:
        """One internal step that never deepens an overlap (see ``blocked``)."""
        assert self._blocked is not None
        x0, y0, th0 = self._x, self._y, self._theta
        depth0 = self._blocked(x0, y0, th0)
        self._substep(u_f, u_t)
        depth = self._blocked(self._x, self._y, self._theta)
        bumped = depth > depth0 + 1e-9
        if bumped:  # into the obstacle: stop against it
            self._x, self._y = x0, y0
            self._v = 0.0
            s = self._in
            s.v_set = s.a_left = s.a_right = 0.0
            depth = self._blocked(x0, y0, self._theta)  # it may still turn, scraping
        if not bumped and depth <= 0.0:
            self._free_s += self._dt
            return
        if self._free_s >= CONTACT_GAP_S:
            self.contacts += 1
        self._free_s = 0.0

    def _substep(self, u_f: float, u_t: float) -> None:
        dt = self._dt
        p = self.params_at(self._x, self._y)
        s = self._in
        v, w, psi = self._v, self._w, self._psi

        # 1. Controller profile: dead zone, expo, turn/speed interaction.
        sf = _profile(u_f, p.dead_zone, p.speed_expo)
        st = _profile(u_t, p.dead_zone, p.turn_expo)
        v_cmd = sf * (p.v_max if sf >= 0.0 else p.v_max_reverse)
        v_cmd *= 1.0 - p.turn_slowdown * abs(st)
        speed_frac = min(1.0, abs(s.v_set) / p.v_max)
        w_cmd = st * p.omega_max * (1.0 - (1.0 - p.turn_at_speed) * speed_frac)

        # 2. Reversal pause: the set-point rests at zero before the direction flips.
        direction = 1.0 if v_cmd > 0.0 else (-1.0 if v_cmd < 0.0 else 0.0)
        if s.pause > 0.0:
            s.pause -= dt
            v_target = 0.0
        elif direction != 0.0 and s.last_dir != 0.0 and direction != s.last_dir:
            # decelerate to zero first, then pause
            v_target = 0.0
            if s.v_set == 0.0:
                s.pause = p.reversal_pause
                s.last_dir = direction
        else:
            v_target = v_cmd
            if direction != 0.0 and s.v_set * direction >= 0.0:
                s.last_dir = direction
        s.v_set = _ramp(s.v_set, v_target, p.accel, p.decel, dt)
        s.w_set = _ramp(s.w_set, w_cmd, p.ang_accel, p.ang_decel, dt)

        # 3. Wheel set-points, scaled together at the motors' top speed (saturation).
        half = 0.5 * p.track_width
        ul = s.v_set - s.w_set * half
        ur = s.v_set + s.w_set * half
        top = max(abs(ul), abs(ur))
        if top > p.wheel_speed_max:
            k = p.wheel_speed_max / top
            ul *= k
            ur *= k

        # 4. Speed loops with load compensation (tuned on a hard floor), current limit,
        #    motor lag.
        kp = 1.0 / p.tau_speed
        ff_v = p.load_comp * p.comp_rolling * math.tanh(s.v_set / _EPS_V)
        ff_w = p.load_comp * p.comp_turn * math.tanh(s.w_set / _EPS_V) * half / p.yaw_ratio
        wl = v - w * half
        wr = v + w * half
        al = kp * (ul - wl) + ff_v - ff_w
        ar = kp * (ur - wr) + ff_v + ff_w
        al = min(p.accel_sat, max(-p.accel_sat, al))
        ar = min(p.accel_sat, max(-p.accel_sat, ar))
        s.a_left += (al - s.a_left) * dt / p.tau_motor
        s.a_right += (ar - s.a_right) * dt / p.tau_motor

        # 5. Effective trailing caster: no-slip swivel kinematics slowed by swivel
        #    friction; the remaining sideways slip scrubs (force along the caster axle).
        xc, d = p.caster_offset, p.caster_trail
        cpsi, spsi = math.cos(psi), math.sin(psi)
        p_perp = -v * spsi + w * xc * cpsi  # pivot velocity normal to the caster wheel
        rate_kin = p_perp / d - w  # d(psi)/dt of a trailing wheel rolling without slip
        psi_dot = p.caster_swivel * rate_kin
        psi_dot = max(-25.0, min(25.0, psi_dot))
        slip = p_perp - (w + psi_dot) * d
        scrub = -p.caster_scrub * math.tanh(slip / _EPS_SLIP)
        fx = -scrub * spsi  # scrub force along the wheel normal (-sin, cos), body frame
        fy = scrub * cpsi

        # 6. Body dynamics (per mass).
        nv, nw, npsi = self._noise()
        sq = math.sqrt(dt)
        moving = abs(v) > 0.01 or abs(w) > 0.01
        dv = (0.5 * (s.a_left + s.a_right) - p.rolling_resistance * math.tanh(v / _EPS_V)
              - p.viscous_drag * v + fx)
        dw = (p.yaw_ratio * (s.a_right - s.a_left) / p.track_width
              - p.turn_resistance * math.tanh(w / _EPS_V) - p.turn_damping * w
              + p.caster_yaw_gain * fy)
        v_new = v + dv * dt + (p.accel_noise_v * sq * nv if moving else 0.0)
        w_new = w + dw * dt + (p.accel_noise_w * sq * nw if moving else 0.0)
        roll = min(1.0, math.hypot(v, w * xc) / 0.2)
        psi = _wrap(psi + psi_dot * dt + p.caster_noise * sq * roll * npsi)

        # 7. Parking brake.
        if s.v_set == 0.0 and s.w_set == 0.0 and abs(v_new) < 0.03 and abs(w_new) < 0.05:
            s.still += dt
        else:
            s.still = 0.0
        if s.still >= 0.15:
            v_new = w_new = 0.0
            s.a_left = s.a_right = 0.0
            s.last_dir = 0.0

        # 8. Pose: midpoint rule on the unicycle.
        th_mid = self._theta + 0.5 * (w + w_new) * 0.5 * dt
        vm = 0.5 * (v + v_new)
        self._x += vm * math.cos(th_mid) * dt
        self._y += vm * math.sin(th_mid) * dt
        self._theta = _wrap(self._theta + 0.5 * (w + w_new) * dt)
        self._v, self._w, self._psi = v_new, w_new, psi
        self._t += dt
