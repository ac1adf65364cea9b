"""The automatic ASGP configuration and the variance calibration (core/calibration.py).

Synthetic chairs with known dynamics and noise, not the package's simulator: the
calibration must reach its coverage on data whose noise level is known, whatever made
them.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
import zipfile

import numpy as np
import pytest

from asgp_ros.cli import main
from asgp_ros.core.calibration import (
    BASIS,
    CalibrationError,
    VarianceCalibration,
    combine,
    coverage,
    fit_calibration,
)
from asgp_ros.core.features import FeatureConfig, input_layout
from asgp_ros.core.modelfile import ModelFileError, load_model, save_model
from asgp_ros.core.resample import Resampled
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.learning import training
from asgp_ros.learning.evaluation import TestSeries, evaluate_model
from asgp_ros.learning.training import (
    PAPER_OPTIONS,
    AutoOptions,
    Series,
    read_series,
    split_holdout,
    train,
    train_auto,
)


def _resampled(joy: np.ndarray, vel: np.ndarray) -> Resampled:
    T = joy.shape[0]
    false = np.zeros(T, dtype=bool)
    return Resampled(
        t=np.arange(T) / 5.0, k=np.arange(T, dtype=np.int64), joy=joy, vel=vel,
        valid=~false, stale=false, tracking_lost=false, gap=false,
        segment=np.zeros(T, dtype=np.int64), truth=np.full((T, 5), np.nan),
        truth_valid=false, rate_hz=5.0)


def synthetic_chair(seconds: float, seed: int, *, slow_noise: float = 0.03,
                    fast_noise: float = 0.008, joy_range: tuple[float, float] = (-1.0, 1.0)
                    ) -> Resampled:
    """A first-order chair at 5 Hz with known, speed-dependent noise.

    v_t = 0.7 v_{t-1} + 0.3 * 0.8 j_fwd + e_v, omega_t = 0.6 omega_{t-1} + 0.4 j_turn + e_w,
    with noise std ``slow_noise`` below 0.2 m/s and ``fast_noise`` above (a floor that a
    homoscedastic GP cannot represent, so the raw ellipses are wrong by regime).
    The joystick holds piecewise-constant commands for 1-4 s.
    """
    rng = np.random.default_rng(seed)
    T = int(seconds * 5)
    joy = np.zeros((T, 2))
    t = 0
    while t < T:
        n = int(rng.integers(5, 20))
        cmd = rng.uniform(*joy_range, size=2)
        cmd[0] = abs(cmd[0]) if rng.random() < 0.7 else cmd[0] * 0.2
        joy[t:t + n] = cmd
        t += n
    vel = np.zeros((T, 2))
    for i in range(1, T):
        sd = slow_noise if abs(vel[i - 1, 0]) < 0.2 else fast_noise
        vel[i, 0] = 0.7 * vel[i - 1, 0] + 0.24 * joy[i, 0] + sd * rng.standard_normal()
        vel[i, 1] = 0.6 * vel[i - 1, 1] + 0.4 * joy[i, 1] + sd * rng.standard_normal()
    return _resampled(joy, vel)


# ------------------------------------------------------------------ calibration fit

def _synthetic_parts(n: int, rng: np.random.Generator) -> np.ndarray:
    """Random basis covariances shaped like a rollout's: [4, n, 2, 2], PSD."""
    parts = []
    for scale in (1e-3, 5e-4, 1.0, 0.5):
        A = rng.normal(size=(n, 2, 2)) * np.sqrt(scale * rng.uniform(0.2, 2.0, size=(n, 1, 1)))
        parts.append(A @ np.swapaxes(A, 1, 2))
    return np.stack(parts)


