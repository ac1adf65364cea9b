"""``asgp dataset``: the paper's recordings, simulated: 8 tile, 8 carpet, 2 hybrid bags.

Layout::

    DIR/manifest.json
    DIR/tile/tile_01 ... tile_08        (ROS 2 bags)
    DIR/carpet/carpet_01 ... carpet_08
    DIR/hybrid/hybrid_01, hybrid_02

Each bag lasts 20 * scale minutes and has its own seed (``seed * 100 + n``, n = 1..18),
so a dataset is reproducible bag by bag. The manifest lists every bag with its surface,
seed, length, message counts, VO failures and the paper's split (per surface, bags 1-6
train and 7-8 test; hybrid bags are test only). Bags already present with the same
surface, seed and length are kept (an interrupted run resumes).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

from asgp_ros.cli import CommandError
from asgp_ros.cli._argtypes import cli_integer, cli_number

LAYOUT = (("tile", 8), ("carpet", 8), ("hybrid", 2))
BAG_MINUTES = 20.0
MANIFEST_VERSION = 1


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "dataset",
        help="simulate the paper's dataset: 8 tile, 8 carpet, 2 hybrid bags",
        description="Simulate the paper's recordings (20-minute bags: 8 on tile, 8 on "
                    "carpet, 2 in a hybrid atrium) into DIR/{tile,carpet,hybrid}/ with a "
                    "manifest.json.",
    )
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--scale", type=cli_number("scale"), default=1.0,
                   help="bag length = 20 min x scale (default 1; 0.05 gives 1-min bags)")
    p.add_argument("--seed", type=cli_integer("seed"), default=0,
                   help="base seed (default 0)")
    p.add_argument("--jobs", type=cli_integer("jobs"), default=1,
                   help="parallel processes (default 1)")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    p.add_argument("--force", action="store_true",
                   help="re-simulate bags that exist (only bags are replaced)")
    p.set_defaults(func=run)


def plan(seed: int, scale: float) -> list[dict[str, Any]]:
    """The bags of a dataset: name, relative path, surface, seed, minutes, split."""
    bags = []
    n = 0
    for surface, count in LAYOUT:
        for k in range(1, count + 1):
            n += 1
            split = "test" if surface == "hybrid" or k > count - 2 else "train"
            name = f"{surface}_{k:02d}"
            bags.append({"name": name, "path": f"{surface}/{name}", "surface": surface,
                         "seed": seed * 100 + n, "minutes": BAG_MINUTES * scale,
                         "split": split})
    return bags


def _make(job: tuple[str, dict[str, Any], str, bool]) -> dict[str, Any]:
    from pathlib import Path

    from asgp_ros.bags import read_sim_metadata, write_bag
    from asgp_ros.fileio import describe_kind, is_ros2_bag
    from asgp_ros.sim.simulate import simulate

    root, bag, storage, force = job
    path = Path(root) / bag["path"]
    start = time.perf_counter()
    if os.path.lexists(path):
        if path.is_symlink() or not is_ros2_bag(path):
            raise RuntimeError(f"{path} exists and is {describe_kind(path)}, not a bag; "
                               "refusing to replace it")
        meta = read_sim_metadata(path) if not force else None
        if (meta and meta.get("seed") == bag["seed"] and meta.get("surface") == bag["surface"]
                and abs(meta.get("duration_s", -1) - 60.0 * bag["minutes"]) < 1e-6):
            return {**bag, **meta.get("summary", {}), "reused": True,
                    "seconds": time.perf_counter() - start}
        if not force:
            raise RuntimeError(f"{path} exists and is not this dataset's bag; use --force "
                               "to replace it")
    rec = simulate(bag["surface"], bag["minutes"], bag["seed"])
    summary = {"joy_messages": int(rec.joy_t.size), "vo_messages": int(rec.vo_t.size),
               "vo_failures": int(rec.failures.shape[0]),
               "moving_s": rec.meta["moving_s"]}
    rec.meta["summary"] = summary
    write_bag(path, rec, storage=storage)
    return {**bag, **summary, "reused": False, "seconds": time.perf_counter() - start}


def _progress(done: int, total: int, label: str, elapsed: float) -> None:
    width = 30
    filled = int(width * done / total)
    bar = "#" * filled + "." * (width - filled)
    sys.stderr.write(f"\r[{bar}] {done}/{total} {label:<18} {elapsed:6.1f} s")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def run(args: argparse.Namespace) -> int:
    import json
    import multiprocessing

    from asgp_ros.bags import BagError
    from asgp_ros.fileio import (
        DATASET_DIR,
        atomic_write_text,
        check_output,
        interruptible_imap,
        quiet_worker_exit,
        signals_deferred,
        write_marker,
    )

    if not args.scale > 0.0 or BAG_MINUTES * args.scale < 0.1:
        raise CommandError(f"--scale must give bags of at least 0.1 min, got {args.scale}")
    if args.jobs < 1:
        raise CommandError("--jobs must be >= 1")
    if args.seed < 0:
        raise CommandError("--seed must be >= 0")
    root = check_output(args.out, DATASET_DIR)
    root.mkdir(parents=True, exist_ok=True)
    write_marker(root, "dataset")  # from here on an interrupted run resumes here
    bags = plan(args.seed, args.scale)
    jobs = [(str(root), b, args.storage, args.force) for b in bags]
    start = time.perf_counter()
    results: dict[str, dict[str, Any]] = {}
    _progress(0, len(jobs), "", 0.0)
    try:
        if args.jobs == 1:
            for job in jobs:
                r = _make(job)
                results[r["name"]] = r
                _progress(len(results), len(jobs), r["name"], time.perf_counter() - start)
        else:
            # On an error or a signal, terminate() stops the workers at once (each removes
            # its own temporaries on the way out) instead of finishing the queue.
            ctx = multiprocessing.get_context("fork")
            with signals_deferred():  # a signal inside fork's hooks would be lost
                pool = ctx.Pool(args.jobs, initializer=quiet_worker_exit)
            with pool:
                for r in interruptible_imap(pool, _make, jobs):
                    results[r["name"]] = r
                    _progress(len(results), len(jobs), r["name"], time.perf_counter() - start)
    except (RuntimeError, ValueError, OSError, BagError) as exc:
        sys.stderr.write("\n")
        raise CommandError(str(exc)) from exc
    manifest = {
        "format": "asgp_ros.dataset",
        "version": MANIFEST_VERSION,
        "description": "Simulated wheelchair recordings in the layout of Fan et al. "
                       "(ICRA 2018): 8 tile, 8 carpet, 2 hybrid bags.",
        "seed": args.seed,
        "scale": args.scale,
        "bag_minutes": BAG_MINUTES * args.scale,
        "storage": args.storage,
        "topics": {"joy": "/joy", "twist": "/vo/twist", "truth": "/ground_truth/odom"},
        "bags": [{k: v for k, v in results[b["name"]].items() if k not in ("seconds",)}
                 for b in bags],
    }
    for b in manifest["bags"]:
        b.pop("reused", None)
    atomic_write_text(root / "manifest.json", json.dumps(manifest, indent=2) + "\n")
    reused = sum(1 for r in results.values() if r.get("reused"))
    print(f"{root}: {len(bags)} bags of {BAG_MINUTES * args.scale:g} min "
          f"({reused} already present) in {time.perf_counter() - start:.1f} s; "
          f"manifest {root / 'manifest.json'}")
    return 0
