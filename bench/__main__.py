"""``python -m bench``: the benchmark -- prints a Markdown report, writes JSON and (full runs)
rewrites ``docs/benchmarks.md``.

Usage::

    .venv/bin/python -m bench                 # full run (about 10 minutes on 2 cores)
    .venv/bin/python -m bench --quick         # short run (fewer repeats, 3 s HTTP levels)
    .venv/bin/python -m bench --quick --cases 1 --no-http --joints 3   # smoke test
    .venv/bin/python -m bench --out bench/results/mine.json
    .venv/bin/python -m bench --goals [options]   # issues 15, 24: generated goals on
                                                  # n = 3..8, the default request, every
                                                  # method and the n-joint baseline, with
                                                  # the targets (= python -m bench.goals_run)

See ``docs/benchmarks.md`` for what is measured.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: The results page a full run rewrites.
PAGE = ROOT / "docs" / "benchmarks.md"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import cases as cases_mod  # noqa: E402
from bench import http_load, report, scaling  # noqa: E402
from bench.inprocess import METHODS, Baselines, Config, configure_native, run_case  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(prog="python -m bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--goals", action="store_true",
                   help="run the benchmark on generated goals (n = 3..8) instead (issues 15, 24): "
                        "every other option is bench.goals_run's (--goals-counts, --repeats, "
                        "--methods, --note, ...)")
    p.add_argument("--quick", action="store_true",
                   help="short run: at most 3 repeats, 3 s per HTTP level, one cold start")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON output (default bench/results/<UTC timestamp>.json)")
    p.add_argument("--report", type=Path, default=None,
                   help=f"Markdown page of the results (default: {PAGE.relative_to(ROOT)} for a "
                        "full run, none for --quick)")
    p.add_argument("--cases", type=int, default=None, help="run only the first N cases")
    p.add_argument("--case", action="append", default=None, metavar="NAME",
                   help="run only this case (repeatable); names: "
                        + ", ".join(c.name for c in cases_mod.CASES))
    p.add_argument("--methods", default=",".join(METHODS),
                   help="comma-separated planner methods (default: all)")
    p.add_argument("--repeats", type=int, default=None, help="largest number of timed repeats")
    p.add_argument("--time-limit", type=float, default=10.0,
                   help="PlanRequest.time_limit of the in-process plans (s), default 10")
    p.add_argument("--no-http", action="store_true", help="skip the HTTP measurements")
    p.add_argument("--http-seconds", type=float, default=None,
                   help="seconds per HTTP load level (default 10, --quick 3)")
    p.add_argument("--no-native", action="store_true",
                   help="evaluate the planner's NLP functions in CasADi's virtual machine, as "
                        "where no C compiler is (default: compiled, optimizer.native)")
    p.add_argument("--no-scaling", action="store_true", help="skip the cost-growth measurements")
    p.add_argument("--joints", default=None,
                   help="comma-separated joint counts of the scaling part (default 3..8)")
    return p.parse_args(argv)


def _git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                             capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=ROOT, capture_output=True, text=True, timeout=10)
        return out.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _versions() -> dict[str, str]:
    vers = {"python": platform.python_version()}
    for mod in ("numpy", "scipy", "casadi", "fastapi", "uvicorn", "httpx"):
        try:
            vers[mod] = str(__import__(mod).__version__)
        except Exception:  # noqa: BLE001 - informational
            vers[mod] = "unavailable"
    return vers


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    return str(obj)


def _clean(obj: Any) -> Any:
    """Replace NaN/inf by None so that the JSON is strict."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run the benchmark described by ``args``; return the results dict."""
    t_start = time.perf_counter()
    now = _dt.datetime.now(_dt.timezone.utc)
    quick = bool(args.quick)
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    cfg = Config(repeats=args.repeats or (3 if quick else 7), min_repeats=1 if quick else 3,
                 budget=2.0 if quick else 10.0, build_repeats=1 if quick else 3,
                 time_limit=args.time_limit, methods=methods)
    selected = cases_mod.select(args.case, args.cases)
    meta = {"timestamp": now.strftime("%Y-%m-%dT%H:%M:%SZ"), "quick": quick,
            "argv": sys.argv[1:], "commit": _git_commit(), "cpus": os.cpu_count(),
            "platform": platform.platform(), "versions": _versions(),
            "loadavg_start": [round(x, 2) for x in os.getloadavg()]}
    meta["native"] = configure_native(bool(args.no_native))
    results: dict[str, Any] = {"meta": meta, "config": {
        "repeats": cfg.repeats, "min_repeats": cfg.min_repeats, "budget_s": cfg.budget,
        "baseline_build_repeats": cfg.build_repeats, "time_limit": cfg.time_limit,
        "methods": list(methods), "reintegration": {
            "method": "DOP853", "rtol": 1e-10, "atol": 1e-12, "grid": 4001,
            "reversal_dead_band_rad": 1e-4}}}

    print(f"# bench: {len(selected)} cases, methods {', '.join(methods)}, "
          f"{'quick' if quick else 'full'} run", flush=True)
    baselines = Baselines(cfg.build_repeats)
    out_cases = []
    for c in selected:
        out_cases.append(run_case(c, baselines, cfg, log=lambda s: print(s, flush=True)))
    results["cases"] = out_cases
    results["baseline_builds"] = {str(n): b for n, b in baselines.builds.items()}

    if args.no_http:
        results["http"] = {"available": False, "reason": "disabled (--no-http)"}
    else:
        print("# HTTP", flush=True)
        secs = args.http_seconds or (3.0 if quick else 10.0)
        results["http"] = http_load.run(seconds=secs, cold_starts=1 if quick else 3,
                                        drain=3.0 if quick else 10.0,
                                        log=lambda s: print(s, flush=True))
        if not results["http"].get("available"):
            print(f"  not available: {results['http'].get('reason')}", flush=True)

    if not args.no_scaling:
        print("# scaling", flush=True)
        joints = tuple(int(x) for x in args.joints.split(",")) if args.joints else scaling.JOINTS
        results["scaling"] = {
            "samples": scaling.samples_scaling(3 if quick else 7, 2.0 if quick else 5.0,
                                               1 if quick else 3),
            "joints": scaling.joint_scaling(2 if quick else 5, 2 if quick else 5,
                                            1.0 if quick else 5.0, joints=joints,
                                            log=lambda s: print(s, flush=True)),
        }

    results["targets"] = report.evaluate_targets(results)
    meta["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    meta["wall_time"] = time.perf_counter() - t_start
    return results


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status (0 unless the run itself broke)."""
    rest = list(sys.argv[1:] if argv is None else argv)
    if "--goals" in rest:  # the generated-goals run has its own options (bench.goals_run)
        from bench import goals_run
        rest.remove("--goals")
        return goals_run.main(rest)
    args = parse_args(argv)
    warnings.simplefilter("ignore")  # discarded members warn by design; results say what failed
    results = run(args)
    out = args.out
    if out is None:
        stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%SZ")
        out = ROOT / "bench" / "results" / f"{stamp}.json"
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results["meta"]["out"] = str(out)
    out.write_text(json.dumps(_clean(results), indent=1, default=_json_default) + "\n")
    print()
    print(report.full_report(results))
    print(f"\nJSON written to {out}")
    page = args.report if args.report is not None else (None if args.quick else PAGE)
    if page is not None:
        page.parent.mkdir(parents=True, exist_ok=True)
        page.write_text(report.results_page(_clean(results)), encoding="utf-8")
        print(f"Results page written to {page}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
