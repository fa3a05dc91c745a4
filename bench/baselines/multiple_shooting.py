"""Direct multiple-shooting baseline planner (CasADi + IPOPT).

This is the planner a user would typically write *instead of* our service: a
textbook direct multiple-shooting transcription of the **original** kinematic
model of the underactuated manipulator, solved with IPOPT.

Model (``n`` joints, ``n >= 3``), state ``q = [phi, th1, ..., thn]``, inputs
``u = [u1, u2]``::

    phi'  = u1
    th1'  = u2
    th_i' = K_i * cos(th_{i-1})**m_i * u1        for i = 2..n

Transcription
-------------
* ``N`` intervals of equal length ``h = T / N`` over a fixed duration ``T``.
* Piecewise-constant inputs ``u1, u2`` on every interval.
* Each interval is integrated with ``rk4_substeps`` classical RK4 steps.
* Continuity constraints ``q_{k+1} = F(q_k, u_k)`` at every node.
* ``q_0 = [phi_start, start_th]``; exact goal ``th1..thn`` at ``t = T``
  (``phi(T)`` is free).
* ``th1 .. th_{n-1}`` are kept inside the box ``box_deg`` (default
  ``[0.5, 89.5]`` deg) at every node.  This is the region where the chained-form
  transform used by our planner is invertible; ``th_n`` is unconstrained except
  for its goal.  (The box is enforced at the nodes only, as usual for multiple
  shooting.)
* Objective (``objective``): ``"energy"`` (the default), minimum input energy
  ``sum_k (u1_k**2 + u2_k**2) * h``; or ``"min_max_deviation"``, the smallest largest
  squared distance of a node's ``(th1..thn)`` from the straight segment start -> goal
  in joint space (the planner's ``deviation``) (an epigraph variable ``S >= dist_k^2`` at every node, minimised), plus
  :data:`MIN_MAX_ENERGY_WEIGHT` times the energy, which only makes the inputs unique. This
  is the peer a user who wants the straightest path would write (issue 26).

The NLP is built once, parametrised by ``phi_start``, the start and the goal
(CasADi parameters), so repeated :meth:`MultipleShootingBaseline.solve` calls
reuse the same solver object.

All quantities are in radians and seconds.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "PROTOTYPE_GAINS",
    "PROTOTYPE_EXPONENTS",
    "BaselineResult",
    "MultipleShootingBaseline",
    "default_model",
]

#: Gains ``(K2, K3)`` of the 3-joint prototype.
PROTOTYPE_GAINS: tuple[float, float] = (0.88658, 0.7115)
#: Exponents ``(m2, m3)`` of the 3-joint prototype.
PROTOTYPE_EXPONENTS: tuple[float, float] = (2, 3)

#: IPOPT return statuses counted as success.
_SUCCESS_STATUSES = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level"})

#: Default IPOPT options (silent, wall-time limited).
_DEFAULT_IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0,
    "sb": "yes",
    "max_wall_time": 30.0,
}

#: The objectives :class:`MultipleShootingBaseline` offers (see the module docstring).
OBJECTIVES = ("energy", "min_max_deviation")
#: Weight of the input energy in the ``min_max_deviation`` objective: small against the
#: squared deviation (rad^2), so that the largest deviation decides; not 0 (the inputs of
#: the intervals whose nodes are not the farthest would be undetermined).
MIN_MAX_ENERGY_WEIGHT = 1e-4

#: Net rotation of ``phi`` (rad) assumed by the initial guess when the goal
#: does not suggest anything better (see :meth:`MultipleShootingBaseline.initial_guess`).
GUESS_PHI_TRAVEL = 0.6


def default_model(n: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Default gains and exponents for an ``n``-joint manipulator.

    Parameters
    ----------
    n : int
        Number of joints (``n >= 3``).

    Returns
    -------
    gains : tuple of float
        ``(K_2, ..., K_n)``: ``K_i = 0.88658`` for ``i < n`` and ``K_n = 0.7115``.
    exponents : tuple of float
        ``(m_2, ..., m_n)``: ``m_i = 2`` for ``i < n`` and ``m_n = 3``.

    Raises
    ------
    ValueError
        If ``n < 3``.
    """
    if n < 3:
        raise ValueError(f"n must be >= 3, got {n}")
    gains = (PROTOTYPE_GAINS[0],) * (n - 2) + (PROTOTYPE_GAINS[1],)
    exponents = (PROTOTYPE_EXPONENTS[0],) * (n - 2) + (PROTOTYPE_EXPONENTS[1],)
    return gains, exponents


