"""Analyses around plans: indicator sweeps over dphi, batch transforms, perturbed-start replays.

These back the service's ``/v1/sweeps``, ``/v1/transforms`` and ``/v1/robustness`` endpoints and
the paper's Figs 11-14 and b0 map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from .chained_form import chained_form
from .errors import InvalidRequestError, NumericalError, PlannerError
from .execution import HandedOutInputs
from .identification import GainEstimator
from .indicators import (compute_indicators, count_reversals, segment_distance,
                         sensitivity_frobenius)
from .model import Robot
from .planner.family import PolynomialFamily
from .planner.intervals import feasible_intervals
from .planner.context import Deadline
from .planner.replan import PlanState, read_plan, replan
from .planner.rules import check_endpoints, kept_limits, make_region
from .region import Region
from .problem import PlanRequest
from .results import Plan
from .verify import PlannedInputs, replay

MAX_SWEEP_POINTS = 5001


def sweep(req: PlanRequest, lo: float, hi: float, points: int,
          intervals: bool = True) -> dict[str, Any]:  # noqa: C901
    """Indicators and feasibility of the paper's family as functions of ``dphi``.

    Parameters
    ----------
    req : PlanRequest
        Robot, start, goal, duration, criterion and constraint points are used; its
        ``time_limit`` bounds the sweep (:class:`SolverTimeoutError` past it).
    lo, hi : float
        ``dphi`` range (rad).
    points : int
        Number of evenly spaced ``dphi`` values.
    intervals : bool
        Also compute the exact feasible intervals inside [lo, hi].

    Returns
    -------
    dict
        ``phi_change``, ``feasible``, ``margin``, ``d_a``, ``t_p``, ``sensitivity``,
        ``energy`` (lists; ``None`` where a member is not feasible) and
        ``feasible_phi_changes``.
    """
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise InvalidRequestError("phi_change_range must be finite with lo < hi",
                                  field="phi_change_range")
    if not 2 <= points <= MAX_SWEEP_POINTS:
        raise InvalidRequestError(f"points = {points} must lie in [2, {MAX_SWEEP_POINTS}]",
                                  field="points")
    region = make_region(req)
    check_endpoints(req, make_region(req, "full"))
    deadline = Deadline(req.time_limit)
    fam = PolynomialFamily(req.robot, req.q_start(), req.q_goal(0.0), req.duration_or_default,
                           req.constraint_points, region, deadline.check)
    ds = np.linspace(lo, hi, points)
    out: dict[str, list[Any]] = {k: [] for k in ("phi_change", "feasible", "margin", "d_a", "t_p",
                                                 "sensitivity", "energy")}
    for d in ds:
        e = fam.evaluate(float(d))
        out["phi_change"].append(float(d))
        out["feasible"].append(bool(e.ok))
        out["margin"].append(float(e.margin) if np.isfinite(e.margin) else None)
        out["d_a"].append(e.d_a if e.ok else None)
        out["t_p"].append(e.t_p if e.ok else None)
        out["sensitivity"].append(float(sensitivity_frobenius(d, req.n)))
        out["energy"].append(e.energy if e.ok else None)
    res: dict[str, Any] = dict(out)
    res["criterion"] = req.singularity
    res["feasible_phi_changes"] = (
        [[a, b] for a, b in feasible_intervals(fam, lo, hi)] if intervals else None)
    return res


@dataclass(frozen=True)
class TransformedPoint:
    values: list[float]
    valid: bool
    reason: str | None


def transform(robot: Robot, direction: str, points: np.ndarray) -> list[TransformedPoint]:
    """Map points ``q -> z`` (``to_chained``) or ``z -> q`` (``from_chained``).

    ``to_chained`` is defined everywhere but is a diffeomorphism only inside the region: points
    outside are mapped and flagged ``valid = False`` with the reason. ``from_chained`` returns
    zeros and the reason where no inverse exists.
    """
    pts = np.atleast_2d(np.asarray(points, float))
    if pts.shape[1] != robot.n + 1:
        raise InvalidRequestError(f"each point must have n + 1 = {robot.n + 1} entries",
                                  field="points")
    if not np.all(np.isfinite(pts)):
        raise InvalidRequestError("points must be finite numbers", field="points")
    cf = chained_form(robot)
    out = []
    if direction == "to_chained":
        z = cf.to_chained(pts)
        region = make_region(PlanRequest(start=tuple([0.5] * robot.n), goal=tuple([0.5] * robot.n),
                                         robot=robot), "full")
        marg = region.margin_q(pts)
        for i in range(pts.shape[0]):
            ok = bool(marg[i] > 0.0)
            reason = None
            if not ok:
                j = int(np.argmin(np.minimum(pts[i, 1:] - region.lower, region.upper - pts[i, 1:])))
                reason = (f"th{j + 1} = {pts[i, j + 1]:.6g} rad is outside (0, pi/2): the transform is "
                          "not invertible there")
            out.append(TransformedPoint(z[i].tolist(), ok, reason))
    elif direction == "from_chained":
        inv = cf.from_chained(pts)
        for i, r in enumerate(inv.reasons()):
            out.append(TransformedPoint(inv.q[i].tolist(), bool(inv.valid[i]), r))
    else:
        raise InvalidRequestError("direction must be 'to_chained' or 'from_chained'",
                                  field="direction")
    return out


def perturbed_starts(nominal: Sequence[float], count: int, spread: float, seed: int) -> np.ndarray:
    """``count`` starts drawn uniformly in ``nominal +- spread`` (rad), reproducibly."""
    rng = np.random.default_rng(seed)
    nom = np.asarray(nominal, float)
    return nom + rng.uniform(-spread, spread, size=(count, nom.size))


def robustness(plan: Plan, starts: np.ndarray, mode: str, goal: Sequence[float],
               time_limit: float | None = None, deadline: Deadline | None = None
               ) -> dict[str, Any]:
    """Replay a plan open loop from perturbed starts (NOTES §7) and measure each run.

    Parameters
    ----------
    plan : Plan
    starts : ndarray (R, n)
        Joint angles ``th_1..th_n`` of each run's start (``phi`` starts at the plan's).
    mode : {"u", "v"}
        ``u``: the handed-out rates ``path.u`` executed by their rule (``path.rule``: what a
        controller runs); ``v``: the plan's chained inputs pushed through eq 5 at the actual
        state.
    goal : sequence of float
        The nominal goal ``th_1..th_n``.
    time_limit : float, optional
        Seconds for all the replays (:class:`SolverTimeoutError` past it, checked between runs).
    deadline : Deadline, optional
        Instead of ``time_limit``: a deadline already running (the request's, started before
        its nominal plan).
    """
    if mode not in ("u", "v"):
        raise InvalidRequestError("replay must be 'u' or 'v'", field="replay")
    cf = chained_form(plan.robot)
    if plan.chained is None and mode == "v":  # actuator-rate plan (shooting)
        raise InvalidRequestError(
            f"replay 'v' needs chained inputs; method {plan.method!r} plans actuator rates "
            "(use replay 'u')", field="replay")
    inputs: Any
    if mode == "u" and plan.execution is not None:
        # what a controller runs: the handed-out rates under their rule (optimizer.execution)
        inputs = HandedOutInputs(plan.path, plan.execution.check.rule)
    elif plan.chained is None:
        inputs = plan.inputs
    else:
        inputs = PlannedInputs(cf, plan.chained)
    t = plan.path.t
    phi0 = float(plan.path.q[0, 0])
    goal_arr = np.asarray(goal, float)
    if deadline is None:
        deadline = Deadline(time_limit if time_limit is not None else float("inf"))
    runs: list[dict[str, Any]] = []
    for s in np.atleast_2d(starts):
        deadline.check(f"the robustness replays ({len(runs)} of {len(np.atleast_2d(starts))} done)")
        if s.size != plan.robot.n or not np.all(np.isfinite(s)):
            raise InvalidRequestError(f"each start must have n = {plan.robot.n} finite angles",
                                      field="starts")
        q0 = np.concatenate([[phi0], s])
        if isinstance(inputs, HandedOutInputs):
            rep = inputs.replay(plan.robot, q0, t)
        else:
            rep = replay(plan.robot, inputs, q0, mode, t)
        if rep.singular:
            ind = None
        else:
            u = inputs.u(t) if mode == "u" else np.gradient(rep.q[:, :2], t, axis=0)
            ind = compute_indicators(t, rep.q, u)
        runs.append({
            "start": s.tolist(),
            "final": rep.final[1:].tolist(),
            "terminal_error": float(np.max(np.abs(rep.final[1:] - goal_arr))),
            "d_a": ind.d_a if ind else None,
            "t_p": ind.t_p if ind else None,
            "singular": bool(rep.singular),
            "singular_time": rep.singular_time,
            "path_q": rep.q.tolist(),
        })
    errs = np.array([r["terminal_error"] for r in runs]) if runs else np.zeros(0)
    das = [r["d_a"] for r in runs if r["d_a"] is not None]
    summary = {
        "runs": len(runs),
        "singular_runs": int(sum(r["singular"] for r in runs)),
        "terminal_error_max": float(errs.max()) if errs.size else 0.0,
        "terminal_error_mean": float(errs.mean()) if errs.size else 0.0,
        "d_a_max": float(max(das)) if das else None,
        "t_p_max": max((r["t_p"] for r in runs if r["t_p"] is not None), default=None),
        "nominal_d_a": plan.indicators.d_a,
        "nominal_t_p": plan.indicators.t_p,
        "sensitivity": plan.indicators.sensitivity,
        "replay": mode,
    }
    return {"runs": runs, "summary": summary}


# ---------------------------------------------------------------------- closed loop
#: Tolerances of the plant's integration (scipy DOP853, between the inputs' knots).
PLANT_RTOL = 1e-11
PLANT_ATOL = 1e-13
#: Samples of each run's executed path per replan period (deviation, margin, reversals, figure).
PATH_POINTS_PER_PERIOD = 6


def _commanded_rates(ps: PlanState, t: np.ndarray) -> np.ndarray:
    """The rates a plan commands at times ``t`` (open loop): ``U(sigma(t)) sigma'(t)``."""
    assert ps.rates is not None
    sig, ds, _ = ps.law.evaluate(t)
    k = np.clip(np.searchsorted(ps.breaks, sig, side="right") - 1, 0, ps.rates.shape[0] - 1)
    return ps.rates[k] * np.asarray(ds)[..., None]


