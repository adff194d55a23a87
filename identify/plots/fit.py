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

__all__ = ["plot_profile", "plot_run_fit", "run_label", "plot_static_friction", "plot_slip_lengths",
           "plot_residuals", "save_fit_plots"]


def run_label(rd) -> str:
    """A run's conditions as a legend names them."""
    return f"k = {rd.k:g} N/m, Nb = {rd.Nb * 1e6:.3g} µN, fp = {rd.fp:g} Hz"


def _zoom_windows(t_trig: np.ndarray, t_frames: np.ndarray, res: np.ndarray, fp: float, n: int = 2) -> list:
    """Up to ``n`` (start, end, label) windows around single slips, wide enough for the
    puller's steps to show (at most 24 steps, at most 2.5 slip periods): the slip whose
    frames the model misses most, and a typical one (median misfit) that does not overlap it."""
    if len(t_trig) < 2:
        return []
    width = min(2.5 * float(np.median(np.diff(t_trig))), 24.0 / fp)
    ok = np.isfinite(res)
    near = np.clip(np.searchsorted(t_trig, t_frames[ok]), 0, len(t_trig) - 1)
    rms = np.zeros(len(t_trig))
    for i in range(len(t_trig)):  # once per slip of one figure: not a hot path
        r = res[ok][near == i]
        rms[i] = np.sqrt(np.mean(r**2)) if len(r) else 0.0
    worst = int(np.argmax(rms))
    picks = [(worst, "the slip the model misses most")]
    apart = np.flatnonzero(np.abs(t_trig - t_trig[worst]) > width)
    if len(apart):
        picks.append((int(apart[np.argsort(rms[apart])[len(apart) // 2]]), "a typical slip"))
    t0, t1 = float(t_frames[0]), float(t_frames[-1])
    out = []
    for i, what in sorted(picks[:n]):
        lo = max(t0, t_trig[i] - 0.4 * width)
        out.append((lo, min(t1, lo + width), what))
    return out


def plot_run_fit(result, i_run, axes=None):
    """One run's fit: the whole run, the residuals under it, and two zoomed windows.

    The model is drawn as what it is: a staircase of puller steps on each plateau, the
    slips as the drops between plateaus (:meth:`FitResult.model_staircase`). The residual
    panel is data − model at the frames (nm) with the ±2σ noise band; frames inside
    slips, which no plateau claims, are left out. The zooms (shaded on the overview) are
    around the slip whose frames the model misses most and a typical one.

    ``axes``: four Axes (overview, residuals, zoom a, zoom b), or None for a new figure.
    Returns the four Axes (a zoom is left blank on a run with fewer than two slips).
    """
    plt = pyplot()
    if axes is None:
        fig = plt.figure(figsize=(8, 6.6), layout="constrained")
        gs = fig.add_gridspec(3, 2, height_ratios=[2.0, 1.0, 2.0])
        ax0 = fig.add_subplot(gs[0, :])
        axes = [ax0, fig.add_subplot(gs[1, :], sharex=ax0), fig.add_subplot(gs[2, 0]), fig.add_subplot(gs[2, 1])]
    ax, axr, za, zb = axes
    rd = result.problem.runs[i_run]
    tr = rd.events.trace
    t, e_model, _ = result.model_elongation(i_run)
    ts, es = result.model_staircase(i_run)
    t_trig = (np.asarray(rd.trigger_steps) + rd.events.step_phase) / rd.fp
    res_nm = (tr.elongation - e_model) * 1e9
    many = len(tr.time_s) > 3000  # dense runs: small marks, rasterised in the PDF
    dot = dict(ls="none", marker=".", ms=1.5 if many else 3, color="0.55", rasterized=many)
    ax.plot(tr.time_s, tr.elongation * 1e6, label="data (frames)", **dot)
    ax.plot(ts, es * 1e6, drawstyle="steps-post", lw=0.7 if many else 1.0, color="C0",
            label="fitted model (steps and slips)")
    ax.set_ylabel("elongation e (µm)")
    ax.figure.suptitle(f"{rd.name}: {run_label(rd)}", fontsize=11)
    ax.tick_params(labelbottom=False)

    axr.axhspan(-2 * rd.sigma * 1e9, 2 * rd.sigma * 1e9, color="C2", alpha=0.15, lw=0,
                label=f"±2σ frame noise (σ = {rd.sigma * 1e9:.3g} nm)")
    axr.plot(t, res_nm, **{**dot, "color": "0.3"})
    axr.axhline(0, color="C0", lw=0.8)
    axr.set(xlabel="time (s)", ylabel="data − model (nm)")
    axr.legend(loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize=7, frameon=False, borderaxespad=0.1)

    windows = _zoom_windows(t_trig, t, res_nm, rd.fp)
    for (lo, hi, what), zax, tag in zip(windows, (za, zb), "ab"):
        ax.axvspan(lo, hi, color="C1", alpha=0.15, lw=0)
        ax.text(lo, 0.98, f" {tag}", transform=ax.get_xaxis_transform(), va="top", ha="left", fontsize=9,
                color="C1", weight="bold")
        f = (tr.time_s >= lo) & (tr.time_s <= hi)
        s = (ts >= lo - 1.0 / rd.fp) & (ts <= hi)
        zax.plot(tr.time_s[f], tr.elongation[f] * 1e6, ls="none", marker=".", ms=3, color="0.55",
                 label="data (frames)")
        zax.plot(ts[s], es[s] * 1e6, drawstyle="steps-post", lw=1.0, color="C0",
                 label="fitted model (steps and slips)")
        tt = t_trig[(t_trig >= lo) & (t_trig <= hi)]
        zax.plot(tt, np.interp(tt, ts, es, left=np.nan) * 1e6, "v", ms=5, color="C3")
        zax.set(xlim=(lo, hi), xlabel="time (s)", title=f"{tag}: {what}")
        zax.title.set_fontsize(9)
    for zax in (za, zb)[len(windows):]:
        zax.set_axis_off()
    za.set_ylabel("elongation e (µm)")
    from matplotlib.lines import Line2D

    handles = ax.get_legend_handles_labels()[0]
    if windows:
        handles.append(Line2D([], [], ls="none", marker="v", ms=5, color="C3",
                              label="slip at its trigger step (zooms)"))
    ax.legend(handles=handles, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=3, fontsize=7, frameon=False,
              borderaxespad=0.1)
    return [ax, axr, za, zb]


def plot_static_friction(result, ax=None):
    """Static friction coefficient of every slip (μs = k·e_peak/Nb) against the rest
    before it, per run, with the fitted law and its 95 % band."""
    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(7.5, 4.2), layout="constrained")
    prob = result.problem
    t_all = []
    markers = "os^Dv<>p*h"
    for j, rd in enumerate(r for r in prob.runs if r.kind == "events"):
        s = rd.events.slips
        mu = rd.k * np.asarray(s["peak_elongation_m"]) / rd.Nb
        t = np.asarray(s["rest_time_s"])
        ok = np.isfinite(mu) & (t > 0)
        ax.semilogx(t[ok], mu[ok], markers[j % len(markers)], ms=3.5, mew=0.6, mfc="none", alpha=0.7,
                    color=f"C{j % 10}", label=run_label(rd))
        t_all.append(t[ok])
    t_all = np.concatenate(t_all) if t_all else np.array([1e-3, 1.0])
    tt = np.logspace(np.log10(max(t_all.min(), 1e-4) / 2), np.log10(t_all.max() * 2), 200)
    mu_law, band = result.static_friction_curve(tt)
    P = prob.params(result.w[: prob.n_theta])
    stick = float(P["A"] * np.log1p(P["v_stick"] / P["vc"]))
    if band is not None:
        ax.fill_between(tt, band[0], band[1], color="k", alpha=0.15, lw=0, label="95 % band of the law")
    ax.semilogx(tt, mu_law, "k-", lw=1.5, label=f"fitted {prob.law.name} aging law"
                + (f"\n+ stick band A·ln(1 + v_stick/vc) = {stick:.3f}" if stick else ""))
    ax.set(xlabel="rest time before the slip (s)",
           ylabel="static friction coefficient μs = k·e_peak / Nb")
    ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return ax


def plot_slip_lengths(result, axes=None):
    """Force drop of the slips, k·δ, against the normal load: each run's mean over its
    slips (± standard error) and the fitted model's, and their difference below.
    Colour is the spring, marker the puller frequency; runs at one load sit side by side."""
    plt = pyplot()
    if axes is None:
        _, axes = plt.subplots(2, 1, figsize=(6, 5.2), sharex=True, height_ratios=[2.2, 1], layout="constrained")
    ax, axd = axes
    prob, w = result.problem, result.w
    delta_model = prob.arc_outputs(w)[0] * LENGTH_UNIT if prob.E else np.zeros(0)
    rows = []
    for i, rd in enumerate(prob.runs):
        if rd.kind != "events":
            continue
        d = rd.k * np.asarray(rd.events.slips["slip_length_m"], float) * 1e6
        d = d[np.isfinite(d)]
        m = rd.k * delta_model[prob.ev_run == i] * 1e6
        if not len(d) or not len(m):
            continue
        se = np.std(d, ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
        rows.append((rd.k, rd.fp, rd.Nb * 1e6, float(np.mean(d)), se, float(np.mean(m))))
    ks = sorted({r[0] for r in rows})
    fps = sorted({r[1] for r in rows})
    markers = "osD^v<>p"
    span = max((r[2] for r in rows), default=1.0)
    for k, fp, nb, dm, se, mm in rows:
        c, mk = f"C{ks.index(k) % 10}", markers[fps.index(fp) % len(markers)]
        x = nb + span * 0.012 * (fps.index(fp) - (len(fps) - 1) / 2)  # side by side at one load
        ax.plot(x, mm, mk, ms=9, mfc="none", mec=c, mew=1.0, zorder=1)
        ax.errorbar(x, dm, yerr=1.96 * se, fmt=mk, ms=4, color=c, zorder=2)
        axd.errorbar(x, dm - mm, yerr=1.96 * se, fmt=mk, ms=4, color=c)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="none", marker="s", color=f"C{j % 10}", label=f"k = {k:g} N/m")
               for j, k in enumerate(ks)]
    handles += [Line2D([], [], ls="none", marker=markers[j % len(markers)], color="0.3", label=f"fp = {fp:g} Hz")
                for j, fp in enumerate(fps)]
    handles += [Line2D([], [], ls="none", marker="o", ms=4, color="0.3", label="data: mean ± 95 %"),
                Line2D([], [], ls="none", marker="o", ms=9, mfc="none", mec="0.3", label="fitted model")]
    ax.legend(handles=handles, fontsize=7, frameon=False, loc="upper left")
    ax.set(ylabel="slip force drop k·δ (µN)", title="Slip force drop against normal load")
    ax.set_ylim(bottom=0)
    axd.axhline(0, color="0.5", lw=0.8)
    axd.set(xlabel="normal load Nb (µN)", ylabel="data − model (µN)")
    return [ax, axd]


def plot_residuals(result, axes=None):
    """Normalised residuals: the plateau levels against block position, per run, and the
    slip triggers' distribution."""
    plt = pyplot()
    own = axes is None
    if own:
        _, axes = plt.subplots(1, 2, figsize=(10, 4.6), width_ratios=[1.6, 1], layout="constrained")
    prob, w = result.problem, result.w
    r, _ = prob.evaluate(w)
    grp = prob.residual_groups()
    a, b = grp["plateaus"]
    x_um = w[prob.i_x : prob.i_x + prob.P]
    markers = "os^Dv<>p*h"
    for j, i in enumerate(sorted(set(prob.pl_run.tolist()))):
        m = prob.pl_run == i
        axes[0].plot(x_um[m], r[a:b][m], markers[j % len(markers)], ms=3, mfc="none", mew=0.6,
                     color=f"C{j % 10}", label=run_label(prob.runs[i]))
    axes[0].axhspan(-2, 2, color="0.93", lw=0, zorder=0, label="±2σ")
    axes[0].axhline(0, color="0.5", lw=0.6)
    axes[0].set(xlabel="block position (µm)", ylabel="plateau residual (σ)",
                title="plateau levels (data − model) / σ")
    if own:
        axes[0].figure.legend(fontsize=7, frameon=False, loc="outside lower center", ncol=3)
    else:
        axes[0].legend(fontsize=7, frameon=False)
    t0, t1 = grp["triggers"]
    if prob.interval_triggers or t1 <= t0:
        axes[1].text(0.5, 0.5, "interval encoding:\nno trigger residuals", transform=axes[1].transAxes,
                     ha="center", va="center", fontsize=8, color="0.4")
    else:
        axes[1].hist(r[t0:t1], bins=30, color="C1", label=f"{t1 - t0} slips")
        axes[1].axvline(0, color="0.5", lw=0.6)
        axes[1].legend(fontsize=7, frameon=False)
    axes[1].set(xlabel="trigger residual (σ)", ylabel="number of slips", title="slip triggers")
    return axes


def plot_profile(profile, ax=None, estimate=None):
    """Profile likelihood: Δχ² against the parameter, with the 95 % threshold and the
    profile interval. Given the fit's ``estimate`` (a :class:`ParameterEstimate`), also the
    parabola its standard error implies, for comparison: where they part, either the
    likelihood is not quadratic over the interval or the standard error (robust by
    default) sees a spread the model's likelihood does not."""
    from identify.model.params import SPECS

    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(5.5, 3.8), layout="constrained")
    spec = SPECS.get(profile.name)
    unit = f" ({spec.unit})" if spec is not None and spec.unit not in ("-", "") else ""
    v = np.asarray(profile.values, float)
    ax.plot(v, profile.delta_chi2, "o-", ms=4, color="C0", label="profile (constrained refits)")
    if estimate is not None and estimate.stderr and np.isfinite(estimate.stderr) and len(v):
        vv = np.linspace(v.min(), v.max(), 200)
        ax.plot(vv, ((vv - estimate.value) / estimate.stderr) ** 2, "--", color="0.5", lw=1,
                label=f"parabola of the stderr ({estimate.value:.4g} ± {estimate.stderr:.2g})")
    ax.axhline(profile.threshold, color="C3", ls=":", lw=1, label=f"95 % threshold (Δχ² = {profile.threshold:.2f})")
    ci = [c for c in (profile.ci95 or ()) if c is not None]
    for c in ci:
        ax.axvline(c, color="C0", lw=0.8, alpha=0.6)
    if ci:
        lo, hi = (profile.ci95 or (None, None))
        ax.plot([], [], color="C0", lw=0.8, alpha=0.6,
                label=f"profile 95 % interval [{'open' if lo is None else f'{lo:.4g}'}, "
                      f"{'open' if hi is None else f'{hi:.4g}'}]")
    failed = getattr(profile, "failed", ())
    if len(failed):
        ax.plot(failed, np.zeros(len(failed)), "x", color="C3", ms=6, label="not converged (left out)")
    top = max(float(np.nanmax(profile.delta_chi2)) if len(v) else 0.0, profile.threshold) * 1.15
    ax.set_ylim(-0.05 * top, top)
    und = getattr(profile, "undetermined", None)
    ax.set(xlabel=profile.name + unit, ylabel="Δχ² against the best fit",
           title=f"Profile likelihood of {profile.name}" + ({"both": " (flat)", "above": " (open above)",
                                                            "below": " (open below)"}.get(und or "", "")))
    ax.legend(fontsize=7, frameon=False, loc="upper center")
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
        save(plot_profile(pr, estimate=result.parameters.get(name)), f"profile_{_safe(name)}")
    return written


def _safe(name: str) -> str:
    import re

    return re.sub(r"[^A-Za-z0-9._-]+", "_", name) or "run"
