"""Simulator checks against exactly known solutions (scipy's habit: exact answers,
errors normalised by the tolerance, work counted rather than timed)."""

import math

import numpy as np
import pytest

from identify import ParameterError, RunConditions, SimulationOptions, simulate, simulate_run
from identify.model.params import parameter_set
from identify.model.symbolic import Model

K, MB = 2.13, 3.64e-10
ENGINES = ["rosenbrock", "idas"]


def _constant_friction(mu, c_extra=0.0):
    """ψ frozen at μmin (no aging within the test, nothing to rejuvenate), no rate term."""
    return {"mu_min": mu, "mu_max": mu + 0.1, "tau": 1e3, "A": 0.0, "c": 0.0, "c_extra": c_extra}


@pytest.mark.parametrize("engine", ENGINES)
def test_half_oscillation_against_closed_form(engine):
    """Constant friction μ, spring released at e0 = r·μ·N/k (r < 3): x follows a half
    cosine, stops after π·sqrt(mb/k) having moved 2(r − 1)·μ·N/k, and is held."""
    mu, r, nb = 0.3, 2.0, 10e-6
    e0 = r * mu * nb / K
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=nb * 1e6, step_frequency_Hz=1.0,
                   n_steps=1, params=_constant_friction(mu), initial_elongation_um=e0 * 1e6,
                   initial_state=mu, options=SimulationOptions(integrator=engine),
                   check_platform=False)  # (τ = 1000 s, outside what a contact has: aging off on purpose)
    ev = res.events
    assert ev["time_s"][0] == 0.0 and ev["reversals"][0] == 0
    assert ev["duration_s"][0] == pytest.approx(math.pi * math.sqrt(MB / K), rel=1e-5)
    assert ev["slip_length_m"][0] == pytest.approx(2 * (r - 1) * mu * nb / K, rel=1e-5)
    # peak speed of the half cosine: ω·(e0 − μN/k)
    assert ev["peak_speed_m_per_s"][0] == pytest.approx(math.sqrt(K / MB) * (e0 - mu * nb / K), rel=2e-3)


@pytest.mark.parametrize(
    "r, a_star, half_cycles",
    [(6.0, 0.0, 3), (1.4, 0.0, 1), (6.0, 0.1, 2), (2.6, 0.0, 1), (3.4, 0.0, 2)],
)
def test_appendix_half_cycle_counts(r, a_star, half_cycles):
    """Paper, Appendix: μmin = 0.1, F0* = μmin + A*·|ẋ*|; the block completes n half
    cycles, n the smallest integer with (r − 1)/2 < n when A* = 0; A* = 0.1 cuts r = 6
    to 2. The linear velocity term is a viscous force, c = A*·sqrt(k·mb)."""
    mu, nb = 0.1, 10e-6
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=nb * 1e6, step_frequency_Hz=1.0,
                   n_steps=1, params=_constant_friction(mu, c_extra=a_star * math.sqrt(K * MB)),
                   initial_elongation_um=r * mu * nb / K * 1e6, initial_state=mu,
                   check_platform=False)  # (τ = 1000 s: aging off on purpose)
    first = res.events
    assert first["reversals"][0] + 1 == half_cycles
    e_end = first["stop_elongation_m"][0]
    assert abs(K * e_end / nb) <= mu * (1 + 1e-6)  # held: |x*| < μmin


@pytest.mark.parametrize("nb_uN", [10.0, 30.0, 60.0])
def test_slip_length_without_velocity_strengthening(nb_uN):
    """A = 0 and saturated aging (rests ≫ τ): δ = 2·Nb·(μmax − μmin)/k (Eq. 14) within 3 %."""
    # enough travel for the first loading to μmax plus three slips
    travel = (0.796 + 3 * 2 * 0.312) * nb_uN / K + 2
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=nb_uN, step_frequency_Hz=10,
                   travel_um=travel, params={"A": 0.0}, options=SimulationOptions(record=False))
    delta = res.slips["slip_length_m"]
    assert len(delta) >= 2
    np.testing.assert_allclose(delta, 2 * nb_uN * 1e-6 * (0.796 - 0.484) / K, rtol=0.03)


def test_first_trigger_step_and_aged_state():
    """From e = 0 and ψ = μmax the first slip starts at the first step with k·e above the
    capacity (μmax·Nb, plus A·ln(1 + v_stick/vc)·Nb with the stick band), and ψ before
    each later slip follows Eq. 11 over the rest."""
    nb, vs = 5e-6, 1e-5
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=5, step_frequency_Hz=100,
                   travel_um=6, stick_speed_m_per_s=vs, options=SimulationOptions(record=False))
    ev = res.events
    n_star = math.floor((0.796 + 0.015 * math.log1p(vs / 1e-6)) * nb / (K * 46e-9)) + 1
    assert ev["step_index"][0] == n_star
    assert ev["peak_elongation_m"][0] == pytest.approx(n_star * 46e-9)
    law, P = res.model.law, res._P
    psi_prev = ev["state_after"][:-1]
    expected = law.rest(psi_prev, ev["rest_time_s"][1:], P)
    np.testing.assert_allclose(ev["state_before"][1:], expected, rtol=1e-9)
    # the trigger rule: the capacity is exceeded at the trigger, not one step earlier
    cap = res.model.hold_coefficient(ev["state_before"], 0.0, P) * nb
    assert np.all(K * ev["peak_elongation_m"] > cap)
    cap_before = res.model.hold_coefficient(law.rest(psi_prev, ev["rest_time_s"][1:] - 0.01, P), 0, P) * nb
    assert np.all(K * (ev["peak_elongation_m"][1:] - 46e-9) <= cap_before)


