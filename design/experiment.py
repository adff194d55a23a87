"""Optimal experiment design: which (k, Nb, fp) runs make the friction parameters
well determined.

The information of a run is taken from the identification's own NLP
(:class:`identify.fitting.problem.Problem`), so the design optimises exactly what the fit will use:
the run is simulated at the nominal parameters without noise, its events extracted, the
NLP built with the camera noise model (``noise_nm``, 90 nm) as the frame standard
deviation, the per-run nuisances (plateau positions) solved with the friction parameters
held at their nominal values, and then

    I_run = Schur complement of the Gauss–Newton matrix JᵀJ on the friction parameters,
            the nuisances eliminated under the shooting constraints.

Nuisances belong to one run, so the information of a plan is the sum of its runs' (plus
a prior, for sequential design). Criteria, on the relative parameters θ/θ_nominal so that
A and E do not depend on units: D (max log det I), A (min trace I⁻¹), E (max λ_min I).
A plan of N runs (replicates allowed) is found by exhaustive enumeration when the number
of plans is small, else by a greedy build followed by Fedorov exchange until no swap
improves the criterion.
"""

from __future__ import annotations

import itertools
import json
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from identify.executors import stop_pool
from identify.fitting.stick_choice import STICK_SPEED_AUTO
from identify.interrupts import Interrupted
from identify.jsonio import dumps
from identify.progress import Stage, reporter

__all__ = ["Candidate", "CRITERIA", "ExperimentPlan", "run_information", "run_information_parts", "run_problem",
           "design_experiment", "paper_plan", "prior_from_fit", "verify_plans"]

CRITERIA = ("D", "A", "E")
DEFAULT_FREE = ("mu_max", "mu_min", "tau", "A")
JITTER_LOAD = 0.05  # verification: replicate loads within ±5 % (redraws the lock phases)
STICK_SPEED = STICK_SPEED_AUTO  # the stick option (README): as written, most of the grid creeps
PAPER_LOADS_UN = (0.98, 8.0, 18.1)
PAPER_FPS_HZ = (10.0, 100.0, 500.0, 1000.0)


@dataclass(frozen=True)
class Candidate:
    """One run a plan may contain."""

    spring_constant_N_per_m: float
    normal_load_uN: float
    step_frequency_Hz: float
    travel_um: float = 30.0

    def to_json(self) -> dict:
        return dict(spring_constant_N_per_m=self.spring_constant_N_per_m, normal_load_uN=self.normal_load_uN,
                    step_frequency_Hz=self.step_frequency_Hz, travel_um=self.travel_um)

    def label(self) -> str:
        return f"k={self.spring_constant_N_per_m:g} Nb={self.normal_load_uN:g}µN fp={self.step_frequency_Hz:g}Hz"


# ----------------------------------------------------------------------------- information
def _simulate(c: Candidate, coating: str, params: Mapping[str, float], stick_speed: float):
    from identify import SimulationOptions, simulate

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return simulate(coating, spring_constant_N_per_m=c.spring_constant_N_per_m,
                        normal_load_uN=c.normal_load_uN, step_frequency_Hz=c.step_frequency_Hz,
                        travel_um=c.travel_um, params=dict(params), stick_speed_m_per_s=stick_speed,
                        options=SimulationOptions(record=False))


def run_information(c: Candidate, coating: str = "FOTAS", *, params: Mapping[str, float] | None = None,
                    free: Sequence[str] = DEFAULT_FREE, noise_nm: float = 90.0,
                    stick_speed_m_per_s: float = STICK_SPEED) -> tuple[np.ndarray, dict]:
    """Fisher information of one run on ``free`` (natural units), and a summary: every
    frame and every trigger an independent observation.

    Zero information (with the reason in the summary) when the run shows neither
    resolvable slips nor steady creep at the nominal parameters.
    """
    I, _, summary = run_information_parts(c, coating, params=params, free=free, noise_nm=noise_nm,
                                          stick_speed_m_per_s=stick_speed_m_per_s, meat=False)
    return I, summary


