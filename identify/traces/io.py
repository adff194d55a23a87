"""Recorded traces: read, check and write the trace format (``shared/TRACE_FORMAT.md``).

One run is two files with the same stem: ``RUN.csv`` (time in s, spring elongation in
µm, optionally the puller position in µm, one row per camera frame) and ``RUN.json``
(the run's conditions). :class:`Trace` holds one run in SI units; :func:`load_traces`
reads files and folders into a :class:`TraceSet` that keeps the good runs and the
reasons every refused run was refused, so one bad file never loses a batch.

Every rule of the format is enforced on read, and a violation raises
:class:`TraceFormatError` naming the file, the physical line (1-based, comments and
all) and the rule.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from identify.model.params import SPECS, ParameterError, normal_load_from_voltage
from identify.model.plausible import PLATFORM_RANGES, platform_problem

__all__ = [
    "FORMAT",
    "TraceFormatError",
    "Trace",
    "TraceSet",
    "load_traces",
    "trace_paths",
]

FORMAT = "nanofrictor-trace/1"
"""Value of the ``format`` key of every trace's JSON file."""

_HEADERS = (("time_s", "elongation_um"), ("time_s", "elongation_um", "puller_um"))
_HEADER_TEXT = " or ".join(repr(",".join(h)) for h in _HEADERS)

# Printed precision of the CSV: 1 ns and 1 pm are far below the camera's resolution, and
# fixed decimals make a write -> read -> write cycle byte-identical.
_TIME_FMT = "%.9f"
_LENGTH_FMT = "%.6f"

# Key order of the JSON file: format first, then who/what, then conditions, then notes;
# keys not listed here follow in sorted order so the output never depends on how the
# dict was built.
_KEY_ORDER = (
    "format",
    "coating",
    "device",
    "spring_constant_N_per_m",
    "normal_load_uN",
    "block_voltage_V",
    "step_frequency_Hz",
    "step_size_nm",
    "frame_rate_Hz",
    "block_mass_kg",
    "notes",
)
_POSITIVE_REQUIRED = ("spring_constant_N_per_m", "step_frequency_Hz")
_POSITIVE_OPTIONAL = ("step_size_nm", "frame_rate_Hz", "block_mass_kg")
_TEXT_OPTIONAL = ("coating", "device", "notes")

# A decimal number as the format allows it (what np.loadtxt and humans agree on); the
# slow path uses this instead of float(), which would also take "1_000" or " nan ".
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


# ----------------------------------------------------------------------------- errors
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


# ----------------------------------------------------------------------------- CSV
def _split_lines(text: str) -> list[str]:
    """Physical lines of ``text`` (universal newlines already applied), no terminator."""
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()  # the terminator of the last line is not a blank line
    return lines


def _is_comment(line: str) -> bool:
    return line.lstrip().startswith("#")


def _read_text(path: Path) -> str:
    """UTF-8 text of ``path`` (a BOM, as spreadsheets write, is dropped)."""
    raw = path.read_bytes()
    try:
        return raw.decode("utf-8-sig").replace("\r\n", "\n").replace("\r", "\n")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise TraceFormatError(path, line, "not UTF-8 text") from None


def _parse_header(path: Path, lines: list[str]) -> tuple[int, tuple[str, ...]]:
    """Index of the header line and its column names."""
    for i, line in enumerate(lines):
        if _is_comment(line):
            continue
        if not line.strip():
            raise TraceFormatError(path, i + 1, "blank line")
        names = tuple(c.strip() for c in line.split(","))
        if names not in _HEADERS:
            raise TraceFormatError(
                path, i + 1, f"bad header {line.strip()!r}: expected {_HEADER_TEXT}"
            )
        return i, names
    raise TraceFormatError(path, None, f"no header line: expected {_HEADER_TEXT}")


def _check_cell(cell: str, column: str) -> str | None:
    """Why ``cell`` is not a valid number of ``column``, or None if it is."""
    s = cell.strip()
    if not s:
        return f"blank cell in column {column}"
    if _NUMBER.fullmatch(s):
        return None
    if _NONFINITE.fullmatch(s):
        return f"{s!r} in column {column}: values must be finite numbers"
    return f"{s!r} in column {column} is not a number"


