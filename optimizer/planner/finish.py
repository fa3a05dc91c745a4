"""One finishing path: a method's inputs -> a checked, sampled, measured and verified :class:`Plan`.

Every method ends here, whatever its inputs:

* chained inputs (:class:`~optimizer.steering.InputSchedule`, the paper's family and the
  constraint-point QP): :func:`finish_plan` checks the continuous chained path against the
  region, fixes the duration, samples it through the inverse map and re-integrates the
  original model under the actuator inputs those chained inputs mean;
* actuator rates (:class:`~optimizer.actuation.ActuatorSchedule`, planned on the original
  model): :func:`finish_actuator_plan` takes the original model re-integrated under the rates
  and checks, samples and measures that.

Both measure the indicators with :func:`~optimizer.indicators.compute_indicators`: chained
plans on the searches' dense grid (:data:`INDICATOR_SAMPLES` points), actuator plans on the
mesh of the quadrature that re-integrates them (its nodes cluster at the breaks, where such a
path has its kinks). Both refuse a plan whose re-integrated path misses the goal by more than
:data:`~.rules.TERMINAL_TOLERANCE` or leaves the joint limits.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import numpy as np

from ..actuation import ActuatorSchedule
from ..chained_form import chained_form
from ..errors import InfeasibleError, NumericalError
from ..execution import (CORRECTION_TARGET, REPLAY_NODES, Execution, execute,
                         handed_out_times)
from ..indicators import Indicators, compute_indicators
from ..problem import MAX_DURATION, PlanRequest
from ..results import Plan
from ..steering import ChainedPath, InputSchedule
from ..timing import Limits, RatesOf, TimeLaw, geometric_path, time_law
from ..verify import (CASCADE_TOL, PlannedInputs, Replay, Verification, integrate,
                      integrate_cascade, verify_plan)
from .family import SEARCH_SAMPLES
from .rules import TERMINAL_TOLERANCE, joint_limits, limits_region, make_region
from .via import check_handed_out, via_schedule, via_time_law_errors

#: The linear form's times, its dense grid and the times' positions in it
#: (:func:`optimizer.execution.handed_out_times`).
Grid = tuple[np.ndarray, np.ndarray, np.ndarray]

#: Points of the dense grid the indicators are measured on (the searches' own density, so
#: that t_p and d_a agree with what was optimised).
INDICATOR_SAMPLES = SEARCH_SAMPLES

#: The largest error estimate (rad) of the cascade quadrature that proves an actuator plan, a
#: tenth of the terminal tolerance; the decisions take it in (the terminal error plus the
#: estimate within the tolerance, the margin above it). The quadrature's own default
#: (:data:`~optimizer.cascade.CASCADE_ACCEPT`, 1e-8) is met by nearly every plan; a long path
#: of large rates is where its estimate stops at a floor above that: a 7-joint plan of 150
#: pieces and rates up to 100 rad/s (three legs, :mod:`.legs`) at 1.5e-8 rad from 150 to 5,600
#: panels, while its end state is 2e-13 rad from DOP853's at rtol 1e-13 run piece by piece.
#: DOP853 at the verification's tolerances, the fallback there, ended 2.4e-7 rad off and took
#: 1.2 s of the plan's time (after its time limit: legs finish the whole path last).
PROOF_ACCEPT = 0.1 * TERMINAL_TOLERANCE


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
    # the plan's own duration: the geometric path depends on tau only; the time law
    # (retime_and_execute) decides how fast the answer runs it
    T = _plan_duration(req)
    inputs = InputSchedule(inputs.breaks, inputs.v1, inputs.v2, T)
    chained = ChainedPath(chained.z0, inputs, chained.polys)
    planned = PlannedInputs(cf, chained)
    t = np.linspace(0.0, T, int(req.samples))
    tau = t / T
    # indicators on a dense grid (at least the search density), independent of `samples`
    # (the same normalised grid as the searches, so t_p and d_a agree with what was optimised)
    td = np.linspace(0.0, T, INDICATOR_SAMPLES)
    # the returned samples and the indicator grid through the maps in one pass (they act
    # point by point, so this is two passes' values with half the calls)
    ns = t.size
    z_all = chained.z(np.concatenate([tau, td / T]))
    inv = cf.from_chained(z_all)
    if not inv.valid[:ns].all():
        raise InfeasibleError("the sampled path leaves the singularity-free region",
                              diagnostics={"margin": chk.margin})
    q = inv.q[:ns]
    dphi = inputs.phi_change
    # th_n takes no part in the region checked above; with a constant v1 it is monotone
    # (th_n' = z_n v1 with z_n > 0 inside), so its extremes are its ends, and the dense grid
    # holds them
    lo, hi = joint_limits(req)
    th_all = inv.q[:, 1:]
    if not (np.all(th_all > lo) and np.all(th_all < hi)):
        worst = int(np.argmin(np.min(np.minimum(th_all - lo, hi - th_all), axis=0)))
        raise InfeasibleError(f"the path takes th{worst + 1} outside its limits "
                              f"[{lo[worst]:.6g}, {hi[worst]:.6g}] rad",
                              diagnostics={"margin": chk.margin, "joint": worst + 1})
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
    # the handed-out path is the plan's path along its time law, corrected for its rule and
    # verified by it (optimizer.timing, optimizer.execution)
    law, exe = retime_and_execute(req, planned.u, planned.breaks, False, req.phi_start + dphi,
                                  ind, method, diagnostics=diagnostics)
    timing["execution"] = exe.seconds
    _note_samples(req, exe, diagnostics)
    return Plan(robot=robot, method=method, phi_change=float(dphi), duration=law.T,
                inputs=inputs, chained=chained, feasible_phi_changes=feasible,
                indicators=_handed_out(exe, ind), margin=float(chk.margin), path=exe.path,
                verification=ver, timing=timing, diagnostics=diagnostics, execution=exe,
                time_law=law, plan_indicators=ind)


def _plan_duration(req: PlanRequest) -> float:
    """The duration of a method's own schedule (its time ``sigma``): the request's, or 1 s.
    With limits and constraint points a duration is needed (their times are in seconds)."""
    if req.has_limits and req.duration is None and req.constraint_points:
        raise InfeasibleError("constraint point times are in seconds: give a duration when "
                              "actuator limits are set", field="duration", diagnostics={})
    return req.duration_or_default


def request_limits(req: PlanRequest) -> Limits:
    """The request's limits of the rates and their derivatives."""
    return Limits((req.max_u1, req.max_u2), (req.max_du1, req.max_du2),
                  (req.max_ddu1, req.max_ddu2))


