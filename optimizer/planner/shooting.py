"""Direct multiple shooting on the ORIGINAL model (method ``shooting``).

Why
---
Goals that the paper's family cannot reach (joints that must move in opposite directions, or
no singularity-free ``dphi``) need ``phi`` to reverse. The penalty method (:mod:`.penalty`)
searches polynomial chained inputs from many starts and takes seconds. This method solves one
small NLP on the original kinematic model instead: milliseconds, and, with the deviation term
below, paths closer to the straight line than the minimum-energy plan a user would write.

Transcription (normalised time ``tau = t / T`` in [0, 1]; ``T`` only rescales the rates)
----------------------------------------------------------------------------------------
* :data:`INTERVALS` equal intervals with piecewise-constant actuator rates ``U = (U1, U2)``
  (``u = U / T``), node states ``q_k = (phi, th_1..th_n)``, continuity by :data:`RK4_SUBSTEPS`
  classical RK4 steps per interval;
* ``q_0`` = the start, ``th(1)`` = the goal; ``phi(1) - phi(0)`` within the request's
  ``phi_change_bounds`` (or equal to ``phi_change``);
* ``th_1..th_n`` inside the region (:class:`~optimizer.region.Region`: ``(0, pi/2)`` for
  ``th_1..th_{n-1}``, intersected with the joint bounds) with a margin of :data:`MARGIN`
  (less when the start or the goal is closer to a bound) at every node;
* objective: ``int |U|^2 dtau + w_dev * S + w_da * S1`` with ``S >=`` the squared distance of
  every interior node's ``(th_1..th_n)`` from the straight line through start and goal (joint
  space) and ``S1 >=`` the squared distance of ``th_1`` from its straight line in time (the
  paper's ``d_a``). The weights are :data:`DEVIATION_WEIGHT`, :data:`D_A_WEIGHT` and 1, or
  ``weights.d_a`` (both deviations) and ``weights.energy`` of a ``weighted`` request. Measured
  on the benchmark's goals beyond the family, this gives smaller ``d_a`` and joint-space
  deviation than the minimum-energy plan, with as many actuator reversals.

Why nodes are enough for the region
-----------------------------------
On an interval ``u`` is constant: ``th_1`` is linear in time, and ``th_i' = K_i
cos(th_{i-1})^{m_i} u1`` has the sign of ``u1`` while ``th_{i-1}`` stays in ``(0, pi/2)``, so
every joint is monotone on the interval (by induction over ``i``) and its extremes are at the
interval's ends. The continuous path is therefore in the region exactly when the nodes of the
TRUE path are. :func:`finish_actuator_plan` checks them on the re-integrated path (cascade
quadrature of the original model, not the NLP's RK4 nodes) and measures everything on it.

Caching and threads
-------------------
The NLP and its IPOPT solver are built once per robot (gains, exponents) and process and
cached; start, goal, weights and bounds are parameters. CasADi objects are not thread-safe:
one thread per process (the service runs each solve in a worker process). The deadline is
enforced by an IPOPT iteration callback (see :mod:`.penalty`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from ..actuation import ActuatorSchedule
from ..chained_form import chained_form
from ..errors import InfeasibleError, InvalidRequestError, NumericalError, SolverTimeoutError
from ..indicators import compute_indicators
from ..problem import PlanRequest
from ..region import Region
from ..results import Plan, SampledPath
from ..verify import CASCADE_TOL, Verification, integrate_cascade

#: Shooting intervals (piecewise-constant inputs).
INTERVALS = 20
#: RK4 steps per interval inside the NLP (the returned path is re-integrated accurately).
RK4_SUBSTEPS = 2
#: Weight of the squared joint-space deviation (rad^2) against the input energy.
DEVIATION_WEIGHT = 3.0
#: Weight of the squared d_a of joint 1 (rad^2; at the nodes) against the input energy.
D_A_WEIGHT = 3.0
#: Distance (rad) kept from the region's bounds at the nodes (0.5 deg).
MARGIN = math.radians(0.5)
#: Net travel of phi (rad) of the initial guess (its sign follows the joints' motion).
GUESS_PHI_TRAVEL = 0.6
#: A plan is verified when the re-integrated model ends this close to the goal (rad).
TERMINAL_TOLERANCE = 1e-6
#: Samples of the indicator grid (the same density as the other methods' searches).
INDICATOR_SAMPLES = 1001

_SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
_TIMEOUT = ("User_Requested_Stop", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")


# ---------------------------------------------------------------------- the cached NLP
class ShootingNLP:
    """The transcription above for one robot, with its IPOPT solver (built once, cached)."""

    def __init__(self, gains: tuple[float, ...], exponents: tuple[int, ...],
                 intervals: int = INTERVALS, substeps: int = RK4_SUBSTEPS) -> None:
        from .penalty import MAX_TIME_LIMIT, _DeadlineCallback

        t0 = time.perf_counter()
        n = self.n = len(gains) + 1
        N = self.N = intervals
        nx = n + 1
        h = 1.0 / N

        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", 2)

        def rhs(q: Any) -> Any:
            dq = [u[0], u[1]]
            for i in range(2, n + 1):
                dq.append(gains[i - 2] * ca.cos(q[i - 1]) ** exponents[i - 2] * u[0])
            return ca.vertcat(*dq)

        dt, y = h / substeps, x
        for _ in range(substeps):
            k1 = rhs(y)
            k2 = rhs(y + dt / 2 * k1)
            k3 = rhs(y + dt / 2 * k2)
            k4 = rhs(y + dt * k3)
            y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        step = ca.Function("rk4", [x, u], [y])

        X = ca.SX.sym("X", nx, N + 1)
        U = ca.SX.sym("U", 2, N)
        S = ca.SX.sym("S", 2)  # epigraphs: joint-space deviation^2, d_a^2 of joint 1
        # p = [a (n), b (n), w_dev, w_energy, w_da]
        P = ca.SX.sym("p", 2 * n + 3)
        a, b, w_dev, w_en, w_da = P[:n], P[n:2 * n], P[2 * n], P[2 * n + 1], P[2 * n + 2]
        g = [X[:, k + 1] - step(X[:, k], U[:, k]) for k in range(N)]
        ell = b - a
        nrm = ca.sumsqr(ell)
        for k in range(1, N):
            d = X[1:, k] - a
            along = ca.if_else(nrm > 0, ca.dot(d, ell) ** 2 / ca.fmax(nrm, 1e-300), 0)
            g.append(ca.sumsqr(d) - along - S[0])
        for k in range(1, N):
            g.append((X[1, k] - (a[0] + (b[0] - a[0]) * k * h)) ** 2 - S[1])
        self.n_eq = nx * N
        f = w_en * h * ca.sumsqr(U) + w_dev * S[0] + w_da * S[1]
        w = ca.vertcat(ca.vec(X), ca.vec(U), S)
        self.nw = int(w.shape[0])
        self.ng = self.n_eq + 2 * (N - 1)
        self.nx_nodes = nx * (N + 1)
        self.callback = _DeadlineCallback(self.nw, self.ng, int(P.shape[0]))
        opts: dict[str, Any] = {
            "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-8, "acceptable_tol": 1e-6,
                      "max_iter": 300, "max_wall_time": float(MAX_TIME_LIMIT)},
            "print_time": False, "error_on_fail": False, "iteration_callback": self.callback}
        self.solver = ca.nlpsol("shooting", "ipopt", {"x": w, "p": P, "f": f,
                                                      "g": ca.vertcat(*g)}, opts)
        self.lbg = np.concatenate([np.zeros(self.n_eq), np.full(2 * (N - 1), -np.inf)])
        self.ubg = np.zeros(self.ng)
        self.build_time = time.perf_counter() - t0

    def guess(self, a: np.ndarray, b: np.ndarray, phi0: float, travel: float) -> np.ndarray:
        """Straight lines in joint space, ``phi`` moving by ``travel``; consistent rates."""
        N, n = self.N, self.n
        s = np.linspace(0.0, 1.0, N + 1)
        X0 = np.empty((n + 1, N + 1))
        X0[0] = phi0 + travel * s
        X0[1:] = a[:, None] + np.outer(b - a, s)
        U0 = np.empty((2, N))
        U0[0], U0[1] = travel, b[0] - a[0]
        d = X0[1:] - a[:, None]
        ell = b - a
        nrm = float(ell @ ell)
        S0 = float(np.max(np.sum(d * d, axis=0) - ((ell @ d) ** 2 / nrm if nrm > 0 else 0.0)))
        return np.concatenate([X0.ravel(order="F"), U0.ravel(order="F"),
                               [max(S0, 0.0) + 1e-4, 1e-4]])


@functools.lru_cache(maxsize=16)
def shooting_nlp(gains: tuple[float, ...], exponents: tuple[int, ...]) -> ShootingNLP:
    """The cached NLP of one robot (per process)."""
    return ShootingNLP(gains, exponents)


@dataclass(frozen=True)
class ShootingSolution:
    """IPOPT's answer in normalised time: node states ``(N+1, n+1)`` and rates ``(N, 2)``."""

    nodes: np.ndarray
    rates: np.ndarray
    status: str
    iterations: int
    start: str


