"""Choosing ``dphi`` inside the feasible intervals (paper §4 and §5.3).

* ``tp_then_da``: fewest ``t_p`` first, then smallest ``d_a`` (joint 1).
* ``tp_then_sensitivity``: fewest ``t_p``, then smallest ``||J_R(T)||_F``; it grows with
  ``|dphi|`` only, so this is the smallest ``|dphi|`` with the fewest ``t_p``.
* ``weighted``: smallest ``w_da d_a + w_s ||J_R(T)||_F + w_e energy + w_tp t_p``.
* ``reversals_then_deviation`` (the product's default): fewest actuator reversals, then the
  smallest joint-space deviation from the straight segment; see :func:`optimise_geometry`.

Each objective is optimised continuously, all candidate members of a step evaluated at once:

1. a screen of nodes inside every interval (at most 0.05 deg apart) on the search samples ranks
   the nodes; they are first scored on every fifth sample, which bounds ``t_p`` and ``d_a`` from
   below (a subset of the samples), and only the nodes whose bound can beat the best score found
   are scored on all samples;
2. the optimum between the best node's neighbours is refined to 1e-9 rad: ``d_a`` (and the
   weighted score without energy and ``t_p`` terms) by zooming (up to 81 members a round, the
   bracket shrinking up to 40-fold) with ``th1`` evaluated only where the deviation can be
   largest (the range swept by the largest deviation of the members around the bracket, and
   the other large local maxima), narrowed round by round; ``tp_then_sensitivity`` by
   multisection toward the end with the smaller ``|dphi|``; other weighted scores by zooming on
   all samples;
3. the refined member is evaluated on all samples and checked on the continuous path
   (:meth:`PolynomialFamily.confirm`, the check the finished plan gets); it is returned when it
   is feasible, keeps the fewest ``t_p`` and scores at least as well as the node. When the
   largest deviation of the result lies away from the samples followed, the zoom is redone
   following them too; when a shortcut does not hold up (``t_p`` grew, a member failed), the
   refinement is redone with bounded Brent minimisation (bisection for
   ``tp_then_sensitivity``) on fully evaluated members. Otherwise the node itself is returned
   if it passes the continuous check, else the next best node is refined.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from ..indicators import sensitivity_frobenius
from ..problem import Weights
from .family import MemberEval, PolynomialFamily, SampledMembers

SCAN_STEP = math.radians(0.05)
XATOL = 1e-9
#: The first screen uses every COARSE_STRIDE-th search sample (a subset: lower bounds).
COARSE_STRIDE = 5
#: Members per zoom round (the bracket shrinks (ZOOM_MEMBERS - 1) / 2-fold a round), fewer
#: (down to 17) while members times samples followed would exceed ZOOM_POINTS_BUDGET.
ZOOM_MEMBERS = 81
ZOOM_POINTS_BUDGET = 8000
#: Members per multisection round of ``tp_then_sensitivity``.
SECTION_MEMBERS = 7
_BAD = 1e9


def _nodes(a: float, b: float) -> np.ndarray:
    k = max(3, int(math.ceil((b - a) / SCAN_STEP)) + 1)
    return np.linspace(a, b, k)


def _score(obj: str, w: Weights) -> Callable[[MemberEval], tuple[float, float]]:
    if obj == "tp_then_da":
        return lambda e: (float(e.t_p), e.d_a)
    if obj == "tp_then_sensitivity":
        return lambda e: (float(e.t_p), abs(e.dphi))
    if obj == "weighted":
        # terms with weight 0 are left out (an indicator not computed is inf)
        terms = [(c, f) for c, f in ((w.d_a, "d_a"), (w.sensitivity, "sensitivity"),
                                     (w.energy, "energy"), (w.t_p, "t_p")) if c != 0.0]
        return lambda e: (0.0, float(sum(c * getattr(e, f) for c, f in terms)))
    raise ValueError(obj)


def _keys(obj: str, w: Weights, s: SampledMembers, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(primary, secondary)`` score arrays of sampled members (inf where not ok)."""
    inf = np.inf
    assert s.t_p is not None
    tp = np.where(s.ok, s.t_p.astype(float), inf)
    if obj == "tp_then_da":
        return tp, np.where(s.ok, s.d_a, inf)
    if obj == "tp_then_sensitivity":
        return tp, np.where(s.ok, np.abs(s.dphi), inf)
    sens = np.asarray(sensitivity_frobenius(s.dphi, n))
    val = np.zeros(s.dphi.size)
    if w.d_a != 0.0:
        val = val + w.d_a * s.d_a
    if w.sensitivity != 0.0:
        val = val + w.sensitivity * sens
    if w.t_p != 0.0:
        val = val + w.t_p * tp
    if w.energy != 0.0:
        assert s.energy is not None
        val = val + w.energy * s.energy
    with np.errstate(invalid="ignore"):
        return np.where(s.ok, 0.0, inf), np.where(s.ok, val, inf)


