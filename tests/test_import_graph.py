"""The package's import graph (docs/import_graph.py): its rooms import one way, with no circle,
and ``design`` reaches into ``identify`` only through public names."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "docs" / "import_graph.py"


@pytest.fixture(scope="module")
def ig():
    spec = importlib.util.spec_from_file_location("import_graph", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["import_graph"] = mod  # (its dataclass looks its module up there)
    spec.loader.exec_module(mod)
    return mod


def _private(name):
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def test_rooms_import_one_way(ig):
    graph = ig.room_graph(ROOT)
    assert {"identify.model", "identify.fitting", "identify.cli", "design", "design.cli"} <= set(graph)
    assert ig.circles(graph) == []
    assert ig.arrows_up(graph, ig.floors(graph)) == []


def test_modules_import_one_way_too(ig):
    # a circle inside a room is hidden from the room graph: the modules' own graph shows it
    graph = {}
    for imp in ig.imports(ROOT):
        graph.setdefault(imp.source, set()).add(imp.target)
    graph = {a: bs - {a} for a, bs in graph.items()}  # (a package's __init__ importing its own names)
    assert ig.circles(graph) == []


def test_the_layers_are_the_documented_ones(ig):
    # docs/engineering-notes.md: cli -> diagnosis -> fitting -> simulation -> traces -> plots -> model
    fl = ig.floors(ig.room_graph(ROOT))
    chain = ["identify.cli", "identify.diagnosis", "identify.fitting", "identify.simulation", "identify.traces",
             "identify.plots", "identify.model"]
    assert [fl[r] for r in chain] == sorted((fl[r] for r in chain), reverse=True)
    assert len({fl[r] for r in chain}) == len(chain)
    assert fl["identify.model"] == fl["identify.jsonio"] == 0


def test_design_imports_only_public_names_of_identify(ig):
    across = [imp for imp in ig.imports(ROOT)
              if imp.source.split(".")[0] == "design" and imp.target.split(".")[0] == "identify"]
    assert across, "design should be found importing identify"
    bad = [imp for imp in across if any(map(_private, imp.target.split("."))) or _private(imp.name or "")]
    assert bad == []


def test_identify_never_imports_design(ig):
    assert [imp for imp in ig.imports(ROOT) if imp.source.split(".")[0] == "identify"
            and imp.target.split(".")[0] == "design"] == []


def test_no_private_name_is_imported_across_modules(ig):
    assert [imp for imp in ig.imports(ROOT) if _private(imp.name or "")] == []


def test_the_script_draws_the_graph(tmp_path):
    out = tmp_path / "graph.png"
    run = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert "circles: 0" in run.stdout and "arrows up: 0" in run.stdout
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _write(root, files):
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text, encoding="utf-8")


def test_a_circle_is_found(ig, tmp_path, capsys):
    # loop.a imports loop.b at import time; loop.b imports loop.a back, relatively and inside a function
    _write(tmp_path, {"loop/__init__.py": "from . import c\n", "loop/c.py": "import os\n",
                      "loop/a/__init__.py": "", "loop/a/x.py": "from loop.b.y import f\n",
                      "loop/b/__init__.py": "", "loop/b/y.py": "def f():\n    from ..a import x\n    return x\n",
                      "loop/cli.py": "import loop.a.x\n"})
    graph = ig.room_graph(tmp_path, ["loop"])
    assert graph == {"loop": {"loop.c"}, "loop.c": set(), "loop.a": {"loop.b"}, "loop.b": {"loop.a"},
                     "loop.cli": {"loop.a"}}
    assert ig.circles(graph) == [["loop.a", "loop.b"]]
    fl = ig.floors(graph)
    assert fl["loop.a"] == fl["loop.b"] == 0 and fl["loop.cli"] == 1
    assert ig.arrows_up(graph, fl) == [("loop.a", "loop.b"), ("loop.b", "loop.a")]
    assert ig.circles(ig.room_graph(tmp_path, ["loop"], lazy=False)) == []  # the way back is lazy
    assert ig.main(["--root", str(tmp_path), "--packages", "loop", "--out", str(tmp_path / "g.png")]) == 1
    assert "loop.a <-> loop.b" in capsys.readouterr().out
    assert (tmp_path / "g.png").exists()


def test_a_flat_package_is_one_room_beside_its_command_line(ig, tmp_path):
    _write(tmp_path, {"flat/__init__.py": "from .core import go\n", "flat/core.py": "def go():\n    pass\n",
                      "flat/cli.py": "from flat.core import go\n", "flat/__main__.py": "from .cli import go\n"})
    assert ig.room_graph(tmp_path, ["flat"]) == {"flat": set(), "flat.cli": {"flat"}}
