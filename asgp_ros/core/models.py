"""Two-channel motion models and the registry of model kinds: the one list of the kinds.

A :class:`MotionModel` predicts V_t = (v_t, omega_t) from the autoregressive input rows of
:mod:`asgp_ros.core.features` with one :class:`ChannelModel` per channel (the paper's f_v
and f_omega). Any regressor with the two methods of :class:`ChannelModel` can be rolled out
(:mod:`asgp_ros.core.rollout`); deterministic baselines return zero variance.

A model *kind* (:class:`ModelKind`) declares, once, everything the package needs to know
about it: its name, default number of lags, how one channel is trained, how its channels
become arrays for the model file (:mod:`asgp_ros.core.modelfile`) and back, and its label
in reports. The kinds that ship with the package are listed in :data:`BUILTIN_KINDS`, at
the end of this module: the ASGP (two :class:`~asgp_ros.core.sparse_gp.SparseGP`, defined
here) and the baselines of :mod:`asgp_ros.core.baselines`. The dependency is one-way: this
module imports the baselines, which know nothing of the registry. Training
(:mod:`asgp_ros.learning.training`), the ``asgp train`` choices, evaluation and the reproduction
all read this registry. Other kinds can be added with :func:`register_kind`.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core import baselines
from asgp_ros.core.calibration import VarianceCalibration
from asgp_ros.core.features import CHANNELS, FeatureConfig, build_inputs
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.core.sparse_gp import SparseGP

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
        calibration: the map applied to each channel's predictive variance before it is
            used or propagated (:mod:`asgp_ros.core.calibration`); the identity unless the
            model was calibrated on held-out data.
        variance_floor: a model of the same inputs whose calibrated predictive variance at
            each input row bounds this one's from below (a model adapted online publishes
            the trained model here: its variance never goes below the trained posterior's,
            :mod:`asgp_ros.core.adaptive`).  Held at run time only: a model file never
            stores it.
    """

    kind: str
    feature_config: FeatureConfig
    resample_config: ResampleConfig
    channels: tuple[ChannelModel, ChannelModel]
    meta: dict[str, Any] = field(default_factory=dict)
    calibration: VarianceCalibration = field(default_factory=VarianceCalibration)
    variance_floor: MotionModel | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        floor = self.variance_floor
        if floor is not None and (not isinstance(floor, MotionModel)
                                  or floor.feature_config != self.feature_config):
            raise TypeError("variance_floor must be a MotionModel of the same input rows")
        if not isinstance(self.calibration, VarianceCalibration):
            raise TypeError("calibration must be a VarianceCalibration, got "
                            f"{type(self.calibration).__name__}")
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
            mean [..., 2] and variance [..., 2] of (v_t, omega_t), the variance calibrated
            (:attr:`calibration`, in the regime of the last measured speed) and not below
            :attr:`variance_floor`'s.
        """
        means, variances = [], []
        for c, ch in enumerate(self.channels):
            X = build_inputs(joy_past, vel_past, joy_now, c, self.feature_config)
            lead = X.shape[:-1]
            m, v = ch.predict(X.reshape(-1, X.shape[-1]), include_noise)
            means.append(np.asarray(m).reshape(lead))
            variances.append(np.asarray(v).reshape(lead))
        speed = np.asarray(vel_past, dtype=np.float64)[..., -1, 0]
        var = self.calibration.apply(np.stack(variances, axis=-1), speed)
        if self.variance_floor is not None:
            _, floor = self.variance_floor.predict_step(joy_past, vel_past, joy_now,
                                                        include_noise)
            var = np.maximum(var, floor)  # a NaN of either stays visible
        return np.stack(means, axis=-1), var


# --------------------------------------------------------------------------- registry

_KIND_RE = re.compile(r"[a-z][a-z0-9_]{0,31}")

Channels = tuple[ChannelModel, ChannelModel]
ToArrays = Callable[[MotionModel], tuple[dict[str, np.ndarray], dict[str, Any]]]
FromArrays = Callable[[Mapping[str, np.ndarray], Mapping[str, Any], FeatureConfig], Channels]
#: progress(message) of one channel's training, for a CLI's progress lines.
ChannelProgress = Callable[[str], None]


@dataclass(frozen=True)
class FitBudget:
    """What one training run may spend, whatever the kind.

    Attributes:
        max_iter: L-BFGS-B iterations (ASGP) or epochs (MLP).
        inducing: pseudo-inputs M per channel (v, omega) (ASGP).
        seed: random seed.
    """

    max_iter: int = 200
    inducing: tuple[int, int] = (20, 40)
    seed: int = 0


#: fit(channel index, X [N, D], y [N], features, budget, progress) -> (model, info): train
#: one channel on the design rows of :func:`asgp_ros.core.features.design_matrix`; info is
#: JSON-able (stored in the model file's meta). Raises ValueError naming the problem.
FitChannel = Callable[[int, FloatArray, FloatArray, FeatureConfig, FitBudget, ChannelProgress],
                      tuple[ChannelModel, dict[str, Any]]]


@dataclass(frozen=True)
class ModelKind:
    """A model kind: everything the package needs to know about it, declared once.

    Attributes:
        name: the kind's identifier (lower case, digits, underscores).
        to_arrays: model -> (arrays, params): named numeric arrays (names matching
            ``[A-Za-z0-9_.]+``) and JSON-able parameters of the kind.
        from_arrays: (arrays, params, feature_config) -> (f_v, f_omega); raises
            ValueError (or KeyError for a missing array) naming the problem when the
            arrays do not make a valid model of this kind.
        description: one line for listings.
        label: the kind's name in reports and plots.
        default_lags: s, the number of past samples per input row, unless asked otherwise.
        fit: trains one channel (:data:`FitChannel`); None for a kind that is only loaded.
        probabilistic: the channels predict a variance worth propagating (else zero:
            evaluated without uncertainty).
        colour: the kind's matplotlib colour in report plots.
    """

    name: str
    to_arrays: ToArrays
    from_arrays: FromArrays
    description: str = ""
    label: str = ""
    default_lags: int = 1
    fit: FitChannel | None = None
    probabilistic: bool = False
    colour: str = "tab:gray"


_REGISTRY: dict[str, ModelKind] = {}


def register_kind(kind: ModelKind, *, replace: bool = False) -> None:
    """Make a model kind known to training and :func:`~asgp_ros.core.modelfile.load_model`."""
    if not _KIND_RE.fullmatch(kind.name):
        raise ValueError(f"model kind must be a short identifier, got {kind.name!r}")
    if kind.name in _REGISTRY and not replace and _REGISTRY[kind.name] is not kind:
        raise ValueError(f"model kind {kind.name!r} is already registered")
    if kind.default_lags < 1:
        raise ValueError(f"model kind {kind.name!r}: default_lags must be >= 1")
    _REGISTRY[kind.name] = kind


def get_kind(name: str) -> ModelKind:
    """The registered kind ``name``; KeyError listing the known kinds otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(
            f"unknown model kind {name!r} (known: {', '.join(sorted(_REGISTRY)) or 'none'})"
        ) from None


