"""The vectorised region engine against the scalar definitions it replaces.

* ``Region.values`` / ``signed_margin_z`` against the joint-space margin of the inverse map;
* ``Region.grid_margins`` (per-member reduction in cos^m space) against the sampled margin;
* ``Region.poly_minimum`` / ``check_path`` against dense brute-force sampling, for the paper's
  family, several joints, joint bounds and piecewise (phi-reversing) inputs;
* the numpy inverse-map levels (closed forms and CasADi expressions translated to numpy)
  against CasADi; batched real roots against numpy.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import polynomial as P

from optimizer.chained_form import chained_form
from optimizer.errors import SingularSystemError
from optimizer.model import Robot
from optimizer.inverse_levels import InverseLevels, compile_sx
from optimizer.poly_roots import real_roots_rows
from optimizer.region import Region
from optimizer.steering import ChainedPath, InputSchedule, solve_polynomial

D = np.deg2rad


def _random_points(robot: Robot, N: int, rng: np.random.Generator, spread: float = 0.3):
    """Chained points around the region: joint-space points inside, mapped, then perturbed so
    that some leave it."""
    n = robot.n
    cf = chained_form(robot)
    q = np.column_stack([np.zeros(N), rng.uniform(0.02, 1.55, (N, n))])
    z = cf.to_chained(q)
    z[:, 1:] *= 1.0 + spread * rng.normal(size=(N, n)) * (rng.uniform(size=(N, 1)) < 0.3)
    return z


@pytest.mark.parametrize("n", [3, 4, 5, 6])
def test_values_inside_equal_the_joint_space_margin(n):
    robot = Robot.default(n)
    cf = chained_form(robot)
    rng = np.random.default_rng(n)
    z = _random_points(robot, 3000, rng)
    # the inverse map loses digits level after level (see chained_form): compare accordingly
    tol = 1e-9 if n <= 4 else 1e-6
    for bounds in (None, [(D(5), D(80))] + [None] * (n - 2) + [(D(-10), D(100))]):
        region = Region(robot, "full", bounds)
        h = region.signed_margin_z(z)
        inv = cf.from_chained(z)
        v = inv.valid
        assert v.sum() > 500 and (~v).sum() > 100
        # inside: the distance of the joints from their bounds (the inverse map is the same;
        # compared where it is well conditioned, all joints at least 5 deg from 0 and 90 deg)
        th = inv.q[:, 1:n]
        cmp = v & np.all((th > D(5)) & (th < D(85)), axis=1)
        assert cmp.sum() > 300
        np.testing.assert_allclose(h[cmp], region.margin_q(inv.q[cmp]), atol=tol)
        # outside: negative, never NaN
        assert np.all(np.isfinite(h)) and np.all(h[~v] <= 0.0)


def test_values_n3_short_path_equals_general_path():
    robot = Robot()
    region = Region(robot)
    z = _random_points(robot, 5000, np.random.default_rng(3), spread=0.5)
    Zr = [z[:, 1], z[:, 2], z[:, 3]]
    np.testing.assert_allclose(region.values(Zr), region.values(Zr, _general=True), atol=1e-13)


@pytest.mark.parametrize("n, criterion, bounds", [
    (3, "full", None), (3, "z2", None), (3, "full", [(D(5), D(80)), None, None]),
    (4, "full", None), (5, "full", None), (6, "full", [None] * 5 + [(D(0), D(90))]),
])
def test_grid_margins_equal_the_sampled_minimum(n, criterion, bounds):
    """The per-member reduction in w = cos(th)^m space gives the smallest sampled margin, for
    members of the paper's family inside and outside the region."""
    robot = Robot.default(n)
    region = Region(robot, criterion, bounds)
    cf = chained_form(robot)
    rng = np.random.default_rng(7 + n)
    q0 = np.concatenate([[0.0], D(rng.uniform(30, 60, n))])
    q1 = q0 + np.concatenate([[0.0], D(rng.uniform(1, 6, n))])
    z0, zT = cf.to_chained(q0), cf.to_chained(q1)
    taus = np.linspace(0.0, 1.0, 41)
    Zs = []
    for d in D(np.linspace(-60, 60, 121)):
        try:
            inp = solve_polynomial(d, n, z0, zT)
        except SingularSystemError:
            continue
        Zs.append(ChainedPath.from_inputs(z0, inp).z(taus))
    z = np.stack(Zs, axis=1)                                    # (G, Dm, n+1)
    G, Dm = z.shape[:2]
    Zr = [z[:, :, k] for k in range(1, n + 1)]
    got = region.grid_margins(Zr)
    ref = region.signed_margin_z(z.reshape(-1, n + 1)).reshape(G, Dm).min(axis=0)
    tol = 1e-9 if n <= 4 else 1e-6
    np.testing.assert_allclose(got, ref, atol=tol, rtol=1e-9)
    assert (got <= 0).any()


