"""Online FITC posterior: a trained channel absorbs new rows, with exponential forgetting.

The hyperparameters (lengthscales, sf2, sn2, jitter) and the pseudo-inputs Z of a trained
:class:`~asgp_ros.core.sparse_gp.SparseGP` stay fixed; only the posterior moves.  All
quantities are in the trained model's standardised units (its x_mean, x_scale, y_mean,
y_scale: a row given in original units is converted with them).  What the rows teach is
measured against a prior mean: by default the trained posterior's mean (A9 below), else
the constant trained y_mean (A1 - A7 as written).

Sufficient statistics (Snelson & Ghahramani 2006; the factors of
:mod:`asgp_ros.core.posterior`, L = chol(Kuu), v = L^-1 k(Z, x) [M]).  FITC's diagonal
depends on its own row only (S&G eq. 6)::

    (A1)  lambda(x) = k(x, x) - v^T v + sn2
    (A2)  A = I + sum_i w_i v_i v_i^T / lambda_i          [M, M] (whitened Kuu + Kuf Lambda^-1 Kfu)
    (A3)  b = sum_i w_i v_i y_i / lambda_i                [M]    (whitened Kuf Lambda^-1 y)

so absorbing a row (x, y) is a rank-one addition to A and b.  With the weights w_i = 1 these
are exactly the batch FITC terms of :func:`asgp_ros.core.fitc.fitc_terms`
(A = LA LA^T, b = LA c), and the cached posterior follows as in P1 and P2::

    (A4)  LA = chol(A),   alpha = L^-T LA^-T LA^-1 b
    (A5)  C = Kuu^-1 - B^T B,   B = LA^-1 L^-1   (Kuu^-1 = L^-T L^-1 computed once)

A fresh Cholesky factorisation of A per update costs M^3/3 flops and C two M^3 products:
O(M^3) per published posterior, a few tenths of a millisecond at M = 80 (see
``benchmarks/adapt.py``; BLAS is limited to one thread during an update, as threading
these small products cost milliseconds on a loaded machine); the statistics themselves
are updated in O(M^2) per row, and :meth:`OnlinePosterior.absorb_rows` absorbs a block of
rows for one factorisation.  (A rank-one Cholesky update would not help: forgetting
scales the data part of A but not its prior part I, a full-rank change.)

The trained posterior is data too.  Its statistics are recovered from its factors,
P_T = LA LA^T - I and b_T = LA LA^T L^T alpha (A2, A3, A4 solved backwards), and kept
apart from the adapted data's P_D, b_D::

    (A6)  A = I + w_T P_T + P_D,   b = w_T b_T + b_D

Forgetting (half-life h in rows, or in seconds of the rows' time stamps): a row that
arrives dt after the previous absorbed one first multiplies the data by
gamma = 2^(-1/h) (rows) or 2^(-dt/h) (seconds), then adds itself with weight 1::

    (A7)  P_D <- gamma P_D + v v^T / lambda,   b_D <- gamma b_D + v y / lambda,
          n_D <- gamma n_D + 1,                w_T <- rho + gamma (w_T - rho)

Its own half-life h_T (``AdaptConfig.trained_half_life``, the data's by default) lets the
trained data fade faster than the new rows, with gamma_T = gamma^(h / h_T)::

    (A7') w_T <- rho + gamma_T (w_T - rho)

n_D, the adapted data's effective size, stays below 1 / (1 - gamma) (about h / ln 2 rows
for a half-life of h rows), so memory and information are bounded.  The trained data fade
with the same half-life, not to nothing but to the floor weight rho
(``AdaptConfig.trained_floor``): where the chair no longer drives, the posterior keeps the
trained function (its data counted rho times, as if their noise were sn2 / rho) instead of
falling back to the prior mean, while where it drives the recent rows outweigh them.
rho = 1 keeps the trained data whole (only the adapted rows fade); rho = 0 lets the
posterior decay to the prior Kuu.  Every term of A6 is positive semi-definite with
non-negative weights, so A >= I: A is always positive definite and C (A5) is between 0
and Kuu^-1.  Time stands still between absorbed rows (rejected rows do not decay
anything, and with a half-life in seconds a pause between two absorbed rows counts as
at most ``AdaptConfig.max_gap_s``): forgetting is driven by new data replacing old.

Safety (the issue's item 4).  The latent variance at x (P2, u = L^-1 k(Z, x)) is::

    (A8)  var_f(x) = sf2 - u^T u + u^T A^-1 u,   0 <= u^T A^-1 u <= u^T u = q(x, x)

whatever is absorbed, the variance at x stays within q(x, x) of the prior's sf2, and the
adapted variance is below the trained one by at most u^T A_t^-1 u <= q(x, x) (A_t the
trained A).  q(x, x), the part of the prior variance the pseudo-inputs explain, vanishes
outside their reach (in the tests the shrinkage is below 1e-8 relative from five
lengthscales on).  The rule: a row farther than ``max_distance`` lengthscales (scaled ARD
distance) from every pseudo-input is not absorbed (rejected as ``outside``), so
measurements beyond the training range never teach the posterior (through the edge
pseudo-inputs they would move the mean and shrink the variance at and beyond the edge).
With forgetting, the fading of the trained data usually raises the variance outside more
than the in-range rows lower it.  (The online variance scale of
:mod:`asgp_ros.core.adaptive`, which may narrow the adapted posterior's ellipses, is held
to the same bound by a floor at prediction time: the trained variance less q(x, x).)

The trained function as the prior mean (``AdaptConfig.trained_mean``, the default).  Above,
the rows teach the function itself, against the constant prior mean y_mean: once the
trained data have faded, the posterior knows only what the recent rows showed, and far
from them it falls back to y_mean.  With ``trained_mean`` the rows teach a correction g
to the trained posterior's mean m_T(x) = k(x, Z)^T alpha_T (P1): the model is
y = m_T(x) + g(x) + noise, g a zero-mean GP of the same kernel, and a row contributes
its residual r = y - m_T(x) to b, while the trained statistics enter A alone (their
residuals to their own fit are taken as zero: where the trained data are dense and not
yet forgotten, they hold the correction near zero)::

    (A9)  b_D <- gamma b_D + v (y - m_T(x)) / lambda,   b = b_D,
          alpha = alpha_T + L^-T A^-1 b_D   (A as in A6)

so before any row is absorbed the published mean is the trained one exactly, and A and C
(the variance) are those of A6 and A5 unchanged.  While the trained data keep their whole
weight (w_T = 1) A9 *is* A6: with L^T alpha_T = A_T^-1 b_T (A4) and
b_D(A9) = b_D(A6) - P_D L^T alpha_T, L^T alpha(A9) = A^-1 ((A - P_D) A_T^-1 b_T + b_D) =
A^-1 (b_T + b_D), since A - P_D = A_T.  They part only as the trained data fade: A6
forgets the trained function with them, A9 forgets only how sure it was of it (its
variance rises as in A6) and keeps it as the mean.  On a new floor the correction is
learnt where the chair drives, and the trained function still holds where it has not:
the trained floor's function is a far better starting point than a constant (measured by
``benchmarks/adapt_data.py``: the carpet model on 5 minutes of tile, 2.0 s success 93.8 %
with the trained mean against 90.2 % without; the tile model 98.0 %).

Noise of the absorbed rows (``AdaptConfig.row_noise``).  FITC fits the trained data with a
noise variance sn2 near zero and explains their scatter by its diagonal (A1), which is
small near the pseudo-inputs: a few hundred rows of a new floor, weighted by 1 / lambda,
are then taken as nearly exact, and the correction follows their noise.  ``row_noise``
adds a variance nu = row_noise * sf2 to the lambda of each absorbed row (not to the
trained data's)::

    (A10) lambda_i <- lambda(x_i) + nu   in the weights of A7 and A9

so a row teaches in proportion to how far its residual stands out of nu: with the prior
Kuu of amplitude sf2, nu / sf2 is the correction's noise-to-signal ratio.  The mean moves
more slowly on the first rows and smooths their noise; A stays >= I, so A8 and the safety
rule hold as before.  ``row_noise = 0`` is FITC's own weighting (and with w_T = 1 the
batch posterior exactly), and the default: on the reproduction's validation bags a row
noise of 0.1 - 1 sf2 lowered the adapting predictor's k-step success (README, "The rows'
noise"; ``benchmarks/adapt_half_life.py --row-noises``).

A row with NaN or inf, a stamp older than the last absorbed one, a non-positive lambda,
a failed factorisation or non-finite cached terms leave the published posterior and the
statistics exactly as they were; :attr:`AdaptStats.rejected` counts each reason.
:meth:`OnlinePosterior.reset` publishes the trained posterior object itself again.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core import blas, kernel
from asgp_ros.core.posterior import FitcPosterior
from asgp_ros.core.sparse_gp import SparseGP

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["AdaptConfig", "AdaptError", "AdaptStats", "OnlinePosterior", "RejectReason"]


_potrf = scipy.linalg.lapack.dpotrf
_trtrs = scipy.linalg.lapack.dtrtrs


def _trsolve(T: FloatArray, B: FloatArray, trans: int = 0) -> FloatArray:
    """T^-1 B (or T^-T B with ``trans=1``) for lower-triangular T, by LAPACK dtrtrs.

    The direct call skips scipy.linalg.solve_triangular's checks (microseconds that count
    at one row per update); T has a positive diagonal here, so info is always 0.
    """
    X, info = _trtrs(T, B, lower=1, trans=trans)
    if info != 0:  # pragma: no cover - a zero on the diagonal of a Cholesky factor
        raise np.linalg.LinAlgError(f"dtrtrs info {info}")
    return X  # type: ignore[no-any-return]


class AdaptError(ValueError):
    """A configuration or a trained posterior that cannot be adapted, or a mis-shaped call."""


#: Farthest an absorbed row's output may lie from the trained outputs' mean, in their
#: standard deviations: no chair's velocity (0.3 m/s of spread: 300 m/s).
MAX_OUTPUT_SCALES = 1e3


class RejectReason(StrEnum):
    """Why a row was not absorbed (the keys of :attr:`AdaptStats.rejected`)."""

    NONFINITE = "nonfinite"
    """The input, the output or the stamp holds NaN or inf (also after standardisation)."""
    TIME_ORDER = "time_order"
    """The stamp is older than the last absorbed row's."""
    OUTSIDE = "outside"
    """The input is farther than ``max_distance`` lengthscales from every pseudo-input."""
    LAMBDA = "lambda"
    """FITC's diagonal lambda (A1) of the row is not positive (round-off)."""
    FACTORISATION = "factorisation"
    """The Cholesky factorisation of A (A4) failed."""
    NONFINITE_TERMS = "nonfinite_terms"
    """The update gave non-finite statistics, alpha or C."""
    OUTPUT_RANGE = "output_range"
    """The output is more than MAX_OUTPUT_SCALES of the trained outputs' scale from their
    mean (y = 1e30 was absorbed, and the mean at the training rows became 1e27)."""


