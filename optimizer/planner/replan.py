"""Closed loop: the continuation of a plan from a measured state, to the same goal, at once.

A controller runs a plan, measures the state ``q_m = (phi, th_1..th_n)`` at time ``t`` and asks
for the rest of the motion from there. :func:`replan` answers with a continuation that

* starts at the rates being commanded at ``t`` (given, or the plan's own at ``t``), so the
  drive sees no jump;
* ends at the plan's goal at rest, by the plan's end or by a new ``duration``;
* is verified on the original model like any plan (cascade quadrature of its exact input
  pieces, the region at every break, the handed-out linear form replayed);
* is a pure function of its arguments (nothing is kept between calls).

How (actuator-rate plans: ``shooting``, ``penalty``, the default)
-----------------------------------------------------------------
A plan's rates are ``u(t) = g(lam(t)) lam'(t)``: piecewise-constant *geometric* rates ``g``
on pieces of the path's parameter ``lam``, run along a time law ``lam(t)``
(:mod:`optimizer.timing`, read by :mod:`.plan_state`; phases of constant jerk, ``lam' = 0``
at every stop; a plan without a time law has ``lam = t`` and rates that jump at its breaks).
The model is driftless: the state reached at ``lam`` does not depend on the time law, so the
geometry and the timing are corrected separately.

1. **Kept motion.** The motion under way runs on to the end of its piece at the commanded
   rates (the current piece's direction is the commanded rate over ``lam'(t)``): where the
   plan's law stops there, as planned; where it runs on to a later stop, ``lam'`` is brought
   to rest at the piece's end (:func:`~.kept_motion.to_piece_end`), so that every later
   piece can change direction (:mod:`.kept_motion`). In the last piece, where nothing would be left, it is braked to rest within
   :data:`BRAKE_TIME` instead (``lam'`` falls linearly; the rest of the piece becomes
   correctable). The rates stay continuous.
2. **Tail and correction.** The last piece is split into a geometric tail
   (:data:`TAIL_PIECES` + 1 parts, each :data:`TAIL_RATIO` of what is left, run in equal
   times: little motion is left near the end, where no later replan corrects the plant).
   The rates of the later pieces start at the plan's (the warm start) and take weighted
   least-norm Gauss-Newton steps onto the goal (``th_1..th_n``; ``phi`` is free). First
   every rate keeps its sign (each step restricted to the rates' signs, an active set): no
   reversal of ``phi`` or ``th1`` is added; five full steps in one compiled call
   (:func:`~.continuation_map.signed_kernel`); least-squares, halved and damped steps
   where its systems were singular (each trial one compiled call,
   :func:`~.continuation_map.damped_correct`). Unless ``keep_reversals``, any sign when that fails (halved steps, one compiled
   call, :func:`~.continuation_map.halving_kernel`). The
   remaining law is kept when nothing was split or stopped early; otherwise every piece runs
   rest to rest in equal times (:func:`~.plan_state.law_after_stop`), within the plan's rate
   limits where it has them (:mod:`.continuation_law`: later than the plan's end where the
   time left is too short for them).
3. **Proof.** The continuation's pieces are integrated on the original model by compiled
   RK4 at two step sizes (:func:`~.piece_proof.integrate_pieces`; Richardson's estimate
   of the error at most 1e-11 rad, else by cascade quadrature); a miss above 1e-9 rad gets
   one defect-corrected step; every joint checked at every break (monotone on a
   constant-rate piece), the handed-out samples replayed by their rule.
   The corrected part keeps :data:`~.continuation_proof.REPLAN_MARGIN` from the limits (or half the room its stop
   or the goal leaves): the plant is not the model, and a path verified 1e-4 rad from pi/2
   is one a plant a few percent off crosses.
4. **Middle route: one warm-started NLP** (:mod:`.warm_continuation`). Where
   Gauss-Newton fails, the shooting NLP of the first rung from the stop, its guess the
   plan's rest from there (rates held to the plan's signs per interval with
   ``keep_reversals``), fatrop alone; then Gauss-Newton from its rates onto the original
   model's goal, and the proof of step 3.
5. **Fallback: the full planner.** Where those fail, or a plan of chained inputs (braked
   first): the full planner (method ``shooting``, then ``penalty``) plans from the stop; its
   last piece is split into the same geometric tail, and its pieces run rest to rest until
   the end.
6. **At the start, at rest** (up to :data:`FRESH_PLAN_UP_TO_JOINTS` joints). At the plan's
   start with nothing under way (the commanded rates 0) no motion needs continuing: where the corrected plan reverses ``phi`` or ``th1``
   more often than the plan, the full planner plans afresh from the measured state (its
   ranking: fewest reversals first), and its plan is answered when it reverses them less
   often. (The first replan of a closed loop corrects the start error: in the benchmark's
   3-joint closed loops with identified gains, 30 goals with starts 0.5 deg off, the loops
   that reversed an actuator more often than the plan went from 4 to 1; later replans
   continue a motion and keep to steps 1-5.)

Why not change the current piece: its direction changed mid-motion would jump the rates; a
stop is where the direction may change. The motion after the last replan is what no replan
corrects (docs/closed-loop.md). At ``n >= 4`` the end map's Jacobian is nearly singular in
the directions only higher brackets reach (smallest weighted singular values 1e-4 of the
largest on the benchmark's goals): an error there needs a second-order correction, which
Gauss-Newton does not find; the warm-started NLP finds it on most 4-joint states and many
5-joint ones, the full planner on the rest. At 3 joints the same happens near goals where a
joint barely follows the one before it (th2 near pi/2: th3 moved by 4e-4 rad over a whole
plan, the end map's third singular value 1e-4 of the first): there the warm NLP answered
in 5-16 ms where the full planner took 13-58 ms.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import InfeasibleError, NumericalError, PlannerError, SolverTimeoutError
from ..model import Robot
from ..problem import PlanRequest
from ..region import Region
from ..results import Plan, json_safe
from .plan import plan as full_plan
from .plan_state import REST, PlanState, TimeLaw, braking, finite_array, invalid, read_plan
from .kept_motion import BRAKE_TIME, Kept, brake_now, run_on
from .continuation_law import braking_time, law_within_limits
from .continuation_map import (HALVING_STEPS, KERNEL_STEPS, WEIGHT_FLOOR, PieceMap,
                               correct_pieces, damped_correct, halving_correct,
                               kernel_correct, piece_end, piece_weights, weighted_step)
from .continuation_proof import Continuation, finish_continuation
from .warm_continuation import warm_nlp_pieces
from .rules import joint_limits, kept_limits

#: The continuation's last piece is split into this many parts and one more...
TAIL_PIECES = 4
#: ... each this fraction of the rest: run in equal times, the motion slows geometrically.
TAIL_RATIO = 0.35
#: The tail's parts as shares of the last piece (each TAIL_RATIO of what is left, the rest last).
_TAIL_SHARES = np.concatenate([(1.0 - TAIL_RATIO) * TAIL_RATIO ** np.arange(TAIL_PIECES),
                               [TAIL_RATIO ** TAIL_PIECES]])
#: The compiled kernel's correction is taken when its map misses by at most this (rad); the
#: verification's defect step removes the map's own error (~1e-9 rad).
KERNEL_ACCEPT = 1e-9
#: Where the kernel misses by more than that but at most this (rad), or gives no finite
#: answer, the damped sign-keeping steps try (:func:`~.continuation_map.damped_correct`, see
#: :func:`_correct`).
LOOP_AFTER_KERNEL = 1e-5
#: Below this many joints the damped steps also try where the kernel's system was singular
#: (no finite answer). They kept the signs there in 3-joint closed loops (22 of 45 singular
#: kernels over two runs of five goals), but from 4 joints on seldom: 0 of 19, 58 and 131
#: singular kernels in closed loops of 4 and 5 joints (with and without identified gains
#: and kept reversals), 2 of 407 on 4- and 5-joint states 0.005-0.5 deg off plans of a seed
#: the benchmark does not use; each try costs about 0.5 ms, a sixth of a 4-joint replan.
#: With ``keep_reversals`` they always try: there the signs are the request (a saved 4-joint
#: closed-loop state, tests/data/replan_kept_signs_case.json, keeps them only through them).
DAMPED_SINGULAR_BELOW_JOINTS = 4
#: Up to this many joints a replan at the plan's start at rest tries a fresh plan where the
#: correction adds reversals (step 6 of the module): from 6 joints the full planner takes
#: seconds on such goals, or finds nothing within the time limit, where the correction has
#: answered in milliseconds.
FRESH_PLAN_UP_TO_JOINTS = 5
# ------------------------------------------------------------------ the replanner
def _commanded(ps: PlanState, t: float) -> np.ndarray:
    """The rates the plan commands at ``t``."""
    if ps.rates is not None:
        sig, ds, _ = ps.law.at(t)
        return ps.rates[ps.piece_at(sig)] * ds
    assert ps.path_t is not None and ps.path_u is not None
    # a chained plan: its handed-out linear form (the later copy of a doubled sample)
    pt, pu = ps.path_t, ps.path_u
    k = min(max(int(np.searchsorted(pt, t, side="right")) - 1, 0), pt.size - 2)
    a, b = pt[k], pt[k + 1]
    w = 0.0 if b <= a else (t - a) / (b - a)
    return np.asarray((1.0 - w) * pu[k] + w * pu[k + 1], float)


def replan(plan: Plan | PlanState | Mapping[str, Any], time_: float, state: Any,
           rates: Any = None, duration: float | None = None, *,
           plain: bool = True, time_limit: float = 10.0,
           keep_reversals: bool = False, gains: Any = None,
           fallback: bool = True) -> dict[str, Any]:
    """The continuation of ``plan`` from the measured ``state`` at ``time_`` (see the module).

    Parameters
    ----------
    plan : Plan, PlanState or dict
        An answer of ``/v1/plans`` or ``/v1/replans`` (or its compact form).
    time_ : float
        Seconds since the plan's start (its time axis: a replan's answer keeps it).
    state : sequence of float
        Measured ``(phi, th_1..th_n)`` (rad).
    rates : sequence of 2 floats, optional
        The rates being commanded at ``time_`` (rad/s); default the plan's.
    duration : float, optional
        A new end time (s, on the plan's time axis); default the plan's end.
    time_limit : float
        Seconds for the full planner, when it runs (the fallback).
    keep_reversals : bool
        Hand out no continuation whose rates reverse ``phi`` or ``th1`` more often than the
        plan's rest does (the fast path keeps every rate's sign; a fallback plan that adds a
        reversal is refused, :class:`InfeasibleError` naming ``keep_reversals``). False (the
        default): the goal first; ``indicators.reversals`` say what the continuation does.
    plain : bool
        True: Python lists and floats (:func:`~optimizer.results.json_safe`); False: numpy
        arrays left in, for an encoder that writes them (the service's orjson).
    gains : sequence of n - 1 floats, optional
        The robot's ``K_2..K_n`` to continue on (a plant's gains as estimated from its
        motion, :mod:`optimizer.identification`); default the plan's. The continuation is
        planned and verified on that model, and its answer's ``robot`` says so.
    fallback : bool
        False: only the fast path and the warm-started NLP (bounded by fatrop's iteration
        cap), never the full planner; :class:`InfeasibleError` naming ``fallback`` where
        they fail.

    Returns
    -------
    dict
        An answer with the shape of a plan's: ``path.t`` runs from ``time_`` to the end.

    Raises
    ------
    InvalidRequestError
        A state outside the region (``state``), a time past the end (``time``), rates of
        the wrong shape (``rates``), a plan that is not one of ours (``plan....``).
    InfeasibleError, NumericalError
        No continuation could be verified.
    """
    t_start = time.perf_counter()
    ps = read_plan(plan)
    n = ps.robot.n
    if gains is not None:
        K = finite_array(gains, "gains")
        if K.shape != (n - 1,) or np.any(K <= 0.0):
            raise invalid(f"gains must give K_2..K_{n} ({n - 1} positive numbers)", "gains")
        ps = replace(ps, robot=Robot(tuple(float(k) for k in K), ps.robot.exponents))
    t = float(time_)
    if not math.isfinite(t) or t < ps.start_time - 1e-12 or t >= ps.end_time:
        raise invalid(f"time = {t!r} s must lie in [{ps.start_time:.6g}, {ps.end_time:.6g}) s, "
                   "the plan's remaining span", "time")
    q_m = finite_array(state, "state")
    if q_m.shape != (n + 1,):
        raise invalid(f"state must give phi and th1..th{n} ({n + 1} numbers), not {q_m.size}",
                   "state")
    T_end = ps.end_time if duration is None else float(duration)
    if not math.isfinite(T_end) or T_end <= t:
        raise invalid(f"duration = {duration!r} s must end after time = {t:.6g} s", "duration")
    # the measured state is checked before the request is built: a state outside the plan's
    # limits is named as the state's element, not as the request's start or bounds
    lo, hi = kept_limits(Region(ps.robot, joint_bounds=ps.joint_bounds), ps.joint_bounds,
                         q_m[1:], ps.goal)
    for i, (x, a, b) in enumerate(zip(q_m[1:], lo, hi)):
        if not a < x < b:
            raise invalid(f"state[{i + 1}] = th{i + 1} = {x:.6g} rad is outside ({a:.6g}, "
                       f"{b:.6g}) rad, the singularity-free region within the joint bounds: "
                       "no continuation starts there", f"state[{i + 1}]")
    req = PlanRequest(start=tuple(q_m[1:]), goal=tuple(ps.goal), robot=ps.robot,
                      phi_start=float(q_m[0]), duration=T_end - t, samples=ps.samples,
                      joint_bounds=ps.joint_bounds, time_limit=float(time_limit))
    u_c = _commanded(ps, t) if rates is None else finite_array(rates, "rates", (2,))
    timing: dict[str, float] = {}
    errors: list[str] = []
    cont: Continuation | None = None
    if ps.rates is not None:
        try:
            cont = _fast(ps, req, t, q_m, u_c, T_end, keep_reversals)
        except PlannerError as exc:
            errors.append(f"{exc.code}: {exc.message}")
        except (ArithmeticError, ValueError, IndexError, np.linalg.LinAlgError) as exc:
            # a defect of the fast path on an edge case: the full planner still answers
            errors.append(f"fast path: {type(exc).__name__}: {exc}")
    timing["correction"] = time.perf_counter() - t_start
    result: dict[str, Any] | None = None
    if cont is not None:
        try:
            result = finish_continuation(ps, req, t, q_m, u_c, cont, timing, (lo, hi))
        except PlannerError as exc:
            errors.append(f"{exc.code}: {exc.message}")
    if result is None and ps.rates is not None:
        try:
            cont = _warm(ps, req, t, q_m, u_c, T_end, keep_reversals,
                         t_start + float(time_limit))
            if keep_reversals:
                _refuse_added_reversals(ps, t, cont, errors)
            result = finish_continuation(ps, req, t, q_m, u_c, cont, timing, (lo, hi))
        except PlannerError as exc:
            errors.append(f"{exc.code}: {exc.message}")
        except (ArithmeticError, ValueError, IndexError, np.linalg.LinAlgError) as exc:
            errors.append(f"warm NLP: {type(exc).__name__}: {exc}")
    if (result is not None and cont is not None and fallback and not keep_reversals
            and n <= FRESH_PLAN_UP_TO_JOINTS and _at_rest_at_start(ps, t, u_c)
            and cont.route != "full_planner"):
        result = _fresh_when_fewer_reversals(ps, req, t, q_m, u_c, T_end, cont, result,
                                             timing, (lo, hi), t_start, errors)
    if result is None:
        if not fallback:
            raise InfeasibleError("the fast path found no continuation, and the full planner "
                                  "was not asked for (fallback=false)", field="fallback",
                                  diagnostics={"fast_path_failed": errors})
        try:
            cont = _fallback(ps, req, t, q_m, u_c, T_end, t_start + float(time_limit))
        except PlannerError as exc:
            exc.diagnostics["fast_path_failed"] = errors
            raise
        if keep_reversals:
            _refuse_added_reversals(ps, t, cont, errors)
        result = finish_continuation(ps, req, t, q_m, u_c, cont, timing, (lo, hi))
    if duration is not None and result["duration"] > T_end + 1e-9 * max(1.0, T_end):
        # the bounds need longer than the duration asked for (without one the continuation
        # ends as early as they allow)
        raise InfeasibleError(
            f"the plan's rate limits need the continuation to end at {result['duration']:.6g} s, "
            f"after duration = {T_end:.6g} s: give a later duration (or none)",
            field="duration", diagnostics={"shortest_end": result["duration"],
                                           "limits": ps.limits.as_dict()})
    result["timing"]["total"] = time.perf_counter() - t_start
    if errors:
        result["diagnostics"]["replan"]["fast_path_failed"] = errors
    return json_safe(result) if plain else result


def _at_rest_at_start(ps: PlanState, t: float, u_c: np.ndarray) -> bool:
    """Nothing is under way yet: ``t`` is the plan's start and the commanded rates are 0."""
    return t <= ps.start_time + 1e-12 and float(np.max(np.abs(u_c))) <= REST


