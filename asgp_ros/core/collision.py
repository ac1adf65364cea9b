"""Probability that the chair touches an obstacle along a predicted path (ROS-free).

Inputs: predicted paths (poses [B, k, 3] with position covariances [B, k, 2, 2] or full pose
covariances [B, k, 3, 3], e.g. a :class:`~asgp_ros.core.online.Prediction` or a batch of
them), the chair's footprint, and the obstacles, either as a laser scan (:class:`Scan`, the
fields of sensor_msgs/LaserScan) or as an occupancy grid (:class:`Grid`, the fields of
nav_msgs/OccupancyGrid).

Model and approximations, stated once:

* **Obstacles.** Points: a scan's end points of its valid beams (in the scan's frame), or
  a grid's occupied cell centres (the rectangle is then grown by half a cell). A scan
  denser than ``MAX_SCAN_POINTS`` has its points merged on a lattice, and the rectangle
  is grown by ``DistanceField.merge`` (the tolerance then includes twice that). A distance
  field on a raster (``resolution``; :class:`DistanceField`,
  OpenCV's exact Euclidean distance transform, less half a cell) only decides which steps
  need sampling: a step that none of its samples can bring within reach of an obstacle
  (its covering discs farther than the draws' largest displacement, plus two cells for
  the field's own raster error) is 0 without sampling.
* **Uncertainty.** With position covariances the position at each step is Gaussian and
  the heading is the predicted mean heading. With pose covariances (x, y, yaw) are drawn
  jointly, so a turning chair's corner sweep counts. The probability is estimated with
  ``samples`` fixed quasi-random standard-normal draws z [S, 3] (scrambled Sobol points,
  the same for every call, so results are deterministic and smooth in the inputs): sample
  j of step i is ``mean_i + chol(cov_i) z_j`` (closed-form lower Cholesky factor; a 2x2
  covariance uses z's first two columns, so it gives exactly what the 3x3 with a zero
  heading variance gives).
* **Per step and within the horizon.** ``per_step[i]`` is the fraction of samples whose
  footprint touches at step i. ``within`` uses the same draw z_j along the whole path
  (the rollout's errors accumulate, so consecutive steps are strongly correlated): it is
  the fraction of sampled paths that touch at any step. It lies between the two limits
  also returned: ``lower = max_i per_step[i]`` (perfectly dependent steps) and ``upper =
  1 - prod_i (1 - per_step[i])`` (independent steps).
* **The footprint test, two methods.** ``method="exact"`` tests the rectangle
  (``length`` x ``width``, centred ``offset`` ahead of the base frame's origin,
  :class:`Footprint`) of every sample against every obstacle point within reach.
  ``method="raster"`` makes it one lookup per sample, as planners do with
  precomputed footprint cells per heading bin (nav2's Smac planner): the headings are cut
  into bins (``heading_bin``); in the frame of a bin's centre heading, the rectangle swept
  over the bin's headings fits in an axis-aligned box, and the raster cells (``raster``)
  that meet a box placed at any obstacle point are marked (summed-area counts of the box
  corners); a sample touches when its position falls in a marked cell of its heading's
  bin. Rasters cover only each bin's window (where its samples are and a box can be).
* **Tolerance of the raster.** It is conservative and never under-estimates: every
  sample the exact test finds touching is touching for the raster too. A sample it finds
  touching touches the rectangle grown on every side by ``Contact.tolerance`` = sqrt(2)
  cells (the cell holding the sample meets a box) plus the bin's sweep (the farthest a
  point of the box lies from the rectangle at any heading of the bin; the bins are cut to
  the headings actually present, so a single heading sweeps nothing). With the defaults
  (2 mm cells, 0.25 degree bins) that is under 6 mm for a single path. Large batches
  would need more than ``_CELL_BUDGET`` cells: the cell is then coarsened, and wider bins
  are tried and kept when they lower the tolerance; ``Contact.tolerance`` reports what
  applied (2.4 cm for a thousand paths of ten steps near a wall, 3.2 cm with the heading
  sampled; README, Shared control). The exact method reports 0.
* **Which method.** ``method="auto"`` (the default) takes the exact test when the samples
  times the obstacle points in their reach are few (``_EXACT_WORK``: a path or two, where
  the exact test is as fast or faster and a raster would mostly cover empty space) and
  the raster otherwise.
* **Speed.** Everything is vectorised over paths, steps and samples; the only loops run
  over chunks of at most ``_CHUNK`` elements (the exact test: 0.5 MB per intermediate
  array, which bounds a decision's memory and is no slower than larger chunks) or
  ``_BOX_CHUNK`` pairs (the raster's box marking) and over retries of the layout.

REP-117 for scans: ``+inf`` or a range beyond ``range_max`` is no return within range
(free as far as the scan sees); ``-inf`` or a range below ``range_min`` is an object too
close to measure, counted as an obstacle at ``range_min``; ``NaN`` is an erroneous
reading. A scan with no usable beam, or with more than ``max_invalid`` of them NaN, is
refused (:class:`CollisionError`): an empty scan never reads as "clear". A run of NaN beams
counts as an obstacle at the nearer of the returns that bound it
(:func:`erroneous_beam_points`): an erroneous sector is never read as a way through.

Unknown space: a grid's unknown cells (-1) and everything outside a grid count as occupied
by default (``unknown_is_obstacle``); outside a scan's window (``range_max`` around the
scanner) there is no information, and a sample whose footprint centre is there counts as
touching.

Refused (:class:`CollisionError`): paths or covariances with NaN or inf, coordinates beyond
``MAX_COORDINATE`` or covariance entries beyond ``MAX_VARIANCE`` (no prediction of a
wheelchair looks like that), shapes that do not match, paths of zero steps (a
:class:`~asgp_ros.core.online.Prediction` that is not ok has empty arrays: no path is never
"clear").
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple, cast

import numpy as np
import scipy.spatial
import scipy.special
from numpy.typing import NDArray

from asgp_ros.core.unicycle import integrate_path

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["DEFAULT_FOOTPRINT", "CollisionError", "Contact", "DistanceField", "Footprint",
           "Grid", "PathCheck", "Scan", "constant_twist_motion", "contact_probability",
           "footprint_deepening", "grid_check", "inverse_pose", "scan_check"]

#: Sobol points per step (a power of two); the probability resolution is 1 / SAMPLES.
SAMPLES = 256
#: Cell of the footprint raster (m) and width of its heading bins (rad), by default.
RASTER = 0.002
HEADING_BIN = math.radians(0.25)
#: Paths beyond +-MAX_COORDINATE (m, rad) or covariance entries above MAX_VARIANCE are
#: refused (CollisionError): no wheelchair's prediction looks like that.
MAX_COORDINATE = 1e6
MAX_VARIANCE = 1e12
#: Smallest |angle_increment| of a scan (rad): 100,000 beams over two thirds of a turn.
MIN_ANGLE_INCREMENT = 4e-5
#: Cells a side of a scan's distance field, at most (range_max 25 m at 5 cm cells).
MAX_SCAN_FIELD_SIDE = 1024
#: A scan's obstacle points (with what obstacle memory adds), at most: a denser scan (a 3-D
#: lidar flattened at 0.01 degrees gives 36,000 beams) has its points merged on the finest
#: square lattice, from MERGE_START and doubling, that leaves at most this many, and the
#: footprint is grown to keep the test conservative (``DistanceField.merge``). The cost of
#: a test grows with the points in reach: 100,000 beams took 0.19 s for one path.
MAX_SCAN_POINTS = 8192
MERGE_START = 0.002
_CELL_BUDGET = 1 << 21  # raster cells of one call (all heading bins): 8 MB of counts
_PAIR_BUDGET = 1 << 18  # (step, heading bin) pairs of one call: bins widen beyond
_EXACT_WORK = 1 << 22  # method "auto": the exact test up to this many sample-point pairs
_CHUNK = 1 << 16  # elements of an intermediate array of the exact test (0.5 MB of float64)
_BOX_CHUNK = 1 << 22  # (heading bin, point) pairs of the raster's box marking per pass
_EPS_M = 1e-7  # boxes grown by this (m): round-off never turns a contact into a miss
_DEPTH_POSES = 64  # poses per pass of footprint_deepening (each with at most 8192 points in reach)


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
        if abs(self.angle_increment) < MIN_ANGLE_INCREMENT and r.size > 1:
            # 1e-12 put every beam on one bearing: a wall ahead read as clear
            raise CollisionError(f"scan angle_increment {self.angle_increment:g} rad is "
                                 f"below {MIN_ANGLE_INCREMENT:g} (no scanner resolves that)")
        # the beams within a turn or two of the laser's x axis (an angle_min of 1e17 put
        # every beam on one bearing, in float64: a wall ahead read as free)
        span = abs(self.angle_increment) * (r.size - 1)
        if abs(self.angle_min) > 2.0 * math.pi or span > 2.0 * math.pi + 1e-6:
            raise CollisionError(f"scan angles from {self.angle_min:g} rad over {span:g} rad "
                                 "are not within one turn of the laser's axis")


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
        if d.dtype.kind not in "iu" and not (d.dtype.kind == "f" and np.all(d == np.round(d))):
            raise CollisionError(f"grid cells must be whole numbers, got dtype {d.dtype}")
        if d.size and (d.min() < -1 or d.max() > 100):
            # int8 wraps: 256 read as 0 (free), and NaN too
            raise CollisionError(f"grid cells must be -1 (unknown) or 0..100, got "
                                 f"{d.min():g} .. {d.max():g}")
        if d.size > 50_000_000:
            raise CollisionError(f"a grid of {d.size} cells is more than 50 million")
        if not (math.isfinite(self.resolution) and 1e-3 <= self.resolution <= 100.0):
            raise CollisionError(f"grid resolution must be in [0.001, 100] m, got "
                                 f"{self.resolution}")
        if not all(math.isfinite(v) for v in self.origin):
            raise CollisionError("grid origin is not finite")
        object.__setattr__(self, "data", d.astype(np.int8, copy=False))


def scan_points(scan: Scan) -> FloatArray:
    """[m, 2] a scan's obstacle points in its own frame: every beam with a return in
    [range_min, range_max], and a beam too close to measure (-inf, or under range_min) at
    ``range_min`` (REP-117); +inf (nothing in range) and NaN (erroneous) give none."""
    r = scan.ranges
    nan = np.isnan(r)
    angles = scan.angle_min + scan.angle_increment * np.arange(r.size)
    close = (r < scan.range_min) & ~nan  # includes -inf: too close to measure
    hit = close | ((r >= scan.range_min) & (r <= scan.range_max))
    rr = np.where(close, scan.range_min, r)[hit]
    pts: FloatArray = np.stack([rr * np.cos(angles[hit]), rr * np.sin(angles[hit])], axis=1)
    return pts


def erroneous_beam_points(scan: Scan) -> FloatArray:
    """[m, 2] points standing in for a scan's NaN (erroneous) beams, in its own frame.

    A NaN beam says nothing, and an obstacle may stand in its direction (a dark or shiny
    surface, a glass door, a beam lost in the sensor). A run of NaN beams is given the
    nearer of the two returns that bound it (a beam too close to measure counts at
    ``range_min``): an erroneous sector between obstacles is never read as a way through.
    A run bounded on both sides by beams with no return in range (or by the edges of a
    scan that is not a full turn) gives no point: its neighbours see nothing either. A
    full-turn scan's first and last beams are neighbours.

    Only the collision test uses these points; scan matching and the obstacle memory keep
    to the returns (:func:`scan_points`)."""
    r = scan.ranges
    nan = np.isnan(r)
    n = r.size
    if not nan.any() or nan.all():
        return np.empty((0, 2))
    # the range each beam shows an obstacle at: a return, range_min when too close, inf
    # for none in range; NaN kept for the erroneous beams
    shown = np.where(r < scan.range_min, scan.range_min, np.where(r <= scan.range_max, r, np.inf))
    shown[nan] = np.nan
    full_turn = abs(scan.angle_increment) * n >= 2.0 * math.pi - 0.5 * abs(scan.angle_increment)
    reps = 3 if full_turn else 1
    ext = np.tile(shown, reps)
    good = ~np.isnan(ext)
    i = np.arange(ext.size)
    before = np.maximum.accumulate(np.where(good, i, -1))
    after = np.minimum.accumulate(np.where(good, i, ext.size)[::-1])[::-1]
    pad = np.append(ext, np.inf)  # index -1 / ext.size: no neighbour there
    left = np.where(before >= 0, pad[before], np.inf)
    right = np.where(after < ext.size, pad[np.minimum(after, ext.size)], np.inf)
    fill = np.minimum(left, right)[(reps // 2) * n:(reps // 2 + 1) * n]
    use = nan & np.isfinite(fill)
    angles = scan.angle_min + scan.angle_increment * np.flatnonzero(use)
    rr = fill[use]
    pts: FloatArray = np.stack([rr * np.cos(angles), rr * np.sin(angles)], axis=1)
    return pts


def _merged(pts: FloatArray) -> tuple[FloatArray, float]:
    """At most MAX_SCAN_POINTS points: ``pts`` themselves, or the centres of the cells of
    the finest lattice (MERGE_START, doubling) that they occupy; and how far (m) any of
    ``pts`` lies from the point that stands for it (half a cell's diagonal)."""
    if pts.shape[0] <= MAX_SCAN_POINTS:
        return pts, 0.0
    q = MERGE_START
    while True:
        ij = np.floor(pts / q).astype(np.int64)
        low = ij.min(axis=0)
        ij -= low
        rows = int(ij[:, 1].max()) + 1
        keys = np.unique(ij[:, 0] * rows + ij[:, 1])  # one int64 a cell: a 1-D sort
        if keys.size <= MAX_SCAN_POINTS:
            cells = np.stack([keys // rows, keys % rows], axis=1) + low
            centres: FloatArray = (cells + 0.5) * q
            return centres, q * math.sqrt(0.5)
        q *= 2.0


#: OpenCV's distance d (cells) is taken as d - slack (1 + d): its float32 values lie within
#: 1e-7 of the exact Euclidean distance, relatively (measured against scipy's transform,
#: rasters up to 3,000 cells a side), so that none then overstates it.
_EDT_SLACK = 1e-6


@functools.cache
def _opencv() -> Any:
    """OpenCV's module, or None where it is not installed (the core needs numpy and scipy
    alone; the package installs OpenCV for its VO, and the distance fields use it when it
    is there). Imported at the first field, not with this module."""
    try:
        import cv2
    except ImportError:
        return None
    return cv2


def _distances(mask: NDArray[np.bool_], res: float) -> FloatArray:
    """Distance (m) from every cell centre to the nearest obstacle cell, less half a cell
    (so it never overstates a clearance); inf without obstacles.

    OpenCV's exact Euclidean transform (``DIST_MASK_PRECISE``, Felzenszwalb and
    Huttenlocher's algorithm): the distances ``scipy.ndimage.distance_transform_edt`` gives,
    to float32 rounding (the slack below), without its index arrays (two int64 per cell);
    a scan's whole field in under half the time (``benchmarks/shared_control.py``). Without
    OpenCV, scipy's transform itself."""
    if not mask.any():
        return np.full(mask.shape, math.inf)
    cv2 = _opencv()
    if cv2 is None:
        import scipy.ndimage

        out: FloatArray = np.asarray(scipy.ndimage.distance_transform_edt(~mask),
                                     dtype=np.float64)
        slack = 0.0  # exact
    else:
        free = np.ascontiguousarray(~mask).view(np.uint8)  # 1 free, 0 obstacle
        out = np.asarray(cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE),
                         dtype=np.float64)
        slack = _EDT_SLACK
    # (d - slack (1 + d) - 1/2) res, in place
    out *= (1.0 - slack) * res
    out -= (0.5 + slack) * res
    return np.maximum(out, 0.0, out=out)


def _pose_matrix(pose: tuple[float, float, float]) -> tuple[FloatArray, FloatArray]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s], [s, c]]), np.array([pose[0], pose[1]], dtype=np.float64)


