"""The shared-control layer over many simulated drives: contacts with and without it.

One drive is chaotic (one different decision changes the rest of it), so versions of the
layer are compared over many seeds. For every seed, drives of an inattentive user
(:func:`asgp_ros.sim.shared_drive.drive`) in each of ``--modes`` (:data:`MODES`; by default
without the layer and with it as the node runs it by default: the heading sampled, earlier
scans remembered, carried by scan matching; the velocity from the matched scans while they
match and from the VO, which loses tracking as a camera does, while they do not). Prints
each drive and the totals: contacts, interventions, the share of time the user's command
passed untouched, the deepest overlap with the furniture, the decisions' solve p50 / p99.

With ``--audit``, every decision of the layer is also checked against the plant
(:func:`asgp_ros.sim.shared_drive.drive`'s ``audit``): the share of the interventions whose
user command, held to the end of the predicted path as the layer assumes, would have touched
("needed"), the decisions that let a touching command pass ("missed"), and how often a held
command touched against the probability the layer gave it, and against the probability the
same check of the same prediction gives with the room's true map in place of the scans
(``p_map``): where the layer's probability is high and the map's low, the scans' obstacle
points, not the prediction, made it so; and the share of those obstacle points that lie
short of the furniture (the scanner's range noise).

Usage: benchmarks/shared_drives.py [MODEL] [--seeds 1-13] [--minutes 10] [--jobs 2]
[--fov DEG] [--modes none,memory] [--contacts] [--audit] [--vo-noise X]
[--velocity-source auto|vo|scan_matching] [--no-vo-losses] [--surface tile|carpet|hybrid]
(the README's figures: the
reproduction's tile model, seeds 1-13, 10 minutes; ``--fov 360`` for a scanner that also
sees behind the chair; about 5 minutes on 2 cores for the two default modes).
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import sys
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from asgp_ros.core.adaptive import AdaptSettings
from asgp_ros.core.modelfile import load_model
from asgp_ros.core.obstacle_memory import MemoryConfig
from asgp_ros.core.scan_match import VELOCITY_SOURCES
from asgp_ros.core.shared_control import SharedControlConfig
from asgp_ros.sim.lidar import LidarConfig
from asgp_ros.sim.shared_drive import DEFAULT_MEMORY, SHORT_OF_FURNITURE_M, VO_NOISE, drive

#: the committed reproduction's tile model
DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "docs/reproduction/models/tile_asgp.npz"

MODES = ("none", "mean heading", "heading sampled", "memory", "scan memory", "adapting")
"""Without the layer; with it checking the mean heading or sampling it (as the node does by
default), against the newest scan alone; sampling it against the scan and the memory of
earlier scans (``memory_s`` > 0), carried by the VO's twists ("memory") or by matching
the scans ("scan memory", :mod:`asgp_ros.core.scan_match`); "scan memory" with the layer's
predictor adapting online ("adapting": ``adapt.enabled``, the default settings)."""
DEFAULT_MODES = ("none", "scan memory")
"""Without the layer, and with it as the node runs it by default."""
MARGIN = 0.05
"""The layer's footprint is the chair's grown by this (m), as in ``drive``'s default."""
P_BINS = (0.0, 0.01, 0.05, 0.2, 0.5, 0.9, 1.0)


def _one(task: tuple[str, int, str, float, float, float, bool, float, str, bool, str, float]
         ) -> dict[str, Any]:
    (path, seed, mode, minutes, fov, memory_s, audit, vo_scale, velocity_source,
     vo_losses, surface, camera_yaw) = task
    memory_mode = mode in ("memory", "scan memory", "adapting")
    # the default scanner, or another field of view at its angular resolution (4 beams/deg)
    lidar = None if fov == LidarConfig().fov_deg else LidarConfig(fov_deg=fov,
                                                                  beams=round(4 * fov))
    with threadpool_limits(limits=1):
        result = drive(load_model(path), 60.0 * minutes, seed, layer=mode != "none",
                       config=SharedControlConfig(heading_uncertainty=mode != "mean heading"),
                       lidar=lidar,
                       memory=MemoryConfig(max_age_s=memory_s) if memory_mode else None,
                       memory_odometry="dead_reckoning" if mode == "memory"
                       else "scan_matching", margin=MARGIN, audit=audit,
                       vo_noise=(vo_scale * VO_NOISE[0], vo_scale * VO_NOISE[1]),
                       velocity_source=velocity_source if mode != "none" else "vo",
                       vo_losses=vo_losses, surface=surface, camera_yaw=camera_yaw,
                       adapt=AdaptSettings() if mode == "adapting" else None)
    return result.summary() | {"seed": seed, "mode": mode, "events": result.contact_events,
                               "audit": [(r.p_user, r.intervened, r.clearance_m, r.touched,
                                          r.p_map) for r in result.audit],
                               "points": (result.obstacle_points, result.points_short)}


