"""What the demo watches, without ROS: rates, latencies, and the online success rate.

Online success rate (the paper's metric, Fan et al. ICRA 2018 Sec. V, scored live against
the simulator's ground truth): a predicted path made at ``t0`` holds poses at
``t0 + i dt`` in ``base_link`` at ``t0``. Once the ground truth reaches ``t0 + h``, the true
displacement from ``t0`` to ``t0 + h`` is expressed in the body frame at ``t0``
(:func:`asgp_ros.core.metrics.relative_displacement`, the function the offline evaluation
uses with ``--truth``) and compared with the predicted (x, y) at ``h``; the prediction is a
success when the distance is at most the threshold (10 cm). The ground truth is
interpolated linearly at ``t0`` and ``t0 + h`` (heading unwrapped), as the resampler
interpolates it onto the grid offline.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M, horizon_key, relative_displacement

FloatArray = NDArray[np.float64]

class RateMeter:
    """Arrivals per second over a sliding window (monotonic seconds)."""

    def __init__(self, window_s: float = 3.0) -> None:
        if not window_s > 0.0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self.window_s = window_s
        self.times: deque[float] = deque()
        self.count = 0

    def tick(self, t: float) -> None:
        self.times.append(t)
        self.count += 1
        self._drop(t)

    def _drop(self, now: float) -> None:
        while self.times and self.times[0] < now - self.window_s:
            self.times.popleft()

    def rate(self, now: float) -> float:
        """Messages per second over the window ending at ``now`` (0 when fewer than two)."""
        self._drop(now)
        if len(self.times) < 2:
            return 0.0
        span = max(now - self.times[0], self.times[-1] - self.times[0], 1e-9)
        return (len(self.times) - 1) / span if now - self.times[-1] < self.window_s else 0.0


class LatencyStats:
    """Latencies (s) of one kind of message: all values kept for percentiles."""

    def __init__(self) -> None:
        self.values: list[float] = []

    def add(self, seconds: float) -> None:
        if math.isfinite(seconds):
            self.values.append(float(seconds))

    def summary_ms(self) -> dict[str, float]:
        """{"n", "median_ms", "p95_ms", "max_ms"} (nan when empty)."""
        if not self.values:
            nan = float("nan")
            return {"n": 0, "median_ms": nan, "p95_ms": nan, "max_ms": nan}
        v = 1e3 * np.asarray(self.values)
        return {"n": int(v.size), "median_ms": float(np.median(v)),
                "p95_ms": float(np.percentile(v, 95)), "max_ms": float(v.max())}


class TruthTrack:
    """Ground-truth poses (x, y, yaw) in time order; yaw unwrapped on arrival."""

    def __init__(self) -> None:
        self._t: list[float] = []
        self._p: list[tuple[float, float, float]] = []

    def add(self, t: float, x: float, y: float, yaw: float) -> None:
        if not all(math.isfinite(v) for v in (t, x, y, yaw)):
            raise ValueError(f"ground truth must be finite, got {(t, x, y, yaw)}")
        if self._t and t <= self._t[-1]:
            return  # duplicate or out of order: the simulator publishes in order
        if self._p:
            prev = self._p[-1][2]
            yaw = prev + math.atan2(math.sin(yaw - prev), math.cos(yaw - prev))
        self._t.append(float(t))
        self._p.append((float(x), float(y), float(yaw)))

    @property
    def newest(self) -> float:
        return self._t[-1] if self._t else -math.inf

    def arrays(self) -> tuple[FloatArray, FloatArray]:
        """(t [N], pose [N, 3])."""
        return np.asarray(self._t, dtype=np.float64), np.asarray(self._p,
                                                                 dtype=np.float64).reshape(-1, 3)

    def at(self, t: float) -> FloatArray | None:
        """Pose [3] interpolated at ``t``, or None outside the track."""
        if not self._t or t < self._t[0] or t > self._t[-1]:
            return None
        i = int(np.searchsorted(self._t, t))
        if i == 0:
            return np.asarray(self._p[0])
        t0, t1 = self._t[i - 1], self._t[i]
        a = (t - t0) / (t1 - t0)
        p0, p1 = np.asarray(self._p[i - 1]), np.asarray(self._p[i])
        p: FloatArray = p0 + a * (p1 - p0)
        return p


@dataclass
class PathRecord:
    """One predicted path as received.

    Attributes:
        t0: prediction time (the path's header stamp).
        times: [k] pose stamps; pose: [k, 3] (x, y, yaw) in base_link at t0.
        ellipses: [k, 3] 95% (semi-major, semi-minor, angle) from the uncertainty markers,
            None until they arrive.
        arrival: wall-clock seconds of arrival (same clock as the stamps).
        errors: horizon key -> position error against ground truth (m), when scored.
        inside: horizon key -> the true position lies in the 95% ellipse, when scored and
            the ellipses had arrived.
    """

    t0: float
    times: FloatArray
    pose: FloatArray
    arrival: float
    ellipses: FloatArray | None = None
    errors: dict[str, float] = field(default_factory=dict)
    inside: dict[str, bool] = field(default_factory=dict)


def in_ellipse(point: ArrayLike, centre: ArrayLike, ellipse: ArrayLike) -> bool:
    """Whether ``point`` [2] lies in the closed ellipse (semi-major a, semi-minor b, angle
    of the major axis from x) around ``centre`` [2].

    A degenerate ellipse is what it is: with b = 0 the segment of half-length a along the
    angle, with a = b = 0 the centre alone (in floating point, few points lie on either).
    Ellipses read from the predictor's markers are never degenerate
    (:func:`asgp_ros.nodes.conversions.ellipses_from_markers`).

    Raises:
        ValueError: axes not finite, negative or b > a; a non-finite point or centre.
    """
    a, b, angle = (float(x) for x in np.asarray(ellipse, dtype=np.float64).reshape(3))
    p = np.asarray(point, dtype=np.float64).reshape(2)
    c0 = np.asarray(centre, dtype=np.float64).reshape(2)
    if not (math.isfinite(a) and math.isfinite(b) and math.isfinite(angle)
            and 0.0 <= b <= a):
        raise ValueError(f"an ellipse needs finite axes a >= b >= 0, got {a}, {b}, {angle}")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(c0))):
        raise ValueError("the point and the centre must be finite")
    dx, dy = float(p[0] - c0[0]), float(p[1] - c0[1])
    c, s = math.cos(angle), math.sin(angle)
    u, v = c * dx + s * dy, -s * dx + c * dy  # along the major and the minor axis
    if b == 0.0:
        return v == 0.0 and abs(u) <= a
    return (u / a) ** 2 + (v / b) ** 2 <= 1.0


class OnlineScore:
    """Scores predicted paths against ground truth as it arrives (module docstring)."""

    def __init__(self, horizons_s: tuple[float, ...] = HORIZONS_S,
                 threshold_m: float = THRESHOLD_M) -> None:
        if not horizons_s or any(not (h > 0.0 and math.isfinite(h)) for h in horizons_s):
            raise ValueError(f"horizons must be positive, got {horizons_s}")
        if not (threshold_m > 0.0 and math.isfinite(threshold_m)):
            raise ValueError(f"threshold must be > 0 m, got {threshold_m}")
        self.horizons = tuple(float(h) for h in horizons_s)
        self.threshold = float(threshold_m)
        self.paths: list[PathRecord] = []
        self._pending: deque[PathRecord] = deque()
        self.unscorable = 0  # paths whose t0 precedes the ground truth, or too short
        self.bad_ellipses = 0  # ellipses that are not ones (NaN, negative axes)

    def add(self, rec: PathRecord) -> None:
        if rec.pose.shape != (rec.times.shape[0], 3) or not np.all(np.isfinite(rec.pose)):
            raise ValueError(f"a path must be finite [k, 3], got shape {rec.pose.shape}")
        self.paths.append(rec)
        self._pending.append(rec)

    def index(self, rec: PathRecord, h: float) -> int | None:
        """Index of the pose at t0 + h in ``rec`` (None if the path is shorter)."""
        if rec.times.size == 0:
            return None
        i = int(np.argmin(np.abs(rec.times - (rec.t0 + h))))
        return i if abs(rec.times[i] - (rec.t0 + h)) < 1e-3 else None

    def update(self, truth: TruthTrack) -> int:
        """Score every pending path whose horizons the ground truth now covers.

        Returns the number of paths completed.
        """
        done = 0
        last_h = max(self.horizons)
        while self._pending and self._pending[0].t0 + last_h <= truth.newest:
            rec = self._pending.popleft()
            done += 1
            p0 = truth.at(rec.t0)
            if p0 is None:
                self.unscorable += 1
                continue
            for h in self.horizons:
                i = self.index(rec, h)
                p1 = truth.at(rec.t0 + h)
                if i is None or p1 is None:
                    continue
                disp = relative_displacement(p0[None, :], p1[None, :])[0]
                key = horizon_key(h)
                rec.errors[key] = float(np.hypot(*(rec.pose[i, :2] - disp)))
                ell = rec.ellipses
                if ell is not None and ell.shape == (rec.times.shape[0], 3):
                    try:
                        rec.inside[key] = in_ellipse(disp, rec.pose[i, :2], ell[i])
                    except ValueError:
                        self.bad_ellipses += 1  # not counted either way
        return done

    def _scored(self, table: str, h: float, t0_filter: set[int] | None,
                dt: float | None) -> list[Any]:
        """The values of ``rec.<table>`` at ``h`` of the scored paths, in order; with
        ``t0_filter`` only those whose grid index round(t0 / dt) is in the set."""
        key = horizon_key(h)
        out = []
        for rec in self.paths:
            scored = getattr(rec, table)
            if key not in scored:
                continue
            if t0_filter is not None:
                assert dt is not None
                if round(rec.t0 / dt) not in t0_filter:
                    continue
            out.append(scored[key])
        return out

    def errors(self, h: float, t0_filter: set[int] | None = None,
               dt: float | None = None) -> FloatArray:
        """Scored errors at ``h`` (m); with ``t0_filter`` only paths whose grid index
        round(t0 / dt) is in the set (to compare on the offline evaluation's cases)."""
        return np.asarray(self._scored("errors", h, t0_filter, dt), dtype=np.float64)

    def coverage(self, h: float, t0_filter: set[int] | None = None,
                 dt: float | None = None) -> tuple[float, int]:
        """(share of the scored paths whose 95% ellipse at ``h`` holds the true position,
        or nan; the number of those paths with ellipses), filtered as :meth:`errors`."""
        hits = self._scored("inside", h, t0_filter, dt)
        return (float(np.mean(hits)) if hits else float("nan")), len(hits)

    def success(self, h: float, **kwargs: Any) -> tuple[float, int]:
        """(success rate in [0, 1] or nan, number of scored paths) at horizon ``h``."""
        e = self.errors(h, **kwargs)
        if e.size == 0:
            return float("nan"), 0
        return float(np.mean(e <= self.threshold)), int(e.size)


def format_status(elapsed_s: float, total_s: float, rates: dict[str, float], vo_state: str,
                  latency_ms: float, score: OnlineScore) -> str:
    """The live status line."""
    parts = [f"{elapsed_s:5.0f}/{total_s:.0f} s",
             " ".join(f"{k} {v:4.1f}" for k, v in rates.items()) + " Hz",
             f"VO {vo_state}",
             f"pred latency {latency_ms:5.1f} ms" if math.isfinite(latency_ms)
             else "pred latency   -  "]
    succ = []
    for h in score.horizons:
        rate, n = score.success(h)
        succ.append(f"{h:g}s {'  -  ' if n == 0 else f'{100 * rate:4.1f}%'}")
    n = score.success(score.horizons[0])[1]
    parts.append("success " + " ".join(succ) + f" (n={n})")
    return " | ".join(parts)
