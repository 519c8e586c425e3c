"""Worker processes that do not outlive the process that started them, and whose warnings reach the caller.

:func:`recorded` runs a task with its warnings recorded, as plain data a pipe can carry; :func:`reissue` warns
them again in the calling process, under its filters and in its format, each naming its task (a fit's window,
a conversion's video). The serial paths use the same pair, so a warning reads the same with or without workers.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
import warnings
from typing import Any, Callable, Sequence, TypeVar

__all__ = ["die_with_parent", "recorded", "reissue", "start_forkserver"]

T = TypeVar("T")

_PR_SET_PDEATHSIG = 1


def die_with_parent(main_pid: int) -> None:
    """Kill this worker when its parent process dies, or when the process ``main_pid`` is gone.

    The parent is the ``forkserver`` of ``main_pid`` (which exits when
    ``main_pid`` dies) or ``main_pid`` itself (``spawn``). Linux:
    ``prctl(PR_SET_PDEATHSIG, SIGKILL)``. Everywhere: a daemon thread that checks
    every 0.2 s whether the parent changed or ``main_pid`` vanished (which also
    covers a parent that died before the ``prctl``).
    """
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # no libc prctl: the thread below still watches
            pass
    parent = os.getppid()

    def orphaned() -> bool:
        if os.getppid() != parent:
            return True
        try:
            os.kill(main_pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:  # exists, another user's (a reused pid): not ours any more
            return True
        return False

    if orphaned():
        os._exit(1)

    def watch() -> None:
        while not orphaned():
            time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


def start_forkserver(context: Any) -> None:
    """Start the server of a ``forkserver`` multiprocessing ``context`` now, ignoring SIGINT (a no-op for another
    start method, or where the server runs already). Ctrl-C goes to the terminal's whole process group: the server,
    importing its preloaded modules for seconds, printed the traceback of a ``KeyboardInterrupt`` in the middle of
    that import, dozens of lines under the caller's one line. Started with SIGINT ignored (a disposition that
    survives ``exec``), the server and the workers it forks never see Ctrl-C: the calling process stops its workers
    itself. SIGHUP likewise (a closed ssh session signals the whole job): the server, its workers and
    multiprocessing's resource tracker (started with the server) ignore it, and the calling process, which stops on
    it (:mod:`cmax._signals`), stops its workers; the tracker, killed by it, was relaunched with a warning and
    tracebacks. The caller's own SIGINT and SIGHUP are blocked meanwhile (on Linux a blocked signal stays pending
    even while ignored), their handlers restored, then unblocked: a signal that came meanwhile reaches it when this
    returns.
    Outside the main thread (where no handler can be set) the server is started as it is."""
    if context.get_start_method() != "forkserver":
        return
    from multiprocessing import forkserver

    if threading.current_thread() is not threading.main_thread():
        forkserver.ensure_running()
        return
    ignored = {signal.SIGINT} | ({signal.SIGHUP} if hasattr(signal, "SIGHUP") else set())
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, ignored)
    try:
        handlers = {signum: signal.signal(signum, signal.SIG_IGN) for signum in ignored}
        try:
            forkserver.ensure_running()
        finally:
            for signum, handler in handlers.items():
                signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def recorded(call: Callable[[], T]) -> tuple[T, tuple[tuple[str, str], ...]]:
    """``call()`` with every warning it raises recorded, not shown: ``(result, ((category, message), ...))``, the
    category as the text ``module:qualname`` (plain data: a class the caller cannot import costs the task
    nothing, :func:`reissue` falls back to UserWarning), for :func:`reissue`."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = call()
    return result, tuple((f"{w.category.__module__}:{w.category.__qualname__}", str(w.message)) for w in caught)


def reissue(prefix: str, caught: Sequence[tuple[str, str]], *, stacklevel: int) -> None:
    """Warn again the ``(category, message)`` pairs ``caught`` (:func:`recorded`'s), each message prefixed with
    ``prefix: ``; ``stacklevel`` as :func:`warnings.warn` takes it, counted from the caller's frame."""
    for name, message in caught:
        warnings.warn(f"{prefix}: {message}", _category_of(name), stacklevel=stacklevel + 1)


def _category_of(name: str) -> type:
    """The warning class that :func:`recorded` named ``module:qualname``, or UserWarning when it cannot be found.

    >>> _category_of("builtins:RuntimeWarning"), _category_of("nowhere:Gone")
    (<class 'RuntimeWarning'>, <class 'UserWarning'>)
    """
    import importlib

    module, _, qualname = name.partition(":")
    try:
        found: Any = importlib.import_module(module)
        for part in qualname.split("."):
            found = getattr(found, part)
    except Exception:
        return UserWarning
    return found if isinstance(found, type) and issubclass(found, Warning) else UserWarning
