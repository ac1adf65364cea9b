"""The shared-control decision (asgp_ros.core.shared_control), on a linear motion model and a
wall given as an analytic collision check."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.stats import norm
from test_predictor import linear_model

from asgp_ros.core import collision
from asgp_ros.core.collision import PathCheck
from asgp_ros.core.online import Predictor, PredictorConfig
from asgp_ros.core.shared_control import (
    SharedControlConfig,
    Why,
    candidate_commands,
    check_covariance,
    decide,
    judge_moved_stick,
    within_stick,
)
from asgp_ros.sim.lidar import cast_to_segments

HALF_LENGTH = 0.6  # front of the footprint ahead of the base frame's origin (m)


def wall_ahead(distance: float):
    """Probability that the footprint's front passes a wall at x = distance (base frame)."""
    def check(pose, cov):
        sd = np.sqrt(np.maximum(cov[..., 0, 0], 1e-12))
        per_step = norm.cdf((pose[..., 0] + HALF_LENGTH - distance) / sd)
        return per_step, per_step.max(axis=-1)
    return check


def driving(forward: float = 0.8, turn: float = 0.0, seconds: float = 4.0,
            t_start: float = 1000.0) -> tuple[Predictor, float]:
    """A predictor fed a steady drive: joystick at 30 Hz, VO at 6 Hz at the steady speed
    (with a little noise: an unchanging reading is a frozen VO)."""
    pred = Predictor(linear_model(), PredictorConfig(horizon_steps=10))
    rng = np.random.default_rng(0)
    gain = np.array([0.4 / 0.4, 0.35 * 0.8 / (1 - 0.6 * 0.8)])  # steady state of the model
    v = gain * np.array([forward, turn])
    events = [(t, "joy") for t in np.arange(t_start, t_start + seconds, 1 / 30)]
    events += [(t, "vo") for t in np.arange(t_start + 0.01, t_start + seconds, 1 / 6)]
    for t, kind in sorted(events):
        if kind == "joy":
            pred.feed_joy(t, (forward, turn))
        else:
            pred.feed_vo(t, v + rng.normal(0.0, 1e-3, 2))
    return pred, t_start + seconds - 0.02


CONFIG = SharedControlConfig()


def test_no_intervention_when_the_way_is_clear():
    pred, now = driving()
    d = decide(pred, now, np.array([0.8, 0.0]), wall_ahead(50.0), CONFIG)
    assert d.why is Why.CLEAR and d.command is None and d.p_user < 1e-6
    assert d.prediction is not None and d.prediction.pose[-1, 0] > 1.0  # it does drive


def test_a_decision_keeps_the_users_command_it_was_made_for():
    """Decision.user was the caller's stick array: a node updating its buffer in place
    changed the command a logged decision says it judged."""
    pred, now = driving()
    stick = np.array([0.8, 0.0])
    d = decide(pred, now, stick, wall_ahead(50.0), CONFIG, learn=False)
    stick[:] = (-0.8, 0.6)  # the hand moves; the buffer is updated in place
    assert d.why is Why.CLEAR and not np.shares_memory(d.user, stick)
    np.testing.assert_array_equal(d.user, [0.8, 0.0])


def test_a_wall_ahead_gets_the_smallest_change_that_avoids_it():
    pred, now = driving()
    user = np.array([0.8, 0.0])
    path_x = decide(pred, now, user, wall_ahead(50.0), CONFIG).prediction.pose[:, 0]
    wall = path_x[-1] + HALF_LENGTH - 0.3  # the user's path reaches 30 cm into it
    d = decide(pred, now, user, wall_ahead(wall), CONFIG)
    assert d.why is Why.INTERVENING and d.p_user > 0.9
    assert d.p_command <= CONFIG.threshold
    assert 0.0 <= d.command[0] < user[0]  # slower, never faster nor backwards
    # no other safe candidate is cheaper: brute force over the same candidates
    cands = candidate_commands(user, CONFIG)
    fut = np.repeat(cands[:, None, :], 10, axis=1)
    batch = pred.predict_batch(fut, now)
    _, p = wall_ahead(wall)(batch.pose, batch.pos_cov)
    change = np.linalg.norm(cands - user, axis=1)
    lost = np.maximum(0.0, path_x[-1] - batch.pose[:, -1, 0])
    cost = change**2 + CONFIG.progress_weight * lost**2
    safe = p <= CONFIG.threshold
    assert safe.any() and d.change == pytest.approx(change[safe][np.argmin(cost[safe])])
    assert d.candidates == len(cands) and d.solve_s > 0.0


def test_no_safe_command_sends_the_least_likely_or_lets_the_user_back_away():
    pred, now = driving()
    user = np.array([0.8, 0.0])
    path_x = decide(pred, now, user, wall_ahead(50.0), CONFIG).prediction.pose[:, 0]
    # a wall so close that even stopping at once is above the threshold, but less likely
    stop_x = decide(pred, now, np.array([0.0, 0.0]) + 1e-3, wall_ahead(50.0),
                    SharedControlConfig(neutral_deadband=0.0)).prediction.pose[-1, 0]
    d = decide(pred, now, user, wall_ahead(stop_x + HALF_LENGTH - 0.01), CONFIG)
    assert d.why is Why.NO_SAFE_COMMAND and d.command is not None
    assert d.p_command < d.p_user and d.command[0] < 0.2
    # already touching: every candidate touches; overriding would pin the chair there
    d = decide(pred, now, user, wall_ahead(HALF_LENGTH - 0.05), CONFIG)
    assert d.why is Why.NO_SAFE_COMMAND and d.command is None and "user" in d.detail
    assert path_x[-1] > stop_x


