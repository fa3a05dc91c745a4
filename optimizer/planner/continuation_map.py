"""The end map of a continuation's pieces and its Jacobian, compiled once per joint count and
exponents (the gains are an input), and the weighted Gauss-Newton corrections that move the
pieces onto the goal.

The robot's gains ``K_2..K_n`` are an input of every compiled function (the last), not
constants in it: the functions are built and compiled once per joint count and exponents, and
serve every robot of that shape (a plant's gains as estimated from its motion, a study's
designs) without another build. :class:`BoundCall` binds them.

A continuation's later pieces are constant geometric rates ``g_k`` over plan-time lengths
``L_k``; the model is driftless, so each piece is the unit-length flow under the displacement
rates ``w_k = g_k L_k``. :func:`jacobian_map` is one CasADi function of the start state and
the ``w_k`` of ``P`` pieces (fewer pieces are padded in front with zero rates, under which
nothing moves) that returns the RK4 end state and its Jacobian in one call: a fixed-size,
reset-free computation whose answer depends on its arguments only.

:func:`correct_pieces` takes weighted least-norm Gauss-Newton steps: the change of a rate is
measured relative to the rate itself (weights ``|w| + floor``), so the correction is shared
in proportion to how much each piece already moves and a rate keeps its sign unless the goal
needs a change of its own size; a step that does not shrink the miss is halved.
:func:`correct_signed` keeps every rate's sign (an active set per step). The common cases
run as one compiled call each (:func:`signed_kernel`, :func:`halving_kernel`): CasADi
functions built from one RK4 piece and its sensitivities, generated as C and compiled
(:class:`CompiledCall`, :mod:`optimizer.native`) when compiled functions are on.
"""

from __future__ import annotations

import functools
import math

import casadi as ca
import numpy as np

from .. import native
from ..dynamics import rk4_step, vector_field
from .solvers import BufferedCall

#: RK4 steps per piece (a piece moves a few hundredths of a radian to a few tenths: the map
#: is within ~1e-9 rad of the exact model on the former; the quadrature of the verification
#: measures the rest, and one defect-corrected step removes it).
SUBSTEPS = 4
#: Sizes of the compiled maps: a continuation of ``M`` pieces uses the smallest ``P >= M``.
SIZES = (4, 8, 12, 16, 20, 24, 32, 48)
#: Relative floor of the weights (of the largest rate): pieces at rest may move a little.
WEIGHT_FLOOR = 0.05
#: Steps stop once the map's miss is this small (rad)...
TARGET = 1e-11
#: ... or after this many steps.
MAX_STEPS = 12
#: Fractions of the Gauss-Newton step tried in turn until one shrinks the miss (near a
#: direction that only brackets reach the full step overshoots).
HALVINGS = tuple(0.5 ** k for k in range(9))
#: Levenberg-Marquardt dampings (relative to the mean diagonal of ``J J^T``) tried in turn when
#: the undamped sign-keeping step, halved, does not shrink the miss.
DAMPINGS = (0.0, 1e-4, 1e-2, 1.0)
#: Most steps of the sign-keeping correction.
SIGNED_STEPS = 30
#: A step that leaves more than this fraction of the squared miss is a stall (three in a row:
#: stop).
STALL = 0.9
#: Rounds of the active set of :func:`signed_step`.
MAX_ACTIVE = 6


class BoundCall:
    """A call of a function whose last input is the robot's gains, with the gains bound:
    ``call(*args)`` is ``function(*args, gains)``."""

    def __init__(self, call: "BufferedCall | CompiledCall", gains: tuple[float, ...]) -> None:
        self.call = call
        self.gains = np.asarray(gains, float)

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        return self.call(*args, self.gains)


def _gains_symbol(exponents: tuple[int, ...]) -> tuple[ca.SX, list[ca.SX]]:
    """The gains as a symbolic input ``K`` (``n - 1``) and as its elements (for
    :func:`~optimizer.dynamics.vector_field`)."""
    K = ca.SX.sym("K", len(exponents))
    return K, [K[i] for i in range(len(exponents))]


@functools.lru_cache(maxsize=16)
def _piece_end(exponents: tuple[int, ...]) -> BufferedCall:
    nq = len(exponents) + 2
    q = ca.SX.sym("q", nq)
    u = ca.SX.sym("u", 2)
    K, gains = _gains_symbol(exponents)
    end = rk4_step(lambda y, r: ca.vertcat(*vector_field(gains, exponents, y, r[0], r[1],
                                                          ca.cos)), q, u, 1.0, 2 * SUBSTEPS)
    return BufferedCall(ca.Function("piece_end", [q, u, K], [end]), 3)


def piece_end(gains: tuple[float, ...], exponents: tuple[int, ...]) -> BoundCall:
    """The end state of one unit piece ``(q0, w) -> q_end``, with twice :data:`SUBSTEPS` RK4
    steps (the motion under way, run on as commanded)."""
    return BoundCall(_piece_end(tuple(exponents)), gains)


