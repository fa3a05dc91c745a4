"""Choosing ``dphi`` inside the feasible intervals (paper §4 and §5.3).

* ``tp_then_da``: fewest ``t_p`` first, then smallest ``d_a`` (joint 1).
* ``tp_then_sensitivity``: fewest ``t_p``, then smallest ``||J_R(T)||_F``; it grows with
  ``|dphi|`` only, so this is the smallest ``|dphi|`` with the fewest ``t_p``.
* ``weighted``: smallest ``w_da d_a + w_s ||J_R(T)||_F + w_e energy + w_tp t_p``.

Each objective is optimised continuously: a scan inside every interval (at most 0.05 deg apart)
finds the best node, then bounded Brent minimisation (or bisection for a boundary optimum)
refines it to 1e-9 rad on the true function.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from ..problem import Weights
from .family import MemberEval, PolynomialFamily

SCAN_STEP = math.radians(0.05)
XATOL = 1e-9


def _nodes(a: float, b: float) -> np.ndarray:
    k = max(3, int(math.ceil((b - a) / SCAN_STEP)) + 1)
    return np.linspace(a, b, k)


def _score(obj: str, w: Weights) -> Callable[[MemberEval], tuple[float, float]]:
    if obj == "tp_then_da":
        return lambda e: (float(e.t_p), e.d_a)
    if obj == "tp_then_sensitivity":
        return lambda e: (float(e.t_p), abs(e.dphi))
    if obj == "weighted":
        return lambda e: (0.0, w.d_a * e.d_a + w.sensitivity * e.sensitivity
                          + w.energy * e.energy + w.t_p * e.t_p)
    raise ValueError(obj)


def optimise(family: PolynomialFamily, intervals: list[tuple[float, float]], objective: str,
             weights: Weights) -> MemberEval | None:
    """The best feasible member by ``objective``; ``None`` when no node is feasible."""
    score = _score(objective, weights)
    nodes: list[float] = []
    for a, b in intervals:
        # stay a hair inside the closed interval: its ends are on the boundary (margin 0)
        eps = min(1e-7, 0.25 * (b - a))
        nodes.extend(_nodes(a + eps, b - eps).tolist())
    evals = family.screen(np.array(nodes))
    feas = [(i, e) for i, e in enumerate(evals) if e.ok]
    best_i, best = -1, None
    # the screen is sampled: confirm the winner on the continuous path (else the next best)
    for i, e in sorted(feas, key=lambda ie: score(ie[1])):
        exact = family.evaluate(e.dphi)
        if exact.ok:
            best_i, best = i, exact
            break
    if best is None:
        return None
    tp_best = best.t_p

    def restricted(d: float) -> float:
        e = family.evaluate(float(d))
        if not e.ok or (objective != "weighted" and e.t_p > tp_best):
            return 1e9
        return score(e)[1]

    lo = nodes[max(best_i - 1, 0)]
    hi = nodes[min(best_i + 1, len(nodes) - 1)]
    if objective == "tp_then_sensitivity":
        # the optimum is where |dphi| is smallest inside the {t_p = min} set: a boundary
        toward = lo if abs(lo) < abs(best.dphi) else hi
        good, bad = best.dphi, toward
        if restricted(bad) < 1e9:
            return family.evaluate(float(bad))
        while abs(good - bad) > XATOL:
            mid = 0.5 * (good + bad)
            if restricted(mid) < 1e9:
                good = mid
            else:
                bad = mid
        return family.evaluate(float(good))
    if hi > lo:
        res = minimize_scalar(restricted, bounds=(lo, hi), method="bounded",
                              options={"xatol": XATOL, "maxiter": 200})
        cand = family.evaluate(float(res.x))
        if cand.ok and score(cand) <= score(best):
            return cand
    return best
