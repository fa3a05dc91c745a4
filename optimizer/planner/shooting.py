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
* equal intervals with piecewise-constant actuator rates ``U = (U1, U2)`` (``u = U / T``),
  node states ``q_k = (phi, th_1..th_n)``, continuity by classical RK4 steps; the number of
  intervals, of steps and the rate bound are a rung of :data:`LADDER` (20 intervals of one
  step first; 50 of two when that NLP does not converge);
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

Correction onto the exact goal
------------------------------
The NLP's RK4 (one step per interval, rates bounded: :data:`LADDER`) is cheap but not
exact: the original model under its rates ends 1e-8 to 1e-5 rad from the goal. Newton steps on
the exact model (:func:`correct_rates`: cascade quadrature for the residual, the RK4 model's
Jacobian for the minimum-norm step) bring that to ~1e-11 rad in one or two steps.

Why nodes are enough for the region
-----------------------------------
On an interval ``u`` is constant: ``th_1`` is linear in time, and ``th_i' = K_i
cos(th_{i-1})^{m_i} u1`` has the sign of ``u1`` while ``th_{i-1}`` stays in ``(0, pi/2)``, so
every joint is monotone on the interval (by induction over ``i``) and its extremes are at the
interval's ends. The continuous path is therefore in the region exactly when the nodes of the
TRUE path are. :func:`finish_actuator_plan` checks them on the re-integrated path (cascade
quadrature of the original model, not the NLP's RK4 nodes) and measures everything on it.

Solvers
-------
fatrop (an interior-point solver for this stage structure, bundled with CasADi) first: about
half IPOPT's time per iteration here. From ``phi`` travelling +0.6 rad, then -0.6 rad
(:data:`ATTEMPTS`); IPOPT from the same guesses when fatrop does not converge. Both solve the
same NLP (a test checks that they find the same solution). With compiled functions configured
(:mod:`optimizer.native`: the service does it), fatrop evaluates the first rung's functions as
compiled C once their library is built (:meth:`ShootingNLP.load_native`): the same iterates,
19-25 % less time per plan; until then, and for the second rung, CasADi's virtual machine.

Caching, threads, deadline
--------------------------
The NLP and its solvers are built once per robot (gains, exponents) and process and cached;
start, goal, weights and bounds are parameters. CasADi objects are not thread-safe: one thread
per process (the service runs each solve in a worker process). No attempt starts after the
deadline; IPOPT is stopped by an iteration callback (see :mod:`.penalty`), fatrop by its
iteration cap :data:`FATROP_MAX_ITER` (tens of milliseconds).
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

from .. import native
from ..actuation import ActuatorSchedule
from ..execution import execute
from ..errors import InfeasibleError, InvalidRequestError, NumericalError, SolverTimeoutError
from ..indicators import compute_indicators
from ..problem import PlanRequest
from ..region import Region
from ..results import Plan
from ..verify import CASCADE_TOL, Verification, integrate_cascade
from .family import SEARCH_SAMPLES as INDICATOR_SAMPLES  # the other methods' indicator grid
from .penalty import MAX_TIME_LIMIT, TIMEOUT, _DeadlineCallback
from .plan import TERMINAL_TOLERANCE

@dataclass(frozen=True)
class Transcription:
    """One rung of the ladder of transcriptions: intervals, RK4 steps per interval inside the
    NLP (the returned path is re-integrated accurately and the rates corrected onto the goal of
    the exact model, see :func:`correct_rates`) and the bound of ``|U1|, |U2|`` (rad per unit
    of normalised time, i.e. per ``T``) that keeps those steps close to the exact model."""

    intervals: int
    substeps: int
    rate_bound: float


#: Tried in order until one NLP converges. The first: 20 intervals, one RK4 step each, at most
#: 0.5 rad per interval (without a bound the NLP found a spurious optimum with phi moving 2 rad
#: in one interval, where RK4 and the exact model part by 0.1 rad; a bound of 6 left 3 of 80
#: random 3- and 4-joint goals unsolved, 10 solved all 80). The second, for goals that need
#: more switching and faster rates (6 joints: the minimum-energy baseline's rates reach 14-21
#: rad/s), has the baseline's 50 intervals, 2 RK4 steps each.
LADDER: tuple[Transcription, ...] = (Transcription(20, 1, 10.0), Transcription(50, 2, 40.0))
#: The Newton correction stops once the exact model ends this close to the goal (rad)...
CORRECTION_TARGET = 1e-10
#: ... or after this many steps.
MAX_CORRECTIONS = 4
#: Weight of the squared joint-space deviation (rad^2) against the input energy.
DEVIATION_WEIGHT = 3.0
#: Weight of the squared d_a of joint 1 (rad^2; at the nodes) against the input energy.
D_A_WEIGHT = 3.0
#: Distance (rad) kept from the region's bounds at the nodes (0.5 deg).
MARGIN = math.radians(0.5)
#: Iteration cap of fatrop (it converged in 15-38 iterations on the bench's goals; a failing run
#: ends early and the next attempt starts).
FATROP_MAX_ITER = 60
#: fatrop's convergence tolerance: the optimum to 1e-6 is plenty, the goal's precision comes
#: from the correction on the exact model (1e-8 took one or two more iterations, same plans).
FATROP_TOL = 1e-6
#: fatrop's initial barrier parameter. Its default, 0.1, failed from the straight-line guess on
#: some goals; 1.0 converged at the first attempt on 30 of 40 random 3- and 4-joint goals
#: (0.1: 23 of 40) and halved the median time.
FATROP_MU_INIT = 1.0
#: Solver and sign of phi's initial travel of each attempt, in order (the first converged
#: solution is returned).
ATTEMPTS: tuple[tuple[str, float], ...] = (("fatrop", 1.0), ("fatrop", -1.0), ("ipopt", 1.0),
                                           ("ipopt", -1.0))
#: Net travel of phi (rad) of the initial guesses (both signs, see :data:`ATTEMPTS`).
GUESS_PHI_TRAVEL = 0.6


def _power(c: Any, m: int) -> Any:
    """``c ** m`` for a small integer ``m >= 1`` as a product (a pow node otherwise)."""
    if isinstance(m, (int, np.integer)) and 1 <= m <= 8:
        out = c
        for _ in range(int(m) - 1):
            out = out * c
        return out
    return c ** m


# ---------------------------------------------------------------------- the cached NLP
class ShootingNLP:
    """The transcription above for one robot, with its solvers (built once, cached).

    Stage-wise layout (what fatrop needs, IPOPT does not mind): ``w = [x_0, u_0, x_1, u_1, ...,
    x_N]`` with ``x_k = (q_k, S_k, S1_k)`` (the two epigraph variables are carried as constant
    states, so that every constraint couples one stage only) and ``u_k = U_k``; constraints per
    stage: the gap ``x_{k+1} - F(x_k, u_k)``, then the stage's own rows (start at ``k = 0``,
    deviation epigraphs inside, goal and, when fixed, ``dphi`` at ``k = N``).

    Solvers: fatrop (bundled with CasADi; it exploits the stage structure, about twice as fast
    per iteration as IPOPT here) first, IPOPT (with the deadline callback) when fatrop fails.
    """

    def __init__(self, gains: tuple[float, ...], exponents: tuple[int, ...], fixed_phi: bool,
                 intervals: int, substeps: int) -> None:
        t0 = time.perf_counter()
        n = self.n = len(gains) + 1
        N = self.N = intervals
        nq = n + 1
        nx = self.nx = nq + 2
        h = 1.0 / N

        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", 2)

        def rhs(q: Any) -> Any:
            dq = [u[0], u[1]]
            for i in range(2, n + 1):
                c = ca.cos(q[i - 1])
                # integer powers as products: smaller derivative graphs than pow nodes
                dq.append(gains[i - 2] * _power(c, exponents[i - 2]) * u[0])
            return ca.vertcat(*dq, 0, 0)

        dt, y = h / substeps, x
        for _ in range(substeps):
            k1 = rhs(y)
            k2 = rhs(y + dt / 2 * k1)
            k3 = rhs(y + dt / 2 * k2)
            k4 = rhs(y + dt * k3)
            y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        step = ca.Function("rk4", [x, u], [y])
        # the NLP model's end state as a function of the start and all rates (single shooting)
        # and its Jacobian: the Newton correction of plan_shooting uses them
        q0s, Us = ca.SX.sym("q0", nq), ca.SX.sym("U", 2 * N)
        xe = ca.vertcat(q0s, 0, 0)
        for k in range(N):
            xe = step(xe, Us[2 * k:2 * k + 2])
        self.end_jacobian = ca.Function("end_jacobian", [q0s, Us],
                                        [ca.jacobian(xe[:nq], Us)])

        # p = [phi0, a (n), b (n), w_dev, w_energy, w_da, dphi]
        P = ca.SX.sym("p", 2 * n + 5)
        phi0, a, b = P[0], P[1:1 + n], P[1 + n:1 + 2 * n]
        w_dev, w_en, w_da, dphi = P[1 + 2 * n], P[2 + 2 * n], P[3 + 2 * n], P[4 + 2 * n]
        ell = b - a
        nrm = ca.sumsqr(ell)
        X = [ca.SX.sym(f"x{k}", nx) for k in range(N + 1)]
        U = [ca.SX.sym(f"u{k}", 2) for k in range(N)]
        w: list[Any] = []
        g: list[Any] = []
        eq: list[bool] = []
        ng: list[int] = []
        f: Any = 0

        def stage_rows(k: int) -> list[tuple[Any, bool]]:
            if k == 0:
                return [(X[0][:nq] - ca.vertcat(phi0, a), True)]
            if k == N:
                rows = [(X[N][1:nq] - b, True)]
                if fixed_phi:
                    rows.append((X[N][0] - phi0 - dphi, True))
                return rows
            d = X[k][1:nq] - a
            along = ca.if_else(nrm > 0, ca.dot(d, ell) ** 2 / ca.fmax(nrm, 1e-300), 0)
            return [(ca.sumsqr(d) - along - X[k][nq], False),
                    ((X[k][1] - (a[0] + (b[0] - a[0]) * k * h)) ** 2 - X[k][nq + 1], False)]

        for k in range(N + 1):
            w.append(X[k])
            if k < N:
                w.append(U[k])
                f += w_en * h * ca.sumsqr(U[k])
                g.append(X[k + 1] - step(X[k], U[k]))  # fatrop wants x_{k+1} - F(x_k, u_k)
                eq += [True] * nx
            rows = stage_rows(k)
            for expr, is_eq in rows:
                g.append(expr)
                eq += [is_eq] * int(expr.shape[0])
            ng.append(sum(int(e.shape[0]) for e, _ in rows))
        f += w_dev * X[N][nq] + w_da * X[N][nq + 1]
        nlp = {"x": ca.vertcat(*w), "p": P, "f": f, "g": ca.vertcat(*g)}
        self.nw = int(nlp["x"].shape[0])
        n_g = int(nlp["g"].shape[0])
        self.equality = np.array(eq)
        self.callback = _DeadlineCallback(self.nw, n_g, int(P.shape[0]))
        ipopt_opts: dict[str, Any] = {
            "ipopt": {"print_level": 0, "sb": "yes", "tol": 1e-8, "acceptable_tol": 1e-6,
                      "max_iter": 300, "max_wall_time": float(MAX_TIME_LIMIT)},
            "print_time": False, "error_on_fail": False, "iteration_callback": self.callback}
        self.solvers: list[tuple[str, Any]] = []
        self.native: native.Library | None = None
        self.compiled = False
        self._native_cfg: native.NativeConfig | None = None
        self._native_opts: dict[str, Any] = {}
        # only the first rung is compiled: the second's C (4-11 MB) takes 10-20 s and up to
        # 1.6 GB to compile, for a rung that runs rarely (and for about a second)
        self.native_ok = (intervals, substeps) == (LADDER[0].intervals, LADDER[0].substeps)
        if ca.has_nlpsol("fatrop"):
            fatrop_opts: dict[str, Any] = {
                "structure_detection": "manual", "nx": [nx] * (N + 1), "nu": [2] * N + [0],
                "ng": ng, "N": N, "equality": eq, "expand": True, "print_time": False,
                "error_on_fail": False,
                "fatrop": {"print_level": 0, "tol": FATROP_TOL, "max_iter": FATROP_MAX_ITER,
                           "mu_init": FATROP_MU_INIT}}
            self.solvers.append(("fatrop", ca.nlpsol("shooting_fatrop", "fatrop", nlp,
                                                     fatrop_opts)))
            # for the same functions compiled (optimizer.native), see load_native
            self._native_opts = {k: v for k, v in fatrop_opts.items() if k != "expand"}
        self.solvers.append(("ipopt", ca.nlpsol("shooting_ipopt", "ipopt", nlp, ipopt_opts)))
        self.lbg = np.where(self.equality, 0.0, -np.inf)
        self.ubg = np.zeros(n_g)
        self.stride = nx + 2
        self.build_time = time.perf_counter() - t0

    def load_native(self, every: float = 1.0, wait: bool = False) -> bool:
        """Use the compiled fatrop functions once their library is built (checked at most
        every ``every`` s; ``wait``: build it now when missing); True when they are in use.

        The library is asked for (:func:`optimizer.native.library_for`: found in the cache,
        or its build started) at the first call after :func:`optimizer.native.configure`, so
        that an NLP built before (the service's forkserver builds it at start-up) gets it too.
        """
        if self.compiled:
            return True
        cfg = native.config()
        if cfg is not self._native_cfg:
            self._native_cfg, self.native = cfg, None
            fatrop = dict(self.solvers).get("fatrop")
            if cfg is not None and fatrop is not None and self.native_ok:
                self.native = native.library_for(native.nlp_source(fatrop), wait=wait)
            every = 0.0
        if self.native is None:
            return False
        path = self.native.ready(every)
        if path is None:
            return False
        try:
            solver = ca.nlpsol("shooting_fatrop", "fatrop", str(path), self._native_opts)
        except Exception:  # noqa: BLE001 - an unloadable library: keep the virtual machine
            self.native = None
            return False
        self.solvers = [("fatrop", solver) if name == "fatrop" else (name, s)
                        for name, s in self.solvers]
        self.compiled = True
        return True

    def guess(self, a: np.ndarray, b: np.ndarray, phi0: float, travel: float) -> np.ndarray:
        """Straight lines in joint space, ``phi`` moving by ``travel``; consistent rates."""
        N, n = self.N, self.n
        s = np.linspace(0.0, 1.0, N + 1)
        Q = np.empty((N + 1, n + 1))
        Q[:, 0] = phi0 + travel * s
        Q[:, 1:] = a + np.outer(s, b - a)
        d = Q[:, 1:] - a
        ell = b - a
        nrm = float(ell @ ell)
        S0 = float(np.max(np.sum(d * d, axis=1) - ((d @ ell) ** 2 / nrm if nrm > 0 else 0.0)))
        W = np.zeros((N + 1, self.stride))
        W[:, :n + 1] = Q
        W[:, n + 1] = max(S0, 0.0) + 1e-4
        W[:, n + 2] = 1e-4
        W[:N, n + 3] = travel
        W[:N, n + 4] = b[0] - a[0]
        return W.ravel()[:self.nw]

    def unpack(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node states ``(N+1, n+1)`` and rates ``(N, 2)`` of a solution vector."""
        W = np.concatenate([w, np.zeros(2)]).reshape(self.N + 1, self.stride)
        return W[:, :self.n + 1].copy(), W[:self.N, self.nx:].copy()


@functools.lru_cache(maxsize=16)
def shooting_nlp(gains: tuple[float, ...], exponents: tuple[int, ...], fixed_phi: bool,
                 intervals: int, substeps: int) -> ShootingNLP:
    """The cached NLP of one robot and transcription (per process)."""
    return ShootingNLP(gains, exponents, fixed_phi, intervals, substeps)


@dataclass(frozen=True)
class ShootingSolution:
    """The NLP's answer in normalised time: node states ``(N+1, n+1)`` and rates ``(N, 2)``."""

    nodes: np.ndarray
    rates: np.ndarray
    status: str
    iterations: int
    start: str
    tried: tuple[dict[str, Any], ...] = ()


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...], *, fixed_phi: bool = False,
            wait: bool = False) -> ShootingNLP:
    """Build (and cache) the first rung's NLP of a robot ahead of its first request; with
    compiled functions configured (:mod:`optimizer.native`) this also starts their build
    (``wait``: builds them before it returns)."""
    tr = LADDER[0]
    nlp = shooting_nlp(tuple(float(k) for k in gains), tuple(int(m) for m in exponents),
                       fixed_phi, tr.intervals, tr.substeps)
    nlp.load_native(every=0.0, wait=wait)
    return nlp


