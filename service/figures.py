"""Figures of plans, sweeps and robustness runs, rendered to PNG or SVG bytes.

Every function takes the JSON dicts the library and the service produce (``Plan.to_dict()``,
``optimizer.analysis.sweep``, ``optimizer.analysis.robustness``), so the service renders from the
data it returns and the CLI (:mod:`service.figures_cli`) from a saved response.

Angles are stored in radians and drawn in degrees (human-facing); chained states are drawn as they
are. Matplotlib is used through :class:`matplotlib.figure.Figure` objects only (no pyplot, no GUI
backend, no global figure registry); rendering holds a module lock because ``rcParams`` (read by
the SVG writer) is process-global, so the module is safe in threads and in worker processes.

Figures (after the paper's):

``joint_angles``
    th1..thn and phi against time with dashed straight references (Figs 6, 7, 9).
``chained_state``
    z2..z_{n+1} against time with the regions where the inverse transform does not exist shaded
    and the constraint points marked (Figs 4, 5).
``robustness``
    Nominal th(t) against open-loop runs from perturbed starts (Figs 11, 14).
``sweep``
    d_a, t_p and ||J_R(T)||_F against dphi with the singularity-free intervals shaded (Fig 12 and
    the paper's b0 map).
``pareto``
    The trade-off of a ``pareto: true`` answer: each member's deviation (deg) against its
    actuator reversals, the main plan starred (issue 26; not in the paper).
"""

from __future__ import annotations

import io
import math
import threading
import time
from typing import Any, Callable, Iterable, Mapping, Sequence

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import MaxNLocator

from .formats import FORMATS, KINDS

__all__ = ["FORMATS", "KINDS", "joint_angles", "chained_state", "robustness", "sweep", "pareto",
           "render"]


#: Width of every figure (inches) and PNG resolution: 9 in x 100 dpi = 900 px.
WIDTH = 9.0
DPI = 100
#: Longest series drawn (longer ones are thinned evenly, keeping both ends).
MAX_POINTS = 2000

_RC: dict[str, Any] = {
    "svg.fonttype": "none",          # keep text as <text> in SVG (searchable, testable)
    "svg.hashsalt": "chained-planner",  # deterministic SVG ids
    "font.size": 10.0,
    "axes.titlesize": 10.5,
    "axes.labelsize": 10.0,
    "legend.fontsize": 9.0,
    "xtick.labelsize": 9.0,
    "ytick.labelsize": 9.0,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "grid.linewidth": 0.6,
    "lines.linewidth": 1.6,
    "figure.facecolor": "white",
    "savefig.facecolor": "white",
}
_LOCK = threading.RLock()
#: Whether :func:`warm_up` has run in this process (or in the parent it was forked from).
_WARM = False

_FORBIDDEN: dict[str, Any] = dict(color="tab:red", alpha=0.12, lw=0, zorder=0)
_FEASIBLE: dict[str, Any] = dict(color="tab:green", alpha=0.15, lw=0, zorder=0)
_GREEK = {"phi": "\u03c6", "theta": "\u03b8"}
DEG = "\u00b0"


# ------------------------------------------------------------------ helpers
def _deg(x: Any) -> np.ndarray:
    return np.degrees(np.asarray(x, dtype=float))


def _fmt_num(x: Any, spec: str = ".3f", unit: str = "") -> str:
    if x is None:
        return "n/a"
    try:
        xf = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(xf):
        return "n/a"
    return f"{xf:{spec}}{unit}"


def _fdeg(x: Any, spec: str = ".3f") -> str:
    """Radians -> formatted degrees (``n/a`` for None / non-finite)."""
    return _fmt_num(None if x is None else _deg(x), spec, DEG)


def _array(obj: Any, what: str, ndim: int) -> np.ndarray:
    """A float array (``None`` -> NaN) of the given rank, or ValueError."""
    try:
        arr = np.array(obj, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be a numeric array") from exc
    if arr.ndim != ndim or arr.shape[0] == 0:
        raise ValueError(f"{what} must be a non-empty {ndim}-D array, got shape {arr.shape}")
    return arr


def _thin(n: int) -> np.ndarray:
    """Indices of at most MAX_POINTS evenly spaced samples out of n, both ends included."""
    if n <= MAX_POINTS:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, MAX_POINTS).round().astype(int))


def _unwrap_plan(data: Mapping[str, Any]) -> Mapping[str, Any]:
    """A plan dict, accepting ``{"plan": {...}}`` wrappers."""
    if not isinstance(data, Mapping):
        raise ValueError("a plan must be a JSON object")
    if "path" not in data and isinstance(data.get("plan"), Mapping):
        data = data["plan"]
    if data.get("status", "success") != "success":
        raise ValueError(f"the plan has status {data.get('status')!r}: only successful plans "
                         "can be drawn")
    if not isinstance(data.get("path"), Mapping):
        raise ValueError("the plan has no 'path' (t, q, z): pass a plan response")
    return data