@dataclass(frozen=True)
class AdaptConfig:
    """Online adaptation settings (validated on construction).

    Attributes:
        half_life_s: forgetting half-life in seconds of the rows' stamps (A7), or None.
        max_gap_s: with ``half_life_s``, the longest interval between two absorbed rows
            that decays as it is; a longer one (a pause of the rows: VO lost, the stick
            silent, a forward clock jump) decays as this many seconds, so that only time
            with data forgets (an hour's jump took the adapted weight from 255 to 14 rows
            and the trained data's to nothing); inf: every interval as it is.
        half_life_rows: forgetting half-life in absorbed rows, or None.  At most one of
            the two; neither means no forgetting (every row counts forever).
        trained_floor: rho in [0, 1], the weight the trained statistics decay to (A7).
        trained_half_life: the trained statistics' own half-life, in the unit of the
            data's (seconds with ``half_life_s``, rows with ``half_life_rows``); None:
            the data's (A7').  Shorter than the data's: a new floor's rows are kept
            longer than the trained floor's.
        max_distance: rows farther than this many lengthscales from every pseudo-input
            are not absorbed (safety rule); None absorbs everywhere.
        trained_mean: the rows teach a correction to the trained posterior's mean (A9);
            False: they teach the function against the constant prior mean (A6).
        row_noise: nu / sf2 of A10, the noise added to each absorbed row's lambda as a
            fraction of the trained signal variance; 0 weights the rows as FITC does.
    """

    half_life_s: float | None = None
    max_gap_s: float = 1.0
    half_life_rows: float | None = None
    trained_floor: float = 0.01
    trained_half_life: float | None = None
    max_distance: float | None = 3.0
    trained_mean: bool = True
    row_noise: float = 0.0

    def __post_init__(self) -> None:
        if self.half_life_s is not None and self.half_life_rows is not None:
            raise AdaptError("give half_life_s or half_life_rows, not both")
        for name in ("half_life_s", "half_life_rows", "trained_half_life", "max_distance"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0.0):
                raise AdaptError(f"{name} must be a finite number > 0 or None, got {value!r}")
        if not self.max_gap_s > 0.0:  # (inf: every interval decays as it is)
            raise AdaptError(f"max_gap_s must be > 0, got {self.max_gap_s!r}")
        if isinstance(self.row_noise, bool) or not isinstance(self.row_noise, int | float) \
                or not (math.isfinite(self.row_noise) and 0.0 <= self.row_noise <= 1e6):
            raise AdaptError(f"row_noise must be a number in [0, 1e6], got {self.row_noise!r}")
        if not 0.0 <= self.trained_floor <= 1.0:
            raise AdaptError(f"trained_floor must be in [0, 1], got {self.trained_floor!r}")
        if self.trained_half_life is not None and not self.forgets:
            raise AdaptError("trained_half_life needs half_life_s or half_life_rows")
        if not isinstance(self.trained_mean, bool | np.bool_):
            raise AdaptError(f"trained_mean must be a bool, got {self.trained_mean!r}")
        object.__setattr__(self, "trained_mean", bool(self.trained_mean))

    @property
    def forgets(self) -> bool:
        """Whether old data fade at all."""
        return self.half_life_s is not None or self.half_life_rows is not None


