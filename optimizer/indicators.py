"""Quality indicators of a path (paper §4-5, NOTES §6).

* ``d_a`` (Definition 4): the largest distance between the path and the straight reference line
  from start to goal. The paper evaluates joint 1 only (``|th1(t) - line(t)|``); per joint and in
  joint space (perpendicular distance in R^n, eq 17) are offered too.
* ``t_p`` (Definition 5): the number of interior extreme points of ``th1(t)``, i.e. reversals of
  the actuator driving joint 1, with a small dead band.
* ``deviation``: the largest distance, in joint space ``(th_1..th_n)``, of the path from the
  straight SEGMENT between start and goal. Geometric: a driftless system's path does not change
  when it is retimed, and neither does this number. What the default objective ranks by.
* ``reversals``: direction changes of each actuator, ``phi`` and ``th_1``, counted with the
  dead band :data:`ACTUATOR_DEAD_BAND` (a motor does not reverse for a wiggle of 1e-4 rad).
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
#: Dead band of the actuator reversals of ``reversals`` (rad, 0.0057 deg).
ACTUATOR_DEAD_BAND = 1e-4


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
    deviation : float
        Largest distance (rad) in joint space of the path from the straight segment start ->
        goal.
    reversals_phi, reversals_th1 : int
        Direction changes of the actuators ``phi`` and ``th_1`` (dead band
        :data:`ACTUATOR_DEAD_BAND`).
    """

    d_a: float
    d_a_per_joint: tuple[float, ...]
    d_a_joint_space: float
    t_p: int
    phi_reversals: int
    sensitivity: float
    sensitivity_max: float
    energy: float
    deviation: float = 0.0
    reversals_phi: int = 0
    reversals_th1: int = 0

    @property
    def reversals(self) -> int:
        """Direction changes of both actuators together."""
        return self.reversals_phi + self.reversals_th1


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


def segment_distance(th: np.ndarray, a: np.ndarray | None = None,
                     b: np.ndarray | None = None) -> float:
    """Largest distance of the rows of ``th`` (N, n) from the segment ``a -> b`` (default: the
    first and last row), in the unit of ``th``."""
    th = np.asarray(th, float)
    a = th[0] if a is None else np.asarray(a, float)
    b = th[-1] if b is None else np.asarray(b, float)
    d = b - a
    rel = th - a
    nrm = float(d @ d)
    s = np.zeros(th.shape[0]) if nrm == 0.0 else np.clip((rel @ d) / nrm, 0.0, 1.0)
    off = rel - s[:, None] * d
    return float(np.sqrt(np.max(np.sum(off * off, axis=1))))


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


def count_reversals_columns(X: np.ndarray, dead_band: float = REVERSAL_DEAD_BAND) -> np.ndarray:
    """:func:`count_reversals` of every column of ``X`` (G, D), vectorised.

    Columns whose turning points are all farther apart than the dead band (the usual case)
    count their turning points; the others (zero steps, small wiggles) go through the scalar
    rule.
    """
    G, D = X.shape
    out = np.zeros(D, dtype=int)
    if D == 0 or G < 3:
        return out
    sg = np.sign(np.diff(X, axis=0))
    flat = (sg == 0.0).any(axis=0)
    turn = sg[1:] != sg[:-1]                      # (G-2, D): turning point at sample g + 1
    g, r = np.nonzero(turn)
    cnt = np.bincount(r, minlength=D)
    slow = flat.copy()
    if r.size:
        order = np.lexsort((g, r))                # by member, then time
        g, r = g[order], r[order]
        vals = X[g + 1, r]
        first = np.ones(r.size, bool)
        first[1:] = r[1:] != r[:-1]
        last = np.ones(r.size, bool)
        last[:-1] = r[:-1] != r[1:]
        small = np.zeros(D, bool)
        if r.size > 1:
            leg = np.abs(np.diff(vals))
            inner = ~first[1:]
            small[r[1:][inner & (leg <= dead_band)]] = True
        small[r[first][np.abs(vals[first] - X[0, r[first]]) <= dead_band]] = True
        small[r[last][np.abs(X[-1, r[last]] - vals[last]) <= dead_band]] = True
        slow |= small
    out[:] = cnt
    for i in np.nonzero(slow)[0]:
        out[i] = count_reversals(X[:, i], dead_band)
    return out


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
        deviation=segment_distance(th),
        reversals_phi=count_reversals(q[:, 0], ACTUATOR_DEAD_BAND),
        reversals_th1=count_reversals(th[:, 0], ACTUATOR_DEAD_BAND),
    )