def optimise(family: PolynomialFamily, intervals: list[tuple[float, float]], objective: str,
             weights: Weights) -> MemberEval | None:
    """The best feasible member by ``objective``; ``None`` when no node is feasible.

    The returned member's ``energy`` is computed only when the objective uses it (else inf).
    """
    if objective == "reversals_then_deviation":
        return optimise_geometry(family, intervals)
    _score(objective, weights)  # validates the objective
    pieces = []
    for a, b in intervals:
        # stay a hair inside the closed interval: its ends are on the boundary (margin 0)
        eps = min(1e-7, 0.25 * (b - a))
        pieces.append(_nodes(a + eps, b - eps))
    if not pieces:
        return None
    nodes = np.concatenate(pieces)
    screen = _Screen(family, nodes, objective, weights)
    score = _score(objective, weights)
    while True:
        best_i = screen.next_best()
        if best_i is None:
            return None
        node = screen.member(best_i)
        lo = float(nodes[max(best_i - 1, 0)])
        hi = float(nodes[min(best_i + 1, nodes.size - 1)])
        cand: MemberEval | None = None
        if objective == "tp_then_sensitivity":
            cand = _refine_sensitivity(family, node, lo, hi)
        elif hi > lo:
            cand = _refine_zoom(family, node, lo, hi, screen, best_i, objective, weights)
        if cand is not None and cand.ok and score(cand) <= score(node):
            return cand
        # the node itself, confirmed on the continuous path (else the next best node)
        ok, m = _confirm(family, node.dphi)
        if ok:
            return MemberEval(node.dphi, True, m, node.t_p, node.d_a, node.sensitivity,
                              node.energy)
        screen.reject(best_i)


# ---------------------------------------------------------------------- step 1: the screen
def _uses_bounds(objective: str, w: Weights) -> bool:
    """Scores on a subset of the samples bound the full scores from below."""
    if objective != "weighted":
        return True
    return w.energy == 0.0 and w.d_a >= 0.0 and w.t_p >= 0.0


def _confirm(family: PolynomialFamily, dphi: float) -> tuple[bool, float]:
    """The member's continuous path is inside the request's region (and the full one)."""
    family.deadline_check("the objective search")
    return family.confirm(float(dphi))


def _member(family: PolynomialFamily, s: SampledMembers, i: int, margin: float) -> MemberEval:
    e = s.member(i, family.n)
    return MemberEval(e.dphi, e.ok, margin, e.t_p, e.d_a, e.sensitivity, e.energy)


