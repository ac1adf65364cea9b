"""Tests of the ROS-free online Predictor (asgp_ros.core.online).

The reference for "online equals offline" is the offline pipeline on the whole recording:
``resample`` of all samples, ``design_matrix`` rows and ``rollout`` on the offline
windows. The online predictor is fed the same samples one by one in arrival order and asked
for a prediction whenever a new grid step completes, as the node does.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import itertools
import math
from dataclasses import dataclass

import numpy as np
import pytest

from asgp_ros.core import online
from asgp_ros.core.features import FeatureConfig, build_inputs, design_matrix
from asgp_ros.core.metrics import CHI2_2DOF_95
from asgp_ros.core.models import MotionModel
from asgp_ros.core.online import (
    Predictor,
    PredictorConfig,
    Reason,
    RejectedInputError,
    confidence_ellipses,
    to_frame,
)
from asgp_ros.core.resample import ResampleConfig, resample
from asgp_ros.core.rollout import rollout
from asgp_ros.core.streams import RawStreams

LAGS = 4


@dataclass
class LinearChannel:
    """A deterministic linear channel model: mean = X w + b, constant variance."""

    w: np.ndarray
    b: float = 0.0
    var: float = 1e-3

    def predict(self, X, include_noise=True):
        X = np.asarray(X, dtype=float)
        return X @ self.w + self.b, np.full(X.shape[0], self.var)

    def predict_with_grad(self, X, include_noise=True):
        mean, var = self.predict(X, include_noise)
        return mean, var, np.broadcast_to(self.w, X.shape).copy()


def linear_model(lags: int = LAGS) -> MotionModel:
    """V_t = 0.6 V_{t-1} + 0.35 j_t + 0.05 j_{t-1} per channel (paper's uncoupled layout)."""
    D = 2 * lags + 1
    w = np.zeros(D)
    w[lags - 1] = 0.05  # j_{t-1}
    w[2 * lags - 1] = 0.6  # V_{t-1}
    w[2 * lags] = 0.35  # j_t
    return MotionModel(kind="linear_test", feature_config=FeatureConfig(lags=lags),
                       resample_config=ResampleConfig(rate_hz=5.0),
                       channels=(LinearChannel(w), LinearChannel(0.8 * w, var=2e-3)))


def make_streams(duration: float = 40.0, seed: int = 0, t_start: float = 1000.0):
    """Joystick at ~30 Hz and VO at a jittery 4-7 Hz (as in the paper), velocity lagging.

    Returns (joy_t [Nj], joy [Nj, 2], vel_t [Nv], vel [Nv, 2]).
    """
    rng = np.random.default_rng(seed)
    jt = t_start + np.cumsum(rng.uniform(0.028, 0.039, size=int(duration * 40)))
    jt = jt[jt < t_start + duration]
    vt = t_start + 0.05 + np.cumsum(rng.uniform(1 / 7, 1 / 4, size=int(duration * 8)))
    vt = vt[vt < t_start + duration]

    def fwd(t):
        return 0.6 * np.sin(0.5 * (t - t_start)) + 0.25 * np.sin(1.7 * (t - t_start) + 1.0)

    def turn(t):
        return 0.5 * np.sin(0.3 * (t - t_start) + 2.0)

    joy = np.stack([fwd(jt), turn(jt)], axis=1)
    vel = np.stack([0.9 * fwd(vt - 0.3), 0.7 * turn(vt - 0.3)], axis=1)
    vel += rng.normal(0.0, 0.01, size=vel.shape)
    return jt, joy, vt, vel


def arrival_order(jt, joy, vt, vel):
    """Events (t, kind, values) merged by time, as a node would receive them."""
    events = [(t, "joy", x) for t, x in zip(jt, joy, strict=True)]
    events += [(t, "vo", x) for t, x in zip(vt, vel, strict=True)]
    events.sort(key=lambda e: e[0])
    return events


def feed(pred: Predictor, event) -> None:
    t, kind, x = event
    if kind == "joy":
        pred.feed_joy(t, x)
    else:
        pred.feed_vo(t, x)


def run_online(pred: Predictor, events, joy_future_of=None, skipped=None):
    """Feed events; predict on every newly completed step. Returns {step: Prediction}.

    ``skipped`` (a set) collects the steps completed together with a newer one by one
    arrival (only the newest complete step is predicted)."""
    out = {}
    last = None
    for ev in events:
        feed(pred, ev)
        step = pred.ready_step()
        if step is None or (last is not None and step <= last):
            continue
        if skipped is not None and last is not None:
            skipped.update(range(last + 1, step))
        last = step
        fut = None if joy_future_of is None else joy_future_of(step)
        result = pred.predict(ev[0], joy_future=fut)
        if result.ok:
            out[result.step] = result
    return out


@pytest.fixture(scope="module")
def data():
    jt, joy, vt, vel = make_streams()
    res = resample(RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel), ResampleConfig())
    return jt, joy, vt, vel, res


def test_online_features_equal_offline_features(data):
    jt, joy, vt, vel, res = data
    model = linear_model()
    pred = Predictor(model, PredictorConfig(horizon_steps=3, buffer_s=5.0))
    skipped: set[int] = set()
    results = run_online(pred, arrival_order(jt, joy, vt, vel), skipped=skipped)
    pos = {int(k): i for i, k in enumerate(res.k)}
    fcfg = model.feature_config
    offline = {c: design_matrix(res, c, fcfg) for c in (0, 1)}
    compared = 0
    for step, r in results.items():
        i = pos[step]
        # the measured window is bit-identical to the offline resampling
        np.testing.assert_array_equal(r.joy_past, res.joy[i - LAGS + 1:i + 1])
        np.testing.assert_array_equal(r.vel_past, res.vel[i - LAGS + 1:i + 1])
        for c in (0, 1):
            X, _, index = offline[c]
            rows = np.flatnonzero(index == i + 1)
            if rows.size == 0:
                continue
            online_row = build_inputs(r.joy_past, r.vel_past, res.joy[i + 1], c, fcfg)
            np.testing.assert_array_equal(online_row, X[rows[0]])
            compared += 1
    # every step whose window is valid offline was predicted online, unless one VO sample
    # completed it together with the next (its interval's middle passed two grid points)
    valid_offline = set(int(res.k[j]) for j in offline[0][2] - 1)
    assert compared > 300
    missed = valid_offline - set(results) - skipped
    assert len(missed) <= 2, sorted(missed)[:10]
    assert len(skipped) < 0.1 * len(results)


