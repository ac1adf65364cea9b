"""Recurrent k-step rollout (Algorithm 1), batching, and uncertainty propagation."""

from __future__ import annotations

import numpy as np
import pytest

from asgp_ros.core.features import FeatureConfig, build_inputs, design_matrix, input_layout
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import ResampleConfig, Resampled
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.core.unicycle import integrate_path

DT = 0.2


class TanhChannel:
    """Stand-in channel: mean = X w + amp tanh(X u), constant variance (exact gradient)."""

    def __init__(self, w: np.ndarray, u: np.ndarray, amp: float, latent: float,
                 noise: float) -> None:
        self.w, self.u, self.amp, self.latent, self.noise = w, u, amp, latent, noise

    def predict(self, X: np.ndarray, include_noise: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        mean = X @ self.w + self.amp * np.tanh(X @ self.u)
        var = np.full(X.shape[0], self.latent + (self.noise if include_noise else 0.0))
        return mean, var

    def predict_with_grad(self, X: np.ndarray, include_noise: bool = True
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        mean, var = self.predict(X, include_noise)
        sech2 = 1.0 - np.tanh(X @ self.u) ** 2
        return mean, var, self.w[None, :] + self.amp * sech2[:, None] * self.u[None, :]


def chair_model(lags: int = 4, nonlinear: float = 1.0, sd: tuple[float, float] = (0.03, 0.05),
                coupled: bool = False) -> MotionModel:
    """A first-order-lag chair with saturating joystick response, as stand-in channels."""
    fc = FeatureConfig(lags=lags, coupled=coupled)
    channels = []
    for c, (gain, pole) in enumerate(((1.5, 0.7), (1.2, 0.6))):
        lay = input_layout(c, fc)
        w = np.zeros(fc.input_dim)
        u = np.zeros(fc.input_dim)
        w[lay.vel_past[-1, c]] = pole
        w[lay.vel_past[-2, c]] = 0.05
        u[lay.joy_now[c]] = 1.3
        u[lay.vel_past[-1, c]] = 0.4 * nonlinear
        if coupled:  # speed reduces the turn rate and vice versa
            w[lay.vel_past[-1, 1 - c]] = -0.05
        channels.append(TanhChannel(w, u, (1 - pole) * gain, sd[c] ** 2 * 0.5,
                                    sd[c] ** 2 * 0.5))
    return MotionModel("asgp", fc, ResampleConfig(), (channels[0], channels[1]))


def windows(rng: np.random.Generator, B: int | None, k: int, s: int = 4
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lead = () if B is None else (B,)
    jp = rng.uniform(-0.6, 0.8, (*lead, s, 2))
    vp = rng.uniform(-0.3, 1.0, (*lead, s, 2))
    jf = rng.uniform(-0.6, 0.8, (B or 1, k, 2))
    return jp, vp, jf


def algorithm_1(model: MotionModel, jp: np.ndarray, vp: np.ndarray,
                jf: np.ndarray) -> np.ndarray:
    """The paper's loop, written plainly for one sequence: [k, 2] predicted V."""
    s = model.lags
    J = list(jp[-s:])
    V = list(vp[-s:])
    out = []
    for j in range(jf.shape[0]):
        J.append(jf[j])
        mean, _ = model.predict_step(np.array(J[-s - 1:-1]), np.array(V[-s:]), jf[j])
        V.append(mean)
        out.append(mean)
    return np.array(out)


def test_k1_equals_a_single_prediction() -> None:
    model = chair_model()
    rng = np.random.default_rng(0)
    jp, vp, jf = windows(rng, None, 1)
    out = rollout(model, jp, vp, jf)
    mean, var = model.predict_step(jp, vp, jf[0, 0])
    np.testing.assert_allclose(out.vel[0, 0], mean, rtol=1e-14)
    np.testing.assert_allclose(out.vel_cov[0, 0], np.diag(var), rtol=1e-12, atol=1e-18)
    # one trapezoid step from the origin with [V_{t-1}, V_t]
    np.testing.assert_allclose(out.pose[0, 0],
                               integrate_path(np.stack([vp[-1], mean]), DT)[1], rtol=1e-14)
    assert out.vel.shape == (1, 1, 2) and out.pose_cov.shape == (1, 1, 3, 3)


def test_matches_algorithm_1() -> None:
    model = chair_model()
    rng = np.random.default_rng(1)
    jp, vp, jf = windows(rng, None, 10)
    for unc in ("none", "linear"):
        out = rollout(model, jp, vp, jf, unc)  # type: ignore[arg-type]
        np.testing.assert_allclose(out.vel[0], algorithm_1(model, jp, vp, jf[0]), rtol=1e-13)
        np.testing.assert_allclose(out.pose[0], integrate_path(
            np.concatenate([vp[-1:], out.vel[0]]), DT)[1:], rtol=1e-13)
    assert np.all(rollout(model, jp, vp, jf, "none").pos_cov == 0.0)


@pytest.mark.parametrize("shared", [True, False])
@pytest.mark.parametrize("unc", ["linear", "none"])
def test_batch_equals_one_by_one(shared: bool, unc: str) -> None:
    model = chair_model(coupled=not shared)
    rng = np.random.default_rng(2)
    B, k = 6, 7
    jp, vp, _ = windows(rng, None if shared else B, k)
    jf = rng.uniform(-0.6, 0.8, (B, k, 2))
    batch = rollout(model, jp, vp, jf, unc)  # type: ignore[arg-type]
    assert batch.vel.shape == (B, k, 2) and batch.pos_cov.shape == (B, k, 2, 2)
    for b in range(B):
        one = rollout(model, jp if shared else jp[b], vp if shared else vp[b], jf[b:b + 1],
                      unc)  # type: ignore[arg-type]
        for name in ("vel", "vel_cov", "pose", "pose_cov", "pos_cov"):
            np.testing.assert_allclose(getattr(batch, name)[b], getattr(one, name)[0],
                                       rtol=1e-12, atol=1e-15, err_msg=name)


def test_linear_ar_variance_closed_form() -> None:
    # V_t = a V_{t-1} + b j_t + e: var(V_{t+j}) = sigma^2 (1 - a^(2(j+1))) / (1 - a^2)
    model = chair_model(nonlinear=0.0)
    for ch in model.channels:
        ch.amp = 0.0  # type: ignore[attr-defined]
        ch.w[:] = 0.0  # type: ignore[attr-defined]
    a = (0.8, -0.5)
    for c, ch in enumerate(model.channels):
        lay = input_layout(c, model.feature_config)
        ch.w[lay.vel_past[-1, c]] = a[c]  # type: ignore[attr-defined]
        ch.w[lay.joy_now[c]] = 0.3  # type: ignore[attr-defined]
    rng = np.random.default_rng(3)
    jp, vp, jf = windows(rng, None, 10)
    out = rollout(model, jp, vp, jf)
    j = np.arange(10)
    for c, sd in enumerate((0.03, 0.05)):
        expected = sd**2 * (1 - a[c] ** (2 * (j + 1))) / (1 - a[c] ** 2)
        np.testing.assert_allclose(out.vel_cov[0, :, c, c], expected, rtol=1e-12)
    np.testing.assert_allclose(out.vel_cov[0, :, 0, 1], 0.0, atol=1e-18)


def test_coupled_linear_covariance_recursion() -> None:
    # coupled lag-1 AR: P_j = A P_{j-1} A^T + Sigma, P_0 = Sigma
    model = chair_model(coupled=True, nonlinear=0.0)
    A = np.array([[0.7, -0.2], [0.3, 0.5]])
    for c, ch in enumerate(model.channels):
        ch.amp = 0.0  # type: ignore[attr-defined]
        ch.w[:] = 0.0  # type: ignore[attr-defined]
        lay = input_layout(c, model.feature_config)
        ch.w[lay.vel_past[-1]] = A[c]  # type: ignore[attr-defined]
    Sigma = np.diag([0.03**2, 0.05**2])
    out = rollout(model, *windows(np.random.default_rng(4), None, 6))
    P = Sigma.copy()
    for j in range(6):
        np.testing.assert_allclose(out.vel_cov[0, j], P, rtol=1e-12, atol=1e-18)
        P = A @ P @ A.T + Sigma


@pytest.mark.parametrize("coupled", [False, True])
def test_linear_agrees_with_monte_carlo(coupled: bool) -> None:
    """Mildly nonlinear model, 2 s horizon: linearised covariances within 10 % of MC.

    Tolerance: MC with n = 20,000 has a relative standard error of sqrt(2 / n) ~ 1 % on a
    variance; the rest is the linearisation error, which this test bounds at 10 % of the
    Frobenius norm of each covariance (and the means within 3 mm / 0.01 m/s).
    """
    model = chair_model(coupled=coupled)
    rng = np.random.default_rng(5)
    jp, vp, jf = windows(rng, 3, 10)
    lin = rollout(model, jp, vp, jf, "linear")
    mc = rollout(model, jp, vp, jf, "mc", n_samples=20000, rng=np.random.default_rng(6))
    np.testing.assert_allclose(mc.vel, lin.vel, atol=0.01)
    np.testing.assert_allclose(mc.pose[..., :2], lin.pose[..., :2], atol=0.003)
    for name in ("vel_cov", "pos_cov", "pose_cov"):
        a, b = getattr(lin, name), getattr(mc, name)
        rel = np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))
        assert rel.max() < 0.10, (name, rel.max())
    # the position uncertainty grows along the horizon
    assert np.all(np.diff(np.trace(lin.pos_cov, axis1=-2, axis2=-1), axis=1) > 0)


def test_linear_is_first_order_exact() -> None:
    """With tiny noise the linearisation is exact: compare against perturbation samples."""
    model = chair_model(sd=(1e-4, 1e-4))
    rng = np.random.default_rng(7)
    jp, vp, jf = windows(rng, None, 8)
    lin = rollout(model, jp, vp, jf, "linear")
    mc = rollout(model, jp, vp, jf, "mc", n_samples=40000, rng=rng)
    np.testing.assert_allclose(mc.pos_cov, lin.pos_cov, rtol=0.05, atol=1e-14)


def test_monte_carlo_is_seeded() -> None:
    model = chair_model()
    jp, vp, jf = windows(np.random.default_rng(8), None, 5)
    a = rollout(model, jp, vp, jf, "mc", n_samples=200, rng=11)
    b = rollout(model, jp, vp, jf, "mc", n_samples=200, rng=11)
    c = rollout(model, jp, vp, jf, "mc", n_samples=200, rng=12)
    np.testing.assert_array_equal(a.pos_cov, b.pos_cov)
    assert not np.array_equal(a.pos_cov, c.pos_cov)
    assert a.uncertainty == "mc"


def test_include_noise_switch() -> None:
    model = chair_model()
    jp, vp, jf = windows(np.random.default_rng(9), None, 3)
    full = rollout(model, jp, vp, jf)
    latent = rollout(model, jp, vp, jf, include_noise=False)
    np.testing.assert_allclose(latent.vel_cov[0, 0], full.vel_cov[0, 0] / 2, rtol=1e-12)


def test_longer_past_windows_use_the_last_s() -> None:
    model = chair_model()
    rng = np.random.default_rng(10)
    jp, vp, jf = windows(rng, None, 4, s=9)
    a = rollout(model, jp, vp, jf)
    b = rollout(model, jp[-4:], vp[-4:], jf)
    np.testing.assert_array_equal(a.pose, b.pose)


def test_bad_input_raises() -> None:
    model = chair_model()
    rng = np.random.default_rng(11)
    jp, vp, jf = windows(rng, None, 5)
    with pytest.raises(ValueError, match=r"joy_past.*lags=4"):
        rollout(model, jp[:3], vp, jf)
    with pytest.raises(ValueError, match="vel_past contains NaN"):
        rollout(model, jp, np.full_like(vp, np.nan), jf)
    with pytest.raises(ValueError, match="joy_future"):
        rollout(model, jp, vp, jf[:, :0])
    with pytest.raises(ValueError, match="joy_future"):
        rollout(model, jp, vp, np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="batch of 3"):
        rollout(model, np.stack([jp] * 3), vp, np.zeros((2, 3, 2)))
    with pytest.raises(ValueError, match="uncertainty"):
        rollout(model, jp, vp, jf, "ukf")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_samples"):
        rollout(model, jp, vp, jf, "mc", n_samples=1)

    class Broken(TanhChannel):
        def predict_with_grad(self, X: np.ndarray, include_noise: bool = True
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            m, v, g = super().predict_with_grad(X, include_noise)
            return m * np.nan, v, g

    ch = model.channels[1]
    broken = Broken(ch.w, ch.u, ch.amp, ch.latent, ch.noise)  # type: ignore[attr-defined]
    bad = MotionModel("asgp", model.feature_config, model.resample_config,
                      (model.channels[0], broken))
    with pytest.raises(ValueError, match="omega predicted NaN"):
        rollout(bad, jp, vp, jf)


# ------------------------------------------------------------ with the real sparse GP

def simulated_resampled(T: int = 1500, seed: int = 0) -> Resampled:
    rng = np.random.default_rng(seed)
    joy = np.clip(np.cumsum(rng.normal(0, 0.12, (T, 2)), axis=0) * 0.3, -1, 1)
    vel = np.zeros((T, 2))
    for t in range(1, T):
        vel[t, 0] = 0.7 * vel[t - 1, 0] + 0.45 * np.tanh(2 * joy[t, 0]) + rng.normal(0, 0.02)
        vel[t, 1] = (0.6 * vel[t - 1, 1] + 0.48 * joy[t, 1] * (1 - 0.3 * abs(vel[t - 1, 0]))
                     + rng.normal(0, 0.02))
    ok = np.ones(T, dtype=bool)
    false = np.zeros(T, dtype=bool)
    return Resampled(t=np.arange(T) * DT, k=np.arange(T, dtype=np.int64), joy=joy, vel=vel,
                     valid=ok, stale=false, tracking_lost=false, gap=false,
                     segment=np.zeros(T, dtype=np.int64), truth=np.full((T, 5), np.nan),
                     truth_valid=false, rate_hz=5.0)


@pytest.fixture(scope="module")
def gp_model() -> tuple[MotionModel, Resampled]:
    res = simulated_resampled()
    fc = FeatureConfig(lags=4)
    gps = []
    for c in range(2):
        X, y, _ = design_matrix(res, c, fc)
        gps.append(SparseGP(num_inducing=20, seed=0).fit(X, y, max_iter=60))
    return MotionModel("asgp", fc, ResampleConfig(), (gps[0], gps[1])), res


def test_sparse_gp_k1_equals_predict(gp_model: tuple[MotionModel, Resampled]) -> None:
    model, res = gp_model
    t = 700
    jp, vp = res.joy[t - 4:t], res.vel[t - 4:t]
    out = rollout(model, jp, vp, res.joy[t][None, None])
    for c, gp in enumerate(model.channels):
        X = build_inputs(jp, vp, res.joy[t], c, model.feature_config)[None]
        mean, var = gp.predict(X)
        # one implementation of the predictive equations (asgp_ros.core.posterior.predict)
        assert out.vel[0, 0, c] == pytest.approx(mean[0], rel=1e-15)
        assert out.vel_cov[0, 0, c, c] == pytest.approx(var[0], rel=1e-15)


def test_sparse_gp_batch_and_monte_carlo(gp_model: tuple[MotionModel, Resampled]) -> None:
    model, res = gp_model
    rng = np.random.default_rng(12)
    starts = rng.integers(10, 1400, 4)
    jp = np.stack([res.joy[t - 4:t] for t in starts])
    vp = np.stack([res.vel[t - 4:t] for t in starts])
    jf = np.stack([res.joy[t:t + 10] for t in starts])
    lin = rollout(model, jp, vp, jf)
    for b in range(4):
        one = rollout(model, jp[b], vp[b], jf[b])
        # (BLAS sums batches in another order; the GP variance sf2 - k'Ck amplifies it)
        np.testing.assert_allclose(lin.pose_cov[b], one.pose_cov[0], rtol=1e-7, atol=1e-14)
        np.testing.assert_allclose(lin.vel[b], algorithm_1(model, jp[b], vp[b], jf[b]),
                                   rtol=1e-12)
    mc = rollout(model, jp, vp, jf, "mc", n_samples=5000, rng=0)
    rel = (np.linalg.norm(lin.pos_cov - mc.pos_cov, axis=(-2, -1))
           / np.linalg.norm(mc.pos_cov, axis=(-2, -1)))
    assert rel.max() < 0.15
    # the recorded path is predicted to within a few centimetres over 1 s
    rec = integrate_path(np.concatenate([vp[:, -1:], np.stack(
        [res.vel[t:t + 10] for t in starts])], axis=1), DT)[:, 1:]
    assert np.median(np.linalg.norm(rec[:, 4, :2] - lin.pose[:, 4, :2], axis=-1)) < 0.05


class Wrapped:
    """Hides the SparseGP type, so rollout takes the generic per-channel path."""

    def __init__(self, gp: SparseGP) -> None:
        self.gp = gp

    def predict(self, X: np.ndarray, include_noise: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        return self.gp.predict(X, include_noise)

    def predict_with_grad(self, X: np.ndarray, include_noise: bool = True
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.gp.predict_with_grad(X, include_noise)


@pytest.mark.parametrize("coupled", [False, True])
def test_fused_sparse_gp_path_equals_the_generic_one(coupled: bool) -> None:
    # different numbers of pseudo-inputs per channel, as the paper's 20 (v) and 40 (omega)
    res = simulated_resampled(T=400, seed=3)
    fc = FeatureConfig(lags=3, coupled=coupled)
    gps = []
    for c, M in enumerate((7, 12)):
        X, y, _ = design_matrix(res, c, fc)
        gps.append(SparseGP(num_inducing=M, seed=1).fit(X, y, max_iter=15))
    fused = MotionModel("asgp", fc, ResampleConfig(), (gps[0], gps[1]))
    generic = MotionModel("asgp", fc, ResampleConfig(), (Wrapped(gps[0]), Wrapped(gps[1])))
    rng = np.random.default_rng(13)
    jp, vp, jf = windows(rng, 5, 6, s=3)
    for unc in ("linear", "none"):
        for noise in (True, False):
            a = rollout(fused, jp, vp, jf, unc, include_noise=noise)  # type: ignore[arg-type]
            b = rollout(generic, jp, vp, jf, unc, include_noise=noise)  # type: ignore[arg-type]
            for name in ("vel", "vel_cov", "pose", "pose_cov"):
                np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9,
                                           atol=1e-15, err_msg=name)
    a = rollout(fused, jp, vp, jf, "mc", n_samples=50, rng=3)
    b = rollout(generic, jp, vp, jf, "mc", n_samples=50, rng=3)
    np.testing.assert_allclose(a.pose_cov, b.pose_cov, rtol=1e-9, atol=1e-15)
    # refitting a channel in place is noticed (the cached posterior is rebuilt)
    before = rollout(fused, jp, vp, jf).vel
    X, y, _ = design_matrix(res, 0, fc)
    gps[0].fit(X, 2.0 * y, max_iter=15)
    after = rollout(fused, jp, vp, jf).vel
    np.testing.assert_allclose(after, rollout(generic, jp, vp, jf).vel, rtol=1e-9)
    assert not np.allclose(before, after)


@pytest.mark.parametrize("use_gp", [False, True])
def test_reused_scratch_memory_does_not_leak_between_rollouts(
        use_gp: bool, gp_model: tuple[MotionModel, Resampled]) -> None:
    import asgp_ros.core.rollout as rollout_module

    model = gp_model[0] if use_gp else chair_model()
    rng = np.random.default_rng(14)
    jp, vp, _ = windows(rng, None, 6)
    jf = rng.uniform(-0.6, 0.8, (3, 6, 2))
    first = rollout(model, jp, vp, jf)
    assert rollout_module._WS.arrays  # scratch memory is in use
    for buf in rollout_module._WS.arrays.values():
        buf.fill(np.nan)  # garbage left by an earlier call must never be read
    again = rollout(model, jp, vp, jf)
    for name in ("vel", "vel_cov", "pose", "pose_cov"):
        np.testing.assert_array_equal(getattr(again, name), getattr(first, name))
    # results are not views of the scratch memory
    rollout(model, jp, vp, rng.uniform(-0.6, 0.8, (3, 6, 2)))
    np.testing.assert_array_equal(again.pose_cov, first.pose_cov)


def test_concurrent_rollouts_from_threads(gp_model: tuple[MotionModel, Resampled]) -> None:
    from concurrent.futures import ThreadPoolExecutor

    model = gp_model[0]
    rng = np.random.default_rng(15)
    jobs = []
    for B in (1, 7, 1, 32, 5, 7):
        jp, vp, _ = windows(rng, None, 8)
        jobs.append((jp, vp, rng.uniform(-0.6, 0.8, (B, 8, 2))))
    serial = [rollout(model, *job).pose_cov for job in jobs]
    with ThreadPoolExecutor(max_workers=3) as pool:
        for _ in range(3):
            parallel = list(pool.map(lambda job: rollout(model, *job).pose_cov, jobs))
            for a, b in zip(serial, parallel, strict=True):
                np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-18)


@pytest.mark.parametrize("use_gp", [False, True])
def test_a_variance_floor_raises_each_step_to_the_floor_models_variance(
        use_gp: bool, gp_model: tuple[MotionModel, Resampled]) -> None:
    """MotionModel.variance_floor: every step's calibrated variance is raised to the floor
    model's at the same input row (the trained model under an adapted one); the mean is
    untouched, and a floor that never binds changes nothing."""
    from dataclasses import replace

    from asgp_ros.core.calibration import VarianceCalibration

    model = gp_model[0] if use_gp else chair_model()
    s = model.lags
    rng = np.random.default_rng(21)
    jp, vp, _ = windows(rng, 6, 8, s=s)
    vp[0] *= 40.0  # far outside anything seen: the floor holds there too
    jf = rng.uniform(-0.9, 0.9, (6, 8, 2))
    narrow = replace(model, calibration=VarianceCalibration(scale=(0.01, 0.02)))
    floored = replace(narrow, variance_floor=model)
    for unc in ("linear", "none"):
        a = rollout(floored, jp, vp, jf, unc)  # type: ignore[arg-type]
        b = rollout(model, jp, vp, jf, unc)  # type: ignore[arg-type]
        # the floor is the wider model at every step: the rollout is the floor's exactly
        for name in ("vel", "vel_cov", "pose", "pose_cov"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-12,
                                       atol=1e-15, err_msg=name)
    assert np.all(rollout(narrow, jp, vp, jf).pos_cov[:, -1, 0, 0]
                  < rollout(floored, jp, vp, jf).pos_cov[:, -1, 0, 0])
    # a floor below the model everywhere never binds
    low_floor = replace(model, variance_floor=narrow)
    np.testing.assert_array_equal(rollout(low_floor, jp, vp, jf).pose_cov,
                                  rollout(model, jp, vp, jf).pose_cov)
    # Monte Carlo samples with the floored variance, the one-step prediction floors too
    np.testing.assert_allclose(rollout(floored, jp, vp, jf, "mc", n_samples=40, rng=2).pose_cov,
                               rollout(model, jp, vp, jf, "mc", n_samples=40, rng=2).pose_cov,
                               rtol=1e-12, atol=1e-15)
    m_f, v_f = floored.predict_step(jp, vp, jf[:, 0])
    m_m, v_m = model.predict_step(jp, vp, jf[:, 0])
    np.testing.assert_array_equal(m_f, m_m)
    np.testing.assert_allclose(v_f, v_m, rtol=1e-12)
    # a NaN of the floor or of the model itself is never hidden: the rollout refuses
    class NanVariance(TanhChannel):
        def predict(self, X: np.ndarray, include_noise: bool = True
                    ) -> tuple[np.ndarray, np.ndarray]:
            mean, var = super().predict(X, include_noise)
            return mean, np.full_like(var, np.nan)

    base = chair_model(lags=s)
    nan_chs = tuple(NanVariance(c.w, c.u, c.amp, c.latent, c.noise) for c in base.channels)
    nan_model = replace(base, channels=nan_chs)
    for a, b in ((base, nan_model), (nan_model, base)):
        with pytest.raises(ValueError, match="NaN"):
            rollout(replace(a, variance_floor=b), jp, vp, jf)
        assert np.all(np.isnan(replace(a, variance_floor=b).predict_step(jp, vp, jf[:, 0])[1]))
    # the floor must read the same input rows
    with pytest.raises(TypeError, match="variance_floor"):
        replace(model, variance_floor=replace(
            model, feature_config=FeatureConfig(lags=s + 1)))


def test_the_fused_outside_floor_equals_the_channel_by_channel_one(
        gp_model: tuple[MotionModel, Resampled]) -> None:
    """Both OutsideFloor channels are evaluated together from the step's input rows
    (P3, :func:`asgp_ros.core.posterior.floor_variance`); the same floors behind a wrapper
    go channel by channel: the rollouts agree, and far outside the training range the
    floor is the trained variance (here it binds), among the pseudo-inputs it does not."""
    from dataclasses import replace

    from asgp_ros.core.calibration import VarianceCalibration
    from asgp_ros.core.posterior import OutsideFloor

    model = gp_model[0]
    floors = tuple(OutsideFloor(ch.posterior) for ch in model.channels)  # type: ignore[attr-defined]

    class Hidden:
        def __init__(self, f: OutsideFloor) -> None:
            self.f = f

        def predict(self, X: np.ndarray, include_noise: bool = True):
            return self.f.predict(X, include_noise)

        def predict_with_grad(self, X: np.ndarray, include_noise: bool = True):
            return self.f.predict_with_grad(X, include_noise)

    fused_floor = replace(model, channels=floors)
    generic_floor = replace(model, channels=(Hidden(floors[0]), Hidden(floors[1])))
    narrow = replace(model, calibration=VarianceCalibration(scale=(0.05, 0.05)))
    rng = np.random.default_rng(22)
    jp, vp, _ = windows(rng, 6, 8)
    vp[:3] *= 40.0  # far outside: the floor binds
    jf = rng.uniform(-0.9, 0.9, (6, 8, 2))
    a = rollout(replace(narrow, variance_floor=fused_floor), jp, vp, jf)
    b = rollout(replace(narrow, variance_floor=generic_floor), jp, vp, jf)
    # the fused floor takes the step's own kernel rows (same pseudo-inputs and kernel)
    from asgp_ros.core import posterior
    from asgp_ros.core.rollout import ChannelStep

    step = ChannelStep(replace(narrow, variance_floor=fused_floor), True, np.zeros(6),
                       scratch=False)
    assert step.floor_shares_kernel
    S = posterior.stack([ch.posterior for ch in model.channels])  # type: ignore[attr-defined]
    assert posterior.same_kernel_rows(S, S)
    assert not posterior.same_kernel_rows(S, S._replace(x_scale=S.x_scale * 1.01))
    assert not posterior.same_kernel_rows(
        S, S._replace(kernel=S.kernel._replace(inv_l2=S.kernel.inv_l2 * 2.0)))
    for name in ("vel", "vel_cov", "pose", "pose_cov"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-10,
                                   atol=1e-15, err_msg=name)
    plain = rollout(model, jp, vp, jf)
    bare = rollout(narrow, jp, vp, jf)
    # far outside: as wide as the unnarrowed model's first step; inside: the narrow one's
    np.testing.assert_allclose(a.vel_cov[:3, 0], plain.vel_cov[:3, 0], rtol=1e-4)  # q ~ 0
    assert np.all(a.vel_cov[3:, 0, 0, 0] < 0.5 * plain.vel_cov[3:, 0, 0, 0])
    assert np.all(a.vel_cov[:, 0] >= bare.vel_cov[:, 0] - 1e-15)
