"""Figures of laboratory recordings: a rate-and-state transient fit (friction against
load-point displacement, data and model, residuals below) and the slip cycles of a
constant drive (each slip's force drop against the reload time after it)."""

from __future__ import annotations

import numpy as np

from identify.plots.base import pyplot

__all__ = ["plot_cycles", "plot_transient_fit"]


def _displacement(result) -> np.ndarray:
    """Load-point displacement (µm) from the window's start, from the drive."""
    from identify.model.rsf import VelocityDrive

    d = result.drive
    return VelocityDrive(tuple(d["times_s"]), tuple(d["velocities_um_per_s"])).displacement_um(result.time_s)


def plot_transient_fit(result, ax=None):
    """Data (grey points) and the fitted law (line) against load-point displacement; with
    ``ax`` None, a figure of two panels whose lower one shows data − model. Returns the
    axes drawn on (a list of two when the figure is made here)."""
    plt = pyplot()
    if ax is None:
        fig, axes = plt.subplots(2, 1, figsize=(6.4, 5.2), sharex=True, gridspec_kw=dict(height_ratios=[3, 1]))
    else:
        axes = [ax]
    x = _displacement(result)
    a0 = axes[0]
    a0.plot(x, result.mu, ".", ms=2, color="0.6", label="data")
    law = dict(aging="aging law", slip="slip law").get(result.law, result.law)
    p = result.parameters
    label = f"{law}: a={p['a'].value:.4g}, b={p['b'].value:.4g}, Dc={p['Dc'].value:.3g} µm"
    a0.plot(x, result.model, "-", color="#2c7fb8", lw=1.5, label=label)
    a0.set_ylabel("friction coefficient μ")
    a0.set_title(f"{result.run}: velocity steps " + " → ".join(f"{v:g}" for v in result.drive["velocities_um_per_s"])
                 + " µm/s", fontsize=10)
    a0.legend(loc="best", fontsize=8, frameon=False)
    if len(axes) > 1:
        a1 = axes[1]
        a1.plot(x, np.asarray(result.mu) - np.asarray(result.model), ".", ms=2, color="0.4")
        a1.axhline(0, color="#2c7fb8", lw=1)
        a1.set_ylabel("data − model")
        a1.set_xlabel("load-point displacement (µm)")
        return list(axes)
    a0.set_xlabel("load-point displacement (µm)")
    return a0


def plot_cycles(cycles, ax=None):
    """Each slip's force drop against the time until the next slip, with the line a
    sawtooth follows (time = drop / (k·V/N): the drive reloads what the slip let go, then
    the next slip comes); for an oscillation, the histogram of its periods. Returns the
    axes."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.4, 4.4), layout="constrained")
    if cycles.drops.size >= 2:
        wait = np.asarray(cycles.periods, float)  # (from each slip to the next)
        drop = np.asarray(cycles.drops, float)[:-1]
        ax.plot(wait, drop, "o", ms=3, color="#2c7fb8", alpha=0.7, label=f"slips ({drop.size})")
        x = np.linspace(0, max(wait.max(), 1e-9) * 1.05, 50)
        ax.plot(x, cycles.drive_rate * x, "--", color="0.3", label=f"k·V/N × time ({cycles.drive_rate:.3g}/s)")
        ax.set_xlabel("time until the next slip (s)")
        ax.set_ylabel("force drop (force / normal load)")
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
    elif cycles.periods.size:
        ax.hist(np.asarray(cycles.periods) * 1e3, bins=30, color="#2c7fb8", alpha=0.8,
                label=f"{cycles.periods.size} cycles")
        ax.set_xlabel("oscillation period (ms)")
        ax.set_ylabel("cycles")
    else:
        ax.text(0.5, 0.5, f"{cycles.regime}: no cycles to draw", ha="center", va="center", transform=ax.transAxes)
    ax.set_title(f"{cycles.name}: {cycles.regime} (force rising {100 * cycles.rising_fraction:.0f} % of the time)",
                 fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", fontsize=8, frameon=False)
    return ax
