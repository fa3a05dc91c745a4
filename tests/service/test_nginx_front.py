"""The compose load balancer (``deploy/nginx.conf``) keeps the service's error contract.

Debian's nginx runs the committed file, with only the upstream address and the listen port
substituted, in front of a live ``python -m service`` and in front of nothing (a closed port):
nginx's own failures are ``application/problem+json`` documents with the service's keys, its
version is not shown, ``/metrics`` is not served, and a plan passes through unchanged.

Set-up: nginx is installed with apt-get (``nginx-light``) when missing and running as root. When
it cannot be had, the tests fail in CI (``CI`` set) and are skipped elsewhere.
"""

from __future__ import annotations

import contextlib
import signal
import http.client
import json
import os
import re
import shutil
import socket
import subprocess
import threading
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import pytest

from svc_support import (DEG, ROOT, WORKED, free_port, read_until_closed, server_process,
                         stop_process)

CONF = ROOT / "deploy" / "nginx.conf"
PROBLEM_KEYS = {"type", "title", "status", "code", "detail", "field", "diagnostics",
                "request_id"}


def _unavailable(why: str) -> None:
    if os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no"):
        pytest.fail(f"the nginx test cannot run in CI: {why}")
    pytest.skip(why)


def nginx_path() -> str:
    """Debian's nginx, installed with apt-get first when missing (as root)."""
    found = shutil.which("nginx") or shutil.which("nginx", path="/usr/sbin:/sbin")
    if found:
        return found
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        _unavailable("nginx is not installed and cannot be (needs root and apt-get)")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "-q", "--no-install-recommends",
               "-o", "DPkg::Lock::Timeout=120", "nginx-light"]
    done = None
    try:
        for attempt in range(3):
            if attempt:  # the package lists may be stale
                subprocess.run(["apt-get", "update", "-q", "-o", "DPkg::Lock::Timeout=120"],
                               capture_output=True, timeout=300, env=env,
                               stdin=subprocess.DEVNULL)
            done = subprocess.run(install, capture_output=True, text=True, timeout=600, env=env,
                                  stdin=subprocess.DEVNULL)
            if done.returncode == 0:
                break
    except subprocess.TimeoutExpired:
        _unavailable("installing nginx with apt-get timed out")
    found = shutil.which("nginx", path="/usr/sbin:/usr/bin:/sbin:/bin")
    if not found:
        tail = (done.stdout + done.stderr)[-2000:] if done is not None else ""
        _unavailable(f"apt-get could not install nginx:\n{tail}")
    return str(found)


def site_config(upstream_ports: int | list[int], listen_port: int,
                read_timeout: str | None = None) -> str:
    """The committed server config with the upstream(s) and the listen address for this machine
    (and, to provoke a 504 quickly, a shorter upstream read timeout). Each upstream port gets the
    committed ``server`` line with its parameters (as Docker's DNS gives one per replica)."""
    text = CONF.read_text(encoding="utf-8")
    ports = [upstream_ports] if isinstance(upstream_ports, int) else upstream_ports
    if read_timeout is not None:
        text, n = re.subn(r"proxy_read_timeout \d+s;", f"proxy_read_timeout {read_timeout};", text)
        assert n == 1, "deploy/nginx.conf changed shape: adapt the test"
    text, upstreams = re.subn(
        r"server planner:8000( [^;]*)?;",
        lambda m: "\n    ".join(f"server 127.0.0.1:{p}{m.group(1) or ''};" for p in ports), text)
    text, listens = re.subn(r"listen 80;", f"listen 127.0.0.1:{listen_port};", text)
    assert upstreams == 1 and listens == 1, "deploy/nginx.conf changed shape: adapt the test"
    return text


