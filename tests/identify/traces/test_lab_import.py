"""Lab recordings into traces: velocity steps found in a load-point displacement, the
continuous drive in the trace format, and what the MEMS tools say of such a run."""

import json

import numpy as np
import pytest

from identify.traces.io import Trace, TraceFormatError
from identify.traces.lab_import import detect_velocity_steps, import_run
from identify.traces.look import Channel, LookFile


def _displacement(times, vels, t):
    x = np.zeros_like(t)
    edges = list(times) + [np.inf]
    for i, v in enumerate(vels):
        x += v * np.clip(np.minimum(t, edges[i + 1]) - edges[i], 0, None)
    return x


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_velocity_steps_and_a_hold_are_found_where_they_are(seed):
    """Steps 1 → 10 µm/s, a hold, and 3 µm/s, with 0.08 µm quantisation and noise and a
    sampling rate that rises after the step (as labs record): the changes within a
    sample or two, the velocities within their standard errors' reach, the hold as 0."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([np.arange(0, 30, 0.1), np.arange(30, 50, 0.01), np.arange(50, 80, 0.1)])
    times, vels = (0.0, 20.0, 40.0, 60.0), (1.0, 10.0, 0.0, 3.0)
    x = _displacement(times, vels, t) + rng.normal(0, 0.05, t.size)
    x = np.round(x / 0.08) * 0.08
    drive, ses = detect_velocity_steps(t, x)
    assert len(drive.times_s) == 4
    np.testing.assert_allclose(drive.times_s[1:], times[1:], atol=0.25)
    for got, want, se in zip(drive.velocities_um_per_s, vels, ses):
        assert got == want if want == 0 else abs(got - want) < max(5 * se, 0.02 * want)


@pytest.mark.parametrize("change", [20.0, 20.037, 20.081])
def test_a_change_between_samples_is_placed_between_them(change):
    """A step 2 → 20 µm/s at 100 Hz, noiseless, falling on a sample or between two: placed
    to within a hundredth of a sample, not on the sample grid (half a sample off, a few
    per cent of a transient's time scale, moved the p655 fit's misfit by 4 %); with the
    noise of a lab's load point (0.4 µm at 22 µm/s) within a sample."""
    t = np.arange(0, 40, 0.01)
    x = _displacement((0.0, change), (2.0, 20.0), t)
    drive, _ = detect_velocity_steps(t, x)
    assert abs(drive.times_s[1] - change) < 1e-4, drive.times_s
    noisy = x + np.random.default_rng(0).normal(0, 0.4, t.size)
    drive, _ = detect_velocity_steps(t, noisy)
    assert abs(drive.times_s[1] - change) < 0.01, drive.times_s


def _lab_file():
    t = np.concatenate([np.arange(0, 20, 0.1), np.arange(20, 40, 0.01)])
    lp = _displacement((0.0, 20.0), (2.0, 20.0), t)
    mu = 0.6 + 0.001 * (t > 20)
    f = LookFile(title="lab1", path="lab1.look")
    f.channels = [Channel("Time", "s", t), Channel("mu", ".", mu), Channel("LP_disp", "um", lp)]
    return f


def test_an_imported_run_is_a_trace_with_its_drive_and_says_what_it_assumed(tmp_path):
    imp = import_run(_lab_file(), friction="mu", time="Time", load_point="LP_disp", stiffness_per_um=2e-3,
                     velocities_um_per_s=[2, 20], name="lab1")
    tr = imp.trace
    assert tr.drive.velocities_um_per_s == (2.0, 20.0) and abs(tr.drive.times_s[1] - 20.0) < 0.05
    assert tr.normal_load == pytest.approx(1.0)  # (1 N, said)
    assert any("normal load not given" in a for a in imp.assumptions)
    assert any("velocities taken as given" in a for a in imp.assumptions)
    # friction comes back as k·e/Nb
    np.testing.assert_allclose(tr.elongation * 1e6 * 2e-3, _lab_file()["mu"].values, rtol=1e-12)
    tr.write(tmp_path / "lab1")
    back = Trace.read(tmp_path / "lab1")
    assert back.drive == tr.drive and "load point at 2 -> 20 µm/s" in repr(back)
    assert json.loads((tmp_path / "lab1.json").read_text())["imported"]["source"] == "lab1.look"
    with pytest.raises(ValueError, match="3 velocities given for the 2 stretch"):
        import_run(_lab_file(), friction="mu", time="Time", load_point="LP_disp", stiffness_per_um=2e-3,
                   velocities_um_per_s=[2, 20, 3])
    with pytest.raises(ValueError, match="stiffness_per_um = 0"):
        import_run(_lab_file(), friction="mu", time="Time", load_point="LP_disp", stiffness_per_um=0)


def _meta(**over):
    meta = {"format": "nanofrictor-trace/1", "spring_constant_N_per_m": 1.0, "normal_load_uN": 1e3,
            "drive": {"kind": "velocity_steps", "times_s": [0, 1], "velocities_um_per_s": [1, 10]},
            "outside_platform_ranges": True}
    meta.update(over)
    return {k: v for k, v in meta.items() if v is not None}


@pytest.mark.parametrize("over, rule", [
    (dict(step_frequency_Hz=10.0), "not both"),
    (dict(drive=None), "missing required key 'step_frequency_Hz' \\(or 'drive'"),
    (dict(drive={"kind": "ramp"}), "drive must be"),
    (dict(drive={"kind": "velocity_steps", "times_s": [1, 0], "velocities_um_per_s": [1, 2]}), "times increasing"),
    (dict(drive={"kind": "velocity_steps", "times_s": [0], "velocities_um_per_s": [-1]}), ">= 0"),
])
def test_a_drive_that_breaks_the_format_is_refused_with_the_rule(over, rule):
    with pytest.raises(TraceFormatError, match=rule):
        Trace("r", np.arange(3.0), np.zeros(3), None, _meta(**over))


def test_the_stick_slip_tools_say_a_continuous_run_is_not_theirs():
    from identify.traces.events import extract_events

    tr = Trace("lab", np.arange(3.0), np.zeros(3), None, _meta())
    with pytest.raises(ValueError, match="'lab' has a continuous drive.*rate-and-state"):
        extract_events(tr)
