"""The package stays a house a newcomer can find their way in: its folders are the layers of
docs/architecture.md and no layer imports a higher one (lazy imports inside functions count too; the
deliberate exceptions are EXCEPTIONS below, each with its reason); no import cycle anywhere (rlexp's
modules, ``if TYPE_CHECKING:`` imports included, and the benchmarks); no module over 500 lines; the
architecture doc names every module and every module it names exists."""

# layout_move.py: written for the new layout (it names old paths on purpose)

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


# -- the layer rule ---------------------------------------------------------------------------------

ARCHITECTURE = REPO / "docs" / "architecture.md"

#: The deliberate imports from a lower layer up to a higher one: (importer, imported) -> why. The
#: one place they are listed; each must still occur (a stale entry fails too).
_CONFIG_NAMES = (
    "the config checks the names it holds against the registries the pieces fill (event, hook and "
    "native-task names, PBT settings), lazily, so a typo fails before anything is built"
)
EXCEPTIONS: dict[tuple[str, str], str] = {
    ("rlexp.config.validate", "rlexp.events.manager"): _CONFIG_NAMES,
    ("rlexp.config.validate", "rlexp.hooks"): _CONFIG_NAMES,
    ("rlexp.config.validate", "rlexp.pbt.config"): _CONFIG_NAMES,
    ("rlexp.config.json_format.task_section", "rlexp.envs.native"): _CONFIG_NAMES,
    ("rlexp.config.json_format.trainer_events", "rlexp.events"): _CONFIG_NAMES,
    ("rlexp.config.json_format.trainer_events", "rlexp.events.builtin"): _CONFIG_NAMES,
    ("rlexp.config.json_format.trainer_events", "rlexp.events.manager"): _CONFIG_NAMES,
    ("rlexp.analysis.reporting.trials", "rlexp.launch.optuna_study"): (
        "rlexp report lists an Optuna sweep's trials through the sweeper's own study reader, a "
        "module that imports nothing from rlexp, lazily (only where rlexp[optuna] is installed)"
    ),
}


def _layer_table(text: str, package: str = "rlexp") -> dict[str, int]:
    """docs/architecture.md's layer table: ``| 2. pieces | `envs/`, `plugins.py` | ... |`` ->
    {"rlexp.envs": 2, "rlexp.plugins": 2}; ``__init__.py`` is the package itself."""
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    layers: dict[str, int] = {}
    for line in section.splitlines():
        row = re.match(r"\|\s*(\d+)\.[^|]*\|([^|]*)\|", line)
        if not row:
            continue
        for name in re.findall(r"`([^`]+)`", row[2]):
            if name == "__init__.py":
                layers[package] = int(row[1])
            else:
                layers[f"{package}.{name.removesuffix('/').removesuffix('.py')}"] = int(row[1])
    return layers


def _layer_of(module: str, layers: dict[str, int], package: str = "rlexp") -> int | None:
    """The layer of the longest table entry that is the module or a package above it."""
    keys = [k for k in layers if module == k or (k != package and module.startswith(k + "."))]
    return layers[max(keys, key=len)] if keys else None


def _upward_imports(
    graph: dict[str, set[str]], layers: dict[str, int], exceptions=()
) -> list[tuple[str, int, str, int]]:
    """Every import from a module to one of a higher layer, less the listed exceptions."""
    out = []
    for importer in sorted(graph):
        for imported in sorted(graph[importer]):
            low, high = _layer_of(importer, layers), _layer_of(imported, layers)
            if low < high and (importer, imported) not in exceptions:
                out.append((importer, low, imported, high))
    return out


def test_every_module_has_a_layer_in_the_architecture_doc():
    layers = _layer_table(ARCHITECTURE.read_text())
    assert len(set(layers.values())) == 6, layers
    missing = [m for m in _modules() if _layer_of(m, layers) is None]
    assert not missing, f"modules in no layer of docs/architecture.md: {missing}"
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert top == [
        "__init__.py",
        "__main__.py",
        "app.py",
        "checkpoint.py",
        "cli.py",
        "extras.py",
        "plugins.py",
    ], f"the top of src/rlexp keeps the entry points and at most four other modules: {top}"


def test_no_layer_imports_a_higher_one():
    """Each package imports only from its own layer and those below, lazy imports counted."""
    layers = _layer_table(ARCHITECTURE.read_text())
    up = _upward_imports(_graph(), layers, EXCEPTIONS)
    assert not up, "imports from a lower layer up to a higher one:\n" + "\n".join(
        f"  {a} (layer {la}) -> {b} (layer {lb})" for a, la, b, lb in up
    )


