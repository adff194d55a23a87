"""Event extraction checked against the simulator's exact slips (``result.slips``) and
against constructed traces with a known answer."""

import json
import math

import numpy as np
import pytest

from identify import Trace, simulate
from identify.traces.events import (
    RunEvents,
    estimate_step_phase,
    extract_events,
    pelt,
    robust_noise,
    step_counts,
)

K = 2.13
NOISE = 90e-9
STEP = 46e-9


@pytest.fixture(scope="module")
def run30():
    """4 long slips (≈ 4.8 µm), rests of 104 steps."""
    return simulate(
        "FOTAS",
        spring_constant_N_per_m=K,
        normal_load_uN=30,
        step_frequency_Hz=100,
        travel_um=30,
        stick_speed_m_per_s=1e-5,
    )


@pytest.fixture(scope="module")
def run5():
    """34 slips of ≈ 0.83 µm (≈ 9σ), rests of 18 steps (36 frames)."""
    return simulate(
        "FOTAS",
        spring_constant_N_per_m=K,
        normal_load_uN=5,
        step_frequency_Hz=100,
        travel_um=30,
        stick_speed_m_per_s=1e-5,
    )


def _shifted(tr, dt, **meta):
    md = dict(tr.metadata)
    md.pop("step_phase", None)
    md.update(meta)
    return Trace(
        name=tr.name, time_s=tr.time_s + dt, elongation=tr.elongation, puller=None, metadata=md
    )


def _check_against_truth(ev: RunEvents, truth, sigma=NOISE):
    big = truth.select(np.abs(truth["slip_length_m"]) > 4 * sigma)
    found = np.isin(big["step_index"], ev.slips["trigger_step"])
    assert found.mean() >= 0.95, f"{found.sum()} of {len(big)} slips > 4σ found at their step"
    assert ev.n_slips <= len(truth) + 1  # no crowd of false slips
    if ev.n_slips == len(big):
        err = (ev.slips["slip_length_m"] - big["slip_length_m"]) / ev.slips["slip_length_se_m"]
        assert np.mean(np.abs(err) <= 3) >= 0.95 and np.all(np.abs(err) <= 4.5)
        perr = (ev.slips["peak_elongation_m"] - big["peak_elongation_m"]) / ev.plateaus[
            "level_se_m"
        ][:-1]
        assert np.mean(np.abs(perr) <= 3) >= 0.95 and np.all(np.abs(perr) <= 4.5)


@pytest.mark.parametrize("seed", [1, 2])
def test_long_slips_found_at_their_steps(run30, seed):
    ev = extract_events(run30.sample(noise_nm=90, seed=seed))
    assert ev.n_slips == len(run30.slips) == 4
    np.testing.assert_array_equal(ev.slips["trigger_step"], run30.slips["step_index"])
    _check_against_truth(ev, run30.slips)
    assert ev.regime == "stick-slip"
    assert ev.step_phase == 0.0
    assert ev.noise_m == pytest.approx(NOISE, rel=0.15)
    # rests: trigger-to-trigger steps, the first from t = 0
    assert ev.slips["rest_steps"][0] == run30.slips["step_index"][0]
    np.testing.assert_array_equal(ev.slips["rest_steps"][1:], np.diff(run30.slips["step_index"]))
    assert ev.slips["rest_time_s"] == pytest.approx(ev.slips["rest_steps"] / 100.0)
    assert np.all(ev.slips["z"] > 20)
    assert ev.warnings == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_short_slips_found_at_their_steps(run5, seed):
    ev = extract_events(run5.sample(noise_nm=90, seed=seed))
    _check_against_truth(ev, run5.slips)
    assert ev.n_slips == len(run5.slips)
    agree = np.mean(ev.slips["trigger_step"] == run5.slips["step_index"])
    assert agree >= 0.95
    assert ev.regime == "stick-slip"
    assert ev.noise_m == pytest.approx(NOISE, rel=0.15)
    # plateaus tile the frames in order
    p = ev.plateaus
    assert np.all(p["first_frame"][1:] > p["last_frame"][:-1])
    assert p["n_frames"].sum() + (ev.plateau_of_frame < 0).sum() == len(ev.trace)
    assert p["level_se_m"] == pytest.approx(ev.noise_m / np.sqrt(p["n_frames"]))


