"""The windows a long ``cmax fit`` has finished, kept on disk as it goes, so that a killed run loses at most the
window it was fitting and ``cmax fit --resume`` continues it.

The folder ``-o/.fit.windows/`` holds ``run.json`` (what the run is: the event file's signature, the other input
files' and every setting that changes a fit; written with the first window) and one file per finished window,
``window_<index>.pickle``: the window's first fit (:class:`cmax.FitResult`, before the resolution and the smoothing
across windows, which run again over all windows) and its warnings. Each file is written atomically
(:func:`cmax.io.atomic.write_bytes_atomic`: private temporary file, fsync, rename), so a file of that name is
complete; each also records the run's digest and the window's start, opens with a line holding the SHA-256 of the
pickle that follows (checked before it is read: a byte changed on disk since makes it a window to fit again), and
is read back with an unpickler that builds only the project's result classes and numpy arrays (a planted file runs
no code).

A resumed run takes a window only when ``run.json`` matches the new run (the same event file by size,
modification time and SHA-256 of its bytes, wherever it is now, the same settings: else the run is refused, naming what differs; a
``run.json`` of an earlier version, which recorded no SHA-256, is refused too: what the windows were fitted on cannot
be checked) and the window's file names
the same run and window start; a window file that cannot be read is fitted again. The folder is removed once the
run's results are in ``-o`` (``summary.json`` is the record of completion, :mod:`cmax.io.run_folder`).
"""
from __future__ import annotations

import argparse
import dataclasses
import enum
import hashlib
import io
import json
import os
import pickle
import re
import shutil
import threading
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cmax.io.atomic import check_unchanged, file_sha256, fsync_folder, write_bytes_atomic, write_text_atomic
from cmax.sim.signature import signature_problem

__all__ = ["WINDOWS_FOLDER", "WindowStore", "KeptRun", "interrupted_windows", "file_signature", "file_signatures",
           "PendingSignatures", "settings_record", "open_kept", "write_run_record", "stopped_line", "code_digest",
           "run_digest", "run_differences", "command_record"]

#: The folder in ``-o`` that holds the finished windows of a run of ``cmax fit`` until its results are in.
WINDOWS_FOLDER = ".fit.windows"
_RUN_FILE = "run.json"
_WINDOW_NAME = re.compile(r"window_(\d{5,})\.pickle")
#: The maps of a :class:`cmax.FitResult` (H, W) kept on disk, not in memory, once the window is saved.
_MAPS = ("depth", "mask", "depth_spread", "iwe_before", "iwe_after")
#: Bytes of input files to hash at the start of a run above which a progress bar shows it.
HASH_PROGRESS_BYTES = 1 << 30
#: The first bytes of a window file, followed by the SHA-256 (hex) of its pickle and a newline.
_SEAL = b"cmax-window sha256="


def interrupted_windows(out: str | os.PathLike) -> int:
    """How many finished windows an interrupted ``cmax fit`` left in the folder ``out`` (0 when none).

    Parameters
    ----------
    out : path
        The run's output folder (``-o``).
    """
    folder = Path(out) / WINDOWS_FOLDER
    return sum(1 for path in folder.iterdir() if _WINDOW_NAME.fullmatch(path.name)) if folder.is_dir() else 0


class _ResultUnpickler(pickle.Unpickler):
    """Builds the classes a window file holds and nothing else: the dataclasses and enums of ``cmax.fitting``,
    numpy arrays and dtypes."""

    _NUMPY = {("numpy", "dtype"), ("numpy", "ndarray"), ("numpy._core.numeric", "_frombuffer"),
              ("numpy.core.numeric", "_frombuffer"), ("numpy._core.multiarray", "_reconstruct"),
              ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "scalar"),
              ("numpy.core.multiarray", "scalar")}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._NUMPY:
            return super().find_class(module, name)
        if module.startswith("cmax.fitting."):
            found = super().find_class(module, name)
            if isinstance(found, type) and (dataclasses.is_dataclass(found) or issubclass(found, enum.Enum)):
                return found
        raise pickle.UnpicklingError(f"a window file may not build {module}.{name}")


def _sealed(payload: bytes) -> bytes:
    """A window file's bytes: :data:`_SEAL`, the SHA-256 (hex) of ``payload`` (a pickle), a newline, ``payload``."""
    return _SEAL + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload


def _opened(data: bytes) -> bytes:
    """The pickle in a window file's bytes ``data`` (:func:`_sealed`); ValueError when it does not have the
    SHA-256 its first line records (changed on disk), or no such line."""
    head, _, payload = data.partition(b"\n")
    if not head.startswith(_SEAL) or head[len(_SEAL):] != hashlib.sha256(payload).hexdigest().encode():
        raise ValueError("not a window file, or changed since it was written")
    return payload


