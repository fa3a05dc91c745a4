"""JSON encoding that never emits ``NaN`` or ``Infinity``."""

from __future__ import annotations

import json
from typing import Any

from optimizer.results import json_safe


def finite_json(content: Any) -> bytes:
    """Serialise ``content`` as compact UTF-8 JSON with no ``NaN`` or ``Infinity`` token, ever.

    ``json.dumps(..., allow_nan=False)`` refuses non-finite floats (and numpy values); content
    it refuses is converted by :func:`optimizer.results.json_safe` (non-finite -> ``null``,
    numpy -> Python) and encoded again. Content that is already JSON-safe (a plan's
    ``to_dict()``) is encoded once, without the conversion's cost.
    """
    try:
        text = json.dumps(content, allow_nan=False, separators=(",", ":"), ensure_ascii=False)
    except (ValueError, TypeError):
        text = json.dumps(json_safe(content), allow_nan=False, separators=(",", ":"),
                          ensure_ascii=False)
    return text.encode("utf-8")
