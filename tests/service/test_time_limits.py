"""Time limits that hold: a job running past its ``time_limit`` is answered 504 ``timeout``
within ``time_limit + timeout_grace`` (0.5 s, the default) of reaching its worker; a worker that
does not answer is SIGKILLed and replaced, and the next request succeeds.

Three ways past the limit:

* a request made to be slow: a robustness job with 200 open-loop v-replays (DOP853 with the
  input map at the actual state, about 45 ms each, so ~9 s; the replays have no deadline checks
  of their own) and a short ``time_limit``;
* a hung worker (SIGSTOP): the pool must kill it, whatever the library does;
* the library's own deadline check (a 3-joint sweep of 2001 points): answered at once, no
  worker killed.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from typing import Any, Iterator

import pytest

from svc_support import DEG, LAG, WORKED, TestClient, assert_problem, running_app

GRACE = 0.5
CHEAP = {**WORKED, "phi_change": 34 * DEG, "samples": 5}
SLOW = {"plan": {**WORKED, "phi_change": 34 * DEG, "samples": 51},
        "random": {"count": 200, "spread": 0.01, "seed": 3}, "replay": "v"}


@pytest.fixture(scope="module")
def one_worker() -> Iterator[TestClient]:
    with running_app(workers=1, queue_size=4, timeout_grace=GRACE) as c:
        yield c


def _idle(client: TestClient, timeout: float = 60.0) -> dict[str, Any]:
    """Wait until the (replaced) worker is idle again."""
    deadline = time.monotonic() + timeout
    while True:
        ready = client.get("/readyz").json()
        if ready["idle"] >= 1:
            return ready
        assert time.monotonic() < deadline, ready
        time.sleep(0.02)


def _gone(pid: int, timeout: float = 10.0) -> bool:
    """True once ``pid`` no longer exists (killed and reaped)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.02)
    return False


@pytest.mark.parametrize("time_limit", [0.3, 1.0])
def test_a_slow_job_is_answered_timeout_within_limit_plus_grace(one_worker, time_limit):
    _idle(one_worker)
    before = one_worker.get("/readyz").json()["restarts"]
    t0 = time.perf_counter()
    r = one_worker.post("/v1/robustness", json={**SLOW, "time_limit": time_limit})
    elapsed = time.perf_counter() - t0
    body = assert_problem(r, 504, "timeout")
    assert body["field"] == "time_limit" and body["diagnostics"]["time_limit"] == time_limit
    print(f"\ntime_limit {time_limit} s: timeout answered after {elapsed:.3f} s "
          f"(+{elapsed - time_limit:.3f} s)")
    # the promise is time_limit + GRACE from the worker taking the job (idle machine: +0.46 s);
    # LAG is the loaded machine's; the job itself runs ~9 s idle, far past either bound
    assert time_limit <= elapsed < time_limit + GRACE + LAG, elapsed
    # the pool recovers: the next request succeeds (on the replacement worker)
    r = one_worker.post("/v1/plans", json=CHEAP)
    assert r.status_code == 200, r.text
    # the library checks the deadline between replays, so the worker usually stops by itself;
    # when a replay straddles the bound the worker is killed and replaced (see the hung-worker
    # test for that path)
    assert one_worker.get("/readyz").json()["restarts"] in (before, before + 1)


def _timeout_restarts(client: Any) -> float:
    """The server's count of workers restarted because a job overran (reason ``timeout``) or,
    stopped, stopped answering pings first (``unresponsive``: on a loaded machine the ping
    can see it before the job's deadline does); 0 before the first."""
    total = 0.0
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(('planner_worker_restarts_total{reason="timeout"}',
                            'planner_worker_restarts_total{reason="unresponsive"}')):
            total += float(line.split()[-1])
    return total


def test_a_hung_worker_is_killed_replaced_and_the_next_request_succeeds(one_worker):
    _idle(one_worker)
    pool = one_worker.app.state.pool
    (old,) = pool.pids()
    before = one_worker.get("/readyz").json()["restarts"]
    timeouts = _timeout_restarts(one_worker)   # (a loaded machine may restart for other reasons)
    # a solve stuck where no deadline check can run: the worker is stopped once it has the
    # job (a worker stopped while idle is replaced before it takes one: test_faults.py)
    answers: list[Any] = []
    sender = threading.Thread(target=lambda: answers.append(one_worker.post(
        "/v1/robustness", json={**SLOW, "time_limit": 0.5})))
    t0 = time.perf_counter()
    sender.start()
    deadline = time.monotonic() + 10
    while pool.stats().idle:
        assert time.monotonic() < deadline
        time.sleep(0.005)
    os.kill(old, signal.SIGSTOP)
    sender.join(timeout=30)
    elapsed = time.perf_counter() - t0
    (r,) = answers
    assert_problem(r, 504, "timeout")
    # (not killed: no answer within the join's 30 s)
    assert 0.5 <= elapsed < 0.5 + GRACE + LAG, elapsed
    assert _gone(old), "the hung worker was not killed and reaped"
    r = one_worker.post("/v1/plans", json=CHEAP)
    assert r.status_code == 200, r.text
    ready = _idle(one_worker)
    assert ready["restarts"] == before + 1 and ready["workers"] == 1
    (new,) = pool.pids()
    assert new != old
    metrics = one_worker.get("/metrics").text
    assert _timeout_restarts(one_worker) == timeouts + 1
    assert 'planner_solve_duration_seconds_count{job="robustness",method="polynomial",' \
           'outcome="timeout"}' in metrics


def test_the_librarys_own_deadline_is_answered_at_once_without_a_kill(one_worker):
    _idle(one_worker)
    before = one_worker.get("/readyz").json()["restarts"]
    t0 = time.perf_counter()
    # a 3-joint sweep (~3 ms of CPU a point, ~6 s in all): the library checks its deadline at
    # every point, and a point stays far inside the grace however loaded the machine (the
    # 8-joint sweep used before took longer than the 0.45 s grace between two checks at load
    # 14 on 2 cores, and the pool's kill came first)
    r = one_worker.post("/v1/sweeps", json={**WORKED, "phi_change_range": [-3.0, 3.0],
                                             "points": 2001, "time_limit": 0.2})
    elapsed = time.perf_counter() - t0
    body = assert_problem(r, 504, "timeout")
    assert body["field"] == "time_limit"
    assert elapsed < 0.2 + GRACE + LAG, elapsed
    # answered by the library's deadline check, not by the pool's kill at 0.2 + GRACE
    assert one_worker.get("/readyz").json()["restarts"] == before
