"""Cutting planes of the non-affine region conditions of the constraint-point QP.

``th_1..th_{n-2}`` in their ranges, i.e. ``w_k = cos(th_{k-1})^m_k`` inside
``[cos(hi - rho)^m, cos(lo + rho)^m]`` for k = 2..n-1, are not affine in the chained state. With
``z_k = a_k w_k + b_k`` (``a_k``, ``b_k`` functions of the levels above, compiled with CasADi in
:class:`LevelMaps`; ``sign a_k = (-1)^(n-k)`` on the region), ``w_k <= c`` reads
``h(z) = s (z_k - b_k(z) - c a_k(z)) <= 0``; :func:`add_level_cuts` linearises ``h`` at points of
a path into affine rows of the QP (see :mod:`.constraint_qp` for which cuts accumulate).
"""

from __future__ import annotations

import functools
import math
from typing import Callable

import casadi as ca
import numpy as np

from ..chained_form import ChainedForm, chained_form
from ..model import Robot

#: Relative shortfall of the angle margin tolerated without another cut round.
MARGIN_SLACK = 0.1


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
        K = ca.DM(cf.gains)      # this robot's numbers: the function is built per robot
        z = ca.SX.sym("z", n + 1)
        th, _ = sym.inverse_expr(z, K)
        qv = ca.vertcat(z[0], *th)
        a = ca.vertcat(*[sym.a[k](qv, K) for k in self.levels])
        b = ca.vertcat(*[sym.b[k](qv, K) for k in self.levels])
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



def add_level_cuts(cuts: dict[tuple, tuple[float, np.ndarray, float]],
              levels: LevelMaps | None, gain_n: float,
              thresholds: Callable[[float], tuple[np.ndarray, np.ndarray]], Z: np.ndarray,
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
    if levels is None or not levels.levels:
        return 0
    n = levels.n
    a, b, Ja, Jb = levels(Z)
    # level validity from the top: z_n is affine; each level needs the ones above inside
    wn = Z[:, n - 1] / gain_n
    above_ok = (wn > 0.0) & (wn < 1.0)
    if seed:
        w_lo_t, w_hi_t = w_lo, w_hi
    else:
        w_lo_t, w_hi_t = thresholds((1.0 - MARGIN_SLACK) * (rho or 0.0))
    added = 0
    for li in reversed(range(len(levels.levels))):
        k = levels.levels[li]
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

