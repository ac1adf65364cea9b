"""Online FITC posterior updates (asgp_ros.core.adapt): equivalence with the batch
posterior, forgetting, recovery after a change of the function, refused and failed
updates, reset, and the safety rule far outside the training range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asgp_ros.core import adapt, kernel
from asgp_ros.core.adapt import AdaptConfig, AdaptError, OnlinePosterior, RejectReason
from asgp_ros.core.features import FeatureConfig
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP

D = 3
LS = np.array([1.5, 3.0, 5.0])
SF2 = 0.5
SN = 0.05
Z = np.random.default_rng(99).uniform(-2.0, 2.0, size=(30, D))


def f(X: np.ndarray, gain: float = 1.0) -> np.ndarray:
    return 2.0 + gain * (np.sin(X[:, 0]) * np.cos(X[:, 1] / 2.0) + 0.3 * X[:, 2])


def rows(n: int, seed: int, gain: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2.0, 2.0, size=(n, D))
    return X, f(X, gain) + SN * rng.standard_normal(n)


def trained(n: int = 300, seed: int = 1) -> SparseGP:
    """A channel 'trained' at fixed hyperparameters (the posterior is all that matters)."""
    X, y = rows(n, seed)
    return SparseGP.from_params(X, y, Z, LS, SF2, SN**2)


def rmse(gp: SparseGP, X: np.ndarray, gain: float = 1.0) -> float:
    mean, _ = gp.predict(X)
    return float(np.sqrt(np.mean((mean - f(X, gain)) ** 2)))


X_TEST = np.random.default_rng(7).uniform(-2.0, 2.0, size=(400, D))


# --------------------------------------------------------------- the batch posterior


#: a better-conditioned kernel for the equivalence (shorter lengthscales, fewer
#: pseudo-inputs): there the batch posterior itself is reproducible to about 1e-11
Z_SHORT = Z[:15]
LS_SHORT = np.array([1.0, 1.5, 2.0])


def _relative_errors(a: SparseGP, b: SparseGP, Xq: np.ndarray) -> list[float]:
    """Largest relative differences of mean, variance (with noise) and latent variance."""
    out = []
    for include_noise in (True, False):
        m_a, v_a = a.predict(Xq, include_noise)
        m_b, v_b = b.predict(Xq, include_noise)
        if include_noise:
            out.append(float(np.max(np.abs(m_a - m_b) / np.abs(m_b))))
        out.append(float(np.max(np.abs(v_a - v_b) / v_b)))
    return out


@pytest.mark.parametrize("short", [True, False], ids=["conditioned", "ill-conditioned"])
def test_row_by_row_without_forgetting_is_the_batch_fitc_posterior(short: bool) -> None:
    """Absorbing rows one at a time gives the FITC posterior of train + new rows.

    from_params standardises y with the data's own mean and scale and uses mean(y) as the
    prior mean, while the online posterior keeps the trained standardisation and prior
    mean.  The y scale does not matter (sf2 and sn2 are given in original units, so the
    posterior in original units is the same for any scale; likewise the input
    standardisation), but the prior mean does: the new rows are shifted so that their
    mean is the trained mean, which makes mean(train + new) the trained prior mean too.
    Predictions are compared in original units, latent and with noise, inside and
    outside the data.

    The batch posterior is itself exact only to round-off amplified by the conditioning
    of Kuu (C = Kuu^-1 - Sigma cancels): with the long lengthscales of the other tests
    (cond(Kuu) ~ 7e6) the same batch on permuted rows differs by up to 1e-6 relative in
    a small latent variance.  With a better-conditioned kernel the online posterior is
    the batch one to 1e-8; with the ill-conditioned one it is as close to the batch as
    the batch is to itself, within a factor of 10.
    """
    Zc, LSc = (Z_SHORT, LS_SHORT) if short else (Z, LS)
    X1, y1 = rows(300, seed=1)
    X2, y2 = rows(200, seed=2)
    y2 = y2 + (y1.mean() - y2.mean())
    gp = SparseGP.from_params(X1, y1, Zc, LSc, SF2, SN**2)
    online = OnlinePosterior.from_sparse_gp(gp)
    for x, y in zip(X2, y2, strict=True):
        assert online.absorb(x, float(y))
    X12, y12 = np.vstack([X1, X2]), np.concatenate([y1, y2])
    batch = SparseGP.from_params(X12, y12, Zc, LSc, SF2, SN**2)
    assert math.isclose(batch.posterior.y_mean, gp.posterior.y_mean, rel_tol=1e-14)
    Xq = np.random.default_rng(3).uniform(-3.5, 3.5, size=(500, D))
    errors = _relative_errors(gp, batch, Xq)
    perm = np.random.default_rng(4).permutation(500)
    floor = _relative_errors(SparseGP.from_params(X12[perm], y12[perm], Zc, LSc, SF2, SN**2),
                             batch, Xq)
    if short:
        assert max(errors) < 1e-8, (errors, floor)
    else:
        for err, ref in zip(errors, floor, strict=True):
            assert err < 10.0 * ref + 1e-12, (errors, floor)
    s = online.stats
    assert s.rows_absorbed == 200 and s.data_weight == 200.0 and s.trained_weight == 1.0
    assert s.effective_size == 500.0
    assert sum(s.rejected.values()) == 0

    # the same rows as blocks: the same posterior
    block = OnlinePosterior(SparseGP.from_params(X1, y1, Zc, LSc, SF2, SN**2).posterior, 300)
    for i in range(0, 200, 50):
        assert block.absorb_rows(X2[i:i + 50], y2[i:i + 50]) == 50
    for name in ("alpha", "C"):
        ref_arr = getattr(online.posterior, name)
        np.testing.assert_allclose(getattr(block.posterior, name), ref_arr, rtol=0.0,
                                   atol=1e-9 * np.abs(ref_arr).max())


def test_published_posterior_is_what_the_model_and_rollout_read() -> None:
    gp = trained()
    online = OnlinePosterior.from_sparse_gp(gp)
    first = gp.posterior
    assert online.posterior is first
    X2, y2 = rows(5, seed=4)
    online.absorb_rows(X2, y2)
    assert gp.posterior is online.posterior is not first  # a new object: caches see it
    assert online.posterior.y_mean == first.y_mean and online.posterior.L is not None
    np.testing.assert_array_equal(online.posterior.Z, first.Z)
    unbound = OnlinePosterior.from_sparse_gp(trained(), bind=False)
    unbound.absorb_rows(X2, y2)
    assert unbound.model is None


class _Hidden:
    """A SparseGP behind another type: rollout's generic per-channel path (no cache)."""

    def __init__(self, gp: SparseGP) -> None:
        self.gp = gp

    def predict(self, X: np.ndarray, include_noise: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        return self.gp.predict(X, include_noise)

    def predict_with_grad(self, X: np.ndarray, include_noise: bool = True
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.gp.predict_with_grad(X, include_noise)


def test_the_fused_rollout_reads_each_published_posterior() -> None:
    """The fused rollout caches the stacked posteriors by identity: after each update it
    predicts from the new ones (the same as the uncached per-channel path)."""
    fc = FeatureConfig(lags=2)
    rng = np.random.default_rng(16)
    gps, onlines = [], []
    for _ in range(2):
        X = rng.uniform(-1.0, 1.0, size=(200, fc.input_dim))
        y = np.tanh(X @ rng.standard_normal(fc.input_dim)) + 0.01 * rng.standard_normal(200)
        gp = SparseGP.from_params(X, y, X[:10], np.full(fc.input_dim, 1.5), 0.5, 1e-4)
        gps.append(gp)
        onlines.append(OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_rows=20.0)))
    fused = MotionModel("asgp", fc, ResampleConfig(), (gps[0], gps[1]))
    generic = MotionModel("asgp", fc, ResampleConfig(), (_Hidden(gps[0]), _Hidden(gps[1])))
    jp = rng.uniform(-0.5, 0.5, (2, 2))
    vp = rng.uniform(0.0, 0.5, (2, 2))
    jf = rng.uniform(-0.5, 0.5, (3, 4, 2))
    before = rollout(fused, jp, vp, jf)
    for step in range(2):
        for c, online in enumerate(onlines):
            X = rng.uniform(-1.0, 1.0, size=(5, fc.input_dim))
            online.absorb_rows(X, np.full(5, 0.8 + 0.1 * step + 0.1 * c))
        a = rollout(fused, jp, vp, jf)
        b = rollout(generic, jp, vp, jf)
        for name in ("vel", "vel_cov", "pose_cov"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9,
                                       atol=1e-12)
        assert np.max(np.abs(a.vel - before.vel)) > 1e-3


