"""Draw the import graph between the package's rooms, and check that it has no circle.

    python docs/import_graph.py [--out PATH]     # default: docs/gallery/import-graph.png

A *room* is a subpackage of ``identify`` (with its own subpackages), one of its top-level
modules, its command line (``cli*``, ``__main__``) or the package itself (``__init__``, the
public API); ``design``, having no subpackages, is one room beside its command line. Imports
are read with :mod:`ast`, relative ones and *lazy* ones (inside functions) included: a lazy
import runs later, yet the room depends on what it imports all the same. A room's floor is the
longest chain of imports below it, so every arrow points down unless rooms import each other
around a circle; the script then draws those arrows red and exits 1.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("identify", "design")
OUT = ROOT / "docs" / "gallery" / "import-graph.png"


@dataclass(frozen=True)
class Import:
    source: str  # the importing module
    target: str  # the imported module: the longest prefix of the dotted name that is a module of the tree
    name: str | None  # the name a ``from`` import takes (None for ``import a.b``)
    lazy: bool  # made inside a function


def modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """Dotted name -> file of every module under ``root/<package>``; a package is its ``__init__``."""
    found = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imports(root: Path, packages=PACKAGES) -> list[Import]:
    """Every import, by a module under ``packages``, of a module under ``packages``."""
    mods = modules(root, packages)

    def known(dotted: str) -> str:
        while dotted and dotted not in mods:
            dotted = dotted.rpartition(".")[0]
        return dotted

    found = []
    for source, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        lazy = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                for n in ast.walk(f)}
        here = source if path.name == "__init__.py" else source.rpartition(".")[0]
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                pairs = [(a.name, None) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # ``from ..x import y``: up level - 1 packages from the module's own
                    up = here.split(".")[: here.count(".") + 2 - node.level]
                    base = ".".join(up + ([node.module] if node.module else []))
                # ``from pkg import mod`` imports the module pkg.mod; ``from pkg import name``, pkg
                pairs = [(f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base, a.name) for a in node.names]
            else:
                continue
            for dotted, name in pairs:
                if known(dotted):
                    found.append(Import(source, known(dotted), name, id(node) in lazy))
    return found


def rooms(root: Path, packages=PACKAGES) -> dict[str, str]:
    """Module -> its room."""
    mods = modules(root, packages)
    nested = {m.partition(".")[0] for m, p in mods.items() if "." in m and p.name == "__init__.py"}

    def room(module: str) -> str:
        top, _, rest = module.partition(".")
        first = rest.partition(".")[0]
        if first.startswith("cli") or first == "__main__":
            return f"{top}.cli"
        # a package without subpackages is one library: its modules are not rooms of their own
        return f"{top}.{first}" if first and top in nested else top

    return {m: room(m) for m in mods}


def room_graph(root: Path, packages=PACKAGES, lazy: bool = True) -> dict[str, set[str]]:
    """Room -> the other rooms it imports (``lazy=False``: only the imports made at import time)."""
    of = rooms(root, packages)
    graph: dict[str, set[str]] = {r: set() for r in of.values()}
    for imp in imports(root, packages):
        if of[imp.source] != of[imp.target] and (lazy or not imp.lazy):
            graph[of[imp.source]].add(of[imp.target])
    return graph


def reach(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """Room -> every room it imports, directly or through others (the graphs are small: a walk each)."""
    found = {}
    for v in set(graph).union(*graph.values()):
        todo, seen = list(graph.get(v, ())), set()
        while todo:
            if (w := todo.pop()) not in seen:
                seen.add(w)
                todo.extend(graph.get(w, ()))
        found[v] = seen
    return found


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with a circle in them: rooms that import each other."""
    r = reach(graph)
    return [list(c) for c in sorted({tuple(sorted(w for w in r[v] if v in r[w])) for v in r if v in r[v]})]


def floors(graph: dict[str, set[str]]) -> dict[str, int]:
    """Room -> floor: 0 if it imports no room, else one above the highest it imports. The rooms of a
    circle share one floor (the layering of the graph with each circle taken as one room)."""
    r = reach(graph)
    memo: dict[str, int] = {}

    def floor(v: str) -> int:
        if v not in memo:
            below = {w for w in r[v] if v not in r[w]}  # what it imports, circles with it left out
            memo[v] = 1 + max(map(floor, below)) if below else 0
        return memo[v]

    return {v: floor(v) for v in r}


def arrows_up(graph: dict[str, set[str]], fl: dict[str, int]) -> list[tuple[str, str]]:
    """The arrows not pointing down: none unless there is a circle."""
    return sorted((a, b) for a in graph for b in graph[a] if fl[b] >= fl[a])


