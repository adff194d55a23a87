"""Analyse a data set of runs: events, reduced analysis and the aging-law comparison.

:func:`analyze` is what ``python -m identify analyze DATA... [--json OUT] [--plots DIR]``
runs: it loads traces (a bad file is refused with its reason, never fatal), extracts
the events of each run (a run whose extraction fails is reported with the reason),
computes each run's reduced analysis, and fits μs(t_rest) across the usable runs with
each aging law (:func:`identify.traces.reduced.reduced_fit`).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from identify.jsonio import jsonable
from identify.traces.events import RunEvents, extract_events
from identify.traces.io import Trace, load_traces
from identify.traces.reduced import ReducedFit, reduced_fit

__all__ = ["AnalyzeResult", "RunAnalysis", "analyze"]

log = logging.getLogger(__name__)


@dataclass
class RunAnalysis:
    """One loaded run: its events (None if extraction failed) and whether the law fit
    used it, with the reason when not."""

    trace: Trace
    events: RunEvents | None
    used: bool = False
    reason: str = ""

    @property
    def name(self) -> str:
        return self.trace.name

    @property
    def regime(self) -> str:
        return self.events.regime if self.events is not None else "error"

    def to_json(self) -> dict:
        ev = self.events
        return jsonable(
            dict(
                name=self.name,
                path=str(self.trace.path) if self.trace.path is not None else None,
                coating=self.trace.coating,
                spring_constant_N_per_m=self.trace.spring_constant,
                normal_load_uN=self.trace.normal_load * 1e6,
                step_frequency_Hz=self.trace.step_frequency,
                n_frames=len(self.trace),
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


@dataclass
class AnalyzeResult:
    """Result of :func:`analyze`.

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

    def to_dict(self) -> dict:
        """The analysis as plain JSON values (what ``identify analyze --json`` writes)."""
        return self.to_json()

    def plot(self, ax=None):
        """The analysis's headline figure, the paper's Fig. 10: static friction against rest
        time with the laws fitted across runs and their 95 % bands."""
        if self.fit is None:
            raise ValueError("plot: no run could be analysed, so no law was fitted to draw")
        return self.fit.plot(ax=ax)

    def save_plots(self, directory: str | os.PathLike) -> list[Path]:
        """Write ``events_<run>.png`` per run, ``fig10_static_friction.png`` and
        ``fig11_aging_rates.png``; returns the paths written."""
        from identify.plots.base import pyplot
        from identify.plots.events import plot_events

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