# --------------------------------------------------------------- streams


def test_stationary_stream_leaves_accuracy_unchanged() -> None:
    gp = trained()
    before = rmse(gp, X_TEST)
    online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_rows=100.0))
    X2, y2 = rows(800, seed=5)
    errors = []
    for i in range(0, 800, 100):
        online.absorb_rows(X2[i:i + 100], y2[i:i + 100])
        errors.append(rmse(gp, X_TEST))
    # the noise is 0.05; the trained error is well below it and stays so
    assert before < 0.5 * SN
    assert max(errors) < before + 0.2 * SN, (before, errors)


def test_switched_stream_recovers_and_old_data_fade() -> None:
    """The function changes (gain x0.7): after a few half-lives the adapted error is
    close to that of a model trained on the new function alone; the unadapted model's
    stays large."""
    h = 100.0
    gp = trained()
    online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_rows=h))
    stale = rmse(gp, X_TEST, gain=0.7)
    X2, y2 = rows(1000, seed=6, gain=0.7)
    for i in range(0, 1000, 50):
        online.absorb_rows(X2[i:i + 50], y2[i:i + 50])
    adapted = rmse(gp, X_TEST, gain=0.7)
    # reference: the same hyperparameters on as many new-function rows as the adapted
    # posterior effectively holds (about h / ln 2), prior mean included
    n_eff = int(h / math.log(2.0))
    reference = SparseGP.from_params(X2[-n_eff:], y2[-n_eff:], Z, LS, SF2, SN**2)
    ref = rmse(reference, X_TEST, gain=0.7)
    assert stale > 4.0 * ref, (stale, ref)
    assert adapted < 1.5 * ref + 0.1 * SN, (adapted, ref, stale)

    # bounded memory: n_D -> 1 / (1 - gamma) ~ h / ln 2 + 1/2, w_T -> the floor
    s = online.stats
    bound = 1.0 / (1.0 - 2.0 ** (-1.0 / h))
    assert bound < h / math.log(2.0) + 1.0
    assert 0.99 * bound < s.data_weight <= bound
    rho = online.config.trained_floor
    assert rho < s.trained_weight < rho + (1.0 - rho) * 2.0 ** (-1000 / h) * 1.0001
    assert s.effective_size == pytest.approx(s.trained_weight * 300 + s.data_weight)
    assert s.rows_absorbed == 1000