class _PlanData:
    """The parts of a plan dict the figures use, checked."""

    def __init__(self, plan: Mapping[str, Any]) -> None:
        plan = _unwrap_plan(plan)
        self.raw = plan
        path = plan["path"]
        self.t = _array(path.get("t"), "path.t", 1)
        self.q = _array(path.get("q"), "path.q", 2)
        if self.q.shape[0] != self.t.size:
            raise ValueError(f"path.q has {self.q.shape[0]} rows but path.t has {self.t.size}")
        robot = plan.get("robot") or {}
        self.n = int(robot.get("n", self.q.shape[1] - 1))
        if self.q.shape[1] != self.n + 1:
            raise ValueError(f"path.q rows must have n + 1 = {self.n + 1} entries "
                             "[phi, th1..thn]")
        self.gains = [float(k) for k in robot.get("gains", [])]
        z = path.get("z")
        self.z = _array(z, "path.z", 2) if z is not None else None
        if self.z is not None and self.z.shape != self.q.shape:
            raise ValueError(f"path.z has shape {self.z.shape}, expected {self.q.shape}")
        self.method = str(plan.get("method", "plan"))
        # how path.u is executed (docs/execution.md); path.q are that execution's states
        self.rule = path.get("rule")
        self.phi_change = plan.get("phi_change")
        if self.phi_change is None:
            self.phi_change = float(self.q[-1, 0] - self.q[0, 0])
        self.duration = plan.get("duration")
        if self.duration is None:
            self.duration = float(self.t[-1] - self.t[0])
        ind = plan.get("indicators") or {}
        self.d_a = ind.get("d_a")
        self.t_p = ind.get("t_p")
        # the exact plan's d_a on its own schedule (the paper's number), when the answer has
        # it: the drawn path runs along the time law, whose d_a is self.d_a
        self.plan_d_a = (plan.get("plan_indicators") or {}).get("d_a")
        self.breaks = self._breaks(plan)
        u = path.get("u")
        self.u = _array(u, "path.u", 2) if u is not None else None
        if self.u is not None and self.u.shape != (self.t.size, 2):
            raise ValueError(f"path.u has shape {self.u.shape}, expected ({self.t.size}, 2)")
        self.limits = dict((plan.get("time_law") or {}).get("limits") or {})

    @staticmethod
    def _breaks(plan: Mapping[str, Any]) -> list[float]:
        """Interior stops of the handed-out path's time law (s), or, for a plan without one,
        its segment boundaries."""
        law = plan.get("time_law") or {}
        if law.get("stops"):
            return [float(x) for x in law["stops"][1:-1]]
        segs = ((plan.get("coefficients") or {}).get("segments")) or []
        out = []
        for s in segs[1:]:
            try:
                out.append(float(s["t_start"]))
            except (KeyError, TypeError, ValueError):
                pass
        return out

    def title(self) -> str:
        return (f"{self.method} plan: dphi = {_fdeg(self.phi_change)}, "
                f"d_a = {_fdeg(self.d_a)}"
                + (f" (plan {math.degrees(self.plan_d_a):.2f}°)" if self.plan_d_a is not None
                   else "")
                + ", "
                f"t_p = {self.t_p if self.t_p is not None else 'n/a'}, "
                f"T = {_fmt_num(self.duration, '.4g', ' s')}"
                + (f", executed ({self.rule})" if self.rule else ""))


def _mark_breaks(ax: Any, breaks: Iterable[float]) -> None:
    for b in breaks:
        ax.axvline(b, color="0.5", lw=0.8, ls=":", zorder=1)


def _new_figure(height: float, nrows: int, sharex: bool = True,
                height_ratios: Sequence[float] | None = None) -> tuple[Figure, list[Any]]:
    fig = Figure(figsize=(WIDTH, height), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)  # Agg raster canvas (no GUI); SVG output switches canvas on save
    axes = fig.subplots(nrows, 1, sharex=sharex, squeeze=False,
                        gridspec_kw={"height_ratios": list(height_ratios)}
                        if height_ratios else None)[:, 0]
    return fig, list(axes)


def _legend_right(ax: Any, handles: Sequence[Any] | None = None, **kw: Any) -> None:
    """Legend outside the axes, on the right (never over the curves)."""
    kwargs = dict(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
                  frameon=False, handlelength=2.2)
    kwargs.update(kw)
    if handles is not None:
        ax.legend(handles=handles, **kwargs)
    else:
        ax.legend(**kwargs)


