"""Background decoding: items made in threads, a bounded number ahead, in order.

Used by the frame sources of :mod:`cmax.sim.video`: OpenCV releases the GIL
while it decodes a video frame or an image, so decoding overlaps with the
simulation of the frames before.

* :func:`prefetched` runs one iterator (a video stream, decoded in order) in
  one background thread;
* :func:`ordered_map` applies a function to independent items (image files)
  in a small pool of threads, several at once, and yields the results in the
  items' order.

Both keep at most ``depth`` results made ahead of the consumer (bounded
memory), raise a worker's exception in the consuming thread at the item
where it happened (after the items before it), and leave no thread running
once the iteration ends, fails, is interrupted (``KeyboardInterrupt``) or is
closed early (``break``, garbage collection).
"""
from __future__ import annotations

import collections
import queue
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

import numpy as np

from cmax._threads import available_cores

__all__ = ["DEFAULT_PREFETCH", "MAX_DECODERS", "default_decoders", "ordered_map", "prefetched"]

T = TypeVar("T")
R = TypeVar("R")
#: Frames decoded ahead of the consumer by default.
DEFAULT_PREFETCH = 4
#: Most decoding threads chosen by :func:`default_decoders`.
MAX_DECODERS = 4


def default_decoders(cores: int | None = None) -> int:
    """Decoding threads for an image folder: the available cores, at most :data:`MAX_DECODERS`.

    Parameters
    ----------
    cores : int, optional
        Cores this process may use (default :func:`cmax._threads.available_cores`).

    Returns
    -------
    int
        ``min(MAX_DECODERS, cores)``, at least 1. The consumer's own thread
        (the simulation) is not subtracted: it waits on the decoders
        whenever decoding is the slower part, which is when more of them help.

    Examples
    --------
    >>> default_decoders(1), default_decoders(2), default_decoders(16)
    (1, 2, 4)
    """
    cores = available_cores() if cores is None else int(cores)
    return max(1, min(MAX_DECODERS, cores))


def _check_decoders(decoders: object) -> int:
    if decoders is None:
        return default_decoders()
    if isinstance(decoders, (bool, np.bool_)) or not isinstance(decoders, (int, np.integer)):
        raise TypeError(f"decoders must be an integer number of threads or None, got {decoders!r}")
    if decoders < 1:
        raise ValueError(f"decoders must be >= 1 thread, got {decoders}")
    return int(decoders)


def _check_prefetch(prefetch: object) -> int:
    if isinstance(prefetch, (bool, np.bool_)) or not isinstance(prefetch, (int, np.integer)):
        raise TypeError(f"prefetch must be an integer number of frames, got {prefetch!r}")
    if prefetch < 0:
        raise ValueError(f"prefetch must be >= 0 frames, got {prefetch}")
    return int(prefetch)


_ITEM, _END, _ERROR = 0, 1, 2


def prefetched(produce: Callable[[], Iterator[T]], depth: int) -> Iterator[T]:
    """The items of ``produce()``, made in a background thread at most ``depth`` ahead.

    Parameters
    ----------
    produce : callable
        Returns a fresh iterator; it runs in the background thread (and is
        closed there, also when the consumer stops early).
    depth : int
        Size of the bounded queue (>= 1); 0 runs ``produce()`` in this thread.

    Yields
    ------
    The items, in order. An exception of the producer is raised here after
    the items made before it.
    """
    if depth == 0:
        yield from produce()
        return
    items: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(entry: tuple[int, object]) -> bool:
        while not stop.is_set():
            try:
                items.put(entry, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def work() -> None:
        iterator = None
        try:
            iterator = produce()
            for item in iterator:
                if not put((_ITEM, item)):
                    return
            put((_END, None))
        except BaseException as error:  # handed to the consumer
            put((_ERROR, error))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()

    thread = threading.Thread(target=work, name="frame-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            kind, value = items.get()
            if kind == _ITEM:
                yield value
            elif kind == _END:
                return
            else:
                raise value
    finally:
        stop.set()
        thread.join()


def ordered_map(function: Callable[[T], R], items: Iterable[T], workers: int,
                depth: int) -> Iterator[R]:
    """``function(item)`` for each item, computed by ``workers`` threads, yielded in order.

    Parameters
    ----------
    function : callable
        Applied to each item in a pool thread; it should release the GIL for
        most of its work (OpenCV's decoders do) for the threads to overlap.
    items : iterable
        Consumed lazily, at most ``depth`` ahead of the consumer.
    workers : int
        Threads of the pool (>= 1); ``min(workers, depth)`` are started.
    depth : int
        Results computed or being computed ahead of the consumer, at most
        (>= 1; the bound on memory); 0 applies ``function`` in this thread.

    Yields
    ------
    The results, in the order of ``items``. An exception of ``function``
    is raised here when its item's turn comes, after the results before it;
    the items submitted after it are cancelled or awaited, and the pool's
    threads have ended when the exception (or ``KeyboardInterrupt``, or
    ``GeneratorExit`` on an early close) leaves this generator.
    """
    if depth == 0:
        for item in items:
            yield function(item)
        return
    if workers < 1 or depth < 0:
        raise ValueError(f"workers must be >= 1 and depth >= 0, got {workers} and {depth}")
    source = iter(items)
    pending: collections.deque[Future] = collections.deque()
    pool = ThreadPoolExecutor(max_workers=min(workers, depth), thread_name_prefix="frame-decode")
    try:
        for item in source:  # fill the window
            pending.append(pool.submit(function, item))
            if len(pending) == depth:
                break
        while pending:
            result = pending.popleft().result()
            for item in source:  # one in, one out: the window stays at most depth
                pending.append(pool.submit(function, item))
                break
            yield result
    finally:
        for future in pending:
            future.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
