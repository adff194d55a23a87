"""The figure gallery (docs/gallery.rst, made by docs/make_gallery.py) shows every
figure the toolkit draws, and its page and images agree."""

import importlib
import importlib.util
import sys
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"


def _gallery():
    spec = importlib.util.spec_from_file_location("make_gallery", DOCS / "make_gallery.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_gallery"] = mod  # (its dataclasses look their module up there)
    spec.loader.exec_module(mod)
    return mod


def test_page_is_what_the_declarations_write():
    g = _gallery()
    assert (DOCS / "gallery.rst").read_text(encoding="utf-8") == g.page_text(), (
        "docs/gallery.rst is stale: run python docs/make_gallery.py")


def test_every_image_on_the_page_exists_and_none_is_left_over():
    g = _gallery()
    named = {f.file for sec in g.GALLERY.values() for f in sec.figures}
    on_disk = {p.name for p in (DOCS / "gallery").glob("*.png")}
    assert named == on_disk


def test_every_plotting_function_is_in_the_gallery():
    g = _gallery()
    drawn = {d for sec in g.GALLERY.values() for f in sec.figures for d in f.draws}
    public = set()
    for name in ("identify.plots.base", "identify.plots.fit", "identify.plots.events", "identify.plots.diagnosis",
                 "identify.plots.transient", "design.plots"):
        public |= {n for n in importlib.import_module(name).__all__ if n.startswith("plot_")}
    assert public <= drawn, f"not in the gallery: {sorted(public - drawn)}"
    assert set(g.MAKERS) == set(g.GALLERY)  # every section is made, nothing made is left off the page


def test_unknown_section_is_refused(capsys):
    g = _gallery()
    with pytest.raises(SystemExit) as err:
        g.main(["nonsense"])
    assert err.value.code == 2
    assert "unknown section(s) nonsense" in capsys.readouterr().err
