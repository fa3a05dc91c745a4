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
import http.client
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import pytest

from svc_support import DEG, ROOT, WORKED, free_port, server_process

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


def site_config(upstream_port: int, listen_port: int, read_timeout: str | None = None) -> str:
    """The committed server config with the upstream and the listen address for this machine
    (and, to provoke a 504 quickly, a shorter upstream read timeout)."""
    text = CONF.read_text(encoding="utf-8")
    if read_timeout is not None:
        text, n = re.subn(r"proxy_read_timeout \d+s;", f"proxy_read_timeout {read_timeout};", text)
        assert n == 1, "deploy/nginx.conf changed shape: adapt the test"
    text, upstreams = re.subn(r"server planner:8000;", f"server 127.0.0.1:{upstream_port};",
                              text)
    text, listens = re.subn(r"listen 80;", f"listen 127.0.0.1:{listen_port};", text)
    assert upstreams == 1 and listens == 1, "deploy/nginx.conf changed shape: adapt the test"
    return text


@contextlib.contextmanager
def nginx_front(directory: Path, upstream_port: int,
                read_timeout: str | None = None) -> Iterator[int]:
    """nginx (foreground) with the site config in front of 127.0.0.1:``upstream_port``."""
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
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


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
    assert "180 s" in doc["detail"]  # the committed timeout, which the test shortened
    no_version(headers)


def test_every_error_nginx_makes_has_a_problem_page():
    text = CONF.read_text(encoding="utf-8")
    pages = dict(re.findall(r"error_page (\d+) (@\w+);", text))
    assert set(pages) == {"413", "502", "503", "504"}
    for status, name in pages.items():
        block = re.search(r"location " + name + r" \{(.*?)\n    \}", text, re.S)
        assert block, name
        assert "default_type application/problem+json;" in block.group(1)
        returned = re.search(r"return (\d+) '(.*)\\n';", block.group(1))
        assert returned and returned.group(1) == status
        doc = json.loads(returned.group(2).replace("$planner_request_id", "id"))
        assert set(doc) == PROBLEM_KEYS and doc["status"] == int(status)
    assert re.search(r"^server_tokens off;", text, re.M)
