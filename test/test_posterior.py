"""The cached FITC posterior: its equations, immutability, state arrays, and the results of
the implementation before the posterior and the kernel became shared modules."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from asgp_ros.core import kernel, posterior
from asgp_ros.core.features import FeatureConfig, design_matrix
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.models import MotionModel
from asgp_ros.core.posterior import FitcPosterior, PosteriorError
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP, SparseGPError

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench(load_benchmark) -> ModuleType:
    """benchmarks/rollout.py: its simulated chair and its reference-revision loader (the
    comparison with the previous implementation needs a source checkout with its history;
    an installed or colcon-copied package has neither)."""
    return load_benchmark("rollout")


def _data(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2.0, 2.0, size=(n, 3)) * np.array([1.0, 3.0, 0.5]) + 1.0
    y = np.sin(X[:, 0]) * np.cos(X[:, 1] / 3.0) + 0.5 * X[:, 2]
    return X, 2.0 + y + 0.1 * rng.standard_normal(n)


@pytest.fixture(scope="module")
def fitted() -> tuple[SparseGP, np.ndarray, np.ndarray]:
    X, y = _data(120, seed=1)
    return SparseGP(num_inducing=9, seed=0).fit(X, y, max_iter=40), X, y


# --------------------------------------------------------------- the cached terms


def test_cached_terms_are_the_fitc_predictive_equations(fitted) -> None:
    """alpha, C, L and LA against the dense formulas (S&G eq. 5; P1, P2)."""
    gp, X, y = fitted
    post = gp.posterior
    Xs = (X - post.x_mean) / post.x_scale
    ys = (y - post.y_mean) / post.y_scale
    ls, sf2, sn2 = post.lengthscales, post.signal_variance, post.noise_variance
    Kuu = kernel.se_ard(post.Z, post.Z, ls, sf2) + post.jitter * sf2 * np.eye(len(post.Z))
    Kuf = kernel.se_ard(post.Z, Xs, ls, sf2)
    Qff_diag = np.sum(Kuf * np.linalg.solve(Kuu, Kuf), axis=0)
    lam = sf2 - Qff_diag + sn2  # Lambda (S&G eq. 6)
    Sigma = Kuu + (Kuf / lam) @ Kuf.T
    np.testing.assert_allclose(post.alpha, np.linalg.solve(Sigma, Kuf @ (ys / lam)),
                               rtol=1e-7, atol=1e-9 * np.abs(post.alpha).max())
    C = np.linalg.solve(Kuu, np.eye(len(Kuu))) - np.linalg.solve(Sigma, np.eye(len(Kuu)))
    np.testing.assert_allclose(post.C, C, rtol=1e-6, atol=1e-9 * np.abs(C).max())
    np.testing.assert_allclose(post.L @ post.L.T, Kuu, rtol=1e-12, atol=1e-14)
    V = np.linalg.solve(post.L, Kuf)
    assert post.LA is not None
    np.testing.assert_allclose(post.LA @ post.LA.T, np.eye(len(Kuu)) + (V / lam) @ V.T,
                               rtol=1e-10)
    np.testing.assert_array_equal(post.C, posterior.variance_matrix(post.L, post.LA))


def test_predict_reads_the_stacked_posterior(fitted) -> None:
    gp, X, _ = fitted
    mean, var, grad = posterior.predict(gp.posterior.stacked, X[None], True, True)
    assert mean.shape == var.shape == (1, len(X)) and grad is not None
    for a, b in zip(gp.predict_with_grad(X), (mean[0], var[0], grad[0]), strict=True):
        np.testing.assert_array_equal(a, b)


# --------------------------------------------------------------- immutability


def test_posterior_is_immutable_and_replaced_whole(fitted) -> None:
    gp, X, y = fitted
    post = gp.posterior
    with pytest.raises(ValueError, match="read-only"):
        post.alpha[0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        post.alpha = np.zeros(9)  # type: ignore[misc]
    # an update builds a new object; derived terms follow the new fields
    doubled = dataclasses.replace(post, alpha=2.0 * post.alpha)
    assert doubled is not post and doubled.stacked is not post.stacked
    twin = SparseGP.from_state(gp.get_state())
    twin.posterior = doubled
    m0, _ = gp.predict(X)
    m1, _ = twin.predict(X)
    np.testing.assert_allclose(m1 - doubled.y_mean, 2.0 * (m0 - post.y_mean), rtol=1e-12)
    assert gp.posterior is post  # the original model is untouched
    with pytest.raises(SparseGPError, match="must be a FitcPosterior"):
        twin.posterior = gp.get_state()  # type: ignore[assignment]
    other = SparseGP(num_inducing=4).fit(X[:, :2], y, max_iter=2).posterior
    with pytest.raises(SparseGPError, match="D=2"):
        twin.posterior = other
    with pytest.raises(PosteriorError, match="alpha has shape"):
        dataclasses.replace(post, alpha=np.zeros(3))


def test_new_weights_give_the_posterior_a_replace_would(fitted) -> None:
    """``with_weights`` (an online update's new posterior) equals ``dataclasses.replace``
    with the same LA, alpha and C, field by field and in every stacked array, is as
    read-only, and refuses wrong shapes; the weights are copied, not kept."""
    gp, X, _ = fitted
    post = gp.posterior
    rng = np.random.default_rng(4)
    M = post.num_inducing
    LA = np.tril(rng.standard_normal((M, M))) + 3.0 * np.eye(M)
    alpha = rng.standard_normal(M)
    C = rng.standard_normal((M, M))
    C = C @ C.T * 1e-3
    got = post.with_weights(LA, alpha, C)
    want = dataclasses.replace(post, LA=LA, alpha=alpha, C=C)
    assert got is not post and got.stacked is not post.stacked
    def same(a: object, b: object, name: str) -> None:
        assert type(a) is type(b), name
        if isinstance(a, tuple):  # kernel, stacked: NamedTuples of arrays (and of tuples)
            for x, z, field in zip(a, b, type(a)._fields, strict=True):
                same(x, z, f"{name}.{field}")
        elif isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name

    for f in dataclasses.fields(FitcPosterior):
        same(getattr(got, f.name), getattr(want, f.name), f.name)
        if isinstance(getattr(got, f.name), np.ndarray):
            assert not getattr(got, f.name).flags.writeable, f.name
    for name in ("LA", "alpha", "C"):
        assert not np.shares_memory(getattr(got, name), locals()[name])
    alpha[0] += 1.0  # the caller's array changes; the posterior's does not
    assert got.alpha[0] != alpha[0]
    for a, b in zip(posterior.predict(got.stacked, X[None], True, True),
                    posterior.predict(want.stacked, X[None], True, True), strict=True):
        np.testing.assert_array_equal(a, b)
    assert post.alpha is not got.alpha and gp.posterior is post  # the original untouched
    with pytest.raises(PosteriorError, match="alpha has shape"):
        post.with_weights(LA, np.zeros(3), C)
    with pytest.raises(PosteriorError, match="C has shape"):
        post.with_weights(LA, alpha, C[:2])


# --------------------------------------------------------------- state arrays


def test_state_keeps_the_factors(fitted) -> None:
    gp, X, _ = fitted
    state = gp.get_state()
    post = posterior.from_state(state)
    for name in ("Z", "lengthscales", "alpha", "C", "L", "LA", "x_mean", "x_scale"):
        np.testing.assert_array_equal(getattr(post, name), getattr(gp.posterior, name))
    np.testing.assert_array_equal(state["chol_a"], gp.posterior.LA)
    for a, b in zip(SparseGP.from_state(state).predict_with_grad(X), gp.predict_with_grad(X),
                    strict=True):
        np.testing.assert_array_equal(a, b)


def test_state_without_chol_a_loads_and_recovers_it(fitted) -> None:
    """Files written before the factor was stored: same predictions, LA from C."""
    gp, X, _ = fitted
    state = gp.get_state()
    del state["chol_a"]
    old = SparseGP.from_state(state)
    for a, b in zip(old.predict_with_grad(X), gp.predict_with_grad(X), strict=True):
        np.testing.assert_array_equal(a, b)
    LA, LA_fit = old.posterior.LA, gp.posterior.LA
    assert LA is not None and LA_fit is not None
    np.testing.assert_allclose(LA, LA_fit, rtol=0, atol=1e-6 * np.abs(LA_fit).max())
    assert "chol_a" in old.get_state()


def test_inconsistent_or_malformed_chol_a_is_refused(fitted) -> None:
    gp, X, y = fitted
    state = gp.get_state()
    other = SparseGP(num_inducing=9, seed=5).fit(X, y, max_iter=5).get_state()
    with pytest.raises(SparseGPError, match="'chol_a' and 'var_matrix' disagree"):
        SparseGP.from_state({**state, "chol_a": other["chol_a"]})
    with pytest.raises(SparseGPError, match="not a lower-triangular"):
        SparseGP.from_state({**state, "chol_a": state["chol_a"].T})
    with pytest.raises(SparseGPError, match=r"'chol_a' has shape \(3, 3\)"):
        SparseGP.from_state({**state, "chol_a": np.eye(3)})


@pytest.mark.parametrize("name", ["both_asgp", "carpet_asgp", "tile_asgp_paper"])
def test_repository_model_files_load_with_their_factors(name: str) -> None:
    path = REPO / "docs" / "reproduction" / "models" / f"{name}.npz"
    if not path.exists():
        pytest.skip(f"{path} is not in this checkout")
    model = load_model(path)
    for gp in model.channels:
        assert isinstance(gp, SparseGP)
        post = gp.posterior
        assert post.LA is not None  # stored, or recovered from C in a file that predates chol_a
        np.testing.assert_allclose(posterior.variance_matrix(post.L, post.LA), post.C,
                                   rtol=0, atol=1e-6 * np.abs(post.C).max())


# --------------------------------------------------------------- the previous implementation


@pytest.fixture(scope="module")
def reference(bench: ModuleType) -> dict[str, ModuleType]:
    """sparse_gp.py and rollout.py of the revision before the shared posterior and kernel."""
    try:
        return bench.load_reference(bench.REFERENCE)
    except RuntimeError as err:
        pytest.skip(f"reference revision not available: {err}")


@pytest.fixture(scope="module")
def chair(bench: ModuleType) -> tuple[MotionModel, np.ndarray, np.ndarray]:
    """Two channels with 12 and 20 pseudo-inputs (the fused rollout pads one)."""
    res = bench.simulated(900, seed=2)
    fc = FeatureConfig(lags=4)
    gps = []
    for c, M in enumerate((12, 20)):
        X, y, _ = design_matrix(res, c, fc)
        gps.append(SparseGP(num_inducing=M, seed=c).fit(X, y, max_iter=40))
    return MotionModel("asgp", fc, ResampleConfig(), (gps[0], gps[1])), res.joy, res.vel


def _assert_close_to_scale(a: np.ndarray, b: np.ndarray, tol: float, what: str) -> None:
    """max |a - b| <= tol max |b|: round-off relative to the size of the quantity."""
    scale = float(np.max(np.abs(b)))
    assert float(np.max(np.abs(a - b))) <= tol * scale, (what, float(np.max(np.abs(a - b))),
                                                         scale)


def test_fits_are_identical_to_the_reference(reference) -> None:
    X, y = _data(300, seed=3)
    for kwargs in ({"num_inducing": 10, "seed": 0}, {"num_inducing": 6, "seed": 4,
                                                      "n_restarts": 1, "init": "spread"}):
        new = SparseGP(**kwargs).fit(X, y, max_iter=30)  # type: ignore[arg-type]
        old = reference["sparse_gp"].SparseGP(**kwargs).fit(X, y, max_iter=30)
        s_new, s_old = new.get_state(), old.get_state()
        assert set(s_old) <= set(s_new)
        for key, value in s_old.items():
            np.testing.assert_allclose(s_new[key], value, rtol=1e-12, atol=0, err_msg=key)
        np.testing.assert_allclose(np.array(new.optimisation_log),
                                   np.array(old.optimisation_log), rtol=1e-12)


def test_predictions_match_the_reference(reference, chair) -> None:
    """The same state predicts as before: means and gradients to 1e-12 of their size, the
    variance to 1e-11 of sf2.

    The single-step prediction now runs the arithmetic of the old fused rollout (inputs
    standardised, then K2 with 1 / l^2) instead of its own (inputs in lengthscale units):
    the same equations, rounded differently.  The variance sf2 - ks^T C ks cancels (near
    the data it is a small fraction of sf2), so its round-off is relative to sf2.
    """
    model, _, _ = chair
    rng = np.random.default_rng(7)
    for gp in model.channels:
        assert isinstance(gp, SparseGP)
        old = reference["sparse_gp"].SparseGP.from_state(gp.get_state())
        D = gp.num_features
        Xs = np.vstack([rng.uniform(-1.0, 1.0, (50, D)), rng.uniform(-4.0, 4.0, (10, D))])
        for noise in (True, False):
            m_new, v_new, g_new = gp.predict_with_grad(Xs, include_noise=noise)
            m_old, v_old, g_old = old.predict_with_grad(Xs, include_noise=noise)
            _assert_close_to_scale(m_new, m_old, 1e-12, "mean")
            _assert_close_to_scale(g_new, g_old, 1e-12, "gradient")
            assert float(np.max(np.abs(v_new - v_old))) <= 1e-11 * gp.signal_variance
        np.testing.assert_array_equal(gp.predict(Xs)[0], gp.predict_with_grad(Xs)[0])


def test_rollouts_match_the_reference(reference, chair) -> None:
    """Means to 1e-12 and covariances to 5e-11 of their size.

    The only change in the arithmetic is |z|_l^2 in log k (K2), now computed as in the
    fit (one product, so that fits stay bit for bit the same) where the old rollout had its
    own einsum: a last-bit change of log k, which moves the propagated covariances by
    about 1e-11 of their size through the cancellation in sf2 - ks^T C ks.
    """
    model, joy, vel = chair
    old_rollout = reference["rollout"].rollout
    rng = np.random.default_rng(8)
    t = 400
    jp, vp = joy[t - 4:t], vel[t - 4:t]
    for B in (1, 7):
        jf = np.clip(joy[t:t + 10][None] + rng.normal(0, 0.3, (B, 10, 2)), -1, 1)
        for unc in ("linear", "none"):
            a = rollout(model, jp, vp, jf, unc)  # type: ignore[arg-type]
            b = old_rollout(model, jp, vp, jf, unc)
            for name in ("vel", "pose"):
                _assert_close_to_scale(getattr(a, name), getattr(b, name), 1e-12, name)
            for name in ("vel_cov", "pose_cov"):
                _assert_close_to_scale(getattr(a, name), getattr(b, name), 5e-11, name)
    a = rollout(model, jp, vp, jf, "mc", n_samples=300, rng=4)
    b = old_rollout(model, jp, vp, jf, "mc", n_samples=300, rng=4)
    _assert_close_to_scale(a.pose_cov, b.pose_cov, 1e-10, "Monte Carlo pose_cov")


def test_rollout_follows_a_replaced_posterior(chair) -> None:
    """The fused rollout reads the posterior the channel holds now (no stale copy)."""
    model, joy, vel = chair
    gp_v = model.channels[0]
    assert isinstance(gp_v, SparseGP)
    t = 300
    jp, vp, jf = joy[t - 4:t], vel[t - 4:t], joy[t:t + 1][None]
    before = rollout(model, jp, vp, jf)
    original: FitcPosterior = gp_v.posterior
    try:
        gp_v.posterior = dataclasses.replace(original, y_mean=original.y_mean + 0.25)
        after = rollout(model, jp, vp, jf)
    finally:
        gp_v.posterior = original
    assert after.vel[0, 0, 0] == pytest.approx(before.vel[0, 0, 0] + 0.25, abs=1e-12)
    assert after.vel[0, 0, 1] == before.vel[0, 0, 1]
    np.testing.assert_array_equal(rollout(model, jp, vp, jf).vel, before.vel)
