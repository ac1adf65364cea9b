"""Calibration of the predictive variance so that the k-step 95 % ellipses cover 95 %.

Why: the FITC posterior underestimates the noise, and a one-step predictive variance does
not account for everything a k-step rollout gets wrong (model error, the odometry's own
error in the reference path, the approximation of the linearised propagation). Measured
on held-out data the raw ellipses cover too little, and by how much depends on the regime:
in slow steady driving the GP has seen many similar rows and its variance is tiny, while
the error has a floor that data cannot remove.

What: an affine map of each channel's one-step predictive variance,

    var_c' = (scale_c * var_c + floor_c) * factor(|v_0|),        c in (v, omega),

applied at every step of a rollout before the variance is propagated (so the velocity
covariances the node publishes and the position ellipses change together). ``scale``
corrects the GP's variance where it is informative; ``floor`` is process noise the model
does not represent, and is what inflates the ellipses most where the GP is most confident.

How (:func:`fit_calibration`): with the linearised propagation of
:mod:`asgp_ros.core.rollout` every position covariance is linear in the four numbers,

    Sigma(theta) = a_v P_v + a_w P_w + b_v U_v + b_w U_w,

where P_c is the covariance propagated from channel c's variance alone and U_c the one
propagated from a unit variance on channel c (four rollouts over the held-out cases).
theta >= 0 is fitted by maximising the Gaussian likelihood of the held-out position errors
at every step of the horizon (a proper scoring rule: it rewards ellipses of the right
shape and size, not only a coverage count). Then the cases are split into speed regimes
(thirds of the measured |v| at the rollout's start, edges stored with the map) and each
regime gets one factor on all four numbers so that its own coverage of the 95 % ellipse
is 95 %: how over-confident the ellipses are depends on the regime (slow driving more than
fast), so one global factor would over-cover one regime to under-cover another. The
regime is known when the prediction is made (the last measured velocity), so the node
applies the same map. The coverage that results is reported per horizon, per speed
regime, per steadiness of the joystick, per regime and steadiness together (slow steady
driving is where a GP is most over-confident) and per held-out recording, cross-validated
(:func:`asgp_ros.learning.training.calibrate`), so that what the map does not fit is visible.

What it does not promise: the calibration holds for data like the held-out part of the
training recordings (same chair, floors, users). Another floor changes the error; the
adaptive predictor tracks that online.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core.metrics import CHI2_2DOF_95, mahalanobis_sq

FloatArray = NDArray[np.float64]

#: Range of a stored scale (dimensionless) and floor (variance in the channel's units^2).
SCALE_RANGE = (0.0, 1e6)
FLOOR_RANGE = (0.0, 1e2)
#: Range of a speed regime's edge (m/s) and factor, and the number of regimes.
EDGE_RANGE = (0.0, 1e3)
FACTOR_RANGE = (1e-6, 1e6)
MAX_REGIMES = 8
#: Speed regimes fitted (equal thirds of the held-out cases' speeds) and the fewest
#: held-out cases (rollouts, whatever their number of steps) a regime needs to get its own
#: factor: below that a factor is noise.
REGIMES = 3
MIN_REGIME_CASES = 300
#: Position standard deviation (m) added in the likelihood fit only, so that a covariance
#: that is singular at the first steps (a chair at rest cannot move sideways) does not
#: make one exact hit dominate: 1 mm, below any odometry's resolution.
FIT_POSITION_STD_M = 1e-3
#: The coverage the ellipses are calibrated to.
TARGET_COVERAGE = 0.95


def _finite(x: int | float) -> bool:
    """A finite number (an integer too large for a float is not: a hostile file)."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


class CalibrationError(ValueError):
    """The calibration cannot be fitted or read; the message says why."""


