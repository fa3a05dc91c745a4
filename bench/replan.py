"""``python -m bench.replan``: closed-loop replanning (issue 29), measured.

Three parts, each on the benchmark's generated goals (:func:`bench.goals.generate`):

* **latency in process** (CPU time of this process, ``time.process_time``: the machine is
  shared): per goal a cold default plan (``plan()``, timed: the baseline of the same run), then replans of it (:func:`optimizer.planner.replan.replan`) at random times from
  states off the plan's by up to 0.5 deg, with the plan's rates at that time; p50 / p99 per
  ``n``, and the ratio of the cold plan's median to the replan's;
* **latency over HTTP** (``--http``): ``python -m service`` in a subprocess (one worker),
  ``POST /v1/replans`` with the whole earlier answer, then with its compact form,
  sequentially: wall-clock p50 / p99 and the server's CPU time per replan;
* **closed loop**: per goal a plant whose gains ``K_i`` are off by ``e_i`` uniform in +-5 %,
  a start off by up to +-0.5 deg per joint, the plan run open loop and in closed loop (a
  replan from the measured state every 0.05 s) by scipy's DOP853
  (:func:`optimizer.analysis.closed_loop_run`): the median ratio of the terminal errors,
  every joint inside throughout, no more reversals than the plan; with ``--identify`` the
  loop also estimates the plant's gains from the measured motion and replans on them
  (:mod:`optimizer.identification`), and the report gives both loops side by side, each
  with the CPU time of the replans it made (p50 / p99: the states a loop measures, where
  the latency part's are drawn at random).

Usage::

    .venv/bin/python -m bench.replan                       # n = 3..5, 5 goals each
    .venv/bin/python -m bench.replan --goals 3 --joints 3 --no-loop
    .venv/bin/python -m bench.replan --http

Compiled functions are on (:mod:`optimizer.native`, the service's default; ``--no-native``:
CasADi's virtual machine), and the replanner's kernels are compiled before anything is
timed (:func:`optimizer.planner.continuation_map.prepare`, ``build=True``): the cold plans
use the compiled NLP too. Timings depend on the machine's load (2 shared cores here):
compare the ratio to the cold plan, measured in the same run, rather than the milliseconds.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from typing import Any

import numpy as np

from optimizer.analysis import closed_loop_run
from optimizer.errors import PlannerError
from optimizer.planner.plan import plan
from optimizer.planner.continuation_map import prepare
from optimizer.planner.piece_proof import prepare as prepare_proof
from optimizer.planner.replan import replan
from optimizer.model import Robot
from optimizer.problem import PlanRequest

from .goals import generate

#: Seed of the perturbations (the goals have their own).
SEED = 29
DEG = math.pi / 180.0


def _perturbed_state(answer: dict[str, Any], rng: np.random.Generator,
                     spread_deg: float = 0.5) -> tuple[float, np.ndarray]:
    """A time in the plan's first 90 % and its handed-out state, the joints moved by up to
    ``spread_deg``."""
    t = np.asarray(answer["path"]["t"], float)
    q = np.asarray(answer["path"]["q"], float)
    i = int(rng.integers(0, int(0.9 * (t.size - 1))))
    state = q[i].copy()
    state[1:] += rng.uniform(-spread_deg, spread_deg, q.shape[1] - 1) * DEG
    return float(t[i]), state


def latency(joints: list[int], goals: int, replans: int,
            spread_deg: float = 0.5) -> dict[str, Any]:
    """Replan latency in process against a cold default plan (see the module), states off
    the plan's by up to ``spread_deg`` per joint."""
    rng = np.random.default_rng(SEED)
    out: dict[str, Any] = {}
    for n in joints:
        plans: list[float] = []
        times: list[float] = []
        routes: dict[str, int] = {}
        for g in generate(n, goals):
            req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(n))
            warm = plan(req).to_dict()             # the NLP built, as in a warm worker
            # the kernels compiled (when compiled functions are on: the service's default)
            prepare(tuple(req.robot.gains), tuple(req.robot.exponents), build=True)
            prepare_proof(tuple(req.robot.gains), tuple(req.robot.exponents), build=True)
            try:
                replan(warm, *_perturbed_state(warm, np.random.default_rng(0)))
            except PlannerError:
                pass
            t0 = time.process_time()
            answer = plan(req).to_dict()
            plans.append(time.process_time() - t0)
            for _ in range(replans):
                t, state = _perturbed_state(answer, rng, spread_deg)
                t1 = time.process_time()
                try:
                    cont = replan(answer, t, state, plain=False)
                    route = cont["diagnostics"]["replan"]["route"]
                except PlannerError as exc:
                    route = f"refused ({exc.code})"
                times.append(time.process_time() - t1)
                routes[route] = routes.get(route, 0) + 1
        p50, p99 = (float(np.percentile(times, q)) for q in (50, 99))
        out[str(n)] = {"replans": len(times), "p50_ms": 1e3 * p50, "p99_ms": 1e3 * p99,
                       "cold_plan_median_ms": 1e3 * float(np.median(plans)),
                       "plan_over_replan": float(np.median(plans)) / p50, "routes": routes}
    return out


