"""``python -m bench.forms``: every handed-out form of the default plan, checked as a drive runs it
(issue 25, "What it must show").

Per generated goal (:mod:`bench.goals`, n = 3..6 by default):

* the **default request** (start, goal, robot): its linear path at rest at both ends, no time
  twice (continuous rates), re-integrated by scipy (:func:`bench.reintegrate.integrate`, DOP853,
  piece by piece between the samples, independent of the planner's integrators): the end within
  1e-6 rad of the goal, every joint inside ``(0, 90)`` deg, and the answer's ``indicators``
  equal to those measured on that re-integration (``d_a`` and ``deviation`` within 0.01 deg,
  the same reversal counts). Its quality (reversals, then deviation) against the exact plan's
  (``plan_indicators``: the path the answer handed out before the time law), and its time
  (``timing.total``, wall clock: the NLP methods solve in worker processes) against the
  same without the handed-out stage (``timing.execution``: the time law, the forms'
  correction and checks);
* the **limited request** (``max_u1 = max_u2 = 1`` rad/s, ``max_du1 = max_du2 = 5`` rad/s^2,
  ``joint_trajectory``), and the same with ``controller_period = 0.01`` s: every form -- the
  linear path, the held (zoh) path, the JointTrajectory's quintic Hermite interpolant (scipy's
  ``BPoly.from_derivatives`` of its positions, velocities and accelerations, what
  ``joint_trajectory_controller`` runs) -- evaluated on a dense grid (101 points per interval):
  rates and their derivatives within 1 % of the limits (a held form's derivative is a jump by
  nature: its rates only), each re-integrated by scipy onto the goal within 1e-6 rad, every
  joint inside; the JointTrajectory's positions equal the re-integrated ``phi, th1`` at its
  points (its velocities are the derivative of the positions' interpolant).

Usage::

    .venv/bin/python -m bench.forms                      # n = 3..6: 12, 6, 4, 2 goals
    .venv/bin/python -m bench.forms --counts 3:4,4:2     # fewer
    .venv/bin/python -m bench.forms --out bench/results/forms.json

Prints a Markdown summary (recorded in ``docs/benchmarks.md``) and writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.goals import Goal, generate  # noqa: E402
from bench.reintegrate import (Segment, integrate, joint_trajectory_arrays,  # noqa: E402
                               path_metrics)

#: Goals per number of joints (n = 6 plans take seconds each).
COUNTS = {3: 12, 4: 6, 5: 4, 6: 2}
LIMITS = {"max_u1": 1.0, "max_u2": 1.0, "max_du1": 5.0, "max_du2": 5.0}
#: Rates and derivatives may exceed a limit by this share on the dense grid.
LIMIT_SHARE = 1.01
TERMINAL_TOL = 1e-6
#: Indicators against the re-integrated path (deg).
INDICATOR_TOL_DEG = 0.01
#: Quality "no worse" than the exact plan's: deviation within this (deg).
QUALITY_TOL_DEG = 0.01
PERIOD = 0.01
DENSE = 101


def _request(g: Goal, **extra: Any) -> Any:
    from optimizer.model import Robot
    from optimizer.problem import PlanRequest
    return PlanRequest.from_dict({"start": list(g.start), "goal": list(g.goal),
                                  "robot": Robot.default(g.n), "time_limit": 120.0, **extra})


def _dense(t: np.ndarray) -> np.ndarray:
    s = np.linspace(0.0, 1.0, DENSE)[:, None]
    return np.unique((t[:-1] + s * np.diff(t)).ravel())


def _reintegrate(g: Goal, t: np.ndarray, u_local: Callable[[int, float], np.ndarray],
                 grid: int = 4001) -> tuple[np.ndarray, np.ndarray]:
    """scipy on the original model, one segment per interval of ``t``."""
    from optimizer.model import Robot
    robot = Robot.default(g.n)
    def piece(k: int) -> Callable[[float], np.ndarray]:
        return lambda tt: u_local(k, tt)
    segs = [Segment(float(a), float(b), piece(k))
            for k, (a, b) in enumerate(zip(t[:-1], t[1:])) if b > a]
    q0 = np.concatenate([[0.0], np.asarray(g.start, float)])
    return integrate(robot.gains, robot.exponents, q0, segs, grid)


def _form_checks(g: Goal, t: np.ndarray, x: np.ndarray) -> dict[str, Any]:
    m = path_metrics(t, x, np.asarray(g.start), np.asarray(g.goal))
    return {"terminal_error": m.terminal_error_rad, "margin_deg": m.region_margin_all_deg,
            "reaches": bool(m.ok and m.terminal_error_rad < TERMINAL_TOL),
            "inside": bool(m.ok and m.region_margin_all_deg > 0.0), "metrics": m}


def _linear_u(t: np.ndarray, u: np.ndarray) -> Callable[[int, float], np.ndarray]:
    def f(k: int, tt: float) -> np.ndarray:
        s = (tt - t[k]) / (t[k + 1] - t[k])
        return (1.0 - s) * u[k] + s * u[k + 1]
    return f


def _ratio(peaks: list[np.ndarray], names: list[tuple[str, str]], limits: dict[str, float]
           ) -> float:
    r = 0.0
    for peak, pair in zip(peaks, names):
        for c, name in enumerate(pair):
            if name in limits:
                r = max(r, float(peak[c]) / limits[name])
    return r


def default_row(g: Goal) -> dict[str, Any]:
    """The default request on ``g``: rest, continuity, re-integration, indicators, quality."""
    from optimizer.planner.plan import plan
    req = _request(g)
    w0 = time.perf_counter()
    p = plan(req)
    wall = time.perf_counter() - w0
    t, u = np.asarray(p.path.t), np.asarray(p.path.u)
    tt, x = _reintegrate(g, t, _linear_u(t, u))
    chk = _form_checks(g, tt, x)
    m = chk.pop("metrics")
    ind, exact = p.indicators, p.plan_indicators
    assert exact is not None
    same = {
        "reversals": (ind.reversals_phi, ind.reversals_th1) == (m.reversals_phi,
                                                                m.reversals_th1),
        "d_a": abs(math.degrees(ind.d_a) - m.d_a_deg) <= INDICATOR_TOL_DEG,
        "deviation": abs(math.degrees(ind.deviation) - m.segment_dev_deg) <= INDICATOR_TOL_DEG,
    }
    no_worse = (ind.reversals < exact.reversals or (
        ind.reversals == exact.reversals
        and math.degrees(ind.deviation) <= math.degrees(exact.deviation) + QUALITY_TOL_DEG))
    execution = float(p.timing.get("execution", 0.0))
    total = float(p.timing.get("total", wall))
    return {
        "n": g.n, "method": p.method, "wall_s": wall, "total_s": total,
        "execution_s": execution,
        # the plan's time against the same plan without its handed-out stage (the time law,
        # the forms' correction and checks): what the forms add to a plan
        "time_ratio": total / max(total - execution, 1e-12),
        "samples": int(t.size), "densified": p.diagnostics.get("samples"),
        "rest_at_ends": bool(np.all(u[0] == 0.0) and np.all(u[-1] == 0.0)),
        "no_repeated_time": bool(np.all(np.diff(t) > 0.0)),
        **chk,
        "indicators_equal": all(same.values()), "indicator_checks": same,
        "handed_out": {"reversals": [ind.reversals_phi, ind.reversals_th1],
                       "deviation_deg": math.degrees(ind.deviation),
                       "d_a_deg": math.degrees(ind.d_a)},
        "reintegrated": {"reversals": [m.reversals_phi, m.reversals_th1],
                         "deviation_deg": m.segment_dev_deg, "d_a_deg": m.d_a_deg},
        "plan": {"reversals": [exact.reversals_phi, exact.reversals_th1],
                 "deviation_deg": math.degrees(exact.deviation),
                 "d_a_deg": math.degrees(exact.d_a)},
        "quality_no_worse": bool(no_worse),
    }


def limited_row(g: Goal) -> dict[str, Any]:
    """The limited request on ``g``: every form against the limits on a dense grid, and
    re-integrated."""
    from scipy.interpolate import BPoly

    from optimizer.planner.plan import plan
    out: dict[str, Any] = {"n": g.n}
    p = plan(_request(g, **LIMITS, joint_trajectory=True))
    out["method"] = p.method
    out["duration"] = float(p.duration)
    # the linear form: rates and slopes (its derivative between samples)
    t, u = np.asarray(p.path.t), np.asarray(p.path.u)
    td = _dense(t)
    ud = np.stack([np.interp(td, t, u[:, c]) for c in range(2)], axis=1)
    slope = np.diff(u, axis=0) / np.diff(t)[:, None]
    out["linear"] = {
        "limit_ratio": _ratio([np.abs(ud).max(axis=0), np.abs(slope).max(axis=0)],
                              [("max_u1", "max_u2"), ("max_du1", "max_du2")], LIMITS),
        "rest_at_ends": bool(np.all(u[0] == 0.0) and np.all(u[-1] == 0.0)),
        "no_repeated_time": bool(np.all(np.diff(t) > 0.0))}
    tt, x = _reintegrate(g, t, _linear_u(t, u))
    out["linear"].update({k: v for k, v in _form_checks(g, tt, x).items() if k != "metrics"})
    # the JointTrajectory: scipy's quintic Hermite interpolant of its points
    jt = p.to_dict()["joint_trajectory"]
    tj, X, V, A = joint_trajectory_arrays(jt)
    polys = [BPoly.from_derivatives(tj, np.stack([X[:, c], V[:, c], A[:, c]], axis=1))
             for c in range(2)]
    tdj = _dense(tj)
    peaks = [np.array([np.abs(bp.derivative(o + 1)(tdj)).max() for bp in polys])
             for o in range(2)]
    rates = [bp.derivative() for bp in polys]

    def jt_u(k: int, s: float) -> np.ndarray:
        return np.array([float(r(s)) for r in rates])
    tt, x = _reintegrate(g, tj, jt_u)
    at_points = np.stack([np.interp(tj, tt, x[:, c]) for c in range(2)], axis=1)
    exact_pts = np.isin(tt, tj)
    pos_err = float(np.max(np.abs(x[exact_pts, :2] - X[np.isin(tj, tt)]))) if exact_pts.any() \
        else float(np.max(np.abs(at_points - X)))
    out["joint_trajectory"] = {
        "limit_ratio": _ratio(peaks, [("max_u1", "max_u2"), ("max_du1", "max_du2")], LIMITS),
        "time_scale": float(jt["time_scale"]),
        "rest_at_ends": bool(np.all(V[0] == 0.0) and np.all(V[-1] == 0.0)),
        "accelerations_filled": bool(A.shape == X.shape),
        "position_error": pos_err,
        "positions_consistent": bool(pos_err < TERMINAL_TOL)}
    out["joint_trajectory"].update(
        {k: v for k, v in _form_checks(g, tt, x).items() if k != "metrics"})
    # the held form on a 10 ms period: its rates (a hold jumps: no derivative)
    ph = plan(_request(g, **LIMITS, controller_period=PERIOD))
    th, uh = np.asarray(ph.path.t), np.asarray(ph.path.u)
    tt, x = _reintegrate(g, th, lambda k, s: uh[k])
    out["zoh"] = {"limit_ratio": _ratio([np.abs(uh).max(axis=0)], [("max_u1", "max_u2")],
                                        LIMITS)}
    out["zoh"].update({k: v for k, v in _form_checks(g, tt, x).items() if k != "metrics"})
    return out


def _share(rows: list[dict[str, Any]], ok: Callable[[dict[str, Any]], bool]) -> str:
    good = sum(1 for r in rows if ok(r))
    return f"{good}/{len(rows)}"


def _within(form: str) -> Callable[[dict[str, Any]], bool]:
    return lambda r: bool(r[form]["limit_ratio"] <= LIMIT_SHARE)


def summarise(default: list[dict[str, Any]], limited: list[dict[str, Any]]) -> str:
    """The Markdown table of the run."""
    lines = ["| n | goals | default: rest, no time twice | reaches 1e-6, inside | "
             "indicators = re-integrated | quality >= plan's | plan s (median) | "
             "time / without forms (median, max) | limited: linear / JT / zoh within 1 % | "
             "re-integrated onto goal, inside (3 forms) | JT positions consistent | "
             "JT time_scale (max) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for n in sorted({r["n"] for r in default}):
        d = [r for r in default if r["n"] == n]
        lim = [r for r in limited if r["n"] == n and "error" not in r]
        ok = [r for r in d if "error" not in r]
        secs = float(np.median([r["total_s"] for r in ok])) if ok else math.nan
        ratios = [r["time_ratio"] for r in ok] or [math.nan]
        forms = ("linear", "joint_trajectory", "zoh")
        within = " / ".join(_share(lim, _within(f)) for f in forms)
        reach = _share(lim, lambda r: all(r[f]["reaches"] and r[f]["inside"] for f in forms))
        lines.append(
            f"| {n} | {len(d)} | "
            f"{_share(d, lambda r: r['rest_at_ends'] and r['no_repeated_time'])} | "
            f"{_share(d, lambda r: r['reaches'] and r['inside'])} | "
            f"{_share(d, lambda r: r['indicators_equal'])} | "
            f"{_share(d, lambda r: r['quality_no_worse'])} | {secs:.3f} | "
            f"{float(np.median(ratios)):.2f}, {max(ratios):.2f} | "
            f"{within} | {reach} | "
            f"{_share(lim, lambda r: r['joint_trajectory']['positions_consistent'])} | "
            f"{max([r['joint_trajectory']['time_scale'] for r in lim] or [float('nan')]):.3f} |")
    errors = [r for r in limited if "error" in r]
    if errors:
        lines.append(f"\nLimited requests refused: {len(errors)} "
                     + "; ".join(f"n={r['n']}: {r['error'][:120]}" for r in errors))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.forms", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", default=None,
                    help="goals per n, e.g. 3:12,4:6,5:4,6:2 (the default)")
    ap.add_argument("--out", type=Path, default=None, help="JSON of every row")
    args = ap.parse_args(argv)
    counts = dict(COUNTS)
    if args.counts:
        counts = {int(a): int(b) for a, b in (x.split(":") for x in args.counts.split(","))}
    default: list[dict[str, Any]] = []
    limited: list[dict[str, Any]] = []
    for n, k in counts.items():
        for g in generate(n, k):
            try:
                default.append(default_row(g))
            except Exception as exc:  # noqa: BLE001 - recorded as a failure of the goal
                default.append({"n": n, "error": f"{type(exc).__name__}: {exc}",
                                "rest_at_ends": False,
                                "no_repeated_time": False, "reaches": False, "inside": False,
                                "indicators_equal": False, "quality_no_worse": False})
            try:
                limited.append(limited_row(g))
            except Exception as exc:  # noqa: BLE001 - recorded
                limited.append({"n": n, "error": f"{type(exc).__name__}: {exc}"})
            print(f"n={n} goal done", file=sys.stderr, flush=True)
    text = summarise(default, limited)
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"default": default, "limited": limited}, indent=1,
                                       default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
