"""What a node given bad start-up arguments does: refuse in one line and exit 1, never a
traceback and never a hang (every node starts through nodes.runtime.run)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from asgp_ros.core import online
from asgp_ros.nodes import polled
from asgp_ros.nodes.runtime import ros_args_problem

pytest.importorskip("rclpy")

MODEL = "docs/reproduction/models/tile_asgp.npz"


def test_ros_args_problem_names_a_params_file_rcl_could_not_open(tmp_path):
    good = tmp_path / "p.yaml"
    good.write_text("/**:\n  ros__parameters: {}\n")
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    assert ros_args_problem(["node", "--ros-args", "--params-file", str(good)]) is None
    assert "not a regular file" in ros_args_problem(
        ["node", "--ros-args", "-p", "a:=1", "--params-file", str(fifo)])
    assert "not a regular file" in ros_args_problem(
        ["node", "--ros-args", "--params-file", str(tmp_path)])
    assert "No such file" in ros_args_problem(
        ["node", "--ros-args", "--log-config-file", str(tmp_path / "absent")])
    # not a ROS argument: the program's own (after --, or before --ros-args)
    assert ros_args_problem(["node", "--params-file", str(fifo)]) is None
    assert ros_args_problem(["node", "--ros-args", "--", "--params-file", str(fifo)]) is None


def test_ros_args_problem_names_an_invalid_namespace_or_node_name():
    """A remap of the node's namespace or name to an invalid one, said in one line with
    what is wrong; another node's rule, topic remaps and valid names pass."""
    def problem(rule: str) -> str | None:
        return ros_args_problem(["node", "--ros-args", "-r", rule], "vo_node")

    assert "must not end with a '/'" in problem("__ns:=/chair1/")
    assert "(__ns:=/chair1?)" in problem("__ns:=/chair1/")
    assert "(__ns:=/chair1?)" in problem("__ns:=chair1")
    assert "repeated '/'" in problem("__ns:=//chair")
    assert "token that starts with a number" in problem("__ns:=/1chair")
    assert "'1abc' is not a valid node name" in problem("__node:=1abc")
    assert "'a/b' is not a valid node name" in problem("__name:=a/b")
    assert "'/x/' is not a valid namespace" in problem("vo_node:__ns:=/x/")
    assert "'/x/' is not a valid namespace" in ros_args_problem(
        ["node", "--ros-args", "--remap", "__ns:=/x/"])
    for fine in ("__ns:=/", "__ns:=/chair1", "__ns:=/a/b_2", "__node:=vo2",
                 "other_node:__ns:=/x/", "joy:=/chair1/joy", "/a:=b/"):
        assert problem(fine) is None, fine
    assert ros_args_problem(["node", "-r", "__ns:=/x/"]) is None  # not a ROS argument


