"""The output folder of a run (``cmax fit -o``, ``cmax emvs -o``, ``cmax depth -o``, ``train.out``): held by one
run at a time, its results written into a private stage and moved in together, so that an interrupted run never
leaves a folder that looks complete with an earlier run's files mixed into a new run's.

The rules of :func:`staged_run` (``cmax fit``, ``cmax emvs``, ``cmax depth`` / ``learned.predict``):

* one lock per folder, :data:`FOLDER_LOCK`, whichever of these commands writes: a second run into the folder, of
  the same command or another, is refused at once (:class:`cmax.io.atomic.OutputLockedError`);
* an earlier run's results are the files any of these commands writes (:data:`RESULT_NAMES`: ``depth_00000.npz``,
  ``window_00000.png``, ``summary.json``, ... by their exact names, never ``depth_groundtruth.png``): a folder
  holding them, of the same command or another, is refused without ``--overwrite``, and ``--overwrite`` removes
  only them;
* ``summary.json`` (:data:`COMPLETION_MARKER`) is every run's record of completion, and :func:`publish` moves it
  in last: it first removes the earlier run's ``summary.json``, then the earlier run's files that the new run does
  not replace, then moves the new files in, and the new ``summary.json`` last. A run interrupted before
  :func:`publish` leaves the folder as it was; one interrupted during it leaves a folder without
  ``summary.json``: **a folder without summary.json holds no complete run** (and the next run into it is refused
  without ``--overwrite``).
* a run's ``summary.json`` records what the run was (``"run"``: its input files' signatures and its options, as
  its kept windows' ``run.json``), so that ``--resume`` of the same run into a folder whose run completed is told
  so, and touches nothing (:class:`ResultsComplete`, :func:`check_complete`), as a requeued job needs; another
  run's results, or results whose ``summary.json`` records no run (an earlier version), are still refused.
* a run's ``summary.json`` also records the size and SHA-256 of each file the run published
  (``"outputs"``, :func:`output_records`): ``--resume`` of the same run calls its results complete only when each
  is there with those bytes (:func:`damaged_outputs`); a file deleted, truncated or changed since makes the run
  run again, and its results replace the damaged ones.
"""
from __future__ import annotations

import json
import os
import re
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, Sequence

from cmax.io.atomic import PathLock, fsync_folder

__all__ = ["FOLDER_LOCK", "COMPLETION_MARKER", "RESULT_NAMES", "run_results", "locked_folder", "staged_run",
           "new_stage", "discard_stages", "publish", "ResultsComplete", "complete_run", "resumed_into_complete",
           "check_complete", "output_records", "damaged_outputs", "named_in_out", "OUTPUTS_KEY"]

_STAGE_SUFFIX = ".partial"
#: The lock of an output folder that :func:`staged_run` holds, the same for every command that writes through it.
FOLDER_LOCK = ".results.lock"
#: The file a run of :func:`staged_run` writes last (:func:`publish`): a folder without it holds no complete run.
COMPLETION_MARKER = "summary.json"
#: The entry of ``summary.json`` that records each published file's size and SHA-256 (:func:`output_records`).
OUTPUTS_KEY = "outputs"
#: The names (whole names, :func:`re.fullmatch`) of the files each command writes into its output folder.
RESULT_NAMES: dict[str, re.Pattern] = {
    "fit": re.compile(r"depth_\d{5,}\.(?:npz|png)|trajectory\.txt|summary\.json"),
    "depth": re.compile(r"window_\d{5,}\.(?:npz|png)|twists\.csv|summary\.json"),
    "emvs": re.compile(r"depth\.(?:npz|png)|points\.ply|summary\.json"),
}


def run_results(out: str | os.PathLike, commands: Sequence[str] | None = None) -> list[Path]:
    """The files in the folder ``out`` named as the ``commands`` (keys of :data:`RESULT_NAMES`; default: all of
    them) name their results, sorted; empty when there are none (or no folder). A user's ``depth_groundtruth.png``
    or ``window_seat.png`` is none of them."""
    out = Path(out)
    if not out.is_dir():
        return []
    patterns = [RESULT_NAMES[command] for command in (RESULT_NAMES if commands is None else commands)]
    return sorted(path for path in out.iterdir()
                  if any(pattern.fullmatch(path.name) for pattern in patterns) and path.is_file())


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


