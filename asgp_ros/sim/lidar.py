"""A simulated 2-D laser scanner on the chair, and the room's map as an occupancy grid.

What the scanner sees: the fronts of the furniture along the walls (``Room.free_box``),
the obstacles the chair must not touch (``Room.contact``). Ranges are cast analytically
from the scanner's pose to the edges of that rectangle, then degraded like a real
scanner's (REP-117 semantics, as sensor_msgs/LaserScan carries them):

* Gaussian range noise (``noise_sd``);
* dropouts: a beam returns NaN (an erroneous reading) with probability ``dropout``;
* beyond ``range_max``: +inf (no return within range); closer than ``range_min``: -inf.

The map (:func:`room_grid`) is the same geometry rasterised like nav_msgs/OccupancyGrid:
100 on the furniture band and beyond (up to the walls), 0 on the free floor, -1 outside
the walls, with its origin at the room's lower-left wall corner, in the room's (odom)
frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from asgp_ros.sim.world import Room

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LidarConfig:
    """The scanner.

    Attributes:
        fov_deg: field of view, centred on the scanner's x axis (degrees).
        beams: number of beams over the field of view.
        range_min, range_max: measurable range (m).
        noise_sd: range noise (m, one standard deviation).
        dropout: probability of a NaN beam.
        mount: scanner pose (x, y, yaw) in the chair's base frame.
        rate_hz: scans per second.
    """

    fov_deg: float = 270.0
    beams: int = 1081
    range_min: float = 0.05
    range_max: float = 8.0
    noise_sd: float = 0.01
    dropout: float = 0.01
    mount: tuple[float, float, float] = (0.3, 0.0, 0.0)
    rate_hz: float = 10.0

    def __post_init__(self) -> None:
        if not (0.0 < self.fov_deg <= 360.0 and 2 <= self.beams <= 100_000):
            raise ValueError(f"bad scanner geometry: {self.fov_deg} deg, {self.beams} beams")
        if not 0.0 <= self.range_min < self.range_max <= 100.0:
            raise ValueError(f"bad range limits [{self.range_min}, {self.range_max}]")
        if not (0.0 <= self.noise_sd <= 1.0 and 0.0 <= self.dropout < 1.0):
            raise ValueError(f"bad noise: sd {self.noise_sd}, dropout {self.dropout}")
        if not 0.1 <= self.rate_hz <= 100.0:
            raise ValueError(f"rate_hz must be in [0.1, 100], got {self.rate_hz}")

    @property
    def angle_min(self) -> float:
        return -0.5 * math.radians(self.fov_deg)

    @property
    def angle_increment(self) -> float:
        return math.radians(self.fov_deg) / (self.beams - 1)


@dataclass(frozen=True)
class ScanArrays:
    """One scan, with the fields of sensor_msgs/LaserScan."""

    ranges: FloatArray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float


def cast_to_box(origin: FloatArray, angles: FloatArray,
                box: tuple[float, float, float, float]) -> FloatArray:
    """Distance from ``origin`` [2] along world ``angles`` [n] to the edges of the box
    (x_lo, x_hi, y_lo, y_hi) seen from inside; 0 when the origin is outside it."""
    x_lo, x_hi, y_lo, y_hi = box
    ox, oy = float(origin[0]), float(origin[1])
    if not (x_lo < ox < x_hi and y_lo < oy < y_hi):
        return np.zeros(angles.shape)
    c, s = np.cos(angles), np.sin(angles)
    with np.errstate(divide="ignore"):
        tx = np.where(c > 0.0, (x_hi - ox) / c, np.where(c < 0.0, (x_lo - ox) / c, np.inf))
        ty = np.where(s > 0.0, (y_hi - oy) / s, np.where(s < 0.0, (y_lo - oy) / s, np.inf))
    return np.minimum(tx, ty)


def cast_to_segments(angles: FloatArray,
                     segments: list[tuple[tuple[float, float], tuple[float, float]]]
                     ) -> FloatArray:
    """Distance from the origin along ``angles`` [n] to the nearest of the line
    ``segments`` [((x1, y1), (x2, y2)), ...] (inf where none is hit): a wall, a cabinet's
    side, in the scanner's frame."""
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    r = np.full(angles.shape, math.inf)
    for (x1, y1), (x2, y2) in segments:
        ex, ey = x2 - x1, y2 - y1
        den = -d[:, 0] * ey + d[:, 1] * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (-x1 * ey + y1 * ex) / den
            u = (d[:, 0] * y1 - d[:, 1] * x1) / den
        hit = (np.abs(den) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        r = np.where(hit & (t < r), t, r)
    return r


class Lidar:
    """The scanner on the chair in ``room``; ``scan(x, y, theta)`` -> :class:`ScanArrays`."""

    def __init__(self, room: Room, config: LidarConfig | None = None, seed: int = 0) -> None:
        self.room = room
        self.config = config or LidarConfig()
        self._rng = np.random.default_rng(seed)
        c = self.config
        self._beam: FloatArray = c.angle_min + c.angle_increment * np.arange(c.beams,
                                                                            dtype=float)

    def true_ranges(self, x: float, y: float, theta: float) -> FloatArray:
        """Noise-free ranges [beams] from the chair's pose (base frame at x, y, theta)."""
        mx, my, myaw = self.config.mount
        c, s = math.cos(theta), math.sin(theta)
        origin = np.array([x + c * mx - s * my, y + s * mx + c * my])
        return cast_to_box(origin, theta + myaw + self._beam, self.room.free_box)

    def scan(self, x: float, y: float, theta: float) -> ScanArrays:
        c = self.config
        r = self.true_ranges(x, y, theta)
        r = r + self._rng.normal(0.0, c.noise_sd, r.shape) if c.noise_sd else r.copy()
        r[r > c.range_max] = math.inf
        r[r < c.range_min] = -math.inf
        r[self._rng.random(r.shape) < c.dropout] = math.nan
        return ScanArrays(r, c.angle_min, c.angle_increment, c.range_min, c.range_max)


@dataclass(frozen=True)
class GridArrays:
    """An occupancy grid with the fields of nav_msgs/OccupancyGrid (row = y index)."""

    data: NDArray[np.int8]
    resolution: float
    origin: tuple[float, float, float]


def room_grid(room: Room, resolution: float = 0.05, margin: float = 0.5) -> GridArrays:
    """The room's map (module docstring), ``margin`` of unknown beyond the walls."""
    if not (math.isfinite(resolution) and 0.005 <= resolution <= 1.0):
        raise ValueError(f"resolution must be in [0.005, 1] m, got {resolution}")
    x0, y0 = room.x_min - margin, room.y_min - margin
    w = math.ceil((room.x_max - room.x_min + 2 * margin) / resolution)
    h = math.ceil((room.y_max - room.y_min + 2 * margin) / resolution)
    xc = x0 + (np.arange(w) + 0.5) * resolution
    yc = y0 + (np.arange(h) + 0.5) * resolution
    X, Y = np.meshgrid(xc, yc)  # [h, w]
    x_lo, x_hi, y_lo, y_hi = room.free_box
    inside_walls = (room.x_min < X) & (room.x_max > X) & (room.y_min < Y) & (room.y_max > Y)
    free = (x_lo < X) & (x_hi > X) & (y_lo < Y) & (y_hi > Y)
    data = np.full((h, w), -1, dtype=np.int8)
    data[inside_walls] = 100
    data[free] = 0
    return GridArrays(data, resolution, (x0, y0, 0.0))