def _save(fig: Figure, fmt: str) -> bytes:
    buf = io.BytesIO()
    meta: dict[str, Any] = {"Software": None} if fmt == "png" else {"Date": None}
    fig.savefig(buf, format=fmt, dpi=DPI, metadata=meta)
    return buf.getvalue()


def _check_fmt(fmt: str) -> str:
    f = str(fmt).lower().lstrip(".")
    if f not in FORMATS:
        raise ValueError(f"unknown figure format {fmt!r}: use one of {sorted(FORMATS)}")
    return f


def render_figure(build: Callable[[], Figure], fmt: str) -> bytes:
    """The figure ``build()`` makes, drawn in the service's style (its rc settings, one figure
    at a time: matplotlib's state is global) and saved as ``fmt`` (``png`` or ``svg``).

    Every figure of this module is drawn through it; :mod:`service.figures_study` too."""
    f = _check_fmt(fmt)
    with _LOCK, matplotlib.rc_context(_RC):  # type: ignore[arg-type]
        fig = build()
        return _save(fig, f)


def warm_up() -> float:
    """Load what a process's first figure would otherwise load inside its drawing allowance.

    Importing this module imports matplotlib; this draws one small figure (a title, a legend,
    degree and Greek labels) as PNG and as SVG, which loads the font list and the font, the
    layout engine and both writers. The worker pool's forkserver calls it at start
    (:func:`service.jobs.warm_up`), so every worker forked from it, replacements included,
    starts with all of it loaded, and a figure's allowance
    (``service.routers.figures.RENDER_SECONDS``) is spent on drawing. A second call in the
    process (or in a child forked after the first) does nothing.

    Returns
    -------
    float
        CPU seconds this call took (0.0 when the process was warm already).
    """
    global _WARM
    if _WARM:
        return 0.0
    t0 = time.process_time()

    def build() -> Figure:
        fig, (ax,) = _new_figure(2.0, 1)
        ax.plot([0.0, 1.0], [0.0, 1.0], label=f"{_GREEK['theta']}1")
        ax.set_title(f"warm-up: {_GREEK['phi']} ({DEG})")
        ax.set_xlabel("t (s)")
        _legend_right(ax)
        return fig

    for fmt in FORMATS:
        render_figure(build, fmt)
    _WARM = True
    return time.process_time() - t0


# ------------------------------------------------------------------ figures
def joint_angles(plan: Mapping[str, Any], fmt: str = "png") -> bytes:
    """Joint angles th1..thn (top) and phi (bottom) against time, in degrees.

    Dashed lines: the straight references from start to goal (the lines ``d_a`` measures against).
    The title gives the method, ``dphi``, ``d_a`` (joint 1), ``t_p`` and ``T``.
    """
    p = _PlanData(plan)

    def build() -> Figure:
        rates = p.u is not None
        fig, axes = _new_figure(8.0 if rates else 6.4, 3 if rates else 2,
                                height_ratios=(2.6, 1.0, 1.2) if rates else (2.6, 1.0))
        ax, axp = axes[0], axes[1]
        idx = _thin(p.t.size)
        t = p.t[idx]
        q = _deg(p.q[idx])
        t0, t1 = p.t[0], p.t[-1]
        colors = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
        handles = []
        for j in range(1, p.n + 1):
            c = colors[(j - 1) % len(colors)]
            ax.plot(t, q[:, j], color=c)
            ax.plot([t0, t1], [q[0, j], q[-1, j]], color=c, ls="--", lw=1.0, alpha=0.75)
            handles.append(Line2D([], [], color=c, label=f"{_GREEK['theta']}{j} (th{j})"))
        handles.append(Line2D([], [], color="0.3", ls="--", lw=1.0,
                              label="straight reference\nstart \u2192 goal"))
        ax.set_ylabel("joint angle [deg]")
        ax.set_title(p.title())
        _legend_right(ax, handles)
        c = "0.15"
        axp.plot(t, q[:, 0], color=c)
        axp.plot([t0, t1], [q[0, 0], q[-1, 0]], color=c, ls="--", lw=1.0, alpha=0.6)
        axp.set_ylabel("phi [deg]")
        _legend_right(axp, [Line2D([], [], color=c, label=f"{_GREEK['phi']} (phi, actuator)"),
                            Line2D([], [], color=c, ls="--", lw=1.0, alpha=0.6,
                                   label="straight reference")])
        if rates:
            _rates_panel(axes[2], p)
        axes[-1].set_xlabel("time t [s]")
        for a in axes:
            _mark_breaks(a, p.breaks)
        axp.set_xlim(t0, t1)
        return fig

    return render_figure(build, fmt)


