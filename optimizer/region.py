"""The singularity-free region and path margins (paper eq 7, 13; NOTES §5).

The chained-form transform is invertible where ``th_1, ..., th_{n-1}`` all lie in (0, pi/2)
(``th_n`` is free). The paper's condition ``z2 < 0`` (eq 13) is necessary for n = 3 but not
sufficient; it is offered as the criterion ``"z2"``. Optional joint bounds shrink the region.

Margins
-------
``full``: the smallest distance (rad) of ``th_1..th_{n-1}`` from their bounds (and of ``th_n``
from its bounds when given) over the path; negative outside. ``z2``: ``-max z2`` over the path.

At one point the inverse map is taken top-down (``th_n``, then ``th_{n-1}``, ...). The point's
signed margin is the smallest margin of the joints found so far (``th_n`` and ``th_{n-1}`` down
to the first joint the inverse cannot give), and, when the inverse fails at some joint, the
margin of that joint extended outside by its local shape (see :meth:`Region.signed_margin_z`):
inside the region this is the joints' distance from their bounds; outside it is negative.

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

Speed: the inverse map is evaluated with numpy: levels n, n - 1 and n - 2 in closed form, lower
levels (n >= 5) by numpy code generated once per robot from the CasADi expressions of the
chained form (:func:`_compile_sx`); a grid of members is reduced per member in
``w = cos(th)^m`` space (:meth:`Region.grid_margins`), where every joint's margin is unimodal,
so that only two values per member and joint are turned into angles.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np
from scipy.optimize import brentq

from .chained_form import W_TOL, ChainedForm, chained_form
from .errors import InvalidRequestError
from .model import Robot
from .steering import ChainedPath, polyval_each

CRITERIA = ("full", "z2")
HALF_PI = 0.5 * math.pi
#: Zoom of every sampled local minimum: nodes per bracket and rounds (each round shrinks the
#: bracket (ZOOM_POINTS - 1) / 2 = 8-fold), then one parabolic step: from nodes ~6e-5 apart it
#: puts the minimum of a smooth margin to ~1e-9 in time, its value exact to rounding.
ZOOM_POINTS = 17
ZOOM_ROUNDS = 2


#: Recent check_path results (see :meth:`Region.check_path`), oldest first.
_CHECKS: "OrderedDict[tuple[Any, ...], PathCheck]" = OrderedDict()
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


# ---------------------------------------------------------------------- numpy from CasADi
_UNARY = {ca.OP_NEG: "-{0}", ca.OP_SQ: "{0} * {0}", ca.OP_TWICE: "{0} + {0}",
          ca.OP_COS: "_np.cos({0})", ca.OP_SIN: "_np.sin({0})", ca.OP_SQRT: "_np.sqrt({0})",
          ca.OP_ACOS: "_np.arccos({0})", ca.OP_ASIN: "_np.arcsin({0})",
          ca.OP_FABS: "_np.abs({0})", ca.OP_INV: "1.0 / {0}", ca.OP_EXP: "_np.exp({0})",
          ca.OP_LOG: "_np.log({0})", ca.OP_TAN: "_np.tan({0})"}
_BINARY = {ca.OP_ADD: "{0} + {1}", ca.OP_SUB: "{0} - {1}", ca.OP_MUL: "{0} * {1}",
           ca.OP_DIV: "{0} / {1}", ca.OP_POW: "{0} ** {1}", ca.OP_CONSTPOW: "{0} ** {1}"}


def _compile_sx(f: ca.Function) -> Callable[[Sequence[Any]], list[Any]] | None:
    """The SX function ``f`` (one vector input, one vector output) as numpy code: a callable
    taking the input's entries (arrays or numbers that broadcast) and returning the output's
    entries. ``None`` when ``f`` uses an operation not translated here.

    One numpy operation per SX instruction, on all points at once: for thousands of points this
    is many times faster than CasADi's column-by-column evaluation.
    """
    if not f.is_a("SXFunction") or f.n_in() != 1 or f.n_out() != 1:
        return None
    consts: list[float] = []
    lines = ["def _f(x):", f"    out = [0.0] * {f.nnz_out(0)}"]
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        i = f.instruction_input(k)
        o = f.instruction_output(k)
        if op == ca.OP_CONST:
            consts.append(float(f.instruction_constant(k)))
            lines.append(f"    w{o[0]} = _c[{len(consts) - 1}]")
        elif op == ca.OP_INPUT:
            lines.append(f"    w{o[0]} = x[{i[1]}]")
        elif op == ca.OP_OUTPUT:
            lines.append(f"    out[{o[1]}] = w{i[0]}")
        elif op in _UNARY:
            lines.append(f"    w{o[0]} = " + _UNARY[op].format(f"w{i[0]}"))
        elif op in _BINARY:
            lines.append(f"    w{o[0]} = " + _BINARY[op].format(f"w{i[0]}", f"w{i[1]}"))
        else:
            return None
    lines.append("    return out")
    scope: dict[str, Any] = {"_np": np, "_c": consts}
    exec("\n".join(lines), scope)  # noqa: S102 - code generated from the instruction list above
    fn: Callable[[Sequence[Any]], list[Any]] = scope["_f"]
    return fn


class _Levels:
    """``a_k``, ``b_k`` of the top-down inverse map (``z_k = a_k w_k + b_k``) as numpy code.

    Level n is ``z_n = K_n w_n``; levels n - 1 and n - 2 in closed form (see :meth:`ab`); below
    (n >= 5) the CasADi expressions of :class:`optimizer.chained_form.SymbolicChainedForm` are
    translated once (:func:`_compile_sx`), with CasADi itself as the fallback.
    """

    def __init__(self, robot: Robot, cf: ChainedForm) -> None:
        self.n = n = robot.n
        self.K = robot.gains
        self.m = robot.exponents
        self.fns: dict[int, Callable[[Sequence[Any]], list[Any]]] = {}
        if n > 4:
            sym = cf.symbolic
            for k in range(2, n - 2):
                fn = _compile_sx(sym.ab[k])
                self.fns[k] = fn if fn is not None else _casadi_caller(sym.ab[k], n)

    def ab(self, k: int, th: dict[int, Any], cs: dict[int, Any]) -> tuple[Any, Any]:
        """``(a_k, b_k)`` from the angles ``th[j]`` (j >= k) and their cosines ``cs[j]``."""
        n = self.n
        if k == n:
            return self.K[-1], 0.0
        K, m = self.K, self.m
        if k >= n - 2:
            # closed forms: z_n = K_n c^m_n (c = cos th_{n-1}), so
            # a_{n-1} = -m_n K_{n-1} K_n c^(m_n-1) s, b_{n-1} = 0, and from
            # z_{n-1} = a_{n-1}(th_{n-1}) w_{n-1}:
            # a_{n-2} = K_{n-2} a_{n-1} d w_{n-1}/d th_{n-2}, b_{n-2} = K_{n-1} a'_{n-1} w_{n-1}^2
            mn = m[-1]
            c = cs[n - 1]
            with np.errstate(invalid="ignore"):
                s = np.sqrt(1.0 - c * c)
            cm1 = c * c if mn == 3 else c ** (mn - 1)
            a1 = (-mn * K[-2] * K[-1]) * cm1 * s
            if k == n - 1:
                return a1, 0.0
            m1 = m[-2]
            c2 = cs[n - 2]
            with np.errstate(invalid="ignore"):
                s2 = np.sqrt(1.0 - c2 * c2)
            w1 = c2 * c2 if m1 == 2 else c2 ** m1
            dw = -m1 * (c2 if m1 == 2 else c2 ** (m1 - 1)) * s2
            da1 = (-mn * K[-2] * K[-1]) * (cm1 * c - (mn - 1) * c ** (mn - 2) * s * s)
            return K[-3] * a1 * dw, K[-2] * da1 * w1 * w1
        q: list[Any] = [0.0] * (n + 1)
        for j in range(k, n + 1):
            q[j] = th[j]
        with np.errstate(all="ignore"):
            out = self.fns[k](q)
        return out[0], out[1]


def _casadi_caller(f: ca.Function, n: int) -> Callable[[Sequence[Any]], list[Any]]:
    def call(q: Sequence[Any]) -> list[Any]:
        arrs = np.broadcast_arrays(*[np.asarray(x, float) for x in q])
        shape = arrs[0].shape
        res = np.asarray(f(np.vstack([a.ravel() for a in arrs])))
        return [res[r].reshape(shape) for r in range(res.shape[0])]
    return call


@functools.lru_cache(maxsize=64)
def _levels(robot: Robot) -> _Levels:
    return _Levels(robot, chained_form(robot))


def _root_m(w: Any, m: int) -> Any:
    """``w^(1/m)`` (the cosine of the joint angle)."""
    if m == 1:
        return w
    if m == 2:
        return np.sqrt(w)
    if m == 3:
        return np.cbrt(w)
    return w ** (1.0 / m)


# ---------------------------------------------------------------------- region
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
        self.lower = np.array(lo)
        self.upper = np.array(hi)
        self.has_custom_bounds = joint_bounds is not None
        self._n = n
        self._m = robot.exponents
        # joints 1..n-1 with their default range (0, pi/2): the margin is min(th, pi/2 - th)
        self._default = [lo[j - 1] == 0.0 and hi[j - 1] == HALF_PI for j in range(1, n)]
        self._thn_bounded = math.isfinite(lo[n - 1]) or math.isfinite(hi[n - 1])
        self._lv: _Levels | None = None
        # n = 3 with the default ranges: a short path for points all inside (see _values3)
        self._fast3 = n == 3 and all(self._default) and not self._thn_bounded
        if n == 3:
            K2, K3 = robot.gains
            self._inv_k3 = 1.0 / K3
            self._neg_a = -robot.exponents[1] * K2 * K3

    @property
    def _level_maps(self) -> _Levels:
        if self._lv is None:
            self._lv = _levels(self.robot) if self.cf is chained_form(self.robot) \
                else _Levels(self.robot, self.cf)
        return self._lv

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
                c = _root_m(w, m)
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
            c2 = _root_m(w3, self._m[1])
            c2sq = c2 * c2
            s2 = np.sqrt(1.0 - c2sq)
            cp = c2sq if self._m[1] == 3 else c2 ** (self._m[1] - 1)
            w2 = z2 / ((cp * s2) * self._neg_a)
            c1 = _root_m(w2, self._m[0])
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
            t = np.arccos(_root_m(np.clip(w, 0.0, 1.0), m))
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
            c = _root_m(w, self._m[n - 2])
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
                    c = _root_m(w, self._m[k - 2])
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
            # the operations of grid_margins (levels 3 and 2 of _Levels.ab), so the same w
            w3 = z3 * (1.0 / self.robot.gains[-1])
            c2 = _root_m(w3, self._m[1])
            s2 = np.sqrt(1.0 - c2 * c2)
            cm1 = c2 * c2 if self._m[1] == 3 else c2 ** (self._m[1] - 1)
            w2 = z2 / (self._neg_a * cm1 * s2)
            inside = (w3 > W_TOL) & (w3 < 1.0 - W_TOL) & (w2 > W_TOL) & (w2 < 1.0 - W_TOL)
        return np.asarray(inside.all(axis=0))

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
        polys = [_polyder(z2)]
        if roots:
            polys.append(z2)
        if self.criterion == "full":
            zn = coef[:, n - 1, :]
            polys.append(_polyder(zn))
            if roots:
                znk = zn.copy()
                znk[:, 0] -= self.robot.gains[-1]
                polys += [zn, znk]
        Pm = np.stack(polys, axis=1)                              # (R, Q, L)
        Q = Pm.shape[1]
        out = _real_roots(Pm.reshape(R * Q, L)).reshape(R, Q * (L - 1))
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
        X = sp[:, None] * _unit_grid(grid)[None, :]
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
        u = _unit_grid(points)
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
        xa = _vertex(x0, x1, x2, f0, f1, f2)
        xb = _vertex(x0, x1, x2, f0 * np.abs(f0), f1 * np.abs(f1), f2 * np.abs(f2))
        pts = np.concatenate([xa, xb, arg])
        res = self.values(polyval_each(np.concatenate([C, C, C]), pts[:, None]), detail=detail)
        fv = (np.asarray(res[0]) if detail else np.asarray(res))[:, 0].reshape(3, K)
        sel = np.argmin(fv, axis=0) * K + ar
        if not detail:
            return fv.ravel()[sel], pts[sel], None
        jt, sd, ou = (np.asarray(r)[:, 0] for r in res[1:])
        return fv.ravel()[sel], pts[sel], (jt[sel], sd[sel], ou[sel])

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
            crossing = 0.0 if j == 0 else _root(h, float(taus[j - 1]), float(taus[j]))
        rr, cc, lo, zb, za = res.samples[2:]
        for r, c_, left, val, tm in zip(rr, cc, lo, zb, za):
            if val > 0.0 or v[r, c_] <= 0.0:
                continue
            # a dip between samples: the crossing is between the bracket's left end and the
            # minimum (the sampled node in the middle of the bracket was inside)
            a = float(breaks[r] + left)
            b = float(breaks[r] + tm)
            c = _root(h, a, b) if h(a) > 0.0 else a
            if crossing is None or c < crossing:
                crossing = c
        if crossing is None:
            crossing = best_tau
        return PathCheck(ok=False, margin=best_val, argmin_tau=best_tau,
                         first_crossing_tau=crossing)


@functools.lru_cache(maxsize=32)
def _unit_grid(points: int) -> np.ndarray:
    g = np.linspace(0.0, 1.0, points)
    g.flags.writeable = False
    return g


def _vertex(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, f0: np.ndarray, f1: np.ndarray,
            f2: np.ndarray) -> np.ndarray:
    """Vertex of the parabola through three points per row, kept inside [x0, x2]."""
    with np.errstate(all="ignore"):
        d10, d12 = x1 - x0, x1 - x2
        g12, g10 = f1 - f2, f1 - f0
        xv = x1 - 0.5 * (d10 * d10 * g12 - d12 * d12 * g10) / (d10 * g12 - d12 * g10)
    # (np.minimum/np.maximum: np.clip's Python wrapper costs more than the work here)
    return np.minimum(np.maximum(np.where(np.isfinite(xv), xv, x1), x0), x2)


def _is_zero(x: Any) -> bool:
    return isinstance(x, float) and x == 0.0


def _polyder(c: np.ndarray) -> np.ndarray:
    """Derivative of row-wise polynomials (R, L), padded back to L coefficients."""
    out = np.zeros_like(c)
    out[:, :-1] = c[:, 1:] * np.arange(1, c.shape[1])
    return out


def _real_roots(Pm: np.ndarray) -> np.ndarray:
    """Real roots of many polynomials (M, L) (increasing powers): (M, L - 1), NaN-padded.

    Coefficients below 1e-14 of a polynomial's largest one are dropped from the top (they only
    move roots far outside [0, 1]). Degrees 1 and 2 in closed form; from degree 3 on the roots
    are the eigenvalues of the companion matrices, all in one batched call (a lower degree is
    padded with a diagonal block whose eigenvalues, 2 and up, lie outside [0, 1]).
    """
    M, L = Pm.shape
    out = np.full((M, L - 1), np.nan)
    absc = np.abs(Pm)
    tol = 1e-14 * absc.max(axis=1, keepdims=True)
    big = absc > tol
    deg = (L - 1) - np.argmax(big[:, ::-1], axis=1)
    deg[~big.any(axis=1)] = 0
    lin = np.nonzero(deg == 1)[0]
    if lin.size:
        with np.errstate(all="ignore"):
            out[lin, 0] = -Pm[lin, 0] / Pm[lin, 1]
    quad = np.nonzero(deg == 2)[0]
    if quad.size:
        # closed form, the stable way; a (numerically) double root counts as real
        a, b, cc = Pm[quad, 2], Pm[quad, 1], Pm[quad, 0]
        with np.errstate(all="ignore"):
            disc = b * b - 4.0 * a * cc
            disc = np.where((disc < 0.0) & (disc > -1e-12 * (b * b + np.abs(4.0 * a * cc))),
                            0.0, disc)
            sq = np.sqrt(disc)                                   # NaN where complex
            q = -0.5 * (b + np.where(b >= 0.0, sq, -sq))
            out[quad, 0] = q / a
            out[quad, 1] = cc / q
    use = np.nonzero(deg >= 3)[0]
    if use.size == 0:
        return out
    dm = int(deg[use].max())
    d = deg[use]
    c = Pm[use, :dm + 1]
    lead = c[np.arange(use.size), d]
    comp = np.zeros((use.size, dm, dm))
    ii = np.arange(dm)
    # companion of the monic polynomial of degree d in the top-left d x d block
    comp[:, ii[1:], ii[:-1]] = (ii[1:][None, :] < d[:, None])
    col = -c[:, :dm] / lead[:, None]
    rows_ok = ii[None, :] < d[:, None]
    comp[np.arange(use.size)[:, None], ii[None, :], (d - 1)[:, None]] = np.where(rows_ok, col, 0.0)
    pad = ~rows_ok
    diag = comp[:, ii, ii]
    comp[:, ii, ii] = np.where(pad, 2.0 + ii[None, :], diag)
    ev = np.linalg.eigvals(comp[:, ::-1, ::-1])
    real = np.where(np.abs(ev.imag) < 1e-9, ev.real, np.nan)
    real[np.abs(real) > 1.5] = np.nan
    out[use, :dm] = real
    return out


def _root(f: Callable[[float], float], a: float, b: float) -> float:
    """The boundary crossing in [a, b] where f(a) > 0 >= f(b) (Brent; bisection if f is flat)."""
    fa, fb = f(a), f(b)
    if fa <= 0.0:
        return a
    if fb == 0.0:
        return b
    if fb > 0.0:
        return b
    return float(brentq(f, a, b, xtol=1e-13, maxiter=200))
