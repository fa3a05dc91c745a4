"""The replanner's compiled end map of constant-rate pieces (optimizer.planner.continuation_map)
against scipy on the tests' own model, its Jacobian against central differences of that
integration, and the correction onto a goal; and two properties of the continuations built
with it: a rate keeps its sign when it can, and little motion is left near the end."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from optimizer.errors import NumericalError
from optimizer.model import Robot
from optimizer import native
from optimizer.planner.continuation_map import (CompiledCall, PieceMap, correct_pieces,
                                                correct_signed, halving_correct, halving_kernel,
                                                kernel_correct, piece_weights, signed_kernel,
                                                signed_step)
from optimizer.planner.piece_proof import integrate_pieces
from optimizer.planner.plan import plan
from optimizer.planner.replan import read_plan, replan, sign_changes
from optimizer.problem import PlanRequest

from reference import PROTOTYPE_K, PROTOTYPE_M, model_rhs

START, GOAL = (0.3, 0.4, 0.5), (0.9, 1.0, 0.8)


def scipy_end(q0: np.ndarray, W: np.ndarray) -> np.ndarray:
    """The tests' model from ``q0`` through unit pieces at the displacement rates ``W``."""
    q = np.asarray(q0, float)
    for w in W:
        sol = solve_ivp(lambda t, x, w=w: model_rhs(x, w, PROTOTYPE_K, PROTOTYPE_M), (0.0, 1.0),
                        q, method="DOP853", rtol=1e-12, atol=1e-13)
        q = sol.y[:, -1]
    return q


@pytest.fixture(scope="module")
def pieces() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    W = rng.uniform(-0.08, 0.08, (7, 2))          # 7 pieces moving a few hundredths of a rad
    return np.array([0.1, *START]), W


def test_end_map_matches_scipy(pieces) -> None:
    q0, W = pieces
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    end, _ = emap(q0, W)
    assert np.max(np.abs(end - scipy_end(q0, W))) < 1e-9


def test_the_maps_take_any_gains_without_a_build(pieces) -> None:
    """The gains are an input of the compiled functions, not constants: a robot with other
    gains (a plant 7 % and -4 % off) gets its end map and proof from the same functions (no
    new CasADi function is built), each matching scipy on that robot's model."""
    from optimizer.planner import continuation_map, piece_proof

    q0, W = pieces
    K = (PROTOTYPE_K[0] * 1.07, PROTOTYPE_K[1] * 0.96)
    PieceMap(tuple(PROTOTYPE_K), tuple(PROTOTYPE_M), 7)
    built = continuation_map._jacobian_map.cache_info().currsize
    end, _ = PieceMap(K, tuple(PROTOTYPE_M), 7)(q0, W)
    assert continuation_map._jacobian_map.cache_info().currsize == built
    q = np.asarray(q0, float)
    for w in W:
        q = solve_ivp(lambda t, x, w=w: model_rhs(x, w, K, PROTOTYPE_M), (0.0, 1.0), q,
                      method="DOP853", rtol=1e-12, atol=1e-13).y[:, -1]
    assert np.max(np.abs(end - q)) < 1e-9
    assert np.max(np.abs(end - scipy_end(q0, W))) > 1e-4     # the gains did change the end
    breaks = np.arange(W.shape[0] + 1, dtype=float)
    proof = piece_proof.integrate_pieces(K, tuple(PROTOTYPE_M), q0, breaks, W, breaks[1:])
    assert proof is not None and np.max(np.abs(proof.final - q)) < 1e-11


def test_jacobian_matches_central_differences(pieces) -> None:
    q0, W = pieces
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    _, J = emap(q0, W)
    h = 1e-5
    for k in (0, 5, 13):                              # columns in the order of W.ravel()
        Wp, Wm = W.copy().ravel(), W.copy().ravel()
        Wp[k] += h
        Wm[k] -= h
        fd = (scipy_end(q0, Wp.reshape(W.shape)) - scipy_end(q0, Wm.reshape(W.shape))) / (2 * h)
        assert np.allclose(J[:, k], fd, rtol=1e-5, atol=1e-8)


def test_correction_reaches_the_goal_on_scipy(pieces) -> None:
    q0, W = pieces
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    goal = scipy_end(q0, W)[1:] + np.array([2e-3, -1e-3, 1.5e-3])
    err, W1, steps = correct_pieces(emap, q0, goal, W)
    assert err < 1e-10 and steps >= 1
    assert np.max(np.abs(scipy_end(q0, W1)[1:] - goal)) < 1e-8