def run_digest(run: dict) -> str:
    """The SHA-256 (hex) of a run's record ``run`` (JSON-ready, keys sorted), less the paths its file signatures
    hold: what each kept window, block or chunk file names, so that a file of another run is never taken for one of
    this run, while a moved input (the same bytes, :func:`run_differences`) keeps its kept files.

    Parameters
    ----------
    run : dict
        What the run is (``run.json``'s contents).

    >>> a = {"file": {"path": "/a/ev.h5", "bytes": 5, "mtime_ns": 1, "sha256": "ab"}, "settings": {"n": 1}}
    >>> run_digest(a) == run_digest({**a, "file": {**a["file"], "path": "/b/ev.h5"}})
    True
    >>> run_digest(a) == run_digest({**a, "settings": {"n": 2}})
    False
    """
    unplaced = {key: ({name: item for name, item in value.items() if name != "path"}
                      if isinstance(value, dict) and "mtime_ns" in value else value) for key, value in run.items()}
    return hashlib.sha256(json.dumps(unplaced, sort_keys=True).encode()).hexdigest()


def _differences(recorded: dict, now: dict) -> list[str]:
    """What differs between two ``run.json`` records, in words (empty when they match)."""
    found = []
    for key in sorted(set(recorded) | set(now)):
        before, after = recorded.get(key), now.get(key)
        if isinstance(before, dict) and isinstance(after, dict) and "mtime_ns" in after:
            if problem := signature_problem(before, after, modified="since"):
                found.append(problem)
            elif "sha256" in after and "sha256" not in before:
                found.append(f"{Path(str(after.get('path', ''))).name}: the kept run recorded no SHA-256 of its bytes "
                             "(an earlier version of cmax), so whether it changed since cannot be checked")
        elif key == "settings" and isinstance(before, dict) and isinstance(after, dict):
            found += [f"{name} was {before.get(name)!r}, now {after.get(name)!r}"
                      for name in sorted(set(before) | set(after)) if before.get(name) != after.get(name)]
        elif key == "code" and before != after:
            found.append("the code of cmax (or learned) changed since those results were kept (another version, "
                         "or an edited install)")
        elif before != after:
            found.append(f"{key} was {before!r}, now {after!r}")
    return found


def run_differences(recorded: dict, now: dict) -> list[str]:
    """What differs between two records of a run (``run.json``: signatures of its files, ``settings``, ``code``),
    one phrase each (empty when they match; a moved file with the same size, modification time and SHA-256
    matches; a signature of ``now`` with a SHA-256 where ``recorded``'s has none does not).

    Parameters
    ----------
    recorded, now : dict
        The kept run's record and the new run's, JSON-ready.
    """
    return _differences(recorded, now)


def open_kept(folder: Path, run: dict | Callable[[], dict], *, found: int, resume: bool, overwrite: bool,
              command: str) -> None:
    """Check the folder of an interrupted run's finished windows (``folder``: ``-o/.fit.windows``,
    ``-o/.depth.windows``) against the new ``run`` (JSON-ready, as ``folder/run.json`` records it; or a callable
    giving it, called only when there are windows to compare with it: a ``resume``); ``found``: how
    many finished windows it holds. The folder is removed when it holds none (a ``run.json`` alone) or with
    ``overwrite`` alone; kept when ``resume`` (with or without ``overwrite``, which is then about an earlier complete
    run's results) and the runs match. ``command`` names the command in messages.

    Raises
    ------
    FileExistsError
        It holds windows and neither ``resume`` nor ``overwrite`` is set.
    ValueError
        ``resume``, and ``run.json`` is unreadable or records another run (each difference named).
    """
    out = folder.parent
    if folder.exists() and (not found or (overwrite and not resume)):
        shutil.rmtree(folder)
    elif found and not resume:
        raise FileExistsError(f"{out} holds {found} finished window(s) of an interrupted {command}: --resume "
                              "continues that run, --overwrite starts over")
    elif found:
        try:
            recorded = json.loads((folder / _RUN_FILE).read_text())
        except (OSError, ValueError):
            recorded = None
        if not isinstance(recorded, dict):
            raise ValueError(f"cannot --resume: {folder / _RUN_FILE} is missing or unreadable, so the finished "
                             "windows cannot be checked: --overwrite starts over")
        if differences := _differences(recorded, run() if callable(run) else run):
            raise ValueError(f"cannot --resume the run in {out}: it was another run (" + "; ".join(differences)
                             + "): give the same file and options, or --overwrite to start over")


