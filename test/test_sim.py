"""Wheelchair, driver and sensor simulator: physics, behaviour, statistics, reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest

from asgp_ros.sim.chair import Chair, ChairParams
from asgp_ros.sim.driver import Driver
from asgp_ros.sim.figure import step_response
from asgp_ros.sim.sensors import (
    SensorParams,
    expected_failures,
    joystick_samples,
    quantise_joystick,
    vo_samples,
)
from asgp_ros.sim.simulate import simulate
from asgp_ros.sim.world import Patch, Room, room_for_surface


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def recordings():
    """Three-minute drives on each surface (shared by several tests)."""
    return {s: simulate(s, 3.0, seed) for seed, s in enumerate(("tile", "carpet", "hybrid"))}


def _hold(chair: Chair, joy, seconds: float):
    states = []
    for _ in range(round(seconds * 100)):
        states.append(chair.step(joy, 0.01))
    return states


# ----------------------------------------------------------------------------- params, world
def test_params_validation_and_presets():
    with pytest.raises(ValueError, match="v_max"):
        ChairParams(v_max=-1.0)
    with pytest.raises(ValueError, match="wheel_speed_max"):
        ChairParams(v_max=2.5, wheel_speed_max=2.0)
    with pytest.raises(ValueError, match="hybrid"):
        ChairParams.preset("hybrid")
    tile, carpet = ChairParams.preset("tile"), ChairParams.preset("carpet")
    assert carpet.rolling_resistance > tile.rolling_resistance
    assert carpet.turn_resistance > tile.turn_resistance
    assert ChairParams.preset("tile", v_max=2.0).v_max == 2.0
    assert 1.5 <= tile.v_max <= 3.0 and 1.0 <= tile.omega_max <= 2.0


def test_room_geometry():
    room = Room()
    assert (room.x_min, room.x_max, room.y_min, room.y_max) == (-6.0, 6.0, -4.5, 4.5)
    assert room.wall_distance(0.0, 0.0) == pytest.approx(4.5)
    # Footprint 1.2 x 0.7 facing +x at x = 5: front edge at 5.6, 0.4 m from the wall.
    assert room.footprint_clearance(5.0, 0.0, 0.0) == pytest.approx(0.4)
    assert room.footprint_clearance(5.0, 0.0, math.pi / 2) == pytest.approx(0.65)
    hybrid = room_for_surface("hybrid")
    grid = [(x, y) for x in np.linspace(-5, 5, 21) for y in np.linspace(-4, 4, 17)]
    kinds = {hybrid.surface_at(x, y) for x, y in grid}
    assert kinds == {"tile", "carpet"}
    with pytest.raises(ValueError):
        room_for_surface("gravel")
    with pytest.raises(ValueError, match="too small"):
        Room(x_min=-1.0, x_max=1.0)


# ----------------------------------------------------------------------------- chair
def test_chair_at_rest_and_dead_zone():
    chair = Chair(ChairParams.preset("tile"), seed=0)
    st = chair.reset((1.0, 2.0, 0.5))
    assert st.braked and st.v == 0.0
    states = _hold(chair, [0.05, -0.05], 2.0)  # inside the 8 % dead zone
    assert all(s.v == 0.0 and s.omega == 0.0 for s in states)
    assert states[-1].pose == pytest.approx((1.0, 2.0, 0.5))
    with pytest.raises(ValueError):
        chair.step([math.nan, 0.0], 0.01)
    with pytest.raises(ValueError):
        chair.step([0.0, 0.0], -0.01)


def test_step_carries_remainder_of_dt():
    a = Chair(ChairParams.preset("tile"), seed=3)
    b = Chair(ChairParams.preset("tile"), seed=3)
    for _ in range(40):
        sa = a.step([0.8, 0.3], 0.015)  # 1.5 internal steps per call
    for _ in range(60):
        sb = b.step([0.8, 0.3], 0.01)
    assert sa.t == pytest.approx(0.6) and sb.t == pytest.approx(0.6)
    assert (sa.x, sa.y, sa.v) == pytest.approx((sb.x, sb.y, sb.v))


def test_step_response_nonlinear_and_surface_dependent():
    tile = np.array([step_response("tile", k, "forward") for k in range(3)])
    carpet = np.array([step_response("carpet", k, "forward") for k in range(3)])
    t = tile[0, :, 0]
    i_rise, i_ss = np.searchsorted(t, 1.8), np.searchsorted(t, 5.5)
    # Lag: nothing in the first 0.1 s after the step, then a ramp.
    assert np.all(np.abs(tile[:, np.searchsorted(t, 1.08), 3]) < 0.02)
    v_ss_tile = tile[:, i_ss - 50:i_ss, 3].mean()
    v_ss_carpet = carpet[:, i_ss - 50:i_ss, 3].mean()
    # Expo profile: 0.7 deflection gives well under 70 % of the 1.8 m/s top speed.
    assert 0.75 < v_ss_tile < 0.7 * 1.8
    # Carpet: slower rise and lower steady speed (rolling resistance droop).
    assert carpet[:, i_rise, 3].mean() < tile[:, i_rise, 3].mean()
    assert v_ss_carpet < v_ss_tile - 0.03
    # Rotation is hit harder on carpet than translation.
    wt = np.array([step_response("tile", k, "turn") for k in range(3)])
    wc = np.array([step_response("carpet", k, "turn") for k in range(3)])
    j = np.searchsorted(t, 2.5)
    assert wc[:, j, 4].mean() / wt[:, j, 4].mean() < v_ss_carpet / v_ss_tile - 0.1


def test_turning_slows_forward_speed_and_wheels_saturate():
    straight = Chair(ChairParams.preset("tile"), seed=1)
    arc = Chair(ChairParams.preset("tile"), seed=1)
    vs = _hold(straight, [1.0, 0.0], 5.0)[-1].v
    st = _hold(arc, [1.0, 1.0], 5.0)[-1]
    assert st.v < 0.75 * vs
    p = ChairParams.preset("tile")
    assert max(abs(st.wheel_left), abs(st.wheel_right)) <= p.wheel_speed_max * 1.05


def test_reversal_caster_lurch_is_history_dependent_and_worse_on_carpet():
    def lurch(surface: str) -> np.ndarray:
        return np.array([
            step_response(surface, k, "forward")[650:1000, 4] for k in range(6)
        ])

    tile, carpet = lurch("tile"), lurch("carpet")
    peak_t, peak_c = np.abs(tile).max(axis=1), np.abs(carpet).max(axis=1)
    assert peak_c.mean() > 1.5 * peak_t.mean()
    assert peak_c.mean() > 0.1  # a visible yaw disturbance without any turn command
    # Which way the chair lurches depends on the caster's history (seed), not a constant.
    signs = np.sign(carpet[np.arange(6), np.abs(carpet).argmax(axis=1)])
    assert set(signs) == {-1.0, 1.0}


def test_hybrid_chair_uses_floor_under_it():
    room = room_for_surface("hybrid")
    params = {s: ChairParams.preset(s) for s in ("tile", "carpet")}
    chair = Chair(params, seed=0, surface_at=room.surface_at)
    assert chair.reset((0.0, 0.0, 0.0)).surface == "carpet"
    assert chair.reset((-3.0, -3.0, 0.0)).surface == "tile"
    with pytest.raises(ValueError, match="surface_at"):
        Chair(params)
    live = Chair.for_room(room, seed=1)
    assert live.reset((0.0, 0.0, 0.0)).surface == "carpet"
    assert Chair.for_room(room_for_surface("tile")).state.surface == "tile"


def test_carpet_is_harder_to_predict(recordings):
    """A linear ARX fit (the simplest motion predictor) explains tile better than carpet."""
    def residual(rec) -> float:
        t = np.arange(0.0, rec.duration, 0.2)
        j = np.stack([np.interp(t, rec.truth_t, rec.command[:, k]) for k in range(2)], 1)
        v = np.stack([np.interp(t, rec.truth_t, rec.truth[:, 3 + k]) for k in range(2)], 1)
        s = 4
        rows = [np.concatenate([j[i - s:i + 1, 1], v[i - s:i, 1], [1.0]])
                for i in range(s, t.size)]
        X, y = np.array(rows), v[s:, 1]
        moving = np.abs(y) + np.abs(X[:, s]) > 0.05
        coef, *_ = np.linalg.lstsq(X[moving], y[moving], rcond=None)
        return float(np.sqrt(np.mean((X[moving] @ coef - y[moving]) ** 2)))

    assert residual(recordings["carpet"]) > 1.2 * residual(recordings["tile"])


# ----------------------------------------------------------------------------- driver
def test_driver_keeps_chair_clear_of_furniture(recordings):
    for surface, rec in recordings.items():
        room = room_for_surface(surface)
        x, y, th = rec.truth[:, 0], rec.truth[:, 1], rec.truth[:, 2]
        poses = zip(x[::5], y[::5], th[::5], strict=True)
        clear = np.array([room.footprint_clearance(*p) for p in poses])
        assert clear.min() >= room.furniture_band, surface
        centre = np.minimum.reduce([x - room.x_min, room.x_max - x, y - room.y_min,
                                    room.y_max - y])
        assert centre.min() >= 0.8 + room.furniture_band, surface


def test_driver_behaviour_variety_and_motionless_ends(recordings):
    for rec in recordings.values():
        cmd, v, w = rec.command, rec.truth[:, 3], rec.truth[:, 4]
        t = rec.truth_t
        first = t[np.argmax(np.any(cmd != 0.0, axis=1))]
        last = t[len(t) - 1 - np.argmax(np.any(cmd[::-1] != 0.0, axis=1))]
        assert first >= 3.0 and rec.duration - last >= 3.0
        still_end = t >= rec.duration - 2.0
        assert np.all(v[still_end] == 0.0) and np.all(w[still_end] == 0.0)
        assert np.all(np.hypot(cmd[:, 0], cmd[:, 1]) <= 1.0 + 1e-9)
        assert (cmd[:, 0] < -0.2).mean() > 0.005  # reversals
        assert (np.abs(v) < 0.05).mean() > 0.05  # stops
        assert (np.abs(cmd[:, 1]) > 0.4).mean() > 0.05  # turns
        assert v.max() > 0.8  # some fast driving
        # Human hand: smooth (no jumps larger than a 20 ms reach allows).
        assert np.abs(np.diff(cmd[::2], axis=0)).max() < 0.35


def test_driver_live_on_a_wall_clock():
    """Live use: the drive starts at the first call, whatever the clock's origin."""
    chair = Chair(ChairParams.preset("tile"), seed=2)
    driver = Driver(5, duration=30.0)
    st, t0, cmds = chair.state, 1.7e9, []
    for i in range(1500):
        cmd = driver.command(t0 + 0.02 * i, st)
        st = chair.step(cmd, 0.02)
        cmds.append(cmd)
    cmds = np.array(cmds)
    moving = np.flatnonzero(np.any(cmds != 0.0, axis=1))
    assert moving.size and moving[0] * 0.02 >= 3.0 and moving[-1] * 0.02 <= 27.0
    assert st.v == 0.0 and st.braked


