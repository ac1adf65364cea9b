"""Autoregressive input rows (paper eq. 3-4), coupling, and segment boundaries."""

from __future__ import annotations

import numpy as np
import pytest

from asgp_ros.core.features import FeatureConfig, build_inputs, design_matrix, input_layout
from asgp_ros.core.resample import Resampled


def make_resampled(joy: np.ndarray, vel: np.ndarray, valid: np.ndarray) -> Resampled:
    T = joy.shape[0]
    segment = -np.ones(T, dtype=np.int64)
    starts = valid & np.r_[True, ~valid[:-1]]
    segment[valid] = (np.cumsum(starts) - 1)[valid]
    false = np.zeros(T, dtype=bool)
    return Resampled(
        t=np.arange(T) / 5.0, k=np.arange(T, dtype=np.int64), joy=joy, vel=vel,
        valid=valid, stale=false, tracking_lost=false, gap=~valid, segment=segment,
        truth=np.full((T, 5), np.nan), truth_valid=false, rate_hz=5.0,
    )


def small_example(T: int = 7) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(T, dtype=float)
    joy = np.stack([10 + t, 20 + t], axis=1)  # forward = 10 + t, turn = 20 + t
    vel = np.stack([30 + t, 40 + t], axis=1)  # v = 30 + t, omega = 40 + t
    return joy, vel


def test_hand_built_rows_eq_3_4() -> None:
    joy, vel = small_example()
    res = make_resampled(joy, vel, np.ones(7, dtype=bool))
    cfg = FeatureConfig(lags=2)
    Xv, yv, idx = design_matrix(res, 0, cfg)
    # t = 2: [j_fwd(0), j_fwd(1), v(0), v(1), j_fwd(2)] -> v(2)
    np.testing.assert_array_equal(Xv[0], [10, 11, 30, 31, 12])
    assert yv[0] == 32
    np.testing.assert_array_equal(idx, [2, 3, 4, 5, 6])
    np.testing.assert_array_equal(Xv[-1], [14, 15, 34, 35, 16])
    assert yv[-1] == 36
    Xw, yw, _ = design_matrix(res, 1, cfg)
    np.testing.assert_array_equal(Xw[0], [20, 21, 40, 41, 22])
    assert yw[0] == 42


def test_coupled_rows_and_shape() -> None:
    joy, vel = small_example()
    res = make_resampled(joy, vel, np.ones(7, dtype=bool))
    cfg = FeatureConfig(lags=2, coupled=True)
    assert cfg.input_dim == 10
    for channel, target in ((0, 32), (1, 42)):
        X, y, _ = design_matrix(res, channel, cfg)
        assert X.shape == (5, 10)
        np.testing.assert_array_equal(X[0], [10, 11, 20, 21, 30, 31, 40, 41, 12, 22])
        assert y[0] == target


def test_default_dimensions() -> None:
    assert FeatureConfig().input_dim == 9  # the paper: s = 4, D = 2s + 1
    assert FeatureConfig(lags=4, coupled=True).input_dim == 18


@pytest.mark.parametrize("coupled", [False, True])
@pytest.mark.parametrize("channel", [0, 1])
def test_layout_describes_build_inputs(coupled: bool, channel: int) -> None:
    cfg = FeatureConfig(lags=3, coupled=coupled)
    rng = np.random.default_rng(0)
    jp, vp, jn = rng.normal(size=(3, 2)), rng.normal(size=(3, 2)), rng.normal(size=2)
    x = build_inputs(jp, vp, jn, channel, cfg)
    lay = input_layout(channel, cfg)
    seen = []
    for arr, src in ((lay.joy_past, jp), (lay.vel_past, vp), (lay.joy_now, jn)):
        mask = arr >= 0
        np.testing.assert_array_equal(x[arr[mask]], src[mask])
        seen.extend(arr[mask].tolist())
    assert sorted(seen) == list(range(cfg.input_dim))
    if not coupled:  # only the matching axis and velocity
        assert np.all(lay.vel_past[:, 1 - channel] == -1)


def test_rows_never_cross_a_gap() -> None:
    joy, vel = small_example(12)
    valid = np.ones(12, dtype=bool)
    valid[5] = False  # a gap at grid index 5
    res = make_resampled(joy, vel, valid)
    cfg = FeatureConfig(lags=2)
    X, _, idx = design_matrix(res, 0, cfg)
    # segment 0 = 0..4 -> targets 2, 3, 4; segment 1 = 6..11 -> targets 8..11
    np.testing.assert_array_equal(idx, [2, 3, 4, 8, 9, 10, 11])
    for row, t in zip(X, idx, strict=True):
        np.testing.assert_array_equal(row[:2], joy[t - 2:t, 0])
        np.testing.assert_array_equal(row[2:4], vel[t - 2:t, 0])
    # adjacent valid segments with different ids (e.g. a resampled gap between two valid
    # points) must also split rows
    res2 = make_resampled(joy, vel, np.ones(12, dtype=bool))
    seg = res2.segment.copy()
    seg[6:] = 1
    object.__setattr__(res2, "segment", seg)
    _, _, idx2 = design_matrix(res2, 0, cfg)
    assert not np.any((idx2 >= 6) & (idx2 < 8))


def test_batched_build_inputs_and_broadcast() -> None:
    cfg = FeatureConfig(lags=4)
    rng = np.random.default_rng(1)
    jp = rng.normal(size=(4, 2))
    vp = rng.normal(size=(5, 4, 2))
    jn = rng.normal(size=(5, 2))
    X = build_inputs(jp, vp, jn, 1, cfg)
    assert X.shape == (5, 9)
    for b in range(5):
        np.testing.assert_array_equal(X[b], build_inputs(jp, vp[b], jn[b], 1, cfg))


def test_short_or_invalid_recording_gives_no_rows() -> None:
    joy, vel = small_example(3)
    X, y, idx = design_matrix(make_resampled(joy, vel, np.ones(3, dtype=bool)), 0,
                              FeatureConfig(lags=4))
    assert X.shape == (0, 9) and y.shape == (0,) and idx.shape == (0,)
    joy, vel = small_example(8)
    X, _, _ = design_matrix(make_resampled(joy, vel, np.zeros(8, dtype=bool)), 0,
                            FeatureConfig(lags=2))
    assert X.shape == (0, 5)


def test_bad_input_raises() -> None:
    cfg = FeatureConfig(lags=2)
    with pytest.raises(ValueError, match="joy_past"):
        build_inputs(np.zeros((3, 2)), np.zeros((2, 2)), np.zeros(2), 0, cfg)
    with pytest.raises(ValueError, match="vel_past contains NaN"):
        build_inputs(np.zeros((2, 2)), np.full((2, 2), np.nan), np.zeros(2), 0, cfg)
    with pytest.raises(ValueError, match="channel"):
        build_inputs(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros(2), 2, cfg)
    with pytest.raises(ValueError, match="lags"):
        FeatureConfig(lags=0)
    with pytest.raises(ValueError, match="lags"):
        FeatureConfig(lags=2.5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="coupled must be a bool"):
        FeatureConfig(lags=2, coupled="yes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown"):
        FeatureConfig.from_dict({"lags": 4, "foo": 1})
    assert FeatureConfig.from_dict(FeatureConfig(3, True).to_dict()) == FeatureConfig(3, True)
