"""The figures of a reproduction: success against the horizon, error distributions, example
paths with their ellipses, and the adapting row against the time since the floor changed."""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import numpy as np

from asgp_ros.common.fileio import naming
from asgp_ros.core.metrics import CHI2_2DOF_95
from asgp_ros.core.modelfile import load_model
from asgp_ros.learning.evaluation import rollout_cases
from asgp_ros.learning.reproduce.protocol import (
    ADAPT_ROW,
    COVERAGE_TARGET,
    MODELS,
    OWN_TRAIN,
    TEST_SETS,
)
from asgp_ros.learning.reproduce.tables import cell_success_rate
from asgp_ros.learning.training import Series

#: Line style of each train set in the success figure.
_STYLES = {"Tile": "-", "Carpet": "--", "Both": ":"}


def write_plots(out: Path, results: list[dict[str, Any]], series: dict[str, Series]) -> None:
    """success_vs_horizon.png, error_distributions.png, example_paths.png and
    adaptation.png into ``out`` (whose ``models/`` holds the run's model files)."""
    # matplotlib (about 0.5 s to import) only for the plots, with its file-only backend
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hk = list(results[0]["evals"]["Tile"].horizons)
    _success_vs_horizon(out, results, hk, plt)
    _error_distributions(out, results, hk, plt)
    _example_paths(out, results, series, hk[-1], plt)
    _adaptation_plot(out, results, hk[-1], plt)


def _success_vs_horizon(out: Path, results: list[dict[str, Any]], hk: list[str],
                        plt: Any) -> None:
    """success_vs_horizon.png: every row's success rate against the horizon, one panel per
    test set."""
    hs = [float(h) for h in hk]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    for ax, test in zip(axes, TEST_SETS, strict=True):
        for r in results:
            ev = r["evals"][test]
            ax.plot(hs, [100 * ev.horizons[h].vo.success_rate for h in hk], marker="o",
                    color=MODELS[r["kind"]].plot_colour, linestyle=_STYLES[r["train"]],
                    label=f"{MODELS[r['kind']].label} / {r['train']}")
        ax.set_title(f"tested on {test}")
        ax.set_xlabel("horizon (s)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate (%), error <= 10 cm")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="center right")
    fig.tight_layout(rect=(0, 0, 0.84, 1))
    _save(fig, out / "success_vs_horizon.png", dpi=110)
    plt.close(fig)


def _error_distributions(out: Path, results: list[dict[str, Any]], hk: list[str],
                         plt: Any) -> None:
    """error_distributions.png: the cumulative distribution of the position error of the
    Both-trained rows, per test set and horizon."""
    fig, axes = plt.subplots(len(TEST_SETS), len(hk), figsize=(4 * len(hk), 3.2 * 3),
                             squeeze=False)
    for i, test in enumerate(TEST_SETS):
        for j, h in enumerate(hk):
            ax = axes[i][j]
            for r in results:
                if r["train"] != "Both":
                    continue
                err = np.sort(100 * r["evals"][test].horizons[h].errors)
                ax.plot(err, np.arange(1, err.size + 1) / err.size,
                        color=MODELS[r["kind"]].plot_colour, label=MODELS[r["kind"]].label)
            ax.axvline(10.0, color="k", lw=0.8, ls="--")
            ax.set_xscale("log")
            ax.set_xlim(0.01, None)
            ax.set_title(f"test {test}, {h} s (trained on Both)", fontsize=9)
            ax.set_xlabel("position error at horizon (cm)")
            ax.set_ylabel("fraction of cases")
            ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    _save(fig, out / "error_distributions.png", dpi=100)
    plt.close(fig)


def _example_paths(out: Path, results: list[dict[str, Any]], series: dict[str, Series],
                   h: str, plt: Any) -> None:
    """example_paths.png: three example cases per test set at the horizon key ``h``, the
    Both-trained ASGP's path with its 95% ellipses (and the MLP's) over the recorded one."""
    asgp = next(r for r in results if r["kind"] == "asgp" and r["train"] == "Both")
    mlp_file = out / "models" / "both_mlp.npz"
    mlp = load_model(mlp_file) if mlp_file.exists() else None
    n_ex = 3
    fig, axes = plt.subplots(len(TEST_SETS), n_ex, figsize=(4 * n_ex, 3.6 * 3), squeeze=False)
    for i, test in enumerate(TEST_SETS):
        ex = asgp["evals"][test].horizons[h].examples or {}
        count = 0 if not ex else min(n_ex, ex["pred"].shape[0])
        for j in range(n_ex):
            ax = axes[i][j]
            if j >= count:
                ax.axis("off")
                continue
            _example_case(ax, ex, j, mlp, series)
            ax.set_title(f"{test}: {ex['t'][j]:.1f} s into the bag, {h} s ahead", fontsize=9)
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    fig.suptitle("Predicted paths (trained on Both) over the VO-integrated recorded path")
    fig.tight_layout()
    _save(fig, out / "example_paths.png", dpi=100)
    plt.close(fig)