def test_prediction_equals_core_rollout_on_offline_windows(data):
    jt, joy, vt, vel, res = data
    model = linear_model()
    k = 6
    pos = {int(kk): i for i, kk in enumerate(res.k)}

    def recorded_future(step):
        i = pos.get(step, -1)
        fut = res.joy[i + 1:i + 1 + k] if i >= 0 else np.zeros((0, 2))
        return fut if fut.shape[0] == k else np.zeros((k, 2))

    pred = Predictor(model, PredictorConfig(horizon_steps=k))
    results = run_online(pred, arrival_order(jt, joy, vt, vel), recorded_future)
    assert len(results) > 150
    for step, r in list(results.items())[::7]:
        i = pos[step]
        ref = rollout(model, res.joy[i - LAGS + 1:i + 1], res.vel[i - LAGS + 1:i + 1],
                      recorded_future(step)[None])
        np.testing.assert_allclose(r.pose, ref.pose[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(r.pos_cov, ref.pos_cov[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(r.vel, ref.vel[0], rtol=0, atol=1e-12)
        assert r.t0 == pytest.approx(step * 0.2)
        np.testing.assert_allclose(r.times, r.t0 + 0.2 * np.arange(1, k + 1))
        assert r.pose.shape == (k, 3) and r.ellipses.shape == (k, 3)


def test_without_plan_the_newest_joystick_command_is_held(data):
    jt, joy, vt, vel, _ = data
    pred = Predictor(linear_model(), PredictorConfig(horizon_steps=5))
    events = [e for e in arrival_order(jt, joy, vt, vel) if e[0] < 1010.0]
    for ev in events:
        feed(pred, ev)
    r = pred.predict(events[-1][0])
    assert r.ok and not r.from_plan
    newest = joy[np.flatnonzero(jt < 1010.0)[-1]]
    np.testing.assert_array_equal(r.joy_future, np.repeat(newest[None], 5, axis=0))


def _fed(until: float, **cfg):
    jt, joy, vt, vel = make_streams(duration=until - 1000.0)
    pred = Predictor(linear_model(), PredictorConfig(**cfg))
    for ev in arrival_order(jt, joy, vt, vel):
        feed(pred, ev)
    return pred, (jt, joy, vt, vel)


def test_stale_vo_stops_prediction_then_it_resumes():
    pred, (jt, _, vt, _) = _fed(1015.0, vo_timeout_s=0.5, joy_timeout_s=0.5)
    now = max(jt[-1], vt[-1])
    assert pred.predict(now).ok
    # joystick continues for 1 s, VO is silent
    for i, t in enumerate(np.arange(now + 0.033, now + 1.0, 0.033)):
        pred.feed_joy(t, (0.3, 0.0 + 0.001 * i))
    r = pred.predict(now + 1.0)
    assert not r.ok and r.reason == Reason.STALE_VO and "VO is" in r.detail
    assert pred.status(now + 1.0).reason == Reason.STALE_VO
    # VO resumes: enough fresh samples to make a valid window again
    times = now + 1.0 + 0.033 * np.arange(1, 61)
    for i, t in enumerate(times):
        pred.feed_joy(t, (0.3, 0.0))
        if i % 6 == 0:
            pred.feed_vo(t + 0.01, (0.2 + 0.05 * math.sin(t), 0.01 * math.cos(t)))
    t = times[-1]
    pred.feed_vo(t + 0.01, (0.21, 0.0))
    pred.feed_joy(t + 0.02, (0.3, 0.0))
    r = pred.predict(t + 0.03)
    assert r.ok, r.detail
    assert r.t0 > now + 2.0


def test_the_joystick_is_behind_only_for_a_step_the_caller_predicts():
    """``joystick_behind(n)``: the VO covers a newer grid step than the joystick, one whose
    index is a multiple of n (a node predicting every n-th step waits for no other)."""
    pred = Predictor(linear_model(), PredictorConfig())
    assert not pred.joystick_behind()  # no samples
    dt = pred.dt
    pred.feed_joy(1000.0 * dt, (0.3, 0.0))  # step 1000
    assert not pred.joystick_behind()  # no VO
    for t in (999.0, 999.5, 1000.0):
        pred.feed_vo(t * dt, (0.2, 0.0))
    # midpoint stamps: the VO covers 999.75 dt, behind the joystick
    assert not pred.joystick_behind()
    pred.feed_vo(1002.2 * dt, (0.2, 0.0))  # covers 1001.1 dt: step 1001 waits
    assert pred.joystick_behind() and pred.joystick_behind(1)
    assert not pred.joystick_behind(2)  # step 1001 is odd, 1000 is the joystick's
    assert pred.joystick_behind(7)  # 1001 = 7 x 143
    pred.feed_vo(1004.2 * dt, (0.2, 0.0))  # covers 1003.2 dt: steps 1001-1003 wait
    assert pred.joystick_behind(2) and not pred.joystick_behind(4)
    pred.feed_joy(1003.5 * dt, (0.3, 0.0))  # the joystick covers step 1003
    assert not pred.joystick_behind() and not pred.joystick_behind(2)
    with pytest.raises(ValueError, match="every_n"):
        pred.joystick_behind(0)


def test_stale_joystick_stops_prediction():
    pred, (jt, _, vt, _) = _fed(1010.0, joy_timeout_s=0.3)
    now = max(jt[-1], vt[-1])
    pred.feed_vo(now + 0.2, (0.1, 0.0))
    pred.feed_vo(now + 0.4, (0.1, 0.0))
    r = pred.predict(now + 0.45)
    assert not r.ok and r.reason == Reason.STALE_JOYSTICK


def _ok_after_silence(silent: str, lead: float, with_now: bool = True) -> float:
    """Joystick at 20 Hz and VO at 5 Hz, fed with the clock at arrival (or without it,
    ``with_now`` False: ``predict(now)`` alone knows the clock), the stamps of the
    ``silent`` stream ``lead`` s ahead of it; that stream falls silent at 110 s on the clock
    (the other goes on): how long predictions stayed ok after its last arrival."""
    pred = Predictor(linear_model(), PredictorConfig(horizon_steps=5))  # timeouts 0.5 s
    last_ok = 110.0
    for i in range(1, 300):
        now = 100.0 + 0.05 * i
        joy_lead, vo_lead = (lead, 0.0) if silent == "joy" else (0.0, lead)
        if not (silent == "joy" and now > 110.0):
            assert pred.feed_joy(now + joy_lead, (0.5 + 0.3 * math.sin(now), 0.1),
                                 now=now if with_now else None)
        if i % 4 == 1 and not (silent == "vo" and now > 110.0):
            assert pred.feed_vo(now + vo_lead, (0.4 + 0.2 * math.sin(now - 0.3), 0.05),
                                now=now if with_now else None)
        if pred.predict(now).ok and now > 110.0:  # a planner's cycle, every 50 ms
            last_ok = now
    return last_ok - 110.0


@pytest.mark.parametrize("silent", ["joy", "vo"])
def test_a_stream_stamped_ahead_of_the_clock_is_stale_a_timeout_after_it_fell_silent(silent):
    """An unsynchronised sender's stamps 0.9 s ahead of the clock (admitted: under
    reset_jump_s) kept a silent stick driving paths for 1.4 s, not joy_timeout_s: its age
    was measured from its stamps. It ages from its last arrival now."""
    assert 0.0 < _ok_after_silence(silent, 0.0) <= 0.5 + 1e-9
    assert 0.0 < _ok_after_silence(silent, 0.9) <= 0.5 + 1e-9


@pytest.mark.parametrize("silent", ["joy", "vo"])
def test_a_stream_stamped_ahead_is_stale_a_timeout_after_it_fell_silent_without_now(silent):
    """The same fed without ``now`` (README's in-process example did so): a joystick
    stamped 0.9 s ahead kept paths coming 1.35 s after the stick fell silent. predict(now)
    takes each sample as heard no later than the first ``now`` that sees it: it arrived by
    then. Stamps behind the clock age from their stamps, as before."""
    assert 0.0 < _ok_after_silence(silent, 0.0, with_now=False) <= 0.5 + 1e-9
    assert 0.0 < _ok_after_silence(silent, 0.9, with_now=False) <= 0.5 + 1e-9
    # the ages as predict counts them, without changing them
    pred = Predictor(linear_model(), PredictorConfig(horizon_steps=5))
    assert pred.feed_joy(101.0, (0.5, 0.0)) and pred.feed_vo(100.0, (0.4, 0.0))
    assert pred.input_ages(100.2) == pytest.approx((0.0, 0.2))
    assert pred.input_ages(100.5) == pytest.approx((0.0, 0.5))
    pred.status(100.2)  # seen at 100.2: from then on it ages from 100.2
    assert pred.input_ages(100.5) == pytest.approx((0.3, 0.5))


def test_a_sample_of_more_than_two_values_or_an_ok_that_is_not_a_bool_is_refused():
    """feed_joy / feed_vo took the first two values of a longer tuple, and feed_vo took
    ok="False" (a string, truthy) as tracked."""
    pred = Predictor(linear_model())
    for bad in ((0.5, 0.0, 0.3), (0.5,), np.zeros((1, 2)), 0.5):
        with pytest.raises(ValueError, match="two values"):
            pred.feed_joy(100.0, bad)
        with pytest.raises(ValueError, match="two values"):
            pred.feed_vo(100.0, bad)
    for ok in ("False", "True", 0, 1, None):
        with pytest.raises(ValueError, match="ok must be a bool"):
            pred.feed_vo(100.0, (0.1, 0.0), ok=ok)
    assert pred.stats.vo_samples == 0 and pred.stats.joy_samples == 0
    assert pred.feed_vo(100.0, np.array([0.1, 0.0]), ok=np.bool_(True))
    assert pred.feed_vo(100.1, (0.1, 0.0), ok=False) and pred.feed_joy(100.0, [0.2, 0.0])


def test_vo_tracking_loss_stops_prediction():
    pred, (jt, _, vt, _) = _fed(1010.0)
    now = max(jt[-1], vt[-1])
    pred.feed_vo(now + 0.01, (float("nan"), float("nan")), ok=False)
    r = pred.predict(now + 0.02)
    assert not r.ok and r.reason == Reason.VO_TRACKING_LOST
    assert pred.stats.dropped_nonfinite == 0  # a reported failure is not "bad data"


def test_backward_clock_jump_resets_and_prediction_resumes():
    pred, (jt, _, vt, _) = _fed(1012.0)
    now = max(jt[-1], vt[-1])
    assert pred.predict(now).ok
    # the bag loops: samples start again 12 s earlier
    jt2, joy2, vt2, vel2 = make_streams(duration=6.0, seed=3, t_start=1000.0)
    events = arrival_order(jt2, joy2, vt2, vel2)
    feed(pred, events[0])
    assert pred.stats.resets == 1
    assert "behind the newest" in pred.last_reset_detail
    for ev in events[1:]:
        feed(pred, ev)
    r = pred.predict(events[-1][0])
    assert r.ok, r.detail
    assert 1004.0 < r.t0 <= 1006.0
    # the clock itself jumping back (a replay loop seen by the watchdog) also resets
    r = pred.predict(events[-1][0] - 5.0)
    assert not r.ok and r.reason == Reason.CLOCK_RESET
    assert pred.stats.resets == 2 and pred.ready_step() is None


def test_nonfinite_samples_are_dropped_and_counted(data):
    jt, joy, vt, vel, _ = data
    events = [e for e in arrival_order(jt, joy, vt, vel) if e[0] < 1012.0]
    clean = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
    dirty = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
    for n, ev in enumerate(events):
        feed(clean, ev)
        feed(dirty, ev)
        if n % 50 == 10:
            assert not dirty.feed_joy(ev[0] + 0.001, (float("nan"), 0.0))
            assert not dirty.feed_vo(ev[0] + 0.002, (0.1, float("inf")))
            assert not dirty.feed_joy(float("nan"), (0.1, 0.0))
    assert dirty.stats.dropped_nonfinite == 3 * len(range(10, len(events), 50))
    now = events[-1][0]
    a, b = clean.predict(now), dirty.predict(now)
    assert a.ok and b.ok
    np.testing.assert_array_equal(a.pose, b.pose)


def test_out_of_order_and_duplicate_stamps_give_the_same_prediction(data):
    jt, joy, vt, vel, _ = data
    events = [e for e in arrival_order(jt, joy, vt, vel) if e[0] < 1015.0]
    shuffled = list(events)
    rng = np.random.default_rng(1)
    for i in rng.choice(len(events) - 2, size=len(events) // 4, replace=False):
        shuffled[i], shuffled[i + 1] = shuffled[i + 1], shuffled[i]
    shuffled += events[-30:-10]  # duplicates (same stamp, same values), late
    ordered = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
    disorder = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
    for ev in events:
        feed(ordered, ev)
    for ev in shuffled:
        feed(disorder, ev)
    assert disorder.stats.out_of_order > 0
    now = events[-1][0]
    a, b = ordered.predict(now), disorder.predict(now)
    assert a.ok and b.ok and a.step == b.step
    np.testing.assert_array_equal(a.pose, b.pose)


def test_of_equal_stamps_the_last_to_arrive_drives_the_prediction(data):
    """A backlog read at once can reach the predictor with equal stamps: of those, the
    newer reading (the last to arrive) is the one kept, in the buffers and the resampler
    alike, so a user who moved the stick from +0.6 to -0.6 is predicted at -0.6."""
    jt, joy, vt, vel, _ = data
    events = [e for e in arrival_order(jt, joy, vt, vel) if e[0] < 1012.0]
    joy_stamps = [e[0] for e in events if e[1] == "joy"][-5:]

    def run(values: list[tuple[float, float]]) -> Predictor:
        pred = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
        for ev in events:
            if ev[1] == "joy" and ev[0] in joy_stamps:
                for v in values:
                    assert pred.feed_joy(ev[0], v)
            else:
                feed(pred, ev)
        return pred

    now = events[-1][0]
    both = run([(0.6, 0.0), (-0.6, 0.0)]).predict(now)
    last = run([(-0.6, 0.0)]).predict(now)
    first = run([(0.6, 0.0)]).predict(now)
    assert both.ok and last.ok and first.ok
    np.testing.assert_array_equal(both.pose, last.pose)
    assert np.max(np.abs(both.pose - first.pose)) > 1e-3


def test_plan_drives_the_future_joystick_and_changes_the_path():
    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=5, plan_timeout_s=1.0)
    now = max(jt[-1], vt[-1])
    held = pred.predict(now)
    assert held.ok and not held.from_plan
    t0 = held.t0
    # plan published half a step after t0: row r is the command at t_{L+1+r}
    plan = np.column_stack([np.linspace(0.1, 0.9, 8), np.linspace(-0.5, 0.5, 8)])
    pred.set_plan(plan, stamp=t0 + 0.1)
    planned = pred.predict(now)
    assert planned.ok and planned.from_plan and planned.step == held.step
    np.testing.assert_array_equal(planned.joy_future, plan[:5])
    assert np.max(np.abs(planned.pose - held.pose)) > 1e-3
    # a plan published one step earlier maps its rows one later: same commands per time
    pred.set_plan(np.vstack([[0.0, 0.0], plan]), stamp=t0 - 0.1)
    np.testing.assert_array_equal(pred.predict(now).joy_future, plan[:5])
    # a plan shorter than the horizon holds its last row
    pred.set_plan(plan[:2], stamp=t0 + 0.1)
    np.testing.assert_array_equal(pred.predict(now).joy_future,
                                  np.vstack([plan[:2], plan[1:2], plan[1:2], plan[1:2]]))
    # a plan issued after t_{L+1} does not revise the command there (the older plan's
    # row holds), but drives the later steps
    pred.set_plan(plan, stamp=t0 + 0.1)
    pred.set_plan(-plan, stamp=t0 + 0.3)
    np.testing.assert_array_equal(pred.predict(now).joy_future,
                                  np.vstack([plan[:1], -plan[:4]]))
    # a stale plan is ignored
    pred.clear_plan()
    pred.set_plan(plan, stamp=now - 1.5)
    stale = pred.predict(now)
    assert not stale.from_plan
    np.testing.assert_array_equal(stale.pose, held.pose)
    with pytest.raises(ValueError, match=r"\[m, 2\]"):
        pred.set_plan(np.zeros((3, 3)), stamp=now)
    with pytest.raises(ValueError, match="finite"):
        pred.set_plan(np.full((3, 2), np.nan), stamp=now)


def test_a_plan_starting_far_ahead_of_the_clock_is_refused():
    """A plan stamped by a clock that jumped 3 s ahead (then back) would drive the future
    joystick once the clock reached its stamp; given ``now``, it is refused as a sample
    stamped that far ahead is."""
    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=5, plan_timeout_s=5.0)
    now = max(jt[-1], vt[-1])
    held = pred.predict(now)
    plan = np.column_stack([np.full(8, 0.9), np.full(8, -0.5)])
    with pytest.raises(RejectedInputError, match="ahead of the clock"):
        pred.set_plan(plan, stamp=now + 3.0, now=now)
    assert pred.stats.rejected[Reason.REJECT_TIME] == 1
    # the clock reaches the refused plan's start: it drives nothing
    later = pred.predict(now, joy_future=None)
    assert not later.from_plan
    assert pred.plan_future(now + 3.0, now + 3.0, 5) is None
    # within reset_jump_s (a planner starting a little ahead) it is taken
    pred.set_plan(plan, stamp=held.t0 + 0.2, now=now)
    assert pred.predict(now).from_plan
    with pytest.raises(ValueError, match="now must be"):
        pred.set_plan(plan, stamp=now, now=float("nan"))


def test_plans_starting_on_grid_times_map_row_by_row_at_epoch_stamps():
    """A planner stamps a plan with the grid time it starts at; at epoch stamps (1.7e9 s)
    that time and t0 + i dt differ by float64 ulps, which once shifted rows by one."""
    pred = Predictor(linear_model(), PredictorConfig(plan_timeout_s=1.0))
    dt = pred.dt
    plan = np.column_stack([np.linspace(0.1, 0.8, 8), np.zeros(8)])
    for step in range(8_500_000_000, 8_500_000_100):
        t0 = step * dt
        pred.clear_plan()
        stamp = round((step + 1) * dt * 1e9) * 1e-9  # as a message's header stamp
        pred.set_plan(plan, stamp)
        np.testing.assert_array_equal(pred.plan_future(t0, t0, 5), plan[:5], err_msg=str(step))


def test_predict_batch_matches_single_predictions():
    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=4)
    now = max(jt[-1], vt[-1])
    rng = np.random.default_rng(2)
    cands = rng.uniform(-1, 1, size=(7, 6, 2))
    batch = pred.predict_batch(cands, now)
    assert batch.ok and batch.pose.shape == (7, 6, 3) and batch.pos_cov.shape == (7, 6, 2, 2)
    assert batch.ellipses.shape == (7, 6, 3) and batch.times.shape == (6,)
    for b in (0, 3, 6):
        single = pred.predict(now, joy_future=cands[b])
        np.testing.assert_allclose(batch.pose[b], single.pose, atol=1e-12)
    with pytest.raises(ValueError, match=r"\[B, k, 2\]"):
        pred.predict_batch(np.zeros((6, 2)), now)
    not_ready = Predictor(linear_model()).predict_batch(cands, now)
    assert not not_ready.ok and not_ready.reason == Reason.NO_INPUT


def test_not_enough_history():
    pred = Predictor(linear_model())
    pred.feed_joy(100.0, (0.1, 0.0))
    pred.feed_vo(100.05, (0.0, 0.0))
    pred.feed_joy(100.5, (0.1, 0.0))
    pred.feed_vo(100.45, (0.05, 0.0))
    r = pred.predict(100.5)
    assert not r.ok and r.reason == Reason.NOT_ENOUGH_HISTORY and "needs 4" in r.detail


def test_confidence_ellipses_and_frame_change():
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 9.0]]])
    e = confidence_ellipses(cov)
    chi = math.sqrt(CHI2_2DOF_95)
    np.testing.assert_allclose(e[0, :2], [2 * chi, chi])
    np.testing.assert_allclose(e[1, :2], [3 * chi, chi])
    assert abs(math.sin(e[0, 2])) < 1e-12 and abs(math.cos(e[1, 2])) < 1e-12
    pose = np.array([[1.0, 0.0, 0.1]])
    p2, c2 = to_frame(pose, cov[:1], np.array([2.0, 3.0, math.pi / 2]))
    np.testing.assert_allclose(p2[0], [2.0, 4.0, 0.1 + math.pi / 2], atol=1e-12)
    np.testing.assert_allclose(c2[0], [[1.0, 0.0], [0.0, 4.0]], atol=1e-12)


