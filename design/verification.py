"""Monte Carlo verification of an experiment plan: simulate and fit the plan and its
reference many times, and measure how far the estimates spread against the predicted
standard errors.

Fits run in worker processes, each finished fit appended to an optional JSON-lines
record, so a stopped verification resumes where it stopped; the repeats of the two plans
are interleaved so that a stop leaves both with about as many.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from identify.executors import stop_pool
from identify.interrupts import Interrupted
from identify.jsonio import dumps
from identify.progress import Stage, reporter

from .experiment_plan import ExperimentPlan, geometric_mean_relative
from .information import STICK_SPEED, simulate_candidate

__all__ = ["JITTER_LOAD", "verify_plans"]

JITTER_LOAD = 0.05  # verification: replicate loads within ±5 % (redraws the lock phases)


def _fit_options(free, stick):
    """The options of every verification fit: ``free`` fitted, the stick option held at ``stick``."""
    from identify import FitOptions

    return FitOptions(free=tuple(free), fixed={"v_stick": stick})


def _jittered(plan, seed: int, jitter: float) -> list:
    """The plan's runs with each load drawn within ±jitter of its nominal value (seeded
    by the repeat): replicates of a real run differ a little, and that is what redraws
    the step phases at which its slips lock. (Without it every repeat of a run has the
    same phases and only the frame noise varies: the Monte Carlo would measure less
    than the estimates' spread over real replicates.)"""
    if not jitter:
        return list(plan)
    f = np.random.default_rng([seed, 20261122]).uniform(1 - jitter, 1 + jitter, len(plan))
    return [replace(c, normal_load_uN=float(c.normal_load_uN * fi)) for c, fi in zip(plan, f)]


def _fit_plan(plan, coating, free, noise_nm, stick, seed, jitter=0.0):
    """One repeat: simulate (the loads jittered), add noise, fit; the estimates and the
    fit's own standard errors and 95 % intervals (its robust covariance)."""
    from identify import fit

    traces = []
    for i, c in enumerate(_jittered(plan, seed, jitter)):
        sim = simulate_candidate(c, coating, {}, stick)
        traces.append(sim.sample(noise_nm=noise_nm, seed=10_000 * seed + i, name=f"run{i}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit(traces, coating=coating, options=_fit_options(free, stick), progress=False)
    return dict(estimates={n: res[n].value for n in free},
                stderr={n: res[n].stderr for n in free},
                ci95={n: list(res[n].ci95) if res[n].ci95 else None for n in free})


def _spread(values: np.ndarray) -> tuple[float, float]:
    """Standard deviation and robust spread (1.4826 × MAD) of repeated estimates."""
    from identify.traces.events import MAD_TO_SIGMA  # the one MAD -> σ constant

    if values.size < 2:
        return float("nan"), float("nan")
    return (float(np.std(values, ddof=1)),
            float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values)))))


def _record_context(plan: ExperimentPlan, noise_nm: float, stick_speed_m_per_s: float,
                    jitter_load: float = 0.0) -> dict:
    """Per plan key, everything its fits depend on (the fit's options included, so a
    changed default refits): a record made under other conditions is not reused (JSON
    round-tripped, to compare equal with what a record holds)."""
    runs_of = {"plan_stderr": plan.plan, "reference_stderr": plan.reference_plan}
    return {k: json.loads(json.dumps(dict(runs=[c.to_json() for c in v], coating=plan.coating,
                                          free=list(plan.free), noise_nm=noise_nm,
                                          stick_speed_m_per_s=stick_speed_m_per_s,
                                          fit_options=repr(_fit_options(plan.free, stick_speed_m_per_s)),
                                          **({"jitter_load": jitter_load} if jitter_load else {}))))
            for k, v in runs_of.items()}


def _load_record(path: Path | None, context: dict) -> dict:
    """Finished fits of an earlier verification of the same plans under the same
    conditions: (key, seed) -> row. Failed fits are not taken (a rerun retries them)."""
    done: dict = {}
    if path is None or not Path(path).exists():
        return done
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut by a stop
        if (isinstance(row, dict) and "estimates" in row and row.get("key") in context
                and row.get("context") == context[row["key"]] and isinstance(row.get("seed"), int)):
            done[(row["key"], row["seed"])] = row
    return done


