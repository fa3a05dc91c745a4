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


# ---------------------------------------------------------------------- json_safe
def _json_safe_reference(obj):
    """The rule of :func:`optimizer.results.json_safe`, written plainly (its former body)."""
    import math
    if isinstance(obj, dict):
        return {str(k): _json_safe_reference(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe_reference(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _json_safe_reference(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    return obj


def _same(a, b) -> None:
    """Equal values of identical types, recursively (1 == 1.0 == True is not enough)."""
    assert type(a) is type(b), (a, b)
    if isinstance(a, dict):
        assert list(a) == list(b)
        for k in a:
            assert type(k) is str
            _same(a[k], b[k])
    elif isinstance(a, list):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _same(x, y)
    else:
        assert a == b or (a != a and b != b), (a, b)


class _Sub(float):
    pass


def test_json_safe_matches_reference_rule():
    from optimizer.results import json_safe
    inf, nan = float("inf"), float("nan")
    cases = [
        1.5, -0.0, inf, -inf, nan, 7, True, False, None, "text", _Sub(2.5), _Sub(inf),
        np.float64(3.25), np.float64(nan), np.float32(1.5), np.int64(4), np.bool_(True),
        [0.1, 0.2, 0.3], [0.1, inf], [0.1, nan, 0.3], [1e308, 1e308], [1e308, 1e308, inf],
        [0.1, 2], [0.1, np.float64(0.2)], [0.1, True], [_Sub(0.5)], [], (0.1, 0.2), (1, inf),
        {1: 0.5, "a": [0.1, -inf], ("t", 2): {"b": np.array([1.0, nan])}},
        {"x": np.array([[0.1, 0.2], [0.3, 0.4]]), "i": np.array([1, 2]), "b": np.array([True])},
        {"nested": [[0.1, 0.2], [inf, 0.4], (np.float64(1.0), None)]},
    ]
    for obj in cases:
        _same(json_safe(obj), _json_safe_reference(obj))
    # a new list every time (a caller may change the answer without changing the plan)
    floats = [0.1, 0.2]
    out = json_safe({"a": floats})
    assert out["a"] == floats and out["a"] is not floats
    rng = np.random.default_rng(5)
    for _ in range(200):
        vals = rng.choice([0.5, -2.0, inf, -inf, nan, 1e308], size=rng.integers(0, 6)).tolist()
        _same(json_safe(vals), _json_safe_reference(vals))
        _same(json_safe({"v": vals, "t": tuple(vals)}), _json_safe_reference({"v": vals,
                                                                              "t": tuple(vals)}))


# ---------------------------------------------------------------------- verify_plan's mesh
@pytest.mark.parametrize("start_deg", [[10.0, 10.0, 10.0], [8.3, 11.6, 9.1], [11.9, 8.2, 10.7]])
def test_verify_plan_initial_width_matches_reference(start_deg):
    """Retimed plans (8 input pieces) verified on panels at most T/6 wide: the estimate meets
    the target, and the states, samples and energy agree with scipy's DOP853 (rtol 1e-12, on
    the test's own model) and with the former mesh (3 panels per piece)."""
    import itertools

    from scipy.integrate import solve_ivp

    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest
    from optimizer.verify import (CASCADE_INITIAL_WIDTH, CASCADE_NAME, integrate_cascade,
                                  verify_plan)
    from reference import model_rhs

    req = PlanRequest(start=tuple(D(start_deg)), goal=tuple(D([30.0, 30.0, 30.0])),
                      method="retimed")
    p = plan(req)
    inputs = PlannedInputs(chained_form(p.robot), p.chained)
    assert inputs.breaks.size > 2
    K, m = p.robot.gains, p.robot.exponents
    # the answer runs the plan along its time law: the plan's own time of every sample
    ts = np.asarray(p.time_law.plan_time(p.path.t), float)
    T_plan = float(inputs.breaks[-1])

    def rhs(t, x):
        u = inputs.u_scalar(t)
        return np.concatenate([model_rhs(x[:-1], u, K, m), [u[0] ** 2 + u[1] ** 2]])

    x = np.concatenate([req.q_start(), [0.0]])
    samples = np.full((ts.size, x.size), np.nan)
    for a, b in itertools.pairwise(inputs.breaks):
        sol = solve_ivp(rhs, (a, b), x, method="DOP853", rtol=1e-12, atol=1e-14,
                        dense_output=True)
        sel = (ts >= a) & (ts <= b)
        samples[sel] = sol.sol(ts[sel]).T
        x = sol.y[:, -1]
    ver = verify_plan(p.robot, inputs, req.q_start(), np.array(req.goal),
                      req.phi_start + p.phi_change, ts, p.path.q)
    assert ver.integrator == CASCADE_NAME and ver.error_estimate <= 1e-11
    np.testing.assert_allclose(ver.final, x[:-1], rtol=0, atol=1e-10)
    assert ver.energy == pytest.approx(x[-1], rel=1e-9)
    assert ver.max_deviation == pytest.approx(np.max(np.abs(samples[:, :-1] - p.path.q)),
                                              abs=1e-9)
    # the mesh: the fewest panels at most T/6 wide per piece, no refinement
    rep = integrate_cascade(p.robot, inputs.u, req.q_start(), T_plan, ts,
                            inputs.breaks, initial_width=CASCADE_INITIAL_WIDTH)
    widths = np.diff(inputs.breaks)
    assert rep.panels == int(np.sum(np.maximum(np.ceil(widths / (T_plan / 6) - 1e-9), 1)))
    old = integrate_cascade(p.robot, inputs.u, req.q_start(), T_plan, ts,
                            inputs.breaks)
    assert old.panels == 3 * widths.size
    np.testing.assert_allclose(rep.final, old.final, rtol=0, atol=1e-13)
    np.testing.assert_allclose(rep.q, old.q, rtol=0, atol=1e-13)
    np.testing.assert_array_equal(rep.final, ver.final)


def test_initial_width_one_piece():
    """One piece of [0, T] under initial_width = 1/6: six equal panels (not seven by rounding)."""
    from optimizer.verify import integrate_cascade
    robot = Robot.default(3)
    for T in (1.0, 0.3, 7.0):
        rep = integrate_cascade(robot, lambda tt: np.column_stack([np.full(tt.size, 0.2),
                                                                   np.full(tt.size, 0.1)]),
                                np.array([0.0, 0.5, 0.5, 0.5]), T, np.linspace(0, T, 5),
                                initial_width=1.0 / 6.0)
        assert rep.panels == 6 and rep.success
