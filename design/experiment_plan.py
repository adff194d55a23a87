"""An experiment plan as found by :func:`design.experiment.design_experiment`: its runs,
criterion and predicted standard errors beside the reference plan's, and, after
:func:`design.verification.verify_plans`, the Monte Carlo spreads; with its report, JSON
and plot."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from identify.jsonio import SavedResult

from .candidates import Candidate
from .information import STICK_SPEED

__all__ = ["ExperimentPlan", "geometric_mean_relative"]


def geometric_mean_relative(se: Mapping[str, float], nominal: Mapping[str, float]) -> float:
    """Geometric mean of the standard errors (or errors) relative to the nominal values: one
    number to compare two plans by; NaN when one is undetermined or zero."""
    rel = [se[n] / abs(nominal[n]) for n in se]
    if not (all(np.isfinite(rel)) and all(r > 0 for r in rel)):
        return float("nan")
    return float(np.exp(np.mean(np.log(rel))))


def _finite_or_nan(x):
    """``x`` with every None (a non-finite number in strict JSON) read back as NaN,
    through dicts and lists."""
    if x is None:
        return float("nan")
    if isinstance(x, dict):
        return {k: _finite_or_nan(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_finite_or_nan(v) for v in x]
    return x


def _candidate(d: Mapping) -> Candidate:
    return Candidate(d["spring_constant_N_per_m"], d["normal_load_uN"], d["step_frequency_Hz"], d["travel_um"])


_CANDIDATE_KEYS = ("spring_constant_N_per_m", "normal_load_uN", "step_frequency_Hz", "travel_um")


@dataclass
class ExperimentPlan(SavedResult):
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
        gp = geometric_mean_relative(self.predicted_stderr, self.nominal)
        gr = geometric_mean_relative(self.reference_stderr, self.nominal)
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

    @classmethod
    def from_dict(cls, d: dict) -> ExperimentPlan:
        """The plan back from :meth:`to_json` (or :meth:`to_dict`, a saved file). The
        candidates' information matrices are not in the JSON: their summaries are."""
        ref = d["reference_plan"]
        mc = d.get("monte_carlo")
        return cls(
            coating=d["coating"], criterion=d["criterion"], free=tuple(d["free"]), nominal=dict(d["nominal"]),
            plan=[_candidate(c) for c in d["plan"]],
            predicted_stderr=_finite_or_nan(dict(d["predicted_stderr"])),
            criterion_value=_finite_or_nan(d["criterion_value"]),
            reference_plan=[_candidate(c) for c in ref["plan"]],
            reference_stderr=_finite_or_nan(dict(ref["predicted_stderr"])),
            reference_criterion_value=_finite_or_nan(ref["criterion_value"]),
            fisher_stderr=_finite_or_nan(dict(d.get("fisher_stderr") or {})),
            reference_fisher_stderr=_finite_or_nan(dict(ref.get("fisher_stderr") or {})),
            reference_note=ref.get("note") or "",
            stick_speed_m_per_s=float(d.get("stick_speed_m_per_s", STICK_SPEED)),
            candidates=[(_candidate(c), {k: v for k, v in c.items() if k not in _CANDIDATE_KEYS})
                        for c in d.get("candidates") or ()],
            enumeration=dict(d.get("enumeration") or {}),
            prior_used=bool(d.get("prior_used", False)),
            monte_carlo=_finite_or_nan(mc) if mc else None,
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
