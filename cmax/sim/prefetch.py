"""Background decoding: an iterator's items made in a thread, a bounded number ahead.

Used by the frame sources of :mod:`cmax.sim.video`: OpenCV releases the GIL
while it decodes a video frame or an image, so a decoding thread overlaps
with the simulation of the frames before.
"""
from __future__ import annotations

import queue
import threading
from typing import Callable, Iterator, TypeVar

import numpy as np

__all__ = ["DEFAULT_PREFETCH", "prefetched"]

T = TypeVar("T")
#: Frames decoded ahead of the consumer by default.
DEFAULT_PREFETCH = 4


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
