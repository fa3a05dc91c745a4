"""RFC 9457 problem details: the one shape of every error answer of the service.

Every failure, whatever raised it, leaves the service as an ``application/problem+json`` body
with ``type``, ``title``, ``status``, a machine-readable ``code``, a human ``detail``, ``field``
when known, ``diagnostics`` and the ``request_id``. Status codes per code:

=================== ====== ==========================================================
code                status meaning
=================== ====== ==========================================================
invalid_request     422    the request is wrong (413 when the body is too large, 400
                           when it is not JSON at all, 415 when it was sent without
                           ``Content-Type: application/json``)
infeasible          422    no singularity-free path under the request's method/bounds
numerical_failure   422    a solver failed numerically or the path failed verification
                           (never 500)
timeout             504    the solve ran past its ``time_limit``
overloaded          503    too many requests wait for a worker, or none became free
                           within ``queue_timeout`` (``Retry-After`` set)
worker_lost         503    the solver process ended under the job twice (it is run
                           once more on another worker first; ``Retry-After`` set)
shutting_down       503    the server is stopping and could not finish the request
                           in time (``Retry-After``, ``Connection: close``)
request_timeout     408    the request's body did not arrive within ``body_timeout``
unauthorized        401    API keys are configured and none valid was sent
not_found           404    no such route
method_not_allowed  405    the route exists, not with this HTTP method
=================== ====== ==========================================================
"""

from __future__ import annotations

from typing import Any

from starlette.responses import JSONResponse

from .encoding import finite_json

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_BASE = "https://chained-planner.invalid/problems/"

#: HTTP status of each problem code.
STATUS_OF: dict[str, int] = {
    "invalid_request": 422,
    "infeasible": 422,
    "numerical_failure": 422,
    "timeout": 504,
    "overloaded": 503,
    "worker_lost": 503,
    "shutting_down": 503,
    "request_timeout": 408,
    "unauthorized": 401,
    "not_found": 404,
    "method_not_allowed": 405,
}

TITLE_OF: dict[str, str] = {
    "invalid_request": "Invalid request",
    "infeasible": "No feasible plan",
    "numerical_failure": "Numerical failure",
    "timeout": "Time limit exceeded",
    "overloaded": "Service overloaded",
    "worker_lost": "Solver process lost",
    "shutting_down": "Service shutting down",
    "request_timeout": "Request timeout",
    "unauthorized": "Unauthorized",
    "not_found": "Not found",
    "method_not_allowed": "Method not allowed",
}

#: Problem codes of the planning library's exceptions that the service passes through.
PLANNER_CODES = ("invalid_request", "infeasible", "timeout", "numerical_failure")


class ServiceProblem(Exception):
    """An error that the service answers as a problem document.

    Parameters
    ----------
    code : str
        One of :data:`STATUS_OF`'s keys.
    detail : str
        Human-readable explanation (no internal paths, no stack traces).
    field : str, optional
        The request field concerned (dotted path, ``[i]`` for list items).
    diagnostics : dict, optional
        Machine-readable details (finite numbers only).
    status : int, optional
        Overrides the code's default status (e.g. 413 for an over-large body).
    headers : dict, optional
        Extra response headers (``Retry-After``).
    """

    def __init__(self, code: str, detail: str, *, field: str | None = None,
                 diagnostics: dict[str, Any] | None = None, status: int | None = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        if code not in STATUS_OF:
            raise ValueError(f"unknown problem code {code!r}")
        self.code = code
        self.detail = detail
        self.field = field
        self.diagnostics = dict(diagnostics or {})
        self.status = status or STATUS_OF[code]
        self.headers = dict(headers or {})

    @classmethod
    def from_error(cls, error: dict[str, Any]) -> "ServiceProblem":
        """Build from a worker's error dict (``code``, ``message``, ``field``, ``diagnostics``)."""
        code = error.get("code")
        if code not in PLANNER_CODES:
            code = "numerical_failure"
        return cls(code, str(error.get("message") or TITLE_OF[code]), field=error.get("field"),
                   diagnostics=error.get("diagnostics") or {})

    def body(self, request_id: str | None = None) -> dict[str, Any]:
        """The problem document."""
        return problem_body(self.code, self.detail, status=self.status, field=self.field,
                            diagnostics=self.diagnostics, request_id=request_id)

    def response(self, request_id: str | None = None) -> "ProblemResponse":
        """The HTTP response carrying :meth:`body`."""
        return ProblemResponse(self.body(request_id), status_code=self.status,
                               headers=self.headers)


def problem_body(code: str, detail: str, *, status: int | None = None,
                 field: str | None = None, diagnostics: dict[str, Any] | None = None,
                 request_id: str | None = None) -> dict[str, Any]:
    """A problem document as a dict (see the module docstring)."""
    return {
        "type": TYPE_BASE + code,
        "title": TITLE_OF[code],
        "status": status or STATUS_OF[code],
        "code": code,
        "detail": detail,
        "field": field,
        "diagnostics": dict(diagnostics or {}),
        "request_id": request_id,
    }


class SafeJSONResponse(JSONResponse):
    """JSON response that refuses non-finite floats (they are sent as ``null``).

    ``bytes`` content is taken as already encoded JSON (the workers encode their results with
    :func:`service.encoding.finite_json`, so large bodies are never re-encoded here).
    """

    media_type = "application/json"

    def render(self, content: Any) -> bytes:
        if isinstance(content, bytes):
            return content
        return finite_json(content)


class ProblemResponse(SafeJSONResponse):
    """An ``application/problem+json`` response."""

    media_type = PROBLEM_MEDIA_TYPE
