"""The penalty-function method (paper Remark 3): the singularity-avoiding inequality as an exact
penalty in the objective instead of hard constraints (method ``penalty``).

Problem
-------
The multiple-shooting transcription of the ORIGINAL model that ``shooting`` solves
(:mod:`.nlp`: piecewise-constant actuator rates, RK4 continuity, start and goal exact, ``dphi``
within the request's bounds; objective ``energy + w_dev S + w_da S1``, the joint-space
deviation and the paper's ``d_a`` of joint 1), built with region mode ``"penalty"``: the region
(every joint inside ``(0, pi/2)`` by default -- for ``th_1..th_{n-1}`` that is where the chained
form is invertible and ``z2 < 0``, eq 13; for ``th_n`` it is this method's default when start
and goal lie there -- intersected with the request's joint bounds, moved in by the transcription's
:data:`~.nlp.MARGIN`) enters as ``rho * sum_k s_k`` with one slack per interior node,
``s_k >= 0`` and ``s_k >=`` the node's largest violation. This is an l1 penalty: exact, i.e. for
``rho`` above the multipliers of the hard constraints its minimisers inside the region are
those of the constrained problem. With ``tp_then_sensitivity`` (or a ``weighted`` request with
``weights.sensitivity``) the objective also has ``||J_R(T)||_F`` of ``s = phi(T) - phi(0)``
(eq 22).

Search
------
* Starts, each for a reason: the caller's plan (``warm_start``; verified, so inside the
  region: the cheapest feasible start there is), then ``shooting``'s straight-line guesses
  (joint-space straight line, inside the region's box; ``phi`` travelling +0.6 rad, then
  -0.6 rad: which way ``phi`` should go first is not known in advance). fatrop from each,
  then IPOPT from each when fatrop does not converge (:data:`SOLVERS`; rates of fixed signs:
  fatrop from the start that travels their way).
* ``rho`` starts at :data:`RHO_START` and is multiplied by :data:`RHO_GROWTH` at most
  :data:`RHO_INCREASES` times, each time warm-started from the last solution, only while that
  solution violates the region by more than :data:`VIOLATION_TOL` at some node. The first
  solution inside is kept; the ladder's finer transcription (:func:`~.nlp.ladder`) is tried
  when every start fails on the first.

Finishing
---------
As ``shooting``'s plans: Newton steps on the exact model move the rates onto the goal
(:func:`~.correction.correct_rates`), then ``finish_actuator_plan`` checks the re-integrated path in
the region (at the interval ends, which suffices for piecewise-constant rates), samples and
measures it. ``plan.diagnostics["penalty"]`` says how large ``rho`` ended
(``penalty_weight``), how far the NLP's nodes were from the region's boundary
(``boundary_distance``, rad, smallest over nodes and joints), the solver's status and
iterations, and every solve (``tried``).

Caching and threads: the NLP and its solvers are built once per robot shape and transcription
(:func:`~.nlp.multiple_shooting_nlp`); one thread per process (CasADi objects are not
thread-safe).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..actuation import ActuatorSchedule
from ..chained_form import chained_form
from ..errors import InfeasibleError, InvalidRequestError, SolverTimeoutError
from ..problem import PlanRequest
from ..region import Region
from ..results import Plan
from ..steering import ChainedPath, InputSchedule
from ..verify import integrate_cascade
from . import nlp as nlp_layer
from .correction import finish_solution
from .nlp import MultipleShootingNLP, Transcription, nlp_for, node_bounds
from .rungs import LIGHT_SHARE, finish_or_refine, solve_rungs
from .solvers import run_solver
from .base import Capabilities, Method
from .context import PlanContext
from .rules import joint_limits, limits_region

#: The penalty weight of the first solve from every start. On the benchmark's ten goals the
#: first solve under 10 ended inside the region on nine (opp3_b needed 100); starting at 100 or
#: 1000 gave the same plans in as many fatrop iterations over the ten (200, 200 and 212).
RHO_START = 10.0
#: Factor of each increase of the penalty weight...
RHO_GROWTH = 10.0
#: ... and at most this many increases per start.
RHO_INCREASES = 2
#: A node outside the penalised set by more than this (rad) is a violation (the NLP's own
#: tolerance is 1e-6; the set is the region moved in by the margin, so such a node is still
#: inside the region itself).
VIOLATION_TOL = 1e-6
#: Weight of ``||J_R(T)||_F`` for ``tp_then_sensitivity`` (against the energy, like the
#: deviation weights).
SENSITIVITY_WEIGHT = 1.0
#: Net travel of phi (rad) of the straight-line starts (as ``shooting``'s guesses).
GUESS_PHI_TRAVEL = 0.6
#: Solvers in order: fatrop from every start, then IPOPT from every start.
SOLVERS = ("fatrop", "ipopt")
#: No solve begins once less than this is left of the deadline (s).
MIN_START_TIME = 1e-3


@dataclass(frozen=True)
class PenaltySolution:
    """The NLP's answer in normalised time, with how it was found."""

    nodes: np.ndarray
    rates: np.ndarray
    rho: float
    violation: float
    status: str
    iterations: int
    start: str
    reason: str
    tried: tuple[dict[str, Any], ...]


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...], *, fixed_phi: bool = False,
            wait: bool = False) -> MultipleShootingNLP:
    """Build (and cache) the first rung's penalty NLP of a robot; with compiled functions
    configured (:mod:`optimizer.native`) this also starts their build (``wait``: builds them
    before it returns)."""
    tr = nlp_layer.ladder(len(gains) + 1)[0]
    nlp = nlp_layer.multiple_shooting_nlp(tuple(float(k) for k in gains),
                                          tuple(int(m) for m in exponents), fixed_phi,
                                          tr.intervals, tr.substeps, "penalty")
    nlp.load_native(every=0.0, wait=wait)
    return nlp


