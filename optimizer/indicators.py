"""Quality indicators of a path (paper §4-5, NOTES §6).

* ``d_a`` (Definition 4): the largest distance between the path and the straight reference line
  from start to goal. The paper evaluates joint 1 only (``|th1(t) - line(t)|``); per joint and in
  joint space (perpendicular distance in R^n, eq 17) are offered too.
* ``t_p`` (Definition 5): the number of interior extreme points of ``th1(t)``, i.e. reversals of
  the actuator driving joint 1, with a small dead band.
* ``||J_R||_F`` (eq 18-23): ``J_R = blockdiag(1, D)``, ``D_ij = s^(i-j)/(i-j)!`` (i >= j) with
  ``s = z1(t) - z1(0)`` (``= b0 t`` for the paper's constant ``v1``; ``dz_{k+1}/ds = z_k``
  holds for any ``v1``, so the formula stays exact when ``v1`` varies).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Dead band of t_p: a reversal counts once the signal has come back by more than this (rad).
REVERSAL_DEAD_BAND = 1e-6


@dataclass(frozen=True)
class Indicators:
    """Indicators of one path (radians; ``sensitivity`` is dimensionless).

    Attributes
    ----------
    d_a : float
        Joint 1 (the paper's reading), rad.
    d_a_per_joint : tuple of float
        ``th_1..th_n``, rad.
    d_a_joint_space : float
        Perpendicular distance from the straight line in joint space (eq 17), rad.
    t_p : int
        Reversals of joint 1's actuator (interior extrema of ``th1``).
    phi_reversals : int
        Reversals of the horizontal actuator (interior extrema of ``phi``).
    sensitivity : float
        ``||J_R(T)||_F``.
    sensitivity_max : float
        ``max_t ||J_R(t)||_F``.
    energy : float
        ``integral of u1^2 + u2^2 dt`` (rad^2/s).
    """

    d_a: float
    d_a_per_joint: tuple[float, ...]
    d_a_joint_space: float
    t_p: int
    phi_reversals: int
    sensitivity: float
    sensitivity_max: float
    energy: float


def line_deviation(tau: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``x(tau) - (x(0) + tau (x(1) - x(0)))`` for samples on [0, 1]; x of shape (N,) or (N, k)."""
    x = np.asarray(x, float)
    tt = tau.reshape(-1, *([1] * (x.ndim - 1)))
    return x - (x[0] + tt * (x[-1] - x[0]))


def approximation_distance(tau: np.ndarray, th: np.ndarray) -> np.ndarray:
    """``d_a`` per column of ``th`` (Definition 4 read per joint), rad."""
    return np.max(np.abs(line_deviation(tau, th)), axis=0)


def joint_space_distance(th: np.ndarray) -> float:
    """Largest perpendicular distance (eq 17) from the samples ``th`` (N, n) to the line through
    the first and last sample."""
    a, b = th[0], th[-1]
    l1 = b - a
    l2 = th - a
    nrm = float(l1 @ l1)
    if nrm == 0.0:
        return float(np.max(np.linalg.norm(l2, axis=1)))
    d2 = np.sum(l2 * l2, axis=1) - (l2 @ l1) ** 2 / nrm
    return float(np.sqrt(np.max(np.maximum(d2, 0.0))))


def count_reversals(x: np.ndarray, dead_band: float = REVERSAL_DEAD_BAND) -> int:
    """Number of interior extrema of a sampled signal, with hysteresis ``dead_band``.

    A reversal is counted when the signal comes back from its running extreme by more than
    ``dead_band``; wiggles smaller than that (numerical noise, flat ends) do not count.
    """
    x = np.asarray(x, float)
    if x.size < 3:
        return 0
    # Between local extrema the signal is monotone, so the hysteresis below only needs the
    # turning points (found vectorised) and the ends.
    d = np.diff(x)
    nz = np.nonzero(d)[0]
    if nz.size == 0:
        return 0
    sg = np.sign(d[nz])
    turns = nz[1:][sg[1:] != sg[:-1]]
    x = np.concatenate([[x[0]], x[turns], [x[-1]]])
    direction = 0
    ext = x[0]
    count = 0
    for v in x[1:]:
        if direction >= 0 and v > ext:
            ext = v
            if direction == 0 and v - x[0] > dead_band:
                direction = 1
        elif direction <= 0 and v < ext:
            ext = v
            if direction == 0 and x[0] - v > dead_band:
                direction = -1
        if direction == 1 and ext - v > dead_band:
            count += 1
            direction, ext = -1, v
        elif direction == -1 and v - ext > dead_band:
            count += 1
            direction, ext = 1, v
    return count


def sensitivity_frobenius(s: np.ndarray | float, n: int) -> np.ndarray:
    """``||J_R||_F`` for ``s = z1(t) - z1(0)`` and n joints (eq 22).

    ``||J_R||_F^2 = 1 + sum_{k=0}^{n-1} (n - k) s^(2k) / (k!)^2``; for n = 3 this is
    ``(2 + s^2/2)^2``.
    """
    s = np.asarray(s, float)
    tot = np.ones_like(s)
    for k in range(n):
        tot = tot + (n - k) * s ** (2 * k) / math.factorial(k) ** 2
    return np.sqrt(tot)


def compute_indicators(t: np.ndarray, q: np.ndarray, u: np.ndarray | None) -> Indicators:
    """All indicators from samples of a path.

    Parameters
    ----------
    t : ndarray, shape (N,)
        Times (s), from 0 to T.
    q : ndarray, shape (N, n+1)
        ``[phi, th1..thn]`` at those times.
    u : ndarray, shape (N, 2), or None
        Actuator inputs at those times; None when the caller computes the energy otherwise
        (``energy`` is then NaN).
    """
    n = q.shape[1] - 1
    T = t[-1] - t[0]
    tau = (t - t[0]) / T
    th = q[:, 1:]
    # approximation_distance(tau, th), on the joints as contiguous rows (same operations)
    thT = np.ascontiguousarray(th.T)
    per = np.max(np.abs(thT - (thT[:, :1] + tau[None, :] * (thT[:, -1:] - thT[:, :1]))), axis=1)
    s = q[:, 0] - q[0, 0]
    sens = sensitivity_frobenius(s, n)
    energy = math.nan if u is None else float(np.trapezoid(np.sum(u * u, axis=1), t))
    return Indicators(
        d_a=float(per[0]),
        d_a_per_joint=tuple(float(x) for x in per),
        d_a_joint_space=joint_space_distance(th),
        t_p=count_reversals(th[:, 0]),
        phi_reversals=count_reversals(q[:, 0]),
        sensitivity=float(sens[-1]),
        sensitivity_max=float(np.max(sens)),
        energy=energy,
    )
