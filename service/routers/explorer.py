"""``GET /``: the plan explorer, a single page over the service's own API.

The page (``service/static/explorer/``: ``index.html``, ``explorer.js``, ``explorer.css``; no
CDN, no build step) is open even when API keys are configured: it only calls the ``/v1`` API
from the browser, with the key the user types sent as ``X-API-Key``. Every URL in it is
relative, so it also works behind a reverse proxy that mounts the service under a prefix.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

PAGE = Path(__file__).resolve().parent.parent / "static" / "explorer" / "index.html"

#: The page loads only its own script, style sheet and images (figures arrive as blobs).
SECURITY_HEADERS = {
    "Content-Security-Policy": "default-src 'none'; script-src 'self'; style-src 'self'; "
                               "img-src 'self' blob: data:; connect-src 'self'; "
                               "base-uri 'none'; form-action 'none'; frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}


def build_router() -> APIRouter:
    """The explorer page route (not part of the OpenAPI document)."""
    router = APIRouter()
    html = PAGE.read_text(encoding="utf-8")

    @router.get("/", include_in_schema=False, response_class=HTMLResponse)
    async def explorer() -> HTMLResponse:
        return HTMLResponse(html, headers=SECURITY_HEADERS)

    return router
