"""The signed margin of chained points from the region's bounds (paper eq 7, 13; NOTES §5).

Margins
-------
``full``: the smallest distance (rad) of ``th_1..th_{n-1}`` from their bounds (and of ``th_n``
from its bounds when given) over the path; negative outside. ``z2``: ``-max z2`` over the path.

At one point the inverse map is taken top-down (``th_n``, then ``th_{n-1}``, ...). The point's
signed margin is the smallest margin of the joints found so far (``th_n`` and ``th_{n-1}`` down
to the first joint the inverse cannot give), and, when the inverse fails at some joint, the
margin of that joint extended outside by its local shape (see :meth:`PointMargins.signed_margin_z`):
inside the region this is the joints' distance from their bounds; outside it is negative.

Speed: the inverse map is evaluated with numpy (:mod:`optimizer.inverse_levels`); a grid of
members is reduced per member in ``w = cos(th)^m`` space (:meth:`PointMargins.grid_margins`),
where every joint's margin is unimodal, so that only two values per member and joint are turned
into angles.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .chained_form import W_TOL, ChainedForm
from .inverse_levels import InverseLevels, inverse_levels, root_m
from .model import Robot

HALF_PI = 0.5 * math.pi


class PointMargins:
    """Signed margins of chained points for given joint ranges (the region's point engine).

    Parameters
    ----------
    robot : Robot
    criterion : {"full", "z2"}
    lower, upper : ndarray (n,)
        Ranges (rad) of ``th_1..th_n``, already validated (see :class:`optimizer.region.Region`).
    transform : ChainedForm
    """

    def __init__(self, robot: Robot, criterion: str, lower: np.ndarray, upper: np.ndarray,
                 transform: ChainedForm) -> None:
        self.robot = robot
        self.criterion = criterion
        self.cf = transform
        n = robot.n
        lo, hi = lower.tolist(), upper.tolist()
        self.lower = lower
        self.upper = upper
        self._n = n
        self._m = robot.exponents
        # joints 1..n-1 with their default range (0, pi/2): the margin is min(th, pi/2 - th)
        self._default = [lo[j - 1] == 0.0 and hi[j - 1] == HALF_PI for j in range(1, n)]
        self._thn_bounded = math.isfinite(lo[n - 1]) or math.isfinite(hi[n - 1])
        self._lv: InverseLevels | None = None
        # n = 3 with the default ranges: a short path for points all inside (see _values3)
        self._fast3 = n == 3 and all(self._default) and not self._thn_bounded
        if n == 3:
            K2, K3 = robot.gains
            self._inv_k3 = 1.0 / K3
            self._neg_a = -robot.exponents[1] * K2 * K3


    @property
    def _level_maps(self) -> InverseLevels:
        if self._lv is None:
            self._lv = inverse_levels(self.robot)
        return self._lv

    def signed_margin_z(self, z: np.ndarray) -> np.ndarray:
        """Continuous signed margin of chained points (see the module docstring); shape (N,).

        Outside, the margin of the joint where the inverse fails is extended by its local shape
        at the boundary: ``th ~ pi/2 - w^(1/m)`` near ``w = cos(th)^m = 0`` and
        ``th ~ sqrt(2 (1 - w) / m)`` near ``w = 1``, so the margin stays continuous (and of one
        scale) across the boundary.
        """
        zz = np.atleast_2d(np.asarray(z, float))
        return np.asarray(self.values([zz[:, k] for k in range(1, self._n + 1)]))

    def values(self, Zr: Sequence[np.ndarray] | np.ndarray, detail: bool = False,
               _general: bool = False) -> Any:
        """Signed margins of points given by their chained components ``Zr = [z2, ..., z_{n+1}]``
        (arrays of one shape; ``z_{n+1}`` may be left out unless ``th_n`` is bounded). With
        ``detail``: ``(margin, joint, side, outside)`` (see :class:`PolyMinimum`)."""
        n = self._n
        z2 = np.asarray(Zr[0], float)
        if self.criterion == "z2":
            if detail:
                zero = np.zeros(z2.shape, int)
                return -z2, zero, zero + 1, np.zeros(z2.shape, bool)
            return -z2
        if self._fast3 and not detail and not _general:
            z3 = np.asarray(Zr[1], float)
            h, bad = self._values3(z2, z3)
            if bad is None:
                return h
            # the points the short path cannot take, through the general one
            idx = np.flatnonzero(bad)
            if idx.size < 0.5 * bad.size:
                sub = self.values([z2.ravel()[idx], z3.ravel()[idx]], _general=True)
                hf = h.ravel()
                hf[idx] = sub
                return hf.reshape(h.shape)
        lv = self._level_maps
        shape = z2.shape
        h = np.full(shape, np.inf)
        joint: Any = None
        side: Any = None
        outside: Any = None
        if detail:
            joint = np.zeros(shape, int)
            side = np.zeros(shape, int)
            outside = np.zeros(shape, bool)
        # z_{n+1} = th_n matters only for its bounds (the levels below do not depend on it)
        thn: Any = np.asarray(Zr[n - 1], float) if len(Zr) > n - 1 else 0.0
        if self._thn_bounded:
            lo_n, hi_n = self.lower[n - 1], self.upper[n - 1]
            a_, b_ = thn - lo_n, hi_n - thn
            h = np.minimum(a_, b_)
            if detail:
                joint[...] = n
                side = (b_ < a_).astype(int)
        # non-finite components need no test of their own: they make some w non-finite, and
        # the inverse fails there (margin -pi/2)
        alive: np.ndarray | None = None
        th: dict[int, Any] = {n: thn}
        cs: dict[int, Any] = {}
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            for k in range(n, 1, -1):
                j = k - 1
                m = self._m[k - 2]
                a, b = lv.ab(k, th, cs)
                zk = np.asarray(Zr[k - 2], float)
                w = zk / a if _is_zero(b) else (zk - b) / a
                good = (w > W_TOL) & (w < 1.0 - W_TOL)
                bad = ~good if alive is None else (alive & ~good)
                if bad.any():
                    below = -np.abs(w) ** (1.0 / m)
                    above = -np.sqrt(2.0 * np.abs(w - 1.0) / m)
                    ext = np.where(w <= 0.5, below, above)
                    ext = np.where(np.isfinite(ext), np.minimum(ext, 0.0), -HALF_PI)
                    hn = np.minimum(h, ext)
                    if detail:
                        upd = bad & (ext < h)
                        joint = np.where(upd, j, joint)
                        side = np.where(upd, (w <= 0.5).astype(int), side)
                        outside = np.where(upd, True, outside)
                    h = np.where(bad, hn, h)
                    alive = good if alive is None else (alive & good)
                    if not alive.any():
                        break
                c = root_m(w, m)
                t = np.arccos(c)
                if self._default[j - 1]:
                    ml, mh = t, HALF_PI - t
                else:
                    ml, mh = t - self.lower[j - 1], self.upper[j - 1] - t
                mk = np.minimum(ml, mh)
                hn = np.minimum(h, mk)
                if detail:
                    upd = mk < h if alive is None else (alive & (mk < h))
                    joint = np.where(upd, j, joint)
                    side = np.where(upd, (mh < ml).astype(int), side)
                    outside = np.where(upd, False, outside)
                h = hn if alive is None else np.where(alive, hn, h)
                th[j] = t
                cs[j] = c
        if self._thn_bounded:
            h = np.where(np.isnan(h), -HALF_PI, h)
        if detail:
            return h, joint, side, outside
        return h

    def _values3(self, z2: np.ndarray, z3: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`values` for n = 3 with the default joint ranges at the points inside:
        ``min(th, pi/2 - th) = arcsin(min(cos th, sin th))`` for th1, th2. Returns the values
        and a mask of the points where the inverse fails (their values are meaningless), or
        None when there are none."""
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            w3 = z3 * self._inv_k3
            c2 = root_m(w3, self._m[1])
            c2sq = c2 * c2
            s2 = np.sqrt(1.0 - c2sq)
            cp = c2sq if self._m[1] == 3 else c2 ** (self._m[1] - 1)
            w2 = z2 / ((cp * s2) * self._neg_a)
            c1 = root_m(w2, self._m[0])
            s1 = np.sqrt(1.0 - c1 * c1) if self._m[0] != 2 else np.sqrt(1.0 - w2)
            m = np.minimum(np.minimum(c1, s1), np.minimum(c2, s2))
            h = np.arcsin(m)
            # all cosines and sines >= 1e-3 puts every w well inside (W_TOL, 1 - W_TOL)
            if m.min() >= 1e-3:
                return h, None
            bad = ~((w3 > W_TOL) & (w3 < 1.0 - W_TOL) & (w2 > W_TOL) & (w2 < 1.0 - W_TOL))
            return h, (bad if bad.any() else None)

    def _level_value(self, wmin: np.ndarray, wmax: np.ndarray, j: int, nan: float = np.nan
                     ) -> np.ndarray:
        """Smallest signed margin of joint ``j`` over sets of points given by their smallest and
        largest ``w = cos(th_j)^m`` (the margin, extended outside, is unimodal in ``w``);
        a NaN bound (no point) gives ``nan``, other non-finite values -pi/2."""
        m = self._m[j - 1]
        D = wmin.size
        w = np.concatenate([wmin, wmax])
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            valid = (w > W_TOL) & (w < 1.0 - W_TOL)
            t = np.arccos(root_m(np.clip(w, 0.0, 1.0), m))
            if self._default[j - 1]:
                out = np.minimum(t, HALF_PI - t)
            else:
                out = np.minimum(t - self.lower[j - 1], self.upper[j - 1] - t)
            if not valid.all():
                below = -np.abs(w) ** (1.0 / m)
                above = -np.sqrt(2.0 * np.abs(w - 1.0) / m)
                ext = np.minimum(np.where(w <= 0.5, below, above), 0.0)
                ext = np.where(np.isinf(w), -HALF_PI, np.where(np.isnan(w), nan, ext))
                out = np.where(valid, out, ext)
        return np.fmin(out[:D], out[D:])

    def grid_margins(self, Zr: Sequence[np.ndarray] | np.ndarray, angles: Sequence[int] = ()
                     ) -> Any:
        """Per member, the smallest signed margin of its sampled points: ``Zr = [z2, ...,
        z_{n+1}]``, each of shape (G, D) (samples first, one column per member; ``z_{n+1}`` may
        be left out unless ``th_n`` is bounded or asked for); returns (D,),
        and with ``angles`` also ``{j: th_j}`` (G, D) for those joints (NaN or meaningless
        where the inverse fails; under ``full`` only).

        Equal to ``signed_margin_z`` minimised over each column, computed per joint in
        ``w = cos(th)^m`` space: a joint's (extended) margin is unimodal in ``w``, so its
        smallest value over a column is attained at the column's smallest or largest ``w``;
        only those two values per member and joint are turned into angles. For n >= 4 the
        lower levels (long expressions) are evaluated only where the levels above are valid.
        """
        n = self._n
        z2 = np.asarray(Zr[0])
        if self.criterion == "z2":
            with np.errstate(invalid="ignore"):
                res = -np.max(z2, axis=0)
            return (res, {}) if angles else res
        lv = self._level_maps
        G, D = z2.shape
        res = np.full(D, np.inf)
        thn: Any = np.asarray(Zr[n - 1]) if len(Zr) > n - 1 else 0.0
        if self._thn_bounded:
            res = np.minimum(np.min(thn, axis=0) - self.lower[n - 1],
                             self.upper[n - 1] - np.max(thn, axis=0))
        kept: dict[int, np.ndarray] = {}
        if n in angles:
            kept[n] = thn
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            # level n: w_n = z_n / K_n, every point
            j = n - 1
            w = np.asarray(Zr[n - 2]) * (1.0 / self.robot.gains[-1])
            res = np.fmin(res, self._level_value(np.min(w, axis=0), np.max(w, axis=0), j,
                                                 nan=-HALF_PI))
            alive = (w > W_TOL) & (w < 1.0 - W_TOL)
            c = root_m(w, self._m[n - 2])
            cs: dict[int, Any] = {j: c}
            th: dict[int, Any] = {n: thn}
            if n > 4 or j in angles:
                th[j] = np.arccos(c)
                if j in angles:
                    kept[j] = th[j]
            flat: np.ndarray | None = None      # compressed: indices of the live points
            for k in range(n - 1, 1, -1):
                j = k - 1
                if flat is None and n > 3 and k > 2 and np.count_nonzero(alive) < 0.75 * G * D:
                    flat = np.flatnonzero(alive)
                    th = {i: (np.asarray(v).ravel()[flat] if np.ndim(v) else v)
                          for i, v in th.items()}
                    cs = {i: np.asarray(v).ravel()[flat] for i, v in cs.items()}
                if flat is None:
                    a, b = lv.ab(k, th, cs)
                    zk = np.asarray(Zr[k - 2])
                    w = zk / a if _is_zero(b) else (zk - b) / a
                    wm = w.copy()
                    np.copyto(wm, np.nan, where=~alive)
                else:
                    if flat.size:
                        a, b = lv.ab(k, th, cs)
                        zk = np.asarray(Zr[k - 2]).ravel()[flat]
                        w = zk / a if _is_zero(b) else (zk - b) / a
                    else:
                        w = np.zeros(0)
                    wm = np.full(G * D, np.nan)
                    wm[flat] = w
                    wm = wm.reshape(G, D)
                res = np.fmin(res, self._level_value(np.fmin.reduce(wm, axis=0),
                                                     np.fmax.reduce(wm, axis=0), j))
                need = k > 2 or j in angles
                if need:
                    c = root_m(w, self._m[k - 2])
                    t = np.arccos(c) if (n > 4 or j in angles) else None
                    if j in angles and t is not None:
                        if flat is None:
                            kept[j] = t
                        else:
                            full_t = np.full(G * D, np.nan)
                            full_t[flat] = t
                            kept[j] = full_t.reshape(G, D)
                if k > 2:
                    good = (w > W_TOL) & (w < 1.0 - W_TOL)
                    if flat is None:
                        alive = alive & good
                        cs[j] = c
                        if t is not None:
                            th[j] = t
                    else:
                        flat = flat[good]
                        th = {i: (v[good] if np.ndim(v) else v) for i, v in th.items()}
                        cs = {i: v[good] for i, v in cs.items()}
                        cs[j] = c[good]
                        if t is not None:
                            th[j] = t[good]
        if angles:
            return res, kept
        return res

    def grid_inside(self, Zr: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
        """``grid_margins(Zr) > 0`` for n = 3, the full criterion and the default joint ranges: per
        member (columns of ``Zr = [z2, z3]``, each (G, D)), whether every sampled point is
        inside.

        There a point's margin is positive exactly when ``w3 = z3 / K3`` and
        ``w2 = z2 / a2(th2)`` both lie in ``(W_TOL, 1 - W_TOL)``: the joints' angles are then
        strictly inside (0, pi/2) (at least ~1e-6 rad), and outside the extended margin is
        <= 0. So only the ``w`` are computed, no angle.
        """
        if not (self._fast3 and self.criterion == "full"):
            raise ValueError("grid_inside needs n = 3, the full criterion and the default "
                             "joint ranges")
        z2, z3 = np.asarray(Zr[0], float), np.asarray(Zr[1], float)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            # the operations of grid_margins (levels 3 and 2 of InverseLevels.ab), so the same w
            w3 = z3 * (1.0 / self.robot.gains[-1])
            c2 = root_m(w3, self._m[1])
            s2 = np.sqrt(1.0 - c2 * c2)
            cm1 = c2 * c2 if self._m[1] == 3 else c2 ** (self._m[1] - 1)
            w2 = z2 / (self._neg_a * cm1 * s2)
            inside = (w3 > W_TOL) & (w3 < 1.0 - W_TOL) & (w2 > W_TOL) & (w2 < 1.0 - W_TOL)
        return np.asarray(inside.all(axis=0))
    def linearised(self, margin: np.ndarray, joint: np.ndarray, side: np.ndarray,
                   outside: np.ndarray) -> np.ndarray:
        """The margin mapped to the distance from the boundary in ``w = cos(th)^m`` space, of
        the joint and side that attain it: same sign, but smooth across the boundary (the angle
        margin behaves like ``sqrt`` or ``cbrt`` of the distance there), for root finding."""
        F = np.asarray(margin, float)
        if self.criterion == "z2":
            return F
        n = self._n
        out = F.copy()
        for j in range(1, n):
            sel = joint == j
            if not sel.any():
                continue
            m = self._m[j - 1]
            lo, hi = self.lower[j - 1], self.upper[j - 1]
            f = F[sel]
            s = side[sel]
            ex = outside[sel]
            wl, wh = math.cos(lo) ** m, max(math.cos(hi), 0.0) ** m
            with np.errstate(invalid="ignore", over="ignore"):
                in_lo = wl - np.cos(np.clip(lo + f, 0.0, HALF_PI)) ** m
                in_hi = np.cos(np.clip(hi - f, 0.0, HALF_PI)) ** m - wh
                out_lo = wl - (1.0 + 0.5 * m * f * f)
                out_hi = -np.abs(f) ** m - wh
            out[sel] = np.where(ex, np.where(s == 0, out_lo, out_hi),
                                np.where(s == 0, in_lo, in_hi))
        return out


def _is_zero(x: Any) -> bool:
    return isinstance(x, float) and x == 0.0
