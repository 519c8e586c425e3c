"""Worker processes that do not outlive the process that started them."""
from __future__ import annotations

import os
import signal
import sys
import threading
import time

__all__ = ["die_with_parent"]

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