def test_driver_rejects_backwards_time():
    d = Driver(0)
    st = Chair(ChairParams.preset("tile")).state
    d.command(1.0, st)
    with pytest.raises(ValueError, match="backwards"):
        d.command(0.5, st)


# ----------------------------------------------------------------------------- sensors
def test_joystick_stream_rate_jitter_quantisation(recordings):
    rec = recordings["tile"]
    dt = np.diff(rec.joy_t)
    assert 1.0 / dt.mean() == pytest.approx(30.0, rel=0.01)
    assert 0.001 < dt.std() < 0.006  # jittery, but a 30 Hz stream
    counts = rec.joy * 511.5
    assert np.allclose(counts, np.round(counts), atol=1e-9)  # 10-bit ADC steps
    assert np.all(np.abs(rec.joy) <= 1.0)
    # Reading follows the true stick within noise + quantisation.
    true = np.stack([np.interp(rec.joy_t, rec.truth_t, rec.command[:, k]) for k in range(2)], 1)
    assert np.abs(rec.joy - true).max() < 0.02
    assert np.all(rec.joy_bag_t > rec.joy_t)
    # A released stick reads exactly zero (start and end of every recording).
    for r in recordings.values():
        assert np.all(r.joy[r.joy_t < 3.0] == 0.0)
        assert np.all(r.joy[r.joy_t > r.duration - 2.0] == 0.0)


