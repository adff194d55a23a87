"""The two files of a run as text: checked parsing of ``RUN.csv`` (the samples) and
``RUN.json`` (the conditions), and the text :meth:`Trace.write` puts in them.

Every rule of the format is enforced on read, and a violation raises
:class:`TraceFormatError` naming the file, the physical line (1-based, comments and
all) and the rule.
"""

from __future__ import annotations

import io
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from identify.traces.trace_format import TraceFormatError
from identify.traces.trace_metadata import check_metadata, key_line, ordered_metadata

__all__ = [
    "check_writable_times",
    "conditions_json_text",
    "parse_conditions_json",
    "parse_samples_csv",
    "samples_csv_text",
]

_HEADERS = (("time_s", "elongation_um"), ("time_s", "elongation_um", "puller_um"))
_HEADER_TEXT = " or ".join(repr(",".join(h)) for h in _HEADERS)

# Printed precision of the CSV: 1 ns and 1 pm are far below the camera's resolution, and
# fixed decimals make a write -> read -> write cycle byte-identical.
_TIME_FMT = "%.9f"
_LENGTH_FMT = "%.6f"

# A decimal number as the format allows it (what np.loadtxt and humans agree on); the
# slow path uses this instead of float(), which would also take "1_000" or " nan ".
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


# ----------------------------------------------------------------------------- text
def _split_lines(text: str) -> list[str]:
    """Physical lines of ``text`` (universal newlines already applied), no terminator."""
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()  # the terminator of the last line is not a blank line
    return lines


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith("#")


def _read_text(path: Path) -> str:
    """UTF-8 text of ``path`` (a BOM, as spreadsheets write, is dropped)."""
    raw = path.read_bytes()
    try:
        return raw.decode("utf-8-sig").replace("\r\n", "\n").replace("\r", "\n")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise TraceFormatError(path, line, "not UTF-8 text") from None


# ----------------------------------------------------------------------------- CSV
def _parse_header(path: Path, lines: list[str]) -> tuple[int, tuple[str, ...]]:
    """Index of the header line and its column names."""
    for i, line in enumerate(lines):
        if _is_comment(line):
            continue
        if not line.strip():
            raise TraceFormatError(path, i + 1, "blank line")
        names = tuple(c.strip() for c in line.split(","))
        if names not in _HEADERS:
            raise TraceFormatError(
                path, i + 1, f"bad header {line.strip()!r}: expected {_HEADER_TEXT}"
            )
        return i, names
    raise TraceFormatError(path, None, f"no header line: expected {_HEADER_TEXT}")


def _check_cell(cell: str, column: str) -> str | None:
    """Why ``cell`` is not a valid number of ``column``, or None if it is."""
    s = cell.strip()
    if not s:
        return f"blank cell in column {column}"
    if _NUMBER.fullmatch(s):
        return None
    if _NONFINITE.fullmatch(s):
        return f"{s!r} in column {column}: values must be finite numbers"
    return f"{s!r} in column {column} is not a number"


def _scan_rows(path: Path, lines: list[str], header: int, names: tuple[str, ...]) -> None:
    """Line-by-line check of the data rows; raises at the first offending line.

    Only called when the vectorised parse found a problem, so clarity beats speed here.
    """
    ncol = len(names)
    previous_time: float | None = None
    for i in range(header + 1, len(lines)):
        line = lines[i]
        if _is_comment(line):
            continue
        if not line.strip():
            raise TraceFormatError(path, i + 1, "blank line")
        cells = line.split(",")
        if len(cells) != ncol:
            raise TraceFormatError(
                path, i + 1, f"expected {ncol} cells ({','.join(names)}), found {len(cells)}"
            )
        for cell, column in zip(cells, names):
            why = _check_cell(cell, column)
            if why is not None:
                raise TraceFormatError(path, i + 1, why)
        t = float(cells[0])
        if previous_time is not None and t <= previous_time:
            kind = "duplicate" if t == previous_time else "decreasing"
            raise TraceFormatError(
                path, i + 1,
                f"{kind} time: time_s = {cells[0].strip()} after {previous_time!r}; "
                "times must strictly increase",
            )
        previous_time = t