@contextlib.contextmanager
def nginx_front(directory: Path, upstream_port: int | list[int],
                read_timeout: str | None = None) -> Iterator[int]:
    """nginx (foreground) with the site config in front of 127.0.0.1:``upstream_port`` (each
    of them, for a list)."""
    exe = nginx_path()
    port = free_port()
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "site.conf").write_text(site_config(upstream_port, port, read_timeout),
                                         encoding="utf-8")
    temp = "".join(f"{kind}_temp_path {directory / kind};\n"
                   for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    # the site file is included in the http block, as the nginx image does with conf.d/*.conf
    (directory / "nginx.conf").write_text(
        ("user root;\n" if os.geteuid() == 0 else "")
        + f"worker_processes 1;\npid {directory / 'nginx.pid'};\n"
          f"error_log {directory / 'error.log'} info;\nevents {{ worker_connections 64; }}\n"
          f"http {{\n access_log off;\n{temp} include {directory / 'site.conf'};\n}}\n",
        encoding="utf-8")
    argv = [exe, "-p", str(directory), "-c", str(directory / "nginx.conf"),
            "-g", "daemon off;"]
    check = subprocess.run(argv[:-2] + ["-t"], capture_output=True, text=True, timeout=30)
    assert check.returncode == 0, check.stderr
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 20
        while True:
            try:
                with contextlib.closing(http.client.HTTPConnection("127.0.0.1", port,
                                                                   timeout=2)) as c:
                    c.connect()
                break
            except OSError:
                assert proc.poll() is None, (directory / "error.log").read_text()
                assert time.monotonic() < deadline, "nginx did not start listening"
                time.sleep(0.05)
        yield port
    finally:
        stop_process(proc, 10.0)


def request(port: int, method: str, path: str, body: bytes | None = None,
            headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    with contextlib.closing(http.client.HTTPConnection("127.0.0.1", port, timeout=60)) as c:
        c.request(method, path, body=body, headers=headers or {})
        r = c.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()


def problem(status: int, headers: dict[str, str], body: bytes, expected: int,
            code: str) -> dict[str, Any]:
    assert status == expected, body[:300]
    assert headers["content-type"].startswith("application/problem+json"), headers
    doc = json.loads(body)
    assert set(doc) == PROBLEM_KEYS, doc
    assert doc["status"] == expected and doc["code"] == code, doc
    assert doc["type"].endswith("/" + code) and doc["title"] and doc["detail"]
    assert b"<html" not in body.lower()
    return doc


def no_version(headers: dict[str, str]) -> None:
    # server_tokens off leaves "Server: nginx"; removing it needs a module the image lacks
    assert not re.search(r"nginx/\d", headers.get("server", "")), headers


@pytest.fixture(scope="module")
def upstream(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    port = free_port()
    log = tmp_path_factory.mktemp("nginx-upstream") / "server.log"
    env = {"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port), "PLANNER_WORKERS": "1"}
    with server_process([sys.executable, "-m", "service"], env, port, log):
        yield port


@pytest.fixture(scope="module")
def front(upstream: int, tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    with nginx_front(tmp_path_factory.mktemp("nginx-front"), upstream) as port:
        yield port


@pytest.fixture(scope="module")
def front_of_nothing(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    closed = free_port()  # nothing listens there
    with nginx_front(tmp_path_factory.mktemp("nginx-nothing"), closed) as port:
        yield port


def test_a_plan_passes_through(front):
    body = json.dumps({**WORKED, "phi_change": 34 * DEG, "samples": 5}).encode()
    status, headers, raw = request(front, "POST", "/v1/plans", body,
                                   {"Content-Type": "application/json",
                                    "X-Request-ID": "lb-test-1"})
    assert status == 200, raw[:300]
    assert json.loads(raw)["status"] == "success"
    assert headers["x-request-id"] == "lb-test-1"
    no_version(headers)


def test_the_services_own_problems_pass_through(front):
    body = json.dumps({"start": [10, 10, 10], "goal": [30, 30, 30]}).encode()
    status, headers, raw = request(front, "POST", "/v1/plans", body,
                                   {"Content-Type": "application/json"})
    doc = problem(status, headers, raw, 422, "invalid_request")
    assert "looks like degrees" in doc["detail"]


def test_an_oversized_body_is_a_413_problem(front):
    status, headers, raw = request(front, "POST", "/v1/plans", b"x" * (1024 * 1024 + 10),
                                   {"Content-Type": "application/json",
                                    "X-Request-ID": "lb-test-413"})
    doc = problem(status, headers, raw, 413, "invalid_request")
    assert doc["request_id"] == "lb-test-413"
    assert "1048576" in doc["detail"]
    no_version(headers)


@pytest.mark.parametrize("path", ["/metrics", "/%6detrics", "//metrics", "/metrics/"])
def test_metrics_are_not_public(front, path):
    status, headers, raw = request(front, "GET", path)
    problem(status, headers, raw, 404, "not_found")
    assert b"planner_" not in raw
    no_version(headers)


def test_nothing_behind_is_a_502_problem(front_of_nothing):
    status, headers, raw = request(front_of_nothing, "GET", "/v1/robots/default",
                                   headers={"X-Request-ID": "bad id with spaces"})
    doc = problem(status, headers, raw, 502, "overloaded")
    assert headers.get("retry-after") == "1"
    # an id the service would not accept is replaced, never written into the document
    assert doc["request_id"] and " " not in doc["request_id"]
    no_version(headers)
    status, headers, raw = request(front_of_nothing, "POST", "/v1/plans",
                                   json.dumps(WORKED).encode(),
                                   {"Content-Type": "application/json"})
    problem(status, headers, raw, 502, "overloaded")


def test_an_upstream_too_slow_is_a_504_problem(tmp_path):
    # a "replica" that accepts connections and never answers
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)
        with nginx_front(tmp_path / "nginx-slow", silent.getsockname()[1], "1s") as port:
            status, headers, raw = request(port, "GET", "/v1/robots/default")
    doc = problem(status, headers, raw, 504, "timeout")
    assert "100 s" in doc["detail"]  # the committed timeout, which the test shortened
    no_version(headers)


def test_every_error_nginx_makes_has_a_problem_page():
    text = CONF.read_text(encoding="utf-8")
    pages = {status: name
             for statuses, name in re.findall(r"error_page ([\d ]+) (@\w+|/[\w./]+);", text)
             for status in statuses.split()}
    assert set(pages) == {"400", "494", "404", "405", "408", "413", "414", "501", "502", "503",
                          "504", "505"}
    for status, name in pages.items():
        if status == "494":  # nginx's own code for headers too large, answered as 400
            status = "400"
        where = name if name.startswith("@") else "= " + re.escape(name)
        block = re.search(r"location " + where + r" \{(.*?)\n    \}", text, re.S)
        assert block, name
        assert "default_type application/problem+json;" in block.group(1)
        returned = re.search(r"return (\d+) '(.*)\\n';", block.group(1))
        assert returned and returned.group(1) == status
        doc = json.loads(returned.group(2).replace("$planner_request_id", "id"))
        assert set(doc) == PROBLEM_KEYS and doc["status"] == int(status)
    assert re.search(r"^server_tokens off;", text, re.M)


# ---------------------------------------------------------------------- nginx's own refusals
@pytest.mark.parametrize("raw, status", [
    (b"NOT HTTP AT ALL\r\n\r\n", 400),
    (b"GET /healthz HTTP/1.1\r\n\r\n", 400),  # no Host
    (b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 20000 + b"\r\n\r\n", 400),
    (b"GET /" + b"a" * 20000 + b" HTTP/1.1\r\nHost: x\r\n\r\n", 414),
    (b"TRACE / HTTP/1.1\r\nHost: x\r\n\r\n", 405),
    (b"POST /v1/plans HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: gzip\r\n\r\n", 501),
    (b"GET /healthz HTTP/2.5\r\nHost: x\r\n\r\n", 505),
    (b"GET /.problem/400 HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n", 404),  # internal pages stay so
], ids=["garbage", "no_host", "header_too_large", "uri_too_long", "trace", "transfer_coding",
        "version", "internal_page"])
def test_nginx_refusals_are_problem_documents(front_of_nothing, raw, status):
    """What nginx refuses itself, before any replica, is a problem document (it was HTML)."""
    with socket.create_connection(("127.0.0.1", front_of_nothing), timeout=30) as s:
        s.sendall(raw)
        got = read_until_closed(s)
    head, _, body = got.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v.strip() for k, _, v in (li.partition(":") for li in lines[1:])}
    code = {404: "not_found", 405: "method_not_allowed"}.get(status, "invalid_request")
    problem(int(lines[0].split()[1]), headers, body, status, code)
    no_version(headers)


# ---------------------------------------------------------------------- several replicas
#: A stand-in replica: answers 503 ``overloaded`` (Retry-After: 1) while the file given as its
#: second argument exists, 200 otherwise; the body names the replica (its first argument).
FAKE_REPLICA = r"""
import json, os, sys
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

name, busy_flag, port = sys.argv[1], sys.argv[2], int(sys.argv[3])

class Replica(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def answer(self):
        length = int(self.headers.get("Content-Length") or 0)
        self.rfile.read(length)
        if os.path.exists(busy_flag):
            status, body = 503, {"type": "https://chained-planner.invalid/problems/overloaded",
                                 "title": "Service overloaded", "status": 503,
                                 "code": "overloaded", "detail": "busy " + name, "field": None,
                                 "diagnostics": {"retry_after": 1}, "request_id": "x"}
            kind = "application/problem+json"
        else:
            status, body, kind = 200, {"replica": name}, "application/json"
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(data)))
        if status == 503:
            self.send_header("Retry-After", "1")
        self.end_headers()
        self.wfile.write(data)

    do_GET = do_POST = answer

    def log_message(self, *args):
        pass

ThreadingHTTPServer.daemon_threads = True
ThreadingHTTPServer(("127.0.0.1", port), Replica).serve_forever()
"""


@contextlib.contextmanager
def fake_replicas(busy_flag: Path, count: int = 2) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``count`` stand-in replicas (:data:`FAKE_REPLICA`) listening, busy while ``busy_flag``
    exists; yields (port, process) pairs."""
    procs, ports = [], []
    try:
        for i in range(count):
            port = free_port()
            procs.append(subprocess.Popen([sys.executable, "-c", FAKE_REPLICA, f"r{i}",
                                           str(busy_flag), str(port)]))
            ports.append(port)
        for port, proc in zip(ports, procs):
            deadline = time.monotonic() + 30
            while True:
                try:
                    socket.create_connection(("127.0.0.1", port), timeout=2).close()
                    break
                except OSError:
                    assert proc.poll() is None and time.monotonic() < deadline
                    time.sleep(0.05)
        yield list(zip(ports, procs))  # type: ignore[misc]
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGCONT)
                proc.kill()
                proc.wait(timeout=10)


def test_a_burst_of_503s_does_not_take_healthy_replicas_out(tmp_path):
    """Two replicas answer 503 ``overloaded`` to a burst of 60 requests (busy), then 200 (no
    longer busy). Their 503s reach the client as they are (Retry-After kept), and right after
    the burst every request is answered 200: no replica was marked failed. Before, each 503
    marked its replica failed (``proxy_next_upstream http_503`` with the default
    ``max_fails=1``): 502 to everyone for the next 10 s while both replicas were healthy."""
    busy = tmp_path / "busy"
    busy.touch()
    with fake_replicas(busy) as replicas, \
            nginx_front(tmp_path / "nginx-503", [p for p, _ in replicas]) as port:
        during = []
        for _ in range(60):
            status, headers, raw = request(port, "POST", "/v1/plans", b"{}",
                                           {"Content-Type": "application/json"})
            during.append(status)
            if status == 503:
                problem(status, headers, raw, 503, "overloaded")
                assert headers.get("retry-after") == "1"
        busy.unlink()
        after = [request(port, "POST", "/v1/plans", b"{}",
                         {"Content-Type": "application/json"}) for _ in range(20)]
    print(f"\n503 burst through nginx: {len(during)} requests during it, statuses "
          f"{sorted(set(during))}; after it {[a[0] for a in after].count(200)} of 20 answered 200")
    assert during and set(during) == {503}, during
    assert [a[0] for a in after] == [200] * 20, [(a[0], a[2][:80]) for a in after]
    assert {json.loads(a[2])["replica"] for a in after} == {"r0", "r1"}  # both in use


def test_a_stopped_replica_is_avoided_and_its_requests_go_elsewhere(tmp_path):
    """One of two replicas is stopped (SIGSTOP: its connections are accepted by the kernel,
    nothing answers). Requests sent meanwhile are answered by the other one at once (fewest
    requests in progress), and those that reached the stopped one are passed to the other
    after ``proxy_read_timeout`` (shortened to 6 s here; 100 s as committed) instead of
    timing out. Before, every other request went to the stopped replica and waited the whole
    read timeout (180 s), then 504."""
    with fake_replicas(tmp_path / "never") as replicas, \
            nginx_front(tmp_path / "nginx-stopped", [p for p, _ in replicas], "6s") as port:
        os.kill(replicas[1][1].pid, signal.SIGSTOP)
        stuck: list[tuple[int, bytes, float]] = []

        def send() -> None:
            t0 = time.monotonic()
            status, _, raw = request(port, "POST", "/v1/plans", b"{}",
                                     {"Content-Type": "application/json"})
            stuck.append((status, raw, time.monotonic() - t0))

        first = [threading.Thread(target=send) for _ in range(4)]
        for t in first:
            t.start()
        time.sleep(0.5)  # some of them wait on the stopped replica
        later = []
        for _ in range(10):
            # "at once": well before the read timeout (6 s) after which a request that went
            # to the stopped replica is passed on; 4 s leaves room for a loaded machine
            with contextlib.closing(http.client.HTTPConnection("127.0.0.1", port,
                                                               timeout=4.0)) as c:
                try:
                    c.request("GET", "/v1/robots/default")
                    r = c.getresponse()
                    later.append((r.status, json.loads(r.read())["replica"]))
                except (TimeoutError, OSError) as exc:
                    later.append((0, repr(exc)))
        for t in first:
            t.join(timeout=60)
    print(f"\nstopped replica behind nginx: later requests {later}; the first four "
          f"{[(s, round(t, 1)) for s, _, t in stuck]}")
    assert later == [(200, "r0")] * 10, later
    assert len(stuck) == 4 and all(s == 200 and json.loads(raw)["replica"] == "r0"
                                   for s, raw, _ in stuck), stuck
