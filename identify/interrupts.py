"""Ctrl-C that lands, even inside CasADi.

A ``KeyboardInterrupt`` raised while CasADi runs one of our Python callbacks (the slip
arcs inside the NLP's Functions, Ipopt's iteration callback) comes back out of CasADi as
a ``RuntimeError``, which the fit's "this trial point could not be integrated" handlers
take for a failed arc: the interrupt was swallowed and the fit finished. So an interrupt
is remembered here as well as raised, and the long loops call :func:`check` at points
outside CasADi, where a ``KeyboardInterrupt`` propagates as Python means it to.

The remembering is done by a SIGINT handler that :func:`honoured` installs for the
length of a long call (only in the main thread, and only over Python's default handler:
a handler the caller installed is called after the note is taken), and by the callbacks
themselves (:func:`note`) for interrupts raised some other way.
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["Interrupted", "caused_by_interrupt", "check", "honoured", "note", "pending"]

_pending = False
_depth = 0


class Interrupted(KeyboardInterrupt):
    """An interrupt with what was finished before it: ``saved`` is the partial result
    (a dict, JSON-ready) the interrupted call hands its caller, ``what`` says in words
    what it holds."""

    def __init__(self, what: str = "", saved: dict | None = None):
        super().__init__(what)
        self.what, self.saved = what, saved


def note() -> None:
    """Remember that an interrupt arrived (called where one is caught inside CasADi)."""
    global _pending
    _pending = True


def pending() -> bool:
    """Whether an interrupt arrived that has not reached the caller yet."""
    return _pending


def caused_by_interrupt(err: BaseException) -> bool:
    """Whether ``err`` is what an interrupt became on its way out of C code: an interrupt
    is pending, or ``err`` was raised from or during one (a ``KeyboardInterrupt`` that
    lands inside CasADi's conversion to an array comes out as a ``SystemError``, "returned
    a result with an exception set")."""
    seen, e = set(), err
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return _pending


def check() -> None:
    """Raise ``KeyboardInterrupt`` if an interrupt arrived: called at points outside
    CasADi, where it propagates. Inside :func:`honoured` the note stays until the
    outermost call ends (a handler that swallows the first raise meets the next check);
    outside, this raise is the interrupt's one delivery."""
    global _pending
    if _pending:
        if _depth == 0:
            _pending = False
        raise KeyboardInterrupt


@contextlib.contextmanager
def honoured():
    """For the length of a long call: SIGINT is noted before it is raised, so that
    :func:`check` sees it wherever CasADi turned it into an error. Nested calls share
    the outermost's handler; the note is cleared when the outermost call ends."""
    global _depth, _pending
    install = _depth == 0 and threading.current_thread() is threading.main_thread()
    previous = signal.getsignal(signal.SIGINT) if install else None

    def handler(signum, frame):
        note()
        if callable(previous) and previous is not signal.default_int_handler:
            previous(signum, frame)
        else:
            raise KeyboardInterrupt

    if install and previous not in (signal.SIG_IGN, None):
        signal.signal(signal.SIGINT, handler)
    else:
        install = False
    _depth += 1
    try:
        yield
    finally:
        _depth -= 1
        if install:
            signal.signal(signal.SIGINT, previous)
        if _depth == 0:
            _pending = False
