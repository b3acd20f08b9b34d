"""The import layering: no two folders import each other, and dmpc's own modules are imported
at the top of a module unless a one-line reason says why not.

The nodes are the installed packages of pyproject.toml: each subpackage of dmpc (``dmpc.agents``
from agents/, ``dmpc.plant`` from plant/, ``dmpc.bus`` from bus/, ``dmpc.design``, ...) is one
node, and each top-level module of dmpc/ (``dmpc.system``, ``dmpc.cli``, ...) is a node of its
own. Every import counts: at the top, inside functions and under ``if TYPE_CHECKING``.
"""
from __future__ import annotations

import ast
import io
import tokenize
import tomllib
from dataclasses import dataclass
from pathlib import Path

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


def unexplained(imports: list[Import]) -> list[str]:
    """In-function imports of dmpc modules without a one-line reason after them."""
    return [f"{i.module}:{i.line} imports {i.target} inside a function without a reason comment"
            for i in imports if i.in_function and not _is_reason(i.reason)]


def _is_reason(comment: str) -> bool:
    return len(comment.split()) >= 3 and not comment.lower().startswith(NOT_A_REASON)


# ---------------------------------------------------------------------------- the tree as it is

def test_the_walker_sees_the_packages_and_their_imports():
    packages, imports = import_graph()
    assert packages["dmpc.agents"] == ROOT / "agents" and packages["dmpc.design"] == ROOT / "dmpc" / "design"
    seen = {(node_of(i.module, packages), node_of(i.target, packages)) for i in imports}
    assert ("dmpc.runtime", "dmpc.plant") in seen and ("dmpc.agents", "dmpc.bus") in seen
    assert ("dmpc.cli", "dmpc.agents") in seen  # an import inside a function counts
    assert node_of("dmpc.system", packages) == "dmpc.system" and node_of("dmpc.plant.node", packages) == "dmpc.plant"


def test_no_two_folders_import_each_other():
    packages, imports = import_graph()
    ties = two_way_ties(packages, imports)
    assert not ties, "folders that import each other:\n" + "\n".join(ties)


def test_imports_of_dmpc_inside_functions_say_why():
    _, imports = import_graph()
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
