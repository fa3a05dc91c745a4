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
