"""Sparse GP regression with pseudo-inputs (SPGP / FITC) and an ARD squared-exponential kernel.

Model (Snelson & Ghahramani 2006, "Sparse Gaussian Processes using Pseudo-inputs", NIPS;
the FITC name is from Quiñonero-Candela & Rasmussen 2005, JMLR 6, section 5), with
X [N, D], y [N], pseudo-inputs Z [M, D], Kuf = k(Z, X) [M, N], Kuu = k(Z, Z) [M, M]::

    k(x, x') = sf2 * exp(-0.5 * sum_d (x_d - x'_d)^2 / l_d^2)   (ARD SE, kernel.py K1)
    y | f ~ N(f, sn2),   p(y) = N(y | 0, Qff + Lambda)                  (S&G eq. 6)
    Qff = Kfu Kuu^-1 Kuf,   Lambda = diag(Kff - Qff) + sn2 I

The pieces, each citing the equations it implements:

* the kernel and its derivatives: :mod:`asgp_ros.core.kernel` (K1 - K4);
* the FITC terms (:class:`asgp_ros.core.fitc.FitcTerms`,
  :func:`asgp_ros.core.fitc.fitc_terms`): the shared Cholesky factors and the log marginal
  likelihood (S&G eq. 6 and 8 by the matrix inversion and determinant lemmas);
* the gradient (:func:`asgp_ros.core.fitc.fitc_gradient`): Snelson's derivatives of the
  likelihood in Lambda, Kuf and Kuu and the chain rule through the kernel (K3, K4); the
  optimiser minimises the negative log marginal likelihood (:meth:`SparseGP._objective`);
* the prediction cache (:class:`asgp_ros.core.posterior.FitcPosterior`): alpha and C of
  the predictive equations (S&G eq. 5), built from the FITC terms once after fitting and
  read by :meth:`SparseGP.predict`, the fused rollout and the model file;
* :class:`SparseGP` (this module): standardisation, initialisation and the optimiser.

The M pseudo-inputs Z and the hyperparameters (log lengthscales, log signal variance,
log noise variance) are learned jointly by maximising the FITC log marginal likelihood
with its analytic gradient (including dL/dZ) and L-BFGS-B with bounds.  Training costs
O(N M^2) time and O(N M) memory; after fitting, the posterior is cached so that a
prediction costs O(M) for the mean and O(M^2) for the variance per test point.

One likelihood-and-gradient evaluation costs five O(N M^2) BLAS-3 calls (two for the
likelihood, three for the gradient) and a few O(N M D) products, on reused column blocks
of the data that are evaluated in parallel threads with single-threaded BLAS.

Internally inputs are standardised per column and the outputs to zero mean and unit
variance; every public quantity (parameters, predictions, log marginal likelihood) is in
the original units.  The prior mean of y is the training mean (a constant, not learned);
the log marginal likelihood is that of the original y under this model, i.e. the
standardised evidence minus N log(std(y)).

Numerical notes:

* ``Kuu`` gets a jitter of ``jitter * sf2`` on its diagonal (relative to the signal
  variance, so it does not depend on the output units; GPy adds an absolute 1e-6).  The
  jitter is part of the model: likelihood, gradient and prediction all use the same Kuu,
  so duplicated or near-duplicated pseudo-inputs stay factorisable (this is how a
  singular kernel matrix is recovered).  With ``jitter=0`` a singular Kuu raises
  :class:`SparseGPError`.
* Inside the optimiser a failed Cholesky factorisation is a rejected step: the objective
  there is a finite wall above every value seen (``inf`` would make scipy's L-BFGS-B stop,
  see :class:`_BestPoint`), and a run that still ends on a failure resumes from the best
  point.  Outside (``from_params``, the initial point, the final posterior) it raises
  :class:`SparseGPError` saying what to change.
* Training inputs, targets and pseudo-inputs are real and within +-``MAX_ABS_VALUE``
  (1e15, a model file's bound); a prediction's inputs are any finite reals, and far beyond
  the data (``_PREDICT_REACH`` standardised units, where the kernel is 0 to the last bit)
  it is the prior.
* A negative predictive latent variance (cancellation in sf2 - k S k^T) is clipped to 0;
  beyond round-off level (below -1e-8 sf2) a RuntimeWarning says so.
* FITC tends to underestimate the noise variance (its input-dependent Lambda absorbs part
  of the noise; Bauer, van der Wilk & Rasmussen, NIPS 2016); the predictive variance of
  a new observation stays calibrated, so use it rather than ``noise_variance`` alone.
"""

from __future__ import annotations

import contextlib
import logging
import math
import warnings
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from asgp_ros.core import blas, fitc, posterior
from asgp_ros.core.fitc import FactorisationError, Params, Workspace
from asgp_ros.core.posterior import FitcPosterior, PosteriorError