def _example_case(ax: Any, ex: dict[str, np.ndarray], j: int, mlp: Any,
                  series: dict[str, Series]) -> None:
    """Example ``j`` of ``ex`` on the axes ``ax``: the recorded path, the ASGP's with its
    95% ellipses, and the MLP's rolled out on the same case (when its file exists)."""
    from matplotlib.patches import Ellipse

    ref, pred, cov = ex["ref"][j], ex["pred"][j], ex["cov"][j]
    ax.plot(np.r_[0, ref[:, 0]], np.r_[0, ref[:, 1]], "k.-", label="recorded (VO)")
    ax.plot(np.r_[0, pred[:, 0]], np.r_[0, pred[:, 1]], ".-",
            color=MODELS["asgp"].plot_colour,
            label="ASGP (95% ellipses)")
    if mlp is not None:
        res = series[str(ex["series"][j])].res
        mp, _, _ = rollout_cases(mlp, res, np.array([int(ex["idx"][j])]), len(pred),
                                 uncertainty="none")
        ax.plot(np.r_[0, mp[0, :, 0]], np.r_[0, mp[0, :, 1]], ".--",
                color=MODELS["mlp"].plot_colour, label=MODELS["mlp"].label)
    for p, c in zip(pred, cov, strict=True):
        lam, vec = np.linalg.eigh(0.5 * (c + c.T))
        lam = np.clip(lam, 0.0, None)
        w, hgt = 2 * np.sqrt(CHI2_2DOF_95 * lam[::-1])
        ang = math.degrees(math.atan2(vec[1, 1], vec[0, 1]))
        ax.add_patch(Ellipse(p, w, hgt, angle=ang, fill=False, lw=0.7,
                             color=MODELS["asgp"].plot_colour, alpha=0.7))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)


#: Width of the time bins of the adaptation figure (s).
ADAPT_BIN_S = 20.0


def _adaptation_plot(out: Path, results: list[dict[str, Any]], h: str, plt: Any) -> None:
    """adaptation.png: success and 95% coverage at horizon h against the time since the
    floor changed (the start of a test bag on the other surface), adapting and not."""
    cells = [(r, te) for tr, te in (("Tile", "Carpet"), ("Carpet", "Tile"))
             for r in results if r["kind"] == ADAPT_ROW and r["train"] == tr
             and te in r.get("adaptation_timeline", {})]
    if not cells:
        return
    fig, axes = plt.subplots(2, len(cells), figsize=(5.5 * len(cells), 6.5), sharex=True,
                             squeeze=False)
    for col, (r, test) in enumerate(cells):
        tl = r["adaptation_timeline"][test]
        t = tl["t"]
        edges = np.arange(0.0, float(t.max()) + ADAPT_BIN_S, ADAPT_BIN_S)
        mid = 0.5 * (edges[1:] + edges[:-1]) / 60.0
        own = cell_success_rate(results, "asgp", OWN_TRAIN[test], test, h)
        for row, (key, label) in enumerate((("hit", f"success at {h} s (%)"),
                                            ("covered", f"95% ellipse coverage at {h} s (%)"))):
            ax = axes[row, col]
            for suffix, style, name in (("", "-", "adapting"), ("_plain", "--", "as trained")):
                v = tl[f"{key}{suffix}@{h}"]
                y = []
                for a, b in itertools.pairwise(edges):
                    sel = (t >= a) & (t < b) & np.isfinite(v)
                    y.append(100 * float(np.mean(v[sel])) if sel.any() else np.nan)
                ax.plot(mid, y, style, label=f"{r['train']}-trained, {name}")
            if key == "hit":
                ax.axhline(100 * own, color="k", lw=0.8, ls=":",
                           label=f"{test}-trained ASGP (whole bags)")
            else:
                ax.axhspan(100 * COVERAGE_TARGET[0], 100 * COVERAGE_TARGET[1], color="g",
                           alpha=0.08, label="target")
            ax.set_ylabel(label)
            ax.set_title(f"trained on {r['train']}, driving on {test}")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="lower right")
        axes[1, col].set_xlabel(f"minutes since the floor changed ({ADAPT_BIN_S:g} s bins, "
                                "the test bags together)")
    fig.tight_layout()
    _save(fig, out / "adaptation.png", dpi=100)
    plt.close(fig)


def _save(fig: Any, path: Path, dpi: int) -> None:
    """``fig.savefig(path)``; an error that names no file (a full disk) names ``path``."""
    with naming(path):
        fig.savefig(path, dpi=dpi)
