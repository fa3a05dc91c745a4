"""Independent check of a plan on the ORIGINAL kinematic model (eq 1-3), and perturbed replays.

The chained form is only a means of planning: here the planned actuator inputs ``u(t)`` are
integrated on ``q' = g1(q) u1 + g2(q) u2`` with scipy (DOP853, tight tolerances), and the result
is compared with the goal and with the planned path.

Replays from a perturbed start (NOTES §7):

* ``u``-replay: the motors replay the planned ``u1(t), u2(t)`` (what open-loop hardware does);
* ``v``-replay: the chained inputs ``v1(t), v2(t)`` are pushed through eq (5) at the actual state.

Both stop at the first time a joint leaves the region (the transform, and for the v-replay the
input map, become singular there) and say so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.integrate import solve_ivp

from .chained_form import ChainedForm
from .model import Robot
from .steering import ChainedPath

RTOL = 1e-10
ATOL = 1e-12
HALF_PI = 0.5 * math.pi


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
    """

    t: np.ndarray
    q: np.ndarray
    final: np.ndarray
    singular: bool
    singular_time: float | None
    success: bool
    message: str
    energy: float = 0.0


@dataclass(frozen=True)
class Verification:
    """The plan's proof: the original model driven by the planned inputs.

    Attributes
    ----------
    terminal_error : float
        ``max_i |th_i(T) - goal_i|`` of the re-integrated model, rad.
    phi_error : float
        ``|phi(T) - (phi_start + dphi)|``, rad.
    max_deviation : float
        Largest ``|q_integrated(t) - q_planned(t)|`` over the samples, rad.
    singular : bool
        The planned or the re-integrated path touches the region's boundary.
    final : tuple of float
        ``q(T)`` of the re-integration.
    rtol, atol : float
        Integrator tolerances.
    energy : float
        Input energy ``integral of u1^2 + u2^2 dt``, integrated with the state.
    """

    terminal_error: float
    phi_error: float
    max_deviation: float
    singular: bool
    final: tuple[float, ...]
    rtol: float
    atol: float
    energy: float = 0.0


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
    K = np.array(robot.gains)
    m = np.array(robot.exponents)

    def rhs(t: float, x: np.ndarray) -> np.ndarray:
        # x = [q, energy]: the input energy is integrated with the state, to the same accuracy
        u = u_of_t(t, x[: n + 1])
        dx = np.empty_like(x)
        dx[0] = u[0]
        dx[1] = u[1]
        dx[2:n + 1] = K * np.cos(x[1:n]) ** m * u[0]
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
                  energy=energy if np.isfinite(energy) else 0.0)


class PlannedInputs:
    """The actuator inputs of a plan as functions of time, derived exactly from the chained path.

    ``u1(t) = v1(t)``, ``u2(t) = (v2(t) - L_g1 z2 v1(t)) / L_g2 z2`` evaluated on the planned
    state ``q(t) = Phi^-1(z(t))`` (eq 5): a function of time only, as the motors replay it.
    """

    def __init__(self, transform: ChainedForm, path: ChainedPath) -> None:
        self.cf = transform
        self.path = path
        self.T = path.inputs.duration
        inp = path.inputs
        # highest power first, for Horner's rule in u_scalar
        self._z_rev = [arr[:, ::-1].T.copy() for arr in path.polys]
        self._v_rev = [(inp.v1[s][::-1].copy(), inp.v2[s][::-1].copy()) for s in range(inp.pieces)]
        self._breaks = inp.breaks
        self._u_fn = transform.symbolic.u_from_zv

    def q(self, t: np.ndarray) -> np.ndarray:
        inv = self.cf.from_chained(self.path.z(np.asarray(t, float) / self.T))
        return inv.q

    def v(self, t: np.ndarray) -> np.ndarray:
        return self.path.inputs.v(t)

    def u(self, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, float))
        return self.cf.u_from_v(self.q(t), self.v(t))

    def u_scalar(self, t: float, _q: np.ndarray | None = None) -> np.ndarray:
        """``u(t)`` for one time: the same mathematics as :meth:`u` (exact polynomial z and v,
        the inverse map and eq 5), evaluated without batching overhead for the integrator."""
        tau = t / self.T
        s = int(np.searchsorted(self._breaks, tau, side="right")) - 1
        s = min(max(s, 0), len(self._z_rev) - 1)
        x = tau - self._breaks[s]
        zc = self._z_rev[s]
        z = zc[0].copy()
        for row in zc[1:]:
            z = z * x + row
        c1, c2 = self._v_rev[s]
        v1 = 0.0
        for c in c1:
            v1 = v1 * x + c
        v2 = 0.0
        for c in c2:
            v2 = v2 * x + c
        u = np.asarray(self._u_fn(z, np.array([v1, v2]))).ravel() / self.T
        if not np.all(np.isfinite(u)):
            raise FloatingPointError(f"the planned path is singular at t = {t:.6g} s")
        return u


def verify_plan(robot: Robot, inputs: PlannedInputs, q_start: np.ndarray, q_goal_th: np.ndarray,
                phi_goal: float, t_samples: np.ndarray, q_planned: np.ndarray) -> Verification:
    """Integrate the original model under the planned ``u(t)`` and compare with goal and plan."""
    rep = integrate(robot, inputs.u_scalar, q_start, inputs.T, t_samples)
    if not rep.success:  # no proof at all: never within any tolerance
        th_err = phi_err = dev = float("inf")
    else:
        th_err = float(np.max(np.abs(rep.final[1:] - q_goal_th)))
        phi_err = abs(float(rep.final[0]) - phi_goal)
        dev = float(np.max(np.abs(rep.q - q_planned)))
    return Verification(terminal_error=th_err, phi_error=phi_err, max_deviation=dev,
                        singular=bool(rep.singular), final=tuple(float(x) for x in rep.final),
                        rtol=RTOL, atol=ATOL, energy=rep.energy)


def replay(robot: Robot, inputs: PlannedInputs, q0: np.ndarray, mode: str,
           t_samples: np.ndarray) -> Replay:
    """Run the plan open loop from a (perturbed) start: ``mode`` is ``"u"`` or ``"v"``."""
    if mode == "u":
        return integrate(robot, inputs.u_scalar, q0, inputs.T, t_samples)
    if mode == "v":
        cf = inputs.cf

        def u_v(t: float, q: np.ndarray) -> np.ndarray:
            v = inputs.v(np.array([t]))[0]
            al, be = cf.input_coefficients(q)
            return np.array([v[0], (v[1] - al * v[0]) / be])
        return integrate(robot, u_v, q0, inputs.T, t_samples)
    raise ValueError(f"replay mode must be 'u' or 'v', not {mode!r}")
