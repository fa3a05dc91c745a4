"""Time laws: a plan's geometric path run from rest to rest, with continuous rates, in limits.

The model has no drift, ``q' = G(q) u``: running a path ``q(sigma)`` along any monotone time law
``sigma(t)`` with the rates ``u(t) = u_plan(sigma(t)) sigma'(t)`` passes through exactly the
same states, so every geometric property of a plan (its region margin, its reversals, its
deviation from the straight segment) is kept, and only the rates change.

The geometric parameter ``lam``
-------------------------------
A plan's rates ``u_plan`` (on its own time ``sigma``) may jump at the breaks of its pieces. At a
break where the rate vectors before and after are positively parallel (only the speed
changes: the retimed method's pieces) the jump is removed by a piecewise-linear change of
parameter ``sigma = sigma_k + c_k (lam - lam_k)``: with ``c_k / c_{k-1} = |u_-| / |u_+|`` the
rates per unit ``lam``, ``g(lam) = c_k u_plan(sigma)``, are continuous there. Where the
direction changes (the shooting plans' piecewise-constant rates) no time law can keep the
rates continuous unless it stops: ``lam' = 0`` there (a **stop**), and at ``t = 0`` and
``t = T``. Between two stops lies a **segment**.

The law on a segment
--------------------
``lam(t)`` is a sequence of phases of constant jerk (a cubic in ``t`` on each), exact and
cheap to evaluate (:class:`Phases`). On a segment of length ``L`` (in ``lam``):

* without limits: the plan's own timing (scaled to ``T``) at every knot, with linear ramps
  of the speed over the first and last quarter of every knot piece (:func:`_plan_timed`):
  from and to rest at the stops, through the smaller of the two pieces' speeds at a knot
  where only the speed changes. A segment of one piece: constant acceleration for a
  quarter of its duration ``D``, cruise, constant braking for a quarter
  (:func:`ramp_profile`; speed ``4 L / (3 D)``). Constraint-point times stay exact. For a
  constant direction the rates are piecewise linear: the linear form holds them exactly;
* with limits on ``|u_i|``, ``|u_i'|`` (and ``|u_i''|``) and a constant direction ``g``
  (piecewise-constant plans): ``|u_i| = |g_i| lam'`` and so on, so the segment is the 1-D
  time-optimal rest-to-rest problem with ``V = min_i max_u_i / |g_i|``, ``A`` and ``J`` alike:
  the trapezoid (:func:`trapezoid_profile`) or, with a jerk limit, the 7-phase S-curve
  (:func:`scurve_profile`), in closed form. With ``max_u`` alone (no acceleration limit there
  is no fastest law with continuous rates) the ramp law cruising at ``V``;
* with limits on a segment whose direction varies (the paper's polynomial paths): the
  time-optimal law of ``b = lam'^2``, a convex program (:func:`topp_segment`); under a jerk
  limit (not convex in ``b``), or should the program fail, a law of fixed shape (the ramp
  law's, or the smooth law's of jerk ``+J, -J, -J, +J``, :func:`smooth_profile`, under a
  jerk limit), of the shortest duration meeting every limit on a dense grid: for a fixed shape
  ``u = a(s) / D``, ``u' = a'(s) / D^2``, ``u'' = a''(s) / D^3`` (``s = t / D``), so each limit
  gives its ``D`` in closed form from the grid's maxima (not time-optimal: said so in the docs).

A requested duration longer than the shortest one stretches every phase by their ratio (a
stretch by ``f >= 1`` divides rates by ``f``, their derivatives by ``f^2`` and ``f^3``: every
limit stays met); a shorter one is refused, naming the limit and the shortest duration.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Sequence

import numpy as np

from .errors import InfeasibleError

RatesOf = Callable[[np.ndarray], np.ndarray]

#: Two rate vectors whose sine of angle is below this are parallel (no stop between them).
PARALLEL_TOLERANCE = 1e-6
#: Points of the dense grid on which a varying segment's limits are measured.
LIMIT_GRID = 1025


# ---------------------------------------------------------------------- limits
@dataclass(frozen=True)
class Limits:
    """Bounds of the actuator rates ``|u_i|`` (rad/s), their derivatives ``|u_i'|`` (rad/s^2)
    and second derivatives ``|u_i''|`` (rad/s^3), per actuator; ``None``: no bound."""

    rate: tuple[float | None, float | None] = (None, None)
    accel: tuple[float | None, float | None] = (None, None)
    jerk: tuple[float | None, float | None] = (None, None)

    NAMES: ClassVar[tuple[tuple[str, str], ...]] = (
        ("max_u1", "max_u2"), ("max_du1", "max_du2"), ("max_ddu1", "max_ddu2"))

    @property
    def any(self) -> bool:
        return any(x is not None for x in self.rate + self.accel + self.jerk)

    @property
    def jerk_bounded(self) -> bool:
        return any(x is not None for x in self.jerk)

    def as_dict(self) -> dict[str, float]:
        """The bounds that are set, by their request names (``max_u1``, ...)."""
        return {name: float(value) for names, values in zip(
            self.NAMES, (self.rate, self.accel, self.jerk))
            for name, value in zip(names, values) if value is not None}

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The three bounds as arrays (2,), ``inf`` where there is none."""
        def arr(v: tuple[float | None, float | None]) -> np.ndarray:
            return np.array([math.inf if x is None else float(x) for x in v])
        return arr(self.rate), arr(self.accel), arr(self.jerk)

    def scaled(self, f: float) -> "Limits":
        """Every bound times ``f`` (the time law plans a little inside them)."""
        def sc(v: tuple[float | None, float | None]) -> tuple[float | None, float | None]:
            a, b = v
            return (None if a is None else a * f, None if b is None else b * f)
        return Limits(sc(self.rate), sc(self.accel), sc(self.jerk))

    def value(self, name: str) -> float | None:
        for order, names in enumerate(self.NAMES):
            if name in names:
                return (self.rate, self.accel, self.jerk)[order][names.index(name)]
        raise KeyError(name)


