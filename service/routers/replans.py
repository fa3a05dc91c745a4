"""``POST /v1/replans``: the continuation of a plan from a measured state (stateless)."""

from typing import Any

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..schemas import ReplanRequest, ReplanResponse
from . import ERROR_RESPONSES
from .common import json_answer


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
        # the fields as validated, the plan as parsed: model_dump would copy the whole
        # earlier answer value by value (2.5 ms of a 40 kB answer; the replan takes about as
        # long), and the library checks the plan itself
        payload: dict[str, Any] = {"plan": body.plan, "time": body.time, "state": body.state,
                                   "keep_reversals": body.keep_reversals,
                                   "time_limit": body.time_limit}
        for name in ("rates", "duration"):
            if getattr(body, name) is not None:
                payload[name] = getattr(body, name)
        return await json_answer(request, "replan", payload, body.time_limit, method="replan")

    return router
