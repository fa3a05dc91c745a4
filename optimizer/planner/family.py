"""The paper's input family for one request: ``v1 = b0`` constant, ``v2`` polynomial (eq 8-11).

For fixed start, goal, duration and constraint points the family has one parameter, ``dphi``.
:class:`PolynomialFamily` evaluates a member (chained path, region margin, indicators) and
memoises it, so that the interval search and the objective search share the work.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..chained_form import ChainedForm, chained_form
from ..indicators import count_reversals, line_deviation, sensitivity_frobenius
from ..model import Robot
from ..region import PathCheck, Region
from ..steering import ChainedPath, ConstraintPoint, InputSchedule, solve_polynomial
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
                 points: tuple[ConstraintPoint, ...], region: Region) -> None:
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
        m = self.check(dphi).margin
        return float(m) if np.isfinite(m) else -np.pi

    def coarse_margins(self, dphis: np.ndarray, grid: int = 97) -> np.ndarray:
        """Region margin on a coarse time grid for many ``dphi`` at once (an upper bound of the
        continuous margin; used only to find brackets, never as the answer)."""
        out = np.full(dphis.size, -np.pi)
        taus = np.linspace(0.0, 1.0, grid)
        zs = []
        keep = []
        for i, d in enumerate(dphis):
            try:
                zs.append(self.path(float(d)).z(taus))
                keep.append(i)
            except SingularSystemError:
                continue
        if not keep:
            return out
        Z = np.concatenate(zs)
        h = self.region.signed_margin_z(Z).reshape(len(keep), grid)
        out[np.array(keep)] = h.min(axis=1)
        return out

    def _evaluate(self, dphi: float) -> MemberEval:
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
