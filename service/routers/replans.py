"""``POST /v1/replans``: the continuation of a plan from a measured state (stateless)."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..schemas import ReplanRequest
from ..responses import ReplanResponse
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
        payload = body.to_library()
        payload["time_limit"] = body.time_limit
        return await json_answer(request, "replan", payload, body.time_limit, method="replan")

    return router
