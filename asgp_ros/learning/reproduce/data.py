"""The dataset of a reproduction: its bags per surface, its manifest and the paper's split.

:func:`discover` finds the bags of DIR/{tile,carpet,hybrid}/, :func:`read_manifest` reads
the manifest ``asgp dataset`` writes (refusing anything else without blocking on it),
:func:`split` makes the paper's train and test sets, and :func:`build_quick_dataset`
simulates the small dataset ``asgp reproduce --quick`` uses when DIR has none.
"""

from __future__ import annotations

import logging
import math
import os
import shlex
from pathlib import Path
from typing import Any

from asgp_ros.common.fileio import OutputError, describe_kind
from asgp_ros.core.modelfile import loads_bounded, open_regular_file
from asgp_ros.learning.dataset import LAYOUT, BuiltDataset, DatasetError, build_dataset
from asgp_ros.learning.dataset import Progress as DatasetProgress
from asgp_ros.learning.reproduce.protocol import ReproduceError

log = logging.getLogger(__name__)

SURFACES = tuple(surface for surface, _count in LAYOUT)
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
#: Scale of the dataset that ``--quick`` builds when DIR has none (18 one-minute-ish bags).
QUICK_SCALE = 0.06


def _is_bag(p: Path) -> bool:
    if p.name.startswith("."):
        return False
    if p.is_file():
        return p.suffix in BAG_SUFFIXES
    return p.is_dir() and (p / "metadata.yaml").exists()


def discover(data: str | os.PathLike[str]) -> dict[str, list[Path]]:
    """Bags per surface in DIR/{tile,carpet,hybrid}/, sorted by name."""
    root = Path(data)
    if not root.is_dir():
        what = ("does not exist" if not os.path.lexists(root)
                else f"is {describe_kind(root)}, not a directory")
        raise ReproduceError(f"dataset directory {root} {what} (make one with "
                             "`asgp dataset --out DIR`)")
    out = {}
    for surface in SURFACES:
        d = root / surface
        out[surface] = sorted((p for p in d.iterdir() if _is_bag(p)),
                              key=lambda p: p.name) if d.is_dir() else []
    return out


def discover_safe(data: Path) -> dict[str, list[Path]]:
    """:func:`discover`, or no bags where ``data`` is not a dataset directory."""
    try:
        return discover(data)
    except ReproduceError:
        return {}


def split(bags: dict[str, list[Path]], manifest: dict[str, Any] | None = None
          ) -> tuple[dict[str, list[Path]], dict[str, list[Path]]]:
    """The paper's train and test sets from the bags per surface (see
    :mod:`asgp_ros.learning.reproduce`).

    With the manifest of ``asgp dataset``, its per-bag "split" decides which tile and carpet
    bags are held out; otherwise the last two of each surface (sorted by name) are.
    """
    held_out: set[str] | None = None
    if manifest is not None:
        held_out = {Path(b["path"]).name for b in manifest.get("bags", [])
                    if b.get("split") == "test"}
        # a test bag the manifest names, gone from the dataset: the last two of the others
        # were tested on, bags the manifest keeps for training, without a word
        missing = sorted(Path(b["path"]).as_posix() for b in manifest.get("bags", [])
                         if b.get("split") == "test" and _surface(b["path"]) in ("tile", "carpet")
                         and Path(b["path"]).name not in {p.name for p in
                                                          bags.get(_surface(b["path"]), [])})
        if missing:
            raise ReproduceError(f"the dataset's manifest holds out {', '.join(missing)} for "
                                 "testing, and the dataset has no such bag: put them back, or "
                                 "make the dataset again (`asgp dataset`)")
    tile, carpet, hybrid = bags["tile"], bags["carpet"], bags["hybrid"]
    problems = []
    for name, lst, need in (("tile", tile, 4), ("carpet", carpet, 4), ("hybrid", hybrid, 1)):
        if len(lst) < need:
            problems.append(f"{len(lst)} {name} bag(s) (need >= {need})")
    if problems:
        raise ReproduceError("the dataset has " + ", ".join(problems) +
                             "; the paper's layout is 8 tile, 8 carpet, 2 hybrid")

    def cut(lst: list[Path]) -> tuple[list[Path], list[Path]]:
        if held_out:
            test = [p for p in lst if p.name in held_out]
            if test and len(test) < len(lst):
                return [p for p in lst if p.name not in held_out], test
        return lst[:-2], lst[-2:]

    tile_train, tile_test = cut(tile)
    carpet_train, carpet_test = cut(carpet)
    half_t, half_c = math.ceil(len(tile_train) / 2), math.ceil(len(carpet_train) / 2)
    train = {"Tile": tile_train, "Carpet": carpet_train,
             "Both": tile_train[:half_t] + carpet_train[:half_c]}
    test = {"Tile": tile_test, "Carpet": carpet_test, "Hybrid": hybrid[-2:]}
    return train, test


