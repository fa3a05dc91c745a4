"""``POST /v1/plans`` without FastAPI's routing and dependency machinery, for valid requests.

FastAPI's way to an endpoint (exception and exit-stack middlewares, route matching, the request
object, body parsing, dependency solving, response serialisation) costs more of the event
loop's CPU than everything else a plan request needs outside its worker, and the plan route is
the one that must serve hundreds of requests per second. :class:`FastPlanRoute` answers it
directly from the request middleware (:mod:`service.middleware`), after the API key and body
size checks, when the request is a well-formed JSON plan request:

* the ``Content-Type`` is ``application/json`` (or ``application/*+json``), the body parses
  and validates against the same pydantic model as the route (``model_validate_json``: the
  model's own checks, so every bound is the same);
* it then runs what the route runs, :func:`service.dispatch.answer_plan` (``to_library``, the
  library's validation, the job on a worker), and answers the same 200 body or the same problem
  document.

Anything else (no or another content type, malformed JSON, a schema violation) is *not*
answered here: the request goes on to the FastAPI route with its body unchanged, so every error
answer is produced, byte for byte, by the one code path that documents it. The OpenAPI
document is the route's.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError
from starlette.types import Send

from .dispatch import answer_plan
from .problems import SafeJSONResponse, ServiceProblem
from .schemas import Schemas

_JSON = "application/json"


def is_json(content_type: str | None) -> bool:
    """Whether a ``Content-Type`` value is JSON as FastAPI reads it (``application/json`` or
    ``application/<something>+json``, parameters ignored)."""
    if not content_type:
        return False
    media = content_type.split(";", 1)[0].strip().lower()
    return media == _JSON or (media.startswith("application/") and media.endswith("+json"))


class FastJSONRoute:
    """A route answered from the request middleware: a well-formed JSON body of the route's
    model is answered here; anything else returns False, unanswered, for the FastAPI route
    (which produces every error answer).

    Subclasses set ``path`` and ``model`` and implement :meth:`answer`.

    Parameters
    ----------
    state : starlette State
        The app's state (``pool``, ``settings``, ``metrics`` once the lifespan runs).
    """

    method = "POST"
    path: str
    model: type[BaseModel]

    def __init__(self, state: Any) -> None:
        self.state = state

    async def answer(self, request: Any, request_id: str) -> Any:
        """The JSON-safe answer of a validated request (raises :class:`ServiceProblem`)."""
        raise NotImplementedError

    async def __call__(self, body: bytes, content_type: str | None, send: Send,
                       request_id: str) -> bool:
        """Answer the request and return True, or return False without side effects (the
        request is then for the FastAPI route)."""
        if not body or not is_json(content_type):
            return False
        try:
            # pydantic parses and validates in one pass (half the CPU of json.loads followed
            # by model_validate on a plan request: 14 against 29 us); what it refuses, the
            # route answers
            request = self.model.model_validate_json(body)
        except (ValueError, ValidationError, RecursionError):
            return False  # the route answers it (400 or 422, as documented)
        try:
            response = SafeJSONResponse(await self.answer(request, request_id))
        except ServiceProblem as problem:
            response = problem.response(request_id)
        await send({"type": "http.response.start", "status": response.status_code,
                    "headers": response.raw_headers})
        await send({"type": "http.response.body", "body": response.body})
        return True


class FastPlanRoute(FastJSONRoute):
    """The fast path of ``POST /v1/plans`` (see the module docstring).

    Parameters
    ----------
    state : starlette State
        The app's state.
    schemas : Schemas
        The app's request models.
    """

    path = "/v1/plans"

    def __init__(self, state: Any, schemas: Schemas) -> None:
        super().__init__(state)
        self.model = schemas.PlanRequest

    async def answer(self, request: Any, request_id: str) -> Any:
        return await answer_plan(self.state, request, request_id)
