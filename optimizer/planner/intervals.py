"""Singularity-free ``dphi`` intervals of the paper's family (input-parameter adjustment, §3.4).

``F(dphi)`` = the region margin of the member's continuous path (see :mod:`optimizer.region`);
the feasible set is ``{F > 0}``. It is found in three steps, each vectorised over members:

1. a scan of ``F`` on a grid of ``dphi`` (coarse time grid, all members at once) gives an
   upper bound of ``F`` at every node; the exact (continuous-path) margin of the nodes where it
   is positive and of their neighbours in one batch (elsewhere ``F <= 0`` already);
2. every sign change of ``F`` between grid nodes is refined, all brackets together, to
   ``xtol`` = 1e-10 rad: each round evaluates the exact margin at a root estimate, at points
   around it spaced 10^-1, 10^-2, 10^-3, ... of the bracket, and at three points spread over
   it, and keeps the sign change nearest the feasible side. The estimate (inverse quadratic or
   secant interpolation) uses the margin linearised (:meth:`Region.linearised`: the distance
   from the boundary in ``cos(th)^m``, where the angle margin behaves like a square or cube
   root), so two rounds usually suffice; the spread points guarantee a 4-fold shrink;
3. every grid local maximum of ``F`` that is not positive, and that could reach 0 between
   the nodes (node value + 3 x the steeper neighbouring rise > 0), is searched for a hidden
   window: the vectorised coarse margin is zoomed onto its maximum between the neighbouring
   nodes (17 members, then 33 members a round, each round shrinking the bracket 16-fold; the
   search stops after the first round when the margin shows no clear rise toward 0), all such
   maxima at once. A member whose exact margin is positive is a window the grid missed; its
   ends are refined like step 2.

Narrow windows: the zoom resolves windows down to ~1e-4 deg when the margin rises toward them
across the bracket. For n = 4 the tests include a window of 0.05 deg found this way and checked
against a brute-force scan. For n >= 5 the family's windows are often thousandths of a degree
wide or less: in a sample of random reachable 5-joint goals about 3 in 5 are found, for 6 joints
none (the answer is then ``infeasible`` although a member exists; the penalty method and ``auto``
do not depend on these windows).

For n = 3 under ``z2`` the margin is exact (the maximum of the cubic ``z2(t)``, eq 14-16); for the
full condition the polynomial conditions are exact and ``th1 > 0`` is refined numerically.
Reported interval ends lie on the feasible side of the boundary, within 1e-10 rad of it.
"""

from __future__ import annotations

import math

import numpy as np

from ..steering import MIN_ABS_DPHI
from .family import PolynomialFamily

GRID_STEP = math.radians(0.25)
XTOL = 1e-10
LIPSCHITZ_SAFETY = 3.0
#: Rounds of the bracket refinement (at worst ~13 from 0.25 deg).
MAX_ROUNDS = 60
#: Points spread evenly over every bracket in each round: it shrinks at least 4-fold even when
#: the root estimate is poor (the margin's active joint differs between the bracket's ends).
_SPREAD = np.array([0.25, 0.5, 0.75])


def dphi_grid(lo: float, hi: float) -> np.ndarray:
    """The interval search's coarse grid over [lo, hi] (also the retimed screen's): it avoids
    dphi = 0 (Remark 2) by splitting around it."""
    pieces = []
    eps = 10 * MIN_ABS_DPHI
    for a, b in ((lo, min(hi, -eps)), (max(lo, eps), hi)):
        if b > a:
            k = max(2, int(math.ceil((b - a) / GRID_STEP)) + 1)
            pieces.append(np.linspace(a, b, k))
    return np.concatenate(pieces) if pieces else np.zeros(0)