def test_sign_keeping_correction_reaches_the_goal_on_scipy(pieces) -> None:
    """The sign-keeping Gauss-Newton reaches a nearby goal (checked by scipy) and no rate
    changes sign."""
    q0, W = pieces
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    goal = scipy_end(q0, W)[1:] + np.array([-1e-3, 1e-3, 1e-3])
    err, W1, steps = correct_signed(emap, q0, goal, W)
    assert err < 1e-10 and steps >= 1
    assert np.all(W1 * np.sign(W) >= 0.0)
    assert np.max(np.abs(scipy_end(q0, W1)[1:] - goal)) < 1e-8


def test_signed_step_solves_the_system_within_the_signs() -> None:
    """Random systems with room to spare: the step solves ``J dx = r`` and leaves every rate
    on its own side of 0 (a rate the plain step would push across stops at 0)."""
    rng = np.random.default_rng(5)
    crossed = 0
    for _ in range(50):
        W = rng.uniform(0.2, 1.0, 16) * rng.choice([-1.0, 1.0], 16)
        J = rng.normal(size=(3, 16))
        r = 4.0 * rng.normal(size=3)
        D2 = piece_weights(W)
        plain = W - (J * D2).T @ np.linalg.solve((J * D2) @ J.T, r)
        crossed += int(np.any(plain * np.sign(W) < 0.0))
        dx = signed_step(J, r, D2, W, np.sign(W))
        assert np.allclose(J @ dx, r, atol=1e-9)
        assert np.all((W - dx) * np.sign(W) >= -1e-15)
    assert crossed >= 5        # the sign constraint was active in some of them


def test_the_compiled_kernel_keeps_the_signs_and_reaches_the_goal_on_scipy(pieces) -> None:
    """The one-call correction (full sign-keeping steps) reaches a nearby goal on scipy's
    integration of the tests' model, keeps every rate's sign and agrees with the Python loop
    of :func:`correct_signed`; where one rate must stop to keep its sign, it stops at 0."""
    q0, W = pieces
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    goal = scipy_end(q0, W)[1:] + np.array([-1e-3, 1e-3, 1e-3])
    err, W1 = kernel_correct(emap, q0, goal, W)
    assert err < 1e-10
    assert np.all(W1 * np.sign(W) >= 0.0)
    assert np.max(np.abs(scipy_end(q0, W1)[1:] - goal)) < 1e-8
    _, W2, _ = correct_signed(emap, q0, goal, W)
    assert np.allclose(W1, W2, rtol=1e-6, atol=1e-9)
    # any sign: the plain weighted Gauss-Newton, on scipy too
    err, W3 = kernel_correct(emap, q0, goal, W, signed=False)
    assert err < 1e-10 and np.max(np.abs(scipy_end(q0, W3)[1:] - goal)) < 1e-8


def test_the_kernel_with_fewer_free_rates_than_joints(pieces) -> None:
    """Late in a motion few rates are left free (the others at rest, held there): the
    kernel's systems are (nearly) singular. It does not claim the goal (the replanner then
    runs the Python loop) and keeps the resting rates at rest; the loop takes the miss
    lower."""
    q0, _ = pieces
    W = np.zeros((4, 2))
    W[2] = [0.05, 0.02]                               # one piece moves: 2 rates, 3 joints
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 4)
    goal = scipy_end(q0, W)[1:] + np.array([3e-8, -2e-8, 1e-8])
    err, W1 = kernel_correct(emap, q0, goal, W)
    assert not err <= 1e-9
    assert np.all(W1[[0, 1, 3]] == 0.0)
    err_loop, W2, _ = correct_signed(emap, q0, goal, W)
    assert err_loop < min(err, 2e-8) and np.all(W2[[0, 1, 3]] == 0.0)


def test_the_halving_kernel_is_the_python_loop(pieces) -> None:
    """The any-sign correction with halved steps in one call: on scipy's model and equal to
    :func:`correct_pieces`, for a goal far enough that full steps overshoot."""
    q0, W = pieces
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    # (the far goal needs rates whose 4 RK4 steps per piece are 1e-5 rad off the model: the
    # map's own error, which the replanner's verification measures and its defect step
    # removes)
    for offset, on_model in (([2e-3, -1e-3, 1.5e-3], 1e-8), ([0.04, -0.05, 0.06], 1e-4)):
        goal = scipy_end(q0, W)[1:] + np.array(offset)
        err, W1 = halving_correct(emap, q0, goal, W)
        err_loop, W2, _ = correct_pieces(emap, q0, goal, W)
        assert err < 1e-10 and err_loop < 1e-10
        assert np.max(np.abs(scipy_end(q0, W1)[1:] - goal)) < on_model
        assert np.allclose(W1, W2, rtol=1e-6, atol=1e-9)


