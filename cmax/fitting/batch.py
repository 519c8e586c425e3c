"""``cmax.fit_windows``: many independent windows fitted in one call, in parallel over the cores.

Each window is one :func:`cmax.fit` in a worker process that runs torch on one thread, so that
``jobs`` workers can keep ``jobs`` cores busy. The results are those of :func:`cmax.fit` on each
window, bit for bit (the fit is deterministic: its subsampling is seeded and its torch runs on one
thread either way; ``tests/test_fit_batch.py``), in the order of the input. On Linux with autogroup
scheduling the kernel shares the cores between sessions, not processes: the workers of one call then
share their session's slice, and more workers gain only where that slice exceeds one core
(``benchmarks/results/speed_batch_fit.md``).

Design choices:

* **Processes, not threads.** The fit spends much of its time in Python (the scipy solver's loop,
  the stage logic), which threads would serialise on the GIL. Workers start with ``forkserver``
  where the platform has it (``spawn`` elsewhere), never ``fork``: a forked child of a process whose
  torch (or CUDA) is already initialised can deadlock. The forkserver preloads the fit's modules,
  so each worker forks with torch already imported. Like every ``spawn``/``forkserver`` pool, a
  script that calls :func:`fit_windows` with ``jobs > 1`` must guard its top level with
  ``if __name__ == "__main__":``.
* **One thread per worker.** Each worker sets torch to one intra-op and one inter-op thread,
  ``CMAX_TORCH_THREADS=1`` (:mod:`cmax._threads`) and its BLAS to one thread
  (:func:`one_blas_thread`), so ``jobs`` workers use ``jobs`` cores and none falls off the
  thread-pool cliff of a busy machine.
* **A failed window stops the call.** An exception in a window's fit cancels the windows not yet
  started and raises :class:`WindowFitError` naming the window's index (the original exception is
  its ``__cause__``). A made-up ``FitResult(success=False)`` would need every field of a fit that
  never happened; ``success=False`` keeps its meaning: a fit that ran and ended on a bound or worse
  than its start. A worker that dies (killed, out of memory) raises it too, for a window it held,
  with ``BrokenProcessPool`` as the cause.
* **Warnings reach the caller.** A worker's warnings (:class:`~cmax.fitting.LowParallaxWarning` and
  the like) are recorded and re-issued in the calling process once all windows are done, in window
  order, each prefixed with ``window i:``; ``jobs=1`` does the same, so both give the same warnings.
* **Ctrl-C.** Workers ignore SIGINT; the calling process gets the ``KeyboardInterrupt``, terminates
  its workers, waits for them and re-raises: no worker outlives the call.
* **CPU only.** :func:`cmax.fit` has no device setting: its torch tensors are float64 on the CPU and
  its default solver (scipy L-BFGS-B) crosses back to numpy at every evaluation of windows of at most
  ``max_events`` events, so a GPU would mostly wait on those round trips. The batched path therefore
  runs on the CPU cores whether or not CUDA is present; workers never initialise CUDA.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
from contextlib import closing
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Sequence

import numpy as np
from tqdm.auto import tqdm

from cmax._signals import sigint_deferred
from cmax._threads import available_cores, set_blas_threads
from cmax._workers import die_with_parent, recorded, reissue, start_forkserver
from cmax.camera import Camera, camera_and_intrinsics, pinhole_events
from cmax.events import Events
from cmax.fitting.api import (MODELS, FitResult, _check_inputs, _check_speed, _known_omega, _pose_twist, _settings,
                              fit)
from cmax.fitting.solvers import make_solver

__all__ = ["WindowFitError", "FitTask", "fit_windows", "check_jobs", "check_options", "run_tasks", "one_blas_thread"]

#: Keywords of :func:`cmax.fit` that :func:`fit_windows` passes on (besides the FitSettings fields).
_FIT_KEYWORDS = frozenset({"speed", "pose", "omega", "depth_grid", "solver", "init", "settings", "num_threads",
                           "quality"})
#: Modules the forkserver imports once, so that each worker forks with them loaded: the fit, and what
#: its first call would import lazily (torch's ``broadcast_shapes`` pulls in sympy through
#: ``symbolic_shapes``; the scipy solvers and filters), which every worker's first window paid
#: otherwise; last :mod:`cmax.fitting._warm`, one small fit that loads the compiled kernels from numba's
#: cache in the server. A module missing in some version is skipped.
_PRELOAD = ["cmax.fitting.batch", "cmax.fitting.polish", "cmax.contrast", "scipy.optimize", "scipy.ndimage",
            "torch.fx.experimental.symbolic_shapes", "cmax.fitting._warm"]
#: Windows submitted per worker ahead of the results (bounds the events held in flight).
_AHEAD = 2


class WindowFitError(RuntimeError):
    """The fit of one window of :func:`fit_windows` raised; ``index`` is its position in the input,
    ``message`` names it and the original exception, which is ``__cause__``."""

    def __init__(self, index: int, message: str) -> None:
        super().__init__(message)
        self.index = index


@dataclass(frozen=True, eq=False)
class FitTask:
    """One window's fit: ``cmax.fit(events, K, model, **options)``; ``index`` orders the results."""

    index: int
    events: Events
    K: "np.ndarray | Camera"
    model: str
    options: dict = field(default_factory=dict)


