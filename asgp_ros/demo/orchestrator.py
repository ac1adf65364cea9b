"""``asgp demo``: train, start the nodes on simulated hardware, watch, stop, report.

Sequence:

1. **Model**: unless one is given, simulate ``train_minutes`` of driving on ``surface`` in
   the demo room (:func:`asgp_ros.sim.simulate.simulate`, a seed different from the live
   drive's), write it as a bag, and train the ASGP on it as ``asgp simulate`` +
   ``asgp train`` would
   (:func:`asgp_ros.learning.training.train_auto`: the configuration chosen, and the
   variance calibrated, on the last part of the drive, held out).
2. **Nodes**, each its own process on a demo-only ROS domain (localhost, UDPv4): the
   simulated hardware (:mod:`asgp_ros.demo.hardware`), ``serial_bridge_node`` on the
   board's pty, ``vo_node`` and ``predictor_node`` with the model; the monitor
   (:mod:`asgp_ros.demo.monitor_node`) runs in this process and records the bag.
3. **Drive**: the hardware starts driving when the bridge, VO and predictor are there;
   the run lasts ``minutes`` from then, with a live status line.
4. **Stop** (also on Ctrl-C, when a node dies, or when the recording fails: a full disk):
   SIGINT to the nodes, deadlines, SIGTERM, SIGKILL; the bag is closed and moved into place
   (a recording cut short keeps what it wrote, closed if it can be, and the report says so).
5. **Report** (:mod:`asgp_ros.demo.report`): ``asgp evaluate --truth`` on the recorded bag
   (:func:`asgp_ros.demo.common.evaluate_bag`),
   the figure, the tables, where the time went. The exit code is 0 only when every node
   produced output and the report was written.
"""

from __future__ import annotations

import contextlib
import glob
import logging
import math
import os
import resource
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, TextIO

import asgp_ros
from asgp_ros.common import topics
from asgp_ros.common.fileio import (
    DEMO_DIR,
    MARKER_NAME,
    OutputError,
    check_output,
    write_marker,
)
from asgp_ros.core.metrics import HORIZONS_S
from asgp_ros.core.modelfile import ModelFileError, load_model, save_model
from asgp_ros.core.models import MotionModel
from asgp_ros.core.scan_match import VELOCITY_SOURCES
from asgp_ros.demo.common import DemoError, RunState
from asgp_ros.demo.monitor import OnlineScore, format_status
from asgp_ros.demo.processes import ProcessGroup
from asgp_ros.demo.report import demo_horizons, write_report
from asgp_ros.learning.training import (
    HOLDOUT_FRACTION,
    AutoOptions,
    TrainingError,
    read_series,
    train_auto,
)
from asgp_ros.recording.bags import BagError, write_bag
from asgp_ros.sim.simulate import simulate

# rclpy (an optional dependency) and the monitor node built on it are imported when the
# monitor starts, so that this module imports without ROS.
if TYPE_CHECKING:
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from asgp_ros.demo.monitor_node import BagRecorder, MonitorNode

log = logging.getLogger(__name__)

Printer = Callable[[str], None]

#: what signal.signal returns and accepts
_SignalHandler = Callable[[int, FrameType | None], Any] | int | None

#: topic -> the component that publishes it (for "silent component" messages)
PRODUCERS = {
    topics.GROUND_TRUTH: "the simulated hardware (asgp_ros.demo.hardware)",
    topics.JOY: "serial_bridge_node (or the simulated board behind it)",
    topics.VO_TWIST: "vo_node",
    topics.PREDICTED_PATH: "predictor_node",
}