def test_half_life_in_seconds_uses_the_stamps() -> None:
    h = 10.0
    online = OnlinePosterior(trained().posterior, 300, AdaptConfig(half_life_s=h,
                                                                   trained_floor=0.0))
    X2, y2 = rows(400, seed=8)
    dt = 0.2
    t = dt * np.arange(400)
    assert online.absorb_rows(X2, y2, t) == 400
    s = online.stats
    assert s.data_weight == pytest.approx(
        (1 - 2.0 ** (-400 * dt / h)) / (1 - 2.0 ** (-dt / h)), rel=1e-12)
    assert s.trained_weight == pytest.approx(2.0 ** (-(t[-1] - t[0]) / h), rel=1e-12)
    # a pause of ten half-lives (VO lost, a forward clock jump): only time with rows
    # forgets, the pause counts as max_gap_s (1 s)
    before, trained_before = s.data_weight, s.trained_weight
    assert online.absorb(X2[0], float(y2[0]), t[-1] + 10 * h)
    assert online.stats.data_weight == pytest.approx(1.0 + before * 2.0 ** (-1.0 / h),
                                                     rel=1e-12)
    assert online.stats.trained_weight == pytest.approx(trained_before * 2.0 ** (-1.0 / h),
                                                        rel=1e-12)
    # uncapped, everything before it counts 2^-10
    uncapped = OnlinePosterior(trained().posterior, 300, AdaptConfig(
        half_life_s=h, trained_floor=0.0, max_gap_s=math.inf))
    assert uncapped.absorb_rows(X2, y2, t) == 400
    assert uncapped.absorb(X2[0], float(y2[0]), t[-1] + 10 * h)
    assert uncapped.stats.data_weight == pytest.approx(1.0 + before / 1024.0, rel=1e-12)
    with pytest.raises(AdaptError, match="max_gap_s"):
        AdaptConfig(half_life_s=h, max_gap_s=float("nan"))
    with pytest.raises(AdaptError, match="time stamps"):
        online.absorb(X2[0], float(y2[0]))


