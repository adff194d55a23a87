"""Benchmarks of the full-model fit (issue: identification, item 8). Not timed tests:
they print what they measure.

    python tests/bench/bench_fit.py calibration --repeats 50 [--workers 2] [--jitter-load 0.05]
        [--record cal.jsonl] [--seeds LO-HI]
    python tests/bench/bench_fit.py speed [--runs 2,5,10,20] [--steps 2000]
    python tests/bench/bench_fit.py summary cal.jsonl
    python tests/bench/bench_fit.py robustness [--sets 20] [--effects all|none|ID,ID] [--seed 0]
        [--workers 2] [--record rob.jsonl]

calibration: each repeat simulates the design (the same noiseless runs every time), draws new 90 nm
camera noise (seed = repeat), fits from a start 20 % off, and records whether each 95 %
interval contains the truth. Prints, per parameter, the coverage (target 90-98 %), the
mean error and the spread of the estimates against the mean reported standard error.
With ``--jitter-load J`` each repeat also scales every run's normal load by a seeded
factor in [1 − J, 1 + J] (simulated afresh): a stick-slip cycle locks its triggers at
one phase of the step interval, a deterministic function of the run's conditions, so
noise repeats of one design share one set of phase errors, and coverage over them is
coverage conditional on those phases. A few per cent of load moves the trigger
elongation by a fraction of a step and redraws the phases: coverage over the jittered
designs is the coverage a researcher can expect, not knowing where their cycles lock.
``--record FILE`` appends each repeat to FILE (JSON lines) as it finishes and skips the
repeats FILE already holds for the same coating, travel, jitter and fit options: a stopped
benchmark resumes where it stopped, and a changed default refits.

robustness: data sets made to vary more than the noise, fitted with the defaults (the
stick option by ``stick_speed="auto"``, which a user is told to pick), each judged by its
data: the default fit must reach the χ² of a fit started from the truth's friction
(within ``CHI2_SLACK``), and, in the clean sets, every 95 % interval of μmax, μmin, τ, A
must hold the truth or be flagged. Clean sets: friction drawn at random (μmax ∈ [0.5,
0.9], μmin ∈ [0.3, μmax − 0.08], τ ∈ [20, 300] ms log-uniform, A ∈ [0.003, 0.03]
log-uniform), 6-8 runs drawn from ``ROBUST_POOL`` that stick-slip under that truth,
alternately from a fully aged contact (ψ0 = μmax) and the simulator's default start,
the frames at ¼ or ¾ of the step period, 90 nm noise. Effect sets: the withheld-effect
library's runs with one effect the model lacks, at its realistic magnitude.

speed: joint fits of N runs of about ``--steps`` puller steps each (FOTAS, 90 nm), the
time per fit, its growth with N (the exponent of a power-law fit; 1 = linear), and where
the time goes (arc integrations, arc Jacobians, the rest: assembly and linear algebra; and, across
them, the share spent deciding the mode sequence after the first solve).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
import warnings

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # "on one core"

import numpy as np  # noqa: E402

V_STICK = 1e-5
FREE = ("mu_max", "mu_min", "tau", "A")
# k (N/m), Nb (µN), fp (Hz): rest times from ~60 ms (near τ) to ~0.7 s
CAL_CONDITIONS = [(2.13, 5, 100), (20.3, 30, 30), (20.3, 30, 100), (2.13, 10, 100)]
# every prefix mixes both springs and short and long rests: a speed test of a design
# that cannot determine the parameters (two runs of one spring and load) measures a
# solver crawling along a flat valley, not the speed of a fit. Every run is pulled slower
# than V_STICK: the third run was (2.13, 20, 300) until 2026-11-23, 13.8 µm/s, on the
# stick threshold's knife edge (RunData.stick_edge): the 5-run fit crawled there at step
# lengths <= 1e-2 from either start tried: a measure of that discontinuity, not of speed
SPEED_CONDITIONS = [(2.13, 5, 100), (20.3, 30, 30), (20.3, 30, 200), (20.3, 30, 100), (2.13, 5, 30),
                    (20.3, 60, 100), (2.13, 10, 100), (2.13, 30, 10), (20.3, 30, 60), (2.13, 10, 30)]


def _simulate(conditions, coating, travel_um):
    from identify import SimulationOptions, simulate

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return [simulate(coating, spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                         travel_um=travel_um, stick_speed_m_per_s=V_STICK, options=SimulationOptions(record=False))
                for k, nb, fp in conditions]


COVARIANCES = ("robust", "cluster", "model")


def _start(truth):
    """20 % off, each parameter pushed the way that makes the fit work hardest."""
    return {"mu_max": truth["mu_max"] / 1.2, "mu_min": truth["mu_min"] * 1.2,
            "tau": truth["tau"] * 1.2, "A": truth["A"] * 1.2}


def _fit_options(start, **changes):
    from identify import FitOptions

    return FitOptions(start=start, fixed={"v_stick": V_STICK}, threads=1, **changes)


def _fit(traces, coating, start, **changes):
    from identify import fit

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit(traces, coating=coating, options=_fit_options(start, **changes))


def _truth(coating):
    from identify.model.params import parameter_set

    return dict(parameter_set(coating), v_stick=V_STICK)


def _one_repeat(args):
    coating, travel_um, seed, jitter = args
    conds = CAL_CONDITIONS
    if jitter:
        f = np.random.default_rng(10_000 + seed).uniform(1 - jitter, 1 + jitter, len(conds))
        conds = [(k, nb * fi, fp) for (k, nb, fp), fi in zip(conds, f)]
    sims = _simulate(conds, coating, travel_um)
    traces = [s.sample(noise_nm=90, seed=1000 * seed + i, name=f"r{i}") for i, s in enumerate(sims)]
    truth = _truth(coating)
    start = _start(truth)
    t0 = time.perf_counter()
    try:
        res = _fit(traces, coating, start)
    except Exception as err:  # one failed repeat is data, not a crash
        return dict(seed=seed, error=f"{type(err).__name__}: {err}")
    out = dict(seed=seed, wall_s=time.perf_counter() - t0, success=bool(res.solver["success"]),
               iterations=res.solver["iterations"], status=res.solver["status"], reduced_chi2=res.redchi,
               start=res.start_source, normal_loads_uN=[c[1] for c in conds],
               slips_inserted=res.solver.get("slips_inserted", 0), restarts=res.solver.get("restarts", []))
    # every covariance at the same solution: one calibration measures them all
    other = {mode: res.uncertainty(mode) for mode in COVARIANCES}
    for n in FREE:
        p = res[n]
        out[n] = dict(value=p.value, stderr=p.stderr, ci95=list(p.ci95) if p.ci95 else None,
                      by_covariance={mode: other[mode][n] for mode in COVARIANCES})
    return out


def _record_rows(record):
    """The rows of a record file, in order (a line cut by a stop skipped)."""
    with open(record) as f:
        for line in f:
            try:
                yield json.loads(line)
            except json.JSONDecodeError:
                continue


def _recorded(record, context) -> dict:
    """Repeats a record file holds for this context (seed -> row)."""
    if not (record and os.path.exists(record)):
        return {}
    return {row["seed"]: row for row in _record_rows(record) if row.get("context") == context}


def calibration(repeats: int, coating: str, travel_um: float, workers: int, jitter: float = 0.0,
                record: str | None = None, seeds: range | None = None) -> dict:
    from concurrent.futures import as_completed

    truth = _truth(coating)
    context = dict(coating=coating, travel_um=travel_um, jitter_load=jitter,
                   fit_options=repr(_fit_options(_start(truth))), covariances=list(COVARIANCES))
    done = _recorded(record, context)
    rows = [done[s] for s in range(repeats) if s in done]
    if rows:
        print(f"  {len(rows)} repeat(s) taken from {record}", file=sys.stderr)
    todo = [s for s in range(repeats) if s not in done and (seeds is None or s in seeds)]
    if seeds is not None:  # a share of the repeats, e.g. on another machine: its repeats in reverse
        todo = todo[::-1]  # (so a process doing all of them in order meets it instead of doubling it)
    jobs = [(coating, travel_um, s, jitter) for s in todo]
    t0 = time.perf_counter()
    with _pool(workers) as ex:
        futures = {ex.submit(_one_repeat, job): job[2] for job in jobs}
        for fut in as_completed(futures):
            row = fut.result()
            rows.append(row)
            if record:
                with open(record, "a") as f:
                    f.write(json.dumps(dict(row, context=context), default=float) + "\n")
            print(f"\r  repeat {len(rows)}/{repeats} done (seed {futures[fut]}, "
                  f"{time.perf_counter() - t0:.0f} s)", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    summary = summarize(rows, coating, travel_um, jitter, workers)
    return dict(coating=coating, repeats=repeats, travel_um=travel_um, conditions=CAL_CONDITIONS,
                jitter_load=jitter, summary=summary, rows=rows)


def coverage_range(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Clopper–Pearson range of a coverage seen k times in n: what the repeats can tell
    apart. 50 of 50 is [0.929, 1], which holds the target band 90-98 %: a coverage
    measured on 50 repeats misses the band only when its whole range lies outside it."""
    from scipy import stats

    a = (1 - level) / 2
    lo = stats.beta.ppf(a, k, n - k + 1) if k > 0 else 0.0
    hi = stats.beta.ppf(1 - a, k + 1, n - k) if k < n else 1.0
    return float(lo), float(hi)


