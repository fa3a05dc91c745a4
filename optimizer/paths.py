"""Time samples of a path: what a plan hands out, and what its forms are re-integrated into."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SampledPath:
    """Time samples of a plan.

    Attributes
    ----------
    t : ndarray (N,)
        s.
    q : ndarray (N, n+1)
        ``[phi, th1..thn]``, rad.
    z : ndarray (N, n+1)
        Chained state.
    u : ndarray (N, 2)
        Actuator rates ``[u1, u2]``, rad/s.
    v : ndarray (N, 2)
        Chained inputs ``[v1, v2]``.
    """

    t: np.ndarray
    q: np.ndarray
    z: np.ndarray
    u: np.ndarray
    v: np.ndarray


__all__ = ["SampledPath"]
