"""The NLP layer's buffered CasADi calls against CasADi's ordinary calls of the same Functions."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from optimizer.model import Robot
from optimizer.planner import nlp as nlp_layer
from optimizer.planner.solvers import BufferedCall, run_solver


def test_buffered_call_matches_the_ordinary_call_on_matrices() -> None:
    """(r, c) inputs are read column-major from the C-contiguous (c, r) array and results are
    the column-major values, as CasADi's DM holds them."""
    A = ca.SX.sym("A", 2, 3)
    v = ca.SX.sym("v", 3)
    f = ca.Function("f", [A, v], [ca.mtimes(A, v), A.T @ A])
    rng = np.random.default_rng(3)
    a, x = rng.normal(size=(2, 3)), rng.normal(size=3)
    ref = [np.asarray(r, float) for r in f(a, x)]
    out = BufferedCall(f, 2, outputs=(0, 1))(np.ascontiguousarray(a.T), x)
    np.testing.assert_array_equal(out[0], ref[0].ravel())
    np.testing.assert_array_equal(out[1].reshape(3, 3).T, ref[1])
    # fresh results on every call: an earlier result is not overwritten
    again = BufferedCall(f, 2)
    first = again(np.ascontiguousarray(a.T), x)[0]
    again(np.zeros((3, 2)), x)
    np.testing.assert_array_equal(first, ref[0].ravel())


def test_buffered_call_refuses_wrong_sizes_and_raises_evaluation_errors() -> None:
    x = ca.MX.sym("x")

    class Failing(ca.Callback):
        def __init__(self) -> None:
            ca.Callback.__init__(self)
            self.construct("failing", {})

        def get_n_in(self) -> int:
            return 1

        def get_n_out(self) -> int:
            return 1

        def eval(self, arg):  # type: ignore[override]
            raise RuntimeError("evaluation failed")

    cb = Failing()
    f = ca.Function("f", [x], [cb(x)])
    call = BufferedCall(f, 1)
    with pytest.raises(ValueError, match="argument 0"):
        call(np.zeros(2))
    with pytest.raises(ValueError, match="takes 1 arguments"):
        call(np.zeros(1), np.zeros(1))
    with pytest.raises(RuntimeError):
        call(np.ones(1))


def test_the_nlp_solver_and_correction_maps_agree_with_ordinary_calls() -> None:
    """fatrop through its buffer returns what the ordinary call returns (same iterates), and
    the fine end map and the RK4 end Jacobian are the Functions' own values."""
    robot = Robot.default(3)
    nlp = nlp_layer.multiple_shooting_nlp(tuple(float(k) for k in robot.gains),
                                          tuple(int(m) for m in robot.exponents), False, 20, 1)
    a, b = np.radians([10.0, 20.0, 30.0]), np.radians([40.0, 25.0, 15.0])
    x0 = nlp.guess(a, b, 0.0, 0.6)
    lb, ub = nlp.bounds()
    lbx, ubx = nlp.flat(lb), nlp.flat(ub)
    p = np.concatenate([[0.0], a, b, [30.0, 1.0, 0.3, 0.0], robot.gains])
    name = nlp.solvers[0][0]
    solver = dict(nlp.solvers)[name]
    ref = np.asarray(solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=nlp.lbg, ubg=nlp.ubg)["x"],
                     float).ravel()
    out = run_solver(nlp, name, x0, p, lbx, ubx, 10.0)
    assert out.success and out.x is not None
    np.testing.assert_array_equal(out.x, ref)
    assert out.iterations == solver.stats()["iter_count"]
    nodes, rates = nlp.unpack(out.x)
    q0 = np.concatenate([[0.0], a])
    K = robot.gains
    np.testing.assert_array_equal(nlp.fine_end(q0, rates, K),
                                  np.asarray(nlp.fine_path(q0, rates.T, K), float)[:, -1])
    np.testing.assert_array_equal(nlp.rk4_end_jacobian(q0, rates, K),
                                  np.asarray(nlp.end_jacobian(q0, rates.ravel(), K), float))


