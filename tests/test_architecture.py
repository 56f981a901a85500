"""The package's import structure: no cycles, lower layers never import higher ones, private names stay private.

Every module under ``studio/`` is parsed (not imported) and every import is counted, at any depth — an import
inside a function is a dependency too, it only runs later. Relative imports are resolved against the module's
package. The layers, lowest first:

* ``sim`` — the simulator; imports no other studio package;
* ``data`` — episodes, store, splits, collection (which runs the simulator): may import ``sim``;
* ``model`` — OSVI-WM and its training: may import ``data``;
* ``eval`` — rollouts and evaluation, where model and simulator meet: ``sim``, ``data``, ``model``;
* ``backend`` — the bus and its job handlers: ``sim``, ``data``, ``model``, ``eval``;
* ``ui`` — anything but ``bench`` (and the command line);
* ``bench``, ``studio.cli``, ``studio.quickstart`` — anything.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "studio"

#: layer -> the studio layers it may import (its own included). ``None``: anything.
ALLOWED: dict[str, set[str] | None] = {
    "sim": {"sim"},
    "data": {"data", "sim"},
    "model": {"model", "data"},
    "eval": {"eval", "sim", "data", "model"},
    "backend": {"backend", "sim", "data", "model", "eval"},
    "ui": {"ui", "backend", "sim", "data", "model", "eval"},
    "bench": None,
    "top": None,
}
#: Modules directly in ``studio/``: the command line sits above everything; the package itself below.
TOP_MODULES = {"studio.cli", "studio.quickstart"}


@dataclass(frozen=True)
class Import:
    importer: str
    imported: str
    line: int
    names: tuple[str, ...] = ()  # the names of a ``from ... import`` (empty for ``import x``)


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def find_modules(root: Path = ROOT) -> dict[str, Path]:
    return {module_name(p, root): p for p in sorted(root.rglob("*.py"))}


def layer(module: str) -> str:
    """The layer of a studio module (``studio.eval.rollout`` -> ``eval``); ``top`` for the command line."""
    parts = module.split(".")
    if module in TOP_MODULES:
        return "top"
    if len(parts) == 1:
        return "package"  # ``studio`` itself (its version): anyone may import it
    return parts[1]


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    package = module.split(".") if is_package else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> Iterator[Import]:
    """The studio modules ``module`` imports, at any depth. ``from pkg import sub`` counts ``pkg.sub``."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "studio":
                    yield Import(module, _nearest(alias.name, modules), node.lineno)
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(module, is_package, node)
            if target.split(".")[0] != "studio":
                continue
            names = tuple(a.name for a in node.names)
            subs = [f"{target}.{n}" for n in names if f"{target}.{n}" in modules]
            if len(subs) < len(names):  # some names are attributes of ``target`` itself
                yield Import(
                    module,
                    _nearest(target, modules),
                    node.lineno,
                    tuple(n for n in names if f"{target}.{n}" not in modules),
                )
            for sub in subs:
                yield Import(module, sub, node.lineno)


def _nearest(name: str, modules: dict[str, Path]) -> str:
    """The module ``name`` refers to (``studio.x.y.attr`` -> ``studio.x.y``)."""
    parts = name.split(".")
    while parts and ".".join(parts) not in modules:
        parts.pop()
    return ".".join(parts) or name


def import_graph(modules: dict[str, Path]) -> tuple[dict[str, set[str]], list[Import]]:
    edges: dict[str, set[str]] = {m: set() for m in modules}
    every: list[Import] = []
    for m, p in modules.items():
        for imp in imports_of(m, p, modules):
            every.append(imp)
            if imp.imported != m and imp.imported in modules:
                edges[m].add(imp.imported)
    return edges, every


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def cycle_path(component: list[str], edges: dict[str, set[str]]) -> list[str]:
    """One concrete cycle through a component's first module, for the failure message: a -> b -> ... -> a."""
    start, members = component[0], set(component)
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(edges[v] & members):
            if w == start:
                return paths[v] + [start]
            if w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    return component


