"""The cascade quadrature compiled (``cascade_kernel.c``): all of it for piecewise-constant
rates, the heavy steps for general inputs.

Why
---
:func:`optimizer.cascade.integrate_cascade` with ``constant_pieces=True`` replays every
actuator schedule a plan hands out. Its numpy code makes about a hundred small array operations
per call (12 panels of 12 nodes for a 3-joint plan): ~1 ms, of a ~10 ms plan. The same
algorithm in C, step for step (the same panels, refinement decisions, error estimate, samples
and singularity test), takes a few tens of microseconds. For general inputs (the linear forms'
replays, a few hundred panels) the numpy code keeps the refinement loop and the inputs'
evaluations; each round's cascade and the final samples are computed here.

How
---
The C source is compiled by :mod:`optimizer.native` (cached on disk by the hash of its source,
once :func:`optimizer.native.configure` has been given a directory) when :func:`prepare` asks
for it, and loaded with :mod:`ctypes` once it is in the cache; a process that never calls
:func:`prepare` keeps the numpy code (its numbers differ in the last bits). Until then, when
compiled functions are off, or when no compiler exists, the functions here return None and the
numpy code answers: both give the same results to rounding (``tests/test_cascade_kernel.py``). The
quadrature rule and the model are passed from Python, so that one definition of every matrix
serves both.
"""

from __future__ import annotations

import ctypes
import math
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from . import native

#: The kernel's source, next to this module.
SOURCE_PATH = Path(__file__).with_name("cascade_kernel.c")
#: Entry points of the library: the whole quadrature of constant pieces; one cascade on a
#: mesh and the outputs of a finished run (general inputs, refined by the numpy code).
ENTRY = "cascade_constant_pieces"
GENERAL_PASS = "cascade_general_pass"
GENERAL_OUTPUTS = "cascade_general_outputs"
#: Largest number of Chebyshev nodes per panel the kernel takes (its stack buffers hold
#: ``nodes + 2`` values and 64 coefficients).
MAX_NODES = 62
_STATUS_NONFINITE = 1
_STATUS_CAPACITY = 3


class KernelRun(NamedTuple):
    """What the kernel computed (the caller builds the :class:`~optimizer.integration.Replay`).

    Attributes
    ----------
    status : str
        ``"ok"`` or ``"nonfinite"`` (a state or the energy is not finite).
    q : ndarray (M, n+1)
        States at the samples.
    energy, estimate : float
    singular_time : float or None
        First node, panel end or sample time where a joint ``th_1..th_{n-1}`` is outside
        ``(0, pi/2)``.
    panels, rounds, evaluations : int
    bounded : bool
        The refinement stopped at ``max_rounds`` / ``max_panels`` with panels still marked.
    mesh_t, mesh_q : ndarray
        Every panel's start and nodes, then ``T``; the states there.
    """

    status: str
    q: np.ndarray
    energy: float
    estimate: float
    singular_time: float | None
    panels: int
    rounds: int
    bounded: bool
    evaluations: int
    mesh_t: np.ndarray
    mesh_q: np.ndarray


class _Loaded:
    """The library of the current native configuration (loaded once it is built)."""

    def __init__(self) -> None:
        self.prepared = False   # :func:`prepare` was called in this process
        self.config: native.NativeConfig | None = None
        self.library: native.Library | None = None
        self.function: Callable[..., int] | None = None       # the constant pieces
        self.general_pass: Callable[..., int] | None = None   # the general case's steps
        self.general_outputs: Callable[..., int] | None = None


_state = _Loaded()


def source() -> str | None:
    """The kernel's C source (None if it is missing from the installation)."""
    try:
        return SOURCE_PATH.read_text()
    except OSError:
        return None


def prepare(wait: bool = True) -> bool:
    """Build the kernel (``wait``: now; else in the background, as the NLPs' libraries are)
    unless it is in the cache already, and load it when it is ready.

    Until this is called in a process the quadrature is the numpy code's alone, even with
    the library in the cache (its numbers differ from numpy's in the last bits: a process
    opts in). Nothing else builds it (a plan never starts a compiler of its own). Call this
    where the NLPs are prepared (a service worker's start, an image build, a benchmark's
    preparation); under a later :func:`optimizer.native.configure` the library is looked
    for again (not built).

    Returns
    -------
    bool
        Whether the compiled kernel is in use (False: compiled functions are off, no
        compiler, the build failed, or it is still running).
    """
    _state.prepared = True
    return _function(build=True, wait=wait, every=0.0) is not None


