"""``cmax.fit`` with numpy's and scipy's OpenBLAS on one thread (the library's scope) against their own default.

The fit's solvers (scipy's L-BFGS-B on a few dozen parameters) call BLAS on tiny vectors; OpenBLAS's pool
spins like torch's and, on a busy machine, a descheduled second thread stalls every call.
:func:`cmax._threads.blas_threads_scope` runs the fit with the BLAS pools on the torch thread count (1 by
default). This script fits the same se3 windows with the scope and with it bypassed (the pools keep
OpenBLAS's default, one thread per core), interleaved, first as the machine is, then with ``--busy``
busy-loop processes; medians of wall seconds per fit. Writes ``benchmarks/results/speed_blas.md``.

Usage::

    python -m benchmarks.speed_blas [--windows 2] [--repeats 3] [--busy 2]
"""
from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import os
import statistics
import time
import warnings
from pathlib import Path

import numpy as np

from benchmarks.speed_threads import _spin  # the same busy loop as the torch thread benchmark

RESULTS = Path(__file__).resolve().parent / "results"


@contextlib.contextmanager
def _bypassed(threads: int):
    """Stands in for ``blas_threads_scope``: leaves the pools as they are."""
    yield threads


def measure(windows, repeats: int) -> dict[str, list[float]]:
    """Wall seconds of ``cmax.fit`` se3 per window, with the scope and bypassed, interleaved."""
    import cmax.fitting.api as api

    scoped = api.blas_threads_scope
    times: dict[str, list[float]] = {"one BLAS thread (scope)": [], "BLAS default (bypassed)": []}
    for _ in range(repeats):
        for w in windows:
            for label, scope in (("one BLAS thread (scope)", scoped), ("BLAS default (bypassed)", _bypassed)):
                api.blas_threads_scope = scope
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        start = time.perf_counter()
                        api.fit(w.events, w.K, speed=float(np.linalg.norm(w.twist[:3])))
                        times[label].append(time.perf_counter() - start)
                finally:
                    api.blas_threads_scope = scoped
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--windows", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--busy", type=int, default=2, help="busy-loop processes in the busy phase")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    from benchmarks.synthetic_windows import make_window
    from cmax._threads import _openblas_pools

    windows = [make_window("indoor_flying", 100 + k, width=160, height=120, focal=115.0) for k in range(args.windows)]
    pools = [int(getter()) for _, getter in _openblas_pools()]
    rows = []
    phases = [("as found", 0)] + ([(f"busy ({args.busy} busy loops)", args.busy)] if args.busy else [])
    for phase, busy in phases:
        stop = multiprocessing.Event()
        spinners = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(busy)]
        for p in spinners:
            p.start()
        try:
            if busy:
                time.sleep(5.0)
            load = os.getloadavg()[0]
            times = measure(windows, args.repeats)
        finally:
            stop.set()
            for p in spinners:
                p.join()
        scope, bypass = (statistics.median(v) for v in times.values())
        rows.append(f"| {phase} | {load:.1f} | {scope:.2f} | {bypass:.2f} | {bypass / scope:.2f}x |")
        print(rows[-1], flush=True)
    lines = ["# cmax.fit with one BLAS thread", "",
             f"Written by `python -m benchmarks.speed_blas --windows {args.windows} --repeats {args.repeats} "
             f"--busy {args.busy}`: se3 fits (`speed=` given) of {args.windows} held-out `indoor_flying` windows at "
             f"160x120, torch on 1 thread in both columns; median wall seconds per fit over {args.repeats} interleaved "
             f"rounds. OpenBLAS pools loaded: {len(pools)}, their default thread counts {pools}; "
             f"{len(os.sched_getaffinity(0))} cores available.", "",
             "| phase | load (1 min) | one BLAS thread (scope) [s] | BLAS default (bypassed) [s] | bypassed / scope |",
             "|---|---:|---:|---:|---:|", *rows, ""]
    if not args.no_write:
        from cmax.io.atomic import write_text_atomic

        write_text_atomic(RESULTS / "speed_blas.md", "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
