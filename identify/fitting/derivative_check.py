"""How exact are the arcs' derivatives? ``python -m identify bench derivatives``.

For a set of slip arcs (the arcs of a data set's detected slips, with the problem's
arc starts at given friction values), compares three Jacobians of the slip length and
the contact state at the horizon with respect to the inputs a fit varies:

* ``exact``: IDAS with forward sensitivities, the stop time through a rootfinder
  (:mod:`identify.fitting.exact_arcs`), at the tolerance asked for;
* ``forward`` and ``central``: finite differences of the event-located arcs as the
  solver and the covariance take them (:mod:`identify.fitting.arcs`);
* the reference: central differences of the event-located arcs at tolerance 1e-10.

It also checks the exact Jacobian against central differences of the IDAS arc itself
(each perturbed arc seeded by its own event-located stop): that is the test of the
differentiation through the stop time, free of the difference between two integrators.
Grazing arcs (:func:`identify.fitting.exact_arcs.grazing_flags`) are counted apart.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from identify import interrupts
from identify.fitting.arcs import arc_functions
from identify.fitting.exact_arcs import EXACT_RELTOL, GRAZING_REASONS, ExactArcs, grazing_flags
from identify.jsonio import dumps
from identify.model.laws import get_law
from identify.model.params import parameter_set
from identify.model.symbolic import Model

__all__ = ["DEFAULT_ROWS", "ArcCase", "arc_case", "compare", "format_result", "grazing_list", "main"]

DEFAULT_ROWS = ("e0_um", "state0", "mu_max", "mu_min", "tau", "A")
REFERENCE_TOL = 1e-10  # tolerance of the reference integrations
REFERENCE_STEP = 1e-5  # relative step of the reference's central differences
# an entry agrees when it is within this relative error of the reference, or this
# absolute error in scaled units (per unit of the input's typical size)
AGREE_REL, AGREE_ABS = 1e-5, 1e-9
# arcs per CasADi call: a Ctrl-C is only seen between calls, and the reference's
# differences over a data set's ~25 arcs at once took 5.5 s (measured)
ARCS_PER_CALL = 6


@dataclass
class ArcCase:
    """The arcs of one data set: inputs A (n_in × n), their event-located outputs Y."""

    name: str
    model: Model
    A: np.ndarray
    Y: np.ndarray
    rows: tuple = field(default=())
    labels: tuple = field(default=())  # per arc, which slip it is ("RUN slip N"), for the grazing list


def arc_case(name: str, traces, values: dict | None = None, coating: str = "FOTAS",
             v_stick: float = 1e-5, law: str = "exponential") -> ArcCase:
    """The arcs of ``traces`` (a list of :class:`identify.traces.io.Trace`) at friction
    ``values`` (default: the coating's preset), with the stick option ``v_stick``
    (0: the equations as written), their starts synced to the previous arcs' ends."""
    from identify.fitting.driver import FitOptions
    from identify.fitting.problem import Problem
    from identify.fitting.rundata import make_run_data
    from identify.traces.events import extract_events

    model = Model(get_law(law))
    truth = dict(parameter_set(coating), v_stick=v_stick, **(values or {}))
    runs = [make_run_data(extract_events(tr)) for tr in traces]
    runs = [r for r in runs if r.kind == "events"]
    full = {**model.defaults(truth), "drift_rate": 0.0, "exposure": 0.0, "v_stick": v_stick}
    prob = Problem(runs, model, full, FitOptions(fixed={"v_stick": v_stick})).build()
    w = prob.initial_w({n: truth[n] for n in prob.theta.names})
    A = prob.arc_inputs(w)
    arcs = arc_functions(model)
    rows = tuple(arcs.index[n] for n in DEFAULT_ROWS)
    labels = tuple(f"{runs[ri].name} slip {int(np.sum(prob.ev_run[:e] == ri)) + 1}"
                   for e, ri in enumerate(prob.ev_run))
    return ArcCase(name, model, A, arcs.evaluate(A), rows, labels)


def grazing_list(flags: np.ndarray, labels: Sequence[str] = ()) -> list[dict]:
    """The grazing arcs of :func:`identify.fitting.exact_arcs.grazing_flags` ``flags``, each
    named by its label ("RUN slip N"; "arc N" without one) with its reasons."""
    return [dict(arc=labels[e] if e < len(labels) else f"arc {e + 1}",
                 reasons=[r for b, r in enumerate(GRAZING_REASONS) if int(flags[e]) >> b & 1])
            for e in np.nonzero(np.asarray(flags))[0]]


def _errors(J: np.ndarray, ref: np.ndarray, rows, typical: np.ndarray, mask: np.ndarray) -> dict:
    """Largest relative and scaled absolute error over the entries of ``rows`` and the
    arcs in ``mask``, and the share of entries that agree (AGREE_REL or AGREE_ABS)."""
    if not mask.any():
        return dict(rel=float("nan"), abs=float("nan"), agree=float("nan"), n=0)
    d = np.abs(J[:, rows][:, :, mask] - ref[:, rows][:, :, mask]) * typical[list(rows), None]
    mag = np.abs(ref[:, rows][:, :, mask]) * typical[list(rows), None]
    with np.errstate(invalid="ignore", divide="ignore"):
        rel = np.where(mag > 0, d / mag, np.where(d > 0, np.inf, 0.0))
    ok = (rel <= AGREE_REL) | (d <= AGREE_ABS)
    fin = np.isfinite(d)
    return dict(rel=float(np.nanmax(np.where(fin, rel, np.nan))) if fin.any() else float("nan"),
                abs=float(np.nanmax(np.where(fin, d, np.nan))) if fin.any() else float("nan"),
                agree=float(ok.mean()), n=int(mask.sum()))


def _by_arcs(fn, *arrays):
    """``fn`` over the arcs (columns of ``arrays``) a few at a time, the interrupt checked
    between calls; its outputs' last axes joined back."""
    n = arrays[0].shape[1]
    parts = []
    for s in range(0, n, ARCS_PER_CALL):
        parts.append(fn(*(a[:, s:s + ARCS_PER_CALL] for a in arrays)))
        interrupts.check()  # (a Ctrl-C inside CasADi's calls is only noted there)
    return tuple(np.concatenate([p[k] for p in parts], axis=-1) for k in range(len(parts[0])))


def _fd(arcs, A, rows, scheme, rel_step):
    def one(a):
        _, J = arcs.evaluate_jacobian(a, rows=list(rows), scheme=scheme, rel_step=rel_step)
        return (J.reshape(2, a.shape[1], arcs.n_in).transpose(0, 2, 1),)

    t0 = time.perf_counter()
    (J,) = _by_arcs(one, A)
    return J, time.perf_counter() - t0


def idas_differences(exact: ExactArcs, arcs, A: np.ndarray, rows, rel_step: float) -> np.ndarray:
    """Central differences of the IDAS arc's own outputs, each perturbed arc seeded by its
    own event-located simulation (2 × n_in × n)."""
    n = A.shape[1]
    J = np.zeros((2, arcs.n_in, n))
    for i in rows:
        h = rel_step * np.maximum(np.abs(A[i]), arcs.typical[i])
        out = []
        for sgn in (1.0, -1.0):
            B = A.copy()
            B[i] += sgn * h
            y, _, _ = _by_arcs(lambda b, r=(i,): exact.jacobian(b, arcs.evaluate(b), rows=r), B)
            out.append(y[:2])
        J[:, i, :] = (out[0] - out[1]) / (2 * h)
    return J


def compare(case: ArcCase, reltol: float = EXACT_RELTOL, self_check: bool = True) -> dict:
    """Every figure of the derivatives check for one case (see the module docstring)."""
    model, A, Y, rows = case.model, case.A, case.Y, case.rows
    arcs = arc_functions(model)
    exact = ExactArcs(model, arcs.input_names, reltol, (reltol,) * 3)
    exact.jacobian(A[:, :1], Y[:, :1], rows)  # (builds the Functions: not timed)
    t0 = time.perf_counter()
    _, J_exact, ok = _by_arcs(lambda a, y: exact.jacobian(a, y, rows), A, Y)
    t_exact = time.perf_counter() - t0
    J_fwd, t_fwd = _fd(arcs, A, rows, "forward", 1e-4)
    J_cen, t_cen = _fd(arcs, A, rows, "central", 1e-4)
    tight = arc_functions(model, REFERENCE_TOL, REFERENCE_TOL * 1e-2)
    J_ref, _ = _fd(tight, A, rows, "central", REFERENCE_STEP)
    flags = grazing_flags(model, A, Y, arcs.index, arcs)
    smooth = (flags == 0) & ok
    out = dict(case=case.name, arcs=int(A.shape[1]), exact_failed=int((~ok).sum()),
               grazing=int((flags != 0).sum()),
               grazing_by_reason={r: int(((flags >> b) & 1).sum()) for b, r in enumerate(GRAZING_REASONS)},
               grazing_arcs=grazing_list(flags, case.labels),
               rows=[arcs.input_names[r] for r in rows], reltol=reltol,
               ms_per_arc=dict(exact=1e3 * t_exact / A.shape[1], forward=1e3 * t_fwd / A.shape[1],
                               central=1e3 * t_cen / A.shape[1]))
    for name, J in (("exact", J_exact), ("forward", J_fwd), ("central", J_cen)):
        out[name] = _errors(J, J_ref, rows, arcs.typical, smooth)
        out[name + "_grazing"] = _errors(J, J_ref, rows, arcs.typical, (flags != 0) & ok)
    if self_check:
        tight_exact = ExactArcs(model, arcs.input_names, REFERENCE_TOL, (REFERENCE_TOL,) * 3)
        J_self = idas_differences(tight_exact, arcs, A, rows, REFERENCE_STEP)
        out["exact_vs_idas_differences"] = _errors(J_exact, J_self, rows, arcs.typical, smooth)
    return out


def _simulated(conditions, v_stick: float, travel_um: float, coating: str = "FOTAS"):
    from identify.simulation.hybrid import SimulationOptions, simulate

    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, nb, fp in conditions:
            run = simulate(coating, spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                           travel_um=travel_um, stick_speed_m_per_s=v_stick,
                           options=SimulationOptions(record=False))
            out.append(run.sample(noise_nm=0.0, seed=0, name=f"k{k:g}_Nb{nb:g}_fp{fp:g}"))
    return out


# fast slips under the stick option; the same conditions as written (stops at reversal,
# after creep tails) make the slow-stop set
FAST_CONDITIONS = ((2.13, 5, 100), (20.3, 30, 30), (2.13, 20, 300))
SLOW_CONDITIONS = ((2.13, 5, 10), (2.13, 10, 10), (20.3, 30, 10))


def default_cases(data: str | None, travel_um: float = 10.0) -> list[ArcCase]:
    """The bundled data set's arcs (when ``data`` is a folder), and simulated sets of
    fast stops (stick option) and slow stops (the equations as written)."""
    cases = []
    if data:
        from identify.traces.io import load_traces

        cases.append(arc_case(f"{data} (v_stick 1e-5)", list(load_traces([data]))[:4], v_stick=1e-5))
    cases.append(arc_case("fast stops (simulated, v_stick 1e-5)",
                          _simulated(FAST_CONDITIONS, 1e-5, travel_um), v_stick=1e-5))
    cases.append(arc_case("slow stops (simulated, as written)",
                          _simulated(SLOW_CONDITIONS, 0.0, travel_um), v_stick=0.0))
    return cases


def format_result(r: dict) -> str:
    reasons = ", ".join(f"{n} {k}" for k, n in r["grazing_by_reason"].items() if n) or "none"
    head = (f"{r['case']}: {r['arcs']} arcs, {r['grazing']} grazing ({reasons}), "
            f"{r['exact_failed']} the exact route could not do; inputs {', '.join(r['rows'])}")
    lines = [head, *(f"  grazing: {g['arc']} ({', '.join(g['reasons'])})" for g in r.get("grazing_arcs", [])),
             f"  {'Jacobian':<28s} {'max rel err':>12s} {'max abs err':>12s} {'agree':>7s} {'ms/arc':>8s}"]
    for name, label in (("exact", f"exact (IDAS {r['reltol']:g})"), ("forward", "forward differences"),
                        ("central", "central differences")):
        e = r[name]
        lines.append(f"  {label:<28s} {e['rel']:12.2e} {e['abs']:12.2e} {100 * e['agree']:6.1f}% "
                     f"{r['ms_per_arc'][name]:8.2f}")
        g = r[name + "_grazing"]
        if g["n"]:
            lines.append(f"    {'(grazing arcs)':<26s} {g['rel']:12.2e} {g['abs']:12.2e} {100 * g['agree']:6.1f}%")
    if "exact_vs_idas_differences" in r:
        e = r["exact_vs_idas_differences"]
        lines.append(f"  {'exact vs IDAS differences':<28s} {e['rel']:12.2e} {e['abs']:12.2e} "
                     f"{100 * e['agree']:6.1f}%")
    lines.append(f"  (reference: central differences of the event-located arcs at tolerance "
                 f"{REFERENCE_TOL:g}, step {REFERENCE_STEP:g}; agree: within {AGREE_REL:g} relative "
                 f"or {AGREE_ABS:g} absolute per unit of each input's scale)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m identify bench derivatives",
                                 description="Arc Jacobians (exact IDAS route and finite differences) "
                                 "against tight central differences, and their cost, measured in this run.")
    ap.add_argument("--data", default="data/FOTAS", help="a folder of runs whose arcs to check "
                    "(default data/FOTAS; '' for none)")
    ap.add_argument("--reltol", type=float, default=EXACT_RELTOL, help="IDAS tolerance of the exact route")
    ap.add_argument("--travel-um", type=float, default=10.0, help="travel of the simulated sets, µm")
    ap.add_argument("--json", metavar="OUT", help="write every figure to this JSON file")
    a = ap.parse_args(argv)
    import os

    data = a.data if a.data and os.path.isdir(a.data) else None
    results = []
    try:
        with interrupts.honoured():
            for case in default_cases(data, a.travel_um):
                r = compare(case, a.reltol)
                results.append(r)
                print(format_result(r), flush=True)
    except KeyboardInterrupt:
        kept = f" (and in {a.json})" if a.json and results else ""
        print(f"interrupted: {len(results)} case(s) finished, printed above{kept}", file=sys.stderr)
        return 130
    finally:  # what finished is written even when interrupted
        if a.json and results:
            with open(a.json, "w") as fh:
                fh.write(dumps(results, indent=1))
    return 0