@dataclass(frozen=True)
class DemoOptions:
    """Settings of one demo run (the ``asgp demo`` options).

    Attributes:
        minutes: live driving time.
        out: output directory (model, bag, report, logs).
        seed: seed of the live drive (the training drive uses seed + 1000).
        train: train a model at the start (else ``model`` or ``out/model.npz`` is used).
        model: a model file to use instead of training.
        domain_id: ROS_DOMAIN_ID of the run (None: picked from the process id, 150..229).
        train_minutes: length of the simulated training drive.
        camera_rate_hz, width, height: the simulated RGB-D camera.
        plan: the hardware publishes the driver's upcoming commands on ``joy_plan`` (else
            the predictor holds the last command).
        startup_timeout_s: the drive must start within this time.
        surface: floor of the demo room.
        force: replace the output of an earlier demo at ``out`` (a directory carrying the
            demo's marker file); anything else at ``out`` is refused.
        shared_control: also run ``shared_control_node`` on the simulated scanner.
        inattention: the simulated driver's inattention (0 = attentive).
        velocity_source: ``shared_control_node``'s velocity_source.
        adapt: the predictor adapts its model online (``adapt.enabled``), and so does the
            shared-control layer's own predictor.
    """

    minutes: float = 2.0
    out: Path = Path("demo-output")
    seed: int = 0
    train: bool = True
    model: Path | None = None
    domain_id: int | None = None
    train_minutes: float = 10.0
    camera_rate_hz: float = 15.0
    width: int = 320
    height: int = 240
    plan: bool = True
    startup_timeout_s: float = 120.0
    surface: str = "tile"
    force: bool = False
    shared_control: bool = False
    inattention: float = 0.0
    velocity_source: str = "auto"
    adapt: bool = True

    def validate(self) -> None:
        if not (math.isfinite(self.minutes) and 0.05 <= self.minutes <= 600.0):
            raise DemoError(f"--minutes must be in [0.05, 600], got {self.minutes}")
        if not 0 <= self.seed <= 2**31 - 1:  # the simulated hardware node's range
            raise DemoError(f"--seed must be in [0, {2**31 - 1}], got {self.seed}")
        if self.domain_id is not None and not 1 <= self.domain_id <= 232:
            raise DemoError(f"--domain-id must be in 1..232 (Fast DDS), got {self.domain_id}")
        if not (math.isfinite(self.train_minutes) and 0.5 <= self.train_minutes <= 120.0):
            raise DemoError(f"--train-minutes must be in [0.5, 120], got {self.train_minutes}")
        if not 1.0 <= self.camera_rate_hz <= 30.0:
            raise DemoError(f"--camera-rate must be in [1, 30] Hz, got {self.camera_rate_hz}")
        if not (32 <= self.width <= 4096 and 24 <= self.height <= 4096):
            raise DemoError(f"--resolution must be between 32x24 and 4096x4096, got "
                            f"{self.width}x{self.height}")
        if not (math.isfinite(self.startup_timeout_s) and 1.0 <= self.startup_timeout_s
                <= 3600.0):
            raise DemoError(f"--startup-timeout must be in [1, 3600] s, got "
                            f"{self.startup_timeout_s}")
        if self.surface not in ("tile", "carpet", "hybrid"):
            raise DemoError(f"--surface must be tile, carpet or hybrid, got {self.surface!r}")
        if not (math.isfinite(self.inattention) and 0.0 <= self.inattention <= 1.0):
            raise DemoError(f"--inattention must be in [0, 1], got {self.inattention}")
        if self.velocity_source not in VELOCITY_SOURCES:
            raise DemoError(f"--velocity-source must be one of "
                            f"{', '.join(VELOCITY_SOURCES)}, got {self.velocity_source!r}")


def package_root() -> Path:
    """Directory that contains the ``asgp_ros`` package."""
    return Path(asgp_ros.__file__).resolve().parent.parent


def config_file(name: str) -> Path | None:
    """A node's YAML: the source tree's config/ (editable install) or share/asgp_ros/config."""
    candidates = [package_root() / "config" / name]
    prefixes = [sys.prefix, *os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)]
    candidates += [Path(p) / "share" / "asgp_ros" / "config" / name for p in prefixes if p]
    return next((c for c in candidates if c.is_file()), None)


def child_env(domain_id: int) -> dict[str, str]:
    """Environment of the node processes: the demo's ROS domain on localhost over UDPv4,
    one BLAS/OpenMP thread each (two cores for everything), this asgp_ros importable."""
    env = dict(os.environ)
    env.update({
        "ROS_DOMAIN_ID": str(domain_id),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MKL_NUM_THREADS": "1",
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "MPLBACKEND": "Agg",
    })
    env.setdefault("AMENT_PREFIX_PATH", sys.prefix)
    root = str(package_root())
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if root not in paths:
        env["PYTHONPATH"] = os.pathsep.join([root, *paths])
    return env


def silent_components(counts: dict[str, int]) -> list[str]:
    """One message per output that never arrived, naming the component that owes it."""
    return [f"{topic} never arrived: {who} produced no output"
            for topic, who in PRODUCERS.items() if counts.get(topic, 0) == 0]


def default_domain_id() -> int:
    return 150 + os.getpid() % 80


# ------------------------------------------------------------------------------------ model

