"""examples/: the notebook executes (nbclient) and the scripts run, printing what they promise."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def test_the_quickstart_notebook_executes_and_draws_its_figures():
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    notebook = nbformat.read(EXAMPLES / "quickstart.ipynb", as_version=4)
    nbclient.NotebookClient(notebook, timeout=240, kernel_name="python3",
                            resources={"metadata": {"path": str(EXAMPLES)}}).execute()
    outputs = [out for cell in notebook.cells if cell.cell_type == "code" for out in cell.outputs]
    assert not [out for out in outputs if out.output_type == "error"]
    text = "".join(out.get("text", "") for out in outputs if out.output_type == "stream")
    assert "verdict ok" in text and "p [m]" in text and "dt = 0.1 s, local-zoh" in text
    assert "cart 1 p [m]: asked 1, reached 1.0000" in text and "cart 3 p [m]: asked -1, reached -0.99" in text
    images = [out for out in outputs if "image/png" in out.get("data", {})]
    assert len(images) == 6  # states, inputs, cost: of the carts, then of the carts with setpoints


def _script(name: str, *args: str) -> str:
    done = subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_own_system_script(tmp_path):
    out = _script("own_system.py", "--out", str(tmp_path), "--steps", "20")
    assert "verdict ok, 20 steps" in out and "v [m/s]" in out
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["own_system_cost.png", "own_system_inputs.png",
                                                               "own_system_states.png"]


def test_continuous_carts_script():
    out = _script("continuous_carts.py", "--steps", "20")
    assert "exact-zoh without truncate: discretisation:" in out and "dropped entries up to 0.000134" in out
    assert "plant nominal (controllers: local-zoh): verdict ok" in out and "plant exact" in out


def test_disturbance_script():
    lines = _script("disturbance_tube.py", "--steps", "25").splitlines()
    assert lines[0].startswith("tube none  : verdict failed, largest state-bound excess +")
    assert lines[1].startswith("tube robust: verdict ok, largest state-bound excess -")


def test_own_plant_script():
    out = _script("own_plant.py", "--steps", "20")
    assert "own plant:    verdict ok" in out and "'function': 'plants:carts_stiffening_springs'" in out


def test_rooms_setpoints_script(tmp_path):
    out = _script("rooms_setpoints.py", "--out", str(tmp_path))
    assert "verdict ok, 288 steps of 300 s, 0 fallbacks" in out
    rows = [line.split() for line in out.splitlines() if line.startswith("room") and line.endswith(" K")]
    assert [(r[0], r[1], r[2], r[3]) for r in rows] == [
        ("room1", "22:00", "03:00", "19.5"), ("room1", "03:00", "09:00", "20.5"), ("room1", "09:00", "22:00", "20.0"),
        ("room2", "22:00", "03:00", "19.5"), ("room2", "03:00", "09:00", "20.5"), ("room2", "09:00", "22:00", "20.0"),
        ("room3", "22:00", "03:00", "20.5"), ("room3", "03:00", "22:00", "21.0"),
        ("room4", "22:00", "03:00", "20.5"), ("room4", "03:00", "22:00", "21.0"),
        ("room5", "22:00", "02:00", "19.5"), ("room5", "02:00", "09:00", "21.5"), ("room5", "09:00", "22:00", "20.5")]
    assert all(abs(float(r[-2])) <= 0.3 for r in rows)  # each room near its setpoint when the next takes over
    assert sorted(p.name for p in tmp_path.glob("*.png")) == ["rooms_setpoints_cost.png", "rooms_setpoints_inputs.png",
                                                               "rooms_setpoints_states.png"]
