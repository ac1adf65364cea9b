"""An ASGP that adapts while it drives: online posterior updates and online calibration.

A trained :class:`~asgp_ros.core.models.MotionModel` of two SparseGP channels is wrapped by
:class:`ModelAdapter`, which the online :class:`~asgp_ros.core.online.Predictor` (and so
the predictor node, the shared-control layer and ``asgp evaluate --adapt``) feeds with the
resampled grid of its buffers.  The user's model object is never modified: the adapter
predicts with its own copy, whose channels read the adapted posteriors.

Two things move, nothing else (hyperparameters, pseudo-inputs, lags and the trained
calibration's shape stay as trained):

1. **The posterior** (:mod:`asgp_ros.core.adapt`).  Every completed grid step whose input
   window and target training would accept (the same resampler, the same
   :func:`~asgp_ros.core.features.design_matrix`, so the same validity, gap,
   tracking-loss and stale-VO rules) is absorbed by both channels, with exponential
   forgetting.  A step is absorbed only once it is ``settle_steps`` behind the newest
   complete step: the stale-VO rule judges a run of repeated readings by its length, so
   a step at the live edge may still turn out stale; after the settle time its flag is
   what the whole recording would give.  The settle time is also at least
   ``OVERRIDE_DELAY_S``: an override that arrives that late still keeps the steps it may
   have driven out (``Predictor.feed_override``).  Settled steps are absorbed in blocks of
   ``update_steps`` (a second at 5 Hz by default): a step's statistics cost O(M^2), a
   published posterior O(M^3).

2. **The variance scale** (online calibration).  Each prediction is checked once its
   outcome has arrived: k steps after a step P, the model *as it was at P* (the snapshot
   of both posteriors) is rolled out from P's measured window with the joystick that was
   actually applied, and its 95 % position ellipses are compared with the path integrated
   from the measured velocities, at every horizon 1..k.  The normalised innovations
   (squared Mahalanobis distances d2) drive one multiplicative scale per speed regime of
   the trained calibration (the regime is the measured speed at P, as in
   :mod:`asgp_ros.core.calibration`), by adaptive conformal inference (Gibbs & Candes,
   "Adaptive conformal inference under distribution shift", NeurIPS 2021) on the log
   scale::

       (C1)  log s_r <- log s_r + clip(gain * (miss - (1 - target)), -max_rate dt, max_rate dt)

   where miss is the fraction of the k horizons whose ellipse, at the scale in force at
   P, missed.  With linearised propagation every position covariance is linear in the
   calibrated velocity variances, so scaling all of them by s scales the ellipses'
   d2 by 1/s exactly: a miss is ``d2 > chi2_95 * s``.  Over a long run ACI's miss rate
   tends to 1 - target whatever the errors do; the step is bounded by ``max_rate`` (log
   units per second) so that one bad step cannot swing the ellipses, and the scale stays
   in [``min_scale``, ``max_scale``].  The trained posterior's scale never goes below 1.
   The adapted posterior's may (down to ``min_scale``, 0.1 by default): on a floor where
   it predicts better than the trained calibration assumed (a smoother floor than the
   trained one, say: the noise variance sn2 is a hyperparameter and stays as trained),
   its ellipses would otherwise over-cover.  Far outside the training range that must not
   narrow anything: the published adapted model's variance is floored, at every step of
   every rollout (:attr:`~asgp_ros.core.models.MotionModel.variance_floor`), by the
   trained model's variance less the part its pseudo-inputs explain
   (:class:`~asgp_ros.core.posterior.OutsideFloor`, at the trained calibration).  So the
   published variance is below the trained model's by at most the calibrated q(x, x) of
   A8 (:mod:`asgp_ros.core.adapt`), which vanishes outside the training range: there the
   variance never goes below the trained posterior's, whatever the scale.  The scale
   itself is learnt without the floor (the checks roll out the posterior at the trained
   calibration and scale the d2), so it says what the adapted posterior needs where it
   has learnt, and does not wind down while the floor holds the ellipses up.  One-step
   velocity innovations (z2 = e^2 / var per channel, chi2 with 1 dof) are tracked for the
   diagnostics.

3. **Which posterior is published** (``AdaptSettings.select``).  Forgetting trades the
   many trained rows for a few hundred recent ones: on a new floor that is the point, on
   the trained floor it only adds variance (measured: a point or more of k-step success
   lost in-domain).  Every checked prediction is therefore made twice, by the trained
   posterior and by the adapted one (each with its own online scale, C1), and the choice
   between them is a Diebold-Mariano test of equal predictive accuracy on the recent
   checks (:class:`PosteriorChoice`): the loss differential is the difference of their
   mean squared k-step position errors, averaged with exponential weights (half-life
   ``select_half_life_s``), its standard error taken with the long-run variance of
   overlapping k-step errors (at most k times the variance: consecutive checks share
   k - 1 outcomes) over the weights' effective number, and the published posterior
   changes only when the other is better at the 5 % level (``SELECT_LEVEL``, two-sided,
   Student t).  The trained posterior is published until the evidence says otherwise.
   The rule it replaced (follow the leader: switch when the other's recent error is 5 %
   smaller) switched on differences the noise of the errors explains: on the hybrid
   atrium, where the floor changes every few metres, the model trained on both floors
   then lost half a point of success to itself not adapting; with the test it loses
   nothing there, and gains on the other floors (README, "Adapting online").  The
   adapted posterior keeps learning while the trained one is published.

What it does not promise: the scale reacts to errors it has seen; the first seconds on a
new floor are covered only as well as the trained calibration covers them. The scale rises
fast and falls slowly: a miss raises log s by ``gain * target``, a hit lowers it by only
``gain * (1 - target)``, 19 times less. Widening to a factor s takes about
``log(s) / (gain * target)`` misses (and at least ``log(s) / max_rate`` seconds); narrowing
back from it about ``log(s) / (gain * (1 - target))`` hits: from the bound of 100, 1,840
checked predictions, about six minutes at 5 Hz (measured: five minutes of VO noise drove the
scale to 100, and it was back near 2 340 s after the noise ended; paths the widened
variance put beyond the physical range meanwhile were refused, ``model_out_of_range``).
"""

