"""Diagnosis benchmark: confusion table over the effect library, detection limits, speed.

    python tests/bench/bench_diagnosis.py confusion [--effects a,b,c+d] [--scales 1,0.3,0.1]
        [--quick] [--workers 2] [--out bench_diagnosis.jsonl] [--progress] [--candidates a,b]
    python tests/bench/bench_diagnosis.py speed [--workers 2] [--progress] [--seed 0]

``confusion``: for each effect (and "none", "outside"), simulate the withheld-effect data
set (:func:`identify.simulation.withheld.withheld_dataset`) with each scale times the effect's
realistic departure from its null (:meth:`identify.model.effects.Effect.scaled_magnitude`),
fit the baseline without it, diagnose with every candidate (or those of ``--candidates``), and
record what was named, what was reported confounded, the verdict and the held-out gap
before/after.
One JSON line per case is appended as soon as it is done (nothing is lost to a stop);
the table is printed at the end. The detection limit of an effect is the smallest
magnitude at which it is still named (or reported confounded). ``a+b``: both effects on
in one data set (forward selection must name each). ``id:variant``: the effect seen by
another camera (``CAMERA``: ``motion_blur:end``, an exposure ending at the timestamp).

``speed``: one full diagnosis of the 8-run withheld-conditions set
(identify.simulation.withheld.CONDITIONS) with all candidates and
leave-one-run-out, against the time of its own baseline fit measured in the same run;
and its peak memory (resident set) against the process's own after that fit: the
workers' largest, and this process's after the diagnosis. ``--seed``: the set's noise
draw (0, the reference, puts one slip of the baseline's solution at a creep tail's
onset, a kink the solvers stall on; most other draws do not).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import identify
from identify.diagnosis.rounds import DiagnosisOptions, diagnose
from identify.model.effects import EFFECTS, get_effect
from identify.simulation.withheld import CONDITIONS, QUICK_CONDITIONS, withheld_dataset


def _baseline_options(eid):
    fixed = {"v_stick": 1e-5}
    free = ("mu_max", "mu_min", "tau", "A")
    if eid == "velocity_strengthening":  # the paper's story: the baseline fixes A = 0
        fixed["A"] = 0.0
        free = ("mu_max", "mu_min", "tau")
    if eid == "stick_threshold":  # the baseline as written; the data have v_stick = 1e-4
        fixed["v_stick"] = 1e-5
    return identify.FitOptions(fixed=fixed, free=free)


PSEUDO = ("outside", "random_walk")  # withheld_dataset's effects outside the library
# rows of two effects at once that the per-run and per-device candidates need: drift of
# each run's own, with the camera's zero wandering besides; a load offset beside it
COMBINED = ("drift_per_run+random_walk", "load_offset+drift_per_run")
# camera variants of an effect, "id:variant": motion blur from an exposure that ends at the
# timestamp, seen by a camera not locked to the steps (5.3 frames per step: frames at every
# phase, some just after the step of a slip)
CAMERA = {"motion_blur:end": dict(exposure_align="end", frames_per_step=5.3)}


def _magnitude(eid, scale):
    if eid is None or eid in PSEUDO:
        return None
    eff = get_effect(eid)
    return eff.scaled_magnitude(scale) if eff.nested and eff.magnitude else None


def case(eid, scale, quick, workers, seed=0, progress=False, candidates=None):
    """One data set: ``eid`` an effect id, None, "outside", or ids joined by "+" (every one
    of them on at once, each at ``scale``; the baseline fixes what any of them needs);
    ``candidates``: the effects the diagnosis tries (default: the whole library)."""
    camera = CAMERA.get(eid, {})
    row_id, eid = eid, (eid.split(":")[0] if eid else eid)
    ids = eid.split("+") if eid and "+" in eid else None
    mag = [_magnitude(e, scale) for e in ids] if ids else _magnitude(eid, scale)
    conds = QUICK_CONDITIONS if quick else CONDITIONS
    base = {"A": 0.015}
    traces = withheld_dataset(ids or eid, mag, seed=seed, conditions=conds, base=base, **camera)
    t0 = time.perf_counter()
    if ids:  # what any of them needs fixed is fixed; free what all of them leave free
        per = [_baseline_options(e) for e in ids]
        fopts = identify.FitOptions(fixed={k: v for o in per for k, v in o.fixed.items()},
                                    free=tuple(n for n in per[0].free if all(n in o.free for o in per)))
    else:
        fopts = _baseline_options(eid)
    dopts = DiagnosisOptions(workers=workers, **({"effects": list(candidates)} if candidates else {}))
    res = diagnose(traces, fit_options=fopts, options=dopts, progress=progress)
    first = {c["effect"]: c for c in res.candidates}
    # (no baseline: the withheld effect's screen record, which may say what it is confounded with)
    screened = {r["effect"]: r for r in res.regime_screen if r["effect"]}
    truth = first.get(ids[0] if ids else eid) or screened.get(ids[0] if ids else eid, {})
    extra = {}
    if ids:  # each withheld effect: its first-round evidence, and whether it was named
        extra["truth_by_effect"] = {e: dict(named=e in res.effects, p=first.get(e, {}).get("p_value"),
                                            closed=first.get(e, {}).get("closed_fraction"),
                                            confounded_with=first.get(e, {}).get("confounded_with"),
                                            estimates=first.get(e, {}).get("estimates"))
                                    for e in ids}
    return dict(effect=row_id, scale=scale, magnitude=mag, verdict=res.verdict, named=res.effects, **extra,
                # a group confounded with the model's own parameters names them after its effects
                confounded=[g["effects"] + list(g.get("confounded_with", [])) for g in res.confounded],
                truth_confounded_with=truth.get("confounded_with"), truth_p=truth.get("p_value"),
                truth_delta_aic=truth.get("delta_aic"), truth_status=truth.get("status"),
                truth_rounds=truth.get("rounds"),
                heldout_before_um=truth.get("heldout_gap_before_um"),
                heldout_after_um=truth.get("heldout_gap_after_um"),
                final_heldout_um=res.final["heldout_gap_um"], final_gap_um=res.final["gap_um"],
                final_values=res.final["values"], twins_final=res.twins_final,
                noise_um=res.final["noise_um"], notes=res.notes,
                significant=[(c["effect"], c.get("p_value"), round(c.get("closed_fraction") or 0, 2), c.get("note"))
                             for c in res.candidates if c.get("significant")],
                where_top=[(m.feature, round(m.misfit_sigma, 1)) for m in res.where[:3]],
                truth_heldout_delta_nll=truth.get("heldout_delta_nll"),
                truth_explained_share=truth.get("explained_share"),
                baseline={k: (res.baseline.solver if res.baseline is not None else {}).get(k)
                          for k in ("status", "iterations", "wall_time_s", "triggers_moved", "slips_inserted",
                                    "slips_removed")},
                refit_s={c["effect"]: round(c.get("wall_s") or 0.0, 1) for c in res.candidates if c.get("effect")},
                # no baseline: the candidates that reproduce the runs' regime (pointed to, not named)
                screen=[r["effect"] for r in res.regime_screen if r["effect"] and r["reproduces_regime"]],
                # a candidate profiled on every run, the runs left out for their regime included
                profile={k: (res.regime_profile or {}).get(k) for k in (
                    "effect", "value", "interval", "p_value", "named", "slip_gap_before_um",
                    "slip_gap_heldout_um")} if res.regime_profile else None,
                wall_s=time.perf_counter() - t0)


def _stamped(msg):
    # a case takes minutes to an hour: where it is, and since when, without a debugger
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def confusion(args):
    ids = args.effects.split(",") if args.effects else (["none", "outside"] + list(EFFECTS) + list(COMBINED)
                                                        + list(CAMERA))
    scales = [float(s) for s in args.scales.split(",")]
    out = Path(args.out)
    for eid in ids:
        nested = eid != "none" and all(e not in PSEUDO and get_effect(e.split(":")[0]).nested
                                       for e in eid.split("+"))
        for sc in (scales if nested else [1.0]):
            try:
                row = case(None if eid == "none" else eid, sc, args.quick, args.workers,
                           progress=_stamped if args.progress else False,
                           candidates=args.candidates.split(",") if args.candidates else None)
            except Exception as err:  # one failed case never sinks the table
                row = dict(effect=eid, scale=sc, error=f"{type(err).__name__}: {err}")
            with out.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)
    rows = [json.loads(x) for x in out.read_text().splitlines() if x.strip()]
    print(f"\n{'data effect':24s} {'scale':>6s} {'verdict':12s} {'named':30s} {'confounded':30s} {'held-out µm':>16s}")
    for r in rows:
        if "error" in r:
            print(f"{r['effect']:24s} {r['scale']:6g} error: {r['error']}")
            continue
        ho = f"{r['heldout_before_um'] or float('nan'):.3f}->{r['final_heldout_um']:.3f}"
        named = ",".join(r["named"]) or (f"(screen: {','.join(r['screen'])})" if r.get("screen") else "-")
        print(f"{str(r['effect']):24s} {r['scale']:6g} {r['verdict']:12s} {named:30s} "
              f"{';'.join('|'.join(g) for g in r['confounded']) or '-':30s} {ho:>16s}")


def peak_rss_mb(who: str = "self") -> float:
    """Peak resident set size in MB of this process (``self``) or of its largest child
    that has ended (``children``: the diagnosis's worker processes, once shut down)."""
    usage = resource.getrusage(resource.RUSAGE_SELF if who == "self" else resource.RUSAGE_CHILDREN)
    return usage.ru_maxrss / (1024 * 1024 if sys.platform == "darwin" else 1024)  # (bytes there, kB on Linux)


def speed(args):
    traces = withheld_dataset(None, conditions=CONDITIONS, seed=args.seed)
    t0 = time.perf_counter()
    base = identify.fit(traces, options=_baseline_options(None))
    t_fit = time.perf_counter() - t0
    mem_fit = peak_rss_mb()
    t1 = time.perf_counter()
    res = diagnose(None, baseline=base, options=DiagnosisOptions(workers=args.workers),
                   progress=_stamped if args.progress else False)
    t_diag = time.perf_counter() - t1
    print(f"baseline fit {t_fit:.1f} s; diagnosis (all {len(EFFECTS)} candidates, leave-one-run-out, "
          f"{args.workers} workers) {t_diag:.1f} s = {t_diag / t_fit:.1f}× the fit; target 60 s "
          f"({'met' if t_fit + t_diag <= 60 else 'missed'}: {t_fit + t_diag:.0f} s in all); verdict {res.verdict}; "
          f"noise seed {args.seed}, baseline {base.solver.get('status')} after {base.solver.get('iterations')} "
          "iterations")
    # where the diagnosis's time goes: each refit's wall time in its worker (they overlap)
    walls = sorted(((c.get("wall_s") or 0.0, c["effect"], c.get("status"), c.get("iterations"))
                    for r in res.rounds for c in r if c.get("effect")), reverse=True)
    print(f"{res.timing['refits']} refits; the longest: " + ", ".join(
        f"{e} {w:.1f} s ({st}, {it} its)" for w, e, st, it in walls[:6]))
    # a diagnosis shorter than the refits' sum over the workers would be impossible; a
    # longer one is time outside the parallel rounds (or workers waiting on the last refit)
    total = sum(w for w, *_ in walls)
    print(f"the candidates' refits sum to {total:.1f} s of worker time, {total / args.workers:.1f} s per worker "
          f"against the diagnosis's {t_diag:.1f} s")
    # (each worker keeps the arcs it integrated, per candidate model, up to MEMO_MAX each)
    mem_self, mem_worker = peak_rss_mb(), peak_rss_mb("children")
    print(f"peak memory: {mem_fit:.0f} MB after the baseline fit; this process {mem_self:.0f} MB "
          f"({mem_self / mem_fit:.2f}×) after the diagnosis, its largest worker {mem_worker:.0f} MB "
          f"({mem_worker / mem_fit:.2f}×)" + ("" if args.workers > 1 else " (no worker processes with --workers 1)"))


def main(argv=None) -> int:
    try:
        _main(argv)
    except KeyboardInterrupt:
        args = list(sys.argv[1:] if argv is None else argv)
        out = (args[args.index("--out") + 1] if "--out" in args[:-1] else "bench_diagnosis.jsonl"
               ) if args and args[0] == "confusion" else None
        print("interrupted: " + (f"the finished rows are in {out}" if out else "nothing saved"), file=sys.stderr)
        return 130
    return 0


def _main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("confusion")
    c.add_argument("--effects", default=None)
    c.add_argument("--scales", default="1")
    c.add_argument("--quick", action="store_true", help="15 µm runs instead of 30 µm")
    c.add_argument("--workers", type=int, default=2)
    c.add_argument("--out", default="bench_diagnosis.jsonl")
    c.add_argument("--candidates", default=None, help="the effects the diagnosis tries, comma-separated "
                   "(default: the whole library)")
    c.add_argument("--progress", action="store_true", help="the diagnosis's progress on stderr, time-stamped")
    c.set_defaults(func=confusion)
    s = sub.add_parser("speed")
    s.add_argument("--workers", type=int, default=2)
    s.add_argument("--progress", action="store_true", help="the diagnosis's progress on stderr, time-stamped")
    s.add_argument("--seed", type=int, default=0, help="the data set's noise draw (0: the reference)")
    s.set_defaults(func=speed)
    args = ap.parse_args(argv)
    from _code import code_under_test

    code_under_test(__file__)
    args.func(args)


if __name__ == "__main__":
    sys.exit(main())
