"""Probability that the chair touches an obstacle along a predicted path (ROS-free).

Inputs: predicted paths (poses [B, k, 3] and position covariances [B, k, 2, 2], e.g. a
:class:`~asgp_ros.core.online.Prediction` or a batch of them), the chair's footprint, and
the obstacles, either as a laser scan (:class:`Scan`, the fields of sensor_msgs/LaserScan)
or as an occupancy grid (:class:`Grid`, the fields of nav_msgs/OccupancyGrid).

Model and approximations, stated once:

* **Obstacles -> distance field.** The obstacles are rasterised at ``resolution`` (a scan:
  the end points of its valid beams in the scan's frame; a grid: its occupied cells) and
  the Euclidean distance from every cell to the nearest obstacle cell is computed once
  (:class:`DistanceField`, ``scipy.ndimage.distance_transform_edt``), less half a cell, so
  the field never overstates a clearance by more than the raster's own error.
* **Footprint.** The rectangle (``length`` x ``width``, centred ``offset`` ahead of the
  base frame's origin, :class:`Footprint`) is tested exactly against the obstacle points
  (a scan's end points; a grid's obstacle cell centres, with the rectangle grown by half a
  cell). The distance field only decides which steps need the test: a step whose
  covering discs (``discs`` along the length, each covering its slice) are farther from
  every obstacle than five standard deviations of its position is below 3e-7 and is not
  sampled.
* **Position uncertainty.** The position at each step is Gaussian with the predicted mean
  and covariance; the heading is the predicted mean heading (the rollout's covariance is
  of the position only). The probability is estimated with ``samples`` fixed
  quasi-random standard-normal draws z (scrambled Sobol points, the same for every call,
  so results are deterministic and smooth in the inputs): sample j of step i is
  ``mean_i + chol(cov_i) z_j``.
* **Per step and within the horizon.** ``per_step[i]`` is the fraction of samples whose
  footprint touches at step i. ``within`` uses the same draw z_j along the whole path
  (the rollout's position errors accumulate, so consecutive steps are strongly
  correlated): it is the fraction of sampled paths that touch at any step. It lies
  between the two limits also returned: ``lower = max_i per_step[i]`` (perfectly
  dependent steps) and ``upper = 1 - prod_i (1 - per_step[i])`` (independent steps).
* **Speed.** Steps far from every obstacle cost a few distance lookups; the others
  ``samples`` x (the obstacle points within reach) comparisons.

REP-117 for scans: ``+inf`` or a range beyond ``range_max`` is no return within range
(free as far as the scan sees); ``-inf`` or a range below ``range_min`` is an object too
close to measure, counted as an obstacle at ``range_min``; ``NaN`` is an erroneous
reading. A scan with no usable beam, or with more than ``max_invalid`` of them NaN, is
refused (:class:`CollisionError`): an empty scan never reads as "clear".

Unknown space: a grid's unknown cells (-1) and everything outside a grid count as occupied
by default (``unknown_is_obstacle``); outside a scan's window (``range_max`` around the
scanner) there is no information, and a sample whose footprint centre is there counts as
touching.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.ndimage
import scipy.spatial
from numpy.typing import NDArray
from scipy.stats import norm, qmc

FloatArray = NDArray[np.float64]

__all__ = ["DEFAULT_FOOTPRINT", "CollisionError", "Contact", "DistanceField", "Footprint",
           "Grid", "Scan", "contact_probability", "grid_check", "scan_check"]

#: Sobol points per step (a power of two); the probability resolution is 1 / SAMPLES.
SAMPLES = 256
#: Steps farther than this many standard deviations from every obstacle are not sampled.
PRUNE_SIGMAS = 5.0


class CollisionError(ValueError):
    """Obstacle data that cannot be judged (an empty scan, a malformed grid, NaN paths)."""


@dataclass(frozen=True)
class Footprint:
    """The chair's footprint: a ``length`` x ``width`` rectangle (m) centred ``offset`` ahead
    of the base frame's origin, covered by ``discs`` discs along its length."""

    length: float = 1.2
    width: float = 0.7
    offset: float = 0.0
    discs: int = 4

    def __post_init__(self) -> None:
        for name in ("length", "width"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.05 <= value <= 10.0):
                raise ValueError(f"footprint {name} must be in [0.05, 10] m, got {value}")
        if not (math.isfinite(self.offset) and abs(self.offset) <= 10.0):
            raise ValueError(f"footprint offset must be within 10 m, got {self.offset}")
        if not 1 <= int(self.discs) <= 32:
            raise ValueError(f"discs must be in [1, 32], got {self.discs}")

    def grown(self, margin: float) -> Footprint:
        """The footprint grown by ``margin`` (m) on every side (a safety margin)."""
        if not (math.isfinite(margin) and 0.0 <= margin <= 1.0):
            raise ValueError(f"margin must be in [0, 1] m, got {margin}")
        return Footprint(self.length + 2 * margin, self.width + 2 * margin, self.offset,
                         self.discs)

    @property
    def radius(self) -> float:
        """Radius of the discs (m): each covers a length / discs slice of the rectangle."""
        return math.hypot(0.5 * self.length / self.discs, 0.5 * self.width)

    def centres(self) -> FloatArray:
        """[discs, 2] disc centres in the base frame."""
        step = self.length / self.discs
        x = self.offset - 0.5 * self.length + step * (np.arange(self.discs) + 0.5)
        return np.stack([x, np.zeros(self.discs)], axis=1)