@dataclass
class BaselineResult:
    """Outcome of one multiple-shooting solve.

    Attributes
    ----------
    success : bool
        ``True`` iff IPOPT reported ``Solve_Succeeded`` or
        ``Solved_To_Acceptable_Level``.
    return_status : str
        IPOPT's return status string.
    build_time : float
        Seconds spent building the NLP and the solver object (``nlpsol``).
        This is paid once per :class:`MultipleShootingBaseline` instance and is
        repeated in every result it returns.
    solve_time : float
        Seconds spent in the solver call alone.
    t_grid : numpy.ndarray
        ``(N + 1,)`` node times.
    q_nodes : numpy.ndarray
        ``(N + 1, n + 1)`` states ``[phi, th1, ..., thn]`` at the nodes.
    u : numpy.ndarray
        ``(N, 2)`` piecewise-constant inputs ``[u1, u2]``, one row per interval.
    duration : float
        Trajectory duration ``T`` in seconds.
    objective : float
        Final objective value (input energy, or the ``min_max_deviation`` objective).
    iterations : int
        Number of IPOPT iterations (``-1`` if unavailable).
    """

    success: bool
    return_status: str
    build_time: float
    solve_time: float
    t_grid: np.ndarray
    q_nodes: np.ndarray
    u: np.ndarray
    duration: float
    objective: float = field(default=float("nan"))
    iterations: int = field(default=-1)

    def u_of_t(self, t: float) -> np.ndarray:
        """Piecewise-constant input at time ``t``.

        The input is right-continuous: at a node time ``t_k`` the input of the
        interval ``[t_k, t_{k+1})`` is returned.  Times before ``0`` use the
        first interval and times at or after ``T`` use the last one.

        Parameters
        ----------
        t : float
            Time in seconds.

        Returns
        -------
        numpy.ndarray
            ``(2,)`` input ``[u1, u2]``.
        """
        k = int(np.searchsorted(self.t_grid, t, side="right")) - 1
        k = min(max(k, 0), self.u.shape[0] - 1)
        return self.u[k].copy()