def _node_bounds(req: PlanRequest, region: Region) -> tuple[np.ndarray, np.ndarray]:
    """Per joint: the region's bounds moved in by :data:`MARGIN` (less near start or goal)."""
    a, b = np.array(req.start), np.array(req.goal)
    lo, hi = np.array(region.lower, float), np.array(region.upper, float)
    inner_lo = np.minimum(a, b) - lo
    inner_hi = hi - np.maximum(a, b)
    lo_m = np.where(np.isfinite(lo), lo + np.minimum(MARGIN, 0.5 * inner_lo), -np.inf)
    hi_m = np.where(np.isfinite(hi), hi - np.minimum(MARGIN, 0.5 * inner_hi), np.inf)
    return lo_m, hi_m


def solve_shooting(req: PlanRequest, deadline: Any) -> ShootingSolution:
    """Solve the NLP for ``req`` (normalised time); raise a typed error when it fails."""
    robot = req.robot
    nlp = shooting_nlp(tuple(robot.gains), tuple(int(m) for m in robot.exponents))
    n, N = nlp.n, nlp.N
    a, b = np.array(req.start), np.array(req.goal)
    region = Region(robot, "full", req.joint_bounds)
    lo, hi = _node_bounds(req, region)
    lbX = np.full((n + 1, N + 1), -np.inf)
    ubX = np.full((n + 1, N + 1), np.inf)
    lbX[1:], ubX[1:] = lo[:, None], hi[:, None]
    lbX[:, 0] = ubX[:, 0] = np.concatenate([[req.phi_start], a])
    lbX[1:, N] = ubX[1:, N] = b
    if req.phi_change is not None:
        lbX[0, N] = ubX[0, N] = req.phi_start + req.phi_change
    else:
        lbX[0, N] = req.phi_start + req.phi_change_bounds[0]
        ubX[0, N] = req.phi_start + req.phi_change_bounds[1]
    lbw = np.concatenate([lbX.ravel(order="F"), np.full(2 * N, -np.inf), [0.0, 0.0]])
    ubw = np.concatenate([ubX.ravel(order="F"), np.full(2 * N, np.inf), [np.inf, np.inf]])
    if req.objective == "weighted":
        w_dev, w_en = float(req.weights.d_a), float(req.weights.energy)
        w_da = w_dev
        if w_dev <= 0.0 and w_en <= 0.0:
            raise InvalidRequestError("method 'shooting' with objective 'weighted' needs a "
                                      "positive weights.d_a or weights.energy", field="weights")
    else:
        w_dev, w_en, w_da = DEVIATION_WEIGHT, 1.0, D_A_WEIGHT
    p = np.concatenate([a, b, [w_dev, w_en, w_da]])
    # phi's net travel: the direction most joints' changes ask for (weighted by 1/K_i)
    drive = float(np.sum((b[1:] - a[1:]) / np.array(robot.gains)))
    lo_phi, hi_phi = float(lbX[0, N] - req.phi_start), float(ubX[0, N] - req.phi_start)
    travels = [math.copysign(GUESS_PHI_TRAVEL, drive if drive != 0.0 else 1.0)]
    travels.append(-travels[0])
    tried: list[dict[str, Any]] = []
    for travel in travels:
        travel = min(max(travel, lo_phi), hi_phi)
        if deadline.remaining <= 1e-3:
            break
        nlp.callback.stop_at = time.perf_counter() + deadline.remaining
        try:
            sol = nlp.solver(x0=nlp.guess(a, b, req.phi_start, travel), p=p, lbx=lbw, ubx=ubw,
                             lbg=nlp.lbg, ubg=nlp.ubg)
        finally:
            nlp.callback.stop_at = math.inf
        stats = nlp.solver.stats()
        status = str(stats.get("return_status", "unknown"))
        tried.append({"phi_travel_guess": travel, "status": status,
                      "iterations": int(stats.get("iter_count", -1))})
        if status in _SUCCESS:
            w = np.asarray(sol["x"]).ravel()
            X = w[:nlp.nx_nodes].reshape((n + 1, N + 1), order="F")
            Uk = w[nlp.nx_nodes:nlp.nx_nodes + 2 * N].reshape((2, N), order="F")
            return ShootingSolution(nodes=X.T.copy(), rates=Uk.T.copy(), status=status,
                                    iterations=int(stats.get("iter_count", -1)),
                                    start=f"phi travel {travel:+.3g} rad")
        if status in _TIMEOUT:
            raise SolverTimeoutError(
                f"the shooting NLP did not converge within the time limit of "
                f"{deadline.seconds:g} s", field="time_limit",
                diagnostics={"stage": "shooting NLP", "tried": tried})
    if not tried:
        raise SolverTimeoutError(
            f"no time was left for the shooting NLP (time limit {deadline.seconds:g} s)",
            field="time_limit", diagnostics={"stage": "shooting NLP"})
    raise InfeasibleError("the shooting NLP found no path from any start: "
                          + "; ".join(t["status"] for t in tried),
                          diagnostics={"blocking": "nlp_failed", "tried": tried})


