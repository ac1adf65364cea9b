"""The demo's end-of-run report: figure, success-rate table, where the time went.

Written to the output directory (every file atomically):

* ``demo.png``: the driven path (ground truth) with the predicted paths placed at the true
  pose of their prediction time and their 95% position ellipses; a zoom on the sharpest
  manoeuvre; the online error at 1.0 s over time;
* ``evaluate.json``: ``asgp evaluate MODEL run_bag --truth --json`` on the run's own bag;
* ``report.md`` and ``report.json``: the success rates online (each published path scored
  against the simulator's ground truth, :mod:`asgp_ros.demo.monitor`) next to the offline
  evaluation of the same run (against VO as in the paper, and against ground truth), on
  all paths and on exactly the offline evaluation's cases; how often the published 95%
  position ellipses held the true position (online, from the uncertainty markers, and
  offline); CPU seconds per process; per-message latencies.

Like with like: online and ``--truth`` offline both compare the predicted (x, y) at the
horizon with the true displacement expressed in base_link at t0. The case sets differ
slightly (the node predicts whenever its s-step past window is valid; the offline
evaluation also needs the k future grid steps valid, for its VO reference): the column
"online, offline cases" restricts the online paths to the offline case set.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from asgp_ros.common import topics
from asgp_ros.common.fileio import atomic_path, atomic_write_text, naming
from asgp_ros.core import metrics
from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M, horizon_key
from asgp_ros.core.models import MotionModel, get_kind
from asgp_ros.core.rollout import rollout
from asgp_ros.demo.common import DemoError, RunState, evaluate_bag, evaluate_timeout
from asgp_ros.demo.monitor import OnlineScore, PathRecord
from asgp_ros.demo.simhw import STEP_S, HardwareConfig, SimulatedHardware
from asgp_ros.learning.training import read_series
from asgp_ros.recording.bags import BagError
from asgp_ros.sim.world import Room, room_for_surface

# matplotlib (slow to import) is imported by figure() alone.
if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from asgp_ros.demo.monitor_node import MonitorNode  # rclpy: the demo's process only

log = logging.getLogger(__name__)


def demo_horizons(model: MotionModel) -> tuple[float, ...]:
    """The horizons a demo scores with ``model``: the paper's, where its grid has them
    (``asgp evaluate``'s rule: a 2.5 Hz model is scored at 1.2, 1.6 and 2.0 s; its paths
    have no pose at 1.0 s, and the figures held there were labelled 1.0 s)."""
    return metrics.scored_horizons(HORIZONS_S, float(model.resample_config.rate_hz))


def offline_cases(bag: Path, model: MotionModel) -> dict[str, set[int]]:
    """Grid index of t0 (= t_{t-1}) of every offline evaluation case, per horizon key."""
    series = read_series([str(bag)], resample_config=model.resample_config,
                         truth_topic=topics.BAG_GROUND_TRUTH)
    rate = float(model.resample_config.rate_hz)
    lags = int(model.feature_config.lags)
    out: dict[str, set[int]] = {}
    for h in demo_horizons(model):
        k = metrics.horizon_steps([h], rate)[0]  # (as evaluation rounds it)
        cases: set[int] = set()
        for s in series:
            idx = metrics.case_indices(s.res.segment, lags, k)
            cases.update(round(float(t) * rate) for t in s.res.t[idx - 1])
        out[horizon_key(h)] = cases
    return out


def offline_held(bag: Path, model: MotionModel) -> dict[str, dict[str, float]]:
    """Offline success against ground truth with the joystick held at J_{t-1} over the
    horizon (the assumption of a predictor without a plan), on the evaluation's cases.

    Same cases, rollout and ground-truth displacement as ``asgp evaluate --truth``
    (:mod:`asgp_ros.learning.evaluation`); only the future joystick differs.
    """
    series = read_series([str(bag)], resample_config=model.resample_config,
                         truth_topic=topics.BAG_GROUND_TRUTH)
    rate = float(model.resample_config.rate_hz)
    s = int(model.feature_config.lags)
    out: dict[str, dict[str, float]] = {}
    for h in demo_horizons(model):
        k = metrics.horizon_steps([h], rate)[0]  # (as evaluation rounds it)
        errors = []
        for ser in series:
            res = ser.res
            idx = metrics.case_indices(res.segment, s, k)
            idx = idx[res.truth_valid[idx - 1] & res.truth_valid[idx + k - 1]]
            if idx.size == 0:
                continue
            held = np.repeat(res.joy[idx - 1][:, None, :], k, axis=1)  # [N, k, 2]
            ro = rollout(model, metrics.windows(res.joy, idx, -s, s),
                         metrics.windows(res.vel, idx, -s, s), held, uncertainty="none")
            gt = metrics.relative_displacement(res.truth[idx - 1, :3],
                                               res.truth[idx + k - 1, :3])
            errors.append(np.hypot(*(np.asarray(ro.pose)[:, -1, :2] - gt).T))
        e = np.concatenate(errors) if errors else np.zeros(0)
        out[horizon_key(h)] = {
            "success_rate": float(np.mean(e <= THRESHOLD_M)) if e.size else float("nan"),
            "cases": int(e.size),
            "median_error_m": float(np.median(e)) if e.size else float("nan")}
    return out


def success_table(score: OnlineScore, evaluation: dict[str, Any] | None,
                  cases: dict[str, set[int]] | None, dt: float,
                  held: dict[str, dict[str, float]] | None = None, *,
                  uncertainty: bool = True) -> list[dict[str, Any]]:
    """One row per horizon: online (all, on offline cases) and offline (truth, VO, and
    truth with the held command)."""
    rows = []
    for h in score.horizons:
        key = horizon_key(h)
        rate, n = score.success(h)
        err = score.errors(h)
        row: dict[str, Any] = {
            "horizon_s": h, "online_success": rate, "online_n": n,
            "online_median_error_m": float(np.median(err)) if err.size else float("nan"),
        }
        if held is not None and key in held:
            row.update(offline_held_success=held[key]["success_rate"],
                       offline_held_n=held[key]["cases"],
                       offline_held_median_error_m=held[key]["median_error_m"])
        # a model without uncertainty (a baseline) publishes zero ellipses: no coverage
        cov, cov_n = score.coverage(h) if uncertainty else (math.nan, 0)
        row.update(online_coverage=cov, online_coverage_n=cov_n)
        if cases is not None:
            r2, n2 = score.success(h, t0_filter=cases[key], dt=dt)
            row.update(online_cases_success=r2, online_cases_n=n2)
            c2, cn2 = (score.coverage(h, t0_filter=cases[key], dt=dt) if uncertainty
                       else (math.nan, 0))
            row.update(online_cases_coverage=c2, online_cases_coverage_n=cn2)
        if evaluation is not None and key in evaluation.get("horizons", {}):
            e = evaluation["horizons"][key]
            row.update(offline_vo_success=e["success_rate"], offline_cases=e["cases"],
                       offline_vo_median_error_m=e["median_error_m"],
                       offline_vo_coverage=e.get("coverage_95"))
            if "truth" in e:
                row.update(offline_truth_success=e["truth"]["success_rate"],
                           offline_truth_n=e["truth"]["cases"],
                           offline_truth_median_error_m=e["truth"]["median_error_m"],
                           offline_truth_coverage=e["truth"].get("coverage_95"))
        rows.append(row)
    return rows


def _pct(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(float(x)) else f"{100 * float(x):.1f}%"


def _cm(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(float(x)) else f"{100 * float(x):.1f} cm"


def markdown(state: RunState, rows: list[dict[str, Any]], cpu: list[dict[str, Any]],
             latencies: list[dict[str, Any]], extras: dict[str, Any],
             shared: list[str] | None = None, adaptation: list[str] | None = None,
             adapted: bool | None = None) -> str:
    """The report's text; ``adapted``: the predictor adapted (default: the run's option)."""
    lines = ["# asgp demo report", ""]
    o = state.options
    lines.append(
        f"Live drive of {state.drive_seconds:.0f} s on {o['surface']} (seed {o['seed']}), "
        f"camera {o['width']}x{o['height']} at {o['camera_rate_hz']:g} Hz, future joystick "
        + ("from the driver's look-ahead on `joy_plan`" if o["plan"]
           else "held (no plan)")
        + f", ROS_DOMAIN_ID {state.domain_id}. Model: `{state.model_path}`"
        + (f" ({state.train_info['configuration']}, trained on a simulated "
           f"{state.train_info['minutes']:g}-minute drive, seed {state.train_info['seed']})"
           if state.train_info.get("configuration") else "") + ".")
    if state.stopped_by:
        lines.append(f"Stopped early by {state.stopped_by}.")
    if state.recording_cut:
        lines += ["", f"**The recording was cut short**: {state.recording_cut}. The bag was "
                  "not evaluated offline (its columns below are empty): the figures are the "
                  "online ones, of every path published during the drive."]
    plan = bool(o["plan"])
    same = "offline `--truth`" if plan else "offline, held command"
    lines += ["", "## Success rate (position error <= 10 cm at the horizon)", "",
              f"| horizon | online vs truth | online, offline cases | {same} | "
              "offline vs VO (paper) | online median error | offline median (truth) |",
              "|---|---|---|---|---|---|---|"]
    pre = "offline_truth" if plan else "offline_held"
    for r in rows:
        lines.append(
            f"| {r['horizon_s']:g} s | {_pct(r['online_success'])} (n={r['online_n']}) | "
            f"{_pct(r.get('online_cases_success'))} (n={r.get('online_cases_n', 0)}) | "
            f"{_pct(r.get(pre + '_success'))} (n={r.get(pre + '_n', 0)}) | "
            f"{_pct(r.get('offline_vo_success'))} (n={r.get('offline_cases', 0)}) | "
            f"{_cm(r['online_median_error_m'])} | "
            f"{_cm(r.get(pre + '_median_error_m'))} |")
    lines += ["", "Online: every `predicted_path` the predictor published, scored against the "
              "simulator's ground truth. Offline: the bag recorded during the same run "
              "(`run_bag`), `asgp evaluate MODEL run_bag --truth` (`evaluate.json`): the "
              "recorded future joystick, scored against ground truth (`--truth`) and against "
              "the path integrated from VO (the paper's metric)."]
    if plan:
        lines.append("The predictor was given the driver's upcoming commands (`joy_plan`), "
                     "the known-future-command assumption of the offline evaluation.")
    else:
        lines.append("No plan: the predictor held the newest joystick sample, so the like-"
                     "for-like offline figure holds J at t0 over the horizon on the same "
                     "cases (`asgp evaluate` assumes the future commands known).")
    held = [r.get("offline_held_success") for r in rows]
    if plan and held[0] is not None:
        lines.append("For comparison, holding the command instead: "
                     + ", ".join(f"{r['horizon_s']:g} s {_pct(r.get('offline_held_success'))}"
                                 for r in rows) + " (offline, truth).")
    lines += ["", "## 95 % position ellipses: how often they hold the position", "",
              "| horizon | online vs truth | online, offline cases | offline `--truth` | "
              "offline vs VO (paper) |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['horizon_s']:g} s | {_pct(r.get('online_coverage'))} "
            f"(n={r.get('online_coverage_n', 0)}) | {_pct(r.get('online_cases_coverage'))} "
            f"(n={r.get('online_cases_coverage_n', 0)}) | "
            f"{_pct(r.get('offline_truth_coverage'))} | {_pct(r.get('offline_vo_coverage'))} |")
    lines += ["", "Online: the ellipses the predictor published (`predicted_path/uncertainty` "
              "markers) with each path, against the true position; offline: `asgp evaluate` "
              "on the recorded bag, the model as trained. 95 % is what they promise. "
              + (("The model's calibration was fitted on the held-out end of its training "
                  "drive (`asgp info MODEL`), whose velocities came from the simulator's VO "
                  "model, not from `vo_node` on the rendered camera."
                  if state.train_info.get("calibrated") else
                  "The model is not calibrated (`asgp info MODEL` says why): its ellipses "
                  "are the GP's own variance.")
                 if state.train_info.get("configuration") else
                 "A calibrated model's calibration was fitted on the held-out end of its "
                 "training bags (`asgp info MODEL`).")
              + (" The predictor adapted online (see 'Adaptation'), its variance scale "
                 "included: the online columns are the adapting predictor's, the offline "
                 "ones the model's as trained."
                 if (o.get("adapt") if adapted is None else adapted) else "")
              + ("" if plan else " No plan: online, the ellipses are those of the held "
                 "command, offline those of the recorded future commands; not like with "
                 "like (the held-command figure of the success table has no ellipses).")]
    lines.append("")
    lines += ["## Where the time went", "", "| process | CPU s | alive s | CPU % of a core |",
              "|---|---|---|---|"]
    for c in cpu:
        lines.append(f"| {c['process']} | {c['cpu_s']:.1f} | {c['alive_s']:.1f} | "
                     f"{c['cpu_percent']:.0f}% |")
    lines += ["", "| message | n | median | p95 | max |", "|---|---|---|---|---|"]
    for lat in latencies:
        lines.append(f"| {lat['what']} | {lat['n']} | {lat['median_ms']:.1f} ms | "
                     f"{lat['p95_ms']:.1f} ms | {lat['max_ms']:.1f} ms |")
    if extras:
        lines += ["", "Component timings from their diagnostics:", ""]
        for k, v in extras.items():
            lines.append(f"- {k}: {v}")
    if shared:
        lines += ["", "## Shared control", "", *shared]
    if adaptation:
        lines += ["", "## Adaptation", "", *adaptation]
    lines += ["", "![demo](demo.png)", ""]
    return "\n".join(lines)


def contacts_without_layer(state: RunState) -> int:
    """Contacts of the same drive (seed, floor, driver) without the layer: the simulated
    hardware alone, offline, for the live drive's duration (the chair follows the stick
    through the firmware's passthrough, as the live board does without overrides)."""
    o = state.options
    hw = SimulatedHardware(HardwareConfig(seed=int(o["seed"]), surface=str(o["surface"]),
                                          inattention=float(o["inattention"])), board=False)
    for _ in range(round(state.drive_seconds / STEP_S)):
        hw.step()
    return hw.contacts


