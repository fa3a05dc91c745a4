"""A continuation proved on the original model and answered in a plan's shape.

The replanner (:mod:`.replan`) finds a continuation: geometric pieces of constant rates from
the measured state and the time law that runs them (:class:`Continuation`). This module is
what every route's continuation goes through before it is handed out
(:func:`finish_continuation`):

* **the pieces' proof**: integrated on the original model by compiled RK4 at two step sizes
  (:func:`~.piece_proof.integrate_pieces`, Richardson's error estimate), by cascade
  quadrature where that estimate is above its target; a miss above 1e-9 rad gets one
  defect-corrected step (the continuation's ``refine``);
* **the region**: every joint at every break (each joint is monotone on a piece of
  constant rates), and the corrected part :data:`REPLAN_MARGIN` from the limits, or half the
  room its stop or the goal leaves (:func:`required_margin`): the plant is not the model;
* **the handed-out form**: samples on an even grid and at every phase start; under a smooth
  time law the linear interpolation of the samples is corrected and replayed
  (:func:`~optimizer.forms.correct`), more densely sampled where it misses or exceeds the
  plan's rate limits;
* **the answer**: a plan answer's fields (indicators measured on the samples, the pieces,
  the time law, the validation of both the exact pieces and the executed form, and the
  replan's diagnostics: route, signs, limits measured against the plan's bounds).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..chained_form import chained_form
from ..errors import InfeasibleError, NumericalError
from ..execution import even_times
from ..forms import EXECUTION_TOLERANCE, LIMIT_TOLERANCE, REPLAY_NODES, correct, linear_form
from ..indicators import compute_indicators
from ..model import Robot
from ..problem import PlanRequest
from ..timing import Limits
from ..verify import integrate_cascade
from .continuation_law import measured_limits, slope_jump
from .finish import DENSIFY_SAMPLES
from .nlp import MARGIN
from .piece_proof import integrate_pieces
from .plan_state import REST, PlanState, TimeLaw
from .rules import TERMINAL_TOLERANCE, limits_region

#: Distance (rad) from the limits that a continuation's corrected part keeps (half the
#: planner's node margin, :data:`~.nlp.MARGIN`), or half the room its stop or goal leaves.
REPLAN_MARGIN = 0.5 * MARGIN


@dataclass(frozen=True)
class Continuation:
    """Geometric pieces from the measured state and the time law that runs them."""

    breaks: np.ndarray          # plan time sigma (s)
    rates: np.ndarray           # (M, 2) rad per s of plan time
    law: TimeLaw
    plan_duration: float
    route: str
    steps: int
    kept: int = 0               # 1: the first piece is the commanded motion run on
    refine: Any = None          # (exact end, free rates) -> free rates (one defect step)
    signs_kept: bool = False    # every corrected rate kept its sign (no reversal added)
    braked: bool = False        # the motion under way braked now (not run to its piece's end)


def required_margin(q_stop: np.ndarray, goal: np.ndarray, lo: np.ndarray, hi: np.ndarray
                     ) -> np.ndarray:
    """Per joint, the distance (rad) from its limits that a continuation's corrected part
    keeps: :data:`REPLAN_MARGIN`, or half the room the stop ``q_stop`` or the goal leaves
    where that is less (the planner's rule for its nodes, :func:`~.nlp.node_bounds`)."""
    room = np.minimum(np.minimum(q_stop - lo, hi - q_stop), np.minimum(goal - lo, hi - goal))
    return np.minimum(REPLAN_MARGIN, 0.5 * np.maximum(room, 0.0))


def _piece(breaks: np.ndarray, s: np.ndarray) -> np.ndarray:
    # (np.minimum/np.maximum: np.clip costs 2-3 us a call on these small arrays)
    return np.minimum(np.maximum(np.searchsorted(breaks, s, side="right") - 1, 0),
                      breaks.size - 2)


def _replay(robot: Robot, q_m: np.ndarray, cont: Continuation, rates: np.ndarray,
            s_eval: np.ndarray) -> Any:
    sb = cont.breaks - cont.breaks[0]
    L = float(sb[-1])
    # compiled RK4 with Richardson's error estimate; where that is above the cascade's
    # target, the cascade quadrature
    proof = integrate_pieces(tuple(robot.gains), tuple(robot.exponents), q_m, sb, rates,
                             np.clip(s_eval, 0.0, L))
    if proof is not None:
        return proof
    return integrate_cascade(robot, lambda s: rates[_piece(sb, s)], q_m, L,
                             np.clip(np.concatenate([sb, s_eval]), 0.0, L), sb,
                             nodes=REPLAY_NODES, initial_panels=1, constant_pieces=True)


def _form_peaks(times: np.ndarray, u: np.ndarray) -> dict[str, float]:
    """The largest ``|u_i|`` of the samples and ``|u_i'|`` of their linear interpolant."""
    dt = np.diff(times)
    ok = dt > 1e-12
    slope = np.abs(np.diff(u, axis=0))[ok] / dt[ok, None]
    peaks = np.abs(u).max(axis=0), slope.max(axis=0, initial=0.0)
    return {name: float(value) for names, values in zip(Limits.NAMES, peaks)
            for name, value in zip(names, values)}


def _form_beyond(ps: PlanState, times: np.ndarray, u: np.ndarray) -> bool:
    """The handed-out linear form exceeds one of the plan's bounds on ``|u|`` or ``|u'|``."""
    if not ps.limits.any:
        return False
    peaks = _form_peaks(times, u)
    return any(peaks[name] > value * (1.0 + LIMIT_TOLERANCE)
               for name, value in ps.limits.as_dict().items() if name in peaks)


def finish_continuation(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
            cont: Continuation, timing: dict[str, float],
            limits: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    """Verify a continuation on the original model and answer it in a plan's shape
    (``limits``: the joints' bounds on the way, :func:`~.rules.joint_limits` of ``req``).

    Raises
    ------
    InfeasibleError
        A joint leaves its limits (checked at every break: each joint is monotone on a piece
        of constant rates), or comes nearer to them after the stop than
        :func:`required_margin` allows.
    NumericalError
        The exact pieces, or the handed-out form, miss the goal by more than
        :data:`~.rules.TERMINAL_TOLERANCE`.
    """
    t0 = time.perf_counter()
    robot, goal = ps.robot, ps.goal
    law = cont.law
    T_end = law.end
    sb = cont.breaks - cont.breaks[0]
    # the handed-out times: an even grid (a sample within a quarter of its spacing of a phase
    # start moved onto it: no sliver intervals, which a naive union left 1e-16 s wide) and
    # every phase start; where the rates jump (a break passed at speed: plans without a time
    # law) the time is there twice
    starts = law.phases[:, 0]
    times = even_times(t, T_end, ps.samples, starts[(starts > t) & (starts < T_end)])
    sig, ds, _ = law.evaluate(times)
    # at the stops sigma' is 0 up to rounding of the cubics: the drive is told exactly 0
    ds[np.abs(ds) <= 1e-12 * max(1.0, float(np.abs(ds).max()))] = 0.0
    sl = np.minimum(np.maximum(sig - cont.breaks[0], 0.0), float(sb[-1]))
    ph = law.phases
    # (a comparison of every pair: np.isin costs about 15 us on these few values)
    at_break = (ph[:, 2, None] == cont.breaks[None, 1:-1]).any(axis=1)
    jump_t = ph[(ph[:, 3] > REST) & at_break & (ph[:, 0] > t), 0]
    rates = cont.rates
    rep = _replay(robot, q_m, cont, rates, sl)
    miss = float(np.abs(rep.final[1:] - goal).max()) if rep.success else math.inf
    if cont.refine is not None and rep.success and miss > 1e-9:
        free = cont.refine(rep.final, rates[cont.kept:])
        again = np.vstack([rates[:cont.kept], free])
        # the defect step has any sign: where the correction kept every rate's sign it may
        # not undo that (a 4-joint closed loop's step turned four positive rates of phi
        # negative, a reversal more that keep_reversals had refused elsewhere)
        if not cont.signs_kept or np.array_equal(np.sign(again), np.sign(rates)):
            rep2 = _replay(robot, q_m, cont, again, sl)
            miss2 = float(np.abs(rep2.final[1:] - goal).max()) if rep2.success else math.inf
            if miss2 < miss:
                rep, miss, rates = rep2, miss2, again
    timing["verification"] = time.perf_counter() - t0
    if not rep.success:
        raise NumericalError(f"the continuation's re-integration failed: {rep.message}")
    lo, hi = limits
    qb = rep.q[:sb.size, 1:]
    margins = np.minimum(qb - lo, hi - qb)
    margin = float(margins.min())
    # (a joint that reaches 0 or pi/2 is outside its limits too: the region is within them)
    if not margin > 0.0 or rep.singular:
        j = int(np.unravel_index(int(np.argmin(margins)), margins.shape)[1])
        raise InfeasibleError(f"the continuation takes th{j + 1} outside its limits "
                              f"({lo[j]:.6g}, {hi[j]:.6g}) rad (margin {margin:.3g} rad)",
                              diagnostics={"margin": margin, "singular": bool(rep.singular)})
    # the corrected part keeps a margin (the plant is not the model: a Gauss-Newton
    # correction that ran a 4-joint continuation 1e-4 rad from pi/2 let a plant with gains
    # 5 % off cross it by 2.6e-3 rad); less only where the stop or the goal is nearer
    need = required_margin(qb[cont.kept], goal, lo, hi)
    later = margins[cont.kept:]
    if (later < need).any():
        j = int(np.unravel_index(int(np.argmin(later - need)), later.shape)[1])
        raise InfeasibleError(
            f"the continuation takes th{j + 1} within {float(np.min(later[:, j])):.3g} rad of "
            f"its limits ({lo[j]:.6g}, {hi[j]:.6g}) rad, nearer than the "
            f"{float(need[j]):.3g} rad a continuation keeps", diagnostics={"margin": margin})
    if not miss <= TERMINAL_TOLERANCE:
        raise NumericalError(f"the continuation misses the goal by {miss:.3g} rad",
                             diagnostics={"terminal_error": miss})
    q = rep.q[sb.size:]
    k = _piece(sb, sl)
    u = rates[k] * ds[:, None]
    u[0] = u_c          # the commanded rates (equal to the plan's up to rounding)
    if jump_t.size:     # the rate before each jump, as the linear form's first copy
        at = np.searchsorted(times, jump_t)
        before = rates[np.maximum(k[at] - 1, 0)] * ds[at][:, None]
        times = np.insert(times, at, jump_t)
        q = np.insert(q, at, q[at], axis=0)
        u = np.insert(u, at, before, axis=0)
    cf = chained_form(robot)
    al, be = cf.input_coefficients(q)
    v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
    smooth_law = not law.piecewise_linear
    exe_initial = None
    corrections = 0
    if smooth_law:
        # continuous rates: linear interpolation of their samples is not the exact rates; the
        # samples are corrected until the original model under that rule reaches the goal
        # (optimizer.execution.correct), the first (the commanded rates) and the last (rest)
        # held
        form = linear_form(times - t, held=np.array([0, times.size - 1]))
        target = np.concatenate([[rep.final[0]], goal])
        u, q, check = correct(robot, form, u, q_m, target, limits_region(req), times - t,
                              ps.limits.rate)
        exe_final = np.asarray(check.final)
        exe_integrator = check.integrator
        exe_initial, corrections = check.initial_terminal_error, check.corrections
        if not check.terminal_error <= EXECUTION_TOLERANCE or check.singular or \
                not check.margin > 0.0 or _form_beyond(ps, times, u):
            if ps.samples < DENSIFY_SAMPLES:
                # too coarse for these rates (a plan under a jerk limit is handed out with
                # hundreds of samples a second): the same continuation, twice as densely
                # sampled, as the planner makes its own path denser
                denser = replace(ps, samples=min(2 * ps.samples - 1, DENSIFY_SAMPLES))
                return finish_continuation(denser, req, t, q_m, u_c, cont, timing, limits)
            executed = (check.terminal_error <= EXECUTION_TOLERANCE and not check.singular
                        and check.margin > 0.0)
            if not executed:    # (beyond a limit only: reported, diagnostics.replan.limits)
                raise NumericalError(
                    f"the handed-out path of {times.size} samples misses the goal by "
                    f"{check.terminal_error:.3g} rad when executed (margin "
                    f"{check.margin:.3g} rad)", diagnostics={"execution": check.as_dict()})
        al, be = cf.input_coefficients(q)
        v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
    else:
        exe_final, exe_integrator = rep.final, rep.integrator
    exe_err = float(np.abs(exe_final[1:] - goal).max())
    ind = compute_indicators(times, q, u)
    timing["sampling"] = time.perf_counter() - t0 - timing["verification"]
    out: dict[str, Any] = {
        "status": "success",
        "method": "replan",
        "robot": robot.as_dict(),
        "goal": goal.tolist(),
        "time": t,
        "phi_change": float(rep.final[0] - q_m[0]),
        "b0": None,
        "duration": T_end,
        "feasible_phi_changes": [],
        "coefficients": {
            "basis": "actuator rates u = (u1, u2) (rad per s of plan time) constant on each "
                     "segment of plan time sigma; the rates at time t are u(sigma(t)) "
                     "sigma'(t) (time_law)",
            "segments": [{"t_start": float(a), "t_end": float(b), "v1": [float(r[0])],
                          "v2": [], "u": [float(r[0]), float(r[1])]}
                         for a, b, r in zip(cont.breaks[:-1], cont.breaks[1:], rates)]},
        "time_law": law.as_dict(cont.plan_duration, cont.breaks, ps.limits),
        "indicators": {
            "d_a": ind.d_a, "d_a_per_joint": list(ind.d_a_per_joint),
            "d_a_joint_space": ind.d_a_joint_space, "t_p": ind.t_p,
            "phi_reversals": ind.phi_reversals, "sensitivity": ind.sensitivity,
            "sensitivity_max": ind.sensitivity_max, "energy": ind.energy, "margin": margin,
            "deviation": ind.deviation,
            "reversals": {"phi": ind.reversals_phi, "th1": ind.reversals_th1}},
        "path": {"t": times, "q": q, "z": cf.to_chained(q), "u": u, "v": v, "rule": "linear"},
        "validation": {
            "terminal_error": miss, "phi_error": 0.0, "max_deviation": 0.0, "singular": False,
            "final": rep.final.tolist(), "integrator": f"{rep.integrator} on the original model",
            "error_estimate": rep.error_estimate, "rtol": None, "atol": None,
            "executed": {"rule": "linear", "terminal_error": exe_err, "phi_error":
                         float(abs(exe_final[0] - rep.final[0])), "margin": margin,
                         "singular": False, "initial_terminal_error":
                         exe_err if exe_initial is None else exe_initial,
                         "corrections": corrections, "integrator": f"{exe_integrator} on the original "
                         "model", "final": exe_final.tolist()}},
        "timing": dict(timing),
        "diagnostics": {"replan": {
            "route": cont.route, "gauss_newton_steps": cont.steps,
            "signs_kept": cont.signs_kept, "braked": cont.braked,
            "kept_piece": bool(cont.kept), "pieces": int(rates.shape[0]),
            "commanded_rates": [float(x) for x in u_c],
            "start_state": q_m.tolist()}},
    }
    if ps.limits.any:
        # the bounds the plan keeps to, and the continuation's rates measured against them
        # (the motion under way, run on or braked from its commanded rates, may need more)
        bounds = ps.limits.as_dict()
        # the rates and slopes of the handed-out linear form (what a drive runs), the
        # rates' second derivative of the law
        measured = {**measured_limits(law, cont.breaks, rates), **_form_peaks(times, u)}
        jump = slope_jump(law, cont.breaks, rates)
        out["diagnostics"]["replan"]["limits"] = {
            "bounds": bounds, "measured": {k: measured[k] for k in bounds},
            # under a jerk bound the rates' slopes must be continuous: a jump (the motion
            # under way braked at a constant rate) is an unbounded jerk
            "slope_jump": jump,
            "within": all(measured[k] <= v * (1.0 + LIMIT_TOLERANCE)
                          for k, v in bounds.items())
            and not (ps.limits.jerk_bounded and jump > 1e-6 * max(1.0, measured["max_du1"],
                                                        measured["max_du2"])),
            "later_than_asked": max(T_end - (t + float(req.duration or 0.0)), 0.0)}
    if ps.joint_bounds is not None:
        out["joint_bounds"] = [None if b is None else list(b) for b in ps.joint_bounds]
    return out


__all__ = ["REPLAN_MARGIN", "Continuation", "finish_continuation", "required_margin"]
