"""Figures of a fit (:meth:`identify.fitting.result.FitResult.save_plots`).

Everything model-side is read from the solved NLP itself (plateau nodes, slip arcs,
the law at the estimates), so the figures show exactly what was fitted, not a fresh
simulation whose slips may fall at other steps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from identify.model.symbolic import LENGTH_UNIT
from identify.plots.base import pyplot, save_figure

__all__ = ["plot_profile", "plot_run_fit", "plot_static_friction", "plot_slip_lengths",
           "plot_residuals", "save_fit_plots"]


def plot_run_fit(result, i_run, ax=None):
    """Elongation against time: data, the fitted staircase, detected slips marked."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(8, 3.2), constrained_layout=True)
    rd = result.problem.runs[i_run]
    tr = rd.events.trace
    t, e_model, _ = result.model_elongation(i_run)
    ax.plot(tr.time_s, tr.elongation * 1e6, ".", ms=2, color="0.6", label="data")
    ax.plot(t, e_model * 1e6, "-", lw=1, color="C0", label="model (fitted plateaus)")
    t_trig = (rd.trigger_steps + rd.events.step_phase) / rd.fp
    ax.plot(t_trig, np.interp(t_trig, tr.time_s, tr.elongation) * 1e6, "v", ms=4, color="C3", label="slips")
    ax.set(xlabel="time (s)", ylabel="elongation e (µm)",
           title=f"{rd.name}: k = {rd.k:g} N/m, Nb = {rd.Nb * 1e6:.3g} µN, fp = {rd.fp:g} Hz")
    ax.legend(loc="upper left", fontsize=7, frameon=False)
    return ax


def plot_static_friction(result, ax=None):
    """μs = k·e_peak/Nb of every slip against its rest time, with the fitted law."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(5.5, 4), constrained_layout=True)
    prob, w = result.problem, result.w
    t_all = []
    for rd in prob.runs:
        if rd.kind != "events":
            continue
        s = rd.events.slips
        mu = rd.k * np.asarray(s["peak_elongation_m"]) / rd.Nb
        t = np.asarray(s["rest_time_s"])
        ok = np.isfinite(mu) & (t > 0)
        ax.semilogx(t[ok], mu[ok], ".", ms=3, alpha=0.5,
                    label=f"k = {rd.k:g}, Nb = {rd.Nb * 1e6:.3g} µN, fp = {rd.fp:g} Hz")
        t_all.append(t[ok])
    P = prob.params(w[: prob.n_theta])
    t_all = np.concatenate(t_all) if t_all else np.array([1e-3, 1.0])
    tt = np.logspace(np.log10(max(t_all.min(), 1e-4) / 2), np.log10(t_all.max() * 2), 200)
    z0 = prob.law.rejuvenated_state(P)
    # a slip starts when the spring force passes the capacity of a block held by the
    # stick band: ψ plus the velocity-strengthening term at v_stick
    band = float(P["A"] * np.log1p(P["v_stick"] / P["vc"]))
    mu_law = prob.law.static_coefficient(prob.law.rest(z0, tt, P), P) + band
    ax.semilogx(tt, mu_law, "k-", lw=1.5, label=f"fitted {prob.law.name} law"
                + (f" + A·ln(1 + v_stick/vc) = {band:.3f}" if band else ""))
    ax.set(xlabel="rest time (s)", ylabel="static friction μs = k·e_peak/Nb")
    ax.legend(fontsize=6, frameon=False)
    return ax


def plot_slip_lengths(result, ax=None):
    """k·δ against Nb per spring: each run's mean over its slips, data and model arcs."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(5.5, 4), constrained_layout=True)
    prob, w = result.problem, result.w
    delta_model = prob.arc_outputs(w)[0] * LENGTH_UNIT if prob.E else np.zeros(0)
    by_k: dict = {}
    for i, rd in enumerate(prob.runs):
        if rd.kind != "events":
            continue
        d_data = np.asarray(rd.events.slips["slip_length_m"])
        d_mod = delta_model[prob.ev_run == i]
        by_k.setdefault(rd.k, []).append((rd.Nb, rd.k * np.nanmean(d_data), rd.k * np.nanmean(d_mod)))
    for j, (k, rows) in enumerate(sorted(by_k.items())):
        rows = np.array(sorted(rows))
        ax.plot(rows[:, 0] * 1e6, rows[:, 1] * 1e6, "o", color=f"C{j}", mfc="none", label=f"data, k = {k:g} N/m")
        ax.plot(rows[:, 0] * 1e6, rows[:, 2] * 1e6, "x-", color=f"C{j}", label=f"model, k = {k:g} N/m")
    ax.set(xlabel="normal load Nb (µN)", ylabel="k·δ (µN)", title="slip force drop")
    ax.legend(fontsize=7, frameon=False)
    return ax