DEFAULT_FOOTPRINT = Footprint()


@dataclass(frozen=True)
class Scan:
    """The fields of a sensor_msgs/LaserScan that the check needs (scan frame: x forward)."""

    ranges: FloatArray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    stamp: float = 0.0

    def __post_init__(self) -> None:
        r = np.asarray(self.ranges, dtype=np.float64)
        object.__setattr__(self, "ranges", r)
        if r.ndim != 1 or r.size == 0:
            raise CollisionError(f"a scan needs a 1-D array of ranges, got shape {r.shape}")
        if r.size > 100_000:
            raise CollisionError(f"a scan of {r.size} beams is more than 100,000")
        for name in ("angle_min", "angle_increment", "range_min", "range_max"):
            if not math.isfinite(getattr(self, name)):
                raise CollisionError(f"scan {name} is not finite")
        if not 0.0 <= self.range_min < self.range_max <= 1000.0:
            raise CollisionError(f"scan range limits [{self.range_min}, {self.range_max}] "
                                 "are not 0 <= min < max <= 1000 m")
        if self.angle_increment == 0.0 and r.size > 1:
            raise CollisionError("scan angle_increment is 0")


@dataclass(frozen=True)
class Grid:
    """The fields of a nav_msgs/OccupancyGrid: ``data`` [height, width] row-major (row =
    y index), -1 unknown, 0..100 occupancy; ``origin`` (x, y, yaw) of cell (0, 0)'s corner
    in the grid's frame."""

    data: NDArray[np.int8]
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        d = np.asarray(self.data)
        if d.ndim != 2 or d.size == 0:
            raise CollisionError(f"a grid needs [height, width] cells, got shape {d.shape}")
        if d.size > 50_000_000:
            raise CollisionError(f"a grid of {d.size} cells is more than 50 million")
        if not (math.isfinite(self.resolution) and 1e-3 <= self.resolution <= 100.0):
            raise CollisionError(f"grid resolution must be in [0.001, 100] m, got "
                                 f"{self.resolution}")
        if not all(math.isfinite(v) for v in self.origin):
            raise CollisionError("grid origin is not finite")
        object.__setattr__(self, "data", d.astype(np.int8, copy=False))


def _distances(mask: NDArray[np.bool_], res: float) -> FloatArray:
    """Distance (m) from every cell centre to the nearest obstacle cell, less half a cell
    (so it never overstates a clearance); inf without obstacles."""
    if not mask.any():
        return np.full(mask.shape, math.inf)
    edt = scipy.ndimage.distance_transform_edt(~mask)
    return np.maximum(np.asarray(edt, dtype=np.float64) * res - 0.5 * res, 0.0)


def _pose_matrix(pose: tuple[float, float, float]) -> tuple[FloatArray, FloatArray]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s], [s, c]]), np.array([pose[0], pose[1]], dtype=np.float64)


