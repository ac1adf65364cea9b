"""Fuzzing, long profile: test/test_fuzz.py with many examples per target, every finding
collected instead of stopping at the first.

Runs pytest on test/test_fuzz.py with ASGP_FUZZ_EXAMPLES examples per test (weighted per
target), at most --budget seconds per target, and every case's outcome logged
(ASGP_FUZZ_COLLECT). Prints the number of cases per target, then every distinct finding
(grouped by cause: exception and place, or the hung function, or the rule broken) with
its shortest reproducer: the ``asgp`` arguments or library call, how each file of the
case was made, the exit code and stderr. The files of each finding are kept (--keep), and
each command-line finding is run once more as a real ``python -m asgp_ros.cli`` process in
a copy of them to confirm it.

    python benchmarks/fuzz.py [--examples 400] [--budget 50] [--timeout 10] [--seed N]
                              [--keep DIR] [--json OUT] [-k EXPRESSION] [--no-fail]

Exit code 1 when there is a finding (0 with --no-fail), 2 when the harness itself failed.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def run_pytest(args: argparse.Namespace, log: Path, keep: Path) -> tuple[int, str, float]:
    env = dict(os.environ, ASGP_FUZZ_EXAMPLES=str(args.examples),
               ASGP_FUZZ_BUDGET=str(args.budget), ASGP_FUZZ_TIMEOUT=str(args.timeout),
               ASGP_FUZZ_COLLECT=str(log), ASGP_FUZZ_KEEP=str(keep))
    if args.seed is not None:
        env["ASGP_FUZZ_SEED"] = str(args.seed)
    cmd = [sys.executable, "-m", "pytest", "test/test_fuzz.py", "-q", "-p", "no:cacheprovider",
           f"--timeout={int(args.budget * 2 + 600)}", "-ra"]
    if args.k:
        cmd += ["-k", args.k]
    start = time.monotonic()
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    return proc.returncode, proc.stdout + proc.stderr, time.monotonic() - start


def read_log(log: Path) -> list[dict[str, Any]]:
    if not log.exists():
        return []
    return [json.loads(line) for line in log.read_text().splitlines() if line.strip()]


def _copy_case(src: Path, dest: Path) -> None:
    """A copy of a kept case directory: FIFOs as FIFOs, symlinks as symlinks."""
    dest.mkdir(parents=True)
    for entry in os.scandir(src):
        target = dest / entry.name
        mode = entry.stat(follow_symlinks=False).st_mode
        if entry.is_symlink():
            os.symlink(os.readlink(entry.path), target)
        elif stat.S_ISDIR(mode):
            _copy_case(Path(entry.path), target)
        elif stat.S_ISFIFO(mode):
            os.mkfifo(target)
        else:
            size = entry.stat().st_size
            if size > 16 * 2**20:  # a sparse giant: same size, no data
                with open(target, "wb") as fh:
                    fh.truncate(size)
            else:
                shutil.copyfile(entry.path, target)


def confirm(finding: dict[str, Any], timeout: float) -> str | None:
    """Run a command-line finding's case as a real process; its exit code and stderr."""
    argv, kept = finding.get("argv"), finding.get("kept")
    if argv is None or not kept or not (Path(kept) / "case").is_dir():
        return None
    with tempfile.TemporaryDirectory(prefix="asgp-fuzz-confirm-") as tmp:
        case = Path(tmp) / "case"
        _copy_case(Path(kept) / "case", case)
        env = dict(os.environ, TMPDIR=tmp, ROS_LOG_DIR=str(Path(tmp) / "ros_log"))
        proc = subprocess.Popen([sys.executable, "-m", "asgp_ros.cli", *argv], cwd=case,
                                env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            _out, err = proc.communicate(timeout=timeout)
            lines = [ln for ln in err.splitlines() if ln.strip()]
            tail = "\n".join(compact(lines)[-12:])
            return f"exit {proc.returncode}, {len(lines)} stderr line(s)" + (
                f":\n{tail}" if tail else "")
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            return f"no result within {timeout:g} s (killed)"


def compact(lines: list[str]) -> list[str]:
    """Traceback lines without source lines and carets."""
    if not any(ln.startswith("Traceback") for ln in lines):
        return lines
    return [ln for ln in lines
            if not ln.startswith(" ") or ln.strip().startswith("File \"")]


def indent(text: str, prefix: str = "      ") -> str:
    return "\n".join(prefix + ln for ln in text.splitlines())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=400,
                    help="examples per test before weighting (default 400)")
    ap.add_argument("--budget", type=float, default=50.0,
                    help="seconds per target (default 50; 16 targets, special files 4 x)")
    ap.add_argument("--timeout", type=float, default=10.0, help="seconds per case (10)")
    ap.add_argument("--seed", type=int, default=None,
                    help="vary the examples (default: the quick profile's fixed ones, more)")
    ap.add_argument("--keep", default=None,
                    help="directory for the files of every finding (default: a temporary "
                         "directory, removed at the end)")
    ap.add_argument("--json", default=None, help="also write the summary as JSON")
    ap.add_argument("-k", default=None, help="pytest -k expression (a subset of targets)")
    ap.add_argument("--no-confirm", action="store_true",
                    help="do not re-run command-line findings as real processes")
    ap.add_argument("--no-fail", action="store_true", help="exit 0 even with findings")
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="asgp-fuzz-"))
    keep = Path(args.keep) if args.keep else work / "findings"
    keep.mkdir(parents=True, exist_ok=True)
    log = work / "cases.jsonl"
    print(f"fuzz: {args.examples} examples per test (weighted), {args.budget:g} s per "
          f"target, {args.timeout:g} s per case, seed "
          f"{'fixed' if args.seed is None else args.seed}", flush=True)
    code, output, elapsed = run_pytest(args, log, keep)
    records = read_log(log)

    per_target: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    findings: dict[str, list[dict[str, Any]]] = collections.defaultdict(list)
    for r in records:
        c = per_target[r["target"]]
        if r.get("skipped"):
            c["skipped"] += 1
            continue
        c["cases"] += 1
        c["seconds"] += r.get("seconds", 0.0)
        if not r["ok"]:
            c["findings"] += 1
            findings[r["finding"]["signature"]].append(r["finding"])

    total = sum(c["cases"] for c in per_target.values())
    print(f"\n{total} cases in {elapsed / 60:.1f} min, {len(findings)} distinct finding(s)\n")
    width = max((len(t) for t in per_target), default=10)
    print(f"{'target':<{width}}  {'cases':>6}  {'failing':>7}  {'skipped':>7}  {'s/case':>6}")
    for target in sorted(per_target):
        c = per_target[target]
        per_case = c["seconds"] / c["cases"] if c["cases"] else 0.0
        print(f"{target:<{width}}  {c['cases']:>6}  {c['findings']:>7}  {c['skipped']:>7}  "
              f"{per_case:>6.2f}")

    summary: dict[str, Any] = {
        "cases": total, "minutes": round(elapsed / 60, 1), "examples": args.examples,
        "budget_s": args.budget, "timeout_s": args.timeout, "seed": args.seed,
        "targets": {t: dict(c) for t, c in sorted(per_target.items())}, "findings": []}
    for n, (sig, group) in enumerate(sorted(findings.items()), 1):
        best = min(group, key=lambda f: len(f["reproducer"]) + sum(
            len(k) + len(v) for k, v in f["files"].items()))
        kept = next((f for f in group if f.get("kept")), None)
        print(f"\n[{n}] {sig}  ({len(group)} case(s))")
        print(f"    case: {best['reproducer']}")
        for path, what in best["files"].items():
            print(f"    file {path}: {what}")
        print(f"    problems: {'; '.join(best['problems'])}")
        print(f"    exit code {best['exit_code']}, signal {best['signal']}, "
              f"{best['seconds']} s")
        text = best["stacks"] if best["timed_out"] else best["stderr"]
        if text.strip():
            lines = text.splitlines()
            shown = lines if len(lines) <= 30 else [*lines[:6], "...", *lines[-22:]]
            print(f"    {'stacks' if best['timed_out'] else 'stderr'}:")
            print(indent("\n".join(shown)))
        confirmed = None
        if kept is not None and not args.no_confirm:
            confirmed = confirm(kept, max(args.timeout, 20.0))
            if confirmed is not None:
                print(f"    real process ({kept['reproducer']}): "
                      f"{confirmed.splitlines()[0]}")
                if len(confirmed.splitlines()) > 1:
                    print(indent("\n".join(confirmed.splitlines()[1:])))
        summary["findings"].append({"signature": sig, "cases": len(group), "example": best,
                                    "kept": kept.get("kept") if kept else None,
                                    "real_process": confirmed})

    if code != 0:  # collecting, findings never fail a test: this is the harness failing
        print(f"\nthe fuzz run itself failed (pytest exit {code}):\n{output[-4000:]}")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2) + "\n")
    if args.keep:
        print(f"\nfiles of every finding: {keep}")
    shutil.rmtree(work, ignore_errors=True)
    if code != 0 or not records:
        return 2
    return 1 if findings and not args.no_fail else 0


if __name__ == "__main__":
    sys.exit(main())