def test_the_kernel_says_when_it_cannot_keep_the_signs(pieces) -> None:
    """A goal that no rates of the same signs reach (th2 back by 0.05 rad, th1 and th3 where
    they are, every rate forward) is out of the signed kernel's reach: it says so by its
    miss, and no rate crossed 0; with any sign it is reached, some rate reversed."""
    q0, _ = pieces
    W = np.tile([0.05, 0.02], (7, 1))                 # phi and th1 forward on every piece
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    end = scipy_end(q0, W)
    goal = end[1:] - np.array([0.0, 0.05, 0.0])      # th2 back, th1 and th3 where they are
    err, W1 = kernel_correct(emap, q0, goal, W)
    assert not err <= 1e-6
    assert np.all(W1 * np.sign(W) >= 0.0)
    err, W3 = kernel_correct(emap, q0, goal, W, signed=False, floor=None)
    assert err < 1e-9 and np.any(W3 * np.sign(W) < 0.0)
    assert np.max(np.abs(scipy_end(q0, W3)[1:] - goal)) < 1e-7


def test_a_failed_evaluation_answers_nan() -> None:
    """A linear solve of a singular system fails in CasADi's virtual machine; through the
    buffer the failure is silent and the results unwritten: the buffered call answers NaN
    (the kernels then report no finite miss), and the same call on a regular system the
    solution."""
    import casadi as ca

    from optimizer.planner.solvers import BufferedCall

    A, b = ca.MX.sym("A", 2, 2), ca.MX.sym("b", 2)
    call = BufferedCall(ca.Function("solve", [A, b], [ca.solve(A, b)]), 2)
    assert np.all(np.isnan(call(np.zeros((2, 2)), np.ones(2))[0]))
    assert np.allclose(call(np.array([[2.0, 0.0], [0.0, 4.0]]), np.ones(2))[0], [0.5, 0.25])


def _built_here(call, n_args: int, tmp_path, monkeypatch):
    """A kernel (a :class:`BoundCall`) as a CompiledCall of its own, compiled into the test's
    cache (not the cached one: built here), and its compiled call."""
    monkeypatch.setattr(native, "_config", None)      # (restored after the test)
    if native.configure(tmp_path / "native") is None:
        pytest.skip("no C compiler")
    fresh = CompiledCall(call.call.function, n_args, (0, 1))
    compiled = fresh.current(wait=True)
    assert compiled is not fresh.vm
    return fresh, compiled


def test_the_compiled_kernel_is_the_virtual_machines(pieces, tmp_path, monkeypatch) -> None:
    """The kernel generated as C and compiled (optimizer.native) gives the virtual machine's
    answer."""
    q0, W = pieces
    robot = Robot.default(3)
    fresh, compiled = _built_here(signed_kernel(tuple(robot.gains), tuple(robot.exponents), 8),
                                  6, tmp_path, monkeypatch)
    full = np.vstack([np.zeros((1, 2)), W])
    emap = PieceMap(tuple(robot.gains), tuple(robot.exponents), 8)
    goal = scipy_end(q0, W)[1:] + np.array([-1e-3, 1e-3, 1e-3])
    D2 = piece_weights(full, np.vstack([[True, True], np.zeros((7, 2), bool)]))
    args = (q0, full, goal, D2, np.sign(full), np.asarray(robot.gains))
    for a, b in zip(fresh.vm(*args), compiled(*args)):
        assert np.allclose(a, b, rtol=1e-12, atol=1e-14)
    assert emap.P == 8


def test_the_compiled_halving_kernel_is_the_virtual_machines(pieces, tmp_path,
                                                             monkeypatch) -> None:
    """The any-sign kernel, whose steps and halvings are conditionals (a branch evaluated
    only when taken), generated as C and compiled, gives the virtual machine's answer: on a
    goal its full steps reach, and on one where they overshoot and halvings are taken."""
    q0, W = pieces
    robot = Robot.default(3)
    fresh, compiled = _built_here(halving_kernel(tuple(robot.gains), tuple(robot.exponents),
                                                 8), 5, tmp_path, monkeypatch)
    full = np.vstack([np.zeros((1, 2)), W])
    D2 = piece_weights(full, None)
    for offset in ([2e-3, -1e-3, 1.5e-3], [0.04, -0.05, 0.06]):
        goal = scipy_end(q0, W)[1:] + np.array(offset)
        args = (q0, full, goal, D2, np.asarray(robot.gains))
        vm, cc = fresh.vm(*args), compiled(*args)
        assert np.abs(vm[1]).max() < 1e-10            # reached, by either
        for a, b in zip(vm, cc):
            assert np.allclose(a, b, rtol=1e-12, atol=1e-14)


