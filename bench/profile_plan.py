"""Profile of the hot path: by default the polynomial plan of [10, 10, 10] -> [30, 30, 30] deg
(T = 1 s); ``--case NAME --method M`` profiles any case of :mod:`bench.cases` and method instead.

After one warm-up plan, ``--plans`` plans are profiled twice:

* with pyinstrument (a sampling profiler, low distortion) when it is installed: the call tree,
  condensed to frames that take at least 2 % of the time;
* with cProfile (deterministic, it inflates many small calls): the top functions by own time and
  by cumulative time.

Both go to ``bench/results/profile.txt`` (or ``--out``), preceded by the mean wall time per plan
without a profiler and the planner's own stage timings.

Usage::

    .venv/bin/python bench/profile_plan.py [--plans 20] [--out bench/results/profile.txt]
    .venv/bin/python bench/profile_plan.py --case n5_small --method shooting
"""

from __future__ import annotations

import argparse
import cProfile
import io
import math
import pstats
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from optimizer.planner.plan import plan  # noqa: E402
from optimizer.problem import PlanRequest  # noqa: E402


def request(case: str | None = None, method: str = "polynomial") -> PlanRequest:
    """The profiled request: [10, 10, 10] -> [30, 30, 30] deg, or a case of
    :mod:`bench.cases` (its robot, T = 1 s)."""
    if case is None:
        return PlanRequest(start=tuple(np.radians([10.0] * 3)),
                           goal=tuple(np.radians([30.0] * 3)), method=method, duration=1.0)
    from bench.cases import select
    from bench.inprocess import make_request
    return make_request(select([case])[0], method, 60.0)  # type: ignore[no-any-return]


def stage_timings(req: PlanRequest, plans: int) -> tuple[float, dict[str, float]]:
    """Mean wall time per plan and mean of the planner's own ``timing`` entries."""
    sums: dict[str, float] = {}
    t0 = time.perf_counter()
    for _ in range(plans):
        p = plan(req)
        for k, v in p.timing.items():
            sums[k] = sums.get(k, 0.0) + float(v)
    wall = (time.perf_counter() - t0) / plans
    return wall, {k: v / plans for k, v in sums.items()}


def pyinstrument_tree(req: PlanRequest, plans: int) -> str | None:
    """pyinstrument's text tree of ``plans`` plans, or None when pyinstrument is missing."""
    try:
        from pyinstrument import Profiler
    except ImportError:
        return None
    prof = Profiler(interval=0.0005)
    prof.start()
    for _ in range(plans):
        plan(req)
    prof.stop()
    text: str = prof.output_text(unicode=False, color=False, show_all=False,
                                 processor_options={"filter_threshold": 0.02})
    return text


def cprofile_tables(req: PlanRequest, plans: int, top: int) -> str:
    """cProfile's top functions by own time and by cumulative time."""
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(plans):
        plan(req)
    prof.disable()
    out = io.StringIO()
    st = pstats.Stats(prof, stream=out)
    st.strip_dirs()
    out.write(f"--- cProfile, {plans} plans, top {top} by own time (tottime) ---\n")
    st.sort_stats("tottime").print_stats(top)
    out.write(f"--- cProfile, {plans} plans, top {top} by cumulative time ---\n")
    st.sort_stats("cumulative").print_stats(top)
    return out.getvalue()


def main(argv: list[str] | None = None) -> int:
    """Profile and write the report; returns 0."""
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--plans", type=int, default=20, help="plans per profile (default 20)")
    ap.add_argument("--top", type=int, default=30, help="rows of the cProfile tables")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "profile.txt")
    ap.add_argument("--case", default=None, help="a case of bench/cases.py (default: the "
                    "[10, 10, 10] -> [30, 30, 30] deg worked example)")
    ap.add_argument("--method", default="polynomial", help="planner method (default polynomial)")
    ap.add_argument("--no-native", action="store_true",
                    help="CasADi's virtual machine for the NLP functions (default: compiled, "
                         "optimizer.native, as in the service)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    req = request(args.case, args.method)
    from bench.inprocess import configure_native
    native = configure_native(off=args.no_native)
    if native["on"] and args.method in ("shooting", "auto"):
        from optimizer.planner.shooting import prepare
        prepare(req.robot.gains, req.robot.exponents, wait=True)
    plan(req)  # warm-up: caches of the chained form, CasADi functions
    wall, stages = stage_timings(req, args.plans)
    parts: list[str] = [
        f"Profile of plan(PlanRequest({args.case or '[10, 10, 10] -> [30, 30, 30] deg'}, "
        f"method={args.method!r}, T = 1 s))",
        f"mean wall time per plan without a profiler: {wall * 1e3:.1f} ms ({args.plans} plans)",
        "planner's own stage timings (mean, ms): " + ", ".join(
            f"{k} {v * 1e3:.1f}" for k, v in stages.items()),
    ]
    tree = pyinstrument_tree(req, args.plans)
    if tree is not None:
        parts.append(f"--- pyinstrument (sampling, 0.5 ms), {args.plans} plans, frames >= 2 % "
                     "---\n" + tree)
    else:
        parts.append("--- pyinstrument not installed: cProfile only ---")
    parts.append(cprofile_tables(req, args.plans, args.top))
    text = "\n\n".join(parts)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text[:4000] + ("\n..." if len(text) > 4000 else ""))
    print(f"\nwritten to {args.out}")
    return 0 if math.isfinite(wall) else 1


if __name__ == "__main__":
    raise SystemExit(main())
