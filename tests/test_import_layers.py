"""The house plan: the package's import graph has no cycle, and no module imports a higher layer.

Every import counts, at the top of a module or inside a function (a function-local import is an
arrow too, just a later one), and so do the lazy public names of a package (``lazy_exports``
tables) and the package ``__init__`` that importing a submodule runs first (except the root
package's, a lazy facade over everything). The graph is read from the source with ``ast``; nothing
is imported.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path
from typing import Dict, List, Set, Tuple

from ._layers import LAYERS, PACKAGE
from .conftest import REPO


def _layer_of(module: str) -> Tuple[int, str] | None:
    """``(rank, entry)`` of a dotted module name (``torch_frontend.io.euroc`` -> the "io" entry)."""
    rel = module[len(PACKAGE) + 1:] if module != PACKAGE else ""
    best = None
    for rank, (_, entries) in enumerate(LAYERS):
        for e in entries:
            if rel == e or (e and rel.startswith(e + ".")):
                if best is None or len(e) > len(best[1]):
                    best = (rank, e)
    return best


def _modules() -> Dict[str, Path]:
    root = REPO / PACKAGE
    out = {}
    for f in sorted(root.rglob("*.py")):
        parts = f.relative_to(REPO).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


def _resolve(module: str, is_pkg: bool, level: int, name: str | None) -> str:
    """Absolute name of ``from <level dots><name> import ...`` written in ``module``."""
    base = module.split(".")
    if not is_pkg:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([name] if name else []))


def _lazy_targets(tree: ast.Module, call: ast.Call) -> List[str]:
    """Module strings of a ``lazy_exports(__name__, {...})`` table (dict literal, ``**`` and dict
    comprehensions, or a module-level name bound to one)."""
    if len(call.args) < 2:
        return []
    table = call.args[1]
    if isinstance(table, ast.Name):
        name = table.id
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == name for t in node.targets):
                table = node.value
    out = []
    for node in ast.walk(table):
        vals = node.values if isinstance(node, ast.Dict) else [node.value] if isinstance(node, ast.DictComp) else []
        out += [v.value for v in vals if isinstance(v, ast.Constant) and isinstance(v.value, str)]
    return out


def import_graph() -> Dict[str, Set[Tuple[str, int, str]]]:
    """``module -> {(imported torch_frontend module, line, via)}`` for every module of the package;
    ``via`` is the submodule whose import runs the imported package's ``__init__`` ("" if direct)."""
    mods = _modules()
    graph: Dict[str, Set[Tuple[str, int, str]]] = {m: set() for m in mods}

    def target(name: str) -> str | None:
        # the deepest existing module of a dotted name (``a.b.func`` -> ``a.b``)
        parts = name.split(".")
        while parts and ".".join(parts) not in mods:
            parts.pop()
        return ".".join(parts) if parts else None

    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            names: List[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                src = node.module if node.level == 0 else _resolve(mod, is_pkg, node.level, node.module)
                if src is None:
                    continue
                # ``from . import x``: x may be a submodule
                names = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src for a in node.names]
            elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "lazy_exports":
                for t in _lazy_targets(tree, node):
                    level = len(t) - len(t.lstrip("."))
                    names.append(_resolve(mod, is_pkg, level + 1, t.lstrip(".")))
            for n in names:
                if n == PACKAGE or n.startswith(PACKAGE + "."):
                    t = target(n)
                    if t is None or t == mod:
                        continue
                    graph[mod].add((t, node.lineno, ""))
                    # importing a.b.c runs a/b/__init__ first (unless a.b is being imported already,
                    # from inside it); the root package's lazy facade is left out of this rule
                    parts = t.split(".")
                    for k in range(2, len(parts)):
                        parent = ".".join(parts[:k])
                        if parent in mods and mod != parent and not mod.startswith(parent + "."):
                            graph[mod].add((parent, node.lineno, t))
    return graph


def _arrow(mod: str, line: int, dst: str, via: str) -> str:
    where = f"{_modules()[mod].relative_to(REPO)}:{line}"
    return f"{where}: {mod} -> {dst}" + (f" (its __init__, run by importing {via})" if via else "")


def test_every_module_has_a_layer():
    missing = [m for m in _modules() if _layer_of(m) is None]
    assert not missing, "modules not in the layer map (add them to LAYERS in tests/test_import_layers.py): " + ", ".join(missing)


def test_no_import_from_a_lower_layer_to_a_higher_one():
    graph = import_graph()
    bad = []
    for mod, edges in sorted(graph.items()):
        lm = _layer_of(mod)
        for dst, line, via in sorted(edges):
            ld = _layer_of(dst)
            if lm is not None and ld is not None and ld[0] > lm[0]:
                bad.append(f"{_arrow(mod, line, dst, via)}: layer {LAYERS[lm[0]][0]!r} imports {LAYERS[ld[0]][0]!r}")
    assert not bad, f"{len(bad)} upward import(s):\n" + "\n".join(bad)


def test_import_graph_has_no_cycle():
    graph = import_graph()
    adj = {m: sorted({d for d, *_ in e}) for m, e in graph.items()}
    # Tarjan's strongly connected components: every component of more than one module is a cycle
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on: Set[str] = set()
    comps: List[List[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in adj[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp))

    for v in sorted(adj):
        if v not in index:
            visit(v)
    lines = []
    for comp in comps:
        members = set(comp)
        lines.append("cycle among " + ", ".join(comp) + ":")
        lines += [f"    {_arrow(m, ln, d, via)}" for m in comp for d, ln, via in sorted(graph[m]) if d in members]
    assert not comps, "\n".join(lines)


def test_the_graph_reader_sees_every_kind_of_import():
    """The reader itself: top-level, function-local, relative and lazy-table imports are arrows."""
    graph = {m: {d for d, *_ in e} for m, e in import_graph().items()}
    assert "torch_frontend.opencv_yaml" in graph["torch_frontend.config"]  # top level, relative
    assert "torch_frontend.camera" in graph["torch_frontend.config"]  # function-local
    assert "torch_frontend.trajectory" in graph["torch_frontend.io"]  # lazy table, parent-relative
    assert "torch_frontend.io.multistream" in graph["torch_frontend.io"]  # lazy table
    assert "torch_frontend.geometry" in graph["torch_frontend.loop.optimize"]
    assert "torch_frontend.io" in graph["torch_frontend.outputs"]  # io/__init__ runs before io.multistream
    assert "torch_frontend.io" not in graph["torch_frontend.io.sources"]  # already being imported


def _layout_rows():
    text = (REPO / "README.md").read_text(encoding="utf-8")
    table = text[text.index("| layer | modules of `torch_frontend/`"):].split("\n\n")[0].splitlines()[2:]
    rows = []
    for line in table:
        cells = [c.strip() for c in line.strip("|").split("|")]
        names = [n.rstrip("/") for n in re.findall(r"`([^`]+)`", cells[1])]
        rows.append((cells[0], tuple("" if n == "__init__" else n for n in names)))
    return rows


def test_layout_table_is_the_import_plan():
    """The README's layout table lists the layers of ``LAYERS`` in order, each with its entries."""
    assert _layout_rows() == [(name, tuple(entries)) for name, entries in LAYERS]
