"""The layout stays readable: imports point one way and no two files import each other.

Every import counts, also those inside functions and under ``TYPE_CHECKING``: a lazy import is still
a dependency a reader has to follow.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("fusion", "service", "worker")

# (importer prefix, forbidden prefixes): lower layers never import higher ones.
FORBIDDEN = [
    ("fusion", ("service", "worker")),  # the method and its tooling know nothing of the service
    ("service", ("worker",)),  # the API starts the embedded worker by command and sends tasks by name
    ("service.store", ("service.api", "service.schedule", "service.cli", "service.client", "service.embedded")),
    ("service.settings", ("service.",)),
    ("service.broker", ("service.api", "service.store", "service.schedule")),
    ("service.api", ("service.cli", "service.client")),
    ("service.schedule", ("service.api", "service.cli", "service.client")),
    ("worker", ("service.api", "service.cli", "service.client", "service.schedule")),
]
METHOD_EXCLUDES = ("fusion.eval",)


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules that ``name`` imports (a name imported from a package counts as its module)."""
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        out.update(t for t in targets if t in modules and t != name)
    return out


def _unresolved(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Project imports that name no module here (a lazy import left behind by a move fails only when run)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            targets = [node.module]
        else:
            continue
        out.update(t for t in targets if t.split(".")[0] in PACKAGES and t not in modules)
    return out


def test_every_project_import_resolves() -> None:
    modules = _modules()
    assert {name: found for name, path in modules.items() if (found := _unresolved(name, path, modules))} == {}


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _parent_package_edge(a: str, b: str) -> bool:
    """A package's ``__init__`` re-exporting its own submodules is not a cycle a reader must untangle."""
    return b.startswith(a + ".") or a.startswith(b + ".")


def test_no_import_cycles(graph: dict[str, set[str]]) -> None:
    pruned = {a: {b for b in deps if not _parent_package_edge(a, b)} for a, deps in graph.items()}
    assert _cycles(pruned) == []


def test_the_walker_sees_a_cycle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".") or (prefix.endswith(".") and name.startswith(prefix))


def test_layers_point_one_way(graph: dict[str, set[str]]) -> None:
    violations = []
    for importer, deps in graph.items():
        for prefix, forbidden in FORBIDDEN:
            if _under(importer, prefix):
                violations += [(importer, d) for d in deps if any(_under(d, f) for f in forbidden)]
        method = _under(importer, "fusion") and not any(_under(importer, e) for e in METHOD_EXCLUDES)
        if method:
            violations += [(importer, d) for d in deps if any(_under(d, e) for e in METHOD_EXCLUDES)]
    assert sorted(set(violations)) == []


def test_the_walker_resolves_relative_and_lazy_imports(tmp_path: Path) -> None:
    (tmp_path / "pkg").mkdir()
    source = "from . import b\n\ndef f():\n    from pkg.c import thing\n"
    (tmp_path / "pkg" / "a.py").write_text(source)
    modules = {"pkg": tmp_path / "pkg" / "__init__.py", "pkg.a": tmp_path / "pkg" / "a.py",
               "pkg.b": tmp_path / "pkg" / "b.py", "pkg.c": tmp_path / "pkg" / "c.py"}
    assert _imports("pkg.a", modules["pkg.a"], modules) == {"pkg.b", "pkg.c"}