def _rates_panel(ax: Any, p: "_PlanData") -> None:
    """The handed-out rates u1 = phi', u2 = th1' against time, by their rule, with the
    limits of the rates (dotted) when the plan keeps some."""
    assert p.u is not None
    colors = ("0.15", "tab:red")
    handles = []
    step = p.rule == "zoh"
    for c, (name, col) in enumerate(zip(("u1 = phi'", "u2 = th1'"), colors)):
        if step:
            ax.step(p.t, p.u[:, c], where="post", color=col)
        else:
            ax.plot(p.t, p.u[:, c], color=col)
        handles.append(Line2D([], [], color=col, label=name))
        lim = p.limits.get(f"max_u{c + 1}")
        if lim is not None:
            for sgn in (1.0, -1.0):
                ax.axhline(sgn * float(lim), color=col, ls=":", lw=1.0)
            handles.append(Line2D([], [], color=col, ls=":", lw=1.0,
                                  label=f"max_u{c + 1} = {float(lim):.3g}"))
    ax.set_ylabel("rates [rad/s]")
    _legend_right(ax, handles)


def _constraint_points(plan: Mapping[str, Any], given: Any) -> list[tuple[float, int, float]]:
    pts = given
    if pts is None:
        pts = plan.get("constraint_points")
        if pts is None:
            pts = (plan.get("request") or {}).get("constraint_points") \
                if isinstance(plan.get("request"), Mapping) else None
    out = []
    for i, cp in enumerate(pts or []):
        try:
            if isinstance(cp, Mapping):
                out.append((float(cp["time"]), int(cp["state"]), float(cp["value"])))
            else:
                out.append((float(cp.time), int(cp.state), float(cp.value)))
        except (KeyError, AttributeError, TypeError, ValueError) as exc:
            raise ValueError(f"constraint_points[{i}] must have time, state and value") from exc
    return out


def chained_state(plan: Mapping[str, Any], fmt: str = "png",
                  constraint_points: Sequence[Any] | None = None) -> bytes:
    """Chained states z2..z_{n+1} against time, one axes each (Figs 4, 5).

    Shaded red: where the inverse transform does not exist: ``z2 >= 0`` (eq 13) and, for
    ``z_n = K_n cos(th_{n-1})^m_n``, outside ``(0, K_n)`` (z3 for the 3-joint arm). Constraint
    points (``{time, state, value}``, state 2..n+1; default: the plan's ``constraint_points`` if
    it carries them) are marked.
    """
    if (constraint_points is None and isinstance(plan, Mapping) and "path" not in plan
            and plan.get("constraint_points") is not None):
        constraint_points = plan["constraint_points"]   # {"plan": ..., "constraint_points": ...}
    p = _PlanData(plan)
    if p.z is None:
        raise ValueError("the plan has no path.z")
    zpath: np.ndarray = p.z
    cps = _constraint_points(p.raw, constraint_points)
    for time_, state, _ in cps:
        if not 2 <= state <= p.n + 1:
            raise ValueError(f"constraint point state {state} must lie in 2..{p.n + 1}")
    k_n = p.gains[-1] if len(p.gains) == p.n - 1 else None

    def build() -> Figure:
        nax = p.n
        fig, axes = _new_figure(1.2 + 1.55 * nax, nax)
        idx = _thin(p.t.size)
        t = p.t[idx]
        z = zpath[idx]
        colors = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
        forbidden_shown = False
        for k, ax in zip(range(2, p.n + 2), axes):
            y = z[:, k - 1]
            c = colors[(k - 2) % len(colors)]
            ax.plot(t, y, color=c)
            ax.plot([t[0], t[-1]], [y[0], y[-1]], "o", color=c, ms=4, zorder=3, clip_on=False)
            ylab = f"z{k} [-]" if k <= p.n else f"z{k} = th{p.n} [rad]"
            ax.set_ylabel(ylab)
            lo, hi = float(np.nanmin(y)), float(np.nanmax(y))
            bands: list[tuple[float, float]] = []
            if k == 2:
                hi = max(hi, 0.0)
                bands.append((0.0, math.inf))
            if k == p.n and k_n is not None:
                lo, hi = min(lo, 0.0), max(hi, k_n)
                bands += [(-math.inf, 0.0), (k_n, math.inf)]
            for time_, state, val in cps:
                if state == k:
                    lo, hi = min(lo, val), max(hi, val)
            span = hi - lo if hi > lo else max(abs(hi), 1.0)
            ylo, yhi = lo - 0.08 * span, hi + 0.08 * span
            if k == 2:
                yhi = max(yhi, 0.2 * span)   # show a visible strip of the forbidden band
            for a, b in bands:
                ax.axhspan(max(a, ylo), min(b, yhi), **_FORBIDDEN)
                ax.axhline(a if math.isfinite(a) else b, color="tab:red", lw=0.8, alpha=0.6,
                           zorder=1)
                forbidden_shown = True
            ax.set_ylim(ylo, yhi)
            for time_, state, val in cps:
                if state == k:
                    ax.plot([time_], [val], marker="D", color="black", mfc="gold", ms=7,
                            zorder=4, ls="none")
            _mark_breaks(ax, p.breaks)
        axes[-1].set_xlabel("time t [s]")
        axes[-1].set_xlim(p.t[0], p.t[-1])
        # two lines: in one, the plan's title ran past the figure's edges (clipped)
        axes[0].set_title("Chained-form state z(t)\n" + p.title())
        handles: list[Any] = [Line2D([], [], color="0.3", ls="none", marker="o", ms=4,
                                     label="start / goal")]
        if forbidden_shown:
            rule = "z2 \u2265 0"
            if k_n is not None:
                rule += f",\nz{p.n} \u2264 0 or z{p.n} \u2265 K{p.n} = {_fmt_num(k_n, '.4g')}"
            handles.append(Patch(label=f"no inverse transform\n(singular): {rule}", **{
                k: v for k, v in _FORBIDDEN.items() if k != "zorder"}))
        if cps:
            handles.append(Line2D([], [], marker="D", color="black", mfc="gold", ms=7,
                                  ls="none", label="constraint point"))
        _legend_right(axes[0], handles)
        return fig

    return render_figure(build, fmt)