if TYPE_CHECKING:  # imported where a fit runs: loading a model needs no optimiser (0.3 s)
    import scipy.optimize

FloatArray = NDArray[np.float64]
ProgressCallback = Callable[[int, float], None]

_LOG = logging.getLogger(__name__)

# Bounds of the optimiser, in standardised units (inputs and outputs have unit variance).
_LOG_LENGTHSCALE_BOUNDS = (math.log(1e-3), math.log(1e4))
_LOG_SIGNAL_VAR_BOUNDS = (math.log(1e-4), math.log(1e2))
_LOG_NOISE_VAR_BOUNDS = (math.log(1e-6), math.log(1e1))

#: Largest |value| of the training inputs, targets and pseudo-inputs (fit, from_params): a
#: model file's own bound (:data:`asgp_ros.core.modelfile.MAX_ABS_VALUE`), so that what is
#: fitted can be saved. y ~ 1e300 gave NaN predictions and X ~ 1e300 infinite lengthscales.
MAX_ABS_VALUE = 1e15
#: Standardised inputs of a prediction are clipped to +- this: the kernel there is 0 to the
#: last bit (|x|^2 / l^2 >= 1e170 for any lengthscale a model file can hold), so the
#: prediction is the prior mean and variance, as the maths says; at 1.7e308 the kernel's
#: inf - inf gave NaN.
_PREDICT_REACH = 1e100

# Keys of get_state() / from_state() besides the posterior's (posterior.STATE_NDIM), with
# their expected number of dimensions.
_FIT_STATE_NDIM: dict[str, int] = {
    "log_marginal_likelihood": 0,  # original units
    "num_data": 0,
}


class SparseGPError(ValueError):
    """Bad input or a numerically impossible model; the message says what and what to do."""


class _Scales(NamedTuple):
    """Standardisation: inputs (x - x_mean) / x_scale, outputs (y - y_mean) / y_scale."""

    x_mean: FloatArray  # [D]
    x_scale: FloatArray  # [D]
    y_mean: float
    y_scale: float


def _theta_bounds(M: int, D: int) -> list[tuple[float | None, float | None]]:
    """L-BFGS-B bounds of theta (:meth:`Params.pack`): the hyperparameters are boxed, the
    pseudo-inputs free."""
    return ([_LOG_LENGTHSCALE_BOUNDS] * D + [_LOG_SIGNAL_VAR_BOUNDS, _LOG_NOISE_VAR_BOUNDS]
            + [(None, None)] * (M * D))


def _clip_to(theta: FloatArray, bounds: list[tuple[float | None, float | None]]) -> FloatArray:
    lo = np.array([b[0] if b[0] is not None else -np.inf for b in bounds])
    hi = np.array([b[1] if b[1] is not None else np.inf for b in bounds])
    return np.clip(theta, lo, hi)


_SINGLE_THREAD_ROWS = 256  # batches from this size get single-threaded BLAS in predict


def _blas_single_thread(rows: int) -> contextlib.AbstractContextManager[object]:
    """Single-threaded BLAS for a prediction batch of ``rows`` rows.

    The products of a prediction are [N*, M] x [M, M] with M ~ 40: OpenBLAS starts
    threading them at a few hundred rows and was then 2.5x to 20x slower than one thread
    on a loaded 2-core machine.  Small batches skip the switch.
    """
    if rows < _SINGLE_THREAD_ROWS:
        return contextlib.nullcontext()
    return blas.single_thread()


def _real(a: ArrayLike, name: str) -> None:
    """Refuse complex numbers (numpy dropped their imaginary part with a ComplexWarning
    alone, and fitted the real part)."""
    if np.iscomplexobj(a):
        raise SparseGPError(f"{name} must be real, got complex values")


def _beyond(arr: FloatArray, name: str) -> None:
    """Refuse a finite value beyond +-MAX_ABS_VALUE, naming where."""
    big = np.abs(arr) > MAX_ABS_VALUE
    if big.any():
        where = np.unravel_index(int(np.argmax(big)), arr.shape)
        at = (f"row {where[0]}, column {where[1]}" if arr.ndim == 2
              else f"index {where[0]}")
        raise SparseGPError(
            f"{name} holds {int(big.sum())} value(s) beyond +-{MAX_ABS_VALUE:g}, the first "
            f"{float(arr[where]):g} at {at} (a model file holds none)")


