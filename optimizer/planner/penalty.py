"""The penalty-function method (paper Remark 3): an NLP over polynomial input coefficients with a
varying ``v1``, so that ``phi`` may reverse (project issues 3.4 and 8).

Why
---
With the paper's constant ``v1`` every joint ``th_2..th_n`` moves in the direction of ``phi``
(NOTES §4): a goal where two of them move in opposite directions (e.g. [10, 20, 30] ->
[40, 25, 15] deg) is out of reach, and even for reachable goals the one-parameter family leaves
``d_a`` of joint 1 around 20 deg. A polynomial ``V1`` gives the optimiser the freedom to move
``phi`` back and forth while ``th1`` follows its straight line more closely.

Parametrisation (normalised time ``tau = t / T`` in [0, 1]; ``T`` only rescales)
-------------------------------------------------------------------------------
``S`` segments of equal length ``h = 1/S`` (default 1, and 2 from n = 4 on); on each, in
``x = tau - tau_s``::

    V1(x) = sum_i a_i P_i(2x/h - 1)        (degree d1 = req.v1_degree, default 2)
    V2(x) = sum_i b_i P_i(2x/h - 1)        (degree d2 = req.v2_degree, default max(5, n + 2))

The decision variables are Legendre coefficients (``P_i``: Legendre polynomials on the
segment; their energy is diagonal), mapped linearly to monomials inside the NLP. The chained
state is polynomial in ``x`` and built *symbolically* (CasADi SX) by coefficient recursions
(convolution, then integration)::

    z1 = z1(tau_s) + int V1,   z2 = z2(tau_s) + int V2,   z_{k+1} = z_{k+1}(tau_s) + int z_k V1

so ``z`` at any time is an exact expression of the decision variables. ``d1 = 0, S = 1`` is
the paper's family (its plans embed exactly and serve as warm starts).

Constraints
-----------
* the exact goal ``z_k(1) = z_k^goal`` (k = 2..n+1); after IPOPT the ``V2`` coefficients get
  the minimum-energy correction that makes it hold to machine precision (for fixed ``V1`` the
  end state is affine in ``V2``);
* ``dphi = z1(1) - z1(0)`` within ``req.phi_change_bounds`` (or equal to ``req.phi_change``);
  the request's constraint points (equalities);
* the region on a grid of ``tau`` (``grid`` interior points, default 41). ``full``: through
  the chained form's symbolic inverse (:func:`inverse_clamped`, the recursion of
  ``SymbolicChainedForm.inverse_expr``), ``w_k = cos(th_{k-1})^m_k`` lies between its values
  at ``th_{k-1} = lo + margin`` and ``hi - margin`` (joint bounds of the request, margin
  :data:`MARGIN` = 0.5 deg, less when the start or goal is closer to a bound), scaled by
  ``1/|dw/dth|`` there: the same set as the angle bounds, in radians near them, and linear in
  ``z`` at the top level (IPOPT was much slower on the angles themselves); ``th_n`` within its
  joint bounds when given. ``z2``: only ``z2 <= -Z2_EPS`` (eq 13). Kind ``"hard"``
  (:data:`CONSTRAINT_KIND`, default): inequalities; ``"penalty"``: ``PENALTY_RHO * sum(min(0,
  g)^2)`` in the objective.

The grid only sees samples: every candidate is checked on the continuous path with the check
``finish_plan`` uses, and a better candidate that fails it is re-solved on a doubled grid (up
to :data:`MAX_REFINEMENTS` times). Under ``z2`` the first refinement keeps the grid and uses
the full constraints, and so does the polish of round 2 (below): a returned plan must lie in
the full region, and the z2-only NLP mostly ran into IPOPT's iteration limit there.

Objective (weights are NLP parameters)
--------------------------------------
* ``d_a`` of joint 1: an epigraph variable ``s >= |th1(tau_j) - line(tau_j)|``;
* ``t_p``: an exact l1 penalty (:data:`TP_WEIGHT`) on th1 moving against a required shape on
  the grid: ``r_j >= rate_j - dir_j (th1(tau_{j+1}) - th1(tau_j))``, ``r_j >= 0``. The shape
  is a parameter: monotone toward the goal (no reversal), or one reversal at a switch point
  (``overshoot``: past the goal and back; ``undershoot``: away first). ``rate_j`` is a small
  minimum rate (:data:`MIN_SLOPE`): without it the optimum has flat stretches of th1 where the
  polynomial path ripples between grid points, and every ripple counts in ``t_p`` (dead band
  1e-6 rad). The derivative of th1 at both ends is checked too (exactly), and reversals still
  found between grid points get "cuts" (pairs of parameter times) and a re-solve;
* the sensitivity ``||J_R(T)||_F`` of ``s = z1(1) - z1(0)`` (exact for any ``v1``);
* the input energy ``int V1^2 + V2^2 dtau`` (always with weight :data:`ENERGY_REGULARISER`).

``tp_then_da``: ``TP_WEIGHT * reversal + d_a``; ``tp_then_sensitivity``: ``TP_WEIGHT * reversal
+ sensitivity``; ``weighted``: ``req.weights`` (monotone shape; weights.t_p on the reversal
measure and weights.energy on the energy of ``V``, the NLP's stand-ins for t_p and the energy of
``u``).

Search
------
Round 1 solves the first shape (monotone) on the base grid from up to :data:`MAX_STARTS`
deterministic starts, pre-screened cheaply (region violation, then objective, at the start):
the warm start (e.g. the polynomial optimum, embedded exactly), the family member with the
largest region margin, constant ``V1 = +-0.5, +-1``, ``V1`` reversing at mid-time ``+-a (1 -
2 tau)``, ``V1`` late (``3 f D tau^2``, several ``f``), early (``3 D (1 - tau)^2``) or back then
forward (``f D (6 tau^2 - 2 tau)``), ``D`` the nominal phi travel (every joint's change over its
gain); for each ``V1`` the ``V2`` is the minimum-energy one that hits the goal. Round 1 stops
early once a plan has no reversal and ``d_a <= 1 deg`` (:data:`GOOD_DA`), or when the shape is
out of reach. Some goals need a reversal of th1 (for [10, 10, 10] -> [30, 30, 30] deg a
monotone th1 can change th3 by at most about 19.8 deg), so round 2 then solves the two shapes
with one reversal from every start and the best round-1 solution, roughly, on a coarse grid
(:data:`EXPLORE_GRID`, loose tolerances), and polishes the best :data:`POLISH` per shape on
the base grid. Every solution is measured like ``finish_plan`` measures plans (t_p and d_a on
1001 samples) and the best by the request's rule (fewest t_p, then d_a; or the weighted sum)
that stays in the region wins. The warm start itself is a candidate, so the result is never
worse than it. ``plan.diagnostics["penalty"]`` names the winning start and shape, IPOPT's
status and iterations, and lists every solve (``starts_tried``).

From n = 4 on (:data:`SHOOTING_FROM_N`) the 4-joint region is so narrow that every polynomial
start ends far outside it and IPOPT runs into its iteration limit; the search then first runs
from one start made by direct multiple shooting on the original model (:func:`shooting_start`:
its ``z1``, ``z2`` fitted per segment), with the polynomial starts as the fallback.

Caching and threads
-------------------
The CasADi NLP and its ``nlpsol`` are built once per :class:`NLPKey` (robot, degrees,
segments, grid, criterion, constraint kind, whether th_n is bounded, constraint-point layout)
and cached with :func:`functools.lru_cache` *per process*; start, goal, bounds, the shape of
th1, cuts and weights are parameters. CasADi objects are not thread-safe and the cached solver
also holds the current deadline: use this module from one thread per process (the service runs
each solve in a worker process).

Deadline
--------
IPOPT options are frozen when an ``nlpsol`` is created, so a cached solver cannot take
``max_wall_time = deadline.remaining`` per call; an IPOPT iteration callback stops the solve
(``User_Requested_Stop``) once the deadline has passed, the same bound at the granularity of
one iteration (about a millisecond); ``max_wall_time`` is the library's largest time limit as
a backstop. No solve starts after the deadline; :class:`SolverTimeoutError` is raised when no
solution was found in time, otherwise the best one so far is returned.

Limits (measured, prototype robot, a shared 2-core machine)
-----------------------------------------------------------
Goals that need no reversal of th1 ([20, 20, 20] -> [40, 40, 40] deg) take one or two solves,
about 0.1 s including verification, with d_a near 0.1 deg. Goals that need one take about 3 s
(some 40 solves, most of them rough ones of 20-120 iterations at 0.5-1 ms each). The landscape
is strongly multimodal and which start wins differs from goal to goal (the late and the back-
then-forward starts were added for [1, 1, 1] and [5, 5, 5] -> [30, 30, 30] deg). For n = 4
(assumed constants; even the paper's family has no singularity-free member for most goals)
plans with opposite joint motions are found and verified from the multiple-shooting start,
but th1 swings widely (t_p of 8-12) and the search takes 4-16 s (plus the verification: up to
15 s for such paths).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np
from numpy.polynomial import Legendre, Polynomial

from ..chained_form import SymbolicChainedForm, chained_form
from ..errors import InfeasibleError, NumericalError, SolverTimeoutError
from ..indicators import REVERSAL_DEAD_BAND, Indicators, compute_indicators
from ..model import Robot
from ..problem import MAX_TIME_LIMIT, PlanRequest
from ..results import Plan
from ..steering import ChainedPath, InputSchedule
from .family import SEARCH_SAMPLES
from .base import Capabilities, Method
from .solvers import DeadlineCallback
from .context import Deadline, PlanContext
from .finish import finish_plan
from .rules import direction_conflict, joint_limits, make_region, phi_search_bounds

# ---------------------------------------------------------------------- options
#: Default kind of the singularity constraints: ``"hard"`` (inequalities) or ``"penalty"``.
CONSTRAINT_KIND = "hard"
CONSTRAINT_KINDS = ("hard", "penalty")
#: Default degree of ``V1`` (0 reproduces the paper's constant-``v1`` family).
DEFAULT_V1_DEGREE = 2
#: Default degree of ``V2`` is ``max(DEFAULT_V2_DEGREE, n + 2)``: the goal takes ``n`` degrees
#: of freedom, the rest shape ``th1``.
DEFAULT_V2_DEGREE = 5
#: Default number of polynomial segments of the inputs.
DEFAULT_SEGMENTS = 1
#: Default number of interior grid points (region constraints, d_a, the t_p surrogate).
#: Fewer points were tried: 21 and 31 lose several degrees of d_a on the paper's goals.
DEFAULT_GRID = 41
#: Times the grid is doubled for a solution whose continuous path leaves the region.
MAX_REFINEMENTS = 2
#: Largest number of starts solved in the first round besides the warm start; the others are
#: ranked out by a cheap pre-screen (region violation, then objective, at the start).
MAX_STARTS = 4
#: Round 1 stops once a solution has no reversal and d_a at most this (rad): good enough.
GOOD_DA = math.radians(1.0)
#: Round 1 stops after two solutions whose reversal measure exceeds this (rad): th1 cannot do
#: without a reversal there, and the time is better spent on round 2.
IMPOSSIBLE_GATE = 1e-3
#: Grid of the exploratory solves of round 2.
EXPLORE_GRID = 21
#: Exploratory solutions polished on the base grid, per mode.
POLISH = 3
#: Scales of the nominal travel for the "late" starts (phi still first, then moving).
LATE_SCALES = (0.5, 0.75, 1.0, 1.25, 1.5)
#: Scales for the "back then forward" starts.
BACK_SCALES = (1.0, 1.5)
#: Number of joints from which the shooting start is added and the inputs have two segments
#: by default (the 4-joint region is narrow enough that no polynomial start gets near it).
SHOOTING_FROM_N = 4
#: Intervals of the multiple-shooting start.
SHOOTING_INTERVALS = 60
#: dphi step of the scan for the family start (rad).
FAMILY_SCAN_STEP = math.radians(0.5)
#: Margin (rad) kept from the region's bounds at grid points (0.5 deg).
MARGIN = math.radians(0.5)
#: ``z2 <= -Z2_EPS`` at grid points under the ``z2`` criterion.
Z2_EPS = 1e-6
#: Weight of the quadratic penalty on constraint violation (constraint kind ``"penalty"``);
#: the violations are in radians, so a 0.01 rad violation costs 10.
PENALTY_RHO = 1e5
#: Weight of the ``t_p`` surrogate (rad of th1 motion against its required direction) in the
#: lexicographic objectives. An exact (l1) penalty: far above d_a's weight (1), so that no d_a
#: gain buys a reversal (10 was not enough: tiny wiggles bought degrees of d_a).
TP_WEIGHT = 1000.0
#: Smallest rate (rad per unit of normalised time) at which th1 must move in its required
#: direction on every grid interval (cut to half its mean rate). Without it the optimum has
#: flat stretches of th1, where the polynomial path ripples between grid points and every
#: ripple counts in t_p (whose dead band is 1e-6 rad).
MIN_SLOPE = 0.05
#: Also require th1's exact derivative at tau = 0 and 1 to follow the shape (with the same
#: minimum rate): u2(0) and u2(1) are otherwise free, and a turn right at an end was the most
#: frequent reversal the grid missed.
END_CHECK = True
#: Pairs of parameter times ("cuts") where th1's direction is checked besides the grid; they
#: are placed where a solution still reverses between grid points, and the NLP re-solved.
MAX_CUTS = 4
#: Factor on the minimum rate of th1 on the grid intervals around a cut.
RATE_BOOST = 4.0
#: Re-solves per solution to move the switch (the allowed reversal) or to add cuts.
MAX_RESOLVES = 3
#: Cuts are added only when the grid-level reversal measure is below this (rad): the shape is
#: met on the grid and only sub-grid ripples remain (otherwise the shape is out of reach).
CUT_GATE = 1e-4
#: Small weight of the input energy always added, so the optimum is unique.
ENERGY_REGULARISER = 1e-5
#: Tiny weight kept on ``d_a`` when the objective does not use it (keeps its epigraph variable
#: determined, which IPOPT's Newton steps like).
DA_FLOOR = 1e-6
#: Default clamp of ``w`` in :func:`inverse_clamped` (the NLP passes tighter ones, at half the
#: margin, per request): it keeps the fractional power and ``acos`` finite outside the region.
W_CLAMP = 1e-9
#: Bound on |Legendre coefficient| (keeps IPOPT from wandering off to huge inputs).
COEFF_BOUND = 1e3
#: Stand-in for an infinite bound of th_n (penalty terms must stay finite).
BIG = 1e3
#: IPOPT statuses that are converged solutions.
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
#: IPOPT statuses that mean "ran out of time".
TIMEOUT = ("User_Requested_Stop", "Maximum_WallTime_Exceeded", "Maximum_CpuTime_Exceeded")
#: Largest violation (goal residual and scaled region constraints, rad) of a candidate.
FEAS_TOL = 1e-6
#: No solve begins once less than this is left of the deadline (s).
MIN_START_TIME = 1e-3

_IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0,
    "sb": "yes",
    "tol": 1e-8,
    "acceptable_tol": 1e-6,
    "constr_viol_tol": 1e-9,
    "max_iter": 300,
    "mu_strategy": "adaptive",
    "max_wall_time": float(MAX_TIME_LIMIT),
}
#: Exploratory solves: a rough local optimum is all they are for (the best are polished).
_IPOPT_EXPLORE: dict[str, Any] = {"tol": 1e-5, "acceptable_tol": 1e-3, "max_iter": 120}


# ---------------------------------------------------------------------- the cached NLP
@dataclass(frozen=True)
class NLPKey:
    """Everything that fixes the NLP's structure (hashable: the cache key).

    Start, goal, bounds, the required shape of th1, cuts and weights are NLP parameters and not
    part of the key, so one solver serves every objective and every request of one shape.
    """

    gains: tuple[float, ...]
    exponents: tuple[int, ...]
    v1_degree: int
    v2_degree: int
    segments: int
    grid: int
    criterion: str
    constraint_kind: str
    bounded_thn: bool = False
    points: tuple[tuple[float, int], ...] = ()
    explore: bool = False  # looser IPOPT tolerances (exploratory solves on a coarse grid)

    @property
    def n(self) -> int:
        return len(self.gains) + 1


@dataclass
class PenaltyNLP:
    """A built NLP: the IPOPT solver plus the layout needed to fill and read it.

    Attributes
    ----------
    key : NLPKey
    solver : casadi.Function
        ``nlpsol`` (IPOPT).
    aux : casadi.Function
        ``(x, p) -> (th1 on the grid with its ends, region constraints (>= 0 inside),
        [reversal, s_da, sensitivity, energy, penalty, f])``.
    callback : DeadlineCallback
    m1, m2 : ndarray
        Legendre -> monomial matrices of one segment for ``V1`` and ``V2``.
    taus : ndarray
        The interior grid.
    n_c1, n_c2 : int
        Numbers of ``V1`` and ``V2`` coefficients (all segments).
    nx, ng, npar : int
        Numbers of variables, constraints and parameters.
    lbg, ubg, lbx, ubx : ndarray
        Bound templates (the dphi row is filled per request).
    layout : dict of slice
        Parameter vector layout.
    build_time : float
    """

    key: NLPKey
    solver: Any
    aux: Any
    callback: DeadlineCallback
    m1: np.ndarray
    m2: np.ndarray
    taus: np.ndarray
    n_c1: int
    n_c2: int
    nx: int
    ng: int
    npar: int
    lbg: np.ndarray
    ubg: np.ndarray
    lbx: np.ndarray
    ubx: np.ndarray
    layout: dict[str, slice] = field(default_factory=dict)
    fill: list[tuple[int, int]] = field(default_factory=list)
    build_time: float = 0.0

    @property
    def breaks(self) -> np.ndarray:
        return np.linspace(0.0, 1.0, self.key.segments + 1)

    @property
    def n_inputs(self) -> int:
        """Number of input coefficients (the leading entries of ``x``)."""
        return self.n_c1 + self.n_c2


def legendre_to_monomial(degree: int, h: float) -> np.ndarray:
    """Matrix ``M`` with ``M[:, i]`` = monomial coefficients (in ``x``) of ``P_i(2x/h - 1)``."""
    M = np.zeros((degree + 1, degree + 1))
    for i in range(degree + 1):
        c = Legendre.basis(i, domain=[0.0, h]).convert(kind=Polynomial).coef
        M[:c.size, i] = c
    return M


def _polyint(c: list, k0: Any) -> list:
    """Antiderivative of a coefficient list (increasing powers) with value ``k0`` at 0."""
    return [k0] + [c[i] / (i + 1) for i in range(len(c))]


def _polymul(a: list, b: list) -> list:
    """Product of two coefficient lists (convolution)."""
    out: list = [0] * (len(a) + len(b) - 1)
    for i, ai in enumerate(a):
        for j, bj in enumerate(b):
            out[i + j] = out[i + j] + ai * bj
    return out


def _polyder(c: list) -> list:
    """Derivative of a coefficient list."""
    return [c[i] * i for i in range(1, len(c))] or [0]


def _polyval(c: list, x: Any) -> Any:
    """Horner evaluation (``x`` numeric or symbolic)."""
    acc = c[-1]
    for ci in reversed(c[:-1]):
        acc = acc * x + ci
    return acc


def inverse_clamped(sym: SymbolicChainedForm, z: list, clamp: Any = None
                    ) -> tuple[list, list, list]:
    """:meth:`SymbolicChainedForm.inverse_expr` with ``w`` clamped before ``acos(w^(1/m))``.

    Returns ``(th, w, rho)``: ``th`` and ``w`` like ``inverse_expr`` (``th[i-1] = theta_i``,
    ``w[k-2] = cos(th_{k-1})^{m_k}``), built from the same ``a_k``, ``b_k`` functions, and
    ``rho[k-2]``, the angle ``th_{k-1}`` extended linearly in ``w`` beyond the clamp (C1, equal
    to the angle inside it, with a gradient everywhere: the region constraints use it). Inside
    the clamp it is the same expression; outside, the clamp keeps every value finite and
    moderate, so that IPOPT can start outside the region. ``clamp`` holds
    ``(lo, hi)`` per ``w_k`` (k = 2..n, as a flat vector); default ``[W_CLAMP, 1 - W_CLAMP]``.
    The NLP clamps at half the margin: the clamp must never act where the constraints hold,
    and a clamp near 0 or 1 lets the next level's ``a_k`` vanish, whose ``w`` then explodes
    (1e13 was seen for n = 4) and sends IPOPT far away.
    """
    n = sym.n
    qsym: list = [z[0]] + [0] * n
    qsym[n] = z[n]
    ws: list = [None] * (n - 1)
    rho: list = [None] * (n - 1)
    for k in range(n, 1, -1):
        qvec = ca.vertcat(*qsym)
        a = sym.a[k](qvec)
        b = sym.b[k](qvec)
        wk = (z[k - 1] - b) / a
        ws[k - 2] = wk
        lo, hi = ((W_CLAMP, 1.0 - W_CLAMP) if clamp is None
                  else (clamp[2 * (k - 2)], clamp[2 * (k - 2) + 1]))
        wc = ca.fmin(ca.fmax(wk, lo), hi)
        mk = sym.exponents[k - 2]
        r = wc ** (1.0 / mk)
        qsym[k - 1] = ca.acos(r)
        # d th / d w = -(1/m) w^(1/m - 1) / sqrt(1 - w^(2/m)), taken at the clamped w
        rho[k - 2] = qsym[k - 1] - (wk - wc) * r / (mk * wc * ca.sqrt(1.0 - r * r))
    return qsym[1:], ws, rho


# weight vector entries
_W_TP, _W_DA, _W_SENS, _W_EN, _W_REG, _RHO = range(6)


def _param_layout(n: int, grid: int, m: int) -> dict[str, slice]:
    sizes = [("z0", n + 1), ("zT", n + 1), ("th1", 2), ("weights", 6), ("wb", 4 * (n - 1)),
             ("thn", 2), ("dirs", grid + 1), ("rates", grid + 1), ("cuts", 3 * MAX_CUTS),
             ("end_rate", 1), ("wclamp", 2 * (n - 1)), ("cp", m)]
    out, i = {}, 0
    for name, s in sizes:
        out[name] = slice(i, i + s)
        i += s
    out["_total"] = slice(0, i)
    return out


def _build(key: NLPKey) -> PenaltyNLP:
    """Build the symbolic NLP and its IPOPT solver (once per key, see :func:`get_nlp`)."""
    t0 = time.perf_counter()
    n = key.n
    S, d1, d2, N = key.segments, key.v1_degree, key.v2_degree, key.grid
    sym = chained_form(Robot(key.gains, key.exponents)).symbolic
    h = 1.0 / S
    breaks = np.linspace(0.0, 1.0, S + 1)
    M1, M2 = legendre_to_monomial(d1, h), legendre_to_monomial(d2, h)
    n_c1, n_c2 = S * (d1 + 1), S * (d2 + 1)
    c = ca.SX.sym("c", n_c1 + n_c2)
    s_da = ca.SX.sym("s_da")
    r = ca.SX.sym("r", N + 1)  # th1 moving against its required direction, per grid interval
    r_cut = ca.SX.sym("r_cut", MAX_CUTS)  # ... across the cut pairs
    r_end = ca.SX.sym("r_end", 2)  # ... at the two ends (derivatives)
    x = ca.vertcat(c, s_da, r, r_cut, r_end)
    m = len(key.points)
    lay = _param_layout(n, N, m)
    p = ca.SX.sym("p", lay["_total"].stop)
    z0, zT = p[lay["z0"]], p[lay["zT"]]
    th1_0, th1_T = p[lay["th1"]][0], p[lay["th1"]][1]
    wts, wb, cpv = p[lay["weights"]], p[lay["wb"]], p[lay["cp"]]
    thn_lo, thn_hi = p[lay["thn"]][0], p[lay["thn"]][1]
    dirs, rates, cuts = p[lay["dirs"]], p[lay["rates"]], p[lay["cuts"]]
    end_rate = p[lay["end_rate"]]
    wclamp = p[lay["wclamp"]]

    # --- the exact polynomial chained state, segment by segment (monomials in local x)
    seg_polys: list[list[list]] = []
    zstart = [z0[i] for i in range(n + 1)]
    energy: Any = 0
    for s in range(S):
        a_leg = c[s * (d1 + 1):(s + 1) * (d1 + 1)]
        b_leg = c[n_c1 + s * (d2 + 1):n_c1 + (s + 1) * (d2 + 1)]
        v1 = [ca.dot(ca.DM(M1[i, :]), a_leg) for i in range(d1 + 1)]
        v2 = [ca.dot(ca.DM(M2[i, :]), b_leg) for i in range(d2 + 1)]
        # int_0^h P_i(2x/h - 1) P_j(2x/h - 1) dx = h delta_ij / (2i + 1): energy is diagonal
        energy = energy + h * (ca.sumsqr(a_leg / np.sqrt(2 * np.arange(d1 + 1) + 1.0))
                               + ca.sumsqr(b_leg / np.sqrt(2 * np.arange(d2 + 1) + 1.0)))
        zs = [_polyint(v1, zstart[0]), _polyint(v2, zstart[1])]
        for k in range(2, n + 1):
            zs.append(_polyint(_polymul(zs[k - 1], v1), zstart[k]))
        seg_polys.append(zs)
        zstart = [_polyval(zk, h) for zk in zs]
    zend = zstart

    def z_at(tau: float) -> list:
        s = min(max(int(np.searchsorted(breaks, tau, side="right")) - 1, 0), S - 1)
        return [_polyval(zk, tau - breaks[s]) for zk in seg_polys[s]]

    def z_at_param(tau: Any) -> list:
        """z at a symbolic (parameter) time: each segment's polynomial, selected by tau."""
        out = [_polyval(zk, tau - breaks[0]) for zk in seg_polys[0]]
        for s in range(1, S):
            vals = [_polyval(zk, tau - breaks[s]) for zk in seg_polys[s]]
            out = [ca.if_else(tau >= breaks[s], v, o) for v, o in zip(vals, out)]
        return out

    taus = np.arange(1, N + 1) / (N + 1.0)
    g: list = []
    lbg: list[float] = []
    ubg: list[float] = []

    def add(expr: Any, lo: float, hi: float) -> None:
        g.append(expr)
        lbg.append(lo)
        ubg.append(hi)

    for k in range(1, n + 1):  # exact goal z2..z_{n+1}
        add(zend[k] - zT[k], 0.0, 0.0)
    add(zend[0] - z0[0], -math.inf, math.inf)  # dphi: bounds filled per request
    for j, (tau_cp, state) in enumerate(key.points):
        add(z_at(tau_cp)[state - 1] - cpv[j], 0.0, 0.0)

    # --- region constraints (scaled, >= 0 inside) and th1 on the grid
    region: list = []
    th1: list = [th1_0]
    hard = key.constraint_kind == "hard"
    fill: list[tuple[int, int]] = []  # (row, k): two-sided rows whose upper bound is per request
    for tau in taus:
        z = z_at(float(tau))
        th, ws, _ = inverse_clamped(sym, z, wclamp)
        th1.append(th[0])
        if key.criterion == "z2":
            region.append(-z[1] - Z2_EPS)
            if hard:
                add(region[-1], 0.0, math.inf)
            continue
        for k in range(2, n + 1):
            # w_k = cos(th_{k-1})^m_k between the values at the angle bounds, scaled by
            # 1/|dw/dth| there: exactly the angle bounds, in radians near them, and linear in
            # z at the top level (the angle itself, through acos, made IPOPT much slower)
            w = ws[k - 2]
            i = 4 * (k - 2)
            region.append((w - wb[i]) * wb[i + 2])      # th_{k-1} <= its upper bound
            region.append((wb[i + 1] - w) * wb[i + 3])  # th_{k-1} >= its lower bound
            if hard:  # one two-sided row: half the rows of IPOPT's KKT system
                fill.append((len(g), k))
                add(region[-2], 0.0, math.inf)
        if key.bounded_thn:
            region.append(z[n] - thn_lo)
            region.append(thn_hi - z[n])
            if hard:
                fill.append((len(g), 0))
                add(z[n], -math.inf, math.inf)
    th1.append(th1_T)
    region_vec = ca.vertcat(*region)
    penalty = 0 if hard else ca.sumsqr(ca.fmin(region_vec, 0.0))

    # --- d_a epigraph: s >= |th1 - line| on the grid
    for j, tau in enumerate(taus):
        dev = th1[j + 1] - (th1_0 + tau * (th1_T - th1_0))
        add(s_da - dev, 0.0, math.inf)
        add(s_da + dev, 0.0, math.inf)
    # --- t_p surrogate: on grid interval j th1 must move in direction dirs[j] (+-1; 0 = free,
    # where the one allowed reversal sits) by at least rates[j]; r_j >= the shortfall (an
    # epigraph, r_j >= 0 by bounds). Its sum is 0 exactly when th1 has the required shape on
    # the grid, and measures the motion against it otherwise.
    for j in range(N + 1):
        add(r[j] + dirs[j] * (th1[j + 1] - th1[j]) - rates[j], 0.0, math.inf)
    reversal: Any = ca.sum1(r)
    # --- the ends: th1's derivative at tau = 0 and 1 (exact; th1 turning back right at the start
    # or the end is the most common reversal the grid misses: u2(0) and u2(1) are free)
    zs_sym = ca.SX.sym("zs", n + 1)
    th1_of_z = inverse_clamped(sym, [zs_sym[i] for i in range(n + 1)], wclamp)[0][0]
    for end, (zz, v1e, v2e) in enumerate(((
            [z0[i] for i in range(n + 1)], _polyval(_polyder(seg_polys[0][0]), 0.0),
            _polyval(_polyder(seg_polys[0][1]), 0.0)), (
            zend, _polyval(_polyder(seg_polys[-1][0]), h),
            _polyval(_polyder(seg_polys[-1][1]), h)))):
        zvec = ca.vertcat(*zz)
        zdot = ca.vertcat(v1e, v2e, *[zz[k - 1] * v1e for k in range(2, n + 1)])
        dth1 = ca.substitute(ca.jtimes(th1_of_z, zs_sym, zdot), zs_sym, zvec)
        add(r_end[end] + dirs[0 if end == 0 else N] * dth1 - end_rate, 0.0, math.inf)
        reversal = reversal + r_end[end] / (N + 1.0)
    # --- cuts: pairs of parameter times (ta, tb) where a previous solution reversed between
    # grid points; th1 must move in direction sc from ta to tb (sc = 0: unused pair)
    for k in range(MAX_CUTS):
        ta, tb, sc = cuts[3 * k], cuts[3 * k + 1], cuts[3 * k + 2]
        tha = inverse_clamped(sym, z_at_param(ta), wclamp)[0][0]
        thb = inverse_clamped(sym, z_at_param(tb), wclamp)[0][0]
        add(r_cut[k] + sc * (thb - tha), 0.0, math.inf)
        reversal = reversal + r_cut[k]

    dphi = zend[0] - z0[0]
    sens2: Any = 1
    for k in range(n):
        sens2 = sens2 + (n - k) * dphi ** (2 * k) / math.factorial(k) ** 2
    sens = ca.sqrt(sens2)
    f = (wts[_W_TP] * reversal + wts[_W_DA] * s_da + wts[_W_SENS] * sens
         + (wts[_W_EN] + wts[_W_REG]) * energy + wts[_RHO] * penalty)

    gvec = ca.vertcat(*g)
    nx, ng, npar = x.numel(), gvec.numel(), p.numel()
    cb = DeadlineCallback(nx, ng, npar)
    ipopt = {**_IPOPT_OPTIONS, **(_IPOPT_EXPLORE if key.explore else {})}
    opts: dict[str, Any] = {"ipopt": ipopt, "print_time": False,
                            "iteration_callback": cb, "error_on_fail": False}
    solver = ca.nlpsol("penalty_nlp", "ipopt", {"x": x, "p": p, "f": f, "g": gvec}, opts)
    aux = ca.Function("penalty_aux", [x, p],
                      [ca.vertcat(*th1), region_vec,
                       ca.vertcat(reversal, s_da, sens, energy, penalty, f)])
    lbx = np.full(nx, -COEFF_BOUND)
    ubx = np.full(nx, COEFF_BOUND)
    lbx[n_c1 + n_c2:] = 0.0  # epigraph variables and slacks
    ubx[n_c1 + n_c2:] = math.inf
    return PenaltyNLP(key=key, solver=solver, aux=aux, callback=cb, m1=M1, m2=M2, taus=taus,
                      n_c1=n_c1, n_c2=n_c2, nx=nx, ng=ng, npar=npar, lbg=np.array(lbg),
                      ubg=np.array(ubg), lbx=lbx, ubx=ubx, layout=lay, fill=fill,
                      build_time=time.perf_counter() - t0)


