"""The cheaper paths of the ``retimed`` plan against independent computations.

* the time-law LP's CSC matrices against scipy's constructor, and the time law with scipy's
  matrices (the fallback) against the default path;
* the coarse screen of the candidates (13 times) against the interval search's 97-time grid
  and a brute-force choice over all members (fewest t_p, then the Fréchet bound, among the
  members that pass the exact check);
* the exact region check runs once per plan, on the returned plan's geometric path.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse

from optimizer import region as region_mod
from optimizer.indicators import count_reversals
from optimizer.planner import retime
from optimizer.planner.intervals import dphi_grid
from optimizer.planner.context import Deadline
from optimizer.planner.family import family_for
from optimizer.planner.plan import plan
from optimizer.planner import qp
from optimizer.planner.retimed import RETIME_SIGMA_SAMPLES
from optimizer.planner.rules import phi_search_bounds
from optimizer.problem import PlanRequest


def _req(start_deg: list[float], goal_deg: list[float], **kw: object) -> PlanRequest:
    return PlanRequest(start=tuple(np.radians(start_deg)), goal=tuple(np.radians(goal_deg)),
                       method="retimed", objective="tp_then_da", **kw)  # type: ignore[arg-type]


def test_csc_matches_scipy() -> None:
    rng = np.random.default_rng(4)
    for shape in ((136, 8), (5, 5), (7, 3)):
        A = rng.normal(size=shape)
        A[rng.uniform(size=shape) < 0.6] = 0.0
        A[:, 1] = 0.0                                       # an empty column
        ours = qp.Csc.from_dense(A)
        ref = sparse.csc_matrix(A)
        ref.sort_indices()
        assert ours.shape == ref.shape and ours.nnz == ref.nnz
        assert np.array_equal(ours.indptr, ref.indptr)
        assert np.array_equal(ours.indices, ref.indices)
        assert np.array_equal(ours.data, ref.data)
        assert np.array_equal(ours.to_scipy().toarray(), A)


def test_time_law_scipy_fallback_agrees(monkeypatch: pytest.MonkeyPatch) -> None:
    f = lambda s: 0.2 + 0.4 * s + 0.15 * np.sin(7 * s)  # noqa: E731 - a th1 with a backtrack
    law = retime.optimal_time_law(f, 0.2, 0.6)

    class Strict(qp.Csc):  # a Clarabel that reads scipy's own attributes only
        def __getattribute__(self, name: str) -> object:
            if name == "has_canonical_format":
                raise AttributeError(name)
            return object.__getattribute__(self, name)

    monkeypatch.setattr(qp.Csc, "from_dense", classmethod(
        lambda cls, A: Strict(*(lambda c: (c.data, c.indices, c.indptr, c.shape))(
            sparse.csc_matrix(A)))))
    ref = retime.optimal_time_law(f, 0.2, 0.6)
    np.testing.assert_allclose(law.knots_tau, ref.knots_tau, rtol=0, atol=1e-12)
    assert abs(law.deviation - ref.deviation) < 1e-12


@pytest.mark.parametrize("start,goal", [([10, 10, 10], [30, 30, 30]), ([1, 1, 1], [30, 30, 30]),
                                        ([20, 20, 20], [40, 40, 40]),
                                        ([9, 11, 10.5], [30, 30, 30])])
def test_screen_keeps_the_choice(start: list[float], goal: list[float]) -> None:
    req = _req(start, goal)
    fam = family_for(req, Deadline(10.0))
    grid = dphi_grid(*phi_search_bounds(req))
    fine = fam.coarse_margins(grid) > 0.0
    screen = fam.coarse_margins(grid, grid=retime.SCREEN_TIMES) > 0.0
    assert np.all(screen[fine])                     # the screen keeps every member of the grid
    for d in grid[screen & ~fine]:                  # the extra ones fail the exact check
        assert not fam.confirm(float(d))[0]
    # members too short to move th_n far enough (K_n |dphi| <= |dth_n|) fail it too
    short = np.abs(grid) * req.robot.gains[-1] <= abs(req.goal[-1] - req.start[-1])
    assert short.any()
    for d in grid[short & fine]:
        assert not fam.confirm(float(d))[0]
    # brute force: among all members passing the exact check, fewest t_p then smallest bound
    best = None
    a, b = req.start[0], req.goal[0]
    sig = np.linspace(0.0, 1.0, RETIME_SIGMA_SAMPLES)
    for d in grid[fine]:
        if not fam.confirm(float(d))[0]:
            continue
        th1 = fam.cf.from_chained(fam.path(float(d)).z(sig)).q[:, 1]
        key = (count_reversals(th1), float(retime.frechet_bound(th1, a, b)))
        if best is None or key < best[0]:
            best = (key, float(d))
    assert best is not None
    p = plan(req)
    assert abs(p.diagnostics["geometric_phi_change"] - best[1]) < 1e-12


def test_exact_check_runs_once_on_the_returned_path(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[tuple[str, tuple[np.ndarray, ...]]] = []
    orig = region_mod.Region._check_path

    def spy(self: region_mod.Region, path: object, grid: int, locate: bool) -> object:
        seen.append((self.criterion, path.polys))  # type: ignore[attr-defined]
        return orig(self, path, grid, locate)  # type: ignore[arg-type]

    monkeypatch.setattr(region_mod.Region, "_check_path", spy)
    region_mod._CHECKS.clear()
    req = _req([10.3, 9.7, 10.1], [30, 30, 30])
    p = plan(req)
    assert len(seen) == 1
    fam = family_for(req, Deadline(10.0))
    geo = fam.path(p.diagnostics["geometric_phi_change"])
    assert seen[0][0] == "full"
    assert all(np.array_equal(x, y) for x, y in zip(seen[0][1], geo.polys))
    # and the returned path passes through the checked one's states
    # (phi runs linearly in sigma on the geometric path: it gives sigma at every time)
    z = p.chained.z(np.linspace(0.0, 1.0, 11))
    sig = (z[:, 0] - z[0, 0]) / p.diagnostics["geometric_phi_change"]
    np.testing.assert_allclose(z, geo.z(sig), atol=1e-12)


@pytest.mark.parametrize("kw", [{}, {"singularity": "z2"},
                                {"joint_bounds": ((0.05, 1.2), None, None)}])
def test_coarse_inside_is_the_sign_of_coarse_margins(kw: dict[str, object]) -> None:
    """The angle-free test of the screen against the sampled margins, on members inside,
    near and far outside the region (every dphi of a dense grid over [-pi, pi])."""
    rng = np.random.default_rng(12)
    grid = np.linspace(-np.pi, np.pi, 4001)
    found = 0
    for _ in range(4):
        start = list(10.0 + rng.uniform(-8.0, 8.0, 3))
        req = _req(start, [30.0, 30.0, 30.0], **kw)
        fam = family_for(req, Deadline(10.0))
        for times in (retime.SCREEN_TIMES, 97):
            inside = fam.coarse_inside(grid, times)
            found += int(inside.sum())
            assert np.array_equal(inside, fam.coarse_margins(grid, times) > 0.0)
    assert found > 0


def test_surely_regular_means_the_condition_test_passes() -> None:
    """Where FamilySystem.surely_regular skips solve_polynomial's condition test, the test
    (computed here) passes, and the inputs are the same with and without it."""
    from optimizer.model import Robot
    from optimizer.steering import (MAX_CONDITION, ConstraintPoint, FamilySystem,
                                    solve_polynomial, steering_system)
    from optimizer.chained_form import chained_form

    rng = np.random.default_rng(3)
    for n, pts in ((3, ()), (4, ()), (6, ()), (3, (ConstraintPoint(0.5, 2, -0.1),)),
                   (3, (ConstraintPoint(0.3, 3, 0.5), ConstraintPoint(0.7, 2, -0.2)))):
        robot = Robot.default(n)
        cf = chained_form(robot)
        z0 = cf.to_chained(np.concatenate([[0.0], rng.uniform(0.1, 0.5, n)]))
        zT = cf.to_chained(np.concatenate([[0.0], rng.uniform(0.5, 1.0, n)]))
        fs = FamilySystem(n, z0, zT, 1.0, pts)
        skipped = 0
        for d in np.concatenate([np.geomspace(1e-6, 1e6, 60), -np.geomspace(1e-6, 1e6, 60)]):
            if not fs.surely_regular(d):
                continue
            skipped += 1
            M, _ = steering_system(float(d), n, z0, zT, n + len(pts), pts, 1.0)
            scale = np.linalg.norm(M, axis=0)
            assert np.linalg.cond(M / scale) <= MAX_CONDITION
            a = solve_polynomial(float(d), n, z0, zT, 1.0, pts, known_regular=True)
            b = solve_polynomial(float(d), n, z0, zT, 1.0, pts)
            assert np.array_equal(a.v2[0], b.v2[0])
        assert skipped > 0