def _fresh_when_fewer_reversals(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray,
                                u_c: np.ndarray, T_end: float, cont: Continuation,
                                result: dict[str, Any], timing: dict[str, float],
                                limits: tuple[np.ndarray, np.ndarray], t_start: float,
                                errors: list[str]) -> dict[str, Any]:
    """At the plan's start at rest a continuation need continue no motion: where the
    corrected plan (``cont``, ``result``) reverses ``phi`` or ``th1`` more often than the plan
    does, a fresh plan from the measured state (the full planner, its ranking: fewest
    reversals first) is answered instead when it reverses them less often."""
    assert ps.rates is not None
    has = sign_changes(cont.rates)
    if has <= sign_changes(ps.rates):
        return result
    try:
        fresh = _fallback(ps, req, t, q_m, u_c, T_end, t_start + float(req.time_limit))
        if sign_changes(fresh.rates) >= has:
            return result
        return finish_continuation(ps, req, t, q_m, u_c, fresh, timing, limits)
    except PlannerError as exc:
        errors.append(f"fresh plan at the start: {exc.code}: {exc.message}")
        return result


def _refuse_added_reversals(ps: PlanState, t: float, cont: Continuation,
                            errors: list[str]) -> None:
    """Raise :class:`InfeasibleError` (``keep_reversals``) where ``cont`` reverses ``phi`` or
    ``th1`` more often than the plan's rest from ``t``."""
    if ps.rates is None:
        return
    k = ps.piece_at(ps.law.at(t)[0])
    had, has = sign_changes(ps.rates[k:]), sign_changes(cont.rates)
    if has > had:
        raise InfeasibleError(
            f"the only continuation found reverses phi or th1 {has} time(s), the plan's "
            f"rest {had}: none was handed out (keep_reversals=false accepts it; or run "
            "on the current plan)", field="keep_reversals",
            diagnostics={"reversals": has, "plan_reversals": had,
                         "fast_path_failed": list(errors)})