@functools.lru_cache(maxsize=32)
def get_nlp(key: NLPKey) -> PenaltyNLP:
    """The cached NLP for ``key``: one cache per process, not for use from several threads."""
    return _build(key)


def clear_cache() -> None:
    """Drop every cached NLP."""
    get_nlp.cache_clear()


# ---------------------------------------------------------------------- one request
@dataclass(frozen=True)
class Mode:
    """One weighting of the objective and the required shape of th1 (NLP parameters only).

    Attributes
    ----------
    name : str
        ``monotone`` (th1 moves from start to goal without reversal), ``overshoot`` (one
        reversal: th1 goes past the goal, or past the start's level in the goal's direction,
        and comes back), ``undershoot`` (one reversal: th1 first moves away from the goal),
        ``weighted`` (monotone shape, req.weights).
    weights : ndarray (6,)
    shape : (float, float)
        Directions (+-1) th1 must move in before and after the switch (the allowed reversal).
    """

    name: str
    weights: np.ndarray = field(compare=False)
    shape: tuple[float, float]

    @property
    def switch(self) -> bool:
        """Whether the mode allows one reversal (at a switch point on the grid)."""
        return self.shape[0] != self.shape[1]


def _weights(req: PlanRequest) -> np.ndarray:
    w = np.zeros(6)
    if req.objective == "tp_then_da":
        w[_W_TP], w[_W_DA] = TP_WEIGHT, 1.0
    elif req.objective == "tp_then_sensitivity":
        w[_W_TP], w[_W_SENS], w[_W_DA] = TP_WEIGHT, 1.0, DA_FLOOR
    else:
        ww = req.weights
        w[_W_TP], w[_W_DA], w[_W_SENS], w[_W_EN] = ww.t_p, max(ww.d_a, DA_FLOOR), \
            ww.sensitivity, ww.energy
    w[_W_REG] = ENERGY_REGULARISER
    w[_RHO] = PENALTY_RHO
    return w


