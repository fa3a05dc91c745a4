"""Constraint-point synthesis as a convex QP (issue 3.3): the paper's trial and error, automated.

The paper's §3.3 avoids the transformation singularity by *choosing* constraint points
``(t_j, z_i(t_j))`` by hand and re-solving eq (11) until the path is singularity-free. Here the
choice is made by a QP.

The method is assembled from four modules of one concept each:

* :mod:`.constraint_qp`: the QP with cuts at one ``dphi`` (formulation, cuts, margins);
* :mod:`.level_cuts`: the cutting planes of the non-affine region conditions;
* :mod:`.legendre_qp`: the orthonormal basis of ``V2``, the grid and the Clarabel solve;
* :mod:`.dphi_scan`: the range of ``dphi``, the scan, its ranking and refinement.

Here: the entry point (checks of the request, the ladder of extra degrees, the report).

The §3.3 example (th from [1, 1, 1] to [30, 30, 30] deg, prototype robot): th2 must rise 29 deg
at a rate <= K2 |u1|, and th3's gain is largest when th2 stays at 1 deg as long as possible and
smallest when it rises at once, which bounds ``dphi`` to (45.0, 51.6) deg for ANY input; the
paper's member crosses ``z2 = 0`` twice (its Fig 4) for dphi < 45.46 deg. So the paper's
situation exists only in (45.0, 45.46) deg: at 45.3 deg the QP (m = 4, one cut round) gives a
path with margin 0.40 deg (th1 starts at 1 deg) in ~15 ms of synthesis. The QP is feasible on
[45.2, 50.2] deg (m = 4; to 50.7 with m = 6) against the family's [45.46, 47.53].

Constraint points, as the paper would state them: ``m`` extra coefficients are fixed by ``m``
points; ``diagnostics["constraint_points"]["points"]`` lists ``z2`` of the QP path at
``t_j = j T / (m + 1)``. Given to :func:`optimizer.steering.solve_polynomial` (eq 11) they
reproduce the QP's ``V2`` (the relative reproduction error is reported; ~1e-12).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..errors import InfeasibleError, SingularSystemError
from ..problem import PlanRequest
from ..results import Plan
from ..steering import ChainedPath, ConstraintPoint, solve_polynomial
from .base import Capabilities, Method
from .constraint_qp import (EXTRA_DEGREES, GRID_POINTS, MAX_CUT_ROUNDS, ConstraintPointQP,
                            Synthesis)
from .context import Deadline, PlanContext
from .dphi_scan import (dphi_scan_range, evaluate_dphi, family_intervals, motion_sign,
                        necessary_dphi_range, search_dphi)
from .finish import finish_plan
from .legendre_qp import BACKEND
from .rules import direction_conflict


def plan_constraint_points(req: PlanRequest, deadline: Deadline) -> Plan:
    """Constraint-point synthesis: the QP with cuts, over ``dphi``, then the verified plan.

    Parameters
    ----------
    req : PlanRequest
        ``phi_change`` fixes ``dphi``; otherwise ``phi_change_bounds`` are scanned. The request's
        own constraint points are kept as equalities.
    deadline : Deadline

    Returns
    -------
    Plan
        Method ``"constraint_points"``; ``diagnostics["constraint_points"]`` holds the
        synthesized constraint points, QP status, cut rounds, margins and the scan.

    Raises
    ------
    InfeasibleError
        Opposite joint motions, a ``phi_change`` of the wrong sign or too small, or no ``dphi``
        with a singularity-free QP path (with every degree of :data:`EXTRA_DEGREES`).
    SolverTimeoutError
        The deadline passed between solves.
    """
    timing: dict[str, float] = {}
    t_start = time.perf_counter()
    conflict = direction_conflict(req)
    if conflict:
        raise InfeasibleError(conflict, diagnostics={"blocking": "opposite_joint_motion"})
    lo, hi, dmin, dmax = dphi_scan_range(req)
    _, _, why = necessary_dphi_range(req)
    necessary = {"min_abs_phi_change": dmin, "max_abs_phi_change": dmax if math.isfinite(dmax)
                 else None}
    if why is not None:
        raise InfeasibleError(why, diagnostics={"blocking": "constant_v1_cannot_reach_goal",
                                                **necessary})
    sgn = motion_sign(req)
    if req.phi_change is not None:
        dphi = float(req.phi_change)
        if not dmin < sgn * dphi < dmax:
            need = "positive" if sgn > 0 else "negative"
            raise InfeasibleError(
                f"phi_change = {dphi:.6g} rad cannot reach the goal with a constant v1: it must be "
                f"{need} with {dmin:.6g} < |phi_change| < {dmax:.6g} rad (each th_i moves "
                "monotonically at a rate bounded by its neighbours' start and goal values)",
                diagnostics={"blocking": "phi_change_outside_necessary_range", **necessary})
    elif not lo < hi:
        raise InfeasibleError(
            f"phi_change_bounds {list(req.phi_change_bounds)} contain no phi_change of the right "
            f"sign with {dmin:.6g} < |phi_change| < {dmax:.6g} rad, the range a constant v1 needs",
            diagnostics={"blocking": "no_feasible_phi_change", **necessary})

    attempts: list[dict[str, Any]] = []
    seeds: list[tuple[float, float]] | None = None
    chosen: Synthesis | None = None
    qp: ConstraintPointQP | None = None
    scanned: dict[str, Any] = {}
    for m in EXTRA_DEGREES:
        deadline.check("constraint-point synthesis")
        qp = ConstraintPointQP(req, extra_degrees=m)
        if req.phi_change is not None:
            s = evaluate_dphi(qp, req, float(req.phi_change))
            attempts.append({"extra_degrees": m, "phi_change": s.dphi, "reason": s.reason})
            if s.ok:
                chosen = s
                break
            continue
        if seeds is None:
            t_fam = time.perf_counter()
            seeds = family_intervals(req, lo, hi)
            timing["family_intervals"] = time.perf_counter() - t_fam
        chosen, scanned = search_dphi(qp, req, lo, hi, deadline, seeds)
        attempts.append({"extra_degrees": m, "searched": [lo, hi], **scanned})
        if chosen is not None:
            break
    timing["synthesis"] = time.perf_counter() - t_start
    if chosen is None or qp is None:
        if req.phi_change is not None:
            msg = (f"phi_change = {req.phi_change:.6g} rad: no singularity-free path with V2 of "
                   f"degree up to {req.n - 1 + EXTRA_DEGREES[-1] + len(req.constraint_points)}: "
                   + attempts[-1]["reason"])
        else:
            top = req.n - 1 + EXTRA_DEGREES[-1] + len(req.constraint_points)
            msg = (f"no phi_change in [{lo:.6g}, {hi:.6g}] rad gives a singularity-free path with "
                   f"V2 of degree up to {top}"
                   + (f" (most common reason: {attempts[-1].get('common_reason')})"
                      if attempts and attempts[-1].get("common_reason") else ""))
        raise InfeasibleError(msg, diagnostics={"blocking": "constraint_point_qp_infeasible",
                                                "attempts": attempts})
    deadline.check("constraint-point synthesis")
    assert chosen.inputs is not None
    diag = {"objective": req.objective, "singularity": req.singularity,
            "constraint_points": _report(qp, chosen, scanned, attempts)}
    return finish_plan(req, chosen.inputs, "constraint_points", list(seeds or []), timing, diag)



def _report(qp: ConstraintPointQP, s: Synthesis, scanned: dict[str, Any],
            attempts: list[dict[str, Any]]) -> dict[str, Any]:
    """The synthesized constraint points as the paper would state them, plus the QP facts."""
    assert s.inputs is not None
    T = qp.T
    m = qp.m
    path = ChainedPath.from_inputs(qp.z0, s.inputs)
    times = [T * (j + 1) / (m + 1) for j in range(m)]
    z2 = path.z(np.array(times) / T)[:, 1]
    pts = [ConstraintPoint(t, 2, float(v)) for t, v in zip(times, z2)]
    try:
        rep = solve_polynomial(s.dphi, qp.n, qp.z0, qp.zT, T, tuple(qp.points) + tuple(pts))
        reproduction = float(np.max(np.abs(rep.v2[0] - s.inputs.v2[0]))
                             / max(1.0, float(np.max(np.abs(s.inputs.v2[0])))))
    except SingularSystemError:
        reproduction = None
    return {
        "points": [{"time": p.time, "state": p.state, "value": p.value} for p in pts],
        "points_reproduce_v2_rel_error": reproduction,
        "request_points": [{"time": p.time, "state": p.state, "value": p.value}
                           for p in qp.points],
        "phi_change": s.dphi,
        "extra_degrees": m,
        "v2_degree": qp.p - 1,
        "qp_objective": qp.objective,
        "qp_status": s.status,
        "qp_solves": s.qp_solves,
        "cut_rounds": s.rounds,
        "cuts": s.cuts,
        "qp_energy": s.energy,
        "region_margin": s.region_margin,
        "argmin_tau": s.argmin_tau,
        "angle_margin_target": s.angle_margin,
        "sign_margin": s.sign_margin,
        "plain_member_feasible": s.plain_ok,
        "plain_member_energy": s.plain_energy,
        "grid_points": int(qp.grid.size),
        "backend": BACKEND,
        "qp_solve_time": s.solve_time,
        "scan": scanned,
        "attempts": attempts,
        "source": s.source,
    }


class ConstraintPointsMethod(Method):
    name = "constraint_points"
    capabilities = Capabilities(constraint_points=True, fixed_phi_change=True,
                                reverses_phi=False, inputs="chained")
    options = {"extra_degrees": EXTRA_DEGREES, "grid_points": GRID_POINTS,
               "max_cut_rounds": MAX_CUT_ROUNDS}

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        return plan_constraint_points(req, ctx.deadline)