def test_odometry_poses_give_the_origin():
    pred, (jt, _, vt, _) = _fed(1010.0)
    for t in np.arange(1005.0, 1010.0, 0.1):
        pred.feed_pose(t, 0.5 * (t - 1005.0), 1.0, 0.2)
    r = pred.predict(max(jt[-1], vt[-1]))
    assert r.ok and r.origin is not None
    np.testing.assert_allclose(r.origin, [0.5 * (r.t0 - 1005.0), 1.0, 0.2], atol=1e-9)


@pytest.mark.parametrize("bad", [
    {"horizon_steps": 0}, {"horizon_steps": 2.5}, {"joy_timeout_s": 0.0},
    {"vo_timeout_s": math.nan}, {"buffer_s": 0.5}, {"uncertainty": "ukf"},
])
def test_config_validation(bad):
    with pytest.raises(ValueError):
        PredictorConfig(**bad)


# ---- bad input never drives a prediction (issue 16) ------------------------------------

@pytest.mark.parametrize("now", [math.nan, math.inf, -math.inf, 1e300])
def test_predict_at_an_invalid_time_is_not_ok(now):
    pred, (jt, _, vt, _) = _fed(1010.0)
    good = max(jt[-1], vt[-1])
    for call in (lambda: pred.predict(now), lambda: pred.predict_batch(np.zeros((1, 3, 2)), now),
                 lambda: pred.status(now)):
        r = call()
        assert r is not None and not r.ok and r.reason == Reason.INVALID_TIME
        assert r.detail.startswith("now: time stamp")
    assert pred.stats.resets == 0  # an invalid clock is not a clock jump
    assert pred.predict(good).ok


