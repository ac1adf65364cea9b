"""`asgp demo`: its ROS-free parts, then a shortened demo end to end (several processes).

The end-to-end tests run the real command (`python -m asgp_ros.cli demo`) on this test
run's ROS domain (conftest.py), check the exit code, the report files, that every
component produced output, that online and offline success rates agree on the same cases,
that Ctrl-C stops everything, and that no node process outlives the demo.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from asgp_ros.core.modelfile import load_model
from asgp_ros.demo.monitor import (
    OnlineScore,
    PathRecord,
    RateMeter,
    TruthTrack,
    format_status,
    horizon_key,
    in_ellipse,
)
from asgp_ros.demo.orchestrator import (
    DemoError,
    DemoOptions,
    child_env,
    node_commands,
    silent_components,
)
from asgp_ros.demo.processes import ProcessGroup, proc_cpu_seconds
from asgp_ros.demo.simhw import (
    HardwareConfig,
    JoystickPath,
    SimulatedHardware,
    depth_to_mm,
    look_ahead,
)

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ simulated hardware


def _run(hw: SimulatedHardware, steps: int, plan_every: int | None = None,
         rows: int = 8) -> tuple[list[tuple[float, float, float]], dict[int, np.ndarray],
                                 dict[int, np.ndarray]]:
    """Step hw; return its poses, look-ahead plans by step, and the reported joystick at
    every hand update."""
    poses, plans, reported = [], {}, {}
    for _ in range(steps):
        n = hw.step_index
        if plan_every and n % plan_every == 0:
            plans[n] = look_ahead(hw.snapshot(), hw.path, plan_every * 0.01, rows)
        hw.step()
        if n % 2 == 0:
            reported[n] = np.asarray(hw.path.reported(hw.command))
        poses.append(hw.state.pose)
    return poses, plans, reported


def test_look_ahead_predicts_the_drive_exactly_without_board_delay():
    hw = SimulatedHardware(HardwareConfig(seed=3), board=False)
    _, plans, reported = _run(hw, 3000, plan_every=20)
    moving = 0
    for n, plan in plans.items():
        for r in range(plan.shape[0]):
            m = n + 20 * (r + 1)
            if m in reported:
                np.testing.assert_array_equal(plan[r], reported[m])
                moving += bool(np.any(plan[r] != 0.0))
    assert moving > 100  # the driver did drive (not a trivially zero plan)


def test_look_ahead_leaves_the_live_drive_untouched():
    a, _, _ = _run(SimulatedHardware(HardwareConfig(seed=5), board=False), 1500, 20)
    b, _, _ = _run(SimulatedHardware(HardwareConfig(seed=5), board=False), 1500, None)
    assert a == b
    assert np.hypot(*np.subtract(a[-1][:2], a[0][:2])) > 0.5  # it moved


def test_look_ahead_rejects_bad_grid():
    hw = SimulatedHardware(HardwareConfig(seed=1), board=False)
    with pytest.raises(ValueError, match="multiple"):
        look_ahead(hw.snapshot(), hw.path, 0.015, 3)
    with pytest.raises(ValueError, match="rows"):
        look_ahead(hw.snapshot(), hw.path, 0.2, 0)


def test_joystick_path_matches_board_and_bridge_rules():
    path = JoystickPath()
    assert path.chair_input(np.zeros(2)) == (0.0, 0.0)
    assert path.reported(np.zeros(2)) == (0.0, 0.0)
    f, t = path.reported(np.array([1.0, -1.0]))
    assert f == pytest.approx(1.0) and t == pytest.approx(-1.0)
    cf, ct = path.chair_input(np.array([0.5, 0.0]))
    assert 0.45 < cf < 0.55 and ct == 0.0
    # inside the dead band: both the firmware and the host read exactly zero
    assert path.chair_input(np.array([0.02, 0.0]))[0] == 0.0
    assert path.reported(np.array([0.02, 0.0]))[0] == 0.0


def test_hardware_config_validation():
    with pytest.raises(ValueError, match="surface"):
        HardwareConfig(surface="ice")
    with pytest.raises(ValueError, match="seed"):
        HardwareConfig(seed=-1)


def test_render_gives_bgr_and_millimetre_depth():
    hw = SimulatedHardware(HardwareConfig(seed=0, width=160, height=120), board=False)
    image, depth = hw.render(hw.state)
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8
    assert depth.shape == (120, 160) and depth.dtype == np.uint16
    valid = depth[depth > 0]
    assert valid.size > 0.3 * depth.size
    assert valid.min() >= 300 and valid.max() <= 6000  # the sensor's 0.3-6 m range


def test_depth_to_mm():
    d = np.array([[0.0, 1.2345, np.nan], [np.inf, -1.0, 70.0]], dtype=np.float32)
    mm = depth_to_mm(d)
    assert mm.dtype == np.uint16
    np.testing.assert_array_equal(mm, [[0, 1234, 0], [0, 0, 0]])


# ------------------------------------------------------------------ conversions


@pytest.mark.ros
def test_image_messages_round_trip():
    from asgp_ros.demo import camera
    from asgp_ros.nodes import conversions as conv

    rng = np.random.default_rng(0)
    bgr = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
    depth = rng.integers(0, 6000, (6, 8)).astype(np.uint16)
    m = camera.image_from_array(12.5, bgr, "cam")
    assert (m.encoding, m.width, m.height, m.step) == ("bgr8", 8, 6, 24)
    assert conv.stamp_to_seconds(m.header.stamp) == pytest.approx(12.5)
    np.testing.assert_array_equal(np.frombuffer(bytes(m.data), np.uint8).reshape(6, 8, 3), bgr)
    d = camera.image_from_array(12.5, depth, "cam")
    assert (d.encoding, d.step) == ("16UC1", 16)
    np.testing.assert_array_equal(np.frombuffer(bytes(d.data), np.uint16).reshape(6, 8), depth)
    assert camera.image_from_array(0.0, depth.astype(np.float32), "c").encoding == "32FC1"
    with pytest.raises(ValueError, match="encoding"):
        camera.image_from_array(0.0, depth.astype(np.int64), "c")


@pytest.mark.ros
def test_camera_info_and_ground_truth_messages():
    from asgp_ros.demo import camera
    from asgp_ros.nodes import conversions as conv

    K = np.array([[262.5, 0.0, 159.5], [0.0, 262.5, 119.5], [0.0, 0.0, 1.0]])
    info = camera.camera_info_from_matrix(3.0, K, 320, 240, "cam")
    assert (info.width, info.height) == (320, 240)
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), K)
    np.testing.assert_allclose(np.reshape(info.p, (3, 4))[:, :3], K)
    assert list(info.d) == [0.0] * 5
    odom = conv.odometry_from_pose(4.0, 1.0, -2.0, 3.0, 0.5, -0.25)
    t, vel, ok, pose = conv.odometry_to_sample(odom)
    assert t == pytest.approx(4.0) and ok
    assert vel == pytest.approx((0.5, -0.25)) and pose == pytest.approx((1.0, -2.0, 3.0))
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")


# ------------------------------------------------------------------ monitor


def _straight_truth(v: float = 0.5, yaw: float = 0.3, t_end: float = 10.0) -> TruthTrack:
    tr = TruthTrack()
    for t in np.arange(0.0, t_end, 0.02):
        tr.add(float(t), v * t * math.cos(yaw), v * t * math.sin(yaw), yaw)
    return tr


def _path(t0: float, offset: float = 0.0, v: float = 0.5) -> PathRecord:
    times = t0 + 0.2 * np.arange(1, 11)
    x = v * (times - t0) + offset
    pose = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    return PathRecord(t0=t0, times=times, pose=pose, arrival=t0 + 0.05)


def test_online_score_against_ground_truth():
    score = OnlineScore()
    score.add(_path(1.0))  # exact: straight ahead in base_link at t0
    score.add(_path(1.2, offset=0.15))  # 15 cm off at every horizon
    score.add(_path(9.0))  # its horizons are beyond the ground truth
    assert score.update(_straight_truth()) == 2
    for h in (1.0, 1.4, 2.0):
        rate, n = score.success(h)
        assert n == 2 and rate == 0.5
        err = score.errors(h)
        assert err[0] == pytest.approx(0.0, abs=1e-9)
        assert err[1] == pytest.approx(0.15, abs=1e-9)
    # restricted to a case set by grid index (round(t0 / dt))
    assert score.success(1.0, t0_filter={5}, dt=0.2) == (1.0, 1)
    assert score.success(1.0, t0_filter={7}, dt=0.2)[1] == 0


def test_online_score_uses_the_body_frame_at_t0():
    tr = TruthTrack()
    for t in np.arange(0.0, 5.0, 0.02):  # driving along +y: heading pi/2
        tr.add(float(t), 0.0, 0.4 * t, math.pi / 2)
    score = OnlineScore(horizons_s=(1.0,))
    rec = _path(1.0, v=0.4)  # straight ahead in base_link = +y in the world
    score.add(rec)
    score.update(tr)
    assert rec.errors["1.0"] == pytest.approx(0.0, abs=1e-9)


def test_in_ellipse_by_hand():
    # semi-axes 0.2 (major, along 30 degrees) and 0.05, around (1, 1)
    ell = np.array([0.2, 0.05, math.radians(30.0)])
    c = np.array([1.0, 1.0])
    along = np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0))])
    across = np.array([-along[1], along[0]])
    assert in_ellipse(c + 0.19 * along, c, ell) and not in_ellipse(c + 0.21 * along, c, ell)
    assert in_ellipse(c + 0.049 * across, c, ell)
    assert not in_ellipse(c + 0.051 * across, c, ell)
    # along x (not the major axis) 0.1 is outside: the ellipse is turned
    assert not in_ellipse(c + np.array([0.0, 0.1]), c, ell)
    # a degenerate ellipse (a chair at rest cannot move sideways) is its segment, and
    # no ellipse at all (a model without uncertainty) is its centre
    flat = np.array([0.1, 0.0, 0.0])
    assert in_ellipse(np.array([0.05, 0.0]), np.zeros(2), flat)
    assert not in_ellipse(np.array([0.05, 1e-6]), np.zeros(2), flat)
    assert not in_ellipse(np.array([5.0, 0.0]), np.zeros(2), flat)  # a segment, not a line
    assert in_ellipse(np.zeros(2), np.zeros(2), np.zeros(3))
    assert not in_ellipse(np.array([5.0, 5.0]), np.zeros(2), np.zeros(3))
    assert not in_ellipse([1e-150, 0.0], [0.0, 0.0], [1e-200, 1e-200, 0.0])  # no underflow
    assert in_ellipse([1e30, 0.0], [0.0, 0.0], [2e30, 1e30, 0.0])
    for bad in ([-0.1, 0.05, 0.0], [0.05, 0.1, 0.0], [np.nan, 0.0, 0.0],
                [np.inf, 1.0, 0.0], [0.1, 0.05, np.inf]):
        with pytest.raises(ValueError, match="axes"):
            in_ellipse(c, c, bad)
    with pytest.raises(ValueError, match="finite"):
        in_ellipse([np.nan, 0.0], c, ell)


def test_online_coverage_of_the_published_ellipses():
    score = OnlineScore()
    hit = _path(1.0, offset=0.03)  # 3 cm ahead of the truth at every horizon
    miss = _path(1.2, offset=0.03)
    none = _path(1.4, offset=0.03)  # its ellipses never arrived
    hit.ellipses = np.tile([0.05, 0.01, 0.0], (10, 1))  # 5 cm along x: holds the truth
    miss.ellipses = np.tile([0.05, 0.01, math.pi / 2], (10, 1))  # turned: 1 cm along x
    for rec in (hit, miss, none):
        score.add(rec)
    score.update(_straight_truth())
    for h in (1.0, 1.4, 2.0):
        assert score.coverage(h) == (0.5, 2)
        assert score.success(h) == (1.0, 3)
    assert score.coverage(1.0, t0_filter={5}, dt=0.2) == (1.0, 1)
    assert score.coverage(1.0, t0_filter={6}, dt=0.2) == (0.0, 1)
    assert score.coverage(1.0, t0_filter={7}, dt=0.2)[1] == 0
    assert math.isnan(OnlineScore().coverage(1.0)[0])
    # no uncertainty (axes 0) holds nothing 3 cm off; a NaN ellipse is not counted at all
    score = OnlineScore(horizons_s=(1.0,))
    zero, broken = _path(1.0, offset=0.03), _path(1.2, offset=0.03)
    zero.ellipses = np.zeros((10, 3))
    broken.ellipses = np.full((10, 3), np.nan)
    score.add(zero)
    score.add(broken)
    score.update(_straight_truth())
    assert score.coverage(1.0) == (0.0, 1) and score.bad_ellipses == 1


def test_report_gives_the_model_and_the_ellipses_coverage():
    from asgp_ros.demo.common import RunState
    from asgp_ros.demo.report import adaptation_summary, markdown, success_table

    score = OnlineScore()
    for i, rot in enumerate((0.0, math.pi / 2)):  # the first ellipse holds the truth
        rec = _path(1.0 + 0.2 * i, offset=0.03)
        rec.ellipses = np.tile([0.05, 0.01, rot], (10, 1))
        score.add(rec)
    score.update(_straight_truth())
    horizons = {horizon_key(h): {"success_rate": 1.0, "cases": 2, "median_error_m": 0.03,
                                 "coverage_95": 0.25,
                                 "truth": {"success_rate": 1.0, "cases": 2,
                                           "median_error_m": 0.03, "coverage_95": 0.75}}
                for h in (1.0, 1.4, 2.0)}
    rows = success_table(score, {"horizons": horizons}, {k: {5, 6} for k in horizons}, 0.2)
    assert rows[0]["online_coverage"] == 0.5 and rows[0]["online_coverage_n"] == 2
    assert rows[0]["online_cases_coverage"] == 0.5
    assert (rows[0]["offline_truth_coverage"], rows[0]["offline_vo_coverage"]) == (0.75, 0.25)
    options = {"surface": "tile", "seed": 0, "width": 320, "height": 240,
               "camera_rate_hz": 15.0, "plan": True, "adapt": False}
    state = RunState(options=options, domain_id=7, model_path="/m.npz",
                     train_info={"configuration": "s = 4, coupled, M = 160 / 160",
                                 "minutes": 10.0, "seed": 1000, "calibrated": False})
    assert "The model is not calibrated" in markdown(state, rows, [], [], {})
    state.train_info["calibrated"] = True
    text = markdown(state, rows, [], [], {})
    assert "The model is not calibrated" not in text
    assert "(s = 4, coupled, M = 160 / 160, trained on a simulated 10-minute drive" in text
    assert "| 1 s | 50.0% (n=2) | 50.0% (n=2) | 75.0% | 25.0% |" in text
    assert "adapted online" not in text and "simulator's VO model" in text
    state.options = dict(options, adapt=True)
    state.train_info = {}  # a model given with --model: no training line
    text = markdown(state, rows, [], [], {})
    assert "adapted online" in text and "trained on a simulated" not in text
    # asked to adapt, a model that cannot (an MLP): the report does not say it adapted
    assert "adapted online" not in markdown(state, rows, [], [], {}, adapted=False)

    class Diagnostics:  # what adaptation_summary reads of the monitor
        def __init__(self, values: dict[str, str]) -> None:
            self.values = values

        def diag_value(self, name_part: str, key: str) -> str | None:
            return self.values.get(key) if name_part == "predictor_node" else None

    lines, data = adaptation_summary(state, Diagnostics(
        {"adapt": "off", "adapt_unavailable": "only an ASGP adapts online; this model is of "
                                               "kind 'mlp'"}))
    assert data == {"unavailable": "only an ASGP adapts online; this model is of kind 'mlp'"}
    assert lines[0].startswith("Asked to adapt, the predictor predicted from the model as "
                               "trained: only an ASGP")
    lines, data = adaptation_summary(state, Diagnostics({"adapt": "on",
                                                        "adapt_rows_absorbed": "12"}))
    assert data["adapt_rows_absorbed"] == "12" and "unavailable" not in data
    assert "simulator's VO model" not in text  # a model given: its calibration is its own
    assert "not like with like" not in text
    state.options = dict(options, plan=False)
    assert "No plan: online, the ellipses are those of the held command" in markdown(
        state, rows, [], [], {})
    # a baseline without uncertainty publishes zero ellipses: no online coverage either
    rows = success_table(score, {"horizons": horizons}, {k: {5, 6} for k in horizons}, 0.2,
                         uncertainty=False)
    assert math.isnan(rows[0]["online_coverage"]) and rows[0]["online_coverage_n"] == 0
    assert math.isnan(rows[0]["online_cases_coverage"])


def test_a_model_at_another_rate_is_scored_at_its_horizons(tmp_path):
    """With a 2.5 Hz model the report's 'holding the command instead: 1 s 77.8%, 1.4 s
    68.2%' was computed at 1.2 and 1.6 s (asgp evaluate's horizons on that grid), and the
    online rows of 1.0 and 1.4 s had n = 0 (no pose there). The demo scores every column at
    the horizons the model's grid has, named as they are."""
    from asgp_ros.cli import main
    from asgp_ros.core.modelfile import load_model
    from asgp_ros.demo.report import demo_horizons, offline_cases, offline_held, success_table

    bag, path = tmp_path / "drive", tmp_path / "m25.npz"
    assert main(["simulate", "--minutes", "0.5", "--seed", "4", "--out", str(bag)]) == 0
    assert main(["train", str(bag), "--paper", "--rate", "2.5", "--max-iter", "10",
                 "--out", str(path)]) == 0
    model = load_model(path)
    assert demo_horizons(model) == (1.2, 1.6, 2.0)
    held, cases = offline_held(bag, model), offline_cases(bag, model)
    assert list(held) == list(cases) == ["1.2", "1.6", "2.0"]
    assert all(v["cases"] > 0 for v in held.values())
    score = OnlineScore(demo_horizons(model))
    rows = success_table(score, None, cases, 0.4, held)
    assert [r["horizon_s"] for r in rows] == [1.2, 1.6, 2.0]
    assert all(r["offline_held_n"] == held[horizon_key(r["horizon_s"])]["cases"] for r in rows)


