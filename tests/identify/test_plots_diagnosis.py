"""Figures of a diagnosis, on a stand-in result (the attributes the plot functions read;
no diagnosis is run): tick labels apart, bars from zero, colours the legend explains,
legends legible and beside the data, the run of every slip told apart."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.colors import to_rgba

from identify.diagnosis.rounds import DiagnosisOptions
from identify.diagnosis.where import Misfit
from identify.plots.base import pyplot
from identify.plots.diagnosis import (
    plot_gap_shrinkage,
    plot_misfit_by_feature,
    plot_residual_vs_position,
    save_diagnosis_plots,
)
from identify.plots.legibility import legend_covers_data, legend_font_too_small, overlapping_tick_labels

FEATURES = ("creep_level", "static_friction_vs_rest", "post_slip_whiteness", "stick_slope", "post_slip_level",
            "time", "static_friction", "slip_length", "position")


class StandIn(SimpleNamespace):
    """What the figures read of a DiagnosisResult."""

    def trigger_misfit_by_run(self):
        return self.by_run

    def trigger_misfit_by_position(self):
        return [(d["label"], d["x_um"], d["misfit_nm"]) for d in self.by_run]


def _cand(effect, held_nm, fitted_nm, **kw):
    # gaps before as measured on data/FOTAS (held out 22.30 nm, fitted 20.79 nm)
    c = dict(effect=effect, ok=True, status="Solve_Succeeded", named=False, significant=False,
             gap_before_um=0.020788, heldout_gap_before_um=0.022301,
             gap_after_um=fitted_nm * 1e-3, heldout_gap_after_um=held_nm * 1e-3 if held_nm is not None else None)
    return {**c, **kw}


def _by_run(labels=("baseline",), n_runs=3, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for label in labels:
        runs = np.repeat([f"FOTAS_k2.13_Nb{5 * (i + 1)}uN_fp100Hz" for i in range(n_runs)], 20)
        x = np.tile(np.linspace(0.5, 28, 20), n_runs)
        out.append(dict(label=label, run=runs, x_um=x, misfit_nm=rng.normal(0, 10, x.size),
                        sigma_nm=np.full(x.size, 46 / math.sqrt(12))))
    return out


def _result(candidates, misfits=None, effects=(), final=None, labels=("baseline",)):
    misfits = misfits if misfits is not None else np.linspace(1.3, 0.0, len(FEATURES))
    where = [Misfit(f, float(s), float(2 * (1 - 0.5)), 0.0, "") for f, s in zip(FEATURES, misfits)]
    where_final = [Misfit(f, float(s), 0.5, 0.0, "") for f, s in zip(FEATURES, final)] if final is not None else []
    base = dict(effect=None, ok=True, gap=dict(gap_um=0.020788, noise_um=0.02117), heldout=dict(gap_um=0.022301))
    return StandIn(verdict="adequate", effects=list(effects), where=where, where_final=where_final,
                   candidates=candidates, rounds=[[base] + candidates], baseline=True,
                   options=DiagnosisOptions(effects=("drift", "step_size")), by_run=_by_run(labels))


# the case reported: two candidates, gaps within 0.1 nm of each other near 21-22 nm
MEASURED = [_cand("step_size", 22.27, 20.784), _cand("drift", 22.382, 20.791)]


@pytest.fixture
def ax():
    plt = pyplot()
    # the size the reported figures had (save_diagnosis_plots now makes them 7.5 in wide)
    fig, ax = plt.subplots(figsize=(6.5, 3.8), constrained_layout=True)
    yield ax
    plt.close("all")


def _legend_ok(ax):
    leg = ax.get_legend()
    assert leg is not None and leg.get_texts(), "no legend"
    assert legend_font_too_small(leg) == []
    return leg


# ----------------------------------------------------------------------------- gap shrinkage
def test_gap_figure_of_a_narrow_range_has_no_overlapping_tick_labels(ax):
    plot_gap_shrinkage(_result(MEASURED), ax=ax)
    assert overlapping_tick_labels(ax) == []


def test_gap_bars_start_at_zero(ax):
    plot_gap_shrinkage(_result(MEASURED), ax=ax)
    assert ax.get_xscale() == "linear" and ax.get_xlim()[0] == 0.0
    held, fitted = ax.containers[:2]
    for bars in (held, fitted):
        assert all(b.get_x() == 0.0 for b in bars)
    # the values the bars stand for, and their changes, are written out (0.1 nm is not a length)
    texts = [t.get_text() for t in ax.texts]
    assert any("22.27" in t and "−0.03" in t for t in texts), texts


def test_gap_colours_are_the_ones_the_legend_explains(ax):
    cands = [_cand("load_offset", 29.8, 20.8, named=True, significant=True),
             _cand("topography", 187.7, 120.5, significant=True), _cand("drift", 201.5, 115.0)]
    plot_gap_shrinkage(_result(cands), ax=ax)
    held = ax.containers[0]
    faces = [to_rgba(b.get_facecolor()) for b in held]
    assert len(set(faces)) == 3  # named, significant, neither: three colours
    leg = _legend_ok(ax)
    legend_colour = {t.get_text(): to_rgba(h.get_facecolor()) for t, h in zip(leg.get_texts(), leg.legend_handles)
                     if hasattr(h, "get_facecolor")}
    for face, what in zip(faces, ("named", "significant, not named", "not significant")):
        assert any(lab.startswith(what) and col == face for lab, col in legend_colour.items()), (what, legend_colour)
    # the title promises no colours (the legend says what they mean)
    title = ax.get_title().lower()
    assert not any(c in title for c in ("blue", "orange", "grey", "red", "green"))


def test_gap_legend_names_no_colour_that_no_bar_has(ax):
    plot_gap_shrinkage(_result(MEASURED), ax=ax)  # nothing named, nothing significant
    leg = _legend_ok(ax)
    labels = [t.get_text() for t in leg.get_texts()]
    assert not any(lab.startswith(("named", "significant")) for lab in labels), labels
    assert any(lab.startswith("not significant") for lab in labels)
    assert not any(c in ax.get_title().lower() for c in ("blue", "orange"))


def test_gap_legend_is_legible_and_covers_no_bar(ax):
    cands = [_cand(f"effect_{i}", 22.3 + 0.05 * i, 20.8, significant=i == 0) for i in range(12)]
    plot_gap_shrinkage(_result(cands), ax=ax)
    assert legend_covers_data(ax, _legend_ok(ax)) == []


def test_a_candidate_without_a_gap_says_why(ax):
    cands = [_cand("damping", None, 20.76), dict(_cand("aging_logarithmic", 1.0, 1.0), worse=True,
                                                  gap_after_um=math.nan, heldout_gap_after_um=math.nan),
             dict(effect="velocity_strengthening", ok=False, status="not applicable")]
    plot_gap_shrinkage(_result(cands), ax=ax)
    texts = [t.get_text() for t in ax.texts]
    assert "no held-out gap" in texts
    assert any("worse than the current model" in t for t in texts)
    assert [t.get_text() for t in ax.get_yticklabels()] == ["damping", "aging logarithmic"]  # not applicable: left out


# ----------------------------------------------------------------------------- misfit by feature
def test_misfit_legend_is_legible_and_beside_the_bars(ax):
    # every feature far past the threshold: a legend inside the axes would cover bars
    plot_misfit_by_feature(_result(MEASURED, misfits=np.linspace(40, 36, len(FEATURES)), effects=["drift"],
                                   final=np.linspace(39, 35, len(FEATURES))), ax=ax)
    leg = _legend_ok(ax)
    assert legend_covers_data(ax, leg) == []
    assert overlapping_tick_labels(ax) == []
    labels = [t.get_text() for t in leg.get_texts()]
    assert labels[0] == "baseline" and labels[1].startswith("final model") and "drift" in labels[1]
    assert any(lab.startswith("significance threshold") for lab in labels)


def test_misfit_bars_of_zero_are_written_out(ax):
    plot_misfit_by_feature(_result(MEASURED), ax=ax)
    assert ax.get_xlim()[0] == 0.0
    values = [t.get_text() for t in ax.texts]
    assert values.count("0.0") >= 1 and len(values) == len(FEATURES)
    assert [t.get_text() for t in ax.get_yticklabels()][0] == "creep level"  # plain words, largest on top


# ----------------------------------------------------------------------------- residual vs position
def test_residuals_tell_the_runs_apart_with_a_legend(ax):
    plot_residual_vs_position(_result(MEASURED), ax=ax)
    leg = _legend_ok(ax)
    labels = [t.get_text() for t in leg.get_texts()]
    runs = [lab for lab in labels if lab.startswith("k2.13")]  # the shared "FOTAS_" left out
    assert runs == ["k2.13_Nb5uN_fp100Hz", "k2.13_Nb10uN_fp100Hz", "k2.13_Nb15uN_fp100Hz"]
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    styles = {(to_rgba(lines[r].get_color()), lines[r].get_marker()) for r in runs}
    assert len(styles) == 3  # a colour and a shape per run
    assert any(lab.startswith("±1 σ of one slip") for lab in labels)  # the misfit's uncertainty
    assert legend_covers_data(ax, leg) == []


def test_residuals_of_a_final_model_show_the_baseline_behind(ax):
    plot_residual_vs_position(_result(MEASURED, effects=["drift"], labels=("baseline", "+ drift")), ax=ax)
    labels = [t.get_text() for t in _legend_ok(ax).get_texts()]
    assert labels[0].startswith("baseline model, all runs")
    assert "final model (+ drift), per run:" in labels


def test_save_diagnosis_plots_writes_three_figures(tmp_path):
    paths = save_diagnosis_plots(_result(MEASURED), tmp_path)
    assert len(paths) == 6 and all(p.stat().st_size > 0 for p in paths)
