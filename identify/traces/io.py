"""Recorded traces: one run as a :class:`Trace`, many as a :class:`TraceSet`
(``shared/TRACE_FORMAT.md``).

One run is two files with the same stem: ``RUN.csv`` (time in s, spring elongation in
µm, optionally the puller position in µm, one row per camera frame) and ``RUN.json``
(the run's conditions). :class:`Trace` holds one run in SI units; :func:`load_traces`
reads files and folders into a :class:`TraceSet` that keeps the good runs and the
reasons every refused run was refused, so one bad file never loses a batch.

Every rule of the format is enforced on read, and a violation raises
:class:`TraceFormatError` naming the file, the physical line (1-based, comments and
all) and the rule. The rules live in :mod:`identify.traces.trace_metadata` (the
conditions) and :mod:`identify.traces.trace_files` (the two files as text).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from identify.model.params import SPECS, normal_load_from_voltage
from identify.model.plausible import PLATFORM_RANGES, platform_problem
from identify.traces.trace_files import (
    check_writable_times,
    conditions_json_text,
    parse_conditions_json,
    parse_samples_csv,
    samples_csv_text,
)
from identify.traces.trace_format import FORMAT as FORMAT
from identify.traces.trace_format import TraceFormatError as TraceFormatError
from identify.traces.trace_metadata import check_metadata, ordered_metadata

__all__ = [
    "FORMAT",
    "TraceFormatError",
    "Trace",
    "TraceSet",
    "load_traces",
    "trace_paths",
]


# ----------------------------------------------------------------------------- numbers
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
        check_metadata(meta, where)
        self.metadata = ordered_metadata(meta)
        if self.path is not None:
            self.path = Path(self.path)

    def __len__(self) -> int:
        """Number of frames."""
        return len(self.time_s)

    def __repr__(self) -> str:
        drive = (f"fp={self.step_frequency:g} Hz" if self.drive is None else "load point at "
                 + " -> ".join(f"{v:g}" for v in self.drive.velocities_um_per_s) + " µm/s")
        return (
            f"Trace({self.name!r}, {len(self)} frames, {self.time_s[0]:g}..{self.time_s[-1]:g} s, "
            f"k={self.spring_constant:g} N/m, Nb={self.normal_load * 1e6:.3g} µN, "
            f"{drive}"
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
        """fp, Hz (a stepper's run; a continuously driven run has none: see :attr:`drive`)."""
        if "step_frequency_Hz" not in self.metadata:
            raise ValueError(f"run {self.name!r} has a continuous drive, not a stepper: it has no step frequency. "
                             "Velocity steps are fitted with the rate-and-state laws (identify.fit_transient; "
                             "'fit --law aging|slip'); a constant drive's cycles are read by "
                             "identify.cycles_of_trace ('analyze')")
        return float(self.metadata["step_frequency_Hz"])

    @property
    def drive(self):
        """The load point's motion of a continuously driven run
        (:class:`identify.model.rsf.VelocityDrive`), None for a stepper's run."""
        from identify.model.rsf import VelocityDrive

        d = self.metadata.get("drive")
        if d is None:
            return None
        return VelocityDrive(tuple(map(float, d["times_s"])), tuple(map(float, d["velocities_um_per_s"])))

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
        check_metadata(meta, json_path)  # the metadata dict may have been edited
        check_writable_times(self.time_s, csv_path)
        csv_text = samples_csv_text(self.time_s, self.elongation, self.puller)
        stem_path.parent.mkdir(parents=True, exist_ok=True)
        with open(csv_path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(csv_text)
        json_text = conditions_json_text(meta)
        with open(json_path, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(json_text)
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
        meta = parse_conditions_json(json_path)
        values, names = parse_samples_csv(csv_path)
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
