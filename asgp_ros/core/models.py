"""Two-channel motion models and the registry of model kinds for the model file.

A :class:`MotionModel` predicts V_t = (v_t, omega_t) from the autoregressive input rows of
:mod:`asgp_ros.core.features` with one :class:`ChannelModel` per channel (the paper's f_v
and f_omega). Any regressor with the two methods of :class:`ChannelModel` can be rolled out
(:mod:`asgp_ros.core.rollout`); deterministic baselines return zero variance.

The model file (:mod:`asgp_ros.core.modelfile`) stores a model as arrays plus JSON; each
model *kind* says how its channels become arrays and back (:class:`ModelKind`). ``"asgp"``
(two :class:`~asgp_ros.core.sparse_gp.SparseGP`) is built in; other kinds register
themselves with :func:`register_kind`.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core.features import CHANNELS, FeatureConfig, build_inputs
from asgp_ros.core.resample import ResampleConfig

FloatArray = NDArray[np.float64]


@runtime_checkable
class ChannelModel(Protocol):
    """One output channel: input rows [N, D] -> predictive mean and variance [N]."""

    def predict(self, X: FloatArray,
                include_noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """Mean [N] and variance [N] (of a new observation unless include_noise=False)."""
        ...

    def predict_with_grad(self, X: FloatArray, include_noise: bool = True
                          ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Mean [N], variance [N] and the mean's input gradient d mean / d X [N, D]."""
        ...