def _drive(plant: Robot, ps: PlanState, q0: np.ndarray, t0: float, t1: float,
           out_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integrate the plant from ``q0`` at ``t0`` to ``t1`` under the plan's rates, knot to knot
    (the rates are smooth between the time law's phase starts); states at ``out_t`` too."""
    knots = ps.law.phases[:, 0]
    edges = np.unique(np.concatenate([[t0, t1], knots[(knots > t0) & (knots < t1)]]))
    q = np.asarray(q0, float)
    rows = []
    for a, b in zip(edges[:-1], edges[1:]):
        mid = 0.5 * (a + b)
        sig_mid = float(ps.law.evaluate(np.array([mid]))[0][0])
        k = int(np.clip(np.searchsorted(ps.breaks, sig_mid, side="right") - 1, 0,
                        ps.breaks.size - 2))
        U = ps.rates[k]   # type: ignore[index]

        def rhs(t: float, x: np.ndarray, U: np.ndarray = U) -> np.ndarray:
            ds = float(ps.law.evaluate(np.array([t]))[1][0])
            return plant.rhs(x, U * ds)

        inside = out_t[(out_t > a) & (out_t <= b)]
        te = np.unique(np.concatenate([inside, [b]]))
        sol = solve_ivp(rhs, (a, b), q, method="DOP853", rtol=PLANT_RTOL, atol=PLANT_ATOL,
                        t_eval=te)
        if not sol.success:
            raise NumericalError(f"the plant's integration failed: {sol.message}")
        rows.append(sol.y.T[np.isin(te, inside)])
        q = sol.y[:, -1]
    states = np.vstack(rows) if rows else np.zeros((0, q.size))
    return q, states


def closed_loop_run(plan: Plan | dict[str, Any], start: Sequence[float] | np.ndarray,
                    gain_errors: Sequence[float] | np.ndarray, period: float | None,
                    noise: float = 0.0, seed: int = 0,
                    joint_limits: tuple[np.ndarray, np.ndarray] | None = None,
                    keep_reversals: bool = False, identify: bool = False,
                    timings: list[float] | None = None) -> dict[str, Any]:
    """Run a plan on a plant whose gains are off, from ``start``; with ``period``, replan from
    the measured state every ``period`` s (:func:`~optimizer.planner.replan.replan`), else
    open loop.

    Parameters
    ----------
    plan : Plan or dict
        An actuator-rate plan (its answer or the library's :class:`Plan`).
    start : sequence of float
        The plant's true start ``th_1..th_n`` (``phi`` starts at the plan's).
    gain_errors : sequence of float
        Relative errors of the plant's ``K_2..K_n`` (``K_i (1 + e_i)``).
    period : float or None
        Seconds between replans (the first at the plan's start); None: open loop.
    noise : float
        Standard deviation (rad) of the measurement noise on every joint and ``phi``.
    seed : int
        Seed of the noise.
    joint_limits : (lo, hi), optional
        For the margin (default: the limits the planner keeps, :func:`~.planner.rules.kept_limits`:
        ``(0, pi/2)`` narrowed by the plan's ``joint_bounds``; the last joint free where its
        start or goal lies outside).
    keep_reversals : bool
        Passed to the replanner: a continuation that adds a reversal is refused, and the run
        goes on with the current plan.
    identify : bool
        Estimate the plant's gains from the measured motion
        (:class:`~optimizer.identification.GainEstimator`, every period) and replan on them.
    timings : list, optional
        Each replan's CPU seconds (``time.process_time``, refused ones too) are appended here
        (a benchmark's latency of the replans a loop makes; not part of the result, which is
        a function of the arguments alone).

    Returns
    -------
    dict
        ``final``, ``terminal_error`` (rad, ``max |th(T) - goal|``), ``reversals``
        (``phi`` and ``th1`` of the executed path), ``deviation`` (largest distance of the
        executed joints from the segment start -> goal, rad), ``margin`` (smallest distance
        to the limits along the path, rad), ``replans`` (accepted), ``replan_failures``,
        ``path_t``, ``path_q``; with ``identify``, ``gains_estimated`` (the last estimate).
    """
    ps = read_plan(plan)
    if ps.rates is None:
        raise InvalidRequestError("closed-loop runs take actuator-rate plans (shooting, "
                                  "penalty)", field="plan.method")
    robot = ps.robot
    plant = Robot(tuple(k * (1.0 + e) for k, e in zip(robot.gains, gain_errors)),
                  robot.exponents)
    rng = np.random.default_rng(seed)
    t, T = ps.start_time, ps.end_time
    phi0 = float(_phi_start(plan))
    q = np.concatenate([[phi0], np.asarray(start, float)])
    current = ps
    out_t = [t]
    out_q = [q.copy()]
    replans = failures = 0
    step = (T - t) / 50 if period is None else float(period)
    estimator = GainEstimator(robot) if identify and period is not None else None
    last: tuple[float, np.ndarray, PlanState] | None = None  # the previous measurement
    while t < T - 1e-12:
        t_next = min(t + step, T)
        if period is not None:
            measured = q + (rng.normal(0.0, noise, q.size) if noise > 0.0 else 0.0)
            gains = None
            if estimator is not None:
                if last is not None:
                    t_a, q_a, driven = last

                    def commanded(s: float, ps_: PlanState = driven) -> np.ndarray:
                        return _commanded_rates(ps_, np.array([s]))[0]
                    estimator.update(q_a, measured, commanded, t_a, t, driven.law.phases[:, 0])
                gains = estimator.gains
            rates_now = _commanded_rates(current, np.array([t]))[0]
            cpu0 = time.process_time()
            try:
                cont = replan(current, t, measured, rates=rates_now, plain=False,
                              keep_reversals=keep_reversals, gains=gains)
                current = read_plan(cont)
                # (a plan with rate limits: a continuation may need longer than the plan)
                T = current.end_time
                replans += 1
            except PlannerError:
                failures += 1
            if timings is not None:
                timings.append(time.process_time() - cpu0)
            last = (t, measured, current)
        grid = np.linspace(t, t_next, PATH_POINTS_PER_PERIOD + 1)[1:]
        q, states = _drive(plant, current, q, t, t_next, grid)
        out_t.extend(grid.tolist())
        out_q.extend(states.tolist())
        t = t_next
    path_q = np.asarray(out_q)
    if joint_limits is None:
        joint_limits = kept_limits(Region(robot, joint_bounds=ps.joint_bounds), ps.joint_bounds,
                                   np.asarray(start, float), ps.goal)
    lo, hi = joint_limits
    th = path_q[:, 1:]
    return {
        "final": q[1:].tolist(),
        "terminal_error": float(np.max(np.abs(q[1:] - ps.goal))),
        "reversals": int(count_reversals(path_q[:, 0]) + count_reversals(path_q[:, 1])),
        "deviation": segment_distance(th, np.asarray(start, float), ps.goal),
        "margin": float(np.min(np.minimum(th - lo, hi - th))),
        "replans": replans,
        "replan_failures": failures,
        "path_t": out_t,
        "path_q": path_q.tolist(),
        **({"gains_estimated": estimator.gains.tolist()} if estimator is not None else {}),
    }


def _phi_start(plan: Plan | dict[str, Any]) -> float:
    if isinstance(plan, Plan):
        return float(plan.path.q[0, 0])
    diag = (plan.get("diagnostics") or {}).get("replan") or {}
    if diag.get("start_state"):
        return float(diag["start_state"][0])
    q = (plan.get("path") or {}).get("q")
    return 0.0 if q is None or len(q) == 0 else float(q[0][0])


#: What each closed-loop run reports side by side (open and closed loop), besides its path.
RUN_FIELDS = ("terminal_error", "reversals", "deviation", "margin", "replans",
              "replan_failures", "final")
#: ... and, closed loop with identification, the last estimate of the plant's gains.
ESTIMATE_FIELD = "gains_estimated"


def closed_loop_robustness(plan: Plan, starts: np.ndarray, gain_error: float, period: float,
                           noise: float = 0.0, seed: int = 0, *, paths: bool = False,
                           deadline: Deadline | None = None,
                           identify: bool = False,
                           keep_reversals: bool = False) -> dict[str, Any]:
    """Each start on its own plant (gains ``K_i (1 + e_i)``, ``e_i`` uniform in
    ``+-gain_error``, seeded), open loop and closed loop (:func:`closed_loop_run` with
    ``period`` and measurement ``noise``; ``identify``: estimating the plant's gains as it
    goes; ``keep_reversals``: a continuation that would reverse an actuator more often than
    the plan's rest is refused, and the run goes on with the current plan), side by side.

    Returns
    -------
    dict
        ``runs``: per start its ``start``, ``gain_errors``, ``open`` and ``closed`` (the
        fields of :data:`RUN_FIELDS`; ``path_t``/``path_q`` too with ``paths``);
        ``summary``: medians and worst of both, the median ratio of the terminal errors, the
        runs with no more reversals closed than the plan has, and those whose joints stayed
        inside throughout.

    Raises
    ------
    InvalidRequestError
        The plan's inputs are not actuator rates (``closed_loop``).
    """
    if plan.chained is not None:
        raise InvalidRequestError(
            f"the closed-loop mode continues actuator-rate plans (shooting, penalty: the default "
            f"auto gives one); method {plan.method!r} plans chained inputs", field="closed_loop")
    answer = plan.to_dict()
    rng = np.random.default_rng(seed)
    nominal = int(plan.indicators.reversals_phi + plan.indicators.reversals_th1)
    runs = []
    keep = RUN_FIELDS + (("path_t", "path_q") if paths else ())
    for i, s in enumerate(np.atleast_2d(starts)):
        if deadline is not None:
            deadline.check(f"the closed-loop runs ({i} of {len(np.atleast_2d(starts))} done)")
        e = rng.uniform(-gain_error, gain_error, plan.robot.n - 1)
        op = closed_loop_run(answer, s, e, None)
        cl = closed_loop_run(answer, s, e, period, noise=noise, seed=seed + 1 + i,
                             identify=identify, keep_reversals=keep_reversals)
        closed = {k: cl[k] for k in keep + ((ESTIMATE_FIELD,) if identify else ())}
        runs.append({"start": np.asarray(s, float).tolist(), "gain_errors": e.tolist(),
                     "open": {k: op[k] for k in keep}, "closed": closed})

    def column(side: str, key: str) -> np.ndarray:
        return np.array([r[side][key] for r in runs], float)

    eo, ec = column("open", "terminal_error"), column("closed", "terminal_error")
    summary = {
        "runs": len(runs), "gain_error": gain_error, "period": period, "noise": noise,
        "identify": identify, "keep_reversals": keep_reversals,
        "plan_reversals": nominal,
        "open": {"terminal_error_median": float(np.median(eo)),
                 "terminal_error_max": float(np.max(eo)),
                 "reversals_max": int(np.max(column("open", "reversals"))),
                 "margin_min": float(np.min(column("open", "margin")))},
        "closed": {"terminal_error_median": float(np.median(ec)),
                   "terminal_error_max": float(np.max(ec)),
                   "reversals_max": int(np.max(column("closed", "reversals"))),
                   "margin_min": float(np.min(column("closed", "margin"))),
                   "replan_failures": int(np.sum(column("closed", "replan_failures")))},
        "terminal_error_ratio_median": float(np.median(eo / np.maximum(ec, 1e-300))),
        "closed_no_more_reversals": int(np.sum(column("closed", "reversals") <= nominal)),
        "closed_inside": int(np.sum(column("closed", "margin") > 0.0)),
    }
    return {"runs": runs, "summary": summary}
