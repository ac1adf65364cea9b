"""How much driving on a new floor the adaptation needs: the data-quantity curve.

Usage::

    python benchmarks/adapt_data.py [MODEL] [--learn BAG --test BAG [BAG ...]]
        [--minutes 0.5 1 2 5 10] [--reference MODEL2] [--parts-from MODEL2]

Without arguments: the carpet model of the committed reproduction
(``docs/reproduction/models/carpet_asgp.npz``, the tile model as the reference) on tile
recordings simulated here with seeds no dataset of seed 0 uses (a 20-minute one to learn
from, two of 10 minutes to test on). On the bags of a dataset made by ``asgp dataset``::

    python benchmarks/adapt_data.py docs/reproduction/models/carpet_asgp.npz \\
        --learn DATA/tile/tile_01 --test DATA/tile/tile_07 DATA/tile/tile_08 \\
        --reference docs/reproduction/models/tile_asgp.npz

For each N of ``--minutes``, MODEL learns from the first N minutes of ``--learn`` (a
recording of the new floor) in three ways, each scored on ``--test`` (k-step success rate at
1.0, 1.4 and 2.0 s, as ``asgp evaluate``, on the same cases):

1. *constant mean*: the online posterior (``asgp_ros.core.adapt.OnlinePosterior``, at
   MODEL's hyperparameters and pseudo-inputs) absorbs every row of the N minutes, with the
   constant prior mean (``AdaptConfig(trained_mean=False)``, A6); the trained data are
   forgotten at once, the new rows never. This is the FITC posterior of those N minutes
   alone: the best the adaptation of earlier versions could reach after N minutes.
2. *trained mean*: the same with the trained posterior's mean as the prior mean (A9, the
   default): the rows teach a correction to the trained function.
3. *linear correction*: MODEL unchanged plus a ridge regression of its one-step residuals
   on the input row (D + 1 weights per channel): few parameters, which learn from little
   data but can only correct what is linear in the inputs.

The adaptation as it runs forgets the new rows too (a half-life of 300 s by default), so
it holds less than N minutes once N is past a few minutes.
MODEL as trained and, with ``--reference``, a model trained on the new floor, are scored
on the same cases beside them.

``--parts-from MODEL2`` (a model of the same inputs: s and coupling) asks which of MODEL's
fixed parts limit it: the whole ``--learn`` recording is conditioned (the FITC posterior,
constant prior mean, as in column 1) at MODEL's pseudo-inputs and hyperparameters with one
part, or several, taken from MODEL2 (the noise variance, the signal variance, the
lengthscales, the pseudo-inputs), and scored. The inputs whose lengthscales differ between
the two by 10 times or more are listed (ARD: a long lengthscale switches an input off).
Prints figures only (no assertions).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from asgp_ros.core.features import CHANNELS, FeatureConfig  # noqa: E402
from asgp_ros.core.modelfile import load_model  # noqa: E402
from asgp_ros.core.models import MotionModel  # noqa: E402
from asgp_ros.core.sparse_gp import SparseGP  # noqa: E402
from asgp_ros.learning.adapting import OfflineAdaptOptions, adapt_model  # noqa: E402
from asgp_ros.learning.evaluation import TestSeries, evaluate_model  # noqa: E402
from asgp_ros.learning.training import (  # noqa: E402
    Series,
    design,
    read_series,
    slice_resampled,
)

HORIZONS_S = (1.0, 1.4, 2.0)
MODELS = REPO / "docs" / "reproduction" / "models"
#: (seed, minutes) of the simulated tile recordings without arguments: learn, test, test
SIMULATED = ((901, 20.0), (902, 10.0), (903, 10.0))
RIDGE = 1e-2  # relative to the number of rows; the lightly regularised fits agree (1e-4)


class LinearCorrection:
    """A channel plus w . x + b: the channel interface of :class:`MotionModel`."""

    def __init__(self, base: object, w: np.ndarray, b: float) -> None:
        self.base, self.w, self.b = base, w, b

    def predict(self, X: np.ndarray, include_noise: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        m, v = self.base.predict(X, include_noise)  # type: ignore[attr-defined]
        return m + X @ self.w + self.b, v

    def predict_with_grad(self, X: np.ndarray, include_noise: bool = True
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m, v, g = self.base.predict_with_grad(X, include_noise)  # type: ignore[attr-defined]
        return m + X @ self.w + self.b, v, g + self.w[None, :]


def adapted(model: MotionModel, learn: list[Series], trained_mean: bool) -> MotionModel:
    """MODEL adapted to every row of ``learn`` (``asgp adapt``'s
    :func:`~asgp_ros.learning.adapting.adapt_model`): none of them forgotten, the trained
    data forgotten at once (their weight is 0 from the first row on), nothing held out."""
    opts = OfflineAdaptOptions(trained_weight=0.0, holdout=0.0, calibrate=False,
                               trained_mean=trained_mean)
    return adapt_model(model, learn, opts)


def corrected(model: MotionModel, learn: list[Series]) -> MotionModel:
    """MODEL plus a ridge fit of its one-step residuals on ``learn``."""
    chans = []
    for c, ch in enumerate(model.channels):
        X, y = design(learn, c, model.feature_config)
        r = y - ch.predict(X)[0]
        A = np.column_stack([X, np.ones(len(X))])
        reg = RIDGE * len(X) * np.eye(A.shape[1])
        reg[-1, -1] = 0.0  # the offset is not shrunk
        coef = np.linalg.solve(A.T @ A + reg, A.T @ r)
        chans.append(LinearCorrection(ch, coef[:-1], float(coef[-1])))
    return dataclasses.replace(model, channels=(chans[0], chans[1]))


#: The parts of a channel --parts-from swaps, and the sets of them tried.
PARTS = ("noise", "signal", "lengthscales", "pseudo-inputs")
PART_SETS: tuple[tuple[str, ...], ...] = (
    (), ("noise",), ("signal",), ("lengthscales",), ("pseudo-inputs",),
    ("lengthscales", "pseudo-inputs"), PARTS)


def with_parts(model: MotionModel, donor: MotionModel, parts: tuple[str, ...],
               learn: list[Series]) -> MotionModel:
    """The FITC posterior of ``learn`` (constant prior mean) at MODEL's pseudo-inputs and
    hyperparameters, with ``parts`` taken from ``donor``."""
    chans = []
    for c, (own, other) in enumerate(zip(model.channels, donor.channels, strict=True)):
        assert isinstance(own, SparseGP) and isinstance(other, SparseGP)
        X, y = design(learn, c, model.feature_config)
        pick = {p: (other if p in parts else own) for p in PARTS}
        chans.append(SparseGP.from_params(
            X, y, pick["pseudo-inputs"].inducing_inputs, pick["lengthscales"].lengthscales,
            pick["signal"].signal_variance, pick["noise"].noise_variance, jitter=own.jitter))
    return dataclasses.replace(model, channels=(chans[0], chans[1]))


def input_names(config: FeatureConfig, channel: int) -> list[str]:
    """The input row's entries (``asgp_ros.core.features.build_inputs``), oldest lag first."""
    s = config.lags
    lags = [f"t-{s - i}" for i in range(s)]
    if config.coupled:
        return ([f"joy forward {lag}" for lag in lags] + [f"joy turn {lag}" for lag in lags]
                + [f"v {lag}" for lag in lags] + [f"omega {lag}" for lag in lags]
                + ["joy forward t", "joy turn t"])
    axis = ("forward", "turn")[channel]
    return ([f"joy {axis} {lag}" for lag in lags] + [f"{CHANNELS[channel]} {lag}" for lag in lags]
            + [f"joy {axis} t"])


