"""The signature of a conversion's source, so that a resumed conversion can tell whether its source changed.

A signature is a small JSON-ready dict: the source's resolved path, the number of files it reads, their
total byte size, the latest modification time (``st_mtime_ns``, integer nanoseconds) and the SHA-256 of
their bytes. A video is one file; an image sequence (a folder, or an ``images.txt`` / ``timestamps.txt``
file) is its timestamp file and the images that file lists (as :func:`cmax.sim.video.read_timestamps`
resolves them). Nothing is decoded, but every file is read once to hash it (:func:`cmax.io.atomic.file_sha256`).
Replacing, re-exporting, copying or touching the source changes it, and so does another file of the same
size given the old modification time (``cp -p``, ``rsync -t``, ``touch -r``, a re-download keeping the
server's time: its SHA-256 differs); moving it (``mv`` keeps bytes, sizes and times: a collection moved to
another disk is not converted again) does not. The path is recorded, not compared. A signature recorded
without a SHA-256 (by an earlier version) is compared by what it holds.

>>> _ = Path("a.mp4").write_bytes(b"12345")
>>> signature = source_signature("a.mp4")
>>> signature["files"], signature["bytes"], signature["sha256"][:12]
(1, 5, '5994471abb01')
>>> signature_problem(signature, source_signature("a.mp4")) is None
True
>>> _ = Path("a.mp4").write_bytes(b"1234567")
>>> signature_problem(signature, source_signature("a.mp4"))
'a.mp4 has 7 bytes, it had 5'
"""
from __future__ import annotations

import os
import warnings
import hashlib
from pathlib import Path
from typing import Any, Callable

from cmax.io.atomic import check_unchanged, file_sha256

__all__ = ["source_files", "source_signature", "signature_problem", "content_sha256"]


def source_files(source: str | os.PathLike) -> list[Path]:
    """The files a conversion of ``source`` reads: the video itself, or an image sequence's timestamp
    file and its images (the same ones :func:`cmax.sim.video.open_source` would read).

    Raises FileNotFoundError for a missing source, ValueError for an image sequence whose timestamp
    file is unreadable (as the conversion itself would).
    """
    from cmax.sim.video import _find_timestamps, read_timestamps

    path = Path(source)
    if not path.exists():
        raise FileNotFoundError(f"no such file or folder: {path}")
    if not path.is_dir() and path.suffix.lower() != ".txt":
        return [path]
    stamps = _find_timestamps(path) if path.is_dir() else path
    with warnings.catch_warnings():  # a note on the times is the conversion's to give, once
        warnings.simplefilter("ignore")
        return [stamps, *read_timestamps(stamps, path if path.is_dir() else path.parent)[1]]


def content_sha256(files: list[Path], read: Callable[[int], None] | None = None) -> str:
    """SHA-256 (hex) of the bytes of ``files``, in order: a single file's own SHA-256
    (:func:`cmax.io.atomic.file_sha256`), else that of the files' SHA-256s, one per line; ``read``: called with the
    bytes [B] of each block hashed (a progress bar's ``update``), or None."""
    if len(files) == 1:
        return file_sha256(files[0], read)
    return hashlib.sha256("".join(file_sha256(file, read) + "\n" for file in files).encode()).hexdigest()


def source_signature(source: str | os.PathLike, read: Callable[[int], None] | None = None) -> dict[str, Any]:
    """``{"path": resolved path, "files": n, "bytes": total bytes, "mtime_ns": latest mtime (ns), "sha256": hex}``
    of the files :func:`source_files` lists (``sha256``: :func:`content_sha256` of them, read after their
    ``stat``); ``read`` as there. ValueError naming a file whose size or modification time changed while it was
    hashed (a video still being downloaded or copied: :func:`cmax.io.atomic.check_unchanged`)."""
    files = source_files(source)
    stats = [os.stat(file) for file in files]
    digest = content_sha256(files, read)
    check_unchanged(files, stats)      # a video still being downloaded or copied: refused, not half recorded
    return {"path": str(Path(source).resolve()), "files": len(files), "bytes": sum(s.st_size for s in stats),
            "mtime_ns": max(s.st_mtime_ns for s in stats), "sha256": digest}


def signature_problem(recorded: dict[str, Any], now: dict[str, Any],
                      modified: str = "after it was converted") -> str | None:
    """How the signature ``now`` differs from ``recorded`` in files, bytes, latest mtime or, where both hold it,
    SHA-256 (a short phrase, which names both paths when they differ too), or None when it does not (the paths may
    differ: a moved source is the same source); ``modified`` says when a changed mtime was modified (``"{name} was
    modified {modified} (mtime ...)"``)."""
    name = Path(str(now.get("path", ""))).name
    if recorded.get("files") != now.get("files"):
        problem = f"{name} has {now.get('files')} files, it had {recorded.get('files')}"
    elif recorded.get("bytes") != now.get("bytes"):
        problem = f"{name} has {now.get('bytes')} bytes, it had {recorded.get('bytes')}"
    elif recorded.get("mtime_ns") != now.get("mtime_ns"):
        problem = (f"{name} was modified {modified} (mtime {now.get('mtime_ns')} ns, was "
                   f"{recorded.get('mtime_ns')} ns)")
    elif "sha256" in recorded and "sha256" in now and recorded["sha256"] != now["sha256"]:
        problem = (f"{name} holds other bytes than it did (another SHA-256, with the same size and modification "
                   "time: a file copied over it with its time kept?)")
    else:
        return None
    if recorded.get("path") != now.get("path"):
        problem = f"it was {recorded.get('path')}, now {now.get('path')}, and {problem}"
    return problem