def _tree_cpu(pid: int) -> float:
    """CPU seconds (user + system) of a process and its children so far."""
    import psutil

    total = 0.0
    try:
        root = psutil.Process(pid)
        for p in [root, *root.children(recursive=True)]:
            try:
                c = p.cpu_times()
                total += c.user + c.system
            except psutil.Error:
                pass
    except psutil.Error:
        pass
    return total


def http_latency(replans: int) -> dict[str, Any]:
    """``POST /v1/replans`` against ``python -m service`` (one worker), sequentially: wall
    clock per request (inflated by a shared machine's load) and CPU seconds of the server's
    process tree per request (the event loop and the worker: what a replan costs the
    server), once with the whole earlier answer sent back and once with its compact form."""
    import httpx

    from optimizer.planner.plan_state import read_plan

    from .http_load import Server

    server = Server({"PLANNER_WORKERS": "1"})
    server.start()
    out: dict[str, Any] = {}
    try:
        with httpx.Client(base_url=server.url, timeout=60.0) as client:
            deadline = time.monotonic() + 180.0
            while time.monotonic() < deadline:
                try:
                    if client.get("/readyz").status_code == 200:
                        break
                except httpx.HTTPError:
                    pass
                time.sleep(0.5)
            g = generate(3, 1)[0]
            answer = client.post("/v1/plans", json={"start": list(g.start),
                                                    "goal": list(g.goal)}).json()
            assert server.proc is not None
            for form, plan_sent in (("answer", answer),
                                    ("compact", read_plan(answer).compact())):
                rng = np.random.default_rng(SEED)
                for _ in range(3):       # the worker's first replans (maps built, caches)
                    t, state = _perturbed_state(answer, rng, 0.05)
                    client.post("/v1/replans", json={"plan": plan_sent, "time": t,
                                                     "state": state.tolist()})
                times, sizes = [], []
                cpu0 = _tree_cpu(server.proc.pid)
                for _ in range(replans):
                    t, state = _perturbed_state(answer, rng, 0.05)
                    body = {"plan": plan_sent, "time": t, "state": state.tolist()}
                    t0 = time.perf_counter()
                    r = client.post("/v1/replans", json=body)
                    times.append(time.perf_counter() - t0)
                    if r.status_code == 200:
                        sizes.append(len(r.content))
                cpu = (_tree_cpu(server.proc.pid) - cpu0) / max(replans, 1)
                out[form] = {"replans": len(times),
                             "p50_ms": 1e3 * float(np.percentile(times, 50)),
                             "p99_ms": 1e3 * float(np.percentile(times, 99)),
                             "server_cpu_ms": 1e3 * cpu,
                             "request_bytes": len(json.dumps(body)),
                             "answer_bytes": int(np.median(sizes)) if sizes else 0,
                             "answered": len(sizes)}
            t0 = time.perf_counter()
            client.post("/v1/plans", json={"start": list(g.start), "goal": list(g.goal)})
            out["one_plan_ms"] = 1e3 * (time.perf_counter() - t0)
    finally:
        server.stop()
    return out


