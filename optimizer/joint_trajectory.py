"""The ROS ``trajectory_msgs/JointTrajectory`` form of a handed-out path, as a controller runs it.

``joint_trajectory_controller`` (ROS 2, and ROS 1's quintic spline segments) interpolates each
joint between consecutive points by the polynomial that matches what the points give: positions
only -> linear, positions and velocities -> cubic Hermite, positions, velocities and
accelerations -> quintic Hermite. The form handed out gives all three, so the controller runs
the quintic: on ``[t_k, t_{k+1}]`` each actuator position is the degree-5 polynomial with both
ends' positions, velocities and accelerations, and the rates the motors get are its
derivative (:func:`optimizer.forms.hermite_form` with ``quintic``). That is the rule corrected
and verified here: the original model driven by those rates ends on the goal, inside the
region, and its rates, their derivatives and second derivatives stay within the request's
limits everywhere between the points (computed exactly: on each interval they are
polynomials, whose extremes are at the ends or at real roots of their derivative).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .errors import InfeasibleError
from .forms import (ExecutionCheck, Form, correct, dense_times,
                    hermite_form)
from .indicators import compute_indicators
from .model import Robot
from .paths import SampledPath
from .problem import PlanRequest
from .region import Region

#: A JointTrajectory stretched for the actuator limits gets this much more time than their
#: ratio asks (its rates come out of a new correction, which moves them by ~1e-9).
STRETCH_MARGIN = 1e-6
#: The request fields of the limits, by derivative order.
LIMIT_NAMES = (("max_u1", "max_u2"), ("max_du1", "max_du2"), ("max_ddu1", "max_ddu2"))
#: The interpolation rule, as the answer states it.
RULE_TEXT = "quintic Hermite (positions, velocities, accelerations)"
#: The JointTrajectory form may exceed a limit by this fraction between its points: it is
#: stretched in time once to its peaks (:data:`STRETCH_MARGIN` more), and its correction
#: onto the goal after the stretch moves the peaks by up to about this much (a 4-joint
#: retimed plan under max_du = 5: 5.4 before the stretch, within 1 % after). The linear
#: and held forms keep the limits to rounding (:data:`~optimizer.forms.LIMIT_TOLERANCE`).
JT_LIMIT_TOLERANCE = 1e-2


def polynomial_extremes(coef: np.ndarray) -> np.ndarray:
    """``max |p(s)|`` over ``s`` in ``[0, 1]`` of polynomials ``p`` (rows of ``coef``,
    ascending powers, shape (N, D)), exactly: at an end or at a real root of ``p'`` inside
    (the roots from the eigenvalues of the companion matrices, all rows at once)."""
    coef = np.asarray(coef, float)
    N, D = coef.shape
    pv = np.polynomial.polynomial.polyval
    best = np.maximum(np.abs(coef[:, 0]), np.abs(coef.sum(axis=1)))
    if D <= 2:
        return best
    der = coef[:, 1:] * np.arange(1, D)                          # p', degree D - 2
    deg = D - 2
    size = np.max(np.abs(der), axis=1)
    lead = der[:, -1]
    full = np.abs(lead) > 1e-9 * size
    if deg == 1:
        s = np.where(full, -der[:, 0] / np.where(full, lead, 1.0), 0.0)
        inside = full & (s > 0.0) & (s < 1.0)
        val = np.abs(coef[:, 0] + s * (coef[:, 1] + s * coef[:, 2]))
        return np.where(inside, np.maximum(best, val), best)
    rows = np.nonzero(full)[0]
    if rows.size:
        comp = np.zeros((rows.size, deg, deg))
        comp[:, np.arange(1, deg), np.arange(deg - 1)] = 1.0
        comp[:, :, -1] = -der[rows, :-1] / lead[rows, None]
        roots = np.linalg.eigvals(comp)                           # (rows, deg)
        real = np.abs(roots.imag) <= 1e-7 * (1.0 + np.abs(roots.real))
        s = np.where(real, roots.real, 0.0)
        s = np.where((s > 0.0) & (s < 1.0), s, 0.0)
        val = np.abs(pv(s.T, coef[rows].T, tensor=False).T)      # (rows, deg)
        best[rows] = np.maximum(best[rows], val.max(axis=1))
    for r in np.nonzero(~full & (size > 0.0))[0]:                 # a lower degree: rare
        s = np.polynomial.polynomial.polyroots(np.trim_zeros(der[r], "b"))
        s = s[np.isreal(s)].real if np.iscomplexobj(s) else s
        s = s[(s > 0.0) & (s < 1.0)]
        if s.size:
            best[r] = max(best[r], float(np.max(np.abs(pv(s, coef[r])))))
    return best


def hermite_peaks(form: Form, p: np.ndarray) -> np.ndarray:
    """``max |u_c|``, ``max |u_c'|`` and ``max |u_c''|`` over ``[0, T]`` of each input of a
    Hermite form (cubic or quintic), exactly, shape (3, 2)."""
    out = np.empty((3, 2))
    for order in range(3):
        coef = form.derivative_coefficients(p, order)            # (K, 2, D)
        for c in range(2):
            out[order, c] = float(np.max(polynomial_extremes(coef[:, c])))
    return out


def hermite_peak_rates(form: Form, p: np.ndarray) -> np.ndarray:
    """``max |u_c(t)|`` of a Hermite form (:func:`hermite_peaks`' first row)."""
    return hermite_peaks(form, p)[0]


def _stretch_for(peaks: np.ndarray, req: PlanRequest) -> float:
    """The smallest ``f >= 1`` that brings peaks of orders 0, 1, 2 within the request's limits
    (a stretch by ``f`` divides them by ``f``, ``f^2``, ``f^3``)."""
    f = 1.0
    for order, pair in enumerate(LIMIT_NAMES):
        for c, name in enumerate(pair):
            lim = getattr(req, name, None)
            if lim is not None and peaks[order, c] > lim:
                f = max(f, (peaks[order, c] / lim) ** (1.0 / (order + 1)))
    return f


def point_derivatives(times: np.ndarray, vel: np.ndarray) -> np.ndarray:
    """Accelerations at the points from their velocities: the derivative at each interior
    point of the parabola through it and its two neighbours (second order on uneven
    spacing), one-sided at the ends."""
    h = np.diff(times)[:, None]
    slope = np.diff(vel, axis=0) / h                              # (m-1, 2)
    acc = np.empty_like(vel)
    acc[1:-1] = (slope[:-1] * h[1:] + slope[1:] * h[:-1]) / (h[:-1] + h[1:])
    acc[0], acc[-1] = slope[0], slope[-1]
    return acc


def _midpoints(path: SampledPath, dense_q: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points of a linear path: its ends and the middle of each of its intervals, where its
    rates are smooth (their slope there is the interval's). A point on a kink of the rates
    would have to take one acceleration for two; between kinks, the quintic through both
    ends' exact positions, velocities and accelerations follows a kink in the middle within
    8 % of the larger slope (16 % where the slope changes sign), against 19 % and 38 % for
    a point on the kink with the mean of both slopes. ``dense_q``: the path's replay at
    :func:`optimizer.forms.dense_times` of ``path.t`` (its middles are the third rows)."""
    t, u = path.t, path.u
    slope = np.diff(u, axis=0) / np.diff(t)[:, None]
    mid = 0.5 * (t[:-1] + t[1:])
    times = np.concatenate([t[:1], mid, t[-1:]])
    pos = np.vstack([path.q[:1, :2], dense_q[2::4][:mid.size, :2], path.q[-1:, :2]])
    vel = np.vstack([np.zeros((1, 2)), 0.5 * (u[:-1] + u[1:]), np.zeros((1, 2))])
    acc = np.vstack([slope[:1], slope, slope[-1:]])
    return times, pos, vel, acc


def _at_samples(form: Form, path: SampledPath
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points at the path's samples (a held path: velocities the mean of the two rates held
    around a point), velocities zero at the ends, accelerations :func:`point_derivatives`."""
    if form.rule == "zoh":
        held = path.u[:-1]
        vel = np.vstack([held[:1], 0.5 * (held[:-1] + held[1:]), held[-1:]])
    else:
        vel = path.u.copy()
    vel[[0, -1]] = 0.0
    return path.t, path.q[:, :2], vel, point_derivatives(path.t, vel)


def joint_trajectory(robot: Robot, region: Region, form: Form, path: SampledPath,
                     q0: np.ndarray, target: np.ndarray, req: PlanRequest,
                     dense_q: np.ndarray | None = None
                     ) -> tuple[dict[str, Any], ExecutionCheck, np.ndarray]:
    """The ROS ``trajectory_msgs/JointTrajectory`` form of an executable path, corrected for
    quintic Hermite interpolation (what ``joint_trajectory_controller`` does with positions,
    velocities and accelerations).

    Points (whole nanoseconds) at the ends and the middles of the intervals of a linear path
    (``dense_q`` given: :func:`_midpoints`), else at its samples (:func:`_at_samples`);
    positions ``(phi, th1)`` of the path's replay, velocities its rates (zero at the first
    and last points), accelerations their slope. The interior positions, velocities and
    accelerations are then corrected so that the original model driven by the derivative of
    the quintic interpolant ends at the goal (the end points are held).

    With limits in ``req`` the interpolant's rates, their derivatives and second derivatives
    (:func:`hermite_peaks`, exact between the points) are brought within them: the points'
    times are stretched by the smallest factor ``f`` that does it (times ``1 +``
    :data:`STRETCH_MARGIN`; usually 1, the path's own rates are planned inside them), the
    velocities divided by ``f``, the accelerations by ``f^2``, and the form is corrected again
    on those times: the model has no drift, so ``u(t / f) / f`` drives it along the same path
    (``time_scale`` in the answer).

    Returns
    -------
    dict
        ``joint_names``, ``points`` (``positions``, ``velocities``, ``accelerations``,
        empty ``effort``, ``time_from_start`` as ``sec`` and ``nanosec``), ``interpolation``
        and ``time_scale``.
    ExecutionCheck
        Its execution by the quintic rule, its own reversals, deviation and ``d_a``.
    ndarray (3, 2)
        :func:`hermite_peaks` of the form handed out.

    Raises
    ------
    InfeasibleError
        A limit is still exceeded by more than :data:`JT_LIMIT_TOLERANCE` after the stretch
        (field ``joint_trajectory``).
    """
    if form.rule == "linear" and dense_q is not None:
        times, pos, vel, acc = _midpoints(path, dense_q)
    else:
        times, pos, vel, acc = _at_samples(form, path)
    ns, keep = np.unique(np.rint(times * 1e9).astype(np.int64), return_index=True)
    times, pos, vel, acc = ns * 1e-9, pos[keep], vel[keep], acc[keep]
    hform = hermite_form(times, quintic=True)
    dense = dense_times(times)[0]
    p, qd, check = correct(robot, hform, np.vstack([pos, vel, acc]), q0, target, region, dense)
    peaks = hermite_peaks(hform, p)
    m = times.size
    scale = _stretch_for(peaks, req)
    if scale > 1.0:
        scale *= 1.0 + STRETCH_MARGIN
        ns = np.rint(ns * scale).astype(np.int64)
        times = ns * 1e-9
        hform = hermite_form(times, quintic=True)
        dense = dense_times(times)[0]
        p0 = np.vstack([p[:m], p[m:2 * m] / scale, p[2 * m:] / scale ** 2])
        p, qd, check = correct(robot, hform, p0, q0, target, region, dense)
        peaks = hermite_peaks(hform, p)
    own = compute_indicators(dense, qd, None)
    check = dataclasses.replace(check, reversals=(own.reversals_phi, own.reversals_th1),
                                deviation=own.deviation, d_a=own.d_a)
    for order, pair in enumerate(LIMIT_NAMES):
        for c, name in enumerate(pair):
            lim = getattr(req, name, None)
            if lim is not None and peaks[order, c] > lim * (1.0 + JT_LIMIT_TOLERANCE):
                raise InfeasibleError(
                    f"the JointTrajectory form, interpolated between its points as "
                    f"joint_trajectory_controller does, reaches {peaks[order, c]:.6g}, above "
                    f"{name} = {lim:g}: more samples, or a longer duration",
                    field="joint_trajectory",
                    diagnostics={"joint_trajectory": check.as_dict(),
                                 "peak": float(peaks[order, c]), "limit": name})
    pos, vel, acc = p[:m], p[m:2 * m], p[2 * m:]
    points = [{"positions": [a, b], "velocities": [c, d], "accelerations": [e, f],
               "effort": [],
               "time_from_start": {"sec": int(x // 1_000_000_000),
                                   "nanosec": int(x % 1_000_000_000)}}
              for (a, b), (c, d), (e, f), x in zip(pos.tolist(), vel.tolist(), acc.tolist(),
                                                   ns.tolist())]
    out = {"joint_names": ["phi", "th1"], "points": points, "interpolation": RULE_TEXT,
           "time_scale": scale}
    return out, check, peaks
