"""How many threads a torch computation may use, so that it never falls off a cliff.

torch's intra-op thread pool (OpenMP) spins and waits at the end of every
parallel region for all its threads. When other processes keep the cores
busy, one descheduled thread stalls the whole region: rendering an
``indoor_flying`` frame at 346x260 drops from about 125 frames/s with one
thread to under 10 frames/s with two threads on a busy two-core machine.
:func:`torch_threads` picks a count the machine can actually serve:

* 1 for small work (``work`` below ``small`` elements), where threads cost
  more to wake than they save;
* otherwise the cores this process may run on (``os.sched_getaffinity``)
  less those other processes keep busy (the 1-minute load average, counting
  this process's own running thread as one), at least 1.

``CMAX_TORCH_THREADS`` in the environment overrides the choice (a positive
integer). :func:`torch_threads_scope` sets torch's thread count for a block
and restores it afterwards; every torch path of the library (renderer, fit,
loss, network) runs inside one.

The BLAS that numpy and scipy load (OpenBLAS) has its own spinning pool with
the same cliff: scipy's L-BFGS-B on the fit's few dozen parameters gains
nothing from a second thread and loses several times over on a busy machine.
:func:`blas_threads_scope` sets those libraries' count for a block (the fit
runs in one, with the torch count).
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Iterator

__all__ = ["available_cores", "torch_threads", "torch_threads_scope", "blas_threads_scope", "set_blas_threads",
           "SMALL_WORK"]

#: Elements of work below which one thread is used.
SMALL_WORK = 1 << 16

_ENV = "CMAX_TORCH_THREADS"


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity; ``os.cpu_count()`` where unknown), >= 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _load_average() -> float:
    try:
        return os.getloadavg()[0]
    except (AttributeError, OSError):  # pragma: no cover - not Unix
        return 0.0


def torch_threads(work: int | None = None, *, small: int = SMALL_WORK,
                  cores: int | None = None, load: float | None = None) -> int:
    """Threads for a torch computation of ``work`` elements on this machine now.

    Parameters
    ----------
    work : int, optional
        Elements the computation touches (e.g. pixels x planes); None: large.
    small : int, keyword-only
        Below this much work, 1 thread.
    cores, load : keyword-only
        The available cores and 1-minute load average; by default measured
        (:func:`available_cores`, ``os.getloadavg``).

    Returns
    -------
    int
        ``$CMAX_TORCH_THREADS`` if set; else 1 for small work; else
        ``min(cores, cores - load + 1)`` rounded, at least 1 (the ``+ 1`` is
        this process's own running thread, which the load average counts).

    Examples
    --------
    >>> torch_threads(10)
    1
    >>> torch_threads(10**7, cores=8, load=1.0), torch_threads(10**7, cores=2, load=4.0)
    (8, 1)
    """
    forced = os.environ.get(_ENV)
    if forced:
        try:
            value = int(forced)
        except ValueError:
            raise ValueError(f"{_ENV} must be a positive integer, got {forced!r}") from None
        if value < 1:
            raise ValueError(f"{_ENV} must be a positive integer, got {forced!r}")
        return value
    if work is not None and work < small:
        return 1
    cores = available_cores() if cores is None else int(cores)
    load = _load_average() if load is None else float(load)
    free = int(cores - load + 1.5)  # rounded: cores - (load - own thread)
    return max(1, min(cores, free))


@contextmanager
def torch_threads_scope(work: int | None = None, *, threads: int | None = None) -> Iterator[int]:
    """Run a block with torch's intra-op threads set by :func:`torch_threads` (or ``threads``).

    Restores the previous count afterwards; yields the count used. torch's
    count is process-wide: a scope entered by another thread meanwhile sees
    this one's setting.

    Examples
    --------
    >>> with torch_threads_scope(100) as n:
    ...     n
    1
    """
    import torch

    before = torch.get_num_threads()
    wanted = torch_threads(work) if threads is None else int(threads)
    if wanted < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    changed = wanted != before
    if changed:
        torch.set_num_threads(wanted)
    try:
        yield wanted
    finally:
        if changed:
            torch.set_num_threads(before)


#: Thread-count setters and getters of the OpenBLAS builds numpy and scipy ship (their symbols are renamed).
_OPENBLAS_SYMBOLS = (("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                     ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
                     ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
                     ("openblas_set_num_threads", "openblas_get_num_threads"))


#: ``(len(sys.modules), pools)`` of the last scan of :func:`_openblas_pools`.
_POOLS_SEEN: tuple[int, list[tuple]] | None = None


def _openblas_pools() -> list[tuple]:
    """``(setter, getter)`` of every OpenBLAS mapped into this process (Linux ``/proc/self/maps``;
    empty elsewhere or when none is loaded).

    The scan reads every mapping of the process (many, with torch and numba loaded), so its result is kept
    until a module is imported: an OpenBLAS comes into the process with the extension module that links
    it (numpy, scipy). A library loaded some other way (``ctypes``) is seen at the next import; missing it
    costs speed only.
    """
    global _POOLS_SEEN
    import sys

    if _POOLS_SEEN is not None and _POOLS_SEEN[0] == len(sys.modules):
        return _POOLS_SEEN[1]
    pools = _scan_openblas()
    _POOLS_SEEN = (len(sys.modules), pools)
    return pools


def _scan_openblas() -> list[tuple]:
    """:func:`_openblas_pools` without the memo: read ``/proc/self/maps`` and load each OpenBLAS's symbols."""
    import ctypes

    try:
        with open("/proc/self/maps", encoding="utf-8") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line.lower() and ".so" in line})
    except OSError:  # pragma: no cover - not Linux
        return []
    pools = []
    for path in paths:
        try:
            library = ctypes.CDLL(path)
        except OSError:  # pragma: no cover - unloadable
            continue
        for set_name, get_name in _OPENBLAS_SYMBOLS:
            if hasattr(library, set_name) and hasattr(library, get_name):
                getter = getattr(library, get_name)
                getter.restype = ctypes.c_int
                pools.append((getattr(library, set_name), getter))
                break
    return pools


def _set_pools(pools: list[tuple], counts: list[int]) -> list[int]:
    """Set each OpenBLAS pool of :func:`_openblas_pools` to its count; returns their counts before."""
    import ctypes

    before = [int(getter()) for _, getter in pools]
    for (setter, _), count in zip(pools, counts):
        setter(ctypes.c_int(count))
    return before


def _check_threads(threads: object) -> int:
    if isinstance(threads, bool) or not (isinstance(threads, int) and threads >= 1):
        raise ValueError(f"threads must be an int >= 1, got {threads!r}")
    return threads


def set_blas_threads(threads: int) -> list[int]:
    """Set every loaded OpenBLAS to ``threads`` (>= 1) threads; returns their counts before, one per
    library (empty: none loaded, or not Linux)."""
    pools = _openblas_pools()
    return _set_pools(pools, [_check_threads(threads)] * len(pools))


@contextmanager
def blas_threads_scope(threads: int) -> Iterator[int]:
    """Run a block with every loaded OpenBLAS (numpy's, scipy's) on ``threads`` threads; restores each
    library's count afterwards. Yields ``threads``.

    Examples
    --------
    >>> import numpy
    >>> with blas_threads_scope(1) as n:
    ...     n
    1
    """
    threads = _check_threads(threads)
    pools = _openblas_pools()
    before = _set_pools(pools, [threads] * len(pools))
    try:
        yield threads
    finally:
        _set_pools(pools, before)
