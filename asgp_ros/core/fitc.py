"""The FITC terms and the gradient of the FITC log marginal likelihood (standardised units).

Model (Snelson & Ghahramani 2006, "Sparse Gaussian Processes using Pseudo-inputs", NIPS;
the FITC name is from Quiñonero-Candela & Rasmussen 2005, JMLR 6, section 5), with
X [N, D], y [N], pseudo-inputs Z [M, D], Kuf = k(Z, X) [M, N], Kuu = k(Z, Z) [M, M]::

    y | f ~ N(f, sn2),   p(y) = N(y | 0, Qff + Lambda)                  (S&G eq. 6)
    Qff = Kfu Kuu^-1 Kuf,   Lambda = diag(Kff - Qff) + sn2 I

The two pieces the optimiser of :class:`asgp_ros.core.sparse_gp.SparseGP` evaluates at
every step, on the same factors:

* :func:`fitc_terms` -- the shared Cholesky factors (:class:`FitcTerms`) and the log
  marginal likelihood, by the matrix inversion and determinant lemmas (S&G eq. 6 and 8);
  the factors also give the cached posterior (:func:`asgp_ros.core.posterior.from_factors`,
  P1 and P2);
* :func:`fitc_gradient` -- its gradient in the log hyperparameters and the pseudo-inputs:
  Snelson's derivatives in Lambda, Kuf and Kuu (Snelson 2007, PhD thesis, appendix C) and
  the chain rule through the kernel (:mod:`asgp_ros.core.kernel`, K3 and K4).  The
  optimiser minimises the negative of the likelihood, with the negative of this gradient.

The training data are split into column blocks (:class:`Workspace`) evaluated in parallel
threads with single-threaded BLAS; per evaluation, the likelihood costs two O(N M^2) BLAS-3
calls and the gradient three, plus a few O(N M D) products.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple, TypeVar, cast

import numpy as np
import scipy.linalg
import scipy.linalg.blas
from numpy.typing import NDArray

from asgp_ros.core import kernel

FloatArray = NDArray[np.float64]
_T = TypeVar("_T")

_LOG_2PI = math.log(2.0 * math.pi)

# Column blocks of the likelihood evaluation (see Workspace).
_BLOCK_COLUMNS = 4096
_MIN_BLOCK_COLUMNS = 1000


class FactorisationError(Exception):
    """A Cholesky factorisation failed or FITC's diagonal went non-positive."""


class Params(NamedTuple):
    """Parameters in standardised units."""

    lengthscales: FloatArray  # [D]
    signal_variance: float
    noise_variance: float
    Z: FloatArray  # [M, D]

    def pack(self) -> FloatArray:
        """The optimiser's vector theta = [log l (D), log sf2, log sn2, Z (M * D)]."""
        return np.concatenate([np.log(self.lengthscales), [math.log(self.signal_variance)],
                               [math.log(self.noise_variance)], self.Z.ravel()])

    @staticmethod
    def unpack(theta: FloatArray, M: int, D: int) -> Params:
        """Inverse of :meth:`pack`."""
        return Params(np.exp(theta[:D]), float(np.exp(theta[D])), float(np.exp(theta[D + 1])),
                      theta[D + 2:].reshape(M, D))


class FitcTerms(NamedTuple):
    """Shared FITC factors of one parameter setting (standardised units).

    One instance feeds the log marginal likelihood, its gradient and the cached posterior
    (:func:`asgp_ros.core.posterior.from_factors`).  The O(N M) factors (Kuf,
    V = L^-1 Kuf, Lambda) live in the column blocks of ``workspace`` and are valid until
    the workspace is used again.
    """

    Kuu: FloatArray  # [M, M] k(Z, Z) + jitter * sf2 * I
    L: FloatArray  # [M, M] chol(Kuu), lower
    LA: FloatArray  # [M, M] chol(A), A = I + V Lambda^-1 V^T
    c: FloatArray  # [M] LA^-1 V Lambda^-1 y
    alpha: FloatArray  # [M] posterior weights L^-T LA^-T c  (mean = Ksu alpha)
    lml: float  # FITC log marginal likelihood of the standardised y
    workspace: Workspace


