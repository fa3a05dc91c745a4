"""The paper's input family for one request: ``v1 = b0`` constant, ``v2`` polynomial (eq 8-11).

For fixed start, goal, duration and constraint points the family has one parameter, ``dphi``.
:class:`PolynomialFamily` evaluates a member (chained path, region margin, indicators) and
memoises it, so that the interval search and the objective search share the work.
"""

from __future__ import annotations

import functools
from typing import Callable
from dataclasses import dataclass

import numpy as np

from ..chained_form import ChainedForm, chained_form
from ..indicators import count_reversals, line_deviation, sensitivity_frobenius
from ..model import Robot
from ..region import PathCheck, Region
from ..steering import (MAX_CONDITION, MIN_ABS_DPHI, ChainedPath, ConstraintPoint, InputSchedule,
                        affine_basis_batch, solve_polynomial)
from ..errors import SingularSystemError

#: Normalised-time samples used to evaluate indicators inside searches.
SEARCH_SAMPLES = 1001


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

    def inputs(self, dphi: float) -> InputSchedule:
        return solve_polynomial(dphi, self.n, self.z0, self.zT, self.duration, self.points)

    def path(self, dphi: float) -> ChainedPath:
        return ChainedPath.from_inputs(self.z0, self.inputs(dphi))

    def check(self, dphi: float) -> PathCheck:
        """Region check under the request's criterion."""
        try:
            return self.region.check_path(self.path(dphi))
        except SingularSystemError:
            return PathCheck(False, -np.inf, 0.0, 0.0)

    def margin(self, dphi: float) -> float:
        self.deadline_check("the interval search")
        try:
            m = self.region.check_path(self.path(dphi), locate=False).margin
        except SingularSystemError:
            return -np.pi
        return float(m) if np.isfinite(m) else -np.pi

    def batch_z(self, dphis: np.ndarray, taus: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Chained states of many members at once: ``z`` of shape (D, G, n+1), a mask of
        members whose steering system is regular (eq 10-11 solved as a stack), and the ``V2``
        coefficients (D, p)."""
        dphis = np.asarray(dphis, float)
        n, p = self.n, self.n + len(self.points)
        ok = np.abs(dphis) >= MIN_ABS_DPHI
        d = np.where(ok, dphis, 1.0)
        # steering systems (eq 11) of all members at once: terminal rows, then constraint rows
        t_rows = np.array([1.0] + [cp.time / self.duration for cp in self.points])
        free_r, basis_r = affine_basis_batch(d, n, self.z0, p, t_rows)
        M = np.concatenate([basis_r[:, 0]] + [basis_r[:, 1 + j, cp.state - 2][:, None, :]
                                              for j, cp in enumerate(self.points)], axis=1)
        r = np.concatenate([self.zT[None, 1:] - free_r[:, 0]]
                           + [cp.value - free_r[:, 1 + j, cp.state - 2][:, None]
                              for j, cp in enumerate(self.points)], axis=1)
        scale = np.linalg.norm(M, axis=1, keepdims=True)
        scale[scale == 0.0] = 1.0
        Mscaled = M / scale
        cond = np.linalg.cond(Mscaled)
        ok &= np.isfinite(cond) & (cond < MAX_CONDITION)
        Mscaled[~ok] = np.eye(p)
        a = np.linalg.solve(Mscaled, r[..., None])[..., 0] / scale[:, 0, :]
        free, basis = affine_basis_batch(d, n, self.z0, p, taus)
        z = np.empty((d.size, taus.size, n + 1))
        z[:, :, 0] = self.z0[0] + d[:, None] * taus[None, :]
        z[:, :, 1:] = free + np.einsum("dgki,di->dgk", basis, a)
        return z, ok, a

    def coarse_margins(self, dphis: np.ndarray, grid: int = 97) -> np.ndarray:
        """Region margin on a coarse time grid for many ``dphi`` at once (an upper bound of the
        continuous margin; used only to find brackets, never as the answer)."""
        taus = np.linspace(0.0, 1.0, grid)
        z, ok, _ = self.batch_z(dphis, taus)
        h = self.region.signed_margin_z(z.reshape(-1, self.n + 1)).reshape(dphis.size, grid)
        return np.where(ok, h.min(axis=1), -np.pi)

    def _evaluate(self, dphi: float) -> MemberEval:
        self.deadline_check("the objective search")
        inf = float("inf")
        try:
            path = self.path(dphi)
        except SingularSystemError:
            return MemberEval(dphi, False, -inf, 10 ** 6, inf, inf, inf)
        chk = self.region.check_path(path)
        ok = chk.ok
        if ok and self.full is not self.region:
            ok = self.full.check_path(path).ok
        if not ok:
            return MemberEval(dphi, False, chk.margin, 10 ** 6, inf, inf, inf)
        z = path.z(self.tau)
        inv = self.cf.from_chained(z)
        if not inv.valid.all():
            return MemberEval(dphi, False, chk.margin, 10 ** 6, inf, inf, inf)
        q = inv.q
        th1 = q[:, 1]
        d_a = float(np.max(np.abs(line_deviation(self.tau, th1))))
        t_p = count_reversals(th1)
        V = path.inputs.V(self.tau)
        U = self.cf.u_from_v(q, V) / self.duration
        energy = float(np.trapezoid(np.sum(U * U, axis=1), self.tau * self.duration))
        sens = float(sensitivity_frobenius(dphi, self.n))
        return MemberEval(dphi, True, chk.margin, t_p, d_a, sens, energy)

    def screen(self, dphis: np.ndarray) -> list[MemberEval]:
        """Indicators of many members on the search samples, vectorised; ``ok`` here means
        valid at the samples only (the continuous check is :meth:`evaluate`'s)."""
        dphis = np.asarray(dphis, float)
        if dphis.size == 0:
            return []
        inf = float("inf")
        G = self.tau.size
        z, regular, a = self.batch_z(dphis, self.tau)
        flat = z.reshape(-1, self.n + 1)
        inv = self.cf.from_chained(flat)
        valid = inv.valid.reshape(dphis.size, G).all(axis=1) & regular
        marg = self.full.margin_q(inv.q).reshape(dphis.size, G).min(axis=1)
        if self.region is not self.full:
            marg = np.minimum(marg, -z[:, :, 1].max(axis=1))
        q = inv.q.reshape(dphis.size, G, self.n + 1)
        th1 = q[:, :, 1]
        dev = th1 - (th1[:, :1] + self.tau[None, :] * (th1[:, -1:] - th1[:, :1]))
        d_a = np.abs(dev).max(axis=1)
        V2 = np.polynomial.polynomial.polyval(self.tau, a.T)          # (D, G)
        V = np.stack([np.broadcast_to(dphis[:, None], V2.shape), V2], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # invalid members' rows are garbage (q = 0 there) and are discarded below
            U = self.cf.u_from_v(inv.q, V.reshape(-1, 2)).reshape(dphis.size, G, 2) / self.duration
            energy = np.trapezoid(np.sum(U * U, axis=2), self.tau * self.duration, axis=1)
        out = []
        for i, d in enumerate(dphis):
            if not (valid[i] and marg[i] > 0):
                out.append(MemberEval(float(d), False, float(marg[i]), 10 ** 6, inf, inf, inf))
                continue
            out.append(MemberEval(float(d), True, float(marg[i]), count_reversals(th1[i]),
                                  float(d_a[i]), float(sensitivity_frobenius(d, self.n)),
                                  float(energy[i])))
        return out
