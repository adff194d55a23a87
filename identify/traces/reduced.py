"""The paper's reduced analysis: σ·√12 per run, Eq. 8 rest time, Eq. 9 aging fits.

Per run (:func:`reduced_run`, MODEL.md "Reduced relations"): on a saw-tooth the
elongation samples are uniform over the slip length δ, so

    δ̄ = σ_e·√12,   e_peak = ē + δ̄/2,   μs = k·e_peak/Nb,   t_rest = δ̄/(fp·Δxp) (Eq. 8),

with ē and σ_e the mean and standard deviation of the elongation samples. Camera noise
adds σ̂² to σ_e², so the noise-corrected δ̄_c = √(12·(σ_e² − σ̂²)) is given as well; the
same numbers straight from the events (mean slip length, mean peak elongation, mean
rest) are the check. Two details of the discrete saw-tooth, both small: a stick of R
steps shows R elongation values Δxp apart, so σ_e² = (δ² − Δxp²)/12 (δ̄ is short by
Δxp²/(2δ), < 1.5 % for δ > 4 steps) and e_peak from σ·√12 is short of the elongation
after the triggering step by Δxp/2.

Across runs (:func:`reduced_fit`, the paper's Figs. 10–11): the static coefficient
against rest time, fitted with each aging law's ``static_curve`` (exponential Eq. 9,
logarithmic Dieterich–Ruina, logistic Carlson–Batista) by bounded least squares, and
compared by AIC and BIC; one law's fit is :func:`identify.traces.law_curves.fit_law_curve`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from identify.jsonio import jsonable
from identify.model.laws import get_law
from identify.traces.io import Trace
from identify.traces.law_curves import LawCurveFit as LawCurveFit
from identify.traces.law_curves import fit_law_curve as fit_law_curve

__all__ = [
    "SOURCES",
    "LawCurveFit",
    "ReducedFit",
    "ReducedRun",
    "fit_law_curve",
    "reduced_fit",
    "reduced_run",
]

SOURCES = ("events", "events_peak", "sqrt12", "sqrt12_raw")
"""Where the (t_rest, μs) points of :func:`reduced_fit` come from:

``events``
    Mean rest time of the detected slips and ``mu_s_events_mid`` = k·(ē_peak − Δxp/2)/Nb:
    the slip was held before its trigger step and not after it, so the static capacity
    lies between k·(e_peak − Δxp)/Nb and k·e_peak/Nb; the middle of that interval is
    unbiased, the top (``events_peak``) is high by k·Δxp/(2·Nb) on average (0.025 at
    k = 2.13 N/m, Nb = 2 µN).
``events_peak``
    Mean rest time and ``mu_s_events`` = k·ē_peak/Nb (the elongation just after the
    triggering step).
``sqrt12``
    σ·√12 with the noise correction (``*_corrected``).
``sqrt12_raw``
    σ·√12 as the paper computes it, noise included.
