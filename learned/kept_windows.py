"""The windows a long ``cmax depth`` / ``python -m learned.predict`` has finished, kept on disk as it goes, so that
a killed run loses at most the block of windows it was predicting and ``--resume`` continues it.

The folder ``-o/.depth.windows/`` holds ``run.json`` (what the run is: the event file's and the checkpoint's size,
modification time and SHA-256, every option that changes a window, the batch; written with the first block) and, per
finished block of windows (one forward pass of the network, ``batch`` windows) that wrote any, their
``window_<k>.npz`` (as the results name them, linked from the run's private stage) and then ``block_<first>.json``: the run's digest, the block's windows with their
``twists.csv`` lines and each file's SHA-256, and how many of its windows were skipped. Once every window is
predicted, the pictures are drawn block by block on the run's colour scale: each block's ``window_<k>.png`` linked in
as well, then ``pictures_<first>.json`` (the run's digest, the scale, each picture's SHA-256). Every file is written
atomically (:mod:`cmax.io.atomic`), the record last, so a block with a record is complete.

A resumed run takes a block only when ``run.json`` matches the new run (else refused, naming what differs:
:func:`cmax.io.window_store.open_kept`) and the block's record names the same run and each of its files has the
recorded SHA-256; any other block is predicted again, in the same blocks as before, so that every forward pass
sees the windows an uninterrupted run gives it and the results are the same bit for bit. A block's pictures are
taken likewise when their record names the same run, the same colour scale and windows, and each picture has its
recorded SHA-256 (a run killed while drawing them draws only the others again).
"""
from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Callable

import numpy as np

from cmax.io.atomic import file_sha256, fsync_folder, write_text_atomic
from cmax.io.window_store import KeptRun, open_kept, write_run_record

__all__ = ["KEPT_FOLDER", "KeptBlocks", "kept_windows"]

#: The folder in ``-o`` that holds the finished blocks of a run of ``cmax depth`` until its results are in.
KEPT_FOLDER = ".depth.windows"
_BLOCK_NAME = re.compile(r"block_(\d+)\.json")


def kept_windows(out: str | os.PathLike) -> int:
    """How many windows the finished blocks an interrupted ``cmax depth`` left in the folder ``out`` hold (0 when
    none).

    Parameters
    ----------
    out : path
        The run's output folder (``-o``).
    """
    folder = Path(out) / KEPT_FOLDER
    return sum(len(record.get("windows", ())) for record in _records(folder)) if folder.is_dir() else 0


def _records(folder: Path) -> list[dict]:
    """The readable block records in ``folder``."""
    records = []
    for path in sorted(folder.iterdir()):
        if _BLOCK_NAME.fullmatch(path.name):
            try:
                record = json.loads(path.read_text())
            except (OSError, ValueError):
                continue
            records.append(record if isinstance(record, dict) else {})
    return records


