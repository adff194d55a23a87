"""Tests of identify.traces.io: every rule of shared/TRACE_FORMAT.md, round trips, folders."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from identify.model.params import SPECS, normal_load_from_voltage
from identify.traces.io import FORMAT, Trace, TraceFormatError, TraceSet, load_traces

GOOD_META = {
    "format": FORMAT,
    "coating": "FOTAS",
    "spring_constant_N_per_m": 2.13,
    "normal_load_uN": 5.0,
    "step_frequency_Hz": 100.0,
    "step_size_nm": 46.0,
    "frame_rate_Hz": 200.0,
    "block_mass_kg": 3.64e-10,
    "device": "chip3-k213-a",
    "notes": "free text",
}
GOOD_CSV = "time_s,elongation_um\n0.000000,0.0000\n0.005000,0.0460\n0.010000,0.0920\n"


def put(folder: Path, stem: str, csv: str | None = GOOD_CSV, meta: dict | str | None = None) -> Path:
    """Write a run's files (``meta`` None: the good metadata; a str: raw JSON text)."""
    folder.mkdir(parents=True, exist_ok=True)
    if csv is not None:
        (folder / f"{stem}.csv").write_text(csv, encoding="utf-8")
    if meta is None:
        meta = GOOD_META
    if meta is not False:
        text = meta if isinstance(meta, str) else json.dumps(meta, indent=2)
        (folder / f"{stem}.json").write_text(text, encoding="utf-8")
    return folder / stem


def refused(tmp_path: Path, csv: str = GOOD_CSV, meta=None) -> TraceFormatError:
    stem = put(tmp_path, "run", csv, meta)
    with pytest.raises(TraceFormatError) as info:
        Trace.read(stem)
    return info.value


def meta_with(**changes) -> dict:
    m = dict(GOOD_META)
    for k, v in changes.items():
        if v is None:
            m.pop(k, None)
        else:
            m[k] = v
    return m


# ----------------------------------------------------------------------------- reading
def test_read_good_run_in_si(tmp_path):
    stem = put(tmp_path, "run07")
    for p in (stem, stem.with_suffix(".csv"), stem.with_suffix(".json"), str(stem)):
        tr = Trace.read(p)
        assert tr.name == "run07"
        assert tr.path == stem
        np.testing.assert_allclose(tr.time_s, [0.0, 0.005, 0.01])
        np.testing.assert_allclose(tr.elongation, [0.0, 46e-9, 92e-9], rtol=1e-12)
        assert tr.puller is None
    assert tr.spring_constant == 2.13
    assert tr.normal_load == pytest.approx(5e-6)
    assert tr.step_frequency == 100.0
    assert tr.step_size == pytest.approx(46e-9)
    assert tr.frame_rate == 200.0
    assert tr.block_mass == 3.64e-10
    assert tr.coating == "FOTAS" and tr.device == "chip3-k213-a"
    assert len(tr) == 3


def test_defaults_and_unknown_keys_kept(tmp_path):
    meta = meta_with(step_size_nm=None, block_mass_kg=None, frame_rate_Hz=None, coating=None,
                     device=None, operator="ada", extra={"a": [1, 2]})
    tr = Trace.read(put(tmp_path, "run", meta=meta))
    assert tr.step_size == SPECS["step_size"].nominal
    assert tr.block_mass == SPECS["mb"].nominal
    assert tr.coating is None and tr.device is None
    assert tr.metadata["operator"] == "ada" and tr.metadata["extra"] == {"a": [1, 2]}


def test_frame_rate_inferred_from_samples(tmp_path):
    t = np.arange(50) / 250.0
    csv = "time_s,elongation_um\n" + "".join(f"{x:.9f},0.1\n" for x in t)
    tr = Trace.read(put(tmp_path, "run", csv, meta_with(frame_rate_Hz=None)))
    assert tr.frame_rate == pytest.approx(250.0, rel=1e-9)


def test_comments_and_whitespace_tolerated(tmp_path):
    csv = "# camera 3\n  time_s , elongation_um \n# start\n0.0, 1.5\n0.1 ,2.5\n# end\n"
    tr = Trace.read(put(tmp_path, "run", csv))
    np.testing.assert_allclose(tr.elongation, [1.5e-6, 2.5e-6])


def test_crlf_line_endings(tmp_path):
    tr = Trace.read(put(tmp_path, "run", GOOD_CSV.replace("\n", "\r\n")))
    assert len(tr) == 3


# ----------------------------------------------------------------------------- CSV rules
def test_bad_header(tmp_path):
    err = refused(tmp_path, "# c\ntime,elongation_um\n0,0\n1,1\n")
    assert err.line == 2 and "header" in err.rule
    assert err.path.endswith("run.csv")
    assert str(err) == f"{err.path}:2: {err.rule}"


