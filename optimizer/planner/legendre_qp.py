"""The building blocks of the constraint-point QP (:mod:`.constraint_qp`): the orthonormal
shifted-Legendre basis of ``V2``, the Chebyshev grid of tau and the least-norm QP
``min 1/2 ||y||^2  s.t.  G y <= h`` (with its margin variant) solved by Clarabel.

Backend
-------
Clarabel through its own Python API (``clarabel.DefaultSolver``, scipy.sparse CSC), with one
solver per problem shape kept per thread and updated in place (``solver.update``; presolve off,
structural zeros kept so the pattern never changes). ``bench/qp_backends.py`` measured, on the
base QP of the §3.3 example at 50 values of ``dphi`` x 5 passes, interleaved (a 2-core machine
shared with other jobs), median per solve from the assembled ``(G, h)`` to the solution:

    m = 4, 160 grid points (4 variables, 480 rows):   persistent 1.70 ms, fresh 2.06 ms,
                                                       cvxpy + DPP Parameters 2.66 ms
    m = 6, 320 grid points (6 variables, 960 rows):   persistent 5.11 ms, fresh 5.84 ms,
                                                       cvxpy + DPP Parameters 6.47 ms

(the three agree to 1e-11; the assembly itself, common to all, takes ~1.5 ms). cvxpy's problem
is built once per (n, m, grid size) and re-solves skip canonicalisation, but its per-solve
parameter mapping and solution retrieval cost more than Clarabel's own setup at this size, so
the direct API is kept; ``solve_qp(..., persistent=False)`` switches solver reuse off
(:mod:`.qp` holds the Clarabel wrapper).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.polynomial import legendre as Leg
from numpy.polynomial import polynomial as P

from ..steering import InputSchedule
from . import qp

BACKEND = "clarabel (direct Python API, scipy.sparse CSC, solver reused per shape)"


@functools.lru_cache(maxsize=32)
def legendre_to_monomial(p: int) -> np.ndarray:
    """``L`` (p, p): column j = the powers-of-tau coefficients of ``sqrt(2j+1) P_j(2 tau - 1)``.

    These shifted Legendre polynomials are orthonormal on [0, 1], so
    ``L.T @ gram_monomials(p) @ L = I`` (exactly; in floating point only to ~1e-6 at p = 9
    because ``gram_monomials`` is a Hilbert matrix: which is why the QP works in this basis).
    """
    L = np.zeros((p, p))
    shift = np.array([-1.0, 2.0])  # x = 2 tau - 1
    for j in range(p):
        cx = Leg.leg2poly(np.eye(p)[j][: j + 1])  # P_j in powers of x
        ct = np.zeros(1)
        xp = np.ones(1)
        for c in cx:  # Horner-free expansion: sum_i c_i (2 tau - 1)^i
            ct = P.polyadd(ct, c * xp)
            xp = P.polymul(xp, shift)
        L[: ct.size, j] = math.sqrt(2 * j + 1) * ct
    return L


def gram_monomials(p: int) -> np.ndarray:
    """``H_ij = int_0^1 tau^i tau^j dtau = 1 / (i + j + 1)``: ``int V2^2 dtau = a^T H a``."""
    i = np.arange(p)
    return 1.0 / (i[:, None] + i[None, :] + 1.0)


@functools.lru_cache(maxsize=16)
def chebyshev_grid(N: int) -> np.ndarray:
    """``N`` interior Chebyshev-Lobatto points of (0, 1), increasing (dense near the ends)."""
    k = np.arange(1, N + 1)
    return 0.5 * (1.0 - np.cos(np.pi * k / (N + 1)))


def solve_qp(G: np.ndarray, h: np.ndarray, margin_column: np.ndarray | None = None,
             margin_cap: float = np.inf, regularisation: float = 1e-4,
             persistent: bool = True) -> tuple[str, np.ndarray | None, float]:
    """``min 1/2 ||y||^2  s.t.  G y <= h`` with Clarabel's Python API (``persistent``: reuse
    the solver of the same shape, updated in place, :func:`.qp.solve_nonneg_persistent`).

    With ``margin_column`` (one entry per row of ``G``) the margin variant is solved instead:
    ``min -t + regularisation/2 ||y||^2  s.t.  G y + margin_column t <= h,  t <= margin_cap``.

    Returns
    -------
    status : str
        Clarabel's status name (``"Solved"``, ``"PrimalInfeasible"``, ...).
    y : ndarray or None
        The solution (without ``t``) when the status is Solved or AlmostSolved.
    t : float
        The margin variable (NaN without ``margin_column``).
    """
    r, d = G.shape
    if margin_column is not None:
        G = np.hstack([G, margin_column[:, None]])
        cap = np.zeros((1, d + 1))
        cap[0, -1] = 1.0
        G = np.vstack([G, cap])
        h = np.append(h, min(margin_cap, 1e6))
        Pd = np.append(np.full(d, regularisation), 0.0)
        q = np.zeros(d + 1)
        q[-1] = -1.0
    else:
        Pd = np.ones(d)
        q = np.zeros(d)
    # rows independent of y: feasible or not, they need no solver
    nrm = np.linalg.norm(G, axis=1)
    keep = nrm > 1e-14 * max(1.0, float(nrm.max(initial=0.0)))
    if np.any(h[~keep] < -1e-12):
        return "PrimalInfeasible", None, math.nan
    G, h, nrm = G[keep], h[keep], nrm[keep]
    # row scaling: rows of z_{n+1} carry dphi^(n-1); Clarabel equilibrates too, this is cheap help
    G = G / nrm[:, None]
    h = h / nrm
    sol = qp.solve_nonneg_persistent(Pd, q, G, h) if persistent else qp.solve(
        qp.diagonal(Pd), q, qp.dense_csc(G), h)
    status = str(sol.status).split(".")[-1]
    if status not in ("Solved", "AlmostSolved"):
        return status, None, math.nan
    x = np.asarray(sol.x, float)
    if margin_column is not None:
        return status, x[:d], float(x[d])
    return status, x, math.nan


def single_piece(dphi: float, v2: np.ndarray, duration: float) -> InputSchedule:
    """One polynomial piece on [0, 1] with ``V1 = dphi`` constant."""
    return InputSchedule(np.array([0.0, 1.0]), (np.array([float(dphi)]),),
                         (np.asarray(v2, float),), float(duration))

