"""Analyse a data set of runs: events, reduced analysis and the aging-law comparison.

:func:`analyze` is what ``python -m identify analyze DATA... [--json OUT] [--plots DIR]``
runs: it loads traces (a bad file is refused with its reason, never fatal), extracts
the events of each run (a run whose extraction fails is reported with the reason),
computes each run's reduced analysis, and fits μs(t_rest) across the usable runs with
each aging law (:func:`identify.traces.reduced.reduced_fit`).
"""

from __future__ import annotations

import logging
import math
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from identify.jsonio import SavedResult, jsonable
from identify.traces.events import RunEvents, extract_events
from identify.traces.io import Trace, load_traces
from identify.traces.reduced import ReducedFit, ReducedRun, reduced_fit

__all__ = ["AnalyzeResult", "RunAnalysis", "SavedEvents", "SavedTrace", "analyze"]

log = logging.getLogger(__name__)


# what a run's JSON says of its trace (RunAnalysis.to_json), written back as read
_TRACE_KEYS = ("name", "path", "coating", "spring_constant_N_per_m", "normal_load_uN", "step_frequency_Hz", "n_frames")


class _ReadBack:
    """Part of a run read back from JSON: what the report and Fig. 10 need. Anything
    else (frames, plateaus, slips) was not saved, and asking for it says so."""

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        run = self.__dict__.get("record", {}).get("name") or getattr(self.__dict__.get("trace"), "name", "?")
        raise AttributeError(
            f"{type(self).__name__}.{name}: run {run!r} was read from JSON, which keeps its summary and "
            "reduced analysis, not its frames or events: analyze() its traces again for this"
        )


@dataclass
class SavedTrace(_ReadBack):
    """A run's trace as :meth:`AnalyzeResult.load` reads it back: its name, path and
    conditions, not its frames."""

    record: dict

    name = property(lambda self: self.record["name"])
    coating = property(lambda self: self.record["coating"])
    spring_constant = property(lambda self: float(self.record["spring_constant_N_per_m"]))
    normal_load = property(lambda self: float(self.record["normal_load_uN"]) * 1e-6)
    step_frequency = property(lambda self: float(self.record["step_frequency_Hz"]))

    @property
    def path(self) -> Path | None:
        return None if self.record["path"] is None else Path(self.record["path"])

    def __len__(self) -> int:
        return int(self.record["n_frames"])


@dataclass
class SavedEvents(_ReadBack):
    """A run's events as :meth:`AnalyzeResult.load` reads them back: the numbers of the
    report (regime, slips, noise, step phase, creep ratio) and the reduced analysis."""

    trace: SavedTrace
    regime: str
    n_slips: int
    noise_m: float
    step_phase: float
    creep_ratio: float
    reduced: ReducedRun
    warnings: list = field(default_factory=list)


def _num(x) -> float:
    return math.nan if x is None else float(x)


@dataclass
class RunAnalysis:
    """One loaded run: its events (None if extraction failed) and whether the law fit
    used it, with the reason when not. A run read back from JSON (:meth:`from_json`)
    has a :class:`SavedTrace` and :class:`SavedEvents` in place of its trace and events."""

    trace: Trace | SavedTrace
    events: RunEvents | SavedEvents | None
    used: bool = False
    reason: str = ""

    @property
    def name(self) -> str:
        return self.trace.name

    @property
    def regime(self) -> str:
        return self.events.regime if self.events is not None else "error"

    @property
    def read_back(self) -> bool:
        """Whether the run was read from JSON (it has no frames or events then)."""
        return isinstance(self.trace, SavedTrace)

    def to_json(self) -> dict:
        ev = self.events
        tr = self.trace
        head = dict(tr.record) if isinstance(tr, SavedTrace) else dict(
            name=self.name,
            path=str(tr.path) if tr.path is not None else None,
            coating=tr.coating,
            spring_constant_N_per_m=tr.spring_constant,
            normal_load_uN=tr.normal_load * 1e6,
            step_frequency_Hz=tr.metadata.get("step_frequency_Hz"),  # (a lab's continuous drive has none)
            n_frames=len(tr),
        )
        return jsonable(
            dict(
                **head,
                regime=self.regime,
                n_slips=ev.n_slips if ev is not None else None,
                noise_nm=ev.noise_m * 1e9 if ev is not None else None,
                step_phase=ev.step_phase if ev is not None else None,
                creep_ratio=ev.creep_ratio if ev is not None else None,
                reduced=ev.reduced.to_json() if ev is not None else None,
                used=self.used,
                reason=self.reason,
                warnings=list(ev.warnings) if ev is not None else [],
            )
        )

    @classmethod
    def from_json(cls, d: dict) -> RunAnalysis:
        """The run :meth:`to_json` describes: its conditions, summary numbers and reduced
        analysis (:class:`SavedTrace`, :class:`SavedEvents`), not its frames."""
        tr = SavedTrace({k: d.get(k) for k in _TRACE_KEYS})
        ev = None
        if d.get("reduced") is not None:
            red = ReducedRun.from_json(d["reduced"])
            ev = SavedEvents(
                trace=tr, regime=d["regime"], n_slips=int(d["n_slips"]),
                noise_m=red.noise_m,  # (σ̂ itself: the JSON's noise_nm is σ̂·1e9)
                step_phase=_num(d["step_phase"]), creep_ratio=_num(d["creep_ratio"]), reduced=red,
                warnings=list(d.get("warnings", [])),
            )
        return cls(tr, ev, bool(d["used"]), d.get("reason", ""))


