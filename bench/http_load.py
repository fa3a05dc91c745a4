"""The HTTP service under load: cold start, latency and throughput, server CPU, worker memory.

``python -m bench.http_load [--seconds 10] [--clients 1,8,32] [--jobs plan:polynomial,...]``
(``python -m bench`` runs the same measurements as part of the whole benchmark).

The service is started as it is deployed, ``python -m service`` (uvicorn, the JSON access log
on, default settings; ``PLANNER_*`` environment variables are passed through and
``PLANNER_HOST``/``PLANNER_PORT`` set to 127.0.0.1 and a free port), as a subprocess. Then:

* **cold start**: from just before the process is spawned to ``GET /readyz`` answering 200,
  and to the first successful ``POST /v1/plans``;
* **load**: for each job (the trivial ones first, then the plan methods ``polynomial``,
  ``retimed`` and ``auto``) and each number of concurrent clients, that many clients (one asyncio
  loop in this process, uvloop when installed, one keep-alive HTTP/1.1 connection each, a
  minimal client written on asyncio streams: httpx spends about 1 ms of CPU per request, which
  on two cores would be taken from the server) send requests in a closed loop for a bounded
  time. Jobs:

  ``plan:<method>``
      ``POST /v1/plans`` with the paper-type goal [30, 30, 30] deg from a start drawn anew for
      every request, uniformly within +-2 deg of [10, 10, 10] deg on every joint (every such
      start is planned; no two requests are alike, so no cache could help), default samples;
      a 200 must carry ``"status":"success"``.
  ``transform``
      ``POST /v1/transforms`` of one random point: a trivial job through the worker pool
      (validation, dispatch, worker round trip, encoding), the service's own overhead.
  ``robot``
      ``GET /v1/robots/default``: answered in the event loop (middleware, routing, encoding).

  Throughput counts the successful answers received within the window; latencies are of
  every answer received (requests still unanswered ``drain`` seconds after the window are
  cancelled and counted as ``unfinished``; the percentiles are then a lower bound). Between two
  levels the bench waits until ``/readyz`` reports no busy or waiting worker;
* **CPU**: during each window, the CPU seconds of this load generator, of the server's event-loop
  process and of its workers (psutil), per answered request, and of each the part spent in the
  kernel (system time: sockets, pipes, page faults); the event loop's share is the service's
  per-request overhead outside the job (``python -m bench.http_stages`` splits it by stage);
* **memory**: resident set size (RSS) and unique set size (USS) of every process of the server's
  tree (psutil), idle after start and after the load.

The load generator shares the machine's CPUs with the server; its CPU share is reported.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .stats import summarise

ROOT = Path(__file__).resolve().parents[1]

#: The paper-type goal of the HTTP measurements (deg); starts are drawn around HTTP_START_DEG.
HTTP_START_DEG = (10.0, 10.0, 10.0)
HTTP_GOAL_DEG = (30.0, 30.0, 30.0)
#: Half-width (deg) of the uniform draw of each start angle around HTTP_START_DEG.
START_SPREAD_DEG = 2.0

#: Request factories: rng -> (method, path, body or None, check of a 200 body).
Job = Callable[[random.Random], tuple[str, str, "bytes | None"]]


def available() -> tuple[bool, str]:
    """Whether ``service.main:app`` imports and builds; the reason when not."""
    for mod in ("psutil", "uvicorn"):
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


def plan_body(method: str, rng: random.Random | None = None) -> dict[str, Any]:
    """The JSON body of a paper-type plan request (radians).

    With ``rng``, every start angle is drawn uniformly within ``START_SPREAD_DEG`` of
    ``HTTP_START_DEG``; without, the start is ``HTTP_START_DEG``.
    """
    start = [x + (rng.uniform(-START_SPREAD_DEG, START_SPREAD_DEG) if rng else 0.0)
             for x in HTTP_START_DEG]
    return {"start": [math.radians(x) for x in start],
            "goal": [math.radians(x) for x in HTTP_GOAL_DEG], "method": method}


def job(name: str) -> tuple[Job, bytes | None]:
    """The request factory of a job name and the marker a 200 body must contain (or None)."""
    if name.startswith("plan:"):
        method = name.split(":", 1)[1]
        return (lambda rng: ("POST", "/v1/plans",
                             json.dumps(plan_body(method, rng)).encode())), b'"status":"success"'
    if name == "transform":
        return (lambda rng: ("POST", "/v1/transforms", json.dumps({
            "direction": "to_chained",
            "points": [[rng.uniform(-1, 1)] + [rng.uniform(0.05, 1.5) for _ in range(3)]]}
        ).encode())), b'"valid":'
    if name == "robot":
        return (lambda rng: ("GET", f"/v1/robots/default?n={rng.randint(3, 8)}", None)), \
            b'"gains":'
    raise ValueError(f"unknown job {name!r} (plan:<method>, transform, robot)")


# ---------------------------------------------------------------------------- minimal client
class HTTPError(Exception):
    """A transport-level failure of :class:`Connection`."""


class Connection:
    """One keep-alive HTTP/1.1 connection on asyncio streams (just enough for this service).

    Requests carry ``Content-Length``; answers are read by ``Content-Length`` (or chunked).
    """

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def _connect(self) -> None:
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        sock = self.writer.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None

    async def request(self, method: str, path: str, body: bytes | None = None,
                      headers: dict[str, str] | None = None) -> tuple[int, bytes]:
        """Send one request; ``(status, body)`` of the answer."""
        if self.writer is None:
            await self._connect()
        assert self.reader is not None and self.writer is not None
        head = f"{method} {path} HTTP/1.1\r\nHost: {self.host}:{self.port}\r\n"
        if body is not None:
            head += f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
        for k, v in (headers or {}).items():
            head += f"{k}: {v}\r\n"
        try:
            self.writer.write(head.encode("latin-1") + b"\r\n" + (body or b""))
            raw = await self.reader.readuntil(b"\r\n\r\n")
            lines = raw.split(b"\r\n")
            status = int(lines[0].split(b" ", 2)[1])
            length, chunked, close = -1, False, False
            for line in lines[1:]:
                name, _, value = line.partition(b":")
                name = name.strip().lower()
                if name == b"content-length":
                    length = int(value)
                elif name == b"transfer-encoding":
                    chunked = b"chunked" in value.lower()
                elif name == b"connection":
                    close = b"close" in value.lower()
            if chunked:
                parts = []
                while True:
                    size = int((await self.reader.readuntil(b"\r\n")).split(b";")[0], 16)
                    parts.append(await self.reader.readexactly(size + 2))
                    if size == 0:
                        break
                data = b"".join(p[:-2] for p in parts)
            elif length >= 0:
                data = await self.reader.readexactly(length)
            else:
                data = await self.reader.read()
                close = True
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError,
                ValueError, IndexError) as exc:
            self.close()
            raise HTTPError(f"{type(exc).__name__}: {exc}") from exc
        if close:
            self.close()
        return status, data


async def get_json(url: str, path: str, timeout: float = 5.0) -> tuple[int, Any]:
    """One GET on a new connection: ``(status, parsed JSON body)``."""
    host, port = url.split("//", 1)[1].split(":")
    conn = Connection(host, int(port))
    try:
        status, data = await asyncio.wait_for(conn.request("GET", path), timeout)
    finally:
        conn.close()
    return status, json.loads(data)


# ---------------------------------------------------------------------------- the server
class Server:
    """The service (``python -m service``) in a subprocess.

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
        """Spawn the service (time origin of the cold start)."""
        cmd = [sys.executable, "-m", "service"]
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
        """SIGTERM the service (it stops its worker pool); after ``timeout`` s SIGKILL it and
        every process of its tree (by pid). Returns the seconds the graceful stop took (NaN when
        it had to be killed)."""
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

    def _tree(self) -> list[tuple[Any, str]]:
        """``(psutil.Process, role)`` of every process of the server's tree."""
        import psutil
        if self.proc is None:
            return []
        root = psutil.Process(self.proc.pid)
        out = []
        for p in [root] + root.children(recursive=True):
            try:
                cmd = " ".join(p.cmdline())
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
            out.append((p, role))
        return out

    def memory(self) -> list[dict[str, Any]]:
        """RSS and USS (MB) of every process of the server's tree, with its role."""
        import psutil
        out = []
        for p, role in self._tree():
            try:
                info = p.memory_full_info()
                out.append({"pid": p.pid, "ppid": p.ppid(), "role": role,
                            "rss_mb": info.rss / 2 ** 20, "uss_mb": info.uss / 2 ** 20})
            except psutil.Error:
                continue
        return out

    def cpu(self) -> dict[str, float]:
        """CPU seconds so far of the event-loop process (``server``) and of the workers
        (``workers``): user + system, and each apart (``server_user``, ``server_system``, ...;
        the kernel's share is the sockets' and pipes' copies)."""
        import psutil
        out = {k: 0.0 for k in ("server", "workers", "server_user", "server_system",
                                "workers_user", "workers_system")}
        for p, role in self._tree():
            try:
                t = p.cpu_times()
            except psutil.Error:
                continue
            key = "server" if role.startswith("uvicorn") else "workers" if role == "worker" \
                else None
            if key:
                out[key] += t.user + t.system
                out[key + "_user"] += t.user
                out[key + "_system"] += t.system
        return out