def _band(k: int, n: int) -> str:
    lo, hi = coverage_range(k, n)
    return f"{k}/{n}, {100 * lo:.0f}-{100 * hi:.0f} %"


def summarize(rows: list, coating: str, travel_um: float, jitter: float, workers: int | None = None) -> dict:
    """Print the calibration's table from its repeats (fitted now, or read from a record
    file by ``summary``) and return it per parameter."""
    truth = _truth(coating)
    rows = sorted(rows, key=lambda r: r["seed"])
    repeats = len(rows)
    ok = [r for r in rows if "error" not in r]
    summary = {}
    print(f"calibration: {coating}, {len(CAL_CONDITIONS)} runs x {travel_um:g} µm, 90 nm, start 20 % off"
          + (f", loads jittered ±{100 * jitter:g} %" if jitter else "")
          + f"; {len(ok)}/{repeats} repeats fitted ({sum(r['success'] for r in ok)} converged)")
    print("  (coverage: k of n repeats and its 95 % Clopper-Pearson range)")
    print(f"  {'param':8} {'coverage':>9} {'k/n, range':>16} {'mean err':>9} {'sd(est)':>9} {'mean se':>9} "
          f"{'sd/se':>6} {'med z':>6}")
    for n in FREE:
        v = np.array([r[n]["value"] for r in ok])
        se = np.array([r[n]["stderr"] if r[n]["stderr"] is not None else np.nan for r in ok], float)
        cover = np.array([r[n]["ci95"] is not None and r[n]["ci95"][0] <= truth[n] <= r[n]["ci95"][1] for r in ok])
        rel = (v - truth[n]) / truth[n]
        z = (v - truth[n]) / se
        summary[n] = dict(coverage=float(cover.mean()) if len(ok) else None, mean_rel_error=float(rel.mean()),
                          sd_rel=float(np.std(rel, ddof=1)) if len(ok) > 1 else None,
                          mean_rel_stderr=float(np.nanmean(se / truth[n])),
                          median_z=float(np.nanmedian(z)) if len(ok) else None)
        s = summary[n]
        s["covered"], s["coverage_range"] = int(cover.sum()), coverage_range(int(cover.sum()), len(ok))
        print(f"  {n:8} {100 * s['coverage']:8.0f}% {_band(s['covered'], len(ok)):>16} "
              f"{100 * s['mean_rel_error']:+8.2f}% {100 * (s['sd_rel'] or np.nan):8.2f}% "
              f"{100 * s['mean_rel_stderr']:8.2f}% {(s['sd_rel'] or np.nan) / s['mean_rel_stderr']:6.2f} "
              f"{s['median_z'] or np.nan:+6.2f}")
    have = [r for r in ok if all("by_covariance" in r[n] for n in FREE)]
    if have:
        print(f"  coverage by covariance ({len(have)} repeats; sd(est)/median se):")
        for mode in COVARIANCES:
            cells = []
            for n in FREE:
                bc = [r[n]["by_covariance"][mode] for r in have]
                hits = [b["ci95"] is not None and b["ci95"][0] <= truth[n] <= b["ci95"][1] for b in bc]
                cov = np.mean(hits)
                se = np.array([b["stderr"] if b["stderr"] is not None else np.nan for b in bc], float)
                sd = np.std([r[n]["value"] for r in have], ddof=1) if len(have) > 1 else np.nan
                lo, hi = coverage_range(int(np.sum(hits)), len(hits))
                cells.append(f"{n} {100 * cov:3.0f}% [{100 * lo:.0f}-{100 * hi:.0f}] ({sd / np.nanmedian(se):4.2f})")
                summary[n].setdefault("coverage_by_covariance", {})[mode] = float(cov)
            print(f"    {mode:8} " + "  ".join(cells))
    walls = [r["wall_s"] for r in ok]
    if walls:
        print(f"  time per fit: median {np.median(walls):.1f} s" + (f" (workers {workers})" if workers else ""))
    # does the second solve of a suspect solution ever pay? (it costs a third of a stall's time)
    started = [r for r in ok if "start" in r]
    again = [r for r in started if "solved again" in r["start"]]
    if started:
        kept = [r["seed"] for r in again if r["start"].endswith(": kept")]
        print(f"  suspect re-solve: {len(again)} of {len(started)} fits, kept in {len(kept)}"
              + (f" (seeds {', '.join(map(str, kept))})" if kept else ""))
    errors = [r for r in rows if "error" in r]
    for r in errors:
        print(f"  repeat {r['seed']} failed: {r['error']}")
    return summary


