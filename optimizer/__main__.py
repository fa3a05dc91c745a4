"""Command line: plan without a server.

``python -m optimizer plan request.json`` prints the same JSON as ``POST /v1/plans`` (a plan, or
a problem object with a non-zero exit status). ``-`` reads the request from standard input.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence

from .errors import PlannerError
from .planner.plan import plan
from .problem import PlanRequest
from .results import json_safe

#: Exit statuses: 0 success, 1 planning failure (infeasible, timeout, numerical), 2 bad input.
EXIT_INVALID = 2
EXIT_FAILED = 1


def problem(exc: PlannerError) -> dict[str, Any]:
    """The problem+json body the service returns for a planner error."""
    return json_safe({"type": f"about:blank#{exc.code}", "title": exc.code.replace("_", " "),
                      "code": exc.code, "detail": exc.message, "field": exc.field,
                      "diagnostics": exc.diagnostics})


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="chained-planner",
                                     description="Singularity-free motion planning (radians, seconds).")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("plan", help="plan one request (JSON as for POST /v1/plans)")
    p.add_argument("request", help="path of a JSON request, or - for standard input")
    p.add_argument("--indent", type=int, default=None, help="pretty-print with this indent")
    args = parser.parse_args(argv)
    try:
        text = sys.stdin.read() if args.request == "-" else open(args.request).read()
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("the request must be a JSON object")
    except (OSError, ValueError) as exc:
        print(json.dumps({"code": "invalid_request", "detail": str(exc)}), file=sys.stdout)
        return EXIT_INVALID
    try:
        out = plan(PlanRequest.from_dict(data)).to_dict()
        status = 0
    except PlannerError as exc:
        out = problem(exc)
        status = EXIT_INVALID if exc.code == "invalid_request" else EXIT_FAILED
    except (TypeError, KeyError, ValueError) as exc:
        out = {"code": "invalid_request", "detail": f"malformed request: {exc}"}
        status = EXIT_INVALID
    print(json.dumps(out, indent=args.indent, allow_nan=False))
    return status


if __name__ == "__main__":
    sys.exit(main())
