"""Figures of the event extraction and of the reduced analysis.

Every function takes ``ax`` (or makes one), returns it, labels axes in display units
(µm, s, ms) and never calls ``plt.show()``.

plot_events
    A run's elongation with the fitted staircase model, slips and excluded frames; a
    long run as an overview above zoomed windows.
plot_reduced_fit
    μs against rest time with each aging law's fitted curve and its confidence band
    (the paper's Fig. 10).
plot_reduced_rates
    dμs/dt_rest of the fitted laws against rest time, with bands (the paper's Fig. 11).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from identify.plots.base import pyplot

__all__ = ["ZOOM_SLIPS", "plot_events", "plot_reduced_fit", "plot_reduced_rates"]

_LEVEL = 0.95  # confidence level of the bands

_LAW_STYLE = {
    "exponential": dict(color="#d7191c", ls="-"),
    "logarithmic": dict(color="#2c7fb8", ls="--"),
    "logistic": dict(color="#1a9641", ls="-."),
}


ZOOM_SLIPS = 40
"""A run shown whole with more slips than this gets zoomed windows below its overview."""

_ZOOM_CYCLES = 6  # stick-slip cycles in each zoomed window
_ZOOM_LETTERS = "abc"
_FRAME = dict(ls="none", marker=".", ms=3, color="0.45", zorder=3)
_EXCLUDED = dict(ls="none", marker="x", ms=4, mew=1.0, color="#d7191c", zorder=4)
_MODEL = dict(lw=1.0, color="#2c7fb8", zorder=2)
_SLIP = dict(ls="none", marker="v", ms=5, mfc="none", mew=1.0, color="#d7191c", zorder=5)


def _new_ax(ax, figsize=(7, 4)):
    if ax is not None:
        return ax
    plt = pyplot()
    _, ax = plt.subplots(figsize=figsize, constrained_layout=True)
    return ax


def _zoom_windows(ts: np.ndarray, t0: float, t1: float) -> list:
    """Up to three windows of :data:`_ZOOM_CYCLES` stick-slip cycles each: after the
    first slip (the one from the fully aged contact, larger, is in the overview), in the
    middle and at the end of the slips, so that they share one elongation scale."""
    n = ts.size
    if n < 3:
        return []
    dt = float(np.median(np.diff(ts)))
    c = min(_ZOOM_CYCLES, n - 1)
    firsts = sorted({1, max((n - c) // 2, 1), n - c})
    return [(max(t0, float(ts[i]) - 0.6 * dt), min(t1, float(ts[i + c - 1]) + 0.6 * dt)) for i in firsts]


def _zoom_axes(ax, n: int) -> list:
    """``n`` axes in a row below ``ax``, which keeps the upper part of its slot; the
    figure grows to make room when ``ax`` is its only axes. [] when ``ax`` has no
    grid slot to share."""
    ss = ax.get_subplotspec()
    if ss is None or n == 0:
        return []
    fig = ax.figure
    if len(fig.axes) == 1:
        w, h = fig.get_size_inches()
        fig.set_size_inches(w, max(h, 0.8 * w))
    gs = ss.subgridspec(2, n, height_ratios=[1.0, 1.0])
    ax.set_subplotspec(gs[0, :])
    zooms = [fig.add_subplot(gs[1, 0])]
    zooms += [fig.add_subplot(gs[1, j], sharey=zooms[0]) for j in range(1, n)]
    return zooms


def _draw_events(events, ax, t0: float, t1: float, labels: bool) -> None:
    tr = events.trace
    t, e = tr.time_s, tr.elongation
    fp, phi = tr.step_frequency, events.step_phase
    sel = (t >= t0) & (t <= t1)
    keep = sel & (events.plateau_of_frame >= 0)
    out = sel & (events.plateau_of_frame < 0)
    lab = (lambda s: s) if labels else (lambda s: "_nolegend_")  # noqa: E731
    ax.plot(t[keep], e[keep] * 1e6, label=lab("camera frames"), **_FRAME)
    if out.any():
        ax.plot(t[out], e[out] * 1e6, label=lab("frames left out (inside a slip)"), **_EXCLUDED)
    # model: constant between step instants, the level changes at trigger steps
    n0 = max(math.floor(t0 * fp - phi), 0)
    n1 = math.ceil(t1 * fp - phi) + 1
    if n1 - n0 <= 200_000:
        knots = (np.arange(n0, n1 + 1) + phi) / fp
        knots = np.concatenate([[t0], knots[(knots > t0) & (knots < t1)], [t1]])
        ax.step(knots, events.model_elongation(knots) * 1e6, where="post", label=lab("staircase model"),
                **_MODEL)
    s = events.slips
    if events.n_slips:
        ts = s["trigger_time_s"]
        m = (ts >= t0) & (ts <= t1)
        ax.plot(ts[m], s["peak_elongation_m"][m] * 1e6, label=lab(f"slips ({events.n_slips}), at the peak"),
                **_SLIP)
    ax.set_xlim(t0, t1)


def plot_events(events, ax=None, t_window: tuple[float, float] | None = None):
    """Elongation (µm) against time (s): frames, the staircase model of the plateaus,
    slips and excluded frames.

    A run shown whole with more than :data:`ZOOM_SLIPS` slips, whose saw-tooth would
    merge into a band, becomes an overview (``ax``, the zoomed windows shaded) above
    three zoomed windows of a few cycles each — at the first slip, the middle and the
    end — drawn in new axes that share ``ax``'s grid slot (the figure grows when ``ax``
    is its only axes).

    Parameters
    ----------
    events : RunEvents
        From :func:`identify.traces.events.extract_events`.
    ax : matplotlib Axes, optional
    t_window : (t0, t1) in s, optional
        Time range shown, in one panel (default the whole run).

    Returns
    -------
    Axes
        The overview (or the only panel).
    """
    plt = pyplot()
    tr = events.trace
    t = tr.time_s
    t0, t1 = (float(t[0]), float(t[-1])) if t_window is None else map(float, t_window)
    ts = np.asarray(events.slips["trigger_time_s"], float) if events.n_slips else np.zeros(0)
    ts = ts[(ts >= t0) & (ts <= t1)]
    windows = _zoom_windows(ts, t0, t1) if t_window is None and ts.size > ZOOM_SLIPS else []
    if ax is None:
        _, ax = plt.subplots(figsize=(8, 6.4) if windows else (8, 4), constrained_layout=True)
    zooms = _zoom_axes(ax, len(windows))
    _draw_events(events, ax, t0, t1, labels=True)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("spring elongation (µm)")
    ax.set_title(
        f"{tr.name}: {events.regime}; camera noise σ = {events.noise_m * 1e9:.0f} nm, "
        f"step phase φ = {events.step_phase:.2f}",
        fontsize=9,
        pad=14 if zooms else 6,  # room for the windows' letters
    )
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, frameon=False)
    if zooms:
        from matplotlib.ticker import MaxNLocator
        from matplotlib.transforms import blended_transform_factory

        top = blended_transform_factory(ax.transData, ax.transAxes)
        for letter, (a, b), z in zip(_ZOOM_LETTERS, windows, zooms):
            ax.axvspan(a, b, color="#fee08b", alpha=0.7, lw=0, zorder=0)
            ax.text((a + b) / 2, 1.005, f"({letter})", transform=top, ha="center", va="bottom", fontsize=8)
            _draw_events(events, z, a, b, labels=False)
            z.set_title(f"({letter})", loc="left", fontsize=8, pad=3)
            z.xaxis.set_major_locator(MaxNLocator(nbins=3))
            z.tick_params(labelsize=8)
            z.set_xlabel("time (s)", fontsize=9)
        zooms[0].set_ylabel("spring elongation (µm)", fontsize=9)
        for z in zooms[1:]:
            z.tick_params(labelleft=False)
    return ax


def _t_grid(fit) -> np.ndarray:
    t = np.asarray(fit.t_rest_s, float)
    if t.size:
        lo, hi = float(t.min()) / 5, float(t.max()) * 5
    else:
        lo, hi = 1e-3, 10.0
    return np.logspace(math.log10(lo), math.log10(hi), 300)


def _band(fit, name: str, tg: np.ndarray, what: str = "predict", level: float = _LEVEL):
    """Pointwise ``level`` confidence band of a law's ``predict`` or ``rate`` at ``tg``,
    from :meth:`ReducedFit.covariance` (delta method, Student's t on n − free degrees of
    freedom; the rate's on its logarithm, so the band stays positive on a log axis);
    None without a covariance."""
    from scipy import stats

    names, cov = fit.covariance(name)
    dof = len(fit.t_rest_s) - len(names)
    if not names or dof < 1:
        return None
    f = fit.fits[name]
    log = what == "rate"

    def g(ff):
        y = getattr(ff, what)(tg)
        if not log:
            return y
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(y)

    G = np.empty((tg.size, len(names)))
    for j, p in enumerate(names):
        v = f.parameters[p]
        h = 1e-6 * max(abs(v), 1e-9)
        G[:, j] = (g(replace(f, parameters={**f.parameters, p: v + h}))
                   - g(replace(f, parameters={**f.parameters, p: v - h}))) / (2 * h)
    se = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", G, cov, G), 0, None))
    q = float(stats.t.ppf(0.5 + level / 2, dof))
    mid = g(f)
    lo, hi = mid - q * se, mid + q * se
    return (np.exp(lo), np.exp(hi)) if log else (lo, hi)


def _time_text(t_s: float) -> str:
    if t_s < 1e-3:
        return f"{t_s * 1e6:.3g} µs"
    if t_s < 1:
        return f"{t_s * 1e3:.3g} ms"
    return f"{t_s:.3g} s"


def _law_label(fit, name: str, f, d_aic: dict) -> str:
    """A law's legend entry: fit quality, rank, and any parameter held at a bound."""
    parts = []
    if math.isfinite(f.r2):
        parts.append(f"R² = {f.r2:.3f}")
    if name == fit.best:
        parts.append("best by AIC")
    elif math.isfinite(d_aic.get(name, math.nan)):
        parts.append(f"ΔAIC = {d_aic[name]:.1f}")
    lab = f"{name}\n  {', '.join(parts)}" if parts else name
    if not f.converged and "undetermined" in (f.message or ""):
        lab += ", undetermined"
    elif not f.converged:
        lab += ", not converged"
    loose = [p for p, v in f.parameters.items() if abs(f.stderr.get(p, math.nan)) > abs(v)]
    if loose:  # why its band is wide
        lab += f"\n  {', '.join(loose)}: error > 100 %"
    for p in f.at_bounds:
        v, side = f.parameters[p], f.bound_side(p)
        val = _time_text(v) if p in ("tau", "t_c") else f"{v:.3g}"
        lab += f"\n  {p} stuck at its {side} bound ({val})"
        if name == "logarithmic" and p == "t_c" and side == "lower":
            lab += ":\n  its best is a straight line in ln t"
    return lab


def _draw_laws(fit, ax, tg, what: str) -> tuple[bool, list]:
    """Each law's curve (``predict`` or ``rate``) and its confidence band; returns
    whether a band was drawn and the finite curve values."""
    d_aic = fit.delta_aic()
    banded, values = False, []
    for name, f in fit.fits.items():
        if not all(map(math.isfinite, f.parameters.values())):
            continue
        style = _LAW_STYLE.get(name, {})
        y = getattr(f, what)(tg)
        ok = np.isfinite(y) & ((y > 0) if what == "rate" else True)
        if not ok.any():
            continue
        values.append(y[ok])
        ax.plot(tg[ok] * 1e3, y[ok], lw=1.5, label=_law_label(fit, name, f, d_aic), zorder=3, **style)
        with np.errstate(all="ignore"):
            band = _band(fit, name, tg[ok], what)
        if band is not None:
            lo, hi = band
            fin = np.isfinite(lo) & np.isfinite(hi) & ((lo > 0) if what == "rate" else True)
            if fin.any():
                ax.fill_between(tg[ok][fin] * 1e3, lo[fin], hi[fin], color=style.get("color", "0.5"), alpha=0.15,
                                lw=0, zorder=1)
                banded = True
    return banded, values


def _legend(ax, banded: bool, **kw):
    from matplotlib.patches import Patch

    handles, labels = ax.get_legend_handles_labels()
    if banded:
        handles.append(Patch(color=_LAW_STYLE["exponential"]["color"], alpha=0.15, lw=0))
        labels.append(f"shaded, in each law's colour:\n  {_LEVEL:.0%} confidence band of the fit")
    return ax.legend(handles, labels, fontsize=7, **kw)


def plot_reduced_fit(fit, ax=None):
    """μs against rest time (log axis), a point per run and each law's fitted curve
    with its pointwise 95 % confidence band (the paper's Fig. 10). A parameter that ended
    on its bound is named in the legend (the logarithmic law's t_c at its lower bound:
    its best is then a straight line in ln t_rest).

    Parameters
    ----------
    fit : ReducedFit
    ax : matplotlib Axes, optional

    Returns
    -------
    Axes
    """
    ax = _new_ax(ax)
    pts = [(r.point(fit.source), u, r) for r, u in zip(fit.runs, fit.used)]
    used = np.array([p for p, u, _ in pts if u], float).reshape(-1, 2)
    unused_runs = [(p, r) for p, u, r in pts if not u and all(map(math.isfinite, p)) and p[0] > 0]
    unused = np.array([p for p, _ in unused_runs], float).reshape(-1, 2)
    tg = _t_grid(fit)
    banded, values = _draw_laws(fit, ax, tg, "predict")
    if used.size:
        ax.plot(used[:, 0] * 1e3, used[:, 1], "o", color="k", ms=5, zorder=5, label=f"runs ({len(used)})")
    if unused.size:
        why = sorted({r.regime for _, r in unused_runs if r.regime != "stick-slip"})
        ax.plot(unused[:, 0] * 1e3, unused[:, 1], "o", mfc="white", color="0.5", ms=5, zorder=5,
                label="runs not used" + (f" (regime: {', '.join(why)})" if why else ""))
    # the axis follows the data and the curves; a band wider than that is clipped
    ys = np.concatenate([used[:, 1], unused[:, 1]] + values)
    ys = ys[np.isfinite(ys)]
    if ys.size:
        lo, hi = float(ys.min()), float(ys.max())
        pad = 0.06 * max(hi - lo, 1e-3)
        ax.set_ylim(lo - pad, hi + pad)
    ax.set_xscale("log")
    ax.set_xlabel("rest time (ms)")
    ax.set_ylabel("static friction coefficient μs")
    ax.set_title(f"Static friction against rest time (points from the {fit.source})", fontsize=9)
    _legend(ax, banded, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, frameon=False)
    return ax


def plot_reduced_rates(fit, ax=None):
    """dμs/dt_rest (1/s) of the fitted laws against rest time, log–log, with pointwise
    95 % confidence bands (Fig. 11).

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
    banded, values = _draw_laws(fit, ax, tg, "rate")
    top = max((float(v.max()) for v in values), default=0.0)
    t = np.asarray(fit.t_rest_s, float)
    if t.size:  # a rug along the bottom: where the data constrain the rates
        from matplotlib.transforms import blended_transform_factory

        ax.plot(t * 1e3, np.full(t.size, 0.035), ls="none", marker="|", ms=10, mew=1.5, color="k", zorder=6,
                transform=blended_transform_factory(ax.transData, ax.transAxes), clip_on=False,
                label="rest times of the runs used")
    ax.set_xscale("log")
    ax.set_yscale("log")
    if top > 0:  # a saturated law's rate falls by many decades: show 6 of them
        ax.set_ylim(top * 1e-6, top * 3)
    ax.set_xlabel("rest time (ms)")
    ax.set_ylabel("aging rate dμs/dt_rest (1/s)")
    ax.set_title("Aging rate of the fitted laws", fontsize=9)
    _legend(ax, banded, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, frameon=False)
    return ax
