"""What every method is handed besides the request: its time budget and what is known already.

A leaf of the planner: it imports nothing of the planner, so every method, the finishing path,
the ranking and the orchestrator can use it without an import circle.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from ..errors import SolverTimeoutError


#: Set by :func:`cancel` (e.g. from a signal handler of a worker process whose client went
#: away): every deadline check then fails, ending the solve at its next check. Cleared by
#: :func:`clear_cancel` before each job.
_cancelled = [False]


def cancel() -> None:
    """End the solve in progress at its next deadline check (safe in a signal handler: it only
    sets a flag; the solve stops where its own checks are, leaving no state half-built)."""
    _cancelled[0] = True


def clear_cancel() -> None:
    """Undo :func:`cancel` (before the next job)."""
    _cancelled[0] = False


class Deadline:
    """Wall-clock budget of one solve; :meth:`check` raises :class:`SolverTimeoutError` (also
    after :func:`cancel`)."""

    def __init__(self, seconds: float) -> None:
        self.start = time.perf_counter()
        self.seconds = float(seconds)

    @property
    def remaining(self) -> float:
        return self.seconds - (time.perf_counter() - self.start)

    def check(self, stage: str) -> None:
        if self.remaining <= 0.0 or _cancelled[0]:
            raise SolverTimeoutError(f"the solve exceeded its time limit of {self.seconds:g} s "
                                     f"during {stage}", field="time_limit",
                                     diagnostics={"stage": stage, "time_limit": self.seconds})


@dataclass
class PlanContext:
    """The context of one method's run.

    Attributes
    ----------
    deadline : Deadline
        The request's budget (shared by every method ``auto`` runs).
    warm_start : object or None
        The inputs of a verified plan already in hand (an
        :class:`~optimizer.steering.InputSchedule` or
        :class:`~optimizer.actuation.ActuatorSchedule`); a method that can start from it may.
    """

    deadline: Deadline
    warm_start: Any = None
