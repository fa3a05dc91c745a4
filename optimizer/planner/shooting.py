"""Direct multiple shooting on the ORIGINAL model (method ``shooting``).

Why
---
Goals that the paper's family cannot reach (joints that must move in opposite directions, or
no singularity-free ``dphi``) need ``phi`` to reverse. This method solves one small NLP on the
original kinematic model: milliseconds, and, with the deviation term below, paths closer to
the straight line than the minimum-energy plan a user would write.

Transcription (:mod:`.nlp`, region mode ``"hard"``; normalised time ``tau = t / T``)
------------------------------------------------------------------------------------
* equal intervals with piecewise-constant actuator rates ``U = (U1, U2)`` (``u = U / T``),
  node states ``q_k = (phi, th_1..th_n)``, continuity by classical RK4 steps; the number of
  intervals, of steps and the rate bound are a rung of :func:`~.nlp.ladder` (one step per
  interval on 12 intervals for 3 joints, 20 for more, first; 50 of two when that NLP does not
  converge);
* ``q_0`` = the start, ``th(1)`` = the goal; ``phi(1) - phi(0)`` within the request's
  ``phi_change_bounds`` (or equal to ``phi_change``);
* ``th_1..th_n`` inside the region (:class:`~optimizer.region.Region`: ``(0, pi/2)`` for
  ``th_1..th_{n-1}``, intersected with the joint bounds) with a margin of :data:`MARGIN`
  (less when the start or the goal is closer to a bound) at every node;
* objective: ``int |U|^2 dtau + w_dev * S + w_da * S1`` with ``S >=`` the squared distance of
  every interior node's ``(th_1..th_n)`` from the straight line through start and goal (joint
  space) and ``S1 >=`` the squared distance of ``th_1`` from its straight line in time (the
  paper's ``d_a``). The weights are :data:`DEVIATION_WEIGHT`, :data:`D_A_WEIGHT` (more under
  ``tp_then_da``) and 1, or ``weights.d_a`` (both deviations) and ``weights.energy`` of a
  ``weighted`` request. Measured on random goals against the minimum-energy plan, this gives a
  smaller joint-space deviation on about nine goals in ten and never more actuator reversals
  (the tenth: plans with fewer reversals, which the default rule ranks first);
* under the default objective the rates' signs: :func:`~.rungs.rungs` and
  :func:`~.rungs.solve_rungs` (no actuator reversing first; a plan in which ``th_1`` reverses is
  compared with the one in which ``th_1`` may not and ``phi`` may).

Correction onto the exact goal
------------------------------
The NLP's RK4 (one step per interval, rates bounded: :func:`~.nlp.ladder`) is cheap but not
exact: the original model under its rates ends 1e-8 to 1e-5 rad from the goal. Newton steps
(:func:`correct_rates`) on the same RK4 with eight times the steps (within ~1e-12 rad of the
exact model on these rates), with the NLP model's Jacobian, bring that to ~1e-12 rad in one or
two steps; the one quadrature of the exact model in :func:`finish_actuator_plan` then measures
the error the plan really has.

Why nodes are enough for the region
-----------------------------------
On an interval ``u`` is constant: ``th_1`` is linear in time, and ``th_i' = K_i
cos(th_{i-1})^{m_i} u1`` has the sign of ``u1`` while ``th_{i-1}`` stays in ``(0, pi/2)``, so
every joint is monotone on the interval (by induction over ``i``) and its extremes are at the
interval's ends. The continuous path is therefore in the region exactly when the nodes of the
TRUE path are. :func:`finish_actuator_plan` checks them on the re-integrated path (cascade
quadrature of the original model, not the NLP's RK4 nodes) and measures everything on it.

Solvers
-------
fatrop (an interior-point solver for this stage structure, bundled with CasADi) first: about
half IPOPT's time per iteration here. From ``phi`` travelling +0.6 rad, then -0.6 rad
(:data:`ATTEMPTS`); IPOPT from the same guess when fatrop does not converge. Both solve the
same NLP (a test checks that they find the same solution). With compiled functions configured
(:mod:`optimizer.native`: the service does it), fatrop evaluates the first rung's functions as
compiled C once their library is built (:meth:`~.nlp.MultipleShootingNLP.load_native`): the
same iterates, 19-25 % less time per plan; until then, and for the second rung, CasADi's
virtual machine.

Caching, threads, deadline
--------------------------
The NLP and its solvers are built once per robot shape (exponents) and process and cached
(:func:`~.nlp.multiple_shooting_nlp`); start, goal, weights, bounds and gains are parameters.
CasADi objects are not thread-safe: one thread per process (the service runs each solve in a
worker process). No attempt starts after the deadline; IPOPT is stopped by the NLP layer's deadline
callback, fatrop by its iteration cap (:data:`~.solvers.FATROP_MAX_ITER`, tens of milliseconds).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InfeasibleError, InvalidRequestError
from ..problem import PlanRequest
from ..results import Plan
from . import nlp as nlp_layer
from .correction import CORRECTION_TARGET, correct_rates, finish_solution
from .nlp import (D_A_WEIGHT, DEVIATION_WEIGHT, LADDER, LADDER_3_JOINTS, MARGIN,
                  SIGN_SLACK_TOL, MultipleShootingNLP, Transcription, ladder,
                  multiple_shooting_nlp, nlp_for, node_bounds, objective_weights)
from .rungs import LIGHT_SHARE, finish_or_refine, solve_rungs
from .attempts import Attempt, MissedGoal, first_converged
from .base import Capabilities, Method
from .context import PlanContext
from .rules import joint_limits

#: Solver and sign of phi's initial travel of each attempt on a free rung, in order (the
#: first converged solution is returned): from each guess fatrop, then IPOPT, which converges
#: where fatrop reaches its iteration cap.
ATTEMPTS: tuple[tuple[str, float], ...] = (("fatrop", 1.0), ("ipopt", 1.0), ("fatrop", -1.0),
                                           ("ipopt", -1.0))

#: Rates held to signs from a cold start (the sign-held rungs) take the NLP with soft signs
#: (:data:`~.nlp.SIGN_PENALTY`) for these numbers of joints; a polish from a solution's nodes
#: keeps them as bounds. On 3 joints fatrop converged on every sign-held NLP of 20 generated
#: goals (22 of 22): the soft NLP's extra input only costs time. On 5 joints it was mixed: 30 %
#: less time on 12 held-out goals, but on the benchmark's 8 goals two rungs that the bounds
#: solved failed soft (one plan 34 -> 128 ms). From 6 joints the elastic goal already ends
#: such rungs (no gain measured).
SOFT_SIGNS = True
SOFT_SIGNS_JOINTS = frozenset({4})

#: Net travel of phi (rad) of the initial guesses (both signs, see :data:`ATTEMPTS`).
GUESS_PHI_TRAVEL = 0.6


@dataclass(frozen=True)
class ShootingSolution:
    """The NLP's answer in normalised time: node states ``(N+1, n+1)`` and rates ``(N, 2)``."""

    nodes: np.ndarray
    rates: np.ndarray
    status: str
    iterations: int
    start: str
    tried: tuple[dict[str, Any], ...] = ()
    #: The answering solver evaluated compiled functions (optimizer.native).
    compiled: bool = False


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...], *, fixed_phi: bool = False,
            wait: bool = False, native: bool = True) -> MultipleShootingNLP:
    """Build (and cache) the first rung's NLPs of a robot (free; with its rates' signs as
    bounds; with soft signs) ahead of its first request; with compiled functions configured
    (:mod:`optimizer.native`) this also loads their library, or starts its build (``wait``:
    builds it before it returns; ``native`` False: neither, the first solve does). The
    solvers themselves are built at their first solve (compiled once the library is loaded;
    :meth:`~.nlp.MultipleShootingNLP.solver` builds one now). Returns the free one."""
    n = len(gains) + 1
    tr = ladder(n)[0]
    # (the free rung's goal may be elastic where the sign-held rungs' is hard:
    # nlp.FREE_ELASTIC_FROM_JOINTS; the same NLP where both modes agree)
    kinds = [(nlp_layer.default_terminal(n, True), False), (nlp_layer.default_terminal(n), False)]
    if n in SOFT_SIGNS_JOINTS:
        kinds.append((nlp_layer.default_terminal(n), True))
    nlps: list[MultipleShootingNLP] = []
    for terminal, soft in kinds:
        nlp = multiple_shooting_nlp(tuple(float(k) for k in gains),
                                    tuple(int(m) for m in exponents), fixed_phi, tr.intervals,
                                    tr.substeps, terminal=terminal, soft_signs=soft)
        if nlp not in nlps:
            nlps.append(nlp)
    for nlp in nlps:
        if nlp.native_ok and "fatrop" in nlp.solver_names:
            # (10-60 ms: computed once, here, so that processes forked after a warm-up, the
            # service's workers, find their libraries without it)
            nlp.fingerprint("fatrop")
        if native:
            nlp.load_native(every=0.0, wait=wait)
    return nlps[0]