def test_noiseless_trace_gives_exact_levels(run5):
    ev = extract_events(run5.sample(noise_nm=0))
    s = run5.slips
    assert len(run5.events) == len(s)  # no sub-step creep events in this run
    np.testing.assert_array_equal(ev.slips["trigger_step"], s["step_index"])
    # plateau levels are the block positions at rest (xp0 = 0, e(0) = 0)
    np.testing.assert_allclose(ev.plateaus["level_m"], run5.stops[:, 1], rtol=0, atol=1e-13)
    np.testing.assert_allclose(ev.slips["slip_length_m"], s["slip_length_m"], rtol=0, atol=1e-13)
    np.testing.assert_allclose(
        ev.slips["peak_elongation_m"], s["peak_elongation_m"], rtol=0, atol=1e-13
    )
    assert ev.regime == "stick-slip"
    assert ev.noise_m < 1e-10


@pytest.mark.parametrize("shift", [0.3, 0.6])
def test_step_phase_recovered_on_shifted_times(run5, shift):
    """Steps at (n + shift)/fp; frames at 0.25 and 0.75 of the original periods, so the
    candidates are the gap midpoints shift and shift + 0.5 (and 0)."""
    tr = _shifted(run5.sample(noise_nm=90, seed=4), shift / 100)
    ev = extract_events(tr)
    assert abs(ev.step_phase - shift) < 0.25  # within its gap between frame phases
    agree = np.mean(ev.slips["trigger_step"] == run5.slips["step_index"])
    assert agree >= 0.95
    phi, info = estimate_step_phase(tr.time_s, tr.elongation, 100.0, STEP)
    assert len(info["candidates"]) == 3 and abs(phi - shift) < 0.25


def test_step_phase_labels_are_relative(run5):
    """A shift of 0.9 period: φ = 0 fits as well as φ = 0.9 (same gap between frame
    phases, step labels one apart); lengths and peak elongations do not care."""
    tr = run5.sample(noise_nm=90, seed=4)
    ev0 = extract_events(tr)
    ev = extract_events(_shifted(tr, 0.9 / 100))
    d = ev.slips["trigger_step"] - ev0.slips["trigger_step"]
    assert np.all(d == d[0]) and abs(d[0]) <= 1
    np.testing.assert_allclose(ev.slips["slip_length_m"], ev0.slips["slip_length_m"], atol=1e-15)
    np.testing.assert_allclose(
        ev.slips["peak_elongation_m"], ev0.slips["peak_elongation_m"], atol=1e-15
    )


def test_step_phase_from_metadata_is_used(run5):
    tr = _shifted(run5.sample(noise_nm=90, seed=4), 0.3 / 100, step_phase=0.3)
    ev = extract_events(tr)
    assert ev.step_phase == 0.3
    np.testing.assert_array_equal(ev.steps, step_counts(tr.time_s, 100.0, 0.3))
    with pytest.raises(ValueError, match="step_phase"):
        extract_events(_shifted(tr, 0.0, step_phase=1.5))


def test_frames_inside_slips_are_excluded(run30):
    tr = run30.sample(noise_nm=90, seed=1)
    s = run30.slips
    rng = np.random.default_rng(7)
    fr = np.array([0.5, 0.3, 0.8])  # fraction of the slip done at the inserted frame
    t_in = s["time_s"][:3] + 20e-6  # 20 µs into a ~130 µs slip
    e_in = s["peak_elongation_m"][:3] - fr * s["slip_length_m"][:3] + rng.normal(0, NOISE, 3)
    t = np.concatenate([tr.time_s, t_in])
    e = np.concatenate([tr.elongation, e_in])
    o = np.argsort(t)
    tr2 = Trace(name="inside", time_s=t[o], elongation=e[o], puller=None, metadata=tr.metadata)
    ev = extract_events(tr2)
    where = np.searchsorted(t[o], t_in)
    np.testing.assert_array_equal(ev.plateau_of_frame[where], -1)
    assert ev.n_slips == 4
    np.testing.assert_array_equal(ev.slips["frames_inside"], [1, 1, 1, 0])
    np.testing.assert_array_equal(ev.slips["trigger_step"], s["step_index"])
    err = (ev.slips["slip_length_m"] - s["slip_length_m"]) / ev.slips["slip_length_se_m"]
    assert np.all(np.abs(err) < 3)


