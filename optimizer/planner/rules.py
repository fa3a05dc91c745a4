"""The request's rules every method follows: the region, the joint limits, the sign of ``dphi``.

A leaf of the planner (imports nothing of it).
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, TypeVar

import numpy as np

from ..problem import PlanRequest
from ..region import Region

#: A plan is verified when the re-integrated original model ends this close to the goal (rad).
TERMINAL_TOLERANCE = 1e-6
HALF_PI = 0.5 * math.pi
T = TypeVar("T")


def make_region(req: PlanRequest, criterion: str | None = None) -> Region:
    """The singularity-free region of the request (its criterion unless one is given)."""
    return Region(req.robot, criterion or req.singularity, req.joint_bounds)


def _per_request(f: Callable[[PlanRequest], T]) -> Callable[[PlanRequest], T]:
    """``f(req)`` computed once per request while a plan asks for it several times (requests
    are frozen); :func:`clear_request_caches` forgets it when the next plan starts, so that a
    plan never reuses another's work. An unhashable request is computed each time."""
    cached = functools.lru_cache(maxsize=8)(f)
    _CACHES.append(cached)

    @functools.wraps(f)
    def get(req: PlanRequest) -> T:
        try:
            return cached(req)
        except TypeError:
            return f(req)
    return get


_CACHES: list[Any] = []


def clear_request_caches() -> None:
    """Forget the per-request values of the previous plans (called as each plan starts)."""
    for c in _CACHES:
        c.cache_clear()


@_per_request
def full_region(req: PlanRequest) -> Region:
    """The full region of the request (shared within a plan: read only)."""
    return make_region(req, "full")


@_per_request
def joint_limits(req: PlanRequest) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (rad) every joint ``th_1..th_n`` keeps on the whole path (read-only arrays):
    :func:`kept_limits` of the request's full region."""
    lo, hi = kept_limits(full_region(req), req.joint_bounds, req.start, req.goal)
    lo.setflags(write=False)
    hi.setflags(write=False)
    return lo, hi


