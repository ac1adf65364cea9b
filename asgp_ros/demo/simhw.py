"""The simulated wheelchair hardware of the demo, without ROS.

What a real installation has, simulated in one object:

* the **user** (:class:`asgp_ros.sim.driver.Driver`) moves the joystick, closed loop on
  the chair's true state;
* the **joystick interface board** (:class:`asgp_ros.sim.board.SimulatedBoard`) samples
  that joystick at 100 Hz and speaks the real link protocol on a pty (the serial bridge
  node opens it), running the firmware's rules (passthrough, overrides, watchdog, clamp);
* the **chair** (:class:`asgp_ros.sim.chair.Chair`) follows the board's analog *output*,
  as the real chair follows what the board writes to its input port, so overrides sent
  through the bridge move it;
* the **camera**: :class:`asgp_ros.sim.render.RGBDRenderer` draws the backward-looking
  RGB-D view from the chair's true pose with the shared extrinsic
  (:data:`asgp_ros.vo.extrinsics.DEFAULT_EXTRINSIC`).

Time: :meth:`SimulatedHardware.step` advances the closed loop by one chair step (10 ms;
the hand is updated every other step, 50 Hz, as in :func:`asgp_ros.sim.simulate.simulate`);
the caller paces the steps against the wall clock. Simulation time ``t`` starts at 0 when
the drive starts; the ROS node maps it to stamps ``t_start + t``.

**Look-ahead plans.** In shared control a planner proposes the chair's next joystick
commands; the paper evaluates its predictor with the future commands known. The demo
gives the predictor those commands honestly: :meth:`SimulatedHardware.snapshot` copies
the driver (with its random state) and the chair at a grid time ``g``;
:func:`look_ahead` runs the copy forward without touching the live system and returns
the joystick the bridge will report at ``g + dt, g + 2 dt, ...`` (the board's ADC and the
host calibration applied). The live drive then does the same thing, except for the board's
sampling delay (the copy feeds the chair the previous step's command, the live chair the
board's latest output), so the plan is the driver's intention, not a recording of the
future.
"""

from __future__ import annotations

import copy
import logging
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from asgp_ros.serial import safety as fw
from asgp_ros.serial.calibration import JoystickCalibration
from asgp_ros.sim.board import SimulatedBoard
from asgp_ros.sim.chair import INTERNAL_RATE_HZ, Chair, ChairParams, ChairState
from asgp_ros.sim.driver import Driver, DriverParams
from asgp_ros.sim.lidar import Lidar
from asgp_ros.sim.world import SURFACES, room_for_surface

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from asgp_ros.sim.render import RGBDRenderer

FloatArray = NDArray[np.float64]

STEP_S = 1.0 / INTERNAL_RATE_HZ
"""One closed-loop step (s): the chair's internal step."""

HAND_EVERY = 2
"""The hand (driver) is updated every HAND_EVERY steps (50 Hz)."""


@dataclass(frozen=True)
class HardwareConfig:
    """Settings of the simulated hardware.

    Attributes:
        seed: seed of the driver, the chair's floor noise and the sensor noise.
        surface: floor of the demo room: "tile", "carpet" or "hybrid".
        width, height: camera image size (px).
        scene_seed: texture and furniture seed of the rendered room.
        board_rate_hz: the board's joystick sampling rate (the firmware's is 100 Hz).
        inattention: the driver's inattention (``DriverParams.inattention``; 0 = never).
    """

    seed: int = 0
    surface: str = "tile"
    width: int = 640
    height: int = 480
    scene_seed: int = 0
    board_rate_hz: float = float(fw.SAMPLE_RATE_HZ)
    inattention: float = 0.0

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.surface not in ("tile", "carpet", "hybrid"):
            raise ValueError(f"surface must be tile, carpet or hybrid, got {self.surface!r}")
        if not (64 <= self.width <= 1920 and 48 <= self.height <= 1080):
            raise ValueError(f"image size {self.width}x{self.height} out of range")
        if not 10.0 <= self.board_rate_hz <= 1000.0:
            raise ValueError(f"board_rate_hz must be in [10, 1000], got {self.board_rate_hz}")
        DriverParams(inattention=self.inattention)  # validates it


def _firmware_output(cal: fw.AxisCal, raw: int) -> float:
    """The deflection the chair sees when the board passes ``raw`` through (firmware rules
    1, 2 and 4 for one axis; see :mod:`asgp_ros.serial.safety`)."""
    if not cal.adc_fault_low <= raw <= cal.adc_fault_high:
        return 0.0
    code, _ = cal.permille_to_dac(cal.adc_to_permille(raw))
    return cal.dac_to_deflection(code)


