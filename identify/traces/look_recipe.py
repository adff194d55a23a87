"""A lab's own reduction recipe for a look file, run as xlook runs it: calibrations,
zeroing, offsets, the elastic correction, friction as the ratio of two columns.

The commands understood are those of the public p655 recipe (``math``, ``math_int``,
``summation``, ``r_col``, ``r_row``, ``zero``, ``offset_int``, ``ec``, ``strain``), with
xlook's conventions: columns numbered from 1, rows from 0, ranges inclusive, ``-1`` for
the last row; a removed column leaves a gap and the others keep their numbers.
``begin``, ``com_file``, ``read`` and ``end`` are bookkeeping and skipped; any other
command is refused with its line, since running half a recipe would give wrong numbers
silently.
"""

from __future__ import annotations

import os
import shlex
from pathlib import Path

import numpy as np

from identify.traces.look import Channel, LookFile, LookFormatError

__all__ = ["RecipeError", "apply_recipe"]

_SKIPPED = {"begin", "com_file", "read", "end"}


class RecipeError(LookFormatError):
    """A recipe line that cannot be run: the message names the file, the line and why."""


class _Columns:
    """Columns by xlook number (1-based); a removed column is None."""

    def __init__(self, look: LookFile):
        self.cols: dict[int, Channel | None] = {i + 1: Channel(c.name, c.units, c.values.astype(float).copy(),
                                                              c.gain, c.comment)
                                                for i, c in enumerate(look.channels)}

    def get(self, n: int) -> np.ndarray:
        c = self.cols.get(n)
        if c is None:
            raise KeyError(f"column {n} holds no data")
        return c.values

    def put(self, n: int, values: np.ndarray, name: str | None, units: str | None) -> None:
        old = self.cols.get(n)
        self.cols[n] = Channel(name if name is not None else (old.name if old else f"col{n}"),
                               units if units is not None else (old.units if old else ""), values)

    def rows(self) -> int:
        return max((len(c.values) for c in self.cols.values() if c is not None), default=0)


def _row_range(first: int, last: int, n: int) -> slice:
    if last == -1 or last == n:
        last = n - 1
    if first < 0 or last >= n or last < first:
        raise ValueError(f"rows {first}..{last} are not inside 0..{n - 1}")
    return slice(first, last + 1)


def _operate(x: np.ndarray, op: str, y) -> np.ndarray:
    if op == "+":
        return x + y
    if op == "-":
        return x - y
    if op == "*":
        return x * y
    if op == "/":
        with np.errstate(divide="ignore", invalid="ignore"):
            return x / y
    raise ValueError(f"operator {op!r} is not one of + - * /")


def _math(cols: _Columns, a: list[str], ranged: bool) -> None:
    c1, op, v, kind, out = int(a[0]), a[1], a[2], a[3], int(a[4])
    rest = a[5:]
    if ranged:
        first, last, rest = int(rest[0]), int(rest[1]), rest[2:]
    x = cols.get(c1)
    if kind == "=":
        y = float(v)
    elif kind == ":":
        y = cols.get(int(v))
    else:
        raise ValueError(f"{kind!r} must be '=' (a number) or ':' (a column)")
    result = _operate(x, op, y)
    if ranged:
        sl = _row_range(first, last, len(x))
        target = cols.get(out).copy() if cols.cols.get(out) is not None else np.zeros_like(x)
        target[sl] = result[sl]
        result = target
    cols.put(out, result, *(rest + [None, None])[:2])


def _run(cols: _Columns, cmd: str, a: list[str]) -> None:
    if cmd in ("math", "math_int"):
        _math(cols, a, ranged=cmd == "math_int")
    elif cmd == "summation":
        cols.put(int(a[1]), np.cumsum(cols.get(int(a[0]))), *(a[2:] + [None, None])[:2])
    elif cmd == "r_col":
        cols.cols[int(a[0])] = None
    elif cmd == "r_row":
        n = cols.rows()
        sl = _row_range(int(a[0]), int(a[1]), n)
        for c in cols.cols.values():
            if c is not None and len(c.values) >= sl.stop:
                c.values = np.delete(c.values, np.arange(sl.start, sl.stop))
    elif cmd == "zero":
        x = cols.get(int(a[0]))
        x -= x[int(a[1])]
    elif cmd == "offset_int":
        x = cols.get(int(a[0]))
        r1, r2 = int(a[1]), int(a[2])
        d = x[r2] - x[r1]
        if len(a) > 3 and a[3] == "y":
            x[r1:r2] = x[r1]
        x[r2:] -= d
    elif cmd in ("ec", "strain"):
        _incremental(cols, cmd, a)
    else:
        raise ValueError(f"command {cmd!r} is not one this reader runs "
                         "(math, math_int, summation, r_col, r_row, zero, offset_int, ec, strain)")


def _incremental(cols: _Columns, cmd: str, a: list[str]) -> None:
    """``ec``: out = disp − (load − load[first])/K (the elastic stretch of the frame taken
    out; K in xlook's single precision, as it parses it); ``strain``: out accumulates the
    displacement's increments over the mean layer thickness."""
    disp, other, out = cols.get(int(a[0])), cols.get(int(a[1])), int(a[2])
    sl = _row_range(int(a[3]), int(a[4]), len(disp))
    target = cols.get(out).copy() if cols.cols.get(out) is not None else np.zeros_like(disp)
    if cmd == "ec":
        K = float(np.float32(a[5]))
        target[sl] = disp[sl] - (other[sl] - other[sl.start]) / K
        names = a[6:]
    else:
        h = other[sl]
        inc = np.diff(disp[sl]) / (0.5 * (h[1:] + h[:-1]))
        target[sl] = disp[sl.start] / h[0] + np.concatenate([[0.0], np.cumsum(inc)])
        names = a[5:]
    cols.put(out, target, *(names + [None, None])[:2])


def apply_recipe(look: LookFile, recipe: str | os.PathLike, *, log: list | None = None) -> LookFile:
    """The columns after the recipe (a path, or the recipe's text) has run on ``look``;
    ``look`` is left as it was. ``log``, when given, gets one line per command run."""
    path = Path(recipe) if not isinstance(recipe, str) or "\n" not in recipe else None
    text = path.read_text(encoding="utf-8") if path is not None else recipe
    where = str(path) if path is not None else "recipe"
    cols = _Columns(look)
    for lineno, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        parts = shlex.split(body.replace(",", " "))
        cmd, args = parts[0].lower(), parts[1:]
        if cmd in _SKIPPED:
            continue
        try:
            _run(cols, cmd, args)
        except (ValueError, IndexError, KeyError) as err:
            msg = err.args[0] if isinstance(err, KeyError) and err.args else err
            raise RecipeError(f"{where}, line {lineno}: {body!r}: {msg}") from None
        if log is not None:
            log.append(f"line {lineno}: {body}")
    out = LookFile(title=look.title, path=look.path)
    out.channels = [c if c is not None else Channel("no_val", "no_val", np.zeros(0))
                    for _, c in sorted(cols.cols.items())]
    return out