#: Sign-keeping Gauss-Newton steps of the compiled kernel (:func:`signed_kernel`): from a
#: measured state a small error off the plan's, full steps converge quadratically (n = 3:
#: 1e-3 -> 1e-5 -> 1e-9 -> 1e-16); a correction that needs more goes the long way.
KERNEL_STEPS = 5
#: Rounds of the kernel's active set per step (:func:`signed_step`'s, a fixed number).
KERNEL_ROUNDS = 4


@functools.lru_cache(maxsize=16)
def _piece_step(exponents: tuple[int, ...]) -> ca.Function:
    """One unit piece with its sensitivities: ``(q, w, K) -> (q_end, d q_end / d q,
    d q_end / d w)`` (the kernel's building block: its C stays small for any size)."""
    nq = len(exponents) + 2
    q = ca.SX.sym("q", nq)
    u = ca.SX.sym("u", 2)
    K, gains = _gains_symbol(exponents)
    end = rk4_step(lambda y, r: ca.vertcat(*vector_field(gains, exponents, y, r[0], r[1],
                                                          ca.cos)), q, u, 1.0, SUBSTEPS)
    return ca.Function("continuation_piece", [q, u, K],
                       [end, ca.densify(ca.jacobian(end, q)), ca.densify(ca.jacobian(end, u))])


def _end_and_jacobian(F: ca.Function, q0: ca.MX, w: ca.MX, K: ca.MX, P: int
                      ) -> tuple[ca.MX, ca.MX]:
    """The end state of ``P`` pieces (rates ``w``, flat; gains ``K``) and its Jacobian:
    forward through the pieces, then the chain rule backwards (``d end / d w_k = A_{P-1} ...
    A_{k+1} B_k``)."""
    x, As, Bs = q0, [], []
    for k in range(P):
        x, A, B = F(x, w[2 * k:2 * k + 2], K)
        As.append(A)
        Bs.append(B)
    S, cols = ca.MX.eye(q0.shape[0]), []
    for k in reversed(range(P)):
        cols.append(ca.mtimes(S, Bs[k]))
        S = ca.mtimes(S, As[k])
    return x, ca.horzcat(*reversed(cols))


def piece_function(exponents: tuple[int, ...], substeps: int) -> ca.Function:
    """One unit piece by ``substeps`` RK4 steps, ``(q, w, K) -> q_end``."""
    nq = len(exponents) + 2
    q = ca.SX.sym("q", nq)
    u = ca.SX.sym("u", 2)
    K, gains = _gains_symbol(exponents)
    return ca.Function(f"piece_rk4_{substeps}", [q, u, K], [rk4_step(
        lambda y, r: ca.vertcat(*vector_field(gains, exponents, y, r[0], r[1], ca.cos)),
        q, u, 1.0, substeps)])


class CompiledCall:
    """A CasADi Function called through its buffer (:class:`~.solvers.BufferedCall`), in its
    compiled form (:mod:`optimizer.native`: generated C, built once per machine and cached)
    once that is built, in CasADi's virtual machine until then or when compiled functions
    are off. The same expressions either way: the compiled kernel runs 3-5 times faster."""

    def __init__(self, function: ca.Function, n_args: int, outputs: tuple[int, ...]) -> None:
        self.function = function
        self._n_args, self._outputs = n_args, outputs
        self.vm = BufferedCall(function, n_args, outputs)
        self.compiled: BufferedCall | None = None
        self._cfg: object = None
        self._library: native.Library | None = None

    def current(self, wait: bool = False) -> BufferedCall:
        """The compiled call when its library is ready (``wait``: build it now when missing),
        else the virtual machine's (a build started in the background)."""
        if self.compiled is not None:
            return self.compiled
        cfg = native.config()
        if cfg is None:
            return self.vm
        if cfg is not self._cfg:
            self._cfg = cfg
            cg = ca.CodeGenerator(f"{self.function.name()}.c", {"with_header": False})
            cg.add(self.function)
            self._library = native.library_for(str(cg.dump()), wait=wait)
        if self._library is None:
            return self.vm
        path = self._library.ready(0.0 if wait else 1.0)
        if path is None:
            return self.vm
        try:
            self.compiled = BufferedCall(ca.external(self.function.name(), str(path)),
                                        self._n_args, self._outputs)
        except Exception:  # noqa: BLE001 - an unloadable library: keep the virtual machine
            self._library = None
            return self.vm
        return self.compiled

    def __call__(self, *args: np.ndarray) -> list[np.ndarray]:
        return self.current()(*args)


def jacobian_map(gains: tuple[float, ...], exponents: tuple[int, ...], P: int) -> BoundCall:
    """The compiled map ``(q0, W) -> (q_end, d q_end / d W)`` of ``P`` unit pieces (``W``:
    ``(2, P)`` column-major, so the C-contiguous ``(P, 2)`` array of the rates; the Jacobian
    comes back flat column-major, ``(n+1, 2P)``), built as the kernels are (one piece and its
    sensitivities, the chain rule backwards: its C compiles in seconds): the Python loops'
    map (:class:`PieceMap`)."""
    return BoundCall(_jacobian_map(tuple(exponents), P), gains)


