"""The realism figure of the simulator (docs/sim_realism.png).

Top: step responses of the simulated chair on tile and carpet (several seeds each): a
forward step that is then reversed (speed, and the caster lurch in yaw rate), and a turn on
the spot. Bottom: a stretch of a simulated carpet recording, VO against the truth, with a
tracking failure during which VO repeats its last estimate.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from asgp_ros.common.fileio import atomic_path, naming
from asgp_ros.sim.chair import INTERNAL_RATE_HZ, Chair, ChairParams
from asgp_ros.sim.sensors import SensorParams
from asgp_ros.sim.simulate import simulate


def step_response(surface: str, seed: int, program: str, seconds: float = 12.0
                  ) -> np.ndarray:
    """Chair response to a scripted joystick program; returns [N, 5] (t, jf, jt, v, omega).

    Programs: ``"forward"``: 0.7 forward for 1-6 s, then 0.7 reverse for 6-9.5 s;
    ``"turn"``: 0.7 turn (left) on the spot for 1-6 s.
    """
    chair = Chair(ChairParams.preset(surface), seed=seed)
    dt = 1.0 / INTERNAL_RATE_HZ
    out = np.zeros((int(seconds * INTERNAL_RATE_HZ), 5))
    for i in range(out.shape[0]):
        t = i * dt
        if program == "forward":
            joy = (0.7 if 1.0 <= t < 6.0 else (-0.7 if 6.0 <= t < 9.5 else 0.0), 0.0)
        elif program == "turn":
            joy = (0.0, 0.7 if 1.0 <= t < 6.0 else 0.0)
        else:
            raise ValueError(f"unknown program {program!r}")
        st = chair.step(joy, dt)
        out[i] = (t + dt, joy[0], joy[1], st.v, st.omega)
    return out


def make_realism_figure(path: str | os.PathLike[str], seeds: int = 4) -> Path:
    """Draw the figure into ``path`` (PNG), atomically; returns the path."""
    import matplotlib  # slow to import: only for the figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"tile": "tab:blue", "carpet": "tab:red"}
    fig = plt.figure(figsize=(11, 8.5), constrained_layout=True)
    grid = fig.add_gridspec(3, 3, height_ratios=[1.0, 1.0, 1.1])
    ax_v = fig.add_subplot(grid[0, :2])
    ax_wl = fig.add_subplot(grid[1, :2], sharex=ax_v)
    ax_w = fig.add_subplot(grid[0:2, 2])
    for surface, colour in colours.items():
        for k in range(seeds):
            fwd = step_response(surface, k, "forward")
            turn = step_response(surface, k, "turn")
            label = surface if k == 0 else None
            ax_v.plot(fwd[:, 0], fwd[:, 3], color=colour, lw=1.0, alpha=0.8, label=label)
            ax_wl.plot(fwd[:, 0], fwd[:, 4], color=colour, lw=1.0, alpha=0.8, label=label)
            ax_w.plot(turn[:, 0], turn[:, 4], color=colour, lw=1.0, alpha=0.8, label=label)
    ax_v.plot(fwd[:, 0], fwd[:, 1], "k--", lw=1.0, label="joystick forward")
    ax_v.set_ylabel("v (m/s)")
    ax_v.set_title("Forward step 0.7, reversed at 6 s (4 seeds per surface)")
    ax_v.legend(loc="upper right", fontsize=8)
    ax_wl.set_ylabel("omega (rad/s)")
    ax_wl.set_xlabel("t (s)")
    ax_wl.set_title("Yaw rate in the same run: caster lurch when the travel reverses")
    ax_w.plot(turn[:, 0], turn[:, 2], "k--", lw=1.0, label="joystick turn")
    ax_w.set_title("Turn on the spot, 0.7")
    ax_w.set_xlabel("t (s)")
    ax_w.set_ylabel("omega (rad/s)")
    ax_w.legend(loc="upper right", fontsize=8)

    # A recording stretch with a VO tracking failure.
    sp = SensorParams(failure_rate_per_min={"tile": 0.4, "carpet": 6.0, "hybrid": 2.0})
    rec = simulate("carpet", 1.5, 11, sensor_params=sp)
    ax = fig.add_subplot(grid[2, :])
    if rec.failures.shape[0]:
        f0, f1 = rec.failures[0]
    else:  # pragma: no cover - the seed above has failures
        f0, f1 = 40.0, 40.0
    lo, hi = max(0.0, f0 - 8.0), min(rec.duration, f1 + 8.0)
    m = (rec.truth_t >= lo) & (rec.truth_t <= hi)
    mv = (rec.vo_t >= lo) & (rec.vo_t <= hi)
    ax.plot(rec.truth_t[m], rec.truth[m, 3], color="0.5", lw=1.2, label="true v")
    ax.plot(rec.truth_t[m], rec.truth[m, 4], color="0.75", lw=1.2, label="true omega")
    ax.step(rec.vo_t[mv], rec.vo[mv, 0], where="post", color="tab:green", marker=".",
            lw=1.0, label="VO v (4-7 Hz)")
    ax.step(rec.vo_t[mv], rec.vo[mv, 1], where="post", color="tab:purple", marker=".",
            lw=1.0, label="VO omega")
    for a, b in rec.failures:
        if b >= lo and a <= hi:
            ax.axvspan(a, b, color="tab:orange", alpha=0.25)
    ax.axvspan(0, 0, color="tab:orange", alpha=0.25, label="tracking failure")
    ax.set_xlim(lo, hi)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("m/s, rad/s")
    ax.set_title("Simulated carpet recording: VO repeats its last estimate while tracking "
                 "is lost")
    ax.legend(loc="upper left", fontsize=8, ncol=5)
    path = Path(path)
    with atomic_path(path) as tmp, naming(tmp):
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