def test_calibration_recovers_a_known_noise_level_by_regime() -> None:
    rng = np.random.default_rng(1)
    theta = np.array([2.5, 0.7, 3e-4, 1e-4])
    n = 30000

    def sample(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        parts = _synthetic_parts(n, rng)
        speed = rng.uniform(0.0, 1.0, n)
        regime_true = np.where(speed < 0.3, 2.0, 1.0)  # slow: twice the variance
        cov = combine(parts, theta) * regime_true[:, None, None]
        L = np.linalg.cholesky(cov)
        err = np.einsum("nij,nj->ni", L, rng.standard_normal((n, 2)))
        return parts, err, speed

    parts, err, speed = sample(n)
    fit = fit_calibration(parts, err, speed, raw=parts[0] + parts[1])
    cal = fit.calibration
    assert fit.raw_coverage < 0.8  # the raw variance is far too small
    # fresh data: 95 % within +-2 points, overall and in every speed regime
    parts2, err2, speed2 = sample(n)
    cov2 = combine(parts2, np.array([*cal.scale, *cal.floor])) \
        * cal.factor(speed2)[:, None, None]
    assert abs(coverage(err2, cov2) - 0.95) < 0.02
    for lo, hi in ((0.0, 0.3), (0.3, 0.6), (0.6, 1.0)):
        m = (speed2 >= lo) & (speed2 < hi)
        assert abs(coverage(err2[m], cov2[m]) - 0.95) < 0.02, (lo, hi)
    # the shape is right, not only the count: scale and floor ratios recovered
    assert cal.scale[0] / cal.scale[1] == pytest.approx(theta[0] / theta[1], rel=0.3)
    # one global factor would not do: the slow regime needs a larger factor
    assert cal.speed_factors[0] > 1.5 * cal.speed_factors[-1]


def test_calibration_refuses_what_it_cannot_fit() -> None:
    rng = np.random.default_rng(0)
    parts = _synthetic_parts(100, rng)
    err = rng.normal(size=(100, 2)) * 0.01
    speed = np.ones(100)
    with pytest.raises(CalibrationError, match="at least 20"):
        fit_calibration(parts[:, :5], err[:5], speed[:5])
    bad = err.copy()
    bad[3, 0] = np.nan
    with pytest.raises(CalibrationError, match="non-finite"):
        fit_calibration(parts, bad, speed)
    with pytest.raises(CalibrationError, match="must be"):
        fit_calibration(parts, err[:50], speed)
    zero = np.zeros_like(parts)  # a covariance of 0 cannot cover a non-zero error
    with pytest.raises(CalibrationError, match="singular"):
        fit_calibration(zero, err, speed)


@pytest.mark.parametrize("bad", [
    {"scale": [1.0], "floor": [0.0, 0.0]},
    {"scale": [1.0, math.nan], "floor": [0.0, 0.0]},
    {"scale": [1.0, 1.0], "floor": [-1.0, 0.0]},
    {"scale": [1.0, 1.0], "floor": [0.0, 1e30]},
    {"scale": [1.0, 1.0], "floor": [0.0, 0.0], "speed_edges": [0.5, 0.2],
     "speed_factors": [1.0, 1.0, 1.0]},
    {"scale": [1.0, 1.0], "floor": [0.0, 0.0], "speed_edges": [0.5], "speed_factors": [1.0]},
    {"scale": [1.0, 1.0], "floor": [0.0, 0.0], "speed_factors": [0.0]},
    {"scale": [True, 1.0], "floor": [0.0, 0.0]},
    {"scale": "1 1", "floor": [0.0, 0.0]},
    {"scale": [1.0, 1.0]},
    {"scale": [1.0, 1.0], "floor": [0.0, 0.0], "extra": 1},
])
def test_calibration_values_are_checked(bad: dict[str, object]) -> None:
    with pytest.raises(CalibrationError):
        VarianceCalibration.from_dict(bad)


def test_calibration_applies_per_regime_in_rollout_and_step() -> None:
    res = synthetic_chair(60, 0)
    base = train([Series("a", res)], dataclasses.replace(PAPER_OPTIONS, inducing_v=8,
                                                         inducing_w=8, max_iter=5))
    cal = VarianceCalibration(scale=(2.0, 3.0), floor=(1e-4, 2e-4), speed_edges=(0.2,),
                              speed_factors=(4.0, 1.0))
    model = dataclasses.replace(base, calibration=cal)
    jp, vp = res.joy[10:14], res.vel[10:14].copy()
    jf = res.joy[14:19]
    for speed, f in ((0.1, 4.0), (0.5, 1.0)):
        vp[-1, 0] = speed
        _, var0 = base.predict_step(jp, vp, jf[0])
        _, var1 = model.predict_step(jp, vp, jf[0])
        np.testing.assert_allclose(var1, (var0 * [2.0, 3.0] + [1e-4, 2e-4]) * f)
        r0 = rollout(base, jp, vp, jf[None])
        r1 = rollout(model, jp, vp, jf[None])
        np.testing.assert_allclose(r1.pose, r0.pose)  # the mean is untouched
        np.testing.assert_allclose(r1.vel_cov[0, 0], np.diag(var1), rtol=1e-12)
    # the basis calibrations decompose the propagated covariance exactly
    parts = [rollout(dataclasses.replace(base, calibration=b), jp, vp, jf[None]).pos_cov
             for b in BASIS]
    theta = np.array([*cal.scale, *cal.floor])
    np.testing.assert_allclose(combine(np.stack(parts), theta) * cal.factor(0.5),
                               rollout(model, jp, vp, jf[None]).pos_cov, rtol=1e-10)


# ------------------------------------------------------------------ the whole procedure

SMALL = {"inducing_v": 10, "inducing_w": 10, "max_iter": 30, "budget_s": 2.0}


@pytest.fixture(scope="module")
def chair() -> list[Series]:
    return [Series(f"drive_{i}", synthetic_chair(600, i)) for i in range(3)]


@pytest.fixture(scope="module")
def auto_model(chair: list[Series]):  # type: ignore[no-untyped-def]
    return train_auto(chair, AutoOptions(seed=3, **SMALL))  # type: ignore[arg-type]


def test_selection_is_deterministic_for_a_seed(chair: list[Series], auto_model) -> None:  # type: ignore[no-untyped-def]
    again = train_auto(chair, AutoOptions(seed=3, **SMALL))  # type: ignore[arg-type]
    strip = [{k: v for k, v in row.items() if k != "seconds"}
             for row in auto_model.meta["selection"]["candidates"]]
    assert strip == [{k: v for k, v in row.items() if k != "seconds"}
                     for row in again.meta["selection"]["candidates"]]
    assert again.meta["selection"]["chosen"] == auto_model.meta["selection"]["chosen"]
    assert again.calibration == auto_model.calibration
    for a, b in zip(auto_model.channels, again.channels, strict=True):
        np.testing.assert_array_equal(a.get_state()["alpha"], b.get_state()["alpha"])
    # every structure was tried, and the best held-out score won
    rows = [r for r in auto_model.meta["selection"]["candidates"] if "score" in r]
    assert {(r["candidate"]["lags"], r["candidate"]["coupled"]) for r in rows} >= {
        (s, c) for s in (2, 4, 6, 8, 10, 12) for c in (False, True)}
    best = max(rows, key=lambda r: (r["score"], -r["mean_median_error_m"]))
    assert best["candidate"] == auto_model.meta["selection"]["chosen"]


def test_the_recordings_order_changes_nothing_fitted(chair: list[Series], auto_model) -> None:  # type: ignore[no-untyped-def]
    """The same recordings in another order chose another configuration (s = 6 against
    s = 4: the rows were stacked and subsampled in the order given). The model is the same
    now, to the bit; the training data's summary keeps the order given."""
    again = train_auto(chair[::-1], AutoOptions(seed=3, **SMALL))  # type: ignore[arg-type]
    strip = [{k: v for k, v in row.items() if k != "seconds"}
             for row in auto_model.meta["selection"]["candidates"]]
    assert strip == [{k: v for k, v in row.items() if k != "seconds"}
                     for row in again.meta["selection"]["candidates"]]
    assert again.calibration == auto_model.calibration
    for a, b in zip(auto_model.channels, again.channels, strict=True):
        np.testing.assert_array_equal(a.get_state()["alpha"], b.get_state()["alpha"])
    assert again.meta["training_data"]["bags"] == [s.name for s in chair[::-1]]
    quick = dataclasses.replace(PAPER_OPTIONS, max_iter=20)
    paper = [train(order, quick) for order in (chair, chair[::-1])]
    for a, b in zip(paper[0].channels, paper[1].channels, strict=True):
        np.testing.assert_array_equal(a.get_state()["alpha"], b.get_state()["alpha"])


def test_the_final_fit_starts_from_the_chosen_candidates_selection_fit(
        chair: list[Series], monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[int, int, int, SparseGP | None, SparseGP]] = []
    real_fit = SparseGP.fit

    def spy(self, X, y, max_iter=200, max_fun=None, callback=None, start=None):  # type: ignore[no-untyped-def]
        out = real_fit(self, X, y, max_iter, max_fun, callback, start)
        calls.append((self.num_inducing, X.shape[1], X.shape[0], start, out))
        return out

    monkeypatch.setattr(SparseGP, "fit", spy)
    opts = AutoOptions(seed=3, **SMALL)  # type: ignore[arg-type]
    model = train_auto(chair, opts)
    chosen = model.meta["selection"]["chosen"]
    D = FeatureConfig(lags=chosen["lags"], coupled=chosen["coupled"]).input_dim
    warm = [c for c in calls if c[3] is not None]
    # only the final fits start warm: one per channel, on the final rows
    assert [(M, d, n) for M, d, n, _, _ in warm] == [
        (chosen["inducing"][c], D, opts.final_rows) for c in (0, 1)]
    # each from its channel's fit of the chosen candidate in the selection
    selection = [c for c in calls if c[3] is None and c[:3] == (chosen["inducing"][0], D,
                                                                opts.selection_rows)]
    assert len(selection) == 2
    for (_, _, _, start, _), (_, _, _, _, fitted) in zip(warm, selection, strict=True):
        assert start is not None
        np.testing.assert_allclose(start.inducing_inputs, fitted.inducing_inputs,
                                   rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(start.lengthscales, fitted.lengthscales, rtol=1e-12)
    assert model.meta["selection"]["final_fit_start"] == "the chosen candidate's selection fit"


def test_calibrated_coverage_on_fresh_data_of_known_noise(auto_model) -> None:  # type: ignore[no-untyped-def]
    test = [TestSeries(f"fresh_{i}", synthetic_chair(600, 100 + i)) for i in range(2)]
    calibrated = evaluate_model(auto_model, test, (1.0, 1.4, 2.0), case_lags=12)
    raw = evaluate_model(dataclasses.replace(auto_model, calibration=VarianceCalibration()),
                         test, (1.0, 1.4, 2.0), case_lags=12)
    for h, ev in calibrated.horizons.items():
        assert abs(ev.vo.coverage_95 - 0.95) <= 0.02, (h, ev.vo.coverage_95)
        assert ev.vo.success_rate == raw.horizons[h].vo.success_rate  # mean untouched
    assert auto_model.meta["calibration"]["cross_validated"]


def test_too_few_held_out_cases_leave_the_model_uncalibrated() -> None:
    # 9 held-out cases of a chair at rest once gave a scale of 1e-5: the ellipses vanished
    from asgp_ros.learning.training import MIN_CALIBRATION_CASES

    short = [Series("short", synthetic_chair(200, 7))]  # 200 s: 40 s held out, 200 steps
    model = train_auto(short, AutoOptions(seed=3, **SMALL))  # type: ignore[arg-type]
    cal = model.meta["calibration"]
    assert not cal["fitted"] and model.calibration.is_identity
    assert f"fewer than the {MIN_CALIBRATION_CASES} a calibration needs" in cal["reason"]


def test_a_held_out_part_of_a_parked_chair_does_not_calibrate(auto_model) -> None:  # type: ignore[no-untyped-def]
    """A recorder left running after the chair was parked: the held-out end of the
    recording is hundreds of cases of a chair at rest. Fitted on them the map shrank the
    v variance 600,000-fold (cross-validation cannot see it: both halves at rest), and on
    driving the ellipses held 1-2 % of the positions. Cases in which the chair moves less
    than the success distance do not count towards the calibration's minimum."""
    from asgp_ros.core.calibration import CalibrationError
    from asgp_ros.learning.training import MIN_CALIBRATION_CASES, calibrate

    T = 2000  # 400 s at rest
    rng = np.random.default_rng(5)
    parked = _resampled(np.zeros((T, 2)), 1e-4 * rng.standard_normal((T, 2)))
    opts = AutoOptions(seed=3, **SMALL)  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match=f"0 of the .* held-out cases move the chair "
                                               f"10 cm or more, fewer than the "
                                               f"{MIN_CALIBRATION_CASES}"):
        calibrate(auto_model, [Series("parked", parked)], opts, auto_model.lags)
    # driving again after it: enough cases move, the calibration is fitted, and on the
    # cases that move alone: ten minutes parked among thirty of driving took the slow
    # regime's factor from 1.16 to 0.65 (its ellipses then held 84 % on other drives)
    drive = synthetic_chair(600, 11)
    cal, report = calibrate(auto_model, [Series("drive", drive), Series("parked", parked)],
                            opts, auto_model.lags)
    assert report["fitted"] and report["cases"] > MIN_CALIBRATION_CASES
    alone, _ = calibrate(auto_model, [Series("drive", drive)], opts, auto_model.lags)
    assert not alone.is_identity and cal == alone
    assert report["still_cases"] > 300
    # an undeadzoned stick reads a few thousandths at rest (one ADC count: 1/205): parked
    # too (under a rule of the exact neutral the slow factor became 0.002, applied)
    counted = _resampled(rng.choice([-1.0, 0.0, 1.0], size=(T, 2)) / 205.0,
                         1e-4 * rng.standard_normal((T, 2)))
    again, _ = calibrate(auto_model, [Series("drive", drive), Series("parked", counted)],
                         opts, auto_model.lags)
    assert again == alone
    # a chair driven slowly (the stick held off neutral, 3 cm/s) is no parked chair
    creeping = _resampled(np.tile([0.04, 0.0], (T, 1)),
                          np.tile([0.03, 0.0], (T, 1)) + 1e-3 * rng.standard_normal((T, 2)))
    _, report = calibrate(auto_model, [Series("drive", drive), Series("creep", creeping)],
                          opts, auto_model.lags)
    assert report["still_cases"] == 0


def test_a_held_out_part_of_a_parked_chair_chooses_nothing() -> None:
    """The recorder left running after the chair was parked: the held-out end of the
    recording is the chair at rest, every candidate scored 100 %, and the median-error
    tie-break chose the paper's configuration, which drove far worse; training said
    'held-out mean success 100.0%'. Too few held-out cases move the chair: the paper's
    configuration, uncalibrated, and the reason said."""
    from asgp_ros.learning.training import MIN_SELECTION_MOVING_CASES

    drive = synthetic_chair(480, 4)
    T = drive.t.shape[0] + 600  # then 120 s parked: the held-out 20 % all at rest
    joy = np.zeros((T, 2))
    vel = np.zeros((T, 2))
    joy[:drive.t.shape[0]], vel[:drive.t.shape[0]] = drive.joy, drive.vel
    vel[drive.t.shape[0]:] = 1e-4 * np.random.default_rng(1).standard_normal((600, 2))
    said: list[str] = []
    model = train_auto([Series("parked", _resampled(joy, vel))],
                       AutoOptions(seed=3, **SMALL),  # type: ignore[arg-type]
                       progress=lambda ch, msg: said.append(msg))
    assert model.meta["training"]["configuration"] == "fallback"
    assert model.calibration.is_identity
    why = model.meta["selection"]["fallback"]
    assert f"fewer than the {MIN_SELECTION_MOVING_CASES} that tell the candidates apart" \
        in why, why
    assert any("tell the candidates apart" in m for m in said)


@pytest.mark.parametrize(("scale", "said"), [
    (1e6, "beyond the physical limits squared"),
    (1e-9, "its variance calibration shrinks the predicted variance")])
def test_a_calibration_that_makes_the_model_refused_is_not_applied(
        chair: list[Series], monkeypatch: pytest.MonkeyPatch, tmp_path, scale: float,
        said: str) -> None:
    """On very noisy odometry the fitted map (its omega scale 28) made the model predict
    variances beyond a wheelchair's: `asgp train` wrote, and said it wrote, a file that
    every command then refused. The map is not applied (said), and save_model never writes
    a model that load_model refuses. The same for a map that claims a certainty the model
    does not have (MAX_CALIBRATION_SHRINK)."""
    from asgp_ros.core.modelfile import ModelFileError, load_model, save_model
    from asgp_ros.learning import training

    huge = VarianceCalibration(scale=(scale, scale))
    real = training.calibrate

    def calibrate(*args, **kwargs):  # type: ignore[no-untyped-def]
        _, meta = real(*args, **kwargs)
        return huge, {**meta, "applied": True}

    monkeypatch.setattr(training, "calibrate", calibrate)
    model = train_auto(chair[:1], AutoOptions(seed=3, **SMALL))  # type: ignore[arg-type]
    assert model.calibration.is_identity
    cal = model.meta["calibration"]
    assert not cal["applied"] and cal["reason"].startswith(
        "not applied: a model file with it is refused (") and said in cal["reason"]
    save_model(tmp_path / "m.npz", model)
    load_model(tmp_path / "m.npz")
    bad = dataclasses.replace(model, calibration=huge)
    with pytest.raises(ModelFileError, match="not a wheelchair's model"):
        save_model(tmp_path / "bad.npz", bad)
    assert not (tmp_path / "bad.npz").exists()


def test_the_leading_structures_are_scored_again_at_the_largest_m(
        chair: list[Series], monkeypatch: pytest.MonkeyPatch) -> None:
    # a held-out landscape where a short past wins at M = 40 by a hair, and a longer past
    # wins clearly once there are pseudo-inputs to use it
    from asgp_ros.learning import training

    def fake_fit(cand, *args, **kwargs):  # type: ignore[no-untyped-def]
        return cand, {}

    def fake_score(cand, held, opts, case_lags):  # type: ignore[no-untyped-def]
        s, m = cand.lags, cand.inducing[0]
        score = 0.80 + (0.01 if cand.coupled else 0.0) + (0.001 if s == 2 else 1e-5 * s)
        score += 0.0002 * s * (m - 40) / 40 + 0.0001 * (m - 40) / 40
        return {"score": score, "mean_median_error_m": 0.05, "horizons": {}}

    monkeypatch.setattr(training, "_fit_candidate", fake_fit)
    monkeypatch.setattr(training, "_score", fake_score)
    opts = AutoOptions(seed=0, budget_s=180.0)
    search = training._Search(chair, chair, opts, None, lambda *a: None, 12)
    chosen = search.run(training._structures(opts))
    largest = opts.affordable_inducing()[-1]
    assert largest > training.AUTO_STRUCTURE_INDUCING
    by_stage: dict[str, list[dict[str, object]]] = {}
    for row in search.table:
        by_stage.setdefault(row["stage"], []).append(row["candidate"])
    # the capacity stage grows the structure stage's winner (s = 2) ...
    assert {c["lags"] for c in by_stage["capacity"]} == {2}
    # ... and its runners-up (s = 12 and 10, coupled) are scored at the largest M
    assert [(c["lags"], c["coupled"], c["inducing"]) for c in by_stage["refine"]] == [
        (12, True, [largest, largest]), (10, True, [largest, largest])]
    assert chosen == training.Candidate(12, True, (largest, largest))
    # pinned pseudo-inputs: no capacity stage, and nothing to score again
    pinned = training._Search(chair, chair, AutoOptions(seed=0, inducing_v=40, inducing_w=40),
                              None, lambda *a: None, 12)
    pinned.run(training._structures(pinned.opts))
    assert {row["stage"] for row in pinned.table} == {"structure"}


def test_held_out_rows_never_reach_a_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    # the held-out ends drive with |joystick| >= 2; the training parts within 1
    series = []
    for i in range(2):
        a = synthetic_chair(480, 10 + i)
        b = synthetic_chair(120, 20 + i, joy_range=(2.0, 2.5))
        series.append(Series(f"d{i}", _resampled(np.concatenate([a.joy, b.joy]),
                                                 np.concatenate([a.vel, b.vel]))))
    lay = input_layout(0, FeatureConfig(lags=2, coupled=True))
    joy_cols = np.concatenate([lay.joy_past.ravel(), lay.joy_now])

    def joy_max(X: np.ndarray) -> float:
        return float(np.max(np.abs(np.asarray(X)[:, joy_cols])))

    calls: list[tuple[str, float]] = []
    fit, from_params = SparseGP.fit, SparseGP.from_params.__func__  # type: ignore[attr-defined]

    def spy_fit(self, X, y, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(("fit", joy_max(X)))
        return fit(self, X, y, *args, **kwargs)

    def spy_post(cls, X, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(("posterior", joy_max(X)))
        return from_params(cls, X, *args, **kwargs)

    monkeypatch.setattr(SparseGP, "fit", spy_fit)
    monkeypatch.setattr(SparseGP, "from_params", classmethod(spy_post))
    train_auto(series, AutoOptions(lags=2, coupled=True, **SMALL))  # type: ignore[arg-type]
    train_part, held = split_holdout(series, 0.2)
    assert all(np.max(np.abs(p.res.joy)) <= 1.0 for p in train_part)
    assert all(np.min(np.abs(h.res.joy).max(axis=1)) >= 2.0 for h in held)
    # the last two posteriors are the shipped model's, on all the data; before them,
    # nothing with a joystick beyond 1 was ever fitted or conditioned on
    *selection, ship_v, ship_w = calls
    assert all(value <= 1.0 + 1e-9 for _, value in selection), selection
    assert ship_v[0] == ship_w[0] == "posterior" and ship_v[1] >= 2.0


def test_model_file_round_trips_configuration_and_calibration(auto_model, tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "m.npz"
    save_model(path, auto_model)
    back = load_model(path)
    assert back.calibration == auto_model.calibration
    assert back.feature_config == auto_model.feature_config
    assert back.meta["selection"] == auto_model.meta["selection"]
    assert back.meta["calibration"] == auto_model.meta["calibration"]
    s = back.lags
    jp, vp = np.zeros((s, 2)), np.full((s, 2), 0.05)
    np.testing.assert_allclose(back.predict_step(jp, vp, np.zeros(2))[1],
                               auto_model.predict_step(jp, vp, np.zeros(2))[1])


def test_a_hostile_calibration_in_a_model_file_is_refused(auto_model, tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "m.npz"
    save_model(path, auto_model)
    with zipfile.ZipFile(path) as zf:
        members = {n: zf.read(n) for n in zf.namelist()}
    meta_npy = members["__meta__.npy"]
    # rewrite the JSON inside the 0-d unicode array, keeping its length
    arr = np.lib.format.read_array(io.BytesIO(meta_npy))
    meta = json.loads(str(arr))
    meta["calibration"]["floor"] = [0.0, -1.0]
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.array(json.dumps(meta)))
    members["__meta__.npy"] = buf.getvalue()
    with zipfile.ZipFile(path, "w") as zf:
        for n, data in members.items():
            zf.writestr(n, data)
    with pytest.raises(ModelFileError, match="calibration floor"):
        load_model(path)


def test_paper_flag_is_exactly_the_paper(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    bag = tmp_path / "bag"
    assert main(["simulate", "--surface", "tile", "--minutes", "1.5", "--seed", "0",
                 "--out", str(bag)]) == 0
    model = tmp_path / "paper.npz"
    assert main(["train", "--paper", str(bag), "--out", str(model), "--max-iter", "5"]) == 0
    m = load_model(model)
    assert (m.feature_config.lags, m.feature_config.coupled) == (4, False)
    assert [ch.num_inducing for ch in m.channels] == [20, 40]
    assert m.calibration.is_identity and "selection" not in m.meta
    # the same as the library's paper configuration
    series = read_series([str(bag)])
    ref = train(series, dataclasses.replace(PAPER_OPTIONS, max_iter=5))
    for a, b in zip(m.channels, ref.channels, strict=True):
        np.testing.assert_array_equal(a.get_state()["alpha"], b.get_state()["alpha"])
    capsys.readouterr()
    for extra in (["--lags", "6"], ["--coupled"], ["--model", "mlp"], ["--inducing-v", "8"]):
        assert main(["train", "--paper", *extra, str(bag), "--out",
                     str(tmp_path / "x.npz")]) == 2
        assert "--paper" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_the_online_predictor_publishes_calibrated_covariances(auto_model) -> None:  # type: ignore[no-untyped-def]
    from asgp_ros.core.online import Predictor, PredictorConfig

    res = synthetic_chair(30, 7)
    raw_model = dataclasses.replace(auto_model, calibration=VarianceCalibration())
    out = []
    for model in (auto_model, raw_model):
        pred = Predictor(model, PredictorConfig(horizon_steps=5))
        for t, joy, vel in zip(res.t, res.joy, res.vel, strict=True):
            pred.feed_joy(float(t), joy)
            pred.feed_vo(float(t), vel)
        p = pred.predict(float(res.t[-1]))
        assert p.ok, p.detail
        out.append(p)
    cal, raw = out
    np.testing.assert_allclose(cal.pose, raw.pose)
    expected = auto_model.calibration.apply(np.diagonal(raw.vel_cov[0]), raw.vel_past[-1, 0])
    np.testing.assert_allclose(np.diagonal(cal.vel_cov[0]), expected, rtol=1e-10)


def test_asgp_info_shows_the_configuration_and_refuses_what_is_no_model(
        auto_model, tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "m.npz"
    save_model(path, auto_model)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    chosen = auto_model.meta["selection"]["chosen"]
    assert f"s = {chosen['lags']}" in out and "<- chosen" in out
    assert "held-out coverage of the 95% ellipse" in out and "drive_0" in out
    assert main(["info", "--json", str(path)]) == 0
    meta = json.loads(capsys.readouterr().out)
    assert meta["calibration"] == auto_model.calibration.to_dict()
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for bad in (tmp_path, fifo, tmp_path / "missing.npz"):
        assert main(["info", str(bad)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(bad) in err


def test_asgp_train_says_the_cross_validated_coverage(auto_model, tmp_path, capsys,
                                                     monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """`asgp train` said 'coverage 89.2% raw -> 95.0%' after every calibration: the pooled
    figure on the cases the map was fitted to, 95.0 % by construction. It gives the
    cross-validated figures per horizon, as asgp info does."""
    from asgp_ros.cli import train as train_cli

    bag = tmp_path / "bag"
    assert main(["simulate", "--minutes", "0.3", "--seed", "2", "--out", str(bag)]) == 0
    monkeypatch.setattr(train_cli, "train_auto", lambda *a, **k: auto_model)
    assert main(["train", str(bag), "--out", str(tmp_path / "m.npz")]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("calibrated"))
    cal = auto_model.meta["calibration"]
    assert "(cross-validated): 1.0 s " in line
    for h in ("1.0", "1.4", "2.0"):
        c = cal["by_horizon"][h]
        assert f"{h} s {100 * c['raw']:.1f}% -> {100 * c['calibrated']:.1f}%" in line
    assert f"-> {100 * cal['coverage']:.1f}% (asgp" not in line


def test_asgp_info_names_the_calibrations_speed_regimes(auto_model) -> None:  # type: ignore[no-untyped-def]
    """Each speed regime's factor with the speeds that split them; a calibration fitted on
    too few held-out cases to split has one factor, and says so."""
    import dataclasses

    from asgp_ros.cli.info import _calibration_lines

    cal = auto_model.calibration
    head = _calibration_lines(auto_model)[0]
    assert len(cal.speed_edges) == 2  # the fixture's held-out part splits into thirds
    assert "speed regimes " + ", ".join(f"{f:.3g}" for f in cal.speed_factors) in head
    assert "split at |v| = " + ", ".join(f"{e:.3g}" for e in cal.speed_edges) in head
    one = dataclasses.replace(auto_model, calibration=dataclasses.replace(
        cal, speed_edges=(), speed_factors=(1.25,)))
    head = _calibration_lines(one)[0]
    assert "one speed regime" in head and "factor 1.25" in head and "split at" not in head


def test_the_coverage_is_reported_per_speed_regime_and_steadiness_together(auto_model) -> None:  # type: ignore[no-untyped-def]
    """Slow steady driving can be over-confident where slow driving as a whole is not: the
    report crosses the speed regimes with the joystick's steadiness, and asgp info shows it."""
    from asgp_ros.cli.info import coverage_lines

    cal = auto_model.meta["calibration"]
    cross, speed = cal["by_speed_and_steadiness"], cal["by_speed"]
    assert list(cross) == [f"{r}, {g}" for r in speed for g in ("steady", "changing")]
    for regime, t in speed.items():
        assert cross[f"{regime}, steady"]["cases"] + cross[f"{regime}, changing"]["cases"] == \
            t["cases"]
    steady = sum(cross[f"{r}, steady"]["cases"] for r in speed)
    assert steady == cal["by_steadiness"]["steady joystick"]["cases"]
    lines = coverage_lines(cal)
    assert sum(", steady" in ln or ", changing" in ln for ln in lines) == 2 * len(speed)


def test_a_pinned_m_gets_the_rows_it_needs_whatever_the_budget() -> None:
    """--inducing-v 600 --budget-s 10 sized the selection subset at 1,000 rows by the budget:
    every candidate was skipped ('1000 rows are too few for M = 600') and the model fell
    back to the paper's, uncalibrated, saying 'too little held-out data'."""
    opts = AutoOptions(budget_s=10.0, inducing_v=600, inducing_w=600)
    assert opts.selection_rows >= 2 * 600
    assert AutoOptions(budget_s=10.0).selection_rows == training.MIN_SELECTION_ROWS


def test_a_budget_overrun_is_said(chair: list[Series], monkeypatch: pytest.MonkeyPatch) -> None:
    """--budget-s 1 ran for 9 s, the plan's floors kept, and nothing said so. (A clock that
    moves a second at each reading makes the overrun certain, whatever the machine.)"""
    ticks = iter(range(10**6))
    monkeypatch.setattr(training.time, "perf_counter", lambda: float(next(ticks)))
    said: list[str] = []
    model = train_auto(chair, AutoOptions(seed=3, **{**SMALL, "budget_s": 1.0}),  # type: ignore[arg-type]
                       progress=lambda channel, message: said.append(message))
    total = model.meta["selection"]["seconds"]["total"]
    assert total > 1.0
    assert any(m.startswith(f"took {total:.1f} s, more than the 1 s planned") for m in said), said