def check_jobs(jobs: object) -> int:
    """Worker processes for ``jobs``: None -> the cores this process may run on
    (:func:`cmax._threads.available_cores`); else a positive integer, returned as is."""
    if jobs is None:
        return available_cores()
    if not isinstance(jobs, (int, np.integer)) or isinstance(jobs, bool) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer or None (all cores), got {jobs!r}")
    return int(jobs)


def fit_windows(windows: Sequence[Events], K: object, model: str = "se3", *, jobs: int | None = None,
                progress: bool = True, **fit_options) -> list[FitResult]:
    """Fit many independent windows, each as :func:`cmax.fit` would, in parallel over the cores.

    Parameters
    ----------
    windows : sequence of Events
        The windows (each at least 10 events over a non-zero time; sensors may differ).
    K : array_like (3, 3) or cmax.Camera
        Pinhole intrinsics [px], shared by every window; or the :class:`cmax.Camera` of their sensor (its
        distortion undone first, as :func:`cmax.fit` does).
    model : {"se3", "rotation", "flow"}
    jobs : int or None, keyword-only
        Worker processes, each running torch on one thread; None: the cores this process may run on
        (``os.sched_getaffinity``). 1 (or a single window) fits in this process, one after another.
        Never more workers than windows.
    progress : bool, keyword-only
        A progress bar over the windows (tqdm).
    **fit_options
        Keywords of :func:`cmax.fit` applied to every window (``speed``, ``pose``, ``omega``,
        ``settings``, ``solver``, ``depth_grid``, ``quality``, ``init``, or :class:`FitSettings`
        fields). ``num_threads`` other than 1 needs ``jobs=1``.

    Returns
    -------
    list of FitResult
        One per window, in the input's order; equal field for field to ``cmax.fit(window, K, model,
        **fit_options)`` (``seconds`` aside).

    Raises
    ------
    TypeError, ValueError
        Not a sequence of ``Events`` (the message names the first bad window), a bad ``K``, model,
        ``jobs`` or option: checked before any fit starts.
    WindowFitError
        A window's fit raised (``index``: which one; the original exception is ``__cause__``); the
        windows not yet started are cancelled.

    Warns
    -----
    The warnings of each window's fit, re-issued in window order once all are done, each message
    prefixed with ``window i:``.

    Examples
    --------
    Two windows of 300 points moving at (40, -20) and (-30, 10) px/s, fitted in this process (``jobs=2``
    would fit them in two worker processes, with the same results):

    >>> import numpy as np
    >>> import cmax
    >>> rng = np.random.default_rng(0)
    >>> K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    >>> def window(fx, fy):
    ...     x0, y0 = rng.uniform(8, 50, 300), rng.uniform(8, 40, 300)
    ...     t_s = np.sort(rng.uniform(0, 0.1, 6000)); point = rng.integers(0, 300, 6000)
    ...     return cmax.Events(np.rint(x0[point] + fx * t_s), np.rint(y0[point] + fy * t_s),
    ...                        np.rint(t_s * 1e6).astype(np.int64), np.ones(6000), width=64, height=48)
    >>> results = cmax.fit_windows([window(40, -20), window(-30, 10)], K, model="flow", jobs=1, progress=False)
    >>> [bool(np.allclose(r.flow, truth, atol=2.0)) for r, truth in zip(results, [(40, -20), (-30, 10)])]
    [True, True]
    """
    if isinstance(windows, Events) or not isinstance(windows, Sequence):
        raise TypeError(f"windows must be a sequence of cmax.Events (one window: cmax.fit), got "
                        f"{type(windows).__name__}")
    workers = check_jobs(jobs)
    camera, K = camera_and_intrinsics(K)
    check_options(model, fit_options, workers)
    windows = list(windows)
    for i, events in enumerate(windows):
        try:
            _check_inputs(events if camera is None else pinhole_events(events, camera)[0], K, model)
        except (TypeError, ValueError) as error:
            raise type(error)(f"windows[{i}]: {error}") from None
    fitted_K = K if camera is None else camera          # each fit undoes the lens itself, as cmax.fit does
    tasks = (FitTask(i, events, fitted_K, model, dict(fit_options)) for i, events in enumerate(windows))
    return run_tasks(tasks, min(workers, max(1, len(windows))), total=len(windows), progress=progress)


