"""The inverse model, the collision check and ``asgp replay`` under hostile input (from
an attack on them): a clear error naming the value, never a hang, a crash inside numpy, a
blocked path read as clear, or a bag that runs code."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_collision import one, wall_scan
from test_inverse import gp_model  # noqa: F401 (a fixture)

from asgp_ros.core import collision as C  # noqa: N812
from asgp_ros.core.inverse import solve
from asgp_ros.core.models import MotionModel


@pytest.fixture(scope="module")
def gp(gp_model: MotionModel) -> MotionModel:  # noqa: F811
    return gp_model


def _past(s: int = 3) -> tuple[np.ndarray, np.ndarray]:
    jp = np.column_stack([np.linspace(0.2, 0.5, s), np.linspace(-0.1, 0.2, s)])
    vp = np.column_stack([np.linspace(0.2, 0.4, s), np.linspace(-0.05, 0.1, s)])
    return jp, vp


TARGET = np.column_stack([np.linspace(0.1, 1.0, 5), np.zeros(5)])


def _within(seconds: int, fn):
    """fn(), or an AssertionError after ``seconds`` (a solver that never returns)."""
    def expired(signum, frame):
        raise AssertionError(f"still running after {seconds} s")
    old = signal.signal(signal.SIGALRM, expired)
    signal.alarm(seconds)
    try:
        return fn()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


# ---- the inverse model ---------------------------------------------------------------

@pytest.mark.parametrize("max_iter", [1.5, math.nan, 0, True])
def test_inverse_iterations_must_be_a_whole_number(gp, max_iter):
    """1.5 or NaN iterations made scipy's solver run forever (it stops when its count of
    evaluations equals the limit exactly); 0 failed inside scipy."""
    jp, vp = _past()
    with pytest.raises(ValueError, match="max_iter"):
        _within(10, lambda: solve(gp, jp, vp, TARGET, max_iter=max_iter))


def test_inverse_targets_and_windows_out_of_range_are_refused(gp):
    jp, vp = _past()
    for value in (1e30, 1e155):  # the cost was 1e61, then inf
        with pytest.raises(ValueError, match="target_xy"):
            solve(gp, jp, vp, np.full((5, 2), value))
    with pytest.raises(ValueError, match="target_xy"):  # the imaginary part was dropped
        solve(gp, jp, vp, TARGET + 1j)
    with pytest.raises(ValueError, match="vel_past"):  # 1e30 m/s: poses of 1e29 m
        solve(gp, jp, np.full_like(vp, 1e30), TARGET)
    with pytest.raises(ValueError, match="joy_past"):
        solve(gp, np.full_like(jp, 5.0), vp, TARGET)


@pytest.mark.parametrize("option, name", [({"samples": 2**40}, "samples"),
                                          ({"seed": -1}, "seed"),
                                          ({"elites": 2.5}, "elites")])
def test_inverse_cem_options_are_checked(gp, option, name):
    """80 TiB asked of numpy, numpy's own seed error, a slice of 2.5 elites."""
    jp, vp = _past()
    with pytest.raises(ValueError, match=name):
        solve(gp, jp, vp, TARGET, method="cem", max_iter=2, **option)


# ---- the collision check ---------------------------------------------------------------

@pytest.mark.parametrize("data", [np.full((100, 100), np.nan), np.full((100, 100), 256),
                                  np.full((100, 100), -7)])
def test_a_map_of_impossible_cells_is_refused_not_read_as_free(data):
    """int8 made NaN and 256 free cells: the chair in the middle of a blocked map got 0."""
    with pytest.raises(C.CollisionError, match="grid cells"):
        C.Grid(data, 0.05, (-2.5, -2.5, 0.0))
    full = C.Grid(np.full((100, 100), 100), 0.05, (-2.5, -2.5, 0.0))
    assert C.grid_check(full)(*one(0.0))[1][0] == 1.0


def test_a_scan_whose_beams_share_one_bearing_is_refused():
    """angle_increment 1e-12 put all 1081 beams on one bearing: a wall ahead read p = 0."""
    wall = wall_scan(1.0)
    assert C.scan_check(wall)(*one(0.5))[1][0] > 0.9
    with pytest.raises(C.CollisionError, match="angle_increment"):
        C.Scan(wall.ranges, -2.35, 1e-12, 0.05, 8.0)


@pytest.mark.parametrize("cov", [-np.eye(2), np.array([[0.0, 5.0], [-5.0, 0.0]]),
                                 np.array([[1.0, 2.0], [2.0, 1.0]])])
