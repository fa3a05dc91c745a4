"""The plan answer crosses the service unchanged: the worker encodes the library's answer once
and the server forwards those bytes. Over HTTP, the default request (``method`` left out, as a
user sends it) and a named method answer exactly what the library's own ``to_dict()`` gives in
this process (every field but the facts of the run: request id, timings), and the fast route parses
bodies that ``json.loads`` and pydantic's own JSON parser could read differently the same way
as the FastAPI route. Floats agree to 1e-12 (the workers prove with the compiled quadrature,
this process with numpy's: the same sums in another order); everything else exactly."""

from __future__ import annotations

import json

import pytest

from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from svc_support import DEG, WORKED, same_json

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

#: The default request of the HTTP benchmark (bench/http_load.py), method left to the service.
DEFAULT = {"start": [10.5 * DEG, 9.2 * DEG, 11.0 * DEG], "goal": [30 * DEG] * 3}


#: Facts of the run, not of the request: the request id, the seconds of each stage and of each
#: method tried, and whether the NLP functions ran compiled (the workers load them; this test
#: process need not).
RUN_FACTS = {"request_id", "timing", "seconds", "compiled"}


def _without_run_facts(answer: object) -> object:
    if isinstance(answer, dict):
        return {k: _without_run_facts(v) for k, v in answer.items() if k not in RUN_FACTS}
    if isinstance(answer, list):
        return [_without_run_facts(v) for v in answer]
    return answer


@pytest.mark.parametrize("body", [DEFAULT, {**WORKED, "samples": 41}],
                         ids=["default request", "polynomial"])
def test_the_answer_over_http_is_the_library_answer(client, body):
    # uncompressed, so that Content-Length counts the body's own bytes
    r = client.post("/v1/plans", json=body, headers={"Accept-Encoding": "identity"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/json"
    assert int(r.headers["content-length"]) == len(r.content)
    # one JSON document, no NaN/Infinity token (json.loads would accept them: forbid them)
    over_http = json.loads(r.content, parse_constant=lambda c: pytest.fail(f"token {c}"))
    local = plan(PlanRequest.from_dict(body)).to_dict()
    # the library's plain answer as JSON (non-finite numbers are null there too)
    local = json.loads(json.dumps(local, allow_nan=False))
    # the service names the path's columns (q_names, u_names); the library leaves them out
    names = {k: over_http["path"].pop(k) for k in ("q_names", "u_names")}
    assert names["q_names"][:2] == ["phi", "th1"] and names["u_names"] == ["u1", "u2"]
    # (floats to 1e-12: the workers' compiled quadrature sums in another order than numpy)
    assert same_json(_without_run_facts(over_http), _without_run_facts(local))[:5] == []


EDGE_BODIES = [
    # a key given twice: both parsers keep the last value
    ("duplicate key", b'{"start": [0.0, 0.0, 0.0], "start": [0.1745, 0.1745, 0.1745], '
                      b'"goal": [0.5236, 0.5236, 0.5236], "method": "polynomial", "samples": 11}'),
    # numbers written as strings (pydantic's lax mode reads them in Python and in JSON mode)
    ("numbers as strings", b'{"start": ["0.1745", "0.1745", "0.1745"], '
                           b'"goal": [0.5236, 0.5236, 0.5236], "method": "polynomial", '
                           b'"samples": 11}'),
    # a number too large for a double (json.loads reads inf; the JSON parser refuses or reads inf)
    ("1e309", b'{"start": [1e309, 0.2, 0.2], "goal": [0.5, 0.5, 0.5]}'),
    ("integers", b'{"start": [0, 0, 0], "goal": [1, 1, 1]}'),
    ("nested depth", b'{"start": ' + b"[" * 200 + b"]" * 200 + b', "goal": [0.5, 0.5, 0.5]}'),
    ("byte order mark", b'\xef\xbb\xbf{"start": [0.1745, 0.1745, 0.1745], '
                        b'"goal": [0.5236, 0.5236, 0.5236], "method": "polynomial"}'),
]


@pytest.fixture(scope="module")
def both():
    """The app with and without the fast route (one worker each), as the fast-path tests."""
    from test_service_fast import _app

    from svc_support import wait_ready

    with _app(True) as fast, _app(False) as slow:
        wait_ready(fast)
        wait_ready(slow)
        yield fast, slow


@pytest.mark.parametrize("name,raw", EDGE_BODIES, ids=[n for n, _ in EDGE_BODIES])
def test_the_fast_route_parses_as_the_fastapi_route(both, name, raw):
    from test_service_fast import _comparable

    fast, slow = both
    headers = {"content-type": "application/json"}
    a = fast.post("/v1/plans", content=raw, headers=headers)
    b = slow.post("/v1/plans", content=raw, headers=headers)
    assert _comparable(a) == _comparable(b), name
