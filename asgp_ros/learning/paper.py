"""The published results of Fan et al. (ICRA 2018), Tables I-III, as data.

Percent of pose predictions with no more than 10 cm (x, y) error at the horizon, against
the path integrated from the recorded VO, on a real chair (Permobil M300, Fovis VO on an
Asus Xtion looking backward, 5 Hz grid). Train sets of 120 minutes (Tile, Carpet, Both
1:1), test sets of 40 minutes (Tile, Carpet, Hybrid). ASGP: s = 4, M = 20 (v) / 40
(omega); MLP: s = 10, 3 x 30 ReLU, Adam, batch 100.

The paper has one table per horizon (I: 1.0 s, II: 1.4 s, III: 2.0 s) with rows test set x
model and columns train set. :data:`TABLES` holds them as printed; :func:`success_rate`
looks a figure up by (test set, train set, model, horizon), the way ``asgp reproduce``
lays out its own tables (one per test set).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

#: The paper's model names.
MODELS = ("MLP", "ASGP")
TRAIN_SETS = ("Tile", "Carpet", "Both")
TEST_SETS = ("Tile", "Carpet", "Hybrid")
_Table = Mapping[str, Mapping[str, tuple[float, float, float]]]


def _table(rows: dict[str, dict[str, tuple[float, float, float]]]) -> _Table:
    return MappingProxyType({test: MappingProxyType(models) for test, models in rows.items()})


#: {horizon: {test set: {model: (Tile, Carpet, Both train set)}}}, success rates in %,
#: exactly as printed in the paper's Tables I-III.
TABLES: Mapping[str, _Table] = MappingProxyType({
    "1.0": _table({
        "Tile": {"MLP": (92.21, 92.66, 91.69), "ASGP": (94.86, 94.55, 94.51)},
        "Carpet": {"MLP": (82.21, 75.26, 83.45), "ASGP": (83.79, 82.12, 82.94)},
        "Hybrid": {"MLP": (79.96, 82.04, 83.46), "ASGP": (84.01, 83.05, 82.35)},
    }),
    "1.4": _table({
        "Tile": {"MLP": (81.07, 79.37, 75.03), "ASGP": (85.91, 85.01, 85.03)},
        "Carpet": {"MLP": (67.66, 50.56, 69.57), "ASGP": (69.40, 68.72, 69.66)},
        "Hybrid": {"MLP": (63.61, 63.55, 67.35), "ASGP": (68.50, 68.73, 67.72)},
    }),
    "2.0": _table({
        "Tile": {"MLP": (63.14, 60.60, 52.06), "ASGP": (72.37, 70.64, 71.19)},
        "Carpet": {"MLP": (43.79, 31.11, 51.00), "ASGP": (50.21, 51.69, 51.69)},
        "Hybrid": {"MLP": (40.76, 41.82, 43.48), "ASGP": (47.91, 50.89, 48.77)},
    }),
})

#: The paper's summary (Sec. V): ASGP's lead over the MLP averaged over the nine
#: train x test pairs, in points, at 1.0, 1.4 and 2.0 s.
MEAN_LEAD_POINTS = MappingProxyType({"1.0": 2.14, "1.4": 5.66, "2.0": 9.73})


def success_rate(test: str, train: str, model: str, horizon: str) -> float | None:
    """The paper's success rate (%) of ``model`` ("ASGP" or "MLP") trained on ``train``
    and tested on ``test`` at ``horizon`` (a key such as "1.0"); None where the paper
    has no such cell (another horizon, model or set)."""
    table = TABLES.get(horizon)
    if table is None or test not in table or model not in table[test]:
        return None
    if train not in TRAIN_SETS:
        return None
    return table[test][model][TRAIN_SETS.index(train)]
