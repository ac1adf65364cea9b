"""Shared control: the smallest change to the user's command that avoids a likely collision.

ROS-free; :mod:`asgp_ros.nodes.shared_control_node` wraps it. Once per model grid step the
layer asks the :class:`~asgp_ros.core.online.Predictor` where the chair goes if the user
holds the current stick for the horizon, and how likely that path is to touch an obstacle
(a :data:`CollisionCheck`, built from a laser scan or an occupancy grid by
:mod:`asgp_ros.core.collision`; with ``heading_uncertainty`` it samples the predicted
heading with the position, from the rollout's pose covariance). At or below
``threshold`` nothing happens: the user's command passes untouched. Above it, the layer
searches for the least intrusive replacement:

* candidates are the user's command with its forward deflection scaled down
  (``speed_scales``) and its turn deflection shifted (``turn_offsets``), and the whole
  command scaled down (both deflections by ``speed_scales``: slowing a turn on the spot,
  down to stopping), each held over the horizon (the decision is remade every step, a
  receding horizon); all are predicted in one batched rollout
  (``Predictor.predict_batch``) and checked in one batched call;
* the change of a candidate is the Euclidean distance between its command and the user's
  (deflection units); the cost is ``change^2 + progress_weight * lost^2``, where ``lost`` is
  the forward distance at the horizon the candidate gives up against the user's path, so
  that among equally small changes the one that keeps the chair moving wins;
* the chosen command is the cheapest candidate whose probability is at or below the
  threshold; when none is, the candidate with the lowest probability is used, the one
  with the least motion among equals (stopping is always a candidate), and the decision
  says ``no_safe_command``;
* if even that is no less likely than the user's command (the chair already touches, or
  stands within the margin, and every candidate is certain to touch, say), how much deeper
  than now the mean paths take the obstacles into the footprint decides (when the check
  gives that, as the scan and map checks of :mod:`asgp_ros.core.collision` do:
  :class:`~asgp_ros.core.collision.PathCheck`): a user's command that takes any obstacle
  point more than ``depth_tolerance`` deeper than the least-deepening candidate does (on
  into the wall, or swinging a corner into it or into other furniture) is replaced by the
  cheapest candidate within ``depth_tolerance`` of the least (``no_safe_command``);
  otherwise the user's command passes (backing away, say): overriding would only pin the
  chair there. Each step judges from where the chair is then: by its mean prediction, no
  command passed or sent deepens a contact by more than ``depth_tolerance`` beyond what the
  least-deepening candidate (stopping, say) would over the horizon.

Safety rules, whatever the numbers say:

* never on stale inputs: no prediction (stale joystick or VO, tracking lost, too little
  history) or no fresh obstacle source means no intervention, with the reason;
* never motion from a neutral stick: with the user's stick in the board's neutral window
  (where the board drives nothing, and ignores overrides: its dead-man rule) the layer
  commands nothing; within ``neutral_deadband`` beyond it (a stick barely touched, which
  the board still drives: 5 % at 0.05) the layer's one candidate is stopping;
* never faster than the user: a candidate's forward deflection has the user's sign and at
  most the user's magnitude, and its turn deflection stays within [-1, 1].
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from asgp_ros.common.board import BOARD_NEUTRAL, OVERRIDE_TIMEOUT_S, WATCHDOG_MS
from asgp_ros.core.collision import PathCheck
from asgp_ros.core.online import Prediction, Predictor, no_input_detail
from asgp_ros.core.streams import joy_problem

FloatArray = NDArray[np.float64]

CollisionCheck = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray]]
"""``check(pose [B, k, 3], cov [B, k, 2, 2] or [B, k, 3, 3]) -> (per_step [B, k],
within [B])``: probability of contact at each step and within the horizon, for paths in
the base frame at the prediction time t0 (x forward); a 3x3 covariance is that of
(x, y, theta) (:data:`asgp_ros.core.collision.CollisionCheck`)."""


class Why(StrEnum):
    """What the layer did at a step and why (published in status and diagnostics)."""

    CLEAR = "clear"
    """The user's path is below the threshold: the command passes untouched."""
    INTERVENING = "intervening"
    """A changed command brings the probability to or below the threshold."""
    NO_SAFE_COMMAND = "no_safe_command"
    """No candidate is below the threshold: the least likely to collide is sent."""
    NEUTRAL = "neutral_stick"
    """The user's stick is neutral: nothing is ever commanded."""
    STALE_INPUT = "stale_input"
    """No prediction (joystick or VO stale, tracking lost, not enough history)."""
    NO_OBSTACLES = "no_obstacle_source"
    """No fresh scan or map: the layer cannot judge and does not intervene."""
    CHECK_FAILED = "check_failed"
    """The prediction or the collision check raised: no intervention."""