@dataclass(frozen=True)
class AdaptStats:
    """What the node shows about one channel's adaptation.

    Attributes:
        rows_absorbed: rows absorbed since construction or the last reset.
        data_weight: n_D, the adapted rows' effective number (sum of their weights, A7).
        trained_weight: w_T, the weight of the trained statistics (1 until forgetting).
        effective_size: w_T N_T + n_D, with N_T the trained model's number of rows.
        last_update_s: wall-clock cost of the last successful update (statistics,
            factorisation and the published posterior), for ``last_update_rows`` rows.
        last_update_rows: rows absorbed by that update.
        rejected: rows not absorbed, by :class:`RejectReason` value.
    """

    rows_absorbed: int
    data_weight: float
    trained_weight: float
    effective_size: float
    last_update_s: float
    last_update_rows: int
    rejected: Mapping[str, int]


class _Stats(NamedTuple):
    """The adapted part of A6 and A7 (replaced, never modified in place)."""

    P_D: FloatArray  # [M, M] sum_i w_i v_i v_i^T / lambda_i
    b_data: FloatArray  # [M] sum_i w_i v_i y_i / lambda_i (y_i - m_T(x_i) with trained_mean)
    n_data: float  # sum_i w_i
    w_trained: float  # weight of the trained statistics
    t_last: float | None  # stamp of the last absorbed row (seconds), None before the first
    rows: int  # rows absorbed