#: The handed-out path may lie this much farther (rad, 0.5 deg) from the straight segment
#: than the plan's exact path, plus :data:`DEVIATION_RELATIVE` of it: a sampled or held form
#: follows the law's ramps only approximately (a 10 ms hold of a 4-joint retimed plan: +0.2
#: deg), while a correction gone astray moves it by tens of degrees (issue 25: 16.5 -> 47.2).
#: The answer's indicators are the handed-out path's either way.
DEVIATION_TOLERANCE = math.radians(0.5)
DEVIATION_RELATIVE = 2e-2
#: The same for a held form (``controller_period``): holding each rate for a period moves
#: the path by more (a 50 ms hold of a 3-joint retimed plan: +0.84 deg of 15 deg).
HELD_DEVIATION_TOLERANCE = math.radians(2.0)
HELD_DEVIATION_RELATIVE = 5e-2


def plan_time_law(req: PlanRequest, rates: RatesOf, breaks: np.ndarray, constant: bool
                  ) -> TimeLaw:
    """The time law of a plan whose exact rates ``rates`` (on its own time) may jump at
    ``breaks`` (``constant``: constant between them), for the request's duration and limits
    (:func:`optimizer.timing.time_law`)."""
    stops = [cp.time for cp in req.constraint_points]
    path = geometric_path(rates, np.asarray(breaks, float), constant=constant, stops=stops)
    with via_time_law_errors(req):  # the via points fix the times: say so in their terms
        return time_law(path, request_limits(req), req.duration, req.duration_or_default,
                        fixed_times=bool(req.constraint_points or req.via_points),
                        max_duration=MAX_DURATION)


