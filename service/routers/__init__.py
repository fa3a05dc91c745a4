"""HTTP routers; each ``build_router`` takes the app's request schemas (their bounds come from
the settings)."""

from typing import Any

from ..responses import Problem

#: Error answers every ``/v1`` operation may give (documented as application/problem+json).
ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    400: {"model": Problem, "description": "invalid_request: the body is not JSON (malformed, "
                                           "not UTF-8, or nested too deeply)."},
    401: {"model": Problem, "description": "unauthorized: API keys are configured and the "
                                           "request has no valid X-API-Key."},
    408: {"model": Problem, "description": "request_timeout: the body did not arrive in "
                                           "time."},
    413: {"model": Problem, "description": "invalid_request: the body is larger than the "
                                           "service accepts."},
    415: {"model": Problem, "description": "invalid_request: the body was sent without "
                                           "Content-Type: application/json."},
    422: {"model": Problem, "description": "invalid_request (schema or library validation), "
                                           "infeasible (no singularity-free path), or "
                                           "numerical_failure (a solver failed or the path "
                                           "failed verification)."},
    503: {"model": Problem, "description": "overloaded: too many requests wait for a worker, "
                                           "or none became free in time; worker_lost: the "
                                           "solver process ended under the job twice; "
                                           "shutting_down: the server is stopping. All with "
                                           "Retry-After."},
    504: {"model": Problem, "description": "timeout: the job ran past its time_limit and was "
                                           "stopped."},
}
