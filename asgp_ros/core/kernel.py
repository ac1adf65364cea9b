"""The ARD squared-exponential kernel and its derivatives: the one implementation.

Training (:mod:`asgp_ros.core.sparse_gp`; the FITC terms and the likelihood gradient in
:mod:`asgp_ros.core.fitc`), prediction and the fused rollout (:mod:`asgp_ros.core.posterior`,
:mod:`asgp_ros.core.rollout`) all evaluate the kernel through this module.  Notation as
GPflow's glossary: inputs X [N, D], pseudo-inputs Z [M, D], lengthscales l [D], signal
variance sf2, and |a|_l^2 = sum_d a_d^2 / l_d^2 (``inv_l2`` = 1 / l^2).

Equations (cited as K1 .. K4 by the callers)::

    (K1)  k(a, b) = sf2 exp(-1/2 sum_d (a_d - b_d)^2 / l_d^2)
    (K2)  log k(x, z) = (log sf2 - |z|_l^2 / 2) + sum_d x_d z_d / l_d^2 - |x|_l^2 / 2
    (K3)  d k(a, b) / d a_d = k(a, b) (b_d - a_d) / l_d^2
    (K4)  d k(a, b) / d log l_d = k(a, b) (a_d - b_d)^2 / l_d^2,   d k / d log sf2 = k

K1 is the squared exponential with ARD metric M = diag(l)^-2 (Rasmussen & Williams 2006,
"Gaussian Processes for Machine Learning", eq. 5.1 and the first form of eq. 5.2), the
covariance of SPGP in Snelson & Ghahramani (2006).  K2 is K1 with the square expanded: for
a fixed Z the z terms are computed once (:class:`CrossFactors`) and a whole batch of inputs
costs one matrix product.  K3 and K4 follow from K1 by the chain rule.

Expanding the square cancels for inputs far from Z (log k is a difference of large
terms); the result is clipped at log sf2 (a squared distance is never negative) and k
underflows to 0 where it is negligible anyway.
"""

from __future__ import annotations

import math
from typing import NamedTuple, cast

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def scaled_sq_dist(A: FloatArray, B: FloatArray, inv_l2: FloatArray) -> FloatArray:
    """Squared ARD distances sum_d (a_d - b_d)^2 / l_d^2 (the exponent of K1, expanded).

    A [P, D], B [Q, D], inv_l2 [D] -> [P, Q], clipped at 0.
    """
    d2 = (A * inv_l2) @ B.T  # [P, Q]
    d2 *= -2.0
    d2 += ((A * A) @ inv_l2)[:, None]
    d2 += ((B * B) @ inv_l2)[None, :]
    np.maximum(d2, 0.0, out=d2)
    return d2


def se_ard(
    A: FloatArray, B: FloatArray, lengthscales: FloatArray, signal_variance: float
) -> FloatArray:
    """Kernel matrix k(A, B) (K1).  A [P, D], B [Q, D], lengthscales [D] -> [P, Q]."""
    inv_l2 = 1.0 / np.square(lengthscales)
    K = scaled_sq_dist(A, B, inv_l2)
    K *= -0.5
    np.exp(K, out=K)
    K *= signal_variance
    return K


def se_ard_jittered(
    Z: FloatArray, lengthscales: FloatArray, signal_variance: float, jitter: float
) -> FloatArray:
    """k(Z, Z) + jitter * sf2 * I [M, M] (K1), its diagonal exactly sf2 (1 + jitter).

    The jitter is relative to sf2, so it does not depend on the output units.
    """
    K = se_ard(Z, Z, lengthscales, signal_variance)
    K[np.diag_indices(Z.shape[0])] = signal_variance * (1.0 + jitter)
    return K


class CrossFactors(NamedTuple):
    """The pseudo-input side of K2 for k(., Z), computed once per parameter setting.

    Shapes broadcast against a batch of inputs [..., N, D]; several kernels (one per output
    channel) stack along leading axes with :func:`stack_factors`.
    """

    zt: FloatArray  # [..., D, M] (Z / l^2)^T
    offset: FloatArray  # [..., 1, M] log sf2 - |z|_l^2 / 2
    inv_l2: FloatArray  # [..., 1, D] 1 / l^2
    log_sf2: FloatArray  # [..., 1, 1] log sf2, the largest value of log k

    @property
    def z_scaled(self) -> FloatArray:
        """[..., M, D] Z / l^2 (a view)."""
        return np.swapaxes(self.zt, -1, -2)


def cross_factors(Z: FloatArray, lengthscales: FloatArray, signal_variance: float
                  ) -> CrossFactors:
    """The Z terms of K2.  Z [M, D], lengthscales [D]."""
    inv_l2 = 1.0 / np.square(lengthscales)  # [D]
    z_scaled = Z * inv_l2  # [M, D]
    log_sf2 = math.log(signal_variance)
    offset = log_sf2 - 0.5 * ((Z * Z) @ inv_l2)  # [M]
    return CrossFactors(
        zt=np.ascontiguousarray(z_scaled.T),
        offset=offset[None, :],
        inv_l2=inv_l2[None, :],
        log_sf2=np.full((1, 1), log_sf2),
    )


def stack_factors(factors: list[CrossFactors]) -> CrossFactors:
    """Kernels of equal M and D stacked on a new leading axis (one per output channel)."""
    return CrossFactors(*(np.ascontiguousarray(np.stack(parts)) for parts in zip(*factors,
                                                                               strict=True)))