def _node_bounds(req: PlanRequest, region: Region) -> tuple[np.ndarray, np.ndarray]:
    """Per joint: the region's bounds moved in by :data:`MARGIN` (less near start or goal)."""
    a, b = np.array(req.start), np.array(req.goal)
    lo, hi = np.array(region.lower, float), np.array(region.upper, float)
    inner_lo = np.minimum(a, b) - lo
    inner_hi = hi - np.maximum(a, b)
    lo_m = np.where(np.isfinite(lo), lo + np.minimum(MARGIN, 0.5 * inner_lo), -np.inf)
    hi_m = np.where(np.isfinite(hi), hi - np.minimum(MARGIN, 0.5 * inner_hi), np.inf)
    return lo_m, hi_m


def nlp_for(req: PlanRequest, tr: Transcription) -> ShootingNLP:
    """The cached NLP of ``req``'s robot under transcription ``tr``."""
    return shooting_nlp(tuple(req.robot.gains), tuple(int(m) for m in req.robot.exponents),
                        req.phi_change is not None, tr.intervals, tr.substeps)


def solve_shooting(req: PlanRequest, deadline: Any,
                   tr: Transcription = LADDER[0]) -> ShootingSolution:
    """Solve the NLP of transcription ``tr`` for ``req`` (normalised time); raise a typed error
    when it fails.

    Attempts in the order of :data:`ATTEMPTS` (fatrop, then IPOPT; ``phi`` travelling +0.6
    rad, then -0.6 rad in the initial guess); the first converged solution is returned.
    """
    robot = req.robot
    fixed_phi = req.phi_change is not None
    nlp = nlp_for(req, tr)
    n, N = nlp.n, nlp.N
    a, b = np.array(req.start), np.array(req.goal)
    region = Region(robot, "full", req.joint_bounds)
    lo, hi = _node_bounds(req, region)
    lbW = np.full((N + 1, nlp.stride), -np.inf)
    ubW = np.full((N + 1, nlp.stride), np.inf)
    lbW[:, 1:n + 1], ubW[:, 1:n + 1] = lo, hi
    lbW[:, n + 1:n + 3] = 0.0  # the squared deviations' epigraphs
    # rates bounded so that the NLP's RK4 steps stay accurate (see LADDER)
    lbW[:N, nlp.nx:nlp.nx + 2], ubW[:N, nlp.nx:nlp.nx + 2] = -tr.rate_bound, tr.rate_bound
    if fixed_phi:
        lo_phi = hi_phi = float(req.phi_change)  # type: ignore[arg-type]
    else:
        lo_phi, hi_phi = req.phi_change_bounds
        lbW[N, 0], ubW[N, 0] = req.phi_start + lo_phi, req.phi_start + hi_phi
    lbw, ubw = lbW.ravel()[:nlp.nw], ubW.ravel()[:nlp.nw]
    if req.objective == "weighted":
        w_dev, w_en = float(req.weights.d_a), float(req.weights.energy)
        w_da = w_dev
        if w_dev <= 0.0 and w_en <= 0.0:
            raise InvalidRequestError("method 'shooting' with objective 'weighted' needs a "
                                      "positive weights.d_a or weights.energy", field="weights")
    else:
        w_dev, w_en, w_da = DEVIATION_WEIGHT, 1.0, D_A_WEIGHT
    p = np.concatenate([[req.phi_start], a, b,
                        [w_dev, w_en, w_da, req.phi_change if fixed_phi else 0.0]])
    nlp.load_native()
    solvers = dict(nlp.solvers)
    tried: list[dict[str, Any]] = []
    for name, sign in ATTEMPTS:
        solver = solvers.get(name)
        if solver is None:
            continue
        if deadline.remaining <= 1e-3:
            break
        travel = min(max(sign * GUESS_PHI_TRAVEL, lo_phi), hi_phi)
        nlp.callback.stop_at = time.perf_counter() + deadline.remaining
        try:
            sol = solver(x0=nlp.guess(a, b, req.phi_start, travel), p=p, lbx=lbw, ubx=ubw,
                         lbg=nlp.lbg, ubg=nlp.ubg)
        finally:
            nlp.callback.stop_at = math.inf
        stats = solver.stats()
        status = str(stats.get("return_status", "unknown"))
        iters = int(stats.get("iter_count", -1))
        tried.append({"solver": name, "phi_travel_guess": travel, "status": status,
                      "iterations": iters})
        if bool(stats.get("success")):
            nodes, rates = nlp.unpack(np.asarray(sol["x"]).ravel())
            return ShootingSolution(nodes=nodes, rates=rates, status=f"{name}: {status}",
                                    iterations=iters, start=f"phi travel {travel:+.3g} rad",
                                    tried=tuple(tried))
        if status in TIMEOUT:
            raise SolverTimeoutError(
                f"the shooting NLP did not converge within the time limit of "
                f"{deadline.seconds:g} s", field="time_limit",
                diagnostics={"stage": "shooting NLP", "tried": tried})
    if not tried or deadline.remaining <= 1e-3:
        raise SolverTimeoutError(
            f"the shooting NLP did not converge within the time limit of {deadline.seconds:g} s",
            field="time_limit", diagnostics={"stage": "shooting NLP", "tried": tried})
    raise InfeasibleError("the shooting NLP found no path from any start: "
                          + "; ".join(f"{t['solver']} {t['status']}" for t in tried),
                          diagnostics={"blocking": "nlp_failed", "tried": tried})


