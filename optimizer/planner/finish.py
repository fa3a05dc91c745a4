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
from ..execution import (CORRECTION_TARGET, REPLAY_NODES, check_period, execute,
                         linear_times)
from ..indicators import compute_indicators
from ..problem import PlanRequest
from ..results import Plan
from ..steering import ChainedPath, InputSchedule
from ..verify import (CASCADE_TOL, PlannedInputs, Replay, Verification, integrate,
                      integrate_cascade, verify_plan)
from .family import SEARCH_SAMPLES
from .rules import TERMINAL_TOLERANCE, joint_limits, limits_region, make_region

#: Points of the dense grid the indicators are measured on (the searches' own density, so
#: that t_p and d_a agree with what was optimised).
INDICATOR_SAMPLES = SEARCH_SAMPLES
#: Normalised-time samples used to find the peak actuator rates for duration scaling.
RATE_SAMPLES = 2001


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
    # the handed-out path is what a controller executes: corrected for its rule and verified
    # by it (optimizer.execution)
    exe = execute(req, planned.u, planned.breaks, T, req.phi_start + dphi,
                  limits_region(req))
    timing["execution"] = exe.seconds
    return Plan(robot=robot, method=method, phi_change=float(dphi), duration=T, inputs=inputs,
                chained=chained, feasible_phi_changes=feasible, indicators=ind,
                margin=float(chk.margin), path=exe.path, verification=ver, timing=timing,
                diagnostics=diagnostics, execution=exe)


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


def actuator_schedule(req: PlanRequest, rates: np.ndarray) -> ActuatorSchedule:
    """Rates ``U`` (N, 2) on equal intervals of normalised time, as a schedule in seconds: the
    duration is the request's, or the shortest that keeps ``|u| = |U| / T`` within its
    actuator limits (the model is driftless: ``T`` does not change the path)."""
    T = req.duration_for_rates(np.max(np.abs(rates), axis=0))
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

    def replay(U: np.ndarray) -> tuple[ActuatorSchedule, np.ndarray, Replay]:
        sched = actuator_schedule(req, U)
        T = sched.duration
        check_period(req, T)
        times = (linear_times(T, req.samples, sched.breaks) if req.controller_period is None
                 else np.empty(0))
        rep = integrate_cascade(robot, sched.u, q0, T, np.concatenate([sched.breaks, times]),
                                sched.breaks, nodes=REPLAY_NODES, initial_panels=1,
                                fallback=sched.u_scalar, constant_pieces=True)
        return sched, times, rep

    def miss(r: Replay) -> float:
        return float(np.max(np.abs(r.final[1:] - goal))) if r.success else math.inf

    schedule, times, rep = replay(rates)
    if refine is not None and rep.success and miss(rep) > CORRECTION_TARGET:
        again = replay(refine(rep.final))
        if miss(again[2]) < miss(rep):
            schedule, times, rep = again
    T, breaks = schedule.duration, schedule.breaks
    if not rep.success:
        raise NumericalError(f"the re-integration failed: {rep.message}",
                             diagnostics={"method": method})
    # the indicators on the quadrature's own mesh (its states are computed there, and its
    # nodes cluster at the breaks, where the path has its kinks); on a uniform grid and the
    # breaks of a DOP853 replay when the quadrature was not accepted
    if rep.mesh_t is not None and rep.mesh_q is not None:
        td, qd = rep.mesh_t, rep.mesh_q
    else:
        td = np.union1d(np.linspace(0.0, T, INDICATOR_SAMPLES), breaks)
        qd = integrate(robot, schedule.u_scalar, q0, T, td).q
    timing["verification"] = time.perf_counter() - t0
    qb = rep.q[:breaks.size]
    lo, hi = joint_limits(req)
    th = qb[:, 1:]
    margins = np.minimum(th - lo, hi - th)
    margin = float(np.min(margins))
    if not margin > 0.0 or rep.singular:
        k, j = np.unravel_index(int(np.argmin(margins)), margins.shape)
        raise InfeasibleError(
            f"the re-integrated path leaves the singularity-free region: th{j + 1} at "
            f"t = {breaks[k]:.6g} s", diagnostics={"margin": margin})
    final = rep.final
    terminal = float(np.max(np.abs(final[1:] - np.array(req.goal))))
    if not terminal <= TERMINAL_TOLERANCE:
        raise NumericalError(
            "the planned inputs do not steer the original model to the goal "
            f"(terminal error {terminal:.3g} rad)",
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
    # the handed-out path is what a controller executes: corrected for its rule and verified
    # by it (optimizer.execution), the breaks in seconds exact in its times
    exe = execute(req, schedule.u, breaks, T, float(final[0]), limits_region(req),
                  constant=rep if times.size else None,
                  linear=times if times.size else None)
    timing["execution"] = exe.seconds
    return Plan(robot=robot, method=method, phi_change=dphi, duration=T, inputs=schedule,
                chained=None, feasible_phi_changes=[], indicators=ind, margin=margin,
                path=exe.path, verification=ver, timing=timing, diagnostics=diagnostics,
                execution=exe)