def train_model(out: Path, seed: int, minutes: float, surface: str, say: Printer
                ) -> tuple[Path, dict[str, Any]]:
    """Simulate a training drive, write its bag, train the ASGP; returns (model, info)."""
    start = time.perf_counter()
    cpu0 = _self_cpu()
    bag = out / "train" / f"{surface}_seed{seed + 1000}"
    if bag.exists():
        shutil.rmtree(bag)
    say(f"training: simulating {minutes:g} min of driving on {surface} (seed {seed + 1000})")
    rec = simulate(surface, minutes, seed + 1000)
    try:
        write_bag(bag, rec)
        series = read_series([str(bag)])
    except BagError as exc:  # (a full disk: it names the bag; it was a traceback)
        raise DemoError(f"cannot write the training drive: {exc}") from exc
    say(f"training: ASGP, configuration chosen and variance calibrated on the last "
        f"{HOLDOUT_FRACTION:.0%} of the drive (as `asgp train` does), on {bag}")
    try:
        model = train_auto(series, AutoOptions(seed=seed),
                           progress=lambda ch, msg: log.debug("train %s: %s", ch, msg))
    except TrainingError as exc:
        raise DemoError(f"training on {bag} failed: {exc} (a longer --train-minutes gives "
                        "more data)") from exc
    path = out / "model.npz"
    save_model(path, model)
    info = {"bag": str(bag), "minutes": minutes, "seed": seed + 1000,
            "rows": model.meta["training_data"].get("training_rows"),
            "configuration": describe_configuration(model),
            "calibrated": not model.calibration.is_identity,
            "seconds": round(time.perf_counter() - start, 2),
            "cpu_s": round(_self_cpu() - cpu0, 2)}
    say(f"training: wrote {path}: {info['configuration']} ({info['rows']} rows, "
        f"{info['seconds']:.1f} s)")
    return path, info


def describe_configuration(model: MotionModel) -> str:
    """'s = 4, coupled, M = 160 / 160' of an ASGP, and whether it is the fallback of the
    automatic configuration (too little held-out data to choose: the paper's, uncalibrated).
    """
    fc = model.feature_config
    m_v, m_w = (getattr(ch, "num_inducing", "?") for ch in model.channels)
    text = f"s = {fc.lags}, {'coupled' if fc.coupled else 'per-axis'}, M = {m_v} / {m_w}"
    if "fallback" in model.meta.get("selection", {}):
        text += (", the paper's configuration, uncalibrated: too little held-out data to "
                 "choose")
    elif model.calibration.is_identity:
        text += ", uncalibrated"
    return text


def _self_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


# ------------------------------------------------------------------------------------ run

def _terminals() -> tuple[int, ...]:
    """Which of standard output and error are a terminal (asked before a hang-up: after it,
    a closed terminal may no longer say it is one)."""
    return tuple(fd for fd in (1, 2) if os.isatty(fd))


def _mute_terminal(fds: tuple[int, ...]) -> None:
    """After a hang-up (the terminal closed: an ssh session dropped) a write to it fails
    (EIO), and the first, the status line's, cut the demo's stop short: the nodes not
    stopped in order, the bag not closed (nothing recoverable), no report. Those of
    standard output and error that were a terminal (``fds``) go to /dev/null from here on
    (a log file they were sent to keeps what follows); what the demo writes to OUT is all
    there."""
    with contextlib.suppress(OSError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        for fd in fds:
            os.dup2(devnull, fd)
        os.close(devnull)


@contextlib.contextmanager
def _hangup_tolerated() -> Iterator[None]:
    """A hang-up outside the drive's own stop handling (:class:`_Stop`: while the nodes are
    stopped, the bag closed, the report written) mutes the terminal and lets the demo finish
    (it was a Terminated half-way: no report)."""
    if signal.getsignal(signal.SIGHUP) is signal.SIG_IGN:
        yield
        return
    fds = _terminals()
    previous = signal.signal(signal.SIGHUP, lambda _signum, _frame: _mute_terminal(fds))
    try:
        yield
    finally:
        signal.signal(signal.SIGHUP, previous)


class _Stop:
    """Signal handlers: the first Ctrl-C (or SIGTERM) asks for a clean stop."""

    def __init__(self) -> None:
        self.reason = ""
        self._old: dict[int, _SignalHandler] = {}
        self._terminals: tuple[int, ...] = ()

    def install(self) -> None:
        self._terminals = _terminals()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            if signal.getsignal(sig) is not signal.SIG_IGN:  # (kept: nohup, a background
                self._old[sig] = signal.signal(sig, self._handler)  # job's SIGINT)

    def restore(self) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)

    def _handler(self, signum: int, _frame: FrameType | None) -> None:
        if not self.reason:
            self.reason = signal.Signals(signum).name
        if signum == signal.SIGHUP:
            _mute_terminal(self._terminals)

    def __bool__(self) -> bool:
        return bool(self.reason)


