"""JSON encoding that never emits ``NaN`` or ``Infinity``."""

from __future__ import annotations

import json
import math
from typing import Any

try:
    import orjson
except ImportError:  # pragma: no cover - a declared dependency; the standard library still works
    orjson = None  # type: ignore[assignment]

_OPTIONS = (orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_NON_STR_KEYS) if orjson is not None else 0


def finite_json(content: Any) -> bytes:
    """Serialise ``content`` as compact UTF-8 JSON with no ``NaN`` or ``Infinity`` token, ever.

    orjson (about ten times faster than :func:`json.dumps` on a plan) writes non-finite floats,
    numpy's included, as ``null`` itself, and numpy arrays and scalars natively. Content it
    refuses (integers beyond 64 bits, strings that are not valid UTF-8, unknown types) is
    converted by :func:`json_safe` (non-finite -> ``null``, numpy -> Python) and encoded again
    by the standard library (``allow_nan=False``: a non-finite number can never get through);
    an object JSON has no form for raises ``TypeError``.
    """
    if orjson is not None:
        try:
            return orjson.dumps(content, default=_default, option=_OPTIONS)
        except (TypeError, ValueError):  # orjson.JSONEncodeError is a TypeError
            pass
    safe = json_safe(content)
    try:
        text = json.dumps(safe, allow_nan=False, separators=(",", ":"), ensure_ascii=False)
        return text.encode("utf-8")
    except UnicodeEncodeError:  # lone surrogates: escaped
        return json.dumps(safe, allow_nan=False, separators=(",", ":"),
                          ensure_ascii=True).encode("ascii")


def _default(obj: Any) -> Any:
    """What orjson does not write itself: numpy arrays that are not C-contiguous (a column or
    a strided view) and numpy scalars of other types, as Python lists or numbers (orjson then
    writes their non-finite floats as ``null`` too)."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def json_safe(obj: Any) -> Any:
    """Recursively convert numpy types to Python and non-finite floats to None.

    The same rule as :func:`optimizer.results.json_safe` (kept here so that the server process
    does not import the solver modules).
    """
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "tolist") and hasattr(obj, "dtype"):  # numpy arrays and scalars
        return json_safe(obj.tolist())
    if isinstance(obj, bool):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        x = float(obj)
        return x if math.isfinite(x) else None
    return obj
