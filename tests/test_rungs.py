"""The ladder's choice among its rungs (:func:`optimizer.planner.rungs.solve_rungs`), with
the NLP solves replaced by answers of known reversals and deviation: which rungs run, and which
answer is kept, by the default rule (fewest reversals of ``phi`` and ``th_1``, then the
smallest deviation from the segment start -> goal), counted here on the answers' nodes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from optimizer.errors import InfeasibleError
from optimizer.indicators import count_reversals
from optimizer.model import Robot
from optimizer.planner import rungs as rungs_mod
from optimizer.planner.nlp import ladder
from optimizer.problem import PlanRequest

N = 20
START = (0.3, 0.4, 0.5, 0.6, 0.7)
GOAL = (0.5, 0.6, 0.7, 0.8, 0.9)


@dataclass
class Answer:
    nodes: np.ndarray
    rates: np.ndarray
    tried: tuple = ()


def answer(phi_turns: int, th1_turns: int, bulge: float = 0.0) -> Answer:
    """Nodes from START to GOAL whose phi and th_1 turn back that many times (by 0.1 rad and
    more, far above the dead band), the other joints bulging ``bulge`` rad off the segment."""
    s = np.linspace(0.0, 1.0, N + 1)

    def zigzag(turns: int, a: float, b: float) -> np.ndarray:
        # a -> beyond b -> before a -> ... -> b: turns + 1 monotone runs, 0.1 rad past the ends
        ends = [b + 0.1 if i % 2 == 0 else a - 0.1 for i in range(turns)]
        way = np.array([a, *ends, b])
        return np.interp(s, np.linspace(0.0, 1.0, way.size), way)

    nodes = np.empty((N + 1, 6))
    nodes[:, 0] = zigzag(phi_turns, 0.0, 1.0)
    nodes[:, 1] = zigzag(th1_turns, START[0], GOAL[0])
    for j in range(1, 5):
        nodes[:, j + 1] = START[j] + (GOAL[j] - START[j]) * s + bulge * np.sin(np.pi * s)
    rates = np.diff(nodes[:, :2], axis=0) * N
    return Answer(nodes, rates)


@pytest.fixture
def request_5() -> PlanRequest:
    return PlanRequest(start=START, goal=GOAL, robot=Robot.default(5))


def run(monkeypatch, req: PlanRequest, held_answer: Answer, free_answer: Answer | None):
    """solve_rungs over two rungs, phi's sign held then free; the rungs each solve ran."""
    tr = ladder(5)[0]
    monkeypatch.setattr(rungs_mod, "rungs", lambda r: [(tr, (1.0, 0.0)), (tr, None)])
    calls: list[str] = []

    def solve(tr_, signs, start_nodes=None, light=False):
        kind = "free" if signs is None else "phi held"
        if start_nodes is not None:      # the polish of a light answer: the same answer
            calls.append("polish")
            return Answer(np.array(start_nodes), held_answer.rates)
        calls.append(kind)
        if signs is None:
            if free_answer is None:
                raise InfeasibleError("no free answer", diagnostics={"tried": []})
            return free_answer
        return held_answer

    sol, _, signs, _ = rungs_mod.solve_rungs(req, solve, light_first=True)
    return sol, signs, [c for c in calls if c != "polish"]


def reversals(a: Answer) -> int:
    return count_reversals(a.nodes[:, 0]) + count_reversals(a.nodes[:, 1])


def test_answers_of_the_fake_have_the_reversals_asked_for():
    assert reversals(answer(0, 3)) == 3 and reversals(answer(1, 0)) == 1
    assert reversals(answer(0, 1)) == 1


def test_a_held_answer_with_several_reversals_is_compared_with_the_free_rung(
        monkeypatch, request_5):
    sol, signs, calls = run(monkeypatch, request_5, answer(0, 3), answer(1, 0))
    assert calls == ["phi held", "free"]
    assert reversals(sol) == 1 and signs is not None and np.ndim(signs) == 2  # the free one


def test_a_held_answer_with_one_reversal_is_kept_without_the_free_rung(
        monkeypatch, request_5):
    sol, signs, calls = run(monkeypatch, request_5, answer(0, 1), answer(1, 0, bulge=-0.01))
    assert calls == ["phi held"]
    assert reversals(sol) == 1


def test_the_held_answer_stays_when_the_free_rung_fails_or_is_no_better(
        monkeypatch, request_5):
    sol, _, calls = run(monkeypatch, request_5, answer(0, 2), None)
    assert calls == ["phi held", "free"] and reversals(sol) == 2
    # as many reversals and farther from the segment: the held answer is kept
    sol, _, calls = run(monkeypatch, request_5, answer(0, 2), answer(2, 0, bulge=0.5))
    assert calls == ["phi held", "free"]
    assert count_reversals(sol.nodes[:, 1]) == 2