def test_a_robot_of_other_gains_uses_the_same_nlp_and_reaches_its_goal() -> None:
    """The gains are the NLP's last parameters: a 4-joint robot whose gains are 6 %, -4 % and
    3 % off the default's is planned with the default robot's NLPs (none is built), and its
    handed-out rates, run by scipy on ITS model piece by piece between the samples, end
    within 1e-6 rad of the goal; on the default model they would miss by far more."""
    from scipy.integrate import solve_ivp

    from optimizer.planner.plan import plan
    from optimizer.problem import PlanRequest
    from reference import model_rhs

    start, goal = (0.3, 0.4, 0.5, 0.6), (0.6, 0.7, 0.75, 0.9)
    base = Robot.default(4)
    plan(PlanRequest(start=start, goal=goal, robot=base))
    built = nlp_layer._shaped_nlp.cache_info().currsize
    K = tuple(k * f for k, f in zip(base.gains, (1.06, 0.96, 1.03)))
    answer = plan(PlanRequest(start=start, goal=goal, robot=Robot(K, base.exponents)))
    assert nlp_layer._shaped_nlp.cache_info().currsize == built
    t, u = np.asarray(answer.path.t), np.asarray(answer.path.u)

    def run(gains: tuple[float, ...]) -> np.ndarray:
        q = np.asarray(answer.path.q[0], float)
        for k in range(len(t) - 1):
            def rhs(s, x, k=k):
                w = (s - t[k]) / (t[k + 1] - t[k])
                return model_rhs(x, (1 - w) * u[k] + w * u[k + 1], gains, base.exponents)
            q = solve_ivp(rhs, (t[k], t[k + 1]), q, method="DOP853", rtol=1e-12,
                          atol=1e-13).y[:, -1]
        return q

    assert np.max(np.abs(run(K)[1:] - np.asarray(goal))) < 1e-6
    assert np.max(np.abs(run(base.gains)[1:] - np.asarray(goal))) > 1e-3



def _resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _example_problem(start: tuple[float, ...], goal: tuple[float, ...]) -> tuple:
    """The first rung's NLP of a 3-joint request and one solve's arguments on it."""
    from optimizer.planner.rules import joint_limits
    from optimizer.problem import PlanRequest

    req = PlanRequest(start=start, goal=goal)
    tr = nlp_layer.ladder(3)[0]
    nlp = nlp_layer.nlp_for(req, tr)
    lo, hi = nlp_layer.node_bounds(req, joint_limits(req))
    lbx, ubx, _ = nlp_layer.variable_bounds(req, nlp, tr, lo, hi)
    p = nlp_layer.parameters(req, *nlp_layer.objective_weights(req, "shooting"))
    x0 = nlp.guess(np.array(req.start), np.array(req.goal), 0.0, 0.6)
    return nlp, (x0, p, lbx, ubx, nlp.lbg, nlp.ubg)


def measure_spent_memories() -> dict[str, float]:
    """In a fresh process (a used heap has room for new memories without growing): the
    estimate of one fatrop memory, the resident growth per new memory, the budget, and the
    growth over enough solves to pass the budget twice. Each solve has a pattern of bounds of
    its own (far bounds on another subset of the unbounded variables), so that each takes a
    new memory."""
    from optimizer.planner import solvers

    nlp, (x0, p, lbx, ubx, lbg, ubg) = _example_problem((0.17, 0.17, 0.17), (0.52, 0.52, 0.52))
    free = np.flatnonzero(~np.isfinite(ubx))
    solves = iter(range(1, 2 ** len(free)))

    def solve() -> None:
        ub = ubx.copy()
        i = next(solves)   # far bounds where i has a bit: never active, another pattern
        ub[[f for b, f in enumerate(free) if i >> b & 1]] = 1e3
        call = nlp.solver_call("fatrop", lbx, ub)
        call(x0, p, lbx, ub, lbg, ubg)
        assert call.stats()["success"]

    estimate = solvers.memory_bytes(dict(nlp.solvers)["fatrop"])
    budget = nlp_layer.SPENT_MEMORY_BYTES
    solve()
    before = _resident_bytes()
    count = min(30, int(budget / estimate) - 2)     # no rebuild yet
    for _ in range(count):
        solve()
    per_memory = (_resident_bytes() - before) / count
    before = _resident_bytes()
    for _ in range(int(2.5 * budget / estimate) + 10):
        solve()
    return {"estimate": estimate, "per_memory": per_memory, "budget": budget,
            "growth": _resident_bytes() - before}