def inverse_pose(pose: tuple[float, float, float]) -> tuple[float, float, float]:
    """The inverse of a planar transform (x, y, yaw)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    x, y = pose[0], pose[1]
    return (-(c * x + s * y), s * x - c * y, -pose[2])


@dataclass(frozen=True)
class DistanceField:
    """Distance (m) to the nearest obstacle on a raster, in the field's frame.

    ``dist[iy, ix]`` is the clearance at the centre of cell (ix, iy), whose centre is at
    ``origin + R(yaw) ((ix + 0.5) res, (iy + 0.5) res)``; ``outside`` is the value off the
    raster (0: off the raster counts as touching).
    """

    dist: FloatArray
    resolution: float
    origin: tuple[float, float, float]
    points: FloatArray  # [m, 2] obstacle points in the field's frame
    grow: float = 0.0  # the footprint is grown by this for the exact test (half a cell)
    outside: float = 0.0
    _inv: tuple[FloatArray, FloatArray] = field(init=False, repr=False, compare=False)
    _tree: scipy.spatial.cKDTree | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        R, t = _pose_matrix(self.origin)
        object.__setattr__(self, "_inv", (R.T, -R.T @ t))
        tree = scipy.spatial.cKDTree(self.points) if self.points.shape[0] else None
        object.__setattr__(self, "_tree", tree)

    @property
    def obstacles(self) -> int:
        return int(self.points.shape[0])

    @staticmethod
    def from_scan(scan: Scan, resolution: float = 0.05, max_invalid: float = 0.5
                  ) -> DistanceField:
        """The field of a scan's obstacles in its own frame, over ``range_max`` around it."""
        r = scan.ranges
        nan = np.isnan(r)
        if nan.all() or nan.mean() > max_invalid:
            raise CollisionError(f"scan has {int(nan.sum())} of {r.size} beams NaN "
                                 "(erroneous): it cannot show the way is clear")
        angles = scan.angle_min + scan.angle_increment * np.arange(r.size)
        close = (r < scan.range_min) & ~nan  # includes -inf: too close to measure
        hit = close | ((r >= scan.range_min) & (r <= scan.range_max))
        rr = np.where(close, scan.range_min, r)[hit]
        pts = np.stack([rr * np.cos(angles[hit]), rr * np.sin(angles[hit])], axis=1)
        half = scan.range_max + 2 * resolution
        n = math.ceil(2 * half / resolution)
        origin = (-half, -half, 0.0)
        mask = np.zeros((n, n), dtype=bool)
        ij = np.floor((pts - np.array(origin[:2])) / resolution).astype(np.int64)
        mask[ij[:, 1], ij[:, 0]] = True  # every point is inside the window
        return DistanceField(_distances(mask, resolution), resolution, origin, pts, 0.0, 0.0)

    @staticmethod
    def from_grid(grid: Grid, occupied: int = 65, unknown_is_obstacle: bool = True
                  ) -> DistanceField:
        """The field of an occupancy grid in the grid's frame (the map's)."""
        if not 0 <= occupied <= 100:
            raise ValueError(f"occupied must be in [0, 100], got {occupied}")
        d = grid.data
        obstacle = d >= occupied
        if unknown_is_obstacle:
            obstacle |= d < 0
        res = grid.resolution
        iy, ix = np.nonzero(obstacle)
        R, t = _pose_matrix(grid.origin)
        pts = np.stack([(ix + 0.5) * res, (iy + 0.5) * res], axis=1) @ R.T + t
        return DistanceField(_distances(obstacle, res), res, grid.origin, pts, 0.5 * res,
                             0.0 if unknown_is_obstacle else math.inf)

    def contains(self, points: FloatArray) -> NDArray[np.bool_]:
        """[..., 2] points in the field's frame -> [...] inside the raster."""
        Rt, tt = self._inv
        local = points @ Rt.T + tt
        h, w = self.dist.shape
        size = np.array([w, h]) * self.resolution
        inside: NDArray[np.bool_] = np.all((local >= 0.0) & (local <= size), axis=-1)
        return inside

    def neighbours(self, centres: FloatArray, radii: FloatArray) -> list[list[int]]:
        """Indices of the obstacle points within ``radii`` [n] of ``centres`` [n, 2]."""
        if self._tree is None:
            return [[] for _ in range(centres.shape[0])]
        found: list[list[int]] = list(self._tree.query_ball_point(centres, radii))
        return found

    def near(self, centre: FloatArray, radius: float) -> FloatArray:
        """[m, 2] obstacle points within ``radius`` of ``centre`` [2]."""
        if self._tree is None:
            return np.zeros((0, 2))
        found: FloatArray = self.points[self._tree.query_ball_point(centre, radius)]
        return found

    def distance(self, points: FloatArray) -> FloatArray:
        """[..., 2] points in the field's frame -> [...] clearance (bilinear)."""
        Rt, tt = self._inv
        local = points @ Rt.T + tt
        u = local[..., 0] / self.resolution - 0.5
        v = local[..., 1] / self.resolution - 0.5
        h, w = self.dist.shape
        inside = (u >= 0.0) & (u <= w - 1) & (v >= 0.0) & (v <= h - 1)
        u = np.clip(u, 0.0, w - 1.0)
        v = np.clip(v, 0.0, h - 1.0)
        i0 = np.minimum(np.floor(u).astype(np.int64), max(w - 2, 0))
        j0 = np.minimum(np.floor(v).astype(np.int64), max(h - 2, 0))
        fu, fv = u - i0, v - j0
        i1, j1 = np.minimum(i0 + 1, w - 1), np.minimum(j0 + 1, h - 1)
        d = self.dist
        if not np.isfinite(d).all():  # no obstacle at all: inf everywhere on the raster
            return np.where(inside, math.inf, self.outside)
        top = d[j0, i0] * (1 - fu) + d[j0, i1] * fu
        bottom = d[j1, i0] * (1 - fu) + d[j1, i1] * fu
        out = top * (1 - fv) + bottom * fv
        return np.where(inside, out, self.outside)


