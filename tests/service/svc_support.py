"""Helpers shared by the service tests (imported as ``svc_support``; fixtures live in conftest).

Every app here is built from :func:`service.settings.default_settings` (the environment's
``PLANNER_*`` variables are ignored) with small worker counts, so the suite fits two cores.
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import subprocess
import time
import urllib.request
import warnings
from pathlib import Path
from typing import Any, Iterator

with warnings.catch_warnings():  # starlette suggests httpx2; httpx works
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from service.main import create_app
from service.settings import default_settings

ROOT = Path(__file__).resolve().parents[2]
DEG = math.pi / 180.0

#: Seconds a loaded machine may add to a timer of a server's event loop, to the answer's way
#: back and to the test's own wake-ups: 2 cores at load 10-12 give a process about a sixth of
#: a core (importing matplotlib took 6.2 s for 1.0 s of CPU). A test adds it to a bound only
#: where the bound stays below whatever else would end the wait (uvicorn's keep-alive of 5 s,
#: a test socket's 10 s, a busy job's length) or where another assertion shows the mechanism
#: (the status, the restarts count); the figures measured on an idle machine are in
#: docs/reliability.md.
LAG = 2.5

#: The API keys and the CORS origin of the shared keyed app (``keyed_client`` in conftest).
KEYS = ["k-one-7d1e", "k-two-90fa", "k-three-c3b2"]
ORIGIN = "http://ui.example.test"

#: The paper's 3-joint worked example (NOTES §5): 10 deg -> 30 deg on every joint.
WORKED = {"start": [10 * DEG] * 3, "goal": [30 * DEG] * 3, "method": "polynomial",
          "objective": "tp_then_da"}


def wait_ready(client: TestClient, timeout: float = 120.0) -> None:
    """Poll ``/readyz`` until the worker pool has warmed up."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if client.get("/readyz").status_code == 200:
            return
        time.sleep(0.05)
    raise AssertionError("the worker pool did not become ready")


@contextlib.contextmanager
def running_app(**overrides: Any) -> Iterator[TestClient]:
    """A TestClient over an app with ``overrides`` applied to the default settings, ready."""
    app = create_app(default_settings(**overrides))
    with TestClient(app, raise_server_exceptions=False) as client:
        wait_ready(client)
        yield client


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def server_process(argv: list[str], env: dict[str, str], port: int, log_path: Path,
                   timeout: float = 120.0) -> Iterator[str]:
    """Run ``argv`` (a server listening on 127.0.0.1:``port``) until it answers ``/readyz``.

    Yields the base URL; the process is stopped (SIGTERM, then SIGKILL) afterwards.
    """
    full_env = {k: v for k, v in os.environ.items() if not k.startswith("PLANNER_")}
    full_env.update(env)
    base = f"http://127.0.0.1:{port}"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(argv, cwd=ROOT, env=full_env, stdout=log,
                                stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + timeout
            while True:
                if proc.poll() is not None:
                    raise AssertionError(f"server exited with {proc.returncode}:\n"
                                         + log_path.read_text(errors="replace")[-3000:])
                try:
                    with urllib.request.urlopen(base + "/readyz", timeout=2) as r:
                        if r.status == 200:
                            break
                except OSError:
                    pass
                if time.monotonic() > deadline:
                    raise AssertionError("server did not become ready:\n"
                                         + log_path.read_text(errors="replace")[-3000:])
                time.sleep(0.1)
            yield base
        finally:
            stop_process(proc, 20.0)


def stop_process(proc: subprocess.Popen[Any], grace: float) -> None:
    """SIGTERM ``proc``; SIGKILL it if it has not exited ``grace`` seconds later; reap it."""
    proc.terminate()
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


def read_until_closed(sock: socket.socket) -> bytes:
    """Everything the peer sends on ``sock`` until it closes the connection (a reset ends it
    too: a server that drops a connection with unread data resets it)."""
    out = b""
    try:
        while chunk := sock.recv(65536):
            out += chunk
    except ConnectionResetError:
        pass
    return out


def assert_problem(response: Any, status: int, code: str) -> dict[str, Any]:
    """Check a problem+json answer and return its body."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["code"] == code, body
    assert body["status"] == status
    for key in ("type", "title", "detail", "diagnostics"):
        assert key in body
    for leak in ("Traceback", str(ROOT), "site-packages", ".py\", line"):
        assert leak not in response.text
    return body


def same_json(a: object, b: object, rel: float = 1e-12, path: str = "",
              abs_tol: float = 1e-12) -> list[str]:
    """Where two JSON documents differ: the same structure, keys, strings, integers, booleans
    and nulls, and floats equal within ``rel`` of the larger magnitude plus ``abs_tol`` (the
    values are radians and seconds of order 1; small ones, differences of such, carry their
    absolute rounding).
    The service's workers prove with the compiled quadrature, a library process that did not
    opt in with numpy's: the same sums in another order, 1e-15 apart."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for k in a for d in same_json(a[k], b[k], rel, f"{path}.{k}", abs_tol)]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: lengths {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b))
                for d in same_json(x, y, rel, f"{path}[{i}]", abs_tol)]
    if isinstance(a, float) or isinstance(b, float):
        if isinstance(a, bool) or isinstance(b, bool) or not isinstance(a, (int, float)) \
                or not isinstance(b, (int, float)):
            return [f"{path}: {a!r} != {b!r}"]
        if abs(a - b) > rel * max(abs(a), abs(b)) + abs_tol:
            return [f"{path}: {a!r} != {b!r}"]
        return []
    return [] if a == b and type(a) is type(b) else [f"{path}: {a!r} != {b!r}"]
