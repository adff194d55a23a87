"""Figures of a diagnosis (:meth:`identify.diagnosis.rounds.DiagnosisResult.save_plots`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from identify.plots.base import pyplot, save_figure

__all__ = ["plot_misfit_by_feature", "plot_residual_vs_position", "plot_gap_shrinkage", "save_diagnosis_plots"]


def plot_misfit_by_feature(result, ax=None):
    """Misfit of every feature (σ), baseline and final model."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.5, 3.6))
    names = [m.feature for m in result.where]
    before = [m.misfit_sigma for m in result.where]
    after_map = {m.feature: m.misfit_sigma for m in result.where_final}
    after = [after_map.get(n, np.nan) for n in names]
    y = np.arange(len(names))
    ax.barh(y + 0.2, before, height=0.4, label="baseline", color="0.6")
    if result.effects:
        ax.barh(y - 0.2, after, height=0.4, label="+ " + ", ".join(result.effects), color="C0")
    n = max(len(result.where), 1)
    from scipy import stats

    thr = stats.norm.isf(result.options.alpha / n / 2)
    ax.axvline(thr, color="C3", ls="--", lw=1, label=f"significant (α = {result.options.alpha:g}, {n} tests)")
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xlabel("misfit (σ of a Gaussian, two-sided)")
    ax.set_title(f"Where the misfit lives — verdict: {result.verdict}")
    ax.legend(fontsize=7, loc="lower right")
    return ax


def plot_residual_vs_position(result, ax=None):
    """Static-friction (trigger) misfit, as elongation, against block position, per run."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.5, 3.6))
    if result.baseline is None:
        ax.text(0.5, 0.5, "no baseline could be fitted", ha="center", transform=ax.transAxes)
        return ax
    for k, (label, x_um, misfit_nm) in enumerate(result.trigger_misfit_by_position()):
        ax.plot(x_um, misfit_nm, "o" if k == 0 else ".", ms=3 if k == 0 else 4,
                alpha=0.6, color="0.5" if k == 0 else "C0", label=label)
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("block position at the slip (µm)")
    ax.set_ylabel("static-friction misfit (nm of elongation)")
    ax.set_title("Residual against position (a ripple common to all runs = topography)")
    ax.legend(fontsize=7)
    return ax


def plot_gap_shrinkage(result, ax=None):
    """Gap (RMS feature misfit, nm) before and after each candidate, fitted and held out."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.5, 3.8))
    cands = [c for c in result.candidates if c.get("ok") and c.get("gap_after_um") is not None]
    if not cands:
        ax.text(0.5, 0.5, "no candidate could be refitted", ha="center", transform=ax.transAxes)
        return ax
    names = [c["effect"] for c in cands]
    y = np.arange(len(names))
    before = cands[0]["heldout_gap_before_um"] * 1e3
    ax.axvline(before, color="0.4", ls="--", lw=1, label=f"baseline, held out ({before:.1f} nm)")
    ax.axvline(cands[0]["gap_before_um"] * 1e3, color="0.7", ls=":", lw=1, label="baseline, fitted")
    ax.barh(y - 0.2, [c["heldout_gap_after_um"] * 1e3 for c in cands], height=0.4, label="held out",
            color=["C0" if c.get("named") else ("C1" if c.get("significant") else "0.6") for c in cands])
    ax.barh(y + 0.2, [c["gap_after_um"] * 1e3 for c in cands], height=0.4, label="fitted", color="0.85")
    ax.set_yticks(y, names)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("gap after adding the candidate (nm, RMS of the features)")
    ax.set_title("Gap shrinkage per candidate (blue: named, orange: significant)")
    ax.legend(fontsize=7, loc="lower right")
    return ax


def save_diagnosis_plots(result, folder) -> list:
    plt = pyplot()
    folder = Path(folder)
    paths = []
    for name, fn in (("misfit_by_feature", plot_misfit_by_feature),
                     ("residual_vs_position", plot_residual_vs_position),
                     ("gap_shrinkage", plot_gap_shrinkage)):
        fig, ax = plt.subplots(figsize=(6.5, 3.8))
        fn(result, ax=ax)
        fig.tight_layout()
        paths += save_figure(fig, folder / name)
        plt.close(fig)
    return paths
