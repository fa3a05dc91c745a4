"""The motion under way when a replan starts (:mod:`.replan`, step 1): run on at the
commanded rates to its next stop (:func:`run_on`), brought to rest at the end of its piece
where the plan's law runs on (:func:`to_piece_end`), or braked now (:func:`brake_now`). The
rates stay continuous in every case; what follows the stop is the replanner's to correct."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import NumericalError
from .continuation_law import braking_time, piece_bounds
from .plan_state import REST, PlanState, TimeLaw

#: Where the plan's bounds need it, the stop of :func:`brake_now` (an S-curve under a jerk
#: bound, else a constant braking) may take at most this share of what is left of the
#: current piece (else half of it).
STOP_SHARE = 0.9
#: Seconds within which the motion under way is braked to rest (:func:`brake_now`; a chained
#: plan's commanded rates too, in the replanner's fallback).
BRAKE_TIME = 0.05


@dataclass(frozen=True)
class Kept:
    """The motion that runs on as commanded: from plan time ``breaks[0]`` (now) to the next
    stop ``breaks[-1]`` (empty at rest), its pieces' rates (the first: the commanded rates
    over ``sigma'``), its law, and ``k``: the first of the plan's pieces after it."""

    k: int
    breaks: np.ndarray
    rates: np.ndarray
    law: TimeLaw
    own: bool = True            # the plan's own law (False: brought to rest early)

    @property
    def pieces(self) -> int:
        return self.rates.shape[0]

    @property
    def s_stop(self) -> float:
        return float(self.breaks[-1])


def run_on(ps: PlanState, t: float, u_c: np.ndarray) -> Kept:
    """What runs on from ``t`` to the next stop (see :class:`Kept`). A plan without a time law
    jumps at every break: there its next break is the stop."""
    assert ps.rates is not None
    s_t, v, _ = ps.law.at(t)
    tol = 1e-9 * max(1.0, ps.plan_duration)
    k = ps.piece_at(s_t + tol)
    if v <= REST:
        if float(np.abs(u_c).max()) > 1e-9:
            raise NumericalError("the plan is at rest at this time but rates were given",
                                 field="rates")
        if abs(s_t - ps.breaks[k]) > tol:
            raise NumericalError("the plan is at rest inside a piece")
        return Kept(k, np.array([s_t]), np.zeros((0, 2)), TimeLaw(np.zeros((0, 6))))
    P = ps.law.phases
    if ps.jumps:
        s_stop = float(ps.breaks[k + 1])
        t_stop = float(P[np.argmin(np.abs(P[:, 2] - s_stop)), 0]) if s_stop < ps.breaks[-1] \
            else ps.law.end
    else:
        at_rest = P[(P[:, 0] > t) & (np.abs(P[:, 3]) <= REST), 0]
        t_stop = float(at_rest[0]) if at_rest.size else ps.law.end
        s_stop = ps.law.at(t_stop)[0] if at_rest.size \
            else ps.law.last_sigma()
    j = int(np.argmin(np.abs(ps.breaks - s_stop)))
    if abs(ps.breaks[j] - s_stop) > 1e-7 * max(1.0, ps.plan_duration):
        raise NumericalError("the time law stops between the plan's breaks")
    if j <= k:      # the stop lies within rounding ahead of t, at the start of piece k
        k = j - 1
    if j > k + 1:
        stopped = to_piece_end(ps, t, s_t, v, k, u_c)
        if stopped is not None:
            return stopped
        # (the end of the piece is nearer than the plan's bounds can stop at: the plan's
        # own law, within them, runs on to its next stop)
    inner = ps.breaks[k + 1:j]
    kb = np.concatenate([[s_t], inner, [ps.breaks[j]]])
    kr = ps.rates[k:j].copy()
    kr[0] = np.asarray(u_c, float) / v
    law = ps.law.after(t)
    kept_rows = law.phases[law.phases[:, 0] < t_stop - 1e-12]
    return Kept(j, kb, kr, TimeLaw(kept_rows))


def to_piece_end(ps: PlanState, t: float, s_t: float, v: float, k: int, u_c: np.ndarray
                  ) -> Kept | None:
    """The commanded motion brought to rest at the end of its piece (where the plan's law runs
    on to a later stop): ``sigma'`` linear from ``v`` to a peak and down to 0, in about the
    time the plan takes to that break (at most ``3.5 l / v``, so the peak stays above
    ``v / 14``). The rates stay continuous; every later piece becomes correctable. None
    where the plan's rate bounds cannot be kept so (the break is too near to stop at), or
    where a jerk bound forbids the law's kinks."""
    assert ps.rates is not None
    s_end = float(ps.breaks[k + 1])
    ell = s_end - s_t
    # the plan's own time to the break (its sigma is increasing: a grid and interpolation)
    grid = np.linspace(t, ps.law.end, 64)
    sg = ps.law.evaluate(grid)[0]
    D_plan = float(np.interp(s_end, sg, grid)) - t if sg[-1] >= s_end else ps.law.end - t
    D = min(max(D_plan, 1e-6), 3.5 * ell / v)
    if ps.limits.any:
        if ps.limits.jerk_bounded:
            return None
        Vb, Ab, _ = piece_bounds((np.asarray(u_c, float) / v)[None, :], ps.limits)
        D_b = _within_bounds(D, ell, v, float(Vb[0]), float(Ab[0]))
        if D_b is None:
            return None
        D = D_b
    h = 0.5 * D
    peak = 0.5 * (4.0 * ell / D - v)
    s_mid = s_t + 0.5 * (v + peak) * h
    law = np.array([[t, h, s_t, v, (peak - v) / h, 0.0],
                    [t + h, h, s_mid, peak, -peak / h, 0.0]])
    rates = (np.asarray(u_c, float) / v)[None, :]
    return Kept(k + 1, np.array([s_t, s_end]), rates, TimeLaw(law), own=False)