def penalised_region(req: PlanRequest) -> Region:
    """The region the penalty keeps the nodes in: every joint within its limits
    (:func:`~.rules.joint_limits`, ``th_n`` included)."""
    return limits_region(req)


def sensitivity_weight(req: PlanRequest) -> float:
    """Weight of ``||J_R(T)||_F`` in the objective for ``req``'s objective."""
    if req.objective == "tp_then_sensitivity":
        return SENSITIVITY_WEIGHT
    if req.objective == "weighted":
        return float(req.weights.sensitivity)
    return 0.0


def warm_start_nodes(req: PlanRequest, warm_start: ActuatorSchedule | InputSchedule,
                     intervals: int) -> np.ndarray | None:
    """The states ``(intervals + 1, n + 1)`` of a plan's path at the nodes of the
    transcription (equal intervals of normalised time), or None when they cannot be had.

    Actuator rates are integrated on the original model (cascade quadrature); chained inputs
    are mapped back from the chained path (the inverse map, valid inside the region).
    """
    tau = np.linspace(0.0, 1.0, intervals + 1)
    if isinstance(warm_start, ActuatorSchedule):
        T = warm_start.duration
        rep = integrate_cascade(req.robot, warm_start.u, req.q_start(), T, tau * T,
                                warm_start.breaks, fallback=warm_start.u_scalar)
        return np.asarray(rep.q, float) if rep.success else None
    cf = chained_form(req.robot)
    path = ChainedPath.from_inputs(cf.to_chained(req.q_start()), warm_start)
    inv = cf.from_chained(path.z(tau))
    return np.asarray(inv.q, float) if bool(np.all(inv.valid)) else None


def _starts(req: PlanRequest, nlp: MultipleShootingNLP, lbw: np.ndarray, ubw: np.ndarray,
            phi_range: tuple[float, float],
            warm_start: ActuatorSchedule | InputSchedule | None
            ) -> list[tuple[str, str, np.ndarray]]:
    """``(name, reason, x0)`` of every start, in order (see the module docstring)."""
    a, b = np.array(req.start), np.array(req.goal)
    out: list[tuple[str, str, np.ndarray]] = []
    if warm_start is not None:
        Q = warm_start_nodes(req, warm_start, nlp.N)
        if Q is not None:
            kind = ("actuator rates" if isinstance(warm_start, ActuatorSchedule)
                    else "chained inputs, mapped to joint space")
            out.append(("warm_start", f"the caller's verified plan ({kind}): inside the region",
                        np.clip(nlp.guess_from_nodes(Q, a, b), lbw, ubw)))
    travels: list[float] = []
    for sign in (1.0, -1.0):
        travel = min(max(sign * GUESS_PHI_TRAVEL, phi_range[0]), phi_range[1])
        if travel in travels:  # a fixed or one-signed dphi: the other guess is the same
            continue
        travels.append(travel)
        out.append((f"straight line, phi travel {travel:+.3g} rad",
                    "joint-space straight line (inside the region's box); phi "
                    + ("forward first" if sign > 0 else "backward first"),
                    nlp.guess(a, b, req.phi_start, travel)))
    return out


