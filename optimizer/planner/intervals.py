"""Singularity-free ``dphi`` intervals of the paper's family (input-parameter adjustment, §3.4).

``F(dphi)`` = the region margin of the member's continuous path (see :mod:`optimizer.region`);
the feasible set is ``{F > 0}``. It is found in three steps:

1. a scan of ``F`` on a grid of ``dphi`` (coarse time grid, vectorised), giving brackets;
2. every sign change of ``F`` between grid nodes is refined with Brent's method on the exact
   (continuous-path) margin, to ``xtol`` = 1e-10 rad;
3. every grid local maximum of ``F`` that is not positive, and that could reach 0 between
   the nodes (node value + 3 x the steeper neighbouring rise > 0), is searched for a hidden
   window: the vectorised coarse margin is zoomed onto its maximum between the neighbouring
   nodes (17 members, then 33 members a round, each round shrinking the bracket 16-fold; the
   search stops after the first round when the margin shows no clear rise toward 0). A member
   whose exact margin is positive is a window the grid missed; its ends are refined like step 2.

Narrow windows: the zoom resolves windows down to ~1e-4 deg when the margin rises toward them
across the bracket. For n = 4 the tests include a window of 0.05 deg found this way and checked
against a brute-force scan. For n >= 5 the family's windows are often thousandths of a degree
wide or less: in a sample of random reachable 5-joint goals about 3 in 5 are found, for 6 joints
none (the answer is then ``infeasible`` although a member exists; the penalty method and ``auto``
do not depend on these windows).

For n = 3 under ``z2`` the margin is exact (the maximum of the cubic ``z2(t)``, eq 14-16); for the
full condition the polynomial conditions are exact and ``th1 > 0`` is refined numerically.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from ..steering import MIN_ABS_DPHI
from .family import PolynomialFamily

GRID_STEP = math.radians(0.25)
XTOL = 1e-10
LIPSCHITZ_SAFETY = 3.0


def _grid(lo: float, hi: float) -> np.ndarray:
    """Grid over [lo, hi] that avoids dphi = 0 (Remark 2) by splitting around it."""
    pieces = []
    eps = 10 * MIN_ABS_DPHI
    for a, b in ((lo, min(hi, -eps)), (max(lo, eps), hi)):
        if b > a:
            k = max(2, int(math.ceil((b - a) / GRID_STEP)) + 1)
            pieces.append(np.linspace(a, b, k))
    return np.concatenate(pieces) if pieces else np.zeros(0)


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
        Sorted, disjoint closed intervals (ends refined to 1e-10 rad; an end equal to a search
        bound is that bound).
    """
    grid = _grid(lo, hi)
    if grid.size == 0:
        return []
    coarse = family.coarse_margins(grid)
    exact = {}

    def F(d: float) -> float:
        d = float(d)
        if d not in exact:
            exact[d] = family.margin(d)
        return exact[d]

    def G(d: float) -> float:
        # same sign as F; the angle margin behaves like sqrt(distance) at the boundary, its
        # signed square like the distance itself, where Brent's method converges fast
        f = F(d)
        return f * abs(f)

    # Candidate nodes: exact margin at nodes that are coarse-positive or next to them, and at
    # coarse local maxima (the coarse margin is an upper bound of the exact one).
    N = grid.size
    cand = set()
    peaks = set()
    for i in range(N):
        if coarse[i] > 0:
            cand.update({max(i - 1, 0), i, min(i + 1, N - 1)})
        left = coarse[i - 1] if i > 0 else -np.inf
        right = coarse[i + 1] if i < N - 1 else -np.inf
        if coarse[i] >= left and coarse[i] >= right and coarse[i] > -np.pi:
            # A peak between nodes can rise above the node by about the local slope times the
            # step; with a safety factor of 3 on the steeper neighbouring slope, a local maximum
            # that cannot reach 0 is not refined.
            rise = max(coarse[i] - left if np.isfinite(left) else 0.0,
                       coarse[i] - right if np.isfinite(right) else 0.0)
            if coarse[i] + LIPSCHITZ_SAFETY * rise > 0.0:
                cand.add(i)
                peaks.add(i)
    sign = np.full(N, False)
    for i in sorted(cand):
        sign[i] = F(grid[i]) > 0.0

    # Step 3: local maxima of the exact margin at candidate nodes that are not positive.
    extra_windows: list[tuple[float, float]] = []
    for i in sorted(peaks):
        if sign[i] or (i > 0 and sign[i - 1]) or (i < N - 1 and sign[i + 1]):
            continue  # next to a positive node: step 2 refines that run's ends
        a = grid[max(i - 1, 0)]
        b = grid[min(i + 1, N - 1)]
        if a < 0.0 < b:
            continue
        peak = _zoom_peak(family, a, b)
        if peak is not None and F(peak) > 0.0:
            left = brentq(G, a, peak, xtol=XTOL) if F(a) <= 0.0 else a
            right = brentq(G, peak, b, xtol=XTOL) if F(b) <= 0.0 else b
            extra_windows.append((float(left), float(right)))

    # Step 2: runs of positive nodes, ends refined between the node and its neighbour.
    intervals: list[tuple[float, float]] = []
    i = 0
    while i < N:
        if not sign[i]:
            i += 1
            continue
        j = i
        while j + 1 < N and sign[j + 1] and not (grid[j] < 0.0 < grid[j + 1]):
            j += 1
        a = grid[i]
        if i > 0 and not (grid[i - 1] < 0.0 < grid[i]):
            a = float(brentq(G, grid[i - 1], grid[i], xtol=XTOL))
        b = grid[j]
        if j < N - 1 and not (grid[j] < 0.0 < grid[j + 1]):
            b = float(brentq(G, grid[j], grid[j + 1], xtol=XTOL))
        intervals.append((float(a), float(b)))
        i = j + 1
    intervals.extend(extra_windows)
    return _merge(sorted(intervals))


def _zoom_peak(family: PolynomialFamily, a: float, b: float, points: int = 33,
               rounds: int = 4) -> float | None:
    """A dphi in (a, b) whose exact margin is positive, found by zooming the vectorised coarse
    margin onto its maximum (33 members a round, the bracket shrinking 16-fold), or None.

    Windows of hundredths of a degree (n >= 4) and thousandths (n >= 5) are much narrower than
    the grid step, and the exact margin outside them is too rough for Brent's method; the coarse
    margin is cheap to evaluate for many members at once, so a dense zoom finds them.
    """
    lo, hi = a, b
    best_d, best_v = None, -np.inf
    node_v = float(family.coarse_margins(np.array([0.5 * (a + b)]))[0])
    for r in range(rounds):
        k = 17 if r == 0 else points
        ds = np.linspace(lo, hi, k)
        vals = family.coarse_margins(ds)
        j = int(np.argmax(vals))
        if vals[j] > best_v:
            best_d, best_v = float(ds[j]), float(vals[j])
        if r == 0 and best_v <= node_v + 0.25 * abs(node_v):
            return None  # no clear rise toward 0 inside the bracket: not a hidden window
        step = (hi - lo) / (k - 1)
        lo, hi = max(a, ds[j] - step), min(b, ds[j] + step)
        if best_v > 0.0 and family.margin(best_d) > 0.0:  # type: ignore[arg-type]
            return best_d
    return None


def _merge(iv: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    for a, b in iv:
        if out and a <= out[-1][1] + 1e-12 and not (out[-1][1] < 0.0 < a):
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