def _within_bounds(D: float, ell: float, v: float, V: float, A: float) -> float | None:
    """The duration nearest ``D`` of :func:`to_piece_end`'s law (``sigma'`` linear from
    ``v`` to a peak ``(4 ell / D - v) / 2`` at ``D / 2`` and down to 0; the peak >= 0 needs
    ``D <= 4 ell / v``) whose peak stays within ``V`` and slopes within ``A``; None where
    none does (the piece's end nearer than the bounds can stop at).
    """
    def excess(d: np.ndarray) -> np.ndarray:
        peak = 0.5 * (4.0 * ell / d - v)
        slope = np.maximum(np.abs(4.0 * ell / d - 3.0 * v), np.abs(4.0 * ell / d - v)) / d
        return np.maximum(peak / V, slope / A)

    if float(excess(np.array([D]))[0]) <= 1.0:
        return D
    grid = np.linspace(1e-3, 1.0, 400) * 4.0 * ell / v
    e = excess(grid)
    ok = grid[e <= 1.0]
    return float(ok[np.argmin(np.abs(ok - D))]) if ok.size else None


def brake_now(ps: PlanState, t: float, u_c: np.ndarray, T_end: float) -> Kept:
    """The commanded motion braked to rest now: ``sigma'`` from its value down to 0 at a
    constant rate within :data:`BRAKE_TIME` (the rates stay continuous, their slope jumps),
    inside the current piece; what is left of that piece and the later pieces follow. Used
    when no piece is left after the next stop (the plan's last segment), and when the rates
    cannot keep their signs with the motion under way run to its piece's end."""
    assert ps.rates is not None
    s_t, v, a0 = ps.law.at(t)
    if v <= REST:
        return run_on(ps, t, u_c)
    k = ps.piece_at(s_t)
    room = float(ps.breaks[k + 1]) - s_t
    rates = (np.asarray(u_c, float) / v)[None, :]
    if ps.limits.jerk_bounded:
        # under a jerk bound the rates' slope may not jump: an S-curve stop from the current
        # speed and acceleration, where the piece leaves room for it
        _, A_b, J_b = piece_bounds(rates, ps.limits)
        stop = scurve_stop(v, a0, float(A_b[0]), float(J_b[0]))
        if stop is not None:
            law = np.column_stack([t + stop[:, 0], stop[:, 1], s_t + stop[:, 2], stop[:, 3:]])
            s_b = s_t + float(_rows_end(stop))
            # (a longer stop than the constant braking's half of the piece: what is left of
            # it after the stop is still corrected with the later pieces)
            if s_b - s_t <= STOP_SHARE * room:
                return Kept(k, np.array([s_t, s_b]), rates, TimeLaw(law))
        raise _no_stop_within(ps)
    # travels v D / 2 <= room / 2; under the plan's acceleration bounds no faster than they
    # allow (up to STOP_SHARE of the piece where they need more than its half)
    D_need = braking_time(v, rates[0], ps.limits)
    if D_need > 2.0 * STOP_SHARE * room / v:
        raise _no_stop_within(ps)
    cap = room / v if D_need <= room / v else 2.0 * STOP_SHARE * room / v
    D = min(max(min(BRAKE_TIME, 0.25 * (T_end - t)), D_need), cap)
    if D <= 0.0:
        raise NumericalError("no room left to brake the current motion")
    s_b = s_t + 0.5 * v * D
    law = np.array([[t, D, s_t, v, -v / D, 0.0]])
    # the rest of the current piece is free: ps.breaks[k + 1:] follow s_b
    return Kept(k, np.array([s_t, s_b]), rates, TimeLaw(law))


