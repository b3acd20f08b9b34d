"""mypy sees every module under the name the package imports it by (pyproject.toml, [tool.mypy]).

setuptools installs agents/, plant/, bus/ and coordinator/ as dmpc.agents, dmpc.plant, dmpc.bus and
dmpc.coordinator (``package-dir``); typecheck/dmpc/ holds the same mapping as symlinks, on mypy's
path. These tests check that the symlinks match ``package-dir``, that the configuration checks
every module and leaves none out, and that a misuse of a ``dmpc.bus`` class written in a dmpc/
module is reported (a copy of the tree's layout in a temporary folder, checked with the project's
configuration through ``mypy.api.run``).
"""
from __future__ import annotations

import os
import re
import shutil
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / "typecheck" / "dmpc"
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())


def mapped_folders() -> dict[str, str]:
    """Subpackage of dmpc -> its top-level folder, from setuptools' ``package-dir`` (``dmpc`` itself aside)."""
    mapping = CONFIG["tool"]["setuptools"]["package-dir"]
    return {name.split(".", 1)[1]: folder for name, folder in mapping.items() if name != "dmpc"}


def test_the_layout_maps_the_folders_as_setuptools_does():
    folders = mapped_folders()
    assert set(folders) == {"agents", "plant", "bus", "coordinator"}
    assert sorted(p.name for p in LAYOUT.iterdir()) == sorted([*folders, "__init__.py"])
    for sub, folder in folders.items():
        link = LAYOUT / sub
        assert link.is_symlink() and link.resolve() == (ROOT / folder).resolve(), sub
    init = LAYOUT / "__init__.py"
    assert init.is_symlink() and init.resolve() == (ROOT / "dmpc" / "__init__.py").resolve()


def test_the_configuration_checks_every_module_and_leaves_none_out():
    mypy = CONFIG["tool"]["mypy"]
    assert sorted(mypy["files"]) == sorted(["dmpc", *(f"typecheck/dmpc/{sub}" for sub in mapped_folders())])
    assert mypy["mypy_path"] == "$MYPY_CONFIG_FILE_DIR/typecheck"
    assert "ignore_missing_imports" not in mypy and "ignore_errors" not in mypy
    for override in mypy.get("overrides", []):
        assert "ignore_errors" not in override, override["module"]
        if override.get("ignore_missing_imports"):  # third-party packages only, each named
            assert all(not m.startswith(("dmpc", *mapped_folders())) and m.endswith(".*") for m in override["module"])
    strict = next(o for o in mypy["overrides"] if o.get("disallow_untyped_defs"))
    assert {"dmpc.core.*", "dmpc.tracking.*", "dmpc.agents.trigger"} <= set(strict["module"])


PLANTED = '''\
from dmpc.bus.messages import Kept


def sent_at(notice: Kept) -> float:
    return notice.sent_at


def plan_of(notice: Kept) -> object:
    return notice.z  # a Kept notice carries no plan


reveal_type(Kept)
'''


@pytest.mark.slow
def test_a_misuse_of_a_bus_class_in_a_dmpc_module_is_reported(tmp_path, monkeypatch):
    """The tree as mypy sees it, in a temporary folder: dmpc/ with one more module (symlinks to the
    rest), the mapped folders and typecheck/ as symlinks, and pyproject.toml copied."""
    api = pytest.importorskip("mypy.api")
    (tmp_path / "dmpc").mkdir()
    for entry in (ROOT / "dmpc").iterdir():
        if entry.name != "__pycache__":
            (tmp_path / "dmpc" / entry.name).symlink_to(entry)
    (tmp_path / "dmpc" / "planted.py").write_text(PLANTED)
    for name in [*mapped_folders().values(), "typecheck"]:
        (tmp_path / name).symlink_to(ROOT / name)
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    monkeypatch.chdir(tmp_path)
    out, err, _ = api.run(["--cache-dir", str(tmp_path / ".mypy_cache"), "--no-error-summary",
                           os.path.join("dmpc", "planted.py")])
    planted = [line for line in out.splitlines() if line.startswith(os.path.join("dmpc", "planted.py"))]
    assert not err, err
    errors = [line for line in planted if ": error:" in line]
    assert len(errors) == 1 and re.search(r'planted\.py:9: error: "Kept" has no attribute "z"', errors[0]), out
    reveal = next(line for line in planted if "Revealed type" in line)
    assert "sender: str" in reveal and reveal.endswith('-> dmpc.bus.messages.Kept"'), reveal  # bus/messages.py's class
