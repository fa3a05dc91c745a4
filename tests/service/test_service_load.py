"""Limits and load: over-large, huge and deeply nested bodies; 32 concurrent requests; the bounded
queue (503 overloaded); a worker that dies mid-job. Time limits: ``test_time_limits.py``."""

from __future__ import annotations

import os
import signal
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from svc_support import DEG, WORKED, assert_problem, running_app


def test_ten_megabyte_body_is_refused_with_413(client):
    big = b'{"start": [' + b"0.1, " * (2 * 1024 * 1024) + b"0.1]}"
    r = client.post("/v1/plans", content=big, headers={"content-type": "application/json"})
    body = assert_problem(r, 413, "invalid_request")
    assert "1048576" in body["detail"]


def test_chunked_body_over_the_limit_is_refused_with_413(client):
    def chunks():
        yield b'{"start": ['
        for _ in range(40):
            yield b"0.1, " * 60000
        yield b"0.1]}"

    r = client.post("/v1/plans", content=chunks(), headers={"content-type": "application/json"})
    assert_problem(r, 413, "invalid_request")


def test_hundred_thousand_samples_is_refused(client):
    r = client.post("/v1/plans", json={**WORKED, "samples": 100000})
    body = assert_problem(r, 422, "invalid_request")
    assert body["field"] == "samples" and "20001" in body["detail"]


def test_answers_are_bounded_in_size(client):
    """No single answer may hold more than max_total_samples path rows."""
    r = client.post("/v1/plans/batch", json={"requests": [{**WORKED, "samples": 20001}] * 11})
    body = assert_problem(r, 422, "invalid_request")
    assert "200000" in body["detail"]
    r = client.post("/v1/robustness", json={
        "plan": {**WORKED, "phi_change": 34 * DEG, "samples": 20001},
        "random": {"count": 20, "spread": 0.01}, "include_paths": True})
    body = assert_problem(r, 422, "invalid_request")
    assert "200000" in body["detail"]


@pytest.mark.parametrize("depth", [100_000, 5000, 500])
def test_deeply_nested_json_is_a_4xx(client, depth):
    raw = '{"start": ' + "[" * depth + "]" * depth + ', "goal": [0.5, 0.5, 0.5]}'
    r = client.post("/v1/plans", content=raw, headers={"content-type": "application/json"})
    assert 400 <= r.status_code < 500, r.text
    assert r.json()["code"] == "invalid_request"


def test_malformed_json_is_a_400_problem(client):
    r = client.post("/v1/plans", content=b'{"start": [0.1,', headers={"content-type":
                                                                     "application/json"})
    assert 400 <= r.status_code < 500
    assert r.json()["code"] == "invalid_request"


def test_32_concurrent_requests_are_all_answered_correctly(client):
    """Fixed-dphi plans with distinct dphi and transforms, interleaved: each answer must be
    the answer to its own request."""
    def job(i: int) -> tuple[int, bool]:
        if i % 4 == 3:
            th = (5 + i) * DEG
            r = client.post("/v1/transforms", json={"direction": "to_chained",
                                                    "points": [[float(i), th, th, th]]},
                            headers={"X-Request-ID": f"c{i}"})
            assert r.status_code == 200, r.text
            assert r.headers["x-request-id"] == f"c{i}"
            return i, r.json()["points"][0]["values"][0] == float(i)
        dphi = (33.4 + 0.05 * i) * DEG
        r = client.post("/v1/plans", json={**WORKED, "phi_change": dphi, "samples": 21},
                        headers={"X-Request-ID": f"c{i}"})
        assert r.status_code == 200, r.text
        assert r.headers["x-request-id"] == f"c{i}"
        body = r.json()
        return i, (abs(body["phi_change"] - dphi) < 1e-12
                   and body["validation"]["terminal_error"] < 1e-6
                   and body["path"]["q"][-1][1:] == pytest.approx(WORKED["goal"], abs=1e-9))

    with ThreadPoolExecutor(max_workers=32) as ex:
        results = list(ex.map(job, range(32)))
    assert [i for i, _ in results] == list(range(32))
    assert all(ok for _, ok in results), results


def test_more_requests_than_the_queue_holds_get_503_overloaded():
    """One worker, one waiting place: of 6 simultaneous slow requests at most 2 are admitted
    while the first one runs; the others are refused at once with Retry-After."""
    slow = {**WORKED, "samples": 201, "phi_change_bounds": [-6.0, 6.0],
            "time_limit": 60}  # admitted ones must not time out on a loaded machine
    with running_app(workers=1, queue_size=1, retry_after=3) as c:
        def send(_: int):
            t0 = time.perf_counter()
            r = c.post("/v1/plans", json=slow)
            return r, time.perf_counter() - t0

        with ThreadPoolExecutor(max_workers=6) as ex:
            answers = list(ex.map(send, range(6)))
        statuses = sorted(r.status_code for r, _ in answers)
        assert set(statuses) <= {200, 503}, statuses
        assert statuses.count(200) >= 1 and statuses.count(503) >= 3, statuses
        for r, seconds in answers:
            if r.status_code == 503:
                assert_problem(r, 503, "overloaded")
                assert r.headers["retry-after"] == "3"
            else:
                assert r.json()["phi_change"] / DEG == pytest.approx(34.57, abs=0.05)
        metrics = c.get("/metrics").text
        assert 'planner_http_requests_total{method="POST",route="/v1/plans",status="503"}' \
            in metrics


def test_a_worker_that_dies_is_replaced_and_the_request_answered():
    """SIGKILL the only worker in the middle of a sweep: the job runs again on the replacement
    (not a 500, not a hang, not a 422) and the next request is served too."""
    with running_app(workers=1, queue_size=4, worker_ping_interval=0) as c:
        (pid,) = c.app.state.pool.pids()
        slow = {"robot": {}, "start": [10 * DEG] * 8, "goal": [30 * DEG] * 8,
                "phi_change_range": [-12.0, 12.0], "points": 201,
                "time_limit": 60}  # the largest: it runs twice, at load 10 well past 30 s
        with ThreadPoolExecutor(max_workers=1) as ex:
            pending = ex.submit(c.post, "/v1/sweeps", json=slow)
            deadline = time.monotonic() + 10
            while c.get("/readyz").json()["busy"] == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            os.kill(pid, signal.SIGKILL)
            r = pending.result(timeout=60)
        assert r.status_code == 200, r.text
        assert len(r.json()["phi_change"]) == 201
        r = c.post("/v1/plans", json={**WORKED, "phi_change": 34 * DEG, "samples": 5})
        assert r.status_code == 200, r.text
        assert 'planner_worker_restarts_total{reason="lost"} 1.0' in c.get("/metrics").text