def test_the_compiled_verification_matches_scipy(pieces) -> None:
    """The compiled integration of constant-rate pieces (the replanner's proof): its states
    at the breaks within 1e-11 rad of scipy's DOP853 on the tests' own model, its Richardson
    estimate below the target, its samples within 1e-9; none where the estimate is above."""
    q0, W = pieces
    robot = Robot.default(3)
    breaks = np.concatenate([[0.0], np.cumsum([0.3, 0.1, 0.25, 0.05, 0.2, 0.4, 0.15])])
    rates = W / np.diff(breaks)[:, None]               # the same displacements as W
    s_eval = np.array([0.0, 0.02, 0.31, 0.77, breaks[-1]])
    proof = integrate_pieces(tuple(robot.gains), tuple(robot.exponents), q0, breaks, rates,
                             s_eval)
    assert proof is not None and not proof.singular
    for k in range(1, W.shape[0] + 1):
        assert np.max(np.abs(proof.q[k] - scipy_end(q0, W[:k]))) < 1e-11
    assert proof.error_estimate < 1e-11
    for j, s in enumerate(s_eval):
        k = min(int(np.searchsorted(breaks, s, side="right")) - 1, W.shape[0] - 1)
        frac = (s - breaks[k]) / (breaks[k + 1] - breaks[k])
        ref = scipy_end(q0, np.vstack([W[:k], W[k] * frac]))
        assert np.max(np.abs(proof.q[breaks.size + j] - ref)) < 1e-9
    # rates ten times larger: the coarse run is off, the estimate says so (and the caller
    # then integrates by the cascade quadrature)
    big = integrate_pieces(tuple(robot.gains), tuple(robot.exponents), q0,
                           breaks, 12.0 * rates, s_eval)
    assert big is None


@pytest.fixture(scope="module")
def answer() -> dict:
    return plan(PlanRequest(start=START, goal=GOAL)).to_dict()


def test_small_errors_keep_every_rates_sign(answer: dict) -> None:
    """A small error early on is corrected without changing any rate's sign: no reversal of
    phi or th1 is added to the rest of the plan."""
    ps = read_plan(answer)
    rng = np.random.default_rng(11)
    kept = 0
    for _ in range(5):
        i = int(rng.integers(1, 30))
        t = answer["path"]["t"][i]
        q = np.array(answer["path"]["q"][i]) + [0.0, *rng.uniform(-2e-4, 2e-4, 3)]
        out = replan(answer, t, q)
        rates = np.array([s["u"] for s in out["coefficients"]["segments"]])
        if out["diagnostics"]["replan"]["signs_kept"]:
            kept += 1
            sig = float(ps.law.evaluate(np.array([t]))[0][0])
            k = int(np.searchsorted(ps.breaks, sig, side="right") - 1)
            assert sign_changes(rates) <= sign_changes(ps.rates[k:])
    assert kept >= 4


def test_little_motion_is_left_near_the_end(answer: dict) -> None:
    """The continuation's own rates, integrated by scipy on the tests' model: in its last
    0.05 s the joints move less than 1 % of their whole travel (the plan's own law, which
    runs its last piece rest to rest in 0.083 s, moves about 4 % there)."""
    from test_replan import run_plant

    q0 = np.array(answer["path"]["q"][0]) + [0.0, 1e-3, -1e-3, 1e-3]
    out = replan(answer, 0.0, q0)
    T = out["duration"]
    late = run_plant(out, q0, 0.0, T - 0.05, PROTOTYPE_K)
    end = run_plant(out, late, T - 0.05, T, PROTOTYPE_K)
    assert np.max(np.abs(end[1:] - np.array(GOAL))) < 1e-8
    assert np.all(np.abs(end - late)[1:] < 0.01 * np.abs(end - q0)[1:])
    plan_late = run_plant(answer, q0, 0.0, T - 0.05, PROTOTYPE_K)
    plan_end = run_plant(answer, plan_late, T - 0.05, T, PROTOTYPE_K)
    assert np.max(np.abs(plan_end - plan_late)[1:] / np.abs(plan_end - q0)[1:]) > 0.02