def solve_shooting(req: PlanRequest, deadline: Any, tr: Transcription | None = None,
                   monotone: tuple[float, float] | np.ndarray | None = None,
                   start_nodes: np.ndarray | None = None, light: bool = False,
                   fatrop_settings: tuple[tuple[str, float], ...] = ()) -> ShootingSolution:
    """Solve the NLP of transcription ``tr`` (default: the first rung of
    :func:`~.nlp.ladder`) for ``req`` (normalised time); raise a typed error when it fails.

    Attempts in the order of :data:`ATTEMPTS` (``phi`` travelling +0.6 rad, then -0.6 rad in
    the initial guess; fatrop, then IPOPT from each); the first converged solution is
    returned. Rates of fixed signs (``monotone``: one sign per actuator, or per interval and
    actuator): fatrop alone, one guess, from ``start_nodes`` (node states, ``(N+1, n+1)``)
    when given, else the straight line. ``fatrop_settings``: fatrop's options on this solve
    (an NLP of its own, sharing the compiled functions; the replanner's longer cap).
    """
    if tr is None:
        tr = ladder(req.n)[0]
    # rates held to signs from a cold start: the signs as penalised rows (nlp.SIGN_PENALTY)
    soft = (SOFT_SIGNS and req.n in SOFT_SIGNS_JOINTS and monotone is not None
            and start_nodes is None)
    nlp = nlp_for(req, tr, soft_signs=soft, free=monotone is None,
                  fatrop_settings=fatrop_settings)
    a, b = np.array(req.start), np.array(req.goal)
    lo, hi = node_bounds(req, joint_limits(req))
    lbw, ubw, (lo_phi, hi_phi) = nlp_layer.variable_bounds(req, nlp, tr, lo, hi,
                                                           None if soft else monotone)
    attempts = ATTEMPTS
    if monotone is not None:
        # rates of fixed signs (see rules.monotone_signs): one guess travelling that way (phi
        # free: the way th2, the first joint phi drives, moves) and fatrop alone: rates of
        # fixed signs may be infeasible (th1 must overshoot on some goals), and fatrop's
        # iteration cap bounds the cost of finding out (IPOPT took 0.1-0.2 s to give up on
        # 4-joint goals); the free rungs follow
        first = float(np.asarray(monotone, float).reshape(-1, 2)[0, 0])
        sign = first or float(np.sign(req.goal[1] - req.start[1])) or 1.0
        attempts = (("fatrop", sign),)
    w_dev, w_energy, w_da = objective_weights(req, "shooting")
    if light:  # nearly the minimum-energy plan (see rungs.LIGHT_FROM_JOINTS)
        w_dev, w_da = w_dev * LIGHT_SHARE, w_da * LIGHT_SHARE
    signs = (np.broadcast_to(np.asarray(monotone, float), (tr.intervals, 2)) if soft
             else None)
    p = nlp_layer.parameters(req, w_dev, w_energy, w_da, signs=signs)
    nlp.load_native()

    def tries() -> Any:  # lazily: a guess is built only when its attempt runs
        for name, sign in attempts:
            if start_nodes is not None:
                yield Attempt(name, "the previous solution's nodes",
                              np.clip(nlp.guess_from_nodes(start_nodes, a, b), lbw, ubw))
            else:
                travel = min(max(sign * GUESS_PHI_TRAVEL, lo_phi), hi_phi)
                yield Attempt(name, f"phi travel {travel:+.3g} rad",
                              nlp.guess(a, b, req.phi_start, travel))

    try:
        out = first_converged(nlp, tries(), p, lbw, ubw, deadline, "the shooting NLP",
                              "shooting NLP")
    except MissedGoal as exc:  # its nodes: a start for the next rung (rungs.solve_rungs)
        raise MissedGoal(exc.message, x=exc.x, nodes=nlp.unpack(exc.x)[0],
                         diagnostics=exc.diagnostics) from None
    slack = nlp.sign_slack(out.x)
    if slack > SIGN_SLACK_TOL:  # converged, but only by leaving the signs: out of reach
        tried = [*out.tried[:-1], {**out.tried[-1], "status": f"{out.status} (the rates "
                                   f"leave their signs by {slack:.2g})"}]
        raise InfeasibleError("the rates cannot keep their signs on the way to the goal",
                              diagnostics={"blocking": "nlp_failed", "tried": tried})
    nodes, rates = nlp.unpack(out.x)
    if soft:  # within the slack tolerance of their signs: onto them
        rates = np.where(signs * rates < 0.0, 0.0, rates)
    return ShootingSolution(nodes=nodes, rates=rates, status=f"{out.solver}: {out.status}",
                            iterations=out.iterations, start=out.guess, tried=out.tried,
                            compiled=nlp.compiled and out.solver == "fatrop")