def shared_control_summary(state: RunState, monitor: MonitorNode
                           ) -> tuple[list[str], dict[str, Any]]:
    """The report's shared-control section (empty without the layer) and its figures."""
    if not state.options.get("shared_control"):
        return [], {}

    def value(who: str, key: str) -> str:
        got = monitor.diag_value(who, key)
        return "n/a" if got is None else got

    with_layer = value("demo_hardware", "contacts")
    without = contacts_without_layer(state)
    overriding = float(value("shared_control_node", "overriding_s").replace("n/a", "nan"))
    drive = max(state.drive_seconds, 1e-9)
    data: dict[str, Any] = {
        "contacts_with_layer": with_layer, "contacts_without_layer": without,
        "interventions": value("shared_control_node", "interventions"),
        "overriding_s": overriding, "untouched_share": 1.0 - overriding / drive,
        "mean_change": value("shared_control_node", "mean_change"),
        "solve_p50_ms": value("shared_control_node", "solve_p50_ms"),
        "solve_p99_ms": value("shared_control_node", "solve_p99_ms"),
        "min_clearance_m": value("demo_hardware", "min_clearance_m"),
        "inattention": state.options.get("inattention"),
    }
    lines = [
        f"The driver was inattentive (`--inattention {data['inattention']}`). The same drive "
        "(seed, floor, driver) without the layer was simulated offline for comparison.", "",
        "| | without the layer | with the layer |", "|---|---|---|",
        f"| contacts with the furniture | {without} | {with_layer} |",
        f"| interventions | 0 | {data['interventions']} |",
        f"| time overriding | 0 s | {overriding:.1f} s |",
        f"| user's command untouched | 100 % | {100 * data['untouched_share']:.1f} % |",
        f"| mean change of the command | - | {data['mean_change']} |",
        f"| decision time p50 / p99 | - | {data['solve_p50_ms']} / {data['solve_p99_ms']} ms |",
        f"| minimum clearance (with the layer) | - | {data['min_clearance_m']} m |",
    ]
    return lines, data