def layer_violations(imports: list[Import]) -> list[str]:
    out = []
    for imp in imports:
        allowed = ALLOWED.get(layer(imp.importer))
        target = layer(imp.imported)
        if allowed is None or target == "package" or target in allowed:
            continue
        out.append(
            f"{imp.importer} (layer {layer(imp.importer)}) imports {imp.imported} (layer {target}), "
            f"line {imp.line}"
        )
    return out


def private_uses(modules: dict[str, Path]) -> list[str]:
    """``from studio.x import _name`` and ``module._name`` (a studio module bound by an import) across modules."""
    out = []
    for m, p in modules.items():
        tree = ast.parse(p.read_text(), str(p))
        bound: dict[str, str] = {}  # local name -> studio module it refers to
        for imp in imports_of(m, p, modules):
            for name in imp.names:
                if name.startswith("_") and not name.startswith("__") and imp.imported != m:
                    out.append(f"{m} imports private {imp.imported}.{name}, line {imp.line}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("studio"):
                        bound[a.asname or a.name.split(".")[0]] = (a.asname and a.name) or a.name.split(".")[
                            0
                        ]
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(m, p.name == "__init__.py", node)
                for a in node.names:
                    if f"{target}.{a.name}" in modules:
                        bound[a.asname or a.name] = f"{target}.{a.name}"
        for node in ast.walk(tree):
            if (
                not isinstance(node, ast.Attribute)
                or not node.attr.startswith("_")
                or node.attr.startswith("__")
            ):
                continue
            owner = _dotted(node.value)
            if owner is None or owner.split(".")[0] not in bound:
                continue
            head, _, rest = owner.partition(".")
            full = bound[head] + ("." + rest if rest else "")
            if full in modules and full != m:
                out.append(f"{m} uses private {full}.{node.attr}, line {node.lineno}")
    return out


def _dotted(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value)
        return None if inner is None else f"{inner}.{node.attr}"
    return None


@pytest.fixture(scope="module")
def graph():
    modules = find_modules()
    edges, imports = import_graph(modules)
    return modules, edges, imports


def test_the_parser_sees_imports_at_every_depth_and_resolves_relative_ones(tmp_path):
    pkg = tmp_path / "studio"
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a" / "__init__.py").write_text("from . import b\n")
    (pkg / "a" / "b.py").write_text("def f():\n    from .c import g\n    return g\n")
    (pkg / "a" / "c.py").write_text(
        "import studio.a.b\nfrom studio.a.b import _hidden\n\ndef g():\n    return studio.a.b._x\n"
    )
    modules = find_modules(pkg)
    edges, _ = import_graph(modules)
    assert edges["studio.a"] == {"studio.a.b"}
    assert edges["studio.a.b"] == {"studio.a.c"}  # inside a function
    assert cycles(edges) == [["studio.a.b", "studio.a.c"]]
    assert sorted(private_uses(modules)) == [
        "studio.a.c imports private studio.a.b._hidden, line 2",
        "studio.a.c uses private studio.a.b._x, line 5",
    ]


def test_no_import_cycles(graph):
    _, edges, _ = graph
    found = [f"{', '.join(c)} (e.g. {' -> '.join(cycle_path(c, edges))})" for c in cycles(edges)]
    assert not found, "import cycles among studio modules:\n" + "\n".join(found)


def test_lower_layers_never_import_higher_ones(graph):
    _, _, imports = graph
    bad = layer_violations(imports)
    assert not bad, "imports against the layers (see this module's docstring):\n" + "\n".join(bad)


def test_every_module_is_in_a_known_layer(graph):
    modules, _, _ = graph
    unknown = sorted(m for m in modules if layer(m) not in ALLOWED and layer(m) != "package")
    assert not unknown, f"modules outside the known layers (add them to ALLOWED): {unknown}"


def test_private_names_stay_in_their_module(graph):
    modules, _, _ = graph
    bad = private_uses(modules)
    assert not bad, "private names used across modules (make them public):\n" + "\n".join(bad)
