"""The ladder a method climbs under the default objective: which transcriptions and rate
signs it tries in turn (:func:`rungs`), and :func:`solve_rungs`, which keeps the answer with
the fewest reversals, then the smallest deviation, over those rungs and the improvements
that follow (``th_1`` held monotone instead, wiggles removed, and for ``shooting`` the
smallest runs of sign merged); the runs of a sign pattern and their merge (:func:`runs`,
:func:`merge`, the reversal budget's too). Used by ``shooting`` and ``penalty``; above the NLP
layer (:mod:`.nlp`, :mod:`.solvers`).
"""

from __future__ import annotations

import time
from typing import Any, Callable, Protocol, TypeVar

import numpy as np

from ..errors import InfeasibleError, NumericalError, SolverTimeoutError
from ..indicators import ACTUATOR_DEAD_BAND, count_reversals, segment_distance
from ..problem import PlanRequest
from .attempts import MissedGoal
from .nlp import Transcription, ladder, node_bounds
from .rules import (direction_conflict, joint_limits, monotone_reach_ok, monotone_signs,
                    th1_monotone_reach_ok)


class NodeSolution(Protocol):
    """What :func:`solve_rungs` reads of a method's NLP answer: its node states and rates."""

    @property
    def nodes(self) -> np.ndarray: ...

    @property
    def rates(self) -> np.ndarray: ...


SolutionT = TypeVar("SolutionT", bound=NodeSolution)
ResultT = TypeVar("ResultT")


#: A run of an actuator's rate of one sign travelling less than this share of the actuator's
#: whole travel is a wiggle (:func:`wiggle_free_signs`).
WIGGLE_SHARE = 0.05


#: The two improvements of :func:`solve_rungs` (``th_1`` held instead, wiggles removed) run
#: below this many joints: they are fatrop's, and on the benchmark's 5-joint goals (the goal
#: then a hard constraint) fatrop failed on 6 of 7 of them, about 20 ms each; from 5 joints
#: the light solve and its polish take their place (:data:`LIGHT_FROM_JOINTS`).
IMPROVE_BELOW_JOINTS = 5


#: A rung's answer (below :data:`IMPROVE_BELOW_JOINTS` joints) with at least this many
#: reversals tries to lose one or two: the run of one actuator's sign that travels least is
#: merged into its neighbours and the NLP solved again with every interval's rates held to
#: that pattern, from the answer's nodes (the reversal budget's merging, :mod:`.budget`),
#: kept when better by (reversals, deviation); the smallest runs first, again from each
#: gain, up to :data:`MERGE_TRIES` NLPs in all. The free NLP minimises deviation and energy,
#: and on goals that a smooth motion does not reach it bought straightness with reversals
#: the default rule does not want: on 12 free 4-joint goals (start and goal of every joint
#: uniform in 15-75 deg, seed 11 of bench.free_goals) 64 reversals in all, 57 with two tries
#: (2, 4 and 8 tries found the same), 6 of the 12 with one or two fewer; on 12 such 3-joint
#: goals 4 of 12 one fewer; on seed 13 (held out) 62 -> 49 and 30 -> 21. The benchmark's
#: generated goals (0-1 reversals) do not try.
MERGE_FROM_REVERSALS = 2
MERGE_TRIES = 2
#: A merge's NLP starts only while more than this many times what the rung took so far (its
#: solve and the improvements before the merging) is left before the deadline
#: (``time_left``): the plan found must still be finished and handed out. Without it, 2 of
#: 12 free 4-joint goals that a time limit of 0.1 s planned timed out.
MERGE_RESERVE = 3.0