def summary_of_record(record: str) -> dict:
    """The calibration table of every context a record file holds (its repeats as they
    were fitted, whatever the code is now): what ``summary FILE`` prints."""
    groups: dict = {}
    for row in _record_rows(record):
        groups.setdefault(json.dumps(row.get("context") or {}, sort_keys=True), {})[row["seed"]] = row
    out = []
    for key, by_seed in groups.items():
        ctx = json.loads(key)
        print(f"{record}: {len(by_seed)} repeat(s) with fit options {ctx.get('fit_options', '?')}")
        out.append(dict(context=ctx, summary=summarize(list(by_seed.values()), ctx.get("coating", "FOTAS"),
                                                     ctx.get("travel_um", 20.0), ctx.get("jitter_load", 0.0))))
    return dict(record=record, contexts=out)


def growth(rows: list) -> dict:
    """How the wall time grows with the number of runs: the least-squares slope of
    log(wall) on log(runs) (``growth_exponent``, 1 = linear) and the slope between
    neighbouring sizes (``growth_steps``): a fitted slope hides one size that costs more
    than its share, as the 5-run set does. Empty with fewer than two sizes."""
    sizes = sorted({r["runs"] for r in rows})
    if len(sizes) < 2:
        return {}
    wall = {n: min(r["wall_s"] for r in rows if r["runs"] == n) for n in sizes}
    x, y = np.log(sizes), np.log([wall[n] for n in sizes])
    steps = [dict(runs=[int(a), int(b)], exponent=float(np.log(wall[b] / wall[a]) / np.log(b / a)))
             for a, b in zip(sizes, sizes[1:])]
    return dict(growth_exponent=float(np.polyfit(x, y, 1)[0]), growth_steps=steps)


