"""SIGTERM and SIGHUP handled as Ctrl-C is: ``timeout``, ``kill``, a SLURM time limit or torchrun stopping a run
(SIGTERM), a closed ssh session or terminal, a batch system's hangup (SIGHUP) raise :class:`Terminated` (a
``KeyboardInterrupt``) in the main thread, so that every ``finally`` and ``with`` block of the run does its clean-up
(locks released and their files removed, private stage folders and temporary files deleted, workers stopped)
instead of the process dying where it stands.

:func:`cmax._args.run_main` runs every command of ``cmax`` and ``python -m learned.*`` inside
:func:`sigterm_as_interrupt` and exits with status 128 + the signal's number after the clean-up (143 for SIGTERM, 129
for SIGHUP); a process started with SIGHUP ignored (``nohup``) keeps ignoring it. Once the command has ended, a
signal during the interpreter's exit is ignored, so that the process exits with the command's status
(:func:`ignore_while_exiting`).
"""
from __future__ import annotations

import signal
import sys
import threading
from contextlib import contextmanager
from typing import Iterator

__all__ = ["Terminated", "sigterm_as_interrupt", "sigterm_deferred", "sigint_deferred", "stop_if_terminated",
           "terminated_by", "ignore_while_exiting", "STOP_SIGNALS", "TERMINATED_STATUS"]

#: The exit status of a run stopped by SIGTERM, as a shell reports a process killed by it.
TERMINATED_STATUS = 128 + int(signal.SIGTERM)
#: The signals that stop a run as Ctrl-C does (:func:`sigterm_as_interrupt`): SIGTERM, and SIGHUP where there is one.
STOP_SIGNALS: tuple[int, ...] = (signal.SIGTERM,) + ((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ())


class Terminated(KeyboardInterrupt):
    """SIGTERM (or SIGHUP: ``signum``), raised where Ctrl-C's ``KeyboardInterrupt`` would be, so that the same
    clean-up runs.

    Parameters
    ----------
    signum : int
        The signal's number (default SIGTERM).
    """

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__()
        self.signum = int(signum)

    @property
    def name(self) -> str:
        """The signal's name, e.g. ``"SIGTERM"``, ``"SIGHUP"``."""
        return signal.Signals(self.signum).name

    @property
    def status(self) -> int:
        """The exit status of a run it stopped: 128 + the signal's number (143 for SIGTERM, 129 for SIGHUP)."""
        return 128 + self.signum


#: The stop signal the handler of :func:`sigterm_as_interrupt` received (its number; None: none): the run was told to
#: stop.
_RECEIVED: dict[str, int | None] = {"signum": None}
#: Open :func:`sigterm_deferred` blocks (main thread), and whether a stop signal came inside one.
_DEFERRAL = {"depth": 0, "pending": False}


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM and SIGHUP (:data:`STOP_SIGNALS`) raise :class:`Terminated` in the main thread
    (once: a second one of either, or a Ctrl-C, is ignored from then on, so it cannot cut the clean-up short nor
    turn the run's status into Ctrl-C's 130); the previous handlers are restored afterwards. A signal ignored when the block starts (SIGHUP under ``nohup``) stays ignored. Outside the
    main thread (where Python cannot install a handler) the block runs unchanged.

    A signal handler runs between any two bytecodes, also inside a finalizer or a weakref callback, where Python
    drops the exception it raises ("Exception ignored in ..."). The signal is remembered as well: such a dropped
    :class:`Terminated` is not printed, and :func:`stop_if_terminated` raises it again where the caller can stop.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _RECEIVED["signum"] = None
    _DEFERRAL["pending"] = False
    handled = [signum for signum in STOP_SIGNALS if signal.getsignal(signum) != signal.SIG_IGN]
    interrupt = signal.getsignal(signal.SIGINT)

    def terminate(signum, frame) -> None:
        for each in (*handled, signal.SIGINT):   # the clean-up runs to its end, and the status stays the signal's
            signal.signal(each, signal.SIG_IGN)
        _RECEIVED["signum"] = signum
        if _DEFERRAL["depth"]:            # inside sigterm_deferred: raised when the block ends
            _DEFERRAL["pending"] = True
            return
        raise Terminated(signum)

    def unraisable(info) -> None:
        if not isinstance(info.exc_value, Terminated):   # a dropped Terminated is remembered, not printed
            hook(info)

    previous = {signum: signal.signal(signum, terminate) for signum in handled}
    hook = sys.unraisablehook
    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        if _RECEIVED["signum"] is not None:
            signal.signal(signal.SIGINT, interrupt if interrupt is not None else signal.SIG_DFL)
        sys.unraisablehook = hook


@contextmanager
def sigterm_deferred() -> Iterator[None]:
    """Within the block, a SIGTERM (or SIGHUP) that :func:`sigterm_as_interrupt` turns into :class:`Terminated` is
    held back and raised when the block ends, so that a step the clean-up relies on is not cut in two: a worker process
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
            raise Terminated(_RECEIVED["signum"] or signal.SIGTERM) from None
        raise
    finally:
        _DEFERRAL["depth"] -= 1
    if not _DEFERRAL["depth"] and _DEFERRAL["pending"]:
        _DEFERRAL["pending"] = False
        raise Terminated(_RECEIVED["signum"] or signal.SIGTERM)


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

    def hold(signum, frame) -> None:
        held.append(signum)

    previous = signal.signal(signal.SIGINT, hold)
    try:
        yield
    except BaseException:
        if held:
            raise KeyboardInterrupt() from None
        raise
    finally:
        if signal.getsignal(signal.SIGINT) is hold:   # else a stop signal came and ignores Ctrl-C for its clean-up
            signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)
    if held:
        if callable(previous) and previous is not signal.default_int_handler:
            previous(signal.SIGINT, None)
        else:
            raise KeyboardInterrupt()


def stop_if_terminated() -> None:
    """Raise :class:`Terminated` when SIGTERM or SIGHUP came but its exception was dropped (see
    :func:`sigterm_as_interrupt`)."""
    if _RECEIVED["signum"] is not None:
        raise Terminated(_RECEIVED["signum"])


def terminated_by() -> int | None:
    """The number of the stop signal (SIGTERM, SIGHUP) the last :func:`sigterm_as_interrupt` block received; None when
    none came."""
    return _RECEIVED["signum"]


def ignore_while_exiting() -> None:
    """From now on, Ctrl-C, SIGTERM and SIGHUP are ignored: for a command that has ended (its clean-up done, its line
    printed, its status returned) and whose process only exits. Python restores the default handlers early in its
    exit, before the modules and torch's libraries are torn down (a second or more), so that a signal then killed
    the process (exit -2 / -15, sometimes a traceback from a finalizer) instead of letting it exit with the
    command's status; an ignored signal stays ignored through it. Only for the process's own command line: Python
    code calling a command's ``main`` keeps its handlers. SIGKILL and SIGQUIT (Ctrl-\\) still end an exit that
    hangs. Outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in (signal.SIGINT, *STOP_SIGNALS):
        signal.signal(signum, signal.SIG_IGN)