class MultipleShootingBaseline:
    """Direct multiple-shooting planner on the original model (CasADi + IPOPT).

    Parameters
    ----------
    gains : sequence of float
        ``(K_2, ..., K_n)``; its length fixes ``n = len(gains) + 1 >= 3``.
    exponents : sequence of float
        ``(m_2, ..., m_n)``, same length as ``gains``.
    intervals : int, optional
        Number of shooting intervals ``N`` (default 50).
    rk4_substeps : int, optional
        RK4 steps per interval (default 4).
    duration : float, optional
        Fixed duration ``T`` in seconds (default 1).
    box_deg : tuple of float, optional
        ``(low, high)`` bounds in **degrees** for ``th1 .. th_{n-1}`` at every
        node (default ``(0.5, 89.5)``).
    ipopt_options : mapping, optional
        IPOPT options (plain IPOPT names, without the ``ipopt.`` prefix) that
        override the defaults ``print_level=0``, ``sb="yes"``,
        ``max_wall_time=30``.
    objective : {"energy", "min_max_deviation"}, optional
        What is minimised (see the module docstring); default ``"energy"``.

    Attributes
    ----------
    n : int
        Number of joints.
    build_time : float
        Seconds spent building the NLP and the ``nlpsol`` object.
    """

    def __init__(
        self,
        gains: Sequence[float],
        exponents: Sequence[float],
        intervals: int = 50,
        rk4_substeps: int = 4,
        duration: float = 1.0,
        box_deg: tuple[float, float] = (0.5, 89.5),
        ipopt_options: Mapping[str, Any] | None = None,
        objective: str = "energy",
    ) -> None:
        gains = tuple(float(k) for k in gains)
        exponents = tuple(float(m) for m in exponents)
        if len(gains) < 2:
            raise ValueError("need at least 2 gains (n >= 3 joints)")
        if len(exponents) != len(gains):
            raise ValueError("gains and exponents must have the same length")
        if intervals < 1 or rk4_substeps < 1:
            raise ValueError("intervals and rk4_substeps must be >= 1")
        if not duration > 0:
            raise ValueError("duration must be positive")
        if not box_deg[0] < box_deg[1]:
            raise ValueError("box_deg must be (low, high) with low < high")
        if objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, not {objective!r}")
        self.objective = objective

        self.gains = gains
        self.exponents = exponents
        self.n = len(gains) + 1
        self.intervals = int(intervals)
        self.rk4_substeps = int(rk4_substeps)
        self.duration = float(duration)
        self.box = (math.radians(box_deg[0]), math.radians(box_deg[1]))
        self.h = self.duration / self.intervals
        self.t_grid = np.linspace(0.0, self.duration, self.intervals + 1)

        ipopt = dict(_DEFAULT_IPOPT_OPTIONS)
        if ipopt_options:
            ipopt.update(ipopt_options)
        self.ipopt_options = ipopt

        t0 = time.perf_counter()
        self._build()
        self.build_time = time.perf_counter() - t0

    # ------------------------------------------------------------------ model
    def rhs(self, q: Any, u: Any) -> Any:
        """Right-hand side of the original model (CasADi or NumPy).

        Parameters
        ----------
        q : casadi.SX or array_like
            State ``[phi, th1, ..., thn]``.
        u : casadi.SX or array_like
            Input ``[u1, u2]``.

        Returns
        -------
        casadi.SX
            ``q'`` as a column vector.
        """
        dq = [u[0], u[1]]
        for i in range(2, self.n + 1):  # joint index i = 2..n
            k, m = self.gains[i - 2], self.exponents[i - 2]
            dq.append(k * ca.cos(q[i - 1]) ** m * u[0])
        return ca.vertcat(*dq)

    def _build(self) -> None:
        """Build the NLP and the IPOPT solver object (called once)."""
        n, N, M = self.n, self.intervals, self.rk4_substeps
        nx = n + 1

        # One interval of RK4 with M substeps, as a CasADi function.
        xs, us = ca.SX.sym("x", nx), ca.SX.sym("u", 2)
        dt = self.h / M
        x = xs
        for _ in range(M):
            k1 = self.rhs(x, us)
            k2 = self.rhs(x + dt / 2 * k1, us)
            k3 = self.rhs(x + dt / 2 * k2, us)
            k4 = self.rhs(x + dt * k3, us)
            x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        self._step = ca.Function("rk4_interval", [xs, us], [x])

        X = ca.SX.sym("X", nx, N + 1)
        U = ca.SX.sym("U", 2, N)
        # p = [phi_start, start_th (n), goal_th (n)]
        P = ca.SX.sym("p", 1 + 2 * n)
        phi0, th0, thg = P[0], P[1 : 1 + n], P[1 + n :]

        rows = [X[:, 0] - ca.vertcat(phi0, th0)]
        rows += [X[:, k + 1] - self._step(X[:, k], U[:, k]) for k in range(N)]
        rows.append(X[1:, N] - thg)
        energy = self.h * ca.sumsqr(U)
        w = ca.vertcat(ca.vec(X), ca.vec(U))
        n_eq = sum(int(r.shape[0]) for r in rows)
        if self.objective == "min_max_deviation":
            # S >= squared distance of every interior node from the line start -> goal
            S = ca.SX.sym("S")
            ell = thg - th0
            nrm = ca.fmax(ca.sumsqr(ell), 1e-300)
            for k in range(1, N):
                d = X[1:, k] - th0
                along = ca.fmin(ca.fmax(ca.dot(d, ell) / nrm, 0.0), 1.0)
                rows.append(ca.sumsqr(d - along * ell) - S)
            f = S + MIN_MAX_ENERGY_WEIGHT * energy
            w = ca.vertcat(w, S)
        else:
            f = energy
        g = ca.vertcat(*rows)
        self._ng = g.shape[0]
        self._lbg = np.zeros(self._ng)
        self._lbg[n_eq:] = -np.inf

        # Variable bounds: th1..th_{n-1} in the box at every node.
        lbX = np.full((nx, N + 1), -np.inf)
        ubX = np.full((nx, N + 1), np.inf)
        lbX[1:n, :] = self.box[0]
        ubX[1:n, :] = self.box[1]
        extra = 1 if self.objective == "min_max_deviation" else 0
        self._lbw = np.concatenate([lbX.ravel(order="F"), np.full(2 * N, -np.inf),
                                    np.zeros(extra)])
        self._ubw = np.concatenate([ubX.ravel(order="F"), np.full(2 * N, np.inf),
                                    np.full(extra, np.inf)])
        self._nX = nx * (N + 1)

        opts: dict[str, Any] = {
            "ipopt": dict(self.ipopt_options),
            "print_time": False,
            "error_on_fail": False,
        }
        self._solver = ca.nlpsol(
            "ms_baseline", "ipopt", {"x": w, "p": P, "f": f, "g": g}, opts
        )

    # ---------------------------------------------------------- initial guess
    def initial_guess(
        self, start_th: np.ndarray, goal_th: np.ndarray, phi_start: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Initial guess for the node states and the inputs.

        ``th`` is interpolated linearly from start to goal, ``phi`` linearly from
        ``phi_start`` to ``phi_start + GUESS_PHI_TRAVEL`` and the inputs are the
        constants consistent with those straight lines:
        ``u1 = GUESS_PHI_TRAVEL / T`` and ``u2 = (goal_th1 - start_th1) / T``.

        Parameters
        ----------
        start_th, goal_th : numpy.ndarray
            ``(n,)`` start and goal joint angles (rad).
        phi_start : float
            Initial ``phi`` (rad).

        Returns
        -------
        X0 : numpy.ndarray
            ``(n + 1, N + 1)`` guessed node states.
        U0 : numpy.ndarray
            ``(2, N)`` guessed inputs.
        """
        N, T = self.intervals, self.duration
        s = self.t_grid / T
        X0 = np.empty((self.n + 1, N + 1))
        X0[0] = phi_start + GUESS_PHI_TRAVEL * s
        X0[1:] = start_th[:, None] + np.outer(goal_th - start_th, s)
        U0 = np.empty((2, N))
        U0[0] = GUESS_PHI_TRAVEL / T
        U0[1] = (goal_th[0] - start_th[0]) / T
        return X0, U0

    # ------------------------------------------------------------------ solve
    def solve(
        self, start_th: ArrayLike, goal_th: ArrayLike, phi_start: float = 0.0
    ) -> BaselineResult:
        """Plan from ``start_th`` to ``goal_th`` in the fixed duration.

        Parameters
        ----------
        start_th : array_like
            ``(n,)`` start joint angles ``th1..thn`` (rad).
        goal_th : array_like
            ``(n,)`` goal joint angles ``th1..thn`` (rad); ``phi`` is free at the end.
        phi_start : float, optional
            Initial ``phi`` (rad), default 0.

        Returns
        -------
        BaselineResult
            The solution (also returned, with ``success=False``, when IPOPT fails).

        Raises
        ------
        ValueError
            If the shapes are wrong, or if ``th1..th_{n-1}`` of the start or the
            goal lie outside the box (the problem would be trivially infeasible).
        """
        n, N = self.n, self.intervals
        start = np.asarray(start_th, dtype=float).reshape(-1)
        goal = np.asarray(goal_th, dtype=float).reshape(-1)
        if start.shape != (n,) or goal.shape != (n,):
            raise ValueError(f"start_th and goal_th must have shape ({n},)")
        lo, hi = self.box
        for name, th in (("start_th", start), ("goal_th", goal)):
            inner = th[: n - 1]
            if np.any(inner < lo) or np.any(inner > hi):
                raise ValueError(
                    f"{name}: th1..th{n - 1} must lie in "
                    f"[{math.degrees(lo)}, {math.degrees(hi)}] deg"
                )

        X0, U0 = self.initial_guess(start, goal, float(phi_start))
        w0 = np.concatenate([X0.ravel(order="F"), U0.ravel(order="F")])
        if self.objective == "min_max_deviation":
            w0 = np.concatenate([w0, [1e-4]])
        p = np.concatenate([[float(phi_start)], start, goal])

        t0 = time.perf_counter()
        sol = self._solver(
            x0=w0, p=p, lbx=self._lbw, ubx=self._ubw, lbg=self._lbg, ubg=0.0
        )
        solve_time = time.perf_counter() - t0

        stats = self._solver.stats()
        status = str(stats.get("return_status", "unknown"))
        w = np.asarray(sol["x"]).reshape(-1)
        X = w[: self._nX].reshape((n + 1, N + 1), order="F")
        U = w[self._nX : self._nX + 2 * N].reshape((2, N), order="F")
        return BaselineResult(
            success=status in _SUCCESS_STATUSES,
            return_status=status,
            build_time=self.build_time,
            solve_time=solve_time,
            t_grid=self.t_grid.copy(),
            q_nodes=X.T.copy(),
            u=U.T.copy(),
            duration=self.duration,
            objective=float(sol["f"]),
            iterations=int(stats.get("iter_count", -1)),
        )