def _pieces_end(robot: Robot, q0: np.ndarray, breaks: np.ndarray, rates: np.ndarray
                ) -> np.ndarray:
    """The state after constant-rate pieces: RK4 (:func:`~.continuation_map.piece_end`) (as
    close to the exact model as the correction's end map; the continuation's quadrature
    proves the whole)."""
    end = piece_end(tuple(robot.gains), tuple(robot.exponents))
    q = np.asarray(q0, float)
    for L, r in zip(breaks[1:] - breaks[:-1], rates):
        if L > 0.0:
            q = end(q, np.asarray(r, float) * L)[0]
    return q


@dataclass(frozen=True)
class _Setup:
    """The kept motion and the correctable pieces after it (plan time ``free``, start rates
    ``W0`` as unit-piece displacements) from the state ``q_stop`` at its stop."""

    kept: Kept
    free: np.ndarray
    W0: np.ndarray
    q_stop: np.ndarray
    emap: PieceMap
    plain_law: bool             # the plan's own law can run the rest
    braked: bool                # the motion under way is braked now


def _setup(ps: PlanState, t: float, q_m: np.ndarray, u_c: np.ndarray, T_end: float,
           brake: bool) -> _Setup:
    """Step 1-2's pieces: the motion under way run to its piece's end (``brake`` False, not
    the last piece) or braked now (the rest of its piece correctable too), the later pieces
    split when few are left, and the geometric tail."""
    assert ps.rates is not None
    kept = run_on(ps, t, u_c)
    n = ps.robot.n
    braked = brake or kept.k >= ps.rates.shape[0]
    if braked:      # stop early, what follows is corrected
        kept = brake_now(ps, t, u_c, T_end)
        braked = kept.pieces > 0        # (at rest: nothing to brake, kept as it is)
    free = np.concatenate([[kept.s_stop], ps.breaks[kept.k + 1:]]) if braked else \
        ps.breaks[kept.k:]
    rates0 = ps.rates[kept.k:]
    M = free.size - 1
    # few pieces left (near the end): split each into equal parts (the same path, more stops)
    # so that the correction has more inputs than joints to move
    split = 1 if 2 * M >= n + 2 else math.ceil((n + 2) / (2 * M))
    if split > 1:
        w = np.arange(split) / split
        free = np.concatenate([(free[:-1, None] + (free[1:] - free[:-1])[:, None] * w).ravel(),
                               free[-1:]])
        rates0 = np.repeat(rates0, split, axis=0)
    free, rates0, tailed = _tail(free, rates0)
    emap = PieceMap(tuple(ps.robot.gains), tuple(ps.robot.exponents), free.size - 1)
    # a piece of plan time L at geometric rate g moves as the unit piece at rate g L
    W0 = rates0 * (free[1:] - free[:-1])[:, None]
    q_stop = _pieces_end(ps.robot, q_m, kept.breaks, kept.rates)
    plain_law = T_end == ps.end_time and split == 1 and not braked and kept.own and not tailed
    return _Setup(kept, free, W0, q_stop, emap, plain_law, braked)


