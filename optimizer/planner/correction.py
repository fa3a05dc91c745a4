"""From an NLP's answer to a plan: Newton steps that move the rates onto the exact model's
goal (:func:`correct_rates`), then the finishing path every actuator plan takes
(:func:`finish_solution`). Used by ``shooting`` and ``penalty``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..indicators import count_reversals
from ..problem import PlanRequest
from ..results import Plan
from .finish import finish_actuator_plan
from .nlp import MultipleShootingNLP, Transcription
from .rules import TERMINAL_TOLERANCE
from .rungs import signs_list
from .via import correct_rates_through_vias


#: The Newton correction stops once the model ends this close to the goal (rad)...
CORRECTION_TARGET = 1e-9


#: ... or after this many steps.
MAX_CORRECTIONS = 4


#: Rates held to signs that the correction brings this close to the goal (rad, fine end map,
#: within ~1e-12 of the exact model) are kept, even where free steps would come closer: the
#: plan's tolerance is :data:`~.rules.TERMINAL_TOLERANCE` (4 times this), and free steps buy
#: their last 1e-8 rad with reversals (a 6-joint goal: 6.6e-8 rad held, 4.6e-8 free with 4
#: more reversals of th1; an 8-joint goal: 1.2e-7 held, 1.1e-7 free with 4 more).
HELD_ACCEPT = 0.25 * TERMINAL_TOLERANCE


def finish_solution(req: PlanRequest, method: str, nlp: MultipleShootingNLP, sol: Any,
                    tr: Transcription, signs: Any, tried: list[dict[str, Any]],
                    timing: dict[str, float], details: dict[str, Any]) -> Plan:
    """The plan of an NLP answer of ``shooting`` or ``penalty``: :func:`correct_rates` onto
    the goal, then :func:`~.finish.finish_actuator_plan` (with the defect correction as its
    ``refine``); ``diagnostics[method]`` holds the transcription, the rungs' record and the
    solver's, updated with the method's own ``details``."""
    t0 = time.perf_counter()
    phi_end = float(sol.nodes[-1, 0])
    held = signs  # the correction keeps the rates of the signs the NLP held them to...
    rates, errors = correct_rates(req, nlp, sol.rates, phi_end, signs=held)
    if held is not None and min(errors) > CORRECTION_TARGET:
        # the held signs keep the correction off the goal: free steps, kept where they come
        # closer with no more reversals, or where the held rates are off by more than
        # HELD_ACCEPT (a reversal of a few thousandths of a degree may come with them then)
        free, more = correct_rates(req, nlp, sol.rates, phi_end)
        if min(more) < min(errors) and (min(errors) > HELD_ACCEPT
                                        or rate_reversals(free) <= rate_reversals(rates)):
            rates, errors, held = free, errors + more, None
    timing["correction"] = time.perf_counter() - t0
    record = {"intervals": rates.shape[0], "rk4_substeps": tr.substeps,
              "rate_bound": tr.rate_bound, "monotone": signs_list(signs),
              "status": sol.status, "iterations": sol.iterations, "start": sol.start,
              "tried": tried + list(sol.tried),
              # the answering solver evaluated compiled C (optimizer.native)
              "compiled": getattr(sol, "compiled",
                                  nlp.compiled and sol.status.startswith("fatrop")),
              "terminal_error_per_correction": errors, **details}

    def refine(exact_end: np.ndarray) -> np.ndarray:
        # the quadrature's end missed the goal: correct for the fine map's error there
        again, more = correct_rates(req, nlp, rates, phi_end, exact_end, signs=held)
        errors.extend(more)
        return again

    diagnostics = {"objective": req.objective, "singularity": "full", method: record}
    return finish_actuator_plan(req, rates, method, sol.nodes, timing, diagnostics, refine)


#: Relative residual ``|J x - r| / |r|`` below which the normal equations' step is kept.
STEP_RESIDUAL = 1e-9
#: Largest change of a rate (per unit of normalised time) a step of the normal equations may
#: make; larger steps come from directions the rates barely move the end in, and are taken
#: from the truncated SVD instead.
STEP_LIMIT = 0.05
#: Singular values of the end map's Jacobian below this fraction of the largest are left out
#: of a step: from 6 joints the Jacobian's singular values span 0.35 to 1e-11 (the highest
#: Lie brackets), and cancelling a 1e-8 rad miss along the weakest would move the rates by
#: hundreds (the NLP's elastic goal leaves almost nothing there, see ``ELASTIC_MISS``).
STEP_RCOND = 1e-7


def rate_reversals(rates: np.ndarray) -> int:
    """Reversals of ``phi`` and ``th_1`` together along rates ``(N, 2)`` of equal intervals,
    counted on the nodes they reach (as the ladder ranks NLP answers)."""
    nodes = np.cumsum(np.vstack([np.zeros((1, 2)), rates]), axis=0) / rates.shape[0]
    return count_reversals(nodes[:, 0]) + count_reversals(nodes[:, 1])


def minimum_norm_step(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The least-norm ``x`` with ``J x = r`` (``J``: few rows, full row rank), as
    ``np.linalg.lstsq`` gives it.

    ``x = J^T y`` with ``(J J^T) y = r`` lies in the row space of ``J``; when it also solves
    ``J x = r`` (relative residual below :data:`STEP_RESIDUAL`) it is the least-norm solution.
    ``J J^T`` can be singular in double precision (nearly parallel rows) while ``J`` itself is
    fine: then the residual shows it and the SVD-based least squares answers instead. The
    normal equations are a small solve, where the SVD's setup dominates a Newton step here.
    """
    try:
        x = J.T @ np.linalg.solve(J @ J.T, r)
    except np.linalg.LinAlgError:
        x = None
    if x is not None:
        res = J @ x - r
        scale = float(r @ r)
        if (math.isfinite(float(x @ x)) and float(res @ res) <= STEP_RESIDUAL ** 2 * scale
                and float(np.max(np.abs(x))) <= STEP_LIMIT):
            return x
    return np.linalg.lstsq(J, r, rcond=STEP_RCOND)[0]