def wall_with_depth(distance: float) -> PathCheck:
    """``wall_ahead`` that also gives how much deeper than now the mean paths go past it."""
    now = max(0.0, HALF_LENGTH - distance)
    return PathCheck(wall_ahead(distance), lambda pose: np.maximum(
        0.0, (pose[..., 0] + HALF_LENGTH - distance).max(axis=-1) - now))


def test_within_the_margin_a_command_into_the_wall_is_stopped_and_backing_away_passes():
    """Every candidate certain to touch (the chair within its margin of the wall): the layer
    let the user's command pass, pushing on into the wall (an offline drive's one contact:
    reversing while turning swung a corner into the furniture). How much deeper than now
    the mean paths go tells the candidates apart now; backing away still passes."""
    pred, now = driving(forward=0.3)
    user = np.array([0.3, 0.0])
    wall = HALF_LENGTH - 0.05  # already 5 cm in
    d = decide(pred, now, user, wall_with_depth(wall), CONFIG)
    assert d.why is Why.NO_SAFE_COMMAND and d.command is not None, d
    assert d.p_command == pytest.approx(1.0) and d.p_user == pytest.approx(1.0)
    assert 0.0 <= d.command[0] < user[0] and "deep" in d.detail
    # the command sent goes no more than depth_tolerance deeper than the shallowest
    cands = candidate_commands(user, CONFIG)
    batch = pred.predict_batch(np.repeat(cands[:, None, :], 10, axis=1), now)
    deeper = wall_with_depth(wall).deepening(batch.pose)
    sent = int(np.flatnonzero(np.all(np.isclose(cands, d.command), axis=1))[0])
    assert deeper[sent] <= deeper.min() + CONFIG.depth_tolerance < deeper[0]
    # a tolerance wider than the difference: the user's command passes, as before
    loose = SharedControlConfig(depth_tolerance=0.5)
    assert decide(pred, now, user, wall_with_depth(wall), loose).command is None
    # without a depth (a plain check) it passes as before
    d = decide(pred, now, user, wall_ahead(wall), CONFIG)
    assert d.why is Why.NO_SAFE_COMMAND and d.command is None and "user" in d.detail
    # reversing away from a wall 30 cm in, every path certain to touch (a check that says
    # so): no candidate is shallower than backing away; the user's command passes
    certain = PathCheck(lambda pose, cov: (np.ones(pose.shape[:2]), np.ones(pose.shape[0])),
                        wall_with_depth(HALF_LENGTH - 0.3).deepening)
    pred, now = driving(forward=-0.3)
    d = decide(pred, now, np.array([-0.3, 0.0]), certain, CONFIG)
    assert d.why is Why.NO_SAFE_COMMAND and d.command is None and "user" in d.detail
    # and one driving on into it is stopped
    pred, now = driving(forward=0.3)
    d = decide(pred, now, np.array([0.3, 0.0]), certain, CONFIG)
    assert d.why is Why.NO_SAFE_COMMAND and d.command is not None and d.command[0] < 0.3


def test_a_depth_that_fails_never_intervenes():
    pred, now = driving(forward=0.3)
    for bad in (lambda pose: np.full(pose.shape[0], np.nan), lambda pose: np.zeros(2),
                lambda pose: np.full(pose.shape[0], -0.1),
                lambda pose: (_ for _ in ()).throw(ValueError("broken"))):
        d = decide(pred, now, np.array([0.3, 0.0]),
                   PathCheck(wall_ahead(HALF_LENGTH - 0.05), bad), CONFIG)
        assert d.why is Why.CHECK_FAILED and d.command is None, d


def test_a_turn_on_the_spot_can_be_stopped():
    """Stopping altogether is a candidate even for a turn on the spot (forward 0), which
    shifting the turn by the offsets alone never reaches."""
    pred, now = driving(forward=0.0, turn=1.0)
    user = np.array([0.0, 1.0])  # the offsets reach down to a turn of 0.2

    def turning_into_it(pose, cov):  # the more it turns left, the likelier
        per_step = np.clip(pose[..., 2] / 0.5, 0.0, 1.0)
        return per_step, per_step.max(axis=-1)

    d = decide(pred, now, user, turning_into_it, CONFIG)
    assert d.command is not None and d.p_command < d.p_user
    np.testing.assert_allclose(d.command, [0.0, 0.0])  # the least turning there is


def test_a_neutral_stick_never_commands_anything():
    pred, now = driving(forward=0.0)
    d = decide(pred, now, np.array([0.0, 0.0]), wall_ahead(0.7), CONFIG)
    assert d.why is Why.NEUTRAL and d.command is None


