"""The paper's input family for one request: ``v1 = b0`` constant, ``v2`` polynomial (eq 8-11).

For fixed start, goal, duration and constraint points the family has one parameter, ``dphi``.
:class:`PolynomialFamily` evaluates members (chained path, region margin, indicators), many at
once: the steering systems of all members share one factorisation
(:class:`optimizer.steering.FamilySystem`), the paths are polynomial coefficient arrays, and the
region checks and the indicators are vectorised over members (:meth:`Region.poly_minimum`,
:meth:`Region.grid_margins`). Single members are memoised (:attr:`PolynomialFamily.evaluate`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..chained_form import ChainedForm, chained_form
from ..indicators import count_reversals_columns, sensitivity_frobenius
from ..model import Robot
from ..region import PathCheck, PolyMinimum, Region
from ..steering import (ChainedPath, ConstraintPoint, FamilySystem, InputSchedule,
                        matmul_single_thread, polyval_rows, solve_polynomial)
from ..errors import InfeasibleError, SingularSystemError
from ..problem import PlanRequest
from .context import Deadline
from .rules import direction_conflict, make_region

#: Normalised-time samples used to evaluate indicators inside searches.
SEARCH_SAMPLES = 1001

_INF = float("inf")
_NO_TP = 10 ** 6


@dataclass(frozen=True)
class MemberEval:
    """One member of the family, evaluated.

    ``ok`` is True when the member's continuous path is inside the region under the request's
    criterion AND invertible (full region), so that it can be turned into joint space at all.
    Indicators are ``inf`` for members that are not ok.
    """

    dphi: float
    ok: bool
    margin: float
    t_p: int
    d_a: float
    sensitivity: float
    energy: float


@dataclass(frozen=True)
class SampledMembers:
    """Indicators of many members on sampled times (:meth:`PolynomialFamily.sample`).

    ``ok``: regular, and every sample inside the full region (and ``z2 < 0`` under the ``z2``
    criterion) with a positive margin; ``margin``: the smallest margin over the samples;
    ``t_p``, ``d_a``, ``energy``: as in :class:`MemberEval` (``10**6``, ``inf`` where not ok;
    ``t_p`` and ``energy`` only when asked for). ``dev``: ``|th1 - line|`` (D, G) when kept.
    """

    dphi: np.ndarray
    ok: np.ndarray
    margin: np.ndarray
    d_a: np.ndarray
    t_p: np.ndarray | None = None
    energy: np.ndarray | None = None
    dev: np.ndarray | None = None

    def member(self, i: int, n: int) -> MemberEval:
        d = float(self.dphi[i])
        if not self.ok[i]:
            return MemberEval(d, False, float(self.margin[i]), _NO_TP, _INF, _INF, _INF)
        return MemberEval(d, True, float(self.margin[i]),
                          int(self.t_p[i]) if self.t_p is not None else _NO_TP,
                          float(self.d_a[i]), float(sensitivity_frobenius(d, n)),
                          float(self.energy[i]) if self.energy is not None else _INF)


class PolynomialFamily:
    """Members ``dphi -> path`` of the paper's family for one request.

    Parameters
    ----------
    robot : Robot
    q0, qT : ndarray (n+1,)
        Start and goal (``phi`` entries ignored).
    duration : float
    points : tuple of ConstraintPoint
    region : Region
        The request's region (criterion and joint bounds).
    """

    def __init__(self, robot: Robot, q0: np.ndarray, qT: np.ndarray, duration: float,
                 points: tuple[ConstraintPoint, ...], region: Region,
                 deadline: "Callable[[str], None] | None" = None) -> None:
        self.robot = robot
        self.n = robot.n
        self.cf: ChainedForm = chained_form(robot)
        self.z0 = self.cf.to_chained(np.asarray(q0, float))
        self.zT = self.cf.to_chained(np.asarray(qT, float))
        self.duration = float(duration)
        self.points = points
        self.region = region
        # the full region (with the request's joint bounds) is always required to return a path
        self.full = region if region.criterion == "full" else Region(
            robot, "full", None if not region.has_custom_bounds else
            list(zip(region.lower, region.upper)), transform=self.cf)
        self.tau = np.linspace(0.0, 1.0, SEARCH_SAMPLES)
        # called with a stage name before every exact (continuous-path) evaluation; raises
        # SolverTimeoutError when the request's time is up
        self.deadline_check = deadline or (lambda stage: None)
        self.evaluate = functools.lru_cache(maxsize=4096)(self._evaluate)
        # a member's chained path (memoised: the planner confirms its chosen member, then
        # finishes the plan on the same path; the path object must not be modified)
        self.path: Callable[[float], ChainedPath] = functools.lru_cache(maxsize=64)(self._path)
        # eq (10-11) for all members at once
        self.system = FamilySystem(self.n, self.z0, self.zT, self.duration, points)

    def inputs(self, dphi: float) -> InputSchedule:
        return solve_polynomial(dphi, self.n, self.z0, self.zT, self.duration, self.points,
                                known_regular=self.system.surely_regular(dphi))

    def _path(self, dphi: float) -> ChainedPath:
        return ChainedPath.from_inputs(self.z0, self.inputs(dphi))

    def check(self, dphi: float) -> PathCheck:
        """Region check under the request's criterion."""
        try:
            return self.region.check_path(self.path(dphi))
        except SingularSystemError:
            return PathCheck(False, -np.inf, 0.0, 0.0)

    def confirm(self, dphi: float) -> tuple[bool, float]:
        """Whether the member's continuous path is inside the request's region and the full
        one (:meth:`Region.check_path` on :meth:`path`, as the finished plan is checked), and
        its margin under the request's criterion."""
        try:
            path = self.path(dphi)
        except SingularSystemError:
            return False, -np.pi
        chk = self.region.check_path(path)
        ok = chk.ok
        if ok and self.full is not self.region:
            ok = self.full.check_path(path).ok
        return ok, float(chk.margin)

    def margin(self, dphi: float) -> float:
        """Region margin of a member's continuous path (request's criterion); -pi if singular."""
        self.deadline_check("the interval search")
        return float(self.margins(np.array([float(dphi)])).margin[0])

    # ------------------------------------------------------------------ many members at once
    def polys(self, dphis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chained paths of many members: coefficients (D, n+1, L) in powers of ``tau`` and a
        mask of the members whose steering system is regular."""
        d = np.atleast_1d(np.asarray(dphis, float))
        a, ok = self.system.coefficients(d)
        return self.system.polys(d, a), ok

    def margins(self, dphis: np.ndarray, detail: bool = False) -> PolyMinimum:
        """Region margins (request's criterion) of many members' continuous paths at once
        (:meth:`Region.poly_minimum`); -pi for singular members."""
        coef, ok = self.polys(dphis)
        res = self.region.poly_minimum(coef, detail=detail)
        m = np.where(ok & np.isfinite(res.margin), res.margin, -np.pi)
        return PolyMinimum(m, res.argmin, res.joint, res.side, res.outside)

    def _components(self, coef: np.ndarray, taus: np.ndarray, only_z2: bool = False,
                    with_last: bool = True) -> np.ndarray:
        """``z2..z_{n+1}`` (or ``z2`` only, or without ``z_{n+1}``) of members at shared times,
        component first and samples before members: (C, G, D)."""
        comps = coef[:, 1:2, :] if only_z2 else coef[:, 1:, :] if with_last \
            else coef[:, 1:-1, :]
        C, L = comps.shape[1], comps.shape[2]
        taus = np.asarray(taus, float)
        V = np.ones((taus.size, L))
        for j in range(1, L):
            np.multiply(V[:, j - 1], taus, out=V[:, j])
        cT = np.ascontiguousarray(comps.transpose(2, 1, 0)).reshape(L, -1)   # (L, C*D)
        return matmul_single_thread(V, cT).reshape(taus.size, C, -1).transpose(1, 0, 2)

    def batch_z(self, dphis: np.ndarray, taus: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Chained states of many members at once: ``z`` of shape (D, G, n+1), a mask of
        members whose steering system is regular (eq 10-11 solved as a stack), and the ``V2``
        coefficients (D, p)."""
        d = np.atleast_1d(np.asarray(dphis, float))
        a, ok = self.system.coefficients(d)
        coef = self.system.polys(d, a)
        z = polyval_rows(coef, np.asarray(taus, float)).transpose(0, 2, 1)
        return z, ok, a

    def coarse_margins(self, dphis: np.ndarray, grid: int = 97) -> np.ndarray:
        """Region margin on a coarse time grid for many ``dphi`` at once (an upper bound of the
        continuous margin; used only to find brackets, never as the answer)."""
        taus = np.linspace(0.0, 1.0, grid)
        dphis = np.atleast_1d(np.asarray(dphis, float))
        # n >= 4: blocks of members (their work arrays stay in cache; measured ~1.5x faster)
        block = dphis.size if self.n == 3 else max(64, 24000 // grid)
        out = []
        for s in range(0, dphis.size, block):
            coef, ok = self.polys(dphis[s:s + block])
            Z = self._components(coef, taus, only_z2=self.region.criterion == "z2",
                                 with_last=self.region._thn_bounded)
            out.append(np.where(ok, self.region.grid_margins(Z), -np.pi))
        return np.concatenate(out) if len(out) > 1 else out[0]

    def coarse_inside(self, dphis: np.ndarray, grid: int = 97) -> np.ndarray:
        """``coarse_margins(dphis, grid) > 0``: the members whose sampled margin is positive.

        n = 3 with the default joint ranges (full criterion): a positive margin at a point is
        the same as both ``w = cos(th)^m`` of the inverse map strictly inside
        ``(W_TOL, 1 - W_TOL)`` (:meth:`Region.grid_inside`), which needs no angles.
        """
        if not (self.region._fast3 and self.region.criterion == "full"):
            return self.coarse_margins(dphis, grid) > 0.0
        dphis = np.atleast_1d(np.asarray(dphis, float))
        coef, ok = self.polys(dphis)
        Z = self._components(coef, np.linspace(0.0, 1.0, grid), with_last=False)
        return ok & self.region.grid_inside(Z)

    def sample(self, dphis: np.ndarray, taus: np.ndarray | None = None, tp: bool = True,
               energy: bool = False, keep_dev: bool = False) -> SampledMembers:
        """Indicators of many members on sampled times (default: the search samples); ``ok``
        means valid at the samples only (the continuous check is :meth:`margins`')."""
        d = np.atleast_1d(np.asarray(dphis, float))
        tau = self.tau if taus is None else np.asarray(taus, float)
        coef, regular = self.polys(d)
        Z = self._components(coef, tau, with_last=energy or self.full._thn_bounded)
        n = self.n
        angles = tuple(range(1, n + 1)) if energy else (1,)
        marg, th = self.full.grid_margins(Z, angles=angles)
        if self.region is not self.full:
            marg = np.minimum(marg, -np.max(Z[0], axis=0))
        ok = regular & (marg > 0.0)
        th1 = th[1]                                                  # (G, D)
        with np.errstate(invalid="ignore"):
            dev = np.abs(th1 - (th1[:1] + tau[:, None] * (th1[-1:] - th1[:1])))
            d_a = np.where(ok, np.max(dev, axis=0), _INF)
        t_p = None
        if tp:
            t_p = np.full(d.size, _NO_TP)
            if ok.any():
                t_p[ok] = count_reversals_columns(th1[:, ok])
        en = None
        if energy:
            en = np.full(d.size, _INF)
            idx = np.nonzero(ok)[0]
            if idx.size:
                G = tau.size
                q = np.empty((idx.size, G, n + 1))
                q[:, :, 0] = self.z0[0] + d[idx, None] * tau[None, :]
                for j in range(1, n + 1):
                    q[:, :, j] = th[j][:, idx].T
                V = np.empty((idx.size, G, 2))
                V[:, :, 0] = d[idx, None]
                # V2 = dz2/dtau
                c2 = coef[idx, 1, 1:] * np.arange(1, coef.shape[2])
                V[:, :, 1] = polyval_rows(c2, tau)
                with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                    U = self.cf.u_from_v(q.reshape(-1, n + 1), V.reshape(-1, 2)).reshape(
                        idx.size, G, 2) / self.duration
                    en[idx] = np.trapezoid(np.sum(U * U, axis=2), tau * self.duration, axis=1)
        return SampledMembers(d, ok, marg, d_a, t_p, en, dev.T if keep_dev else None)

    # ------------------------------------------------------------------ one member
    def _evaluate(self, dphi: float) -> MemberEval:
        self.deadline_check("the objective search")
        d = np.array([float(dphi)])
        coef, regular = self.polys(d)
        if not regular[0]:
            return MemberEval(float(dphi), False, -_INF, _NO_TP, _INF, _INF, _INF)
        margin = float(self.region.poly_minimum(coef).margin[0])
        ok = margin > 0.0
        if ok and self.full is not self.region:
            ok = float(self.full.poly_minimum(coef).margin[0]) > 0.0
        if not ok:
            return MemberEval(float(dphi), False, margin, _NO_TP, _INF, _INF, _INF)
        s = self.sample(d, energy=True)
        if not s.ok[0]:
            return MemberEval(float(dphi), False, margin, _NO_TP, _INF, _INF, _INF)
        return MemberEval(float(dphi), True, margin, int(s.t_p[0]) if s.t_p is not None else 0,
                          float(s.d_a[0]), float(sensitivity_frobenius(float(dphi), self.n)),
                          float(s.energy[0]) if s.energy is not None else _INF)

    def screen(self, dphis: np.ndarray) -> list[MemberEval]:
        """Indicators of many members on the search samples, vectorised; ``ok`` here means
        valid at the samples only (the continuous check is :meth:`evaluate`'s)."""
        dphis = np.asarray(dphis, float)
        if dphis.size == 0:
            return []
        s = self.sample(dphis, energy=True)
        return [s.member(i, self.n) for i in range(dphis.size)]


def family_for(req: PlanRequest, deadline: Deadline) -> PolynomialFamily:
    """The paper's family for ``req``; :class:`InfeasibleError` when no member can reach the
    goal (joints that must move in opposite directions, or not at all)."""
    conflict = direction_conflict(req)
    if conflict:
        raise InfeasibleError(conflict, diagnostics={"blocking": "opposite_joint_motion"})
    return PolynomialFamily(req.robot, req.q_start(), req.q_goal(0.0), req.duration_or_default,
                            req.constraint_points, make_region(req), deadline.check)