class KeptBlocks(KeptRun):
    """The finished blocks of windows of one ``cmax depth`` run in ``out/.depth.windows``. Open it holding
    ``out``'s lock (:func:`cmax.io.run_folder.staged_run`).

    Parameters
    ----------
    out : path
        The run's output folder (``-o``).
    run : dict or callable
        What the run is, JSON-ready (:func:`cmax.io.window_store.file_signature` for its files); or a callable
        giving it (:class:`cmax.io.window_store.PendingSignatures`), called the first time it is needed: at once
        to compare it with kept blocks (``resume``), else with the first block saved (:attr:`run`).
    resume : bool
        Take the blocks an interrupted run with the same ``run`` left (else they are an error).
    overwrite : bool
        Without ``resume``: remove the blocks an interrupted run left and start over.

    Raises
    ------
    FileExistsError, ValueError
        As :func:`cmax.io.window_store.open_kept`.
    """

    def __init__(self, out: str | os.PathLike, run: dict | Callable[[], dict], *, resume: bool,
                 overwrite: bool) -> None:
        super().__init__(run)
        self.folder = Path(out) / KEPT_FOLDER
        self.resumed = self.unverified = 0
        open_kept(self.folder, lambda: self.run, found=kept_windows(out), resume=resume, overwrite=overwrite,
                  command="cmax depth")

    def load(self, first: int) -> tuple[list[int], list[str], int] | None:
        """``(indices, lines, skipped)`` of the finished block whose first window is ``first``: the windows it
        wrote (their files checked against the recorded SHA-256), their ``twists.csv`` lines and how many of its
        windows held too few events; None when the block is not finished, or not verified (counted in
        :attr:`unverified`)."""
        try:
            record = json.loads((self.folder / f"block_{first}.json").read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            self.unverified += 1
            return None
        try:
            if record["run"] != self.digest or record["first"] != first:
                raise ValueError("another run's block")
            indices = [int(w["index"]) for w in record["windows"]]
            for w in record["windows"]:
                if file_sha256(self.window_file(int(w["index"]))) != w["sha256"]:
                    raise ValueError("a window file changed")
            lines, skipped = [str(w["line"]) for w in record["windows"]], int(record["skipped"])
        except (KeyError, TypeError, ValueError, OSError):
            self.unverified += 1
            return None
        self.resumed += len(indices)
        return indices, lines, skipped

    def adopt(self, out: str | os.PathLike, summary: dict, count: int, batch: int) -> int:
        """Keep, as finished blocks of this run, the blocks of windows whose results the same run published
        complete in ``out`` and that are there as they were published, so that a complete run with a file deleted or
        changed predicts only the blocks that lost one (``--resume``, after
        :func:`cmax.io.run_folder.check_complete` found it to be the same run). ``summary``: ``out``'s
        ``summary.json``; ``count``: the run's windows; ``batch``: windows per block. A block is kept when
        ``twists.csv`` and each ``window_<k>.npz`` of the block have the size and SHA-256 ``summary`` records
        (``"outputs"``): its windows are linked into the folder and recorded with their ``twists.csv`` lines, as
        :meth:`save` does. Returns how many windows were kept (0 when ``summary`` records no outputs or
        ``twists.csv`` is not intact)."""
        from cmax.io.run_folder import OUTPUTS_KEY

        out, outputs = Path(out), summary.get(OUTPUTS_KEY)

        def intact(name: str) -> bool:
            record, path = outputs.get(name), out / name
            return (isinstance(record, dict) and path.is_file() and not path.is_symlink()
                    and path.stat().st_size == record.get("bytes") and file_sha256(path) == record.get("sha256"))

        if not isinstance(outputs, dict) or not intact("twists.csv"):
            return 0
        lines = {}
        for line in (out / "twists.csv").read_text().splitlines()[1:]:
            lines[int(line.split(",", 1)[0])] = line
        adopted = 0
        for first in range(0, count, batch):
            indices = [index for index in range(first, min(first + batch, count)) if index in lines]
            names = [self.window_file(index).name for index in indices]
            if (not indices or (self.folder / f"block_{first}.json").exists()
                    or not all(intact(name) for name in names)):
                continue
            write_run_record(self.folder, self.run)
            windows = []
            for index, name in zip(indices, names):
                self.window_file(index).unlink(missing_ok=True)
                _link(out / name, self.window_file(index))
                windows.append({"index": index, "line": lines[index], "sha256": outputs[name]["sha256"]})
            fsync_folder(self.folder)
            write_text_atomic(self.folder / f"block_{first}.json",
                              json.dumps({"run": self.digest, "first": first, "windows": windows,
                                          "skipped": min(first + batch, count) - first - len(indices)}))
            adopted += len(indices)
        return adopted

    def window_file(self, index: int) -> Path:
        """Where window ``index``'s ``window_<k>.npz`` is kept."""
        return self.folder / f"window_{index:05d}.npz"

    def save(self, first: int, indices: list[int], lines: list[str], skipped: int, stage: Path) -> None:
        """Keep the block whose first window is ``first`` as finished: its windows ``indices``, whose files are
        written in ``stage``, are linked (or copied) into the folder, then recorded with their ``twists.csv``
        ``lines`` and the count ``skipped``. A block without a window is not kept (it costs no forward pass)."""
        if not indices:
            return
        write_run_record(self.folder, self.run)      # with the first block: what the run is
        (self.folder / f"pictures_{first}.json").unlink(missing_ok=True)   # pictures of an unverified block
        windows = []
        for index, line in zip(indices, lines):
            kept = self.window_file(index)
            kept.unlink(missing_ok=True)             # an unverified one of an earlier run
            _link(stage / kept.name, kept)
            windows.append({"index": index, "line": line, "sha256": file_sha256(kept)})
        fsync_folder(self.folder)
        write_text_atomic(self.folder / f"block_{first}.json",
                          json.dumps({"run": self.digest, "first": first, "windows": windows, "skipped": skipped}))

    def load_pictures(self, first: int, indices: list[int], scale, stage: Path) -> bool:
        """Put the kept pictures of the block whose first window is ``first`` into ``stage`` and return True when
        they are verified: their record names this run, the colour ``scale`` (a :class:`cmax.viz.DepthScale`) and the
        windows ``indices``, and each ``window_<k>.png`` has its recorded SHA-256; else False (draw them)."""
        try:
            record = json.loads((self.folder / f"pictures_{first}.json").read_text())
            if (record["run"] != self.digest or record["scale"] != [scale.near, scale.far]
                    or [int(w["index"]) for w in record["windows"]] != list(indices)):
                return False
            for w in record["windows"]:
                if file_sha256(self.picture_file(int(w["index"]))) != w["sha256"]:
                    return False
        except (OSError, ValueError, KeyError, TypeError):
            return False
        for index in indices:
            _link(self.picture_file(index), stage / self.picture_file(index).name)
        return True

    def save_pictures(self, first: int, indices: list[int], scale, stage: Path) -> None:
        """Keep the pictures of the block whose first window is ``first`` (windows ``indices``), drawn in ``stage``
        on the colour ``scale``: linked (or copied) into the folder, then recorded with their SHA-256."""
        windows = []
        for index in indices:
            kept = self.picture_file(index)
            kept.unlink(missing_ok=True)             # an unverified one of an earlier run
            _link(stage / kept.name, kept)
            windows.append({"index": index, "sha256": file_sha256(kept)})
        fsync_folder(self.folder)
        write_text_atomic(self.folder / f"pictures_{first}.json",
                          json.dumps({"run": self.digest, "scale": [scale.near, scale.far], "windows": windows}))

    def picture_file(self, index: int) -> Path:
        """Where window ``index``'s ``window_<k>.png`` is kept."""
        return self.folder / f"window_{index:05d}.png"

    def sample_of(self, index: int) -> np.ndarray:
        """The ``depth`` (H, W) [m] of the kept window ``index``."""
        with np.load(self.window_file(index)) as saved:
            return saved["depth"]

    def place(self, index: int, stage: Path) -> None:
        """Put the kept window ``index``'s file into ``stage`` (a hard link, or a copy where links fail)."""
        _link(self.window_file(index), stage / self.window_file(index).name)

    def remove(self) -> None:
        """Remove the folder (the run's results are in ``out``)."""
        shutil.rmtree(self.folder, ignore_errors=True)
        fsync_folder(self.folder.parent)


def _link(source: Path, target: Path) -> None:
    """``target`` as a hard link to ``source`` (a copy, flushed, where the file system has no links)."""
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)
        with open(target, "rb+") as file:
            os.fsync(file.fileno())