def test_every_listed_exception_still_occurs():
    graph = _graph()
    stale = [pair for pair in EXCEPTIONS if pair[1] not in graph.get(pair[0], set())]
    assert not stale, f"EXCEPTIONS lists imports that no longer exist (remove them): {stale}"


def test_the_layer_checker_flags_a_lower_layer_importing_a_higher_one(tmp_path):
    """The checker itself, on a small fake package: a leaf that imports the entry layer lazily,
    inside a function, is flagged; the same layer, a lower one and a listed exception are not."""
    pkg = tmp_path / "fakepkg"
    (pkg / "leaves").mkdir(parents=True)
    (pkg / "run").mkdir()
    files = {
        "__init__.py": "",
        "leaves/__init__.py": "",
        "leaves/table.py": "import os\n",
        "leaves/words.py": "from fakepkg.leaves import table\n",
        "leaves/bad.py": "def f():\n    from fakepkg.app import main\n    return main\n",
        "run/__init__.py": "",
        "run/loop.py": "from fakepkg.leaves.table import x\nimport fakepkg.app\n",
        "app.py": "from fakepkg.run import loop\nfrom fakepkg.leaves import words\n",
    }
    for rel, text in files.items():
        (pkg / rel).write_text(text)
    modules = {}
    for rel in files:
        name = "fakepkg." + rel.removesuffix(".py").replace("/", ".")
        modules[name.removesuffix(".__init__")] = pkg / rel
    graph = {n: _imports(p, n, modules, root="fakepkg") for n, p in modules.items()}
    doc = (
        "## Layers\n\n| layer | folders | holds |\n|---|---|---|\n"
        "| 0. leaves | `__init__.py`, `leaves/` | x |\n| 1. run | `run/` | y |\n"
        "| 2. entry | `app.py` | z |\n\n## Module map\n"
    )
    layers = _layer_table(doc, "fakepkg")
    assert layers == {"fakepkg": 0, "fakepkg.leaves": 0, "fakepkg.run": 1, "fakepkg.app": 2}
    assert _upward_imports(graph, layers) == [
        ("fakepkg.leaves.bad", 0, "fakepkg.app", 2),
        ("fakepkg.run.loop", 1, "fakepkg.app", 2),
    ]
    listed = {("fakepkg.run.loop", "fakepkg.app"): "on purpose"}
    assert _upward_imports(graph, layers, listed) == [("fakepkg.leaves.bad", 0, "fakepkg.app", 2)]


# -- docs/architecture.md matches the tree ----------------------------------------------------------


def _named_paths(text: str) -> set[str]:
    """The module paths (``run/rundir.py``, ``envs/native/``, ``app.py``) the module map names."""
    section = text.split("## Module map", 1)[1].split("\n## ", 1)[0]
    found = set()
    for line in section.splitlines():
        if not line.startswith("| `"):
            continue
        first, _, role = line[1:].partition(" | ")
        found |= set(re.findall(r"`([\w/]+(?:\.py|/))`", first))
        for folder in re.findall(r"`([\w/]+/)`", first):  # a package's files named in its row
            found |= {folder + f for f in re.findall(r"`(\w+\.py)`", role)}
    return found


def test_every_module_the_architecture_doc_names_exists():
    named = _named_paths(ARCHITECTURE.read_text())
    assert len(named) > 100
    gone = sorted(p for p in named if not (PACKAGE / p).exists())
    assert not gone, f"docs/architecture.md names modules that do not exist: {gone}"


def test_the_architecture_doc_names_every_module():
    """docs/architecture.md matches the tree: every module of rlexp has its line in the map."""
    named = _named_paths(ARCHITECTURE.read_text())
    missing = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if rel.name == "__init__.py" and rel.parent != Path("."):
            continue  # the folder's own docstring
        if rel.name == "__init__.py":
            continue
        if str(rel) not in named:
            missing.append(str(rel))
    assert not missing, f"docs/architecture.md's module map does not name {missing}"


def test_every_folder_says_what_it_holds_and_what_it_may_import():
    """A package's ``__init__`` docstring is its room's sign: what it holds, what it may import."""
    silent = []
    for init in sorted(PACKAGE.rglob("__init__.py")):
        if init.parent == PACKAGE:
            continue
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        if "May import" not in doc or len(doc.split("May import")[0].strip()) < 20:
            silent.append(str(init.parent.relative_to(PACKAGE)))
    assert not silent, (
        f"folders whose __init__ docstring does not say what they may import: {silent}"
    )