def lengthscale_differences(model: MotionModel, donor: MotionModel, factor: float = 10.0
                            ) -> list[str]:
    """Lines naming the inputs whose lengthscales in the two models differ ``factor``-fold."""
    lines = []
    for c, (own, other) in enumerate(zip(model.channels, donor.channels, strict=True)):
        assert isinstance(own, SparseGP) and isinstance(other, SparseGP)
        names = input_names(model.feature_config, c)
        for name, a, b in zip(names, own.lengthscales, other.lengthscales, strict=True):
            if max(a, b) >= factor * min(a, b):
                lines.append(f"    {CHANNELS[c]}: {name}: {a:.3g} (MODEL) vs {b:.3g} (MODEL2)")
    return lines


def simulate_tile(out: Path, recordings: tuple[tuple[int, float], ...]) -> list[str]:
    """Tile recordings (seed, minutes) simulated into ``out`` by ``asgp simulate``."""
    bags = []
    for seed, minutes in recordings:
        bags.append(str(out / f"tile_{seed}"))
        print(f"simulating {minutes:g} minutes of tile (seed {seed}) ...", flush=True)
        subprocess.run([sys.executable, "-m", "asgp_ros.cli", "simulate", "--surface",
                        "tile", "--minutes", str(minutes), "--seed", str(seed), "--out",
                        bags[-1], "--no-truth"], cwd=REPO, check=True,
                       env=dict(os.environ, PYTHONPATH=str(REPO)))
    return bags


