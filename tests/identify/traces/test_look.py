"""Lab recordings: the binary look format, plain text tables, and the lab's reduction
recipe run with xlook's conventions."""

import struct
from pathlib import Path

import numpy as np
import pytest

from identify.traces.look import LookFormatError, read_look, read_table
from identify.traces.look_recipe import RecipeError, apply_recipe

P655 = Path(__file__).resolve().parents[3] / "data" / "real" / "p655"


def write_look(path, columns, names, units, title="test", descriptors=32):
    """A look file as xlook writes its float32 kind: title, big-endian counts, 32
    channel descriptors of 84 bytes, then each column as big-endian float32."""
    n = len(columns[0])
    head = title.encode().ljust(20, b"\0") + struct.pack(">iiif", n, len(columns), 0, 0.0)
    for i in range(descriptors):
        if i < len(columns):
            head += struct.pack(">13s13sf50si", names[i].encode(), units[i].encode(), 1.0, b"", n)
        else:
            head += struct.pack(">13s13sf50si", b"no_val", b"no_val", 0.0, b"none", 0)
    body = b"".join(np.asarray(c, ">f4").tobytes() for c in columns)
    Path(path).write_bytes(head + body)


def test_a_look_file_reads_back_its_columns(tmp_path):
    cols = [np.arange(5.0), np.linspace(-1, 1, 5), np.array([1e3, 2e3, 3e3, 4e3, 5e3])]
    write_look(tmp_path / "r", cols, ["Time", "disp", "load"], ["sec", "um", "bits"], title="p1")
    f = read_look(tmp_path / "r")
    assert f.title == "p1" and f.n_rows == 5 and [c.name for c in f.channels] == ["Time", "disp", "load"]
    for c, want in zip(f.channels, cols):
        np.testing.assert_array_equal(c.values, np.asarray(want, np.float32))
    assert f["DISP"].units == "um" and f[2].name == "load"
    with pytest.raises(KeyError, match="no channel named 'mu'.*Time, disp, load"):
        f["mu"]
    assert "3 channels" in f.describe()


def test_a_file_that_is_not_a_look_file_is_refused_with_its_name(tmp_path):
    short = tmp_path / "short"
    short.write_bytes(b"x" * 100)
    with pytest.raises(LookFormatError, match="short.*shorter than a look file's header"):
        read_look(short)
    write_look(tmp_path / "cut", [np.arange(1000.0)], ["Time"], ["s"])
    data = (tmp_path / "cut").read_bytes()
    (tmp_path / "cut").write_bytes(data[:-8])
    with pytest.raises(LookFormatError, match="runs past the end of the file"):
        read_look(tmp_path / "cut")
    bad = bytearray(data)
    bad[24:28] = struct.pack(">i", 99)  # 99 channels
    (tmp_path / "bad").write_bytes(bytes(bad))
    with pytest.raises(LookFormatError, match="99 channels"):
        read_look(tmp_path / "bad")


def test_the_p655_recording_reads_as_the_lab_describes_it():
    f = read_look(P655 / "p655intact100l")
    assert f.title == "p655intact100" and f.n_rows == 86814
    assert [c.name for c in f.channels] == ["Time", "Vert_Disp", "Vert_Load", "Hor_Disp", "Hor_Load."]
    assert f[0].values[0] == 10000.0  # the first sample period, in 1e-4 s


