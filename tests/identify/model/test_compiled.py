"""identify.model.compiled: JIT compile, cache on disk, reload; no files left in TMPDIR or cwd."""

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]

# a plain Function (compiled whole) and an integrator (CasADi JITs its dependencies and
# writes that C file to the cwd): the two ways identify uses compiled()
SCRIPT = r"""
import json, sys
import casadi as ca
from identify.model import compiled as c

x = ca.SX.sym("x")
f = c.compiled(lambda o: ca.Function("f", [x], [ca.sin(x) * x], o), tag="f")
i = c.compiled(lambda o: ca.integrator("i", "cvodes", {"x": x, "ode": -x}, 0.0, 1.0,
                                       {"abstol": 1e-12, "reltol": 1e-12, **o}), tag="i")
json.dump(dict(failed=c._failed, f=float(f(2.0)), i=float(i(x0=1.0)["xf"])), sys.stdout)
"""


def _run(tmpdir: Path, cache: Path, cwd: Path) -> dict:
    env = dict(os.environ, TMPDIR=str(tmpdir), NANOFRICTOR_CACHE=str(cache), NANOFRICTOR_JIT="1",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=cwd, capture_output=True,
                         text=True, timeout=600)  # a hang guard, not a timing (compiles under load)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.mark.skipif(shutil.which("gcc") is None, reason="no C compiler")
def test_compile_and_load_leave_no_files(tmp_path):
    tmpdir, cache, cwd = (tmp_path / n for n in ("tmp", "cache", "cwd"))
    for d in (tmpdir, cwd):
        d.mkdir()
    first = _run(tmpdir, cache, cwd)  # compiles and saves
    assert not first["failed"]
    entries = sorted(p.name for p in cache.rglob("*.casadi"))
    assert len(entries) == 2
    cached = sorted(p.name for p in cache.rglob("*"))
    for _ in range(2):  # later processes load from the cache
        again = _run(tmpdir, cache, cwd)
        assert again == first  # same (compiled) results
    assert sorted(p.name for p in cache.rglob("*")) == cached  # loading writes nothing
    assert list(tmpdir.iterdir()) == [] and list(cwd.iterdir()) == []
    assert first["f"] == pytest.approx(2.0 * math.sin(2.0), rel=1e-15)
    assert first["i"] == pytest.approx(math.exp(-1.0), rel=1e-8)


@pytest.mark.skipif(shutil.which("gcc") is None, reason="no C compiler")
def test_a_broken_entry_is_compiled_again(tmp_path):
    """An entry whose library is another Function's (what differentiating a cached
    Function does: CasADi writes the derivative under the same C name) is compiled
    again, not a reason to run every Function interpreted."""
    tmpdir, cache, cwd = (tmp_path / n for n in ("tmp", "cache", "cwd"))
    for d in (tmpdir, cwd):
        d.mkdir()
    first = _run(tmpdir, cache, cwd)
    libs = {p.name.split("_")[0]: p for p in cache.rglob("*") if p.suffix not in (".casadi", "") and "_" in p.name}
    assert set(libs) == {"f", "i"}, sorted(p.name for p in cache.rglob("*"))
    shutil.copyfile(libs["i"], libs["f"])  # f's library replaced by another
    again = _run(tmpdir, cache, cwd)
    assert not again["failed"] and again == first
    assert _run(tmpdir, cache, cwd) == first  # the entry compiled again is loadable


def test_casadi_event_notice_is_held_back_and_other_stderr_kept(capsys, monkeypatch):
    """CasADi's "Event support is experimental" line, printed on every creation or load of
    an integrator with events, is dropped; anything else written meanwhile reaches stderr."""
    import casadi as ca

    from identify.model import compiled as c

    monkeypatch.setenv("NANOFRICTOR_JIT", "0")  # (the notice comes from creating the Function)
    x = ca.SX.sym("x")

    def build(o):
        sys.stderr.write("something else CasADi said\n")
        return ca.integrator("ev", "cvodes", {"x": x, "ode": -x, "zero": x - 0.5}, 0.0, 1.0, o)

    F = c.compiled(build, tag="ev")
    err = capsys.readouterr().err
    assert c.EVENT_NOTICE not in err
    assert "something else CasADi said" in err
    assert isinstance(F, ca.Function)
    # without the filter CasADi does print it (a change of its wording would show here)
    ca.integrator("ev2", "cvodes", {"x": x, "ode": -x, "zero": x - 0.5}, 0.0, 1.0)
    assert c.EVENT_NOTICE in capsys.readouterr().err