def robustness(plan: Mapping[str, Any], robustness: Mapping[str, Any], fmt: str = "png") -> bytes:
    """Nominal th_i(t) against open-loop runs from perturbed starts, one axes per joint (deg).

    ``robustness`` is the dict of :func:`optimizer.analysis.robustness`; each run's ``path_q`` has
    rows ``[phi, th1..thn]`` at the plan's ``path.t``. Runs that hit a singularity are drawn red
    up to ``singular_time`` and end in a cross.
    """
    p = _PlanData(plan)
    if not isinstance(robustness, Mapping) or not isinstance(robustness.get("runs"), list):
        raise ValueError("robustness must be an object with a 'runs' list")
    runs = []
    for i, r in enumerate(robustness["runs"]):
        if not isinstance(r, Mapping) or r.get("path_q") is None:
            raise ValueError(f"robustness.runs[{i}] has no path_q")
        q = _array(r["path_q"], f"runs[{i}].path_q", 2)
        if q.shape[1] != p.n + 1:
            raise ValueError(f"runs[{i}].path_q rows must have n + 1 = {p.n + 1} entries")
        t = p.t if q.shape[0] == p.t.size else np.linspace(p.t[0], p.t[-1], q.shape[0])
        st = r.get("singular_time")
        singular = bool(r.get("singular"))
        if singular and st is not None:
            keep = t <= float(st) + 1e-12
            keep[0] = True
            t, q = t[keep], q[keep]
        runs.append((t, _deg(q), singular))
    summary = robustness.get("summary") or {}
    # the closed-loop mode: each start on a plant with gains off, open and closed loop
    loops: list[tuple[np.ndarray, np.ndarray, str]] = []
    loop = robustness.get("closed_loop")
    if isinstance(loop, Mapping):
        for i, r in enumerate(loop.get("runs") or []):
            for side in ("open", "closed"):
                run = r.get(side) if isinstance(r, Mapping) else None
                if isinstance(run, Mapping) and run.get("path_q") is not None:
                    loops.append((_array(run["path_t"], f"closed_loop.runs[{i}].{side}.path_t",
                                         1),
                                  _deg(_array(run["path_q"],
                                              f"closed_loop.runs[{i}].{side}.path_q", 2)),
                                  side))

    def build() -> Figure:
        fig, axes = _new_figure(1.5 + 1.9 * p.n, p.n)
        idx = _thin(p.t.size)
        tn, qn = p.t[idx], _deg(p.q[idx])
        alpha = 0.75 if len(runs) <= 10 else max(0.15, 7.5 / len(runs))
        for j, ax in zip(range(1, p.n + 1), axes):
            for t, q, singular in runs:
                ii = _thin(t.size)
                ax.plot(t[ii], q[ii, j], color="tab:red" if singular else "tab:orange",
                        lw=0.9, alpha=alpha, zorder=2)
                if singular:
                    ax.plot([t[-1]], [q[-1, j]], "x", color="tab:red", ms=7, mew=1.8, zorder=4)
            for t, q, side in loops:
                ax.plot(t, q[:, j], color="tab:purple" if side == "open" else "tab:green",
                        lw=0.9, alpha=0.8, ls=":" if side == "open" else "-", zorder=2)
            ax.plot([tn[0], tn[-1]], [qn[0, j], qn[-1, j]], color="0.35", ls="--", lw=1.0,
                    zorder=2)
            ax.plot(tn, qn[:, j], color="black", lw=2.0, zorder=3)
            ax.plot([tn[-1]], [qn[-1, j]], marker="*", color="tab:blue", ms=11, zorder=5,
                    ls="none", clip_on=False)
            ax.set_ylabel(f"{_GREEK['theta']}{j} (th{j})")
            _mark_breaks(ax, p.breaks)
        axes[-1].set_xlabel("time t [s]")
        axes[-1].set_xlim(p.t[0], p.t[-1])
        fig.supylabel("joint angle [deg]", fontsize=10)
        n_sing = sum(1 for r in runs if r[2])
        mode = summary.get("replay")
        replay = {"u": "u-replay (motors run the handed-out u1, u2 by their rule)",
                  "v": "v-replay (chained inputs v1, v2)"}.get(str(mode), "open-loop replay")
        e_max = summary.get("terminal_error_max")
        da_max = summary.get("d_a_max")
        line1 = (f"Perturbed starts: {len(runs)} runs, {replay}" +
                 (f", {n_sing} singular" if n_sing else ""))
        line2 = (f"max terminal error = {_fdeg(e_max)}, "
                 f"d_a max = {_fdeg(da_max)} "
                 f"(nominal {_fdeg(p.d_a)}), "
                 f"t_p max = {summary.get('t_p_max', 'n/a')} (nominal {p.t_p})")
        title = line1 + "\n" + line2
        if isinstance(loop, Mapping) and loop.get("summary"):
            ls = loop["summary"]
            title += (f"\nplant gains +-{100 * float(ls.get('gain_error', 0)):.3g} %: terminal "
                      f"error median open {_fdeg(ls['open']['terminal_error_median'])}, closed "
                      f"loop (replans every {ls.get('period')} s) "
                      f"{_fdeg(ls['closed']['terminal_error_median'])}")
        axes[0].set_title(title)
        handles = [Line2D([], [], color="black", lw=2.0, label="nominal plan"),
                   Line2D([], [], color="tab:orange", lw=0.9, label="perturbed start"),
                   Line2D([], [], color="0.35", ls="--", lw=1.0, label="straight reference"),
                   Line2D([], [], marker="*", color="tab:blue", ms=11, ls="none", label="goal")]
        if n_sing:
            handles.insert(2, Line2D([], [], color="tab:red", lw=0.9, marker="x", mew=1.8,
                                     label="singular run\n(stopped)"))
        if loops:
            handles += [Line2D([], [], color="tab:purple", lw=0.9, ls=":",
                               label="plant with gains off,\nopen loop"),
                        Line2D([], [], color="tab:green", lw=0.9,
                               label="same plant, closed\nloop (replans)")]
        _legend_right(axes[0], handles)
        return fig

    return render_figure(build, fmt)


