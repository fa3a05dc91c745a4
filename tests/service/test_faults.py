"""Faults, as a fault audit injects them: the service heals itself and tells the truth.

* Every worker SIGKILLed again and again (replacements killed while they start too): the pool
  is back at full size within 15 s and plans are answered; while no worker is live ``/readyz``
  is not 200, and whenever it is 200 a worker is live.
* A worker killed under a job: the job runs once more on another worker (200); killed twice,
  503 ``worker_lost`` with ``Retry-After``.
* A stopped (SIGSTOP) idle worker is found by its ping and replaced before it holds a request.
* Connections: an oversized header (431 problem document), a body trickled after an early
  401/413 (cut off about ``body_timeout`` after the answer), a stalled body (408, within
  ``body_timeout``), a silent connection (closed within ``header_timeout``), a slow reader
  (dropped after ``send_timeout``; server memory bounded), the connection cap.
* A shutdown that cannot drain: its queued requests are answered 503 ``shutting_down``.

Live servers on loopback (``python -m service``), each test bounded well under a minute.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from typing import Any, Iterator

import httpx
import psutil
import pytest

from service.schemas import build_schemas
from service.settings import Limits
from svc_support import (DEG, KEYS, LAG, ROOT, WORKED, assert_problem, free_port,
                         read_until_closed, running_app, server_process)

CHEAP = {**WORKED, "phi_change": 34 * DEG, "samples": 5}
#: ~1 s of work for one worker: a plan, then 40 open-loop v-replays (DOP853 with the input
#: map at the actual state, ~20 ms each; the u-replays of the handed-out form take ~1 ms).
#: Under the largest time limit: at load 16 on 2 cores a job run again after its worker was
#: killed ran past 30 s (504), and what these tests check is where a job runs, not how fast.
SLOWISH = {"plan": {**WORKED, "phi_change": 34 * DEG, "samples": 51},
           "random": {"count": 40, "spread": 0.01, "seed": 5}, "replay": "v", "time_limit": 60}


#: A job long by nature, to be caught running: a plan, then 3 closed-loop runs of 10 replans
#: (1.8 s on an idle machine; SLOWISH's open-loop replays once ended before a poll saw them).
IN_FLIGHT = {"plan": {"start": [10 * DEG] * 3, "goal": [30 * DEG] * 3},
             "random": {"count": 3, "spread": 0.01, "seed": 5},
             "closed_loop": {"gain_error": 0.05, "period": 0.1, "seed": 1}, "time_limit": 60}


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


#: Connection bounds of the test server, tightened so that each test takes seconds.
BOUNDS = {"PLANNER_HEADER_TIMEOUT": "1", "PLANNER_BODY_TIMEOUT": "1", "PLANNER_SEND_TIMEOUT": "2",
          "PLANNER_MAX_CONNECTIONS": "40", "PLANNER_MAX_HEADER_BYTES": "16384"}


def _bounded_server(tmp_path_factory: pytest.TempPathFactory, name: str,
                    **env: str) -> Iterator[str]:
    """``python -m service`` with :data:`BOUNDS`, one worker and the settings ``env``; yields
    its base URL."""
    port = free_port()
    log = tmp_path_factory.mktemp(name) / "server.log"
    full = {"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port), "PLANNER_WORKERS": "1",
            "PLANNER_LOG_LEVEL": "warning", **BOUNDS, **env}
    with server_process([sys.executable, "-m", "service"], full, port, log) as base:
        yield base


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, int]]:
    """``python -m service`` with 2 workers; yields the base URL and the server's pid."""
    port = free_port()
    log = tmp_path_factory.mktemp("faults") / "server.log"
    env = {"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port), "PLANNER_WORKERS": "2",
           "PLANNER_QUEUE_SIZE": "100", "PLANNER_LOG_LEVEL": "warning",
           # the slow readers' 8 plans queue for 2 workers: at load 13-16 on 2 cores (~10 s
           # a plan) the last ones waited past the default 30 s and were answered 503, which
           # is small enough never to stall, so they were never counted dropped
           "PLANNER_QUEUE_TIMEOUT": "240",
           "PLANNER_MAX_ROBUSTNESS_RUNS": "1000", **BOUNDS}
    with server_process([sys.executable, "-m", "service"], env, port, log) as base:
        yield base, _server_pid(port)