from __future__ import annotations

import copy
import math
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple, cast

import numpy as np
import scipy.special
from numpy.typing import NDArray

from asgp_ros.common.board import NEUTRAL_WINDOW
from asgp_ros.core.adapt import AdaptConfig, AdaptError, OnlinePosterior
from asgp_ros.core.calibration import FACTOR_RANGE
from asgp_ros.core.features import design_matrix
from asgp_ros.core.metrics import CHI2_1DOF_95, CHI2_2DOF_95, THRESHOLD_M, mahalanobis_sq
from asgp_ros.core.models import MotionModel
from asgp_ros.core.posterior import FitcPosterior, OutsideFloor
from asgp_ros.core.resample import Resampled
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.core.unicycle import integrate_path

FloatArray = NDArray[np.float64]

__all__ = ["AdaptSettings", "AdapterStats", "CoverageConfig", "ModelAdapter",
           "PosteriorChoice"]

#: Weight of the newest check in the coverage averages shown by the diagnostics
#: (about the last 100 checked predictions).
COVERAGE_EWMA = 0.01
#: Default forgetting of the online posterior: the rows it absorbs with a half-life of
#: 300 s of driving, the trained data with one of 10 s and down to nothing (the trained
#: posterior itself stays available, item 3, and its mean stays the prior mean, A9 of
#: :mod:`asgp_ros.core.adapt`). The trained data's weight goes fast, because with it the
#: posterior holds the correction near zero; the new rows stay, because a floor's
#: function takes hundreds of rows to learn. The trained half-life was chosen on the other
#: floor's training bags of the reproduction's dataset (the carpet model on tile_01-02,
#: the tile model on carpet_01-02, from 60 s in, success at 2.0 s): 1 / 3 / 10 / 30 /
#: 120 s gave 95.6 / 95.6 / 95.2 / 92.5 / 79.2 % and 89.2 / 89.3 / 89.2 / 85.6 / 73.5 %;
#: 10 s is the longest on the plateau. The models on their own floor's bags were the same
#: with 3, 10 and 30 s (within 0.1 points, and of not adapting). The rows' own half-life:
#: 300 / 900 / 1800 s gave 95.2 / 95.1 / 95.0 % and 89.2 / 89.4 / 89.5 %; 300 s follows the
#: next change of floor sooner. ``benchmarks/adapt_half_life.py`` prints these figures.
DEFAULT_HALF_LIFE_S = 300.0
#: How late an override may reach the predictor (``Predictor.feed_override``) and still keep
#: the steps it drove from being learnt: a step is absorbed at least this long after it
#: (``settle_steps``).  Overrides come from a node on the same machine in milliseconds; a
#: later one is counted (``PredictorStats.overrides_late``).
OVERRIDE_DELAY_S = 0.5
DEFAULT_TRAINED_HALF_LIFE_S = 10.0
DEFAULT_TRAINED_FLOOR = 0.0
#: The published posterior changes when a test of equal recent k-step error rejects at
#: this level (two-sided), in favour of the other (:class:`PosteriorChoice`).
SELECT_LEVEL = 0.05
#: The experts (index into the scales and errors).
TRAINED, ADAPTED = 0, 1
EXPERTS = ("trained", "adapted")


