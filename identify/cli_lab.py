"""The command line for friction-lab recordings: ``import`` (a lab's file into traces) and
the rate-and-state transient fit that ``fit`` runs on continuously driven runs."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from identify.jsonio import write_json

__all__ = ["add_import", "continuous_runs", "run_cycle_analysis", "run_transient_fit"]


class LabCLIError(ValueError):
    """Bad command-line input for a lab recording."""


def _range(text: str | None, flag: str) -> tuple[float, float] | None:
    if text is None:
        return None
    lo, sep, hi = text.partition(":")
    try:
        out = (float(lo), float(hi))
    except ValueError:
        out = None
    if not sep or out is None or not out[0] < out[1]:
        raise LabCLIError(f"{flag} {text!r}: expected START:END in seconds, START < END")
    return out


def _column(text: str) -> str | int:
    """A column by name, or by number counted from 1 as xlook counts."""
    return int(text) - 1 if text.strip().isdigit() else text


def add_import(sub) -> None:
    p = sub.add_parser(
        "import", help="a friction lab's recording (xlook 'look' file or text table) into traces",
        description="Read a lab recording, run its reduction recipe, keep a window, find the load point's "
        "velocity steps and write a format-v1 trace (friction as elongation through the stated stiffness). "
        "Prints every assumption made.")
    p.add_argument("source", metavar="FILE", help="binary look file, or a text table with a header line")
    p.add_argument("--format", default="auto", choices=("auto", "look", "table", "mat"),
                   help="'auto': MATLAB for .mat, a text table if the file reads as text, else a look file")
    p.add_argument("--recipe", metavar="FILE", help="the lab's xlook reduction recipe to run first")
    p.add_argument("--time", default="Time", metavar="COLUMN", help="time column, s (name or number from 1)")
    p.add_argument("--friction", default="mu", metavar="COLUMN", help="friction column (name or number from 1)")
    p.add_argument("--load-point", default=None, metavar="COLUMN",
                   help="load-point displacement column, µm (name or number from 1); without one the drive is "
                        "the one velocity --velocities gives")
    p.add_argument("--stiffness-per-um", type=float, required=True, metavar="K",
                   help="the loading system's stiffness in friction per µm of load-point displacement")
    p.add_argument("--normal-load-uN", type=float, default=None,
                   help="normal load as stated (default: 1 N; only k/Nb enters a fit)")
    p.add_argument("--window", metavar="START:END", help="the stretch to keep, s")
    p.add_argument("--velocities", metavar="V1,V2,...",
                   help="nominal load-point velocities of the stretches found, µm/s (as the lab states them), "
                        "in place of the measured ones")
    p.add_argument("--name", default=None, help="run name (default: the output's file name)")
    p.add_argument("--out", required=True, metavar="STEM", help="output trace STEM (writes STEM.csv, STEM.json)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing trace at --out")
    p.set_defaults(func=cmd_import)


def _read(path: Path, fmt: str):
    from identify.traces.look import read_look, read_mat, read_table

    if fmt == "mat" or (fmt == "auto" and path.suffix.lower() == ".mat"):
        return read_mat(path)
    if fmt == "auto":
        head = path.read_bytes()[:4096]
        fmt = "table" if b"\0" not in head else "look"
    return read_table(path) if fmt == "table" else read_look(path)


def cmd_import(args) -> int:
    from identify.traces.io import trace_paths
    from identify.traces.lab_import import import_run
    from identify.traces.look_recipe import apply_recipe

    source = Path(args.source)
    if not source.is_file():
        raise FileNotFoundError(f"{source}: no such file")
    csv_path, json_path = trace_paths(args.out)
    existing = [p for p in (csv_path, json_path) if p.exists()]
    if existing and not args.overwrite:
        raise LabCLIError(f"{existing[0]} exists: give --overwrite to replace it, or another --out")
    look = _read(source, args.format)
    if args.recipe:
        look = apply_recipe(look, Path(args.recipe))
    velocities = None
    if args.velocities:
        try:
            velocities = [float(v) for v in args.velocities.split(",")]
        except ValueError:
            raise LabCLIError(f"--velocities {args.velocities!r}: expected numbers separated by commas") from None
    imp = import_run(look, friction=_column(args.friction), time=_column(args.time),
                     load_point=_column(args.load_point) if args.load_point else None,
                     stiffness_per_um=args.stiffness_per_um,
                     normal_load_uN=args.normal_load_uN, window_s=_range(args.window, "--window"),
                     velocities_um_per_s=velocities, name=args.name or Path(args.out).name,
                     notes=f"imported from {source.name}" + (f" with the recipe {Path(args.recipe).name}"
                                                            if args.recipe else ""))
    for line in imp.assumptions:
        print(f"assumed: {line}")
    paths = imp.trace.write(args.out)
    print(f"wrote {paths[0]} and {paths[1]} ({len(imp.trace)} samples)")
    return 0


def continuous_runs(data) -> list | None:
    """The runs of ``data`` (paths) when they are continuously driven (None when they are
    the stepper's: the MEMS fit takes them); refused files are reported, mixed sets are
    an error."""
    from identify.traces.io import load_traces

    paths = [data] if isinstance(data, (str, Path)) else list(data)
    if not all(isinstance(p, (str, Path)) for p in paths):
        return None
    runs = load_traces(paths)
    driven = [t for t in runs if t.drive is not None]
    if not driven:
        return None
    if len(driven) != len(runs):
        stepper = [t.name for t in runs if t.drive is None]
        raise LabCLIError(f"runs with a stepper ({', '.join(stepper)}) and with a continuous drive in one fit: "
                          "fit them apart")
    for err in runs.errors:
        print(f"refused: {err}", file=sys.stderr)
    return driven


@dataclass
class _Request:
    law: str
    fixed: tuple
    trend: bool
    start: dict
    seed: int
    window: tuple | None
    stiffness_per_um: float | None


def _transient_request(args) -> _Request:
    """The transient fit's choices from ``fit``'s flags: --law aging|slip (default aging),
    --free among mu0, a, b, Dc, k (default the first four), --fix NAME=VALUE and --start in
    the law's lab units, --trend, --window, --stiffness-per-um."""
    from identify.fitting.transient import FIT_PARAMETERS
    from identify.model.rsf import RSF_LAWS

    law = args.law or "aging"
    if law not in RSF_LAWS:
        raise LabCLIError(f"--law {law}: continuously driven runs are fitted with the rate-and-state laws "
                          f"{' or '.join(RSF_LAWS)}")
    free = [n.strip() for n in (args.free or "mu0,a,b,Dc").split(",") if n.strip()]
    bad = [n for n in free if n not in FIT_PARAMETERS or n == "c"]
    if bad:
        raise LabCLIError(f"--free {','.join(bad)}: not among mu0, a, b, Dc, k (c comes with --trend)")
    fixed_values = _values(args.fix, "--fix")
    start = {**_values(args.start, "--start"), **fixed_values}
    fixed = tuple(n for n in FIT_PARAMETERS if n not in free and n != "c") + tuple(fixed_values)
    return _Request(law, fixed, bool(getattr(args, "trend", False)), start,
                    args.seed if args.seed is not None else 0, _range(getattr(args, "window", None), "--window"),
                    getattr(args, "stiffness_per_um", None))


def _values(items, flag: str) -> dict:
    from identify.fitting.transient import FIT_PARAMETERS

    out = {}
    for item in items or []:
        for part in item.split(","):
            name, sep, value = part.partition("=")
            try:
                out[name.strip()] = float(value)
            except ValueError:
                raise LabCLIError(f"{flag} {part!r}: expected NAME=VALUE with a number") from None
            if not sep or name.strip() not in FIT_PARAMETERS:
                raise LabCLIError(f"{flag} {part!r}: the transient fit's parameters are "
                                  f"{', '.join(FIT_PARAMETERS)} (Dc in µm, k and c per µm)")
    return out


def run_transient_fit(args, traces) -> int:
    """``fit`` on continuously driven runs: each run's rate-and-state transient fitted with
    the law ``--law`` (aging or slip), its report printed, the JSON and figures written."""
    from identify.fitting.transient import TransientRun, fit_transient

    req = _transient_request(args)
    constant = [t.name for t in traces if len(t.drive.velocities_um_per_s) == 1]
    if constant:
        raise LabCLIError(f"{', '.join(constant)}: driven at one constant velocity, no transient to fit; "
                          "'analyze' reads such a run's regime and slip cycles (fitting stick-slip under a "
                          "continuous drive is not built yet)")
    results = []
    for trace in traces:
        run = TransientRun.from_trace(trace, stiffness_per_um=req.stiffness_per_um)
        if req.window is not None:
            run = run.window(*req.window)
        res = fit_transient(run, req.law, fixed=req.fixed, trend=req.trend, start=req.start, seed=req.seed)
        results.append(res)
        print(res.report())
        if args.plots:
            from identify.plots.base import save_figure

            axes = res.plot()
            paths = save_figure(axes[0].figure, Path(args.plots) / f"transient_{trace.name}")
            print(f"wrote {', '.join(map(str, paths))}")
    if args.json:
        body = results[0].to_dict() if len(results) == 1 else {"fits": [r.to_dict() for r in results]}
        print(f"wrote {write_json(args.json, body)}", file=sys.stderr)
    bad = [r.run for r in results if not r.success]
    if bad:
        print(f"fit: not converged for {', '.join(bad)}; exit status 3", file=sys.stderr)
        return 3
    return 0


def run_cycle_analysis(args, traces) -> int:
    """``analyze`` on continuously driven runs: each run's regime (stick-slip, inertial,
    steady) and slip cycles, as the data show them."""
    from identify.traces.force_cycles import cycles_of_trace

    results = []
    for trace in traces:
        try:
            res = cycles_of_trace(trace)
        except ValueError as err:  # one run that cannot be read this way never sinks the others
            print(f"refused: {err}", file=sys.stderr)
            continue
        results.append(res)
        print(res.report())
    if args.json and results:
        print(f"wrote {write_json(args.json, {'cycles': [r.to_dict() for r in results]})}")
    return 0 if results else 2