def test_a_stick_barely_touched_is_guarded_by_stopping_alone():
    """Within neutral_deadband (0.05) the board still drives the chair (5 % at 0.05): the
    layer said "neutral" and let it creep into a wall with a contact certain. It is guarded
    now, but only by stopping: never steered from a stick barely touched."""
    pred, now = driving(forward=0.04, turn=-0.03)
    user = np.array([0.04, -0.03])
    d = decide(pred, now, user, wall_ahead(HALF_LENGTH + 0.01), CONFIG)
    assert d.why in (Why.INTERVENING, Why.NO_SAFE_COMMAND), d  # stopping, the best there is
    np.testing.assert_array_equal(d.command, [0.0, 0.0])
    assert d.candidates == 2  # the user's command and stopping, nothing else
    far = decide(pred, now, user, wall_ahead(5.0), CONFIG)
    assert far.why is Why.CLEAR and far.command is None


def test_stale_inputs_or_no_obstacle_source_never_intervene():
    pred, now = driving()
    user = np.array([0.8, 0.0])
    d = decide(pred, now, user, None, CONFIG)
    assert d.why is Why.NO_OBSTACLES and d.command is None
    d = decide(pred, now, np.array([math.nan, 0.0]), wall_ahead(1.0), CONFIG)
    assert d.why is Why.STALE_INPUT and d.command is None
    # a command no stick gives (a stray publisher's 1e30): refused as such, not a failed
    # prediction, and nothing commanded
    for bad in ([1e30, 0.0], [0.5, -7.0], [1.5, 0.0]):
        d = decide(pred, now, np.array(bad), wall_ahead(1.0), CONFIG)
        assert d.why is Why.STALE_INPUT and d.command is None and "outside" in d.detail
    d = decide(pred, now + 2.0, user, wall_ahead(1.0), CONFIG)  # joystick and VO 2 s old
    assert d.why is Why.STALE_INPUT and d.command is None and "stale" in d.detail


def test_no_joystick_yet_is_said_so_not_a_nan_stick():
    """A layer that has heard no joystick said "the user's command: forward deflection is
    nan" (it passed NaN for the missing stick): it says there is no joystick sample yet,
    in the predictor's words, and judges nothing."""
    pred, now = driving()
    d = decide(pred, now, None, wall_ahead(1.0), CONFIG)
    assert d.why is Why.STALE_INPUT and d.command is None and d.prediction is None
    assert d.detail == "the user's command: no joystick sample yet"
    assert "nan" not in d.detail.lower()
    vo_only = Predictor(linear_model())  # the predictor's words for the same
    vo_only.feed_vo(now - 0.1, (0.5, 0.0))
    assert d.detail.endswith(": " + vo_only.predict(now).detail)


def test_a_failing_or_non_finite_check_never_intervenes():
    pred, now = driving()
    user = np.array([0.8, 0.0])

    def nan_check(pose, cov):
        return np.full(pose.shape[:2], np.nan), np.full(pose.shape[0], np.nan)

    def raising(pose, cov):
        raise ValueError("scan has no valid return")

    for check in (nan_check, raising):
        d = decide(pred, now, user, check, CONFIG)
        assert d.why is Why.CHECK_FAILED and d.command is None


def test_the_check_gets_the_pose_covariance_with_heading_uncertainty():
    """The prediction carries the rollout's pose covariance; the layer passes it (heading
    sampled) unless told to use the position covariance and the mean heading."""
    pred, now = driving(turn=0.5)
    user = np.array([0.8, 0.5])
    seen: list[tuple[int, ...]] = []

    def recording(wall: float):
        inner = wall_ahead(wall)

        def check(pose, cov):
            seen.append(cov.shape)
            return inner(pose, cov)
        return check

    d = decide(pred, now, user, recording(50.0), CONFIG)
    p = d.prediction
    assert p.pose_cov.shape == (10, 3, 3) and seen == [(1, 10, 3, 3)]
    np.testing.assert_array_equal(p.pose_cov[:, :2, :2], p.pos_cov)
    assert np.all(p.pose_cov[:, 2, 2] > 0.0)  # the heading is uncertain
    wall = p.pose[-1, 0] + HALF_LENGTH - 0.3
    seen.clear()
    decide(pred, now, user, recording(wall), CONFIG)  # intervenes: candidates checked too
    assert seen == [(1, 10, 3, 3), (len(candidate_commands(user, CONFIG)), 10, 3, 3)]
    seen.clear()
    decide(pred, now, user, recording(wall), SharedControlConfig(heading_uncertainty=False))
    assert [s[-2:] for s in seen] == [(2, 2), (2, 2)]


def test_candidates_never_drive_faster_than_the_user_or_leave_the_stick_range():
    for user in ([0.8, 0.0], [-0.5, 0.9], [0.3, -1.0], [1.0, 1.0]):
        u = np.array(user)
        c = candidate_commands(u, CONFIG)
        np.testing.assert_array_equal(c[0], u)  # the user's own command first
        assert np.all(np.abs(c[:, 0]) <= abs(u[0]) + 1e-12)
        assert np.all(c[:, 0] * u[0] >= 0.0)  # never reversing the user's direction
        assert np.all(np.abs(c[:, 1]) <= 1.0)
        assert len(np.unique(c, axis=0)) == len(c)
        assert any(np.allclose(row, [0.0, u[1]]) for row in c)  # stopping forward
        assert any(np.allclose(row, [0.0, 0.0]) for row in c)  # stopping altogether
        assert any(np.allclose(row, 0.55 * u) for row in c)  # slowing the whole command