def _scan_rows(path: Path, lines: list[str], header: int, names: tuple[str, ...]) -> None:
    """Line-by-line check of the data rows; raises at the first offending line.

    Only called when the vectorised parse found a problem, so clarity beats speed here.
    """
    ncol = len(names)
    previous_time: float | None = None
    for i in range(header + 1, len(lines)):
        line = lines[i]
        if _is_comment(line):
            continue
        if not line.strip():
            raise TraceFormatError(path, i + 1, "blank line")
        cells = line.split(",")
        if len(cells) != ncol:
            raise TraceFormatError(
                path, i + 1, f"expected {ncol} cells ({','.join(names)}), found {len(cells)}"
            )
        for cell, column in zip(cells, names):
            why = _check_cell(cell, column)
            if why is not None:
                raise TraceFormatError(path, i + 1, why)
        t = float(cells[0])
        if previous_time is not None and t <= previous_time:
            kind = "duplicate" if t == previous_time else "decreasing"
            raise TraceFormatError(
                path, i + 1,
                f"{kind} time: time_s = {cells[0].strip()} after {previous_time!r}; "
                "times must strictly increase",
            )
        previous_time = t


def _parse_csv(path: Path) -> tuple[np.ndarray, tuple[str, ...]]:
    """Checked samples of a trace CSV: array (n_rows, n_cols) in file units, and names."""
    text = _read_text(path)
    lines = _split_lines(text)
    if not lines:
        raise TraceFormatError(path, None, f"empty file: expected the header {_HEADER_TEXT}")
    header, names = _parse_header(path, lines)
    body = lines[header + 1:]
    # Fast path: drop comments, hand the rest to numpy's C parser, check with array
    # operations. np.loadtxt silently skips blank lines, so those are looked for here.
    data = [ln for ln in body if not _is_comment(ln)]
    clean = all(ln.strip() for ln in data)
    values: np.ndarray | None = None
    parse_error: Exception | None = None
    if clean and data:
        try:
            values = np.loadtxt(data, delimiter=",", comments=None, ndmin=2, dtype=np.float64)
        except ValueError as exc:
            parse_error = exc
    if values is not None:
        ok = (
            values.shape[1] == len(names)
            and bool(np.isfinite(values).all())
            and bool((np.diff(values[:, 0]) > 0).all())
        )
        if ok:
            if len(values) < 2:
                raise TraceFormatError(
                    path, None, f"at least 2 data rows are needed, found {len(values)}"
                )
            return values, names
    # Slow path: find and name the first offending line.
    _scan_rows(path, lines, header, names)
    if not data:
        raise TraceFormatError(path, None, "at least 2 data rows are needed, found 0")
    # The scan accepted every line although numpy did not: report numpy's reason.
    raise TraceFormatError(path, None, f"cannot parse the samples: {parse_error}")


# ----------------------------------------------------------------------------- JSON
def _key_line(text: str | None, key: str) -> int | None:
    """Line of the first ``"key":`` in ``text`` (None if absent or no text)."""
    if text is None:
        return None
    m = re.search(r'"' + re.escape(key) + r'"\s*:', text)
    return None if m is None else text.count("\n", 0, m.start()) + 1


def _is_number(v: Any) -> bool:
    # bool is an int subclass; true/false are not numbers in this format
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check_metadata(meta: Mapping[str, Any], path: str | Path, text: str | None = None) -> None:
    """Check the conditions of a run against the format; ``text`` locates lines."""

    def fail(key: str | None, rule: str) -> NoReturn:
        raise TraceFormatError(path, _key_line(text, key) if key else None, rule)

    if "format" not in meta:
        fail(None, f"missing required key 'format' (must be {FORMAT!r})")
    if meta["format"] != FORMAT:
        fail("format", f"format must be {FORMAT!r}, found {meta['format']!r}")
    for key in _POSITIVE_REQUIRED:
        if key not in meta:
            fail(None, f"missing required key {key!r}")
    for key in _POSITIVE_REQUIRED + _POSITIVE_OPTIONAL:
        if key in meta:
            v = meta[key]
            if not _is_number(v) or not math.isfinite(v) or v <= 0:
                fail(key, f"{key} = {v!r}: must be a finite number > 0")
    has_load, has_voltage = "normal_load_uN" in meta, "block_voltage_V" in meta
    if has_load and has_voltage:
        fail("block_voltage_V", "give exactly one of normal_load_uN or block_voltage_V, not both")
    if not (has_load or has_voltage):
        fail(None, "missing the normal load: give exactly one of normal_load_uN or block_voltage_V")
    if has_load:
        v = meta["normal_load_uN"]
        if not _is_number(v) or not math.isfinite(v) or v <= 0:
            fail("normal_load_uN", f"normal_load_uN = {v!r}: must be a finite number > 0")
    else:
        v = meta["block_voltage_V"]
        if not _is_number(v) or not math.isfinite(v):
            fail("block_voltage_V", f"block_voltage_V = {v!r}: must be a finite number")
        try:
            normal_load_from_voltage(v)
        except ParameterError as exc:
            fail("block_voltage_V", str(exc))
    for key in _TEXT_OPTIONAL:
        v = meta.get(key)
        if v is not None and not isinstance(v, str):
            fail(key, f"{key} = {v!r}: must be text")
    outside = meta.get("outside_platform_ranges", False)
    if not isinstance(outside, bool):
        fail("outside_platform_ranges", f"outside_platform_ranges = {outside!r}: must be true or false")
    if not outside:
        for key in PLATFORM_RANGES:
            if key in meta and (problem := platform_problem(key, float(meta[key]))):
                fail(key, problem)