def speed(n_runs_list, steps: int, coating: str, solvers=("ipopt", "gauss-newton")) -> dict:
    """Each run count fitted by each solver in turn; the later solvers are the baseline
    the first is measured against (the ratio column: its time over theirs)."""
    truth = _truth(coating)
    start = _start(truth)
    travel = steps * 46e-3
    n_max = max(n_runs_list)
    conds = [SPEED_CONDITIONS[i % len(SPEED_CONDITIONS)] for i in range(n_max)]
    print(f"speed: simulating {n_max} runs of {steps} steps ({travel:.0f} µm)", file=sys.stderr)
    sims = _simulate(conds, coating, travel)
    rows = []
    print(f"  {'runs':>4} {'solver':>12} {'slips':>6} {'wall s':>8} {'ratio':>6} {'its':>4} {'s/it':>6} "
          f"{'arcs s':>8} {'jac s':>7} {'rest s':>8} {'seq s':>7}  status")
    for n in n_runs_list:
        traces = [s.sample(noise_nm=90, seed=i, name=f"r{i}") for i, s in enumerate(sims[:n])]
        first = None
        for solver in solvers:
            t0 = time.perf_counter()
            res = _fit(traces, coating, start, solver=solver)
            wall = time.perf_counter() - t0
            t = res.timing
            its = res.solver["iterations"]
            row = dict(runs=n, solver=solver, slips=res.n_events, wall_s=wall, iterations=its,
                       s_per_iteration=wall / max(its, 1),
                       arc_s=t["arc_s"], jac_s=t["jac_s"], rest_s=max(wall - t["arc_s"] - t["jac_s"], 0),
                       # of the wall time: deciding the mode sequence after the first solve
                       sequence_s=t.get("sequence_s", float("nan")),
                       status=res.solver["status"], start=res.start_source, chi2=res.chi2,
                       # a slow fit that ends far from the truth is a start problem, not a speed one
                       rel_error={n_: res[n_].value / truth[n_] - 1 for n_ in FREE},
                       reduced_chi2=res.redchi)
            first = first or row
            row["ratio"] = first["wall_s"] / wall  # (the first solver's time over this one's)
            rows.append(row)
            print(f"  {n:4d} {solver:>12} {row['slips']:6d} {wall:8.1f} {row['ratio']:6.2f} {its:4d} "
                  f"{row['s_per_iteration']:6.2f} {row['arc_s']:8.1f} {row['jac_s']:7.1f} {row['rest_s']:8.1f} "
                  f"{row['sequence_s']:7.1f}  {row['status']}", flush=True)
            print("        errors " + ", ".join(f"{k} {v:+.2%}" for k, v in row["rel_error"].items())
                  + f"; chi2 {row['chi2']:.2f}, reduced {row['reduced_chi2']:.3g}; start: {row['start']}",
                  flush=True)
    out = dict(coating=coating, steps=steps, rows=rows)
    lead = [r for r in rows if r["solver"] == solvers[0]]
    out.update(growth(lead))
    if "growth_exponent" in out:
        print(f"  {solvers[0]}'s time grows as runs^{out['growth_exponent']:.2f} (1 = linear; fitted over all "
              "sizes); " + ", ".join(f"{g['runs'][0]}->{g['runs'][1]}: ^{g['exponent']:.2f}"
                                     for g in out["growth_steps"]))
    ten = [r for r in lead if r["runs"] == 10]
    if ten:
        print(f"  10 runs, {solvers[0]}: {ten[0]['wall_s']:.1f} s (goal 10 s) -> "
              + ("met" if ten[0]["wall_s"] <= 10 else "missed"))
    return out


