"""``GET /v1/robots/default``."""

from fastapi import APIRouter, Query
from starlette.responses import Response

from optimizer.model import Robot

from ..problems import SafeJSONResponse
from ..responses import DefaultRobot
from ..schema_fields import MAX_JOINTS, MIN_JOINTS
from . import ERROR_RESPONSES

ASSUMED_NOTE = ("The paper gives constants for n = 3 only; for other n these are the assumed "
                "extension K_i = 0.88658 (i < n), K_n = 0.7115, m_i = 2 (i < n), m_n = 3.")


def build_router(max_joints: int = MAX_JOINTS) -> APIRouter:
    """The robot routes (``n`` up to ``max_joints``)."""
    router = APIRouter(tags=["robots"])

    @router.get("/robots/default", response_model=DefaultRobot,
                responses={k: v for k, v in ERROR_RESPONSES.items() if k in (401, 422)},
                summary="The default robot constants for n joints")
    async def default_robot(
        n: int = Query(3, ge=MIN_JOINTS, le=max_joints, description="Number of joints."),
    ) -> Response:
        info = Robot.default(n).as_dict()
        info["note"] = ASSUMED_NOTE if info.get("assumed_constants") else None
        return SafeJSONResponse(info)

    return router
