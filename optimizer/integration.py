"""Integration of the ORIGINAL kinematic model (eq 1-3) by scipy's DOP853, and its outcome.

:func:`integrate` takes any ``u(t, q)`` (also state feedback: the v-replay) and stops where a
joint ``th_1..th_{n-1}`` leaves ``(0, pi/2)``; :class:`Replay` is the outcome shared by every
integrator of the model (this one, :func:`optimizer.cascade.integrate_cascade`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.integrate import solve_ivp

from .dynamics import vector_field
from .model import Robot

RTOL = 1e-10
ATOL = 1e-12
HALF_PI = 0.5 * math.pi
#: Integrator names reported in :class:`Replay` and :class:`optimizer.verify.Verification`.
CASCADE_NAME = "cascade-chebyshev"
DOP853_NAME = "DOP853"


@dataclass(frozen=True)
class Replay:
    """Outcome of integrating the original model under some inputs.

    Attributes
    ----------
    t : ndarray (N,)
    q : ndarray (N, n+1)
        States at ``t`` (rows after a singular stop repeat the last state reached).
    final : ndarray (n+1,)
    singular : bool
        A joint ``th_1..th_{n-1}`` reached 0 or pi/2 before T.
    singular_time : float or None
    success : bool
        The integrator finished (or stopped at the singular event) without error.
    message : str
    energy : float
        ``integral of u1^2 + u2^2 dt`` over the integrated span (rad^2/s).
    integrator : str
        :data:`DOP853_NAME` or :data:`CASCADE_NAME`.
    error_estimate : float or None
        Cascade only: the estimated largest error of any state (rad) and of the energy
        (relative), whichever is larger. ``None`` for DOP853 (it controls local errors only).
    evaluations : int
        Number of input evaluations ``u(t)``.
    panels : int
        Cascade only: quadrature panels after refinement.
    mesh_t, mesh_q : ndarray or None
        Cascade only: the quadrature's own mesh in time order, every panel's start and its
        Chebyshev nodes, then ``T`` (``(M,)``, ``(M, n+1)``): states computed directly, not
        interpolated, and clustered toward the panel ends, where the inputs jump.

    Notes
    -----
    DOP853 stops at a singular event and repeats the last state after it. The cascade integrates
    the whole span (the model itself is defined everywhere; only the chained transform is
    singular) and flags ``singular`` at the first node or sample outside the region.
    """

    t: np.ndarray
    q: np.ndarray
    final: np.ndarray
    singular: bool
    singular_time: float | None
    success: bool
    message: str
    energy: float = 0.0
    integrator: str = DOP853_NAME
    error_estimate: float | None = None
    evaluations: int = 0
    panels: int = 0
    mesh_t: np.ndarray | None = None
    mesh_q: np.ndarray | None = None


def _singular_events(n: int) -> list[Callable[..., float]]:
    events: list[Callable[..., float]] = []
    for i in range(1, n):
        def lo(t: float, q: np.ndarray, i: int = i) -> float:
            return float(q[i])

        def hi(t: float, q: np.ndarray, i: int = i) -> float:
            return float(HALF_PI - q[i])
        for ev in (lo, hi):
            ev.terminal = True  # type: ignore[attr-defined]
            ev.direction = -1  # type: ignore[attr-defined]
            events.append(ev)
    return events


def integrate(robot: Robot, u_of_t: Callable[[float, np.ndarray], np.ndarray], q0: np.ndarray,
              duration: float, t_eval: np.ndarray, rtol: float = RTOL, atol: float = ATOL
              ) -> Replay:
    """Integrate the original model ``q' = g1(q) u1 + g2(q) u2`` from ``q0`` over [0, T].

    Parameters
    ----------
    u_of_t : callable ``(t, q) -> [u1, u2]``
        Open-loop inputs ignore ``q``; the v-replay uses it.
    """
    n = robot.n
    gains, exponents = robot.gains, robot.exponents

    def rhs(t: float, x: np.ndarray) -> np.ndarray:
        # x = [q, energy]: the input energy is integrated with the state, to the same accuracy
        u = u_of_t(t, x[: n + 1])
        dx = np.empty_like(x)
        dx[: n + 1] = vector_field(gains, exponents, x, u[0], u[1])
        dx[n + 1] = u[0] * u[0] + u[1] * u[1]
        return dx

    x0 = np.concatenate([np.asarray(q0, float), [0.0]])
    try:
        sol = solve_ivp(rhs, (0.0, duration), x0, method="DOP853", rtol=rtol, atol=atol,
                        dense_output=True, events=_singular_events(n))
    except FloatingPointError as exc:  # the inputs themselves became singular
        return Replay(t=t_eval, q=np.zeros((t_eval.size, n + 1)), final=np.zeros(n + 1),
                      singular=True, singular_time=None, success=False, message=str(exc),
                      energy=0.0)
    t_end = float(sol.t[-1])
    singular = sol.status == 1
    tt = np.minimum(t_eval, t_end)
    xs = sol.sol(tt).T if sol.sol is not None else np.tile(sol.y[:, -1], (t_eval.size, 1))
    q = np.where(np.isfinite(xs[:, : n + 1]), xs[:, : n + 1], 0.0)
    final = sol.y[: n + 1, -1].copy()
    energy = float(sol.y[n + 1, -1])
    ok = sol.status >= 0 and bool(np.all(np.isfinite(final)))
    return Replay(t=t_eval, q=q, final=np.where(np.isfinite(final), final, 0.0),
                  singular=bool(singular), singular_time=t_end if singular else None,
                  success=ok, message=str(sol.message),
                  energy=energy if np.isfinite(energy) else 0.0, evaluations=int(sol.nfev))