def test_out_of_range_samples_are_refused_with_a_reason(data):
    jt, joy, vt, vel, _ = data
    events = [e for e in arrival_order(jt, joy, vt, vel) if e[0] < 1012.0]
    clean = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
    dirty = Predictor(linear_model(), PredictorConfig(horizon_steps=4))
    bad = 0
    for n, ev in enumerate(events):
        feed(clean, ev)
        feed(dirty, ev)
        if n % 50 == 10:
            t = ev[0]
            assert not dirty.feed_joy(t + 0.001, (1e30, 0.0))
            assert not dirty.feed_joy(t + 0.002, (0.0, -1.2))
            assert not dirty.feed_vo(t + 0.003, (6.0, 0.0))  # faster than any wheelchair
            assert not dirty.feed_vo(t + 0.004, (0.1, -1e30))
            assert not dirty.feed_joy(1e300, (0.1, 0.0))
            assert not dirty.feed_vo(-1e11, (0.1, 0.0))
            bad += 1
    assert dirty.stats.rejected == {Reason.REJECT_JOY: 2 * bad, Reason.REJECT_VO: 2 * bad,
                                    Reason.REJECT_TIME: 2 * bad}
    assert dirty.stats.last_rejected == (
        "time_out_of_range: VO: time stamp -1e+11 s is beyond +-1e+10 s")
    assert dirty.stats.dropped_nonfinite == 0 and dirty.stats.resets == 0
    now = events[-1][0]
    a, b = clean.predict(now), dirty.predict(now)
    assert a.ok and b.ok
    np.testing.assert_array_equal(a.pose, b.pose)


