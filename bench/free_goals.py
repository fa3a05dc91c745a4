"""``python -m bench.free_goals``: the default request on freely chosen goals, per joint count.

The goals benchmark (:mod:`bench.goals_run`) plans *generated* goals, the ends of smooth
motions of the mechanism. A user may instead name any start and goal: here each joint's start
and goal are drawn independently and uniformly in ``[LOW_DEG, HIGH_DEG]`` (every joint moves,
most by tens of degrees), and ``[10]*n -> [30]*n`` deg is planned too. Per ``n``: how many
are planned, the median and slowest times (wall clock, one process, after one warm-up plan),
the reversals of the planned paths, and the typed answer of the others. Each planned path is
the planner's verified one (scipy re-integration is the goals benchmark's job; here the
question is whether a path is found, and when). ``--first-requests`` plans instead, per ``n``,
the requests a user writes first (:func:`first_requests`: every joint by one large move, the
last joint alone, joints moving in opposite directions) and says how many legs
(:mod:`optimizer.planner.legs`) each answer took.

Usage::

    .venv/bin/python -m bench.free_goals                       # seed 7: n = 3..8
    .venv/bin/python -m bench.free_goals --counts 3:10,4:10 --seed 11
    .venv/bin/python -m bench.free_goals --first-requests --counts 5:1,6:1,7:1
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.goals_run import parse_counts, prepare_native  # noqa: E402
from bench.inprocess import configure_native  # noqa: E402

#: Each joint's start and goal are drawn in this range (deg).
LOW_DEG, HIGH_DEG = 15.0, 75.0
#: Goals per joint count of a default run.
COUNTS = {3: 10, 4: 10, 5: 10, 6: 8, 7: 6, 8: 6}


def free_pairs(n: int, count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` (start, goal) pairs of ``n`` joints (rad), from ``default_rng([seed, n])``."""
    rng = np.random.default_rng([seed, n])
    return [(np.radians(rng.uniform(LOW_DEG, HIGH_DEG, n)),
             np.radians(rng.uniform(LOW_DEG, HIGH_DEG, n))) for _ in range(count)]


def plan_one(start: np.ndarray, goal: np.ndarray) -> dict[str, Any]:
    """The default request's outcome: seconds, and the reversals or the error's class."""
    from optimizer.errors import PlannerError
    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest

    t0 = time.perf_counter()
    try:
        p = plan(PlanRequest.from_dict({"start": start.tolist(), "goal": goal.tolist()}))
    except PlannerError as exc:
        return {"seconds": time.perf_counter() - t0, "answer": exc.code}
    return {"seconds": time.perf_counter() - t0, "answer": "success",
            "reversals": p.indicators.reversals_phi + p.indicators.reversals_th1,
            "legs": (p.diagnostics.get("legs") or {}).get("count", 1)}


def first_requests(n: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Requests a user writes first (deg): every joint by the same large move either way, one
    joint alone, joints moving in opposite directions."""
    alternating = [20.0 if i % 2 == 0 else 60.0 for i in range(n)]
    return [(name, np.radians(a), np.radians(b)) for name, a, b in (
        ("every joint 10 -> 80", [10.0] * n, [80.0] * n),
        ("every joint 30 -> 60", [30.0] * n, [60.0] * n),
        ("every joint 60 -> 30", [60.0] * n, [30.0] * n),
        (f"th{n} +30 (all at 30)", [30.0] * n, [30.0] * (n - 1) + [60.0]),
        ("20/60 alternating -> 60/20", alternating, [80.0 - x for x in alternating]))]


def run_first_requests(ns: list[int]) -> list[dict[str, Any]]:
    """One row per request of :func:`first_requests` per ``n``."""
    rows = []
    for n in ns:
        prepare_native(n)
        plan_one(np.radians([20.0] * n), np.radians([25.0] * n))      # warm-up
        for name, a, b in first_requests(n):
            rows.append({"n": n, "request": name, **plan_one(a, b)})
    return rows


def first_requests_markdown(rows: list[dict[str, Any]]) -> str:
    """The rows of :func:`run_first_requests` as a Markdown table."""
    lines = ["First requests (the default request, `time_limit` 10 s):", "",
             "| n | request (deg) | answer | seconds | reversals (phi + th1) | legs |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        ok = r["answer"] == "success"
        lines.append(f"| {r['n']} | {r['request']} | {r['answer']} | {r['seconds']:.2f} | "
                     f"{r['reversals'] if ok else '-'} | {r['legs'] if ok else '-'} |")
    return "\n".join(lines)


def run(counts: dict[int, int], seed: int) -> list[dict[str, Any]]:
    """One row per ``n`` (see the module)."""
    rows = []
    for n, count in counts.items():
        prepare_native(n)               # the compiled NLPs built first, as in a warm worker
        plan_one(np.radians([20.0] * n), np.radians([25.0] * n))      # warm-up
        outs = [plan_one(a, b) for a, b in free_pairs(n, count, seed)]
        uniform = plan_one(np.radians([10.0] * n), np.radians([30.0] * n))
        planned = [o for o in outs if o["answer"] == "success"]
        others: dict[str, int] = {}
        for o in outs:
            if o["answer"] != "success":
                others[o["answer"]] = others.get(o["answer"], 0) + 1
        rows.append({
            "n": n, "goals": count, "planned": len(planned),
            "median_s": float(np.median([o["seconds"] for o in outs])),
            "slowest_planned_s": max((o["seconds"] for o in planned), default=math.nan),
            "reversals": sorted(o["reversals"] for o in planned), "others": others,
            "uniform": uniform})
    return rows


def markdown(rows: list[dict[str, Any]], seed: int) -> str:
    """The rows as a Markdown table."""
    lines = [f"Free goals (each joint's start and goal uniform in [{LOW_DEG:g}, {HIGH_DEG:g}] deg, "
             f"seed {seed}), the default request:", "",
             "| n | planned | median time | slowest planned | reversals (phi + th1) | others "
             "| [10]*n -> [30]*n deg |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        revs = r["reversals"]
        span = f"{revs[0]}-{revs[-1]}" if revs else "-"
        slow = "-" if math.isnan(r["slowest_planned_s"]) else f"{r['slowest_planned_s']:.2f} s"
        others = ", ".join(f"{v} {k}" for k, v in sorted(r["others"].items())) or "-"
        u = r["uniform"]
        uni = (f"{u['seconds']:.2f} s, {u['reversals']} reversals" if u["answer"] == "success"
               else f"{u['answer']} after {u['seconds']:.1f} s")
        lines.append(f"| {r['n']} | {r['planned']} of {r['goals']} | {r['median_s']:.2f} s | "
                     f"{slow} | {span} | {others} | {uni} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.free_goals", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", type=parse_counts, default=COUNTS,
                    help="n:count,... (default 3:10,4:10,5:10,6:8,7:6,8:6)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--first-requests", action="store_true",
                    help="plan the requests a user writes first (bench.free_goals."
                         "first_requests) for each n of --counts instead of the free goals")
    args = ap.parse_args(argv)
    configure_native(False)
    if args.first_requests:
        print(first_requests_markdown(run_first_requests(list(args.counts))))
    else:
        print(markdown(run(args.counts, args.seed), args.seed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
