"""Piecewise-constant actuator rates: the input schedule of plans made on the original model."""

from __future__ import annotations

import bisect
import functools
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ActuatorSchedule:
    """Piecewise-constant actuator rates ``u = (u1, u2)`` (rad/s) on ``[0, T]``.

    Attributes
    ----------
    breaks : ndarray (N+1,)
        Times (s) where the rates change, ``breaks[0] = 0``, ``breaks[-1] = T``.
    rates : ndarray (N, 2)
        ``(u1, u2)`` on each interval.
    """

    breaks: np.ndarray
    rates: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.breaks[-1])

    @property
    def T(self) -> float:  # the name the integrators use
        return self.duration

    @property
    def pieces(self) -> int:
        return int(self.rates.shape[0])

    @property
    def constant_v1(self) -> bool:
        """Never the paper's family (``v1`` is piecewise constant, ``v2`` not polynomial)."""
        return False

    @property
    def phi_change(self) -> float:
        return float(np.dot(np.diff(self.breaks), self.rates[:, 0]))

    def piece_index(self, t: np.ndarray) -> np.ndarray:
        idx = np.searchsorted(self.breaks, t, side="right") - 1
        return np.clip(idx, 0, self.pieces - 1)

    def u(self, t: np.ndarray) -> np.ndarray:
        """Rates at many times, shape (N, 2) (open loop: a function of time only)."""
        return self.rates[self.piece_index(np.atleast_1d(np.asarray(t, float)))]

    def u_scalar(self, t: float, _q: np.ndarray | None = None) -> np.ndarray:
        """Rates at one time (the integrators' right-hand side: called 10^4-10^5 times by a
        DOP853 replay, so found by bisection on plain lists, not numpy's per-call
        machinery; the same piece as :meth:`piece_index`)."""
        inner, rows = self._lookup
        return np.array(rows[bisect.bisect_right(inner, t)])

    @functools.cached_property
    def _lookup(self) -> tuple[list[float], list[tuple[float, float]]]:
        # the inner breaks (a time at or after breaks[k] lies in piece k: piece_index's
        # side="right", clipped to the first and last pieces) and each piece's rates
        inner = [float(b) for b in self.breaks[1:-1]]
        rows = [(float(r[0]), float(r[1])) for r in self.rates]
        return inner, rows

    def physical_coefficients(self) -> list[dict[str, object]]:
        """Per interval: times (s), ``v1 = u1`` (constant) and the actuator rates ``u1, u2``.

        ``v2`` is not a polynomial here (``v2 = L_g1 z2 u1 + L_g2 z2 u2`` along the path): its
        list is empty; the rates regenerate the plan.
        """
        return [{"t_start": float(self.breaks[k]), "t_end": float(self.breaks[k + 1]),
                 "v1": [float(self.rates[k, 0])], "v2": [],
                 "u": [float(self.rates[k, 0]), float(self.rates[k, 1])]}
                for k in range(self.pieces)]
