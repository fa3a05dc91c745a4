"""The HTTP service under load: cold start, latency and throughput, worker memory.

The service (``service.main:app``) is started with uvicorn as a subprocess on 127.0.0.1 and a
free port, with its default settings (``PLANNER_*`` environment variables are passed through;
``PLANNER_HOST``/``PLANNER_PORT`` are set to match). Then:

* **cold start**: from just before the process is spawned to ``GET /readyz`` answering 200,
  and to the first successful ``POST /v1/plans``;
* **load**: for each method and each number of concurrent clients, that many httpx clients
  (one asyncio loop in this process, keep-alive connections) post the same plan request in a
  closed loop for a bounded time. Throughput counts the successful answers received within the
  window; latencies are of every answer received (requests still unanswered ``drain`` seconds
  after the window are cancelled and counted as ``unfinished``; when there are such requests,
  the percentiles are those of the answered ones only, a lower bound). Between two levels the
  bench waits until ``/readyz`` reports no busy or waiting worker;
* **memory**: resident set size (RSS) and unique set size (USS) of every process of the server's
  tree (psutil), idle after start and after the load.

The load generator shares the machine's CPUs with the server.
"""

from __future__ import annotations

import asyncio
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from .stats import summarise

ROOT = Path(__file__).resolve().parents[1]

#: The paper-type goal of the HTTP measurements (deg).
HTTP_START_DEG = (10.0, 10.0, 10.0)
HTTP_GOAL_DEG = (30.0, 30.0, 30.0)


def available() -> tuple[bool, str]:
    """Whether ``service.main:app`` imports and builds; the reason when not."""
    for mod in ("httpx", "psutil", "uvicorn"):
        try:
            __import__(mod)
        except Exception as exc:  # noqa: BLE001 - the reason is the result
            return False, f"{mod} is not importable: {type(exc).__name__}: {exc}"
    code = "import service.main as m; assert m.app is not None"
    try:
        proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                              text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return False, "importing service.main took more than 120 s"
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return False, "service.main:app is not importable: " + " | ".join(tail)
    return True, ""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def plan_body(method: str) -> dict[str, Any]:
    """The JSON body of the paper-type plan request (radians)."""
    return {"start": [math.radians(x) for x in HTTP_START_DEG],
            "goal": [math.radians(x) for x in HTTP_GOAL_DEG], "method": method}


class Server:
    """The service under uvicorn in a subprocess.

    Parameters
    ----------
    env : dict, optional
        Extra environment variables (e.g. ``PLANNER_WORKERS``).
    """

    def __init__(self, env: dict[str, str] | None = None) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = dict(os.environ)
        self.env.update(env or {})
        self.env.update(PLANNER_HOST="127.0.0.1", PLANNER_PORT=str(self.port))
        self.env["PYTHONPATH"] = str(ROOT) + os.pathsep + self.env.get("PYTHONPATH", "")
        self.log = tempfile.NamedTemporaryFile(prefix="bench-service-", suffix=".log",
                                               delete=False)
        self.proc: subprocess.Popen[bytes] | None = None
        self.t_spawn = math.nan

    def start(self) -> None:
        """Spawn uvicorn (time origin of the cold start)."""
        cmd = [sys.executable, "-m", "uvicorn", "service.main:app", "--host", "127.0.0.1",
               "--port", str(self.port), "--no-access-log"]
        self.t_spawn = time.perf_counter()
        self.proc = subprocess.Popen(cmd, cwd=ROOT, env=self.env, stdout=self.log,
                                     stderr=subprocess.STDOUT)

    def log_tail(self, lines: int = 5) -> str:
        """The last lines of the server's output."""
        try:
            text = Path(self.log.name).read_text(errors="replace")
        except OSError:
            return ""
        return " | ".join(text.strip().splitlines()[-lines:])

    def stop(self, timeout: float = 5.0) -> float:
        """SIGTERM uvicorn (it stops its worker pool); after ``timeout`` s SIGKILL it and every
        process of its tree (by pid). Returns the seconds the graceful stop took (NaN when it
        had to be killed)."""
        import psutil
        if self.proc is None:
            return math.nan
        try:
            tree = psutil.Process(self.proc.pid).children(recursive=True)
        except psutil.Error:
            tree = []
        t0 = time.perf_counter()
        self.proc.terminate()
        graceful = math.nan
        try:
            self.proc.wait(timeout)
            graceful = time.perf_counter() - t0
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        for child in tree:
            try:
                child.wait(0.5 if math.isnan(graceful) else 2)
            except psutil.TimeoutExpired:
                try:
                    child.kill()
                except psutil.Error:
                    pass
            except psutil.Error:
                pass
        self.proc = None
        try:
            os.unlink(self.log.name)
        except OSError:
            pass
        return graceful

    def memory(self) -> list[dict[str, Any]]:
        """RSS and USS (MB) of every process of the server's tree, with its role."""
        import psutil
        if self.proc is None:
            return []
        root = psutil.Process(self.proc.pid)
        procs = [root] + root.children(recursive=True)
        out = []
        for p in procs:
            try:
                cmd = " ".join(p.cmdline())
                info = p.memory_full_info()
                parent = p.ppid()
            except psutil.Error:
                continue
            # workers are forked by the forkserver and inherit its command line
            if p.pid == root.pid:
                role = "uvicorn (event loop)"
            elif parent == root.pid and "resource_tracker" in cmd:
                role = "resource tracker"
            elif parent == root.pid and "forkserver" in cmd:
                role = "forkserver"
            else:
                role = "worker"
            out.append({"pid": p.pid, "ppid": parent, "role": role,
                        "rss_mb": info.rss / 2 ** 20, "uss_mb": info.uss / 2 ** 20})
        return out