def test_missing_header(tmp_path):
    err = refused(tmp_path, "0.0,0.0\n0.1,0.1\n")
    assert err.line == 1 and "header" in err.rule


def test_text_cell(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,abc\n0.2,0.3\n")
    assert err.line == 3 and "not a number" in err.rule and "elongation_um" in err.rule


def test_blank_cell(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,\n0.2,0.3\n")
    assert err.line == 3 and "blank cell" in err.rule


def test_wrong_cell_count(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,0.2,0.3\n0.2,0.3\n")
    assert err.line == 3 and "expected 2 cells" in err.rule


def test_nan_and_inf_refused(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,0.2\n0.2,nan\n")
    assert err.line == 4 and "finite" in err.rule
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,-inf\n0.2,0.1\n")
    assert err.line == 3 and "finite" in err.rule


def test_duplicate_time(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,0.1\n0.1,0.2\n")
    assert err.line == 4 and "duplicate time" in err.rule


def test_decreasing_time_names_the_physical_line(tmp_path):
    csv = ("# recorded 2024-05-01\n# camera 3\ntime_s,elongation_um\n0.0,0.0\n"
           "# a comment between rows\n0.2,0.1\n0.1,0.2\n0.3,0.3\n")
    err = refused(tmp_path, csv)
    assert err.line == 7 and "decreasing time" in err.rule
    assert str(err).endswith(f"run.csv:7: {err.rule}")


def test_blank_line(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n\n0.1,0.1\n")
    assert err.line == 3 and err.rule == "blank line"


def test_first_offence_reported(tmp_path):
    # a text cell on line 3 comes before the decreasing time on line 5
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n0.1,x\n0.2,0.1\n0.1,0.2\n")
    assert err.line == 3


def test_too_few_rows(tmp_path):
    err = refused(tmp_path, "time_s,elongation_um\n0.0,0.0\n")
    assert "at least 2" in err.rule
    err = refused(tmp_path, "time_s,elongation_um\n# nothing\n")
    assert "at least 2" in err.rule


def test_empty_csv(tmp_path):
    err = refused(tmp_path, "")
    assert "empty" in err.rule


# ----------------------------------------------------------------------------- JSON rules
def test_missing_json(tmp_path):
    stem = put(tmp_path, "run", meta=False)
    with pytest.raises(TraceFormatError, match=r"run\.csv: missing run\.json"):
        Trace.read(stem)


def test_missing_csv(tmp_path):
    stem = put(tmp_path, "run", csv=None)
    with pytest.raises(TraceFormatError, match=r"run\.json: missing run\.csv"):
        Trace.read(stem)


def test_no_run_at_all(tmp_path):
    with pytest.raises(FileNotFoundError):
        Trace.read(tmp_path / "nothing")


def test_invalid_json_names_line(tmp_path):
    err = refused(tmp_path, meta='{\n  "format": "nanofrictor-trace/1",\n  "k": ,\n}\n')
    assert err.path.endswith("run.json") and err.line == 3 and "invalid JSON" in err.rule


def test_json_not_an_object(tmp_path):
    err = refused(tmp_path, meta="[1, 2]")
    assert "object" in err.rule


def test_bad_format_string(tmp_path):
    err = refused(tmp_path, meta=meta_with(format="nanofrictor-trace/2"))
    assert "format" in err.rule and err.line == 2
    err = refused(tmp_path, meta=meta_with(format=None))
    assert "format" in err.rule


def test_both_load_keys(tmp_path):
    err = refused(tmp_path, meta=meta_with(block_voltage_V=20.0))
    assert "exactly one" in err.rule


def test_neither_load_key(tmp_path):
    err = refused(tmp_path, meta=meta_with(normal_load_uN=None))
    assert "exactly one" in err.rule


def test_negative_spring_constant(tmp_path):
    err = refused(tmp_path, meta=meta_with(spring_constant_N_per_m=-2.13))
    assert "spring_constant_N_per_m" in err.rule and "> 0" in err.rule
    assert err.line == 4  # json.dumps(indent=2) puts it on line 4


@pytest.mark.parametrize("key", ["spring_constant_N_per_m", "step_frequency_Hz"])
def test_required_keys(tmp_path, key):
    err = refused(tmp_path, meta=meta_with(**{key: None}))
    assert key in err.rule and "missing" in err.rule


@pytest.mark.parametrize("key,value", [
    ("step_frequency_Hz", 0), ("step_size_nm", -46.0), ("frame_rate_Hz", "200"),
    ("block_mass_kg", True), ("normal_load_uN", -1.0),
])
def test_bad_numbers(tmp_path, key, value):
    err = refused(tmp_path, meta=meta_with(**{key: value}))
    assert key in err.rule


def test_nan_in_json_refused(tmp_path):
    text = json.dumps(GOOD_META, indent=2).replace('"normal_load_uN": 5.0', '"normal_load_uN": NaN')
    err = refused(tmp_path, meta=text)
    assert "NaN" in err.rule and err.line == 5


def test_duplicate_json_key(tmp_path):
    text = json.dumps(GOOD_META, indent=2)[:-2] + ',\n  "normal_load_uN": 6.0\n}'
    err = refused(tmp_path, meta=text)
    assert "duplicate key" in err.rule


def test_voltage_derived_load(tmp_path):
    tr = Trace.read(put(tmp_path, "run", meta=meta_with(normal_load_uN=None, block_voltage_V=7.15)))
    assert tr.normal_load == pytest.approx(0.98e-6, rel=0.02)
    assert tr.normal_load == normal_load_from_voltage(7.15)


def test_voltage_too_low(tmp_path):
    err = refused(tmp_path, meta=meta_with(normal_load_uN=None, block_voltage_V=0.5))
    assert isinstance(err, TraceFormatError) and "block_voltage_V" in err.rule


def test_error_is_picklable():
    err = TraceFormatError("a/run.csv", 7, "blank line")
    back = pickle.loads(pickle.dumps(err))
    assert (back.path, back.line, back.rule, str(back)) == ("a/run.csv", 7, "blank line", "a/run.csv:7: blank line")
    assert str(TraceFormatError("a/run.json", None, "x")) == "a/run.json: x"
    assert isinstance(err, ValueError)


# ----------------------------------------------------------------------------- writing
def _trace(n=200, puller=False, seed=0) -> Trace:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(1e-3, 1e-2, n))
    e = rng.normal(0.0, 1e-6, n)
    xp = np.cumsum(rng.uniform(0, 50e-9, n)) if puller else None
    return Trace("sim", t, e, xp, dict(GOOD_META))


@pytest.mark.parametrize("puller", [False, True])
def test_round_trip_exact_to_printed_precision(tmp_path, puller):
    tr = _trace(puller=puller)
    csv1, json1 = tr.write(tmp_path / "a" / "run1")
    assert csv1.name == "run1.csv" and json1.name == "run1.json" and tr.path == tmp_path / "a" / "run1"
    first_line = csv1.read_text().splitlines()[0]
    assert first_line == ("time_s,elongation_um,puller_um" if puller else "time_s,elongation_um")
    back = Trace.read(csv1)
    np.testing.assert_array_less(np.abs(back.time_s - tr.time_s), 0.5e-9 + 1e-15)
    np.testing.assert_array_less(np.abs(back.elongation - tr.elongation) * 1e6, 0.5e-6 + 1e-12)
    if puller:
        np.testing.assert_array_less(np.abs(back.puller - tr.puller) * 1e6, 0.5e-6 + 1e-12)
    else:
        assert back.puller is None
    assert back.metadata == tr.metadata
    csv2, json2 = back.write(tmp_path / "b" / "run1")
    assert csv2.read_bytes() == csv1.read_bytes()
    assert json2.read_bytes() == json1.read_bytes()


def test_json_layout(tmp_path):
    meta = {"zeta": 1, "notes": "n", "step_frequency_Hz": 100.0, "alpha": 2,
            "spring_constant_N_per_m": 2.13, "normal_load_uN": 5.0}
    tr = Trace("x", [0.0, 1.0], [0.0, 1e-6], None, meta)
    _, jp = tr.write(tmp_path / "x")
    text = jp.read_text()
    assert text.startswith('{\n  "format": "nanofrictor-trace/1",\n')
    assert list(json.loads(text)) == ["format", "spring_constant_N_per_m", "normal_load_uN",
                                      "step_frequency_Hz", "notes", "alpha", "zeta"]


def test_write_refuses_bad_metadata(tmp_path):
    tr = _trace()
    tr.metadata["spring_constant_N_per_m"] = 0.0
    with pytest.raises(TraceFormatError, match="spring_constant"):
        tr.write(tmp_path / "bad")
    assert not (tmp_path / "bad.csv").exists()


def test_write_refuses_times_closer_than_precision(tmp_path):
    tr = Trace("x", [0.0, 1e-10, 1.0], [0.0, 0.0, 0.0], None, dict(GOOD_META))
    with pytest.raises(TraceFormatError, match="1 ns"):
        tr.write(tmp_path / "x")


def test_construction_checks_samples():
    with pytest.raises(TraceFormatError, match="strictly increase"):
        Trace("x", [0.0, 0.0], [0.0, 0.0], None, dict(GOOD_META))
    with pytest.raises(TraceFormatError, match="length"):
        Trace("x", [0.0, 1.0], [0.0], None, dict(GOOD_META))
    with pytest.raises(TraceFormatError, match="non-finite"):
        Trace("x", [0.0, 1.0], [0.0, np.nan], None, dict(GOOD_META))


def test_large_file(tmp_path):
    n = 100_000
    t = np.arange(n) / 200.0
    e = 1e-6 * np.sin(t)
    Trace("big", t, e, None, dict(GOOD_META)).write(tmp_path / "big")
    tr = Trace.read(tmp_path / "big")
    assert len(tr) == n and tr.frame_rate == 200.0
    # an error near the end of a large file is found by the line-by-line scan
    lines = (tmp_path / "big.csv").read_text().splitlines()
    lines[n - 10] = lines[n - 10].split(",")[0] + ",oops"
    (tmp_path / "big.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(TraceFormatError) as info:
        Trace.read(tmp_path / "big")
    assert info.value.line == n - 9


# ----------------------------------------------------------------------------- folders
def test_folder_with_one_bad_run(tmp_path):
    for name in ("run01", "run02", "run04"):
        put(tmp_path, name)
    put(tmp_path, "run03", "time_s,elongation_um\n0.0,0.0\n0.1,bad\n0.2,0.0\n")
    (tmp_path / "summary.json").write_text("{}")  # lone JSON: not a run, ignored
    ts = load_traces(tmp_path)
    assert isinstance(ts, TraceSet)
    assert ts.names == ["run01", "run02", "run04"] and len(ts) == 3
    assert len(ts.errors) == 1
    err = ts.errors[0]
    assert err.path.endswith("run03.csv") and err.line == 3
    report = ts.report()
    assert "run01" in report and "run03.csv:3" in report and "refused 1 run" in report
    assert [tr.name for tr in ts] == ts.names and ts["run02"].name == "run02"


def test_folder_lone_csv_reported(tmp_path):
    put(tmp_path, "run01")
    put(tmp_path, "run02", meta=False)
    ts = load_traces(tmp_path)
    assert ts.names == ["run01"]
    assert "missing run02.json" in str(ts.errors[0])


def test_mixed_paths_each_stem_once(tmp_path):
    a = put(tmp_path / "d", "a")
    put(tmp_path / "d", "b")
    ts = load_traces([a.with_suffix(".csv"), tmp_path / "d", str(a), a.with_suffix(".json")])
    assert ts.names == ["a", "b"] and not ts.errors


def test_recursive(tmp_path):
    put(tmp_path / "x", "r1")
    put(tmp_path / "x" / "sub", "r2")
    assert load_traces(tmp_path / "x").names == ["r1"]
    assert load_traces(tmp_path / "x", recursive=True).names == ["r1", "r2"]


def test_empty_folder_and_missing_path(tmp_path):
    ts = load_traces(tmp_path)
    assert len(ts) == 0 and ts.errors == [] and "loaded 0 runs" in ts.report()
    with pytest.raises(FileNotFoundError, match="nope"):
        load_traces([tmp_path / "nope"])


def test_non_trace_file_refused(tmp_path):
    (tmp_path / "readme.txt").write_text("hi")
    ts = load_traces(tmp_path / "readme.txt")
    assert len(ts) == 0 and "not a trace file" in str(ts.errors[0])


# ----------------------------------------------------------------------------- simulation
def test_from_simulation_round_trip(tmp_path):
    import identify

    res = identify.simulate("FOTAS", spring_constant_N_per_m=2.13, step_frequency_Hz=100.0,
                            travel_um=2, normal_load_uN=5.0)
    tr = res.sample(noise_nm=1.0, seed=3, name="sim01")
    m = tr.metadata
    assert tr.name == "sim01" and list(m)[0] == "format" and m["format"] == FORMAT
    assert m["coating"] == "FOTAS" and m["spring_constant_N_per_m"] == 2.13
    assert m["normal_load_uN"] == 5.0 and m["step_size_nm"] == 46.0
    assert m["frame_rate_Hz"] == 200.0 and m["block_mass_kg"] == res.parameters["mb"]
    sim = m["simulation"]
    assert sim["law"] == "exponential" and sim["regime"] == res.regime
    assert sim["n_slips"] == len(res.events) and sim["parameters"]["tau"] == res.parameters["tau"]
    assert tr.normal_load == pytest.approx(res.conditions.normal_load, rel=1e-12)
    tr.write(tmp_path / "sim01")
    back = Trace.read(tmp_path / "sim01")
    assert back.metadata == tr.metadata
    np.testing.assert_allclose(back.elongation, tr.elongation, atol=0.5e-12 + 1e-18)
    np.testing.assert_allclose(back.time_s, tr.time_s, atol=0.5e-9)
    extra = Trace.from_simulation(res, tr.time_s, tr.elongation, extra={"device": "sim", "notes": None})
    assert extra.device == "sim" and "notes" not in extra.metadata