def _minutes(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"minutes must be a number > 0, got {text}")
    return value


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", nargs="?", default=str(MODELS / "carpet_asgp.npz"),
                    help="the trained ASGP (another floor's; default the committed carpet "
                         "model)")
    ap.add_argument("--learn", help="a recording of the new floor to learn from")
    ap.add_argument("--test", nargs="+", help="recordings of the new floor")
    ap.add_argument("--minutes", nargs="+", type=_minutes, default=[0.5, 1, 2, 5, 10],
                    help="learn from the first N minutes (and from the whole recording)")
    ap.add_argument("--reference", help="a model trained on the new floor, scored beside "
                    "(default with simulated recordings: the committed tile model)")
    ap.add_argument("--parts-from", metavar="MODEL2",
                    help="also condition the whole --learn recording at MODEL's parameters "
                         "with parts of MODEL2's (same inputs)")
    args = ap.parse_args(argv)
    if (args.learn is None) != (args.test is None):
        ap.error("give both --learn and --test, or neither (simulated tile recordings)")
    if args.learn is not None:
        return run(args)
    with tempfile.TemporaryDirectory() as tmp:
        bags = simulate_tile(Path(tmp), SIMULATED)
        args.learn, args.test = bags[0], bags[1:]
        if args.reference is None:
            args.reference = str(MODELS / "tile_asgp.npz")
        return run(args)


def run(args: argparse.Namespace) -> int:
    """Print the curve for parsed arguments (``--learn`` and ``--test`` given)."""
    model = load_model(args.model)
    rc = model.resample_config
    learn = read_series([args.learn], resample_config=rc)[0]
    tests = [TestSeries(s.name, s.res) for s in read_series(args.test, resample_config=rc)]
    rate = rc.rate_hz
    steps_held = int(learn.res.t.shape[0])
    minutes_held = steps_held / rate / 60.0
    lags = [model.lags]
    reference = load_model(args.reference) if args.reference else None
    if reference is not None:
        lags.append(reference.lags)
    case_lags = max(lags)

    def score(m: MotionModel) -> str:
        ev = evaluate_model(m, tests, HORIZONS_S, case_lags=case_lags, uncertainty="none")
        return " / ".join(f"{100 * h.vo.success_rate:5.1f}" for h in ev.horizons.values())

    print(f"model {args.model} (s = {model.lags}); learning from {args.learn} "
          f"({minutes_held:.1f} min); testing on {len(tests)} recording(s)")
    print(f"success (%) at {' / '.join(f'{h:g}' for h in HORIZONS_S)} s")
    with threadpool_limits(limits=1):
        print(f"  as trained:                          {score(model)}")
        if reference is not None:
            print(f"  trained on the new floor (reference): {score(reference)}")
        print("  minutes   constant mean          trained mean           linear correction")
        for minutes in [m for m in args.minutes if m < minutes_held] + [minutes_held]:
            steps = min(round(minutes * 60 * rate), steps_held)
            part = [Series(learn.name, slice_resampled(learn.res, 0, steps))]
            print(f"  {minutes:7.3g}   {score(adapted(model, part, False))}    "
                  f"{score(adapted(model, part, True))}    {score(corrected(model, part))}",
                  flush=True)
        if args.parts_from:
            donor = load_model(args.parts_from)
            if donor.feature_config != model.feature_config or donor.kind != "asgp" \
                    or model.kind != "asgp":
                print(f"--parts-from: {args.parts_from} is not an ASGP of MODEL's inputs "
                      f"(s = {donor.lags}, coupled = {donor.feature_config.coupled})")
                return 2
            print(f"  the whole recording at MODEL's parameters, parts from {args.parts_from}:")
            for parts in PART_SETS:
                label = "all" if parts == PARTS else ", ".join(parts) or "none"
                print(f"    {label:33s} {score(with_parts(model, donor, parts, [learn]))}",
                      flush=True)
            print("  inputs whose lengthscales differ 10-fold or more:")
            print("\n".join(lengthscale_differences(model, donor)) or "    none")
    return 0


if __name__ == "__main__":
    sys.exit(main())