def node_commands(opts: DemoOptions, model: Path, port: str) -> list[tuple[str, str, list[str]]]:
    """(name, entry point, arguments) of the node processes."""
    def params(name: str) -> list[str]:
        path = config_file(name)
        return ["--params-file", str(path)] if path is not None else []

    hw = ["--ros-args", "-p", f"seed:={opts.seed}", "-p", f"port:={port}",
          "-p", f"surface:={opts.surface}",
          "-p", f"camera_rate_hz:={float(opts.camera_rate_hz)}",
          "-p", f"width:={opts.width}", "-p", f"height:={opts.height}",
          "-p", f"plan_rows:={13 if opts.plan else 0}",
          "-p", f"inattention:={float(opts.inattention)}",
          # drive anyway a while before the demo gives up, so that a silent node is
          # named from the data (what never arrived), not guessed
          "-p", f"start_timeout_s:={0.75 * float(opts.startup_timeout_s)}"]
    return [
        ("hardware", "asgp_ros.demo.hardware:main", hw),
        ("serial_bridge", "asgp_ros.nodes.serial_bridge_node:main",
         ["--ros-args", *params("bridge.yaml"), "-p", f"port:={port}"]),
        ("vo", "asgp_ros.nodes.vo_node:main", ["--ros-args", *params("vo.yaml")]),
        ("predictor", "asgp_ros.nodes.predictor_node:main",
         ["--ros-args", *params("predictor.yaml"), "-p", f"model_path:={model}",
          "-p", f"adapt.enabled:={str(opts.adapt).lower()}"]),
    ] + ([("shared_control", "asgp_ros.nodes.shared_control_node:main",
           ["--ros-args", *params("shared_control.yaml"), "-p", f"model_path:={model}",
            "-p", f"velocity_source:={opts.velocity_source}",
            "-p", f"adapt.enabled:={str(opts.adapt).lower()}"])]
         if opts.shared_control else [])