# conditions a clean set draws from: rests from ~3 ms (300 Hz) to ~0.7 s, both springs
ROBUST_POOL = [(2.13, 5, 100), (2.13, 10, 30), (2.13, 20, 10), (2.13, 8, 10), (2.13, 30, 100), (2.13, 12, 100),
               (20.3, 30, 30), (20.3, 60, 100), (20.3, 50, 10), (20.3, 30, 100), (2.13, 5, 300)]
ROBUST_EFFECTS = ("spring_nonlinearity", "load_offset", "aging_logarithmic", "drift", "topography")
CHI2_SLACK = 1.0  # χ²: a default fit within this of the truth-started fit reached its solution


def _clean_set(index: int, seed: int):
    """(truth, traces) of clean set ``index``."""
    from identify import SimulationOptions, simulate

    rng = np.random.default_rng(seed * 1000 + index)
    mu_max = rng.uniform(0.5, 0.9)
    truth = dict(mu_max=mu_max, mu_min=rng.uniform(0.3, mu_max - 0.08),
                 tau=float(np.exp(rng.uniform(np.log(0.02), np.log(0.3)))),
                 A=float(np.exp(rng.uniform(np.log(0.003), np.log(0.03)))))
    want = int(rng.integers(6, 9))
    traces = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for j in rng.permutation(len(ROBUST_POOL)):
            k, nb, fp = ROBUST_POOL[j]
            aged = len(traces) % 2 == 0
            sim = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                           travel_um=20.0, stick_speed_m_per_s=V_STICK, params=truth,
                           initial_state=mu_max if aged else None, options=SimulationOptions(record=True))
            if sim.regime != "stick-slip":
                continue
            traces.append(sim.sample(noise_nm=90, seed=int(rng.integers(1 << 30)), name=f"k{k}_Nb{nb}_fp{fp}",
                                     frame_phase=0.25 if len(traces) % 2 else 0.75))
            if len(traces) == want:
                break
    return truth, traces