def _duration(req: PlanRequest, rates: np.ndarray) -> float:
    """``T``: the request's, or the shortest that respects the actuator limits."""
    limits = (req.max_u1, req.max_u2)
    if all(x is None for x in limits):
        return req.duration_or_default
    need = max(float(np.max(np.abs(rates[:, j]))) / lim
               for j, lim in enumerate(limits) if lim is not None)
    if req.duration is None:
        return max(need, 1e-3)
    if req.duration < need * (1 - 1e-12):
        raise InfeasibleError(
            f"duration {req.duration:g} s is too short for the actuator limits: the shortest "
            f"duration that respects them is {need:.6g} s",
            diagnostics={"shortest_duration": need})
    return float(req.duration)


def finish_actuator_plan(req: PlanRequest, schedule: ActuatorSchedule, method: str,
                         planned_nodes: np.ndarray, timing: dict[str, float],
                         diagnostics: dict[str, Any]) -> Plan:
    """Re-integrate, check, sample and measure a piecewise-constant-rate plan.

    The path is the original model integrated under ``schedule`` (cascade quadrature, error
    estimate <= 1e-11 rad, DOP853 as fallback): samples, indicators, the region check at the
    interval ends (enough, see the module docstring) and the terminal error all come from it.
    ``planned_nodes`` (the NLP's own node states) give the verification's ``max_deviation``.

    Raises
    ------
    InfeasibleError
        A node of the true path is outside the region.
    NumericalError
        The true path does not reach the goal.
    """
    t0 = time.perf_counter()
    robot = req.robot
    cf = chained_form(robot)
    T = schedule.duration
    q0 = req.q_start()
    t = np.linspace(0.0, T, int(req.samples))
    td = np.linspace(0.0, T, INDICATOR_SAMPLES)
    t_all = np.concatenate([t, td, schedule.breaks])
    rep = integrate_cascade(robot, schedule.u, q0, T, t_all, schedule.breaks,
                            fallback=schedule.u_scalar)
    timing["verification"] = time.perf_counter() - t0
    if not rep.success:
        raise NumericalError(f"the re-integration failed: {rep.message}",
                             diagnostics={"method": method})
    ns, nd = t.size, td.size
    q, qd, qb = rep.q[:ns], rep.q[ns:ns + nd], rep.q[ns + nd:]
    region = Region(robot, "full", req.joint_bounds)
    lo, hi = np.array(region.lower, float), np.array(region.upper, float)
    th = qb[:, 1:]
    margins = np.minimum(th - lo, hi - th)
    margin = float(np.min(margins))
    if not margin > 0.0 or rep.singular:
        k, j = np.unravel_index(int(np.argmin(margins)), margins.shape)
        raise InfeasibleError(
            f"the re-integrated path leaves the singularity-free region: th{j + 1} at "
            f"t = {schedule.breaks[k]:.6g} s", diagnostics={"margin": margin})
    final = rep.final
    terminal = float(np.max(np.abs(final[1:] - np.array(req.goal))))
    if not terminal <= TERMINAL_TOLERANCE:
        raise NumericalError(
            "the planned inputs do not steer the original model to the goal "
            f"(terminal error {terminal:.3g} rad)",
            diagnostics={"terminal_error": terminal, "method": method})
    t1 = time.perf_counter()
    u = schedule.u(t)
    # v = (u1, L_g1 z2 u1 + L_g2 z2 u2) along the path (eq 5); z by the forward map (eq 4)
    al, be = cf.input_coefficients(q)
    v = np.column_stack([u[:, 0], al * u[:, 0] + be * u[:, 1]])
    z = cf.to_chained(q)
    ind = compute_indicators(td, qd, schedule.u(td))
    ind = dataclasses.replace(ind, energy=rep.energy)
    dphi = float(final[0] - q0[0])
    ver = Verification(terminal_error=terminal, phi_error=0.0,
                       max_deviation=float(np.max(np.abs(qb - planned_nodes))),
                       singular=False, final=tuple(float(x) for x in final),
                       rtol=CASCADE_TOL, atol=CASCADE_TOL, energy=rep.energy,
                       integrator=rep.integrator, error_estimate=rep.error_estimate)
    timing["sampling"] = time.perf_counter() - t1
    return Plan(robot=robot, method=method, phi_change=dphi, duration=T, inputs=schedule,
                chained=None, feasible_phi_changes=[], indicators=ind, margin=margin,
                path=SampledPath(t=t, q=q, z=z, u=u, v=v), verification=ver, timing=timing,
                diagnostics=diagnostics)


def plan_shooting(req: PlanRequest, deadline: Any) -> Plan:
    """Method ``shooting``: the NLP above, then :func:`finish_actuator_plan`."""
    if req.constraint_points:
        raise InvalidRequestError(
            "method 'shooting' takes no constraint points (they are points of the chained "
            "polynomial inputs: use 'polynomial' or 'constraint_points')",
            field="constraint_points")
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    sol = solve_shooting(req, deadline)
    timing["nlp"] = time.perf_counter() - t0
    deadline.check("the shooting NLP")
    T = _duration(req, sol.rates)
    N = sol.rates.shape[0]
    schedule = ActuatorSchedule(breaks=np.linspace(0.0, T, N + 1), rates=sol.rates / T)
    diagnostics = {"objective": req.objective, "singularity": "full",
                   "shooting": {"intervals": N, "rk4_substeps": RK4_SUBSTEPS,
                                "ipopt_status": sol.status, "iterations": sol.iterations,
                                "start": sol.start}}
    return finish_actuator_plan(req, schedule, "shooting", sol.nodes, timing, diagnostics)


__all__ = ["ActuatorSchedule", "ShootingNLP", "plan_shooting", "finish_actuator_plan",
           "solve_shooting"]
