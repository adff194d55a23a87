"""Where the fitted model and the data part: features tested in units of their own noise.

Every test turns its statistic into a p-value under "the model is adequate and the
noise is what the data say it is", and reports it as ``misfit_sigma``: the two-sided
normal quantile of that p-value (how many σ of a Gaussian the misfit is worth), so that
tests of different kinds rank on one scale.

Tests (features as in :mod:`identify.diagnosis.features`):

``post_slip_level``          χ² of the plateau levels (df: plateaus − one position per run)
``post_slip_whiteness``      lag-1 autocorrelation of the plateau residuals within runs
                             (an accumulating slip-length error makes the levels wander)
``slip_length``              per run, the mean slip-length misfit (telescoped, exact noise):
                             χ² over runs
``slip_length_vs_conditions``  weighted regression of those means on ln Nb, ln k, ln fp (F)
``static_friction``          per run, the mean trigger residual: χ² over runs (conservative
                             under phase-locked slips: a run's slips share one phase error)
``static_friction_vs_rest``  trend of the runs' mean trigger residuals against their mean
                             ln(rest time) (between runs; variance as above)
``stick_slope``              χ² of the staircase slopes
``time``                     trend of the plateau residuals against time within runs
``position``                 a ripple of the static-friction residuals against block
                             position common to every run (periodogram over wavelengths,
                             per-run means removed; p from the largest peak, Bonferroni
                             over the independent wavelengths)
``creep_level``              χ² of the creep runs' steady levels
``regime``                   the runs left out for their regime, simulated under the model:
                             its saw-tooth against theirs (:mod:`identify.fitting.regime_check`;
                             added by the diagnosis, :func:`with_regime`)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from scipy import stats

from identify.diagnosis.features import feature_values
from identify.model.symbolic import LENGTH_UNIT

__all__ = ["Misfit", "where", "misfit_sigma", "position_ripple", "with_regime"]

MAX_SIGMA = 40.0


@dataclass
class Misfit:
    """One feature's misfit."""

    feature: str
    misfit_sigma: float
    p_value: float
    statistic: float
    detail: str
    extra: dict = field(default_factory=dict)
    # the largest misfit a feature is given: a p-value below double precision's reach says only "more"
    cap_sigma: ClassVar[float] = MAX_SIGMA

    @classmethod
    def from_json(cls, d: dict) -> Misfit:
        """A misfit from :meth:`to_json` (its array-valued extras are not in the JSON)."""
        known = ("feature", "misfit_sigma", "p_value", "statistic", "detail")
        nan = float("nan")
        return cls(**{k: (nan if d.get(k) is None and k in ("misfit_sigma", "p_value", "statistic") else d.get(k))
                      for k in known}, extra={k: v for k, v in d.items() if k not in known})

    def to_json(self) -> dict:
        return dict(feature=self.feature, misfit_sigma=self.misfit_sigma, p_value=self.p_value,
                    statistic=self.statistic, detail=self.detail, **{k: v for k, v in self.extra.items()
                                                                       if not isinstance(v, np.ndarray)})


def misfit_sigma(p: float) -> float:
    """Two-sided normal quantile of a p-value, capped at 40 σ."""
    if not np.isfinite(p):
        return float("nan")
    if p <= 0:
        return MAX_SIGMA
    return float(min(stats.norm.isf(min(p, 1.0) / 2), MAX_SIGMA))


def _chi2(z, df, name, detail):
    z = np.asarray(z, float)
    q = float(np.sum(z**2))
    df = max(int(df), 1)
    p = float(stats.chi2.sf(q, df))
    return Misfit(name, misfit_sigma(p), p, q, f"χ²/df = {q / df:.2f} (df {df}); {detail}",
                  extra=dict(rms_sigma=float(np.sqrt(np.mean(z**2))) if z.size else float("nan")))


def _cluster_trend(y, x, cluster):
    """Slope of y on x with per-cluster means removed; t from a cluster-robust variance."""
    y = np.asarray(y, float)
    x = np.asarray(x, float)
    yc, xc = y.copy(), x.copy()
    for c in np.unique(cluster):
        m = cluster == c
        yc[m] -= y[m].mean()
        xc[m] -= x[m].mean()
    sxx = float(xc @ xc)
    if sxx <= 0 or len(np.unique(cluster)) < 2:
        return 0.0, float("nan"), 1.0
    b = float(xc @ yc) / sxx
    e = yc - b * xc
    meat = sum(float(xc[cluster == c] @ e[cluster == c]) ** 2 for c in np.unique(cluster))
    G = len(np.unique(cluster))
    se = math.sqrt(meat * G / max(G - 1, 1)) / sxx
    t = b / se if se > 0 else float("inf")
    p = float(2 * stats.t.sf(abs(t), max(G - 1, 1)))
    return b, t, p


