"""The cached FITC posterior: one object read by prediction, the fused rollout and the file.

Snelson & Ghahramani (2006) give the SPGP / FITC predictive distribution at a test input x
(S&G eq. 5; Quiñonero-Candela & Rasmussen 2005, eq. 24b), with ks = k(Z, x) [M]::

    mean(x)  = ks^T alpha,                alpha = (Kuu + Kuf Lambda^-1 Kfu)^-1 Kuf Lambda^-1 y
    var_f(x) = sf2 - ks^T C ks,           C = Kuu^-1 - (Kuu + Kuf Lambda^-1 Kfu)^-1
    var_y(x) = var_f(x) + sn2

In the factors of the FITC likelihood (:class:`asgp_ros.core.fitc.FitcTerms`),
L = chol(Kuu) and LA = chol(A) with A = I + V Lambda^-1 V^T, V = L^-1 Kuf:

    (P1)  alpha = L^-T LA^-T c,   c = LA^-1 V Lambda^-1 y
    (P2)  C = L^-T (I - A^-1) L^-1 = L^-T L^-1 - B^T B,   B = LA^-1 L^-1

so a prediction costs O(M) for the mean and O(M^2) for the variance per test point.
:class:`FitcPosterior` holds these cached terms (alpha, C, the pseudo-inputs, the kernel
parameters, the input and output scales, and the Cholesky factors L and LA they come
from).  It is immutable (its arrays are read-only): an update (a refit, a rank-one update
of LA and c) builds a new object, with :func:`from_factors` (P2 from the new factors), and
replaces the old one in a single assignment, so a reader holding the old one keeps a
consistent posterior and caches keyed on the object (the fused rollout's) cannot go stale.

:func:`predict` is the one implementation of the predictive equations and of the mean's
input gradient; it works on :class:`Stacked` posteriors, one or several channels (the
rollout evaluates v and omega together, a channel with fewer pseudo-inputs padded with
zero weights, which adds exact zeros).  The state arrays (:func:`to_state`,
:func:`from_state`) are those of the model file's ``asgp`` kind.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple, cast

import numpy as np
import scipy.linalg
from numpy.typing import ArrayLike, NDArray

from asgp_ros.core import kernel
from asgp_ros.core.kernel import CrossFactors

FloatArray = NDArray[np.float64]
#: scratch(name, shape) -> an array to overwrite (see :func:`predict`)
Scratch = Callable[[str, tuple[int, ...]], FloatArray]


class PosteriorError(ValueError):
    """A posterior or a stored state that is not valid; the message names the problem."""


@dataclass(frozen=True, eq=False)
class FitcPosterior:
    """The cached FITC posterior of one output, in standardised units (see module docstring).

    Inputs are standardised as (x - x_mean) / x_scale and outputs as (y - y_mean) / y_scale;
    Z, the lengthscales, sf2 and sn2 are in those units.  Build one with
    :func:`from_factors` (after a fit) or :func:`from_state` (a stored model); replace
    fields with :func:`dataclasses.replace`, which validates and re-derives the rest.

    Attributes:
        x_mean, x_scale: [D] input standardisation.
        y_mean, y_scale: output standardisation.
        Z: [M, D] pseudo-inputs.
        lengthscales: [D] ARD lengthscales.
        signal_variance: sf2.
        noise_variance: sn2.
        jitter: relative jitter of Kuu (Kuu = k(Z, Z) + jitter sf2 I).
        L: [M, M] lower Cholesky factor of Kuu.
        LA: [M, M] lower Cholesky factor of A = I + V Lambda^-1 V^T, or None for a state
            stored without it whose C does not give it back (see :func:`from_state`).
        alpha: [M] mean weights (P1).
        C: [M, M] variance matrix (P2), state key ``var_matrix``.
        kernel: (derived) the Z terms of the kernel, K2 of :mod:`asgp_ros.core.kernel`.
        stacked: (derived) this posterior as a one-channel :class:`Stacked`.
    """

    x_mean: FloatArray
    x_scale: FloatArray
    y_mean: float
    y_scale: float
    Z: FloatArray
    lengthscales: FloatArray
    signal_variance: float
    noise_variance: float
    jitter: float
    L: FloatArray
    LA: FloatArray | None
    alpha: FloatArray
    C: FloatArray
    kernel: CrossFactors = field(init=False, repr=False)
    stacked: Stacked = field(init=False, repr=False)

    def __post_init__(self) -> None:
        M, D = np.shape(self.Z)
        shapes = {"x_mean": (D,), "x_scale": (D,), "lengthscales": (D,), "Z": (M, D),
                  "L": (M, M), "LA": (M, M), "alpha": (M,), "C": (M, M)}
        for name, shape in shapes.items():
            value = getattr(self, name)
            if value is None and name == "LA":
                continue
            arr = np.array(value, dtype=np.float64)  # a private, read-only copy
            if arr.shape != shape:
                raise PosteriorError(f"posterior: {name} has shape {arr.shape}, expected "
                                     f"{shape} for M={M} pseudo-inputs in D={D} dimensions")
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        for name in ("y_mean", "y_scale", "signal_variance", "noise_variance", "jitter"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "kernel",
                           kernel.cross_factors(self.Z, self.lengthscales,
                                                self.signal_variance))
        object.__setattr__(self, "stacked", stack([self]))

    def with_weights(self, LA: FloatArray, alpha: FloatArray, C: FloatArray) -> FitcPosterior:
        """This posterior with new LA, alpha and C: what an online update changes (the
        inputs, pseudo-inputs and hyperparameters are the same).

        Equal to ``dataclasses.replace(self, LA=LA, alpha=alpha, C=C)``, but the unchanged
        (read-only) arrays and the derived kernel terms are shared, not copied, checked and
        derived again (nothing writes to them), and ``stacked`` is this one's with the new
        weights: an update of ``asgp_ros.core.adapt`` publishes a posterior per block of
        rows. LA, alpha and C are copied.
        """
        M = self.num_inducing
        new = {}
        for name, value, shape in (("LA", LA, (M, M)), ("alpha", alpha, (M,)),
                                   ("C", C, (M, M))):
            arr = np.array(value, dtype=np.float64)  # a private, read-only copy
            if arr.shape != shape:
                raise PosteriorError(f"posterior: {name} has shape {arr.shape}, expected "
                                     f"{shape}")
            arr.flags.writeable = False
            new[name] = arr
        out = object.__new__(FitcPosterior)
        out.__dict__.update(self.__dict__)
        out.__dict__.update(new)
        a = new["alpha"][None, :, None]  # as stack([out]) lays out one channel
        out.__dict__["stacked"] = self.stacked._replace(
            alpha=a, alpha_z=a * self.Z[None], C=new["C"][None])
        return out

    @property
    def num_inducing(self) -> int:
        """M."""
        return int(self.Z.shape[0])

    @property
    def num_features(self) -> int:
        """D."""
        return int(self.Z.shape[1])


def from_factors(x_mean: FloatArray, x_scale: FloatArray, y_mean: float, y_scale: float,
                 Z: FloatArray, lengthscales: FloatArray, signal_variance: float,
                 noise_variance: float, jitter: float, L: FloatArray, LA: FloatArray,
                 alpha: FloatArray) -> FitcPosterior:
    """The posterior from the Cholesky factors of a FITC fit: C by P2.

    Args: as the attributes of :class:`FitcPosterior` (standardised units); L, LA and
    alpha [M] from :class:`~asgp_ros.core.fitc.FitcTerms`.
    """
    return FitcPosterior(x_mean=x_mean, x_scale=x_scale, y_mean=y_mean, y_scale=y_scale,
                         Z=Z, lengthscales=lengthscales, signal_variance=signal_variance,
                         noise_variance=noise_variance, jitter=jitter, L=L, LA=LA,
                         alpha=alpha, C=variance_matrix(L, LA))


def variance_matrix(L: FloatArray, LA: FloatArray) -> FloatArray:
    """C = L^-T (I - A^-1) L^-1 [M, M] (P2) by triangular solves, symmetrised."""
    M = L.shape[0]
    Linv = scipy.linalg.solve_triangular(L, np.eye(M), lower=True, check_finite=False)
    B = scipy.linalg.solve_triangular(LA, Linv, lower=True, check_finite=False)  # LA^-1 L^-1
    S = Linv.T @ Linv - B.T @ B
    return cast(FloatArray, 0.5 * (S + S.T))


def chol_kuu(Z: FloatArray, lengthscales: FloatArray, signal_variance: float, jitter: float
             ) -> FloatArray:
    """L = chol(k(Z, Z) + jitter sf2 I) [M, M], lower; np.linalg.LinAlgError if singular."""
    Kuu = kernel.se_ard_jittered(Z, lengthscales, signal_variance, jitter)
    return cast(FloatArray, scipy.linalg.cholesky(Kuu, lower=True, check_finite=False))


def _chol_a_from_c(L: FloatArray, C: FloatArray) -> FloatArray | None:
    """LA from C and L for a state stored without it, or None if that is not possible.

    P2 gives A^-1 = I - L^T C L.  With J the reversal permutation and J A^-1 J = R R^T
    (R lower), A = (J R J)^-T (J R J)^-1, so LA = J R^-T J (lower): one Cholesky
    factorisation and one triangular solve, no inverse.  The subtraction cancels where
    A^-1 is small (much data), so LA is accurate to about eps times the conditioning of
    Kuu and A (1e-8 to 1e-7 relative for the paper's N = 36,000, M = 40), not to round-off.
    """
    M = L.shape[0]
    A_inv = np.eye(M) - L.T @ C @ L
    A_inv = 0.5 * (A_inv + A_inv.T)
    try:
        R = scipy.linalg.cholesky(A_inv[::-1, ::-1], lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    R_inv_t = scipy.linalg.solve_triangular(R, np.eye(M), lower=True, trans="T",
                                            check_finite=False)  # R^-T, upper
    LA = np.ascontiguousarray(R_inv_t[::-1, ::-1])  # J R^-T J, lower
    if not (np.all(np.isfinite(LA)) and np.all(np.diag(LA) > 0.0)):
        return None
    return LA


# ------------------------------------------------------------------------ state arrays

#: State entries of the posterior with their number of dimensions (``chol_a`` optional).
STATE_NDIM: dict[str, int] = {
    "x_mean": 1,  # [D]
    "x_scale": 1,  # [D]
    "y_mean": 0,
    "y_scale": 0,
    "inducing_inputs": 2,  # [M, D] standardised
    "lengthscales": 1,  # [D] standardised
    "signal_variance": 0,  # standardised
    "noise_variance": 0,  # standardised
    "jitter": 0,
    "alpha": 1,  # [M] posterior weights: mean = k(x, Z) @ alpha
    "var_matrix": 2,  # [M, M] C = Kuu^-1 - (Kuu + Kuf Lambda^-1 Kfu)^-1
}
OPTIONAL_STATE_NDIM: dict[str, int] = {
    "chol_a": 2,  # [M, M] LA = chol(I + V Lambda^-1 V^T); absent in older files
}


def to_state(post: FitcPosterior) -> dict[str, FloatArray]:
    """The posterior as named arrays (writable copies) for the model file."""
    f = np.float64
    state = {
        "x_mean": post.x_mean.copy(),
        "x_scale": post.x_scale.copy(),
        "y_mean": np.asarray(post.y_mean, dtype=f),
        "y_scale": np.asarray(post.y_scale, dtype=f),
        "inducing_inputs": post.Z.copy(),
        "lengthscales": post.lengthscales.copy(),
        "signal_variance": np.asarray(post.signal_variance, dtype=f),
        "noise_variance": np.asarray(post.noise_variance, dtype=f),
        "jitter": np.asarray(post.jitter, dtype=f),
        "alpha": post.alpha.copy(),
        "var_matrix": post.C.copy(),
    }
    if post.LA is not None:
        state["chol_a"] = post.LA.copy()
    return state


def state_array(state: Mapping[str, ArrayLike], key: str, ndim: int) -> FloatArray:
    """Entry ``key`` of a state as a finite float64 array of ``ndim`` dimensions."""
    if key not in state:
        raise PosteriorError(f"missing entry {key!r}")
    try:
        a = np.asarray(state[key], dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise PosteriorError(f"entry {key!r} is not numeric") from err
    if a.ndim != ndim:
        raise PosteriorError(f"entry {key!r} must have {ndim} dimension(s), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise PosteriorError(f"entry {key!r} contains NaN or inf")
    return a


#: Noise variances a stored state may have (standardised outputs; the fit keeps them in
#: [1e-6, 10]).
NOISE_VARIANCE_RANGE = (1e-9, 1e3)


def from_state(state: Mapping[str, ArrayLike]) -> FitcPosterior:
    """The posterior of :func:`to_state` arrays; alpha and C are used as stored.

    L is recomputed from the kernel parameters (the same arithmetic as the fit, so the
    same factor).  LA is the stored ``chol_a`` (checked against C); a state without it
    (files written before it was stored) gets LA from C by :func:`_chol_a_from_c`, or
    None where C does not give a positive definite A.

    Raises:
        PosteriorError (a ValueError) naming the missing, mis-shaped, non-finite or
        inconsistent entry.
    """
    arrs: dict[str, FloatArray] = {}
    for key, ndim in STATE_NDIM.items():
        arrs[key] = state_array(state, key, ndim)
    for key, ndim in OPTIONAL_STATE_NDIM.items():
        if key in state:
            arrs[key] = state_array(state, key, ndim)
    M, D = arrs["inducing_inputs"].shape
    expected = {"x_mean": (D,), "x_scale": (D,), "lengthscales": (D,), "alpha": (M,),
                "var_matrix": (M, M), "chol_a": (M, M)}
    for key, shape in expected.items():
        if key in arrs and arrs[key].shape != shape:
            raise PosteriorError(
                f"entry {key!r} has shape {arrs[key].shape}, expected {shape} for M={M} "
                f"pseudo-inputs in D={D} dimensions"
            )
    if M < 1 or D < 1:
        raise PosteriorError("entry 'inducing_inputs' is empty")
    for key in ("x_scale", "y_scale", "lengthscales", "signal_variance", "noise_variance"):
        if not np.all(arrs[key] > 0.0):
            raise PosteriorError(f"entry {key!r} must be > 0")
    if arrs["jitter"] < 0.0:
        raise PosteriorError("entry 'jitter' must be >= 0")
    # the fit's bounds (standardised outputs: 1e-6 .. 10) with a margin
    if not NOISE_VARIANCE_RANGE[0] <= float(arrs["noise_variance"]) <= NOISE_VARIANCE_RANGE[1]:
        raise PosteriorError(f"entry 'noise_variance' = {float(arrs['noise_variance']):g} is "
                             f"outside [{NOISE_VARIANCE_RANGE[0]:g}, "
                             f"{NOISE_VARIANCE_RANGE[1]:g}] (outputs have unit variance)")
    Z = np.ascontiguousarray(arrs["inducing_inputs"])
    sf2, jitter = float(arrs["signal_variance"]), float(arrs["jitter"])
    try:
        L = chol_kuu(Z, arrs["lengthscales"], sf2, jitter)
    except np.linalg.LinAlgError as err:
        raise PosteriorError("the kernel matrix of the pseudo-inputs is not positive "
                             f"definite for the stored parameters ({err})") from err
    C = arrs["var_matrix"]
    LA = arrs.get("chol_a")
    if LA is None:
        # nothing to check C against: L^T C L = I - A^-1 has its eigenvalues in [0, 1] for
        # any FITC posterior, and C is symmetric
        B = L.T @ C @ L
        eig = np.linalg.eigvalsh(0.5 * (B + B.T))
        asym = float(np.max(np.abs(C - C.T)))
        if asym > 1e-9 * max(float(np.max(np.abs(C))), 1e-300) \
                or eig[0] < -1e-6 or eig[-1] > 1.0 + 1e-6:
            raise PosteriorError("entry 'var_matrix' is no FITC posterior's (L^T C L has "
                                 f"eigenvalues {eig[0]:.3g} .. {eig[-1]:.3g}, not within "
                                 "[0, 1], or it is not symmetric)")
        LA = _chol_a_from_c(L, C)
    else:
        if not (np.allclose(LA, np.tril(LA), rtol=0.0, atol=0.0) and np.all(np.diag(LA) > 0)):
            raise PosteriorError("entry 'chol_a' is not a lower-triangular Cholesky factor")
        # A factor of another model differs by O(1); round-off in the recomputed L (another
        # BLAS, say) stays far below 1e-6.
        mismatch = float(np.max(np.abs(variance_matrix(L, LA) - C)))
        if not mismatch <= 1e-6 * max(float(np.max(np.abs(C))), 1e-300):
            raise PosteriorError(f"entries 'chol_a' and 'var_matrix' disagree (by {mismatch:.3g})")
    return FitcPosterior(
        x_mean=arrs["x_mean"], x_scale=arrs["x_scale"], y_mean=float(arrs["y_mean"]),
        y_scale=float(arrs["y_scale"]), Z=Z, lengthscales=arrs["lengthscales"],
        signal_variance=sf2, noise_variance=float(arrs["noise_variance"]), jitter=jitter,
        L=L, LA=LA, alpha=arrs["alpha"], C=C,
    )


# ------------------------------------------------------------------------ prediction

class Stacked(NamedTuple):
    """Posteriors of P channels laid out for :func:`predict` (leading axis: channel).

    Every array broadcasts against inputs [P, N, D].  Channels with fewer pseudo-inputs
    are padded to the largest M with z = 0 and zero weights (zero rows and columns of C),
    which adds exact zeros to every sum.
    """

    x_mean: FloatArray  # [P, 1, D]
    x_scale: FloatArray  # [P, 1, D]
    kernel: CrossFactors  # zt [P, D, M], offset [P, 1, M], inv_l2 [P, 1, D], log_sf2 [P, 1, 1]
    alpha: FloatArray  # [P, M, 1]
    alpha_z: FloatArray  # [P, M, D] alpha_m z_m, for the mean's gradient (K3)
    C: FloatArray  # [P, M, M]
    signal_variance: FloatArray  # [P, 1]
    noise_variance: FloatArray  # [P, 1]
    y_mean: FloatArray  # [P, 1]
    y_scale: FloatArray  # [P, 1]
    y_var: FloatArray  # [P, 1] y_scale^2
    grad_scale: FloatArray  # [P, 1, D] y_scale / (x_scale l^2): d mean / d x by K3


def stack(posteriors: Sequence[FitcPosterior]) -> Stacked:
    """One :class:`Stacked` of P posteriors of equal D (M may differ)."""
    M = max(p.num_inducing for p in posteriors)
    D = posteriors[0].num_features
    if any(p.num_features != D for p in posteriors):
        raise PosteriorError("posteriors to stack have different input dimensions")
    P = len(posteriors)
    Z = np.zeros((P, M, D))
    alpha = np.zeros((P, M, 1))
    C = np.zeros((P, M, M))
    factors = []
    for c, post in enumerate(posteriors):
        m = post.num_inducing
        Z[c, :m] = post.Z
        alpha[c, :m, 0] = post.alpha
        C[c, :m, :m] = post.C
        factors.append(post.kernel if m == M else
                       kernel.cross_factors(Z[c], post.lengthscales, post.signal_variance))
    kern = kernel.stack_factors(factors)

    def col(name: str) -> FloatArray:
        return np.array([getattr(p, name) for p in posteriors], dtype=np.float64)[:, None]

    x_scale = np.stack([p.x_scale for p in posteriors])[:, None, :]
    y_scale = col("y_scale")
    return Stacked(
        x_mean=np.stack([p.x_mean for p in posteriors])[:, None, :],
        x_scale=x_scale,
        kernel=kern,
        alpha=alpha,
        alpha_z=alpha * Z,
        C=C,
        signal_variance=col("signal_variance"),
        noise_variance=col("noise_variance"),
        y_mean=col("y_mean"),
        y_scale=y_scale,
        y_var=np.square(y_scale),
        grad_scale=y_scale[:, :, None] * kern.inv_l2 / x_scale,
    )


def _empty(name: str, shape: tuple[int, ...]) -> FloatArray:
    return np.empty(shape)


def predict(S: Stacked, X: FloatArray, include_noise: bool, with_grad: bool,
            scratch: Scratch | None = None, stacklevel: int = 2
            ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Predictive mean, variance and the mean's input gradient (S&G eq. 5, K2, K3):
    :func:`predict_with_kernel` without the kernel matrix."""
    mean, var, grad, _ = predict_with_kernel(S, X, include_noise, with_grad, scratch,
                                             stacklevel + 1)
    return mean, var, grad


def predict_with_kernel(S: Stacked, X: FloatArray, include_noise: bool, with_grad: bool,
                        scratch: Scratch | None = None, stacklevel: int = 2
                        ) -> tuple[FloatArray, FloatArray, FloatArray | None, FloatArray]:
    """Predictive mean, variance and the mean's input gradient (S&G eq. 5, K2, K3), and the
    kernel matrix K [P, N, M] of X against the pseudo-inputs (for :func:`floor_variance`).

    Args:
        S: P stacked posteriors.
        X: [P, N, D] inputs in original units (row n of channel p goes to posterior p);
            not modified.
        include_noise: the variance of a new observation (var_f + sn2) or of f.
        with_grad: also return d mean / d x.
        scratch: ``scratch(name, shape)`` gives arrays to overwrite (reused between
            calls by the rollout); by default fresh arrays.  The gradient is then a view
            of scratch memory, valid until the next call.
        stacklevel: of the negative-variance warning, as seen from the caller.

    Returns:
        mean [P, N], variance [P, N] (original units), d mean / d x [P, N, D] or None, and
        K [P, N, M] (scratch memory when ``scratch`` is given, like the gradient).

    A negative latent variance (cancellation in sf2 - ks^T C ks) is clipped to 0; below
    -1e-8 sf2 a RuntimeWarning says so.
    """
    get = scratch or _empty
    P, N = X.shape[:2]
    M = S.alpha.shape[1]
    Xn = np.subtract(X, S.x_mean, out=get("Xn", X.shape))  # standardised inputs
    Xn /= S.x_scale
    K = kernel.cross(Xn, S.kernel, out=get("K", (P, N, M)), tmp=get("XL", X.shape))
    k_alpha = np.matmul(K, S.alpha)[..., 0]  # [P, N] standardised mean (P1)
    mean = k_alpha * S.y_scale
    KC = np.matmul(K, S.C, out=get("KC", (P, N, M)))  # O(M^2) per point (P2)
    var = S.signal_variance - np.einsum("pnm,pnm->pn", KC, K)
    if not var.min(initial=0.0) >= 0.0:
        _clip_negative(var, S.signal_variance, stacklevel + 1)
    if include_noise:
        var += S.noise_variance
    var *= S.y_var
    mean += S.y_mean
    grad = None
    if with_grad:
        grad = kernel.cross_grad(K, Xn, S.alpha_z, k_alpha, S.grad_scale,
                                 out=get("g", X.shape))
    return mean, var, grad, K


def same_kernel_rows(a: Stacked, b: Stacked) -> bool:
    """Inputs give the same kernel matrix K under both stacks: equal input scaling,
    pseudo-inputs and kernel hyperparameters (an adapted posterior and its trained floor)."""
    return all(np.array_equal(x, y) for x, y in
               ((a.x_mean, b.x_mean), (a.x_scale, b.x_scale), *zip(a.kernel, b.kernel,
                                                                  strict=True)))


def _clip_negative(var: FloatArray, signal_variance: FloatArray, stacklevel: int) -> None:
    """Clip a negative latent variance [P, N] to 0 in place, warning beyond round-off."""
    worst = np.min(var / signal_variance)
    if worst < -1e-8:
        count = int(np.sum(var < 0.0))
        warnings.warn(
            f"SparseGP: {count} negative latent variance(s) (min {worst:.3g} sf2) from "
            "round-off clipped to 0; the model is ill-conditioned, consider a larger jitter",
            RuntimeWarning,
            stacklevel=stacklevel + 1,
        )
    np.maximum(var, 0.0, out=var)


# --------------------------------------------------------------------------- the floor

class OutsideFloor:
    """A posterior's predictive variance less what its pseudo-inputs explain.

    At x, with u = L^-1 k(Z, x) and q(x, x) = u^T u (A8 of :mod:`asgp_ros.core.adapt`)::

        (P3)  floor(x) = max(var(x) - q(x, x), 0) = max(sf2 - k^T (C + Kuu^-1) k [+ sn2], 0)

    in original units.  Among the pseudo-inputs q(x, x) is nearly the whole prior
    variance sf2 and the floor is at most the noise (usually nothing); far from them q
    vanishes and the floor is the posterior's variance there.  An adapted model publishes
    the trained posterior's floors as its
    :attr:`~asgp_ros.core.models.MotionModel.variance_floor` (at the trained calibration,
    :mod:`asgp_ros.core.adaptive`), so that its online scale narrows the ellipses where
    the pseudo-inputs reach and nowhere else: the published variance is below the trained
    model's by at most the calibrated q(x, x), which vanishes outside the training range.
    It is a channel (``predict``) whose mean is the posterior's (:func:`predict`); it has no
    gradient.  The
    rollout evaluates both channels' floors together (:func:`stack_floors`,
    :func:`floor_variance`).

    At an online scale s >= 1 the floor never binds: the adapted latent variance is
    sf2 - q + u^T A^-1 u >= sf2 - q, while var_T - q = sf2 - 2 q + u^T A_T^-1 u
    <= sf2 - q (A8), and the calibration's map is increasing in both.
    """

    def __init__(self, post: FitcPosterior) -> None:
        M = post.num_inducing
        Linv = scipy.linalg.solve_triangular(post.L, np.eye(M), lower=True)
        self.post = post
        self.Q: FloatArray = post.C + Linv.T @ Linv  # C + Kuu^-1

    def predict(self, X: ArrayLike, include_noise: bool = True
                ) -> tuple[FloatArray, FloatArray]:
        Xa = np.atleast_2d(np.asarray(X, dtype=np.float64))
        mean, _, _ = predict(self.post.stacked, Xa[None], include_noise, with_grad=False)
        return mean[0], floor_variance(self.post.stacked, self.Q[None], Xa[None],
                                       include_noise)[0]

    def predict_with_grad(self, X: ArrayLike, include_noise: bool = True
                          ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Not provided: a floor is read for its variance only (never propagated)."""
        raise NotImplementedError("a variance floor has no mean gradient; use predict")


def stack_floors(floors: Sequence[OutsideFloor]) -> tuple[Stacked, FloatArray]:
    """The floors' posteriors stacked (:func:`stack`) and their Q = C + Kuu^-1 [P, M, M],
    padded with zeros as C is."""
    S = stack([f.post for f in floors])
    M = S.C.shape[1]
    Q = np.zeros((len(floors), M, M))
    for c, f in enumerate(floors):
        m = f.post.num_inducing
        Q[c, :m, :m] = f.Q
    return S, Q


def floor_variance(S: Stacked, Q: FloatArray, X: FloatArray, include_noise: bool,
                   K: FloatArray | None = None) -> FloatArray:
    """The floor (P3) [P, N] at inputs X [P, N, D] (original units); Q [P, M, M] as
    :func:`stack_floors` gives it. ``K``: X's kernel matrix [P, N, M] under ``S`` when
    already computed (by :func:`predict_with_kernel` on a stack with
    :func:`same_kernel_rows`), instead of computing it again."""
    if K is None:
        Xn = (X - S.x_mean) / S.x_scale
        K = kernel.cross(Xn, S.kernel)  # [P, N, M]
    short = S.signal_variance - np.einsum("pnm,pnm->pn", np.matmul(K, Q), K)
    if include_noise:
        short = short + S.noise_variance
    out: FloatArray = np.maximum(short, 0.0) * S.y_var
    return out