async def _wait_ready(url: str, deadline: float) -> float:
    """Poll ``/readyz`` until 200; the ``perf_counter`` time it answered."""
    while time.perf_counter() < deadline:
        try:
            status, _ = await get_json(url, "/readyz", 2.0)
            if status == 200:
                return time.perf_counter()
        except Exception:  # noqa: BLE001 - not up yet
            pass
        await asyncio.sleep(0.01)
    raise TimeoutError("the service did not become ready")


async def _first_plan(url: str, body: bytes, deadline: float) -> float:
    """Post until a plan succeeds; the ``perf_counter`` time it did."""
    last = ""
    host, port = url.split("//", 1)[1].split(":")
    while time.perf_counter() < deadline:
        conn = Connection(host, int(port))
        try:
            status, data = await asyncio.wait_for(conn.request("POST", "/v1/plans", body), 60)
            if status == 200:
                return time.perf_counter()
            last = f"HTTP {status}: {data[:200]!r}"
        except Exception as exc:  # noqa: BLE001 - retried
            last = f"{type(exc).__name__}: {exc}"
        finally:
            conn.close()
        await asyncio.sleep(0.01)
    raise TimeoutError(f"no successful plan: {last}")


async def cold_start(server: Server, timeout: float = 120.0) -> dict[str, Any]:
    """Start ``server`` and time readiness and the first successful plan."""
    server.start()
    deadline = time.perf_counter() + timeout
    t_ready = await _wait_ready(server.url, deadline)
    t_plan = await _first_plan(server.url, json.dumps(plan_body("polynomial")).encode(),
                               deadline)
    _, ready = await get_json(server.url, "/readyz")
    return {"ready_s": t_ready - server.t_spawn, "first_plan_s": t_plan - server.t_spawn,
            "readyz": ready}