def _intervals_from_flags(ds: np.ndarray, ok: np.ndarray) -> list[tuple[float, float]]:
    out = []
    i = 0
    while i < ds.size:
        if ok[i]:
            j = i
            while j + 1 < ds.size and ok[j + 1]:
                j += 1
            out.append((float(ds[i]), float(ds[j])))
            i = j + 1
        else:
            i += 1
    return out


def sweep(sweep: Mapping[str, Any], fmt: str = "png", planned: float | None = None) -> bytes:
    """d_a (deg), t_p and ||J_R(T)||_F against dphi (deg), three stacked axes sharing x.

    Shaded green: the singularity-free ``dphi`` intervals (``feasible_phi_changes``; from the
    ``feasible`` flags when those were not computed). The star marks the grid's best member by
    the paper's §4 rule (fewest t_p, then smallest d_a); ``planned`` (rad), a plan's dphi, is
    drawn as a dashed line.
    """
    if not isinstance(sweep, Mapping) or not isinstance(sweep.get("phi_change"),
                                                      (list, tuple, np.ndarray)):
        hint = (" (this looks like a plan response)" if isinstance(sweep, Mapping)
                and "path" in sweep else "")
        raise ValueError("a sweep must be an object with lists 'phi_change', 'd_a', 't_p', "
                         "'sensitivity'" + hint)
    ds = _array(sweep["phi_change"], "phi_change", 1)

    def series(key: str) -> np.ndarray:
        v = sweep.get(key)
        if v is None:
            return np.full(ds.size, np.nan)
        a = _array(v, key, 1)
        if a.size != ds.size:
            raise ValueError(f"{key} has {a.size} values but phi_change has {ds.size}")
        return a

    d_a, t_p, sens = series("d_a"), series("t_p"), series("sensitivity")
    flags = sweep.get("feasible")
    ok = (np.array([bool(x) for x in flags]) if flags is not None and len(flags) == ds.size
          else np.isfinite(d_a))
    iv = sweep.get("feasible_phi_changes")
    if iv is None:
        intervals = _intervals_from_flags(ds, ok)
    else:
        try:
            intervals = [(float(a), float(b)) for a, b in iv]
        except (TypeError, ValueError) as exc:
            raise ValueError("feasible_phi_changes must be a list of [lo, hi] pairs") from exc
    criterion = sweep.get("criterion")

    def build() -> Figure:
        fig, axes = _new_figure(7.2, 3, height_ratios=(1.4, 0.9, 1.1))
        ax_da, ax_tp, ax_s = axes
        x = _deg(ds)
        for ax in axes:
            for a, b in intervals:
                if a == b:
                    ax.axvline(math.degrees(a), color="tab:green", alpha=0.4, lw=2, zorder=0)
                else:
                    ax.axvspan(math.degrees(a), math.degrees(b), **_FEASIBLE)
        ms = 3.5 if ds.size <= 150 else (2.0 if ds.size <= 600 else 0.0)
        ax_da.plot(x, _deg(d_a), "o-", color="tab:blue", ms=ms)
        ax_da.set_ylabel("deviation d_a [deg]")
        ax_da.margins(y=0.12)
        ax_tp.plot(x, t_p, "s", color="tab:purple", ms=max(ms, 1.5))
        ax_tp.yaxis.set_major_locator(MaxNLocator(integer=True))
        if np.isfinite(t_p).any():
            ax_tp.set_ylim(min(-0.3, np.nanmin(t_p) - 0.5), np.nanmax(t_p) + 0.5)
        ax_tp.set_ylabel("reversals t_p [-]")
        ax_s.plot(x, sens, "-", color="0.5", lw=1.2)
        ax_s.plot(np.where(ok, x, np.nan), np.where(ok, sens, np.nan), "-", color="tab:red",
                  lw=2.0)
        ax_s.set_ylabel("sensitivity ||J_R(T)||_F [-]")
        ax_s.set_xlabel("phi change dphi [deg]   (= b0 \u00b7 T)")
        ax_s.set_xlim(x.min(), x.max())
        if planned is not None:
            for ax in axes:
                ax.axvline(math.degrees(planned), color="black", ls="--", lw=1.0, zorder=4)
        best = None
        if np.isfinite(t_p).any() and np.isfinite(d_a).any():
            cand = [i for i in range(ds.size) if np.isfinite(t_p[i]) and np.isfinite(d_a[i])]
            if cand:
                best = min(cand, key=lambda i: (t_p[i], d_a[i]))
                ax_da.plot([x[best]], [math.degrees(d_a[best])], "*", color="tab:orange",
                           ms=14, mec="black", mew=0.6, zorder=5, clip_on=False)
        if not ok.any() and not intervals:
            ax_da.text(0.5, 0.5, "no singularity-free dphi in this range",
                       transform=ax_da.transAxes, ha="center", va="center", color="tab:red")
        span = (f"{x.min():.2f}\u00b0 to {x.max():.2f}\u00b0, {ds.size} points")
        crit = f", {criterion} criterion" if criterion else ""
        feas = ", ".join(f"[{math.degrees(a):.3f}\u00b0, {math.degrees(b):.3f}\u00b0]"
                         for a, b in intervals) or "none"
        ax_da.set_title(f"Indicators against dphi ({span}{crit})\n"
                        f"singularity-free dphi: {feas}")
        handles = [Patch(label="singularity-free\ndphi interval",
                         **{k: v for k, v in _FEASIBLE.items() if k != "zorder"}),
                   Line2D([], [], color="tab:blue", marker="o", ms=3.5,
                          label="deviation d_a\n(of joint 1)")]
        if best is not None:
            handles.append(Line2D([], [], marker="*", color="tab:orange", mec="black", mew=0.6,
                                  ms=12, ls="none",
                                  label=f"best on grid (fewest\nt_p, then smallest d_a):\n"
                                        f"dphi = {x[best]:.2f}\u00b0, t_p = {int(t_p[best])}"))
        if planned is not None:
            handles.append(Line2D([], [], color="black", ls="--", lw=1.0,
                                  label=f"planned dphi =\n{math.degrees(planned):.2f}\u00b0"))
        _legend_right(ax_da, handles)
        _legend_right(ax_tp, [Line2D([], [], marker="s", color="tab:purple", ms=4, ls="none",
                                     label="t_p (reversals\nof joint 1)")])
        _legend_right(ax_s, [Line2D([], [], color="tab:red", lw=2.0,
                                    label="sensitivity ||J_R(T)||_F,\nsingularity-free"),
                             Line2D([], [], color="0.5", lw=1.2,
                                    label="sensitivity ||J_R(T)||_F,\nother dphi")])
        return fig

    return render_figure(build, fmt)