@pytest.mark.parametrize("bad", [dict(threshold=0.0), dict(threshold=1.0),
                                 dict(threshold=math.nan), dict(speed_scales=(0.5, 1.0)),
                                 dict(speed_scales=(0.0, 0.5)), dict(turn_offsets=(0.2,)),
                                 dict(neutral_deadband=-0.1), dict(progress_weight=-1.0),
                                 dict(depth_tolerance=-0.01), dict(depth_tolerance=math.nan)])
def test_invalid_settings_are_refused(bad):
    with pytest.raises(ValueError):
        SharedControlConfig(**bad)


@pytest.fixture(scope="module")
def chair_model(tmp_path_factory):
    """A small ASGP of the simulated chair (2 minutes of tile, as `asgp train --paper`)."""
    from asgp_ros.learning.training import TrainOptions, read_series, train
    from asgp_ros.sim.simulate import simulate, write_recording

    bag = tmp_path_factory.mktemp("sc") / "tile"
    write_recording(bag, simulate("tile", 2.0, 5))
    return train(read_series([str(bag)]), TrainOptions(kind="asgp", max_iter=40, seed=0))


def test_the_layer_prevents_contacts_of_an_inattentive_driver(chair_model):
    """The offline closed loop (asgp_ros.sim.shared_drive): the same inattentive user with
    and without the layer; the layer takes contacts away and leaves most driving alone."""
    from asgp_ros.sim.shared_drive import drive

    without = drive(chair_model, 60.0, 4, layer=False, inattention=0.5)
    with_layer = drive(chair_model, 60.0, 4, layer=True, inattention=0.5)
    assert without.contacts >= 2 and without.interventions == 0
    assert without.untouched_share == 1.0
    assert with_layer.contacts < without.contacts
    assert with_layer.interventions >= 1 and with_layer.untouched_share > 0.6
    assert with_layer.decisions.get("intervening", 0) >= 1 and with_layer.solve_ms
    again = drive(chair_model, 12.0, 4, layer=True, inattention=0.5)
    assert again.summary() | {"solve_p50_ms": 0, "solve_p99_ms": 0} == \
        drive(chair_model, 12.0, 4, layer=True, inattention=0.5).summary() | {
            "solve_p50_ms": 0, "solve_p99_ms": 0}  # deterministic for a seed


def test_the_offline_layer_can_adapt_and_learns_nothing_its_overrides_drove(chair_model):
    """drive(adapt=...): the layer's predictor adapts as the node's does (adapt.enabled),
    learning after each decision; the steps its overrides drove are refused."""
    from asgp_ros.core.adaptive import AdaptSettings
    from asgp_ros.sim.shared_drive import drive

    plain = drive(chair_model, 60.0, 4, layer=True, inattention=0.5)
    assert plain.adaptation == {} and not any(k.startswith("adapt_") for k in plain.summary())
    adapting = drive(chair_model, 60.0, 4, layer=True, inattention=0.5,
                     adapt=AdaptSettings())
    a = adapting.summary()
    assert adapting.interventions >= 1
    assert a["adapt_rows_absorbed"] >= 100
    # every override keeps its steps out: at least the steps of the time spent overriding
    assert a["adapt_steps_refused"] >= round(adapting.intervention_s * 5.0)
    assert 0.0 <= a["adapt_coverage_95"] <= 1.0 and a["adapt_scale_max"] > 0.0


@pytest.mark.parametrize("bad", [(math.nan, 0.01), (0.01, math.inf), (-0.01, 0.01),
                                 (1e30, 0.01), (0.01,)])
def test_the_offline_drives_vo_noise_is_checked(chair_model, bad):
    from asgp_ros.sim.shared_drive import drive

    with pytest.raises(ValueError, match="vo_noise"):
        drive(chair_model, 1.0, 4, layer=False, vo_noise=bad)


def test_the_offline_drives_vo_noise_reaches_the_layers_input(chair_model):
    """A noisier VO changes what the layer sees (and so the drive) when the layer takes its
    velocity from the VO; none changes nothing; with 'auto' the matched scans give it."""
    from asgp_ros.sim.shared_drive import drive

    def run(**kw):
        return drive(chair_model, 40.0, 4, layer=True, inattention=0.5, **kw)

    base = run(velocity_source="vo")
    same = run(velocity_source="vo", vo_noise=(0.01, 0.01))
    noisy = run(velocity_source="vo", vo_noise=(0.3, 0.3))
    strip = {"solve_p50_ms": 0, "solve_p99_ms": 0}
    assert base.interventions >= 1  # the layer acted, on what the VO told it
    assert base.summary() | strip == same.summary() | strip
    assert noisy.summary() | strip != base.summary() | strip
    auto = run()
    assert auto.summary() | strip == run(vo_noise=(0.3, 0.3)).summary() | strip
    assert auto.velocity_switches == 0 and auto.interventions >= 1


