"""Schemathesis fuzzing of every operation of the committed OpenAPI document.

The cases come from ``openapi/openapi.json`` (the committed spec, built from the default
settings) and are sent over HTTP to ``python -m service`` on a loopback port, started with
settings that keep every request cheap: small ``max_samples``, ``max_time_limit`` and request
sizes, so a generated request is refused at once (422) or finishes within about a second.
(A live server rather than in-process ASGI: schemathesis' pytest plugin ends an ASGI app's
lifespan after every test, which would restart the worker pool once per operation.) Both
positive (schema-valid) and negative (schema-violating) cases are generated, with API keys
configured, and every built-in check is on, ``max_response_time`` included.

A case passes when

* the answer is not a server error: no 500, ever; a 503 only as ``overloaded`` with
  ``Retry-After`` and a 504 only as ``timeout`` (a generated ``time_limit`` of 1e-6 s is a
  legitimate request that times out; both are documented answers);
* status code, content type, headers and body conform to the document (all checks on);
* no JSON body holds ``NaN`` or ``Infinity``, and no body a stack trace or an internal path;
* the server's log shows no unhandled error and no unexpected library exception (both are
  answered as clean 422 ``numerical_failure`` problems, so only the log reveals them).

Cases per operation: ``FUZZ_EXAMPLES`` (default 40 in CI, i.e. a few hundred cases in total;
``FUZZ_EXAMPLES=5000`` is the long run documented in docs/security.md; ``FUZZ_SEED``
changes the seed) for the fuzzing phase, plus the explicit-example and coverage phases. The
last test checks the total and the server log.
"""

from __future__ import annotations

import json
import os
import sys
from collections import Counter
from typing import Any, Iterator

import hypothesis
import pytest
import requests
import schemathesis

from service.routers.figures import RENDER_SECONDS
from svc_support import LAG, ROOT, free_port, server_process

SPEC = ROOT / "openapi" / "openapi.json"
EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "40"))
SEED = int(os.environ.get("FUZZ_SEED", "20240517"))
MIN_TOTAL_CASES = 300

#: Settings of the fuzzed app: cheap requests (the spec keeps the default, larger bounds, so
#: schema-valid cases above these bounds are answered 422 by the app: an accepted answer).
#: API keys are set, so that the authentication checks are meaningful.
FUZZ_KEY = "fuzz-key-0123456789"
FUZZ_SETTINGS: dict[str, Any] = dict(
    api_keys=[FUZZ_KEY], workers=2, queue_size=1000, queue_timeout=3.0, max_samples=101,
    max_time_limit=1.0, default_time_limit=0.5, timeout_grace=0.3, max_batch_size=3,
    max_robustness_runs=4, max_sweep_points=41, max_transform_points=50, max_total_samples=303)
#: No answer may take longer than the service's own bounds allow: a wait for a worker (the
#: queue timeout: a worker killed at its time limit is replaced in the background, which took
#: many seconds on a loaded machine), then the largest time limit plus grace, plus the
#: drawing allowance of a figure (a worker's first figure imports matplotlib: 6 s at load 10
#: on 2 cores), plus LAG for the way back. A fixed 5 s failed on a loaded 2-core machine.
MAX_RESPONSE_SECONDS = (FUZZ_SETTINGS["queue_timeout"] + FUZZ_SETTINGS["max_time_limit"]
                        + FUZZ_SETTINGS["timeout_grace"] + RENDER_SECONDS + LAG)

PORT = free_port()
CONFIG = schemathesis.Config.from_dict({
    "base-url": f"http://127.0.0.1:{PORT}",
    "seed": SEED,
    # the transport's own timeout (10 s by default) stays above the response-time check, so a
    # slow answer fails that check, with its bound, and a hung one still fails
    "request-timeout": MAX_RESPONSE_SECONDS + 30.0,
    "auth": {"openapi": {"APIKeyHeader": {"api_key": FUZZ_KEY}}},
    # positive and negative cases; explicit examples, coverage and fuzzing phases (defaults)
    "generation": {"mode": "all", "max-examples": EXAMPLES},
    "checks": {
        "max_response_time": MAX_RESPONSE_SECONDS,
        # documented 5xx answers (checked precisely by `documented_server_errors` below)
        "not_a_server_error": {"expected-statuses": ["2xx", "3xx", "4xx", "503", "504"]},
        # a schema-valid request may still be refused: infeasible (422), a start outside
        # the region (422), the app's tighter limits (422), a too-short time limit (504)
        "positive_data_acceptance": {"expected-statuses": ["2xx", "401", "404", "413",
                                                          "422", "503", "504"]},
        # schemathesis' default list, and 413: a schema-violating body over 1 MB is refused
        # by size before it is parsed (found by a long run)
        "negative_data_rejection": {"expected-statuses": [
            "400", "401", "403", "404", "405", "406", "409", "413", "415", "422", "428",
            "429", "5xx"]},
    },
})