def new_stage(out: Path, prefix: str) -> Path:
    """A new, empty private folder ``out/.<prefix>.<16 hex>.partial`` for a run's results (``out`` held with
    :func:`locked_folder`)."""
    stage = Path(out) / f".{prefix}.{secrets.token_hex(8)}{_STAGE_SUFFIX}"
    stage.mkdir()
    return stage


def discard_stages(out: Path, prefix: str) -> list[Path]:
    """Remove the private folders (``.<prefix>.<16 hex>.partial``) that killed runs left in ``out``; returns them.
    Call it holding ``out``'s lock."""
    pattern = re.compile(r"\." + re.escape(prefix) + r"\.[0-9a-f]{16}" + re.escape(_STAGE_SUFFIX))
    stale = [folder for folder in Path(out).glob(f".{prefix}.*{_STAGE_SUFFIX}")
             if pattern.fullmatch(folder.name) and folder.is_dir() and not folder.is_symlink()]
    for folder in stale:
        shutil.rmtree(folder, ignore_errors=True)
    return stale


def publish(stage: Path, out: Path, earlier: Sequence[Path], *,
            last: Sequence[str] = (COMPLETION_MARKER,)) -> list[Path]:
    """Move the files of ``stage`` into ``out`` (renames within one folder tree) in place of ``earlier`` (an
    earlier run's files); returns the files now in ``out``.

    The order keeps an interrupted move from looking complete: first the earlier run's record of completion (its
    files named in ``last``, and any file of ``out`` a new one of those names would replace) is removed, then the
    earlier files that no new one replaces, then the new files are moved in, and those named in ``last`` after all
    the others (the folder synced between the steps)."""
    out = Path(out)
    new = sorted((file for file in Path(stage).iterdir() if file.is_file() and not file.is_symlink()),
                 key=lambda file: (file.name in last, file.name))
    names = {file.name for file in new}
    markers = {file for file in earlier if file.name in last} | {out / name for name in last if name in names}
    for marker in sorted(markers):
        if os.path.lexists(marker):
            marker.unlink()
    fsync_folder(out)   # the earlier record gone before anything else changes
    for stale in earlier:
        if stale.name not in names:
            stale.unlink(missing_ok=True)
    for file in new:
        if file.name in last:
            fsync_folder(out)   # every other file in place before the record of completion
        os.replace(file, out / file.name)
    fsync_folder(out)
    return [out / file.name for file in new]


class ResultsComplete(Exception):
    """Raised (by :func:`check_complete`) in the block of :func:`staged_run` when ``--resume`` finds the results
    of the same run complete in its folder: nothing is to be done, and nothing was changed. ``args[0]`` is the
    line to print; ``summary`` the complete run's ``summary.json`` (a dict)."""

    def __init__(self, line: str, summary: dict) -> None:
        super().__init__(line)
        self.summary = summary


def complete_run(out: str | os.PathLike) -> dict | None:
    """The ``summary.json`` (:data:`COMPLETION_MARKER`) of the complete run in the folder ``out``, as a dict;
    None when ``out`` holds none (no complete run) or one that is not a JSON object.

    Parameters
    ----------
    out : path
        An output folder (``-o``).
    """
    try:
        summary = json.loads((Path(out) / COMPLETION_MARKER).read_text())
    except (OSError, ValueError):
        return None
    return summary if isinstance(summary, dict) else None


def resumed_into_complete(out: str | os.PathLike, *, resume: bool, overwrite: bool) -> dict | None:
    """The ``summary.json`` of the complete run in ``out`` (a dict; ``{}`` when it cannot be read as one) when a
    ``resume`` without ``overwrite`` goes into it: what :func:`check_complete` must compare this run with, before
    any work, in the block of :func:`staged_run`; None otherwise (no complete run there, or no ``--resume``).

    Parameters
    ----------
    out : path
        The output folder (``-o``).
    resume, overwrite : bool
        The command's ``--resume`` and ``--overwrite``.
    """
    if not resume or overwrite or not (Path(out) / COMPLETION_MARKER).is_file():
        return None
    return complete_run(out) or {}