def test_the_offline_vo_loses_tracking_as_a_camera_does():
    """Episodes at the floor's rate of the recordings, 0.5-3 s each, none when off; and no
    VO while the camera faces something nearer than its minimum depth."""
    from asgp_ros.core.collision import Scan
    from asgp_ros.sim.sensors import SensorParams
    from asgp_ros.sim.shared_drive import (
        VO_MIN_DEPTH_M,
        _camera_blind,
        _lost_at,
        _vo_loss_episodes,
    )

    episodes = _vo_loss_episodes(np.random.default_rng(3), "hybrid", 3600.0, True)
    rate = SensorParams().failure_rate("hybrid")  # per minute
    assert 0.7 * rate * 60 <= len(episodes) <= 1.3 * rate * 60
    durations = episodes[:, 1] - episodes[:, 0]
    assert durations.min() >= 0.5 and durations.max() <= 3.0
    assert np.all(episodes[1:, 0] >= episodes[:-1, 1])  # sorted, one at a time
    np.testing.assert_array_equal(
        episodes, _vo_loss_episodes(np.random.default_rng(3), "hybrid", 3600.0, True))
    lost = _lost_at(episodes)
    assert all(lost(0.5 * (a + b)) for a, b in episodes)
    gaps = [(b, c) for (_, b), (c, _) in itertools.pairwise(episodes)
            if c - b > 1e-3]
    assert gaps and not any(lost(0.5 * (b + c)) for b, c in gaps)
    assert not lost(float(episodes[0, 0]) - 1e-6) and not lost(-1.0)
    assert _vo_loss_episodes(np.random.default_rng(3), "hybrid", 3600.0, False).shape == (0, 2)
    assert not _lost_at(np.zeros((0, 2)))(5.0)

    angles = np.linspace(-0.75 * np.pi, 0.75 * np.pi, 541)

    def scan(ahead: float, side: float = 5.0) -> Scan:
        r = np.where(np.abs(angles) < 0.6, ahead, side)
        return Scan(r, float(angles[0]), float(angles[1] - angles[0]), 0.05, 8.0)

    mount = (0.3, 0.0, 0.0)
    assert _camera_blind(scan(0.8 * VO_MIN_DEPTH_M), mount)
    assert not _camera_blind(scan(2.0 * VO_MIN_DEPTH_M), mount)
    assert not _camera_blind(scan(np.inf), mount)  # no returns: open space, not a wall
    assert not _camera_blind(scan(2.0, side=0.1), mount)  # a wall beside, none ahead
    assert _camera_blind(scan(2.0, side=0.1), (0.3, 0.0, np.pi / 2))  # a camera facing it
    # a camera looking backward (the package's) is not blinded by a wall ahead, and is by
    # one behind (the scanner here seeing all round)
    round_angles = np.linspace(-np.pi, np.pi, 721, endpoint=False)
    behind = np.where(np.abs(round_angles) > np.pi - 0.4, 0.8 * VO_MIN_DEPTH_M, 5.0)
    ahead = np.where(np.abs(round_angles) < 0.4, 0.8 * VO_MIN_DEPTH_M, 5.0)
    inc = float(round_angles[1] - round_angles[0])
    assert not _camera_blind(Scan(ahead, -np.pi, inc, 0.05, 8.0), mount, camera_yaw=np.pi)
    assert _camera_blind(Scan(behind, -np.pi, inc, 0.05, 8.0), mount, camera_yaw=np.pi)
    assert _camera_blind(Scan(ahead, -np.pi, inc, 0.05, 8.0), mount)
    # a camera looking where the scanner does not was never blinded: refused (the default
    # 270-degree scanner and a backward camera), as a camera_yaw that is no angle
    from asgp_ros.sim.lidar import LidarConfig
    from asgp_ros.sim.shared_drive import _camera_in_view, drive

    assert _camera_in_view(0.0, LidarConfig()) and _camera_in_view(1.5, LidarConfig())
    assert not _camera_in_view(np.pi, LidarConfig())
    assert _camera_in_view(np.pi, LidarConfig(fov_deg=360.0, beams=1440))
    for yaw in (np.pi, np.nan):
        with pytest.raises(ValueError, match="camera_yaw"):
            drive(None, 60.0, 0, layer=True, camera_yaw=yaw)  # type: ignore[arg-type]


def test_with_the_vo_lost_auto_keeps_the_layers_input_fresh(chair_model):
    """The same drive with the VO losing tracking (a feature-poor floor): from the VO alone
    the layer's input goes stale; 'auto' takes the scans and decides throughout."""
    from asgp_ros.sim.shared_drive import drive

    def run(source):
        # 60 s hold this seed's tracking losses (7.8 s of them): 90 s gave the same counts
        return drive(chair_model, 60.0, 3, layer=True, inattention=0.5, surface="hybrid",
                     velocity_source=source)

    vo, auto = run("vo"), run("auto")
    assert vo.vo_lost_s > 0.0 and auto.vo_lost_s > 0.0
    assert vo.decisions.get("stale_input", 0) >= 5  # 15 when written
    assert auto.decisions.get("stale_input", 0) <= 1
    free = drive(chair_model, 30.0, 3, layer=True, inattention=0.5, surface="hybrid",
                 velocity_source="vo", vo_losses=False)
    assert free.vo_lost_s == 0.0 and free.decisions.get("stale_input", 0) <= 1


def test_the_offline_layer_can_take_its_velocity_from_scan_matching(chair_model):
    """velocity_source 'scan_matching', as the node's: the layer predicts from the matched
    scans' twists and still prevents the inattentive driver's contacts."""
    from asgp_ros.sim.shared_drive import drive

    without = drive(chair_model, 60.0, 4, layer=False, inattention=0.5)
    scans = drive(chair_model, 60.0, 4, layer=True, inattention=0.5,
                  velocity_source="scan_matching")
    assert scans.contacts < without.contacts and scans.interventions >= 1
    assert scans.decisions.get("stale_input", 0) <= 2  # the scans keep its input fresh
    with pytest.raises(ValueError, match="velocity_source"):
        drive(chair_model, 1.0, 4, layer=True, velocity_source="wheels")