def modes_for(req: PlanRequest) -> list[Mode]:
    """The objective's weightings and shapes, in the order they are tried.

    For the lexicographic objectives the first mode asks for no reversal of th1. Some goals
    need one (e.g. [10, 10, 10] -> [30, 30, 30] deg: with th1 monotone the reachable change of
    th3 is at most about 19.8 deg, by integrating dth3/dth2 = (K3/K2) cos(th2)^3 / cos(th1)^2
    by parts), and there the monotone surrogate would trade d_a for the size of the unavoidable
    reversal; the two other modes allow exactly one reversal, at a switch point, and penalise
    every other one.
    """
    w = _weights(req)
    sg = 1.0 if req.goal[0] >= req.start[0] else -1.0
    if req.objective == "weighted":
        return [Mode("weighted", w, (sg, sg))]
    return [Mode("monotone", w, (sg, sg)), Mode("overshoot", w, (sg, -sg)),
            Mode("undershoot", w, (-sg, sg))]


def _margins(req: PlanRequest) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lower/upper angle limits of th1..thn at the grid, with margins, and the raw bounds.

    The margin is :data:`MARGIN`, shrunk for a joint whose start or goal is closer than about
    twice that to a bound (those ends are fixed, so grid points next to them must be feasible).
    """
    region = make_region(req, "full")
    lo, hi = region.lower.copy(), region.upper.copy()
    ends = np.array([req.start, req.goal])
    for i in range(req.n):
        if not (math.isfinite(lo[i]) and math.isfinite(hi[i])):
            continue
        room = float(np.min(np.minimum(ends[:, i] - lo[i], hi[i] - ends[:, i])))
        mg = min(MARGIN, 0.45 * max(room, 0.0))
        lo[i] += mg
        hi[i] -= mg
    return lo, hi, region.lower, region.upper


def _w_bounds(req: PlanRequest, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per ``w_k`` (k = 2..n): ``(w at the upper angle, w at the lower angle, 1/|dw/dth| at
    each)``: ``(w - w_hi) / |dw/dth|`` is the angle bound, in radians near the bound."""
    n = req.n
    wb = np.zeros(4 * (n - 1))
    for k in range(2, n + 1):
        j = k - 2
        mk = req.robot.exponents[k - 2]
        a, b = lo[j], hi[j]
        s_hi = 1.0 / max(mk * math.cos(b) ** (mk - 1) * math.sin(b), 1e-12)
        s_lo = 1.0 / max(mk * math.cos(a) ** (mk - 1) * math.sin(a), 1e-12)
        wb[4 * j:4 * j + 4] = (math.cos(b) ** mk, math.cos(a) ** mk, s_hi, s_lo)
    return wb