def test_truth_track_unwraps_and_interpolates():
    tr = TruthTrack()
    tr.add(0.0, 0.0, 0.0, math.pi - 0.1)
    tr.add(1.0, 1.0, 2.0, -math.pi + 0.1)  # +0.2 rad across the wrap
    p = tr.at(0.5)
    assert p == pytest.approx([0.5, 1.0, math.pi])
    assert tr.at(-0.1) is None and tr.at(1.1) is None
    with pytest.raises(ValueError):
        tr.add(2.0, float("nan"), 0.0, 0.0)


def test_rate_meter():
    m = RateMeter(window_s=2.0)
    for i in range(21):
        m.tick(10.0 + 0.1 * i)
    assert m.rate(12.0) == pytest.approx(10.0, rel=0.06)
    assert m.rate(20.0) == 0.0


def test_status_line_and_keys():
    score = OnlineScore()
    line = format_status(12.0, 120.0, {"joy": 100.0, "vo": 14.9}, "tracking", 3.2, score)
    assert "12/120 s" in line and "joy 100.0" in line and "VO tracking" in line
    assert horizon_key(1.0) == "1.0" and horizon_key(1.4) == "1.4"


# ------------------------------------------------------------------ orchestration


def test_the_demo_trains_what_asgp_train_trains(tmp_path, monkeypatch):
    from asgp_ros.demo import orchestrator
    from asgp_ros.learning.training import TrainingError

    said: list[str] = []
    # a minute and a half: enough held-out cases in motion to choose (half a minute's held-out
    # end is the chair at rest: it falls back, as below)
    path, info = orchestrator.train_model(tmp_path, 0, 1.5, "tile", said.append)
    model = load_model(path)
    chosen = model.meta["selection"]["chosen"]
    assert info["configuration"].startswith(
        f"s = {chosen['lags']}, {'coupled' if chosen['coupled'] else 'per-axis'}, "
        f"M = {chosen['inducing'][0]} / {chosen['inducing'][1]}")
    assert info["configuration"] in said[-1] and info["rows"] > 100
    # too little held out to calibrate: said
    assert info["configuration"].endswith(", uncalibrated") and not info["calibrated"]
    # half a minute on the hybrid floor, too little to choose: the automatic configuration
    # falls back to the paper's (it once crashed the demo with a KeyError)
    path, info = orchestrator.train_model(tmp_path / "hybrid", 3, 0.5, "hybrid", said.append)
    assert "fallback" in load_model(path).meta["selection"]
    assert info["configuration"] == ("s = 4, per-axis, M = 20 / 40, the paper's configuration, "
                                     "uncalibrated: too little held-out data to choose")

    def refuse(*args, **kwargs):
        raise TrainingError("the held-out data are too short")

    monkeypatch.setattr(orchestrator, "train_auto", refuse)
    with pytest.raises(DemoError, match=r"failed: the held-out data are too short .*"
                                        r"--train-minutes"):
        orchestrator.train_model(tmp_path / "again", 0, 0.5, "tile", said.append)