def _seeds(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def _modes(text: str) -> tuple[str, ...]:
    modes = tuple(m.strip() for m in text.split(","))
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown modes {unknown}; known: {MODES}")
    return modes


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", nargs="?", default=str(DEFAULT_MODEL),
                    help="model file (default: the committed tile model)")
    ap.add_argument("--seeds", type=_seeds, default=_seeds("1-13"))
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--fov", type=float, default=270.0, help="scanner field of view (deg)")
    ap.add_argument("--memory-s", type=float, default=DEFAULT_MEMORY.max_age_s,
                    help="how long the memory keeps a point (s)")
    ap.add_argument("--modes", type=_modes, default=DEFAULT_MODES,
                    help=f"comma-separated, of {', '.join(MODES)}")
    ap.add_argument("--contacts", action="store_true",
                    help="also print every contact: the layer's last decision before it and "
                         "how far from the touching footprint the nearest obstacle point it "
                         "knew (scan or memory) was")
    ap.add_argument("--audit", action="store_true",
                    help="check every decision against the plant: interventions needed, "
                         "touching commands let pass, probabilities against outcomes")
    ap.add_argument("--vo-noise", type=float, default=1.0,
                    help="the VO's noise as a multiple of the offline drive's "
                         f"({VO_NOISE[0]:g} m/s, {VO_NOISE[1]:g} rad/s per twist)")
    ap.add_argument("--velocity-source", choices=VELOCITY_SOURCES, default="auto",
                    help="where the layer's predictor takes the velocity from (auto: the "
                         "matched scans', the VO's while they do not match)")
    ap.add_argument("--no-vo-losses", action="store_true",
                    help="the VO never loses tracking (by default it does, in episodes at "
                         "the floor's rate and when the camera faces something nearer than "
                         "its minimum depth)")
    ap.add_argument("--camera-yaw", type=float, default=0.0,
                    help="where the VO's camera looks, from the chair's forward (rad): 0, "
                         "forward (default: the worst case, losses as the chair heads for "
                         "something); the package's camera looks backward, 3.1416, which "
                         "the scans tell of only with --fov 360")
    ap.add_argument("--surface", choices=("tile", "carpet", "hybrid"), default="tile",
                    help="the floor driven on (its room, chair and VO losses): a model "
                         "trained on another floor shows what adapting does")
    args = ap.parse_args(argv)
    if not (np.isfinite(args.vo_noise) and 0.0 <= args.vo_noise <= 100.0):
        ap.error(f"--vo-noise must be in [0, 100], got {args.vo_noise}")
    tasks = [(args.model, seed, mode, args.minutes, args.fov, args.memory_s, args.audit,
              args.vo_noise, args.velocity_source, not args.no_vo_losses, args.surface,
              args.camera_yaw)
             for seed in args.seeds for mode in args.modes]
    with multiprocessing.Pool(args.jobs) as pool:
        rows = pool.map(_one, tasks)
    print(f"{len(args.seeds)} seeds x {args.minutes:g} min on {args.surface}, scanner "
          f"{args.fov:g} deg, "
          f"memory {args.memory_s:g} s, VO noise x {args.vo_noise:g}, the layer's velocity "
          f"from {args.velocity_source}, VO losses "
          f"{'off' if args.no_vo_losses else 'on'} (camera at {args.camera_yaw:g} rad)")
    print("seed | mode            | contacts | interventions | intervening (s) | mean change "
          "| untouched | deepest (m) | solve p50 / p99 ms")
    for r in rows:
        print(f"{r['seed']:4d} | {r['mode']:15s} | {r['contacts']:8d} | "
              f"{r['interventions']:13d} | {r['intervention_s']:15.1f} | "
              f"{r['mean_change']:11.2f} | {100 * r['untouched_share']:8.1f}% | "
              f"{r['min_clearance_m']:11.3f} | {r['solve_p50_ms']:.1f} / {r['solve_p99_ms']:.0f}")
    if args.contacts:
        print("contacts: seed | mode | t (s) | decision | p of the command | nearest known "
              "obstacle to the footprint (m)")
        for r in rows:
            for e in r["events"]:
                print(f"  {r['seed']:4d} | {r['mode']:15s} | {e['t']:7.2f} | "
                      f"{e.get('decision', '-'):15s} | {e.get('p_command', float('nan')):.3f} "
                      f"| {e.get('known_obstacle_m', float('nan')):.3f}")
    print("totals:")
    for mode in args.modes:
        mine = [r for r in rows if r["mode"] == mode]
        untouched = np.array([r["untouched_share"] for r in mine])
        print(f"  {mode:15s}: {sum(r['contacts'] for r in mine)} contacts, "
              f"{sum(r['interventions'] for r in mine)} interventions, untouched "
              f"{100 * untouched.mean():.1f} % on average ({100 * untouched.min():.1f}-"
              f"{100 * untouched.max():.1f} % per drive)")
        adapting = [r for r in mine if "adapt_rows_absorbed" in r]
        if adapting:
            print(f"  {'':15s}  the layer's predictor at the end: "
                  + "; ".join(f"seed {r['seed']}: {r['adapt_rows_absorbed']} steps learnt, "
                              f"{r['adapt_steps_refused']} refused, "
                              f"{'adapted' if r['adapt_adapted_published'] else 'trained'}, "
                              f"scale <= {r['adapt_scale_max']:.2f}, coverage "
                              f"{100 * r['adapt_coverage_95']:.1f} %" for r in adapting))
    if args.audit:
        _print_audit(rows, args.modes)
    return 0