def _judge(traces, truth: dict, seed: int, check_intervals: bool) -> dict:
    from identify import FitOptions, fit

    row = dict(truth={k: float(v) for k, v in truth.items()})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        try:
            res = fit(traces, coating="FOTAS", options=FitOptions(stick_speed="auto", seed=seed, threads=1))
        except Exception as err:  # noqa: BLE001 - a failed fit is a result here
            row.update(ok=False, wall_s=time.perf_counter() - t0, error=str(err)[:200])
            return row
        row["wall_s"] = time.perf_counter() - t0
        try:
            ref = fit(traces, coating="FOTAS", options=FitOptions(
                fixed={"v_stick": V_STICK}, start={n: truth[n] for n in FREE}, staged_start=False, auto_starts=0,
                threads=1))
            row["truth_chi2"] = float(ref.chi2)
        except Exception as err:  # noqa: BLE001
            row["truth_chi2"], row["ref_error"] = float("nan"), str(err)[:200]
    row.update(chi2=float(res.chi2), redchi=float(res.redchi), status=res.solver["status"],
               concerns=res.concerns, start=res.start_source,
               # slips at a creep tail's onset: a miss beside one may be a pocket of the kink
               creep_onsets=[f"{o['run']} slip {o['slip']}" for o in res.solver.get("creep_onsets", [])],
               values={n: float(res[n].value) for n in FREE},
               # what each interval said, to see how far a miss was
               intervals={n: dict(ci95=list(res[n].ci95) if res[n].ci95 else None, stderr=res[n].stderr,
                                  flag=res[n].flag) for n in FREE})
    reached = bool(np.isfinite(row["truth_chi2"]) and row["chi2"] <= row["truth_chi2"] + CHI2_SLACK)
    held = {}
    alt = res.solver.get("stick_alternative")
    for n in FREE:
        p = res[n]
        inside = p.ci95 is not None and p.ci95[0] <= truth[n] <= p.ci95[1]
        if n == "mu_max" and alt and p.ci95 is not None:
            # the flag names μmax under the other stick option, and a stick speed between the
            # two gives a value between: held if the span of both intervals holds it
            shift = alt["mu_max"] - p.value
            inside = min(p.ci95[0], p.ci95[0] + shift) <= truth[n] <= max(p.ci95[1], p.ci95[1] + shift)
            other_flags = [f for f in (p.flag or "").split("; ") if f and not f.startswith("depends on the stick")]
            held[n] = inside or bool(other_flags)
        else:
            held[n] = bool(p.flag) or inside
    row.update(reached=reached, intervals_hold=held,
               ok=reached and (all(held.values()) if check_intervals else True))
    return row


def _robust_job(job):
    """One robustness set, by name: ("clean", i, seed) or ("effect", id, seed)."""
    kind, which, seed = job
    if kind == "clean":
        truth, traces = _clean_set(which, seed)
        return dict(_judge(traces, truth, seed + which, True), set=f"clean {which}", runs=len(traces))
    from identify.model.params import parameter_set
    from identify.simulation.withheld import QUICK_CONDITIONS, withheld_dataset

    truth = {n: float(parameter_set("FOTAS")[n]) for n in FREE}
    traces = withheld_dataset(which, conditions=QUICK_CONDITIONS, seed=seed)
    return dict(_judge(traces, truth, seed, False), set=f"effect {which}", runs=len(traces))