def test_options_are_validated():
    with pytest.raises(DemoError, match="minutes"):
        DemoOptions(minutes=0.0).validate()
    with pytest.raises(DemoError, match="domain"):
        DemoOptions(domain_id=233).validate()
    # the simulated hardware node's range: 2^31 passed here and made the node fail with a
    # traceback
    with pytest.raises(DemoError, match="seed"):
        DemoOptions(seed=2**31).validate()
    DemoOptions(seed=2**31 - 1).validate()
    DemoOptions().validate()


def test_a_demo_stopped_before_its_nodes_spoke_blames_none_of_them():
    """Ctrl-C while the demo waited for its nodes gave exit 1 and 'joy never arrived:
    serial_bridge_node ... produced no output' for each of them; now exit 130."""
    from types import SimpleNamespace

    from asgp_ros.demo import orchestrator

    for stopped_by, silent in (("SIGINT", 0), ("", len(orchestrator.PRODUCERS))):
        state = orchestrator.RunState(options={}, domain_id=1, stopped_by=stopped_by)
        orchestrator._check_components(SimpleNamespace(counts={}),
                                       SimpleNamespace(children=[]), state)
        assert len(state.errors) == silent, state.errors


@pytest.mark.parametrize(("by", "rc"), [("SIGINT", 130), ("SIGTERM", 143), ("SIGHUP", 129)])
def test_a_stopped_demo_exits_as_every_command(monkeypatch, by, rc):
    """128 + the signal, as every asgp command: SIGHUP (the terminal closed) gave 143."""
    from types import SimpleNamespace

    from asgp_ros.demo import orchestrator

    monkeypatch.setattr(orchestrator, "write_report", lambda *a: {})
    state = orchestrator.RunState(options={}, domain_id=1, stopped_by=by)
    assert orchestrator._report(Path("out"), state, SimpleNamespace(), None,  # type: ignore[arg-type]
                                Path("bag"), {}, lambda _: None) == rc