@dataclass(frozen=True)
class SharedControlConfig:
    """Settings of the shared-control layer (validated on construction).

    Attributes:
        threshold: probability of contact within the horizon above which the layer acts.
        neutral_deadband: a stick whose deflections are both within this (barely touched,
            yet driven by the board unless in its neutral window, :data:`BOARD_NEUTRAL`) is
            guarded by stopping alone: never steered.
        speed_scales: factors applied to the user's forward deflection (must include 0,
            so that stopping is always a candidate, and 1).
        turn_offsets: shifts added to the user's turn deflection (must include 0).
        progress_weight: weight of the forward progress given up, per metre squared,
            against the command change squared.
        heading_uncertainty: give the check the prediction's full pose covariance, so that
            the heading is sampled with the position (a turning chair's corners sweep);
            False: the position covariance and the mean heading.
        depth_tolerance: when no candidate is less likely to touch than the user's command
            (every one certain, say), the user's command passes if its mean path takes the
            obstacles no more than this (m) deeper into the footprint than the chair has
            them now, or than the least-deepening candidate does
            (:func:`~asgp_ros.core.collision.footprint_deepening`); else the cheapest
            candidate within this of the least is sent. Prediction noise, and the most a
            held command may deepen a contact by over the horizon.
    """

    threshold: float = 0.05
    neutral_deadband: float = 0.05
    speed_scales: tuple[float, ...] = (1.0, 0.85, 0.7, 0.55, 0.4, 0.25, 0.1, 0.0)
    turn_offsets: tuple[float, ...] = (0.0, -0.15, 0.15, -0.3, 0.3, -0.5, 0.5, -0.8, 0.8)
    progress_weight: float = 0.5
    heading_uncertainty: bool = True
    depth_tolerance: float = 0.002

    def __post_init__(self) -> None:
        if not (math.isfinite(self.threshold) and 0.0 < self.threshold < 1.0):
            raise ValueError(f"threshold must be in (0, 1), got {self.threshold}")
        if not (math.isfinite(self.neutral_deadband) and 0.0 <= self.neutral_deadband < 0.5):
            raise ValueError(f"neutral_deadband must be in [0, 0.5), got "
                             f"{self.neutral_deadband}")
        scales = np.asarray(self.speed_scales, dtype=np.float64)
        if (scales.ndim != 1 or not np.all(np.isfinite(scales)) or np.any(scales < 0.0)
                or np.any(scales > 1.0) or 0.0 not in scales or 1.0 not in scales):
            raise ValueError("speed_scales must lie in [0, 1] and include 0 and 1, got "
                             f"{self.speed_scales}")
        offsets = np.asarray(self.turn_offsets, dtype=np.float64)
        if (offsets.ndim != 1 or not np.all(np.isfinite(offsets))
                or np.any(np.abs(offsets) > 2.0) or 0.0 not in offsets):
            raise ValueError(f"turn_offsets must lie in [-2, 2] and include 0, got "
                             f"{self.turn_offsets}")
        if not (math.isfinite(self.progress_weight) and self.progress_weight >= 0.0):
            raise ValueError(f"progress_weight must be >= 0, got {self.progress_weight}")
        if not (math.isfinite(self.depth_tolerance) and 0.0 <= self.depth_tolerance <= 0.5):
            raise ValueError(f"depth_tolerance must be in [0, 0.5] m, got "
                             f"{self.depth_tolerance}")


