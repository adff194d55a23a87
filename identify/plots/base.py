"""Figures a researcher would put in a paper. Every function takes ``ax``/``axes`` (or
makes them), returns them, labels axes in display units (µm, µN, ms) and never calls
``plt.show()``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["plot_simulation", "plot_regime_map", "save_figure"]

_REGIME_COLOURS = {
    "stick-slip": "#2c7fb8",
    "stepping": "#fdae61",
    "creep": "#d7191c",
    "no-slip": "#bdbdbd",
    "error": "#000000",
}


def pyplot():
    import matplotlib

    if matplotlib.get_backend().lower() not in ("agg", "pdf", "svg", "ps", "cairo") and not _interactive():
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _interactive() -> bool:
    import sys

    return hasattr(sys, "ps1") or "ipykernel" in sys.modules


def save_figure(fig, path) -> list:
    """Save ``fig`` to ``path``; a path without suffix gets both .png and .pdf."""
    from pathlib import Path

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    # run names carry dots (k2.13): only a known figure format counts as a suffix
    if p.suffix.lower() in (".png", ".pdf", ".svg", ".eps", ".jpg", ".jpeg", ".tif", ".tiff"):
        paths = [p]
    else:
        paths = [p.with_name(p.name + ".png"), p.with_name(p.name + ".pdf")]
    for q in paths:
        fig.savefig(q, dpi=200, bbox_inches="tight")
    return paths


def plot_simulation(result, axes: Sequence | None = None, t_window: tuple[float, float] | None = None,
                    n_slips: int = 4):
    """The five panels of the paper's Fig. 13 for a simulated run.

    (a) puller and block positions, (b) block velocity, (c) spring elongation,
    (d) contact state ψ, (e) friction capacity F0 = μ·N against the spring force.

    Parameters
    ----------
    result : SimulationResult
    axes : sequence of 5 Axes, optional
    t_window : (t0, t1) in s, optional
        Default: from just before the second slip to just after the ``n_slips``-th later
        one (the first slip starts from the fully aged contact).
    """
    plt = pyplot()
    if axes is None:
        fig, axes = plt.subplots(5, 1, figsize=(7, 10), sharex=True, constrained_layout=True)
    c = result.conditions
    t0, t1 = _simulation_window(result, n_slips) if t_window is None else t_window
    t = _simulation_times(result, t0, t1)
    bounds = _draw_simulation_panels(axes, result, t)
    _frame_simulation_panels(axes, bounds)
    axes[0].set_title(
        f"{result.coating + ', ' if result.coating else ''}k = {c.spring_constant:g} N/m, "
        f"$N_b$ = {c.normal_load * 1e6:g} µN, $f_p$ = {c.step_frequency:g} Hz (regime: {result.regime})",
        fontsize=10,
    )
    return axes


def plot_simulation_elongation(result, ax, t_window: tuple[float, float] | None = None, n_slips: int = 4):
    """Panel (c) of :func:`plot_simulation` alone on ``ax``: the spring elongation over
    the same window, titled with the run's conditions and regime. Returns ``ax``. Reached
    through :meth:`identify.simulation.result.SimulationResult.plot` with one Axes."""
    t0, t1 = _simulation_window(result, n_slips) if t_window is None else t_window
    t = _simulation_times(result, t0, t1)
    ax.plot(t * 1e3, result.elongation(t) * 1e6, color="C2")
    ax.set_xlabel("time (ms)")
    ax.set_ylabel("spring elongation (µm)")
    c = result.conditions
    ax.set_title(f"{result.coating + ', ' if result.coating else ''}k = {c.spring_constant:g} N/m, "
                 f"$N_b$ = {c.normal_load * 1e6:g} µN, $f_p$ = {c.step_frequency:g} Hz "
                 f"(regime: {result.regime})", fontsize=10)
    return ax


def _simulation_window(result, n_slips: int) -> tuple[float, float]:
    """Default time window of :func:`plot_simulation`: from just before the second slip to
    just after the ``n_slips``-th later one, or the whole run with fewer than 2 slips."""
    ev = result.slips
    c = result.conditions
    if len(ev) < 2:
        return 0.0, c.end_time
    i0 = 1
    i1 = min(len(ev) - 1, i0 + n_slips)
    t0 = ev["time_s"][i0] - 0.25 * max(ev["rest_time_s"][i0], 1 / c.step_frequency)
    t1 = ev["time_s"][i1] + ev["duration_s"][i1] + 0.1 * max(ev["rest_time_s"][i1], 1 / c.step_frequency)
    if i1 == i0:
        t1 = min(c.end_time, t0 + 3 * max(ev["rest_time_s"][i0], 1 / c.step_frequency))
    return t0, t1


def _simulation_times(result, t0: float, t1: float) -> np.ndarray:
    """Times to draw in [t0, t1]: an even grid, the integrator's own points, and both
    sides of every puller step so the staircases come out crisp."""
    c = result.conditions
    t = np.linspace(t0, t1, 4000)
    extra = [ph.t for ph in result.phases]
    if extra:
        t = np.unique(np.concatenate([t] + [x[(x >= t0) & (x <= t1)] for x in extra]))
    # values just after each step instant, for crisp staircases
    n_first = int(np.ceil((t0 - c.t_first) * c.step_frequency))
    steps = c.t_first + np.arange(max(n_first, 0), c.n_steps) / c.step_frequency
    steps = steps[(steps >= t0) & (steps <= t1)]
    return np.unique(np.concatenate([t, steps, steps - 1e-12]))


def _draw_simulation_panels(ax, result, t: np.ndarray) -> list:
    """Draw the curves of the five panels of Fig. 13 at times ``t``; returns the state limits
    [μmin, μmax] drawn in panel (d)."""
    P = result._P
    model = result.model
    xp = result.puller_position(t)
    x = result.block_position(t)
    v = result.velocity(t)
    state = result.state_at(t)
    e = xp - x
    N = model.normal_load(P)
    psi = model.law.static_coefficient(state, P)
    # at rest the capacity is what holds the block (with the stick band when that option is on)
    cap = np.where(v == 0, model.hold_coefficient(state, x, P),
                   model.friction_coefficient(state, np.abs(v), x, P)) * N
    spring = model.spring_force(e, P)
    tm = t * 1e3
    ax[0].plot(tm, xp * 1e6, color="0.5", label="puller $x_p$")
    ax[0].plot(tm, x * 1e6, color="C0", label="block $x$")
    ax[0].set_ylabel("position (µm)")
    # cm/s for slips; a creeping block (well under 1 mm/s) in µm/s, not as 0.0004 cm/s
    vmax = float(np.nanmax(np.abs(v))) if v.size else 0.0
    v_scale, v_unit = (1e2, "cm/s") if vmax >= 1e-3 else (1e6, "µm/s")
    ax[1].plot(tm, v * v_scale, color="C1")
    ax[1].set_ylabel(f"velocity ({v_unit})")
    ax[2].plot(tm, e * 1e6, color="C2")
    ax[2].set_ylabel("spring elongation (µm)")
    ax[3].plot(tm, psi, color="C3", label=r"state $\psi$")
    bounds = [P.get(n, np.nan) for n in ("mu_min", "mu_max")]
    for b, lab in zip(bounds, (r"limits $\mu_{min}$, $\mu_{max}$", None)):
        ax[3].axhline(b, color="0.45", ls=":", lw=1, label=lab)
    ax[3].set_ylabel("friction state ψ (–)")
    # the capacity wide under the spring force: where they are equal (slips, creep) both show
    ax[4].plot(tm, cap * 1e6, color="C3", lw=2.0, zorder=2, label=r"friction capacity $F_0=\mu N_b$")
    ax[4].plot(tm, spring * 1e6, color="C2", lw=1.0, zorder=3, label=r"spring force $k\,e$")
    ax[4].set_ylabel("force (µN)")
    ax[4].set_xlabel("time (ms)")
    return bounds


def _frame_simulation_panels(ax, bounds: list) -> None:
    """Y limits, panel letter and legend of each Fig. 13 panel: a band above the data
    (sized in points) keeps the letter and the legend off the curves whatever the run."""
    fig = ax[0].figure
    for a, letter, extra in zip(ax, "abcde", ([], [], [], bounds, [])):
        ys = [ln.get_ydata() for ln in a.get_lines() if len(ln.get_xdata()) > 2] + [np.asarray(extra, float)]
        y = np.concatenate([np.ravel(np.asarray(v, float)) for v in ys])
        y = y[np.isfinite(y)]
        if y.size:
            lo, hi = float(y.min()), float(y.max())
            r = hi - lo if hi > lo else max(abs(hi), 1e-12)
            h_pt = a.get_position().height * fig.get_figheight() * 72 * 0.85
            top = min(max(1 - 24 / max(h_pt, 1.0), 0.55), 0.85)  # data below this fraction
            span = r / (top - 0.04)
            a.set_ylim(lo - 0.04 * span, lo - 0.04 * span + span)
        a.text(0.005, 0.98, f"({letter})", transform=a.transAxes, ha="left", va="top", fontsize=9,
               fontweight="bold")
        if a.get_legend_handles_labels()[0]:
            a.legend(loc="upper right", fontsize=8, ncol=2, frameon=False, borderaxespad=0.2,
                     handlelength=1.6, columnspacing=1.2)


def plot_regime_map(rmap, ax=None):
    """Regimes over (Nb, fp) for one spring, as coloured cells on log axes.

    One cell per grid point, centred on it; the ticks sit at the grid values (thinned
    where their labels would touch, the rest as minor ticks). White cells were not
    simulated. The legend, right of the axes, names the regimes present.
    """
    from matplotlib import rcParams
    from matplotlib.font_manager import FontProperties
    from matplotlib.patches import Patch
    from matplotlib.ticker import FixedLocator, Locator, NullFormatter

    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(5.5, 4), constrained_layout=True)
    loads = np.asarray(rmap.normal_loads_uN, float)
    freqs = np.asarray(rmap.step_frequencies_Hz, float)

    def edges(v):
        lv = np.log10(v)
        mid = (lv[1:] + lv[:-1]) / 2
        d0 = (lv[1] - lv[0]) / 2 if len(lv) > 1 else 0.5
        d1 = (lv[-1] - lv[-2]) / 2 if len(lv) > 1 else 0.5
        return 10 ** np.concatenate([[lv[0] - d0], mid, [lv[-1] + d1]])

    def label(v: float) -> str:  # 3 significant digits, no exponent for 1000 Hz
        g = float(f"{v:.3g}")
        return f"{g:.0f}" if 100 <= g < 1e6 else f"{g:g}"

    class GridLocator(Locator):
        """The grid values whose labels do not touch at the axis' drawn size, kept in
        order from the lowest (measured when the figure is drawn, after the layout)."""

        def __init__(self, values, vertical):
            self.values, self.vertical = np.sort(np.asarray(values, float)), vertical
            size = rcParams["ytick.labelsize" if vertical else "xtick.labelsize"]
            self.size_pt = FontProperties(size=size).get_size_in_points()

        def __call__(self):
            axis = self.axis
            if axis is None or axis.axes is None:
                return self.values
            tr = axis.axes.transData
            xy = np.column_stack([self.values, self.values])
            pos = tr.transform(xy)[:, 1 if self.vertical else 0]
            px = axis.axes.figure.dpi / 72 * self.size_pt
            kept, last = [], -np.inf
            for v, p in zip(self.values, pos):
                need = 1.6 * px if self.vertical else 0.62 * px * len(label(v)) + 0.8 * px
                if p - last >= need:
                    kept.append(v)
                    last = p
            return np.asarray(kept)

    fe, le = edges(freqs), edges(loads)
    for i in range(len(loads)):
        for j in range(len(freqs)):
            col = _REGIME_COLOURS.get(rmap.regimes[i, j], "white")
            ax.fill_between([fe[j], fe[j + 1]], le[i], le[i + 1], color=col, lw=0)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(fe[0], fe[-1])
    ax.set_ylim(le[0], le[-1])
    for axis, v, vertical in ((ax.xaxis, freqs, False), (ax.yaxis, loads, True)):
        axis.set_major_locator(GridLocator(v, vertical))
        axis.set_major_formatter(lambda x, _pos: label(x))
        axis.set_minor_locator(FixedLocator(v))
        axis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("step frequency $f_p$ (Hz)")
    ax.set_ylabel("normal load $N_b$ (µN)")
    opt = ("equations as written" if not rmap.stick_speed_m_per_s
           else f"stick threshold {rmap.stick_speed_m_per_s * 1e6:g} µm/s")
    ax.set_title(f"{rmap.coating}, k = {rmap.spring_constant_N_per_m:g} N/m ({opt})", fontsize=10)
    seen = set(np.asarray(rmap.regimes).ravel())
    handles = [Patch(color=_REGIME_COLOURS[r], label=r) for r in _REGIME_COLOURS if r in seen]
    if seen - set(_REGIME_COLOURS):
        handles.append(Patch(fc="white", ec="0.5", lw=0.8, label="not simulated"))
    ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0),
              title="regime", title_fontsize=8)
    return ax