def test_child_environment_isolates_the_demo():
    env = child_env(42)
    assert env["ROS_DOMAIN_ID"] == "42"
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"
    assert str(REPO) in env["PYTHONPATH"].split(os.pathsep)
    names = [name for name, _, _ in node_commands(DemoOptions(), Path("m.npz"), "/tmp/p")]
    assert names == ["hardware", "serial_bridge", "vo", "predictor"]
    # adapting by default (as the nodes do), --no-adapt says so explicitly
    args = {name: a for name, _, a in node_commands(DemoOptions(), Path("m.npz"), "/tmp/p")}
    assert args["predictor"][-2:] == ["-p", "adapt.enabled:=true"]
    args = {name: a for name, _, a in node_commands(DemoOptions(adapt=False), Path("m.npz"),
                                                    "/tmp/p")}
    assert args["predictor"][-2:] == ["-p", "adapt.enabled:=false"]
    # the shared-control layer's own predictor adapts with it
    args = {name: a for name, _, a in node_commands(
        DemoOptions(shared_control=True), Path("m.npz"), "/tmp/p")}
    assert args["shared_control"][-2:] == ["-p", "adapt.enabled:=true"]
    args = {name: a for name, _, a in node_commands(
        DemoOptions(shared_control=True, adapt=False), Path("m.npz"), "/tmp/p")}
    assert args["shared_control"][-2:] == ["-p", "adapt.enabled:=false"]


def test_silent_components_are_named():
    counts = {"ground_truth/odom": 10, "joy": 5, "vo/twist": 0}
    msgs = silent_components(counts)
    assert len(msgs) == 2
    assert "vo/twist" in msgs[0] and "vo_node" in msgs[0]
    assert "predicted_path" in msgs[1] and "predictor_node" in msgs[1]
    assert silent_components(dict.fromkeys(("ground_truth/odom", "joy", "vo/twist",
                                            "predicted_path"), 1)) == []


def test_report_and_orchestrator_do_not_import_each_other():
    """What both need (DemoError, evaluate_bag) lies below both, in demo.common."""
    import ast

    def imports(name: str) -> set[str]:
        tree = ast.parse((REPO / "asgp_ros" / "demo" / f"{name}.py").read_text())
        return {node.module for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.module}

    assert "asgp_ros.demo.orchestrator" not in imports("report")
    assert not {m for m in imports("common") if m.startswith("asgp_ros.demo")}
    from asgp_ros.demo import common, orchestrator

    assert orchestrator.DemoError is common.DemoError


def test_proc_cpu_seconds():
    assert proc_cpu_seconds(os.getpid()) > 0.0
    assert proc_cpu_seconds(2**22 + 12345) is None


_STUCK_NODE = """
import signal, time

def waiting_for_ever():
    time.sleep(3600)

def main():
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    print("ready", flush=True)
    waiting_for_ever()
"""


