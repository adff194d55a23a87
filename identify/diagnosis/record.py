"""A diagnosis's resumable record: the baseline fit, then every finished refit.

A diagnosis takes minutes to hours, most of it in independent refits. Each is appended
to the record the moment it finishes, so an interrupted diagnosis (Ctrl-C, a lost
machine) started again with ``resume`` takes the baseline and every finished refit from
the record and computes only the rest.

How a refit is recognised: every refit goes through the diagnosis's executor, and the
record's executor (:class:`RecordedExecutor`) keys each task by a digest of its content
(the function, its numbers, its runs: :func:`digest`), not by its place in the rounds. A
diagnosis resumed on the same data and options asks for the same tasks, in the same
order, and finds them; a task the record does not hold (the inputs moved) is simply
computed.

The record is a stream of pickles, appended and flushed one entry at a time: a
truncated last entry (the process killed while writing) is dropped on reading. It is a
file for the machine that made it to resume from, like a cache, not one to exchange:
unpickling runs code, so never resume from a record of unknown origin.
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import functools
import hashlib
import os
import pickle
import threading
from pathlib import Path

import numpy as np

__all__ = ["DiagnosisRecord", "RecordedExecutor", "digest", "inputs_digest"]

_VERSION = 1


def digest(obj) -> str:
    """A content digest of ``obj`` (numbers, arrays, containers, dataclasses and plain
    objects by their attributes, functions by name): equal for equal content, whatever
    the objects' identity or memory layout."""
    h = hashlib.sha256()
    _feed(h, obj, set())
    return h.hexdigest()