@pytest.mark.parametrize("unit", ["s", "rows"])
def test_trained_data_fade_with_their_own_half_life(unit: str) -> None:
    """A7': the trained weight decays with h_T, the new rows with h, in either unit."""
    h, h_t, rho = 500.0, 50.0, 0.1
    cfg = (AdaptConfig(half_life_s=h, trained_half_life=h_t, trained_floor=rho) if unit == "s"
           else AdaptConfig(half_life_rows=h, trained_half_life=h_t, trained_floor=rho))
    online = OnlinePosterior(trained().posterior, 300, cfg)
    X2, y2 = rows(200, seed=9)
    t = 1.0 * np.arange(200)  # one second per row: seconds and rows decay alike
    assert online.absorb_rows(X2[:120], y2[:120], t[:120]) == 120
    assert online.absorb_rows(X2[120:], y2[120:], t[120:]) == 80
    s = online.stats
    # stamps: the first row decays nothing (no earlier stamp); rows: every row decays
    decays = 199 if unit == "s" else 200
    assert s.data_weight == pytest.approx(sum(2.0 ** (-i / h) for i in range(200)), rel=1e-12)
    assert s.trained_weight == pytest.approx(rho + (1 - rho) * 2.0 ** (-decays / h_t),
                                             rel=1e-12)
    with pytest.raises(AdaptError, match="needs half_life"):
        AdaptConfig(trained_half_life=5.0)
    with pytest.raises(AdaptError, match="trained_half_life"):
        AdaptConfig(half_life_s=10.0, trained_half_life=float("nan"))


def test_forgetting_with_floor_zero_returns_to_the_prior_where_no_data_come() -> None:
    """rho = 0: the trained data fade completely; far from the new rows the posterior is
    the prior (mean y_mean, variance sf2), and it stays positive definite."""
    gp = trained()
    online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_rows=5.0,
                                                            trained_floor=0.0))
    rng = np.random.default_rng(9)
    X2 = rng.uniform(-2.0, 2.0, size=(400, D))
    X2[:, 0] = rng.uniform(1.5, 2.0, size=400)  # the new rows all at x0 in [1.5, 2]
    online.absorb_rows(X2, f(X2) + SN * rng.standard_normal(400))
    assert online.stats.trained_weight < 1e-20
    Xq = np.column_stack([np.full(20, -9.0), rng.uniform(-2, 2, size=(20, 2))])
    mean, var = gp.predict(Xq, include_noise=False)
    post = gp.posterior
    np.testing.assert_allclose(mean, post.y_mean, atol=1e-3 * post.y_scale)
    np.testing.assert_allclose(var, SF2, rtol=1e-3)
    assert np.all(np.linalg.eigvalsh(post.LA @ post.LA.T) >= 1.0 - 1e-9)


# --------------------------------------------------------------- the trained mean (A9)


@pytest.mark.parametrize("config", [dict(), dict(half_life_rows=50.0, trained_floor=0.3)],
                         ids=["no forgetting", "forgetting"])