def _keyed_spec() -> dict[str, Any]:
    """The committed document (built without keys, so without the key scheme) as the server
    under test serves it: with API keys on, every ``/v1`` operation requires ``X-API-Key``."""
    doc = json.loads(SPEC.read_text(encoding="utf-8"))
    doc.setdefault("components", {})["securitySchemes"] = {
        "APIKeyHeader": {"type": "apiKey", "in": "header", "name": "X-API-Key"}}
    for path, item in doc["paths"].items():
        if path.startswith("/v1/"):
            for op in item.values():
                op["security"] = [{"APIKeyHeader": []}]
    return doc


schema = schemathesis.openapi.from_dict(_keyed_spec(), config=CONFIG)

CASES: Counter[str] = Counter()
STATUSES: Counter[tuple[str, int]] = Counter()
SERVER_LOG: list[Any] = []
LEAKS = ("Traceback", str(ROOT), "site-packages", '.py"', ".py'", 'File "')


def _content_type(response: schemathesis.Response) -> str:
    value = response.headers.get("content-type") or [""]
    return str(value[0] if isinstance(value, list) else value)


@schemathesis.check
def no_non_finite_numbers(ctx: Any, response: schemathesis.Response, case: Any) -> bool:
    """JSON bodies parse without any NaN/Infinity constant."""
    if "json" not in _content_type(response):
        return True

    def refuse(token: str) -> Any:
        raise AssertionError(f"non-finite number {token} in the body")

    json.loads(response.content, parse_constant=refuse)
    return True


@schemathesis.check
def no_internal_details(ctx: Any, response: schemathesis.Response, case: Any) -> bool:
    """No stack trace or internal path in any answer."""
    if _content_type(response).startswith("image/png"):
        return True
    text = response.content.decode("utf-8", errors="replace")
    for leak in LEAKS:
        if leak in text:
            raise AssertionError(f"the body leaks {leak!r}")
    return True


@schemathesis.check
def documented_server_errors(ctx: Any, response: schemathesis.Response, case: Any) -> bool:
    """A 5xx is only 503 overloaded (with Retry-After) or 504 timeout."""
    if response.status_code < 500:
        return True
    assert response.status_code in (503, 504), response.status_code
    body = json.loads(response.content)
    if response.status_code == 503:
        assert body.get("code") == "overloaded" and "retry-after" in {
            k.lower() for k in response.headers}, body
    else:
        assert body["code"] == "timeout", body
    return True


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[requests.Session]:
    """``python -m service`` with the cheap limits on PORT; a keep-alive session to it."""
    env = {"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(PORT)}
    env.update({f"PLANNER_{k.upper()}": (",".join(v) if isinstance(v, list) else str(v))
                for k, v in FUZZ_SETTINGS.items()})
    log = tmp_path_factory.mktemp("fuzz") / "server.log"
    SERVER_LOG.append(log)
    with server_process([sys.executable, "-m", "service"], env, PORT, log):
        with requests.Session() as session:
            yield session


@schema.parametrize()
@hypothesis.settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
                     suppress_health_check=list(hypothesis.HealthCheck), database=None)
def test_fuzz(case: Any, fuzz_server: requests.Session) -> None:
    label = case.operation.label
    CASES[label] += 1
    response = case.call_and_validate(session=fuzz_server)
    STATUSES[(label, response.status_code)] += 1


def test_fuzz_ran_enough_cases() -> None:
    """Runs after the fuzz tests (file order): every operation fuzzed, enough cases in all."""
    operations = {op.ok().label for op in schema.get_all_operations()}
    ran = set(CASES)
    print(f"\nfuzz cases: {sum(CASES.values())} over {len(CASES)} operations; statuses:",
          dict(sorted(STATUSES.items())))
    assert ran == operations, operations ^ ran
    assert sum(CASES.values()) >= MIN_TOTAL_CASES
    # failures the answers cannot show: an unhandled exception in the server (the last-resort
    # guard answers it as a 422) or an unexpected library exception in a worker
    lines = SERVER_LOG[0].read_text(errors="replace").splitlines()
    bad = [line for line in lines if '"unhandled error"' in line
           or "failed unexpectedly" in line or '"level": "error"' in line]
    assert not bad, "\n".join(bad[:5])