def test_the_reasons_name_the_problem():
    pred = Predictor(linear_model())
    assert pred.feed_joy(1.0, (1.04, -1.05))  # calibration overshoot is tolerated
    assert not pred.feed_joy(1.0, (1.06, 0.0))
    assert pred.stats.last_rejected == ("joy_out_of_range: joystick: forward deflection 1.06 "
                                        "is outside [-1.05, 1.05]")
    assert pred.feed_vo(1.0, (-5.0, 10.0))
    assert not pred.feed_vo(1.0, (0.0, 10.5))
    assert pred.stats.last_rejected == "vo_out_of_range: VO: |omega| = 10.5 rad/s is beyond " \
                                       "10 rad/s"
    assert not pred.feed_vo(1.0, (math.nan, 0.0))
    assert pred.stats.last_rejected == "nonfinite: VO: v is nan"
    assert pred.stats.dropped_nonfinite == 1
    # a sample reporting tracking loss carries no velocity: kept as a failure, any values
    assert pred.feed_vo(1.1, (1e30, math.nan), ok=False)
    assert not pred.feed_pose(1.0, 2e6, 0.0, 0.0)
    assert pred.stats.last_rejected == "pose_out_of_range: pose |x| = 2e+06 is beyond 1e+06"
    assert pred.feed_pose(1.0, -1e6, 1e6, 3.0)
    assert pred.stats.rejected == {Reason.REJECT_JOY: 1, Reason.REJECT_VO: 1,
                                   Reason.REJECT_NONFINITE: 1, Reason.REJECT_POSE: 1}