def _no_stop_within(ps: PlanState) -> NumericalError:
    # a drive cannot follow rates beyond its bounds: none are handed out; the caller runs on
    # the current plan (or a later replan, from a state where there is room, corrects)
    return NumericalError(
        "the motion under way cannot be brought to rest within the plan's rate limits "
        f"({', '.join(f'{k} = {v:g}' for k, v in ps.limits.as_dict().items())}) before the "
        "end of its piece: run on the current plan", field="state")


def scurve_stop(v: float, a0: float, A: float, J: float) -> np.ndarray | None:
    """Rows ``(t0, dt, x0, v0, a0, jerk)`` (times and positions from 0) that bring a speed
    ``v > 0`` with acceleration ``a0`` to rest with the acceleration back at 0: jerk ``-J``
    down to ``-Ap``, ``-Ap`` held, jerk ``+J`` up to 0, ``Ap <= A`` (the shortest such stop).
    None where ``J`` is not finite or the motion already decelerates harder than that."""
    if not (math.isfinite(J) and J > 0.0):
        return None
    Ap = A if math.isfinite(A) else math.inf
    hold = (v + a0 * a0 / (2.0 * J) - Ap * Ap / J) / Ap if math.isfinite(Ap) else -1.0
    if hold < 0.0:              # no held deceleration: the peak is below A
        Ap, hold = math.sqrt(J * v + 0.5 * a0 * a0), 0.0
    t1 = (a0 + Ap) / J
    if t1 < 0.0:
        return None
    rows, t, x, s, a = [], 0.0, 0.0, v, a0
    for h, j in ((t1, -J), (hold, 0.0), (Ap / J, J)):
        if h > 0.0:
            rows.append([t, h, x, s, a, j])
            x += h * (s + h * (a / 2.0 + h * j / 6.0))
            s += h * (a + h * j / 2.0)
            a += h * j
            t += h
    return np.array(rows)


def _rows_end(rows: np.ndarray) -> float:
    """The position at the end of the last of ``rows``."""
    _, h, x, s, a, j = rows[-1].tolist()
    return x + h * (s + h * (a / 2.0 + h * j / 6.0))


__all__ = ["BRAKE_TIME", "Kept", "brake_now", "run_on", "scurve_stop", "to_piece_end"]
