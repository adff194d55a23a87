"""The features of a fitted run set, in micrometres and in units of their own noise.

The identification NLP's residuals are already the data's features, σ-normalised
(:mod:`identify.fitting.problem`): plateau levels, staircase slopes, slip triggers, creep levels.
This module maps each residual row and each decision variable to its run, and turns a
residual vector into the features the diagnosis talks about:

``post_slip_level``   ē_p − e_model,p per plateau (µm; noise σ/√n_p)
``slip_length``       data − model slip length, −(ρ_{p+1} − ρ_p) (µm; σ·√(1/n_p + 1/n_{p+1}))
``static_friction``   where the model puts the capacity in the trigger step's interval,
                      as elongation: (position − phase)·Δx (µm; uniform noise Δx/√12)
``stick_slope``       staircase slope misfit accumulated over the run's mean stick (µm)
``creep_level``       steady elongation of a creep run, data − model (µm)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from identify.model.scopes import label, parse

__all__ = ["Layout", "FeatureValues", "feature_values", "gap"]

UM = 1e6


@dataclass
class Layout:
    """Which run each residual row, constraint row and decision variable belongs to
    (−1: shared, i.e. the model parameters); ``theta_run``: the run a per-run parameter
    belongs to (:mod:`identify.model.scopes`; −1 for the others). A held-out run's own
    parameters are estimated from its own frames, as its other variables are."""

    row_run: np.ndarray
    con_run: np.ndarray
    var_run: np.ndarray
    groups: dict
    theta_runs: tuple = ()  # per parameter: the runs it acts on (() for the shared ones)

    def fold_vars(self, fold) -> np.ndarray:
        """Whether each decision variable is the fold's own: a run's variables, and a
        per-run or per-device parameter whose every run is in the fold (out of it, it acts
        on nothing)."""
        own = np.isin(self.var_run, list(fold))
        fold = set(int(i) for i in fold)
        for i, runs in enumerate(self.theta_runs):
            if runs and set(runs) <= fold:
                own[i] = True
        return own

    @classmethod
    def of(cls, prob) -> Layout:
        grp = prob.residual_groups()
        slope_runs = [i for i, r in enumerate(prob.runs) if r.kind == "events" and r.s_nn > 0]
        creep_runs = [i for i, r in enumerate(prob.runs) if r.kind == "creep"]
        p0, p1 = grp["priors"]  # (shared: a prior belongs to no run)
        rows = np.r_[prob.pl_run, np.array(slope_runs, int), prob.trigger_runs(), np.array(creep_runs, int),
                     prob.dr_run, np.full(p1 - p0, -1, int)]
        var = np.full(prob.n_w, -1, int)
        if prob.n_off:
            var[prob.i_off : prob.i_off + prob.n_off] = np.arange(prob.n_off)
        var[prob.i_x : prob.i_x + prob.P] = prob.pl_run
        for ri, k in prob.phase_of_run.items():
            var[prob.i_phi + k] = ri
        var[prob.i_s : prob.i_s + prob.n_s] = prob.ev_run[: prob.n_s]
        # constraints: slip-length continuity per slip, then the start positions'
        con = np.r_[prob.ev_run, prob.ev_run[prob.ev_next] if prob.n_s else np.zeros(0, int)]
        return cls(row_run=rows.astype(int), con_run=con.astype(int), var_run=var, groups=grp,
                   theta_runs=tuple(_acts_on(prob, n) for n in prob.theta.names))


def _acts_on(prob, name: str) -> tuple:
    """The runs a per-run or per-device parameter acts on (() for a shared one)."""
    _, scope, lab = parse(name)
    if scope is None:
        return ()
    if scope == "run":
        return tuple(i for i, r in enumerate(prob.runs) if label(r.name) == lab)
    return tuple(i for i in range(len(prob.runs)) if prob.run_device(i) == lab)


@dataclass
class FeatureValues:
    """Feature misfits (data − model) of one residual vector, µm, with their noise and run."""

    name: str
    value_um: np.ndarray
    sigma_um: np.ndarray
    run: np.ndarray

    def restrict(self, runs) -> FeatureValues:
        m = np.isin(self.run, list(runs))
        return FeatureValues(self.name, self.value_um[m], self.sigma_um[m], self.run[m])


def feature_values(prob, w: np.ndarray, r: np.ndarray) -> dict:
    """Feature misfits (µm) of residual vector ``r`` of ``prob`` (fitted or predicted);
    ``w`` gives the model's puller step."""
    grp = prob.residual_groups()
    dx = float(prob.model.step(prob.params(w[: prob.n_theta])))
    out: dict = {}
    p0, p1 = grp["plateaus"]
    sig_pl = prob.pl_sigma / np.sqrt(np.maximum(prob.pl_n, 1))
    rho = r[p0:p1] * sig_pl  # m
    out["post_slip_level"] = FeatureValues("post_slip_level", rho * UM, sig_pl * UM, prob.pl_run.copy())
    same = prob.pl_run[1:] == prob.pl_run[:-1]
    d = -(rho[1:] - rho[:-1])[same]
    sd = np.sqrt(sig_pl[1:] ** 2 + sig_pl[:-1] ** 2)[same]
    out["slip_length"] = FeatureValues("slip_length", d * UM, sd * UM, prob.pl_run[1:][same])
    s0, s1 = grp["slopes"]
    vals, sigs, runs = [], [], []
    k = s0
    for i, rd in enumerate(prob.runs):
        if rd.kind == "events" and rd.s_nn > 0:
            n_stick = float(np.mean(np.diff(np.r_[0, rd.trigger_steps]))) if len(rd.trigger_steps) else 1.0
            se = rd.sigma / math.sqrt(rd.s_nn)
            vals.append(-r[k] * se * n_stick)  # the residual is model − data slope
            sigs.append(se * n_stick)
            runs.append(i)
            k += 1
    out["stick_slope"] = FeatureValues("stick_slope", np.array(vals) * UM, np.array(sigs) * UM, np.array(runs, int))
    t0, t1 = grp["triggers"]
    n_trig = prob.n_trig
    z = r[t0 : t0 + n_trig]
    out["static_friction"] = FeatureValues(
        "static_friction", z / math.sqrt(12) * dx * UM, np.full(n_trig, dx / math.sqrt(12) * UM),
        prob.ev_run[prob.ev_next].astype(int))
    c0, c1 = grp["creep"]
    cr = [i for i, rd in enumerate(prob.runs) if rd.kind == "creep"]
    se = np.array([prob.runs[i].steady_se for i in cr])
    out["creep_level"] = FeatureValues("creep_level", r[c0:c1] * se * UM, se * UM, np.array(cr, int))
    return out


def gap(features: dict, runs=None) -> dict:
    """RMS misfit (µm) pooled over the features, per feature, and the noise floor."""
    sel = {k: (v.restrict(runs) if runs is not None else v) for k, v in features.items()}
    allv = np.concatenate([v.value_um for v in sel.values()]) if sel else np.zeros(0)
    alls = np.concatenate([v.sigma_um for v in sel.values()]) if sel else np.zeros(0)
    rms = lambda a: float(np.sqrt(np.mean(a**2))) if a.size else float("nan")  # noqa: E731
    return dict(
        gap_um=rms(allv),
        noise_um=rms(alls),
        # each feature in its own noise units (1: at the noise), as the fit and the
        # feature tests weigh them; the µm gap is ruled by the features largest in µm
        gap_sigma=rms(allv[alls > 0] / alls[alls > 0]),
        by_feature={k: rms(v.value_um) for k, v in sel.items() if v.value_um.size},
        n=int(allv.size),
    )

