"""The online predictor's work per path, in one process, side by side with a reference.

    .venv/bin/python benchmarks/predictor.py [--model MODEL] [--minutes 3] [--joy-hz 100]
                                             [--adapt both] [--reference REV | none]
                                             [--idle-ms 200]

What lies between a VO message and the published path in ``predictor_node``:
``Predictor.predict(now, learn=False)`` (the buffers read, the window resampled and checked,
the rollout with its covariances); the node calls ``learn`` after publishing. A simulated
tile drive (``--minutes``, seed ``--seed``) is replayed sample by sample into two predictors
on the same model, this tree's ``asgp_ros/core/online.py`` and revision ``--reference``'s
(extracted with ``git show`` and imported beside it; its own imports resolve to this
tree), and at each completed grid step both predict, in alternating order, each timed by
the wall clock. The joystick is resampled to ``--joy-hz`` (the serial bridge publishes the
board's 100 Hz; a gamepad driver often 30-50 Hz): the buffers hold ``buffer_s`` of it, and
reading them is part of every path. The two paths are compared too: the same inputs must
give the same path, to the last bits.

``--idle-ms 200`` sleeps that long before each timed call, as the node idles between its
paths at 5 Hz: on a virtual machine a call right after an idle spell has taken twice as
long as back to back (a woken vCPU, caches and branch predictors cold), whatever the code.

``--adapt both`` runs the pair twice, without and with online adaptation (each predictor
then learns after every path, untimed). The node's latency across processes, DDS and the
executor included: ``benchmarks/predictor_latency.py``.

Prints figures only (no assertions); p50 / p90 / p99 in ms, and the ratio current /
reference of each. Timings depend on the machine's load (printed).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rollout import load_reference  # benchmarks/rollout.py

from asgp_ros.core.adaptive import AdaptSettings
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.online import Predictor

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "docs" / "reproduction" / "models" / "tile_asgp.npz"
#: The last revision whose buffers kept their samples as tuples (converted at every read).
REFERENCE = "43d20cc2685c7e1af37e097903d69f6c07ed4f0d"


def drive(minutes: float, seed: int, joy_hz: float
          ) -> list[tuple[float, int, tuple[float, ...]]]:
    """(t, 0 joystick / 1 VO, values) of a simulated tile drive in time order, the joystick
    held at ``joy_hz`` (sample-and-hold of the simulator's own stream)."""
    from asgp_ros.sim.simulate import simulate

    rec = simulate("tile", minutes, seed)
    joy_t = np.arange(rec.joy_t[0], rec.joy_t[-1], 1.0 / joy_hz)
    idx = np.clip(np.searchsorted(rec.joy_t, joy_t, side="right") - 1, 0, len(rec.joy_t) - 1)
    events = [(float(t), 0, (float(rec.joy[i, 0]), float(rec.joy[i, 1])))
              for t, i in zip(joy_t, idx, strict=True)]
    events += [(float(t), 1, (float(v[0]), float(v[1]), 0.0 if stale else 1.0))
               for t, v, stale in zip(rec.vo_t, rec.vo, rec.vo_stale, strict=True)]
    return sorted(events, key=lambda e: (e[0], e[1]))


def percentiles(ms: np.ndarray) -> np.ndarray:
    return np.percentile(ms, [50, 90, 99])


def side_by_side(model: object, classes: tuple[type, type], adapt: AdaptSettings | None,
                 events: list[tuple[float, int, tuple[float, ...]]], idle_s: float = 0.0
                 ) -> tuple[np.ndarray, np.ndarray, int, float]:
    """Per-path wall times (ms) of the two predictors, the paths compared, the largest
    difference of their poses and position covariances."""
    preds = [cls(model, adapt=adapt) for cls in classes]
    times: list[list[float]] = [[], []]
    last = None
    worst = 0.0
    for t, kind, values in events:
        for p in preds:
            if kind == 0:
                p.feed_joy(t, values[:2])
            else:
                p.feed_vo(t, values[:2], values[2] > 0.5)
        step = preds[0].ready_step()
        if kind != 1 or step is None or step == last:
            continue
        last = step
        order = (0, 1) if step % 2 == 0 else (1, 0)
        out = [None, None]
        took = [0.0, 0.0]
        for i in order:
            if idle_s > 0.0:
                time.sleep(idle_s)
            start = time.perf_counter()
            out[i] = preds[i].predict(t, learn=False)
            took[i] = time.perf_counter() - start
        a, b = out
        assert a is not None and b is not None
        if a.ok != b.ok:
            raise SystemExit(f"step {step}: the predictors disagree ({a.detail!r} vs "
                             f"{b.detail!r})")
        if a.ok:
            worst = max(worst, float(np.max(np.abs(a.pose - b.pose))),
                        float(np.max(np.abs(a.pos_cov - b.pos_cov))))
            for i in (0, 1):
                times[i].append(took[i] * 1e3)
        for p in preds:
            p.learn()
    return np.asarray(times[0]), np.asarray(times[1]), len(times[0]), worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=str(MODEL))
    ap.add_argument("--minutes", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--joy-hz", type=float, default=100.0)
    ap.add_argument("--adapt", choices=("off", "on", "both"), default="both")
    ap.add_argument("--reference", default=REFERENCE,
                    help="git revision of online.py to run beside ('none': this tree twice)")
    ap.add_argument("--idle-ms", type=float, default=0.0,
                    help="sleep this long before each timed call (the node's 5 Hz: 200)")
    args = ap.parse_args()
    if not (args.joy_hz > 0 and np.isfinite(args.joy_hz)):
        ap.error("--joy-hz must be a positive number")
    if not (0.0 <= args.idle_ms <= 10_000.0):
        ap.error("--idle-ms must be in [0, 10000]")

    model = load_model(args.model)
    if args.reference == "none":
        reference: type = Predictor
    else:
        try:
            reference = load_reference(args.reference, ("online",))["online"].Predictor
        except RuntimeError as err:
            raise SystemExit(f"reference {args.reference}: not available ({err})") from None
    events = drive(args.minutes, args.seed, args.joy_hz)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"model {args.model} (s = {model.feature_config.lags}); a {args.minutes:g}-minute "
          f"tile drive, joystick at {args.joy_hz:g} Hz; reference {args.reference[:12]}; "
          f"idle {args.idle_ms:g} ms before each call")
    print("predict(), ms per path: p50 / p90 / p99 current | reference | ratio current / "
          "reference")
    modes = {"off": [None], "on": [AdaptSettings()], "both": [None, AdaptSettings()]}
    for adapt in modes[args.adapt]:
        cur, ref, n, worst = side_by_side(model, (Predictor, reference), adapt, events,
                                          args.idle_ms / 1e3)
        a, b = percentiles(cur), percentiles(ref)
        label = "adapting    " if adapt is not None else "not adapting"
        print(f"  {label} {n} paths: "
              + " / ".join(f"{x:.3f}" for x in a) + " | "
              + " / ".join(f"{x:.3f}" for x in b) + " | "
              + " / ".join(f"{x / y:.2f}" for x, y in zip(a, b, strict=True))
              + f"   largest difference of the paths {worst:.1e}")


if __name__ == "__main__":
    main()