@dataclass(frozen=True)
class MotionModel:
    """A trained two-channel predictor.

    Attributes:
        kind: registered model kind (``"asgp"``, ...).
        feature_config: lags and coupling of the input rows.
        resample_config: the grid (rate) and validity rules the model was trained with.
        channels: (f_v, f_omega).
        meta: JSON-able information (training data summary, fit diagnostics, ...).
    """

    kind: str
    feature_config: FeatureConfig
    resample_config: ResampleConfig
    channels: tuple[ChannelModel, ChannelModel]
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or not _KIND_RE.fullmatch(self.kind):
            raise ValueError(f"model kind must be a short identifier, got {self.kind!r}")
        if len(self.channels) != 2:
            raise ValueError(f"a motion model has 2 channels (v, omega), got {len(self.channels)}")
        for name, ch in zip(CHANNELS, self.channels, strict=True):
            if not isinstance(ch, ChannelModel):
                raise TypeError(f"channel {name}: {type(ch).__name__} lacks predict / "
                                "predict_with_grad")
        object.__setattr__(self, "channels", tuple(self.channels))

    @property
    def lags(self) -> int:
        return self.feature_config.lags

    @property
    def rate_hz(self) -> float:
        return self.resample_config.rate_hz

    @property
    def dt(self) -> float:
        return self.resample_config.dt

    def predict_step(self, joy_past: ArrayLike, vel_past: ArrayLike, joy_now: ArrayLike,
                     include_noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """One-step prediction of V_t from windows.

        Args:
            joy_past: [..., s, 2]; vel_past: [..., s, 2]; joy_now: [..., 2].

        Returns:
            mean [..., 2] and variance [..., 2] of (v_t, omega_t).
        """
        means, variances = [], []
        for c, ch in enumerate(self.channels):
            X = build_inputs(joy_past, vel_past, joy_now, c, self.feature_config)
            lead = X.shape[:-1]
            m, v = ch.predict(X.reshape(-1, X.shape[-1]), include_noise)
            means.append(np.asarray(m).reshape(lead))
            variances.append(np.asarray(v).reshape(lead))
        return np.stack(means, axis=-1), np.stack(variances, axis=-1)


# --------------------------------------------------------------------------- registry

_KIND_RE = re.compile(r"[a-z][a-z0-9_]{0,31}")

Channels = tuple[ChannelModel, ChannelModel]
ToArrays = Callable[[MotionModel], tuple[dict[str, np.ndarray], dict[str, Any]]]
FromArrays = Callable[[Mapping[str, np.ndarray], Mapping[str, Any], FeatureConfig], Channels]


@dataclass(frozen=True)
class ModelKind:
    """How a model kind is stored.

    Attributes:
        name: the kind's identifier (lower case, digits, underscores).
        to_arrays: model -> (arrays, params): named numeric arrays (names matching
            ``[A-Za-z0-9_.]+``) and JSON-able parameters of the kind.
        from_arrays: (arrays, params, feature_config) -> (f_v, f_omega); raises
            ValueError (or KeyError for a missing array) naming the problem when the
            arrays do not make a valid model of this kind.
        description: one line for listings.
    """

    name: str
    to_arrays: ToArrays
    from_arrays: FromArrays
    description: str = ""


_REGISTRY: dict[str, ModelKind] = {}


def register_kind(kind: ModelKind, *, replace: bool = False) -> None:
    """Make a model kind known to :func:`~asgp_ros.core.modelfile.load_model`."""
    if not _KIND_RE.fullmatch(kind.name):
        raise ValueError(f"model kind must be a short identifier, got {kind.name!r}")
    if kind.name in _REGISTRY and not replace and _REGISTRY[kind.name] is not kind:
        raise ValueError(f"model kind {kind.name!r} is already registered")
    _REGISTRY[kind.name] = kind


def _import_builtin_kinds() -> None:
    """Register the kinds that ship with the package (the baselines live in their own module).

    Imported lazily because baselines.py itself registers through this module.
    """
    import asgp_ros.core.baselines  # noqa: F401  (registers "mlp", ... on import)


def get_kind(name: str) -> ModelKind:
    """The registered kind ``name``; KeyError listing the known kinds otherwise."""
    if name not in _REGISTRY:
        _import_builtin_kinds()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(
            f"unknown model kind {name!r} (known: {', '.join(sorted(_REGISTRY)) or 'none'})"
        ) from None


def registered_kinds() -> list[str]:
    _import_builtin_kinds()
    return sorted(_REGISTRY)


# ------------------------------------------------------------------- the "asgp" kind

def _asgp_to_arrays(model: MotionModel) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays: dict[str, np.ndarray] = {}
    for name, gp in zip(CHANNELS, model.channels, strict=True):
        get_state = getattr(gp, "get_state", None)
        if get_state is None:
            raise TypeError(f"channel {name} of an 'asgp' model is a {type(gp).__name__}, "
                            "not a SparseGP")
        for key, value in get_state().items():
            arrays[f"{name}.{key}"] = np.asarray(value)
    return arrays, {
        "channel_class": "SparseGP",
        "normalisation": "inputs standardised per column (<channel>.x_mean, .x_scale), "
        "outputs by <channel>.y_mean, .y_scale; kernel parameters in standardised units",
    }


def _asgp_from_arrays(arrays: Mapping[str, np.ndarray], params: Mapping[str, Any],
                      features: FeatureConfig) -> Channels:
    from asgp_ros.core.sparse_gp import SparseGP

    gps = []
    for name in CHANNELS:
        prefix = f"{name}."
        state = {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}
        if not state:
            raise ValueError(f"no arrays for channel {name!r}")
        try:
            gp = SparseGP.from_state(state)
        except (KeyError, ValueError, TypeError, IndexError) as exc:
            raise ValueError(f"channel {name}: invalid sparse GP state: {exc}") from exc
        dim = int(np.asarray(gp.inducing_inputs).shape[-1])
        if dim != features.input_dim:
            raise ValueError(
                f"channel {name}: inputs have {dim} columns but lags={features.lags}, "
                f"coupled={features.coupled} need {features.input_dim}"
            )
        try:
            mean, var = gp.predict(np.zeros((1, dim)))
        except (ValueError, IndexError) as exc:
            raise ValueError(f"channel {name}: state does not predict: {exc}") from exc
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var))):
            raise ValueError(f"channel {name}: state predicts non-finite values")
        gps.append(gp)
    return gps[0], gps[1]


register_kind(ModelKind(
    name="asgp",
    to_arrays=_asgp_to_arrays,
    from_arrays=_asgp_from_arrays,
    description="autoregressive sparse GP (FITC), one per channel (Fan et al. 2018)",
))
