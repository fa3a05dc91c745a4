"""``POST /v1/robustness``."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..dispatch import check_plan, run_job
from ..problems import SafeJSONResponse, ServiceProblem
from ..schemas import RobustnessResponse, Schemas
from . import ERROR_RESPONSES


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
        payload = body.to_library()
        check_plan(payload["plan"], prefix="plan.")
        n = len(body.plan.start)
        for i, row in enumerate(body.starts or []):
            if len(row) != n:
                raise ServiceProblem("invalid_request", f"starts[{i}] has {len(row)} angles but "
                                     f"the plan has n = {n} joints", field=f"starts[{i}]")
        result = await run_job(request, "robustness", payload, body.time_limit,
                               method=body.plan.method)
        return SafeJSONResponse(result)

    return router
