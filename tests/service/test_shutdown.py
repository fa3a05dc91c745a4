"""Graceful shutdown: on SIGTERM the server (``python -m service``) stops accepting connections,
lets the requests in flight finish and answer completely, then stops its workers and exits 0.
SIGTERM to the server alone (docker, Kubernetes) and to its whole process group (Ctrl-C-like,
systemd): the workers ignore it, the server decides when they stop."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from typing import Any

import httpx
import psutil
import pytest

from svc_support import DEG, ROOT, WORKED, free_port

#: Work for the only worker, long enough to be caught in flight: a plan, then 3 closed-loop
#: runs of 10 replans each (1.8 s on an idle machine). Open-loop replays were too short to
#: rely on: 160 of them once answered in 0.37 s, between two polls of /readyz under load.
SLOWISH = {"plan": {"start": [10 * DEG] * 3, "goal": [30 * DEG] * 3},
           "random": {"count": 3, "spread": 0.01, "seed": 5},
           "closed_loop": {"gain_error": 0.05, "period": 0.1, "seed": 1}, "time_limit": 30}


def _start(port: int, log: Any) -> subprocess.Popen[bytes]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PLANNER_")}
    env.update({"PLANNER_HOST": "127.0.0.1", "PLANNER_PORT": str(port),
                "PLANNER_WORKERS": "1", "PLANNER_SHUTDOWN_TIMEOUT": "20"})
    return subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=env, stdout=log,
                            stderr=subprocess.STDOUT, start_new_session=True)


def _wait_ready(base: str, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        assert proc.poll() is None, "the server exited while starting"
        try:
            with urllib.request.urlopen(base + "/readyz", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.1)
    raise AssertionError("the server did not become ready")


@pytest.mark.parametrize("target", ["server", "process_group"])
def test_sigterm_lets_the_request_in_flight_finish_and_exits_0(tmp_path, target):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    log_path = tmp_path / "server.log"
    with open(log_path, "wb") as log:
        proc = _start(port, log)
        try:
            _wait_ready(base, proc)
            children = psutil.Process(proc.pid).children(recursive=True)
            assert children, "no worker processes"
            answer: dict[str, Any] = {}

            def send() -> None:
                t0 = time.perf_counter()
                r = httpx.post(base + "/v1/robustness", json=SLOWISH, timeout=60)
                answer.update(status=r.status_code, text=r.text,
                              seconds=time.perf_counter() - t0, at=time.monotonic())

            client = threading.Thread(target=send)
            client.start()
            deadline = time.monotonic() + 30
            while httpx.get(base + "/readyz").json()["busy"] == 0:  # the job is running
                assert time.monotonic() < deadline and not answer, (
                    "the job was never seen in flight", answer.get("seconds"))
                time.sleep(0.01)
            sent_at = time.monotonic()
            if target == "server":
                proc.send_signal(signal.SIGTERM)
            else:
                os.killpg(proc.pid, signal.SIGTERM)
            # new connections are refused once the server has begun to shut down
            time.sleep(0.3)
            with pytest.raises(httpx.ConnectError):
                httpx.get(base + "/healthz", timeout=2)
            client.join(timeout=60)
            code = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(timeout=10)
    log_text = log_path.read_text(errors="replace")
    assert answer.get("status") == 200, (answer, log_text[-2000:])
    body = json.loads(answer["text"])  # complete JSON
    runs = SLOWISH["random"]["count"]
    assert body["summary"]["runs"] == runs and len(body["runs"]) == runs
    assert body["closed_loop"]["summary"]["runs"] == runs   # the whole job, closed loop too
    assert answer["at"] > sent_at  # it was in flight when SIGTERM came
    assert code == 0, log_text[-2000:]
    # the workers were stopped by the server; the forkserver follows its parent out
    _, alive = psutil.wait_procs(children, timeout=10)
    assert not alive, [(p.pid, p.cmdline()) for p in alive]
    assert "Traceback" not in log_text, log_text[-3000:]