def _print_audit(rows: list[dict[str, Any]], modes: tuple[str, ...]) -> None:
    print("audit (the user's command held to the end of the layer's path, driven by a copy of "
          "the chair):")
    print("seed | mode            | interventions | needed | missed")
    for r in rows:
        if r["audit"]:
            print(f"{r['seed']:4d} | {r['mode']:15s} | {r['audit_interventions']:13d} | "
                  f"{100 * r['audit_needed_share']:5.1f}% | {r['audit_missed']:6d}")
    for mode in modes:
        a = np.array([row for r in rows if r["mode"] == mode for row in r["audit"]],
                     dtype=float).reshape(-1, 5)  # p, intervened, clearance, touched, p_map
        if not a.size:
            continue
        acted = a[:, 1] > 0
        print(f"  {mode}: {int(acted.sum())} intervening decisions, "
              f"{100 * a[acted, 3].mean():.1f} % needed (their held command touched; "
              f"{100 * (a[acted, 2] < MARGIN).mean():.1f} % with the layer's margin); "
              f"{int(a[~acted, 3].sum())} of {int((~acted).sum())} passing decisions let a "
              "touching command pass")
        seen = sum(r["points"][0] for r in rows if r["mode"] == mode)
        short = np.sum([r["points"][1] for r in rows if r["mode"] == mode], axis=0)
        if seen:
            print(f"    the checks' obstacle points: {seen}; short of the furniture by more "
                  "than " + ", ".join(f"{100 * d:.0f} cm: {100 * c / seen:.2f} %" for d, c in
                                      zip(SHORT_OF_FURNITURE_M, short, strict=True)))
        for col, name in ((0, "p (layer)  "), (4, "p (map)    ")):
            print(f"    {name} | decisions | mean p (layer / map) | touched | "
                  "footprint + margin touched")
            for lo, hi in itertools.pairwise(P_BINS):
                sel = (a[:, col] >= lo) & ((a[:, col] < hi) | (hi == P_BINS[-1]))
                if sel.any():
                    print(f"    {lo:4.2f} - {hi:4.2f} | {int(sel.sum()):9d} | "
                          f"{a[sel, 0].mean():10.3f} / {np.nanmean(a[sel, 4]):5.3f} | "
                          f"{100 * a[sel, 3].mean():6.1f}% | "
                          f"{100 * (a[sel, 2] < MARGIN).mean():6.1f}%")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