def cholesky(K: FloatArray) -> FloatArray:
    """Lower Cholesky factor, or FactorisationError."""
    try:
        return cast(FloatArray, scipy.linalg.cholesky(K, lower=True, check_finite=False))
    except np.linalg.LinAlgError as err:
        raise FactorisationError(str(err)) from err


# ---------------------------------------------------------------------- the column blocks


class _Block:
    """One column block of the training data with its reusable O(n M) buffers."""

    def __init__(self, X: FloatArray, y: FloatArray, M: int) -> None:
        n = X.shape[0]
        self.y = y  # [n]
        X_sq = X * X
        self.X_sq = X_sq  # [n, D]
        # [X, X^2, 1]: the moments of dL/dKuf o Kuf the kernel's chain rule needs
        self.X1 = np.hstack([X, X_sq, np.ones((n, 1))])  # [n, 2D + 1]
        # [X^T; 1; |x|^2_l] so that log Kuf is one matrix product (K2; last row per call).
        self.xaug_t = kernel.augmented_inputs(X)  # [D + 2, n]
        self.kuf = np.empty((M, n))  # Kuf
        self.v = np.empty((M + 1, n))  # [V; r^T]: V = L^-1 Kuf and a row for the residual
        self.a = np.empty((M, n))
        self.b = np.empty((M, n))
        self.lam = np.empty(n)  # Lambda
        self.beta = np.empty(n)  # 1 / Lambda