def _parse_json(path: Path) -> dict:
    """Checked metadata of a trace JSON file."""
    text = _read_text(path)

    def pairs(items: list[tuple[str, Any]]) -> dict:
        out: dict = {}
        for k, v in items:
            if k in out:
                # json would keep the last value silently; a duplicated condition is
                # ambiguous, so refuse it
                raise TraceFormatError(path, _key_line(text, k), f"duplicate key {k!r}")
            out[k] = v
        return out

    def constant(name: str) -> NoReturn:
        m = re.search(r"(?<![\w\"])-?" + re.escape(name.lstrip("-")), text)
        line = None if m is None else text.count("\n", 0, m.start()) + 1
        raise TraceFormatError(path, line, f"invalid JSON: {name} is not a JSON number")

    try:
        meta = json.loads(text, object_pairs_hook=pairs, parse_constant=constant)
    except json.JSONDecodeError as exc:
        raise TraceFormatError(path, exc.lineno, f"invalid JSON: {exc.msg}") from None
    if not isinstance(meta, dict):
        raise TraceFormatError(path, None, "the JSON content must be an object {...}")
    _check_metadata(meta, path, text)
    return meta


def _ordered(meta: Mapping[str, Any]) -> dict:
    known = [k for k in _KEY_ORDER if k in meta]
    rest = sorted(k for k in meta if k not in _KEY_ORDER)
    return {k: meta[k] for k in known + rest}


def _json_default(obj: Any) -> Any:
    # numpy scalars and arrays sneak into metadata from simulation results
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _tidy(x: float) -> float:
    """``x`` to 12 significant digits: hides the last-bit noise of unit conversions
    (5e-6 N × 1e6 = 4.999999999999999 µN) in the JSON a person reads."""
    return float(f"{float(x):.12g}")


# ----------------------------------------------------------------------------- paths
def _stem_of(path: str | os.PathLike) -> Path:
    """The stem path of a run from ``RUN.csv``, ``RUN.json`` or ``RUN``."""
    p = Path(path)
    if p.suffix.lower() in (".csv", ".json"):
        return p.with_suffix("")
    return p


def _pair(stem: Path) -> tuple[Path, Path]:
    # string concatenation, not with_suffix: a stem such as "run.07" has a dot
    return Path(str(stem) + ".csv"), Path(str(stem) + ".json")


def trace_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """The (CSV, JSON) files of the run at ``path`` (``RUN``, ``RUN.csv`` or ``RUN.json``),
    as :meth:`Trace.write` names them."""
    return _pair(_stem_of(path))