def kept_limits(region: Region, joint_bounds: Any, start: Any, goal: Any
                ) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (rad) of ``th_1..th_n`` on a path from ``start`` to ``goal`` in ``region``.

    ``th_1..th_{n-1}`` lie in the region where the chained form is invertible, (0, pi/2),
    narrowed by ``joint_bounds``. ``th_n`` takes no part in that region, but a joint that
    leaves (0, pi/2) is of no use to the arm either: it keeps (0, pi/2) too unless
    ``joint_bounds`` says otherwise (narrower or wider), or its start or goal lies outside.
    """
    lo = np.array(region.lower, float)
    hi = np.array(region.upper, float)
    n = lo.size
    last = None if joint_bounds is None else joint_bounds[n - 1]
    if last is None and all(0.0 < float(x[n - 1]) < HALF_PI for x in (start, goal)):
        lo[n - 1], hi[n - 1] = 0.0, HALF_PI
    return lo, hi


@_per_request
def limits_region(req: PlanRequest) -> Region:
    """The full region with every joint held to its limits (:func:`joint_limits`; shared
    within a plan: read only)."""
    lo, hi = joint_limits(req)
    return Region(req.robot, "full", [(float(a), float(b)) if np.isfinite(a) or np.isfinite(b)
                                      else None for a, b in zip(lo, hi)])


def check_endpoints(req: PlanRequest, region: Region) -> None:
    """Start and goal must be inside the (full) region: there the transform exists."""
    region.check_point_q(np.array((0.0,) + req.start), "start")
    region.check_point_q(np.array((0.0,) + req.goal), "goal")


def direction_conflict(req: PlanRequest) -> str | None:
    """Why the constant-v1 family cannot reach the goal, or None.

    With ``v1`` constant every ``th_i`` (i >= 2) moves monotonically in the direction of
    ``dphi`` (``th_i' = K_i cos(th_{i-1})^m_i u1`` with a positive factor in the region).
    """
    d = [g - s for g, s in zip(req.goal[1:], req.start[1:])]
    up = [i + 2 for i, x in enumerate(d) if x > 0]
    down = [i + 2 for i, x in enumerate(d) if x < 0]
    if up and down:
        return (f"joints th{up[0]} and th{down[0]} must move in opposite directions: with a "
                "constant v1 every joint th2..thn moves in the direction of phi, so phi must "
                "reverse (use method 'shooting', 'penalty' or 'auto')")
    if not up and not down:
        return ("joints th2..thn do not move, which needs dphi = 0 where the steering system is "
                "singular (Remark 2); phi must go and come back (use method 'shooting', "
                "'penalty' or 'auto')")
    return None


def phi_search_bounds(req: PlanRequest) -> tuple[float, float]:
    """The request's ``dphi`` bounds, cut to the sign the joints' motion demands."""
    lo, hi = req.phi_change_bounds
    d = [g - s for g, s in zip(req.goal[1:], req.start[1:])]
    if all(x >= 0 for x in d):
        lo = max(lo, 0.0)
    elif all(x <= 0 for x in d):
        hi = min(hi, 0.0)
    return lo, hi


#: Gauss-Legendre nodes of the integrals in :func:`monotone_reach_ok` (smooth integrands).
_GL = np.polynomial.legendre.leggauss(24)


def _cos_power_integral(a: float, b: float, m: int) -> float:
    """``int_a^b cos(x)^m dx`` (signed)."""
    x, w = _GL
    mid, half = 0.5 * (a + b), 0.5 * (b - a)
    return float(half * np.sum(w * np.cos(mid + half * x) ** m))


def monotone_reach_ok(req: PlanRequest, th1_monotone: bool) -> bool:
    """A necessary condition for a path in which ``phi`` does not reverse (and, with
    ``th1_monotone``, neither does ``th_1``) to reach the goal.

    With ``phi`` monotone every ``th_i`` (i >= 2) is monotone, so it stays between its start
    and goal, and along the path ``dth_{i+1} / dth_i = K_{i+1} cos(th_i)^{m_{i+1}} /
    (K_i cos(th_{i-1})^{m_i})``. With ``th_{i-1}`` confined to a range where ``cos^{m_i}`` lies
    in ``[c_lo, c_hi]``, ``|dth_{i+1}|`` lies between ``K_{i+1}/K_i |int cos^{m_{i+1}} dth_i|``
    divided by ``c_hi`` and by ``c_lo``. ``th_1`` is confined to its start..goal range when it is
    monotone, else to its limits. A goal outside these bounds cannot be reached that way: the
    NLP need not be asked (it takes tens of iterations to give up).
    """
    n = req.n
    a, b = [float(x) for x in req.start], [float(x) for x in req.goal]
    K, m = req.robot.gains, req.robot.exponents
    if any(x == y for x, y in zip(a[1:], b[1:])):
        return False  # th_i' = K_i cos(.)^m u1 != 0 while phi moves: th_i must change
    for i in range(2, n):  # joints th_i -> th_{i+1}, 1-based; arrays 0-based
        prev = i - 2                                   # th_{i-1}
        if prev == 0 and not th1_monotone:
            lo_lim, hi_lim = joint_limits(req)
            r_lo, r_hi = max(float(lo_lim[0]), 0.0), min(float(hi_lim[0]), HALF_PI)
        else:
            r_lo, r_hi = min(a[prev], b[prev]), max(a[prev], b[prev])
        c_hi, c_lo = math.cos(r_lo) ** m[i - 2], math.cos(r_hi) ** m[i - 2]
        integral = abs(_cos_power_integral(a[i - 1], b[i - 1], m[i - 1]))
        ratio = K[i - 1] / K[i - 2]
        need = abs(b[i] - a[i])
        low = ratio * integral / c_hi
        if need < low * (1.0 - 1e-9):
            return False
        if c_lo > 0.0 and need > ratio * integral / c_lo * (1.0 + 1e-9):
            return False
    return _triples_reach_ok(req, th1_monotone)


#: Absolute slack (rad) of :func:`_triples_reach_ok`: a change of a joint this close to what
#: its bound allows is not refused (the bound's quadrature is exact to about 1e-12 rad).
TRIPLE_SLACK = 1e-6


def _cos_power_recursion(x: Any, c: Any, s_: Any, m: int) -> Any:
    """``C_m`` from ``x``, ``cos x`` and ``sin x`` (arrays or floats alike): ``C_0 = x``,
    ``C_1 = sin x``, ``C_m = cos^{m-1} sin / m + (m - 1) / m C_{m-2}``."""
    k, total = (0, x) if m % 2 == 0 else (1, s_)
    while k + 2 <= m:
        k += 2
        total = c ** (k - 1) * s_ / k + (k - 1) / k * total
    return total


def cos_power_antiderivative(x: np.ndarray, m: int) -> np.ndarray:
    """``C_m(x) = int_0^x cos(s)^m ds`` in closed form (:func:`_cos_power_recursion`)."""
    x = np.asarray(x, float)
    return np.asarray(_cos_power_recursion(x, np.cos(x), np.sin(x), m))


def _cos_power_scalar(x: float, m: int) -> float:
    """:func:`cos_power_antiderivative` of one value, in floats (a tenth of numpy's time)."""
    return float(_cos_power_recursion(x, math.cos(x), math.sin(x), m))


def _cos_power_inverse(gamma: float, m: int, lo: float, hi: float) -> float:
    """``x`` in ``[lo, hi]`` (within ``[0, pi/2)``) with ``C_m(x) = gamma``
    (:func:`cos_power_antiderivative`, increasing there): Newton's steps kept inside a
    bracket that bisects where a step would leave it (``C_m`` flattens towards ``pi/2``)."""
    x_lo, x_hi = lo, hi
    c_lo, c_hi = _cos_power_scalar(lo, m), _cos_power_scalar(hi, m)
    if gamma <= c_lo:
        return lo
    if gamma >= c_hi:
        return hi
    x = lo + (hi - lo) * (gamma - c_lo) / (c_hi - c_lo)
    for _ in range(100):
        f = _cos_power_scalar(x, m) - gamma
        if f > 0.0:
            x_hi = x
        else:
            x_lo = x
        d = math.cos(x) ** m
        step = x - f / d if d > 0.0 else -1.0
        new = step if x_lo < step < x_hi else 0.5 * (x_lo + x_hi)
        if abs(new - x) <= 1e-15 * max(1.0, abs(x)) or x_hi - x_lo <= 1e-15:
            return new
        x = new
    return x


def _piece_integral(ax: float, sx: float, u0: float, u1: float, g0: float, g1: float,
                    slope: float, mx: int, mg: int) -> float:
    """``int_{u0}^{u1} cos(x)^mx / cos(g)^mg du`` with ``x = ax + sx u`` and ``g`` moving
    from ``g0`` to ``g1`` with ``C_mg(g)`` linear in ``u`` at ``slope`` (:func:`_triples_reach_ok`).
    Over ``g`` (``du = cos(g)^mg dg / slope``: the steep ``1 / cos(g)^mg`` near ``pi/2``
    cancels), or over ``u`` with ``g`` fixed where ``g`` hardly moves."""
    x_gl, w_gl = _GL
    if slope * (u1 - u0) <= 1e-12 or g0 == g1:
        half = 0.5 * (u1 - u0)
        uu = 0.5 * (u0 + u1) + half * x_gl
        return half * float(np.sum(w_gl * np.cos(ax + sx * uu) ** mx)) / math.cos(g0) ** mg
    half = 0.5 * (g1 - g0)
    gg = 0.5 * (g0 + g1) + half * x_gl
    uu = u0 + np.abs(cos_power_antiderivative(gg, mg) - _cos_power_scalar(g0, mg)) / slope
    return abs(half) * float(np.sum(w_gl * np.cos(ax + sx * uu) ** mx)) / slope


def _triples_reach_ok(req: PlanRequest, th1_monotone: bool) -> bool:
    """The joint triples' part of :func:`monotone_reach_ok`: with ``phi`` monotone, joints
    ``g = th_j``, ``x = th_{j+1}``, ``y = th_{j+2}`` (``j >= 2``) all move monotonically, and
    along the path ``cos(g)^{m_{j+1}} dg = (K_j / K_{j+1}) cos(th_{j-1})^{m_j} dx``: in the
    variable ``gamma = C(g) = int cos^{m_{j+1}}``, ``g`` is a monotone function of ``x`` whose
    slope ``|dgamma/dx|`` lies within ``[s_lo, s_hi]``, ``(K_j / K_{j+1}) cos^{m_j}`` at the
    ends of ``th_{j-1}``'s range (as in :func:`monotone_reach_ok`), from its start to its goal.
    ``y`` changes by ``(K_{j+2} / K_{j+1}) int cos(x)^{m_{j+2}} / cos(g)^{m_{j+1}} dx``, whose
    integrand grows with ``g`` (so with ``gamma``): over every such path the integral is
    largest (smallest) when ``gamma`` moves at ``s_hi`` first and ``s_lo`` after (or the
    reverse), and a change of ``y`` outside the two extremes is out of reach. Sharper than
    the pairs' bound, which lets ``g`` take its extreme value at once: on the goals
    benchmark's ``r4_000`` ``th_4`` must move 0.04807 rad, the pairs allow 0.0433 to 0.0679,
    the triples 0.0486 to 0.0497 (its NLP of rates of fixed signs ran to fatrop's iteration
    cap, 12 ms, to find that out); on ``r4_003`` 0.4517 against at most 0.4486 (an NLP of 8
    ms that ended with its sign slack)."""
    n = req.n
    a, b = [float(x) for x in req.start], [float(x) for x in req.goal]
    K, m = req.robot.gains, req.robot.exponents
    for j in range(2, n - 1):            # 1-based g = th_j, x = th_{j+1}, y = th_{j+2}
        gi, xi, yi, pi = j - 1, j, j + 1, j - 2          # 0-based indices (pi: th_{j-1})
        if pi == 0 and not th1_monotone:
            lo_lim, hi_lim = joint_limits(req)
            p_lo, p_hi = max(float(lo_lim[0]), 0.0), min(float(hi_lim[0]), HALF_PI)
        else:
            p_lo, p_hi = min(a[pi], b[pi]), max(a[pi], b[pi])
        g_lo, g_hi = min(a[gi], b[gi]), max(a[gi], b[gi])
        if g_hi >= HALF_PI or p_lo >= HALF_PI:
            continue
        mg = m[j - 1]
        ratio = K[j - 2] / K[j - 1]
        s_lo, s_hi = ratio * math.cos(p_hi) ** m[j - 2], ratio * math.cos(p_lo) ** m[j - 2]
        c_a, c_b = _cos_power_scalar(a[gi], mg), _cos_power_scalar(b[gi], mg)
        dx = b[xi] - a[xi]
        L, G = abs(dx), abs(c_b - c_a)
        if not s_lo * L - TRIPLE_SLACK <= G <= s_hi * L + TRIPLE_SLACK:
            return False                 # g cannot move so far (so little) while x moves
        if L == 0.0 or s_hi - s_lo <= 1e-12 * s_hi or not s_lo * L <= G <= s_hi * L:
            continue                     # (one path of g, or none: the bound above decides)
        sg, sx = (1.0 if b[gi] >= a[gi] else -1.0), math.copysign(1.0, dx)
        ends = []
        # gamma moved from the start: fastest first (turning at u_fast), slowest first
        for u_turn, first, second in (((G - s_lo * L) / (s_hi - s_lo), s_hi, s_lo),
                                      ((s_hi * L - G) / (s_hi - s_lo), s_lo, s_hi)):
            g_turn = _cos_power_inverse(c_a + sg * first * u_turn, mg, g_lo, g_hi)
            total = 0.0
            if u_turn > 0.0:
                total += _piece_integral(a[xi], sx, 0.0, u_turn, a[gi], g_turn, first, m[j], mg)
            if L > u_turn:
                total += _piece_integral(a[xi], sx, u_turn, L, g_turn, b[gi], second, m[j], mg)
            ends.append(K[j] / K[j - 1] * total)
        need = abs(b[yi] - a[yi])
        if not min(ends) - TRIPLE_SLACK <= need <= max(ends) + TRIPLE_SLACK:
            return False
    return True


def th1_monotone_reach_ok(req: PlanRequest, lo2: float, hi2: float,
                          slack: float = 1e-4) -> bool:
    """A necessary condition for a path in which ``th_1`` does not reverse (``phi`` free) to
    reach the goal, with ``th_2`` kept within ``[lo2, hi2]``.

    With ``th_1`` monotone, ``dth_3 = (K_3 / K_2) w(th_1, th_2) dth_2`` with
    ``w = cos(th_2)^{m_3} / cos(th_1)^{m_2}``. Let ``F(t, x) = int_0^x w(t, s) ds``; along the
    path ``int w dth_2 = F(b_1, b_2) - F(a_1, a_2) - int dF/dth_1 dth_1`` and ``dF/dth_1 >= 0``
    grows with ``th_2``, so with ``th_1`` moving one way the last integral lies between its
    values for ``th_2`` held at ``lo2`` and at ``hi2``: ``G(c) = F(b_1, b_2) - F(a_1, a_2) -
    (F(b_1, c) - F(a_1, c))``. A change of ``th_3`` outside ``(K_3 / K_2) [G(lo2), G(hi2)]``
    (in either order), widened by ``slack`` (rad: the NLP's RK4 is that far from the exact
    model), cannot be reached that way. True for fewer than 3 joints.
    """
    if req.n < 3:
        return True
    a, b = np.array(req.start, float), np.array(req.goal, float)
    K, m = req.robot.gains, req.robot.exponents

    ca, cb = math.cos(a[0]) ** m[0], math.cos(b[0]) ** m[0]
    ends = _cos_power_integral(0.0, b[1], m[1]) / cb - _cos_power_integral(0.0, a[1], m[1]) / ca

    def G(c: float) -> float:  # F(b_1, b_2) - F(a_1, a_2) - (F(b_1, c) - F(a_1, c))
        return ends - _cos_power_integral(0.0, c, m[1]) * (1.0 / cb - 1.0 / ca)

    lo, hi = sorted((K[1] / K[0] * G(lo2), K[1] / K[0] * G(hi2)))
    return lo - slack <= b[2] - a[2] <= hi + slack


def travel_reach_error(req: PlanRequest, phi_travel: float) -> str | None:
    """Why no path with at most ``phi_travel`` rad of ``phi`` motion (the sum of ``|dphi|``
    over the path) reaches the goal within the joint limits, or None.

    Along any path, ``phi`` reversing or not, ``dth_{i+1} = r dth_i`` with ``r =
    (K_{i+1} / K_i) cos(th_i)^{m_{i+1}} / cos(th_{i-1})^{m_i}``; with ``th_{i-1}`` and ``th_i``
    within their limits ``r`` lies in ``[r_lo, r_hi]``, so ``|dth_{i+1} - r_mid dth_i|`` over the
    path is at most ``(r_hi - r_lo) / 2`` times the travel of ``th_i``, itself at most
    ``K_i max cos(th_{i-1})^{m_i}`` times ``phi_travel`` (``th_2``'s travel for ``i = 1``
    alike). Narrow limits make ``r`` nearly constant, and then a joint moves with the one
    before it, by a bounded amount however ``phi`` goes back and forth: the NLPs would search
    to their time limit for a path whose length their rate bounds exclude.
    """
    lo, hi = joint_limits(req)
    lo = np.clip(lo, 0.0, HALF_PI)
    hi = np.clip(hi, 0.0, HALF_PI)
    a, b = np.array(req.start, float), np.array(req.goal, float)
    K, m = req.robot.gains, req.robot.exponents
    n = req.n

    def cos_range(j: int, power: int) -> tuple[float, float]:  # of cos(th_j)^power, 0-based j
        return math.cos(hi[j]) ** power, math.cos(lo[j]) ** power

    travel = np.zeros(n)  # the largest travel of each th_i (0-based), i >= 1
    travel[1] = K[0] * cos_range(0, m[0])[1] * phi_travel
    for i in range(1, n - 1):  # th_{i+1} (0-based) from th_i and th_{i-1}
        c_prev_lo, c_prev_hi = cos_range(i - 1, m[i - 1])
        c_lo, c_hi = cos_range(i, m[i])
        if c_prev_lo <= 0.0:
            return None  # th_{i-1} may reach pi/2 within its limits: r is unbounded
        ratio = K[i] / K[i - 1]
        r_lo, r_hi = ratio * c_lo / c_prev_hi, ratio * c_hi / c_prev_lo
        r_mid = 0.5 * (r_lo + r_hi)
        reach = 0.5 * (r_hi - r_lo) * travel[i]
        need = abs((b[i + 1] - a[i + 1]) - r_mid * (b[i] - a[i]))
        if need > reach + 1e-9:
            names = f"th{i} and th{i + 1}"
            most = abs(r_mid * (b[i] - a[i])) + reach
            return (f"th{i + 2} cannot move {abs(b[i + 1] - a[i + 1]):.4g} rad with {names} "
                    f"kept within their limits: there it follows th{i + 1} at a rate between "
                    f"{r_lo:.4g} and {r_hi:.4g}, so with at most {phi_travel:g} rad of phi "
                    f"travel (the planner's largest) th{i + 2} moves at most {most:.4g} rad. "
                    f"Widen joint_bounds of th{i} and th{i + 1}, or move th{i + 2} less")
        travel[i + 1] = min(r_hi * travel[i], K[i] * c_hi * phi_travel)
    return None


def monotone_signs(req: PlanRequest) -> tuple[float, float] | None:
    """Signs of ``(u1, u2)`` of a plan in which neither actuator reverses, or None when the
    goal needs ``phi`` to reverse (:func:`direction_conflict`).

    With ``u1`` of one sign every joint ``th_2..th_n`` moves in ``phi``'s direction, so the
    sign is the one the joints' motion demands; ``u2``'s is that of ``th_1``'s change (0: free,
    ``th_1`` need not move).
    """
    if direction_conflict(req) is not None:
        return None
    lo, hi = phi_search_bounds(req)
    if req.phi_change is not None:
        s1 = float(np.sign(req.phi_change))
    elif lo >= 0.0:
        s1 = 1.0
    elif hi <= 0.0:
        s1 = -1.0
    else:  # pragma: no cover - a direction is always demanded without a conflict
        return None
    if s1 == 0.0:
        return None
    d1 = req.goal[0] - req.start[0]
    return s1, float((d1 > 0) - (d1 < 0))