def adc_counts(cal: fw.AxisCal, deflection: float) -> int:
    """The board's ADC reading of a stick deflection (as ``SimulatedBoard``, no noise)."""
    d = min(1.0, max(-1.0, float(deflection)))
    return int(min(1023, max(0, round(cal.adc_neutral + d * cal.adc_span))))


class JoystickPath:
    """Stick deflection -> what the chair sees and what the bridge reports.

    Args:
        board_cal: the board firmware's (forward, turn) calibration.
        host_cal: the bridge's calibration (``config/bridge.yaml``; its defaults describe
            the same joystick).
    """

    def __init__(self, board_cal: tuple[fw.AxisCal, fw.AxisCal] | None = None,
                 host_cal: JoystickCalibration | None = None) -> None:
        self.board_cal = board_cal or fw.default_calibration()
        self.host_cal = host_cal or JoystickCalibration()

    def chair_input(self, cmd: FloatArray) -> tuple[float, float]:
        """[2] stick -> [2] deflection the chair sees in passthrough."""
        raw = [adc_counts(c, d) for c, d in zip(self.board_cal, cmd, strict=True)]
        # rule 2: both axes inside the dead band -> neutral (per axis it already is)
        return (_firmware_output(self.board_cal[0], raw[0]),
                _firmware_output(self.board_cal[1], raw[1]))

    def reported(self, cmd: FloatArray) -> tuple[float, float]:
        """[2] stick -> [2] the ``joy`` axes the bridge publishes."""
        f = adc_counts(self.board_cal[0], cmd[0])
        t = adc_counts(self.board_cal[1], cmd[1])
        return self.host_cal(f, t)


@dataclass
class Snapshot:
    """A copy of the closed loop at a step boundary (for :func:`look_ahead`)."""

    step: int
    driver: Driver
    chair: Chair
    state: ChairState
    cmd: FloatArray


class SimulatedHardware:
    """Driver, board, chair and camera (see the module docstring).

    Args:
        config: settings.
        link_path: path of the board's port (a symlink to its pty) the bridge opens; None
            for the bare pty device (see :attr:`port`).
        board: start the board (False: the chair follows the driver's stick directly
            through :class:`JoystickPath`, for tests without a pty).
    """

    def __init__(self, config: HardwareConfig | None = None,
                 link_path: str | os.PathLike[str] | None = None, board: bool = True) -> None:
        self.config = config or HardwareConfig()
        c = self.config
        self.room = room_for_surface(c.surface)
        ss = np.random.SeedSequence([c.seed, 8])
        s_chair, s_driver, s_cam, s_board = (int(s.generate_state(1)[0]) for s in ss.spawn(4))
        presets = {s: ChairParams.preset(s) for s in SURFACES}
        blocked = self.room.overlap  # the furniture stops the chair; contacts are counted
        if self.room.patches:
            self.chair = Chair(presets, seed=s_chair, surface_at=self.room.surface_at,
                               blocked=blocked)
        else:
            self.chair = Chair(presets[self.room.base_surface], seed=s_chair, blocked=blocked)
        self.driver = Driver(s_driver, self.room, duration=None,
                             params=DriverParams(inattention=c.inattention))
        # the scanner has a seed of its own, so the other streams are those of earlier demos
        s_scan = int(np.random.SeedSequence([c.seed, 9]).generate_state(1)[0])
        self.lidar = Lidar(self.room, seed=s_scan)
        self.path = JoystickPath()
        self.state = self.chair.reset((0.0, 0.0, 0.0))
        self.step_index = 0
        self.min_clearance = float("inf")  # footprint to furniture, lowest so far (m)
        self._cmd = np.zeros(2)
        self._board_cmd: tuple[float, float] = (0.0, 0.0)
        self._driving = False
        self.board = None
        if board:
            self.board = SimulatedBoard(self._stick, rate_hz=c.board_rate_hz,
                                        link_path=link_path, seed=s_board)
        self._cam_seed = s_cam
        self._renderer: RGBDRenderer | None = None

    # ---- the board -------------------------------------------------------------------

    def _stick(self, _t: float) -> tuple[float, float]:
        """The board's joystick source (called from the board's thread)."""
        return self._board_cmd

    def start_board(self) -> str:
        """Open the pty and start the board; returns the port the bridge opens."""
        if self.board is None:
            raise RuntimeError("this SimulatedHardware has no board")
        self.board.start()
        return self.board.port

    @property
    def port(self) -> str:
        return "" if self.board is None else self.board.port

    def stop(self) -> None:
        if self.board is not None:
            self.board.stop()

    # ---- the closed loop -------------------------------------------------------------

    @property
    def t(self) -> float:
        """Simulation time (s) of the current state."""
        return self.step_index * STEP_S

    def step(self) -> ChairState:
        """Advance the closed loop by one step (10 ms); returns the new state.

        The chair follows the board's analog output; without a board, the previous
        step's stick through the firmware's rules (what the board would output).
        """
        prev = self._cmd
        if self.step_index % HAND_EVERY == 0:
            self._cmd = self.driver.command(self.t, self.state)
            self._board_cmd = (float(self._cmd[0]), float(self._cmd[1]))
        if self.board is not None:
            out = self.board.output
            chair_in = (out.forward, out.turn)
        else:
            chair_in = self.path.chair_input(prev)
        self.state = self.chair.step(chair_in, STEP_S)
        st = self.state
        self.min_clearance = min(self.min_clearance, self.room.footprint_clearance(
            st.x, st.y, st.theta) - self.room.furniture_band)
        self.step_index += 1
        return self.state

    @property
    def contacts(self) -> int:
        """Contacts of the chair with the furniture so far."""
        return self.chair.contacts

    @property
    def command(self) -> FloatArray:
        """The stick position now [2] (forward, turn)."""
        return self._cmd.copy()

    def snapshot(self) -> Snapshot:
        """Copy of the closed loop now (driver with its random state, chair, command)."""
        driver, chair = copy.deepcopy((self.driver, self.chair))
        return Snapshot(self.step_index, driver, chair, self.state, self._cmd.copy())

    # ---- the camera ------------------------------------------------------------------

    @property
    def renderer(self) -> RGBDRenderer:
        """The RGB-D renderer (built on first use: about a second for the textures)."""
        if self._renderer is None:
            # OpenCV (slow to import) only once the camera is used.
            from asgp_ros.sim.render import RGBDRenderer
            from asgp_ros.sim.scene import build_scene

            scene = build_scene(self.room, "rich", seed=self.config.scene_seed)
            self._renderer = RGBDRenderer(scene, width=self.config.width,
                                          height=self.config.height, seed=self._cam_seed)
        return self._renderer

    def render(self, state: ChairState) -> tuple[NDArray[np.uint8], NDArray[np.uint16]]:
        """Colour [h, w, 3] uint8 BGR and depth [h, w] uint16 millimetres (0 = no data)
        seen from the chair at ``state``'s true pose."""
        image, depth = self.renderer.render_chair(state.x, state.y, state.theta)
        return image, depth_to_mm(depth)


