"""The singularity-free region and path margins (paper eq 7, 13; NOTES §5).

The chained-form transform is invertible where ``th_1, ..., th_{n-1}`` all lie in (0, pi/2)
(``th_n`` is free). The paper's condition ``z2 < 0`` (eq 13) is necessary for n = 3 but not
sufficient; it is offered as the criterion ``"z2"``. Optional joint bounds shrink the region.

Margins
-------
``full``: the smallest distance (rad) of ``th_1..th_{n-1}`` from their bounds (and of ``th_n``
from its bounds when given) over the path; negative outside. ``z2``: ``-max z2`` over the path.

A path is checked on the continuous path, not only on samples: the signed margin is evaluated on
a dense grid that also contains the exact roots and critical points of the polynomial boundary
conditions (``z2 = 0`` and ``z_n in {0, K_n}``), every sampled local minimum is refined by bounded
scalar minimisation, and the first crossing is located by Brent's method.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.polynomial import polynomial as P
from scipy.optimize import brentq

from .chained_form import ChainedForm, chained_form
from .errors import InvalidRequestError
from .model import Robot
from .steering import ChainedPath

CRITERIA = ("full", "z2")
HALF_PI = 0.5 * math.pi


@dataclass(frozen=True)
class PathCheck:
    """Result of checking a whole path against the region.

    Attributes
    ----------
    ok : bool
        The path stays strictly inside (margin > 0).
    margin : float
        See the module docstring; negative when the path leaves the region.
    argmin_tau : float
        Normalised time of the smallest margin.
    first_crossing_tau : float or None
        Normalised time where the path first leaves the region (None when it never does).
    """

    ok: bool
    margin: float
    argmin_tau: float
    first_crossing_tau: float | None


class Region:
    """The singularity-free region of one robot, with optional joint bounds.

    Parameters
    ----------
    robot : Robot
    criterion : {"full", "z2"}
    joint_bounds : sequence of (lo, hi), optional
        Bounds (rad) for ``th_1..th_n``; for ``th_1..th_{n-1}`` they must lie inside [0, pi/2].
        ``None`` entries keep the default.
    """

    def __init__(self, robot: Robot, criterion: str = "full",
                 joint_bounds: Sequence[tuple[float, float] | None] | None = None,
                 transform: ChainedForm | None = None) -> None:
        if criterion not in CRITERIA:
            raise InvalidRequestError(f"singularity = {criterion!r} must be one of {CRITERIA}",
                                      field="singularity")
        self.robot = robot
        self.criterion = criterion
        self.cf = transform or chained_form(robot)
        n = robot.n
        lo = np.array([0.0] * (n - 1) + [-np.inf])
        hi = np.array([HALF_PI] * (n - 1) + [np.inf])
        if joint_bounds is not None:
            if len(joint_bounds) != n:
                raise InvalidRequestError(f"joint_bounds must have n = {n} entries",
                                          field="joint_bounds")
            for i, b in enumerate(joint_bounds):
                if b is None:
                    continue
                l, h = float(b[0]), float(b[1])
                if not (math.isfinite(l) and math.isfinite(h) and l < h):
                    raise InvalidRequestError(
                        f"joint_bounds[{i}] = [{l}, {h}] must be finite with lo < hi",
                        field=f"joint_bounds[{i}]")
                if i < n - 1 and (l < 0.0 or h > HALF_PI):
                    raise InvalidRequestError(
                        f"joint_bounds[{i}] = [{l}, {h}] must lie inside [0, pi/2] (the region "
                        f"where the chained form is invertible)", field=f"joint_bounds[{i}]")
                lo[i], hi[i] = l, h
        self.lower = lo
        self.upper = hi
        self.has_custom_bounds = joint_bounds is not None

    # --------------------------------------------------------------- points
    def margin_q(self, q: np.ndarray) -> np.ndarray:
        """Distance (rad) of joint-space points from the bounds, negative outside; shape (N,)."""
        qq = np.atleast_2d(np.asarray(q, float))
        th = qq[:, 1:]
        with np.errstate(invalid="ignore"):
            d = np.minimum(th - self.lower, self.upper - th)
        return np.min(d, axis=1)

    def check_point_q(self, q: np.ndarray, field: str) -> None:
        """Raise :class:`InvalidRequestError` when a joint-space point is outside the region."""
        q = np.asarray(q, float)
        for i in range(self.robot.n):
            th = q[i + 1]
            if not (self.lower[i] < th < self.upper[i]):
                lo, hi = self.lower[i], self.upper[i]
                raise InvalidRequestError(
                    f"{field}[{i}] = {th:.6g} rad ({math.degrees(th):.4g} deg) is outside "
                    f"({lo:.6g}, {hi:.6g}) rad: the chained-form transform is singular or the joint "
                    f"bound is violated there", field=f"{field}[{i}]")

    def signed_margin_z(self, z: np.ndarray) -> np.ndarray:
        """Continuous signed margin of chained points (see the module docstring); shape (N,)."""
        zz = np.atleast_2d(np.asarray(z, float))
        if self.criterion == "z2":
            return -zz[:, 1]
        inv = self.cf.from_chained(zz)
        out = np.empty(zz.shape[0])
        v = inv.valid
        if v.any():
            out[v] = self.margin_q(inv.q[v])
        if (~v).any():
            bad = np.nonzero(~v)[0]
            lvl = inv.failed_level[bad]
            wk = inv.w[bad, lvl - 1]
            m = np.array(self.robot.exponents)[lvl - 1]
            # Outside, extend the angle margin by its local shape at the boundary:
            # th ~ pi/2 - w^(1/m) near w = 0 and th ~ sqrt(2 (1 - w) / m) near w = 1, so the
            # margin stays continuous (and of one scale) across the boundary.
            with np.errstate(invalid="ignore", over="ignore"):
                below = -np.abs(wk) ** (1.0 / m)
                above = -np.sqrt(2.0 * np.abs(wk - 1.0) / m)
            ext = np.where(wk <= 0.5, below, above)
            out[bad] = np.where(np.isfinite(ext), np.minimum(ext, 0.0), -HALF_PI)
        return out

    # --------------------------------------------------------------- paths
    def _exact_points(self, path: ChainedPath) -> list[float]:
        """Roots and critical points in [0, 1] of the polynomial boundary conditions."""
        n = self.robot.n
        comps = [(1, 0.0)]  # z2 = 0
        if self.criterion == "full":
            Kn = self.robot.gains[-1]
            comps += [(n - 1, 0.0), (n - 1, Kn)]  # z_n in {0, K_n}  <=>  th_{n-1} in {pi/2, 0}
        pts: list[float] = []
        for k, level in comps:
            for a, b, c in path.component_pieces(k):
                c = np.array(c, float)
                c[0] -= level
                for poly in (c, P.polyder(c)):
                    if poly.size < 2 or not np.any(poly[1:]):
                        continue
                    r = P.polyroots(poly)
                    r = r[np.abs(r.imag) < 1e-9].real + a
                    pts.extend(float(x) for x in r if a <= x <= b)
        return pts

    def check_path(self, path: ChainedPath, grid: int = 257, locate: bool = True) -> PathCheck:
        """Check a chained path on [0, 1] against the region, on the continuous path.

        Parameters
        ----------
        path : ChainedPath
        grid : int
            Number of uniform samples before refinement.
        locate : bool
            Locate the first crossing (skip it when only the margin is needed).
        """
        taus = np.unique(np.concatenate([np.linspace(0.0, 1.0, grid), path.inputs.breaks,
                                         np.array(self._exact_points(path))]))
        if self.criterion == "z2":
            return self._check_z2(path, taus)

        def h(t: float) -> float:
            return float(self.signed_margin_z(path.z(np.array([t])))[0])

        vals = self.signed_margin_z(path.z(taus))
        crossing: float | None = None
        bad = np.nonzero(vals <= 0.0)[0]
        if bad.size:
            j = int(bad[0])
            crossing = 0.0 if (j == 0 or not locate) else _root(h, taus[j - 1], taus[j])
        # Refine every sampled local minimum (ends included) by zooming in, all at once.
        last = len(taus) - 1
        cand = np.array([i for i in range(len(taus))
                         if (i == 0 or vals[i] <= vals[i - 1])
                         and (i == last or vals[i] <= vals[i + 1])])
        lo = taus[np.maximum(cand - 1, 0)]
        hi = taus[np.minimum(cand + 1, last)]
        mins, argmins = _zoom_minimise(lambda t: self.signed_margin_z(path.z(t)), lo, hi)
        best_val, best_tau = float(vals.min()), float(taus[int(vals.argmin())])
        k = int(np.argmin(mins))
        if mins[k] < best_val:
            best_val, best_tau = float(mins[k]), float(argmins[k])
        for i, val, tm in zip(cand, mins, argmins):
            if val <= 0.0 and vals[i] > 0.0 and locate:
                # a dip between samples: the crossing is between the left sample and the minimum
                left = float(lo[list(cand).index(i)])
                c = _root(h, left, float(tm)) if h(left) > 0.0 else left
                if crossing is None or c < crossing:
                    crossing = c
        if not locate and best_val <= 0.0 and crossing is None:
            crossing = best_tau  # not located: only known to exist
        ok = crossing is None and best_val > 0.0
        return PathCheck(ok=ok, margin=best_val, argmin_tau=best_tau, first_crossing_tau=crossing)

    def _check_z2(self, path: ChainedPath, taus: np.ndarray) -> PathCheck:
        # z2 is a polynomial: its maximum is attained at a critical point or an end, which
        # _exact_points already put into taus; the crossing is an exact root.
        z2 = path.z(taus)[:, 1]
        i = int(np.argmax(z2))
        margin = -float(z2[i])
        crossing = None
        # the exact roots of z2 are among taus; allow for their rounding when locating
        bad = np.nonzero(z2 >= -1e-13)[0]
        if bad.size:
            crossing = float(taus[bad[0]])
        return PathCheck(ok=margin > 0.0, margin=margin, argmin_tau=float(taus[i]),
                         first_crossing_tau=crossing)


def _root(f, a: float, b: float) -> float:
    """The boundary crossing in [a, b] where f(a) > 0 >= f(b) (Brent; bisection if f is flat)."""
    fa, fb = f(a), f(b)
    if fa <= 0.0:
        return a
    if fb == 0.0:
        return b
    return float(brentq(f, a, b, xtol=1e-13, maxiter=200))


def _zoom_minimise(f, lo: np.ndarray, hi: np.ndarray, points: int = 33, rounds: int = 5
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Minimise ``f`` (vectorised over times) on many brackets ``[lo_i, hi_i]`` at once.

    Each round samples every bracket at ``points`` nodes and shrinks it to the two cells around
    its best node (a factor ``(points - 1) / 2`` per round), so five rounds shrink a bracket by
    16^5 ~ 1e6: for the smooth margins here the minimum is then exact to rounding.
    """
    lo = np.asarray(lo, float).copy()
    hi = np.asarray(hi, float).copy()
    grid = np.linspace(0.0, 1.0, points)
    best = np.full(lo.size, np.inf)
    arg = lo.copy()
    for _ in range(rounds):
        t = lo[:, None] + (hi - lo)[:, None] * grid[None, :]
        v = f(t.ravel()).reshape(t.shape)
        j = np.argmin(v, axis=1)
        rows = np.arange(lo.size)
        better = v[rows, j] < best
        best = np.where(better, v[rows, j], best)
        arg = np.where(better, t[rows, j], arg)
        step = (hi - lo) / (points - 1)
        lo, hi = np.maximum(t[rows, j] - step, lo), np.minimum(t[rows, j] + step, hi)
    return best, arg
