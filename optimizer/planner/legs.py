"""A goal too far for one NLP, reached through intermediate goals on the joint-space segment.

Why: from 5 joints the shooting NLP's first rungs (16 to 50 intervals, rates bounded per
interval) cannot hold the loops that a large move of every joint needs, and its elastic goal
converges far off (a 5-joint move of every joint 10 -> 80 deg: 0.39 rad off after 4.5 s of
rungs; ``penalty`` then fails too). The same move in two halves planned in 0.09 and 1.2 s. The
model is driftless, so motions compose: the path to an intermediate state, followed by a path
from the state it reached, is a path.

How (:func:`plan_in_legs`): the straight segment ``start -> goal`` in joint space is bisected.
A leg from the state reached so far to the point at fraction ``b`` of the segment is planned by
``shooting`` (the default ladder, its own finishing and proof); where that search finds no path
(``blocking: nlp_failed``, not a proof), the leg is split in two at its middle, down to
:data:`MAX_LEGS` legs. Each leg starts where the previous one *ended* (its re-integrated end,
phi included), and the last one's goal is the request's, so errors do not accumulate. Every
intermediate goal lies on the segment, inside the joint box of start and goal and so inside
the region and any joint bounds. The legs' rates are then one schedule (each leg's pieces, in
order, on equal intervals of normalised time) and :func:`~.finish.finish_actuator_plan`
re-integrates it from the request's start, checks the region at every break and the goal, and
hands it out under the request's time law and limits like any plan: the proof is of the whole
path, not of the legs. A junction of legs is a break like any other: the time law stops there
where a rate changes direction.

The cost is reversals and deviation: each leg reverses ``phi`` and ``th_1`` as its own goal
needs, and the handed-out counts are those of the whole path.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import numpy as np

from ..actuation import ActuatorSchedule
from ..cascade import integrate_cascade
from ..errors import InfeasibleError, NumericalError
from ..problem import PlanRequest
from ..results import Plan
from .context import PlanContext
from .finish import finish_actuator_plan

#: At most this many legs (three bisections). Moves that need more are left to ``penalty``
#: and to the caller (an intermediate goal of their own). Each leg runs ``shooting``'s whole
#: ladder: with its first transcription only (a leg that misses there split at once), the
#: failing legs took 0.2-0.4 s instead of 4-10 s, but more legs were needed, with 1.75-3.3
#: times the reversals (a 6-joint move of the last joint by 30 deg: 79 against 24), and two
#: 7-joint moves found no path at all.
MAX_LEGS = 8

#: The method that plans each leg.
LEG_METHOD = "shooting"


def can_split(req: PlanRequest) -> bool:
    """Whether a request may be planned in legs: nothing tied to the whole motion (a fixed
    ``phi`` change, via or constraint points at times of the whole path), and a move."""
    return (req.phi_change is None and not req.via_points and not req.constraint_points
            and req.start != req.goal)


def leg_request(req: PlanRequest, q_from: np.ndarray, goal: np.ndarray) -> PlanRequest:
    """The request of one leg: from the full state ``q_from`` (phi first) to the joint angles
    ``goal``, with the request's robot, region, bounds and objective; no timing of its own
    (the whole path is timed once, :func:`plan_in_legs`)."""
    return dataclasses.replace(
        req, start=tuple(float(x) for x in q_from[1:]), goal=tuple(float(x) for x in goal),
        phi_start=float(q_from[0]), method=LEG_METHOD, duration=None, max_u1=None,
        max_u2=None, max_du1=None, max_du2=None, max_ddu1=None, max_ddu2=None,
        controller_period=None, joint_trajectory=False, max_reversals=None, pareto=False)


def _schedule(plan: Plan) -> ActuatorSchedule:
    """A leg's actuator rates (``shooting`` plans on the original model: always these)."""
    if not isinstance(plan.inputs, ActuatorSchedule):
        raise NumericalError(f"a leg planned by {plan.method!r} has no actuator rates",
                             diagnostics={"method": plan.method})
    return plan.inputs