def check_options(model: str, options: dict, workers: int) -> None:
    """Refuse bad keywords of :func:`cmax.fit` shared by every window (unknown names, the settings,
    ``speed``/``pose``/``omega``, the solver, ``num_threads`` with ``workers > 1``) before any fit starts."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    settings_fields = set(options) - _FIT_KEYWORDS
    _settings(options.get("settings"), {k: options[k] for k in settings_fields}, model)
    speed, pose, omega = options.get("speed"), options.get("pose"), options.get("omega")
    _check_speed(speed)
    if (speed is not None or pose is not None or omega is not None) and model != "se3":
        raise ValueError(f"speed, pose and omega apply to model='se3', not {model!r}")
    if omega is not None:
        _known_omega(omega, pose)
    if pose is not None:
        _pose_twist(pose, 1.0)          # its shape and finiteness (the window's duration scales a (4, 4) pose)
    make_solver(options.get("solver", "scipy"))
    if workers > 1 and options.get("num_threads", 1) != 1:
        raise ValueError(f"num_threads={options['num_threads']!r} needs jobs=1: every worker runs torch on one "
                         "thread")


def run_tasks(tasks: Iterable[FitTask], jobs: int, *, total: int | None = None, progress: bool = False,
              desc: str = "windows", on_result=None) -> list[FitResult]:
    """Run fit tasks (an iterable, consumed lazily) on ``jobs`` workers (1: in this process).

    The core of :func:`fit_windows` and of ``fit_sequence(jobs=)``; the tasks are trusted (checked by
    the caller), ``total`` only sizes the progress bar. ``on_result(index, result, caught)``, when given, is
    called in this process as each fit finishes (``caught``: its warnings, ``((category, message), ...)``) and
    returns the result to keep in its place (e.g. one whose large maps were written to a file); the warnings are
    then the caller's to issue. Returns the results sorted by ``FitTask.index``; raises :class:`WindowFitError`
    on the first task whose fit raised; without ``on_result``, re-issues the fits' warnings in index order.
    """
    done: dict[int, tuple[FitResult, tuple]] = {}
    keep = (lambda index, outcome: outcome) if on_result is None else \
        (lambda index, outcome: (on_result(index, *outcome), outcome[1]))
    with tqdm(total=total, desc=desc, unit="window", disable=not progress) as bar:
        if jobs == 1:
            for task in tasks:
                done[task.index] = keep(task.index, _guarded(task))
                bar.update(1)
        else:
            with closing(_in_workers(tasks, jobs)) as outcomes:
                for index, outcome in outcomes:
                    done[index] = keep(index, outcome)
                    bar.update(1)
    for index in sorted(done) if on_result is None else ():
        reissue(f"window {index}", done[index][1], stacklevel=3)
    return [done[index][0] for index in sorted(done)]


def _fit_task(task: FitTask) -> tuple[int, FitResult, tuple]:
    """One task's fit with its warnings recorded: ``(index, result, ((category, message), ...))``."""
    result, caught = recorded(lambda: fit(task.events, task.K, task.model, **task.options))
    return task.index, result, caught


def _failure(task_index: int, events: Events | None, error: BaseException) -> WindowFitError:
    span = "" if events is None or len(events) == 0 else f" ({int(events.t[0])}-{int(events.t[-1])} us)"
    return WindowFitError(task_index, f"window {task_index}{span}: {type(error).__name__}: {error}")


def _guarded(task: FitTask) -> tuple[FitResult, tuple]:
    """:func:`_fit_task` in this process, an exception turned into :class:`WindowFitError`."""
    try:
        _, result, caught = _fit_task(task)
    except Exception as error:
        raise _failure(task.index, task.events, error) from error
    return result, caught


