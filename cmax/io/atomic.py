"""Writing files that cannot lose data: an exclusive lock, a private temporary file, a checked rename.

Every writer of the project follows one protocol, given here as :class:`AtomicOutput`:

1. an exclusive lock ``<name>.lock`` beside the target is taken before anything
   is created or truncated (``flock``; a second writer of the same path fails at
   once with :class:`OutputLockedError` and changes nothing);
2. the data go to a temporary file of a unique name, ``<name>.<16 hex>.partial``
   in the target's folder, created with ``O_CREAT | O_EXCL | O_NOFOLLOW``: an
   existing file or a planted symbolic link is never opened, followed or truncated;
3. on success the temporary file is flushed (``fsync``), renamed onto the target
   (``os.replace`` replaces a link at the target, never what it points to) and
   the folder is flushed; on failure it is removed and the target is untouched.

Temporaries left by a killed writer are removed by the next writer of the same
target (under the lock). Small outputs use :func:`write_text_atomic` and
:func:`save_npz_atomic`, which follow steps 2 and 3.

A write error (full disk ``ENOSPC``, file-size limit ``EFBIG``, quota ``EDQUOT``)
is raised as :class:`OSError` with the errno kept and the message naming the
target; the temporary file is gone by then.
"""
from __future__ import annotations

import errno
import hashlib
import os
import re
import secrets
import signal
import stat
import threading
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = [
    "AtomicOutput", "OutputLockedError", "write_with", "write_text_atomic", "save_npz_atomic", "write_bytes_atomic",
    "ignore_file_size_signal", "PathLock", "lock_path", "temporaries", "discard_leftovers", "write_error",
    "check_unchanged", "file_sha256", "fsync_folder",
]

_TEMP_SUFFIX = ".partial"
_TOKEN_HEX = 16
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)


class OutputLockedError(BlockingIOError):
    """Another writer (process or object) holds the lock of this output; nothing was changed."""


def ignore_file_size_signal() -> None:
    """Make a file-size limit (``RLIMIT_FSIZE``) an ``EFBIG`` error instead of the signal ``SIGXFSZ``.

    CPython ignores ``SIGXFSZ`` at start-up; this restores that disposition when
    something reset it to the default (which kills the process). Only the main
    thread may change signal dispositions; elsewhere this does nothing.
    """
    sigxfsz = getattr(signal, "SIGXFSZ", None)
    if sigxfsz is None or threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(sigxfsz) == signal.SIG_DFL:
        signal.signal(sigxfsz, signal.SIG_IGN)


def _temp_name(path: Path) -> Path:
    return path.with_name(f"{path.name}.{secrets.token_hex(_TOKEN_HEX // 2)}{_TEMP_SUFFIX}")


def _temp_pattern(path: Path) -> re.Pattern:
    return re.compile(re.escape(path.name) + r"\.[0-9a-f]{%d}%s\Z" % (_TOKEN_HEX, re.escape(_TEMP_SUFFIX)))


def temporaries(path: str | os.PathLike) -> list[Path]:
    """The temporary files of ``path`` present in its folder (regular files only, links excluded)."""
    path = Path(path)
    pattern = _temp_pattern(path)
    try:
        names = os.listdir(path.parent)
    except OSError:
        return []
    found = []
    for name in sorted(names):
        if pattern.match(name):
            candidate = path.parent / name
            try:
                if stat.S_ISREG(os.lstat(candidate).st_mode):
                    found.append(candidate)
            except FileNotFoundError:
                continue
    return found


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file of the output ``path``: ``<name>.lock`` beside it."""
    path = Path(path)
    return path.with_name(path.name + ".lock")


def discard_leftovers(path: str | os.PathLike) -> list[Path]:
    """Remove the temporaries a killed writer of ``path`` left (under its lock); returns them.

    Raises :class:`OutputLockedError` while a writer of ``path`` is alive.
    """
    with PathLock(lock_path(path), path):
        stale = temporaries(path)
        for file in stale:
            file.unlink(missing_ok=True)
    return stale


def _create_exclusive(path: Path) -> int:
    """A new file at ``path`` (read-write, 0644 less umask); never an existing file, never through a link."""
    return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC, 0o644)


def fsync_folder(folder: Path) -> None:
    """Make the names in ``folder`` durable (files created, renamed or removed in it): fsync the folder itself,
    where the system lets a folder be opened; nothing happens where it does not."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0) | _CLOEXEC)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError as error:  # some file systems cannot sync a folder
        if error.errno not in (errno.EINVAL, errno.EBADF, errno.ENOTSUP, errno.EROFS):
            raise
    finally:
        os.close(fd)


