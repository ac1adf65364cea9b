"""``asgp info MODEL``: what a model file holds: its kind, configuration, training data,
the automatic configuration's candidates and the variance calibration with its held-out
coverage."""

from __future__ import annotations

import argparse
import json
from typing import Any

from asgp_ros.cli import CommandError
from asgp_ros.cli.adapt import summary_lines
from asgp_ros.cli.train import selection_table
from asgp_ros.core.modelfile import ModelFileError, load_model
from asgp_ros.core.models import MotionModel


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "info",
        help="show a model file's configuration, training data and calibration",
        description="Print what a model file holds: kind, lags, coupling, pseudo-inputs, "
                    "grid, training data, the automatic configuration's candidates with "
                    "their held-out scores, and the variance calibration with the held-out "
                    "coverage of its 95%% ellipses per horizon, speed regime, joystick "
                    "steadiness and recording.",
    )
    p.add_argument("model", metavar="MODEL", help="model file (.npz)")
    p.add_argument("--json", action="store_true",
                   help="print the model's metadata as JSON instead")
    p.set_defaults(func=run)


def _pct(x: Any) -> str:
    return "  -  " if x is None else f"{100 * x:5.1f}"


def coverage_lines(cal: dict[str, Any]) -> list[str]:
    """The held-out coverage table of a calibration's report (raw -> calibrated, %)."""
    if not cal.get("fitted"):
        return [f"not calibrated{': ' + cal['reason'] if cal.get('reason') else ''}"]
    hs = [h for h in cal["by_horizon"] if h != "cases"]
    applied = cal.get("applied", True)
    cv = "cross-validated" if cal.get("cross_validated") else "in-sample"
    lines = ([] if applied else [f"calibration {cal['reason']}"]) + [
             f"held-out coverage of the 95% ellipse, raw -> calibrated ({cv}), %:",
             f"  {'':<28} {'cases':>6}  " + "  ".join(f"{h + ' s':>13}" for h in hs)]

    def row(name: str, t: dict[str, Any]) -> str:
        return (f"  {name:<28} {t['cases']:>6}  "
                + "  ".join(f"{_pct(t[h]['raw'])} -> {_pct(t[h]['calibrated'])}"
                            for h in hs))

    lines.append(row("all", cal["by_horizon"]))
    for group in ("by_speed", "by_steadiness", "by_recording"):
        for name, t in cal.get(group, {}).items():
            lines.append(row(name[-28:], t))
    return lines


_STAMPS = {"midpoint": "the middle of its frame interval", "frame": "its frame's stamp"}


def describe(path: str, model: MotionModel) -> list[str]:
    fc = model.feature_config
    meta = model.meta
    training = meta.get("training", {})
    lines = [f"{path}: {model.kind}, s = {fc.lags}, "
             f"{'coupled' if fc.coupled else 'one axis per channel'}, "
             f"{model.rate_hz:g} Hz grid, VO read at "
             f"{_STAMPS[model.resample_config.vel_stamp]}, "
             f"{training.get('configuration', 'explicit')} configuration"]
    for ch, info in training.get("channels", {}).items():
        extras = [f"{k} {info[k]}" for k in ("num_inducing", "rows", "posterior_rows",
                                             "iterations", "epochs") if k in info]
        if "noise_std" in info:
            extras.append(f"noise std {info['noise_std']:.4g}")
        lines.append(f"  {ch}: " + ", ".join(extras))
    data = meta.get("training_data", {})
    if data:
        lines.append(f"training data: {len(data.get('bags', []))} bag(s), "
                     f"{data.get('duration_s', 0.0) / 60:.1f} min, "
                     f"{data.get('training_rows', '?')} rows, {data.get('segments', '?')} "
                     f"segments, stale {100 * data.get('stale_fraction', 0.0):.1f}%")
    sel = meta.get("selection")
    if isinstance(sel, dict):
        secs = sel.get("seconds", {})
        lines.append("automatic configuration: " + (
            f"fell back ({sel['fallback']})" if "fallback" in sel else
            f"chosen by {sel.get('criterion', '?')} on the last "
            f"{100 * sel.get('holdout_fraction', 0):.0f}% of each bag; "
            f"{secs.get('total', '?')} s"))
        lines += ["  " + line for line in selection_table(model)]
    lines += summary_lines(meta)
    cal = model.calibration
    lines.append("variance calibration: "
                 + ("identity" if cal.is_identity else
                    f"scale v {cal.scale[0]:.4g}, omega {cal.scale[1]:.4g}; floor v "
                    f"{cal.floor[0]:.3g} (m/s)^2, omega {cal.floor[1]:.3g} (rad/s)^2; "
                    "speed regimes "
                    + ", ".join(f"{f:.3g}" for f in cal.speed_factors)
                    + (f" split at |v| = {', '.join(f'{e:.3g}' for e in cal.speed_edges)}"
                       " m/s" if cal.speed_edges else "")))
    lines += ["  " + line for line in coverage_lines(meta.get("calibration", {}))]
    return lines


def run(args: argparse.Namespace) -> int:
    try:
        model = load_model(args.model)
    except ModelFileError as exc:
        raise CommandError(str(exc)) from exc
    if args.json:
        print(json.dumps({"kind": model.kind, "features": model.feature_config.to_dict(),
                          "resample": model.resample_config.to_dict(),
                          "calibration": model.calibration.to_dict(), "meta": model.meta},
                         indent=1, sort_keys=True))
        return 0
    for line in describe(args.model, model):
        print(line)
    return 0



