"""The vectorised evaluation paths of the retimed plan against independent computations.

* ``ChainedPath.z`` / ``InputSchedule.V`` (all pieces at once) against numpy's ``polyval``
  piece by piece (the former loop), bit for bit;
* ``compute_indicators`` without inputs: the same indicators, energy NaN.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.polynomial import polynomial as P

from optimizer.indicators import compute_indicators
from optimizer.steering import ChainedPath, InputSchedule


def _piecewise_reference(path: ChainedPath, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    inp = path.inputs
    idx = np.clip(np.searchsorted(inp.breaks, tau, side="right") - 1, 0, inp.pieces - 1)
    z = np.empty((tau.size, path.z0.size))
    V = np.empty((tau.size, 2))
    for i, (x0, s) in enumerate(zip(tau, idx)):
        x = x0 - inp.breaks[s]
        z[i] = [P.polyval(x, c) for c in path.polys[s]]
        V[i] = P.polyval(x, inp.v1[s]), P.polyval(x, inp.v2[s])
    return z, V


def test_piecewise_evaluation_matches_polyval() -> None:
    rng = np.random.default_rng(7)
    for pieces in (1, 2, 7):
        br = np.concatenate([[0.0], np.sort(rng.uniform(0, 1, pieces - 1)), [1.0]])
        # pieces of different degrees (zero padding must not change the values)
        v1 = tuple(rng.normal(size=rng.integers(1, 3)) for _ in range(pieces))
        v2 = tuple(rng.normal(size=rng.integers(1, 5)) for _ in range(pieces))
        inp = InputSchedule(br, v1, v2, 2.5)
        path = ChainedPath.from_inputs(rng.normal(size=4), inp)
        tau = np.concatenate([np.linspace(0.0, 1.0, 301), br, rng.uniform(0, 1, 40)])
        z_ref, V_ref = _piecewise_reference(path, tau)
        assert np.array_equal(path.z(tau), z_ref)
        assert np.array_equal(path.z_components(tau, 1, 3), z_ref[:, 1:3])
        assert np.array_equal(inp.V(tau), V_ref)
        np.testing.assert_allclose(inp.v(2.5 * tau), V_ref / 2.5, rtol=1e-14, atol=1e-15)


def test_indicators_without_inputs() -> None:
    rng = np.random.default_rng(2)
    t = np.linspace(0.0, 2.0, 101)
    q = np.cumsum(rng.normal(size=(101, 4)), axis=0) * 0.01
    u = rng.normal(size=(101, 2))
    full = compute_indicators(t, q, u)
    none = compute_indicators(t, q, None)
    assert math.isnan(none.energy)
    for f in full.__dataclass_fields__:
        if f != "energy":
            assert getattr(none, f) == getattr(full, f)


def _from_inputs_reference(z0: np.ndarray, inputs: InputSchedule) -> list[np.ndarray]:
    """The chained path's coefficients with numpy.polynomial throughout (the former code)."""
    zs = np.asarray(z0, float).copy()
    out = []
    for s in range(inputs.pieces):
        v1, v2 = inputs.v1[s], inputs.v2[s]
        cs = [P.polyint(v1, k=zs[0]), P.polyint(v2, k=zs[1])]
        for k in range(2, zs.size):
            cs.append(P.polyint(P.polymul(cs[k - 1], v1), k=zs[k]))
        arr = np.zeros((zs.size, max(c.size for c in cs)))
        for k, c in enumerate(cs):
            arr[k, :c.size] = c
        out.append(arr)
        h = inputs.breaks[s + 1] - inputs.breaks[s]
        zs = np.array([P.polyval(h, c) for c in arr])
    return out