def _brute(region: Region, path: ChainedPath, N: int = 200001) -> float:
    return float(region.signed_margin_z(path.z(np.linspace(0.0, 1.0, N))).min())


@pytest.mark.parametrize("n, start, goal, dphis", [
    (3, [10, 10, 10], [30, 30, 30], [33.3, 34.0, 34.57, 35.2, 36.0, 20.0]),
    (4, [47.7, 66.9, 44.9, 66.0], [62.6, 72.2, 47.5, 71.9], [25.12, 25.14, 25.16, 24.0]),
    (5, [20, 30, 40, 50, 60], [25, 35, 45, 55, 65], [10.0, 20.0, 30.0]),
])
def test_poly_minimum_matches_dense_sampling(n, start, goal, dphis):
    """Many members in one call: the continuous minimum agrees with a 200001-sample scan
    (which can only be larger), and the sign always agrees."""
    robot = Robot.default(n)
    cf = chained_form(robot)
    z0 = cf.to_chained(np.concatenate([[0.0], D(start)]))
    zT = cf.to_chained(np.concatenate([[0.0], D(goal)]))
    paths = [ChainedPath.from_inputs(z0, solve_polynomial(D(d), n, z0, zT)) for d in dphis]
    L = max(p.polys[0].shape[1] for p in paths)
    coef = np.zeros((len(paths), n + 1, L))
    for i, p in enumerate(paths):
        coef[i, :, :p.polys[0].shape[1]] = p.polys[0]
    for criterion in ("full", "z2"):
        region = Region(robot, criterion)
        res = region.poly_minimum(coef, detail=True)
        for i, p in enumerate(paths):
            b = _brute(region, p)
            assert (res.margin[i] > 0) == (b > 0)
            chk = region.check_path(p)
            assert chk.ok == (res.margin[i] > 0)
            if b > -0.05:
                # near and inside the region the minimum is exact (far outside, near the poles
                # of the inverse map, only its sign is)
                assert res.margin[i] <= b + 1e-12
                assert res.margin[i] == pytest.approx(b, abs=1e-8)
                assert chk.margin == pytest.approx(res.margin[i], abs=1e-10)


def test_linearised_margin_keeps_the_sign():
    robot = Robot()
    region = Region(robot)
    cf = chained_form(robot)
    z0 = cf.to_chained(D([0, 10, 10, 10]))
    zT = cf.to_chained(D([0, 30, 30, 30]))
    ds = D(np.linspace(33.0, 35.5, 51))
    coef = np.stack([ChainedPath.from_inputs(z0, solve_polynomial(d, 3, z0, zT)).polys[0]
                     for d in ds])
    res = region.poly_minimum(coef, detail=True)
    E = region.linearised(res.margin, res.joint, res.side, res.outside)
    assert np.all(np.sign(E) == np.sign(res.margin))


