"""Method ``retimed``: the paper's geometric path run along the time law that minimises ``d_a``
(:mod:`.retime`). Retiming changes neither the geometric path nor ``t_p``, ``deviation`` or
``||J_R(T)||_F``; it changes ``d_a`` (joint 1 against the straight line in time)."""

from __future__ import annotations

import time

import numpy as np

from ..errors import InfeasibleError, InvalidRequestError
from ..indicators import count_reversals_columns
from ..problem import PlanRequest
from ..results import Plan
from ..steering import polyval_rows
from .base import Capabilities, Method
from .context import Deadline, PlanContext
from .family import family_for
from .finish import finish_plan
from .intervals import dphi_grid, feasible_intervals
from .objectives import optimise, window_nodes
from .retime import SCREEN_TIMES, frechet_bound, optimal_time_law, retimed_path
from .rules import phi_search_bounds

#: Members of the window ranked by their Fréchet bound before the time-law LP.
RETIME_CANDIDATES = 24
#: Path samples per member for that ranking.
RETIME_SIGMA_SAMPLES = 257


def plan_retimed(req: PlanRequest, deadline: Deadline) -> Plan:
    """The paper's geometric path, run along the time law that minimises ``d_a`` (:mod:`.retime`).

    The member (``dphi``) is the request's ``phi_change`` or, for ``tp_then_da``, the one with
    the fewest ``t_p`` and then the smallest Fréchet bound (the best ``d_a`` any time law can
    reach on it); for the other objectives the polynomial method's choice, which retiming does
    not change (``t_p``, ``||J_R(T)||_F`` and the region are geometric).
    """
    if req.constraint_points:
        raise InvalidRequestError(
            "method 'retimed' changes when the path passes its points, so it takes no "
            "constraint points (use 'polynomial' or 'constraint_points')",
            field="constraint_points")
    timing: dict[str, float] = {}
    fam = family_for(req, deadline)
    a, b = float(req.start[0]), float(req.goal[0])
    t0 = time.perf_counter()
    feasible: list[tuple[float, float]] = []
    if req.phi_change is not None:
        fam.inputs(float(req.phi_change))  # raises SingularSystemError for dphi = 0 (Remark 2)
        if not fam.evaluate(float(req.phi_change)).ok:
            raise InfeasibleError(
                f"phi_change = {req.phi_change:.6g} rad gives a path that leaves the "
                f"singularity-free region ({req.singularity} criterion)",
                diagnostics={"blocking": "singularity"})
        dphi = float(req.phi_change)
    else:
        lo, hi = phi_search_bounds(req)

        def by_bound(cands: np.ndarray) -> float | None:
            """The member with the fewest t_p, then the smallest Fréchet bound (sampled),
            that passes the continuous check."""
            sig = np.linspace(0.0, 1.0, RETIME_SIGMA_SAMPLES)
            if fam.cf.backend == "closed":
                # n = 3: only z2 and z3 at the samples (the members' coefficients are finite
                # where regular, so z1 and z4 are too)
                coef, regular = fam.polys(cands)
                z23 = polyval_rows(coef[:, 1:3, :], sig)                # (D, 2, G)
                th1, okf = fam.cf.th1_from_z23(z23[:, 0], z23[:, 1])
                th1 = np.where(okf, th1, 0.0)
                valid = regular & okf.all(axis=1)
            else:
                z, regular, _ = fam.batch_z(cands, sig)
                th1f, okf = fam.cf.th1_from_chained(z.reshape(-1, req.robot.n + 1))
                th1 = th1f.reshape(cands.size, sig.size)
                valid = regular & okf.reshape(cands.size, sig.size).all(axis=1)
            bound = frechet_bound(th1, a, b)
            tps = count_reversals_columns(th1.T)          # count_reversals of every row, vectorised
            for i in np.lexsort((bound, tps)):
                # the continuous check of the path that is returned (Region.check_path on
                # fam.path, request's criterion and the full region): finish_plan's check of
                # the same path is then answered from check_path's memo, not run twice
                if valid[i] and fam.confirm(float(cands[i]))[0]:
                    return float(cands[i])
            return None

        chosen: float | None = None
        if req.objective == "tp_then_da":
            # Members whose sampled margin is positive on the interval search's own coarse
            # grid are enough to rank by the bound (the winner is checked exactly), without
            # refining the interval ends. Windows narrower than the grid (n >= 4) leave none:
            # then the exact intervals, as for the other objectives.
            # The candidates are screened on SCREEN_TIMES times only: a member's
            # continuous margin is at most its margin at any sampled times, so a member with a
            # margin <= 0 there (all but a few) cannot pass the exact check, and one that is
            # kept but fails it is skipped by `by_bound` like any other. Equivalent to the
            # 97-time coarse grid of the interval search, at a third of the cost.
            # Nor can a member with K_n |dphi| <= |th_n(T) - th_n(0)|: inside the region
            # 0 < z_n < K_n, and th_n' = z_n phi' (a hair of slack for the solve's rounding).
            grid = dphi_grid(lo, hi)
            reach = abs(req.goal[-1] - req.start[-1]) * (1.0 - 1e-9)
            grid = grid[np.abs(grid) * req.robot.gains[-1] > reach]
            coarse = grid[fam.coarse_inside(grid, grid=SCREEN_TIMES)] if grid.size else grid
            if coarse.size:
                chosen = by_bound(coarse)
            timing["coarse_scan"] = time.perf_counter() - t0
        if chosen is None:
            t1 = time.perf_counter()
            feasible = feasible_intervals(fam, lo, hi)
            timing["intervals"] = time.perf_counter() - t1
            deadline.check("the interval search")
            if not feasible:
                raise InfeasibleError(
                    f"no phi_change in [{lo:.6g}, {hi:.6g}] rad gives a singularity-free path "
                    "of the polynomial family", diagnostics={
                        "blocking": "no_feasible_phi_change", "searched": [lo, hi]})
            t2 = time.perf_counter()
            if req.objective == "tp_then_da":
                chosen = by_bound(window_nodes(feasible, RETIME_CANDIDATES))
            else:  # the polynomial method's choice (retiming changes neither t_p nor ||J_R||)
                best_e = optimise(fam, feasible, req.objective, req.weights)
                chosen = None if best_e is None else best_e.dphi
            timing["objective"] = time.perf_counter() - t2
        if chosen is None:
            raise InfeasibleError("the feasible intervals are too narrow to hold a path",
                                  diagnostics={"feasible_phi_changes": feasible})
        dphi = chosen
    path = fam.path(dphi)
    t2 = time.perf_counter()
    cf = fam.cf
    if cf.backend == "closed":  # n = 3: th1 from z2, z3 (z1, z4 of a member are finite)
        def th1_of(s: np.ndarray) -> np.ndarray:
            z23 = path.z_components(s, 1, 3)
            th, ok = cf.th1_from_z23(z23[:, 0], z23[:, 1])
            return np.where(ok, th, 0.0)
    else:
        def th1_of(s: np.ndarray) -> np.ndarray:
            return cf.th1_from_chained(path.z(s))[0]
    law = optimal_time_law(th1_of, a, b)
    retimed = retimed_path(path, law)
    timing["time_law"] = time.perf_counter() - t2
    deadline.check("the time law")
    return finish_plan(req, retimed.inputs, "retimed", feasible, timing,
                       {"objective": req.objective, "singularity": req.singularity,
                        "geometric_phi_change": dphi,
                        "time_law": {"knots_t_over_T": law.knots_tau.tolist(),
                                     "lp_d_a": law.deviation, "d_a_lower_bound": law.bound}},
                       chained=retimed, geometry=path)


class RetimedMethod(Method):
    name = "retimed"
    capabilities = Capabilities(constraint_points=False, fixed_phi_change=True,
                                reverses_phi=False, inputs="chained")

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        return plan_retimed(req, ctx.deadline)
