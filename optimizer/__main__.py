"""Command line: plan without a server.

``python -m optimizer plan request.json`` prints the same JSON as ``POST /v1/plans`` (a plan, or
a problem object with a non-zero exit status). ``-`` reads the request from standard input.

``python -m optimizer study --random 1000 --out rows.csv`` (also ``chained-planner study``)
plans many goals for one or more mechanisms, locally or on a Dask cluster, one row per
(mechanism, goal) (:mod:`optimizer.studies`, docs/studies.md).
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
    _study_parser(sub)
    args = parser.parse_args(argv)
    if args.command == "study":
        return _study(args)
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


def _study_parser(sub: Any) -> None:
    s = sub.add_parser("study", help="plan many goals x mechanisms; one row each (CSV/Parquet)",
                       description="Plan every (mechanism, goal) pair and write one row each "
                                   "to --out (.csv, or .parquet with pyarrow). Rows already in "
                                   "--out are kept and not planned again.")
    s.add_argument("--out", required=True, help="output file: rows.csv or rows.parquet")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--goals", help="JSON or CSV file of start/goal pairs (rad)")
    src.add_argument("--random", type=int, metavar="N",
                     help="N reachable goals per mechanism, generated on its own model")
    s.add_argument("--seed", type=int, default=None, help="seed of --random (default fixed)")
    s.add_argument("--robot", help="JSON file: one mechanism {gains, exponents, name} or a list")
    s.add_argument("--n", type=int, default=3,
                   help="joints of the default robot when neither --robot nor --goals says")
    s.add_argument("--workers", type=int, default=None,
                   help="local worker processes (default: CPU count; 0: this process)")
    s.add_argument("--scheduler", help="Dask scheduler tcp://HOST:PORT (pip install "
                                       "'chained-planner[cluster]')")
    s.add_argument("--chunk", type=int, default=None, help="plans per task (default: automatic)")
    s.add_argument("--method", default="auto", help="planning method (default auto)")
    s.add_argument("--time-limit", type=float, default=10.0, help="seconds per plan")
    s.add_argument("--samples", type=int, default=101, help="samples of each path")


def _study(args: argparse.Namespace) -> int:
    """``study``: read the inputs, run :func:`optimizer.studies.run_study`, print a summary."""
    from . import study_io, studies
    from .model import Robot
    from .reachable import BASE_SEED

    try:
        if args.random is not None and args.random < 1:
            raise ValueError(f"--random {args.random}: give a number of goals >= 1")
        if args.chunk is not None and args.chunk < 1:
            raise ValueError(f"--chunk {args.chunk}: give a number of plans >= 1")
        if args.workers is not None and args.workers < 0:
            raise ValueError(f"--workers {args.workers}: give 0 (this process) or more")
        study_io.output_format(args.out)
        goals = study_io.read_goals(args.goals) if args.goals else None
        if args.robot:
            mechanisms = study_io.read_mechanisms(args.robot)
        else:
            sizes = sorted({len(g[1]) for g in goals}) if goals else [args.n]
            mechanisms = [(f"default-n{n}", Robot.default(n)) for n in sizes]
        options = studies.PlanOptions(method=args.method, time_limit=args.time_limit,
                                      samples=args.samples)
        PlanRequest(start=(0.5,) * mechanisms[0][1].n, goal=(0.5,) * mechanisms[0][1].n,
                    robot=mechanisms[0][1], method=args.method, time_limit=args.time_limit,
                    samples=args.samples)  # checks the options once, naming the field
        tasks = studies.make_tasks(mechanisms, goals, random=args.random,
                                   seed=BASE_SEED if args.seed is None else args.seed,
                                   options=options)
        result = studies.run_study(tasks, out=args.out, workers=args.workers,
                                   scheduler=args.scheduler, size=args.chunk)
    except ValueError as exc:  # InvalidRequestError is one
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_INVALID
    print(json.dumps({"out": str(args.out), "rows": len(result.rows), "planned": result.planned,
                      "skipped": result.skipped, "chunk": result.chunk_size,
                      "wall_seconds": round(result.wall_seconds, 3),
                      "mechanisms": studies.summary(result.rows)}, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
