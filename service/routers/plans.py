"""``POST /v1/plans`` and ``POST /v1/plans/batch``."""

import asyncio
from typing import Any

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..dispatch import answer_plan, check_plan, overloaded, request_id, run_job
from ..encoding import finite_json
from ..problems import SafeJSONResponse, ServiceProblem
from ..schemas import Schemas
from ..responses import BatchResponse, PlanResponse
from ..workers import Overloaded
from . import ERROR_RESPONSES


def build_router(S: Schemas) -> APIRouter:
    """The plan routes for the request models ``S``."""
    router = APIRouter(tags=["plans"])

    @router.post("/plans", response_model=PlanResponse, responses=ERROR_RESPONSES,
                 summary="Plan a singularity-free motion",
                 description="Plans a path from `start` to `goal` (joint angles, rad), verified "
                             "by re-integrating the original model. A request that cannot be "
                             "planned is answered with a problem document, never a 200.")
    async def create_plan(body: S.PlanRequest, request: Request) -> Response:  # type: ignore[name-defined]
        return SafeJSONResponse(await answer_plan(request.app.state, body,
                                                  request_id(request)))

    @router.post("/plans/batch", response_model=BatchResponse, responses=ERROR_RESPONSES,
                 summary="Plan many motions in parallel",
                 description="Solves every request across the workers; the answer lists one "
                             "item per request, in order, each with its plan or its problem. "
                             "A batch is admitted (or refused with 503) as a whole; its items "
                             "then wait for workers.")
    async def create_plans(body: S.BatchRequest, request: Request) -> Response:  # type: ignore[name-defined]
        pool = request.app.state.pool
        try:
            pool.admit(reserve=len(body.requests))  # the items' places in the queue
        except Overloaded as exc:
            raise overloaded(request.app.state.settings, str(exc)) from None
        started = 0

        async def one(index: int, item: Any) -> tuple[bool, bytes]:
            # each item is JSON already: the plans come encoded from the workers
            nonlocal started
            try:
                payload = item.to_library()
                check_plan(payload, prefix=f"requests[{index}].")
                started += 1  # run_job takes the item's reserved place before any await
                plan = await run_job(request, "plan", payload, item.time_limit,
                                     method=item.method, admit=False)
                return True, b'{"index":%d,"status":"success","plan":%s,"problem":null}' % (
                    index, plan)
            except ServiceProblem as problem:
                return False, finite_json({"index": index, "status": "error", "plan": None,
                                           "problem": problem.body(request_id(request))})

        try:
            results = await asyncio.gather(*(one(i, r) for i, r in enumerate(body.requests)))
        finally:
            pool.release(len(body.requests) - started)  # items refused before they ran
        ok = sum(success for success, _ in results)
        return SafeJSONResponse(b'{"results":[%s],"succeeded":%d,"failed":%d}' % (
            b",".join(item for _, item in results), ok, len(results) - ok))

    return router
