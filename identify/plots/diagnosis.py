"""Figures of a diagnosis (:meth:`identify.diagnosis.result.DiagnosisResult.save_plots`).

plot_misfit_by_feature
    Each feature test's misfit (σ) for the baseline and the final model, with the
    significance threshold.
plot_residual_vs_position
    The static-friction misfit of every slip against the block's position, a colour per
    run, with its ±1 σ band.
plot_gap_shrinkage
    Each candidate's gap (RMS feature misfit, nm) after its refit, held out and fitted,
    coloured by what the diagnosis made of it; bars from zero, the changes written out.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from identify.plots.base import pyplot, save_figure

__all__ = ["plot_misfit_by_feature", "plot_residual_vs_position", "plot_gap_shrinkage", "save_diagnosis_plots"]

LEGEND_FONT = 7
_BASELINE = "0.6"
_NOISE = "#41ab5d"
_MARKERS = "os^Dv<>pPX"  # a shape per run besides its colour: coinciding runs stay apart
_BOX = dict(fc="white", ec="none", alpha=0.9, pad=0.5)  # behind a value written over a line
_FINAL = "#2c7fb8"
# a candidate's held-out bar colour: what the diagnosis made of it (key, colour, legend text)
_STATUS = (
    ("named", "#2c7fb8", "named (added to the model)"),
    ("significant", "#f08a24", "significant, not named"),
    ("other", "0.6", "not significant"),
)


def _words(name: str) -> str:
    return str(name).replace("_", " ")


def _outside_legend(ax, handles=None, labels=None, **kw):
    """A legend right of the axes, where it covers no data."""
    args = () if handles is None else (handles, labels)
    return ax.legend(*args, fontsize=LEGEND_FONT, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                     borderaxespad=0.0, frameon=False, **kw)


def _finite(v) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return math.nan
    return v if math.isfinite(v) else math.nan


def plot_misfit_by_feature(result, ax=None):
    """Misfit of every feature (σ), baseline and final model."""
    from scipy import stats

    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(7.5, 4.0), constrained_layout=True)
    names = [m.feature for m in result.where]
    cap = min((getattr(m, "cap_sigma", math.inf) for m in result.where), default=math.inf)
    before = np.array([_finite(m.misfit_sigma) for m in result.where])
    after_map = {m.feature: _finite(m.misfit_sigma) for m in result.where_final}
    after = np.array([after_map.get(n, math.nan) for n in names])
    y = np.arange(len(names))
    two = bool(result.effects)
    h = 0.38 if two else 0.6
    ax.barh(y - (0.2 if two else 0.0), np.nan_to_num(before), height=h, color=_BASELINE, label="baseline")
    if two:
        ax.barh(y + 0.2, np.nan_to_num(after), height=h, color=_FINAL,
                label="final model: + " + ", ".join(map(_words, result.effects)))
    n = max(len(result.where), 1)
    alpha = result.options.alpha
    thr = float(stats.norm.isf(alpha / n / 2))
    ax.axvline(thr, color="#d7191c", ls="--", lw=1,
               label=f"significance threshold ({thr:.1f} σ:\nα = {alpha:g} over {n} tests)")
    top = max(thr, float(np.nanmax(np.r_[before, after, 0.0])))
    for vals, dy in ((before, -0.2 if two else 0.0), (after, 0.2)) if two else ((before, 0.0),):
        for yi, v in zip(y, vals):
            if not math.isfinite(v):
                ax.text(0.01 * top, yi + dy, "not tested", va="center", ha="left", fontsize=7, color="0.3",
                        style="italic")
            else:  # the value: a bar of zero length is a zero, not a gap in the figure
                ax.text(v + 0.01 * top, yi + dy, f"≥ {cap:g}" if v >= cap else f"{v:.1f}",
                        va="center", ha="left", fontsize=7, zorder=4, bbox=_BOX)
    ax.set_xlim(0, top * 1.12)
    ax.set_yticks(y, [_words(s) for s in names])
    ax.set_ylim(len(names) - 0.5, -0.5)  # the largest misfit on top
    ax.set_xlabel("misfit of the feature's test (σ: normal equivalent of its two-sided p-value)")
    ax.set_title(f"Where the model and the data part (verdict: {result.verdict})", fontsize=10)
    handles, labels = ax.get_legend_handles_labels()
    order = sorted(range(len(labels)), key=lambda i: labels[i].startswith("significance"))  # bars first
    _outside_legend(ax, [handles[i] for i in order], [labels[i] for i in order])
    return ax


def _short_names(names) -> list:
    """Run names without the first word (to the first "_") when they all share it: the
    coating, usually."""
    names = [str(n) for n in names]
    first = {n.split("_", 1)[0] + "_" for n in names if "_" in n}
    if len(names) > 1 and len(first) == 1 and all("_" in n for n in names):
        return [n.split("_", 1)[1] or n for n in names]
    return names


def plot_residual_vs_position(result, ax=None):
    """Static-friction (trigger) misfit, as elongation, against block position, a colour
    per run (the final model's when an effect was added, the baseline's in grey behind)."""
    from matplotlib.patches import Patch

    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(7.5, 4.0), constrained_layout=True)
    if result.baseline is None:
        ax.text(0.5, 0.5, "no baseline could be fitted", ha="center", transform=ax.transAxes)
        return ax
    models = result.trigger_misfit_by_run()
    if not models:
        ax.text(0.5, 0.5, "no slip follows another: no static-friction misfit", ha="center",
                transform=ax.transAxes)
        return ax
    shown = models[-1]
    if len(models) > 1:
        b = models[0]
        ax.plot(b["x_um"], b["misfit_nm"], ls="none", marker="o", ms=4, mfc="none", mec="0.6", mew=0.7,
                zorder=2, label=f"{_words(b['label'])} model, all runs (grey)")
    sig = float(np.nanmedian(shown["sigma_nm"])) if len(shown["sigma_nm"]) else math.nan
    if math.isfinite(sig):
        ax.axhspan(-sig, sig, color="0.9", lw=0, zorder=0,
                   label=f"±1 σ of one slip ({sig:.0f} nm:\none puller step / √12)")
    ax.axhline(0, color="k", lw=0.6, zorder=1)
    runs = list(dict.fromkeys(shown["run"].tolist()))
    cmap = plt.get_cmap("tab10" if len(runs) <= 10 else "tab20")
    short = _short_names(runs)
    title = ("baseline model" if shown["label"] == "baseline" else f"final model ({_words(shown['label'])})"
             ) + ", per run:"
    handles, labels = ax.get_legend_handles_labels()
    run_handles = []
    for k, (run, lab) in enumerate(zip(runs, short)):
        m = shown["run"] == run
        (line,) = ax.plot(shown["x_um"][m], shown["misfit_nm"][m], ls="none", marker=_MARKERS[k % len(_MARKERS)],
                          ms=4, color=cmap(k % cmap.N), mfc="none", mew=1.0, zorder=3, label=lab)
        run_handles.append(line)
    handles.append(Patch(visible=False))  # a heading for the runs
    labels.append(title)
    ax.set_xlabel("block position at the slip (µm)")
    ax.set_ylabel("static-friction misfit\n(nm of spring elongation)")
    ax.set_title("Static-friction misfit along the track\n(a ripple common to all runs would be topography)",
                 fontsize=10)
    _outside_legend(ax, handles + run_handles, labels + short)
    return ax


def _signed(d: float) -> str:
    txt = f"{d:+.2f}"
    return "0.00" if float(txt) == 0 else txt.replace("-", "−")


def _status(c) -> str:
    return "named" if c.get("named") else "significant" if c.get("significant") else "other"


def _why_no_gap(c) -> str:
    st = str(c.get("status") or "")
    if st == "Not_Differentiable":
        return "refit could not start (not differentiable there): no gap"
    if c.get("worse"):
        return "refit ended worse than the current model: no gap"
    if not c.get("ok"):
        return f"refit failed ({st or c.get('reason') or 'no reason given'})"
    return "no gap"


def plot_gap_shrinkage(result, ax=None):
    """Gap (RMS feature misfit, nm) after each candidate's refit (first round), held out
    (filled) and fitted (outlined), bars from zero; the colour says whether the candidate
    was named, significant or neither, and each bar's value and change are written out."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    plt = pyplot()
    if ax is None:
        _, ax = plt.subplots(figsize=(7.5, 4.0), constrained_layout=True)
    cands = [c for c in result.candidates if c.get("effect") and c.get("status") != "not applicable"]
    if not cands:
        ax.text(0.5, 0.5, "no candidate could be refitted", ha="center", transform=ax.transAxes)
        return ax
    nm = lambda v: _finite(v) * 1e3  # noqa: E731  (µm -> nm; None -> NaN)
    held = np.array([nm(c.get("heldout_gap_after_um")) for c in cands])
    fitted = np.array([nm(c.get("gap_after_um")) for c in cands])
    held0 = next((nm(c.get("heldout_gap_before_um")) for c in cands
                  if math.isfinite(nm(c.get("heldout_gap_before_um")))), math.nan)
    fit0 = next((nm(c.get("gap_before_um")) for c in cands if math.isfinite(nm(c.get("gap_before_um")))),
                math.nan)
    base = next((c for c in (result.rounds[0] if getattr(result, "rounds", None) else [])
                 if c.get("effect") is None and c.get("gap")), None)
    noise = nm(base["gap"].get("noise_um")) if base else math.nan
    colour = {k: col for k, col, _ in _STATUS}
    status = [_status(c) for c in cands]
    y = np.arange(len(cands))
    top = float(np.nanmax(np.r_[held, fitted, held0, fit0, noise, 1e-9]))
    if math.isfinite(noise):
        ax.axvline(noise, color=_NOISE, lw=1.5, zorder=3)
    ax.barh(y - 0.2, np.nan_to_num(held), height=0.38, color=[colour[s] for s in status], zorder=2)
    ax.barh(y + 0.2, np.nan_to_num(fitted), height=0.38, facecolor="white",
            edgecolor=[colour[s] for s in status], lw=1.2, zorder=2)
    if math.isfinite(held0):
        ax.axvline(held0, color="k", ls="--", lw=1, zorder=3)
    if math.isfinite(fit0):
        ax.axvline(fit0, color="k", ls=":", lw=1, zorder=3)
    note = dict(va="center", ha="left", fontsize=7, color="0.3", style="italic", zorder=4, bbox=_BOX)
    for yi, c, h_, f_ in zip(y, cands, held, fitted):
        for v, v0, dy, kind in ((h_, held0, -0.2, "held out"), (f_, fit0, 0.2, "fitted")):
            if math.isfinite(v):
                d = f" ({_signed(v - v0)})" if math.isfinite(v0) else ""
                ax.text(1.02 * top, yi + dy, f"{kind}: {v:.2f}{d}", va="center", ha="left", fontsize=7,
                        zorder=4)  # a column right of every bar and line
        if not math.isfinite(h_) and math.isfinite(f_):
            ax.text(0.01 * top, yi - 0.2, "no held-out gap", **note)
        elif not math.isfinite(h_):
            ax.text(0.01 * top, yi, _why_no_gap(c), **note)
    ax.set_xlim(0, top * 1.45)  # room for the values
    ax.set_yticks(y, [_words(c["effect"]) for c in cands])
    ax.set_ylim(len(cands) - 0.5, -0.5)
    ax.set_xlabel("gap after adding the candidate (nm): RMS misfit of the features")
    ax.set_title("Gap per candidate, first round (values in nm; change from the baseline)", fontsize=10)
    drawn = {s for s, h_, f_ in zip(status, held, fitted) if math.isfinite(h_) or math.isfinite(f_)}
    handles = [Patch(color=col, label=txt) for k, col, txt in _STATUS if k in drawn]
    handles.append(Patch(facecolor="white", edgecolor="0.35", lw=1.2,
                         label="outlined bar: runs fitted\n(filled: held out)"))
    if math.isfinite(held0):
        handles.append(Line2D([], [], color="k", ls="--", lw=1, label=f"baseline, held out ({held0:.2f} nm)"))
    if math.isfinite(fit0):
        handles.append(Line2D([], [], color="k", ls=":", lw=1, label=f"baseline, fitted ({fit0:.2f} nm)"))
    if math.isfinite(noise):
        handles.append(Line2D([], [], color=_NOISE, lw=1.5, label=f"noise floor ({noise:.2f} nm)"))
    _outside_legend(ax, handles, [h.get_label() for h in handles])
    return ax


def save_diagnosis_plots(result, folder) -> list:
    plt = pyplot()
    folder = Path(folder)
    paths = []
    for name, fn in (("misfit_by_feature", plot_misfit_by_feature),
                     ("residual_vs_position", plot_residual_vs_position),
                     ("gap_shrinkage", plot_gap_shrinkage)):
        fig, ax = plt.subplots(figsize=(7.5, 4.0), constrained_layout=True)
        fn(result, ax=ax)
        paths += save_figure(fig, folder / name)
        plt.close(fig)
    return paths
