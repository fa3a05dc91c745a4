"""Constraint-point synthesis as a QP (``optimizer/planner/convex.py``, issue 3.3).

Every returned path is checked independently of the planner:

* the region: the chained path is sampled on 20001 points of tau and mapped back to joint space
  with the closed-form inverse of NOTES §2 written here (n = 3), or with the library's inverse
  plus a forward round trip (n = 4); every th_1..th_{n-1} must lie strictly inside (0, pi/2);
* the goal: the ORIGINAL model (eq 1-3, right-hand side written here) is integrated with scipy
  from the start under the planned actuator inputs ``PlannedInputs(...).u_scalar`` and must end
  within 1e-6 rad of the goal;
* the energy: ``int V2^2 dtau`` is integrated here from the polynomial coefficients.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.polynomial import polynomial as P
from scipy.integrate import solve_ivp

from optimizer.chained_form import chained_form
from optimizer.errors import InfeasibleError, SolverTimeoutError
from optimizer.model import Robot
from optimizer.planner.constraint_qp import ConstraintPointQP
from optimizer.planner.convex import plan_constraint_points
from optimizer.planner.dphi_scan import necessary_dphi_range
from optimizer.planner.legendre_qp import gram_monomials, legendre_to_monomial
from optimizer.planner.context import Deadline
from optimizer.planner.plan import plan
from optimizer.problem import PlanRequest
from optimizer.region import Region
from optimizer.steering import ChainedPath, ConstraintPoint, solve_polynomial
from optimizer.verify import PlannedInputs
from reference import model_rhs

D = math.radians
K2, K3 = 0.88658, 0.7115  # prototype constants (NOTES §1), typed in independently
A = 3 * K2 * K3
DENSE = 20001
GOAL_TOL = 1e-6


# ---------------------------------------------------------------------- independent checks
def inverse_n3(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NOTES §2 closed form: z3 = K3 c2^3, z2 = -A c1^2 c2^2 s2  ->  th1, th2 (NaN outside)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        c2 = np.cbrt(z[:, 2] / K3)
        s2 = np.sqrt(1.0 - c2 ** 2)
        c1sq = -z[:, 1] / (A * c2 ** 2 * s2)
        th2 = np.where((c2 > 0) & (c2 < 1), np.arccos(np.clip(c2, -1, 1)), np.nan)
        th1 = np.where((c1sq > 0) & (c1sq < 1), np.arccos(np.sqrt(np.clip(c1sq, 0, 1))), np.nan)
    return th1, th2, z[:, 3]



def terminal_error(req: PlanRequest, p) -> float:
    """Integrate the original model under the planned u(t); max |th(T) - goal| (rad)."""
    robot = req.robot
    u = PlannedInputs(chained_form(robot), p.chained).u_scalar
    sol = solve_ivp(lambda t, q: model_rhs(q, u(t), robot.gains, robot.exponents),
                    (0.0, p.duration), req.q_start(), method="DOP853", rtol=1e-11, atol=1e-12)
    assert sol.success, sol.message
    return float(np.max(np.abs(sol.y[1:, -1] - np.array(req.goal))))


def assert_inside_n3(path: ChainedPath) -> None:
    tau = np.linspace(0.0, 1.0, DENSE)
    z = path.z(tau)
    th1, th2, _ = inverse_n3(z)
    assert np.all(np.isfinite(th1)) and np.all(np.isfinite(th2)), "path leaves the region"
    assert np.all((th1 > 0) & (th1 < np.pi / 2)), (th1.min(), th1.max())
    assert np.all((th2 > 0) & (th2 < np.pi / 2)), (th2.min(), th2.max())
    assert np.max(z[:, 1]) < 0.0  # the paper's eq (13), everywhere


def v2_energy(coeffs: np.ndarray) -> float:
    """int_0^1 V2(tau)^2 dtau, exactly, from monomial coefficients."""
    return float(P.polyval(1.0, P.polyint(P.polymul(coeffs, coeffs))))


def paper_request(**kw) -> PlanRequest:
    """§3.3: prototype robot, th from [1, 1, 1] to [30, 30, 30] deg."""
    base = dict(start=(D(1),) * 3, goal=(D(30),) * 3, duration=10.0, method="constraint_points")
    base.update(kw)
    return PlanRequest(**base)


# ---------------------------------------------------------------------- §3.3
def test_section_3_3_qp_repairs_a_path_crossing_z2_zero():
    """At dphi = 45.3 deg the paper's polynomial has z2 crossing 0 twice (its Fig 4); the QP
    path at the same dphi passes the full check and reaches the goal."""
    dphi = D(45.3)
    req = paper_request(phi_change=dphi)
    cf = chained_form(req.robot)
    z0, zT = cf.to_chained(req.q_start()), cf.to_chained(req.q_goal(0.0))
    np.testing.assert_allclose(z0[1:], [-0.033007, 0.711175, 0.017453], atol=1e-6)
    plain = ChainedPath.from_inputs(z0, solve_polynomial(dphi, 3, z0, zT, 10.0))
    z2 = plain.z(np.linspace(0, 1, DENSE))[:, 1]
    assert z2.max() > 0 and np.count_nonzero(np.diff(np.sign(z2))) == 2

    p = plan(req)
    assert p.method == "constraint_points" and p.inputs.constant_v1 and p.inputs.pieces == 1
    assert p.phi_change == pytest.approx(dphi)
    cp = p.diagnostics["constraint_points"]
    m = cp["extra_degrees"]
    assert p.inputs.v2[0].size == 3 + m  # V2 of degree n - 1 + m
    assert_inside_n3(p.chained)
    assert terminal_error(req, p) < GOAL_TOL
    assert p.verification.terminal_error < GOAL_TOL
    assert cp["qp_status"] in ("Solved", "AlmostSolved") and cp["region_margin"] > 0

    # the synthesized constraint points, given to the paper's eq (11), reproduce V2
    pts = tuple(ConstraintPoint(q["time"], q["state"], q["value"]) for q in cp["points"])
    assert len(pts) == m and all(0 < q.time < 10.0 for q in pts)
    rep = solve_polynomial(dphi, 3, z0, zT, 10.0, pts)
    np.testing.assert_allclose(rep.v2[0], p.inputs.v2[0], rtol=1e-7, atol=1e-9)
    # the QP's objective is the exact input energy (orthonormal basis: Gram = identity)
    assert cp["qp_energy"] == pytest.approx(v2_energy(p.inputs.v2[0]), rel=1e-7)


def test_orthonormal_basis_makes_the_gram_matrix_the_identity():
    """The QP's basis is orthonormal on [0, 1] (Gauss quadrature, exact for these degrees), so
    ``||x||^2 = a^T H a`` with H the Gram matrix of the monomials (a Hilbert matrix, whose
    condition number is why the QP does not use monomials: in floating point ``L^T H L``
    itself is only good to ~1e-6 at p = 9)."""
    x, w = np.polynomial.legendre.leggauss(20)
    tau, w = 0.5 * (x + 1.0), 0.5 * w
    for p in (3, 5, 7, 9):
        L = legendre_to_monomial(p)
        V = np.stack([P.polyval(tau, L[:, j]) for j in range(p)], axis=1)
        np.testing.assert_allclose(V.T @ (w[:, None] * V), np.eye(p), atol=1e-11)
        Hq = np.stack([tau ** i for i in range(p)], axis=1)
        np.testing.assert_allclose(Hq.T @ (w[:, None] * Hq), gram_monomials(p), atol=1e-14)


@pytest.mark.parametrize("objective", ["tp_then_da", "tp_then_sensitivity"])
def test_section_3_3_dphi_scan(objective):
    """Without phi_change the scan finds a dphi inside the necessary range and the plan is
    verified; tp_then_sensitivity goes to a smaller |dphi| than tp_then_da or equal."""
    req = paper_request(objective=objective, duration=1.0)
    p = plan(req)
    lo, hi, _ = necessary_dphi_range(req)
    assert lo < p.phi_change < hi
    assert_inside_n3(p.chained)
    assert terminal_error(req, p) < GOAL_TOL
    scan = p.diagnostics["constraint_points"]["scan"]
    assert scan["nodes"] >= 10 and scan["feasible_nodes"] >= 1
    if objective == "tp_then_sensitivity":
        other = plan(paper_request(objective="tp_then_da", duration=1.0))
        assert abs(p.phi_change) <= abs(other.phi_change) + 1e-9


def test_margin_objective_keeps_z2_further_from_zero():
    req = paper_request()
    e = ConstraintPointQP(req, objective="energy").solve(D(45.3))
    mgn = ConstraintPointQP(req, objective="margin").solve(D(45.3))
    assert e.ok and mgn.ok
    tau = np.linspace(0, 1, DENSE)
    z0 = chained_form(req.robot).to_chained(req.q_start())
    zmax_e = ChainedPath.from_inputs(z0, e.inputs).z(tau)[:, 1].max()
    zmax_m = ChainedPath.from_inputs(z0, mgn.inputs).z(tau)[:, 1].max()
    assert zmax_m < zmax_e < 0
    assert mgn.energy >= e.energy  # the margin costs energy


# ---------------------------------------------------------------------- beyond the family
@pytest.mark.parametrize("start, goal, bounds, dphi_deg, T", [
    # plain family feasible only in [33.20, 35.26] deg
    ((10, 10, 10), (30, 30, 30), (36.0, 37.0), 36.5, 1.0),
    # plain family feasible only in [45.46, 47.53] deg
    ((1, 1, 1), (30, 30, 30), (48.0, 50.0), 49.0, 10.0),
])
def test_qp_finds_paths_where_the_paper_family_has_none(start, goal, bounds, dphi_deg, T):
    kw = dict(start=tuple(map(D, start)), goal=tuple(map(D, goal)), duration=T)
    with pytest.raises(InfeasibleError):
        plan(PlanRequest(method="polynomial", phi_change_bounds=(D(bounds[0]), D(bounds[1])),
                         **kw))
    req = PlanRequest(method="constraint_points", phi_change=D(dphi_deg), **kw)
    p = plan(req)
    assert p.phi_change == pytest.approx(D(dphi_deg))
    assert_inside_n3(p.chained)
    assert terminal_error(req, p) < GOAL_TOL
    assert p.diagnostics["constraint_points"]["source"] == "qp"


def test_request_constraint_points_are_kept():
    """A constraint point of the request is an equality of the QP: the path passes it."""
    cp = ConstraintPoint(5.0, 2, -0.3)
    req = PlanRequest(start=(D(10),) * 3, goal=(D(30),) * 3, duration=10.0,
                      method="constraint_points", phi_change=D(34.5), constraint_points=(cp,))
    p = plan(req)
    assert p.chained.z(np.array([0.5]))[0, 1] == pytest.approx(-0.3, abs=1e-10)
    assert_inside_n3(p.chained)
    assert terminal_error(req, p) < GOAL_TOL


def test_four_joint_path_where_the_plain_member_fails():
    """n = 4 (assumed constants): at dphi = 85 deg the paper's member leaves the region (its
    feasible window is about [79.7, 83.2] deg); the QP path does not and reaches the goal."""
    robot = Robot.default(4)
    req = PlanRequest(start=tuple(map(D, (16.4, 45.5, 31.5, 16.0))),
                      goal=tuple(map(D, (24.4, 70.4, 54.4, 37.0))), robot=robot,
                      method="constraint_points", phi_change=D(85.0))
    cf = chained_form(robot)
    z0, zT = cf.to_chained(req.q_start()), cf.to_chained(req.q_goal(0.0))
    plain = ChainedPath.from_inputs(z0, solve_polynomial(D(85.0), 4, z0, zT))
    assert not Region(robot, "full").check_path(plain).ok

    p = plan(req)
    tau = np.linspace(0.0, 1.0, DENSE)
    z = p.chained.z(tau)
    inv = cf.from_chained(z)
    assert inv.valid.all()
    th = inv.q[:, 1:4]
    assert np.all((th > 0) & (th < np.pi / 2))
    np.testing.assert_allclose(cf.to_chained(inv.q), z, atol=1e-9)  # the inverse is exact
    assert terminal_error(req, p) < GOAL_TOL


# ---------------------------------------------------------------------- energy vs the paper
@pytest.mark.parametrize("start, goal, dphis", [
    ((10, 10, 10), (30, 30, 30), (33.5, 34.57, 35.0)),
    ((1, 1, 1), (30, 30, 30), (45.6, 46.5, 47.4)),
])
@pytest.mark.parametrize("extra", [2, 4, 6])
def test_energy_never_above_a_feasible_plain_member(start, goal, dphis, extra):
    """Where the paper's member is singularity-free it is a feasible point of the QP, so the QP's
    energy (integrated here) is no larger; in fact the member is the QP's optimum (the
    unconstrained least-energy input is a polynomial of degree n - 1)."""
    req = PlanRequest(start=tuple(map(D, start)), goal=tuple(map(D, goal)), duration=1.0)
    cf = chained_form(req.robot)
    z0, zT = cf.to_chained(req.q_start()), cf.to_chained(req.q_goal(0.0))
    region = Region(req.robot, "full")
    qp = ConstraintPointQP(req, extra_degrees=extra)
    for d in dphis:
        plain = solve_polynomial(D(d), 3, z0, zT)
        assert region.check_path(ChainedPath.from_inputs(z0, plain)).ok
        s = qp.solve(D(d))
        assert s.ok and s.source == "qp"
        e_qp, e_plain = v2_energy(s.inputs.v2[0]), v2_energy(plain.v2[0])
        assert e_qp <= e_plain * (1 + 1e-7)
        assert s.energy == pytest.approx(e_qp, rel=1e-7)


# ---------------------------------------------------------------------- failures
def test_opposite_motions_are_infeasible_with_a_reason():
    req = PlanRequest(start=tuple(map(D, (10, 20, 30))), goal=tuple(map(D, (40, 25, 15))),
                      method="constraint_points")
    with pytest.raises(InfeasibleError) as exc:
        plan(req)
    assert "opposite directions" in exc.value.message
    assert exc.value.diagnostics["blocking"] == "opposite_joint_motion"


def test_phi_change_outside_the_necessary_range_is_explained():
    req = PlanRequest(start=(D(10),) * 3, goal=(D(30),) * 3, method="constraint_points",
                      phi_change=D(20.0))
    with pytest.raises(InfeasibleError) as exc:
        plan(req)
    assert exc.value.diagnostics["blocking"] == "phi_change_outside_necessary_range"
    assert exc.value.diagnostics["min_abs_phi_change"] > D(20.0)


def test_qp_infeasible_dphi_reports_the_qp_status():
    """dphi = 38 deg is inside the simple necessary range but beyond what th2's monotone
    motion allows for th3 (reachability bound ~37.3 deg): the QP proves it (n = 3: the cuts
    are outer approximations)."""
    req = PlanRequest(start=(D(10),) * 3, goal=(D(30),) * 3, method="constraint_points",
                      phi_change=D(38.0))
    with pytest.raises(InfeasibleError) as exc:
        plan(req)
    assert "QP" in exc.value.message
    att = exc.value.diagnostics["attempts"]
    assert [a["extra_degrees"] for a in att] == [4, 6]


def test_deadline_is_honoured():
    req = paper_request()
    with pytest.raises(SolverTimeoutError):
        plan_constraint_points(req, Deadline(1e-9))