def run_information_parts(c: Candidate, coating: str = "FOTAS", *, params: Mapping[str, float] | None = None,
                          free: Sequence[str] = DEFAULT_FREE, noise_nm: float = 90.0,
                          stick_speed_m_per_s: float = STICK_SPEED, meat: bool = True):
    """(B, M, summary) of one run on ``free`` (natural units): B its Fisher information
    (:func:`run_information`), M the covariance of its score under the error model the
    fit's robust covariance uses — a run's slips recur at nearly one phase of the step
    interval, so their trigger errors are largely one shared error (exchangeable, with
    the correlation the simulated positions show). Over a plan B and M add up and the
    estimator's covariance is B⁻¹MB⁻¹: what the fit will report, and (measured) what its
    estimates spread by, where B⁻¹ alone promised up to 1.8 times less."""
    prob, w, summary = run_problem(c, coating, params=params, free=free, noise_nm=noise_nm,
                                   stick_speed_m_per_s=stick_speed_m_per_s)
    n = len(free)
    if prob is None:
        return np.zeros((n, n)), (np.zeros((n, n)) if meat else None), summary
    B, M = _schur_information(prob, w, meat)
    D = prob.theta.jacobian_diag(w[: prob.n_theta])  # d natural / d scaled
    DD = np.outer(D, D)
    return B / DD, (M / DD if meat else None), summary


