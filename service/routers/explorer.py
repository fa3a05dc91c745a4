"""``GET /``: the plan explorer, a single page over the service's own API.

The page (``service/static/explorer/``: ``index.html``, ``explorer.js``, ``explorer.css``; no
CDN, no build step) is open even when API keys are configured: it only calls the ``/v1`` API
from the browser, with the key the user types sent as ``X-API-Key``. Every URL in it is
relative, so it also works behind a reverse proxy that mounts the service under a prefix.
"""

from __future__ import annotations

import html as html_text
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

from optimizer.planner.registry import AUTO, METHODS
from optimizer.problem import DEFAULT_OBJECTIVE, OBJECTIVES

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


#: How the page names the objectives (one not listed here shows its own name).
OBJECTIVE_LABELS = {
    "reversals_then_deviation": "fewest actuator reversals, then deviation",
    "tp_then_da": "t_p, then d_a (the paper)",
    "tp_then_sensitivity": "t_p, then ||J_R||_F (the paper)",
    "weighted": "weighted",
}


def _option(value: str, label: str, selected: bool, title: str = "") -> str:
    attrs = f' value="{html_text.escape(value)}"' + (" selected" if selected else "")
    if title:
        attrs += f' title="{html_text.escape(title)}"'
    return f"          <option{attrs}>{html_text.escape(label)}</option>"


def method_options() -> str:
    """The method choices, from the planner's registry (``auto`` first, selected: the API's
    default), each with its one-line summary as a tooltip."""
    lines = [_option(AUTO, "auto (the best verified plan of the methods that can win)", True,
                     "runs the methods that can win for the request and returns the best "
                     "verified plan by the objective (docs/methods.md)")]
    lines += [_option(name, name.replace("_", " "), False, entry.summary)
              for name, entry in METHODS.items()]
    return "\n".join(lines)


def objective_options() -> str:
    """The objective choices, the API's default selected (the page plans what the API
    plans when nothing is changed)."""
    return "\n".join(_option(o, OBJECTIVE_LABELS.get(o, o) + (" (default)" if o == DEFAULT_OBJECTIVE
                                                               else ""), o == DEFAULT_OBJECTIVE)
                     for o in OBJECTIVES)


def page() -> str:
    """The explorer's HTML with its choices filled in."""
    text = PAGE.read_text(encoding="utf-8")
    for marker, options in (("METHOD_OPTIONS", method_options()),
                            ("OBJECTIVE_OPTIONS", objective_options())):
        text, count = _replace_marker(text, marker, options)
        assert count == 1, f"index.html lost its {marker} marker"
    return text


def _replace_marker(text: str, marker: str, options: str) -> tuple[str, int]:
    start = text.find(f"<!-- {marker}")
    if start < 0:
        return text, 0
    line_start = text.rfind("\n", 0, start) + 1
    end = text.index("-->", start) + 3
    return text[:line_start] + options + text[end:], 1


def build_router() -> APIRouter:
    """The explorer page route (not part of the OpenAPI document)."""
    router = APIRouter()
    html = page()

    @router.get("/", include_in_schema=False, response_class=HTMLResponse)
    async def explorer() -> HTMLResponse:
        return HTMLResponse(html, headers=SECURITY_HEADERS)

    return router