def write_run_record(folder: Path, run: dict) -> None:
    """Create ``folder`` and write ``folder/run.json`` (``run``, JSON-ready) atomically, unless it is there."""
    if not (folder / _RUN_FILE).is_file():
        folder.mkdir(exist_ok=True)
        write_text_atomic(folder / _RUN_FILE, json.dumps(run, indent=2, sort_keys=True))


class KeptRun:
    """What an interrupted run's kept work is checked against: the run record ``run`` (JSON-ready; or a callable
    giving it, e.g. once :class:`PendingSignatures` has hashed the files), taken the first time :attr:`run` or
    :attr:`digest` is read. The base of :class:`WindowStore` and ``learned.kept_windows.KeptBlocks``."""

    def __init__(self, run: dict | Callable[[], dict]) -> None:
        self._run, self._digest = run, None

    @property
    def run(self) -> dict:
        """What the run is (``run.json``'s contents); the callable given as ``run`` is called the first time."""
        if callable(self._run):
            self._run = self._run()
        return self._run

    @property
    def digest(self) -> str:
        """:func:`run_digest` of :attr:`run`: what each kept window or block names."""
        if self._digest is None:
            self._digest = run_digest(self.run)
        return self._digest


class WindowStore(KeptRun):
    """The finished windows of one ``cmax fit`` run in ``out/.fit.windows`` (the ``store`` of
    :func:`cmax.fit_sequence`). Open it holding ``out``'s lock (:func:`cmax.io.run_folder.staged_run`).

    Parameters
    ----------
    out : path
        The run's output folder (``-o``).
    run : dict or callable
        What the run is, JSON-ready: ``{"file": signature, ..., "settings": {...}}`` (a signature as
        :func:`file_signature` gives it; compared by size, modification time and SHA-256); or a callable giving it
        (e.g. once :class:`PendingSignatures` has hashed the files), called the first time it is needed: at once
        to compare it with kept windows (``resume``), else with the first window saved (:attr:`run`).
    resume : bool
        Take the windows an interrupted run with the same ``run`` left (else they are an error).
    overwrite : bool
        Without ``resume``: remove the windows an interrupted run left and start over.

    Raises
    ------
    FileExistsError
        ``out`` holds windows of an interrupted run and neither ``resume`` nor ``overwrite`` is set.
    ValueError
        ``resume``, and the interrupted run was another (another event file, or other settings): the message
        names each difference.
    """

    def __init__(self, out: str | os.PathLike, run: dict | Callable[[], dict], *, resume: bool,
                 overwrite: bool) -> None:
        super().__init__(run)
        self.folder = Path(out) / WINDOWS_FOLDER
        self.resumed = self.unreadable = 0
        self._with_maps: set[int] = set()
        open_kept(self.folder, lambda: self.run, found=interrupted_windows(out), resume=resume, overwrite=overwrite,
                  command="cmax fit")

    def _path(self, index: int) -> Path:
        return self.folder / f"window_{index:05d}.pickle"

    def _read(self, index: int, start_us: int):
        """The saved ``(result, caught)`` of window ``index`` (None: not saved, another window's, or unreadable)."""
        path = self._path(index)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return None
        try:
            record = _ResultUnpickler(io.BytesIO(_opened(data))).load()
            if record["run"] != self.digest or record["start_us"] != start_us:
                raise ValueError("another run's window")
            return record["result"], tuple(tuple(item) for item in record["caught"])
        except Exception:   # a damaged or foreign file: the window is fitted again
            self.unreadable += 1
            return None

    def load(self, index: int, start_us: int):
        """``(result, caught)`` of the finished window ``index`` starting at ``start_us`` [µs], its maps left on
        disk (see :meth:`save`), or None when it is not finished."""
        record = self._read(index, start_us)
        if record is None:
            return None
        self.resumed += 1
        return self._slim(index, record[0]), record[1]

    def save(self, index: int, start_us: int, result, caught: tuple):
        """Write the finished window ``index`` (starting at ``start_us`` [µs]) with its warnings ``caught``;
        returns ``result`` without its (H, W) maps (``depth``, ``mask``, ``depth_spread``, ``iwe_before``,
        ``iwe_after`` set to None; :meth:`maps` reads them back), so that a long run's memory does not grow
        with them."""
        record = {"run": self.digest, "start_us": int(start_us), "result": result, "caught": tuple(caught)}
        try:
            write_run_record(self.folder, self.run)      # with the first window: what the run is
            write_bytes_atomic(self._path(index), _sealed(pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)))
        except BaseException:   # a full disk: a folder without a window is no interrupted run to resume
            if not interrupted_windows(self.folder.parent):
                shutil.rmtree(self.folder, ignore_errors=True)
            raise
        return self._slim(index, result)

    def _slim(self, index: int, result):
        if result.depth is not None:
            self._with_maps.add(index)
        return dataclasses.replace(result, **{name: None for name in _MAPS})

    def maps(self, index: int, result):
        """``result`` (a kept result of window ``index``, perhaps re-fitted since) with the maps of its first fit
        read back when :meth:`save` or :meth:`load` left them out; a result that holds its own maps (a re-fit)
        is returned as it is."""
        if result.depth is not None or index not in self._with_maps:
            return result
        first = _ResultUnpickler(io.BytesIO(_opened(self._path(index).read_bytes()))).load()["result"]
        return dataclasses.replace(result, **{name: getattr(first, name) for name in _MAPS})

    def remove(self) -> None:
        """Remove the folder (the run's results are in ``out``)."""
        shutil.rmtree(self.folder, ignore_errors=True)
        fsync_folder(self.folder.parent)