def test_a_held_command_is_replayed_on_a_copy_of_the_chair():
    """The audit's plant: a copy of the chair drives a command held for the horizon and
    reports the closest approach; the chair itself does not move."""
    from asgp_ros.sim.chair import Chair
    from asgp_ros.sim.shared_drive import held_clearance
    from asgp_ros.sim.world import room_for_surface

    room = room_for_surface("tile")
    chair = Chair.for_room(room, seed=1, blocked=room.overlap)
    xs = np.linspace(0.0, room.x_max, 601)
    gaps = [room.footprint_clearance(x, 0.0, 0.0) - room.furniture_band for x in xs]
    x = float(xs[np.argmin(np.abs(np.array(gaps) - 0.3))])  # 0.3 m from the furniture ahead
    chair.reset((x, 0.0, 0.0))
    before = chair.state
    ahead, touched = held_clearance(chair, room, np.array([1.0, 0.0]), 2.0)
    assert touched and ahead <= 0.0
    still, touched = held_clearance(chair, room, np.array([0.0, 0.0]), 2.0)
    assert not touched and still == pytest.approx(0.3, abs=0.01)
    back, touched = held_clearance(chair, room, np.array([-0.5, 0.0]), 2.0)
    assert not touched and back >= still
    now, touched = held_clearance(chair, room, np.array([1.0, 0.0]), 0.0)  # no time: now
    assert not touched and now == pytest.approx(0.3, abs=0.01)
    assert chair.state == before and chair.contacts == 0


def test_the_audit_checks_the_layers_decisions_without_changing_the_drive(chair_model):
    from asgp_ros.sim.shared_drive import drive

    plain = drive(chair_model, 40.0, 4, layer=True, inattention=0.5)
    audited = drive(chair_model, 40.0, 4, layer=True, inattention=0.5, audit=True)
    keys = ("contacts", "interventions", "intervention_s", "untouched_share",
            "min_clearance_m")
    assert {k: audited.summary()[k] for k in keys} == {k: plain.summary()[k] for k in keys}
    assert plain.audit == [] and "audit_needed_share" not in plain.summary()
    rows = audited.audit
    assert 0 < len(rows) <= sum(audited.decisions.values())
    acted = [r for r in rows if r.intervened]
    assert acted and audited.summary()["audit_interventions"] == len(acted)
    # the layer acts where the held command touches, and passes where it does not
    assert np.mean([r.touched for r in acted]) > 0.5
    assert np.mean([r.touched for r in rows if not r.intervened]) < 0.1
    assert all(r.clearance_m <= 0.0 for r in rows if r.touched)
    # the replay ends with the layer's path, which starts at the last complete grid step
    assert all(1.6 <= r.seconds <= 2.0 for r in rows)
    # the same check against the room's true map: known for every decision, and it too
    # tells the held commands that touched from those that did not
    assert all(0.0 <= r.p_map <= 1.0 for r in rows)
    assert np.mean([r.p_map for r in rows if r.touched]) > 0.8
    assert np.mean([r.p_map for r in rows if not r.touched]) < 0.1
    # the checks' obstacle points, counted by how far short of the furniture they lie (the
    # scanner's 1 cm range noise: a few beyond 1 cm, fewer beyond 2 cm)
    one, two = audited.points_short
    assert audited.obstacle_points > 1000 and two <= one < 0.5 * audited.obstacle_points
    assert plain.obstacle_points == 0 and plain.points_short == [0, 0]


def test_short_of_furniture_is_the_depth_inside_the_free_floor():
    from asgp_ros.sim.shared_drive import short_of_furniture
    from asgp_ros.sim.world import room_for_surface

    room = room_for_surface("tile")
    x_lo, x_hi, y_lo, y_hi = room.free_box
    pts = np.array([[x_hi, 0.0], [x_hi - 0.03, 0.0], [x_hi + 0.1, 0.0], [0.0, y_lo + 0.02],
                    [x_lo + 0.5, y_hi - 0.01]])
    np.testing.assert_allclose(short_of_furniture(pts, room), [0.0, 0.03, -0.1, 0.02, 0.01],
                               atol=1e-12)


