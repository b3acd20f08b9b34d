"""Reading a run folder (docs/records.md) into a RunState, also while the run still writes it.

``steps.jsonl`` is read from where the last read stopped, up to its last complete line: the
line being written is left for the next read. ``summary.json`` is replaced atomically by the
writer, and read again whenever it changes (``dmpc run`` rewrites it with the agents' reports).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from dmpc.core.errors import InputError
from dmpc.prepared.bundle import load_bundle
from dmpc.records.files import BUNDLE, DESIGN, SCENARIO, STEP_LOG, SUMMARY
from dmpc.scenario import load_scenario
from dmpc.setup import prepare
from dmpc.watch.meta import RunMeta, meta_json
from dmpc.watch.state import RunState

CHUNK = 8 << 20  # bytes of the step log read at most per poll, so a huge log cannot stall the page


class FolderError(InputError, ValueError):
    """The path is not a run folder, or its description cannot be read."""


def folder_meta(path: Path, run_id: str = "") -> RunMeta:
    """The description of the run in folder ``path`` from ``scenario.yaml`` and ``design.json``
    (with the scenario's names and units), else from ``run.json``; ``run_id`` if known.

    Raises
    ------
    FolderError
        Neither can be read.
    """
    path = Path(path)
    try:
        prepared = _from_scenario(path)
    except FolderError:
        if not (path / BUNDLE).is_file():
            raise

        try:
            prepared = load_bundle(path / BUNDLE)
        except ValueError as exc:
            raise FolderError(str(exc)) from None
    return RunMeta.from_json(meta_json(prepared, run_id or path.name))


def _from_scenario(path: Path):
    if not (path / SCENARIO).is_file():
        raise FolderError(f"{path} is not a run folder (it has no {SCENARIO})")

    try:
        design = json.loads((path / DESIGN).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise FolderError(f"{path}: cannot read {DESIGN} ({exc})") from None
    try:
        return prepare(load_scenario(path / SCENARIO), design_data=design)
    except Exception as exc:  # noqa: BLE001 - a scenario or design that does not load: say which folder
        raise FolderError(f"{path}: cannot read the run's scenario ({type(exc).__name__}: {exc})") from None


class FolderFeed:
    """Feeds a RunState from a run folder.

    Parameters
    ----------
    path : path-like
    state : RunState
    steps : bool
        Read ``steps.jsonl`` as it grows. False (when the steps come over the bus) reads it
        once the summary is there, to fill any step the bus did not deliver.
    """

    def __init__(self, path, state: RunState, steps: bool = True) -> None:
        self.path = Path(path)
        self.state = state
        self.steps = steps
        self._offset = 0
        self._summary_stamp: tuple[int, int] | None = None

    def load_meta(self) -> None:
        """Read the run's description into the state (FolderError if it cannot be read)."""
        self.state.set_meta(folder_meta(self.path, self.state.run_id))

    def poll(self) -> None:
        """Read what was added since the last poll; never raises on a half-written folder."""
        if self.state.meta is None:
            try:
                self.load_meta()
            except FolderError:
                return
        self._read_summary()
        if self.steps or self.state.summary is not None:
            self._read_steps()

    def _read_steps(self) -> None:
        try:
            with open(self.path / STEP_LOG, "rb") as fh:
                fh.seek(self._offset)
                chunk = fh.read(CHUNK)
        except FileNotFoundError:
            return
        complete = chunk.rfind(b"\n") + 1
        self._offset += complete
        for raw in chunk[:complete].splitlines():
            if not raw.strip():
                continue
            try:
                line = json.loads(raw)
            except (UnicodeDecodeError, json.JSONDecodeError) as exc:
                self.state.note_dropped(f"{STEP_LOG}: a line that is not JSON ({exc})")
                continue
            if isinstance(line, dict):
                self.state.add_step(line)
            else:
                self.state.note_dropped(f"{STEP_LOG}: a line that is not an object")

    def _read_summary(self) -> None:
        path = self.path / SUMMARY
        try:
            st = os.stat(path)
        except FileNotFoundError:
            return
        stamp = (st.st_mtime_ns, st.st_size)
        if stamp == self._summary_stamp:
            return
        try:
            summary = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return  # read again at the next poll
        self._summary_stamp = stamp
        if isinstance(summary, dict):
            self.state.set_summary(summary, "run folder")