def _init_worker(main_pid: int) -> None:
    """Each worker: killed when the calling process ``main_pid`` dies (:func:`cmax._workers.die_with_parent`: a
    SIGKILL of ``cmax fit --jobs N`` left its workers running, about 1 GB), torch on one thread (intra- and
    inter-op), ``CMAX_TORCH_THREADS=1`` for :mod:`cmax._threads`, BLAS on one thread (:func:`one_blas_thread`),
    SIGINT left to the calling process (which terminates the workers)."""
    die_with_parent(main_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ["CMAX_TORCH_THREADS"] = "1"
    import torch

    torch.set_num_threads(1)
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # pragma: no cover - already set (a forkserver preloaded it)
        pass
    one_blas_thread()


def one_blas_thread() -> int:
    """Set the BLAS libraries loaded in this process (numpy's and scipy's) to one thread; returns how
    many were set.

    OpenBLAS threads spin while they wait for work, like torch's OpenMP pool: on a busy machine a
    worker whose BLAS keeps two threads fits its windows several times slower than with one, and
    ``jobs`` workers would ask for ``2 jobs`` cores. With ``threadpoolctl`` installed it sets every
    BLAS and OpenMP library it knows; otherwise the OpenBLAS builds mapped into this process (Linux)
    are set through their own setter (:func:`cmax._threads.set_blas_threads`).
    """
    try:
        import threadpoolctl
    except ImportError:
        threadpoolctl = None
    if threadpoolctl is not None:
        threadpoolctl.threadpool_limits(limits=1)
        return len(threadpoolctl.threadpool_info())
    return len(set_blas_threads(1))


def _context() -> multiprocessing.context.BaseContext:
    """``forkserver`` (preloading the fit) where the platform has it, else ``spawn``; never ``fork``."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(_PRELOAD)
        start_forkserver(context)       # Ctrl-C while it imports: no traceback of the server's
        return context
    return multiprocessing.get_context("spawn")  # pragma: no cover - not on Linux


def _in_workers(tasks: Iterable[FitTask], workers: int) -> Iterator[tuple[int, tuple[FitResult, tuple]]]:
    """``(index, (result, warnings))`` of each task as the workers finish them, at most ``_AHEAD``
    tasks per worker in flight; on any exception or interrupt the workers are terminated first."""
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=_context(), initializer=_init_worker,
                               initargs=(os.getpid(),))
    pending: dict[Future, FitTask] = {}
    source = iter(tasks)
    try:
        while True:
            for task in source:
                with sigint_deferred():   # a worker the pool starts here is recorded (and stopped below)
                    future = pool.submit(_fit_task, task)
                pending[future] = task
                if len(pending) >= _AHEAD * workers:
                    break
            if not pending:
                break
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in sorted(finished, key=lambda f: pending[f].index):
                task = pending.pop(future)
                try:
                    index, result, caught = future.result()
                except Exception as error:
                    raise _failure(task.index, task.events, error) from error
                yield index, (result, caught)
    except BaseException:
        _terminate(pool)
        raise
    pool.shutdown(wait=True)


def _terminate(pool: ProcessPoolExecutor) -> None:
    """Stop ``pool`` now: cancel what has not started, terminate (then kill) the workers and wait for them,
    then close this process's end of the results pipe so that nothing waits on a result that will never come."""
    processes = list((getattr(pool, "_processes", None) or {}).values())   # the executor keeps no public list
    result_queue = getattr(pool, "_result_queue", None)
    call_queue = getattr(pool, "_call_queue", None)
    if call_queue is not None:
        # Its feeder thread may be blocked writing a window into a pipe that no worker will read again; the
        # executor's clean-up joins that thread without a timeout (the hang of CPython gh-94777, which 3.11
        # avoids only once it finds a worker dead). Nothing in the queue matters any more: do not wait for it.
        call_queue.cancel_join_thread()
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=5)
        if process.is_alive():  # pragma: no cover - a worker stuck in uninterruptible I/O
            process.kill()
            process.join(timeout=5)
    writer = getattr(result_queue, "_writer", None)
    if writer is not None:
        # A worker terminated while it wrote its result (a FitResult spans several pipe buffers) leaves part of a
        # message in the results pipe: the executor's manager thread then waits in recv() for the rest, which no
        # one will write, and this process's exit joins that thread forever (it held a Ctrl-C'd run open, rarely,
        # under load). This process holds the pipe's write end too; with the workers gone, closing it gives the
        # reader end-of-file, and the manager thread counts the pool broken and ends.
        writer.close()
