"""The identify CLI: simulate writes the trace and the summary; bad input exits 2 with one
line naming the parameter and the rule, never a traceback."""

import pathlib
import subprocess
import sys

import pytest

from identify.cli import main

BASE = ["simulate", "--coating", "FOTAS", "--spring-constant", "2.13", "--normal-load-uN", "5",
        "--fp", "100", "--travel-um", "5"]


def test_help_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "identify", "--help"], capture_output=True, text=True).stdout
    for cmd in ("demo", "simulate", "regimes", "analyze", "fit", "bench"):
        assert cmd in out


def test_simulate_writes_trace_and_summary(tmp_path, capsys, strict_json):
    out = tmp_path / "runs" / "r1"
    code = main(BASE + ["--noise-nm", "90", "--seed", "1", "--stick-speed", "1e-5", "--out", str(out),
                        "--json", str(tmp_path / "summary.json"), "--plot"])
    assert code == 0
    assert out.with_suffix(".csv").exists() and out.with_suffix(".json").exists()
    assert (tmp_path / "runs" / "r1_fig13.png").exists()
    s = strict_json(tmp_path / "summary.json")
    strict_json(out.with_suffix(".json"))  # the trace's metadata
    for key in ("n_slips", "regime", "slip_lengths_um", "peak_elongations_um", "peak_slip_speed_m_per_s",
                "mean_rest_time_s", "wall_time_s"):
        assert key in s
    assert s["regime"] == "stick-slip" and s["n_slips"] >= 1


