"""The time law of a continuation within the plan's rate limits.

A plan asked with ``max_u*``, ``max_du*`` (and ``max_ddu*``) runs its path within them
(:mod:`optimizer.timing`); its answer says which (``time_law.limits``), and a continuation of
it (:mod:`.replan`) keeps to the same bounds: a drive that cannot follow the plan's
accelerations cannot follow a continuation's either.

A continuation's corrected pieces run rest to rest, piece ``k`` with constant geometric rates
``g_k`` (rad per unit of plan time ``sigma``) over ``L_k`` of plan time. Its actuator rates
are ``u = g_k sigma'``, ``u' = g_k sigma''``, ``u'' = g_k sigma'''``, so the bounds on ``u``
are bounds on ``sigma'``: ``V_k = min_i max_u_i / |g_ki|`` (``A_k``, ``J_k`` alike), and the
fastest rest-to-rest law of the piece is :func:`optimizer.timing.rest_to_rest` (trapezoid, or
S-curve under a jerk bound) of duration ``D_min_k``. Stretching it to ``D >= D_min_k``
divides ``u`` by ``D / D_min_k``, ``u'`` by its square and ``u''`` by its cube: every bound
stays met.

:func:`law_within_limits` gives each piece ``max(c D_k, D_min_k)``, ``D_k`` the duration the
unlimited law gives it (equal shares, or shares in proportion to plan time) and ``c <= 1``
the largest factor with which the pieces still end at ``T_end``; where even the shortest
durations do not fit, the continuation ends later than ``T_end`` (as late as the bounds
need). :func:`braking_time` is the shortest constant-rate braking of the motion under way.
:func:`measured_limits` measures what an answer hands out.
"""

from __future__ import annotations

import math

import numpy as np

from ..timing import Limits, rest_to_rest
from .plan_state import TimeLaw, law_after_stop

#: The laws are planned for the bounds times ``1 - LIMIT_MARGIN`` (as the planner's,
#: :func:`optimizer.timing.time_law`): the handed-out samples are rounded, not the bounds.
LIMIT_MARGIN = 1e-3
#: Points per phase at which :func:`measured_limits` evaluates the rates.
MEASURE_POINTS = 9