def test_the_audits_map_check_places_the_prediction_by_the_true_pose():
    """``map_probability``: the prediction (in its base frame) is placed by the true pose,
    turned and moved, against the room's map."""
    from asgp_ros.core import collision
    from asgp_ros.core.online import Prediction, Reason
    from asgp_ros.sim.chair import Chair
    from asgp_ros.sim.lidar import room_grid
    from asgp_ros.sim.shared_drive import map_probability
    from asgp_ros.sim.world import room_for_surface

    room = room_for_surface("tile")
    g = room_grid(room, 0.02)
    fld = collision.DistanceField.from_grid(collision.Grid(g.data, g.resolution, g.origin))
    k = 10
    pose = np.zeros((k, 3))
    pose[:, 0] = 0.1 * np.arange(1, k + 1)  # 1 m straight ahead over the horizon
    cov = np.tile(np.diag([1e-4, 1e-4, 1e-4]), (k, 1, 1))
    pred = Prediction(True, Reason.OK, t0=0.0, pose=pose, pos_cov=cov[:, :2, :2],
                      pose_cov=cov)
    config = SharedControlConfig()
    fp = collision.DEFAULT_FOOTPRINT.grown(0.05)
    x_lo, x_hi, _, _ = room.free_box
    chair = Chair.for_room(room, seed=1)

    def at(x: float, theta: float) -> float:
        return map_probability(fld, pred, chair.reset((x, 0.0, theta)), fp, config)

    near = x_hi - 0.6 - 0.5  # the front 0.5 m from the furniture, facing it
    assert at(near, 0.0) == 1.0 and at(near, math.pi) == 0.0
    far = x_lo + 0.6 + 0.5  # the back 0.5 m from the opposite furniture
    assert at(far, math.pi) == 1.0 and at(far, 0.0) == 0.0
    assert 0.0 < at(x_hi - 0.6 - 1.05, 0.0) < 1.0  # the last step at the margin's edge


FOOTPRINT_M = 0.05  # the node's default margin


def seg_scan(segments, beams: int = 720, too_close=()) -> collision.Scan:
    """A 360-degree scan at the base origin of line segments [((x1, y1), (x2, y2))]; beams
    listed in ``too_close`` read -inf (REP-117: too close to measure)."""
    fov = 2 * math.pi * (beams - 1) / beams
    a0, inc = -fov / 2, fov / (beams - 1)
    r = cast_to_segments(a0 + inc * np.arange(beams), segments)
    r = np.where(r > 8.0, np.inf, r)
    r[list(too_close)] = -np.inf
    return collision.Scan(r, a0, inc, 0.05, 8.0)


def _grown() -> collision.Footprint:
    return collision.DEFAULT_FOOTPRINT.grown(FOOTPRINT_M)


@pytest.mark.parametrize("user", [(0.0, 0.5), (0.3, 0.0), (0.2, 0.6), (0.3, 0.03)])
def test_in_a_closed_loop_the_layer_never_takes_the_chair_into_the_wall(user):
    """The chair moved by the model's first predicted step of what it was sent, the layer
    deciding every 0.2 s from a scan of a wall its grown nose is 3 cm into, the user holding
    a command into it. With every candidate certain, the first rule replaced a turn on the
    spot by a slow turn within 2 cm of the shallowest candidate's depth, measured again from
    each step's place: the layer's own command ratcheted the chair's real footprint 3 cm
    into the wall. Judged by how much deeper than now each path goes, it does not."""
    wall_x = 0.62  # world frame; the grown nose at 0.65
    pred, now = driving(forward=0.0)
    pose = np.zeros(3)
    k = pred.config.horizon_steps
    rng = np.random.default_rng(0)
    corners = np.array([[0.6, 0.35], [0.6, -0.35], [-0.6, 0.35], [-0.6, -0.35]])
    layer_drove = 0
    for _ in range(40):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        # the wall in the chair's frame: the line x_world = wall_x
        ends = [np.array([wall_x, y]) - pose[:2] for y in (-5.0, 5.0)]
        body = [((c * e[0] + s * e[1], -s * e[0] + c * e[1])) for e in ends]
        d = decide(pred, now, np.array(user), collision.scan_check(
            seg_scan([(body[0], body[1])]), _grown()), CONFIG)
        applied = np.array(user) if d.command is None else d.command
        layer_drove += d.command is not None
        step = pred.predict(now, joy_future=np.repeat(applied[None], k, 0))
        dx, dy, dth = step.pose[0]
        pose = pose + np.array([c * dx - s * dy, s * dx + c * dy, dth])
        for t in np.arange(now + 1 / 30, now + 0.2 + 1e-9, 1 / 30):
            pred.feed_joy(t, tuple(applied))
        for t in (now + 0.1, now + 0.2):
            pred.feed_vo(t, step.vel[0] + rng.normal(0.0, 1e-3, 2))
        now += 0.2
        R = np.array([[math.cos(pose[2]), -math.sin(pose[2])],
                      [math.sin(pose[2]), math.cos(pose[2])]])
        real = float((corners @ R.T + pose[:2])[:, 0].max() - wall_x)
        assert real <= 0.0, f"the real footprint {real:.3f} m into the wall ({d.detail})"
    assert layer_drove > 0


def test_a_corner_swept_into_furniture_behind_is_seen_whatever_touches_in_front():
    """The nose 5.9 cm into the margin of the furniture ahead, every candidate certain: a
    reversing turn (seed 10's command) sweeping a rear corner into a cabinet behind passed,
    the front's depth hiding the new contact (a path's depth was one maximum over every
    point). Each point against its own depth now, it is replaced; and one beam too close
    to measure (-inf, a point deep inside the footprint) no longer turns the rule off."""
    user = np.array([-0.49, -0.55])
    rear = ((-2.5, 0.83), (-0.75, 0.83))  # a cabinet behind, on the left
    for nose, too_close in ((0.03, ()), (0.059, ()), (0.03, (180,))):
        front = 0.65 - nose
        check = collision_scan_check(seg_scan([((front, -3.0), (front, 3.0)), rear],
                                              too_close=too_close))
        pred, now = driving(forward=0.0)
        d = decide(pred, now, user, check, CONFIG)
        assert d.p_user == pytest.approx(1.0)
        assert d.why is Why.NO_SAFE_COMMAND and d.command is not None, (nose, d.detail)
    # reversing straight out passes
    pred, now = driving(forward=0.0)
    front = 0.65 - 0.059
    d = decide(pred, now, np.array([-0.5, 0.0]), collision_scan_check(
        seg_scan([((front, -3.0), (front, 3.0)), rear])), CONFIG)
    assert d.command is None, d.detail


