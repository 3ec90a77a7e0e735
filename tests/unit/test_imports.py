"""The package's shape, read from its source with :mod:`ast`: no import circle among its modules and
no module over 600 lines.

Every import counts, at any depth (inside functions, under ``TYPE_CHECKING``, in ``__main__``
blocks): a circle that only a lazy import keeps from failing still ties the modules together for a
reader, and it fails the day someone moves the import up. A package's ``__init__`` counts as a module
(``patexgs_jax.training``), so an import of the package is an edge to its ``__init__``.
"""

from __future__ import annotations

import ast
from pathlib import Path

from locations import REPO

PACKAGE = "patexgs_jax"
MAX_LINES = 600


def _modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every ``.py`` under the package (``__init__`` named by its
    package)."""
    out = {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _owner(name: str, modules: dict[str, Path]) -> str | None:
    """The package module that ``name`` (a module, or a name inside one) lives in, or None."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _imported(module: str, path: Path, modules: dict[str, Path]) -> dict[str, int]:
    """The package modules ``module`` imports, each with the line of its first import."""
    is_package = path.name == "__init__.py"
    out: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                here = module.split(".") if is_package else module.split(".")[:-1]
                base = here[:len(here) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # `from pkg import sub` imports the submodule; `from mod import name` imports mod.
            names = [f"{source}.{a.name}" if f"{source}.{a.name}" in modules else source for a in node.names]
        for name in names:
            owner = _owner(name, modules)
            if owner is not None and owner != module:
                out.setdefault(owner, node.lineno)
    return out


def import_graph(root: Path = REPO) -> tuple[dict[str, Path], dict[str, dict[str, int]]]:
    """(modules, edges): ``edges[a][b]`` is the line of ``a``'s first import of ``b``."""
    modules = _modules(root)
    return modules, {m: _imported(m, p, modules) for m, p in modules.items()}


def circles(edges: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative),
    each sorted; every import circle lies inside one."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges[w]))))
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


def _describe(comp: list[str], modules: dict[str, Path], edges: dict[str, dict[str, int]]) -> str:
    inside = set(comp)
    lines = [f"{len(comp)} modules: {', '.join(comp)}"]
    for a in comp:
        for b in sorted(set(edges[a]) & inside):
            lines.append(f"    {modules[a].relative_to(REPO)}:{edges[a][b]} -> {modules[b].relative_to(REPO)}")
    return "\n".join(lines)


def test_the_circle_finder_finds_circles_and_only_them():
    edges = {"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1, "d": 1}, "d": {}, "e": {"e": 1}, "f": {"d": 1}}
    assert circles(edges) == [["a", "b", "c"]]
    assert circles({"x": {"y": 1}, "y": {"x": 1}, "z": {"x": 1}}) == [["x", "y"]]


def test_the_graph_sees_imports_at_any_depth():
    """A function-level relative import and a package import are edges (the two readers of COLMAP
    models import their shared records; training's config is imported as a submodule)."""
    modules, edges = import_graph()
    assert f"{PACKAGE}.data.colmap_records" in edges[f"{PACKAGE}.data.colmap_binary"]
    assert f"{PACKAGE}.training.config" in edges[f"{PACKAGE}.sources"]  # (imported inside a function)
    assert f"{PACKAGE}.render" in edges[PACKAGE]


def test_no_import_circle():
    modules, edges = import_graph()
    found = circles(edges)
    assert not found, "import circles among the package's modules (file:line -> file):\n" + "\n".join(
        _describe(c, modules, edges) for c in found)


def test_no_module_over_600_lines():
    modules, _ = import_graph()
    long = {str(p.relative_to(REPO)): n for p in modules.values() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}; split them by concern"
