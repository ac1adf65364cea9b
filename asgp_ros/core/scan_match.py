"""Laser odometry: the chair's motion from its own scans, by point-to-line ICP.

The obstacle memory (:mod:`asgp_ros.core.obstacle_memory`) carries earlier scans' points
along with the chair, and is only as good as the odometry that carries them. A frame-to-
frame VO drifts centimetres within seconds; a planar scanner indoors measures the motion
between two of its scans to millimetres, because walls and furniture are seen from both.

:func:`match` aligns a scan to a reference scan (both as points in the base frame) by
point-to-line ICP (Censi, "An ICP variant using a point-to-line metric", ICRA 2008): each
reference point gets the normal of the line through its neighbours (a local principal
axis; points whose neighbours are not on a line get none), each current point is paired
with the nearest reference point, and the pose T = (x, y, theta) of the current base frame
in the reference one minimises::

    (M1)  sum_i  (n_j(i) . (R(theta) c_i + t - p_j(i)))^2

over the pairs closer than a distance that shrinks as the iterations converge, trimmed of
the worst ``trim`` share; each iteration is one Gauss-Newton step of (M1). The match says
whether it can be trusted (:class:`Match`): enough pairs, a small residual, and a
well-conditioned problem. A corridor constrains nothing along its axis, a round room
nothing of a rotation about its centre: the smallest eigenvalue of the normal equations
per pair (the rotation in metres at the points' RMS radius) must be at least
``min_constraint``; otherwise the match is refused, not guessed.

:class:`ScanOdometer` chains matches into the pose of the base frame at each scan, against
a keyframe scan that is replaced once the chair has moved ``keyframe_m`` or turned
``keyframe_rad`` (matching every scan to its predecessor would add their errors).  The
twist odometry (VO, wheel odometry), when given, seeds each match; a refused match, a
stamp going back, a gap longer than ``max_gap_s`` or a scan whose ranges repeat the previous
one's exactly (a stuck driver re-stamping its last scan: a real scanner's noise never
repeats) starts a new epoch (the memory then
forgets what it held), as :class:`~asgp_ros.core.obstacle_memory.Odometer` does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.spatial
from numpy.typing import NDArray

from asgp_ros.core.collision import Scan, inverse_pose, scan_points
from asgp_ros.core.obstacle_memory import MEMORY_ODOMETRY, MemoryConfig, Odometer, compose

FloatArray = NDArray[np.float64]
Pose = tuple[float, float, float]

__all__ = ["VELOCITY_SOURCES", "Match", "MatchConfig", "Reference", "ScanOdometer",
           "VelocitySelector", "match", "normals"]


@dataclass(frozen=True)
class MatchConfig:
    """Settings of the matcher (validated on construction).

    Attributes:
        neighbours: reference points a normal is fitted to (the point and its nearest).
        max_line_rms: a normal is kept where its neighbours lie this close (m, RMS) to a
            line; elsewhere (corners, clutter) the point takes no part.
        max_pair_m: pairs farther apart than this are not used at the first iteration;
            the bound shrinks towards ``min_pair_m`` as the match converges.
        min_pair_m: the smallest pairing bound.
        trim: share of the pairs (the worst) left out of each step.
        iterations: at most this many Gauss-Newton steps.
        min_pairs: a match needs at least this many pairs.
        max_rms_m: a match whose point-to-line RMS residual is larger is refused.
        min_constraint: the smallest eigenvalue of the pairs' normal equations per pair,
            the rotation measured in metres at the points' RMS radius (for the
            translation alone the normal scatter mean n n^T: 1/2 for normals spread
            evenly, 0 in a straight corridor; 0 too for a rotation about the scanner in
            a round room) a match needs.
        max_step_m, max_step_rad: a match further than this from its seed is refused (a
            wrong basin, not a chair's motion between two scans).
        max_points: points of the current scan used (evenly spaced along it).
        min_overlap: share of the current scan's points that must find a reference point
            within the final pairing bound (a match of a few walls while the rest of the
            scan disagrees is a wrong one).
    """

    neighbours: int = 5
    max_line_rms: float = 0.02
    max_pair_m: float = 0.3
    min_pair_m: float = 0.05
    trim: float = 0.1
    iterations: int = 30
    min_pairs: int = 40
    max_rms_m: float = 0.03
    min_constraint: float = 0.05
    min_overlap: float = 0.7
    max_step_m: float = 0.3
    max_step_rad: float = 0.35
    max_points: int = 600

    def __post_init__(self) -> None:
        for name, low, high in (("max_line_rms", 1e-4, 1.0), ("max_pair_m", 1e-3, 10.0),
                                ("min_pair_m", 1e-3, 10.0), ("trim", 0.0, 0.5),
                                ("max_rms_m", 1e-4, 1.0), ("min_constraint", 0.0, 0.5),
                                ("min_overlap", 0.0, 1.0),
                                ("max_step_m", 1e-3, 10.0), ("max_step_rad", 1e-3, math.pi)):
            value = getattr(self, name)
            if not (math.isfinite(value) and low <= value <= high):
                raise ValueError(f"{name} must be in [{low}, {high}], got {value}")
        if self.min_pair_m > self.max_pair_m:
            raise ValueError("min_pair_m exceeds max_pair_m")
        for name, low, high in (("neighbours", 3, 50), ("iterations", 1, 1000),
                                ("min_pairs", 3, 1_000_000), ("max_points", 3, 1_000_000)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


@dataclass(frozen=True)
class Match:
    """The result of :func:`match`.

    Attributes:
        pose: (x, y, theta) of the current scan's base frame in the reference one.
        ok: the match can be trusted (``why`` says why not).
        why: empty when ok, else the reason it was refused.
        pairs: pairs used at the last step.
        rms: point-to-line RMS residual of those pairs (m).
        constraint: smallest eigenvalue of their normal scatter (module docstring).
        iterations: Gauss-Newton steps taken.
    """

    pose: Pose
    ok: bool
    why: str
    pairs: int
    rms: float
    constraint: float
    iterations: int


def normals(points: FloatArray, config: MatchConfig | None = None
            ) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Unit normals [n, 2] of the line through each point's neighbours, and whether each
    point's neighbours lie on a line (``max_line_rms``)."""
    cfg = config or MatchConfig()
    n = points.shape[0]
    if n < cfg.neighbours:
        return np.zeros((n, 2)), np.zeros(n, dtype=bool)
    tree = scipy.spatial.cKDTree(points)
    _, idx = tree.query(points, k=cfg.neighbours)
    nb = points[idx]  # [n, k, 2]
    d = nb - nb.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", d, d) / cfg.neighbours  # [n, 2, 2]
    w, v = np.linalg.eigh(cov)  # ascending: v[..., 0] is the normal
    good = (w[:, 0] <= cfg.max_line_rms ** 2) & (w[:, 1] > 4.0 * w[:, 0])
    return v[:, :, 0], good


class Reference:
    """A reference scan prepared for :func:`match`: its line points (those with a normal,
    :func:`normals`), their normals and a k-d tree of them, built once per keyframe."""

    def __init__(self, points: FloatArray, config: MatchConfig | None = None) -> None:
        cfg = config or MatchConfig()
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        nrm, good = normals(pts, cfg)
        self.points: FloatArray = pts[good]
        self.normals: FloatArray = nrm[good]
        self.tree = scipy.spatial.cKDTree(self.points) if self.points.shape[0] else None


def match(reference: FloatArray | Reference, current: FloatArray,
          seed: Pose = (0.0, 0.0, 0.0), config: MatchConfig | None = None) -> Match:
    """The pose of ``current``'s frame in ``reference``'s by point-to-line ICP (M1).

    Args:
        reference: [n, 2] points of the reference scan (its base frame), or the same
            prepared as a :class:`Reference`.
        current: [m, 2] points of the current scan (its base frame); at most
            ``max_points`` of them (evenly spaced along the scan) are used.
        seed: initial guess of the pose (from the twist odometry, say).
        config: the settings.
    """
    cfg = config or MatchConfig()
    ref = reference if isinstance(reference, Reference) else Reference(reference, cfg)
    cur = np.asarray(current, dtype=np.float64).reshape(-1, 2)
    cur = cur[np.all(np.isfinite(cur), axis=1)]
    if cur.shape[0] > cfg.max_points:
        cur = cur[np.linspace(0, cur.shape[0] - 1, cfg.max_points).astype(np.int64)]
    if not all(math.isfinite(s) for s in seed):
        return Match(seed, False, "non-finite seed", 0, math.nan, 0.0, 0)
    if cur.shape[0] < cfg.min_pairs:
        return Match(seed, False, "too few points", 0, math.nan, 0.0, 0)
    if ref.tree is None or ref.points.shape[0] < cfg.min_pairs:
        return Match(seed, False, "too few line points in the reference", 0, math.nan, 0.0, 0)
    lines, lnorm, tree = ref.points, ref.normals, ref.tree
    x, y, th = (float(s) for s in seed)
    bound = cfg.max_pair_m
    pairs, rms, constraint, overlap, it = 0, math.nan, 0.0, 0.0, 0
    for it in range(1, cfg.iterations + 1):
        c, s = math.cos(th), math.sin(th)
        moved = cur @ np.array([[c, s], [-s, c]]) + (x, y)  # R c + t
        dist, j = tree.query(moved, distance_upper_bound=bound)
        use = np.isfinite(dist)
        overlap = float(use.mean())
        if int(use.sum()) < cfg.min_pairs:
            return Match((x, y, th), False, "too few pairs", int(use.sum()), math.nan, 0.0, it)
        p, n, q, cu = lines[j[use]], lnorm[j[use]], moved[use], cur[use]
        r = np.einsum("ij,ij->i", n, q - p)  # point-to-line residuals
        if cfg.trim > 0.0:
            drop = int(cfg.trim * r.shape[0])
            if drop:
                keep = np.argpartition(np.abs(r), r.shape[0] - drop - 1)[:r.shape[0] - drop]
                n, cu, r = n[keep], cu[keep], r[keep]
        # d(R c + t)/d theta = (-s cx - c cy, c cx - s cy)
        dq = np.stack([-s * cu[:, 0] - c * cu[:, 1], c * cu[:, 0] - s * cu[:, 1]], axis=1)
        J = np.column_stack([n, np.einsum("ij,ij->i", n, dq)])  # [pairs, 3]
        H = J.T @ J
        pairs = int(r.shape[0])
        rms = float(np.sqrt(np.mean(r * r)))
        # the weakest direction of (x, y, theta), theta in metres at the points' RMS
        # radius: a corridor leaves a translation free, a round room a rotation
        radius = math.sqrt(float(np.mean(np.sum(cu * cu, axis=1)))) or 1.0
        unit = np.array([1.0, 1.0, 1.0 / radius])
        constraint = float(np.linalg.eigvalsh(H * np.outer(unit, unit) / pairs)[0])
        try:
            step = np.linalg.solve(H + 1e-9 * np.eye(3), -J.T @ r)
        except np.linalg.LinAlgError:
            return Match((x, y, th), False, "singular normal equations", pairs, rms,
                         constraint, it)
        x, y, th = x + float(step[0]), y + float(step[1]), th + float(step[2])
        bound = max(cfg.min_pair_m, min(bound, 3.0 * rms + cfg.min_pair_m))
        if math.hypot(step[0], step[1]) < 1e-4 and abs(step[2]) < 1e-4:
            break
    pose = (x, y, math.remainder(th, 2.0 * math.pi))
    if not all(math.isfinite(v) for v in pose):
        return Match(seed, False, "non-finite result", pairs, rms, constraint, it)
    if constraint < cfg.min_constraint:
        return Match(pose, False, f"degenerate (constraint {constraint:.3f})", pairs, rms,
                     constraint, it)
    if overlap < cfg.min_overlap:
        return Match(pose, False, f"overlap {overlap:.2f} too small", pairs, rms, constraint,
                     it)
    if not rms <= cfg.max_rms_m:
        return Match(pose, False, f"residual {rms:.3f} m too large", pairs, rms, constraint,
                     it)
    if math.hypot(x - seed[0], y - seed[1]) > cfg.max_step_m or \
            abs(math.remainder(th - seed[2], 2.0 * math.pi)) > cfg.max_step_rad:
        return Match(pose, False, "too far from the seed", pairs, rms, constraint, it)
    return Match(pose, True, "", pairs, rms, constraint, it)


def _between(a: Pose, b: Pose) -> Pose:
    """b in a's frame (a^-1 b)."""
    return compose(inverse_pose(a), b)


class ScanOdometer:
    """The base frame's pose at each scan, from scan matching (module docstring).

    Args:
        mount: the scanner's pose in the base frame (x, y, yaw).
        config: the matcher's settings.
        keyframe_m, keyframe_rad: motion after which the current scan becomes the keyframe.
        max_gap_s: scans further apart than this start a new epoch.
    """

    def __init__(self, mount: Pose = (0.0, 0.0, 0.0), config: MatchConfig | None = None,
                 keyframe_m: float = 0.1, keyframe_rad: float = math.radians(10.0),
                 max_gap_s: float = 0.5) -> None:
        if not (math.isfinite(max_gap_s) and max_gap_s > 0.0):
            raise ValueError(f"max_gap_s must be > 0, got {max_gap_s}")
        self.mount = (float(mount[0]), float(mount[1]), float(mount[2]))
        self.config = config or MatchConfig()
        self.keyframe_m, self.keyframe_rad, self.max_gap_s = keyframe_m, keyframe_rad, max_gap_s
        self.epoch = 0
        self.breaks = 0  # epochs started after the first
        self.refused: dict[str, int] = {}
        self.last: Match | None = None
        self._key: tuple[Reference, Pose] | None = None
        self._pose: Pose = (0.0, 0.0, 0.0)
        self._stamp = -math.inf
        self._velocity: Pose = (0.0, 0.0, 0.0)  # per second, in the base frame
        self._ranges: FloatArray | None = None  # the previous scan's ranges
        #: (interval s, dx, dy, dtheta) of the newest :meth:`add` that matched, the motion in
        #: the base frame at the previous scan; None when it did not (a new epoch, a
        #: repeated stamp)
        self.last_step: tuple[float, float, float, float] | None = None

    @property
    def last_twist(self) -> tuple[float, float] | None:
        """(forward m/s, turn rad/s) of the newest matched interval (:attr:`last_step`), as a
        frame-to-frame odometry reports it; None when the newest scan did not match."""
        if self.last_step is None:
            return None
        gap, dx, _, dtheta = self.last_step
        return dx / gap, dtheta / gap

    def _base_points(self, scan: Scan) -> FloatArray:
        pts = scan_points(scan)
        c, s = math.cos(self.mount[2]), math.sin(self.mount[2])
        out: FloatArray = pts @ np.array([[c, s], [-s, c]]) + self.mount[:2]
        return out

    def _restart(self, pts: FloatArray, t: float, why: str) -> Pose:
        if self._key is not None:
            self.epoch += 1
            self.breaks += 1
            self.refused[why] = self.refused.get(why, 0) + 1
        self._pose = (0.0, 0.0, 0.0)
        self._key = (Reference(pts, self.config), self._pose)
        self._stamp = t
        self._velocity = (0.0, 0.0, 0.0)
        return self._pose

    def add(self, scan: Scan, motion: Pose | None = None) -> Pose:
        """The base pose at ``scan`` in this epoch's frame (:attr:`epoch`).

        Args:
            scan: the newest scan.
            motion: the chair's motion since the previous scan from other odometry, in the
                base frame at the previous scan (the match's seed); None: the motion of
                the previous interval is assumed again.
        """
        t = float(scan.stamp)
        pts = self._base_points(scan)
        self.last_step = None
        # a copy: a caller may fill one buffer in place for every scan
        previous_ranges, self._ranges = self._ranges, scan.ranges.copy()
        if self._key is None or not math.isfinite(t):
            return self._restart(pts, t, "no stamp")
        gap = t - self._stamp
        if not gap > 0.0:
            return self._restart(pts, t, "stamp went back") if gap < 0.0 else self._pose
        if gap > self.max_gap_s:
            return self._restart(pts, t, "gap")
        if previous_ranges is not None and np.array_equal(previous_ranges, scan.ranges,
                                                          equal_nan=True):
            # a real scanner's ranges are never bit-identical twice, even standing still: a
            # driver repeating its last scan with new stamps would read as a standstill
            return self._restart(pts, t, "repeated ranges")
        if motion is None or not all(math.isfinite(m) for m in motion):
            motion = (self._velocity[0] * gap, self._velocity[1] * gap,
                      self._velocity[2] * gap)
        key, key_pose = self._key
        seed = _between(key_pose, compose(self._pose, motion))
        result = match(key, pts, seed, self.config)
        self.last = result
        if not result.ok:
            return self._restart(pts, t, result.why.split(" (")[0])
        previous = self._pose
        self._pose = compose(key_pose, result.pose)
        step = _between(previous, self._pose)
        self._velocity = (step[0] / gap, step[1] / gap, step[2] / gap)
        self.last_step = (gap, step[0], step[1], step[2])
        self._stamp = t
        if math.hypot(result.pose[0], result.pose[1]) >= self.keyframe_m or \
                abs(result.pose[2]) >= self.keyframe_rad:
            self._key = (Reference(pts, self.config), self._pose)
        return self._pose


def memory_odometers(memory: MemoryConfig | None, kind: str,
                     mount: tuple[float, float, float]
                     ) -> tuple[Odometer | None, ScanOdometer | None]:
    """What carries an obstacle memory: ``kind`` "dead_reckoning" gives the twist
    :class:`Odometer`, "scan_matching" the :class:`ScanOdometer` of the laser at ``mount``
    (the other one None); both None without a memory.

    Raises:
        ValueError: ``kind`` is not one of :data:`MEMORY_ODOMETRY`.
    """
    if kind not in MEMORY_ODOMETRY:
        raise ValueError(f"memory_odometry must be one of {MEMORY_ODOMETRY}, got {kind!r}")
    if memory is None:
        return None, None
    if kind == "dead_reckoning":
        return Odometer(memory.max_gap_s), None
    return None, ScanOdometer(mount, max_gap_s=memory.max_gap_s)


#: Where a predictor takes the chair's velocity from: the VO's twists, the scans' matched
#: intervals, or the scans while they match and the VO while they do not.
VELOCITY_SOURCES = ("auto", "vo", "scan_matching")


class VelocitySelector:
    """Which velocity samples go to a predictor (``VELOCITY_SOURCES``).

    - ``vo``: every VO twist, no scan twist.
    - ``scan_matching``: every scan's matched-interval twist, and a tracking loss for a scan
      that did not match; no VO twist.
    - ``auto``: the scans' twists while they match; a scan that does not match gives
      nothing, and the VO's twists are taken from then on, and whenever no matched scan
      has come for ``fallback_s`` (a laser that stops, or none fitted). Both streams
      measure the same motion, so the predictor's buffer takes them in one sequence; a
      sample is never held back for the other stream, so one lost sensor does not make
      the predictor's input stale while the other one sees.

    Attributes:
        current: "scans" or "vo", the stream the newest sample given came from ("none"
            before any).
        switches: how many times ``current`` changed.
    """

    def __init__(self, mode: str, fallback_s: float = 0.3) -> None:
        if mode not in VELOCITY_SOURCES:
            raise ValueError(f"velocity_source must be one of {VELOCITY_SOURCES}, got "
                             f"{mode!r}")
        if not (math.isfinite(fallback_s) and fallback_s > 0.0):
            raise ValueError(f"fallback_s must be a positive number, got {fallback_s!r}")
        self.mode = mode
        self.fallback_s = float(fallback_s)
        self.current = "none"
        self.switches = 0
        self._matched_t = -math.inf  # stamp of the newest matched scan twist given

    @property
    def uses_scans(self) -> bool:
        """Whether scans are matched for their twist at all."""
        return self.mode != "vo"

    def _took(self, stream: str) -> None:
        if self.current not in ("none", stream):
            self.switches += 1
        self.current = stream

    def scan(self, t: float, twist: tuple[float, float] | None
             ) -> tuple[bool, tuple[float, float] | None]:
        """A scan stamped ``t`` with its matched twist (None: it did not match).

        Returns:
            (give, twist): whether the predictor is given a sample, and the twist to give
            it (None: a tracking loss).
        """
        if self.mode == "vo":
            return False, None
        if twist is None:
            self._matched_t = -math.inf
            if self.mode == "auto":
                return False, None
            self._took("scans")
            return True, None
        self._matched_t = float(t)
        self._took("scans")
        return True, twist

    def vo(self, t: float) -> bool:
        """Whether the VO's sample stamped ``t`` goes to the predictor."""
        if self.mode == "scan_matching":
            return False
        # a matched scan within fallback_s either side (a VO stamp may trail the scans'
        # a little; a clock that went back by more does not hold the VO off)
        if self.mode == "auto" and abs(float(t) - self._matched_t) <= self.fallback_s:
            return False
        self._took("vo")
        return True

    def describe(self) -> str:
        """The mode, and in ``auto`` the stream in use and the switches so far."""
        if self.mode != "auto":
            return self.mode
        return f"auto ({self.current}; {self.switches} switches)"
