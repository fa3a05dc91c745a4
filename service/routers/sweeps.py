"""``POST /v1/sweeps``."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..schemas import Schemas
from ..responses import SweepResponse
from . import ERROR_RESPONSES
from .common import checked_sweep, json_answer


def build_router(S: Schemas) -> APIRouter:
    """The sweep route for the request models ``S``."""
    router = APIRouter(tags=["analysis"])

    @router.post("/sweeps", response_model=SweepResponse, responses=ERROR_RESPONSES,
                 summary="Indicators and feasibility as functions of dphi",
                 description="Evaluates the polynomial family (v1 constant) at `points` evenly "
                             "spaced dphi values in `phi_change_range` and, with `intervals`, "
                             "the exact singularity-free dphi intervals there. The request's "
                             "`time_limit` bounds the whole sweep.")
    async def create_sweep(body: S.SweepRequest, request: Request) -> Response:  # type: ignore[name-defined]
        return await json_answer(request, "sweep", checked_sweep(body), body.time_limit,
                                 method="sweep")

    return router
