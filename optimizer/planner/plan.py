"""One entry point: a plan request -> a verified plan, or a typed, explained failure.

The methods live in their own modules behind one interface (:mod:`.base`), listed in
:mod:`.registry`; ``auto`` (:mod:`.auto`) picks among them. Every plan, whatever the method,
goes through the one finishing path (:mod:`.finish`): continuous region check, sampling,
indicators and re-integration of the original model. A plan that fails there is never
returned.
"""

from __future__ import annotations

import time
from dataclasses import replace

from ..errors import InfeasibleError, NumericalError
from ..problem import DEFAULT_OBJECTIVE, PlanRequest
from ..results import Plan
from .auto import NOT_A_PROOF, plan_auto
from .budget import check_budget_request, plan_with_budget
from .context import Deadline, PlanContext
from .registry import AUTO, get
from .nlp import ladder
from .via import via_failure
from .rules import check_endpoints, clear_request_caches, full_region, travel_reach_error


def plan(req: PlanRequest) -> Plan:
    """Plan a singularity-free path for ``req``.

    Returns
    -------
    Plan
        Verified on the original model (terminal error <= 1e-6 rad).

    Raises
    ------
    InvalidRequestError, InfeasibleError, SolverTimeoutError, NumericalError
    """
    ctx = PlanContext(Deadline(req.time_limit))
    t0 = time.perf_counter()
    clear_request_caches()
    check_endpoints(req, full_region(req))
    check_reach(req)
    budget = req.max_reversals is not None or req.pareto
    if budget:
        check_budget_request(req)
    try:
        result = _planned(req, ctx)
    except (InfeasibleError, NumericalError) as exc:
        if not budget:
            raise via_failure(req, exc)  # (exc itself without via points)
        # the budget's own candidates may still find a path (and say how few reversals)
        result = plan_with_budget(req, ctx, None, exc, _fewest_reversals(req, ctx))
    else:
        if budget:
            result = plan_with_budget(req, ctx, result, None, _fewest_reversals(req, ctx))
    # the answer carries the request's bounds: a replan of it (handed back as it is) keeps them
    if req.joint_bounds is not None:
        result = replace(result, joint_bounds=req.joint_bounds)
    result.timing["total"] = time.perf_counter() - t0
    return result


def _planned(req: PlanRequest, ctx: PlanContext) -> Plan:
    """The plan of ``req``'s method (``auto`` or one method) under its objective. A method
    asked for by name whose NLPs converged nowhere near a path says, as ``auto`` does, that
    this is a search that found none (:data:`~.auto.NOT_A_PROOF`), in its message and in
    ``diagnostics.searched_without_proof``."""
    if req.method == AUTO:
        return plan_auto(req, ctx)
    try:
        return get(req.method).plan(req, ctx)
    except InfeasibleError as exc:
        if exc.diagnostics.get("blocking") != "nlp_failed":
            raise
        raise InfeasibleError(f"{exc.message} ({req.method}: {NOT_A_PROOF})", field=exc.field,
                              diagnostics={**exc.diagnostics,
                                           "searched_without_proof": [req.method]}) from None


def _fewest_reversals(req: PlanRequest, ctx: PlanContext) -> Plan | None:
    """Under another objective than the default, the default objective's plan (the ladder's
    fewest reversals) for the reversal budget: the objective's own plan may reverse far more
    (a 4-joint ``weighted`` plan 10 times where the default's reverses twice), and the budget
    looks for no fewer reversals than its candidates' fewest. None under the default objective
    (its plan is that plan) or where it finds no plan."""
    if req.objective == DEFAULT_OBJECTIVE:
        return None
    try:
        return _planned(replace(req, objective=DEFAULT_OBJECTIVE), ctx)
    except (InfeasibleError, NumericalError):
        return None


def check_reach(req: PlanRequest) -> None:
    """Refuse at once a goal that no method's paths can reach within the joint limits.

    The most ``phi`` travels in any method's path: the NLPs' largest rate bound (rad per unit
    of normalised time, so rad over the path) and the paper's family its ``|dphi|`` bound. (A
    ``duration`` too short for the rate limits is the time law's to name: ``duration``.)

    Raises
    ------
    InfeasibleError
        Naming ``joint_bounds`` (:func:`~.rules.travel_reach_error`).
    """
    travel = max(max(t.rate_bound for t in ladder(req.n)),
                 max(abs(x) for x in req.phi_change_bounds))
    why = travel_reach_error(req, travel)
    if why is not None:
        raise InfeasibleError(why, field="joint_bounds",
                              diagnostics={"phi_travel_bound": travel})
