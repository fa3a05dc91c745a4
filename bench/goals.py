"""Reachable goals no one tuned for: the original model driven forward from random starts.

Each goal is made by the system itself, so it is reachable by construction:

1. a start drawn uniformly inside the region, every joint in ``[START_MARGIN, pi/2 -
   START_MARGIN]``;
2. smooth random actuator rates on ``[0, 1]`` s: ``u_k(t) = sum_j a_kj P_j(2t - 1)`` (Legendre
   polynomials of degree <= 3, random coefficients), of one of three kinds:

   ``same``
       ``u1`` keeps one sign: every joint ``th_2..th_n`` moves in the direction of ``phi``
       (the paper's family may reach these);
   ``opposite``
       ``u1`` changes sign once and the goal needs two of ``th_2..th_n`` to move in opposite
       directions (out of the family's reach);
   ``reversing``
       ``u1`` changes sign, whatever the joints' directions;

3. the ORIGINAL model integrated with scipy (DOP853, rtol 1e-10); the goal is kept only where
   every joint stays inside ``[PATH_MARGIN, pi/2 - PATH_MARGIN]`` on the whole path, the goal
   differs from the start by at least :data:`MIN_MOVE` in some joint, and (``opposite``) the
   directions do oppose.

The seed is fixed per ``(n, index)``: the same goals on every machine and run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import legendre
from scipy.integrate import solve_ivp

from .baselines.multiple_shooting import default_model

#: Distance (rad) of a start's joints from the region's bounds (3 deg).
START_MARGIN = math.radians(3.0)
#: Distance (rad) every joint of the generating path keeps from the bounds (1 deg).
PATH_MARGIN = math.radians(1.0)
#: Smallest change (rad) of some joint between start and goal (2 deg).
MIN_MOVE = math.radians(2.0)
#: Scale (rad/s) of the random rates' Legendre coefficients.
RATE_SCALE = 0.8
#: The kinds, in the order they are cycled through.
KINDS = ("same", "opposite", "reversing")
#: Goals per number of joints in the benchmark.
COUNTS = {3: 60, 4: 25, 5: 15, 6: 8, 7: 5, 8: 5}
BASE_SEED = 20261124


@dataclass(frozen=True)
class Goal:
    """One generated start/goal pair (rad).

    ``rates`` are the Legendre coefficients (rows ``u1``, ``u2``; argument ``2t - 1`` on
    ``[0, 1]`` s) of the inputs that produced the goal: a witness of its reachability that anyone
    can re-integrate (:func:`rates_at`).
    """

    name: str
    kind: str
    start: tuple[float, ...]
    goal: tuple[float, ...]
    rates: tuple[tuple[float, ...], ...] = ()

    @property
    def n(self) -> int:
        return len(self.start)


def _rhs(gains: np.ndarray, exps: np.ndarray, coef: np.ndarray):  # type: ignore[no-untyped-def]
    def f(t: float, q: np.ndarray) -> np.ndarray:
        u1 = legendre.legval(2.0 * t - 1.0, coef[0])
        u2 = legendre.legval(2.0 * t - 1.0, coef[1])
        dq = np.empty_like(q)
        dq[0], dq[1] = u1, u2
        dq[2:] = gains * np.cos(q[1:-1]) ** exps * u1
        return dq
    return f


def rates_at(g: Goal, t: float) -> np.ndarray:
    """``(u1, u2)`` of the inputs that generated ``g``, at ``t`` in ``[0, 1]`` s."""
    coef = np.asarray(g.rates, float)
    return np.array([legendre.legval(2.0 * t - 1.0, coef[0]),
                     legendre.legval(2.0 * t - 1.0, coef[1])])


def _rates(rng: np.random.Generator, kind: str) -> np.ndarray:
    """Legendre coefficients (2, 4) of ``u1, u2`` of the given kind."""
    c = rng.normal(0.0, RATE_SCALE, size=(2, 4)) / np.arange(1, 5)
    if kind == "same":
        # u1 = c0 + small ripple, one sign throughout
        c[0, 0] = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.0)
        c[0, 1:] *= 0.25 * abs(c[0, 0]) / max(np.sum(np.abs(c[0, 1:])), 1e-12)
    else:
        # a dominant odd term: u1 changes sign inside (0, 1)
        c[0, 1] = rng.choice([-1.0, 1.0]) * rng.uniform(0.6, 1.4)
        c[0, 0] = rng.uniform(-0.4, 0.4) * abs(c[0, 1])
    return c


def generate(n: int, count: int, seed: int = BASE_SEED) -> list[Goal]:
    """``count`` reachable goals for the default ``n``-joint robot, cycling through :data:`KINDS`."""
    gains, exps = (np.array(x, float) for x in default_model(n))
    out: list[Goal] = []
    index = 0
    while len(out) < count:
        kind = KINDS[len(out) % len(KINDS)]
        rng = np.random.default_rng([seed, n, index])
        index += 1
        if index > 200 * count:
            raise RuntimeError(f"could not generate {count} goals for n = {n}")
        th0 = rng.uniform(START_MARGIN, 0.5 * math.pi - START_MARGIN, size=n)
        coef = _rates(rng, kind)
        sol = solve_ivp(_rhs(gains, exps, coef), (0.0, 1.0), np.concatenate([[0.0], th0]),
                        method="DOP853", rtol=1e-10, atol=1e-12, dense_output=True)
        if not sol.success:
            continue
        th = sol.sol(np.linspace(0.0, 1.0, 2001))[1:].T
        if not (th.min() >= PATH_MARGIN and th.max() <= 0.5 * math.pi - PATH_MARGIN):
            continue
        goal = th[-1]
        d = goal - th0
        if np.max(np.abs(d)) < MIN_MOVE:
            continue
        rest = d[1:]
        opposed = bool(np.any(rest > 1e-6) and np.any(rest < -1e-6))
        if kind == "opposite" and not opposed:
            continue
        if kind == "same" and opposed:
            continue
        out.append(Goal(name=f"r{n}_{len(out):03d}_{kind}", kind=kind,
                        start=tuple(float(x) for x in th0), goal=tuple(float(x) for x in goal),
                        rates=tuple(tuple(float(c) for c in row) for row in coef)))
    return out


def benchmark_goals(counts: dict[int, int] | None = None) -> list[Goal]:
    """The benchmark's goals: :data:`COUNTS` per number of joints (or ``counts``)."""
    out: list[Goal] = []
    for n, k in (counts or COUNTS).items():
        out.extend(generate(n, k))
    return out
