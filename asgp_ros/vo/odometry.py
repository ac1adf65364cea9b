"""Sparse-feature RGB-D visual odometry after Fovis (Huang et al., ISRR 2011).

Pipeline per frame, the stages of Huang, Bachrach, Henry, Krainin, Maturana, Fox, Roy,
"Visual Odometry and Mapping for Autonomous Flight Using an RGB-D Camera", ISRR 2011,
section 3:

1. grey image, Gaussian pyramid of ``num_levels`` levels;
2. FAST corners per level with a threshold adapted toward ``target_pixels_per_feature``,
   bucketed into ``bucket_size`` px cells keeping the ``max_features_per_bucket``
   strongest;
3. depth look-up at level-0 position; features with no depth, out-of-range depth or on a
   depth discontinuity are dropped;
4. prediction of where the reference (key) frame's features appear from the previous
   motion (constant velocity); when that fails, the search is repeated around "no motion"
   and around the rotation that aligns heavily down-sampled images (phase correlation of
   <= 80 px images: Fovis's initial rotation estimate);
5. matching within ``search_radius`` level pixels of the prediction on the same pyramid
   level: zero-mean, unit-variance 9x9 patches compared by the sum of absolute differences,
   mutual best matches only, an ambiguous best (ratio to the second best above
   ``match_ratio``) dropped; sub-pixel refinement of the match by Lucas-Kanade on the
   level image;
6. inliers: a set of matches whose pairwise 3-D distances all agree between the two frames
   (rigidity), a clique of the consistency graph of Howard 2008 ("Real-time stereo visual
   odometry for autonomous ground vehicles", IROS) found by deleting the least consistent
   match until the rest is a clique (a greedy approximation of the largest such set; Fovis
   grows one from the best-connected match instead, see :func:`_max_clique`);
7. motion: closed-form absolute orientation on the clique (Umeyama 1991, IEEE PAMI 13(4),
   eq. 39-42, without scale), then Gauss-Newton on the bidirectional reprojection error,
   rejection of matches above ``outlier_reprojection_threshold`` px and re-refinement;
   an estimate whose translation is ill-constrained (``max_translation_std``), whose mean
   error is too high, or that implies an implausible speed is rejected with a status;
8. keyframe: the reference frame is kept while at least ``ref_frame_change_threshold``
   inliers remain; otherwise the current frame becomes the reference;
9. covariance of the estimate T_cur_ref, H^-1 (M + B) H^-1 t f g s with H = J^T W J of the last
   Gauss-Newton step (a sandwich estimate: Huber 1967, White 1980):

   * M = 2 sigma^2 H, the model part: a match's forward and backward residuals are one
     measurement seen twice (correlation about -1), so the n inliers give 2 n independent
     residuals, sigma^2 = cost / (2 (2 n - 6)) on nu = 2 n - 6 degrees of freedom and the
     information is H / 2; sigma^2 is at least the variance eps^2 / 3 of the uniform error
     that Lucas-Kanade's stopping step eps = 0.03 px leaves;
   * B, the cluster-robust part (Liang & Zeger 1986): the outer products of the inliers'
     gradients J_i^T W r_i summed per ``bucket_size`` image cell (G cells, factor
     G / (G - 1) (n - 1) / (n - 6)); errors that nearby features share, which the
     residuals do not show to M, count once per cell;
   * t = d / (d - 2), the Student-t predictive factor, with d the Welch-Satterthwaite
     degrees of freedom of M + B (nu for M, G - 1 for B): the covariance grows when the
     inliers are few or bunched in a few cells (degenerate geometry), on top of the growth
     of H^-1 itself;
   * f = 1 + (n0 / n)^p, the few-inliers factor (n0 =
     :attr:`VisualOdometry.inlier_count_scale`, p = :attr:`VisualOdometry.inlier_count_power`):
     frames with few inliers (the last ones before the camera turns to a bare wall, the
     first ones after it turns back) err beyond what M, B and t account for, and frames with
     many do not; f is about 1 above a few hundred inliers;
   * g = 1 + (c theta)^2, the rotation factor of the angle theta between the reference and
     the current frame (c = :attr:`VisualOdometry.rotation_gain`): a rotation deforms the
     image between the two (a point at angle a from the optical axis moves by
     f (tan(a + theta) - tan a): at 0.2 rad the image's sides stretch by up to 20 %), and
     the translation-only sub-pixel matching of 9x9 patches errs with the deformation, in
     part alike over large parts of the image, which the fit absorbs and the residuals
     (M, B) cannot show. Measured on rendered turns on the spot, noise-free images too, the
     errors grow beyond the model's once theta passes about 0.15 rad (0.1 rad per frame at
     3 rad/s and 30 Hz, 0.2 at 15 Hz; or a reference kept over several frames), whatever
     the camera's offset from the axis; the error's std taken to grow as theta, its
     variance adds (c theta)^2 of the model's;
   * s = :attr:`VisualOdometry.covariance_scale`, calibrated on rendered drives with f and
     g so that 95 % of the frames' planar increments fall inside their 95 % ellipsoid in
     every group of calibration frames (all of them, those near a loss, inlier counts 0-50,
     50-100, 100-200 and more, each kind of drive, rotations to the reference of 0-0.05,
     0.05-0.1, 0.1-0.15 rad and more), n0, p and c being the sharpest choice that does
     so (``benchmarks/vo_nees.py --calibrate``; ``docs/vo_nees.md`` has the held-out
     figures); the first :attr:`VisualOdometry.recovery_frames` tracked frames after a loss
     (``VOResult.recovering``) may carry :attr:`VisualOdometry.recovery_scale` as well,
     calibrated on those frames alone (1: f covers them).

   The reported ``covariance`` is that of ``motion``: when the reference was kept,
   motion = T_ref_prev^-1 T_ref_cur, and the previous frame's covariance, moved into the
   current frame by the adjoint, is added (two estimates taken as independent).

Honest failure: a frame that cannot be tracked returns a failure :class:`Status`, no motion
and no twist; the pose is held and the next frame is matched against the last good
reference. After ``max_frames_lost`` untracked frames that do have features, the current
frame becomes the new reference (the motion during the gap is lost and reported so).

All poses are in camera optical frames (x right, y down, z forward), metres and radians.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields
from enum import Enum
from typing import Any, NamedTuple

import cv2
import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from asgp_ros.vo.extrinsics import DEFAULT_EXTRINSIC, CameraExtrinsic, adjoint, invert

_log = logging.getLogger(__name__)

PATCH = 9  # descriptor patch side (px)
_LK_EPS = 0.03  # Lucas-Kanade stops when its step is below this (level px)
_HALF = PATCH // 2
_BORDER = _HALF + 2


class Status(str, Enum):
    """Outcome of :meth:`VisualOdometry.process` for one frame."""

    OK = "ok"
    REFERENCE_SET = "reference_set"  # first frame (or re-initialisation): no motion yet
    INSUFFICIENT_FEATURES = "insufficient_features"
    INSUFFICIENT_INLIERS = "insufficient_inliers"
    OPTIMIZATION_FAILURE = "optimization_failure"
    REPROJECTION_ERROR_TOO_HIGH = "reprojection_error_too_high"
    NO_DEPTH = "no_depth"
    BAD_INPUT = "bad_input"


@dataclass(frozen=True)
class VOOptions:
    """Options of :class:`VisualOdometry` (Fovis names and defaults where they exist)."""

    num_levels: int = 3
    target_pixels_per_feature: float = 400.0
    fast_threshold: float = 20.0
    fast_threshold_min: float = 8.0
    fast_threshold_max: float = 70.0
    fast_adaptive_gain: float = 0.5
    bucket_size: int = 80
    max_features_per_bucket: int = 25
    min_depth: float = 0.3
    max_depth: float = 6.0
    depth_scale: float = 0.001
    depth_edge_fraction: float = 0.05
    search_radius: float = 15.0
    max_descriptor_distance: float = 0.55
    match_ratio: float = 0.9
    max_matches: int = 500
    clique_inlier_threshold: float = 0.05
    clique_depth_coefficient: float = 0.004
    min_features_for_estimate: int = 10
    min_inliers: int = 12
    outlier_reprojection_threshold: float = 0.5
    max_mean_reprojection_error: float = 0.35
    ref_frame_change_threshold: int = 250
    max_frames_lost: int = 5
    min_valid_depth_fraction: float = 0.01
    gauss_newton_iterations: int = 5
    max_translation_std: float = 0.008
    max_speed: float = 3.0
    max_twist_interval: float = 0.5
    max_angular_speed: float = 4.0
    use_prediction: bool = True

    def __post_init__(self) -> None:
        positive = ("target_pixels_per_feature", "fast_threshold_max", "min_depth",
                    "max_depth", "depth_scale", "search_radius", "max_descriptor_distance",
                    "clique_inlier_threshold", "outlier_reprojection_threshold",
                    "max_mean_reprojection_error", "match_ratio", "max_speed",
                    "max_twist_interval",
                    "max_translation_std",
                    "max_angular_speed")
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"VO option {name} must be positive and finite, got {v!r}")
        at_least_one = ("num_levels", "bucket_size", "max_features_per_bucket", "max_matches",
                        "gauss_newton_iterations")
        for name in at_least_one:
            if int(getattr(self, name)) < 1:
                raise ValueError(f"VO option {name} must be >= 1, got {getattr(self, name)!r}")
        if self.num_levels > 5:
            raise ValueError(f"num_levels must be <= 5, got {self.num_levels}")
        if self.min_features_for_estimate < 6:
            raise ValueError("min_features_for_estimate must be >= 6")
        if self.min_inliers < 7:
            # a motion of 6 parameters from 6 inliers leaves no degree of freedom for its
            # covariance (the cluster-robust small-sample factor divides by n - 6)
            raise ValueError(f"min_inliers must be >= 7, got {self.min_inliers}")
        if self.match_ratio > 1.0:
            raise ValueError(f"match_ratio must be in (0, 1], got {self.match_ratio}")
        if self.max_depth <= self.min_depth:
            raise ValueError(f"max_depth {self.max_depth} must exceed min_depth {self.min_depth}")
        if not 0 < self.fast_threshold_min <= self.fast_threshold <= self.fast_threshold_max:
            raise ValueError("need 0 < fast_threshold_min <= fast_threshold <= fast_threshold_max")
        for name in ("fast_adaptive_gain", "clique_depth_coefficient", "depth_edge_fraction",
                     "min_valid_depth_fraction"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"VO option {name} must be >= 0, got {v!r}")
        if self.ref_frame_change_threshold < 0 or self.max_frames_lost < 0:
            raise ValueError("ref_frame_change_threshold and max_frames_lost must be >= 0")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


@dataclass
class VOResult:
    """Result of one frame.

    Attributes:
        status: the :class:`Status`; ``ok`` is ``status is Status.OK``.
        stamp: the frame's time stamp (s).
        motion: [4, 4] pose of the current camera in the previous *tracked* frame's camera
            frame (the previous frame unless frames were lost in between); None unless ok.
        pose: [4, 4] pose of the current camera in the first frame's camera frame (held at
            the last tracked pose when not ok).
        covariance: [6, 6] covariance of ``motion``, as a perturbation (tx, ty, tz, rx, ry,
            rz) on its right, in the current optical frame (m^2, rad^2): the true motion is
            motion exp(e) with e of this covariance (step 9 of the module docstring); None
            unless ok.
        dt: time since the previous tracked frame (s); None unless ok.
        twist: (v m/s, omega rad/s) of base_link from ``motion``, ``dt`` and the extrinsic;
            None unless ok, and None when dt > ``max_twist_interval`` (after a loss the
            motion spans the gap: the pose is right, its average speed is not a twist).
        twist_covariance: [6, 6] covariance of the base_link twist (v, w order); None when
            ``twist`` is.
        num_features, num_matches, num_inliers: counts at each stage for this frame.
        reprojection_error: mean reprojection error of the inliers in pixels of their pyramid
            level, nan if not estimated.
        keyframe_changed: the current frame became the reference for the next one.
        reset: tracking was re-initialised on this frame (the motion since the last tracked
            frame is lost).
        recovering: one of the first :attr:`VisualOdometry.recovery_frames` tracked frames
            after a frame that could not be tracked; its covariances carry
            :attr:`VisualOdometry.recovery_scale`.
        message: human-readable detail for failures.
        elapsed: processing time (s).
    """

    status: Status
    stamp: float
    pose: np.ndarray
    motion: np.ndarray | None = None
    covariance: np.ndarray | None = None
    dt: float | None = None
    twist: tuple[float, float] | None = None
    twist_covariance: np.ndarray | None = None
    num_features: int = 0
    num_matches: int = 0
    num_inliers: int = 0
    reprojection_error: float = float("nan")
    keyframe_changed: bool = False
    reset: bool = False
    recovering: bool = False
    message: str = ""
    elapsed: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status is Status.OK


@dataclass
class _Frame:
    """Features of one frame (N features over all levels)."""

    levels: list[np.ndarray]  # grey pyramid, level 0 full resolution
    depth: np.ndarray  # [h, w] float32 metres, 0 = invalid
    xy: np.ndarray  # [N, 2] float32 level coordinates (integer valued)
    level: np.ndarray  # [N] int
    uv: np.ndarray  # [N, 2] level-0 pixel coordinates
    pts: np.ndarray  # [N, 3] camera-frame points
    desc: np.ndarray  # [N, PATCH*PATCH] float32 normalised patches
    stamp: float
    coarse: np.ndarray | None = None  # <= 80 px wide blurred float32 image (rotation guess)
    pose: np.ndarray | None = None  # pose in the first camera frame when it is a reference


class _Matches(NamedTuple):
    """n refined matches between the reference and the current frame (steps 4-5)."""

    P: np.ndarray  # [n, 3] reference camera-frame points
    Q: np.ndarray  # [n, 3] current camera-frame points
    uv_ref: np.ndarray  # [n, 2] level-0 pixel positions in the reference image
    uv_cur: np.ndarray  # [n, 2] level-0 pixel positions in the current image (sub-pixel)
    level: np.ndarray  # [n] pyramid level of the reference feature
    w: np.ndarray  # [n] residual weight 1 / 2^level (coarse positions are less precise)


class _GaussNewton(NamedTuple):
    """Result of :meth:`VisualOdometry._gauss_newton`."""

    T: np.ndarray  # [4, 4] T_cur_ref
    H: np.ndarray  # [6, 6] J^T W J at the last linearisation point
    cost: float  # weighted squared residual sum there
    ok: bool
    scores: np.ndarray  # [n, 6] per match J_i^T W_i r_i there (its four residuals)


class _Refinement(NamedTuple):
    """The refined motion and its final inlier set (step 7)."""

    T: np.ndarray  # [4, 4] T_cur_ref
    inliers: np.ndarray  # [k] indices into the matches
    H: np.ndarray  # [6, 6] J^T W J of the last Gauss-Newton step
    cost: float  # its weighted squared residual sum (level px^2)
    error: float  # mean inlier reprojection error (level px)
    scores: np.ndarray  # [k, 6] per-inlier gradients J_i^T W_i r_i of that step


class _Covariance(NamedTuple):
    """Covariance of the refined motion T_cur_ref (step 9)."""

    covariance: np.ndarray  # [6, 6] of (tx, ty, tz, rx, ry, rz) in the current optical frame
    sigma2: float  # residual variance per independent residual (level px^2)
    dof: float  # effective degrees of freedom of the covariance estimate
    cells: int  # image cells holding inliers (clusters of the score covariance)
    translation_std: float  # largest translation std of the acceptance test (m)


class _Attempt(NamedTuple):
    """Outcome of one motion estimate around one prediction (steps 4-7 and 9)."""

    status: Status
    T_cur_ref: np.ndarray | None = None
    covariance: np.ndarray | None = None
    num_inliers: int = 0
    num_matches: int = 0
    error: float = math.nan
    message: str = ""


class _RejectedError(Exception):
    """A stage of :meth:`VisualOdometry._estimate` rejects the estimate (``attempt``)."""

    def __init__(self, status: Status, message: str, num_inliers: int = 0,
                 num_matches: int = 0, error: float = math.nan) -> None:
        super().__init__(message)
        self.attempt = _Attempt(status, None, None, num_inliers, num_matches, error, message)


class VisualOdometry:
    """Fovis-like RGB-D odometry (module docstring).

    Args:
        camera_matrix: K [3, 3] of the colour camera (depth registered to colour).
        extrinsic: camera mounting on base_link, for the planar twist.
        image_size: (width, height); default: the first frame's size.
        **options: fields of :class:`VOOptions`.
    """

    #: Calibrated scale of the covariance model (module docstring, step 9):
    #: ``benchmarks/vo_nees.py --calibrate`` on the calibration drives.
    covariance_scale: float = 1.577
    #: The few-inliers factor 1 + (inlier_count_scale / n)^inlier_count_power on the
    #: covariance of an estimate from n inliers (module docstring, step 9; chosen by
    #: ``benchmarks/vo_nees.py --calibrate``; 0 turns it off).
    inlier_count_scale: float = 25.0
    inlier_count_power: float = 2.0
    #: The rotation factor 1 + (rotation_gain theta)^2 on the covariance of an estimate
    #: whose motion against its reference frame turns by theta (rad): the image deforms
    #: between the two (up to 20 % stretch at the image's sides at 0.2 rad), the
    #: translation-only sub-pixel matching errs with it, partly in common over the image
    #: where the residuals cannot show it (module docstring, step 9; chosen by
    #: ``benchmarks/vo_nees.py --calibrate``; 0 turns it off).
    rotation_gain: float = 4.0
    #: The first ``recovery_frames`` tracked frames after a frame that could not be tracked
    #: are a regime of their own (a new or long-kept reference seen from the edge of what
    #: the camera can track): their covariances are multiplied by ``recovery_scale``,
    #: calibrated on those frames of the calibration drives alone
    #: (``benchmarks/vo_nees.py --calibrate``): 1 since the few-inliers factor, which
    #: covers them.
    recovery_frames: int = 5
    recovery_scale: float = 1.0

    def __init__(self, camera_matrix: ArrayLike,
                 extrinsic: CameraExtrinsic = DEFAULT_EXTRINSIC,
                 image_size: tuple[int, int] | None = None, **options: Any) -> None:
        K = np.asarray(camera_matrix, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(f"camera_matrix must be a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9 or np.any(K[2, :2] != 0):
            raise ValueError(f"camera_matrix is not a pinhole K: {K.tolist()}")
        unknown = set(options) - set(VOOptions.names())
        if unknown:
            raise TypeError(f"unknown VO options: {sorted(unknown)}")
        self.options = VOOptions(**options)
        self.K = K
        self.extrinsic = extrinsic
        self.image_size = None if image_size is None else (int(image_size[0]),
                                                           int(image_size[1]))
        if self.image_size is not None:
            problem = self._size_problem(*self.image_size)
            if problem:
                raise ValueError(problem)
        self._fast_threshold = float(self.options.fast_threshold)
        self.reset()

    # ------------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the reference frame and the pose (the next frame starts a new track)."""
        self._ref: _Frame | None = None
        self._T_ref_prev = np.eye(4)  # pose of the last tracked frame in the reference frame
        self._ref_prev_cov = np.zeros((6, 6))  # its covariance (0: it is the reference)
        self._step = np.eye(4)  # last frame-to-frame camera motion (for the prediction)
        self._step_dt: float | None = None
        self._pose = np.eye(4)  # pose of the last tracked frame in the first frame
        self._prev_stamp: float | None = None  # last processed frame
        self._ok_stamp: float | None = None  # last tracked frame
        self._lost = 0
        self._since_loss = self.recovery_frames  # tracked frames since an untracked one
        self._restarted = False  # the next reference re-initialises a held pose

    def restart(self, pose: ArrayLike | None = None) -> None:
        """Forget the reference frame but hold the pose (this track's, or ``pose`` [4, 4],
        e.g. from the instance this one replaces after a new camera calibration): the next
        frame with features becomes the reference, reported as a re-initialisation
        (``VOResult.reset``: the motion in between is unknown), as after
        ``max_frames_lost``."""
        held = self._pose.copy() if pose is None else np.asarray(pose, dtype=float).copy()
        if held.shape != (4, 4) or not np.all(np.isfinite(held)):
            raise ValueError(f"pose must be a finite 4x4 matrix, got shape {held.shape}")
        self.reset()
        self._pose = held
        self._restarted = True

    @property
    def pose(self) -> np.ndarray:
        """Pose [4, 4] of the last tracked camera in the first frame."""
        return self._pose.copy()

    # ------------------------------------------------------------------------------------
    def process(self, image: np.ndarray, depth: np.ndarray, stamp: float) -> VOResult:
        """Track one RGB-D frame.

        Args:
            image: [h, w] grey or [h, w, 3] BGR (or [h, w, 4] BGRA) uint8.
            depth: [h, w] float32/float64 metres or uint16 in units of ``depth_scale``
                (mm by default); 0, NaN and inf are "no data".
            stamp: time stamp (s), strictly increasing.
        Returns:
            the :class:`VOResult`; never raises on bad data (status ``bad_input``).
        """
        t0 = time.perf_counter()
        try:
            stamp = float(stamp)
        except (TypeError, ValueError):
            return self._fail(Status.BAD_INPUT, math.nan, t0, f"stamp {stamp!r} is not a number")
        problem = self._check_input(image, depth, stamp)
        if problem:
            return self._fail(Status.BAD_INPUT, stamp, t0, problem)
        if image.ndim == 2 or image.shape[2] == 1:
            gray = np.ascontiguousarray(image.reshape(image.shape[:2]))
        else:
            gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_BGR2GRAY
                                if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        depth_m = self._depth_metres(depth)
        self._prev_stamp = stamp
        if np.count_nonzero(depth_m) < self.options.min_valid_depth_fraction * depth_m.size:
            return self._fail(Status.NO_DEPTH, stamp, t0, "no valid depth in the frame")
        frame = self._features(gray, depth_m, stamp)
        nfeat = len(frame.level)
        if nfeat < self.options.min_features_for_estimate:
            if self._ref is None:
                return self._fail(Status.INSUFFICIENT_FEATURES, stamp, t0,
                                  f"{nfeat} features with depth, no reference yet", nfeat)
            return self._fail(Status.INSUFFICIENT_FEATURES, stamp, t0,
                              f"{nfeat} features with depth", nfeat)
        if self._ref is None or len(self._ref.level) < self.options.min_features_for_estimate:
            return self._set_reference(frame, t0, reset=self._restarted)
        result = self._track(frame, t0)
        if result.ok:
            return self._recovery(result)
        self._lost += 1
        self._since_loss = 0
        if self._lost > self.options.max_frames_lost:
            # the reference cannot be found again: start over from this frame, pose held
            reset = self._set_reference(frame, t0, reset=True)
            reset.status, reset.message = result.status, result.message + "; re-initialised"
            reset.num_matches, reset.num_inliers = result.num_matches, result.num_inliers
            return reset
        return result

    # ------------------------------------------------------------------------------------
    def _check_input(self, image: np.ndarray, depth: np.ndarray, stamp: float) -> str:
        if not math.isfinite(stamp):
            return f"stamp {stamp} is not finite"
        if self._prev_stamp is not None and stamp <= self._prev_stamp:
            return f"stamp {stamp:.6f} is not after the previous frame's {self._prev_stamp:.6f}"
        if not isinstance(image, np.ndarray) or not isinstance(depth, np.ndarray):
            return "image and depth must be numpy arrays"
        if image.dtype != np.uint8:
            return f"image must be uint8, got {image.dtype}"
        if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3, 4))):
            return f"image must be HxW, HxWx3 or HxWx4, got shape {image.shape}"
        if depth.ndim != 2:
            return f"depth must be HxW, got shape {depth.shape}"
        if depth.dtype not in (np.float32, np.float64, np.uint16):
            return f"depth must be float32/float64 metres or uint16, got {depth.dtype}"
        if depth.shape != image.shape[:2]:
            return f"depth {depth.shape} and image {image.shape[:2]} sizes differ"
        h, w = image.shape[:2]
        if self.image_size is None:
            problem = self._size_problem(w, h)
            if problem:
                return problem
            self.image_size = (w, h)
        elif (w, h) != self.image_size:
            return f"image size {w}x{h} differs from the expected {self.image_size[0]}x" \
                   f"{self.image_size[1]}"
        return ""

    def _size_problem(self, w: int, h: int) -> str:
        """Why images of w x h cannot be tracked with this K and these options, or ""."""
        if not (0 <= self.K[0, 2] < w and 0 <= self.K[1, 2] < h):
            return f"principal point outside the {w}x{h} image: K does not fit"
        if min(w, h) >> (self.options.num_levels - 1) < 2 * _BORDER + 2:
            return f"image {w}x{h} too small for {self.options.num_levels} levels"
        return ""

    def _depth_metres(self, depth: np.ndarray) -> np.ndarray:
        o = self.options
        if depth.dtype == np.uint16:
            d = depth.astype(np.float32) * np.float32(o.depth_scale)
        else:
            d = depth.astype(np.float32, copy=True)
        bad = ~((d >= o.min_depth) & (d <= o.max_depth))  # also catches NaN
        d[bad] = 0.0
        return d

    def _recovery(self, result: VOResult) -> VOResult:
        """Marks (and widens the covariances of) a tracked frame soon after a loss."""
        if self._since_loss < self.recovery_frames:
            result.recovering = True
            s = self.recovery_scale
            if s != 1.0:
                if result.covariance is not None:
                    result.covariance = s * result.covariance
                if result.twist_covariance is not None:
                    result.twist_covariance = s * result.twist_covariance
        self._since_loss += 1
        return result

    def _fail(self, status: Status, stamp: float, t0: float, message: str,
              nfeat: int = 0) -> VOResult:
        if status is Status.BAD_INPUT:
            _log.debug("bad input: %s", message)
        elif self._ref is not None:  # a frame lost once tracking has started
            self._since_loss = 0
        return VOResult(status=status, stamp=stamp, pose=self._pose.copy(), message=message,
                        num_features=nfeat, elapsed=time.perf_counter() - t0)

    def _set_reference(self, frame: _Frame, t0: float, reset: bool) -> VOResult:
        self._restarted = False
        frame.pose = self._pose.copy()
        self._ref = frame
        self._T_ref_prev = np.eye(4)
        self._ref_prev_cov = np.zeros((6, 6))
        self._step = np.eye(4)
        self._step_dt = None
        self._ok_stamp = frame.stamp
        self._lost = 0
        return VOResult(status=Status.REFERENCE_SET, stamp=frame.stamp, pose=self._pose.copy(),
                        num_features=len(frame.level), keyframe_changed=True, reset=reset,
                        message="reference frame set", elapsed=time.perf_counter() - t0)

    # ------------------------------------------------------------------------------------
    def _features(self, gray: np.ndarray, depth: np.ndarray, stamp: float) -> _Frame:
        """Pyramid, FAST with bucketing, depth look-up and descriptors (steps 1-3)."""
        o = self.options
        levels = [gray]
        for _ in range(1, o.num_levels):
            levels.append(cv2.pyrDown(levels[-1]))
        fast = cv2.FastFeatureDetector_create(  # type: ignore[attr-defined]
            round(self._fast_threshold), True)
        xy_all, lvl_all, desc_all = [], [], []
        n_level0 = 0
        for lv, img in enumerate(levels):
            kps = fast.detect(img)
            if lv == 0:
                n_level0 = len(kps)
            if not kps:
                continue
            xy = cv2.KeyPoint_convert(kps)  # type: ignore[attr-defined]  # [n, 2] float32
            resp = np.fromiter((k.response for k in kps), np.float32, len(kps))
            h, w = img.shape
            xy = np.round(xy)
            inside = ((xy[:, 0] >= _BORDER) & (xy[:, 0] < w - _BORDER)
                      & (xy[:, 1] >= _BORDER) & (xy[:, 1] < h - _BORDER))
            xy, resp = xy[inside], resp[inside]
            keep = _bucket(xy, resp, o.bucket_size, o.max_features_per_bucket, w)
            xy = xy[keep]
            xy_all.append(xy)
            lvl_all.append(np.full(len(xy), lv, np.int32))
            desc_all.append(_patches(img, xy.astype(np.int32)))
        # adapt the FAST threshold toward the target density (Fovis)
        target = gray.size / o.target_pixels_per_feature
        ratio = max(n_level0, 1) / target
        self._fast_threshold = float(np.clip(self._fast_threshold * ratio ** o.fast_adaptive_gain,
                                             o.fast_threshold_min, o.fast_threshold_max))
        if xy_all:
            xy = np.concatenate(xy_all).astype(np.float32)
            level = np.concatenate(lvl_all)
            desc = np.concatenate(desc_all)
        else:
            xy = np.zeros((0, 2), np.float32)
            level = np.zeros(0, np.int32)
            desc = np.zeros((0, PATCH * PATCH), np.float32)
        uv = xy * (2.0 ** level)[:, None].astype(np.float32)
        z = _depth_at(depth, uv, o.depth_edge_fraction)
        good = z > 0
        uv, z = uv[good], z[good]
        coarse = levels[-1]
        # at most 80 px wide, and at least 8 px high (a very wide image would otherwise
        # end 1 px high, where no window fits)
        while coarse.shape[1] > 80 and coarse.shape[0] >= 16:
            coarse = cv2.pyrDown(coarse)
        coarse = cv2.GaussianBlur(coarse.astype(np.float32), (0, 0), 1.0)
        return _Frame(levels=levels, depth=depth, xy=xy[good], level=level[good], uv=uv,
                      pts=self._backproject(uv, z), desc=desc[good], stamp=stamp,
                      coarse=coarse)

    def _rotation_guess(self, ref: _Frame, cur: _Frame) -> np.ndarray:
        """T_cur_ref [4, 4] of the pure rotation that best explains the global image shift.

        Fovis estimates an initial rotation by aligning heavily down-sampled images;
        here phase correlation of the <= 80 px images gives the shift (du, dv) of the
        content, and a rotation by du / fx about the optical y axis and -dv / fy about x
        moves the image by that much (small-angle pinhole model).
        """
        assert ref.coarse is not None and cur.coarse is not None
        h, w = cur.coarse.shape
        if min(h, w) < 2:  # no window to correlate in: no guess
            return np.eye(4)
        window = cv2.createHanningWindow((w, h), cv2.CV_32F)
        (dx, dy), _ = cv2.phaseCorrelate(ref.coarse, cur.coarse, window)
        scale = cur.levels[0].shape[1] / w
        b = math.atan2(dx * scale, self.K[0, 0])
        a = -math.atan2(dy * scale, self.K[1, 1])
        T = np.eye(4)
        T[:3, :3] = _se3_exp(np.array([0.0, 0.0, 0.0, a, b, 0.0]))[:3, :3]
        return T

    def _backproject(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        K = self.K
        x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
        y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
        return np.column_stack([x, y, z]).astype(np.float64)

    def _project(self, X: np.ndarray) -> np.ndarray:
        K = self.K
        z = X[:, 2]
        return np.column_stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]])

    # ------------------------------------------------------------------------------------
    def _track(self, cur: _Frame, t0: float) -> VOResult:
        ref = self._ref
        assert ref is not None
        o = self.options
        still = self._T_ref_prev  # no motion since the last tracked frame
        predict = still
        if o.use_prediction and self._step_dt is not None and self._ok_stamp is not None:
            # constant velocity: scale the last step to the time since the last tracked frame
            scale = (cur.stamp - self._ok_stamp) / self._step_dt
            if 0.0 < scale < 4.0:
                predict = still @ _scale_motion(self._step, scale)
        attempt = self._estimate(ref, cur, invert(predict), o.search_radius)
        if attempt.status is not Status.OK and predict is not still:
            # the prediction may be wrong (the chair stopped or turned): search around "still"
            retry = self._estimate(ref, cur, invert(still), 1.5 * o.search_radius)
            if retry.status is Status.OK or retry.num_inliers > attempt.num_inliers:
                attempt = retry
        if attempt.status not in (Status.OK, Status.OPTIMIZATION_FAILURE):
            # fast rotation after a gap: Fovis's initial rotation from image alignment
            retry = self._estimate(ref, cur, self._rotation_guess(ref, cur),
                                   1.5 * o.search_radius)
            if retry.status is Status.OK or retry.num_inliers > attempt.num_inliers:
                attempt = retry
        ninl, nmatch, err = attempt.num_inliers, attempt.num_matches, attempt.error
        if attempt.status is not Status.OK:
            res = self._fail(attempt.status, cur.stamp, t0, attempt.message, len(cur.level))
            res.num_matches, res.num_inliers, res.reprojection_error = nmatch, ninl, err
            return res
        assert attempt.T_cur_ref is not None and attempt.covariance is not None
        T_ref_cur = invert(attempt.T_cur_ref)
        assert ref.pose is not None and self._ok_stamp is not None
        pose = ref.pose @ T_ref_cur
        motion = invert(self._pose) @ pose
        dt = cur.stamp - self._ok_stamp
        speed = float(np.linalg.norm(motion[:3, 3])) / dt
        turn = math.acos(float(np.clip((np.trace(motion[:3, :3]) - 1.0) / 2.0, -1, 1))) / dt
        if speed > o.max_speed or turn > o.max_angular_speed:
            # physically implausible: typically repetitive texture at one depth, where a
            # rotation and a sideways shift explain the same (wrong) matches
            res = self._fail(Status.OPTIMIZATION_FAILURE, cur.stamp, t0,
                             f"implausible motion: {speed:.2f} m/s, {turn:.2f} rad/s",
                             len(cur.level))
            res.num_matches, res.num_inliers, res.reprojection_error = nmatch, ninl, err
            return res
        # covariance of ``motion`` = T_ref_prev^-1 T_ref_cur: that of T_ref_cur plus that of
        # T_ref_prev moved into the current frame (independent estimates, first order:
        # exp(-a) M exp(b) = M exp(b - Ad(M^-1) a)); T_ref_prev = I when it is the reference
        A = adjoint(invert(motion))
        cov = attempt.covariance + A @ self._ref_prev_cov @ A.T
        cov = 0.5 * (cov + cov.T)
        self._step, self._step_dt = motion, dt
        self._pose = pose
        self._ok_stamp = cur.stamp
        self._lost = 0
        keyframe = ninl < o.ref_frame_change_threshold
        if keyframe:
            cur.pose = pose.copy()
            self._ref = cur
            self._T_ref_prev = np.eye(4)
            self._ref_prev_cov = np.zeros((6, 6))
        else:
            self._T_ref_prev = T_ref_cur
            self._ref_prev_cov = attempt.covariance
        twist, twist_cov = None, None
        if dt <= o.max_twist_interval:  # else an average over a gap, not the current twist
            twist = self.extrinsic.planar_twist(motion, dt)
            twist_cov = self.extrinsic.twist_covariance(cov, dt, motion)
        return VOResult(status=Status.OK, stamp=cur.stamp, pose=pose.copy(), motion=motion,
                        covariance=cov, dt=dt, twist=twist, twist_covariance=twist_cov,
                        num_features=len(cur.level), num_matches=nmatch, num_inliers=ninl,
                        reprojection_error=err, keyframe_changed=keyframe,
                        elapsed=time.perf_counter() - t0)

    def _estimate(self, ref: _Frame, cur: _Frame, T_cur_ref_pred: np.ndarray,
                  radius: float) -> _Attempt:
        """Steps 4-7 and 9: match, clique, refine, covariance; the first rejection ends it."""
        try:
            matches = self._match(ref, cur, T_cur_ref_pred, radius)
            clique = self._clique(matches)
            fit = self._refine(matches, clique)
            cov = self._covariance(matches, fit)
        except _RejectedError as rejected:
            return rejected.attempt
        return _Attempt(Status.OK, fit.T, cov.covariance, len(fit.inliers), len(matches.P),
                        fit.error)

    def _match(self, ref: _Frame, cur: _Frame, T_cur_ref_pred: np.ndarray,
               radius: float) -> _Matches:
        """Steps 4-5: matches of reference features in ``cur`` around their predicted
        positions, refined to sub-pixel and with depth.

        Raises :class:`_RejectedError` when fewer than ``min_features_for_estimate`` remain.
        """
        o = self.options
        # 4. predicted positions of the reference features (level coordinates)
        Xp = ref.pts @ T_cur_ref_pred[:3, :3].T + T_cur_ref_pred[:3, 3]
        front = Xp[:, 2] > 0.05
        pred = np.full((len(Xp), 2), -1e6)
        pred[front] = self._project(Xp[front])
        scale_ref = (2.0 ** ref.level)[:, None]
        pred_l = pred / scale_ref
        # 5. candidate pairs within the search radius, same level (level as a far 3rd axis)
        a = np.column_stack([pred_l, ref.level * 1e5])
        b = np.column_stack([cur.xy, cur.level * 1e5])
        sdm = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius, output_type="ndarray")
        if len(sdm) < o.min_features_for_estimate:
            raise _RejectedError(Status.INSUFFICIENT_INLIERS, f"{len(sdm)} candidate matches")
        ii, jj = sdm["i"].astype(np.int64), sdm["j"].astype(np.int64)
        sad = np.abs(ref.desc[ii] - cur.desc[jj]).mean(axis=1)
        ok = sad < o.max_descriptor_distance
        ii, jj, sad = ii[ok], jj[ok], sad[ok]
        mutual = _mutual_best(ii, jj, sad, o.match_ratio, o.max_descriptor_distance)
        if len(mutual) < o.min_features_for_estimate:
            raise _RejectedError(Status.INSUFFICIENT_INLIERS, f"{len(mutual)} mutual matches",
                                 num_matches=len(mutual))
        if len(mutual) > o.max_matches:
            mutual = mutual[np.argsort(sad[mutual])[:o.max_matches]]
        mi, mj = ii[mutual], jj[mutual]
        uv_cur, good = _subpixel(ref, cur, mi, mj)
        zc = _depth_at(cur.depth, uv_cur, o.depth_edge_fraction)
        good &= zc > 0
        mi, uv_cur, zc = mi[good], uv_cur[good], zc[good]
        nmatch = len(mi)
        if nmatch < o.min_features_for_estimate:
            raise _RejectedError(Status.INSUFFICIENT_INLIERS,
                                 f"{nmatch} refined matches with depth", num_matches=nmatch)
        lvl = ref.level[mi]
        return _Matches(P=ref.pts[mi], Q=self._backproject(uv_cur, zc), uv_ref=ref.uv[mi],
                        uv_cur=uv_cur, level=lvl,
                        w=1.0 / (2.0 ** lvl))  # coarse-level positions are less precise

    def _clique(self, m: _Matches) -> np.ndarray:
        """Step 6: indices [k] of the rigidly consistent matches (see :func:`_max_clique`).

        Raises :class:`_RejectedError` when fewer than ``min_inliers`` are consistent.
        """
        o = self.options
        # 6. rigidity: pairwise distances must agree within the depth-noise band
        inl = _max_clique(m.P, m.Q, o.clique_inlier_threshold, o.clique_depth_coefficient)
        if len(inl) < o.min_inliers:
            raise _RejectedError(Status.INSUFFICIENT_INLIERS,
                                 f"{len(inl)} mutually consistent matches of {len(m.P)}",
                                 num_inliers=len(inl), num_matches=len(m.P))
        return inl

    def _refine(self, m: _Matches, inl: np.ndarray) -> _Refinement:
        """Step 7: absolute orientation on the clique, then Gauss-Newton on the bidirectional
        reprojection error with rejection of matches above ``outlier_reprojection_threshold``
        and re-refinement (at most four rounds).

        Raises :class:`_RejectedError` when the optimisation fails, too few inliers remain or
        their mean error is too high.
        """
        o = self.options
        nmatch = len(m.P)
        P, Q, uv_ref, uv_cur, w = m.P, m.Q, m.uv_ref, m.uv_cur, m.w
        T = _umeyama(P[inl], Q[inl])
        for round_ in range(4):
            T, H, r2, ok_gn, scores = self._gauss_newton(T, P[inl], Q[inl], uv_ref[inl],
                                                         uv_cur[inl], w[inl])
            if not ok_gn:
                raise _RejectedError(Status.OPTIMIZATION_FAILURE,
                                     "Gauss-Newton diverged or was singular",
                                     num_inliers=len(inl), num_matches=nmatch)
            if round_ == 3:
                break
            err_all = self._reprojection_errors(T, P, Q, uv_ref, uv_cur) * w
            keep = np.flatnonzero(err_all < o.outlier_reprojection_threshold)
            if len(keep) < o.min_inliers:
                raise _RejectedError(Status.INSUFFICIENT_INLIERS,
                                     f"{len(keep)} inliers after reprojection outlier rejection",
                                     num_inliers=len(keep), num_matches=nmatch)
            if np.array_equal(keep, inl):
                break
            inl = keep
        # mean reprojection error in pixels of each feature's pyramid level
        err = float(np.mean(self._reprojection_errors(T, P[inl], Q[inl], uv_ref[inl],
                                                      uv_cur[inl]) * w[inl]))
        if err > o.max_mean_reprojection_error:
            raise _RejectedError(Status.REPROJECTION_ERROR_TOO_HIGH,
                                 f"mean reprojection error {err:.2f} px",
                                 num_inliers=len(inl), num_matches=nmatch, error=err)
        return _Refinement(T=T, inliers=inl, H=H, cost=r2, error=err, scores=scores)

    def _covariance(self, m: _Matches, fit: _Refinement) -> _Covariance:
        """Step 9: covariance [6, 6] of the refined T_cur_ref (the module docstring's model).

        Raises :class:`_RejectedError` when the information matrix is singular or the
        covariance not finite, or when the translation std of the acceptance test exceeds
        ``max_translation_std`` (the inliers do not constrain the motion).
        """
        o = self.options
        n, nmatch, err = len(fit.inliers), len(m.P), fit.error

        def reject(status: Status, message: str) -> _RejectedError:
            return _RejectedError(status, message, num_inliers=n, num_matches=nmatch,
                                  error=err)

        if n < 7:  # (min_inliers is at least 7) no degree of freedom left for a covariance
            raise reject(Status.INSUFFICIENT_INLIERS, f"{n} inliers: a covariance needs 7")
        # acceptance test: translation std of sigma^2 H^-1 with sigma^2 >= 0.05 level px^2
        dof4 = max(1, 4 * n - 6)
        try:
            gate = max(fit.cost / dof4, 0.05) * np.linalg.inv(fit.H)
        except np.linalg.LinAlgError:
            raise reject(Status.OPTIMIZATION_FAILURE, "singular information matrix") from None
        if not np.all(np.isfinite(gate)):
            raise reject(Status.OPTIMIZATION_FAILURE, "non-finite covariance")
        gate = 0.5 * (gate + gate.T)
        t_std = math.sqrt(max(float(np.linalg.eigvalsh(gate[:3, :3])[-1]), 0.0))
        if t_std > o.max_translation_std:
            # inliers bunched on one small object or all far away: the fit is ill-posed
            raise reject(Status.INSUFFICIENT_INLIERS,
                         f"{n} inliers do not constrain the motion "
                         f"(translation std {1e3 * t_std:.1f} mm)")
        try:
            factor = cho_factor(fit.H)
        except np.linalg.LinAlgError:
            raise reject(Status.OPTIMIZATION_FAILURE, "singular information matrix") from None
        Hi = cho_solve(factor, np.eye(6))
        # (a) model part: a match's forward and backward residuals are one measurement seen
        # twice (their correlation is about -1), so 2 n independent residuals: sigma^2 =
        # cost / (2 (2 n - 6)) per residual, on nu = 2 n - 6 degrees of freedom, and the
        # information is H / 2; sigma^2 is at least the Lucas-Kanade stopping step's
        # uniform variance
        nu = 2 * n - 6
        sigma2 = max(fit.cost / (2.0 * nu), _LK_EPS**2 / 3.0)
        model = 2.0 * sigma2 * Hi
        # (b) cluster-robust part (Liang & Zeger 1986, with the CR1 small-sample factor): the
        # inliers' scores J_i^T W r_i summed per bucket_size image cell, so that errors that
        # nearby features share (and the residuals hide from (a)) count once per cell;
        # G cells give it G - 1 degrees of freedom (Cameron & Miller 2015, "A practitioner's
        # guide to cluster-robust inference", J. Human Resources 50(2), section VI)
        cell = np.floor(m.uv_cur[fit.inliers] / o.bucket_size).astype(np.int64)
        _, index = np.unique(cell[:, 0] * 1_000_003 + cell[:, 1], return_inverse=True)
        G = int(index.max()) + 1
        S = np.zeros((G, 6))
        np.add.at(S, index.ravel(), fit.scores)
        clustered = (Hi @ (S.T @ S) @ Hi) * (G / max(G - 1, 1) * (n - 1) / (n - 6))
        # degrees of freedom of the sum (Welch-Satterthwaite on tr(H C), unit-free), and the
        # Student-t predictive factor dof / (dof - 2): the covariance grows as the inliers
        # become few or bunched in few cells
        a, b = 2.0 * sigma2 * 6.0, float(np.trace(fit.H @ clustered))
        dof = max((a + b) ** 2 / (a * a / nu + b * b / max(G - 1, 1)), 3.0)
        few = 1.0 + (self.inlier_count_scale / n) ** self.inlier_count_power
        turn = 1.0 + (self.rotation_gain * _rotation_angle(fit.T)) ** 2
        cov = (self.covariance_scale * dof / (dof - 2.0) * few * turn) * (model + clustered)
        cov = 0.5 * (cov + cov.T)
        if not np.all(np.isfinite(cov)):
            raise reject(Status.OPTIMIZATION_FAILURE, "non-finite covariance")
        return _Covariance(covariance=cov, sigma2=sigma2, dof=dof, cells=G,
                           translation_std=t_std)

    def _reprojection_errors(self, T: np.ndarray, P: np.ndarray, Q: np.ndarray,
                             uv_ref: np.ndarray, uv_cur: np.ndarray) -> np.ndarray:
        """Per match max of forward and backward reprojection error (px) [n]."""
        X = P @ T[:3, :3].T + T[:3, 3]
        Y = (Q - T[:3, 3]) @ T[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            ef = np.linalg.norm(self._project(X) - uv_cur, axis=1)
            eb = np.linalg.norm(self._project(Y) - uv_ref, axis=1)
        e: np.ndarray = np.maximum(ef, eb)
        e[~np.isfinite(e) | (X[:, 2] <= 0) | (Y[:, 2] <= 0)] = np.inf
        return e

    def _gauss_newton(self, T: np.ndarray, P: np.ndarray, Q: np.ndarray, uv_ref: np.ndarray,
                      uv_cur: np.ndarray, w: np.ndarray) -> _GaussNewton:
        """Minimise the bidirectional reprojection error over T_cur_ref (as Fovis).

        r_f = pi(R P + t) - uv_cur, r_b = pi(R^T (Q - t)) - uv_ref, weights w^2, update
        T <- exp(delta) T with delta = (rho, omega) in the current frame. Jacobians:
        d(RP+t)/d delta = [I, -[X]x]; d(R^T(Q-t))/d delta = R^T [-I, [Q]x], so with
        A = d pi/dY R^T the backward rows are [-A, a x Q] per row a of A.
        Returns the :class:`_GaussNewton` (T, H [6, 6], weighted squared residual sum,
        success).
        """
        fx, fy = self.K[0, 0], self.K[1, 1]
        w2 = np.repeat(w * w, 2)
        prev_cost = math.inf
        H = np.eye(6)
        cost = math.inf
        scores = np.zeros((len(P), 6))
        for _ in range(self.options.gauss_newton_iterations):
            R, t = T[:3, :3], T[:3, 3]
            X = P @ R.T + t
            Y = (Q - t) @ R
            if np.any(X[:, 2] <= 1e-3) or np.any(Y[:, 2] <= 1e-3):
                return _GaussNewton(T, H, cost, False, scores)
            rf = self._project(X) - uv_cur
            rb = self._project(Y) - uv_ref
            Jf = _jac_forward(X, fx, fy)  # [n, 2, 6]
            A = _proj_jac(Y, fx, fy) @ R.T  # [n, 2, 3]
            Jb = np.concatenate([-A, np.cross(A, Q[:, None, :])], axis=2)
            J = np.concatenate([Jf, Jb]).reshape(-1, 6)
            r = np.concatenate([rf, rb]).reshape(-1)
            wr = np.concatenate([w2, w2])
            cost = float(np.sum(wr * r * r))
            H = J.T @ (J * wr[:, None])
            g = J.T @ (wr * r)
            # per match: its two forward rows (first 2n) and its two backward rows
            Jr = (J * (wr * r)[:, None]).reshape(2, len(P), 2, 6)
            scores = Jr.sum(axis=(0, 2))
            try:
                delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                return _GaussNewton(T, H, cost, False, scores)
            if not np.all(np.isfinite(delta)):
                return _GaussNewton(T, H, cost, False, scores)
            T = _se3_exp(delta) @ T
            if abs(prev_cost - cost) < 1e-4 * max(cost, 1e-12) or np.linalg.norm(delta) < 1e-7:
                break
            prev_cost = cost
        if not math.isfinite(cost) or np.linalg.norm(T[:3, 3]) > 10.0:
            return _GaussNewton(T, H, cost, False, scores)
        return _GaussNewton(T, H, cost, True, scores)


# ----------------------------------------------------------------------------------------
def _bucket(xy: np.ndarray, resp: np.ndarray, cell: int, per_cell: int, width: int) -> np.ndarray:
    """Indices of the ``per_cell`` strongest features in each ``cell`` x ``cell`` bucket."""
    if len(xy) == 0:
        return np.zeros(0, np.int64)
    ncol = width // cell + 1
    key = (xy[:, 1] // cell).astype(np.int64) * ncol + (xy[:, 0] // cell).astype(np.int64)
    order = np.lexsort((-resp, key))
    k = key[order]
    start = np.r_[0, np.flatnonzero(k[1:] != k[:-1]) + 1]
    rank = np.arange(len(k)) - np.repeat(start, np.diff(np.r_[start, len(k)]))
    kept: np.ndarray = order[rank < per_cell]
    return kept


_DY, _DX = np.mgrid[-_HALF:_HALF + 1, -_HALF:_HALF + 1]
_DY, _DX = _DY.ravel(), _DX.ravel()


def _mutual_best(ii: np.ndarray, jj: np.ndarray, sad: np.ndarray, match_ratio: float,
                 max_distance: float) -> np.ndarray:
    """Indices into the candidate pairs (ii, jj) [m] with distances sad [m] of the matches.

    Mutual best: the best j for each i and the best i for each j; a reference feature whose
    second-best candidate is nearly as good (best >= ``match_ratio`` x second) is ambiguous
    (repetitive texture: Lowe 2004, section 7.1 ratio test) and dropped. Every sad is below
    ``max_distance``, so sorting by index + sad / (1.01 max_distance) groups the candidates
    of one feature, best first (ties break by sad). Returns sorted indices.
    """
    scale = 1.0 / (max_distance * 1.01)  # sad * scale < 1: ties break by sad
    order = np.argsort(ii + sad * scale)
    if len(order):
        starts = np.r_[True, ii[order][1:] != ii[order][:-1]]
        first_i = order[starts]
        sorted_sad = sad[order]
        pos = np.flatnonzero(starts)
        has2 = ~np.r_[starts[1:], True][pos]  # the group has a second candidate
        ratio_ok = np.ones(len(pos), bool)
        ratio_ok[has2] = (sorted_sad[pos[has2]]
                          < match_ratio * sorted_sad[pos[has2] + 1])
        first_i = first_i[ratio_ok]
    else:
        first_i = order
    order = np.argsort(jj + sad * scale)
    first_j = order[np.r_[True, jj[order][1:] != jj[order][:-1]]] if len(order) else order
    return np.intersect1d(first_i, first_j)


def _subpixel(ref: _Frame, cur: _Frame, mi: np.ndarray,
              mj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel positions of the matches (ref feature mi [n] -> cur feature mj [n]).

    Lucas-Kanade on the reference feature's level image, started at the matched feature;
    returns the level-0 positions uv_cur [n, 2] and good [n] (converged, moved < 1.5 level
    px).
    """
    uv_cur = np.empty((len(mi), 2))
    good = np.zeros(len(mi), bool)
    for lv in np.unique(ref.level[mi]):
        sel = np.flatnonzero(ref.level[mi] == lv)
        p0 = ref.xy[mi[sel]].reshape(-1, 1, 2).astype(np.float32)
        p1 = cur.xy[mj[sel]].reshape(-1, 1, 2).astype(np.float32).copy()
        p1r, st, _ = cv2.calcOpticalFlowPyrLK(
            ref.levels[lv], cur.levels[lv], p0, p1, winSize=(PATCH, PATCH), maxLevel=0,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, _LK_EPS),
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p1r = p1r.reshape(-1, 2)
        shift = np.abs(p1r - p1.reshape(-1, 2)).max(axis=1)
        good[sel] = (st.ravel() == 1) & (shift < 1.5)
        uv_cur[sel] = p1r * (2.0 ** lv)
    return uv_cur, good


def _patches(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Zero-mean unit-variance PATCHxPATCH patches [n, PATCH^2] float32 around integer xy."""
    if len(xy) == 0:
        return np.zeros((0, PATCH * PATCH), np.float32)
    p: np.ndarray = img[xy[:, 1, None] + _DY[None], xy[:, 0, None] + _DX[None]].astype(
        np.float32)
    p -= p.mean(axis=1, keepdims=True)
    p /= np.maximum(p.std(axis=1, keepdims=True), 1.0)
    return p


def _depth_at(depth: np.ndarray, uv: np.ndarray, edge_fraction: float) -> np.ndarray:
    """Depth [n] at level-0 positions uv [n, 2]; 0 where invalid or on a depth edge.

    The nearest pixel's depth, rejected when any 4-neighbour at 2 px is invalid or differs
    by more than ``edge_fraction`` of it (a discontinuity makes the depth ambiguous).
    """
    h, w = depth.shape
    if len(uv) == 0:
        return np.zeros(0, np.float32)
    x = np.rint(uv[:, 0]).astype(np.int64)
    y = np.rint(uv[:, 1]).astype(np.int64)
    inside = (x >= 2) & (x < w - 2) & (y >= 2) & (y < h - 2)
    x, y = np.clip(x, 2, w - 3), np.clip(y, 2, h - 3)
    z = depth[y, x]
    ok = inside & (z > 0)
    for dx, dy in ((2, 0), (-2, 0), (0, 2), (0, -2)):
        zn = depth[y + dy, x + dx]
        ok &= (zn > 0) & (np.abs(zn - z) <= edge_fraction * z)
    return np.where(ok, z, 0.0).astype(np.float32)


def _max_clique(P: np.ndarray, Q: np.ndarray, thr: float, coeff: float) -> np.ndarray:
    """A clique of the rigidity-consistency graph, found by min-degree peeling.

    Graph (Howard 2008, "Real-time stereo visual odometry for autonomous ground vehicles",
    section III-C): matches i, j are consistent when | |P_i - P_j| - |Q_i - Q_j| | < thr +
    coeff (z_i^2 + z_j^2), z from P (the band grows with the z^2 depth noise).

    What is computed: the match with the fewest consistent partners among the remaining
    ones (the lowest index on ties) is deleted, again and again, until every remaining pair
    is consistent; the survivors are returned, sorted. They always form a clique, but not
    necessarily a maximum clique, nor even a maximal one (a deleted match can be consistent
    with every survivor). The cost is one O(n) step per deleted match after the O(n^2)
    graph.

    This is not Fovis's clique step. Fovis (``computeMaximallyConsistentClique``) *grows* a
    clique: matches sorted by their degree in the whole graph, the first one starts the
    clique, each next one joins when it is consistent with all members, and the scan stops
    at the first whose degree is below the clique size (Howard grows one too, choosing each
    next member by its degree among the candidates left). All are greedy approximations of
    the maximum clique; they agree when the true matches form one dense clique that the
    mismatches hardly touch, and can return different sets otherwise.
    """
    dP = cdist(P, P)  # [n, n]
    dQ = cdist(Q, Q)
    z2 = P[:, 2] ** 2
    C = np.abs(dP - dQ) < thr + coeff * (z2[:, None] + z2[None, :])  # diagonal is True
    Ci = C.view(np.uint8)
    deg = C.sum(axis=1).astype(np.int64)
    alive = np.ones(len(P), bool)
    n_alive = len(P)
    big = len(P) + 1
    while n_alive > 0:
        score = np.where(alive, deg, big)
        k = int(np.argmin(score))
        if score[k] >= n_alive:  # every remaining node is consistent with all the others
            break
        alive[k] = False
        deg -= Ci[k]
        n_alive -= 1
    return np.flatnonzero(alive)


def _umeyama(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Rigid T [4, 4] minimising sum |Q - (R P + t)|^2 (Umeyama 1991, eq. 39-42, c = 1)."""
    mp, mq = P.mean(0), Q.mean(0)
    S = (Q - mq).T @ (P - mp) / len(P)
    U, _, Vt = np.linalg.svd(S)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mq - R @ mp
    return T


def _jac_forward(X: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Jacobian [n, 2, 6] of pi(exp(delta) X) at delta = 0, delta = (rho, omega).

    d pi / d rho = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]] and d pi / d omega =
    [[-fx xy/z^2, fx (1 + x^2/z^2), -fx y/z], [-fy (1 + y^2/z^2), fy xy/z^2, fy x/z]]
    (Blanco 2010, "A tutorial on SE(3) transformation parameterizations", eq. 10.22-10.23).
    """
    x, y, iz = X[:, 0], X[:, 1], 1.0 / X[:, 2]
    xz, yz = x * iz, y * iz
    J = np.empty((len(X), 2, 6))
    J[:, 0, 0] = fx * iz
    J[:, 0, 1] = 0.0
    J[:, 0, 2] = -fx * xz * iz
    J[:, 0, 3] = -fx * xz * yz
    J[:, 0, 4] = fx * (1.0 + xz * xz)
    J[:, 0, 5] = -fx * yz
    J[:, 1, 0] = 0.0
    J[:, 1, 1] = fy * iz
    J[:, 1, 2] = -fy * yz * iz
    J[:, 1, 3] = -fy * (1.0 + yz * yz)
    J[:, 1, 4] = fy * xz * yz
    J[:, 1, 5] = fy * xz
    return J


def _proj_jac(X: np.ndarray, fx: float, fy: float) -> np.ndarray:
    """Jacobian [n, 2, 3] of the pinhole projection at camera points X [n, 3]."""
    iz = 1.0 / X[:, 2]
    J = np.zeros((len(X), 2, 3))
    J[:, 0, 0] = fx * iz
    J[:, 0, 2] = -fx * X[:, 0] * iz * iz
    J[:, 1, 1] = fy * iz
    J[:, 1, 2] = -fy * X[:, 1] * iz * iz
    return J


def _se3_exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential [4, 4] of xi = (rho, omega) (Barfoot 2017, eq. 7.83-7.86)."""
    rho, om = xi[:3], xi[3:]
    th = float(np.linalg.norm(om))
    W = np.array([[0.0, -om[2], om[1]], [om[2], 0.0, -om[0]], [-om[1], om[0], 0.0]])
    if th < 1e-10:
        R = np.eye(3) + W
        V = np.eye(3) + 0.5 * W
    else:
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th**2
        c = (th - math.sin(th)) / th**3
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + c * W @ W
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = V @ rho
    return T


def _se3_log(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm xi = (rho, omega) [6] of T [4, 4] (inverse of :func:`_se3_exp`)."""
    R = T[:3, :3]
    cos_th = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    th = math.acos(cos_th)
    if th < 1e-10:
        om = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
        small: np.ndarray = np.r_[T[:3, 3], om]
        return small
    om = th / (2.0 * math.sin(th)) * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0],
                                                 R[1, 0] - R[0, 1]])
    W = np.array([[0.0, -om[2], om[1]], [om[2], 0.0, -om[0]], [-om[1], om[0], 0.0]])
    b = (1.0 - math.cos(th)) / th**2
    c = (th - math.sin(th)) / th**3
    V = np.eye(3) + b * W + c * W @ W
    xi: np.ndarray = np.r_[np.linalg.solve(V, T[:3, 3]), om]
    return xi


def _rotation_angle(T: np.ndarray) -> float:
    """Angle (rad) of the rotation of the rigid transform T [4, 4]."""
    return math.acos(float(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def _scale_motion(T: np.ndarray, s: float) -> np.ndarray:
    """exp(s log T): the motion T scaled to s times the time."""
    return _se3_exp(s * _se3_log(T))
