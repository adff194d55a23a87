"""Plots of the design package (the paper's Fig. 3, spring sets, operating ranges).

Every function takes ``ax=None`` (a new figure is made with pyplot when None) and returns
the axes. Axes are in display units: spring constant k in N/m (x, log), normal load Nb in
µN (y, log); step frequency fp in Hz (x, log) for operating ranges. Nothing here calls
``plt.show()``.
"""

from __future__ import annotations

import numpy as np

from . import constraints as tc

# The functions read their argument's attributes (a SpringSet, SpringSetResult or
# OperatingRanges) without importing those classes: the results import the plots.

__all__ = ["plot_feasible_region", "plot_spring_set", "plot_design", "plot_operating_ranges"]

_UN = 1e6  # N -> µN


def _axes(ax):
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots(figsize=(6.0, 4.5))
    return ax


def plot_feasible_region(ax=None, *, k_limits_N_per_m: tuple[float, float] = (3e-3, 300.0),
                         color: str = "0.85", boundaries: bool = True):
    """Shade the Table I region: (k, Nb) allowed for every μ in [0.1, 0.9] (Fig. 3).

    Parameters
    ----------
    ax : matplotlib Axes, optional
    k_limits_N_per_m : (float, float)
        x-axis limits (N/m).
    color : str
        Fill colour of the allowed region.
    boundaries : bool
        Also draw the resolution (e = 90 nm at μ = 0.1) and travel (e = 100 µm at μ = 0.9)
        lines over the whole axis.

    Returns
    -------
    matplotlib Axes
    """
    ax = _axes(ax)
    k = np.geomspace(tc.K_MIN.bound, tc.K_MAX.bound, 400)
    lo, hi = tc.allowed_load_range(k)
    ok = np.isfinite(lo)
    ax.fill_between(k[ok], lo[ok] * _UN, hi[ok] * _UN, color=color, lw=0,
                    label=f"allowed by Table I for every μ in [{tc.MU_MIN.bound:g}, {tc.MU_MAX.bound:g}]")
    if boundaries:
        kk = np.geomspace(*k_limits_N_per_m, 50)
        lo_e, hi_e = tc.elongation_window(kk, kk)
        style = dict(color="0.5", lw=0.8, ls=":")
        ax.plot(kk, lo_e * _UN, **style,
                label="Table I limits: k, Nb, 90 nm resolution at μ = 0.1, 100 µm travel at μ = 0.9")
        ax.plot(kk, hi_e * _UN, **style)
        for c in (tc.LOAD_MIN, tc.LOAD_MAX):
            ax.axhline(c.bound * _UN, **style)
        for c in (tc.K_MIN, tc.K_MAX):
            ax.axvline(c.bound, **style)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(*k_limits_N_per_m)
    ax.set_ylim(tc.LOAD_MIN.bound * _UN / 3, tc.LOAD_MAX.bound * _UN * 3)
    ax.set_xlabel("spring constant k (N/m)")
    ax.set_ylabel("normal load Nb (µN)")
    return ax


def plot_spring_set(
    spring_set,
    ax=None,
    *,
    color: str = "C0",
    label: str | None = None,
    linestyle: str = "-",
):
    """Draw a spring set on the k–Nb plane.

    Each spring is a vertical segment at its nominal k over its allowed Nb range (worst case
    over the etch bias), with horizontal segments at both ends spanning its realised
    k range [k_soft, k_stiff].

    Returns
    -------
    matplotlib Axes
    """
    ax = _axes(ax)
    ks, kt = spring_set.spring_constant_ranges
    lo, hi = spring_set.load_ranges
    label = spring_set.label if label is None else label
    for i, k in enumerate(spring_set.spring_constants):
        if not np.isfinite(lo[i]):
            continue
        ax.plot([k, k], [lo[i] * _UN, hi[i] * _UN], color=color, ls=linestyle, lw=2,
                label=label if i == 0 else None)
        for y in (lo[i], hi[i]):
            ax.plot([ks[i], kt[i]], [y * _UN, y * _UN], color=color, ls="-", lw=1.5)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("spring constant k (N/m)")
    ax.set_ylabel("normal load Nb (µN)")
    return ax


def plot_design(result, ax=None):
    """Fig. 3 with an optimised set, the paper's set and the requested load range.

    The legend sits right of the axes (it covers no line); the requested-range lines are
    drawn over the springs' end caps they may coincide with.

    Returns
    -------
    matplotlib Axes
    """
    from matplotlib.lines import Line2D

    def wrap(text: str) -> str:
        return _wrap(text, 30)

    ax = plot_feasible_region(ax)
    lo, hi = result.load_range
    for y in (lo, hi):
        ax.axhline(y * _UN, color="C3", lw=1, ls="--", zorder=4)

    def ks(s) -> str:
        return ", ".join(f"{k:.3g}" for k in s.spring_constants) + " N/m"

    plot_spring_set(result.reference, ax, color="0.35", linestyle="--",
                    label=wrap("paper's set: " + ks(result.reference)))
    plot_spring_set(result.spring_set, ax, color="C0", label=wrap("optimised set: " + ks(result.spring_set)))
    handles, _ = ax.get_legend_handles_labels()
    for h in handles:
        if h.get_label().startswith("Table I limits"):
            h.set_label(wrap(h.get_label()))
        elif h.get_label().startswith("allowed"):
            h.set_label(wrap(h.get_label()))
    handles.append(Line2D([], [], color="C3", lw=1, ls="--",
                          label=wrap(f"requested load range ({lo * _UN:.3g}-{hi * _UN:.3g} µN)")))
    springs = {h: _HandlerSpring() for h in handles if h.get_label().endswith("N/m")}
    ax.legend(handles=handles, handler_map=springs, loc="upper left", bbox_to_anchor=(1.02, 1.0),
              fontsize=8, handleheight=1.6, alignment="left", title_fontsize=8,
              title=wrap("each spring: a bar over the loads it resolves for every μ, end caps "
                         f"over its k range at etch bias ±{result.etch_bias_um:g} µm"))
    ax.set_title(f"Spring sets in the Table I region, etch bias ±{result.etch_bias_um:g} µm per edge",
                 fontsize="medium")
    return ax


