"""``POST /v1/replans``: the continuation of a plan from a measured state (stateless).

A controller replans every few tens of milliseconds, so a valid request is answered by
:class:`FastReplanRoute` from the request middleware, as ``POST /v1/plans`` is
(:mod:`service.fastpath`): FastAPI's routing, dependency solving and response handling cost
the event loop more CPU than the rest of a replan request outside its worker. Anything it
does not take (another content type, malformed JSON, a schema violation) goes on to the
FastAPI route below with its body unchanged, so every error answer comes from the one route
that documents it.
"""

from typing import Any

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..dispatch import execute
from ..fastpath import FastJSONRoute
from ..responses import ReplanResponse
from ..schemas import ReplanRequest
from . import ERROR_RESPONSES
from .common import json_answer


def _payload(body: ReplanRequest) -> dict[str, Any]:
    """The job's payload: the fields as validated, the plan's fields that a replan reads as
    parsed (:class:`~service.schemas.ReplanPlan`; ``model_dump`` would copy them value by
    value; the library checks the plan itself)."""
    payload: dict[str, Any] = {"plan": body.plan.as_payload(), "time": body.time,
                               "state": body.state,
                               "keep_reversals": body.keep_reversals,
                               "fallback": body.fallback, "time_limit": body.time_limit}
    for name in ("rates", "duration", "gains"):
        if getattr(body, name) is not None:
            payload[name] = getattr(body, name)
    return payload


class FastReplanRoute(FastJSONRoute):
    """``POST /v1/replans`` answered from the request middleware (see the module docstring;
    :class:`service.fastpath.FastJSONRoute`)."""

    path = "/v1/replans"
    model = ReplanRequest

    async def answer(self, request: Any, request_id: str) -> Any:
        return await execute(self.state, "replan", _payload(request), request.time_limit,
                             method="replan", request_id=request_id)


def build_router() -> APIRouter:
    """The replan route."""
    router = APIRouter(tags=["plans"])

    @router.post("/replans", response_model=ReplanResponse, responses=ERROR_RESPONSES,
                 summary="Continue a plan from the measured state",
                 description="Takes a plan (an answer of /v1/plans or /v1/replans as returned, "
                             "or its compact form), the time since its start, the measured "
                             "state and the rates being commanded, and answers the rest of the "
                             "motion to the same goal, at rest by the plan's end (or a new "
                             "`duration`): it starts at those rates (no jump), is warm-started "
                             "from the plan's remaining part and verified on the original model "
                             "like any plan. Nothing is kept on the server: send the answer "
                             "back for the next replan. A state outside the region, a time past "
                             "the end, a plan that is not one of ours: 422 naming the field.")
    async def create_replan(body: ReplanRequest, request: Request) -> Response:
        return await json_answer(request, "replan", _payload(body), body.time_limit,
                                 method="replan")

    return router
