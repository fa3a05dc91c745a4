"""``POST /v1/figures/{kind}``: the service's figures as PNG or SVG.

One route per kind, each taking the JSON request of the route whose answer it draws:

=============================  =====================  ==========================================
route                          body                   figure (:mod:`service.figures`)
=============================  =====================  ==========================================
``/v1/figures/joint_angles``   plan request           th1..thn and phi against time (deg)
``/v1/figures/chained_state``  plan request           z2..z_{n+1} with the singular regions
``/v1/figures/sweep``          sweep request          d_a, t_p, ||J_R||_F against dphi
``/v1/figures/robustness``     robustness request     nominal path against perturbed runs
``/v1/figures/pareto``         plan request           reversals against deviation of the
                                                      trade-off (``pareto`` set to true)
=============================  =====================  ==========================================

and two that draw an answer the client already has, without computing it again (the plan
explorer uses them: one plan per click):

=========================================  ===========================  ========================
route                                      body                         figure
=========================================  ===========================  ========================
``/v1/figures/from_plan/{kind}``           a plan answer                joint_angles,
                                                                        chained_state or
                                                                        pareto
``/v1/figures/from_sweep``                 ``{"sweep": answer,          sweep, the planned dphi
                                           "planned_phi_change"}``      dashed
=========================================  ===========================  ========================

The worker plans (or sweeps, or replays) exactly as the JSON route would, then renders the
figure with matplotlib in the same process (the ``figure`` job of :mod:`service.jobs`), so the
event loop never draws. The format is the ``format`` query parameter, else the ``Accept``
header (``image/svg+xml`` or ``image/png``), else PNG. Failures are the same problem documents
as the JSON routes (``infeasible`` 422, ``timeout`` 504, ...).
"""

import math
from typing import Any, Literal, Optional

from fastapi import APIRouter, Query, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.responses import Response

from ..dispatch import run_job
from ..formats import FORMATS
from ..problems import ServiceProblem
from ..schemas import Schemas, SweepFigureRequest
from ..responses import PlanResponse
from ..schema_fields import MIN_JOINTS
from . import ERROR_RESPONSES
from .common import checked_plan, checked_robustness, checked_sweep

#: Seconds a figure job may take beyond the request's ``time_limit`` (the drawing itself).
RENDER_SECONDS = 15.0

FigureFormat = Literal["png", "svg"]

IMAGE_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"description": "The figure: `image/png` (900 px wide) or `image/svg+xml` (text kept "
                         "as `<text>`), chosen by `format`, else by `Accept`, else PNG.",
          "content": {"image/png": {"schema": {"type": "string", "format": "binary"}},
                      "image/svg+xml": {"schema": {"type": "string"}}},
          "headers": {"Content-Disposition": {"description": "`inline; filename=\"<kind>."
                                                             "<format>\"`",
                                              "schema": {"type": "string"}}}},
    **ERROR_RESPONSES,
}

FORMAT_QUERY = Query(None, description="Image format. Omitted: from the `Accept` header "
                                       "(`image/svg+xml` or `image/png`), else png.")

COMMON = (" The job's `time_limit` bounds the computation; drawing may take up to "
          f"{RENDER_SECONDS:g} s more. Angles are drawn in degrees (labelled).")


def strict_answer(model: type[BaseModel], raw: bytes) -> None:
    """Check an answer sent back to be drawn as strictly as the service's own requests are:
    numbers as JSON numbers (not strings), all finite (no ``NaN``, ``Infinity`` or ``1e309``,
    which JSON parsers read as infinite). The answer models are the service's response models,
    lax as such; FastAPI has already parsed the body leniently. A 422 names the field."""
    try:
        checked = model.model_validate_json(raw, strict=True)
    except ValidationError as exc:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])}
                                      for e in exc.errors(include_input=False)]) from None
    where = _non_finite(checked.model_dump())
    if where is not None:
        raise RequestValidationError([{
            "loc": ("body", *where), "type": "finite_number",
            "msg": "Input should be a finite number (NaN, Infinity and numbers too large for a "
                   "double, like 1e309, are not)"}])


def _non_finite(value: Any, path: tuple[Any, ...] = ()) -> tuple[Any, ...] | None:
    """The location of the first non-finite float in ``value`` (None: there is none)."""
    if isinstance(value, float):
        return None if math.isfinite(value) else path
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, (list, tuple)):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _non_finite(item, (*path, key))
        if found is not None:
            return found
    return None