#: From this many joints the free rung of the default objective is solved twice: first nearly
#: for minimum energy (the deviation weights times :data:`LIGHT_SHARE`), then with the full
#: weights from that solution's nodes, its rates held to its runs of signs (wiggles merged).
#: The deviation term buys straightness with reversals, and from 5 joints it bought many: on
#: 8 held-out 6-joint goals the full weights gave 0, 4, 3, 4, 7, 3, 3, 1 reversals where the
#: light ones gave 0, 1, 3, 2, 1, 1, 2, 1 at 0.2-1.7 deg more deviation. The default ranks
#: reversals first, so the polished light plan is the better by its own rule.
LIGHT_FROM_JOINTS = 5
#: The share of the deviation weights in the light solve.
LIGHT_SHARE = 1.0 / 3000.0
#: A light answer with ``phi``'s sign held (``th_1`` free) and more reversals than this is
#: compared with the free rung's: a free plan may reverse ``phi`` once where ``th_1`` reversed
#: three times (a five-joint goal: 3 reversals and 10.5 deg held, 1 and 4.8 deg free). With
#: one reversal it is among the fewest, as both signs held did not converge before it.
HELD_ENOUGH = 1


def rungs(req: PlanRequest) -> list[tuple[Transcription, tuple[float, float] | None]]:
    """The transcriptions a method tries in turn, each with the signs its rates are held to.

    Under the default objective (fewest actuator reversals first) a plan in which no actuator
    reverses wins whatever its deviation: the first rung with rates of fixed signs
    (:func:`~.rules.monotone_signs`), then with phi's sign alone fixed, then :func:`ladder`
    free.
    """
    steps = ladder(req.n)
    out: list[tuple[Transcription, tuple[float, float] | None]] = [(t, None) for t in steps]
    signs = monotone_signs(req) if req.objective == "reversals_then_deviation" else None
    if signs is not None:
        # only the rungs the goal's reach does not rule out (monotone_reach_ok)
        out[:0] = (([(steps[0], signs)] if signs[1] != 0.0 and monotone_reach_ok(req, True)
                    else [])
                   + ([(steps[0], (signs[0], 0.0))] if monotone_reach_ok(req, False) else []))
    return out


def _reversals_and_deviation(req: PlanRequest, nodes: np.ndarray) -> tuple[int, float]:
    """The default rule's key of an NLP's answer, read from its nodes: reversals of ``phi`` and
    ``th_1`` together, then the largest distance of the nodes from the segment start -> goal
    (the plan's own indicators come later, from its re-integrated path)."""
    nodes = np.asarray(nodes, float)
    rev = count_reversals(nodes[:, 0]) + count_reversals(nodes[:, 1])
    return rev, segment_distance(nodes[:, 1:], np.array(req.start), np.array(req.goal))


def run_signs(rates: np.ndarray) -> np.ndarray:
    """Per-interval signs ``(N, 2)`` of ``rates``: :func:`wiggle_free_signs`, or the rates' own
    signs (a zero rate in the run before it) when they have no wiggle."""
    merged = wiggle_free_signs(rates)
    if merged is not None:
        return merged
    return np.stack([_own_signs(np.asarray(rates[:, c], float)) for c in (0, 1)], axis=1)


def _own_signs(col: np.ndarray) -> np.ndarray:
    """The signs of one actuator's rates, a zero rate taking the sign of the run before it
    (the first run's at the start; all positive when every rate is 0)."""
    sign = np.sign(col)
    nz = np.flatnonzero(sign)
    if nz.size == 0:
        return np.ones_like(col)
    index = np.arange(col.size)
    return sign[np.maximum.accumulate(np.where(sign != 0.0, index, nz[0]))]


