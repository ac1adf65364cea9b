"""Visual odometry benchmark: this package's Fovis-like VO against OpenCV 5's cv2.Odometry.

Renders RGB-D sequences with ground truth (asgp_ros.sim.render, realistic depth noise),
driven by smooth chair trajectories with the backward-looking camera, then runs on the
same frames, on one core:

* ``asgp`` : asgp_ros.vo.VisualOdometry (frame to keyframe, failures reported);
* ``cv-rgb``, ``cv-depth``, ``cv-rgbd`` : cv2.Odometry with OdometryType RGB, DEPTH and
  RGB_DEPTH (frame to previous frame; camera matrix float32, depth float32 metres,
  max depth and max depth difference set for the scene).

Printed per sequence and method: per-frame time (median, p90), tracked frames, relative
pose error per frame (translation mm, rotation deg: median and RMS over tracked frames),
drift per metre travelled (end-point translation error of the integrated path / path
length), and for asgp the chair twist error against the simulator's (v, omega).

    python benchmarks/vo.py            # full run (a few minutes)
    python benchmarks/vo.py --quick    # small run (about a minute)
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core: before numpy is imported
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import math
import sys
import time
from pathlib import Path

# run from a source checkout without installing the package
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from asgp_ros.sim.render import RGBDRenderer
from asgp_ros.sim.scene import blank_wall_drive, build_scene, loop_drive
from asgp_ros.vo import DEFAULT_EXTRINSIC, VisualOdometry
from asgp_ros.vo.extrinsics import invert

MAX_DEPTH = 6.0  # the renderer's range limit
MAX_DEPTH_DIFF = 0.3  # cv2.Odometry: largest depth change of a point between frames (m)


def _rot_angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def render_sequence(preset: str, kind: str, seconds: float, rate: float, seed: int):
    scene = build_scene(preset=preset, seed=seed)
    renderer = RGBDRenderer(scene, seed=seed)
    drive = loop_drive(seconds, rate) if kind == "loop" else blank_wall_drive(rate, scene=scene)
    if kind != "loop" and seconds < drive.t[-1]:
        drive = drive.head(int(seconds * rate) + 1)
    poses = [DEFAULT_EXTRINSIC.camera_pose_planar(x, y, th)
             for x, y, th in zip(drive.x, drive.y, drive.theta, strict=True)]
    frames, times = [], []
    for T in poses:
        t0 = time.perf_counter()
        frames.append(renderer.render(T))
        times.append(time.perf_counter() - t0)
    return renderer.K, drive, poses, frames, np.array(times)


def run_asgp(K, drive, frames):
    vo = VisualOdometry(K)
    out = []
    for k, (img, depth) in enumerate(frames):
        t0 = time.perf_counter()
        r = vo.process(img, depth, float(drive.t[k]))
        dt = time.perf_counter() - t0
        out.append((r, dt))
    return out


def run_cv(K, kind, frames):
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(K.astype(np.float32))
    settings.setMaxDepth(MAX_DEPTH)
    settings.setMaxDepthDiff(MAX_DEPTH_DIFF)
    odo = cv2.Odometry(kind, settings, cv2.OdometryAlgoType_COMMON)
    out = [(None, 0.0)]
    grays = [cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) for img, _ in frames]
    for k in range(1, len(frames)):
        d0, d1 = frames[k - 1][1], frames[k][1]
        t0 = time.perf_counter()
        if kind == cv2.OdometryType_DEPTH:
            ok, Rt = odo.compute(d0, d1)
        else:
            ok, Rt = odo.compute(d0, grays[k - 1], d1, grays[k])
        dt = time.perf_counter() - t0
        # Rt maps points of the previous frame into the current one: motion = Rt^-1
        motion = invert(Rt) if ok and np.all(np.isfinite(Rt)) else None
        out.append((motion, dt))
    return out


def evaluate(name, poses, drive, motions, times, twists=None):
    """motions[k]: (motion [4, 4] since frame prev[k]) or None; returns a metrics dict."""
    et, er = [], []
    pose = np.eye(4)
    for k in range(1, len(poses)):
        m, prev, _ = motions[k]
        if m is None:
            continue
        gt = invert(poses[prev]) @ poses[k]
        d = invert(gt) @ m
        et.append(np.linalg.norm(d[:3, 3]))
        er.append(_rot_angle_deg(d[:3, :3]))
    for k in range(1, len(poses)):
        if motions[k][0] is not None and motions[k][2]:
            pose = pose @ motions[k][0]
    gt_end = invert(poses[0]) @ poses[-1]
    length = sum(np.linalg.norm(poses[k][:3, 3] - poses[k - 1][:3, 3])
                 for k in range(1, len(poses)))
    drift = np.linalg.norm(pose[:3, 3] - gt_end[:3, 3]) / max(length, 1e-9)
    rot_drift = _rot_angle_deg((invert(gt_end) @ pose)[:3, :3]) / max(length, 1e-9)
    t = np.array(times[1:]) * 1e3
    res = {
        "method": name,
        "time_ms_median": float(np.median(t)),
        "time_ms_p90": float(np.percentile(t, 90)),
        "tracked": len(et) / max(1, len(poses) - 1),
        "rpe_t_mm_median": float(np.median(et)) * 1e3 if et else math.nan,
        "rpe_t_mm_rms": float(np.sqrt(np.mean(np.square(et)))) * 1e3 if et else math.nan,
        "rpe_r_deg_median": float(np.median(er)) if er else math.nan,
        "rpe_r_deg_rms": float(np.sqrt(np.mean(np.square(er)))) if er else math.nan,
        "drift_pct": 100.0 * drift,
        "rot_drift_deg_per_m": rot_drift,
        "path_m": length,
    }
    if twists is not None:
        ev = [abs(v - drive.v[k]) for k, (v, _) in twists]
        ew = [abs(w - drive.omega[k]) for k, (_, w) in twists]
        res["twist_v_rms"] = float(np.sqrt(np.mean(np.square(ev)))) if ev else math.nan
        res["twist_w_rms"] = float(np.sqrt(np.mean(np.square(ew)))) if ew else math.nan
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short sequences (about a minute)")
    ap.add_argument("--seconds", type=float, default=None, help="length of the loop sequences")
    ap.add_argument("--rate", type=float, default=30.0, help="camera rate (Hz)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-cv", action="store_true", help="skip cv2.Odometry")
    ap.add_argument("--json", help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    seconds = args.seconds or (4.0 if args.quick else 20.0)
    sequences = [("rich", "loop", seconds), ("poor", "loop", seconds),
                 ("poor", "blank", 3.0 if args.quick else 100.0)]
    if args.quick:
        sequences = [("rich", "loop", seconds), ("poor", "blank", 11.0)]
    cv_kinds = [] if args.no_cv else [("cv-rgb", cv2.OdometryType_RGB),
                                      ("cv-depth", cv2.OdometryType_DEPTH),
                                      ("cv-rgbd", cv2.OdometryType_RGB_DEPTH)]
    report = []
    for preset, kind, secs in sequences:
        K, drive, poses, frames, rtimes = render_sequence(preset, kind, secs, args.rate,
                                                          args.seed)
        label = f"{preset}-{kind} ({len(frames)} frames {frames[0][0].shape[1]}x" \
                f"{frames[0][0].shape[0]} @ {args.rate:g} Hz)"
        print(f"\n== {label}; render {np.median(rtimes) * 1e3:.1f} ms/frame median")
        rows = []
        results = run_asgp(K, drive, frames)
        motions, times, twists, prev = [(None, 0, False)], [0.0], [], 0
        statuses: dict[str, int] = {}
        for k, (r, dt) in enumerate(results):
            statuses[r.status.value] = statuses.get(r.status.value, 0) + 1
            times.append(dt) if k else None
            if k == 0:
                continue
            if r.ok:
                motions.append((r.motion, prev, True))
                twists.append((k, r.twist))
                prev = k
            else:
                motions.append((None, prev, False))
                if r.reset:
                    prev = k
        rows.append(evaluate("asgp", poses, drive, motions, times, twists))
        rows[-1]["statuses"] = statuses
        for name, cvk in cv_kinds:
            out = run_cv(K, cvk, frames)
            motions = [(None, 0, False)] + [(m, k - 1, True) for k, (m, _) in
                                             enumerate(out) if k > 0]
            rows.append(evaluate(name, poses, drive, motions, [dt for _, dt in out]))
        head = (f"{'method':9s} {'med ms':>7s} {'p90 ms':>7s} {'tracked':>8s} {'RPE t mm':>9s} "
                f"{'(rms)':>7s} {'RPE r deg':>9s} {'(rms)':>7s} {'drift %':>8s} "
                f"{'deg/m':>6s}")
        print(head)
        for m in rows:
            print(f"{m['method']:9s} {m['time_ms_median']:7.1f} {m['time_ms_p90']:7.1f} "
                  f"{100 * m['tracked']:7.1f}% {m['rpe_t_mm_median']:9.2f} "
                  f"{m['rpe_t_mm_rms']:7.2f} {m['rpe_r_deg_median']:9.3f} "
                  f"{m['rpe_r_deg_rms']:7.3f} {m['drift_pct']:8.2f} "
                  f"{m['rot_drift_deg_per_m']:6.2f}")
        a = rows[0]
        print(f"asgp statuses: {a['statuses']}; twist error rms: v {a['twist_v_rms']:.3f} m/s,"
              f" omega {a['twist_w_rms']:.3f} rad/s")
        for m in rows[1:]:
            print(f"  {m['method']} / asgp time ratio: "
                  f"{m['time_ms_median'] / a['time_ms_median']:.1f}x; RPE t ratio "
                  f"{m['rpe_t_mm_median'] / a['rpe_t_mm_median']:.2f}")
        report.append({"sequence": label, "render_ms_median": float(np.median(rtimes) * 1e3),
                       "methods": rows})
    if args.json:
        from asgp_ros.common.fileio import atomic_write_text
        atomic_write_text(args.json, json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
