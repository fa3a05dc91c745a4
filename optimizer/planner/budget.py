"""A reversal budget and the whole trade-off between actuator reversals and deviation.

A user who allows ``max_reversals`` direction changes (of ``phi`` and ``th_1`` together, counted
as the answer counts them: :attr:`~optimizer.indicators.Indicators.reversals`) asks for the
straightest verified path with at most that many; ``pareto`` asks for the non-dominated set
over ``(reversals, deviation)``. Both come from one set of candidates, each a verified plan of
the ``shooting`` transcription (:mod:`.nlp`), finished by the one finishing path
(:func:`~.nlp.finish_solution`: the Newton correction onto the goal, then the re-integration of
the original model in the handed-out form):

1. **the plan the objective picks** (the caller's: ``auto`` or the method asked for), under the
   default objective the ladder's fewest-reversal plan; under another objective that plan
   too (the objective's may reverse far more: ``weighted`` 9 times where the default 3, and
   the merging below looks for no fewer reversals than the first candidates have);
2. **the straightest**: the transcription with free rate signs on :data:`BUDGET_TRANSCRIPTION`
   (30 intervals: more switching than the ladder's first rung allows), its deviation epigraph
   bounding the squared distance from the SEGMENT start -> goal (the answer's ``deviation``;
   :data:`~.nlp.DEVIATION_MODES`) of every node and of every interval's midpoint
   (:data:`DEVIATION_POINTS`: with the nodes alone the path bulged between them), weighted
   :data:`FREE_DEVIATION_WEIGHT` (a thousand times the default's: the energy then only makes
   the rates unique). Its plan has the most reversals ``R_free`` and the smallest deviation
   found;
3. **fewer reversals, bought back**: the straightest plan's sign pattern (per interval and
   actuator) has runs; merging the run that travels least into its neighbours (it takes their
   sign) removes one reversal (a run at an end) or two (inside), for the least loss of the
   motion that bought straightness. The sign-held NLP (the rungs' machinery: every interval's
   rates held to the pattern's signs, from the previous solution's nodes, by fatrop below 5
   joints, else or where fatrop fails by IPOPT: :data:`HELD_SOLVERS`) gives the straightest
   plan of that pattern; merging goes on until no run is left to merge or the count reaches
   the first candidate's. When a pattern's NLP fails (the goal needs that run: ``th_1`` must
   move its way, or ``phi`` must reverse) the next-smallest run is merged instead.

An NLP answer whose nodes alone are no straighter than the first candidate (which has no more
reversals than any other) is no front member: it is not finished and the merging stops there
(:func:`_dominated`).

Each candidate is kept only when it is verified; the front is the candidates sorted by
reversals, each kept when its deviation is smaller than every one with fewer reversals (by more
than :data:`DEVIATION_TOLERANCE`). ``max_reversals = k`` answers the front's member with the
most reversals ``<= k`` (the straightest); none: :class:`~optimizer.errors.InfeasibleError`
naming ``max_reversals`` and the fewest reversals found. A ``k`` below the first candidates'
fewest reversals (the ladder's plan: the fewest the planner finds) is refused so before any
of the budget's NLPs runs: the merging stops at that count.

Cost: one plan for the first candidate, two free NLPs (IPOPT, 40-200 iterations; the second
fatrop below 5 joints), then one sign-held NLP (30-90 iterations) and one finishing per other
candidate, and one NLP per failed merge. The NLP and its solvers are built once per robot
shape (exponents; the gains are parameters) and transcription per process (:func:`prepare`,
:func:`~.nlp.multiple_shooting_nlp`): start, goal,
weights, bounds and signs are parameters and bounds, and every solve runs on a memory that
answers as a fresh one (:meth:`~.nlp.MultipleShootingNLP.solver_call`), so nothing of one
request reaches the next (tests/test_budget_purity.py). Measured
(``diagnostics.budget.tried`` records each NLP's and each finishing's CPU seconds;
:mod:`bench.budget` sums them): the NLPs take about 90 % of the front. Of an IPOPT solve of 3
joints about 65 % is IPOPT's own work, mostly its sparse solver MUMPS (1.2-1.5 ms per
iteration on this KKT system of some 500 rows; its options and the SPRAL solver did not
help), 30 % the functions' evaluation. fatrop takes about half IPOPT's time per iteration in
CasADi's virtual machine. Compiled (:mod:`optimizer.native`), fatrop's functions took 7 of a
3-joint solve's 31-44 ms (61 iterations): its own work, about 0.5 ms per iteration, stays; and
the C of these NLPs (3.3, 4.8 and 12.6 MB for 3, 4 and 5 joints, with the correction's
maps) is over the size :mod:`optimizer.native` compiles (the 3-joint one took 75 s to compile).
A member still costs several default plans (docs/benchmark-budget.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InfeasibleError, NumericalError, PlannerError
from ..indicators import ACTUATOR_DEAD_BAND
from ..problem import PlanRequest
from ..results import Plan, ParetoMember
from . import nlp as nlp_layer
from .context import PlanContext
from .correction import finish_solution
from .nlp import D_A_WEIGHT, Transcription, node_bounds
from .rungs import merge, runs, th1_reach_ok
from .attempts import Attempt, first_converged
from .ranking import best
from .rules import joint_limits, monotone_reach_ok, monotone_signs
from .shooting import GUESS_PHI_TRAVEL, ShootingSolution

#: Weight of the squared joint-space deviation (rad^2) against the input energy in the
#: budget's NLPs (the default plan's is 30): 1 deg of deviation then costs about 9, the energy
#: of a move of about 3 rad. On the 3-joint goal [10, 20, 30] -> [40, 25, 15] deg (50
#: intervals) the straightest deviation was 20.0, 14.5 and 13.5 deg at weights 3e3, 3e4 and
#: 3e5 (line distance), at 3e4 and 3e5 the same 7.3 deg (segment distance).
FREE_DEVIATION_WEIGHT = 30000.0
#: The transcription of the budget's NLPs: 30 intervals of one RK4 step, rates up to 20 rad
#: per T (2/3 rad per interval, as the first rung's 0.5). Measured on 10 generated 3-joint
#: goals against 50 intervals of two steps (the ladder's second rung): the straightest
#: candidate within 0.3 deg of it on all 10 (closer to the min-max peer on 3, farther on 4),
#: each NLP about a third of the time. From :data:`TWO_STEPS_FROM_JOINTS` joints two steps
#: per interval (:func:`budget_transcription`).
BUDGET_TRANSCRIPTION = Transcription(30, 1, 20.0)
#: From this many joints the budget's NLPs take two RK4 steps per interval. With one, the NLP's
#: model ended 8.5e-6 rad from the exact model's goal on 5-joint goals (weak bracket directions
#: carry that miss), and the Newton correction, whose Jacobian is that model's, moved away
#: (8.5e-6 -> 4e-4 -> 1.6e-5 rad after its four steps): on the bench's goal r5_003 both
#: straightest candidates were dropped unverified, and the front was the 0-reversal plan alone
#: (2.97 deg, the min-max peer 2.70 at 12 reversals). With two steps the same NLP ended
#: 1.4e-6 rad away and the correction reached 3e-10.
TWO_STEPS_FROM_JOINTS = 5


def budget_transcription(n: int) -> Transcription:
    """The transcription of the budget's NLPs for ``n`` joints: :data:`BUDGET_TRANSCRIPTION`,
    with two RK4 steps per interval from :data:`TWO_STEPS_FROM_JOINTS` joints."""
    tr = BUDGET_TRANSCRIPTION
    if n >= TWO_STEPS_FROM_JOINTS:
        return Transcription(tr.intervals, 2 * tr.substeps, tr.rate_bound)
    return tr


#: Inner points per interval (its midpoint) where the deviation epigraph bounds the distance
#: too, besides the nodes. With the nodes alone the NLP bought straightness the path does not
#: have: it returned to the segment at the nodes and bulged between them (on a 3-joint goal the
#: nodes' largest distance 2.04 deg, the re-integrated path's 4.30 deg; with the midpoint
#: 3.10 and 3.40, with three inner points 3.27 and 3.27). On 20 generated 3-joint goals of a
#: seed the bench does not use, ``max_reversals`` = the min-max peer's count came within
#: 0.25 deg of the peer on 18 without, 20 with the midpoint (the front's time +28 %).
DEVIATION_POINTS = 1
#: Solvers of the free NLPs (the straightest), tried in order: IPOPT. fatrop (below) found
#: other local optima from the straight line: on three generated 3-joint goals its
#: straightest lost two reversals for 0.18 deg (9 reversals at 1.02 deg became 6 at 1.20).
FREE_SOLVERS = ("ipopt",)
#: ... and of the second free NLP (phi's other direction; the straighter verified one of the
#: two is kept, so a worse local optimum here costs nothing): fatrop first, as the held NLPs.
SECOND_FREE_SOLVERS = ("fatrop", "ipopt")
#: Solvers of the sign-held NLPs (every merge, from the previous candidate's nodes), tried in
#: order, below :data:`FATROP_BELOW_JOINTS` joints: fatrop (the structure-exploiting interior
#: point method, about half IPOPT's time per iteration here in CasADi's virtual machine:
#: IPOPT's sparse solver MUMPS alone took 1.2-1.5 ms per iteration of a 3-joint NLP, whose KKT
#: system has some 500 rows), with :data:`FATROP_SETTINGS` and the objective scaled by
#: :data:`FATROP_OBJECTIVE_SCALE`; then IPOPT (unscaled: it scales its problem itself) where
#: fatrop fails. From :data:`FATROP_BELOW_JOINTS` joints IPOPT alone.
HELD_SOLVERS = ("fatrop", "ipopt")
#: fatrop on the 5-joint NLPs (two RK4 steps per interval): it failed on 15 of the 18 NLPs of
#: two generated fronts (150 iterations, about 0.6 s each) at every scale tried.
FATROP_BELOW_JOINTS = 5
#: fatrop's options on the budget's NLPs (its defaults elsewhere: mu_init 1, 60 iterations).
#: Measured on the 25 NLPs of three generated 3-joint fronts (scaled as below): mu_init 0.1
#: converged on 25, 1452 iterations in all; mu_init 1 on 23, 1761 (IPOPT: 25, 1074, its time
#: 1.4 times fatrop's); the largest count 148, hence the cap.
FATROP_SETTINGS: tuple[tuple[str, float], ...] = (("mu_init", 0.1), ("max_iter", 150))
#: The budget's NLPs take the goal elastic from this many joints (the default's from
#: :data:`~.nlp.ELASTIC_FROM_JOINTS`): with the goal elastic, the straightest NLP of a
#: 5-joint goal converged 6.6e-7 and 6.7e-7 rad off the goal from both guesses (IPOPT, 152 and
#: 192 iterations, 1.6 s), so the front kept only the default plan, where with the goal hard
#: it ended on the goal.
ELASTIC_FROM_JOINTS = 6
#: With the goal elastic the objective's weights are divided by this: the goal's exact
#: penalty (:data:`~.nlp.ELASTIC_WEIGHT`) was chosen against the default NLP's weights, and
#: the budget's deviation weight is :data:`FREE_DEVIATION_WEIGHT`, a thousand times the
#: default's; at full weight the penalty was not exact. On 12 generated goals of 6 to 8 joints
#: (seed 606) the straightest NLP then converged 4e-7 to 1e-4 rad off the goal, and sign-held
#: merges 3.5e-4 off, so that 8 of the 12 fronts were the objective's plan alone (the other
#: four: 2-5 members); divided by 1000 (the default's ratio), 6 of those 8 got a front (3-15
#: members, the straightest 1.2-6.8 deg where the objective's plan lies 1.4-18.8 deg off); on
#: the four that had fronts, the straightest path within a given number of reversals was
#: straighter at most numbers (by up to 4.3 deg) and less straight at a few (by 0.04-0.17
#: deg). The work grows with the members: these fronts took 2.3-9.8 s (1.1-9.4 s before);
#: one 7-joint front needs about 10 s. (Divided by 30 or 100: fewer members, and 3 and 1 of
#: the 12 timed out at 10 s.)
ELASTIC_OBJECTIVE_DIVISOR = FREE_DEVIATION_WEIGHT / nlp_layer.DEVIATION_WEIGHT
#: ... and an elastic answer is a candidate when it ends this close to the goal (rad; the
#: ladder's rungs need :data:`~.solvers.ELASTIC_ACCEPT`, since a finer rung follows them): the
#: finishing's Newton correction on the exact model and the quadrature decide, as for every
#: candidate. With :data:`~.solvers.ELASTIC_ACCEPT` (3e-7) one 6-joint front of those above
#: lost all its members (its straightest NLPs ended 4e-7 off the goal; corrected, verified).
ACCEPT_MISS = 1e-5
#: The objective's weights (deviation 3e4, energy 1) times this for fatrop, which does not
#: scale the problem itself (IPOPT scales the objective so that its largest gradient is 100).
#: Unscaled, fatrop converged on 13-14 of those 25 NLPs, at 1/30 on 23, at 1/300 on 25; at
#: 1/30000 the objective (about 1e-4) is below fatrop's tolerance and it stops early.
FATROP_OBJECTIVE_SCALE = 1.0 / 300.0
#: A front member must be straighter than every member with fewer reversals by more than this
#: (rad): smaller differences are numerical noise, not a trade.
DEVIATION_TOLERANCE = 1e-6
#: Merges tried at one step when the NLP of the smallest run's merge fails.
MERGE_TRIES = 2
#: No NLP starts once less than this is left of the deadline (s).
MIN_SOLVE_TIME = 1e-3


@dataclass
class Candidate:
    """A verified plan and where it came from (``objective``, ``straightest``, ``merged``)."""

    plan: Plan
    origin: str
    signs: np.ndarray | None = None

    @property
    def key(self) -> tuple[int, float]:
        return self.plan.indicators.reversals, self.plan.indicators.deviation


@dataclass
class Front:
    """The candidates, the non-dominated ones and what was tried."""

    candidates: list[Candidate]
    members: list[Candidate]
    tried: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def fewest(self) -> int | None:
        return min((c.key[0] for c in self.candidates), default=None)


def check_budget_request(req: PlanRequest) -> None:
    """A budget or a front needs a method that plans actuator rates (``auto``, ``shooting``)
    and no constraint points (:class:`~optimizer.errors.InvalidRequestError` naming the field).
    """
    from ..errors import InvalidRequestError
    field_name = "max_reversals" if req.max_reversals is not None else "pareto"
    if req.method not in ("auto", "shooting"):
        raise InvalidRequestError(
            f"{field_name} needs method 'auto' or 'shooting' (paths of piecewise-constant "
            f"actuator rates, which may reverse): not {req.method!r}", field=field_name)
    if req.constraint_points:
        raise InvalidRequestError(
            f"{field_name} takes no constraint points (they are points of the paper's "
            "polynomial inputs; the reversal budget plans actuator rates)", field=field_name)


def _solve(req: PlanRequest, deadline: Any, tr: Transcription,
           signs: np.ndarray | None, start_nodes: np.ndarray | None,
           w_dev: float, phi_travel: float = GUESS_PHI_TRAVEL,
           solvers: tuple[str, ...] | None = None) -> ShootingSolution:
    """The transcription ``tr`` with deviation weight ``w_dev`` and rates held to ``signs``
    (per interval and actuator, 0: free), from ``start_nodes`` or else the straight line with
    ``phi`` travelling ``phi_travel`` (rad).

    Solvers ``solvers``, by default :data:`FREE_SOLVERS` (free signs) or :data:`HELD_SOLVERS`
    (held), in order (fatrop below :data:`FATROP_BELOW_JOINTS` joints), by the one loop of
    attempts (:func:`~.attempts.first_converged`). No time cap of its own
    (the answer would depend on the machine's load): patterns the rules rule out are not
    solved (:func:`possible`), and at most :data:`MERGE_TRIES` fail per level.
    """
    nlp = _nlp(req, tr)
    a, b = np.array(req.start), np.array(req.goal)
    lo, hi = node_bounds(req, joint_limits(req))
    lbw, ubw, (lo_phi, hi_phi) = nlp_layer.variable_bounds(req, nlp, tr, lo, hi, signs)
    if start_nodes is not None:
        guess, x0 = "the previous candidate's nodes", nlp.guess_from_nodes(start_nodes, a, b)
    else:
        travel = min(max(phi_travel, lo_phi), hi_phi)
        guess, x0 = f"phi travel {travel:+.3g} rad", nlp.guess(a, b, req.phi_start, travel)
    x0 = np.clip(x0, lbw, ubw)
    have = nlp.solver_names
    if solvers is None:
        solvers = HELD_SOLVERS if signs is not None else FREE_SOLVERS
    names = [name for name in solvers
             if name in have and (req.n < FATROP_BELOW_JOINTS or name != "fatrop")]
    tried: list[dict[str, Any]] = []
    for name in names:
        scale = FATROP_OBJECTIVE_SCALE if name.startswith("fatrop") else 1.0
        p = nlp_layer.parameters(req, w_dev * scale, scale, D_A_WEIGHT * scale)
        if nlp.terminal == "elastic":
            p = nlp.tightened(p, ELASTIC_OBJECTIVE_DIVISOR)
        try:
            out = first_converged(nlp, [Attempt(name, guess, x0)], p, lbw, ubw, deadline,
                                  "the reversal budget's NLP", "budget NLP",
                                  accept_miss=ACCEPT_MISS)
        except InfeasibleError as exc:
            tried.extend(exc.diagnostics.get("tried", []))
            continue
        nodes, rates = nlp.unpack(out.x)
        return ShootingSolution(nodes=nodes, rates=rates, status=f"{out.solver}: {out.status}",
                                # (with those of the solvers that failed before it)
                                iterations=out.iterations + sum(
                                    max(int(t.get("iterations", 0)), 0) for t in tried),
                                start=out.guess,
                                tried=(*tried, *out.tried),
                                compiled=nlp.compiled and out.solver == "fatrop")
    raise InfeasibleError("the reversal budget's NLP found no path: "
                          + "; ".join(f"{t['solver']} {t['status']}" for t in tried),
                          diagnostics={"blocking": "nlp_failed", "tried": tried})


def _finish(req: PlanRequest, tr: Transcription, sol: ShootingSolution,
            signs: np.ndarray | None, origin: str) -> Plan:
    """The verified plan of an NLP answer (the one finishing path of ``shooting``)."""
    timing = {"nlp": 0.0}
    return finish_solution(req, "shooting", _nlp(req, tr), sol, tr, signs, [], timing,
                           {"budget": origin})


def _nlp(req: PlanRequest, tr: Transcription) -> nlp_layer.MultipleShootingNLP:
    """The budget's NLP of ``req`` under ``tr``: the deviation from the segment, bounded at
    the nodes and :data:`DEVIATION_POINTS` inner points per interval (built once per robot shape,
    transcription and variant per process, :func:`~.nlp.multiple_shooting_nlp`)."""
    return _nlp_of(tuple(float(k) for k in req.robot.gains),
                   tuple(int(m) for m in req.robot.exponents), req.phi_change is not None, tr)


def _nlp_of(gains: tuple[float, ...], exponents: tuple[int, ...], fixed_phi: bool,
            tr: Transcription) -> nlp_layer.MultipleShootingNLP:
    terminal = "elastic" if len(exponents) + 1 >= ELASTIC_FROM_JOINTS else "hard"
    return nlp_layer.multiple_shooting_nlp(
        gains, exponents, fixed_phi, tr.intervals, tr.substeps, "hard", "segment",
        DEVIATION_POINTS, terminal, False, FATROP_SETTINGS)


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...], *,
            fixed_phi: bool = False) -> nlp_layer.MultipleShootingNLP:
    """Build (and cache) the budget's NLP of a robot and its IPOPT solver ahead of its first
    ``max_reversals`` or ``pareto`` request (building it took 0.3-0.4 s of 3-joint CPU, more
    from 5 joints: otherwise the first such request pays it). The built solver holds nothing
    of a request: every solve takes a memory that answers as a fresh one
    (:meth:`~.nlp.MultipleShootingNLP.solver_call`), start, goal, weights and bounds are its
    parameters."""
    nlp = _nlp_of(tuple(float(k) for k in gains), tuple(int(m) for m in exponents),
                  fixed_phi, budget_transcription(len(gains) + 1))
    for name in nlp.solver_names:  # (an NLP builds its solvers at their first use)
        nlp.prepare_solver(name)
    return nlp


def pattern(rates: np.ndarray) -> np.ndarray:
    """The sign pattern ``(N, 2)`` of rates, with runs whose travel is within the reversal
    dead band merged into their neighbours (they reverse nothing the answer counts; a zero rate
    takes the sign before it)."""
    N = rates.shape[0]
    signs = np.sign(rates).astype(float)
    for c in (0, 1):
        col = signs[:, c]
        nz = np.flatnonzero(col)
        if nz.size == 0:
            col[:] = 1.0
            continue
        last = np.maximum.accumulate(np.where(col != 0.0, np.arange(N), nz[0]))
        signs[:, c] = col[last]
    while True:
        small = [r for r in runs(signs, rates) if r[0] <= ACTUATOR_DEAD_BAND
                 and _count(signs[:, r[1]]) > 0]
        if not small:
            return signs
        signs = merge(signs, min(small))


def possible(req: PlanRequest, signs: np.ndarray) -> bool:
    """False when rules of :mod:`.rules` show that no path has the sign pattern ``signs``
    (an actuator of one sign the goal does not allow): the NLP need not be asked."""
    phi_one, th1_one = _count(signs[:, 0]) == 0, _count(signs[:, 1]) == 0
    if phi_one:
        demanded = monotone_signs(req)  # None: the joints th2..thn demand a reversal of phi
        if demanded is None or signs[0, 0] != demanded[0]:
            return False
        if not monotone_reach_ok(req, th1_one):
            return False
    if th1_one:
        d1 = float(np.sign(req.goal[0] - req.start[0]))
        if d1 != 0.0 and signs[0, 1] != d1:
            return False
        if not phi_one and not th1_reach_ok(req):
            return False
    return True


def _count(col: np.ndarray) -> int:
    return int(np.count_nonzero(np.diff(col)))


def _verified(req: PlanRequest, tr: Transcription, sol: ShootingSolution,
              signs: np.ndarray | None, origin: str,
              tried: list[dict[str, Any]]) -> Candidate | None:
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        plan = _finish(req, tr, sol, signs, origin)
    except (InfeasibleError, NumericalError) as exc:
        tried.append({"candidate": origin, "outcome": f"{exc.code}: {exc.message[:120]}",
                      "seconds": round(time.perf_counter() - t0, 6),
                      "finish_cpu_seconds": time.process_time() - c0})
        return None
    tried.append({"candidate": origin, "outcome": "plan",
                  "reversals": plan.indicators.reversals,
                  "deviation_deg": math.degrees(plan.indicators.deviation),
                  "seconds": round(time.perf_counter() - t0, 6),
                  "finish_cpu_seconds": time.process_time() - c0})
    return Candidate(plan, origin, signs)


#: What ``diagnostics.budget.tried`` says of an NLP answer that :func:`_dominated` dropped.
DOMINATED = "dominated by the objective's plan: not finished, no merge of it tried"


def node_deviation(req: PlanRequest, nodes: np.ndarray) -> float:
    """The largest distance (rad) of the NLP's nodes ``(N+1, n+1)`` from the segment start ->
    goal in joint space: the path of the answer passes through them (to the correction's
    step, about 1e-7 rad), so its deviation is at least this."""
    a, b = np.asarray(req.start, float), np.asarray(req.goal, float)
    th, d = nodes[:, 1:], b - a
    nrm = float(d @ d)
    s = np.clip((th - a) @ d / nrm, 0.0, 1.0) if nrm > 0.0 else np.zeros(th.shape[0])
    return float(np.max(np.linalg.norm(th - a - s[:, None] * d, axis=1)))


def _dominated(req: PlanRequest, sol: ShootingSolution, first: Plan | None) -> bool:
    """True when the NLP answer ``sol`` cannot be a front member: its nodes alone are already
    no straighter than ``first`` (the first candidate of the fewest reversals, whose reversals
    end the merging, so it has no more than any candidate). Such an answer is not finished
    (the correction and the quadrature cost about one default plan) and not merged further
    (paths with fewer reversals are no straighter, see :func:`build_front`)."""
    if first is None:
        return False
    return node_deviation(req, sol.nodes) >= first.indicators.deviation - DEVIATION_TOLERANCE


def build_front(req: PlanRequest, ctx: PlanContext, first: Plan | None,
                fewest: Plan | None = None) -> Front:
    """The candidates of the module docstring and their non-dominated set.

    ``first``: the plan the objective picked (None when none was found); ``fewest``: under
    another objective than the default, the default objective's plan (the ladder's fewest
    reversals), a candidate too. The one of them with the fewest reversals ends the merging
    (fewer are not looked for) and is the reference of :func:`_dominated`.
    """
    t0 = time.perf_counter()
    deadline = ctx.deadline
    tried: list[dict[str, Any]] = []
    cands: list[Candidate] = []
    if first is not None:
        cands.append(Candidate(first, "objective"))
    if fewest is not None:
        cands.append(Candidate(fewest, "fewest reversals"))
    # the fewest reversals among the first candidates: where the merging ends
    reference = min((c.plan for c in cands), key=lambda p: p.indicators.reversals,
                    default=None)
    floor = reference.indicators.reversals if reference is not None else 0
    tr = budget_transcription(req.n)
    # the straightest from both of phi's directions (the NLP has local optima: on the bench's
    # 3-joint goals the two differed by up to 0.7 deg), the straighter verified one kept
    sol: ShootingSolution | None = None
    top: Candidate | None = None
    for sign, solvers in ((1.0, FREE_SOLVERS), (-1.0, SECOND_FREE_SOLVERS)):
        c0 = time.process_time()
        try:
            alt = _solve(req, deadline, tr, None, None, FREE_DEVIATION_WEIGHT,
                         sign * GUESS_PHI_TRAVEL, solvers)
        except InfeasibleError as exc:
            tried.append({"candidate": "straightest", "outcome": f"infeasible: {exc.message}",
                          "tried": exc.diagnostics.get("tried", []),
                          "nlp_cpu_seconds": time.process_time() - c0})
            continue
        tried.append({"candidate": "straightest", "status": alt.status,
                      "iterations": alt.iterations, "nlp_cpu_seconds": time.process_time() - c0})
        if _dominated(req, alt, reference):
            tried.append({"candidate": "straightest", "outcome": DOMINATED})
            continue
        cand = _verified(req, tr, alt, None, "straightest", tried)
        if cand is not None and (top is None or cand.key[1] < top.key[1]):
            sol, top = alt, cand
    if sol is not None and top is not None:
        signs = pattern(sol.rates)
        cands.append(top)
        level = _count(signs[:, 0]) + _count(signs[:, 1])
        prev = sol
        while level > floor and deadline.remaining > MIN_SOLVE_TIME:
            options = sorted(r for r in runs(signs, prev.rates) if _count(signs[:, r[1]]) > 0)
            found = False
            trials = [t for t in (merge(signs, run) for run in options) if possible(req, t)]
            for trial in trials[:MERGE_TRIES]:
                fewer = _count(trial[:, 0]) + _count(trial[:, 1])
                c0 = time.process_time()
                try:
                    alt = _solve(req, deadline, tr, trial, prev.nodes, FREE_DEVIATION_WEIGHT)
                except InfeasibleError as exc:
                    tried.append({"candidate": f"merged to {fewer}", "outcome": "infeasible",
                                  "tried": exc.diagnostics.get("tried", []),
                                  "nlp_cpu_seconds": time.process_time() - c0})
                    continue
                tried.append({"candidate": f"merged to {fewer}", "status": alt.status,
                              "iterations": alt.iterations,
                              "nlp_cpu_seconds": time.process_time() - c0})
                if _dominated(req, alt, reference):
                    # no straighter than the objective's plan, which has no more reversals;
                    # the merges after it would have fewer still (every path with fewer
                    # reversals is one with more: the straightest of them is no straighter;
                    # the NLPs' optima are local, so this is the rule, not a proof)
                    tried.append({"candidate": f"merged to {fewer}", "outcome": DOMINATED})
                    found = False
                    break
                cand = _verified(req, tr, alt, trial, f"merged to {fewer}", tried)
                if cand is not None:
                    cands.append(cand)
                # the NLP may have emptied more runs (rates 0 where the sign allowed it):
                # the next merge starts from the pattern it really has
                signs = pattern(np.where(trial == 0.0, alt.rates, trial * np.abs(alt.rates)))
                level, prev, found = _count(signs[:, 0]) + _count(signs[:, 1]), alt, True
                break
            if not found:
                break
    members = non_dominated(cands)
    return Front(cands, members, tried, time.perf_counter() - t0)


def non_dominated(cands: list[Candidate]) -> list[Candidate]:
    """The candidates no other beats on both reversals and deviation, by reversals (each
    straighter than every one with fewer by more than :data:`DEVIATION_TOLERANCE`; of equal
    reversals the straightest, the earlier on a tie)."""
    out: list[Candidate] = []
    for c in sorted(cands, key=lambda c: c.key):  # stable: the earlier first on a tie
        if not out or c.key[1] < out[-1].key[1] - DEVIATION_TOLERANCE:
            if out and out[-1].key[0] == c.key[0]:
                continue
            out.append(c)
    return out


def within_budget(front: Front, k: int) -> Candidate | None:
    """The straightest member with at most ``k`` reversals (None: none)."""
    fit = [c for c in front.members if c.key[0] <= k]
    return fit[-1] if fit else None


def member(c: Candidate, main: Plan) -> ParetoMember:
    """What the answer says of a front member."""
    return ParetoMember(plan=c.plan, origin=c.origin, max_reversals=c.key[0],
                        chosen=c.plan is main)


def plan_with_budget(req: PlanRequest, ctx: PlanContext, first: Plan | None,
                     first_error: PlannerError | None, fewest: Plan | None = None) -> Plan:
    """The answer of a request with ``max_reversals`` or ``pareto`` (see the module docstring):
    ``first`` is the plan the objective picked (None, with ``first_error``, when none was);
    ``fewest``, under another objective, the default objective's plan (:func:`build_front`)."""
    k = req.max_reversals
    floor = min((p.indicators.reversals for p in (first, fewest) if p is not None),
                default=None)
    if k is not None and floor is not None and k < floor:
        # the front goes down to these plans' fewest reversals and no further (build_front):
        # a budget below them is refused before its NLPs run (a 5-joint max_reversals = 0
        # took 6 s to be refused, the default plan with 2 reversals 0.1 s)
        raise InfeasibleError(
            f"no verified path with at most max_reversals = {k} direction changes of phi "
            f"and th1 was found: the fewest found is {floor}; allow at least {floor}",
            field="max_reversals",
            diagnostics={"fewest_reversals": floor, "max_reversals": k,
                         "budget": {"tried": [], "why": "below the fewest reversals of the "
                                    "ladder's plan, where the front ends"}})
    front = build_front(req, ctx, first, fewest)
    main: Plan | None
    if k is not None:
        pick = within_budget(front, k)
        if pick is None:
            least = front.fewest
            if least is None and first_error is not None:
                raise first_error
            raise InfeasibleError(
                f"no verified path with at most max_reversals = {k} direction changes of phi "
                f"and th1 was found: the fewest found is {least}; allow at least {least}"
                if least is not None else
                f"no verified path with at most max_reversals = {k} was found",
                field="max_reversals",
                diagnostics={"fewest_reversals": least, "max_reversals": k,
                             "budget": {"tried": front.tried}})
        main = pick.plan
    else:
        main = best([c.plan for c in front.candidates], req.objective, req.weights) or first
        if main is None:
            assert first_error is not None
            raise first_error
    main.diagnostics["budget"] = {
        "max_reversals": k,
        "candidates": [{"origin": c.origin, "reversals": c.key[0],
                        "deviation_deg": math.degrees(c.key[1])} for c in front.candidates],
        "front": [c.key[0] for c in front.members],
        "seconds": front.seconds, "tried": front.tried}
    if req.pareto:
        main = _with_front(main, [member(c, main) for c in front.members], front.seconds)
    return main


def _with_front(main: Plan, members: list[ParetoMember], seconds: float) -> Plan:
    import dataclasses
    return dataclasses.replace(main, pareto=tuple(members),
                               timing={**main.timing, "front": seconds})


__all__ = ["Candidate", "DOMINATED", "Front", "FREE_DEVIATION_WEIGHT", "build_front",
           "check_budget_request", "merge", "node_deviation", "non_dominated", "pattern",
           "plan_with_budget", "prepare", "runs", "within_budget"]
