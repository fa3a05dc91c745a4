"""The ASGI app of the planning service: ``service.main:app`` (``python -m service`` runs it).

:func:`create_app` wires settings, the worker pool (started and stopped by the lifespan), the
routers under ``/v1``, problem-document error handlers, the request middleware (request id,
body limit, metrics, access log), offline docs pages and the OpenAPI document.
"""

from __future__ import annotations

import asyncio
import difflib
import functools
import typing

from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse
from fastapi.routing import APIRoute
from fastapi.security import APIKeyHeader
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import Response

from . import __version__
from .auth import CHALLENGE, UNAUTHORIZED_DETAIL, authorized, encode_keys
from .compression import GZipWhenAccepted
from .dispatch import request_id
from .fastpath import FastPlanRoute, is_json
from .metrics import Metrics
from .middleware import RequestContextMiddleware
from .problems import PROBLEM_MEDIA_TYPE, SafeJSONResponse, ServiceProblem
from .routers import (explorer, figures, health, plans, replans, robots, robustness, sweeps,
                      transforms)
from .schemas import build_schemas
from .settings import Settings
from .workers import WorkerPool

STATIC_DIR = Path(__file__).parent / "static"
#: Answers shorter than this are sent as they are (one TCP segment: gzip would not pay).
GZIP_MINIMUM_BYTES = 1400
#: Answers never compressed: the continuations a control loop waits for
#: (:mod:`service.compression`).
UNCOMPRESSED_PATHS = frozenset({"/v1/replans"})
TITLE = "Chained-form motion planner"
DESCRIPTION = """\
Singularity-free motion planning for an underactuated n-joint manipulator whose kinematics
convert to chained form.

* JSON bodies, snake_case fields, **radians and seconds** everywhere.
* Failures are `application/problem+json` documents with a machine-readable `code`:
  `invalid_request` (422; 413 for an over-large body, 431 for over-large headers, 400 for
  malformed HTTP or JSON; 415 for a body sent without `Content-Type: application/json`),
  `request_timeout` (408: the body did not arrive in time),
  `infeasible` (422), `numerical_failure` (422: a solver failed numerically or the path failed
  verification on the original model; the service never answers 500), `timeout` (504),
  `overloaded` (503: the queue is full or no worker became free in time), `worker_lost` (503:
  the solver process ended under the job, twice), `shutting_down` (503: the server is
  stopping), all 503s with `Retry-After`, and `unauthorized` (401).
* No `NaN` or `Infinity` is ever sent: undefined numbers are `null`.
* When the server has API keys configured, `/v1` needs an `X-API-Key` header (or
  `Authorization: Bearer <key>`).
"""