@dataclass
class _Problem:
    """The numeric side of one request on one NLP: start/goal, parameters, bounds."""

    req: PlanRequest
    nlp: PenaltyNLP
    z0: np.ndarray
    zT: np.ndarray
    p: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    duration: float
    energy_w: np.ndarray  # diagonal energy metric of the V2 coefficients

    @classmethod
    def create(cls, req: PlanRequest, nlp: PenaltyNLP) -> "_Problem":
        n = req.n
        cf = chained_form(req.robot)
        z0 = cf.to_chained(req.q_start())
        zT = cf.to_chained(req.q_goal(0.0))
        lay = nlp.layout
        p = np.zeros(nlp.npar)
        p[lay["z0"]] = z0
        p[lay["zT"]] = zT
        p[lay["th1"]] = (req.start[0], req.goal[0])
        p[lay["weights"]] = _weights(req)
        lo, hi, raw_lo, raw_hi = _margins(req)
        wb = _w_bounds(req, lo, hi)
        p[lay["wb"]] = wb
        # clamp of w inside the inverse: halfway between the grid bounds and the region's
        wc = np.zeros(2 * (n - 1))
        for k in range(2, n + 1):
            j, mk = k - 2, req.robot.exponents[k - 2]
            th_hi = 0.5 * (hi[j] + min(raw_hi[j], 0.5 * math.pi))
            th_lo = 0.5 * (lo[j] + max(raw_lo[j], 0.0))
            wc[2 * j:2 * j + 2] = (math.cos(th_hi) ** mk, math.cos(th_lo) ** mk)
        p[lay["wclamp"]] = wc
        p[lay["thn"]] = (lo[-1] if math.isfinite(lo[-1]) else -BIG,
                         hi[-1] if math.isfinite(hi[-1]) else BIG)
        p[lay["cp"]] = [cp.value for cp in req.constraint_points]
        lbg, ubg = nlp.lbg.copy(), nlp.ubg.copy()
        for row, k in nlp.fill:  # upper bounds of the two-sided region rows
            if k == 0:  # th_n itself
                lbg[row], ubg[row] = p[lay["thn"]]
            else:
                i = 4 * (k - 2)
                ubg[row] = (wb[i + 1] - wb[i]) * wb[i + 2]
        i_dphi = req.n  # the row after the n goal rows
        if req.phi_change is not None:
            lbg[i_dphi] = ubg[i_dphi] = float(req.phi_change)
        else:
            lbg[i_dphi], ubg[i_dphi] = req.phi_change_bounds
        key = nlp.key
        ew = np.tile(1.0 / (2 * np.arange(key.v2_degree + 1) + 1.0), key.segments) / key.segments
        return cls(req=req, nlp=nlp, z0=z0, zT=zT, p=p, lbg=lbg, ubg=ubg,
                   duration=req.duration_or_default, energy_w=ew)

    def params(self, mode: Mode, switch: int = 0, cuts: np.ndarray | None = None
               ) -> np.ndarray:
        """The parameter vector for ``mode`` with its switch at grid point ``switch`` (1..N,
        for modes with a reversal) and ``cuts``."""
        p = self.p.copy()
        lay = self.nlp.layout
        N = self.nlp.key.grid
        p[lay["weights"]] = mode.weights
        rate = min(MIN_SLOPE, 0.5 * abs(self.req.goal[0] - self.req.start[0])) / (N + 1.0)
        j = np.arange(N + 1)
        if mode.switch:
            dirs = np.where(j < switch, mode.shape[0], mode.shape[1])
            rates = np.where((j == switch - 1) | (j == switch), 0.0, rate)
        else:
            dirs = np.full(N + 1, mode.shape[0])
            rates = np.full(N + 1, rate)
        if cuts is not None:
            # around each cut, th1 must also move faster on the grid: a ripple between grid
            # points is otherwise only pushed aside by the cut pair
            edges = np.arange(N + 2) / (N + 1.0)
            for k in range(MAX_CUTS):
                ta, tb, sc = cuts[3 * k:3 * k + 3]
                if sc == 0.0:
                    continue
                near = ((edges[1:] > ta - 1.0 / (N + 1.0)) & (edges[:-1] < tb + 1.0 / (N + 1.0))
                        & (dirs == sc) & (rates > 0.0))
                rates = np.where(near, RATE_BOOST * rate, rates)
        p[lay["dirs"]] = dirs
        p[lay["rates"]] = rates
        p[lay["cuts"]] = 0.0 if cuts is None else cuts
        p[lay["end_rate"]] = rate * (N + 1.0) if END_CHECK else -BIG
        return p

    def coeffs(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Legendre coefficients per segment: arrays (S, d1+1) and (S, d2+1)."""
        k = self.nlp.key
        c1 = x[:self.nlp.n_c1].reshape(k.segments, k.v1_degree + 1)
        c2 = x[self.nlp.n_c1:self.nlp.n_inputs].reshape(k.segments, k.v2_degree + 1)
        return c1, c2

    def schedule(self, x: np.ndarray) -> InputSchedule:
        """The :class:`InputSchedule` (monomial coefficients per segment) of ``x``."""
        c1, c2 = self.coeffs(x)
        return InputSchedule(self.nlp.breaks.copy(), tuple(self.nlp.m1 @ a for a in c1),
                             tuple(self.nlp.m2 @ b for b in c2), self.duration)

    def end_residual(self, x: np.ndarray) -> np.ndarray:
        """Goal residual (z2..z_{n+1}) and constraint-point residuals of ``x``."""
        path = ChainedPath.from_inputs(self.z0, self.schedule(x))
        r = [path.z_end()[1:] - self.zT[1:]]
        pts = self.nlp.key.points
        if pts:
            vals = self.p[self.nlp.layout["cp"]]
            zs = path.z(np.array([t for t, _ in pts]))
            r.append(np.array([zs[j, st - 1] - vals[j] for j, (_, st) in enumerate(pts)]))
        return np.concatenate(r)

    def project_goal(self, x: np.ndarray) -> np.ndarray:
        """Minimum-energy change of the ``V2`` coefficients that makes the goal (and the
        constraint points) exact: for fixed ``V1`` they are affine in ``V2``."""
        x = np.array(x, float)
        i0, i1 = self.nlp.n_c1, self.nlp.n_inputs
        r0 = self.end_residual(x)
        G = np.empty((r0.size, i1 - i0))
        for j in range(i1 - i0):
            xe = x.copy()
            xe[i0 + j] += 1.0
            G[:, j] = self.end_residual(xe) - r0
        Winv = 1.0 / self.energy_w
        A = (G * Winv) @ G.T
        if np.linalg.cond(A) < 1e14:
            dx = Winv * (G.T @ np.linalg.solve(A, -r0))
        else:  # V1 makes the goal map singular (e.g. V1 = 0): best effort
            dx = np.linalg.lstsq(G, -r0, rcond=None)[0]
        x[i0:i1] += dx
        return x

    def fit(self, V1: Callable[[np.ndarray], np.ndarray],
            V2: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """``x`` (slack entries 0) of given ``V1(tau), V2(tau)`` by least squares per segment
        at Chebyshev points: exact for polynomials of no higher degree."""
        key = self.nlp.key
        br = self.nlp.breaks
        c1 = np.zeros((key.segments, key.v1_degree + 1))
        c2 = np.zeros((key.segments, key.v2_degree + 1))
        npts = 2 * max(key.v1_degree, key.v2_degree) + 8
        for s in range(key.segments):
            h = br[s + 1] - br[s]
            xs = 0.5 * h * (1.0 - np.cos(np.pi * (np.arange(npts) + 0.5) / npts))
            tau = br[s] + xs
            for deg, fun, out in ((key.v1_degree, V1, c1), (key.v2_degree, V2, c2)):
                B = np.polynomial.legendre.legvander(2.0 * xs / h - 1.0, deg)
                out[s] = np.linalg.lstsq(B, fun(tau), rcond=None)[0]
        x = np.zeros(self.nlp.nx)
        x[:self.nlp.n_c1] = c1.ravel()
        x[self.nlp.n_c1:self.nlp.n_inputs] = c2.ravel()
        return x

    def evaluate(self, x: np.ndarray, p: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(th1 on the grid with its ends, region constraints, objective terms)`` at ``x``."""
        th1, reg, parts = self.nlp.aux(x, p)
        return (np.asarray(th1).ravel(), np.asarray(reg).ravel(), np.asarray(parts).ravel())

    def switch_of(self, x: np.ndarray, mode: Mode) -> int:
        """The grid point where th1 is most advanced in the first piece's direction."""
        th1, _, _ = self.evaluate(x, self.params(mode))
        N = self.nlp.key.grid
        return int(np.clip(np.argmax(mode.shape[0] * th1[1:-1]) + 1, 1, N))

    def initial(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``x`` with its slack variables set just above their smallest feasible values."""
        x = np.array(x, float)
        ni, N1 = self.nlp.n_inputs, self.nlp.key.grid + 1
        x[ni:] = 0.0
        th1, _, _ = self.evaluate(x, p)
        lay = self.nlp.layout
        taus = np.concatenate([[0.0], self.nlp.taus, [1.0]])
        dev = th1 - (th1[0] + taus * (th1[-1] - th1[0]))
        x[ni] = float(np.max(np.abs(dev[1:-1]))) + 1e-4
        x[ni + 1:ni + 1 + N1] = np.maximum(
            0.0, p[lay["rates"]] - p[lay["dirs"]] * np.diff(th1)) + 1e-5
        x[ni + 1 + N1:] = 1e-3  # cut slacks (the cuts' own values are set by the solve)
        return x

    def violation(self, x: np.ndarray, p: np.ndarray) -> float:
        """Largest violation of the goal and of the grid region constraints at ``x`` (rad)."""
        _, reg, _ = self.evaluate(x, p)
        v = float(np.max(np.abs(self.end_residual(x))))
        if reg.size:
            v = max(v, float(-min(0.0, reg.min())))
        return v


# ---------------------------------------------------------------------- starts
def _const(c: float) -> Callable[[np.ndarray], np.ndarray]:
    return lambda tau: np.full_like(np.asarray(tau, float), c)


def _schedule_funcs(s: InputSchedule) -> tuple[Callable, Callable]:
    return (lambda tau: s.V(tau)[:, 0]), (lambda tau: s.V(tau)[:, 1])


def _travel(req: PlanRequest) -> float:
    """A scale of the phi travel the goal needs: every joint's change at its nominal rate."""
    d = np.abs(np.array(req.goal[1:]) - np.array(req.start[1:]))
    return float(np.sum(d / np.array(req.robot.gains)))


def _family_start(req: PlanRequest) -> InputSchedule | None:
    """The constant-v1 member with the largest coarse region margin (a cheap start inside the
    region when the paper's family has one; None when the joints' motions conflict)."""
    if direction_conflict(req) is not None or req.constraint_points:
        return None
    from .family import PolynomialFamily
    fam = PolynomialFamily(req.robot, req.q_start(), req.q_goal(0.0), req.duration_or_default,
                           (), make_region(req, "full"))
    if req.phi_change is not None:
        grid = np.array([float(req.phi_change)])
    else:
        lo, hi = phi_search_bounds(req)
        # 0.5 deg apart: feasible windows of the family can be 2 deg narrow
        grid = np.linspace(lo, hi, int(math.ceil((hi - lo) / FAMILY_SCAN_STEP)) + 1)
        grid = grid[np.abs(grid) > 1e-3]
    if grid.size == 0:
        return None
    mar = fam.coarse_margins(grid, grid=33)
    i = int(np.argmax(mar))
    if not mar[i] > 0.0:
        return None
    return fam.inputs(float(grid[i]))


@functools.lru_cache(maxsize=8)
def _shooting_nlp(gains: tuple[float, ...], exponents: tuple[int, ...], intervals: int) -> Any:
    """A small direct multiple-shooting NLP on the ORIGINAL model (minimum input energy,
    piecewise-constant u, RK4), used only to produce a start (cached per process)."""
    n = len(gains) + 1
    N = intervals
    h = 1.0 / N
    Q = ca.SX.sym("Q", n + 1, N + 1)
    U = ca.SX.sym("U", 2, N)
    p = ca.SX.sym("p", 2 * n + 3)  # q0 (n+1), goal (n), lo, hi

    def rhs(q: Any, u: Any) -> Any:
        return ca.vertcat(u[0], u[1], *[gains[i - 2] * ca.cos(q[i - 1]) ** exponents[i - 2]
                                        * u[0] for i in range(2, n + 1)])

    g = [Q[:, 0] - p[:n + 1], Q[1:, N] - p[n + 1:2 * n + 1]]
    for k in range(N):
        q = Q[:, k]
        for _ in range(2):  # two RK4 substeps per interval
            hh = 0.5 * h
            k1 = rhs(q, U[:, k])
            k2 = rhs(q + 0.5 * hh * k1, U[:, k])
            k3 = rhs(q + 0.5 * hh * k2, U[:, k])
            k4 = rhs(q + hh * k3, U[:, k])
            q = q + hh / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        g.append(Q[:, k + 1] - q)
    box = ca.vec(Q[1:n, :])
    g.append(box - p[2 * n + 1])
    g.append(p[2 * n + 2] - box)
    f = h * ca.sumsqr(U) + 1e-2 / h * ca.sumsqr(U[:, 1:] - U[:, :-1])
    x = ca.vertcat(ca.vec(Q), ca.vec(U))
    solver = ca.nlpsol("penalty_shooting", "ipopt", {"x": x, "p": p, "f": f, "g": ca.vertcat(*g)},
                       {"ipopt": {"print_level": 0, "sb": "yes", "max_iter": 200},
                        "print_time": False, "error_on_fail": False})
    n_eq = (n + 1) + n + N * (n + 1)
    return solver, n_eq, box.numel()


def shooting_start(req: PlanRequest, segments: int, d1: int, d2: int,
                   intervals: int = SHOOTING_INTERVALS) -> tuple[Callable, Callable] | None:
    """``V1(tau), V2(tau)`` of a path found by direct multiple shooting on the original model,
    for goals where the polynomial starts all end far outside the region (n >= 4 with opposite
    joint motions): ``z1`` and ``z2`` of that path are fitted per segment by polynomials of
    degree ``d1 + 1`` and ``d2 + 1`` (along the path ``dz_{k+1} = z_k dz1`` holds, so fitting
    ``z1`` and ``z2`` carries the rest) and differentiated. None when the shooting fails."""
    n = req.n
    solver, n_eq, nbox = _shooting_nlp(req.robot.gains, req.robot.exponents, intervals)
    q0, qT = req.q_start(), req.q_goal(0.0)
    tau = np.linspace(0.0, 1.0, intervals + 1)
    Q0 = q0[:, None] + (qT - q0)[:, None] * tau[None, :]
    x0 = np.concatenate([Q0.T.ravel(), np.tile(qT[:2] - q0[:2], intervals)])
    lo, hi = 2.0 * MARGIN, 0.5 * math.pi - 2.0 * MARGIN
    sol = solver(x0=x0, p=np.concatenate([q0, qT[1:], [lo, hi]]),
                 lbg=np.concatenate([np.zeros(n_eq), np.zeros(2 * nbox)]),
                 ubg=np.concatenate([np.zeros(n_eq), np.full(2 * nbox, np.inf)]))
    if not solver.stats().get("success", False):
        return None
    Q = np.asarray(sol["x"]).ravel()[:(n + 1) * (intervals + 1)].reshape(intervals + 1, n + 1)
    z = chained_form(req.robot).to_chained(Q)
    br = np.linspace(0.0, 1.0, segments + 1)
    fits = []
    for s in range(segments):
        m = (tau >= br[s] - 1e-12) & (tau <= br[s + 1] + 1e-12)
        xs = tau[m] - br[s]
        fits.append((np.polynomial.polynomial.polyder(
            np.polynomial.polynomial.polyfit(xs, z[m, 0], d1 + 1)),
            np.polynomial.polynomial.polyder(
            np.polynomial.polynomial.polyfit(xs, z[m, 1], d2 + 1))))

    def make(i: int) -> Callable:
        def fn(t: np.ndarray) -> np.ndarray:
            t = np.atleast_1d(np.asarray(t, float))
            idx = np.clip(np.searchsorted(br, t, side="right") - 1, 0, segments - 1)
            return np.array([np.polynomial.polynomial.polyval(tt - br[j], fits[j][i])
                             for tt, j in zip(t, idx)])
        return fn

    return make(0), make(1)


def starts_for(req: PlanRequest, warm_start: InputSchedule | None
               ) -> list[tuple[str, Callable, Callable | None]]:
    """Deterministic starts ``(name, V1(tau), V2(tau) or None)``; ``V2 = None`` means the
    minimum-energy ``V2`` that hits the goal for that ``V1``.

    The warm start; the family member with the largest margin; constant ``V1`` of +-0.5 and +-1
    rad; ``V1`` reversing at mid-time, ``+-a (1 - 2 tau)`` with ``a`` four times the nominal
    travel ``D``; and, for ``d1 >= 2``, ``V1`` late (``3 f D tau^2``, f in
    :data:`LATE_SCALES`: phi still while th1 moves first), early (``3 D (1 - tau)^2``) and back
    then forward (``f D (6 tau^2 - 2 tau)``, f in :data:`BACK_SCALES`), ``D`` signed like the
    joints' motion: the structures of the d_a-optimal paths where th1 must move a lot.
    """
    out: list[tuple[str, Callable, Callable | None]] = []
    if warm_start is not None:
        out.append(("warm_start", *_schedule_funcs(warm_start)))
    fam = _family_start(req)
    if fam is not None:
        out.append(("family_max_margin", *_schedule_funcs(fam)))
    trav = max(_travel(req), 0.25)
    a = 4.0 * trav
    for sg in (1.0, -1.0):
        out.append((f"reverse_v1={sg * a:+.3g}(1-2tau)",
                    (lambda tau, sg=sg: sg * a * (1.0 - 2.0 * np.asarray(tau, float))), None))
    for c in (0.5, -0.5, 1.0, -1.0):
        out.append((f"const_v1={c:+g}", _const(c), None))
    d = np.array(req.goal[1:]) - np.array(req.start[1:])
    D = (1.0 if float(np.sum(d)) >= 0.0 else -1.0) * trav
    if req.v1_degree is None or req.v1_degree >= 2:
        for f in LATE_SCALES:
            out.append((f"late_v1={3 * f * D:+.3g}tau^2",
                        (lambda tau, f=f: 3.0 * f * D * np.asarray(tau, float) ** 2), None))
        out.append((f"early_v1={3 * D:+.3g}(1-tau)^2",
                    (lambda tau: 3.0 * D * (1.0 - np.asarray(tau, float)) ** 2), None))
        for f in BACK_SCALES:
            # phi back first (moving th2.. toward their lower end), then forward: the shape of
            # the paths that keep d_a small when th1 must move a lot
            out.append((f"back_forward_v1={f * D:+.3g}(6tau^2-2tau)",
                        (lambda tau, f=f: f * D * (6.0 * np.asarray(tau, float) ** 2
                                                   - 2.0 * np.asarray(tau, float))), None))
    return out


# ---------------------------------------------------------------------- solving
@dataclass
class _Candidate:
    """One NLP solution (or the given warm start), with its true indicators."""

    name: str
    mode: Mode
    x: np.ndarray
    status: str
    iterations: int
    objective: float
    success: bool
    grid: int
    level: int = 0
    switch: int = 0
    cuts: np.ndarray = field(default_factory=lambda: np.zeros(3 * MAX_CUTS))
    reversal: float = math.inf
    inputs: InputSchedule | None = None
    indicators: Indicators | None = None
    score: tuple[float, float] = (math.inf, math.inf)
    region_ok: bool | None = None
    refined: bool = False


def _extrema(x: np.ndarray, dead_band: float = REVERSAL_DEAD_BAND) -> list[int]:
    """Indices of the interior extrema that :func:`optimizer.indicators.count_reversals`
    counts (the same hysteresis), in order."""
    out: list[int] = []
    direction, ext, iext = 0, x[0], 0
    for i in range(1, x.size):
        v = x[i]
        if direction >= 0 and v > ext:
            ext, iext = v, i
            if direction == 0 and v - x[0] > dead_band:
                direction = 1
        elif direction <= 0 and v < ext:
            ext, iext = v, i
            if direction == 0 and x[0] - v > dead_band:
                direction = -1
        if direction == 1 and ext - v > dead_band:
            out.append(iext)
            direction, ext, iext = -1, v, i
        elif direction == -1 and v - ext > dead_band:
            out.append(iext)
            direction, ext, iext = 1, v, i
    return out


def _new_cuts(req: PlanRequest, cand: _Candidate) -> list[tuple[float, float, float]]:
    """Cut pairs ``(ta, tb, direction)`` for the stretches where the candidate's th1 (sampled
    as for t_p) moves against the direction its mode requires there; largest first."""
    cf = chained_form(req.robot)
    tau = np.linspace(0.0, 1.0, SEARCH_SAMPLES)
    path = ChainedPath.from_inputs(cf.to_chained(req.q_start()), cand.inputs)  # type: ignore
    th1 = cf.from_chained(path.z(tau)).q[:, 1]
    sig0, sig1 = cand.mode.shape
    t_sw = float(tau[int(np.argmax(sig0 * th1))]) if cand.mode.switch else 2.0
    idx = [0] + _extrema(th1) + [tau.size - 1]
    out = []
    for a, b in zip(idx[:-1], idx[1:]):
        want = sig0 if 0.5 * (tau[a] + tau[b]) < t_sw else sig1
        moved = float(th1[b] - th1[a])
        if want * moved < 0.0:
            out.append((abs(moved), (float(tau[a]), float(tau[b]), float(want))))
    out.sort(key=lambda t: -t[0])
    return [c for _, c in out]


def score(req: PlanRequest, ind: Indicators) -> tuple[float, float]:
    """The request's rule on indicators (as in :mod:`.objectives`), smaller is better."""
    if req.objective == "tp_then_da":
        return float(ind.t_p), float(ind.d_a)
    if req.objective == "tp_then_sensitivity":
        return float(ind.t_p), float(ind.sensitivity)
    w = req.weights
    return 0.0, (w.d_a * ind.d_a + w.sensitivity * ind.sensitivity + w.energy * ind.energy
                 + w.t_p * ind.t_p)


def quick_indicators(req: PlanRequest, inputs: InputSchedule) -> Indicators | None:
    """Indicators of a schedule on the grid ``finish_plan`` uses, without the verification
    (None when the sampled path is not invertible)."""
    cf = chained_form(req.robot)
    path = ChainedPath.from_inputs(cf.to_chained(req.q_start()), inputs)
    T = req.duration_or_default
    td = np.linspace(0.0, T, SEARCH_SAMPLES)
    inv = cf.from_chained(path.z(td / T))
    if not inv.valid.all():
        return None
    sched = InputSchedule(inputs.breaks, inputs.v1, inputs.v2, T)
    u = cf.u_from_v(inv.q, sched.v(td))
    return compute_indicators(td, inv.q, u)


def _brief(ind: Indicators | None) -> dict[str, float] | None:
    if ind is None:
        return None
    return {"d_a_deg": math.degrees(ind.d_a), "t_p": ind.t_p, "phi_reversals": ind.phi_reversals,
            "sensitivity": ind.sensitivity}


class _Runner:
    """Solves, records and evaluates the candidates of one request."""

    def __init__(self, req: PlanRequest, deadline: Deadline, base: NLPKey) -> None:
        self.req = req
        self.deadline = deadline
        self.base = base
        self.full = make_region(req, "full")
        self.z0 = chained_form(req.robot).to_chained(req.q_start())
        self.tried: list[dict[str, Any]] = []
        self.pool: list[_Candidate] = []
        self.timed_out = False
        self.build_time = 0.0
        self.solve_time = 0.0
        self._problems: dict[NLPKey, _Problem] = {}

    def problem(self, level: int) -> _Problem:
        """The NLP of grid level ``level``: 0 is the base grid, each level up doubles it, and
        -1 is the coarse exploratory grid (:data:`EXPLORE_GRID`, loose tolerances)."""
        b = self.base
        if level < 0:
            grid = EXPLORE_GRID
        elif b.criterion == "z2":
            # under z2 a solution mostly fails the full check for the criterion, not for the
            # grid: the first refinement keeps the grid and switches to the full constraints
            grid = b.grid * 2 ** max(level - 1, 0)
        else:
            grid = b.grid * 2 ** level
        key = NLPKey(b.gains, b.exponents, b.v1_degree, b.v2_degree, b.segments,
                     grid, b.criterion if level <= 0 else "full",
                     b.constraint_kind, b.bounded_thn, b.points, level < 0)
        if key not in self._problems:
            t0 = time.perf_counter()
            nlp = get_nlp(key)
            self.build_time += time.perf_counter() - t0
            self._problems[key] = _Problem.create(self.req, nlp)
        return self._problems[key]

    def solve(self, name: str, mode: Mode, x_in: np.ndarray, level: int = 0,
              switch: int | None = None, cuts: np.ndarray | None = None,
              resolves: int = MAX_RESOLVES) -> _Candidate | None:
        """One IPOPT solve from the input coefficients ``x_in``, the exact goal projection, the
        checks and the true indicators; then, while the solution reverses where its mode does
        not allow it, re-solves from it with the switch moved or with cuts."""
        prob = self.problem(level)
        nlp = prob.nlp
        x0 = np.zeros(nlp.nx)
        x0[:nlp.n_inputs] = x_in[:nlp.n_inputs]
        if mode.switch and switch is None:
            switch = prob.switch_of(x0, mode)
        switch = switch or 0
        cuts = np.zeros(3 * MAX_CUTS) if cuts is None else np.asarray(cuts, float)
        info: dict[str, Any] = {"start": name, "mode": mode.name, "grid": nlp.key.grid}
        if mode.switch:
            info["switch_tau"] = float(nlp.taus[switch - 1])
        if np.any(cuts[2::3]):
            info["cuts"] = int(np.count_nonzero(cuts[2::3]))
        self.tried.append(info)
        if self.deadline.remaining <= MIN_START_TIME:
            self.timed_out = True
            info["ipopt_status"] = "not_run_deadline"
            return None
        p = prob.params(mode, switch, cuts)
        t0 = time.perf_counter()
        nlp.callback.stop_at = t0 + max(self.deadline.remaining, 0.0)
        try:
            sol = nlp.solver(x0=prob.initial(x0, p), p=p, lbx=nlp.lbx, ubx=nlp.ubx,
                             lbg=prob.lbg, ubg=prob.ubg)
        finally:
            nlp.callback.stop_at = math.inf
        dt = time.perf_counter() - t0
        self.solve_time += dt
        st = nlp.solver.stats()
        status = str(st.get("return_status", "unknown"))
        iters = int(st.get("iter_count", -1))
        info.update({"ipopt_status": status, "iterations": iters, "seconds": round(dt, 6)})
        if status in TIMEOUT:
            self.timed_out = True
        x = np.asarray(sol["x"]).ravel()
        if not np.all(np.isfinite(x)):
            return None
        x = prob.project_goal(x)
        viol = prob.violation(x, p)
        info["violation"] = viol
        # the penalty kind may leave tiny violations of the margin, never of the region
        tol = FEAS_TOL if nlp.key.constraint_kind == "hard" else 0.5 * MARGIN
        if not viol <= tol:
            return None
        parts = prob.evaluate(x, p)[2]
        fval = float(parts[-1])
        info.update({"objective": fval, "reversal": float(parts[0])})
        cand = _Candidate(name, mode, x, status, iters, fval, status in SUCCESS, nlp.key.grid,
                          level, switch, cuts.copy(), float(parts[0]))
        cand.inputs = prob.schedule(x)
        self._score(cand)
        info["indicators"] = _brief(cand.indicators)
        dup = any(c.mode.name == mode.name and c.grid == cand.grid and c.switch == switch
                  and abs(c.objective - fval) <= 1e-6 * max(1.0, abs(fval)) for c in self.pool)
        self.pool.append(cand)
        if dup:  # the same solution from another start: its follow-ups were already done
            info["duplicate"] = True
            return cand
        if resolves > 0 and cand.indicators is not None:
            nxt = self._follow_up(cand, prob, resolves)
            if nxt is not None:
                return nxt
        return cand

    def _follow_up(self, cand: _Candidate, prob: _Problem, resolves: int
                   ) -> _Candidate | None:
        """Re-solve a solution that reverses more than its mode allows: move the switch to
        where the solution turns, or (when the grid already sees the required shape) add cuts
        where it reverses between grid points."""
        allowed = 1 if cand.mode.switch else 0
        ind = cand.indicators
        if ind is None or ind.t_p <= allowed:
            return None
        if cand.mode.switch and cand.reversal > CUT_GATE:
            sw = prob.switch_of(cand.x, cand.mode)
            if sw != cand.switch:
                return self.solve(cand.name + f"+switch{sw}", cand.mode, cand.x, cand.level,
                                  sw, cand.cuts, resolves - 1)
        if cand.reversal > CUT_GATE:
            return None  # the shape itself is out of reach in this mode
        active = [tuple(cand.cuts[3 * k:3 * k + 3]) for k in range(MAX_CUTS)
                  if cand.cuts[3 * k + 2] != 0.0]
        new = [c for c in _new_cuts(self.req, cand) if c not in active]
        if not new:
            return None
        cuts = np.zeros(3 * MAX_CUTS)
        for k, c in enumerate((new + active)[:MAX_CUTS]):  # the newest (largest) first
            cuts[3 * k:3 * k + 3] = c
        return self.solve(cand.name + "+cuts", cand.mode, cand.x, cand.level, cand.switch,
                          cuts, resolves - 1)

    def _score(self, cand: _Candidate) -> None:
        ind = quick_indicators(self.req, cand.inputs)  # type: ignore[arg-type]
        cand.indicators = ind
        cand.score = score(self.req, ind) if ind is not None else (math.inf, math.inf)

    def add_schedule(self, name: str, inputs: InputSchedule) -> None:
        """Add a given schedule (the warm start itself) as a candidate."""
        cand = _Candidate(name, Mode("given", np.zeros(6), (1.0, 1.0)), np.zeros(0), "given", 0,
                          math.nan, True, 0, inputs=inputs)
        self._score(cand)
        if cand.indicators is not None:
            self.pool.append(cand)

    def check(self, cand: _Candidate) -> bool:
        """The continuous-path region check of ``finish_plan`` (memoised)."""
        if cand.region_ok is None:
            cand.region_ok = (cand.indicators is not None and cand.inputs is not None and bool(
                self.full.check_path(ChainedPath.from_inputs(self.z0, cand.inputs)).ok))
        return cand.region_ok

    def best(self) -> tuple[_Candidate | None, list[_Candidate]]:
        """The best candidate by the request's rule on its true indicators whose continuous
        path stays in the region; and the ones worth a finer grid: better-scored ones that
        leave the region, and ones (whose sampled path may already leave it) that have their
        mode's shape on the grid and a better NLP objective than every passing solution of
        their mode."""
        order = sorted(self.pool, key=lambda c: (c.score, not c.success,
                                                 c.objective if math.isfinite(c.objective)
                                                 else math.inf))
        winner = next((c for c in order if c.indicators is not None and self.check(c)), None)
        # per mode, the NLP objective of its best candidate that passes
        passing: dict[str, float] = {}
        for c in self.pool:
            if c.x.size and c.indicators is not None and self.check(c):
                passing[c.mode.name] = min(passing.get(c.mode.name, math.inf), c.objective)
        failed = []
        for c in self.pool:
            if c.x.size == 0 or (c.indicators is not None and self.check(c)):
                continue
            if (c.indicators is not None and (winner is None or c.score < winner.score)) or (
                    c.reversal <= CUT_GATE and c.objective < passing.get(c.mode.name, math.inf)):
                failed.append(c)
        failed.sort(key=lambda c: (c.score, c.objective))
        return winner, failed


def _search(run: _Runner, prob0: _Problem, modes: list[Mode],
            starts: list[tuple[str, Callable, Callable | None]], has_warm: bool, K: int
            ) -> _Candidate | None:
    """Rounds 1 and 2 and the grid refinement from one set of starts (see the module
    docstring); the best candidate so far (over every set tried), or None."""
    req, deadline, N = run.req, run.deadline, run.base.grid
    raw = []
    for name, V1, V2 in starts:
        x0 = prob0.fit(V1, V2 if V2 is not None else _const(0.0))
        raw.append((name, prob0.project_goal(x0) if V2 is None else x0))

    def screen(mode: Mode, limit: int) -> list[tuple[str, np.ndarray]]:
        """The warm start (always) and the first ``limit`` other starts, ranked by a cheap look
        at the NLP in ``mode`` (region violation on the grid, then objective)."""
        ranked = []
        for name, x0 in raw:
            p = prob0.params(mode, prob0.switch_of(x0, mode) if mode.switch else 0)
            _, reg, parts = prob0.evaluate(prob0.initial(x0, p), p)
            viol = float(np.sum(np.maximum(-reg, 0.0))) if reg.size else 0.0
            ranked.append(((0 if name == "warm_start" else 1, viol, float(parts[-1])), name, x0))
        ranked.sort(key=lambda t: t[0])
        keep = limit + (1 if has_warm else 0)
        for _, name, _ in ranked[keep:]:
            run.tried.append({"start": name, "mode": mode.name, "grid": N,
                              "ipopt_status": "not_run_prescreen"})
        return [(name, x0) for _, name, x0 in ranked[:keep]]

    # ---- round 1: the first mode (for the lexicographic objectives: no reversal of th1)
    impossible = 0
    for name, x0 in screen(modes[0], K):
        cand = run.solve(name, modes[0], x0)
        best, _ = run.best()
        if (len(modes) > 1 and best is not None and best.indicators is not None
                and best.indicators.t_p == 0 and best.indicators.d_a <= GOOD_DA):
            break  # no reversal and d_a small: good enough, time matters more
        if len(modes) > 1 and cand is not None and cand.reversal > IMPOSSIBLE_GATE:
            impossible += 1
            if impossible >= 2:
                break  # th1 cannot go without reversal here: spend the time on round 2

    # ---- round 2 (lexicographic objectives): exactly one reversal of th1 allowed, when no
    # solution without reversal was found. The landscape has many local minima, so every start
    # (and the best round-1 solution) is first solved roughly on a coarse grid; the best few
    # by NLP objective are then polished on the base grid
    best, _ = run.best()
    if len(modes) > 1 and (best is None or best.indicators is None or best.indicators.t_p > 0):
        polish_level = 1 if req.singularity == "z2" else 0
        seeds = sorted((c for c in run.pool if c.x.size), key=lambda c: (c.score, c.objective))
        seed_x = [(c.name, c.x) for c in seeds[:1]] + raw
        for mode in modes[1:]:
            rough = [c for c in (run.solve(name, mode, x0, level=-1, resolves=0)
                                 for name, x0 in seed_x) if c is not None]
            rough.sort(key=lambda c: c.objective)
            kept: list[_Candidate] = []
            for c in rough:
                if all(abs(c.objective - o.objective) > 1e-6 * max(1.0, abs(c.objective))
                       for o in kept):
                    kept.append(c)
            # polish the ones that reached the mode's shape (if any did): the others are
            # stuck with a reversal measure the polish will not remove
            shaped = [c for c in kept if c.reversal <= CUT_GATE] or kept
            for c in shaped[:POLISH]:
                # under z2 the polish already uses the full constraints: a returned plan must
                # pass the full check, and polishing under z2 alone mostly ran into max_iter
                run.solve(c.name, mode, c.x, level=polish_level, cuts=c.cuts)

    # ---- grid refinement for candidates whose continuous path leaves the region
    best, failed = run.best()
    for _ in range(2 * MAX_REFINEMENTS):
        todo = [c for c in failed if not c.refined and c.level < MAX_REFINEMENTS][:3]
        if not todo or deadline.remaining <= MIN_START_TIME:
            break
        for c in todo:
            c.refined = True
            grid_next = run.problem(c.level + 1).nlp.key.grid
            run.solve(f"{c.name}@full{grid_next}", c.mode, c.x, c.level + 1,
                      None if not c.mode.switch else None, c.cuts)
        best, failed = run.best()
    return best


def plan_penalty(req: PlanRequest, deadline: Deadline, *, warm_start: InputSchedule | None = None,
                 constraint_kind: str | None = None, segments: int | None = None,
                 grid: int | None = None, max_starts: int | None = None) -> Plan:
    """Plan with the penalty-function NLP (varying ``v1``; see the module docstring).

    Parameters
    ----------
    req : PlanRequest
        Uses start, goal, robot, objective and weights, singularity criterion, joint bounds,
        phi-change bounds (or the fixed ``phi_change``), constraint points, ``v1_degree`` and
        ``v2_degree``.
    deadline : Deadline
        Wall-clock budget shared with the caller.
    warm_start : InputSchedule, optional
        A plan's inputs to start from (e.g. the polynomial optimum): embedded exactly when its
        degrees fit, always solved from, and kept as a candidate, so that the result is never
        worse than it by the request's rule.
    constraint_kind : {"hard", "penalty"}, optional
        Singularity constraints as inequalities or as a quadratic penalty
        (default :data:`CONSTRAINT_KIND`).
    segments : int, optional
        Polynomial pieces of the inputs (default :data:`DEFAULT_SEGMENTS`).
    grid : int, optional
        Interior grid points of the first solve (default :data:`DEFAULT_GRID`).
    max_starts : int, optional
        Starts solved in the first round (default :data:`MAX_STARTS`).

    Returns
    -------
    Plan
        ``method == "penalty"``, verified on the original model by ``finish_plan``;
        ``diagnostics["penalty"]`` holds the winning start and mode, IPOPT's status and
        iterations, and what every solve did (``starts_tried``).

    Raises
    ------
    SolverTimeoutError
        No start finished before the deadline.
    InfeasibleError
        IPOPT reported infeasibility from every start, or no solution stays in the region on
        the continuous path even after grid refinement.
    NumericalError
        IPOPT failed from every start, or the verification on the original model failed.
    """
    t_start = time.perf_counter()
    kind = constraint_kind or CONSTRAINT_KIND
    if kind not in CONSTRAINT_KINDS:
        raise ValueError(f"constraint_kind must be one of {CONSTRAINT_KINDS}, not {kind!r}")
    n = req.n
    d1 = DEFAULT_V1_DEGREE if req.v1_degree is None else int(req.v1_degree)
    d2 = max(DEFAULT_V2_DEGREE, n + 2) if req.v2_degree is None else int(req.v2_degree)
    S = (DEFAULT_SEGMENTS if n < SHOOTING_FROM_N else 2) if segments is None else int(segments)
    N = DEFAULT_GRID if grid is None else int(grid)
    K = MAX_STARTS if max_starts is None else int(max_starts)
    if S < 1 or N < 3 or K < 1:
        raise ValueError("segments >= 1, grid >= 3 and max_starts >= 1 are required")
    if deadline.remaining <= MIN_START_TIME:
        raise SolverTimeoutError("no time left for the penalty method",
                                 diagnostics={"stage": "penalty", "time_limit": deadline.seconds})
    T = req.duration_or_default
    _, _, raw_lo, raw_hi = _margins(req)
    base = NLPKey(req.robot.gains, req.robot.exponents, d1, d2, S, N, req.singularity, kind,
                  bool(math.isfinite(raw_lo[-1]) or math.isfinite(raw_hi[-1])),
                  tuple((cp.time / T, int(cp.state)) for cp in req.constraint_points))
    run = _Runner(req, deadline, base)
    modes = modes_for(req)

    # ---- the start sets: for n >= SHOOTING_FROM_N a multiple-shooting start (with the warm
    # start) first, since the polynomial starts end far outside the narrow 4-joint region and
    # IPOPT then runs into its iteration limit at several ms an iteration; the polynomial
    # starts are the fallback
    prob0 = run.problem(0)
    if warm_start is not None:
        run.add_schedule("warm_start(unchanged)", warm_start)
    polynomial_starts = starts_for(req, warm_start)
    start_sets = [polynomial_starts]
    if n >= SHOOTING_FROM_N and deadline.remaining > MIN_START_TIME:
        shot = shooting_start(req, S, d1, d2)
        if shot is not None:
            start_sets.insert(0, [("multiple_shooting", *shot)] + [
                st for st in polynomial_starts if st[0] == "warm_start"])
    best: _Candidate | None = None
    for starts in start_sets:
        best = _search(run, prob0, modes, starts, warm_start is not None, K)
        if best is not None or deadline.remaining <= MIN_START_TIME:
            break

    timing = {"penalty_nlp": time.perf_counter() - t_start, "penalty_build": run.build_time,
              "penalty_ipopt": run.solve_time}
    if best is None:
        statuses = sorted({str(t.get("ipopt_status")) for t in run.tried})
        diag = {"penalty": {"starts_tried": run.tried, "statuses": statuses}}
        if run.timed_out and not any(t.get("ipopt_status") in SUCCESS for t in run.tried):
            raise SolverTimeoutError(
                f"the penalty method found no solution within the time limit of "
                f"{deadline.seconds:g} s",
                diagnostics={"stage": "penalty", "time_limit": deadline.seconds, **diag})
        if any(t.get("ipopt_status") in SUCCESS for t in run.tried):
            raise InfeasibleError(
                "the penalty method's solutions leave the singularity-free region between grid "
                "points even after grid refinement", diagnostics=diag)
        if "Infeasible_Problem_Detected" in statuses:
            raise InfeasibleError("IPOPT found the penalty NLP infeasible from every start (goal, "
                                  "joint bounds or phi_change bounds cannot be met inside the "
                                  "region)", diagnostics=diag)
        raise NumericalError("IPOPT failed from every start of the penalty method: "
                             + ", ".join(statuses), diagnostics=diag)

    diagnostics: dict[str, Any] = {
        "objective": req.objective, "singularity": req.singularity,
        "penalty": {
            "start": best.name, "mode": best.mode.name, "ipopt_status": best.status,
            "iterations": best.iterations,
            "objective_value": best.objective if math.isfinite(best.objective) else None,
            "grid": best.grid, "constraint_kind": kind, "v1_degree": d1, "v2_degree": d2,
            "segments": S, "starts_tried": run.tried,
        },
    }
    inputs = best.inputs
    assert inputs is not None
    inputs = InputSchedule(inputs.breaks, inputs.v1, inputs.v2, T)
    return finish_plan(req, inputs, "penalty", [], timing, diagnostics)


class PenaltyMethod(Method):
    name = "penalty"
    summary = ("the paper's Remark 3: the singularity-avoiding inequality as a penalty in the "
               "objective; phi may reverse")
    capabilities = Capabilities(constraint_points=True, fixed_phi_change=True,
                                reverses_phi=True, inputs="chained")

    def run(self, req: PlanRequest, ctx: PlanContext) -> Plan:
        warm = ctx.warm_start if isinstance(ctx.warm_start, InputSchedule) else None
        lo, hi = joint_limits(req)
        bounds = tuple(None if req.joint_bounds is None and j < req.n - 1 else (lo[j], hi[j])
                       for j in range(req.n))
        return plan_penalty(dataclasses.replace(req, joint_bounds=bounds), ctx.deadline,
                            warm_start=warm)
