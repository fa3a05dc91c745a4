"""One entry point: a plan request -> a verified plan, or a typed, explained failure.

Methods
-------
``polynomial``
    The paper's family (``v1 = b0``, ``v2`` polynomial with the request's constraint points):
    singularity-free ``dphi`` intervals (§3.4), then the objective (§4, §5.3).
``constraint_points``
    Constraint-point synthesis as a QP (:mod:`.convex`), replacing the paper's trial and error.
``penalty``
    The penalty-function NLP (:mod:`.penalty`, Remark 3) with a varying ``v1`` (phi may reverse).
``retimed``
    The polynomial method's geometric path run along a ``d_a``-optimal time law
    (:mod:`.retime`): same region, ``t_p`` and ``||J_R(T)||_F``, far smaller ``d_a``.
``shooting``
    Direct multiple shooting on the original model (:mod:`.shooting`): piecewise-constant
    actuator rates, minimum energy plus joint-space deviation; phi may reverse.
``auto``
    polynomial, then constraint points, then penalty; with ``tp_then_da`` the retimed plan and
    the penalty method (from the polynomial optimum) are also tried, and when the family cannot
    reach the goal the shooting plan too; the best plan by (t_p, d_a) is returned.

Every plan, whatever the method, goes through :func:`finish_plan`: continuous region check,
sampling, indicators and re-integration of the original model. A plan that fails there is never
returned.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import numpy as np

from ..chained_form import chained_form
from ..errors import (InfeasibleError, InvalidRequestError, NumericalError, PlannerError,
                      SolverTimeoutError)
from ..indicators import compute_indicators
from ..problem import PlanRequest
from ..region import Region
from ..results import Plan, SampledPath
from ..steering import ChainedPath, InputSchedule
from ..verify import PlannedInputs, verify_plan
from .family import SEARCH_SAMPLES, PolynomialFamily
from .intervals import dphi_grid, feasible_intervals
from .objectives import optimise

#: A plan is verified when the re-integrated original model ends this close to the goal (rad).
TERMINAL_TOLERANCE = 1e-6
#: Normalised-time samples used to find the peak actuator rates for duration scaling.
RATE_SAMPLES = 2001
#: Members of the window ranked by their Fréchet bound before the time-law LP (``retimed``).
RETIME_CANDIDATES = 24
#: Path samples per member for that ranking.
RETIME_SIGMA_SAMPLES = 257


#: Set by :func:`cancel` (e.g. from a signal handler of a worker process whose client went
#: away): every deadline check then fails, ending the solve at its next check. Cleared by
#: :func:`clear_cancel` before each job.
_cancelled = [False]


def cancel() -> None:
    """End the solve in progress at its next deadline check (safe in a signal handler: it only
    sets a flag; the solve stops where its own checks are, leaving no state half-built)."""
    _cancelled[0] = True


def clear_cancel() -> None:
    """Undo :func:`cancel` (before the next job)."""
    _cancelled[0] = False


class Deadline:
    """Wall-clock budget of one solve; :meth:`check` raises :class:`SolverTimeoutError` (also
    after :func:`cancel`)."""

    def __init__(self, seconds: float) -> None:
        self.start = time.perf_counter()
        self.seconds = float(seconds)

    @property
    def remaining(self) -> float:
        return self.seconds - (time.perf_counter() - self.start)

    def check(self, stage: str) -> None:
        if self.remaining <= 0.0 or _cancelled[0]:
            raise SolverTimeoutError(f"the solve exceeded its time limit of {self.seconds:g} s "
                                     f"during {stage}", field="time_limit",
                                     diagnostics={"stage": stage, "time_limit": self.seconds})


def make_region(req: PlanRequest, criterion: str | None = None) -> Region:
    return Region(req.robot, criterion or req.singularity, req.joint_bounds)


def check_endpoints(req: PlanRequest, region: Region) -> None:
    """Start and goal must be inside the (full) region: there the transform exists."""
    region.check_point_q(np.array((0.0,) + req.start), "start")
    region.check_point_q(np.array((0.0,) + req.goal), "goal")


def direction_conflict(req: PlanRequest) -> str | None:
    """Why the constant-v1 family cannot reach the goal, or None.

    With ``v1`` constant every ``th_i`` (i >= 2) moves monotonically in the direction of
    ``dphi`` (``th_i' = K_i cos(th_{i-1})^m_i u1`` with a positive factor in the region).
    """
    d = np.array(req.goal[1:]) - np.array(req.start[1:])
    up = [i + 2 for i, x in enumerate(d) if x > 0]
    down = [i + 2 for i, x in enumerate(d) if x < 0]
    if up and down:
        return (f"joints th{up[0]} and th{down[0]} must move in opposite directions: with a "
                "constant v1 every joint th2..thn moves in the direction of phi, so phi must "
                "reverse (use method 'penalty' or 'auto')")
    if not up and not down:
        return ("joints th2..thn do not move, which needs dphi = 0 where the steering system is "
                "singular (Remark 2); phi must go and come back (use method 'penalty' or 'auto')")
    return None


def phi_search_bounds(req: PlanRequest) -> tuple[float, float]:
    """The request's ``dphi`` bounds, cut to the sign the joints' motion demands."""
    lo, hi = req.phi_change_bounds
    d = np.array(req.goal[1:]) - np.array(req.start[1:])
    if np.all(d >= 0):
        lo = max(lo, 0.0)
    elif np.all(d <= 0):
        hi = min(hi, 0.0)
    return lo, hi


def finish_plan(req: PlanRequest, inputs: InputSchedule, method: str,
                feasible: list[tuple[float, float]], timing: dict[str, float],
                diagnostics: dict[str, Any], *, chained: ChainedPath | None = None,
                geometry: ChainedPath | None = None) -> Plan:
    """Scale, sample, check, measure and verify a candidate; return it as a :class:`Plan`.

    ``chained`` is the candidate's chained path when the method built it already (it must be
    the path of ``inputs`` from the start); ``geometry`` a path that passes through exactly the
    same states (a retimed plan's geometric path): the continuous region check then runs on
    it, which is cheaper (one polynomial piece instead of many) and equivalent.

    Raises
    ------
    InfeasibleError
        The continuous path leaves the region, or the actuator limits cannot be met.
    NumericalError
        The original model driven by the planned inputs does not reach the goal.
    """
    t0 = time.perf_counter()
    robot = req.robot
    cf = chained_form(robot)
    q0 = req.q_start()
    if chained is None:
        chained = ChainedPath.from_inputs(cf.to_chained(q0), inputs)
    full = make_region(req, "full")
    chk = full.check_path(geometry if geometry is not None else chained)
    if not chk.ok:
        when = chk.first_crossing_tau
        raise InfeasibleError(
            "the path leaves the singularity-free region"
            + (f" at t/T = {when:.6g}" if when is not None else ""),
            diagnostics={"margin": chk.margin, "first_crossing_tau": when})
    # Duration: the geometric path depends on tau only; T rescales the rates.
    T = _duration(req, cf, chained)
    inputs = InputSchedule(inputs.breaks, inputs.v1, inputs.v2, T)
    chained = ChainedPath(chained.z0, inputs, chained.polys)
    planned = PlannedInputs(cf, chained)
    t = np.linspace(0.0, T, int(req.samples))
    tau = t / T
    # indicators on a dense grid (at least the search density), independent of `samples`
    # (the same normalised grid as the searches, so t_p and d_a agree with what was optimised)
    td = np.linspace(0.0, T, SEARCH_SAMPLES)
    # the returned samples and the indicator grid through the maps in one pass (they act
    # point by point, so this is two passes' values with half the calls)
    ns = t.size
    z_all = chained.z(np.concatenate([tau, td / T]))
    inv = cf.from_chained(z_all)
    if not inv.valid[:ns].all():
        raise InfeasibleError("the sampled path leaves the singularity-free region",
                              diagnostics={"margin": chk.margin})
    z = z_all[:ns]
    q = inv.q[:ns]
    v = inputs.v(t)
    u = cf.u_from_v(q, v)
    dphi = inputs.phi_change
    # no inputs on the dense grid: the sampled energy is replaced by the integrated one below
    ind = compute_indicators(td, inv.q[ns:], None)
    timing["sampling"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    ver = verify_plan(robot, planned, q0, np.array(req.goal), req.phi_start + dphi, t, q)
    timing["verification"] = time.perf_counter() - t1
    # the sampled energy misses sharp input peaks (u2 near th1 = 0): use the integrated one
    ind = dataclasses.replace(ind, energy=ver.energy)
    if ver.singular or not ver.terminal_error <= TERMINAL_TOLERANCE:
        raise NumericalError(
            "the planned inputs do not steer the original model to the goal "
            f"(terminal error {ver.terminal_error:.3g} rad, singular={ver.singular})",
            diagnostics={"terminal_error": ver.terminal_error, "singular": ver.singular,
                         "method": method})
    return Plan(robot=robot, method=method, phi_change=float(dphi), duration=T, inputs=inputs,
                chained=chained, feasible_phi_changes=feasible, indicators=ind,
                margin=float(chk.margin), path=SampledPath(t=t, q=q, z=z, u=u, v=v),
                verification=ver, timing=timing, diagnostics=diagnostics)


def _duration(req: PlanRequest, cf: Any, chained: ChainedPath) -> float:
    limits = (req.max_u1, req.max_u2)
    if all(x is None for x in limits):
        return req.duration_or_default
    tau = np.linspace(0.0, 1.0, RATE_SAMPLES)
    q = cf.from_chained(chained.z(tau)).q
    U = cf.u_from_v(q, chained.inputs.V(tau))  # rates per unit normalised time
    if req.duration is None and req.constraint_points:
        raise InfeasibleError("constraint point times are in seconds: give a duration when "
                              "actuator limits are set", diagnostics={})
    return req.duration_for_rates(np.max(np.abs(U), axis=0))


# ---------------------------------------------------------------------- methods
def family_for(req: PlanRequest, deadline: Deadline) -> PolynomialFamily:
    """The paper's family for ``req``; :class:`InfeasibleError` when no member can reach the
    goal (joints that must move in opposite directions, or not at all)."""
    conflict = direction_conflict(req)
    if conflict:
        raise InfeasibleError(conflict, diagnostics={"blocking": "opposite_joint_motion"})
    return PolynomialFamily(req.robot, req.q_start(), req.q_goal(0.0), req.duration_or_default,
                            req.constraint_points, make_region(req), deadline.check)


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
            near = _closest_feasible(fam, float(req.phi_change), deadline)
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
            near = _closest_feasible(fam, 0.5 * (lo + hi), deadline, exclude=(lo, hi))
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


def plan_retimed(req: PlanRequest, deadline: Deadline) -> Plan:
    """The paper's geometric path, run along the time law that minimises ``d_a`` (:mod:`.retime`).

    The member (``dphi``) is the request's ``phi_change`` or, for ``tp_then_da``, the one with
    the fewest ``t_p`` and then the smallest Fréchet bound (the best ``d_a`` any time law can
    reach on it); for the other objectives the polynomial method's choice, which retiming does
    not change (``t_p``, ``||J_R(T)||_F`` and the region are geometric).
    """
    from ..steering import polyval_rows
    from .family import _reversals_cols
    from .retime import SCREEN_TIMES, frechet_bound, optimal_time_law, retimed_path

    if req.constraint_points:
        raise InvalidRequestError(
            "method 'retimed' changes when the path passes its points, so it takes no "
            "constraint points (use 'polynomial' or 'constraint_points')",
            field="constraint_points")
    timing: dict[str, float] = {}
    fam = family_for(req, deadline)
    a, b = float(req.start[0]), float(req.goal[0])
    t0 = time.perf_counter()
    feasible: list[tuple[float, float]] = []
    if req.phi_change is not None:
        fam.inputs(float(req.phi_change))  # raises SingularSystemError for dphi = 0 (Remark 2)
        if not fam.evaluate(float(req.phi_change)).ok:
            raise InfeasibleError(
                f"phi_change = {req.phi_change:.6g} rad gives a path that leaves the "
                f"singularity-free region ({req.singularity} criterion)",
                diagnostics={"blocking": "singularity"})
        dphi = float(req.phi_change)
    else:
        lo, hi = phi_search_bounds(req)

        def by_bound(cands: np.ndarray) -> float | None:
            """The member with the fewest t_p, then the smallest Fréchet bound (sampled),
            that passes the continuous check."""
            sig = np.linspace(0.0, 1.0, RETIME_SIGMA_SAMPLES)
            if fam.cf.backend == "closed":
                # n = 3: only z2 and z3 at the samples (the members' coefficients are finite
                # where regular, so z1 and z4 are too)
                coef, regular = fam.polys(cands)
                z23 = polyval_rows(coef[:, 1:3, :], sig)                # (D, 2, G)
                th1, okf = fam.cf.th1_from_z23(z23[:, 0], z23[:, 1])
                th1 = np.where(okf, th1, 0.0)
                valid = regular & okf.all(axis=1)
            else:
                z, regular, _ = fam.batch_z(cands, sig)
                th1f, okf = fam.cf.th1_from_chained(z.reshape(-1, req.robot.n + 1))
                th1 = th1f.reshape(cands.size, sig.size)
                valid = regular & okf.reshape(cands.size, sig.size).all(axis=1)
            bound = frechet_bound(th1, a, b)
            tps = _reversals_cols(th1.T)          # count_reversals of every row, vectorised
            for i in np.lexsort((bound, tps)):
                # the continuous check of the path that is returned (Region.check_path on
                # fam.path, request's criterion and the full region): finish_plan's check of
                # the same path is then answered from check_path's memo, not run twice
                if valid[i] and fam.confirm(float(cands[i]))[0]:
                    return float(cands[i])
            return None

        chosen: float | None = None
        if req.objective == "tp_then_da":
            # Members whose sampled margin is positive on the interval search's own coarse
            # grid are enough to rank by the bound (the winner is checked exactly), without
            # refining the interval ends. Windows narrower than the grid (n >= 4) leave none:
            # then the exact intervals, as for the other objectives.
            # The candidates are screened on SCREEN_TIMES times only: a member's
            # continuous margin is at most its margin at any sampled times, so a member with a
            # margin <= 0 there (all but a few) cannot pass the exact check, and one that is
            # kept but fails it is skipped by `by_bound` like any other. Equivalent to the
            # 97-time coarse grid of the interval search, at a third of the cost.
            # Nor can a member with K_n |dphi| <= |th_n(T) - th_n(0)|: inside the region
            # 0 < z_n < K_n, and th_n' = z_n phi' (a hair of slack for the solve's rounding).
            grid = dphi_grid(lo, hi)
            reach = abs(req.goal[-1] - req.start[-1]) * (1.0 - 1e-9)
            grid = grid[np.abs(grid) * req.robot.gains[-1] > reach]
            coarse = grid[fam.coarse_inside(grid, grid=SCREEN_TIMES)] if grid.size else grid
            if coarse.size:
                chosen = by_bound(coarse)
            timing["coarse_scan"] = time.perf_counter() - t0
        if chosen is None:
            t1 = time.perf_counter()
            feasible = feasible_intervals(fam, lo, hi)
            timing["intervals"] = time.perf_counter() - t1
            deadline.check("the interval search")
            if not feasible:
                raise InfeasibleError(
                    f"no phi_change in [{lo:.6g}, {hi:.6g}] rad gives a singularity-free path "
                    "of the polynomial family", diagnostics={
                        "blocking": "no_feasible_phi_change", "searched": [lo, hi]})
            t2 = time.perf_counter()
            if req.objective == "tp_then_da":
                chosen = by_bound(_window_nodes(feasible, RETIME_CANDIDATES))
            else:  # the polynomial method's choice (retiming changes neither t_p nor ||J_R||)
                best_e = optimise(fam, feasible, req.objective, req.weights)
                chosen = None if best_e is None else best_e.dphi
            timing["objective"] = time.perf_counter() - t2
        if chosen is None:
            raise InfeasibleError("the feasible intervals are too narrow to hold a path",
                                  diagnostics={"feasible_phi_changes": feasible})
        dphi = chosen
    path = fam.path(dphi)
    t2 = time.perf_counter()
    cf = fam.cf
    if cf.backend == "closed":  # n = 3: th1 from z2, z3 (z1, z4 of a member are finite)
        def th1_of(s: np.ndarray) -> np.ndarray:
            z23 = path.z_components(s, 1, 3)
            th, ok = cf.th1_from_z23(z23[:, 0], z23[:, 1])
            return np.where(ok, th, 0.0)
    else:
        def th1_of(s: np.ndarray) -> np.ndarray:
            return cf.th1_from_chained(path.z(s))[0]
    law = optimal_time_law(th1_of, a, b)
    retimed = retimed_path(path, law)
    timing["time_law"] = time.perf_counter() - t2
    deadline.check("the time law")
    return finish_plan(req, retimed.inputs, "retimed", feasible, timing,
                       {"objective": req.objective, "singularity": req.singularity,
                        "geometric_phi_change": dphi,
                        "time_law": {"knots_t_over_T": law.knots_tau.tolist(),
                                     "lp_d_a": law.deviation, "d_a_lower_bound": law.bound}},
                       chained=retimed, geometry=path)


def _window_nodes(intervals: list[tuple[float, float]], count: int) -> np.ndarray:
    """About ``count`` nodes spread over the intervals in proportion to their widths, each a
    hair inside (interval ends are on the boundary, margin 0)."""
    widths = np.array([b - a for a, b in intervals])
    total = float(widths.sum())
    out: list[np.ndarray] = []
    for (a, b), w in zip(intervals, widths):
        k = max(3, int(round(count * w / total)) if total > 0 else 3)
        eps = min(1e-7, 0.25 * (b - a))
        out.append(np.linspace(a + eps, b - eps, k))
    return np.concatenate(out)


def _closest_feasible(fam: PolynomialFamily, target: float, deadline: Deadline,
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


def _method(name: str) -> Callable[[PlanRequest, Deadline], Plan]:
    if name == "polynomial":
        return plan_polynomial
    if name == "retimed":
        return plan_retimed
    if name == "constraint_points":
        from .convex import plan_constraint_points
        return plan_constraint_points
    if name == "penalty":
        from .penalty import plan_penalty
        return plan_penalty
    if name == "shooting":
        from .shooting import plan_shooting
        return plan_shooting
    raise ValueError(name)


def better(a: Plan, b: Plan, objective: str) -> Plan:
    """The better of two plans by the request's rule (ties keep ``a``)."""
    ia, ib = a.indicators, b.indicators
    if objective == "tp_then_sensitivity":
        ka, kb = (ia.t_p, ia.sensitivity), (ib.t_p, ib.sensitivity)
    else:
        ka, kb = (ia.t_p, ia.d_a), (ib.t_p, ib.d_a)
    return b if kb < ka else a


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
    deadline = Deadline(req.time_limit)
    t0 = time.perf_counter()
    check_endpoints(req, make_region(req, "full"))
    if req.method != "auto":
        result = _method(req.method)(req, deadline)
    else:
        result = _plan_auto(req, deadline)
    result.timing["total"] = time.perf_counter() - t0
    return result


def _plan_auto(req: PlanRequest, deadline: Deadline) -> Plan:
    failures: dict[str, str] = {}
    poly: Plan | None = None
    try:
        poly = plan_polynomial(req, deadline)
    except (InfeasibleError, NumericalError) as exc:
        failures["polynomial"] = exc.message
    if poly is None and not req.constraint_points and direction_conflict(req) is None:
        try:
            cp = _method("constraint_points")(req, deadline)
            cp.diagnostics["auto"] = {"tried": ["polynomial", "constraint_points"],
                                      "failures": failures}
            return cp
        except (InfeasibleError, NumericalError) as exc:
            failures["constraint_points"] = exc.message
    if poly is not None and req.objective != "tp_then_da":
        poly.diagnostics["auto"] = {"tried": ["polynomial"], "failures": failures}
        return poly
    # the same geometric path under a d_a-optimal time law: milliseconds, often the best
    retimed: Plan | None = None
    if poly is not None and not req.constraint_points:
        try:
            retimed = plan_retimed(req, deadline)
        except (InfeasibleError, NumericalError) as exc:
            failures["retimed"] = exc.message
    # beyond the family: one multiple-shooting NLP on the original model (milliseconds)
    shot: Plan | None = None
    if poly is None and not req.constraint_points:
        try:
            shot = _method("shooting")(req, deadline)
        except (InfeasibleError, NumericalError, SolverTimeoutError) as exc:
            failures["shooting"] = exc.message
    deadline.check("auto")
    fallback = poly if poly is not None else shot  # a verified plan already in hand
    try:
        penalty: Callable[..., Plan] = _method("penalty")
        # the penalty NLP also starts from the polynomial optimum (and never returns worse)
        pen = penalty(req, deadline, warm_start=poly.inputs if poly is not None else None)
    except SolverTimeoutError:
        if fallback is None:
            raise
        failures["penalty"] = "stopped by the time limit"
        pen = None
    except PlannerError as exc:
        if fallback is None and not isinstance(exc, (InfeasibleError, NumericalError)):
            raise
        failures["penalty"] = exc.message
        pen = None
    except Exception as exc:  # a bug in one method must not hide a verified plan of another
        if fallback is None:
            raise
        failures["penalty"] = f"internal error: {type(exc).__name__}"
        pen = None
    if fallback is None and pen is None:
        raise InfeasibleError("no method found a singularity-free path: "
                              + "; ".join(f"{k}: {v}" for k, v in failures.items()),
                              diagnostics={"failures": failures})
    chosen: Plan | None = None
    for cand in (poly, retimed, shot, pen):  # ties keep the earlier, simpler plan
        if cand is not None:
            chosen = cand if chosen is None else better(chosen, cand, req.objective)
    assert chosen is not None
    found = {"polynomial": poly, "retimed": retimed, "shooting": shot, "penalty": pen}
    chosen.diagnostics["auto"] = {
        "tried": [k for k in ("polynomial", "constraint_points", "retimed", "shooting", "penalty")
                  if k in failures or found.get(k) is not None],
        "failures": failures,
        "chosen": chosen.method,
        "rule": "fewest t_p, then smallest d_a" if req.objective == "tp_then_da" else req.objective,
    }
    return chosen