api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                              description="Needed only when the server has API keys set.")


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the service.

    Parameters
    ----------
    settings : Settings, optional
        Default: read from the environment (``PLANNER_*``).

    Returns
    -------
    FastAPI
        ``app.state`` holds ``settings``, ``metrics`` and (while the lifespan runs) ``pool``.
    """
    settings = settings or Settings()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        pool = WorkerPool(settings.workers, settings.queue_size,
                          start_method=settings.start_method, warmup=settings.warmup,
                          start_timeout=settings.worker_start_timeout,
                          log_level=settings.log_level, nice=settings.worker_nice,
                          native_cache=settings.native_cache_dir,
                          on_restart=lambda reason: metrics.restarts.labels(reason).inc(),
                          queue_timeout=settings.queue_timeout,
                          ping_interval=settings.worker_ping_interval,
                          ping_timeout=settings.worker_ping_timeout)
        app.state.pool = pool
        metrics.bind_pool(pool.stats)
        # the OpenAPI document (about 1 s to build on a busy machine) while the workers warm
        # up, not when the first reader opens /docs
        await asyncio.gather(pool.start(), asyncio.to_thread(app.openapi))
        try:
            yield
        finally:
            await pool.close()

    app = FastAPI(title=TITLE, version=__version__, description=DESCRIPTION,
                  lifespan=lifespan, docs_url=None, redoc_url=None,
                  default_response_class=SafeJSONResponse,
                  generate_unique_id_function=lambda route: route.name)
    app.state.settings = settings
    app.state.metrics = metrics

    schemas = build_schemas(settings.limits)
    # the key is required (and documented in the OpenAPI document) only when keys are set
    guard = [Depends(_api_key_guard(settings.api_keys))] if settings.api_keys else []
    # the paths of the OpenAPI document, known without building it (that takes 0.2 s)
    known = {"/docs", "/redoc", "/openapi.json"}
    for router in (plans.build_router(schemas), replans.build_router(),
                   sweeps.build_router(schemas),
                   transforms.build_router(schemas), robustness.build_router(schemas),
                   robots.build_router(settings.max_joints), figures.build_router(schemas)):
        app.include_router(router, prefix="/v1", dependencies=guard)
        known |= _schema_paths(router, "/v1")
    for router in (health.build_router(), explorer.build_router()):
        app.include_router(router)
        known |= _schema_paths(router, "", hidden=True)
    _add_docs(app)
    _add_error_handlers(app)
    app.openapi = lambda: _openapi(app)  # type: ignore[method-assign]

    app.add_middleware(RequestContextMiddleware, max_body_bytes=settings.max_body_bytes,
                       metrics=metrics, known_paths=lambda: known, api_keys=settings.api_keys,
                       fast_routes=[FastPlanRoute(app.state, schemas),
                                    replans.FastReplanRoute(app.state)],
                       body_timeout=settings.body_timeout, send_timeout=settings.send_timeout)
    # gzip for clients that accept it (a plan at the default 201 samples: 62 KB of JSON), outside
    # the request middleware so that its own answers (the fast path, 401, 413) are compressed
    # too; its answers pass through in the same chunks, each still under send_timeout. Level 1:
    # the event loop compresses, and JSON of floats shrinks almost as much as at level 9.
    # Requests that do not accept gzip skip the middleware (service.compression)
    app.add_middleware(GZipWhenAccepted, minimum_size=GZIP_MINIMUM_BYTES, compresslevel=1,
                       uncompressed=UNCOMPRESSED_PATHS)
    if settings.cors_origins:  # outermost: its headers are on every answer, a 401 or 413 too
        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST"],
                           allow_headers=["Content-Type", "X-API-Key", "Authorization",
                                          "X-Request-ID"],
                           expose_headers=["X-Request-ID", "Retry-After"])
    return app


def _schema_paths(router: Any, prefix: str, hidden: bool = False) -> set[str]:
    """The paths ``router`` adds to the OpenAPI document under ``prefix`` (with ``hidden``,
    also those it leaves out of it: the explorer's ``/``). Templates (``{kind}``) stay so:
    the metrics label a request by its template."""
    return {prefix + r.path for r in router.routes
            if isinstance(r, APIRoute) and (r.include_in_schema or hidden)}


# ---------------------------------------------------------------------- auth
def _api_key_guard(keys: list[str]) -> Any:
    """A dependency accepting any of ``keys`` (everything when ``keys`` is empty).

    The request middleware already refuses ``/v1`` requests without a valid key, before their
    body is read (:mod:`service.auth`); this dependency documents the scheme in the OpenAPI
    document and checks again.
    """
    encoded = encode_keys(keys)

    async def guard(request: Request, api_key: str | None = Depends(api_key_header)) -> None:
        if not authorized(request.headers, encoded):
            raise ServiceProblem("unauthorized", UNAUTHORIZED_DETAIL, headers=dict(CHALLENGE))

    return guard


# ---------------------------------------------------------------------- errors
def _add_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ServiceProblem)
    async def on_problem(request: Request, exc: ServiceProblem) -> Response:
        return exc.response(request_id(request))

    @app.exception_handler(RequestValidationError)
    async def on_validation(request: Request, exc: RequestValidationError) -> Response:
        names = _body_field_names(request.scope.get("route"))
        errors = [_validation_error(e, names) for e in exc.errors()]
        first = errors[0] if errors else {"field": None, "message": "invalid request"}
        detail = "; ".join(e["message"] if not e["field"] or e["message"].startswith(e["field"])
                           else f"{e['field']}: {e['message']}" for e in errors[:5])
        if len(errors) > 5:
            detail += f"; and {len(errors) - 5} more"
        # a body that is not JSON at all is a 400, like one that is not UTF-8 (FastAPI's own)
        status = 400 if any(e["type"] == "json_invalid" for e in errors) else None
        if request.method == "POST" and not is_json(request.headers.get("content-type")) and \
                await request.body():
            # FastAPI does not parse such a body as JSON; its errors would speak of a dictionary
            status, first = 415, {"field": None}
            detail = (f"the body was sent with Content-Type: "
                      f"{request.headers.get('content-type') or '(none)'}; send it as JSON "
                      f"with the header Content-Type: application/json")
            errors = [{"field": None, "message": detail, "type": "content_type"}]
        return ServiceProblem("invalid_request", detail, field=first["field"], status=status,
                              diagnostics={"errors": errors[:50]}).response(request_id(request))

    @app.exception_handler(StarletteHTTPException)
    async def on_http(request: Request, exc: StarletteHTTPException) -> Response:
        code = {401: "unauthorized", 404: "not_found", 405: "method_not_allowed",
                503: "overloaded", 504: "timeout"}.get(exc.status_code, "invalid_request")
        detail = exc.detail if isinstance(exc.detail, str) else "invalid request"
        return ServiceProblem(code, detail, status=exc.status_code,
                              headers=dict(exc.headers or {})).response(request_id(request))


def _body_field_names(route: Any) -> frozenset[str]:
    """Every field name of the route's body model, nested models' included (for "did you
    mean")."""
    body_field = getattr(route, "body_field", None)
    model = getattr(getattr(body_field, "field_info", None), "annotation", None)
    return _model_field_names(model) if model is not None else frozenset()


@functools.lru_cache(maxsize=64)
def _model_field_names(annotation: Any) -> frozenset[str]:
    names: set[str] = set()
    pending, seen = [annotation], set()
    while pending:
        a = pending.pop()
        if id(a) in seen:
            continue
        seen.add(id(a))
        if isinstance(a, type) and issubclass(a, BaseModel):
            for name, info in a.model_fields.items():
                names.add(info.alias or name)
                pending.append(info.annotation)
        else:
            pending.extend(typing.get_args(a))
    return frozenset(names)


def _validation_error(err: dict[str, Any], names: frozenset[str] = frozenset()
                      ) -> dict[str, Any]:
    """One pydantic error as ``field``/``message``/``type`` (never the offending input); an
    unknown field gets the closest known name (``names``) as "did you mean"."""
    loc = [p for p in err.get("loc", ()) if p not in ("body", "query", "path", "header")]
    field = ""
    for part in loc:
        if isinstance(part, int):
            field += f"[{part}]"
        else:
            field += ("." if field else "") + str(part)
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    ctx = err.get("ctx") or {}
    named = ctx.get("field")
    if isinstance(named, str):  # a check of several values names the element at fault
        last = loc[-1] if loc else None
        if isinstance(last, str) and named.split("[")[0] == last:
            field = field[:-len(last)] + named
        else:
            field = (field + "." if field else "") + named
    if err.get("type") == "extra_forbidden":
        msg = "unknown field"
        given = loc[-1] if loc else None
        close = difflib.get_close_matches(str(given), sorted(names), n=1, cutoff=0.6) \
            if isinstance(given, str) else []
        if close:
            msg += f"; did you mean {close[0]!r}?"
    if err.get("type") == "json_invalid":  # the location is a character position, not a field
        reason = str((err.get("ctx") or {}).get("error", "malformed"))
        where = f" at character {loc[0]}" if loc and isinstance(loc[0], int) else ""
        return {"field": None, "message": f"the body is not valid JSON ({reason}{where})",
                "type": "json_invalid"}
    return {"field": field or None, "message": msg, "type": err.get("type")}


# ---------------------------------------------------------------------- docs and OpenAPI
def _add_docs(app: FastAPI) -> None:
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title=f"{TITLE} - Swagger UI",
                                   swagger_js_url="/static/swagger-ui/swagger-ui-bundle.js",
                                   swagger_css_url="/static/swagger-ui/swagger-ui.css",
                                   swagger_favicon_url="/static/favicon.png",
                                   swagger_ui_parameters={"validatorUrl": None})

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url="/openapi.json", title=f"{TITLE} - ReDoc",
                              redoc_js_url="/static/redoc/redoc.standalone.js",
                              redoc_favicon_url="/static/favicon.png", with_google_fonts=False)


def _openapi(app: FastAPI) -> dict[str, Any]:
    """The OpenAPI document, with error answers typed ``application/problem+json``."""
    if app.openapi_schema:
        return app.openapi_schema
    doc = get_openapi(title=app.title, version=app.version, description=app.description,
                      routes=app.routes)
    for operations in doc.get("paths", {}).values():
        for op in operations.values():
            for status, response in op.get("responses", {}).items():
                content = response.get("content", {})
                if status.isdigit() and int(status) >= 400 and "application/json" in content:
                    schema = content.pop("application/json")
                    ref = schema.get("schema", {}).get("$ref", "")
                    if ref.endswith("/Problem"):
                        content[PROBLEM_MEDIA_TYPE] = schema
                    else:
                        content["application/json"] = schema
    app.openapi_schema = doc
    return doc


app = create_app()
