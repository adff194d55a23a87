"""Compile CasADi Functions once per machine and keep them on disk.

Interpreting the slip model's expression graph dominates the cost of an integration
(measured: 3.6 ms interpreted against 0.39 ms compiled for one slip). CasADi can
JIT-compile a Function with the system C compiler (``jit`` with the ``shell`` compiler)
and embed the binary in its serialised form (``jit_serialize='embed'``), so a compiled
Function is saved under a key derived from its own serialised expression and reloaded in
a few milliseconds by every later process.

Environment:
    NANOFRICTOR_JIT=0        never compile (use the interpreted Functions)
    NANOFRICTOR_CACHE=DIR    where compiled Functions live
                             (default ~/.cache/nanofrictor/casadi-<version>)

When no compiler works the interpreted Function is used and a warning is logged once;
results are the same, only slower.

Where the binary lives. CasADi bakes the absolute path of the shared library it compiled
into the saved Function; loading (``Function.load``) opens that path, and only when no
file is there writes the embedded copy to it (re-creating its directory). With
``jit_temp_suffix`` (the default) every load also creates an empty ``jit_tmp*.c`` next to
it. Compiled in a temporary directory, each later process therefore re-created that
directory in /tmp and left a file in it per load. So the library is built under a fixed
name in the cache directory, ``<tag>_<key>.so`` next to ``<tag>-<key>.casadi``, and the
C name carries no temporary suffix: a load finds the library in place and writes
nothing. An entry whose library is missing (or one from before this layout) is compiled
again. A lock file in the cache directory keeps a compile from replacing a library while
another process loads it.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import re
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import casadi as ca

try:
    import fcntl
except ImportError:  # no POSIX file locks: concurrent first compiles are not serialised
    fcntl = None

__all__ = ["compiled", "cache_dir", "jit_enabled"]

log = logging.getLogger(__name__)
_lock = threading.Lock()
_memory: dict[str, ca.Function] = {}
_failed = False


def jit_enabled() -> bool:
    return os.environ.get("NANOFRICTOR_JIT", "1").strip().lower() not in ("0", "false", "no", "off")


def cache_dir() -> Path:
    root = os.environ.get("NANOFRICTOR_CACHE")
    base = Path(root) if root else Path.home() / ".cache" / "nanofrictor"
    return base / f"casadi-{ca.__version__}"


# CasADi prints this through Python's stderr each time an integrator with events is
# created or loaded (ten lines and more per fit, with a timestamp each): a statement about
# its API, not about the run. It is logged once instead (logger identify.model.compiled, debug).
EVENT_NOTICE = 'WARNING("Event support is experimental")'
_notice_logged = False
_stderr_lock = threading.RLock()  # (re-entrant: a build may itself call compiled())


@contextmanager
def held_stderr(then: Callable[[str], None]) -> Iterator[None]:
    """Hold what is written to ``sys.stderr`` meanwhile (CasADi writes through it) and
    hand it to ``then`` afterwards, the redirection undone. One redirection at a time:
    two threads' interleaved swaps, e.g. tasks of a dask worker, could leave sys.stderr
    pointing at a discarded buffer."""
    held = io.StringIO()
    with _stderr_lock:
        try:
            with contextlib.redirect_stderr(held):
                yield
        finally:
            then(held.getvalue())


def _pass_on_without_notice(text: str) -> None:
    global _notice_logged
    kept = [line for line in text.splitlines(keepends=True) if EVENT_NOTICE not in line]
    if len(kept) < len(text.splitlines()) and not _notice_logged:
        _notice_logged = True
        log.debug("CasADi: %s (shown once)", EVENT_NOTICE)
    if kept and sys.stderr is not None:
        sys.stderr.write("".join(kept))


def _without_event_notice():
    """What CasADi writes to stderr meanwhile, passed on without :data:`EVENT_NOTICE` lines;
    anything else it wrote is kept, in order."""
    return held_stderr(_pass_on_without_notice)


def compiled(build: Callable[[dict], ca.Function], tag: str = "f") -> ca.Function:
    """A compiled version of ``build(opts)`` (``opts`` are extra Function options).

    ``build({})`` must be cheap (it only creates the Function); its serialised form is
    the cache key, so a change of model, tolerance or grid gives a new entry.
    """
    with _without_event_notice():
        return _compiled(build, tag)


def _compiled(build: Callable[[dict], ca.Function], tag: str) -> ca.Function:
    global _failed
    plain = build({})
    if not jit_enabled() or _failed:
        return plain
    key = hashlib.sha1(plain.serialize().encode()).hexdigest()[:20]
    name = f"{tag}-{key}"
    with _lock:
        if name in _memory:
            return _memory[name]
        folder = cache_dir()
        path = folder / f"{name}.casadi"
        stem = re.sub(r"\W", "_", name)  # jit_name must be a C identifier
        lib = folder / f"{stem}{ca.CasadiMeta.shared_library_suffix()}"  # named in the file
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with _file_lock(folder, exclusive=False):
                fn = _load_or_none(path, lib)
            if fn is None:
                with _file_lock(folder, exclusive=True):
                    fn = _load_or_none(path, lib)  # another process may have compiled it meanwhile
                    if fn is None:
                        fn = _compile(build, folder, stem, path, lib)
                        log.info("compiled %s -> %s", tag, path)
        except Exception as err:  # no compiler, read-only cache, ...: stay interpreted
            _failed = True
            log.warning("CasADi JIT compilation unavailable (%s); using interpreted Functions "
                        "(same results, slower). Set NANOFRICTOR_JIT=0 to silence.", err)
            return plain
        _memory[name] = fn
        return fn


@contextmanager
def _file_lock(folder: Path, exclusive: bool) -> Iterator[None]:
    """Shared (load) or exclusive (compile) lock on ``folder/.lock``; none where no
    POSIX locks or the folder is read-only (loading still works there)."""
    try:
        fh = open(folder / ".lock", "a") if fcntl is not None else None
    except OSError:
        fh = None
    if fh is None:
        yield
        return
    with fh:
        fcntl.flock(fh, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _load_or_none(path: Path, lib: Path) -> ca.Function | None:
    """:func:`_load`, or None (the entry is then compiled again) when the entry cannot
    be loaded. How an entry breaks: CasADi writes a JIT'ed Function's derivative under
    the Function's own C name into its directory, so differentiating a cached Function
    (``ca.jtimes`` through the compiled arc, tried 2026-11-24) replaced the arc's
    library with another; every later process failed to load it and, before this,
    fell back to interpreted Functions for good: ten times slower (0.45 → 5.3 ms per
    arc, measured), with one warning."""
    try:
        return _load(path, lib)
    except Exception as err:
        log.warning("cached compiled Function %s cannot be loaded (%s); compiling it again",
                    path, str(err).strip().splitlines()[-1] if str(err).strip() else err)
        return None


def _load(path: Path, lib: Path) -> ca.Function | None:
    """The cached Function, if its entry and the library it names are both in place
    (else CasADi would write the library itself: see the module docstring)."""
    if path.exists() and lib.exists():
        return ca.Function.load(str(path))
    return None


def _compile(build: Callable[[dict], ca.Function], folder: Path, stem: str, path: Path,
             lib: Path) -> ca.Function:
    # a library left by an interrupted compile may be mapped by another process: unlink
    # it rather than let the linker rewrite it in place
    lib.unlink(missing_ok=True)
    scratch = [folder / f"{stem}{ext}" for ext in (".c", ca.CasadiMeta.object_file_suffix())]
    ok = False
    try:
        with tempfile.TemporaryDirectory(prefix="nanofrictor-jit-") as tmp:
            # an integrator JITs its dependencies to a C file in the cwd whatever the
            # options say (OracleFunction::jit_dependencies): compile from a scratch cwd
            cwd = os.getcwd()
            os.chdir(tmp)
            try:
                fn = build(dict(
                    compiler="shell", jit=True, jit_serialize="embed",
                    jit_name=stem, jit_temp_suffix=False,  # a load creates no jit_tmp*.c
                    jit_cleanup=False,  # (would warn on every later unload: no such file)
                    # directory must hold no whitespace (the shell command is not quoted)
                    jit_options=dict(flags=["-O2"], directory=str(folder) + os.sep, name=stem,
                                     temp_suffix=False, cleanup=False, verbose=False),
                ))
            finally:
                os.chdir(cwd)
        # atomic: a reader sees the whole entry or none
        fd, tmp_path = tempfile.mkstemp(dir=folder, suffix=".part")
        os.close(fd)
        try:
            fn.save(tmp_path)
            os.replace(tmp_path, path)
        finally:
            Path(tmp_path).unlink(missing_ok=True)
        ok = True
        return fn
    finally:
        for p in scratch:
            p.unlink(missing_ok=True)
        if not ok:
            lib.unlink(missing_ok=True)