def test_engines_agree():
    """IDAS with toolkit-located stops and Rosenbrock with native events, same model."""
    kw = dict(spring_constant_N_per_m=K, normal_load_uN=30, step_frequency_Hz=100, travel_um=25)
    a = simulate("FOTAS", options=SimulationOptions(integrator="rosenbrock", record=False), **kw)
    b = simulate("FOTAS", options=SimulationOptions(integrator="idas", record=False), **kw)
    assert len(a.events) == len(b.events) >= 3
    np.testing.assert_allclose(a.events["slip_length_m"], b.events["slip_length_m"], atol=1e-10)
    # idas samples the peak on a replay grid (parabola-refined); rosenbrock records it by an event
    np.testing.assert_allclose(a.slips["peak_speed_m_per_s"], b.slips["peak_speed_m_per_s"], rtol=2e-3)


def test_work_grows_with_slips_not_with_steps():
    """Integrator calls per run: about one per moving phase, however many stick steps."""
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=30, step_frequency_Hz=10,
                   travel_um=25, options=SimulationOptions(record=False))
    assert res.conditions.n_steps > 500
    assert res.integrator_calls <= len(res.events) + 2


def test_camera_sampling():
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=5, step_frequency_Hz=100,
                   travel_um=3, stick_speed_m_per_s=1e-5)
    tr = res.sample()
    # two frames per step, in the middle of each half period
    np.testing.assert_allclose(np.diff(tr.time_s), 1 / 200)
    assert tr.time_s[0] == pytest.approx(1 / 400)
    exact = res.elongation(tr.time_s)
    np.testing.assert_allclose(tr.elongation, exact)
    a = res.sample(noise_nm=90, seed=3).elongation - exact
    b = res.sample(noise_nm=90, seed=3).elongation - exact
    np.testing.assert_array_equal(a, b)
    assert np.std(a) == pytest.approx(90e-9, rel=0.15)
    # a frame phase of 0 puts a frame on every step instant: e is the value after the step
    tr0 = res.sample(frame_rate_Hz=100, frame_phase=0.0)
    assert tr0.time_s[1] == pytest.approx(0.01)


def test_initial_conditions_are_overridable():
    res = simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=5, step_frequency_Hz=100,
                   travel_um=1, initial_elongation_um=1.0, initial_state=0.6,
                   options=SimulationOptions(record=False))
    assert res.stops[0, 3] == pytest.approx(1e-6)
    assert res.stops[0, 2] == 0.6


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(spring_constant_N_per_m=0.0), "spring_constant"),
        (dict(spring_constant_N_per_m=float("nan")), "spring_constant"),
        (dict(normal_load_uN=-1.0), "normal_load_uN"),
        (dict(step_frequency_Hz=0.0), "step_frequency"),
        (dict(travel_um=0.0), "travel_um"),
        (dict(travel_um=float("nan")), "travel_um"),
        (dict(law="power"), "law 'power' is not known"),
        (dict(params={"mu_min": 0.9}), "mu_min"),
        (dict(params={"taux": 0.1}), "unknown parameter 'taux'"),
    ],
)
def test_bad_input_names_parameter_and_rule(kw, match):
    base = dict(spring_constant_N_per_m=K, normal_load_uN=5, step_frequency_Hz=100, travel_um=2)
    base.update(kw)
    with pytest.raises(ValueError, match=match):
        simulate("FOTAS", **base)


def test_load_given_twice_or_not_at_all():
    with pytest.raises(ParameterError, match="exactly one of normal_load_uN or block_voltage_V"):
        simulate("FOTAS", spring_constant_N_per_m=K, normal_load_uN=5, block_voltage_V=7.15,
                 step_frequency_Hz=100, travel_um=1)


def test_travel_beyond_the_nanotractor_warns():
    with pytest.warns(UserWarning, match="exceeds the nanotractor"):
        simulate("FOTAS", spring_constant_N_per_m=20.3, normal_load_uN=1, step_frequency_Hz=1000,
                 travel_um=101, options=SimulationOptions(record=False))


def test_block_voltage_gives_the_load():
    res = simulate("FOTAS", spring_constant_N_per_m=K, block_voltage_V=7.15, step_frequency_Hz=100,
                   travel_um=1)
    assert res.conditions.normal_load == pytest.approx(0.98e-6, rel=0.02)


def test_bad_options():
    with pytest.raises(ValueError, match="integrator = 'cvodes'"):
        SimulationOptions(integrator="cvodes")
    with pytest.raises(ParameterError, match="n_steps"):
        RunConditions(2.13, 5e-6, 100.0, 0)


def test_simulate_run_keeps_failures_as_warnings(monkeypatch):
    """A failing moving phase ends the run with what was computed, and says so."""
    import identify.simulation.hybrid as sim

    calls = {"n": 0}
    real = sim._Runner.move

    def flaky(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("integrator failure (injected)")
        return real(self, *a, **k)

    monkeypatch.setattr(sim._Runner, "move", flaky)
    values = parameter_set("FOTAS")
    res = simulate_run(Model(), values, RunConditions(K, 30e-6, 100.0, 600))
    assert not res.completed and len(res.events) == 2
    assert "injected" in res.warnings[0]