def _validate_inputs(X: ArrayLike, name: str, num_features: int | None = None,
                     bounded: bool = True) -> FloatArray:
    """X as a finite real [N, D] float array; ``bounded``: within +-MAX_ABS_VALUE (training
    data; a prediction's inputs are any finite values)."""
    _real(X, name)
    arr = np.asarray(X, dtype=np.float64)
    if arr.ndim != 2:
        raise SparseGPError(f"{name} must be a 2-D array [N, D], got shape {arr.shape}")
    if num_features is not None and arr.shape[1] != num_features:
        raise SparseGPError(
            f"{name} has {arr.shape[1]} columns but the model was trained on {num_features}"
        )
    if arr.shape[1] == 0:
        raise SparseGPError(f"{name} has no columns")
    bad = ~np.isfinite(arr)
    if bad.any():
        rows, cols = np.nonzero(bad)
        raise SparseGPError(
            f"{name} contains {bad.sum()} NaN/inf value(s), first at row {rows[0]}, "
            f"column {cols[0]}"
        )
    if bounded:
        _beyond(arr, name)
    return np.ascontiguousarray(arr)


def _validate_y(y: ArrayLike, n: int) -> FloatArray:
    _real(y, "y")
    arr = np.asarray(y, dtype=np.float64)
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.ndim != 1 or arr.shape[0] != n:
        raise SparseGPError(f"y must have shape [N] = [{n}] to match X, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise SparseGPError(
            f"y contains {bad.sum()} NaN/inf value(s), first at index {np.argmax(bad)}"
        )
    _beyond(arr, "y")
    return np.ascontiguousarray(arr)


def _positive(value: ArrayLike, name: str, shape: tuple[int, ...]) -> FloatArray:
    _real(value, name)
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        if arr.size == 1 and math.prod(shape) == 1:
            arr = arr.reshape(shape)
        else:
            raise SparseGPError(f"{name} must have shape {list(shape)}, got {arr.shape}")
    if not np.all(np.isfinite(arr)) or not np.all(arr > 0.0):
        raise SparseGPError(f"{name} must be finite and > 0, got {arr}")
    return arr


class _BestPoint:
    """The best finite objective value of one optimiser start, and failed evaluations.

    A parameter vector whose factorisation fails has no likelihood.  Returning ``inf``
    there makes scipy's L-BFGS-B end the run (its line search cannot backtrack from an
    infinite value and reports convergence), so a failed point is instead given a wall:
    f_best + w with gradient 2 w (x - x_best) / |x - x_best|^2, w = 10 (1 + |f_best|).
    The wall is higher than every finite value seen and slopes back towards the best
    point, so the line search shortens the step and the run continues.
    """

    def __init__(self) -> None:
        self.f = math.inf
        self.x: FloatArray | None = None
        self.failures = 0

    def reset(self) -> None:
        self.f, self.x = math.inf, None

    def failed_at(self, theta: FloatArray) -> tuple[float, FloatArray]:
        self.failures += 1
        if self.x is None:
            return math.inf, np.zeros_like(theta)
        d = theta - self.x
        wall = 10.0 * (1.0 + abs(self.f))
        return self.f + wall, (2.0 * wall / max(float(d @ d), 1e-300)) * d


class _IterationLogger:
    """L-BFGS-B callback: records (iteration, log marginal likelihood in original units)."""

    def __init__(
        self,
        log: list[tuple[int, float]],
        num_data: int,
        offset: float,
        callback: ProgressCallback | None,
    ) -> None:
        self.log = log
        self.num_data = num_data
        self.offset = offset
        self.callback = callback
        self.iteration = 0

    def __call__(self, intermediate_result: scipy.optimize.OptimizeResult) -> None:
        self.iteration += 1
        # The optimiser minimises -L / N of the standardised outputs.
        lml = -float(intermediate_result.fun) * self.num_data + self.offset
        self.log.append((self.iteration, lml))
        _LOG.debug("SPGP iteration %d: log marginal likelihood %.6g", self.iteration, lml)
        if self.callback is not None:
            self.callback(self.iteration, lml)