def negotiate(fmt: Optional[str], accept: Optional[str]) -> str:
    """The image format: ``fmt`` when given, else the preferred of png/svg in ``accept``.

    ``Accept`` entries are weighed by their ``q``; ``image/*`` and ``*/*`` count for PNG; a
    header naming neither image type (``application/json`` from a generic client) gives PNG.
    """
    if fmt:
        return fmt
    best, best_q = "png", 0.0
    for part in (accept or "").split(","):
        fields = [f.strip() for f in part.split(";")]
        media = fields[0].lower()
        q = 1.0
        for f in fields[1:]:
            if f.lower().startswith("q="):
                try:
                    q = float(f[2:])
                except ValueError:
                    q = 0.0
        choice = {"image/svg+xml": "svg", "image/png": "png", "image/*": "png",
                  "*/*": "png"}.get(media)
        # an exact type beats a wildcard of the same weight
        if choice and (q > best_q or (q == best_q and media in ("image/svg+xml", "image/png"))):
            best, best_q = choice, q
    return best


async def _image(request: Request, job: str, kind: str, fmt: Optional[str], key: str,
                 value: Any, limit: float) -> Response:
    """Run figure job ``job`` (``figure`` or ``figure_of_answer``) with ``{key: value}`` for
    figure ``kind`` in the negotiated format and answer with the image."""
    chosen = negotiate(fmt, request.headers.get("accept"))
    image = await run_job(request, job, {"figure": kind, "format": chosen, key: value}, limit,
                          method=kind)
    return Response(image, media_type=FORMATS[chosen],
                    headers={"Content-Disposition": f'inline; filename="{kind}.{chosen}"',
                             "Vary": "Accept"})


async def _figure(request: Request, kind: str, job_payload: dict[str, Any], time_limit: float,
                  fmt: Optional[str]) -> Response:
    """Compute as the JSON route does (``job_payload``: its job's payload, checked), then draw."""
    return await _image(request, "figure", kind, fmt, "request", job_payload,
                        time_limit + RENDER_SECONDS)


async def _drawn(request: Request, kind: str, data: dict[str, Any],
                 fmt: Optional[str]) -> Response:
    """Draw ``data`` (an answer the client sent) as figure ``kind`` in a worker."""
    return await _image(request, "figure_of_answer", kind, fmt, "data", data, RENDER_SECONDS)


