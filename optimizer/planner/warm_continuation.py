"""The replanner's middle route: one NLP from the stop, warm-started on the plan's rest.

Gauss-Newton on the plan's remaining pieces (:mod:`.continuation_map`) is a local method: from
4 joints on, the end map's Jacobian is nearly singular in the directions only higher Lie
brackets reach, and a state error there needs a correction that is not small in the rates
(second order and above). The full planner finds one, but it plans from scratch: the ladder
of sign-held rungs, two solvers, the time law and the handed-out forms, then the
replanner's own proof on top.

This module solves the one NLP that matters: the shooting NLP of the first rung
(:func:`~.nlp.ladder`) from the state at the stop of the motion under way to the goal, its
initial guess the plan's own remaining path from that state (node states integrated under the
plan's remaining rates), fatrop alone. With ``hold_signs`` each interval's rates keep the
signs of the plan's rates over that interval (an interval that holds a change of sign is free
in that actuator): the continuation then reverses ``phi`` and ``th1`` no more often than the
plan's rest. The caller (:mod:`.replan`) runs its Gauss-Newton correction from this NLP's
rates onto the original model's goal and proves the result like any continuation.

fatrop may iterate longer here than in a plan (:data:`WARM_MAX_ITER`): a plan's rung that
stops at the cap makes way for the next attempt, a few milliseconds; this NLP makes way for
the full planner, tens of milliseconds to seconds.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import NumericalError
from ..problem import PlanRequest
from .context import Deadline
from .continuation_map import piece_end
from .nlp import MultipleShootingNLP, default_terminal, ladder, multiple_shooting_nlp
from .plan_state import PlanState
from .shooting import solve_shooting

#: Fewer plan time than this (s) after the stop leaves nothing to plan.
MIN_SPAN = 1e-9

#: fatrop's iteration cap on this NLP (a plan's: 60, from 5 joints 120,
#: :func:`~.solvers.fatrop_max_iter`; these measurements were made with 60). On
#: the replan benchmark's 5-joint states 0.05 deg off their plans, half of the warm NLPs that
#: failed stopped at 60 iterations, still converging: with 150, of 120 states each (6 goals)
#: of the benchmark's goals and of a seed it does not use, the full planner answered
#: 3 and 24 where it had answered 29 and 56 (p99 75 -> 39 ms and 185 -> 170 ms, p50 about
#: the same); at 4 joints 1 where 2 (p99 31 -> 14 ms). What the full planner would have
#: answered instead reverses ``phi`` and ``th1`` less often (6.1 against 8.0 times, mean of
#: the states that changed route): the middle route's trade, as before.
WARM_MAX_ITER = 150


#: fatrop's options on this NLP (a variant of the first rung's, :func:`prepare`).
WARM_SETTINGS: tuple[tuple[str, float], ...] = (("max_iter", WARM_MAX_ITER),)


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...]) -> MultipleShootingNLP:
    """Build (and cache) this NLP for a robot ahead of its first replan, as
    :func:`~.shooting.prepare` does a plan's: the first rung with the plan's signs held (its
    goal as the sign-held rungs'), fatrop capped at :data:`WARM_MAX_ITER`; the iteration cap
    is not part of the compiled functions, so it finds the first rung's library."""
    n = len(gains) + 1
    tr = ladder(n)[0]
    nlp = multiple_shooting_nlp(tuple(float(k) for k in gains),
                                tuple(int(m) for m in exponents), False, tr.intervals,
                                tr.substeps, terminal=default_terminal(n),
                                fatrop_settings=WARM_SETTINGS)
    if nlp.native_ok and "fatrop" in nlp.solver_names:
        nlp.fingerprint("fatrop")
    return nlp


def rest_of_plan(ps: PlanState, s_stop: float) -> tuple[np.ndarray, np.ndarray]:
    """The plan's pieces after its path parameter ``s_stop``: breaks from ``s_stop`` to the
    end and their rates (the piece that holds ``s_stop`` cut there)."""
    assert ps.rates is not None
    later = ps.breaks[ps.breaks > s_stop + MIN_SPAN]
    if later.size == 0:
        return np.array([s_stop]), np.zeros((0, 2))
    k = ps.piece_at(s_stop)
    return np.concatenate([[s_stop], later]), ps.rates[k:k + later.size]


def nodes_along(ps: PlanState, q0: np.ndarray, breaks: np.ndarray, rates: np.ndarray,
                grid: np.ndarray) -> np.ndarray:
    """The states at the parameters ``grid`` (ascending, from ``breaks[0]`` to
    ``breaks[-1]``) of the constant-rate pieces ``breaks, rates`` run from ``q0``: RK4
    (:func:`~.continuation_map.piece_end`), as close as the NLP's own dynamics."""
    end = piece_end(tuple(ps.robot.gains), tuple(ps.robot.exponents))
    cuts = np.union1d(breaks, grid)
    states = np.empty((cuts.size, np.size(q0)))
    states[0] = q0
    pieces = np.clip(np.searchsorted(breaks, 0.5 * (cuts[:-1] + cuts[1:]), side="right") - 1,
                     0, rates.shape[0] - 1)
    for i, k in enumerate(pieces):
        states[i + 1] = end(states[i], rates[k] * (cuts[i + 1] - cuts[i]))[0]
    return states[np.searchsorted(cuts, grid)]


def interval_signs(breaks: np.ndarray, rates: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``(len(grid) - 1, 2)``: per interval of ``grid`` and actuator the sign every piece
    overlapping the interval has (at rest pieces skipped), 0 where they differ."""
    N = grid.size - 1
    signs = np.zeros((N, 2))
    first = np.searchsorted(breaks, grid[:-1], side="right") - 1
    last = np.searchsorted(breaks, grid[1:], side="left") - 1
    s = np.sign(rates)
    for j in range(N):
        a, b = max(int(first[j]), 0), min(max(int(last[j]), int(first[j])), rates.shape[0] - 1)
        for c in range(2):
            seen = s[a:b + 1, c]
            seen = seen[seen != 0.0]
            if seen.size and np.all(seen == seen[0]):
                signs[j, c] = seen[0]
    return signs


def warm_nlp_pieces(ps: PlanState, req: PlanRequest, s_stop: float, q_stop: np.ndarray,
                    hold_signs: bool, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Pieces ``(breaks, rates)`` on the plan's parameter from ``s_stop`` to the plan's end
    that steer the NLP's model from ``q_stop`` to ``req.goal`` (see the module).

    Raises
    ------
    PlannerError
        The NLP did not converge (its typed error), or nothing is left to plan.
    """
    rest_breaks, rest_rates = rest_of_plan(ps, s_stop)
    span = float(rest_breaks[-1] - s_stop)
    if not span > MIN_SPAN or rest_rates.shape[0] == 0:
        raise NumericalError("nothing of the plan is left after the stop")
    tr = ladder(req.n)[0]
    grid = s_stop + span * np.linspace(0.0, 1.0, tr.intervals + 1)
    grid[-1] = rest_breaks[-1]
    nodes = nodes_along(ps, q_stop, rest_breaks, rest_rates, grid)
    signs = (interval_signs(rest_breaks, rest_rates, grid) if hold_signs
             else np.zeros((tr.intervals, 2)))
    sub = replace(req, start=tuple(float(x) for x in q_stop[1:]), phi_start=float(q_stop[0]),
                  duration=None, method="shooting", time_limit=seconds)
    # signs given (0: either) means one fatrop attempt from the nodes, no second guess
    sol = solve_shooting(sub, Deadline(seconds), tr, signs, nodes,
                         fatrop_settings=WARM_SETTINGS)
    # the NLP's rates are per unit of its normalised time: per unit of the plan's parameter
    return grid, np.asarray(sol.rates, float) / span
