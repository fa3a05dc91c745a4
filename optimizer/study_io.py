"""The files of a study: its goals and mechanisms in, its rows out (CSV or Parquet).

Rows are flat records, one per (mechanism, goal), with the columns of :func:`columns`. CSV is
written with the standard library (floats as ``repr``, so they read back bit for bit; a missing
number is an empty field); Parquet through ``pyarrow``, only when it is installed
(``pip install chained-planner[cluster]``).

Interrupted studies resume from their output file (:func:`read_rows`): a CSV file grows by whole
chunks of rows, and a line that a kill cut short (no final newline, or too few fields) is
dropped, so its plan is simply planned again. A Parquet file cannot grow; it is rewritten whole,
atomically, at most every :data:`CHECKPOINT_SECONDS` s and at the end.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

from .model import MAX_JOINTS, Robot

#: Columns before the start/goal angles, with their types.
BASE_COLUMNS: dict[str, type] = {
    "id": str, "mechanism": str, "goal": str, "kind": str, "n": int, "status": str,
    "method": str, "deviation": float, "reversals": int, "reversals_phi": int,
    "reversals_th1": int, "d_a": float, "t_p": int, "sensitivity": float,
    "phi_change": float, "duration": float, "terminal_error": float, "margin": float,
    "detail": str, "seconds": float,
}
#: Output formats by file extension.
FORMATS = {".csv": "csv", ".parquet": "parquet"}
#: Least time (s) between two rewrites of a Parquet file during a study.
CHECKPOINT_SECONDS = 10.0


def columns(n_max: int) -> list[str]:
    """The row's columns for a study whose largest mechanism has ``n_max`` joints: the base
    columns, then ``start_1..start_{n_max}`` and ``goal_1..goal_{n_max}`` (rad; empty beyond a
    row's own ``n``)."""
    return (list(BASE_COLUMNS) + [f"start_{i}" for i in range(1, n_max + 1)]
            + [f"goal_{i}" for i in range(1, n_max + 1)])


def column_type(name: str) -> type:
    """The Python type of a column's values."""
    return BASE_COLUMNS.get(name, float)


def output_format(path: str | os.PathLike[str]) -> str:
    """``csv`` or ``parquet`` from the file's extension.

    Raises
    ------
    ValueError
        Another extension, or ``.parquet`` without pyarrow installed.
    """
    ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        raise ValueError(f"--out {path}: the extension must be one of {sorted(FORMATS)} "
                         "(CSV works everywhere; Parquet needs pyarrow)")
    if FORMATS[ext] == "parquet":
        _pyarrow()
    return FORMATS[ext]


def _pyarrow() -> Any:
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError as exc:
        raise ValueError("Parquet output needs pyarrow: pip install 'chained-planner[cluster]' "
                         "(or write a .csv file)") from exc
    return pyarrow


def _parse(name: str, text: str) -> Any:
    if text == "":
        return "" if column_type(name) is str else None
    tp = column_type(name)
    return tp(text)


def _format(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ""
    return str(value)


def read_rows(path: str | os.PathLike[str]) -> tuple[list[str], list[dict[str, Any]]]:
    """The columns and complete rows of an existing output file (``([], [])`` when absent).

    Incomplete CSV rows (a last line without its newline, a wrong number of fields, a value
    that does not parse) are left out: their plans are planned again.
    """
    p = Path(path)
    if not p.exists() or p.stat().st_size == 0:
        return [], []
    if output_format(p) == "parquet":
        pa = _pyarrow()
        table = pa.parquet.read_table(p)
        return list(table.column_names), [_clean(r) for r in table.to_pylist()]
    text = p.read_text(encoding="utf-8")
    if not text.endswith("\n"):
        text = text[:text.rfind("\n") + 1]
    reader = csv.reader(io.StringIO(text, newline=""))
    header = next(reader, [])
    rows: list[dict[str, Any]] = []
    for fields in reader:
        if len(fields) != len(header):
            continue
        try:
            rows.append({k: _parse(k, v) for k, v in zip(header, fields)})
        except ValueError:
            continue
    return header, rows


def _clean(row: Mapping[str, Any]) -> dict[str, Any]:
    """A Parquet row with NaN (a missing number) as None and strings never None."""
    out: dict[str, Any] = {}
    for k, v in row.items():
        if isinstance(v, float) and not math.isfinite(v):
            v = None
        if v is None and column_type(k) is str:
            v = ""
        out[k] = v
    return out


class RowWriter:
    """Writes a study's rows as they come, to CSV (appended) or Parquet (checkpointed).

    Parameters
    ----------
    path : path
    cols : list of str
        The columns, in order.
    existing : list of dict
        Rows already in the file (a resumed study): kept.
    """

    def __init__(self, path: str | os.PathLike[str], cols: Sequence[str],
                 existing: Sequence[Mapping[str, Any]] = ()) -> None:
        self.path = Path(path)
        self.format = output_format(self.path)
        self.columns = list(cols)
        self.rows: list[dict[str, Any]] = [dict(r) for r in existing]
        self._last_checkpoint = time.monotonic()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # a clean file holding the complete rows only (drops a cut-off last line)
        self._rewrite(self.rows)

    def add(self, rows: Iterable[Mapping[str, Any]]) -> None:
        """Append rows (one chunk's) and make them durable (CSV at once, Parquet at the next
        checkpoint)."""
        new = [dict(r) for r in rows]
        self.rows.extend(new)
        if self.format == "csv":
            buf = io.StringIO()
            w = csv.writer(buf, lineterminator="\n")
            for r in new:
                w.writerow([_format(r.get(c)) for c in self.columns])
            with open(self.path, "a", encoding="utf-8", newline="") as fh:
                fh.write(buf.getvalue())
                fh.flush()
        elif time.monotonic() - self._last_checkpoint >= CHECKPOINT_SECONDS:
            self._rewrite(self.rows)

    def finish(self, order: Sequence[str]) -> list[dict[str, Any]]:
        """Rewrite the file with every row in ``order`` of ids (others after, as found);
        returns the rows in that order."""
        rank = {k: i for i, k in enumerate(order)}
        rows = sorted(self.rows, key=lambda r: rank.get(str(r.get("id")), len(rank)))
        self._rewrite(rows)
        self.rows = rows
        return rows

    def _rewrite(self, rows: Sequence[Mapping[str, Any]]) -> None:
        tmp = self.path.with_name(self.path.name + ".tmp")
        if self.format == "csv":
            with open(tmp, "w", encoding="utf-8", newline="") as fh:
                w = csv.writer(fh, lineterminator="\n")
                w.writerow(self.columns)
                for r in rows:
                    w.writerow([_format(r.get(c)) for c in self.columns])
        else:
            pa = _pyarrow()
            types = {str: pa.string(), int: pa.int64(), float: pa.float64()}
            schema = pa.schema([(c, types[column_type(c)]) for c in self.columns])
            data = {c: [r.get(c) for r in rows] for c in self.columns}
            pa.parquet.write_table(pa.table(data, schema=schema), tmp)
        os.replace(tmp, self.path)
        self._last_checkpoint = time.monotonic()


# ------------------------------------------------------------------ inputs

def _load(path: str | os.PathLike[str]) -> Any:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from exc
    if Path(path).suffix.lower() == ".csv":
        return list(csv.DictReader(io.StringIO(text, newline="")))
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from exc


def read_goals(path: str | os.PathLike[str]) -> list[tuple[str, tuple[float, ...],
                                                           tuple[float, ...]]]:
    """``(name, start, goal)`` (rad) of a goals file.

    JSON: a list of ``{"start": [...], "goal": [...], "name": optional}`` (or an object with
    that list under ``"goals"``). CSV: columns ``start_1..start_n`` and ``goal_1..goal_n``
    (empty beyond a row's ``n``), ``name`` optional. Names default to ``g00000``, ... in file
    order and must be unique.

    Raises
    ------
    ValueError
        Naming the entry and what is wrong with it.
    """
    data = _load(path)
    if isinstance(data, dict):
        data = data.get("goals")
    if not isinstance(data, list) or not data:
        raise ValueError(f"{path}: expected a non-empty list of goals (JSON list, "
                         "{\"goals\": [...]}, or CSV rows)")
    out = []
    seen: set[str] = set()
    for i, entry in enumerate(data):
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: goal {i} must be an object with start and goal")
        try:
            if "start" in entry:
                start = tuple(float(x) for x in entry["start"])
                goal = tuple(float(x) for x in entry["goal"])
            else:  # CSV columns
                start = tuple(float(entry[f"start_{k}"]) for k in range(1, MAX_JOINTS + 1)
                              if entry.get(f"start_{k}") not in (None, ""))
                goal = tuple(float(entry[f"goal_{k}"]) for k in range(1, MAX_JOINTS + 1)
                             if entry.get(f"goal_{k}") not in (None, ""))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: goal {i} needs start and goal as lists of numbers "
                             f"(rad): {exc}") from exc
        if not start or len(start) != len(goal):
            raise ValueError(f"{path}: goal {i} has {len(start)} start and {len(goal)} goal "
                             "angles; both need the robot's n")
        if not all(math.isfinite(x) for x in start + goal):
            raise ValueError(f"{path}: goal {i} has a non-finite angle")
        name = str(entry.get("name") or entry.get("id") or f"g{i:05d}")
        if name in seen:
            raise ValueError(f"{path}: goal name {name!r} appears twice")
        seen.add(name)
        out.append((name, start, goal))
    return out


def mechanism_name(robot: Robot) -> str:
    """A readable default name: ``K0.88658-0.7115_m2-3``."""
    return ("K" + "-".join(f"{k:g}" for k in robot.gains) + "_m"
            + "-".join(str(m) for m in robot.exponents))


def read_mechanisms(path: str | os.PathLike[str]) -> list[tuple[str, Robot]]:
    """``(name, robot)`` of a mechanism file: one ``{"gains": [...], "exponents": [...],
    "name": optional}`` (as a plan request's ``robot``), a list of them, or an object with that
    list under ``"mechanisms"``. Names must be unique.

    Raises
    ------
    ValueError
        Naming the entry (the robot's own checks name the field and limit).
    """
    data = _load(path)
    if isinstance(data, dict) and "mechanisms" in data:
        data = data["mechanisms"]
    entries = data if isinstance(data, list) else [data]
    out: list[tuple[str, Robot]] = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or "gains" not in entry or "exponents" not in entry:
            raise ValueError(f"{path}: mechanism {i} must be an object with gains (K2..Kn) "
                             "and exponents (m2..mn)")
        try:
            robot = Robot(tuple(entry["gains"]), tuple(entry["exponents"]))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: mechanism {i}: {exc}") from exc
        name = str(entry.get("name") or mechanism_name(robot))
        if name in {nm for nm, _ in out}:
            raise ValueError(f"{path}: mechanism name {name!r} appears twice")
        out.append((name, robot))
    if not out:
        raise ValueError(f"{path}: no mechanism")
    return out
