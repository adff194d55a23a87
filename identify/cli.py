"""Command line: ``python -m identify <command> ...``, a thin layer over the library.

Every command is a function ``_cmd_<name>(args) -> int``. Exit status:

* 0: done;
* 1: done in part (a command that says which part);
* 2: bad input: one ``error:`` line on stderr naming the file, line or parameter and the
  rule it broke (an error the toolkit raised on purpose: ``ValueError`` and its
  subclasses raised by a ``raise`` of ours, missing or unreadable files);
* 3: ``fit`` finished, but its result is not one to use as it stands (not converged,
  reduced χ² above 2, a parameter at a bound, μmin ≥ μmax): the report's first line
  says why; the report and the JSON are written all the same;
* 4: an internal error, a fault of the toolkit rather than of the input: one line says
  so, names the exception, and where its traceback was written; files already written
  are kept;
* 130: interrupted.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from identify import interrupts
from identify.cli_lab import add_import
from identify.jsonio import write_json
from identify.progress import cli_reporter

from . import __version__

__all__ = ["main", "build_parser", "program_name"]

log = logging.getLogger("identify")


def program_name(package: str) -> str:
    """The command as the user typed it, for usage lines: the installed script's name
    (``nanofrictor-identify``) when run through it, else ``python -m <package>``."""
    base = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    if base.startswith("nanofrictor-"):
        return base
    return f"python -m {package}"


class CLIError(ValueError):
    """Bad command-line input."""


def _parse_params(items: Sequence[str] | None, flag: str = "--param") -> dict[str, float]:
    """``["tau=0.05", "A=0"]`` -> {"tau": 0.05, "A": 0.0}; ``exposure_align`` also takes
    start, centre or end."""
    from identify.model.params import ParameterError, exposure_align

    out: dict[str, float] = {}
    for item in items or []:
        for part in item.split(","):
            if not part.strip():
                continue
            if "=" not in part:
                raise CLIError(f"{flag} {part!r}: expected NAME=VALUE")
            name, value = part.split("=", 1)
            try:
                out[name.strip()] = float(value)
            except ValueError:
                if name.strip() != "exposure_align":
                    raise CLIError(f"{flag} {part!r}: {value!r} is not a number") from None
                try:
                    out[name.strip()] = exposure_align(value)
                except ParameterError as err:
                    raise CLIError(f"{flag} {part!r}: {err}") from None
    return out


# ----------------------------------------------------------------------------- simulate
def _add_simulate(sub):
    p = sub.add_parser(
        "simulate", help="simulate one run and write its camera trace",
        description="Simulate one run of the platform (hybrid stick/slip model) and write the "
        "camera trace as DIR/NAME.csv + DIR/NAME.json (shared trace format v1).",
    )
    p.add_argument("--coating", default="FOTAS", help="parameter preset (Table II): FOTAS or OTS")
    p.add_argument("--spring-constant", type=float, required=True, metavar="K",
                   help="spring constant k in N/m (= µN/µm)")
    load = p.add_mutually_exclusive_group(required=True)
    load.add_argument("--normal-load-uN", type=float, help="normal load Nb in µN")
    load.add_argument("--block-voltage-V", type=float, help="block voltage Vb in V (Eqs. 5-6)")
    p.add_argument("--fp", type=float, required=True, help="puller step frequency in Hz")
    p.add_argument("--travel-um", type=float, required=True, help="puller travel in µm")
    p.add_argument("--law", default="exponential", help="aging law: exponential, logarithmic, logistic")
    p.add_argument("--param", action="append", metavar="NAME=VALUE",
                   help="override a model parameter, SI (repeatable, e.g. --param tau=0.05)")
    p.add_argument("--stick-speed", type=float, default=None, metavar="M_PER_S",
                   help="stick-threshold option v_stick in m/s (default 0: equations as written)")
    p.add_argument("--noise-nm", type=float, default=0.0, help="camera noise, standard deviation in nm")
    p.add_argument("--seed", type=int, default=None, help="seed of the noise")
    p.add_argument("--frame-rate", type=float, default=None, help="frames per second (default 2 per step)")
    p.add_argument("--frame-phase", type=float, default=0.5,
                   help="frame times (j + phase)/frame_rate; 0.5 = middle of each sub-interval")
    p.add_argument("--integrator", default="rosenbrock", choices=("rosenbrock", "idas"),
                   help="engine for moving phases (see README)")
    p.add_argument("--outside-platform-ranges", action="store_true",
                   help="simulate conditions outside what the platform can do (refused otherwise, as a likely "
                   "unit slip); the trace says so in its metadata")
    p.add_argument("--out", required=True, metavar="DIR/NAME", help="output stem of the trace files")
    p.add_argument("--plot", action="store_true", help="also write DIR/NAME_fig13.png/.pdf (paper's Fig. 13)")
    p.add_argument("--json", metavar="SUMMARY.json", help="write a JSON summary of the run")
    p.add_argument("--overwrite", action="store_true",
                   help="replace trace, summary and figure files that already exist (refused otherwise)")
    p.set_defaults(func=_cmd_simulate)


def _cmd_simulate(args) -> int:
    from identify.simulation.hybrid import SimulationOptions, simulate

    params = _parse_params(args.param)
    stem = Path(args.out)
    if args.json and Path(args.json).resolve() == stem.with_suffix(".json").resolve():
        raise CLIError(f"--json {args.json}: that is the trace's own metadata file; choose another name")
    if not args.overwrite:  # (before simulating: a recorded or earlier trace is never replaced unasked)
        from identify.traces.io import trace_paths

        outputs = [*trace_paths(stem)]
        outputs += [Path(args.json)] if args.json else []
        outputs += [stem.parent / f"{stem.name}_fig13{x}" for x in (".png", ".pdf")] if args.plot else []
        there = [str(p) for p in outputs if p.exists()]
        if there:
            raise CLIError(f"--out {args.out}: {', '.join(there)} already exist(s); choose another --out or give "
                           "--overwrite to replace them")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        res = simulate(
            args.coating, spring_constant_N_per_m=args.spring_constant,
            normal_load_uN=args.normal_load_uN, block_voltage_V=args.block_voltage_V,
            step_frequency_Hz=args.fp, travel_um=args.travel_um, law=args.law, params=params,
            stick_speed_m_per_s=args.stick_speed, options=SimulationOptions(integrator=args.integrator),
            check_platform=not args.outside_platform_ranges,
        )
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    trace = res.sample(frame_rate_Hz=args.frame_rate, frame_phase=args.frame_phase,
                       noise_nm=args.noise_nm, seed=args.seed, name=stem.name,
                       metadata=({"block_voltage_V": args.block_voltage_V} if args.block_voltage_V else None))
    if args.block_voltage_V is not None:
        trace.metadata.pop("normal_load_uN", None)
    csv_path, json_path = trace.write(stem)
    print(res.report())
    print(f"wrote {csv_path} and {json_path} ({len(trace.time_s)} frames)")
    if args.plot:
        from identify.plots.base import plot_simulation, save_figure

        axes = plot_simulation(res)
        paths = save_figure(axes[0].figure, stem.parent / f"{stem.name}_fig13")
        print("wrote " + ", ".join(map(str, paths)))
    if args.json:
        summary = res.summary()
        summary["trace"] = {"csv": str(csv_path), "json": str(json_path), "frames": len(trace.time_s),
                            "noise_nm": args.noise_nm, "seed": args.seed}
        print(f"wrote {write_json(args.json, summary)}")
    return 0 if res.completed else 1


# ----------------------------------------------------------------------------- regimes
def _add_regimes(sub):
    p = sub.add_parser("regimes", help="regime map (stick-slip/stepping/creep) over Nb and fp",
                       description="Simulate a grid of (Nb, fp) runs for one spring and classify each.")
    p.add_argument("--coating", default="FOTAS")
    p.add_argument("--spring-constant", type=float, default=2.13)
    p.add_argument("--loads-uN", type=float, nargs="+", default=[1, 2, 5, 10, 20, 30, 60])
    p.add_argument("--fp", type=float, nargs="+", default=[10, 30, 100, 300, 1000, 3000, 10000])
    p.add_argument("--travel-um", type=float, default=None,
                   help="travel per run (default: enough for the first loading and a few slips)")
    p.add_argument("--stick-speed", type=float, default=0.0)
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--plot", metavar="FILE")
    p.set_defaults(func=_cmd_regimes)


def _cmd_regimes(args) -> int:
    from identify.simulation.regimes import regime_map

    m = regime_map(args.coating, args.spring_constant, args.loads_uN, args.fp, args.travel_um,
                   args.stick_speed, progress=cli_reporter("[regimes] "))
    print(m.table())
    if args.json:
        print(f"wrote {write_json(args.json, m.to_json())}")
    if args.plot:
        from identify.plots.base import save_figure

        ax = m.plot()
        print("wrote " + ", ".join(map(str, save_figure(ax.figure, args.plot))))
    return 0


# ----------------------------------------------------------------------------- analyze
def _add_analyze(sub):
    p = sub.add_parser("analyze", help="events and the paper's reduced analysis of recorded runs",
                       description="Extract slip events and stick staircases from each run, the "
                       "paper's reduced analysis (Eq. 8) per run, and the Eq. 9 law fit across "
                       "runs with the logarithmic and logistic laws compared by AIC.")
    p.add_argument("data", nargs="+", metavar="DATA", help="trace files (.csv) or folders of runs")
    p.add_argument("--recursive", action="store_true", help="also look in sub-folders")
    p.add_argument("--source", default="events",
                   help="(t_rest, μs) points: events (per-slip triggers) or sqrt12 (the paper's σ√12)")
    p.add_argument("--json", metavar="OUT.json")
    p.add_argument("--plots", metavar="DIR", help="write per-run event plots and Figs. 10-11")
    p.set_defaults(func=_cmd_analyze)


def _cmd_analyze(args) -> int:
    from identify.cli_lab import continuous_runs, run_cycle_analysis
    from identify.traces.analyze import analyze

    lab = continuous_runs(args.data)
    if lab is not None:
        return run_cycle_analysis(args, lab)

    res = analyze(args.data, source=args.source, recursive=args.recursive)
    print(res.report())
    if args.json:
        print(f"wrote {write_json(args.json, res.to_json())}")
    if args.plots:
        paths = res.save_plots(args.plots)
        print(f"wrote {len(paths)} figure(s) to {args.plots}")
    if not any(ra.events is not None for ra in res.runs):
        # (the report above says why each run was refused; nothing else is wrong)
        print("error: no run could be analysed (each run's reason is listed above)", file=sys.stderr)
        return 2
    return 0


# ----------------------------------------------------------------------------- fit
def _add_fit_arguments(p, json_required: bool):
    p.add_argument("--coating", default=None, help="FOTAS or OTS (default: the runs' majority)")
    p.add_argument("--law", default=None,
                   help="aging law: exponential (default), logarithmic, logistic; for continuously driven "
                        "runs (imported lab data) the rate-and-state law: aging (default) or slip")
    p.add_argument("--free", default=None, metavar="NAMES",
                   help="comma-separated free parameters (default mu_max,mu_min,tau,A); drift_rate, k_scale, "
                   "load_offset, load_scale and clock_shift may take one value per run or device: drift_rate@run "
                   "(every run), drift_rate@run:NAME (one run), k_scale@device:LABEL (a trace's device, else "
                   "k<spring constant>)")
    p.add_argument("--fix", action="append", metavar="NAME=VALUE",
                   help="fix a parameter at a value, SI (repeatable; e.g. --fix v_stick=1e-5)")
    p.add_argument("--bound", action="append", metavar="NAME=LO:HI", help="bounds of a free parameter")
    p.add_argument("--start", action="append", metavar="NAME=VALUE", help="start value of a free parameter")
    p.add_argument("--prior", action="append", metavar="NAME=SD",
                   help="a zero-mean Gaussian prior of standard deviation SD (SI) on a free parameter, whose size "
                   "the data must then argue for (repeatable; NAME@run: every run's); the chi-square reported "
                   "is the data's, the penalty apart")
    p.add_argument("--walk-nm-per-sqrt-s", type=float, default=None, metavar="SIGMA",
                   help="model a random walk of the camera's zero in each run, of intensity SIGMA nm/√s: frees "
                   "its six modes per run (walk_1@run ... walk_6@run, unless some are named in --free) with "
                   "the Wiener process's priors; pair it with drift_rate@run for each run's own drift")
    p.add_argument("--free-offset", action="store_true", help="estimate a per-run elongation zero offset")
    p.add_argument("--drop-frames", action="store_true",
                   help="observe the frames around each slip one by one: an exposure straddling a slip shows there "
                   "(free exposure, with --fix exposure_align=start|centre|end or a clock_shift@run free)")
    p.add_argument("--outside-platform-ranges", action="store_true",
                   help="take --fix and --start values outside what a contact on the platform can plausibly have "
                   "(refused otherwise, as a likely unit slip: tau=67.4 is ms typed for s)")
    p.add_argument("--stick-speed", default="check", metavar="check|auto|off|M_PER_S",
                   help="the stick option: a speed in m/s fixes v_stick (as --fix v_stick=...); otherwise "
                        "'check' (default) stops at once where the equations as written creep but the data "
                        "stick-slip, saying what to do; 'auto' then takes v_stick = 1e-5 m/s and names it in the "
                        "report; 'off' fits as written regardless")
    p.add_argument("--multistart", type=int, default=0, help="extra random starts (pyPESTO-style summary)")
    p.add_argument("--seed", type=int, default=None, help="seed of the multistart")
    p.add_argument("--sequence-trials", type=int, default=None, metavar="N",
                   help="trials of the last mode-sequence repair, where the model's slip triggers "
                        "misfit (default: FitOptions.sequence_trials, 64; 0 turns it off)")
    p.add_argument("--sequence-passes", default=None, metavar="P1,P2",
                   help="the mode-sequence repairs to make, of triggers, missed, batch, ambiguous, misfit "
                        "(default: all; 'none' fits the sequence as detected)")
    p.add_argument("--solver", default="ipopt", choices=("ipopt", "gauss-newton"),
                   help="Ipopt (default) or the toolkit's own Gauss-Newton SQP: slower, and on some hard "
                        "data sets it ends in a better basin (README, Known limits)")
    p.add_argument("--trigger", default="uniform", choices=("uniform", "interval"),
                   help="trigger encoding: uniform residuals (default), or intervals solved last "
                        "(for noiseless data, where the uniform's pull biases by ~2e-3; not for diagnose)")
    p.add_argument("--profile", default=None, metavar="NAMES",
                   help="comma-separated free parameters to profile (likelihood profiles)")
    p.add_argument("--json", required=json_required, metavar="OUT.json")
    p.add_argument("--plots", metavar="DIR", help="write data-vs-model figures (PNG + PDF)")


def _add_fit(sub):
    p = sub.add_parser("fit", help="identify friction parameters from recorded runs (full model)",
                       description="Joint multiple-shooting fit of the hybrid model over all runs.")
    p.add_argument("data", nargs="+", metavar="DATA", help="trace files (.csv) or folders of runs")
    _add_fit_arguments(p, json_required=True)
    g = p.add_argument_group("continuously driven runs (imported lab data: a rate-and-state transient fit)")
    g.add_argument("--window", metavar="START:END", help="fit only the samples in this time window, s")
    g.add_argument("--trend", action="store_true",
                   help="also fit c, a linear trend of friction with load-point displacement")
    g.add_argument("--stiffness-per-um", type=float, default=None, metavar="K",
                   help="the loading stiffness in friction per µm, in place of the run's k/Nb")
    p.set_defaults(func=_cmd_fit)


def _parse_bounds(items) -> dict:
    out = {}
    for item in items or []:
        name, _, rng = item.partition("=")
        lo, _, hi = rng.partition(":")
        try:
            out[name.strip()] = (float(lo), float(hi))
        except ValueError:
            raise CLIError(f"--bound {item!r}: expected NAME=LO:HI with numbers") from None
    return out


def _fit_options(args):
    from identify.fitting.options import DEFAULT_FREE, FitOptions
    from identify.model.params import walk_mode, walk_names

    free = tuple(n.strip() for n in args.free.split(",") if n.strip()) if args.free else DEFAULT_FREE
    stick = _stick_mode(args)  # (first: a speed given there joins --fix)
    walk = getattr(args, "walk_nm_per_sqrt_s", None)
    if walk is not None and not (math.isfinite(walk) and walk > 0):
        raise CLIError(f"--walk-nm-per-sqrt-s {walk:g}: a random walk's intensity must be > 0 nm/√s")
    if walk is not None and not any(walk_mode(n) for n in free):
        free += tuple(f"{n}@run" for n in walk_names())
    return FitOptions(law=args.law or "exponential", free=free, fixed=_parse_params(args.fix, "--fix"),
                      bounds=_parse_bounds(args.bound), start=_parse_params(args.start, "--start"),
                      priors=_parse_params(getattr(args, "prior", None), "--prior"),
                      walk_intensity=None if walk is None else walk * 1e-9,
                      free_offset=args.free_offset, drop_frames=getattr(args, "drop_frames", False),
                      multistart=args.multistart, seed=args.seed,
                      solver=args.solver, trigger=args.trigger, stick_speed=stick,
                      check_platform=not getattr(args, "outside_platform_ranges", False),
                      **({} if args.sequence_trials is None else {"sequence_trials": args.sequence_trials}),
                      **_sequence_passes(getattr(args, "sequence_passes", None)))


def _sequence_passes(text: str | None) -> dict:
    """``--sequence-passes`` as the option (none given: the options' default)."""
    if text is None:
        return {}
    if text.strip().lower() == "none":
        return {"sequence_passes": ()}
    return {"sequence_passes": tuple(p.strip() for p in text.split(",") if p.strip())}


def _stick_mode(args) -> str:
    """``--stick-speed``: a mode, or a speed that fixes v_stick (added to ``args.fix``)."""
    value = str(getattr(args, "stick_speed", "check"))
    if value in ("check", "auto", "off"):
        return value
    try:
        speed = float(value)
    except ValueError:
        raise CLIError(f"--stick-speed {value}: expected check, auto, off or a speed in m/s") from None
    if any(item.split("=")[0].strip() == "v_stick" for item in (args.fix or [])):
        raise CLIError("--stick-speed and --fix v_stick both given: give one")
    args.fix = [*(args.fix or []), f"v_stick={speed!r}"]
    return "check"


def _run_fit(args, data, true_values=None) -> int:
    from identify.cli_lab import continuous_runs, run_transient_fit
    from identify.fitting.driver import fit

    lab = continuous_runs(data)
    if lab is not None:
        return run_transient_fit(args, lab)

    opts = _fit_options(args)
    profiles = [n.strip() for n in (args.profile or "").split(",") if n.strip()]
    for name in profiles:  # (before the fit, not after it)
        if name not in opts.free:
            raise CLIError(f"--profile {name}: not a free parameter ({', '.join(opts.free)})")
    say = cli_reporter("[fit] ")
    try:
        res = fit(data, coating=args.coating, options=opts, true_values=true_values, progress=say)
    except interrupts.Interrupted as err:
        return _save_interrupted(err, Path(args.json).with_suffix(".interrupted.json"))
    # the fit is saved before any optional extra work, so nothing computed is lost
    if args.json:
        print(f"wrote {write_json(args.json, res.to_json())}", file=sys.stderr)
    for name in profiles:
        try:
            with interrupts.honoured():
                res = res.with_profiles(res.profile(name, progress=say))
        except KeyboardInterrupt:
            before = " and the profiles before it" if name != profiles[0] else ""
            print(f"interrupted during the profile of {name}: saved the fit{before} in {args.json}", file=sys.stderr)
            return 130
        if args.json:
            write_json(args.json, res.to_json())
    print(res.report())
    if args.plots:
        paths = res.save_plots(args.plots)
        print(f"wrote {len(paths)} figure file(s) to {args.plots}")
    if res.concerns:
        print(f"fit: not a result to use as it stands ({'; '.join(res.concerns)}); exit status 3",
              file=sys.stderr)
        return 3
    return 0


def _save_interrupted(err, path: Path) -> int:
    """Write what an interrupted fit reached (``err.saved``) to ``path``; one line says
    what was saved; exit status 130 (128 + SIGINT, the shell's convention)."""
    if not err.saved:
        print(f"interrupted: nothing saved ({err.what})", file=sys.stderr)
        return 130
    write_json(path, {"interrupted": True, **err.saved})
    print(f"interrupted: saved {err.what} to {path}", file=sys.stderr)
    return 130


def _cmd_fit(args) -> int:
    return _run_fit(args, args.data)


# ----------------------------------------------------------------------------- demo
def _default_data(coating: str) -> Path:
    here = Path(__file__).resolve().parent.parent / "data" / coating
    return here


def _add_demo(sub):
    p = sub.add_parser("demo", help="fit the bundled synthetic FOTAS data set (the main job)",
                       description="Fit the bundled synthetic data set (data/FOTAS, made with the "
                       "simulator's stick option v_stick = 1e-5 m/s, see data/README.md), print "
                       "the report and write the figures and the JSON to --out.")
    p.add_argument("--coating", default="FOTAS", choices=("FOTAS", "OTS"))
    p.add_argument("--data", default=None, metavar="DIR", help="data folder (default: the bundled set)")
    p.add_argument("--out", default="nanofrictor-demo", metavar="DIR",
                   help="folder for fit.json and the figures (default ./nanofrictor-demo)")
    p.set_defaults(func=_cmd_demo)


def _cmd_demo(args) -> int:
    from identify.model.params import parameter_set

    data = Path(args.data) if args.data else _default_data(args.coating)
    if not data.is_dir():
        raise CLIError(f"{data}: bundled data not found (installed without the repository?); "
                       "pass --data DIR")
    out = Path(args.out)
    # the fit command's own defaults (a hand-kept copy of them drifted: it kept the old solver)
    fit_parser = argparse.ArgumentParser(add_help=False)
    _add_fit_arguments(fit_parser, json_required=True)
    fit_args = fit_parser.parse_args(["--coating", args.coating, "--law", "exponential", "--fix", "v_stick=1e-5",
                                      "--json", str(out / "fit.json"), "--plots", str(out / "figures")])
    print(f"demo: fitting {data} (synthetic, made with v_stick = 1e-5 m/s; true values from the "
          f"{args.coating} preset shown beside the estimates)", file=sys.stderr)
    truth = parameter_set(args.coating)
    code = _run_fit(fit_args, [str(data)], true_values=truth)
    print(f"demo: results in {out}/ (fit.json, figures/)")
    return code


# ----------------------------------------------------------------------------- diagnose
def _add_diagnose(sub):
    p = sub.add_parser("diagnose", help="where model and data part, which unmodelled effect, how far it closes",
                       description="Fit the baseline, locate its misfit feature by feature, refit every "
                       "candidate effect (parallel), score it (LR, AIC, BIC, held-out gap) and give a verdict.")
    p.add_argument("data", nargs="+", metavar="DATA", help="trace files (.csv) or folders of runs")
    _add_fit_arguments(p, json_required=True)
    p.add_argument("--effects", default="all", metavar="all|ID,ID",
                   help="candidate effects, default all: " + ", ".join(_effect_ids()))
    p.add_argument("--folds", default="loo", metavar="loo|K", help="held-out runs: leave-one-run-out or K folds")
    p.add_argument("--alpha", type=float, default=0.01, help="family-wise level of the tests (default 0.01)")
    p.add_argument("--max-effects", type=int, default=3, help="forward selection stops after this many")
    p.add_argument("--resequence", choices=("auto", "always", "never"), default="auto",
                   help="decide the mode sequence again once an effect is named: while the named model's "
                   "held-out gap is above the tolerance (auto, default), always, or never")
    p.add_argument("--workers", type=int, default=2, help="local worker processes for the refits (default 2)")
    p.add_argument("--dask", default=None, metavar="ADDRESS", help="run the refits on a dask.distributed cluster")
    p.add_argument("--record", default=None, metavar="FILE",
                   help="keep the baseline fit and every finished refit here as they finish (default: the "
                   "--json path with the suffix .record)")
    p.add_argument("--resume", action="store_true",
                   help="go on from the record of an interrupted diagnosis of the same data and options")
    p.set_defaults(func=_cmd_diagnose)


def _effect_ids():
    from identify.model.effects import EFFECTS

    return list(EFFECTS)


def _cmd_diagnose(args) -> int:
    from identify.diagnosis.rounds import DiagnosisOptions, diagnose
    from identify.model.effects import EFFECTS

    effects = "all" if args.effects.strip() == "all" else [e.strip() for e in args.effects.split(",") if e.strip()]
    for e in (effects if effects != "all" else []):
        if e not in EFFECTS:
            raise CLIError(f"--effects {e!r}: unknown effect; choose from {', '.join(EFFECTS)}")
    folds = args.folds if args.folds == "loo" else _int_arg(args.folds, "--folds")
    dopts = DiagnosisOptions(effects=effects, folds=folds, alpha=args.alpha, max_effects=args.max_effects,
                             workers=args.workers, dask=args.dask, seed=args.seed or 0,
                             resequence={"auto": "auto", "always": True, "never": False}[args.resequence],
                             record=args.record or str(Path(args.json).with_suffix(".record")), resume=args.resume)
    say = cli_reporter("[diagnose] ")
    try:
        res = diagnose(args.data, coating=args.coating, fit_options=_fit_options(args), options=dopts, progress=say)
    except interrupts.Interrupted as err:
        if err.saved and "record" in err.saved:
            print(f"interrupted: saved {err.what}; run the same command with --resume to go on", file=sys.stderr)
            return 130
        return _save_interrupted(err, Path(args.json).with_suffix(".baseline.interrupted.json"))
    print(f"wrote {res.save_json(args.json)}", file=sys.stderr)
    print(res.report())
    if args.plots:
        paths = res.save_plots(args.plots)
        print(f"wrote {len(paths)} figure file(s) to {args.plots}")
    return 0


def _int_arg(text: str, flag: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise CLIError(f"{flag} {text!r}: expected 'loo' or an integer") from None


# ----------------------------------------------------------------------------- bench
def _add_bench(sub):
    p = sub.add_parser("bench", help="'bench derivatives': the arcs' Jacobians against tight differences "
                       "(the speed benchmarks are scripts in the repository's tests/bench)",
                       add_help=False, prefix_chars="\0")
    p.add_argument("rest", nargs=argparse.REMAINDER)
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(args) -> int:
    if args.rest and args.rest[0] == "derivatives":
        from identify.fitting.derivative_check import main as derivatives_main

        return int(derivatives_main(args.rest[1:]) or 0)
    raise CLIError("bench: the installed command has one check, 'bench derivatives'; the speed benchmarks "
                   "(simulator, fit, diagnosis) are scripts in the repository: tests/bench/bench_simulator.py, "
                   "tests/bench/bench_fit.py, tests/bench/bench_diagnosis.py")


# ----------------------------------------------------------------------------- main
_COMMANDS = [_add_demo, _add_simulate, _add_regimes, _add_analyze, _add_fit, _add_diagnose, _add_bench, add_import]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=program_name("identify"),
        description="nanofrictor: simulate, analyse and identify MEMS stick-slip friction runs.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("--version", action="version", version=f"%(prog)s (nanofrictor) {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (FileNotFoundError, IsADirectoryError, PermissionError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:
        # FitError, ParameterError and TraceFormatError are ValueErrors; so is what a
        # builtin or a library raises on a bug of ours (``min()`` of an empty sequence):
        # only an error some ``raise`` of ours made on purpose blames the input
        if not _raised_on_purpose(err):
            return _internal_error(err)
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: nothing saved", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # the reader of our output went away (``| head``): not a fault, nothing to say
        # to it; stdout is pointed at devnull so the interpreter's final flush is quiet
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Exception as err:  # noqa: BLE001 - the last line of defence: no traceback on the terminal
        return _internal_error(err)


def _raised_on_purpose(err: BaseException) -> bool:
    """Whether ``err`` comes from a ``raise`` statement in the toolkit's own code (the
    innermost frame of its traceback is ours and its line raises): a message written for
    the user, as opposed to an exception out of a builtin or a library."""
    import linecache
    import traceback

    if type(err).__module__.split(".")[0] in ("identify", "design"):
        return True  # (our own error classes: FitError, CLIError, TraceFormatError, ...)
    frames = traceback.extract_tb(err.__traceback__)
    if not frames:
        return True
    last = frames[-1]
    ours = any(f"{sep}{pkg}{sep}" in last.filename for pkg in ("identify", "design") for sep in ("/", "\\"))
    # (a raise statement spread over lines reports one of them: look a few lines up)
    lines = [linecache.getline(last.filename, n).lstrip() for n in range(max(last.lineno - 4, 1), last.lineno + 1)]
    return ours and any(line.startswith("raise") for line in lines)


def _internal_error(err: BaseException) -> int:
    import tempfile
    import time
    import traceback

    path = None
    try:
        fd, path = tempfile.mkstemp(prefix=f"nanofrictor-error-{time.strftime('%Y%m%d-%H%M%S')}-", suffix=".txt")
        with open(fd, "w") as fh:
            fh.write(f"nanofrictor {_version()}: {' '.join(sys.argv)}\n\n")
            traceback.print_exception(type(err), err, err.__traceback__, file=fh)
    except OSError:
        path = None
    print(f"internal error (a fault of nanofrictor, not of your input): {type(err).__name__}: {err}"
          + (f"; traceback in {path}" if path else "") + "; files already written are kept", file=sys.stderr)
    return 4


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("nanofrictor")
    except Exception:  # noqa: BLE001
        return "(version unknown)"