def cross(X: FloatArray, f: CrossFactors, out: FloatArray | None = None,
          tmp: FloatArray | None = None) -> FloatArray:
    """k(X, Z) by K2 for a batch of inputs X [..., N, D] -> [..., N, M].

    ``out`` [..., N, M] and ``tmp`` [..., N, D] are optional scratch arrays for the result
    and for X / l^2.
    """
    logk = np.matmul(X, f.zt, out=out)  # [..., N, M] x . z / l^2
    XL = np.multiply(X, f.inv_l2, out=tmp)  # [..., N, D]
    logk -= 0.5 * np.einsum("...nd,...nd->...n", XL, X)[..., None]
    logk += f.offset
    np.minimum(logk, f.log_sf2, out=logk)  # |x - z|_l^2 >= 0
    return cast(FloatArray, np.exp(logk, out=logk))


def augmented_pseudo_inputs(f: CrossFactors) -> FloatArray:
    """[M, D + 2] rows [z / l^2, log sf2 - |z|_l^2 / 2, -1/2] (single kernel).

    With the matching augmented inputs [x; 1; |x|_l^2] (:func:`augmented_inputs`) one
    product gives log k(Z, X) [M, N] by K2 (:func:`cross_t`), the layout the blocked FITC
    likelihood works in.
    """
    M, D = f.zt.shape[1], f.zt.shape[0]
    z_aug = np.empty((M, D + 2))
    z_aug[:, :D] = f.z_scaled
    z_aug[:, D] = f.offset[0]
    z_aug[:, D + 1] = -0.5
    return z_aug


def augmented_inputs(X: FloatArray) -> FloatArray:
    """[D + 2, N] rows [X^T; 1; |x|_l^2] for X [N, D]; the last row is set per lengthscale
    setting by :func:`set_augmented_norms`."""
    N, D = X.shape
    x_aug_t = np.empty((D + 2, N))
    x_aug_t[:D] = X.T
    x_aug_t[D] = 1.0
    return x_aug_t


def set_augmented_norms(x_aug_t: FloatArray, X_sq: FloatArray, inv_l2: FloatArray) -> None:
    """Write |x|_l^2 = X^2 inv_l2 into the last row of ``x_aug_t`` (X_sq [N, D] = X * X)."""
    np.matmul(X_sq, inv_l2, out=x_aug_t[-1])


def cross_t(z_aug: FloatArray, x_aug_t: FloatArray, out: FloatArray | None = None
            ) -> FloatArray:
    """k(Z, X) [M, N] by K2 from the augmented factors (one product and one exp)."""
    K = np.matmul(z_aug, x_aug_t, out=out)
    return np.exp(K, out=K)


def cross_grad(K: FloatArray, X: FloatArray, wZ: FloatArray, Kw: FloatArray,
               scale: FloatArray, out: FloatArray | None = None) -> FloatArray:
    """Input gradient of a weighted sum of kernels, g(x) = d/dx sum_m w_m k(x, z_m) (K3).

    K3 gives g(x) = (sum_m w_m k(x, z_m) z_m - x sum_m w_m k(x, z_m)) / l^2.

    Args:
        K: [..., N, M] k(X, Z) (:func:`cross`).
        X: [..., N, D] the inputs K was evaluated at.
        wZ: [..., M, D] w_m z_m.
        Kw: [..., N] K w.
        scale: [..., 1, D] 1 / l^2, times any chain-rule factor of the caller (units).
        out: optional [..., N, D] result array.

    Returns:
        [..., N, D] g(x) * l^2 * scale.
    """
    g = np.matmul(K, wZ, out=out)
    g -= X * Kw[..., None]
    g *= scale
    return g


def param_grads(Z: FloatArray, inv_l2: FloatArray, WX: FloatArray, WX_sq: FloatArray,
                w_row: FloatArray, Wuu: FloatArray) -> tuple[FloatArray, float, FloatArray]:
    """Chain rule through K1 for a function of Kuf = k(Z, X) and Kuu = k(Z, Z) (K3, K4).

    With W = dF/dKuf o Kuf [M, N] (given by its moments, so that it is never formed whole:
    WX = W X [M, D], WX_sq = W X^2 [M, D], w_row = W 1 [M]) and Wuu = dF/dKuu o Kuu [M, M]
    symmetric (diagonal included), returns

        dF/dlog l [D] = sum_mn W_mn (z_m - x_n)^2 / l^2 + sum_mm' Wuu (z_m - z_m')^2 / l^2
        dF/dlog sf2   = sum W + sum Wuu       (through k only; the caller adds its own)
        dF/dZ [M, D]  = (WX - w_row Z + 2 (Wuu Z - Wuu 1 Z)) / l^2

    Kuu's diagonal k(z, z) = sf2 (with or without jitter) depends on sf2 only, and Kuu is
    symmetric, so each off-diagonal pair counts twice.
    """
    d_log_sf2 = float(w_row.sum() + np.sum(Wuu))
    Wu = Wuu.copy()
    Wu[np.diag_indices(Wu.shape[0])] = 0.0  # the diagonal does not depend on l or Z
    wu_row = Wu.sum(axis=1)
    WuZ = Wu @ Z
    # (K4) summed against W (Kuf) and Wu (Kuu, each pair twice)
    sum_sq = w_row @ (Z * Z) - 2.0 * np.einsum("md,md->d", Z, WX) + WX_sq.sum(axis=0)
    sum_sq += 2.0 * (wu_row @ (Z * Z) - np.einsum("md,md->d", Z, WuZ))
    d_log_l = sum_sq * inv_l2
    # (K3) in the first argument z_m of k(z_m, x_n) and of k(z_m, z_m')
    dZ = (WX - w_row[:, None] * Z + 2.0 * (WuZ - wu_row[:, None] * Z)) * inv_l2
    return d_log_l, d_log_sf2, dZ
