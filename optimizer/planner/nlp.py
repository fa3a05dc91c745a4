"""The multiple-shooting transcription of the ORIGINAL model shared by ``shooting`` and
``penalty`` (the NLP layer: it imports nothing from the methods or the orchestrator).

Transcription (normalised time ``tau = t / T`` in [0, 1]; ``T`` only rescales the rates)
----------------------------------------------------------------------------------------
* equal intervals with piecewise-constant actuator rates ``U = (U1, U2)`` (``u = U / T``),
  node states ``q_k = (phi, th_1..th_n)``, continuity by classical RK4 steps
  (:func:`optimizer.dynamics.rk4_step` of :func:`optimizer.dynamics.vector_field`); the number
  of intervals, of steps and the rate bound are a rung of :func:`ladder`;
* ``q_0`` = the start, ``th(1)`` = the goal; ``phi(1) - phi(0)`` equal to a parameter when
  ``fixed_phi`` (else the caller bounds ``phi_N``);
* objective: ``w_en int |U|^2 dtau + w_dev S + w_da S1`` with ``S >=`` the squared distance of
  every interior node's ``(th_1..th_n)`` from the straight line through start and goal (joint
  space) and ``S1 >=`` the squared distance of ``th_1`` from its straight line in time (the
  paper's ``d_a``);
* the region, by ``region``:

  ``"hard"``
      the caller's bounds on the node states (``lbx``/``ubx``): inequality constraints;
  ``"penalty"``
      an exact (l1) penalty (paper Remark 3): a slack ``s_k >= 0`` per interior node with
      ``s_k >= lo_j - th_kj`` and ``s_k >= th_kj - hi_j`` for every joint, and
      ``rho * sum_k s_k`` in the objective (``lo``, ``hi``, ``rho`` are parameters). This
      mode's objective also has ``w_sens ||J_R(T)||_F`` of ``s = phi(1) - phi(0)`` (eq 22).

Stage-wise layout (what fatrop needs, IPOPT does not mind): ``w = [x_0, u_0, x_1, u_1, ...,
x_N]`` with ``x_k = (q_k, S_k, S1_k)`` (the two epigraph variables are carried as constant
states, so that every constraint couples one stage only) and ``u_k = U_k`` (``"hard"``) or
``(U_k, s_k)`` (``"penalty"``); constraints per stage: the gap ``x_{k+1} - F(x_k, u_k)``, then
the stage's own rows (start at ``k = 0``; deviation epigraphs and, with the penalty, the slack
rows inside; goal and, when fixed, ``dphi`` at ``k = N``).

The solvers (fatrop, IPOPT), their options and one call of them are :mod:`.solvers`; the ladder
of rungs a method climbs is :mod:`.rungs`; the correction of an answer onto the exact model's
goal is :mod:`.correction`. With compiled functions configured (:mod:`optimizer.native`),
fatrop evaluates the first rung's functions as compiled C once their library is built
(:meth:`MultipleShootingNLP.load_native`).

Caching, threads
----------------
The NLP and its solvers are built once per robot shape (joint count and exponents),
transcription and region mode per process (:func:`multiple_shooting_nlp`); start, goal,
weights, bounds and the robot's gains are parameters, so a robot of other gains (a perturbed
plant, a study's design, gains estimated in closed loop) is served without a build. CasADi objects
are not thread-safe and the cached callback holds the current deadline: one thread per process.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np

from .. import native
from ..dynamics import rk4_step, vector_field
from ..errors import InvalidRequestError
from ..problem import PlanRequest
from . import via
from .solvers import (REUSED_MEMORIES, SPENT_MEMORY_BYTES, BufferedCall, DeadlineCallback,
                      SolverPace, bound_pattern, fatrop_max_iter, fatrop_options, ipopt_options,
                      memory_bytes)


@dataclass(frozen=True)
class Transcription:
    """One rung of the ladder of transcriptions: intervals, RK4 steps per interval inside the
    NLP (the returned path is re-integrated accurately and the rates corrected onto the goal of
    the exact model, see :func:`correct_rates`) and the bound of ``|U1|, |U2|`` (rad per unit
    of normalised time, i.e. per ``T``) that keeps those steps close to the exact model."""

    intervals: int
    substeps: int
    rate_bound: float


#: Tried in order until one NLP converges. The first: 16 intervals, one RK4 step each, rates at
#: most 10 rad per T (without a bound the NLP found a spurious optimum with phi moving 2 rad
#: in one interval, where RK4 and the exact model part by 0.1 rad; a bound of 6 left 3 of 80
#: random 3- and 4-joint goals unsolved, 10 solved all 80). 16 intervals against the 20 of
#: before, on generated goals of seeds the benchmark does not use (each plan re-integrated,
#: ranked by reversals, then deviation, a difference under 0.25 deg counted as none): alike
#: on 146 of 165 goals, better on 14, worse on 5 (the largest: 1 reversal at 4.6 deg became 2
#: at 9.4 deg); the plan's median CPU 1.13-1.28 times lower on 4 joints (80 goals), 1.29 on 5
#: (30), 1.17 on 6 (20), 1.6 on 7 (25: its NLP's C is now small enough to compile, see
#: :mod:`optimizer.native`) and 1.23 on 8 (10). The second, for goals that need more
#: switching and faster rates (6 joints: the minimum-energy baseline's rates reach 14-21
#: rad/s), has the baseline's 50 intervals, 2 RK4 steps each.
LADDER: tuple[Transcription, ...] = (Transcription(16, 1, 10.0), Transcription(50, 2, 40.0))
#: The ladder of 3-joint robots: a first rung of 12 intervals (the same rate bound: the rates
#: are per unit of normalised time, the path's speed, whatever the grid). Measured against 20
#: on the benchmark's 60 goals and on 60 of a seed it does not use: the same number of goals
#: with a deviation no larger than the baseline's (54 and 56) and no more reversals (60 and
#: 60), 57 of the 60 plans within 0.05 deg of each other; each solve about 40 % cheaper. On 4
#: and 5 joints 12 intervals lost (16 of 40 goals with a larger deviation or more reversals,
#: one 5-joint goal from 2 reversals to 4): they keep :data:`LADDER`.
LADDER_3_JOINTS: tuple[Transcription, ...] = (Transcription(12, 1, 10.0), LADDER[1])


def ladder(n: int) -> tuple[Transcription, ...]:
    """The rungs of a robot of ``n`` joints, in order (:data:`LADDER_3_JOINTS`, :data:`LADDER`)."""
    return LADDER_3_JOINTS if n <= 3 else LADDER
#: Weight of the squared joint-space deviation (rad^2) against the input energy. The default
#: objective ranks by deviation; the energy (about 1 for a move of about 1 rad) only makes the
#: rates unique. At 3, 5 deg of deviation cost 0.02: the plan was nearly the minimum-energy
#: one. Measured on 60 random 3-joint goals of a seed the benchmark does not use, against the
#: minimum-energy plan, deviation no larger on 52 (weight 3), 55 (10), 56 (30). At 30 the
#: deviation term also bought small wiggles (59 of 60 with no more reversals) until
#: :func:`solve_rungs` removed them; with that, 60 of 60 at 10 and at 30.
DEVIATION_WEIGHT = 30.0
#: Weight of the squared d_a of joint 1 (rad^2; at the nodes) against the input energy: small,
#: as the default objective does not rank d_a, but not 0 (its epigraph variable would be
#: unbounded, the interior point's barrier pushing it off: twice the iterations).
D_A_WEIGHT = 0.3
#: ... and under the paper's ``tp_then_da``, which ranks by it.
PAPER_D_A_WEIGHT = 3.0
#: Region modes of the transcription (see the module docstring).
REGION_MODES = ("hard", "penalty")
#: What the deviation epigraph ``S`` bounds: the squared distance of a node from the LINE
#: through start and goal (every method's), or from the SEGMENT start -> goal (the reversal
#: budget's straightest candidates, :mod:`.budget`: the answer's ``deviation``; the squared
#: distance from a convex set is continuously differentiable, so the solvers do not mind).
DEVIATION_MODES = ("line", "segment")
#: How the goal enters: as equality rows ("hard"), or "elastic": ``|th_N - goal|_inf <= E``
#: with ``ELASTIC_WEIGHT * E`` in the objective, an exact penalty (the answer ends on the goal
#: whenever the weight exceeds the goal rows' multipliers; the Newton correction removes what
#: is left). With the goal as equalities the KKT systems of 6- to 8-joint NLPs are singular
#: wherever the iterate's end map loses rank in a bracket direction (IPOPT: "Error in step
#: computation", fatrop: "constraint Jacobian not full rank"): on 5 generated 7-joint goals
#: IPOPT converged from 5 of 10 guesses in 23-500 iterations; elastic, from 10 of 10 in
#: 15-24, and on 6-joint and 8-joint goals from 24 of 24 in 18-35. At 5 joints fatrop reached
#: its iteration cap on most free and sign-held rungs with the goal hard, so IPOPT answered
#: them (60-160 ms a plan); elastic, fatrop answered 8 of the benchmark's first 12 goals
#: without IPOPT, half the median time (52 against 93 ms, the same goals in turn), the same
#: reversals on 11 (deviation within 0.6 deg, better on 4; the twelfth: see
#: :data:`~.rungs.HELD_ENOUGH`).
TERMINAL_MODES = ("hard", "elastic")
#: Weight of the goal's exact penalty (rad^-1; the energy of a 1 rad move is about 1).
ELASTIC_WEIGHT = 1e5
#: From this many joints IPOPT evaluates the first rung's functions as compiled C too (see
#: :meth:`MultipleShootingNLP.load_native`): from 5 joints it answered where fatrop did not on
#: 4 of 12 five-joint goals (the goal elastic), and on 8 such goals its
#: solves took 12-27 % less time with the same iterates. Below, it runs more rarely, and a
#: library costs a compile; the soft-sign NLPs are fatrop's alone.
IPOPT_COMPILED_FROM_JOINTS = 5
#: From this many joints the goal is elastic by default.
ELASTIC_FROM_JOINTS = 5
#: ... and from this many, on the free rungs (no rate's sign held). On 4 joints with the goal
#: hard, fatrop sometimes stalled at its iteration cap on the free rung (steps of 1e-4 to 1e-7
#: of the Newton step, the barrier parameter stuck at 1e-2) and IPOPT answered after it
#: (40-80 ms a plan). Paired in one process on 60 held-out 4-joint goals (two seeds): the
#: same answers on all 60 (deviation within 0.01 deg), time -8 % and -6 % in sum, one plan
#: 146 -> 82 ms and one 76 -> 51 ms. With the sign-held rungs elastic too it was slower in sum
#: (+5 %): a rung whose signs cannot reach the goal then takes two elastic rounds to say so.
FREE_ELASTIC_FROM_JOINTS = 4
#: Rates held to signs (the sign-held rungs of :mod:`.rungs`) from a cold start enter as
#: penalised rows, not bounds: ``sign_j U_j + t >= 0``, ``t >= 0`` (one slack per interval),
#: ``SIGN_PENALTY t`` in the objective (an exact penalty: where the signs can be kept the solution is the one
#: with bounds, to 1e-7 rad on 24 four-joint goals). With bounds, an NLP whose signs cannot
#: reach the goal left fatrop wandering to its iteration cap (IPOPT proved 4 of 6 such
#: four-joint NLPs infeasible, after 100-166 iterations); with the penalty it converges with
#: a slack instead, the certificate that those signs are out of reach (6 of 13 such NLPs,
#: in 28-58 iterations; 1 more now converged to a sign-keeping plan): 27 % less time on the
#: sign-held rungs of those goals.
SIGN_PENALTY = 1e3
#: A soft-sign solution whose largest slack is above this (rad per unit of normalised time)
#: does not keep its signs: the rung is infeasible.
SIGN_SLACK_TOL = 1e-6
#: fatrop's iteration cap on the soft-sign NLPs (the others': :func:`~.solvers.fatrop_max_iter`).
#: At the other rungs' cap (60) 8 soft-sign NLPs of 40 held-out 4-joint goals (seeds 777 and
#: 9001) stopped unconverged; given 300 iterations, 3 of them found plans that keep the signs (79, 123 and
#: 135 iterations), 3 certified the signs out of reach (a slack, after 66, 68 and 176) and 2
#: did not converge. With 150 two of those goals' plans reverse less (5 -> 2, 2 -> 1), the
#: other 38 are the same (one 1e-4 rad straighter before) and so are the benchmark's 25
#: four-joint goals; the time in sum +3 % on one seed and +30 % on the other, where one plan
#: went from 66 to 150 ms (its sign-held answer is then refined on the 50-interval rung).
SOFT_SIGNS_MAX_ITER = 150
#: Distance (rad) kept from the region's bounds at the nodes (0.5 deg).
MARGIN = math.radians(0.5)
#: RK4 steps of the correction's end map per RK4 step of the NLP. On the bench's goals (rates
#: of about 1 rad per unit of normalised time) 8 steps per 0.05 of it end 1e-13 to 2e-12 rad
#: from the exact model (cascade quadrature), 4 steps 1e-12 to 3e-11; the error grows as the
#: fifth power of the rates, so at the rung's bound it is about 1e-7: the quadrature that
#: proves the plan measures it, and the defect correction (``exact_end``) then removes it.
FINE_SUBSTEPS = 8
#: A bound of a joint the region leaves open (th_n without joint bounds), for the penalty's
#: parameters, which must be finite.
OPEN_BOUND = 1e3


# ---------------------------------------------------------------------- solver presets


# ---------------------------------------------------------------------- the transcription
class MultipleShootingNLP:
    """The transcription of the module docstring for one robot, with its solvers (built once,
    cached by :func:`multiple_shooting_nlp`).

    Parameters
    ----------
    exponents : tuple
        The robot's ``m_2..m_n`` (its gains ``K_2..K_n`` are the last parameters).
    fixed_phi : bool
        ``phi(1) - phi(0)`` is a parameter (else the caller bounds ``phi_N``).
    intervals, substeps : int
        A rung of :data:`LADDER`.
    region : {"hard", "penalty"}
        How the region enters (see the module docstring).
    deviation : {"line", "segment"}
        What the deviation epigraph measures (:data:`DEVIATION_MODES`).
    deviation_points : int
        Inner points per interval (equally spaced) whose distance the deviation epigraph
        bounds too, besides the nodes (0: the nodes alone).
    terminal : {"hard", "elastic"}
        How the goal enters (:data:`TERMINAL_MODES`).
    soft_signs : bool
        The rates' signs (parameters) as penalised rows with a slack ``t`` per interval (one
        more input), see :data:`SIGN_PENALTY`.
    fatrop_settings : tuple of (str, float)
        fatrop options that replace :func:`~.solvers.fatrop_options`' (``mu_init``,
        ``max_iter``, ...) for this NLP (the reversal budget's, :mod:`.budget`).

    Attributes
    ----------
    solvers : list of (name, nlpsol)
        fatrop (when CasADi has it) and IPOPT.
    end_jacobian : casadi.Function
        ``(q0, U) -> d q_N / d U`` of the NLP's RK4 model (single shooting; the Newton
        correction of :func:`correct_rates`).
    fine_path : casadi.Function
        ``(q0, U (2, N)) -> q_1..q_N (nq, N)``: the model under the rates with
        :data:`FINE_SUBSTEPS` times the NLP's RK4 steps (the correction's end map).
    """

    def __init__(self, exponents: tuple[int, ...], fixed_phi: bool,
                 intervals: int, substeps: int, region: str = "hard",
                 deviation: str = "line", deviation_points: int = 0,
                 terminal: str = "hard", soft_signs: bool = False,
                 fatrop_settings: tuple[tuple[str, float], ...] = ()) -> None:
        if region not in REGION_MODES:
            raise ValueError(f"region must be one of {REGION_MODES}, not {region!r}")
        if deviation not in DEVIATION_MODES:
            raise ValueError(f"deviation must be one of {DEVIATION_MODES}, not {deviation!r}")
        if terminal not in TERMINAL_MODES:
            raise ValueError(f"terminal must be one of {TERMINAL_MODES}, not {terminal!r}")
        t0 = time.perf_counter()
        n = self.n = len(exponents) + 1
        N = self.N = intervals
        # the gains K_2..K_n are parameters (the last n - 1 of p), not constants: one NLP, one
        # compiled library and one set of solvers serve every robot of these exponents
        Kp = ca.SX.sym("K", n - 1)
        gains = [Kp[i] for i in range(n - 1)]
        self.region = region
        self.terminal = terminal
        penalty = region == "penalty"
        elastic = terminal == "elastic"
        nq = n + 1
        # (q, S, S1) and, elastic, E: the epigraphs (and E) are constant along the path
        nx = self.nx = nq + (3 if elastic else 2)
        self.soft_signs = soft_signs
        if soft_signs and penalty:
            raise ValueError("soft_signs is for the hard region")
        nu = self.nu = 3 if penalty or soft_signs else 2
        h = 1.0 / N

        def field(y: Any, rates: Any) -> Any:
            # the epigraph states are constant along the path
            return ca.vertcat(*vector_field(gains, exponents, y, rates[0], rates[1], ca.cos),
                              *([0] * (nx - nq)))

        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", 2)
        step = ca.Function("rk4", [x, u, Kp], [rk4_step(field, x, u, h, substeps)])
        # the states at deviation_points equally spaced inner times of an interval (the
        # interval's RK4 steps from its node, shortened): the deviation epigraph bounds them
        # too, so that a path cannot come back to the line at the nodes only (the budget's)
        inner = [ca.Function(f"rk4_inner{j}", [x, u, Kp], [rk4_step(
            field, x, u, h * j / (deviation_points + 1), substeps)])
            for j in range(1, deviation_points + 1)]
        # the NLP model's end state as a function of the start and all rates (single shooting)
        # and its Jacobian: the Newton correction (correct_rates) uses them
        q0s, Us = ca.SX.sym("q0", nq), ca.SX.sym("U", 2 * N)
        xe = ca.vertcat(q0s, *([0] * (nx - nq)))
        for k in range(N):
            xe = step(xe, Us[2 * k:2 * k + 2], Kp)
        self.end_jacobian = ca.Function("end_jacobian", [q0s, Us, Kp],
                                        [ca.densify(ca.jacobian(xe[:nq], Us))])
        # the same model with FINE_SUBSTEPS times the steps: the correction's end map, close
        # enough to the exact model (see FINE_SUBSTEPS) that no quadrature runs per step
        xq = ca.SX.sym("q", nq)
        fine = ca.Function("rk4_fine", [xq, u, Kp], [rk4_step(
            lambda y, r: ca.vertcat(*vector_field(gains, exponents, y, r[0], r[1], ca.cos)),
            xq, u, h, substeps * FINE_SUBSTEPS)])
        Ur = ca.SX.sym("U", 2, N)
        Ks = ca.repmat(Kp, 1, N)
        self.fine_path = ca.Function("fine_path", [xq, Ur, Kp],
                                     [fine.mapaccum("fine_steps", N)(xq, Ur, Ks)])
        # the correction's maps, compiled with the NLP's functions when those are
        # (load_native); the end state alone (no path) is all the correction needs
        self._correction_maps = (ca.Function("fine_end", [xq, Ur, Kp],
                                             [fine.fold(N)(xq, Ur, Ks)]),
                                 self.end_jacobian)
        self._fine_end = BufferedCall(self._correction_maps[0], 3)
        self._end_jacobian = BufferedCall(self.end_jacobian, 3)

        # p = [phi0, a (n), b (n), w_dev, w_energy, w_da, dphi] and, with the penalty,
        #     [w_sens, rho, lo (n), hi (n)]
        P = ca.SX.sym("p", 2 * n + 5 + (2 + 2 * n if penalty else 0)
                      + (2 * N + 1 if soft_signs else 0))
        phi0, a, b = P[0], P[1:1 + n], P[1 + n:1 + 2 * n]
        w_dev, w_en, w_da, dphi = P[1 + 2 * n], P[2 + 2 * n], P[3 + 2 * n], P[4 + 2 * n]
        ell = b - a
        nrm = ca.sumsqr(ell)
        X = [ca.SX.sym(f"x{k}", nx) for k in range(N + 1)]
        U = [ca.SX.sym(f"u{k}", nu) for k in range(N)]
        w: list[Any] = []
        g: list[Any] = []
        eq: list[bool] = []
        ng: list[int] = []
        f: Any = 0
        if penalty:
            w_sens, rho = P[5 + 2 * n], P[6 + 2 * n]
            lo, hi = P[7 + 2 * n:7 + 3 * n], P[7 + 3 * n:7 + 4 * n]

        def dist2_of(th: Any) -> Any:
            d = th - a
            if deviation == "segment":  # (reversal budget) squared distance from the segment
                s_k = ca.fmin(ca.fmax(ca.dot(d, ell) / ca.fmax(nrm, 1e-300), 0.0), 1.0)
                return ca.sumsqr(d - s_k * ell)
            along = ca.if_else(nrm > 0, ca.dot(d, ell) ** 2 / ca.fmax(nrm, 1e-300), 0)
            return ca.sumsqr(d) - along

        def inner_rows(k: int) -> list[tuple[Any, bool]]:
            # the interval's inner points (x_k, u_k: one stage), bounded by x_k's epigraph
            return [(dist2_of(f(X[k], U[k][:2], Kp)[1:nq]) - X[k][nq], False) for f in inner]

        def stage_rows(k: int) -> list[tuple[Any, bool]]:
            if k == 0:
                return ([(X[0][:nq] - ca.vertcat(phi0, a), True)] + inner_rows(0)
                        + sign_rows(0))
            if k == N:
                if elastic:
                    miss = X[N][1:nq] - b
                    rows = [(miss - X[N][nq + 2], False), (-miss - X[N][nq + 2], False)]
                else:
                    rows = [(X[N][1:nq] - b, True)]
                if fixed_phi:
                    rows.append((X[N][0] - phi0 - dphi, True))
                return rows
            rows = [(dist2_of(X[k][1:nq]) - X[k][nq], False),
                    ((X[k][1] - (a[0] + (b[0] - a[0]) * k * h)) ** 2 - X[k][nq + 1], False)]
            if penalty:
                th, s = X[k][1:nq], U[k][2]
                rows += [(th - s - hi, False), (lo - th - s, False)]
            return rows + inner_rows(k) + sign_rows(k)

        def sign_rows(k: int) -> list[tuple[Any, bool]]:
            # soft signs: sign_j U_j + t >= 0 (j = 1, 2) with one slack t >= 0 per interval
            # and rho_s t in the objective
            if not soft_signs or k >= N:
                return []
            sg = P[P.shape[0] - 2 * N - 1 + 2 * k:P.shape[0] - 2 * N - 1 + 2 * k + 2]
            return [(-(sg[j] * U[k][j] + U[k][2]), False) for j in (0, 1)]

        for k in range(N + 1):
            w.append(X[k])
            if k < N:
                w.append(U[k])
                f += w_en * h * ca.sumsqr(U[k][:2])
                if penalty:
                    f += rho * U[k][2]
                if soft_signs:
                    f += P[P.shape[0] - 1] * U[k][2]
                g.append(X[k + 1] - step(X[k], U[k][:2], Kp))  # x_{k+1} - F(x_k, u_k)
                eq += [True] * nx
            rows = stage_rows(k)
            for expr, is_eq in rows:
                g.append(expr)
                eq += [is_eq] * int(expr.shape[0])
            ng.append(sum(int(e.shape[0]) for e, _ in rows))
        f += w_dev * X[N][nq] + w_da * X[N][nq + 1]
        if elastic:
            f += ELASTIC_WEIGHT * X[N][nq + 2]
        if penalty:
            f += w_sens * sensitivity_frobenius(X[N][0] - phi0, n)
        nlp = {"x": ca.vertcat(*w), "p": ca.vertcat(P, Kp), "f": f, "g": ca.vertcat(*g)}
        self.nw = int(nlp["x"].shape[0])
        self.np = int(P.shape[0]) + n - 1
        n_g = int(nlp["g"].shape[0])
        self.equality = np.array(eq)
        self.callback = DeadlineCallback(self.nw, n_g, self.np)
        self.native: native.Library | None = None
        self.native_ipopt: native.Library | None = None
        self.compiled = False
        self.ipopt_compiled = False
        self._native_cfg: native.NativeConfig | None = None
        self._fatrop_opts: dict[str, Any] = {}
        # only the first rung is compiled: the second's C (4-11 MB) takes 10-20 s and up to
        # 1.6 GB to compile, for a rung that runs rarely (and for about a second)
        first = ladder(n)[0]
        self.native_ok = ((intervals, substeps) == (first.intervals, first.substeps)
                          and deviation == "line"  # (the budget's NLPs: not compiled)
                          and deviation_points == 0
                          and terminal in (default_terminal(n), default_terminal(n, True)))
        name = ("shooting" if region == "hard" else "penalty") + ("_soft" if soft_signs else "")
        # how each solver is built, kept so that it can be built anew (see solver_call)
        self._factories: dict[str, Callable[[], Any]] = {}
        if ca.has_nlpsol("fatrop"):
            fatrop_opts = fatrop_options(
                [nx] * (N + 1), [nu] * N + [0], ng, eq,
                max_iter=SOFT_SIGNS_MAX_ITER if soft_signs else fatrop_max_iter(n))
            fatrop_opts["fatrop"].update(dict(fatrop_settings))
            self._factories["fatrop"] = functools.partial(
                ca.nlpsol, f"{name}_fatrop", "fatrop", nlp, fatrop_opts)
            self._fatrop_opts = fatrop_opts
        self._ipopt_opts = ipopt_options(self.callback)
        self._factories["ipopt"] = functools.partial(ca.nlpsol, f"{name}_ipopt", "ipopt", nlp,
                                                     self._ipopt_opts)
        #: the solvers' names, in the order the methods try them
        self.solver_names: tuple[str, ...] = tuple(self._factories)
        #: how fast its solvers' iterations went (fatrop, at its own cap, is not started
        #: past the deadline)
        self.pace = SolverPace({"fatrop": int(self._fatrop_opts["fatrop"]["max_iter"])}
                               if self._fatrop_opts else {})
        # each solver is built at its first use (solver): on CasADi's virtual machine that
        # builds its derivative functions, 0.1-0.9 s at 4 to 7 joints, which a process whose
        # compiled library is in the cache never needs
        self._built: dict[str, Any] = {}
        self._problem = nlp
        self._fingerprints: dict[str, str] = {}
        self._spent: dict[str, list[BufferedCall]] = {key: [] for key in self._factories}
        self._by_pattern: dict[str, dict[bytes, BufferedCall]] = {
            key: {} for key in self._factories}
        self._calling: dict[str, Any] = {}  # the solvers of solver_call
        self._name = name
        self.lbg = np.where(self.equality, 0.0, -np.inf)
        self.ubg = np.zeros(n_g)
        self.stride = nx + nu
        self.build_time = time.perf_counter() - t0

    def load_native(self, every: float = 1.0, wait: bool = False) -> bool:
        """Use the compiled fatrop functions once their library is built (checked at most
        every ``every`` s; ``wait``: build it now when missing); True when they are in use.
        From :data:`IPOPT_COMPILED_FROM_JOINTS` joints IPOPT's functions (another set: its
        gradient returns the objective too) get a library of their own the same way
        (:attr:`ipopt_compiled`).

        The libraries are asked for (:func:`optimizer.native.library_for`: found in the cache,
        or their build started) at the first call after :func:`optimizer.native.configure`, so
        that an NLP built before (the service's forkserver builds it at start-up) gets them
        too.
        """
        cfg = native.config()
        if cfg is not self._native_cfg:
            self._native_cfg, self.native, self.native_ipopt = cfg, None, None
            if cfg is not None and self.native_ok:
                if "fatrop" in self._factories and not self.compiled:
                    self.native = native.library_for_fingerprint(
                        self.fingerprint("fatrop"), lambda: native.nlp_source(
                            self.solver("fatrop"), self._correction_maps), wait=wait)
                if (not self.ipopt_compiled and not self.soft_signs
                        and self.n >= IPOPT_COMPILED_FROM_JOINTS):
                    self.native_ipopt = native.library_for_fingerprint(
                        self.fingerprint("ipopt"),
                        lambda: native.nlp_source(self.solver("ipopt")), wait=wait)
            every = 0.0
        if self.native_ipopt is not None and not self.ipopt_compiled:
            self._load_ipopt(every)
        if self.compiled:
            return True
        if self.native is None:
            return False
        path = self.native.ready(every)
        if path is None:
            return False
        try:
            # the same options but expand: the library's functions are compiled already
            opts = {k: v for k, v in self._fatrop_opts.items() if k != "expand"}
            build = functools.partial(ca.nlpsol, f"{self._name}_fatrop", "fatrop", str(path),
                                      opts)
            solver = build()
            fine_end, end_jacobian = (ca.external(f.name(), str(path))
                                      for f in self._correction_maps)
        except Exception:  # noqa: BLE001 - an unloadable library: keep the virtual machine
            self.native = None
            return False
        self._fine_end = BufferedCall(fine_end, 3)
        self._end_jacobian = BufferedCall(end_jacobian, 3)
        self._factories["fatrop"] = build
        self._replace("fatrop", solver)
        self.compiled = True
        return True

    def _load_ipopt(self, every: float) -> None:
        """IPOPT's solver on its compiled library once it is built: the same iterates (bit
        for bit on the benchmark's five-joint goals), the functions' share of the time
        compiled, and a build of a solver in about 2 ms instead of the symbolic one's 90 ms
        (see :meth:`solver_call`)."""
        assert self.native_ipopt is not None
        path = self.native_ipopt.ready(every)
        if path is None:
            return
        build = functools.partial(ca.nlpsol, f"{self._name}_ipopt", "ipopt", str(path),
                                  self._ipopt_opts)
        try:
            solver = build()
        except Exception:  # noqa: BLE001 - an unloadable library: keep the virtual machine
            self.native_ipopt = None
            return
        self._factories["ipopt"] = build
        self._replace("ipopt", solver)
        self.ipopt_compiled = True

    @property
    def solvers(self) -> list[tuple[str, Any]]:
        """``(name, nlpsol)`` of fatrop (when CasADi has it) and IPOPT (each built now when
        it was not yet: :meth:`solver`)."""
        return [(key, self.solver(key)) for key in self.solver_names]

    def solver(self, name: str) -> Any:
        """Solver ``name`` (built at its first use: compiled when its library is loaded,
        else on CasADi's virtual machine)."""
        solver = self._built.get(name)
        if solver is None:
            solver = self._built[name] = self._factories[name]()
        return solver

    def prepare_solver(self, name: str) -> None:
        """Build solver ``name`` (:meth:`solver`) and the one :meth:`solver_call` runs on,
        ahead of the first solve, which would otherwise pay that build (on CasADi's virtual
        machine 27-130 ms, the reversal budget's NLP 0.3-0.4 s; compiled about 1 ms)."""
        self.solver(name)
        if name not in self._calling:
            self._new_calling_solver(name)

    def _new_calling_solver(self, name: str) -> Any:
        """A new solver ``name`` for :meth:`solver_call`, with no memory yet (the previous
        one's go with it)."""
        solver = self._calling[name] = self._factories[name]()
        self._spent[name], self._by_pattern[name] = [], {}
        return solver

    def fingerprint(self, name: str) -> str:
        """What solver ``name``'s compiled library is generated from, as a string that changes
        whenever its C source would (:func:`optimizer.native.library_for_fingerprint`): the
        serialised problem ``(x, p) -> (f, g)``, the solver's plugin and options (those that
        are data, but fatrop's own, which its solver reads at run time), and for fatrop the
        correction's maps compiled with it."""
        found = self._fingerprints.get(name)
        if found is None:
            # (the options the source is generated under: the virtual machine's solver's)
            opts = self._fatrop_opts if name == "fatrop" else self._ipopt_opts
            data = {k: v for k, v in opts.items()
                    if isinstance(v, (str, int, float, bool, list, tuple, dict))}
            # fatrop's own options (its cap, tolerances, barrier) are the solver's at run
            # time, not the functions the library holds: an NLP whose fatrop may iterate
            # longer (the replanner's warm NLP) shares the library
            data.pop("fatrop", None)
            parts = [name, repr(sorted(data.items())), self._serialised_problem]
            if name == "fatrop":
                parts += [f.serialize() for f in self._correction_maps]
            found = self._fingerprints[name] = "\0".join(parts)
        return found

    @functools.cached_property
    def _serialised_problem(self) -> str:
        return ca.Function("nlp", [self._problem["x"], self._problem["p"]],
                           [self._problem["f"], self._problem["g"]]).serialize()

    def _replace(self, name: str, solver: Any) -> None:
        self._built[name] = solver
        # the calls' solver is built anew from the new factory at the next solver_call (its
        # memories go with it)
        self._calling.pop(name, None)
        self._spent[name] = []
        self._by_pattern[name] = {}

    def solver_call(self, name: str, lbx: np.ndarray, ubx: np.ndarray) -> BufferedCall:
        """Solver ``name`` (see :attr:`solvers`) as a :class:`BufferedCall` of ``(x0, p, lbx,
        ubx, lbg, ubg) -> x`` for a solve under the variable bounds ``lbx``, ``ubx``, on a
        memory whose solves are functions of their arguments alone.

        fatrop builds its solver objects at a memory's first solve and keeps them with the
        memory; CasADi builds them anew where a solve's bounds have another pattern (which
        bounds are finite, which are equalities), and a solver built that way answers
        differently from one built at a memory's first solve (the README's example needed 12
        iterations on a fresh memory and 29, then failing, after one hard request; on one
        3-joint NLP, each of 3 problems of one pattern came out different after any of 13 of
        the other, and each of those 13 after any of the 3). A memory that has only ever
        solved under one pattern answers every solve as a fresh memory does (0 of 741 solves
        of 3- to 5-joint plans differed, bit for bit and in iterations, in random orders after
        the hard request). So fatrop keeps one memory per pattern of bounds
        (:func:`~.solvers.bound_pattern`) and reuses it, which saves building the objects:
        0.7-1 ms of a 3-joint solve of about 2 ms. IPOPT takes a fresh memory per solve (at
        no measurable cost: 12.5 against 12.6 ms on a used one, the same 15 iterations).
        A memory given back would go to the next call with what it holds, so these calls run
        on a solver of their own (not :meth:`solver`, which anyone may call), whose memories
        are never given back; once they hold about :data:`SPENT_MEMORY_BYTES`
        (:func:`~.solvers.memory_bytes`: 1-3 MB each), that solver is built anew (the old one
        frees them, and the next memories reuse that heap): about 1 ms compiled, 27-130 ms on
        CasADi's virtual machine (3 to 8 joints).
        """
        pattern = bound_pattern(lbx, ubx, self.lbg, self.ubg) if name in REUSED_MEMORIES \
            else None
        kept = self._by_pattern[name]
        if pattern is not None and pattern in kept:
            return kept[pattern]
        solver = self._calling.get(name)
        spent = self._spent[name]
        if solver is None or (spent and len(spent) * memory_bytes(solver) > SPENT_MEMORY_BYTES):
            solver = self._new_calling_solver(name)
            spent, kept = self._spent[name], self._by_pattern[name]
        call = BufferedCall(solver, 6)
        spent.append(call)
        if pattern is not None:
            kept[pattern] = call
        return call

    def fine_end(self, q0: np.ndarray, rates: np.ndarray, gains: Sequence[float]
                 ) -> np.ndarray:
        """The end state of :attr:`fine_path` from ``q0`` under ``rates`` (N, 2), on the robot
        of ``gains``."""
        return self._fine_end(q0, rates, np.asarray(gains, float))[0]

    def rk4_end_jacobian(self, q0: np.ndarray, rates: np.ndarray, gains: Sequence[float]
                         ) -> np.ndarray:
        """:attr:`end_jacobian` at ``rates`` (N, 2) on the robot of ``gains``: ``(n+1, 2N)``,
        columns in the order of ``rates.ravel()``."""
        return self._end_jacobian(q0, rates, np.asarray(gains, float))[0].reshape(
            2 * self.N, self.n + 1).T

    @functools.cached_property
    def _unit_grid(self) -> np.ndarray:
        """The nodes' normalised times ``k / N`` (read only)."""
        s = np.linspace(0.0, 1.0, self.N + 1)
        s.setflags(write=False)
        return s

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Open variable bounds ``(N+1, stride)`` (row ``k``: ``x_k`` then ``u_k``; the last
        row's ``u`` part is not in ``w``), with the epigraphs and slacks >= 0 and the start's
        slack 0 (the start is fixed): the caller adds its own and ravels with :meth:`flat`."""
        n = self.n
        lb = np.full((self.N + 1, self.stride), -np.inf)
        ub = np.full((self.N + 1, self.stride), np.inf)
        lb[:, n + 1:self.nx] = 0.0
        if self.region == "penalty":
            lb[:, self.nx + 2] = 0.0
            ub[0, self.nx + 2] = 0.0
        if self.soft_signs:
            lb[:, self.nx + 2] = 0.0
        return lb, ub

    def flat(self, W: np.ndarray) -> np.ndarray:
        """A ``(N+1, stride)`` table of variables as the NLP's vector."""
        return np.asarray(W, float).ravel()[:self.nw]

    def guess(self, a: np.ndarray, b: np.ndarray, phi0: float, travel: float) -> np.ndarray:
        """Straight lines in joint space (inside the region's box when start and goal are),
        ``phi`` moving by ``travel``; consistent rates."""
        N, n = self.N, self.n
        s = self._unit_grid
        Q = np.empty((N + 1, n + 1))
        Q[:, 0] = phi0 + travel * s
        Q[:, 1:] = a + s[:, None] * (b - a)
        # every node on both lines: the epigraphs just above 0
        return self._table(Q, 1e-4, 1e-4, np.array([travel, b[0] - a[0]]))

    def guess_from_nodes(self, Q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """A guess through node states ``Q`` (N+1, n+1): the rates of ``phi`` and ``th1``
        that join them, the deviations' epigraphs just above their values, zero slacks."""
        N = self.N
        d = Q[:, 1:] - a
        ell = b - a
        nrm = float(ell @ ell)
        S0 = float(np.max(np.sum(d * d, axis=1) - ((d @ ell) ** 2 / nrm if nrm > 0 else 0.0)))
        line1 = a[0] + (b[0] - a[0]) * self._unit_grid
        return self._table(Q, max(S0, 0.0) + 1e-4,
                           float(np.max((Q[:, 1] - line1) ** 2)) + 1e-4,
                           N * np.diff(Q[:, :2], axis=0))

    def _table(self, Q: np.ndarray, S: float, S1: float, rates: np.ndarray) -> np.ndarray:
        """The variables of node states ``Q``, epigraphs ``S``, ``S1`` and ``rates`` ((N, 2),
        or one pair for every interval), zero slacks, as the NLP's vector."""
        N, n = self.N, self.n
        W = np.zeros((N + 1, self.stride))
        W[:, :n + 1] = Q
        W[:, n + 1] = S
        W[:, n + 2] = S1
        if self.terminal == "elastic":  # the straight line's guess ends on the goal
            W[:, n + 3] = 1e-4
        W[:N, self.nx:self.nx + 2] = rates
        return self.flat(W)

    def unpack(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node states ``(N+1, n+1)`` and rates ``(N, 2)`` of a solution vector."""
        W = np.concatenate([w, np.zeros(self.nu)]).reshape(self.N + 1, self.stride)
        return W[:, :self.n + 1].copy(), W[:self.N, self.nx:self.nx + 2].copy()

    def goal_miss(self, w: np.ndarray, p: np.ndarray) -> float:
        """``max |th_N - goal|`` of a solution vector: 0 for a hard goal, which the solver
        meets to its tolerance, else the elastic goal's miss (see :data:`TERMINAL_MODES`)."""
        if self.terminal != "elastic":
            return 0.0
        n = self.n
        end = np.asarray(w, float)[self.N * self.stride + 1:self.N * self.stride + n + 1]
        return float(np.max(np.abs(end - np.asarray(p, float)[1 + n:1 + 2 * n])))

    def tightened(self, p: np.ndarray, factor: float) -> np.ndarray:
        """``p`` with the objective's weights divided by ``factor``: the elastic goal's
        penalty (fixed in the NLP) then weighs ``factor`` times more against them."""
        q = np.array(p, float)
        n = self.n
        q[1 + 2 * n:4 + 2 * n] /= factor
        if self.region == "penalty":  # the sensitivity's weight and the region's penalty
            q[5 + 2 * n:7 + 2 * n] /= factor
        return q

    def sign_slack(self, w: np.ndarray) -> float:
        """The largest soft-sign slack of a solution vector (0 without soft signs)."""
        if not self.soft_signs:
            return 0.0
        W = np.concatenate([w, np.zeros(self.nu)]).reshape(self.N + 1, self.stride)
        return float(np.max(W[:self.N, self.nx + 2]))

    def slacks(self, w: np.ndarray) -> np.ndarray:
        """The penalty's slacks ``s_0..s_{N-1}`` of a solution vector (zeros when hard)."""
        if self.region != "penalty":
            return np.zeros(self.N)
        W = np.concatenate([w, np.zeros(self.nu)]).reshape(self.N + 1, self.stride)
        return W[:self.N, self.nx + 2].copy()


def sensitivity_frobenius(s: Any, n: int) -> Any:
    """``||J_R||_F`` of ``s = z1(T) - z1(0)`` (eq 22) for a CasADi symbol ``s``:
    ``sqrt(1 + sum_{k<n} (n - k) s^(2k) / (k!)^2)``."""
    tot: Any = 1.0
    for k in range(n):
        tot = tot + (n - k) * s ** (2 * k) / math.factorial(k) ** 2
    return ca.sqrt(tot)


def default_terminal(n: int, free: bool = False) -> str:
    """The terminal mode of an ``n``-joint robot's NLPs (see :data:`TERMINAL_MODES`);
    ``free``: of a free rung, no rate's sign held (:data:`FREE_ELASTIC_FROM_JOINTS`)."""
    elastic = n >= ELASTIC_FROM_JOINTS or (free and n >= FREE_ELASTIC_FROM_JOINTS)
    return "elastic" if elastic else "hard"


def multiple_shooting_nlp(gains: tuple[float, ...], exponents: tuple[int, ...], fixed_phi: bool,
                          intervals: int, substeps: int,
                          region: str = "hard", deviation: str = "line",
                          deviation_points: int = 0,
                          terminal: str | None = None,
                          soft_signs: bool = False,
                          fatrop_settings: tuple[tuple[str, float], ...] = ()
                          ) -> MultipleShootingNLP:
    """The cached NLP of one robot's shape (its exponents: the gains are parameters,
    :func:`parameters`), transcription, region, deviation and terminal mode (per process;
    ``terminal`` None: :func:`default_terminal`; ``fatrop_settings``: see
    :class:`MultipleShootingNLP`)."""
    return _shaped_nlp(tuple(int(m) for m in exponents), fixed_phi, intervals, substeps, region,
                       deviation, deviation_points,
                       terminal or default_terminal(len(exponents) + 1), soft_signs,
                       fatrop_settings)


@functools.lru_cache(maxsize=16)
def _shaped_nlp(exponents: tuple[int, ...], fixed_phi: bool, intervals: int, substeps: int,
                region: str, deviation: str, deviation_points: int, terminal: str,
                soft_signs: bool, fatrop_settings: tuple[tuple[str, float], ...]
                ) -> MultipleShootingNLP:
    return MultipleShootingNLP(exponents, fixed_phi, intervals, substeps, region, deviation,
                               deviation_points, terminal, soft_signs, fatrop_settings)


def nlp_for(req: PlanRequest, tr: Transcription, region: str = "hard",
            deviation: str = "line", deviation_points: int = 0,
            soft_signs: bool = False, free: bool = False,
            fatrop_settings: tuple[tuple[str, float], ...] = ()) -> MultipleShootingNLP:
    """The cached NLP of ``req``'s robot under transcription ``tr`` (``deviation_points``:
    inner points per interval that the deviation epigraph bounds too, besides the nodes;
    ``soft_signs``: the rates' signs as penalised rows, see :data:`SIGN_PENALTY`; ``free``:
    of a free rung, its terminal mode :func:`default_terminal`'s for free rungs;
    ``fatrop_settings``: see :class:`MultipleShootingNLP`)."""
    n = len(req.robot.exponents) + 1
    return multiple_shooting_nlp(tuple(float(k) for k in req.robot.gains),
                                 tuple(int(m) for m in req.robot.exponents),
                                 req.phi_change is not None, tr.intervals, tr.substeps, region,
                                 deviation, deviation_points, default_terminal(n, free),
                                 soft_signs, fatrop_settings)


def node_bounds(req: PlanRequest, limits: tuple[np.ndarray, np.ndarray],
                margin: float = MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """Per joint: its limits ``(lo, hi)`` moved in by ``margin`` (less near start or goal)."""
    lo_m, hi_m = [], []
    for a, b, lo, hi in zip(req.start, req.goal, *(np.asarray(x, float).tolist()
                                                      for x in limits)):
        # (an infinite bound stays infinite; the margin is at most half the room left)
        lo_m.append(lo + min(margin, 0.5 * (min(a, b) - lo)) if math.isfinite(lo) else -math.inf)
        hi_m.append(hi - min(margin, 0.5 * (hi - max(a, b))) if math.isfinite(hi) else math.inf)
    return np.array(lo_m), np.array(hi_m)


def objective_weights(req: PlanRequest, method: str) -> tuple[float, float, float]:
    """``(w_dev, w_energy, w_da)`` of the transcription's objective for ``req``:
    :data:`DEVIATION_WEIGHT`, 1 and :data:`D_A_WEIGHT` (:data:`PAPER_D_A_WEIGHT` under
    ``tp_then_da``), or ``weights.d_a`` (both deviations)
    and ``weights.energy`` of a ``weighted`` request.

    Raises
    ------
    InvalidRequestError
        ``weighted`` with neither ``weights.d_a`` nor ``weights.energy`` positive.
    """
    if req.objective == "weighted":
        w_dev, w_en = float(req.weights.d_a), float(req.weights.energy)
        if w_dev <= 0.0 and w_en <= 0.0:
            raise InvalidRequestError(f"method '{method}' with objective 'weighted' needs a "
                                      "positive weights.d_a or weights.energy", field="weights")
        return w_dev, w_en, w_dev
    return DEVIATION_WEIGHT, 1.0, (PAPER_D_A_WEIGHT if req.objective == "tp_then_da"
                                   else D_A_WEIGHT)


def variable_bounds(req: PlanRequest, nlp: MultipleShootingNLP, tr: Transcription,
                    node_lo: np.ndarray | None = None, node_hi: np.ndarray | None = None,
                    rate_signs: tuple[float, float] | np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """``lbx, ubx`` of ``req`` on ``nlp``: the rates within ``tr.rate_bound`` (keeps the NLP's
    RK4 steps accurate, see :data:`LADDER`), ``phi_N`` within the request's ``dphi`` bounds
    (unless fixed), the joints of every node within ``node_lo, node_hi`` when given (the hard
    region), each rate of the sign ``rate_signs`` gives it (0: either); also the ``dphi`` range
    ``(lo, hi)`` the guesses must respect."""
    n, N = nlp.n, nlp.N
    lbW, ubW = nlp.bounds()
    if node_lo is not None and node_hi is not None:
        lbW[:, 1:n + 1], ubW[:, 1:n + 1] = node_lo, node_hi
    lbW[:N, nlp.nx:nlp.nx + 2], ubW[:N, nlp.nx:nlp.nx + 2] = -tr.rate_bound, tr.rate_bound
    # one sign per actuator, or one per interval and actuator (N, 2); 0: either
    if rate_signs is not None:
        signs = np.broadcast_to(np.asarray(rate_signs, float), (N, 2))
        rate_lb, rate_ub = lbW[:N, nlp.nx:nlp.nx + 2], ubW[:N, nlp.nx:nlp.nx + 2]  # views
        rate_lb[signs > 0] = 0.0
        rate_ub[signs < 0] = 0.0
    if req.phi_change is not None:
        lo_phi = hi_phi = float(req.phi_change)
    else:
        lo_phi, hi_phi = req.phi_change_bounds
        lbW[N, 0], ubW[N, 0] = req.phi_start + lo_phi, req.phi_start + hi_phi
    if req.via_points:  # each via point's joint fixed at its node (optimizer.planner.via)
        via.pin_via_nodes(req, N, lbW, ubW)
    return nlp.flat(lbW), nlp.flat(ubW), (lo_phi, hi_phi)


def parameters(req: PlanRequest, w_dev: float, w_energy: float, w_da: float,
               penalty: tuple[float, float, np.ndarray, np.ndarray] | None = None,
               signs: np.ndarray | None = None) -> np.ndarray:
    """The parameter vector of ``req``: start, goal, weights, fixed ``dphi``, for the
    penalty mode ``(w_sens, rho, lo, hi)`` (infinite bounds become :data:`OPEN_BOUND`) and,
    with soft signs, the signs ``(N, 2)`` of the rates (0: either) and :data:`SIGN_PENALTY`;
    last, the robot's gains ``K_2..K_n``."""
    dphi = 0.0 if req.phi_change is None else float(req.phi_change)
    p = [np.array([req.phi_start]), np.array(req.start), np.array(req.goal),
         np.array([w_dev, w_energy, w_da, dphi])]
    if penalty is not None:
        w_sens, rho, lo, hi = penalty
        p += [np.array([w_sens, rho]), np.clip(lo, -OPEN_BOUND, OPEN_BOUND),
              np.clip(hi, -OPEN_BOUND, OPEN_BOUND)]
    if signs is not None:
        p += [np.asarray(signs, float).ravel(), np.array([SIGN_PENALTY])]
    p.append(np.asarray(req.robot.gains, float))
    return np.concatenate(p).astype(float)
