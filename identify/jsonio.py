"""Strict JSON for every file the toolkit writes.

JSON has no NaN or infinity: a value that is not a finite number (an undetermined
interval end, a χ² that could not be computed) is written as ``null``, so any strict
parser reads what we write. numpy scalars and arrays become Python numbers and lists,
paths become strings.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["jsonable", "dumps", "write_json", "SavedResult"]


def jsonable(x: Any) -> Any:
    """``x`` with every container rebuilt of plain JSON values (non-finite floats -> None)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, set, frozenset)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def dumps(data: Any, indent: int | None = 2) -> str:
    """Strict JSON text of ``data`` (raises ``ValueError`` rather than write NaN)."""
    return json.dumps(jsonable(data), indent=indent, allow_nan=False, ensure_ascii=False)


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as strict JSON to ``path`` (parent folders made), return the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(dumps(data) + "\n", encoding="utf-8")
    return p


class SavedResult:
    """The part of the result protocol every result shares: ``to_dict()`` (strict-JSON
    values), ``save(path)`` and ``load(path)``. A result class gives ``to_json()`` and
    ``from_dict(d)``; ``from_dict(r.to_dict())`` gives back a result with the same
    ``to_dict()``."""

    def to_json(self) -> dict:  # (each result writes its own)
        raise NotImplementedError

    def to_dict(self) -> dict:
        """The result as plain JSON values (null where a number is not finite)."""
        return jsonable(self.to_json())

    def save(self, path) -> Path:
        """Write the result as strict JSON to ``path``; :meth:`load` reads it back."""
        return write_json(path, self.to_dict())

    @classmethod
    def load(cls, path):
        """A result saved by :meth:`save` (or written by the command line's ``--json``)."""
        with open(path, encoding="utf-8") as fh:
            return cls.from_dict(json.load(fh))
