"""benchmarks/adapt_data.py --parts-from: the inputs it names are the entries of the row
``build_inputs`` forms, and each part it swaps is the donor's and nothing else."""

from __future__ import annotations

import numpy as np
import pytest

from asgp_ros.core.features import FeatureConfig, build_inputs
from asgp_ros.core.models import MotionModel
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.core.sparse_gp import SparseGP


@pytest.fixture(scope="module")
def bench(load_benchmark):
    return load_benchmark("adapt_data")


@pytest.mark.parametrize("coupled", [True, False])
@pytest.mark.parametrize("channel", [0, 1])
def test_input_names_follow_the_row(bench, coupled, channel):
    s = 3
    config = FeatureConfig(lags=s, coupled=coupled)
    # every entry of the windows tells where it came from: 1000 * kind + 10 * lag + axis
    joy_past = np.array([[1000 + 10 * (s - i) + a for a in (0, 1)] for i in range(s)],
                        dtype=float)
    vel_past = np.array([[2000 + 10 * (s - i) + a for a in (0, 1)] for i in range(s)],
                        dtype=float)
    joy_now = np.array([1000.0, 1001.0])
    row = build_inputs(joy_past, vel_past, joy_now, channel, config)
    names = bench.input_names(config, channel)
    assert len(names) == row.shape[-1]
    axis_name = {(1000, 0): "joy forward", (1000, 1): "joy turn", (2000, 0): "v",
                 (2000, 1): "omega"}
    for name, value in zip(names, row, strict=True):
        kind, rest = int(value) // 1000 * 1000, int(value) % 1000
        lag, axis = rest // 10, rest % 10
        assert name == f"{axis_name[kind, axis]} {'t' if lag == 0 else f't-{lag}'}"


def _channel(rng, X, y, M, scale):
    Z = X[rng.choice(len(X), M, replace=False)]
    return SparseGP.from_params(X, y, Z, scale * np.ones(X.shape[1]), 0.5 * scale,
                                0.01 * scale)


def test_with_parts_takes_each_part_from_the_donor(bench, monkeypatch):
    rng = np.random.default_rng(0)
    config = FeatureConfig(lags=2, coupled=False)
    D = 5
    X = rng.normal(size=(200, D))
    y = np.sin(X[:, 0])

    def model(scale, M):
        chans = (_channel(rng, X, y, M, scale), _channel(rng, X, y, M, scale))
        return MotionModel("asgp", config, ResampleConfig(), chans)

    own, donor = model(1.0, 10), model(2.0, 12)
    learn = [object()]
    # the rows of the "recording"
    monkeypatch.setattr(bench, "design", lambda series, c, fc: (X[:150], y[:150]))
    for parts in bench.PART_SETS:
        out = bench.with_parts(own, donor, parts, learn)
        for c in range(2):
            gp, a, b = out.channels[c], own.channels[c], donor.channels[c]
            src = {p: (b if p in parts else a) for p in bench.PARTS}
            # conditioned on the recording's rows, not on the models' own
            ref = SparseGP.from_params(X[:150], y[:150], src["pseudo-inputs"].inducing_inputs,
                                       src["lengthscales"].lengthscales,
                                       src["signal"].signal_variance,
                                       src["noise"].noise_variance)
            np.testing.assert_allclose(gp.predict(X[150:])[0], ref.predict(X[150:])[0])
            np.testing.assert_allclose(gp.inducing_inputs, src["pseudo-inputs"].inducing_inputs,
                                       rtol=1e-12)
            np.testing.assert_allclose(gp.lengthscales, src["lengthscales"].lengthscales,
                                       rtol=1e-12)
            assert gp.signal_variance == pytest.approx(src["signal"].signal_variance, rel=1e-12)
            assert gp.noise_variance == pytest.approx(src["noise"].noise_variance, rel=1e-12)
    lines = bench.lengthscale_differences(own, donor, factor=1.5)
    assert len(lines) == 2 * D and "joy forward t-2" in lines[0]
    assert bench.lengthscale_differences(own, donor) == []
