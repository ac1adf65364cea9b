"""A node on a chair never hangs: predictor_node and vo_node as real processes.

Each node runs as its own process (``python -m``, as the console scripts do) on the test
run's DDS domain; the test drives it into a state (starting up and loading the model,
waiting for input, predicting or tracking), sends SIGINT or SIGTERM and requires the
process to be gone within the spec's safety bound of 2 s. A model path that is a FIFO
makes predictor_node refuse to start at once with an error naming the path.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from asgp_ros.demo import camera as demo_camera
from asgp_ros.nodes import conversions as conv

pytestmark = pytest.mark.ros

# A hang detector, not the 2 s exit target (issue 16), which depends on the machine's load:
# benchmarks/node_signals.py and benchmarks/soak.py measure that.
EXIT_BOUND_S = 15.0
SIGNALS = [signal.SIGINT, signal.SIGTERM]


class NodeProcess:
    """A node in a subprocess; its log lines are collected by a reader thread."""

    def __init__(self, repo_root: Path, module: str, *ros_args: str, code: str | None = None
                 ) -> None:
        """Runs ``python -m module``, or ``python -c code`` when ``code`` is given."""
        env = dict(os.environ, PYTHONPATH=str(repo_root), PYTHONUNBUFFERED="1",
                   RCUTILS_LOGGING_BUFFERED_STREAM="0")
        program = ["-c", code] if code is not None else ["-m", module]
        self.proc = subprocess.Popen(
            [sys.executable, *program, "--ros-args", *ros_args], cwd=repo_root, env=env,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, text: str, timeout: float = 60.0) -> None:
        """Wait (polling, with a deadline) until a log line contains ``text``."""
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.lines):
            assert self.proc.poll() is None, f"exited early:\n{self.output}"
            assert time.monotonic() < deadline, f"no {text!r} in:\n{self.output}"
            time.sleep(0.01)

    def stop(self, sig: int, while_waiting: Callable[[], None] = lambda: None) -> int:
        """Send ``sig``; the process must be gone within EXIT_BOUND_S. Returns its code.

        ``while_waiting`` is called in the polling loop (to keep feeding the node input).
        """
        self.proc.send_signal(sig)
        sent = time.monotonic()
        while self.proc.poll() is None:
            waited = time.monotonic() - sent
            assert waited < EXIT_BOUND_S, (
                f"{signal.Signals(sig).name}: still running {waited:.2f} s after the "
                f"signal:\n{self.output}")
            while_waiting()
            time.sleep(0.005)
        self._reader.join(timeout=10.0)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    """A small ASGP model (as test_predictor_node's)."""
    from test_predictor import make_streams

    from asgp_ros.core.features import FeatureConfig, design_matrix
    from asgp_ros.core.modelfile import save_model
    from asgp_ros.core.models import MotionModel
    from asgp_ros.core.resample import ResampleConfig, resample
    from asgp_ros.core.sparse_gp import SparseGP
    from asgp_ros.core.streams import RawStreams

    jt, joy, vt, vel = make_streams(60.0)
    res = resample(RawStreams(joy_t=jt, joy=joy, vel_t=vt, vel=vel))
    fc = FeatureConfig(lags=4)
    channels = []
    for c in (0, 1):
        X, y, _ = design_matrix(res, c, fc)
        channels.append(SparseGP(num_inducing=10, seed=0).fit(X, y, max_iter=30))
    path = tmp_path_factory.mktemp("model") / "chair.npz"
    save_model(path, MotionModel(kind="asgp", feature_config=fc,
                                 resample_config=ResampleConfig(), channels=tuple(channels)))
    return str(path)


# ---- predictor_node ----------------------------------------------------------------------

PREDICTOR = "asgp_ros.nodes.predictor_node"


def test_a_fifo_model_path_fails_fast_with_a_clear_error(repo_root, tmp_path):
    """Issue 16: the node blocked forever opening a FIFO and then ignored SIGTERM."""
    fifo = tmp_path / "chair.npz"
    os.mkfifo(fifo)
    node = NodeProcess(repo_root, PREDICTOR, "-p", f"model_path:={fifo}")
    try:
        node.proc.wait(timeout=60.0)  # a deadline for a failing start, not a timing claim
    except subprocess.TimeoutExpired:
        code = node.stop(signal.SIGTERM)
        pytest.fail(f"still starting after 60 s (SIGTERM gave {code}):\n{node.output}")
    finally:
        node.kill()
    node._reader.join(timeout=10.0)
    assert node.proc.returncode == 1, node.output
    assert f"refusing to start: cannot load the model: model file {fifo}: is a FIFO " \
           "(named pipe), not a regular file" in node.output


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("module", [PREDICTOR, "asgp_ros.nodes.shared_control_node"])
def test_a_node_on_a_stopped_simulated_clock_still_stops(repo_root, model_file, module, sig):
    """``use_sim_time`` with no /clock (a bag replay that ended, a simulator that stopped):
    no timer is ever due, and the executor's wait returns only for work. The stop signal's
    wake-up (a guard condition with no work) restarted the wait, and the node hung until
    killed (the predictor's "shutdown hang after heavy traffic": the benchmark's feeder had
    stopped its clock before the SIGINT). The signal now gives the executor a task."""
    node = NodeProcess(repo_root, module, "-p", f"model_path:={model_file}",
                       "-p", "use_sim_time:=true")
    try:
        node.wait_for("horizon")
        time.sleep(0.5)  # the main thread settles into its wait (no deadline is relied on)
        code = node.stop(sig)
    finally:
        node.kill()
    assert code == 0, node.output
    assert "Traceback" not in node.output, node.output


class _Feeder:
    """Joystick (20 Hz) and VO (5 Hz) with wall-clock stamps; collects predicted paths."""

    def __init__(self, context) -> None:
        import rclpy
        from geometry_msgs.msg import TwistStamped
        from nav_msgs.msg import Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from sensor_msgs.msg import Joy

        self.node = rclpy.create_node("signal_test_feeder", context=context)
        self.joy = self.node.create_publisher(Joy, "joy", qos_profile_sensor_data)
        self.vo = self.node.create_publisher(TwistStamped, "vo/twist", qos_profile_sensor_data)
        self.paths: list = []
        self.node.create_subscription(PathMsg, "predicted_path", self.paths.append,
                                      QoSProfile(depth=50))
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self._next_joy = self._next_vo = 0.0

    def step(self) -> None:
        """Publish what is due now and spin briefly."""
        now = time.monotonic()
        t = time.time()
        if now >= self._next_joy:
            self._next_joy = now + 0.05
            self.joy.publish(conv.joy_from_sample(t, 0.5 + 0.3 * math.sin(t), 0.2))
        if now >= self._next_vo:
            self._next_vo = now + 0.2
            self.vo.publish(conv.twist_stamped_from_sample(t, 0.4 + 0.2 * math.sin(t), 0.1))
        self.executor.spin_once(timeout_sec=0.005)

    def until(self, cond: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            self.step()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("state", ["loading", "waiting", "predicting"])
def test_predictor_node_exits_on_signals_in_every_state(repo_root, rclpy_context, model_file,
                                                        state, sig):
    node = NodeProcess(repo_root, PREDICTOR, "-p", f"model_path:={model_file}",
                       "-p", "horizon_steps:=5")
    feeder = _Feeder(rclpy_context) if state == "predicting" else None
    try:
        node.wait_for("loading model")
        if state in ("waiting", "predicting"):
            node.wait_for("horizon 5 steps")
        if feeder is not None:
            feeder.until(lambda: len(feeder.paths) >= 3, 60.0, "predicted paths")
        code = node.stop(sig, while_waiting=feeder.step if feeder else lambda: None)
    finally:
        node.kill()
        if feeder is not None:
            feeder.close()
    assert code == 0, node.output
    assert "Traceback" not in node.output, node.output


@pytest.mark.parametrize("how", ["context_shutdown", "sigint"])
def test_a_stop_while_the_model_read_blocks_ends_start_up(rclpy_context, model_file,
                                                          monkeypatch, how):
    """A read that never returns (a hung network file system) cannot keep the node alive:
    the loader is stuck, then the context shuts down, or a SIGINT comes (which only sets
    the stop flag of nodes.runtime): start-up ends either way."""
    import rclpy
    from rclpy.parameter import Parameter

    from asgp_ros.core.modelfile import ModelFileError
    from asgp_ros.nodes import predictor_node as pn
    from asgp_ros.nodes import runtime

    entered, release = threading.Event(), threading.Event()

    def stuck_read(path, kind=None):
        entered.set()
        release.wait(30.0)
        raise ModelFileError(path, "released by the test")

    monkeypatch.setattr(pn, "load_model", stuck_read)
    stopped_at: list[float] = []

    def stop() -> None:
        assert entered.wait(30.0)
        stopped_at.append(time.monotonic())
        if how == "sigint":
            os.kill(os.getpid(), signal.SIGINT)
        else:
            rclpy.try_shutdown(context=rclpy_context)

    thread = threading.Thread(target=stop)
    try:
        with runtime.StopSignals():
            thread.start()
            with pytest.raises(pn.StartupInterruptedError, match="while loading"):
                pn.PredictorNode(context=rclpy_context,
                                 parameter_overrides=[Parameter("model_path", value=model_file)])
            assert time.monotonic() - stopped_at[0] < EXIT_BOUND_S
            assert runtime.stop_requested() == (how == "sigint")
        assert not runtime.stop_requested()  # cleared with the handlers restored
    finally:
        release.set()
        thread.join()


# ---- vo_node -----------------------------------------------------------------------------

VO = "asgp_ros.nodes.vo_node"


@pytest.fixture(scope="module")
def camera():
    """K and a few rendered RGB-D frames of a chair driving an arc."""
    from asgp_ros.sim.render import RGBDRenderer
    from asgp_ros.sim.scene import build_scene, segment_drive

    scene = build_scene(preset="rich", seed=0)
    r = RGBDRenderer(scene, width=320, height=240, seed=7)  # as the demo, for UDP transport
    drive = segment_drive((0.0, 0.5, 0.3), [(0.4, 0.25, 2.0)], 15.0)
    frames = []
    for x, y, th in zip(drive.x, drive.y, drive.theta, strict=True):
        color, depth = r.render_chair(x, y, th)
        frames.append((color, np.rint(depth * 1000).astype(np.uint16)))  # 16UC1 millimetres
    return r.K, frames


class _Camera:
    """Publishes camera_info and colour/depth pairs at 15 Hz; collects vo/twist."""

    def __init__(self, context, K, frames) -> None:
        import rclpy
        from geometry_msgs.msg import TwistStamped
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image

        self.node = rclpy.create_node("signal_test_camera", context=context)
        self.color = self.node.create_publisher(Image, "camera/color/image_raw",
                                                qos_profile_sensor_data)
        self.depth = self.node.create_publisher(Image, "camera/depth/image_raw",
                                                qos_profile_sensor_data)
        self.info = self.node.create_publisher(CameraInfo, "camera/color/camera_info",
                                               qos_profile_sensor_data)
        self.twists: list = []
        self.node.create_subscription(TwistStamped, "vo/twist", self.twists.append,
                                      QoSProfile(depth=100))
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.K, self.frames = K, frames
        self.i = 0
        self._next = 0.0

    def step(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + 1.0 / 15.0
            t = time.time()
            color, depth = self.frames[self.i % len(self.frames)]
            self.i += 1
            h, w = color.shape[:2]
            self.info.publish(demo_camera.camera_info_from_matrix(t, self.K, w, h, "camera"))
            self.color.publish(demo_camera.image_from_array(t, color, "camera"))
            self.depth.publish(demo_camera.image_from_array(t, depth, "camera"))
        self.executor.spin_once(timeout_sec=0.005)

    def until(self, cond: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            self.step()

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
@pytest.mark.parametrize("state", ["waiting", "tracking"])
def test_vo_node_exits_on_signals_in_every_state(repo_root, rclpy_context, camera, state,
                                                 sig):
    node = NodeProcess(repo_root, VO)
    cam = _Camera(rclpy_context, *camera) if state == "tracking" else None
    try:
        node.wait_for("VO on /camera/color/image_raw")
        if cam is not None:
            cam.until(lambda: len(cam.twists) >= 3, 60.0, "VO twists")
        code = node.stop(sig, while_waiting=cam.step if cam else lambda: None)
    finally:
        node.kill()
        if cam is not None:
            cam.close()
    assert code == 0, node.output
    assert "Traceback" not in node.output, node.output


_SIGINT_IN_PYTHON_CODE = """
import os, signal, sys, time
import rclpy
from rclpy.utilities import ok
from asgp_ros.nodes import runtime
if sys.argv[1] == "node":
    stops = runtime.StopSignals().__enter__()
    runtime.init()
else:
    rclpy.init()
os.kill(os.getpid(), signal.SIGINT)
deadline = time.monotonic() + 10.0
spins = 0
while not runtime.stop_requested() and time.monotonic() < deadline:
    spins += 1  # plain Python code when the signal lands
print("stop requested" if runtime.stop_requested() else "no stop", flush=True)
print("context up" if ok() else "context down", flush=True)
rclpy.try_shutdown()
"""


_THREAD_MASKS = """
import os, signal
import rclpy
from asgp_ros.nodes import runtime
def blocked(tid):
    with open(f"/proc/self/task/{tid}/status") as fh:
        mask = int(next(l for l in fh if l.startswith("SigBlk")).split()[1], 16)
    return {sig for sig in (signal.SIGINT, signal.SIGTERM) if mask >> (sig - 1) & 1}
with runtime.StopSignals():
    runtime.init()
    pid = os.getpid()
    others = [int(t) for t in os.listdir("/proc/self/task") if int(t) != pid]
    print(len(others), sum(1 for t in others if len(blocked(t)) == 2), len(blocked(pid)))
    rclpy.try_shutdown()
"""


def test_threads_rclpy_starts_never_receive_the_stop_signals(repo_root):
    """rclpy.init starts a C++ thread (its deferred signal handler) that inherits the
    caller's signal mask. A SIGINT the kernel hands to it runs Python's C handler there,
    which does not make the main thread look: a main thread busy in Python code alone never
    ran the handler (11 of 120 tries, CI once). runtime.init blocks the signals in the
    threads it starts and leaves the main thread's mask as it was."""
    out = subprocess.run([sys.executable, "-c", _THREAD_MASKS], cwd=repo_root,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    others, blocking, main_blocked = (int(v) for v in out.stdout.split())
    assert others >= 1  # rclpy's thread exists: the check is not vacuous
    assert blocking == others and main_blocked == 0, out.stdout


def test_a_stop_signal_only_sets_the_flag_the_main_thread_shuts_down(repo_root):
    """Every node stops through nodes.runtime: a SIGINT raises nothing wherever the main
    thread is (with rclpy's handlers it raised KeyboardInterrupt there, and inside
    ``rclpy.task.Future.__del__`` that printed a traceback at the VO node's exit in CI),
    and nothing shuts the context down behind the main thread's back. Plain rclpy.init is
    the control: there rclpy's own thread shuts the context down, and the same SIGINT
    usually raises KeyboardInterrupt in the main thread too (once in CI, under load, it did
    not: the context was down and the loop ran to its deadline)."""
    def run(mode: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-c", _SIGINT_IN_PYTHON_CODE, mode],
                              cwd=repo_root, capture_output=True, text=True, timeout=60)

    control = run("plain")
    raised = control.returncode != 0 and "KeyboardInterrupt" in control.stderr
    assert raised or "context down" in control.stdout, control
    node = run("node")
    assert node.returncode == 0, node.stderr
    assert node.stdout.split("\n")[:2] == ["stop requested", "context up"], node.stdout
    assert "Traceback" not in node.stderr, node.stderr


_SLOW_PREDICTION = """
import sys, time
from asgp_ros.core import online
from asgp_ros.nodes import predictor_node
original = online.Predictor.predict
calls = [0]
def slow(self, *args, **kwargs):
    calls[0] += 1
    if calls[0] == 5:
        print("slow prediction: started", flush=True)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:  # Python code, where a KeyboardInterrupt would land
            pass
        print("slow prediction: finished", flush=True)
    return original(self, *args, **kwargs)
publish = predictor_node.PredictorNode._publish
def announced(self, result):
    publish(self, result)
    if calls[0] == 5:
        print("slow prediction: published", flush=True)
online.Predictor.predict = slow
predictor_node.PredictorNode._publish = announced
sys.exit(predictor_node.main())
"""


def test_a_sigint_during_a_prediction_lets_it_finish_and_publish(repo_root, rclpy_context,
                                                                 model_file):
    """The node in the middle of a callback when SIGINT comes: the callback runs to its end
    (its path is published) and the node then exits 0 without a traceback. Under rclpy's
    handlers the signal raised KeyboardInterrupt inside the prediction and shut the
    context down under it."""
    node = NodeProcess(repo_root, PREDICTOR, "-p", f"model_path:={model_file}",
                       "-p", "horizon_steps:=5", code=_SLOW_PREDICTION)
    feeder = _Feeder(rclpy_context)
    try:
        node.wait_for("horizon 5 steps")
        feeder.until(lambda: "slow prediction: started" in node.output, 60.0,
                     "the slow prediction")
        code = node.stop(signal.SIGINT, while_waiting=feeder.step)
    finally:
        node.kill()
        feeder.close()
    assert code == 0, node.output
    assert "slow prediction: published" in node.output, node.output
    assert "Traceback" not in node.output, node.output


_FROZEN_AT_SPIN = """
import gc, os, signal, sys
import rclpy
from rclpy.node import Node
from asgp_ros.nodes import runtime

class Probe(Node):
    def __init__(self):
        super().__init__("gc_probe")
        self.model = [[i] for i in range(20000)]  # what a node keeps from its start-up
        self.create_timer(0.01, self.tick)
    def tick(self):
        frozen = gc.get_freeze_count()
        tracked = len(gc.get_objects())
        print(frozen, tracked, flush=True)
        os.kill(os.getpid(), signal.SIGINT)

sys.exit(runtime.run(Probe, None, name="gc_probe", refused=()))
"""


def test_a_node_spins_with_its_start_up_objects_out_of_the_collector(repo_root):
    """A full collection visits every object the collector tracks: after rclpy, numpy and
    a model are loaded, a node's interpreter holds over 60,000, and the full collection
    Python starts now and then took tens of ms in one callback. runtime.run freezes what
    the start-up left (gc.freeze) before the node spins: the collector then looks only at
    what the node made since."""
    out = subprocess.run([sys.executable, "-c", _FROZEN_AT_SPIN], cwd=repo_root,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    frozen, tracked = (int(v) for v in out.stdout.split()[:2])
    assert frozen > 20000  # the node's own start-up objects among them
    assert tracked < 5000, out.stdout  # what the collector still visits in a collection
