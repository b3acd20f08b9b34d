"""The import layering: the packages stand in a declared order of layers, each importing only
the layers below it, so no two folders import each other and no import goes round in a circle;
the top of dmpc/ holds only the package's own ``__init__``; and dmpc's own modules are imported at
the top of a module unless a one-line reason says why not.

The nodes are the installed packages of pyproject.toml: each subpackage of dmpc (``dmpc.agents``
from agents/, ``dmpc.plant`` from plant/, ``dmpc.coordinator`` from coordinator/, ``dmpc.bus``
from bus/, ``dmpc.core``, ``dmpc.offline``, ...) is one node, and a module directly in dmpc/ would
be a node of its own. Every import counts: at the top, inside functions and under
``if TYPE_CHECKING``.
"""
from __future__ import annotations

import ast
import io
import tokenize
import tomllib
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOT_A_REASON = ("noqa", "type:", "pragma", "fmt:", "isort:")


@dataclass(frozen=True)
class Import:
    """One import of a dmpc module: where it is and what it reaches."""

    module: str
    line: int
    target: str
    in_function: bool
    reason: str  # the statement's trailing comment ("" if none)


def package_dirs(root: Path = ROOT) -> dict[str, Path]:
    """Package name -> folder, from pyproject.toml's setuptools ``package-dir`` and ``packages``."""
    config = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapping = config["package-dir"]
    out = {}
    for package in config["packages"]:
        head = max((p for p in mapping if package == p or package.startswith(p + ".")), key=len)
        rest = package[len(head):].lstrip(".")
        out[package] = (root / mapping[head]).joinpath(*rest.split(".")) if rest else root / mapping[head]
    return out


def modules_of(packages: dict[str, Path]) -> dict[str, Path]:
    """Module name -> file for every module of the packages (a package's own file is its __init__)."""
    out = {}
    for package, folder in packages.items():
        for path in sorted(folder.glob("*.py")):
            out[package if path.stem == "__init__" else f"{package}.{path.stem}"] = path
    return out


def node_of(module: str, packages: dict[str, Path]) -> str:
    """A subpackage of dmpc for its modules; a top-level module of dmpc for itself."""
    parts = module.split(".")
    sub = ".".join(parts[:2])
    return sub if len(parts) >= 2 and sub in packages else module