class Contact(NamedTuple):
    """Probabilities of contact: ``per_step`` [B, k]; within the horizon ``within`` [B]
    (the sampled paths), with its limits ``lower`` [B] and ``upper`` [B] (module
    docstring)."""

    per_step: FloatArray
    within: FloatArray
    lower: FloatArray
    upper: FloatArray


_NORMAL_DRAWS: dict[int, FloatArray] = {}


def _draws(samples: int) -> FloatArray:
    """[samples, 2] fixed standard-normal draws (scrambled Sobol, seed 0)."""
    if samples not in _NORMAL_DRAWS:
        sobol = qmc.Sobol(d=2, scramble=True, seed=0).random(samples)
        _NORMAL_DRAWS[samples] = norm.ppf(np.clip(sobol, 1e-12, 1 - 1e-12))
    return _NORMAL_DRAWS[samples]


def _chol2(cov: FloatArray) -> FloatArray:
    """[..., 2, 2] PSD -> lower Cholesky factors (closed form; a negative round-off
    variance is clipped to 0)."""
    a = np.maximum(cov[..., 0, 0], 0.0)
    b = 0.5 * (cov[..., 0, 1] + cov[..., 1, 0])
    c = np.maximum(cov[..., 1, 1], 0.0)
    l11 = np.sqrt(a)
    l21 = np.divide(b, l11, out=np.zeros_like(b), where=l11 > 0.0)
    l22 = np.sqrt(np.maximum(c - l21**2, 0.0))
    L = np.zeros(cov.shape)
    L[..., 0, 0], L[..., 1, 0], L[..., 1, 1] = l11, l21, l22
    return L