def _feed(h, obj, seen: set) -> None:
    if obj is None or isinstance(obj, (bool, int, str, bytes)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif isinstance(obj, float):
        h.update(f"f:{float(obj).hex()};".encode())
    elif isinstance(obj, np.generic):
        _feed(h, obj.item(), seen)
    elif isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        h.update(f"a:{a.dtype.str}:{a.shape};".encode())
        if a.dtype == object:
            for x in a.ravel():
                _feed(h, x, seen)
        else:
            h.update(a.tobytes())
    elif isinstance(obj, dict):
        h.update(f"d{len(obj)};".encode())
        for k in sorted(obj, key=lambda k: digest(k)):
            _feed(h, k, seen)
            _feed(h, obj[k], seen)
    elif isinstance(obj, (list, tuple, set, frozenset)):
        items = sorted(obj, key=digest) if isinstance(obj, (set, frozenset)) else obj
        h.update(f"{type(obj).__name__}{len(obj)};".encode())
        for x in items:
            _feed(h, x, seen)
    elif isinstance(obj, functools.partial):
        _feed(h, ("partial", obj.func, obj.args, obj.keywords), seen)
    elif callable(obj) and hasattr(obj, "__qualname__"):
        h.update(f"fn:{getattr(obj, '__module__', '')}.{obj.__qualname__};".encode())
    else:
        if id(obj) in seen:  # (a cycle: its place is enough)
            h.update(b"cycle;")
            return
        seen.add(id(obj))
        h.update(f"o:{type(obj).__module__}.{type(obj).__qualname__};".encode())
        if dataclasses.is_dataclass(obj):
            state = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
        elif hasattr(obj, "__dict__"):
            state = vars(obj)
        else:
            state = {s: getattr(obj, s) for s in getattr(type(obj), "__slots__", ()) if hasattr(obj, s)}
            if not state:
                try:
                    state = {"pickle": pickle.dumps(obj)}
                except Exception:  # noqa: BLE001 - (an object only its identity names: never reused)
                    state = {"id": id(obj)}
        _feed(h, state, seen)
        seen.discard(id(obj))


def inputs_digest(data, *rest) -> str:
    """What a record is for: the data (files and folders by their contents, objects by
    theirs) and the options that decide the diagnosis."""
    h = hashlib.sha256()
    items = [data] if isinstance(data, (str, bytes)) or hasattr(data, "__fspath__") else list(data or [])
    for item in items:
        if isinstance(item, (str, bytes)) or hasattr(item, "__fspath__"):
            p = Path(os.fsdecode(item))
            files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
            for f in files:
                h.update(f.name.encode())
                h.update(hashlib.sha256(f.read_bytes()).digest() if f.exists() else b"missing")
        else:
            h.update(digest(item).encode())
    h.update(digest(rest).encode())
    return h.hexdigest()


class DiagnosisRecord:
    """The record file: a header (what it is for), the baseline, finished refits."""

    def __init__(self, path, inputs: str, resume: bool = False):
        self.path = Path(path)
        self.inputs = inputs
        self.baseline = None
        self.results: dict[str, object] = {}
        self.resumed = 0  # refits taken from the record in this run
        self._lock = threading.Lock()
        if resume:
            if not self.path.exists():
                raise ValueError(f"resume: there is no record at {self.path} to resume from")
            self._read()
            self._file = open(self.path, "ab")  # noqa: SIM115 - open for the diagnosis's length
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")  # noqa: SIM115
            self._append(("header", _VERSION, inputs))

    def _read(self) -> None:
        entries = []
        with open(self.path, "rb") as f:
            while True:
                try:
                    entries.append(pickle.load(f))
                except EOFError:
                    break
                except (pickle.UnpicklingError, ValueError, AttributeError, ImportError, IndexError):
                    break  # (a truncated last entry: dropped)
        if not entries or entries[0][:2] != ("header", _VERSION):
            raise ValueError(f"resume: {self.path} is not a diagnosis record of this version")
        if entries[0][2] != self.inputs:
            raise ValueError(f"resume: {self.path} was made for other data or options; start again "
                             "without resume (the record is then replaced)")
        for kind, key, payload in (e for e in entries[1:] if len(e) == 3):
            if kind == "baseline":
                self.baseline = payload
            elif kind == "refit":
                self.results[key] = payload

    def _append(self, entry) -> None:
        with self._lock:
            pickle.dump(entry, self._file, protocol=pickle.HIGHEST_PROTOCOL)
            self._file.flush()

    def keep_baseline(self, result) -> None:
        """Record the baseline fit: its result without the problem, and what rebuilds the
        problem (runs, values, options, mode sequence)."""
        prob = result.problem
        bundle = dict(result=dataclasses.replace(result, problem=None), runs=prob.runs, values=prob.values,
                      opts=prob.opts, ev_M=np.array(prob.ev_M), law=prob.law.name,
                      regime_runs=list(getattr(result, "regime_runs", None) or []))
        self.baseline = bundle
        self._append(("baseline", None, bundle))

    def restored_baseline(self):
        """The recorded baseline fit with its problem rebuilt, or None."""
        if self.baseline is None:
            return None
        from identify.fitting.problem import Problem
        from identify.model.laws import get_law
        from identify.model.symbolic import Model

        b = self.baseline
        prob = Problem(b["runs"], Model(get_law(b["law"])), dict(b["values"]), b["opts"])
        if len(b["ev_M"]) == prob.E:
            prob.ev_M = np.array(b["ev_M"])
        prob.build()
        res = dataclasses.replace(b["result"], problem=prob)
        res.regime_runs = b["regime_runs"]
        return res

    def keep(self, key: str, result) -> None:
        self.results[key] = result
        self._append(("refit", key, result))

    def close(self) -> None:
        with self._lock:
            self._file.close()


class RecordedExecutor(cf.Executor):
    """An executor that takes a task's result from the record when it holds one, and
    records every result that finishes (an exception is not recorded: it is computed
    again on a resume)."""

    def __init__(self, inner: cf.Executor, record: DiagnosisRecord):
        self.inner, self.record = inner, record

    def submit(self, fn, *args, **kwargs):
        """A future of ``fn(*args, **kwargs)``: done at once when the record holds it."""
        key = digest((fn, args, kwargs))
        if key in self.record.results:
            f: cf.Future = cf.Future()
            f.set_result(self.record.results[key])
            self.record.resumed += 1
            return f
        fut = self.inner.submit(fn, *args, **kwargs)

        def done(f, key=key):
            if not f.cancelled() and f.exception() is None:
                self.record.keep(key, f.result())

        fut.add_done_callback(done)
        return fut

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False):
        """Shut the wrapped executor down."""
        self.inner.shutdown(wait=wait, cancel_futures=cancel_futures)