@functools.lru_cache(maxsize=64)
def _jacobian_map(exponents: tuple[int, ...], P: int) -> CompiledCall:
    F = _piece_step(exponents)
    q0 = ca.MX.sym("q0", len(exponents) + 2)
    W = ca.MX.sym("W", 2, P)
    K = ca.MX.sym("K", len(exponents))
    x, J = _end_and_jacobian(F, q0, ca.vec(W), K, P)
    return CompiledCall(ca.Function(f"continuation_map_{P}", [q0, W, K], [x, J]), 3, (0, 1))


def signed_kernel(gains: tuple[float, ...], exponents: tuple[int, ...], P: int) -> BoundCall:
    """Up to :data:`KERNEL_STEPS` full sign-keeping Gauss-Newton steps in one call (they stop
    once the map's miss is below :data:`TARGET`, or not finite):
    ``(q0, W, goal, D2, signs) -> (W_end, th_end - goal)`` (``W``: ``(2, P)`` as for
    :func:`jacobian_map`; ``D2``, ``signs``: flat like ``vec(W)``).

    Each step is :func:`signed_step` with :data:`KERNEL_ROUNDS` rounds of its active set (a
    rate the step would take across 0 held at 0, the others solved again), without halving
    or damping: what needs those (or does not converge) is for the caller to see in the miss
    (non-finite when a system was singular) and to correct the long way
    (:func:`correct_signed`). One CasADi call instead of a Python loop of map calls and small
    solves: the replanner's common case (n = 3: 82 % of the states 0.05 deg off a plan, the
    same cases as the long way keeps the signs on)."""
    return BoundCall(_signed_kernel(tuple(exponents), P), gains)


@functools.lru_cache(maxsize=64)
def _signed_kernel(exponents: tuple[int, ...], P: int) -> CompiledCall:
    n = len(exponents) + 1
    F = _piece_step(exponents)
    K = ca.MX.sym("K", n - 1)
    q0 = ca.MX.sym("q0", n + 1)
    goal = ca.MX.sym("goal", n)
    D2 = ca.MX.sym("D2", 2 * P)
    signs = ca.MX.sym("signs", 2 * P)
    w = ca.MX.sym("w", 2 * P)
    r_in = ca.MX.sym("r", n)
    x, J = _end_and_jacobian(F, q0, w, K, P)
    r = x[1:] - goal
    size = ca.norm_inf(r)
    converged = size <= TARGET
    # steps stop at a miss below TARGET, and at one that is not finite (a singular system
    # before: every later step would carry its NaN); the steps skipped cost nothing (the
    # conditionals evaluate one branch)
    step = ca.Function(f"continuation_kernel_step_{P}", [q0, w, goal, D2, signs, K, r_in], [
        ca.if_else(converged, w, w - _signed_direction(J[1:, :], r, w, D2, signs, None,
                                                       KERNEL_ROUNDS)),
        r, ca.logic_or(converged, ca.logic_not(size < ca.inf))])
    stay = ca.Function(f"continuation_kernel_stay_{P}", [q0, w, goal, D2, signs, K, r_in],
                       [w, r_in, 1])
    step_or_stay = ca.Function.if_else(f"continuation_kernel_if_{P}", stay, step)
    end = q0
    for k in range(P):
        end = F(end, w[2 * k:2 * k + 2], K)[0]
    miss_at = ca.Function(f"continuation_kernel_miss_{P}", [q0, w, goal, K, r_in],
                          [end[1:] - goal])
    keep = ca.Function(f"continuation_kernel_keep_{P}", [q0, w, goal, K, r_in], [r_in])
    final_miss = ca.Function.if_else(f"continuation_kernel_final_{P}", keep, miss_at)
    W = ca.MX.sym("W", 2, P)
    w_k, r_k, done = ca.vec(W), ca.MX(ca.DM.inf(n)), ca.MX(0)
    for _ in range(KERNEL_STEPS):
        w_k, r_k, done = step_or_stay.call([done, q0, w_k, goal, D2, signs, K, r_k])
    r_k = final_miss.call([done, q0, w_k, goal, K, r_k])[0]
    fn = ca.Function(f"continuation_kernel_{P}", [q0, W, goal, D2, signs, K],
                     [ca.reshape(w_k, 2, P), r_k])
    return CompiledCall(fn, 6, (0, 1))


#: Steps and halvings of the any-sign kernel (:func:`halving_kernel`).
HALVING_STEPS = 12
HALVING_TRIES = 7
#: Halvings the damped kernel tries at most (:func:`damped_kernel`'s ``halvings``, the first
#: of :data:`HALVINGS`).
DAMPED_TRIES = 5


