"""The singularity-free region and path margins (paper eq 7, 13; NOTES §5).

The chained-form transform is invertible where ``th_1, ..., th_{n-1}`` all lie in (0, pi/2)
(``th_n`` is free). The paper's condition ``z2 < 0`` (eq 13) is necessary for n = 3 but not
sufficient; it is offered as the criterion ``"z2"``. Optional joint bounds shrink the region.

Here: the region's bounds (validated), its check of points in joint space, and the smallest
signed margin of whole polynomial paths; the signed margin of chained points, and its
definition, are in :mod:`optimizer.margins` (the region's base class).

A path is checked on the continuous path, not only on samples: the signed margin is evaluated on
a dense grid (257 samples per polynomial piece) that also contains the critical points of the
polynomial boundary conditions (``z2`` and ``z_n``: their extremes, so that every excursion
across ``z2 = 0`` or ``z_n in {0, K_n}`` has a sample inside it) and, when a crossing is to be
located, their roots; every sampled local minimum is refined by zooming in (two rounds of 17
nodes, then the vertices of the parabolas through the best node and its neighbours, of the
margin and of ``margin |margin|``, which is smooth where the margin behaves like a square root
at the boundary), all minima of all paths of a batch at once; the first crossing is located by
Brent's method. The work is vectorised over many paths (:meth:`Region.poly_minimum`), so that
the planner checks whole sets of candidate members in one call.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from .chained_form import ChainedForm, chained_form
from .errors import InvalidRequestError
from .margins import HALF_PI, PointMargins
from .model import Robot
from .poly_roots import bracket_root, parabola_vertex, polyder_rows, real_roots_rows, unit_grid
from .steering import ChainedPath, polyval_each

CRITERIA = ("full", "z2")
#: Zoom of every sampled local minimum: nodes per bracket and rounds (each round shrinks the
#: bracket (ZOOM_POINTS - 1) / 2 = 8-fold), then one parabolic step: from nodes ~6e-5 apart it
#: puts the minimum of a smooth margin to ~1e-9 in time, its value exact to rounding.
ZOOM_POINTS = 17
ZOOM_ROUNDS = 2


#: Recent check_path results (see :meth:`Region.check_path`), oldest first.
_CHECKS: OrderedDict[tuple[Any, ...], PathCheck] = OrderedDict()
_CHECKS_SIZE = 16
_CHECKS_LOCK = threading.Lock()


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


@dataclass(frozen=True)
class PolyMinimum:
    """Smallest signed margin of many polynomial paths (:meth:`Region.poly_minimum`).

    Attributes
    ----------
    margin, argmin : ndarray (R,)
        Per path, the smallest margin over its span and the local time where it is attained.
    joint, side, outside : ndarray (R,)
        At the argmin: the joint whose margin it is (1..n; 0 under ``z2``), the side of its
        range (0: the lower bound, 1: the upper bound) and whether the inverse map fails there
        (the margin is the extended one). Only with ``detail=True``.
    samples : tuple or None
        ``(x, values, rows, cols, lo, best, arg)``: the sampled local times and margins (R, T),
        and per zoomed bracket its path, sample index, left end, minimum and argmin (only with
        ``keep=True``).
    """

    margin: np.ndarray
    argmin: np.ndarray
    joint: np.ndarray | None = None
    side: np.ndarray | None = None
    outside: np.ndarray | None = None
    samples: tuple[np.ndarray, ...] | None = None


class Region(PointMargins):
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
        n = robot.n
        lo = [0.0] * (n - 1) + [-math.inf]
        hi = [HALF_PI] * (n - 1) + [math.inf]
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
        # (the bounds are worked out on floats: a region is built for every request)
        super().__init__(robot, criterion, np.array(lo), np.array(hi),
                         transform or chained_form(robot))
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
        for i, (th, lo, hi) in enumerate(zip(q[1:].tolist(), self.lower.tolist(),
                                            self.upper.tolist())):
            if not (lo < th < hi):
                raise InvalidRequestError(
                    f"{field}[{i}] = {th:.6g} rad ({math.degrees(th):.4g} deg) is outside "
                    f"({lo:.6g}, {hi:.6g}) rad: the chained-form transform is singular or the joint "
                    f"bound is violated there", field=f"{field}[{i}]")

    # --------------------------------------------------------------- polynomial paths
    def _exact_points(self, coef: np.ndarray, span: np.ndarray, roots: bool = True
                      ) -> np.ndarray | None:
        """Critical points (and with ``roots`` also roots) in [0, span] of the polynomial
        boundary conditions, per path (R, Q); NaN where a slot holds none.

        The critical points alone make the sampled margin exact where a polynomial condition
        is the closest (its extreme is a sample), and catch every excursion across such a
        boundary between samples (the excursion holds an extreme); the roots locate crossings.
        """
        n = self._n
        R, _, L = coef.shape
        if L < 2:
            return None
        z2 = coef[:, 1, :]
        polys = [polyder_rows(z2)]
        if roots:
            polys.append(z2)
        if self.criterion == "full":
            zn = coef[:, n - 1, :]
            polys.append(polyder_rows(zn))
            if roots:
                znk = zn.copy()
                znk[:, 0] -= self.robot.gains[-1]
                polys += [zn, znk]
        Pm = np.stack(polys, axis=1)                              # (R, Q, L)
        Q = Pm.shape[1]
        out = real_roots_rows(Pm.reshape(R * Q, L)).reshape(R, Q * (L - 1))
        sp = span[:, None]
        with np.errstate(invalid="ignore"):
            out[~((out >= 0.0) & (out <= sp))] = np.nan
        return out

    def poly_minimum(self, coef: np.ndarray, span: np.ndarray | None = None, grid: int = 257,
                     detail: bool = False, keep: bool = False, roots: bool = False
                     ) -> PolyMinimum:
        """Smallest signed margin over many polynomial paths at once, on the continuous paths.

        Parameters
        ----------
        coef : ndarray (R, n+1, L)
            Per path, the coefficients (increasing powers of the local time ``x``) of
            ``z1..z_{n+1}``.
        span : ndarray (R,), optional
            The paths live on ``x in [0, span]`` (default 1).
        grid : int
            Uniform samples per path before the exact points and the zoom.
        detail, keep : bool
            See :class:`PolyMinimum`.
        roots : bool
            Also sample the roots of the polynomial conditions (to locate crossings; the
            margin and its sign need only their critical points).
        """
        coef = np.asarray(coef, float)
        R = coef.shape[0]
        sp = np.ones(R) if span is None else np.asarray(span, float)
        z2only = self.criterion == "z2"
        comps = coef[:, 1:2, :] if z2only else coef[:, 1:, :] if self._thn_bounded \
            else coef[:, 1:-1, :]
        X = sp[:, None] * unit_grid(grid)[None, :]
        E = self._exact_points(coef, sp, roots=roots)
        if E is not None:
            # empty slots become extra samples inside the span (off the uniform grid)
            Q = E.shape[1]
            fill = sp[:, None] * ((np.arange(Q) + 0.6180339887) / (Q + 1))[None, :]
            E = np.where(np.isnan(E), fill, E)
            X = np.concatenate([X, E], axis=1)
            X.sort(axis=1)
        Z = polyval_each(comps, X)                                   # (C, R, T)
        v = np.asarray(self.values(Z))
        rows = np.arange(R)
        if z2only:
            # -z2 is exact at the samples: its extremes (critical points) are among them
            i = np.argmin(v, axis=1)
            best, arg = v[rows, i], X[rows, i]
            out = PolyMinimum(best, arg, samples=(X, v) if keep else None)
            if detail:
                zero = np.zeros(R, int)
                out = PolyMinimum(best, arg, zero, zero + 1, zero.astype(bool), out.samples)
            return out
        # every sampled local minimum (ends included), zoomed; the global sampled minimum is
        # one of them, and each zoom re-evaluates its centre
        T = X.shape[1]
        lm = np.empty(v.shape, bool)
        lm[:, 1:-1] = (v[:, 1:-1] <= v[:, :-2]) & (v[:, 1:-1] <= v[:, 2:])
        lm[:, 0] = v[:, 0] <= v[:, 1]
        lm[:, -1] = v[:, -1] <= v[:, -2]
        rr, cc = np.nonzero(lm)
        lo = X[rr, np.maximum(cc - 1, 0)]
        hi = X[rr, np.minimum(cc + 1, T - 1)]
        zb, za, dets = self._zoom(comps, rr, lo, hi, detail)
        # per path, its best bracket (rr is sorted)
        first = np.ones(rr.size, bool)
        first[1:] = rr[1:] != rr[:-1]
        starts = np.flatnonzero(first)
        seg = np.cumsum(first) - 1
        segmin = np.minimum.reduceat(zb, starts)
        hit = np.flatnonzero(zb <= segmin[seg])
        hs = np.ones(hit.size, bool)
        hs[1:] = seg[hit[1:]] != seg[hit[:-1]]
        pick = hit[hs]                                              # one bracket per path
        best = zb[pick]
        arg = za[pick]
        out = PolyMinimum(best, arg,
                          samples=(X, v, rr, cc, lo, zb, za) if keep else None)
        if detail:
            assert dets is not None
            out = PolyMinimum(best, arg, dets[0][pick], dets[1][pick], dets[2][pick],
                              out.samples)
        return out

    def _zoom(self, comps: np.ndarray, rows: np.ndarray, lo: np.ndarray, hi: np.ndarray,
              detail: bool = False, points: int = ZOOM_POINTS, rounds: int = ZOOM_ROUNDS
              ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...] | None]:
        """Minimise the margin on many brackets ``[lo_i, hi_i]`` of paths ``rows`` at once.

        Each round samples every bracket at ``points`` nodes and shrinks it to the two cells
        around its best node; then the vertex of the parabola through the best node and its
        neighbours is tried (the margin is smooth at its local minima: a local minimum of a
        minimum of smooth functions is a local minimum of one of them). The result is the best
        margin evaluated, never an extrapolation. With ``detail``, also the joint, side and
        outside flag at each bracket's result.
        """
        K = lo.size
        C = comps[rows]
        u = unit_grid(points)
        ar = np.arange(K)
        arg = lo
        t = v = j = None
        for _ in range(rounds):
            t = lo[:, None] + (hi - lo)[:, None] * u[None, :]
            v = np.asarray(self.values(polyval_each(C, t)))
            j = np.argmin(v, axis=1)
            arg = t[ar, j]
            step = (hi - lo) * (1.0 / (points - 1))
            lo, hi = np.maximum(arg - step, lo), np.minimum(arg + step, hi)
        assert t is not None and v is not None and j is not None
        # (each round re-samples its best node: best never increases)
        # parabolic vertices through the best node of the last round and its neighbours: of the
        # margin h (smooth minima) and of h |h| (near a boundary h behaves like the square root
        # of a smooth function, sharp at its minimum; h |h| is that function)
        jm = np.minimum(np.maximum(j, 1), points - 2)
        x0, x1, x2 = t[ar, jm - 1], t[ar, jm], t[ar, jm + 1]
        f0, f1, f2 = v[ar, jm - 1], v[ar, jm], v[ar, jm + 1]
        xa = parabola_vertex(x0, x1, x2, f0, f1, f2)
        xb = parabola_vertex(x0, x1, x2, f0 * np.abs(f0), f1 * np.abs(f1), f2 * np.abs(f2))
        pts = np.concatenate([xa, xb, arg])
        res = self.values(polyval_each(np.concatenate([C, C, C]), pts[:, None]), detail=detail)
        fv = (np.asarray(res[0]) if detail else np.asarray(res))[:, 0].reshape(3, K)
        sel = np.argmin(fv, axis=0) * K + ar
        if not detail:
            return fv.ravel()[sel], pts[sel], None
        jt, sd, ou = (np.asarray(r)[:, 0] for r in res[1:])
        return fv.ravel()[sel], pts[sel], (jt[sel], sd[sel], ou[sel])
    # --------------------------------------------------------------- paths
    def check_path(self, path: ChainedPath, grid: int = 257, locate: bool = True) -> PathCheck:
        """Check a chained path on [0, 1] against the region, on the continuous path.

        Parameters
        ----------
        path : ChainedPath
        grid : int
            Number of uniform samples (per input piece) before refinement.
        locate : bool
            Locate the first crossing (skip it when only the margin is needed).

        The last results are remembered per region and path (the same inputs from the same
        start): the planner checks its chosen member before returning it, and the plan is
        checked once more when it is finished.
        """
        key = self._check_key(path, grid, locate)
        with _CHECKS_LOCK:
            hit = _CHECKS.get(key)
        if hit is not None:
            return hit
        chk = self._check_path(path, grid, locate)
        with _CHECKS_LOCK:
            _CHECKS[key] = chk
            while len(_CHECKS) > _CHECKS_SIZE:
                _CHECKS.popitem(last=False)
        return chk

    def _check_key(self, path: ChainedPath, grid: int, locate: bool) -> tuple[Any, ...]:
        inp = path.inputs
        return (self.robot, self.criterion, self.lower.tobytes(), self.upper.tobytes(),
                np.asarray(path.z0, float).tobytes(), np.asarray(inp.breaks, float).tobytes(),
                tuple(np.asarray(c, float).tobytes() for c in inp.v1),
                tuple(np.asarray(c, float).tobytes() for c in inp.v2),
                tuple(p.tobytes() for p in path.polys), grid, locate)

    def _check_path(self, path: ChainedPath, grid: int, locate: bool) -> PathCheck:
        breaks = np.asarray(path.inputs.breaks, float)
        S = len(path.polys)
        L = max(p.shape[1] for p in path.polys)
        coef = np.zeros((S, self._n + 1, L))
        for s, arr in enumerate(path.polys):
            coef[s, :, :arr.shape[1]] = arr
        span = np.diff(breaks)[:S]
        res = self.poly_minimum(coef, span, grid=grid, keep=True, roots=locate)
        s_best = int(np.argmin(res.margin))
        best_val = float(res.margin[s_best])
        best_tau = float(breaks[s_best] + res.argmin[s_best])
        assert res.samples is not None
        X, v = res.samples[0], res.samples[1]
        taus = (breaks[:S, None] + X).ravel()
        vals = v.ravel()
        crossing: float | None = None
        if self.criterion == "z2":
            # z2 is a polynomial: its maximum is attained at a critical point or an end, both
            # among the samples; the crossing is an exact root (allow for its rounding)
            bad = np.nonzero(-vals >= -1e-13)[0]
            if bad.size:
                crossing = float(taus[bad[0]])
            return PathCheck(ok=best_val > 0.0, margin=best_val, argmin_tau=best_tau,
                             first_crossing_tau=crossing)
        if best_val > 0.0:
            return PathCheck(ok=True, margin=best_val, argmin_tau=best_tau,
                             first_crossing_tau=None)
        if not locate:
            return PathCheck(ok=False, margin=best_val, argmin_tau=best_tau,
                             first_crossing_tau=best_tau)

        def h(t: float) -> float:
            return float(self.signed_margin_z(path.z(np.array([t])))[0])

        bad = np.nonzero(vals <= 0.0)[0]
        if bad.size:
            j = int(bad[0])
            crossing = 0.0 if j == 0 else bracket_root(h, float(taus[j - 1]), float(taus[j]))
        rr, cc, lo, zb, za = res.samples[2:]
        for r, c_, left, val, tm in zip(rr, cc, lo, zb, za):
            if val > 0.0 or v[r, c_] <= 0.0:
                continue
            # a dip between samples: the crossing is between the bracket's left end and the
            # minimum (the sampled node in the middle of the bracket was inside)
            a = float(breaks[r] + left)
            b = float(breaks[r] + tm)
            c = bracket_root(h, a, b) if h(a) > 0.0 else a
            if crossing is None or c < crossing:
                crossing = c
        if crossing is None:
            crossing = best_tau
        return PathCheck(ok=False, margin=best_val, argmin_tau=best_tau,
                         first_crossing_tau=crossing)