def test_quantise_joystick_range():
    rng = np.random.default_rng(0)
    q = quantise_joystick(np.array([[-1.0, 1.0], [0.0, 0.0], [2.0, -3.0]]), rng)
    assert q.min() >= -1.0 and q.max() <= 1.0
    assert q[0] == pytest.approx([-1.0, 1.0], abs=2.5 / 511.5)


def test_vo_stream_rate_jitter_and_staleness(recordings):
    for rec in recordings.values():
        dt = np.diff(rec.vo_t)
        assert dt.min() >= 1.0 / 7.0 - 1e-9 and dt.max() <= 1.0 / 4.0 + 1e-9
        assert 5.0 < 1.0 / dt.mean() < 5.8
        assert dt.std() > 0.02
        lat = rec.vo_bag_t - rec.vo_t
        assert lat.min() >= 0.03 and lat.max() <= 0.09
        # Stale reports repeat the previous value exactly; failures cover them.
        idx = np.flatnonzero(rec.vo_stale)
        assert np.all(rec.vo[idx] == rec.vo[idx - 1])
        for i in idx:
            assert np.any((rec.failures[:, 0] <= rec.vo_t[i]) & (rec.vo_t[i] < rec.failures[:, 1]))
        # Outside failures, VO tracks the truth with speed-dependent noise.
        true_v = np.interp(rec.vo_t, rec.truth_t, rec.truth[:, 3])
        good = ~rec.vo_stale
        err = np.abs(rec.vo[good, 0] - true_v[good])
        assert np.median(err) < 0.05