def output_grid(samples: int, breaks: np.ndarray) -> np.ndarray:
    """Where the path is wanted, in units of ``breaks``: the returned samples, the indicators'
    dense grid and the interval ends (the region check)."""
    T = float(breaks[-1])
    return np.concatenate([np.linspace(0.0, T, int(samples)),
                           np.linspace(0.0, T, INDICATOR_SAMPLES), breaks])


def finish_actuator_plan(req: PlanRequest, schedule: ActuatorSchedule, method: str,
                         planned_nodes: np.ndarray, timing: dict[str, float],
                         diagnostics: dict[str, Any], replay: Any) -> Plan:
    """Check, sample and measure a piecewise-constant-rate plan.

    ``replay`` is the original model integrated under the schedule's rates (cascade quadrature,
    error estimate <= 1e-11 rad, DOP853 as fallback) in normalised time (``t / T``: the model
    is driftless, the path is the same), on :func:`output_grid` of the normalised breaks:
    samples, indicators, the region check at the interval ends (enough, see the module
    docstring) and the terminal error all come from it. ``planned_nodes`` (the NLP's own node
    states) give the verification's ``max_deviation``.

    Raises
    ------
    InfeasibleError
        A node of the true path is outside the region.
    NumericalError
        The true path does not reach the goal.
    """
    robot = req.robot
    T = schedule.duration
    q0 = req.q_start()
    t = np.linspace(0.0, T, int(req.samples))
    td = np.linspace(0.0, T, INDICATOR_SAMPLES)
    rep = replay
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
    # the replay ran in normalised time: int |u|^2 dt = int |U|^2 dtau / T
    energy = rep.energy / T
    ind = dataclasses.replace(compute_indicators(td, qd, None), energy=energy)
    dphi = float(final[0] - q0[0])
    ver = Verification(terminal_error=terminal, phi_error=0.0,
                       max_deviation=float(np.max(np.abs(qb - planned_nodes))),
                       singular=False, final=tuple(float(x) for x in final),
                       rtol=CASCADE_TOL, atol=CASCADE_TOL, energy=energy,
                       integrator=rep.integrator, error_estimate=rep.error_estimate)
    timing["sampling"] = time.perf_counter() - t1
    # the handed-out path is what a controller executes: corrected for its rule and verified
    # by it (optimizer.execution), the breaks in seconds exact in its times
    exe = execute(req, schedule.u, schedule.breaks, T, float(final[0]))
    timing["execution"] = exe.seconds
    return Plan(robot=robot, method=method, phi_change=dphi, duration=T, inputs=schedule,
                chained=None, feasible_phi_changes=[], indicators=ind, margin=margin,
                path=exe.path, verification=ver, timing=timing, diagnostics=diagnostics,
                execution=exe)


