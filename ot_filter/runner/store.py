"""A run's output directory: atomic files, finished cells, and the check that a rerun resumes the
same run.

Layout of ``out/``::

    config.json     everything needed to rerun exactly (experiment, resolved options, command,
                    package / jax versions, backend); written first
    cells/<id>.json a finished cell's numbers (per simulation), written when the cell finishes
    cells/<id>.npz  its arrays (curves over time, ensembles for figures)
    metrics.json    the summary over all cells (deterministic: identical after a resumed run)
    timings.json    compile and run seconds per cell (these differ between runs)
    *.png           figures

Every file is written to a temporary name in the same directory and renamed into place, so an
interrupted run never leaves a half-written file under a final name. A cell counts as finished
only when both of its files exist (the ``.npz`` is renamed first, the ``.json`` last).
"""

from __future__ import annotations

import io
import json
import os
import tempfile

import numpy as np

__all__ = ["RunDirectory", "RunError", "write_bytes_atomic", "write_json_atomic"]


class RunError(Exception):
    """A problem the command line reports as one line (bad name, option, or output directory)."""


def write_bytes_atomic(path: str, data: bytes) -> None:
    """``data`` to ``path`` through a temporary file in the same directory and a rename."""
    directory = os.path.dirname(path) or "."
    handle, temporary = tempfile.mkstemp(dir=directory, prefix=".", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.chmod(temporary, 0o644)  # mkstemp makes it private; results are meant to be shared
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise


def write_json_atomic(path: str, value) -> None:
    write_bytes_atomic(path, (json.dumps(value, indent=2, sort_keys=True) + "\n").encode())


class RunDirectory:
    """The output directory of one run; ``open`` creates it or checks it holds the same run."""

    def __init__(self, root: str):
        self.root = root
        self.cells = os.path.join(root, "cells")

    @classmethod
    def open(cls, root: str, config: dict, identity_keys: tuple[str, ...]) -> "RunDirectory":
        """Creates ``root`` (and ``cells/``) and writes ``config.json``; if ``root`` already holds
        a run, it must be the same one (equal ``config[k]`` for ``k`` in ``identity_keys``),
        else ``RunError``. Unwritable or non-directory paths raise ``RunError`` too."""
        run = cls(root)
        try:
            os.makedirs(run.cells, exist_ok=True)
            probe = os.path.join(root, ".write-test")
            with open(probe, "w"):
                pass
            os.unlink(probe)
        except OSError as error:
            raise RunError(f"cannot write to output directory {root!r}: {error.strerror or error}") from None
        path = os.path.join(root, "config.json")
        if os.path.exists(path):
            try:
                with open(path) as stream:
                    previous = json.load(stream)
            except (OSError, ValueError):
                previous = None
            differing = [k for k in identity_keys if previous is None or previous.get(k) != config.get(k)]
            if differing:
                raise RunError(
                    f"{root!r} holds a different run (its {', '.join(differing)} differ); "
                    f"choose another --out or delete it"
                )
        else:
            write_json_atomic(path, config)
        return run

    def _paths(self, cell_id: str) -> tuple[str, str]:
        return os.path.join(self.cells, cell_id + ".json"), os.path.join(self.cells, cell_id + ".npz")

    def is_finished(self, cell_id: str) -> bool:
        return all(os.path.exists(p) for p in self._paths(cell_id))

    def save_cell(self, cell_id: str, record: dict, arrays: dict) -> None:
        json_path, npz_path = self._paths(cell_id)
        buffer = io.BytesIO()
        np.savez(buffer, **{k: np.asarray(v) for k, v in arrays.items()})
        write_bytes_atomic(npz_path, buffer.getvalue())
        write_json_atomic(json_path, record)  # last: its presence marks the cell finished

    def load_cell(self, cell_id: str) -> tuple[dict, dict]:
        json_path, npz_path = self._paths(cell_id)
        with open(json_path) as stream:
            record = json.load(stream)
        with np.load(npz_path) as data:
            arrays = {k: data[k] for k in data.files}
        return record, arrays

    def write_json(self, name: str, value) -> str:
        path = os.path.join(self.root, name)
        write_json_atomic(path, value)
        return path
