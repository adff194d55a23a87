"""Repeated messages said once: a warning that recurs at every slip of a run (the same
words, other numbers) is shown a few times and then counted, so the one that matters is
not buried under hundreds of copies."""

from __future__ import annotations

import re
from collections.abc import Iterable

__all__ = ["summarise"]

_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def summarise(messages: Iterable[str], keep: int = 3) -> list[str]:
    """``messages`` with each kind (the same words once the numbers are left out) kept
    ``keep`` times, in order, and one line after the last kept one counting the rest."""
    messages = list(messages)
    kind = [_NUMBER.sub("#", m) for m in messages]
    total: dict[str, int] = {}
    for k in kind:
        total[k] = total.get(k, 0) + 1
    out, seen = [], {}
    for m, k in zip(messages, kind):
        seen[k] = seen.get(k, 0) + 1
        if seen[k] <= keep:
            out.append(m)
            if seen[k] == keep and total[k] > keep:
                out.append(f"... and {total[k] - keep} more like it")
    return out