class _Screen:
    """The nodes ranked by their score on all search samples, evaluated lazily: every node is
    first scored on every COARSE_STRIDE-th sample (a lower bound), and nodes are scored on all
    samples in the order of their bounds until the best full score beats every bound left.
    Ties go to the first node, as in a full screen."""

    def __init__(self, family: PolynomialFamily, nodes: np.ndarray, objective: str,
                 w: Weights) -> None:
        family.deadline_check("the objective search")
        self.family, self.nodes, self.objective, self.w = family, nodes, objective, w
        self.energy = objective == "weighted" and w.energy != 0.0
        K = nodes.size
        self.fine_p = np.full(K, np.inf)
        self.fine_s = np.full(K, np.inf)
        self.done = np.zeros(K, bool)
        self.samples: dict[int, tuple[SampledMembers, int]] = {}
        bounded = _uses_bounds(objective, w)
        if bounded:
            coarse = family.sample(nodes, taus=family.tau[::COARSE_STRIDE])
            self.lb_p, self.lb_s = _keys(objective, w, coarse, family.n)
        else:
            self.lb_p, self.lb_s = np.full(K, -np.inf), np.full(K, -np.inf)
        self.order = [int(i) for i in np.lexsort((np.arange(K), self.lb_s, self.lb_p))
                      if np.isfinite(self.lb_p[i]) or not bounded]
        self.pos = 0
        self.chunk = 4
        self.rejected: set[int] = set()

    def evaluate(self, idx: list[int]) -> None:
        idx = [i for i in idx if not self.done[i]]
        if not idx:
            return
        self.family.deadline_check("the objective search")
        ii = np.array(idx)
        s = self.family.sample(self.nodes[ii], energy=self.energy, keep_dev=True)
        p_, s_ = _keys(self.objective, self.w, s, self.family.n)
        self.fine_p[ii], self.fine_s[ii] = p_, s_
        self.done[ii] = True
        for r, i in enumerate(idx):
            self.samples[i] = (s, r)

    def next_best(self) -> int | None:
        while True:
            cand = [(self.fine_p[i], self.fine_s[i], int(i)) for i in np.nonzero(self.done)[0]
                    if int(i) not in self.rejected and np.isfinite(self.fine_p[i])]
            best = min(cand) if cand else None
            while self.pos < len(self.order) and self.done[self.order[self.pos]]:
                self.pos += 1
            nxt = self.order[self.pos] if self.pos < len(self.order) else None
            if best is not None and (nxt is None
                                     or best <= (self.lb_p[nxt], self.lb_s[nxt], nxt)):
                return best[2]
            if nxt is None:
                return None
            take = self.order[self.pos:self.pos + self.chunk]
            self.chunk = min(2 * self.chunk, 64)
            self.evaluate(take)

    def member(self, i: int) -> MemberEval:
        s, r = self.samples[i]
        return _member(self.family, s, r, float(s.margin[r]))

    def dev(self, idx: list[int]) -> tuple[np.ndarray, np.ndarray, bool]:
        """``|th1 - line|`` rows, ``d_a`` and whether all sampled-feasible, for nodes."""
        self.evaluate(idx)
        rows = []
        da = []
        ok = True
        for i in idx:
            s, r = self.samples[i]
            ok = ok and bool(s.ok[r])
            assert s.dev is not None
            rows.append(s.dev[r])
            da.append(s.d_a[r])
        return np.array(rows), np.array(da), ok

    def reject(self, i: int) -> None:
        self.rejected.add(i)


