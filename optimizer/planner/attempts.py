"""One NLP solved from a sequence of attempts (a solver and a guess) until one converges.

``shooting`` (:func:`~.shooting.solve_shooting`) and the reversal budget (:mod:`.budget`) both
run the same loop: stop when the deadline is spent, run a solver (:func:`~.solvers.run_solver`),
record the attempt, return the first converged answer, raise
:class:`~optimizer.errors.SolverTimeoutError` when a solver ran out of time and
:class:`~optimizer.errors.InfeasibleError` when every attempt failed. This module is that loop.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Protocol

import numpy as np

from ..errors import InfeasibleError, SolverTimeoutError
from .solvers import ELASTIC_ACCEPT, SolvableNLP, run_solver

class AttemptableNLP(SolvableNLP, Protocol):
    """What :func:`first_converged` needs of an NLP: :class:`~.solvers.SolvableNLP` and the
    names of its solvers, in order (``solver_names``)."""

    solver_names: tuple[str, ...]


#: No attempt starts once less than this is left of the deadline (s).
MIN_ATTEMPT_TIME = 1e-3
#: The status of an attempt not run because its solver already ran from the same guess: a
#: solve is a function of its arguments (nlp.MultipleShootingNLP.solver_call), so it would
#: answer the same again. ``shooting`` from a previous solution's nodes offers each solver
#: twice, once per direction of ``phi``'s guess, which a start from nodes does not use: on a
#: failing 5-joint ladder (every joint 10 -> 80 deg) the repeats were 414 of its iterations.
#: Skipping another solver where one converged off the goal was tried too: IPOPT then
#: converged off the goal as well on 50 of 52 such tries, but one of the other two was a
#: 6-joint goal (issue 25's) that IPOPT planned from a fatrop miss of 1.3e-4 rad, with 11
#: reversals, where without it the legs answered with 15 and rates of 39 rad/s.
SKIPPED_REPEAT = "skipped: this solver ran from this guess already"


class MissedGoal(InfeasibleError):
    """Every attempt failed, one of them by converging off the goal (the elastic goal's miss
    stayed; :func:`~.solvers.run_solver`): its solution vector ``x`` (and, where the caller
    unpacked it, its node states ``nodes``) is a start for a finer transcription, closer to a
    path than any straight line."""

    def __init__(self, message: str, *, x: np.ndarray, nodes: np.ndarray | None = None,
                 diagnostics: dict[str, Any] | None = None) -> None:
        super().__init__(message, diagnostics=diagnostics)
        self.x = x
        self.nodes = nodes


@dataclass(frozen=True)
class Attempt:
    """One try: solver ``solver`` (a name of the NLP's ``solvers``) from ``x0``, the guess
    ``guess`` describes (for the diagnostics)."""

    solver: str
    guess: str
    x0: np.ndarray


@dataclass(frozen=True)
class Converged:
    """The first converged attempt: its solution vector, solver, status, iterations and guess,
    and the record of every attempt run (this one last)."""

    x: np.ndarray
    solver: str
    status: str
    iterations: int
    guess: str
    tried: tuple[dict[str, Any], ...]


def first_converged(nlp: AttemptableNLP, attempts: Iterable[Attempt], p: np.ndarray,
                    lbx: np.ndarray, ubx: np.ndarray, deadline: Any, what: str,
                    stage: str, *, accept_miss: float = ELASTIC_ACCEPT) -> Converged:
    """Run ``attempts`` in order (lazily: an iterable's guesses are built only when tried)
    until one converges; an attempt whose solver already ran from the same guess is not run
    (:data:`SKIPPED_REPEAT`).

    Parameters
    ----------
    nlp : AttemptableNLP
        The NLP (its ``solvers``, ``callback``, ``lbg``, ``ubg``).
    attempts : iterable of Attempt
        Solvers the NLP does not have are skipped.
    p, lbx, ubx : numpy.ndarray
        Parameters and variable bounds, the same for every attempt.
    deadline : Deadline
        ``remaining`` and ``seconds`` (:class:`~optimizer.deadline.Deadline`).
    what, stage : str
        The NLP's name in the messages (``"the shooting NLP"``) and the diagnostics' stage.
    accept_miss : float
        How far from an elastic goal a converged answer may end (rad,
        :func:`~.solvers.run_solver`).

    Raises
    ------
    SolverTimeoutError
        A solver stopped at the deadline, or the deadline left no time for an attempt
        (``field="time_limit"``; ``diagnostics["tried"]``).
    InfeasibleError
        Every attempt failed (``diagnostics["blocking"] = "nlp_failed"``, ``["tried"]``);
        :class:`MissedGoal` when one converged off the goal (its ``x``, the first such).
    NumericalError
        A solver raised (:func:`~.solvers.run_solver`).
    """
    names = set(nlp.solver_names)
    tried: list[dict[str, Any]] = []
    missed: np.ndarray | None = None

    def timeout() -> SolverTimeoutError:
        return SolverTimeoutError(
            f"{what} did not converge within the time limit of {deadline.seconds:g} s",
            field="time_limit", diagnostics={"stage": stage, "tried": tried})

    ran: set[tuple[str, bytes]] = set()    # (solver, guess's bytes) of the attempts run
    for at in attempts:
        if at.solver not in names:
            continue
        key = (at.solver, np.ascontiguousarray(at.x0, float).tobytes())
        if key in ran:
            tried.append({"solver": at.solver, "guess": at.guess, "status": SKIPPED_REPEAT,
                          "iterations": 0})
            continue
        ran.add(key)
        if deadline.remaining <= MIN_ATTEMPT_TIME:
            break
        out = run_solver(nlp, at.solver, at.x0, p, lbx, ubx, deadline.remaining,
                         accept_miss=accept_miss)
        tried.append({"solver": at.solver, "guess": at.guess, "status": out.status,
                      "iterations": out.iterations})
        if out.success and out.x is not None:
            return Converged(x=out.x, solver=at.solver, status=out.status,
                             iterations=out.iterations, guess=at.guess, tried=tuple(tried))
        if out.kind == "timeout":
            raise timeout()
        if out.kind == "infeasible" and out.x is not None and missed is None:
            missed = out.x
    if not tried or deadline.remaining <= MIN_ATTEMPT_TIME:
        raise timeout()
    message = (f"{what} found no path from any start: "
               + "; ".join(f"{t['solver']} {t['status']}" for t in tried))
    diagnostics = {"blocking": "nlp_failed", "tried": tried}
    if missed is not None:
        raise MissedGoal(message, x=missed, diagnostics=diagnostics)
    raise InfeasibleError(message, diagnostics=diagnostics)


__all__ = ["Attempt", "AttemptableNLP", "Converged", "MIN_ATTEMPT_TIME", "MissedGoal",
           "SKIPPED_REPEAT", "first_converged"]