def file_signature(path: str | os.PathLike | None, read: Callable[[int], None] | None = None) -> dict | None:
    """The signature of an input file: ``{"path": resolved path, "files": 1, "bytes": size, "mtime_ns":
    modification time [ns], "sha256": SHA-256 (hex) of its bytes}`` (as :func:`cmax.sim.signature.source_signature`
    gives a video's), or None when ``path`` is None. The whole file is read (:func:`cmax.io.atomic.file_sha256`),
    after its ``stat``: another file of the same size given the old modification time (``cp -p``, ``rsync -t``) has
    another signature. A file whose size or modification time changed while it was hashed (still being written
    or copied) is refused: ValueError naming it (:func:`cmax.io.atomic.check_unchanged`).

    Parameters
    ----------
    path : path or None
        An input file of the run (the events, ``--gyro``, ``--calib``); None as well when it is not a file.
    read : callable, optional
        Called with the bytes [B] of each block hashed (a progress bar's ``update``).
    """
    if path is None or not os.path.isfile(path):    # a missing file is for its reader to name
        return None
    info = os.stat(path)
    digest = file_sha256(path, read)
    check_unchanged([path], [info])
    return {"path": str(Path(path).resolve()), "files": 1, "bytes": info.st_size, "mtime_ns": info.st_mtime_ns,
            "sha256": digest}


def file_signatures(paths: dict[str, str | os.PathLike | None], *, progress: bool = True,
                    read: Callable[[int], None] | None = None) -> dict[str, dict | None]:
    """:func:`file_signature` of each of ``paths`` (by name: ``{"file": events, "gyro": ..., ...}``), with a
    progress bar [bytes] on stderr while they are hashed when they hold more than :data:`HASH_PROGRESS_BYTES`.

    Parameters
    ----------
    paths : dict of str to path or None
        A run's input files by the name its record gives them.
    progress : bool
        Allow the progress bar (off for ``--quiet``).
    read : callable, optional
        Called with the bytes [B] of each block hashed, before the bar counts it (an exception it raises stops
        the hashing: :class:`PendingSignatures` stops so).
    """
    from tqdm.auto import tqdm

    total = sum(os.path.getsize(path) for path in paths.values() if path is not None and os.path.isfile(path))
    with tqdm(total=total, desc="hashing input files (checked by --resume)", unit="B", unit_scale=True,
              unit_divisor=1024, disable=not progress or total <= HASH_PROGRESS_BYTES) as bar:
        counted = bar.update if read is None else (lambda nbytes: (read(nbytes), bar.update(nbytes)))
        return {name: file_signature(path, counted) for name, path in paths.items()}


class _Stopped(Exception):
    """Raised in :class:`PendingSignatures`' thread to stop its hashing."""


