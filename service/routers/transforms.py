"""``POST /v1/transforms``."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..dispatch import check_robot
from ..schemas import Schemas
from ..responses import TransformResponse
from . import ERROR_RESPONSES
from .common import json_answer


def build_router(S: Schemas) -> APIRouter:
    """The transform route for the request models ``S``."""
    router = APIRouter(tags=["analysis"])

    @router.post("/transforms", response_model=TransformResponse, responses=ERROR_RESPONSES,
                 summary="Map points between joint space and chained form",
                 description="`to_chained` maps rows q = [phi, th1..thn] to z = [z1..z_{n+1}] "
                             "(eq 4); `from_chained` maps z back. Points outside the region "
                             "where the map is a diffeomorphism are flagged `valid: false` with "
                             "the `reason`.")
    async def create_transform(body: S.TransformRequest, request: Request) -> Response:  # type: ignore[name-defined]
        payload = body.to_library()
        check_robot(payload.get("robot"), len(body.points[0]) - 1)
        return await json_answer(request, "transform", payload, body.time_limit,
                                 method="transform")

    return router
