"""The inverse model on the simulated chair as the ground-truth plant.

Held-out drives of the simulator (a seed not used for training). Every ``--every`` seconds:
the desired path is the true path of the next 2 s (in the frame of the pose at t0); the
inverse (:func:`asgp_ros.core.inverse.solve`) gets the measured past on the model grid as the
predictor would have it (the joystick the board reports, and the simulator's Fovis-like VO
of the drive, without tracking failures, resampled by the model's own settings, its VO stamp
convention included); a copy of the simulated chair, in the same
state (its floor noise included), is driven with the solved commands (each held for its grid
step, through the board's passthrough) and its position is compared with the desired one at
1.0 and 2.0 s. Beside it, the same with:

* the recorded joystick (the oracle: what the user actually did, held per grid step);
* a naive inverse: per step, the forward speed and turn rate the target path asks for,
  divided by the chair's steady-state gains (measured on the model: full deflection held).

Usage: benchmarks/inverse_tracking.py [MODEL] [--minutes M] [--seed S] [--every E]
[--jerk W] [--effort W]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core.inverse import solve
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.resample import ResampleConfig, resample
from asgp_ros.core.rollout import rollout
from asgp_ros.core.streams import RawStreams
from asgp_ros.demo.simhw import JoystickPath
from asgp_ros.sim.chair import Chair
from asgp_ros.sim.driver import Driver
from asgp_ros.sim.sensors import SensorParams, vo_samples
from asgp_ros.sim.world import room_for_surface

#: the committed reproduction's tile model
DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "docs/reproduction/models/tile_asgp.npz"

STEP = 0.01


def _frame(pose0: np.ndarray, xy: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose0[2]), math.sin(pose0[2])
    d = xy - pose0[:2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def _drive_copy(chair: Chair, commands: np.ndarray, per_row: int, path: JoystickPath
                ) -> np.ndarray:
    """Positions at the end of each grid step, driving ``commands`` [k, 2]."""
    out = []
    for u in commands:
        for _ in range(per_row):
            st = chair.step(path.chair_input(u), STEP)
        out.append((st.x, st.y))
    return np.array(out)


def _measured_velocity(dense: np.ndarray, grid_cmd: np.ndarray, dt: float, surface: str,
                       config: ResampleConfig, rng: np.random.Generator) -> np.ndarray:
    """[n_grid, 2] VO velocity on the grid t = g dt: the simulator's Fovis-like VO of the
    true drive (no tracking failures), resampled with the model's settings; rows the
    resampler cannot give are NaN (those steps are not tested)."""
    t_dense = STEP * np.arange(dense.shape[0])
    params = dataclasses.replace(SensorParams(), failure_rate_per_min={surface: 0.0})
    vo = vo_samples(float(t_dense[-1]), t_dense, dense, np.ones(t_dense.size, dtype=bool),
                    surface, rng, params)
    t_grid = dt * np.arange(grid_cmd.shape[0])
    res = resample(RawStreams(joy_t=t_grid, joy=grid_cmd, vel_t=vo.stamp, vel=vo.vel), config)
    out = np.full((t_grid.size, 2), np.nan)
    ok = res.valid
    out[res.k[ok]] = res.vel[ok]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?", default=str(DEFAULT_MODEL),
                    help="model file (default: the committed tile model)")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=777)
    ap.add_argument("--every", type=float, default=2.0)
    ap.add_argument("--surface", default="tile")
    ap.add_argument("--jerk", type=float, default=0.005,
                    help="the inverse's jerk weight (its default)")
    ap.add_argument("--effort", type=float, default=0.0,
                    help="the inverse's effort weight (its default)")
    args = ap.parse_args(argv)
    model = load_model(args.model)
    dt = 1.0 / float(model.resample_config.rate_hz)
    per_row = round(dt / STEP)
    s, k = model.feature_config.lags, round(2.0 / dt)
    i1 = round(1.0 / dt) - 1
    rng = np.random.default_rng(args.seed)
    room = room_for_surface(args.surface)
    chair = Chair.for_room(room, seed=args.seed)
    state = chair.reset((0.0, 0.0, 0.0))
    driver = Driver(args.seed, room)
    path = JoystickPath()
    # steady-state gains of the model (full deflection held for 4 s)
    ss = []
    for u in ((1.0, 0.0), (0.0, 1.0)):
        r = rollout(model, np.zeros((s, 2)), np.zeros((s, 2)),
                    np.tile(u, (1, round(4.0 / dt), 1)), uncertainty="none")
        ss.append(r.vel[0, -1])
    gain = np.array([ss[0][0], ss[1][1]])

    # the whole drive first: states and commands on the grid, and the chair before each step
    n_grid = round(60 * args.minutes / dt)
    grid_state: list = []
    grid_cmd: list = []
    chairs: list = []
    dense: list = [(state.x, state.y, state.theta)]  # the true pose every STEP
    cmd = np.zeros(2)
    for g in range(n_grid):
        chairs.append(copy.deepcopy(chair))
        grid_state.append(state)
        for j in range(per_row):
            n = g * per_row + j
            if n % 2 == 0:
                cmd = driver.command(n * STEP, state)
            if j == 0:
                grid_cmd.append(path.reported(cmd))
            state = chair.step(path.chair_input(cmd), STEP)
            dense.append((state.x, state.y, state.theta))
    pos = np.array([(st.x, st.y) for st in grid_state])
    vel_meas = _measured_velocity(np.asarray(dense), np.asarray(grid_cmd), dt, args.surface,
                                  model.resample_config, rng)
    errs: dict[str, list[tuple[float, float]]] = {"inverse": [], "oracle": [], "naive": []}
    # the model's own prediction of each driven path: how far the model, not the solver, is off
    model_errs: dict[str, list[tuple[float, float]]] = {name: [] for name in errs}
    every = max(1, round(args.every / dt))
    with threadpool_limits(limits=1):
        for g in range(max(s, round(10 / dt)), n_grid - k - 1, every):
            st = grid_state[g]
            if abs(st.v) < 0.05 and abs(st.omega) < 0.05:
                continue  # standing still: nothing to track
            pose0 = np.array([st.x, st.y, st.theta])
            target = _frame(pose0, pos[g + 1:g + 1 + k])
            jp = np.array(grid_cmd[g - s + 1:g + 1])
            vp = vel_meas[g - s + 1:g + 1]
            if not np.all(np.isfinite(vp)):
                continue  # the resampler has no valid VO there
            # the model's t0 is the grid time g: the commands of g+1 .. g+k drive the path
            res = solve(model, jp, vp, target, jerk=args.jerk, effort=args.effort)
            oracle = np.array(grid_cmd[g + 1:g + 1 + k])
            seg = np.diff(np.vstack([[0.0, 0.0], target]), axis=0)
            v_need = np.linalg.norm(seg, axis=1) / dt
            heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
            w_need = np.diff(np.concatenate([[0.0], heading])) / dt
            naive = np.clip(np.stack([v_need / gain[0], w_need / gain[1]], axis=1), -1, 1)
            for name, U in (("inverse", res.joystick), ("oracle", oracle), ("naive", naive)):
                got = _drive_copy(copy.deepcopy(chairs[g]), U, per_row, path)
                e = np.linalg.norm(_frame(pose0, got) - target, axis=1)
                errs[name].append((float(e[i1]), float(e[-1])))
                predicted = rollout(model, jp, vp, U[None], uncertainty="none").pose[0, :, :2]
                m = np.linalg.norm(predicted - _frame(pose0, got), axis=1)
                model_errs[name].append((float(m[i1]), float(m[-1])))
    print(f"{len(errs['inverse'])} test steps on a held-out {args.minutes:g}-minute drive "
          f"({args.surface}, seed {args.seed}; inverse jerk {args.jerk:g}, effort "
          f"{args.effort:g}); error of the driven path (cm), and of the model's own prediction "
          "of that path:")
    print("method    | 1.0 s median | 1.0 s p90 | 2.0 s median | 2.0 s p90 | model 2.0 s median")
    for name, e in errs.items():
        a = 100 * np.array(e)
        mm = 100 * np.median(np.array(model_errs[name])[:, 1])
        print(f"{name:9s} | {np.median(a[:, 0]):12.1f} | {np.percentile(a[:, 0], 90):9.1f} | "
              f"{np.median(a[:, 1]):12.1f} | {np.percentile(a[:, 1], 90):9.1f} | {mm:18.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
