"""Fast paths of the verification's inputs and of the worker's answer, against independent values.

* :meth:`optimizer.verify.PlannedInputs.u` (one gather per Horner step over all pieces) against
  ``numpy.polynomial.polynomial.polyval`` piece by piece, through the reference maps
  ``from_chained`` and ``u_from_v``: the same values, bit for bit where the maps are the same.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.polynomial import polynomial as P

from optimizer.chained_form import chained_form
from optimizer.model import Robot
from optimizer.steering import ChainedPath, InputSchedule
from optimizer.verify import PlannedInputs

D = np.deg2rad


def _schedule(n: int) -> tuple[Robot, np.ndarray, InputSchedule]:
    """Pieces of different degrees (v1 of sizes 2, 1, 3; v2 of 2, 2, 1), phi reversing."""
    robot = Robot.default(n)
    q0 = np.concatenate([[0.1], D([35.0, 40.0, 30.0, 35.0, 40.0][:n])])
    sched = InputSchedule(np.array([0.0, 0.3, 0.55, 1.0]),
                          (np.array([0.5, 0.4]), np.array([-0.3]), np.array([0.45, 0.0, -0.2])),
                          (np.array([0.1, -0.3]), np.array([-0.05, 0.2]), np.array([0.15])),
                          2.0)
    return robot, q0, sched


def _reference_u(cf, path: ChainedPath, t: np.ndarray) -> np.ndarray:
    """Piece by piece with numpy's polyval (right-continuous pieces, the last one closed)."""
    inp = path.inputs
    T = inp.duration
    tau = t / T
    s = np.clip(np.searchsorted(inp.breaks, tau, side="right") - 1, 0, inp.pieces - 1)
    out = np.empty((t.size, 2))
    for k in range(t.size):
        x = tau[k] - inp.breaks[s[k]]
        z = np.array([P.polyval(x, c) for c in path.polys[s[k]]])
        v = np.array([P.polyval(x, inp.v1[s[k]]), P.polyval(x, inp.v2[s[k]])]) / T
        with np.errstate(all="ignore"):
            out[k] = cf.u_from_v(cf.from_chained(z[None]).q, v[None])[0]
    return out


@pytest.mark.parametrize("n", [3, 4, 5])
def test_planned_inputs_u_matches_piecewise_polyval(n):
    robot, q0, sched = _schedule(n)
    cf = chained_form(robot)
    path = ChainedPath.from_inputs(cf.to_chained(q0), sched)
    inputs = PlannedInputs(cf, path)
    t = np.concatenate([np.linspace(0.0, 2.0, 301), inputs.breaks,
                        np.nextafter(inputs.breaks, -np.inf)[1:]])
    ref = _reference_u(cf, path, t)
    got = inputs.u(t)
    assert got.shape == (t.size, 2)
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
    np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-13)
    # u1 = v1 / T takes no map: the polynomial values themselves, bit for bit
    np.testing.assert_array_equal(got[:, 0], ref[:, 0])
    # and the scalar inputs of the DOP853 fallback agree (where the path is in the region; the
    # n = 5 schedule leaves it, where both give non-finite values)
    ok = np.isfinite(ref).all(axis=1)
    assert ok.any()
    sca = np.array([inputs.u_scalar(x) for x in t[ok]])
    np.testing.assert_allclose(got[ok], sca, rtol=1e-13, atol=1e-13)


def test_planned_inputs_u_one_piece():
    robot = Robot.default(3)
    cf = chained_form(robot)
    q0 = np.concatenate([[0.0], D([35.0, 40.0, 30.0])])
    sched = InputSchedule.single([0.4], [0.1, -0.2, 0.05], 1.5)
    path = ChainedPath.from_inputs(cf.to_chained(q0), sched)
    inputs = PlannedInputs(cf, path)
    t = np.linspace(0.0, 1.5, 97)
    ref = _reference_u(cf, path, t)
    np.testing.assert_allclose(inputs.u(t), ref, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(inputs.u(t)[:, 0], ref[:, 0])
