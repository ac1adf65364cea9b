"""The paper's path-prediction metrics and the selection of test cases.

Fan et al. (ICRA 2018), Sec. V: for a test time step t with s past and k future samples
inside one valid segment, the velocities V_t..V_{t+k-1} are predicted by the recurrent
sliding window (Algorithm 1) from the recorded past and the recorded future joystick,
integrated by the unicycle model (eq. 5) from the origin, and the (x, y) at the horizon is
compared with the path integrated the same way from the recorded velocities. The
"success rate" is the fraction of such predictions whose position error at the horizon is
at most 10 cm.

Indexing (see ``rollout``): the pose path starts at the origin at t0 = time of the last
measured sample V_{t-1}; pose i (0-based) is at t0 + (i+1) dt, so the horizon of k steps is
pose k-1, at time t_{t+k-1}. The reference path integrates V_{t-1}, V_t, ..., V_{t+k-1}.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: chi-square quantile with 2 degrees of freedom at 0.95: -2 ln(0.05) = 5.991 (closed form
#: for 2 dof): the squared Mahalanobis radius of a 95% position ellipse.
CHI2_2DOF_95 = -2.0 * math.log(0.05)
#: chi-square quantile with 1 degree of freedom at 0.95 (1.95996^2): the squared radius of
#: a 95% interval of one Gaussian quantity (a velocity's one-step innovation).
CHI2_1DOF_95 = 3.841458820694124

#: The paper's prediction horizons in seconds (k = 5, 7, 10 steps at 5 Hz).
HORIZONS_S: tuple[float, ...] = (1.0, 1.4, 2.0)

#: The paper's success threshold on the position error at the horizon (m).
THRESHOLD_M = 0.10


def horizon_key(h: float) -> str:
    """JSON key of a horizon in seconds: 1.0 -> "1.0", 1.4 -> "1.4", 1.25 -> "1.25"."""
    s = f"{h:.3f}".rstrip("0")
    return s + "0" if s.endswith(".") else s


def horizon_steps(horizons_s: list[float] | tuple[float, ...], rate_hz: float) -> list[int]:
    """Horizons in seconds -> numbers of steps k = h * rate rounded half up (1.0, 1.4, 2.0 s
    -> 5, 7, 10; 0.5 s at 5 Hz -> 3, not Python's round-half-even 2).

    Raises ValueError for a non-positive horizon, or one shorter than half a step.
    """
    if not rate_hz > 0.0 or not math.isfinite(rate_hz):
        raise ValueError(f"rate must be positive and finite, got {rate_hz}")
    steps = []
    for h in horizons_s:
        if not math.isfinite(h) or h <= 0.0:
            raise ValueError(f"horizon must be a positive number of seconds, got {h}")
        k = math.floor(h * rate_hz + 0.5)
        if k < 1:
            raise ValueError(
                f"horizon {h} s is shorter than one step at {rate_hz} Hz ({1.0 / rate_hz} s)"
            )
        steps.append(k)
    return steps


def scored_horizons(horizons_s: Sequence[float], rate_hz: float) -> tuple[float, ...]:
    """The horizons as a ``rate_hz`` grid scores them: each at its steps (``horizon_steps``)
    k / rate, once (1.0 and 1.4 s at 1 Hz: 1.0 s)."""
    out: list[float] = []
    for k in horizon_steps(list(horizons_s), rate_hz):
        if k / rate_hz not in out:
            out.append(k / rate_hz)
    return tuple(out)


def segment_runs(segment: NDArray[np.integer]) -> list[tuple[int, int]]:
    """Maximal runs [start, stop) of equal, non-negative segment ids.

    Args:
        segment: [T] segment id per grid point, -1 where the point is invalid.
    """
    seg = np.asarray(segment).reshape(-1)
    if seg.size == 0:
        return []
    change = np.flatnonzero(np.diff(seg) != 0) + 1
    starts = np.concatenate(([0], change))
    stops = np.concatenate((change, [seg.size]))
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if seg[a] >= 0]


def case_indices(segment: NDArray[np.integer], lags: int, steps: int) -> IntArray:
    """Target indices t with grid points t-lags .. t+steps-1 all inside one valid segment.

    Args:
        segment: [T] segment id per grid point (-1 invalid).
        lags: s, the number of past samples the model needs (>= 1: V_{t-1} starts the path).
        steps: k, the number of predicted steps (>= 1).

    Returns:
        [N] sorted target indices t (the first predicted step).
    """
    if lags < 1 or steps < 1:
        raise ValueError(f"need lags >= 1 and steps >= 1, got lags={lags}, steps={steps}")
    out = [np.arange(a + lags, b - steps + 1) for a, b in segment_runs(segment)]
    out = [o for o in out if o.size]
    if not out:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate(out).astype(np.int64)


def windows(series: FloatArray, idx: IntArray, start: int, length: int) -> FloatArray:
    """Gather series[t + start : t + start + length] for every t in idx.

    Args:
        series: [T, C] grid series.
        idx: [N] indices.

    Returns:
        [N, length, C].
    """
    offsets = np.arange(start, start + length)
    return cast(FloatArray, np.asarray(series)[np.asarray(idx)[:, None] + offsets[None, :]])


def relative_displacement(pose0: FloatArray, pose1: FloatArray) -> FloatArray:
    """(x, y) of pose1 expressed in the body frame of pose0.

    Args:
        pose0, pose1: [N, 3] (x, y, theta) in a common world frame.

    Returns:
        [N, 2] displacement rotated by -theta0 (the frame the predictions are made in).
    """
    d = pose1[:, :2] - pose0[:, :2]
    c, s = np.cos(pose0[:, 2]), np.sin(pose0[:, 2])
    return np.stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]), axis=1)


def mahalanobis_sq(err: FloatArray, cov: FloatArray) -> FloatArray:
    """Squared Mahalanobis distance e^T Sigma^-1 e of 2-vectors, closed-form 2x2 inverse.

    Args:
        err: [N, 2] errors; cov: [N, 2, 2] covariances.

    Returns:
        [N]; inf where the covariance is not positive definite (a zero covariance covers
        nothing but an exact hit, which is counted as 0).
    """
    a, b, d = cov[:, 0, 0], 0.5 * (cov[:, 0, 1] + cov[:, 1, 0]), cov[:, 1, 1]
    det = a * d - b * b
    ex, ey = err[:, 0], err[:, 1]
    quad = d * ex * ex - 2.0 * b * ex * ey + a * ey * ey
    out = np.full(err.shape[0], np.inf)
    pd = (det > 0.0) & (a > 0.0)
    out[pd] = quad[pd] / det[pd]
    exact = ~pd & (ex == 0.0) & (ey == 0.0)
    out[exact] = 0.0
    return out


@dataclass(frozen=True)
class HorizonResult:
    """Scores of one model at one horizon over one set of test cases."""

    horizon_s: float
    steps: int
    cases: int
    success_rate: float  # fraction in [0, 1]
    median_error_m: float
    mean_error_m: float
    p90_error_m: float
    coverage_95: float | None  # fraction of cases inside the predicted 95% ellipse
    threshold_m: float

    def to_json(self) -> dict[str, object]:
        return {
            "horizon_s": self.horizon_s,
            "steps": self.steps,
            "cases": self.cases,
            "success_rate": self.success_rate,
            "median_error_m": self.median_error_m,
            "mean_error_m": self.mean_error_m,
            "p90_error_m": self.p90_error_m,
            "coverage_95": self.coverage_95,
            "threshold_m": self.threshold_m,
        }


def score(
    pred_xy: FloatArray,
    ref_xy: FloatArray,
    *,
    horizon_s: float,
    steps: int,
    threshold_m: float,
    pos_cov: FloatArray | None = None,
) -> tuple[HorizonResult, FloatArray]:
    """Success rate, error statistics and ellipse coverage of predictions at one horizon.

    Args:
        pred_xy: [N, 2] predicted position at the horizon.
        ref_xy: [N, 2] reference position (integrated recorded VO, or ground truth).
        pos_cov: [N, 2, 2] predicted position covariance, or None for a deterministic model
            (then no coverage is reported).

    Returns:
        (result, errors [N]). Raises ValueError when there are no cases or non-finite
        predictions (a NaN must never be counted as a miss silently).
    """
    pred_xy = np.asarray(pred_xy, dtype=np.float64)
    ref_xy = np.asarray(ref_xy, dtype=np.float64)
    if pred_xy.shape != ref_xy.shape or pred_xy.ndim != 2 or pred_xy.shape[1] != 2:
        raise ValueError(f"pred {pred_xy.shape} and reference {ref_xy.shape} must be [N, 2]")
    n = pred_xy.shape[0]
    if n == 0:
        raise ValueError(f"no test cases for the {horizon_s} s horizon")
    if not np.all(np.isfinite(pred_xy)):
        raise ValueError(f"{int(np.sum(~np.isfinite(pred_xy)))} non-finite predicted positions")
    if not np.all(np.isfinite(ref_xy)):
        raise ValueError("non-finite reference positions")
    if not threshold_m > 0.0:
        raise ValueError(f"threshold must be positive, got {threshold_m}")
    err_vec = pred_xy - ref_xy
    err = np.hypot(err_vec[:, 0], err_vec[:, 1])
    coverage = None
    if pos_cov is not None:
        cov = np.asarray(pos_cov, dtype=np.float64)
        if cov.shape != (n, 2, 2):
            raise ValueError(f"position covariance must be [{n}, 2, 2], got {cov.shape}")
        if np.any(cov[:, 0, 0] > 0.0) or np.any(cov[:, 1, 1] > 0.0):
            d2 = mahalanobis_sq(err_vec, cov)
            coverage = float(np.mean(d2 <= CHI2_2DOF_95))
    result = HorizonResult(
        horizon_s=float(horizon_s),
        steps=int(steps),
        cases=int(n),
        success_rate=float(np.mean(err <= threshold_m)),
        median_error_m=float(np.median(err)),
        mean_error_m=float(np.mean(err)),
        p90_error_m=float(np.quantile(err, 0.9)),
        coverage_95=coverage,
        threshold_m=float(threshold_m),
    )
    return result, err
