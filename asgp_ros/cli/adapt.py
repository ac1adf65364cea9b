"""``asgp adapt``: a trained ASGP brought to a new floor, chair or user by recordings made
there (:mod:`asgp_ros.learning.adapting`), saved as a new model file."""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from typing import Any

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import number
from asgp_ros.cli._bagargs import add_topic_args, read_series_or_fail
from asgp_ros.common.fileio import MODEL_FILE, bag_inputs, check_output
from asgp_ros.core.modelfile import ModelFileError, load_model, save_model
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import learning_config
from asgp_ros.learning.adapting import (
    AdaptingError,
    OfflineAdaptOptions,
    adapt_model,
    check_adaptable,
)
from asgp_ros.learning.training import series_identity
from asgp_ros.recording.bags import find_recording, recording_identity, same_recording


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "adapt",
        help="adapt a trained ASGP to recordings of a new floor, chair or user and save it "
             "as a new model file",
        description="Absorb every row of the bags that training would accept into the "
                    "trained ASGP's posterior (hyperparameters and pseudo-inputs as "
                    "trained; the rows teach a correction to the trained function), fit "
                    "the variance calibration again on the last 20% of each bag (held "
                    "out, then absorbed too), and write the result as a new model file. "
                    "Prints the held-out k-step success of the model as trained and as "
                    "adapted. MODEL is never modified.",
    )
    p.add_argument("model", metavar="MODEL", help="trained ASGP model file (.npz)")
    p.add_argument("bags", nargs="+", metavar="BAG",
                   help="recordings of the new floor, chair or user (ROS 1 or ROS 2)")
    p.add_argument("--out", required=True, metavar="MODEL2", help="model file to write (.npz)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing model file at --out (never MODEL itself)")
    p.add_argument("--trained-weight", type=number(0.0, 1.0), default=0.0,
                   help="weight the trained data keep against the new rows: 0 (default) "
                        "lets the new rows alone correct the trained function where they "
                        "reach; 1 keeps the trained data whole (the posterior of old and "
                        "new rows together)")
    p.add_argument("--no-calibration", action="store_true",
                   help="keep the trained variance calibration (and hold nothing out)")
    add_topic_args(p)
    p.set_defaults(func=run)


def _pct(x: float | None) -> str:
    return "  -  " if x is None else f"{100 * x:5.1f}%"


def _adaptations(record: object) -> list[object]:
    """The data records of an ``adaptation`` meta record and of the earlier ones in it."""
    if not isinstance(record, dict):
        return []
    earlier = record.get("earlier")
    return [*(r.get("data") for r in (earlier if isinstance(earlier, list) else [])
              if isinstance(r, dict)), record.get("data")]


def _recordings(*records: object) -> list[object]:
    """What identifies the recordings of data records (a model file's ``training_data``,
    an adaptation's ``data``; any shape in a foreign file), for
    :func:`asgp_ros.recording.bags.find_recording`: their ``recordings`` (real path,
    storage and, since they were kept, messages), or, in a file written before those were
    kept, the real paths of the bags they name that exist from here."""
    out: list[object] = []
    for data in records:
        kept = data.get("recordings") if isinstance(data, dict) else None
        if isinstance(kept, list):
            out.extend(kept)
        else:
            out.extend({"path": os.path.realpath(b)} for b in _bag_names(data)
                       if os.path.exists(b))
    return out


def _minutes(data: object) -> str:
    seconds = data.get("duration_s") if isinstance(data, dict) else None
    if isinstance(seconds, bool) or not isinstance(seconds, int | float):
        return "?"
    return f"{seconds / 60:.1f}"


def learnt_from(model: MotionModel, bag: str | Mapping[str, Any]) -> tuple[str, str] | None:
    """("trained on" or "adapted to", "same" or "start") when ``bag`` (or its identity,
    with the digests of its messages as read: :func:`series_identity`) is one of the
    recordings ``model`` learnt from (its model file's records), or shares its start with
    one (one is the other cut short), else None. A record of a model file written before
    the messages' digests were kept tells a byte-for-byte copy, not a repaired or
    converted one (:func:`asgp_ros.recording.bags.find_recording`)."""
    mine = bag if isinstance(bag, Mapping) else recording_identity(bag)
    for verb, records in (("trained on", _recordings(model.meta.get("training_data"))),
                          ("adapted to", _recordings(*_adaptations(
                              model.meta.get("adaptation"))))):
        how = find_recording(mine, records)
        if how is not None:
            return verb, how
    return None