def _fast(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
          T_end: float, keep_reversals: bool = False) -> Continuation:
    """Steps 1-2 of the module: the kept motion, then Gauss-Newton on the later pieces.

    The rates keep their signs first with the motion under way run to its piece's end, then
    with it braked now (its piece's rest correctable too: near the end the piece under way
    holds most of what is left); then, unless ``keep_reversals``, any sign (run to the end).
    From :data:`DAMPED_SINGULAR_BELOW_JOINTS` joints (unless ``keep_reversals``) the damped
    sign-keeping steps after a singular kernel come last, where every other try failed: the
    steps with any sign mostly answer first, and the damped ones cost more than they find.
    """
    assert ps.rates is not None
    goal = ps.goal
    first = _setup(ps, t, q_m, u_c, T_end, brake=False)
    setups = [first]

    def signed(damp: bool) -> tuple[_Setup, Any] | None:
        for i in range(2):
            if i == len(setups):  # (built at its first use: most replans need none)
                if not (first.kept.pieces and not first.braked):
                    break
                setups.append(_setup(ps, t, q_m, u_c, T_end, brake=True))
            try:
                return setups[i], _correct(setups[i].emap, setups[i].q_stop, goal,
                                           setups[i].W0, True, damp_singular=damp)
            except NumericalError:
                pass
        return None

    damp_first = keep_reversals or ps.robot.n < DAMPED_SINGULAR_BELOW_JOINTS
    found = signed(damp_first)
    any_sign: NumericalError | None = None  # (its message has the miss in rad)
    if found is None and not keep_reversals:
        try:
            found = first, _correct(first.emap, first.q_stop, goal, first.W0, False,
                                    signed_first=False)
        except NumericalError as exc:
            if damp_first:
                raise
            any_sign = exc
    if found is None and not damp_first:
        found = signed(True)
    if found is None:
        if any_sign is not None:
            raise any_sign
        raise NumericalError("the Gauss-Newton correction of the later pieces' rates did not "
                             "reach the goal keeping their signs")
    st, correction = found
    return _corrected(ps, t, T_end, st.kept, st.free, st.q_stop, st.emap, correction,
                      st.plain_law, "gauss_newton", st.braked)


