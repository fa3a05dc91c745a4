"""The gains of a plant estimated from its measured motion.

A plan is computed on the model ``th_i' = K_i cos(th_{i-1})^{m_i} u1`` (``i >= 2``); a real
arm's friction disks transmit a little more or less than the catalogue's ``K_i``. Closed loop,
the replanner starts every continuation from the measured state, but it plans on the model, and
the plant's gain error acts again on every continuation: with gains 5 % off, the motion left
after the last replan decides the miss. The encoders that give the state also give what the
gains are.

Between two measurements ``(t_a, q_a)`` and ``(t_b, q_b)`` the plant moved under the rates the
controller commanded, ``u(t)``. Joint ``i >= 2`` then moved by

    th_i(t_b) - th_i(t_a) = K_i I_i,    I_i = int_{t_a}^{t_b} cos(th_{i-1}(t))^{m_i} u1(t) dt,

along the plant's own path. ``phi`` and ``th_1`` are driven directly; ``th_{i-1}(t)`` is not
measured between the two instants, so it is taken from the model with the gains being
estimated, from ``q_a`` under ``u``: the gains of one period are the fixed point of
``K_i = Delta th_i / I_i(K)``. ``I_i`` depends on ``K`` only through the path of
``th_{i-1}``, a change of a few percent of a period's short motion, so the fixed point is
found in two or three rounds (:data:`ROUNDS`; measured: the first round leaves 1e-4 relative,
the third 1e-11). Over many periods the estimate is the least-squares one,
``K_i = sum I_i Delta_i / sum I_i^2``: a period in which ``u1`` barely moves weighs nothing,
and measurement noise averages out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.integrate import solve_ivp

from .dynamics import vector_field
from .errors import NumericalError
from .model import Robot

#: Fixed-point rounds per period (each one integration of the period).
ROUNDS = 3
#: Relative tolerance of the period's integration (scipy's DOP853; ``atol`` a hundredth).
RTOL = 1e-11
#: A period whose ``|I_i|`` is below this (rad) tells nothing of ``K_i``.
MIN_MOTION = 1e-9
#: A period whose own gains lie further than this (relative) from the model's is not taken:
#: a friction disk is not off by half, an encoder glitch is.
MAX_RELATIVE_ERROR = 0.5


def period_integrals(exponents: Sequence[int], gains: np.ndarray, q_a: np.ndarray,
                     rates: Callable[[float], np.ndarray], t_a: float, t_b: float,
                     breaks: Sequence[float] | np.ndarray = ()) -> tuple[np.ndarray, np.ndarray]:
    """The model with ``gains`` from ``q_a`` under ``rates(t)`` over ``[t_a, t_b]``: its end
    state and the integrals ``I_i = int cos(th_{i-1})^{m_i} u1 dt`` (``i = 2..n``).

    ``breaks``: times inside the period where the rates are not smooth (integrated between).

    Raises
    ------
    NumericalError
        The integration failed.
    """
    K = [float(k) for k in gains]
    gains_arr = np.asarray(K)
    n1 = len(K) + 2

    def rhs(t: float, y: np.ndarray) -> np.ndarray:
        u = rates(t)
        q = y[:n1]
        dq = np.asarray(vector_field(K, exponents, q, u[0], u[1]), float)
        return np.concatenate([dq, dq[2:] / gains_arr])   # I_i' = th_i' / K_i

    edges = np.unique(np.concatenate([[t_a, t_b], [b for b in breaks if t_a < b < t_b]]))
    y = np.concatenate([np.asarray(q_a, float), np.zeros(len(K))])
    for a, b in zip(edges[:-1], edges[1:]):
        sol = solve_ivp(rhs, (a, b), y, method="DOP853", rtol=RTOL, atol=RTOL * 1e-2)
        if not sol.success:
            raise NumericalError(f"the identification's integration failed: {sol.message}")
        y = sol.y[:, -1]
    return y[:n1], y[n1:]


@dataclass
class GainEstimator:
    """Least-squares estimate of a plant's ``K_2..K_n`` from its measured periods.

    Parameters
    ----------
    robot : Robot
        The model: its exponents, and its gains as the estimate before any motion.

    Attributes
    ----------
    gains : ndarray
        The current estimate.
    periods : int
        Periods that informed it.
    """

    robot: Robot
    gains: np.ndarray = field(init=False)
    periods: int = field(init=False, default=0)
    _s_id: np.ndarray = field(init=False, repr=False)
    _s_ii: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.gains = np.asarray(self.robot.gains, float).copy()
        self._s_id = np.zeros_like(self.gains)
        self._s_ii = np.zeros_like(self.gains)

    def update(self, q_a: np.ndarray, q_b: np.ndarray, rates: Callable[[float], np.ndarray],
               t_a: float, t_b: float, breaks: Sequence[float] | np.ndarray = ()) -> np.ndarray:
        """Take the period from the measured ``q_a`` at ``t_a`` to the measured ``q_b`` at
        ``t_b`` under the commanded ``rates(t)`` (``breaks``: see :func:`period_integrals`);
        returns the new estimate. A joint whose period gives gains more than
        :data:`MAX_RELATIVE_ERROR` off the model's keeps its estimate (the period is not
        taken for it)."""
        delta = np.asarray(q_b, float)[2:] - np.asarray(q_a, float)[2:]
        nominal = np.asarray(self.robot.gains, float)
        K = self.gains.copy()
        I = np.zeros_like(K)
        taken = np.zeros(K.shape, bool)
        for _ in range(ROUNDS):
            _, I = period_integrals(self.robot.exponents, K, q_a, rates, t_a, t_b, breaks)
            moved = np.abs(I) > MIN_MOTION
            own = delta / np.where(moved, I, 1.0)
            # (an implausible joint keeps its estimate, so that the next joint's path is right)
            taken = moved & (np.abs(own / nominal - 1.0) <= MAX_RELATIVE_ERROR)
            K = np.where(taken, own, self.gains)
        self._s_id += np.where(taken, I * delta, 0.0)
        self._s_ii += np.where(taken, I * I, 0.0)
        known = self._s_ii > 0.0
        estimate = np.where(known, self._s_id / np.where(known, self._s_ii, 1.0), self.gains)
        if np.all(np.isfinite(estimate)) and np.all(estimate > 0.0):
            self.gains = estimate
            self.periods += 1
        return self.gains.copy()


__all__ = ["GainEstimator", "MAX_RELATIVE_ERROR", "MIN_MOTION", "ROUNDS", "RTOL",
           "period_integrals"]