def test_from_inputs_matches_numpy_polynomial() -> None:
    rng = np.random.default_rng(11)
    cases = [InputSchedule.single([0.6], rng.normal(size=3), 1.0),
             InputSchedule.single([-0.4], [0.2, -0.1, 0.0], 1.0),          # trailing zero
             InputSchedule.single([0.3], [0.0], 1.0),                     # V2 = 0
             InputSchedule(np.array([0.0, 0.4, 1.0]), (np.array([0.5]), np.array([0.2, 0.1])),
                           (rng.normal(size=4), rng.normal(size=2)), 2.0)]
    for inp in cases:
        for nz in (4, 6):
            z0 = rng.normal(size=nz)
            got = ChainedPath.from_inputs(z0, inp).polys
            ref = _from_inputs_reference(z0, inp)
            assert len(got) == len(ref)
            for g, r in zip(got, ref):
                assert g.shape == r.shape
                assert np.array_equal(g, r)


def test_from_chained_closed_form_all_valid() -> None:
    """n = 3: a batch of valid points (whole-column path) against the same points inverted
    together with an invalid one (the general, per-level indexed path) and the forward map."""
    from optimizer.chained_form import chained_form
    from optimizer.model import Robot

    cf = chained_form(Robot())
    rng = np.random.default_rng(5)
    q = np.column_stack([rng.uniform(-1, 1, 300), rng.uniform(0.01, 1.56, (300, 3))])
    z = cf.to_chained(q)
    fast = cf.from_chained(z)
    bad = np.vstack([z, [[0.0, 0.5, 0.3, 0.1]]])             # z2 > 0: outside the region
    slow = cf.from_chained(bad)
    assert fast.valid.all() and not slow.valid[-1] and slow.valid[:-1].all()
    assert np.array_equal(fast.q, slow.q[:-1])
    assert np.array_equal(fast.w, slow.w[:-1])
    assert np.array_equal(fast.failed_level, slow.failed_level[:-1])
    np.testing.assert_allclose(fast.q, q, atol=1e-9)


def test_piece_index_and_indicator_d_a() -> None:
    rng = np.random.default_rng(9)
    for pieces in (1, 3, 8):
        br = np.concatenate([[0.0], np.sort(rng.uniform(0, 1, pieces - 1)), [1.0]])
        inp = InputSchedule(br, tuple(np.ones(1) for _ in range(pieces)),
                            tuple(np.ones(1) for _ in range(pieces)), 1.0)
        tau = np.concatenate([br, rng.uniform(-0.5, 1.5, 200), [np.nan]])
        ref = np.clip(np.searchsorted(br, tau, side="right") - 1, 0, pieces - 1)
        assert np.array_equal(inp.piece_index(tau), ref)
    from optimizer.indicators import approximation_distance
    t = np.linspace(0.0, 3.0, 1001)
    q = np.cumsum(rng.normal(size=(1001, 4)), axis=0) * 0.01
    ind = compute_indicators(t, q, None)
    per = approximation_distance(t / 3.0, q[:, 1:])
    assert ind.d_a == per[0] and ind.d_a_per_joint == tuple(float(x) for x in per)


def test_th1_from_chained_matches_from_chained() -> None:
    """th1 and validity of the planner's scans against the full inverse map, with points
    outside the region, non-finite ones, and n = 4 (CasADi backend)."""
    from optimizer.chained_form import chained_form
    from optimizer.model import Robot

    rng = np.random.default_rng(21)
    for n in (3, 4):
        cf = chained_form(Robot.default(n))
        q = np.column_stack([rng.uniform(-1, 1, 500), rng.uniform(-0.3, 1.8, (500, n))])
        z = cf.to_chained(q)
        z[::7, 1] *= -1.0
        z[::11, 2] = 0.95
        z[5, 0] = np.nan
        z[9, n] = np.inf
        inv = cf.from_chained(z)
        th1, ok = cf.th1_from_chained(z)
        assert 0 < ok.sum() < ok.size
        assert np.array_equal(ok, inv.valid)
        assert np.array_equal(th1, inv.q[:, 1])
        if n == 3:
            fin = np.isfinite(z).all(axis=1)
            th, ok23 = cf.th1_from_z23(z[:, 1], z[:, 2])
            assert np.array_equal(ok23[fin], inv.valid[fin])
            assert np.array_equal(th[inv.valid], inv.q[inv.valid, 1])