class SparseGP:
    """SPGP / FITC regression with an ARD squared-exponential kernel (single output).

    Example::

        gp = SparseGP(num_inducing=40, seed=0).fit(X, y, max_iter=200)   # X [N, D], y [N]
        mean, var = gp.predict(Xs)             # [N*], [N*] (var of a new observation)
        mean, var, dmean_dx = gp.predict_with_grad(Xs)    # ..., [N*, D]

    Args:
        num_inducing: M, the number of pseudo-inputs (fit needs N >= M samples).
        seed: seeds the k-means initialisation and restarts; equal seeds give equal fits.
        jitter: added to the diagonal of Kuu, relative to the signal variance.
        n_restarts: extra optimisations from re-drawn pseudo-inputs (different k-means
            seeds) and perturbed lengthscales; the best log marginal likelihood wins.
        init: "kmeans" (k-means++ centroids of the standardised inputs) or "spread"
            (a farthest-point subset of the training inputs).
        threads: worker threads of the likelihood while fitting.  The data are split into
            column blocks of about 4,096 samples evaluated in parallel; the block layout
            depends on N only and the block sums are added in a fixed order, so the result
            does not depend on ``threads``.
        blas_threads: BLAS threads while fitting (None leaves the process setting).  The
            default 1 is deliberate: FITC's products are skinny ([M, N] with M ~ 40) and
            multi-threaded OpenBLAS spent more time synchronising than computing (measured
            1.5x slower at N = 36,000 and 25x slower at N = 3,000 on a 2-core machine);
            parallelism comes from ``threads`` instead.
    """

    def __init__(
        self,
        num_inducing: int = 40,
        seed: int = 0,
        jitter: float = 1e-6,
        n_restarts: int = 0,
        init: str = "kmeans",
        threads: int = 2,
        blas_threads: int | None = 1,
    ) -> None:
        if int(num_inducing) != num_inducing or num_inducing < 1:
            raise SparseGPError(f"num_inducing must be a positive integer, got {num_inducing}")
        if not (math.isfinite(jitter) and jitter >= 0.0):
            raise SparseGPError(f"jitter must be finite and >= 0, got {jitter}")
        if int(n_restarts) != n_restarts or n_restarts < 0:
            raise SparseGPError(f"n_restarts must be an integer >= 0, got {n_restarts}")
        if init not in ("kmeans", "spread"):
            raise SparseGPError(f"init must be 'kmeans' or 'spread', got {init!r}")
        self.num_inducing = int(num_inducing)
        self.seed = int(seed)
        self.jitter = float(jitter)
        self.n_restarts = int(n_restarts)
        self.init = init
        if blas_threads is not None and (int(blas_threads) != blas_threads or blas_threads < 1):
            raise SparseGPError(f"blas_threads must be None or >= 1, got {blas_threads}")
        self.blas_threads = blas_threads
        if int(threads) != threads or threads < 1:
            raise SparseGPError(f"threads must be an integer >= 1, got {threads}")
        self.threads = int(threads)
        #: (iteration, log marginal likelihood in original units) after each L-BFGS-B
        #: iteration of the last fit (all restarts, iteration counted per restart).
        self.optimisation_log: list[tuple[int, float]] = []
        #: scipy's OptimizeResult of the run that was kept (None before fit).
        self.optimiser_result: scipy.optimize.OptimizeResult | None = None
        self._posterior: FitcPosterior | None = None
        self._lml = math.nan
        self._num_data = 0

    # ------------------------------------------------------------------ data handling
    @staticmethod
    def _standardisation(X: FloatArray, y: FloatArray) -> _Scales:
        x_scale = X.std(axis=0)
        const = np.nonzero(~(x_scale > 1e-12 * np.maximum(1.0, np.abs(X).max(axis=0))))[0]
        if const.size:
            raise SparseGPError(
                f"column(s) {const.tolist()} of X are constant; a constant input carries no "
                "information and cannot be standardised: drop it from the features"
            )
        y_scale = float(y.std())
        if not y_scale > 1e-12 * max(1.0, float(np.abs(y).max())):
            raise SparseGPError("y is constant; there is nothing to regress")
        return _Scales(X.mean(axis=0), x_scale, float(y.mean()), y_scale)

    @staticmethod
    def _standardise(X: FloatArray, y: FloatArray, sc: _Scales) -> tuple[FloatArray, FloatArray]:
        Xs = (X - sc.x_mean) / sc.x_scale
        ys = (y - sc.y_mean) / sc.y_scale
        return np.ascontiguousarray(Xs), ys

    def _check_sizes(self, X: FloatArray) -> None:
        n = X.shape[0]
        if n < self.num_inducing:
            raise SparseGPError(
                f"N = {n} training samples is fewer than num_inducing = {self.num_inducing}: "
                "use more data or fewer pseudo-inputs"
            )

    # ------------------------------------------------------------------ initialisation
    def _initial_inducing(self, Xs: FloatArray, seed: int) -> FloatArray:
        """[M, D] initial pseudo-inputs (standardised units), deterministic in ``seed``."""
        rng = np.random.default_rng(seed)
        M, N = self.num_inducing, Xs.shape[0]
        # A seeded subsample keeps k-means cheap for large N.
        sub = Xs if N <= 5000 else Xs[np.sort(rng.choice(N, 5000, replace=False))]
        if self.init == "kmeans":
            from scipy.cluster.vq import kmeans2  # (0.3 s to import: only where a fit starts)

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # an empty cluster is repaired below
                Z, _ = kmeans2(sub, M, iter=20, minit="++", seed=rng)
        else:
            Z = self._farthest_points(sub, M, rng)
        # Repair duplicated centroids (empty clusters) with distinct random data points.
        _, first = np.unique(np.round(Z, 12), axis=0, return_index=True)
        dup = np.setdiff1d(np.arange(M), first)
        if dup.size:
            Z[dup] = sub[rng.choice(sub.shape[0], dup.size, replace=False)]
        return np.ascontiguousarray(Z, dtype=np.float64)

    @staticmethod
    def _farthest_points(X: FloatArray, M: int, rng: np.random.Generator) -> FloatArray:
        idx = [int(rng.integers(X.shape[0]))]
        d2 = np.sum((X - X[idx[0]]) ** 2, axis=1)
        for _ in range(1, M):
            idx.append(int(np.argmax(d2)))
            d2 = np.minimum(d2, np.sum((X - X[idx[-1]]) ** 2, axis=1))
        return X[idx].copy()

    def initial_params(self, X: ArrayLike, y: ArrayLike) -> dict[str, FloatArray]:
        """The starting point of :meth:`fit` in original units (for comparisons).

        Returns a dict with ``inducing_inputs`` [M, D], ``lengthscales`` [D],
        ``signal_variance`` and ``noise_variance`` (0-d arrays).
        """
        Xa = _validate_inputs(X, "X")
        ya = _validate_y(y, Xa.shape[0])
        self._check_sizes(Xa)
        sc = self._standardisation(Xa, ya)
        Xs, _ = self._standardise(Xa, ya, sc)
        p = self._initial_params(Xs, self.seed)
        return {
            "inducing_inputs": p.Z * sc.x_scale + sc.x_mean,
            "lengthscales": p.lengthscales * sc.x_scale,
            "signal_variance": np.asarray(p.signal_variance * sc.y_scale**2),
            "noise_variance": np.asarray(p.noise_variance * sc.y_scale**2),
        }

    def _initial_params(self, Xs: FloatArray, seed: int) -> Params:
        # Lengthscales from the data ranges: half the (standardised) range of each input.
        span = Xs.max(axis=0) - Xs.min(axis=0)
        lengthscales = np.clip(0.5 * span, 0.1, 100.0)
        return Params(lengthscales, 1.0, 0.1, self._initial_inducing(Xs, seed))

    # ------------------------------------------------------------------ fitting
    def fit(
        self,
        X: ArrayLike,
        y: ArrayLike,
        max_iter: int = 200,
        max_fun: int | None = None,
        callback: ProgressCallback | None = None,
        start: SparseGP | None = None,
    ) -> SparseGP:
        """Learn Z and the hyperparameters by maximising the FITC evidence; cache the posterior.

        Args:
            X: [N, D] training inputs (N >= num_inducing, no constant column).
            y: [N] training targets.
            max_iter: L-BFGS-B iteration budget per (re)start.
            max_fun: L-BFGS-B function-evaluation budget per start (default 2 max_iter + 20).
            callback: called as ``callback(iteration, log_marginal_likelihood)`` after each
                L-BFGS-B iteration (original units), e.g. for a progress display.
            start: a fitted SparseGP with as many pseudo-inputs and inputs, whose
                pseudo-inputs and hyperparameters (in original units) are the first start of
                the optimiser instead of the data-driven one (a warm start: the same model
                fitted before on other rows, or for fewer iterations). Restarts after the
                first start as they do without it.

        Returns:
            self.
        """
        if int(max_iter) != max_iter or max_iter < 0:
            raise SparseGPError(f"max_iter must be an integer >= 0, got {max_iter}")
        if max_fun is not None and (int(max_fun) != max_fun or max_fun < 1):
            raise SparseGPError(f"max_fun must be None or an integer >= 1, got {max_fun}")
        if start is not None and not (isinstance(start, SparseGP)
                                      and start._posterior is not None):
            raise SparseGPError("start must be a fitted SparseGP")
        if self.blas_threads is None:
            return self._fit(X, y, int(max_iter), max_fun, callback, start)
        with threadpool_limits(limits=self.blas_threads, user_api="blas"):
            return self._fit(X, y, int(max_iter), max_fun, callback, start)

    def _fit(
        self,
        X: ArrayLike,
        y: ArrayLike,
        max_iter: int,
        max_fun: int | None,
        callback: ProgressCallback | None,
        start: SparseGP | None,
    ) -> SparseGP:
        Xa = _validate_inputs(X, "X")
        ya = _validate_y(y, Xa.shape[0])
        self._check_sizes(Xa)
        if start is not None and start.inducing_inputs.shape != (self.num_inducing,
                                                                  Xa.shape[1]):
            raise SparseGPError(
                f"start has {start.inducing_inputs.shape[0]} pseudo-inputs of "
                f"{start.inducing_inputs.shape[1]} inputs; this fit has {self.num_inducing} "
                f"of {Xa.shape[1]}")
        sc = self._standardisation(Xa, ya)
        Xs, ys = self._standardise(Xa, ya, sc)
        first = None if start is None else self._warm_start(start, sc)
        ws = Workspace(Xs, ys, self.num_inducing, self.threads)
        try:
            return self._optimise(Xs, ys, sc, ws, max_iter, max_fun, callback, first)
        finally:
            ws.close()

    @staticmethod
    def _warm_start(start: SparseGP, sc: _Scales) -> Params:
        """A fitted model's parameters in this fit's standardised units."""
        y2 = sc.y_scale**2
        return Params(start.lengthscales / sc.x_scale, start.signal_variance / y2,
                      start.noise_variance / y2, (start.inducing_inputs - sc.x_mean) / sc.x_scale)

    def _optimise(
        self,
        Xs: FloatArray,
        ys: FloatArray,
        sc: _Scales,
        ws: Workspace,
        max_iter: int,
        max_fun: int | None,
        callback: ProgressCallback | None,
        first: Params | None = None,
    ) -> SparseGP:
        N, D = Xs.shape
        M = self.num_inducing
        lml_offset = -N * math.log(sc.y_scale)
        self.optimisation_log = []
        if max_fun is None:
            max_fun = 2 * int(max_iter) + 20
        track = _BestPoint()  # best finite evaluation of a start, to resume from
        objective = self._objective(Xs, ys, ws, track)
        bounds = _theta_bounds(M, D)
        best: tuple[float, FloatArray, scipy.optimize.OptimizeResult] | None = None
        for restart in range(self.n_restarts + 1):
            track.reset()
            p0 = first if first is not None and restart == 0 else self._start_point(Xs, restart)
            theta0 = _clip_to(p0.pack(), bounds)
            f0, _ = objective(theta0)
            if not math.isfinite(f0):
                raise SparseGPError(
                    "the initial kernel matrices are not positive definite; increase jitter "
                    f"(now {self.jitter:g}) or check X for duplicated rows"
                )
            on_iteration = _IterationLogger(self.optimisation_log, N, lml_offset, callback)
            if max_iter == 0:
                import scipy.optimize

                res = scipy.optimize.OptimizeResult(
                    x=theta0, fun=f0, success=True, message="max_iter = 0", nit=0, nfev=1
                )
            else:
                res = self._minimise(objective, theta0, bounds, track, max_iter, max_fun,
                                     on_iteration)
                if not res.success and "LIMIT" not in str(res.message).upper():
                    _LOG.warning("SPGP optimiser: %s", res.message)
            if best is None or res.fun < best[0]:
                best = (float(res.fun), res.x, res)
        assert best is not None
        self.optimiser_result = best[2]
        self._num_data = N
        self._set_posterior(Xs, ys, sc, Params.unpack(best[1].copy(), M, D), lml_offset, ws)
        _LOG.debug(
            "SPGP fit: N=%d D=%d M=%d, %d iterations, log marginal likelihood %.6g",
            N, D, M, int(getattr(best[2], "nit", 0)), self._lml,
        )
        return self

    def _start_point(self, Xs: FloatArray, restart: int) -> Params:
        """Start of optimiser run ``restart``: the data-driven initial point, with the
        lengthscales perturbed (log-normal, sigma 0.5) for every restart after the first."""
        p0 = self._initial_params(Xs, self.seed + 7919 * restart)
        if restart:
            rng = np.random.default_rng([self.seed, restart])
            D = Xs.shape[1]
            p0 = p0._replace(lengthscales=p0.lengthscales * np.exp(rng.normal(0, 0.5, D)))
        return p0

    def _objective(self, Xs: FloatArray, ys: FloatArray, ws: Workspace, track: _BestPoint
                   ) -> Callable[[FloatArray], tuple[float, FloatArray]]:
        """theta -> (-L / N, -dL/dtheta / N), the negative log marginal likelihood and its
        gradient: the FITC terms (:func:`asgp_ros.core.fitc.fitc_terms`), then the gradient
        (:func:`asgp_ros.core.fitc.fitc_gradient`); a failed factorisation is a finite wall
        (:class:`_BestPoint`). Dividing by N keeps the value O(1), so that L-BFGS-B's
        tolerances stay meaningful."""
        N, D = Xs.shape
        M = self.num_inducing

        def objective(theta: FloatArray) -> tuple[float, FloatArray]:
            p = Params.unpack(theta, M, D)
            try:
                terms = fitc.fitc_terms(Xs, ys, p, self.jitter, ws)
            except FactorisationError:
                return track.failed_at(theta)
            d_l, d_sf2, d_sn2, dZ = fitc.fitc_gradient(p, terms)
            grad = np.concatenate([d_l, [d_sf2, d_sn2], dZ.ravel()])
            f = -terms.lml / N
            if f < track.f:
                track.f, track.x = f, theta.copy()
            return f, -grad / N

        return objective

    @staticmethod
    def _minimise(
        objective: Callable[[FloatArray], tuple[float, FloatArray]],
        theta0: FloatArray,
        bounds: list[tuple[float | None, float | None]],
        track: _BestPoint,
        max_iter: int,
        max_fun: int,
        on_iteration: _IterationLogger,
    ) -> scipy.optimize.OptimizeResult:
        """L-BFGS-B within the budget; resumes from the best point after a failed evaluation.

        L-BFGS-B treats an ``inf`` objective (a failed factorisation) as the end of the
        line search and stops, so a run that hit one is continued from the best finite
        point seen, while it still makes progress and budget is left.
        """
        import scipy.optimize

        start, nit, nfev = theta0, 0, 0
        while True:
            failures, f_start = track.failures, track.f
            res = scipy.optimize.minimize(
                objective,
                start,
                jac=True,
                method="L-BFGS-B",
                bounds=bounds,
                callback=on_iteration,
                options={"maxiter": max_iter - nit, "maxfun": max_fun - nfev},
            )
            nit += int(res.nit)
            nfev += int(res.nfev)
            if (
                track.failures == failures
                or nit >= max_iter
                or nfev >= max_fun
                or not track.f < f_start
                or track.x is None
            ):
                break
            _LOG.info("SPGP: a factorisation failed in the line search; resuming L-BFGS-B")
            start = track.x
        if track.x is not None and not res.fun <= track.f:
            res.x, res.fun = track.x, track.f
        res.nit, res.nfev = nit, nfev
        return res

    def _set_posterior(
        self,
        Xs: FloatArray,
        ys: FloatArray,
        sc: _Scales,
        p: Params,
        offset: float,
        ws: Workspace | None = None,
    ) -> None:
        """Cache the posterior of the FITC terms at ``p`` (posterior.from_factors, P1, P2)."""
        try:
            t = fitc.fitc_terms(Xs, ys, p, self.jitter, ws)
        except FactorisationError as err:
            raise SparseGPError(
                f"FITC factorisation failed ({err}): the kernel matrix of the pseudo-inputs "
                f"is singular for these parameters; increase jitter (now {self.jitter:g}), "
                "remove duplicated pseudo-inputs or shorten the lengthscales"
            ) from err
        self._posterior = posterior.from_factors(
            x_mean=sc.x_mean, x_scale=sc.x_scale, y_mean=sc.y_mean, y_scale=sc.y_scale,
            Z=p.Z, lengthscales=p.lengthscales, signal_variance=p.signal_variance,
            noise_variance=p.noise_variance, jitter=self.jitter, L=t.L, LA=t.LA,
            alpha=t.alpha,
        )
        self._lml = t.lml + offset

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_params(
        cls,
        X: ArrayLike,
        y: ArrayLike,
        Z: ArrayLike,
        lengthscales: ArrayLike,
        signal_variance: float,
        noise_variance: float,
        jitter: float = 1e-6,
    ) -> SparseGP:
        """The FITC posterior at fixed parameters, no fitting (all in original units).

        Args:
            X: [N, D] training inputs.  y: [N] targets (the prior mean is mean(y)).
            Z: [M, D] pseudo-inputs.  lengthscales: [D].  signal_variance, noise_variance:
            kernel amplitude sf2 and Gaussian noise variance sn2.
            jitter: relative jitter on Kuu (Kuu + jitter * sf2 * I).
        """
        Xa = _validate_inputs(X, "X")
        ya = _validate_y(y, Xa.shape[0])
        Za = _validate_inputs(Z, "Z", Xa.shape[1])
        D = Xa.shape[1]
        ls = _positive(lengthscales, "lengthscales", (D,))
        sf2 = float(_positive(signal_variance, "signal_variance", ()))
        sn2 = float(_positive(noise_variance, "noise_variance", ()))
        gp = cls(num_inducing=Za.shape[0], jitter=jitter)
        sc = gp._standardisation(Xa, ya)
        Xs, ys = gp._standardise(Xa, ya, sc)
        y2 = sc.y_scale**2
        p = Params(ls / sc.x_scale, sf2 / y2, sn2 / y2, (Za - sc.x_mean) / sc.x_scale)
        gp._num_data = Xa.shape[0]
        gp._set_posterior(Xs, ys, sc, p, -Xa.shape[0] * math.log(sc.y_scale))
        return gp

    def get_state(self) -> dict[str, FloatArray]:
        """Arrays that restore this fitted model exactly (see :meth:`from_state`).

        The posterior's arrays (:func:`asgp_ros.core.posterior.to_state`: standardisation,
        kernel parameters, pseudo-inputs, ``alpha``, ``var_matrix`` and ``chol_a``) and
        the fit's ``log_marginal_likelihood`` and ``num_data``.
        """
        state = posterior.to_state(self._fitted())
        state["log_marginal_likelihood"] = np.asarray(self._lml, dtype=np.float64)
        state["num_data"] = np.asarray(float(self._num_data), dtype=np.float64)
        return state

    @classmethod
    def from_state(cls, state: Mapping[str, ArrayLike]) -> SparseGP:
        """Rebuild a fitted model from :meth:`get_state` arrays (no training data needed).

        States written before ``chol_a`` was stored load too (see
        :func:`asgp_ros.core.posterior.from_state`).

        Raises:
            ValueError (SparseGPError) naming the missing, mis-shaped or non-finite entry.
        """
        try:
            post = posterior.from_state(state)
            fit = {key: posterior.state_array(state, key, ndim)
                   for key, ndim in _FIT_STATE_NDIM.items()}
        except PosteriorError as err:
            raise SparseGPError(f"SparseGP state: {err}") from err
        gp = cls(num_inducing=post.num_inducing, jitter=post.jitter)
        gp._posterior = post
        n = float(fit["num_data"])
        if not (0.0 <= n < 1e13 and n == round(n)):
            raise SparseGPError(f"SparseGP state: entry 'num_data' must be a whole number "
                                f">= 0, got {n:g}")
        gp._lml = float(fit["log_marginal_likelihood"])
        gp._num_data = int(n)
        return gp

    # ------------------------------------------------------------------ prediction
    @property
    def posterior(self) -> FitcPosterior:
        """The cached posterior (immutable; standardised units) that every prediction reads.

        Assigning a new :class:`~asgp_ros.core.posterior.FitcPosterior` (e.g. after an
        online update) replaces it atomically: a prediction or rollout in progress keeps
        the one it started with.  The log marginal likelihood and the number of data
        still describe the last fit.
        """
        return self._fitted()

    @posterior.setter
    def posterior(self, post: FitcPosterior) -> None:
        if not isinstance(post, FitcPosterior):
            raise SparseGPError(f"posterior must be a FitcPosterior, got {type(post).__name__}")
        if self._posterior is not None and post.num_features != self._posterior.num_features:
            raise SparseGPError(
                f"posterior has D={post.num_features} inputs, the model "
                f"{self._posterior.num_features}"
            )
        self.num_inducing = post.num_inducing
        self._posterior = post

    def _fitted(self) -> FitcPosterior:
        if self._posterior is None:
            raise SparseGPError("the SparseGP is not fitted: call fit() or from_params() first")
        return self._posterior

    def _predict(
        self, Xs: ArrayLike, include_noise: bool, with_grad: bool
    ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        post = self._fitted()
        Xa = _validate_inputs(Xs, "Xs", post.num_features, bounded=False)
        S = post.stacked
        reach = _PREDICT_REACH * S.x_scale[0, 0]
        if np.any(np.abs(Xa - S.x_mean[0, 0]) > reach):  # far beyond the data: the prior
            Xa = np.clip(Xa, S.x_mean[0, 0] - reach, S.x_mean[0, 0] + reach)
        with _blas_single_thread(Xa.shape[0]):
            mean, var, grad = posterior.predict(post.stacked, Xa[None], include_noise,
                                                with_grad, stacklevel=3)
        return mean[0], var[0], None if grad is None else grad[0]

    def predict(self, Xs: ArrayLike, include_noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """Predictive mean [N*] and variance [N*] at Xs [N*, D] (original units).

        The variance is that of a new observation (latent variance + noise variance)
        unless ``include_noise=False``, which gives the latent f variance.
        """
        mean, var, _ = self._predict(Xs, include_noise, with_grad=False)
        return mean, var

    def predict_with_grad(
        self, Xs: ArrayLike, include_noise: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Predictive mean [N*], variance [N*] and d mean / d x [N*, D] (original units).

        The input gradient of the mean is what linearised (EKF-style) uncertainty
        propagation through the autoregressive recursion needs.
        """
        mean, var, grad = self._predict(Xs, include_noise, with_grad=True)
        assert grad is not None
        return mean, var, grad

    def log_marginal_likelihood(self) -> float:
        """FITC log evidence log p(y) of the training data at the fitted parameters."""
        self._fitted()
        return self._lml

    # ------------------------------------------------------------------ parameters
    @property
    def inducing_inputs(self) -> FloatArray:
        """[M, D] pseudo-inputs Z in original input units."""
        post = self._fitted()
        return post.Z * post.x_scale + post.x_mean

    @property
    def lengthscales(self) -> FloatArray:
        """[D] ARD lengthscales in original input units."""
        post = self._fitted()
        return post.lengthscales * post.x_scale

    @property
    def signal_variance(self) -> float:
        """Kernel amplitude sf2 in squared output units."""
        post = self._fitted()
        return post.signal_variance * post.y_scale**2

    @property
    def noise_variance(self) -> float:
        """Gaussian observation noise variance sn2 in squared output units."""
        post = self._fitted()
        return post.noise_variance * post.y_scale**2

    @property
    def num_features(self) -> int:
        """D, the input dimension."""
        return self._fitted().num_features

    def __repr__(self) -> str:
        if self._posterior is None:
            return f"SparseGP(num_inducing={self.num_inducing}, seed={self.seed}, unfitted)"
        return (
            f"SparseGP(M={self.num_inducing}, D={self.num_features}, N={self._num_data}, "
            f"log_marginal_likelihood={self._lml:.6g})"
        )
