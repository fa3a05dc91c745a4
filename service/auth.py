"""Optional API keys for ``/v1``.

When ``PLANNER_API_KEYS`` is set, every request whose path is ``/v1`` or under it (unknown
``/v1`` paths and wrong methods included, CORS preflights excepted) must carry one of the keys,
as ``X-API-Key: <key>`` or ``Authorization: Bearer <key>``; otherwise it is answered 401
``unauthorized`` by the request middleware, before its body is read. Health (``/healthz``,
``/readyz``), ``/metrics``, the docs (``/docs``, ``/redoc``, ``/openapi.json``, ``/static``) and
the explorer page (``/``) stay open.

A request with two different keys (two ``X-API-Key`` headers, or two ``Authorization``
headers) is refused: which one a component reads first must not decide.

Keys are compared with :func:`hmac.compare_digest` against *every* configured key (no early exit),
so the time taken does not tell which bytes or which key matched. Keys are never logged.
"""

from __future__ import annotations

import hmac
from typing import Mapping, Sequence

UNAUTHORIZED_DETAIL = ("a valid API key is required (X-API-Key header or Authorization: "
                       "Bearer)")
CHALLENGE = {"WWW-Authenticate": 'Bearer realm="planner", charset="UTF-8"'}


def protected(path: str, method: str) -> bool:
    """Whether a request needs a key (when keys are configured)."""
    return (path == "/v1" or path.startswith("/v1/")) and method.upper() != "OPTIONS"


#: The value the request middleware records for a header sent twice with different values.
CONFLICTING = "\x00conflicting"


def _single(headers: Mapping[str, str], name: str) -> str | None:
    """The one value of header ``name`` (``""`` when absent), None when it came twice with
    different values."""
    getlist = getattr(headers, "getlist", None)  # starlette's Headers keep every copy
    if getlist is not None:
        values = {v.strip() for v in getlist(name)}
        if len(values) > 1:
            return None
        return values.pop() if values else ""
    value = headers.get(name, "").strip()
    return None if value == CONFLICTING else value


def presented_key(headers: Mapping[str, str]) -> str:
    """The key a request presents (``X-API-Key``, else a Bearer token), or ``""`` (also when
    either header came twice with different values).

    ``headers`` are starlette's headers, or lower-cased names with latin-1 decoded values (as
    the middleware builds them, :data:`CONFLICTING` for a conflicting duplicate).
    """
    key = _single(headers, "x-api-key")
    authorization = _single(headers, "authorization")
    if key is None or authorization is None:
        return ""
    if key:
        return key
    scheme, _, token = authorization.partition(" ")
    return token.strip() if scheme.lower() == "bearer" else ""


def encode_keys(keys: Sequence[str]) -> list[bytes]:
    """Configured keys as the bytes a client sends (UTF-8)."""
    return [k.encode("utf-8") for k in keys if k]


def authorized(headers: Mapping[str, str], keys: Sequence[bytes]) -> bool:
    """True when no keys are configured or the request presents one of ``keys``."""
    if not keys:
        return True
    given = presented_key(headers)
    if not given:
        return False
    raw = given.encode("latin-1", errors="replace")  # the bytes on the wire
    match = False
    for key in keys:  # no short cut: every key is compared
        match |= hmac.compare_digest(raw, key)
    return match