def _exact(family: PolynomialFamily, ds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact margins and their linearised values (same sign) of members ``ds``."""
    family.deadline_check("the interval search")
    res = family.margins(ds, detail=True)
    F = res.margin
    assert res.joint is not None and res.side is not None and res.outside is not None
    E = family.region.linearised(F, res.joint, res.side, res.outside)
    E = np.where(np.isfinite(E), E, F)
    E = np.where(F > 0.0, np.maximum(E, np.finfo(float).tiny), np.minimum(E, 0.0))
    return F, E


def feasible_intervals(family: PolynomialFamily, lo: float, hi: float
                       ) -> list[tuple[float, float]]:
    """All maximal sub-intervals of [lo, hi] where the family's path is singularity-free.

    Parameters
    ----------
    family : PolynomialFamily
    lo, hi : float
        Search bounds for ``dphi`` (rad).

    Returns
    -------
    list of (float, float)
        Sorted, disjoint closed intervals (ends refined to 1e-10 rad, on the feasible side; an
        end equal to a search bound is that bound).
    """
    grid = dphi_grid(lo, hi)
    if grid.size == 0:
        return []
    N = grid.size
    family.deadline_check("the interval search")
    coarse = family.coarse_margins(grid)
    # Candidate nodes: exact margin at nodes that are coarse-positive or next to them, and at
    # coarse local maxima (the coarse margin is an upper bound of the exact one).
    ninf = np.array([-np.inf])
    left = np.concatenate([ninf, coarse[:-1]])
    right = np.concatenate([coarse[1:], ninf])
    pos = coarse > 0.0
    cand = pos.copy()
    cand[1:] |= pos[:-1]
    cand[:-1] |= pos[1:]
    # A peak between nodes can rise above the node by about the local slope times the step;
    # with a safety factor of 3 on the steeper neighbouring slope, a local maximum that cannot
    # reach 0 is not refined.
    with np.errstate(invalid="ignore"):
        rise = np.maximum(np.where(np.isfinite(left), coarse - left, 0.0),
                          np.where(np.isfinite(right), coarse - right, 0.0))
    peaks = ((coarse >= left) & (coarse >= right) & (coarse > -np.pi)
             & (coarse + LIPSCHITZ_SAFETY * rise > 0.0))
    # (a node that is not coarse-positive has F <= coarse <= 0: only the positive nodes and
    # their neighbours, the ends of brackets, need the exact margin)
    Fv = np.full(N, np.nan)
    Ev = np.full(N, np.nan)
    ci = np.nonzero(cand)[0]
    if ci.size:
        Fv[ci], Ev[ci] = _exact(family, grid[ci])
    sign = np.zeros(N, bool)
    sign[ci] = Fv[ci] > 0.0
    split = np.zeros(N, bool)              # split[i]: dphi = 0 lies between nodes i and i + 1
    split[:-1] = (grid[:-1] < 0.0) & (grid[1:] > 0.0)

    # Step 3: local maxima of the exact margin at candidate nodes that are not positive.
    pk = np.nonzero(peaks)[0]
    near = sign.copy()
    near[1:] |= sign[:-1]
    near[:-1] |= sign[1:]
    pk = pk[~near[pk]]
    A = grid[np.maximum(pk - 1, 0)]
    B = grid[np.minimum(pk + 1, N - 1)]
    keep = ~((A < 0.0) & (0.0 < B))
    pk, A, B = pk[keep], A[keep], B[keep]
    brackets: list[tuple[float, float, float, float]] = []   # (x_out, x_in, E_out, E_in)
    targets: list[tuple[list[float], int]] = []               # (interval, end) per bracket
    found_iv: list[list[float]] = []
    if pk.size:
        found, _, Efound = _zoom_peaks(family, A, B)
        hit = np.nonzero(np.isfinite(found))[0]
        if hit.size:
            Fe, Ee = _exact(family, np.concatenate([A[hit], B[hit]]))
            m = hit.size
            for r, h in enumerate(hit):
                w = [float(A[h]), float(B[h])]
                found_iv.append(w)
                for side, x_out, r_out in ((0, A[h], r), (1, B[h], m + r)):
                    if Fe[r_out] <= 0.0:
                        targets.append((w, side))
                        brackets.append((float(x_out), float(found[h]), float(Ee[r_out]),
                                         float(Efound[h])))

    # Step 2: runs of positive nodes, ends refined between the node and its neighbour.
    runs: list[list[float]] = []
    prev_pos = np.zeros(N, bool)
    prev_pos[1:] = sign[:-1] & ~split[:-1]
    next_pos = np.zeros(N, bool)
    next_pos[:-1] = sign[1:] & ~split[:-1]
    starts = np.nonzero(sign & ~prev_pos)[0]
    stops = np.nonzero(sign & ~next_pos)[0]
    for i, j in zip(starts, stops):
        run = [float(grid[i]), float(grid[j])]
        runs.append(run)
        if i > 0 and not split[i - 1]:
            targets.append((run, 0))
            brackets.append((float(grid[i - 1]), float(grid[i]), float(Ev[i - 1]),
                             float(Ev[i])))
        if j < N - 1 and not split[j]:
            targets.append((run, 1))
            brackets.append((float(grid[j + 1]), float(grid[j]), float(Ev[j + 1]),
                             float(Ev[j])))
    if brackets:
        ends = _refine(family, brackets)
        for (iv, side), x in zip(targets, ends):
            iv[side] = float(x)
    intervals = [(a, b) for a, b in runs + found_iv]
    return _merge(sorted(intervals))


def _refine(family: PolynomialFamily, brackets: list[tuple[float, float, float, float]]
            ) -> np.ndarray:
    """Boundary of the feasible set in every bracket ``(x_out, x_in, E_out, E_in)``
    (``E_out <= 0 < E_in``, linearised margins), to :data:`XTOL`, all brackets at once.

    Each round puts points at the root estimate (inverse quadratic interpolation through the
    bracket's ends and the evaluated point nearest to it, else the secant of the bracket),
    around it at 10^-1, 10^-2, ... of the bracket, and evenly over the bracket; the new bracket
    is the sign change nearest the feasible side. Returns the end on the feasible side of each final bracket.
    """
    xo = np.array([b[0] for b in brackets], float)
    xi = np.array([b[1] for b in brackets], float)
    eo = np.array([b[2] for b in brackets], float)
    ei = np.array([b[3] for b in brackets], float)
    hist: list[list[tuple[float, float]]] = [[(xo[b], eo[b]), (xi[b], ei[b])]
                                             for b in range(len(brackets))]
    for _ in range(MAX_ROUNDS):
        active = np.nonzero(np.abs(xi - xo) > XTOL)[0]
        if active.size == 0:
            break
        pts: list[np.ndarray] = []
        owner: list[np.ndarray] = []
        for b in active:
            w = xi[b] - xo[b]
            x_est = _estimate(hist[b], xo[b], xi[b], eo[b], ei[b])
            t = (x_est - xo[b]) / w
            offs = [0.0]
            o = 0.1
            while o * abs(w) > 0.25 * XTOL:
                offs.append(o)
                o *= 0.1
            offs.append(0.25 * XTOL / abs(w))
            o_ = np.array(offs)
            ts = np.concatenate([t + o_, t - o_[1:], _SPREAD])
            ts = np.unique(ts[(ts > 0.0) & (ts < 1.0)])
            pts.append(xo[b] + ts * w)
            owner.append(np.full(ts.size, b))
        X = np.concatenate(pts)
        own = np.concatenate(owner)
        Ex = _exact(family, X)[1]
        for b, xs in zip(active, pts):
            e = Ex[own == b]
            hist[b].extend(zip(xs.tolist(), e.tolist()))
            # order from x_out to x_in; the sign change nearest the feasible side
            order = np.argsort((xs - xo[b]) / (xi[b] - xo[b]))
            xs_o, e_o = xs[order], e[order]
            bad = np.nonzero(e_o <= 0.0)[0]
            k = int(bad[-1]) if bad.size else -1
            if k >= 0:
                xo[b], eo[b] = xs_o[k], e_o[k]
            if k + 1 < xs_o.size:
                xi[b], ei[b] = xs_o[k + 1], e_o[k + 1]
    return xi


def _estimate(hist: list[tuple[float, float]], xo: float, xi: float, eo: float, ei: float
              ) -> float:
    """Root estimate inside the bracket [xo, xi]: inverse quadratic interpolation through the
    three evaluated points with the smallest |E| when it falls inside, else the secant."""
    lo, hi = min(xo, xi), max(xo, xi)
    den = ei - eo
    xs = xi - ei * (xi - xo) / den if den > 0.0 and math.isfinite(den) else 0.5 * (xo + xi)
    # the bracket's ends and the evaluated point nearest to the bracket
    others = [p for p in hist if math.isfinite(p[1]) and not lo <= p[0] <= hi]
    if others:
        x2, f2 = min(others, key=lambda p: min(abs(p[0] - lo), abs(p[0] - hi)))
        (x0, f0), (x1, f1) = (xo, eo), (xi, ei)
        if f0 != f1 and f1 != f2 and f0 != f2:
            xq = (x0 * f1 * f2 / ((f0 - f1) * (f0 - f2)) + x1 * f0 * f2 / ((f1 - f0) * (f1 - f2))
                  + x2 * f0 * f1 / ((f2 - f0) * (f2 - f1)))
            if lo < xq < hi:
                return xq
    if not lo < xs < hi:
        xs = 0.5 * (xo + xi)
    return xs


def _zoom_peaks(family: PolynomialFamily, A: np.ndarray, B: np.ndarray, points: int = 33,
                rounds: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every bracket ``(A_i, B_i)``, a dphi whose exact margin is positive, found by zooming
    the vectorised coarse margin onto its maximum (17, then 33 members a round, the bracket
    shrinking 16-fold), or NaN; all brackets at once. Also the exact margin and its linearised
    value at each found dphi.

    Windows of hundredths of a degree (n >= 4) and thousandths (n >= 5) are much narrower than
    the grid step, and the exact margin outside them is too rough for a scalar root finder; the
    coarse margin is cheap to evaluate for many members at once, so a dense zoom finds them.
    """
    P = A.size
    found = np.full(P, np.nan)
    Ff = np.full(P, np.nan)
    Ef = np.full(P, np.nan)
    lo, hi = A.copy(), B.copy()
    best_d = np.full(P, np.nan)
    best_v = np.full(P, -np.inf)
    active = np.arange(P)
    node_v = np.zeros(P)
    for r in range(rounds):
        if active.size == 0:
            break
        family.deadline_check("the interval search")
        k = 17 if r == 0 else points
        u = np.linspace(0.0, 1.0, k)
        ds = lo[active, None] + (hi - lo)[active, None] * u[None, :]
        flat = ds.ravel()
        if r == 0:
            flat = np.concatenate([flat, 0.5 * (A + B)])
        vals_all = family.coarse_margins(flat)
        if r == 0:
            node_v = vals_all[active.size * k:]
            vals_all = vals_all[:active.size * k]
        vals = vals_all.reshape(active.size, k)
        j = np.argmax(vals, axis=1)
        rows = np.arange(active.size)
        vj, dj = vals[rows, j], ds[rows, j]
        better = vj > best_v[active]
        best_v[active] = np.where(better, vj, best_v[active])
        best_d[active] = np.where(better, dj, best_d[active])
        if r == 0:
            # no clear rise toward 0 inside the bracket: not a hidden window
            rises = best_v[active] > node_v[active] + 0.25 * np.abs(node_v[active])
            active, j, dj = active[rises], j[rises], dj[rises]
            if active.size == 0:
                break
        step = (hi[active] - lo[active]) / (k - 1)
        lo[active] = np.maximum(A[active], dj - step)
        hi[active] = np.minimum(B[active], dj + step)
        test = active[best_v[active] > 0.0]
        if test.size:
            F, E = _exact(family, best_d[test])
            okk = F > 0.0
            found[test[okk]] = best_d[test[okk]]
            Ff[test[okk]] = F[okk]
            Ef[test[okk]] = E[okk]
            active = np.setdiff1d(active, test[okk])
    return found, Ff, Ef


def _merge(iv: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    for a, b in iv:
        if out and a <= out[-1][1] + 1e-12 and not (out[-1][1] < 0.0 < a):
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
