"""The paper's reference numbers (MODEL.md), checked with the equations as written unless
a check needs the stick-threshold option. Where the model does not give the paper's
number the test says so and pins the number the model gives (the README repeats it)."""

import numpy as np
import pytest

from identify import SimulationOptions, simulate

FAST = SimulationOptions(record=False)
STICK = 1e-5  # m/s, the stick band that reproduces Figs. 9 and 13 (README)


def run(coating="FOTAS", k=2.13, nb=5.0, fp=100.0, travel=20.0, **kw):
    return simulate(coating, spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp,
                    travel_um=travel, options=FAST, **kw)


def test_fig13_as_written():
    """Fig. 13 (FOTAS, 5 µN, 2.13 N/m, 100 Hz): the first slip, from a fully aged contact,
    peaks at 2.79 cm/s (paper: about 2 cm/s) and ψ falls to μmin; afterwards the model as
    written creeps (DESIGN.md §1), so 'ψ ≈ μmin at every slip' needs the stick band."""
    r = run()
    v = r.slips["peak_speed_m_per_s"]
    assert v[0] == pytest.approx(0.0279, rel=0.02)
    assert 0.01 < v[0] < 0.04  # the paper's "about 2 cm/s", within a factor 2
    assert r.slips["state_after"][0] == pytest.approx(0.484, abs=2e-3)
    assert r.regime == "creep"


def test_fig13_with_stick_band():
    """With the stick band the run is stick-slip, ψ returns to μmin at every slip, and
    the peak is 3.46 cm/s (the band raises the capacity by A·ln(1 + v_stick/vc))."""
    r = run(stick_speed_m_per_s=STICK)
    sl = r.slips
    assert r.regime == "stick-slip" and len(sl) >= 15
    np.testing.assert_allclose(sl["state_after"], 0.484, atol=2e-3)
    assert sl["peak_speed_m_per_s"].max() == pytest.approx(0.0346, rel=0.02)


def test_peak_speed_30uN_k213_as_written():
    """FOTAS, 30 µN, 100 Hz, k = 2.13 N/m: the paper's simulation peaks at 15 cm/s; the
    model as written gives 14.6 cm/s."""
    r = run(nb=30, travel=30)
    v = r.slips["peak_speed_m_per_s"]
    np.testing.assert_allclose(v, 0.1457, rtol=0.01)
    assert v.max() == pytest.approx(0.15, rel=0.05)


def test_peak_speeds_30uN_in_the_papers_proportion():
    """15 cm/s at k = 2.13 and 1.7 cm/s at k = 20.3 N/m (ratio 8.8): the k = 20.3 run
    creeps as written, so the comparison uses the stick band and the steady cycle (after
    the first slips from the fully aged start): 18.1 and 1.98 cm/s, ratio 9.1."""
    soft = run(nb=30, travel=30, stick_speed_m_per_s=STICK).slips
    stiff = run(k=20.3, nb=30, travel=30, stick_speed_m_per_s=STICK).slips
    v_soft = np.median(soft["peak_speed_m_per_s"][1:])
    v_stiff = np.median(stiff["peak_speed_m_per_s"][3:])
    assert v_soft == pytest.approx(0.181, rel=0.02)
    assert v_stiff == pytest.approx(0.0198, rel=0.02)
    assert v_soft / v_stiff == pytest.approx(15 / 1.7, rel=0.1)


def test_fig15_force_drop_smaller_for_the_stiffer_spring():
    """Fig. 15: kδ at a given Nb is smaller for k = 20.3 than for 2.13 N/m (shorter
    rests, less aging)."""
    for nb in (10.0, 30.0):
        soft = run(nb=nb, travel=30, stick_speed_m_per_s=STICK).slips
        stiff = run(k=20.3, nb=nb, travel=30, stick_speed_m_per_s=STICK).slips
        kd_soft = 2.13 * np.median(soft["slip_length_m"][1:])
        kd_stiff = 20.3 * np.median(stiff["slip_length_m"][3:])
        assert kd_stiff < 0.8 * kd_soft


def test_fig14_velocity_strengthening_shortens_slips():
    """Fig. 14: with A = 0 the slips follow 2·Nb·(μmax − μmin)/k; A = 0.015 shortens them."""
    a0 = run(nb=30, fp=10, travel=30, params={"A": 0.0}).slips["slip_length_m"]
    a15 = run(nb=30, fp=10, travel=30).slips["slip_length_m"]
    np.testing.assert_allclose(a0, 2 * 30e-6 * 0.312 / 2.13, rtol=0.03)
    assert np.median(a15) < 0.9 * np.median(a0)


def test_fig9_static_friction_falls_with_step_frequency():
    """Fig. 9 (k = 2.13 N/m, Nb = 0.98 µN): μs = k·ē_peak/Nb falls by 0.31 (FOTAS) and
    0.17 (OTS) from 10 to 1000 Hz. As written FOTAS creeps at 1 kHz (no μs); with the
    stick band the model gives 0.27 (FOTAS) and 0.17 (OTS)."""
    drops = {}
    for coating in ("FOTAS", "OTS"):
        mus = []
        for fp in (10.0, 1000.0):
            sl = run(coating, nb=0.98, fp=fp, travel=10, stick_speed_m_per_s=STICK).slips
            mus.append(2.13 * np.mean(sl["peak_elongation_m"][1:]) / 0.98e-6)
        drops[coating] = mus[0] - mus[1]
    assert drops["FOTAS"] == pytest.approx(0.27, abs=0.02)
    assert drops["OTS"] == pytest.approx(0.17, abs=0.02)
    assert drops["FOTAS"] == pytest.approx(0.31, abs=0.06)
    assert drops["OTS"] == pytest.approx(0.17, abs=0.03)