async def _wait_ready(client: Any, url: str, deadline: float) -> float:
    """Poll ``/readyz`` until 200; the ``perf_counter`` time it answered."""
    while time.perf_counter() < deadline:
        try:
            r = await client.get(url + "/readyz", timeout=2.0)
            if r.status_code == 200:
                return time.perf_counter()
        except Exception:  # noqa: BLE001 - not up yet
            pass
        await asyncio.sleep(0.01)
    raise TimeoutError("the service did not become ready")


async def _first_plan(client: Any, url: str, body: dict[str, Any], deadline: float) -> float:
    """Post until a plan succeeds; the ``perf_counter`` time it did."""
    last = ""
    while time.perf_counter() < deadline:
        try:
            r = await client.post(url + "/v1/plans", json=body, timeout=60.0)
            if r.status_code == 200:
                return time.perf_counter()
            last = f"HTTP {r.status_code}: {r.text[:200]}"
        except Exception as exc:  # noqa: BLE001 - retried
            last = f"{type(exc).__name__}: {exc}"
        await asyncio.sleep(0.01)
    raise TimeoutError(f"no successful plan: {last}")


async def cold_start(server: Server, timeout: float = 120.0) -> dict[str, Any]:
    """Start ``server`` and time readiness and the first successful plan."""
    import httpx
    server.start()
    async with httpx.AsyncClient() as client:
        deadline = time.perf_counter() + timeout
        t_ready = await _wait_ready(client, server.url, deadline)
        t_plan = await _first_plan(client, server.url, plan_body("polynomial"), deadline)
        ready = await client.get(server.url + "/readyz")
    return {"ready_s": t_ready - server.t_spawn, "first_plan_s": t_plan - server.t_spawn,
            "readyz": ready.json()}


async def wait_idle(url: str, timeout: float) -> float:
    """Wait until ``/readyz`` reports no busy and no waiting worker; seconds waited."""
    import httpx
    t0 = time.perf_counter()
    async with httpx.AsyncClient() as client:
        while time.perf_counter() - t0 < timeout:
            try:
                st = (await client.get(url + "/readyz", timeout=2.0)).json()
                if st.get("busy", 1) == 0 and st.get("waiting", 1) == 0 and \
                        st.get("status") == "ready":
                    return time.perf_counter() - t0
            except Exception:  # noqa: BLE001 - retried
                pass
            await asyncio.sleep(0.05)
    return math.nan