def draw(graph: dict[str, set[str]], fl: dict[str, int], out: Path, lazy_only=(), sizes=None,
         packages=PACKAGES) -> None:
    """Rooms as boxes on their floors (callers on top), arrows from importer to imported; ``sizes``:
    room -> number of modules."""
    from matplotlib.figure import Figure  # no pyplot: no backend, no global state
    from matplotlib.lines import Line2D
    from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

    dx, dy, w, h = 2.5, 1.4, 2.2, 0.55
    top = max(fl.values(), default=0)
    rows = {f: sorted(r for r in fl if fl[r] == f) for f in range(top + 1)}
    callers = {r: {a for a in graph if r in graph[a]} for r in fl}
    x: dict[str, float] = {}

    def place(f: int, near: dict[str, set[str]]) -> None:
        # a room sits under (or over) the mean of its neighbours, so fewer arrows cross
        rows[f].sort(key=lambda r: sum(x.get(n, 0) for n in near[r]) / len(near[r]) if near[r] else 0)
        x.update({r: (i - (len(rows[f]) - 1) / 2) * dx for i, r in enumerate(rows[f])})

    for f in range(top + 1):
        place(f, {r: graph.get(r, set()) for r in rows[f]})
    for f in range(top - 1, -1, -1):
        place(f, callers)
    width = max(map(len, rows.values())) * dx
    fig = Figure(figsize=(0.75 * width + 1.5, 0.75 * (top + 1) * dy + 1.2), layout="constrained")
    ax = fig.add_subplot()
    boxes = {}
    colours = {t: ("#dbe8f5", "#f5e6cc", "#dcefd9", "#eddcef")[i % 4] for i, t in enumerate(packages)}
    for r, f in fl.items():
        boxes[r] = FancyBboxPatch((x[r] - w / 2, f * dy - h / 2), w, h, boxstyle="round,pad=0.05", zorder=3,
                                  facecolor=colours[r.partition(".")[0]], edgecolor="0.3")
        ax.add_patch(boxes[r])
        n = (sizes or {}).get(r, 0)
        note = "\n(public API)" if "." not in r and n == 1 else f"\n{n} modules" if n > 1 else ""
        ax.text(x[r], f * dy, r + note, ha="center", va="center", fontsize=8.5, zorder=4)
    n_circles = len(circles(graph))
    for a in sorted(graph):
        for b in sorted(graph[a]):
            bad = fl[b] >= fl[a]  # the rooms of a circle share a floor: its arrows, and only they, are level
            # an arrow over several floors bows out, the more the longer, not to hide behind the boxes between;
            # to either side by the floor it lands on, so that a column's arrows spread both ways
            rad = min(0.12 * (fl[a] - fl[b] - 1), 0.45) * (-1) ** fl[b] if abs(x[a] - x[b]) < dx else 0.05
            ax.add_patch(FancyArrowPatch((x[a], fl[a] * dy), (x[b], fl[b] * dy), patchA=boxes[a], patchB=boxes[b],
                                         arrowstyle="-|>", mutation_scale=9, connectionstyle=f"arc3,rad={rad}",
                                         linestyle="--" if (a, b) in lazy_only else "-", linewidth=0.8, zorder=2,
                                         color="red" if bad else "0.6" if (a, b) in lazy_only else "0.3"))
    for f in range(top + 1):
        ax.text(-width / 2 - 0.4, f * dy, f"floor {f}", ha="right", va="center", fontsize=8, color="0.4")
    ax.legend(handles=[Line2D([], [], color="0.3", label="imported at import time"),
                       Line2D([], [], color="0.6", ls="--", label="imported only inside functions"),
                       Line2D([], [], color="red", label="in a circle")], loc="upper left", fontsize=8, frameon=False)
    ax.set_xlim(-width / 2 - 1.6, width / 2 + 0.2)
    ax.set_ylim(-dy / 2, top * dy + dy / 2 + 0.3)
    ax.axis("off")
    ax.set_title(f"Import graph of {' and '.join(packages)}: {len(fl)} rooms on {top + 1} floors, "
                 f"{n_circles} circle{'s' * (n_circles != 1)}", fontsize=10)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT, help=f"the PNG to write (default: {OUT.relative_to(ROOT)})")
    ap.add_argument("--root", type=Path, default=ROOT, help="the folder holding the packages (default: the repo)")
    ap.add_argument("--packages", nargs="+", default=PACKAGES, help=f"default: {' '.join(PACKAGES)}")
    args = ap.parse_args(argv)
    graph = room_graph(args.root, args.packages)
    eager = room_graph(args.root, args.packages, lazy=False)
    lazy_only = {(a, b) for a in graph for b in graph[a] - eager[a]}
    fl, found = floors(graph), circles(graph)
    up = arrows_up(graph, fl)
    sizes = Counter(rooms(args.root, args.packages).values())
    print(f"rooms: {len(graph)} ({sum(sizes.values())} modules)")
    print(f"floors: {max(fl.values(), default=-1) + 1}")
    for f in sorted(set(fl.values()), reverse=True):
        print(f"  {f}: {', '.join(sorted(r for r in fl if fl[r] == f))}")
    print(f"edges: {sum(map(len, graph.values()))} ({len(lazy_only)} only inside functions)")
    for a, b in sorted(lazy_only):
        print(f"  {a} -> {b} (lazy)")
    print(f"circles: {len(found)}" + "".join(f"\n  {' <-> '.join(c)}" for c in found))
    print(f"arrows up: {len(up)}" + "".join(f"\n  {a} -> {b}" for a, b in up))
    draw(graph, fl, args.out, lazy_only, sizes, args.packages)
    print(f"wrote {args.out}")
    return 1 if found or up else 0


if __name__ == "__main__":
    sys.exit(main())