def wiggle_free_signs(rates: np.ndarray) -> np.ndarray | None:
    """Per-interval signs ``(N, 2)`` of ``rates`` (per unit of normalised time on ``N`` equal
    intervals) with their wiggles merged into the neighbouring runs, or None without wiggles.

    A wiggle is a run of one sign of an actuator's rate whose travel is above the reversal
    dead band (it counts as two reversals, one at an end of the path) but below
    :data:`WIGGLE_SHARE` of the actuator's whole travel. The smallest is merged first (it takes
    its neighbours' sign), until none is left.
    """
    N = rates.shape[0]
    h = 1.0 / N
    out = np.zeros((N, 2))
    found = False
    for c in (0, 1):
        col = np.asarray(rates[:, c], float)
        sign = _own_signs(col)
        size = np.abs(col) * h
        total = float(np.sum(size))
        while True:
            edges = np.flatnonzero(np.diff(sign)) + 1
            if edges.size == 0:
                break
            starts, ends = np.r_[0, edges], np.r_[edges, N]
            travel = np.add.reduceat(size, starts)
            small = np.flatnonzero((travel > ACTUATOR_DEAD_BAND) & (travel < WIGGLE_SHARE * total))
            if small.size == 0:
                break
            r = int(small[np.argmin(travel[small])])
            sign[starts[r]:ends[r]] = sign[starts[r] - 1] if r > 0 else sign[ends[r]]
            found = True
        out[:, c] = sign
    return out if found else None


def signs_list(signs: Any) -> Any:
    """Rate signs (a pair, or one pair per interval) as JSON-ready lists (None: free)."""
    return None if signs is None else np.asarray(signs, float).tolist()


