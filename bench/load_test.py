"""Load test of the live HTTP service with locust (headless): a mix of endpoints for a bounded time.

``python -m bench.load_test [--duration 60] [--users 32] [--workers N] [--json out.json]``

1. starts the service (``python -m service``: uvicorn, ``PLANNER_HOST=127.0.0.1``, a free port,
   the default settings otherwise; ``--workers`` sets ``PLANNER_WORKERS``) as a subprocess and
   waits for ``/readyz``;
2. records the memory (RSS and USS, psutil) of the server process and of each worker;
3. runs ``locust -f bench/load_test.py --headless -u USERS -r USERS -t DURATION --host URL``:
   ``USERS`` simulated clients, each sending its next request as soon as the last one is
   answered (closed loop), with this mix (weights):

   ===============================  ======  ===========================================
   request                          weight  what
   ===============================  ======  ===========================================
   ``POST /v1/plans`` fixed dphi      24    3-joint plan, dphi drawn in the feasible
                                            interval, 51 samples
   ``POST /v1/plans`` searched         6    the paper's worked example (dphi searched)
   ``POST /v1/transforms``            20    10 points, to_chained
   ``POST /v1/sweeps`` small           8    21 dphi values, no exact intervals
   ``POST /v1/robustness`` small       5    4 random perturbed starts
   ``GET /v1/robots/default``         15    n from 3 to 8
   ``GET /healthz``                   15
   deliberate bad requests             7    malformed JSON (400), samples over the limit,
                                            a start outside the region, a non-finite
                                            number (422): each must get exactly its 4xx
   ===============================  ======  ===========================================

   A request counts as an error when its answer is not the expected one (200, or the exact
   4xx of a deliberate bad request) or it fails at the transport level;
4. records the memory again, stops the server (SIGTERM), and reports throughput (answers per
   second), latency percentiles p50/p95/p99 (ms) overall and per request kind, the errors
   (must be 0), the deliberate bad requests answered as expected, and the memory at start and
   end. The exit status is 1 when there was any error.

The load generator (one locust process) shares the machine's CPUs with the server. This file is
also the locustfile: the user class is defined when locust imports it.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DEG = math.pi / 180.0
START = [10 * DEG] * 3
GOAL = [30 * DEG] * 3
#: The worked example's feasible dphi interval (deg), slightly inside.
DPHI_DEG = (33.4, 35.0)
BAD_KINDS = ("bad: malformed json", "bad: samples over limit", "bad: start outside region",
             "bad: non-finite number")


# ---------------------------------------------------------------------------- request mix
def plan_fixed(rng: random.Random) -> dict[str, Any]:
    return {"start": START, "goal": GOAL, "method": "polynomial",
            "phi_change": rng.uniform(*DPHI_DEG) * DEG, "samples": 51}


def plan_searched(rng: random.Random) -> dict[str, Any]:
    return {"start": START, "goal": GOAL, "method": "polynomial", "samples": 51}


def transform(rng: random.Random) -> dict[str, Any]:
    return {"direction": "to_chained",
            "points": [[rng.uniform(-1, 1)] + [rng.uniform(0.05, 1.5) for _ in range(3)]
                       for _ in range(10)]}


def sweep(rng: random.Random) -> dict[str, Any]:
    lo = rng.uniform(0.4, 0.6)
    return {"start": START, "goal": GOAL, "phi_change_range": [lo, lo + 0.2], "points": 21,
            "intervals": False}


def robustness(rng: random.Random) -> dict[str, Any]:
    return {"plan": plan_fixed(rng), "random": {"count": 4, "spread": 0.01,
                                                "seed": rng.randrange(1000)}}


#: kind -> (method, path, body as bytes, expected status)
def bad_request(kind: str) -> tuple[str, bytes, int]:
    if kind == "bad: malformed json":
        return "/v1/plans", b'{"start": [0.17, 0.17,', 400
    if kind == "bad: samples over limit":
        return "/v1/plans", json.dumps({"start": START, "goal": GOAL,
                                        "samples": 10 ** 6}).encode(), 422
    if kind == "bad: start outside region":
        return "/v1/plans", json.dumps({"start": [100 * DEG, 0.2, 0.2], "goal": GOAL,
                                        "method": "polynomial"}).encode(), 422
    return "/v1/transforms", b'{"direction": "to_chained", "points": [[0, 0.2, NaN, 0.2]]}', 422


if "locust" in sys.modules:  # imported by `locust -f bench/load_test.py`: the simulated client
    from locust import FastHttpUser, constant, task

    class PlannerClient(FastHttpUser):
        """One client in a closed loop over the request mix."""

        wait_time = constant(0)
        network_timeout = 120.0
        connection_timeout = 30.0

        def on_start(self) -> None:
            self.rng = random.Random()

        def _post(self, name: str, path: str, body: dict[str, Any]) -> None:
            with self.client.post(path, json=body, name=name, catch_response=True) as r:
                if r.status_code != 200:
                    r.failure(f"status {r.status_code}: {(r.text or '')[:200]}")
                    return
                try:
                    json.loads(r.content)
                except ValueError as exc:
                    r.failure(f"not JSON: {exc}")
                    return
                r.success()

        @task(24)
        def plan_fixed_dphi(self) -> None:
            self._post("POST /v1/plans (fixed dphi)", "/v1/plans", plan_fixed(self.rng))

        @task(6)
        def plan_searched_dphi(self) -> None:
            self._post("POST /v1/plans (searched dphi)", "/v1/plans", plan_searched(self.rng))

        @task(20)
        def transforms(self) -> None:
            self._post("POST /v1/transforms", "/v1/transforms", transform(self.rng))

        @task(8)
        def sweeps(self) -> None:
            self._post("POST /v1/sweeps (21 points)", "/v1/sweeps", sweep(self.rng))

        @task(5)
        def robustness_runs(self) -> None:
            self._post("POST /v1/robustness (4 runs)", "/v1/robustness",
                       robustness(self.rng))

        @task(15)
        def default_robot(self) -> None:
            n = self.rng.randint(3, 8)
            with self.client.get(f"/v1/robots/default?n={n}", name="GET /v1/robots/default",
                                 catch_response=True) as r:
                if r.status_code != 200 or r.json().get("n") != n:
                    r.failure(f"status {r.status_code}")
                else:
                    r.success()

        @task(15)
        def healthz(self) -> None:
            with self.client.get("/healthz", name="GET /healthz", catch_response=True) as r:
                if r.status_code != 200:
                    r.failure(f"status {r.status_code}")
                else:
                    r.success()

        @task(7)
        def deliberate_bad_request(self) -> None:
            kind = self.rng.choice(BAD_KINDS)
            path, body, expected = bad_request(kind)
            # locust's hints say str, but bytes go out as they are (one body is not UTF-8)
            with self.client.post(path, data=body, name=kind,  # type: ignore[arg-type]
                                  catch_response=True,
                                  headers={"content-type": "application/json"}) as r:
                ok = (r.status_code == expected
                      and r.headers.get("content-type", "").startswith(
                          "application/problem+json")
                      and r.json().get("code") == "invalid_request")
                if ok:
                    r.success()
                else:
                    r.failure(f"expected {expected}, got {r.status_code}")


# ---------------------------------------------------------------------------- the driver
def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def memory(pid: int) -> dict[str, Any]:
    """RSS and USS (MB) of the server process and of each worker (and the tree's total RSS)."""
    import psutil

    root = psutil.Process(pid)
    out: dict[str, Any] = {"server_rss_mb": None, "workers": [], "total_rss_mb": 0.0}
    for proc in [root] + root.children(recursive=True):
        try:
            info = proc.memory_full_info()
            cmd = " ".join(proc.cmdline())
            parent = proc.ppid()
        except psutil.Error:
            continue
        rss, uss = info.rss / 2 ** 20, info.uss / 2 ** 20
        out["total_rss_mb"] += rss
        if proc.pid == pid:
            out["server_rss_mb"] = round(rss, 1)
        elif parent == pid and ("forkserver" in cmd or "resource_tracker" in cmd):
            continue  # the forkserver and the resource tracker (counted in the total)
        else:  # forked by the forkserver (they inherit its command line)
            out["workers"].append({"pid": proc.pid, "rss_mb": round(rss, 1),
                                   "uss_mb": round(uss, 1)})
    out["total_rss_mb"] = round(out["total_rss_mb"], 1)
    return out


def wait_ready(url: str, proc: subprocess.Popen[bytes], timeout: float = 180.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with {proc.returncode}")
        try:
            with urllib.request.urlopen(url + "/readyz", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.1)
    raise RuntimeError("the service did not become ready")


def _number(text: str) -> float | None:
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def read_stats(csv_prefix: Path) -> dict[str, dict[str, Any]]:
    """Locust's ``<prefix>_stats.csv``: per request kind and ``Aggregated``."""
    rows: dict[str, dict[str, Any]] = {}
    with open(f"{csv_prefix}_stats.csv", newline="", encoding="utf-8") as fh:
        for row in csv.DictReader(fh):
            name = row["Name"] if row["Name"] != "Aggregated" else "all"
            rows[name] = {
                "requests": int(row["Request Count"]), "errors": int(row["Failure Count"]),
                "rps": _number(row["Requests/s"]),
                "p50_ms": _number(row["50%"]), "p95_ms": _number(row["95%"]),
                "p99_ms": _number(row["99%"]), "max_ms": _number(row["Max Response Time"]),
                "mean_ms": _number(row["Average Response Time"]),
            }
    return rows


def read_failures(csv_prefix: Path) -> list[dict[str, Any]]:
    path = Path(f"{csv_prefix}_failures.csv")
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as fh:
        return [{"name": r["Name"], "error": r["Error"][:300], "count": int(r["Occurrences"])}
                for r in csv.DictReader(fh)]


def run(duration: float, users: int, workers: int | None, spawn_rate: float | None = None,
        locust_timeout: float | None = None) -> dict[str, Any]:
    """Start the service, drive it with locust for ``duration`` s, stop it; the report."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PLANNER_")}
    env.update(PLANNER_HOST="127.0.0.1", PLANNER_PORT=str(port), PLANNER_LOG_LEVEL="warning")
    if workers:
        env["PLANNER_WORKERS"] = str(workers)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    tmp = Path(tempfile.mkdtemp(prefix="load-test-"))
    server_log = open(tmp / "server.log", "wb")
    server = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=env,
                              stdout=server_log, stderr=subprocess.STDOUT)
    report: dict[str, Any] = {"url": url, "duration_s": duration, "users": users}
    try:
        wait_ready(url, server)
        with urllib.request.urlopen(url + "/readyz", timeout=5) as r:
            report["workers"] = json.load(r)["workers"]
        report["memory_start"] = memory(server.pid)
        prefix = tmp / "locust"
        locust = Path(sys.executable).with_name("locust")
        cmd = [str(locust) if locust.exists() else "locust", "-f", str(Path(__file__).resolve()),
               "--headless", "-u", str(users), "-r", str(spawn_rate or users),
               "-t", f"{duration:g}s", "--host", url, "--csv", str(prefix), "--only-summary",
               "--stop-timeout", "30", "--loglevel", "WARNING", "--exit-code-on-error", "0"]
        t0 = time.perf_counter()
        done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=locust_timeout or duration + 120)
        report["wall_s"] = round(time.perf_counter() - t0, 1)
        if done.returncode != 0:
            raise RuntimeError(f"locust exited with {done.returncode}: {done.stderr[-2000:]}")
        report["memory_end"] = memory(server.pid)
        stats = read_stats(prefix)
        report["failures"] = read_failures(prefix)
    finally:
        server.terminate()
        try:
            server.wait(30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(10)
        server_log.close()
    total = stats["all"]
    bad = {k: v for k, v in stats.items() if k in BAD_KINDS}
    report.update(
        requests=total["requests"], throughput_rps=total["rps"],
        p50_ms=total["p50_ms"], p95_ms=total["p95_ms"], p99_ms=total["p99_ms"],
        max_ms=total["max_ms"], errors=total["errors"],
        deliberate_bad_requests=sum(v["requests"] for v in bad.values()),
        deliberate_bad_answered_as_expected=sum(v["requests"] - v["errors"]
                                                for v in bad.values()),
        per_kind={k: v for k, v in stats.items() if k != "all"})
    return report


def render(report: dict[str, Any]) -> str:
    """A text summary of :func:`run`'s report."""
    def ms(x: float | None) -> str:
        return "-" if x is None else f"{x:.0f}"

    lines = [f"{report['users']} clients, {report['duration_s']:g} s, "
             f"{report['workers']} workers, {report['url']}",
             f"{'request':34s} {'n':>7s} {'rps':>7s} {'p50':>6s} {'p95':>6s} {'p99':>6s} "
             f"{'max':>6s} {'err':>5s}"]
    for name, row in sorted(report["per_kind"].items()):
        lines.append(f"{name:34s} {row['requests']:7d} {row['rps'] or 0:7.1f} "
                     f"{ms(row['p50_ms']):>6s} {ms(row['p95_ms']):>6s} "
                     f"{ms(row['p99_ms']):>6s} {ms(row['max_ms']):>6s} {row['errors']:5d}")
    lines.append(f"{'all':34s} {report['requests']:7d} {report['throughput_rps'] or 0:7.1f} "
                 f"{ms(report['p50_ms']):>6s} {ms(report['p95_ms']):>6s} "
                 f"{ms(report['p99_ms']):>6s} {ms(report['max_ms']):>6s} "
                 f"{report['errors']:5d}")
    lines.append(f"deliberate bad requests: {report['deliberate_bad_requests']} "
                 f"({report['deliberate_bad_answered_as_expected']} answered with their 4xx)")
    for when in ("memory_start", "memory_end"):
        m = report[when]
        workers = ", ".join(f"{w['rss_mb']:.0f}" for w in m["workers"])
        lines.append(f"{when.replace('_', ' ')}: server {m['server_rss_mb']:.0f} MB RSS, "
                     f"workers [{workers}] MB RSS, tree {m['total_rss_mb']:.0f} MB")
    for f in report["failures"]:
        lines.append(f"ERROR {f['count']} x {f['name']}: {f['error']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of load")
    parser.add_argument("--users", type=int, default=32, help="concurrent clients")
    parser.add_argument("--spawn-rate", type=float, default=None,
                        help="clients started per second (default: all at once)")
    parser.add_argument("--workers", type=int, default=None,
                        help="PLANNER_WORKERS (default: the service's, the CPU count)")
    parser.add_argument("--json", type=Path, default=None, help="write the report here")
    args = parser.parse_args(argv)
    report = run(args.duration, args.users, args.workers, args.spawn_rate)
    print(render(report))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return 0 if report["errors"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
