"""Cascade quadrature of the ORIGINAL kinematic model under inputs known as functions of time.

The model is a cascade, ``phi' = u1, th1' = u2, th_i' = K_i cos(th_{i-1})^{m_i} u1``, and the
planned inputs are known functions of time: each state is a plain integral of a known function
once the joint before it is known. :func:`integrate_cascade` computes it by Chebyshev (Fejer)
cumulative quadrature on panels aligned with the input schedule's breaks, refined adaptively
until the estimated error (tails of the Chebyshev coefficients, propagated down the cascade) is
below :data:`CASCADE_TOL`. No time stepping: a few hundred vectorised input evaluations instead
of ~460 scalar ones, ~0.3 ms instead of ~25 ms per plan. It falls back to DOP853
(:func:`optimizer.integration.integrate`) when its estimate cannot be met.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.polynomial import chebyshev as cheb

from . import cascade_kernel
from .dynamics import joint_rate
from .integration import CASCADE_NAME, HALF_PI, Replay, integrate
from .model import Robot


#: Target of the cascade quadrature's error estimate: rad on every state, and relative on the
#: input energy. Panels are cut until the estimate is below it (or only rounding noise is left).
CASCADE_TOL = 1e-11
#: Largest estimate accepted when the inputs' rounding noise keeps it above the target: near
#: the region's edges the inverse map amplifies rounding (plateaus of 1e-11 in u2 are common)
#: and the estimate propagates that worst case down the cascade. DOP853 integrates the same
#: noise, without any estimate (its errors on such plans reach 3e-10). Two orders below the
#: plans' terminal tolerance (1e-6 rad). Above it: DOP853 fallback.
CASCADE_ACCEPT = 1e-8
#: Largest relative estimate of the input energy's quadrature accepted. The energy is an
#: indicator (the states prove the path): a JointTrajectory form of a 4-joint plan (quintic
#: Hermite rates on 1,226 panels, the panel budget spent) had its states to 1e-12 rad and its
#: energy to 1.5e-7 relative, and was refused under :data:`CASCADE_ACCEPT`, and with it the
#: plan. A millionth is far below the digits an energy is compared by.
CASCADE_ENERGY_ACCEPT = 1e-6
#: Noise plateau: the last coefficients are no smaller than this fraction of the middle ones...
CASCADE_PLATEAU = 0.1
#: ... and at most this fraction of the largest (a smooth but unresolved function is far above).
CASCADE_NOISE = 1e-8
#: Chebyshev nodes per panel (first kind: no node on a panel's ends, so none on an input break).
CASCADE_NODES = 32
#: Initial panels per input piece.
CASCADE_INITIAL_PANELS = 3
#: Initial panels of :func:`verify_plan` for schedules of several pieces: at most this fraction
#: of ``T`` wide, at least one per piece (instead of :data:`CASCADE_INITIAL_PANELS` per piece):
#: a retimed plan's 8 pieces, 4 long and 4 short, get 12 panels instead of 24. Measured on 80
#: retimed plans: no refinement needed, largest estimate 7e-15 rad (5e-15 on 24 panels; target
#: :data:`CASCADE_TOL`), 15 % less time. One-piece plans keep 3 initial panels (6 gained
#: nothing there: they refine 3 to about 6 at the same cost).
CASCADE_INITIAL_WIDTH = 1.0 / 6.0
#: A panel that needs refinement is cut into this many.
CASCADE_SPLIT = 4
#: Refinement rounds and panels at most.
CASCADE_MAX_ROUNDS = 30
CASCADE_MAX_PANELS = 2048
#: Trailing Chebyshev coefficients whose magnitude estimates a panel's truncation error (several,
#: because even or odd integrands have every other coefficient zero).
CASCADE_TAIL = 4


@dataclass(frozen=True)
class _ChebRule:
    """Chebyshev quadrature on [-1, 1] with ``p`` first-kind nodes (all built with
    :mod:`numpy.polynomial.chebyshev`).

    Attributes
    ----------
    x : ndarray (p,)
        Nodes, increasing.
    to_coef : ndarray (p, p)
        Values at the nodes -> coefficients of the interpolating Chebyshev series.
    integ : ndarray (p+1, p)
        Values -> coefficients of its integral from -1 (degree p).
    cum_total : ndarray (p+1, p)
        Values -> that integral at the nodes (rows 0..p-1, cumulative quadrature) and at 1
        (row p: Fejer's first rule, positive weights).
    total : ndarray (p,)
        Row p of ``cum_total``.
    xb, wb : ndarray (p+2,)
        The nodes with both ends, ``[-1, x, 1]``, and their barycentric weights: the
        integral of the interpolant, a polynomial of degree ``p``, is interpolated exactly
        from its values there.
    slopes : ndarray (2, p)
        Values -> the interpolant's derivative at -1 and at 1.
    """

    x: np.ndarray
    to_coef: np.ndarray
    integ: np.ndarray
    cum_total: np.ndarray
    total: np.ndarray
    xb: np.ndarray
    wb: np.ndarray
    slopes: np.ndarray


@functools.lru_cache(maxsize=16)
def _cheb_rule(p: int) -> _ChebRule:
    if p < CASCADE_TAIL + 2:
        raise ValueError(f"the cascade quadrature needs at least {CASCADE_TAIL + 2} nodes, not {p}")
    x = cheb.chebpts1(p)
    to_coef = np.linalg.inv(cheb.chebvander(x, p - 1))
    # column j of chebint(I) holds the coefficients of the integral (from -1) of T_j
    integ = cheb.chebint(np.eye(p), lbnd=-1, axis=0) @ to_coef
    cum_total = cheb.chebvander(np.append(x, 1.0), p) @ integ
    xb = np.concatenate([[-1.0], x, [1.0]])
    diff = xb[:, None] - xb[None, :]
    np.fill_diagonal(diff, 1.0)
    wb = 1.0 / np.prod(diff, axis=1)
    wb /= np.max(np.abs(wb))  # the formula is invariant to a common factor
    # column j of chebder(I) holds the coefficients of T_j' (degree p - 2)
    slopes = cheb.chebvander(np.array([-1.0, 1.0]), p - 2) @ cheb.chebder(np.eye(p), axis=0) \
        @ to_coef
    for arr in (x, to_coef, integ, cum_total, xb, wb, slopes):
        arr.setflags(write=False)
    return _ChebRule(x=x, to_coef=to_coef, integ=integ, cum_total=cum_total,
                     total=cum_total[p], xb=xb, wb=wb, slopes=slopes)


def _tails(rule: _ChebRule, G: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Truncation-error estimates of integrands on panels, and their Chebyshev coefficients.

    Parameters
    ----------
    G : ndarray (I, P, p)
        Integrand values at the nodes of ``P`` panels.
    h : ndarray (P,)
        Panel widths.

    Returns
    -------
    err : ndarray (I, P)
        ``2 h max |c_k|`` over the last :data:`CASCADE_TAIL` Chebyshev coefficients.
    coef : ndarray (I, P, p)
        ``|c_k|``, for :func:`_noise`.
    """
    C = np.abs(G @ rule.to_coef.T)
    return 2.0 * h * C[:, :, -CASCADE_TAIL:].max(axis=2), C


def _noise(C: np.ndarray) -> np.ndarray:
    """Which coefficient sequences ``C`` (..., p) have stopped decaying at a level far below
    the function's: a plateau of rounding noise (e.g. the inverse map's amplified rounding
    near a joint at 0), where cutting the panel would not lower the estimate."""
    p = C.shape[-1]
    tail = C[..., p - CASCADE_TAIL:].max(axis=-1)
    mid = C[..., min(p // 2, p - CASCADE_TAIL - 1):p - CASCADE_TAIL].max(axis=-1)
    return (tail >= CASCADE_PLATEAU * mid) & (tail <= CASCADE_NOISE * C.max(axis=-1))


def _marks(err: np.ndarray, C: np.ndarray, weight: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Panels to cut: some integrand's weighted error above the panel's share ``limit`` and its
    coefficients not at a noise plateau (tested only for those, the rare case)."""
    over = err * weight[:, None] > limit
    if over.any():
        i, j = np.nonzero(over)
        flat = _noise(C[i, j])
        over[i[flat], j[flat]] = False
    return np.any(over, axis=0)


def _chain_weights(lam: np.ndarray) -> np.ndarray:
    """How much an error of ``th_j`` (j = 1..n-1... n) can grow by ``th_n``: entry ``j - 1`` is
    ``max(1, max_i prod_{l=j+1..i} Lambda_l)``, with ``lam[l - 2] = Lambda_l`` (l = 2..n)."""
    w = [1.0]
    for lam_l in reversed(np.asarray(lam, float).tolist()):
        w.append(max(1.0, lam_l * w[-1]))
    return np.array(w[::-1])


@functools.lru_cache(maxsize=8)
def _cuts(k: int) -> tuple[np.ndarray, np.ndarray]:
    """How to cut a panel in ``k``, relative to it: starts and widths, rows uniform, graded
    toward the left end (ratio ``1/k``: starts ``[0, k^-(k-1), ..., 1/k]``) and toward the
    right end."""
    uniform = np.arange(k) / k
    left = np.concatenate([[0.0], float(k) ** -np.arange(k - 1, 0, -1.0)])
    right = 1.0 - np.concatenate([left[1:], [1.0]])[::-1]
    starts = np.array([uniform, left, right])
    widths = np.diff(np.concatenate([starts, np.ones((3, 1))], axis=1), axis=1)
    for arr in (starts, widths):
        arr.setflags(write=False)
    return starts, widths


def _cut(rule: _ChebRule, cuts: tuple[np.ndarray, np.ndarray], a: np.ndarray, h: np.ndarray,
         U: np.ndarray, graded: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """New panels from the panels ``(a, h)``: each cut as :func:`_cuts`, graded toward the end
    where ``u1^2 + u2^2`` is steeper (by more than 4x; else, or without ``graded``, uniformly:
    constant rates have no steeper end, and their computed slopes are rounding noise).

    A nearby singularity of the inputs (a joint close to 0 at the start of the motion) makes
    the function steep at the panel's end that faces it; geometric grading reaches it in a few
    rounds where bisection would need many.
    """
    starts, widths = cuts
    if not graded:
        return ((a[:, None] + h[:, None] * starts[0]).ravel(), (h[:, None] * widths[0]).ravel())
    slope = np.abs((U[0] * U[0] + U[1] * U[1]) @ rule.slopes.T)   # (Pm, 2): at -1, at 1
    kind = (slope[:, 0] > 4.0 * slope[:, 1]) + 2 * (slope[:, 1] > 4.0 * slope[:, 0])
    return ((a[:, None] + h[:, None] * starts[kind]).ravel(),
            (h[:, None] * widths[kind]).ravel())


def integrate_cascade(robot: Robot, u_of_t: Callable[[np.ndarray], np.ndarray], q0: np.ndarray,
                      duration: float, t_eval: np.ndarray, breaks: np.ndarray | None = None, *,
                      nodes: int = CASCADE_NODES, tol: float = CASCADE_TOL,
                      accept: float = CASCADE_ACCEPT,
                      initial_panels: int = CASCADE_INITIAL_PANELS,
                      initial_width: float | None = None, split: int = CASCADE_SPLIT,
                      max_rounds: int = CASCADE_MAX_ROUNDS, max_panels: int = CASCADE_MAX_PANELS,
                      fallback: Callable[[float, np.ndarray], np.ndarray] | None = None,
                      constant_pieces: bool = False, compiled: bool = True) -> Replay:
    """Integrate the original model under OPEN-LOOP inputs by cumulative quadrature.

    The model is triangular: ``phi = int u1``, ``th1 = int u2``, then
    ``th_i = int K_i cos(th_{i-1})^{m_i} u1`` joint after joint, each a plain integral of a
    function already known on the nodes. This is exact (no splitting, no time stepping); the
    only error is quadrature.

    Parameters
    ----------
    robot : Robot
    u_of_t : callable
        Vectorised inputs: times, shape (N,) -> ``[u1, u2]``, shape (N, 2). Open loop only
        (the inputs must not depend on the state).
    q0 : ndarray (n+1,)
    duration : float
        ``T`` (s).
    t_eval : ndarray (M,)
        Output times in [0, T].
    breaks : ndarray, optional
        Times (s) where the inputs may be non-smooth (the schedule's piece boundaries); panels
        never straddle them. Default: ``[0, T]``.
    nodes : int
        Chebyshev nodes per panel (at least ``CASCADE_TAIL + 2``).
    tol : float
        Target of the error estimate (rad; relative for the energy): panels are cut until it
        is met, or until only rounding noise is left.
    accept : float
        Largest error estimate accepted (above ``tol`` only when the inputs' own rounding
        noise, or the refinement bounds, stop the refinement); above it, and above ``tol``,
        the run falls back to DOP853.
    initial_panels : int
        Panels per input piece before refinement (unless ``initial_width`` is given).
    initial_width : float, optional
        Instead: each input piece is cut into the fewest equal panels at most
        ``initial_width * T`` wide (at least one per piece).
    split : int
        A panel that needs refinement is cut into this many panels: equal ones, or graded
        geometrically (ratio ``1/split``) toward the end where the inputs are steeper.
    max_rounds, max_panels : int
        Bounds on the refinement.
    fallback : callable ``(t, q) -> u``, optional
        Scalar inputs for :func:`integrate` (DOP853), used when the estimate is above
        ``accept`` or not finite. Without it such a run returns ``success=False``.
    constant_pieces : bool
        The inputs are constant between ``breaks`` (actuator schedules): they are read once
        per panel, at its middle, and their quadrature is exact (no error estimate of their
        own); the joints' integrands are resolved as always. Refined panels are cut
        uniformly. The compiled kernel (:mod:`optimizer.cascade_kernel`) computes this case
        when it is available: the same panels, estimate and outputs, to rounding.
    compiled : bool
        Use the compiled kernel for ``constant_pieces`` when it is available (False: always
        the numpy code; the tests compare both).

    Returns
    -------
    Replay
        ``integrator`` says which integrator produced it, ``error_estimate`` the cascade's
        estimate, ``singular`` whether a joint ``th_1..th_{n-1}`` is outside (0, pi/2) at a
        quadrature node, a sample or a panel end. Non-finite inputs make the run singular and
        unsuccessful at once, as :func:`integrate` reports them (the planned path itself is
        singular there: no fallback).

    Notes
    -----
    Each panel carries ``nodes`` Chebyshev points of the first kind (interior: no input is
    evaluated on a break or at t = 0, T). From the values there, precomputed matrices give the
    integral at the nodes and over the panel, and the integral's Chebyshev series (for the
    samples ``t_eval``: exact evaluation of the integrated interpolant, no extra inputs).

    Error estimate: for each integrand on each panel of width ``h``, ``2 h max |c_k|`` over
    the last :data:`CASCADE_TAIL` Chebyshev coefficients estimates the quadrature error (a
    standard spectral estimate, valid once the coefficients decay). An error ``e`` (in the
    max norm over time) of ``th_{i-1}`` moves ``th_i`` by at most ``Lambda_i e`` with
    ``Lambda_i = int |d f_i / d th_{i-1}| dt = K_i m_i int |cos^(m_i-1) sin u1| dt``; so
    the estimate of ``th_i`` is its own quadrature error plus ``Lambda_i`` times that of
    ``th_{i-1}``. The energy's estimate is relative.

    Refinement: panels whose share of ``tol`` is exceeded are cut (``split``) and the inputs
    evaluated on the new panels only. The inputs are resolved first (their coefficient tails,
    weighted by the bounds ``Lambda_i <= K_i m_i int |u1| dt``), then the cascade runs on the
    mesh and the estimate of every integrand decides. Near-singular inputs (a joint close to
    0 at the start) get geometrically graded panels in a few rounds. A panel whose
    coefficients have reached a plateau of rounding noise is not cut further (cutting cannot
    lower noise); its plateau stays in the estimate, and ``accept`` bounds it.
    """
    n = robot.n
    nq = n + 1                      # states; the integrands add the energy (index nq)
    K = np.asarray(robot.gains, float)
    m = np.asarray(robot.exponents, float)
    q0 = np.asarray(q0, float)
    t_eval = np.atleast_1d(np.asarray(t_eval, float))
    T = float(duration)
    rule = _cheb_rule(int(nodes))
    p = rule.x.size
    cuts = _cuts(max(int(split), 2))
    share = tol / T / (nq + 1)      # per unit time and integrand: the shares sum to <= tol

    edges = np.array([0.0, T]) if breaks is None else np.asarray(breaks, float)
    if edges.size < 2 or edges[0] != 0.0 or edges[-1] != T or not np.all(np.diff(edges) > 0.0):
        edges = np.unique(np.concatenate([[0.0, T], np.clip(edges, 0.0, T)]))
    if initial_width is None and int(initial_panels) <= 1:  # (the same numbers, fewer steps)
        new_a, new_h = edges[:-1], np.diff(edges)
    elif initial_width is None:
        k = max(int(initial_panels), 1)
        new_a = (edges[:-1, None] + np.diff(edges)[:, None] * (np.arange(k) / k)).ravel()
        new_h = np.repeat(np.diff(edges) / k, k)
    else:
        widths = np.diff(edges)
        # (a ratio that is an integer up to rounding, such as T / (T / 6), is not rounded up)
        ks = np.maximum(np.ceil(widths / (float(initial_width) * T) * (1.0 - 1e-12)), 1.0)
        ks = ks.astype(np.intp)
        first = np.cumsum(ks) - ks
        j = np.arange(int(ks.sum())) - np.repeat(first, ks)   # panel number within its piece
        kk = np.repeat(ks, ks)
        new_a = np.repeat(edges[:-1], ks) + np.repeat(widths, ks) * (j / kk)
        new_h = np.repeat(widths / ks, ks)
    # panels (in no particular order until the cascade sorts them) and what is known on them
    a = np.empty(0)                     # panels (in no particular order until sorted)
    evaluations = rounds = 0

    def failed(reason: str, singular_time: float | None = None,
               panels: int | None = None) -> Replay:
        if singular_time is None and fallback is not None:
            rep = integrate(robot, fallback, q0, T, t_eval)
            return dataclasses.replace(
                rep, message=f"cascade quadrature not accepted ({reason}); DOP853: {rep.message}",
                evaluations=rep.evaluations + evaluations)
        return Replay(t=t_eval, q=np.zeros((t_eval.size, nq)), final=np.zeros(nq),
                      singular=singular_time is not None, singular_time=singular_time,
                      success=False, message=reason, energy=0.0, integrator=CASCADE_NAME,
                      evaluations=evaluations,
                      panels=a.size + new_a.size if panels is None else panels)

    if constant_pieces and compiled and new_a.size and cascade_kernel.ready():
        run = _run_kernel(robot, u_of_t, q0, T, t_eval, new_a, new_h, rule, cuts, tol,
                          max_rounds, max_panels)
        if run is not None:  # (else the numpy code below)
            evaluations = run.evaluations
            if run.status != "ok":
                return failed("a state is not finite", panels=run.panels)
            if not run.estimate <= max(accept, tol):
                return failed(f"error estimate {run.estimate:.3g} above {max(accept, tol):.3g} "
                              f"after {run.rounds} refinements ({run.panels} panels)",
                              panels=run.panels)
            return _kernel_replay(run, t_eval, p, tol)

    # the general case: one cascade per round and the outputs by the kernel when it is loaded
    use_kernel = compiled and cascade_kernel.ready()
    packed = _packed_rule(p, cuts[0].shape[1])
    # what is known on the panels
    h = np.empty(0)
    tn = np.empty((0, p))
    U = np.empty((2, 0, p))             # u1, u2 at the nodes
    in_err = np.empty((3, 0))           # tails of u1, u2, u1^2 + u2^2
    in_coef = np.empty((3, 0, p))       # and their coefficients (magnitudes)
    w_in = np.ones(3)

    def fits(mark: np.ndarray) -> bool:  # may the marked panels be cut?
        more = (cuts[0].shape[1] - 1) * int(mark.sum())
        return rounds < max_rounds and a.size + more <= max_panels

    while True:
        if new_a.size:
            # the inputs on the new panels only, and their coefficient tails
            tnn = new_a[:, None] + 0.5 * new_h[:, None] * (rule.x + 1.0)
            if constant_pieces:
                t_read = new_a + 0.5 * new_h
                Um = np.asarray(u_of_t(t_read), float).reshape(new_a.size, 2)
                Un = np.broadcast_to(Um[:, None, :], (new_a.size, p, 2))
                evaluations += t_read.size
            else:
                Un = np.asarray(u_of_t(tnn.ravel()), float).reshape(new_a.size, p, 2)
                evaluations += tnn.size
            if not np.isfinite(Un).all():
                t_bad = float(np.min(tnn[~np.isfinite(Un).all(axis=2)]))
                return failed(f"the planned inputs are not finite at t = {t_bad:.6g} s", t_bad)
            Un = Un.transpose(2, 0, 1)
            if constant_pieces:  # a constant's quadrature is exact
                e, c = np.zeros((3, new_a.size)), np.zeros((3, new_a.size, p))
            else:
                e, c = _tails(rule, np.concatenate([Un, (Un[0] ** 2 + Un[1] ** 2)[None]]),
                              new_h)
            if a.size:
                a, h = np.concatenate([a, new_a]), np.concatenate([h, new_h])
                tn = np.concatenate([tn, tnn])
                U = np.concatenate([U, Un], axis=1)
                in_err = np.concatenate([in_err, e], axis=1)
                in_coef = np.concatenate([in_coef, c], axis=1)
            else:
                a, h, tn, U, in_err, in_coef = new_a, new_h, tnn, Un, e, c
            if rounds == 0 and not constant_pieces:
                # weights of the inputs' errors in the worst state, from the first mesh (only
                # scales of the tolerance): u2 reaches th_n through the Lambda bounds, u1 every
                # th_i directly (times K_i) and down the chain; the energy's is relative
                hh = 0.5 * h
                lam_b = K * m * float(np.abs(U[0]) @ rule.total @ hh)
                chain = _chain_weights(lam_b)
                e_scale = float((U[0] * U[0] + U[1] * U[1]) @ rule.total @ hh)
                w_in = np.array([max(1.0, float(np.max(K * chain[1:]))), chain[0],
                                 1.0 / e_scale if e_scale > 0.0 else 1.0])
            new_a = new_h = np.empty(0)
        mark = (np.zeros(a.size, bool) if constant_pieces
                else _marks(in_err, in_coef, w_in, share * h))
        if not (mark.any() and fits(mark)):
            # the inputs are resolved: the cascade on this mesh, in time order
            if rounds:
                order = np.argsort(a)
                a, h, tn = a[order], h[order], tn[order]
                U, in_err, in_coef = U[:, order], in_err[:, order], in_coef[:, order]
            compiled_step = (cascade_kernel.general_pass(
                *_model_arrays(robot.gains, robot.exponents), q0, h, U, packed, p, CASCADE_TAIL)
                if use_kernel else None)
            energy, lam, X, ends, e, c = (compiled_step if compiled_step is not None else
                                          _cascade_numpy(robot, rule, q0, h, U))
            if not (math.isfinite(float(ends[:, -1].sum())) and math.isfinite(energy)):
                return failed("a state is not finite")
            chain = _chain_weights(lam)
            w = np.concatenate([[1.0], chain, [1.0 / abs(energy) if energy != 0.0 else 1.0]])
            # the inputs' tails are known: only the joints' integrands (e, c) are new
            err = np.concatenate([in_err[:2], e, in_err[2:]])
            mark = _marks(err, np.concatenate([in_coef[:2], c, in_coef[2:]]), w, share * h)
            if not (mark.any() and fits(mark)):
                bounded = bool(mark.any())  # stopped by max_rounds / max_panels
                break
        rounds += 1
        # cut the marked panels (toward their rough end); inputs evaluated in the next round
        new_a, new_h = _cut(rule, cuts, a[mark], h[mark], U[:, mark], not constant_pieces)
        keep = ~mark
        a, h, tn = a[keep], h[keep], tn[keep]
        U, in_err, in_coef = U[:, keep], in_err[:, keep], in_coef[:, keep]

    # the estimate: quadrature errors propagated down the cascade (est_i = q_i + Lambda_i est_{i-1})
    quad = err.sum(axis=1).tolist()
    est = quad[:2]
    for s in range(2, nq):
        est.append(quad[s] + float(lam[s - 2]) * est[-1])
    energy_est = quad[nq] / abs(energy) if energy != 0.0 else (0.0 if quad[nq] == 0.0 else math.inf)
    estimate = max(max(est), energy_est)
    if not max(est) <= max(accept, tol):
        return failed(f"error estimate {max(est):.3g} rad above {max(accept, tol):.3g} after "
                      f"{rounds} refinements ({a.size} panels)")
    if not energy_est <= max(CASCADE_ENERGY_ACCEPT, tol):
        return failed(f"the energy's relative error estimate {energy_est:.3g} is above "
                      f"{max(CASCADE_ENERGY_ACCEPT, tol):.3g} after {rounds} refinements "
                      f"({a.size} panels)")

    final = ends[:, -1].copy()
    outs = (cascade_kernel.general_outputs(a, h, X, ends, T, HALF_PI, t_eval, packed, p)
            if use_kernel else None)
    singular_time, q, mesh_t, mesh_q = (outs if outs is not None else
                                        _outputs_numpy(rule, a, h, X, ends, T, t_eval))
    msg = (f"cascade quadrature: {a.size} panels x {p} nodes, {rounds} refinements, error "
           f"estimate {estimate:.2g}")
    if estimate > tol:
        msg += (" (above the target: refinement bounds reached)" if bounded else
                " (above the target: limited by the inputs' rounding noise)")
    return Replay(t=t_eval, q=q, final=final, singular=singular_time is not None,
                  singular_time=singular_time, success=True, message=msg, energy=energy,
                  integrator=CASCADE_NAME, error_estimate=estimate, evaluations=evaluations,
                  panels=a.size, mesh_t=mesh_t, mesh_q=mesh_q)


def _cascade_numpy(robot: Robot, rule: _ChebRule, q0: np.ndarray, h: np.ndarray,
                   U: np.ndarray) -> cascade_kernel.GeneralPass:
    """The cascade on panels in time order (widths ``h``) with inputs ``U`` (2, P, p) at their
    nodes: each state the cumulative quadrature of its integrand, joint after joint."""
    n = robot.n
    nq = n + 1
    P, p = U.shape[1], U.shape[2]
    K = np.asarray(robot.gains, float)
    m = np.asarray(robot.exponents, float)
    half = 0.5 * h
    F = np.empty((nq + 1, P, p))     # u1, u2, K_i cos(th_{i-1})^m_i u1, energy
    X = np.empty((nq, P, p))         # states at the nodes
    ends = np.empty((nq, P + 1))     # states at the panel ends
    cosx = np.empty((n - 1, P, p))   # cos(th_1..th_{n-1}) at the nodes
    F[0], F[1] = U[0], U[1]
    F[nq] = U[0] * U[0] + U[1] * U[1]
    for s in range(nq):
        R = (F[s] @ rule.cum_total.T) * half[:, None]  # cumulative at nodes; total
        ends[s, 0] = q0[s]
        np.cumsum(R[:, p], out=ends[s, 1:])
        ends[s, 1:] += q0[s]
        X[s] = R[:, :p] + ends[s, :-1, None]
        if 1 <= s < n:  # th_s drives th_{s+1}
            cosx[s - 1] = np.cos(X[s])
            F[s + 1] = joint_rate(robot.gains, robot.exponents, s + 1, X[s], F[0])
    energy = float(F[nq] @ rule.total @ half)
    # Lambda_i = int |d f_i / d th_{i-1}| dt = K_i m_i int |cos^(m_i-1) sin u1| dt
    mm = m[:, None, None]
    with np.errstate(all="ignore"):  # (non-finite states are reported by the caller)
        lam = K * m * (np.abs(cosx ** (mm - 1.0) * np.sin(X[1:n]) * F[0]) @ rule.total @ half)
        err, coef = _tails(rule, F[2:nq], h)
    return cascade_kernel.GeneralPass(energy, lam, X, ends, err, coef)


def _outputs_numpy(rule: _ChebRule, a: np.ndarray, h: np.ndarray, X: np.ndarray,
                   ends: np.ndarray, T: float, t_eval: np.ndarray
                   ) -> tuple[float | None, np.ndarray, np.ndarray, np.ndarray]:
    """The first singular time, the samples at ``t_eval``, ``mesh_t`` and ``mesh_q`` of a run
    on panels ``(a, h)`` in time order."""
    nq, P, p = X.shape
    n = nq - 1
    half = 0.5 * h
    # samples: the integrated interpolant, a polynomial of degree p on each panel, known at the
    # p nodes and both ends: barycentric interpolation through those p + 2 values is exact
    Xb = np.concatenate([ends[:, :-1, None], X, ends[:, 1:, None]], axis=2)  # (nq, P, p+2)
    Xb = np.ascontiguousarray(Xb.transpose(1, 0, 2))                       # (P, nq, p+2)
    te = np.minimum(np.maximum(t_eval, 0.0), T)
    idx = np.searchsorted(a, te, side="right") - 1
    idx[idx < 0] = 0
    d = (2.0 * (te - a[idx]) / h[idx] - 1.0)[:, None] - rule.xb
    with np.errstate(divide="ignore", invalid="ignore"):
        wd = rule.wb / d
        q = np.einsum("mk,msk->ms", wd, Xb[idx]) / wd.sum(axis=1)[:, None]
    hit = np.nonzero(~np.isfinite(q[:, 0]))[0]  # a sample exactly on a node or a panel end
    if hit.size:
        q[hit] = Xb[idx[hit], :, np.argmin(np.abs(d[hit]), axis=1)]

    # singularity: th_1..th_{n-1} outside (0, pi/2) at a node, a sample or a panel end
    tn = a[:, None] + half[:, None] * (rule.x + 1.0)
    singular_time: float | None = None
    checks = ((tn, X[1:n]), (te, q[:, 1:n].T), (np.append(a, T), ends[1:n]))
    if any(v.min() <= 0.0 or v.max() >= HALF_PI for _, v in checks):
        for tt, v in checks:
            out = np.any((v <= 0.0) | (v >= HALF_PI), axis=0)
            if out.any():
                ts = float(np.min(tt[out]))
                singular_time = ts if singular_time is None else min(singular_time, ts)
    mesh_t = np.append((a[:, None] + half[:, None] * (rule.xb[:p + 1] + 1.0)).ravel(), T)
    mesh_q = np.vstack([Xb[:, :, :p + 1].transpose(0, 2, 1).reshape(-1, nq), ends[:, -1]])
    return singular_time, q, mesh_t, mesh_q


@functools.lru_cache(maxsize=64)
def _model_arrays(gains: tuple[float, ...],
                  exponents: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    out = np.asarray(gains, float), np.asarray(exponents, float)
    for arr in out:
        arr.setflags(write=False)
    return out


@functools.lru_cache(maxsize=16)
def _packed_rule(p: int, k: int) -> np.ndarray:
    r = _cheb_rule(p)
    starts, widths = _cuts(k)
    packed = cascade_kernel.pack_rule(r.x, r.cum_total, r.to_coef, r.xb, r.wb, starts[0],
                                      widths[0])
    packed.setflags(write=False)
    return packed


def _run_kernel(robot: Robot, u_of_t: Callable[[np.ndarray], np.ndarray], q0: np.ndarray,
                T: float, t_eval: np.ndarray, a0: np.ndarray, h0: np.ndarray, rule: _ChebRule,
                cuts: tuple[np.ndarray, np.ndarray], tol: float, max_rounds: int,
                max_panels: int) -> cascade_kernel.KernelRun | None:
    """:func:`integrate_cascade` of constant pieces by the compiled kernel, from the initial
    panels ``(a0, h0)``; None when the kernel is not there (or the rates are not finite: the
    numpy code reports those)."""
    k = cuts[0].shape[1]
    rates = np.asarray(u_of_t(a0 + 0.5 * h0), float).reshape(a0.size, 2)
    if not np.isfinite(rates).all():
        return None
    gains, exponents = _model_arrays(robot.gains, robot.exponents)
    return cascade_kernel.run(
        gains, exponents, q0, T, t_eval, a0, h0, rates, _packed_rule(rule.x.size, k),
        rule.x.size, k, tol=tol,
        half_pi=HALF_PI, plateau=CASCADE_PLATEAU, noise=CASCADE_NOISE, tail=CASCADE_TAIL,
        max_rounds=int(max_rounds), max_panels=int(max_panels))


def _kernel_replay(run: cascade_kernel.KernelRun, t_eval: np.ndarray, p: int,
                   tol: float) -> Replay:
    """The :class:`Replay` of an accepted kernel run (as the numpy code builds it)."""
    msg = (f"cascade quadrature: {run.panels} panels x {p} nodes, {run.rounds} refinements, "
           f"error estimate {run.estimate:.2g}")
    if run.estimate > tol:
        msg += (" (above the target: refinement bounds reached)" if run.bounded else
                " (above the target: limited by the inputs' rounding noise)")
    return Replay(t=t_eval, q=run.q, final=run.mesh_q[-1].copy(),
                  singular=run.singular_time is not None, singular_time=run.singular_time,
                  success=True, message=msg, energy=run.energy, integrator=CASCADE_NAME,
                  error_estimate=run.estimate, evaluations=run.evaluations, panels=run.panels,
                  mesh_t=run.mesh_t, mesh_q=run.mesh_q)
