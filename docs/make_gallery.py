"""Regenerate the figure gallery: every kind of figure the toolkit makes, on the bundled data.

    python docs/make_gallery.py            # every section, a few minutes on 2 cores
    python docs/make_gallery.py fit design # only these sections' images

Each section makes its figures the way a user does (the result objects' ``save_plots``
and ``plot`` methods, into a scratch folder), and the figures the gallery shows are
copied into ``docs/gallery/`` as PNG, scaled to at most 1400 px wide. The page,
``docs/gallery.rst``, is written from the same declarations (:data:`GALLERY`), so the
page and the files cannot disagree. A section that fails is reported and the others
still run; the script then exits 1.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "gallery"
PAGE = HERE / "gallery.rst"
DATA = HERE.parent / "data" / "FOTAS"
MAX_WIDTH_PX = 1400


@dataclass(frozen=True)
class Figure:
    pattern: str  # which of the section's files (glob)
    file: str  # its name in docs/gallery/
    title: str
    caption: str
    draws: tuple = ()  # the plotting functions (identify.plots.*, design.plots) that draw it


@dataclass(frozen=True)
class Section:
    title: str
    made_by: str  # the calls and commands that make these figures
    figures: tuple


GALLERY: dict[str, Section] = {
    "simulate": Section(
        "Simulation", "``identify.plots.base.plot_simulation(identify.simulate(...))``; "
        "``python -m identify simulate ... --plot``",
        (Figure("fig13.png", "simulation_fig13.png", "A simulated run (the paper's Fig. 13)",
                "Puller and block positions, block speed, spring elongation, contact state ψ and friction "
                "capacity against the spring force, over a few slips of a 2.13 N/m spring at 5 µN and "
                "100 Hz under the stick option.", draws=("plot_simulation",)),)),
    "regimes": Section(
        "Regime map", "``identify.simulation.regimes.regime_map(...).plot()``; "
        "``python -m identify regimes ... --plot FILE``",
        (Figure("regimes.png", "regime_map.png", "Regime map of one spring",
                "The simulated regime (stick-slip, stepping, creep) over normal load and puller "
                "frequency for the 2.13 N/m spring under the stick option.", draws=("plot_regime_map",)),)),
    "analyze": Section(
        "Reduced analysis (the paper's method)", "``identify.analyze([...]).save_plots(DIR)``; "
        "``python -m identify analyze DATA --plots DIR``",
        (Figure("events_*k20.3_Nb30uN_fp100Hz*.png", "events_dense.png", "Events of a run with many slips",
                "Slips and stick plateaus detected in a stiff-spring run (20.3 N/m, 30 µN, 100 Hz).",
                draws=("plot_events",)),
         Figure("events_*k2.13_Nb30uN_fp10Hz*.png", "events_sparse.png", "Events of a run with few slips",
                "The same for a soft spring at 10 Hz: long loadings, few slips.", draws=("plot_events",)),
         Figure("fig10*.png", "analyze_fig10.png", "Static friction against rest time (Fig. 10)",
                "Static friction against rest time with the aging laws fitted across runs (Eq. 9).",
                draws=("plot_reduced_fit",)),
         Figure("fig11*.png", "analyze_fig11.png", "Aging rates (Fig. 11)",
                "The reduced analysis' aging rates against the laws' prediction.", draws=("plot_reduced_rates",)))),
    "fit": Section(
        "Full-model fit", "``identify.fit(...).save_plots(DIR)``; ``python -m identify fit DATA --plots DIR``",
        (Figure("fit_*k20.3_Nb30uN_fp100Hz.png", "fit_run_dense.png", "One run's fit: many slips",
                "Data (grey) and the fitted model as the staircase of puller steps and slips it is; "
                "data − model under it with the ±2σ noise band; below, zooms on the slip the model misses "
                "most and on a typical one (shaded above).", draws=("plot_run_fit",)),
         Figure("fit_*k2.13_Nb30uN_fp10Hz.png", "fit_run_sparse.png", "One run's fit: few slips",
                "The same for a soft spring at 10 Hz.", draws=("plot_run_fit",)),
         Figure("static_friction_vs_rest.png", "fit_static_friction.png", "Static friction against rest time",
                "Every slip's μs = k·e_peak/Nb against the rest before it, per run, with the fitted law "
                "(plus the stick band when the stick option is on) and its 95 % band from the covariance.",
                draws=("plot_static_friction",)),
         Figure("slip_force_drop_vs_load.png", "fit_slip_force_drop.png", "Slip force drop against load",
                "Each run's mean k·δ (± 95 %) and the model's; colour is the spring, marker the puller "
                "frequency; the lower panel is their difference.", draws=("plot_slip_lengths",)),
         Figure("residuals.png", "fit_residuals.png", "Normalised residuals",
                "Plateau-level residuals against block position per run, and the slip triggers' residuals.",
                draws=("plot_residuals",)),
         Figure("profile_tau.png", "fit_profile_tau.png", "Profile likelihood",
                "Δχ² of constrained refits against τ, the 95 % threshold and the profile interval, beside "
                "the parabola of the reported standard error.", draws=("plot_profile",)))),
    "diagnose": Section(
        "Diagnosis of the sim-to-real gap", "``identify.diagnose(...).save_plots(DIR)``; "
        "``python -m identify diagnose DATA --json FILE --plots DIR``",
        (Figure("misfit_by_feature.png", "diagnose_misfit_by_feature.png", "Where the misfit lives",
                "Each feature's misfit for the baseline and the final model, against the significance line.",
                draws=("plot_misfit_by_feature",)),
         Figure("residual_vs_position.png", "diagnose_residual_vs_position.png", "Residual against position",
                "Static-friction misfit against block position per run: a ripple common to every run is "
                "topography.", draws=("plot_residual_vs_position",)),
         Figure("gap_shrinkage.png", "diagnose_gap_shrinkage.png", "Gap shrinkage per candidate",
                "The gap after adding each candidate effect, fitted and on held-out runs.",
                draws=("plot_gap_shrinkage",)))),
    "design": Section(
        "Design", "``design_spring_set(...).plot()``, ``operating_ranges(...).plot()``, "
        "``design_experiment(...).plot()``; ``python -m design springs|ranges|experiment ... --plot FILE``",
        (Figure("springs.png", "design_springs_fig3.png", "Spring set (the paper's Fig. 3)",
                "The Table I region in the k–Nb plane with the optimised spring set and the paper's.",
                draws=("plot_design", "plot_feasible_region", "plot_spring_set")),
         Figure("ranges.png", "design_ranges.png", "Operating ranges of one spring",
                "Regime over (Nb, fp) for the 2.13 N/m spring; the points Table I excludes are hatched.",
                draws=("plot_operating_ranges", "plot_regime_map")),
         Figure("experiment.png", "design_experiment.png", "Experiment plan",
                "Predicted relative standard errors of each parameter for a D-optimal plan of four runs and "
                "for the paper's conditions.", draws=("ExperimentPlan.plot",)))),
    "lab": Section(
        "Laboratory data: a velocity step", "``identify.fit_transient(...).plot()``; "
        "``python -m identify import ...`` then ``python -m identify fit DATA --law aging --plots DIR``",
        (Figure("transient_*.png", "lab_velocity_step.png", "A velocity step fitted with the aging law",
                "The Penn State p655 gouge (data/real/p655): friction against load-point displacement through "
                "the step 2.28 → 22.85 µm/s at 100 MPa, the aging law fitted at the lab's stiffness 1e-3/µm; "
                "data − model below.", draws=("plot_transient_fit",)),
         Figure("cycles_*.png", "lab_stick_slip_cycles.png", "Stick-slip cycles under a constant drive",
                "Colas et al.'s paper on paper (data/real/colas2019), 168 N/m at 42 µm/s: each slip's force drop "
                "against the time until the next slip, beside the line a sawtooth follows.",
                draws=("plot_cycles",)))),
    "imports": Section(
        "Package structure", "``python docs/import_graph.py``, which also checks it",
        (Figure("import-graph.png", "import-graph.png", "Import graph",
                "The rooms of the package (the subpackages of identify, its top-level modules, the command "
                "lines, design) on floors by the longest chain of imports below them: every arrow points down "
                "and none goes round a circle. Dashed arrows are imports made only inside functions.",),)),
}


# ----------------------------------------------------------------------------- makers
def _save(fig, path: Path) -> None:
    from identify.plots.base import pyplot, save_figure

    try:
        save_figure(fig, path)
    finally:
        pyplot().close(fig)


def make_simulate(folder: Path) -> None:
    import identify
    from identify.plots.base import plot_simulation

    run = identify.simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=5, step_frequency_Hz=100,
                            travel_um=20, stick_speed_m_per_s=1e-5)
    _save(plot_simulation(run)[0].figure, folder / "fig13.png")


def make_regimes(folder: Path) -> None:
    from identify.simulation.regimes import regime_map

    m = regime_map("FOTAS", 2.13, [2, 5, 10, 30, 60], [10, 100, 1000, 10000], None, 1e-5)
    _save(m.plot().figure, folder / "regimes.png")


def make_analyze(folder: Path) -> None:
    import identify

    identify.analyze([str(DATA)]).save_plots(folder)


_FIT: dict = {}


def _fit():
    import identify

    if "result" not in _FIT:
        res = identify.fit([str(DATA)], options=identify.FitOptions(fixed={"v_stick": 1e-5}))
        _FIT["result"] = res.with_profiles(res.profile("tau", n_points=7))
    return _FIT["result"]


def make_fit(folder: Path) -> None:
    _fit().save_plots(folder)


def make_diagnose(folder: Path) -> None:
    import identify

    opts = identify.DiagnosisOptions(effects=("drift", "step_size"), workers=1)
    identify.diagnose(None, baseline=_fit(), options=opts).save_plots(folder)


def make_design(folder: Path) -> None:
    from design import design_experiment
    from design.ranges import operating_ranges
    from design.spring_set import design_spring_set
    from identify.plots.base import pyplot

    plt = pyplot()

    def draw(result, name):
        fig, ax = plt.subplots(figsize=(7, 5), layout="constrained")
        result.plot(ax=ax)
        _save(fig, folder / name)

    draw(design_spring_set((0.5, 450.0)), "springs.png")
    draw(operating_ranges(2.13, "FOTAS", loads_uN=[2, 5, 10, 20, 30], fps_Hz=[10, 100, 1000]), "ranges.png")
    draw(design_experiment(4, "FOTAS"), "experiment.png")


def make_lab(folder: Path) -> None:
    import identify

    p655 = HERE.parent / "data" / "real" / "p655"
    look = identify.apply_recipe(identify.read_look(p655 / "p655intact100l"), p655 / "p655_r-reduction.txt")
    trace = identify.import_run(look, friction="mu", time="Time", load_point="LP_disp", stiffness_per_um=1e-3,
                                window_s=(3847.35, 3857.35), velocities_um_per_s=[2.28, 22.85], name="p655").trace
    res = identify.fit_transient(identify.TransientRun.from_trace(trace), law="aging")
    _save(res.plot()[0].figure, folder / "transient_p655.png")
    colas = identify.read_mat(HERE.parent / "data" / "real" / "colas2019" / "k168Nm_v42.mat")
    cyc = identify.analyze_cycles(colas["t"].values, colas["Fnorm"].values, drive_rate=168 * 42e-6 / 0.301,
                                  name="k168, 42 µm/s")
    _save(cyc.plot().figure, folder / "cycles_k168_v42.png")


def make_imports(folder: Path) -> None:
    import subprocess

    # its own script, so that it runs without the gallery; it exits 1 on a circle
    subprocess.run([sys.executable, str(HERE / "import_graph.py"), "--out", str(folder / "import-graph.png")],
                   check=True)


MAKERS = {"simulate": make_simulate, "regimes": make_regimes, "analyze": make_analyze, "fit": make_fit,
          "diagnose": make_diagnose, "design": make_design, "lab": make_lab, "imports": make_imports}


# ----------------------------------------------------------------------------- output
def keep(folder: Path, fig: Figure) -> Path:
    """Copy the section's figure matching ``fig.pattern`` into the gallery, scaled down."""
    from PIL import Image

    hits = sorted(folder.glob(fig.pattern))
    if not hits:
        raise FileNotFoundError(f"no figure matching {fig.pattern!r} among {sorted(p.name for p in folder.iterdir())}")
    OUT.mkdir(parents=True, exist_ok=True)
    with Image.open(hits[0]) as im:
        if im.width > MAX_WIDTH_PX:
            im = im.resize((MAX_WIDTH_PX, round(im.height * MAX_WIDTH_PX / im.width)), Image.LANCZOS)
        # a figure has few colours: a palette PNG is a third of the size, and looks the same
        im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(OUT / fig.file, optimize=True)
    return OUT / fig.file