# ----------------------------------------------------------------------------- Trace
@dataclass(eq=False)
class Trace:
    """One recorded (or simulated) run: samples in SI and the run's conditions.

    Parameters
    ----------
    name : str
        Run name, the file stem (``run07``).
    time_s : ndarray, shape (n,)
        Frame times, s, strictly increasing, n >= 2.
    elongation : ndarray, shape (n,)
        Measured spring elongation e = xp − x, m.
    puller : ndarray, shape (n,) or None
        Measured puller (nanotractor) position, m, when it was tracked.
    metadata : dict
        The JSON content (format keys with units in their names; unknown keys kept).
        ``format`` is added when missing; the dict is copied.
    path : Path or None
        Stem path the trace was read from or last written to.

    Raises
    ------
    TraceFormatError
        If the samples or the metadata break a rule of the format (``path`` of the
        error is ``<trace NAME>``, line None).
    """

    name: str
    time_s: np.ndarray
    elongation: np.ndarray
    puller: np.ndarray | None
    metadata: dict
    path: Path | None = None

    def __post_init__(self):
        where = f"<trace {self.name}>"
        self.time_s = np.ascontiguousarray(self.time_s, dtype=np.float64)
        self.elongation = np.ascontiguousarray(self.elongation, dtype=np.float64)
        if self.puller is not None:
            self.puller = np.ascontiguousarray(self.puller, dtype=np.float64)
        n = self.time_s.shape
        for label, arr in (("time_s", self.time_s), ("elongation", self.elongation),
                           ("puller", self.puller)):
            if arr is None:
                continue
            if arr.ndim != 1 or arr.shape != n:
                raise TraceFormatError(
                    where, None, f"{label} must be 1-D with the length of time_s {n}, has shape {arr.shape}"
                )
            if not np.isfinite(arr).all():
                raise TraceFormatError(where, None, f"{label} holds non-finite values")
        if n[0] < 2:
            raise TraceFormatError(where, None, f"at least 2 samples are needed, found {n[0]}")
        if not (np.diff(self.time_s) > 0).all():
            raise TraceFormatError(where, None, "time_s must strictly increase")
        meta = dict(self.metadata)
        meta.setdefault("format", FORMAT)
        _check_metadata(meta, where)
        self.metadata = _ordered(meta)
        if self.path is not None:
            self.path = Path(self.path)

    def __len__(self) -> int:
        """Number of frames."""
        return len(self.time_s)

    def __repr__(self) -> str:
        return (
            f"Trace({self.name!r}, {len(self)} frames, {self.time_s[0]:g}..{self.time_s[-1]:g} s, "
            f"k={self.spring_constant:g} N/m, Nb={self.normal_load * 1e6:.3g} µN, "
            f"fp={self.step_frequency:g} Hz"
            + (", with puller" if self.puller is not None else "")
            + ")"
        )

    # ------------------------------------------------------------- conditions (SI)
    @property
    def spring_constant(self) -> float:
        """k, N/m."""
        return float(self.metadata["spring_constant_N_per_m"])

    @property
    def normal_load(self) -> float:
        """Nb, N: ``normal_load_uN``, or the electrostatic model (Eqs. 5-6) applied to
        ``block_voltage_V``."""
        if "normal_load_uN" in self.metadata:
            return float(self.metadata["normal_load_uN"]) * 1e-6
        return float(normal_load_from_voltage(self.metadata["block_voltage_V"]))

    @property
    def step_frequency(self) -> float:
        """fp, Hz."""
        return float(self.metadata["step_frequency_Hz"])

    @property
    def step_size(self) -> float:
        """Nominal puller step Δxp, m (``step_size_nm``, default the platform's)."""
        if "step_size_nm" in self.metadata:
            return float(self.metadata["step_size_nm"]) * 1e-9
        return SPECS["step_size"].nominal

    @property
    def frame_rate(self) -> float:
        """Camera frame rate, Hz (``frame_rate_Hz``, else from the median frame interval)."""
        if "frame_rate_Hz" in self.metadata:
            return float(self.metadata["frame_rate_Hz"])
        return float(1.0 / np.median(np.diff(self.time_s)))

    @property
    def block_mass(self) -> float:
        """Effective block mass mb, kg (``block_mass_kg``, default the platform's)."""
        if "block_mass_kg" in self.metadata:
            return float(self.metadata["block_mass_kg"])
        return SPECS["mb"].nominal

    @property
    def coating(self) -> str | None:
        return self.metadata.get("coating")

    @property
    def device(self) -> str | None:
        return self.metadata.get("device")

    # ------------------------------------------------------------- files
    def write(self, stem: str | os.PathLike) -> tuple[Path, Path]:
        """Write ``STEM.csv`` and ``STEM.json`` (parent folders are created).

        Parameters
        ----------
        stem : str or PathLike
            Path without extension (a ``.csv``/``.json`` suffix is dropped).

        Returns
        -------
        (Path, Path)
            The CSV and JSON paths. ``self.path`` becomes the stem.

        Raises
        ------
        TraceFormatError
            If the metadata no longer pass the format's rules, or if two frame times
            are closer than the printed precision (1 ns) and would read back as equal.
        """
        stem_path = _stem_of(stem)
        csv_path, json_path = _pair(stem_path)
        meta = dict(self.metadata)
        meta.setdefault("format", FORMAT)
        _check_metadata(meta, json_path)  # the metadata dict may have been edited
        t_printed = np.round(self.time_s, 9)
        bad = np.flatnonzero(np.diff(t_printed) <= 0)
        if bad.size:
            raise TraceFormatError(
                csv_path, None,
                f"frames {bad[0]} and {bad[0] + 1} are closer than 1 ns and would be "
                "written with equal times",
            )
        columns = [self.time_s, self.elongation * 1e6]
        header = "time_s,elongation_um"
        fmt = [_TIME_FMT, _LENGTH_FMT]
        if self.puller is not None:
            columns.append(self.puller * 1e6)
            header += ",puller_um"
            fmt.append(_LENGTH_FMT)
        buf = io.StringIO()
        np.savetxt(buf, np.column_stack(columns), fmt=fmt, delimiter=",",
                   header=header, comments="")
        stem_path.parent.mkdir(parents=True, exist_ok=True)
        with open(csv_path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(buf.getvalue())
        text = json.dumps(_ordered(meta), indent=2, ensure_ascii=False, allow_nan=False,
                          default=_json_default)
        with open(json_path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text + "\n")
        self.path = stem_path
        return csv_path, json_path

    @classmethod
    def read(cls, path: str | os.PathLike) -> Trace:
        """Read one run from ``RUN.csv``, ``RUN.json`` or the stem ``RUN``.

        Raises
        ------
        FileNotFoundError
            If neither file of the run exists.
        TraceFormatError
            If one of the two files is missing or breaks a rule of the format.
        """
        stem = _stem_of(path)
        csv_path, json_path = _pair(stem)
        has_csv, has_json = csv_path.is_file(), json_path.is_file()
        if not (has_csv or has_json):
            raise FileNotFoundError(
                f"{path}: no such trace (looked for {csv_path.name} and {json_path.name} "
                f"in {csv_path.parent})"
            )
        if not has_json:
            raise TraceFormatError(csv_path, None, f"missing {json_path.name} (the run's conditions)")
        if not has_csv:
            raise TraceFormatError(json_path, None, f"missing {csv_path.name} (the run's samples)")
        meta = _parse_json(json_path)
        values, names = _parse_csv(csv_path)
        # file units -> SI: divide rather than multiply by 1e-6 so that printing the
        # value back in µm gives the same digits
        return cls(
            name=stem.name,
            time_s=values[:, 0],
            elongation=values[:, 1] / 1e6,
            puller=values[:, 2] / 1e6 if len(names) == 3 else None,
            metadata=meta,
            path=stem,
        )

    @classmethod
    def from_simulation(
        cls,
        result,
        time_s: np.ndarray,
        elongation_m: np.ndarray,
        name: str = "run",
        extra: Mapping[str, Any] | None = None,
    ) -> Trace:
        """A trace of a simulated run (what :meth:`SimulationResult.sample` returns).

        Parameters
        ----------
        result : identify.simulation.hybrid.SimulationResult
            The run; its conditions and parameters fill the metadata, and the
            ``simulation`` key records law, parameters (SI), regime and slip count.
        time_s : ndarray
            Frame times, s.
        elongation_m : ndarray
            Sampled elongation, m.
        name : str
            Run name.
        extra : mapping, optional
            Metadata keys that override or add to the generated ones; a None value
            removes a key.

        Notes
        -----
        ``step_size_nm`` is the nominal step (``step_size``), not the effective one
        (``step_size·step_scale``): the file records what the experimenter would
        believe. ``frame_rate_Hz`` comes from ``extra`` or the median frame interval.
        """
        c = result.conditions
        P = result.parameters
        t = np.asarray(time_s, dtype=np.float64)
        meta: dict[str, Any] = {
            "format": FORMAT,
            "coating": result.coating,
            "spring_constant_N_per_m": float(c.spring_constant),
            "normal_load_uN": _tidy(c.normal_load * 1e6),
            "step_frequency_Hz": float(c.step_frequency),
            "step_size_nm": _tidy(P["step_size"] * 1e9),
            "frame_rate_Hz": _tidy(1.0 / np.median(np.diff(t))) if t.size >= 2 else None,
            "block_mass_kg": float(P["mb"]),
            "notes": "synthetic: simulated by nanofrictor",
            "simulation": {
                "law": result.model.law.name,
                "parameters": {k: float(v) for k, v in P.items()},
                "regime": result.regime,
                "n_slips": int(len(result.events)),
                "initial_elongation_m": float(c.initial_elongation),
            },
        }
        if any(platform_problem(k, float(meta[k])) for k in PLATFORM_RANGES if meta.get(k) is not None):
            meta["outside_platform_ranges"] = True  # (simulated so on purpose: readable again)
        meta.update(extra or {})
        meta = {k: v for k, v in meta.items() if v is not None}
        return cls(name=name, time_s=t, elongation=elongation_m, puller=None, metadata=meta)


# ----------------------------------------------------------------------------- sets
@dataclass
class TraceSet:
    """Runs loaded by :func:`load_traces` and the files that were refused.

    Attributes
    ----------
    traces : list of Trace
        The good runs, in load order.
    errors : list of TraceFormatError
        One per refused run, naming file, line and rule.
    """

    traces: list[Trace] = field(default_factory=list)
    errors: list[TraceFormatError] = field(default_factory=list)

    def __iter__(self) -> Iterator[Trace]:
        return iter(self.traces)

    def __len__(self) -> int:
        return len(self.traces)

    def __getitem__(self, key: int | str) -> Trace:
        """A trace by position or by name (the first with that name)."""
        if isinstance(key, str):
            for tr in self.traces:
                if tr.name == key:
                    return tr
            raise KeyError(f"no trace named {key!r}; loaded: {', '.join(self.names) or 'none'}")
        return self.traces[key]

    @property
    def names(self) -> list[str]:
        return [tr.name for tr in self.traces]

    def report(self) -> str:
        """Plain-text list of the loaded runs and of the refused files with reasons."""
        out = [f"loaded {len(self.traces)} run{'s' if len(self.traces) != 1 else ''}"
               + (":" if self.traces else "")]
        for tr in self.traces:
            where = f"  ({tr.path})" if tr.path is not None else ""
            out.append(
                f"  {tr.name}: {len(tr)} frames, {tr.time_s[-1] - tr.time_s[0]:.4g} s, "
                f"k = {tr.spring_constant:g} N/m, Nb = {tr.normal_load * 1e6:.4g} µN, "
                f"fp = {tr.step_frequency:g} Hz"
                + (f", {tr.coating}" if tr.coating else "")
                + where
            )
        if self.errors:
            out.append(f"refused {len(self.errors)} run{'s' if len(self.errors) != 1 else ''}:")
            out.extend(f"  {e}" for e in self.errors)
        return "\n".join(out)


def _runs_in(folder: Path, recursive: bool) -> list[Path]:
    """Stems of the runs in ``folder``: every ``*.csv`` (sorted by path).

    A CSV without its JSON is kept so that reading it reports the missing file; a
    lone JSON is ignored, as folders of runs may also hold other JSON (fit results).
    """
    pattern = "**/*.csv" if recursive else "*.csv"
    csvs = [p for p in folder.glob(pattern) if p.is_file()]
    return [p.with_suffix("") for p in sorted(csvs, key=lambda p: p.relative_to(folder).as_posix())]


def load_traces(
    paths: str | os.PathLike | Iterable[str | os.PathLike], *, recursive: bool = False
) -> TraceSet:
    """Load runs from files and folders; a bad run is refused, never fatal.

    Parameters
    ----------
    paths : path or iterable of paths
        Each a run (``RUN.csv``, ``RUN.json`` or the stem ``RUN``) or a folder (every
        ``*.csv`` in it, by name; a CSV without its JSON is reported as refused).
    recursive : bool
        Also look in sub-folders of the folders.

    Returns
    -------
    TraceSet
        The good runs in the order given (folders expanded in name order), each stem
        once, and a :class:`TraceFormatError` per refused run. An empty folder gives
        an empty set.

    Raises
    ------
    FileNotFoundError
        For a path that is neither a folder nor a run.
    """
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    # stems to read, or the error of a file that is no trace at all, in argument order
    items: list[Path | TraceFormatError] = []
    for p in map(Path, paths):
        if p.is_dir():
            items.extend(_runs_in(p, recursive))
            continue
        if p.is_file() and p.suffix.lower() not in (".csv", ".json"):
            items.append(TraceFormatError(p, None, "not a trace file (expected RUN.csv or RUN.json)"))
            continue
        stem = _stem_of(p)
        csv_path, json_path = _pair(stem)
        if not (p.exists() or csv_path.exists() or json_path.exists()):
            raise FileNotFoundError(f"{p}: no such file, folder or run (STEM.csv + STEM.json)")
        items.append(stem)
    out = TraceSet()
    seen: set[Path] = set()
    for item in items:
        if isinstance(item, TraceFormatError):
            out.errors.append(item)
            continue
        key = item.resolve()
        if key in seen:
            continue
        seen.add(key)
        try:
            out.traces.append(Trace.read(item))
        except TraceFormatError as exc:
            out.errors.append(exc)
    return out
