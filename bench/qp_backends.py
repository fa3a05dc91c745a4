"""Which QP backend for constraint-point synthesis (``optimizer/planner/convex.py``)?

The same base QP (no cuts) of the paper's §3.3 example -- prototype robot, th from [1, 1, 1] to
[30, 30, 30] deg, ``m`` extra V2 coefficients, Chebyshev grid -- is solved for ``--solves``
different ``dphi`` by three backends, each set up ONCE and then re-solved:

``clarabel-fresh``
    Clarabel's own Python API, a fresh ``clarabel.DefaultSolver`` per solve from
    scipy.sparse CSC data (:func:`optimizer.planner.legendre_qp.solve_qp` with
    ``persistent=False``).
``clarabel-persistent``
    The same, but one solver per problem shape, built once and then updated in place
    (``solver.update(A=..., b=...)``, presolve off, structural zeros kept): what legendre_qp.py uses
    (``persistent=True``).
``cvxpy-dpp``
    One ``cvxpy.Problem`` built once with ``Parameter`` G and h (DPP-compliant, so re-solves
    skip canonicalisation), solved by Clarabel through cvxpy.

The timed region of each solve starts from the assembled matrices ``(G_y, h_y)`` (their
assembly, common to all backends, is timed separately) and ends with the solution vector. The
script prints the median and the 10 %/90 % quantiles and checks that the three agree.

Usage::

    .venv/bin/python bench/qp_backends.py [--solves 50] [--extra 4] [--grid 160]
"""

from __future__ import annotations

import argparse
import gc
import math
import statistics
import sys
import time
import warnings
from pathlib import Path

import cvxpy as cp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from optimizer.planner import legendre_qp  # noqa: E402
from optimizer.planner.constraint_qp import ConstraintPointQP  # noqa: E402
from optimizer.problem import PlanRequest  # noqa: E402


def normalise(G: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row scaling as in :func:`solve_qp` (all backends get the same problem)."""
    nrm = np.linalg.norm(G, axis=1)
    return G / nrm[:, None], h / nrm


class CvxpyDPP:
    """One cvxpy Problem with Parameters, built once (DPP: no re-canonicalisation)."""

    def __init__(self, r: int, d: int) -> None:
        self.y = cp.Variable(d)
        self.G = cp.Parameter((r, d))
        self.h = cp.Parameter(r)
        self.prob = cp.Problem(cp.Minimize(0.5 * cp.sum_squares(self.y)),
                               [self.G @ self.y <= self.h])
        assert self.prob.is_dpp()

    def solve(self, G: np.ndarray, h: np.ndarray) -> np.ndarray:
        self.G.value, self.h.value = normalise(G, h)
        self.prob.solve(solver=cp.CLARABEL)
        assert self.prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE), self.prob.status
        return np.asarray(self.y.value)


def clarabel_via_convex(persistent: bool):
    """legendre_qp.solve_qp, the method's own solve path, with or without solver reuse."""
    def solve(G: np.ndarray, h: np.ndarray) -> np.ndarray:
        status, y, _ = legendre_qp.solve_qp(G, h, persistent=persistent)
        assert y is not None, status
        return y
    return solve


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--solves", type=int, default=50)
    ap.add_argument("--extra", type=int, default=4, help="extra V2 coefficients m")
    ap.add_argument("--grid", type=int, default=160, help="interior grid points")
    ap.add_argument("--repeat", type=int, default=3, help="passes over the dphi values")
    args = ap.parse_args()
    # cvxpy warns on Clarabel's AlmostSolved ("optimal_inaccurate"); the agreement check below
    # is what matters
    warnings.filterwarnings("ignore", message="Solution may be inaccurate")

    d2r = math.radians
    req = PlanRequest(start=(d2r(1),) * 3, goal=(d2r(30),) * 3, duration=10.0,
                      method="constraint_points")
    qp = ConstraintPointQP(req, extra_degrees=args.extra, grid=args.grid)
    # dphi where the base QP is feasible (plain family: [45.46, 47.53] deg; QP wider)
    dphis = np.radians(np.linspace(45.5, 47.5, args.solves))
    t0 = time.perf_counter()
    data = [qp.assemble(qp.setup(float(d)))[:2] for d in dphis]
    t_asm = (time.perf_counter() - t0) / len(dphis)
    r, d = data[0][0].shape
    print(f"base QP: n = 3, m = {args.extra}, grid = {args.grid}: {d} variables (null space "
          f"of the goal), {r} inequality rows; assembly (setup + rows) {t_asm * 1e3:.2f} ms/solve")

    backends = {
        "clarabel-fresh (solver per solve)": clarabel_via_convex(False),
        "clarabel-persistent (convex.py)": clarabel_via_convex(True),
        "cvxpy-dpp (Clarabel)": CvxpyDPP(r, d).solve,
    }
    for fn in backends.values():  # build once: cvxpy compiles its parameter map here
        fn(*data[0])
    sols: dict[str, list[np.ndarray]] = {k: [] for k in backends}
    times: dict[str, list[float]] = {k: [] for k in backends}
    names = list(backends)
    # interleaved (round robin, rotating order): load from other processes on the machine
    # then hits every backend alike instead of whichever happens to run during a busy spell
    gc.disable()
    for rep in range(args.repeat):
        for j, (G, h) in enumerate(data):
            order = names[(j + rep) % len(names):] + names[:(j + rep) % len(names)]
            for name in order:
                t = time.perf_counter()
                y = backends[name](G, h)
                times[name].append(time.perf_counter() - t)
                if rep == 0:
                    sols[name].append(y)
    gc.enable()
    print(f"{'backend':34s} {'median':>9s} {'p10':>9s} {'p90':>9s}   ({args.solves} solves x "
          f"{args.repeat} repeats, interleaved)")
    medians = {}
    for name in names:
        q = np.quantile(times[name], [0.1, 0.9])
        medians[name] = statistics.median(times[name])
        print(f"{name:34s} {medians[name] * 1e3:8.3f}ms {q[0] * 1e3:8.3f}ms {q[1] * 1e3:8.3f}ms")
    fastest = min(medians, key=medians.__getitem__)
    print(f"fastest: {fastest}; cvxpy-dpp / fastest = "
          f"{medians['cvxpy-dpp (Clarabel)'] / medians[fastest]:.2f}")
    ref = sols["clarabel-fresh (solver per solve)"]
    for name, out in sols.items():
        err = max(float(np.max(np.abs(a - b)) / max(1.0, float(np.max(np.abs(b)))))
                  for a, b in zip(out, ref))
        print(f"  {name:32s} max relative difference from clarabel-fresh: {err:.1e}")


if __name__ == "__main__":
    main()