def file_sha256(path: str | os.PathLike, read: Callable[[int], None] | None = None) -> str:
    """SHA-256 (hex) of a file's bytes at ``path``, read in 4 MiB blocks; ``read``: called with the bytes [B] of
    each block hashed (a progress bar's ``update``), or None."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 22), b""):
            digest.update(block)
            if read is not None:
                read(len(block))
    return digest.hexdigest()


def check_unchanged(paths: list, stats: list) -> None:
    """ValueError naming the first of ``paths`` whose size or modification time is no longer that of its ``stat``
    in ``stats`` (taken before it was read to hash it): a file still being written or copied, whose hash would
    stand for bytes that were never whole (and the run would read others).

    Parameters
    ----------
    paths : list of path
        The files hashed.
    stats : list of os.stat_result
        Their ``os.stat`` before they were read, in the same order.
    """
    for path, before in zip(paths, stats):
        try:
            after = os.stat(path)
        except OSError:
            after = None
        if after is None or (after.st_size, after.st_mtime_ns) != (before.st_size, before.st_mtime_ns):
            if after is None:
                now = "is gone"
            elif after.st_size != before.st_size:
                now = f"has {after.st_size:,} bytes (had {before.st_size:,})"
            else:
                now = "was modified"
            raise ValueError(f"{path} changed while it was read to hash it: it {now}; is it still being written or "
                             "copied? Run again once it is complete")


def write_error(error: OSError, path: Path, what: str = "writing") -> OSError:
    """``error`` as an :class:`OSError` of the same errno whose message names ``path``; one without an errno (the
    ``FileExistsError`` of a target that appeared before the rename) keeps its type and words."""
    code = error.errno
    if code is None:   # was: OSError('[Errno None] ...'), which a caller catching FileExistsError missed
        return type(error)(f"{error}; nothing was written under this name (the temporary file was removed)")
    reason = os.strerror(code) if code else str(error)
    return OSError(code, f"{reason} while {what}; nothing was written under this name "
                         "(the temporary file was removed)", str(path))


class PathLock:
    """An exclusive ``flock`` on the file ``lock_path`` (created if needed, never through a link).

    Taken at construction without waiting (:class:`OutputLockedError` when held
    elsewhere, ``what`` names the thing protected); :meth:`release` removes the
    lock file while still holding it, then lets go. A lock file left by a killed
    process holds no lock and is reused; a file of that name that holds data is no
    lock file (they are empty) and is refused (FileExistsError), never removed.
    """

    def __init__(self, lock_path: str | os.PathLike, what: str | os.PathLike | None = None) -> None:
        import fcntl

        self.path = Path(lock_path)
        what = self.path if what is None else what
        for _ in range(8):  # the file may be unlinked by its last holder between open and lock
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | _NOFOLLOW | _CLOEXEC | os.O_NONBLOCK, 0o644)
            except OSError as error:
                if error.errno == errno.ELOOP:
                    raise OSError(errno.ELOOP, "lock file is a symbolic link; refusing to follow it",
                                  str(self.path)) from None
                raise
            try:
                info = os.fstat(fd)
                if not stat.S_ISREG(info.st_mode):
                    raise OSError(errno.EINVAL, "lock file is not a regular file", str(self.path))
                if info.st_size:   # a lock file is empty: this one is someone's data, which release() would delete
                    raise FileExistsError(errno.EEXIST, f"{self.path.name} exists and holds data, so it is not a "
                                          "lock file of cmax (those are empty): move it, nothing was changed",
                                          str(self.path))
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    raise OutputLockedError(
                        errno.EWOULDBLOCK, f"{what} is being written by another writer "
                        f"(lock {self.path.name} held); nothing was changed", str(what)) from None
                try:
                    now = os.lstat(self.path)
                except FileNotFoundError:
                    now = None
                if now is not None and (now.st_ino, now.st_dev) == (info.st_ino, info.st_dev):
                    self._fd = fd
                    return
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)  # locked a lock file that was just removed: take the new one
        raise OutputLockedError(errno.EWOULDBLOCK, "could not take the lock", str(self.path))

    def __enter__(self) -> "PathLock":
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()

    def release(self) -> None:
        fd, self._fd = getattr(self, "_fd", None), None
        if fd is None:
            return
        try:
            os.unlink(self.path)  # still held: no other writer is between its lock and this unlink
        except FileNotFoundError:
            pass
        finally:
            os.close(fd)


class AtomicOutput:
    """One output file written under a lock to a private temporary file, then renamed.

    Parameters
    ----------
    path : path
        The target; its folder must exist.
    overwrite : bool
        Replace an existing target (only when the write succeeds). Without it an
        existing target (file or link) raises :class:`FileExistsError`, at the
        start and again at the rename.

    Attributes
    ----------
    path : Path
        The target.
    temp : Path
        The temporary file (``<name>.<hex>.partial``), open as :attr:`fd`.
    fd : int
        Read-write descriptor of the temporary file.

    Raises
    ------
    OutputLockedError
        Another writer holds the target's lock.
    FileExistsError, FileNotFoundError
        As above; a missing folder.
    """

    def __init__(self, path: str | os.PathLike, *, overwrite: bool = False) -> None:
        self.path = Path(path)
        self.overwrite = bool(overwrite)
        if not self.path.parent.is_dir():
            raise FileNotFoundError(f"cannot write {self.path}: its folder {self.path.parent} does not exist "
                                    "(No such file or directory)")
        ignore_file_size_signal()
        self._lock = PathLock(lock_path(self.path), self.path)
        self.fd: int | None = None
        try:
            self._check_target()
            for stale in temporaries(self.path):  # left by a killed writer: the lock is ours now
                stale.unlink(missing_ok=True)
            self.temp = _temp_name(self.path)
            self.fd = _create_exclusive(self.temp)
        except BaseException:
            self._lock.release()
            raise
        self.state = "open"

    def _check_target(self) -> None:
        if os.path.lexists(self.path):
            if os.path.isdir(self.path) and not os.path.islink(self.path):
                raise IsADirectoryError(errno.EISDIR, "output is a folder", str(self.path))
            if not self.overwrite:
                raise FileExistsError(f"{self.path} exists (pass overwrite=True to replace it)")

    def write(self, data) -> None:
        """Append ``data`` (bytes-like) at the current position of :attr:`fd`, all of it."""
        view = memoryview(data).cast("B")
        while view.nbytes:
            written = os.write(self.fd, view)
            view = view[written:]

    def commit(self) -> Path:
        """Flush the temporary file to disk, rename it onto the target, release the lock."""
        if self.state != "open":
            raise ValueError(f"the output {self.path} is {self.state}")
        try:
            try:   # a replaced file keeps its permission bits: a 0600 file does not come back 0644
                replaced = os.lstat(self.path)
                if stat.S_ISREG(replaced.st_mode):
                    os.fchmod(self.fd, stat.S_IMODE(replaced.st_mode))
            except FileNotFoundError:
                pass
            os.fsync(self.fd)
            os.close(self.fd)
            self.fd = None
            self._check_target()
            os.replace(self.temp, self.path)
            self.state = "committed"
            fsync_folder(self.path.parent)
        except BaseException:
            self.abort()
            raise
        finally:
            self._lock.release()
        return self.path

    def abort(self) -> None:
        """Remove the temporary file and release the lock; the target is untouched."""
        if self.state == "committed":
            return
        self.state = "aborted"
        if self.fd is not None:
            fd, self.fd = self.fd, None
            os.close(fd)
        try:
            os.unlink(self.temp)
        except FileNotFoundError:
            pass
        finally:
            self._lock.release()

    def __enter__(self) -> "AtomicOutput":
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


def write_with(path: str | os.PathLike, fill: Callable[[AtomicOutput], None], *, overwrite: bool = True) -> Path:
    """Write ``path`` through ``fill(output)`` (an :class:`AtomicOutput`), then commit; returns the path.

    Any exception of ``fill`` removes the temporary file; an :class:`OSError` of
    ``fill`` or of the commit (full disk, file-size limit) is raised with its
    errno and a message naming ``path``.
    """
    path = Path(path)
    output = AtomicOutput(path, overwrite=overwrite)
    try:
        fill(output)
    except OSError as error:
        output.abort()
        raise write_error(error, path) from None
    except BaseException:
        output.abort()
        raise
    try:
        return output.commit()
    except OSError as error:
        raise write_error(error, path) from None


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (lock, private temporary file, fsync, rename); returns the path."""
    return write_with(Path(path), lambda output: output.write(data))


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def save_npz_atomic(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to ``path`` atomically (the name is kept as given); returns the path."""

    def fill(output: AtomicOutput) -> None:
        with os.fdopen(os.dup(output.fd), "wb") as file:  # a file object: numpy would append ".npz" to a path
            np.savez_compressed(file, **arrays)

    return write_with(Path(path), fill)