def contact_probability(fld: DistanceField, pose: FloatArray, pos_cov: FloatArray,
                        footprint: Footprint = DEFAULT_FOOTPRINT,
                        transform: tuple[float, float, float] = (0.0, 0.0, 0.0),
                        samples: int = SAMPLES) -> Contact:
    """Probability that the footprint touches an obstacle of ``fld`` (module docstring).

    Args:
        fld: the obstacles.
        pose: [k, 3] or [B, k, 3] (x, y, yaw) of the base frame along each path.
        pos_cov: [k, 2, 2] or [B, k, 2, 2] position covariances.
        footprint: the chair.
        transform: pose (x, y, yaw) of the paths' frame in the field's frame.
        samples: Sobol draws per step (a power of two).

    Raises:
        CollisionError: shapes that do not match, NaN or inf in the paths.
    """
    P = np.asarray(pose, dtype=np.float64)
    C = np.asarray(pos_cov, dtype=np.float64)
    if P.ndim == 2:
        P, C = P[None], C[None]
    if P.ndim != 3 or P.shape[-1] != 3 or C.shape != (*P.shape[:2], 2, 2):
        raise CollisionError(f"paths must be [B, k, 3] with covariances [B, k, 2, 2], got "
                             f"{P.shape} and {C.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(C))):
        raise CollisionError("a path or its covariance holds NaN or inf")
    if samples < 2 or samples & (samples - 1):
        raise ValueError(f"samples must be a power of two >= 2, got {samples}")
    B, k = P.shape[:2]
    R, t = _pose_matrix(transform)
    xy = P[..., :2] @ R.T + t  # [B, k, 2] in the field's frame
    yaw = P[..., 2] + transform[2]
    cov = R @ C @ R.T
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # [B, k, 2, 2]
    offsets = np.einsum("bkij,dj->bkdi", rot, footprint.centres())  # [B, k, D, 2]
    r = footprint.radius

    # steps far from every obstacle: probability 0 without sampling
    clearance = fld.distance(xy[:, :, None, :] + offsets).min(axis=-1) - r  # [B, k]
    sigma = np.sqrt(np.maximum(np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
                               [..., 1], 0.0))
    near = clearance < PRUNE_SIGMAS * sigma + fld.resolution
    per_step = np.zeros((B, k))
    touch_any = np.zeros((B, samples), dtype=bool)
    if np.any(near):
        z = _draws(samples)  # [S, 2]
        half_w = 0.5 * footprint.width + fld.grow
        x_lo = footprint.offset - 0.5 * footprint.length - fld.grow
        x_hi = footprint.offset + 0.5 * footprint.length + fld.grow
        reach = math.hypot(max(abs(x_lo), abs(x_hi)), half_w)
        bi, ki = np.nonzero(near)
        d_all = np.einsum("sj,nij->nsi", z, _chol2(cov[bi, ki]))  # [n, S, 2] offsets
        centres = xy[bi, ki]  # [n, 2]
        rots = rot[bi, ki]  # [n, 2, 2]
        if fld.outside == 0.0:  # off the raster: no information, counted as touching
            touch_all = ~fld.contains(centres[:, None, :] + d_all)  # [n, S]
        else:
            touch_all = np.zeros((bi.size, samples), dtype=bool)
        # in the footprint's frame at the step's heading: q = R^T (o - centre - d)
        e_all = np.einsum("nsi,nij->nsj", d_all, rots)  # [n, S, 2] = R^T d
        radii = reach + np.abs(d_all).max(axis=(1, 2)) + 1e-9
        for n, idx in enumerate(fld.neighbours(centres, radii)):
            if not idx:
                continue
            q = (fld.points[idx] - centres[n]) @ rots[n]  # [m, 2]
            qx = q[None, :, 0] - e_all[n, :, None, 0]
            qy = q[None, :, 1] - e_all[n, :, None, 1]
            touch_all[n] |= ((qx >= x_lo) & (qx <= x_hi) & (np.abs(qy) <= half_w)).any(axis=1)
        per_step[bi, ki] = touch_all.mean(axis=1)
        np.logical_or.at(touch_any, bi, touch_all)
    within = touch_any.mean(axis=1)
    lower = per_step.max(axis=1) if k else np.zeros(B)
    upper = 1.0 - np.prod(1.0 - per_step, axis=1)
    return Contact(per_step, np.maximum(within, lower), lower, upper)


CollisionCheck = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray]]


def scan_check(scan: Scan, footprint: Footprint = DEFAULT_FOOTPRINT,
               mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
               base_motion: tuple[float, float, float] = (0.0, 0.0, 0.0),
               resolution: float = 0.05) -> CollisionCheck:
    """A check of paths in the base frame against ``scan``.

    Args:
        scan: the scan.
        footprint: the chair.
        mount: pose of the scanner in the base frame (x, y, yaw).
        base_motion: pose of the paths' base frame (at the prediction time) in the base
            frame at the scan's time: the chair's motion in between.
        resolution: raster of the distance field (m).

    Raises:
        CollisionError: a scan that cannot show the way is clear.
    """
    fld = DistanceField.from_scan(scan, resolution)
    Rm, tm = _pose_matrix(inverse_pose(mount))
    Rb, tb = _pose_matrix(base_motion)
    R = Rm @ Rb
    t = Rm @ tb + tm
    transform = (float(t[0]), float(t[1]), math.atan2(R[1, 0], R[0, 0]))

    def check(pose: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
        c = contact_probability(fld, pose, cov, footprint, transform)
        return c.per_step, c.within

    return check


def grid_check(grid: Grid | DistanceField, footprint: Footprint = DEFAULT_FOOTPRINT,
               origin: tuple[float, float, float] | FloatArray = (0.0, 0.0, 0.0),
               occupied: int = 65, unknown_is_obstacle: bool = True) -> CollisionCheck:
    """A check of paths in the base frame against a map (or its prebuilt field).

    Args:
        grid: the map, or :meth:`DistanceField.from_grid` of it (build it once per map).
        footprint: the chair.
        origin: pose of the paths' base frame in the map's frame (x, y, yaw).
        occupied, unknown_is_obstacle: as :meth:`DistanceField.from_grid`.
    """
    fld = grid if isinstance(grid, DistanceField) else DistanceField.from_grid(
        grid, occupied, unknown_is_obstacle)
    o = tuple(float(v) for v in origin)
    if len(o) != 3 or not all(math.isfinite(v) for v in o):
        raise CollisionError(f"origin must be a finite (x, y, yaw), got {origin}")
    transform = (o[0], o[1], o[2])

    def check(pose: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
        c = contact_probability(fld, pose, cov, footprint, transform)
        return c.per_step, c.within

    return check
