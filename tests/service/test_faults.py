"""Faults, as a fault audit injects them: the service heals itself and tells the truth.

* Every worker SIGKILLed again and again (replacements killed while they start too): the pool
  is back at full size within 15 s and plans are answered; while no worker is live ``/readyz``
  is not 200, and whenever it is 200 a worker is live.
* A worker killed under a job: the job runs once more on another worker (200); killed twice,
  503 ``worker_lost`` with ``Retry-After``.
* A stopped (SIGSTOP) idle worker is found by its ping and replaced before it holds a request.
* Connections: an oversized header (431 problem document), a stalled body (408, within
  ``body_timeout``), a silent connection (closed within ``header_timeout``), a slow reader
  (dropped after ``send_timeout``; server memory bounded), the connection cap.
* A shutdown that cannot drain: its queued requests are answered 503 ``shutting_down``.

Live servers on loopback (``python -m service``), each test bounded well under a minute.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

import httpx
import psutil
import pytest

from svc_support import (DEG, WORKED, TestClient, assert_problem, free_port, running_app,
                         server_process)

CHEAP = {**WORKED, "phi_change": 34 * DEG, "samples": 5}
#: ~1.5-2 s of work for one worker: a plan, then 40 open-loop replays.
SLOWISH = {"plan": {**WORKED, "phi_change": 34 * DEG, "samples": 51},
           "random": {"count": 40, "spread": 0.01, "seed": 5}, "time_limit": 30}


def _workers(server_pid: int) -> list[psutil.Process]:
    """The worker processes of a ``python -m service`` server: the forkserver's children."""
    out = []
    for child in psutil.Process(server_pid).children():
        try:
            if "forkserver" in " ".join(child.cmdline()):
                out.extend(child.children())
        except psutil.NoSuchProcess:
            pass
    return out


def _kill_all(procs: list[psutil.Process]) -> int:
    killed = 0
    for p in procs:
        try:
            p.send_signal(signal.SIGKILL)
            killed += 1
        except psutil.NoSuchProcess:
            pass
    return killed


def _server_pid(port: int) -> int:
    for conn in psutil.net_connections("tcp"):
        if conn.status == psutil.CONN_LISTEN and conn.laddr.port == port and conn.pid:
            return conn.pid
    raise AssertionError("no process listens on the port")


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, int]]:
    """``python -m service`` with 2 workers; yields the base URL and the server's pid."""
    port = free_port()
    log = tmp_path_factory.mktemp("faults") / "server.log"
    env = {"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port), "PLANNER_WORKERS": "2",
           "PLANNER_QUEUE_SIZE": "8", "PLANNER_LOG_LEVEL": "warning"}
    with server_process([sys.executable, "-m", "service"], env, port, log) as base:
        yield base, _server_pid(port)


# ---------------------------------------------------------------------- the pool heals
def test_after_repeated_kills_of_every_worker_the_pool_heals_and_readyz_tells_the_truth(
        two_workers):
    base, pid = two_workers
    with httpx.Client(base_url=base, timeout=10) as client:
        before = client.get("/readyz").json()
        assert before["live"] == 2
        seen: list[tuple[int, dict[str, Any]]] = []
        stop = threading.Event()

        def poll() -> None:
            with httpx.Client(base_url=base, timeout=10) as c:
                while not stop.is_set():
                    r = c.get("/readyz")
                    seen.append((r.status_code, r.json()))
                    time.sleep(0.02)

        poller = threading.Thread(target=poll)
        poller.start()
        killed = 0
        try:
            end = time.monotonic() + 4.0  # every worker, and every replacement as it starts
            while time.monotonic() < end:
                killed += _kill_all(_workers(pid))
                time.sleep(0.05)
        finally:
            stop.set()
            poller.join(timeout=20)
        healed_at = None
        t0 = time.monotonic()
        while time.monotonic() - t0 < 15.0:
            r = client.get("/readyz")
            if r.status_code == 200 and r.json()["live"] == 2:
                healed_at = time.monotonic() - t0
                break
            time.sleep(0.05)
        print(f"\n{killed} kills; healed to 2 live workers {healed_at} s after the last; "
              f"/readyz seen {len(seen)} times, {sum(c != 200 for c, _ in seen)} not 200")
        assert healed_at is not None, client.get("/readyz").json()
        assert killed >= 4
        # the truth meanwhile: never 200 without a live worker, never 'ready' while none is
        for status, body in seen:
            assert (status == 200) == (body["status"] == "ready"), body
            assert (status == 200) == (body["live"] > 0), body
        assert any(status == 503 and body["live"] == 0 for status, body in seen), \
            "no /readyz answer saw the pool without workers"
        for _ in range(4):
            r = client.post("/v1/plans", json=CHEAP)
            assert r.status_code == 200, r.text
        ready = client.get("/readyz").json()
        assert ready["restarts"] >= before["restarts"] + 2
        metrics = client.get("/metrics").text
        assert "planner_workers_live 2.0" in metrics
        assert "planner_workers_configured 2.0" in metrics