class Status:
    """The live status line: rewritten in place on a terminal, a line every 10 s otherwise."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stdout
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = 0.0
        self._width = 0

    def show(self, line: str, force: bool = False) -> None:
        with contextlib.suppress(OSError):  # (a reader gone: see _tolerant)
            self._show(line, force)

    def _show(self, line: str, force: bool) -> None:
        now = time.monotonic()
        period = 1.0 if self.tty else 10.0
        if not force and now - self._last < period:
            return
        self._last = now
        if self.tty:
            pad = max(0, self._width - len(line))
            self.stream.write("\r" + line + " " * pad)
            self._width = len(line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def end(self) -> None:
        if self.tty and self._width:
            self._width = 0
            with contextlib.suppress(OSError):
                self.stream.write("\n")
                self.stream.flush()


def _status_line(mon: MonitorNode, elapsed: float, total: float) -> str:
    rates = {"joy": mon.rate(topics.JOY), "img": mon.rate(topics.CAMERA_INFO),
             "vo": mon.rate(topics.VO_TWIST), "path": mon.rate(topics.PREDICTED_PATH)}
    vo_state = "-" if mon.vo_ok is None else ("tracking" if mon.vo_ok else "LOST")
    lat = mon.diag_value("predictor", "last_latency_ms")
    try:
        latency = float(lat) if lat is not None else float("nan")
    except ValueError:
        latency = float("nan")
    return format_status(elapsed, total, rates, vo_state, latency, mon.score)


#: The longest name of a demo's output directory: the names it is kept under beside itself
#: (``.NAME.previous.<8 hex>``, ``NAME.unfinished.<8 hex>``) must fit a file name's 255 bytes.
MAX_DEMO_NAME_BYTES = 255 - len(".unfinished.") - 8


def _tolerant(say: Printer) -> Printer:
    """``say``, whose failure to write (stdout a pipe whose reader is gone: ``asgp demo |
    tee`` with tee killed) is no failure of the demo: the stop, the bag and the report go
    on."""
    def tolerant(line: str) -> None:
        with contextlib.suppress(OSError):
            say(line)
    return tolerant


def run_demo(opts: DemoOptions, say: Printer = print) -> int:
    """Run the demo (module docstring); returns the exit code (0 = every node produced
    output and the report was written)."""
    opts.validate()
    say = _tolerant(say)
    reuse = opts.model is None and not opts.train  # OUT/model.npz of an earlier run
    try:
        out = check_output(opts.out, DEMO_DIR, force=opts.force or reuse,
                           inputs=[opts.model] if opts.model is not None else [])
    except OutputError as exc:
        raise DemoError(str(exc)) from exc
    if len(os.fsencode(out.name)) > MAX_DEMO_NAME_BYTES:
        # found only once the earlier demo had been set aside, when this run's could not be
        raise DemoError(f"--out {out}: a name of {len(os.fsencode(out.name))} bytes; at most "
                        f"{MAX_DEMO_NAME_BYTES} for a demo (an earlier demo there, and an "
                        "unfinished run, are kept beside it as NAME.unfinished.<8 hex>)")
    # An earlier demo there (--force, or its model reused) is set aside, not written over:
    # it is removed once this one is complete (it drove, every node produced output, not
    # stopped early), and put back otherwise (this run's output beside it, unless it was
    # stopped before the drive).
    for stray in sorted(out.parent.glob(f".{glob.escape(out.name)}.previous.*")):
        # set aside by a run killed (SIGKILL, power) before it could put it back or remove it
        say(f"{stray} holds an earlier demo that a killed run set aside; it is kept (move it "
            f"back over {out}, or delete it)")
    previous = None
    if out.exists():
        previous = out.with_name(f".{out.name}.previous.{os.urandom(4).hex()}")
        os.rename(out, previous)
    domain = opts.domain_id if opts.domain_id is not None else default_domain_id()
    state = RunState(options={k: str(v) if isinstance(v, Path) else v
                              for k, v in asdict(opts).items()}, domain_id=domain)
    try:
        out.mkdir(parents=True)
        write_marker(out, "demo")
        if reuse and previous is not None and (previous / "model.npz").is_file():
            shutil.copy2(previous / "model.npz", out / "model.npz")
        rc = _run_in(opts, out, state, say)
    except BaseException as exc:
        if state.drive_start_wall is not None:
            # interrupted after it drove (Ctrl-C while the report was written): this run's
            # drive is kept, beside the earlier demo (it was deleted with the rest)
            _set_aside(out, previous, f"stopped ({type(exc).__name__})", say)
        else:
            _put_back(out, previous)
        if previous is None and out.is_dir() and set(os.listdir(out)) <= {MARKER_NAME}:
            shutil.rmtree(out, ignore_errors=True)  # made by this run, and nothing in it
        raise
    if previous is None:
        return rc
    if state.stopped_by and state.drive_start_wall is None:
        _put_back(out, previous)
        say(f"stopped before the drive: the earlier demo in {out} is kept")
    elif rc != 0 or state.stopped_by or state.drive_start_wall is None:
        # an existing demo is replaced only by a complete one: a run that failed (a node
        # never came up, or produced nothing) or was stopped early deleted a good demo
        _set_aside(out, previous, f"exit {rc}", say)
    else:
        shutil.rmtree(previous, ignore_errors=True)
    return rc


def _put_back(out: Path, previous: Path | None) -> None:
    """The earlier demo back where it was (this run's output removed)."""
    if previous is None:
        return
    shutil.rmtree(out, ignore_errors=True)
    os.rename(previous, out)


def _set_aside(out: Path, previous: Path | None, why: str, say: Printer) -> None:
    """The earlier demo back where it was, this run's output beside it (both kept)."""
    if previous is None:
        return
    aside = out.with_name(f"{out.name}.unfinished.{os.urandom(4).hex()}")
    os.rename(out, aside)
    os.rename(previous, out)
    say(f"this run did not complete ({why}): the earlier demo in {out} is kept, and this "
        f"run's output is in {aside}")


def _run_in(opts: DemoOptions, out: Path, state: RunState, say: Printer) -> int:
    """The demo's steps, its output in ``out``; the exit code."""
    model, motion_model = _demo_model(opts, out, state, say)  # 1. the model
    env = _enter_domain(state.domain_id, say)  # 2. environment of this process and the nodes
    bag_final = out / "run_bag"
    with _hangup_tolerated():  # (the drive's stop handling, inside, takes SIGHUP as a stop)
        monitor, group = _run_nodes(opts, out, model, env, state.domain_id, bag_final, state,
                                    say, demo_horizons(motion_model))
        _check_components(monitor, group, state)  # 3. what every component produced
        return _report(out, state, monitor, motion_model, bag_final, env, say)  # 4. report


def _demo_model(opts: DemoOptions, out: Path, state: RunState, say: Printer
                ) -> tuple[Path, MotionModel]:
    """The model the predictor runs: the one given, one trained now, or OUT/model.npz of an
    earlier run; its path and the model loaded (recorded in ``state``)."""
    if opts.model is not None:
        model = Path(opts.model)
    elif opts.train:
        model, state.train_info = train_model(out, opts.seed, opts.train_minutes,
                                              opts.surface, say)
    else:
        model = out / "model.npz"
    try:
        motion_model = load_model(model)
    except (ModelFileError, OSError, ValueError) as exc:
        raise DemoError(f"cannot use the model {model}: {exc}") from exc
    state.model_path = str(model.resolve())
    return model, motion_model


def _enter_domain(domain: int, say: Printer) -> dict[str, str]:
    """The nodes' environment (:func:`child_env`); this process joins the same ROS domain."""
    env = child_env(domain)
    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "FASTDDS_BUILTIN_TRANSPORTS",
                "AMENT_PREFIX_PATH"):
        os.environ[key] = env[key]
    say(f"ROS_DOMAIN_ID={domain} (watch with: ROS_DOMAIN_ID={domain} "
        "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ros2 topic list)")
    return env


