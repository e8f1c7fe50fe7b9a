"""The package layout the design doc promises: no import cycles between the library's modules
(imports inside functions included) and no library module importing the experiment code."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
LIBRARY = "stochastic_fields"
EXPERIMENTS = "stochastic_fields_bench"


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def imported_modules(path: Path, known: set[str]) -> set[str]:
    """Every module of ``known`` that ``path`` imports, at any depth of its code.

    ``from a.b import c`` counts as importing ``a.b.c`` when that is a module, else ``a.b``;
    a package's ``__init__`` is not counted for its own submodules' relative imports."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [(mod, a.name) for a in node.names]
        else:
            continue
        for mod, attr in targets:
            if attr and f"{mod}.{attr}" in known:
                out.add(f"{mod}.{attr}")
            elif mod in known:
                out.add(mod)
    out.discard(name)
    return out


def import_graph() -> dict[str, set[str]]:
    paths = [p for pkg in (LIBRARY, EXPERIMENTS) for p in (SRC / pkg).rglob("*.py")]
    known = {module_name(p) for p in paths}
    return {module_name(p): imported_modules(p, known) for p in paths}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle (a list of modules, first == last) or None (iterative DFS)."""
    state: dict[str, int] = {}
    for root in sorted(graph):
        if state.get(root):
            continue
        stack = [(root, iter(sorted(graph[root])))]
        path = [root]
        state[root] = 1
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                state[node] = 2
                stack.pop()
                path.pop()
                continue
            if state.get(child) == 1:
                return path[path.index(child):] + [child]
            if not state.get(child):
                state[child] = 1
                path.append(child)
                stack.append((child, iter(sorted(graph.get(child, ())))))
    return None


def test_cycle_finder_finds_a_planted_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_library_has_no_import_cycles():
    graph = {m: {d for d in deps if not d.startswith(EXPERIMENTS)} for m, deps in import_graph().items()
             if m.startswith(LIBRARY + ".") or m == LIBRARY}
    # a package __init__ re-exporting its modules is not a cycle of the modules themselves
    graph = {m: {d for d in deps if not (m.startswith(d + ".") and d in graph)} for m, deps in graph.items()}
    assert find_cycle(graph) is None, f"import cycle: {' -> '.join(find_cycle(graph))}"


def test_library_never_imports_the_experiment_code():
    offenders = {m: sorted(d for d in deps if d.startswith(EXPERIMENTS))
                 for m, deps in import_graph().items() if not m.startswith(EXPERIMENTS)}
    offenders = {m: d for m, d in offenders.items() if d}
    assert not offenders, f"library modules importing {EXPERIMENTS}: {offenders}"
    assert any(d.startswith(LIBRARY) for d in import_graph()[f"{EXPERIMENTS}.tables"])  # the scan sees imports
