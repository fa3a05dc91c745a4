"""Independent check of a plan on the ORIGINAL kinematic model (eq 1-3), and perturbed replays.

The chained form is only a means of planning: here the planned actuator inputs ``u(t)`` are
integrated on ``q' = g1(q) u1 + g2(q) u2`` and the result is compared with the goal and with the
planned path.

Two integrators:

* :func:`integrate_cascade` (the default of :func:`verify_plan`). The model is a cascade,
  ``phi' = u1, th1' = u2, th_i' = K_i cos(th_{i-1})^{m_i} u1``, and the planned inputs are known
  functions of time: each state is a plain integral of a known function once the joint before it
  is known. It is computed by Chebyshev (Fejer) cumulative quadrature on panels aligned with the
  input schedule's breaks, refined adaptively until the estimated error (tails of the Chebyshev
  coefficients, propagated down the cascade) is below :data:`CASCADE_TOL`. No time stepping: a
  few hundred vectorised input evaluations instead of ~460 scalar ones, ~0.3 ms instead of
  ~25 ms per plan.
* :func:`integrate` (scipy DOP853, rtol 1e-10): any ``u(t, q)``, also state feedback. The
  cascade falls back to it when its estimate cannot be met, and the replays use it (the
  v-replay is not open loop).

Replays from a perturbed start (NOTES §7):

* ``u``-replay: the motors replay the planned ``u1(t), u2(t)`` (what open-loop hardware does);
* ``v``-replay: the chained inputs ``v1(t), v2(t)`` are pushed through eq (5) at the actual state.

Both stop at the first time a joint leaves the region (the transform, and for the v-replay the
input map, become singular there) and say so.

The integrators live in :mod:`optimizer.integration` (DOP853, :class:`Replay`) and
:mod:`optimizer.cascade` (the cascade quadrature); their names are re-exported here.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .cascade import (CASCADE_ACCEPT, CASCADE_INITIAL_PANELS,  # noqa: F401 (re-exported)
                      CASCADE_INITIAL_WIDTH, CASCADE_MAX_PANELS, CASCADE_MAX_ROUNDS,
                      CASCADE_NODES, CASCADE_NOISE, CASCADE_PLATEAU, CASCADE_SPLIT,
                      CASCADE_TAIL, CASCADE_TOL, integrate_cascade)
from .chained_form import ChainedForm
from .integration import (ATOL, CASCADE_NAME, DOP853_NAME, HALF_PI,  # noqa: F401
                          RTOL, Replay, integrate)
from .model import Robot
from .steering import ChainedPath


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
        Tolerances. DOP853: its relative and absolute local tolerances. Cascade: the target
        of its error estimate (:data:`CASCADE_TOL`), relative for the energy (``rtol``) and
        absolute for the states (``atol``, rad); the achieved value is ``error_estimate``.
    energy : float
        Input energy ``integral of u1^2 + u2^2 dt``, integrated with the state.
    integrator : str
        Which integrator produced the proof: ``"cascade-chebyshev"`` or ``"DOP853"`` (also when
        the cascade fell back to it).
    error_estimate : float or None
        Cascade: the estimated error of the re-integration (rad on the states, samples
        included; relative on the energy). At most ``atol``, except when the inputs' own
        rounding noise (near the region's edges) keeps it above: then at most
        :data:`CASCADE_ACCEPT` (1e-8), else DOP853 ran. ``None`` for DOP853 (it controls
        local errors only).
    """

    terminal_error: float
    phi_error: float
    max_deviation: float
    singular: bool
    final: tuple[float, ...]
    rtol: float
    atol: float
    energy: float = 0.0
    integrator: str = DOP853_NAME
    error_estimate: float | None = None


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
        self._breaks = inp.breaks
        # the inner breaks: the piece of tau is searchsorted(inner, tau, "right"), as
        # InputSchedule.piece_index (right-continuous, the last piece closed)
        self._inner = inp.breaks[1:-1]
        # for u(t): rows [z_1..z_{n+1}, V1, V2] of every piece, shape (L, S, n+3), highest power
        # first, zero-padded to one degree L (a leading zero leaves Horner's values unchanged,
        # bit for bit): one Horner pass evaluates the state and the inputs of all pieces together
        polys = path.polys
        nz = path.z0.size
        pieces = len(polys)
        lz = max(c.shape[1] for c in polys)
        l1 = max(c.size for c in inp.v1)
        l2 = max(c.size for c in inp.v2)
        c = np.zeros((max(lz, l1, l2), pieces, nz + 2))
        if all(a.shape[1] == lz for a in polys) and all(a.size == l1 for a in inp.v1) \
                and all(a.size == l2 for a in inp.v2):
            # one copy per block (the usual case: pieces of one degree)
            c[:lz, :, :nz] = np.stack(polys).transpose(2, 0, 1)
            c[:l1, :, nz] = np.stack(inp.v1).T
            c[:l2, :, nz + 1] = np.stack(inp.v2).T
        else:
            for s in range(pieces):
                c[:polys[s].shape[1], s, :nz] = polys[s].T
                c[:inp.v1[s].size, s, nz] = inp.v1[s]
                c[:inp.v2[s].size, s, nz + 1] = inp.v2[s]
        self._zv_rev = c[::-1].copy()

    @functools.cached_property
    def _z_rev(self) -> list[np.ndarray]:
        # per piece, highest power first, for Horner's rule in u_scalar (built on first use:
        # only the DOP853 fallback and the replays evaluate the inputs one time at a time)
        return [arr[:, ::-1].T.copy() for arr in self.path.polys]

    @functools.cached_property
    def _v_rev(self) -> list[tuple[np.ndarray, np.ndarray]]:
        inp = self.path.inputs
        return [(inp.v1[s][::-1].copy(), inp.v2[s][::-1].copy()) for s in range(inp.pieces)]

    @functools.cached_property
    def _u_fn(self) -> Callable[..., object]:
        fn, gains = self.cf.symbolic.u_from_zv, self.cf.gains
        return lambda z, v: fn(z, v, gains)

    def q(self, t: np.ndarray) -> np.ndarray:
        inv = self.cf.from_chained(self.path.z(np.asarray(t, float) / self.T))
        return inv.q

    def v(self, t: np.ndarray) -> np.ndarray:
        return self.path.inputs.v(t)

    def u(self, t: np.ndarray) -> np.ndarray:
        """``u(t)``, shape (N, 2), for many times at once (``u_from_v(q(t), v(t))``).

        One pass over all points (:meth:`ChainedForm.u_from_zv`: numpy closed form for
        n = 3, one stacked CasADi call otherwise); non-finite where the path leaves the region.
        """
        t = np.atleast_1d(np.asarray(t, float))
        tau = t / self.T
        nz = self.path.z0.size
        zv = self._horner(tau)
        return self.cf.u_from_zv(zv[:, :nz], zv[:, nz:] / self.T)

    def _horner(self, tau: np.ndarray) -> np.ndarray:
        """Rows ``[z(tau), V(tau)]``, shape (N, n+3): per point, the piece's coefficients (one
        gather per Horner step, ``np.take`` into one buffer) and the same Horner steps as
        ``numpy.polynomial.polynomial.polyval`` at ``x = tau - tau_s`` (same rounding)."""
        c = self._zv_rev
        if c.shape[1] == 1:  # one piece: its rows broadcast, no gather
            x = (tau - self._breaks[0])[:, None]
            acc = c[0, 0] + 0.0 * x
            for k in range(1, c.shape[0]):
                acc *= x
                acc += c[k, 0]
            return acc
        idx = np.searchsorted(self._inner, tau, side="right")
        x = (tau - self._breaks[idx])[:, None]
        acc = np.take(c[0], idx, axis=0)
        acc += 0.0 * x
        row = np.empty_like(acc)
        for k in range(1, c.shape[0]):
            acc *= x
            acc += np.take(c[k], idx, axis=0, out=row, mode="clip")  # idx is in range
        return acc

    @property
    def breaks(self) -> np.ndarray:
        """Times (s) where the input schedule changes piece: the inputs are smooth between."""
        return self.T * self._breaks

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
                phi_goal: float, t_samples: np.ndarray, q_planned: np.ndarray,
                integrator: str = "cascade") -> Verification:
    """Integrate the original model under the planned ``u(t)`` and compare with goal and plan.

    Parameters
    ----------
    integrator : {"cascade", "DOP853"}
        ``"cascade"`` (default): :func:`integrate_cascade` (several input pieces: initial
        panels at most :data:`CASCADE_INITIAL_WIDTH` of ``T`` wide), falling back to DOP853 when its
        error estimate cannot be met; ``"DOP853"``: :func:`integrate` only.
    """
    if integrator == "cascade":
        width = CASCADE_INITIAL_WIDTH if inputs.breaks.size > 2 else None
        rep = integrate_cascade(robot, inputs.u, q_start, inputs.T, t_samples, inputs.breaks,
                                initial_width=width, fallback=inputs.u_scalar)
    elif integrator == DOP853_NAME:
        rep = integrate(robot, inputs.u_scalar, q_start, inputs.T, t_samples)
    else:
        raise ValueError(f"integrator must be 'cascade' or 'DOP853', not {integrator!r}")
    if not rep.success:  # no proof at all: never within any tolerance
        th_err = phi_err = dev = float("inf")
    else:
        th_err = float(np.max(np.abs(rep.final[1:] - q_goal_th)))
        phi_err = abs(float(rep.final[0]) - phi_goal)
        dev = float(np.max(np.abs(rep.q - q_planned)))
    cascade = rep.integrator == CASCADE_NAME
    return Verification(terminal_error=th_err, phi_error=phi_err, max_deviation=dev,
                        singular=bool(rep.singular), final=tuple(float(x) for x in rep.final),
                        rtol=CASCADE_TOL if cascade else RTOL,
                        atol=CASCADE_TOL if cascade else ATOL, energy=rep.energy,
                        integrator=rep.integrator, error_estimate=rep.error_estimate)


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