def test_a_node_that_does_not_stop_writes_its_stacks_before_it_is_killed(tmp_path):
    (tmp_path / "stuck_node.py").write_text(_STUCK_NODE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    group = ProcessGroup(env, tmp_path / "logs")
    child = group.start("stuck", "stuck_node:main", [])
    deadline = time.monotonic() + 30.0
    while "ready" not in child.log_tail() and time.monotonic() < deadline:
        assert not group.reap(child), child.log_tail()
        time.sleep(0.02)
    group.stop_all(int_deadline_s=0.2, term_deadline_s=0.2)
    assert child.returncode == -signal.SIGKILL and child.signal_used == "SIGKILL"
    log_text = child.log_path.read_text()
    # faulthandler's dump: the main thread, inside the function it was stuck in
    assert "Current thread" in log_text or "Thread 0x" in log_text, log_text
    assert "waiting_for_ever" in log_text, log_text


# ------------------------------------------------------------------ end to end


def _tail(path: Path, lines: int) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError as exc:
        return f"({exc})"


def _demo_argv(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "asgp_ros.cli", "demo", "--out", str(out),
            "--domain-id", os.environ["ROS_DOMAIN_ID"], "--startup-timeout", "60", *extra]


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    return env


def _demo_children(demo_pid: int | None = None) -> list[str]:
    """Command lines of live node processes started by a demo (``asgp_ros.demo.child``):
    those of the demo ``demo_pid``, or with None the orphans (their demo is gone or they
    were re-parented)."""
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if fields[0] == "Z" or b"asgp_ros.demo.child" not in cmd:
            continue
        i = cmd.index(b"asgp_ros.demo.child")
        parent = int(cmd[i + 1])
        if demo_pid is not None:
            match = parent == demo_pid
        else:
            match = int(fields[1]) != parent or not Path(f"/proc/{parent}").exists()
        if match:
            found.append(" ".join(c.decode(errors="replace") for c in cmd))
    return found


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    proc = subprocess.run(_demo_argv(out, "--minutes", "0.4", "--train-minutes", "2",
                                     "--seed", "3", "--shared-control"),
                          env=_env(), capture_output=True, text=True, timeout=170)
    return proc, out


@pytest.mark.e2e
@pytest.mark.slow
def test_demo_runs_end_to_end(demo_run):
    proc, out = demo_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for name in ("report.md", "report.json", "demo.png", "evaluate.json", "model.npz",
                 "run_bag/metadata.yaml", "logs/hardware.log", "logs/predictor.log"):
        assert (out / name).exists(), name
    assert (out / "demo.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads((out / "report.json").read_text())
    msgs = report["messages"]
    for topic in ("joy", "joy_applied", "vo/twist", "predicted_path", "ground_truth/odom",
                  "joy_plan"):
        assert msgs[topic] > 0, f"no {topic}"
    # the predictor took its joystick from the board's measured output (joy_applied)
    predictor = report["diagnostics"]["predictor_node: prediction"]["values"]
    assert int(predictor["joy_measured"]) > 0.5 * msgs["joy_applied"]
    # the shared-control layer ran on the simulated scanner; the report compares the drive
    # with the same drive without it
    shared = report["shared_control"]
    assert int(shared["contacts_without_layer"]) >= 0 and int(shared["contacts_with_layer"]) >= 0
    assert shared["solve_p50_ms"] not in ("n/a", "nan")
    assert "## Shared control" in (out / "report.md").read_text()
    assert (out / "logs" / "shared_control.log").exists()
    # the run's bag holds the layer's decisions and the scans they were made on (a contact
    # could not be traced from it)
    assert msgs["scan"] > 0 and msgs["shared_control/status"] > 0
    from asgp_ros.recording.bags import bag_topics

    recorded = bag_topics(out / "run_bag")
    assert recorded["/scan"] == "sensor_msgs/msg/LaserScan"
    assert recorded["/shared_control/status"] == "diagnostic_msgs/msg/DiagnosticStatus"
    assert msgs["joy"] > 50 * 20  # ~100 Hz for 24 s
    assert msgs["predicted_path"] > 40  # ~5 Hz
    # the hardware counts the plans it published (its last diagnostics, a moment before the
    # end of the run: a count stuck at 0 once went unnoticed)
    sim = report["diagnostics"]["demo_hardware: simulation"]["values"]
    assert int(sim["plans"]) > 0.8 * msgs["joy_plan"] > 0
    run = report["run"]
    assert run["errors"] == []
    # every node stopped cleanly on SIGINT (a node killed wrote its threads' stacks to its log)
    assert set(run["returncodes"].values()) == {0}, {
        name: (code, run["stop_signals"].get(name),
               _tail(out / "logs" / f"{name}.log", 60))
        for name, code in run["returncodes"].items() if code != 0}
    assert all(cpu > 0 for cpu in run["cpu"].values())
    row = report["success"][0]
    assert row["horizon_s"] == 1.0 and row["online_n"] > 40
    # like with like: the same cases online and offline (same model, same run)
    assert abs(row["online_cases_success"] - row["offline_truth_success"]) <= 0.10
    assert "| 1 s |" in (out / "report.md").read_text()
    # the model is what `asgp train` makes: configuration chosen, variance calibrated; the
    # report says how often the published ellipses held the true position
    assert report["run"]["train_info"]["configuration"].startswith("s = ")
    assert "selection" in load_model(out / "model.npz").meta
    assert row["online_coverage_n"] > 40 and 0.0 <= row["online_coverage"] <= 1.0
    assert row["offline_truth_coverage"] is not None
    assert "## 95 % position ellipses" in (out / "report.md").read_text()
    # what make demo runs: the predictor adapted, and the report says so
    text = (out / "report.md").read_text()
    assert "## Adaptation" in text and "The predictor adapted online" in text
    assert report["run"]["options"]["adapt"] is True
    # the layer's own predictor adapted with it (--shared-control --adapt), and learnt
    layer = report["adaptation"]["shared_control_node"]
    assert int(layer["adapt_rows_absorbed"]) > 0 and layer["adapt_published"] in (
        "trained", "adapted")
    assert layer["overrides_seen"].isdigit() and layer["overrides_late"].isdigit()
    assert "| shared-control layer |" in text


@pytest.mark.e2e
@pytest.mark.slow
def test_a_second_demo_replaces_the_first_ones_evaluation(demo_run):
    """`make demo` twice: the second run's offline evaluation goes where the first one's is
    (it failed at the very end with 'an evaluation JSON file exists there')."""
    from asgp_ros.demo.common import evaluate_bag

    _, out = demo_run
    before = (out / "evaluate.json").stat().st_mtime_ns
    got = evaluate_bag(out / "model.npz", out / "run_bag", out / "evaluate.json", _env())
    assert got == json.loads((out / "evaluate.json").read_text())
    assert (out / "evaluate.json").stat().st_mtime_ns != before


@pytest.mark.e2e
@pytest.mark.slow
def test_demo_leaves_no_processes_and_stops_on_ctrl_c(demo_run, tmp_path):
    _, first_out = demo_run
    assert not _demo_children()  # nothing left behind by the first run
    out = tmp_path / "interrupted"
    proc = subprocess.Popen(_demo_argv(out, "--minutes", "5", "--model",
                                       str(first_out / "model.npz"), "--no-train"),
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    deadline = time.monotonic() + 90
    try:
        # let it drive until the first predictions have been scored, then Ctrl-C
        while time.monotonic() < deadline and not any("(n=" in ln and "(n=0)" not in ln
                                                      for ln in lines):
            assert proc.poll() is None, "".join(lines)
            time.sleep(0.2)
        assert len(_demo_children(proc.pid)) == 4, "the four nodes should be running"
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(5)
    text = "".join(lines)
    assert rc == 130, text[-3000:]
    assert "stopped early by SIGINT" in text
    assert (out / "run_bag" / "metadata.yaml").exists()
    assert (out / "report.md").exists()
    assert not _demo_children(proc.pid)
    assert not _demo_children()


def test_a_forced_demo_stopped_before_it_drove_keeps_the_earlier_one(tmp_path, monkeypatch):
    """``asgp demo --force`` over a complete demo, then Ctrl-C before the drive: report.md
    became one of a 0 s drive and run_bag held nothing recoverable. The earlier demo is
    set aside and put back; only a complete demo replaces it. One that failed without
    driving (its nodes not up within --startup-timeout: exit 1), or was stopped during the
    drive, deleted it: it is put back now, that run's output kept beside it."""
    from asgp_ros.common.fileio import write_marker
    from asgp_ros.demo import orchestrator

    out = tmp_path / "demo"
    out.mkdir()
    write_marker(out, "demo")
    (out / "report.md").write_text("the earlier demo\n")
    model = tmp_path / "m.npz"
    model.write_bytes(b"")
    said: list[str] = []

    def stopped(opts, into, state, say):
        (into / "report.md").write_text("a 0 s drive\n")
        state.stopped_by = "SIGINT"
        return 130

    def drove(opts, into, state, say):
        (into / "report.md").write_text("the new demo\n")
        state.drive_start_wall = 1.0
        return 0

    def stopped_driving(opts, into, state, say):
        (into / "report.md").write_text("stopped early\n")
        state.stopped_by, state.drive_start_wall = "SIGINT", 1.0
        return 130

    def never_up(opts, into, state, say):
        (into / "report.md").write_text("a 0 s drive: no node came up\n")
        return 1

    def asides() -> list[Path]:
        return sorted(tmp_path.glob("demo.unfinished.*"))

    def failed(opts, into, state, say):
        (into / "report.md").write_text("half\n")
        raise DemoError("the model cannot be used")

    opts = DemoOptions(out=out, force=True, model=model)
    monkeypatch.setattr(orchestrator, "_run_in", stopped)
    assert orchestrator.run_demo(opts, said.append) == 130
    assert (out / "report.md").read_text() == "the earlier demo\n"
    monkeypatch.setattr(orchestrator, "_run_in", failed)
    with pytest.raises(DemoError):
        orchestrator.run_demo(opts, said.append)
    assert (out / "report.md").read_text() == "the earlier demo\n"
    for run, rc, text in ((never_up, 1, "a 0 s drive: no node came up\n"),
                          (stopped_driving, 130, "stopped early\n")):
        monkeypatch.setattr(orchestrator, "_run_in", run)
        said.clear()
        assert orchestrator.run_demo(opts, said.append) == rc
        assert (out / "report.md").read_text() == "the earlier demo\n"
        assert (asides()[-1] / "report.md").read_text() == text
        assert any("did not complete" in line and str(asides()[-1]) in line for line in said)
        shutil.rmtree(asides()[-1])
    # Ctrl-C while the report of a run that drove was written: its drive was deleted
    def interrupted_report(opts, into, state, say):
        (into / "run_bag").mkdir()
        state.drive_start_wall = 1.0
        raise KeyboardInterrupt

    monkeypatch.setattr(orchestrator, "_run_in", interrupted_report)
    with pytest.raises(KeyboardInterrupt):
        orchestrator.run_demo(opts, said.append)
    assert (out / "report.md").read_text() == "the earlier demo\n"
    assert (asides()[-1] / "run_bag").is_dir()
    shutil.rmtree(asides()[-1])
    monkeypatch.setattr(orchestrator, "_run_in", drove)
    assert orchestrator.run_demo(opts, said.append) == 0
    assert (out / "report.md").read_text() == "the new demo\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo", "m.npz"]  # nothing aside
    # a name whose set-aside names do not fit a file name: refused before anything moves
    long = tmp_path / ("d" * (orchestrator.MAX_DEMO_NAME_BYTES + 1))
    long.mkdir()
    write_marker(long, "demo")
    with pytest.raises(DemoError, match="at most 235 for a demo"):
        orchestrator.run_demo(DemoOptions(out=long, force=True, model=model), said.append)
    assert sorted(p.name for p in long.iterdir()) == [".asgp-output"]
    shutil.rmtree(long)
    # a new directory that a failed run made, with nothing in it, is not left behind
    monkeypatch.setattr(orchestrator, "_run_in", lambda *a: (_ for _ in ()).throw(
        DemoError("no model")))
    with pytest.raises(DemoError):
        orchestrator.run_demo(DemoOptions(out=tmp_path / "new", model=model), said.append)
    assert not (tmp_path / "new").exists()
    # a run killed (SIGKILL) while its earlier demo was set aside: the next run says where
    aside = tmp_path / ".demo.previous.0badc0de"
    aside.mkdir()
    (aside / "report.md").write_text("the killed run's earlier demo\n")
    said.clear()
    monkeypatch.setattr(orchestrator, "_run_in", drove)
    assert orchestrator.run_demo(opts, said.append) == 0
    assert any(str(aside) in line and "kept" in line for line in said), said
    assert (aside / "report.md").read_text() == "the killed run's earlier demo\n"


@pytest.mark.ros
def test_a_demo_refuses_a_domain_in_use(rclpy_context):
    """Two demos on one domain recorded and scored each other's streams (online success
    20-35 % instead of 80 %) and both exited 0. A demo listens for other nodes before it
    starts its own, and stops when one of its outputs has a second publisher."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Joy

    from asgp_ros.common import topics
    from asgp_ros.demo import orchestrator

    monitor = rclpy.create_node("asgp_demo_monitor", context=rclpy_context)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(monitor)
    try:
        assert orchestrator._nodes_already_there(monitor, executor, seconds=0.2) == []
        other = rclpy.create_node("serial_bridge_node", context=rclpy_context)
        hidden = rclpy.create_node("_ros2cli_daemon", context=rclpy_context)
        assert orchestrator._nodes_already_there(monitor, executor, seconds=5.0) == [
            "/serial_bridge_node"]
        assert orchestrator._foreign_publishers(monitor) == []
        pubs = [n.create_publisher(Joy, topics.JOY, 10) for n in (other, hidden)]
        assert orchestrator._foreign_publishers(monitor) == [topics.JOY]
        for n, p in zip((other, hidden), pubs, strict=True):
            n.destroy_publisher(p)
            n.destroy_node()
    finally:
        executor.shutdown()
        monitor.destroy_node()


@pytest.mark.ros
def test_a_demo_that_recorded_nothing_leaves_no_bag(rclpy_context, tmp_path):
    """A fresh demo stopped before the drive left run_bag, which 'asgp bag info' read as
    'nothing recoverable'."""
    from rclpy.executors import SingleThreadedExecutor

    from asgp_ros.demo import orchestrator
    from asgp_ros.demo.monitor_node import BagRecorder, MonitorNode

    partial, final = tmp_path / ".run_bag.partial", tmp_path / "run_bag"
    node = MonitorNode(recorder=BagRecorder(partial), context=rclpy_context)
    executor = SingleThreadedExecutor(context=rclpy_context)
    executor.add_node(node)
    orchestrator._stop_monitor(node, executor, rclpy_context, partial, final)
    assert not final.exists() and not partial.exists()


_HANGUP_PROBE = r"""
import os, pty, signal, sys
from asgp_ros.demo.orchestrator import Status, _Stop

master, slave = pty.openpty()
os.dup2(slave, 1)
os.dup2(slave, 2)
stop = _Stop()
stop.install()
status = Status()
status.show("driving", force=True)
os.close(master)  # the terminal is gone: a write to it fails (EIO)
signal.raise_signal(signal.SIGHUP)
status.show("stopping", force=True)
status.end()
print("said after the hang-up", flush=True)
sys.stderr.write("and on stderr\n")
stop.restore()
sys.exit(0 if stop.reason == "SIGHUP" else 3)
"""


def test_the_demos_terminal_closing_is_a_clean_stop_not_an_error(repo_root):
    """The demo's terminal closed during the drive (an ssh session dropped): its status
    line's next write failed (EIO) and cut the stop short: nodes not stopped in order, the
    bag not closed (nothing recoverable), no report. After SIGHUP what it says goes to
    /dev/null, and the stop goes on."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", _HANGUP_PROBE], cwd=repo_root,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-500:]


