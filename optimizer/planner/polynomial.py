"""Method ``polynomial``: the paper's family (``v1 = b0``, ``v2`` polynomial, the request's
constraint points), its singularity-free ``dphi`` intervals (§3.4), then the objective (§4,
§5.3, or the default geometric rule)."""

from __future__ import annotations

import math
import time

from ..errors import InfeasibleError, SolverTimeoutError
from ..problem import PlanRequest
from ..results import Plan
from .base import Capabilities, Method
from .context import Deadline, PlanContext
from .family import PolynomialFamily, family_for
from .finish import finish_plan
from .intervals import feasible_intervals
from .objectives import optimise
from .rules import phi_search_bounds


def plan_polynomial(req: PlanRequest, deadline: Deadline) -> Plan:
    """The paper's method: intervals of dphi, then the objective."""
    timing: dict[str, float] = {}
    fam = family_for(req, deadline)
    t0 = time.perf_counter()
    if req.phi_change is not None:
        fam.inputs(float(req.phi_change))  # raises SingularSystemError for dphi = 0 (Remark 2)
        e = fam.evaluate(float(req.phi_change))
        timing["search"] = time.perf_counter() - t0
        if not e.ok:
            chk = fam.check(float(req.phi_change))
            near = closest_feasible(fam, float(req.phi_change), deadline)
            raise InfeasibleError(
                f"phi_change = {req.phi_change:.6g} rad gives a path that leaves the "
                f"singularity-free region ({req.singularity} criterion)"
                + (f" at t/T = {chk.first_crossing_tau:.6g}"
                   if chk.first_crossing_tau is not None else "")
                + (f"; the closest feasible phi_change is {near:.6g} rad" if near is not None
                   else ""),
                diagnostics={"margin": chk.margin, "first_crossing_tau": chk.first_crossing_tau,
                             "blocking": "singularity", "closest_feasible_phi_change": near})
        feasible: list[tuple[float, float]] = []
        best = e
    else:
        lo, hi = phi_search_bounds(req)
        feasible = feasible_intervals(fam, lo, hi)
        timing["intervals"] = time.perf_counter() - t0
        deadline.check("the interval search")
        if not feasible:
            near = closest_feasible(fam, 0.5 * (lo + hi), deadline, exclude=(lo, hi))
            raise InfeasibleError(
                f"no phi_change in [{lo:.6g}, {hi:.6g}] rad gives a singularity-free path of "
                "the polynomial family"
                + (f"; the closest feasible phi_change outside these bounds is {near:.6g} rad"
                   if near is not None else ""),
                diagnostics={"blocking": "no_feasible_phi_change", "searched": [lo, hi],
                             "closest_feasible_phi_change": near})
        t1 = time.perf_counter()
        best_e = optimise(fam, feasible, req.objective, req.weights)
        timing["objective"] = time.perf_counter() - t1
        deadline.check("the objective search")
        if best_e is None:
            raise InfeasibleError("the feasible intervals are too narrow to hold a path",
                                  diagnostics={"feasible_phi_changes": feasible})
        best = best_e
    inputs = fam.inputs(best.dphi)
    return finish_plan(req, inputs, "polynomial", feasible, timing,
                       {"objective": req.objective, "singularity": req.singularity})


def closest_feasible(fam: PolynomialFamily, target: float, deadline: Deadline,
                      exclude: tuple[float, float] | None = None) -> float | None:
    """The feasible dphi in [-pi, pi] closest to ``target`` (outside ``exclude``), or None.

    Only attempted while at least half of the request's time remains.
    """
    if deadline.remaining < 0.5 * deadline.seconds:
        return None
    try:
        ivs = feasible_intervals(fam, -math.pi, math.pi)
    except SolverTimeoutError:
        return None
    best: float | None = None
    for a, b in ivs:
        # a point a hair inside the interval (its ends are on the boundary)
        eps = min(1e-6, 0.25 * (b - a))
        for x in (min(max(target, a + eps), b - eps), a + eps, b - eps):
            if exclude is not None and exclude[0] <= x <= exclude[1]:
                continue
            if best is None or abs(x - target) < abs(best - target):
                best = x
    return best


class PolynomialMethod(Method):
    name = "polynomial"
    capabilities = Capabilities(constraint_points=True, fixed_phi_change=True,
                                reverses_phi=False, inputs="chained")

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        return plan_polynomial(req, ctx.deadline)