def parse_samples_csv(path: Path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Checked samples of a trace CSV: array (n_rows, n_cols) in file units, and names."""
    text = _read_text(path)
    lines = _split_lines(text)
    if not lines:
        raise TraceFormatError(path, None, f"empty file: expected the header {_HEADER_TEXT}")
    header, names = _parse_header(path, lines)
    body = lines[header + 1:]
    # Fast path: drop comments, hand the rest to numpy's C parser, check with array
    # operations. np.loadtxt silently skips blank lines, so those are looked for here.
    data = [ln for ln in body if not _is_comment(ln)]
    clean = all(ln.strip() for ln in data)
    values: np.ndarray | None = None
    parse_error: Exception | None = None
    if clean and data:
        try:
            values = np.loadtxt(data, delimiter=",", comments=None, ndmin=2, dtype=np.float64)
        except ValueError as exc:
            parse_error = exc
    if values is not None:
        ok = (
            values.shape[1] == len(names)
            and bool(np.isfinite(values).all())
            and bool((np.diff(values[:, 0]) > 0).all())
        )
        if ok:
            if len(values) < 2:
                raise TraceFormatError(
                    path, None, f"at least 2 data rows are needed, found {len(values)}"
                )
            return values, names
    # Slow path: find and name the first offending line.
    _scan_rows(path, lines, header, names)
    if not data:
        raise TraceFormatError(path, None, "at least 2 data rows are needed, found 0")
    # The scan accepted every line although numpy did not: report numpy's reason.
    raise TraceFormatError(path, None, f"cannot parse the samples: {parse_error}")


def check_writable_times(time_s: np.ndarray, csv_path: Path) -> None:
    """Refuse frame times closer than the printed precision (1 ns): they would read back
    as equal."""
    t_printed = np.round(time_s, 9)
    bad = np.flatnonzero(np.diff(t_printed) <= 0)
    if bad.size:
        raise TraceFormatError(
            csv_path, None,
            f"frames {bad[0]} and {bad[0] + 1} are closer than 1 ns and would be "
            "written with equal times",
        )


def samples_csv_text(time_s: np.ndarray, elongation: np.ndarray, puller: np.ndarray | None) -> str:
    """The CSV text of samples in SI (lengths printed in µm, fixed decimals)."""
    columns = [time_s, elongation * 1e6]
    header = "time_s,elongation_um"
    fmt = [_TIME_FMT, _LENGTH_FMT]
    if puller is not None:
        columns.append(puller * 1e6)
        header += ",puller_um"
        fmt.append(_LENGTH_FMT)
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack(columns), fmt=fmt, delimiter=",",
               header=header, comments="")
    return buf.getvalue()


# ----------------------------------------------------------------------------- JSON
def parse_conditions_json(path: Path) -> dict:
    """Checked metadata of a trace JSON file."""
    text = _read_text(path)

    def pairs(items: list[tuple[str, Any]]) -> dict:
        out: dict = {}
        for k, v in items:
            if k in out:
                # json would keep the last value silently; a duplicated condition is
                # ambiguous, so refuse it
                raise TraceFormatError(path, key_line(text, k), f"duplicate key {k!r}")
            out[k] = v
        return out

    def constant(name: str) -> NoReturn:
        m = re.search(r"(?<![\w\"])-?" + re.escape(name.lstrip("-")), text)
        line = None if m is None else text.count("\n", 0, m.start()) + 1
        raise TraceFormatError(path, line, f"invalid JSON: {name} is not a JSON number")

    try:
        meta = json.loads(text, object_pairs_hook=pairs, parse_constant=constant)
    except json.JSONDecodeError as exc:
        raise TraceFormatError(path, exc.lineno, f"invalid JSON: {exc.msg}") from None
    if not isinstance(meta, dict):
        raise TraceFormatError(path, None, "the JSON content must be an object {...}")
    check_metadata(meta, path, text)
    return meta


def _json_default(obj: Any) -> Any:
    # numpy scalars and arrays sneak into metadata from simulation results
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def conditions_json_text(meta: Mapping[str, Any]) -> str:
    """The JSON text of a run's conditions: keys in the format's order, indented, with a
    final newline."""
    text = json.dumps(ordered_metadata(meta), indent=2, ensure_ascii=False, allow_nan=False,
                      default=_json_default)
    return text + "\n"
