"""The paper's recordings, simulated: 8 tile, 8 carpet, 2 hybrid bags (``asgp dataset``).

Layout::

    DIR/manifest.json
    DIR/tile/tile_01 ... tile_08        (ROS 2 bags)
    DIR/carpet/carpet_01 ... carpet_08
    DIR/hybrid/hybrid_01, hybrid_02

Each bag lasts 20 * scale minutes and has its own seed (``seed * 100 + n``, n = 1..18),
so a dataset is reproducible bag by bag. The manifest lists every bag with its surface,
seed, length, message counts, VO failures and the paper's split (per surface, bags 1-6
train and 7-8 test; hybrid bags are test only). Bags already present with the same
surface, seed, length and storage are kept (an interrupted run resumes); one of them
that is damaged (cut or lost since) is simulated again.

:func:`build_dataset` is what ``asgp dataset`` runs, and what ``asgp reproduce --quick``
runs to make its small dataset.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asgp_ros.common.fileio import (
    DATASET_DIR,
    atomic_write_text,
    check_output,
    describe_kind,
    interruptible_imap,
    is_ros2_bag,
    worker_pool,
    write_marker,
)
from asgp_ros.common.topics import BAG_GROUND_TRUTH, BAG_JOY, BAG_VO_TWIST
from asgp_ros.recording.bags import BagError, read_sim_metadata, recover_bag, write_bag
from asgp_ros.sim.simulate import simulate

LAYOUT = (("tile", 8), ("carpet", 8), ("hybrid", 2))
BAG_MINUTES = 20.0
#: The shortest bag a dataset may have (minutes): below, nothing but lead-in and tail.
MIN_BAG_MINUTES = 0.1
MANIFEST_VERSION = 1
log = logging.getLogger(__name__)

STORAGES = ("mcap", "sqlite3")

#: progress(bags done, bags in all, name of the bag just done ("" at the start), seconds).
Progress = Callable[[int, int, str, float], None]


class DatasetOptionError(ValueError):
    """An argument of :func:`build_dataset` is out of range; nothing was written.

    Attributes:
        option: the argument's name (that of the ``asgp dataset`` option too).
        problem: what is wrong with it.
    """

    def __init__(self, option: str, problem: str) -> None:
        super().__init__(f"{option} {problem}")
        self.option = option
        self.problem = problem


class DatasetError(RuntimeError):
    """A bag could not be made (a stranger's file in the way, a failed simulation...)."""


@dataclass(frozen=True)
class BuiltDataset:
    """What :func:`build_dataset` did."""

    root: Path
    manifest: dict[str, Any]
    reused: int
    seconds: float

    @property
    def manifest_path(self) -> Path:
        return self.root / "manifest.json"

    def describe(self) -> str:
        """One line: where, how many bags of which length, how many kept, how long."""
        return (f"{self.root}: {len(self.manifest['bags'])} bags of "
                f"{self.manifest['bag_minutes']:g} min ({self.reused} already present) in "
                f"{self.seconds:.1f} s; manifest {self.manifest_path}")


def check_options(*, scale: float, seed: int, jobs: int) -> None:
    """Raise :class:`DatasetOptionError` for arguments :func:`build_dataset` refuses."""
    if not scale > 0.0 or BAG_MINUTES * scale < MIN_BAG_MINUTES:
        raise DatasetOptionError(
            "scale", f"must give bags of at least {MIN_BAG_MINUTES:g} min, got {scale}")
    if jobs < 1:
        raise DatasetOptionError("jobs", "must be >= 1")
    if seed < 0:
        raise DatasetOptionError("seed", "must be >= 0")


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


def _damage(path: Path) -> str | None:
    """What is wrong with a bag already there (None: it is intact)."""
    try:
        damage = recover_bag(path, topics=()).damage  # the bytes of no topic are kept
    except BagError as exc:
        return str(exc)
    return None if damage.intact else "; ".join(damage.problems)


def _make(job: tuple[str, dict[str, Any], str, bool]) -> dict[str, Any]:
    """Simulate and write one bag (or keep the one there); runs in a pool worker."""
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
            suffix = {"mcap": ".mcap", "sqlite3": ".db3"}[storage]
            if not any(e.name.endswith(suffix) for e in os.scandir(path)):
                raise RuntimeError(f"{path} is this dataset's bag in another storage than "
                                   f"{storage}; use --force to simulate the bags again")
            damage = _damage(path)
            if damage is None:
                return {**bag, **meta.get("summary", {}), "reused": True,
                        "seconds": time.perf_counter() - start}
            # its own bag, cut or lost since it was written: made again, not reused
            log.warning("%s is damaged (%s): simulating it again", path, damage)
        elif not force:
            raise RuntimeError(f"{path} exists and is not this dataset's bag; use --force "
                               "to replace it")
    rec = simulate(bag["surface"], bag["minutes"], bag["seed"])
    summary = {"joy_messages": int(rec.joy_t.size), "vo_messages": int(rec.vo_t.size),
               "vo_failures": int(rec.failures.shape[0]),
               "moving_s": rec.meta["moving_s"]}
    rec.meta["summary"] = summary
    write_bag(path, rec, storage=storage)
    return {**bag, **summary, "reused": False, "seconds": time.perf_counter() - start}


def build_dataset(out: str | os.PathLike[str], *, scale: float = 1.0, seed: int = 0,
                  jobs: int = 1, storage: str = "mcap", force: bool = False,
                  progress: Progress | None = None) -> BuiltDataset:
    """Simulate the paper's dataset into ``out`` (module docstring) and write its manifest.

    ``out`` is checked first (:func:`asgp_ros.common.fileio.check_output`): a new directory, or
    a dataset directory (carrying the dataset's marker file), which is resumed; anything
    else is refused. With ``force``, bags already there are simulated again (only bags
    are replaced). ``jobs`` > 1 simulates in a pool of that many processes.

    Raises:
        DatasetOptionError: an argument out of range (before anything is written).
        asgp_ros.common.fileio.OutputError: ``out`` is refused.
        DatasetError: a bag could not be made; the bags made so far are kept.
    """
    check_options(scale=scale, seed=seed, jobs=jobs)
    if storage not in STORAGES:
        raise DatasetOptionError("storage", f"must be one of {', '.join(STORAGES)}, got "
                                            f"{storage!r}")
    report = progress or (lambda done, total, name, elapsed: None)
    root = check_output(out, DATASET_DIR)
    root.mkdir(parents=True, exist_ok=True)
    write_marker(root, "dataset")  # from here on an interrupted run resumes here
    # Until this run ends the directory is not the dataset an earlier manifest described:
    # `--force` with another --scale, stopped half-way, left the old manifest beside a mix
    # of bags of both, and `asgp reproduce` used them, stating the old scale.
    try:
        atomic_write_text(root / "manifest.json", json.dumps(
            {"format": "asgp_ros.dataset", "version": MANIFEST_VERSION, "unfinished": True,
             "seed": seed, "scale": scale, "storage": storage, "bags": []}, indent=2) + "\n")
    except OSError as exc:
        raise DatasetError(f"{root / 'manifest.json'}: cannot be written: "
                           f"{exc.strerror or exc}") from exc
    bags = plan(seed, scale)
    jobs_args = [(str(root), b, storage, force) for b in bags]
    start = time.perf_counter()
    results: dict[str, dict[str, Any]] = {}
    report(0, len(jobs_args), "", 0.0)
    try:
        if jobs == 1:
            for job in jobs_args:
                r = _make(job)
                results[r["name"]] = r
                report(len(results), len(jobs_args), r["name"], time.perf_counter() - start)
        else:
            # On an error or a signal the workers stop at once (each removes its own
            # temporaries on the way out) instead of finishing the queue.
            with worker_pool(jobs) as pool:
                for r in interruptible_imap(pool, _make, jobs_args):
                    results[r["name"]] = r
                    report(len(results), len(jobs_args), r["name"],
                           time.perf_counter() - start)
    except (RuntimeError, ValueError, OSError, BagError) as exc:
        raise DatasetError(str(exc)) from exc
    manifest: dict[str, Any] = {
        "format": "asgp_ros.dataset",
        "version": MANIFEST_VERSION,
        "description": "Simulated wheelchair recordings in the layout of Fan et al. "
                       "(ICRA 2018): 8 tile, 8 carpet, 2 hybrid bags.",
        "seed": seed,
        "scale": scale,
        "bag_minutes": BAG_MINUTES * scale,
        "storage": storage,
        "topics": manifest_topics(),
        "bags": [{k: v for k, v in results[b["name"]].items() if k not in ("seconds",)}
                 for b in bags],
    }
    for b in manifest["bags"]:
        b.pop("reused", None)
    atomic_write_text(root / "manifest.json", json.dumps(manifest, indent=2) + "\n")
    reused = sum(1 for r in results.values() if r.get("reused"))
    return BuiltDataset(root, manifest, reused, time.perf_counter() - start)


def manifest_topics(manifest: dict[str, Any] | None = None) -> dict[str, str]:
    """The bag topics by role ("joy", "twist", "truth"): a manifest's, or the defaults
    (those the simulated bags are written with) for what it does not say."""
    topics = (manifest or {}).get("topics") or {}
    defaults = {"joy": BAG_JOY, "twist": BAG_VO_TWIST, "truth": BAG_GROUND_TRUTH}
    return {role: str(topics.get(role, default)) for role, default in defaults.items()}