def check_complete(out: str | os.PathLike, summary: dict, now: dict, *, command: str) -> str:
    """Compare the run ``now`` (JSON-ready, as the command records it in ``summary.json``'s ``"run"``) with the
    one whose results are complete in ``out`` (``summary``: its ``summary.json``, :func:`complete_run`), for
    ``--resume``. Raises :class:`ResultsComplete` (one line to print) when they are the same run (the same input
    files by size, modification time and SHA-256, wherever they are now; the same options and code:
    :func:`cmax.io.window_store.run_differences`) and every file ``summary`` records (``"outputs"``) is in ``out``
    with its recorded size and SHA-256 (:func:`damaged_outputs`); FileExistsError when ``summary`` records no run
    (written by an earlier version: whether it is this run cannot be checked); ValueError naming each difference
    otherwise. Returns a note (one line) when it is the same run but a recorded file is missing or changed: the
    run is to run again, and :func:`staged_run` then replaces the damaged results with its own.

    Parameters
    ----------
    out : path
        The output folder (``-o``).
    summary : dict
        Its ``summary.json``.
    now : dict
        What the new run is.
    command : str
        The command's name, for the messages.
    """
    from cmax.io.window_store import run_differences

    recorded = summary.get("run")
    if not isinstance(recorded, dict):
        raise FileExistsError(f"cannot --resume into {out}: it holds the complete results of an earlier run whose "
                              f"{COMPLETION_MARKER} records no run identity (written by an earlier version), so "
                              "whether they are this run's cannot be checked: --overwrite replaces them, or give "
                              "another -o")
    now = json.loads(json.dumps(now))
    if differences := run_differences(recorded, now):
        raise ValueError(f"cannot --resume into {out}: it holds the complete results of another run ("
                         + "; ".join(differences) + "): --overwrite replaces them, or give another -o")
    if damaged := damaged_outputs(out, summary):
        listed = "; ".join(damaged[:3]) + (f"; and {len(damaged) - 3} more" if len(damaged) > 3 else "")
        return (f"the results of this run in {out} are not complete ({listed}): running it again (they are "
                "replaced once it is done)")
    raise ResultsComplete(f"the results in {out} are already complete: {command} --resume of the same input files "
                          "and options has nothing to do (nothing changed)", summary)


def output_records(stage: str | os.PathLike) -> dict[str, dict]:
    """What ``summary.json`` records of the files a run is about to publish (``"outputs"``): the size [bytes] and
    SHA-256 (hex) of each regular file in the folder ``stage`` but ``summary.json``, by name.

    Parameters
    ----------
    stage : path
        The run's private folder of results (:func:`staged_run`), every file but ``summary.json`` written.
    """
    from cmax.io.atomic import file_sha256

    return {path.name: {"bytes": path.stat().st_size, "sha256": file_sha256(path)}
            for path in sorted(Path(stage).iterdir())
            if path.name != COMPLETION_MARKER and path.is_file() and not path.is_symlink()}


def damaged_outputs(out: str | os.PathLike, summary: dict) -> list[str]:
    """The files ``summary`` (a ``summary.json``) records (``"outputs"``, :func:`output_records`) that are not in the
    folder ``out`` as they were published, one phrase each (``depth_00001.npz is missing``, ``trajectory.txt has 0
    bytes, it had 912``, ``depth.png holds other bytes (another SHA-256)``); empty when all are. A ``summary`` that
    records none (``"outputs"`` missing or not a mapping: an earlier version's, or an edited one) gives one phrase
    saying that its results cannot be verified: they are never taken as intact on trust. Each file of the recorded
    size is read once.

    Parameters
    ----------
    out : path
        The output folder (``-o``).
    summary : dict
        Its ``summary.json``.
    """
    from cmax.io.atomic import file_sha256

    recorded = summary.get(OUTPUTS_KEY)
    if not isinstance(recorded, dict):
        return [f"{COMPLETION_MARKER} records no size and SHA-256 of its results (\"{OUTPUTS_KEY}\": written by an "
                "earlier version, or edited), so they cannot be verified"]
    damaged = []
    for name, record in recorded.items():
        path = Path(out) / str(name)
        if Path(str(name)).name != name or not isinstance(record, dict):
            damaged.append(f"{COMPLETION_MARKER} records {name!r} unreadably")
        elif not path.is_file() or path.is_symlink():
            damaged.append(f"{name} is missing")
        elif path.stat().st_size != record.get("bytes"):
            damaged.append(f"{name} has {path.stat().st_size:,} bytes, it had {record.get('bytes')}")
        elif file_sha256(path) != record.get("sha256"):
            damaged.append(f"{name} holds other bytes than it did (another SHA-256)")
    return damaged