@pytest.mark.ros
def test_the_hardware_nodes_board_link_goes_when_its_start_up_is_cut_short(
        rclpy_context, tmp_path, monkeypatch):
    """The demo's hardware node started its board (a pty and a link to it at ``port``),
    then built its room (a second): a Ctrl-C or SIGTERM then left the link behind, pointing
    at whichever pty next took its number. The board starts last now, and a stop right after
    it takes the link down."""
    from rclpy.parameter import Parameter

    from asgp_ros.demo import hardware
    from asgp_ros.demo.simhw import SimulatedHardware

    port = tmp_path / "joystick"
    real_start = SimulatedHardware.start_board
    order: list[str] = []

    def start_then_ctrl_c(self):
        order.append("board")
        real_start(self)
        assert port.is_symlink()
        raise KeyboardInterrupt  # a Ctrl-C as the board came up

    monkeypatch.setattr(SimulatedHardware, "start_board", start_then_ctrl_c)
    real_timer = hardware.HardwareNode.create_timer

    def timer(self, *args, **kwargs):
        order.append("timer")
        return real_timer(self, *args, **kwargs)

    monkeypatch.setattr(hardware.HardwareNode, "create_timer", timer)
    with pytest.raises(KeyboardInterrupt):
        hardware.HardwareNode(context=rclpy_context, parameter_overrides=[
            Parameter("port", value=str(port)), Parameter("width", value=64),
            Parameter("height", value=48)])
    assert not os.path.lexists(port)
    assert order[-1] == "board"  # after the rest of the start-up


def test_an_offline_evaluation_that_overruns_its_time_is_a_demo_error(tmp_path):
    """`asgp evaluate` of the drive taking longer than the demo gives it (a long drive on a
    loaded laptop, a child stuck on I/O) raised TimeoutExpired: a traceback, and the drive's
    report was not written. It is one of the evaluation's failures, which the report says."""
    import os

    from asgp_ros.demo.common import evaluate_bag

    with pytest.raises(DemoError, match="asgp evaluate took more than"):
        evaluate_bag(tmp_path / "model.npz", tmp_path / "bag", tmp_path / "e.json",
                     dict(os.environ), timeout_s=0.001)


