"""``POST /v1/robustness``."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..schemas import Schemas
from ..responses import RobustnessResponse
from . import ERROR_RESPONSES
from .common import checked_robustness, json_answer


def build_router(S: Schemas) -> APIRouter:
    """The robustness route for the request models ``S``."""
    router = APIRouter(tags=["analysis"])

    @router.post("/robustness", response_model=RobustnessResponse, responses=ERROR_RESPONSES,
                 summary="Replay a plan open loop from perturbed starts",
                 description="Plans `plan`, then replays its inputs from each perturbed "
                             "start and measures where each run ends: `u` runs the handed-out "
                             "`path.u` by its rule (`path.rule`, what a controller executes; "
                             "see docs/execution.md), `v` the chained inputs through the input "
                             "map at the actual state. The top-level `time_limit` bounds the "
                             "whole job.")
    async def create_robustness(body: S.RobustnessRequest, request: Request) -> Response:  # type: ignore[name-defined]
        return await json_answer(request, "robustness", checked_robustness(body),
                                 body.time_limit, method=body.plan.method)

    return router