#: The predictor's adaptation diagnostics the report shows: (key, what it is).
ADAPT_KEYS = (
    ("adapt_rows_absorbed", "steps learnt from"),
    ("adapt_steps_refused", "steps refused (not valid training rows: VO lost or stuck, "
                            "a gap, an override)"),
    ("overrides_seen", "overrides seen on joy_override (the layer: its own)"),
    ("overrides_late", "overrides that came after a step they may have driven was learnt"),
    ("adapt_published", "posterior published at the end"),
    ("adapt_variance_scale", "variance scale per speed regime"),
    ("adapt_coverage_95", "95 % ellipse coverage of the checked predictions"),
    ("adapt_switches", "switches between the trained and the adapted posterior"),
)


def adaptation_summary(state: RunState, monitor: MonitorNode
                       ) -> tuple[list[str], dict[str, Any]]:
    """The report's adaptation section (empty unless the predictor adapted), from the
    predictor's last diagnostics, and the shared-control layer's (its own predictor adapts
    with it) when the layer ran."""
    if not state.options.get("adapt"):
        return [], {}
    unavailable = monitor.diag_value("predictor_node", "adapt_unavailable")
    if unavailable:  # a model that does not adapt (an MLP): the predictor ran as trained
        return [f"Asked to adapt, the predictor predicted from the model as trained: "
                f"{unavailable}."], {"unavailable": unavailable}
    data: dict[str, Any] = {key: monitor.diag_value("predictor_node", key) or "n/a"
                            for key, _ in ADAPT_KEYS}
    if not state.options.get("shared_control"):
        lines = ["The predictor adapted its model online (`adapt.enabled`); from its last "
                 "diagnostics:", "", "| | |", "|---|---|"]
        lines += [f"| {what} | {data[key]} |" for key, what in ADAPT_KEYS]
        return lines, data
    # the layer's overrides_seen/late count its own overrides (it does not listen for others)
    layer = {key: monitor.diag_value("shared_control_node", key) or "n/a"
             for key, _ in ADAPT_KEYS}
    data["shared_control_node"] = layer
    lines = ["The predictor and the shared-control layer's own predictor adapted their models "
             "online (`adapt.enabled`); from their last diagnostics:", "",
             "| | predictor | shared-control layer |", "|---|---|---|"]
    lines += [f"| {what} | {data[key]} | {layer.get(key, '-')} |" for key, what in ADAPT_KEYS]
    return lines, data


