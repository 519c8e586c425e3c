"""SIGTERM handled as Ctrl-C is: ``timeout``, ``kill``, a SLURM time limit or torchrun stopping a run raise
:class:`Terminated` (a ``KeyboardInterrupt``) in the main thread, so that every ``finally`` and ``with`` block of the
run does its clean-up (locks released and their files removed, private stage folders and temporary files deleted,
workers stopped) instead of the process dying where it stands.

:func:`cmax._args.run_main` runs every command of ``cmax`` and ``python -m learned.*`` inside
:func:`sigterm_as_interrupt` and exits with status 143 (128 + SIGTERM) after the clean-up.
"""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Iterator

__all__ = ["Terminated", "sigterm_as_interrupt", "sigterm_deferred", "sigint_deferred", "stop_if_terminated",
           "TERMINATED_STATUS"]

#: The exit status of a run stopped by SIGTERM, as a shell reports a process killed by it.
TERMINATED_STATUS = 128 + int(signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C's ``KeyboardInterrupt`` would be, so that the same clean-up runs."""


#: Set by the SIGTERM handler of :func:`sigterm_as_interrupt`: the run was told to stop.
_SIGTERM_RECEIVED = threading.Event()
#: Open :func:`sigterm_deferred` blocks (main thread), and whether a SIGTERM came inside one.
_DEFERRAL = {"depth": 0, "pending": False}


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread (once: a second one is ignored, so
    it cannot cut the clean-up short); the previous handler is restored afterwards. Outside the main thread (where
    Python cannot install a handler) the block runs unchanged.

    A signal handler runs between any two bytecodes, also inside a finalizer or a weakref callback, where Python
    drops the exception it raises ("Exception ignored in ..."). The signal is remembered as well: such a dropped
    :class:`Terminated` is not printed, and :func:`stop_if_terminated` raises it again where the caller can stop.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _SIGTERM_RECEIVED.clear()
    _DEFERRAL["pending"] = False

    def terminate(signum, frame) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _SIGTERM_RECEIVED.set()
        if _DEFERRAL["depth"]:            # inside sigterm_deferred: raised when the block ends
            _DEFERRAL["pending"] = True
            return
        raise Terminated()

    def unraisable(info) -> None:
        if not isinstance(info.exc_value, Terminated):   # a dropped Terminated is remembered, not printed
            hook(info)

    previous, hook = signal.signal(signal.SIGTERM, terminate), sys.unraisablehook
    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
        sys.unraisablehook = hook


@contextmanager
def sigterm_deferred() -> Iterator[None]:
    """Within the block, a SIGTERM that :func:`sigterm_as_interrupt` turns into :class:`Terminated` is held back
    and raised when the block ends, so that a step the clean-up relies on is not cut in two: a worker process
    started AND recorded as running (one started but not yet recorded would be neither stopped nor cleaned up
    after). A block left by an exception while a SIGTERM is held back raises :class:`Terminated` instead: the
    failure is the signal's doing (the ``forkserver``, signalled with the process group by ``timeout`` or a batch
    system, dies under ``Process.start``: ``EOFError``), and the run stops on the signal, in one line. Outside
    :func:`sigterm_as_interrupt` (or outside the main thread) the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _DEFERRAL["depth"] += 1
    try:
        yield
    except BaseException:
        if _DEFERRAL["depth"] == 1 and _DEFERRAL["pending"]:
            _DEFERRAL["pending"] = False
            raise Terminated() from None
        raise
    finally:
        _DEFERRAL["depth"] -= 1
    if not _DEFERRAL["depth"] and _DEFERRAL["pending"]:
        _DEFERRAL["pending"] = False
        raise Terminated()


@contextmanager
def sigint_deferred() -> Iterator[None]:
    """Within the block, Ctrl-C (SIGINT) is held back and its ``KeyboardInterrupt`` raised when the block ends, as
    :func:`sigterm_deferred` holds SIGTERM: a worker process started AND recorded, so that the clean-up stops it
    (one started but not recorded was left to fail on its own, printing a traceback once the caller had exited). A
    block left by an exception while a Ctrl-C is held raises ``KeyboardInterrupt`` instead. The previous handler is
    restored afterwards, and a held Ctrl-C goes to it when it is a handler of the caller's own (not Python's
    default); outside the main thread (where Python cannot set a handler), or where SIGINT is ignored (a command
    started with ``nohup`` or in the background of a script), the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        yield
    except BaseException:
        if held:
            raise KeyboardInterrupt() from None
        raise
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
    if held:
        if callable(previous) and previous is not signal.default_int_handler:
            previous(signal.SIGINT, None)
        else:
            raise KeyboardInterrupt()


def stop_if_terminated() -> None:
    """Raise :class:`Terminated` when SIGTERM came but its exception was dropped (see :func:`sigterm_as_interrupt`)."""
    if _SIGTERM_RECEIVED.is_set():
        raise Terminated()
