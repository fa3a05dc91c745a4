"""What the JSON and figure routes share: the checks a request passes in the event loop before
its job is queued (the library's own, :mod:`service.dispatch`), and the JSON answer of a job.

A figure route checks its body exactly as the JSON route whose answer it draws, through the
same function here, so that the two cannot refuse differently.
"""

from typing import Any

from fastapi import Request
from starlette.responses import Response

from ..dispatch import check_plan, run_job
from ..problems import SafeJSONResponse, ServiceProblem


def checked_plan(body: Any, **extra: Any) -> dict[str, Any]:
    """A plan request model's job payload (with ``extra`` fields set), checked by the library."""
    payload: dict[str, Any] = {**body.to_library(), **extra}
    check_plan(payload)
    return payload


def checked_sweep(body: Any) -> dict[str, Any]:
    """A sweep request model's job payload, its plan request checked by the library."""
    payload: dict[str, Any] = body.to_library()
    check_plan(payload["request"])
    return payload


def checked_robustness(body: Any) -> dict[str, Any]:
    """A robustness request model's job payload: its plan checked by the library (errors named
    ``plan.<field>``), and every given start as long as the plan's start (``starts[i]``)."""
    payload: dict[str, Any] = body.to_library()
    check_plan(payload["plan"], prefix="plan.")
    n = len(body.plan.start)
    for i, row in enumerate(body.starts or []):
        if len(row) != n:
            raise ServiceProblem("invalid_request", f"starts[{i}] has {len(row)} angles but "
                                 f"the plan has n = {n} joints", field=f"starts[{i}]")
    return payload


async def json_answer(request: Request, kind: str, payload: dict[str, Any], time_limit: float,
                      *, method: str) -> Response:
    """Run job ``kind`` on a worker (:func:`service.dispatch.run_job`) and answer its JSON, as
    the worker encoded it."""
    return SafeJSONResponse(await run_job(request, kind, payload, time_limit, method=method))