def latency_rows(monitor: MonitorNode) -> list[dict[str, Any]]:
    what = {
        topics.JOY: "joystick: bridge stamp -> monitor",
        topics.VO_TWIST: f"VO: camera frame stamp -> {topics.VO_TWIST} at the monitor",
        topics.PREDICTED_PATH: "prediction: t0 (last complete grid step) -> path at the "
                               "monitor",
    }
    rows = []
    for topic, text in what.items():
        s = monitor.latency[topic].summary_ms()
        rows.append({"what": text, **s})
    return rows


def diagnostic_timings(monitor: MonitorNode) -> dict[str, str]:
    """Timing values the components report in their diagnostics."""
    out = {}
    for name, entry in sorted(monitor.diag.items()):
        for key, value in entry.values.items():
            if "_ms" in key or key.endswith("_hz") or key in ("max_lag_s", "lag_s"):
                out[f"{name}: {key}"] = value
    return out


def cpu_rows(state: RunState) -> list[dict[str, Any]]:
    rows = []
    for name, cpu in state.cpu.items():
        alive = state.lifetimes.get(name, float("nan"))
        rows.append({"process": name, "cpu_s": cpu, "alive_s": alive,
                     "cpu_percent": 100.0 * cpu / alive if alive and alive > 0 else float("nan")})
    return rows


