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
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
import threading
from pathlib import Path
from typing import Callable

import casadi as ca

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


def compiled(build: Callable[[dict], ca.Function], tag: str = "f") -> ca.Function:
    """A compiled version of ``build(opts)`` (``opts`` are extra Function options).

    ``build({})`` must be cheap (it only creates the Function); its serialised form is
    the cache key, so a change of model, tolerance or grid gives a new entry.
    """
    global _failed
    plain = build({})
    if not jit_enabled() or _failed:
        return plain
    key = hashlib.sha1(plain.serialize().encode()).hexdigest()[:20]
    name = f"{tag}-{key}"
    with _lock:
        if name in _memory:
            return _memory[name]
        path = cache_dir() / f"{name}.casadi"
        try:
            if path.exists():
                fn = ca.Function.load(str(path))
            else:
                path.parent.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryDirectory(prefix="nanofrictor-jit-") as tmp:
                    # CasADi writes the generated C file relative to the cwd whatever the
                    # options say; compile from inside the temporary directory
                    cwd = os.getcwd()
                    os.chdir(tmp)
                    try:
                        fn = build(dict(
                            jit=True, compiler="shell", jit_serialize="embed", jit_cleanup=False,
                            jit_options=dict(flags=["-O2"], directory=tmp + os.sep, verbose=False,
                                             cleanup=False),  # the temporary directory goes
                        ))
                    finally:
                        os.chdir(cwd)
                    # atomic: concurrent processes may compile the same Function
                    fd, tmp_path = tempfile.mkstemp(dir=path.parent, suffix=".part")
                    os.close(fd)
                    fn.save(tmp_path)
                    os.replace(tmp_path, path)
                log.info("compiled %s -> %s", tag, path)
        except Exception as err:  # no compiler, read-only cache, ...: stay interpreted
            _failed = True
            log.warning("CasADi JIT compilation unavailable (%s); using interpreted Functions "
                        "(same results, slower). Set NANOFRICTOR_JIT=0 to silence.", err)
            return plain
        _memory[name] = fn
        return fn