def _leg_nodes(leg: PlanRequest, sched: ActuatorSchedule) -> np.ndarray:
    """The leg's states at its breaks (its schedule re-integrated from its start)."""
    rep = integrate_cascade(leg.robot, sched.u, leg.q_start(), sched.duration, sched.breaks,
                            sched.breaks, fallback=sched.u_scalar, constant_pieces=True)
    return np.asarray(rep.q[:sched.breaks.size], float)


def plan_in_legs(req: PlanRequest, ctx: PlanContext,
                 plan_leg: Callable[[PlanRequest, PlanContext], Plan]) -> Plan:
    """The request's path through intermediate goals on its joint-space segment (see the
    module), planned leg by leg with ``plan_leg`` (the registry's ``shooting``), finished and
    verified as one plan. :class:`InfeasibleError` (blocking ``nlp_failed``) when a leg of
    ``1 / MAX_LEGS`` of the segment found no path either; a leg's other errors (a timeout, a
    proof) go to the caller."""
    t0 = time.perf_counter()
    start = np.array(req.start, float)
    goal = np.array(req.goal, float)
    legs: list[tuple[PlanRequest, Plan, float]] = []    # (request, plan, fraction reached)
    record: list[dict[str, Any]] = []
    q_now = req.q_start()

    def point(frac: float) -> np.ndarray:
        return goal.copy() if frac >= 1.0 else start + frac * (goal - start)

    def reach(a: float, b: float) -> None:
        nonlocal q_now
        leg = leg_request(req, q_now, point(b))
        began = time.perf_counter()
        try:
            plan = plan_leg(leg, PlanContext(ctx.deadline))
        except InfeasibleError as exc:
            searched = exc.diagnostics.get("blocking") == "nlp_failed"
            record.append({"from": a, "to": b, "outcome": f"{exc.code}",
                           "seconds": round(time.perf_counter() - began, 6)})
            if not searched or (b - a) * MAX_LEGS <= 1.0 + 1e-9:
                raise
            middle = 0.5 * (a + b)
            reach(a, middle)
            reach(middle, b)
            return
        record.append({"from": a, "to": b, "outcome": "plan",
                       "reversals": plan.indicators.reversals,
                       "seconds": round(time.perf_counter() - began, 6)})
        legs.append((leg, plan, b))
        q_now = np.array(plan.verification.final, float)

    # the whole move already failed (the caller's attempt): two halves first
    try:
        reach(0.0, 0.5)
        reach(0.5, 1.0)
    except InfeasibleError as exc:
        raise InfeasibleError(
            f"planning in legs (intermediate goals on the joint-space segment, down to "
            f"1/{MAX_LEGS} of it) found no path: {exc.message}",
            diagnostics={"blocking": "nlp_failed", "legs": record}) from None
    # one schedule: every leg's pieces in order, each on an equal share of normalised time
    schedules = [_schedule(plan) for _, plan, _ in legs]
    moves = np.vstack([s.rates * np.diff(s.breaks)[:, None] for s in schedules])
    rates = moves * moves.shape[0]
    nodes = [_leg_nodes(leg, s) for (leg, _, _), s in zip(legs, schedules)]
    planned = np.vstack([nodes[0]] + [n[1:] for n in nodes[1:]])
    timing: dict[str, float] = {"legs": time.perf_counter() - t0}
    diagnostics: dict[str, Any] = {
        "objective": req.objective, "singularity": req.singularity,
        "legs": {"count": len(legs),
                 "why": "one NLP found no path to the goal: planned through intermediate "
                        "goals on the joint-space segment start -> goal",
                 "fractions": [b for _, _, b in legs[:-1]], "tried": record}}
    return finish_actuator_plan(req, rates, LEG_METHOD, planned, timing, diagnostics)


__all__ = ["LEG_METHOD", "MAX_LEGS", "can_split", "leg_request", "plan_in_legs"]