def _function(build: bool = False, wait: bool = False,
              every: float = 1.0) -> Callable[..., int] | None:
    cfg = native.config()
    st = _state
    if cfg is None or not st.prepared:
        return None
    if st.config is not cfg or (build and st.function is None):
        # a new configuration, or a build asked for: look the library up again
        st.config, st.library, st.function = cfg, None, None
        src = source()
        if src is None:
            return None
        st.library = (native.library_for(src, wait=wait) if build else
                      native.Library(native.library_key(src, cfg), cfg))
    if st.function is not None:
        return st.function
    if st.library is None:
        return None
    path = st.library.ready(every)  # (it refuses a library others may write)
    if path is None:
        return None
    try:
        lib = ctypes.CDLL(str(path))
        fns = [getattr(lib, name) for name in (ENTRY, GENERAL_PASS, GENERAL_OUTPUTS)]
    except (OSError, AttributeError):
        st.library = None
        return None
    for fn, args in zip(fns, (3, 4, 5)):
        fn.restype = ctypes.c_int
        fn.argtypes = [ctypes.c_void_p] * args
    st.general_pass, st.general_outputs = fns[1], fns[2]
    st.function = fns[0]
    return st.function


def ready() -> bool:
    """Whether :func:`run` will use the compiled kernel: :func:`prepare` was called in this
    process and the library is loaded, or found in the cache (looked for at most once a
    second; nothing is built)."""
    return _function() is not None


def run(gains: np.ndarray, exponents: np.ndarray, q0: np.ndarray, T: float, t_eval: np.ndarray,
        a0: np.ndarray, h0: np.ndarray, rates0: np.ndarray, rule: np.ndarray, nodes: int,
        split: int, *, tol: float, half_pi: float,
        plateau: float, noise: float, tail: int, max_rounds: int, max_panels: int
        ) -> KernelRun | None:
    """Run the compiled kernel; None when it is not available (the caller's numpy code then
    answers).

    Parameters
    ----------
    gains, exponents : ndarray (n-1,)
    q0 : ndarray (n+1,)
    T : float
    t_eval : ndarray (M,)
    a0, h0 : ndarray (P0,)
        Initial panels, in time order.
    rates0 : ndarray (P0, 2)
        The rates on each (finite).
    rule : ndarray
        ``x, cum_total, to_coef, xb, wb`` of the Chebyshev rule and how a refined panel is
        cut (relative starts and widths of its ``split`` children), flattened and
        concatenated (:func:`pack_rule`).
    nodes : int
    split : int
        Children of a refined panel.
    tol, half_pi, plateau, noise, tail, max_rounds, max_panels
        As in :func:`optimizer.cascade.integrate_cascade`.
    """
    fn = _function()
    if fn is None or nodes > MAX_NODES:
        return None
    n = int(gains.size) + 1
    nq = n + 1
    P0 = int(a0.size)
    M = int(t_eval.size)
    # the outputs for the usual case (little refinement); run again if the mesh needs more
    capacity = min(max(int(max_panels), P0), 4 * P0 + 64)
    head = [n, nodes, P0, split, max_rounds, max_panels, tail, M, capacity,
            tol, half_pi, plateau, noise, T]
    din = np.concatenate([head, gains, exponents, q0, a0, h0, rates0.T.ravel(), t_eval])
    rule_at = _address(rule)
    while True:
        rows = capacity * (nodes + 1) + 1
        dout = np.empty(7 + M * nq + rows * (1 + nq))
        status = fn(_address(din), rule_at, _address(dout))
        if status != _STATUS_CAPACITY:
            break
        capacity = int(dout[0])
        din[8] = capacity
    if status not in (0, _STATUS_NONFINITE):
        return None  # out of memory: the numpy code tries
    P, rounds, bounded, evaluations, energy, estimate, sing = dout[:7].tolist()
    used = int(P) * (nodes + 1) + 1
    mesh = 7 + M * nq
    return KernelRun("ok" if status == 0 else "nonfinite", dout[7:mesh].reshape(M, nq), energy,
                     estimate, None if math.isnan(sing) else sing, int(P), int(rounds),
                     bounded != 0.0, int(evaluations), dout[mesh:mesh + used],
                     dout[mesh + rows:mesh + rows + used * nq].reshape(used, nq))