#: The handed-out path is made denser up to this many samples (doubling the intervals)
#: before a plan is refused for its form: a coarse linear form can miss a sharp rate peak
#: (more reversals, a larger deviation, or no correction onto the goal), a denser one holds it.
#: A 6-joint plan under a jerk limit on u1 (200 S-curve phases in 5.6 s) missed by 8.3e-6 rad
#: at 4097 samples, and the correction of that miss, along the end map's weak directions,
#: reversed th1 39 times: refused. At 8193 samples it missed by 2.9e-7 and needed none.
DENSIFY_SAMPLES = 16385


def retime_and_execute(req: PlanRequest, rates: RatesOf, breaks: np.ndarray, constant: bool,
                       phi_end: float, exact: Indicators, method: str, *,
                       law: TimeLaw | None = None, initial: Replay | None = None,
                       grid: Grid | None = None,
                       diagnostics: dict[str, Any] | None = None) -> tuple[TimeLaw, Execution]:
    """The plan's path along its time law (:func:`optimizer.timing.time_law`: rest to rest,
    continuous rates, within the request's limits), handed out and verified
    (:func:`optimizer.execution.execute`).

    ``rates`` are the plan's exact rates on its own time, which may jump at ``breaks``
    (``constant``: constant between them); ``exact`` its indicators; ``law`` the time law
    when the caller made it (:func:`plan_time_law`), ``initial`` the replay of
    :func:`optimizer.execution.execute` and ``grid`` the linear form's times on which it was
    made (:func:`optimizer.execution.handed_out_times`). The handed-out path's (and the JointTrajectory
    form's) reversals and deviation are compared with them: a form that adds a reversal or
    lies farther from the straight segment (by more than :data:`DEVIATION_TOLERANCE` plus
    :data:`DEVIATION_RELATIVE` of it), or that its correction cannot bring onto the goal
    inside the region and the limits, is not handed out: the linear form is made denser
    (the intervals halved, up to :data:`DENSIFY_SAMPLES` samples, ``samples`` is a minimum)
    until it is the plan's. A held form (``controller_period``, the user's) of a request that
    leaves the duration free is tried on a law :data:`HELD_STRETCH` times longer (the same
    path, slower: each period holds less of it), up to :data:`HELD_STRETCHES` times, and said
    so in ``diagnostics["duration"]``; else it is refused.

    Raises
    ------
    InfeasibleError
        The duration is too short for the limits, or no handed-out path is the plan's.
    NumericalError
        No handed-out path reaches the goal.
    """
    if law is None:
        law = plan_time_law(req, rates, breaks, constant)
    held = req.controller_period is not None
    samples = int(req.samples)
    planned_T, stretches = law.T, 0

    def slower(current: TimeLaw) -> TimeLaw | None:
        # the same path on a longer law, where the request leaves the duration free
        nonlocal stretches
        longer = HELD_STRETCH * current.T
        if (not held or req.duration is not None or req.via_points or req.constraint_points
                or stretches >= HELD_STRETCHES or longer > MAX_DURATION):
            return None
        stretches += 1
        return plan_time_law(dataclasses.replace(req, duration=longer), rates, breaks, constant)

    while True:
        asked = req if samples == int(req.samples) else dataclasses.replace(req, samples=samples)
        denser = min(2 * samples - 1, max(DENSIFY_SAMPLES, int(req.samples)))
        can_densify = not held and denser > samples
        try:
            exe = execute(asked, law.rates, law_kinks(law), law.T, phi_end, limits_region(req),
                          stops=law.stops, exact=law.piecewise_linear,
                          initial=initial if asked is req and stretches == 0 else None,
                          grid=grid if asked is req and stretches == 0 else None)
        except (InfeasibleError, NumericalError) as err:
            if can_densify and err.field in FORM_FIELDS:
                samples = denser
                continue
            longer = slower(law) if err.field == "controller_period" else None
            if longer is not None:
                law = longer
                continue
            raise
        worse = _not_the_plans(exe, exact, held)
        if not worse:
            if stretches and diagnostics is not None:
                diagnostics["duration"] = {
                    "planned": planned_T, "handed_out": law.T,
                    "why": f"the controller period {req.controller_period:g} s holds the "
                           "plan's path only on a slower time law (the same path); give a "
                           "duration to keep one"}
            return law, exe
        if can_densify:
            samples = denser
            continue
        longer = slower(law)
        if longer is not None:
            law = longer
            continue
        field = "controller_period" if held else "samples"
        got = exe.indicators
        assert got is not None
        raise InfeasibleError(
            f"the handed-out path, corrected onto the goal, is not the {method} plan's: "
            + "; ".join(worse) + (" (a shorter controller_period)" if held else
                                  f" (also at {samples} samples)"), field=field,
            diagnostics={"execution": exe.check.as_dict(),
                         "handed_out": {"reversals": {"phi": got.reversals_phi,
                                                      "th1": got.reversals_th1},
                                        "deviation": got.deviation, "samples": samples},
                         "plan": {"reversals": {"phi": exact.reversals_phi,
                                                "th1": exact.reversals_th1},
                                  "deviation": exact.deviation}})


