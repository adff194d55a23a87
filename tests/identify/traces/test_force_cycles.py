"""Stick-slip or inertial oscillation, read from a force record under a constant drive."""

import numpy as np
import pytest

from identify.traces.force_cycles import CycleAnalysis, analyze_cycles

RATE = 0.05  # k·V/N, per s
DT = 5e-4


def _sawtooth(drop, period, seconds=60.0, slip_s=0.02, seed=0, noise=1e-3, spikes=True):
    """Loading at RATE for (period − slip_s), a linear drop of ``drop`` over slip_s;
    white noise and, with ``spikes``, single-sample impulses of ±0.02 (as paper does)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, seconds, DT)
    phase = np.mod(t, period)
    up = period - slip_s
    f = np.where(phase < up, RATE * phase, RATE * up - drop * (phase - up) / slip_s)
    f = 0.3 + f + rng.normal(0, noise, t.size)
    if spikes:
        at = rng.choice(t.size, t.size // 500, replace=False)
        f[at] += rng.choice([-0.02, 0.02], at.size)
    return t, f


@pytest.mark.parametrize("seed", [0, 1])
def test_a_sawtooth_is_stick_slip_with_its_drops_and_period(seed):
    period = 1.2
    drop = RATE * (period - 0.02)  # the force comes back to where each cycle began
    t, f = _sawtooth(drop, period, seed=seed)
    c = analyze_cycles(t, f, drive_rate=RATE)
    assert c.regime == "stick-slip" and c.rising_fraction > 0.9 and c.stuck_fraction > 0.8
    assert c.mean_drop == pytest.approx(drop, rel=0.1)
    assert c.mean_period == pytest.approx(period, rel=0.02)
    assert c.rise_rate == pytest.approx(RATE, rel=0.1)
    assert c.noise == pytest.approx(1e-3, rel=0.2)  # (the impulses do not count as noise)


def test_an_oscillation_is_inertial_with_its_period():
    t = np.arange(0, 10, DT)
    f = 0.3 + 0.05 * np.sin(2 * np.pi * t / 0.08) + np.random.default_rng(2).normal(0, 1e-3, t.size)
    c = analyze_cycles(t, f, drive_rate=2.0)
    assert c.regime == "inertial" and abs(c.rising_fraction - 0.5) < 0.05
    assert c.mean_period == pytest.approx(0.08, rel=0.02) and c.drops.size == 0
    flat = analyze_cycles(t, 0.3 + np.random.default_rng(3).normal(0, 1e-3, t.size), drive_rate=2.0)
    assert flat.regime == "steady"
    assert analyze_cycles(t, np.full(t.size, 0.3), drive_rate=2.0).regime == "steady"  # (noiseless)


def test_the_analysis_reports_and_round_trips(tmp_path, strict_json):
    t, f = _sawtooth(0.04, 1.0, seconds=20)
    c = analyze_cycles(t, f, drive_rate=RATE, name="saw")
    assert c.report().startswith("saw: stick-slip (the force rises")
    back = CycleAnalysis.load(c.save(tmp_path / "c.json"))
    strict_json(tmp_path / "c.json")
    assert back.to_dict() == c.to_dict() and back.report() == c.report()
    import matplotlib

    matplotlib.use("Agg")
    ax = back.plot()
    assert ax.get_xlabel() == "time until the next slip (s)" and len(ax.lines) == 2
    t_osc = np.arange(0, 5, DT)
    osc = analyze_cycles(t_osc, 0.3 + 0.05 * np.sin(2 * np.pi * t_osc / 0.08), drive_rate=2.0)
    assert osc.plot().get_xlabel() == "oscillation period (ms)"
    import matplotlib.pyplot as plt

    plt.close("all")
    with pytest.raises(ValueError, match="drive_rate = 0 must be > 0"):
        analyze_cycles(t, f, drive_rate=0)
    with pytest.raises(ValueError, match="time increasing"):
        analyze_cycles(t[::-1], f, drive_rate=RATE)


def test_an_upward_crossing_counts_once_through_the_hysteresis_band():
    """Noise that wanders about the median inside the band, or dips into it from above,
    adds no crossing: a crossing is a sample above the band whose last sample outside it
    was below."""
    from identify.traces.force_cycles import _oscillation_periods

    f = np.array([0.0, 0.0, 2.0, 0.9, 1.1, 2.0, 0.0, 1.05, 0.95, 2.0, 2.0, 0.0, 2.0])
    t = np.arange(f.size, dtype=float)
    # median 1.05, band [0.75, 1.35]: ups at t = 2, 9, 12
    np.testing.assert_array_equal(_oscillation_periods(t, f, hysteresis=0.3), [7.0, 3.0])
    assert _oscillation_periods(t[:3], f[:3], 0.3).size == 0  # one crossing: no period
