"""Autoregressive input rows of the motion predictor (Fan et al., ICRA 2018, eq. 3-4).

For output channel c (0 = v, 1 = omega) and lag s, the paper's uncoupled input at grid
step t is (eq. 3 for v, eq. 4 for omega)::

    X_t = [j_{t-s}, ..., j_{t-1},  V_{t-s}, ..., V_{t-1},  j_t]      D = 2 s + 1

with j the matching joystick axis (forward deflection for v, turn deflection for omega)
and V the channel's own velocity. The ``coupled`` option feeds both axes and both
velocities::

    X_t = [J_{t-s..t-1}[fwd], J_{t-s..t-1}[turn], V_{t-s..t-1}[v], V_{t-s..t-1}[omega],
           J_t[fwd], J_t[turn]]                                     D = 4 s + 2

:func:`build_inputs` is the one place a row is formed (training, evaluation, rollout and
the online node all call it); :func:`input_layout` describes the same layout as column
indices, for code that needs the input gradient with respect to the velocity window.
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core.resample import Resampled

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Names of the two output channels, in order.
CHANNELS = ("v", "omega")

#: Range of the number of lags s (inclusive): the paper uses 4, its MLP 10; 1000 steps are
#: 200 s at 5 Hz, beyond any history a prediction can use.
LAGS_RANGE = (1, 1000)


@dataclass(frozen=True)
class FeatureConfig:
    """Autoregressive feature settings.

    Attributes:
        lags: s, the number of past steps of joystick and velocity (the paper uses 4),
            in ``LAGS_RANGE``.
        coupled: feed both joystick axes and both velocities to each channel.
    """

    lags: int = 4
    coupled: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.lags, bool) or not isinstance(self.lags, int | np.integer):
            raise ValueError(f"lags must be an integer, got {self.lags!r}")
        low, high = LAGS_RANGE
        if not low <= int(self.lags) <= high:
            raise ValueError(f"lags must be in [{low}, {high}], got {self.lags}")
        if not isinstance(self.coupled, bool | np.bool_):
            raise ValueError(f"coupled must be a bool, got {self.coupled!r}")
        object.__setattr__(self, "lags", int(self.lags))
        object.__setattr__(self, "coupled", bool(self.coupled))

    @property
    def input_dim(self) -> int:
        """D, the width of an input row."""
        return 4 * self.lags + 2 if self.coupled else 2 * self.lags + 1

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FeatureConfig:
        unknown = set(d) - {"lags", "coupled"}
        if unknown:
            raise ValueError(f"unknown feature settings: {sorted(unknown)}")
        return cls(**d)


class InputLayout(NamedTuple):
    """Where each quantity sits in an input row of width D.

    ``joy_past[l, a]`` is the column of joystick axis a at lag l (l = 0 is t-s, s-1 is
    t-1), -1 if that axis is not fed; ``vel_past[l, c]`` likewise for velocity component c;
    ``joy_now[a]`` the column of J_t[a] or -1.
    """

    joy_past: IntArray  # [s, 2]
    vel_past: IntArray  # [s, 2]
    joy_now: IntArray  # [2]


def _check_channel(channel: int) -> int:
    if channel not in (0, 1):
        raise ValueError(f"channel must be 0 (v) or 1 (omega), got {channel!r}")
    return int(channel)


@functools.lru_cache(maxsize=64)
def input_layout(channel: int, config: FeatureConfig) -> InputLayout:
    """Column indices of the row built by :func:`build_inputs` (see :class:`InputLayout`).

    The arrays are read-only (the result is cached).
    """
    c = _check_channel(channel)
    s = config.lags
    jp = -np.ones((s, 2), dtype=np.int64)
    vp = -np.ones((s, 2), dtype=np.int64)
    jn = -np.ones(2, dtype=np.int64)
    lag = np.arange(s)
    if config.coupled:
        jp[:, 0], jp[:, 1] = lag, s + lag
        vp[:, 0], vp[:, 1] = 2 * s + lag, 3 * s + lag
        jn[:] = [4 * s, 4 * s + 1]
    else:
        jp[:, c] = lag
        vp[:, c] = s + lag
        jn[c] = 2 * s
    for arr in (jp, vp, jn):
        arr.setflags(write=False)
    return InputLayout(jp, vp, jn)


def build_inputs(joy_past: ArrayLike, vel_past: ArrayLike, joy_now: ArrayLike, channel: int,
                 config: FeatureConfig, *, validate: bool = True,
                 out: FloatArray | None = None) -> FloatArray:
    """Form input rows (paper eq. 3-4) from windows; the single definition of a row.

    Args:
        joy_past: [..., s, 2] joystick (forward, turn) at t-s .. t-1.
        vel_past: [..., s, 2] velocity (v, omega) at t-s .. t-1.
        joy_now: [..., 2] joystick at t.
        channel: 0 for v (forward axis), 1 for omega (turn axis).
        config: lags and coupling.
        validate: check shapes and finiteness (hot loops that checked once may skip).
        out: optional [..., D] array to write the rows into.

    Returns:
        [..., D] input rows (leading dimensions broadcast).
    """
    c = _check_channel(channel)
    s = config.lags
    jp = np.asarray(joy_past, dtype=np.float64)
    vp = np.asarray(vel_past, dtype=np.float64)
    jn = np.asarray(joy_now, dtype=np.float64)
    if validate:
        for name, arr, tail in (("joy_past", jp, (s, 2)), ("vel_past", vp, (s, 2)),
                                ("joy_now", jn, (2,))):
            if arr.shape[arr.ndim - len(tail):] != tail or arr.ndim < len(tail):
                raise ValueError(
                    f"{name}: expected shape [..., {', '.join(map(str, tail))}] for lags={s}, "
                    f"got {arr.shape}"
                )
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or inf")
    if config.coupled:
        parts = [jp[..., 0], jp[..., 1], vp[..., 0], vp[..., 1], jn]
    else:
        parts = [jp[..., c], vp[..., c], jn[..., c, None]]
    if not (jp.shape[:-2] == vp.shape[:-2] == jn.shape[:-1]):
        lead = np.broadcast_shapes(jp.shape[:-2], vp.shape[:-2], jn.shape[:-1])
        parts = [np.broadcast_to(p, (*lead, p.shape[-1])) for p in parts]
    return np.concatenate(parts, axis=-1, out=out)


def design_matrix(res: Resampled, channel: int,
                  config: FeatureConfig) -> tuple[FloatArray, FloatArray, IntArray]:
    """Training / evaluation rows from a resampled recording.

    A row is formed for every grid index t whose s predecessors and itself all lie in one
    valid segment (so no row spans a gap, a tracking failure or stale odometry).

    Args:
        res: resampled recording.
        channel: 0 for v, 1 for omega.
        config: lags and coupling.

    Returns:
        X [N, D] inputs, y [N] targets V_t[channel], index [N] grid index t of each target.
    """
    c = _check_channel(channel)
    s = config.lags
    n_grid = res.t.shape[0]
    D = config.input_dim
    if n_grid <= s:
        return np.zeros((0, D)), np.zeros(0), np.zeros(0, dtype=np.int64)
    seg = res.segment
    t_idx = np.arange(s, n_grid, dtype=np.int64)
    ok = (seg[t_idx] >= 0) & (seg[t_idx - s] == seg[t_idx])
    index = t_idx[ok]
    if index.size == 0:
        return np.zeros((0, D)), np.zeros(0), index
    # [T-s+1, 2, s+1] windows -> pick the ones ending at each target index
    joy_w = np.lib.stride_tricks.sliding_window_view(res.joy, s + 1, axis=0)[index - s]
    vel_w = np.lib.stride_tricks.sliding_window_view(res.vel, s, axis=0)[index - s]
    joy_past = np.swapaxes(joy_w[..., :s], -1, -2)  # [N, s, 2]
    joy_now = joy_w[..., s]  # [N, 2]
    vel_past = np.swapaxes(vel_w, -1, -2)  # [N, s, 2]
    X = build_inputs(joy_past, vel_past, joy_now, c, config)
    y = np.ascontiguousarray(res.vel[index, c])
    return X, y, index