@dataclass
class AnalyzeResult(SavedResult):
    """Result of :func:`analyze`.

    ``to_dict()`` is what ``identify analyze --json`` writes; :meth:`from_dict` and
    :meth:`load` read it back with what the report and :meth:`plot` (Fig. 10) need:
    the runs' conditions, summary numbers and reduced analyses and the law fits, not
    the frames or the events themselves (:meth:`save_plots` needs those).

    Attributes
    ----------
    runs : list of RunAnalysis
        Every loaded run, in load order.
    refused : list of (str, str)
        (file, reason) of every file that could not be loaded.
    fit : ReducedFit or None
        The law comparison over the used runs (None without loaded runs).
    source : str
        Source of the (t_rest, μs) points (:data:`identify.traces.reduced.SOURCES`).
    warnings : list of str
    """

    runs: list
    refused: list
    fit: ReducedFit | None
    source: str = "events"
    warnings: list = field(default_factory=list)

    @property
    def best_law(self) -> str | None:
        return self.fit.best if self.fit is not None else None

    def report(self) -> str:
        lines = [
            f"Analysis of {len(self.runs)} run(s)"
            + (f", {len(self.refused)} refused" if self.refused else "")
        ]
        for ra in self.runs:
            ev = ra.events
            if ev is None:
                lines.append(f"  {ra.name}: extraction failed: {ra.reason}")
                continue
            r = ev.reduced
            lines.append(
                f"  {ra.name}: {ev.regime}, {ev.n_slips} slips, σ = {ev.noise_m * 1e9:.0f} nm, "
                f"φ = {ev.step_phase:.2f}; δ̄ = {r.slip_sqrt12_corrected_m * 1e6:.3f} µm (σ√12), "
                f"{r.mean_slip_m * 1e6:.3f} µm (events); μs = {r.mu_s_events_mid:.4f}, "
                f"t_rest = {r.mean_rest_time_s * 1e3:.4g} ms"
                + ("" if ra.used else f"  [not used: {ra.reason}]")
            )
        if self.refused:
            lines.append("refused:")
            lines += [f"  {f}: {why}" for f, why in self.refused]
        if self.fit is not None:
            lines.append("")
            lines.append(self.fit.report())
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)

    def to_json(self) -> dict:
        return jsonable(
            dict(
                runs=[ra.to_json() for ra in self.runs],
                law_fits=self.fit.to_json()["fits"] if self.fit is not None else {},
                best_law=self.best_law,
                source=self.source,
                refused=[dict(file=f, reason=why) for f, why in self.refused],
                warnings=list(self.warnings),
            )
        )

    @classmethod
    def from_dict(cls, d: dict) -> AnalyzeResult:
        """The analysis :meth:`to_dict` (or ``identify analyze --json``) describes: its
        report, JSON and Fig. 10 are those of the analysis written; each run is read back
        without its frames (:meth:`RunAnalysis.from_json`)."""
        runs = [RunAnalysis.from_json(r) for r in d["runs"]]
        source = d.get("source", "events")
        good = [ra for ra in runs if ra.events is not None]
        fit = None
        if good:  # (analyze fits the laws whenever a run has events)
            listed = dict(source=source, runs=[dict(name=ra.name, used=ra.used) for ra in good],
                          fits=d.get("law_fits") or {}, best=d.get("best_law"))
            fit = ReducedFit.from_json(listed, [ra.events.reduced for ra in good])
        return cls(
            runs=runs,
            refused=[(r["file"], r["reason"]) for r in d.get("refused", [])],
            fit=fit,
            source=source,
            warnings=list(d.get("warnings", [])),
        )

    def plot(self, ax=None):
        """The analysis's headline figure, the paper's Fig. 10: static friction against rest
        time with the laws fitted across runs and their 95 % bands."""
        if self.fit is None:
            raise ValueError("plot: no run could be analysed, so no law was fitted to draw")
        return self.fit.plot(ax=ax)

    def save_plots(self, directory: str | os.PathLike) -> list[Path]:
        """Write ``events_<run>.png`` per run, ``fig10_static_friction.png`` and
        ``fig11_aging_rates.png``; returns the paths written. An analysis read from JSON
        has no frames to draw the events of: analyse the traces again."""
        from identify.plots.base import pyplot
        from identify.plots.events import plot_events

        if any(ra.read_back and ra.events is not None for ra in self.runs):
            raise ValueError(
                "save_plots: this analysis was read from JSON, which keeps no frames or events to draw "
                "(plot() draws Fig. 10 from what it keeps): analyze() the traces again for the figures"
            )
        plt = pyplot()
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        written: list[Path] = []
        for ra in self.runs:
            if ra.events is None:
                continue
            fig, ax = plt.subplots(figsize=(8, 4), constrained_layout=True)
            try:
                plot_events(ra.events, ax=ax)
                p = out / f"events_{_safe(ra.name)}.png"
                fig.savefig(p, dpi=150)
                written.append(p)
            finally:
                plt.close(fig)
        if self.fit is not None:
            for fname, method in (
                ("fig10_static_friction.png", self.fit.plot),
                ("fig11_aging_rates.png", self.fit.plot_rates),
            ):
                fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
                try:
                    method(ax=ax)
                    p = out / fname
                    fig.savefig(p, dpi=150)
                    written.append(p)
                finally:
                    plt.close(fig)
        return written


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "run"


