"""Every parameter of every public function and method of dmpc is named in its docstring.

As python-control's ``tests/docstrings_test.py`` does, but with the rule this package writes its
docstrings by (numpy style, with shapes in the prose):

* **What is checked.** Every module of the installed package (pyproject.toml's ``packages``, the
  mapped folders agents/, plant/, bus/, coordinator/ included) whose name has no part starting
  with ``_`` (``__init__`` is the package itself and is checked); in it, every function and class
  defined there whose name does not start with ``_``; of a class, every method defined in it whose
  name does not start with ``_``, and its constructor (``__init__``, or the fields a dataclass
  makes it from).
* **What counts as named.** The parameter's name appears as a whole word in the docstring
  ``help()`` shows: ``x : ndarray`` in a ``Parameters`` section, ``x, y : float``, or in the prose
  (``from the global state x (n,)``, ````timeout```` seconds). A constructor's parameters may be
  named in the class docstring (its ``Parameters`` or ``Attributes``) or in ``__init__``'s. A
  method without a docstring of its own takes that of the method it overrides, as ``help()``
  does (``inspect.getdoc``).
* **Exempt.** ``self``, ``cls``, ``*args``, ``**kwargs`` and parameters whose names start with
  ``_``. A command of the command line documents its parameters in their ``typer`` ``help=``
  texts (what ``dmpc <command> --help`` shows); a pydantic model (a scenario's part) documents its
  fields in their ``Field(description=...)`` (the scenario reference and the JSON Schema show
  those), so each of its fields needs a description instead.
"""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import re
import tomllib
import typing
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXEMPT = {"self", "cls"}


def package_modules(root: Path = ROOT) -> list[str]:
    """The public modules of the package, from pyproject.toml's setuptools ``package-dir`` and ``packages``."""
    config = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapping, out = config["package-dir"], []
    for package in config["packages"]:
        head = max((p for p in mapping if package == p or package.startswith(p + ".")), key=len)
        rest = package[len(head):].lstrip(".")
        folder = (root / mapping[head]).joinpath(*rest.split(".")) if rest else root / mapping[head]
        for path in sorted(folder.glob("*.py")):
            if path.stem == "__init__":
                out.append(package)
            elif not path.stem.startswith("_"):
                out.append(f"{package}.{path.stem}")
    return [m for m in out if not any(part.startswith("_") for part in m.split("."))]


def named(name: str, doc: str) -> bool:
    """Whether ``name`` appears in ``doc`` as a whole word."""
    return re.search(rf"(?<![\w.]){re.escape(name)}(?!\w)", doc) is not None


def _parameters(function: typing.Callable) -> list[inspect.Parameter]:
    try:
        signature = inspect.signature(function)
    except (TypeError, ValueError):  # a builtin without a signature
        return []
    return [p for p in signature.parameters.values()
            if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD) and p.name not in EXEMPT and not p.name.startswith("_")]


def _typer_help(function: typing.Callable) -> set[str]:
    """The parameters documented by a ``typer`` ``help=`` (a command of the command line)."""
    try:
        hints = typing.get_type_hints(function, include_extras=True)
    except Exception:  # noqa: BLE001 - hints that do not resolve document nothing
        return set()
    out = set()
    for name, hint in hints.items():
        for extra in getattr(hint, "__metadata__", ()):
            if getattr(extra, "help", None):
                out.add(name)
    return out


def _is_pydantic(cls: type) -> bool:
    return any(base.__module__.startswith("pydantic") and base.__name__ == "BaseModel" for base in cls.__mro__)


def missing_in(module_name: str) -> list[str]:
    """``module:qualname: parameter`` for every parameter of the module's public functions and
    methods that its docstring does not name (for a pydantic model, every field without a description)."""
    module = importlib.import_module(module_name)
    out: list[str] = []

    def check(qualname: str, function: typing.Callable, doc: str) -> None:
        documented = _typer_help(function)
        for p in _parameters(function):
            if p.name not in documented and not named(p.name, doc):
                out.append(f"{module_name}:{qualname}: {p.name}")

    for name, obj in vars(module).items():
        if name.startswith("_") or getattr(obj, "__module__", None) != module_name:
            continue
        if inspect.isfunction(obj):
            check(name, obj, inspect.getdoc(obj) or "")
        elif inspect.isclass(obj):
            if _is_pydantic(obj):
                out.extend(f"{module_name}:{name}: {field} (no description)"
                           for field, info in obj.model_fields.items() if not info.description)
                continue
            class_doc = inspect.getdoc(obj) or ""
            init = obj.__dict__.get("__init__")
            if init is not None and inspect.isfunction(init):
                check(f"{name}.__init__", init, class_doc + "\n" + (init.__doc__ or ""))
            elif dataclasses.is_dataclass(obj) and "__init__" in obj.__dict__:
                check(f"{name}.__init__", obj.__init__, class_doc)
            for attr, member in obj.__dict__.items():
                if attr.startswith("_"):
                    continue
                function = member.__func__ if isinstance(member, (staticmethod, classmethod)) else member
                if inspect.isfunction(function):
                    check(f"{name}.{attr}", function, inspect.getdoc(getattr(obj, attr)) or "")
    return out


MODULES = package_modules()


def test_the_walker_sees_the_package_and_its_mapped_folders():
    assert "dmpc" in MODULES and "dmpc.core.system" in MODULES and "dmpc.bus.messages" in MODULES
    assert "dmpc.agents.trigger" in MODULES and "dmpc.coordinator.barrier" in MODULES
    assert not [m for m in MODULES if "._" in m]


@pytest.mark.parametrize("module_name", MODULES)
def test_every_parameter_is_named_in_its_docstring(module_name):
    missing = missing_in(module_name)
    assert not missing, "parameters not named in their docstrings:\n" + "\n".join(missing)


# ---------------------------------------------------------------------------- the check can fail

def test_a_parameter_missing_from_a_docstring_is_found(tmp_path, monkeypatch):
    (tmp_path / "docstring_sample.py").write_text('''
from dataclasses import dataclass


def documented(x, steps=1, *args, **kwargs):
    """Advance x (n,) by ``steps`` steps."""


def undocumented(x, rate):
    """Advance x (n,)."""


def _private(anything):
    pass


@dataclass
class Box:
    """A box.

    Attributes
    ----------
    lower : ndarray
    """

    lower: float
    upper: float

    def scaled(self, factor, _cache=None):
        """The box times a number."""


class Sub(Box):
    def scaled(self, factor, _cache=None):
        pass
''')
    monkeypatch.syspath_prepend(str(tmp_path))
    assert missing_in("docstring_sample") == [
        "docstring_sample:undocumented: rate",
        "docstring_sample:Box.__init__: upper",
        "docstring_sample:Box.scaled: factor",
        "docstring_sample:Sub.scaled: factor",  # the docstring it inherits does not name it either
    ]
    assert named("x", "from x (n,)") and named("steps", "``steps`` steps") and not named("x", "the box x_s")
    assert not named("rate", "the rates") and not named("k", "np.k")
