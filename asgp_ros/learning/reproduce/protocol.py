"""What ``asgp reproduce`` compares: the models, the train and test sets, the budgets.

The rows of the tables are the :data:`MODELS` (:func:`compared_models`); the train sets
:data:`TRAIN_SETS` and test sets :data:`TEST_SETS` are the paper's; :class:`Settings` holds
a run's budgets. The targets of the checks: :data:`COVERAGE_TARGET` (issue 11), the cells
where the training data cover the test surface (:data:`MATCHED`), and those issue 12 names
for the adapting row (:data:`ADAPT_ACROSS`, :data:`OWN_TRAIN`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace

from asgp_ros.core.adaptive import AdaptSettings
from asgp_ros.core.metrics import HORIZONS_S, THRESHOLD_M
from asgp_ros.core.models import ModelKind, get_kind, trainable_kinds
from asgp_ros.learning.paper import success_rate as published_rate
from asgp_ros.learning.training import PAPER_OPTIONS, TrainOptions

#: The automatic ASGP adapting online while it is scored, and the seconds into each test
#: bag from which issue 12's targets count (quick mode: its short bags' first sixth).
ADAPT_ROW = "asgp_adapt"
ADAPT_FROM_S = 60.0
QUICK_ADAPT_FROM_S = 10.0
#: What the adapting row runs with (the defaults of the node and of ``asgp evaluate
#: --adapt``); the report states them from here.
ADAPT_SETTINGS = AdaptSettings()


@dataclass(frozen=True)
class Compared:
    """One model of the comparison: a registered kind in a fixed or automatic configuration.

    Attributes:
        name: its key in the tables, results and model file names ("asgp_paper", ...).
        kind: the model kind (:mod:`asgp_ros.core.models`).
        label: its name in the report.
        options: the fixed configuration it is trained with (the seed and the iteration
            budget come from :class:`Settings`); None: the automatic configuration
            (:func:`asgp_ros.learning.training.train_auto`).
        paper: the paper's model this row is run as ("ASGP", "MLP";
            :mod:`asgp_ros.learning.paper`), whose published figures stand beside its cells;
            None for a model the paper did not run.
        colour: plot colour, if not the kind's.
        adapts: not trained itself: the automatic ASGP's model file, adapting online while
            it is scored (:func:`asgp_ros.learning.evaluation.evaluate_adaptive`).
    """

    name: str
    kind: str
    label: str
    options: TrainOptions | None
    paper: str | None = None
    colour: str | None = None
    adapts: bool = False

    @property
    def model_kind(self) -> ModelKind:
        return get_kind(self.kind)

    @property
    def automatic(self) -> bool:
        return self.options is None

    @property
    def plot_colour(self) -> str:
        return self.colour or self.model_kind.colour


def compared_models() -> dict[str, Compared]:
    """The rows of the tables, in order: the ASGP as the paper ran it and as ``asgp train``
    configures it, then every other trainable kind as the paper runs it (default lags)."""
    models = []
    for name in trainable_kinds():
        kind = get_kind(name)
        if name == PAPER_OPTIONS.kind:
            models += [Compared("asgp_paper", name, f"{kind.label} (paper)", PAPER_OPTIONS,
                                paper="ASGP", colour="tab:cyan"),
                       Compared(name, name, kind.label or name, None),
                       Compared(ADAPT_ROW, name, f"{kind.label or name} + adapt", None,
                                colour="tab:purple", adapts=True)]
        else:
            models.append(Compared(name, name, kind.label or name,
                                   TrainOptions(kind=name, lags=kind.default_lags),
                                   paper="MLP" if name == "mlp" else None))
    return {m.name: m for m in models}


#: The models compared, by name (see :func:`compared_models`).
MODELS = compared_models()
TRAIN_SETS = ("Tile", "Carpet", "Both")
TEST_SETS = ("Tile", "Carpet", "Hybrid")
TABLE_OF_TEST = {"Tile": "I", "Carpet": "II", "Hybrid": "III"}
#: ASGP calibration target (issue 11): 95% ellipse coverage within this range at every
#: horizon, where the training data cover the test surface.
COVERAGE_TARGET = (0.90, 0.98)
#: The ASGP rows whose claims and calibration are checked: the paper's, the automatic one.
ASGP_ROWS = ("asgp_paper", "asgp")


#: (train, test) pairs whose test surface the training data cover (hybrid = tile + carpet),
#: in the order of the report.
MATCHED_ORDER = (("Tile", "Tile"), ("Carpet", "Carpet"), ("Both", "Tile"), ("Both", "Carpet"),
                 ("Both", "Hybrid"))
MATCHED = frozenset(MATCHED_ORDER)


#: The cells issue 12 names (train on one surface, test on another) and the train set whose
#: automatic ASGP stands for "the model trained on the test surface" (Hybrid: Both).
ADAPT_ACROSS = (("Tile", "Carpet"), ("Tile", "Hybrid"), ("Carpet", "Tile"), ("Carpet", "Hybrid"))
OWN_TRAIN = {"Tile": "Tile", "Carpet": "Carpet", "Hybrid": "Both"}


def paper_rate(model: str, test: str, train: str, horizon: str) -> float | None:
    """The paper's published success rate (%) beside our row ``model`` (a key of
    :data:`MODELS`) on (test set, train set, horizon key); None for a row the paper has no
    figure for."""
    as_in_paper = MODELS[model].paper
    return None if as_in_paper is None else published_rate(test, train, as_in_paper, horizon)


class ReproduceError(ValueError):
    """The dataset or the options do not allow the protocol (message says why)."""


@dataclass(frozen=True)
class Settings:
    """Budgets of one run. ``auto_budget_s``: the automatic configuration's time budget
    (:class:`asgp_ros.learning.training.AutoOptions`; None: its default, sized for 120
    minutes of data)."""

    quick: bool = False
    asgp_max_iter: int = PAPER_OPTIONS.max_iter
    mlp_max_epochs: int = 200
    auto_budget_s: float | None = None
    seed: int = 0
    jobs: int = 2
    horizons: tuple[float, ...] = HORIZONS_S
    threshold_m: float = THRESHOLD_M

    @classmethod
    def for_mode(cls, quick: bool, jobs: int | None = None, seed: int = 0) -> Settings:
        base = cls(quick=quick, seed=seed, jobs=jobs or min(2, os.cpu_count() or 1))
        if quick:
            return replace(base, asgp_max_iter=40, auto_budget_s=10.0)
        return base

    def options(self, model: Compared) -> TrainOptions:
        """The fixed configuration of ``model`` with this run's seed and budget."""
        if model.options is None:
            raise ValueError(f"{model.label} has no fixed configuration")
        budget = self.mlp_max_epochs if model.kind == "mlp" else self.asgp_max_iter
        return replace(model.options, seed=self.seed, max_iter=budget)


def case_lags(trained_lags: Sequence[int] = ()) -> int:
    """Past samples every test case has: the largest s of the compared models (the fixed
    configurations' and ``trained_lags``, those of the trained models)."""
    fixed = [m.options.resolved_lags() for m in MODELS.values() if m.options is not None]
    return max([*fixed, *trained_lags])