def solve_rungs(req: PlanRequest, solve: Callable[..., SolutionT], light_first: bool = False,
                merge_runs: bool = False, time_left: Callable[[], float] | None = None
                ) -> tuple[SolutionT, Transcription, Any, list[dict[str, Any]]]:
    """The first solution of ``solve(transcription, signs[, start_nodes])`` over :func:`rungs`:
    ``(solution, transcription, signs, attempts of the rungs that failed)``;
    :class:`InfeasibleError` naming every rung when none converged (a finer or free rung may
    converge where one failed).

    Under the default objective (fewest reversals, then deviation) and below
    :data:`IMPROVE_BELOW_JOINTS` joints, two more NLPs may follow, each kept only when better by
    (reversals, deviation) at the nodes:

    * a solution in which ``th_1`` reverses (``phi``'s sign fixed, or both free) is compared
      with the same transcription with ``th_1``'s sign fixed and ``phi`` free, which may
      reverse ``phi`` once where the first reversed ``th_1`` once, on a straighter path
      (skipped when :func:`~.rules.th1_monotone_reach_ok` rules it out). Where ``phi`` must
      reverse (:func:`~.rules.direction_conflict`: no path has fewer than one reversal) that
      NLP runs first, and when its path reverses once (``phi``) it is among the fewest and
      the free NLP is not run;
    * a solution with wiggles (:func:`wiggle_free_signs`: short runs of an actuator's rate
      against its neighbours, each two reversals for little travel, which the deviation term
      can favour on long moves) is solved again from its own nodes with every interval's
      rates held to the signs without them.

    * ``merge_runs`` (the ``shooting`` method's): an answer that still reverses
      :data:`MERGE_FROM_REVERSALS` times or more has its smallest runs merged, each solved
      held to that pattern (:data:`MERGE_TRIES` NLPs at most, each only while ``time_left()``
      seconds exceed :data:`MERGE_RESERVE` times the rung's time so far; one that runs out of time
      ends the merging with the best answer so far).

    ``light_first`` (``solve`` then takes ``light=True``): from :data:`LIGHT_FROM_JOINTS`
    joints, under the default objective, a free rung is solved light first and then polished
    with its signs held (see :data:`LIGHT_FROM_JOINTS`); the better of the two by (reversals,
    deviation) is the rung's answer.
    """
    failures: list[str] = []
    tried: list[dict[str, Any]] = []
    improve = req.objective == "reversals_then_deviation" and req.n < IMPROVE_BELOW_JOINTS
    th1_sign = float(np.sign(req.goal[0] - req.start[0]))
    th1_held = (0.0, th1_sign)
    # where phi must reverse (the joints move both ways: no path has fewer than one reversal),
    # a path with th1 held to its sign and one reversal of phi is one of the fewest: that
    # NLP goes first, and the free one runs only when it does not give such a path
    ahead_first = (improve and th1_sign != 0.0 and direction_conflict(req) is not None
                   and th1_reach_ok(req))
    light = (light_first and req.objective == "reversals_then_deviation"
             and req.n >= LIGHT_FROM_JOINTS)
    # the nodes of a light rung's answer that converged off the goal (too coarse a model for
    # it): the next rung starts there first (a 6-joint goal's 50-interval rung: 44 fatrop
    # iterations from there, against 251 of IPOPT's 300 from the straight line)
    near: np.ndarray | None = None
    # a light answer of phi's sign held whose th_1 reverses more than once: the free rung
    # after it may reverse less (phi once, th_1 not at all), so it runs too
    phi_held: tuple[SolutionT, Transcription, Any, list[dict[str, Any]]] | None = None
    phi_held_key: tuple[int, float] | None = None

    for tr, signs in rungs(req):
        rung_started = time.perf_counter()
        if light and (signs is None or not all(signs)):
            sol = None
            if near is not None:
                try:
                    sol = solve(tr, signs, resample_nodes(near, tr.intervals), light=True)
                except InfeasibleError as exc:
                    tried.extend(exc.diagnostics.get("tried", []))
            if sol is None:
                try:
                    sol = solve(tr, signs, light=True)
                except InfeasibleError as exc:
                    tried.extend(exc.diagnostics.get("tried", []))
                    failures.append(f"{tr.intervals} intervals"
                                    + (" (monotone)" if signs else "")
                                    + f" (light): {exc.message}")
                    if near is None and isinstance(exc, MissedGoal):
                        near = exc.nodes
                    continue
            run_pattern = run_signs(sol.rates)
            found: tuple[SolutionT, Transcription, Any, list[dict[str, Any]]]
            try:
                polished = solve(tr, run_pattern, sol.nodes)
            except InfeasibleError as exc:
                tried.extend(exc.diagnostics.get("tried", []))
                found = (sol, tr, signs, tried)
            else:
                if _reversals_and_deviation(req, polished.nodes) <= _reversals_and_deviation(
                        req, sol.nodes):
                    tried.extend(getattr(sol, "tried", ()))
                    found = (polished, tr, run_pattern, tried)
                else:
                    tried.extend(getattr(polished, "tried", ()))
                    found = (sol, tr, signs, tried)
            found_key = _reversals_and_deviation(req, found[0].nodes)
            if phi_held is None and signs is not None and found_key[0] > HELD_ENOUGH:
                phi_held, phi_held_key = found, found_key
                continue
            if phi_held is not None and phi_held_key is not None and phi_held_key <= found_key:
                return phi_held
            return found
        ahead: Any = None
        # th1 held on this rung already ran and failed: the same NLP is not solved again
        th1_held_failed = False
        if ahead_first and signs is None:
            try:
                ahead = solve(tr, th1_held)
            except InfeasibleError as exc:
                tried.extend(exc.diagnostics.get("tried", []))
                th1_held_failed = True
        if ahead is not None and _reversals_and_deviation(req, ahead.nodes)[0] <= 1:
            sol, signs, ahead = ahead, th1_held, None
        else:
            try:
                sol = solve(tr, signs)
            except InfeasibleError as exc:
                tried.extend(exc.diagnostics.get("tried", []))
                if ahead is None:
                    failures.append(f"{tr.intervals} intervals" + (" (monotone)" if signs else "")
                                    + f": {exc.message}")
                    continue
                sol, signs, ahead = ahead, th1_held, None
        if not improve:
            # (the improvements below are fatrop's, which from 5 joints failed on 6 of the
            # benchmark's 7 tries, about 20 ms each: see IMPROVE_BELOW_JOINTS)
            return sol, tr, signs, tried
        best: tuple[Any, Any] = (sol, signs)
        key: tuple[int, float] | None = None   # the best's, computed once there is a rival

        def compare(alt: Any, alt_signs: Any) -> None:
            nonlocal best, key
            if key is None:
                key = _reversals_and_deviation(req, best[0].nodes)
            alt_key = _reversals_and_deviation(req, alt.nodes)
            if alt_key < key:
                # the superseded solution's attempts stay in the record, before the winner's
                tried.extend(getattr(best[0], "tried", ()))
                best, key = (alt, alt_signs), alt_key
            else:
                tried.extend(getattr(alt, "tried", ()))

        def consider(alt_signs: Any, start: np.ndarray | None = None) -> None:
            try:
                alt = solve(tr, alt_signs) if start is None else solve(tr, alt_signs, start)
            except InfeasibleError as exc:
                tried.extend(exc.diagnostics.get("tried", []))
                return
            compare(alt, alt_signs)

        if ahead is not None:  # solved first, without the fewest reversals: compared
            compare(ahead, th1_held)
        elif (th1_sign != 0.0 and (signs is None or signs[1] == 0.0) and not th1_held_failed
                and count_reversals(sol.nodes[:, 1]) > 0 and th1_reach_ok(req)):
            consider(th1_held)
        # rates held to one sign per actuator (the first rung) have no runs to merge
        held = best[1] is not None and np.ndim(best[1]) == 1 and all(best[1])
        pattern = None if held else wiggle_free_signs(best[0].rates)
        if pattern is not None:
            consider(pattern, best[0].nodes)
        tries = MERGE_TRIES if merge_runs else 0
        if tries and key is None:
            key = _reversals_and_deviation(req, best[0].nodes)
        rung_seconds = time.perf_counter() - rung_started

        def time_for_one() -> bool:
            return time_left is None or time_left() > MERGE_RESERVE * rung_seconds

        while tries > 0 and key is not None and key[0] >= MERGE_FROM_REVERSALS:
            # fewer reversals bought back: the run that travels least merged into its
            # neighbours (its rates take their sign), from the best's nodes; the next
            # smallest where that NLP fails or gains nothing; again from a gain
            signs_now = run_signs(best[0].rates)
            before = key
            several = [c for c in (0, 1) if np.any(np.diff(signs_now[:, c]))]
            for run in sorted(r for r in runs(signs_now, best[0].rates) if r[1] in several
                              )[:tries]:
                if not time_for_one():
                    tries = 0
                    break
                tries -= 1
                try:
                    consider(merge(signs_now, run), best[0].nodes)
                except SolverTimeoutError as exc:   # (optional: the best so far stands)
                    tried.extend(exc.diagnostics.get("tried", []))
                    tries = 0
                    break
                if key < before:
                    break
            if not key < before:
                break
        return best[0], tr, best[1], tried
    if phi_held is not None:
        return phi_held
    raise InfeasibleError("; ".join(failures),
                          diagnostics={"blocking": "nlp_failed", "tried": tried})