def test_trained_mean_has_the_same_variance_and_without_fading_the_same_mean(
        config: dict[str, float]) -> None:
    """A9 changes the mean only: C (and LA) are those of A6 for the same rows; while the
    trained data keep their whole weight the mean is A6's too (A9 is A6 then, by the
    algebra in the module docstring), and once they fade it is not."""
    X2, y2 = rows(200, seed=21, gain=0.6)
    posts = {}
    for trained_mean in (False, True):
        gp = trained()
        online = OnlinePosterior.from_sparse_gp(
            gp, AdaptConfig(trained_mean=trained_mean, **config))  # type: ignore[arg-type]
        assert online.absorb_rows(X2, y2) == 200
        posts[trained_mean] = (online.posterior, gp)
    (a6, gp6), (a9, gp9) = posts[False], posts[True]
    np.testing.assert_array_equal(a9.C, a6.C)
    np.testing.assert_array_equal(a9.LA, a6.LA)
    m6, v6 = gp6.predict(X_TEST)
    m9, v9 = gp9.predict(X_TEST)
    np.testing.assert_array_equal(v9, v6)
    if not config:
        np.testing.assert_allclose(m9, m6, rtol=0.0, atol=1e-9 * np.abs(m6).max())
    else:
        assert np.max(np.abs(m9 - m6)) > 1e-3


def _trained_mean_reference(gp: SparseGP, X_new: np.ndarray, y_new: np.ndarray,
                            Xq: np.ndarray, extra_noise: float = 0.0) -> np.ndarray:
    """A9 with the trained data forgotten (w_T = 0), from the dense FITC formulas: the
    trained mean plus the FITC posterior mean of the residuals y - m_T(x) under the
    zero-mean prior of the same kernel (standardised units, S&G eq. 5); ``extra_noise``
    (standardised) is added to each new row's lambda (A10)."""
    post = gp.posterior
    m_T = gp.predict(X_new)[0]
    r = (y_new - m_T) / post.y_scale
    Xs = (X_new - post.x_mean) / post.x_scale
    Xqs = (Xq - post.x_mean) / post.x_scale
    Kuu = kernel.se_ard_jittered(post.Z, post.lengthscales, post.signal_variance, post.jitter)
    Kuf = kernel.se_ard(post.Z, Xs, post.lengthscales, post.signal_variance)
    Q_diag = np.einsum("mn,mn->n", Kuf, np.linalg.solve(Kuu, Kuf))
    lam = post.signal_variance + post.noise_variance - Q_diag + extra_noise
    Sigma = Kuu + (Kuf / lam) @ Kuf.T
    ks = kernel.se_ard(post.Z, Xqs, post.lengthscales, post.signal_variance)
    correction = ks.T @ np.linalg.solve(Sigma, Kuf @ (r / lam))
    return gp.predict(Xq)[0] + post.y_scale * correction


def test_trained_mean_is_the_trained_function_plus_a_residual_posterior() -> None:
    """With the trained data forgotten (floor 0, a short trained half-life) and the new rows
    kept, the published mean is m_T + the FITC posterior of the residuals (dense
    reference), and where no new row came the trained function still holds, while the
    constant prior mean (A6) falls back to y_mean there."""
    rng = np.random.default_rng(31)
    X2 = rng.uniform(-2.0, 2.0, size=(300, D))
    X2[:, 0] = rng.uniform(1.0, 2.0, size=300)  # the new rows all at x0 in [1, 2]
    y2 = f(X2, gain=0.5) + SN * rng.standard_normal(300)
    config = dict(half_life_rows=1e12, trained_half_life=1e-6, trained_floor=0.0)
    gp9, gp6 = trained(), trained()
    reference = trained()
    o9 = OnlinePosterior.from_sparse_gp(gp9, AdaptConfig(trained_mean=True, **config))
    o6 = OnlinePosterior.from_sparse_gp(gp6, AdaptConfig(trained_mean=False, **config))
    assert o9.absorb_rows(X2, y2) == 300 and o6.absorb_rows(X2, y2) == 300
    assert o9.stats.trained_weight == 0.0
    Xq = np.random.default_rng(32).uniform(-2.5, 2.5, size=(300, D))
    expected = _trained_mean_reference(reference, X2, y2, Xq)
    np.testing.assert_allclose(gp9.predict(Xq)[0], expected, rtol=0.0,
                               atol=1e-6 * np.abs(expected).max())
    # where the chair drove, both learnt the new function; elsewhere only A9 kept the old
    near = np.column_stack([rng.uniform(1.2, 1.8, 200), rng.uniform(-2.0, 2.0, (200, 2))])
    far = np.column_stack([rng.uniform(-2.0, -1.5, 200), rng.uniform(-2.0, 2.0, (200, 2))])
    assert rmse(gp9, near, gain=0.5) < 0.05 and rmse(gp6, near, gain=0.5) < 0.05
    assert rmse(gp9, far) < 0.5 * rmse(gp6, far)


