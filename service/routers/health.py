"""``GET /healthz``, ``GET /readyz`` and ``GET /metrics`` (no authentication)."""

from fastapi import APIRouter, Request
from starlette.responses import Response

from ..problems import SafeJSONResponse
from ..schemas import Health, Readiness


def build_router() -> APIRouter:
    """The operational routes."""
    router = APIRouter(tags=["operations"])

    @router.get("/healthz", response_model=Health, summary="Liveness: the server answers")
    async def healthz() -> Response:
        return SafeJSONResponse({"status": "ok"})

    @router.get("/readyz", response_model=Readiness,
                responses={503: {"model": Readiness, "description": "Not ready yet (workers "
                                                                      "starting) or stopping."}},
                summary="Readiness: the worker pool is up and warmed up")
    async def readyz(request: Request) -> Response:
        pool = getattr(request.app.state, "pool", None)
        if pool is None:
            return SafeJSONResponse({"status": "starting", "workers": 0, "idle": 0, "busy": 0,
                                     "waiting": 0, "restarts": 0}, status_code=503)
        st = pool.stats()
        status = "ready" if pool.ready else ("stopping" if st.started and st.warmed
                                             else "starting")
        return SafeJSONResponse({"status": status, "workers": st.size, "idle": st.idle,
                                 "busy": st.busy, "waiting": st.waiting,
                                 "restarts": st.restarts},
                                status_code=200 if status == "ready" else 503)

    @router.get("/metrics", summary="Prometheus metrics (text exposition format)",
                response_class=Response,
                responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}},
                                 "description": "Prometheus text format."}})
    async def metrics(request: Request) -> Response:
        m = request.app.state.metrics
        return Response(m.render(), media_type=m.content_type)

    return router