def position_ripple(x_m, y, w, run, wavelengths_m):
    """Weighted least-squares ripple a·sin(2πx/λ) + b·cos(2πx/λ) common to all runs (per-run
    means removed) at each λ: (Δχ², amplitude, phase) arrays."""
    x_m, y, w, run = (np.asarray(a) for a in (x_m, y, w, run))
    ok = np.isfinite(x_m) & np.isfinite(y) & np.isfinite(w)  # (NaN rows: a model not evaluable there)
    x_m, y, w, run = x_m[ok].astype(float), y[ok].astype(float), w[ok].astype(float), run[ok]
    if not len(y):
        nan = np.full(len(wavelengths_m), np.nan)
        return nan, nan, nan
    runs = np.unique(run)
    D = np.stack([(run == r).astype(float) for r in runs], axis=1)
    sw = np.sqrt(w)
    # project out the per-run means once (weighted)
    Dw = D * sw[:, None]
    Q, _ = np.linalg.qr(Dw)
    yw = y * sw
    y_res = yw - Q @ (Q.T @ yw)
    out = np.zeros((len(wavelengths_m), 3))
    for i, lam in enumerate(wavelengths_m):
        ph = 2 * np.pi * x_m / lam
        X = np.stack([np.sin(ph), np.cos(ph)], axis=1) * sw[:, None]
        X = X - Q @ (Q.T @ X)
        coef, *_ = np.linalg.lstsq(X, y_res, rcond=None)
        fitted = X @ coef
        out[i, 0] = float(fitted @ fitted)
        out[i, 1] = float(np.hypot(*coef))
        out[i, 2] = float(np.arctan2(coef[1], coef[0]))
    return out[:, 0], out[:, 1], out[:, 2]


RIPPLE_PEAK_SHARE = 1 / 3
RIPPLE_MAX_PEAKS = 8
"""The periodogram's local maxima kept as starts of the topography candidate: those with at
least :data:`RIPPLE_PEAK_SHARE` of the highest one's Δχ², at most :data:`RIPPLE_MAX_PEAKS`.
The baseline fitted without the ripple absorbs part of it (moved triggers, bent friction
coefficients), which spreads its power over other wavelengths. Measured on the benchmark's
topography set (λ = 4 µm, a = 0.03; baseline at 8c17533): the highest peak was at 1.09 µm
(Δχ² 929) and the refit from it ended at λ = 1.11 µm with Δnll 1451; the 7th, at 3.66 µm
(Δχ² 482, 52 % of the highest), refitted to λ = 4.02 µm with Δnll 10175, the same point as
a start at the truth. Each refit took ~10 s."""


def ripple_peaks(d2: np.ndarray) -> list:
    """Indices of the periodogram's leading local maxima, highest first (see
    :data:`RIPPLE_PEAK_SHARE`)."""
    d2 = np.asarray(d2, dtype=float)
    if not d2.size or not np.isfinite(d2).any():
        return []
    v = np.where(np.isfinite(d2), d2, -np.inf)
    left = np.r_[-np.inf, v[:-1]]
    right = np.r_[v[1:], -np.inf]
    loc = np.flatnonzero((v > left) & (v >= right) & np.isfinite(v))  # (a flat top counts once)
    loc = loc[np.argsort(-v[loc], kind="stable")]
    top = v[loc[0]]
    if not top > 0:
        return []
    return [int(j) for j in loc if v[j] >= RIPPLE_PEAK_SHARE * top][:RIPPLE_MAX_PEAKS]


def where(prob, w: np.ndarray, r: np.ndarray | None = None) -> list:
    """The ranked list of where the misfit of a fitted problem lives (largest first)."""
    if r is None:
        r = prob.residuals(w)
    feats = feature_values(prob, w, r)
    runs = prob.runs
    out: list[Misfit] = []
    out += _plateau_misfits(feats["post_slip_level"], runs)
    out += _slip_length_misfits(feats["slip_length"], runs)
    out += _static_friction_misfits(prob, w, feats["static_friction"])
    out += _stick_slope_misfits(feats["stick_slope"], runs)
    out += _time_misfits(prob, feats["post_slip_level"])
    out += _time_by_run_misfits(prob, feats["post_slip_level"])
    out += _creep_misfits(feats["creep_level"], runs)
    out.sort(key=lambda m: -(m.misfit_sigma if np.isfinite(m.misfit_sigma) else -1))
    return out