def test_row_noise_weights_the_new_rows_as_rows_of_that_noise() -> None:
    """A10: with row_noise the new rows count as if their lambda were larger by row_noise
    sf2 (dense reference); the mean then moves less on the same rows, and with a very
    large row_noise hardly at all. row_noise 0 is the default and FITC's weighting."""
    rng = np.random.default_rng(41)
    X2 = rng.uniform(-2.0, 2.0, size=(200, D))
    y2 = f(X2, gain=0.5) + SN * rng.standard_normal(200)
    config = dict(half_life_rows=1e12, trained_half_life=1e-6, trained_floor=0.0)
    Xq = np.random.default_rng(42).uniform(-2.0, 2.0, size=(300, D))
    moved = []
    for nu in (0.0, 0.3, 1e6):
        gp = trained()
        online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(row_noise=nu, **config))
        assert online.absorb_rows(X2, y2) == 200
        reference = trained()
        expected = _trained_mean_reference(
            reference, X2, y2, Xq, extra_noise=nu * reference.posterior.signal_variance)
        np.testing.assert_allclose(gp.predict(Xq)[0], expected, rtol=0.0,
                                   atol=1e-6 * np.abs(expected).max())
        moved.append(float(np.abs(gp.predict(Xq)[0] - reference.predict(Xq)[0]).mean()))
    assert moved[0] > moved[1] > 1e3 * moved[2], moved
    assert AdaptConfig().row_noise == 0.0


# --------------------------------------------------------------- refused and failed


def _snapshot(gp: SparseGP) -> tuple[np.ndarray, np.ndarray]:
    return gp.predict(X_TEST)


def test_invalid_rows_are_counted_and_change_nothing() -> None:
    gp = trained()
    online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_s=30.0))
    X2, y2 = rows(3, seed=10)
    assert online.absorb_rows(X2, y2, [0.0, 0.2, 0.4]) == 3
    post, stats = online.posterior, online.stats
    m0, v0 = _snapshot(gp)
    x = X2[0]
    assert gp.posterior.y_scale < 1.0
    bad = [
        (np.array([np.nan, 0.0, 0.0]), 1.0, 1.0, RejectReason.NONFINITE),
        (np.array([0.0, np.inf, 0.0]), 1.0, 1.0, RejectReason.NONFINITE),
        (x, np.nan, 1.0, RejectReason.NONFINITE),
        (x, -np.inf, 1.0, RejectReason.NONFINITE),
        (x, 1.0, np.nan, RejectReason.NONFINITE),
        (x, -np.finfo(np.float64).max, 1.0, RejectReason.NONFINITE),  # -inf scaled
        (x, 1.0, 0.3, RejectReason.TIME_ORDER),  # older than the last absorbed row
        (np.array([9.0, 0.0, 0.0]), 1.0, 1.0, RejectReason.OUTSIDE),
        # finite but absurd: absorbed, it moved the mean at the training rows to 1e27
        (x, 1e30, 1.0, RejectReason.OUTPUT_RANGE),
        (x, -1e4, 1.0, RejectReason.OUTPUT_RANGE),
    ]
    for xb, yb, tb, _ in bad:
        assert not online.absorb(xb, yb, tb)
    assert online.posterior is post and gp.posterior is post
    m1, v1 = _snapshot(gp)
    np.testing.assert_array_equal(m1, m0)
    np.testing.assert_array_equal(v1, v0)
    s = online.stats
    for reason in RejectReason:
        expected = sum(r is reason for *_, r in bad)
        assert s.rejected[reason] == expected, reason
    assert (s.rows_absorbed, s.data_weight, s.trained_weight) == (
        stats.rows_absorbed, stats.data_weight, stats.trained_weight)
    # a block with a bad row absorbs the good ones around it
    X3, y3 = rows(3, seed=11)
    X3[1, 2] = np.nan
    assert online.absorb_rows(X3, y3, [1.0, 1.2, 1.4]) == 2
    assert online.stats.rejected[RejectReason.NONFINITE] == 7
    with pytest.raises(AdaptError):
        online.absorb(np.zeros(D + 1), 1.0, 2.0)
    with pytest.raises(AdaptError):
        online.absorb_rows(np.zeros((2, D)), np.zeros(3), [3.0, 4.0])


