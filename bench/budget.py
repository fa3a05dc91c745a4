"""The reversal budget and the trade-off front (issue 26) against two IPOPT peers, in one run.

Usage::

    .venv/bin/python -m bench.budget                          # 20 goals per n = 3..6
    .venv/bin/python -m bench.budget --goals-counts 3:5,4:3 --out /tmp/b.json   # smoke test

For every generated reachable goal (:func:`bench.goals.generate`, the same goals on every
machine), in one process:

* the **peers** (:mod:`bench.baselines.multiple_shooting`, IPOPT, 50 intervals of 4 RK4 steps):
  ``min_max_deviation`` (the straightest path a user would write) and ``energy`` (minimum
  energy), each re-integrated with scipy (:mod:`bench.reintegrate`) and measured there:
  reversals of ``phi`` and ``th_1`` (the planner's dead band) and the deviation from the
  segment start -> goal;
* the **default plan** (``PlanRequest(start, goal, robot)``), timed (a warm-up call, then one
  timed call; every time here is CPU time, ``time.process_time``, as the machine is shared),
  re-integrated the same way;
* on n <= :data:`BUDGET_JOINTS` (``--budget-joints``): **``max_reversals`` = the min-max peer's reversal count**,
  re-integrated: is its deviation within :data:`DEVIATION_SLACK_DEG` of the peer's?
* on those n: **``pareto: true``**, timed: every member re-integrated and
  verified (terminal error < 1e-6 rad, every joint strictly inside (0, pi/2)); the front's time
  against the default plan's and against ``K + 1`` default plans (``K`` members), and where
  it went: its NLPs' count, iterations and share of its CPU (``diagnostics.budget.tried``).

The targets (issue 26): within 0.25 deg of the min-max peer on >= 90 % of the n = 3 goals and
>= 80 % of n = 4, 5; every member verified; the default's reversals no more than the
min-energy peer's on >= 90 % of the goals per n up to 6, and never worse on both reversals and
deviation. The report (Markdown, printed; JSON to ``--out``, default
``bench/results/budget_<UTC stamp>.json``) gives per n the shares and the times.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import platform
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.goals import Goal, generate  # noqa: E402
from bench.goals_run import parse_counts, verified  # noqa: E402
from bench.inprocess import configure_native, describe, status_of  # noqa: E402
from bench.reintegrate import reintegrate_baseline, reintegrate_plan  # noqa: E402
from optimizer.planner.budget import DOMINATED  # noqa: E402

#: Goals per number of joints of a default run.
COUNTS = {3: 20, 4: 20, 5: 20, 6: 20}
#: The budget and the front are measured up to this many joints (the issue's n = 3..5).
BUDGET_JOINTS = 5
#: "No larger than the peer's" allows this much (deg).
DEVIATION_SLACK_DEG = 0.25
#: Targets: share within the slack per n, share of the default's reversals <= the min-energy
#: peer's.
TARGET_WITHIN = {3: 0.90, 4: 0.80, 5: 0.80}
TARGET_REVERSALS = 0.90
TIME_LIMIT = 60.0


def _rev(m: dict[str, Any] | None) -> int | None:
    if not m or not m.get("ok"):
        return None
    return int(m["reversals_phi"]) + int(m["reversals_th1"])


def _peer(g: Goal, peers: dict[tuple[int, str], Any], objective: str) -> dict[str, Any]:
    from bench.baselines.multiple_shooting import MultipleShootingBaseline, default_model
    gains, exps = default_model(g.n)
    if (g.n, objective) not in peers:
        peers[(g.n, objective)] = MultipleShootingBaseline(gains, exps, objective=objective)
    bl = peers[(g.n, objective)]
    a, b = np.asarray(g.start), np.asarray(g.goal)
    c0 = time.process_time()
    res = bl.solve(a, b)
    cpu = time.process_time() - c0
    m = reintegrate_baseline(res, gains, [int(x) for x in exps], a, b).as_dict()
    return {"status": res.return_status, "success": res.success, "time": cpu,
            "wall": res.solve_time,
            "verified": bool(res.success and verified(m)), "reversals": _rev(m),
            "deviation_deg": m["segment_dev_deg"]}


def _plan(g: Goal, timed: bool = False, **extra: Any) -> tuple[Any, dict[str, Any]]:
    from optimizer.model import Robot
    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest
    req = PlanRequest(start=g.start, goal=g.goal, robot=Robot.default(g.n),
                      time_limit=TIME_LIMIT, **extra)
    out: dict[str, Any] = {}
    if timed:  # a warm-up call (not counted: the NLPs' first build), then the timed one
        try:
            plan(req)
        except Exception:  # noqa: BLE001 - the timed call records it
            pass
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        p = plan(req)
    except Exception as exc:  # noqa: BLE001 - recorded
        out.update(status=status_of(exc), error=describe(exc), time=time.process_time() - c0,
                   wall=time.perf_counter() - t0, verified=False,
                   fewest=getattr(exc, "diagnostics", {}).get("fewest_reversals"))
        return None, out
    # CPU time (the machine is shared: wall-clock times are inflated by the others' load)
    out["time"], out["wall"] = time.process_time() - c0, time.perf_counter() - t0
    m = reintegrate_plan(p, np.asarray(g.start), np.asarray(g.goal)).as_dict()
    out.update(status="success", verified=verified(m), reversals=_rev(m),
               deviation_deg=m["segment_dev_deg"],
               planner_reversals=p.indicators.reversals)
    return p, out


def run_goal(g: Goal, peers: dict[tuple[int, str], Any],
             budget_joints: int = BUDGET_JOINTS) -> dict[str, Any]:
    """Everything of the module docstring on one goal (the budget and the front up to
    ``budget_joints`` joints)."""
    row: dict[str, Any] = {"name": g.name, "n": g.n, "kind": g.kind,
                           "start": list(g.start), "goal": list(g.goal)}
    row["minmax"] = _peer(g, peers, "min_max_deviation")
    row["energy"] = _peer(g, peers, "energy")
    _, row["default"] = _plan(g, timed=True)
    if g.n > budget_joints:
        return row
    k = row["minmax"]["reversals"]
    if row["minmax"]["verified"] and k is not None:
        _, row["budget"] = _plan(g, max_reversals=k)
        row["budget"]["max_reversals"] = k
    # the budget's NLP built before the front is timed, as the default's is by its warm-up
    # call (the service builds it at start-up: optimizer.planner.budget.prepare)
    from optimizer.model import Robot
    from optimizer.planner.budget import prepare
    robot = Robot.default(g.n)
    prepare(robot.gains, robot.exponents)
    p, front = _plan(g, pareto=True)
    if p is not None and p.pareto is not None:
        members = []
        for mem in p.pareto:
            m = reintegrate_plan(mem.plan, np.asarray(g.start), np.asarray(g.goal)).as_dict()
            members.append({"max_reversals": mem.max_reversals, "origin": mem.origin,
                            "verified": verified(m), "reversals": _rev(m),
                            "deviation_deg": m["segment_dev_deg"]})
        front["members"] = members
        # where the front's CPU went: its NLPs (IPOPT) and its finishings (correction,
        # quadrature, checks), as the planner records them
        tried = p.diagnostics.get("budget", {}).get("tried", [])
        front["nlps"] = sum(1 for t in tried if "nlp_cpu_seconds" in t)
        front["nlp_iterations"] = sum(int(t.get("iterations", 0)) for t in tried
                                      if "nlp_cpu_seconds" in t)
        front["nlp_cpu"] = sum(float(t.get("nlp_cpu_seconds", 0.0)) for t in tried)
        # NLP answers dropped unfinished as no front member (budget.DOMINATED)
        front["dropped"] = sum(1 for t in tried if t.get("outcome") == DOMINATED)
        front["finish_cpu"] = sum(float(t.get("finish_cpu_seconds", 0.0)) for t in tried)
    row["front"] = front
    return row


def _share(flags: list[bool]) -> float:
    return sum(flags) / len(flags) if flags else math.nan


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per n: the shares of the targets, the front's members and times."""
    out: dict[str, Any] = {}
    for n in sorted({r["n"] for r in rows}):
        rs = [r for r in rows if r["n"] == n]
        s: dict[str, Any] = {"goals": len(rs)}
        within, no_more, worse_both = [], [], []
        for r in rs:
            d, e = r["default"], r["energy"]
            if e["verified"]:
                ok = d["verified"] and d["reversals"] is not None
                no_more.append(bool(ok and d["reversals"] <= e["reversals"]))
                worse_both.append(bool(ok and d["reversals"] > e["reversals"]
                                       and d["deviation_deg"] > e["deviation_deg"] + 1e-6))
            b, mm = r.get("budget"), r["minmax"]
            if b is not None:
                within.append(bool(b["verified"] and b["reversals"] is not None
                                   and b["reversals"] <= b["max_reversals"]
                                   and b["deviation_deg"] <= mm["deviation_deg"]
                                   + DEVIATION_SLACK_DEG))
        s["default_reversals_no_more_than_energy_peer"] = _share(no_more)
        s["default_worse_on_both"] = sum(worse_both)
        s["compared_with_energy_peer"] = len(no_more)
        if any("front" in r for r in rs):  # (measured up to the run's --budget-joints)
            s["budget_within_slack"] = _share(within)
            s["budget_compared"] = len(within)
            fronts = [r["front"] for r in rs if r.get("front", {}).get("members")]
            mems = [m for f in fronts for m in f["members"]]
            s["front_members"] = len(mems)
            s["front_members_verified"] = sum(m["verified"] for m in mems)
            s["front_K_median"] = float(np.median([len(f["members"]) for f in fronts])) \
                if fronts else math.nan
            ratio = [f["time"] / r["default"]["time"] for r, f in
                     ((r, r["front"]) for r in rs) if f.get("members") and r["default"].get("time")]
            per_k = [f["time"] / ((len(f["members"]) + 1) * r["default"]["time"]) for r, f in
                     ((r, r["front"]) for r in rs) if f.get("members") and r["default"].get("time")]
            s["front_time_median_s"] = float(np.median([f["time"] for f in fronts])) \
                if fronts else math.nan
            s["front_over_default_median"] = float(np.median(ratio)) if ratio else math.nan
            s["front_over_K_plus_1_plans_median"] = float(np.median(per_k)) if per_k \
                else math.nan
            s["front_within_K_plus_1_plans"] = _share([x <= 1.0 for x in per_k])
            nlp = [f for f in fronts if f.get("nlps")]
            s["front_nlp_share_median"] = float(np.median(
                [f["nlp_cpu"] / f["time"] for f in nlp])) if nlp else math.nan
            s["front_nlps_median"] = float(np.median([f["nlps"] for f in nlp])) if nlp \
                else math.nan
            s["front_nlps_dropped"] = sum(int(f.get("dropped", 0)) for f in fronts)
            s["front_finish_share_median"] = float(np.median(
                [f["finish_cpu"] / f["time"] for f in nlp])) if nlp else math.nan
            s["front_ms_per_nlp_iteration_median"] = float(np.median(
                [1e3 * f["nlp_cpu"] / f["nlp_iterations"] for f in nlp
                 if f["nlp_iterations"]])) if nlp else math.nan
            s["minmax_peer_time_median_s"] = float(np.median([r["minmax"]["time"] for r in rs]))
        s["default_time_median_s"] = float(np.median([r["default"].get("time", math.nan)
                                                      for r in rs]))
        out[str(n)] = s
    return out