@dataclass(frozen=True)
class CoverageConfig:
    """Online calibration settings (C1; validated on construction).

    Attributes:
        gain: ACI step on the log scale per checked prediction.
        max_rate: bound on |d log s| per second of stream time.
        min_scale, max_scale: range of each regime's scale (the trained posterior's
            scale stays at 1 or above whatever ``min_scale`` says; the adapted one's
            published variance is floored by the trained model's, module docstring).
        target: the coverage the 95 % ellipses are held to.
    """

    gain: float = 0.05
    max_rate: float = 0.25
    min_scale: float = 0.1
    max_scale: float = 100.0
    target: float = 0.95

    def __post_init__(self) -> None:
        for name, lo, hi in (("gain", 0.0, 10.0), ("max_rate", 0.0, 100.0),
                             ("min_scale", 1e-3, 1e3), ("max_scale", 1e-3, 1e6),
                             ("target", 0.5, 0.999)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or not (math.isfinite(value) and lo < value <= hi):
                raise AdaptError(f"{name} must be a number in ({lo:g}, {hi:g}], got {value!r}")
        if self.min_scale > self.max_scale:
            raise AdaptError(f"min_scale {self.min_scale} exceeds max_scale {self.max_scale}")


class PosteriorChoice:
    """Which of two predictors to publish, by a test of equal predictive accuracy.

    A Diebold-Mariano test on exponentially weighted checks: each :meth:`update` takes the
    loss differential ``d`` of one checked prediction (the other expert's loss minus the
    published one's, here mean squared k-step position errors). With weights that halve
    every ``half_life`` checks, the mean of d, its variance, and the weights' effective
    number n (Kish: (sum w)^2 / sum w^2) give the statistic

        t = mean(d) / sqrt(var(d) * lag / n),

    where ``lag`` (the horizon k) bounds the long-run variance of overlapping k-step
    losses (consecutive checks share k - 1 outcomes; with the triangular correlation of
    such overlaps the long-run variance is k times the variance). The published expert
    changes when t rejects equal accuracy at ``level`` (two-sided, Student t with
    n / lag - 1 degrees of freedom) in favour of the other; with fewer than two
    independent outcomes' worth of checks, or no spread in d, nothing changes.

    Args:
        half_life: checks after which a check's weight has halved (> 0).
        lag: horizon of the checked predictions, in checks (>= 1).
        level: test level in (0, 1).
        published: the expert published at first (0 or 1).
    """

    def __init__(self, half_life: float, lag: int, level: float = SELECT_LEVEL,
                 published: int = 0) -> None:
        if not (math.isfinite(half_life) and half_life > 0.0):
            raise AdaptError(f"half_life must be > 0 checks, got {half_life}")
        if not (isinstance(lag, int) and lag >= 1):
            raise AdaptError(f"lag must be an integer >= 1, got {lag!r}")
        if not (math.isfinite(level) and 0.0 < level < 1.0):
            raise AdaptError(f"level must be in (0, 1), got {level}")
        if published not in (0, 1):
            raise AdaptError(f"published must be 0 or 1, got {published!r}")
        self.decay = 2.0 ** (-1.0 / half_life)
        self.lag = lag
        self.level = level
        self.published = published
        self.switches = 0
        self._w = self._w2 = self._s1 = self._s2 = 0.0  # sums over checks: w, w^2, w d, w d^2

    def statistic(self) -> tuple[float, float]:
        """(t, its critical value) of the losses so far, oriented as "the other expert's
        loss minus the published one's"; (nan, nan) while there is no test to make."""
        if self._w <= 0.0:
            return math.nan, math.nan
        n = self._w * self._w / self._w2
        dof = n / self.lag - 1.0
        mean = self._s1 / self._w
        var = (self._s2 / self._w - mean * mean) * n / max(n - 1.0, 1e-12)
        if dof < 1.0 or not var > 0.0:
            return math.nan, math.nan
        t = mean / math.sqrt(var * self.lag / n)
        return t, float(scipy.special.stdtrit(dof, 1.0 - self.level / 2.0))

    def update(self, d: float) -> int:
        """Add one check's loss differential (the other's loss minus the published one's;
        a ``d`` that is not finite or whose square is not is ignored) and return the expert
        to publish."""
        if not math.isfinite(d * d):  # NaN, inf, or too large to square: no evidence
            return self.published
        k = self.decay
        self._w, self._w2 = k * self._w + 1.0, k * k * self._w2 + 1.0
        self._s1, self._s2 = k * self._s1 + d, k * self._s2 + d * d
        t, crit = self.statistic()
        if t < -crit:  # the other expert's loss is smaller: publish it
            self.published = 1 - self.published
            self.switches += 1
            # the differential is now the other way round
            self._s1 = -self._s1
        return self.published


@dataclass(frozen=True)
class AdaptSettings:
    """Everything the online adaptation needs.

    Attributes:
        posterior: forgetting and safety of the posterior updates (:class:`AdaptConfig`).
        coverage: online calibration, or None to keep the trained calibration (and to
            publish the adapted posterior always: the choice needs the checks).
        select: publish the trained posterior until a test on the recent checks says the
            adapted one predicts better, and back (item 3 of the module docstring,
            :class:`PosteriorChoice`); False always publishes the adapted one.
        select_half_life_s: half-life of the weights of the checks that test compares.
        update_steps: absorb settled steps in blocks of this many (one posterior published
            per block, i.e. once a second at 5 Hz by default: an update costs O(M^3), a
            step's statistics O(M^2)); 1 absorbs every step as it settles.
    """

    posterior: AdaptConfig = field(
        default_factory=lambda: AdaptConfig(half_life_s=DEFAULT_HALF_LIFE_S,
                                            trained_floor=DEFAULT_TRAINED_FLOOR,
                                            trained_half_life=DEFAULT_TRAINED_HALF_LIFE_S))
    coverage: CoverageConfig | None = field(default_factory=CoverageConfig)
    select: bool = True
    select_half_life_s: float = 20.0
    update_steps: int = 5

    def __post_init__(self) -> None:
        if isinstance(self.update_steps, bool) or not isinstance(self.update_steps, int) \
                or not 1 <= self.update_steps <= 100:
            raise AdaptError(f"update_steps must be an integer in [1, 100], got "
                             f"{self.update_steps!r}")
        if not (math.isfinite(self.select_half_life_s) and self.select_half_life_s > 0.0):
            raise AdaptError(f"select_half_life_s must be > 0, got {self.select_half_life_s}")
        if not isinstance(self.posterior, AdaptConfig):
            raise AdaptError("posterior must be an AdaptConfig")
        if self.coverage is not None and not isinstance(self.coverage, CoverageConfig):
            raise AdaptError("coverage must be a CoverageConfig or None")


@dataclass(frozen=True)
class AdapterStats:
    """What the diagnostics show (a snapshot).

    Attributes:
        rows_absorbed: grid steps absorbed (each by both channels).
        steps_refused: completed grid steps that training would not accept (invalid
            window or target: gap, tracking loss, stale VO, another segment), those that
            left the buffer unjudged (no query while the VO was lost) too.
        rows_rejected: rows a channel refused (non-finite, outside the training range,
            a failed update), summed over the channels, by reason.
        effective_size: per channel, trained rows times their weight plus the adapted
            rows' effective number.
        scales: the published posterior's online variance scale per speed regime (1 = the
            trained calibration).
        published: which posterior predictions use now, "trained" or "adapted".
        recent_error: recent mean squared k-step position error (m^2) of the trained and
            of the adapted posterior (NaN before the first check).
        checked: predictions whose outcome has been checked.
        choice_t: the choice's test statistic (:class:`PosteriorChoice`: the other
            posterior's recent k-step loss minus the published one's, over its standard
            error; below ``-choice_critical`` the other is published), NaN while there is
            no test to make.
        choice_critical: the statistic's critical value at ``SELECT_LEVEL``, or NaN.
        switches: changes of the published posterior since the start or the last reset.
        coverage: recent share of checked k-step ellipses that covered (EWMA), or NaN;
            for the adapted posterior without the trained floor, so a lower bound of the
            published ellipses' coverage.
        coverage_one_step: recent share of one-step velocity innovations inside their
            95 % interval (both channels), or NaN.
        last_update_s: wall-clock cost of the last absorption (both channels).
        last_check_s: wall-clock cost of the last coverage check.
    """

    rows_absorbed: int
    steps_refused: int
    rows_rejected: dict[str, int]
    effective_size: tuple[float, float]
    scales: tuple[float, ...]
    published: str
    recent_error: tuple[float, float]
    checked: int
    choice_t: float
    choice_critical: float
    switches: int
    coverage: float
    coverage_one_step: float
    last_update_s: float
    last_check_s: float


class _Snapshot(NamedTuple):
    """The model as a prediction at grid step ``step`` used it."""

    step: int
    posteriors: tuple[FitcPosterior, FitcPosterior]
    log_scales: FloatArray  # [2 experts, regimes]
    published: int


class ModelAdapter:
    """Online posterior and calibration of one ASGP model (see the module docstring).

    Args:
        model: a trained model whose two channels are SparseGP (kind ``asgp``); it is not
            modified.
        settings: forgetting, safety and online calibration.
        horizon_steps: k of the checked predictions (the predictor's horizon).
        settle_steps: how far behind the newest complete step a step is absorbed and a
            prediction checked; default from the model's stale-VO rule and
            ``OVERRIDE_DELAY_S`` (:meth:`default_settle_steps`).

    Raises:
        AdaptError: a model that cannot adapt (not two SparseGP channels, no LA factor).
    """

    def __init__(self, model: MotionModel, settings: AdaptSettings | None = None,
                 horizon_steps: int = 10, settle_steps: int | None = None) -> None:
        if not all(type(ch) is SparseGP for ch in model.channels):
            raise AdaptError(f"only an ASGP adapts online; this model is of kind "
                             f"{model.kind!r}")
        self.settings = settings if settings is not None else AdaptSettings()
        self.base = model
        self.horizon_steps = int(horizon_steps)
        if not 1 <= self.horizon_steps <= 200:
            raise AdaptError(f"horizon_steps must be in [1, 200], got {horizon_steps}")
        self.settle_steps = (self.default_settle_steps(model) if settle_steps is None
                             else int(settle_steps))
        if self.settle_steps < 0:
            raise AdaptError(f"settle_steps must be >= 0, got {settle_steps}")
        channels = tuple(copy.copy(cast(SparseGP, ch)) for ch in model.channels)
        self._channels: tuple[SparseGP, SparseGP] = (channels[0], channels[1])
        self._online = tuple(OnlinePosterior.from_sparse_gp(ch, self.settings.posterior)
                             for ch in self._channels)
        regimes = len(model.calibration.speed_edges) + 1
        self._log_scales = np.zeros((2, regimes))
        self._published = ADAPTED if self.settings.coverage is None or not self.settings.select \
            else TRAINED
        self._errors = np.full(2, np.nan)
        self._choice = self._new_choice()
        base = cast(tuple[SparseGP, SparseGP], model.channels)
        self._floor = replace(model, channels=(OutsideFloor(base[0].posterior),
                                               OutsideFloor(base[1].posterior)))
        self.model = self._publish()
        self._check_channels: tuple[SparseGP, SparseGP] = (
            copy.copy(self._channels[0]), copy.copy(self._channels[1]))
        self._check_model = replace(model, channels=self._check_channels)
        self._restart_state()
        self._steps_refused = 0
        self._checked = 0
        self._coverage = math.nan
        self._coverage_one = math.nan
        self._last_check_s = 0.0

    def set_horizon(self, horizon_steps: int) -> None:
        """Check predictions of ``horizon_steps`` from now on (the predictor's horizon
        changed at runtime): what was learnt is kept, and the pending checks are made at
        the new horizon (a check rolls its snapshot's posterior out again, at any k)."""
        k = int(horizon_steps)
        if not 1 <= k <= 200:
            raise AdaptError(f"horizon_steps must be in [1, 200], got {horizon_steps}")
        self.horizon_steps = k
        self._choice.lag = k

    @staticmethod
    def default_settle_steps(model: MotionModel) -> int:
        """Steps after which a grid step's stale-VO flag no longer changes (plus one), and
        at least ``OVERRIDE_DELAY_S`` (plus one): an override that arrives that late still
        keeps the steps it drove from being learnt."""
        rc = model.resample_config
        windows = [w for w in (rc.stale_after_s, rc.stale_still_after_s, rc.held_after_s)
                   if math.isfinite(w)]
        stale = min(math.ceil(max(windows) * rc.rate_hz - 1e-9) + 1, 50) if windows else 1
        return max(stale, math.ceil(OVERRIDE_DELAY_S * rc.rate_hz - 1e-9) + 1)

    @property
    def absorbed_to(self) -> int | None:
        """The newest grid index absorbed or judged (None before the first)."""
        return self._absorbed_to

    def history_steps(self, horizon_steps: int | None = None) -> int:
        """Grid steps of history the adapter needs in each resampled window (at its
        horizon, or at ``horizon_steps``)."""
        k = self.horizon_steps if horizon_steps is None else int(horizon_steps)
        return self.base.lags + k + self.settle_steps + self.settings.update_steps + 1

    @staticmethod
    def history_steps_for(model: MotionModel, settings: AdaptSettings,
                          horizon_steps: int) -> int:
        """:meth:`history_steps` of an adapter of ``model`` with the default settle time,
        before one is made (to size a buffer)."""
        return (int(model.feature_config.lags) + int(horizon_steps)
                + ModelAdapter.default_settle_steps(model) + settings.update_steps + 1)

    # ------------------------------------------------------------------ state

    def _publish(self) -> MotionModel:
        """The model predictions use: the published posterior at its online scales."""
        e = self._published
        cal = self.base.calibration
        lo, hi = FACTOR_RANGE  # (the update keeps them there; rounding aside)
        factors = tuple(min(max(float(f * math.exp(ls)), lo), hi)
                        for f, ls in zip(cal.speed_factors, self._log_scales[e], strict=True))
        if e == TRAINED:
            return replace(self.base, calibration=replace(cal, speed_factors=factors))
        # at a scale >= 1 the floor cannot bind (OutsideFloor): it costs a second
        # evaluation per step, so it is attached only while a regime's scale is below 1
        narrowed = bool(np.any(self._log_scales[ADAPTED] < 0.0))
        return replace(self.base, channels=self._channels,
                       calibration=replace(cal, speed_factors=factors),
                       variance_floor=self._floor if narrowed else None)

    def _new_choice(self) -> PosteriorChoice:
        half_life = self.settings.select_half_life_s / self.base.dt
        return PosteriorChoice(half_life, self.horizon_steps, SELECT_LEVEL, self._published)

    def _restart_state(self) -> None:
        self._absorbed_to: int | None = None  # newest grid index absorbed or judged
        self._checked_to: int | None = None
        self._snapshots: deque[_Snapshot] = deque()

    def restart_stream(self) -> None:
        """The stream restarted (the predictor's buffers were reset after a clock jump):
        keep what was learnt, forget the grid positions and the pending checks."""
        self._restart_state()
        for online in self._online:
            online.restart_clock()

    def reset(self) -> None:
        """Back to the trained posterior and calibration (the counters are kept).

        Steps already absorbed are not absorbed again; predictions made before the reset
        are not checked.
        """
        for online in self._online:
            online.reset()
        self._log_scales = np.zeros_like(self._log_scales)
        self._errors = np.full(2, np.nan)
        self._coverage = self._coverage_one = math.nan  # (of the posterior before)
        if self.settings.coverage is not None and self.settings.select:
            self._published = TRAINED
        self._choice = self._new_choice()
        self.model = self._publish()
        self._snapshots.clear()

    @property
    def stats(self) -> AdapterStats:
        rejected: dict[str, int] = {}
        for online in self._online:
            for key, n in online.stats.rejected.items():
                rejected[key] = rejected.get(key, 0) + n
        s_v, s_w = (online.stats for online in self._online)
        choice = self._choice.statistic()
        return AdapterStats(
            rows_absorbed=min(s_v.rows_absorbed, s_w.rows_absorbed),
            steps_refused=self._steps_refused, rows_rejected=rejected,
            effective_size=(s_v.effective_size, s_w.effective_size),
            scales=tuple(float(math.exp(x)) for x in self._log_scales[self._published]),
            published=EXPERTS[self._published],
            recent_error=(float(self._errors[0]), float(self._errors[1])),
            checked=self._checked, choice_t=choice[0], choice_critical=choice[1],
            switches=self._choice.switches, coverage=self._coverage,
            coverage_one_step=self._coverage_one,
            last_update_s=s_v.last_update_s + s_w.last_update_s,
            last_check_s=self._last_check_s)

    # ------------------------------------------------------------------ updates

    def observe(self, res: Resampled, complete: int) -> None:
        """Learn from the first ``complete`` grid points of a resampled window.

        Call it right after predicting at the newest of those points (the step a
        prediction was just made at): ``res`` is the predictor's buffer on the grid and
        ``complete`` the number of its points covered by both streams.  The model the
        prediction used is recorded for its check; then the steps that have settled
        (``settle_steps`` behind the newest) are absorbed, once at least ``update_steps``
        of them are waiting, and the predictions whose outcomes have settled are checked.
        """
        if complete <= 0:
            return
        ks = np.asarray(res.k[:complete], dtype=np.int64)
        newest = int(ks[-1])
        settled = newest - self.settle_steps
        if self.settings.coverage is not None and (
                not self._snapshots or self._snapshots[-1].step < newest):
            self._snapshots.append(_Snapshot(
                newest, (self._channels[0].posterior, self._channels[1].posterior),
                self._log_scales.copy(), self._published))
        self._absorb(res, ks, settled)
        if self.settings.coverage is not None:
            self._check(res, ks, settled)
            oldest = settled - self.horizon_steps - self.settings.update_steps
            while self._snapshots and self._snapshots[0].step < oldest:
                self._snapshots.popleft()

    def _absorb(self, res: Resampled, ks: NDArray[np.int64], settled: int) -> None:
        start = ks[0] - 1 if self._absorbed_to is None else self._absorbed_to
        if settled - start < self.settings.update_steps:
            return
        lo = int(np.searchsorted(ks, start, side="right"))
        hi = int(np.searchsorted(ks, settled, side="right"))
        fc = self.base.feature_config
        rows = [design_matrix(res, c, fc) for c in (0, 1)]
        index = rows[0][2]
        take = (index >= lo) & (index < hi)
        # every step after the last one judged is refused unless absorbed: those that left
        # the buffer unjudged too (no query came while the VO was lost: its steps counted as
        # long as they stayed in the buffer, and a 60 s outage counted none); at the very
        # start the first `lags` steps, which no row can have as its target, are not steps
        first = int(ks[0]) + self.base.lags if self._absorbed_to is None else start + 1
        self._steps_refused += max(0, settled - first + 1 - int(np.count_nonzero(take)))
        self._absorbed_to = settled
        if not np.any(take):
            return
        t = np.asarray(res.t)[index[take]]
        for online, (X, y, _) in zip(self._online, rows, strict=True):
            online.absorb_rows(X[take], y[take], t)
        self.model = self._publish()

    def _check(self, res: Resampled, ks: NDArray[np.int64], settled: int) -> None:
        """Check the predictions made at steps P with P + k <= settled (C1), in order, once
        ``update_steps`` of them are waiting.

        The rollouts of the cases that share a snapshot of the posteriors are batched (the
        posterior changes once per absorbed block); the scales and the choice are then
        updated case by case, each with the scale that was in force at its P.
        """
        cfg = self.settings.coverage
        assert cfg is not None
        k, s = self.horizon_steps, self.base.lags
        seg = np.asarray(res.segment)
        ready = 0
        for snap in self._snapshots:  # in the order of their steps
            if snap.step + k > settled:
                break
            ready += 1
        if ready == 0 or (ready < self.settings.update_steps and settled - (
                self._snapshots[0].step + k) < self.settings.update_steps):
            # checked in blocks (batched rollouts): of update_steps predictions, or of those
            # waiting since update_steps steps (a caller that predicts every n-th step only
            # never has update_steps of them ready at once, and they were dropped unchecked)
            return
        cases: list[tuple[int, _Snapshot]] = []
        while self._snapshots and self._snapshots[0].step + k <= settled:
            snap = self._snapshots.popleft()
            if self._checked_to is not None and snap.step <= self._checked_to:
                continue
            self._checked_to = snap.step
            i = int(np.searchsorted(ks, snap.step))
            if i >= ks.shape[0] or ks[i] != snap.step or i - s + 1 < 0 \
                    or i + k >= ks.shape[0]:
                continue
            window = seg[i - s + 1:i + k + 1]
            if window[0] < 0 or not np.all(window == window[0]):
                continue  # the outcome is not a valid training case: nothing to learn
            cases.append((i, snap))
        if not cases:
            return
        start = time.perf_counter()
        outcomes = self._rollouts(res, cases)
        if outcomes is not None:
            for (i, snap), out in zip(cases, outcomes, strict=True):
                if _still(out):
                    continue
                self._check_case(np.asarray(res.vel)[i, 0], snap, out, cfg)
            self.model = self._publish()
        self._last_check_s = time.perf_counter() - start

    def _rollouts(self, res: Resampled, cases: list[tuple[int, _Snapshot]]
                  ) -> list[tuple[Any, ...]] | None:
        """Per case: (error [2 experts, k, 2], d2 [2, k], one-step error [2, 2] and its
        variances [2, 2], predicted positions [2, k, 2], the stick within the board's
        neutral window over the past and future windows), from batched rollouts; None if a rollout
        failed."""
        k, s = self.horizon_steps, self.base.lags
        joy, vel = np.asarray(res.joy), np.asarray(res.vel)
        idx = np.array([i for i, _ in cases])
        offs = np.arange(-s + 1, 1)
        jp, vp = joy[idx[:, None] + offs], vel[idx[:, None] + offs]  # [n, s, 2]
        jf = joy[idx[:, None] + np.arange(1, k + 1)]  # [n, k, 2]
        ref = np.asarray(integrate_path(vel[idx[:, None] + np.arange(0, k + 1)],
                                        self.base.dt))[:, 1:]  # [n, k, 3]
        try:
            trained = rollout(self.base, jp, vp, jf, uncertainty="linear")
            adapted: dict[int, Any] = {}
            groups: dict[tuple[int, int], list[int]] = {}
            for n, (_, snap) in enumerate(cases):
                key = (id(snap.posteriors[0]), id(snap.posteriors[1]))
                groups.setdefault(key, []).append(n)
            for members in groups.values():
                posteriors = cases[members[0]][1].posteriors
                for ch, post in zip(self._check_channels, posteriors, strict=True):
                    ch.posterior = post
                sel = np.asarray(members)
                out = rollout(self._check_model, jp[sel], vp[sel], jf[sel], uncertainty="linear")
                for j, n in enumerate(members):
                    adapted[n] = (out.pose[j], out.pos_cov[j], out.vel[j], out.vel_cov[j])
        except ValueError:
            return None
        per_case = []
        for n, i in enumerate(idx):
            rows = [(trained.pose[n], trained.pos_cov[n], trained.vel[n], trained.vel_cov[n]),
                    adapted[n]]
            err = np.stack([ref[n, :, :2] - r[0][:, :2] for r in rows])  # [2, k, 2]
            d2 = np.stack([mahalanobis_sq(err[e], np.asarray(rows[e][1])) for e in range(2)])
            e1 = np.stack([vel[i + 1] - r[2][0] for r in rows])  # [2, 2]
            var1 = np.stack([np.diagonal(r[3][0]) for r in rows])  # [2, 2]
            pred = np.stack([r[0][:, :2] for r in rows])  # [2, k, 2]
            quiet = bool(np.all(np.abs(jp[n]) <= NEUTRAL_WINDOW)
                         and np.all(np.abs(jf[n]) <= NEUTRAL_WINDOW))
            per_case.append((err, d2, e1, var1, pred, quiet))
        return per_case

    def _check_case(self, speed: float, snap: _Snapshot, out: tuple[Any, ...],
                    cfg: CoverageConfig) -> None:
        """One checked prediction: C1 for both experts, their recent errors, the choice."""
        err, d2, e1, var1 = out[:4]
        regime = int(self.base.calibration.regime(speed))
        bound = cfg.max_rate * self.base.dt
        alpha = 1.0 - 2.0 ** (-self.base.dt / self.settings.select_half_life_s)
        inside = inside1 = math.nan
        loss = [math.nan, math.nan]  # mean squared k-step position error per posterior
        for e in (TRAINED, ADAPTED):
            scale = math.exp(float(snap.log_scales[e, regime]))
            miss = float(np.mean(d2[e] > CHI2_2DOF_95 * scale))
            step = cfg.gain * (miss - (1.0 - cfg.target))
            ls = self._log_scales[e]
            lowest = math.log(cfg.min_scale if e == ADAPTED else max(cfg.min_scale, 1.0))
            highest = math.log(cfg.max_scale)
            # the scaled factor stays a calibration's factor (FACTOR_RANGE): a model whose
            # factor is near a limit made every publication raise, and the scale ran on
            factor = self.base.calibration.speed_factors[regime]
            lowest = max(lowest, math.log(FACTOR_RANGE[0] / factor))
            highest = max(min(highest, math.log(FACTOR_RANGE[1] / factor)), lowest)
            ls[regime] = min(max(ls[regime] + min(max(step, -bound), bound), lowest),
                             highest)
            loss[e] = sq = float(np.mean(np.sum(err[e] * err[e], axis=1)))
            self._errors[e] = sq if math.isnan(self._errors[e]) else \
                (1.0 - alpha) * self._errors[e] + alpha * sq
            if e == snap.published:
                inside = 1.0 - miss
                with np.errstate(divide="ignore", invalid="ignore"):
                    inside1 = float(np.mean(e1[e] * e1[e] <= CHI2_1DOF_95 * var1[e] * scale))
        if self.settings.select:
            self._published = self._choice.update(loss[1 - self._published]
                                                  - loss[self._published])
        a = COVERAGE_EWMA
        for name, value in (("_coverage", inside), ("_coverage_one", inside1)):
            old = getattr(self, name)
            setattr(self, name, value if math.isnan(old) else (1 - a) * old + a * value)
        self._checked += 1


def _still(out: tuple[Any, ...]) -> bool:
    """Whether a checked prediction is of a parked chair: the stick within the board's
    neutral window over the whole case (``NEUTRAL_WINDOW``: nothing commanded, though an
    undeadzoned joystick reads a few thousandths), and the measured path and both
    posteriors' predicted paths within the success distance (``THRESHOLD_M``) of where they
    started.
    Such a case says nothing of how wrong a driven chair's prediction gets: a stop of a few
    minutes with the nodes running checked thousands of them, every ellipse held, the slow
    regime's scale fell to its minimum (the choice test switched on error differences of
    1e-10 m^2), and when the user drove off the 95 % ellipses held 65-85 % of the positions
    for two minutes. A chair driven slowly (the stick beyond the window) is checked however
    little it moves, and one moved 10 cm or more with the stick within it (pushed, on a
    slope) too. The training calibration leaves out the same cases."""
    err, pred, quiet = out[0], out[4], out[5]
    if not quiet:
        return False
    measured = pred[0] + err[0]  # the reference path, from either posterior's error
    return bool(np.max(np.hypot(measured[:, 0], measured[:, 1])) < THRESHOLD_M
                and np.max(np.hypot(pred[..., 0], pred[..., 1])) < THRESHOLD_M)


def describe(stats: AdapterStats) -> dict[str, Any]:
    """JSON-able view of :class:`AdapterStats` (for diagnostics and reports)."""
    return {
        "rows_absorbed": stats.rows_absorbed, "steps_refused": stats.steps_refused,
        "rows_rejected": dict(stats.rows_rejected),
        "effective_size": list(stats.effective_size), "scales": list(stats.scales),
        "published": stats.published, "recent_error": list(stats.recent_error),
        "checked": stats.checked, "choice_t": stats.choice_t,
        "choice_critical": stats.choice_critical, "switches": stats.switches,
        "coverage": stats.coverage,
        "coverage_one_step": stats.coverage_one_step,
        "last_update_s": stats.last_update_s, "last_check_s": stats.last_check_s,
    }
