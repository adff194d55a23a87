"""Command line of the design package: ``python -m design <command> ...``.

A thin layer over the library: one ``_cmd_<name>(args) -> int`` per subcommand, registered
in :func:`build_parser`. Bad input (any ValueError, or an unwritable output file) prints
one line ``error: <message>`` to stderr and returns 2; no traceback.

Commands
--------
springs
    Design the fewest springs covering a normal-load range (:func:`design_spring_set`),
    print the report beside the paper's set, write JSON and optionally a Fig. 3 plot.
ranges
    Operating ranges of one spring (:func:`design.ranges.operating_ranges`): the Table I
    load range and the usable (Nb, fp) grid points from simulated runs; progress on
    stderr, report on stdout, JSON and optionally the regime-map plot.
experiment
    Optimal experiment plan (:func:`design.experiment.design_experiment`) beside the paper's
    conditions; ``--verify N`` measures both plans' spread by simulation and identification.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from identify import __version__
from identify.cli import program_name
from identify.fitting.stick_choice import STICK_SPEED_AUTO
from identify.jsonio import write_json
from identify.progress import cli_reporter

__all__ = ["main", "build_parser"]

_PLOT_SUFFIXES = (".png", ".pdf", ".svg")


class _UsageError(ValueError):
    """A command-line usage error (raised instead of argparse's exit)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, no usage dump, exit code 2 via main
        raise _UsageError(f"{self.prog}: {message}")


def _check_outputs(args: argparse.Namespace) -> None:
    """Refuse a bad --plot suffix or a missing output directory before any work."""
    if args.plot is not None and args.plot.suffix.lower() not in _PLOT_SUFFIXES:
        raise ValueError(
            f"--plot {args.plot}: the file must end in one of {', '.join(_PLOT_SUFFIXES)}"
        )
    for opt, path in (("--json", args.json), ("--plot", args.plot)):
        if path is not None and not path.parent.exists():
            raise ValueError(f"{opt} {path}: directory {path.parent} does not exist")


def _write_outputs(args: argparse.Namespace, result) -> None:
    """Write ``result.to_json()`` to --json and ``result.plot`` to --plot when given."""
    if args.json is not None:
        write_json(args.json, result.to_json())
        print(f"wrote {args.json}")
    if args.plot is not None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(6.5, 5.0), layout="constrained")
        result.plot(ax=fig.add_subplot())
        fig.savefig(args.plot, dpi=150)
        print(f"wrote {args.plot}")


# --------------------------------------------------------------------------------------
# springs
# --------------------------------------------------------------------------------------
def _add_springs(sub) -> None:
    p = sub.add_parser(
        "springs",
        help="design the fewest springs covering a normal-load range (Table I, Fig. 3)",
        description=(
            "Fewest springs covering a normal-load range for every μ in [0.1, 0.9], robust "
            "to the etch bias; the paper's four springs are reported under the same measures."
        ),
    )
    p.add_argument(
        "--load-range-uN", nargs=2, type=float, metavar=("LOW", "HIGH"), default=None,
        help="normal-load range to cover (µN); default: Table I's 0.01-452 µN with the low "
        "end raised to the lowest load reachable at this etch bias",
    )
    p.add_argument("--n-springs", type=int, default=None, metavar="N",
                   help="fix the number of springs (error if N cannot cover the range)")
    p.add_argument("--etch-bias-um", type=float, default=None, metavar="B",
                   help="etch-bias uncertainty per edge (µm); realised widths w ± 2B (default 0.1)")
    p.add_argument("--max-springs", type=int, default=None, metavar="N",
                   help="largest number of springs tried (default 8)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT",
                   help="write the result as JSON to OUT")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE",
                   help="save Fig. 3 with the set to FILE (.png, .pdf or .svg)")
    p.set_defaults(func=_cmd_springs)


def _cmd_springs(args: argparse.Namespace) -> int:
    from .spring_set import MAX_SPRINGS, design_spring_set
    from .springs import ETCH_BIAS_UM

    _check_outputs(args)
    result = design_spring_set(
        args.load_range_uN,
        n_springs=args.n_springs,
        etch_bias_um=ETCH_BIAS_UM if args.etch_bias_um is None else args.etch_bias_um,
        max_springs=MAX_SPRINGS if args.max_springs is None else args.max_springs,
    )
    print(result.report())
    _write_outputs(args, result)
    return 0