def runs(signs: np.ndarray, rates: np.ndarray) -> list[tuple[float, int, int, int]]:
    """The runs of one sign of each actuator in a sign pattern ``(N, 2)``: ``(travel, actuator,
    first interval, end)``, travel the run's ``sum |U| / N`` under ``rates`` (N, 2)."""
    N = signs.shape[0]
    out: list[tuple[float, int, int, int]] = []
    for c in (0, 1):
        edges = np.flatnonzero(np.diff(signs[:, c])) + 1
        starts, ends = np.r_[0, edges], np.r_[edges, N]
        for s, e in zip(starts, ends):
            out.append((float(np.sum(np.abs(rates[s:e, c]))) / N, c, int(s), int(e)))
    return out


def merge(signs: np.ndarray, run: tuple[float, int, int, int]) -> np.ndarray:
    """``signs`` with ``run`` (of :func:`runs`) given its neighbours' sign."""
    _, c, s, e = run
    out = signs.copy()
    N = signs.shape[0]
    out[s:e, c] = signs[s - 1, c] if s > 0 else signs[e, c] if e < N else signs[s, c]
    return out


def resample_signs(signs: Any, intervals: int) -> Any:
    """Rate signs held per actuator (a pair) as they are; per interval ``(N, 2)``: each of
    ``intervals`` equal intervals takes the sign of the old interval holding its midpoint."""
    arr = np.asarray(signs, float)
    if arr.ndim == 1:
        return signs
    mid = (np.arange(int(intervals)) + 0.5) / int(intervals)
    return arr[np.minimum((mid * arr.shape[0]).astype(int), arr.shape[0] - 1)]