def pareto(plan: Mapping[str, Any], fmt: str = "png") -> bytes:
    """The members of a ``pareto: true`` answer: deviation (deg) against reversals (phi and th1
    together), each labelled with the ``max_reversals`` that asks for it, the main plan starred.
    """
    data = _unwrap_plan(plan)
    members = data.get("pareto")
    if not isinstance(members, list) or not members:
        raise ValueError("the plan has no 'pareto' members: ask for it with pareto: true")
    keys: list[tuple[int, float, bool]] = []
    for i, m in enumerate(members):
        try:
            ind = m["indicators"]
            rev = int(ind["reversals"]["phi"]) + int(ind["reversals"]["th1"])
            dev = math.degrees(float(ind["deviation"]))
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"pareto[{i}] has no indicators.reversals and "
                             "indicators.deviation") from None
        if not math.isfinite(dev):
            raise ValueError(f"pareto[{i}].indicators.deviation is not a finite number")
        keys.append((rev, dev, bool(m.get("chosen"))))

    def build() -> Figure:
        fig, (ax,) = _new_figure(4.2, 1)
        r = [k[0] for k in keys]
        d = [k[1] for k in keys]
        ax.step(r, d, where="post", color="0.6", lw=1.0, zorder=1)
        ax.plot(r, d, "o", color="tab:blue", zorder=2)
        handles = [Line2D([], [], color="tab:blue", marker="o", ls="",
                          label="verified plan\n(label: max_reversals)")]
        for rev, dev, chosen in keys:
            ax.annotate(str(rev), (rev, dev), textcoords="offset points", xytext=(4, 4),
                        fontsize=8)
            if chosen:
                ax.plot([rev], [dev], "*", color="tab:orange", ms=16, zorder=3)
        if any(k[2] for k in keys):
            handles.append(Line2D([], [], color="tab:orange", marker="*", ls="", ms=12,
                                  label="main plan"))
        ax.set_xlabel("actuator reversals (phi and th1) [-]")
        ax.set_ylabel("deviation from the straight segment [deg]")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(f"Reversals against deviation: {len(keys)} non-dominated plans, from "
                     f"{_fmt_num(keys[0][1], '.3g', DEG)} at {keys[0][0]} to "
                     f"{_fmt_num(keys[-1][1], '.3g', DEG)} at {keys[-1][0]}")
        _legend_right(ax, handles)
        return fig

    return render_figure(build, fmt)


