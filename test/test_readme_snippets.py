"""README's python snippets run as written: each block on its own (it imports what it uses),
given only the inputs its text stands for (a time, the stick, a model, data), with
"chair.npz" the committed tile model. "Adapting online"'s snippet used Predictor,
PredictorConfig and load_model without importing them (NameError): no test ran the blocks.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from asgp_ros.core.modelfile import load_model
from asgp_ros.core.online import Predictor, PredictorConfig

REPO = Path(__file__).resolve().parents[1]
MODEL = REPO / "docs" / "reproduction" / "models" / "tile_asgp.npz"


README = REPO / "README.md"


def python_blocks() -> list[tuple[int, str]]:
    """(line, code) of every ```python block of README.md (none in a copy of the package
    without it: colcon's, test_package)."""
    if not README.exists():
        return []
    text = README.read_text()
    return [(text[:m.start()].count("\n") + 1, m.group(1))
            for m in re.finditer(r"^```python\n(.*?)^```$", text, flags=re.M | re.S)]


def inputs() -> dict[str, Any]:
    """The values the snippets' placeholders stand for: data and objects a user has, never
    a name the package provides (a snippet imports those itself)."""
    model = load_model(MODEL)
    s, k = model.feature_config.lags, 10
    rng = np.random.default_rng(0)
    X = rng.uniform(-2.0, 2.0, size=(60, 3))
    grey = rng.integers(0, 255, size=(120, 160), dtype=np.uint8)
    return {
        "t": 100.0, "now": 100.0, "fwd": 0.5, "turn": 0.1, "v": 0.4, "omega": 0.05,
        "candidates": np.zeros((4, k, 2)),
        "model": model, "predictor": Predictor(model, PredictorConfig(horizon_steps=k)),
        "joy_past": np.tile([0.5, 0.0], (s, 1)), "vel_past": np.tile([0.4, 0.0], (s, 1)),
        "target_xy": np.c_[0.08 * np.arange(1, k + 1), np.zeros(k)],
        "K": np.array([[100.0, 0.0, 80.0], [0.0, 100.0, 60.0], [0.0, 0.0, 1.0]]),
        "bgr_or_grey": grey, "depth": np.full(grey.shape, 2.0, dtype=np.float32),
        "X": X, "y": np.sin(X[:, 0]) + 0.1 * rng.standard_normal(60), "Xs": X[:5],
        "Z": X[:40], "lengthscales": np.ones(3), "signal_variance": 1.0,
        "noise_variance": 0.1,
    }


BLOCKS = python_blocks()


def test_readme_has_python_snippets():
    if not README.exists():
        pytest.skip("README.md is not beside this copy of the package")
    assert len(BLOCKS) >= 5


@pytest.mark.parametrize(("line", "code"), BLOCKS, ids=[f"README:{n}" for n, _ in BLOCKS])
def test_a_readme_python_snippet_runs_on_its_own(line, code):
    code = code.replace('"chair.npz"', repr(str(MODEL)))
    namespace = inputs()
    exec(compile(code, f"README.md:{line}", "exec"), namespace)