async def load(url: str, body: dict[str, Any], clients: int, seconds: float,
               drain: float) -> dict[str, Any]:
    """``clients`` closed-loop clients posting ``body`` for ``seconds``.

    Returns
    -------
    dict
        ``throughput`` (successful plans per second within the window), latency summary (s) and
        p50/p99 (ms) of the answers, status counts, ``unfinished`` requests.
    """
    import httpx
    latencies: list[float] = []
    ok_in_window = 0
    statuses: dict[str, int] = {}
    limits = httpx.Limits(max_connections=clients + 2, max_keepalive_connections=clients + 2)
    async with httpx.AsyncClient(limits=limits, timeout=httpx.Timeout(120.0)) as client:
        t0 = time.perf_counter()
        stop_at = t0 + seconds

        async def one_client() -> None:
            nonlocal ok_in_window
            while time.perf_counter() < stop_at:
                a = time.perf_counter()
                try:
                    r = await client.post(url + "/v1/plans", json=body)
                    key = str(r.status_code)
                    if r.status_code == 200:
                        # the service must answer with a plan, not only a 200
                        if r.json().get("status") != "success":
                            key = "200-not-success"
                except httpx.HTTPError as exc:
                    key = type(exc).__name__
                b = time.perf_counter()
                latencies.append(b - a)
                statuses[key] = statuses.get(key, 0) + 1
                if key == "200" and b <= stop_at:
                    ok_in_window += 1

        tasks = [asyncio.create_task(one_client()) for _ in range(clients)]
        done, pending = await asyncio.wait(tasks, timeout=seconds + drain)
        for t in pending:
            t.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
    lat = np.asarray(latencies)
    summ = summarise(latencies)
    return {
        "clients": clients, "seconds": seconds, "throughput": ok_in_window / seconds,
        "answered": int(lat.size), "unfinished": len(pending), "statuses": statuses,
        "p50_ms": float(np.percentile(lat, 50) * 1e3) if lat.size else math.nan,
        "p99_ms": float(np.percentile(lat, 99) * 1e3) if lat.size else math.nan,
        "mean_ms": float(lat.mean() * 1e3) if lat.size else math.nan,
        "max_ms": float(lat.max() * 1e3) if lat.size else math.nan,
        "latency": {k: v for k, v in summ.as_dict().items() if k != "samples"},
    }


async def _run(seconds: float, levels: tuple[int, ...], methods: tuple[str, ...],
               cold_starts: int, drain: float, log: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"available": True, "start_deg": list(HTTP_START_DEG),
                           "goal_deg": list(HTTP_GOAL_DEG), "seconds_per_level": seconds,
                           "settings_env": {k: v for k, v in os.environ.items()
                                            if k.startswith("PLANNER_")}}
    colds = []
    server: Server | None = None
    try:
        for i in range(max(1, cold_starts)):
            server = Server()
            try:
                colds.append(await cold_start(server))
            except Exception as exc:
                raise RuntimeError(f"{exc}; server log: {server.log_tail()}") from exc
            log(f"  cold start {i + 1}: ready {colds[-1]['ready_s']:.2f} s, first plan "
                f"{colds[-1]['first_plan_s']:.2f} s")
            if i < max(1, cold_starts) - 1:
                server.stop()
        assert server is not None
        out["cold_start"] = {
            "runs": colds,
            "ready_s": summarise([c["ready_s"] for c in colds]).as_dict(),
            "first_plan_s": summarise([c["first_plan_s"] for c in colds]).as_dict(),
            "workers": colds[-1]["readyz"].get("workers"),
        }
        out["memory_idle"] = server.memory()
        loads: dict[str, list[dict[str, Any]]] = {}
        for method in methods:
            loads[method] = []
            for c in levels:
                idle = await wait_idle(server.url, 120.0)
                res = await load(server.url, plan_body(method), c, seconds, drain)
                res["waited_for_idle_s"] = idle
                loads[method].append(res)
                log(f"  {method} x{c}: {res['throughput']:.2f} plans/s, p50 "
                    f"{res['p50_ms']:.0f} ms, p99 {res['p99_ms']:.0f} ms, statuses "
                    f"{res['statuses']}, unfinished {res['unfinished']}")
            out["memory_after_" + method] = server.memory()
        out["load"] = loads
        mems = [m for key in out if key.startswith("memory") for m in out[key]
                if m["role"] == "worker"]
        out["worker_rss_mb_max"] = max((m["rss_mb"] for m in mems), default=math.nan)
        out["worker_uss_mb_max"] = max((m["uss_mb"] for m in mems), default=math.nan)
    finally:
        if server is not None:
            server.stop()
    return out


def run(seconds: float = 10.0, levels: tuple[int, ...] = (1, 8, 32),
        methods: tuple[str, ...] = ("polynomial", "auto"), cold_starts: int = 3,
        drain: float = 10.0, log: Any = print) -> dict[str, Any]:
    """All HTTP measurements, or ``{"available": False, "reason": ...}``.

    Parameters
    ----------
    seconds : float
        Length of each load level.
    levels : tuple of int
        Numbers of concurrent clients.
    methods : tuple of str
        Plan methods posted.
    cold_starts : int
        Server starts timed (the last one serves the load).
    drain : float
        Seconds allowed after a window for the requests still in flight.
    log : callable
        Progress printer.

    Returns
    -------
    dict
    """
    ok, why = available()
    if not ok:
        return {"available": False, "reason": why}
    try:
        return asyncio.run(_run(seconds, levels, methods, cold_starts, drain, log))
    except Exception as exc:  # noqa: BLE001 - the reason is the result
        return {"available": False, "reason": f"{type(exc).__name__}: {exc}"}