def _corrected(ps: PlanState, t: float, T_end: float, kept: Kept, free: np.ndarray,
               q_stop: np.ndarray, emap: PieceMap,
               correction: tuple[float, np.ndarray, int, np.ndarray, bool], plain_law: bool,
               route: str, braked: bool) -> Continuation:
    """The continuation of the kept motion and the corrected pieces ``free`` (a result of
    :func:`_correct`), with the defect step of its proof."""
    err, W, steps, weights, signs_kept = correction
    goal = ps.goal
    L = (free[1:] - free[:-1])[:, None]
    M = free.size - 1
    new_rates = W / L
    t_stop = kept.law.end if kept.law.phases.size else t
    if plain_law:
        later = ps.law.after(t_stop).phases
    else:
        later = law_within_limits(t_stop, T_end, free, new_rates, ps.limits, equal=True)

    def refine(exact_end: np.ndarray, current: np.ndarray) -> np.ndarray:
        # the quadrature's end missed: one step aimed where the map must end for the exact
        # model to reach the goal (a defect correction)
        _, J = emap(q_stop, current * L)
        return current - weighted_step(J[1:], exact_end[1:] - goal, weights).reshape(M, 2) / L

    return replace(_assemble(kept, free, new_rates, later, ps.plan_duration, route,
                             steps, refine), signs_kept=signs_kept, braked=braked)