def registered_kinds() -> list[str]:
    """Names of every registered kind, sorted."""
    return sorted(_REGISTRY)


def trainable_kinds() -> tuple[str, ...]:
    """Names of the kinds that can be trained, in the order they were registered."""
    return tuple(name for name, kind in _REGISTRY.items() if kind.fit is not None)


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


def _asgp_fit(channel: int, X: FloatArray, y: FloatArray, features: FeatureConfig,
              budget: FitBudget, progress: ChannelProgress
              ) -> tuple[ChannelModel, dict[str, Any]]:
    """SPGP / FITC with M pseudo-inputs by L-BFGS-B (Snelson & Ghahramani 2006)."""
    M = budget.inducing[channel]
    if X.shape[0] < M:
        raise ValueError(f"channel {CHANNELS[channel]}: {X.shape[0]} training rows < {M} "
                         "pseudo-inputs; record more data or lower --inducing-*")
    every = max(1, budget.max_iter // 10)

    def cb(it: int, lml: float) -> None:
        if it % every == 0:
            progress(f"iteration {it:4d}  log likelihood {lml:.2f}")

    gp = SparseGP(num_inducing=M, seed=budget.seed).fit(X, y, max_iter=budget.max_iter,
                                                        callback=cb)
    res = gp.optimiser_result
    info: dict[str, Any] = {
        "num_inducing": M, "log_likelihood": float(gp.log_marginal_likelihood()),
        "iterations": int(getattr(res, "nit", -1)) if res is not None else -1,
        "noise_std": float(np.sqrt(gp.noise_variance)),
        "lengthscales": [float(v) for v in gp.lengthscales]}
    progress(f"done: {info['iterations']} iterations, log likelihood "
             f"{info['log_likelihood']:.2f}, noise std {info['noise_std']:.4f}")
    return gp, info


# ------------------------------------------------------------- the baseline kinds

def _channel_storage(cls: Any) -> tuple[ToArrays, FromArrays]:
    """Model-file storage of a kind whose channels are instances of ``cls`` (a class with
    ``to_arrays()``, ``from_arrays(arrays)`` and ``input_dim``), one array prefix each."""
    name = cls.kind

    def to_arrays(model: MotionModel) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays: dict[str, np.ndarray] = {}
        for ch_name, ch in zip(CHANNELS, model.channels, strict=True):
            if not isinstance(ch, cls):
                raise TypeError(f"channel {ch_name} of a {name!r} model is a "
                                f"{type(ch).__name__}, not a {cls.__name__}")
            for key, value in ch.to_arrays().items():
                arrays[f"{ch_name}.{key}"] = np.asarray(value)
        return arrays, {"channel_class": cls.__name__}

    def from_arrays(arrays: Mapping[str, np.ndarray], params: Mapping[str, Any],
                    features: FeatureConfig) -> Channels:
        out = []
        for ch_name in CHANNELS:
            prefix = f"{ch_name}."
            sub = {k[len(prefix):]: np.asarray(v) for k, v in arrays.items()
                   if k.startswith(prefix)}
            if not sub:
                raise ValueError(f"no arrays for channel {ch_name!r}")
            try:
                ch = cls.from_arrays(sub)
            except KeyError as exc:
                raise ValueError(f"channel {ch_name}: missing array {exc}") from exc
            if ch.input_dim != features.input_dim:
                raise ValueError(
                    f"channel {ch_name}: inputs have {ch.input_dim} columns but "
                    f"lags={features.lags}, coupled={features.coupled} need "
                    f"{features.input_dim}")
            out.append(ch)
        return out[0], out[1]

    return to_arrays, from_arrays


def _kind(cls: Any, **declared: Any) -> ModelKind:
    to_arrays, from_arrays = _channel_storage(cls)
    return ModelKind(name=cls.kind, to_arrays=to_arrays, from_arrays=from_arrays, **declared)


# ------------------------------------------------------------------- the kinds, once

#: The kinds that ship with the package, in the order of listings, tables and plots.
BUILTIN_KINDS: tuple[ModelKind, ...] = (
    ModelKind(
        name="asgp", to_arrays=_asgp_to_arrays, from_arrays=_asgp_from_arrays,
        description="autoregressive sparse GP (FITC), one per channel (Fan et al. 2018)",
        label="ASGP", default_lags=4, fit=_asgp_fit, probabilistic=True, colour="tab:blue"),
    _kind(baselines.MLPChannel,
          description="the paper's MLP baseline: 3 x 30 ReLU per channel (Adam, batch 100)",
          label="MLP", default_lags=10, fit=baselines.fit_mlp, colour="tab:orange"),
    _kind(baselines.ConstantVelocityChannel,
          description="constant velocity: V_t = V_{t-1}",
          label="Const. velocity", default_lags=1, fit=baselines.fit_constant_velocity,
          colour="tab:gray"),
    _kind(baselines.FirstOrderLagChannel,
          description="first-order lag per channel: V_t = a V_{t-1} + b j_t + c",
          label="First-order lag", default_lags=1, fit=baselines.fit_first_order_lag,
          colour="tab:green"),
)

for _builtin in BUILTIN_KINDS:
    register_kind(_builtin)