def piece_bounds(rates: np.ndarray, limits: Limits) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per piece the bounds on ``sigma'``, ``sigma''``, ``sigma'''`` that the actuators'
    bounds give under geometric rates ``rates`` ``(M, 2)`` (``inf`` where none binds)."""
    g = np.abs(np.asarray(rates, float))
    out = []
    for bound in limits.scaled(1.0 - LIMIT_MARGIN).arrays():
        with np.errstate(divide="ignore", invalid="ignore"):
            per = np.where(g > 0.0, bound[None, :] / np.where(g > 0.0, g, 1.0), math.inf)
        out.append(per.min(axis=1))
    return out[0], out[1], out[2]


def law_within_limits(t_stop: float, T_end: float, breaks: np.ndarray, rates: np.ndarray,
                      limits: Limits, equal: bool = False) -> np.ndarray:
    """Rows (:class:`~.plan_state.TimeLaw`'s) of the pieces ``breaks, rates`` run rest to
    rest from ``t_stop`` within ``limits``: by ``T_end`` where the bounds allow it, else as
    early as they do (see the module). Without bounds: :func:`~.plan_state.law_after_stop`."""
    if not limits.any:
        return law_after_stop(t_stop, T_end, breaks, equal)
    breaks = np.asarray(breaks, float)
    L = breaks[1:] - breaks[:-1]
    R = T_end - t_stop
    V, A, J = piece_bounds(rates, limits)
    fastest = [rest_to_rest(float(ell), float(v), float(a), float(j))
               for ell, v, a, j in zip(L, V, A, J)]
    D_min = np.array([0.0 if p is None else p.duration for p in fastest])
    share = np.full(L.size, 1.0 / L.size) if equal else L / L.sum()
    # (a piece on which no bound binds has no shortest duration: it keeps its share of the
    # time, of the bounded pieces' time where that is longer than what is left)
    base = max(R, float(D_min.sum()), 1e-3)
    D = _durations(base * share, D_min, R)
    rows = []
    t0 = t_stop
    for ell, d, p, s0 in zip(L, D, fastest, breaks[:-1]):
        if p is None:       # (no bound binds this piece: the default law's shape)
            rows.append(law_after_stop(t0, t0 + d, np.array([s0, s0 + ell])))
        else:
            q = p.stretched(d / p.duration)
            rows.append(np.column_stack([t0 + q.start, q.length, s0 + q.x0, q.v0, q.a0,
                                         q.jerk]))
        t0 += d
    return np.vstack(rows)


def _durations(default: np.ndarray, shortest: np.ndarray, total: float) -> np.ndarray:
    """``max(c default, shortest)`` with the largest ``c <= 1`` whose sum is at most
    ``total``; ``shortest`` itself where its sum exceeds ``total`` (``default`` where that is
    0: no bound binds the piece)."""
    if shortest.sum() >= total:
        return np.where(shortest > 0.0, shortest, default)
    if np.all(default >= shortest):
        return default.copy()
    lo, hi = 0.0, 1.0           # the sum is increasing in c; at c = 1 above total
    for _ in range(60):
        c = 0.5 * (lo + hi)
        if np.maximum(c * default, shortest).sum() > total:
            hi = c
        else:
            lo = c
    D = np.maximum(lo * default, shortest)
    D[-1] += max(total - D.sum(), 0.0)      # the law ends at total exactly
    return D


def braking_time(speed: float, direction: np.ndarray, limits: Limits) -> float:
    """The shortest time in which ``sigma'`` falls linearly from ``speed`` to 0 under the
    acceleration bounds (rates ``direction * sigma'``); 0 without them."""
    _, A, _ = piece_bounds(np.asarray(direction, float)[None, :], limits)
    return 0.0 if not math.isfinite(float(A[0])) else speed / float(A[0])


def _phase_rates(law: TimeLaw, breaks: np.ndarray, rates: np.ndarray) -> np.ndarray:
    """``(phases, 2)``: the geometric rates of the piece each phase of ``law`` runs (a phase
    lies within one piece: the one that holds its middle)."""
    P = law.phases
    mid = law.evaluate(P[:, 0] + 0.5 * P[:, 1])[0]
    k = np.minimum(np.maximum(np.searchsorted(breaks, mid, side="right") - 1, 0),
                   rates.shape[0] - 1)
    return np.asarray(rates, float)[k]


def measured_limits(law: TimeLaw, breaks: np.ndarray, rates: np.ndarray
                    ) -> dict[str, float]:
    """The largest ``|u_i|``, ``|u_i'|``, ``|u_i''|`` of the rates ``rates[piece(sigma(t))]
    sigma'(t)`` along ``law``, named as the limits are: each phase's own cubic at
    :data:`MEASURE_POINTS` points of it."""
    P = law.phases
    if P.shape[0] == 0:
        return {}
    r = P[:, 1, None] * np.linspace(0.0, 1.0, MEASURE_POINTS)[None, :]
    v0, a0, j = P[:, 3, None], P[:, 4, None], P[:, 5, None]
    ds = v0 + r * (a0 + 0.5 * j * r)
    dds = a0 + j * r
    ddds = np.broadcast_to(j, r.shape)
    g = np.abs(_phase_rates(law, breaks, rates))
    peaks = [(g * np.abs(x).max(axis=1)[:, None]).max(axis=0) for x in (ds, dds, ddds)]
    return {name: float(value) for names, values in zip(Limits.NAMES, peaks)
            for name, value in zip(names, values)}


def slope_jump(law: TimeLaw, breaks: np.ndarray, rates: np.ndarray) -> float:
    """The largest jump of ``|u_i'|`` from one phase of ``law`` to the next (rad/s^2): 0
    where the rates' slopes are continuous, as a jerk bound needs them."""
    P = law.phases
    if P.shape[0] < 2:
        return 0.0
    g = _phase_rates(law, breaks, rates)
    end = g[:-1] * (P[:-1, 4] + P[:-1, 5] * P[:-1, 1])[:, None]
    start = g[1:] * P[1:, 4, None]
    return float(np.abs(start - end).max())


__all__ = ["LIMIT_MARGIN", "braking_time", "law_within_limits", "measured_limits",
           "piece_bounds", "slope_jump"]
