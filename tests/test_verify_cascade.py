"""The cascade quadrature that verifies plans (``optimizer.verify.integrate_cascade``).

Every check is against an INDEPENDENT computation: the original model written in
``tests/reference.py`` (``model_rhs``) integrated with scipy's DOP853 at rtol 1e-12 (piece by
piece, so that no step straddles an input break), closed forms, or scipy's adaptive quadrature
of a closed-form integrand. The reference and the cascade share only the planned inputs
``u(t)``, and those are checked on their own (the vectorised ``u`` against the scalar one).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy.integrate import quad, solve_ivp

from optimizer.chained_form import chained_form
from optimizer.model import Robot
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.steering import ChainedPath, InputSchedule, solve_polynomial
from optimizer.verify import (CASCADE_INITIAL_PANELS, CASCADE_NAME, DOP853_NAME, PlannedInputs,
                              integrate, integrate_cascade, verify_plan)

from reference import model_rhs

D = np.deg2rad

#: Plans of the polynomial family for n = 3, 4, 5 (the n = 5 goal was produced by running a
#: member of the family forward, so that the planner has something to find).
REQUESTS = {
    "n3_worked_example": {"start": D([10, 10, 10]), "goal": D([30, 30, 30])},
    "n4_narrow_window": {"start": D([47.7, 66.9, 44.9, 66.0]),
                         "goal": D([62.6, 72.2, 47.5, 71.9])},
    "n5": {"start": D([34.1586, 61.2241, 57.2974, 26.3407, 60.3174]),
           "goal": D([45.3168, 79.636, 61.2915, 35.2931, 78.2472])},
}


def reference(u_scalar, q0, T, K, m, t_eval, breaks):
    """DOP853 (rtol 1e-12) on the test's own model with the energy as an extra state, restarted
    at every break. Returns (final state, samples, energy)."""
    def rhs(t, x):
        u = u_scalar(t)
        return np.concatenate([model_rhs(x[:-1], u, K, m), [u[0] ** 2 + u[1] ** 2]])

    x = np.concatenate([np.asarray(q0, float), [0.0]])
    samples = np.full((t_eval.size, x.size), np.nan)
    for a, b in itertools.pairwise(breaks):
        sol = solve_ivp(rhs, (a, b), x, method="DOP853", rtol=1e-12, atol=1e-14,
                        dense_output=True)
        assert sol.success, sol.message
        sel = (t_eval >= a) & (t_eval <= b)
        samples[sel] = sol.sol(t_eval[sel]).T
        x = sol.y[:, -1]
    assert np.all(np.isfinite(samples))
    return x[:-1], samples[:, :-1], x[-1]


def assert_matches_reference(rep, ref, final_tol=1e-10, sample_tol=1e-9, energy_rtol=1e-9):
    final, samples, energy = ref
    assert rep.success and not rep.singular, rep.message
    np.testing.assert_allclose(rep.final, final, rtol=0, atol=final_tol)
    np.testing.assert_allclose(rep.q, samples, rtol=0, atol=sample_tol)
    assert abs(rep.energy - energy) <= energy_rtol * energy


@pytest.fixture(scope="module", params=sorted(REQUESTS))
def planned(request):
    spec = REQUESTS[request.param]
    n = len(spec["start"])
    req = PlanRequest(start=tuple(spec["start"]), goal=tuple(spec["goal"]),
                      robot=Robot.default(n), method="polynomial")
    p = plan(req)
    inputs = PlannedInputs(chained_form(p.robot), p.chained)
    ref = reference(inputs.u_scalar, req.q_start(), p.duration, p.robot.gains,
                    p.robot.exponents, p.path.t, inputs.breaks)
    return req, p, inputs, ref


@pytest.fixture(scope="module")
def piecewise():
    """A 3-piece schedule (v1 changes, phi reverses in the middle piece; v2 jumps at the
    breaks) from a start well inside the region, checked densely to stay inside it."""
    robot = Robot.default(3)
    cf = chained_form(robot)
    q0 = np.concatenate([[0.1], D([35.0, 40.0, 30.0])])
    sched = InputSchedule(np.array([0.0, 0.3, 0.55, 1.0]),
                          (np.array([0.5, 0.4]), np.array([-0.3]), np.array([0.45, 0.0, -0.2])),
                          (np.array([0.1, -0.3]), np.array([-0.05, 0.2]), np.array([0.15])),
                          2.0)
    path = ChainedPath.from_inputs(cf.to_chained(q0), sched)
    inv = cf.from_chained(path.z(np.linspace(0, 1, 4001)))
    th = inv.q[:, 1:3]
    assert inv.valid.all() and th.min() > D(5) and th.max() < D(85)
    inputs = PlannedInputs(cf, path)
    t = np.unique(np.concatenate([np.linspace(0, 2.0, 101), inputs.breaks]))
    ref = reference(inputs.u_scalar, q0, 2.0, robot.gains, robot.exponents, t, inputs.breaks)
    return robot, q0, inputs, t, ref


# ---------------------------------------------------------------------- against DOP853
def test_plans_match_reference(planned):
    req, p, inputs, ref = planned
    rep = integrate_cascade(p.robot, inputs.u, req.q_start(), p.duration, p.path.t,
                            inputs.breaks)
    assert rep.integrator == CASCADE_NAME
    assert rep.error_estimate is not None and rep.error_estimate <= 1e-11
    assert_matches_reference(rep, ref)


def test_verify_plan_uses_cascade(planned):
    """verify_plan's default is the cascade; its numbers agree with the reference and with the
    DOP853 path of verify_plan (rtol 1e-10)."""
    req, p, inputs, (final, samples, energy) = planned
    args = (p.robot, inputs, req.q_start(), np.array(req.goal), req.phi_start + p.phi_change,
            p.path.t, p.path.q)
    ver = verify_plan(*args)
    assert ver.integrator == CASCADE_NAME
    assert ver.error_estimate is not None and ver.error_estimate <= ver.atol
    assert not ver.singular
    np.testing.assert_allclose(ver.final, final, rtol=0, atol=1e-10)
    assert ver.terminal_error == pytest.approx(np.max(np.abs(final[1:] - req.goal)), abs=1e-10)
    assert ver.max_deviation == pytest.approx(np.max(np.abs(samples - p.path.q)), abs=1e-9)
    assert ver.energy == pytest.approx(energy, rel=1e-9)
    old = verify_plan(*args, integrator="DOP853")
    assert old.integrator == DOP853_NAME and old.error_estimate is None
    np.testing.assert_allclose(ver.final, old.final, rtol=0, atol=1e-8)


def test_piecewise_schedule_matches_reference(piecewise):
    robot, q0, inputs, t, ref = piecewise
    rep = integrate_cascade(robot, inputs.u, q0, 2.0, t, inputs.breaks)
    assert_matches_reference(rep, ref)
    # no panel straddles a break: the samples exactly at the breaks are right too
    at = np.isin(t, inputs.breaks)
    np.testing.assert_allclose(rep.q[at], ref[1][at], rtol=0, atol=1e-10)


def test_the_mesh_holds_the_exact_states(piecewise):
    """The quadrature's own mesh (panel starts and nodes, then T) is in time order, holds every
    break and carries the states of the reference there."""
    robot, q0, inputs, t, _ = piecewise
    rep = integrate_cascade(robot, inputs.u, q0, 2.0, t, inputs.breaks)
    assert rep.mesh_t is not None and rep.mesh_q is not None
    assert np.all(np.diff(rep.mesh_t) > 0.0) and rep.mesh_t[0] == 0.0 and rep.mesh_t[-1] == 2.0
    assert np.all(np.isin(inputs.breaks, rep.mesh_t))
    assert rep.mesh_q.shape == (rep.mesh_t.size, 4)
    _, at_mesh, _ = reference(inputs.u_scalar, q0, 2.0, robot.gains, robot.exponents,
                              rep.mesh_t, inputs.breaks)
    np.testing.assert_allclose(rep.mesh_q, at_mesh, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(rep.mesh_q[-1], rep.final)


@pytest.mark.parametrize("nodes", [12, 8])
def test_constant_pieces_read_once_per_panel_and_match_reference(nodes):
    """Piecewise-constant rates (an actuator schedule, phi reversing): read once per panel
    (``constant_pieces``) the replay matches the reference and the general path, on the same
    mesh; the joints' integrands are refined (more so with fewer nodes), and the new panels
    read their rates too."""
    from optimizer.actuation import ActuatorSchedule

    robot = Robot.default(3)
    q0 = np.concatenate([[0.2], D([20.0, 50.0, 40.0])])
    rates = np.array([[0.8, 0.3], [0.5, -0.2], [-0.4, 0.1], [-0.7, 0.25], [0.3, -0.1]])
    sched = ActuatorSchedule(breaks=np.array([0.0, 0.3, 0.5, 0.9, 1.2, 1.6]), rates=rates)
    T = sched.duration
    t = np.unique(np.concatenate([np.linspace(0.0, T, 41), sched.breaks]))
    ref = reference(sched.u_scalar, q0, T, robot.gains, robot.exponents, t, sched.breaks)
    fast = integrate_cascade(robot, sched.u, q0, T, t, sched.breaks, nodes=nodes,
                             initial_panels=1, constant_pieces=True)
    general = integrate_cascade(robot, sched.u, q0, T, t, sched.breaks, nodes=nodes,
                                initial_panels=1)
    assert fast.integrator == CASCADE_NAME and fast.error_estimate <= 1e-11
    assert_matches_reference(fast, ref)
    assert fast.panels == general.panels > sched.pieces
    assert fast.evaluations * (nodes - 1) < general.evaluations
    np.testing.assert_allclose(fast.q, general.q, rtol=0, atol=1e-13)


def test_breaks_are_needed_for_piecewise_inputs(piecewise):
    """Without the breaks the panels straddle the input jumps: the estimate must notice (more
    panels, or a fallback), and the answer must still be right."""
    robot, q0, inputs, t, ref = piecewise
    rep = integrate_cascade(robot, inputs.u, q0, 2.0, t, None, fallback=inputs.u_scalar)
    with_breaks = integrate_cascade(robot, inputs.u, q0, 2.0, t, inputs.breaks)
    assert rep.integrator == DOP853_NAME or rep.panels > with_breaks.panels
    np.testing.assert_allclose(rep.final, ref[0], rtol=0, atol=1e-8)


def test_vectorised_inputs_equal_scalar(planned, piecewise):
    for inputs, T in ((planned[2], planned[1].duration), (piecewise[2], 2.0)):
        t = np.concatenate([np.linspace(0.0, T, 333), inputs.breaks])
        vec = inputs.u(t)
        sca = np.array([inputs.u_scalar(x) for x in t])
        np.testing.assert_allclose(vec, sca, rtol=1e-13, atol=1e-13)


# ---------------------------------------------------------------------- closed form
def test_constant_inputs_closed_form():
    """u1 = a, u2 = b constant: phi and th1 are linear, th2 = th2(0) + K2 a int cos^2(th1) has a
    closed form; th3 = th3(0) + K3 a int cos^3(th2) by scipy's adaptive quadrature of that
    closed form; the energy is (a^2 + b^2) T."""
    robot = Robot.default(3)
    K2, K3 = robot.gains
    a, b, T = 0.7, 0.4, 1.5
    q0 = np.array([0.2, 0.3, 0.25, 0.35])

    def th2(t):
        th1 = q0[1] + b * t
        return q0[2] + K2 * a * (t / 2 + (np.sin(2 * th1) - np.sin(2 * q0[1])) / (4 * b))

    t = np.linspace(0.0, T, 41)
    th3 = np.array([q0[3] + K3 * a * quad(lambda s: math.cos(th2(s)) ** 3, 0.0, x,
                                          epsabs=1e-14, epsrel=1e-13, limit=200)[0]
                    for x in t])
    exact = np.column_stack([q0[0] + a * t, q0[1] + b * t, th2(t), th3])
    rep = integrate_cascade(robot, lambda tt: np.column_stack([np.full(tt.size, a),
                                                               np.full(tt.size, b)]),
                            q0, T, t)
    assert rep.success and not rep.singular
    np.testing.assert_allclose(rep.q, exact, rtol=0, atol=1e-13)
    np.testing.assert_allclose(rep.final, exact[-1], rtol=0, atol=1e-13)
    assert rep.energy == pytest.approx((a * a + b * b) * T, rel=1e-14)
    assert rep.error_estimate is not None and rep.error_estimate <= 1e-11


# ---------------------------------------------------------------------- singularities
def test_inputs_driving_a_joint_out_are_singular():
    """u2 = -0.5 from th1 = 0.2 takes th1 through 0 at t = 0.4 s."""
    robot = Robot.default(3)
    q0 = np.array([0.0, 0.2, 0.5, 0.5])
    rep = integrate_cascade(robot, lambda tt: np.column_stack([np.full(tt.size, 0.3),
                                                               np.full(tt.size, -0.5)]),
                            q0, 1.0, np.linspace(0.0, 1.0, 11))
    assert rep.singular
    assert rep.singular_time == pytest.approx(0.4, abs=0.02)
    # th2 (an inner joint too) through pi/2: u1 large and th1 small
    q0 = np.array([0.0, 0.05, 1.4, 0.5])
    rep = integrate_cascade(robot, lambda tt: np.column_stack([np.full(tt.size, 1.0),
                                                               np.zeros(tt.size)]),
                            q0, 1.0, np.linspace(0.0, 1.0, 11))
    assert rep.singular and 0.0 < rep.singular_time < 1.0


def test_planned_path_leaving_the_region_is_singular():
    """The worked example with dphi = 37.5 deg (outside its feasible interval): the planned path
    leaves the region, its inputs are not finite there, verification says singular."""
    robot = Robot.default(3)
    cf = chained_form(robot)
    q0 = np.concatenate([[0.0], D([10, 10, 10])])
    qT = np.concatenate([[D(37.5)], D([30, 30, 30])])
    sched = solve_polynomial(D(37.5), 3, cf.to_chained(q0), cf.to_chained(qT))
    path = ChainedPath.from_inputs(cf.to_chained(q0), sched)
    assert not cf.from_chained(path.z(np.linspace(0, 1, 2001))).valid.all()
    inputs = PlannedInputs(cf, path)
    t = np.linspace(0.0, 1.0, 51)
    ver = verify_plan(robot, inputs, q0, qT[1:], qT[0], t, np.zeros((t.size, 4)))
    assert ver.singular and not ver.terminal_error < 1.0


# ---------------------------------------------------------------------- estimate, refinement
def test_few_nodes_refine_and_stay_right(planned):
    """Twelve nodes on one panel cannot resolve the inputs: the estimate must ask for panels,
    and the refined answer must still match the reference."""
    req, p, inputs, ref = planned
    rep = integrate_cascade(p.robot, inputs.u, req.q_start(), p.duration, p.path.t,
                            inputs.breaks, nodes=12, initial_panels=1)
    assert rep.integrator == CASCADE_NAME
    assert rep.panels > 1
    assert_matches_reference(rep, ref)


def test_unmet_estimate_falls_back_to_dop853(planned):
    req, p, inputs, (final, _, _) = planned
    kw = {"nodes": 8, "initial_panels": 1, "max_rounds": 0}
    alone = integrate_cascade(p.robot, inputs.u, req.q_start(), p.duration, p.path.t,
                              inputs.breaks, **kw)
    assert not alone.success and "estimate" in alone.message
    rep = integrate_cascade(p.robot, inputs.u, req.q_start(), p.duration, p.path.t,
                            inputs.breaks, fallback=inputs.u_scalar, **kw)
    assert rep.success and rep.integrator == DOP853_NAME and rep.error_estimate is None
    assert "cascade quadrature not accepted" in rep.message
    np.testing.assert_allclose(rep.final, final, rtol=0, atol=1e-8)


@pytest.mark.parametrize("tol", [1e-4, 1e-6, 1e-8])
def test_estimate_bounds_the_actual_error(planned, tol):
    """With a loose target the cascade stops early; its estimate must not be smaller than the
    error it actually makes (states and samples against the reference; energy relative). The
    floor 1e-12 is the reference's own accuracy (DOP853 at rtol 1e-12)."""
    req, p, inputs, (final, samples, energy) = planned
    rep = integrate_cascade(p.robot, inputs.u, req.q_start(), p.duration, p.path.t,
                            inputs.breaks, tol=tol, nodes=12, initial_panels=1)
    assert rep.integrator == CASCADE_NAME and rep.error_estimate is not None
    actual = max(np.max(np.abs(rep.final - final)), np.max(np.abs(rep.q - samples)),
                 abs(rep.energy - energy) / energy)
    assert actual <= max(rep.error_estimate, 1e-12)


