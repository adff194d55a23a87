"""The information of one run: what a (k, Nb, fp) run tells the fit about the friction
parameters.

The run is simulated at the nominal parameters without noise, its events extracted, the
identification's own NLP (:class:`identify.fitting.problem.Problem`) built with the
camera noise model as the frame standard deviation and its per-run nuisances solved with
the friction parameters held; the information is the Schur complement of the
Gauss–Newton matrix on the friction parameters (see :mod:`design.experiment`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from identify.fitting.stick_choice import STICK_SPEED_AUTO

from .candidates import Candidate

__all__ = ["DEFAULT_FREE", "STICK_SPEED", "run_information", "run_information_parts", "run_problem",
           "simulate_candidate"]

DEFAULT_FREE = ("mu_max", "mu_min", "tau", "A")
STICK_SPEED = STICK_SPEED_AUTO  # the stick option (README): as written, most of the grid creeps


def simulate_candidate(c: Candidate, coating: str, params: Mapping[str, float], stick_speed: float):
    """The simulated run of a candidate (its warnings silenced: a design simulates many)."""
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
    sim = simulate_candidate(c, coating, dict(params or {}), stick_speed_m_per_s)
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
