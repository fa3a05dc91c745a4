"""The benchmark on generated goals (issue 15): the default request, every method and the baseline.

Usage::

    .venv/bin/python -m bench.goals_run                       # 60 / 25 / 15 goals (n = 3 / 4 / 5)
    .venv/bin/python -m bench --goals                         # the same
    .venv/bin/python -m bench.goals_run --goals-counts 3:30,4:10,5:8 --repeats 3
    .venv/bin/python -m bench.goals_run --goals-counts 3:3,4:1 --repeats 1 \\
        --methods polynomial,retimed --out /tmp/g.json --md /tmp/g.md   # smoke test

For every goal of :func:`bench.goals.benchmark_goals`, in one process and one run:

* the DEFAULT request, ``PlanRequest(start, goal, robot=Robot.default(n), time_limit=10)``
  (method ``auto``, objective ``reversals_then_deviation``), timed in-process: one warm-up call
  (not counted), then the median of up to ``--repeats`` calls;
* each registered method (``--methods``, default every one in ``optimizer.planner.registry``),
  the same request with ``method=...``, timed the same way (fewer repeats when a call is slow);
* on n = 3, the multiple-shooting baseline (:mod:`bench.baselines.multiple_shooting`): built
  once (its build is timed apart and excluded), its ``solve`` timed like a plan.

Every path is re-integrated with scipy from its exact segments (:mod:`bench.reintegrate`). A
plan is VERIFIED when its re-integrated terminal error is below :data:`TERMINAL_TOL` rad and every
joint ``th_1..th_n`` stays strictly inside ``(0, pi/2)`` on the whole re-integrated path.

The report (Markdown, printed and written to ``docs/benchmark-goals.md`` unless ``--md``; JSON to
``bench/results/goals_<UTC stamp>.json`` unless ``--out``) gives per n the verified goals and the
default plan's p50/p95/max time, per method the successes and median time, on n = 3 the
comparison with the baseline, the issue's targets next to the numbers and the goals that miss
one.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.goals import COUNTS, Goal, benchmark_goals  # noqa: E402
from bench.inprocess import Baselines, configure_native, describe, status_of  # noqa: E402
from bench.reintegrate import reintegrate_baseline, reintegrate_plan  # noqa: E402
from bench.stats import time_repeats  # noqa: E402

#: Re-integrated terminal error (rad) below which a path reaches its goal.
TERMINAL_TOL = 1e-6
#: Slack (rad) of "the default plan's deviation is no larger than the baseline's".
DEVIATION_TOL = 1e-6
#: A default plan is "near its time limit" when a call took at least this share of it.
NEAR_LIMIT_SHARE = 0.5
#: The issue's targets.
TARGET_SHARE = 0.90
TARGET_SPEED_RATIO = 3.0
TARGET_P95_S = {3: 0.030, 4: 0.100, 5: 0.100}
#: The baseline runs on these numbers of joints only (the issue compares on n = 3).
BASELINE_JOINTS = (3,)


@dataclass
class GoalsConfig:
    """How the run measures.

    Attributes
    ----------
    repeats : int
        Largest number of timed calls after the warm-up (default plan, methods, baseline).
    budget : float
        Seconds of timed calls per (goal, method): a slow method gets fewer repeats (at least
        one), so that a 5-joint NLP does not take the run's whole hour.
    time_limit : float
        ``PlanRequest.time_limit`` (s).
    methods : tuple of str
        Registered methods run besides the default request.
    """

    repeats: int = 5
    budget: float = 2.0
    time_limit: float = 10.0
    methods: tuple[str, ...] = ()


def parse_counts(text: str) -> dict[int, int]:
    """``"3:60,4:25"`` -> ``{3: 60, 4: 25}``."""
    out: dict[int, int] = {}
    for part in text.split(","):
        if part.strip():
            n, k = part.split(":")
            out[int(n)] = int(k)
    return out


def verified(m: dict[str, Any] | None) -> bool:
    """The re-integrated path reaches the goal and keeps every joint strictly inside."""
    if not m or not m.get("ok"):
        return False
    err, margin = m.get("terminal_error_rad"), m.get("region_margin_all_deg")
    return (err is not None and margin is not None and math.isfinite(err)
            and math.isfinite(margin) and err < TERMINAL_TOL and margin > 0.0)


def _request(g: Goal, time_limit: float, method: str | None,
             limits: dict[str, float] | None = None) -> Any:
    from optimizer.model import Robot
    from optimizer.problem import PlanRequest
    if method is None:  # the user's default request: nothing but start, goal, robot, limit
        return PlanRequest.from_dict({"start": g.start, "goal": g.goal,
                                      "robot": Robot.default(g.n), "time_limit": time_limit,
                                      **(limits or {})})
    return PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(g.n),
                       time_limit=time_limit, method=method)


def prepare_native(n: int) -> dict[str, Any]:
    """Build or load the compiled NLP functions of ``n`` joints before anything is timed (a
    one-off per machine, like the baseline's build)."""
    from optimizer.model import Robot
    from optimizer.planner import penalty, shooting
    robot = Robot.default(n)
    t0 = time.perf_counter()
    compiled = [prep(robot.gains, robot.exponents, wait=True).compiled
                for prep in (shooting.prepare, penalty.prepare)]
    return {"compiled": all(compiled), "seconds": time.perf_counter() - t0}


def run_plan(g: Goal, method: str | None, cfg: GoalsConfig) -> dict[str, Any]:
    """Time one request on ``g`` (``method=None``: the default request) and re-integrate it."""
    from optimizer.planner.plan import plan
    out: dict[str, Any] = {"method": method or "default"}
    try:
        req = _request(g, cfg.time_limit, method)
    except Exception as exc:  # noqa: BLE001 - recorded
        out.update(status="error", error=describe(exc), verified=False)
        return out
    call: Callable[[], Any] = lambda: plan(req)  # noqa: E731
    timed = time_repeats(call, cfg.repeats, cfg.budget, 1)
    out["status"] = status_of(timed.error)
    out["error"] = describe(timed.error)
    out["first_call"] = timed.first
    out["time"] = timed.summary.as_dict()
    # the slowest call, warm-up included: what a user waiting on the limit would see
    out["slowest_call"] = max([timed.first] + list(timed.summary.samples))
    if timed.repeat_errors:
        out["repeat_errors"] = sorted(set(e[:300] for e in timed.repeat_errors))
    p = timed.result
    if p is None:
        out["verified"] = False
        return out
    if timed.error is not None:  # the warm-up failed, a repeat did not
        out["status"] = "flaky"
    ind = p.indicators
    out["chosen_method"] = p.method
    out["planner"] = {"deviation_deg": math.degrees(ind.deviation),
                      "reversals_phi": int(ind.reversals_phi),
                      "reversals_th1": int(ind.reversals_th1)}
    out["handed_out"] = handed_out_checks(p)
    rm = reintegrate_plan(p, np.asarray(g.start), np.asarray(g.goal)).as_dict()
    out["reintegration"] = rm
    out["verified"] = verified(rm)
    return out


#: The limits of the limited request of every goal (issue 25): max_u = 1 rad/s, max_du = 5
#: rad/s^2 on both actuators, checked within :data:`LIMIT_SHARE` on the handed-out form.
LIMITS = {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0}
LIMIT_SHARE = 1.01


def handed_out_checks(p: Any, limits: dict[str, float] | None = None) -> dict[str, Any]:
    """The handed-out linear form of a plan: rates 0 at both ends, no repeated time (no
    jump), and with ``limits`` the largest rates and slopes (its derivative between samples)
    against them."""
    t, u = np.asarray(p.path.t), np.asarray(p.path.u)
    out: dict[str, Any] = {"rest_at_ends": bool(np.all(u[0] == 0.0) and np.all(u[-1] == 0.0)),
                           "continuous": bool(np.all(np.diff(t) > 0.0)),
                           "duration": float(p.duration)}
    if limits:
        slope = np.abs(np.diff(u, axis=0) / np.diff(t)[:, None])
        peak_u, peak_du = np.abs(u).max(axis=0), slope.max(axis=0)
        ratio = max(max(peak_u[c] / limits[f"max_u{c + 1}"] for c in range(2)),
                    max(peak_du[c] / limits[f"max_du{c + 1}"] for c in range(2)))
        out.update(limit_ratio=float(ratio), within_limits=bool(ratio <= LIMIT_SHARE))
    return out


def run_limited(g: Goal, cfg: GoalsConfig) -> dict[str, Any]:
    """The default request with :data:`LIMITS` (one untimed call): its handed-out checks."""
    from optimizer.planner.plan import plan
    try:
        req = _request(g, cfg.time_limit, None, LIMITS)
        p = plan(req)
    except Exception as exc:  # noqa: BLE001 - recorded
        return {"status": "error", "error": describe(exc)}
    return {"status": "success", **handed_out_checks(p, LIMITS)}


def run_baseline(g: Goal, baselines: Baselines, cfg: GoalsConfig) -> dict[str, Any]:
    """Time the baseline's ``solve`` on ``g`` (its build excluded) and re-integrate it."""
    out: dict[str, Any] = {"method": "baseline"}
    start, goal = np.asarray(g.start), np.asarray(g.goal)
    try:
        bl = baselines.get(g.n)
    except Exception as exc:  # noqa: BLE001 - recorded
        out.update(status="error", error=describe(exc), verified=False)
        return out
    timed = time_repeats(lambda: bl.solve(start, goal), cfg.repeats, cfg.budget, 1)
    out["first_call"] = timed.first
    out["time"] = timed.summary.as_dict()
    res = timed.result
    if timed.error is not None or res is None:
        out.update(status="error", error=describe(timed.error), verified=False)
        return out
    out["status"] = "success" if res.success else "solver_failure"
    out["ipopt_status"] = res.return_status
    rm = reintegrate_baseline(res, bl.gains, bl.exponents, start, goal).as_dict()
    out["reintegration"] = rm
    out["verified"] = verified(rm)
    return out


def run_goal(g: Goal, baselines: Baselines, cfg: GoalsConfig,
             log: Callable[[str], None] = print) -> dict[str, Any]:
    """The default request, each method and (n = 3) the baseline on one goal."""
    t0 = time.perf_counter()
    default = run_plan(g, None, cfg)
    default["limited"] = run_limited(g, cfg)
    methods = {m: run_plan(g, m, cfg) for m in cfg.methods}
    base = run_baseline(g, baselines, cfg) if g.n in BASELINE_JOINTS else None
    row: dict[str, Any] = {"name": g.name, "kind": g.kind, "n": g.n,
                           "start": list(g.start), "goal": list(g.goal),
                           "default": default, "methods": methods, "baseline": base,
                           "wall_time": time.perf_counter() - t0}
    med = default.get("time", {}).get("median", math.nan)
    dev = (default.get("reintegration") or {}).get("segment_dev_deg", math.nan)
    text = (f"  {g.name}: default {default['status']} "
            f"{'verified' if default['verified'] else 'NOT verified'} {med * 1e3:.1f} ms, "
            f"dev {dev:.3g} deg")
    if base is not None:
        bmed = base.get("time", {}).get("median", math.nan)
        bdev = (base.get("reintegration") or {}).get("segment_dev_deg", math.nan)
        text += f"; baseline {base['status']} {bmed * 1e3:.1f} ms, dev {bdev:.3g} deg"
    fails = [m for m, r in methods.items() if not r["verified"]]
    if fails:
        text += f"; not verified: {', '.join(fails)}"
    log(text)
    return row


# ----------------------------------------------------------------------------- summary


def _pct(xs: Sequence[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else math.nan


def _reversals(m: dict[str, Any] | None) -> int | None:
    if not m or not m.get("ok"):
        return None
    return int(m["reversals_phi"]) + int(m["reversals_th1"])


def compare_with_baseline(row: dict[str, Any]) -> dict[str, Any] | None:
    """Per-goal comparison of the default plan with the baseline (None without a baseline
    path). A default plan that is not verified is no better than anything."""
    base = row.get("baseline")
    if not base or base.get("status") != "success" or not base.get("reintegration", {}).get("ok"):
        return None
    d, b = row["default"], base
    dm, bm = d.get("reintegration"), b["reintegration"]
    ok = d["verified"]
    dev_d = dm["segment_dev_deg"] if ok else math.nan
    dev_b = bm["segment_dev_deg"]
    rev_d, rev_b = (_reversals(dm) if ok else None), _reversals(bm)
    t_d, t_b = d["time"]["median"], b["time"]["median"]
    return {
        "default_dev_deg": dev_d, "baseline_dev_deg": dev_b,
        "dev_no_larger": bool(ok and math.radians(dev_d) <= math.radians(dev_b) + DEVIATION_TOL),
        "default_reversals": rev_d, "baseline_reversals": rev_b,
        "reversals_no_more": bool(ok and rev_d is not None and rev_b is not None
                                  and rev_d <= rev_b),
        "fewer_reversals": bool(ok and rev_d is not None and rev_b is not None
                                and rev_d < rev_b),
        "speed_ratio": (t_b / t_d) if (t_d and t_d > 0) else math.nan,
        "default_time": t_d, "baseline_time": t_b,
    }


def summarise_goals(rows: list[dict[str, Any]], cfg: GoalsConfig) -> dict[str, Any]:
    """Per n, per method and against the baseline; the targets; the goals that miss one."""
    per_n: dict[str, Any] = {}
    targets: list[dict[str, Any]] = []
    misses: list[dict[str, Any]] = []
    for n in sorted({r["n"] for r in rows}):
        sub = [r for r in rows if r["n"] == n]
        times = [r["default"]["time"]["median"] for r in sub
                 if math.isfinite(r["default"]["time"]["median"])]
        near = [r for r in sub
                if r["default"]["slowest_call"] >= NEAR_LIMIT_SHARE * cfg.time_limit]
        nver = sum(r["default"]["verified"] for r in sub)
        methods: dict[str, Any] = {}

        def per_goal_ratio(num: Callable[[dict[str, Any]], Any],
                           den: Callable[[dict[str, Any]], Any]) -> float:
            """Median over the goals where both ran and verified of num(row) / den(row)."""
            out = []
            for r in sub:
                a, b = num(r), den(r)
                if (a and b and a.get("verified") and b.get("verified")
                        and math.isfinite(a["time"]["median"]) and b["time"]["median"] > 0):
                    out.append(a["time"]["median"] / b["time"]["median"])
            return _pct(out, 50)

        for m in ["default"] + list(cfg.methods):
            runs = [r["default"] if m == "default" else r["methods"][m] for r in sub]
            mt = [x["time"]["median"] for x in runs if math.isfinite(x["time"]["median"])]

            def run_of(r: dict[str, Any], m: str = m) -> Any:
                return r["default"] if m == "default" else r["methods"][m]

            methods[m] = {"success": sum(x["status"] == "success" for x in runs),
                          "verified": sum(bool(x["verified"]) for x in runs),
                          "median_time": _pct(mt, 50), "goals": len(runs),
                          # issue 14's measures: median per goal, same run
                          "baseline_over_method": per_goal_ratio(
                              lambda r: r.get("baseline"), run_of),
                          "method_over_shooting": (per_goal_ratio(
                              run_of, lambda r: r["methods"]["shooting"])
                              if "shooting" in cfg.methods else math.nan),
                          "failures": {x_name: x["status"] if x["status"] != "success"
                                       else "not verified"
                                       for x_name, x in zip((r["name"] for r in sub), runs)
                                       if not x["verified"]}}
        ho = [r["default"].get("handed_out") or {} for r in sub]
        lim = [r["default"].get("limited") or {} for r in sub]
        entry: dict[str, Any] = {
            "goals": len(sub), "verified": nver, "p50": _pct(times, 50), "p95": _pct(times, 95),
            "max": max(times) if times else math.nan, "near_limit": len(near),
            "methods": methods,
            # issue 25: what a motor is asked to do
            "rest_at_ends": sum(bool(h.get("rest_at_ends")) for h in ho),
            "continuous": sum(bool(h.get("continuous")) for h in ho),
            "limited_planned": sum(x.get("status") == "success" for x in lim),
            "limited_within": sum(bool(x.get("within_limits")) for x in lim),
            "limited_worst_ratio": max([x["limit_ratio"] for x in lim if "limit_ratio" in x],
                                       default=math.nan)}
        p95_bound = TARGET_P95_S.get(n, max(TARGET_P95_S.values()))
        targets += [
            {"n": n, "target": "every goal verified", "measured": f"{nver}/{len(sub)}",
             "met": nver == len(sub)},
            {"n": n, "target": f"p95 of the default plan <= {p95_bound * 1e3:.0f} ms",
             "measured": f"{entry['p95'] * 1e3:.1f} ms", "met": entry["p95"] <= p95_bound},
            {"n": n, "target": "no default plan near its time limit",
             "measured": f"{len(near)} within {NEAR_LIMIT_SHARE:.0%} of {cfg.time_limit:g} s",
             "met": not near},
        ]
        cmps = [(r, compare_with_baseline(r)) for r in sub]
        have = [(r, c) for r, c in cmps if c is not None]
        if n in BASELINE_JOINTS and have:
            k = len(have)
            dev_ok = sum(c["dev_no_larger"] for _, c in have)
            dev_or_fewer = sum(c["dev_no_larger"] or c["fewer_reversals"] for _, c in have)
            rev_ok = sum(c["reversals_no_more"] for _, c in have)
            ratios = [c["speed_ratio"] for _, c in have if math.isfinite(c["speed_ratio"])]
            entry["baseline"] = {
                "compared": k, "baseline_failed": len(sub) - k,
                # the baseline keeps th1..th_{n-1} in its box at the nodes only: say how many of
                # its paths would pass the default plan's own check
                "baseline_verified": sum(bool(r["baseline"]["verified"]) for r, _ in have),
                "baseline_median_time": _pct([c["baseline_time"] for _, c in have], 50),
                "dev_no_larger": dev_ok, "reversals_no_more": rev_ok,
                "dev_no_larger_or_fewer_reversals": dev_or_fewer,
                "median_speed_ratio": _pct(ratios, 50),
                "per_goal": {r["name"]: c for r, c in have}}
            targets += [
                {"n": n, "target": "deviation no larger than the baseline's on >= 90 % of goals",
                 "measured": f"{dev_ok}/{k} = {dev_ok / k:.0%}",
                 "met": dev_ok >= TARGET_SHARE * k},
                {"n": n, "target": "reversals no more than the baseline's on >= 90 % of goals",
                 "measured": f"{rev_ok}/{k} = {rev_ok / k:.0%}",
                 "met": rev_ok >= TARGET_SHARE * k},
                {"n": n, "target": "median speed ratio (baseline solve / default plan) >= 3",
                 "measured": f"{entry['baseline']['median_speed_ratio']:.2f}",
                 "met": entry["baseline"]["median_speed_ratio"] >= TARGET_SPEED_RATIO},
            ]
        elif n in BASELINE_JOINTS:  # nothing to compare with: the targets are not shown met
            targets.append({"n": n, "target": "comparison with the baseline",
                            "measured": "no baseline solution", "met": False})
        for r, c in cmps:
            d = r["default"]
            why: list[str] = []
            if not d["verified"]:
                rm = d.get("reintegration") or {}
                why.append(f"not verified ({d['status']}"
                           + (f", terminal error {rm.get('terminal_error_rad', math.nan):.2g} rad"
                              f", margin {rm.get('region_margin_all_deg', math.nan):.3g} deg"
                              if rm else "")
                           + (f": {d['error'][:120]}" if d.get("error") else "") + ")")
            if d["time"]["median"] > p95_bound:
                why.append(f"slow: {d['time']['median'] * 1e3:.1f} ms > {p95_bound * 1e3:.0f} ms")
            if d["slowest_call"] >= NEAR_LIMIT_SHARE * cfg.time_limit:
                why.append(f"near the time limit: {d['slowest_call']:.2f} s")
            if c is not None:
                if not c["dev_no_larger"]:
                    why.append(f"deviation {c['default_dev_deg']:.4g} deg > baseline "
                               f"{c['baseline_dev_deg']:.4g} deg"
                               + (f" (with fewer reversals: {c['default_reversals']} < "
                                  f"{c['baseline_reversals']})" if c["fewer_reversals"]
                                  else ""))
                if not c["reversals_no_more"]:
                    why.append(f"reversals {c['default_reversals']} > baseline "
                               f"{c['baseline_reversals']}")
                if c["speed_ratio"] < TARGET_SPEED_RATIO:
                    why.append(f"speed ratio {c['speed_ratio']:.2f} < 3")
            elif n in BASELINE_JOINTS and r.get("baseline"):
                why.append(f"baseline {r['baseline']['status']}: not compared")
            if why:
                misses.append({"name": r["name"], "kind": r["kind"], "n": n,
                               "chosen_method": d.get("chosen_method"), "why": why})
        per_n[str(n)] = entry
    return {"per_n": per_n, "targets": targets, "misses": misses}


# ----------------------------------------------------------------------------- report


def _ms(x: Any) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x * 1e3:.1f}"


def markdown(results: dict[str, Any]) -> str:
    """The Markdown report of a run."""
    s = results["summary"]
    meta = results["meta"]
    lines = [f"## Generated goals (issue 15) -- {meta['timestamp']}, commit {meta['commit']}",
             "",
             f"`{meta['command']}`; {meta['cpus']} CPUs, load {meta['loadavg_start']} -> "
             f"{meta.get('loadavg_end')}; native NLP: {meta['native'].get('on')}; "
             f"time limit {results['config']['time_limit']:g} s; up to "
             f"{results['config']['repeats']} timed calls after a warm-up; "
             f"wall {meta.get('wall_time', math.nan):.0f} s.",
             "",
             "Verified = scipy re-integration ends within 1e-6 rad of the goal and every joint "
             "stays strictly inside (0, 90 deg). Times: per-goal median, in-process.",
             "",
             "### Default request, per n", "",
             "| n | goals | verified | p50 ms | p95 ms | max ms | near limit |",
             "|---|---|---|---|---|---|---|"]
    for n, e in s["per_n"].items():
        lines.append(f"| {n} | {e['goals']} | {e['verified']} | {_ms(e['p50'])} | "
                     f"{_ms(e['p95'])} | {_ms(e['max'])} | {e['near_limit']} |")
    lines += ["", "### Handed-out rates (issue 25)", "",
              "Default request: rates 0 at both ends, no repeated time (continuous rates). "
              f"Limited request (the default with {LIMITS}): planned, and its linear form's "
              f"rates and slopes within {LIMIT_SHARE - 1:.0%} of the limits.", "",
              "| n | goals | rest at ends | continuous | limited planned | within limits "
              "| worst peak / limit |", "|---|---|---|---|---|---|---|"]
    for n, e in s["per_n"].items():
        lines.append(f"| {n} | {e['goals']} | {e.get('rest_at_ends', '-')} | "
                     f"{e.get('continuous', '-')} | {e.get('limited_planned', '-')} | "
                     f"{e.get('limited_within', '-')} | "
                     f"{e.get('limited_worst_ratio', math.nan):.4f} |")
    lines += ["", "### Per method (success = planner answered; verified = re-integration)", "",
              "| n | method | success | verified | median ms (all goals) | baseline / method "
              "(median per goal) | method / shooting (median per goal) |",
              "|---|---|---|---|---|---|---|"]

    def _x(v: Any) -> str:
        return "-" if v is None or not math.isfinite(v) else f"{v:.2f}"

    for n, e in s["per_n"].items():
        for m, me in e["methods"].items():
            lines.append(f"| {n} | {m} | {me['success']}/{me['goals']} | "
                         f"{me['verified']}/{me['goals']} | {_ms(me['median_time'])} | "
                         f"{_x(me.get('baseline_over_method'))} | "
                         f"{_x(me.get('method_over_shooting'))} |")
    for n, e in s["per_n"].items():
        b = e.get("baseline")
        if not b:
            continue
        k = b["compared"]
        lines += ["", f"### n = {n} against the baseline (same goals, same run)", "",
                  f"compared on {k} goals (baseline failed on {b['baseline_failed']}; "
                  f"{b['baseline_verified']} of its {k} paths pass the verification); "
                  f"baseline median solve {_ms(b['baseline_median_time'])} ms", "",
                  "| measure | value | target |", "|---|---|---|",
                  f"| deviation no larger | {b['dev_no_larger']}/{k} "
                  f"({b['dev_no_larger'] / k:.0%}) | >= 90 % |",
                  f"| reversals (phi + th1) no more | {b['reversals_no_more']}/{k} "
                  f"({b['reversals_no_more'] / k:.0%}) | >= 90 % |",
                  f"| deviation no larger, or fewer reversals (the default rule's order) | "
                  f"{b['dev_no_larger_or_fewer_reversals']}/{k} "
                  f"({b['dev_no_larger_or_fewer_reversals'] / k:.0%}) | - |",
                  f"| median speed ratio | {b['median_speed_ratio']:.2f} | >= 3 |"]
    lines += ["", "### Targets", "", "| n | target | measured | met |", "|---|---|---|---|"]
    for t in s["targets"]:
        lines.append(f"| {t['n']} | {t['target']} | {t['measured']} | "
                     f"{'yes' if t['met'] else '**no**'} |")
    lines += ["", f"### Goals that miss a target ({len(s['misses'])})", ""]
    if not s["misses"]:
        lines.append("none")
    for m in s["misses"]:
        lines.append(f"- `{m['name']}` ({m['kind']}, chose {m['chosen_method']}): "
                     + "; ".join(m["why"]))
    fails = [(n, m, me["failures"]) for n, e in s["per_n"].items()
             for m, me in e["methods"].items() if me["failures"] and m != "default"]
    if fails:
        lines += ["", "### Methods without a verified plan", ""]
        for n, m, f in fails:
            lines.append(f"- n = {n}, {m}: " + ", ".join(f"`{g}` ({why})" for g, why in f.items()))
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- CLI


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    from optimizer.planner.registry import METHODS
    p = argparse.ArgumentParser(prog="python -m bench.goals_run", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--goals-counts", default=",".join(f"{n}:{k}" for n, k in COUNTS.items()),
                   help="goals per number of joints, e.g. 3:60,4:25,5:15 (the default)")
    p.add_argument("--repeats", type=int, default=5,
                   help="largest number of timed calls after the warm-up (default 5)")
    p.add_argument("--budget", type=float, default=2.0,
                   help="seconds of timed calls per goal and method; slow ones get fewer "
                        "repeats, at least one (default 2)")
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated registered methods besides the default request "
                        "(default: every one; empty: none)")
    p.add_argument("--time-limit", type=float, default=10.0,
                   help="PlanRequest.time_limit (s), default 10")
    p.add_argument("--no-native", action="store_true",
                   help="the planner's NLP functions in CasADi's virtual machine")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON output (default bench/results/goals_<UTC stamp>.json)")
    p.add_argument("--md", type=Path, default=None,
                   help="Markdown output (default docs/benchmark-goals.md)")
    args = p.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for the report's command line
    return args


def run(args: argparse.Namespace, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the goals benchmark described by ``args``; the results dict."""
    from bench.__main__ import _git_commit, _versions
    t_start = time.perf_counter()
    counts = parse_counts(args.goals_counts)
    cfg = GoalsConfig(repeats=max(1, args.repeats), budget=args.budget,
                      time_limit=args.time_limit,
                      methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()))
    now = _dt.datetime.now(_dt.timezone.utc)
    meta: dict[str, Any] = {
        "timestamp": now.strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": _git_commit(),
        "command": " ".join(["python -m bench.goals_run", *args.argv]),
        "cpus": os.cpu_count(), "platform": platform.platform(), "versions": _versions(),
        "loadavg_start": [round(x, 2) for x in os.getloadavg()]}
    meta["native"] = configure_native(bool(args.no_native))
    goals = benchmark_goals(counts)
    log(f"# goals: {counts}, methods {', '.join(cfg.methods) or '-'}, up to {cfg.repeats} "
        f"repeats")
    meta["native_prepare"] = {}
    if meta["native"].get("on"):
        for n in sorted(counts):
            meta["native_prepare"][str(n)] = prepare_native(n)
    baselines = Baselines(build_repeats=1)
    rows = [run_goal(g, baselines, cfg, log) for g in goals]
    results: dict[str, Any] = {
        "meta": meta,
        "config": {"counts": {str(n): k for n, k in counts.items()}, "repeats": cfg.repeats,
                   "budget_s": cfg.budget, "time_limit": cfg.time_limit,
                   "methods": list(cfg.methods), "terminal_tol_rad": TERMINAL_TOL,
                   "deviation_tol_rad": DEVIATION_TOL, "near_limit_share": NEAR_LIMIT_SHARE},
        "baseline_builds": {str(n): b for n, b in baselines.builds.items()},
        "goals": rows}
    results["summary"] = summarise_goals(rows, cfg)
    meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    meta["wall_time"] = time.perf_counter() - t_start
    return results


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns 0 unless the run itself broke (missed targets are results)."""
    from bench.__main__ import _clean, _json_default
    args = parse_args(argv)
    warnings.simplefilter("ignore")  # discarded members warn by design; results say what failed
    results = run(args)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    out = Path(args.out or ROOT / "bench" / "results" / f"goals_{stamp}.json")
    md = Path(args.md or ROOT / "docs" / "benchmark-goals.md")
    for path in (out, md):
        path.parent.mkdir(parents=True, exist_ok=True)
    results["meta"]["out"] = str(out)
    out.write_text(json.dumps(_clean(results), indent=1, default=_json_default) + "\n")
    text = markdown(results)
    md.write_text(text)
    print()
    print(text)
    print(f"JSON written to {out}, Markdown to {md}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