def learnt_text(bag: str, model_path: str, learnt: tuple[str, str]) -> str:
    """What :func:`learnt_from` found, in words: "BAG is one of the recordings MODEL was
    trained on", or that it begins as one of them does."""
    verb, how = learnt
    if how == "same":
        return f"{bag} is one of the recordings {model_path} was {verb}"
    return (f"{bag} begins with the same messages as one of the recordings {model_path} was "
            f"{verb} (one is the other cut short)")


def _bag_names(data: object) -> list[str]:
    """The bags a data record names (a foreign file's record may be of any shape)."""
    bags = data.get("bags") if isinstance(data, dict) else None
    return [b for b in bags if isinstance(b, str)] if isinstance(bags, list) else []


def summary_lines(meta: dict[str, Any]) -> list[str]:
    """What ``asgp adapt`` did, from the model's ``adaptation`` meta (also ``asgp info``)."""
    ad = meta.get("adaptation")
    if not isinstance(ad, dict):
        return []
    data = ad.get("data")
    chans = ad.get("channels", {})
    lines = [f"adapted to {len(_bag_names(data))} bag(s), "
             f"{_minutes(data)} min; trained data's weight "
             f"{ad.get('trained_weight', '?')}; calibration {ad.get('calibration', '?')}"]
    earlier = [r for r in ad.get("earlier", []) if isinstance(r, dict)] \
        if isinstance(ad.get("earlier"), list) else []
    for n, record in enumerate(earlier, 1):
        lines.append(f"  before that ({n} of {len(earlier)}): adapted to "
                     f"{', '.join(_bag_names(record.get('data'))) or '?'}")
    for name, ch in chans.items():
        refused = ", ".join(f"{v} {k}" for k, v in ch.get("refused", {}).items()) or "none"
        lines.append(f"  {name}: {ch.get('absorbed', '?')} of {ch.get('rows', '?')} rows "
                     f"absorbed (refused: {refused}), effective size "
                     f"{ch.get('effective_size', 0.0):.0f}")
    held = ad.get("held_out", {})
    before, after = held.get("trained"), held.get("adapted")
    if before and after:
        cv = any(row.get("coverage_cross_validated") for row in after.values())
        lines.append("  held-out success (coverage of the 95% ellipse"
                     + (", cross-validated when adapted" if cv else "")
                     + "), as trained -> adapted on the rest:")
        for key in before:
            b, a = before[key], after.get(key, {})
            lines.append(f"    {key} s: {_pct(b.get('success'))} ({_pct(b.get('coverage_95'))})"
                         f" -> {_pct(a.get('success'))} ({_pct(a.get('coverage_95'))}), "
                         f"{b.get('cases', 0)} cases")
    elif ad.get("holdout_fraction"):
        lines.append("  held-out success: no held-out case (recordings too short)")
    return lines


def run(args: argparse.Namespace) -> int:
    check_output(args.out, MODEL_FILE, inputs=[args.model, *bag_inputs(args.bags)],
                 force=args.force)
    twice = same_recording(args.bags)
    if twice is not None:  # a bag given twice would count its rows twice
        raise CommandError(f"{twice[1]}: the same recording as {twice[0]}; give each once")
    opts = OfflineAdaptOptions(trained_weight=args.trained_weight,
                               holdout=0.0 if args.no_calibration else 0.2,
                               calibrate=not args.no_calibration)
    try:
        opts.validate()
        model = load_model(args.model)
        check_adaptable(model)  # before reading the bags
    except (AdaptingError, ModelFileError) as exc:
        raise CommandError(f"{args.model}: {exc}" if isinstance(exc, AdaptingError)
                           else str(exc)) from exc
    # learnt under the held-chair rule even where the model predicts without it
    series = read_series_or_fail(args.bags, args,
                                 resample_config=learning_config(model.resample_config))
    for bag, s in zip(args.bags, series, strict=True):  # told by the messages read
        learnt = learnt_from(model, series_identity(s))
        if learnt is not None:
            print(f"warning: {learnt_text(bag, args.model, learnt)}: its rows are in the "
                  "posterior already"
                  + (" and count twice with --trained-weight 1"
                     if args.trained_weight > 0.0 or learnt[0] == "adapted to" else ""),
                  flush=True)

    def progress(stage: str, message: str) -> None:
        print(f"[adapt {stage}] {message}", flush=True)

    try:
        adapted = adapt_model(model, series, opts, progress=progress)
    except (AdaptingError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    try:
        save_model(args.out, adapted)
    except ModelFileError as exc:  # a model the loader would refuse is not written
        raise CommandError(f"the adapted model is not saved: {exc}") from exc
    for line in summary_lines(adapted.meta):
        print(line)
    print(f"wrote {args.out}: {args.model} adapted (asgp info {args.out} shows it)")
    return 0
