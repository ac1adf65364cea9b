"""How quickly `asgp reproduce` ends on a stop signal sent while its worker pool starts.

Runs ``asgp reproduce --quick --jobs 2`` on a tiny dataset again and again, sends the
signal as soon as the report's temporary directory appears (the pool is being forked then),
and prints how long each run took to exit: runs that needed the pool's kill fallback
(``asgp_ros.common.fileio.POOL_STOP_GRACE_S``) and runs that did not end at all within the
timeout are counted separately. ``--load N`` keeps N busy loops running beside it: signal
delivery races show under load. On a hang the stuck process tree is printed (per-thread
signal masks and pending sets from /proc) and killed.

Usage: benchmarks/pool_signals.py [--runs 100] [--load 3] [--signal TERM|INT] [--timeout 20]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from asgp_ros.common.fileio import POOL_STOP_GRACE_S


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _asgp(args: list[str], cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "asgp_ros.cli", *args], cwd=cwd,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_default_sigint)


def _threads(pid: int) -> list[str]:
    lines = []
    for tid in sorted(os.listdir(f"/proc/{pid}/task")):
        base = f"/proc/{pid}/task/{tid}"
        try:
            text = Path(f"{base}/status").read_text()
            status = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
            wchan = Path(f"{base}/wchan").read_text()
        except OSError:
            continue
        keys = ("State", "SigPnd", "ShdPnd", "SigBlk", "SigIgn", "SigCgt")
        lines.append(f"  {pid}/{tid} {wchan} " + " ".join(f"{k}={status[k].strip()}"
                                                          for k in keys))
    return lines


def _one(root: Path, data: Path, sig: int, timeout: float) -> float | None:
    out = root / "report"
    shutil.rmtree(out, ignore_errors=True)
    proc = _asgp(["reproduce", "--data", str(data), "--out", str(out), "--quick", "--jobs",
                  "2"], root)
    while not any(p.name.startswith(".report.") for p in root.iterdir()):
        if proc.poll() is not None:
            raise SystemExit(f"reproduce ended before the signal: {proc.stderr.read()[-500:]}"
                             if proc.stderr else "reproduce ended before the signal")
        time.sleep(0.005)
    proc.send_signal(sig)
    t0 = time.monotonic()
    try:
        proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        kids = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True,
                              text=True).stdout.split()
        print(f"hang: reproduce {proc.pid}, workers {' '.join(kids) or 'none'}")
        for pid in [proc.pid, *map(int, kids)]:
            print("\n".join(_threads(pid)))
        for pid in map(int, kids):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.kill()
        proc.communicate()
        return None
    finally:
        for p in root.iterdir():
            if p.name.startswith(".report."):
                shutil.rmtree(p, ignore_errors=True)
    if proc.returncode != 128 + sig:
        print(f"unexpected exit status {proc.returncode}")
    return time.monotonic() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--load", type=int, default=3, help="busy loops beside the runs")
    ap.add_argument("--signal", choices=("TERM", "INT"), default="TERM")
    ap.add_argument("--timeout", type=float, default=20.0)
    args = ap.parse_args()
    sig = signal.Signals[f"SIG{args.signal}"]
    root = Path(tempfile.mkdtemp(prefix="pool_signals."))
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
            for _ in range(args.load)]
    try:
        data = root / "data"
        subprocess.run([sys.executable, "-m", "asgp_ros.cli", "dataset", "--out", str(data),
                        "--scale", "0.02", "--jobs", "2"], check=True,
                       stdout=subprocess.DEVNULL)
        took = [_one(root, data, sig, args.timeout) for _ in range(args.runs)]
    finally:
        for p in load:
            p.kill()
        shutil.rmtree(root, ignore_errors=True)
    ended = np.array([t for t in took if t is not None])
    slow = int(np.sum(ended >= POOL_STOP_GRACE_S))
    print(f"{args.runs} runs, SIG{args.signal}, {args.load} busy loops beside: "
          f"exit p50 {np.median(ended):.2f} s, p99 {np.quantile(ended, 0.99):.2f} s, "
          f"max {ended.max():.2f} s; {slow} needed the kill fallback "
          f"(>= {POOL_STOP_GRACE_S:.0f} s); {args.runs - len(ended)} did not end within "
          f"{args.timeout:.0f} s")


if __name__ == "__main__":
    main()
