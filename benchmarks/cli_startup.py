"""Start-up of the ``asgp`` command: a command that names its subcommand imports that module
alone, against every subcommand's module imported (the parser as it was built before).

Usage::

    python benchmarks/cli_startup.py                     # asgp info MODEL, asgp --help
    python benchmarks/cli_startup.py --runs 10 --model docs/reproduction/models/tile_asgp.npz

Each run is a fresh interpreter (``python -c``), timed from its start to its exit; the two
ways alternate, so that the machine's load falls on both. Prints figures only (no
assertions). The reference is the same ``asgp_ros.cli.main`` with the subcommand's name
hidden from it, which builds the parser of every command, as ``asgp --help`` does.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MODEL = ROOT / "docs" / "reproduction" / "models" / "tile_asgp.npz"

#: ``asgp ARGS``, as the console script runs it.
NAMED = "import sys; from asgp_ros.cli import main; sys.exit(main({args!r}))"
#: The same, every subcommand's module imported first (the name not seen).
EVERY = ("import sys; from asgp_ros import cli; cli._named_command = lambda argv: None; "
         "sys.exit(cli.main({args!r}))")


def _run(code: str) -> float:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.DEVNULL,
                       stderr=subprocess.PIPE, text=True, check=False)
    seconds = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{code!r} exited {r.returncode}: {r.stderr.strip()[-500:]}")
    return seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="runs of each (alternated)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="for asgp info")
    args = ap.parse_args()
    if args.runs < 1:
        ap.error("--runs must be >= 1")
    if not args.model.is_file():
        ap.error(f"no model file {args.model}")

    print(f"python {platform.python_version()} on {platform.machine()}, {args.runs} runs "
          "each, fresh interpreters, alternated")
    bare = _run("pass")
    print(f"an empty interpreter: {bare * 1e3:.0f} ms")
    commands = [["info", str(args.model)], ["train", "--help"]]
    for words in commands:
        named, every = [], []
        for _ in range(args.runs):
            named.append(_run(NAMED.format(args=words)))
            every.append(_run(EVERY.format(args=words)))
        a, b = statistics.median(named), statistics.median(every)
        shown = " ".join(w if w.startswith("-") else Path(w).name for w in words)
        print(f"asgp {shown}: its module alone {a:.2f} s (min {min(named):.2f}), every "
              f"module {b:.2f} s (min {min(every):.2f}); ratio {a / b:.2f}")
    top = [_run(NAMED.format(args=["--help"])) for _ in range(args.runs)]
    print(f"asgp --help (every module, by design): {statistics.median(top):.2f} s "
          f"(min {min(top):.2f})")


if __name__ == "__main__":
    main()