def halving_kernel(gains: tuple[float, ...], exponents: tuple[int, ...], P: int
                   ) -> BoundCall:
    """:func:`correct_pieces` in one call: up to :data:`HALVING_STEPS` weighted least-norm
    Gauss-Newton steps with any sign, each the largest of :data:`HALVING_TRIES` halvings
    that shrinks the miss, ``(q0, W, goal, D2) -> (W_end, th_end - goal)``; as the loop,
    the steps stop once the miss is below :data:`TARGET` or when no halving shrinks it (the
    rates stay). Every candidate is the map's end state without its Jacobian (RK4 as
    :func:`jacobian_map`'s), evaluated only where the larger steps failed: conditionals, so
    that the steps and halvings not needed cost nothing (they were all evaluated before:
    0.5-2 ms a compiled call at 4 and 5 joints, now 0.25-1 ms)."""
    return BoundCall(_halving_kernel(tuple(exponents), P), gains)


@functools.lru_cache(maxsize=64)
def _halving_kernel(exponents: tuple[int, ...], P: int) -> CompiledCall:
    n = len(exponents) + 1
    F = _piece_step(exponents)
    K = ca.MX.sym("K", n - 1)
    q0 = ca.MX.sym("q0", n + 1)
    w = ca.MX.sym("w", 2 * P)
    goal = ca.MX.sym("goal", n)
    D2 = ca.MX.sym("D2", 2 * P)
    ones = ca.DM.ones(n, 1)
    x, J = _end_and_jacobian(F, q0, w, K, P)
    Jt = J[1:, :]
    r = x[1:] - goal
    JD = Jt * ca.mtimes(ones, D2.T)
    dx = ca.mtimes(JD.T, ca.solve(ca.mtimes(JD, Jt.T), r))
    choose = _halving_choice(exponents, P, HALVING_TRIES)
    chosen_w, chosen_r, moved = choose.call([q0, w, dx, goal, K, ca.sumsqr(r), r,
                                             HALVING_TRIES])
    # one step, a Function of its own: the generated C holds it once, called in turn
    step = ca.Function(f"continuation_halving_step_{P}", [q0, w, goal, D2, K],
                       [chosen_w, chosen_r, moved])
    # steps stop once the miss is below TARGET (as correct_pieces's loop does), or after a step
    # whose halvings all failed: it left the rates as they were, and every later step would
    # repeat it exactly (a conditional evaluates one branch only: the steps skipped cost
    # nothing)
    r_in = ca.MX.sym("r", n)
    stalled = ca.Function(f"continuation_halving_stalled_{P}", [q0, w, goal, D2, K, r_in],
                          [w, r_in, 0])
    going = ca.Function(f"continuation_halving_going_{P}", [q0, w, goal, D2, K, r_in],
                        step.call([q0, w, goal, D2, K]))
    step_or_stay = ca.Function.if_else(f"continuation_halving_if_{P}", going, stalled)
    W = ca.MX.sym("W", 2, P)
    w_k, r_k, moved_k = ca.vec(W), ca.MX(ca.DM.inf(n)), ca.MX(1)
    for _ in range(HALVING_STEPS):
        going_on = ca.logic_and(moved_k, ca.norm_inf(r_k) > TARGET)
        w_k, r_k, moved_k = step_or_stay.call([going_on, q0, w_k, goal, D2, K, r_k])
    fn = ca.Function(f"continuation_halving_{P}", [q0, W, goal, D2, K],
                     [ca.reshape(w_k, 2, P), r_k])
    return CompiledCall(fn, 5, (0, 1))


@functools.lru_cache(maxsize=128)
def _halving_choice(exponents: tuple[int, ...], P: int, tries: int) -> ca.Function:
    """``(q0, w, dx, goal, K, size, r, limit) -> (w_new, r_new, moved)``: the first of ``w -
    dx / 2^j``, ``j = 0 .. min(tries, limit) - 1``, whose miss ``th_end - goal`` has a squared
    norm below ``size`` (the largest such step), with that miss and ``moved = 1``; none:
    ``(w, r, 0)``. Each trial is a conditional's branch, evaluated only where the larger steps
    failed (most steps take the first: one map evaluation instead of ``tries``)."""
    n = len(exponents) + 1
    forward = piece_function(exponents, SUBSTEPS).mapaccum("forward", P)
    q0, w, dx = ca.MX.sym("q0", n + 1), ca.MX.sym("w", 2 * P), ca.MX.sym("dx", 2 * P)
    goal, K, size, r = (ca.MX.sym("goal", n), ca.MX.sym("K", n - 1), ca.MX.sym("size"),
                        ca.MX.sym("r", n))
    limit = ca.MX.sym("limit")
    args = [q0, w, dx, goal, K, size, r, limit]
    chain = ca.Function(f"continuation_choice_none_{P}", args, [w, r, 0])
    V_in, rV_in = ca.MX.sym("V", 2 * P), ca.MX.sym("rV", n)
    take = ca.Function(f"continuation_choice_take_{P}", [V_in, rV_in, *args],
                       [V_in, rV_in, 1])
    for j in reversed(range(tries)):   # built from the smallest step up
        V = w - 0.5 ** j * dx
        rV = forward(q0, ca.reshape(V, 2, P), ca.repmat(K, 1, P))[1:, P - 1] - goal
        later = ca.Function(f"continuation_choice_after_{j}_{tries}_{P}",
                            [V_in, rV_in, *args], chain.call(args))
        pick = ca.Function.if_else(f"continuation_choice_pick_{j}_{tries}_{P}", take, later)
        chain = ca.Function(f"continuation_choice_from_{j}_{tries}_{P}", args, pick.call(
            [ca.logic_and(ca.sumsqr(rV) < size, j < limit), V, rV, *args]))
    return chain


