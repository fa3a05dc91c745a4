"""``GET /healthz``, ``GET /readyz`` and ``GET /metrics`` (no authentication)."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..problems import SafeJSONResponse
from ..responses import Health, Readiness


def build_router() -> APIRouter:
    """The operational routes."""
    router = APIRouter(tags=["operations"])

    @router.get("/healthz", response_model=Health, summary="Liveness: the server answers")
    async def healthz() -> Response:
        return SafeJSONResponse({"status": "ok"})

    @router.get("/readyz", response_model=Readiness,
                responses={503: {"model": Readiness, "description": "No live worker (starting, "
                                                                      "or all lost and being "
                                                                      "replaced) or stopping."}},
                summary="Readiness: at least one worker process is live")
    async def readyz(request: Request) -> Response:
        pool = getattr(request.app.state, "pool", None)
        if pool is None:
            return SafeJSONResponse({"status": "starting", "workers": 0, "live": 0, "idle": 0,
                                     "busy": 0, "waiting": 0, "restarts": 0}, status_code=503)
        st = pool.stats()
        if st.closing:
            status = "stopping"
        elif not st.warmed:
            status = "starting"
        else:
            status = "ready" if st.live > 0 else "unavailable"
        return SafeJSONResponse({"status": status, "workers": st.size, "live": st.live,
                                 "idle": st.idle, "busy": st.busy, "waiting": st.waiting,
                                 "restarts": st.restarts},
                                status_code=200 if status == "ready" else 503)

    @router.get("/metrics", summary="Prometheus metrics (text exposition format)",
                response_class=Response,
                responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                 "description": "Prometheus text format."}})
    async def metrics(request: Request) -> Response:
        m = request.app.state.metrics
        return Response(m.render(), media_type=m.content_type)

    # HEAD too (load balancers and uptime checks probe with it; it was 405): the same routes,
    # one operation each in the OpenAPI document
    router.add_api_route("/healthz", healthz, methods=["HEAD"], include_in_schema=False,
                         name="healthz_head")
    router.add_api_route("/readyz", readyz, methods=["HEAD"], include_in_schema=False,
                         name="readyz_head")
    return router
