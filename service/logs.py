"""Structured JSON logs: one JSON object per line on stderr.

Every record carries ``ts``, ``level``, ``logger`` and ``message``, plus whatever the call put in
``extra`` (the access log adds ``request_id``, ``method``, ``path``, ``route``, ``status`` and
``duration_ms``). Request bodies are never logged.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any

try:
    import orjson
except ImportError:  # pragma: no cover - a declared dependency
    orjson = None  # type: ignore[assignment]

#: LogRecord attributes that are not user ``extra`` fields.
_STANDARD = frozenset(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime"}


class JSONFormatter(logging.Formatter):
    """Format a record as one line of JSON."""

    _second = -1
    _stamp = ""

    def format(self, record: logging.LogRecord) -> str:
        second = int(record.created)
        if second != self._second:  # one strftime per second, not per line
            self._stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(second))
            self._second = second
        out: dict[str, Any] = {
            "ts": f"{self._stamp}.{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key, value in record.__dict__.items():
            if key not in _STANDARD and key[:1] != "_" and key != "color_message":
                out[key] = value  # (uvicorn's color_message repeats message with ANSI codes)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        if orjson is not None:
            try:
                return orjson.dumps(out, default=str).decode("utf-8")
            except (TypeError, ValueError):
                pass
        return json.dumps(out, default=str)


def configure_logging(level: str = "info") -> None:
    """Send every logger (uvicorn's included) through one JSON handler on stderr."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JSONFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        lg = logging.getLogger(name)
        lg.handlers[:] = []
        lg.propagate = True
    logging.getLogger("uvicorn.access").disabled = True  # the service logs its own access lines