@dataclass(frozen=True)
class Decision:
    """One step of the layer.

    Attributes:
        why: what was done (:class:`Why`).
        detail: words for the status line.
        user: [2] the user's command (forward, turn).
        command: [2] the command to send, or None (the user's command passes).
        p_user: probability of contact within the horizon with the user's command held
            (NaN when not computed).
        p_command: the same for ``command`` (NaN when there is none).
        change: Euclidean change of the command (0 without intervention).
        solve_s: time spent predicting and checking (s).
        candidates: candidates evaluated.
        prediction: the prediction of the user's command (None when there was none).
    """

    why: Why
    detail: str
    user: FloatArray
    command: FloatArray | None = None
    p_user: float = float("nan")
    p_command: float = float("nan")
    change: float = 0.0
    solve_s: float = 0.0
    candidates: int = 0
    prediction: Prediction | None = None

    @property
    def intervening(self) -> bool:
        return self.command is not None


def is_neutral(command: FloatArray, deadband: float) -> bool:
    """Both deflections within the deadband."""
    return bool(np.all(np.abs(command) <= deadband))


#: How long the board drives with an override frame after it (s): its watchdog
#: (``ASGP_WATCHDOG_MS``, firmware/asgp_bridge/config.h).
BOARD_WATCHDOG_S = WATCHDOG_MS / 1000.0
#: How long after a ``joy_override`` message stamped on arrival the board may still drive
#: with it (s): the serial bridge re-sends it while fresh (``override_timeout``, default
#: 0.15 s), and the board applies each frame for its watchdog (0.2 s).
OVERRIDE_APPLIED_S = OVERRIDE_TIMEOUT_S + BOARD_WATCHDOG_S


def applied_command(user: FloatArray, override: FloatArray | None, age_s: float,
                    hold_s: float, deadband: float = BOARD_NEUTRAL) -> FloatArray | None:
    """The command the board drives the chair with, modelled from what was sent: the
    override when it is at least 0 and less than ``hold_s`` old and the user's stick is out
    of the ``deadband`` (the firmware's rules 2 and 3), else None (the user's stick drives).

    A model, not a measurement: an override lost on the way, or one the board refused, is
    taken as applied.
    """
    if override is None or not 0.0 <= age_s < hold_s or is_neutral(user, deadband):
        return None
    return override


def check_covariance(pred: Prediction, config: SharedControlConfig) -> FloatArray:
    """The covariance a check gets for ``pred`` (single or batch): the pose covariance
    with ``heading_uncertainty`` when the prediction has one, else the position's."""
    if config.heading_uncertainty and pred.pose_cov.shape == (*pred.pose.shape[:-1], 3, 3):
        return pred.pose_cov
    return pred.pos_cov


def candidate_commands(user: FloatArray, config: SharedControlConfig) -> FloatArray:
    """[C, 2] commands: the user's forward scaled and turn shifted, then the whole command
    scaled (row 0 is the user's; stopping, (0, 0), is always there)."""
    scales = np.asarray(config.speed_scales, dtype=np.float64)
    offsets = np.asarray(config.turn_offsets, dtype=np.float64)
    order_s = np.argsort(-scales, kind="stable")  # 1.0 first
    order_o = np.argsort(np.abs(offsets), kind="stable")  # 0.0 first
    fwd = user[0] * scales[order_s]
    turn = np.clip(user[1] + offsets[order_o], -1.0, 1.0)
    grid = np.stack(np.meshgrid(fwd, turn, indexing="ij"), axis=-1).reshape(-1, 2)
    grid = np.concatenate([grid, scales[order_s, None] * user[None, :]])
    # the same command from two offsets clipped to the same turn: keep the first
    _, first = np.unique(np.round(grid, 9), axis=0, return_index=True)
    return grid[np.sort(first)]


