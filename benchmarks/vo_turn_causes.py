"""Why the VO's covariance was over-confident on fast turns on the spot: one drive, changed one
cause at a time.

The drive: 3 s on the spot in the tiled room of seed 0 at 3 rad/s (and 0.5 rad/s to compare),
the camera at 15 Hz (0.2 rad between frames). For each variant, over its tracked frames:

* NEES6: the camera motion's error (its right perturbation, 6 dof) against the reported
  ``covariance`` (mean; 6 for a consistent covariance, about 1.6 here at slow turns: the
  calibrated model is conservative), and the share above the 95 % bound 12.59;
* outside: twists outside their own 95 % (v, omega) ellipse;
* inliers (mean).

Variants: the default odometry (with ``--rotation-gain`` to set the rotation factor's c,
0 = without it, as the odometry was); noise-free images (``DepthNoise.perfect``); exact depth
(no disparity noise nor quantisation); 20 Gauss-Newton iterations instead of 5 (the
linearisation); the camera on the axle (a turn on the spot is then a pure camera rotation:
no lever arm); the camera not tilted; level-0 features only (no coarse-level windows); and
the reference frame kept however few inliers remain (at 0.5 rad/s the rotation to the
reference then grows over many frames).

With ``--matches`` it also prints the true sub-pixel match errors of the inliers (against
the renderer's ground truth, noise-free images) at 0.5 and 3 rad/s: their RMS, and the
frame-to-frame spread of the per-frame least-squares fit e = a + b x of the error over the
image (x normalised image coordinate): independent errors would give a spread of a of about
RMS / sqrt(n).

    python benchmarks/vo_turn_causes.py --rotation-gain 0      # the odometry without the factor
    python benchmarks/vo_turn_causes.py --matches
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one core: before numpy is imported
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from asgp_ros.sim.render import DepthNoise, RGBDRenderer
from asgp_ros.sim.scene import build_scene, segment_drive
from asgp_ros.vo import CameraExtrinsic, VisualOdometry
from asgp_ros.vo import odometry as od
from asgp_ros.vo.extrinsics import invert, planar_pose

CHI2_2_95 = 5.991464547107979
CHI2_6_95 = 12.591587243743977


class _Probe(VisualOdometry):
    """The odometry, recording each estimate's inliers against the true motion."""

    truth: dict[float, np.ndarray]
    records: list[dict]

    def _estimate(self, ref, cur, T_cur_ref_pred, radius):  # type: ignore[no-untyped-def]
        self._pair = (ref.stamp, cur.stamp)
        return super()._estimate(ref, cur, T_cur_ref_pred, radius)

    def _covariance(self, m, fit):  # type: ignore[no-untyped-def]
        cov = super()._covariance(m, fit)
        ref_t, cur_t = self._pair
        T = invert(self.truth[cur_t]) @ self.truth[ref_t]  # true T_cur_ref
        inl = fit.inliers
        X = m.P[inl] @ T[:3, :3].T + T[:3, 3]
        err = (self._project(X) - m.uv_cur[inl]) * m.w[inl, None]  # level px
        self.records.append({"err": err, "uv": m.uv_cur[inl]})
        return cov