def _plateau_misfits(pl, runs) -> list:
    """``post_slip_level`` (χ² of the plateau levels) and ``post_slip_whiteness`` (their
    lag-1 autocorrelation within runs: an accumulating slip-length error makes them wander)."""
    if not pl.value_um.size:
        return []
    n_ev = sum(1 for rd in runs if rd.kind == "events")
    z = pl.value_um / pl.sigma_um
    worst = int(np.argmax(np.abs(z)))
    out = [_chi2(z, pl.value_um.size - n_ev, "post_slip_level",
                 f"largest {z[worst]:+.1f} σ in {runs[pl.run[worst]].name}")]
    num, den = 0.0, float(z @ z)
    n_pairs = 0
    for ri in np.unique(pl.run):
        zz = z[pl.run == ri]
        num += float(zz[1:] @ zz[:-1])
        n_pairs += max(len(zz) - 1, 0)
    if den > 0 and n_pairs > 2:
        rho = num / den * len(z) / max(n_pairs, 1)
        zst = rho * math.sqrt(n_pairs)
        p = float(2 * stats.norm.sf(abs(zst)))
        out.append(Misfit("post_slip_whiteness", misfit_sigma(p), p, rho,
                          f"lag-1 autocorrelation {rho:+.2f} of the plateau levels within runs "
                          f"({n_pairs} pairs)"))
    return out


def _slip_length_misfits(sl, runs) -> list:
    """``slip_length`` (each run's mean slip misfit: the sum telescopes, so its noise comes
    from the end plateaus) and ``slip_length_vs_conditions`` (those means against the runs')."""
    if not sl.value_um.size:
        return []
    means, ses, conds, labels = [], [], [], []
    for ri in np.unique(sl.run):
        m = sl.run == ri
        v = sl.value_um[m]
        rd = runs[ri]
        n = rd.plateau_n
        se_sum = rd.sigma * 1e6 * math.sqrt(1 / max(n[0], 1) + 1 / max(n[-1], 1))
        means.append(v.mean())
        ses.append(se_sum / len(v))
        conds.append([math.log(rd.Nb), math.log(rd.k), math.log(rd.fp)])
        labels.append(runs[ri].name)
    means, ses = np.array(means), np.array(ses)
    z = means / ses
    worst = int(np.argmax(np.abs(z)))
    return [_chi2(z, len(z), "slip_length",
                  f"mean slip misfit {means[worst] * 1e3:+.0f} nm ({z[worst]:+.1f} σ) in {labels[worst]}"),
            _condition_trend(means, ses, np.array(conds), "slip_length_vs_conditions", "slip-length misfit")]


def _static_friction_misfits(prob, w: np.ndarray, st) -> list:
    """``static_friction`` (each run's mean trigger residual), then its trend against rest
    time across runs and its ripple along the track (:func:`_rest_trend`, :func:`_position_misfits`)."""
    if not st.value_um.size:
        return []
    zt = st.value_um / st.sigma_um
    zr = []
    labels = []
    for ri in np.unique(st.run):
        zr.append(zt[st.run == ri].mean())
        labels.append(prob.runs[ri].name)
    zr = np.array(zr)
    worst = int(np.argmax(np.abs(zr)))
    out = [_chi2(zr, len(zr), "static_friction",
                 f"mean trigger misfit {zr[worst]:+.1f} σ "
                 f"({st.value_um[st.run == np.unique(st.run)[worst]].mean() * 1e3:+.0f} nm "
                 f"of elongation) in {labels[worst]}")]
    return out + _rest_trend(prob, st, zr) + _position_misfits(prob, w, st, zt)


def _rest_trend(prob, st, zr: np.ndarray) -> list:
    """``static_friction_vs_rest``: the runs' mean trigger residuals ``zr`` against their mean
    ln(rest time), between runs (none where the rests barely differ)."""
    nx = prob.ev_next
    pv = nx - 1
    rest = (prob.ev_step[nx] - prob.ev_step[pv] - prob.ev_M[pv]) / prob.ev_fp[pv]
    # between runs: each run's mean residual against its mean ln(rest), variance ≤ 1
    # as above. (Within a run the rests barely vary, and the trigger encoding's own
    # error near τ would dominate such a trend.)
    lr = np.array([np.log(np.maximum(rest[st.run == ri], 1e-9)).mean() for ri in np.unique(st.run)])
    if not (len(lr) > 2 and np.ptp(lr) > 0.1):
        return []
    xc = lr - lr.mean()
    b = float(xc @ zr) / float(xc @ xc)
    zst = b * math.sqrt(float(xc @ xc))
    p = float(2 * stats.norm.sf(abs(zst)))
    return [Misfit("static_friction_vs_rest", misfit_sigma(p), p, zst,
                   f"trend {b:+.2f} σ per e-fold of rest time across runs (z = {zst:+.1f})")]