def test_vo_failure_frequency_per_surface():
    """On a long synthetic drive, failures per minute of exposure match the configuration."""
    sp = SensorParams()
    minutes = 300.0
    t = np.arange(0.0, minutes * 60.0, 0.05)
    pose = np.stack([0.5 * t, np.zeros_like(t), 0.01 * t], 1)
    moving = np.ones(t.size, dtype=bool)
    moving[(t % 60.0) < 10.0] = False  # 10 s of every minute still: no failures then
    rates = {}
    for k, surface in enumerate(("tile", "carpet", "hybrid")):
        vo = vo_samples(t[-1], t, pose, moving, surface, np.random.default_rng(k), sp)
        fail_time = np.sum(vo.failures[:, 1] - vo.failures[:, 0])
        exposed = moving.mean() * t[-1] - fail_time
        n = vo.failures.shape[0]
        lam = expected_failures(exposed, surface, sp)
        assert abs(n - lam) < 4.0 * math.sqrt(lam) + 1, (surface, n, lam)
        rates[surface] = n / minutes
        starts = np.searchsorted(t, vo.failures[:, 0])
        assert np.all(moving[starts] | moving[np.maximum(starts - 1, 0)])
        dur = vo.failures[:, 1] - vo.failures[:, 0]
        assert dur.min() >= 0.5 - 1e-9 and dur.max() <= 3.0 + 0.26
    assert rates["carpet"] > 2 * rates["tile"] and rates["hybrid"] > 2 * rates["tile"]


def test_joystick_samples_follow_command():
    t = np.linspace(0.0, 10.0, 1001)
    cmd = np.stack([np.sin(t), np.cos(t)], 1) * 0.5
    stamp, reading, bag = joystick_samples(10.0, t, cmd, np.random.default_rng(1))
    assert np.all(np.diff(stamp) > 0) and np.all(bag > stamp)
    assert np.abs(reading[:, 0] - 0.5 * np.sin(stamp)).max() < 0.01


# ----------------------------------------------------------------------------- simulate
def test_simulate_reproducible_and_seed_sensitive():
    a = simulate("hybrid", 0.3, 42)
    b = simulate("hybrid", 0.3, 42)
    c = simulate("hybrid", 0.3, 43)
    for name in ("joy_t", "joy", "vo_t", "vo", "truth", "command", "failures"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.truth, c.truth)
    assert a.meta == b.meta


def test_simulate_streams_and_bad_arguments(recordings):
    rec = recordings["hybrid"]
    streams = rec.to_streams()
    assert streams.joy.shape == rec.joy.shape and streams.has_truth
    assert streams.vel_ok.all() and rec.vo_stale.any()
    assert np.array_equal(rec.to_streams(flag_failures=True).vel_ok, ~rec.vo_stale)
    assert streams.joy_t[0] == pytest.approx(rec.joy_t[0] + rec.epoch_ns * 1e-9)
    assert 0.05 < rec.meta["carpet_fraction"] < 0.95  # the hybrid drive crosses both floors
    with pytest.raises(ValueError, match="surface"):
        simulate("grass", 1.0, 0)
    with pytest.raises(ValueError, match="minutes"):
        simulate("tile", 0.0, 0)
    with pytest.raises(ValueError, match="seed"):
        simulate("tile", 1.0, -1)


def test_realism_figure(tmp_path):
    pytest.importorskip("matplotlib")
    from asgp_ros.sim.figure import make_realism_figure

    out = make_realism_figure(tmp_path / "fig.png", seeds=1)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["fig.png"]


@pytest.mark.parametrize("kwargs, match", [
    ({"base_surface": "ice"}, "unknown surface"),
    ({"furniture_band": -0.1}, "furniture_band"),
    ({"x_min": -1.0, "x_max": 1.0}, "too small"),
    ({"x_min": 0.5, "x_max": 10.0}, "start pose"),
])
def test_room_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Room(**kwargs)


def test_patch_validation():
    with pytest.raises(ValueError, match="no area"):
        Patch(0.0, 0.0, 0.0, 1.0, "carpet")
    with pytest.raises(ValueError, match="unknown surface"):
        Patch(0.0, 0.0, 1.0, 1.0, "ice")