def test_outlier_frame_is_excluded_not_a_slip(run30):
    tr = run30.sample(noise_nm=90, seed=1)
    e = tr.elongation.copy()
    j = 100  # inside the loading ramp
    e[j] += 3e-6
    ev = extract_events(
        Trace(name="glitch", time_s=tr.time_s, elongation=e, puller=None, metadata=tr.metadata)
    )
    assert ev.plateau_of_frame[j] == -1
    assert ev.n_slips == 4
    assert any("outlier" in w for w in ev.warnings)


def test_creep_run_is_unresolved():
    """fp = 1 kHz, Nb = 5 µN, equations as written: the block creeps after its first
    slips; PELT cuts the ramp of b into pieces, which the creep ratio recognises."""
    r = simulate(
        "FOTAS", spring_constant_N_per_m=K, normal_load_uN=5, step_frequency_Hz=1000, travel_um=20
    )
    assert r.regime == "creep"
    for seed in (1, 2):
        ev = extract_events(r.sample(noise_nm=90, seed=seed))
        assert ev.regime == "unresolved" or ev.n_slips <= len(r.slips)
        assert ev.regime == "unresolved"
        assert ev.creep_ratio > 0.25
        assert any("puller speed" in w for w in ev.warnings)


def test_loading_ramp_only_is_no_slip():
    r = simulate(
        "FOTAS", spring_constant_N_per_m=K, normal_load_uN=30, step_frequency_Hz=100, travel_um=5
    )
    assert len(r.slips) == 0
    ev = extract_events(r.sample(noise_nm=90, seed=3))
    assert ev.regime == "no-slip" and ev.n_slips == 0
    assert ev.n_plateaus == 1
    assert math.isnan(ev.reduced.mean_slip_m)


def _staircase_trace(levels_m, rest_steps, noise, seed, fp=100.0):
    """A constructed run: 2 frames per step (middle of each half period), the block at
    ``levels_m[i]`` for ``rest_steps[i]`` steps."""
    x = np.repeat(levels_m, np.asarray(rest_steps) * 2)
    j = np.arange(x.size)
    t = (j + 0.5) / (2 * fp)
    n = step_counts(t, fp, 0.0)
    e = STEP * n - x + np.random.default_rng(seed).normal(0, noise, x.size)
    meta = {"spring_constant_N_per_m": K, "normal_load_uN": 10.0, "step_frequency_Hz": fp}
    return Trace(name="staircase", time_s=t, elongation=e, puller=None, metadata=meta)


def test_backward_jump_is_kept_and_reported():
    tr = _staircase_trace([0.0, 2e-6, 1.2e-6, 3e-6], [30, 30, 30, 30], NOISE, 5)
    ev = extract_events(tr)
    assert ev.n_slips == 3
    assert ev.slips["slip_length_m"][1] == pytest.approx(
        -0.8e-6, abs=4 * ev.slips["slip_length_se_m"][1]
    )
    assert ev.slips["z"][1] < -5
    assert any("backward" in w for w in ev.warnings)
    np.testing.assert_array_equal(ev.slips["trigger_step"], [30, 60, 90])


@pytest.mark.parametrize("seed", [1, 2])
def test_wrong_step_size_in_metadata_does_not_cut_plateaus(run30, seed):
    """Metadata step 5 % short of the true one: b slopes back 2.2 nm per step, 230 nm
    (2.5σ) over each 104-step plateau; the plateaus must still be the true ones, and the
    trend is reported, not hidden."""
    tr = run30.sample(noise_nm=90, seed=seed)
    wrong = Trace(name=tr.name, time_s=tr.time_s, elongation=tr.elongation, puller=None,
                  metadata={**tr.metadata, "step_size_nm": 46 / 1.05})
    ev = extract_events(wrong)
    np.testing.assert_array_equal(ev.slips["trigger_step"], run30.slips["step_index"])
    true_speed = (46 / 1.05 - 46) * 1e-9 * 100  # m/s
    assert ev.segmentation_trend_m_per_s == pytest.approx(true_speed, rel=0.2)
    assert any("backward" in w and "step" in w for w in ev.warnings)
    assert ev.to_json()["segmentation_trend_m_per_s"] == ev.segmentation_trend_m_per_s
    # the right metadata leave b as it is
    assert extract_events(tr).segmentation_trend_m_per_s == 0.0