#: A held form (``controller_period``) that is not the plan's path is tried on a time law this
#: many times longer, at most :data:`HELD_STRETCHES` times, where the request leaves the
#: duration free: the model has no drift, so the path is the same, and each period then holds
#: a shorter stretch of it (the form's error falls about as the square of the period over
#: the law's ramps). On 5- to 8-joint goals whose held form at 0.02 s missed the goal by
#: 1.1e-6 to 5.4e-6 rad (the tolerance 1e-6), the plan failed over to the ladder's finer
#: rung, 1.2-5.5 s on CasADi's virtual machine.
HELD_STRETCH = 2.0
HELD_STRETCHES = 3


#: The fields of the handed-out forms' refusals that a denser linear form can fix.
FORM_FIELDS = frozenset({"samples", "joint_trajectory", "max_u1", "max_u2", "max_du1",
                         "max_du2"})


def _not_the_plans(exe: Execution, exact: Indicators, held: bool) -> list[str]:
    """What makes the handed-out forms (the path, and the JointTrajectory form when asked
    for) another path than the plan's: more reversals, or a larger deviation beyond the
    tolerance."""
    rel = HELD_DEVIATION_RELATIVE if held else DEVIATION_RELATIVE
    tol = HELD_DEVIATION_TOLERANCE if held else DEVIATION_TOLERANCE
    forms: list[tuple[str, tuple[int, int], float]] = []
    got = exe.indicators
    assert got is not None
    forms.append(("the path", (got.reversals_phi, got.reversals_th1), got.deviation))
    jt = exe.joint_trajectory_check
    if jt is not None and jt.reversals is not None and jt.deviation is not None:
        forms.append(("the JointTrajectory", jt.reversals, jt.deviation))
    worse = []
    for what, (rp, rt), dev in forms:
        if rp > exact.reversals_phi:
            worse.append(f"{what}: phi reverses {rp} times (the plan {exact.reversals_phi})")
        if rt > exact.reversals_th1:
            worse.append(f"{what}: th1 reverses {rt} times (the plan {exact.reversals_th1})")
        if dev > exact.deviation * (1.0 + rel) + tol:
            worse.append(f"{what}: its deviation is {math.degrees(dev):.4g} deg (the plan "
                         f"{math.degrees(exact.deviation):.4g} deg)")
    return worse


def _note_samples(req: PlanRequest, exe: Execution, diagnostics: dict[str, Any]) -> None:
    """Say so in the diagnostics when the handed-out path has more samples than asked."""
    if req.controller_period is None and exe.samples > int(req.samples):
        diagnostics["samples"] = {
            "asked": int(req.samples), "handed_out": exe.samples,
            "why": "a linear form of the samples asked for is not the plan's path (more "
                   "reversals, a larger deviation, or no correction onto the goal)"}


def law_kinks(law: TimeLaw) -> np.ndarray:
    """Times where the handed-out rates may have kinks: the phases' starts and the stops."""
    return np.union1d(law.phases.start, law.stops)


