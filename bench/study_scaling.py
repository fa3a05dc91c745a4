"""How a study scales with workers: 1,000 generated goals on 1 and on 2 local worker processes.

    .venv/bin/python -m bench.study_scaling [--goals 1000] [--n 3] [--repeats 1] [--json out.json]

What is measured
    * the goals: ``--goals`` reachable goals of the default ``n``-joint robot
      (:func:`optimizer.reachable.generate`, fixed seed), generated before any timing;
    * for 1 and 2 workers, a process pool (:func:`optimizer.studies.process_pool`) is started
      and warmed (every worker has planned once, so imports and the robot's NLP are built),
      then the whole :func:`optimizer.studies.run_study` is timed (wall clock, chunking as by
      default: about 8 chunks per worker); also the cold run, pool start included, for 2;
    * parallel efficiency ``E = T(1) / (2 T(2))`` (target >= 90 %);
    * the share of the workers' time spent planning, ``sum(row seconds) / (workers x wall)``:
      the rest is scheduling, transfer and the idle tail (target: scheduling < 5 %);
    * the workers' CPU time during the timed run (psutil): equal for 1 and 2 workers when
      splitting the work adds none; a ``T(2)`` above ``T(1) / 2`` with equal CPU time means
      the workers waited for a core (other processes), not for the study;
    * the rows of every run are compared (all columns but ``seconds``): they must be equal.

The machine is shared: the load average before and after is printed with the numbers. On a
machine whose other processes take CPU time, two workers cannot get two cores and ``E`` falls
for that reason alone.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from optimizer import studies  # noqa: E402
from optimizer.model import Robot  # noqa: E402

TARGET_EFFICIENCY = 0.90


def _strip(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


def _warm(pool: Any, tasks: list[studies.StudyTask], workers: int) -> None:
    """Start every worker and let each plan once (one single-plan chunk per worker, submitted
    together, each blocking long enough that no worker takes two)."""
    futures = [pool.submit(studies.run_chunk, tasks[i:i + 1] * 3) for i in range(workers)]
    for f in futures:
        f.result()


def _cpu_seconds(pool: Any) -> float | None:
    """CPU time (user + system, s) of the pool's worker processes so far (psutil), or None."""
    try:
        import psutil
    except ImportError:
        return None
    total = 0.0
    for pid in list(getattr(pool, "_processes", {}) or {}):
        t = psutil.Process(pid).cpu_times()
        total += t.user + t.system
    return total


def timed_run(tasks: list[studies.StudyTask], workers: int, warm: bool) -> dict[str, Any]:
    """One study of ``tasks`` on a pool of ``workers``; wall time and its breakdown."""
    cpu: float | None = None
    if warm:
        pool = studies.process_pool(workers)
        _warm(pool, tasks, workers)
        cpu0 = _cpu_seconds(pool)
        t0 = time.perf_counter()
        result = studies.run_study(tasks, executor=pool, workers=workers)
        wall = time.perf_counter() - t0
        cpu1 = _cpu_seconds(pool)
        cpu = None if cpu0 is None or cpu1 is None else cpu1 - cpu0
        pool.shutdown()
    else:
        t0 = time.perf_counter()
        result = studies.run_study(tasks, workers=workers)
        wall = time.perf_counter() - t0
    planning = sum(float(r["seconds"]) for r in result.rows)
    return {"workers": workers, "warm": warm, "wall_seconds": wall, "cpu_seconds": cpu,
            "plan_seconds": planning, "busy_share": planning / (workers * wall),
            "chunk": result.chunk_size, "chunks": -(-len(tasks) // result.chunk_size),
            "success": sum(r["status"] == "success" for r in result.rows),
            "rows": result.rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.study_scaling", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--goals", type=int, default=1000)
    ap.add_argument("--n", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=1, help="runs per worker count (best kept)")
    ap.add_argument("--json", default=None, help="write the numbers here")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()
    tasks = studies.make_tasks([(f"default-n{args.n}", Robot.default(args.n))],
                               random=args.goals)
    runs: dict[str, dict[str, Any]] = {}
    for key, workers, warm in (("1", 1, True), ("2", 2, True), ("2 cold", 2, False)):
        best = None
        for _ in range(args.repeats):
            r = timed_run(tasks, workers, warm)
            if best is None or r["wall_seconds"] < best["wall_seconds"]:
                best = r
        assert best is not None
        runs[key] = best
    same = all(_strip(r["rows"]) == _strip(runs["1"]["rows"]) for r in runs.values())
    t1, t2 = runs["1"]["wall_seconds"], runs["2"]["wall_seconds"]
    eff = t1 / (2 * t2)
    eff_cold = t1 / (2 * runs["2 cold"]["wall_seconds"])
    load1 = os.getloadavg()
    print(f"study scaling: {args.goals} goals, n = {args.n}, {os.cpu_count()} CPUs, "
          f"load average {load0[0]:.2f} before, {load1[0]:.2f} after")
    print("| workers | pool | wall s | workers' CPU s | plans s | busy share | chunk | success |")
    print("|---|---|---|---|---|---|---|---|")
    for key, r in runs.items():
        cpu = "" if r["cpu_seconds"] is None else f"{r['cpu_seconds']:.2f}"
        print(f"| {r['workers']} | {'warm' if r['warm'] else 'cold (start timed)'} | "
              f"{r['wall_seconds']:.2f} | {cpu} | {r['plan_seconds']:.2f} | "
              f"{100 * r['busy_share']:.1f} % | {r['chunk']} x {r['chunks']} | "
              f"{r['success']}/{args.goals} |")
    print(f"parallel efficiency T1 / (2 T2): {100 * eff:.1f} % (target >= "
          f"{100 * TARGET_EFFICIENCY:.0f} %: {'met' if eff >= TARGET_EFFICIENCY else 'NOT met'});"
          f" with the 2-worker pool's start timed: {100 * eff_cold:.1f} %")
    print(f"rows equal across runs (all but seconds): {same}")
    if args.json:
        out = {"goals": args.goals, "n": args.n, "cpus": os.cpu_count(),
               "load_before": load0, "load_after": load1, "efficiency": eff,
               "efficiency_cold": eff_cold, "rows_equal": same,
               "runs": {k: {kk: vv for kk, vv in v.items() if kk != "rows"}
                        for k, v in runs.items()}}
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