def collision_scan_check(scan):
    return collision.scan_check(scan, _grown())


def _post_check(px: float, py: float, half: float):
    """A cabinet's front face and sides, in the base frame."""
    return collision_scan_check(seg_scan([((px, py - half), (px, py + half)),
                                          ((px, py - half), (px + 0.3, py - half)),
                                          ((px, py + half), (px + 0.3, py + half))]))


def _p_held(pred, now, command, check) -> float:
    k = pred.config.horizon_steps
    b = pred.predict_batch(np.repeat(np.asarray(command, float)[None, None, :], k, axis=1),
                           now, learn=False)
    return float(check(b.pose, check_covariance(b, CONFIG))[1][0])


def test_a_stick_moved_while_deciding_gets_only_what_is_judged_with_it():
    """The layer steers round a cabinet corner; while it decided, the user slowed to 0.4 and
    steered the layer's way. The decision's command scaled down (turn and forward alike,
    the first version) swept the corner (p 0.13 where the user's stick alone was 0): what
    is sent for a moved stick is judged with it, and the stick passes when it is clear."""
    pred, now = driving(0.8, 0.0)
    check = _post_check(1.6, -0.4, 0.1)
    d = decide(pred, now, np.array([0.8, 0.0]), check, CONFIG, learn=False)
    assert d.why is Why.INTERVENING and d.command[1] != 0.0, d
    stick = np.array([0.4, d.command[1]])
    judged = judge_moved_stick(pred, now, d, stick, CONFIG, lambda _p: check)
    sent = stick if judged.command is None else judged.command
    assert _p_held(pred, now, sent, check) <= max(CONFIG.threshold,
                                                  _p_held(pred, now, stick, check))
    if judged.command is not None:
        assert judged.command[0] <= stick[0] + 1e-12


@pytest.mark.parametrize(("fwd", "turn", "wall"), [(0.3, 0.6, 0.8), (0.5, 0.4, 0.9)])
def test_a_stick_pulled_back_while_deciding_is_not_pinned_at_the_wall(fwd, turn, wall):
    """Near a wall the decision turns on the spot; while it was made the user pulled the
    stick back to reverse away: the turn on the spot was sent unchanged (pinning the chair,
    p 0.3-0.6) where the stick backing away is clear. It passes."""
    pred, now = driving(fwd, turn)
    check = collision_scan_check(seg_scan([((wall, -3.0), (wall, 3.0))]))
    d = decide(pred, now, np.array([fwd, turn]), check, CONFIG, learn=False)
    assert d.command is not None and d.command[0] == 0.0, d
    judged = judge_moved_stick(pred, now, d, np.array([-0.5, 0.0]), CONFIG,
                               lambda _p: check)
    assert judged.why is Why.CLEAR and judged.command is None, judged
    # a stick barely touched is only ever stopped, never steered
    barely = judge_moved_stick(pred, now, d, np.array([0.03, 0.0]), CONFIG,
                               lambda _p: check)
    assert barely.command is None or not np.any(barely.command), barely
    # a forward decision bounded to a slower stick keeps its turn, its forward no more
    np.testing.assert_allclose(within_stick(np.array([0.5, -0.3]), np.array([0.2, 0.4])),
                               [0.2, -0.3])
    np.testing.assert_allclose(within_stick(np.array([0.5, -0.3]), np.array([-0.2, 0.0])),
                               [0.0, -0.3])
    np.testing.assert_allclose(within_stick(np.array([-0.5, 0.3]), np.array([-0.2, 0.0])),
                               [-0.2, 0.3])


def test_a_moved_stick_gets_the_clear_command_that_changes_it_least():
    """Driving at a wall: the stick moved while the layer decided. Of the candidates
    judged with it (the stick slowed, the decision within it, stopping), the clear one
    that changes the stick least is sent (stopping made every such intervention a large
    change)."""
    from asgp_ros.core.shared_control import MOVED_STICK_SLOWER

    pred, now = driving(0.8, 0.0)
    check = collision_scan_check(seg_scan([((1.5, -3.0), (1.5, 3.0))]))
    d = decide(pred, now, np.array([0.8, 0.0]), check, CONFIG, learn=False)
    assert d.intervening, d
    stick = np.array([0.8, 0.15])
    judged = judge_moved_stick(pred, now, d, stick, CONFIG, lambda _p: check)
    candidates = [stick * f for f in MOVED_STICK_SLOWER]
    candidates += [within_stick(d.command, stick), np.zeros(2)]
    clear = [c for c in candidates if _p_held(pred, now, c, check) <= CONFIG.threshold]
    assert _p_held(pred, now, stick, check) > CONFIG.threshold and clear
    assert judged.why is Why.INTERVENING and judged.command is not None, judged
    least = min(float(np.linalg.norm(c - stick)) for c in clear)
    assert judged.change == pytest.approx(least)
    assert least < float(np.linalg.norm(stick))  # gentler than stopping