def _job_order(keys: tuple[str, ...], repeats: int, seed: int, done) -> list[tuple[str, int]]:
    """The (key, repeat) fits still to run, interleaved so that a stopped verification
    leaves every plan with about as many repeats (the comparison needs all of them): the
    key with the fewest fits so far, recorded or scheduled, goes next."""
    pending = {k: [r for r in range(repeats) if (k, seed + r) not in done] for k in keys}
    have = {k: repeats - len(rs) for k, rs in pending.items()}
    jobs = []
    while any(pending.values()):
        k = min((k for k in keys if pending[k]), key=lambda k: have[k])
        jobs.append((k, pending[k].pop(0)))
        have[k] += 1
    return jobs


def verify_plans(plan: ExperimentPlan, repeats: int, *, seed: int = 0, noise_nm: float = 90.0,
                 stick_speed_m_per_s: float = STICK_SPEED, workers: int = 1,
                 progress: Callable[[str], None] | bool | None = None, record: str | Path | None = None,
                 jitter_load: float = JITTER_LOAD) -> dict:
    """Simulate and identify the plan and the reference ``repeats`` times each (seeded
    noise, repeat r uses seed + r for both plans); the measured spread of the estimates
    per parameter. Fits run in ``workers`` processes. ``progress``
    (:mod:`identify.progress`): None draws a bar of the fits with the time left on a
    terminal, False is silent, a callable gets each message.

    ``jitter_load``: each repeat draws every run's load within ± this fraction of its
    nominal value (the trace carries the drawn load), as real replicates differ; it
    redraws the step phases the slips lock to, which the predicted standard errors
    count as random. 0: every repeat simulates the nominal runs.

    ``record``: a JSON-lines file that gets one line per finished fit, as it finishes;
    fits already in it (same plan, same seed) are not run again, so a stopped
    verification resumes where it stopped.

    Returns (and stores as ``plan.monte_carlo``): ``plan_stderr`` and
    ``reference_stderr`` (standard deviation of the estimates), ``*_robust_stderr``
    (1.4826 × MAD: one fit stuck in a wrong solution does not set it), ``*_mean``,
    ``*_rms_error`` (against the nominal values the data were made with),
    ``*_measured_over_predicted`` (robust spread / predicted standard error),
    ``*_failed``, ``geometric_mean_ratio`` (reference / plan, of the RMS errors),
    ``*_coverage`` (share of the fits whose own 95 % interval holds the nominal value),
    ``*_estimates`` (per fit), ``repeats`` and ``jitter_load``.
    """
    from concurrent.futures import ProcessPoolExecutor

    say = reporter(progress) or (lambda msg: None)
    runs_of = {"plan_stderr": plan.plan, "reference_stderr": plan.reference_plan}
    context = _record_context(plan, noise_nm, stick_speed_m_per_s, jitter_load)
    done = _load_record(record, context)
    if done:
        say(f"verification: {len(done)} fit(s) taken from {record}")
    jobs = _job_order(tuple(runs_of), repeats, seed, done)
    rows = {k: v for k, v in done.items() if 0 <= k[1] - seed < repeats}
    fh = _open_record(record)
    ex = ProcessPoolExecutor(max_workers=max(int(workers), 1))
    try:
        futs = {ex.submit(_fit_plan, runs_of[key], plan.coating, plan.free, noise_nm, stick_speed_m_per_s,
                          seed + r, jitter_load): (key, r) for key, r in jobs}
        _collect_fits(futs, rows, seed, context, fh, Stage(say, "verification fits", len(jobs)), say)
    except KeyboardInterrupt:
        stop_pool(ex)
        kept = f"; the {len(rows)} finished fit(s) are in {record}, and a rerun with it resumes" if record else ""
        raise Interrupted(f"verification stopped after {len(rows)} of {len(runs_of) * repeats} fit(s){kept}",
                          dict(record=str(record) if record else None, fits=len(rows))) from None
    finally:
        ex.shutdown()  # (after stop_pool there is nothing left to wait for)
        if fh is not None:
            fh.close()
    out: dict = {}
    for key, predicted in (("plan_stderr", plan.predicted_stderr), ("reference_stderr", plan.reference_stderr)):
        out.update(_measured_spread(plan, rows, key, predicted))
    g_plan = geometric_mean_relative(out["plan_rms_error"], plan.nominal)
    g_ref = geometric_mean_relative(out["reference_rms_error"], plan.nominal)
    out["geometric_mean_ratio"] = g_ref / g_plan if g_plan and np.isfinite(g_plan) else float("nan")
    out["repeats"] = repeats
    out["seed"] = seed
    out["jitter_load"] = jitter_load
    plan.monte_carlo = out
    return out


