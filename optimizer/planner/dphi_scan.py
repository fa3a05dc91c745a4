"""The choice of ``dphi`` for the constraint-point QP: the range a constant ``v1`` needs, the
scan, the ranking by the request's objective rule and the refinement.

Choice of ``dphi``
------------------
``req.phi_change`` when given. Otherwise a scan inside the request's bounds cut to the motion's
sign and to the open interval that a constant ``v1`` needs (:func:`necessary_dphi_range`: each
th_i, i >= 2, moves monotonically with ``|th_i'| = K_i cos(th_{i-1})^m_i |u1|`` and th_{i-1}
between its start and goal values for i >= 3); :data:`MIN_SCAN_NODES` to :data:`MAX_SCAN_NODES`
uniform interior nodes, plus three nodes inside each singularity-free interval of the paper's
family (:func:`family_intervals`; they are part of the QP's feasible set, and for n >= 4 can be
hundredths of a degree wide, too narrow for any uniform scan), so the method succeeds whenever
the paper's does;
each feasible node is ranked by the request's objective rule on its cheap indicators (t_p, d_a,
|dphi|, energy, computed as finish_plan does), then the best is refined by bounded Brent
minimisation between its neighbours (bisection toward the smallest ``|dphi|`` for
``tp_then_sensitivity``). If nothing is feasible, ``m`` goes up the ladder :data:`.constraint_qp.EXTRA_DEGREES`.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy.optimize import minimize_scalar

from ..chained_form import chained_form
from ..errors import SingularSystemError
from ..indicators import compute_indicators
from ..problem import PlanRequest
from ..steering import MIN_ABS_DPHI, ChainedPath, InputSchedule
from .constraint_qp import ConstraintPointQP, Synthesis
from .context import Deadline
from .family import SEARCH_SAMPLES, PolynomialFamily
from .intervals import feasible_intervals
from .rules import make_region, phi_search_bounds

#: Scan spacing of dphi and the smallest and largest number of uniform scan nodes.
SCAN_STEP = math.radians(0.5)
MIN_SCAN_NODES = 8
MAX_SCAN_NODES = 40
#: Refinement of the best dphi node (rad) and its evaluation budget.
REFINE_XATOL = 1e-5
REFINE_MAXITER = 30
#: Seconds kept in reserve for finish_plan (sampling, re-integration) when refining.
FINISH_RESERVE = 0.5


def cheap_indicators(req: PlanRequest, inputs: InputSchedule) -> dict[str, float] | None:
    """t_p, d_a, sensitivity and energy on the search grid (what finish_plan will report)."""
    cf = chained_form(req.robot)
    T = inputs.duration
    z0 = cf.to_chained(req.q_start())
    path = ChainedPath.from_inputs(z0, inputs)
    td = np.linspace(0.0, T, SEARCH_SAMPLES)
    inv = cf.from_chained(path.z(td / T))
    if not inv.valid.all():
        return None
    ud = cf.u_from_v(inv.q, inputs.v(td))
    ind = compute_indicators(td, inv.q, ud)
    return {"t_p": float(ind.t_p), "d_a": ind.d_a, "sensitivity": ind.sensitivity,
            "energy": ind.energy}


def score_synthesis(req: PlanRequest, s: Synthesis) -> tuple[float, float]:
    """The request's rule (plan.py's objectives) on the cheap indicators; lower is better."""
    ind = s.indicators
    if req.objective == "tp_then_da":
        return ind["t_p"], ind["d_a"]
    if req.objective == "tp_then_sensitivity":
        return ind["t_p"], abs(s.dphi)
    w = req.weights
    return 0.0, (w.d_a * ind["d_a"] + w.sensitivity * ind["sensitivity"]
                 + w.energy * ind["energy"] + w.t_p * ind["t_p"])


def evaluate_dphi(qp: ConstraintPointQP, req: PlanRequest, dphi: float) -> Synthesis:
    s = qp.solve(dphi)
    if s.ok and not s.indicators:
        ind = cheap_indicators(req, s.inputs)  # type: ignore[arg-type]
        if ind is None:  # cannot happen after a passed check; be safe
            s.ok = False
            s.reason = "the sampled path is not invertible"
        else:
            s.indicators = ind
            s.score = score_synthesis(req, s)
    return s


def motion_sign(req: PlanRequest) -> float:
    """+1 when th2..thn move up (or stay), -1 when they move down (no conflict assumed)."""
    return 1.0 if np.any(np.array(req.goal[1:]) > np.array(req.start[1:])) else -1.0


def necessary_dphi_range(req: PlanRequest) -> tuple[float, float, str | None]:
    """Open interval ``(dmin, dmax)`` of ``|dphi|`` outside which a constant ``v1`` cannot work.

    With ``v1`` constant every ``th_i`` (i >= 2) moves monotonically, ``th_i' = K_i
    cos(th_{i-1})^m_i u1``. ``th1`` is free, so ``|dth_2| < K_2 |dphi|``; for i >= 3,
    ``th_{i-1}`` stays between its start and goal values, so ``cos(th_{i-1})^m_i`` stays between
    their values ``[c_lo, c_hi]`` and ``K_i c_lo |dphi| < |dth_i| < K_i c_hi |dphi|``.

    Returns
    -------
    dmin, dmax : float
    why : str or None
        Why the interval is empty (a joint that must move does not, or the bounds cross).
    """
    th0 = np.array(req.start)
    thT = np.array(req.goal)
    K = np.array(req.robot.gains)
    m = np.array(req.robot.exponents, float)
    n = req.n
    dth = np.abs(thT - th0)
    still = [i + 1 for i in range(1, n) if dth[i] == 0.0]
    if still:
        return 0.0, 0.0, (f"th{still[0]} does not move, but with a constant v1 != 0 every joint "
                          "th2..thn moves strictly (phi must reverse: use method 'penalty')")
    dmin = dth[1] / K[0]
    dmax = math.inf
    for i in range(2, n):  # 0-based joint index i is th_{i+1}, driven by th_i
        c = np.cos(np.array([th0[i - 1], thT[i - 1]])) ** m[i - 1]
        dmin = max(dmin, dth[i] / (K[i - 1] * float(c.max())))
        dmax = min(dmax, dth[i] / (K[i - 1] * float(c.min())))
    why = None
    if not dmin < dmax:
        why = (f"the joints' motions need |phi_change| > {dmin:.6g} rad and < {dmax:.6g} rad at "
               "once (each th_i, i >= 3, gains between K_i cos(th_(i-1))^m_i |dphi| at its start "
               "and goal values): no constant v1 reaches this goal")
    return float(dmin), float(dmax), why


def dphi_scan_range(req: PlanRequest) -> tuple[float, float, float, float]:
    """``(lo, hi, dmin, dmax)``: the request's bounds cut to the motion's sign and to the open
    interval of :func:`necessary_dphi_range`."""
    lo, hi = phi_search_bounds(req)
    dmin, dmax, _ = necessary_dphi_range(req)
    sgn = motion_sign(req)
    floor = max(dmin, 10 * MIN_ABS_DPHI)
    if sgn > 0:
        lo, hi = max(lo, floor), min(hi, dmax)
    else:
        lo, hi = max(lo, -dmax), min(hi, -floor)
    return lo, hi, dmin, dmax


def family_intervals(req: PlanRequest, lo: float, hi: float) -> list[tuple[float, float]]:
    """The paper's family's singularity-free ``dphi`` intervals in [lo, hi] (full region).

    Where the family is feasible so is the QP (its member is then the QP's optimum), so these
    windows, which can be hundredths of a degree wide for n >= 4, seed the scan.
    """
    fam = PolynomialFamily(req.robot, req.q_start(), req.q_goal(0.0), req.duration_or_default,
                           req.constraint_points, make_region(req, "full"))
    try:
        return feasible_intervals(fam, lo, hi)
    except SingularSystemError:
        return []


def search_dphi(qp: ConstraintPointQP, req: PlanRequest, lo: float, hi: float,
            deadline: Deadline, seeds: Sequence[tuple[float, float]] = ()
            ) -> tuple[Synthesis | None, dict[str, Any]]:
    """Scan ``dphi`` in (lo, hi), keep the best feasible node by the request's rule, refine.

    ``seeds`` are intervals known to be feasible (the paper's family): three nodes inside each
    join the uniform ones, so that narrow windows are never missed.
    """
    k = int(min(MAX_SCAN_NODES, max(MIN_SCAN_NODES, math.ceil((hi - lo) / SCAN_STEP) - 1)))
    # interior nodes: the ends are the necessary bounds (infeasible) or the request's bounds
    extra = [a + f * (b - a) for a, b in seeds for f in (0.25, 0.5, 0.75) if b > a]
    full = np.unique(np.concatenate([np.linspace(lo, hi, k + 2), np.array(extra, float)]))
    nodes = full[1:-1]
    k = int(nodes.size)
    evals: list[Synthesis] = []
    for d in nodes:
        deadline.check("the constraint-point dphi scan")
        evals.append(evaluate_dphi(qp, req, float(d)))
    feas = [(i, s) for i, s in enumerate(evals) if s.ok]
    reasons: dict[str, int] = {}
    for s in evals:
        if not s.ok:
            key = s.reason.split(":")[0].split(" after")[0]
            reasons[key] = reasons.get(key, 0) + 1
    info: dict[str, Any] = {"nodes": int(k), "feasible_nodes": len(feas),
                            "common_reason": (max(reasons, key=lambda r: reasons[r])
                                              if reasons else None)}
    if not feas:
        return None, info
    best_i, best = min(feas, key=lambda t: t[1].score)
    tp_best = best.score[0]

    def restricted(d: float) -> float:
        s = evaluate_dphi(qp, req, float(d))
        if not s.ok or (req.objective != "weighted" and s.score[0] > tp_best):
            return 1e9
        return s.score[1]

    a, b = float(full[best_i]), float(full[best_i + 2])  # the best node's neighbours
    evals_before = qp.solves
    if req.objective == "tp_then_sensitivity":
        # the optimum is the smallest |dphi| with the fewest t_p: bisect toward it
        good = best.dphi
        bad = a if abs(a) < abs(b) else b
        if bad != good and restricted(bad) < 1e9:
            good = bad
        else:
            while abs(good - bad) > REFINE_XATOL and deadline.remaining > FINISH_RESERVE:
                mid = 0.5 * (good + bad)
                if restricted(mid) < 1e9:
                    good = mid
                else:
                    bad = mid
        cand = evaluate_dphi(qp, req, good)
    elif b > a and deadline.remaining > FINISH_RESERVE:
        budget = [REFINE_MAXITER]

        def f(d: float) -> float:
            if budget[0] <= 0 or deadline.remaining <= FINISH_RESERVE:
                return 1e9  # out of time: the scan's best stands
            budget[0] -= 1
            return restricted(d)
        res = minimize_scalar(f, bounds=(a, b), method="bounded",
                              options={"xatol": REFINE_XATOL, "maxiter": REFINE_MAXITER})
        cand = evaluate_dphi(qp, req, float(res.x))
    else:
        cand = best
    if cand.ok and cand.score <= best.score:
        best = cand
    info.update({"refinement_solves": qp.solves - evals_before,
                 "best_node": float(nodes[best_i]), "refined_phi_change": best.dphi})
    return best, info

