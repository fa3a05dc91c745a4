"""One ranking of plans by the request's objective, used by every method and by ``auto``.

Objectives (smaller keys are better, compared as tuples):

``reversals_then_deviation`` (the default)
    Fewest actuator reversals (``phi`` and ``th_1`` together), then the smallest ``deviation``:
    the largest distance in joint space of the path from the straight segment start -> goal.
    What a robot drives: it measures every joint, and no retiming changes it.
``tp_then_da``
    The paper's §4 rule: fewest ``t_p`` (interior extrema of ``th_1``), then the smallest
    ``d_a`` of joint 1.
``tp_then_sensitivity``
    The paper's §5.3 rule: fewest ``t_p``, then the smallest ``||J_R(T)||_F``.
``weighted``
    The smallest ``w_da d_a + w_s ||J_R(T)||_F + w_e energy + w_tp t_p`` (``weights``).
"""

from __future__ import annotations

from typing import Iterable

from ..indicators import Indicators
from ..problem import DEFAULT_OBJECTIVE, Weights
from ..results import Plan

#: What each objective ranks by, in words (diagnostics and documentation).
RULES = {
    "reversals_then_deviation": "fewest actuator reversals (phi and th1), then smallest "
                                "joint-space deviation from the straight segment",
    "tp_then_da": "fewest t_p (extrema of th1), then smallest d_a of joint 1",
    "tp_then_sensitivity": "fewest t_p, then smallest ||J_R(T)||_F",
    "weighted": "smallest weighted score w_da d_a + w_s ||J_R(T)||_F + w_e energy + w_tp t_p",
}


def rank_key(ind: Indicators, objective: str = DEFAULT_OBJECTIVE,
             weights: Weights | None = None) -> tuple[float, float]:
    """The ranking key of a plan's indicators under ``objective`` (smaller is better)."""
    if objective == "reversals_then_deviation":
        return float(ind.reversals), ind.deviation
    if objective == "tp_then_da":
        return float(ind.t_p), ind.d_a
    if objective == "tp_then_sensitivity":
        return float(ind.t_p), ind.sensitivity
    if objective == "weighted":
        w = weights or Weights()
        score = 0.0
        # terms with weight 0 are left out (an indicator may be undefined)
        for c, x in ((w.d_a, ind.d_a), (w.sensitivity, ind.sensitivity), (w.energy, ind.energy),
                     (w.t_p, float(ind.t_p))):
            if c != 0.0:
                score += c * x
        return 0.0, score
    raise ValueError(f"unknown objective {objective!r}")


def better(a: Plan, b: Plan, objective: str = DEFAULT_OBJECTIVE,
           weights: Weights | None = None) -> Plan:
    """The better of two plans (ties keep ``a``)."""
    if rank_key(ranked_indicators(b, objective), objective, weights) < \
            rank_key(ranked_indicators(a, objective), objective, weights):
        return b
    return a


def ranked_indicators(plan: Plan, objective: str = DEFAULT_OBJECTIVE) -> Indicators:
    """The indicators a plan is ranked by: the handed-out path's (``plan.indicators``) for
    the default objective; for the paper's objectives (``t_p``, ``d_a``, sensitivity, their
    weights) the exact plan's on its own schedule (``plan.plan_indicators``), which the
    methods optimise: ``d_a`` and the energy depend on the timing, and the handed-out path
    runs the plan along its time law."""
    if objective == "reversals_then_deviation" or plan.plan_indicators is None:
        return plan.indicators
    return plan.plan_indicators


def best(plans: Iterable[Plan | None], objective: str = DEFAULT_OBJECTIVE,
         weights: Weights | None = None) -> Plan | None:
    """The best of the plans given (``None`` entries skipped; ties keep the earlier)."""
    chosen: Plan | None = None
    for p in plans:
        if p is not None:
            chosen = p if chosen is None else better(chosen, p, objective, weights)
    return chosen