def _least_deepening(check: CollisionCheck, pose: FloatArray, low: NDArray[np.intp],
                     cost: FloatArray, tolerance: float) -> tuple[int, float, float] | None:
    """Among the candidates ``low`` (as likely to touch as the user's command, row 0 of the
    paths ``pose`` [C, k, 3]), the cheapest whose mean path takes the obstacles no more
    than ``tolerance`` deeper into the footprint than the least-deepening one does
    (:func:`~asgp_ros.core.collision.footprint_deepening`), with the user's deepening and
    its own; None when the user's command itself takes them no more than ``tolerance``
    deeper than that, or the check cannot tell."""
    if not isinstance(check, PathCheck):
        return None

    def deepening(paths: FloatArray) -> FloatArray:
        got = np.asarray(check.deepening(paths), dtype=np.float64)
        if got.shape != (paths.shape[0],) or not np.all(np.isfinite(got)) or np.any(got < 0):
            raise ValueError(f"the check gave deepenings {got.shape} for {paths.shape[0]} "
                             "paths, or non-finite or negative ones")
        return got

    user = float(deepening(pose[:1])[0])
    if user <= tolerance:  # none goes less deep than 0: the common case, one path's cost
        return None
    deeper = deepening(pose[low])
    least = float(deeper.min())
    if user <= least + tolerance:
        return None
    pick = int(np.argmin(np.where(deeper <= least + tolerance, cost[low], np.inf)))
    return int(low[pick]), user, float(deeper[pick])