def test_plans_and_futures_out_of_range_are_refused():
    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=4)
    now = max(jt[-1], vt[-1])
    for plan, stamp, reason, match in (
            (np.full((3, 2), 1e30), now, Reason.REJECT_PLAN, "plan row 0: forward deflection"),
            (np.array([[0.1, 0.0], [0.2, -1.5]]), now, Reason.REJECT_PLAN,
             r"plan row 1: turn deflection -1.5 is outside \[-1.05, 1.05\]"),
            (np.zeros((online.MAX_PLAN_STEPS + 1, 2)), now, Reason.REJECT_PLAN,
             "1001 steps, more than 1000"),
            (np.zeros((3, 2)), math.nan, Reason.REJECT_NONFINITE, "plan: time stamp is nan"),
            (np.zeros((3, 2)), 1e12, Reason.REJECT_TIME, "plan: time stamp 1e\\+12 s")):
        with pytest.raises(online.RejectedInputError, match=match) as info:
            pred.set_plan(plan, stamp)
        assert info.value.reason == reason
        assert pred.stats.last_rejected.startswith(f"{reason}: ")
    assert not pred.predict(now).from_plan  # none of them was kept
    with pytest.raises(online.RejectedInputError, match="joy_future row 2"):
        pred.predict(now, joy_future=np.array([[0.0, 0.0]] * 2 + [[2.0, 0.0]]))
    with pytest.raises(online.RejectedInputError, match="candidates 1 row 1: turn deflection 1e"):
        pred.predict_batch(np.array([[[0.5, 0.5]] * 2, [[0.5, 0.5], [0.5, 1e30]]]), now)


def test_stamps_at_the_edge_of_the_time_range_still_predict():
    jt, joy, vt, vel = make_streams(duration=10.0, t_start=9.9e9)
    pred = Predictor(linear_model(), PredictorConfig(horizon_steps=3))
    for ev in arrival_order(jt, joy, vt, vel):
        feed(pred, ev)
    r = pred.predict(max(jt[-1], vt[-1]))
    assert r.ok, r.detail
    assert pred.stats.rejected == {}


def test_reason_codes_are_one_documented_enum():
    """Every reason is a distinct snake_case string, documented where it is defined; the
    predictor's refusals use the REJECT_* members."""
    values = [r.value for r in Reason]
    assert len(set(values)) == len(values)
    assert all(v.isidentifier() and v == v.lower() for v in values)
    assert all(isinstance(r, str) and f"{r}" == r.value for r in Reason)
    body = ast.parse(inspect.getsource(Reason)).body[0].body
    documented = {stmt.targets[0].id for stmt, nxt in itertools.pairwise(body)
                  if isinstance(stmt, ast.Assign) and isinstance(nxt, ast.Expr)
                  and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)}
    assert documented == {r.name for r in Reason}
    pred = Predictor(linear_model(), PredictorConfig(horizon_steps=5))
    assert not pred.feed_joy(1.0, (math.nan, 0.0))
    assert list(pred.stats.rejected) == [Reason.REJECT_NONFINITE]
    assert pred.predict(1.0).reason is Reason.NO_INPUT