def build_router(S: Schemas) -> APIRouter:
    """The figure routes for the request models ``S``."""
    router = APIRouter(tags=["figures"])

    def plan_figure(kind: str, summary: str, description: str, **extra: Any) -> None:
        """Add ``POST /v1/figures/{kind}``: plan the request like ``POST /v1/plans`` (its
        payload with the fields ``extra``), then draw figure ``kind`` of the answer."""
        async def handler(body: S.PlanRequest, request: Request,  # type: ignore[name-defined]
                          format: Optional[FigureFormat] = FORMAT_QUERY) -> Response:
            return await _figure(request, kind, checked_plan(body, **extra), body.time_limit,
                                 format)

        router.post(f"/figures/{kind}", response_class=Response, responses=IMAGE_RESPONSES,
                    name=f"figure_{kind}", summary=summary,
                    description=description + COMMON)(handler)

    plan_figure("joint_angles", "Figure: joint angles and phi against time",
                "Plans the request like `POST /v1/plans`, then draws th1..thn (top) and phi "
                "(bottom) against time in degrees, with the straight start-to-goal references "
                "that d_a measures against.")
    plan_figure("chained_state", "Figure: chained-form state against time",
                "Plans the request like `POST /v1/plans`, then draws z2..z_{n+1} against time "
                "with the regions where the inverse transform does not exist shaded and the "
                "request's constraint points marked.")
    plan_figure("pareto", "Figure: the trade-off between reversals and deviation",
                "Plans the request like `POST /v1/plans` with `pareto: true`, then draws each "
                "non-dominated plan's deviation (deg) against its actuator reversals, the main "
                "plan starred.", pareto=True)

    @router.post("/figures/sweep", response_class=Response, responses=IMAGE_RESPONSES,
                 summary="Figure: indicators against dphi",
                 description="Sweeps like `POST /v1/sweeps`, then draws d_a (deg), t_p and "
                             "||J_R(T)||_F against dphi (deg) with the singularity-free dphi "
                             "intervals shaded and the grid's best member starred." + COMMON)
    async def figure_sweep(body: S.SweepRequest, request: Request,  # type: ignore[name-defined]
                           format: Optional[FigureFormat] = FORMAT_QUERY) -> Response:
        return await _figure(request, "sweep", checked_sweep(body), body.time_limit, format)

    @router.post("/figures/robustness", response_class=Response, responses=IMAGE_RESPONSES,
                 summary="Figure: nominal path against open-loop runs from perturbed starts",
                 description="Plans and replays like `POST /v1/robustness`, then draws each "
                             "joint's nominal path against the perturbed runs (singular runs "
                             "red, stopped where they met the singularity). `include_paths` is "
                             "ignored: the runs' paths are what the figure draws, so runs x "
                             "plan.samples is bounded as with `include_paths`." + COMMON)
    async def figure_robustness(body: S.RobustnessRequest, request: Request,  # type: ignore[name-defined]
                                format: Optional[FigureFormat] = FORMAT_QUERY) -> Response:
        payload = checked_robustness(body)
        runs = len(body.starts) if body.starts is not None else body.random.count
        most = request.app.state.settings.max_total_samples
        if runs * body.plan.samples > most:
            raise ServiceProblem("invalid_request", f"runs x plan.samples = "
                                 f"{runs * body.plan.samples} exceeds {most} path rows (the "
                                 "figure draws every run's path)", field="plan.samples",
                                 diagnostics={"max_total_samples": most})
        return await _figure(request, "robustness", payload, body.time_limit, format)

    @router.post("/figures/from_plan/{kind}", response_class=Response,
                 responses=IMAGE_RESPONSES, summary="Figure of a plan answer you already have",
                 description="Draws the answer of `POST /v1/plans` (sent back unchanged) "
                             "without planning again: `joint_angles` (th1..thn and phi against "
                             "time, deg), `chained_state` (z2..z_{n+1} with the singular "
                             "regions shaded) or `pareto` (a `pareto: true` answer's members, "
                             "deviation against reversals). Angles are drawn in degrees "
                             "(labelled).")
    async def figure_from_plan(kind: Literal["joint_angles", "chained_state", "pareto"],
                               body: PlanResponse, request: Request,
                               format: Optional[FigureFormat] = FORMAT_QUERY) -> Response:
        strict_answer(PlanResponse, await request.body())
        settings = request.app.state.settings
        # bounds of the drawing's cost: the answers the service itself gives stay within them
        n, rows = body.robot.n, len(body.path.t)
        if not MIN_JOINTS <= n <= settings.max_joints:
            raise ServiceProblem("invalid_request", f"robot.n = {n} must lie in [{MIN_JOINTS}, "
                                 f"{settings.max_joints}]", field="robot.n")
        if not 2 <= rows <= settings.max_samples:
            raise ServiceProblem("invalid_request", f"path.t has {rows} samples; a plan answer "
                                 f"has 2..{settings.max_samples}", field="path.t")
        return await _drawn(request, kind, body.model_dump(), format)

    @router.post("/figures/from_sweep", response_class=Response, responses=IMAGE_RESPONSES,
                 summary="Figure of a sweep answer you already have",
                 description="Draws the answer of `POST /v1/sweeps` (sent back unchanged) "
                             "without sweeping again: d_a (deg), t_p and ||J_R(T)||_F against "
                             "dphi (deg), the singularity-free intervals shaded, the grid's "
                             "best member starred and `planned_phi_change` (a plan's dphi) "
                             "dashed.")
    async def figure_from_sweep(body: SweepFigureRequest, request: Request,
                                format: Optional[FigureFormat] = FORMAT_QUERY) -> Response:
        strict_answer(SweepFigureRequest, await request.body())
        points = len(body.sweep.phi_change)
        most = request.app.state.settings.max_sweep_points
        if not 2 <= points <= most:
            raise ServiceProblem("invalid_request", f"sweep.phi_change has {points} points; a "
                                 f"sweep answer has 2..{most}", field="sweep.phi_change")
        return await _drawn(request, "sweep", body.model_dump(), format)

    return router