def plot_residuals(result, axes=None):
    """Normalised residuals of the plateau levels and the triggers."""
    plt = pyplot()
    if axes is None:
        _, axes = plt.subplots(1, 2, figsize=(9, 3.2), constrained_layout=True)
    prob, w = result.problem, result.w
    r, _ = prob.evaluate(w)
    grp = prob.residual_groups()
    a, b = grp["plateaus"]
    x_um = w[prob.i_x : prob.i_x + prob.P]
    for j, i in enumerate(sorted(set(prob.pl_run.tolist()))):
        m = prob.pl_run == i
        axes[0].plot(x_um[m], r[a:b][m], ".", ms=3, color=f"C{j % 10}")
    axes[0].set(xlabel="block position (µm)", ylabel="plateau residual (σ)", title="plateau levels")
    t0, t1 = grp["triggers"]
    axes[1].hist(r[t0:t1], bins=30, color="C1")
    axes[1].set(xlabel="trigger residual (σ)", ylabel="count", title="slip triggers")
    if prob.interval_triggers:
        axes[1].text(0.5, 0.5, "interval encoding:\nno trigger residuals", transform=axes[1].transAxes,
                     ha="center", va="center", fontsize=8, color="0.4")
    for ax in axes:
        ax.axvline(0, color="0.7", lw=0.5) if ax is axes[1] else ax.axhline(0, color="0.7", lw=0.5)
    return axes


def plot_profile(profile, ax=None):
    """Profile likelihood: Δχ² against the parameter, with the 95 % threshold."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(4.5, 3.5), constrained_layout=True)
    ax.plot(profile.values, profile.delta_chi2, "o-", ms=3)
    ax.axhline(profile.threshold, color="C3", ls="--", lw=1, label=f"95 % (Δχ² = {profile.threshold:.2f})")
    for c in profile.ci95 or ():
        if c is not None:
            ax.axvline(c, color="0.6", lw=0.8)
    failed = getattr(profile, "failed", ())
    if len(failed):
        ax.plot(failed, np.zeros(len(failed)), "x", color="C3", ms=5, label="not converged (left out)")
    und = getattr(profile, "undetermined", None)
    ax.set(xlabel=profile.name, ylabel="Δχ²",
           title=f"profile of {profile.name}" + ({"both": " (flat)", "above": " (open above)",
                                                   "below": " (open below)"}.get(und or "", "")))
    ax.legend(fontsize=7, frameon=False)
    return ax


def save_fit_plots(result, folder) -> list:
    """Every figure of a fit as PNG and PDF in ``folder``; returns the paths."""
    plt = pyplot()
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    written: list = []

    def save(ax_or_axes, stem):
        fig = (ax_or_axes[0] if isinstance(ax_or_axes, (list, tuple, np.ndarray)) else ax_or_axes).figure
        try:
            written.extend(save_figure(fig, out / stem))
        finally:
            plt.close(fig)

    prob = result.problem
    for i, rd in enumerate(prob.runs):
        if rd.kind == "events":
            save(plot_run_fit(result, i), f"fit_{_safe(rd.name)}")
    if prob.E:
        save(plot_static_friction(result), "static_friction_vs_rest")
        save(plot_slip_lengths(result), "slip_force_drop_vs_load")
        save(plot_residuals(result), "residuals")
    for name, pr in result.profiles.items():
        save(plot_profile(pr), f"profile_{name}")
    return written


def _safe(name: str) -> str:
    import re

    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "run"
