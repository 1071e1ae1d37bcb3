"""The house in floors, and no import cycles among first-party modules.

Every package has a rank (`FLOORS`, the table of docs/architecture.md); a module imports only from
its own package or from packages of a lower rank, imports inside functions included, so a
newcomer knows from a file's folder what it may touch, and no library module reaches up into a
command.

A cycle among top-level imports makes the order modules happen to be imported in decide whether a
name exists yet; the usual way out, hiding one edge inside a function, keeps the tangle and only
moves the failure. So both are checked: the graph of top-level imports, and the graph with the
imports inside functions added (those are fine for keeping torch, PettingZoo or matplotlib out of
light processes and the CLI quick to start, but not for closing a cycle). The graph is read from
the source with `ast` (nothing is imported), so a cycle is caught even between modules no test
imports together.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The floors, lowest first: each package may import only those below it (docs/architecture.md).
FLOORS: list[tuple[str, ...]] = [
    ("hammer.protocol",),  # the contract: messages, keys, the session, access rules
    ("hammer.envs",),  # environments behind one VecEnv contract
    ("hammer.learning", "hammer.faults"),  # the maths and networks; link faults, counters and step logs
    ("hammer.runtime",),  # what every role process shares: the loop, weights intake, settings, process setup
    ("hammer.central_agent", "hammer.env_host", "hammer.local_agent", "hammer.learner"),  # the roles
    ("hammer.serve",),  # a trained team served: bundles, the policy server, the edge agent
    ("hammer.deploy",),  # a whole run launched and supervised
    ("hammer.experiments", "hammer.view"),  # sweeps, reports, analyses; the web view of run directories
    ("hammer.benchmarks",),  # measures everything below, from outside
    ("hammer",),  # the commands (hammer.commands, hammer.cli) and the console entry
]
RANK = {pkg: rank for rank, floor in enumerate(FLOORS) for pkg in floor}


def package_dirs() -> dict[str, Path]:
    """Each import package pyproject installs (`hammer.protocol`, ...) and the folder it comes from."""
    mapping = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return {name: ROOT / folder for name, folder in mapping.items()}


def first_party_packages() -> list[str]:
    """The installed packages: `hammer` and its sub-packages, by import name."""
    return sorted(package_dirs())


def package_of(module: str) -> str:
    """The installed package a module belongs to (`hammer.protocol.session` -> `hammer.protocol`;
    the modules of `hammer` itself, e.g. `hammer.cli`, -> `hammer`)."""
    parts = module.split(".")
    sub = ".".join(parts[:2])
    return sub if sub in package_dirs() else "hammer"


def module_files() -> dict[str, Path]:
    files = {}
    for pkg, folder in package_dirs().items():
        for path in folder.rglob("*.py"):  # hammer/commands/ is the one sub-package of a folder
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join([pkg, *(parts[:-1] if parts[-1] == "__init__" else parts)])
            files[name] = path
    return files


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


def _every_import(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Every import that can run, anywhere in the module; those under `if TYPE_CHECKING:` never run
    (they name a type for annotations only), so they close no cycle."""
    found: list[ast.Import | ast.ImportFrom] = []
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import | ast.ImportFrom):
            found.append(node)
        elif _is_type_checking(node):
            stack.extend(node.orelse)
        else:
            stack.extend(ast.iter_child_nodes(node))
    return found


def _top_level_imports(tree: ast.Module) -> list[ast.Import | ast.ImportFrom]:
    """Imports that run when the module is imported: module level, including inside if/try blocks,
    but not inside functions or classes, and not under `if TYPE_CHECKING:`."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(body: list[ast.stmt]) -> None:
        for node in body:
            if isinstance(node, ast.Import | ast.ImportFrom):
                found.append(node)
            elif isinstance(node, ast.If):
                if not _is_type_checking(node):
                    visit(node.body)
                visit(node.orelse)
            elif isinstance(node, ast.Try):
                for block in (node.body, node.orelse, node.finalbody, *(h.body for h in node.handlers)):
                    visit(block)

    visit(tree.body)
    return found


def import_graph(inside_functions: bool = False) -> dict[str, set[str]]:
    """module -> the first-party modules its imports load (a package's __init__ included): its
    top-level imports, and with `inside_functions` every import anywhere in it. The root package
    `hammer`, which Python imports before any `hammer.x`, is no edge: it imports nothing when
    imported (checked below), only its lazy front door does, on first use of one of its names."""
    files = module_files()
    graph: dict[str, set[str]] = {}
    for mod, path in files.items():
        is_pkg = path.name == "__init__.py"
        edges: set[str] = set()
        tree = ast.parse(path.read_text(), str(path))
        for node in (_every_import if inside_functions else _top_level_imports)(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    anchor = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join([*anchor, base] if base else anchor)
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            for target in targets:
                parts = target.split(".")
                for i in range(1, len(parts) + 1):  # importing a.b.c runs a and a.b first
                    name = ".".join(parts[:i])
                    if name in files and name != mod and name != "hammer":
                        edges.add(name)
        graph[mod] = edges
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
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
            connect(v)
    return found


def test_the_graph_covers_every_first_party_package():
    graph = import_graph()
    assert {package_of(m) for m in graph} == set(first_party_packages())
    assert "hammer.learning.config" in graph["hammer.learning.trainer"]  # the reader sees real edges


def test_the_source_imports_only_through_the_one_package():
    """Every first-party import names `hammer.`: a bare `protocol` or `learning` would load a second
    copy of the module in a checkout, and nothing at all from the wheel."""
    bare = set()
    folders = {path.name for path in package_dirs().values()} - {"hammer"}
    for mod, path in module_files().items():
        for node in _every_import(ast.parse(path.read_text(), str(path))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            bare |= {f"{mod}: {n}" for n in names if node.__class__ is ast.Import or not node.level
                     if n.split(".")[0] in folders}
    assert bare == set()


def test_no_import_cycles_among_first_party_modules():
    assert cycles(import_graph()) == []


def test_no_cycle_hidden_behind_an_import_inside_a_function():
    assert cycles(import_graph(inside_functions=True)) == []


def test_a_cycle_is_found():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_the_library_does_not_import_the_benchmarks():
    """Benchmarks measure the library from outside; only the CLI wires `hammer bench` to them."""
    graph = import_graph(inside_functions=True)
    importers = {m for m, edges in graph.items() if not m.startswith("hammer.benchmarks")
                 and any(e.startswith("hammer.benchmarks") for e in edges)}
    assert importers == {"hammer.commands.bench"}


def test_every_package_has_a_floor():
    assert sorted(RANK) == first_party_packages()


def test_each_package_imports_only_from_the_floors_below_it():
    """Function-level imports counted: hiding an import in a function does not move a package's floor."""
    up = sorted(f"{m} -> {e}" for m, edges in import_graph(inside_functions=True).items() for e in edges
                if package_of(m) != package_of(e) and RANK[package_of(e)] >= RANK[package_of(m)])
    assert up == []


def test_the_root_package_imports_nothing_when_imported():
    """Everything imports `hammer/__init__.py` first: it imports nothing at module level (the front door,
    hammer/api.py, loads on first use of one of its names)."""
    tree = ast.parse((ROOT / "hammer" / "__init__.py").read_text())
    # os only: the interpreter's start (site) has loaded it before any script runs, so it costs nothing
    assert [ast.unparse(n) for n in _top_level_imports(tree)] in ([], ["import os as _os"])