def _run_nodes(opts: DemoOptions, out: Path, model: Path, env: dict[str, str], domain: int,
               bag_final: Path, state: RunState, say: Printer,
               horizons: tuple[float, ...] = HORIZONS_S) -> tuple[MonitorNode, ProcessGroup]:
    """Start the monitor (which records the bag) and the nodes, drive, and stop them all,
    whatever happens; each node's CPU time, lifetime, exit code and stop signal go to
    ``state``, the recorded bag to ``bag_final``."""
    runtime = Path(tempfile.mkdtemp(prefix="asgp-demo-"))
    port = str(runtime / "joystick")
    group = ProcessGroup(env, out / "logs")
    stop = _Stop()
    stop.install()
    bag_tmp = out / ".run_bag.partial"
    started: tuple[MonitorNode, SingleThreadedExecutor, Context] | None = None
    status = Status()
    cut_drive = False  # the recording's failure stopped the drive
    cpu_before = _self_cpu()
    t_mon = time.monotonic()
    try:
        started = monitor, executor, _ = _start_monitor(domain, bag_tmp, horizons)
        others = _nodes_already_there(monitor, executor)
        if others:  # another demo (or anything) on this domain: each would score the other
            raise DemoError(f"ROS_DOMAIN_ID {domain} is in use (nodes "
                            f"{', '.join(others[:5])}{', ...' if len(others) > 5 else ''}); "
                            "choose another with --domain-id")
        for name, entry, args in node_commands(opts, model.resolve(), port):
            if stop:  # (a Ctrl-C while the monitor started: no node to stop at once)
                break
            group.start(name, entry, args)
        say(f"started {', '.join(c.name for c in group.children)} (logs in {out / 'logs'}); "
            f"board on {port}")
        cut_drive = _drive(opts, monitor, executor, group, stop, status, state, say)
    finally:
        try:
            status.end()
            group.stop_all()
            stop.restore()
            for c in group.children:
                state.cpu[c.name] = round(c.cpu_s, 3)
                state.lifetimes[c.name] = round(c.lifetime_s, 3)
                state.returncodes[c.name] = c.returncode
                state.stop_signals[c.name] = c.signal_used
            if started is not None:
                _stop_monitor(*started, bag_tmp, bag_final)
                _note_recording_cut(started[0].recorder, bag_final, state, cut_drive)
            state.cpu["asgp demo (monitor, recorder)"] = round(_self_cpu() - cpu_before, 3)
            state.lifetimes["asgp demo (monitor, recorder)"] = round(
                time.monotonic() - t_mon, 3)
        finally:  # (the board's pty: left behind by every run that failed here)
            shutil.rmtree(runtime, ignore_errors=True)
    return monitor, group