def correct_rates(req: PlanRequest, nlp: MultipleShootingNLP, rates: np.ndarray,
                  phi_end: float, exact_end: np.ndarray | None = None,
                  signs: Any = None) -> tuple[np.ndarray, list[float]]:
    """Newton steps that move the NLP's rates onto the goal of the original model.

    The NLP's RK4 (one step per interval) ends 1e-8 to 1e-5 rad from the goal of the original
    model under its rates. Each step measures the end error with the fine end map
    (:attr:`MultipleShootingNLP.fine_path`: the same RK4 with :data:`FINE_SUBSTEPS` times the
    steps, within ~1e-12 rad of the exact model) and applies the minimum-norm change of the
    rates that cancels it to first order, with the Jacobian of the NLP's RK4 model (close to
    the exact one: the error falls by orders of magnitude per step). ``phi``'s end is held at
    the NLP's value (its row is exact). The proof is not here: the caller re-integrates the
    corrected rates by quadrature (:func:`optimizer.planner.finish.finish_actuator_plan`).

    Parameters
    ----------
    exact_end : ndarray (n+1,), optional
        The exact model's end state under ``rates`` (that quadrature), when it missed the
        goal: the fine map's error there (``exact_end`` minus its own end) is subtracted from
        the goal, so the steps aim the fine map at where it must end for the exact model to
        reach the goal (a defect correction; the error changes little with the rates).
    signs : pair or ndarray (N, 2), optional
        The signs the NLP held the rates to (0: free). A held rate stays of its sign: one at
        0 (its bound) is left out of the steps, and a step is cut back to the bound, so that
        the correction adds no reversal (a rate of -0.0026 between two positive ones, each
        0.0075 deg of travel, added two reversals of th1 to a 6-joint plan).

    Returns
    -------
    rates : ndarray (N, 2)
        The best rates met (a step that made things worse is not kept).
    errors : list of float
        ``max |th(1) - goal|`` of the fine end map before each step and after the last.
    """
    if req.via_points:  # the via angles too (optimizer.planner.via)
        return correct_rates_through_vias(req, nlp, rates, phi_end, exact_end)
    N = rates.shape[0]
    q0 = req.q_start()
    target = np.concatenate([[phi_end], req.goal])
    U = np.array(rates, float)
    if exact_end is not None:
        target = target - (np.asarray(exact_end, float)
                           - nlp.fine_end(q0, U, req.robot.gains))
    held = None if signs is None else np.broadcast_to(np.asarray(signs, float), (N, 2))
    errors: list[float] = []
    best: tuple[float, np.ndarray] | None = None
    end = nlp.fine_end(q0, U, req.robot.gains)
    for k in range(MAX_CORRECTIONS + 1):
        r = end - target
        err = float(np.max(np.abs(r[1:])))
        errors.append(err)
        if not math.isfinite(err):
            break
        if best is None or err < best[0]:
            best = (err, U)
        if err <= 1e-3 * CORRECTION_TARGET or k == MAX_CORRECTIONS:
            break
        J = nlp.rk4_end_jacobian(q0, U, req.robot.gains)
        if held is not None:
            J = np.where((held != 0.0) & (U * held <= 0.0), 0.0, J.reshape(-1, N, 2)
                         ).reshape(J.shape)
        U = _held_to(held, U - minimum_norm_step(J, r).reshape(N, 2))
        end = nlp.fine_end(q0, U, req.robot.gains)
    return (U if best is None else best[1]), errors


def _held_to(held: np.ndarray | None, U: np.ndarray) -> np.ndarray:
    """``U`` with every held rate cut back to its sign's bound (0)."""
    if held is None:
        return U
    return np.where(held > 0.0, np.maximum(U, 0.0), np.where(held < 0.0, np.minimum(U, 0.0), U))