def _warm(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
          T_end: float, keep_reversals: bool, deadline: float) -> Continuation:
    """The middle route (:mod:`.warm_continuation`): the motion under way run to its stop,
    one NLP from there warm-started on the plan's rest (rates held to the plan's signs with
    ``keep_reversals``, free otherwise), then Gauss-Newton onto the goal of the original
    model from the NLP's rates.

    Raises
    ------
    PlannerError
        The NLP did not converge, or its correction did not reach the goal.
    """
    assert ps.rates is not None
    st = _setup(ps, t, q_m, u_c, T_end, brake=False)
    breaks, rates = warm_nlp_pieces(ps, req, st.kept.s_stop, st.q_stop, keep_reversals,
                                    _time_left(req, deadline))
    free, rates0, _ = _tail(breaks, rates)
    emap = PieceMap(tuple(ps.robot.gains), tuple(ps.robot.exponents), free.size - 1)
    correction = _correct(emap, st.q_stop, ps.goal, rates0 * (free[1:] - free[:-1])[:, None],
                          keep_reversals)
    return _corrected(ps, t, T_end, st.kept, free, st.q_stop, emap, correction, False,
                      "warm_nlp", st.braked)


def _correct(emap: PieceMap, q0: np.ndarray, goal: np.ndarray, W0: np.ndarray,
             keep_reversals: bool, signed_first: bool = True, *,
             damp_singular: bool | None = None
             ) -> tuple[float, np.ndarray, int, np.ndarray, bool]:
    """The later pieces' rates moved onto the goal: first with no rate changing sign
    (:func:`~.continuation_map.kernel_correct`, one compiled call of full sign-keeping steps:
    a rate at rest stays at rest, one may come to rest and no further): no reversal of
    ``phi`` or ``th1`` is added; then, unless ``keep_reversals``, with any sign
    (:func:`~.continuation_map.halving_correct`, the halved steps of
    :func:`~.continuation_map.correct_pieces` in one compiled call; weighted, then the plain
    least-norm step). Returns the map's miss, the rates, the steps, the
    weights used (for the defect step) and whether the signs were kept.

    ``keep_reversals``: no rate may change sign (raise where they cannot all keep theirs).
    ``damp_singular``: the damped sign-keeping steps follow a kernel whose system was
    singular (default: with ``keep_reversals``, or below
    :data:`DAMPED_SINGULAR_BELOW_JOINTS` joints).

    Raises
    ------
    NumericalError
        No correction reached the goal.
    """
    err = math.inf
    if damp_singular is None:
        damp_singular = keep_reversals or q0.size - 1 < DAMPED_SINGULAR_BELOW_JOINTS
    if signed_first:
        # one compiled call of full steps; where a system was singular (fewer rates left
        # free than joints to move: no finite answer, or a hair off the goal), the long way,
        # which solves those by least squares and halves and damps its steps (each trial one
        # compiled call). In closed loop (n = 3, five goals) it kept the signs on 7 of 118
        # corrections where the kernel had not, each of them singular (without it two goals
        # reversed four times more); where the kernel ends far off the goal (1e-4 to 1e3
        # rad) it reached it on 1 of 74 corrections at n = 4 and none of 81 random states:
        # not run there; nor after a singular kernel from DAMPED_SINGULAR_BELOW_JOINTS on,
        # unless the signs must be kept (keep_reversals)
        err, W = kernel_correct(emap, q0, goal, W0)
        if err <= KERNEL_ACCEPT:
            return err, W, KERNEL_STEPS, piece_weights(W0, W == 0.0), True
        if err <= LOOP_AFTER_KERNEL or (not math.isfinite(err) and damp_singular):
            err, W, steps = damped_correct(emap, q0, goal, W0)
            if err <= 1e-6:
                return err, W, steps, piece_weights(W0, W == 0.0), True
    if not keep_reversals:
        # halved steps (full steps with any sign jumped to rates that take a joint out of
        # the region, 6 of 120 states at n = 3), in one compiled call; the Python loop only
        # where a system was singular (it solves those by least squares)
        for floor in (WEIGHT_FLOOR, None):
            err, W = halving_correct(emap, q0, goal, W0, floor=floor)
            if err <= 1e-6:         # (the loop's own acceptance)
                return err, W, HALVING_STEPS, piece_weights(W0, None, floor), False
            if not math.isfinite(err):
                err, W, steps = correct_pieces(emap, q0, goal, W0, floor=floor)
                if err <= 1e-6:
                    return err, W, steps, piece_weights(W0, None, floor), False
    raise NumericalError("the Gauss-Newton correction of the later pieces' rates did not "
                         "reach the goal" + (" keeping their signs" if keep_reversals else
                                             f" (miss {err:.3g} rad)"))