def robustness(n_sets: int, effects, seed: int, workers: int = 1, record: str | None = None,
               only: list | None = None) -> dict:
    from concurrent.futures import as_completed

    from identify.fitting.driver import FitOptions

    # a changed default refits: the record is keyed by the options a default fit uses
    context = dict(kind="robustness", seed=seed, fit_options=repr(FitOptions(stick_speed="auto")))
    done = {}
    if record and os.path.exists(record):
        done = {row["set"]: row for row in _record_rows(record) if row.get("context") == context}
    jobs = [("clean", i, seed) for i in (only if only is not None else range(n_sets))] \
        + [("effect", e, seed) for e in effects]
    names = [f"{kind} {which}" for kind, which, _ in jobs]
    print(f"  {'set':<24} {'wall s':>7} {'chi2':>10} {'truth chi2':>10}  reached  intervals  status")
    rows = {}
    for name in names:
        if name in done:
            rows[name] = done[name]
            _robust_line(done[name])
    todo = [job for job, name in zip(jobs, names) if name not in done]
    with _pool(max(1, workers)) as ex:
        for fut in as_completed([ex.submit(_robust_job, job) for job in todo]):
            row = fut.result()
            rows[row["set"]] = row
            if record:
                with open(record, "a") as f:
                    f.write(json.dumps(dict(row, context=context), default=float) + "\n")
            _robust_line(row)
    rows = [rows[name] for name in names]
    clean = [r for r in rows if r["set"].startswith("clean")]
    eff = [r for r in rows if r["set"].startswith("effect")]
    walls = [r["wall_s"] for r in rows]
    out = dict(seed=seed, rows=rows, clean_ok=sum(r["ok"] for r in clean), clean_sets=len(clean),
               effect_ok=sum(r["ok"] for r in eff), effect_sets=len(eff),
               median_wall_s=float(np.median(walls)) if walls else float("nan"),
               max_wall_s=float(max(walls)) if walls else float("nan"))
    print(f"  clean sets: {out['clean_ok']} of {out['clean_sets']} reached the truth's chi2 with every interval "
          f"holding the truth or flagged (target: 19 of 20)")
    # the sets' criterion asks all four intervals at once: at exact 95 % coverage each, that
    # holds in about 0.95^4 = 81 % of the sets (more where the estimates are correlated), so
    # each parameter's coverage is printed too, against the 95 % its interval states
    held = [r for r in clean if "intervals_hold" in r]
    out["coverage"] = {}
    for n in FREE:
        k = sum(bool(r["intervals_hold"][n]) for r in held)
        lo, hi = coverage_range(k, len(held)) if held else (float("nan"), float("nan"))
        out["coverage"][n] = dict(held=k, sets=len(held), range=[lo, hi])
    if held:
        print("  per-parameter coverage of the clean sets' 95 % intervals (flagged counted as held), "
              "Clopper-Pearson 95 % range: "
              + ", ".join(f"{n} {c['held']}/{c['sets']} [{100 * c['range'][0]:.0f}-{100 * c['range'][1]:.0f} %]"
                          for n, c in out["coverage"].items()))
    print(f"  effect sets: {out['effect_ok']} of {out['effect_sets']} reached the truth-started fit's chi2 "
          f"(target: all)")
    print(f"  time per set: median {out['median_wall_s']:.1f} s, max {out['max_wall_s']:.1f} s")
    return out


def _robust_line(row):
    if "error" in row:
        print(f"  {row['set']:<24} {row['wall_s']:7.1f}  failed: {row['error']}", flush=True)
        return
    missed = [n for n, ok in row.get("intervals_hold", {}).items() if not ok]
    print(f"  {row['set']:<24} {row['wall_s']:7.1f} {row['chi2']:10.1f} {row['truth_chi2']:10.1f}  "
          f"{'yes' if row['reached'] else 'NO':>7}  {'all' if not missed else 'miss ' + ','.join(missed):>9}  "
          f"{row['status']}", flush=True)


