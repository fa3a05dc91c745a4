"""The proof of a continuation: its constant-rate pieces integrated on the original model by
compiled RK4 at two step sizes, with Richardson's estimate of the error (the replanner's
verification, :mod:`.replan` step 3).

Each piece is the flow of the model under constant rates; RK4 with 32 steps on a piece that
moves a few tenths of a radian is within 1e-13 rad of the exact flow, and the run with 16
steps says how far (RK4's error falls 16-fold when the step is halved: the fine run's error
is about ``|fine - coarse| / 15``). Where that estimate is above :data:`VERIFY_TOL`, or not
finite, :func:`integrate_pieces` answers None and the replanner integrates by the cascade
quadrature (:func:`optimizer.cascade.integrate_cascade`) instead. Every joint is monotone on a
constant-rate piece, so the states at the breaks bound the whole path (the region check).
The functions are compiled like the correction's kernels
(:class:`~.continuation_map.CompiledCall`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .continuation_map import BoundCall, CompiledCall, SIZES, piece_function, size_for


#: RK4 steps per unit piece of the compiled verification's coarse run (its fine run takes
#: twice as many): on the benchmark's continuations the two differ by 1e-13 rad or less.
VERIFY_SUBSTEPS = 16
#: Richardson's estimate of the fine run's error (``|fine - coarse| / 15``, RK4) accepted
#: (rad): the cascade quadrature's own target. Above it the cascade integrates instead.
VERIFY_TOL = 1e-11
#: Sizes of the compiled sample maps (samples padded to the next).
SAMPLE_SIZES = (64, 128, 256, 512, 1024, 2048, 4096)
#: RK4 steps of a sample from its piece's start (a part of a piece; the samples show the
#: path, the states at the breaks prove it). Against 256 steps on the continuations of the
#: latency benchmark's states: within 1.2e-9 rad (n = 3) and 3e-9 (n = 5) with 4 steps, 7e-11
#: and 1.8e-10 with 8, a thousandth of the plan's terminal tolerance either way; the samples
#: dominate the proof's cost (32 steps took 1.2 ms for 230 samples), and 4 steps instead of 8
#: made the 3-joint replan 4-5 % cheaper (p50 0.91 / 0.89 / 0.92 -> 0.90 / 0.86 / 0.84 ms,
#: alternating processes on a quiet machine).
SAMPLE_SUBSTEPS = 4


def break_states(gains: tuple[float, ...], exponents: tuple[int, ...], P: int) -> BoundCall:
    """The states at the ends of ``P`` unit pieces twice, ``(q0, W) -> (X_fine, X_coarse)``
    (``(n+1, P)`` each, flat column-major; RK4 with 2 :data:`VERIFY_SUBSTEPS` and
    :data:`VERIFY_SUBSTEPS` steps per piece): the fine states and, from their difference,
    Richardson's estimate of their error."""
    return BoundCall(_break_states(tuple(exponents), P), gains)


@functools.lru_cache(maxsize=64)
def _break_states(exponents: tuple[int, ...], P: int) -> CompiledCall:
    fine = piece_function(exponents, 2 * VERIFY_SUBSTEPS).mapaccum("fine", P)
    coarse = piece_function(exponents, VERIFY_SUBSTEPS).mapaccum("coarse", P)
    q0 = ca.MX.sym("q0", len(exponents) + 2)
    W = ca.MX.sym("W", 2, P)
    K = ca.MX.sym("K", len(exponents))
    Ks = ca.repmat(K, 1, P)
    fn = ca.Function(f"continuation_breaks_{P}", [q0, W, K],
                     [fine(q0, W, Ks), coarse(q0, W, Ks)])
    return CompiledCall(fn, 3, (0, 1))


def sample_states(gains: tuple[float, ...], exponents: tuple[int, ...], N: int) -> BoundCall:
    """``N`` partial pieces at once, ``(Q, W) -> Q_end`` (``(n+1, N)`` starts, ``(2, N)``
    displacement rates; RK4 with :data:`SAMPLE_SUBSTEPS` steps each): the handed-out
    samples from the states at their pieces' starts."""
    return BoundCall(_sample_states(tuple(exponents), N), gains)


