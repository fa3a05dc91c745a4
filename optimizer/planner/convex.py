"""Constraint-point synthesis as a convex QP (issue 3.3): the paper's trial and error, automated.

The paper's §3.3 avoids the transformation singularity by *choosing* constraint points
``(t_j, z_i(t_j))`` by hand and re-solving eq (11) until the path is singularity-free. Here the
choice is made by a QP.

Formulation (fixed ``dphi``)
----------------------------
With ``V1 = dphi`` (normalised time ``tau = t / T``) the chained state is affine in the
coefficients of ``V2`` (eq 10, :func:`optimizer.steering.affine_basis`). ``V2`` gets degree
``n - 1 + m`` (``m`` extra coefficients beyond the paper's ``n``, plus one per constraint point
of the request), written in the orthonormal shifted-Legendre basis
``V2(tau) = sum_j x_j sqrt(2j+1) P_j(2 tau - 1)``:

* energy: ``int_0^1 V2^2 dtau = x^T (L^T H L) x = ||x||^2`` exactly, ``H_ij = 1/(i+j+1)`` the
  Gram matrix of the monomials and ``L`` the basis change (:func:`legendre_to_monomial`). In
  monomials ``H`` is a Hilbert matrix (condition ~1e10 at degree 8); here the Hessian is ``I``;
* goal (and the request's constraint points): linear equalities ``A_eq x = b_eq``, eliminated
  exactly, ``x = x_p + N y`` (``x_p`` minimum-norm, ``N`` an orthonormal null-space basis): the
  goal is met to rounding error, never to a solver tolerance, and ``||x||^2 = ||x_p||^2 +
  ||y||^2``. The QP is in ``y`` (``m`` variables) with inequalities only;
* affine parts of the region, on a Chebyshev grid of tau (dense near the ends, where paths
  start and end close to the boundary): ``z_{n-1} <= -mu`` (for n = 3 the paper's ``z2 < 0``,
  eq 13; for n >= 4 ``z2`` is not sign-definite on the region: on random points of the 4-joint
  region it ranges over (-1.68, 1.11); the exact sign condition is ``z_{n-1} = a_{n-1} w_{n-1}
  < 0``, th_{n-2} < pi/2), ``K_n cos(hi - rho)^m_n <= z_n <= K_n cos(lo + rho)^m_n`` (th_{n-1}
  inside its bounds by ``rho``) and, with joint bounds, ``lo + rho <= z_{n+1} = th_n <= hi - rho``.

A fact that organises the rest: without inequalities the least-energy ``V2`` meeting the goal is
the paper's own quadratic (degree ``n - 1``) member, because the goal functionals are
``int_0^1 V2(s) (dphi (1 - s))^k / k! ds`` and the minimum-norm solution lies in their span. So
wherever the paper's member is singularity-free it is the QP's optimum (the margins are capped
at its own, see below, so that it stays feasible), and the QP departs from it exactly where the
paper would need constraint points.

Non-affine part and cuts
------------------------
``th_1..th_{n-2}`` in their ranges, i.e. ``w_k = cos(th_{k-1})^m_k`` inside
``[cos(hi - rho)^m, cos(lo + rho)^m]`` for k = 2..n-1, is enforced by an exact post-check of the
continuous path (:meth:`optimizer.region.Region.check_path`) plus cutting planes. With
``z_k = a_k w_k + b_k`` (``a_k``, ``b_k`` functions of the levels above, compiled with CasADi in
:class:`LevelMaps`; ``sign a_k = (-1)^(n-k)`` on the region), ``w_k <= c`` reads
``h(z) = s (z_k - b_k(z) - c a_k(z)) <= 0``. Where the solution violates, or comes within
:data:`MARGIN_SLACK` of, a target on the grid or at the checker's worst point, ``h`` is
linearised at the current ``z(tau)`` and added as an affine row; the QP is solved again
(at most :data:`MAX_CUT_ROUNDS` rounds).

* Level n-1, side ``th_{n-2} > lo`` (for n = 3: ``th1 > 0``, ``h = -z2 - c A c2^2 s2``): ``h``
  is convex (``g(z3) = A c2^2 s2`` is concave on (0, K3); checked on 1e5 points and on random
  segments for n = 3, 4, 5), so its cuts are valid outer approximations and accumulate
  (Kelley): no feasible path is ever cut off, and an infeasible QP proves the ``dphi``
  infeasible (for the degree, grid and margins).
* The other levels (n >= 4) and sides are not convex (15-20 % of random segments violate the
  midpoint inequality): their cuts are re-linearised at the latest solution (one per tau, level
  and side) instead of accumulated, since an old tangent may cut off feasible paths. For
  n >= 4 the first QP is seeded with tangents at the straight joint-space path (inside the
  region); when that fails the unseeded Kelley start is tried too, and (energy objective) the
  paper's member is returned when it is feasible and the cuts did worse (``source``).

Margins: ``rho`` <= :data:`ANGLE_MARGIN` and ``mu`` <= :data:`SIGN_MARGIN`, both capped by what
the start and goal have (``rho`` <= half their angle margin, ``mu`` <= :data:`SIGN_FRACTION` of
their ``-z_{n-1}``: a start at ``th = 1 deg`` allows ``rho`` = 0.5 deg, ``mu`` = 0.0033), and,
for the energy objective, by the paper's member's own margins when it is singularity-free.
``mu`` is small on purpose: ``z2 = -A c1^2 c2^2 s2`` is small wherever th2 is small, so a large
``mu`` forces th2 to rise early and cuts off paths that exist.

Choice of ``dphi``
------------------
``req.phi_change`` when given. Otherwise a scan inside the request's bounds cut to the motion's
sign and to the open interval that a constant ``v1`` needs (:func:`necessary_dphi_range`: each
th_i, i >= 2, moves monotonically with ``|th_i'| = K_i cos(th_{i-1})^m_i |u1|`` and th_{i-1}
between its start and goal values for i >= 3); :data:`MIN_SCAN_NODES` to :data:`MAX_SCAN_NODES`
uniform interior nodes, plus three nodes inside each singularity-free interval of the paper's
family (:func:`family_intervals`; they are part of the QP's feasible set, and for n >= 4 can be
hundredths of a degree wide, too narrow for any uniform scan), so the method succeeds whenever
the paper's does;
each feasible node is ranked by the request's objective rule on its cheap indicators (t_p, d_a,
|dphi|, energy, computed as finish_plan does), then the best is refined by bounded Brent
minimisation between its neighbours (bisection toward the smallest ``|dphi|`` for
``tp_then_sensitivity``). If nothing is feasible, ``m`` goes up the ladder :data:`EXTRA_DEGREES`.

The §3.3 example (th from [1, 1, 1] to [30, 30, 30] deg, prototype robot): th2 must rise 29 deg
at a rate <= K2 |u1|, and th3's gain is largest when th2 stays at 1 deg as long as possible and
smallest when it rises at once, which bounds ``dphi`` to (45.0, 51.6) deg for ANY input; the
paper's member crosses ``z2 = 0`` twice (its Fig 4) for dphi < 45.46 deg. So the paper's
situation exists only in (45.0, 45.46) deg: at 45.3 deg the QP (m = 4, one cut round) gives a
path with margin 0.40 deg (th1 starts at 1 deg) in ~15 ms of synthesis. The QP is feasible on
[45.2, 50.2] deg (m = 4; to 50.7 with m = 6) against the family's [45.46, 47.53].

Constraint points, as the paper would state them: ``m`` extra coefficients are fixed by ``m``
points; ``diagnostics["constraint_points"]["points"]`` lists ``z2`` of the QP path at
``t_j = j T / (m + 1)``. Given to :func:`optimizer.steering.solve_polynomial` (eq 11) they
reproduce the QP's ``V2`` (the relative reproduction error is reported; ~1e-12).

Backend
-------
Clarabel through its own Python API (``clarabel.DefaultSolver``, scipy.sparse CSC), with one
solver per problem shape kept per thread and updated in place (``solver.update``; presolve off,
structural zeros kept so the pattern never changes). ``bench/qp_backends.py`` measured, on the
base QP of the §3.3 example at 50 values of ``dphi`` x 5 passes, interleaved (a 2-core machine
shared with other jobs), median per solve from the assembled ``(G, h)`` to the solution:

    m = 4, 160 grid points (4 variables, 480 rows):   persistent 1.70 ms, fresh 2.06 ms,
                                                       cvxpy + DPP Parameters 2.66 ms
    m = 6, 320 grid points (6 variables, 960 rows):   persistent 5.11 ms, fresh 5.84 ms,
                                                       cvxpy + DPP Parameters 6.47 ms

(the three agree to 1e-11; the assembly itself, common to all, takes ~1.5 ms). cvxpy's problem
is built once per (n, m, grid size) and re-solves skip canonicalisation, but its per-solve
parameter mapping and solution retrieval cost more than Clarabel's own setup at this size, so
the direct API is kept; ``solve_qp(..., persistent=False)`` switches solver reuse off
(:mod:`.qp` holds the Clarabel wrapper).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import casadi as ca
import numpy as np
from numpy.polynomial import legendre as Leg
from numpy.polynomial import polynomial as P
from scipy.linalg import null_space
from scipy.optimize import minimize_scalar

from ..chained_form import ChainedForm, chained_form
from ..errors import InfeasibleError, SingularSystemError
from ..indicators import compute_indicators
from ..model import Robot
from ..problem import PlanRequest
from ..region import PathCheck, Region
from ..results import Plan
from ..steering import (MIN_ABS_DPHI, ChainedPath, ConstraintPoint, InputSchedule, affine_basis,
                        solve_polynomial)
from . import qp
from .family import SEARCH_SAMPLES, PolynomialFamily
from .intervals import feasible_intervals
from .base import Capabilities, Method
from .context import Deadline, PlanContext
from .finish import finish_plan
from .rules import direction_conflict, make_region, phi_search_bounds

#: Extra V2 coefficients tried in turn until some dphi is feasible (the paper's m).
EXTRA_DEGREES = (4, 6)
#: Interior Chebyshev points of tau carrying the affine constraints and the cuts.
GRID_POINTS = 160
#: Rounds of cutting planes after the first QP before a dphi is declared infeasible.
MAX_CUT_ROUNDS = 15
#: Target distance (rad) of th_1..th_{n-1} from their bounds (capped by the endpoints' own).
ANGLE_MARGIN = math.radians(2.0)
#: Target margin of the sign condition z_{n-1} <= -mu (z units), and its cap as a fraction of
#: the endpoints' own ``-z_{n-1}``. Kept small on purpose: ``z2 = -A c1^2 c2^2 s2`` is small
#: wherever th2 is small, so a large mu forces th2 to rise early and cuts off paths that exist
#: (the §3.3 example near dphi = 45.3 deg needs th2 to stay near 1 deg for a while; with
#: mu = 0.0165 the QP there is infeasible). The angle margin rho (cuts) is what keeps th_{n-2}
#: away from pi/2.
SIGN_MARGIN = 0.01
SIGN_FRACTION = 0.1
#: Share of the largest sign margin kept by the "margin" objective before minimising energy.
MARGIN_KEEP = 0.9
#: Relative shortfall of the angle margin tolerated without another cut round.
MARGIN_SLACK = 0.1
#: Scan spacing of dphi and the smallest and largest number of uniform scan nodes.
SCAN_STEP = math.radians(0.5)
MIN_SCAN_NODES = 8
MAX_SCAN_NODES = 40
#: Refinement of the best dphi node (rad) and its evaluation budget.
REFINE_XATOL = 1e-5
REFINE_MAXITER = 30
#: Seconds kept in reserve for finish_plan (sampling, re-integration) when refining.
FINISH_RESERVE = 0.5
BACKEND = "clarabel (direct Python API, scipy.sparse CSC, solver reused per shape)"


# ---------------------------------------------------------------------- small building blocks
@functools.lru_cache(maxsize=32)
def legendre_to_monomial(p: int) -> np.ndarray:
    """``L`` (p, p): column j = the powers-of-tau coefficients of ``sqrt(2j+1) P_j(2 tau - 1)``.

    These shifted Legendre polynomials are orthonormal on [0, 1], so
    ``L.T @ gram_monomials(p) @ L = I`` (exactly; in floating point only to ~1e-6 at p = 9
    because ``gram_monomials`` is a Hilbert matrix: which is why the QP works in this basis).
    """
    L = np.zeros((p, p))
    shift = np.array([-1.0, 2.0])  # x = 2 tau - 1
    for j in range(p):
        cx = Leg.leg2poly(np.eye(p)[j][: j + 1])  # P_j in powers of x
        ct = np.zeros(1)
        xp = np.ones(1)
        for c in cx:  # Horner-free expansion: sum_i c_i (2 tau - 1)^i
            ct = P.polyadd(ct, c * xp)
            xp = P.polymul(xp, shift)
        L[: ct.size, j] = math.sqrt(2 * j + 1) * ct
    return L


def gram_monomials(p: int) -> np.ndarray:
    """``H_ij = int_0^1 tau^i tau^j dtau = 1 / (i + j + 1)``: ``int V2^2 dtau = a^T H a``."""
    i = np.arange(p)
    return 1.0 / (i[:, None] + i[None, :] + 1.0)


@functools.lru_cache(maxsize=16)
def chebyshev_grid(N: int) -> np.ndarray:
    """``N`` interior Chebyshev-Lobatto points of (0, 1), increasing (dense near the ends)."""
    k = np.arange(1, N + 1)
    return 0.5 * (1.0 - np.cos(np.pi * k / (N + 1)))


class LevelMaps:
    """``a_k(z)``, ``b_k(z)`` and their gradients for the nonlinear levels k = 2..n-1.

    ``z_k = a_k w_k + b_k`` with ``w_k = cos(th_{k-1})^m_k`` (see :mod:`optimizer.chained_form`);
    ``a_k``, ``b_k`` depend on ``z_{k+1}..z_{n+1}`` through the top-down inverse map, so they are
    defined wherever the levels above k are inside the region. Compiled once per robot with
    CasADi (symbolic Jacobians), evaluated column-wise on many points at once.
    """

    def __init__(self, cf: ChainedForm) -> None:
        n = cf.n
        self.n = n
        self.levels = list(range(2, n))  # nonlinear levels (level n is z_n = K_n w_n, affine)
        sym = cf.symbolic
        z = ca.SX.sym("z", n + 1)
        th, _ = sym.inverse_expr(z)
        qv = ca.vertcat(z[0], *th)
        a = ca.vertcat(*[sym.a[k](qv) for k in self.levels])
        b = ca.vertcat(*[sym.b[k](qv) for k in self.levels])
        self._f = ca.Function("levels", [z], [a, b, ca.jacobian(a, z), ca.jacobian(b, z)])

    def __call__(self, Z: np.ndarray) -> tuple[np.ndarray, ...]:
        """For points ``Z`` (N, n+1): ``a, b`` (N, L) and ``Ja, Jb`` (N, L, n+1), L = n - 2.

        Entries are NaN where a level above is outside the region (the inverse is undefined).
        """
        N = Z.shape[0]
        nl = len(self.levels)
        with np.errstate(all="ignore"):
            a, b, Ja, Jb = (np.asarray(x) for x in self._f(Z.T))
        a = a.reshape(nl, N).T
        b = b.reshape(nl, N).T
        Ja = Ja.reshape(nl, N, self.n + 1).transpose(1, 0, 2)
        Jb = Jb.reshape(nl, N, self.n + 1).transpose(1, 0, 2)
        return a, b, Ja, Jb


@functools.lru_cache(maxsize=32)
def level_maps(robot: Robot) -> LevelMaps:
    """Cached :class:`LevelMaps` of ``robot``."""
    return LevelMaps(chained_form(robot))


def solve_qp(G: np.ndarray, h: np.ndarray, margin_column: np.ndarray | None = None,
             margin_cap: float = np.inf, regularisation: float = 1e-4,
             persistent: bool = True) -> tuple[str, np.ndarray | None, float]:
    """``min 1/2 ||y||^2  s.t.  G y <= h`` with Clarabel's Python API (``persistent``: reuse
    the solver of the same shape, updated in place, :func:`.qp.solve_nonneg_persistent`).

    With ``margin_column`` (one entry per row of ``G``) the margin variant is solved instead:
    ``min -t + regularisation/2 ||y||^2  s.t.  G y + margin_column t <= h,  t <= margin_cap``.

    Returns
    -------
    status : str
        Clarabel's status name (``"Solved"``, ``"PrimalInfeasible"``, ...).
    y : ndarray or None
        The solution (without ``t``) when the status is Solved or AlmostSolved.
    t : float
        The margin variable (NaN without ``margin_column``).
    """
    r, d = G.shape
    if margin_column is not None:
        G = np.hstack([G, margin_column[:, None]])
        cap = np.zeros((1, d + 1))
        cap[0, -1] = 1.0
        G = np.vstack([G, cap])
        h = np.append(h, min(margin_cap, 1e6))
        Pd = np.append(np.full(d, regularisation), 0.0)
        q = np.zeros(d + 1)
        q[-1] = -1.0
    else:
        Pd = np.ones(d)
        q = np.zeros(d)
    # rows independent of y: feasible or not, they need no solver
    nrm = np.linalg.norm(G, axis=1)
    keep = nrm > 1e-14 * max(1.0, float(nrm.max(initial=0.0)))
    if np.any(h[~keep] < -1e-12):
        return "PrimalInfeasible", None, math.nan
    G, h, nrm = G[keep], h[keep], nrm[keep]
    # row scaling: rows of z_{n+1} carry dphi^(n-1); Clarabel equilibrates too, this is cheap help
    G = G / nrm[:, None]
    h = h / nrm
    sol = qp.solve_nonneg_persistent(Pd, q, G, h) if persistent else qp.solve(
        qp.diagonal(Pd), q, qp.dense_csc(G), h)
    status = str(sol.status).split(".")[-1]
    if status not in ("Solved", "AlmostSolved"):
        return status, None, math.nan
    x = np.asarray(sol.x, float)
    if margin_column is not None:
        return status, x[:d], float(x[d])
    return status, x, math.nan


def _single(dphi: float, v2: np.ndarray, duration: float) -> InputSchedule:
    """One polynomial piece on [0, 1] with ``V1 = dphi`` constant."""
    return InputSchedule(np.array([0.0, 1.0]), (np.array([float(dphi)]),),
                         (np.asarray(v2, float),), float(duration))


# ---------------------------------------------------------------------- results
@dataclass
class Synthesis:
    """Outcome of the QP with cuts at one ``dphi``.

    Attributes
    ----------
    dphi : float
    ok : bool
        The continuous path passed the full region check.
    inputs : InputSchedule or None
        ``V1 = dphi``, ``V2`` in monomials of tau (when ok).
    status : str
        Clarabel's status of the last QP solved.
    rounds : int
        Cut rounds after the first QP.
    cuts : int
        Cutting planes added in all.
    qp_solves : int
    energy : float
        ``int_0^1 V2^2 dtau`` (the QP objective), inf when not ok.
    region_margin : float
        Full-region margin of the continuous path (rad), ``-inf`` when there is no path.
    argmin_tau : float
    sign_margin, angle_margin : float
        ``mu`` and ``rho`` used.
    plain_ok : bool
        The paper's plain member at this ``dphi`` is singularity-free.
    plain_energy : float
        Its ``int V2^2 dtau`` (inf when not ok).
    reason : str
        Why it failed (empty when ok).
    solve_time : float
        Seconds spent in Clarabel.
    qp_margin : float
        The largest sign margin ``t`` found by the "margin" objective (NaN otherwise).
    extra_degrees : int
        ``m`` of the QP.
    source : {"qp", "plain_member"}
        Where ``inputs`` come from (see the module docstring, n >= 4 safety net).
    score : tuple of float
        The request's objective rule on ``indicators`` (lower is better; set by the scan).
    indicators : dict
        ``t_p``, ``d_a``, ``sensitivity``, ``energy`` of the path (set by the scan).
    """

    dphi: float
    ok: bool = False
    inputs: InputSchedule | None = None
    status: str = "not solved"
    rounds: int = 0
    cuts: int = 0
    qp_solves: int = 0
    energy: float = math.inf
    region_margin: float = -math.inf
    argmin_tau: float = math.nan
    sign_margin: float = math.nan
    angle_margin: float = math.nan
    qp_margin: float = math.nan
    plain_ok: bool = False
    plain_energy: float = math.inf
    reason: str = ""
    solve_time: float = 0.0
    extra_degrees: int = 0
    source: str = "qp"
    score: tuple[float, float] = (math.inf, math.inf)
    indicators: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------- the synthesiser
class ConstraintPointQP:
    """The QP with cuts of one request: start, goal, duration, joint bounds, constraint points.

    Parameters
    ----------
    req : PlanRequest
    extra_degrees : int
        ``m``: coefficients of ``V2`` beyond the ``n`` of the paper's family (and beyond one per
        request constraint point).
    grid : int
        Interior Chebyshev points of tau.
    objective : {"energy", "margin"}
        Minimise ``int V2^2 dtau`` with the margins fixed; or first maximise the sign margin
        ``t`` (``z_{n-1} <= -t``, at most ``margin_cap`` and the endpoints' ``-z_{n-1}``), then
        minimise the energy keeping :data:`MARGIN_KEEP` of it (two QPs per round).
    angle_margin, sign_margin : float
        Targets ``rho`` (rad) and ``mu`` (before the caps described in the module docstring).
    max_rounds : int
        Cut rounds after the first QP.
    margin_cap : float
        Upper bound of the "margin" objective's ``t``.
    seed_cuts : bool
        For n >= 4, seed the non-convex levels with tangents at the straight joint-space path
        (an unseeded attempt follows when the seeded one fails).
    """

    def __init__(self, req: PlanRequest, extra_degrees: int = EXTRA_DEGREES[0],
                 grid: int = GRID_POINTS, objective: str = "energy",
                 angle_margin: float = ANGLE_MARGIN, sign_margin: float = SIGN_MARGIN,
                 max_rounds: int = MAX_CUT_ROUNDS, margin_cap: float = math.inf,
                 seed_cuts: bool = True) -> None:
        if objective not in ("energy", "margin"):
            raise ValueError(f"objective must be 'energy' or 'margin', not {objective!r}")
        if extra_degrees < 1:
            raise ValueError("extra_degrees must be >= 1 (else there is nothing to optimise)")
        self.req = req
        self.robot = req.robot
        self.n = n = req.n
        self.cf = chained_form(req.robot)
        self.levels = level_maps(req.robot) if n > 2 else None
        self.T = req.duration_or_default
        self.z0 = self.cf.to_chained(req.q_start())
        self.zT = self.cf.to_chained(req.q_goal(0.0))
        self.points: tuple[ConstraintPoint, ...] = tuple(req.constraint_points)
        self.m = int(extra_degrees)
        self.p = n + len(self.points) + self.m
        self.L = legendre_to_monomial(self.p)
        self.grid = chebyshev_grid(int(grid))
        self.objective = objective
        self.max_rounds = int(max_rounds)
        self.margin_cap = float(margin_cap)
        self.seed_cuts = bool(seed_cuts)
        self.region: Region = make_region(req, "full")
        self.lower = self.region.lower.copy()
        self.upper = self.region.upper.copy()
        K = np.array(self.robot.gains)
        mexp = np.array(self.robot.exponents, float)
        self.K = K
        self.mexp = mexp
        # endpoint margins cap the targets: a constraint stricter than the endpoints themselves
        # would be infeasible next to them (or force absurd slopes)
        th_ends = np.array([req.start, req.goal])[:, : n - 1]
        end_angle = float(np.min(np.minimum(th_ends - self.lower[: n - 1],
                                             self.upper[: n - 1] - th_ends)))
        if self.region.has_custom_bounds and np.isfinite(self.lower[n - 1]):
            thn = np.array([req.start[n - 1], req.goal[n - 1]])
            end_angle = min(end_angle, float(np.min(np.minimum(thn - self.lower[n - 1],
                                                               self.upper[n - 1] - thn))))
        end_sign = float(min(-self.z0[n - 2], -self.zT[n - 2]))  # -z_{n-1} at the ends
        self.end_sign = end_sign
        self.angle_target = max(0.0, min(angle_margin, 0.5 * end_angle))
        self.sign_target = max(0.0, min(sign_margin, SIGN_FRACTION * end_sign))
        self._cache: dict[float, Synthesis] = {}

    # ------------------------------------------------------------------ helpers
    def thresholds(self, rho: float) -> tuple[np.ndarray, np.ndarray]:
        """``(w_lo, w_hi)`` per level k = 2..n: ``th_{k-1}`` in ``[lo + rho, hi - rho]``."""
        n = self.n
        lo = self.lower[: n - 1] + rho
        hi = self.upper[: n - 1] - rho
        m = self.mexp
        w_hi = np.cos(np.clip(lo, 0.0, 0.5 * math.pi)) ** m
        w_lo = np.cos(np.clip(hi, 0.0, 0.5 * math.pi)) ** m
        return w_lo, w_hi

    def equality(self, dphi: float) -> tuple[np.ndarray, np.ndarray]:
        """``A_eq x = b_eq``: the goal (eq 11 without points) and the request's points."""
        n = self.n
        taus = np.array([1.0] + [cp.time / self.T for cp in self.points])
        free, basis = affine_basis(dphi, n, self.z0, self.p, taus)
        BL = basis @ self.L
        rows = [BL[0]]
        rhs = [self.zT[1:] - free[0]]
        for j, cp in enumerate(self.points):
            kk = cp.state - 2
            rows.append(BL[j + 1, kk][None, :])
            rhs.append(np.array([cp.value - free[j + 1, kk]]))
        return np.vstack(rows), np.concatenate(rhs)

    def inputs_from(self, dphi: float, x: np.ndarray) -> InputSchedule:
        """``V1 = dphi``, ``V2`` in monomials of tau from the orthonormal coefficients ``x``."""
        return _single(dphi, self.L @ x, self.T)

    def plain(self, dphi: float) -> tuple[bool, float, float, float]:
        """The paper's member (degree n - 1 + points) at ``dphi``.

        Returns ``(ok, energy, angle margin, sign margin)``: passes the full check, its
        ``int V2^2 dtau``, its region margin (rad) and ``-max z_{n-1}`` over [0, 1].
        """
        try:
            inp = solve_polynomial(dphi, self.n, self.z0, self.zT, self.T, self.points)
        except SingularSystemError:
            return False, math.inf, -math.inf, -math.inf
        path = ChainedPath.from_inputs(self.z0, inp)
        chk = self.region.check_path(path)
        if not chk.ok:
            return False, math.inf, chk.margin, -math.inf
        a = inp.v2[0]
        energy = float(a @ gram_monomials(a.size) @ a)
        # exact max of the polynomial z_{n-1}: ends and critical points
        c = path.polys[0][self.n - 2]
        crit = P.polyroots(P.polyder(c)) if c.size > 2 else np.zeros(0)
        crit = crit[np.abs(crit.imag) < 1e-9].real
        crit = crit[(crit >= 0.0) & (crit <= 1.0)]
        zmax = float(np.max(P.polyval(np.concatenate([[0.0, 1.0], crit]), c)))
        return True, energy, float(chk.margin), -zmax

    # ------------------------------------------------------------------ one dphi
    def solve(self, dphi: float) -> Synthesis:
        """The QP with cuts at ``dphi`` (memoised)."""
        key = float(dphi)
        if key not in self._cache:
            s = self._solve(key, self.seed_cuts)
            if not s.ok and self.n >= 4 and self.seed_cuts:
                # the seeded tangents of the non-convex levels are inner approximations that
                # can exclude every path: try again from the plain Kelley start
                s2 = self._solve(key, False)
                s2.qp_solves += s.qp_solves
                s2.solve_time += s.solve_time
                s = s2 if s2.ok else s
            if s.plain_ok and self.objective == "energy" and (
                    not s.ok or s.energy > s.plain_energy * (1.0 + 1e-9)):
                # the paper's member is the unconstrained minimum-energy input, feasible here:
                # a non-convex cut artefact (n >= 4) must not make the answer worse than it
                s = self._plain_synthesis(s)
            self._cache[key] = s
        return self._cache[key]

    def _plain_synthesis(self, s: Synthesis) -> Synthesis:
        inp = solve_polynomial(s.dphi, self.n, self.z0, self.zT, self.T, self.points)
        v2 = np.zeros(self.p)
        v2[: inp.v2[0].size] = inp.v2[0]
        inputs = _single(s.dphi, v2, self.T)
        chk = self.region.check_path(ChainedPath.from_inputs(self.z0, inputs))
        s.ok, s.inputs, s.energy = True, inputs, s.plain_energy
        s.region_margin, s.argmin_tau = float(chk.margin), float(chk.argmin_tau)
        s.source, s.reason = "plain_member", ""
        return s

    def setup(self, dphi: float) -> dict[str, Any]:
        """Everything of the QP at ``dphi`` that does not change between cut rounds.

        Returns a dict with the margins ``rho``, ``mu`` (after the caps), the level thresholds
        ``w_lo``, ``w_hi``, the eliminated equality (``x_p``, null-space basis ``N``), the affine
        row specification and the plain member's facts; ``error`` is set when the goal and the
        request's points leave no freedom.
        """
        n = self.n
        plain_ok, plain_energy, plain_angle, plain_sign = self.plain(dphi)
        rho, mu = self.angle_target, self.sign_target
        if plain_ok and self.objective == "energy":
            # keep the paper's member feasible for the QP, so the QP never does worse (energy)
            rho = min(rho, plain_angle * (1.0 - 1e-6))
            mu = min(mu, plain_sign * (1.0 - 1e-6))
        w_lo, w_hi = self.thresholds(rho)
        Aeq, beq = self.equality(dphi)
        x_p, *_ = np.linalg.lstsq(Aeq, beq, rcond=None)
        Nsp = null_space(Aeq)
        error = None
        if Nsp.shape[1] == 0 or np.linalg.norm(Aeq @ x_p - beq) > 1e-9 * (1 + np.linalg.norm(beq)):
            error = "the goal and constraint points leave no freedom (singular system)"
        # affine rows (column kk of z2..z_{n+1}, sign, bound): sign * z_{kk+2}(tau) <= bound;
        # z_{n-1} <= -mu, K_n w_lo_n <= z_n <= K_n w_hi_n, and the optional th_n bounds
        Kn = self.K[-1]
        affine: list[tuple[int, float, float]] = [(n - 3, 1.0, -mu),
                                                  (n - 2, 1.0, Kn * w_hi[-1]),
                                                  (n - 2, -1.0, -Kn * w_lo[-1])]
        if self.region.has_custom_bounds:
            lo_n, hi_n = self.lower[n - 1], self.upper[n - 1]
            if np.isfinite(hi_n):
                affine.append((n - 1, 1.0, hi_n - rho))
            if np.isfinite(lo_n):
                affine.append((n - 1, -1.0, -(lo_n + rho)))
        return {"dphi": dphi, "rho": rho, "mu": mu, "w_lo": w_lo, "w_hi": w_hi, "x_p": x_p,
                "N": Nsp, "affine": affine, "plain_ok": plain_ok, "plain_energy": plain_energy,
                "error": error}

    def assemble(self, st: dict[str, Any], extra_taus: Sequence[float] = (),
                 cut_list: Sequence[tuple[float, np.ndarray, float]] = ()
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``G_y y <= h_y`` in the null-space coordinates ``y`` (``x = x_p + N y``), and the
        column marking the sign rows ``z_{n-1} <= -mu`` (for the margin objective)."""
        n = self.n
        taus_aff = np.concatenate([self.grid, np.asarray(extra_taus, float)])
        taus = np.concatenate([taus_aff, np.array([c[0] for c in cut_list])])
        free, basis = affine_basis(st["dphi"], n, self.z0, self.p, taus)
        BL = basis @ self.L  # (Nt, n, p): z(tau) = free + BL x
        Na = taus_aff.size
        G_rows, h_rows, marg = [], [], []
        for kk, sgn, bound in st["affine"]:
            G_rows.append(sgn * BL[:Na, kk])
            h_rows.append(bound - sgn * free[:Na, kk])
            marg.append(np.full(Na, 1.0 if (kk == n - 3 and sgn > 0) else 0.0))
        if len(cut_list):
            g = np.array([c[1] for c in cut_list])  # (C, n)
            G_rows.append(np.einsum("ck,ckp->cp", g, BL[Na:]))
            h_rows.append(np.array([c[2] for c in cut_list]) - np.einsum("ck,ck->c", g, free[Na:]))
            marg.append(np.zeros(len(cut_list)))
        G = np.vstack(G_rows)
        h = np.concatenate(h_rows)
        return G @ st["N"], h - G @ st["x_p"], np.concatenate(marg)

    def _solve(self, dphi: float, seed: bool) -> Synthesis:
        n = self.n
        out = Synthesis(dphi=dphi, extra_degrees=self.m)
        if not math.isfinite(dphi) or abs(dphi) < MIN_ABS_DPHI:
            out.reason = "phi_change is 0 (steering system singular, Remark 2)"
            return out
        st = self.setup(dphi)
        out.plain_ok, out.plain_energy = st["plain_ok"], st["plain_energy"]
        rho, mu, w_lo, w_hi = st["rho"], st["mu"], st["w_lo"], st["w_hi"]
        out.angle_margin, out.sign_margin = rho, mu
        if st["error"]:
            out.reason = st["error"]
            return out
        x_p, Nsp = st["x_p"], st["N"]
        extra_taus: list[float] = []
        # cuts g . z(tau) <= rhs (g over z2..z_{n+1}). Cuts of the convex conditions (level
        # n-1, th_{n-2} > lo) accumulate (Kelley: each is a valid outer approximation); the
        # others are re-linearised at the latest solution (one cut per tau, level and side)
        # because an old tangent of a non-convex condition may cut off feasible paths.
        cuts: dict[tuple, tuple[float, np.ndarray, float]] = {}
        if n >= 4 and seed:
            # seed the non-convex levels with tangents at the straight joint-space path, which
            # lies inside the region (a box): the first QP then starts from a sensible model
            # of th_1..th_{n-3} instead of from a path that may be far outside
            q0, qT = self.req.q_start(), self.req.q_goal(dphi)
            Zr = self.cf.to_chained(q0 + self.grid[:, None] * (qT - q0))
            self._add_cuts(cuts, Zr, self.grid, w_lo, w_hi, None, seed=True)
        best: tuple[float, InputSchedule, PathCheck] | None = None
        t_solve = 0.0
        chk = None
        for rnd in range(self.max_rounds + 1):
            taus_aff = np.concatenate([self.grid, np.array(extra_taus)])
            Gy, hy, mcol = self.assemble(st, extra_taus, list(cuts.values()))
            t0 = time.perf_counter()
            t_marg = math.nan
            if self.objective == "margin":
                # stage 1: the largest t with z_{n-1} <= -t (rows z_{n-1} <= -mu get mu back);
                # stage 2: the least energy keeping MARGIN_KEEP of it. Lexicographic in two
                # well-scaled solves rather than one badly scaled weighted objective.
                h0 = hy + mu * mcol
                st1, _, t1 = solve_qp(Gy, h0, mcol, min(self.margin_cap, self.end_sign))
                out.qp_solves += 1
                if st1 in ("Solved", "AlmostSolved") and t1 * MARGIN_KEEP > mu:
                    t_marg = t1
                    hy = h0 - MARGIN_KEEP * t1 * mcol
            status, y, _ = solve_qp(Gy, hy)
            t_solve += time.perf_counter() - t0
            out.qp_solves += 1
            out.status = status
            out.rounds = rnd
            if y is None:
                out.reason = (f"QP {status} after {rnd} cut round(s)" if rnd else
                              f"QP {status}: no polynomial V2 of degree {self.p - 1} meets the "
                              "goal and the affine region conditions at this phi_change")
                break
            x = x_p + Nsp @ y
            inputs = self.inputs_from(dphi, x)
            path = ChainedPath.from_inputs(self.z0, inputs)
            chk = self.region.check_path(path)
            new_taus: list[float] = []
            taus_lin = self.grid
            if not chk.ok:
                # the checker's worst point and first crossing get the affine rows and cuts too
                for t in (chk.argmin_tau, chk.first_crossing_tau):
                    if (t is not None and 0.0 < t < 1.0
                            and not np.any(np.isclose(taus_aff, t, rtol=0.0, atol=1e-12))):
                        new_taus.append(float(t))
                taus_lin = np.concatenate([self.grid, np.array(new_taus)])
            added = self._add_cuts(cuts, path.z(taus_lin), taus_lin, w_lo, w_hi, rho)
            if chk.ok:
                # the latest passing solution is the one closest to meeting every target
                best = (float(x @ x), inputs, chk)
                out.qp_margin = t_marg
                if not added:
                    break
            if not added and not new_taus:
                out.reason = ("the path leaves the region but no cut applies there "
                              f"(margin {chk.margin:.3g} rad at t/T = {chk.argmin_tau:.4g})")
                break
            extra_taus.extend(new_taus)
            out.cuts += added
        else:
            if best is None and chk is not None:
                out.reason = (f"no singularity-free path after {self.max_rounds} cut rounds "
                              f"(last margin {chk.margin:.3g} rad at t/T = {chk.argmin_tau:.4g})")
        out.solve_time = t_solve
        if best is not None:
            energy, best_inputs, best_chk = best
            out.ok = True
            out.inputs = best_inputs
            out.energy = energy
            out.region_margin = float(best_chk.margin)
            out.argmin_tau = float(best_chk.argmin_tau)
            out.reason = ""
        return out

    def _add_cuts(self, cuts: dict[tuple, tuple[float, np.ndarray, float]], Z: np.ndarray,
                  taus: np.ndarray, w_lo: np.ndarray, w_hi: np.ndarray, rho: float | None,
                  seed: bool = False) -> int:
        """Linearise the nonlinear level conditions at the points ``Z`` (at ``taus``) and store
        the cuts in ``cuts``; return how many were added or replaced.

        A condition ``w_k <= c`` (side "hi", ``th_{k-1} >= lo + rho``) or ``w_k >= c`` ("lo",
        ``th_{k-1} <= hi - rho``) is written ``h(z) = sg (z_k - b_k(z) - c a_k(z)) <= 0`` with
        ``sg = +-sign(a_k)``, and cut as ``h(zbar) + grad h(zbar) . (z - zbar) <= 0``. Without
        ``seed`` only points outside the band ``[(1 - MARGIN_SLACK) rho]`` get a cut; with
        ``seed`` every point of the levels below n-1 does.
        """
        n = self.n
        if self.levels is None or not self.levels.levels:
            return 0
        a, b, Ja, Jb = self.levels(Z)
        # level validity from the top: z_n is affine; each level needs the ones above inside
        wn = Z[:, n - 1] / self.K[-1]
        above_ok = (wn > 0.0) & (wn < 1.0)
        if seed:
            w_lo_t, w_hi_t = w_lo, w_hi
        else:
            w_lo_t, w_hi_t = self.thresholds((1.0 - MARGIN_SLACK) * (rho or 0.0))
        added = 0
        for li in reversed(range(len(self.levels.levels))):
            k = self.levels.levels[li]
            s = (-1.0) ** (n - k)  # sign of a_k on the region
            with np.errstate(all="ignore"):
                w = (Z[:, k - 1] - b[:, li]) / a[:, li]
            fin = above_ok & np.isfinite(w) & np.isfinite(a[:, li])
            for side, c_cut, c_trig in (("hi", w_hi[k - 2], w_hi_t[k - 2]),
                                        ("lo", w_lo[k - 2], w_lo_t[k - 2])):
                convex = k == n - 1 and side == "hi"
                if seed:
                    if k >= n - 1:
                        continue
                    pick = fin
                else:
                    pick = fin & ((w > c_trig) if side == "hi" else (w < c_trig))
                sg = s if side == "hi" else -s
                for i in np.nonzero(pick)[0]:
                    zbar = Z[i]
                    hval = sg * (zbar[k - 1] - b[i, li] - c_cut * a[i, li])
                    grad = -sg * (Jb[i, li] + c_cut * Ja[i, li])
                    grad[k - 1] += sg
                    g = grad[1:]  # z1 is fixed by dphi; a_k, b_k do not depend on it
                    rhs = float(g @ zbar[1:] - hval)
                    if not (np.all(np.isfinite(g)) and math.isfinite(rhs)):
                        continue
                    key: tuple = (round(float(taus[i]), 12), k, side)
                    if convex:
                        key = key + (len(cuts),)
                    cuts[key] = (float(taus[i]), g, rhs)
                    added += 1
            above_ok = fin & (w > 0.0) & (w < 1.0)
        return added


# ---------------------------------------------------------------------- scoring
def _cheap_indicators(req: PlanRequest, inputs: InputSchedule) -> dict[str, float] | None:
    """t_p, d_a, sensitivity and energy on the search grid (what finish_plan will report)."""
    cf = chained_form(req.robot)
    T = inputs.duration
    z0 = cf.to_chained(req.q_start())
    path = ChainedPath.from_inputs(z0, inputs)
    td = np.linspace(0.0, T, SEARCH_SAMPLES)
    inv = cf.from_chained(path.z(td / T))
    if not inv.valid.all():
        return None
    ud = cf.u_from_v(inv.q, inputs.v(td))
    ind = compute_indicators(td, inv.q, ud)
    return {"t_p": float(ind.t_p), "d_a": ind.d_a, "sensitivity": ind.sensitivity,
            "energy": ind.energy}


def _score(req: PlanRequest, s: Synthesis) -> tuple[float, float]:
    """The request's rule (plan.py's objectives) on the cheap indicators; lower is better."""
    ind = s.indicators
    if req.objective == "tp_then_da":
        return ind["t_p"], ind["d_a"]
    if req.objective == "tp_then_sensitivity":
        return ind["t_p"], abs(s.dphi)
    w = req.weights
    return 0.0, (w.d_a * ind["d_a"] + w.sensitivity * ind["sensitivity"]
                 + w.energy * ind["energy"] + w.t_p * ind["t_p"])


def _evaluate(qp: ConstraintPointQP, req: PlanRequest, dphi: float) -> Synthesis:
    s = qp.solve(dphi)
    if s.ok and not s.indicators:
        ind = _cheap_indicators(req, s.inputs)  # type: ignore[arg-type]
        if ind is None:  # cannot happen after a passed check; be safe
            s.ok = False
            s.reason = "the sampled path is not invertible"
        else:
            s.indicators = ind
            s.score = _score(req, s)
    return s


def motion_sign(req: PlanRequest) -> float:
    """+1 when th2..thn move up (or stay), -1 when they move down (no conflict assumed)."""
    return 1.0 if np.any(np.array(req.goal[1:]) > np.array(req.start[1:])) else -1.0


def necessary_dphi_range(req: PlanRequest) -> tuple[float, float, str | None]:
    """Open interval ``(dmin, dmax)`` of ``|dphi|`` outside which a constant ``v1`` cannot work.

    With ``v1`` constant every ``th_i`` (i >= 2) moves monotonically, ``th_i' = K_i
    cos(th_{i-1})^m_i u1``. ``th1`` is free, so ``|dth_2| < K_2 |dphi|``; for i >= 3,
    ``th_{i-1}`` stays between its start and goal values, so ``cos(th_{i-1})^m_i`` stays between
    their values ``[c_lo, c_hi]`` and ``K_i c_lo |dphi| < |dth_i| < K_i c_hi |dphi|``.

    Returns
    -------
    dmin, dmax : float
    why : str or None
        Why the interval is empty (a joint that must move does not, or the bounds cross).
    """
    th0 = np.array(req.start)
    thT = np.array(req.goal)
    K = np.array(req.robot.gains)
    m = np.array(req.robot.exponents, float)
    n = req.n
    dth = np.abs(thT - th0)
    still = [i + 1 for i in range(1, n) if dth[i] == 0.0]
    if still:
        return 0.0, 0.0, (f"th{still[0]} does not move, but with a constant v1 != 0 every joint "
                          "th2..thn moves strictly (phi must reverse: use method 'penalty')")
    dmin = dth[1] / K[0]
    dmax = math.inf
    for i in range(2, n):  # 0-based joint index i is th_{i+1}, driven by th_i
        c = np.cos(np.array([th0[i - 1], thT[i - 1]])) ** m[i - 1]
        dmin = max(dmin, dth[i] / (K[i - 1] * float(c.max())))
        dmax = min(dmax, dth[i] / (K[i - 1] * float(c.min())))
    why = None
    if not dmin < dmax:
        why = (f"the joints' motions need |phi_change| > {dmin:.6g} rad and < {dmax:.6g} rad at "
               "once (each th_i, i >= 3, gains between K_i cos(th_(i-1))^m_i |dphi| at its start "
               "and goal values): no constant v1 reaches this goal")
    return float(dmin), float(dmax), why


def dphi_scan_range(req: PlanRequest) -> tuple[float, float, float, float]:
    """``(lo, hi, dmin, dmax)``: the request's bounds cut to the motion's sign and to the open
    interval of :func:`necessary_dphi_range`."""
    lo, hi = phi_search_bounds(req)
    dmin, dmax, _ = necessary_dphi_range(req)
    sgn = motion_sign(req)
    floor = max(dmin, 10 * MIN_ABS_DPHI)
    if sgn > 0:
        lo, hi = max(lo, floor), min(hi, dmax)
    else:
        lo, hi = max(lo, -dmax), min(hi, -floor)
    return lo, hi, dmin, dmax


# ---------------------------------------------------------------------- entry point
def plan_constraint_points(req: PlanRequest, deadline: Deadline) -> Plan:
    """Constraint-point synthesis: the QP with cuts, over ``dphi``, then the verified plan.

    Parameters
    ----------
    req : PlanRequest
        ``phi_change`` fixes ``dphi``; otherwise ``phi_change_bounds`` are scanned. The request's
        own constraint points are kept as equalities.
    deadline : Deadline

    Returns
    -------
    Plan
        Method ``"constraint_points"``; ``diagnostics["constraint_points"]`` holds the
        synthesized constraint points, QP status, cut rounds, margins and the scan.

    Raises
    ------
    InfeasibleError
        Opposite joint motions, a ``phi_change`` of the wrong sign or too small, or no ``dphi``
        with a singularity-free QP path (with every degree of :data:`EXTRA_DEGREES`).
    SolverTimeoutError
        The deadline passed between solves.
    """
    timing: dict[str, float] = {}
    t_start = time.perf_counter()
    conflict = direction_conflict(req)
    if conflict:
        raise InfeasibleError(conflict, diagnostics={"blocking": "opposite_joint_motion"})
    lo, hi, dmin, dmax = dphi_scan_range(req)
    _, _, why = necessary_dphi_range(req)
    necessary = {"min_abs_phi_change": dmin, "max_abs_phi_change": dmax if math.isfinite(dmax)
                 else None}
    if why is not None:
        raise InfeasibleError(why, diagnostics={"blocking": "constant_v1_cannot_reach_goal",
                                                **necessary})
    sgn = motion_sign(req)
    if req.phi_change is not None:
        dphi = float(req.phi_change)
        if not dmin < sgn * dphi < dmax:
            need = "positive" if sgn > 0 else "negative"
            raise InfeasibleError(
                f"phi_change = {dphi:.6g} rad cannot reach the goal with a constant v1: it must be "
                f"{need} with {dmin:.6g} < |phi_change| < {dmax:.6g} rad (each th_i moves "
                "monotonically at a rate bounded by its neighbours' start and goal values)",
                diagnostics={"blocking": "phi_change_outside_necessary_range", **necessary})
    elif not lo < hi:
        raise InfeasibleError(
            f"phi_change_bounds {list(req.phi_change_bounds)} contain no phi_change of the right "
            f"sign with {dmin:.6g} < |phi_change| < {dmax:.6g} rad, the range a constant v1 needs",
            diagnostics={"blocking": "no_feasible_phi_change", **necessary})

    attempts: list[dict[str, Any]] = []
    seeds: list[tuple[float, float]] | None = None
    chosen: Synthesis | None = None
    qp: ConstraintPointQP | None = None
    scanned: dict[str, Any] = {}
    for m in EXTRA_DEGREES:
        deadline.check("constraint-point synthesis")
        qp = ConstraintPointQP(req, extra_degrees=m)
        if req.phi_change is not None:
            s = _evaluate(qp, req, float(req.phi_change))
            attempts.append({"extra_degrees": m, "phi_change": s.dphi, "reason": s.reason})
            if s.ok:
                chosen = s
                break
            continue
        if seeds is None:
            t_fam = time.perf_counter()
            seeds = family_intervals(req, lo, hi)
            timing["family_intervals"] = time.perf_counter() - t_fam
        chosen, scanned = _search(qp, req, lo, hi, deadline, seeds)
        attempts.append({"extra_degrees": m, "searched": [lo, hi], **scanned})
        if chosen is not None:
            break
    timing["synthesis"] = time.perf_counter() - t_start
    if chosen is None or qp is None:
        if req.phi_change is not None:
            msg = (f"phi_change = {req.phi_change:.6g} rad: no singularity-free path with V2 of "
                   f"degree up to {req.n - 1 + EXTRA_DEGREES[-1] + len(req.constraint_points)}: "
                   + attempts[-1]["reason"])
        else:
            top = req.n - 1 + EXTRA_DEGREES[-1] + len(req.constraint_points)
            msg = (f"no phi_change in [{lo:.6g}, {hi:.6g}] rad gives a singularity-free path with "
                   f"V2 of degree up to {top}"
                   + (f" (most common reason: {attempts[-1].get('common_reason')})"
                      if attempts and attempts[-1].get("common_reason") else ""))
        raise InfeasibleError(msg, diagnostics={"blocking": "constraint_point_qp_infeasible",
                                                "attempts": attempts})
    deadline.check("constraint-point synthesis")
    assert chosen.inputs is not None
    diag = {"objective": req.objective, "singularity": req.singularity,
            "constraint_points": _report(qp, chosen, scanned, attempts)}
    return finish_plan(req, chosen.inputs, "constraint_points", list(seeds or []), timing, diag)


def family_intervals(req: PlanRequest, lo: float, hi: float) -> list[tuple[float, float]]:
    """The paper's family's singularity-free ``dphi`` intervals in [lo, hi] (full region).

    Where the family is feasible so is the QP (its member is then the QP's optimum), so these
    windows, which can be hundredths of a degree wide for n >= 4, seed the scan.
    """
    fam = PolynomialFamily(req.robot, req.q_start(), req.q_goal(0.0), req.duration_or_default,
                           req.constraint_points, make_region(req, "full"))
    try:
        return feasible_intervals(fam, lo, hi)
    except SingularSystemError:
        return []


def _search(qp: ConstraintPointQP, req: PlanRequest, lo: float, hi: float,
            deadline: Deadline, seeds: Sequence[tuple[float, float]] = ()
            ) -> tuple[Synthesis | None, dict[str, Any]]:
    """Scan ``dphi`` in (lo, hi), keep the best feasible node by the request's rule, refine.

    ``seeds`` are intervals known to be feasible (the paper's family): three nodes inside each
    join the uniform ones, so that narrow windows are never missed.
    """
    k = int(min(MAX_SCAN_NODES, max(MIN_SCAN_NODES, math.ceil((hi - lo) / SCAN_STEP) - 1)))
    # interior nodes: the ends are the necessary bounds (infeasible) or the request's bounds
    extra = [a + f * (b - a) for a, b in seeds for f in (0.25, 0.5, 0.75) if b > a]
    full = np.unique(np.concatenate([np.linspace(lo, hi, k + 2), np.array(extra, float)]))
    nodes = full[1:-1]
    k = int(nodes.size)
    evals: list[Synthesis] = []
    for d in nodes:
        deadline.check("the constraint-point dphi scan")
        evals.append(_evaluate(qp, req, float(d)))
    feas = [(i, s) for i, s in enumerate(evals) if s.ok]
    reasons: dict[str, int] = {}
    for s in evals:
        if not s.ok:
            key = s.reason.split(":")[0].split(" after")[0]
            reasons[key] = reasons.get(key, 0) + 1
    info: dict[str, Any] = {"nodes": int(k), "feasible_nodes": len(feas),
                            "common_reason": (max(reasons, key=lambda r: reasons[r])
                                              if reasons else None)}
    if not feas:
        return None, info
    best_i, best = min(feas, key=lambda t: t[1].score)
    tp_best = best.score[0]

    def restricted(d: float) -> float:
        s = _evaluate(qp, req, float(d))
        if not s.ok or (req.objective != "weighted" and s.score[0] > tp_best):
            return 1e9
        return s.score[1]

    a, b = float(full[best_i]), float(full[best_i + 2])  # the best node's neighbours
    evals_before = len(qp._cache)
    if req.objective == "tp_then_sensitivity":
        # the optimum is the smallest |dphi| with the fewest t_p: bisect toward it
        good = best.dphi
        bad = a if abs(a) < abs(b) else b
        if bad != good and restricted(bad) < 1e9:
            good = bad
        else:
            while abs(good - bad) > REFINE_XATOL and deadline.remaining > FINISH_RESERVE:
                mid = 0.5 * (good + bad)
                if restricted(mid) < 1e9:
                    good = mid
                else:
                    bad = mid
        cand = _evaluate(qp, req, good)
    elif b > a and deadline.remaining > FINISH_RESERVE:
        budget = [REFINE_MAXITER]

        def f(d: float) -> float:
            if budget[0] <= 0 or deadline.remaining <= FINISH_RESERVE:
                return 1e9  # out of time: the scan's best stands
            budget[0] -= 1
            return restricted(d)
        res = minimize_scalar(f, bounds=(a, b), method="bounded",
                              options={"xatol": REFINE_XATOL, "maxiter": REFINE_MAXITER})
        cand = _evaluate(qp, req, float(res.x))
    else:
        cand = best
    if cand.ok and cand.score <= best.score:
        best = cand
    info.update({"refinement_solves": len(qp._cache) - evals_before,
                 "best_node": float(nodes[best_i]), "refined_phi_change": best.dphi})
    return best, info


def _report(qp: ConstraintPointQP, s: Synthesis, scanned: dict[str, Any],
            attempts: list[dict[str, Any]]) -> dict[str, Any]:
    """The synthesized constraint points as the paper would state them, plus the QP facts."""
    assert s.inputs is not None
    T = qp.T
    m = qp.m
    path = ChainedPath.from_inputs(qp.z0, s.inputs)
    times = [T * (j + 1) / (m + 1) for j in range(m)]
    z2 = path.z(np.array(times) / T)[:, 1]
    pts = [ConstraintPoint(t, 2, float(v)) for t, v in zip(times, z2)]
    try:
        rep = solve_polynomial(s.dphi, qp.n, qp.z0, qp.zT, T, tuple(qp.points) + tuple(pts))
        reproduction = float(np.max(np.abs(rep.v2[0] - s.inputs.v2[0]))
                             / max(1.0, float(np.max(np.abs(s.inputs.v2[0])))))
    except SingularSystemError:
        reproduction = None
    return {
        "points": [{"time": p.time, "state": p.state, "value": p.value} for p in pts],
        "points_reproduce_v2_rel_error": reproduction,
        "request_points": [{"time": p.time, "state": p.state, "value": p.value}
                           for p in qp.points],
        "phi_change": s.dphi,
        "extra_degrees": m,
        "v2_degree": qp.p - 1,
        "qp_objective": qp.objective,
        "qp_status": s.status,
        "qp_solves": s.qp_solves,
        "cut_rounds": s.rounds,
        "cuts": s.cuts,
        "qp_energy": s.energy,
        "region_margin": s.region_margin,
        "argmin_tau": s.argmin_tau,
        "angle_margin_target": s.angle_margin,
        "sign_margin": s.sign_margin,
        "plain_member_feasible": s.plain_ok,
        "plain_member_energy": s.plain_energy,
        "grid_points": int(qp.grid.size),
        "backend": BACKEND,
        "qp_solve_time": s.solve_time,
        "scan": scanned,
        "attempts": attempts,
        "source": s.source,
    }


class ConstraintPointsMethod(Method):
    name = "constraint_points"
    capabilities = Capabilities(constraint_points=True, fixed_phi_change=True,
                                reverses_phi=False, inputs="chained")
    options = {"extra_degrees": EXTRA_DEGREES, "grid_points": GRID_POINTS,
               "max_cut_rounds": MAX_CUT_ROUNDS}

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        return plan_constraint_points(req, ctx.deadline)
