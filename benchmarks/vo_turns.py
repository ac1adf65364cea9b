"""Turns on the spot: are the VO's twists inside their own 95 % ellipse, per turn rate?

The drives are the turn-on-the-spot drives of ``benchmarks/vo_nees.py`` (``kind`` "turn":
3 s at each of 0.5, 1, 1.5, 2, 2.5 and 3 rad/s from a start pose drawn from the seed, the
camera at 30, 15 and 20 Hz in turn, the tiled room for even seeds, the carpet room for odd
ones; calibration seeds 6, 8, 9 and 14-16, held-out seeds 80-85). For every published
twist (v, omega) of a tracked frame, against the true (0, omega_true), with the (v, omega)
block C of ``VOResult.twist_covariance`` (what ``vo_node`` publishes on ``vo/twist``):

* outside, v: e_v^2 / C_vv > 3.841 (chi-square, 1 dof, 95 %); the same for omega;
* outside, joint: e^T C^-1 e > 5.991 (chi-square, 2 dof, 95 %); its mean (2 when the
  covariance is consistent);
* the mean and RMS of the v error (a bias shows in the mean);
* per band of the rotation between the frame and its reference frame (the span the matches
  had to bridge): the joint share outside.

5 % outside is what a consistent covariance gives. ``--json`` writes the per-twist values.

    python benchmarks/vo_turns.py                    # held-out turns (about a minute)
    python benchmarks/vo_turns.py --role calibration
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core: before numpy is imported
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import itertools
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import cv2
import numpy as np
import vo_nees

CHI2_1_95 = 3.841458820694124
CHI2_2_95 = 5.991464547107979
ROTATION_BANDS = (0.0, 0.03, 0.07, 0.12, 0.17)
"""Edges (rad) of the bands of rotation between a frame and its reference."""


def turn_twists(spec: vo_nees.DriveSpec) -> list[dict]:
    """Per published twist of one turn drive: errors, covariance block and context."""
    drive, results = vo_nees.run_drive(spec)
    rotation = vo_nees.reference_rotation(results)
    out = []
    for k, r in enumerate(results):
        if not r.ok or r.twist is None or r.twist_covariance is None:
            continue
        e = np.array([r.twist[0] - drive.v[k], r.twist[1] - drive.omega[k]])
        C = r.twist_covariance[np.ix_([0, 5], [0, 5])]
        out.append({"drive": spec.name, "k": k, "rate": abs(spec.turn_rate),
                    "camera_hz": spec.rate, "e_v": float(e[0]), "e_w": float(e[1]),
                    "nees_v": float(e[0] ** 2 / C[0, 0]), "nees_w": float(e[1] ** 2 / C[1, 1]),
                    "nees": vo_nees.nees(e, C), "rotation": float(rotation[k]),
                    "inliers": r.num_inliers})
    return out


def table(rows: list[dict]) -> None:
    print("| turn rate | twists | outside: v | omega | joint | mean joint NEES (2) | "
          "v error: mean | RMS | rotation to the reference (mean) |")
    print("|---|---|---|---|---|---|---|---|---|")
    rates = sorted({r["rate"] for r in rows})
    for rate in (*rates, None):
        sel = [r for r in rows if rate is None or r["rate"] == rate]
        if not sel:
            continue

        def col(key, sel=sel):
            return np.array([r[key] for r in sel], float)
        ev = col("e_v")
        name = "**all**" if rate is None else f"{rate:g} rad/s"
        print(f"| {name} | {len(sel)} | {100 * np.mean(col('nees_v') > CHI2_1_95):.1f} % | "
              f"{100 * np.mean(col('nees_w') > CHI2_1_95):.1f} % | "
              f"{100 * np.mean(col('nees') > CHI2_2_95):.1f} % | {np.mean(col('nees')):.2f} | "
              f"{1e3 * np.mean(ev):+.1f} mm/s | {1e3 * math.sqrt(np.mean(ev ** 2)):.1f} mm/s | "
              f"{np.mean(col('rotation')):.3f} rad |")
    rot = np.array([r["rotation"] for r in rows], float)
    joint = np.array([r["nees"] for r in rows], float)
    words = []
    for lo, hi in itertools.pairwise((*ROTATION_BANDS, math.inf)):
        m = (rot >= lo) & (rot < hi)
        if m.any():
            words.append(f"{lo:g}-{hi:g} rad {100 * np.mean(joint[m] > CHI2_2_95):.1f} % "
                         f"({int(m.sum())})")
    print("\nby rotation to the reference, joint share outside: " + ", ".join(words))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--role", choices=("calibration", "held-out", "all"), default="held-out")
    ap.add_argument("--json", help="also write the per-twist values to this JSON file")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    specs = [s for s in vo_nees.drives() if s.kind == "turn"
             and args.role in ("all", s.role)]
    rows_by_role: dict[str, list[dict]] = {}
    for spec in specs:
        rows_by_role.setdefault(spec.role, []).extend(turn_twists(spec))
    for role, rows in rows_by_role.items():
        drives = len({r["drive"] for r in rows})
        print(f"\n{role}: {drives} turn drives; twists outside their own 95 % ellipse "
              f"(v and omega alone: chi-square 1 dof, joint: 2 dof)\n")
        table(rows)
    if args.json:
        from asgp_ros.common.fileio import atomic_write_text
        atomic_write_text(args.json, json.dumps(rows_by_role, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