def _position_misfits(prob, w: np.ndarray, st, zt: np.ndarray) -> list:
    """``position``: a ripple of the static friction along the track common to every run, in
    friction-coefficient units (p from the periodogram's peak, Bonferroni over wavelengths)."""
    runs = prob.runs
    nx = prob.ev_next
    x_um = w[prob.i_x : prob.i_x + prob.P]
    x_prev = x_um[prob.ev_prev[nx]] * LENGTH_UNIT
    dx = float(prob.model.step(prob.params(w[: prob.n_theta])))
    N = np.array([runs[i].Nb for i in st.run])
    k = np.array([runs[i].k for i in st.run])
    dmu = -zt * k * dx / (math.sqrt(12) * N)  # capacity the model misses, per unit load
    wt = (math.sqrt(12) * N / (k * dx)) ** 2
    # slips the model could not evaluate (NaN) are left out of the ripple and its scale
    ok = np.isfinite(x_prev) & np.isfinite(dmu) & np.isfinite(wt)
    x_prev, dmu, wt, rip_run = x_prev[ok], dmu[ok], wt[ok], st.run[ok]
    span = float(np.ptp(x_prev)) if x_prev.size else 0.0
    if not (x_prev.size > 8 and span > 0):
        return []
    lo = 1e-6  # the topography candidate's shortest wavelength (identify.model.effects)
    lams = np.geomspace(lo, max(span / 2, 2 * lo), 240)
    d2, amp, ph = position_ripple(x_prev, dmu, wt, rip_run, lams)
    # clusters (phase-locked slips) inflate the weights: scale by the residual dispersion
    dof = max(len(dmu) - len(np.unique(rip_run)), 1)
    disp = max(float(np.sum(wt * (dmu - _run_means(dmu, wt, rip_run)) ** 2)) / dof, 1.0)
    peaks = ripple_peaks(d2)
    i = peaks[0] if peaks else int(np.argmax(np.nan_to_num(d2, nan=-np.inf)))
    n_ind = max(int(span / lo), 1)
    q = d2[i] / disp
    p = float(min(1.0, n_ind * math.exp(-q / 2)))
    return [Misfit("position", misfit_sigma(p), p, q,
                   f"ripple of the static friction along the track: λ = {lams[i] * 1e6:.2f} µm, "
                   f"amplitude {amp[i]:.3g} (μ units)",
                   extra=dict(wavelength_m=float(lams[i]), amplitude=float(amp[i]), phase=float(ph[i]),
                              peaks=[dict(wavelength_m=float(lams[j]), amplitude=float(amp[j]),
                                          phase=float(ph[j]), delta_chi2=float(d2[j])) for j in peaks]))]


def _stick_slope_misfits(ss, runs) -> list:
    """``stick_slope``: χ² of the staircase slopes."""
    if not ss.value_um.size:
        return []
    z = ss.value_um / ss.sigma_um
    worst = int(np.argmax(np.abs(z)))
    return [_chi2(z, len(z), "stick_slope", f"largest {z[worst]:+.1f} σ in {runs[ss.run[worst]].name}")]


def _time_misfits(prob, pl) -> list:
    """``time``: the trend of the plateau residuals against time within runs."""
    if not pl.value_um.size > 3:
        return []
    z = pl.value_um / pl.sigma_um
    b, t, p = _cluster_trend(z, prob.pl_mean_t, pl.run) if len(np.unique(pl.run)) > 1 else (0.0, 0.0, 1.0)
    if not np.isfinite(t):
        return []
    return [Misfit("time", misfit_sigma(p), p, t, f"plateau-level trend {b:+.3g} σ/s within runs (t = {t:+.1f})")]


