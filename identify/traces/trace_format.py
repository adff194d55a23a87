"""The trace format's name and the error that every broken rule of it raises.

Kept apart so that the checks of the samples, of the conditions and the :class:`Trace`
class can all raise :class:`TraceFormatError` without importing one another.
"""

from __future__ import annotations

import os

__all__ = ["FORMAT", "TraceFormatError"]

FORMAT = "nanofrictor-trace/1"
"""Value of the ``format`` key of every trace's JSON file."""


class TraceFormatError(ValueError):
    """A trace file breaks a rule of the format.

    Attributes
    ----------
    path : str
        The offending file.
    line : int or None
        1-based physical line number in that file (comment lines counted), or None
        when the rule concerns the whole file.
    rule : str
        What is wrong, in words.
    """

    def __init__(self, path: str | os.PathLike, line: int | None, rule: str):
        self.path = str(path)
        self.line = line
        self.rule = rule
        super().__init__(str(self))

    def __str__(self) -> str:
        if self.line is None:
            return f"{self.path}: {self.rule}"
        return f"{self.path}:{self.line}: {self.rule}"

    def __reduce__(self):
        # The default reduction would call __init__ with the formatted message only
        # (multiprocessing / dask pickle exceptions).
        return (type(self), (self.path, self.line, self.rule))