def finish_or_refine(req: PlanRequest, tr: Transcription, sol: SolutionT, signs: Any,
                     tried: list[dict[str, Any]],
                     finish: Callable[[Transcription, Any, Any, list[dict[str, Any]],
                                       dict[str, Any]], ResultT],
                     solve: Callable[[Transcription, Any, np.ndarray], Any],
                     check: Callable[[], None]) -> ResultT:
    """``finish(tr, sol, signs, tried, diagnostics)``: the rung's answer finished (corrected
    onto the goal of the exact model, re-integrated, verified); where that fails on a rung
    below the ladder's last, the next rung solved from the answer's path and finished instead.

    The rung's model (RK4 on its intervals) may end off the goal in a direction the Newton
    correction cannot reach (the end map's weakest singular value; a 5-joint goal near the
    region's edge: 1.5e-6 rad along a direction of singular value 5e-8), or the original
    model's path may leave the region where the rung's nodes stay inside (a 6-joint goal with
    th2 near pi/2: th5 at -0.1 rad; an :class:`InfeasibleError` with the path's ``margin``).
    The next rung, a finer model, then starts from this path (``solve(finer, signs, nodes)``),
    its rates held to the same signs, else free (that 5-joint goal's finer NLP did not converge
    held in 60 iterations; free, it did at once); ``check()`` between the solve and the
    finishing (the deadline's). The finer answer's diagnostics say
    ``refined_from_intervals``.
    """
    try:
        return finish(tr, sol, signs, tried, {})
    except (NumericalError, InfeasibleError) as exc:
        steps = ladder(req.n)
        if tr not in steps[:-1] or (isinstance(exc, InfeasibleError)
                                    and "margin" not in exc.diagnostics):
            raise
    finer = steps[steps.index(tr) + 1]
    nodes = resample_nodes(sol.nodes, finer.intervals)
    held = None if signs is None else resample_signs(signs, finer.intervals)
    again = None
    if held is not None:
        try:
            again = solve(finer, held, nodes)
        except InfeasibleError:
            held = None
    if again is None:
        again = solve(finer, None, nodes)
    check()
    return finish(finer, again, held, tried + list(getattr(sol, "tried", ())),
                  {"refined_from_intervals": tr.intervals})


def resample_nodes(nodes: np.ndarray, intervals: int) -> np.ndarray:
    """Node states ``(N+1, n+1)`` on equal intervals, linearly interpolated onto
    ``intervals`` equal intervals (``(intervals+1, n+1)``)."""
    s = np.linspace(0.0, 1.0, nodes.shape[0])
    t = np.linspace(0.0, 1.0, int(intervals) + 1)
    return np.stack([np.interp(t, s, nodes[:, j]) for j in range(nodes.shape[1])], axis=1)


def th1_reach_ok(req: PlanRequest) -> bool:
    """:func:`~.rules.th1_monotone_reach_ok` with ``th_2`` within its node bounds."""
    lo, hi = node_bounds(req, joint_limits(req))
    return th1_monotone_reach_ok(req, float(lo[1]), float(hi[1]))