def _open_record(record: str | Path | None):
    """The record opened for appending (None without one), a line cut by a stop ended first
    so that it cannot swallow the next record."""
    if record is None:
        return None
    cut = False
    if Path(record).exists() and Path(record).stat().st_size:
        with open(record, "rb") as raw:
            raw.seek(-1, 2)
            cut = raw.read(1) != b"\n"
    fh = open(record, "a", encoding="utf-8")
    if cut:
        fh.write("\n")
    return fh


def _collect_fits(futs: dict, rows: dict, seed: int, context: dict, fh, stage: Stage,
                  say: Callable[[str], None]) -> None:
    """Each fit as it finishes into ``rows`` and the record (one line each), its progress
    reported; a fit that raised becomes a row with its error."""
    from concurrent.futures import as_completed

    for f in as_completed(futs):
        key, r = futs[f]
        try:
            row = dict(key=key, seed=seed + r, context=context[key], **f.result())
        except Exception as err:  # a failed repeat is counted, not fatal (and retried on a rerun)
            row = dict(key=key, seed=seed + r, context=context[key], error=f"{type(err).__name__}: {err}")
            say(f"  {key.split('_')[0]} repeat {r + 1} failed: {err}")
        rows[(key, seed + r)] = row
        if fh is not None:
            fh.write(dumps(row, indent=None) + "\n")
            fh.flush()
        stage.advance(f"{key.split('_')[0]} repeat {r + 1}" + (" failed" if "error" in row else ""))


def _measured_spread(plan: ExperimentPlan, rows: dict, key: str, predicted: dict) -> dict:
    """One plan's measures over its finished fits (``key`` is ``plan_stderr`` or
    ``reference_stderr``): spreads, mean, RMS error, coverage, failures, estimates."""
    good = [row for (k, _), row in sorted(rows.items()) if k == key and "estimates" in row]
    ok = [row["estimates"] for row in good]
    pre = key.replace("_stderr", "")
    sd, robust, mean, rms, ratio, cover = {}, {}, {}, {}, {}, {}
    for n in plan.free:
        cis = [row["ci95"][n] for row in good if row.get("ci95")]
        cover[n] = (float(np.mean([ci is not None and ci[0] <= plan.nominal[n] <= ci[1] for ci in cis]))
                    if cis else float("nan"))
        v = np.array([e[n] for e in ok], float)
        sd[n], robust[n] = _spread(v)
        mean[n] = float(v.mean()) if v.size else float("nan")
        rms[n] = float(np.sqrt(np.mean((v - plan.nominal[n]) ** 2))) if v.size else float("nan")
        ratio[n] = robust[n] / predicted[n] if predicted[n] else float("nan")
    return {
        key: sd,
        f"{pre}_robust_stderr": robust,
        f"{pre}_mean": mean,
        f"{pre}_rms_error": rms,
        f"{pre}_measured_over_predicted": ratio,
        f"{pre}_coverage": cover,
        f"{pre}_coverage_fits": sum(1 for row in good if row.get("ci95")),
        f"{pre}_failed": sum(1 for (k, _), row in rows.items() if k == key and "error" in row),
        f"{pre}_estimates": ok,
    }
