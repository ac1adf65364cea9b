"""What the laser scanner saw a moment ago, carried along by the visual odometry.

A chair's scanner sees a sector (270 degrees on most chairs): the furniture behind the
chair is out of view, and a chair turning on the spot swings its rear corners through
it. A check against the newest scan alone reads that sector as clear. The chair usually
drove past those obstacles seconds before, with them in view: this module keeps them.

* :class:`Odometer` integrates the VO's twists into the base frame's pose in a local
  frame (dead reckoning: a few centimetres over the seconds the memory lasts). Lost
  tracking, a gap in the twists or a stamp going back starts a new *epoch*: poses of
  different epochs are unrelated, and the memory forgets everything it held.
* :class:`ScanMemory` keeps the obstacle points of earlier scans in that frame, one per
  ``cell_m`` square (the newest), for ``max_age_s`` and within ``radius_m`` of the chair.
  Every new scan is the authority on what it sees: a remembered point on one of its beams
  that the beam passed through, or hit, is forgotten (the beam's new return replaces it;
  an obstacle that moved away is gone at once); a point behind the beam's return
  (occluded), on a NaN beam (no reading) or outside the field of view is kept.
* :meth:`ScanMemory.add` returns the remembered points that the scan itself does not
  hold, in the scan's frame, for :func:`asgp_ros.core.collision.scan_check` (``extra``).

The memory never makes the check more optimistic than the scan alone: it only adds
points. Stale odometry never moves it: without a pose at the scan's stamp the memory is
emptied and the scan is used alone.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core.collision import Scan, scan_points

FloatArray = NDArray[np.float64]
Pose = tuple[float, float, float]

#: Largest |v| (m/s) and |omega| (rad/s) the odometer integrates: beyond, the twist is
#: not a chair's and the odometer starts a new epoch.
MAX_SPEED = 10.0
MAX_TURN_RATE = 20.0

#: Twists an :class:`Odometer` keeps (a flood of them keeps the newest).
MAX_HISTORY = 4096

#: What can carry the memory: the scans matched to each other
#: (:class:`asgp_ros.core.scan_match.ScanOdometer`), or dead reckoning of twists
#: (:class:`Odometer`).
MEMORY_ODOMETRY = ("scan_matching", "dead_reckoning")


@dataclass(frozen=True)
class MemoryConfig:
    """Settings of the obstacle memory (validated on construction).

    Attributes:
        max_age_s: a remembered point is forgotten this long after the scan that saw it.
        radius_m: points farther than this from the chair are forgotten.
        cell_m: one point is kept per square of this size (the newest).
        clear_tolerance_m: a beam clears a remembered point up to its return plus this
            (range noise and the beam's width).
        max_points: at most this many points are kept (the oldest go first).
        max_gap_s: twists further apart than this break the dead reckoning (a new epoch);
            a scan further than this from the newest twist gets no pose.
    """

    max_age_s: float = 10.0
    radius_m: float = 3.0
    cell_m: float = 0.02
    clear_tolerance_m: float = 0.05
    max_points: int = 20_000
    max_gap_s: float = 0.5

    def __post_init__(self) -> None:
        for name, low, high in (("max_age_s", 0.0, 600.0), ("radius_m", 0.1, 100.0),
                                ("cell_m", 1e-3, 1.0), ("clear_tolerance_m", 0.0, 1.0),
                                ("max_gap_s", 0.01, 10.0)):
            value = getattr(self, name)
            if not (math.isfinite(value) and low <= value <= high):
                raise ValueError(f"{name} must be in [{low}, {high}], got {value}")
        if not 1 <= self.max_points <= 10_000_000:
            raise ValueError(f"max_points must be in [1, 1e7], got {self.max_points}")


def compose(a: Pose, b: Pose) -> Pose:
    """The planar transform a then b (b expressed in a's frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
            math.remainder(a[2] + b[2], 2.0 * math.pi))


def arc(v: float, w: float, dt: float) -> Pose:
    """Pose after ``dt`` >= 0 seconds at the constant twist (v, w), from the origin: the
    exact circular arc (a straight line as w -> 0)."""
    if dt <= 0.0:
        return (0.0, 0.0, 0.0)
    th = w * dt
    if abs(th) < 1e-6:  # series of sin(th)/th and (1 - cos(th))/th
        a, b = 1.0 - th * th / 6.0, 0.5 * th
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th
    d = v * dt
    return (d * a, d * b, th)


class Odometer:
    """Dead reckoning from the VO's twists (module docstring).

    Each twist (v, omega) stamped t is held from the previous twist's stamp to t (a
    frame-to-frame VO measures the motion between its frames and stamps the newer one).
    """

    def __init__(self, max_gap_s: float = 0.5, history_s: float = 5.0) -> None:
        if not (math.isfinite(max_gap_s) and max_gap_s > 0.0):
            raise ValueError(f"max_gap_s must be > 0, got {max_gap_s}")
        self.max_gap_s = max_gap_s
        self.history_s = history_s
        self.epoch = 0
        self.breaks = 0  # epochs started after the first
        # (t, pose, v, w); at most MAX_HISTORY entries, whatever rate the twists come at
        self._history: deque[tuple[float, Pose, float, float]] = deque(maxlen=MAX_HISTORY)

    @property
    def stamp(self) -> float | None:
        """The newest twist's stamp in this epoch (None: none yet)."""
        return self._history[-1][0] if self._history else None

    def lost(self) -> None:
        """Tracking lost: the next twist starts a new epoch."""
        if self._history:
            self._history.clear()
            self.epoch += 1
            self.breaks += 1

    def feed(self, t: float, v: float, w: float) -> bool:
        """Integrate the twist stamped ``t``. Returns False (and starts over at the next
        one) for a non-finite or impossible twist, or a stamp that goes back."""
        if not (math.isfinite(t) and math.isfinite(v) and math.isfinite(w)
                and abs(v) <= MAX_SPEED and abs(w) <= MAX_TURN_RATE):
            self.lost()
            return False
        if self._history:
            t_last, pose, _, _ = self._history[-1]
            if t <= t_last:
                if t < t_last:  # back in time (a bag restarted): unrelated poses
                    self.lost()
                return False
            if t - t_last > self.max_gap_s:
                self.lost()
                self._history.append((t, (0.0, 0.0, 0.0), v, w))
                return True
            self._history.append((t, compose(pose, arc(v, w, t - t_last)), v, w))
            while self._history and self._history[0][0] < t - self.history_s:
                self._history.popleft()
            return True
        self._history.append((t, (0.0, 0.0, 0.0), v, w))
        return True

    def pose_at(self, t: float) -> Pose | None:
        """The base pose at ``t`` in this epoch's frame: interpolated at the twist held
        over the interval, extrapolated up to ``max_gap_s`` past the newest twist; None
        without odometry there (before the history, or stale)."""
        h = self._history
        if not h or not math.isfinite(t) or t < h[0][0] or t > h[-1][0] + self.max_gap_s:
            return None
        if t >= h[-1][0]:
            t_last, pose, v, w = h[-1]
            return compose(pose, arc(v, w, t - t_last))
        stamps = [e[0] for e in h]
        i = int(np.searchsorted(stamps, t, side="right"))  # h[i-1].t <= t < h[i].t
        t0, pose0, _, _ = h[i - 1]
        _, _, v, w = h[i]  # the twist held over (h[i-1].t, h[i].t]
        return compose(pose0, arc(v, w, t - t0))


class ScanMemory:
    """Obstacle points of earlier scans, in the odometer's frame (module docstring).

    Args:
        mount: the scanner's pose in the base frame (x, y, yaw).
        config: the settings.
    """

    def __init__(self, mount: Pose = (0.0, 0.0, 0.0), config: MemoryConfig | None = None
                 ) -> None:
        self.mount = (float(mount[0]), float(mount[1]), float(mount[2]))
        self.config = config or MemoryConfig()
        self._epoch: int | None = None
        self._stamp = -math.inf  # newest scan's stamp
        self._xy = np.zeros((0, 2))  # [m, 2] points, odometer frame
        self._t = np.zeros(0)  # [m] stamps of the scans that saw them
        self.resets = 0

    @property
    def size(self) -> int:
        return int(self._t.size)

    def reset(self) -> None:
        """Forget everything (no odometry, or a new epoch)."""
        if self._t.size:
            self.resets += 1
        self._xy, self._t = np.zeros((0, 2)), np.zeros(0)
        self._epoch, self._stamp = None, -math.inf

    def add(self, scan: Scan, pose: Pose | None, epoch: int = 0) -> FloatArray:
        """Take in ``scan``, seen from the base pose ``pose`` (odometer frame, at the
        scan's stamp; None: no odometry, the memory is emptied).

        Returns:
            [m, 2] the remembered points the scan does not hold, in the scan's frame
            (empty without a pose).
        """
        if pose is None or not all(math.isfinite(p) for p in pose) or \
                not math.isfinite(scan.stamp):
            self.reset()
            return np.zeros((0, 2))
        if epoch != self._epoch or scan.stamp < self._stamp:
            self.reset()
        cfg = self.config
        sensor = compose((float(pose[0]), float(pose[1]), float(pose[2])), self.mount)
        R = np.array([[math.cos(sensor[2]), -math.sin(sensor[2])],
                      [math.sin(sensor[2]), math.cos(sensor[2])]])
        origin = np.array(sensor[:2])
        base = np.array([pose[0], pose[1]], dtype=np.float64)

        # the old points, in the scan's frame: what this scan's view decides about them
        local = (self._xy - origin) @ R
        keep = ((scan.stamp - self._t <= cfg.max_age_s)
                & (np.hypot(*(self._xy - base).T) <= cfg.radius_m)
                & ~self._seen_through(scan, local))
        old_xy, old_t, old_local = self._xy[keep], self._t[keep], local[keep]

        new_local = scan_points(scan)
        new_xy = new_local @ R.T + origin
        near = np.hypot(*(new_xy - base).T) <= cfg.radius_m
        xy = np.concatenate([new_xy[near], old_xy])  # newest first
        t = np.concatenate([np.full(int(near.sum()), scan.stamp), old_t])
        keys = np.floor(xy / cfg.cell_m).astype(np.int64)
        _, first = np.unique(keys, axis=0, return_index=True)
        first.sort()  # newest first still
        first = first[:cfg.max_points]
        self._xy, self._t = xy[first], t[first]
        self._epoch, self._stamp = epoch, scan.stamp

        remembered = first >= int(near.sum())  # rows from the old points
        index = first[remembered] - int(near.sum())
        out: FloatArray = old_local[index]
        return out

    def _seen_through(self, scan: Scan, local: FloatArray) -> NDArray[np.bool_]:
        """[m] the points (scan frame) this scan's beams passed through or hit."""
        if local.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        r = scan.ranges
        n = r.size
        rho = np.hypot(local[:, 0], local[:, 1])
        bearing = np.arctan2(local[:, 1], local[:, 0])
        inc = scan.angle_increment
        if n == 1 or inc == 0.0:
            return np.zeros(local.shape[0], dtype=bool)
        two_pi = 2.0 * math.pi
        offset = np.mod((bearing - scan.angle_min) * math.copysign(1.0, inc), two_pi)
        idx = np.rint(offset / abs(inc)).astype(np.int64)
        full_circle = n * abs(inc) >= two_pi - 1e-9
        idx = np.where(full_circle, idx % n, idx)
        # the nearest beam, if within half a beam of it (a point just past the sector's
        # last beam is outside the view)
        in_view = (idx >= 0) & (idx < n)
        safe = np.clip(idx, 0, n - 1)
        beam = r[safe]
        reach = np.where(np.isnan(beam), -math.inf,  # no reading: nothing cleared
                         np.where(beam < scan.range_min, scan.range_min,
                                  np.where(beam > scan.range_max, scan.range_max, beam)))
        hit_or_free = np.where(beam > scan.range_max, rho < reach,  # nothing in range
                               rho <= reach + self.config.clear_tolerance_m)
        seen: NDArray[np.bool_] = in_view & hit_or_free
        return seen
