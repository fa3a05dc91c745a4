"""The service's fast paths: ``POST /v1/plans`` answered by the request middleware (the same
answers as the FastAPI route), the asyncio pipes to the workers (large messages, an idle worker
that dies), a light server process (no solver modules, no matplotlib) and workers that start with
matplotlib loaded."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.fastpath import FastPlanRoute, is_json
from service.main import create_app
from service.middleware import RequestContextMiddleware
from service.settings import default_settings
from svc_support import DEG, ROOT, WORKED, TestClient, assert_problem, wait_ready

#: A start inside the region but outside its joint bound: the library refuses it.
OUTSIDE_BOUND = {"start": [0.2, 0.2, 0.2], "joint_bounds": [[0.3, 1.0], None, None]}

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

CHEAP = {**WORKED, "phi_change": 34 * DEG, "samples": 11}


def _app(fast: bool) -> TestClient:
    app = create_app(default_settings(workers=1, queue_size=8))
    if not fast:
        for m in app.user_middleware:
            if m.cls is RequestContextMiddleware:
                m.kwargs["fast_routes"] = []
    return TestClient(app, raise_server_exceptions=False)


@pytest.fixture(scope="module")
def both():
    """Two apps, with and without the fast route (one worker each)."""
    with _app(True) as fast, _app(False) as slow:
        wait_ready(fast)
        wait_ready(slow)
        yield fast, slow


def _comparable(r) -> tuple[int, dict, dict]:
    assert r.headers.get("content-encoding") == "gzip" or \
        int(r.headers["content-length"]) == len(r.content)
    # (the length varies with the timings)
    headers = {k: v for k, v in r.headers.items()
               if k not in ("x-request-id", "date", "content-length")}
    body = r.json()
    body.pop("request_id", None)
    body.pop("timing", None)  # seconds per stage vary from run to run
    return r.status_code, headers, body


REQUESTS = [
    ("success", {"json": CHEAP}),
    ("success, charset", {"content": json.dumps(CHEAP).encode(),
                          "headers": {"content-type": "application/json; charset=utf-8"}}),
    ("infeasible", {"json": {"start": [10 * DEG, 20 * DEG, 30 * DEG],
                             "goal": [40 * DEG, 25 * DEG, 15 * DEG], "method": "polynomial"}}),
    ("library validation", {"json": {**CHEAP, **OUTSIDE_BOUND}}),
    ("schema", {"json": {**CHEAP, "samples": 10 ** 6}}),
    ("unknown field", {"json": {**CHEAP, "colour": "red"}}),
    ("not JSON", {"content": b'{"start": [0.1,', "headers": {"content-type": "application/json"}}),
    ("not UTF-8", {"content": b'{"start": "\xff"}', "headers": {"content-type": "application/json"}}),
    ("form", {"data": {"start": "1"}}),
    ("no content type", {"content": json.dumps(CHEAP).encode(), "headers": {}}),
    ("a JSON array", {"json": [1, 2, 3]}),
    ("empty body", {"content": b"", "headers": {"content-type": "application/json"}}),
    ("NaN", {"content": b'{"start": [NaN, 0.2, 0.2], "goal": [0.5, 0.5, 0.5]}',
             "headers": {"content-type": "application/json"}}),
]


@pytest.mark.parametrize("name,kwargs", REQUESTS, ids=[n for n, _ in REQUESTS])
def test_the_fast_route_answers_as_the_fastapi_route(both, name, kwargs):
    fast, slow = both
    a = fast.post("/v1/plans", **kwargs)
    b = slow.post("/v1/plans", **kwargs)
    assert _comparable(a) == _comparable(b), name
    assert a.headers["x-content-type-options"] == "nosniff" and a.headers["x-request-id"]


def test_valid_plans_take_the_fast_route_and_others_do_not(both, monkeypatch):
    fast, _ = both
    taken: list[bool] = []
    original = FastPlanRoute.__call__

    async def spy(self, *args, **kwargs):
        answered = await original(self, *args, **kwargs)
        taken.append(answered)
        return answered

    monkeypatch.setattr(FastPlanRoute, "__call__", spy)
    r = fast.post("/v1/plans", json=CHEAP, headers={"X-Request-ID": "fast-1"})
    assert r.status_code == 200 and r.headers["x-request-id"] == "fast-1"
    assert r.headers["content-type"] == "application/json"
    assert r.headers.get("content-encoding") == "gzip" or \
        int(r.headers["content-length"]) == len(r.content)
    bad = fast.post("/v1/plans", json={**CHEAP, "samples": 1})
    assert_problem(bad, 422, "invalid_request")
    infeasible = fast.post("/v1/plans", json={"start": [10 * DEG, 20 * DEG, 30 * DEG],
                                              "goal": [40 * DEG, 25 * DEG, 15 * DEG],
                                              "method": "polynomial"})
    assert_problem(infeasible, 422, "infeasible")
    assert taken == [True, False, True]
    metrics = fast.get("/metrics").text
    assert 'planner_http_requests_total{method="POST",route="/v1/plans",status="200"}' in metrics
    assert 'planner_solve_duration_seconds_count{job="plan",method="polynomial",' \
           'outcome="success"}' in metrics


def test_json_content_types():
    assert is_json("application/json") and is_json("Application/JSON; charset=utf-8")
    assert is_json("application/problem+json")
    assert not is_json(None) and not is_json("") and not is_json("text/plain")
    assert not is_json("application/x-www-form-urlencoded")


def test_large_messages_cross_the_worker_pipes(client):
    """A 10 000-point transform: ~0.4 MB to the worker and ~1.3 MB back, in many reads."""
    points = [[0.1 * (i % 7), 0.2 + 1e-5 * i, 0.3, 0.4] for i in range(10_000)]
    r = client.post("/v1/transforms", json={"direction": "to_chained", "points": points})
    assert r.status_code == 200, r.text
    body = r.json()
    assert len(body["points"]) == 10_000 and all(p["valid"] for p in body["points"])


def test_an_idle_worker_that_dies_is_replaced_before_a_request_takes_it():
    app = create_app(default_settings(workers=1, queue_size=4))
    with TestClient(app, raise_server_exceptions=False) as c:
        wait_ready(c)
        (pid,) = app.state.pool.pids()
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            ready = c.get("/readyz").json()
            pids = app.state.pool.pids()
            if ready["restarts"] == 1 and ready["idle"] == 1 and pids and pids[0] != pid:
                break
            time.sleep(0.02)
        else:
            raise AssertionError(f"not replaced: {ready}")
        r = c.post("/v1/plans", json=CHEAP)
        assert r.status_code == 200, r.text
        assert 'planner_worker_restarts_total{reason="lost"} 1.0' in c.get("/metrics").text


def test_the_known_paths_are_the_openapi_paths():
    app = create_app(default_settings())
    (mw,) = [m for m in app.user_middleware if m.cls is RequestContextMiddleware]
    known = mw.kwargs["known_paths"]()
    # (and the explorer's /, left out of the document)
    assert known == set(app.openapi()["paths"]) | {"/", "/docs", "/redoc", "/openapi.json"}


def test_the_server_process_loads_neither_the_solvers_nor_matplotlib():
    code = ("import sys, service.main; "
            "print(sorted(m for m in ('matplotlib', 'scipy', 'casadi', 'cvxpy', 'clarabel') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def _maps_matplotlib(pid: int) -> bool:
    return "matplotlib" in Path(f"/proc/{pid}/maps").read_text()


def _mapped_files(pid: int) -> set[str]:
    """The shared libraries (``.so`` files: extension modules, fonts' FreeType) mapped."""
    return {line.split()[-1] for line in Path(f"/proc/{pid}/maps").read_text().splitlines()
            if ".so" in line.split()[-1]}


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs /proc")
def test_workers_start_with_matplotlib_loaded_and_warm():
    """matplotlib is loaded (and a figure drawn) in the forkserver before the workers start, so
    that a figure's drawing allowance is spent on drawing: a cold worker's import alone took
    6 s at load 10-14 on two cores. A worker's first figure then loads none of it."""
    app = create_app(default_settings(workers=1, queue_size=4))
    with TestClient(app, raise_server_exceptions=False) as c:
        wait_ready(c)
        (pid,) = app.state.pool.pids()
        assert _maps_matplotlib(pid)  # mapped before any figure was asked for
        libraries = _mapped_files(pid)
        r = c.post("/v1/figures/joint_angles?format=png", json=CHEAP)
        assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n"
        r = c.post("/v1/figures/chained_state?format=svg", json=CHEAP)
        assert r.status_code == 200 and r.text.lstrip().startswith("<?xml")
        assert _mapped_files(pid) == libraries  # nothing new was loaded to draw them