def test_the_offline_evaluation_has_time_in_proportion_to_the_drive(tmp_path, monkeypatch):
    """A fixed 300 s stopped the evaluation of a long drive (about 1 s a minute: a 10-hour
    demo's needs ten minutes), and its report lost the offline rows: the time given grows
    with the minutes driven."""
    import types

    from asgp_ros.common import topics
    from asgp_ros.demo import report
    from asgp_ros.demo.common import RunState

    given: list[float] = []

    class SeenError(Exception):
        pass

    def evaluate(model, bag, out_json, env, timeout_s=300.0):
        given.append(timeout_s)
        raise SeenError

    monkeypatch.setattr(report, "evaluate_bag", evaluate)
    bag = tmp_path / "bag"
    bag.mkdir()
    monitor = types.SimpleNamespace(counts={topics.PREDICTED_PATH: 1, topics.VO_TWIST: 1})
    model = types.SimpleNamespace(resample_config=types.SimpleNamespace(rate_hz=5.0))
    for hours in (0.05, 10.0):
        state = RunState(options={}, domain_id=0, model_path="m.npz",
                         drive_seconds=hours * 3600.0)
        with pytest.raises(SeenError):
            report.write_report(tmp_path, state, monitor, model, bag, {}, lambda _: None)
    assert given[0] >= 300.0 and given[1] >= 300.0 + 5.0 * 600.0  # 5 s a minute, at least


def test_a_node_stopped_while_python_starts_exits_cleanly(tmp_path):
    """A Ctrl-C as the demo started its nodes: each child got SIGINT during Python's start
    (0.7 s of imports, before the node's handlers): a KeyboardInterrupt in an import, a
    traceback, exit code 1, and the demo blamed the node. The children start with the stop
    signals held; one that came before the node began ends the child with 0."""
    import os
    import signal

    from asgp_ros.demo.processes import ProcessGroup

    group = ProcessGroup(dict(os.environ), tmp_path / "logs")
    child = group.start("predictor", "asgp_ros.nodes.predictor_node:main", [])
    os.kill(child.pid, signal.SIGINT)  # at once: Python is starting
    assert child.proc.wait(timeout=60) == 0, child.log_path.read_text()[-800:]
    assert "stopped (SIGINT) before asgp_ros.nodes.predictor_node started" in \
        child.log_path.read_text()


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_node_stopped_after_its_import_and_before_its_handlers_stops(tmp_path, sig):
    """A stop that came after demo.child's check of the stops held during the import and
    before the node's own handlers was noted by a handler nothing read: the node ran on
    (the demo waited 6 s and warned; a SIGTERM from the kernel when the demo died left it
    running with no parent). The stop signals stay held until the node's handlers are in
    place, which take it."""
    import os
    import time

    from asgp_ros.demo.processes import ProcessGroup

    (tmp_path / "entry_signalled.py").write_text(
        "import os, signal\n"
        "from asgp_ros.nodes import vo_node\n\n"
        "def main():\n"
        f"    os.kill(os.getpid(), signal.{sig})  # after the import, before its handlers\n"
        "    return vo_node.main()\n")
    env = child_env(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), env.get("PYTHONPATH", "")])
    group = ProcessGroup(env, tmp_path / "logs")
    child = group.start("vo", "entry_signalled:main", [])
    try:
        deadline = time.monotonic() + 30.0
        while not group.reap(child):
            assert time.monotonic() < deadline, child.log_path.read_text()[-600:]
            time.sleep(0.05)
        assert child.returncode == 0, child.log_path.read_text()[-600:]
    finally:
        group.stop_all()


def test_a_hang_up_mutes_a_terminal_not_a_log_file(tmp_path):
    """`asgp demo > demo.log 2>&1`, then SIGHUP: its output went to /dev/null whatever it
    was, and the log lost its last lines (the report's paths, the errors)."""
    import subprocess
    import sys

    probe = (
        "import os, signal, sys\n"
        "from asgp_ros.demo.orchestrator import _Stop\n"
        "stop = _Stop(); stop.install()\n"
        "signal.raise_signal(signal.SIGHUP)\n"
        "stop.restore()\n"
        "print('after the hang-up', flush=True)\n")
    log = tmp_path / "demo.log"
    with open(log, "w") as fh:
        subprocess.run([sys.executable, "-c", probe], stdout=fh, stderr=subprocess.STDOUT,
                       check=True, timeout=60)
    assert "after the hang-up" in log.read_text()


# ------------------------------------------------------------------ a full disk

class _DiskOf:
    """The recorder's storage file on a disk that fills: once armed, a write past ``room``
    more bytes writes what fits and raises ENOSPC, as a full disk does."""

    def __init__(self, inner, room: int | None = None) -> None:
        self.inner = inner
        self.limit: int | None = None
        self.room = room
        if room is not None:
            self.arm()

    def arm(self) -> None:
        if self.limit is None:
            self.limit = self.inner.tell() + self.room

    def write(self, data) -> int:
        data = bytes(data)
        if self.limit is not None and self.inner.tell() + len(data) > self.limit:
            self.inner.write(data[:max(self.limit - self.inner.tell(), 0)])
            raise OSError(28, "No space left on device")
        return self.inner.write(data)

    def __getattr__(self, name: str):
        return getattr(self.inner, name)


@pytest.mark.ros
@pytest.mark.parametrize("when", ["writing", "closing"])
def test_a_recording_on_a_full_disk_stops_and_keeps_a_closed_bag(tmp_path, when):
    """A full disk during the demo's drive: the recorder's write raised in the monitor's
    callback (the demo aborted: `error: No space left on device`, no report, the bag left
    unclosed in a hidden .run_bag.partial). The recording stops, says why, and the bag is
    closed as it was at its last chunk on disk (the part-written chunk cut off)."""
    pytest.importorskip("rclpy")
    from rosbags.rosbag2 import Reader

    from asgp_ros.demo.monitor_node import BagRecorder
    from asgp_ros.recording.bags import recover_bag

    rec = BagRecorder(tmp_path / "bag")
    rec.add_topic("/joy", "sensor_msgs/msg/Joy")
    # 2.5 MB of room: two chunks of 1 MB, the third fails; closing: 1.5 MB, the last fails
    n, room = (400, 2_500_000) if when == "writing" else (150, 1_500_000)
    disk = rec._writer.storage.bio = _DiskOf(rec._writer.storage.bio, room)
    data = bytes(range(256)) * 40  # 10 kB a message
    for i in range(n):
        rec.write("/joy", 10**9 + i * 10**7, data)  # (raised OSError)
    rec.close()
    assert rec.failure == f"cannot write {rec.file}: No space left on device"
    assert rec.cause == "No space left on device" and rec.closed, rec.close_problem
    assert disk.inner.closed and rec.failed_closing == (when == "closing")
    kept = rec.messages
    per_chunk = 1 + 2**20 // (len(data) + 31)  # (a chunk is closed past 1 MiB)
    assert kept == (2 if when == "writing" else 1) * per_chunk, kept
    failed = 3 * per_chunk - 1 if when == "writing" else n - 1  # the write that failed
    assert rec.failed_ns == 10**9 + failed * 10**7
    assert rec.dropped == n - 1 - failed
    with Reader(tmp_path / "bag") as reader:  # indexed, with its metadata.yaml
        assert reader.message_count == kept
        stamps = [t for _, t, _ in reader.messages()]
    assert stamps == [10**9 + i * 10**7 for i in range(kept)]
    assert rec.kept_ns == (stamps[0], stamps[-1])
    assert recover_bag(tmp_path / "bag", topics=()).damage.intact
    rec.write("/joy", 5 * 10**9, data)  # after the failure: dropped, the bag untouched
    rec.close()
    with Reader(tmp_path / "bag") as reader:
        assert reader.message_count == kept


