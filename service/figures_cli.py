"""Render a figure from a saved JSON response.

Usage::

    python -m service.figures_cli KIND input.json [--format png|svg] [-o out.png]

``KIND`` is one of ``joint_angles``, ``chained_state`` (input: a plan response, optionally
``{"plan": ..., "constraint_points": [...]}``), ``robustness`` (input:
``{"plan": ..., "robustness": ...}``) or ``sweep`` (input: a sweep response). ``input.json`` may
be ``-`` for standard input. Without ``--format`` the format follows the extension of ``-o``
(default png); without ``-o`` the figure is written next to the input as
``<input stem>.<kind>.<format>``; ``-o -`` writes the bytes to standard output.

Exit status: 0 on success, 2 on a usage or input error (message on standard error).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

from .figures import FORMATS, KINDS, render


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m service.figures_cli",
        description="Render a plan, robustness or sweep figure (PNG or SVG) from saved JSON.")
    ap.add_argument("kind", choices=KINDS, help="figure to draw")
    ap.add_argument("input", help="JSON file (plan response, sweep response or "
                                  "{\"plan\": ..., \"robustness\": ...}); '-' for stdin")
    ap.add_argument("--format", "-f", choices=sorted(FORMATS), default=None,
                    help="output format (default: from the -o extension, else png)")
    ap.add_argument("-o", "--output", default=None,
                    help="output file ('-' for stdout; default <input stem>.<kind>.<format>)")
    return ap


def output_format(fmt: str | None, output: str | None) -> str:
    """The format to write: ``fmt`` when given, else the extension of ``output`` when it is a
    known format (not for ``-``, standard output), else png."""
    if fmt is not None:
        return fmt
    if output is None or output == "-":
        return "png"
    ext = Path(output).suffix.lower().lstrip(".")
    return ext if ext in FORMATS else "png"


def write_figure(content: bytes, output: str | Path, fmt: str) -> int:
    """Write ``content`` (a figure in format ``fmt``) to ``output`` (``-``: standard output)
    and say so on standard error.

    Returns
    -------
    int
        The exit status: 0, or 2 when the file cannot be written (the reason on standard
        error).
    """
    if str(output) == "-":
        sys.stdout.buffer.write(content)
        sys.stdout.buffer.flush()
        return 0
    try:
        Path(output).write_bytes(content)
    except OSError as exc:
        print(f"error: cannot write {output}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"wrote {output} ({FORMATS[fmt]}, {len(content)} bytes)", file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    fmt = output_format(args.format, args.output)
    try:
        if args.input == "-":
            data = json.load(sys.stdin)
        else:
            with open(args.input, encoding="utf-8") as fh:
                data = json.load(fh)
    except OSError as exc:
        print(f"error: cannot read {args.input}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except json.JSONDecodeError as exc:
        print(f"error: {args.input} is not valid JSON: {exc}", file=sys.stderr)
        return 2
    try:
        content, _media_type = render(args.kind, data, fmt)
    except ValueError as exc:
        print(f"error: cannot draw {args.kind} from {args.input}: {exc}", file=sys.stderr)
        return 2
    if args.output is None:
        stem = "figure" if args.input == "-" else str(Path(args.input).with_suffix(""))
        return write_figure(content, f"{stem}.{args.kind}.{fmt}", fmt)
    return write_figure(content, args.output, fmt)


if __name__ == "__main__":
    sys.exit(main())