# --------------------------------------------------------------------------------------
# ranges
# --------------------------------------------------------------------------------------
def _add_ranges(sub) -> None:
    p = sub.add_parser(
        "ranges",
        help="operating ranges of one spring: usable (Nb, fp) from Table I and the simulator",
        description=(
            "Table I load range of a spring and, from simulated runs over an (Nb, fp) grid, "
            "where runs are clean stick-slip with resolvable slips (>= 90 nm), at least 20 "
            "slips in the travel and >= 2 camera frames per step (10 000 fps maximum)."
        ),
    )
    p.add_argument("--spring-constant", type=float, required=True, metavar="K",
                   help="spring constant k (N/m)")
    p.add_argument("--coating", default="FOTAS", help="Table II preset: FOTAS or OTS")
    p.add_argument("--loads-uN", type=float, nargs="+", default=None, metavar="NB",
                   help="normal loads (µN); default 6 log-spaced over the Table I range")
    p.add_argument("--fp", type=float, nargs="+", default=None, metavar="FP",
                   help="step frequencies (Hz); default 10 30 100 300 1000 3000")
    p.add_argument("--travel-um", type=float, default=100.0, metavar="T",
                   help="puller travel the 20 slips must fit in (µm, default 100)")
    p.add_argument("--stick-speed", type=float, default=STICK_SPEED_AUTO, metavar="V",
                   help="stick option v_stick (m/s; default %(default)g, as design experiment and "
                   "identify fit --stick-speed auto); 0 = the equations as written")
    p.add_argument("--json", type=Path, default=None, metavar="OUT",
                   help="write the result as JSON to OUT")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE",
                   help="save the regime map to FILE (.png, .pdf or .svg)")
    p.set_defaults(func=_cmd_ranges)


def _cmd_ranges(args: argparse.Namespace) -> int:
    from .ranges import operating_ranges

    _check_outputs(args)

    result = operating_ranges(
        args.spring_constant, args.coating, loads_uN=args.loads_uN, fps_Hz=args.fp,
        travel_um=args.travel_um, stick_speed_m_per_s=args.stick_speed, progress=cli_reporter("[ranges] "),
    )
    print(result.report())
    _write_outputs(args, result)
    return 0


# --------------------------------------------------------------------------------------
# experiment
# --------------------------------------------------------------------------------------
def _add_experiment(sub) -> None:
    p = sub.add_parser(
        "experiment",
        help="optimal experiment plan: which (k, Nb, fp) runs determine the friction parameters",
        description=(
            "Fisher information of each candidate run from the identification NLP (90 nm noise), "
            "a D/A/E-optimal plan of N runs, and the paper's conditions with the same run count "
            "beside it; --verify simulates and identifies both plans N times."
        ),
    )
    p.add_argument("--coating", default="FOTAS", help="Table II preset: FOTAS or OTS")
    p.add_argument("--runs", type=int, required=True, help="number of runs in the plan")
    p.add_argument("--springs", default="2.13,20.3", help="comma-separated spring constants (N/m)")
    p.add_argument("--criterion", default="D", help="D (default), A or E")
    p.add_argument("--prior", type=Path, default=None, metavar="FIT.json",
                   help="a fit's JSON (python -m identify fit --json): design what to run next")
    p.add_argument("--travel-um", type=float, default=30.0, help="travel of every run (µm, default 30)")
    p.add_argument("--stick-speed", type=float, default=STICK_SPEED_AUTO, metavar="V",
                   help="stick option v_stick the runs are planned and verified with (m/s; default %(default)g, "
                   "as design ranges); 0 = the equations as written")
    p.add_argument("--loads-uN", type=float, nargs="+", default=None, metavar="NB",
                   help="candidate loads (µN; default 4 log-spaced in each spring's Table I range, <= 60)")
    p.add_argument("--fp", type=float, nargs="+", default=None, metavar="FP",
                   help="candidate step frequencies (Hz; default 10 30 100 300 1000)")
    p.add_argument("--verify", type=int, default=0, metavar="N",
                   help="simulate + identify the plan and the reference N times each (slow)")
    p.add_argument("--seed", type=int, default=0, help="seed of the verification noise")
    p.add_argument("--workers", type=int, default=1, help="processes for the verification fits")
    p.add_argument("--verify-jitter", type=float, default=None, metavar="J",
                   help="verification: draw each run's load within ±J of nominal per repeat, as real "
                        "replicates differ (redraws the step phases slips lock to; default 0.05, 0: none)")
    p.add_argument("--verify-record", type=Path, default=None, metavar="FILE",
                   help="JSON lines, one per finished verification fit; a rerun resumes from it "
                        "(default: OUT.verify.jsonl beside --json OUT)")
    p.add_argument("--json", type=Path, default=None, metavar="OUT")
    p.add_argument("--plot", type=Path, default=None, metavar="FILE")
    p.set_defaults(func=_cmd_experiment)


