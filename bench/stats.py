"""Repeated wall-clock timing in-process, and summaries of samples."""

from __future__ import annotations

import gc
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import numpy as np


@dataclass
class Summary:
    """Median and spread of a sample (seconds unless said otherwise).

    Attributes
    ----------
    median, q1, q3, min, max : float
    count : int
    samples : list of float
    """

    median: float
    q1: float
    q3: float
    min: float
    max: float
    count: int
    samples: list[float] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly copy."""
        return asdict(self)


def summarise(samples: Sequence[float]) -> Summary:
    """Median, quartiles and extremes of ``samples`` (NaN everywhere when empty)."""
    xs = [float(x) for x in samples]
    if not xs:
        nan = math.nan
        return Summary(nan, nan, nan, nan, nan, 0, [])
    a = np.asarray(xs)
    q1, med, q3 = np.percentile(a, [25, 50, 75])
    return Summary(float(med), float(q1), float(q3), float(a.min()), float(a.max()), a.size, xs)


@dataclass
class Timed:
    """Outcome of :func:`time_repeats`.

    Attributes
    ----------
    first : float
        The warm-up call (s).
    summary : Summary
        The timed repeats after the warm-up.
    result : Any
        The last call's return value (None when it raised).
    error : BaseException or None
        The warm-up call's exception, if any.
    repeat_errors : list of str
        ``"Type: message"`` of every timed repeat that raised (the outcome may change between
        repeats, e.g. when a solve runs into its deadline).
    """

    first: float
    summary: Summary
    result: Any = None
    error: BaseException | None = None
    repeat_errors: list[str] = field(default_factory=list)


def time_repeats(fn: Callable[[], Any], repeats: int, budget: float, min_repeats: int = 1,
                 repeat_failures: bool = True) -> Timed:
    """Time ``fn()`` after one warm-up call.

    The number of repeats adapts to the cost: at most ``repeats``, at least ``min_repeats``,
    and otherwise as many as fit in ``budget`` seconds judging by the warm-up.

    The garbage is collected once before the warm-up, and the collector is off during the
    timed repeats (:mod:`timeit`'s convention), so that no collection lands inside a timed
    call. A full collection before every call instead (as here until session 11) walks every
    object of the process and leaves the caches cold: in the goals benchmark's process the
    3-joint default plan then measured 4.5 ms p50 instead of 3.5, the IPOPT baseline 9.7
    instead of 8.1 ms; no service or notebook collects before every plan.

    Parameters
    ----------
    fn : callable
        Called with no arguments; may raise.
    repeats : int
        Largest number of timed repeats.
    budget : float
        Seconds the timed repeats may take (roughly).
    min_repeats : int
        Smallest number of timed repeats.
    repeat_failures : bool
        Also time repeats when the warm-up raised (a fast, typed rejection is a result too).

    Returns
    -------
    Timed
        ``result`` is the last successful call's value (None when every call raised).
    """
    gc.collect()
    t0 = time.perf_counter()
    result: Any = None
    error: BaseException | None = None
    try:
        result = fn()
    except Exception as exc:  # noqa: BLE001 - recorded, not hidden
        error = exc
    first = time.perf_counter() - t0
    if error is not None and not repeat_failures:
        return Timed(first, summarise([]), None, error)
    k = max(min_repeats, min(repeats, int(budget / max(first, 1e-6))))
    samples = []
    repeat_errors: list[str] = []
    enabled = gc.isenabled()
    gc.disable()
    try:
        for _ in range(k):
            t0 = time.perf_counter()
            try:
                out = fn()
            except Exception as exc:  # noqa: BLE001 - recorded
                repeat_errors.append(f"{type(exc).__name__}: {exc}")
            else:
                result = out
            samples.append(time.perf_counter() - t0)
    finally:
        if enabled:
            gc.enable()
    return Timed(first, summarise(samples), result, error, repeat_errors)
