"""Batched members of the paper's family against the one-member definitions.

* ``FamilySystem`` (eq 10-11 for many dphi from one factorisation) against
  ``solve_polynomial``: coefficients, singular members, chained polynomials;
* ``PolynomialFamily.sample`` / ``coarse_margins`` / ``margins`` against the inverse map and
  ``Region.check_path`` member by member;
* the vectorised reversal count against ``count_reversals``;
* interval ends lie on the feasible side of the boundary, within 1e-10 rad of it.
"""

from __future__ import annotations

import numpy as np
import pytest

from optimizer.errors import SingularSystemError
from optimizer.indicators import count_reversals, line_deviation
from optimizer.model import Robot
from optimizer.indicators import count_reversals_columns
from optimizer.planner.family import PolynomialFamily
from optimizer.planner.intervals import feasible_intervals
from optimizer.planner.rules import make_region
from optimizer.problem import PlanRequest
from optimizer.steering import (ChainedPath, ConstraintPoint, FamilySystem, polyval_rows,
                                solve_polynomial)

D = np.deg2rad


@pytest.mark.parametrize("n, T, points", [
    (3, 1.0, ()),
    (3, 10.0, (ConstraintPoint(5.0, 2, -0.3),)),
    (4, 2.0, (ConstraintPoint(0.5, 3, -0.1), ConstraintPoint(1.5, 2, -0.3))),
    (5, 1.0, ()),
    (6, 0.5, ()),
    (8, 1.0, ()),
])
def test_family_system_matches_solve_polynomial(n, T, points):
    rng = np.random.default_rng(n)
    z0 = np.concatenate([[0.3], 0.3 * rng.normal(size=n)])
    zT = np.concatenate([[0.0], 0.3 * rng.normal(size=n)])
    fs = FamilySystem(n, z0, zT, T, points)
    ds = np.concatenate([np.geomspace(1e-7, 12, 120), -np.geomspace(1e-7, 12, 120), [0.0]])
    a, ok = fs.coefficients(ds)
    coef = fs.polys(ds, a)
    taus = np.linspace(0.0, 1.0, 5)
    Z = polyval_rows(coef, taus)
    for i, d in enumerate(ds):
        try:
            inp = solve_polynomial(d, n, z0, zT, T, points)
        except SingularSystemError:
            assert not ok[i]
            continue
        assert ok[i]
        ref = ChainedPath.from_inputs(z0, inp).z(taus).T
        scale = max(1.0, float(np.abs(ref).max()))
        np.testing.assert_allclose(Z[i], ref, atol=1e-6 * scale)
        np.testing.assert_allclose(a[i], inp.v2[0], atol=1e-6 * max(1.0, np.abs(a[i]).max()))


def _family(start_deg, goal_deg, criterion="full", robot=None, bounds=None):
    robot = robot or Robot.default(len(start_deg))
    req = PlanRequest(start=tuple(D(start_deg)), goal=tuple(D(goal_deg)), robot=robot,
                      singularity=criterion, joint_bounds=bounds)
    return PolynomialFamily(robot, req.q_start(), req.q_goal(0.0), 1.0, (), make_region(req))


@pytest.mark.parametrize("start, goal, criterion", [
    ([10, 10, 10], [30, 30, 30], "full"),
    ([10, 10, 10], [30, 30, 30], "z2"),
    ([47.7, 66.9, 44.9, 66.0], [62.6, 72.2, 47.5, 71.9], "full"),
])
def test_sampled_members_match_the_inverse_map(start, goal, criterion):
    """``sample``: validity, margin, d_a, t_p and energy of many members at once equal the
    one-member computation with ``from_chained``; ``coarse_margins`` is the sampled margin;
    ``margins`` equals ``check_path`` member by member."""
    fam = _family(start, goal, criterion)
    cf = fam.cf
    ds = np.linspace(D(20.0), D(40.0), 41)
    s = fam.sample(ds, energy=True)
    tau = fam.tau
    for i, d in enumerate(ds):
        path = fam.path(d)
        inv = cf.from_chained(path.z(tau))
        ok = bool(inv.valid.all()) and fam.full.margin_q(inv.q).min() > 0
        if criterion == "z2":
            ok = ok and path.z(tau)[:, 1].max() < 0
        assert s.ok[i] == ok
        if not ok:
            continue
        th1 = inv.q[:, 1]
        assert s.d_a[i] == pytest.approx(np.abs(line_deviation(tau, th1)).max(), abs=1e-12)
        assert s.t_p[i] == count_reversals(th1)
        e = fam.evaluate(float(d))
        assert s.energy[i] == pytest.approx(e.energy, rel=1e-9)
    taus = np.linspace(0.0, 1.0, 97)
    coarse = fam.coarse_margins(ds)
    exact = fam.margins(ds).margin
    for i, d in enumerate(ds):
        z = fam.path(d).z(taus)
        assert coarse[i] == pytest.approx(fam.region.signed_margin_z(z).min(), abs=1e-9)
        chk = fam.region.check_path(fam.path(d))
        assert (exact[i] > 0) == chk.ok
        if chk.margin > -0.05:   # far outside (poles of the inverse map) only the sign is exact
            assert exact[i] == pytest.approx(chk.margin, abs=1e-10)
            assert exact[i] <= coarse[i] + 1e-12


def test_reversal_count_vectorised():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 1, 1001)
    cols = []
    for i in range(600):
        x = (np.sin(2 * np.pi * rng.uniform(0, 3) * t + rng.uniform(0, 6))
             * rng.choice([1, 1e-6, 1e-7, 3e-6]) + rng.choice([0, 1]) * t * rng.normal())
        k = i % 4
        if k == 1:
            x = np.round(x, 6)          # flat steps
        elif k == 2:
            x[:100] = x[100]            # a flat start
        elif k == 3:
            x = x + 1e-7 * rng.normal(size=t.size)   # wiggles inside the dead band
        cols.append(x)
    X = np.array(cols).T.copy()
    np.testing.assert_array_equal(count_reversals_columns(X),
                                  [count_reversals(X[:, i]) for i in range(X.shape[1])])


@pytest.mark.parametrize("start, goal, criterion, bounds", [
    ([10, 10, 10], [30, 30, 30], "full", None),
    ([10, 10, 10], [30, 30, 30], "z2", None),
    ([10, 10, 10], [30, 30, 30], "full", [(D(5.0), D(80.0)), None, None]),
    ([47.7, 66.9, 44.9, 66.0], [62.6, 72.2, 47.5, 71.9], "full", None),
])
def test_interval_ends_on_the_feasible_side(start, goal, criterion, bounds):
    """Every reported end is a feasible member (exact margin > 0, and the path passes
    check_path), and a member 1e-10 rad outside it is not (unless the end is a search bound)."""
    fam = _family(start, goal, criterion, bounds=bounds)
    iv = feasible_intervals(fam, 0.0, np.pi)
    assert iv
    for a, b in iv:
        inside = fam.margins(np.array([a, b])).margin
        assert np.all(inside > 0)
        assert fam.check(a).ok and fam.check(b).ok
        outside = fam.margins(np.array([a - 1e-10, b + 1e-10])).margin
        assert np.all(outside <= 0)