def figure(path: Path, monitor: MonitorNode, room: Room | None = None) -> None:
    """The demo picture (module docstring), written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, truth = monitor.truth.arrays()
    paths = [p for p in monitor.score.paths if monitor.truth.at(p.t0) is not None]
    fig = plt.figure(figsize=(13, 7.2), dpi=110)
    gs = fig.add_gridspec(2, 2, width_ratios=(1.45, 1.0), height_ratios=(1.3, 1.0))
    ax = fig.add_subplot(gs[:, 0])
    az = fig.add_subplot(gs[0, 1])
    ae = fig.add_subplot(gs[1, 1])
    _drive_panel(ax, monitor, room, t, truth, paths)
    _zoom_panel(az, monitor, t, truth, paths)
    _error_panel(ae, t, paths, monitor.score.horizons)
    fig.tight_layout()
    try:
        with atomic_path(path) as tmp, naming(tmp):
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)


def _draw_paths(axis: Axes, monitor: MonitorNode, recs: list[PathRecord], ellipses: bool,
                lw: float) -> None:
    """Predicted paths placed at the true pose where they start, green or red by their
    error at the shortest horizon (1.0 s), with their 95% ellipses if asked."""
    from matplotlib.patches import Ellipse

    for rec in recs:
        p0 = monitor.truth.at(rec.t0)
        assert p0 is not None  # the paths drawn are those with a true pose at t0
        c, s = math.cos(p0[2]), math.sin(p0[2])
        xy = rec.pose[:, :2] @ np.array([[c, s], [-s, c]]) + p0[:2]
        ok = rec.errors.get(horizon_key(monitor.score.horizons[0]))
        colour = "tab:green" if ok is not None and ok <= THRESHOLD_M else (
            "tab:red" if ok is not None else "tab:gray")
        axis.plot(np.r_[p0[0], xy[:, 0]], np.r_[p0[1], xy[:, 1]], "-", color=colour,
                  lw=lw, alpha=0.8)
        if ellipses and rec.ellipses is not None:
            for (major, minor, ang), (ex, ey) in zip(rec.ellipses, xy, strict=False):
                axis.add_patch(Ellipse((ex, ey), 2 * major, 2 * minor,
                                       angle=math.degrees(ang + p0[2]), fill=False,
                                       lw=0.6, color="tab:blue", alpha=0.5))


def _drive_panel(ax: Axes, monitor: MonitorNode, room: Room | None, t: np.ndarray,
                 truth: np.ndarray, paths: list[PathRecord]) -> None:
    """The whole drive: the room, the driven path, where shared control overrode, and a
    predicted path every second."""
    from matplotlib.patches import Rectangle

    if room is not None:
        ax.add_patch(Rectangle((room.x_min, room.y_min), room.x_max - room.x_min,
                               room.y_max - room.y_min, fill=False, lw=1.5, color="k"))
        b = room.furniture_band
        ax.add_patch(Rectangle((room.x_min + b, room.y_min + b),
                               room.x_max - room.x_min - 2 * b, room.y_max - room.y_min - 2 * b,
                               fill=False, lw=0.8, ls="--", color="0.5"))
    if t.size:
        ax.plot(truth[:, 0], truth[:, 1], "k-", lw=1.0, label="driven path (ground truth)")
        where = [p for p in (monitor.truth.at(t) for t in monitor.overrides[::4])
                 if p is not None]
        if where:
            w = np.asarray(where)
            ax.plot(w[:, 0], w[:, 1], "x", color="tab:purple", ms=5, mew=1.2,
                    label="shared control overriding")
    _draw_paths(ax, monitor, paths[::5], ellipses=True, lw=0.9)
    ax.plot([], [], color="tab:green", label="predicted 2 s path, 1.0 s error <= 10 cm")
    ax.plot([], [], color="tab:red", label="predicted 2 s path, 1.0 s error > 10 cm")
    ax.plot([], [], color="tab:blue", lw=0.6, label="95% position ellipses")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Live drive: predicted paths every second")
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85)


def _zoom_panel(az: Axes, monitor: MonitorNode, t: np.ndarray, truth: np.ndarray,
                paths: list[PathRecord]) -> None:
    """Zoom: the 6 s window with the largest heading change, a predicted path every 0.4 s."""
    if t.size > 10 and paths:
        yaw = truth[:, 2]
        win = 6.0
        j = np.searchsorted(t, t + win)
        j = np.minimum(j, t.size - 1)
        turn = np.abs(yaw[j] - yaw)
        i0 = int(np.argmax(turn))
        ta, tb = t[i0], t[j[i0]]
        sel = (t >= ta) & (t <= tb + 2.0)
        az.plot(truth[sel, 0], truth[sel, 1], "k-", lw=1.5)
        _draw_paths(az, monitor, [p for p in paths if ta <= p.t0 <= tb][::2], ellipses=True,
                    lw=1.0)
        az.set_aspect("equal", adjustable="datalim")
        az.set_title(f"Zoom: {win:.0f} s of the sharpest manoeuvre, a path every 0.4 s",
                     fontsize=9)
        az.set_xlabel("x (m)")


def _error_panel(ae: Axes, t: np.ndarray, paths: list[PathRecord],
                 horizons: tuple[float, ...]) -> None:
    """The online prediction error at the shortest and the longest horizon (1.0 and 2.0 s
    at 5 Hz) against time, and the 10 cm line."""
    t_start = t[0] if t.size else 0.0
    top = 30.0
    for key, colour in ((horizon_key(horizons[0]), "tab:purple"),
                        (horizon_key(horizons[-1]), "tab:orange")):
        tt = [p.t0 - t_start for p in paths if key in p.errors]
        ee = [min(100 * p.errors[key], top) for p in paths if key in p.errors]
        ae.plot(tt, ee, ".", ms=2.5, color=colour, label=f"error at {key} s")
    ae.axhline(100 * THRESHOLD_M, color="k", lw=0.8, ls="--", label="10 cm (success)")
    ae.set_ylim(0.0, top)
    ae.set_xlabel("time since the start of the drive (s)")
    ae.set_ylabel(f"error vs ground truth (cm, clipped at {top:.0f})")
    ae.legend(fontsize=7, loc="upper right")
    ae.set_title("Online prediction error", fontsize=9)


def write_report(out: Path, state: RunState, monitor: MonitorNode, model: MotionModel, bag: Path,
                 env: dict[str, str], say: Callable[[str], None]) -> dict[str, Path]:
    """Evaluate the run's bag offline and write the report files; returns their paths."""
    written: dict[str, Path] = {}
    dt = 1.0 / float(model.resample_config.rate_hz)
    evaluation = None
    cases = None
    held = None
    if state.recording_cut:  # (it stopped at an error, said: the figures are online)
        say("note: no offline evaluation: the recording was cut short")
    elif bag.exists() and monitor.counts.get(topics.PREDICTED_PATH, 0) and \
            monitor.counts.get(topics.VO_TWIST, 0):
        say("evaluating the recorded bag offline: asgp evaluate --truth ...")
        try:
            evaluation = evaluate_bag(Path(state.model_path), bag, out / "evaluate.json", env,
                                      evaluate_timeout(state.drive_seconds))
            written["offline evaluation"] = out / "evaluate.json"
            cases = offline_cases(bag, model)
            held = offline_held(bag, model)
        except (DemoError, OSError, ValueError, BagError) as exc:
            problem = f"offline evaluation of {bag} failed: {exc}"
            if state.stopped_by:  # a run cut short may be too short to evaluate
                say(f"note: {problem}")
            else:
                state.errors.append(problem)
    rows = success_table(monitor.score, evaluation, cases, dt, held,
                         uncertainty=get_kind(model.kind).probabilistic)
    cpu = cpu_rows(state)
    lat = latency_rows(monitor)
    extras = diagnostic_timings(monitor)
    if monitor.truth.arrays()[0].size:
        figure(out / "demo.png", monitor, room_for_surface(state.options["surface"]))
        written["figure"] = out / "demo.png"
    data = {"run": asdict(state), "success": rows, "cpu": cpu, "latency": lat,
            "diagnostics": {n: {"level": e.level, "message": e.message, "values": e.values}
                            for n, e in monitor.diag.items()},
            "messages": dict(monitor.counts), "paths_unscorable": monitor.score.unscorable,
            "threshold_m": THRESHOLD_M}
    atomic_write_text(out / "report.json",
                      json.dumps(_clean(data), indent=2, default=str) + "\n")
    # (written first without them: the layer's comparison simulates the drive again)
    shared, shared_data = shared_control_summary(state, monitor)
    adaptation, adaptation_data = adaptation_summary(state, monitor)
    if shared_data or adaptation_data:
        if shared_data:
            data["shared_control"] = shared_data
        if adaptation_data:
            data["adaptation"] = adaptation_data
        atomic_write_text(out / "report.json",
                          json.dumps(_clean(data), indent=2, default=str) + "\n")
    text = markdown(state, rows, cpu, lat, extras, shared, adaptation,
                    adapted=bool(adaptation_data) and "unavailable" not in adaptation_data)
    atomic_write_text(out / "report.md", text)
    written["report"] = out / "report.md"
    say("")
    for line in text.splitlines()[2:]:
        if line.startswith("![") or line.startswith("Component timings"):
            break
        say(line)
    return written


def _clean(x: object) -> object:
    """JSON-safe copy: numpy scalars to Python, non-finite floats to null."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, (np.floating, np.integer)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
