"""Reading the binary "look" files of rock-mechanics labs (xlook, pylook), and plain text
tables, into named columns.

A look file is a 20-byte title, the record and channel counts (big-endian int32), two
more int32 words, 32 channel descriptors of 84 bytes (name, units: 13 bytes each; gain:
float32; comment: 50 bytes; element count: int32), then each channel's samples as
big-endian float32, one column after another. Only the first ``channel count``
descriptors are used.
"""

from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["Channel", "LookFile", "LookFormatError", "MissingColumnError", "read_look", "read_mat", "read_table"]

_TITLE = 20
_COUNTS = struct.Struct(">ii")
_HEADER = _TITLE + 16  # title, record and channel counts, two reserved words
_N_DESCRIPTORS = 32
_DESCRIPTOR = struct.Struct(">13s13sf50si")  # 84 bytes


class LookFormatError(ValueError):
    """A file that does not follow the look format (or a table that cannot be read):
    the message names the file and the rule."""


class MissingColumnError(LookFormatError, KeyError):
    """A column asked for by a name the file does not have (both a ``KeyError``, as a
    lookup, and a :class:`LookFormatError`, as input that does not fit)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


@dataclass
class Channel:
    """One column: its ``name``, ``units``, the ``gain`` and ``comment`` the lab stored,
    and its samples ``values`` (float64, as read: in the recording's own units)."""

    name: str
    units: str
    values: np.ndarray
    gain: float = 1.0
    comment: str = ""


@dataclass
class LookFile:
    """A file's ``title`` and its ``channels`` in order; ``path`` it was read from."""

    title: str
    channels: list[Channel] = field(default_factory=list)
    path: str = ""

    @property
    def n_rows(self) -> int:
        return len(self.channels[0].values) if self.channels else 0

    def __getitem__(self, key: int | str) -> Channel:
        """A channel by 0-based index or by name (case-insensitive)."""
        if isinstance(key, int):
            return self.channels[key]
        for c in self.channels:
            if c.name.lower() == str(key).lower():
                return c
        raise MissingColumnError(f"{self.path or self.title}: no channel named {key!r}; "
                       f"the channels are {', '.join(c.name for c in self.channels)}")

    def describe(self) -> str:
        """One line per channel: index, name, units and range."""
        lines = [f"{self.path or self.title}: {self.n_rows} rows, {len(self.channels)} channels"]
        for i, c in enumerate(self.channels):
            v = c.values
            rng = f"{np.nanmin(v):.6g} .. {np.nanmax(v):.6g}" if v.size else "empty"
            lines.append(f"  {i}: {c.name} [{c.units}] {rng}")
        return "\n".join(lines)


def _text(raw: bytes) -> str:
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


def read_look(path: str | os.PathLike) -> LookFile:
    """Read a binary look file; raise :class:`LookFormatError` naming the file and what
    does not fit (a short file, impossible counts)."""
    path = Path(path)
    raw = path.read_bytes()
    need = _HEADER + _N_DESCRIPTORS * _DESCRIPTOR.size
    if len(raw) < need:
        raise LookFormatError(f"{path}: {len(raw)} bytes, shorter than a look file's header ({need} bytes)")
    n_rec, n_chan = _COUNTS.unpack_from(raw, _TITLE)
    if not (0 < n_chan <= _N_DESCRIPTORS) or n_rec < 0:
        raise LookFormatError(f"{path}: header says {n_rec} records and {n_chan} channels; a look file "
                              f"has 1 to {_N_DESCRIPTORS} channels (is this a look file, big-endian?)")
    out = LookFile(title=_text(raw[:_TITLE]), path=str(path))
    offset = need
    for i in range(n_chan):
        name, units, gain, comment, n_elem = _DESCRIPTOR.unpack_from(raw, _HEADER + i * _DESCRIPTOR.size)
        if n_elem != n_rec:
            raise LookFormatError(f"{path}: channel {i} ({_text(name)!r}) holds {n_elem} values, "
                                  f"the header says {n_rec} records")
        end = offset + 4 * n_rec
        if end > len(raw):
            raise LookFormatError(f"{path}: channel {i} ({_text(name)!r}) runs past the end of the file "
                                  f"({len(raw)} bytes, {end} needed)")
        values = np.frombuffer(raw, dtype=">f4", count=n_rec, offset=offset).astype(float)
        out.channels.append(Channel(_text(name), _text(units), values, float(gain), _text(comment)))
        offset = end
    return out


_DELIMITED = re.compile(r"\s*[,\t;]\s*")
_BLANKS = re.compile(r"\s+")


def _cells(text: str) -> list[str]:
    """A line's cells: split at commas, tabs or semicolons when it has any (so a header
    cell may hold a space, ``time [s]``), else at blanks."""
    parts = _DELIMITED.split(text) if re.search(r"[,\t;]", text) else _BLANKS.split(text)
    return [c for c in parts if c]


def read_table(path: str | os.PathLike, names: list[str] | None = None) -> LookFile:
    """Read a plain text table (columns separated by commas, tabs, semicolons or blanks;
    ``#`` comments; an optional header line of names, ``name [unit]`` or ``name_unit``)
    into the same shape as :func:`read_look`. ``names`` overrides the header. A cell that
    is not a number is refused with its line and column."""
    path = Path(path)
    header, rows, width = None, [], None
    for lineno, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        cells = _cells(text)
        try:
            row = [float(c) for c in cells]
        except ValueError:
            if header is None and not rows:
                header = cells
                continue
            bad = next(c for c in cells if not _is_number(c))
            raise LookFormatError(f"{path}, line {lineno}: {bad!r} is not a number") from None
        if width is None:
            width = len(row)
        elif len(row) != width:
            raise LookFormatError(f"{path}, line {lineno}: {len(row)} columns where the table has {width}")
        rows.append(row)
    if not rows:
        raise LookFormatError(f"{path}: no rows of numbers")
    data = np.array(rows, float)
    names = list(names or header or [f"col{i + 1}" for i in range(width)])
    if len(names) != width:
        raise LookFormatError(f"{path}: {len(names)} column names for {width} columns")
    out = LookFile(title=path.stem, path=str(path))
    for i, n in enumerate(names):
        m = re.fullmatch(r"(.*?)\s*\[(.*)\]", n)
        name, unit = (m.group(1), m.group(2)) if m else (n, "")
        out.channels.append(Channel(name, unit, data[:, i].copy()))
    return out


def read_mat(path: str | os.PathLike) -> LookFile:
    """Read a MATLAB file's vectors as columns (every numeric variable of one dimension
    beyond the singleton ones, all of one length); refuse a file whose vectors differ in
    length, naming them."""
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    path = Path(path)
    try:
        raw = loadmat(path)
    except (MatReadError, ValueError, TypeError, OSError) as err:
        raise LookFormatError(f"{path}: not a MATLAB file scipy can read ({err})") from None
    cols = {k: np.ravel(v).astype(float) for k, v in raw.items()
            if not k.startswith("__") and isinstance(v, np.ndarray) and v.dtype.kind in "fiu"
            and sum(d > 1 for d in v.shape) == 1}
    if not cols:
        raise LookFormatError(f"{path}: no numeric vectors")
    lengths = {k: len(v) for k, v in cols.items()}
    if len(set(lengths.values())) > 1:
        raise LookFormatError(f"{path}: vectors of different lengths {lengths}")
    out = LookFile(title=path.stem, path=str(path))
    out.channels = [Channel(k, "", v) for k, v in cols.items()]
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
