"""Cost of the shared-control layer's deepening rule (``collision.footprint_deepening``):
the decisions where every candidate is certain to touch (the chair within its margin of a
wall ahead, a cabinet behind, the user reversing while turning into it).

Prints, for scans of 720, 1,081 and 4,000 beams: the median time of ``decide`` with the scan
check as the node builds it (a ``PathCheck``, the deepening rule applied) and, side by side,
with the same check stripped of its deepening (the rule before it: the user's command passes),
and their ratio; the decision each gave.

Usage: benchmarks/shared_control_deepening.py [MODEL] [--repeats N]
(MODEL: default the committed tile model, docs/reproduction/models/tile_asgp.npz).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from asgp_ros.core import collision
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.online import Predictor, PredictorConfig
from asgp_ros.core.shared_control import SharedControlConfig, decide
from asgp_ros.sim.lidar import cast_to_segments

ROOT = Path(__file__).resolve().parents[1]
USER = np.array([-0.49, -0.55])  # reversing while turning
WALLS = [((0.59, -3.0), (0.59, 3.0)), ((-2.5, 0.83), (-0.75, 0.83))]  # ahead, behind left


def scan_of(segments, beams: int) -> collision.Scan:
    """A 360-degree scan at the base origin of line segments."""
    fov = 2 * math.pi * (beams - 1) / beams
    a0, inc = -fov / 2, fov / (beams - 1)
    r = cast_to_segments(a0 + inc * np.arange(beams), segments)
    return collision.Scan(np.where(r > 8.0, np.inf, r), a0, inc, 0.05, 8.0)


def standing(model) -> tuple[Predictor, float]:
    """A predictor fed 4 s of a chair standing (stick neutral, VO with a VO's noise)."""
    pred = Predictor(model, PredictorConfig(horizon_steps=10))
    rng = np.random.default_rng(0)
    events = [(t, "joy") for t in np.arange(1000.0, 1004.0, 1 / 30)]
    events += [(t, "vo") for t in np.arange(1000.01, 1004.0, 1 / 6)]
    for t, kind in sorted(events):
        if kind == "joy":
            pred.feed_joy(t, (0.0, 0.0))
        else:
            pred.feed_vo(t, rng.normal(0.0, 1e-3, 2))
    return pred, 1003.98


def without_deepening(check: collision.PathCheck) -> collision.CollisionCheck:
    """The same check as a plain callable: the layer cannot apply the deepening rule."""
    def plain(pose: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return check(pose, cov)
    return plain


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", nargs="?", default=ROOT / "docs/reproduction/models/tile_asgp.npz")
    ap.add_argument("--repeats", type=int, default=12)
    args = ap.parse_args()
    model = load_model(args.model)
    config = SharedControlConfig()
    footprint = collision.DEFAULT_FOOTPRINT.grown(0.05)
    print(f"model {args.model}; user command {tuple(USER.tolist())}; median of {args.repeats} "
          "decisions (the first two not timed)")
    print("beams | with the deepening rule (ms) | without (ms) | ratio | decision with / without")
    for beams in (720, 1081, 4000):
        scan = scan_of(WALLS, beams)
        times: dict[str, list[float]] = {"with": [], "without": []}
        why = {}
        for _ in range(args.repeats + 2):
            for kind in ("with", "without"):
                pred, now = standing(model)
                check = collision.scan_check(scan, footprint)
                used = check if kind == "with" else without_deepening(check)
                start = time.perf_counter()
                d = decide(pred, now, USER, used, config)
                times[kind].append(time.perf_counter() - start)
                why[kind] = "sent" if d.command is not None else "passed"
        w, wo = (1e3 * float(np.median(times[k][2:])) for k in ("with", "without"))
        print(f"{beams:5d} | {w:28.1f} | {wo:12.1f} | {w / wo:5.2f} | "
              f"{why['with']} / {why['without']}")


if __name__ == "__main__":
    main()