@pytest.mark.parametrize("failure", ["factorisation", "nonfinite_terms"])
def test_failed_update_leaves_the_posterior_bitwise_unchanged(
    monkeypatch: pytest.MonkeyPatch, failure: str
) -> None:
    """An update whose terms are not finite, or whose Cholesky factorisation fails (both
    simulated: A >= I cannot fail in exact arithmetic, and an absurd y is refused row by
    row), is rejected whole: the posterior and the statistics stay as they were."""
    gp = trained()
    online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_rows=50.0))
    X2, y2 = rows(4, seed=12)
    online.absorb_rows(X2[:2], y2[:2])
    post, stats = online.posterior, online.stats
    alpha, C = post.alpha.copy(), post.C.copy()
    y_bad = y2[2:].copy()
    potrf = adapt._potrf

    def broken_potrf(A: np.ndarray, **kw: int) -> tuple[np.ndarray, int]:
        LA, info = potrf(A, **kw)
        if failure == "factorisation":
            return LA, 3  # "the leading minor of order 3 is not positive definite"
        LA[0, 0] = np.nan  # a factor that overflowed
        return LA, info
    monkeypatch.setattr(adapt, "_potrf", broken_potrf)
    assert online.absorb_rows(X2[2:], y_bad) == 0
    assert online.posterior is post and gp.posterior is post
    np.testing.assert_array_equal(post.alpha, alpha)
    np.testing.assert_array_equal(post.C, C)
    s = online.stats
    assert s.rejected[failure] == 2
    assert sum(s.rejected.values()) == 2
    assert (s.rows_absorbed, s.data_weight, s.trained_weight) == (
        stats.rows_absorbed, stats.data_weight, stats.trained_weight)
    monkeypatch.undo()
    assert online.absorb_rows(X2[2:], y2[2:]) == 2  # the statistics were not touched
    assert online.stats.rows_absorbed == 4


def test_reset_returns_exactly_the_trained_predictions() -> None:
    gp = trained()
    online = OnlinePosterior.from_sparse_gp(gp, AdaptConfig(half_life_rows=20.0))
    m0, v0 = _snapshot(gp)
    first = gp.posterior
    X2, y2 = rows(300, seed=13, gain=0.5)
    online.absorb_rows(X2, y2)
    m1, _ = _snapshot(gp)
    assert np.max(np.abs(m1 - m0)) > 0.1
    online.reset()
    assert gp.posterior is first and online.posterior is first
    m2, v2 = _snapshot(gp)
    np.testing.assert_array_equal(m2, m0)
    np.testing.assert_array_equal(v2, v0)
    s = online.stats
    assert (s.rows_absorbed, s.data_weight, s.trained_weight, s.effective_size) == (
        0, 0.0, 1.0, 300.0)
    # and adapting again from there is the same as the first time
    online.absorb_rows(X2, y2)
    np.testing.assert_array_equal(_snapshot(gp)[0], m1)


# --------------------------------------------------------------- safety


def _min_distance(X: np.ndarray) -> np.ndarray:
    """Scaled ARD distance (in lengthscales) of each row to its nearest pseudo-input."""
    return np.sqrt(kernel.scaled_sq_dist(X, Z, 1.0 / LS**2).min(axis=1))