def run_trends(prob, pl) -> tuple[np.ndarray, np.ndarray]:
    """Per run with four plateaus or more: the trend of its plateau residuals (σ units)
    against time, as a t statistic, with the run's index. The scatter about the trend
    sets its standard error where it exceeds the noise (a misfit of another kind, as a
    wrong load, then does not pass for a trend)."""
    z = pl.value_um / pl.sigma_um
    ts, idx = [], []
    for ri in np.unique(pl.run):
        m = pl.run == ri
        if m.sum() < 4:
            continue
        x = prob.pl_mean_t[m] - prob.pl_mean_t[m].mean()
        y = z[m] - z[m].mean()
        sxx = float(x @ x)
        if sxx <= 0:
            continue
        b = float(x @ y) / sxx
        s2 = max(float(((y - b * x) ** 2).sum()) / max(m.sum() - 2, 1), 1.0)
        ts.append(b / math.sqrt(s2 / sxx))
        idx.append(int(ri))
    return np.array(ts), np.array(idx, int)


def _time_by_run_misfits(prob, pl) -> list:
    """``time_by_run``: χ² of each run's own trend of its plateau residuals against time (a
    drift at a rate and sign of each run's own, which the pooled ``time`` trend averages
    away)."""
    if not pl.value_um.size:
        return []
    t, idx = run_trends(prob, pl)
    if t.size < 1:
        return []
    worst = int(np.argmax(np.abs(t)))
    return [_chi2(t, t.size, "time_by_run",
                  f"the runs' own trends in time; largest t = {t[worst]:+.1f} in {prob.runs[idx[worst]].name}")]


def _creep_misfits(cr, runs) -> list:
    """``creep_level``: χ² of the creep runs' steady levels."""
    if not cr.value_um.size:
        return []
    z = cr.value_um / cr.sigma_um
    worst = int(np.argmax(np.abs(z)))
    return [_chi2(z, len(z), "creep_level",
                  f"{cr.value_um[worst] * 1e3:+.0f} nm ({z[worst]:+.1f} σ) in {runs[cr.run[worst]].name}")]


def with_regime(misfits: list, check) -> list:
    """``misfits`` with the ``regime`` feature of a :class:`identify.fitting.regime_check.RegimeCheck`
    (the runs the fit left out for their regime, under the model) ranked in; unchanged
    when there is no check or no run could be simulated."""
    if check is None or not check.df:
        return list(misfits)
    m = Misfit("regime", misfit_sigma(check.p_value), check.p_value, check.chi2,
               f"χ²/df = {check.chi2 / check.df:.2f} (df {check.df}); {check.text()}",
               extra=dict(mismatched=check.mismatched, runs=check.runs))
    out = [x for x in misfits if x.feature != "regime"] + [m]
    out.sort(key=lambda x: -(x.misfit_sigma if np.isfinite(x.misfit_sigma) else -1))
    return out


def _run_means(y, w, run):
    out = np.empty_like(y)
    for r in np.unique(run):
        m = run == r
        out[m] = np.sum(w[m] * y[m]) / np.sum(w[m])
    return out


def _condition_trend(y, se, X, feature, what):
    """Weighted regression of per-run misfits on run conditions (columns of X that vary)."""
    ok = np.isfinite(y) & np.isfinite(se) & (se > 0) & np.all(np.isfinite(X), axis=1)
    y, se, X = np.asarray(y)[ok], np.asarray(se)[ok], np.asarray(X)[ok]
    keep = [j for j in range(X.shape[1]) if np.ptp(X[:, j]) > 1e-9] if len(y) else []
    names = np.array(["ln Nb", "ln k", "ln fp"])[keep]
    n = len(y)
    A = np.column_stack([np.ones(n)] + [X[:, j] for j in keep])
    if n <= A.shape[1] + 1 or not keep:
        return Misfit(feature, 0.0, 1.0, 0.0, f"too few runs or conditions to test a trend of the {what}")
    wts = 1 / se**2
    sw = np.sqrt(wts)
    coef, *_ = np.linalg.lstsq(A * sw[:, None], y * sw, rcond=None)
    res_full = float(np.sum(wts * (y - A @ coef) ** 2))
    mean = float(np.sum(wts * y) / np.sum(wts))
    res_0 = float(np.sum(wts * (y - mean) ** 2))
    q = len(keep)
    df2 = n - A.shape[1]
    F = ((res_0 - res_full) / q) / max(res_full / df2, 1.0)  # never below the noise
    p = float(stats.f.sf(F, q, df2))
    j = int(np.argmax(np.abs(coef[1:])))
    return Misfit(feature, misfit_sigma(p), p, F,
                  f"{what} depends on the run conditions (F = {F:.1f}; largest: {coef[1 + j] * 1e3:+.0f} nm "
                  f"per unit {names[j]})")