def test_piecewise_paths_checked_piece_by_piece():
    """Inputs with phi reversing (two pieces) under joint bounds: check_path agrees with a dense
    scan, and a crossing between samples is located where the scan finds it."""
    rng = np.random.default_rng(11)
    for n in (3, 4, 5):
        robot = Robot.default(n)
        cf = chained_form(robot)
        region = Region(robot, "full", [(D(2), D(88))] + [None] * (n - 1))
        for _ in range(6):
            q0 = np.concatenate([[0.0], D(rng.uniform(20, 70, n))])
            inp = InputSchedule(np.array([0.0, 0.4, 1.0]),
                                (rng.normal(size=1), rng.normal(size=2) * 0.5),
                                (rng.normal(size=3) * 0.3, rng.normal(size=2) * 0.3), 1.0)
            path = ChainedPath.from_inputs(cf.to_chained(q0), inp)
            chk = region.check_path(path, grid=9)
            tau = np.linspace(0.0, 1.0, 200001)
            h = region.signed_margin_z(path.z(tau))
            assert chk.ok == bool(h.min() > 0)
            if chk.ok:
                assert chk.margin == pytest.approx(h.min(), abs=1e-8)
            else:
                first = tau[np.nonzero(h <= 0)[0][0]]
                assert chk.first_crossing_tau == pytest.approx(first, abs=1e-5)


@pytest.mark.parametrize("n", [3, 4, 5, 6, 8])
def test_level_maps_match_casadi(n):
    """a_k, b_k of the inverse map: closed forms (levels n-1, n-2) and the CasADi expressions
    translated to numpy (lower levels), also for other exponents."""
    for robot in (Robot.default(n),
                  Robot(gains=tuple(np.linspace(0.5, 1.3, n - 1)),
                        exponents=tuple([1, 2, 3, 4, 2, 3, 1][:n - 1]))):
        cf = chained_form(robot)
        lv = InverseLevels(robot)
        rng = np.random.default_rng(n)
        th = rng.uniform(0.05, 1.5, (n + 1, 40))
        th[0] = 0.0
        cs = {j: np.cos(th[j]) for j in range(1, n)}
        thd = {j: th[j] for j in range(1, n + 1)}
        for k in range(n - 1, 1, -1):
            a, b = lv.ab(k, thd, cs)
            ref = np.asarray(cf.symbolic.ab[k](th, cf.gains))
            np.testing.assert_allclose(np.broadcast_to(a, (40,)), ref[0], rtol=1e-12, atol=1e-13)
            np.testing.assert_allclose(np.broadcast_to(b, (40,)), ref[1], rtol=1e-12, atol=1e-13)


def test_compiled_sx_matches_casadi():
    import casadi as ca
    x = ca.SX.sym("x", 3)
    f = ca.Function("f", [x], [ca.vertcat(ca.sin(x[0]) * x[1] ** 2 - ca.sqrt(x[2]) / x[0],
                                           ca.acos(x[2] / 2) + 3.0, 2 * x[1] - ca.fabs(x[0]))])
    g = compile_sx(f)
    assert g is not None
    rng = np.random.default_rng(0)
    X = rng.uniform(0.1, 1.9, (3, 100))
    out = g([X[0], X[1], X[2]])
    np.testing.assert_allclose(np.vstack(out), np.asarray(f(X)), rtol=1e-14)
    # a second input: numbers (the gains)
    k = ca.SX.sym("k", 2)
    h = ca.Function("h", [x, k], [ca.vertcat(k[0] * ca.cos(x[0]) + x[1], x[2] / k[1])])
    gh = compile_sx(h)
    assert gh is not None
    np.testing.assert_allclose(np.vstack(gh([X[0], X[1], X[2]], (0.7, 1.3))),
                               np.asarray(h(X, ca.DM([0.7, 1.3]))), rtol=1e-14)


def test_real_roots_match_numpy():
    rng = np.random.default_rng(1)
    Pm = rng.normal(size=(600, 6))
    Pm[:100, 4:] = 0.0
    Pm[100:200, 3:] = 0.0
    Pm[200:250, 2:] = 0.0
    Pm[250] = 0.0
    for i in range(300, 350):       # double roots in [0, 1]
        r = rng.uniform(0, 1)
        Pm[i] = 0.0
        Pm[i, :3] = P.polyfromroots([r, r])
    got = real_roots_rows(Pm)
    for i, c in enumerate(Pm):
        c = np.trim_zeros(c, "b")
        ref = P.polyroots(c) if c.size > 1 else np.zeros(0)
        ref = ref[(np.abs(ref.imag) < 1e-6) & (np.abs(ref.real) < 1.4)].real
        g = got[i][np.isfinite(got[i])]
        for x in ref:
            assert np.min(np.abs(g - x)) < 1e-6
