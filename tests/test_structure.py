"""The package stays a house a newcomer can find their way in: its folders are the layers of
docs/architecture.md and no layer imports a higher one (lazy imports inside functions count too; the
deliberate exceptions are EXCEPTIONS below, each with its reason); no import cycle anywhere (rlexp's
modules, ``if TYPE_CHECKING:`` imports included, and the benchmarks); no module over 500 lines; the
architecture doc names every module and every module it names exists."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from conftest import REPO

SRC = REPO / "src"
PACKAGE = SRC / "rlexp"
MAX_LINES = 500


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(
    path: Path, name: str, modules: dict[str, Path], typing: bool = False, root: str = "rlexp"
) -> set[str]:
    """The modules of ``modules`` that ``name`` imports, anywhere in its code (``if TYPE_CHECKING:``
    blocks only with ``typing``)."""
    tree = ast.parse(path.read_text())
    is_package = path.name == "__init__.py"
    found: set[str] = set()

    def resolve(target: str) -> str | None:
        while target and target not in modules:
            target = target.rpartition(".")[0]
        return target or None

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _is_type_checking(node) and not typing:
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == root:
                    found.add(resolve(alias.name) or alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from its package
                base = name if is_package else name.rpartition(".")[0]
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            if module.split(".")[0] == root:
                for alias in node.names:  # `from pkg import submodule` imports the submodule
                    sub = f"{module}.{alias.name}"
                    found.add(sub if sub in modules else resolve(module) or module)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    found.discard(name)
    return {m for m in found if m in modules}


def _graph(typing: bool = False) -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(path, name, modules, typing) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def strong(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
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
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return out


def _package_reexport(cycle: list[str]) -> bool:
    """A package's ``__init__`` re-exporting its own submodules, which import names from it: how
    Python packages work, not a circle (as ../shared/tools/structure.py counts). Any member outside
    the package makes it a real cycle."""
    packages = [m for m in cycle if _modules()[m].name == "__init__.py"]
    return any(all(m == p or m.startswith(p + ".") for m in cycle) for p in packages)


def test_no_import_cycle_among_rlexp_modules():
    cycles = [c for c in _cycles(_graph()) if not _package_reexport(c)]
    assert not cycles, f"import cycles (every import counts, lazy ones too): {cycles}"


def test_the_cycle_finder_finds_a_lazy_cycle(tmp_path):
    """The check itself: a circle closed by an import inside a function is found."""
    modules = {"rlexp.a": tmp_path / "a.py", "rlexp.b": tmp_path / "b.py"}
    modules["rlexp.a"].write_text("from rlexp import b\n")
    modules["rlexp.b"].write_text("def f():\n    from rlexp.a import x\n")
    typed = tmp_path / "c.py"
    typed.write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from rlexp.a import x\n"
    )
    graph = {n: _imports(p, n, modules) for n, p in modules.items()}
    assert _cycles(graph) == [["rlexp.a", "rlexp.b"]]
    assert _imports(typed, "rlexp.c", modules) == set()


def test_no_module_over_500_lines():
    long = {
        str(p.relative_to(REPO)): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_LINES
    }
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_the_architecture_doc_names_every_module():
    """docs/architecture.md matches the tree: every module and package of rlexp is in its map."""
    text = (REPO / "docs" / "architecture.md").read_text()
    missing = []
    for path in sorted(PACKAGE.iterdir()):
        if path.name.startswith("_") or path.name == "__pycache__":
            continue
        if path.is_dir() and (path / "__init__.py").is_file():
            names = [f"{path.name}/"]
        elif path.suffix == ".py":
            names = [path.name, path.stem]
        else:
            continue
        if not any(f"`{n}" in text or f" {n}" in text for n in names):
            missing.append(path.name)
    assert not missing, f"docs/architecture.md does not mention {missing}"


def test_no_import_cycle_counting_type_checking_imports():
    """A circle closed only by an ``if TYPE_CHECKING:`` import is still a circle in the drawing
    (``envs/native/state.py`` <-> ``tasks.py`` was one)."""
    cycles = [c for c in _cycles(_graph(typing=True)) if not _package_reexport(c)]
    assert not cycles, f"import cycles (TYPE_CHECKING imports included): {cycles}"


def _benchmark_graph() -> dict[str, set[str]]:
    """The benchmarks import each other by file name (``from end_to_end import ROWS``)."""
    files = {p.stem: p for p in sorted((REPO / "benchmarks").glob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                found.add(node.module.split(".")[0])
        graph[name] = {m for m in found if m in files and m != name}
    return graph


def test_no_import_cycle_among_the_benchmarks():
    graph = _benchmark_graph()
    assert "end_to_end" in graph and "ppo_throughput" in graph
    assert not _cycles(graph), f"import cycles among benchmarks/: {_cycles(graph)}"