def test_a_job_whose_worker_is_killed_is_retried_on_another_worker(two_workers):
    base, pid = two_workers
    answer: dict[str, Any] = {}

    def send() -> None:
        r = httpx.post(base + "/v1/robustness", json=SLOWISH, timeout=60)
        answer.update(status=r.status_code, body=r.json(), headers=dict(r.headers))

    with httpx.Client(base_url=base, timeout=10) as client:
        _wait_live(client, 2)
        sender = threading.Thread(target=send)
        sender.start()
        deadline = time.monotonic() + 20
        while client.get("/readyz").json()["busy"] == 0:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        time.sleep(0.2)  # the job is well under way
        assert _kill_all(_workers(pid)) == 2  # the job's worker and the idle one
        sender.join(timeout=60)
    assert answer["status"] == 200, answer
    assert answer["body"]["summary"]["runs"] == 40


def test_a_job_lost_twice_is_answered_503_worker_lost():
    with running_app(workers=1, queue_size=4, worker_ping_interval=0) as client:
        pool = client.app.state.pool
        answer: dict[str, Any] = {}

        def send() -> None:
            r = client.post("/v1/robustness", json=SLOWISH)
            answer.update(response=r)

        sender = threading.Thread(target=send)
        sender.start()
        killed: list[int] = []
        deadline = time.monotonic() + 40
        while len(killed) < 2 and time.monotonic() < deadline:
            st = pool.stats()
            pids = pool.pids()
            if st.busy == 1 and st.idle == 0 and st.live == 1 and pids and pids[0] not in killed:
                time.sleep(0.1)  # the job has reached the worker
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
            time.sleep(0.01)
        sender.join(timeout=60)
        assert len(killed) == 2
        body = assert_problem(answer["response"], 503, "worker_lost")
        assert answer["response"].headers["retry-after"] == "1"
        assert body["diagnostics"]["retry_after"] == 1
        r = client.post("/v1/plans", json=CHEAP)  # the pool has a worker again
        assert r.status_code == 200, r.text


def test_a_stopped_idle_worker_is_replaced_before_it_holds_a_request():
    with running_app(workers=1, queue_size=4, worker_ping_interval=0.2,
                     worker_ping_timeout=0.3) as client:
        pool = client.app.state.pool
        (old,) = pool.pids()
        os.kill(old, signal.SIGSTOP)
        try:
            deadline = time.monotonic() + 10
            while old in pool.pids():
                assert time.monotonic() < deadline, "the stopped worker was not replaced"
                time.sleep(0.02)
            _wait_live(client, 1)
            t0 = time.perf_counter()
            r = client.post("/v1/plans", json={**CHEAP, "time_limit": 5})
            assert r.status_code == 200, r.text
            assert time.perf_counter() - t0 < 2.0
            metrics = client.get("/metrics").text
            assert 'planner_worker_restarts_total{reason="unresponsive"} 1.0' in metrics
        finally:
            try:
                os.kill(old, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_request_waits_for_a_worker_at_most_queue_timeout():
    with running_app(workers=1, queue_size=4, queue_timeout=0.5) as client:
        def slow() -> None:
            client.post("/v1/robustness", json=SLOWISH)

        t = threading.Thread(target=slow)
        t.start()
        pool = client.app.state.pool
        deadline = time.monotonic() + 20
        while pool.stats().idle:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        t0 = time.perf_counter()
        r = client.post("/v1/plans", json=CHEAP)
        elapsed = time.perf_counter() - t0
        body = assert_problem(r, 503, "overloaded")
        assert "retry-after" in r.headers and "no worker became free" in body["detail"]
        assert 0.5 <= elapsed < 1.5, elapsed
        t.join(timeout=60)


def _wait_live(client: Any, n: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        ready = client.get("/readyz").json()
        if ready["live"] >= n and ready["idle"] >= n:
            return
        assert time.monotonic() < deadline, ready
        time.sleep(0.05)