def _note_recording_cut(recorder: BagRecorder | None, bag_final: Path, state: RunState,
                        cut_drive: bool = False) -> None:
    """A recording cut short by a write that failed (a full disk; :class:`BagRecorder`) in
    ``state``: an error, and the report's words (when, why, what the bag kept);
    ``cut_drive``: the failure stopped the drive."""
    if recorder is None or not recorder.failure:
        return
    start = state.drive_start_wall
    failed = (recorder.failed_ns or 0) * 1e-9
    if recorder.failed_closing:
        when = "was cut when it was closed"
    elif start is None or failed < start:
        when = "stopped before the drive started"
    else:
        when = f"stopped at {failed - start:.1f} s of the drive"
    if cut_drive:
        when += ", and the drive with it"
    if recorder.messages and recorder.kept_ns is not None:
        end = recorder.kept_ns[1] * 1e-9
        kept = (f"{bag_final} keeps "
                + ("what was recorded before the drive" if start is None or end < start
                   else f"the drive's first {end - start:.1f} s")
                + f" ({recorder.messages} messages)")
        if recorder.closed:
            kept += ", closed"
        else:
            kept += (f", not closed ({recorder.close_problem}): a scan reads it, and "
                     f"`asgp bag repair {bag_final} COPY` writes a clean copy where there is "
                     "room")
    else:
        kept = "nothing of it could be kept"
    state.recording_cut = (f"the recording {when}: cannot write {bag_final}: "
                           f"{recorder.cause}; {kept}")
    state.errors.append(state.recording_cut)


def _check_components(monitor: MonitorNode, group: ProcessGroup, state: RunState) -> None:
    """An error in ``state`` for each component that produced nothing, and for each node that
    exited with a failure (not by the stop signal it was sent)."""
    # stopped by the user before a component had its turn: that is no failure of it
    silent = [] if state.stopped_by else silent_components(monitor.counts)
    for c in group.children:
        if c.returncode not in (0, None) and c.signal_used in ("", "SIGINT") and \
                c.returncode != -signal.SIGINT:
            state.errors.append(f"{c.name} exited with code {c.returncode} "
                                f"(log {c.log_path}):\n{c.log_tail()}")
    state.errors[:0] = silent


def _report(out: Path, state: RunState, monitor: MonitorNode, motion_model: MotionModel,
            bag_final: Path, env: dict[str, str], say: Printer) -> int:
    """Write the report and say where it is and what went wrong; the exit code."""
    try:
        paths = write_report(out, state, monitor, motion_model, bag_final, env, say)
    except (DemoError, OSError, ValueError, RuntimeError) as exc:
        log.exception("report failed")
        state.errors.append(f"the report could not be written: {type(exc).__name__}: {exc}")
        paths = {}
    for key, p in paths.items():
        say(f"{key}: {p}")
    if state.errors:
        for e in state.errors:
            say(f"error: {e}")
        return 1
    if state.stopped_by:
        say(f"stopped early by {state.stopped_by}")
        # 130 / 143 / 129, as every command (SIGHUP, its terminal closed, gave 143)
        return 128 + int(getattr(signal.Signals, state.stopped_by, signal.SIGTERM))
    return 0


#: How long the demo listens for other nodes on its domain before it starts its own.
DOMAIN_CHECK_S = 1.0


def _nodes_already_there(monitor: MonitorNode, executor: SingleThreadedExecutor,
                         seconds: float = DOMAIN_CHECK_S) -> list[str]:
    """The nodes on the demo's domain other than its monitor, within ``seconds`` of
    discovery (at once when one shows up: absence takes the whole wait)."""
    own = (monitor.get_name(), monitor.get_namespace())
    deadline = time.monotonic() + seconds
    while True:
        found = sorted(f"{ns.rstrip('/')}/{name}" for name, ns in
                       monitor.get_node_names_and_namespaces()
                       if (name, ns) != own and not name.startswith("_"))  # not hidden ones
        if found or time.monotonic() >= deadline:
            return found
        executor.spin_once(timeout_sec=0.05)


def _foreign_publishers(monitor: MonitorNode) -> list[str]:
    """The demo's outputs that more than one node publishes (another demo that started at
    the same moment on the same domain)."""
    return [topic for topic in PRODUCERS if monitor.count_publishers(topic) > 1]