"""

def _f(x) -> float:
    return float(x) if x is not None else math.nan


# ----------------------------------------------------------------------------- per run
@dataclass
class ReducedRun:
    """Reduced analysis of one run (SI; see the module docstring for the relations).

    Attributes
    ----------
    name : str
    mean_elongation_m, std_elongation_m : float
        ē and σ_e of the elongation samples after the initial loading ramp, m (the
        window is ``frames_used``: from the first slip to the last one, i.e. whole
        saw-tooth cycles, when the run has at least 2 slips).
    slip_sqrt12_m : float
        δ̄ = σ_e·√12, m.
    slip_sqrt12_corrected_m : float
        δ̄_c = √(12·(σ_e² − σ̂²)), m (0 when σ_e ≤ σ̂).
    peak_sqrt12_m : float
        e_peak = ē + δ̄/2, m.
    mu_s_sqrt12 : float
        k·e_peak/Nb.
    rest_time_sqrt12_s : float
        δ̄/(fp·Δxp), s (Eq. 8).
    peak_sqrt12_corrected_m, mu_s_sqrt12_corrected, rest_time_sqrt12_corrected_s : float
        The same with δ̄_c.
    mean_slip_m, mean_peak_elongation_m, mean_rest_time_s : float
        From the events, over the slips after the first (the first follows the loading
        ramp from a fully aged contact); the one slip if there is only one; NaN without.
    mu_s_events : float
        k·mean_peak_elongation_m/Nb.
    mu_s_events_mid : float
        k·(mean_peak_elongation_m − Δxp/2)/Nb, the middle of the force interval of the
        triggering step (see :data:`SOURCES`).
    n_slips, frames_used : int
    noise_m : float
        σ̂ used for the correction, m.
    spring_constant, normal_load, step_frequency, step_size : float
        k (N/m), Nb (N), fp (Hz), Δxp (m).
    coating : str or None
    regime : str
        The events' regime (``stick-slip``, ``unresolved``, ``no-slip``).
    """

    name: str
    mean_elongation_m: float
    std_elongation_m: float
    slip_sqrt12_m: float
    slip_sqrt12_corrected_m: float
    peak_sqrt12_m: float
    mu_s_sqrt12: float
    rest_time_sqrt12_s: float
    peak_sqrt12_corrected_m: float
    mu_s_sqrt12_corrected: float
    rest_time_sqrt12_corrected_s: float
    mean_slip_m: float
    mean_peak_elongation_m: float
    mu_s_events: float
    mean_rest_time_s: float
    mu_s_events_mid: float
    n_slips: int
    frames_used: int
    noise_m: float
    spring_constant: float
    normal_load: float
    step_frequency: float
    step_size: float
    coating: str | None = None
    regime: str = ""

    @property
    def usable(self) -> bool:
        """Whether the run has a resolved saw-tooth (regime ``stick-slip``)."""
        return self.regime == "stick-slip"

    def point(self, source: str = "events") -> tuple[float, float]:
        """(t_rest in s, μs) of this run for the law fits (:data:`SOURCES`)."""
        if source == "events":
            return self.mean_rest_time_s, self.mu_s_events_mid
        if source == "events_peak":
            return self.mean_rest_time_s, self.mu_s_events
        if source == "sqrt12":
            return self.rest_time_sqrt12_corrected_s, self.mu_s_sqrt12_corrected
        if source == "sqrt12_raw":
            return self.rest_time_sqrt12_s, self.mu_s_sqrt12
        raise ValueError(f"source = {source!r}: choose one of {', '.join(SOURCES)}")

    def to_json(self) -> dict:
        return jsonable(
            dict(
                name=self.name,
                regime=self.regime,
                coating=self.coating,
                spring_constant_N_per_m=self.spring_constant,
                normal_load_N=self.normal_load,
                step_frequency_Hz=self.step_frequency,
                step_size_m=self.step_size,
                noise_m=self.noise_m,
                frames_used=self.frames_used,
                n_slips=self.n_slips,
                mean_elongation_m=self.mean_elongation_m,
                std_elongation_m=self.std_elongation_m,
                slip_sqrt12_m=self.slip_sqrt12_m,
                slip_sqrt12_corrected_m=self.slip_sqrt12_corrected_m,
                peak_sqrt12_m=self.peak_sqrt12_m,
                mu_s_sqrt12=self.mu_s_sqrt12,
                rest_time_sqrt12_s=self.rest_time_sqrt12_s,
                peak_sqrt12_corrected_m=self.peak_sqrt12_corrected_m,
                mu_s_sqrt12_corrected=self.mu_s_sqrt12_corrected,
                rest_time_sqrt12_corrected_s=self.rest_time_sqrt12_corrected_s,
                mean_slip_m=self.mean_slip_m,
                mean_peak_elongation_m=self.mean_peak_elongation_m,
                mu_s_events=self.mu_s_events,
                mu_s_events_mid=self.mu_s_events_mid,
                mean_rest_time_s=self.mean_rest_time_s,
            )
        )


    @classmethod
    def from_json(cls, d: dict) -> ReducedRun:
        """The run :meth:`to_json` describes (a null number is read back as NaN)."""
        kw = {"regime": "", "coating": None, **{_RUN_KEYS.get(k, k): v for k, v in d.items()}}
        out = {}
        for f in fields(cls):
            v = kw.get(f.name)
            if f.name in ("name", "coating", "regime"):
                out[f.name] = v
            elif f.name in ("n_slips", "frames_used"):
                out[f.name] = int(v)
            else:
                out[f.name] = _f(v)
        return cls(**out)


# JSON key -> ReducedRun field, where they differ
_RUN_KEYS = dict(spring_constant_N_per_m="spring_constant", normal_load_N="normal_load",
                 step_frequency_Hz="step_frequency", step_size_m="step_size")


def reduced_run(trace: Trace, events) -> ReducedRun:
    """Reduced analysis of one run (module docstring); :func:`identify.extract_events`
    makes it for every run it reads (``RunEvents.reduced``).

    Parameters
    ----------
    trace : Trace
        The run.
    events : RunEvents
        Its events (:func:`identify.extract_events` of ``trace``).

    Returns
    -------
    ReducedRun
        ē and σ_e exclude the initial loading ramp (frames before the first slip) and,
        with ≥ 2 slips, the incomplete cycle after the last slip.
    """
    k, Nb, fp, dx = trace.spring_constant, trace.normal_load, trace.step_frequency, trace.step_size
    e = trace.elongation
    pl, sl = events.plateaus, events.slips
    n_slips = len(sl["trigger_step"])
    if n_slips >= 2:
        window = slice(int(pl["last_frame"][0]) + 1, int(pl["last_frame"][-2]) + 1)
    elif n_slips == 1:
        window = slice(int(pl["last_frame"][0]) + 1, len(e))
    else:
        window = slice(0, len(e))
    w = e[window]
    sigma = float(events.noise_m)
    if w.size >= 2:
        mean = float(w.mean())
        std = float(w.std(ddof=1))
    else:
        mean = std = math.nan
    d = std * math.sqrt(12.0)
    var_c = std * std - sigma * sigma
    dc = math.sqrt(12.0 * var_c) if var_c > 0 else (0.0 if math.isfinite(var_c) else math.nan)
    peak = mean + d / 2
    peak_c = mean + dc / 2
    if n_slips:
        sel = slice(1, None) if n_slips >= 2 else slice(0, None)
        mean_slip = float(np.mean(sl["slip_length_m"][sel]))
        mean_peak = float(np.mean(sl["peak_elongation_m"][sel]))
        mean_rest = float(np.mean(sl["rest_time_s"][sel]))
    else:
        mean_slip = mean_peak = mean_rest = math.nan
    return ReducedRun(
        name=trace.name,
        mean_elongation_m=mean,
        std_elongation_m=std,
        slip_sqrt12_m=d,
        slip_sqrt12_corrected_m=dc,
        peak_sqrt12_m=peak,
        mu_s_sqrt12=k * peak / Nb,
        rest_time_sqrt12_s=d / (fp * dx),
        peak_sqrt12_corrected_m=peak_c,
        mu_s_sqrt12_corrected=k * peak_c / Nb,
        rest_time_sqrt12_corrected_s=dc / (fp * dx),
        mean_slip_m=mean_slip,
        mean_peak_elongation_m=mean_peak,
        mu_s_events=k * mean_peak / Nb,
        mean_rest_time_s=mean_rest,
        mu_s_events_mid=k * (mean_peak - dx / 2) / Nb,
        n_slips=n_slips,
        frames_used=int(w.size),
        noise_m=sigma,
        spring_constant=k,
        normal_load=Nb,
        step_frequency=fp,
        step_size=dx,
        coating=trace.coating,
        regime=getattr(events, "regime", ""),
    )


# ----------------------------------------------------------------------------- across runs
_DISPLAY = {"tau": ("ms", 1e3), "t_c": ("ms", 1e3)}


def _fmt_param(name: str, value: float, se: float) -> str:
    unit, f = _DISPLAY.get(name, ("", 1.0))
    v, s = value * f, se * f
    txt = f"{name} = {v:.4g}"
    txt += f" ± {s:.2g}" if math.isfinite(s) else " ± ?"
    return txt + (f" {unit}" if unit else "")


@dataclass
class ReducedFit:
    """The static friction coefficient against rest time across runs, fitted with each
    aging law (the paper's Figs. 10–11).

    Attributes
    ----------
    runs : list of ReducedRun
        All runs given.
    used : list of bool
        Which runs gave a data point (regime ``stick-slip`` and finite values).
    t_rest_s, mu_s : ndarray
        The data points (used runs).
    fits : dict
        Law name -> :class:`LawCurveFit`.
    best : str or None
        The converged fit with the smallest AIC (None when no fit converged).
    source : str
        :data:`SOURCES`.
    """

    runs: list
    used: list
    t_rest_s: np.ndarray
    mu_s: np.ndarray
    fits: dict
    best: str | None
    source: str

    def delta_aic(self) -> dict:
        aics = [f.aic for f in self.fits.values() if f.converged and math.isfinite(f.aic)]
        ref = min(aics) if aics else math.nan
        return {
            name: f.aic - ref if (f.converged and math.isfinite(f.aic)) else math.nan
            for name, f in self.fits.items()
        }

    def report(self) -> str:
        n_used = int(sum(self.used))
        lines = [
            f"Static friction vs rest time ({self.source}): {n_used} of {len(self.runs)} runs used",
        ]
        for r, u in zip(self.runs, self.used):
            t, m = r.point(self.source)
            lines.append(
                f"  {'*' if u else ' '} {r.name}: k = {r.spring_constant:g} N/m, Nb = "
                f"{r.normal_load * 1e6:.4g} µN, fp = {r.step_frequency:g} Hz, {r.regime}: "
                + (
                    f"t_rest = {t * 1e3:.4g} ms, μs = {m:.4f}"
                    if math.isfinite(t) and math.isfinite(m)
                    else "no point"
                )
            )
        lines.append(f"  {'law':<12} {'parameters':<62} {'R²':>7} {'AIC':>9} {'ΔAIC':>7}")
        dA = self.delta_aic()
        for name, f in self.fits.items():
            pars = ", ".join(
                _fmt_param(p, f.parameters[p], f.stderr.get(p, math.nan)) for p in f.parameters
            )
            mark = " <- best" if name == self.best else ""
            lines.append(
                f"  {name:<12} {pars:<62} {f.r2:7.4f} {f.aic:9.2f} "
                + (f"{dA[name]:7.2f}" if math.isfinite(dA[name]) else "      -")
                + mark
            )
            if f.message:
                lines.append(f"  {'':<12} ({f.message})")
        return "\n".join(lines)

    def to_json(self) -> dict:
        dA = self.delta_aic()
        return jsonable(
            dict(
                source=self.source,
                runs=[
                    dict(
                        name=r.name,
                        used=bool(u),
                        t_rest_s=r.point(self.source)[0],
                        mu_s=r.point(self.source)[1],
                    )
                    for r, u in zip(self.runs, self.used)
                ],
                fits={
                    name: {**f.to_json(), "delta_aic": dA[name]} for name, f in self.fits.items()
                },
                best=self.best,
            )
        )

    @classmethod
    def from_json(cls, d: dict, runs: Sequence[ReducedRun]) -> ReducedFit:
        """The fit :meth:`to_json` describes, over ``runs`` (the runs it lists, in its order:
        the JSON names them, :meth:`ReducedRun.from_json` reads them). The data points
        are the used runs' points, as :func:`reduced_fit` takes them."""
        runs = list(runs)
        listed = d.get("runs", [])
        if [r["name"] for r in listed] != [r.name for r in runs]:
            raise ValueError("ReducedFit.from_json: the runs given are not the runs the fit lists")
        used = [bool(r["used"]) for r in listed]
        t, mu = _sorted_points([r.point(d["source"]) for r, u in zip(runs, used) if u])
        fits = {name: _law_curve_from_json(f) for name, f in (d.get("fits") or {}).items()}
        return cls(runs=runs, used=used, t_rest_s=t, mu_s=mu, fits=fits, best=d.get("best"), source=d["source"])

    def covariance(self, law: str) -> tuple[list, np.ndarray]:
        """Covariance of a law fit's parameters (times in s) as its standard errors come
        from it: s²·(JᵀJ)⁻¹ at the data points, s² = RSS/(n − free), over the parameters
        not on a bound; returns (those parameters' names, the matrix). ([], 0×0) where it
        is not defined (an undetermined or failed fit, a singular JᵀJ)."""
        f = self.fits[law]
        names = [p for p in f.parameters if p not in f.at_bounds]
        empty = ([], np.zeros((0, 0)))
        t = np.asarray(self.t_rest_s, float)
        if not names or t.size < f.k + 1 or not all(math.isfinite(f.stderr.get(p, math.nan)) for p in names):
            return empty
        curve = get_law(f.law)
        order = list(curve.curve_parameters)
        theta = np.array([f.parameters[p] for p in order], float)
        J = np.empty((t.size, len(names)))
        for j, p in enumerate(names):  # central differences in the natural parameters
            i = order.index(p)
            h = 1e-6 * max(abs(theta[i]), 1e-9)
            up, dn = theta.copy(), theta.copy()
            up[i] += h
            dn[i] -= h
            J[:, j] = (curve.static_curve(t, up) - curve.static_curve(t, dn)) / (2 * h)
        try:
            cov = f.rss / (t.size - len(names)) * np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            return empty
        return (names, cov) if np.all(np.isfinite(cov)) else empty

    def plot(self, ax=None):
        """μs against rest time (log axis): data and the fitted laws (paper Fig. 10)."""
        from identify.plots.events import plot_reduced_fit

        return plot_reduced_fit(self, ax=ax)

    def plot_rates(self, ax=None):
        """dμs/dt_rest of the fitted laws against rest time (paper Fig. 11)."""
        from identify.plots.events import plot_reduced_rates

        return plot_reduced_rates(self, ax=ax)


def reduced_fit(
    runs: Sequence[ReducedRun],
    *,
    source: str = "events",
    laws: Sequence[str] = ("exponential", "logarithmic", "logistic"),
) -> ReducedFit:
    """Fit μs(t_rest) across runs with each law and rank the laws by AIC.

    Parameters
    ----------
    runs : sequence of ReducedRun
        Runs with regime ``stick-slip`` and finite points are used; the others are kept
        in the result, marked unused.
    source : str
        :data:`SOURCES`.
    laws : sequence of str
        Law names (:data:`identify.model.laws.LAWS`).

    Returns
    -------
    ReducedFit
        Fits with fewer points than parameters + 1 are flagged not converged
        (undetermined) rather than raising.
    """
    if source not in SOURCES:
        raise ValueError(f"source = {source!r}: choose one of {', '.join(SOURCES)}")
    runs = list(runs)
    used, pts = [], []
    for r in runs:
        t, m = r.point(source)
        ok = r.usable and math.isfinite(t) and math.isfinite(m) and t > 0
        used.append(bool(ok))
        if ok:
            pts.append((t, m))
    t, mu = _sorted_points(pts)
    fits = {get_law(name).name: fit_law_curve(name, t, mu) for name in laws}
    ok = {n: f for n, f in fits.items() if f.converged and math.isfinite(f.aic)}
    best = min(ok, key=lambda n: ok[n].aic) if ok else None
    return ReducedFit(
        runs=runs, used=used, t_rest_s=t, mu_s=mu, fits=fits, best=best, source=source
    )


def _sorted_points(pts: list) -> tuple[np.ndarray, np.ndarray]:
    """(t_rest, μs) arrays of the points ``pts``, by increasing rest time."""
    arr = np.array(pts, float).reshape(-1, 2)
    order = np.argsort(arr[:, 0], kind="stable")
    return arr[order, 0], arr[order, 1]


def _law_curve_from_json(d: dict) -> LawCurveFit:
    """The law fit ``LawCurveFit.to_json`` describes (null numbers read back as NaN)."""
    return LawCurveFit(
        law=d["law"],
        parameters={p: _f(v) for p, v in d["parameters"].items()},
        stderr={p: _f(v) for p, v in d["stderr"].items()},
        rss=_f(d["rss"]),
        n=int(d["n"]),
        k=int(d["k"]),
        aic=_f(d["aic"]),
        bic=_f(d["bic"]),
        r2=_f(d["r2"]),
        converged=bool(d["converged"]),
        message=d.get("message", ""),
        at_bounds=list(d.get("at_bounds", [])),
    )