def test_no_input_names_the_input_that_is_missing():
    """Without any joystick sample, VO at 10 Hz said "waiting for joystick and VO samples":
    the detail names what has no sample, the joystick, the VO, or both."""
    def detail(joy: bool, vo: bool) -> str:
        pred = Predictor(linear_model())
        for i in range(20):
            t = 100.0 + 0.1 * i
            if joy:
                pred.feed_joy(t, (0.3, 0.0))
            if vo:
                pred.feed_vo(t, (0.2, 0.0))
        status, got = pred.status(102.0), pred.predict(102.0)
        assert status is not None and (status.reason, status.detail) == (got.reason, got.detail)
        assert not got.ok and got.reason is Reason.NO_INPUT
        return got.detail

    assert detail(joy=False, vo=True) == "no joystick sample yet"
    assert detail(joy=True, vo=False) == "no VO sample yet"
    assert detail(joy=False, vo=False) == "no joystick sample and no VO sample yet"


def test_the_sample_buffer_keeps_what_a_list_would():
    """The buffers keep their samples in one array that grows by replacement and is pruned
    from the front: against a plain list, through growth, pruning by the newest stamp (in
    arrival order, stopping at the first sample inside the window), the cap on rows (the
    oldest go, counted), out-of-order and equal stamps, and clears; arrays handed out
    earlier never change."""
    rng = np.random.default_rng(3)
    cap = 60
    buf = online._Buffer(2, cap)
    ref: list[tuple[float, float, float]] = []
    newest = -math.inf
    handed: list[tuple[np.ndarray, np.ndarray]] = []
    t = 0.0
    for i in range(5000):
        if i % 1700 == 1699:
            buf.clear()
            ref.clear()
            newest = -math.inf
        t += float(rng.choice([0.01, 0.0, -0.05, 0.3, 2.5], p=[0.8, 0.05, 0.1, 0.04, 0.01]))
        row = (t, float(rng.normal()), float(rng.normal()))
        assert buf.add(t, row[1:]) == (t < newest)
        ref.append(row)
        newest = max(newest, t)
        horizon = float(rng.choice([1.0, 10.0]))
        capped = buf.prune(horizon)
        while ref and ref[0][0] < newest - horizon:
            ref.pop(0)
        assert capped == max(0, len(ref) - cap)
        del ref[:capped]
        assert len(buf) == len(ref)
        if i % 97 == 0:
            stamps, values = buf.arrays()
            want = np.array(ref).reshape(-1, 3)
            np.testing.assert_array_equal(stamps, want[:, 0])
            np.testing.assert_array_equal(values, want[:, 1:])
            handed.append((stamps, values, want))
            if ref:
                last_newest = max(range(len(ref)), key=lambda k: (ref[k][0], k))
                np.testing.assert_array_equal(buf.newest_row(), ref[last_newest])
    for stamps, values, want in handed:
        np.testing.assert_array_equal(stamps, want[:, 0])
        np.testing.assert_array_equal(values, want[:, 1:])


def test_a_flood_of_samples_does_not_grow_the_buffers_without_bound():
    """A sender stuck on one stamp (or flooding) would keep every sample inside the time
    window: the buffers keep at most MAX_SAMPLE_RATE_HZ per second of buffer_s, the newest,
    and count what they dropped."""
    pred = Predictor(linear_model(), PredictorConfig(buffer_s=3.0))
    cap = math.ceil(3.0 * online.MAX_SAMPLE_RATE_HZ)
    for i in range(cap + 500):
        assert pred.feed_joy(100.0, (0.001 * (i % 7), 0.0))
    stamps, values = pred._joy.arrays()
    assert len(stamps) == cap and pred.stats.dropped_overflow == 500
    assert values[-1, 0] == pytest.approx(0.001 * ((cap + 499) % 7))


def test_a_longer_buffer_set_at_runtime_moves_the_cap():
    """buffer_s changed after the predictor was made (a node's parameter at runtime): the
    cap on rows stayed the first buffer_s's, so a 100 Hz stick over 300 s with buffer_s
    600 set from 2 dropped 10,000 samples counted as a flood, and the buffer kept 200 s."""
    pred = Predictor(linear_model(), PredictorConfig(buffer_s=3.0))
    pred.config = dataclasses.replace(pred.config, buffer_s=600.0)
    for i in range(30_000):
        assert pred.feed_joy(100.0 + 0.01 * i, (0.5, 0.0))
    assert len(pred._joy) == 30_000 and pred.stats.dropped_overflow == 0
    pred.config = dataclasses.replace(pred.config, buffer_s=3.0)  # and back: capped again
    assert pred.feed_joy(400.0, (0.5, 0.0))
    assert len(pred._joy) <= math.ceil(3.0 * online.MAX_SAMPLE_RATE_HZ)


def beyond_physics_predictors():
    """(predictor, now): fed predictors of two models far outside physics, one predicting
    speeds of 1e6 m/s, one variances of 1e6."""
    jt, joy, vt, vel = make_streams(duration=10.0)
    for channels in ((LinearChannel(np.zeros(2 * LAGS + 1), b=1e6), LinearChannel(
            np.zeros(2 * LAGS + 1))), (linear_model().channels[0], LinearChannel(
                np.zeros(2 * LAGS + 1), var=1e6))):
        model = dataclasses.replace(linear_model(), channels=channels)
        pred = Predictor(model, PredictorConfig(horizon_steps=5))
        for ev in arrival_order(jt, joy, vt, vel):
            feed(pred, ev)
        yield pred, jt[-1]


def test_a_model_that_predicts_beyond_physics_gives_no_path():
    """A model (loaded before its file was checked, or far outside its data) predicting
    speeds beyond any wheelchair's, or variances beyond them squared: no path, reason
    model_out_of_range, never a path of 1e6 m/s."""
    for pred, now in beyond_physics_predictors():
        r = pred.predict(now)
        assert not r.ok and r.reason == Reason.MODEL_OUT_OF_RANGE, r
        assert r.pose.shape == (0, 3)
        batch = pred.predict_batch(np.zeros((3, 5, 2)), now)
        assert not batch.ok and batch.reason == Reason.MODEL_OUT_OF_RANGE