def decide(predictor: Predictor, now: float, user: FloatArray | None,
           check: CollisionCheck | None, config: SharedControlConfig, *,
           check_for: Callable[[Prediction], CollisionCheck | None] | None = None,
           learn: bool = True) -> Decision:
    """One step of the layer (module docstring).

    Args:
        predictor: fed with the commands the chair actually received and the VO.
        now: current time on the predictor's clock.
        user: [2] the user's newest command (forward, turn), or None when no joystick
            sample has arrived yet (nothing to judge: said so, as the predictor says it).
        check: the collision check of the fresh obstacle source, or None when there is none.
        config: the settings.
        check_for: instead of ``check``, builds it from the user's prediction (its t0,
            origin and velocities place the paths relative to the obstacles' data).
        learn: an adapting predictor learns before returning (``Predictor.predict``); a
            node that acts on the decision first passes False and calls
            ``predictor.learn()`` afterwards.
    """
    if user is None:  # (the Decision's user: NaN, not a stick's reading)
        return Decision(Why.STALE_INPUT, f"the user's command: {no_input_detail(True, False)}",
                        np.full(2, np.nan))
    # a copy: Decision.user is the command decided on, not the caller's live stick buffer
    user = np.array(user, dtype=np.float64).reshape(2)
    problem = joy_problem(float(user[0]), float(user[1]))
    if problem is not None:  # not a stick's reading (a stray publisher): nothing to judge
        return Decision(Why.STALE_INPUT, f"the user's command: {problem}", user)
    if is_neutral(user, BOARD_NEUTRAL):
        return Decision(Why.NEUTRAL, "the stick is neutral: nothing is commanded", user)
    # within neutral_deadband the board still drives the chair (a stick at 0.05 creeps at
    # 5 %): guarded, but only by stopping, never steered from a stick barely touched
    creeping = is_neutral(user, config.neutral_deadband)
    start = time.perf_counter()
    k = predictor.config.horizon_steps
    held = np.repeat(user[None, :], k, axis=0)
    try:
        pred = predictor.predict(now, joy_future=held, learn=learn)
    except ValueError as exc:
        return Decision(Why.CHECK_FAILED, f"prediction failed: {exc}", user,
                        solve_s=time.perf_counter() - start)
    if not pred.ok:
        return Decision(Why.STALE_INPUT, f"no prediction: {pred.reason}: {pred.detail}", user)
    if check_for is not None:
        try:
            check = check_for(pred)
        except ValueError as exc:
            return Decision(Why.CHECK_FAILED, f"obstacle data refused: {exc}", user,
                            solve_s=time.perf_counter() - start, prediction=pred)
    if check is None:
        return Decision(Why.NO_OBSTACLES, "no fresh scan or map", user, prediction=pred)
    try:
        _, within = check(pred.pose[None], check_covariance(pred, config)[None])
        p_user = float(within[0])
    except ValueError as exc:
        return Decision(Why.CHECK_FAILED, f"collision check failed: {exc}", user,
                        solve_s=time.perf_counter() - start, prediction=pred)
    if not math.isfinite(p_user):
        return Decision(Why.CHECK_FAILED, "collision check gave a non-finite probability",
                        user, solve_s=time.perf_counter() - start, prediction=pred)
    if p_user <= config.threshold:
        return Decision(Why.CLEAR, f"p = {p_user:.3f}", user, p_user=p_user,
                        solve_s=time.perf_counter() - start, prediction=pred)

    commands = (np.array([user, [0.0, 0.0]]) if creeping
                else candidate_commands(user, config))  # [C, 2], row 0 the user's
    futures = np.repeat(commands[:, None, :], k, axis=1)  # [C, k, 2]
    try:
        batch = predictor.predict_batch(futures, now, learn=learn)
        if not batch.ok:
            raise ValueError(f"{batch.reason}: {batch.detail}")
        _, p_all = check(batch.pose, check_covariance(batch, config))
    except ValueError as exc:
        return Decision(Why.CHECK_FAILED, f"candidates failed: {exc}", user, p_user=p_user,
                        solve_s=time.perf_counter() - start, prediction=pred)
    p_all = np.where(np.isfinite(p_all), p_all, 1.0)
    change = np.linalg.norm(commands - user, axis=1)
    ahead = 1.0 if user[0] >= 0.0 else -1.0  # reversing: progress is backwards
    lost = np.maximum(0.0, ahead * (pred.pose[-1, 0] - batch.pose[:, -1, 0]))
    cost = change**2 + config.progress_weight * lost**2
    safe = p_all <= config.threshold
    if np.any(safe):
        best = int(np.flatnonzero(safe)[np.argmin(cost[safe])])
        why, words = Why.INTERVENING, "changed the command"
    else:
        low = np.flatnonzero(p_all <= p_all.min() + 1e-12)
        motion = np.linalg.norm(commands[low], axis=1)  # ties: the least motion
        best = int(low[np.lexsort((cost[low], motion))[0]])
        why, words = Why.NO_SAFE_COMMAND, "no candidate is below the threshold"
        if p_all[best] >= min(p_user, float(p_all[0])) - 1e-9:
            # no candidate is less likely to touch than the user's command (already within
            # the margin, say): how much deeper the mean paths go tells them apart
            try:
                shallower = _least_deepening(check, batch.pose, low, cost,
                                             config.depth_tolerance)
            except ValueError as exc:
                return Decision(Why.CHECK_FAILED, f"depth of the candidates failed: {exc}",
                                user, p_user=p_user, solve_s=time.perf_counter() - start,
                                prediction=pred)
            if shallower is None:  # the user's command goes no deeper (backing away, say):
                # overriding would only pin the chair there; the user's command passes
                return Decision(why, f"{words}, and none does better than the user's "
                                f"command (p {p_user:.3f})", user, p_user=p_user,
                                solve_s=time.perf_counter() - start,
                                candidates=int(commands.shape[0]), prediction=pred)
            best, d_user, d_best = shallower
            words = (f"{words}; the user's command goes {d_user:.3f} m deeper, this "
                     f"{d_best:.3f} m")
    elapsed = time.perf_counter() - start
    if best == 0 and why is Why.INTERVENING:  # cannot happen: row 0 is the user's (unsafe)
        return Decision(Why.CLEAR, f"p = {p_user:.3f}", user, p_user=p_user,
                        solve_s=elapsed, prediction=pred)
    return Decision(why, f"{words}: p {p_user:.3f} -> {float(p_all[best]):.3f}", user,
                    command=commands[best].copy(), p_user=p_user,
                    p_command=float(p_all[best]), change=float(change[best]),
                    solve_s=elapsed, candidates=int(commands.shape[0]), prediction=pred)


#: The user's stick scaled by these (both axes: its path, slower) are the gentle candidates
#: for a stick that moved while the layer decided (:func:`judge_moved_stick`).
MOVED_STICK_SLOWER = (0.75, 0.5, 0.25)