def test_the_damped_steps_are_the_python_loop_where_the_kernel_is_singular(pieces) -> None:
    """Where the full-step kernel's systems are singular (one piece moves, three joints), the
    damped sign-keeping steps (each trial one compiled call) do what :func:`correct_signed`
    does: the same miss and rates, the resting rates still at rest, the goal reached on
    scipy's integration of the tests' model."""
    from optimizer.planner.continuation_map import damped_correct

    q0, _ = pieces
    W = np.zeros((4, 2))
    W[2] = [0.05, 0.02]
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 4)
    end = scipy_end(q0, W)
    goal = end[1:] + np.array([3e-8, -2e-8, 1e-8])
    err_k, _ = kernel_correct(emap, q0, goal, W)
    assert not err_k <= 1e-9                          # the full steps could not
    err_loop, W_loop, steps_loop = correct_signed(emap, q0, goal, W)
    err, W1, steps = damped_correct(emap, q0, goal, W)
    assert np.all(W1[[0, 1, 3]] == 0.0) and np.all(W1[2] * W[2] >= 0.0)
    assert err <= max(2.0 * err_loop, 1e-12) and steps >= 1
    assert np.allclose(W1, W_loop, rtol=1e-6, atol=1e-12)
    # a nearby goal that many pieces reach, signs kept: the goal on scipy's model
    q0b, Wb = pieces
    emapb = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    goalb = scipy_end(q0b, Wb)[1:] + np.array([-1e-3, 1e-3, 1e-3])
    err, W2, _ = damped_correct(emapb, q0b, goalb, Wb)
    assert err < 1e-10 and np.all(W2 * np.sign(Wb) >= 0.0)
    assert np.max(np.abs(scipy_end(q0b, W2)[1:] - goalb)) < 1e-8


def test_the_damped_steps_say_when_the_signs_cannot_reach(pieces) -> None:
    """th2 back with every rate forward: no sign-keeping rates reach it; the damped steps
    stop off the goal (no claim), and no rate crossed 0."""
    from optimizer.planner.continuation_map import damped_correct

    q0, _ = pieces
    W = np.tile([0.05, 0.02], (7, 1))
    emap = PieceMap(tuple(Robot.default(3).gains), tuple(Robot.default(3).exponents), 7)
    goal = scipy_end(q0, W)[1:] - np.array([0.0, 0.05, 0.0])
    err, W1, _ = damped_correct(emap, q0, goal, W)
    assert not err <= 1e-6
    assert np.all(W1 * np.sign(W) >= 0.0)


@pytest.mark.parametrize("n, damped", [(3, True), (4, False)])
def test_the_damped_steps_follow_a_singular_kernel_below_four_joints(monkeypatch, n, damped
                                                                     ) -> None:
    """Where the full-step kernel's system is singular (no finite answer), the damped
    sign-keeping steps try before any sign is given up on 3 joints (in closed loop they kept
    the signs there), not from 4 joints on (they seldom did: the steps with any sign follow
    at once) unless the request keeps its reversals. A kernel that ends near the goal is
    followed by them at every n."""
    from optimizer.planner import replan as rp

    calls: list[str] = []
    W0 = np.full((6, 2), 0.01)

    def kernel(emap, q0, goal, W):
        calls.append("kernel")
        return (float("inf") if len(calls) == 1 else 5e-6), W

    def damped_steps(emap, q0, goal, W):
        calls.append("damped")
        return 1.0, W, 3

    def halving(emap, q0, goal, W, floor=None):
        calls.append("halving")
        return 0.0, W

    monkeypatch.setattr(rp, "kernel_correct", kernel)
    monkeypatch.setattr(rp, "damped_correct", damped_steps)
    monkeypatch.setattr(rp, "halving_correct", halving)
    q0 = np.zeros(n + 1)
    *_, kept = rp._correct(None, q0, np.zeros(n), W0, keep_reversals=False)
    assert calls == (["kernel", "damped", "halving"] if damped else ["kernel", "halving"])
    assert kept is False
    calls.clear()
    calls.append("first")       # the kernel now ends 5e-6 rad off: damped steps at every n
    rp._correct(None, q0, np.zeros(n), W0, keep_reversals=False)
    assert calls == ["first", "kernel", "damped", "halving"]
    calls.clear()               # the signs asked for: damped steps after a singular kernel
    with pytest.raises(NumericalError):
        rp._correct(None, q0, np.zeros(n), W0, keep_reversals=True)
    assert calls == ["kernel", "damped"]
