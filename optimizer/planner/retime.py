"""Retiming: the paper's geometric path, run along a time law that minimises ``d_a``.

With the paper's constant ``v1`` the chained path ``z(sigma)`` is fixed by ``dphi`` alone; the
region check, ``t_p`` (extrema of ``th1`` along the path) and ``||J_R(T)||_F`` are properties of
that *geometric* path. ``d_a`` is not: it measures ``th1(t)`` against the straight line *in
time*, so the speed at which the path is run changes it. A monotone time law ``sigma(tau)``
keeps everything geometric and can lower ``d_a`` a great deal.

The time law is piecewise linear: knots ``sigma_j`` are reached at normalised times ``tau_j``
(the unknowns). The knots split the path evenly by a mix of ``sigma`` and the variation of
``th1`` (near ``th1 = 0`` the map makes ``th1`` rise steeply in ``sigma``: such a stretch needs
pieces of its own, since a piece runs at one speed). On piece ``j`` the path runs at constant speed, so ``V1`` is constant
and ``V2(tau) = r_j z2'(sigma(tau))`` is a polynomial: the retimed plan is again a
piecewise-polynomial :class:`~optimizer.steering.InputSchedule`, exact and replayable.

Why an LP: at a sample ``sigma_i`` inside piece ``j`` (weight ``w_i``) the time is
``tau(sigma_i) = (1 - w_i) tau_{j-1} + w_i tau_j``, so the deviation
``th1(sigma_i) - line(tau(sigma_i))`` is *affine* in the unknown knot times. Minimising its
largest magnitude is a linear program (a small QP with a light regulariser toward uniform
timing, which picks one optimum among many); Clarabel solves it. The lower bound of any
monotone time law is the 1-D Fréchet distance between ``th1(sigma)`` and the line
(:func:`frechet_bound`), used to rank candidate ``dphi`` before the LP.

A speed bound keeps the time law sane: every piece lasts at least ``1 / (K max_speedup)``, i.e.
phi runs at most ``max_speedup`` times faster than with the paper's constant ``v1``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.special import comb

from ..errors import NumericalError
from ..steering import ChainedPath, InputSchedule
from . import qp
from .qp import Csc

#: Pieces of the piecewise-linear time law.
PIECES = 8
#: Samples of th1 per piece in the LP.
SAMPLES_PER_PIECE = 8
#: phi may run at most this many times faster than under the paper's constant v1.
MAX_SPEEDUP = 8.0
#: Weight of the regulariser sum (h_j - 1/K)^2 (K h_j is the relative duration of piece j).
REGULARISATION = 1e-4
#: Normalised times at which the planner screens the family's members before ranking them
#: (a member's continuous margin is at most its margin at any sampled times).
SCREEN_TIMES = 13


@dataclass(frozen=True)
class TimeLaw:
    """A piecewise-linear time law ``sigma(tau)`` through ``(tau_j, j / K)``.

    Attributes
    ----------
    knots_tau : ndarray (K+1,)
        ``0 = tau_0 < ... < tau_K = 1``.
    knots_sigma : ndarray (K+1,)
        ``0 = sigma_0 < ... < sigma_K = 1``: where the path is at ``tau_j``.
    deviation : float
        The LP's largest ``|th1 - line|`` at its samples (rad).
    bound : float
        The Fréchet lower bound of any monotone time law (rad).
    """

    knots_tau: np.ndarray
    knots_sigma: np.ndarray
    deviation: float
    bound: float

    @property
    def pieces(self) -> int:
        return self.knots_tau.size - 1


def frechet_bound(th1: np.ndarray, a: float, b: float) -> np.ndarray:
    """Lower bound of ``max |th1(sigma(tau)) - line(tau)|`` over monotone time laws.

    ``th1`` has shape (..., G) on an increasing ``sigma`` grid; the line runs from ``a`` to
    ``b``. Two things no retiming can hide: a value beyond the line's range (``th1 > max(a, b)``
    or ``< min(a, b)``), and a backtrack against the line's direction, which costs half its
    depth (the path goes back while the line goes on).
    """
    f = np.asarray(th1, float)
    if b < a:
        f, a, b = -f, -a, -b
    back = 0.5 * (np.maximum.accumulate(f, axis=-1) - f).max(axis=-1)
    over = np.maximum((f - b).max(axis=-1), (a - f).max(axis=-1))
    return np.maximum(np.maximum(back, over), 0.0)


def optimal_time_law(th1_of_sigma: Callable[[np.ndarray], np.ndarray], a: float, b: float,
                     pieces: int = PIECES, samples_per_piece: int = SAMPLES_PER_PIECE,
                     max_speedup: float = MAX_SPEEDUP) -> TimeLaw:
    """The piecewise-linear time law that minimises ``max |th1(sigma(tau)) - line(tau)|``.

    Parameters
    ----------
    th1_of_sigma : callable
        ``sigma (array in [0, 1]) -> th1`` along the geometric path.
    a, b : float
        ``th1`` at start and goal (the line's ends).
    """
    K, M = int(pieces), int(samples_per_piece)
    knots = _knots(th1_of_sigma, K)
    lp = _lp_structure(K, M)
    j, ww = lp.j, lp.ww
    sig = knots[j - 1] + ww * (knots[j] - knots[j - 1])
    th = np.asarray(th1_of_sigma(np.append(sig, 1.0)), float)
    bound = float(frechet_bound(th, a, b))
    th = th[:-1]
    slope = b - a
    S = sig.size
    # +-(th - a - slope tau) <= delta  ->  rows of G x <= h (x = tau_1..tau_{K-1}, delta);
    # tau(sigma_i) = coef_i . x + const_i (see _lp_structure), then the piece durations
    G = np.empty((2 * S + K, K))
    G[:S, :-1] = -slope * lp.coef
    G[S:2 * S, :-1] = slope * lp.coef
    G[:2 * S, -1] = -1.0
    G[2 * S:] = lp.neg_Dd
    h_up = a + slope * lp.const - th
    h_dn = th - a - slope * lp.const
    # monotone with a minimum piece duration (the speed bound): -(Dd x + off) <= -h_min
    h_min: np.ndarray = np.diff(knots) / max_speedup
    h = np.concatenate([h_up, h_dn, lp.off - h_min])
    # objective delta + rho * sum_j (duration_j - dsigma_j)^2, as 1/2 x'Px + q'x
    r: np.ndarray = lp.off - np.diff(knots)
    q = lp.reg_DdT @ r
    q[-1] += 1.0
    sol = qp.solve(lp.P, q, Csc.from_dense(G), h)
    if str(sol.status) not in ("Solved", "AlmostSolved"):
        raise NumericalError(f"the time-law LP did not solve ({sol.status})",
                             diagnostics={"status": str(sol.status)})
    x = np.asarray(sol.x)
    tau = np.concatenate([[0.0], x[:-1], [1.0]])
    # guard against round-off: strictly increasing by construction of the constraints
    tau = np.maximum.accumulate(tau)
    return TimeLaw(knots_tau=tau, knots_sigma=knots, deviation=float(x[-1]), bound=bound)


@dataclass(frozen=True)
class _LpStructure:
    """The parts of the time-law LP that depend on the numbers of pieces and samples only."""

    j: np.ndarray          # piece of each sample (1-based)
    ww: np.ndarray         # its weight inside the piece
    coef: np.ndarray       # (S, K-1): tau(sigma_i) = coef_i . (tau_1..tau_{K-1}) + const_i
    const: np.ndarray
    neg_Dd: np.ndarray     # (K, K): minus the piece durations' matrix (tau_j - tau_{j-1})
    off: np.ndarray        # the durations' constant part (tau_K = 1)
    reg_DdT: np.ndarray    # 2 rho Dd^T (the regulariser's linear term is reg_DdT @ r)
    P: Csc                # upper triangle of 2 rho Dd^T Dd


@functools.lru_cache(maxsize=8)
def _lp_structure(K: int, M: int) -> _LpStructure:
    w = np.arange(M) / M                                   # weights inside a piece
    j = np.repeat(np.arange(1, K + 1), M)                  # piece of each sample (1-based)
    ww = np.tile(w, K)
    S = j.size
    nv = K  # unknowns tau_1..tau_{K-1}, then delta
    # tau(sigma_i) = (1 - w) tau_{j-1} + w tau_j, with tau_0 = 0 and tau_K = 1 known
    coef = np.zeros((S, nv))
    const = np.zeros(S)
    left, right = j - 1, j
    for idx, wt in ((left, 1.0 - ww), (right, ww)):
        inner = (idx >= 1) & (idx <= K - 1)
        coef[np.nonzero(inner)[0], idx[inner] - 1] += wt[inner]
        const += np.where(idx == K, wt, 0.0)
    # piece durations tau_j - tau_{j-1} = Dd x + off (tau_0 = 0 and tau_K = 1 are known)
    Dd = np.hstack([np.eye(K, K - 1) - np.eye(K, K - 1, k=-1), np.zeros((K, 1))])
    off = np.zeros(K)
    off[-1] = 1.0
    reg_DdT = 2.0 * REGULARISATION * Dd.T
    out = _LpStructure(j, ww, np.ascontiguousarray(coef[:, :-1]), const, -Dd, off, reg_DdT,
                       Csc.from_dense(np.triu(reg_DdT @ Dd)))
    for arr in (j, ww, out.coef, const, out.neg_Dd, off, reg_DdT):
        arr.flags.writeable = False                     # shared between calls
    return out


def _knots(th1_of_sigma: Callable[[np.ndarray], np.ndarray], K: int, grid: int = 513
           ) -> np.ndarray:
    """Knots that split [0, 1] evenly by half ``sigma``, half the variation of ``th1``."""
    s = np.linspace(0.0, 1.0, grid)
    th = np.asarray(th1_of_sigma(s), float)
    var = np.concatenate([[0.0], np.cumsum(np.abs(np.diff(th)))])
    c = 0.5 * s + (0.5 * var / var[-1] if var[-1] > 0 else 0.5 * s)
    knots = np.interp(np.linspace(0.0, 1.0, K + 1), c, s)
    knots[0], knots[-1] = 0.0, 1.0
    return knots


def _shift_matrices(s0: np.ndarray, r: np.ndarray, size: int) -> np.ndarray:
    """``T[j]`` maps the coefficients of ``p(sigma)`` to those of ``p(s0_j + r_j x)`` in ``x``:
    ``T[j, k, i] = C(i, k) s0_j^(i-k) r_j^k`` (a Taylor shift and a scaling, exact)."""
    binom, power, k = _shift_tables(size)
    return (binom[None] * s0[:, None, None] ** power[None]
            * r[:, None, None] ** k[None])


@functools.lru_cache(maxsize=16)
def _shift_tables(size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``C(i, k)`` (0 for i < k), the powers ``max(i - k, 0)`` and ``k`` (a column) of
    :func:`_shift_matrices`, read-only."""
    i = np.arange(size)
    k = i[:, None]
    binom = comb(i[None, :], k)                                     # (size, size), 0 for i < k
    power = np.clip(i[None, :] - k, 0, None)
    for a in (binom, power, k):
        a.flags.writeable = False
    return binom, power, k


def retimed_path(path: ChainedPath, law: TimeLaw) -> ChainedPath:
    """``path`` (one piece, constant ``V1``) run along ``law``: inputs and chained state.

    On piece ``j``: ``sigma = sigma_{j-1} + r_j (tau - tau_{j-1})`` with
    ``r_j = (sigma_j - sigma_{j-1}) / (tau_j - tau_{j-1})``, so ``V1 = dphi r_j``,
    ``V2(tau) = r_j V2_geo(sigma(tau))`` (the chain rule) and ``z(tau) = z_geo(sigma(tau))``:
    every polynomial of the geometric path composed with the piece's linear map, so the
    retimed path passes through exactly the geometric path's states.
    """
    inp = path.inputs
    if inp.pieces != 1 or np.any(inp.v1[0][1:] != 0.0):
        raise ValueError("retiming needs a single-piece path with constant V1")
    dphi = float(inp.v1[0][0])
    t, sg = law.knots_tau, law.knots_sigma
    s0 = sg[:-1]
    r = np.diff(sg) / np.diff(t)
    geo = path.polys[0]                                             # (n+1, deg+1)
    Tz = _shift_matrices(s0, r, geo.shape[1])
    zpolys = np.einsum("jki,ni->jnk", Tz, geo)                      # (K, n+1, deg+1)
    v2 = inp.v2[0]
    Tv = _shift_matrices(s0, r, v2.size)
    v2s = r[:, None] * np.einsum("jki,i->jk", Tv, v2)
    inputs = InputSchedule(t.copy(), tuple(np.array([dphi * x]) for x in r),
                           tuple(v2s), inp.duration)
    return ChainedPath(path.z0, inputs, tuple(zpolys))