def _directions(n: int, rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """n inputs in random directions, lo .. hi lengthscales from the nearest pseudo-input."""
    out: list[np.ndarray] = []
    while sum(len(o) for o in out) < n:
        dirs = rng.standard_normal((4 * n, D))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        X = dirs * LS * rng.uniform(lo, hi + 3.0, size=(4 * n, 1))
        d = _min_distance(X)
        out.append(X[(d >= lo) & (d <= hi)])
    return np.vstack(out)[:n]


def _q(gp: SparseGP, X: np.ndarray) -> np.ndarray:
    """q(x, x) = k_x^T Kuu^-1 k_x in original units (A8)."""
    post = gp.posterior
    K = kernel.cross((X - post.x_mean) / post.x_scale, post.kernel)  # [n, M]
    U = np.linalg.solve(post.L, K.T)
    return np.einsum("mn,mn->n", U, U) * post.y_scale**2


def test_far_outside_the_training_range_the_variance_does_not_shrink() -> None:
    """Rows beyond max_distance (3) lengthscales of every pseudo-input are not absorbed,
    so they cannot shrink the variance where they are; the change the absorbed in-range
    rows make there is at most q(x, x) (A8), which vanishes with the distance: below
    1e-8 relative from five lengthscales on."""
    rng = np.random.default_rng(14)
    X_out = _directions(150, rng, 3.2, 4.5)  # just outside: the rule's domain
    X_far = _directions(300, rng, 5.0, 9.0)  # far outside
    X_in, y_in = rows(300, seed=15)
    X_all = np.vstack([X_in, X_out])
    y_all = np.concatenate([y_in, np.full(len(X_out), 4.0)])
    order = rng.permutation(len(y_all))
    gp0 = trained()
    _, v_out0 = gp0.predict(X_out, include_noise=False)
    _, v_far0 = gp0.predict(X_far, include_noise=False)
    q_out, q_far = _q(gp0, X_out), _q(gp0, X_far)

    gated = []
    for config in (AdaptConfig(), AdaptConfig(half_life_rows=50.0)):
        gp = trained()
        online = OnlinePosterior.from_sparse_gp(gp, config)
        for i in order:
            online.absorb(X_all[i], float(y_all[i]))
        assert online.stats.rejected[RejectReason.OUTSIDE] == len(X_out)
        assert online.stats.rows_absorbed == len(X_in)
        _, v_out = gp.predict(X_out, include_noise=False)
        _, v_far = gp.predict(X_far, include_noise=False)
        gated.append(v_out)
        assert np.all(v_out >= v_out0 - q_out) and np.all(v_far >= v_far0 - q_far)
        assert np.all(v_far >= v_far0 * (1.0 - 1e-8)), np.min(v_far / v_far0 - 1.0)
        if config.forgets:
            # the trained data fade towards the floor faster than the in-range rows
            # inform the outside: in this stream the variance outside only grows
            assert np.all(v_out >= v_out0) and np.all(v_far >= v_far0)
        else:
            assert np.all(v_out >= v_out0 * (1.0 - 1e-3)), np.min(v_out / v_out0 - 1.0)

    # Without the rule the outside rows are absorbed and shrink the variance there
    # further (little: FITC's lambda = sf2 - q + sn2 makes them weak data, A1 and A8).
    ungated = OnlinePosterior.from_sparse_gp(trained(), AdaptConfig(max_distance=None))
    for i in order:
        ungated.absorb(X_all[i], float(y_all[i]))
    assert ungated.stats.rows_absorbed == len(y_all)
    assert ungated.model is not None
    _, v_ungated = ungated.model.predict(X_out, include_noise=False)
    assert np.all(v_ungated <= gated[0]) and np.any(v_ungated < gated[0])


def test_config_is_validated() -> None:
    for bad in (dict(half_life_s=1.0, half_life_rows=1.0), dict(half_life_s=0.0),
                dict(half_life_rows=-1.0), dict(half_life_s=math.inf),
                dict(trained_floor=1.5), dict(trained_floor=-0.1), dict(max_distance=0.0),
                dict(trained_mean=1), dict(row_noise=-0.1), dict(row_noise=math.nan),
                dict(row_noise=math.inf), dict(row_noise=True), dict(row_noise=1e7)):
        with pytest.raises(AdaptError):
            AdaptConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(AdaptError):
        OnlinePosterior(trained().posterior, -1)
