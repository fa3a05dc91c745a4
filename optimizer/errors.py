"""Typed exceptions of the planning library.

Every failure the planner can meet is one of these; the service maps each class to one
machine-readable problem code (see ``code``).
"""

from __future__ import annotations

from typing import Any


class PlannerError(Exception):
    """Base class of every error raised on purpose by :mod:`optimizer`.

    Parameters
    ----------
    message : str
        Human-readable explanation naming the problem (field, limit, condition).
    field : str, optional
        The request field the error is about, when there is one.
    diagnostics : dict, optional
        Machine-readable details (JSON-serialisable, finite numbers only).
    """

    code = "planner_error"

    def __init__(self, message: str, *, field: str | None = None,
                 diagnostics: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field
        self.diagnostics = dict(diagnostics or {})


class InvalidRequestError(PlannerError, ValueError):
    """The request itself is wrong: out of range, non-finite, outside the region."""

    code = "invalid_request"


class SingularSystemError(InvalidRequestError):
    """The steering system (eq 11) is singular: dphi = 0 (Remark 2) or bad constraint times."""

    code = "invalid_request"


class InfeasibleError(PlannerError):
    """No singularity-free path exists under the request's method and bounds."""

    code = "infeasible"


class SolverTimeoutError(PlannerError):
    """The solve ran past its time limit."""

    code = "timeout"


class NumericalError(PlannerError):
    """A solver failed numerically, or a path failed verification on the original model."""

    code = "numerical_failure"
