"""Compiled kernels on demand: :func:`kernel` wraps a plain-Python loop for numba.

numba is imported, and the function compiled (or loaded from numba's on-disk
cache), at the first call, so importing a module that defines kernels costs
nothing. Kernels are compiled with ``nopython`` mode, ``nogil`` (they can run
in a worker thread alongside numpy and OpenCV) and ``cache=True``. A kernel
may only call numba-compilable code: other kernels are reached through their
``.compiled`` attribute inside the wrapper that calls them, never as globals.
"""
from __future__ import annotations

import threading
from typing import Any, Callable

_LOCK = threading.Lock()


class _Kernel:
    """A function compiled by ``numba.njit`` at its first call."""

    def __init__(self, function: Callable, options: dict[str, Any]) -> None:
        self._function, self._options, self._compiled = function, options, None
        self.__doc__, self.__name__ = function.__doc__, function.__name__
        self.__wrapped__ = function

    @property
    def compiled(self) -> Callable:
        """The numba dispatcher (compiling it on first access)."""
        if self._compiled is None:
            with _LOCK:
                if self._compiled is None:
                    import numba

                    self._compiled = numba.njit(**self._options)(self._function)
        return self._compiled

    def __call__(self, *args: Any) -> Any:
        return self.compiled(*args)


def kernel(function: Callable | None = None, **options: Any) -> Callable:
    """Decorate a loop kernel: compiled by numba (nogil, cached) at its first call.

    ``@kernel`` or ``@kernel(fastmath=True)``; ``options`` go to ``numba.njit``.
    """
    settings = {"cache": True, "nogil": True, **options}
    if function is None:
        return lambda f: _Kernel(f, settings)
    return _Kernel(function, settings)