@pytest.fixture(scope="module", params=["httptools", "h11"])
def bounded(request: pytest.FixtureRequest, two_workers: tuple[str, int],
            tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The base URL of a server with :data:`BOUNDS`, for each of uvicorn's HTTP protocols."""
    if request.param == "httptools":  # the default: the module's server
        yield two_workers[0]
        return
    yield from _bounded_server(tmp_path_factory, "faults_h11", PLANNER_HTTP="h11")


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


def test_a_job_whose_workers_are_all_killed_is_answered_200_or_503(two_workers):
    """Every worker killed under a job: run again on a replacement (200), or, should that be
    lost too, 503 ``worker_lost``; never a 422, a 500 or a hang."""
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
        _wait_live(client, 2)
    assert answer["status"] in (200, 503), answer
    if answer["status"] == 200:
        assert answer["body"]["summary"]["runs"] == 40
    else:
        assert answer["body"]["code"] == "worker_lost" and answer["headers"]["retry-after"]


def test_a_job_whose_worker_is_killed_is_run_again_on_another_worker():
    with running_app(workers=2, queue_size=4, worker_ping_interval=0) as client:
        pool = client.app.state.pool
        answer: dict[str, Any] = {}

        def send() -> None:
            answer.update(response=client.post("/v1/robustness", json=SLOWISH))

        sender = threading.Thread(target=send)
        sender.start()
        deadline = time.monotonic() + 20
        while not (busy := [w for w in list(pool._all) if w.busy]):
            assert time.monotonic() < deadline
            time.sleep(0.01)
        time.sleep(0.2)  # the job is well under way
        os.kill(busy[0].process.pid, signal.SIGKILL)
        sender.join(timeout=60)
        r = answer["response"]
        assert r.status_code == 200, r.text
        assert r.json()["summary"]["runs"] == 40
        assert 'planner_worker_restarts_total{reason="lost"} 1.0' in client.get("/metrics").text


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
            assert r.status_code == 200, r.text  # (a stopped worker holding it: 504 after 5 s)
            assert time.perf_counter() - t0 < 5.0
            metrics = client.get("/metrics").text
            assert 'planner_worker_restarts_total{reason="unresponsive"} 1.0' in metrics
        finally:
            try:
                os.kill(old, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_replacement_that_fails_to_start_is_retried_whatever_the_error():
    """No descriptors left (EMFILE), three times in a row: the slot is still filled."""
    with running_app(workers=1, queue_size=4) as client:
        pool = client.app.state.pool
        real, failures = pool._new_process, []

        def flaky() -> Any:
            if len(failures) < 3:
                failures.append(1)
                raise OSError(errno.EMFILE, "Too many open files")
            return real()

        pool._new_process = flaky
        (old,) = pool.pids()
        os.kill(old, signal.SIGKILL)
        deadline = time.monotonic() + 15
        while not (pool.stats().live == 1 and pool.pids() != [old]):
            assert time.monotonic() < deadline, pool.stats()
            time.sleep(0.02)
        assert len(failures) == 3
        r = client.post("/v1/plans", json=CHEAP)
        assert r.status_code == 200, r.text


def test_a_request_waits_for_a_worker_at_most_queue_timeout():
    # no liveness pings: the test needs its one worker busy with the slow job, and at load 12
    # a niced idle worker that misses a 1 s ping is replaced, so the slow job itself may wait
    # past the 0.5 s queue timeout (suspected in a CI run at load 11-12; pings have tests of
    # their own)
    with running_app(workers=1, queue_size=4, queue_timeout=0.5,
                     worker_ping_interval=0) as client:
        slow_answer: list[Any] = []

        def slow() -> None:
            slow_answer.append(client.post("/v1/robustness", json=SLOWISH))

        t = threading.Thread(target=slow)
        t.start()
        pool = client.app.state.pool
        deadline = time.monotonic() + 20
        while pool.stats().idle:
            assert time.monotonic() < deadline, (pool.stats(), slow_answer)
            time.sleep(0.01)
        t0 = time.perf_counter()
        r = client.post("/v1/plans", json=CHEAP)
        elapsed = time.perf_counter() - t0
        restarts = [line for line in client.get("/metrics").text.splitlines()
                    if line.startswith("planner_worker_restarts_total")]
        assert r.status_code == 503, (r.status_code, elapsed, restarts, slow_answer)
        body = assert_problem(r, 503, "overloaded")
        assert "retry-after" in r.headers and "no worker became free" in body["detail"]
        # a request that waited for the worker would be answered 200 once the ~1 s job (far
        # longer on a loaded machine) ends: the 503 above is what shows the queue timeout
        assert 0.5 <= elapsed < 0.5 + LAG, elapsed
        t.join(timeout=60)


# ---------------------------------------------------------------------- bounded connections
def _raw(port: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    return s


def _port(base: str) -> int:
    return int(base.rsplit(":", 1)[1])


def _problem_of(raw: bytes) -> tuple[int, dict[str, Any]]:
    head, _, body = raw.partition(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    assert b"content-type: application/problem+json" in head.lower(), head
    return status, json.loads(body)


def test_an_oversized_header_is_refused_431_and_malformed_http_400(bounded):
    base = bounded
    r = httpx.get(base + "/healthz", headers={"X-Big": "a" * 100_000}, timeout=10)
    body = assert_problem(r, 431, "invalid_request")
    assert body["diagnostics"]["max_header_bytes"] == 16384
    r = httpx.get(base + "/healthz", headers={"X-Fine": "a" * 8000}, timeout=10)
    assert r.status_code == 200
    # a head sent in pieces (h11's own bound)
    with _raw(_port(base)) as s:
        s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        for _ in range(5):
            s.sendall(b"X-Piece: " + b"b" * 4000 + b"\r\n")
            time.sleep(0.01)
        status, body = _problem_of(read_until_closed(s))
    assert status == 431 and body["code"] == "invalid_request"
    with _raw(_port(base)) as s:
        s.sendall(b"NOT HTTP AT ALL\r\n\r\n")
        status, body = _problem_of(read_until_closed(s))
    assert status == 400 and body["code"] == "invalid_request"


@pytest.mark.parametrize("sent", [b"", b"GET /healthz HTTP/1.1\r\nHost: x\r\n"],
                         ids=["silent", "partial_head"])
def test_a_connection_without_a_complete_head_is_closed_after_header_timeout(bounded, sent):
    base = bounded
    with _raw(_port(base)) as s:
        s.sendall(sent)
        t0 = time.monotonic()
        assert read_until_closed(s) == b""
        elapsed = time.monotonic() - t0
    # header timeout 1 s; without it the connection stays open until the socket's 10 s
    assert 0.9 <= elapsed < 1.0 + LAG, elapsed


@pytest.mark.parametrize("trickle", [False, True], ids=["stalled", "trickled"])
def test_a_body_that_does_not_arrive_in_time_is_answered_408(bounded, trickle):
    base = bounded
    with _raw(_port(base)) as s:
        s.sendall(b"POST /v1/plans HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                  b"Content-Length: 100\r\n\r\n{")
        t0 = time.monotonic()
        if trickle:  # a byte every 0.2 s: each read is quick, the whole body is not
            s.settimeout(0.2)
            for _ in range(20):
                try:
                    s.sendall(b" ")
                    if s.recv(1, socket.MSG_PEEK):
                        break
                except (TimeoutError, BrokenPipeError, ConnectionResetError):
                    continue
            s.settimeout(10)
        raw = read_until_closed(s)
        elapsed = time.monotonic() - t0
    status, body = _problem_of(raw)
    assert status == 408 and body["code"] == "request_timeout", body
    assert b"connection: close" in raw.lower()
    assert 0.9 <= elapsed < 1.0 + LAG, elapsed  # body timeout 1 s


#: The head of a request answered 413 at once (its Content-Length is past the 1 MiB limit).
_TOO_LONG = (b"POST /v1/plans HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
             b"Content-Length: 50000000\r\n\r\n{")
#: A chunked body that passes the limit after a while (413 once the middleware has read 1 MiB).
_CHUNKED_PAST = (b"POST /v1/plans HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                 b"Transfer-Encoding: chunked\r\n\r\n"
                 + (b"10000\r\n" + b" " * 0x10000 + b"\r\n") * 17 + b"10000\r\n")


def _trickle(socks: list[socket.socket], seconds: float,
             until: Any = None) -> tuple[list[bytes], list[float | None]]:
    """Send a byte every 0.25 s on each socket (a body trickled for ``seconds``, or until
    ``until()`` is true), reading what comes back. Returns what each received and the time,
    after the start, at which the server closed it (None: still open)."""
    got = [b""] * len(socks)
    closed: list[float | None] = [None] * len(socks)
    for s in socks:
        s.setblocking(False)
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds and any(c is None for c in closed):
        if until is not None and until():
            break
        for i, s in enumerate(socks):
            if closed[i] is not None:
                continue
            try:
                while chunk := s.recv(65536):
                    got[i] += chunk
                closed[i] = time.monotonic() - t0  # b"": the server closed it
                continue
            except BlockingIOError:
                pass
            except ConnectionResetError:
                closed[i] = time.monotonic() - t0
                continue
            try:
                s.send(b" ")
            except BlockingIOError:
                pass
            except (BrokenPipeError, ConnectionResetError):
                closed[i] = time.monotonic() - t0
        time.sleep(0.25)
    return got, closed


@pytest.mark.parametrize("head", [_TOO_LONG, _CHUNKED_PAST], ids=["content_length", "chunked"])
def test_a_body_trickled_after_a_413_is_cut_off(bounded, head):
    """Answered 413 before its body is in, the connection is closed about ``body_timeout``
    (1 s here) after the answer however slowly the rest trickles (it stayed open as long as
    the trickle went on, locking out new clients once there were enough)."""
    with _raw(_port(bounded)) as s:
        s.sendall(head)
        (got,), (closed,) = _trickle([s], 20.0)
    status, body = _problem_of(got)
    assert status == 413 and body["code"] == "invalid_request", body
    assert closed is not None and closed < 8.0, closed


@pytest.fixture(scope="module")
def keyed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A server with API keys and :data:`BOUNDS`."""
    yield from _bounded_server(tmp_path_factory, "faults_keyed", PLANNER_API_KEYS="k1")


def test_trickled_bodies_after_a_401_cannot_lock_out_new_clients(keyed):
    """As many keyless clients as the connection cap (40), each answered 401 before its body
    and trickling the body on: once their answers are out they are cut off (about
    ``body_timeout``, 1 s, later) and a new client is served. Before, they held every
    connection for as long as they trickled, and every new client was refused 503."""
    head = (b"POST /v1/plans HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 100000\r\n\r\n{")
    socks = [_raw(_port(keyed)) for _ in range(40)]
    try:
        for s in socks:
            s.sendall(head)
        served: list[float] = []
        t0 = time.monotonic()

        def a_new_client_is_served() -> bool:
            if time.monotonic() - t0 > 0.5 * (len(served) + 1):  # a probe every 0.5 s
                try:
                    r = httpx.get(keyed + "/healthz", timeout=5)
                except httpx.TransportError:
                    return False
                served.append(time.monotonic() - t0)
                return r.status_code == 200
            return False

        got, closed = _trickle(socks, 20.0, until=a_new_client_is_served)
        waited = time.monotonic() - t0
        got2, closed2 = _trickle(socks, 10.0)  # the rest are cut off too
    finally:
        for s in socks:
            s.close()
    answers = [a + b for a, b in zip(got, got2)]
    print(f"\n40 trickled bodies after 401: a new client served {waited:.1f} s after they "
          f"asked; all cut off by {max(c or 99 for c in closed2):.1f} s more")
    assert waited < 10.0, waited
    assert all(c is not None for c in closed2), closed2
    for a in answers:
        status, body = _problem_of(a)
        assert status == 401 and body["code"] == "unauthorized"
    metrics = httpx.get(keyed + "/metrics", timeout=10).text
    assert _metric(metrics, 'planner_connections_closed_total{reason="unread_body"}') >= 40


def test_connections_past_the_cap_are_answered_503_at_once(bounded):
    base = bounded
    socks = [_raw(_port(base)) for _ in range(50)]  # the cap is 40
    try:
        for s in socks:
            s.setblocking(False)
        got = [b""] * len(socks)

        def read() -> int:
            for i, s in enumerate(socks):
                try:
                    got[i] += s.recv(65536)
                except (BlockingIOError, ConnectionResetError):
                    pass
            return sum(1 for g in got if g)

        # the refusals come at once, but on a loaded machine "at once" is when the event loop
        # gets to them: wait for the 10 (LAG at most), then a little more for any 11th
        deadline = time.monotonic() + LAG
        while read() < 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
        read()
        refused = [g for g in got if g]  # (none of the 40 within the cap is answered)
        assert len(refused) == 10, len(refused)
        status, body = _problem_of(refused[0])
        assert status == 503 and body["code"] == "overloaded"
    finally:
        for s in socks:
            s.close()


def test_slow_readers_are_dropped_and_server_memory_stays_bounded(two_workers):
    """8 clients ask for a 5 MB answer each (a plan at 20001 samples) and never read it. Bound:
    while they stall the server holds at most about one answer per stalled client (asserted:
    1.5 x); once ``send_timeout`` (2 s) passes without progress each is dropped, and once all
    are the server process is back within 50 MB of where it started (less than the 8 answers:
    measured 0 MB on an idle machine, 35 MB in one loaded run, cause of the rest not found): the
    answers' memory went back to the system (:mod:`service.memory`; before, glibc kept 5 MB blocks in the heap and a
    server that had dropped 200 such clients stayed at 1 GB).

    Made for a loaded machine: the clients' answers may take long to be computed (a plan at
    20001 samples took 2.5 s on two busy cores), so the test waits until the server has counted
    every client dropped (up to 4 minutes), not a fixed time."""
    base, pid = two_workers
    port = _port(base)
    # the longest time limit the server allows (PLANNER_MAX_TIME_LIMIT, 60 s): the default
    # 10 s ran out at load 10 on 2 cores (504), and how long the plan takes is not the point
    body = json.dumps({**CHEAP, "samples": 20001, "time_limit": 60}).encode()
    dropped_line = 'planner_connections_closed_total{reason="send_timeout"}'
    with httpx.Client(base_url=base, timeout=120) as client:
        _wait_live(client, 2, timeout=120)
        # one answer read in full first: the workers' own memory grows to what such an answer
        # takes once, whoever asks; what is measured below is what slow readers add
        for _ in range(2):
            r = client.post("/v1/plans", content=body,
                            headers={"Content-Type": "application/json"})
            assert r.status_code == 200
        answer_mb = len(r.content) / 1e6
        dropped_before = _metric(client.get("/metrics").text, dropped_line)
    server = psutil.Process(pid)

    def rss_mb() -> float:
        return server.memory_info().rss / 1e6

    before = rss_mb()
    n = 8
    socks = []
    for _ in range(n):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.connect(("127.0.0.1", port))
        s.sendall(b"POST /v1/plans HTTP/1.1\r\nHost: x\r\nContent-Type: application/json"
                  b"\r\nContent-Length: %d\r\n\r\n" % len(body) + body)
        socks.append(s)
    try:
        peak = before
        t0 = time.monotonic()
        with httpx.Client(base_url=base, timeout=30) as client:
            while True:
                peak = max(peak, rss_mb())
                dropped = _metric(client.get("/metrics").text, dropped_line) - dropped_before
                if dropped >= n:
                    break
                assert time.monotonic() - t0 < 240, f"only {dropped} of {n} dropped"
                time.sleep(0.2)
        dropped_after = time.monotonic() - t0
        settle = time.monotonic() + 10.0  # the trim runs about 1 s after the last answer
        while (after := rss_mb()) - before >= 50 and time.monotonic() < settle:
            time.sleep(0.2)
    finally:
        for s in socks:
            s.close()
    print(f"\nslow readers: {n} x {answer_mb:.1f} MB answers; server RSS {before:.0f} MB "
          f"before, peak {peak:.0f}, {after:.0f} after; all dropped {dropped_after:.1f} s "
          f"after they asked")
    assert peak - before < n * 1.5 * answer_mb, peak - before
    assert after - before < 50, (before, peak, after)
    metrics = httpx.get(base + "/metrics", timeout=30).text
    assert 'route="/v1/plans",status="499"}' in metrics  # counted as not answered


def _metric(text: str, prefix: str) -> float:
    """The value of the sample line starting with ``prefix`` (0 when absent)."""
    for line in text.splitlines():
        if line.startswith(prefix):
            return float(line.split()[-1])
    return 0.0


def test_a_client_that_leaves_takes_its_queued_job_with_it(two_workers):
    base, _ = two_workers
    # ~20 s of replays (this module's server allows that many runs): past the busy clients'
    # 10 s on any machine; the jobs stop when those clients leave
    long_job = {**SLOWISH, "random": {"count": 1000, "spread": 0.01, "seed": 3}}

    def post(path: str, body: dict[str, Any], timeout: float) -> None:
        with pytest.raises(httpx.TimeoutException):  # the client gives up
            httpx.post(base + path, json=body, timeout=timeout)

    with httpx.Client(base_url=base, timeout=30) as client:
        _wait_live(client, 2)
        gone = 'planner_requests_cancelled_total{reason="client_gone"}'
        plans_499 = 'planner_http_requests_total{method="POST",route="/v1/plans",status="499"}'
        metrics = client.get("/metrics").text
        before = _metric(metrics, gone), _metric(metrics, plans_499)
        # the busy clients stay past the leavers (5 s), and leave before their jobs end
        busy = [threading.Thread(target=post, args=("/v1/robustness", long_job, 10.0))
                for _ in range(2)]
        for t in busy:
            t.start()
        deadline = time.monotonic() + 20
        while client.get("/readyz").json()["idle"] > 0:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        # 5 s to give up: time for six threads to connect and queue on a loaded machine
        leavers = [threading.Thread(target=post, args=("/v1/plans", CHEAP, 5.0))
                   for _ in range(6)]
        for t in leavers:
            t.start()
        deadline = time.monotonic() + 4.5
        while (waiting := client.get("/readyz").json()["waiting"]) < 6:
            assert time.monotonic() < deadline, waiting
            time.sleep(0.02)
        # (polling while they wait: an idle keep-alive connection is closed by the server
        # after keep_alive_timeout, 5 s, about as long as the leavers wait, and a request sent
        # as it closes is reset)
        while any(t.is_alive() for t in leavers):
            client.get("/readyz")
            time.sleep(0.5)
        deadline = time.monotonic() + LAG  # the server notices each leaver as its loop runs
        while (ready := client.get("/readyz").json())["waiting"] and time.monotonic() < deadline:
            time.sleep(0.05)
        # the jobs left the queue, while the busy ones (their clients stay 10 s) still run
        assert ready["waiting"] == 0 and ready["idle"] == 0, ready
        metrics = client.get("/metrics").text
        assert _metric(metrics, gone) >= before[0] + 6
        assert _metric(metrics, plans_499) == before[1] + 6
        for t in busy:
            t.join(timeout=30)


def test_a_client_that_leaves_stops_its_running_job_where_the_method_can(two_workers):
    """Robustness replays check their deadline between runs: a job of ~20 s (1,000 replays of
    ~20 ms on an idle machine, several times that on a loaded one) whose client gives up after
    0.5 s frees its worker at the next check, not 20 s later."""
    base, _ = two_workers
    long_job = {**SLOWISH, "random": {"count": 1000, "spread": 0.01, "seed": 3}}
    with httpx.Client(base_url=base, timeout=30) as client:
        _wait_live(client, 2)
        before = client.get("/readyz").json()["restarts"]
        t0 = time.monotonic()
        for _ in range(2):
            with pytest.raises(httpx.TimeoutException):
                httpx.post(base + "/v1/robustness", json=long_job, timeout=0.5)
        deadline = time.monotonic() + 10  # half the jobs' length on an idle machine
        while (ready := client.get("/readyz").json())["idle"] < 2:
            assert time.monotonic() < deadline, ready
            time.sleep(0.05)
        freed = time.monotonic() - t0
        assert ready["restarts"] == before  # stopped by the job itself, no worker killed
        r = client.post("/v1/plans", json=CHEAP)
        assert r.status_code == 200, r.text
    print(f"\ntwo ~20 s jobs whose clients left after 0.5 s each: workers free after "
          f"{freed:.1f} s")
    assert freed < 11.0


def test_a_client_that_leaves_mid_body_is_counted_499_not_400(two_workers):
    base, _ = two_workers
    with _raw(_port(base)) as s:
        s.sendall(b"POST /v1/sweeps HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                  b"Content-Length: 100\r\n\r\n{\"start\":")
        time.sleep(0.1)
    deadline = time.monotonic() + LAG  # counted once the event loop sees the connection go
    while True:
        metrics = httpx.get(base + "/metrics", timeout=10).text
        if 'route="/v1/sweeps",status="' in metrics or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert 'route="/v1/sweeps",status="499"} 1.0' in metrics
    assert 'route="/v1/sweeps",status="400"}' not in metrics


# ---------------------------------------------------------------------- shutdown
def test_a_shutdown_that_cannot_drain_answers_503_shutting_down(tmp_path):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PLANNER_")}
    env.update({"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port), "PLANNER_WORKERS": "1",
                "PLANNER_SHUTDOWN_TIMEOUT": "3", "PLANNER_LOG_LEVEL": "info"})
    log_path = tmp_path / "server.log"
    answers: list[httpx.Response | BaseException] = []

    def send() -> None:
        try:
            answers.append(httpx.post(base + "/v1/robustness", json=SLOWISH, timeout=60))
        except httpx.HTTPError as exc:
            answers.append(exc)

    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=env,
                                stdout=log, stderr=subprocess.STDOUT)
        try:
            with httpx.Client(base_url=base, timeout=10) as client:
                deadline = time.monotonic() + 120
                while True:
                    assert proc.poll() is None
                    try:
                        if client.get("/readyz").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass
                    assert time.monotonic() < deadline
                    time.sleep(0.1)
                senders = [threading.Thread(target=send) for _ in range(5)]  # ~8 s of work
                for t in senders:
                    t.start()
                while client.get("/readyz").json()["waiting"] < 4:
                    assert time.monotonic() < deadline
                    time.sleep(0.01)
            t0 = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            for t in senders:
                t.join(timeout=30)
            code = proc.wait(timeout=30)
            stopped = time.monotonic() - t0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
    log_text = log_path.read_text(errors="replace")
    assert all(isinstance(a, httpx.Response) for a in answers), answers
    statuses = sorted(a.status_code for a in answers if isinstance(a, httpx.Response))
    print(f"\nshutdown with ~8 s of work and a 3 s timeout: {statuses}, stopped in "
          f"{stopped:.1f} s")
    assert len(statuses) == 5 and set(statuses) <= {200, 503} and 503 in statuses, statuses
    for a in answers:
        assert isinstance(a, httpx.Response)
        if a.status_code == 503:
            assert_problem(a, 503, "shutting_down")
            assert a.headers["retry-after"] == "1" and a.headers["connection"] == "close"
    # the 503s above show the deadline; this bound catches a server that stays on after it
    # (idle machine: 2.6-2.8 s; load 13 on 2 cores: 8.1 s, the exit stopping the workers after
    # the answers; draining the work instead takes 5 jobs' time, ~50 s at that load)
    assert code == 0 and stopped < 3.0 + 4 * LAG, log_text[-2000:]
    assert not re.search(r'"status": ?500\b', log_text), log_text[-3000:]
    assert "Traceback" not in log_text and "Exception in ASGI" not in log_text, log_text[-3000:]
    assert re.search(r'"status": ?503\b', log_text)  # the access log counts them as answered


# ---------------------------------------------------------------------- smaller items
def test_two_different_api_keys_are_refused_by_middleware_and_route_alike(keyed_client):
    client, (k1, k2) = keyed_client, KEYS[:2]
    for path, body in (("/v1/plans", CHEAP), ("/v1/sweeps", {})):
        r = client.post(path, json=body, headers=[("X-API-Key", k1), ("X-API-Key", k2)])
        assert_problem(r, 401, "unauthorized")
        r = client.post(path, json=body, headers=[("Authorization", f"Bearer {k1}"),
                                                  ("Authorization", "Bearer zz")])
        assert_problem(r, 401, "unauthorized")
    r = client.post("/v1/plans", json=CHEAP, headers=[("X-API-Key", k1), ("X-API-Key", k1)])
    assert r.status_code == 200, r.text


def test_the_robustness_time_limit_is_not_capped_by_the_plans_default():
    schemas = build_schemas(Limits())
    req = schemas.RobustnessRequest.model_validate(
        {"plan": CHEAP, "random": {"count": 2, "spread": 0.01, "seed": 1}, "time_limit": 30})
    assert req.to_library()["plan"]["time_limit"] == 30
    req = schemas.RobustnessRequest.model_validate(
        {"plan": {**CHEAP, "time_limit": 5}, "random": {"count": 2, "spread": 0.01, "seed": 1},
         "time_limit": 30})
    assert req.to_library()["plan"]["time_limit"] == 5


def test_the_workers_log_of_an_unexpected_failure_names_the_request(caplog):
    from service import jobs
    with caplog.at_level(logging.ERROR, logger="service.worker"):
        out = jobs.run_job("transform", {"direction": "to_chained", "points": []}, "req-42")
    assert out["ok"] is False and out["error"]["code"] == "numerical_failure"
    (record,) = [r for r in caplog.records if "failed unexpectedly" in r.getMessage()]
    assert record.request_id == "req-42"


def _wait_live(client: Any, n: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        ready = client.get("/readyz").json()
        if ready["live"] >= n and ready["idle"] >= n:
            return
        assert time.monotonic() < deadline, ready
        time.sleep(0.05)


def test_a_worker_stopped_between_pings_never_holds_a_request():
    """Pings too rare to notice (60 s): a worker stopped while idle is found stopped when a
    request takes it, replaced, and the request runs on the other worker at once (it waited
    its whole time limit before: 504 after 10.5 s)."""
    with running_app(workers=2, queue_size=8, worker_ping_interval=60,
                     worker_ping_timeout=0.3) as client:
        pool = client.app.state.pool
        _wait_live(client, 2)
        stopped = pool.pids()[0]
        os.kill(stopped, signal.SIGSTOP)
        try:
            for _ in range(4):  # each worker is taken in turn: the stopped one among them
                t0 = time.perf_counter()
                r = client.post("/v1/plans", json={**CHEAP, "time_limit": 20})
                assert r.status_code == 200, r.text
                assert time.perf_counter() - t0 < 10.0
            assert stopped not in pool.pids()
            metrics = client.get("/metrics").text
            assert 'planner_worker_restarts_total{reason="unresponsive"} 1.0' in metrics
        finally:
            try:
                os.kill(stopped, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_job_whose_worker_is_stopped_under_it_runs_on_another_worker():
    """A worker stopped while it runs a job (~1 s of replays on an idle machine): the job is
    given to the other worker within about ``worker_ping_timeout`` and answered 200, not 504
    after its time limit (60 s: at load 14 on 2 cores the job's second run took more than 20)."""
    with running_app(workers=2, queue_size=8, worker_ping_interval=60,
                     worker_ping_timeout=0.3) as client:
        pool = client.app.state.pool
        _wait_live(client, 2)
        before = set(pool.pids())
        answer: list[Any] = []
        t = threading.Thread(target=lambda: answer.append(
            client.post("/v1/robustness", json=IN_FLIGHT)))
        t0 = time.perf_counter()
        t.start()
        deadline = time.monotonic() + 20
        while pool.stats().idle > 1:  # a worker has the job
            assert time.monotonic() < deadline
            time.sleep(0.01)
        busy = [w.process.pid for w in pool._all if w.busy]
        assert len(busy) == 1
        os.kill(busy[0], signal.SIGSTOP)
        try:
            t.join(timeout=60)
            elapsed = time.perf_counter() - t0
            (r,) = answer
            assert r.status_code == 200, r.text  # (504 after the whole time limit before)
            print(f"\nworker stopped under a job: 200 after {elapsed:.1f} s")
            assert busy[0] not in pool.pids() and busy[0] in before
        finally:
            try:
                os.kill(busy[0], signal.SIGKILL)
            except ProcessLookupError:
                pass