def correct_rates(req: PlanRequest, nlp: ShootingNLP, rates: np.ndarray,
                  phi_end: float) -> tuple[np.ndarray, list[float], Any]:
    """Newton steps on the EXACT model that move the NLP's rates onto the goal.

    The NLP integrates with RK4, so the original model under its rates ends 1e-8 to 1e-5 rad
    from the goal. Each step integrates the original model (cascade quadrature, normalised
    time: the model is driftless, so ``T`` does not change the path), and applies the
    minimum-norm change of the rates that cancels the end error to first order, with the
    Jacobian of the NLP's RK4 model (close to the exact one: the error falls by orders of
    magnitude per step). ``phi``'s end is held at the NLP's value (its row is exact).

    Returns
    -------
    rates : ndarray (N, 2)
    errors : list of float
        ``max |th(T) - goal|`` of the exact model before each step and after the last.
    replay : Replay
        The exact model under the returned rates, on :func:`output_grid` (normalised time):
        the plan's verification.
    """
    N = rates.shape[0]
    breaks = np.linspace(0.0, 1.0, N + 1)
    q0 = req.q_start()
    target = np.concatenate([[phi_end], req.goal])
    U = rates.copy()
    errors: list[float] = []
    grid = output_grid(req.samples, breaks)
    best: tuple[float, np.ndarray, Any] | None = None
    for k in range(MAX_CORRECTIONS + 1):
        sched = ActuatorSchedule(breaks=breaks, rates=U)
        rep = integrate_cascade(req.robot, sched.u, q0, 1.0, grid, breaks,
                                fallback=sched.u_scalar)
        if not rep.success:
            break
        r = rep.final - target
        errors.append(float(np.max(np.abs(r[1:]))))
        if best is None or errors[-1] < best[0]:
            best = (errors[-1], U, rep)
        if errors[-1] <= CORRECTION_TARGET or k == MAX_CORRECTIONS:
            break
        J = np.asarray(nlp.end_jacobian(q0, U.ravel()))
        step = J.T @ np.linalg.solve(J @ J.T, r)
        U = U - step.reshape(N, 2)
    if best is None:  # the first integration failed: finish_actuator_plan reports it
        return U, errors, rep
    return best[1], errors, best[2]  # a step that made things worse is not kept