def run(rate: float, hz: float = 15.0, seconds: float = 3.0, noise: DepthNoise | None = None,
        extrinsic: CameraExtrinsic | None = None, probe: bool = False,
        rotation_gain: float | None = None, **options) -> dict:
    """One turn on the spot (tiled room, seed 0, from the room's centre)."""
    ext = extrinsic or CameraExtrinsic()
    renderer = RGBDRenderer(build_scene(preset="rich", seed=0), seed=100, noise=noise,
                            extrinsic=ext)
    drive = segment_drive((0.0, 0.0, 0.0), [(0.0, rate, seconds)], hz)
    vo = (_Probe if probe else VisualOdometry)(renderer.K, extrinsic=ext, **options)
    if rotation_gain is not None:
        vo.rotation_gain = rotation_gain
    if probe:
        vo.truth, vo.records = {}, []
    Tbc = ext.T_base_optical
    nees6, outside, inliers = [], [], []
    prev = 0
    for k in range(len(drive)):
        T = ext.camera_pose_planar(drive.x[k], drive.y[k], drive.theta[k])
        if probe:
            vo.truth[float(drive.t[k])] = T
        r = vo.process(*renderer.render(T), float(drive.t[k]))
        if r.ok and r.motion is not None and r.covariance is not None:
            true_b = invert(planar_pose(drive.x[prev], drive.y[prev], drive.theta[prev])) \
                @ planar_pose(drive.x[k], drive.y[k], drive.theta[k])
            e = od._se3_log(invert(r.motion) @ (invert(Tbc) @ true_b @ Tbc))
            nees6.append(float(e @ np.linalg.solve(r.covariance, e)))
            inliers.append(r.num_inliers)
            if r.twist is not None and r.twist_covariance is not None:
                et = np.array([r.twist[0] - drive.v[k], r.twist[1] - drive.omega[k]])
                C = r.twist_covariance[np.ix_([0, 5], [0, 5])]
                outside.append(float(et @ np.linalg.solve(C, et)) > CHI2_2_95)
        if r.ok or r.reset or r.keyframe_changed:
            prev = k
    out = {"nees6": float(np.mean(nees6)), "above": float(np.mean(np.array(nees6) > CHI2_6_95)),
           "outside": float(np.mean(outside)), "inliers": float(np.mean(inliers)),
           "frames": len(nees6)}
    if probe:
        out["records"] = vo.records
    return out


def match_errors(rate: float, cx: float = 319.5, f: float = 525.0) -> str:
    res = run(rate, noise=DepthNoise.perfect(0.3, 6.0), probe=True)
    err = np.concatenate([r["err"] for r in res["records"]])
    fits = []
    for r in res["records"]:
        x = (r["uv"][:, 0] - cx) / f
        A = np.column_stack([np.ones_like(x), x])
        fits.append(np.linalg.lstsq(A, r["err"][:, 0], rcond=None)[0])
    a, b = np.array(fits).T
    n = np.mean([len(r["err"]) for r in res["records"]])
    rms_x = math.sqrt(float(np.mean(err[:, 0] ** 2)))
    return (f"| {rate:g} rad/s | {math.sqrt(float(np.mean(err ** 2)) * 2):.3f} px | "
            f"{rms_x:.3f} px | {np.std(a):.3f} px (independent: {rms_x / math.sqrt(n):.3f}) | "
            f"{np.std(b):.2f} px |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rotation-gain", type=float, default=None,
                    help="the rotation factor's c (1/rad; default: the odometry's)")
    ap.add_argument("--matches", action="store_true",
                    help="also the true sub-pixel match errors (noise-free images)")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    g = args.rotation_gain
    variants = [
        ("default", {}),
        ("noise-free images", {"noise": DepthNoise.perfect(0.3, 6.0)}),
        ("exact depth", {"noise": DepthNoise(disparity_sigma=0.0, subpixel=0.0)}),
        ("20 Gauss-Newton iterations", {"gauss_newton_iterations": 20}),
        ("camera on the axle", {"extrinsic": CameraExtrinsic(x=0.0)}),
        ("camera not tilted", {"extrinsic": CameraExtrinsic(pitch=0.0)}),
        ("level-0 features only", {"num_levels": 1}),
    ]
    print("| variant | turn | frames | inliers | NEES6 mean (6) | NEES6 > 12.59 | twists outside "
          "(5 %) |")
    print("|---|---|---|---|---|---|---|")
    for name, kw in variants:
        for rate in (0.5, 3.0):
            s = run(rate, rotation_gain=g, **kw)  # type: ignore[arg-type]
            print(f"| {name} | {rate:g} rad/s | {s['frames']} | {s['inliers']:.0f} | "
                  f"{s['nees6']:.2f} | {100 * s['above']:.0f} % | {100 * s['outside']:.0f} % |",
                  flush=True)
    s = run(0.5, rotation_gain=g, ref_frame_change_threshold=0)
    print(f"| reference kept (0.5 rad/s) | 0.5 rad/s | {s['frames']} | {s['inliers']:.0f} | "
          f"{s['nees6']:.2f} | {100 * s['above']:.0f} % | {100 * s['outside']:.0f} % |")
    if args.matches:
        print("\ntrue match errors of the inliers (noise-free images; level px):\n")
        print("| turn | RMS (2-D) | RMS x | per-frame mean over the image, spread | "
              "per-frame slope in x, spread |")
        print("|---|---|---|---|---|")
        for rate in (0.5, 3.0):
            print(match_errors(rate), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
