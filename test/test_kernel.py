"""The ARD squared-exponential kernel (K1 - K4): direct formula, GPy, finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asgp_ros.core import kernel


def _k_direct(A: np.ndarray, B: np.ndarray, ls: np.ndarray, sf2: float) -> np.ndarray:
    """K1 written out with an [P, Q, D] difference array."""
    d = (A[:, None, :] - B[None, :, :]) / ls
    return sf2 * np.exp(-0.5 * np.sum(d * d, axis=-1))


@pytest.fixture
def setting() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(0)
    D = 4
    X = rng.normal(size=(30, D)) * np.array([1.0, 2.0, 0.5, 1.5])
    Z = rng.normal(size=(7, D))
    return X, Z, np.array([0.8, 1.7, 0.6, 2.5]), 1.9


def test_gram_and_cross_forms_agree_with_the_formula(setting) -> None:
    X, Z, ls, sf2 = setting
    ref = _k_direct(X, Z, ls, sf2)
    np.testing.assert_allclose(kernel.se_ard(X, Z, ls, sf2), ref, rtol=1e-12)
    f = kernel.cross_factors(Z, ls, sf2)
    np.testing.assert_allclose(kernel.cross(X, f), ref, rtol=1e-12)
    # the training layout: k(Z, X) [M, N] from augmented factors
    x_aug_t = kernel.augmented_inputs(X)
    kernel.set_augmented_norms(x_aug_t, X * X, f.inv_l2[0])
    np.testing.assert_allclose(kernel.cross_t(kernel.augmented_pseudo_inputs(f), x_aug_t),
                               ref.T, rtol=1e-12)
    Kuu = kernel.se_ard_jittered(Z, ls, sf2, 1e-6)
    np.testing.assert_array_equal(np.diag(Kuu), sf2 * (1.0 + 1e-6))
    np.testing.assert_allclose(Kuu, Kuu.T, rtol=1e-14)
    off = ~np.eye(len(Z), dtype=bool)
    np.testing.assert_allclose(Kuu[off], _k_direct(Z, Z, ls, sf2)[off], rtol=1e-12)


def test_cross_is_clipped_at_the_signal_variance(setting) -> None:
    _, Z, ls, sf2 = setting
    far = Z * 1e4  # |x|_l^2 ~ 1e8: the expanded square cancels badly
    K = kernel.cross(np.vstack([Z, far]), kernel.cross_factors(Z, ls, sf2))
    assert np.all(np.less_equal(K, sf2))
    np.testing.assert_allclose(np.diag(K[: len(Z)]), sf2, rtol=1e-12)
    assert np.all(np.isfinite(K))


def test_stacked_kernels_evaluate_each_channel(setting) -> None:
    X, Z, ls, sf2 = setting
    Z2, ls2, sf2b = Z[::-1] + 0.3, ls[::-1], 0.4
    stacked = kernel.stack_factors([kernel.cross_factors(Z, ls, sf2),
                                    kernel.cross_factors(Z2, ls2, sf2b)])
    K = kernel.cross(np.stack([X, X + 1.0]), stacked)
    assert K.shape == (2, len(X), len(Z))
    np.testing.assert_allclose(K[0], _k_direct(X, Z, ls, sf2), rtol=1e-12)
    np.testing.assert_allclose(K[1], _k_direct(X + 1.0, Z2, ls2, sf2b), rtol=1e-12)


def test_matches_gpy_rbf(setting) -> None:
    GPy = pytest.importorskip("GPy")
    X, Z, ls, sf2 = setting
    rbf = GPy.kern.RBF(X.shape[1], variance=sf2, lengthscale=ls, ARD=True)
    np.testing.assert_allclose(kernel.se_ard(X, Z, ls, sf2), rbf.K(X, Z), rtol=1e-12)
    # K3 against GPy's input gradient of sum_m w_m k(x, z_m)
    w = np.random.default_rng(1).normal(size=len(Z))
    K = kernel.cross(X, kernel.cross_factors(Z, ls, sf2))
    g = kernel.cross_grad(K, X, w[:, None] * Z, K @ w, 1.0 / ls**2)
    ref = rbf.gradients_X(np.ones((len(X), 1)) * w[None, :], X, Z)
    np.testing.assert_allclose(g, ref, rtol=1e-10, atol=1e-12)


def test_input_gradient_matches_finite_differences(setting) -> None:
    X, Z, ls, sf2 = setting
    f = kernel.cross_factors(Z, ls, sf2)
    w = np.random.default_rng(2).normal(size=len(Z))
    K = kernel.cross(X, f)
    g = kernel.cross_grad(K, X, w[:, None] * Z, K @ w, f.inv_l2)
    h = 1e-6
    for d in range(X.shape[1]):
        e = np.zeros(X.shape[1])
        e[d] = h
        fd = (kernel.cross(X + e, f) @ w - kernel.cross(X - e, f) @ w) / (2 * h)
        np.testing.assert_allclose(g[:, d], fd, rtol=1e-6, atol=1e-9)


def test_parameter_gradients_match_finite_differences(setting) -> None:
    """K3, K4 for sum G o k(Z, X) + sum Gu o (k(Z, Z) + jitter sf2 I)."""
    X, Z, ls, sf2 = setting
    rng = np.random.default_rng(3)
    M, D = Z.shape
    G = rng.normal(size=(M, X.shape[0]))
    Gu = rng.normal(size=(M, M))
    Gu = Gu + Gu.T
    jitter = 1e-3

    def objective(log_l: np.ndarray, log_sf2: float, Zp: np.ndarray) -> float:
        ls_, sf2_ = np.exp(log_l), math.exp(log_sf2)
        Kuu = kernel.se_ard_jittered(Zp, ls_, sf2_, jitter)
        return float(np.sum(G * kernel.se_ard(Zp, X, ls_, sf2_)) + np.sum(Gu * Kuu))

    W = G * kernel.se_ard(Z, X, ls, sf2)
    X1 = np.hstack([X, X * X, np.ones((len(X), 1))])
    S = W @ X1
    d_log_l, d_log_sf2, dZ = kernel.param_grads(
        Z, 1.0 / ls**2, S[:, :D], S[:, D:2 * D], S[:, 2 * D],
        Gu * kernel.se_ard_jittered(Z, ls, sf2, jitter))
    h = 1e-6
    log_l, log_sf2 = np.log(ls), math.log(sf2)
    for d in range(D):
        e = np.zeros(D)
        e[d] = h
        fd = (objective(log_l + e, log_sf2, Z) - objective(log_l - e, log_sf2, Z)) / (2 * h)
        assert d_log_l[d] == pytest.approx(fd, rel=1e-6, abs=1e-8)
    fd = (objective(log_l, log_sf2 + h, Z) - objective(log_l, log_sf2 - h, Z)) / (2 * h)
    assert d_log_sf2 == pytest.approx(fd, rel=1e-6)
    for m in range(M):
        for d in range(D):
            e = np.zeros_like(Z)
            e[m, d] = h
            fd = (objective(log_l, log_sf2, Z + e) - objective(log_l, log_sf2, Z - e)) / (2 * h)
            assert dZ[m, d] == pytest.approx(fd, rel=1e-6, abs=1e-8)
