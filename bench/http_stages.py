"""What one ``POST /v1/plans`` costs, stage by stage, in CPU time (``time.process_time``).

``python -m bench.http_stages [--requests 200] [--rounds 5]``

The HTTP load benchmark (:mod:`bench.http_load`) gives CPU per request per process; this
splits it. Every stage runs here, in one process, on the load benchmark's own requests (a start
drawn anew for each, default samples, ``method: auto``), and is timed as the CPU time of a
batch of ``--requests`` calls divided by their number; the batches of all stages are
interleaved over ``--rounds`` rounds and the median round is reported (the machine is shared:
CPU time is less disturbed by the other jobs than wall time, but not immune to them).

Event loop (the server process):

* ``validate``: the fast route's ``model_validate_json`` of the body;
* ``to_library + library check``: the request model to the library's dict, and
  ``PlanRequest.from_dict`` of it (the check that answers a bad request without a worker);
* ``job pickle``: the job message as the pipe frames it;
* ``answer unpickle``: the worker's outcome (its JSON bytes inside) read from the pipe's frame;
* ``ASGI app``: the whole app called as uvicorn calls it (the request middleware, gzip, the fast
  route with all the above, metrics, the JSON access log), with a stub pool that unpickles a
  worker's real answer instead of running the job. What the event loop spends beyond it is
  uvicorn's (httptools, the transport) and asyncio's. The load benchmark's client does not
  accept gzip; ``ASGI app, the client accepts gzip`` is the same for a client that does (most
  HTTP libraries and browsers), the answer then compressed in the event loop.

Worker:

* ``job unpickle``, ``PlanRequest.from_dict``, ``plan``, ``to_dict``, column names,
  ``JSON (orjson)``, ``answer pickle``: :func:`service.jobs.run_job` step by step.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import pickle
import random
import statistics
import sys
import time
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.http_load import plan_body  # noqa: E402


def _bodies(count: int, seed: int = 0) -> list[bytes]:
    rng = random.Random(seed)
    return [json.dumps(plan_body("auto", rng)).encode() for _ in range(count)]


class _StubPool:
    """Stands for :class:`service.workers.WorkerPool` in the ASGI measurement: frames the job
    as the pipe does and answers with a worker's real outcome, unpickled from its frame."""

    def __init__(self, outcome_frame: bytes) -> None:
        from service.worker_protocol import frame
        self.frame = frame
        self.outcome = outcome_frame

    async def run(self, kind: str, payload: dict[str, Any], limit: float, *,
                  admit: bool = True, request_id: str | None = None) -> dict[str, Any]:
        self.frame((kind, payload, request_id))
        return pickle.loads(self.outcome)  # type: ignore[no-any-return]


def _asgi_caller(app: Any, gzip: bool = False) -> Callable[[bytes], None]:
    """One ``POST /v1/plans`` through ``app`` per call, on one event loop (with ``gzip``, from
    a client that accepts gzip)."""
    loop = asyncio.new_event_loop()

    def call(body: bytes) -> None:
        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
                 "method": "POST", "scheme": "http", "path": "/v1/plans", "raw_path": b"/v1/plans",
                 "query_string": b"", "root_path": "", "client": ("127.0.0.1", 1),
                 "server": ("127.0.0.1", 8000),
                 "headers": [(b"host", b"127.0.0.1:8000"), (b"content-type", b"application/json"),
                             (b"content-length", str(len(body)).encode()),
                             *([(b"accept-encoding", b"gzip")] if gzip else [])]}
        sent: list[dict[str, Any]] = []
        messages = [{"type": "http.request", "body": body, "more_body": False}]

        async def receive() -> dict[str, Any]:
            if messages:
                return messages.pop()
            await asyncio.sleep(3600)  # the client stays: the disconnect watch waits
            return {"type": "http.disconnect"}

        async def send(message: dict[str, Any]) -> None:
            sent.append(message)

        loop.run_until_complete(app(scope, receive, send))
        assert sent[0]["status"] == 200, sent

    return call


