"""Figures of the event extraction and of the reduced analysis.

Every function takes ``ax`` (or makes one), returns it, labels axes in display units
(µm, s, ms) and never calls ``plt.show()``.

plot_events
    A run's elongation with the fitted staircase model, slips and excluded frames.
plot_reduced_fit
    μs against rest time with each aging law's fitted curve (the paper's Fig. 10).
plot_reduced_rates
    dμs/dt_rest of the fitted laws against rest time (the paper's Fig. 11).
"""

from __future__ import annotations

import math

import numpy as np

from identify.plots.base import pyplot

__all__ = ["plot_events", "plot_reduced_fit", "plot_reduced_rates"]

_LAW_STYLE = {
    "exponential": dict(color="#d7191c", ls="-"),
    "logarithmic": dict(color="#2c7fb8", ls="--"),
    "logistic": dict(color="#1a9641", ls="-."),
}


def _new_ax(ax, figsize=(7, 4)):
    if ax is not None:
        return ax
    plt = pyplot()
    _, ax = plt.subplots(figsize=figsize, constrained_layout=True)
    return ax


def plot_events(events, ax=None, t_window: tuple[float, float] | None = None):
    """Elongation (µm) against time (s): frames, the staircase model of the plateaus,
    slips and excluded frames.

    Parameters
    ----------
    events : RunEvents
        From :func:`identify.traces.events.extract_events`.
    ax : matplotlib Axes, optional
    t_window : (t0, t1) in s, optional
        Time range shown (default the whole run).

    Returns
    -------
    Axes
    """
    ax = _new_ax(ax, figsize=(8, 4))
    tr = events.trace
    t, e = tr.time_s, tr.elongation
    fp, phi = tr.step_frequency, events.step_phase
    t0, t1 = (float(t[0]), float(t[-1])) if t_window is None else map(float, t_window)
    sel = (t >= t0) & (t <= t1)
    keep = sel & (events.plateau_of_frame >= 0)
    out = sel & (events.plateau_of_frame < 0)
    ax.plot(t[keep], e[keep] * 1e6, ".", ms=2.5, color="0.55", label="frames")
    if out.any():
        ax.plot(t[out], e[out] * 1e6, "x", ms=6, color="#d7191c", label="excluded (inside a slip)")
    # model: constant between step instants, the level changes at trigger steps
    n0 = max(math.floor(t0 * fp - phi), 0)
    n1 = math.ceil(t1 * fp - phi) + 1
    if n1 - n0 <= 200_000:
        knots = (np.arange(n0, n1 + 1) + phi) / fp
        knots = np.concatenate([[t0], knots[(knots > t0) & (knots < t1)], [t1]])
        ax.step(
            knots,
            events.model_elongation(knots) * 1e6,
            where="post",
            lw=1.0,
            color="#2c7fb8",
            label="staircase model",
        )
    s = events.slips
    if events.n_slips:
        ts = s["trigger_time_s"]
        m = (ts >= t0) & (ts <= t1)
        ax.plot(
            ts[m],
            s["peak_elongation_m"][m] * 1e6,
            "v",
            ms=5,
            color="#d7191c",
            label=f"slips ({events.n_slips})",
        )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("elongation (µm)")
    ax.set_xlim(t0, t1)
    ax.set_title(
        f"{tr.name}: {events.regime}, σ = {events.noise_m * 1e9:.0f} nm, "
        f"φ = {events.step_phase:.2f}",
        fontsize=9,
    )
    ax.legend(fontsize=7, loc="best")
    return ax


def _t_grid(fit) -> np.ndarray:
    t = np.asarray(fit.t_rest_s, float)
    if t.size:
        lo, hi = float(t.min()) / 5, float(t.max()) * 5
    else:
        lo, hi = 1e-3, 10.0
    return np.logspace(math.log10(lo), math.log10(hi), 300)


def plot_reduced_fit(fit, ax=None):
    """μs against rest time (log axis), a point per run and each law's fitted curve
    (the paper's Fig. 10).

    Parameters
    ----------
    fit : ReducedFit
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    ax = _new_ax(ax)
    pts = [(r.point(fit.source), u) for r, u in zip(fit.runs, fit.used)]
    used = np.array([p for p, u in pts if u], float).reshape(-1, 2)
    unused = np.array(
        [p for p, u in pts if not u and all(map(math.isfinite, p)) and p[0] > 0], float
    ).reshape(-1, 2)
    if used.size:
        ax.plot(used[:, 0] * 1e3, used[:, 1], "o", color="k", ms=5, label="runs")
    if unused.size:
        ax.plot(
            unused[:, 0] * 1e3, unused[:, 1], "o", mfc="none", color="0.6", ms=5, label="not used"
        )
    tg = _t_grid(fit)
    for name, f in fit.fits.items():
        if not all(map(math.isfinite, f.parameters.values())):
            continue
        style = _LAW_STYLE.get(name, {})
        lab = f"{name} (R² = {f.r2:.3f})" if math.isfinite(f.r2) else name
        if name == fit.best:
            lab += " best"
        if not f.converged:
            lab += " (undetermined)"
        ax.plot(tg * 1e3, f.predict(tg), lw=1.5, label=lab, **style)
    ax.set_xscale("log")
    ax.set_xlabel("rest time (ms)")
    ax.set_ylabel("static friction coefficient μs")
    ax.set_title(f"static friction vs rest time ({fit.source})", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    return ax


def plot_reduced_rates(fit, ax=None):
    """dμs/dt_rest (1/s) of the fitted laws against rest time, log–log (Fig. 11).

    Parameters
    ----------
    fit : ReducedFit
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    ax = _new_ax(ax)
    tg = _t_grid(fit)
    top = 0.0
    for name, f in fit.fits.items():
        if not all(map(math.isfinite, f.parameters.values())):
            continue
        rate = f.rate(tg)
        ok = rate > 0
        if ok.any():
            top = max(top, float(rate[ok].max()))
            ax.plot(tg[ok] * 1e3, rate[ok], lw=1.5, label=name, **_LAW_STYLE.get(name, {}))
    t = np.asarray(fit.t_rest_s, float)
    if t.size:
        ax.axvspan(
            t.min() * 1e3, t.max() * 1e3, color="0.9", zorder=0, label="rest times of the runs"
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    if top > 0:  # a saturated law's rate falls by many decades: show 6 of them
        ax.set_ylim(top * 1e-6, top * 3)
    ax.set_xlabel("rest time (ms)")
    ax.set_ylabel("dμs/dt_rest (1/s)")
    ax.set_title("aging rate of the fitted laws", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    return ax