def _comments(source: str) -> dict[int, str]:
    return {tok.start[0]: tok.string.lstrip("#").strip()
            for tok in tokenize.generate_tokens(io.StringIO(source).readline) if tok.type == tokenize.COMMENT}


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    """The imports of dmpc modules in one file."""
    source = path.read_text()
    tree = ast.parse(source)
    comments = _comments(source)
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    package = module if path.stem == "__init__" else module.rpartition(".")[0]

    def known(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    def inside_function(node: ast.AST) -> bool:
        node = parents.get(node)
        while node is not None:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                return True
            node = parents.get(node)
        return False

    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = {known(alias.name) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            targets = {f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else known(base)
                       for alias in node.names}
        else:
            continue
        reason = next((comments[line] for line in range(node.lineno, node.end_lineno + 1) if line in comments), "")
        out.extend(Import(module, node.lineno, target, inside_function(node), reason)
                   for target in sorted(t for t in targets if t is not None))
    return out


def import_graph(root: Path = ROOT) -> tuple[dict[str, Path], list[Import]]:
    packages = package_dirs(root)
    modules = modules_of(packages)
    return packages, [imp for module, path in modules.items() for imp in imports_of(module, path, modules)]


def two_way_ties(packages: dict[str, Path], imports: list[Import]) -> list[str]:
    """One line per pair of nodes that import each other, naming the imports both ways."""
    edges: dict[tuple[str, str], list[Import]] = {}
    for imp in imports:
        a, b = node_of(imp.module, packages), node_of(imp.target, packages)
        if a != b:
            edges.setdefault((a, b), []).append(imp)
    ties = []
    for (a, b), forward in sorted(edges.items()):
        if a < b and (b, a) in edges:
            shown = "; ".join(f"{i.module}:{i.line} -> {i.target}" for i in forward + edges[(b, a)])
            ties.append(f"{a} <-> {b}: {shown}")
    return ties


def cycles(packages: dict[str, Path], imports: list[Import]) -> list[list[str]]:
    """The circles of nodes that import each other, directly or through others (each sorted)."""
    edges: dict[str, set[str]] = {}
    for imp in imports:
        a, b = node_of(imp.module, packages), node_of(imp.target, packages)
        if a != b:
            edges.setdefault(a, set()).add(b)

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in edges.get(todo.pop(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    reached = {node: reach(node) for node in edges}
    found = {tuple(sorted(n for n in reached if n in reached[node] and node in reached[n]))
             for node in reached if node in reached[node]}
    return sorted(list(c) for c in found)


def layer_of(node: str, layers: tuple[tuple[str, ...], ...]) -> int | None:
    """The index of the layer that holds ``node`` (None if no layer does)."""
    return next((i for i, layer in enumerate(layers) if node in layer), None)


def upward(packages: dict[str, Path], imports: list[Import], layers: tuple[tuple[str, ...], ...]) -> list[str]:
    """One line per import of a node in the same layer or a higher one (a node's own modules aside)."""
    found = []
    for imp in imports:
        a, b = node_of(imp.module, packages), node_of(imp.target, packages)
        if a == b:
            continue
        la, lb = layer_of(a, layers), layer_of(b, layers)
        if la is not None and lb is not None and lb >= la:
            where = "the same layer" if la == lb else f"layer {lb}, above its own {la}"
            found.append(f"{imp.module}:{imp.line} imports {imp.target}, of {where}")
    return found


def unexplained(imports: list[Import]) -> list[str]:
    """In-function imports of dmpc modules without a one-line reason after them."""
    return [f"{i.module}:{i.line} imports {i.target} inside a function without a reason comment"
            for i in imports if i.in_function and not _is_reason(i.reason)]


def _is_reason(comment: str) -> bool:
    return len(comment.split()) >= 3 and not comment.lower().startswith(NOT_A_REASON)


# ---------------------------------------------------------------------------- the tree as it is

LAYERS: tuple[tuple[str, ...], ...] = (
    ("dmpc.core", "dmpc.terminal"),  # the numerical core; what the terminal shows and the exit codes
    ("dmpc.offline", "dmpc.bus", "dmpc.estimation"),  # offline design, transport; offset-free estimation and
    # its targets (the setpoint targets build on them)
    ("dmpc.methods", "dmpc.tracking", "dmpc.security"),  # the methods' terminal sets; setpoint targets and the
    # reference governor; TLS, access control, checks of what arrives
    ("dmpc.cooperative",),  # the cooperative method's iterate and agent QPs (around setpoint targets)
    ("dmpc.scenario",),  # scenario files
    ("dmpc.prepared",),  # a prepared run: what every role is built from
    ("dmpc.records",),  # the run folder
    ("dmpc.agents", "dmpc.plant"),  # the agents; the plant
    ("dmpc.coordinator",),  # the step barrier, its node and process
    ("dmpc.runtime",),  # a run in this process, as processes, or by direct calls
    ("dmpc.setup",),  # from a scenario to a prepared run (it tries the first step)
    ("dmpc.evaluation", "dmpc.watch", "dmpc.plots"),  # comparisons, the live view, figures
    ("dmpc.bench",),  # benchmarks
    ("dmpc.api", "dmpc.cli"),  # the entry points: Python and the command line
    ("dmpc",),  # the package: the public names, loaded on first use
)
"""The layers, lowest first: a node imports only nodes of lower layers."""


@pytest.fixture(scope="module")
def tree() -> tuple[dict[str, Path], list[Import]]:
    """The package's folders and the imports of its modules, each module parsed once for the
    tests of the tree as it is (none of them changes what it is given)."""
    return import_graph()


def test_the_walker_sees_the_packages_and_their_imports(tree):
    packages, imports = tree
    assert packages["dmpc.agents"] == ROOT / "agents" and packages["dmpc.offline"] == ROOT / "dmpc" / "offline"
    assert packages["dmpc.coordinator"] == ROOT / "coordinator"
    seen = {(node_of(i.module, packages), node_of(i.target, packages)) for i in imports}
    assert ("dmpc.runtime", "dmpc.coordinator") in seen and ("dmpc.agents", "dmpc.bus") in seen
    assert ("dmpc.cli", "dmpc.agents") in seen  # an import inside a function counts
    assert ("dmpc.prepared", "dmpc.scenario") in seen  # an import under TYPE_CHECKING counts
    assert node_of("dmpc.core.system", packages) == "dmpc.core" and node_of("dmpc.coordinator.node", packages) == "dmpc.coordinator"
    assert node_of("dmpc.cli.forkserver", packages) == "dmpc.cli"


def test_every_package_has_one_layer():
    packages = package_dirs()
    placed = [node for layer in LAYERS for node in layer]
    assert sorted(placed) == sorted(set(placed)), "a package is in two layers"
    assert sorted(placed) == sorted(packages), "packages without a layer, or layers without a package"


def test_no_package_imports_its_layer_or_a_higher_one(tree):
    packages, imports = tree
    found = upward(packages, imports, LAYERS)
    assert not found, "imports against the layers:\n" + "\n".join(found)


def test_no_import_goes_round_in_a_circle(tree):
    packages, imports = tree
    assert cycles(packages, imports) == []


def test_no_two_folders_import_each_other(tree):
    packages, imports = tree
    ties = two_way_ties(packages, imports)
    assert not ties, "folders that import each other:\n" + "\n".join(ties)


def test_the_top_of_dmpc_holds_only_the_package_itself():
    """Every module of dmpc/ is in a folder that says what it holds; no package imports the top."""
    assert sorted(path.name for path in (ROOT / "dmpc").glob("*.py")) == ["__init__.py"]


def test_imports_of_dmpc_inside_functions_say_why(tree):
    _, imports = tree
    missing = unexplained(imports)
    assert not missing, "\n".join(missing)


# ---------------------------------------------------------------------------- the checks can fail

def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    (tmp_path / "pyproject.toml").write_text(
        '[tool.setuptools]\npackage-dir = { "dmpc" = "dmpc", "dmpc.agents" = "agents" }\n'
        'packages = ["dmpc", "dmpc.runtime", "dmpc.agents"]\n')
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path


def test_a_two_way_tie_is_found_and_named(tmp_path):
    root = _tree(tmp_path, {
        "dmpc/__init__.py": "", "dmpc/system.py": "",
        "dmpc/runtime/__init__.py": "", "dmpc/runtime/setup.py": "from dmpc.system import x\n",
        "dmpc/runtime/launch.py": "from dmpc.agents.process import run\n",
        "agents/__init__.py": "", "agents/process.py": "from dmpc.runtime import setup\n",
    })
    packages, imports = import_graph(root)
    ties = two_way_ties(packages, imports)
    assert len(ties) == 1
    assert ties[0].startswith("dmpc.agents <-> dmpc.runtime")
    assert "dmpc.agents.process:1 -> dmpc.runtime.setup" in ties[0]
    assert "dmpc.runtime.launch:1 -> dmpc.agents.process" in ties[0]


def test_an_import_inside_a_function_needs_a_reason(tmp_path):
    root = _tree(tmp_path, {
        "dmpc/__init__.py": "", "dmpc/system.py": "",
        "dmpc/runtime/__init__.py": "",
        "dmpc/runtime/setup.py": ("def f():\n    from dmpc.system import x\n\n\n"
                                  "def g():\n    from dmpc.system import y  # start-up time: numpy only here\n\n\n"
                                  "def h():\n    from dmpc.system import z  # noqa: F401\n\n\n"
                                  "def k():\n    import json\n"),
        "agents/__init__.py": "",
    })
    _, imports = import_graph(root)
    missing = unexplained(imports)
    assert [m.split(" ")[0] for m in missing] == ["dmpc.runtime.setup:2", "dmpc.runtime.setup:10"]


def test_an_import_against_the_layers_is_found_inside_a_function_and_under_type_checking(tmp_path):
    root = _tree(tmp_path, {
        "dmpc/__init__.py": "", "dmpc/system.py": "",
        "dmpc/runtime/__init__.py": "", "dmpc/runtime/setup.py": "from dmpc.system import x\n",
        "agents/__init__.py": "",
        "agents/process.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from dmpc.runtime import setup\n"
                              "def f():\n    from dmpc.runtime.setup import y  # start-up time: only here\n"),
    })
    packages, imports = import_graph(root)
    layers = (("dmpc.system",), ("dmpc.agents",), ("dmpc.runtime",), ("dmpc",))
    found = upward(packages, imports, layers)
    assert [line.split(" ")[0] for line in found] == ["dmpc.agents.process:3", "dmpc.agents.process:5"]
    assert "of layer 2, above its own 1" in found[0]
    assert upward(packages, imports, (("dmpc.system",), ("dmpc.runtime",), ("dmpc.agents",), ("dmpc",))) == []
    assert "of the same layer" in upward(packages, imports, (("dmpc.system",), ("dmpc.agents", "dmpc.runtime")))[0]


def test_a_circle_of_three_folders_is_found(tmp_path):
    """No two of them import each other, yet the imports go round."""
    root = _tree(tmp_path, {
        "dmpc/__init__.py": "",
        "dmpc/runtime/__init__.py": "", "dmpc/runtime/launch.py": "from dmpc.agents.process import run\n",
        "agents/__init__.py": "", "agents/process.py": "def f():\n    from dmpc.watch import view  # only here\n",
        "dmpc/watch/__init__.py": "", "dmpc/watch/view.py": "from dmpc.runtime import launch\n",
    })
    (root / "pyproject.toml").write_text(
        '[tool.setuptools]\npackage-dir = { "dmpc" = "dmpc", "dmpc.agents" = "agents" }\n'
        'packages = ["dmpc", "dmpc.runtime", "dmpc.watch", "dmpc.agents"]\n')
    packages, imports = import_graph(root)
    assert two_way_ties(packages, imports) == []
    assert cycles(packages, imports) == [["dmpc.agents", "dmpc.runtime", "dmpc.watch"]]
