"""Progress of long calls: plain messages, counted stages with an estimated time left,
and a progress bar on a terminal.

Every long call (:func:`identify.fit`, :meth:`FitResult.profile`, :func:`identify.diagnose`,
:func:`identify.simulation.regimes.regime_map`, and ``design``'s ranges, experiment and
verification) takes ``progress``:

* ``None`` (the default): on a terminal or in a notebook, a bar per counted stage
  (profile points, solver starts, a diagnosis round's refits, ...) with its ETA, drawn
  by tqdm, and the other messages as lines; otherwise, e.g. in a batch job whose stderr
  is a file, the messages go to the ``identify`` logger at INFO;
* ``False``: nothing;
* a callable: it is called with each message. The message is a :class:`ProgressEvent`,
  a ``str`` (a callback that prints or logs it needs nothing more) that also carries,
  for a counted stage, ``stage``, ``done``, ``total``, ``elapsed_s`` and ``eta_s``.

Worker processes (the diagnosis's refits) never draw: their parent reports for them.
"""

from __future__ import annotations

import logging
import multiprocessing
import shutil
import sys
import time
from collections.abc import Callable

log = logging.getLogger("identify")

__all__ = ["ProgressEvent", "Stage", "reporter", "cli_reporter", "TerminalReporter"]


def _duration(s: float) -> str:
    s = max(0.0, float(s))
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


class ProgressEvent(str):
    """A progress message. As a string it reads ``message`` followed, for a counted
    stage, by ``[done/total, elapsed, ETA]``; the parts are attributes too (``stage``,
    ``message``, ``done``, ``total``, ``elapsed_s``, ``eta_s``; None where not counted)."""

    stage: str | None
    message: str
    done: int | None
    total: int | None
    elapsed_s: float | None

    def __new__(cls, message: str, stage: str | None = None, done: int | None = None, total: int | None = None,
                elapsed_s: float | None = None):
        eta = None
        if done is not None and total is not None and elapsed_s is not None and done > 0:
            eta = elapsed_s / done * max(total - done, 0)
        tail = ""
        if done is not None and total is not None:
            tail = f" [{done}/{total}" + (f", {_duration(elapsed_s)}" if elapsed_s is not None else "")
            tail += (f", about {_duration(eta)} left]" if eta is not None and done < total else "]")
        obj = super().__new__(cls, message + tail)
        obj.stage, obj.message, obj.done, obj.total, obj.elapsed_s = stage, message, done, total, elapsed_s
        obj._eta = eta
        return obj

    @property
    def eta_s(self) -> float | None:
        """Seconds left at the stage's mean pace so far (None before the first item)."""
        return self._eta


class Stage:
    """A counted stage of a long call: ``total`` items, each reported by :meth:`advance`
    with the time taken so far and an estimate of the time left."""

    def __init__(self, say: Callable[[str], None] | None, name: str, total: int):
        self.say, self.name, self.total, self.done = say, name, int(total), 0
        self.t0 = time.perf_counter()

    def start(self, note: str = "") -> None:
        """Say the stage has begun (0 of ``total`` done)."""
        if self.say is not None:
            self.say(ProgressEvent(f"{self.name}: {note}" if note else self.name, self.name, 0, self.total, 0.0))

    def advance(self, note: str = "", n: int = 1) -> None:
        """``n`` more items done; ``note`` says which."""
        self.done += n
        if self.say is not None:
            self.say(ProgressEvent(f"{self.name}: {note}" if note else self.name, self.name, self.done, self.total,
                                   time.perf_counter() - self.t0))


def _drawable() -> bool:
    """A terminal or a notebook to draw on, in the main process."""
    if multiprocessing.parent_process() is not None:
        return False
    if "ipykernel" in sys.modules:
        return True
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


class TerminalReporter:
    """Draws a tqdm bar per counted stage and writes the other messages above the bars.
    ``prefix`` starts every line (the CLI's ``[fit] ``)."""

    def __init__(self, prefix: str = ""):
        self.prefix = prefix
        self.bars: dict = {}

    def __call__(self, msg) -> None:
        from tqdm.auto import tqdm

        stage, done, total = getattr(msg, "stage", None), getattr(msg, "done", None), getattr(msg, "total", None)
        if stage is None or total is None:
            tqdm.write(f"{self.prefix}{msg}", file=sys.stderr)
            return
        bar = self.bars.get(stage)
        if bar is None:
            # (a terminal that reports no size, as a fresh pseudo-terminal does, gets no bar
            # at all from tqdm's own detection: shutil falls back on COLUMNS/LINES, then 100×24)
            size = shutil.get_terminal_size((100, 24))
            bar = self.bars[stage] = tqdm(total=total, desc=f"{self.prefix}{stage}", file=sys.stderr, leave=True,
                                          ncols=size.columns, nrows=size.lines, unit="")
        note = msg.message[len(stage) + 2:] if msg.message.startswith(stage + ": ") else ""
        bar.n = done
        bar.set_postfix_str(note[:60], refresh=False)
        bar.refresh()
        if done >= total:
            bar.close()
            del self.bars[stage]


def reporter(progress=None, prefix: str = "") -> Callable[[str], None] | None:
    """The callback a long call reports to, from its ``progress`` argument (see the
    module's description); None for ``False``."""
    if progress is False:
        return None
    if callable(progress):
        return progress
    if progress not in (None, True):
        raise TypeError(f"progress = {progress!r}: expected None, False or a callable taking a message")
    if _drawable():
        return TerminalReporter(prefix)
    return lambda msg: log.info("%s%s", prefix, msg)


def cli_reporter(prefix: str) -> Callable[[str], None]:
    """The command line's: bars on a terminal; otherwise each message as a line on
    stderr, a counted stage's with its count and time left."""
    if _drawable():
        return TerminalReporter(prefix)
    return lambda msg: print(f"{prefix}{msg}", file=sys.stderr, flush=True)