def _cmd_experiment(args: argparse.Namespace) -> int:
    from .experiment import CRITERIA, default_candidates, design_experiment, prior_from_fit, verify_plans

    _check_outputs(args)
    if args.criterion not in CRITERIA:
        raise ValueError(f"--criterion {args.criterion!r}: no such criterion; choose one of {', '.join(CRITERIA)}")
    if args.runs < 1:
        raise ValueError(f"--runs {args.runs}: must be at least 1")
    if args.verify_jitter is not None and not (0 <= args.verify_jitter < 1):
        raise ValueError(f"--verify-jitter {args.verify_jitter}: a fraction of the load, 0 <= J < 1")
    try:
        springs = [float(x) for x in args.springs.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--springs {args.springs!r}: expected comma-separated numbers") from None
    if not springs or any(not (k > 0) for k in springs):
        raise ValueError(f"--springs {args.springs!r}: spring constants must be > 0")
    prior = prior_from_fit(args.prior, args.coating) if args.prior is not None else None
    say = cli_reporter("[experiment] ")
    if args.fp is not None and any(not (f > 0) for f in args.fp):
        raise ValueError(f"--fp {args.fp}: step frequencies must be > 0")
    cands = default_candidates(springs, args.travel_um, loads_uN=args.loads_uN,
                               **({"fps_Hz": args.fp} if args.fp else {}))
    if not cands:
        raise ValueError("no candidate run: every --loads-uN value lies outside the springs' Table I ranges")
    plan = design_experiment(args.runs, args.coating, candidates=cands, criterion=args.criterion,
                             prior_information=prior, travel_um=args.travel_um, progress=say,
                             stick_speed_m_per_s=args.stick_speed)
    if args.verify:
        if args.json is not None:  # the design is saved before the long verification
            write_json(args.json, plan.to_json())
        record = args.verify_record
        if record is None and args.json is not None:
            record = args.json.with_suffix(".verify.jsonl")
        jitter = {} if args.verify_jitter is None else {"jitter_load": args.verify_jitter}
        verify_plans(plan, args.verify, seed=args.seed, workers=args.workers, progress=say, record=record,
                     stick_speed_m_per_s=args.stick_speed, **jitter)
    print(plan.report())
    _write_outputs(args, plan)
    return 0


_SUBCOMMANDS: tuple[Callable, ...] = (_add_springs, _add_ranges, _add_experiment)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser: one subparser per entry of ``_SUBCOMMANDS``."""
    parser = _Parser(
        prog=program_name("design"),
        description="nanofrictor design: springs, operating ranges and experiments.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log solver progress")
    parser.add_argument("--version", action="version", version=f"%(prog)s (nanofrictor) {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for add in _SUBCOMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit code (0 ok, 2 bad input)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command is None:
            raise _UsageError(
                f"{parser.prog}: choose a command: "
                + ", ".join(a.__name__[len("_add_"):] for a in _SUBCOMMANDS)
            )
        if args.verbose:
            logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
        return int(args.func(args))
    except SystemExit as exc:  # --help
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    except (ValueError, OSError) as exc:
        msg = " ".join(str(exc).split())
        print(f"error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # (128 + SIGINT, the shell's convention)
        what = getattr(exc, "what", "") or "nothing saved"
        print(f"interrupted: {what}", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
