"""The output folder of a run of :mod:`learned` (``cmax depth -o OUT``, ``train.out``), held by one run at a time."""
from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from cmax.io.atomic import PathLock

__all__ = ["locked_folder"]


@contextmanager
def locked_folder(folder: str | os.PathLike, lock_name: str) -> Iterator[Path]:
    """Hold the folder ``folder`` (created if needed) for one run: an exclusive lock on ``folder/lock_name``
    (:class:`cmax.io.atomic.PathLock`, as ``cmax simulate`` locks its output folder), released, and its file
    removed, when the block ends, however it ends (a killed process's lock is released by the system).

    A second run into the same folder fails at once with :class:`cmax.io.atomic.OutputLockedError` (an
    ``OSError``, one line) and changes nothing. A folder this call created is removed again when the block
    leaves it empty (a refused run writes nothing). Yields ``folder`` as a Path.
    """
    folder = Path(folder)
    if os.path.lexists(folder) and not folder.is_dir():
        raise FileExistsError(f"the output {folder} is a file: give a folder")
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        with PathLock(folder / lock_name, folder):
            yield folder
    finally:
        if created:
            try:
                folder.rmdir()   # only when empty: nothing of this run, nor another run's lock, is in it
            except OSError:
                pass