def test_a_text_table_reads_with_its_header_and_units(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# a comment\ntime [s]\tmu\tLP_disp_um\n0\t0.5\t0\n0.1\t0.51\t0.2\n0.2, 0.52, 0.4\n")
    f = read_table(p)
    assert [c.name for c in f.channels] == ["time", "mu", "LP_disp_um"] and f["time"].units == "s"
    np.testing.assert_allclose(f["mu"].values, [0.5, 0.51, 0.52])
    p.write_text("t mu\n0 0.5\n0.1 oops\n")
    with pytest.raises(LookFormatError, match=r"t.txt, line 3: 'oops' is not a number"):
        read_table(p)
    p.write_text("0 0.5\n0.1 0.5 3\n")
    with pytest.raises(LookFormatError, match="line 2: 3 columns where the table has 2"):
        read_table(p)


def _look(tmp_path, *cols):
    write_look(tmp_path / "r", list(cols), [f"c{i + 1}" for i in range(len(cols))], ["u"] * len(cols))
    return read_look(tmp_path / "r")


def test_recipe_commands_follow_xlooks_conventions(tmp_path):
    """Columns from 1, rows from 0, ranges inclusive, -1 the last row; '=' a number and
    ':' a column; zero subtracts one row's value from the whole column; offset_int holds
    r1..r2 at x[r1] and shifts the rest; a removed column leaves a gap."""
    x = np.array([1.0, 2, 4, 8, 16, 32])
    y = np.array([2.0, 2, 2, 2, 2, 2])
    look = _look(tmp_path, x, y)
    out = apply_recipe(look, "math 1 * 3 = 3 triple u\nmath 1 / 2 : 4 ratio .\n"
                             "math_int 1 * 0.0 = 5 1 2 part .\nzero 2,0\nr_col 2\n")
    np.testing.assert_allclose(out[2].values, 3 * x)
    np.testing.assert_allclose(out[3].values, x / y)
    assert out[3].name == "ratio"
    np.testing.assert_allclose(out[4].values, [0, 0, 0, 0, 0, 0])  # (a new column: zeros outside rows 1..2)
    assert out[1].name == "no_val" and out[0].values is not look[0].values  # the input is left as it was
    np.testing.assert_allclose(look[0].values, x)
    shifted = apply_recipe(look, "offset_int 1 1 3 y\n")[0].values
    np.testing.assert_allclose(shifted, [1, 2, 2, 2, 10, 26])  # d = x[3] − x[1] = 6
    rows = apply_recipe(look, "r_row 1 2\nsummation 1 1 s s\n")[0].values
    np.testing.assert_allclose(rows, np.cumsum([1, 8, 16, 32]))
    ranged = apply_recipe(look, "math_int 1 + 100 = 1 4 -1 x .\n")[0].values
    np.testing.assert_allclose(ranged, [1, 2, 4, 8, 116, 132])


def test_the_elastic_correction_and_strain_are_xlooks(tmp_path):
    disp = np.array([0.0, 1, 2, 3, 4])
    load = np.array([0.0, 0.5, 1, 1.5, 2])
    thick = np.array([10.0, 10, 12, 12, 14])
    look = _look(tmp_path, disp, load, thick)
    out = apply_recipe(look, "ec 1 2 4 0 -1 0.5 ec_disp um\nstrain 1 3 5 0 -1 g .\n")
    np.testing.assert_allclose(out[3].values, disp - (load - load[0]) / 0.5)
    want = np.concatenate([[0.0], np.cumsum(np.diff(disp) / (0.5 * (thick[1:] + thick[:-1])))])
    np.testing.assert_allclose(out[4].values, want)


def test_a_recipe_line_that_cannot_run_is_refused_with_its_line(tmp_path):
    look = _look(tmp_path, np.arange(4.0))
    with pytest.raises(RecipeError, match=r"recipe, line 2: 'qi 1 2 3'.*not one this reader runs"):
        apply_recipe(look, "# reduce\nqi 1 2 3\n")
    with pytest.raises(RecipeError, match=r"line 1: 'math 7 \* 2 = 1'.*column 7 holds no data"):
        apply_recipe(look, "math 7 * 2 = 1\n")
    with pytest.raises(RecipeError, match="rows 2..9 are not inside 0..3"):
        apply_recipe(look, "math_int 1 * 2 = 1 2 9\n")
    recipe = tmp_path / "r.txt"
    recipe.write_text("begin\nread whatever\nmath 1 ^ 2 = 1\n")
    with pytest.raises(RecipeError, match=r"r.txt, line 3.*not one of \+ - \* /"):
        apply_recipe(look, recipe)


def test_the_p655_recipe_gives_the_friction_the_lab_reports():
    """The lab's own recipe on its raw file: μ ≈ 0.487 before the 2.28 → 22.85 µm/s step
    at 100 MPa, and the load point moving at 2.28 µm/s there."""
    out = apply_recipe(read_look(P655 / "p655intact100l"), P655 / "p655_r-reduction.txt")
    t, mu, lp, sn = (out[n].values for n in ("Time", "mu", "LP_disp", "Nor_stress"))
    assert len(t) == 86813  # (one row removed by r_row)
    pre = (t > 3840) & (t < 3852)
    assert np.median(mu[pre]) == pytest.approx(0.4870, abs=5e-4)
    assert np.median(sn[pre]) == pytest.approx(99.9, abs=0.2)
    assert np.polyfit(t[pre], lp[pre], 1)[0] == pytest.approx(2.285, abs=0.01)
