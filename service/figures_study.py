"""The figure of a mechanism study: where in the workspace plans succeed, and how far they
deviate, over a 2-D slice of the goals.

Input: a study's rows (:mod:`optimizer.studies`; the CSV or Parquet file of ``chained-planner
study``). For each mechanism (one row of panels, at most :data:`MAX_MECHANISMS`), two panels
over two goal coordinates (default ``goal_1`` and ``goal_2``, drawn in degrees):

* **success**: each goal a point, green where the plan succeeded, red (marker by status) where
  it failed, with the share reached in the title;
* **deviation**: the successful goals coloured by ``deviation`` (the path's largest joint-space
  distance from the straight segment, degrees), the failures as grey crosses.

Usage::

    python -m service.figures_study rows.csv -o map.png [--x goal_2 --y goal_3]
                                             [--mechanism NAME] [--format png|svg]

The study command (``python -m optimizer``) does not draw: the library knows no figures (the
service's figure code lives here), so a study is drawn from its file afterwards.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.backends.backend_agg import FigureCanvasAgg

from optimizer.study_io import read_rows

from .figures import DEG, DPI, WIDTH, render_figure
from .figures_cli import output_format, write_figure
from .formats import FORMATS

#: Mechanisms drawn at most (one row of panels each).
MAX_MECHANISMS = 6
_FAIL_MARKERS = {"infeasible": "x", "timeout": "s", "numerical_failure": "^",
                 "invalid_request": "D", "error": "*"}


def _coord(rows: Sequence[Mapping[str, Any]], col: str) -> np.ndarray:
    vals = [r.get(col) for r in rows]
    if any(v is None for v in vals):
        raise ValueError(f"column {col!r} is missing in some rows (a goal with fewer joints?)")
    return np.degrees(np.asarray(vals, float))


def study_map(rows: Sequence[Mapping[str, Any]], fmt: str = "png", x: str = "goal_1",
              y: str = "goal_2", mechanism: str | None = None) -> bytes:
    """Render the success and deviation maps of a study's rows.

    Parameters
    ----------
    rows : sequence of mapping
        Study rows (at least ``mechanism``, ``status``, ``deviation`` and the columns ``x``
        and ``y``, in radians).
    fmt : {"png", "svg"}
    x, y : str
        The goal (or start) coordinates of the slice, e.g. ``goal_1``, ``goal_3``,
        ``start_2``.
    mechanism : str, optional
        Only this mechanism (default: every one, up to :data:`MAX_MECHANISMS`).

    Raises
    ------
    ValueError
        No rows (of that mechanism), an unknown column, or a bad format.
    """
    if mechanism is not None:
        rows = [r for r in rows if r.get("mechanism") == mechanism]
    if not rows:
        raise ValueError("no rows to draw" + (f" for mechanism {mechanism!r}" if mechanism
                                              else ""))
    for col in (x, y):
        if col not in rows[0] or not (col.startswith("goal_") or col.startswith("start_")):
            raise ValueError(f"column {col!r}: choose goal_i or start_i of the rows")
    names = list(dict.fromkeys(str(r["mechanism"]) for r in rows))[:MAX_MECHANISMS]

    def build() -> Figure:
        fig = Figure(figsize=(WIDTH, 3.6 * len(names)), dpi=DPI, layout="constrained")
        FigureCanvasAgg(fig)
        axes = fig.subplots(len(names), 2, squeeze=False)
        for (ax_ok, ax_dev), name in zip(axes, names):
            mine = [r for r in rows if r["mechanism"] == name]
            px, py = _coord(mine, x), _coord(mine, y)
            ok = np.array([r["status"] == "success" for r in mine])
            ax_ok.scatter(px[ok], py[ok], s=14, color="tab:green", label="success")
            for status in sorted({str(r["status"]) for r in mine} - {"success"}):
                sel = np.array([r["status"] == status for r in mine])
                ax_ok.scatter(px[sel], py[sel], s=22, color="tab:red",
                              marker=_FAIL_MARKERS.get(status, "o"), label=status)
            share = ok.mean() if len(ok) else math.nan
            ax_ok.set_title(f"{name}: {ok.sum()} of {len(mine)} reached ({100 * share:.0f} %)")
            ax_ok.legend(loc="best", fontsize=8)
            dev = np.degrees(np.asarray([r["deviation"] if r["deviation"] is not None
                                         else math.nan for r in mine], float))
            if ok.any():
                sc = ax_dev.scatter(px[ok], py[ok], c=dev[ok], s=16, cmap="viridis")
                fig.colorbar(sc, ax=ax_dev, label=f"deviation ({DEG})")
            if (~ok).any():
                ax_dev.scatter(px[~ok], py[~ok], s=14, color="0.6", marker="x", label="failed")
                ax_dev.legend(loc="best", fontsize=8)
            ax_dev.set_title(f"{name}: deviation from the straight segment")
            for ax in (ax_ok, ax_dev):
                ax.set_xlabel(f"{x} ({DEG})")
                ax.set_ylabel(f"{y} ({DEG})")
        return fig

    return render_figure(build, fmt)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m service.figures_study",
                                 description="Draw a study's success and deviation maps.")
    ap.add_argument("rows", help="the study's rows (.csv or .parquet)")
    ap.add_argument("-o", "--output", required=True,
                    help="figure file (.png or .svg; '-' for stdout)")
    ap.add_argument("--x", default="goal_1", help="horizontal coordinate (default goal_1)")
    ap.add_argument("--y", default="goal_2", help="vertical coordinate (default goal_2)")
    ap.add_argument("--mechanism", default=None, help="only this mechanism")
    ap.add_argument("--format", "-f", choices=sorted(FORMATS), default=None,
                    help="default: from the extension of -o, else png")
    args = ap.parse_args(argv)
    fmt = output_format(args.format, args.output)
    try:
        _, rows = read_rows(args.rows)
        if not rows:
            raise ValueError(f"{args.rows} holds no rows")
        content = study_map(rows, fmt, args.x, args.y, args.mechanism)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return write_figure(content, args.output, fmt)


if __name__ == "__main__":
    sys.exit(main())
