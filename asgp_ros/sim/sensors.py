"""Sensor models: the Arduino's joystick reading and Fovis-like visual odometry.

Joystick: the board samples the joystick's two potentiometers with its 10-bit ADC at about
30 Hz (timing jitter of the serial link), with a little electrical noise; a reading is
``(count - centre) / half_range`` in [-1, 1].

Visual odometry (Fovis on an RGB-D camera, as in the paper): a frame every 1/4-1/7 s
(jittery 4-7 Hz); each estimate is the body-frame displacement between consecutive frames
divided by their interval (so it averages the motion over the interval), plus noise that
grows with speed. Now and then (while moving) tracking is lost for 0.5-3 s; Fovis then
keeps reporting the last good velocity, which is what a recording contains. The episodes
are kept in the ground truth (``Recording.failures``) so that tests and evaluations can
find them. Failures are more frequent on carpet and in the hybrid atrium (feature-poor
views). The estimate's header stamp is the frame time; it reaches the bag after the
processing latency.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SensorParams:
    """Sensor model parameters.

    Attributes:
        joy_rate_hz: joystick sampling rate of the board (Hz), ~30.
        joy_jitter_s: standard deviation of the joystick stamp jitter (s).
        joy_latency_s: serial + driver latency from stamp to bag (s).
        adc_bits: ADC resolution (10 on an Arduino Mega).
        adc_noise_counts: electrical noise on each reading (ADC counts, std).
        centre_deadband_counts: readings within this many counts of the centre read 0 (the
            board's firmware centre band, so a released stick reads exactly 0).
        vo_rate_hz: (min, max) instantaneous VO frame rate (Hz); intervals uniform in rate.
        vo_latency_s: (min, max) processing latency of a VO estimate (s).
        vo_noise_v: (a, b): std of v = a + b |v| (m/s).
        vo_noise_w: (a, b, c): std of omega = a + b |omega| + c |v| (rad/s).
        vo_noise_scale: multiplier of the VO noise per recording surface.
        failure_rate_per_min: tracking failures per minute of motion, per surface.
        failure_duration_s: (min, max) duration of a failure (s).
    """

    joy_rate_hz: float = 30.0
    joy_jitter_s: float = 0.002
    joy_latency_s: float = 0.003
    adc_bits: int = 10
    adc_noise_counts: float = 0.35
    centre_deadband_counts: int = 1
    vo_rate_hz: tuple[float, float] = (4.0, 7.0)
    vo_latency_s: tuple[float, float] = (0.03, 0.09)
    vo_noise_v: tuple[float, float] = (0.008, 0.03)
    vo_noise_w: tuple[float, float, float] = (0.01, 0.04, 0.01)
    vo_noise_scale: dict[str, float] = field(
        default_factory=lambda: {"tile": 1.0, "carpet": 1.3, "hybrid": 1.5}
    )
    failure_rate_per_min: dict[str, float] = field(
        default_factory=lambda: {"tile": 0.4, "carpet": 1.5, "hybrid": 2.0}
    )
    failure_duration_s: tuple[float, float] = (0.5, 3.0)

    def __post_init__(self) -> None:
        if not (self.joy_rate_hz > 0 and self.adc_bits >= 4):
            raise ValueError("joy_rate_hz must be > 0 and adc_bits >= 4")
        lo, hi = self.vo_rate_hz
        if not 0 < lo <= hi:
            raise ValueError(f"vo_rate_hz must be 0 < min <= max, got {self.vo_rate_hz}")
        lo, hi = self.failure_duration_s
        if not 0 < lo <= hi:
            raise ValueError("failure_duration_s must be 0 < min <= max")

    def failure_rate(self, surface: str) -> float:
        try:
            return float(self.failure_rate_per_min[surface])
        except KeyError:
            raise ValueError(f"no VO failure rate for surface {surface!r}") from None


def quantise_joystick(
    u: FloatArray, rng: np.random.Generator, params: SensorParams | None = None
) -> FloatArray:
    """ADC reading of joystick deflections ``u`` [..., 2] -> [..., 2] in [-1, 1].

    The potentiometer voltage maps [-1, 1] onto [0, 2^bits - 1] counts; noise is added
    before rounding; the reading is ``(count - centre) / (centre - 0.5)`` with centre
    2^(bits-1) (512 for 10 bits), clipped to [-1, 1]; counts within
    ``centre_deadband_counts`` of the centre read exactly 0.
    """
    p = params if params is not None else SensorParams()
    u = np.asarray(u, dtype=float)
    centre = 2 ** (p.adc_bits - 1)
    half = centre - 0.5
    counts = np.rint(centre + np.clip(u, -1.0, 1.0) * half
                     + p.adc_noise_counts * rng.standard_normal(u.shape))
    counts = np.clip(counts, 0, 2**p.adc_bits - 1)
    counts[np.abs(counts - centre) <= p.centre_deadband_counts] = centre
    out: FloatArray = np.clip((counts - centre) / half, -1.0, 1.0)
    return out


def joystick_samples(
    t_end: float, cmd_t: FloatArray, cmd: FloatArray, rng: np.random.Generator,
    params: SensorParams | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The board's joystick stream over [0, t_end].

    Args:
        t_end: end of the recording (s).
        cmd_t: [N] times of the true stick positions; cmd: [N, 2] the positions.
        rng: random generator.

    Returns:
        (stamp [M], reading [M, 2], bag_time [M]).
    """
    p = params if params is not None else SensorParams()
    period = 1.0 / p.joy_rate_hz
    nominal = np.arange(0.0, t_end, period)
    stamp = nominal + p.joy_jitter_s * rng.standard_normal(nominal.shape[0])
    stamp = np.clip(stamp, 0.0, t_end)
    stamp = np.maximum.accumulate(stamp)
    keep = np.ones(stamp.shape[0], dtype=bool)
    keep[1:] = np.diff(stamp) > 1e-4
    stamp = stamp[keep]
    true = np.stack([np.interp(stamp, cmd_t, cmd[:, k]) for k in range(2)], axis=1)
    reading = quantise_joystick(true, rng, p)
    bag_time = stamp + p.joy_latency_s * (1.0 + 0.3 * rng.random(stamp.shape[0]))
    return stamp, reading, bag_time


@dataclass(frozen=True)
class VoStream:
    """Simulated VO output.

    Attributes:
        stamp: [K] frame times (s). bag_time: [K] arrival in the bag (s).
        vel: [K, 2] reported (v, omega). true_vel: [K, 2] the interval-average truth.
        stale: [K] True for reports repeated during a tracking failure.
        failures: [F, 2] (start, end) of each failure: time of the first stale report
            and of the first good report after it (or the recording's end).
    """

    stamp: FloatArray
    bag_time: FloatArray
    vel: FloatArray
    true_vel: FloatArray
    stale: NDArray[np.bool_]
    failures: FloatArray


def vo_samples(
    t_end: float, truth_t: FloatArray, pose: FloatArray, moving: NDArray[np.bool_],
    surface: str, rng: np.random.Generator, params: SensorParams | None = None,
) -> VoStream:
    """Fovis-like VO over [0, t_end] from the true trajectory.

    Args:
        t_end: end of the recording (s).
        truth_t: [N] times of the true poses (dense, e.g. 100 Hz); pose: [N, 3] (x, y, theta).
        moving: [N] True where the chair moves (failures accrue only then).
        surface: recording surface (noise scale and failure rate).
        rng: random generator.
    """
    p = params if params is not None else SensorParams()
    lo, hi = p.vo_rate_hz
    # Frame times: first frame a little after the start, intervals 1/U(lo, hi).
    n_guess = int(t_end * hi) + 16
    intervals = 1.0 / rng.uniform(lo, hi, n_guess)
    frames = rng.uniform(0.0, 1.0 / hi) + np.concatenate([[0.0], np.cumsum(intervals)])
    frames = frames[frames <= t_end]
    if frames.shape[0] < 2:
        raise ValueError(f"recording of {t_end:.2f} s is too short for VO")
    theta_u = np.unwrap(pose[:, 2])
    x = np.interp(frames, truth_t, pose[:, 0])
    y = np.interp(frames, truth_t, pose[:, 1])
    th = np.interp(frames, truth_t, theta_u)
    dt = np.diff(frames)
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    dx, dy = np.diff(x), np.diff(y)
    v_true = (c * dx + s * dy) / dt  # body-frame forward displacement per second
    w_true = np.diff(th) / dt
    # The first frame has no predecessor: Fovis reports zero motion.
    true_vel = np.stack([np.concatenate([[0.0], v_true]), np.concatenate([[0.0], w_true])], 1)
    k = frames.shape[0]
    scale = float(p.vo_noise_scale.get(surface, 1.0))
    sv = scale * (p.vo_noise_v[0] + p.vo_noise_v[1] * np.abs(true_vel[:, 0]))
    sw = scale * (p.vo_noise_w[0] + p.vo_noise_w[1] * np.abs(true_vel[:, 1])
                  + p.vo_noise_w[2] * np.abs(true_vel[:, 0]))
    noise = rng.standard_normal((k, 2))
    vel = true_vel + noise * np.stack([sv, sw], axis=1)
    # Still chair, still image: Fovis reports (almost exactly) zero.
    still = ~np.interp(frames, truth_t, moving.astype(float)).astype(bool)
    vel[still] = 0.0

    # Tracking failures: a Poisson process on the time spent moving.
    moving_f = np.interp(frames, truth_t, moving.astype(float)) > 0.5
    dt_all = np.concatenate([[0.0], dt])
    moving_time = np.cumsum(np.where(moving_f, dt_all, 0.0))
    rate_s = p.failure_rate(surface) / 60.0
    stale = np.zeros(k, dtype=bool)
    failures: list[tuple[float, float]] = []
    if rate_s > 0.0:
        acc = 0.0
        while True:
            acc += rng.exponential(1.0 / rate_s)
            if acc >= moving_time[-1]:
                break
            i = int(np.searchsorted(moving_time, acc))
            i = max(i, 1)
            duration = rng.uniform(*p.failure_duration_s)
            if stale[i - 1] or (failures and frames[i] < failures[-1][1]):
                continue  # overlaps the previous episode: merged away
            j = int(np.searchsorted(frames, frames[i] + duration))
            j = min(max(j, i + 1), k)
            stale[i:j] = True
            vel[i:j] = vel[i - 1]
            end = float(frames[j]) if j < k else float(t_end)
            failures.append((float(frames[i]), end))
            acc = float(moving_time[j - 1])  # no new failure before recovery
    lat_lo, lat_hi = p.vo_latency_s
    bag_time = frames + rng.uniform(lat_lo, lat_hi, k)
    return VoStream(
        stamp=frames, bag_time=bag_time, vel=vel, true_vel=true_vel, stale=stale,
        failures=np.asarray(failures, dtype=float).reshape(-1, 2),
    )


def expected_failures(
    exposed_seconds: float, surface: str, params: SensorParams | None = None
) -> float:
    """Expected number of tracking failures in ``exposed_seconds`` of motion outside
    failure episodes (the Poisson clock restarts when tracking recovers)."""
    p = params if params is not None else SensorParams()
    return p.failure_rate(surface) / 60.0 * max(0.0, exposed_seconds)