class Workspace:
    """Training data split into column blocks, evaluated by up to ``threads`` threads.

    Fresh multi-megabyte temporaries cost page faults on every evaluation, so the
    optimiser reuses one workspace.  Blocks of about ``_BLOCK_COLUMNS`` columns keep each
    block's [M, n] buffers in cache (measured 20 % faster than one block at N = 36,000)
    and give the threads independent work; numpy and BLAS release the GIL, so blocks run
    in parallel with single-threaded BLAS in each.  The block layout depends on N only and
    the sums over blocks (A, V Lambda^-1 y and the gradient's reductions) are added in a
    fixed order, so results do not depend on the number of threads.
    """

    def __init__(self, X: FloatArray, y: FloatArray, M: int, threads: int = 1) -> None:
        N = X.shape[0]
        self.X = X
        self.y = y
        self.M = M
        n_blocks = max(1, -(-N // _BLOCK_COLUMNS), 2 if N >= 2 * _MIN_BLOCK_COLUMNS else 1)
        edges = np.linspace(0, N, n_blocks + 1).astype(int)
        self.blocks = [
            _Block(X[a:b], y[a:b], M) for a, b in itertools.pairwise(edges.tolist())
        ]
        workers = min(int(threads), n_blocks)
        self._pool: ThreadPoolExecutor | None = None
        if workers > 1:
            self._pool = ThreadPoolExecutor(workers, thread_name_prefix="spgp")

    def fits(self, X: FloatArray, y: FloatArray, M: int) -> bool:
        return self.X is X and self.y is y and self.M == M

    def map(self, fn: Callable[[_Block], _T]) -> list[_T]:
        if self._pool is None:
            return [fn(b) for b in self.blocks]
        return list(self._pool.map(fn, self.blocks))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


def _trsm_inplace(L: FloatArray, B: FloatArray) -> FloatArray:
    """B <- L^-1 B for lower-triangular L [M, M] and a C-ordered B [M, N]; returns B.

    BLAS dtrsm on the transposed problem B^T <- B^T L^-T (side = right, "RLT"): the
    C-ordered [M, N] buffer is a Fortran-ordered [N, M] matrix, so it is solved in place.
    (OpenBLAS's RLT kernel is also about twice as fast as the other variants for M << N.)
    """
    out = scipy.linalg.blas.dtrsm(1.0, L, B.T, side=1, lower=1, trans_a=1, overwrite_b=1)
    if not np.shares_memory(out, B):  # pragma: no cover - only for exotic layouts
        B[...] = out.T
    return B


# ---------------------------------------------------------------------- the FITC terms


class _BlockSums(NamedTuple):
    """One block's share of the FITC terms (summed over the blocks in a fixed order)."""

    A: FloatArray  # [M, M] V Lambda^-1 V^T, lower triangle
    Vby: FloatArray  # [M] V Lambda^-1 y
    log_det_lam: float  # sum log Lambda
    y_lam_y: float  # y^T Lambda^-1 y


def _forward_block(b: _Block, L: FloatArray, z_aug: FloatArray, inv_l2: FloatArray,
                   sf2: float, sn2: float) -> _BlockSums | None:
    """Kuf, V = L^-1 Kuf and Lambda of one block (kept in its buffers) and its share of the
    sums; None where Lambda is not positive.

    Lambda = diag(Kff - Qff) + sn2 = sf2 + sn2 - colsum(V o V)  (S&G eq. 6), and
    log Kuf = [Z / l^2, log sf2 - |z|_l^2 / 2, -1/2] @ [X^T; 1; |x|_l^2]  (K2).
    """
    M = L.shape[0]
    kernel.set_augmented_norms(b.xaug_t, b.X_sq, inv_l2)
    kernel.cross_t(z_aug, b.xaug_t, out=b.kuf)  # [M, n] Kuf
    V = b.v[:M]
    np.copyto(V, b.kuf)
    _trsm_inplace(L, V)  # [M, n] L^-1 Kuf
    # Lambda = diag(Kff - Qff) + sn2  (S&G eq. 6)
    np.subtract(sf2 + sn2, np.einsum("mn,mn->n", V, V), out=b.lam)
    if not np.all(b.lam > 0.0):
        return None
    np.divide(1.0, b.lam, out=b.beta)
    Vb = np.multiply(V, np.sqrt(b.beta), out=b.a)  # [M, n] V Lambda^-1/2
    # V Lambda^-1 V^T by a rank-n update (dsyrk fills the lower triangle, which is all
    # the Cholesky factorisation reads).
    A_part = scipy.linalg.blas.dsyrk(1.0, Vb.T, trans=1, lower=1)  # [M, M]
    Vby = V @ (b.beta * b.y)  # [M]
    return _BlockSums(A_part, Vby, float(np.sum(np.log(b.lam))), float(b.beta @ (b.y * b.y)))


def _log_marginal_likelihood(N: int, log_det_lam: float, y_lam_y: float, LA: FloatArray,
                             c: FloatArray) -> float:
    """log N(y | 0, Qff + Lambda) from the factors, by the matrix inversion and determinant
    lemmas (S&G eq. 8; Rasmussen & Williams 2006, eq. A.9 and A.10)::

        -1/2 (N log 2 pi + log|Lambda| + log|A| + y^T Lambda^-1 y - c^T c),
        A = LA LA^T,  c = LA^-1 V Lambda^-1 y
    """
    return -0.5 * (
        N * _LOG_2PI
        + log_det_lam
        + 2.0 * float(np.sum(np.log(np.diag(LA))))
        + y_lam_y
        - float(c @ c)
    )


def fitc_terms(
    X: FloatArray, y: FloatArray, p: Params, jitter: float, ws: Workspace | None = None
) -> FitcTerms:
    """All FITC factors at parameters ``p`` and the log marginal likelihood.  X [N, D], y [N].

    Kuu = k(Z, Z) + jitter sf2 I (K1), L = chol(Kuu); per block V = L^-1 Kuf and Lambda
    (S&G eq. 6); A = I + V Lambda^-1 V^T = LA LA^T, c = LA^-1 V Lambda^-1 y and the
    posterior weights alpha = L^-T LA^-T c (P1 of :mod:`asgp_ros.core.posterior`); the
    likelihood by S&G eq. 8 (:func:`_log_marginal_likelihood`).

    Raises FactorisationError when Kuu or A is not positive definite or Lambda <= 0.
    """
    N = X.shape[0]
    M = p.Z.shape[0]
    if ws is None or not ws.fits(X, y, M):
        ws = Workspace(X, y, M)
    sf2, sn2 = p.signal_variance, p.noise_variance
    Kuu = kernel.se_ard_jittered(p.Z, p.lengthscales, sf2, jitter)  # [M, M] (K1)
    L = cholesky(Kuu)
    # log Kuf = [Z / l^2, log sf2 - |z|_l^2 / 2, -1/2] @ [X^T; 1; |x|_l^2]  (K2)
    factors = kernel.cross_factors(p.Z, p.lengthscales, sf2)
    inv_l2 = factors.inv_l2[0]
    z_aug = kernel.augmented_pseudo_inputs(factors)  # [M, D + 2]
    parts = ws.map(lambda b: _forward_block(b, L, z_aug, inv_l2, sf2, sn2))
    if any(part is None for part in parts):
        raise FactorisationError("FITC diagonal Lambda is not positive")
    A = np.eye(M)
    Vby = np.zeros(M)
    log_det_lam = y_lam_y = 0.0
    for part in parts:
        assert part is not None
        A += part.A
        Vby += part.Vby
        log_det_lam += part.log_det_lam
        y_lam_y += part.y_lam_y
    LA = cholesky(A)
    c = scipy.linalg.solve_triangular(LA, Vby, lower=True, check_finite=False)
    tmp = scipy.linalg.solve_triangular(LA, c, lower=True, trans="T", check_finite=False)
    alpha = scipy.linalg.solve_triangular(L, tmp, lower=True, trans="T", check_finite=False)
    lml = _log_marginal_likelihood(N, log_det_lam, y_lam_y, LA, c)
    return FitcTerms(Kuu, L, LA, c, alpha, lml, ws)


# ---------------------------------------------------------------------- the gradient


class _BackwardSums(NamedTuple):
    """One block's share of the gradient (summed over the blocks in a fixed order)."""

    gram: FloatArray  # [M, M] 2 V dL/dLambda V^T
    moments: FloatArray  # [M, 2D + 1] -(dL/dKuf o Kuf) [X, X^2, 1]
    sum_dlam: float  # sum dL/dLambda


def _backward_block(b: _Block, left: FloatArray, u: FloatArray, Lr: FloatArray
                    ) -> _BackwardSums:
    """dL/dLambda and dL/dKuf of one block (Snelson 2007, appendix C), reduced to what the
    chain rule needs: the Kuu term V dL/dLambda V^T, the moments of dL/dKuf o Kuf, and
    sum dL/dLambda.

    ``left`` = J [A^-1, -u] (rows reversed), ``u`` = LA^-T c, ``Lr`` = J L^T J (see
    :func:`fitc_gradient`); with r = y - Kfu alpha and P = L^-T A^-1 L^-1::

        dL/dLambda = 0.5 (beta^2 (diag(Kfu P Kuf) + r^2) - beta)
        dL/dKuf = alpha (beta r)^T - P Kuf beta - 2 Kuu^-1 Kuf dL/dLambda
    """
    M = u.shape[0]
    V, beta, y = b.v[:M], b.beta, b.y
    r = y - V.T @ u  # [n] residual y - Kfu alpha  (Kfu alpha = V^T LA^-T c)
    b.v[M] = r
    Yr = np.matmul(left, b.v, out=b.a)  # [M, n]  J (A^-1 V - u r^T)
    # diag(Kfu P Kuf) = diag(V^T A^-1 V) = colsum(V o Y) + r (V^T u),  V^T u = y - r.
    q = np.einsum("mn,mn->n", V[::-1], Yr) + r * (y - r)
    dlam = 0.5 * (beta * beta * (q + r * r) - beta)  # [n] dL/dLambda
    Vd = np.multiply(V, 2.0 * dlam, out=b.b)  # [M, n]  2 V dL/dLambda
    gram = Vd @ V.T  # [M, M]  2 V dL/dLambda V^T
    # -dL/dKuf = L^-T T, T = Y beta + 2 V dL/dLambda (alpha (beta r)^T = L^-T u (beta r)^T
    # is folded into Y).
    Yr *= beta
    Yr += Vd[::-1]
    _trsm_inplace(Lr, Yr)  # J (-dL/dKuf)
    Wn = np.multiply(Yr[::-1], b.kuf, out=b.b)  # [M, n]  -(dL/dKuf o Kuf)
    return _BackwardSums(gram, Wn @ b.X1, float(np.sum(dlam)))  # [M, M], [M, 2D + 1]


def _kuu_gradient(L: FloatArray, Ainv: FloatArray, gram: FloatArray, alpha: FloatArray
             ) -> FloatArray:
    """dL/dKuu [M, M] (Snelson 2007, appendix C), symmetrised::

        dL/dKuu = 0.5 (Kuu^-1 - P - alpha alpha^T) + Kuu^-1 Kuf dL/dLambda Kfu Kuu^-1
                = L^-T [0.5 (I - A^-1) + V dL/dLambda V^T] L^-1 - 0.5 alpha alpha^T

    with ``gram`` = 2 V dL/dLambda V^T summed over the blocks.
    """
    M = L.shape[0]
    inner = 0.5 * (np.eye(M) - Ainv + gram)
    tmp = scipy.linalg.solve_triangular(L, inner, lower=True, trans="T", check_finite=False)
    dKuu = scipy.linalg.solve_triangular(L, tmp.T, lower=True, trans="T", check_finite=False)
    dKuu -= 0.5 * np.outer(alpha, alpha)
    return cast(FloatArray, 0.5 * (dKuu + dKuu.T))


def fitc_gradient(p: Params, t: FitcTerms) -> tuple[FloatArray, float, float, FloatArray]:
    """Gradient of the FITC log marginal likelihood at the factors ``t`` of ``p``.

    Returns (dL/dlog l [D], dL/dlog sf2, dL/dlog sn2, dL/dZ [M, D]); the optimiser of
    :class:`asgp_ros.core.sparse_gp.SparseGP` minimises -L, with the negative of these.

    The derivatives with respect to Lambda, Kuf and Kuu are Snelson's (Snelson 2007, PhD
    thesis, appendix C; the same expressions as GPy's FITC), with P = L^-T A^-1 L^-1:

        r = y - Kfu alpha,   dL/dLambda = 0.5 (beta^2 (diag(Kfu P Kuf) + r^2) - beta)
        dL/dKuf = alpha (beta r)^T - P Kuf beta - 2 Kuu^-1 Kuf dL/dLambda
        dL/dKuu = 0.5 (Kuu^-1 - P - alpha alpha^T) + Kuu^-1 Kuf dL/dLambda Kfu Kuu^-1

    (per block in :func:`_backward_block`, dL/dKuu in :func:`_kuu_gradient`), followed by the
    chain rule through the SE kernel (:func:`asgp_ros.core.kernel.param_grads`, K3 and
    K4), all as matrix products (no [N, M, D] temporaries).  Cost: three O(N M^2) BLAS-3
    calls and one O(N M D) product per block.
    """
    M, D = p.Z.shape
    sf2, sn2 = p.signal_variance, p.noise_variance
    inv_l2 = 1.0 / np.square(p.lengthscales)
    L, LA, alpha = t.L, t.LA, t.alpha
    Ainv = scipy.linalg.cho_solve((LA, True), np.eye(M), check_finite=False)  # [M, M], A >= I
    u = scipy.linalg.solve_triangular(LA, t.c, lower=True, trans="T", check_finite=False)
    # Y = A^-1 V - u r^T as one product [A^-1, -u] [V; r^T]; its rows are computed in
    # reversed order (J Y, J the reversal) for the triangular solve below.
    left = np.empty((M, M + 1))
    left[:, :M] = Ainv[::-1]
    left[:, M] = -u[::-1]
    # L^-T = J Lr^-1 J with Lr = J L^T J lower triangular: the fast in-place solve.
    Lr = np.ascontiguousarray(L[::-1, ::-1].T)
    parts = t.workspace.map(lambda b: _backward_block(b, left, u, Lr))
    gram = np.zeros((M, M))
    S = np.zeros((M, 2 * D + 1))
    sum_dlam = 0.0
    for part in parts:
        gram += part.gram
        S -= part.moments
        sum_dlam += part.sum_dlam
    # With W = dL/dKuf o Kuf:  S = W [X, X^2, 1]  ->  W X, rows of W X^2, row sums of W.
    WX, WX_sq, w_row = S[:, :D], S[:, D : 2 * D], S[:, 2 * D]
    dKuu = _kuu_gradient(L, Ainv, gram, alpha)

    # Chain rule through k (K3, K4), with Wu = dL/dKuu o Kuu (its diagonal includes the
    # jitter, which scales with sf2); Lambda's diag(Kff) = sf2 adds sf2 sum(dL/dLambda).
    d_log_l, d_log_sf2_k, dZ = kernel.param_grads(p.Z, inv_l2, WX, WX_sq, w_row,
                                                  dKuu * t.Kuu)
    d_log_sf2 = float(d_log_sf2_k + sf2 * sum_dlam)
    d_log_sn2 = float(sn2 * sum_dlam)
    return d_log_l, d_log_sf2, d_log_sn2, dZ
