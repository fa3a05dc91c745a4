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


def _distances(thT: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest distances of the columns of ``thT`` (n, N) from the LINE through ``a`` and ``b``
    and from the SEGMENT ``a -> b``: ``(line, segment)``.

    With ``rel = th - a``, ``d = b - a``, ``p = rel . d`` and ``s = clip(p / |d|^2, 0, 1)``:
    the squared distances are ``|rel|^2 - p^2 / |d|^2`` and ``|rel - s d|^2 = |rel|^2 -
    s (2 p - s |d|^2)``. Joints as rows: the sums over joints are adds of whole rows.
    """
    d = b - a
    rel = thT - a[:, None]
    sq = np.einsum("ij,ij->j", rel, rel)
    nrm = float(d @ d)
    if nrm == 0.0:
        r = math.sqrt(float(sq.max()))
        return r, r
    proj = d @ rel
    line2 = sq - proj * proj / nrm
    s = np.minimum(np.maximum(proj / nrm, 0.0), 1.0)   # (np.clip: 2-3 us more a call)
    seg2 = sq - s * (2.0 * proj - s * nrm)
    # (the arrays' own max: np.max's dispatch costs about a microsecond a call)
    return (math.sqrt(max(float(line2.max()), 0.0)),
            math.sqrt(max(float(seg2.max()), 0.0)))


def joint_space_distance(th: np.ndarray) -> float:
    """Largest perpendicular distance (eq 17) from the samples ``th`` (N, n) to the line through
    the first and last sample."""
    thT = np.ascontiguousarray(np.asarray(th, float).T)
    return _distances(thT, thT[:, 0], thT[:, -1])[0]


def segment_distance(th: np.ndarray, a: np.ndarray | None = None,
                     b: np.ndarray | None = None) -> float:
    """Largest distance of the rows of ``th`` (N, n) from the segment ``a -> b`` (default: the
    first and last row), in the unit of ``th``."""
    thT = np.ascontiguousarray(np.asarray(th, float).T)
    a = thT[:, 0] if a is None else np.asarray(a, float)
    b = thT[:, -1] if b is None else np.asarray(b, float)
    return _distances(thT, a, b)[1]


def count_reversals(x: np.ndarray, dead_band: float = REVERSAL_DEAD_BAND) -> int:
    """Number of interior extrema of a sampled signal, with hysteresis ``dead_band``.

    A reversal is counted when the signal comes back from its running extreme by more than
    ``dead_band``; wiggles smaller than that (numerical noise, flat ends) do not count.
    """
    return _hysteresis_count(_turning_values(x), dead_band)


def _turning_values(x: np.ndarray) -> np.ndarray:
    """The first value of ``x``, its values at its turning points and its last value: between
    local extrema the signal is monotone, so the hysteresis needs these only."""
    x = np.asarray(x, float)
    if x.size < 3:
        return x[:0]
    d = x[1:] - x[:-1]
    nz = np.nonzero(d)[0]
    if nz.size == 0:
        return x[:0]
    sg = np.sign(d[nz])
    turns = nz[1:][sg[1:] != sg[:-1]]
    return np.concatenate([x[:1], x[turns], x[-1:]])


def _hysteresis_count(values: np.ndarray, dead_band: float) -> int:
    """:func:`count_reversals` of the values :func:`_turning_values` kept."""
    if values.size == 0:
        return 0
    x = values.tolist()
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


def _frobenius(s: float, n: int) -> float:
    """:func:`sensitivity_frobenius` of one value, in floats (the same operations)."""
    tot = 1.0
    for k in range(n):
        tot = tot + (n - k) * s ** (2 * k) / math.factorial(k) ** 2
    return math.sqrt(tot)


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
    # the joints as contiguous rows: the per-joint operations run on whole rows
    thT = np.ascontiguousarray(q[:, 1:].T)
    # approximation_distance(tau, th) (same operations)
    per = np.abs(thT - (thT[:, :1] + tau[None, :] * (thT[:, -1:] - thT[:, :1]))).max(axis=1)
    line, segment = _distances(thT, thT[:, 0], thT[:, -1])
    # ||J_R||_F grows with s^2 (every term of its square is a positive multiple of a power
    # of s^2): its largest value over the samples is at the largest |s|
    s = q[:, 0] - q[0, 0]
    sens = [_frobenius(float(x), n) for x in (s[-1], np.abs(s).max())]
    if u is None:
        energy = math.nan
    else:   # np.trapezoid's operations, without its dispatch (a third of this function)
        e = np.einsum("ij,ij->i", u, u)
        energy = float(((t[1:] - t[:-1]) * (e[1:] + e[:-1]) / 2.0).sum())
    turns_th1, turns_phi = _turning_values(thT[0]), _turning_values(q[:, 0])
    return Indicators(
        d_a=float(per[0]),
        d_a_per_joint=tuple(float(x) for x in per),
        d_a_joint_space=line,
        t_p=_hysteresis_count(turns_th1, REVERSAL_DEAD_BAND),
        phi_reversals=_hysteresis_count(turns_phi, REVERSAL_DEAD_BAND),
        sensitivity=float(sens[0]),
        sensitivity_max=float(max(sens[0], sens[1])),
        energy=energy,
        deviation=segment,
        reversals_phi=_hysteresis_count(turns_phi, ACTUATOR_DEAD_BAND),
        reversals_th1=_hysteresis_count(turns_th1, ACTUATOR_DEAD_BAND),
    )
