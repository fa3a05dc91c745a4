"""Independent reference implementations for the tests.

The reference model here is written from the paper's eq (1)-(3) (NOTES §1, §3) and does not use
the library, so tests that integrate it check the library against an independent computation.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

PROTOTYPE_K = (0.88658, 0.7115)
PROTOTYPE_M = (2, 3)


def model_rhs(q: np.ndarray, u: np.ndarray, K, m) -> np.ndarray:
    """phi' = u1, th1' = u2, th_i' = K_i cos(th_{i-1})^m_i u1 (written independently)."""
    dq = np.zeros_like(q)
    dq[0] = u[0]
    dq[1] = u[1]
    for i in range(2, len(q)):
        dq[i] = K[i - 2] * np.cos(q[i - 1]) ** m[i - 2] * u[0]
    return dq


def integrate_model(u_of_t, q0, T, K, m, t_eval=None):
    """Integrate the original model with scipy (DOP853, rtol 1e-10, atol 1e-12)."""
    sol = solve_ivp(lambda t, q: model_rhs(q, u_of_t(t), K, m), (0.0, T), np.asarray(q0, float),
                    method="DOP853", rtol=1e-10, atol=1e-12, t_eval=t_eval)
    assert sol.success, sol.message
    return sol


def turns(x: np.ndarray, band: float = 1e-4) -> int:
    """Direction changes of a sampled signal: one each time it comes back from its running
    extreme by more than ``band`` (written here, not the library's)."""
    count, direction, ext = 0, 0, float(x[0])
    for v in map(float, x[1:]):
        if direction == 0:
            if abs(v - x[0]) > band:
                direction, ext = (1 if v > x[0] else -1), v
        elif direction * (v - ext) > 0:
            ext = v
        elif direction * (ext - v) > band:
            count, direction, ext = count + 1, -direction, v
    return count
