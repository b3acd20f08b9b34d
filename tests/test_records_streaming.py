"""Run records that do not grow in memory: rows on disk, arrays built at the end, readers of a cut log."""
from __future__ import annotations

import errno
import json
import math

import numpy as np
import pytest

from dmpc.records import columns as columns_module
from dmpc.records.columns import StepColumns, write_npz
from dmpc.records.files import ROWS
from dmpc.records.run_folder import RecordWriteError, RunFolder, trajectory_arrays
from dmpc.records.step_log import arrays_from_log, read_step_log
from dmpc.runtime.inprocess import simulate
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from tests.helpers.cli import call


@pytest.fixture(scope="module")
def paper_records():
    prepared = prepare(load_scenario("scenarios/paper.yaml", {"options.method": "ellipsoid-adaptive"}))
    records = []
    simulate(prepared, records.append)
    return prepared, records


def test_rows_on_disk_give_the_same_arrays_as_in_memory(tmp_path, paper_records):
    prepared, records = paper_records
    on_disk = StepColumns(prepared.system, tmp_path / ROWS)
    for rec in records:
        on_disk.add(rec)
    on_disk.close()
    a, b = on_disk.arrays(), trajectory_arrays(prepared.system, records)
    assert set(a) == set(b) | {"fallback_code"}
    for key in b:
        assert a[key].shape == b[key].shape and a[key].dtype == b[key].dtype, key
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert b["r"].shape == (31, 4)  # the ellipsoid levels get their final row too
    np.testing.assert_array_equal(b["x"][-1], records[-1].x_next)
    np.testing.assert_array_equal(b["plan_z_3"][7], records[7].plans_z[2])


def test_memory_does_not_hold_the_steps(tmp_path, paper_records):
    prepared, records = paper_records
    folder = RunFolder(tmp_path / "run", prepared.system)
    for rec in records:
        folder.append_step(rec)
    assert not hasattr(folder, "records")
    assert folder.columns._rows == [] and folder.columns.last is records[-1]
    row_bytes = (tmp_path / "run" / ROWS).stat().st_size
    assert row_bytes == len(records) * folder.columns.width * 8
    summary = folder.finish()
    assert not (tmp_path / "run" / ROWS).exists()
    with np.load(tmp_path / "run" / "trajectory.npz") as npz:
        expected = trajectory_arrays(prepared.system, records)
        for key in expected:
            np.testing.assert_array_equal(npz[key], expected[key], err_msg=key)
    assert summary["steps"] == 30


def test_write_npz_in_blocks_equals_savez(tmp_path, monkeypatch):
    monkeypatch.setattr(columns_module, "BLOCK_ROWS", 7)
    rng = np.random.default_rng(0)
    arrays = {"a": rng.normal(size=(50, 3, 2)), "b": np.arange(23), "c": np.array(["x", "yy"]), "d": np.zeros((0, 4)),
              "e": rng.normal(size=(50, 5)) > 0}
    write_npz(tmp_path / "t.npz", arrays)
    with np.load(tmp_path / "t.npz") as npz:
        assert set(npz.files) == set(arrays)
        for key, value in arrays.items():
            np.testing.assert_array_equal(npz[key], value)
            assert npz[key].dtype == value.dtype


def test_a_failed_row_write_is_cut_back_and_named(tmp_path, paper_records):
    prepared, records = paper_records
    folder = RunFolder(tmp_path / "run", prepared.system)
    for rec in records[:5]:
        folder.append_step(rec)
    folder.columns._file = _Failing(folder.columns._file)  # some bytes get through, then the disk is full
    with pytest.raises(RecordWriteError, match=r"cannot write .*\.steps\.f64: No space left on device"):
        folder.append_step(records[5])
    assert (tmp_path / "run" / ROWS).stat().st_size == 5 * folder.columns.width * 8
    log = read_step_log(tmp_path / "run" / "steps.jsonl")
    assert [s["k"] for s in log.steps] == [0, 1, 2, 3, 4] and not log.partial