def _start_monitor(domain: int, bag_tmp: Path, horizons: tuple[float, ...] = HORIZONS_S
                   ) -> tuple[MonitorNode, SingleThreadedExecutor, Context]:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from asgp_ros.demo.monitor_node import BagRecorder, MonitorNode

    if bag_tmp.exists():
        shutil.rmtree(bag_tmp)
    from asgp_ros.nodes.runtime import log_file_arguments

    context = rclpy.context.Context()
    extra, problem = log_file_arguments()  # (a read-only log directory: no file)
    rclpy.init(args=extra, context=context, domain_id=domain,
               signal_handler_options=SignalHandlerOptions.NO)
    if problem:
        log.warning(problem)
    recorder = BagRecorder(bag_tmp)
    node = MonitorNode(recorder=recorder, score=OnlineScore(horizons), context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    return node, executor, context


def _stop_monitor(node: MonitorNode, executor: SingleThreadedExecutor, context: Context,
                  bag_tmp: Path, bag_final: Path) -> None:
    import rclpy

    recorder = node.recorder
    executor.remove_node(node)
    node.destroy_node()
    executor.shutdown()
    rclpy.utilities.try_shutdown(context=context)
    if recorder is not None:
        recorder.close()
        if bag_final.exists():
            shutil.rmtree(bag_final)
        if recorder.messages:
            os.replace(bag_tmp, bag_final)
        else:  # stopped before anything was recorded: no bag (it read "nothing recoverable")
            shutil.rmtree(bag_tmp, ignore_errors=True)


def _drive(opts: DemoOptions, mon: MonitorNode, executor: SingleThreadedExecutor,
           group: ProcessGroup, stop: _Stop,
           status: Status, state: RunState, say: Printer) -> bool:
    """Spin the monitor until the drive has lasted ``minutes`` (or a stop / failure);
    whether the recording's failure (a full disk) stopped it."""
    total = 60.0 * opts.minutes
    start_deadline = time.monotonic() + opts.startup_timeout_s
    t_start: float | None = None
    say("waiting for the nodes (bridge joy, camera, VO, predictor) before driving")
    last_wait = 0.0
    last_check = time.monotonic()
    cut = False
    while True:
        executor.spin_once(timeout_sec=0.05)
        now = time.monotonic()
        if stop:
            state.stopped_by = stop.reason
            break
        if mon.recorder is not None and mon.recorder.failure:
            say(f"the recording stopped: {mon.recorder.failure}; stopping the drive")
            cut = True
            break
        if now - last_check > 2.0:
            last_check = now
            doubled = _foreign_publishers(mon)
            if doubled:
                state.errors.append(
                    f"{', '.join(doubled)} published by more than one node: another demo on "
                    f"ROS_DOMAIN_ID {state.domain_id}? (choose another with --domain-id)")
                break
        dead = [c for c in group.poll()]
        if dead:
            for c in dead:
                state.errors.append(f"{c.name} stopped during the run (exit code "
                                    f"{c.returncode}, log {c.log_path}):\n{c.log_tail()}")
            break
        if t_start is None:
            if mon.first_truth_wall is not None:
                t_start = mon.first_truth_wall
                state.drive_start_wall = time.time() - (now - t_start)
                say(f"driving for {opts.minutes:g} min (Ctrl-C stops early)")
            elif now > start_deadline:
                state.errors.append(
                    f"the drive did not start within {opts.startup_timeout_s:.0f} s: "
                    + _waiting_for(mon))
                break
            elif now - last_wait > 10.0:
                last_wait = now
                if now - (start_deadline - opts.startup_timeout_s) > 5.0:
                    say("  still waiting: " + _waiting_for(mon))
            continue
        elapsed = now - t_start
        state.drive_seconds = elapsed
        status.show(_status_line(mon, elapsed, total))
        if elapsed >= total:
            break
    # the last paths' horizons: keep receiving the ground truth a little longer
    end = time.monotonic() + (2.5 if t_start is not None and not stop else 0.0)
    while time.monotonic() < end and not stop:
        executor.spin_once(timeout_sec=0.05)
    if t_start is not None:
        status.show(_status_line(mon, time.monotonic() - t_start, total), force=True)
    return cut


def _waiting_for(mon: MonitorNode) -> str:
    """What has not been heard from yet (for start-up messages)."""
    missing = [f"{topic} ({who})" for topic, who in PRODUCERS.items()
               if mon.counts.get(topic, 0) == 0 and topic != topics.GROUND_TRUTH]
    text = ("no messages yet on " + ", ".join(missing)) if missing else "all inputs seen"
    hw = next((e.message for name, e in mon.diag.items() if "demo_hardware" in name), None)
    return text + (f"; hardware: {hw}" if hw else "; no diagnostics from the hardware yet")