# ---------------------------------------------------------------------- phases
@dataclass(frozen=True)
class Phases:
    """A law ``x(t)`` made of phases of constant jerk: on phase ``k`` (``start[k] <= t <=
    start[k] + length[k]``, ``r = t - start[k]``) ``x = x0 + v0 r + a0 r^2 / 2 + jerk r^3 / 6``.
    The acceleration may jump between phases (a trapezoid), the speed does not."""

    start: np.ndarray
    length: np.ndarray
    x0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray
    jerk: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.start[-1] + self.length[-1]) if self.start.size else 0.0

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``x, x', x'', x'''`` at times ``t`` (right-continuous at the phases' ends)."""
        t = np.atleast_1d(np.asarray(t, float))
        k = np.clip(np.searchsorted(self.start, t, side="right") - 1, 0, self.start.size - 1)
        r = np.clip(t - self.start[k], 0.0, self.length[k])
        j, a, v = self.jerk[k], self.a0[k], self.v0[k]
        x = self.x0[k] + r * (v + r * (a / 2.0 + r * j / 6.0))
        return x, v + r * (a + r * j / 2.0), a + r * j, j.copy()

    def stretched(self, f: float) -> "Phases":
        """``x(t / f)``: the same positions, ``f`` times slower."""
        return Phases(self.start * f, self.length * f, self.x0, self.v0 / f, self.a0 / f ** 2,
                      self.jerk / f ** 3)

    @property
    def end(self) -> float:
        """``x`` at the end of the last phase."""
        if not self.start.size:
            return 0.0
        h = float(self.length[-1])
        return float(self.x0[-1] + h * (self.v0[-1] + h * (self.a0[-1] / 2.0
                                                           + h * self.jerk[-1] / 6.0)))

    @staticmethod
    def concatenate(parts: Sequence["Phases"], origins: np.ndarray | None = None) -> "Phases":
        """Consecutive laws end to end: each part's times shifted to start where the previous
        one ended, and its positions to start at ``origins[k]`` (default: where the previous
        one ended)."""
        lengths = np.array([p.duration for p in parts])
        t0 = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        if origins is None:
            origins = np.concatenate([[0.0], np.cumsum([p.end for p in parts])[:-1]])
        sizes = [p.start.size for p in parts]
        rep = np.repeat(np.arange(len(parts)), sizes)
        cat = [np.concatenate([getattr(p, f) for p in parts])
               for f in ("start", "length", "x0", "v0", "a0", "jerk")]
        return Phases(cat[0] + t0[rep], cat[1], cat[2] + origins[rep], cat[3], cat[4], cat[5])


def phases_from(pieces: Sequence[tuple[float, float, float]]) -> Phases:
    """A law from rest at 0: ``pieces`` of ``(length, acceleration at its start, jerk)``; the
    positions and speeds are integrated exactly; pieces of zero length are dropped."""
    pieces = [p for p in pieces if p[0] > 0.0]
    P = len(pieces)
    start, length, x0, v0, a0, jerk = (np.zeros(P) for _ in range(6))
    t = x = v = 0.0
    for k, (h, a, j) in enumerate(pieces):
        start[k], length[k], x0[k], v0[k], a0[k], jerk[k] = t, h, x, v, a, j
        x += h * (v + h * (a / 2.0 + h * j / 6.0))
        v += h * (a + h * j / 2.0)
        t += h
    return Phases(start, length, x0, v0, a0, jerk)


# ---------------------------------------------------------------------- rest-to-rest profiles
def smooth_profile(L: float, D: float) -> Phases:
    """The smooth rest-to-rest law over distance ``L`` in time ``D``: jerk ``+J, -J, -J, +J``
    for ``D / 4`` each, ``J = 32 L / D^3``; speed peak ``2 L / D`` at ``D / 2``, acceleration
    peak ``8 L / D^2`` at ``D / 4``, continuous acceleration."""
    J = 32.0 * L / D ** 3
    q = D / 4.0
    return phases_from([(q, 0.0, J), (q, J * q, -J), (q, 0.0, -J), (q, -J * q, J)])


#: The smooth profile's peaks per unit distance and duration: speed, acceleration, jerk.
SMOOTH_PEAKS = (2.0, 8.0, 32.0)
#: The default law's ramps: each takes this fraction of the segment's duration.
RAMP = 0.25


def ramp_profile(L: float, D: float, ramp: float = RAMP) -> Phases:
    """The default rest-to-rest law over distance ``L`` in time ``D``: constant acceleration
    for ``ramp D``, cruise at ``L / ((1 - ramp) D)``, constant braking for ``ramp D``. Its
    speed is piecewise linear, so rates of a constant direction are too: the linear form holds
    them exactly with samples at the ramps' ends."""
    v = L / ((1.0 - ramp) * D)
    A = v / (ramp * D)
    return phases_from([(ramp * D, A, 0.0), ((1.0 - 2.0 * ramp) * D, 0.0, 0.0),
                        (ramp * D, -A, 0.0)])


def trapezoid_profile(L: float, V: float, A: float) -> Phases:
    """The time-optimal rest-to-rest law under ``|x'| <= V``, ``|x''| <= A`` (``V`` may be
    ``inf``): accelerate at ``A``, cruise at ``V`` if it is reached, brake at ``A``. Duration
    ``L / V + V / A`` when ``L >= V^2 / A``, else ``2 sqrt(L / A)``."""
    if L * A >= V * V:
        ta, tv = V / A, L / V - V / A
    else:
        ta, tv = math.sqrt(L / A), 0.0
    return phases_from([(ta, A, 0.0), (tv, 0.0, 0.0), (ta, -A, 0.0)])


def _accel_phase(v: float, A: float, J: float) -> tuple[float, float]:
    """The jerk-limited rise from rest to speed ``v``: ``(Tj, Tc)``, the times at jerk ``J``
    (twice) and at acceleration ``A`` (once)."""
    if v * J >= A * A:           # A is reached (never when A is inf)
        return A / J, v / A - A / J
    return math.sqrt(v / J), 0.0


def scurve_profile(L: float, V: float, A: float, J: float) -> Phases:
    """The time-optimal rest-to-rest law under ``|x'| <= V``, ``|x''| <= A``, ``|x'''| <= J``
    (``V``, ``A`` may be ``inf``): the 7-phase S-curve. The peak speed is ``V`` when the
    distance allows it, else the speed whose symmetric rise and fall cover ``L`` exactly
    (closed forms: ``v^2 / A + v A / J = L`` when ``A`` is reached, ``2 v sqrt(v / J) = L``
    when it is not)."""
    def rise_distance(v: float) -> float:      # rise to v and fall back: distance covered
        tj, tc = _accel_phase(v, A, J)
        return v * (2.0 * tj + tc)

    if math.isfinite(V) and rise_distance(V) <= L:
        v = V
    else:
        v = (L * L * J / 4.0) ** (1.0 / 3.0)   # A not reached
        if math.isfinite(A) and v * J > A * A:
            v = 0.5 * A * (-A / J + math.sqrt((A / J) ** 2 + 4.0 * L / A))
    tj, tc = _accel_phase(v, A, J)
    a = J * tj
    tv = max(L - rise_distance(v), 0.0) / v
    return phases_from([(tj, 0.0, J), (tc, a, 0.0), (tj, a, -J), (tv, 0.0, 0.0),
                        (tj, 0.0, -J), (tc, -a, 0.0), (tj, -a, J)])


def rest_to_rest(L: float, V: float, A: float, J: float) -> Phases | None:
    """The fastest rest-to-rest law of the families above within ``V, A, J`` (``inf``: no
    bound); ``None`` when nothing bounds it."""
    if math.isfinite(J):
        return scurve_profile(L, V, A, J)
    if math.isfinite(A):
        return trapezoid_profile(L, V, A)
    if math.isfinite(V):
        return ramp_profile(L, L / ((1.0 - RAMP) * V))
    return None


# ---------------------------------------------------------------------- the geometric path
@dataclass(frozen=True)
class GeometricPath:
    """A plan's path on the parameter ``lam``: ``sigma = sigma[k] + slope[k] (lam - lam[k])``
    on piece ``k``, rates per unit ``lam`` ``g(lam) = slope[k] u_plan(sigma)``.

    Attributes
    ----------
    sigma, lam : ndarray (K+1,)
        The pieces' ends in plan time (s) and in ``lam``.
    slope : ndarray (K,)
    stop : ndarray (K+1,) of bool
        Where the rates must be zero (the ends, direction changes, constraint-point times).
    rates : callable
        ``u_plan``: plan times (M,) -> (M, 2).
    constant : bool
        ``u_plan`` is constant on each piece.
    piece_rates : ndarray (K, 2) or None
        With ``constant``: ``u_plan`` on each piece (read at its middle).
    """

    sigma: np.ndarray
    lam: np.ndarray
    slope: np.ndarray
    stop: np.ndarray
    rates: RatesOf
    constant: bool
    piece_rates: np.ndarray | None = None

    def piece(self, lam: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.lam, lam, side="right") - 1, 0, self.slope.size - 1)

    def sigma_of(self, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Plan time and ``d sigma / d lam`` at ``lam``."""
        lam = np.atleast_1d(np.asarray(lam, float))
        k = self.piece(lam)
        return self.sigma[k] + self.slope[k] * (lam - self.lam[k]), self.slope[k]

    def g(self, lam: np.ndarray) -> np.ndarray:
        """Rates per unit ``lam``, shape (M, 2): piece ``k``'s plan rates times its slope."""
        lam = np.atleast_1d(np.asarray(lam, float))
        k = self.piece(lam)
        # piece k's own rates: a lam within rounding of a knot maps to a plan time on the
        # break or past it, where the rates are the next piece's. Where the knot is no stop
        # (parallel pieces of different speeds, the slopes making g continuous) those rates
        # times this piece's slope were a spike in g: a sample on it put the spike into a
        # linear form that was taken to hold the plan's rates (a 4-joint front's plan handed
        # out a path 6e-4 rad off its goal, its check 2e-12)
        if self.piece_rates is not None:
            return self.piece_rates[k] * self.slope[k][:, None]
        s = self.sigma[k] + self.slope[k] * (lam - self.lam[k])
        s = np.minimum(np.maximum(s, self.sigma[k]), np.nextafter(self.sigma[k + 1], -np.inf))
        return np.asarray(self.rates(s), float) * self.slope[k][:, None]

    @property
    def segments(self) -> np.ndarray:
        """Indices of the stop knots (first 0, last K)."""
        return np.nonzero(self.stop)[0]


def geometric_path(rates: RatesOf, breaks: np.ndarray, *, constant: bool,
                   stops: Sequence[float] = ()) -> GeometricPath:
    """The parameter ``lam`` of a plan whose rates ``rates`` (on plan time) may jump at
    ``breaks`` (``[0, ..., T0]``); ``stops``: more plan times where the rates must be zero."""
    b = np.asarray(breaks, float)
    extra = np.asarray([x for x in stops if b[0] < x < b[-1]], float)
    sig = np.unique(np.concatenate([b, extra]))
    K = sig.size - 1
    h = np.diff(sig)
    mid = None
    if constant:
        mid = np.array(rates(0.5 * (sig[:-1] + sig[1:])), dtype=float)   # (a copy: frozen)
        mid.setflags(write=False)
        left, right = mid[:-1], mid[1:]         # before and after each inner knot
    else:
        eps = 1e-9 * np.minimum(h[:-1], h[1:])
        left = np.asarray(rates(sig[1:-1] - eps), float)
        right = np.asarray(rates(sig[1:-1] + eps), float)
    nl, nr = np.linalg.norm(left, axis=1), np.linalg.norm(right, axis=1)
    cross = np.abs(left[:, 0] * right[:, 1] - left[:, 1] * right[:, 0])
    dot = np.sum(left * right, axis=1)
    parallel = (nl > 0) & (nr > 0) & (dot > 0) & (cross <= PARALLEL_TOLERANCE * nl * nr)
    stop = np.ones(K + 1, bool)
    stop[1:-1] = ~parallel
    if extra.size:
        stop[np.searchsorted(sig, extra)] = True
    slope = np.ones(K)
    for k in range(1, K):
        if not stop[k]:
            slope[k] = slope[k - 1] * nl[k - 1] / nr[k - 1]
    lam = np.concatenate([[0.0], np.cumsum(h / slope)])
    return GeometricPath(sig, lam, slope, stop, rates, constant, mid)


# ---------------------------------------------------------------------- the time law
@dataclass(frozen=True)
class TimeLaw:
    """``lam(t)`` over ``[0, T]`` along a :class:`GeometricPath`: the handed-out rates are
    ``u(t) = g(lam(t)) lam'(t)``.

    Attributes
    ----------
    path : GeometricPath
    phases : Phases
        ``lam(t)``.
    stops : ndarray
        Times (s) where ``lam' = 0`` (the rates are zero): ``0``, the inner stops, ``T``.
    shortest : float or None
        The shortest duration within the limits along this path (None without limits).
    binding : str or None
        The request field of the limit that set ``shortest``.
    limits : Limits
        The limits the law keeps.
    """

    path: GeometricPath
    phases: Phases
    stops: np.ndarray
    shortest: float | None = None
    binding: str | None = None
    limits: Limits = field(default_factory=Limits)

    @property
    def T(self) -> float:
        return float(self.stops[-1])

    @property
    def piecewise_linear(self) -> bool:
        """Whether the rates are linear between the phases' starts (constant directions and
        no jerk phase): the linear form with samples there holds them exactly."""
        return self.path.constant and not np.any(self.phases.jerk)

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``lam, lam', lam'', lam'''`` at ``t``."""
        return self.phases.evaluate(t)

    def rates(self, t: np.ndarray) -> np.ndarray:
        """``u(t)``, shape (M, 2)."""
        lam, dlam, _, _ = self.evaluate(t)
        return self.path.g(lam) * dlam[:, None]

    def rates_and_derivative(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``u(t)`` and ``u'(t) = g'(lam) lam'^2 + g(lam) lam''`` (``g'`` by a central
        difference inside the piece of ``lam``: exact for a constant piece)."""
        lam, dlam, ddlam, _ = self.evaluate(t)
        g = self.path.g(lam)
        k = self.path.piece(lam)
        h = 1e-6 * (self.path.lam[k + 1] - self.path.lam[k])
        lo = np.maximum(lam - h, self.path.lam[k])
        hi = np.minimum(lam + h, self.path.lam[k + 1] * (1 - 1e-15))
        gd = (self.path.g(hi) - self.path.g(lo)) / np.maximum(hi - lo, 1e-300)[:, None]
        return g * dlam[:, None], gd * (dlam ** 2)[:, None] + g * ddlam[:, None]

    def plan_time(self, t: np.ndarray) -> np.ndarray:
        """``sigma(t)``: where on the plan's own schedule the path is at ``t``."""
        return self.path.sigma_of(self.evaluate(t)[0])[0]

    def as_dict(self) -> dict[str, Any]:
        """The JSON shape of ``time_law`` in an answer."""
        p = self.phases
        return {
            "rule": "u(t) = u_plan(sigma) * dsigma/dlam * lam'(t); on phase k, with "
                    "r = t - start: lam = lam0 + v0 r + a0 r^2/2 + jerk r^3/6; "
                    "sigma = sigma_k + slope_k (lam - lam_k) on the knots' piece k",
            "plan_duration": float(self.path.sigma[-1]),
            "stops": self.stops,
            "knots": {"lam": self.path.lam, "sigma": self.path.sigma,
                      "slope": self.path.slope},
            "phases": {"start": p.start, "length": p.length, "lam0": p.x0, "v0": p.v0,
                       "a0": p.a0, "jerk": p.jerk},
            "shortest_duration": self.shortest,
            "binding_limit": self.binding,
            "limits": self.limits.as_dict(),
        }


def _shape_need(path: GeometricPath, lam0: float, L: float,
                bounds: tuple[np.ndarray, np.ndarray, np.ndarray],
                shape: Callable[[float, float], Phases]) -> tuple[float, int, int]:
    """The shortest duration of a law of the given shape on a segment ``[lam0, lam0 + L]``
    whose direction varies: ``(D, order, actuator)`` of the binding limit, from the dense
    grid."""
    unit = shape(1.0, 1.0)
    s = np.linspace(0.0, 1.0, LIMIT_GRID)
    x, v, _, _ = unit.evaluate(s)
    a = path.g(lam0 + L * x) * (L * v)[:, None]         # u * D
    da = np.gradient(a, s, axis=0, edge_order=2)        # u' * D^2
    dda = np.gradient(da, s, axis=0, edge_order=2)      # u'' * D^3
    best = (0.0, 0, 0)
    for order, (vals, lim) in enumerate(zip((a, da, dda), bounds)):
        peak = np.max(np.abs(vals), axis=0)
        for i in range(2):
            if math.isfinite(lim[i]) and peak[i] > 0:
                with np.errstate(over="ignore"):
                    D = (peak[i] / lim[i]) ** (1.0 / (order + 1))
                if D > best[0]:
                    best = (D, order, i)
    return best


#: An actuator whose rate on a segment of constant direction is at most this share of the
#: other's is still there for the limits: the segment takes the pace of the segments whose
#: limits bind. Why: an NLP's rate that is nearly 0 (an 8-joint plan's u2 at 2e-6 of u1 on
#: three pieces, interior-point solutions do not end on 0 exactly) divided into ``max_u2``
#: ran those pieces of 0.05 rad of phi in 1e-7 s each, u1 at 5e5 rad/s: no motor's motion,
#: and no form of a few thousand samples holds it. The still actuator then moves at a
#: thousandth of the other's rate at most, within its limit at any pace the others allow.
STILL_SHARE = 1e-3


#: Intervals of the convex time-optimal retiming of a segment whose direction varies.
TOPP_INTERVALS = 160
#: It keeps this much more room below each limit (its constraints hold at the grid's
#: points; between them the rates are checked on the handed-out form).
TOPP_MARGIN = 5e-3


def topp_segment(path: GeometricPath, lam0: float, L: float,
                 bounds: tuple[np.ndarray, np.ndarray, np.ndarray],
                 intervals: int = TOPP_INTERVALS) -> Phases | None:
    """The time-optimal rest-to-rest law along a segment ``[lam0, lam0 + L]`` whose direction
    varies, under the rate and acceleration bounds (``bounds[2]``, jerk, is not convex here
    and is ignored: the caller does not ask then).

    With ``b = lam'^2`` as a function of ``lam`` (time-optimal path parameterisation), the
    rates are ``u = g sqrt(b)`` and their derivatives ``u' = g'(lam) b + g(lam) b'/2``: linear
    in ``b``. On a grid ``lam_k`` with ``b`` linear between the points (constant acceleration
    ``a_k = (b_{k+1} - b_k) / (2 d_k)`` on interval ``k``), ``|g_i| sqrt(b_k) <= max_u_i`` and
    ``|g_i' b + g_i a_k| <= max_du_i`` at both ends of every interval (``g'`` from inside it)
    are linear constraints; the time ``sum 2 d_k / (sqrt(b_k) + sqrt(b_{k+1}))`` is convex in
    ``s = sqrt(b)`` with ``s^2 <= b``. cvxpy over Clarabel solves it; ``None`` when it fails.
    """
    import cvxpy as cp

    rate, accel, _ = bounds
    knots = path.lam[(path.lam > lam0) & (path.lam < lam0 + L)]
    even = np.linspace(lam0, lam0 + L, intervals + 1)
    if knots.size:          # the knots (kinks of g) are grid points; no sliver next to one
        near = np.min(np.abs(even[:, None] - knots[None, :]), axis=1) < 0.25 * L / intervals
        near[[0, -1]] = False
        even = even[~near]
    grid = np.union1d(even, knots)
    d = np.diff(grid)
    g = path.g(grid)
    eps = 1e-3 * d
    g_in_left = (path.g(grid[:-1] + eps) - g[:-1]) / eps[:, None]    # g' at each start
    g_in_right = (g[1:] - path.g(grid[1:] - eps)) / eps[:, None]     # g' at each end
    g_left = path.g(grid[:-1] + 1e-9 * d)                            # g inside, at the ends
    g_right = path.g(grid[1:] - 1e-9 * d)
    N = grid.size
    b = cp.Variable(N, nonneg=True)
    sq = cp.Variable(N, nonneg=True)
    acc = cp.multiply(b[1:] - b[:-1], 1.0 / (2.0 * d))
    cons = [b[0] == 0, b[N - 1] == 0, cp.square(sq) <= b]
    for i in range(2):
        if math.isfinite(rate[i]):
            gi = np.maximum(np.abs(g[:, i]), np.abs(np.r_[g_left[:, i], g_right[-1, i]]))
            cap = np.where(gi > 0, (rate[i] / np.where(gi > 0, gi, 1.0)) ** 2, np.inf)
            finite = np.isfinite(cap)
            if finite.any():
                cons.append(b[np.nonzero(finite)[0]] <= cap[finite])
        if math.isfinite(accel[i]):
            lhs = [cp.multiply(g_in_left[:, i], b[:-1]) + cp.multiply(g_left[:, i], acc),
                   cp.multiply(g_in_right[:, i], b[1:]) + cp.multiply(g_right[:, i], acc)]
            cons += [cp.abs(e) <= accel[i] for e in lhs]
    if not any(math.isfinite(x) for x in np.r_[rate, accel]):
        return None
    time_ = cp.sum(cp.multiply(2.0 * d, cp.inv_pos(sq[:-1] + sq[1:])))
    prob = cp.Problem(cp.Minimize(time_), cons)
    try:
        with warnings.catch_warnings():
            # an "optimal_inaccurate" solve is kept and its law checked like any other (the
            # limits are measured on the handed-out path): cvxpy's warning about it would
            # reach the service's stderr
            warnings.simplefilter("ignore", UserWarning)
            prob.solve(solver=cp.CLARABEL)
    except (cp.error.SolverError, ValueError):
        return None
    if prob.status not in ("optimal", "optimal_inaccurate") or b.value is None:
        return None
    bv = np.maximum(np.asarray(b.value, float), 0.0)
    bv[0] = bv[-1] = 0.0
    v = np.sqrt(bv)
    if np.any(v[:-1] + v[1:] <= 0.0):
        return None
    dt = 2.0 * d / (v[:-1] + v[1:])
    a = (bv[1:] - bv[:-1]) / (2.0 * d)
    return phases_from([(float(h), float(x), 0.0) for h, x in zip(dt, a)])


#: A law that never ends (a limit too small for any finite duration).
_NEVER = Phases(np.zeros(1), np.array([math.inf]), np.zeros(1), np.zeros(1), np.zeros(1),
                np.zeros(1))


def _constant_need(g: np.ndarray, L: float,
                   bounds: tuple[np.ndarray, np.ndarray, np.ndarray]
                   ) -> tuple[Phases | None, int, int]:
    """The fastest law on a segment of constant direction ``g``, and its binding limit
    ``(order, actuator)`` (the bound with the least room per unit ``lam``)."""
    ag = np.abs(g)
    # an actuator that barely moves on the segment does not set its pace (see STILL_SHARE)
    ag = np.where(ag <= STILL_SHARE * float(np.max(ag)), 0.0, ag)
    per: list[tuple[float, int, int]] = []         # (bound per unit lam, order, actuator)
    for order, lim in enumerate(bounds):
        with np.errstate(divide="ignore"):
            r = np.where(ag > 0, lim / np.where(ag > 0, ag, 1.0), math.inf)
        i = int(np.argmin(r))
        per.append((float(r[i]), order, i))
    V, A, J = (x[0] for x in per)
    if min(V, A, J) * max(L, 1.0) < 1e-200 or not L / max(min(V, A, J), 1e-300) < 1e200:
        # a limit so small that no duration is finite: the caller refuses it
        return _NEVER, per[int(np.argmin([V, A, J]))][1], per[int(np.argmin([V, A, J]))][2]
    law = rest_to_rest(L, V, A, J)
    if law is None:
        return None, 0, 0
    # the binding one: the bound whose profile alone takes longest
    alone = []
    for val, order, i in per:
        if math.isfinite(val):
            b = [math.inf, math.inf, math.inf]
            b[order] = val
            one = rest_to_rest(L, *b)
            alone.append((one.duration if one is not None else 0.0, order, i))
    _, order, i = max(alone)
    return law, order, i


def time_law(path: GeometricPath, limits: Limits, duration: float | None, nominal: float,
             *, fixed_times: bool = False, max_duration: float = math.inf,
             margin: float = 1e-3) -> TimeLaw:
    """The time law of a plan (see the module's docstring for the rules).

    Parameters
    ----------
    path : GeometricPath
    limits : Limits
    duration : float or None
        The requested ``T``; ``None``: the shortest within the limits, or ``nominal`` without.
    nominal : float
        ``T`` without limits and duration.
    fixed_times : bool
        The stops' times must be the plan's own (constraint points): the segments share ``T``
        in proportion to the plan's times even with limits, which are then only checked.
    max_duration : float
        The largest duration allowed.
    margin : float
        The law is planned for the limits times ``1 - margin`` (the handed-out samples are
        corrected afterwards, which moves them a little).

    Raises
    ------
    InfeasibleError
        The requested duration is too short for the limits (``field='duration'``, the
        binding limit and ``shortest_duration`` in the diagnostics), or the limits need a
        duration above ``max_duration``.
    """
    seg = path.segments
    lam_ends = path.lam[seg]
    Ls = np.diff(lam_ends)
    hs = np.diff(path.sigma[seg])
    bounds = limits.scaled(1.0 - margin).arrays()
    if not limits.any or fixed_times:
        T = nominal if duration is None else float(duration)
        scale = T / float(hs.sum())
        if seg.size == path.lam.size:  # a stop at every knot: one ramp law per piece
            law = _one_piece_segments(path, scale, limits)
        else:
            parts = [_plan_timed(path, int(a), int(b), scale)
                     for a, b in zip(seg[:-1], seg[1:])]
            law = _assemble(path, parts, None, None, limits)
        if limits.any:
            _check_fixed(law, limits)
        return law
    # a varying direction: the ramp law's shape, or the smooth one under a jerk limit (the
    # ramp's acceleration jumps)
    shape = smooth_profile if np.isfinite(bounds[2]).any() else ramp_profile
    parts_min: list[Phases | None] = []
    binding: list[tuple[float, int, int]] = []
    for j, L in enumerate(Ls):
        if not all(p is None or math.isfinite(p.duration) for p in parts_min):
            break                       # a limit too small already: refused below
        if path.constant:
            mid = 0.5 * (lam_ends[j] + lam_ends[j + 1])
            law_j, order, i = _constant_need(path.g(np.array([mid]))[0], float(L), bounds)
            parts_min.append(law_j)
            binding.append((law_j.duration if law_j is not None else 0.0, order, i))
        else:
            D, order, i = _shape_need(path, float(lam_ends[j]), float(L), bounds, shape)
            fast = None
            # the convex retiming needs an acceleration limit (without one its optimum jumps
            # the speed over one grid interval) and no jerk limit (not convex)
            if shape is ramp_profile and D > 0 and np.isfinite(bounds[1]).any():
                fast = topp_segment(path, float(lam_ends[j]), float(L),
                                    limits.scaled(1.0 - TOPP_MARGIN).arrays())
            if fast is not None and fast.duration < D:
                parts_min.append(fast)
                binding.append((fast.duration, order, i))
            else:
                parts_min.append(shape(float(L), D) if D > 0 else None)
                binding.append((D, order, i))
    bounded = [p.duration for p in parts_min if p is not None]
    hb = sum(h for p, h in zip(parts_min, hs) if p is not None)
    # seconds per plan second where a limit binds; where none binds anywhere (the limited
    # actuators never move), the plan's own pace over the nominal duration
    rate = sum(bounded) / hb if hb > 0.0 else nominal / float(sum(hs))
    parts = [p if p is not None else ramp_profile(float(L), float(h) * rate)
             for p, L, h in zip(parts_min, Ls, hs)]
    shortest = float(sum(p.duration for p in parts))
    _, order, i = max(binding)
    name = Limits.NAMES[order][i]
    if not shortest <= max_duration:
        raise InfeasibleError(
            f"the limits need a duration of {shortest:.6g} s along this path ({name} = "
            f"{limits.value(name):g} binds), above the largest allowed {max_duration:g} s",
            field=name, diagnostics={"shortest_duration": shortest if math.isfinite(shortest)
                                     else None, "binding_limit": name})
    T = shortest if duration is None else float(duration)
    if T < shortest * (1.0 - 1e-9):
        raise InfeasibleError(
            f"duration {T:g} s is too short for the limits along this path: {name} = "
            f"{limits.value(name):g} binds and the shortest duration that respects the limits "
            f"is {shortest:.6g} s", field="duration",
            diagnostics={"shortest_duration": shortest, "binding_limit": name})
    f = T / shortest
    if f != 1.0:
        parts = [p.stretched(f) for p in parts]
    return _assemble(path, parts, shortest, name, limits)


def _plan_timed(path: GeometricPath, first: int, last: int, scale: float,
                ramp: float = RAMP) -> Phases:
    """The law of the segment between the knots ``first`` and ``last`` that keeps the plan's
    own timing (times ``scale``) at every knot: on knot piece ``k`` (length ``L_k`` in ``lam``,
    duration ``D_k``, mean speed ``v_k = L_k / D_k``) the speed ramps linearly over ``ramp
    D_k`` from its value at the piece's start to a cruise speed and over the last ``ramp D_k``
    to its value at the piece's end: 0 at the segment's ends, ``min(v_{k-1}, v_k)`` at an
    inner knot (the plan's speed steps there: the retimed method's pieces). The cruise speed
    makes the piece cover ``L_k`` exactly, so the knots are reached at the plan's times; it is
    at least ``v_k``. A segment of one piece gets :func:`ramp_profile`."""
    L = np.diff(path.lam[first:last + 1])
    D = np.diff(path.sigma[first:last + 1]) * scale
    v = L / D
    edge = np.concatenate([[0.0], np.minimum(v[:-1], v[1:]), [0.0]])
    pieces: list[tuple[float, float, float]] = []
    for k in range(L.size):
        v_in, v_out = edge[k], edge[k + 1]
        cruise = (v[k] - ramp * 0.5 * (v_in + v_out)) / (1.0 - ramp)
        r = ramp * D[k]
        pieces += [(r, (cruise - v_in) / r, 0.0), (D[k] - 2.0 * r, 0.0, 0.0),
                   (r, (v_out - cruise) / r, 0.0)]
    return phases_from(pieces)


def _one_piece_segments(path: GeometricPath, scale: float, limits: Limits,
                        ramp: float = RAMP) -> TimeLaw:
    """The law of :func:`_plan_timed` where every knot is a stop (a plan of constant rates
    whose direction changes at every break: each segment is one knot piece), for all segments
    at once: per segment a ramp up over ``ramp D``, a cruise and a ramp down, the same
    arithmetic as :func:`phases_from` of those three pieces."""
    L = np.diff(path.lam)
    D = np.diff(path.sigma) * scale
    cruise = (L / D - 0.0) / (1.0 - ramp)
    r = ramp * D
    acc = cruise / r
    mid = D - 2.0 * r
    x1 = r * (r * (acc / 2.0))
    v1 = r * acc
    x2 = x1 + mid * (v1 + mid * 0.0)
    ends = np.cumsum((r + mid) + r)   # (each segment's duration as phases_from sums it)
    t0 = np.concatenate([[0.0], ends[:-1]])
    lam0 = path.lam[:-1]
    zero = np.zeros_like(L)
    stack = lambda *cols: np.column_stack(cols).ravel()  # noqa: E731 - phases in time order
    phases = Phases(start=stack(t0, t0 + r, t0 + (r + mid)), length=stack(r, mid, r),
                    x0=stack(lam0, lam0 + x1, lam0 + x2), v0=stack(zero, v1, v1),
                    a0=stack(acc, zero, -acc), jerk=np.zeros(3 * L.size))
    return TimeLaw(path, phases, np.concatenate([[0.0], ends]), None, None, limits)


def _assemble(path: GeometricPath, parts: Sequence[Phases], shortest: float | None,
              binding: str | None, limits: Limits) -> TimeLaw:
    # each segment starts exactly on its stop knot's lam (the rounding of an integrated
    # profile stays inside its segment)
    phases = Phases.concatenate(parts, path.lam[path.segments][:-1])
    stops = np.concatenate([[0.0], np.cumsum([p.duration for p in parts])])
    return TimeLaw(path, phases, stops, shortest, binding, limits)


def _check_fixed(law: TimeLaw, limits: Limits) -> None:
    """The limits on a law whose times are fixed: refuse it when it exceeds one."""
    t = np.linspace(0.0, law.T, 8 * LIMIT_GRID)
    u, du = law.rates_and_derivative(t)
    rate, accel, _ = limits.arrays()
    for order, (vals, lim) in enumerate(((u, rate), (du, accel))):
        peak = np.max(np.abs(vals), axis=0)
        for i in range(2):
            if peak[i] > lim[i] * (1.0 + 1e-9):
                name = Limits.NAMES[order][i]
                raise InfeasibleError(
                    f"the constraint points fix the plan's times and its rates reach "
                    f"{peak[i]:.6g} there, above {name} = {lim[i]:g}: a longer duration",
                    field=name, diagnostics={"peak": float(peak[i]), "limit": name})
