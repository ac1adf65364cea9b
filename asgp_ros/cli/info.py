"""``asgp info MODEL``: what a model file holds: its kind, configuration, training data,
the automatic configuration's candidates and the variance calibration with its held-out
coverage."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import Any

from asgp_ros.cli import CommandError, one_line
from asgp_ros.cli.adapt import summary_lines
from asgp_ros.cli.train import selection_table
from asgp_ros.core.modelfile import ModelFileError, load_model
from asgp_ros.core.models import MotionModel


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "info",
        help="show a model file's configuration, training data and calibration",
        description="Print what a model file holds: kind, lags, coupling, pseudo-inputs, "
                    "grid, training data, the automatic configuration's candidates with "
                    "their held-out scores, and the variance calibration with the held-out "
                    "coverage of its 95% ellipses per horizon, speed regime, joystick "
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
    still = cal.get("still_cases")
    at_rest = (f"; {still} held-out cases of the chair parked (the stick in the board's "
               "neutral window, neither the chair nor its prediction moved 10 cm) are not "
               "counted"
               if isinstance(still, int)
               and not isinstance(still, bool) and still > 0 else "")
    lines = ([] if applied else [f"calibration {cal['reason']}"]) + [
             f"held-out coverage of the 95% ellipse, raw -> calibrated ({cv}), %{at_rest}:",
             f"  {'':<28} {'cases':>6}  " + "  ".join(f"{h + ' s':>13}" for h in hs)]

    def row(name: str, t: dict[str, Any]) -> str:
        return (f"  {name:<28} {t['cases']:>6}  "
                + "  ".join(f"{_pct(t[h]['raw'])} -> {_pct(t[h]['calibrated'])}"
                            for h in hs))

    lines.append(row("all", cal["by_horizon"]))
    for group in ("by_speed", "by_steadiness", "by_speed_and_steadiness", "by_recording"):
        for name, t in cal.get(group, {}).items():
            lines.append(row(name[-28:], t))
    return lines


_STAMPS = {"midpoint": "the middle of its frame interval", "frame": "its frame's stamp"}


#: What a section's description may raise on a model file whose metadata record (free
#: JSON: what training, selection, calibration and adaptation wrote) has another shape.
_MALFORMED = (AttributeError, TypeError, KeyError, ValueError, IndexError, ArithmeticError)


def _section(name: str, lines: Callable[[], list[str]]) -> list[str]:
    """``lines()``, or one line saying the section's record is malformed: a model file's
    metadata is a record for people, and a damaged one must not hide the rest."""
    try:
        return lines()
    except _MALFORMED as exc:
        return [f"{name}: not readable in this file ({type(exc).__name__})"]


def _channel_lines(training: dict[str, Any]) -> list[str]:
    lines = []
    for ch, info in training.get("channels", {}).items():
        extras = [f"{k} {info[k]}" for k in ("num_inducing", "rows", "posterior_rows",
                                             "iterations", "epochs") if k in info]
        if "noise_std" in info:
            extras.append(f"noise std {info['noise_std']:.4g}")
        lines.append(f"  {ch}: " + ", ".join(extras))
    return lines


def _data_lines(data: dict[str, Any]) -> list[str]:
    if not data:
        return []
    overridden = data.get("overridden_samples")
    extra = (f", {overridden} grid points overridden (not used)"
             if isinstance(overridden, int) and not isinstance(overridden, bool)
             and overridden > 0 else "")
    return [f"training data: {len(data.get('bags', []))} bag(s), "
            f"{data.get('duration_s', 0.0) / 60:.1f} min, "
            f"{data.get('training_rows', '?')} rows, {data.get('segments', '?')} "
            f"segments, stale {100 * data.get('stale_fraction', 0.0):.1f}%{extra}"]


def _selection_lines(model: MotionModel) -> list[str]:
    sel = model.meta.get("selection")
    if not isinstance(sel, dict):
        return []
    secs = sel.get("seconds", {})
    return ["automatic configuration: " + (
        f"fell back ({sel['fallback']})" if "fallback" in sel else
        f"chosen by {sel.get('criterion', '?')} on the last "
        f"{100 * sel.get('holdout_fraction', 0):.0f}% of each bag; "
        f"{secs.get('total', '?')} s, planned for {sel.get('budget_s', '?')} s")] + [
            "  " + line for line in selection_table(model)]


def _calibration_lines(model: MotionModel) -> list[str]:
    cal = model.calibration  # (checked on loading)
    head = ("variance calibration: "
            + ("identity" if cal.is_identity else
               f"scale v {cal.scale[0]:.4g}, omega {cal.scale[1]:.4g}; floor v "
               f"{cal.floor[0]:.3g} (m/s)^2, omega {cal.floor[1]:.3g} (rad/s)^2; "
               + (("speed regimes " + ", ".join(f"{f:.3g}" for f in cal.speed_factors)
                   + f" split at |v| = {', '.join(f'{e:.3g}' for e in cal.speed_edges)} m/s")
                  if cal.speed_edges else
                  f"one speed regime (too few held-out cases, or speeds, to split), factor "
                  f"{cal.speed_factors[0]:.3g}")))
    return [head, *_section("  held-out coverage", lambda: [
        "  " + line for line in coverage_lines(model.meta.get("calibration", {}))])]


def describe(path: str, model: MotionModel) -> list[str]:
    fc = model.feature_config
    meta = model.meta
    training = meta.get("training", {})
    configuration = training.get("configuration", "explicit") \
        if isinstance(training, dict) else "?"
    lines = [f"{path}: {model.kind}, s = {fc.lags}, "
             f"{'coupled' if fc.coupled else 'one axis per channel'}, "
             f"{model.rate_hz:g} Hz grid, VO read at "
             f"{_STAMPS[model.resample_config.vel_stamp]}, "
             f"{configuration} configuration"]
    lines += _section("  channels", lambda: _channel_lines(training))
    lines += _section("training data", lambda: _data_lines(meta.get("training_data", {})))
    lines += _section("automatic configuration", lambda: _selection_lines(model))
    lines += _section("adaptation", lambda: summary_lines(meta))
    return lines + _calibration_lines(model)


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
        print(one_line(line))  # the file's strings: a newline or escape forged report lines
    return 0