def within_stick(command: FloatArray, stick: FloatArray) -> FloatArray:
    """A decision's command with its forward part no further forward or back than the
    user's newest stick (zero where the stick no longer drives that way: pulled back, or let
    go), its turn as decided (scaled down with the forward, the turn built up while the
    chair coasted straighter than the decision predicted)."""
    out = np.asarray(command, dtype=np.float64).reshape(2).copy()
    fwd, now = float(out[0]), float(np.asarray(stick, dtype=np.float64).reshape(2)[0])
    out[0] = 0.0 if fwd * now <= 0.0 else math.copysign(min(abs(fwd), abs(now)), fwd)
    return out


def judge_moved_stick(predictor: Predictor, now: float, decision: Decision,
                      stick: FloatArray, config: SharedControlConfig,
                      check_for: Callable[[Prediction], CollisionCheck | None]) -> Decision:
    """What to send for a stick that moved since ``decision`` was made (while it was made,
    or while the layer was too busy to decide again), judged against that stick at once:
    the stick itself, the stick slowed (:data:`MOVED_STICK_SLOWER`), the decision's command
    within it (:func:`within_stick`) and stopping, held over the horizon as :func:`decide`
    holds them (one batch of six paths, no search). The stick passes if it is clear; else
    the clear one that changes it least; else the least likely to touch (the stick's: it
    passes). A stick within ``neutral_deadband`` is only ever stopped. Never sends a
    command judged against an older stick: one pulled back was pinned by the decision's
    turn on the spot, and a turn scaled down with the forward swept a corner the decision
    had steered around."""
    stick = np.asarray(stick, dtype=np.float64).reshape(2)
    problem = joy_problem(float(stick[0]), float(stick[1]))
    if problem is not None:
        return Decision(Why.STALE_INPUT, f"the user's command: {problem}", stick)
    if is_neutral(stick, BOARD_NEUTRAL):
        return Decision(Why.NEUTRAL, "the stick is neutral: nothing is commanded", stick)
    if decision.command is None:
        return Decision(Why.CHECK_FAILED, "no command decided", stick)
    start = time.perf_counter()
    if is_neutral(stick, config.neutral_deadband):
        commands = np.array([stick, [0.0, 0.0]])
    else:  # the stick, slowed (gently first), the decision within it, stopping
        commands = np.array([stick, *(f * stick for f in MOVED_STICK_SLOWER),
                             within_stick(decision.command, stick), [0.0, 0.0]])
    futures = np.repeat(commands[:, None, :], predictor.config.horizon_steps, axis=1)
    try:
        batch = predictor.predict_batch(futures, now, learn=False)
        if not batch.ok:
            raise ValueError(f"{batch.reason}: {batch.detail}")
        check = check_for(batch)
        if check is None:
            return Decision(Why.NO_OBSTACLES, "no fresh scan or map", stick)
        _, p = check(batch.pose, check_covariance(batch, config))
    except ValueError as exc:
        return Decision(Why.CHECK_FAILED, f"the moved stick: {exc}", stick,
                        solve_s=time.perf_counter() - start)
    p = np.where(np.isfinite(p), p, 1.0)
    elapsed = time.perf_counter() - start
    n = int(commands.shape[0])
    words = "the stick moved while the layer decided: judged again with it"
    if p[0] <= config.threshold:
        return Decision(Why.CLEAR, f"{words}, clear (p = {p[0]:.3f})", stick,
                        p_user=float(p[0]), solve_s=elapsed, candidates=n)
    change = np.linalg.norm(commands - stick, axis=1)
    clear = np.flatnonzero(p <= config.threshold)
    # the least change of the clear ones; none clear: the least likely to touch (then the
    # least change)
    best = (int(clear[np.argmin(change[clear])]) if clear.size
            else int(np.lexsort((change, p))[0]))
    if best == 0:  # nothing does better than the stick: it passes
        return Decision(Why.NO_SAFE_COMMAND, f"{words}; nothing less likely to touch than "
                        f"the stick (p {p[0]:.3f})", stick, p_user=float(p[0]),
                        solve_s=elapsed, candidates=n)
    return Decision(Why.INTERVENING if clear.size else Why.NO_SAFE_COMMAND,
                    f"{words}: p {p[0]:.3f} -> {p[best]:.3f}", stick,
                    command=commands[best].copy(), p_user=float(p[0]),
                    p_command=float(p[best]), change=float(change[best]), solve_s=elapsed,
                    candidates=n)