@pytest.fixture(scope="module")
def fresh_contact_run():
    """A fresh contact on a soft spring (2.13 N/m, 12 µN, 30 Hz): a 3 s rest before the
    first slip, then seven slips of 1.7 µm."""
    import warnings as _w

    with _w.catch_warnings():
        _w.simplefilter("ignore")
        return simulate(spring_constant_N_per_m=2.13, normal_load_uN=12.0, step_frequency_Hz=30.0, travel_um=15.0,
                        params=dict(mu_max=0.80, mu_min=0.50, tau=0.08, A=0.018), stick_speed_m_per_s=1e-5,
                        initial_state=0.55, initial_elongation_um=0.3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_forward_drift_does_not_cut_plateaus_into_slips(fresh_contact_run, seed):
    """The camera's zero drifting by 50 nm/s raises b by 160 nm over the first rest: PELT
    cut that ramp into pieces that passed as slips (measured: 5 to 7 spurious slips among
    the seven, z 5 to 7, in each of six seeds). The forward speed is removed for the
    partition, as a backward one is, and reported."""
    run = fresh_contact_run
    tr = run.sample(frame_rate_Hz=100.0, noise_nm=40.0, seed=seed, drift_rate_m_per_s=-5e-8)
    ev = extract_events(tr)
    np.testing.assert_array_equal(ev.slips["trigger_step"], run.slips["step_index"])
    assert ev.segmentation_trend_m_per_s == pytest.approx(5e-8, rel=0.25)
    assert any("moves forward" in w and "drifts" in w for w in ev.warnings)
    # without the drift nothing is removed
    assert extract_events(run.sample(frame_rate_Hz=100.0, noise_nm=40.0, seed=seed)).segmentation_trend_m_per_s == 0.0


def test_small_slips_every_few_steps_are_not_a_forward_drift(monkeypatch):
    """Small slips every five steps (20.3 N/m, 30 µN, 100 Hz, the true step 5 % longer than
    the metadata's; z 5 to 21) raise the plateaus' slopes where the plateaus cut across
    them: 0.16 of the puller speed. That is the block's own advance, not a drift:
    removing it merged real slips (39 for 46). Below a tenth of the puller speed only."""
    import identify.traces.plateaus as plateaus
    from identify.simulation.withheld import QUICK_CONDITIONS, withheld_dataset

    (tr,) = withheld_dataset("step_size", conditions=[c for c in QUICK_CONDITIONS if c[:3] == (20.3, 30.0, 100.0)],
                             base={"A": 0.015})
    ev = extract_events(tr)
    assert ev.segmentation_trend_m_per_s == 0.0 and ev.n_slips == 46
    monkeypatch.setattr(plateaus, "FORWARD_TREND_LIMIT", 0.0)  # (the forward removal off)
    assert extract_events(tr).slips["trigger_step"].tolist() == ev.slips["trigger_step"].tolist()


def test_given_noise_is_used_and_inputs_checked():
    tr = _staircase_trace([0.0, 1e-6, 2e-6], [20, 20, 20], NOISE, 6)
    ev = extract_events(tr, noise_m=100e-9)
    assert ev.noise_m == 100e-9
    assert ev.n_slips == 2
    with pytest.raises(ValueError, match="noise_m"):
        extract_events(tr, noise_m=-1.0)
    with pytest.raises(ValueError, match="min_z"):
        extract_events(tr, min_z=0)


def test_pelt_finds_known_change_points():
    rng = np.random.default_rng(0)
    y = np.concatenate(
        [np.zeros(200), np.full(150, 8.0), np.full(300, 3.0), np.full(5, 12.0), np.zeros(100)]
    )
    y = y + rng.normal(0, 1, y.size)
    starts = pelt(y, 2 * math.log(y.size) * 1.5)
    np.testing.assert_array_equal(starts, [0, 200, 350, 650, 655])
    assert pelt(rng.normal(0, 1, 2000), 2 * math.log(2000) * 1.5).tolist() == [0]


def test_robust_noise_ignores_rare_jumps():
    rng = np.random.default_rng(1)
    b = np.repeat(np.arange(50) * 1e-6, 40) + rng.normal(0, NOISE, 2000)
    assert robust_noise(b) == pytest.approx(NOISE, rel=0.1)


def test_json_report_and_plot(run5):
    ev = extract_events(run5.sample(noise_nm=90, seed=1))
    d = ev.to_json()
    text = json.dumps(d)
    assert d["n_slips"] == ev.n_slips == len(d["slips"]["trigger_step"])
    assert set(d["plateaus"]) == {
        "first_frame",
        "last_frame",
        "n_frames",
        "level_m",
        "level_se_m",
        "mean_puller_m",
    }
    assert "NaN" not in text
    rep = ev.report()
    assert "stick-slip" in rep and f"{ev.n_slips} slips" in rep
    # the staircase model reproduces the noise-free elongation at the frames
    clean = run5.sample(noise_nm=0)
    resid = ev.model_elongation() - clean.elongation
    assert np.sqrt(np.mean(resid**2)) < 0.2 * NOISE

    from identify.plots.events import plot_events

    ax = plot_events(ev)
    assert ax.get_xlabel() == "time (s)" and "µm" in ax.get_ylabel()
    import matplotlib.pyplot as plt

    plt.close(ax.figure)


def test_puller_and_block_arrays(run5):
    tr = run5.sample(noise_nm=90, seed=1)
    ev = extract_events(tr)
    np.testing.assert_allclose(ev.puller_m, STEP * ev.steps)
    np.testing.assert_allclose(ev.block_m, ev.puller_m - tr.elongation)
    # the simulator's puller position is Δxp·n(t)
    np.testing.assert_allclose(ev.puller_m, run5.puller_position(tr.time_s), atol=1e-15)


def test_an_ambiguous_trigger_names_its_other_step():
    """Measured case (OTS, k = 20.3 N/m, 30 µN, 30 Hz, noise seed 6): the two frames after
    slip 56 carry +98 and +222 nm of noise, the best split of the frames falls a step
    late, and the detector says which other step the frames nearly allow. Every other
    slip is detected at its true step."""
    from identify.traces.events import AMBIGUOUS_RSS

    run = simulate("OTS", spring_constant_N_per_m=20.3, normal_load_uN=30, step_frequency_Hz=30, travel_um=30,
                   stick_speed_m_per_s=1e-5)
    ev = extract_events(run.sample(noise_nm=90, seed=6))
    truth = run.slips["step_index"]
    det, alt, margin = (ev.slips[k] for k in ("trigger_step", "alt_trigger_step", "alt_margin"))
    assert len(det) == len(truth) == len(alt) == len(margin)
    wrong = np.flatnonzero(det != truth)
    assert wrong.tolist() == [56] and det[56] == truth[56] + 1
    assert alt[56] == truth[56] and margin[56] < AMBIGUOUS_RSS
    # few boundaries are ambiguous (measured: 5 of 80, median margin 25 σ²)
    assert np.sum(margin < AMBIGUOUS_RSS) <= 8 and np.median(margin) > 2 * AMBIGUOUS_RSS


@pytest.mark.parametrize("noise_nm", [1.0, 10.0, 90.0])
def test_a_slow_slip_caught_in_several_frames_is_one_slip(noise_nm):
    """A soft spring (2.13 N/m, 30 µN, 100 Hz) with a small gap μmax − μmin under the
    stick option slips slowly, over ~5 frames (2.5 steps): at low noise each of those
    frames got a level of its own, and every slip came out as five (54 slips for 9, the
    regime 'unresolved'); at 90 nm the noise grouped the first three into a segment of
    their own, and every slip came out as two (16 for 9: the bias of robustness set 8).
    The frames climb from one plateau to the next far faster than the block's average
    advance per step, in a run whose rests last ~50 frames: they are one slip's."""
    import warnings as _w

    truth = dict(mu_max=0.6308, mu_min=0.5476, tau=0.0474, A=0.0184)
    with _w.catch_warnings():
        _w.simplefilter("ignore")
        sim = simulate("FOTAS", spring_constant_N_per_m=2.13, normal_load_uN=30, step_frequency_Hz=100,
                       travel_um=20.0, stick_speed_m_per_s=1e-5, params=truth, initial_state=truth["mu_max"])
    ev = extract_events(sim.sample(noise_nm=noise_nm, seed=5, name="slow", frame_phase=0.75))
    assert ev.regime == "stick-slip" and ev.n_slips == len(sim.events) == 9