def test_simulate_never_replaces_files_unasked(tmp_path, capsys):
    out = tmp_path / "r1"
    assert main(BASE + ["--out", str(out), "--plot"]) == 0
    before = out.with_suffix(".csv").read_bytes()
    capsys.readouterr()
    assert main(BASE + ["--out", str(out), "--seed", "2", "--noise-nm", "90"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already exist" in err and "--overwrite" in err and str(out) in err
    assert out.with_suffix(".csv").read_bytes() == before  # refused before simulating
    # the figure alone (a new stem's plot would land on an old figure) is also refused
    (out.parent / "r2_fig13.png").write_bytes(b"x")
    assert main(BASE + ["--out", str(out.parent / "r2"), "--plot"]) == 2
    assert "r2_fig13.png" in capsys.readouterr().err
    assert main(BASE + ["--out", str(out), "--seed", "2", "--noise-nm", "90", "--overwrite"]) == 0
    assert out.with_suffix(".csv").read_bytes() != before


@pytest.mark.parametrize("change, words", [
    (["--spring-constant", "-1"], ["spring", "> 0"]),
    (["--fp", "nan"], ["step_frequency", "finite"]),
    (["--law", "power"], ["power"]),
    (["--param", "mu_min=0.9"], ["mu_min", "mu_max"]),
    (["--param", "bogus=1"], ["bogus"]),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, change, words):
    argv = list(BASE)
    if change[0] in argv:
        i = argv.index(change[0])
        argv[i + 1] = change[1]
    else:
        argv += change
    code = main(argv + ["--out", str(tmp_path / "x")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert "Traceback" not in err and err.startswith("error:"), err
    for w in words:
        assert w.lower() in err.lower(), (w, err)


def test_travel_beyond_range_warns(tmp_path, capsys):
    argv = [a if a != "5" or i != BASE.index("--travel-um") + 1 else "120" for i, a in enumerate(BASE)]
    code = main(argv + ["--out", str(tmp_path / "long")])
    assert code == 0 and "warning" in capsys.readouterr().err.lower()


def test_an_internal_error_is_not_blamed_on_the_input(monkeypatch, capsys):
    """A bug of ours that raises a ValueError from a builtin (the diagnosis once died
    with ``error: min() arg is an empty sequence`` and exit 2, as if the input were bad)
    is reported as the toolkit's fault: exit 4, one line, the traceback in a file."""
    import identify.cli as cli

    def broken(args):
        return min([])

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    for action in parser._subparsers._group_actions[0].choices.values():
        action.set_defaults(func=broken)
    code = cli.main(["fit", "nowhere", "--json", "unused.json"])
    err = capsys.readouterr().err
    assert code == 4
    assert err.startswith("internal error (a fault of nanofrictor, not of your input): ValueError")
    assert "Traceback" not in err
    path = err.split("traceback in ")[1].split(";")[0]
    assert "min() arg is an empty sequence" in open(path).read()


def test_an_error_raised_on_purpose_blames_the_input(capsys):
    import identify.cli as cli

    code = cli.main(["fit", "/no/such/folder/anywhere", "--json", "unused.json"])
    err = capsys.readouterr().err
    assert code == 2 and "error: /no/such/folder/anywhere" in err and "internal" not in err


def test_sequence_passes_are_read_and_a_bad_one_is_named(capsys):
    import argparse

    import identify.cli as cli

    def options(text):
        ns = argparse.Namespace(free=None, fix=None, bound=None, start=None, law=None, free_offset=False,
                                multistart=0, seed=None, solver="ipopt", trigger="uniform",
                                sequence_trials=None, sequence_passes=text, stick_speed="check")
        return cli._fit_options(ns).sequence_passes

    assert options(None) == ("triggers", "missed", "batch", "ambiguous", "misfit")
    assert options("none") == () and options("misfit, batch") == ("misfit", "batch")
    data = str(pathlib.Path(__file__).resolve().parents[2] / "data" / "FOTAS")
    code = cli.main(["fit", data, "--sequence-passes", "triggers,bogus", "--json", "unused.json"])
    err = capsys.readouterr().err
    assert code == 2 and "'bogus' is not a pass" in err and "Traceback" not in err


def test_fit_of_only_bad_runs_names_each_file_once(tmp_path, capsys):
    (tmp_path / "r1.csv").write_text("time_s,elongation_m\n0,1e-6\n")
    (tmp_path / "r1.json").write_text('{"format": "nanofrictor-trace/1"}')
    assert main(["fit", str(tmp_path), "--json", str(tmp_path / "f.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("error: no run could be used: ") and err.count("r1.json") == 1


def test_the_demo_fits_the_bundled_data_with_the_fit_commands_defaults(tmp_path, capsys, strict_json):
    """The README's first command: the bundled FOTAS set fitted with the fit command's own
    defaults (a hand-kept copy of them once kept the old solver), the report printed and
    the JSON and figures written (measured: 12 s, 11 Ipopt iterations, χ² 10441.2)."""
    code = main(["demo", "--out", str(tmp_path / "demo")])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "Fit converged" in out and "solver             = Ipopt" in out
    js = strict_json(tmp_path / "demo" / "fit.json")
    assert js["solver"]["method"].startswith("Ipopt") and js["solver"]["success"]
    assert any((tmp_path / "demo" / "figures").glob("*.png"))


def test_the_exposure_alignment_is_given_by_name_and_the_drop_frames_asked_for(capsys):
    import argparse

    import identify.cli as cli

    def options(fix, drop=True):
        ns = argparse.Namespace(free="mu_max,exposure", fix=fix, bound=None, start=None, law=None, free_offset=False,
                                drop_frames=drop, multistart=0, seed=None, solver="ipopt", trigger="uniform",
                                sequence_trials=None, sequence_passes=None, stick_speed="check")
        return cli._fit_options(ns)

    o = options(["exposure_align=end,v_stick=1e-5"])
    assert o.fixed == {"exposure_align": 1.0, "v_stick": 1e-5} and o.drop_frames
    assert options(["exposure_align=0.25"]).fixed == {"exposure_align": 0.25}
    with pytest.raises(cli.CLIError, match="start, centre, end"):
        options(["exposure_align=middle"])
    with pytest.raises(cli.CLIError, match="is not a number"):
        options(["tau=end"])
    data = str(pathlib.Path(__file__).resolve().parents[2] / "data" / "FOTAS")
    code = cli.main(["fit", data, "--fix", "exposure_align=sideways", "--json", "unused.json"])
    err = capsys.readouterr().err
    assert code == 2 and "exposure_align" in err and "Traceback" not in err
