"""What the demo's orchestrator and its report both need: the error type, the record of
the run and the offline evaluation of the recorded bag. Below both (they import it; it
imports neither)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class DemoError(Exception):
    """The demo cannot run as asked (bad option, missing model...); the message says why."""


@dataclass
class RunState:
    """What happened, for the report."""

    options: dict[str, Any]
    domain_id: int
    model_path: str = ""
    train_info: dict[str, Any] = field(default_factory=dict)
    drive_start_wall: float | None = None
    drive_seconds: float = 0.0
    stopped_by: str = ""
    #: the recording stopped before the drive's end (a full disk): when, why, what was kept
    recording_cut: str = ""
    errors: list[str] = field(default_factory=list)
    cpu: dict[str, float] = field(default_factory=dict)
    lifetimes: dict[str, float] = field(default_factory=dict)
    returncodes: dict[str, int | None] = field(default_factory=dict)
    stop_signals: dict[str, str] = field(default_factory=dict)


def _text(data: str | bytes | None) -> str:
    return data.decode(errors="replace") if isinstance(data, bytes) else data or ""


#: The offline evaluation of a drive may take this long, plus EVALUATE_S_PER_MINUTE for each
#: minute driven, before it is stopped: about 1 s a minute on an idle laptop (a fixed 300 s
#: stopped a 10-hour drive's evaluation, which needs about ten minutes, and lost its report).
EVALUATE_TIMEOUT_S = 300.0
EVALUATE_S_PER_MINUTE = 10.0


def evaluate_timeout(drive_seconds: float) -> float:
    """How long the offline evaluation of ``drive_seconds`` of driving may take."""
    return EVALUATE_TIMEOUT_S + EVALUATE_S_PER_MINUTE * max(drive_seconds, 0.0) / 60.0


def evaluate_bag(model: Path, bag: Path, out_json: Path, env: dict[str, str],
                 timeout_s: float = EVALUATE_TIMEOUT_S) -> dict[str, Any]:
    """``asgp evaluate MODEL BAG --truth --json OUT --force`` in a subprocess; its JSON.

    ``--force``: ``out_json`` lies in the demo's own output directory, which the demo has
    checked is new or an earlier demo's (and ``asgp demo --force`` replaces the latter): a
    second run into it replaces the first one's evaluation instead of failing at the end.
    """
    argv = [sys.executable, "-m", "asgp_ros.cli", "evaluate", str(model), str(bag), "--truth",
            "--json", str(out_json), "--force"]
    try:
        proc = subprocess.run(argv, env=env, capture_output=True, text=True,
                              timeout=timeout_s, check=False)
    except subprocess.TimeoutExpired as exc:  # (a traceback, and the report was not written)
        raise DemoError(f"asgp evaluate took more than {timeout_s:g} s (stopped): "
                        f"{_text(exc.stderr).strip()[-500:]}") from exc
    if proc.returncode != 0:
        raise DemoError(f"asgp evaluate failed ({proc.returncode}): "
                        f"{(proc.stderr or proc.stdout).strip()[-2000:]}")
    scores: dict[str, Any] = json.loads(out_json.read_text())
    return scores