class OnlinePosterior:
    """The online FITC posterior of one channel (see the module docstring).

    Args:
        trained: the trained posterior (with its LA factor).
        num_data: N_T, the number of rows it was trained on (for ``effective_size``).
        config: forgetting and safety settings.
        model: if given, every published posterior (and :meth:`reset`) is assigned to
            ``model.posterior``, so its predictions and the fused rollout read it.

    Not thread-safe for concurrent updates; readers of :attr:`posterior` (or of the
    model's) always see a complete, immutable posterior.
    """

    def __init__(self, trained: FitcPosterior, num_data: int, config: AdaptConfig | None = None,
                 model: SparseGP | None = None) -> None:
        if trained.LA is None:
            raise AdaptError("the trained posterior has no LA factor (a model file whose "
                             "var_matrix does not give it back); refit or re-save the model")
        if not (isinstance(num_data, int | np.integer) and num_data >= 0):
            raise AdaptError(f"num_data must be an integer >= 0, got {num_data!r}")
        self.config = config if config is not None else AdaptConfig()
        self.trained = trained
        self.num_data = int(num_data)
        self.model = model
        M = trained.num_inducing
        L, LA = trained.L, trained.LA
        eye = np.eye(M)
        self._Linv = scipy.linalg.solve_triangular(L, eye, lower=True,
                                                   check_finite=False)  # [M, M] L^-1
        self._Kinv = self._Linv.T @ self._Linv  # [M, M] Kuu^-1, the first term of A5
        A_T = LA @ LA.T
        self._P_T = A_T - eye  # [M, M] trained part of A (A6)
        self._b_T = A_T @ (L.T @ trained.alpha)  # [M] trained part of b (A4 backwards)
        # rows farther than max_distance lengthscales have k(x, z) < sf2 exp(-r^2 / 2) (K1)
        r = self.config.max_distance
        self._k_min = -1.0 if r is None else trained.signal_variance * math.exp(-0.5 * r * r)
        self._rejected = dict.fromkeys((str(reason) for reason in RejectReason), 0)
        self._last_cost = 0.0
        self._last_rows = 0
        self._reset_state()

    @classmethod
    def from_sparse_gp(cls, gp: SparseGP, config: AdaptConfig | None = None,
                       bind: bool = True) -> OnlinePosterior:
        """The online posterior of a trained SparseGP (bound to it when ``bind``)."""
        num_data = int(gp.get_state()["num_data"])
        return cls(gp.posterior, num_data, config, gp if bind else None)

    # ------------------------------------------------------------------ state

    def _reset_state(self) -> None:
        M = self.trained.num_inducing
        self._stats = _Stats(np.zeros((M, M)), np.zeros(M), 0.0, 1.0, None, 0)
        self._posterior = self.trained
        self._publish_to_model()

    def reset(self) -> None:
        """Forget every absorbed row: the trained posterior (the same object) again.

        The rejection counters and the last update's cost are kept (they describe the
        stream, not the posterior).
        """
        self._reset_state()

    def restart_clock(self) -> None:
        """Accept stamps from a restarted clock: forget the last absorbed row's stamp
        (what was absorbed stays; the next row decays nothing)."""
        self._stats = self._stats._replace(t_last=None)

    def _publish_to_model(self) -> None:
        if self.model is not None:
            self.model.posterior = self._posterior

    @property
    def posterior(self) -> FitcPosterior:
        """The current posterior (immutable; replaced by each successful update)."""
        return self._posterior

    @property
    def stats(self) -> AdaptStats:
        """Counters and sizes of the adaptation (a snapshot)."""
        s = self._stats
        return AdaptStats(
            rows_absorbed=s.rows, data_weight=s.n_data, trained_weight=s.w_trained,
            effective_size=s.w_trained * self.num_data + s.n_data, last_update_s=self._last_cost,
            last_update_rows=self._last_rows, rejected=MappingProxyType(dict(self._rejected)),
        )

    # ------------------------------------------------------------------ updates

    def absorb(self, x: ArrayLike, y: float, t: float | None = None) -> bool:
        """Absorb one row: input x [D] and output y in original units, stamp t (seconds).

        ``t`` is required with ``half_life_s`` (and checked for order whenever given).
        Returns whether the row was absorbed and a new posterior published.
        """
        xa = np.asarray(x, dtype=np.float64)
        if xa.shape != (self.trained.num_features,):
            raise AdaptError(f"x has shape {xa.shape}, expected ({self.trained.num_features},)")
        return self.absorb_rows(xa[None], [y], None if t is None else [t]) == 1

    def absorb_rows(self, X: ArrayLike, y: ArrayLike, t: ArrayLike | None = None) -> int:
        """Absorb a block of rows in order and publish one posterior for them.

        Args:
            X: [n, D] inputs, y: [n] outputs (original units), t: [n] stamps in seconds
                (required with ``half_life_s``).

        Returns:
            The number of rows absorbed.  Rows refused one by one (non-finite, outside,
            out of order, lambda) are counted and skipped; if the block's factorisation
            fails or gives non-finite terms, none of its rows is absorbed (all counted)
            and the previous posterior stays.
        """
        start = time.perf_counter()
        post = self.trained
        D = post.num_features
        Xa = np.asarray(X, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        if Xa.ndim != 2 or Xa.shape[1] != D:
            raise AdaptError(f"X has shape {Xa.shape}, expected (n, {D})")
        n = Xa.shape[0]
        if ya.shape != (n,):
            raise AdaptError(f"y has shape {ya.shape}, expected ({n},)")
        ta: FloatArray | None = None
        if t is not None:
            ta = np.asarray(t, dtype=np.float64)
            if ta.shape != (n,):
                raise AdaptError(f"t has shape {ta.shape}, expected ({n},)")
        elif self.config.half_life_s is not None:
            raise AdaptError("half_life_s forgetting needs the rows' time stamps t")
        if n == 0:
            return 0
        with blas.single_thread():
            return self._absorb(Xa, ya, ta, start)

    def _absorb(self, Xa: FloatArray, ya: FloatArray, ta: FloatArray | None, start: float
                ) -> int:
        post = self.trained
        with np.errstate(over="ignore", invalid="ignore"):  # checked just below
            Xs = (Xa - post.x_mean) / post.x_scale  # [n, D] standardised
            ys = (ya - post.y_mean) / post.y_scale  # [n]
        finite = np.all(np.isfinite(Xs), axis=1) & np.isfinite(ys)
        if ta is not None:
            finite &= np.isfinite(ta)
        Xs[~finite] = 0.0
        ys[~finite] = 0.0
        in_range = np.abs(ys) <= MAX_OUTPUT_SCALES
        K = kernel.cross(Xs, post.kernel)  # [n, M] k(x, Z) (K2)
        if self.config.trained_mean:
            with np.errstate(over="ignore", invalid="ignore"):  # checked in _posterior_of
                ys = ys - K @ post.alpha  # the residual to the trained mean (A9)
        V = _trsolve(post.L, K.T)  # [M, n] L^-1 Kuf
        lam = post.signal_variance + post.noise_variance - np.einsum("mn,mn->n", V, V)  # A1
        inside = K.max(axis=1) >= self._k_min
        lam_ok = lam > 0.0

        s = self._stats
        keep, gammas, t_last = self._select(finite, in_range, inside, lam_ok, ta, s.t_last)
        if not keep:
            return 0
        idx = np.asarray(keep)
        g = np.asarray(gammas)  # decay applied before each kept row (A7)
        total = float(np.prod(g))
        # weight of kept row i at the end of the block: the decays of the rows after it
        after = np.concatenate([np.cumprod(g[:0:-1])[::-1], [1.0]])  # [n_keep]
        Vk = V[:, idx]  # [M, n_keep]
        wk = after / (lam[idx] + self.config.row_noise * post.signal_variance)  # A10
        with np.errstate(over="ignore", invalid="ignore"):  # checked in _posterior_of
            P_D = total * s.P_D + (Vk * wk) @ Vk.T  # A7, rank n_keep
            b_D = total * s.b_data + Vk @ (wk * ys[idx])
        rho = self.config.trained_floor
        w_T = rho + self._trained_decay(total) * (s.w_trained - rho) \
            if self.config.forgets else 1.0
        new = _Stats(P_D, b_D, total * s.n_data + float(after.sum()), w_T, t_last,
                     s.rows + len(keep))
        published = self._posterior_of(new)
        if isinstance(published, RejectReason):
            self._rejected[str(published)] += len(keep)
            return 0
        self._stats = new
        self._posterior = published
        self._publish_to_model()
        self._last_cost = time.perf_counter() - start
        self._last_rows = len(keep)
        return len(keep)

    def _trained_decay(self, total: float) -> float:
        """The trained weight's decay over a block whose data decay by ``total`` (A7')."""
        cfg = self.config
        h = cfg.half_life_s if cfg.half_life_s is not None else cfg.half_life_rows
        if cfg.trained_half_life is None or h is None:
            return total
        return float(total ** (h / cfg.trained_half_life))

    def _select(self, finite: BoolArray, in_range: BoolArray, inside: BoolArray,
                lam_ok: BoolArray, ta: FloatArray | None, t_last: float | None
                ) -> tuple[list[int], list[float], float | None]:
        """The rows to keep, in order, with the decay before each, and the last stamp."""
        keep: list[int] = []
        gammas: list[float] = []
        cfg = self.config
        row_gamma = 1.0 if cfg.half_life_rows is None else 2.0 ** (-1.0 / cfg.half_life_rows)
        for i in range(finite.shape[0]):
            if not finite[i]:
                reason = RejectReason.NONFINITE
            elif not in_range[i]:
                reason = RejectReason.OUTPUT_RANGE
            elif not inside[i]:
                reason = RejectReason.OUTSIDE
            elif not lam_ok[i]:
                reason = RejectReason.LAMBDA
            elif ta is not None and t_last is not None and ta[i] < t_last:
                reason = RejectReason.TIME_ORDER
            else:
                gamma = row_gamma
                if ta is not None:
                    ti = float(ta[i])
                    if cfg.half_life_s is not None and t_last is not None:
                        gap = min(ti - t_last, cfg.max_gap_s)  # a pause forgets nothing
                        gamma = 2.0 ** (-gap / cfg.half_life_s)
                    t_last = ti
                keep.append(i)
                gammas.append(gamma)
                continue
            self._rejected[str(reason)] += 1
        return keep, gammas, t_last

    def _posterior_of(self, s: _Stats) -> FitcPosterior | RejectReason:
        """The cached posterior of the statistics ``s`` (A4 - A6), or why there is none."""
        post = self.trained
        M = post.num_inducing
        trained_mean = self.config.trained_mean
        b = s.b_data if trained_mean else s.w_trained * self._b_T + s.b_data  # A9 / A6
        if not np.all(np.isfinite(b)):
            return RejectReason.NONFINITE_TERMS
        A = s.w_trained * self._P_T + s.P_D  # A6 (dpotrf reads the lower triangle only)
        A[np.diag_indices(M)] += 1.0
        LA, info = _potrf(A, lower=1, clean=1, overwrite_a=1)
        if info != 0:  # a non-finite A gives info != 0 or a non-finite LA, and C below
            return RejectReason.FACTORISATION
        c = _trsolve(LA, b)
        alpha = _trsolve(post.L, _trsolve(LA, c, trans=1), trans=1)  # A4
        if trained_mean:
            alpha = alpha + post.alpha  # A9
        B = _trsolve(LA, self._Linv)  # [M, M] LA^-1 L^-1
        S = self._Kinv - B.T @ B  # A5, as posterior.variance_matrix
        C = 0.5 * (S + S.T)
        if not (np.all(np.isfinite(alpha)) and np.all(np.isfinite(C))):
            return RejectReason.NONFINITE_TERMS
        return post.with_weights(LA, alpha, C)