def test_a_clock_step_back_restarts_and_refuses_the_old_timeline():
    """clock_stepped_back (a node's clock read going back: NTP): the buffers restart, and
    until the clock is back where it was, samples stamped more than STEP_LEAD_S ahead of it
    (sent before the step, delivered after) are refused; the new timeline's are taken."""
    pred = Predictor(linear_model(), PredictorConfig())
    for i in range(50):
        t = 100.0 + 0.1 * i
        assert pred.feed_joy(t, (0.5, 0.0), now=t)
    assert len(pred._joy) == 50
    pred.clock_stepped_back(104.0, 0.9)  # the clock read 104.9, now 104.0
    assert len(pred._joy) == 0 and "stepped back by 0.900 s" in pred.last_reset_detail
    assert not pred.feed_joy(104.95, (0.5, 0.0), now=104.0)  # of the old timeline
    assert pred.stats.rejected[Reason.REJECT_TIME] == 1
    assert pred.feed_joy(104.05, (0.3, 0.0), now=104.0)  # the new one's (a little ahead)
    assert pred.feed_joy(104.9, (0.3, 0.0), now=104.9)  # the clock back where it was
    assert pred.feed_joy(105.3, (0.3, 0.0), now=105.0)  # and the guard lifted
    assert len(pred._joy) == 3
    # a bag looped (the clock an hour back), its samples 0.2 s ahead of a 5 Hz /clock: the
    # guard lasts STEP_GUARD_S, not the hour (half the samples were refused all along)
    pred.clock_stepped_back(10.0, 3600.0)
    assert not pred.feed_joy(10.2, (0.3, 0.0), now=10.0)
    assert pred.feed_joy(10.0 + online.STEP_GUARD_S + 0.2, (0.3, 0.0),
                         now=10.0 + online.STEP_GUARD_S)


def test_a_buffer_shorter_than_the_window_and_the_stale_look_back_is_refused():
    """buffer_s 2 s was accepted (PredictorConfig takes 1 s, and min_buffer_s said 1.0 for
    a predictor that does not adapt): the stale-VO rule saw a run of frozen readings cut
    short by the buffer's edge, and stale VO drove paths the 10 s buffer refused. The
    minimum is the model's lags x dt, the rules' look-back and two VO gaps, and named."""
    model = linear_model(8)  # 8 lags at 5 Hz, as the committed tile model
    with pytest.raises(ValueError, match=r"at least 3\.40 s, got 2 s: .*8 lags x 0\.2 s"):
        Predictor(model, PredictorConfig(buffer_s=2.0))
    need = 8 * 0.2 + 0.6 + 2 * 0.6
    assert Predictor(model).min_buffer_s == pytest.approx(need)
    assert Predictor.window_history_s(model) == pytest.approx(need)
    pred = Predictor(model, PredictorConfig(buffer_s=10.0))
    with pytest.raises(ValueError, match=r"at least 3\.40 s"):
        pred.config = dataclasses.replace(pred.config, buffer_s=3.0)
    assert pred.config.buffer_s == 10.0
    assert Predictor.buffer_for(model, 10, None, 1.0) == pytest.approx(need)

    # VO frozen at zero for 20 s while the stick pushes, then moving: at the minimum, every
    # window gets the verdict of a 10 s buffer; with 2 s (forced past the check) some
    # windows that hold stale steps drove paths
    rng = np.random.default_rng(1)
    t0, t1, end = 1000.0, 1020.0, 1026.0
    jt = np.arange(t0, end, 1 / 30)
    vt = t0 + np.cumsum(rng.uniform(0.15, 0.25, size=200))
    vt = vt[vt < end]
    vel = np.where((vt < t1)[:, None], 0.0,
                   np.c_[0.5 + 0.1 * np.sin(vt), 0.05 * np.cos(vt)])
    events = arrival_order(jt, np.tile([0.8, 0.0], (jt.size, 1)), vt, vel)
    full = Predictor(model, PredictorConfig(buffer_s=10.0))
    least = Predictor(model, PredictorConfig(buffer_s=need))
    short = Predictor(model, PredictorConfig(buffer_s=10.0))
    short._config = dataclasses.replace(short.config, buffer_s=2.0)
    i, differ, differ_short = 0, 0, 0
    for now in np.arange(t1 - 1.0, end, 0.02):
        while i < len(events) and events[i][0] <= now:
            for p in (full, least, short):
                feed(p, (events[i][0], events[i][1], tuple(events[i][2])))
            i += 1
        want = full.predict(now)
        got = least.predict(now)
        differ += (want.ok, want.reason) != (got.ok, got.reason)
        differ_short += short.predict(now).ok and not want.ok
    assert differ == 0 and differ_short > 10


def test_a_prediction_holds_its_own_copy_of_the_commands_it_was_made_for():
    """Prediction.joy_future was the caller's joy_future / candidates array (a planner that
    refills one buffer each cycle changed the commands of the paths it kept), and
    solve_inverse's window shared its joystick with the InverseResult."""
    pred, (jt, _, vt, _) = _fed(1012.0, horizon_steps=6)
    now = max(jt[-1], vt[-1])
    cand = np.zeros((4, 6, 2))
    cand[:, :, 0] = [[0.2], [0.4], [0.6], [0.8]]
    kept = pred.predict_batch(cand, now)
    cand[:] = -0.5  # the next cycle's candidates
    np.testing.assert_array_equal(kept.joy_future[:, :, 0],
                                  np.repeat([[0.2], [0.4], [0.6], [0.8]], 6, axis=1))
    fut = np.tile([0.6, 0.0], (6, 1))
    r = pred.predict(now, fut)
    fut[:] = 0.0
    np.testing.assert_array_equal(r.joy_future, np.tile([0.6, 0.0], (6, 1)))
    window, res = pred.solve_inverse(r.pose[:, :2] * 0.5, now)
    assert res is not None and not np.shares_memory(window.joy_future, res.joystick)
    solved = res.joystick.copy()
    res.joystick[:] = 0.0
    np.testing.assert_array_equal(window.joy_future, solved)