def depth_to_mm(depth: NDArray[np.floating]) -> NDArray[np.uint16]:
    """Depth [h, w] in metres (0 or non-finite = no data) -> uint16 millimetres, 0 = none.

    Values beyond 65.535 m (never produced by the renderer's range limit) read as no data.
    """
    d = np.asarray(depth, dtype=np.float32)
    mm = np.rint(np.where(np.isfinite(d), d, 0.0) * 1000.0)
    mm[(mm < 0.0) | (mm > 65535.0)] = 0.0
    return mm.astype(np.uint16)


def look_ahead(snap: Snapshot, path: JoystickPath, grid_dt: float, rows: int) -> FloatArray:
    """The joystick the bridge will report at snapshot time + (r + 1) grid_dt, r < rows.

    Runs the copy in ``snap`` (which it consumes) forward exactly like
    :meth:`SimulatedHardware.step`, except that the chair is fed the stick of the previous
    step through the board's firmware rules (the live chair follows the board's output,
    which lags the stick by up to one board sample).

    Returns:
        [rows, 2] (forward, turn): the hand's stick at step ``snap.step + (r + 1) * n``
        (n = grid_dt / step) as the bridge reports it.
    """
    if rows < 1:
        raise ValueError(f"rows must be >= 1, got {rows}")
    per_row = grid_dt / STEP_S
    if abs(per_row - round(per_row)) > 1e-6 or round(per_row) < 1:
        raise ValueError(f"grid_dt {grid_dt} must be a multiple of the {STEP_S} s step")
    per_row = round(per_row)
    driver, chair, state = snap.driver, snap.chair, snap.state
    cmd = prev = snap.cmd
    out = np.zeros((rows, 2))
    last = rows * per_row
    for k in range(last + 1):
        n = snap.step + k
        if n % HAND_EVERY == 0:
            cmd = driver.command(n * STEP_S, state)
        if k and k % per_row == 0:
            out[k // per_row - 1] = path.reported(cmd)
        if k == last:
            break
        state = chair.step(path.chair_input(prev), STEP_S)
        prev = cmd
    return out
