"""The figure of a rate-and-state transient fit: friction against load-point
displacement since the velocity change, data and model, with the residuals below."""

from __future__ import annotations

import numpy as np

from identify.plots.base import pyplot

__all__ = ["plot_transient_fit"]


def _displacement(result) -> np.ndarray:
    """Load-point displacement (µm) from the window's start, from the drive."""
    t = np.asarray(result.time_s, float)
    times = np.asarray(result.drive["times_s"], float)
    vels = np.asarray(result.drive["velocities_um_per_s"], float)
    edges = np.concatenate([times, [max(t[-1], times[-1])]])
    x = np.zeros_like(t)
    for i, v in enumerate(vels):
        x += v * np.clip(np.minimum(t, edges[i + 1]) - edges[i], 0, None)
    return x


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