def test_dop853_integrate_unchanged(planned):
    """The DOP853 integrator (kept for fallbacks and replays) still agrees with the reference."""
    req, p, inputs, (final, _, energy) = planned
    rep = integrate(p.robot, inputs.u_scalar, req.q_start(), p.duration, p.path.t)
    assert rep.integrator == DOP853_NAME and rep.evaluations > 0
    np.testing.assert_allclose(rep.final, final, rtol=0, atol=1e-8)
    assert rep.energy == pytest.approx(energy, rel=1e-8)


def test_rounding_noise_is_accepted_not_refined():
    """Inputs carrying noise far below their size (as the inverse map's amplified rounding
    does near the region's edges; here an unresolvable 1e9 rad/s ripple of 3e-11): cutting
    panels cannot lower it, so the cascade does not refine, and its estimate covers the noise
    (between the target and the acceptance limit) and the actual error."""
    robot = Robot.default(3)
    q0 = np.array([0.0, 0.5, 0.5, 0.5])
    rep = integrate_cascade(robot, lambda t: np.column_stack([np.full(t.size, 0.5),
                                                              np.cos(t) + 3e-11 * np.sin(1e9 * t)]),
                            q0, 1.0, np.linspace(0.0, 1.0, 11))
    assert rep.success and rep.integrator == CASCADE_NAME and rep.panels == CASCADE_INITIAL_PANELS
    assert 1e-11 < rep.error_estimate <= 1e-8 and "noise" in rep.message
    assert abs(rep.final[1] - (0.5 + math.sin(1.0))) <= rep.error_estimate


def test_one_time_rates_are_those_of_the_piece_the_times_vector_finds():
    """``ActuatorSchedule.u_scalar`` (the DOP853 replay's right-hand side, by bisection on
    lists) gives the rates ``u`` (numpy's search) gives, at random times, at every break, a
    rounding either side of it, and outside ``[0, T]``."""
    from optimizer.actuation import ActuatorSchedule

    rng = np.random.default_rng(5)
    breaks = np.concatenate([[0.0], np.sort(rng.uniform(0.0, 3.0, 30)), [3.0]])
    sched = ActuatorSchedule(breaks=breaks, rates=rng.normal(size=(31, 2)))
    times = np.concatenate([rng.uniform(-1.0, 4.0, 500), breaks,
                            np.nextafter(breaks, np.inf), np.nextafter(breaks, -np.inf)])
    expected = sched.u(times)
    got = np.array([sched.u_scalar(float(t)) for t in times])
    assert np.array_equal(got, expected)
    # a fresh array each call: the caller may write into it
    first = sched.u_scalar(0.5)
    first[:] = 99.0
    assert not np.any(sched.u_scalar(0.5) == 99.0)