def violation(nodes: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Largest distance (rad) of a node's joint outside ``[lo, hi]`` (0 inside)."""
    th = nodes[:, 1:]
    return float(max(0.0, np.max(lo - th), np.max(th - hi)))


def solve_penalty(req: PlanRequest, deadline: Any, tr: Transcription | None = None, *,
                  warm_start: ActuatorSchedule | InputSchedule | None = None,
                  rate_signs: tuple[float, float] | np.ndarray | None = None,
                  start_nodes: np.ndarray | None = None, light: bool = False
                  ) -> PenaltySolution:
    """Solve the penalty NLP of transcription ``tr`` for ``req`` (normalised time), raising
    ``rho`` while the solution violates the region; raise a typed error when it fails.

    ``rate_signs``: one sign per actuator, or per interval and actuator (0: either);
    ``start_nodes``: node states ``(N+1, n+1)`` to start from instead of the usual starts;
    ``light``: the deviation weights times :data:`~.rungs.LIGHT_SHARE` (as ``shooting``).

    Raises
    ------
    SolverTimeoutError
        The deadline passed before a solution inside the region was found.
    InfeasibleError
        No start gave a solution inside the region.
    """
    if tr is None:
        tr = nlp_layer.ladder(req.n)[0]
    nlp = nlp_for(req, tr, "penalty")
    lo, hi = node_bounds(req, joint_limits(req))
    lbw, ubw, phi_range = nlp_layer.variable_bounds(req, nlp, tr, rate_signs=rate_signs)
    w_dev, w_en, w_da = nlp_layer.objective_weights(req, "penalty")
    if light:
        w_dev, w_da = w_dev * LIGHT_SHARE, w_da * LIGHT_SHARE
    w_sens = sensitivity_weight(req)
    starts = _starts(req, nlp, lbw, ubw, phi_range, warm_start)
    nlp.load_native()
    solvers = [s for s in SOLVERS if s in nlp.solver_names]
    if rate_signs is not None:
        # rates of fixed signs may be infeasible: fatrop's iteration cap bounds the cost of
        # finding out (the free rungs follow), from the one start that travels their way
        solvers = solvers[:1]
        first = float(np.asarray(rate_signs, float).reshape(-1, 2)[0, 0])
        sign = first or float(np.sign(req.goal[1] - req.start[1])) or 1.0
        straight = [st for st in starts if st[0] != "warm_start"]
        keep = [st for st in straight if (sign > 0) == ("+" in st[0])] or straight[:1]
        starts = [st for st in starts if st[0] == "warm_start"] + keep
    if start_nodes is not None:
        a, b = np.array(req.start), np.array(req.goal)
        starts = [("previous_solution", "the previous solution's nodes (its rates' signs "
                   "held: see nlp.solve_rungs)",
                   np.clip(nlp.guess_from_nodes(start_nodes, a, b), lbw, ubw))]
    tried: list[dict[str, Any]] = []
    for solver in solvers:
        for name, reason, x0 in starts:
            rho = RHO_START
            for _ in range(RHO_INCREASES + 1):
                if deadline.remaining <= MIN_START_TIME:
                    raise _timeout(deadline, tried)
                p = nlp_layer.parameters(req, w_dev, w_en, w_da, (w_sens, rho, lo, hi))
                out = run_solver(nlp, solver, x0, p, lbw, ubw, deadline.remaining)
                entry: dict[str, Any] = {"solver": solver, "start": name, "rho": rho,
                                         "status": out.status, "iterations": out.iterations}
                tried.append(entry)
                if out.kind == "timeout":
                    raise _timeout(deadline, tried)
                if not out.success or out.x is None:
                    break
                nodes, rates = nlp.unpack(out.x)
                entry["violation"] = viol = violation(nodes, lo, hi)
                if viol <= VIOLATION_TOL:
                    return PenaltySolution(nodes=nodes, rates=rates, rho=rho, violation=viol,
                                           status=f"{solver}: {out.status}",
                                           iterations=out.iterations, start=name,
                                           reason=reason, tried=tuple(tried))
                rho *= RHO_GROWTH
                x0 = out.x
    if not tried:
        raise _timeout(deadline, tried)
    raise InfeasibleError("the penalty NLP found no path inside the region from any start: "
                          + "; ".join(f"{t['solver']} from {t['start']} (rho {t['rho']:g}): "
                                      f"{t['status']}" for t in tried),
                          diagnostics={"blocking": "nlp_failed", "tried": tried})


def _timeout(deadline: Any, tried: list[dict[str, Any]]) -> SolverTimeoutError:
    return SolverTimeoutError(
        f"the penalty NLP found no path within the time limit of {deadline.seconds:g} s",
        field="time_limit", diagnostics={"stage": "penalty NLP", "tried": tried})


def plan_penalty(req: PlanRequest, deadline: Any, *,
                 warm_start: ActuatorSchedule | InputSchedule | None = None) -> Plan:
    """Plan with the penalty-function NLP (see the module docstring).

    Parameters
    ----------
    req : PlanRequest
        Uses start, goal, robot, objective and weights, joint bounds, ``phi_change`` or its
        bounds, duration and actuator limits, samples. The region is always the full one (the
        ``z2`` criterion is implied by it).
    deadline : Deadline
        Wall-clock budget shared with the caller.
    warm_start : ActuatorSchedule or InputSchedule, optional
        A verified plan's inputs (e.g. ``auto``'s polynomial optimum): converted to node states
        of the transcription (:func:`warm_start_nodes`) and solved from first.

    Returns
    -------
    Plan
        ``method == "penalty"``, piecewise-constant actuator rates, verified on the original
        model by ``finish_actuator_plan``.

    Raises
    ------
    InvalidRequestError
        Constraint points (points of chained polynomial inputs, which this method has not).
    SolverTimeoutError, InfeasibleError, NumericalError
    """
    if req.constraint_points:
        raise InvalidRequestError(
            "method 'penalty' takes no constraint points (they are points of the chained "
            "polynomial inputs: use 'polynomial' or 'constraint_points')",
            field="constraint_points")
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    sol, tr, signs, tried = solve_rungs(
        req, lambda tr, rate_signs, start=None, light=False: solve_penalty(
            req, deadline, tr, warm_start=warm_start, rate_signs=rate_signs, start_nodes=start,
            light=light), light_first=True)
    timing["nlp"] = time.perf_counter() - t0
    deadline.check("the penalty NLP")
    region = penalised_region(req)

    def finish(tr: Transcription, sol: PenaltySolution, signs: Any,
               tried: list[dict[str, Any]], diagnostics: dict[str, Any]) -> Plan:
        th = sol.nodes[:, 1:]
        distance = float(np.min(np.minimum(th - region.lower, region.upper - th)))
        return finish_solution(
            req, "penalty", nlp_for(req, tr, "penalty"), sol, tr, signs, tried, timing,
            {"penalty_weight": sol.rho,
             "boundary_distance": distance if math.isfinite(distance) else None,
             "violation": sol.violation, "start_reason": sol.reason, **diagnostics})

    def solve_finer(tr: Transcription, signs: Any, nodes: np.ndarray) -> PenaltySolution:
        t1 = time.perf_counter()
        try:
            return solve_penalty(req, deadline, tr, rate_signs=signs, start_nodes=nodes)
        finally:
            timing["nlp"] += time.perf_counter() - t1

    return finish_or_refine(req, tr, sol, signs, tried, finish, solve_finer,
                            lambda: deadline.check("the penalty NLP"))


class PenaltyMethod(Method):
    name = "penalty"
    capabilities = Capabilities(constraint_points=False, fixed_phi_change=True,
                                reverses_phi=True, inputs="actuator", via_points=True)
    options = {"rho_start": RHO_START, "rho_growth": RHO_GROWTH,
               "rho_increases": RHO_INCREASES, "solvers": SOLVERS}

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        return plan_penalty(req, ctx.deadline, warm_start=ctx.warm_start)


__all__ = ["PenaltyMethod", "PenaltySolution", "plan_penalty", "penalised_region", "prepare",
           "solve_penalty",
           "warm_start_nodes"]