# ---------------------------------------------------------------------- step 2: refinement
def _refine_zoom(family: PolynomialFamily, best: MemberEval, lo: float, hi: float,
                 screen: _Screen, best_i: int, objective: str, w: Weights
                 ) -> MemberEval | None:
    """The minimum of the score on [lo, hi], refined to XATOL and confirmed on the continuous
    path; None when that fails."""
    tp_best = best.t_p
    restricted = objective == "tp_then_da" or (w.energy == 0.0 and w.t_p == 0.0)
    n = family.n
    nodes = screen.nodes
    G = family.tau.size
    dev = np.zeros((0, G))
    da = np.zeros(0)
    S0 = np.arange(G)
    if restricted:
        # the samples where |th1 - line| can be largest between the neighbouring nodes
        nb = sorted({max(best_i - 1, 0), best_i, min(best_i + 1, nodes.size - 1)})
        dev, da, ok3 = screen.dev(nb)
        if not ok3:
            restricted = False
        else:
            S0 = _hot_samples(np.arange(G), dev, da, G)

    def scores(ds: np.ndarray, S: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        family.deadline_check("the objective search")
        if restricted:
            s = family.sample(ds, taus=family.tau[S], tp=False, keep_dev=True)
            if objective == "tp_then_da":
                return np.where(s.ok, s.d_a, _BAD), s.dev
            sens = np.asarray(sensitivity_frobenius(ds, n))
            val = w.sensitivity * sens if w.sensitivity != 0.0 else np.zeros(ds.size)
            if w.d_a != 0.0:
                val = val + w.d_a * s.d_a
            return np.where(s.ok, val, _BAD), s.dev
        s = family.sample(ds, energy=w.energy != 0.0 and objective == "weighted")
        v_ = _keys(objective, w, s, n)[1]
        if objective == "tp_then_da":
            assert s.t_p is not None
            return np.where(s.ok & (s.t_p <= tp_best), s.d_a, _BAD), None
        return np.where(np.isfinite(v_), v_, _BAD), None

    P = ZOOM_MEMBERS if restricted else 17
    score = _score(objective, w)
    for _ in range(4):
        a, b = lo, hi
        bd, bv = best.dphi, np.inf
        S = S0
        while b - a > XATOL:
            # members per round: fewer while many samples are followed
            Pr = P if not restricted else \
                int(max(17, min(P, (ZOOM_POINTS_BUDGET // max(S.size, 1)) | 1)))
            ds = np.linspace(a, b, Pr)
            v, devS = scores(ds, S)
            j = int(np.argmin(v))
            if v[j] < bv:
                bd, bv = float(ds[j]), float(v[j])
            step = (b - a) / (Pr - 1)
            a, b = max(lo, float(ds[j]) - step), min(hi, float(ds[j]) + step)
            if devS is not None:
                # follow the maxima of the members around the new bracket only
                rows = [max(j - 1, 0), j, min(j + 1, Pr - 1)]
                if np.all(v[rows] < _BAD):
                    S = _hot_samples(S, devS[rows], np.asarray(v[rows]), G)
        cand, dev1 = _full_member(family, bd, objective, w)
        if cand is not None and restricted and \
                not score(cand)[1] <= bv + 1e-12 * max(1.0, abs(bv)):
            # the largest deviation of the result lies away from the samples followed: follow
            # its maxima too and zoom again
            assert dev1 is not None
            dev = np.vstack([dev, dev1])
            da = np.append(da, cand.d_a)
            S0 = _hot_samples(np.arange(G), dev, da, G)
            continue
        if cand is not None and objective != "weighted" and cand.t_p > tp_best:
            break
        if cand is not None:
            return cand
        break
    # the shortcut did not hold: bounded Brent on fully evaluated members
    return _refine_brent(family, best, lo, hi, objective, w)


def _hot_samples(S: np.ndarray, dev: np.ndarray, d_a: np.ndarray, G: int, gap: int = 150,
                 pad: int = 8) -> np.ndarray:
    """Sample indices (of the G search samples) where ``|th1 - line|`` can be largest for
    members between the rows of ``dev`` (their deviations at the samples ``S``): the range
    swept by the rows' largest deviations (it moves with dphi), and around the other
    significant local maxima of every row (at least half its largest deviation; maxima closer
    than ``gap`` samples joined into one range), widened by ``pad``; plus both ends (they define
    the line)."""
    sel = np.zeros(G, bool)
    sel[0] = sel[-1] = True
    top = S[np.argmax(dev, axis=1)]
    sel[max(int(top.min()) - pad, 0):min(int(top.max()) + pad, G - 1) + 1] = True
    pos: list[int] = []
    for row, m in zip(dev, d_a):
        inner = np.nonzero((row[1:-1] >= row[:-2]) & (row[1:-1] >= row[2:])
                           & (row[1:-1] >= 0.5 * m))[0] + 1
        pos.extend(int(S[g]) for g in inner)
    pos.sort()
    if pos:
        start = prev = pos[0]
        for g in pos[1:] + [-1]:
            if g >= 0 and g - prev <= gap:
                prev = g
                continue
            sel[max(start - pad, 0):min(prev + pad, G - 1) + 1] = True
            start = prev = g
    return np.nonzero(sel)[0]


def _full_member(family: PolynomialFamily, dphi: float, objective: str, w: Weights
                 ) -> tuple[MemberEval | None, np.ndarray | None]:
    """A member evaluated on all samples and on the continuous path (None if not feasible),
    and its ``|th1 - line|`` on the samples."""
    family.deadline_check("the objective search")
    s = family.sample(np.array([dphi]), energy=objective == "weighted" and w.energy != 0.0,
                      keep_dev=True)
    dev = s.dev[0] if s.dev is not None else None
    if not s.ok[0]:
        return None, dev
    ok, m = _confirm(family, dphi)
    if not ok:
        return None, dev
    return _member(family, s, 0, m), dev


def _refine_brent(family: PolynomialFamily, best: MemberEval, lo: float, hi: float,
                  objective: str, w: Weights) -> MemberEval | None:
    score = _score(objective, w)
    tp_best = best.t_p

    def restricted(d: float) -> float:
        e = family.evaluate(float(d))
        if not e.ok or (objective != "weighted" and e.t_p > tp_best):
            return _BAD
        return score(e)[1]

    res = minimize_scalar(restricted, bounds=(lo, hi), method="bounded",
                          options={"xatol": XATOL, "maxiter": 200})
    cand = family.evaluate(float(res.x))
    return cand if cand.ok else None


def _refine_sensitivity(family: PolynomialFamily, best: MemberEval, lo: float, hi: float
                        ) -> MemberEval | None:
    """Smallest |dphi| inside the {t_p = min} set next to ``best``: a boundary, found by
    multisection toward the bracket end with the smaller |dphi|; confirmed on the continuous
    path (None when that fails)."""
    tp_best = best.t_p
    toward = lo if abs(lo) < abs(best.dphi) else hi

    def passes(ds: np.ndarray) -> np.ndarray:
        family.deadline_check("the objective search")
        s = family.sample(ds)
        assert s.t_p is not None
        return s.ok & (s.t_p <= tp_best)

    if passes(np.array([toward]))[0]:
        e = _full_member(family, toward, "tp_then_sensitivity", Weights())[0]
        if e is not None:
            return e
        return _bisect_sensitivity(family, best, toward)
    good, bad = best.dphi, toward
    while abs(good - bad) > XATOL:
        ts = np.linspace(0.0, 1.0, SECTION_MEMBERS + 2)[1:-1]
        ds = good + ts * (bad - good)
        ok = passes(ds)
        fail = np.nonzero(~ok)[0]
        k = int(fail[0]) if fail.size else ds.size
        if k > 0:
            good = float(ds[k - 1])
        if k < ds.size:
            bad = float(ds[k])
    e = _full_member(family, good, "tp_then_sensitivity", Weights())[0]
    if e is not None and e.t_p <= tp_best:
        return e
    return _bisect_sensitivity(family, best, toward)


def _bisect_sensitivity(family: PolynomialFamily, best: MemberEval, toward: float
                        ) -> MemberEval | None:
    """The original scalar rule on fully evaluated members (fallback)."""
    tp_best = best.t_p

    def ok(d: float) -> bool:
        e = family.evaluate(float(d))
        return e.ok and e.t_p <= tp_best

    good, bad = best.dphi, toward
    if ok(bad):
        return family.evaluate(float(bad))
    while abs(good - bad) > XATOL:
        mid = 0.5 * (good + bad)
        if ok(mid):
            good = mid
        else:
            bad = mid
    e = family.evaluate(float(good))
    return e if e.ok else None


# ---------------------------------------------------------------------- geometric objective
#: Members screened over all intervals by the geometric objective (at least 3 per interval).
GEOMETRY_NODES = 24
#: Path samples per member of the geometric objective (the indicators' grid is finer; the
#: winner is measured there).
GEOMETRY_SAMPLES = 257


def _geometry_keys(family: PolynomialFamily, dphis: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(reversals, deviation)`` of members (inf where a member cannot be inverted)."""
    from ..indicators import ACTUATOR_DEAD_BAND, count_reversals, segment_distance

    sig = np.linspace(0.0, 1.0, GEOMETRY_SAMPLES)
    z, regular, _ = family.batch_z(dphis, sig)
    D = dphis.size
    inv = family.cf.from_chained(z.reshape(-1, family.n + 1))
    q = inv.q.reshape(D, sig.size, family.n + 1)
    valid = regular & inv.valid.reshape(D, sig.size).all(axis=1)
    rev = np.full(D, np.inf)
    dev = np.full(D, np.inf)
    for i in np.flatnonzero(valid):
        th = q[i, :, 1:]
        # phi = b0 t is monotone in the family: only th1's actuator can reverse
        rev[i] = count_reversals(th[:, 0], ACTUATOR_DEAD_BAND)
        dev[i] = segment_distance(th)
    return rev, dev


def optimise_geometry(family: PolynomialFamily, intervals: list[tuple[float, float]]
                      ) -> MemberEval | None:
    """The member with the fewest actuator reversals, then the smallest joint-space deviation
    from the straight segment start -> goal.

    A screen of :data:`GEOMETRY_NODES` members spread over the intervals, then bounded Brent
    minimisation of the deviation between the best node's neighbours (among members with as
    few reversals), and the continuous check of the result; the next best node when that check
    fails.
    """
    if not intervals:
        return None
    nodes = window_nodes(intervals, GEOMETRY_NODES)
    rev, dev = _geometry_keys(family, nodes)
    order = np.lexsort((dev, rev))
    for i in order:
        if not np.isfinite(dev[i]):
            return None
        r0 = rev[i]
        lo = float(nodes[max(i - 1, 0)])
        hi = float(nodes[min(i + 1, nodes.size - 1)])
        x_best, f_best = float(nodes[i]), float(dev[i])
        if hi > lo:
            def f(x: float) -> float:
                r, d = _geometry_keys(family, np.array([x]))
                return float(d[0]) if r[0] <= r0 else _BAD

            res = minimize_scalar(f, bounds=(lo, hi), method="bounded",
                                  options={"xatol": 1e-6, "maxiter": 40})
            if res.success and float(res.fun) < f_best:
                x_best, f_best = float(res.x), float(res.fun)
        for x in (x_best, float(nodes[i])):
            ok, m = _confirm(family, x)
            if ok:
                return MemberEval(x, True, m, int(r0), _INF_F, _INF_F, _INF_F)
    return None


_INF_F = float("inf")


def window_nodes(intervals: list[tuple[float, float]], count: int) -> np.ndarray:
    """About ``count`` nodes spread over the intervals in proportion to their widths, each a
    hair inside (interval ends are on the boundary, margin 0)."""
    widths = np.array([b - a for a, b in intervals])
    total = float(widths.sum())
    out: list[np.ndarray] = []
    for (a, b), w in zip(intervals, widths):
        k = max(3, int(round(count * w / total)) if total > 0 else 3)
        eps = min(1e-7, 0.25 * (b - a))
        out.append(np.linspace(a + eps, b - eps, k))
    return np.concatenate(out)