def test_a_covariance_that_is_no_covariance_is_refused(cov):
    """-I, a skew matrix or an indefinite one was clipped to zero: certainty, p = 0 beside
    a wall where +I gives 0.36."""
    check = C.scan_check(wall_scan(2.0))
    pose = np.array([[1.3, 0.0, 0.0]])
    assert check(pose, np.eye(2)[None])[1][0] > 0.3
    with pytest.raises(C.CollisionError, match="positive semi-definite"):
        check(pose, cov[None])


@pytest.mark.parametrize("res", [math.nan, math.inf, 1e308, 0.0])
def test_a_field_resolution_out_of_range_is_refused_by_name(res):
    with pytest.raises(C.CollisionError, match="resolution"):
        C.scan_check(wall_scan(2.0), resolution=res)


# ---- asgp replay -------------------------------------------------------------------------

def _joy(T):
    H, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    kw = {"seq": 0} if "seq" in H.__dataclass_fields__ else {}
    return T["sensor_msgs/msg/Joy"](header=H(stamp=Time(sec=0, nanosec=0), frame_id="js",
                                             **kw),
                                    axes=np.array([0.1, 0.0], dtype=np.float32),
                                    buttons=np.array([], dtype=np.int32))


def _bag(path: Path, extra: list[tuple[str, str]] = (), t0_ns: int = 1_700_000_000 * 10**9,
         ros1: bool = False, types: tuple[tuple[str, str], ...] = ()) -> Path:
    """/joy (5 messages) and, per ``extra`` (topic, type), one message more."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    for text, name in types:
        store.register(get_types_from_msg(text, name))
    if ros1:
        from rosbags.rosbag1 import Writer
        writer, ser = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        ser = store.serialize_cdr
    with writer:
        joy = writer.add_connection("/joy", "sensor_msgs/msg/Joy", typestore=store)
        for i in range(5):
            writer.write(joy, t0_ns + i * 50_000_000, ser(_joy(store.types),
                                                          "sensor_msgs/msg/Joy"))
        for topic, msgtype in extra:
            conn = writer.add_connection(topic, msgtype, typestore=store)
            msg = _joy(store.types) if msgtype == "sensor_msgs/msg/Joy" \
                else store.types[msgtype](count=1)
            writer.write(conn, t0_ns + 1, ser(msg, msgtype))
    return path


def _replay(repo_root: Path, *args: object) -> tuple[int, str, str]:
    env = dict(os.environ, PYTHONPATH=str(repo_root))
    p = subprocess.run([sys.executable, "-m", "asgp_ros.cli", "replay", *map(str, args),
                        "--wait-subscribers", "0"], cwd=repo_root, env=env,
                       capture_output=True, text=True, timeout=60)
    return p.returncode, p.stdout, p.stderr


def _one_line(rc: int, err: str) -> None:
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, (rc, err)


@pytest.mark.ros
def test_replay_refuses_what_it_cannot_publish_in_one_line(repo_root, tmp_path):
    bag = _bag(tmp_path / "plain")
    for target in ("/a//b", "/rosout", "/bad-name", "/clock"):
        rc, _, err = _replay(repo_root, bag, "--remap", f"/joy:={target}")
        _one_line(rc, err)
        assert "/joy" in err
    rc, _, err = _replay(repo_root, bag, "--remap", "/nope:=/x")  # played on, silently
    _one_line(rc, err)
    assert "/nope" in err
    # a bag stamped in 2065: /clock's int32 seconds would wrap negative
    rc, _, err = _replay(repo_root, _bag(tmp_path / "y2065", t0_ns=3_000_000_000 * 10**9))
    _one_line(rc, err)
    assert "2038" in err


@pytest.mark.ros
def test_replay_skips_what_a_bag_names_but_ros2_cannot_take(repo_root, tmp_path):
    """A ROS 1 topic name ROS 2 refuses is skipped with a warning (it was a traceback), and
    a type naming a package that is no ROS interface package is never imported: the bag
    named 'this', and the module's code ran."""
    rc, out, err = _replay(repo_root, _bag(tmp_path / "names.bag",
                                           [("/cam/image-raw", "sensor_msgs/msg/Joy")],
                                           ros1=True))
    assert rc == 0 and "Traceback" not in err, err
    assert "/cam/image-raw" in out + err
    rc, out, err = _replay(repo_root, _bag(tmp_path / "this_bag", [("/zen", "this/msg/Foo")],
                                           types=(("uint32 count\n", "this/msg/Foo"),)))
    assert rc == 0 and "Zen of Python" not in out + err, (rc, out, err)
    assert "this/msg/Foo" in out + err
