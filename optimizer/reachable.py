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

3. the ORIGINAL model (:mod:`optimizer.dynamics`) integrated with scipy (DOP853, rtol 1e-10);
   the goal is kept only where every joint stays inside ``[PATH_MARGIN, pi/2 - PATH_MARGIN]``
   on the whole path, the goal differs from the start by at least :data:`MIN_MOVE` in some
   joint, and (``opposite``) the directions do oppose.

The seed is fixed per ``(seed, n, index)``: the same goals on every machine and run. Two
mechanisms with the same ``n`` get the same starts and the same input rates, hence goals that
differ only by what their transmissions make of the same inputs.

The benchmark (``bench/goals.py``) and the studies (:mod:`optimizer.studies`) both draw their
goals here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.polynomial import legendre
from scipy.integrate import solve_ivp

from .dynamics import field_numpy
from .model import Robot

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
BASE_SEED = 20261124
#: Draws allowed per requested goal before the generator gives up.
MAX_DRAWS_PER_GOAL = 200


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


def _rhs(robot: Robot, coef: np.ndarray) -> Callable[[float, np.ndarray], np.ndarray]:
    """The original model's ``q'`` under the Legendre rates ``coef``."""
    def f(t: float, q: np.ndarray) -> np.ndarray:
        x = 2.0 * t - 1.0
        u = (legendre.legval(x, coef[0]), legendre.legval(x, coef[1]))
        return field_numpy(robot.gains, robot.exponents, q, u)
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


def generate(n: int, count: int, seed: int = BASE_SEED, robot: Robot | None = None) -> list[Goal]:
    """``count`` reachable goals of an ``n``-joint robot, cycling through :data:`KINDS`.

    Parameters
    ----------
    n : int
        Number of joints.
    count : int
        Goals wanted (>= 0).
    seed : int
        Base seed; goal ``index`` draws from ``numpy.random.default_rng([seed, n, index])``.
    robot : Robot, optional
        The mechanism whose model makes the goals (default ``Robot.default(n)``); its ``n``
        must be ``n``.

    Returns
    -------
    list of Goal
        A prefix of a longer request with the same ``seed`` is the same goals.

    Raises
    ------
    ValueError
        ``count < 0``, ``robot.n != n``, or fewer than ``count`` goals found in
        ``MAX_DRAWS_PER_GOAL * count`` draws (a mechanism whose joints leave the region under
        almost any input).
    """
    if count < 0:
        raise ValueError(f"count = {count} must be >= 0")
    rob = Robot.default(n) if robot is None else robot
    if rob.n != n:
        raise ValueError(f"the robot has n = {rob.n} joints, not {n}")
    out: list[Goal] = []
    index = 0
    while len(out) < count:
        kind = KINDS[len(out) % len(KINDS)]
        rng = np.random.default_rng([seed, n, index])
        index += 1
        if index > MAX_DRAWS_PER_GOAL * count:
            raise ValueError(f"could not generate {count} reachable goals for n = {n} "
                             f"(found {len(out)} in {index - 1} draws)")
        th0 = rng.uniform(START_MARGIN, 0.5 * math.pi - START_MARGIN, size=n)
        coef = _rates(rng, kind)
        sol = solve_ivp(_rhs(rob, coef), (0.0, 1.0), np.concatenate([[0.0], th0]),
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