def plan_shooting(req: PlanRequest, deadline: Any) -> Plan:
    """Method ``shooting``: the NLP above, the Newton correction onto the goal of the exact
    model (:func:`correct_rates`), then :func:`finish_actuator_plan`."""
    if req.constraint_points:
        raise InvalidRequestError(
            "method 'shooting' takes no constraint points (they are points of the chained "
            "polynomial inputs: use 'polynomial' or 'constraint_points')",
            field="constraint_points")
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    failures: list[str] = []
    tried: list[dict[str, Any]] = []
    for tr in LADDER:
        try:
            sol = solve_shooting(req, deadline, tr)
            break
        except InfeasibleError as exc:  # a finer transcription may still converge
            failures.append(f"{tr.intervals} intervals: {exc.message}")
            tried.extend(exc.diagnostics.get("tried", []))
    else:
        raise InfeasibleError("; ".join(failures),
                              diagnostics={"blocking": "nlp_failed", "tried": tried})
    timing["nlp"] = time.perf_counter() - t0
    deadline.check("the shooting NLP")
    t1 = time.perf_counter()
    nlp = nlp_for(req, tr)
    rates, errors, replay = correct_rates(req, nlp, sol.rates, float(sol.nodes[-1, 0]))
    timing["correction_and_verification"] = time.perf_counter() - t1
    T = req.duration_for_rates(np.max(np.abs(rates), axis=0))
    N = rates.shape[0]
    schedule = ActuatorSchedule(breaks=np.linspace(0.0, T, N + 1), rates=rates / T)
    diagnostics = {"objective": req.objective, "singularity": "full",
                   "shooting": {"intervals": N, "rk4_substeps": tr.substeps,
                                "rate_bound": tr.rate_bound,
                                "status": sol.status, "iterations": sol.iterations,
                                "start": sol.start, "tried": tried + list(sol.tried),
                                # the answering solver evaluated compiled C (optimizer.native)
                                "compiled": nlp.compiled and sol.status.startswith("fatrop"),
                                "terminal_error_per_correction": errors}}
    return finish_actuator_plan(req, schedule, "shooting", sol.nodes, timing, diagnostics,
                                replay=replay)


__all__ = ["ActuatorSchedule", "ShootingNLP", "plan_shooting", "finish_actuator_plan",
           "prepare", "solve_shooting"]
