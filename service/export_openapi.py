"""``python -m service.export_openapi [PATH]``: write the service's OpenAPI document.

The document is built from the default settings (the environment is ignored), so it is the same
on every machine; ``tests/service`` fails when the committed ``openapi/openapi.json`` differs.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

DEFAULT_PATH = Path(__file__).resolve().parent.parent / "openapi" / "openapi.json"


def openapi_document() -> dict[str, Any]:
    """The OpenAPI document of an app built with the default settings."""
    from .main import create_app
    from .settings import default_settings

    return create_app(default_settings()).openapi()


def render(doc: dict[str, Any]) -> str:
    """The committed text form: indented, sorted keys, trailing newline."""
    return json.dumps(doc, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Write the document to ``argv[0]`` (default ``openapi/openapi.json``)."""
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0]) if args else DEFAULT_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(render(openapi_document()), encoding="utf-8")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
