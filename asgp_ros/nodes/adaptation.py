"""Online adaptation in the nodes (:mod:`asgp_ros.core.adaptive`): the ``adapt.*``
parameters, the settings they make, the diagnostics it shows and the service that resets
it; one definition for ``predictor_node`` and ``shared_control_node``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

from rclpy.node import Node
from std_srvs.srv import Trigger

from asgp_ros.common.paramspec import ParamSpec
from asgp_ros.core.adapt import AdaptConfig, AdaptError
from asgp_ros.core.adaptive import (
    DEFAULT_HALF_LIFE_S,
    DEFAULT_TRAINED_FLOOR,
    DEFAULT_TRAINED_HALF_LIFE_S,
    AdapterStats,
    AdaptSettings,
    CoverageConfig,
)
from asgp_ros.core.online import Predictor

#: The ``adapt.*`` parameters (all read at start-up).
ADAPT_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("adapt.enabled", True, "adapt an ASGP online: absorb each valid completed step "
              "into its posterior and keep its 95% ellipses covering (asgp_ros.core.adaptive); "
              "a model that cannot adapt (not an ASGP) predicts as trained, with a warning"),
    ParamSpec("adapt.half_life_s", DEFAULT_HALF_LIFE_S, "forgetting half-life of the rows the "
              "adapted posterior absorbs, seconds of driving", 1.0, 86400.0),
    ParamSpec("adapt.trained_half_life_s", DEFAULT_TRAINED_HALF_LIFE_S, "half-life of the "
              "trained data's weight in the adapted posterior, seconds of driving",
              1.0, 86400.0),
    ParamSpec("adapt.trained_floor", DEFAULT_TRAINED_FLOOR, "weight the trained data decay to "
              "(0 = forget them, 1 = keep them whole)", 0.0, 1.0),
    ParamSpec("adapt.trained_mean", True, "the rows teach a correction to the trained "
              "function (its mean is the prior mean); false: the function itself, against a "
              "constant mean"),
    ParamSpec("adapt.calibrate", True, "adjust the variance scale from the outcomes of the "
              "predictions"),
    ParamSpec("adapt.max_rate", 0.25, "largest change of the log variance scale per second",
              0.001, 100.0),
)
ADAPT_NAMES = frozenset(spec.name for spec in ADAPT_PARAMS)


def adapt_settings(values: Mapping[str, Any]) -> AdaptSettings | None:
    """The settings of checked ``adapt.*`` values (a missing one takes its default); None
    when ``adapt.enabled`` is false. ValueError for settings adaptation refuses."""
    v = {spec.name: values.get(spec.name, spec.default) for spec in ADAPT_PARAMS}
    try:
        settings = AdaptSettings(
            AdaptConfig(half_life_s=float(v["adapt.half_life_s"]),
                        trained_floor=float(v["adapt.trained_floor"]),
                        trained_half_life=float(v["adapt.trained_half_life_s"]),
                        trained_mean=bool(v["adapt.trained_mean"])),
            CoverageConfig(max_rate=float(v["adapt.max_rate"]))
            if v["adapt.calibrate"] else None)
    except AdaptError as exc:
        raise ValueError(f"adapt: {exc}") from exc
    return settings if v["adapt.enabled"] else None


def make_predictor(node: Node, build: Callable[[AdaptSettings | None], Predictor],
                   settings: AdaptSettings | None) -> tuple[Predictor, str]:
    """``build(settings)``; when the model cannot adapt (an MLP or a baseline, a model file
    without the posterior's factor: :class:`AdaptError`), ``build(None)``, so that the node
    predicts from the model as trained, with a warning. Returns the predictor and why it
    does not adapt although asked to ('' otherwise)."""
    if settings is None:
        return build(None), ""
    try:
        return build(settings), ""
    except AdaptError as exc:
        node.get_logger().warning(f"adapt.enabled, but this model does not adapt ({exc}): "
                                  "predicting from it as trained")
        return build(None), str(exc)


def describe(values: Mapping[str, Any], settings: AdaptSettings | None) -> str:
    """The start-up log line of an adapting node ('' when not adapting)."""
    if settings is None:
        return ""
    v = {spec.name: values.get(spec.name, spec.default) for spec in ADAPT_PARAMS}
    return (f"adapting online: half-life {v['adapt.half_life_s']:g} s (trained data "
            f"{v['adapt.trained_half_life_s']:g} s), trained floor "
            f"{v['adapt.trained_floor']:g}, calibration "
            f"{'on' if settings.coverage is not None else 'off'}")


def diagnostic_values(adaptation: AdapterStats | None, unavailable: str = "",
                      ellipses: bool = True) -> dict[str, str]:
    """The diagnostics' key-values of a predictor's adaptation ('adapt': on or off; with
    ``unavailable``, why a model asked to adapt does not, see :func:`make_predictor`).
    ``ellipses`` False: the node publishes no ellipses (uncertainty 'none'), so no
    coverage of them is claimed."""
    if adaptation is None:
        return {"adapt": "off", **({"adapt_unavailable": unavailable} if unavailable else {})}
    return {
        "adapt": "on",
        "adapt_rows_absorbed": str(adaptation.rows_absorbed),
        "adapt_steps_refused": str(adaptation.steps_refused),
        "adapt_rows_rejected": ", ".join(
            f"{k}={n}" for k, n in sorted(adaptation.rows_rejected.items()) if n) or "none",
        "adapt_effective_size": "/".join(f"{x:.0f}" for x in adaptation.effective_size),
        "adapt_variance_scale": "/".join(f"{x:.3g}" for x in adaptation.scales),
        "adapt_checked": str(adaptation.checked),
        "adapt_published": adaptation.published,
        "adapt_choice_t": (f"{adaptation.choice_t:.2f} (critical "
                           f"{adaptation.choice_critical:.2f})"
                           if math.isfinite(adaptation.choice_t)
                           else "no test yet (too few checks, or no spread)"),
        "adapt_switches": str(adaptation.switches),
        "adapt_coverage_95": f"{adaptation.coverage:.3f}" if ellipses
        else "n/a (uncertainty 'none': no ellipses)",
        "adapt_coverage_one_step": f"{adaptation.coverage_one_step:.3f}",
        "adapt_last_update_ms": f"{1e3 * adaptation.last_update_s:.3f}",
        "adapt_last_check_ms": f"{1e3 * adaptation.last_check_s:.3f}",
    }


def reset_service(node: Node, predictor: Predictor, unavailable: str = "") -> None:
    """``~/reset_adaptation`` (std_srvs/Trigger): back to the trained model (``unavailable``:
    why the model does not adapt, see :func:`make_predictor`)."""

    def reset(request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        del request
        if predictor.adaptation is None:
            response.success = False
            response.message = (f"this model does not adapt: {unavailable}" if unavailable
                                else "adaptation is off (adapt.enabled)")
        else:
            predictor.reset_adaptation()
            response.success, response.message = True, "back to the trained model"
            node.get_logger().info("adaptation reset to the trained model")
        return response

    node.create_service(Trigger, "~/reset_adaptation", reset)