def test_th1_held_that_failed_before_the_free_rung_is_not_solved_again(monkeypatch):
    """Where phi must reverse, th_1 held runs before the free rung; when it fails, the free
    answer (th_1 reversing) is not compared with the same NLP solved a second time."""
    req = PlanRequest(start=START[:4], goal=GOAL[:4], robot=Robot.default(4))
    tr = ladder(4)[0]
    monkeypatch.setattr(rungs_mod, "rungs", lambda r: [(tr, None)])
    monkeypatch.setattr(rungs_mod, "direction_conflict", lambda r: "th2 against th3")
    monkeypatch.setattr(rungs_mod, "th1_reach_ok", lambda r: True)
    free = answer(1, 1)
    free.nodes = free.nodes[:, :5]
    calls: list[str] = []

    def solve(tr_, signs, start_nodes=None, light=False):
        calls.append("free" if signs is None else f"held {np.asarray(signs).tolist()}")
        if signs is None:
            return free
        raise InfeasibleError("out of reach", diagnostics={"tried": []})

    sol, _, signs, _ = rungs_mod.solve_rungs(req, solve, merge_runs=True)
    # (then up to MERGE_TRIES patterns of its runs merged, each failing here)
    assert calls[:2] == ["held [0.0, 1.0]", "free"]
    assert calls.count("held [0.0, 1.0]") == 1
    assert len(calls) == 2 + rungs_mod.MERGE_TRIES
    assert sol is free and signs is None


def _one_free_rung(monkeypatch, phi_turns: int, th1_turns: int) -> tuple[PlanRequest, Answer]:
    """A 4-joint request whose ladder is one free rung (no th_1-held alternative) and that
    rung's answer: rates forward but for a short run backwards of phi (intervals 6-7) and,
    with ``th1_turns``, of th_1 (12-13), each 8 % of its actuator's travel (no wiggle,
    rungs.WIGGLE_SHARE)."""
    req = PlanRequest(start=START[:4], goal=GOAL[:4], robot=Robot.default(4))
    tr = ladder(4)[0]
    monkeypatch.setattr(rungs_mod, "rungs", lambda r: [(tr, None)])
    monkeypatch.setattr(rungs_mod, "direction_conflict", lambda r: None)
    monkeypatch.setattr(rungs_mod, "th1_reach_ok", lambda r: False)
    rates = np.ones((N, 2))
    rates[6:8, 0] = -1.0
    if th1_turns:
        rates[12:14, 1] = -1.0
    free = answer(phi_turns, th1_turns)
    free.nodes, free.rates = free.nodes[:, :5], rates
    return req, free


def test_a_merge_that_loses_a_reversal_is_kept_and_one_that_fails_is_not(monkeypatch):
    """An answer with two reversals or more: its runs, the one that travels least first, are
    merged into their neighbours and the NLP held to each pattern (rungs.MERGE_TRIES in all);
    the first that gains is kept, and the merging goes on from it."""
    # phi: + for 6 intervals, - for 2 (a short run), + for the rest: 2 reversals; th1 forward
    req, free = _one_free_rung(monkeypatch, 2, 0)
    held_seen: list[np.ndarray] = []
    merged = answer(0, 0)
    merged.nodes = merged.nodes[:, :5]

    def solve(tr_, signs, start_nodes=None, light=False):
        if signs is None:
            return free
        held_seen.append(np.asarray(signs))
        return merged

    sol, _, signs, _ = rungs_mod.solve_rungs(req, solve, merge_runs=True)
    assert sol is merged
    assert len(held_seen) == 1          # one gain, then nothing left to merge
    assert np.all(held_seen[0][:, 0] == 1.0) and np.all(held_seen[0][:, 1] == 1.0)


def test_merging_leaves_the_time_a_plan_needs(monkeypatch):
    """A merge's NLP starts only while MERGE_RESERVE times the rung's solve time is left, and
    one that runs out of time ends the merging with the answer found: the merging is an
    improvement, never the reason a found plan times out."""
    from optimizer.errors import SolverTimeoutError

    req, free = _one_free_rung(monkeypatch, 2, 2)
    held: list[str] = []

    def solve(tr_, signs, start_nodes=None, light=False):
        if signs is None:
            return free
        held.append("held")
        raise SolverTimeoutError("out of time", field="time_limit",
                                 diagnostics={"tried": [{"solver": "fatrop"}]})

    # no time left: no merge starts
    sol, _, _, _ = rungs_mod.solve_rungs(req, solve, merge_runs=True, time_left=lambda: 0.0)
    assert sol is free and held == []
    # time left, but the first merge runs out of it: the free answer stands, no second merge
    sol, _, _, tried = rungs_mod.solve_rungs(req, solve, merge_runs=True,
                                             time_left=lambda: 1e3)
    assert sol is free and held == ["held"]
    assert {"solver": "fatrop"} in tried