@functools.lru_cache(maxsize=64)
def _sample_states(exponents: tuple[int, ...], N: int) -> CompiledCall:
    fine = piece_function(exponents, SAMPLE_SUBSTEPS).map(N)
    nq = len(exponents) + 2
    Q = ca.MX.sym("Q", nq, N)
    W = ca.MX.sym("W", 2, N)
    K = ca.MX.sym("K", nq - 2)
    return CompiledCall(ca.Function(f"continuation_samples_{N}", [Q, W, K],
                                    [fine(Q, W, ca.repmat(K, 1, N))]), 3, (0,))


@dataclass(frozen=True)
class PieceProof:
    """The compiled integration of a continuation's pieces (:func:`integrate_pieces`)."""

    q: np.ndarray               # states at the breaks, then at the samples ((B + S, n+1))
    final: np.ndarray
    error_estimate: float       # rad, Richardson's (fine against coarse)
    singular: bool              # a joint th_1..th_{n-1} outside (0, pi/2) at a break
    success: bool = True
    message: str = ""
    integrator: str = f"RK4 (2 x {VERIFY_SUBSTEPS} steps per piece, compiled)"


def integrate_pieces(gains: tuple[float, ...], exponents: tuple[int, ...], q0: np.ndarray,
                     breaks: np.ndarray, rates: np.ndarray, s_eval: np.ndarray
                     ) -> PieceProof | None:
    """The original model through constant-rate pieces (plan-time ``breaks`` from 0, rates
    ``(M, 2)``) from ``q0``: the states at every break and at the plan times ``s_eval``, by
    compiled RK4 on each piece, with Richardson's estimate of the error (the run at half the
    steps). None when the estimate is above :data:`VERIFY_TOL` or not finite: integrate
    otherwise (the cascade quadrature).

    Each joint is monotone on a piece (``th_i' = K_i cos(th_{i-1})^{m_i} u_1`` with ``u_1``
    constant and ``cos > 0`` inside), so the states at the breaks bound the whole path."""
    L = breaks[1:] - breaks[:-1]
    M = L.size
    W = np.asarray(rates, float) * L[:, None]
    P = size_for(M)
    full = np.zeros((P, 2))
    full[P - M:] = W
    fine, coarse = break_states(gains, exponents, P)(np.asarray(q0, float), full)
    nq = len(gains) + 2
    Xf = fine.reshape(P, nq)[P - M:]
    Xc = coarse.reshape(P, nq)[P - M:]
    est = float(np.max(np.abs(Xf - Xc), initial=0.0)) / 15.0
    if not math.isfinite(est) or est > VERIFY_TOL:
        return None
    Xb = np.vstack([np.asarray(q0, float)[None, :], Xf])          # (M + 1, nq)
    S = s_eval.size
    k = np.minimum(np.maximum(np.searchsorted(breaks, s_eval, side="right") - 1, 0), M - 1)
    N = next((x for x in SAMPLE_SIZES if x >= S), S)
    Q = np.zeros((N, nq))
    Q[:S] = Xb[k]
    Ws = np.zeros((N, 2))
    Ws[:S] = np.asarray(rates, float)[k] * (s_eval - breaks[k])[:, None]
    Qs = sample_states(gains, exponents, N)(Q, Ws)[0].reshape(N, nq)[:S]
    th = Xb[:, 1:-1]
    singular = bool((th <= 0.0).any() or (th >= 0.5 * math.pi).any())
    return PieceProof(np.vstack([Xb, Qs]), Xb[-1].copy(), est, singular)


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...], build: bool = False
            ) -> None:
    """Every size's break-state function and the smaller sample maps of a robot's shape (they
    serve every gains of its exponents), built now
    (``build``: their compiled libraries too, as :func:`~.continuation_map.prepare`)."""
    exponents = tuple(exponents)
    functions = ([_break_states(exponents, P) for P in SIZES]
                 + [_sample_states(exponents, N) for N in SAMPLE_SIZES[:3]])
    if build:
        for f in functions:
            f.current(wait=True)


__all__ = ["PieceProof", "SAMPLE_SIZES", "SAMPLE_SUBSTEPS", "VERIFY_SUBSTEPS", "VERIFY_TOL",
           "break_states", "integrate_pieces", "prepare", "sample_states"]
