"""``auto``: run only the methods that can win for the request, and return the best by its rule.

What runs (each method through :mod:`.registry`, its capabilities checked there):

* **Constraint points given**: only the paper's family honours them: ``polynomial`` and
  ``constraint_points``, both, ranked.
* **Via points given** (joint angles at times): only ``shooting`` and ``penalty`` honour them;
  the rules below run, and :meth:`~.base.Method.can_plan` skips every other method.
* **The paper's objectives** (``tp_then_da``, ``tp_then_sensitivity``): the family
  (``polynomial`` and, for ``tp_then_da``, ``retimed``: the same path under the ``d_a``-optimal
  time law) and ``shooting``, ranked. The family has one parameter (``dphi``) where
  ``shooting``'s NLP weighs ``d_a`` over 24 to 40 rates: its plan was the better by the
  paper's own rule on 9 of 22 goals the family reached (:data:`PAPER_OBJECTIVES`), 6 of them
  with fewer extrema of ``th_1``. ``constraint_points`` only when
  neither planned (it is the family's remedy for a goal the family misses, and it cost 0.4 to
  3 s to find none where ``shooting`` planned in milliseconds), ``penalty`` last.
* **The default objective** (fewest reversals, then smallest joint-space deviation) and
  ``weighted``: ``shooting`` first. Its NLP minimises the deviation directly over 24 to 40 rates
  on the original model, where the family has one parameter, so the family is not waited for;
  it runs only when ``shooting`` fails (``weighted`` runs both, the weights decide), or when
  ``shooting``'s plan comes from its finer rung after the first rung's answer missed the goal
  (then it is not the ladder's answer, and the family may beat it). Where ``shooting``'s
  NLPs converged nowhere near the goal (a search that found none, not a proof) and neither
  did the family, the same ``shooting`` plans the move in legs through intermediate goals on
  the joint-space segment (:mod:`.legs`: a 5-joint move of every joint 10 -> 80 deg, 0.39
  rad off in one NLP, plans in two legs), recorded as ``legs``. ``penalty`` solves the same
  transcription with the region as an exact penalty: at equal objective it cannot beat a
  converged ``shooting`` plan, so it runs only when neither found one.

A method that fails (infeasible, numerical, or an unexpected exception: a bug in one method
must not hide another's verified plan) is recorded and the next one runs; the deadline is
shared. ``diagnostics.auto`` says what was tried, what won and by which rule.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

from ..errors import InfeasibleError, PlannerError, SolverTimeoutError
from ..problem import PlanRequest
from ..results import Plan
from .context import PlanContext
from .legs import LEG_METHOD, can_split, plan_in_legs
from .ranking import RULES, best, rank_key
from .registry import get
from .rules import direction_conflict

log = logging.getLogger(__name__)

#: Length (characters) of a failure's message kept in the diagnostics.
MESSAGE_CHARS = 160
#: What an answer says where an NLP converged nowhere near a path: a search that found none
#: is no proof that none exists (an 8-joint goal of every joint +20 deg: every method
#: exhausted in 10 s, where an NLP of other intervals or rates may still find one).
NOT_A_PROOF = ("a search that found none, not a proof that none exists: the goal may be "
               "reached by a path these NLPs do not find; planning to an intermediate goal "
               "first may help")
#: The paper's objectives (fewest extrema of th1, then d_a or ||J_R||). ``shooting`` runs
#: beside the family under them: on the 22 goals of 3 to 5 joints the family reached (of 30
#: generated per objective, seeds 77 and 78) its plan was the better by the paper's rule on
#: 9, 6 of them by fewer extrema (4 -> 0, 3 -> 1, 3 -> 2, 2 -> 1, 1 -> 0 twice); its NLP took
#: 3-77 ms. Where the family found no path, ``constraint_points`` found none either on 17 of
#: 17 goals of 5 to 8 joints (seed 31), in 0.4 to 3 s each, where ``shooting`` planned in 7 to
#: 190 ms.
PAPER_OBJECTIVES = ("tp_then_da", "tp_then_sensitivity")


class _Run:
    """The methods tried for one request and what came of each."""

    def __init__(self, req: PlanRequest, ctx: PlanContext) -> None:
        self.req = req
        self.ctx = ctx
        self.tried: list[dict[str, Any]] = []
        self.plans: list[Plan] = []
        self.errors: list[tuple[str, PlannerError]] = []
        self.timed_out: SolverTimeoutError | None = None

    def attempt(self, name: str) -> Plan | None:
        method = get(name)
        if (not method.can_plan(self.req) or self.timed_out is not None
                or any(t["method"] == name for t in self.tried)):  # (a method runs once)
            return None
        return self._record(name, lambda: method.plan(
            self.req, PlanContext(self.ctx.deadline, warm_start=self.ctx.warm_start)))

    def attempt_legs(self) -> Plan | None:
        """``shooting`` through intermediate goals (:mod:`.legs`), recorded as ``legs``."""
        if self.timed_out is not None:
            return None
        return self._record("legs", lambda: plan_in_legs(self.req, self.ctx,
                                                         get(LEG_METHOD).plan))

    def _record(self, name: str, run: Callable[[], Plan]) -> Plan | None:
        """Run one attempt and record what came of it (a failure is that attempt's only)."""
        t0 = time.perf_counter()
        entry: dict[str, Any] = {"method": name}
        plan: Plan | None = None
        try:
            plan = run()
        except SolverTimeoutError as exc:
            self.timed_out = exc
            entry["outcome"] = "timeout"
        except PlannerError as exc:
            entry["outcome"] = f"{exc.code}: {exc.message[:MESSAGE_CHARS]}"
            self.errors.append((name, exc))
        except Exception as exc:  # noqa: BLE001 - one method's bug is that method's failure
            log.exception("method %s failed unexpectedly inside auto", name)
            entry["outcome"] = f"internal_error: {type(exc).__name__}"
        entry["seconds"] = round(time.perf_counter() - t0, 6)
        if plan is not None:
            entry["outcome"] = "plan"
            entry["rank_key"] = list(rank_key(plan.indicators, self.req.objective,
                                              self.req.weights))
            self.plans.append(plan)
        self.tried.append(entry)
        return plan

    def searched(self, name: str) -> bool:
        """Whether method ``name`` failed as a search (its NLPs converged nowhere near a path),
        not by a proof or a refusal."""
        return any(n == name and exc.diagnostics.get("blocking") == "nlp_failed"
                   for n, exc in self.errors)

    def finish(self) -> Plan:
        req = self.req
        chosen = best(self.plans, req.objective, req.weights)
        if chosen is None:
            if self.timed_out is not None:
                self.timed_out.diagnostics["auto"] = {"tried": self.tried}
                raise self.timed_out
            # each method's whole message (what to change is often at its end: "a shorter
            # controller_period"), and the field when every failure that names one names the
            # same (the request's, such as duration or controller_period)
            fields = {exc.field for _, exc in self.errors if exc.field is not None}
            full = {name: f"{exc.code}: {exc.message}" for name, exc in self.errors}
            # the answer says which failures were searches (NOT_A_PROOF)
            searched = [name for name, exc in self.errors
                        if exc.diagnostics.get("blocking") == "nlp_failed"]
            raise InfeasibleError(
                "no method found a singularity-free path"
                + (f" ({', '.join(searched)}: {NOT_A_PROOF})" if searched else "")
                + ": " + "; ".join(
                    f"{t['method']}: {full.get(t['method'], t['outcome'])}" for t in self.tried),
                field=fields.pop() if len(fields) == 1 else None,
                diagnostics={"auto": {"tried": self.tried, "searched_without_proof": searched}})
        chosen.diagnostics["auto"] = {
            "tried": self.tried,
            "chosen": chosen.method,
            "rule": RULES[req.objective],
        }
        return chosen


def plan_auto(req: PlanRequest, ctx: PlanContext) -> Plan:
    """The best verified plan of the methods that can win for ``req`` (see the module)."""
    run = _Run(req, ctx)
    reachable = direction_conflict(req) is None
    if req.constraint_points:
        run.attempt("polynomial")
        run.attempt("constraint_points")
        return run.finish()
    if req.objective in PAPER_OBJECTIVES:
        if reachable:
            run.attempt("polynomial")
            if req.objective == "tp_then_da" and run.plans:
                run.attempt("retimed")
        run.attempt("shooting")
        if reachable and not run.plans:
            run.attempt("constraint_points")
        if not run.plans:
            run.attempt("penalty")
        return run.finish()
    # the default objective and weighted
    shot = run.attempt("shooting")
    refined = shot is not None and "refined_from_intervals" in shot.diagnostics.get(
        "shooting", {})
    if (req.objective == "weighted" or refined) and reachable:
        # (a shooting plan found on the finer rung after the first rung's answer missed the
        # goal is not the ladder's: the family may beat it, as it does on a 4-joint goal, 0 + 1
        # reversals against 1 + 1)
        run.attempt("polynomial")
    if shot is None:
        if reachable and not run.plans:
            run.attempt("polynomial")
        if not run.plans and run.searched("shooting") and can_split(req):
            run.attempt_legs()
        if not run.plans:
            run.attempt("penalty")
    return run.finish()


__all__ = ["NOT_A_PROOF", "PAPER_OBJECTIVES", "plan_auto"]
