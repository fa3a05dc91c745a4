"""Batched helpers on many polynomials at once, for the region's continuous-path check: their
derivatives and real roots (closed forms to degree 2, batched companion eigenvalues above), the
vertex of a parabola through three points, and a bracketed root (Brent).
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np
from scipy.optimize import brentq


@functools.lru_cache(maxsize=32)
def unit_grid(points: int) -> np.ndarray:
    g = np.linspace(0.0, 1.0, points)
    g.flags.writeable = False
    return g


def parabola_vertex(x0: np.ndarray, x1: np.ndarray, x2: np.ndarray, f0: np.ndarray, f1: np.ndarray,
            f2: np.ndarray) -> np.ndarray:
    """Vertex of the parabola through three points per row, kept inside [x0, x2]."""
    with np.errstate(all="ignore"):
        d10, d12 = x1 - x0, x1 - x2
        g12, g10 = f1 - f2, f1 - f0
        xv = x1 - 0.5 * (d10 * d10 * g12 - d12 * d12 * g10) / (d10 * g12 - d12 * g10)
    # (np.minimum/np.maximum: np.clip's Python wrapper costs more than the work here)
    return np.minimum(np.maximum(np.where(np.isfinite(xv), xv, x1), x0), x2)



def polyder_rows(c: np.ndarray) -> np.ndarray:
    """Derivative of row-wise polynomials (R, L), padded back to L coefficients."""
    out = np.zeros_like(c)
    out[:, :-1] = c[:, 1:] * np.arange(1, c.shape[1])
    return out


def real_roots_rows(Pm: np.ndarray) -> np.ndarray:
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


def bracket_root(f: Callable[[float], float], a: float, b: float) -> float:
    """The boundary crossing in [a, b] where f(a) > 0 >= f(b) (Brent; bisection if f is flat)."""
    fa, fb = f(a), f(b)
    if fa <= 0.0:
        return a
    if fb == 0.0:
        return b
    if fb > 0.0:
        return b
    return float(brentq(f, a, b, xtol=1e-13, maxiter=200))
