"""Baseline channel models: the paper's MLP, constant velocity and a first-order lag.

Each class is a ``ChannelModel`` (``predict`` / ``predict_with_grad`` on the feature rows of
``features.build_inputs``), so the same rollout (Algorithm 1), evaluation and model file
serve every kind. All are deterministic: their predictive variance is 0.

* ``MLPChannel``: Fan et al. (ICRA 2018), Sec. V-B: three hidden layers of 30 ReLU units,
  trained with Adam, batch 100, on s = 10 lags, with early stopping on held-out rows
  (the step size reduced on plateau, see ``MLPChannel.fit``). Trained with scikit-learn's
  MLPRegressor, but stored and evaluated as plain weight arrays (numpy forward pass and its input
  gradient), so loading a model never unpickles anything.
* ``ConstantVelocityChannel``: hold the last measured velocity, V_t = V_{t-1}.
* ``FirstOrderLagChannel``: V_t = a V_{t-1} + b j_t + c per channel, fitted by least squares:
  the exact discretisation of a first-order lag dV/dt = (K j - V) / tau with a zero-order
  hold on j (a = exp(-dt/tau), b = K (1 - a)), plus an offset.

The columns holding V_{t-1} and j_t in a feature row come from ``features.input_layout``
at training time (so the baselines follow the feature layout, coupled or not) and are
stored with the model.

``fit_mlp``, ``fit_constant_velocity`` and ``fit_first_order_lag`` train one channel each
(the ``fit`` of a :class:`~asgp_ros.core.models.ModelKind`). The registry of kinds
(:mod:`asgp_ros.core.models`) lists these kinds; this module does not import it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core.features import FeatureConfig

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

#: Adam's step sizes of the MLP's training stages (each runs to its early stop; the next
#: continues from the best weights): the paper's optimiser, reduced on plateau.
MLP_LEARNING_RATES = (1e-3, 1e-4, 1e-5)
#: Epochs without a better held-out score before a stage stops.
MLP_PATIENCE = 15


def _as_rows(X: object, dim: int, name: str) -> FloatArray:
    Xa = np.asarray(X, dtype=np.float64)
    if Xa.ndim == 1:
        Xa = Xa[None, :]
    if Xa.ndim != 2 or Xa.shape[1] != dim:
        raise ValueError(f"{name}: expected inputs of shape [N, {dim}], got {Xa.shape}")
    if not np.all(np.isfinite(Xa)):
        raise ValueError(f"{name}: inputs contain NaN or inf")
    return Xa


def _scalar(arrays: dict[str, np.ndarray], key: str) -> float:
    return float(np.asarray(arrays[key]).reshape(()))


def _index(arrays: dict[str, np.ndarray], key: str, dim: int) -> int:
    i = int(np.asarray(arrays[key]).reshape(()))
    if not 0 <= i < dim:
        raise ValueError(f"column index {key}={i} outside [0, {dim})")
    return i


def probe_columns(channel: int, feature_config: Any) -> tuple[int, int, int]:
    """(D, column of V_{t-1} of this channel, column of j_t of this channel's axis).

    Read from ``features.input_layout``, the description of ``build_inputs``'s row.
    """
    from asgp_ros.core.features import input_layout

    layout = input_layout(channel, feature_config)
    vel_col = int(layout.vel_past[feature_config.lags - 1, channel])
    joy_col = int(layout.joy_now[channel])
    if vel_col < 0 or joy_col < 0:
        raise ValueError(f"feature layout feeds no V_{{t-1}} / j_t for channel {channel}")
    return int(feature_config.input_dim), vel_col, joy_col


class ConstantVelocityChannel:
    """V_t = V_{t-1}: the prediction is the feature column holding the last velocity."""

    kind = "constant_velocity"

    def __init__(self, input_dim: int, vel_col: int) -> None:
        if not 0 <= vel_col < input_dim:
            raise ValueError(f"velocity column {vel_col} outside [0, {input_dim})")
        self.input_dim = int(input_dim)
        self.vel_col = int(vel_col)

    def predict(self, X: object, include_noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """X [N, D] -> (mean [N], var [N] = 0)."""
        Xa = _as_rows(X, self.input_dim, self.kind)
        return Xa[:, self.vel_col].copy(), np.zeros(Xa.shape[0])

    def predict_with_grad(
        self, X: object, include_noise: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """X [N, D] -> (mean [N], var [N] = 0, dmean/dX [N, D])."""
        mean, var = self.predict(X)
        grad = np.zeros((mean.shape[0], self.input_dim))
        grad[:, self.vel_col] = 1.0
        return mean, var, grad

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"input_dim": np.asarray(self.input_dim), "vel_col": np.asarray(self.vel_col)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> ConstantVelocityChannel:
        dim = int(np.asarray(arrays["input_dim"]).reshape(()))
        return cls(dim, _index(arrays, "vel_col", dim))


class FirstOrderLagChannel:
    """V_t = a V_{t-1} + b j_t + c (least squares on the training rows)."""

    kind = "first_order_lag"

    def __init__(self, input_dim: int, vel_col: int, joy_col: int,
                 a: float, b: float, c: float) -> None:
        for name, col in (("velocity", vel_col), ("joystick", joy_col)):
            if not 0 <= col < input_dim:
                raise ValueError(f"{name} column {col} outside [0, {input_dim})")
        coef = np.array([a, b, c], dtype=np.float64)
        if not np.all(np.isfinite(coef)):
            raise ValueError(f"first-order lag coefficients must be finite, got {coef}")
        self.input_dim = int(input_dim)
        self.vel_col = int(vel_col)
        self.joy_col = int(joy_col)
        self.a, self.b, self.c = (float(x) for x in coef)

    @classmethod
    def fit(cls, X: object, y: object, input_dim: int, vel_col: int,
            joy_col: int) -> FirstOrderLagChannel:
        """Least-squares fit on design rows X [N, D] and targets y [N]."""
        Xa = _as_rows(X, input_dim, cls.kind)
        ya = np.asarray(y, dtype=np.float64).reshape(-1)
        if ya.shape[0] != Xa.shape[0] or Xa.shape[0] < 3:
            raise ValueError(f"need >= 3 rows and one target per row, got X {Xa.shape}, "
                             f"y {ya.shape}")
        A = np.column_stack((Xa[:, vel_col], Xa[:, joy_col], np.ones(Xa.shape[0])))
        coef, *_ = np.linalg.lstsq(A, ya, rcond=None)
        return cls(input_dim, vel_col, joy_col, *(float(x) for x in coef))

    @property
    def time_constant_steps(self) -> float:
        """tau / dt = -1 / ln(a) for 0 < a < 1 (inf otherwise)."""
        return float(-1.0 / np.log(self.a)) if 0.0 < self.a < 1.0 else float("inf")

    def predict(self, X: object, include_noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """X [N, D] -> (mean [N], var [N] = 0)."""
        Xa = _as_rows(X, self.input_dim, self.kind)
        mean = self.a * Xa[:, self.vel_col] + self.b * Xa[:, self.joy_col] + self.c
        return mean, np.zeros(Xa.shape[0])

    def predict_with_grad(
        self, X: object, include_noise: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """X [N, D] -> (mean [N], var [N] = 0, dmean/dX [N, D])."""
        mean, var = self.predict(X)
        grad = np.zeros((mean.shape[0], self.input_dim))
        grad[:, self.vel_col] = self.a
        grad[:, self.joy_col] = self.b
        return mean, var, grad

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "input_dim": np.asarray(self.input_dim),
            "vel_col": np.asarray(self.vel_col),
            "joy_col": np.asarray(self.joy_col),
            "coef": np.array([self.a, self.b, self.c]),
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> FirstOrderLagChannel:
        dim = int(np.asarray(arrays["input_dim"]).reshape(()))
        coef = np.asarray(arrays["coef"], dtype=np.float64).reshape(-1)
        if coef.shape != (3,):
            raise ValueError(f"coef must have 3 entries, got {coef.shape}")
        return cls(dim, _index(arrays, "vel_col", dim), _index(arrays, "joy_col", dim),
                   float(coef[0]), float(coef[1]), float(coef[2]))


class MLPChannel:
    """A ReLU multilayer perceptron as plain arrays: standardise, hidden ReLU layers, linear.

    mean(x) = y_mean + y_scale * (W_L^T relu(... relu(W_1^T ((x - x_mean) / x_scale) + b_1)
    ...) + b_L); weights [n_in, n_out] per layer as in scikit-learn's ``coefs_``.
    """

    kind = "mlp"

    def __init__(self, weights: list[FloatArray], biases: list[FloatArray],
                 x_mean: FloatArray, x_scale: FloatArray, y_mean: float, y_scale: float) -> None:
        if len(weights) != len(biases) or not weights:
            raise ValueError("MLP needs one bias vector per weight matrix, at least one layer")
        self.weights = [np.asarray(w, dtype=np.float64) for w in weights]
        self.biases = [np.asarray(b, dtype=np.float64).reshape(-1) for b in biases]
        self.x_mean = np.asarray(x_mean, dtype=np.float64).reshape(-1)
        self.x_scale = np.asarray(x_scale, dtype=np.float64).reshape(-1)
        self.y_mean = float(y_mean)
        self.y_scale = float(y_scale)
        dim = self.x_mean.shape[0]
        if self.x_scale.shape != (dim,) or np.any(self.x_scale <= 0.0):
            raise ValueError("MLP input scale must be positive with one entry per input")
        n_in = dim
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            if w.ndim != 2 or w.shape[0] != n_in or b.shape != (w.shape[1],):
                raise ValueError(f"MLP layer {i}: weights {w.shape} / bias {b.shape} do not "
                                 f"follow a layer of width {n_in}")
            n_in = w.shape[1]
        if n_in != 1:
            raise ValueError(f"MLP output layer must have 1 unit, has {n_in}")
        params = [*self.weights, *self.biases, self.x_mean, self.x_scale]
        if not all(np.all(np.isfinite(p)) for p in params) or not (
            np.isfinite(self.y_mean) and np.isfinite(self.y_scale) and self.y_scale > 0.0
        ):
            raise ValueError("MLP parameters must be finite (and the output scale positive)")
        self.input_dim = dim

    @classmethod
    def fit(
        cls,
        X: object,
        y: object,
        *,
        hidden: tuple[int, ...] = (30, 30, 30),
        batch_size: int = 100,
        max_iter: int = 200,
        seed: int = 0,
        learning_rates: tuple[float, ...] = MLP_LEARNING_RATES,
        patience: int = MLP_PATIENCE,
    ) -> tuple[MLPChannel, dict[str, Any]]:
        """Train with scikit-learn's MLPRegressor (ReLU, Adam) on standardised data.

        Early stopping on held-out rows: 10% of the rows (drawn once, by ``seed``) are never
        trained on; training stops when their R^2 has not improved for ``patience``
        epochs, and the weights with the best held-out score are kept. Any improvement
        counts (``tol = 0``): sklearn's default tolerance (1e-4 in R^2) stops one-step
        predictors with R^2 near 1 while the held-out error still falls by a few percent
        per epoch, long before the rollout error stops improving.

        Adam's step is reduced on plateau: each learning rate of ``learning_rates`` runs
        until its early stop, and the next (smaller) one continues from the best weights
        with a fresh Adam state on the same split. ``max_iter`` caps the epochs of all
        stages together.

        Returns:
            (model, info) with info = {"epochs" (all stages), "stage_epochs",
            "early_stopped" (the last stage stopped on its held-out score, not at the
            cap), "final_loss", "best_validation_score" (held-out R^2)}.
        """
        from sklearn.neural_network import MLPRegressor

        Xa, ya = _mlp_training_data(X, y)
        if not learning_rates or any(not lr > 0.0 for lr in learning_rates):
            raise ValueError(f"learning rates must be positive, got {learning_rates}")
        if max_iter < 1 or patience < 1:
            raise ValueError(f"max_iter and patience must be >= 1, got {max_iter}, {patience}")
        x_mean = Xa.mean(axis=0)
        x_scale = Xa.std(axis=0)
        x_scale[x_scale < 1e-12] = 1.0
        y_mean = float(ya.mean())
        y_scale = float(ya.std()) or 1.0
        Xs, ys = (Xa - x_mean) / x_scale, (ya - y_mean) / y_scale
        reg = MLPRegressor(
            hidden_layer_sizes=hidden,
            activation="relu",
            solver="adam",
            batch_size=min(batch_size, Xa.shape[0]),
            learning_rate_init=learning_rates[0],
            max_iter=max_iter,
            early_stopping=True,
            validation_fraction=0.1,
            n_iter_no_change=patience,
            tol=0.0,
            random_state=seed,  # an int: every stage draws the same held-out rows
        )
        stage_epochs, early_stopped = _fit_in_stages(reg, Xs, ys, learning_rates, max_iter)
        model = cls(list(reg.coefs_), list(reg.intercepts_), x_mean, x_scale, y_mean, y_scale)
        info = {
            "epochs": int(sum(stage_epochs)),
            "stage_epochs": stage_epochs,
            "early_stopped": bool(early_stopped),
            "final_loss": float(reg.loss_),
            "best_validation_score": float(reg.best_validation_score_),
        }
        return model, info

    def _forward(self, X: object) -> tuple[FloatArray, list[NDArray[np.bool_]]]:
        Xa = _as_rows(X, self.input_dim, self.kind)
        h = (Xa - self.x_mean) / self.x_scale
        masks = []
        for w, b in zip(self.weights[:-1], self.biases[:-1], strict=True):
            z = h @ w + b
            mask = z > 0.0
            masks.append(mask)
            h = np.where(mask, z, 0.0)
        out = (h @ self.weights[-1] + self.biases[-1])[:, 0]
        return self.y_mean + self.y_scale * out, masks

    def predict(self, X: object, include_noise: bool = True) -> tuple[FloatArray, FloatArray]:
        """X [N, D] -> (mean [N], var [N] = 0)."""
        mean, _ = self._forward(X)
        return mean, np.zeros(mean.shape[0])

    def predict_with_grad(
        self, X: object, include_noise: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """X [N, D] -> (mean [N], var [N] = 0, dmean/dX [N, D]) by backpropagation."""
        mean, masks = self._forward(X)
        n = mean.shape[0]
        # d out / d h_L-1 = W_L^T, then through each ReLU (its mask) and linear layer.
        g = np.broadcast_to(self.weights[-1][:, 0] * self.y_scale, (n, self.weights[-1].shape[0]))
        for w, mask in zip(reversed(self.weights[:-1]), reversed(masks), strict=True):
            g = (g * mask) @ w.T
        return mean, np.zeros(n), g / self.x_scale

    def to_arrays(self) -> dict[str, np.ndarray]:
        out: dict[str, np.ndarray] = {
            "n_layers": np.asarray(len(self.weights)),
            "x_mean": self.x_mean,
            "x_scale": self.x_scale,
            "y_norm": np.array([self.y_mean, self.y_scale]),
        }
        for i, (w, b) in enumerate(zip(self.weights, self.biases, strict=True)):
            out[f"W{i}"] = w
            out[f"b{i}"] = b
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> MLPChannel:
        n = int(np.asarray(arrays["n_layers"]).reshape(()))
        if not 1 <= n <= 64:
            raise ValueError(f"implausible number of MLP layers: {n}")
        missing = [k for i in range(n) for k in (f"W{i}", f"b{i}") if k not in arrays]
        if missing:
            raise ValueError(f"MLP arrays missing: {missing}")
        y_norm = np.asarray(arrays["y_norm"], dtype=np.float64).reshape(-1)
        if y_norm.shape != (2,):
            raise ValueError(f"y_norm must have 2 entries, got {y_norm.shape}")
        return cls(
            [np.asarray(arrays[f"W{i}"]) for i in range(n)],
            [np.asarray(arrays[f"b{i}"]) for i in range(n)],
            np.asarray(arrays["x_mean"]),
            np.asarray(arrays["x_scale"]),
            float(y_norm[0]),
            float(y_norm[1]),
        )


# ------------------------------------------------------------------- channel trainers


def _mlp_training_data(X: object, y: object) -> tuple[FloatArray, FloatArray]:
    """X [N, D] and y [N] as float arrays, checked: one target per row, at least 20 rows,
    all finite."""
    Xa = np.asarray(X, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64).reshape(-1)
    if Xa.ndim != 2 or ya.shape[0] != Xa.shape[0]:
        raise ValueError(f"X must be [N, D] with one target each, got {Xa.shape}, {ya.shape}")
    if Xa.shape[0] < 20:
        raise ValueError(f"too few training rows for the MLP: {Xa.shape[0]}")
    if not (np.all(np.isfinite(Xa)) and np.all(np.isfinite(ya))):
        raise ValueError("MLP training data contain NaN or inf")
    return Xa, ya


def _fit_in_stages(reg: Any, Xs: FloatArray, ys: FloatArray,
                   learning_rates: tuple[float, ...], max_iter: int) -> tuple[list[int], bool]:
    """Train ``reg`` (an early-stopping MLPRegressor) once per learning rate, each stage
    from the best weights of the last with a fresh Adam state, ``max_iter`` epochs in all;
    (epochs of each stage, whether the last stage stopped on its held-out score)."""
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    stage_epochs: list[int] = []
    early_stopped = False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        for stage, lr in enumerate(learning_rates):
            left = max_iter - sum(stage_epochs)
            if left < 1:
                break
            if stage:
                # Continue from the best weights (restored by the last stop). Copies:
                # sklearn restored them by reference, and Adam updates in place.
                reg.coefs_ = [w.copy() for w in reg.coefs_]
                reg.intercepts_ = [b.copy() for b in reg.intercepts_]
                # The patience count ran out at the last stop; warm_start keeps it.
                reg._no_improvement_count = 0
            reg.set_params(learning_rate_init=lr, max_iter=left, warm_start=stage > 0)
            reg.fit(Xs, ys)
            stage_epochs.append(int(reg.n_iter_))
            early_stopped = int(reg.n_iter_) < left
    return stage_epochs, early_stopped

class Budget(Protocol):
    """The part of :class:`asgp_ros.core.models.FitBudget` the baselines use."""

    max_iter: int
    seed: int


def _train_rmse(model: Any, X: FloatArray, y: FloatArray) -> float:
    mean, _ = model.predict(X)
    return float(np.sqrt(np.mean((mean - y) ** 2)))


def fit_mlp(channel: int, X: FloatArray, y: FloatArray, features: FeatureConfig,
            budget: Budget, progress: Callable[[str], None]
            ) -> tuple[MLPChannel, dict[str, Any]]:
    """The paper's MLP on one channel: at most ``budget.max_iter`` epochs."""
    model, info = MLPChannel.fit(X, y, max_iter=budget.max_iter, seed=budget.seed)
    stages = " + ".join(str(e) for e in info["stage_epochs"])
    how = "early stop" if info["early_stopped"] else "epoch cap reached"
    progress(f"done: {info['epochs']} epochs ({stages}, {how}), loss {info['final_loss']:.4f}"
             f", held-out R^2 {info['best_validation_score']:.5f}")
    return model, info


def fit_constant_velocity(channel: int, X: FloatArray, y: FloatArray, features: FeatureConfig,
                          budget: Budget, progress: Callable[[str], None]
                          ) -> tuple[ConstantVelocityChannel, dict[str, Any]]:
    """V_t = V_{t-1} on one channel: nothing to fit, only the column to read."""
    dim, vel_col, _ = probe_columns(channel, features)
    model = ConstantVelocityChannel(dim, vel_col)
    progress("constant velocity: nothing to fit")
    return model, {"train_rmse": _train_rmse(model, X, y)}


def fit_first_order_lag(channel: int, X: FloatArray, y: FloatArray, features: FeatureConfig,
                        budget: Budget, progress: Callable[[str], None]
                        ) -> tuple[FirstOrderLagChannel, dict[str, Any]]:
    """V_t = a V_{t-1} + b j_t + c on one channel, by least squares."""
    dim, vel_col, joy_col = probe_columns(channel, features)
    model = FirstOrderLagChannel.fit(X, y, dim, vel_col, joy_col)
    tau = model.time_constant_steps
    info: dict[str, Any] = {"coef": [model.a, model.b, model.c],
                            "time_constant_steps": tau if np.isfinite(tau) else None}
    progress(f"V_t = {model.a:.4f} V_t-1 + {model.b:.4f} j_t + {model.c:.4f}")
    info["train_rmse"] = _train_rmse(model, X, y)
    return model, info