@dataclass(frozen=True)
class VarianceCalibration:
    """var' = (scale * var + floor) * factor(speed) per channel (v, omega).

    ``factor`` depends on the regime of the rollout, told by the measured speed |v| at its
    start: ``speed_factors[i]`` applies for speeds in [speed_edges[i-1], speed_edges[i]).
    With no edges it is the one factor ``speed_factors[0]``. The default is the identity.
    """

    scale: tuple[float, float] = (1.0, 1.0)
    floor: tuple[float, float] = (0.0, 0.0)
    speed_edges: tuple[float, ...] = ()
    speed_factors: tuple[float, ...] = (1.0,)

    def __post_init__(self) -> None:
        for name, values, (lo, hi), count in (
                ("scale", self.scale, SCALE_RANGE, 2), ("floor", self.floor, FLOOR_RANGE, 2),
                ("speed_edges", self.speed_edges, EDGE_RANGE, None),
                ("speed_factors", self.speed_factors, FACTOR_RANGE, None)):
            if not isinstance(values, tuple | list):
                raise CalibrationError(f"calibration {name} must be a list of numbers")
            if count is not None and len(values) != count:
                raise CalibrationError(f"calibration {name} needs {count} values (v, omega), "
                                       f"got {len(values)}")
            for x in values:
                if isinstance(x, bool) or not isinstance(x, int | float) \
                        or not _finite(x) or not lo <= x <= hi:
                    raise CalibrationError(f"calibration {name} must hold numbers in "
                                           f"[{lo:g}, {hi:g}], got {x!r}")
            object.__setattr__(self, name, tuple(float(x) for x in values))
        if len(self.speed_edges) > MAX_REGIMES - 1:
            raise CalibrationError(f"at most {MAX_REGIMES} speed regimes, got "
                                   f"{len(self.speed_edges) + 1}")
        if len(self.speed_factors) != len(self.speed_edges) + 1:
            raise CalibrationError(f"{len(self.speed_edges)} speed edges need "
                                   f"{len(self.speed_edges) + 1} factors, got "
                                   f"{len(self.speed_factors)}")
        if any(b <= a for a, b in zip(self.speed_edges, self.speed_edges[1:], strict=False)):
            raise CalibrationError("calibration speed_edges must increase")

    @property
    def is_identity(self) -> bool:
        return (self.scale == (1.0, 1.0) and self.floor == (0.0, 0.0)
                and self.speed_factors == (1.0,))

    def regime(self, speed: ArrayLike) -> NDArray[np.intp]:
        """The speed regime (index into ``speed_factors``) of measured speeds |v| (any
        shape; the result has its shape)."""
        sp = np.abs(np.asarray(speed, dtype=np.float64))
        return np.searchsorted(np.asarray(self.speed_edges), sp, side="right")

    def factor(self, speed: ArrayLike) -> FloatArray:
        """The regime factor for measured speeds |v| (any shape; the result has its shape)."""
        return np.asarray(self.speed_factors)[self.regime(speed)]

    def coefficients(self, speed: ArrayLike | None) -> tuple[FloatArray, FloatArray]:
        """(scale, floor) arrays [..., 2] for rollouts starting at the given speeds [...]
        (None: a rollout of no particular speed, allowed only with a single regime)."""
        scale, floor = np.asarray(self.scale), np.asarray(self.floor)
        if speed is None:
            if self.speed_edges:
                raise CalibrationError("this calibration depends on the speed at the start")
            return scale * self.speed_factors[0], floor * self.speed_factors[0]
        f = self.factor(speed)[..., None]
        return scale * f, floor * f

    def apply(self, var: ArrayLike, speed: ArrayLike | None = None) -> FloatArray:
        """Calibrated variances of an array [..., 2] of (v, omega) variances (a new array),
        for rollouts starting at measured speeds ``speed`` [...]."""
        scale, floor = self.coefficients(speed)
        return np.asarray(var, dtype=np.float64) * scale + floor

    def to_dict(self) -> dict[str, list[float]]:
        return {"scale": list(self.scale), "floor": list(self.floor),
                "speed_edges": list(self.speed_edges),
                "speed_factors": list(self.speed_factors)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VarianceCalibration:
        """Parse :meth:`to_dict`'s output; CalibrationError naming the problem otherwise."""
        keys = {"scale", "floor", "speed_edges", "speed_factors"}
        if not isinstance(d, Mapping) or set(d) - keys:
            raise CalibrationError(f"calibration must be an object with {sorted(keys)}")
        try:
            return cls(scale=d["scale"], floor=d["floor"],
                       speed_edges=d.get("speed_edges", ()),
                       speed_factors=d.get("speed_factors", (1.0,)))
        except KeyError as exc:
            raise CalibrationError(f"calibration lacks {exc.args[0]!r}") from None


#: The four calibrations whose rollouts give the basis covariances (P_v, P_w, U_v, U_w).
BASIS = (
    VarianceCalibration(scale=(1.0, 0.0), floor=(0.0, 0.0)),
    VarianceCalibration(scale=(0.0, 1.0), floor=(0.0, 0.0)),
    VarianceCalibration(scale=(0.0, 0.0), floor=(1.0, 0.0)),
    VarianceCalibration(scale=(0.0, 0.0), floor=(0.0, 1.0)),
)


def combine(parts: FloatArray, theta: FloatArray) -> FloatArray:
    """Sigma(theta) = sum_i theta_i parts[i]: parts [4, ..., 2, 2], theta [4]."""
    return np.tensordot(np.asarray(theta, dtype=np.float64), parts, axes=1)


def _nll(log_theta: FloatArray, parts: FloatArray, err: FloatArray, eps2: float
         ) -> tuple[float, FloatArray]:
    """Mean Gaussian negative log likelihood of 2-d errors and its gradient in log theta."""
    theta = np.exp(log_theta)
    S = combine(parts, theta)
    a = S[:, 0, 0] + eps2
    d = S[:, 1, 1] + eps2
    b = 0.5 * (S[:, 0, 1] + S[:, 1, 0])
    det = a * d - b * b
    ex, ey = err[:, 0], err[:, 1]
    quad = (d * ex * ex - 2.0 * b * ex * ey + a * ey * ey) / det
    nll = 0.5 * float(np.mean(np.log(det) + quad))
    # Sigma^-1 and w = Sigma^-1 e, then dNLL/dtheta_i = 0.5 mean(tr(Sinv P_i) - w^T P_i w)
    ia, ib, id_ = d / det, -b / det, a / det
    wx = ia * ex + ib * ey
    wy = ib * ex + id_ * ey
    grad = np.empty(parts.shape[0])
    for i in range(parts.shape[0]):
        P = parts[i]
        pa, pd = P[:, 0, 0], P[:, 1, 1]
        pb = 0.5 * (P[:, 0, 1] + P[:, 1, 0])
        tr = ia * pa + 2.0 * ib * pb + id_ * pd
        wpw = wx * wx * pa + 2.0 * wx * wy * pb + wy * wy * pd
        grad[i] = 0.5 * float(np.mean(tr - wpw))
    return nll, grad * theta


def coverage(err: FloatArray, cov: FloatArray, chi2: float = CHI2_2DOF_95) -> float:
    """Fraction of errors [N, 2] inside the ellipses of covariances [N, 2, 2]."""
    if err.shape[0] == 0:
        return math.nan
    return float(np.mean(mahalanobis_sq(err, cov) <= chi2))


@dataclass(frozen=True)
class CalibrationFit:
    """Result of :func:`fit_calibration`.

    Attributes:
        calibration: the fitted map.
        ml_theta: the likelihood fit (a_v, a_w, b_v, b_w), before the regimes' factors.
        raw_coverage: pooled coverage of the uncalibrated ellipses.
        coverage: pooled coverage after calibration (on the pairs it was fitted on).
        cases: number of (case, step) pairs used.
    """

    calibration: VarianceCalibration
    ml_theta: tuple[float, float, float, float]
    raw_coverage: float
    coverage: float
    cases: int


def regime_edges(speed: FloatArray, regimes: int = REGIMES,
                 min_pairs: int = MIN_REGIME_CASES) -> tuple[float, ...]:
    """Edges splitting the speeds into ``regimes`` equal parts; fewer (down to none) when
    a part would hold fewer than ``min_pairs`` values or the speeds do not separate."""
    sp = np.abs(np.asarray(speed, dtype=np.float64))
    for n in range(min(regimes, MAX_REGIMES), 1, -1):
        edges = np.quantile(sp, np.arange(1, n) / n)
        if np.all(np.diff(edges) > 0) and edges[0] > 0:
            counts = np.bincount(np.searchsorted(edges, sp, side="right"), minlength=n)
            if counts.min() >= min_pairs:
                return tuple(float(e) for e in edges)
    return ()


def fit_calibration(parts: FloatArray, err: FloatArray, speed: FloatArray, *,
                    raw: FloatArray | None = None, target: float = TARGET_COVERAGE,
                    regimes: int = REGIMES, steps_per_case: int = 1) -> CalibrationFit:
    """Fit the variance map on held-out k-step errors (see the module docstring).

    Args:
        parts: [4, N, 2, 2] basis covariances (P_v, P_w, U_v, U_w) of N (case, step) pairs,
            from rollouts with the calibrations of :data:`BASIS`.
        err: [N, 2] position errors (reference - prediction) of the same pairs.
        speed: [N] measured |v| at the start of each pair's rollout (the regime).
        raw: [N, 2, 2] the uncalibrated covariances (= P_v + P_w) for the report, optional.
        target: the coverage of the 95 % ellipse to reach in every regime.
        regimes: speed regimes (equal parts of the pairs' speeds; fewer when a part would
            hold fewer than :data:`MIN_REGIME_CASES` cases).
        steps_per_case: pairs per case (the k steps of one rollout share its speed).

    Raises:
        CalibrationError: too few pairs, non-finite input, or an optimisation that fails.
    """
    parts = np.asarray(parts, dtype=np.float64)
    err = np.asarray(err, dtype=np.float64)
    speed = np.abs(np.asarray(speed, dtype=np.float64))
    if parts.ndim != 4 or parts.shape[0] != 4 or parts.shape[2:] != (2, 2):
        raise CalibrationError(f"basis covariances must be [4, N, 2, 2], got {parts.shape}")
    if err.shape != (parts.shape[1], 2) or speed.shape != (parts.shape[1],):
        raise CalibrationError(f"errors must be [{parts.shape[1]}, 2] and speeds "
                               f"[{parts.shape[1]}], got {err.shape} and {speed.shape}")
    if err.shape[0] < 20:
        raise CalibrationError(f"{err.shape[0]} held-out errors; calibration needs at least 20")
    if not (np.all(np.isfinite(parts)) and np.all(np.isfinite(err))
            and np.all(np.isfinite(speed))):
        raise CalibrationError("non-finite held-out errors, covariances or speeds")
    if not 0.5 <= target < 1.0:
        raise CalibrationError(f"target coverage must be in [0.5, 1), got {target}")
    eps2 = FIT_POSITION_STD_M**2
    x0 = np.log(np.array([1.0, 1.0, 1e-4, 1e-4]))
    bounds = [(math.log(1e-6), math.log(1e4))] * 2 + [(math.log(1e-10), math.log(1e2))] * 2
    import scipy.optimize  # here: loading a calibrated model needs no optimiser (0.3 s)

    res = scipy.optimize.minimize(_nll, x0, args=(parts, err, eps2), jac=True,
                                  method="L-BFGS-B", bounds=bounds,
                                  options={"maxiter": 500})
    if not np.all(np.isfinite(res.x)) or not math.isfinite(float(res.fun)):
        raise CalibrationError(f"the likelihood fit failed: {res.message}")
    theta = np.exp(res.x)
    # one factor per speed regime so that each regime's coverage meets the target
    d2 = mahalanobis_sq(err, combine(parts, theta))
    edges = regime_edges(speed, regimes, MIN_REGIME_CASES * max(1, steps_per_case))
    regime = np.searchsorted(np.asarray(edges), speed, side="right")
    factors = []
    for r in range(len(edges) + 1):
        with np.errstate(invalid="ignore"):  # inf - inf when more than 5 % are singular
            f = float(np.quantile(d2[regime == r], target) / CHI2_2DOF_95)
        if not math.isfinite(f) or f <= 0.0:
            raise CalibrationError("the held-out errors do not determine a coverage factor "
                                   "(the predicted covariance is singular where the error is "
                                   "not)")
        factors.append(min(max(f, FACTOR_RANGE[0]), FACTOR_RANGE[1]))
    cal = VarianceCalibration(scale=(float(theta[0]), float(theta[1])),
                              floor=(float(theta[2]), float(theta[3])),
                              speed_edges=edges, speed_factors=tuple(factors))
    cov_after = combine(parts, theta) * cal.factor(speed)[:, None, None]
    return CalibrationFit(calibration=cal,
                          ml_theta=(float(theta[0]), float(theta[1]), float(theta[2]),
                                    float(theta[3])),
                          raw_coverage=coverage(err, raw) if raw is not None else math.nan,
                          coverage=coverage(err, cov_after), cases=int(err.shape[0]))