def _surface(path: str) -> str:
    """The surface directory of a manifest's bag path ('tile/tile_07' -> 'tile')."""
    parts = Path(path).parts
    return parts[0] if len(parts) > 1 else ""


MAX_MANIFEST_BYTES = 16 * 1024 * 1024
"""A dataset manifest lists a few dozen bags: a larger file is not one."""


def read_manifest(data: Path) -> dict[str, Any] | None:
    """DIR/manifest.json of ``asgp dataset``, or None when absent.

    The file must be a regular file of at most 16 MiB (a FIFO, a device or a directory is
    refused without opening it), JSON of bounded nesting, and laid out as ``asgp dataset``
    writes it: an object whose "bags" is a list of objects with a string "path" (and an
    optional string "split"), and whose optional "topics" maps roles to topic names.
    """
    path = Path(data) / "manifest.json"
    if not os.path.lexists(path):
        return None
    try:
        with open_regular_file(path, MAX_MANIFEST_BYTES) as fh:
            text = fh.read().decode("utf-8")
        manifest = loads_bounded(text, max_chars=MAX_MANIFEST_BYTES)
    except (OSError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
        reason = getattr(exc, "strerror", None) or exc
        raise ReproduceError(f"{path}: not a readable JSON manifest: {reason}") from None
    problem = _manifest_problem(manifest)
    if problem:
        raise ReproduceError(f"{path}: unexpected manifest layout: {problem}")
    assert isinstance(manifest, dict)  # what _manifest_problem checked first
    return manifest


def unfinished_dataset(manifest: dict[str, Any] | None) -> bool:
    """Whether a manifest is the one ``asgp dataset`` writes while it runs (the bags are not
    all made, or are of another dataset)."""
    return manifest is not None and manifest.get("unfinished") is True


def dataset_options(manifest: dict[str, Any] | None, data: Path | None = None) -> str:
    """' (`asgp dataset --out DATA --scale X --seed Y`)' of an unfinished dataset's manifest
    (with ``data``, the command that finishes it as it is: it said no --out), or ''."""
    opts = [f"--{k} {manifest[k]}" for k in ("scale", "seed")
            if manifest is not None and isinstance(manifest.get(k), int | float)
            and not isinstance(manifest.get(k), bool)]
    storage = manifest.get("storage") if manifest is not None else None
    if isinstance(storage, str) and storage != "mcap" and storage.isidentifier():
        opts.append(f"--storage {storage}")  # resumed in another, its bags are refused
    if opts and data is not None:
        opts.insert(0, f"--out {shlex.quote(str(data))}")
    return f" (`asgp dataset {' '.join(opts)}`)" if opts else ""


def _manifest_problem(manifest: Any) -> str | None:
    if not isinstance(manifest, dict):
        return "not a JSON object"
    bags = manifest.get("bags", [])
    if not isinstance(bags, list):
        return '"bags" is not a list'
    for i, b in enumerate(bags):
        if not isinstance(b, dict) or not isinstance(b.get("path"), str):
            return f'bag {i} is not an object with a "path" string'
        if not isinstance(b.get("split", ""), str):
            return f'bag {i}: "split" is not a string'
    topics = manifest.get("topics", {})
    if not isinstance(topics, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in topics.items()):
        return '"topics" does not map roles to topic names'
    return None


def build_quick_dataset(data: Path, scale: float = QUICK_SCALE, *,
                        progress: DatasetProgress | None = None) -> BuiltDataset:
    """Simulate a small paper-layout dataset into ``data`` (:func:`asgp_ros.learning.dataset.
    build_dataset`, as ``asgp dataset --out DATA --scale SCALE --jobs 2``)."""
    log.info("building a small dataset (scale %s) in %s", scale, data)
    try:
        earlier = read_manifest(data) if data.is_dir() else None
    except ReproduceError:
        earlier = None
    try:
        return build_dataset(data, scale=scale, jobs=2, progress=progress)
    except (DatasetError, OutputError, ValueError) as exc:
        if unfinished_dataset(earlier) and earlier is not None \
                and earlier.get("scale") != scale:
            # its bags are another dataset's: `reproduce --force` is about the report
            raise ReproduceError(
                f"{data} holds a dataset that did not finish{dataset_options(earlier)}, "
                f"not the small one --quick makes (--scale {scale:g}): finish it with "
                f"`asgp dataset --out {data}` and its options, or give --data another "
                "directory") from exc
        raise ReproduceError(f"building a dataset in {data} failed: {exc}") from exc