def run_problem(c: Candidate, coating: str = "FOTAS", *, params: Mapping[str, float] | None = None,
                free: Sequence[str] = DEFAULT_FREE, noise_nm: float = 90.0,
                stick_speed_m_per_s: float = STICK_SPEED):
    """The identification NLP of one noiselessly simulated run, its nuisances solved at
    the nominal parameters: (Problem, w, summary), or (None, None, summary) when the run
    carries no information."""
    from identify.fitting.driver import FitOptions, make_run_data
    from identify.fitting.problem import Problem
    from identify.model.laws import get_law
    from identify.model.params import parameter_set
    from identify.model.symbolic import Model
    from identify.traces.events import extract_events

    p_nom = parameter_set(coating, dict(params or {}))
    fixed = {"v_stick": stick_speed_m_per_s} if "v_stick" not in free else {}
    p_nom.update(fixed)
    sim = _simulate(c, coating, dict(params or {}), stick_speed_m_per_s)
    info = dict(regime=sim.regime, n_slips=int(len(sim.slips)))
    trace = sim.sample(noise_nm=0.0, name=c.label())
    try:
        ev = extract_events(trace, noise_m=noise_nm * 1e-9)
        rd = make_run_data(ev)
    except (ValueError, RuntimeError) as err:
        return None, None, dict(info, used=False, reason=f"event extraction failed: {err}")
    rd.sigma = noise_nm * 1e-9  # the design's noise model, not the noiseless trace's
    if rd.kind == "creep":
        if sim.regime == "stick-slip" and info["n_slips"] < 2:
            return None, None, dict(info, used=False,
                                    reason=f"only {info['n_slips']} slip(s) in {c.travel_um:g} µm of travel")
        if sim.regime != "creep":
            return None, None, dict(info, used=False, reason=f"{sim.regime}: slips too short to resolve "
                                                               "from steps at this noise")
        n_half = max(len(trace.time_s) // 2, 1)
        rd.steady_se = math.sqrt(rd.sigma**2 / n_half + (trace.step_size / math.sqrt(12)) ** 2)
    elif len(rd.trigger_steps) < 2:
        return None, None, dict(info, used=False, reason="fewer than two slips")
    model = Model(get_law("exponential"))
    opts = FitOptions(free=tuple(free), fixed=fixed, staged_start=False)
    prob = Problem([rd], model, dict(model.defaults(p_nom)), opts).build()
    w = prob.initial_w({k: p_nom[k] for k in free})
    if prob.E:
        prob.size_arcs(w)
        w = prob.solve(w, fixed={i: w[i] for i in range(prob.n_theta)})["w"]
    return prob, w, dict(info, used=True, reason=None, kind=rd.kind, n_events=int(prob.E))


def _schur_information(prob, w, meat: bool = True):
    """(information, score covariance or None) on the scaled parameters, the nuisances
    eliminated (the NLP's own; the frames at the design's stated noise)."""
    try:
        return prob.information_parts(w, meat=meat, frame_scale=1.0)
    except ValueError as err:
        raise ValueError(f"the run's {err} (nominal parameters)") from None


# ----------------------------------------------------------------------------- criteria
def _criterion(I_rel: np.ndarray, name: str) -> float:
    """Larger is better for every criterion (A is negated).

    D and A need a positive definite information: a plan that leaves a direction
    undetermined scores −inf. (Measured: a near-singular matrix with a rounding-size
    negative eigenvalue gave −trace(inverse) = +1.5e16, and the A criterion chose that
    plan, whose standard errors are NaN; slogdet's sign misses an even count of them.)"""
    if name not in CRITERIA:
        raise ValueError(f"criterion {name!r}: choose one of {', '.join(CRITERIA)}")
    lam = np.linalg.eigvalsh(0.5 * (I_rel + I_rel.T))
    if name == "E":
        return float(lam[0])
    if not (np.all(np.isfinite(lam)) and lam[0] > 1e-12 * max(lam[-1], 0.0)):
        return -np.inf
    if name == "D":
        return float(np.sum(np.log(lam)))
    return -float(np.sum(1.0 / lam))


def _effective(B: np.ndarray, M: np.ndarray) -> np.ndarray:
    """B·M⁻¹·B: the inverse of the sandwich covariance B⁻¹MB⁻¹ (what the criteria and the
    predicted standard errors are taken of). M's pseudo-inverse: a direction in which the
    score does not vary (a plan that does not inform it) carries no information, rather
    than a huge one from a near-singular solve."""
    if not np.all(np.isfinite(M)) or not np.any(M):
        return np.zeros_like(B)
    E = B @ np.linalg.pinv(M, rcond=1e-12, hermitian=True) @ B
    return 0.5 * (E + E.T)


def _stderr(I_nat: np.ndarray) -> np.ndarray:
    try:
        C = np.linalg.inv(I_nat)
        d = np.diag(C)
        return np.where(d > 0, np.sqrt(np.abs(d)), np.nan)
    except np.linalg.LinAlgError:
        return np.full(len(I_nat), np.nan)


# ----------------------------------------------------------------------------- plans
@dataclass
class ExperimentPlan:
    """A plan (runs, replicates allowed), its criterion and predicted standard errors,
    beside a reference plan of the same size."""

    coating: str
    criterion: str
    free: tuple
    nominal: dict
    plan: list
    predicted_stderr: dict
    criterion_value: float
    reference_plan: list
    reference_stderr: dict
    reference_criterion_value: float
    # B⁻¹ alone: every trigger an independent observation (what phase locking undoes)
    fisher_stderr: dict = field(default_factory=dict)
    reference_fisher_stderr: dict = field(default_factory=dict)
    # why the reference cannot be compared ('' when it can): runs without information, or
    # too few runs with it to fix every parameter
    reference_note: str = ""
    stick_speed_m_per_s: float = STICK_SPEED  # the stick option the runs were planned with
    candidates: list = field(default_factory=list)  # (Candidate, summary)
    enumeration: dict = field(default_factory=dict)
    prior_used: bool = False
    monte_carlo: dict | None = None

    @staticmethod
    def _gmean(se: Mapping[str, float], nominal: Mapping[str, float]) -> float:
        rel = [se[n] / abs(nominal[n]) for n in se]
        if not (all(np.isfinite(rel)) and all(r > 0 for r in rel)):
            return float("nan")
        return float(np.exp(np.mean(np.log(rel))))

    def report(self) -> str:
        option = (f"stick option v_stick = {self.stick_speed_m_per_s:g} m/s" if self.stick_speed_m_per_s
                  else "equations as written")
        lines = [f"Experiment plan: {self.coating}, {len(self.plan)} runs, {self.criterion}-optimal ({option})"
                 + (" (with prior information)" if self.prior_used else ""),
                 f"  search: {self.enumeration.get('method')}, {self.enumeration.get('plans_evaluated')} plans "
                 f"evaluated over {len(self.candidates)} candidates"]
        lines.append("  plan:")
        for c in self.plan:
            lines.append(f"    {c.label()}, travel {c.travel_um:g} µm")
        lines.append("  reference (the paper's conditions, same run count):")
        for c in self.reference_plan:
            lines.append(f"    {c.label()}, travel {c.travel_um:g} µm")
        lines.append("  predicted standard errors (a run's slips sharing their phase error; in brackets the")
        lines.append("  Fisher information alone, every trigger independent):")
        lines.append(f"  {'parameter':10} {'plan stderr':>12} {'reference':>12} {'ratio':>7}")
        for n in self.free:
            a, b = self.predicted_stderr[n], self.reference_stderr[n]
            fa, fb = self.fisher_stderr.get(n, float("nan")), self.reference_fisher_stderr.get(n, float("nan"))
            lines.append(f"  {n:10} {a:12.4g} {b:12.4g} {b / a if a else float('nan'):7.2f}"
                         f"   ({fa:.3g}, {fb:.3g})")
        gp = self._gmean(self.predicted_stderr, self.nominal)
        gr = self._gmean(self.reference_stderr, self.nominal)
        if self.reference_note:
            lines.append(f"  geometric-mean relative stderr: plan {gp:.4g}; the reference (nan above) cannot be "
                         f"compared: {self.reference_note}")
        else:
            lines.append(f"  geometric-mean relative stderr: plan {gp:.4g}, reference {gr:.4g} "
                         f"(reference / plan = {gr / gp:.2f})")
        if self.monte_carlo:
            mc = self.monte_carlo
            jit = mc.get("jitter_load", 0.0)
            lines.append(f"  Monte Carlo ({mc['repeats']} seeded repeats each"
                         + (f", loads within ±{100 * jit:g} %" if jit else "")
                         + f"; failed fits: plan {mc['plan_failed']}, reference {mc['reference_failed']}), "
                         "measured spread (sd / robust 1.4826·MAD) against the predicted stderr:")
            for n in self.free:
                lines.append(
                    f"    {n:10} plan {mc['plan_stderr'][n]:.3g} / {mc['plan_robust_stderr'][n]:.3g} "
                    f"(predicted {self.predicted_stderr[n]:.3g}, x{mc['plan_measured_over_predicted'][n]:.2f}); "
                    f"reference {mc['reference_stderr'][n]:.3g} / {mc['reference_robust_stderr'][n]:.3g} "
                    f"(predicted {self.reference_stderr[n]:.3g}, x{mc['reference_measured_over_predicted'][n]:.2f})")
            if "plan_coverage" in mc:
                cov = lambda c: ", ".join(f"{n} {100 * c[n]:.0f} %" for n in self.free)  # noqa: E731
                lines.append(f"  the fits' own 95 % intervals hold the truth: plan {cov(mc['plan_coverage'])} "
                             f"({mc['plan_coverage_fits']} fits); reference {cov(mc['reference_coverage'])} "
                             f"({mc['reference_coverage_fits']} fits)")
            lines.append(f"  measured geometric-mean RMS error, reference / plan = {mc['geometric_mean_ratio']:.2f}")
        unused = [(c, s) for c, s in self.candidates if not s.get("used")]
        if unused:
            lines.append("  candidates without information:")
            lines += [f"    {c.label()}: {s.get('reason')}" for c, s in unused]
        return "\n".join(lines)

    def to_json(self) -> dict:
        return dict(
            coating=self.coating, criterion=self.criterion, free=list(self.free), nominal=self.nominal,
            stick_speed_m_per_s=self.stick_speed_m_per_s,
            plan=[c.to_json() for c in self.plan], predicted_stderr=self.predicted_stderr,
            fisher_stderr=self.fisher_stderr, criterion_value=self.criterion_value,
            reference_plan=dict(plan=[c.to_json() for c in self.reference_plan],
                                predicted_stderr=self.reference_stderr,
                                fisher_stderr=self.reference_fisher_stderr,
                                criterion_value=self.reference_criterion_value,
                                note=self.reference_note or None),
            enumeration=self.enumeration, prior_used=self.prior_used,
            candidates=[dict(c.to_json(), **{k: v for k, v in s.items() if k != "information"})
                        for c, s in self.candidates],
            **({"monte_carlo": self.monte_carlo} if self.monte_carlo else {}),
        )

    def plot(self, ax=None):
        """Predicted relative standard errors of the plan and the reference, per parameter.

        Markers on a log axis (no bars: a log axis has no zero to start a bar from); after
        a verification, the Monte Carlo spreads beside them as open markers with their
        95 % interval (χ² on the number of fits). A standard error that cannot be
        determined is marked as such at the bottom. Legend (titled with the coating and run
        count) above the axes.
        """
        import re
        import textwrap

        from identify.model.params import SPECS
        from identify.plots.base import pyplot

        plt = pyplot()
        if ax is None:
            _, ax = plt.subplots(figsize=(6.5, 3.8), constrained_layout=True)
        x = np.arange(len(self.free))

        def rel(se) -> np.ndarray:
            return np.array([se.get(n, np.nan) / abs(self.nominal[n]) for n in self.free], float)

        def name(n: str) -> str:  # "μmax\nsaturated static\nfriction coefficient"
            spec = SPECS.get(n)
            if spec is None or not spec.description:
                return n
            text = re.sub(r"\s*\(Eq\.[^)]*\)\s*$", "", spec.description).split(": ", 1)[-1]
            words, _, symbol = text.rpartition(" ")
            return symbol + ("\n" + textwrap.fill(words, 13) if words else "")

        mc = self.monte_carlo or {}
        series = [("plan", f"{self.criterion}-optimal plan", self.predicted_stderr, "C0", "o"),
                  ("reference", "paper's conditions", self.reference_stderr, "C1", "s")]
        offsets = (-0.27, -0.09, 0.09, 0.27) if mc else (-0.12, 0.12)
        shown: list[np.ndarray] = []
        missing = []
        for k, (key, label, se, colour, marker) in enumerate(series):
            dx = offsets[2 * k] if mc else offsets[k]
            y = rel(se)
            ax.plot(x + dx, y, ls="", marker=marker, ms=7, color=colour, label=f"{label}: predicted")
            shown.append(y)
            missing += [(xi + dx, colour) for xi, yi in zip(x, y) if not (np.isfinite(yi) and yi > 0)]
            if mc and f"{key}_stderr" in mc:
                from scipy.stats import chi2

                ym = rel(mc[f"{key}_stderr"])
                n_fits = len(mc.get(f"{key}_estimates", ())) or int(mc.get("repeats", 0))
                lo = hi = np.full_like(ym, np.nan)
                if n_fits >= 2:
                    lo = ym * np.sqrt((n_fits - 1) / chi2.ppf(0.975, n_fits - 1))
                    hi = ym * np.sqrt((n_fits - 1) / chi2.ppf(0.025, n_fits - 1))
                ok = np.isfinite(ym) & (ym > 0)
                ax.errorbar(x[ok] + offsets[2 * k + 1], ym[ok],
                            yerr=np.abs(np.vstack([ym - lo, hi - ym])[:, ok]), ls="", marker=marker,
                            ms=7, mfc="white", color=colour, capsize=3, lw=1,
                            label=f"{label}: measured, {n_fits} fits (95 % interval)")
                shown += [lo[ok], hi[ok], ym[ok]]
        ax.set_yscale("log")
        vals = np.concatenate(shown) if shown else np.array([])
        vals = vals[np.isfinite(vals) & (vals > 0)]
        if vals.size:
            ax.set_ylim(vals.min() / 3, vals.max() * 3)
        for xm, colour in missing:
            ax.text(xm, 0.02, "not determined", transform=ax.get_xaxis_transform(), rotation=90,
                    ha="center", va="bottom", fontsize=8, color=colour)
        ax.set_xticks(x, [name(n) for n in self.free], fontsize=8)
        ax.set_xlim(-0.6, len(self.free) - 0.4)
        ax.grid(axis="y", which="major", color="0.9", lw=0.8)
        ax.set_axisbelow(True)
        ax.set_ylabel("relative standard error\n(standard error / nominal value)")
        # above the axes, so that it covers no marker whatever the values
        handles, labels = ax.get_legend_handles_labels()
        order = sorted(range(len(labels)), key=lambda i: "measured" in labels[i])
        ax.legend([handles[i] for i in order], [labels[i] for i in order], fontsize=8,
                  loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=2, frameon=False,
                  title=f"{self.coating}, {len(self.plan)} runs per plan", title_fontsize=10)
        return ax


def _reference_note(ref, infos, se_ref, free) -> str:
    """Why the reference plan's standard errors are undefined ('' when they are not)."""
    missing = [n for n in free if not np.isfinite(se_ref.get(n, np.nan))]
    if not missing:
        return ""
    unused = [f"{c.label()}: {infos[c][2].get('reason')}" for c in ref if not infos[c][2].get("used")]
    used = len(ref) - len(unused)
    why = (f"{used} of its {len(ref)} run(s) carry information, too little to fix {', '.join(missing)}"
           if used else f"none of its {len(ref)} run(s) carries information")
    return why + (" (" + "; ".join(unused) + ")" if unused else "") + \
        "; give more runs (--runs) or a longer travel (--travel-um)"


def paper_plan(n_runs: int, travel_um: float = 30.0) -> list:
    """The paper's conditions (k = 2.13 N/m, Nb ∈ {0.98, 8, 18.1} µN, fp ∈ {10, 100, 500,
    1000} Hz: 12 runs) cut or repeated to ``n_runs``, spread evenly over the 12."""
    grid = [Candidate(2.13, nb, fp, travel_um) for nb in PAPER_LOADS_UN for fp in PAPER_FPS_HZ]
    idx = np.floor(np.arange(n_runs) * len(grid) / n_runs).astype(int) if n_runs <= len(grid) \
        else np.arange(n_runs) % len(grid)
    return [grid[i] for i in idx]


def default_candidates(springs: Sequence[float], travel_um: float = 30.0,
                       loads_uN: Sequence[float] | None = None,
                       fps_Hz: Sequence[float] = (10.0, 30.0, 100.0, 300.0, 1000.0)) -> list:
    """(k, Nb, fp) grid inside Table I for each spring, camera at ≤ 5000 Hz."""
    from .constraints import allowed_load_range

    out = []
    for k in springs:
        lo, hi = (float(np.asarray(v).ravel()[0]) * 1e6 for v in allowed_load_range(k))
        loads = loads_uN if loads_uN is not None else np.geomspace(lo, min(hi, 60.0), 4)
        for nb in loads:
            if lo * (1 - 1e-9) <= nb <= hi * (1 + 1e-9):
                out += [Candidate(float(k), float(np.round(nb, 3)), float(fp), travel_um)
                        for fp in fps_Hz if fp <= 5000]
    return out


def design_experiment(n_runs: int, coating: str = "FOTAS", *, springs: Sequence[float] = (2.13, 20.3),
                      candidates: Sequence[Candidate] | None = None, criterion: str = "D",
                      free: Sequence[str] = DEFAULT_FREE, prior_information: np.ndarray | None = None,
                      noise_nm: float = 90.0, stick_speed_m_per_s: float = STICK_SPEED, travel_um: float = 30.0,
                      max_enumerate: int = 20000, reference: Sequence[Candidate] | None = None,
                      progress: Callable[[str], None] | bool | None = None) -> ExperimentPlan:
    """Choose ``n_runs`` runs from the candidate grid that optimise ``criterion``.

    ``progress`` (:mod:`identify.progress`): None draws a bar of the candidates'
    simulations with the time left on a terminal, False is silent, a callable gets each
    message."""
    from identify.model.params import parameter_set

    if criterion not in CRITERIA:
        raise ValueError(f"criterion {criterion!r}: choose one of {', '.join(CRITERIA)}")
    if int(n_runs) < 1:
        raise ValueError(f"runs = {n_runs!r}: must be a positive integer")
    free = tuple(free)
    nominal = {n: float(parameter_set(coating)[n]) for n in free}
    scale = np.array([abs(nominal[n]) for n in free])
    say = reporter(progress) or (lambda msg: None)
    cands = list(candidates) if candidates is not None else default_candidates(springs, travel_um)
    ref = list(reference) if reference is not None else paper_plan(n_runs, travel_um)
    infos: dict = {}

    def info_of(c: Candidate):
        """(B, M) of the run: its information and its score covariance."""
        if c not in infos:
            try:
                B, M, s = run_information_parts(c, coating, free=free, noise_nm=noise_nm,
                                                stick_speed_m_per_s=stick_speed_m_per_s)
            except Exception as err:  # one candidate that fails to simulate is dropped, not fatal
                B = M = np.zeros((len(free),) * 2)
                s = dict(used=False, reason=f"{type(err).__name__}: {err}")
            infos[c] = (B, M, s)
        return infos[c][:2]

    stage = Stage(say, "information of the candidates", len(cands))
    for c in cands:
        info_of(c)
        stage.advance(c.label())
    for c in ref:
        info_of(c)
    I0 = np.zeros((len(free),) * 2) if prior_information is None else np.asarray(prior_information, float)
    rel = lambda I: I * np.outer(scale, scale)  # noqa: E731 - information on θ/θ_nominal
    usable = [c for c in cands if infos[c][2].get("used")]
    if not usable:
        raise ValueError("no candidate run carries information (all creep-free of slips or failed)")
    mats = [info_of(c) for c in usable]

    def effective(idx, extra=0.0):
        # a prior (a fit's covariance inverted) counts as efficient information: B = M
        B = I0 + extra + sum(mats[i][0] for i in idx)
        M = I0 + extra + sum(mats[i][1] for i in idx)
        return _effective(B, M)

    value = lambda idx: _criterion(rel(effective(idx)), criterion)  # noqa: E731
    n_plans = math.comb(len(usable) + n_runs - 1, n_runs)
    evaluated = 0
    if n_plans <= max_enumerate:
        best, best_v = None, -np.inf
        for idx in itertools.combinations_with_replacement(range(len(usable)), n_runs):
            v = value(idx)
            evaluated += 1
            if v > best_v:
                best, best_v = list(idx), v
        method = "exhaustive enumeration"
    else:
        # greedy build: the run that adds most, with a tiny ridge so the first picks compare
        ridge = 1e-9 * np.eye(len(free))
        best = []
        for _ in range(n_runs):
            gains = [_criterion(rel(effective(best + [j], ridge)), criterion) for j in range(len(usable))]
            evaluated += len(gains)
            best.append(int(np.argmax(gains)))
        best_v = value(best)
        method = "greedy + Fedorov exchange"
        improved = True
        while improved:
            improved = False
            for pos in range(n_runs):
                for j in range(len(usable)):
                    trial = best.copy()
                    trial[pos] = j
                    v = value(trial)
                    evaluated += 1
                    if v > best_v + 1e-12:
                        best, best_v, improved = trial, v, True
    plan = [usable[i] for i in sorted(best)]
    B_ref = I0 + sum(info_of(c)[0] for c in ref)
    I_ref = _effective(B_ref, I0 + sum(info_of(c)[1] for c in ref))
    B_plan = I0 + sum(mats[i][0] for i in best)
    se = dict(zip(free, _stderr(effective(best)).tolist()))
    se_ref = dict(zip(free, _stderr(I_ref).tolist()))
    return ExperimentPlan(
        reference_note=_reference_note(ref, infos, se_ref, free), stick_speed_m_per_s=stick_speed_m_per_s,
        coating=coating, criterion=criterion, free=free, nominal=nominal, plan=plan, predicted_stderr=se,
        criterion_value=float(best_v), reference_plan=ref, reference_stderr=se_ref,
        reference_criterion_value=float(_criterion(rel(I_ref), criterion)),
        fisher_stderr=dict(zip(free, _stderr(B_plan).tolist())),
        reference_fisher_stderr=dict(zip(free, _stderr(B_ref).tolist())),
        candidates=[(c, dict(infos[c][2])) for c in cands],
        enumeration=dict(method=method, plans_evaluated=evaluated, plans_possible=n_plans,
                         best_value_enumerated=float(best_v) if method.startswith("exhaustive") else None),
        prior_used=prior_information is not None,
    )


# ----------------------------------------------------------------------------- prior
def prior_from_fit(path: str | Path, coating: str, free: Sequence[str] = DEFAULT_FREE) -> np.ndarray:
    """Information already in hand, from a fit's JSON (``python -m identify fit --json``):
    the inverse of its covariance (standard errors and correlation) on ``free``."""
    p = Path(path)
    try:
        js = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"--prior {p}: not a readable fit JSON ({err})") from None
    if str(js.get("coating", "")).upper() != coating.upper():
        raise ValueError(f"--prior {p}: a fit of coating {js.get('coating')!r}, not {coating}; "
                         "information from another coating does not carry over")
    pars = js.get("parameters", {})
    missing = [n for n in free if n not in pars or not pars[n].get("free") or pars[n].get("stderr") is None]
    if missing:
        raise ValueError(f"--prior {p}: no free estimate with a standard error for {', '.join(missing)}")
    se = np.array([pars[n]["stderr"] for n in free], float)
    corr = js.get("correlation", {})
    R = np.eye(len(free))
    for i, a in enumerate(free):
        for j, b in enumerate(free):
            if i != j:
                v = (corr.get(a, {}) or {}).get(b) if isinstance(corr.get(a), dict) else None
                R[i, j] = 0.0 if v is None else float(v)
    return np.linalg.inv(np.outer(se, se) * R)


