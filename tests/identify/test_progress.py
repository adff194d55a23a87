"""Progress of long calls: counted stages with the time left, a bar on a terminal, the
log elsewhere, silence on request."""

import io
import logging
import os
import pty
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest

from identify import SimulationOptions, simulate
from identify.fitting.driver import FitOptions, fit
from identify.progress import ProgressEvent, Stage, TerminalReporter, cli_reporter, reporter

ROOT = Path(__file__).resolve().parents[2]


def test_event_reads_as_its_message_with_count_and_time_left():
    ev = ProgressEvent("profile of tau: tau held at 0.07", "profile of tau", 3, 12, 30.0)
    assert isinstance(ev, str) and ev.startswith("profile of tau: tau held at 0.07")
    assert ev.eta_s == pytest.approx(90.0)  # 10 s an item so far, 9 left
    assert str(ev).endswith("[3/12, 30 s, about 90 s left]")
    assert ProgressEvent("loading").eta_s is None and str(ProgressEvent("loading")) == "loading"
    assert str(ProgressEvent("x", "x", 4, 4, 200.0)).endswith("[4/4, 3 min]")  # done: no time left
    assert ProgressEvent("x", "x", 0, 4, 0.0).eta_s is None  # nothing to go by yet


def test_stage_counts_to_its_total():
    said = []
    st = Stage(said.append, "round 1", 3)
    st.start("3 refits")
    for name in ("a", "b", "c"):
        st.advance(name)
    assert [(m.done, m.total) for m in said] == [(0, 3), (1, 3), (2, 3), (3, 3)]
    assert said[2].message == "round 1: b" and said[-1].eta_s == 0.0
    Stage(None, "silent", 2).advance()  # no callback: nothing to say, no error


def test_reporter_choices(caplog):
    assert reporter(False) is None
    f = print
    assert reporter(f) is f
    with pytest.raises(TypeError, match="progress = 3"):
        reporter(3)
    # under pytest stderr is captured, not a terminal: the log at INFO
    say = reporter(None)
    with caplog.at_level(logging.INFO, logger="identify"):
        say("hello")
    assert "hello" in caplog.text


def test_terminal_reporter_draws_a_bar_per_stage_and_lines_for_the_rest(monkeypatch):
    buf = io.StringIO()
    monkeypatch.setattr(sys, "stderr", buf)
    rep = TerminalReporter("[fit] ")
    rep("loading 2 inputs")
    st = Stage(rep, "solver starts", 2)
    st.start()
    st.advance("start 1 of 2: Solve_Succeeded")
    assert "solver starts" in rep.bars
    st.advance("start 2 of 2: Solve_Succeeded")
    assert not rep.bars  # closed at its total
    out = buf.getvalue()
    assert "[fit] loading 2 inputs" in out and "[fit] solver starts" in out and "2/2" in out


@pytest.fixture(scope="module")
def two_runs():
    runs = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i, (k, nb, fp) in enumerate([(2.13, 5, 100), (20.3, 30, 30)]):
            r = simulate("FOTAS", spring_constant_N_per_m=k, normal_load_uN=nb, step_frequency_Hz=fp, travel_um=10,
                         stick_speed_m_per_s=1e-5, options=SimulationOptions(record=False))
            runs.append(r.sample(noise_nm=90, seed=i, name=f"r{i}"))
    return runs


def test_fit_and_profile_report_counted_stages(two_runs):
    said = []
    res = fit(two_runs, options=FitOptions(fixed={"v_stick": 1e-5}, multistart=2, seed=1), progress=said.append)
    starts = [m for m in said if getattr(m, "stage", None) == "solver starts"]
    assert [(m.done, m.total) for m in starts] == [(0, 3), (1, 3), (2, 3), (3, 3)]
    assert starts[1].eta_s is not None and starts[-1].eta_s == 0.0
    said = []
    res.profile("tau", n_points=5, progress=said.append)
    prof = [m for m in said if getattr(m, "stage", None) == "profile of tau"]
    assert prof and all(m.done <= m.total for m in prof)
    assert prof[-1].done == prof[-1].total  # the estimate of the points to solve came true
    assert [m.done for m in prof] == list(range(1, len(prof) + 1))


def test_fit_is_silent_on_request(two_runs, caplog):
    with caplog.at_level(logging.INFO, logger="identify"):
        fit(two_runs[:1], options=FitOptions(fixed={"v_stick": 1e-5}), progress=False)
    assert not [r for r in caplog.records if r.name == "identify"]


def test_cli_reporter_writes_lines_with_the_time_left_off_a_terminal(capsys):
    say = cli_reporter("[diagnose] ")
    st = Stage(say, "diagnosis round 1", 2)
    st.advance("drift (Solve_Succeeded)")
    err = capsys.readouterr().err
    assert err.startswith("[diagnose] diagnosis round 1: drift (Solve_Succeeded) [1/2, ")
    assert "left]" in err


@pytest.mark.skipif(not hasattr(pty, "openpty") or sys.platform == "win32", reason="needs a pseudo-terminal")
def test_a_script_on_a_terminal_shows_a_bar(tmp_path):
    """A user's script that calls ``fit`` with no progress argument, in a terminal, sees
    a bar (tqdm's) for the solver starts and the fit's messages: not minutes of silence."""
    script = tmp_path / "s.py"
    script.write_text(textwrap.dedent(f"""
        import identify
        identify.fit([{str(ROOT / 'data' / 'FOTAS' / 'FOTAS_k2.13_Nb5uN_fp100Hz.csv')!r}],
                     options=identify.FitOptions(fixed={{"v_stick": 1e-5}}, multistart=1, seed=0))
    """))
    leader, follower = pty.openpty()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "100"}
    proc = subprocess.Popen([sys.executable, str(script)], stdin=follower, stdout=follower, stderr=follower,
                            env=env, cwd=tmp_path)
    os.close(follower)
    chunks = []
    while True:
        try:
            data = os.read(leader, 4096)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    proc.wait(timeout=300)
    os.close(leader)
    out = b"".join(chunks).decode("utf-8", "replace")
    assert proc.returncode == 0, out
    assert "loading 1 input(s)" in out
    assert "solver starts" in out and "2/2" in out and "100%" in out