async def wait_idle(url: str, timeout: float) -> float:
    """Wait until ``/readyz`` reports no busy and no waiting worker; seconds waited."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < timeout:
        try:
            _, st = await get_json(url, "/readyz", 2.0)
            if st.get("busy", 1) == 0 and st.get("waiting", 1) == 0 and \
                    st.get("status") == "ready":
                return time.perf_counter() - t0
        except Exception:  # noqa: BLE001 - retried
            pass
        await asyncio.sleep(0.05)
    return math.nan


async def load(url: str, name: str, clients: int, seconds: float, drain: float,
               server: Server | None = None, seed: int = 0) -> dict[str, Any]:
    """``clients`` closed-loop clients sending job ``name``'s requests for ``seconds``.

    Returns
    -------
    dict
        ``throughput`` (successful answers per second within the window), p50/p99/mean/max
        (ms) of the answers, status counts, ``unfinished`` requests, and ``cpu``: CPU seconds
        of the load generator, the server's event loop and its workers during the window, and
        per answered request (ms).
    """
    make, marker = job(name)
    host, port = url.split("//", 1)[1].split(":")
    latencies: list[float] = []
    ok_in_window = 0
    statuses: dict[str, int] = {}
    conns = [Connection(host, int(port)) for _ in range(clients)]
    t0 = time.perf_counter()
    stop_at = t0 + seconds

    async def one_client(conn: Connection, rng: random.Random) -> None:
        nonlocal ok_in_window
        while time.perf_counter() < stop_at:
            method, path, body = make(rng)
            a = time.perf_counter()
            try:
                status, data = await conn.request(method, path, body)
                key = str(status)
                if status == 200 and marker is not None and marker not in data:
                    key = "200-unexpected-body"  # e.g. a plan that is not a success
            except HTTPError as exc:
                key = str(exc).split(":", 1)[0]
            b = time.perf_counter()
            latencies.append(b - a)
            statuses[key] = statuses.get(key, 0) + 1
            if key == "200" and b <= stop_at:
                ok_in_window += 1

    cpu0 = server.cpu() if server is not None else None
    own0 = time.process_time()
    own_times0 = os.times()
    wall0 = time.perf_counter()
    tasks = [asyncio.create_task(one_client(c, random.Random(seed * 1000 + i)))
             for i, c in enumerate(conns)]
    done, pending = await asyncio.wait(tasks, timeout=seconds + drain)
    wall = time.perf_counter() - wall0
    own = time.process_time() - own0
    own_times1 = os.times()
    cpu1 = server.cpu() if server is not None else None
    for t in pending:
        t.cancel()
    await asyncio.gather(*pending, return_exceptions=True)
    for c in conns:
        c.close()
    lat = np.asarray(latencies)
    summ = summarise(latencies)
    answered = int(lat.size)
    cpu: dict[str, Any] = {"wall_s": wall, "client_s": own,
                           "client_system_s": own_times1.system - own_times0.system}
    if cpu0 is not None and cpu1 is not None:
        for key in ("server", "workers", "server_system", "workers_system"):
            cpu[key + "_s"] = cpu1[key] - cpu0[key]
        total = own + cpu["server_s"] + cpu["workers_s"]
        cpu["client_share"] = own / total if total > 0 else math.nan
    per = 1e3 / answered if answered else math.nan
    cpu.update({k[:-2] + "_ms_per_request": v * per for k, v in list(cpu.items())
                if k.endswith("_s") and k != "wall_s"})
    return {
        "job": name, "clients": clients, "seconds": seconds,
        "throughput": ok_in_window / seconds, "answered": answered,
        "unfinished": len(pending), "statuses": statuses,
        "p50_ms": float(np.percentile(lat, 50) * 1e3) if lat.size else math.nan,
        "p99_ms": float(np.percentile(lat, 99) * 1e3) if lat.size else math.nan,
        "mean_ms": float(lat.mean() * 1e3) if lat.size else math.nan,
        "max_ms": float(lat.max() * 1e3) if lat.size else math.nan,
        "cpu": cpu,
        "latency": {k: v for k, v in summ.as_dict().items() if k != "samples"},
    }


def _describe(res: dict[str, Any]) -> str:
    cpu = res["cpu"]
    text = (f"{res['throughput']:.1f}/s, p50 {res['p50_ms']:.1f} ms, p99 {res['p99_ms']:.1f} ms"
            f", statuses {res['statuses']}, unfinished {res['unfinished']}; CPU per request: "
            f"client {cpu.get('client_ms_per_request', math.nan):.2f} ms")
    if "server_ms_per_request" in cpu:
        text += (f", event loop {cpu['server_ms_per_request']:.2f} ms, workers "
                 f"{cpu['workers_ms_per_request']:.2f} ms (client share "
                 f"{cpu['client_share']:.0%}); of which system: client "
                 f"{cpu['client_system_ms_per_request']:.2f}, event loop "
                 f"{cpu['server_system_ms_per_request']:.2f}, workers "
                 f"{cpu['workers_system_ms_per_request']:.2f} ms")
    return text


async def _run(seconds: float, levels: tuple[int, ...], methods: tuple[str, ...],
               cold_starts: int, drain: float, log: Any,
               overhead_jobs: tuple[str, ...]) -> dict[str, Any]:
    out: dict[str, Any] = {"available": True, "start_deg": list(HTTP_START_DEG),
                           "start_spread_deg": START_SPREAD_DEG,
                           "goal_deg": list(HTTP_GOAL_DEG), "seconds_per_level": seconds,
                           "client": "asyncio streams, keep-alive HTTP/1.1"
                                     + (" (uvloop)" if _uvloop() else ""),
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
        # the trivial jobs first: a slow method's requests left unfinished keep the workers
        # busy for a while after its last level
        overhead: dict[str, list[dict[str, Any]]] = {}
        for name in overhead_jobs:
            overhead[name] = []
            for c in levels:
                idle = await wait_idle(server.url, 120.0)
                res = await load(server.url, name, c, seconds, drain, server)
                res["waited_for_idle_s"] = idle
                overhead[name].append(res)
                log(f"  {name} x{c}: {_describe(res)}")
        out["overhead"] = overhead
        loads: dict[str, list[dict[str, Any]]] = {}
        for method in methods:
            loads[method] = []
            for c in levels:
                idle = await wait_idle(server.url, 120.0)
                res = await load(server.url, f"plan:{method}", c, seconds, drain, server)
                res["waited_for_idle_s"] = idle
                loads[method].append(res)
                log(f"  plan:{method} x{c}: {_describe(res)}")
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


def _uvloop() -> bool:
    try:
        import uvloop  # noqa: F401
    except ImportError:
        return False
    return True


def _asyncio_run(coro: Any) -> Any:
    """``asyncio.run`` on uvloop when installed (a cheaper client)."""
    if _uvloop():
        import uvloop
        return uvloop.run(coro)
    return asyncio.run(coro)


def run(seconds: float = 10.0, levels: tuple[int, ...] = (1, 8, 32),
        methods: tuple[str, ...] = ("polynomial", "retimed", "auto"), cold_starts: int = 3,
        drain: float = 10.0, log: Any = print,
        overhead_jobs: tuple[str, ...] = ("transform", "robot")) -> dict[str, Any]:
    """All HTTP measurements, or ``{"available": False, "reason": ...}``.

    Parameters
    ----------
    seconds : float
        Length of each load level.
    levels : tuple of int
        Numbers of concurrent clients.
    methods : tuple of str
        Plan methods posted (``load``).
    cold_starts : int
        Server starts timed (the last one serves the load).
    drain : float
        Seconds allowed after a window for the requests still in flight.
    log : callable
        Progress printer.
    overhead_jobs : tuple of str
        Trivial jobs measured at the same levels (``overhead``): ``transform`` (through the
        worker pool), ``robot`` (in the event loop).

    Returns
    -------
    dict
    """
    ok, why = available()
    if not ok:
        return {"available": False, "reason": why}
    _prebuild_native(log)
    try:
        return _asyncio_run(_run(seconds, levels, methods, cold_starts, drain, log,
                                 overhead_jobs))
    except Exception as exc:  # noqa: BLE001 - the reason is the result
        return {"available": False, "reason": f"{type(exc).__name__}: {exc}"}


def _prebuild_native(log: Any) -> None:
    """Build the default robot's compiled shooting NLP into the service's default cache
    before the server starts, as on a machine that has served before (or in the image):
    otherwise its first start compiles in the background, inside the cold-start and load
    measurements."""
    from optimizer.model import Robot
    from optimizer.planner.shooting import prepare

    from .inprocess import configure_native
    info = configure_native()
    if info["on"]:
        robot = Robot()
        prepare(robot.gains, robot.exponents, wait=True)
    else:
        log(f"  compiled NLP functions not prebuilt: {info['reason']}")


def main(argv: list[str] | None = None) -> int:
    """``python -m bench.http_load``: the HTTP part of the benchmark alone."""
    p = argparse.ArgumentParser(prog="python -m bench.http_load", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=10.0, help="seconds per level")
    p.add_argument("--clients", default="1,8,32", help="comma-separated client counts")
    p.add_argument("--methods", default="polynomial,retimed,auto",
                   help="plan methods ('' for none)")
    p.add_argument("--overhead", default="transform,robot",
                   help="trivial jobs measured too ('' for none): transform, robot")
    p.add_argument("--cold-starts", type=int, default=3)
    p.add_argument("--drain", type=float, default=10.0)
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    args = p.parse_args(argv)
    split = (lambda s: tuple(x for x in s.split(",") if x))  # noqa: E731
    out = run(args.seconds, tuple(int(c) for c in split(args.clients)), split(args.methods),
              args.cold_starts, args.drain, log=lambda s: print(s, flush=True),
              overhead_jobs=split(args.overhead))
    if not out.get("available"):
        print(f"not available: {out.get('reason')}")
        return 1
    cs = out["cold_start"]
    print(f"cold start: ready {cs['ready_s']['median']:.2f} s, first plan "
          f"{cs['first_plan_s']['median']:.2f} s (median of {len(cs['runs'])}); worker RSS max "
          f"{out['worker_rss_mb_max']:.0f} MB, USS max {out['worker_uss_mb_max']:.0f} MB")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