#: The damping of the compiled "undamped" step (relative to the mean diagonal): a system that
#: is singular (a joint no free rate moves) then gets its least-squares step, as numpy's
#: lstsq gives the Python loop; CasADi's compiled solve fails the whole call on it (with
#: 1e-12 and 1e-10 it did, on one piece moving three joints). 1e-8 moves a regular step by a
#: relative 1e-8 or so, and the steps still converge fast to the target.
SINGULAR_DAMPING = 1e-8


def damped_kernel(gains: tuple[float, ...], exponents: tuple[int, ...], P: int) -> BoundCall:
    """One step of :func:`correct_signed` in one call, ``(q0, W, goal, D2, signs, damping,
    halvings) -> (th - goal, W_new, th_new - goal, accepted)``: the miss at ``W`` and the
    sign-keeping step (:func:`signed_step`, :data:`MAX_ACTIVE` rounds of its active set)
    damped by ``damping`` (Levenberg-Marquardt, relative to the mean diagonal), the first of
    its first ``halvings`` fractions (:data:`HALVINGS`) that shrinks the miss; ``accepted``
    0 when none does (then ``W_new`` is ``W``). :func:`damped_correct` drives it (the
    dampings in turn, early stops): what the Python loop did with a map call per trial and a
    numpy active set per damping."""
    return BoundCall(_damped_kernel(tuple(exponents), P), gains)


def _signed_direction(Jt: ca.MX, r: ca.MX, w: ca.MX, D2: ca.MX, signs: ca.MX,
                      damping: ca.MX | None, rounds: int) -> ca.MX:
    """:func:`signed_step` as an expression: the weighted least-norm step ``dx`` (``w - dx``
    the new rates) damped by ``damping`` (None: undamped), ``rounds`` rounds of its active
    set (a rate the step would take across 0 is held there)."""
    m = Jt.shape[0]
    ones = ca.DM.ones(m, 1)
    fixed = D2 == 0
    dx = w
    for _ in range(rounds):
        d = D2 * (1 - fixed)
        JD = Jt * ca.mtimes(ones, d.T)
        A = ca.mtimes(JD, Jt.T)
        if damping is not None:
            A = A + damping * (ca.trace(A) / m) * ca.MX.eye(m)
        rhs = r - ca.mtimes(Jt, fixed * w)
        step = ca.mtimes(JD.T, ca.solve(A, rhs))
        dx = step * (1 - fixed) + w * fixed
        fixed = fixed + (1 - fixed) * ((w - dx) * signs < 0)
    crossed = (w - dx) * signs < 0
    return dx * (1 - crossed) + w * crossed


@functools.lru_cache(maxsize=64)
def _damped_kernel(exponents: tuple[int, ...], P: int) -> CompiledCall:
    n = len(exponents) + 1
    F = _piece_step(exponents)
    K = ca.MX.sym("K", n - 1)
    q0 = ca.MX.sym("q0", n + 1)
    W = ca.MX.sym("W", 2, P)
    goal = ca.MX.sym("goal", n)
    D2 = ca.MX.sym("D2", 2 * P)
    signs = ca.MX.sym("signs", 2 * P)
    damping = ca.MX.sym("damping")
    halvings = ca.MX.sym("halvings")
    w = ca.vec(W)
    x, J = _end_and_jacobian(F, q0, w, K, P)
    Jt = J[1:, :]
    r = x[1:] - goal
    size = ca.sumsqr(r)
    dx = _signed_direction(Jt, r, w, D2, signs, ca.fmax(damping, SINGULAR_DAMPING), MAX_ACTIVE)
    # the first of the first `halvings` fractions that shrinks the miss, each tried only where
    # the larger ones failed (HALVINGS are 2^-j)
    choose = _halving_choice(exponents, P, DAMPED_TRIES)
    chosen_w, chosen_r, accepted = choose.call([q0, w, dx, goal, K, size, r, halvings])
    fn = ca.Function(f"continuation_damped_{P}", [q0, W, goal, D2, signs, damping, halvings, K],
                     [r, ca.reshape(chosen_w, 2, P), chosen_r, accepted])
    return CompiledCall(fn, 8, (0, 1, 2, 3))