# ----------------------------------------------------------------------------- verification
def _fit_options(free, stick):
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
        sim = _simulate(c, coating, {}, stick)
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
    from concurrent.futures import ProcessPoolExecutor, as_completed

    say = reporter(progress) or (lambda msg: None)
    runs_of = {"plan_stderr": plan.plan, "reference_stderr": plan.reference_plan}
    context = _record_context(plan, noise_nm, stick_speed_m_per_s, jitter_load)
    done = _load_record(record, context)
    if done:
        say(f"verification: {len(done)} fit(s) taken from {record}")
    jobs = _job_order(tuple(runs_of), repeats, seed, done)
    rows = {k: v for k, v in done.items() if 0 <= k[1] - seed < repeats}
    fh = None
    if record is not None:
        cut = False
        if Path(record).exists() and Path(record).stat().st_size:
            with open(record, "rb") as raw:  # a line cut by a stop must not swallow the next record
                raw.seek(-1, 2)
                cut = raw.read(1) != b"\n"
        fh = open(record, "a", encoding="utf-8")
        if cut:
            fh.write("\n")
    ex = ProcessPoolExecutor(max_workers=max(int(workers), 1))
    try:
        futs = {ex.submit(_fit_plan, runs_of[key], plan.coating, plan.free, noise_nm, stick_speed_m_per_s,
                          seed + r, jitter_load): (key, r) for key, r in jobs}
        stage = Stage(say, "verification fits", len(jobs))
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
        out[key] = sd
        out[f"{pre}_robust_stderr"] = robust
        out[f"{pre}_mean"] = mean
        out[f"{pre}_rms_error"] = rms
        out[f"{pre}_measured_over_predicted"] = ratio
        out[f"{pre}_coverage"] = cover
        out[f"{pre}_coverage_fits"] = sum(1 for row in good if row.get("ci95"))
        out[f"{pre}_failed"] = sum(1 for (k, _), row in rows.items() if k == key and "error" in row)
        out[f"{pre}_estimates"] = ok
    g_plan = plan._gmean(out["plan_rms_error"], plan.nominal)
    g_ref = plan._gmean(out["reference_rms_error"], plan.nominal)
    out["geometric_mean_ratio"] = g_ref / g_plan if g_plan and np.isfinite(g_plan) else float("nan")
    out["repeats"] = repeats
    out["seed"] = seed
    out["jitter_load"] = jitter_load
    plan.monte_carlo = out
    return out