def measure(requests: int = 200, rounds: int = 5, log: Any = print) -> dict[str, Any]:
    """The stages' CPU time per request (us): median over ``rounds`` of batch means."""
    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest
    from service import jobs
    from service.dispatch import check_plan
    from service.encoding import finite_json
    from service.main import create_app
    from service.schemas import build_schemas
    from service.settings import default_settings
    from service.worker_protocol import frame

    logging.getLogger("service.access").setLevel(logging.INFO)
    from service.logs import configure_logging
    configure_logging("info")
    # the access log goes to stderr as in the server: sent to /dev/null here, its formatting kept
    for handler in logging.getLogger().handlers:
        if hasattr(handler, "setStream"):
            handler.setStream(open("/dev/null", "w"))  # noqa: SIM115

    # compiled NLP functions and quadrature, as the service's workers prepare them (without,
    # the plan ran on CasADi's virtual machine and numpy's quadrature: 12 ms instead of 6)
    from bench.inprocess import configure_native
    configure_native()
    from optimizer.model import Robot
    from optimizer.planner.shooting import prepare
    robot = Robot.default(3)
    prepare(robot.gains, robot.exponents, wait=True)
    settings = default_settings()
    model = build_schemas(settings.limits).PlanRequest
    bodies = _bodies(requests)
    jobs.warm_up()
    models: list[Any] = [model.model_validate_json(b) for b in bodies]
    payloads = [m.to_library() for m in models]
    job_frames = [b"".join(frame(("plan", p, "0" * 32))[1:]) for p in payloads]
    requests_lib = [PlanRequest.from_dict(p) for p in payloads]
    for req in requests_lib[:5]:
        plan(req)  # warm caches
    plans = [plan(r) for r in requests_lib]
    dicts = [p.to_dict(plain=False) for p in plans]
    named = [jobs.with_column_names(dict(d)) for d in dicts]
    encoded = [finite_json(d) for d in named]
    outcomes = [{"ok": True, "body": e, "seconds": 0.003} for e in encoded]
    outcome_frames = [b"".join(frame(o)[1:]) for o in outcomes]

    app = create_app(settings)
    app.state.pool = _StubPool(outcome_frames[0])
    call = _asgi_caller(app)
    call_gzip = _asgi_caller(app, gzip=True)
    for b in bodies[:10]:
        call(b)
        call_gzip(b)

    stages: list[tuple[str, str, Callable[[int], Any]]] = [
        ("event loop", "validate (model_validate_json)",
         lambda i: model.model_validate_json(bodies[i])),
        ("event loop", "to_library + library check (from_dict)",
         lambda i: check_plan(models[i].to_library())),
        ("event loop", "job pickle", lambda i: frame(("plan", payloads[i], "0" * 32))),
        ("event loop", "answer unpickle", lambda i: pickle.loads(outcome_frames[i])),
        ("event loop", "ASGI app (all of the above, middleware, access log)",
         lambda i: call(bodies[i])),
        ("event loop", "ASGI app, the client accepts gzip (level 1 in the event loop)",
         lambda i: call_gzip(bodies[i])),
        ("worker", "job unpickle", lambda i: pickle.loads(job_frames[i])),
        ("worker", "PlanRequest.from_dict", lambda i: PlanRequest.from_dict(payloads[i])),
        ("worker", "plan", lambda i: plan(requests_lib[i])),
        ("worker", "to_dict(plain=False)", lambda i: plans[i].to_dict(plain=False)),
        ("worker", "column names", lambda i: jobs.with_column_names(dict(dicts[i]))),
        ("worker", "JSON (finite_json)", lambda i: finite_json(named[i])),
        ("worker", "answer pickle", lambda i: frame(outcomes[i])),
        ("worker", "run_job (all the worker's steps)",
         lambda i: jobs.run_job("plan", payloads[i], None)),
    ]
    per: dict[str, list[float]] = {name: [] for _, name, _ in stages}
    for r in range(rounds):
        for _, name, fn in stages:
            t0 = time.process_time()
            for i in range(requests):
                fn(i)
            per[name].append((time.process_time() - t0) / requests * 1e6)
        log(f"  round {r + 1}/{rounds}: plan {per['plan'][-1]:.0f} us, ASGI "
            f"{per['ASGI app (all of the above, middleware, access log)'][-1]:.0f} us")
    sizes = {"body_bytes": statistics.median(len(b) for b in bodies),
             "answer_json_bytes": statistics.median(len(e) for e in encoded),
             "job_frame_bytes": statistics.median(len(f) for f in job_frames),
             "answer_frame_bytes": statistics.median(len(f) for f in outcome_frames)}
    rows = [{"process": proc, "stage": name, "cpu_us": statistics.median(per[name]),
             "cpu_us_rounds": per[name]} for proc, name, _ in stages]
    return {"requests": requests, "rounds": rounds, "sizes": sizes, "stages": rows}


def table(result: dict[str, Any]) -> str:
    """A markdown table of :func:`measure`'s result."""
    lines = ["| process | stage | CPU per request (us), median round [min-max] |",
             "|---|---|---|"]
    for row in result["stages"]:
        r = row["cpu_us_rounds"]
        lines.append(f"| {row['process']} | {row['stage']} | {row['cpu_us']:.0f} "
                     f"[{min(r):.0f}-{max(r):.0f}] |")
    s = result["sizes"]
    lines.append("")
    lines.append(f"Sizes (median): request body {s['body_bytes']:.0f} B, job frame "
                 f"{s['job_frame_bytes']:.0f} B, answer JSON {s['answer_json_bytes']:.0f} B, "
                 f"answer frame {s['answer_frame_bytes']:.0f} B.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.http_stages", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--requests", type=int, default=200, help="calls per batch")
    p.add_argument("--rounds", type=int, default=5, help="interleaved rounds")
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    args = p.parse_args(argv)
    out = measure(args.requests, args.rounds, log=lambda s: print(s, flush=True))
    print(table(out))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
