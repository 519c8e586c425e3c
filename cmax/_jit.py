"""Compiled kernels on demand: :func:`kernel` wraps a plain-Python loop for numba.

numba is imported, and the function compiled (or loaded from numba's on-disk
cache), at the first call, so importing a module that defines kernels costs
nothing. Kernels are compiled with ``nopython`` mode, ``nogil`` (they can run
in a worker thread alongside numpy and OpenCV) and ``cache=True``. A kernel
may call other kernels by their global names: those are compiled first and
given to it in their compiled form.
"""
from __future__ import annotations

import threading
import types
from typing import Any, Callable

_LOCK = threading.RLock()  # re-entered when a kernel compiles the kernels it calls


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
                    self._compiled = self._compile()
        return self._compiled

    def _compile(self) -> Callable:
        import numba

        function = self._function
        names, scope = function.__code__.co_names, function.__globals__
        callees = {name: scope[name] for name in names if isinstance(scope.get(name), _Kernel)}
        if callees:  # the same code, seeing the other kernels compiled
            resolved = {name: callee.compiled for name, callee in callees.items()}
            function = types.FunctionType(function.__code__, {**scope, **resolved},
                                          function.__name__, function.__defaults__,
                                          function.__closure__)
        return numba.njit(**self._options)(function)

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


def vector_kernel(function: Callable | None = None, **options: Any) -> Callable:
    """:func:`kernel` with numpy's error model: a float division by zero gives inf or nan instead of
    raising ``ZeroDivisionError``.

    numba's default (Python's) model tests every divisor, and that branch keeps LLVM from vectorising
    the loop around it; under this model a loop of divisions runs on SIMD registers. For kernels whose
    divisors cannot be zero (clamped depths, positive counts plus an epsilon): a divisor that can be
    zero needs its own guard.
    """
    return kernel(function, error_model="numpy", **options)