class PendingSignatures:
    """:func:`file_signatures` of a run's input files, taken in a background thread from construction, so that
    the run's work starts at once; :meth:`result` waits for them. A run needs them only when it compares them
    with a kept run (``--resume``) or records them (with its first kept window or block, :class:`WindowStore`):
    a fresh run spends the hashing of multi-GB inputs fitting instead of waiting.

    Always :meth:`close` it (``try``/``finally``): it stops the thread within one 4 MiB block and waits for it,
    so that no thread outlives the run (a Ctrl-C, an error).

    Parameters
    ----------
    paths : dict of str to path or None
        A run's input files by the name its record gives them (as :func:`file_signatures`).
    progress : bool
        Allow :func:`file_signatures`' progress bar [bytes] on stderr (off for ``--quiet``).
    """

    def __init__(self, paths: dict[str, str | os.PathLike | None], *, progress: bool = True) -> None:
        self._stop = threading.Event()
        self._signatures: dict[str, dict | None] | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._hash, args=(dict(paths), progress), daemon=True,
                                        name="cmax-hash-inputs")
        self._thread.start()

    def _hash(self, paths: dict, progress: bool) -> None:
        def read(_nbytes: int) -> None:
            if self._stop.is_set():
                raise _Stopped

        try:
            self._signatures = file_signatures(paths, progress=progress, read=read)
        except BaseException as error:      # raised again by result(), in the run's thread
            self._error = error

    def result(self) -> dict[str, dict | None]:
        """The signatures by name (:func:`file_signatures`), once every file is hashed (waits for the thread).

        Raises
        ------
        ValueError, OSError
            What :func:`file_signature` raised: a file whose size or modification time changed while it was
            hashed (:func:`cmax.io.atomic.check_unchanged`), an unreadable file.
        """
        self._thread.join()
        if isinstance(self._error, _Stopped):
            raise RuntimeError("the input files' hashing was stopped (close) before it ended")
        if self._error is not None:
            raise self._error
        return self._signatures

    def close(self) -> None:
        """Stop the hashing (within one block) and wait for the thread; a finished one is left as it is."""
        self._stop.set()
        self._thread.join()


def settings_record(values: dict) -> dict:
    """``values`` as JSON-ready data: paths as text, tuples and arrays as lists, numpy scalars as numbers.

    Parameters
    ----------
    values : dict
        A command's options by name (``vars(args)``, less what does not change a result).
    """
    def plain(value):
        if isinstance(value, (Path, os.PathLike)):
            return str(value)
        if isinstance(value, np.ndarray):
            return value.tolist()
        if isinstance(value, (tuple, list)):
            return [plain(item) for item in value]
        if isinstance(value, np.generic):
            return value.item()
        return value

    return json.loads(json.dumps({key: plain(value) for key, value in values.items()}))


def command_record(args: argparse.Namespace, files: dict, *, code: str, ignored: tuple[str, ...],
                   extra: dict | None = None) -> dict:
    """What a run of a command is, for ``--resume`` to compare (:func:`run_differences`): the version of cmax, the
    digest ``code`` of its code (:func:`code_digest`), the signatures ``files`` of its input files by name
    (:func:`file_signatures`; None: not given) and every other option of ``args`` but the ``ignored`` ones (those
    that change no result), then ``extra``, as :func:`settings_record` writes them; an input file's path counts only
    through its signature, so that a moved file, the same bytes, is the same run.

    Parameters
    ----------
    args : argparse.Namespace
        The command's parsed options.
    files : dict
        The input files' signatures by the names their options have in ``args``.
    code : str
        The digest of cmax's code.
    ignored : tuple of str
        The options that change no result.
    extra : dict, optional
        Further settings derived from the options (e.g. whether windows are warm-started).
    """
    import cmax

    settings = {key: value for key, value in vars(args).items()
                if key not in ignored and not (key in files and files[key] is not None)}
    return {"cmax": cmax.__version__, "code": code, **files, "settings": settings_record({**settings, **(extra or {})})}


def stopped_line(label: str, stop: KeyboardInterrupt, kept: int, folder: Path) -> tuple[str, int]:
    """The one line and the exit status of a run stopped by Ctrl-C, SIGTERM or SIGHUP (``stop``, a
    :class:`cmax._signals.Terminated` for the last two) that kept ``kept`` finished windows in ``folder``; ``label``:
    the command's name.

    >>> stopped_line("cmax fit", KeyboardInterrupt(), 3, Path("o/.fit.windows"))
    ('cmax fit: interrupted: 3 finished window(s) kept in o/.fit.windows: the same command with --resume continues the run', 130)
    """
    from cmax._signals import Terminated

    what, status = ((f"terminated ({stop.name})", stop.status) if isinstance(stop, Terminated)
                    else ("interrupted", 130))
    return (f"{label}: {what}: {kept} finished window(s) kept in {folder}: the same command with --resume continues "
            "the run", status)


def code_digest(*packages: str) -> str:
    """SHA-256 (hex) of the Python files of the imported ``packages`` (e.g. ``"cmax"``, ``"learned"``), by path and
    bytes: a resumed run takes windows only from the same code, also where the version number did not change.

    Parameters
    ----------
    packages : str
        Names of imported packages.
    """
    import importlib

    digest = hashlib.sha256()
    for name in packages:
        root = Path(importlib.import_module(name).__file__).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(str(path.relative_to(root.parent)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()
