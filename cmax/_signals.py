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

__all__ = ["Terminated", "sigterm_as_interrupt", "stop_if_terminated", "TERMINATED_STATUS"]

#: The exit status of a run stopped by SIGTERM, as a shell reports a process killed by it.
TERMINATED_STATUS = 128 + int(signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C's ``KeyboardInterrupt`` would be, so that the same clean-up runs."""


#: Set by the SIGTERM handler of :func:`sigterm_as_interrupt`: the run was told to stop.
_SIGTERM_RECEIVED = threading.Event()


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

    def terminate(signum, frame) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        _SIGTERM_RECEIVED.set()
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


def stop_if_terminated() -> None:
    """Raise :class:`Terminated` when SIGTERM came but its exception was dropped (see :func:`sigterm_as_interrupt`)."""
    if _SIGTERM_RECEIVED.is_set():
        raise Terminated()
