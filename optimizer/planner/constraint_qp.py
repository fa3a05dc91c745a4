"""The constraint-point QP with cuts at one ``dphi`` (issue 3.3): one request's start, goal,
duration, joint bounds and constraint points, solved for the least-energy singularity-free ``V2``.

Formulation (fixed ``dphi``)
----------------------------
With ``V1 = dphi`` (normalised time ``tau = t / T``) the chained state is affine in the
coefficients of ``V2`` (eq 10, :func:`optimizer.steering.affine_basis`). ``V2`` gets degree
``n - 1 + m`` (``m`` extra coefficients beyond the paper's ``n``, plus one per constraint point
of the request), written in the orthonormal shifted-Legendre basis
``V2(tau) = sum_j x_j sqrt(2j+1) P_j(2 tau - 1)``:

* energy: ``int_0^1 V2^2 dtau = x^T (L^T H L) x = ||x||^2`` exactly, ``H_ij = 1/(i+j+1)`` the
  Gram matrix of the monomials and ``L`` the basis change (:func:`.legendre_qp.legendre_to_monomial`). In
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
:class:`.level_cuts.LevelMaps`; ``sign a_k = (-1)^(n-k)`` on the region), ``w_k <= c`` reads
``h(z) = s (z_k - b_k(z) - c a_k(z)) <= 0``. Where the solution violates, or comes within
:data:`.level_cuts.MARGIN_SLACK` of, a target on the grid or at the checker's worst point, ``h`` is
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
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from numpy.polynomial import polynomial as P
from scipy.linalg import null_space

from ..chained_form import chained_form
from ..errors import SingularSystemError
from ..problem import PlanRequest
from ..region import PathCheck, Region
from ..steering import (MIN_ABS_DPHI, ChainedPath, ConstraintPoint, InputSchedule, affine_basis,
                        solve_polynomial)
from .legendre_qp import (chebyshev_grid, gram_monomials, legendre_to_monomial, single_piece,
                          solve_qp)
from .level_cuts import add_level_cuts, level_maps
from .rules import make_region

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
        return single_piece(dphi, self.L @ x, self.T)

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
        inputs = single_piece(s.dphi, v2, self.T)
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
            add_level_cuts(cuts, self.levels, float(self.K[-1]), self.thresholds, Zr,
                           self.grid, w_lo, w_hi, None, seed=True)
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
            added = add_level_cuts(cuts, self.levels, float(self.K[-1]), self.thresholds,
                                   path.z(taus_lin), taus_lin, w_lo, w_hi, rho)
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

    @property
    def solves(self) -> int:
        """How many distinct ``dphi`` have been solved (the memo's size)."""
        return len(self._cache)