def _padded(emap: "PieceMap", W0: np.ndarray, signed: bool, floor: float | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' inputs of the rates ``W0`` ``(M, 2)``, padded in front to the map's size
    ``P``: the rates ``W`` (``signed``: those at rest exactly 0), their signs (0 at rest),
    and the padded rates, signs (``signed``; else 0: any sign) and squared weights
    (:func:`piece_weights`: ``signed``, 0 where at rest; else of ``floor``)."""
    W = np.array(W0, float)
    scale = float(np.max(np.abs(W), initial=0.0))
    signs = np.where(np.abs(W) > 1e-9 * scale, np.sign(W), 0.0)
    if signed:
        W[signs == 0.0] = 0.0
    P, M = emap.P, emap.M
    full = np.zeros((P, 2))
    full[P - M:] = W
    s_full = np.zeros((P, 2))
    if signed:
        s_full[P - M:] = signs
    D2_full = np.zeros(2 * P)
    D2_full[2 * (P - M):] = (piece_weights(W0, signs == 0.0) if signed
                             else piece_weights(W0, None, floor))
    return W, signs, full, s_full, D2_full


def _unpadded(emap: "PieceMap", W_end: np.ndarray, err: float, W: np.ndarray,
              signs: np.ndarray, signed: bool) -> tuple[float, np.ndarray]:
    """A kernel's answer ``(miss, rates (M, 2))`` from its padded rates ``W_end``: the miss
    ``inf`` and the rates ``W`` back when it is not finite or (``signed``) a sign crossed;
    ``signed``, the rates at rest held at exactly 0 (the kernels' arithmetic leaves denormals
    there)."""
    W_new = np.asarray(W_end, float).reshape(emap.P, 2)[emap.P - emap.M:].copy()
    if signed:
        W_new[signs == 0.0] = 0.0
    if not (math.isfinite(err) and np.isfinite(W_new).all()) or \
            (signed and (W_new * signs < 0.0).any()):
        return math.inf, W
    return err, W_new


def damped_correct(emap: "PieceMap", q0: np.ndarray, goal: np.ndarray, W0: np.ndarray,
                   target: float = TARGET, max_steps: int = SIGNED_STEPS
                   ) -> tuple[float, np.ndarray, int]:
    """:func:`correct_signed` with each trial one compiled call (:func:`damped_kernel`): the
    same steps, dampings, halvings and stops. Returns the map's miss (rad, max norm), the
    rates ``(M, 2)`` and the steps taken."""
    W, signs, full, s_full, D2_full = _padded(emap, W0, True, None)
    P = emap.P
    fn = damped_kernel(emap.gains, emap.exponents, P)
    q0 = np.asarray(q0, float)
    goal = np.asarray(goal, float)
    err, size = math.inf, math.inf
    steps = stalls = 0
    mu = 0.0
    while steps <= max_steps:
        accepted = False
        for damping in ((mu,) if mu else ()) + DAMPINGS:
            r, V, rV, ok = fn(q0, full, goal, D2_full, s_full, np.array([damping]),
                              np.array([5.0 if damping == 0.0 else 2.0]))
            err, size = float(np.abs(r).max()), float(r @ r)
            if not math.isfinite(size) or err <= target or steps == max_steps:
                break
            if ok[0] == 1.0:
                accepted = True
                break
        if not accepted:
            break
        mu = 0.5 * damping if damping > 1e-6 else 0.0
        s2 = float(rV @ rV)
        stalls = stalls + 1 if s2 > STALL * size else 0
        full = V.reshape(P, 2)
        steps += 1
        if stalls >= 3:
            err = float(np.abs(rV).max())
            break
    return (*_unpadded(emap, full, err, W, signs, True), steps)


def halving_correct(emap: "PieceMap", q0: np.ndarray, goal: np.ndarray, W0: np.ndarray,
                    floor: float | None = WEIGHT_FLOOR) -> tuple[float, np.ndarray]:
    """The any-sign correction in one compiled call (:func:`halving_kernel`) from ``W0``
    ``(M, 2)``, weights of ``floor``: the map's miss (rad, max norm; inf when not finite)
    and the rates ``(M, 2)``."""
    W, signs, full, _, D2_full = _padded(emap, W0, False, floor)
    fn = halving_kernel(emap.gains, emap.exponents, emap.P)
    W_end, r = fn(np.asarray(q0, float), full, np.asarray(goal, float), D2_full)
    return _unpadded(emap, W_end, float(np.abs(r).max()), W, signs, False)


def kernel_correct(emap: "PieceMap", q0: np.ndarray, goal: np.ndarray, W0: np.ndarray,
                   signed: bool = True, floor: float | None = WEIGHT_FLOOR
                   ) -> tuple[float, np.ndarray]:
    """The correction in one compiled call (:func:`signed_kernel`) from ``W0`` ``(M, 2)``:
    ``signed``, no rate changes sign (a rate at rest stays at rest); else any sign, weights
    of ``floor`` (:func:`piece_weights`). Returns the map's miss (rad, max norm; inf when a
    step was singular or, ``signed``, a sign crossed) and the rates ``(M, 2)``."""
    W, signs, full, s_full, D2_full = _padded(emap, W0, signed, floor)
    fn = signed_kernel(emap.gains, emap.exponents, emap.P)
    W_end, r = fn(np.asarray(q0, float), full, np.asarray(goal, float), D2_full, s_full)
    return _unpadded(emap, W_end, float(np.abs(r).max()), W, signs, signed)


def prepare(gains: tuple[float, ...], exponents: tuple[int, ...], build: bool = False
            ) -> None:
    """Build every size's map and kernels of a robot ahead of its first replan (a warm
    worker: the first call of a size otherwise pays its construction, 10-100 ms).

    ``build`` (a benchmark): also compile the missing kernels now when compiled functions
    are on (:func:`optimizer.native.configure`; 3-10 s each, cached per machine). Otherwise
    a kernel's build starts in the background at its first call (a service does not start
    some thirty compilers at once at its start-up). The verification's functions:
    :func:`~.piece_proof.prepare`."""
    exponents = tuple(exponents)
    _piece_end(exponents)
    kernels: list[CompiledCall] = []
    for P in SIZES:
        kernels += [_signed_kernel(exponents, P), _halving_kernel(exponents, P),
                    _damped_kernel(exponents, P),
                    _jacobian_map(exponents, P)]
    if build:
        for kernel in kernels:
            kernel.current(wait=True)


def size_for(M: int) -> int:
    """The compiled size that holds ``M`` pieces (``M`` itself above the largest)."""
    return next((P for P in SIZES if P >= M), M)


class PieceMap:
    """The end state and Jacobian of ``M`` pieces of displacement rates ``(M, 2)`` from ``q0``
    (the compiled :func:`jacobian_map` of the next size, padded in front)."""

    def __init__(self, gains: tuple[float, ...], exponents: tuple[int, ...], M: int) -> None:
        self.M, self.P = M, size_for(M)
        self.gains, self.exponents = gains, exponents
        self.nq = len(gains) + 2
        self._call = jacobian_map(gains, exponents, self.P)

    def __call__(self, q0: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """End state and Jacobian ``(n+1, 2M)`` at rates ``W`` ``(M, 2)``."""
        full = np.zeros((self.P, 2))
        full[self.P - self.M:] = W
        end, jac = self._call(np.asarray(q0, float), full)
        J = jac.reshape(2 * self.P, self.nq).T[:, 2 * (self.P - self.M):]
        return end, J


def piece_weights(W0: np.ndarray, held: np.ndarray | None = None,
                  floor: float | None = WEIGHT_FLOOR) -> np.ndarray:
    """The squared weights of the rates' changes (flat): ``(|w| + floor max|w|)^2``, 0 where
    held; ``floor`` None: all 1 (the plain least-norm step)."""
    d = np.abs(np.asarray(W0, float)).ravel()
    if floor is None:
        d = np.ones_like(d)
    else:
        d = d + floor * max(float(d.max(initial=0.0)), 1e-3)
    D2 = d * d
    if held is not None:
        D2[np.asarray(held, bool).ravel()] = 0.0
    return D2


def weighted_step(J: np.ndarray, r: np.ndarray, D2: np.ndarray, mu: float = 0.0) -> np.ndarray:
    """The ``dx`` of least ``|D^-1 dx|`` with ``J dx = r`` (damped by ``mu`` relative to the
    mean diagonal of ``J D^2 J^T``), flat.

    A singular system (rows no free rate moves) is solved in the least-squares sense.
    """
    JD = J * D2
    A = JD @ J.T
    if mu:
        A = A + mu * (float(np.trace(A)) / A.shape[0]) * np.eye(A.shape[0])
    try:
        y = np.linalg.solve(A, r)
    except np.linalg.LinAlgError:
        # rows that the free rates cannot move (all held): least squares on the others
        y = np.linalg.lstsq(A, r, rcond=None)[0]
    return np.asarray(JD.T @ y)


def correct_pieces(emap: PieceMap, q0: np.ndarray, goal: np.ndarray, W0: np.ndarray,
                   target: float = TARGET, max_steps: int = MAX_STEPS,
                   held: np.ndarray | None = None, floor: float | None = WEIGHT_FLOOR
                   ) -> tuple[float, np.ndarray, int]:
    """Weighted least-norm Gauss-Newton from ``W0`` onto ``th(end) = goal`` (``phi`` free).

    Each step solves ``min |D^-1 dW|`` subject to ``J dW = -r`` (``D = |W0| + floor``), damped
    by ``mu`` (``(J D^2 J^T + mu I)``) when the full step does not shrink the miss.

    Returns
    -------
    (float, ndarray, int)
        The map's miss (rad, max norm), the rates ``(M, 2)``, the steps taken.
    """
    W = np.array(W0, float)
    D2 = piece_weights(W, held, floor)
    if held is not None:
        W[np.asarray(held, bool)] = 0.0
    end, J = emap(q0, W)
    r = end[1:] - goal
    err = float(np.abs(r).max())
    size = float(r @ r)
    steps = 0
    while err > target and steps < max_steps:
        accepted = False
        try:
            full = weighted_step(J[1:], r, D2).reshape(W.shape)
        except np.linalg.LinAlgError:
            break
        for alpha in HALVINGS:
            V = W - alpha * full
            end2, J2 = emap(q0, V)
            r2 = end2[1:] - goal
            e2 = float(np.abs(r2).max())
            s2 = float(r2 @ r2)
            if math.isfinite(s2) and s2 < size:
                accepted = True
                break
        if not accepted:
            break
        W, J, r, err, size = V, J2, r2, e2, s2
        steps += 1
    return err, W, steps


def signed_step(J: np.ndarray, r: np.ndarray, D2: np.ndarray, W: np.ndarray,
                 signs: np.ndarray, mu: float = 0.0) -> np.ndarray:
    """The weighted least-norm step (:func:`weighted_step`) of the rates ``W`` (flat) in
    which no rate crosses to the sign opposite ``signs`` (0: held at rest): a rate the step
    would take across 0 is set to 0 exactly (its share of ``J dx = r`` moved to the right
    side) and the others solved again (an active set, a few rounds). Returns ``dx`` with
    ``W - dx`` the new rates."""
    free = D2 > 0.0
    fixed = np.zeros_like(free)
    rhs = r
    dx = np.zeros_like(W)
    for _ in range(MAX_ACTIVE):
        d = np.where(free & ~fixed, D2, 0.0)
        step = weighted_step(J, rhs, d, mu)
        step[fixed] = W[fixed]
        new = W - step
        bad = ~fixed & (new * signs < 0.0)
        dx = step
        if not bad.any():
            return dx
        fixed |= bad
        rhs = r - J[:, fixed] @ W[fixed]
    dx[(W - dx) * signs < 0.0] = W[(W - dx) * signs < 0.0]
    return dx


def correct_signed(emap: PieceMap, q0: np.ndarray, goal: np.ndarray, W0: np.ndarray,
                   target: float = TARGET, max_steps: int = SIGNED_STEPS
                   ) -> tuple[float, np.ndarray, int]:
    """Gauss-Newton onto ``th(end) = goal`` in which no rate changes sign (a rate at rest
    stays at rest; one may come to rest and move again in its own direction): each step is
    the weighted least-norm step of :func:`correct_pieces` restricted to the rates' signs
    (:func:`signed_step`), halved until the miss shrinks, then damped (Levenberg-Marquardt,
    :data:`DAMPINGS`): near the directions only higher brackets reach the plain step
    overshoots, a damped one still descends.

    Returns
    -------
    (float, ndarray, int)
        The map's miss (rad, max norm), the rates ``(M, 2)``, the steps taken.
    """
    W = np.array(W0, float)
    scale = float(np.max(np.abs(W), initial=0.0))
    signs = np.where(np.abs(W) > 1e-9 * scale, np.sign(W), 0.0).ravel()
    W[(signs == 0.0).reshape(W.shape)] = 0.0
    D2 = piece_weights(W0, signs == 0.0)
    end, J = emap(q0, W)
    r = end[1:] - goal
    err = float(np.abs(r).max())
    size = float(r @ r)
    steps = stalls = 0
    mu = 0.0
    while err > target and steps < max_steps:
        accepted = False
        for damping in ((mu,) if mu else ()) + DAMPINGS:
            try:
                dx = signed_step(J[1:], r, D2, W.ravel(), signs, damping).reshape(W.shape)
            except np.linalg.LinAlgError:
                continue
            for alpha in HALVINGS[:5] if damping == 0.0 else HALVINGS[:2]:
                V = W - alpha * dx
                end2, J2 = emap(q0, V)
                r2 = end2[1:] - goal
                s2 = float(r2 @ r2)
                if math.isfinite(s2) and s2 < size:
                    accepted = True
                    break
            if accepted:
                # keep a damping that was needed (halved), drop it once plain steps work
                mu = 0.5 * damping if damping > 1e-6 else 0.0
                break
        if not accepted:
            break
        # Gauss-Newton that can reach the goal converges fast: a step that removes little of
        # the miss (twice) says the signs keep the goal out of reach
        stalls = stalls + 1 if s2 > STALL * size else 0
        W, J, r, size = V, J2, r2, s2
        err = float(np.abs(r).max())
        steps += 1
        if stalls >= 3:
            break
    return err, W, steps


__all__ = ["jacobian_map", "piece_function", "HALVING_STEPS", "HALVING_TRIES", "halving_correct", "halving_kernel", "damped_correct", "damped_kernel", "CompiledCall", "KERNEL_STEPS", "KERNEL_ROUNDS", "kernel_correct", "signed_kernel", "DAMPINGS", "HALVINGS", "correct_signed", "signed_step", "MAX_STEPS", "PieceMap", "SIZES", "SUBSTEPS", "TARGET", "WEIGHT_FLOOR",
           "correct_pieces", "piece_end", "BoundCall", "prepare", "piece_weights", "size_for",
           "weighted_step"]