def _tail(free: np.ndarray, rates: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """The last piece split into :data:`TAIL_PIECES` + 1 parts of geometrically shrinking
    length (ratio :data:`TAIL_RATIO`): the same path, run stop and go in equal times, so that
    the motion left near the end (what no later replan can correct) is a small part of the
    whole. A path that already ends shorter than its previous piece is left as it is (a
    continuation's tail is not split again). Returns the breaks, the rates and whether the
    tail was split."""
    L = free[1:] - free[:-1]
    if L.size >= 2 and L[-1] < 0.9 * L[-2]:
        return free, rates, False
    a, ell = float(free[-2]), float(L[-1])
    parts = ell * _TAIL_SHARES
    ends = a + np.cumsum(parts)
    ends[-1] = free[-1]
    return (np.concatenate([free[:-1], ends]),
            np.vstack([rates[:-1], np.repeat(rates[-1:], TAIL_PIECES + 1, axis=0)]), True)


def sign_changes(rates: np.ndarray) -> int:
    """Sign changes of ``u1`` and of ``u2`` along pieces (zeros skipped): the reversals of
    ``phi`` and ``th1``, which integrate them."""
    total = 0
    for col in np.asarray(rates, float).T:
        nz = np.sign(col[np.abs(col) > 1e-12])
        total += int(np.sum(nz[1:] != nz[:-1]))
    return total


def _assemble(kept: Kept, free: np.ndarray, new_rates: np.ndarray, later: np.ndarray,
              T0: float, route: str, steps: int, refine: Any = None) -> Continuation:
    if kept.pieces:
        breaks = np.concatenate([kept.breaks[:-1], free])
        rates = np.vstack([kept.rates, new_rates])
        phases = np.vstack([kept.law.phases, later])
    else:
        breaks, rates, phases = free.copy(), new_rates, later
        breaks[0] = kept.breaks[0]
    return Continuation(breaks, rates, TimeLaw(phases), T0, route, steps, kept.pieces, refine)


def _fallback(ps: PlanState, req: PlanRequest, t: float, q_m: np.ndarray, u_c: np.ndarray,
              T_end: float, deadline: float) -> Continuation:
    """Step 4 of the module: the kept motion (or a braking), then the full planner, both of
    its methods within what is left of the replan's time limit (``deadline``, on
    :func:`time.perf_counter`'s clock).

    Raises
    ------
    SolverTimeoutError
        The time limit ran out (``field='time_limit'``).
    """
    if ps.rates is not None:
        kept = run_on(ps, t, u_c)
        if kept.k >= ps.rates.shape[0]:
            kept = brake_now(ps, t, u_c, T_end)
    elif float(np.abs(u_c).max()) > REST:
        # (within the plan's acceleration bounds: sigma' falls from 1 to 0, u' = u_c / Db)
        Db = max(min(BRAKE_TIME, 0.5 * (T_end - t)),
                 braking_time(1.0, np.asarray(u_c, float), ps.limits))
        kept = Kept(0, np.array([0.0, 0.5 * Db]), np.asarray(u_c, float)[None, :],
                    TimeLaw(braking(t, Db, 0.0)))
    else:
        kept = Kept(0, np.array([0.0]), np.zeros((0, 2)), TimeLaw(np.zeros((0, 6))))
    q_stop = _pieces_end(ps.robot, q_m, kept.breaks, kept.rates)
    t_stop = kept.law.end if kept.law.phases.size else t
    if T_end - t_stop <= 1e-9:
        raise NumericalError("nothing is left after the current motion's stop to correct the "
                             "miss: give a later duration", field="duration")
    lo, hi = joint_limits(req)
    if not (np.isfinite(q_stop).all() and (q_stop[1:] > lo).all() and (q_stop[1:] < hi).all()):
        raise InfeasibleError("the motion under way leaves the region before its next stop: "
                              "no continuation starts there", field="state")
    sub = replace(req, start=tuple(q_stop[1:]), phi_start=float(q_stop[0]), duration=None,
                  method="shooting", samples=11, time_limit=_time_left(req, deadline))
    try:
        try:
            p = full_plan(sub)
        except PlannerError:
            # (each planner honours its own limit: the second gets what the first left)
            p = full_plan(replace(sub, method="penalty", time_limit=_time_left(req, deadline)))
    except SolverTimeoutError as exc:
        # in the replan's terms: its time limit, not the share of it a method of the full
        # planner had ("the penalty NLP found no path within the time limit of 4.6 s")
        raise SolverTimeoutError(
            f"no continuation was found within the time limit of {req.time_limit:g} s "
            "(raise time_limit)", field="time_limit",
            diagnostics={"full_planner": exc.message}) from None
    except (InfeasibleError, NumericalError) as exc:
        raise type(exc)(
            "no continuation was found from the measured state (after the fast path, the "
            f"full planner: {exc.message})",
            field=exc.field, diagnostics=dict(exc.diagnostics)) from None
    sched = p.inputs
    breaks = kept.s_stop + np.asarray(sched.breaks, float)   # its plan time after the stop
    rates = np.asarray(sched.rates, float)                    # type: ignore[union-attr]
    # it ends in a geometric tail too: little is left for the plant's error after the last
    # replan (a fresh plan's last piece is 1/12 to 1/20 of its path)
    breaks, rates, tailed = _tail(breaks, rates)
    later = law_within_limits(t_stop, T_end, breaks, rates, ps.limits, equal=tailed)
    return _assemble(kept, breaks, rates, later, kept.s_stop + float(sched.breaks[-1]),
                     "full_planner", 0)


def _time_left(req: PlanRequest, deadline: float) -> float:
    """Seconds left before ``deadline`` for the full planner (raises
    :class:`SolverTimeoutError` when none is)."""
    left = deadline - time.perf_counter()
    if not left > 0.0:
        raise SolverTimeoutError(f"no continuation was found within the time limit of "
                                 f"{req.time_limit:g} s (raise time_limit)", field="time_limit")
    return left


__all__ = ["Continuation", "Kept", "PlanState", "TimeLaw", "read_plan",
           "replan", "sign_changes"]