def plot_operating_ranges(ranges, ax=None):
    """Regime map of one spring over (fp, Nb) with its usable points (issue 4, item 4).

    Cells are coloured by the simulated regime (:func:`identify.plots.base.plot_regime_map`).
    Cells excluded by a rule other than the regime are hatched: ``..`` camera too slow (white,
    not simulated), ``//`` slips too short or too few, ``\\\\`` load outside the spring's
    Table I range (a cell failing both shows both, which no single hatch looks like).
    Usable cells carry a dot, drawn above every line. Dashed lines: the spring's Table I
    Nb limits that fall on the grid (the legend gives both values; the axes stay on the
    grid's cells).

    Returns
    -------
    matplotlib Axes
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    from identify.plots.base import plot_regime_map

    def wrap(text: str) -> str:
        return _wrap(text, 28)

    ax = _axes(ax)
    # OperatingRanges carries the attributes plot_regime_map reads from a RegimeMap.
    plot_regime_map(ranges, ax=ax)
    old = ax.get_legend()
    regimes = [h for h in (old.legend_handles if old is not None else [])
               if h.get_label() != "not simulated"]
    if old is not None:
        old.remove()
    fe, le = _cell_edges(ranges.step_frequencies_Hz), _cell_edges(ranges.normal_loads_uN)
    hatch_of = {"camera": "..", "slip_length": "//", "slip_count": "//", "table_i": "\\\\"}
    seen = set()
    for i, nb in enumerate(ranges.normal_loads_uN):
        for j, fp in enumerate(ranges.step_frequencies_Hz):
            rules = [r for r, _ in ranges.failed[i, j]]
            if not rules:
                ax.plot(fp, nb, "o", color="k", mec="w", ms=6, zorder=5)
                seen.add("usable")
            for hatch in dict.fromkeys(hatch_of[r] for r in rules if r in hatch_of):
                ax.add_patch(Rectangle((fe[j], le[i]), fe[j + 1] - fe[j], le[i + 1] - le[i],
                                       fill=False, lw=0, ec="0.15", hatch=hatch, zorder=2))
                seen.add(hatch)
    lo, hi = ranges.normal_load_range_uN
    for y in (lo, hi):
        if le[0] <= y <= le[-1]:
            ax.axhline(y, color="k", lw=1.2, ls="--", zorder=3)
    r = ranges.rules
    extra = {
        "usable": Line2D([], [], ls="", marker="o", ms=6, color="k", mec="w",
                         label="usable (every rule holds)"),
        "//": Patch(fill=False, hatch="//", ec="0.15",
                    label=wrap(f"excluded: slips shorter than {r.min_slip_m * 1e9:g} nm or fewer "
                               f"than {r.min_slips} slips in {ranges.travel_um:g} µm of travel")),
        "\\\\": Patch(fill=False, hatch="\\\\", ec="0.15",
                      label=wrap("excluded: load outside the spring's Table I range")),
        "..": Patch(fill=False, hatch="..", ec="0.15",
                    label=wrap(f"not simulated: camera too slow above {r.max_step_frequency_Hz:g} Hz")),
    }
    handles = regimes + [h for key, h in extra.items() if key in seen]
    handles.append(Line2D([], [], ls="--", color="k", lw=1.2,
                          label=wrap(f"Table I load limits ({lo:.3g} and {hi:.3g} µN)")))
    ax.legend(handles=handles, fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    return ax


def _wrap(text: str, width: int) -> str:
    """Wrap a legend label, never between a number and its unit."""
    import textwrap

    for unit in ("µN", "µm", "nm", "N/m", "Hz"):
        text = text.replace(" " + unit, "\u00a0" + unit)
    return textwrap.fill(text, width)


def _HandlerSpring():
    """Legend handler drawing a spring as the plot does: a bar with end caps (an 'I')."""
    from matplotlib.legend_handler import HandlerBase
    from matplotlib.lines import Line2D

    class Handler(HandlerBase):
        def create_artists(self, legend, orig_handle, xdescent, ydescent, width, height,
                           fontsize, trans):
            x, y0, y1 = width / 2 - xdescent, -ydescent, height - ydescent
            c = orig_handle.get_color()
            bar = Line2D([x, x], [y0, y1], color=c, lw=orig_handle.get_linewidth(),
                         ls=orig_handle.get_linestyle(), transform=trans)
            caps = [Line2D([x - width / 4, x + width / 4], [y, y], color=c, lw=1.5, transform=trans)
                    for y in (y0, y1)]
            return [bar, *caps]

    return Handler()


def _cell_edges(v: np.ndarray) -> np.ndarray:
    """Cell edges on a log axis around grid values ``v`` (as the regime map draws them)."""
    lv = np.log10(np.asarray(v, float))
    d0 = (lv[1] - lv[0]) / 2 if lv.size > 1 else 0.5
    d1 = (lv[-1] - lv[-2]) / 2 if lv.size > 1 else 0.5
    return 10 ** np.concatenate([[lv[0] - d0], (lv[1:] + lv[:-1]) / 2, [lv[-1] + d1]])