@contextlib.contextmanager
def _pool(workers: int):
    """A process pool that an interrupt stops at once (its finished rows are in the
    record already) rather than waiting, as a ``with`` pool's exit does, for every
    running fit."""
    from concurrent.futures import ProcessPoolExecutor

    from identify.executors import stop_pool

    ex = ProcessPoolExecutor(max_workers=workers)
    try:
        yield ex
    except KeyboardInterrupt:
        stop_pool(ex)
        raise
    finally:
        ex.shutdown()


def main(argv=None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:
        args = list(sys.argv[1:] if argv is None else argv)
        record = args[args.index("--record") + 1] if "--record" in args[:-1] else None
        hint = " (--record FILE keeps each finished row and resumes)" if args[:1] in (["calibration"],
                                                                                      ["robustness"]) else ""
        print("interrupted: " + (f"the finished rows are in {record}; the same command resumes from it" if record
                                 else "nothing saved" + hint), file=sys.stderr)
        return 130


def _main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    c = sub.add_parser("calibration")
    c.add_argument("--repeats", type=int, default=50)
    c.add_argument("--coating", default="FOTAS")
    c.add_argument("--travel-um", type=float, default=20.0)
    c.add_argument("--workers", type=int, default=1)
    c.add_argument("--jitter-load", type=float, default=0.0, metavar="J",
                   help="scale each run's load by a seeded factor in [1-J, 1+J] per repeat")
    c.add_argument("--record", metavar="FILE", help="append each repeat as it finishes; resume from FILE")
    c.add_argument("--seeds", metavar="LO-HI", help="fit only these repeats (inclusive), highest first: "
                   "a second process or machine sharing the record file")
    r = sub.add_parser("summary", help="the calibration table of a record file, without fitting")
    r.add_argument("record", metavar="FILE")
    s = sub.add_parser("speed")
    s.add_argument("--runs", default="2,5,10,20", help="run counts to fit (runs 11-20 repeat the ten conditions "
                   "with other noise); default %(default)s")
    s.add_argument("--steps", type=int, default=2000)
    s.add_argument("--coating", default="FOTAS")
    s.add_argument("--solvers", default="ipopt,gauss-newton",
                   help="solvers to time, the first against the others (default %(default)s)")
    b = sub.add_parser("robustness", help="defaults-only fits of varied data, judged by their data")
    b.add_argument("--sets", type=int, default=20, help="clean sets (default %(default)s)")
    b.add_argument("--effects", default="all", help="all, none, or comma-separated effect ids")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--workers", type=int, default=1)
    b.add_argument("--record", metavar="FILE", help="append each set as it finishes; resume from FILE")
    b.add_argument("--only", metavar="I,J", help="only these clean sets (e.g. the ones a change is for)")
    for p in (c, s, r, b):
        p.add_argument("--json", metavar="OUT")
    a = ap.parse_args(argv)
    from _code import code_under_test

    code = code_under_test(__file__)
    if a.what == "calibration":
        if not 0 <= a.jitter_load < 1:
            ap.error(f"--jitter-load {a.jitter_load}: must be in [0, 1)")
        seeds = None
        if a.seeds:
            try:
                lo, hi = (int(x) for x in a.seeds.split("-"))
            except ValueError:
                ap.error(f"--seeds {a.seeds}: expected LO-HI, e.g. 25-49")
            seeds = range(lo, hi + 1)
        out = calibration(a.repeats, a.coating, a.travel_um, a.workers, a.jitter_load, a.record, seeds)
    elif a.what == "summary":
        if not os.path.exists(a.record):
            ap.error(f"summary {a.record}: no such file")
        out = summary_of_record(a.record)
    elif a.what == "robustness":
        effects = (ROBUST_EFFECTS if a.effects == "all" else () if a.effects == "none"
                   else tuple(e.strip() for e in a.effects.split(",") if e.strip()))
        only = [int(x) for x in a.only.split(",")] if a.only else None
        out = robustness(a.sets, effects, a.seed, a.workers, a.record, only)
    else:
        out = speed([int(x) for x in a.runs.split(",")], a.steps, a.coating,
                    tuple(x.strip() for x in a.solvers.split(",") if x.strip()))
    if a.json:
        with open(a.json, "w") as f:
            json.dump(dict(out, code=code), f, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
