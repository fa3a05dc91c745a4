"""The one loop of NLP attempts (:mod:`optimizer.planner.attempts`), on a stand-in NLP whose
solvers answer from a script (so every branch is reached without CasADi)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from optimizer.errors import InfeasibleError, SolverTimeoutError
from optimizer.planner.attempts import Attempt, first_converged


class ScriptedSolver:
    def __init__(self, status: str, success: bool) -> None:
        self.status, self.success = status, success

    def __call__(self, x0, p, lbx, ubx, lbg, ubg) -> list[np.ndarray]:
        return [np.asarray(x0, float) + 1.0]

    def stats(self) -> dict[str, Any]:
        return {"return_status": self.status, "success": self.success, "iter_count": 7}


class Callback:
    stop_at = math.inf


class ScriptedNLP:
    """Solver ``name`` answers the next (status, success) of its script."""

    def __init__(self, script: dict[str, list[tuple[str, bool]]]) -> None:
        self.script = {k: list(v) for k, v in script.items()}
        self.solver_names = tuple(script)
        self.callback = Callback()
        self.lbg = self.ubg = np.zeros(0)
        self.calls: list[str] = []

    def solver_call(self, name: str, lbx: np.ndarray, ubx: np.ndarray) -> ScriptedSolver:
        self.calls.append(name)
        return ScriptedSolver(*self.script[name].pop(0))

    def goal_miss(self, x: np.ndarray, p: np.ndarray) -> float:
        return 0.0  # the goal as hard rows: no heavier rounds (solvers.run_solver)

    def tightened(self, p: np.ndarray, factor: float) -> np.ndarray:
        return p


class Clock:
    def __init__(self, remaining: float = 10.0) -> None:
        self.remaining, self.seconds = remaining, 10.0


def run(nlp: ScriptedNLP, attempts, clock: Clock | None = None):
    z = np.zeros(2)
    return first_converged(nlp, attempts, z, z - 1, z + 1, clock or Clock(), "the test NLP",
                           "test")


def test_the_first_converged_attempt_is_returned_with_the_record() -> None:
    nlp = ScriptedNLP({"fatrop": [("1", False)], "ipopt": [("Solve_Succeeded", True)]})
    out = run(nlp, [Attempt("fatrop", "a", np.zeros(2)), Attempt("ipopt", "b", np.ones(2)),
                    Attempt("fatrop", "c", np.zeros(2))])
    assert out.solver == "ipopt" and out.guess == "b" and out.iterations == 7
    assert np.array_equal(out.x, np.full(2, 2.0))
    assert [t["solver"] for t in out.tried] == ["fatrop", "ipopt"]
    assert nlp.calls == ["fatrop", "ipopt"]  # nothing after the converged one


def test_attempts_are_built_lazily_and_unknown_solvers_skipped() -> None:
    built: list[str] = []

    def attempts():
        for name in ("knitro", "ipopt", "fatrop"):
            built.append(name)
            yield Attempt(name, name, np.zeros(2))

    nlp = ScriptedNLP({"ipopt": [("Solve_Succeeded", True)], "fatrop": []})
    assert run(nlp, attempts()).solver == "ipopt"
    assert built == ["knitro", "ipopt"]


def test_a_solver_stopped_at_the_deadline_raises_a_timeout() -> None:
    nlp = ScriptedNLP({"ipopt": [("Maximum_WallTime_Exceeded", False)],
                       "fatrop": [("success", True)]})
    with pytest.raises(SolverTimeoutError) as info:
        run(nlp, [Attempt("ipopt", "a", np.zeros(2)), Attempt("fatrop", "b", np.zeros(2))])
    assert info.value.field == "time_limit"
    assert nlp.calls == ["ipopt"]
    assert "the test NLP" in info.value.message


def test_no_time_left_runs_nothing_and_raises_a_timeout() -> None:
    nlp = ScriptedNLP({"ipopt": [("Solve_Succeeded", True)]})
    with pytest.raises(SolverTimeoutError):
        run(nlp, [Attempt("ipopt", "a", np.zeros(2))], Clock(0.0))
    assert nlp.calls == []


def test_every_attempt_failing_is_infeasible_with_the_record() -> None:
    nlp = ScriptedNLP({"ipopt": [("Infeasible_Problem_Detected", False),
                                 ("Maximum_Iterations_Exceeded", False)]})
    with pytest.raises(InfeasibleError) as info:
        run(nlp, [Attempt("ipopt", "a", np.zeros(2)), Attempt("ipopt", "b", np.ones(2))])
    assert info.value.diagnostics["blocking"] == "nlp_failed"
    assert [t["guess"] for t in info.value.diagnostics["tried"]] == ["a", "b"]
    assert nlp.calls == ["ipopt", "ipopt"]


def test_a_solver_is_not_run_twice_from_the_same_guess() -> None:
    """A solve is a function of its arguments: the same solver from the same guess (the
    shooting NLP offers each solver once per direction of phi's guess, which a start from
    nodes ignores) would answer the same again, so it is recorded as skipped, not run."""
    from optimizer.planner.attempts import SKIPPED_REPEAT

    nlp = ScriptedNLP({"fatrop": [("1", False), ("1", False)],
                       "ipopt": [("Maximum_Iterations_Exceeded", False)] * 2})
    same = np.array([0.5, -0.5])
    with pytest.raises(InfeasibleError) as info:
        run(nlp, [Attempt("fatrop", "nodes", same), Attempt("ipopt", "nodes", same),
                  Attempt("fatrop", "nodes", same.copy()), Attempt("ipopt", "nodes", same.copy()),
                  Attempt("fatrop", "other", same + 1e-12)])
    assert nlp.calls == ["fatrop", "ipopt", "fatrop"]
    statuses = [t["status"] for t in info.value.diagnostics["tried"]]
    assert statuses[2:4] == [SKIPPED_REPEAT] * 2 and statuses[4] == "1"


class ElasticNLP(ScriptedNLP):
    """Every round converges; round ``k`` misses the goal by ``misses[k]`` (rad)."""

    def __init__(self, misses: list[float]) -> None:
        super().__init__({"fatrop": [("Solve_Succeeded", True)] * len(misses)})
        self.misses = list(misses)

    def goal_miss(self, x: np.ndarray, p: np.ndarray) -> float:
        return self.misses[len(self.calls) - 1]


@pytest.mark.parametrize("misses, rounds, kind", [
    ([1e-9], 1, "success"),                   # on the goal at once
    ([1e-5, 1e-8], 2, "success"),             # the heavier round reaches it
    ([1e-5, 5e-7, 1e-9], 3, "success"),       # each round ten times closer: all three run
    ([6e-5, 3.3e-5, 3.3e-5], 2, "failure"),   # stalled: no third round, and no answer
    ([2e-3, 1.9e-3, 1e-9], 2, "infeasible"),  # far and stalled: out of reach
])
def test_elastic_rounds_run_while_each_comes_ten_times_closer(misses, rounds, kind):
    from optimizer.planner.solvers import ELASTIC_ROUNDS, run_solver
    assert len(misses) <= ELASTIC_ROUNDS + 1
    nlp = ElasticNLP(misses)
    z = np.zeros(2)
    out = run_solver(nlp, "fatrop", z, z, z - 1, z + 1, 10.0)  # type: ignore[arg-type]
    assert len(nlp.calls) == rounds
    assert out.kind == kind
    assert out.iterations == 7 * rounds


def test_fatrop_is_not_started_when_its_cap_at_its_pace_outlasts_the_time_left() -> None:
    """fatrop calls no iteration callback: a solve whose iteration cap, at the pace of its
    NLP's recent solves, would end after the deadline is not started (a timeout at once, no
    solver memory taken); IPOPT, which the deadline stops, is started all the same."""
    from optimizer.planner.solvers import FATROP_MAX_ITER, SolverPace, run_solver

    nlp = ScriptedNLP({"fatrop": [("success", True)], "ipopt": [("Solve_Succeeded", True)]})
    nlp.pace = SolverPace({"fatrop": FATROP_MAX_ITER})  # type: ignore[attr-defined]
    nlp.pace.record("fatrop", 0.5, 10)          # 0.05 s an iteration
    nlp.pace.record("ipopt", 5.0, 10)
    z = np.zeros(2)
    left = 0.9 * 0.05 * FATROP_MAX_ITER
    out = run_solver(nlp, "fatrop", z, z, z - 1, z + 1, left)  # type: ignore[arg-type]
    assert out.kind == "timeout" and "not started" in out.status and out.x is None
    assert nlp.calls == []
    out = run_solver(nlp, "ipopt", z, z, z - 1, z + 1, left)  # type: ignore[arg-type]
    assert out.kind == "success" and nlp.calls == ["ipopt"]
    # with time for the cap it runs, and its own solve sets the pace
    enough = 1.1 * 0.05 * FATROP_MAX_ITER
    out = run_solver(nlp, "fatrop", z, z, z - 1, z + 1, enough)  # type: ignore[arg-type]
    assert out.kind == "success" and nlp.calls == ["ipopt", "fatrop"]
    assert len(nlp.pace.recent["fatrop"]) == 2
    # through the attempts' loop: a timeout naming the time limit
    nlp2 = ScriptedNLP({"fatrop": [("success", True)]})
    nlp2.pace = SolverPace({"fatrop": FATROP_MAX_ITER})  # type: ignore[attr-defined]
    nlp2.pace.record("fatrop", 100.0, 10)
    with pytest.raises(SolverTimeoutError) as info:
        run(nlp2, [Attempt("fatrop", "a", np.zeros(2))])
    assert info.value.field == "time_limit" and nlp2.calls == []


def test_the_pace_is_the_slowest_of_the_recent_solves() -> None:
    from optimizer.planner.solvers import PACE_MIN_ITERATIONS, PACE_SOLVES, SolverPace

    pace = SolverPace({"fatrop": 60})
    assert not pace.too_slow("fatrop", 1e-9)              # unknown: no guess
    pace.record("fatrop", 1.0, PACE_MIN_ITERATIONS - 1)   # too few iterations: not counted
    assert not pace.too_slow("fatrop", 1e-9)
    pace.record("fatrop", 6.7, 1000)                      # 6.7 ms an iteration
    pace.record("fatrop", 2.2, 1000)
    assert pace.too_slow("fatrop", 0.40) and not pace.too_slow("fatrop", 0.41)
    for _ in range(PACE_SOLVES - 1):                      # the slow one ages out
        pace.record("fatrop", 2.2, 1000)
    assert not pace.too_slow("fatrop", 0.14) and pace.too_slow("fatrop", 0.13)
    pace.record("ipopt", 100.0, 10)                       # no cap (its callback stops it)
    assert not pace.too_slow("ipopt", 1e-9)


def test_the_pace_counts_the_nlps_own_iteration_cap() -> None:
    """The reversal budget's NLP caps fatrop at 150 iterations, not 60: its pace says so."""
    from optimizer.model import Robot
    from optimizer.planner import budget
    from optimizer.planner.solvers import FATROP_MAX_ITER

    robot = Robot.default(3)
    nlp = budget.prepare(robot.gains, robot.exponents)
    assert nlp.pace.caps == {"fatrop": dict(budget.FATROP_SETTINGS)["max_iter"]} != {
        "fatrop": FATROP_MAX_ITER}