def plan_shooting(req: PlanRequest, deadline: Any) -> Plan:
    """Method ``shooting``: the NLP above, the Newton correction onto the goal of the exact
    model (:func:`correct_rates`), then :func:`finish_actuator_plan`."""
    if req.constraint_points:
        raise InvalidRequestError(
            "method 'shooting' takes no constraint points (they are points of the chained "
            "polynomial inputs: use 'polynomial' or 'constraint_points')",
            field="constraint_points")
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    # the rungs (nlp.rungs): under the default objective rates of fixed signs first (a plan
    # in which no actuator reverses wins whatever its deviation), then free
    sol, tr, mono, tried = solve_rungs(
        req, lambda tr, signs, start=None, light=False: (
            solve_shooting(req, deadline, tr, signs, start, light=True) if light
            else solve_shooting(req, deadline, tr, signs, start)), light_first=True,
        merge_runs=True, time_left=lambda: float(deadline.remaining))
    timing["nlp"] = time.perf_counter() - t0
    deadline.check("the shooting NLP")

    def finish(tr: Transcription, sol: Any, signs: Any, tried: list[dict[str, Any]],
               diagnostics: dict[str, Any]) -> Plan:
        return finish_solution(req, "shooting", nlp_for(req, tr, free=signs is None), sol, tr,
                               signs, tried, timing, diagnostics)

    def solve_finer(tr: Transcription, signs: Any, nodes: np.ndarray) -> Any:
        t1 = time.perf_counter()
        try:
            return solve_shooting(req, deadline, tr, signs, nodes)
        finally:
            timing["nlp"] += time.perf_counter() - t1

    return finish_or_refine(req, tr, sol, mono, tried, finish, solve_finer,
                            lambda: deadline.check("the shooting NLP"))


class ShootingMethod(Method):
    name = "shooting"
    capabilities = Capabilities(constraint_points=False, fixed_phi_change=True,
                                reverses_phi=True, inputs="actuator", via_points=True)
    options = {"ladder": {"3 joints": [dataclasses.asdict(t) for t in LADDER_3_JOINTS],
                          "more joints": [dataclasses.asdict(t) for t in LADDER]},
               "margin": MARGIN,
               "deviation_weight": DEVIATION_WEIGHT, "d_a_weight": D_A_WEIGHT}

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        return plan_shooting(req, ctx.deadline)


__all__ = ["CORRECTION_TARGET", "DEVIATION_WEIGHT", "D_A_WEIGHT", "LADDER", "LADDER_3_JOINTS",
           "MARGIN", "ShootingMethod", "correct_rates", "plan_shooting", "prepare",
           "solve_shooting"]