def closed_loop(joints: list[int], goals: int, gain_error: float, spread_deg: float,
                period: float, keep_reversals: bool = False,
                identify: bool = False) -> dict[str, Any]:
    """Open against closed loop on perturbed plants (see the module)."""
    rng = np.random.default_rng(SEED + 1)
    out: dict[str, Any] = {}
    for n in joints:
        rows = []
        loop_seconds: list[float] = []
        for g in generate(n, goals):
            p = plan(PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(n)))
            answer = p.to_dict()
            start = np.asarray(g.start) + rng.uniform(-spread_deg, spread_deg, n) * DEG
            e = rng.uniform(-gain_error, gain_error, n - 1)
            op = closed_loop_run(answer, start, e, None)
            cl = closed_loop_run(answer, start, e, period, keep_reversals=keep_reversals,
                                 identify=identify, timings=loop_seconds)
            nominal = p.indicators.reversals_phi + p.indicators.reversals_th1
            rows.append({"goal": g.name, "open": op["terminal_error"],
                         "closed": cl["terminal_error"],
                         "ratio": op["terminal_error"] / max(cl["terminal_error"], 1e-300),
                         "inside": cl["margin"] > 0.0, "reversals_plan": nominal,
                         "reversals_open": op["reversals"], "reversals_closed": cl["reversals"],
                         "replan_failures": cl["replan_failures"],
                         **({"gain_estimate_error": float(np.max(np.abs(
                             np.asarray(cl["gains_estimated"])
                             / (np.asarray(p.robot.gains) * (1.0 + e)) - 1.0)))}
                            if identify else {})})
        ratios = [r["ratio"] for r in rows]
        out[str(n)] = {
            "goals": len(rows),
            "open_median_rad": float(np.median([r["open"] for r in rows])),
            "closed_median_rad": float(np.median([r["closed"] for r in rows])),
            "ratio_of_medians": float(np.median([r["open"] for r in rows])
                                      / np.median([r["closed"] for r in rows])),
            "ratio_median": float(np.median(ratios)),
            "inside": sum(r["inside"] for r in rows),
            "no_more_reversals": sum(r["reversals_closed"] <= r["reversals_plan"] for r in rows),
            # the replans this loop made (CPU time; the first of each run corrects the start
            # error, the later ones a period's drift)
            "replan_p50_ms": 1e3 * float(np.percentile(loop_seconds, 50)),
            "replan_p99_ms": 1e3 * float(np.percentile(loop_seconds, 99)),
            "rows": rows}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.replan", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--joints", type=int, nargs="+", default=[3, 4, 5])
    ap.add_argument("--goals", type=int, default=5, help="goals per n (default 5)")
    ap.add_argument("--replans", type=int, default=40, help="replans per goal (latency)")
    ap.add_argument("--http", action="store_true", help="also measure over HTTP")
    ap.add_argument("--state-error-deg", type=float, default=0.05,
                    help="latency: states off the plan's by up to this per joint (default "
                         "0.05 deg: a 0.05 s period's drift under 5 %% gain errors)")
    ap.add_argument("--no-loop", action="store_true", help="skip the closed-loop runs")
    ap.add_argument("--gain-error", type=float, default=0.05)
    ap.add_argument("--spread-deg", type=float, default=0.5)
    ap.add_argument("--period", type=float, default=0.05)
    ap.add_argument("--keep-reversals", action="store_true",
                    help="closed loop: refuse continuations that add reversals")
    ap.add_argument("--identify", action="store_true",
                    help="closed loop: also run it estimating the plant's gains as it goes")
    ap.add_argument("--no-native", action="store_true",
                    help="CasADi's virtual machine only (no compiled kernels)")
    ap.add_argument("--out", help="write the JSON here too")
    args = ap.parse_args(argv)
    from .inprocess import configure_native

    report: dict[str, Any] = {"native": configure_native(args.no_native)}
    report["latency"] = latency(args.joints, args.goals, args.replans, args.state_error_deg)
    if args.http:
        report["http"] = http_latency(10 * args.replans)
    if not args.no_loop:
        report["closed_loop"] = closed_loop(args.joints, args.goals, args.gain_error,
                                            args.spread_deg, args.period, args.keep_reversals)
        if args.identify:
            report["closed_loop_identified"] = closed_loop(
                args.joints, args.goals, args.gain_error, args.spread_deg, args.period,
                args.keep_reversals, identify=True)
    print(f"compiled functions: {report['native']}")
    print(f"latency: states off the plan by up to {args.state_error_deg:g} deg per joint")
    for n, r in report["latency"].items():
        print(f"n = {n}: replan p50 {r['p50_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms; cold "
              f"default plan median {r['cold_plan_median_ms']:.1f} ms "
              f"({r['plan_over_replan']:.1f}x); routes {r['routes']}")
    for form, h in report.get("http", {}).items():
        if isinstance(h, dict):
            print(f"HTTP ({form} sent back, {h['request_bytes']} B): replan wall p50 "
                  f"{h['p50_ms']:.2f} ms, p99 {h['p99_ms']:.2f} ms; server CPU "
                  f"{h['server_cpu_ms']:.2f} ms per replan ({h['replans']} sequential, "
                  f"answer {h['answer_bytes']} B, {h['answered']} answered)")
    loops = [("closed loop", report.get("closed_loop", {})),
             ("closed loop, gains identified", report.get("closed_loop_identified", {}))]
    for label, n, r in ((label, n, r) for label, rs in loops for n, r in rs.items()):
        print(f"{label} n = {n} ({r['goals']} goals): terminal error median open "
              f"{r['open_median_rad']:.3g} rad, closed {r['closed_median_rad']:.3g} rad, median "
              f"ratio {r['ratio_median']:.0f}x; inside {r['inside']}/{r['goals']}; no more "
              f"reversals than the plan {r['no_more_reversals']}/{r['goals']}; its replans "
              f"p50 {r['replan_p50_ms']:.2f} ms, p99 {r['replan_p99_ms']:.2f} ms (CPU)")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(report, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