@contextmanager
def staged_run(out: str | os.PathLike, prefix: str, earlier_results: Callable[[Path], list[Path]], *,
               overwrite: bool, what: str, why: str = "that would mix with this run's",
               option: str = "--overwrite", resume: bool = False) -> Iterator[Path]:
    """Hold ``out`` for one run (the lock ``out/``:data:`FOLDER_LOCK`, :func:`locked_folder`, shared by every
    command that writes through this function) and yield an empty private folder ``out/.<prefix>.<hex>.partial``
    for its results; when the block ends without an error, move them into ``out`` (:func:`publish`: the new
    ``summary.json`` last) in place of the earlier results: ``earlier_results(out)`` (the command's own) and any
    other command's (:func:`run_results`). An error, or a kill, before the move leaves ``out`` as it was (a killed
    run's private folder is removed by the next run); a kill during the move leaves it without ``summary.json``.

    Raises FileExistsError, before any work, when ``out`` holds an earlier run's results, of this command or
    another, and ``overwrite`` is False (``what`` names the command's own results for the message, ``why`` says
    what this run would do to them, ``option`` is the flag that allows it), and
    :class:`cmax.io.atomic.OutputLockedError` when another run, of any of these commands, holds ``out``. With
    ``resume``, a folder whose run completed (it holds ``summary.json``) is not refused here: the block must call
    :func:`check_complete` before any work, which ends it (:class:`ResultsComplete` when it is the same run with
    its results intact, raised on with ``out`` untouched; another run is refused) or, when files of the same run
    are missing or changed, lets it run again: its results replace the damaged ones only when the
    ``summary.json`` it wrote records the same run as the one in ``out``.
    """
    out = Path(out)
    with locked_folder(out, FOLDER_LOCK):   # from the look at earlier results to the last file moved in
        discard_stages(out, prefix)
        own = set(earlier_results(out))
        earlier = sorted(own | set(run_results(out)))
        unchecked = resume and not overwrite and out / COMPLETION_MARKER in earlier   # for check_complete
        if earlier and not overwrite and not unchecked:
            if not own.issuperset(earlier):   # another command's results: name them as they are
                what = ", ".join(path.name for path in earlier[:3]) + (", ..." if len(earlier) > 3 else "")
            raise FileExistsError(f"{out} holds the results of an earlier run ({len(earlier)} files: {what}) {why}: "
                                  f"{option} replaces them, or give another -o")
        stage = new_stage(out, prefix)
        try:
            try:
                yield stage
            except OSError as error:   # before publish: out is untouched
                raise named_in_out(error, stage, out) from None
            if unchecked and not _same_run(out, stage):   # check_complete not called: the complete results kept
                raise RuntimeError(f"{out}: the complete results of an earlier run were not checked against this "
                                   "run (check_complete): they are kept, nothing was written")
            publish(stage, out, earlier)
        finally:
            shutil.rmtree(stage, ignore_errors=True)


def _same_run(out: Path, stage: Path) -> bool:
    """Whether the complete run in ``out`` and the one whose results are in ``stage`` are the same run (both
    ``summary.json`` record a ``"run"``, with no difference: :func:`cmax.io.window_store.run_differences`)."""
    from cmax.io.window_store import run_differences

    earlier, now = complete_run(out), complete_run(stage)
    return (earlier is not None and now is not None and isinstance(earlier.get("run"), dict)
            and isinstance(now.get("run"), dict) and not run_differences(earlier["run"], now["run"]))


def named_in_out(error: OSError, stage: Path, out: Path) -> OSError:
    """``error`` of a file in the private ``stage`` (a full disk, a file-size limit) as the same error naming the
    file it would have become in ``out``, and saying that ``out`` is as it was; other errors unchanged.

    Parameters
    ----------
    error : OSError
        The error of writing a file in ``stage``.
    stage, out : Path
        A run's private folder (:func:`new_stage`) and its output folder.
    """
    name = getattr(error, "filename", None)
    if not name or Path(name).parent != stage:
        return error
    reason = os.strerror(error.errno) if error.errno else str(error)
    return type(error)(error.errno, f"{reason} while writing the results; {out} is as it was (nothing of this run "
                                    "was moved into it)", str(out / Path(name).name))
