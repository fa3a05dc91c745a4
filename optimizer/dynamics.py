"""The original model's vector field and a classical RK4 step, written once (paper eq 1-3).

State ``q = [phi, th1, ..., thn]``, actuator rates ``u = [u1, u2]``::

    phi'  = u1
    th1'  = u2
    th_i' = K_i cos(th_{i-1})^{m_i} u1        (i = 2..n)

Why one definition for two kinds of numbers
-------------------------------------------
The same expressions serve numpy (re-integration, the robot's ``rhs``) and CasADi symbols (the
NLPs of :mod:`optimizer.planner.nlp`): the functions below use only indexing, ``+``, ``*`` and
the ``cos`` they are given, which numpy arrays and CasADi ``SX``/``MX`` both support. A change of
the model is then made in one place and cannot leave an NLP and its verification disagreeing.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

#: ``x, u -> x'`` of any number type (numpy array or CasADi symbol).
Field = Callable[[Any, Any], Any]


def power(c: Any, m: int) -> Any:
    """``c ** m`` for an integer ``m >= 1`` as a product.

    For CasADi this keeps the derivative graphs smaller than a ``pow`` node does; the same
    operations are used for numpy so that both evaluate the same expression.
    """
    out = c
    for _ in range(int(m) - 1):
        out = out * c
    return out


def joint_rate(gains: Sequence[Any], exponents: Sequence[int], i: int, th_prev: Any, u1: Any,
               cos: Callable[[Any], Any] = np.cos) -> Any:
    """``th_i' = K_i cos(th_{i-1})^{m_i} u1`` of joint ``i`` (2..n) from ``th_{i-1}``: the one
    place the transmission's law is written (the cascade quadrature of
    :mod:`optimizer.verify` integrates the joints one after another with it)."""
    return gains[i - 2] * power(cos(th_prev), exponents[i - 2]) * u1


def vector_field(gains: Sequence[Any], exponents: Sequence[int], q: Any, u1: Any, u2: Any,
                 cos: Callable[[Any], Any] = np.cos) -> list[Any]:
    """The components ``[phi', th1', th2', ..., thn']`` of the model (eq 2-3).

    Parameters
    ----------
    gains, exponents : sequence
        ``K_2..K_n`` (numbers, or CasADi symbols: the compiled maps take them as an input)
        and ``m_2..m_n``.
    q : indexable
        ``q[0] = phi, q[i] = th_i``: a 1-D numpy array, an array whose FIRST axis is the
        state (``q[i]`` then holds many states' ``th_i``), or a CasADi column vector.
    u1, u2 : number, array or symbol
        The actuator rates (broadcast against ``q[i]``).
    cos : callable
        ``numpy.cos`` (default) or ``casadi.cos``.

    Returns
    -------
    list
        ``n + 1`` components, in the type of the arguments (stack them with ``numpy.stack`` or
        ``casadi.vertcat``).
    """
    out = [u1, u2]
    for i in range(2, len(gains) + 2):
        out.append(joint_rate(gains, exponents, i, q[i - 1], u1, cos))
    return out


def field_numpy(gains: Sequence[float], exponents: Sequence[int], q: np.ndarray,
                u: Sequence[Any]) -> np.ndarray:
    """``q'`` for numpy states ``q`` of shape ``(..., n+1)`` and rates ``u = (u1, u2)``."""
    q = np.asarray(q, dtype=float)
    comps = vector_field(gains, exponents, np.moveaxis(q, -1, 0), u[0], u[1], np.cos)
    return np.stack(np.broadcast_arrays(*comps), axis=-1).astype(float, copy=False)


def rk4_step(f: Field, x: Any, u: Any, h: Any, substeps: int = 1) -> Any:
    """``substeps`` classical Runge-Kutta steps of ``x' = f(x, u)`` over ``h`` (``u`` held).

    Works for numpy arrays and CasADi symbols alike (only ``+`` and ``*`` on ``x``).
    """
    dt, y = h / substeps, x
    for _ in range(int(substeps)):
        k1 = f(y, u)
        k2 = f(y + dt / 2 * k1, u)
        k3 = f(y + dt / 2 * k2, u)
        k4 = f(y + dt * k3, u)
        y = y + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y


__all__ = ["Field", "field_numpy", "joint_rate", "power", "rk4_step", "vector_field"]