def test_fatrop_memories_are_reused_per_pattern_of_bounds_and_answer_as_fresh_ones() -> None:
    """A solve on a reused memory is the solve on a memory no solve has used, bit for bit and
    in iterations, after a solve of the same pattern of bounds and after one of another (the
    hard request's th3 is unbounded: fatrop's objects are built anew for it, and a memory
    that held them answered the README's example differently)."""
    nlp, example = _example_problem((0.1745, 0.1745, 0.1745), (0.5236, 0.5236, 0.5236))
    nlp_hard, hard = _example_problem((0.2, 0.2, -6.0), (0.21, 0.21, 6.0))
    nlp_near, near = _example_problem((0.2, 0.25, 0.3), (0.5, 0.45, 0.4))
    assert nlp_hard is nlp and nlp_near is nlp
    assert _pattern(example) != _pattern(hard) and _pattern(example) == _pattern(near)

    def fresh(args: tuple) -> tuple[np.ndarray, int]:
        call = BufferedCall(nlp.solver("fatrop"), 6)
        return call(*args)[0], call.stats()["iter_count"]

    def reused(args: tuple) -> tuple[np.ndarray, int]:
        call = nlp.solver_call("fatrop", args[2], args[3])
        return call(*args)[0], call.stats()["iter_count"]

    ref, ref_iterations = fresh(example)
    for before in (hard, near, hard):
        reused(before)
        x, iterations = reused(example)
        np.testing.assert_array_equal(x, ref)
        assert iterations == ref_iterations
    # one memory per pattern, reused
    assert nlp.solver_call("fatrop", example[2], example[3]) is \
        nlp.solver_call("fatrop", near[2], near[3])
    assert nlp.solver_call("fatrop", example[2], example[3]) is not \
        nlp.solver_call("fatrop", hard[2], hard[3])


def _pattern(args: tuple) -> bytes:
    from optimizer.planner.solvers import bound_pattern

    return bound_pattern(args[2], args[3], args[4], args[5])


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"),
                    reason="resident memory is read from Linux's /proc")
def test_spent_solver_memories_are_estimated_from_above_and_stay_within_the_budget() -> None:
    """Every new pattern of bounds takes a new memory (purity), and fatrop builds about 1 MB
    of objects in it: :func:`memory_bytes` must not underestimate that (it once counted the
    work vectors alone, 51 KB, and a worker grew by about 1 GB per solver before one was built
    anew), and the spent memories must stay within :data:`SPENT_MEMORY_BYTES`."""
    root = Path(__file__).resolve().parents[1]
    code = ("import json, test_nlp_buffered as t\n"
            "print(json.dumps(t.measure_spent_memories()))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=root,
                         env={"PYTHONPATH": f"{root}:{root / 'tests'}", "PATH": "/usr/bin:/bin",
                              "OPENBLAS_NUM_THREADS": "1"},
                         capture_output=True, text=True, timeout=600, check=True)
    m = json.loads(out.stdout.strip().splitlines()[-1])
    assert 0.2 * m["estimate"] < m["per_memory"] <= m["estimate"]
    assert m["growth"] <= 1.2 * m["budget"]


def test_a_prepared_solver_is_the_one_the_first_solve_runs_on() -> None:
    """The service's warm-up and the budget's ``prepare`` build the solvers ahead of the first
    request: ``prepare_solver`` must build the one :meth:`solver_call` runs on (its own, not
    :meth:`solver`'s), so that the first solve builds nothing."""
    nlp, (x0, p, lbx, ubx, lbg, ubg) = _example_problem((0.17, 0.17, 0.17), (0.52, 0.52, 0.52))
    nlp._replace("fatrop", nlp._factories["fatrop"]())   # as built: nothing prepared
    nlp.prepare_solver("fatrop")
    factories = dict(nlp._factories)

    def no_build() -> None:
        raise AssertionError("a solver was built at the first solve")

    nlp._factories["fatrop"] = no_build
    try:
        call = nlp.solver_call("fatrop", lbx, ubx)
        call(x0, p, lbx, ubx, lbg, ubg)
        assert call.stats()["success"]
    finally:
        nlp._factories.update(factories)