#: ``asgp demo`` whose disk fills a few seconds into the drive (the recorder's storage file
#: on a :class:`_DiskOf` armed by the first ground truth); prints the runtime directory.
_FULL_DISK_DEMO = r"""
import sys, tempfile
sys.path.insert(0, TEST_DIR)
from test_demo import _DiskOf
from asgp_ros.cli import main
from asgp_ros.demo.monitor_node import BagRecorder, MonitorNode

disks = []
init, on_truth, mkdtemp = (BagRecorder.__init__, MonitorNode._on_ground_truth_odom,
                           tempfile.mkdtemp)

def recorder(self, path):
    init(self, path)
    disks.append(_DiskOf(self._writer.storage.bio))
    self._writer.storage.bio = disks[-1]

def truth(self, msg, now):
    on_truth(self, msg, now)
    disks[-1].room = 1_600_000
    disks[-1].arm()

def made(*args, **kwargs):
    path = mkdtemp(*args, **kwargs)
    print("runtime:", path, flush=True)
    return path

BagRecorder.__init__, MonitorNode._on_ground_truth_odom = recorder, truth
tempfile.mkdtemp = made
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.e2e
@pytest.mark.slow
def test_a_demo_whose_disk_fills_during_the_drive_stops_it_and_reports(tmp_path):
    """The disk filled during the drive: `error: No space left on device` (no path), exit 2,
    no report, the recorded seconds in a hidden OUT/.run_bag.partial nothing mentioned, and
    the runtime directory (/tmp/asgp-demo-*) left behind. The recording stops, the drive
    ends (the nodes stopped), the report is written and says the recording was cut short,
    and why; exit 1; the bag is OUT/run_bag, closed; the runtime directory is removed."""
    from asgp_ros.recording.bags import recover_bag

    out = tmp_path / "demo"
    script = _FULL_DISK_DEMO.replace("TEST_DIR", repr(str(REPO / "test")))
    argv = [sys.executable, "-c", script, *_demo_argv(out, "--minutes", "0.5", "--model",
                                                      str(REPO / "docs/reproduction/models/"
                                                          "tile_asgp.npz"))[3:]]
    proc = subprocess.run(argv, env=_env(), capture_output=True, text=True, timeout=170)
    said = proc.stdout.splitlines()
    assert proc.returncode == 1, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert proc.stderr == ""
    runtime = [line.split(": ", 1)[1] for line in said if line.startswith("runtime: ")]
    assert runtime and not os.path.exists(runtime[0])
    partial = out / ".run_bag.partial"
    assert not partial.exists()
    assert any(line.startswith(f"the recording stopped: cannot write {partial}/") and
               line.endswith("No space left on device; stopping the drive")
               for line in said), proc.stdout[-3000:]
    report = json.loads((out / "report.json").read_text())
    cut = report["run"]["recording_cut"]
    assert cut.startswith("the recording stopped at ") and \
        f"s of the drive, and the drive with it: cannot write {out / 'run_bag'}: No space " \
        "left on device; " in cut, cut
    assert f"{out / 'run_bag'} keeps the drive's first " in cut and cut.endswith(", closed")
    assert report["run"]["errors"] == [cut], report["run"]["errors"]
    assert report["run"]["drive_seconds"] < 25.0  # stopped, not the 30 s asked
    assert "**The recording was cut short**" in (out / "report.md").read_text()
    assert "note: no offline evaluation: the recording was cut short" in said
    assert f"error: {cut}" in said
    damage = recover_bag(out / "run_bag", topics=()).damage
    assert damage.intact and damage.messages > 0
    assert not (out / "evaluate.json").exists()
    # the nodes were stopped by the demo, none failed
    assert set(report["run"]["returncodes"].values()) == {0}, report["run"]["returncodes"]


def test_a_demo_that_trains_on_a_full_disk_says_which_file_in_one_line(tmp_path, monkeypatch,
                                                                      capsys):
    """A demo that trains its own model on a full disk ended in a traceback, exit 1
    (BagError: .../train/tile_seed1000: cannot write bag: [Errno 28] ...)."""
    from rosbags.rosbag2 import Writer

    from asgp_ros.cli import main

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Writer, "write", full)
    out = tmp_path / "demo"
    rc = main(["demo", "--out", str(out), "--train-minutes", "0.5", "--minutes", "0.1",
               "--domain-id", os.environ["ROS_DOMAIN_ID"]])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith(
        f"error: cannot write the training drive: {out}/train/tile_seed1000: cannot write "
        "bag: "), err
    assert "No space left on device" in err
    assert not out.exists()  # nothing left of it


def test_the_demo_figure_on_a_full_disk_names_its_file(tmp_path, monkeypatch):
    """matplotlib's ENOSPC named no file (or the hidden temporary): the report said
    "the report could not be written: OSError: [Errno 28] No space left on device"."""
    from types import SimpleNamespace

    from matplotlib.figure import Figure

    from asgp_ros.demo import report

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Figure, "savefig", full)
    monitor = SimpleNamespace(truth=TruthTrack(), score=OnlineScore(), overrides=[])
    with pytest.raises(OSError, match="No space left on device") as err:
        report.figure(tmp_path / "demo.png", monitor)  # type: ignore[arg-type]
    assert err.value.filename == str(tmp_path / "demo.png")
    assert not list(tmp_path.iterdir())


def test_what_a_cut_recording_kept_is_said():
    """The words of a recording cut by a full disk: when, why, what run_bag keeps."""
    from types import SimpleNamespace

    from asgp_ros.demo import orchestrator

    def said(cut_drive=False, **recorder):
        rec = {"failure": "cannot write x: No space left on device",
               "cause": "No space left on device", "failed_ns": 130 * 10**9,
               "failed_closing": False, "messages": 5, "kept_ns": (99 * 10**9, 120 * 10**9),
               "closed": True, "close_problem": "", **recorder}
        state = orchestrator.RunState(options={}, domain_id=1, drive_start_wall=100.0)
        orchestrator._note_recording_cut(SimpleNamespace(**rec), Path("o/run_bag"), state,
                                         cut_drive)
        assert state.errors == [state.recording_cut]
        return state.recording_cut

    assert said(True) == ("the recording stopped at 30.0 s of the drive, and the drive with "
                          "it: cannot write o/run_bag: No space left on device; o/run_bag "
                          "keeps the drive's first 20.0 s (5 messages), closed")
    assert said(failed_closing=True).startswith("the recording was cut when it was closed: ")
    assert said(failed_ns=50 * 10**9, kept_ns=(40 * 10**9, 45 * 10**9)) == (
        "the recording stopped before the drive started: cannot write o/run_bag: No space "
        "left on device; o/run_bag keeps what was recorded before the drive (5 messages), "
        "closed")
    assert said(messages=0, kept_ns=None).endswith("; nothing of it could be kept")
    assert said(closed=False, close_problem="o/run_bag/metadata.yaml: No space").endswith(
        ", not closed (o/run_bag/metadata.yaml: No space): a scan reads it, and `asgp bag "
        "repair o/run_bag COPY` writes a clean copy where there is room")
    state = orchestrator.RunState(options={}, domain_id=1)
    orchestrator._note_recording_cut(SimpleNamespace(failure=""), Path("b"), state)
    assert state.errors == [] and state.recording_cut == ""