def _handed_out(exe: Execution, exact: Indicators) -> Indicators:
    """The indicators of the handed-out path (the default form's replay on the original
    model): all of them, ``d_a`` included (measured on the time the path is handed out
    with). The exact plan's, on its own schedule, are the plan's ``plan_indicators``."""
    return exact if exe.indicators is None else exe.indicators


def actuator_schedule(req: PlanRequest, rates: np.ndarray) -> ActuatorSchedule:
    """Rates ``U`` (N, 2) on equal intervals of normalised time, as a schedule in seconds on
    the plan's own duration (:func:`_plan_duration`; the time law fits the answer's duration
    and limits afterwards: the model is driftless, ``T`` does not change the path)."""
    if req.via_points:  # the via nodes at the via times (optimizer.planner.via)
        return via_schedule(req, rates)
    T = _plan_duration(req)
    return ActuatorSchedule(breaks=np.linspace(0.0, T, rates.shape[0] + 1), rates=rates / T)


def finish_actuator_plan(req: PlanRequest, rates: np.ndarray, method: str,
                         planned_nodes: np.ndarray, timing: dict[str, float],
                         diagnostics: dict[str, Any],
                         refine: Callable[[np.ndarray], np.ndarray] | None = None) -> Plan:
    """Re-integrate, check, sample and measure a plan of piecewise-constant rates.

    ``rates`` (N, 2) are per unit of normalised time on N equal intervals
    (:func:`actuator_schedule` makes them a schedule in seconds). One quadrature of the
    original model under them (cascade quadrature between the breaks, error estimate <= 1e-11
    rad, DOP853 as fallback) proves the plan: on its own mesh (the indicators), at the
    breaks (the region check: enough, every joint is monotone between them, see
    :mod:`.shooting`), at its end (the terminal error) and at the handed-out path's times. The
    linear form of the handed-out path holds these rates exactly, so the same replay is that
    form's own (:func:`optimizer.execution.execute`, its ``constant``); a controller period's
    held form is corrected and replayed on its own. ``planned_nodes`` (the NLP's own node
    states) give the verification's ``max_deviation``.

    ``refine``, given the replay's end state when it misses the goal by more than
    :data:`~optimizer.execution.CORRECTION_TARGET`, returns rates corrected for that miss; they
    are re-integrated and kept when they end closer (once).

    Raises
    ------
    InfeasibleError
        A node of the true path is outside the region.
    NumericalError
        The true path does not reach the goal.
    """
    robot = req.robot
    q0 = req.q_start()
    goal = np.array(req.goal)
    t0 = time.perf_counter()

    def replay(U: np.ndarray) -> tuple[ActuatorSchedule, TimeLaw, Replay, Grid | None,
                                       tuple[np.ndarray, np.ndarray] | None]:
        sched = actuator_schedule(req, U)
        law = plan_time_law(req, sched.u, sched.breaks, True)
        t_eval = sched.breaks
        grid = None
        if law.piecewise_linear and req.controller_period is None:
            # the handed-out linear form holds the law's rates exactly: its replay is this
            # path at the plan times the law reaches on the form's dense grid
            grid = handed_out_times(req, law.T, law.stops, law_kinks(law), True)
            t_eval = np.concatenate([sched.breaks, law.plan_time(grid[1])])
        rep = integrate_cascade(robot, sched.u, q0, sched.duration, t_eval,
                                sched.breaks, nodes=REPLAY_NODES, initial_panels=1,
                                accept=PROOF_ACCEPT, fallback=None, constant_pieces=True)
        dense = None
        if not rep.success and not rep.singular:
            # the quadrature not accepted (on a long path, such as legs', its estimate sums
            # to over its target across the panels): one DOP853 run gives the replay and the
            # indicators' grid, where two ran (seconds each on a 7-joint path of 150 pieces)
            td = np.union1d(np.linspace(0.0, sched.duration, INDICATOR_SAMPLES), sched.breaks)
            full = integrate(robot, sched.u_scalar, q0, sched.duration,
                             np.concatenate([t_eval, td]))
            k = t_eval.size
            rep = dataclasses.replace(
                full, t=t_eval, q=full.q[:k], evaluations=full.evaluations + rep.evaluations,
                message=f"cascade quadrature not accepted ({rep.message}); DOP853: "
                        f"{full.message}")
            dense = (td, full.q[k:])
        return sched, law, rep, grid, dense

    def miss(r: Replay) -> float:
        return float(np.max(np.abs(r.final[1:] - goal))) if r.success else math.inf

    schedule, law, rep, grid, dense = replay(rates)
    if refine is not None and rep.success and miss(rep) > CORRECTION_TARGET:
        again = replay(refine(rep.final))
        if miss(again[2]) < miss(rep):
            schedule, law, rep, grid, dense = again
    breaks = schedule.breaks
    if not rep.success:
        raise NumericalError(f"the re-integration failed: {rep.message}",
                             diagnostics={"method": method})
    # the indicators on the quadrature's own mesh (its states are computed there, and its
    # nodes cluster at the breaks, where the path has its kinks); on a uniform grid and the
    # breaks of a DOP853 replay when the quadrature was not accepted
    if rep.mesh_t is not None and rep.mesh_q is not None:
        td, qd = rep.mesh_t, rep.mesh_q
    else:   # (a replay is the quadrature's, with its mesh, or DOP853's, with its grid)
        assert dense is not None
        td, qd = dense
    timing["verification"] = time.perf_counter() - t0
    qb = rep.q[:breaks.size]
    lo, hi = joint_limits(req)
    th = qb[:, 1:]
    margins = np.minimum(th - lo, hi - th)
    margin = float(np.min(margins))
    # the quadrature's estimate bounds its states' error (DOP853 gives none)
    estimate = float(rep.error_estimate or 0.0)
    if not margin > estimate or rep.singular:
        k, j = np.unravel_index(int(np.argmin(margins)), margins.shape)
        raise InfeasibleError(
            f"the re-integrated path leaves the singularity-free region: th{j + 1} at "
            f"t = {breaks[k]:.6g} s" + ("" if margin <= 0.0 or rep.singular else
                                        f" (within the quadrature's error estimate "
                                        f"{estimate:.2g} rad of its boundary)"),
            diagnostics={"margin": margin})
    final = rep.final
    terminal = float(np.max(np.abs(final[1:] - np.array(req.goal))))
    if not terminal + estimate <= TERMINAL_TOLERANCE:
        raise NumericalError(
            "the planned inputs do not steer the original model to the goal "
            f"(terminal error {terminal:.3g} rad, the quadrature's estimate {estimate:.2g})",
            diagnostics={"terminal_error": terminal, "method": method})
    t1 = time.perf_counter()
    energy = rep.energy
    ind = dataclasses.replace(compute_indicators(td, qd, None), energy=energy)
    dphi = float(final[0] - q0[0])
    ver = Verification(terminal_error=terminal, phi_error=0.0,
                       max_deviation=float(np.max(np.abs(qb - planned_nodes))),
                       singular=False, final=tuple(float(x) for x in final),
                       rtol=CASCADE_TOL, atol=CASCADE_TOL, energy=energy,
                       integrator=rep.integrator, error_estimate=rep.error_estimate)
    timing["sampling"] = time.perf_counter() - t1
    # the handed-out path is the plan's path along its time law (stop and go at every
    # change of direction), corrected for its rule and verified by it
    law, exe = retime_and_execute(req, schedule.u, breaks, True, float(final[0]), ind, method,
                                  law=law, initial=rep, grid=grid, diagnostics=diagnostics)
    if req.via_points:  # the handed-out path through every via point, measured
        diagnostics["via_points"] = check_handed_out(req, exe.path, exe.check.rule)
    timing["execution"] = exe.seconds
    _note_samples(req, exe, diagnostics)
    return Plan(robot=robot, method=method, phi_change=dphi, duration=law.T, inputs=schedule,
                chained=None, feasible_phi_changes=[], indicators=_handed_out(exe, ind),
                margin=margin, path=exe.path, verification=ver, timing=timing,
                diagnostics=diagnostics, execution=exe, time_law=law, plan_indicators=ind)