# ------------------------------------------------------------------ dispatch
def render(kind: str, data: Mapping[str, Any], fmt: str) -> tuple[bytes, str]:
    """Render figure ``kind`` from ``data`` in ``fmt``; returns ``(bytes, media_type)``.

    Parameters
    ----------
    kind : {"joint_angles", "chained_state", "robustness", "sweep", "pareto"}
    data : dict
        A plan response (``joint_angles``, ``chained_state``, ``pareto``: one of
        ``pareto: true``; optionally wrapped as
        ``{"plan": ..., "constraint_points": [...]}``), ``{"plan": ..., "robustness": ...}``
        (``robustness``) or a sweep response (``sweep``; optionally wrapped as
        ``{"sweep": ..., "planned_phi_change": dphi}``).
    fmt : {"png", "svg"}

    Raises
    ------
    ValueError
        Unknown kind or format, or data of the wrong shape.
    """
    f = _check_fmt(fmt)
    k = str(kind).strip().lower().replace("-", "_")
    if k not in KINDS:
        raise ValueError(f"unknown figure kind {kind!r}: use one of {list(KINDS)}")
    if not isinstance(data, Mapping):
        raise ValueError("data must be a JSON object")
    if k == "joint_angles":
        out = joint_angles(data, f)
    elif k == "pareto":
        out = pareto(data, f)
    elif k == "chained_state":
        out = chained_state(data, f)
    elif k == "robustness":
        if "plan" not in data or "robustness" not in data:
            raise ValueError("robustness figures need {'plan': ..., 'robustness': ...}")
        out = robustness(data["plan"], data["robustness"], f)
    elif isinstance(data.get("sweep"), Mapping):  # {"sweep": ..., "planned_phi_change": ...}
        planned = data.get("planned_phi_change")
        out = sweep(data["sweep"], f, None if planned is None else float(planned))
    else:
        out = sweep(data, f)
    return out, FORMATS[f]