def markdown(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    """The report's table."""
    def f(x: Any, pct: bool = False) -> str:
        if x is None or (isinstance(x, float) and math.isnan(x)):
            return "-"
        return f"{100 * x:.0f} %" if pct else (f"{x:.3g}" if isinstance(x, float) else str(x))

    lines = [f"Reversal budget and front (issue 26), {meta['stamp']}, {meta['machine']}", "",
             "| n | goals | max_reversals = min-max peer's: within 0.25 deg | members verified "
             "| K median | front CPU [s] (median) | min-max peer [s] | front / default plan "
             "| front / (K+1) plans (median; share <= 1) "
             "| NLPs (median; dropped unfinished, all goals) | NLP share of front "
             "| ms per NLP iteration "
             "| default reversals <= min-energy peer's | worse on both |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for n, s in summary.items():
        t = TARGET_WITHIN.get(int(n))
        lines.append(
            f"| {n} | {s['goals']} | "
            + (f"{f(s.get('budget_within_slack'), True)} of {s.get('budget_compared')}"
               f" (target {f(t, True)})" if 'budget_within_slack' in s else "-")
            + f" | {s.get('front_members_verified', '-')} / {s.get('front_members', '-')}"
            f" | {f(s.get('front_K_median'))} | {f(s.get('front_time_median_s'))}"
            f" | {f(s.get('minmax_peer_time_median_s'))}"
            f" | {f(s.get('front_over_default_median'))}"
            f" | {f(s.get('front_over_K_plus_1_plans_median'))}; "
            f"{f(s.get('front_within_K_plus_1_plans'), True)}"
            f" | {f(s.get('front_nlps_median'))}; {s.get('front_nlps_dropped', '-')}"
            f" | {f(s.get('front_nlp_share_median'), True)}"
            f" | {f(s.get('front_ms_per_nlp_iteration_median'))}"
            f" | {f(s['default_reversals_no_more_than_energy_peer'], True)} of "
            f"{s['compared_with_energy_peer']} (target 90 %) | {s['default_worse_on_both']} |")
    return "\n".join(lines)


def run(counts: dict[int, int], log: Callable[[str], None] = print,
        budget_joints: int = BUDGET_JOINTS) -> dict[str, Any]:
    native = configure_native()
    peers: dict[tuple[int, str], Any] = {}
    rows = []
    for n, k in counts.items():
        for g in generate(n, k):
            t0 = time.perf_counter()
            row = run_goal(g, peers, budget_joints)
            rows.append(row)
            b, fr = row.get("budget"), row.get("front", {})
            log(f"  {g.name}: minmax {row['minmax']['reversals']} rev "
                f"{row['minmax']['deviation_deg']:.3g} deg; energy {row['energy']['reversals']}"
                f" rev; default {row['default'].get('reversals')} rev "
                f"{row['default'].get('deviation_deg', math.nan):.3g} deg "
                f"{row['default'].get('time', math.nan) * 1e3:.0f} ms"
                + (f"; budget {b.get('reversals')} rev {b.get('deviation_deg', math.nan):.3g} "
                   f"deg {b['status']}" if b else "")
                + (f"; front K={len(fr.get('members', []))} {fr.get('time', math.nan):.2f} s"
                   if fr else "") + f" [{time.perf_counter() - t0:.1f} s]")
    meta = {"stamp": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            "counts": {str(n): k for n, k in counts.items()}, "native": native,
            "budget_joints": budget_joints}
    summary = summarise(rows)
    return {"meta": meta, "summary": summary, "rows": rows,
            "markdown": markdown(summary, meta)}


#: The page a run writes (unless ``--md``).
PAGE = ROOT / "docs" / "benchmark-budget.md"
PAGE_INTRO = """\
# Benchmark: the reversal budget and the trade-off (issue 26)

Written by `python -m bench.budget` (see its docstring for what each column means); the JSON
with every goal goes to `bench/results/`. The machine is shared by several engineers: times
are from one run under that load, compare the ratios.

    .venv/bin/python -m bench.budget --goals-counts 3:10,4:10,5:10   # the run below
    .venv/bin/python -m bench.budget --report-only bench/results/budget_....json   # page only

"""


def page(res: dict[str, Any]) -> str:
    """The results page: the intro, the table and the goals that miss the budget target."""
    misses = []
    for r in res["rows"]:
        b = r.get("budget")
        if b is None:
            continue
        mm = r["minmax"]
        if not (b.get("verified") and b.get("reversals") is not None
                and b["reversals"] <= b["max_reversals"]
                and b["deviation_deg"] <= mm["deviation_deg"] + DEVIATION_SLACK_DEG):
            misses.append(f"| {r['name']} | {mm['reversals']} | {mm['deviation_deg']:.3f} | "
                          f"{b.get('reversals')} | {b.get('deviation_deg', math.nan):.3f} | "
                          f"{b['status']} |")
    text = PAGE_INTRO + res["markdown"] + "\n"
    if res["meta"].get("note"):
        text += "\n" + res["meta"]["note"] + "\n"
    if misses:
        text += ("\nGoals where max_reversals = the peer's reversals is not within 0.25 deg of "
                 "the peer:\n\n| goal | peer reversals | peer deviation [deg] | reversals | "
                 "deviation [deg] | status |\n|---|---|---|---|---|---|\n"
                 + "\n".join(misses) + "\n")
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--goals-counts", default=",".join(f"{n}:{k}" for n, k in COUNTS.items()),
                    help="goals per n, e.g. 3:20,4:20,5:20,6:20")
    ap.add_argument("--budget-joints", type=int, default=BUDGET_JOINTS,
                    help="measure the budget and the front up to this many joints (default "
                         f"{BUDGET_JOINTS}, the issue's; beyond, the default against the peers)")
    ap.add_argument("--out", default=None, help="JSON results (default bench/results/...)")
    ap.add_argument("--md", default=str(PAGE), help="the results page (default "
                                                     "docs/benchmark-budget.md)")
    ap.add_argument("--report-only", default=None, metavar="JSON",
                    help="write the page from a run's JSON, run nothing")
    args = ap.parse_args(argv)
    if args.report_only:
        res = json.loads(Path(args.report_only).read_text())
        res["summary"] = summarise(res["rows"])
        res["markdown"] = markdown(res["summary"], res["meta"])
    else:
        res = run(parse_counts(args.goals_counts), log=lambda s: print(s, flush=True),
                  budget_joints=args.budget_joints)
        out = Path(args.out) if args.out else ROOT / "bench" / "results" / (
            "budget_" + res["meta"]["stamp"].replace(":", "") + ".json")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=1, default=float))
        print(f"JSON: {out}")
    Path(args.md).write_text(page(res))
    print(res["markdown"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
