"""Analyses around plans: indicator sweeps over dphi, batch transforms, perturbed-start replays.

These back the service's ``/v1/sweeps``, ``/v1/transforms`` and ``/v1/robustness`` endpoints and
the paper's Figs 11-14 and b0 map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from .chained_form import chained_form
from .errors import InvalidRequestError
from .execution import HandedOutInputs
from .indicators import compute_indicators, sensitivity_frobenius
from .model import Robot
from .planner.family import PolynomialFamily
from .planner.intervals import feasible_intervals
from .planner.context import Deadline
from .planner.rules import check_endpoints, make_region
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