def _address(arr: np.ndarray) -> int:
    """The address of a C-contiguous float array's data (a third of ``arr.ctypes.data``'s
    time, which builds a helper object; that only for a read-only array)."""
    if not arr.flags.writeable:
        return int(arr.ctypes.data)
    return ctypes.addressof(ctypes.c_char.from_buffer(arr))  # type: ignore[arg-type]


def pack_rule(x: np.ndarray, cum_total: np.ndarray, to_coef: np.ndarray, xb: np.ndarray,
              wb: np.ndarray, cut_starts: np.ndarray, cut_widths: np.ndarray) -> np.ndarray:
    """The rule's arrays and the cut of a refined panel in the kernel's layout (one
    contiguous vector)."""
    return np.concatenate([x, cum_total.ravel(), to_coef.ravel(), xb, wb, cut_starts,
                           cut_widths]).astype(float)


class GeneralPass(NamedTuple):
    """One cascade on a mesh (:func:`general_pass`).

    Attributes
    ----------
    energy : float
    lam : ndarray (n-1,)
        ``Lambda_2..Lambda_n``.
    X : ndarray (n+1, P, p)
        States at the nodes.
    ends : ndarray (n+1, P+1)
        States at the panel ends.
    err : ndarray (n-1, P)
        Tails of the joints' integrands ``th_2'..th_n'``.
    coef : ndarray (n-1, P, p)
        Their Chebyshev coefficients' magnitudes.
    """

    energy: float
    lam: np.ndarray
    X: np.ndarray
    ends: np.ndarray
    err: np.ndarray
    coef: np.ndarray


def general_pass(gains: np.ndarray, exponents: np.ndarray, q0: np.ndarray, h: np.ndarray,
                 U: np.ndarray, rule: np.ndarray, nodes: int, tail: int) -> GeneralPass | None:
    """The cascade on a mesh in time order with inputs ``U`` (2, P, p) at its nodes; None
    when the kernel is not loaded."""
    fn = _state.general_pass
    if fn is None or _state.config is not native.config() or nodes > MAX_NODES:
        return None
    n = int(gains.size) + 1
    nq = n + 1
    P = int(h.size)
    Pp = P * nodes
    din = np.concatenate([(n, nodes, P, tail), gains, exponents, q0, h])
    Uc = np.ascontiguousarray(U, dtype=float)
    size = 1 + (n - 1) + nq * Pp + nq * (P + 1) + (n - 1) * P + (n - 1) * Pp
    dout = np.empty(size)
    if fn(_address(din), _address(rule), _address(Uc), _address(dout)) != 0:
        return None
    at = 1 + (n - 1)
    X = dout[at:at + nq * Pp].reshape(nq, P, nodes)
    at += nq * Pp
    ends = dout[at:at + nq * (P + 1)].reshape(nq, P + 1)
    at += nq * (P + 1)
    err = dout[at:at + (n - 1) * P].reshape(n - 1, P)
    at += (n - 1) * P
    return GeneralPass(float(dout[0]), dout[1:n], X, ends, err,
                       dout[at:].reshape(n - 1, P, nodes))


def general_outputs(a: np.ndarray, h: np.ndarray, X: np.ndarray, ends: np.ndarray, T: float,
                    half_pi: float, t_eval: np.ndarray, rule: np.ndarray, nodes: int
                    ) -> tuple[float | None, np.ndarray, np.ndarray, np.ndarray] | None:
    """Samples at ``t_eval``, the first singular time, ``mesh_t`` and ``mesh_q`` of a finished
    run (panels ``a, h`` in time order, ``X``, ``ends`` as :func:`general_pass` gives them);
    None when the kernel is not loaded."""
    fn = _state.general_outputs
    if fn is None or _state.config is not native.config() or nodes > MAX_NODES:
        return None
    nq = int(X.shape[0])
    P = int(a.size)
    M = int(t_eval.size)
    rows = P * (nodes + 1) + 1
    din = np.concatenate([(nq - 1, nodes, P, M, T, half_pi), a, h, t_eval])
    Xc = np.ascontiguousarray(X, dtype=float)
    Ec = np.ascontiguousarray(ends, dtype=float)
    dout = np.empty(1 + M * nq + rows * (1 + nq))
    if fn(_address(din), _address(rule), _address(Xc), _address(Ec),
          _address(dout)) != 0:
        return None
    sing = float(dout[0])
    at = 1 + M * nq
    return (None if math.isnan(sing) else sing, dout[1:at].reshape(M, nq),
            dout[at:at + rows], dout[at + rows:].reshape(rows, nq))