def analyze(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    plots_dir: str | os.PathLike | None = None,
    source: str = "events",
    recursive: bool = False,
) -> AnalyzeResult:
    """Events, reduced analysis and law comparison of a data set.

    Parameters
    ----------
    paths : path or iterable of paths
        Runs and folders of runs (:func:`identify.traces.io.load_traces`).
    plots_dir : path, optional
        If given, :meth:`AnalyzeResult.save_plots` writes the figures there.
    source : str
        (t_rest, μs) points of the law fits (:data:`identify.traces.reduced.SOURCES`).
    recursive : bool
        Also look in sub-folders.

    Returns
    -------
    AnalyzeResult
        Runs whose files break the format are in ``refused``; runs whose extraction
        fails have ``events = None`` and the reason; runs without a resolved saw-tooth
        are kept but not used in the law fits.
    """
    ts = load_traces(paths, recursive=recursive)
    refused = [(e.path, (f"line {e.line}: " if e.line else "") + e.rule) for e in ts.errors]
    runs: list[RunAnalysis] = []
    for tr in ts.traces:
        try:
            ev = extract_events(tr)
        except Exception as exc:  # noqa: BLE001 - a failing run is reported, never fatal
            log.warning("%s: event extraction failed: %s", tr.name, exc)
            runs.append(
                RunAnalysis(
                    tr, None, False, f"event extraction failed: {type(exc).__name__}: {exc}"
                )
            )
            continue
        runs.append(RunAnalysis(tr, ev))
    warnings: list[str] = []
    fit = None
    good = [ra for ra in runs if ra.events is not None]
    if good:
        fit = reduced_fit([ra.events.reduced for ra in good], source=source)
        for ra, used in zip(good, fit.used):
            ra.used = bool(used)
            if not used:
                if ra.events.regime != "stick-slip":
                    ra.reason = f"regime {ra.events.regime}"
                else:
                    ra.reason = f"no finite ({source}) rest time and μs"
        coatings = {ra.trace.coating for ra in good if ra.used}
        if len(coatings) > 1:
            warnings.append(
                "runs of several coatings ("
                + ", ".join(sorted(str(c) for c in coatings))
                + ") share one law fit; analyse each coating separately"
            )
        if fit.best is None:
            n_used = sum(fit.used)
            warnings.append(f"no law fit is determined ({n_used} usable run(s))")
    result = AnalyzeResult(runs=runs, refused=refused, fit=fit, source=source, warnings=warnings)
    if plots_dir is not None:
        result.save_plots(plots_dir)
    return result