class _Failing:
    """A file whose writes put 100 bytes through and then fail as on a full disk."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def write(self, data) -> int:
        self.inner.write(bytes(data)[:100])
        raise OSError(errno.ENOSPC, "No space left on device")

    def __getattr__(self, name):
        return getattr(self.inner, name)


def test_the_step_log_reader_skips_a_partial_last_line(tmp_path):
    path = tmp_path / "steps.jsonl"
    path.write_text(json.dumps({"k": 0}) + "\n" + json.dumps({"k": 1}) + "\n" + '{"k": 2, "x": [1.0, ')
    log = read_step_log(path)
    assert [s["k"] for s in log.steps] == [0, 1] and log.partial and "incomplete" in log.note
    path.write_text(json.dumps({"k": 0}) + "\n")
    assert not read_step_log(path).partial
    path.write_text("not json\n" + json.dumps({"k": 1}) + "\n")
    with pytest.raises(ValueError, match="line 1"):
        read_step_log(path)


def test_report_draws_a_run_that_ended_before_its_arrays_from_the_log(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    assert call(monkeypatch, capsys, "simulate", "scenarios/paper.yaml", "--out", str(out), "--quiet")[0] == 0
    with np.load(out / "trajectory.npz") as npz:
        x = npz["x"]
    (out / "trajectory.npz").unlink()
    text = (out / "steps.jsonl").read_text()
    (out / "steps.jsonl").write_text(text[:-50])  # the last line cut
    rebuilt = arrays_from_log(read_step_log(out / "steps.jsonl"))
    np.testing.assert_array_equal(rebuilt["x"], x[:30])  # 29 steps and the state after the last
    code, stdout, _ = call(monkeypatch, capsys, "report", str(out))
    assert code == 0
    assert "drawn from the 29 steps of steps.jsonl" in stdout and "incomplete and is skipped" in stdout
    assert len(list((out / "figures").glob("*.png"))) == 6


def test_the_files_a_run_was_loaded_from_are_not_written_again(tmp_path, paper_records):
    """``dmpc run`` writes scenario.yaml and design.json, then starts the plant on them: the
    plant's recorder leaves them as they are; given elsewhere, it writes its own copies."""
    from dmpc.records.files import DESIGN, SCENARIO
    from dmpc.records.session import RunRecorder

    prepared, _ = paper_records
    run = tmp_path / "run"
    run.mkdir()
    for name in (SCENARIO, DESIGN):
        (run / name).write_text(f"as the launcher wrote {name}\n")
    roundabout = tmp_path / ".." / tmp_path.name / "run" / DESIGN  # the same file by another path
    with RunRecorder(run, prepared, show_progress=False, sources=[run / SCENARIO, roundabout]):
        pass
    assert [(run / name).read_text() for name in (SCENARIO, DESIGN)] == \
        [f"as the launcher wrote {name}\n" for name in (SCENARIO, DESIGN)]
    with RunRecorder(tmp_path / "other", prepared, show_progress=False, sources=[run / SCENARIO, run / DESIGN]):
        pass
    assert json.loads((tmp_path / "other" / DESIGN).read_text())["digest"] == prepared.digest
    assert "subsystems" in (tmp_path / "other" / SCENARIO).read_text()


def test_the_step_log_line_equals_the_json_of_the_step_line(paper_records):
    """steps.jsonl is written by a C encoder; it must read back as the strict-JSON step line:
    NaN and infinities as null, arrays (strided ones too) as lists, numpy scalars as numbers."""
    from dataclasses import replace

    from dmpc.records.run_folder import step_line, step_text

    _, records = paper_records
    rec = records[3]
    odd = replace(rec, x=np.arange(2 * rec.x.size, dtype=float)[::2], beta=np.float64(np.inf), J=math.nan,
                  latency=[math.nan] + list(rec.latency[1:]), alpha=np.full(rec.alpha.shape, -np.inf),
                  qp_iterations=[np.int64(q) for q in rec.qp_iterations], note="k=3: agent 1 lost")
    for r in (rec, odd, records[-1]):
        text = step_text(r)
        assert text.endswith("\n") and text.count("\n") == 1
        assert json.loads(text) == json.loads(json.dumps(step_line(r), allow_nan=False))
    parsed = json.loads(step_text(odd))
    assert parsed["beta"] is None and parsed["J"] is None and parsed["latency"][0] is None
    assert parsed["alpha"] == [None] * rec.alpha.size and parsed["x"] == list(range(0, 2 * rec.x.size, 2))