def page_text() -> str:
    lines = ["Figure gallery", "==============", "",
             "Every kind of figure the toolkit makes, on the bundled data (``data/FOTAS``; ``data/real`` for",
             "the laboratory recording). The images and",
             "this page are regenerated together by one command::", "", "    python docs/make_gallery.py", "",
             "Every call and command named below also writes each figure as PDF.", ""]
    for sec in GALLERY.values():
        lines += [sec.title, "-" * len(sec.title), "", f"Made by {sec.made_by}.", ""]
        for f in sec.figures:
            lines += [f.title, "~" * len(f.title), "", f".. image:: gallery/{f.file}", "   :width: 100%",
                      f"   :alt: {f.title}", "", f.caption, ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", metavar="SECTION", help=f"any of {', '.join(GALLERY)} (default: all)")
    args = ap.parse_args(argv)
    unknown = [s for s in args.sections if s not in GALLERY]
    if unknown:
        ap.error(f"unknown section(s) {', '.join(unknown)}: choose from {', '.join(GALLERY)}")
    failed = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.sections or list(GALLERY):
            t0 = time.perf_counter()
            print(f"[gallery] {name} ...", file=sys.stderr, flush=True)
            folder = Path(tmp) / name
            folder.mkdir()
            try:
                MAKERS[name](folder)
                for fig in GALLERY[name].figures:
                    keep(folder, fig)
            except Exception:  # reported; the other sections still run
                failed.append(name)
                traceback.print_exc()
                continue
            print(f"[gallery] {name}: {len(GALLERY[name].figures)} figure(s) in {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)
    PAGE.write_text(page_text(), encoding="utf-8")
    print(f"wrote {PAGE} and the figures in {OUT}")
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
