"""The top-down inverse map of the chained form, level by level, as numpy code.

At one point the inverse is taken from the top: ``z_n = K_n w_n`` gives ``th_{n-1}``, and each
level below, ``z_k = a_k w_k + b_k`` with ``w_k = cos(th_{k-1})^m_k``, gives ``th_{k-1}`` from the
joints above. :class:`InverseLevels` returns ``(a_k, b_k)``: levels n, n - 1 and n - 2 in closed
form, lower levels (n >= 5) by numpy code generated once per robot from the CasADi expressions
of the chained form (:func:`compile_sx`), one numpy operation per SX instruction on all points
at once.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Sequence

import casadi as ca
import numpy as np

from .chained_form import symbolic_form
from .model import Robot

_UNARY = {ca.OP_NEG: "-{0}", ca.OP_SQ: "{0} * {0}", ca.OP_TWICE: "{0} + {0}",
          ca.OP_COS: "_np.cos({0})", ca.OP_SIN: "_np.sin({0})", ca.OP_SQRT: "_np.sqrt({0})",
          ca.OP_ACOS: "_np.arccos({0})", ca.OP_ASIN: "_np.arcsin({0})",
          ca.OP_FABS: "_np.abs({0})", ca.OP_INV: "1.0 / {0}", ca.OP_EXP: "_np.exp({0})",
          ca.OP_LOG: "_np.log({0})", ca.OP_TAN: "_np.tan({0})"}
_BINARY = {ca.OP_ADD: "{0} + {1}", ca.OP_SUB: "{0} - {1}", ca.OP_MUL: "{0} * {1}",
           ca.OP_DIV: "{0} / {1}", ca.OP_POW: "{0} ** {1}", ca.OP_CONSTPOW: "{0} ** {1}"}


def compile_sx(f: ca.Function) -> Callable[..., list[Any]] | None:
    """The SX function ``f`` (one vector input, or two: the second the gains; one vector
    output) as numpy code: a callable ``fn(x, g=())`` taking the first input's entries ``x``
    (arrays or numbers that broadcast) and the second's ``g`` (numbers), and returning the
    output's entries. ``None`` when ``f`` uses an operation not translated here.

    One numpy operation per SX instruction, on all points at once: for thousands of points this
    is many times faster than CasADi's column-by-column evaluation.
    """
    if not f.is_a("SXFunction") or f.n_in() not in (1, 2) or f.n_out() != 1:
        return None
    consts: list[float] = []
    lines = ["def _f(x, g=()):", f"    out = [0.0] * {f.nnz_out(0)}"]
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        i = f.instruction_input(k)
        o = f.instruction_output(k)
        if op == ca.OP_CONST:
            consts.append(float(f.instruction_constant(k)))
            lines.append(f"    w{o[0]} = _c[{len(consts) - 1}]")
        elif op == ca.OP_INPUT:
            lines.append(f"    w{o[0]} = {'x' if i[0] == 0 else 'g'}[{i[1]}]")
        elif op == ca.OP_OUTPUT:
            lines.append(f"    out[{o[1]}] = w{i[0]}")
        elif op in _UNARY:
            lines.append(f"    w{o[0]} = " + _UNARY[op].format(f"w{i[0]}"))
        elif op in _BINARY:
            lines.append(f"    w{o[0]} = " + _BINARY[op].format(f"w{i[0]}", f"w{i[1]}"))
        else:
            return None
    lines.append("    return out")
    scope: dict[str, Any] = {"_np": np, "_c": consts}
    exec("\n".join(lines), scope)  # noqa: S102 - code generated from the instruction list above
    fn: Callable[..., list[Any]] = scope["_f"]
    return fn


@functools.lru_cache(maxsize=16)
def _level_functions(exponents: tuple[int, ...]) -> dict[int, Callable[..., list[Any]]]:
    """``(q, gains) -> (a_k, b_k)`` of the levels k = 2..n-3 as numpy code, once per exponents
    (the gains an argument: 77 ms of translation at n = 8 that a robot of new gains does not
    pay again)."""
    n = len(exponents) + 1
    sym = symbolic_form(exponents)
    fns: dict[int, Callable[..., list[Any]]] = {}
    for k in range(2, n - 2):
        fn = compile_sx(sym.ab[k])
        fns[k] = fn if fn is not None else casadi_caller(sym.ab[k], n)
    return fns


class InverseLevels:
    """``a_k``, ``b_k`` of the top-down inverse map (``z_k = a_k w_k + b_k``) as numpy code.

    Level n is ``z_n = K_n w_n``; levels n - 1 and n - 2 in closed form (see :meth:`ab`); below
    (n >= 5) the CasADi expressions of :class:`optimizer.chained_form.SymbolicChainedForm` are
    translated once per exponents (:func:`compile_sx`, the gains an argument), with CasADi
    itself as the fallback.
    """

    def __init__(self, robot: Robot) -> None:
        self.n = n = robot.n
        self.K = robot.gains
        self.m = robot.exponents
        self.fns = _level_functions(tuple(robot.exponents)) if n > 4 else {}

    def ab(self, k: int, th: dict[int, Any], cs: dict[int, Any]) -> tuple[Any, Any]:
        """``(a_k, b_k)`` from the angles ``th[j]`` (j >= k) and their cosines ``cs[j]``."""
        n = self.n
        if k == n:
            return self.K[-1], 0.0
        K, m = self.K, self.m
        if k >= n - 2:
            # closed forms: z_n = K_n c^m_n (c = cos th_{n-1}), so
            # a_{n-1} = -m_n K_{n-1} K_n c^(m_n-1) s, b_{n-1} = 0, and from
            # z_{n-1} = a_{n-1}(th_{n-1}) w_{n-1}:
            # a_{n-2} = K_{n-2} a_{n-1} d w_{n-1}/d th_{n-2}, b_{n-2} = K_{n-1} a'_{n-1} w_{n-1}^2
            mn = m[-1]
            c = cs[n - 1]
            with np.errstate(invalid="ignore"):
                s = np.sqrt(1.0 - c * c)
            cm1 = c * c if mn == 3 else c ** (mn - 1)
            a1 = (-mn * K[-2] * K[-1]) * cm1 * s
            if k == n - 1:
                return a1, 0.0
            m1 = m[-2]
            c2 = cs[n - 2]
            with np.errstate(invalid="ignore"):
                s2 = np.sqrt(1.0 - c2 * c2)
            w1 = c2 * c2 if m1 == 2 else c2 ** m1
            dw = -m1 * (c2 if m1 == 2 else c2 ** (m1 - 1)) * s2
            da1 = (-mn * K[-2] * K[-1]) * (cm1 * c - (mn - 1) * c ** (mn - 2) * s * s)
            return K[-3] * a1 * dw, K[-2] * da1 * w1 * w1
        q: list[Any] = [0.0] * (n + 1)
        for j in range(k, n + 1):
            q[j] = th[j]
        with np.errstate(all="ignore"):
            out = self.fns[k](q, self.K)
        return out[0], out[1]


def casadi_caller(f: ca.Function, n: int) -> Callable[..., list[Any]]:
    def call(q: Sequence[Any], gains: Sequence[float]) -> list[Any]:
        arrs = np.broadcast_arrays(*[np.asarray(x, float) for x in q])
        shape = arrs[0].shape
        res = np.asarray(f(np.vstack([a.ravel() for a in arrs]), ca.DM(list(gains))))
        return [res[r].reshape(shape) for r in range(res.shape[0])]
    return call


@functools.lru_cache(maxsize=64)
def inverse_levels(robot: Robot) -> InverseLevels:
    return InverseLevels(robot)


def root_m(w: Any, m: int) -> Any:
    """``w^(1/m)`` (the cosine of the joint angle)."""
    if m == 1:
        return w
    if m == 2:
        return np.sqrt(w)
    if m == 3:
        return np.cbrt(w)
    return w ** (1.0 / m)