def test_a_node_rcl_cannot_create_is_refused_in_one_line(repo_root):
    """rcl's refusal to create the node (a name rcl's argument parser let through) is a
    one-line refusal, rcl's source locations cut; any other RuntimeError of a start-up stays
    a traceback."""
    script = """if True:
        import sys
        from rclpy.impl.implementation_singleton import rclpy_implementation as impl
        from asgp_ros.nodes import runtime

        def build():
            raise impl.RCLError(sys.argv[1])

        sys.exit(runtime.run(build, ["x"], name="x", refused=()))
    """
    said = "error creating node: invalid node namespace: it is bad"
    out = subprocess.run([sys.executable, "-c", script, said + ", at /project/src/x.c:68"],
                         cwd=repo_root, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out
    assert "Traceback" not in out.stderr and f"refusing to start: {said}\n" in out.stderr
    out = subprocess.run([sys.executable, "-c", script, "something else"], cwd=repo_root,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and "Traceback" in out.stderr, out


def test_a_horizon_beyond_the_steps_of_a_path_names_horizon_s():
    """A 25 Hz model's 10 s (horizon_s within its range) was refused as 'horizon_steps
    ... got 250', a parameter the shared-control node does not have."""
    assert online.horizon_steps(2.0, 5.0) == 10
    # rounded as evaluation rounds a horizon (half up: the node's 0.5 s was 2 steps, the
    # evaluation's 3)
    assert online.horizon_steps(0.5, 5.0) == 3
    with pytest.raises(ValueError, match="shorter than one step"):
        online.horizon_steps(0.01, 5.0)
    with pytest.raises(ValueError, match=r"horizon_s 10 s is 250 steps at the model's 25 Hz"):
        online.horizon_steps(10.0, 25.0)


def test_a_drain_period_between_0_and_5_ms_is_refused():
    """joy_poll_period_s 1e-9 made a drain timer that fired at every spin: an idle node
    took 66-97 % of a core."""
    for ok in (0.0, polled.MIN_PERIOD_S, 0.25, 1.0):
        assert polled.period_problem("joy_poll_period_s", ok) is None
    for bad in (1e-9, 0.004, -0.1, 1.5, float("nan"), float("inf")):
        assert "joy_poll_period_s must be 0" in polled.period_problem("joy_poll_period_s", bad)


def _cases(tmp_path):
    fifo = tmp_path / "params.yaml"
    os.mkfifo(fifo)
    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text('/**:\n  ros__parameters:\n    horizon_s: [1.0, "a"\n')
    model = ["-p", f"model_path:={MODEL}"]
    typo_yaml = tmp_path / "typo.yaml"
    typo_yaml.write_text("/**:\n  ros__parameters:\n    footprint_widht: 0.9\n")
    node_key_yaml = tmp_path / "node_key.yaml"
    node_key_yaml.write_text("/**/shared_contrl_node:\n  ros__parameters:\n    "
                             "threshold: 0.2\n")
    empty_yaml = tmp_path / "empty.yaml"
    empty_yaml.write_text("# nothing\n")
    return {
        # rcl opened the FIFO in rclpy.init with SIGINT and SIGTERM held: unkillable
        "fifo": ("vo_node", ["--params-file", str(fifo)], "not a regular file"),
        "missing": ("serial_bridge_node", ["--params-file", str(tmp_path / "absent.yaml")],
                    "No such file"),
        "malformed": ("shared_control_node", [*model, "--params-file", str(bad_yaml)],
                      "params file"),
        # rclpy's own parameter, of another type (launch's use_sim_time:=1 is an integer)
        "sim_time_int": ("predictor_node", [*model, "-p", "use_sim_time:=1"], "use_sim_time"),
        "sim_time_int_vo": ("vo_node", ["-p", "use_sim_time:=1"], "use_sim_time"),
        # an invalid topic name reached rclpy's endpoint creation
        "topic": ("predictor_node", [*model, "-p", "path_topic:=a//b"],
                  "path_topic: 'a//b' is not a valid topic name"),
        "topic_layer": ("shared_control_node", [*model, "-p", "scan_topic:=scan 2"],
                        "scan_topic"),
        "topic_vo": ("vo_node", ["-p", "color_topic:=1color"], "color_topic"),
        "poll": ("predictor_node", [*model, "-p", "joy_poll_period_s:=1e-9"],
                 "joy_poll_period_s must be 0"),
        # a misspelt key left its setting at the default with a warning: the axis not
        # inverted for 'inverted', a 0.7 m footprint checked for 'footprint_widht'
        "typo_bridge": ("serial_bridge_node", ["-p", "inverted:=true"], "misspelt?): inverted"),
        "typo_file": ("shared_control_node", [*model, "--params-file", str(typo_yaml)],
                      "misspelt?): footprint_widht"),
        # a params file that sets nothing for the node (its name misspelt, another node's
        # file, an empty one): rcl applied none of it, and the node ran on every default
        "node_key": ("shared_control_node", [*model, "--params-file", str(node_key_yaml)],
                     "has no section for this node (/shared_control_node)"),
        "other_file": ("vo_node", ["--params-file", str(Path("config/predictor.yaml"))],
                       "has no section for this node (/vo_node)"),
        "empty_file": ("predictor_node", [*model, "--params-file", str(empty_yaml)],
                       "sections are none"),
        # a namespace ending in '/': rcl's parser took it, and the node's creation raised
        # (a traceback from each node: "node name must not start with a number"); other bad
        # names were refused in rcl's parser's words ("Expected lexeme type (18)")
        **{f"ns_slash_{node}": (node, [*model, "-r", "__ns:=/chair1/"],
                                "-r __ns:=/chair1/: '/chair1/' is not a valid namespace: "
                                "namespace must not end with a '/'")
           for node in ("predictor_node", "vo_node", "serial_bridge_node",
                        "shared_control_node")},
        "ns_this_node": ("predictor_node", [*model, "-r", "predictor_node:__ns:=/chair1/"],
                         "'/chair1/' is not a valid namespace"),
        "ns_relative": ("serial_bridge_node", ["-r", "__ns:=chair1"],
                        "'chair1' is not a valid namespace: namespace must be absolute"),
        "node_digit": ("vo_node", ["-r", "__node:=1abc"],
                       "'1abc' is not a valid node name: node name must not start with a "
                       "number"),
    }


def test_bad_start_up_arguments_are_refused_in_one_line(repo_root, tmp_path):
    """All at once (each is a process of its own): each exits 1 within the deadline with
    'refusing to start' and the reason, and no traceback."""
    cases = _cases(tmp_path)
    procs = {name: subprocess.Popen(
        [sys.executable, "-m", f"asgp_ros.nodes.{node}", "--ros-args", *args], cwd=repo_root,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for name, (node, args, _) in cases.items()}
    deadline = time.monotonic() + 120.0
    outputs = {}
    try:
        for name, proc in procs.items():
            try:
                outputs[name] = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))[0]
            except subprocess.TimeoutExpired:
                pytest.fail(f"{name}: still running after the deadline (hung)")
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    for name, (_, _, reason) in cases.items():
        out = outputs[name]
        assert procs[name].returncode == 1, (name, out)
        assert "Traceback" not in out, (name, out)
        assert "refusing to start" in out and reason in out, (name, out)


def test_a_params_file_is_matched_to_the_node_as_rcl_does(tmp_path):
    """Keys with wildcards, a namespace's nested form, another node's file, an empty one."""
    from asgp_ros.nodes.runtime import params_file_problem

    def problem(text: str, fqn: str) -> str | None:
        f = tmp_path / "p.yaml"
        f.write_text(text)
        return params_file_problem(["node", "--ros-args", "--params-file", str(f)], fqn)

    ok = {"/**:\n  ros__parameters:\n    a: 1\n": "/chair1/predictor_node",
          "/**/predictor_node:\n  ros__parameters:\n    a: 1\n": "/chair1/predictor_node",
          "chair1:\n  predictor_node:\n    ros__parameters:\n      a: 1\n":
              "/chair1/predictor_node",
          "/*/predictor_node:\n  ros__parameters:\n    a: 1\n": "/chair1/predictor_node",
          "predictor_node:\n  ros__parameters:\n    a: 1\n": "/predictor_node"}
    for text, fqn in ok.items():
        assert problem(text, fqn) is None, text
    bad = {"/**/predictor_nod:\n  ros__parameters:\n    a: 1\n": "/predictor_node",
           "chair2:\n  predictor_node:\n    ros__parameters:\n      a: 1\n":
               "/chair1/predictor_node",
           "vo_node:\n  ros__parameters:\n    a: 1\n": "/chair1/predictor_node",
           "": "/predictor_node",
           # a bare name at the top is the node in / only (rcl applied none of it under
           # /chair1: the node ran on its defaults without a word)
           "predictor_node:\n  ros__parameters:\n    b: 1\n": "/chair1/predictor_node"}
    for text, fqn in bad.items():
        assert "has no section for this node" in (problem(text, fqn) or ""), text
    assert "'/**/predictor_node' is the node in any namespace" in problem(
        "predictor_node:\n  ros__parameters:\n    b: 1\n", "/chair1/predictor_node")
    # nested 2,000 levels deep (rcl reads it): one line, not yaml's RecursionError
    deep = "".join("  " * i + f"k{i}:\n" for i in range(2000))
    deep += "  " * 2000 + "ros__parameters:\n" + "  " * 2001 + "a: 1\n"
    assert "nested too deeply" in (problem(deep, "/predictor_node") or "")
    # no params file, or one after "--" (the program's own): nothing to check
    assert params_file_problem(["node"], "/predictor_node") is None
    assert params_file_problem(["node", "--ros-args", "--", "--params-file", "x"],
                               "/predictor_node") is None


@pytest.mark.ros
def test_a_node_takes_its_own_dump_back(rclpy_context, repo_root):
    """A start-up parameter set to the value it has was refused ('restart the node to
    change it'), so the node's own dump given back with one runtime change (``ros2 param
    load``, or atomically) was refused whole. A change is still refused."""
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.predictor_node import PredictorNode
    from asgp_ros.nodes.shared_control_node import SharedControlNode
    from asgp_ros.nodes.vo_node import VONode

    model = str(repo_root / MODEL)
    for make, runtime in ((PredictorNode, ("vo_timeout_s", 0.8)),
                          (SharedControlNode, None), (VONode, None)):
        overrides = [] if make is VONode else [Parameter("model_path", value=model)]
        node = make(context=rclpy_context, parameter_overrides=overrides)
        try:
            dump = [node.get_parameter(name) for name in sorted(node._parameters)
                    if not node.describe_parameter(name).read_only]  # (rclpy's own)
            if runtime is not None:
                dump = [Parameter(runtime[0], value=runtime[1]) if p.name == runtime[0] else p
                        for p in dump]
            result = node.set_parameters_atomically(dump)
            assert result.successful, (make.__name__, result.reason)
            if runtime is not None:
                assert node.get_parameter(runtime[0]).value == runtime[1]
            name = "model_path" if make is not VONode else "color_topic"
            changed = node.set_parameters([Parameter(name, value="/elsewhere")])[0]
            assert not changed.successful and "read at start-up" in changed.reason
        finally:
            node.destroy_node()


@pytest.mark.ros
def test_a_bad_joy_axes_parameter_is_named_as_the_parameter(rclpy_context, repo_root):
    """The nodes' joy_axes refusal named the command line's --joy-axes."""
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.predictor_node import PredictorNode
    from asgp_ros.nodes.predictor_node import StartupError as PredictorStartupError
    from asgp_ros.nodes.shared_control_node import SharedControlNode
    from asgp_ros.nodes.shared_control_node import StartupError as LayerStartupError

    overrides = [Parameter("model_path", value=str(repo_root / MODEL)),
                 Parameter("joy_axes", value="0,x")]
    for make, error in ((PredictorNode, PredictorStartupError),
                        (SharedControlNode, LayerStartupError)):
        with pytest.raises(error) as info:
            make(context=rclpy_context, parameter_overrides=overrides)
        assert "joy_axes '0,x'" in str(info.value) and "--joy-axes" not in str(info.value)


@pytest.mark.ros
def test_a_path_topic_whose_ellipses_topic_is_too_long_is_refused(rclpy_context, repo_root):
    """A path_topic of 245 characters is a valid name; '<it>/uncertainty' is not: the
    ellipses' publisher raised from rclpy, naming neither, and left the node half made."""
    from rclpy.parameter import Parameter

    from asgp_ros.nodes.predictor_node import PredictorNode, StartupError

    long_name = "p" * 245
    with pytest.raises(StartupError, match="parameter path_topic: the ellipses' topic"):
        PredictorNode(context=rclpy_context, parameter_overrides=[
            Parameter("model_path", value=str(repo_root / MODEL)),
            Parameter("path_topic", value=long_name)])


@pytest.mark.ros
def test_the_advice_to_read_odometry_names_its_topic_too(rclpy_context, repo_root):
    """path_frame 'odom' (the predictor) or a map (the layer) need odometry poses: the
    refusal said to set vo_type to 'odometry', and a node doing just that subscribed to
    vo/twist for Odometry. It names vo_topic too, and the advice followed starts the node."""
    from rclpy.parameter import Parameter

    from asgp_ros.nodes import predictor_node, shared_control_node

    model = Parameter("model_path", value=str(repo_root / MODEL))
    for make, refused, asked in (
            (predictor_node.PredictorNode, predictor_node.StartupError,
             Parameter("path_frame", value="odom")),
            (shared_control_node.SharedControlNode, shared_control_node.StartupError,
             Parameter("obstacles", value="grid"))):
        with pytest.raises(refused, match="vo_topic to the odometry's topic"):
            make(context=rclpy_context, parameter_overrides=[model, asked])
        make(context=rclpy_context, parameter_overrides=[
            model, asked, Parameter("vo_type", value="odometry"),
            Parameter("vo_topic", value="vo/odom")]).destroy_node()


def test_a_node_runs_where_its_log_file_cannot_be_written(repo_root, tmp_path):
    """A disk remounted read-only or out of inodes (here a ROS_LOG_DIR that cannot be made):
    rclpy.init raised ("failed to initialize logging") and every node refused to start, so
    a chair whose disk filled had no bridge, predictor or layer after a restart. The node
    runs without its log file and says so; the console has its messages."""
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    env = dict(os.environ, ROS_LOG_DIR=str(blocked / "log"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "asgp_ros.nodes.vo_node", "--ros-args", "-p",
         "diagnostics_period_s:=0.2"], cwd=repo_root, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline and proc.poll() is None:
            line = proc.stdout.readline()
            lines.append(line)
            if "vo_node" in line and "no log file" not in line and any(
                    "no log file" in x for x in lines):
                break  # (the warning, then the node's own start-up line)
        assert proc.poll() is None, "".join(lines)
        proc.send_signal(signal.SIGINT)
        out = "".join(lines) + proc.communicate(timeout=30)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert f"no log file: {blocked / 'log'}" in out and "Traceback" not in out, out
