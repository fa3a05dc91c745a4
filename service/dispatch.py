"""The routers' one way to the workers: validate, run a job, map every outcome to HTTP.

A job's outcome becomes either its JSON body (encoded by the worker) or a
:class:`ServiceProblem`:

==============================  ===========================================================
pool / worker outcome           problem
==============================  ===========================================================
``Overloaded``, ``QueueTimeout`` 503 ``overloaded`` with ``Retry-After``
``JobTimeout`` (worker killed)  504 ``timeout``
``WorkerLost`` (lost twice)     503 ``worker_lost`` with ``Retry-After``
``ShuttingDown``                503 ``shutting_down`` with ``Retry-After``,
                                ``Connection: close``
library ``PlannerError``        its own code (``invalid_request``, ``infeasible``,
                                ``timeout``, ``numerical_failure``)
==============================  ===========================================================
"""

from __future__ import annotations

import time
from typing import Any, Callable, TypeVar

from fastapi import Request

from optimizer.errors import PlannerError
from optimizer.problem import PlanRequest

from .robot_spec import robot_from
from .problems import ServiceProblem
from .settings import Settings
from .workers import JobTimeout, Overloaded, ShuttingDown, WorkerLost, WorkerPool

T = TypeVar("T")

#: Seconds of the grace kept for killing an overrunning worker and sending the answer, so that a
#: timeout is answered within ``time_limit + timeout_grace`` of the job reaching a worker (the
#: worker is killed at ``time_limit + timeout_grace - ANSWER_MARGIN``, never before
#: ``time_limit``).
ANSWER_MARGIN = 0.05


def request_id(request: Request) -> str | None:
    """The request's id (set by the middleware)."""
    return getattr(request.state, "request_id", None)


def library_check(build: Callable[..., T], *args: Any, prefix: str = "") -> T:
    """Run one of the library's cheap constructors/validators here, before queueing.

    ``PlanRequest.from_dict`` and ``Robot`` validate the request as the workers will; a
    failure is answered at once without occupying a worker. ``prefix`` is put before the
    error's field (``plan.``, ``requests[3].``).
    """
    try:
        return build(*args)
    except PlannerError as exc:
        field = exc.field
        if prefix:
            field = prefix + field if field else prefix.rstrip(".")
        raise ServiceProblem("invalid_request", exc.message, field=field,
                             diagnostics=exc.diagnostics) from None


def check_plan(payload: dict[str, Any], prefix: str = "") -> None:
    """Validate a plan-request dict with :meth:`optimizer.problem.PlanRequest.from_dict`."""
    library_check(PlanRequest.from_dict, payload, prefix=prefix)


def check_robot(spec: dict[str, Any] | None, n: int) -> None:
    """Validate a robot spec for ``n`` joints with :class:`optimizer.model.Robot`."""
    library_check(robot_from, spec, n)


async def run_job(request: Request, kind: str, payload: dict[str, Any], time_limit: float, *,
                  method: str, admit: bool = True) -> bytes:
    """Run ``kind`` on a worker with ``time_limit`` (+ grace) and return its result as JSON.

    Parameters
    ----------
    request : Request
    kind : str
        ``plan``, ``sweep``, ``transform`` or ``robustness``.
    payload : dict
    time_limit : float
        The job's own limit (s); the worker is killed ``timeout_grace - ANSWER_MARGIN`` s after
        it, so that the timeout is answered within ``time_limit + timeout_grace``.
    method : str
        Label of the solve metric (the requested method, or the job kind).
    admit : bool
        Apply the queue bound (False for items of an admitted batch).

    Returns
    -------
    bytes
        The result, encoded as JSON by the worker (finite numbers only).

    Raises
    ------
    ServiceProblem
    """
    return await execute(request.app.state, kind, payload, time_limit, method=method,
                         admit=admit, request_id=request_id(request))


async def answer_plan(state: Any, body: Any, request_id: str | None = None) -> bytes:
    """``POST /v1/plans`` for a validated request model: the library's own checks, then the
    plan on a worker. The one body of both entry points (the route and
    :mod:`service.fastpath`), so that they cannot answer differently.

    Raises
    ------
    ServiceProblem
    """
    payload = body.to_library()
    check_plan(payload)
    return await execute(state, "plan", payload, body.time_limit, method=body.method,
                         request_id=request_id)


async def execute(state: Any, kind: str, payload: dict[str, Any], time_limit: float, *,
                  method: str, admit: bool = True, request_id: str | None = None) -> bytes:
    """:func:`run_job` given the app's ``state`` (``pool``, ``settings``, ``metrics``)."""
    pool: WorkerPool = state.pool
    settings: Settings = state.settings
    metrics = state.metrics
    started = time.perf_counter()
    try:
        wait = time_limit + max(settings.timeout_grace - ANSWER_MARGIN, 0.0)
        outcome = await pool.run(kind, payload, wait, admit=admit, request_id=request_id)
    except Overloaded as exc:
        raise overloaded(settings, str(exc)) from None
    except ShuttingDown as exc:
        metrics.observe_solve(kind, method, "shutting_down", time.perf_counter() - started)
        raise shutting_down(settings, str(exc)) from None
    except JobTimeout:
        metrics.observe_solve(kind, method, "timeout", time.perf_counter() - started)
        raise ServiceProblem("timeout", f"the job exceeded its time limit of {time_limit:g} s "
                             "and was stopped", field="time_limit",
                             diagnostics={"time_limit": time_limit}) from None
    except WorkerLost:
        metrics.observe_solve(kind, method, "worker_lost", time.perf_counter() - started)
        raise ServiceProblem("worker_lost", "the solver process ended under this job twice "
                             "(it was replaced each time); retry later",
                             headers={"Retry-After": str(settings.retry_after)},
                             diagnostics={"retry_after": settings.retry_after}) from None
    seconds = float(outcome.get("seconds") or (time.perf_counter() - started))
    if outcome["ok"]:
        metrics.observe_solve(kind, method, "success", seconds)
        return outcome["body"]
    problem = ServiceProblem.from_error(outcome["error"])
    if problem.code == "timeout" and problem.field is None:
        problem.field = "time_limit"  # the library's own deadline check fired
        problem.diagnostics.setdefault("time_limit", time_limit)
    metrics.observe_solve(kind, method, problem.code, seconds)
    raise problem


def shutting_down(settings: Settings, why: str) -> ServiceProblem:
    """The 503 of a request the stopping server gives up (the connection closes after it)."""
    return ServiceProblem("shutting_down", f"{why}; retry (another replica may answer)",
                          headers={"Retry-After": str(settings.retry_after),
                                   "Connection": "close"},
                          diagnostics={"retry_after": settings.retry_after})


def overloaded(settings: Settings, why: str) -> ServiceProblem:
    """The 503 problem with ``Retry-After``."""
    return ServiceProblem("overloaded", f"the service is busy ({why}); retry later",
                          headers={"Retry-After": str(settings.retry_after)},
                          diagnostics={"retry_after": settings.retry_after})