def inverse_pose(pose: tuple[float, float, float]) -> tuple[float, float, float]:
    """The inverse of a planar transform (x, y, yaw)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    x, y = pose[0], pose[1]
    return (-(c * x + s * y), s * x - c * y, -pose[2])


def constant_twist_motion(v: float, w: float, dt: float) -> tuple[float, float, float]:
    """The pose (x, y, yaw) after ``dt`` seconds at the constant twist (v, w), in the frame
    of the start (``dt`` < 0: the pose ``-dt`` seconds before, in the frame of now); as the
    trapezoidal unicycle integrates it (:func:`asgp_ros.core.unicycle.integrate_path`).
    Moves a scan stamped at t_s into the frame of a prediction at t0: dt = t0 - t_s."""
    if abs(dt) < 1e-9:
        return (0.0, 0.0, 0.0)
    end = integrate_path(np.array([[v, w], [v, w]]), abs(dt))[-1]
    pose = (float(end[0]), float(end[1]), float(end[2]))
    return pose if dt > 0.0 else inverse_pose(pose)


@dataclass(frozen=True)
class DistanceField:
    """Distance (m) to the nearest obstacle on a raster, in the field's frame.

    ``dist[iy, ix]`` is the clearance at the centre of cell (ix, iy), whose centre is at
    ``origin + R(yaw) ((ix + 0.5) res, (iy + 0.5) res)``. ``outside`` 0: off the raster
    counts as touching; otherwise every obstacle point lies on the raster, and off it the
    clearance is at least the distance to the raster's edge.
    """

    dist: FloatArray
    resolution: float
    origin: tuple[float, float, float]
    points: FloatArray  # [m, 2] obstacle points in the field's frame
    grow: float = 0.0  # the footprint is grown by this for the exact test (half a cell)
    outside: float = 0.0
    # every obstacle point of the source lies within this (m) of one of ``points`` (a dense
    # scan's points merged on a lattice, MAX_SCAN_POINTS); the footprint is grown by it
    merge: float = 0.0
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
    def from_scan(scan: Scan, resolution: float = 0.05, max_invalid: float = 0.5,
                  extra: FloatArray | None = None) -> DistanceField:
        """The field of a scan's obstacles in its own frame, over ``range_max`` around it.

        ``extra`` [m, 2]: more obstacle points in the scan's frame (what an
        :class:`~asgp_ros.core.obstacle_memory.ScanMemory` remembers outside the scan's
        view); those farther than ``range_max`` from the scanner are left out, as the
        window ends there (beyond it everything counts as touching).

        The raster has at most :data:`MAX_SCAN_FIELD_SIDE` cells a side: a long-range scan
        gets coarser cells (the pruning's margins grow with them; the footprint tests use
        the points themselves), never gigabytes of raster."""
        if not (isinstance(resolution, int | float) and 1e-3 <= resolution <= 10.0):
            raise CollisionError(f"resolution must be in [0.001, 10] m, got {resolution}")
        if not (isinstance(max_invalid, int | float) and 0.0 <= max_invalid <= 1.0):
            raise CollisionError(f"max_invalid must be in [0, 1], got {max_invalid}")
        nan = np.isnan(scan.ranges)
        if nan.all() or nan.mean() > max_invalid:
            raise CollisionError(f"scan has {int(nan.sum())} of {nan.size} beams NaN "
                                 "(erroneous): it cannot show the way is clear")
        pts = np.concatenate([scan_points(scan), erroneous_beam_points(scan)])
        resolution = max(resolution, 2.0 * scan.range_max / (MAX_SCAN_FIELD_SIDE - 4))
        half = scan.range_max + 2 * resolution
        if extra is not None and extra.shape[0]:
            extra = np.asarray(extra, dtype=np.float64).reshape(-1, 2)
            if not np.all(np.isfinite(extra)) or np.abs(extra).max() > MAX_COORDINATE:
                raise CollisionError("extra obstacle points must be finite and within "
                                     f"{MAX_COORDINATE:g} m")
            pts = np.concatenate([pts, extra[np.hypot(extra[:, 0], extra[:, 1])
                                             <= scan.range_max]])
        pts, merge = _merged(pts)
        n = math.ceil(2 * half / resolution)
        origin = (-half, -half, 0.0)
        mask = np.zeros((n, n), dtype=bool)
        ij = np.floor((pts - np.array(origin[:2])) / resolution).astype(np.int64)
        np.clip(ij, 0, n - 1, out=ij)  # a merged point may sit half a lattice cell out
        mask[ij[:, 1], ij[:, 0]] = True  # every point is inside the window
        return DistanceField(_distances(mask, resolution), resolution, origin, pts, 0.0, 0.0,
                             merge)

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
        """[..., 2] points in the field's frame -> [...] clearance (bilinear on the raster;
        off it 0, or the distance to its edge: class docstring)."""
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
        if self.outside == 0.0:
            return np.where(inside, out, 0.0)
        size = np.array([w, h]) * self.resolution
        beyond = np.maximum(np.maximum(-local, local - size), 0.0)  # [..., 2]
        return np.where(inside, out, np.hypot(beyond[..., 0], beyond[..., 1]))


class Contact(NamedTuple):
    """Probabilities of contact: ``per_step`` [B, k]; within the horizon ``within`` [B]
    (the sampled paths), with its limits ``lower`` [B] and ``upper`` [B]; ``tolerance``
    (m): a sample counted as touching touches with the footprint grown by this much on
    every side (0 for the exact test; module docstring)."""

    per_step: FloatArray
    within: FloatArray
    lower: FloatArray
    upper: FloatArray
    tolerance: float = 0.0


_NORMAL_DRAWS: dict[int, FloatArray] = {}


def _draws(samples: int) -> FloatArray:
    """[samples, 3] fixed standard-normal draws (scrambled Sobol, seed 0): columns 0 and 1
    move the position, column 2 only the heading (through a lower Cholesky factor)."""
    if samples not in _NORMAL_DRAWS:
        from scipy.stats import qmc  # at the first draw: scipy.stats takes 0.4 s to import

        sobol = qmc.Sobol(d=3, scramble=True, seed=0).random(samples)
        _NORMAL_DRAWS[samples] = scipy.special.ndtri(np.clip(sobol, 1e-12, 1 - 1e-12))
    return _NORMAL_DRAWS[samples]


def prepare(samples: int = SAMPLES) -> None:
    """Load now what the first check would load: OpenCV (where it is installed) and the
    Sobol draws of ``samples`` per step (scipy.stats' import, about 0.4 s). A node calls it
    at start-up, so that its first decision is not the slow one."""
    _opencv()
    _draws(samples)


def _chol3(cov: FloatArray) -> FloatArray:
    """[..., 3, 3] (or [..., 2, 2], padded with a zero heading) PSD -> [..., 3, 3] lower
    Cholesky factors in closed form. A negative round-off variance or Schur complement is
    clipped to 0 and each off-diagonal entry to the magnitude a PSD matrix allows, so a
    singular or slightly indefinite covariance still gives finite factors."""
    n = cov.shape[-1]
    sym = 0.5 * (cov + np.swapaxes(cov, -1, -2))

    def entry(i: int, j: int) -> FloatArray:
        if i < n and j < n:
            return np.asarray(sym[..., i, j])
        return np.zeros(cov.shape[:-2])

    def ratio(num: FloatArray, den: FloatArray, bound: FloatArray) -> FloatArray:
        out = np.divide(num, den, out=np.zeros_like(num), where=den > 0.0)
        return np.clip(out, -bound, bound)

    a00, a11, a22 = (np.maximum(entry(i, i), 0.0) for i in range(3))
    l00 = np.sqrt(a00)
    l10 = ratio(entry(1, 0), l00, np.sqrt(a11))
    l20 = ratio(entry(2, 0), l00, np.sqrt(a22))
    l11 = np.sqrt(np.maximum(a11 - l10**2, 0.0))
    l21 = ratio(entry(2, 1) - l20 * l10, l11, np.sqrt(np.maximum(a22 - l20**2, 0.0)))
    l22 = np.sqrt(np.maximum(a22 - l20**2 - l21**2, 0.0))
    L = np.zeros((*cov.shape[:-2], 3, 3))
    L[..., 0, 0], L[..., 1, 0], L[..., 1, 1] = l00, l10, l11
    L[..., 2, 0], L[..., 2, 1], L[..., 2, 2] = l20, l21, l22
    return L


class _Rect(NamedTuple):
    """The footprint rectangle in the base frame, grown for the field (``fld.grow``)."""

    x_lo: float
    x_hi: float
    half_w: float

    @property
    def reach(self) -> float:
        """Distance of its farthest corner from the base frame's origin."""
        return math.hypot(max(abs(self.x_lo), abs(self.x_hi)), self.half_w)


class _Samples(NamedTuple):
    """The samples of the near steps: n steps, S draws each (field frame)."""

    mu: FloatArray  # [n, 2] mean positions
    theta: FloatArray  # [n] mean headings
    L: FloatArray  # [n, 3, 3] Cholesky factors of (x, y, theta)
    z: FloatArray  # [S, 3] standard-normal draws
    half: FloatArray  # [n, 2] half-extent of the position samples around mu (x, y)
    turn: FloatArray  # [n] largest heading offset of a sample (rad); 0: the mean heading

    def positions(self, rows: slice | NDArray[np.intp] = slice(None)
                  ) -> tuple[FloatArray, FloatArray]:
        """([n, S] x, [n, S] y) of the samples (of ``rows``)."""
        L, mu, z = self.L[rows], self.mu[rows], self.z
        px = mu[:, :1] + L[:, 0, :1] * z[None, :, 0]
        py = mu[:, 1:] + L[:, 1, :1] * z[None, :, 0] + L[:, 1, 1:2] * z[None, :, 1]
        return px, py

    def headings(self, rows: slice | NDArray[np.intp] = slice(None)) -> FloatArray:
        """[n, S] headings of the samples (of ``rows``)."""
        L = self.L[rows]
        return np.asarray(self.theta[rows][:, None] + L[:, 2, :] @ self.z.T)


def _reach_radii(rect: _Rect, smp: _Samples) -> FloatArray:
    """[n] radius around each step's mean position holding every sample's footprint."""
    radii: FloatArray = rect.reach + np.hypot(smp.half[:, 0], smp.half[:, 1]) + 1e-9
    return radii


def _exact_work(fld: DistanceField, rect: _Rect, smp: _Samples) -> float:
    """Sample-point pairs the exact test would start from (inf when clearly many)."""
    S = int(smp.z.shape[0])
    if fld._tree is None:  # no obstacle point
        return 0.0
    if smp.mu.shape[0] * S > _EXACT_WORK:
        return math.inf
    counts = fld._tree.query_ball_point(smp.mu, _reach_radii(rect, smp), return_length=True)
    return float(np.sum(counts)) * S


def _exact_touch(fld: DistanceField, rect: _Rect, smp: _Samples) -> BoolArray:
    """[n, S] exact footprint test of every sample against the obstacle points within
    reach of its step (a CSR gather of the neighbours, all steps at once in chunks).

    A point is first placed in the frame of its step's mean pose: one that every sample's
    footprint holds (inside the rectangle shrunk by the samples' largest displacement)
    decides the step, one that none can reach is dropped, and only the rest is tested
    sample by sample."""
    n, S = smp.mu.shape[0], smp.z.shape[0]
    touch = np.zeros((n, S), dtype=bool)
    found = fld.neighbours(smp.mu, _reach_radii(rect, smp))
    counts = np.fromiter((len(f) for f in found), dtype=np.intp, count=n)
    if not counts.any():
        return touch
    step = np.repeat(np.arange(n), counts)  # [m] pairs (step, point)
    o = fld.points[np.fromiter(itertools.chain.from_iterable(found), dtype=np.intp,
                               count=int(counts.sum()))]
    c, s = np.cos(smp.theta), np.sin(smp.theta)
    dx, dy = o[:, 0] - smp.mu[step, 0], o[:, 1] - smp.mu[step, 1]
    qx = c[step] * dx + s[step] * dy  # R(theta)^T (o - mu)
    qy = c[step] * dy - s[step] * dx
    # a sample moves the point by at most its displacement plus |q| times its turn
    shift = (np.hypot(smp.half[step, 0], smp.half[step, 1])
             + np.hypot(qx, qy) * np.minimum(smp.turn[step], 2.0) + 1e-9)
    sure = ((qx >= rect.x_lo + shift) & (qx <= rect.x_hi - shift)
            & (np.abs(qy) <= rect.half_w - shift))
    touch[step[sure]] = True
    band = ~touch[step, 0] & (qx >= rect.x_lo - shift) & (qx <= rect.x_hi + shift) & (
        np.abs(qy) <= rect.half_w + shift)
    step, o = step[band], o[band]
    if not step.size:
        return touch
    steps, first = np.unique(step, return_index=True)
    first = np.append(first, step.size)
    per_chunk = max(1, _CHUNK // S)
    one_heading = not np.any(smp.turn)
    lo = 0
    while lo < steps.size:  # chunks of whole steps of at most _CHUNK pair-samples
        hi = max(lo + 1, int(np.searchsorted(first, first[lo] + per_chunk, side="right")) - 1)
        rows = steps[lo:hi]
        a, b = first[lo], first[hi]
        local = np.searchsorted(rows, step[a:b])  # [m'] row of each pair in the chunk
        px, py = smp.positions(rows)  # [r, S]
        if one_heading:
            cr, sr = c[rows, None], s[rows, None]
        else:
            th = smp.headings(rows)
            cr, sr = np.cos(th), np.sin(th)
        ex = cr * px + sr * py  # samples and points in the sample's heading frame
        ey = cr * py - sr * px
        ox, oy = o[a:b, :1], o[a:b, 1:]
        qx, qy = ex[local], ey[local]  # [m', S], then R(theta)^T (o - p) in place
        if one_heading:
            cp, sp = c[step[a:b], None], s[step[a:b], None]
            np.subtract(cp * ox + sp * oy, qx, out=qx)
            np.subtract(cp * oy - sp * ox, qy, out=qy)
        else:
            cp, sp = cr[local], sr[local]
            qx = np.subtract(cp * ox + sp * oy, qx, out=qx)
            qy = np.subtract(cp * oy - sp * ox, qy, out=qy)
        np.abs(qy, out=qy)
        hit = qx >= rect.x_lo
        hit &= qx <= rect.x_hi
        hit &= qy <= rect.half_w
        touch[rows] |= np.logical_or.reduceat(hit, first[lo:hi] - a, axis=0)
        lo = hi
    return touch


def _swept_box(rect: _Rect, delta: FloatArray) -> FloatArray:
    """[nb, 4] (x_lo, x_hi, y_lo, y_hi): a box holding the rectangle rotated by every angle
    within +-delta [nb] (corner (x, y) rotated by a: x cos a - y sin a <= max(x, x cos d)
    + |y| sin d, and likewise for y), grown by ``_EPS_M``."""
    sd, cd = np.sin(delta), np.cos(delta)
    ax = max(abs(rect.x_lo), abs(rect.x_hi))
    w = rect.half_w
    return np.stack([
        np.minimum(rect.x_lo, rect.x_lo * cd) - w * sd - _EPS_M,
        np.maximum(rect.x_hi, rect.x_hi * cd) + w * sd + _EPS_M,
        -w - ax * sd - _EPS_M,
        w + ax * sd + _EPS_M,
    ], axis=1)


class _Plan(NamedTuple):
    """The heading bins and the raster's layout of one call (:func:`_raster_plan`)."""

    nb: int  # bins around the circle
    width: float  # of a bin (rad)
    b_lo: NDArray[np.int64]  # [n] first and last unwrapped bin of each step
    b_hi: NDArray[np.int64]
    lut: NDArray[np.intp]  # [nb] bin -> used bin
    cos: FloatArray  # [nu] cos and sin of each used bin's centre heading
    sin: FloatArray
    delta: FloatArray  # [nu] half the span of headings in the bin
    box: FloatArray  # [nu, 4] the footprint swept over the bin (_swept_box)
    cell: float  # (m)
    origin: FloatArray  # [nu, 2] (u, v) of each window's first cell, in the bin's frame
    size: NDArray[np.int64]  # [nu, 2] cells of each window (0: nothing to touch)
    row: NDArray[np.int64]  # [nu + 1] first row of each block in the shared array
    wc: int  # columns of the shared array
    sweep: float  # (m) the part of the tolerance due to the heading bins

    @property
    def tolerance(self) -> float:
        """(m) a touching sample touches the footprint grown by this (module docstring),
        before the round-off margin."""
        return math.sqrt(2.0) * self.cell + self.sweep


def _support_points(pts: FloatArray) -> FloatArray:
    """The points of ``pts`` [m, 2] that can be extreme in some direction: the vertices of
    their convex hull (Qhull, in double precision), or all of them when the hull is
    degenerate (fewer than three points, all on a line). The extent of the points along any
    direction is the extent of these; :func:`_raster_plan` widens it by _EPS_M for the
    round-off of a point Qhull took for one on an edge."""
    if pts.shape[0] <= 8:
        return pts
    try:
        hull = scipy.spatial.ConvexHull(pts)
    except (scipy.spatial.QhullError, ValueError):
        return pts
    out: FloatArray = pts[hull.vertices]
    return out


def _raster_plan(pts: FloatArray, support: FloatArray, rect: _Rect, smp: _Samples,
                 cell: float, nb: int) -> _Plan:
    """The heading bins reached by the samples (``nb`` around the circle, fewer when the
    (step, bin) pairs would exceed their budget), and for each a window in its frame:
    where its samples are and a box of an obstacle point in ``pts`` can be (found from
    ``support``, their :func:`_support_points`). ``cell`` is coarsened when the windows
    would exceed the cell budget."""
    n = smp.mu.shape[0]
    # bins reached by each step: its headings span theta +- turn (unwrapped bin numbers)
    th_lo, th_hi = smp.theta - smp.turn, smp.theta + smp.turn
    while True:
        width = 2.0 * math.pi / nb
        b_lo = np.floor(th_lo / width).astype(np.int64)
        b_hi = np.floor(th_hi / width).astype(np.int64)
        full = b_hi - b_lo + 1 >= nb
        count = np.where(full, nb, b_hi - b_lo + 1)
        if nb <= 2 or int(count.sum()) <= max(_PAIR_BUDGET, 2 * n):
            break
        nb = max(2, nb // 2)
    step = np.repeat(np.arange(n), count)  # [pairs]: (step, bin) pairs
    first = np.repeat(np.cumsum(count) - count, count)
    ub = b_lo[step] + (np.arange(step.size) - first)  # unwrapped bin of the pair
    rel_lo = np.where(full[step], 0.0, np.maximum(th_lo[step], ub * width) - ub * width)
    rel_hi = np.where(full[step], width,
                      np.minimum(th_hi[step], (ub + 1) * width) - ub * width)
    pair_mod = np.mod(ub, nb)
    used = np.flatnonzero(np.bincount(pair_mod, minlength=nb))
    nu = used.size
    lut = np.zeros(nb, dtype=np.intp)
    lut[used] = np.arange(nu)
    pair_bin = lut[pair_mod]
    lo = np.full(nu, np.inf)
    hi = np.full(nu, -np.inf)
    np.minimum.at(lo, pair_bin, rel_lo)
    np.maximum.at(hi, pair_bin, rel_hi)
    phi = used * width + 0.5 * (lo + hi)  # [nu] centre heading of each used bin
    delta = 0.5 * (hi - lo) + 1e-12  # [nu] half the headings' span in the bin
    box = _swept_box(rect, delta)  # [nu, 4]
    cb, sb = np.cos(phi), np.sin(phi)

    # the samples' extent in each bin's frame (u = R(phi)^T p)
    cp, sp = cb[pair_bin], sb[pair_bin]
    cu = cp * smp.mu[step, 0] + sp * smp.mu[step, 1]
    cv = cp * smp.mu[step, 1] - sp * smp.mu[step, 0]
    hx, hy = smp.half[step, 0], smp.half[step, 1]
    hu = np.abs(cp) * hx + np.abs(sp) * hy + _EPS_M
    hv = np.abs(sp) * hx + np.abs(cp) * hy + _EPS_M
    win = np.empty((nu, 4))
    win[:, 0], win[:, 2] = np.inf, np.inf
    win[:, 1], win[:, 3] = -np.inf, -np.inf
    np.minimum.at(win[:, 0], pair_bin, cu - hu)
    np.maximum.at(win[:, 1], pair_bin, cu + hu)
    np.minimum.at(win[:, 2], pair_bin, cv - hv)
    np.maximum.at(win[:, 3], pair_bin, cv + hv)
    # ... cut to where a box can be: the points' extent in each bin's frame, less the box
    for rows in _chunks(nu, support.shape[0]):
        ou = cb[rows, None] * support[None, :, 0] + sb[rows, None] * support[None, :, 1]
        ov = cb[rows, None] * support[None, :, 1] - sb[rows, None] * support[None, :, 0]
        win[rows, 0] = np.maximum(win[rows, 0], ou.min(axis=1) - _EPS_M - box[rows, 1])
        win[rows, 1] = np.minimum(win[rows, 1], ou.max(axis=1) + _EPS_M - box[rows, 0])
        win[rows, 2] = np.maximum(win[rows, 2], ov.min(axis=1) - _EPS_M - box[rows, 3])
        win[rows, 3] = np.minimum(win[rows, 3], ov.max(axis=1) + _EPS_M - box[rows, 2])
    empty = (win[:, 1] < win[:, 0]) | (win[:, 3] < win[:, 2]) | (pts.shape[0] == 0)

    # the layout: block b holds rows [row[b], row[b] + H_b + 2) of a [rows, wc] array;
    # cells 1..W_b x 1..H_b are the window, row/column 0 and W_b + 1 / H_b + 1 stay 0
    safe = np.where(empty[:, None], 0.0, win)
    while True:
        origin = np.floor(safe[:, [0, 2]] / cell) * cell
        size = (np.floor((safe[:, [1, 3]] - origin) / cell) + 1).astype(np.int64)
        size[empty] = 0
        wc = int(size[:, 0].max()) + 2
        row = np.concatenate([[0], np.cumsum(size[:, 1] + 2)])
        if int(row[-1]) * wc <= _CELL_BUDGET:
            break
        cell *= 1.05 * math.sqrt(int(row[-1]) * wc / _CELL_BUDGET)  # a coarser raster
    sweep = float(_sweep_tolerance(rect, box, delta).max()) if nu else 0.0
    return _Plan(nb, width, b_lo, b_hi, lut, cb, sb, delta, box, cell, origin, size, row, wc,
                 sweep)


def _chunks(nu: int, m: int) -> list[NDArray[np.intp]]:
    """Bins in chunks of at most _BOX_CHUNK (bin, point) pairs; none without points."""
    per = max(1, _BOX_CHUNK // max(m, 1))
    return [np.arange(a, min(a + per, nu)) for a in range(0, nu, per)] if m else []


def _summed_area(diff: NDArray[np.float32]) -> NDArray[np.float32]:
    """[h, w] -> [h + 1, w + 1] summed-area table (zero first row and column), in float32:
    ``cv2.integral``, or numpy's running sums without OpenCV. The entries are whole numbers
    (+1/-1 marks and their sums), exact in float32 either way."""
    cv2 = _opencv()
    if cv2 is not None:
        return cast(NDArray[np.float32], cv2.integral(diff, sdepth=cv2.CV_32F))
    out = np.zeros((diff.shape[0] + 1, diff.shape[1] + 1), dtype=np.float32)
    np.cumsum(diff, axis=0, out=out[1:, 1:])
    np.cumsum(out[1:, 1:], axis=1, out=out[1:, 1:])
    return out


def _boxes(pts: FloatArray, cb: FloatArray, sb: FloatArray, box: FloatArray
           ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """[r, m] extent (u0, u1, v0, v1) of the box at each point ``pts`` [m, 2], in the
    frames of r bins (``cb``, ``sb`` [r], ``box`` [r, 4]): a sample at (u, v) of a bin can
    touch point o only if u0 <= u <= u1 and v0 <= v <= v1 (u0 = o_u - box x_hi...)."""
    ou = cb[:, None] * pts[None, :, 0] + sb[:, None] * pts[None, :, 1]
    ov = cb[:, None] * pts[None, :, 1] - sb[:, None] * pts[None, :, 0]
    return ou - box[:, 1:2], ou - box[:, 0:1], ov - box[:, 3:4], ov - box[:, 2:3]


def _raster_touch(fld: DistanceField, rect: _Rect, smp: _Samples, cell: float,
                  heading_bin: float) -> tuple[BoolArray, float]:
    """[n, S] conservative footprint test by one lookup per sample, and its tolerance (m).

    The headings are cut into bins of ``heading_bin``; for each bin that holds a sample, the
    obstacle points are expressed in the frame of the bin's centre heading, where the
    footprint swept over the bin's headings (:func:`_swept_box`) is an axis-aligned box,
    and every raster cell that meets a box placed at an obstacle point is marked (+1/-1 at
    each box's corners, then a summed-area table). A sample touches when its position
    falls in a marked cell of its heading's bin. All bins share one array (blocks of rows
    with zero borders), built in one pass and read in one gather.

    Budgets: when the windows would need more than _CELL_BUDGET cells at ``cell``, the
    cell grows; then wider heading bins (fewer windows, a larger sweep) are tried, and
    kept while they give a smaller tolerance.
    """
    n = smp.mu.shape[0]
    # obstacle points that any sample's footprint can reach (field frame)
    reach = rect.reach + _EPS_M
    ext_lo = (smp.mu - smp.half).min(axis=0) - reach
    ext_hi = (smp.mu + smp.half).max(axis=0) + reach
    pts = fld.points[np.all((fld.points >= ext_lo) & (fld.points <= ext_hi), axis=1)]
    m = pts.shape[0]
    support = _support_points(pts)
    plan = _raster_plan(pts, support, rect, smp, cell,
                        max(1, math.ceil(2.0 * math.pi / heading_bin - 1e-9)))
    while plan.cell > 1.5 * cell and plan.nb > 2:
        wider = _raster_plan(pts, support, rect, smp, cell, plan.nb // 2)
        if wider.tolerance >= plan.tolerance:
            break
        plan = wider
    p = plan
    cell, nb, width, wc, row = p.cell, p.nb, p.width, p.wc, p.row
    nx, ny = p.size[:, 0], p.size[:, 1]

    # the samples' cells (u = c x + s y, v = c y - s x in cells, x = mu_x + L00 z0,
    # y = mu_y + L10 z0 + L11 z1; +2: the window's border and the summed-area table's row)
    c_, s_ = p.cos / cell, p.sin / cell
    a_u, a_v = 2.0 - p.origin[:, 0] / cell, 2.0 - p.origin[:, 1] / cell
    top = (p.size + 2).astype(np.float64)  # [nu, 2] far borders
    L, mu, z = smp.L, smp.mu, smp.z
    one_bin = not np.any(smp.turn)  # one heading per step: one bin per step, one product
    if one_bin:
        ib = p.lut[np.mod(np.floor(smp.theta / width).astype(np.int64), nb)]
        c, s = c_[ib], s_[ib]
        coef = np.empty((n, 2, 3))  # rows u, v; columns 1, z0, z1
        coef[:, 0, 0] = c * mu[:, 0] + s * mu[:, 1] + a_u[ib]
        coef[:, 0, 1] = c * L[:, 0, 0] + s * L[:, 1, 0]
        coef[:, 0, 2] = s * L[:, 1, 1]
        coef[:, 1, 0] = c * mu[:, 1] - s * mu[:, 0] + a_v[ib]
        coef[:, 1, 1] = c * L[:, 1, 0] - s * L[:, 0, 0]
        coef[:, 1, 2] = c * L[:, 1, 1]
        mag = float(np.abs(coef[..., 0]).max() + (np.abs(coef[..., 1:]) @ np.abs(z[:, :2])
                                                   .max(axis=0)).max())
    else:
        mag = float((np.abs(mu) + smp.half).max() / cell * 2.0
                    + max(np.abs(a_u).max(), np.abs(a_v).max()))
    # round-off of the samples' cells (float32 when small): the boxes are grown by it
    single = one_bin and mag < 2.0**15
    pad = mag * (2.0**-20 if single else 2.0**-48) + 1e-9

    # mark the cells each box meets: +1/-1 at its corners, then the summed-area table
    # (entry (r + 1, c + 1) sums rows <= r, columns <= c: the cover count)
    diff = np.zeros((int(row[-1]), wc), dtype=np.float32)
    flat_diff = diff.reshape(-1)
    for rows in _chunks(p.cos.size, m):
        rows = rows[p.size[rows, 0] > 0]
        if not rows.size:
            continue
        u0, u1, v0, v1 = _boxes(pts, p.cos[rows], p.sin[rows], p.box[rows])
        ou, ov = p.origin[rows, :1], p.origin[rows, 1:]
        x0 = np.floor((u0 - ou) / cell - pad).astype(np.int64) + 1
        x1 = np.floor((u1 - ou) / cell + pad).astype(np.int64) + 1
        y0 = np.floor((v0 - ov) / cell - pad).astype(np.int64) + 1
        y1 = np.floor((v1 - ov) / cell + pad).astype(np.int64) + 1
        W, H = nx[rows, None], ny[rows, None]
        keep = (x1 >= 1) & (x0 <= W) & (y1 >= 1) & (y0 <= H)
        bi = np.broadcast_to(row[rows, None], keep.shape)[keep]
        W, H = np.broadcast_to(W, keep.shape)[keep], np.broadcast_to(H, keep.shape)[keep]
        x0, x1 = np.maximum(x0[keep], 1), np.minimum(x1[keep], W) + 1
        y0, y1 = np.maximum(y0[keep], 1), np.minimum(y1[keep], H) + 1
        np.add.at(flat_diff, np.concatenate([(bi + y0) * wc + x0, (bi + y1) * wc + x1]),
                  np.float32(1.0))
        np.add.at(flat_diff, np.concatenate([(bi + y0) * wc + x1, (bi + y1) * wc + x0]),
                  np.float32(-1.0))
    covered = _summed_area(diff).reshape(-1)  # cover counts
    stride = np.int32(wc + 1)

    # one lookup per sample: its cell in its heading's bin
    if one_bin:
        dtype = np.float32 if single else np.float64
        ones_z = np.concatenate([np.ones((z.shape[0], 1)), z[:, :2]], axis=1).T
        g = (coef.reshape(2 * n, 3).astype(dtype) @ ones_z.astype(dtype)).reshape(n, 2, -1)
        np.clip(g, 1.0, top[ib].astype(dtype)[:, :, None], out=g)
        cells = g.astype(np.int32)
        flat = cells[:, 1] * stride + cells[:, 0] + (row[ib] * stride).astype(
            np.int32)[:, None]
    else:  # a bin per sample
        # x, y and heading / bin width of every sample in one product (rows 1, z0, z1, z2);
        # the steps' heading ranges have slack for the round-off of the bins' numbers
        A = np.zeros((n, 3, 4))
        A[:, 0, 0], A[:, 1, 0], A[:, 2, 0] = mu[:, 0], mu[:, 1], smp.theta / width
        A[:, :2, 1:] = L[:, :2, :]
        A[:, 2, 1:] = L[:, 2, :] / width
        ones_z = np.concatenate([np.ones((z.shape[0], 1)), z], axis=1).T
        D = (A.reshape(3 * n, 4) @ ones_z).reshape(n, 3, -1)  # [n, 3, S]
        px, py = D[:, 0], D[:, 1]
        k = np.floor(D[:, 2], out=D[:, 2])  # unwrapped bin numbers
        first_bin, span = int(p.b_lo.min()), int(p.b_hi.max() - p.b_lo.min()) + 1
        if span <= 8 * nb:  # a table over the unwrapped bins: no modulo per sample
            k -= first_bin
            ib2 = p.lut[np.mod(np.arange(first_bin, first_bin + span), nb)][k.astype(np.intp)]
        else:
            ib2 = p.lut[np.mod(k.astype(np.int64), nb)]  # [n, S]
        c, s = np.take(c_, ib2), np.take(s_, ib2)  # (take: faster than indexing)
        gu = c * px
        gu += s * py
        gu += np.take(a_u, ib2)
        gv = c * py
        gv -= s * px
        gv += np.take(a_v, ib2)
        np.minimum(gu, np.take(top[:, 0], ib2), out=gu)
        np.maximum(gu, 1.0, out=gu)
        np.minimum(gv, np.take(top[:, 1], ib2), out=gv)
        np.maximum(gv, 1.0, out=gv)
        flat = gv.astype(np.int32)
        flat += np.take(row.astype(np.int32), ib2)
        flat *= stride
        flat += gu.astype(np.int32)
    touch: BoolArray = covered[flat] > 0.5
    return touch, math.sqrt(2.0) * cell * (1.0 + pad) + p.sweep


def _sweep_tolerance(rect: _Rect, box: FloatArray, delta: FloatArray) -> FloatArray:
    """[nb] farthest a point of ``box`` [nb, 4] lies from the rectangle rotated by any
    angle within +-``delta`` [nb] (m). Distance to a convex set is convex, so the farthest
    point is a corner; the angle is scanned on 33 values, and what lies between them adds
    at most |corner| * the half-spacing."""
    a = np.linspace(-1.0, 1.0, 33)[None, :] * delta[:, None]  # [nb, A]
    corners = np.stack([box[:, [0, 0, 1, 1]], box[:, [2, 3, 2, 3]]], axis=-1)  # [nb, 4, 2]
    c, s = np.cos(a)[:, None, :], np.sin(a)[:, None, :]
    x = c * corners[..., :1] + s * corners[..., 1:]  # R(-a) corner, [nb, 4, A]
    y = c * corners[..., 1:] - s * corners[..., :1]
    dx = np.maximum(np.maximum(rect.x_lo - x, x - rect.x_hi), 0.0)
    dy = np.maximum(np.abs(y) - rect.half_w, 0.0)
    gap = np.linalg.norm(corners, axis=-1).max(axis=1) * delta / 32.0
    far: FloatArray = np.hypot(dx, dy).max(axis=(1, 2)) + gap
    return far


def _check_inputs(pose: FloatArray, cov: FloatArray,
                  transform: tuple[float, float, float]) -> tuple[FloatArray, FloatArray]:
    P = np.asarray(pose, dtype=np.float64)
    C = np.asarray(cov, dtype=np.float64)
    if P.ndim == 2:
        P, C = P[None], C[None]
    d = C.shape[-1] if C.ndim else 0
    if P.ndim != 3 or P.shape[-1] != 3 or d not in (2, 3) or C.shape != (*P.shape[:2], d, d):
        raise CollisionError(f"paths must be [B, k, 3] with covariances [B, k, 2, 2] or "
                             f"[B, k, 3, 3], got {P.shape} and {C.shape}")
    if P.shape[1] == 0:  # a not-ok Prediction's empty path: no steps never read as clear
        raise CollisionError("a path of zero steps cannot be checked (no prediction, e.g. "
                             "a Prediction that is not ok): it never reads as clear")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(C))):
        raise CollisionError("a path or its covariance holds NaN or inf")
    if P.size and np.abs(P).max() > MAX_COORDINATE:
        raise CollisionError(f"a path leaves +-{MAX_COORDINATE:g} m (or rad)")
    if C.size and np.abs(C).max() > MAX_VARIANCE:
        raise CollisionError(f"a covariance entry exceeds {MAX_VARIANCE:g}")
    # a covariance is symmetric positive semi-definite, to round-off: -I or a skew one was
    # clipped to zero, and read as certainty (a path beside a wall as clear)
    if C.size and _psd_problem(C):
        raise CollisionError("a covariance is not symmetric positive semi-definite")
    if not all(math.isfinite(v) and abs(v) <= MAX_COORDINATE for v in transform):
        raise CollisionError(f"transform must be a finite (x, y, yaw), got {transform}")
    return P, C


def _psd_problem(C: FloatArray) -> bool:
    """Whether any of the [..., d, d] matrices (d = 2 or 3) is not symmetric positive
    semi-definite, to round-off (1e-6 of its largest entry): every principal minor >= 0,
    in closed form (an eigendecomposition per matrix took 7 ms for a thousand paths)."""
    scale = np.abs(C).max(axis=(-1, -2)) + 1e-300
    tol = 1e-6 * scale
    if np.any(np.abs(C - np.swapaxes(C, -1, -2)).max(axis=(-1, -2)) > tol):
        return True
    S = 0.5 * (C + np.swapaxes(C, -1, -2))
    d = C.shape[-1]
    bad = np.any(np.diagonal(S, axis1=-2, axis2=-1) < -tol[..., None], axis=-1)
    for i in range(d):
        for j in range(i + 1, d):
            minor = S[..., i, i] * S[..., j, j] - S[..., i, j] ** 2
            bad |= minor < -tol * scale
    if d == 3:  # the determinant, by its first row
        det = (S[..., 0, 0] * (S[..., 1, 1] * S[..., 2, 2] - S[..., 1, 2] ** 2)
               - S[..., 0, 1] * (S[..., 0, 1] * S[..., 2, 2] - S[..., 1, 2] * S[..., 0, 2])
               + S[..., 0, 2] * (S[..., 0, 1] * S[..., 1, 2] - S[..., 1, 1] * S[..., 0, 2]))
        bad |= det < -tol * scale * scale
    return bool(np.any(bad))


def contact_probability(fld: DistanceField, pose: FloatArray, cov: FloatArray,
                        footprint: Footprint = DEFAULT_FOOTPRINT,
                        transform: tuple[float, float, float] = (0.0, 0.0, 0.0),
                        samples: int = SAMPLES, *, method: str = "auto",
                        raster: float = RASTER, heading_bin: float = HEADING_BIN) -> Contact:
    """Probability that the footprint touches an obstacle of ``fld`` (module docstring).

    Args:
        fld: the obstacles.
        pose: [k, 3] or [B, k, 3] (x, y, yaw) of the base frame along each path.
        cov: [k, 2, 2] or [B, k, 2, 2] position covariances (the mean heading is used), or
            [k, 3, 3] / [B, k, 3, 3] covariances of (x, y, yaw) (headings sampled too).
        footprint: the chair.
        transform: pose (x, y, yaw) of the paths' frame in the field's frame.
        samples: Sobol draws per step (a power of two).
        method: ``"raster"`` (a lookup per sample, conservative by ``Contact.tolerance``),
            ``"exact"`` (the rectangle tested against every obstacle point in reach), or
            ``"auto"``: exact when the samples times the obstacle points in their reach
            are at most ``_EXACT_WORK`` (a path or two), else the raster.
        raster: cell of the raster method (m); coarser only when the samples spread over
            more than ``_CELL_BUDGET`` cells (the returned tolerance says so).
        heading_bin: width of the raster method's heading bins (rad).

    Raises:
        CollisionError: shapes that do not match, NaN, inf or absurd magnitudes in the paths,
            paths of zero steps.
    """
    P, C = _check_inputs(pose, cov, transform)
    if samples < 2 or samples & (samples - 1):
        raise ValueError(f"samples must be a power of two >= 2, got {samples}")
    if method not in ("auto", "raster", "exact"):
        raise ValueError(f"method must be 'auto', 'raster' or 'exact', got {method!r}")
    if not (math.isfinite(raster) and 1e-3 <= raster <= 1.0):
        raise ValueError(f"raster must be in [0.001, 1] m, got {raster}")
    if not (math.isfinite(heading_bin) and 1e-3 <= heading_bin <= math.pi):
        raise ValueError(f"heading_bin must be in [0.001, pi] rad, got {heading_bin}")
    B, k = P.shape[:2]
    R, t = _pose_matrix(transform)
    xy = P[..., :2] @ R.T + t  # [B, k, 2] in the field's frame
    yaw = P[..., 2] + transform[2]
    T = np.eye(C.shape[-1])
    T[:2, :2] = R
    L = _chol3(T @ C @ T.T)  # [B, k, 3, 3] of (x, y, yaw) in the field's frame
    z = _draws(samples)  # [S, 3]
    zmax = np.abs(z).max(axis=0)  # [3]
    zn_pos, zn = float(np.linalg.norm(z[:, :2], axis=1).max()), float(
        np.linalg.norm(z, axis=1).max())
    half = np.stack([np.abs(L[..., 0, 0]) * zmax[0],
                     np.abs(L[..., 1, 0]) * zmax[0] + np.abs(L[..., 1, 1]) * zmax[1]], -1)
    turn = np.abs(L[..., 2, :]) @ zmax  # [B, k] largest heading offset of a sample, with
    turn = np.where(turn > 0.0, turn * (1 + 1e-9) + 1e-12 * (1.0 + np.abs(yaw)), 0.0)  # slack
    centres = footprint.centres()[:, 0]  # [D] along x
    offsets = np.stack([np.cos(yaw)[..., None] * centres,
                        np.sin(yaw)[..., None] * centres], axis=-1)  # [B, k, D, 2]

    # steps that no sample can bring into contact: probability 0 without sampling. A
    # sample moves the position by at most sigma_max |z|, a disc centre c by |c| |dtheta|
    # more; the field understates no clearance by more than 2 cells (bilinear, half a cell)
    clearance = fld.distance(xy[:, :, None, :] + offsets).min(axis=-1) - footprint.radius
    vx = L[..., 0, 0] ** 2  # position covariance (of the clipped factor)
    vy = L[..., 1, 0] ** 2 + L[..., 1, 1] ** 2
    cxy = L[..., 0, 0] * L[..., 1, 0]
    sig_pos = np.sqrt(0.5 * (vx + vy) + np.hypot(0.5 * (vx - vy), cxy))  # largest sd
    sig_th = np.linalg.norm(L[..., 2, :], axis=-1)
    arm = float(np.abs(centres).max())
    need = (sig_pos * zn_pos + arm * np.minimum(sig_th * zn, 2.0) + 2.0 * fld.resolution
            + 2.0 * fld.merge)
    near = clearance < need
    if fld.outside == 0.0:  # samples off the raster count as touching: near its edge too
        edge = _edge_margin(fld, xy) < sig_pos * zn_pos + 2.0 * fld.resolution
        near |= edge
    per_step = np.zeros((B, k))
    touch_any: BoolArray = np.zeros((B, samples), dtype=bool)
    tolerance = 0.0
    if np.any(near):
        bi, ki = np.nonzero(near)
        smp = _Samples(xy[bi, ki], yaw[bi, ki], L[bi, ki], z, half[bi, ki], turn[bi, ki])
        grow = fld.grow + fld.merge
        rect = _Rect(footprint.offset - 0.5 * footprint.length - grow,
                     footprint.offset + 0.5 * footprint.length + grow,
                     0.5 * footprint.width + grow)
        if method == "auto":
            method = "exact" if _exact_work(fld, rect, smp) <= _EXACT_WORK else "raster"
        if method == "exact":
            touch = _exact_touch(fld, rect, smp)
        else:
            touch, tolerance = _raster_touch(fld, rect, smp, raster, heading_bin)
        # a merged point stands within ``merge`` of the points it replaced: the grown
        # footprint that meets it meets them grown by twice that
        tolerance += 2.0 * fld.merge
        if fld.outside == 0.0:  # off the raster: no information, counted as touching
            off = np.flatnonzero(_edge_margin(fld, smp.mu, smp.half) < 0.0)
            if off.size:
                px, py = smp.positions(off)
                touch[off] |= ~fld.contains(np.stack([px, py], axis=-1))
        per_step[bi, ki] = np.count_nonzero(touch, axis=1) / samples
        every = np.zeros((B * k, samples), dtype=bool)
        every[bi * k + ki] = touch
        touch_any = np.asarray(every.reshape(B, k, samples).any(axis=1))
    within = np.count_nonzero(touch_any, axis=1) / samples
    lower = per_step.max(axis=1) if k else np.zeros(B)
    upper = 1.0 - np.prod(1.0 - per_step, axis=1)
    return Contact(per_step, np.maximum(within, lower), lower, upper, tolerance)


def _edge_margin(fld: DistanceField, xy: FloatArray, half: FloatArray | None = None
                 ) -> FloatArray:
    """[...] distance (m) from points [..., 2] (or boxes of half-extent ``half`` around
    them, axis-aligned in the field's frame) to the raster's edge; negative outside."""
    Rt, tt = fld._inv
    local = xy @ Rt.T + tt
    reach = np.zeros(local.shape[:-1]) if half is None else (
        np.abs(Rt) @ half[..., None])[..., 0].max(axis=-1)
    h, w = fld.dist.shape
    size = np.array([w, h]) * fld.resolution
    margin: FloatArray = np.minimum(local, size - local).min(axis=-1) - reach
    return margin


CollisionCheck = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray]]
"""``check(pose [B, k, 3], cov [B, k, 2, 2] or [B, k, 3, 3]) -> (per_step [B, k],
within [B])``: :func:`contact_probability` of paths in the base frame (a 3x3 covariance of
(x, y, yaw) samples the heading too)."""


def footprint_deepening(fld: DistanceField, pose: FloatArray,
                        footprint: Footprint = DEFAULT_FOOTPRINT,
                        transform: tuple[float, float, float] = (0.0, 0.0, 0.0)
                        ) -> FloatArray:
    """[B] how much deeper (m) any obstacle point goes inside the footprint along each mean
    path than it stands inside the footprint at the paths' origin (the chair now): over the
    path's poses and the obstacle points, the largest of a point's depth inside the
    rectangle (its distance to the nearest edge; 0 outside) less its depth now; 0 when no
    point goes deeper.

    No uncertainty: the mean poses only. Where every path is certain to touch (the chair
    already stands within its margin of a wall, say), probabilities cannot tell the paths
    apart, and this can: a path that backs away or stands takes no point deeper, one that
    swings a corner into the wall, or into other furniture, does. Each point is measured
    against its own depth now, so that what the chair already touches in front hides no
    new contact behind, and a command is judged against where the chair is (a step after
    step of small deepenings is each judged from the chair's new place, and each counts).
    The rectangle is grown as :func:`contact_probability` grows it (``fld.grow +
    fld.merge``); off a scan's window there are no points, and nothing counts there.

    Args:
        fld: the obstacles.
        pose: [k, 3] or [B, k, 3] (x, y, yaw) of the base frame along each path.
        footprint: the chair.
        transform: pose (x, y, yaw) of the paths' frame in the field's frame.

    Raises:
        CollisionError: a path with NaN, inf or absurd coordinates, or not [B, k, 3], or of
            zero steps.
    """
    P = np.asarray(pose, dtype=np.float64)
    if P.ndim == 2:
        P = P[None]
    if P.ndim != 3 or P.shape[-1] != 3:
        raise CollisionError(f"paths must be [B, k, 3], got {P.shape}")
    P, _ = _check_inputs(P, np.zeros((*P.shape[:2], 2, 2)), transform)
    B, k = P.shape[:2]
    deeper = np.zeros(B * k)
    if fld._tree is None or not P.size:
        return np.zeros(B)
    R, t = _pose_matrix(transform)
    xy = (P[..., :2] @ R.T + t).reshape(-1, 2)
    yaw = (P[..., 2] + transform[2]).reshape(-1)
    grow = fld.grow + fld.merge
    rect = _Rect(footprint.offset - 0.5 * footprint.length - grow,
                 footprint.offset + 0.5 * footprint.length + grow,
                 0.5 * footprint.width + grow)

    def depth(o: FloatArray, at_xy: FloatArray, at_yaw: FloatArray | float) -> FloatArray:
        """Depth of points ``o`` [m, 2] inside the rectangle at poses ``at_xy`` [m, 2] or
        [2], ``at_yaw`` [m] or scalar; 0 outside."""
        c, s = np.cos(at_yaw), np.sin(at_yaw)
        dx, dy = o[:, 0] - at_xy[..., 0], o[:, 1] - at_xy[..., 1]
        qx, qy = c * dx + s * dy, np.abs(c * dy - s * dx)
        out: FloatArray = np.maximum(np.minimum(np.minimum(qx - rect.x_lo, rect.x_hi - qx),
                                                rect.half_w - qy), 0.0)
        return out

    # the covering discs farther from every obstacle than their radius (with the field's
    # raster error, two cells) hold no point: only the other poses are searched
    centres = footprint.centres()[:, 0]
    discs = xy[:, None, :] + np.stack([np.cos(yaw)[:, None] * centres,
                                       np.sin(yaw)[:, None] * centres], axis=-1)
    clear = fld.distance(discs).min(axis=-1) - footprint.radius
    near = np.flatnonzero(clear < 2.0 * fld.resolution + grow + 1e-9)
    for lo in range(0, near.size, _DEPTH_POSES):
        rows = near[lo:lo + _DEPTH_POSES]
        found = fld.neighbours(xy[rows], np.full(rows.size, rect.reach + 1e-9))
        counts = np.fromiter((len(f) for f in found), dtype=np.intp, count=rows.size)
        if not counts.any():
            continue
        which = np.repeat(rows, counts)
        index = np.fromiter(itertools.chain.from_iterable(found), dtype=np.intp,
                            count=int(counts.sum()))
        o = fld.points[index]
        # each point against its own depth at the paths' origin (the chair now)
        np.maximum.at(deeper, which, depth(o, xy[which], yaw[which])
                      - depth(o, t, transform[2]))
    return deeper.reshape(B, k).max(axis=1) if k else np.zeros(B)


class PathCheck:
    """A :data:`CollisionCheck` (called as one) that also gives :func:`footprint_deepening`
    of the mean paths (``deepening(pose [B, k, 3]) -> [B]``) against the same obstacles:
    the shared-control layer's tie-break among paths all certain to touch."""

    def __init__(self, probability: CollisionCheck,
                 deepening: Callable[[FloatArray], FloatArray]) -> None:
        self._probability = probability
        self._deepening = deepening

    def __call__(self, pose: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
        return self._probability(pose, cov)

    def deepening(self, pose: FloatArray) -> FloatArray:
        """[B] :func:`footprint_deepening` of paths [B, k, 3] in the base frame."""
        return self._deepening(pose)

    @staticmethod
    def either(checks: Sequence[CollisionCheck]) -> CollisionCheck:
        """One check of several obstacle sources (a scan and a map): the larger of their
        probabilities, and of their deepenings when every one of them gives one."""
        if not checks:
            raise ValueError("either() needs at least one check")
        if len(checks) == 1:
            return checks[0]
        parts = tuple(checks)

        def probability(pose: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
            results = [c(pose, cov) for c in parts]
            return (functools.reduce(np.maximum, [r[0] for r in results]),
                    functools.reduce(np.maximum, [r[1] for r in results]))

        if not all(isinstance(c, PathCheck) for c in parts):
            return probability
        with_depth = cast(tuple[PathCheck, ...], parts)

        def deepening(pose: FloatArray) -> FloatArray:
            return functools.reduce(np.maximum, [c.deepening(pose) for c in with_depth])

        return PathCheck(probability, deepening)


def scan_check(scan: Scan, footprint: Footprint = DEFAULT_FOOTPRINT,
               mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
               base_motion: tuple[float, float, float] = (0.0, 0.0, 0.0),
               resolution: float = 0.05, extra: FloatArray | None = None) -> PathCheck:
    """A check of paths in the base frame against ``scan`` (:data:`CollisionCheck`).

    Args:
        scan: the scan.
        footprint: the chair.
        mount: pose of the scanner in the base frame (x, y, yaw).
        base_motion: pose of the paths' base frame (at the prediction time) in the base
            frame at the scan's time: the chair's motion in between.
        resolution: raster of the distance field (m).
        extra: [m, 2] more obstacle points in the scan's frame
            (:meth:`asgp_ros.core.obstacle_memory.ScanMemory.points`: what earlier scans
            saw outside this one's view).

    Raises:
        CollisionError: a scan that cannot show the way is clear.
    """
    fld = DistanceField.from_scan(scan, resolution, extra=extra)
    Rm, tm = _pose_matrix(inverse_pose(mount))
    Rb, tb = _pose_matrix(base_motion)
    R = Rm @ Rb
    t = Rm @ tb + tm
    transform = (float(t[0]), float(t[1]), math.atan2(R[1, 0], R[0, 0]))

    def check(pose: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
        c = contact_probability(fld, pose, cov, footprint, transform)
        return c.per_step, c.within

    return PathCheck(check, lambda pose: footprint_deepening(fld, pose, footprint, transform))


def grid_check(grid: Grid | DistanceField, footprint: Footprint = DEFAULT_FOOTPRINT,
               origin: tuple[float, float, float] | FloatArray = (0.0, 0.0, 0.0),
               occupied: int = 65, unknown_is_obstacle: bool = True) -> PathCheck:
    """A check of paths in the base frame against a map (or its prebuilt field;
    :data:`CollisionCheck`).

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

    return PathCheck(check, lambda pose: footprint_deepening(fld, pose, footprint, transform))
