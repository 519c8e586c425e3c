"""Windows per second of :func:`cmax.fit_windows` with 1, 2, ... worker processes.

Fits the same ``--windows`` se3 windows (``indoor_flying`` preset windows of
:func:`benchmarks.synthetic_windows.preset_window`, 0.1665 s each, at
``--width`` x ``--height``, scale unknown) with ``fit_windows(..., jobs=n)`` for
each ``n`` of ``--jobs``, interleaved over ``--repeats`` rounds; windows/s =
windows / median wall time of one call. A call with ``jobs > 1`` includes
starting its workers (forked from the forkserver); the forkserver's own start
(once per process: a new interpreter importing torch) is timed apart, by a
first call on two windows before the rounds. The results are checked equal to
the ``jobs=1`` results (``seconds`` aside). The 1-minute load average is
written next to every round: on a shared machine other work takes cores too.

Writes ``benchmarks/results/speed_batch_fit.md``.

jobs=1 fits in this process, with its BLAS as the environment sets it: run
with ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1`` for the workers' one thread
(two spinning BLAS threads made each fit several times slower on a busy machine).

Usage::

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python -m benchmarks.speed_batch_fit [--windows 6] [--jobs 1,2]
        [--repeats 3] [--width 160 --height 120]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import warnings
from pathlib import Path

import numpy as np

from benchmarks.machine import cpu_name

RESULTS = Path(__file__).resolve().parent / "results"


def windows_of(count: int, width: int, height: int, first_seed: int = 100) -> tuple[list, np.ndarray]:
    """``count`` indoor_flying windows (seeds ``first_seed``...) and their shared K (3, 3)."""
    from benchmarks.synthetic_windows import preset_window

    made = [preset_window("indoor_flying", first_seed + i, width=width, height=height, duration_s=0.1665,
                          texture_size=128) for i in range(count)]
    return [w.events for w in made], made[0].K


def autogroup_enabled() -> bool | None:
    """Whether the kernel shares the cores between sessions (autogroups) rather than processes; None: unknown."""
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return None


def other_busy_sessions() -> int | None:
    """Sessions (autogroups) other than this process's with a running process now, from /proc; None: unknown."""
    try:
        own = Path("/proc/self/autogroup").read_text().split()[0]
    except OSError:
        return None
    busy = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
            group = (entry / "autogroup").read_text().split()[0] if state == "R" else None
        except (OSError, IndexError):
            continue
        if group is not None and group != own:
            busy.add(group)
    return len(busy)


def tree_cpu_seconds() -> float:
    """CPU seconds [s] (user + system) of this process, its children and the children they waited for:
    the workers of :func:`cmax.fit_windows` are children of the forkserver, which waits for them, so
    their time shows in its ``cutime``/``cstime`` once they exit (Linux ``/proc``)."""
    own = os.times()
    total = own.user + own.system + own.children_user + own.children_system
    tick = os.sysconf("SC_CLK_TCK")
    me = str(os.getpid())
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[1] == me:                      # ppid; utime, stime, cutime, cstime follow at 11-14
            total += sum(int(v) for v in fields[11:15]) / tick
    return total


def timed_call(windows: list, K: np.ndarray, jobs: int) -> tuple[float, float, list, list[int]]:
    """Wall time and CPU time of this process tree [s] (:func:`tree_cpu_seconds`) of one
    ``fit_windows(..., jobs=jobs)`` call, its results, and the other busy sessions sampled every
    0.5 s during it (:func:`other_busy_sessions`)."""
    import threading

    from cmax.fitting import fit_windows

    samples: list[int] = []
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.5):
            count = other_busy_sessions()
            if count is not None:
                samples.append(count)

    sampler = threading.Thread(target=sample, daemon=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sampler.start()
        cpu, start = tree_cpu_seconds(), time.perf_counter()
        try:
            results = fit_windows(windows, K, jobs=jobs, progress=False)
        finally:
            seconds = time.perf_counter() - start
            stop.set()
            sampler.join()
        time.sleep(0.3)                            # the forkserver waits for the exited workers
        return seconds, tree_cpu_seconds() - cpu, results, samples


def start_forkserver() -> float:
    """Seconds to start the workers' forkserver and one worker (a new interpreter importing torch and the
    fit: once per process), by a pool of one worker running a trivial task."""
    from concurrent.futures import ProcessPoolExecutor

    from cmax.fitting import batch

    start = time.perf_counter()
    with ProcessPoolExecutor(1, mp_context=batch._context(), initializer=batch._init_worker) as pool:
        pool.submit(abs, -1).result()
    return time.perf_counter() - start


def same_results(a: list, b: list) -> bool:
    """Whether two result lists agree: motion, depth grid and objective of every window, bit for bit."""
    return all(np.array_equal(x.v, y.v) and np.array_equal(x.omega, y.omega)
               and np.array_equal(x.inverse_depth_grid, y.inverse_depth_grid) and x.objective_after == y.objective_after
               for x, y in zip(a, b)) and len(a) == len(b)


def report(calls: dict[int, list[float]], cpu: dict[int, list[float]], loads: list[float],
           sessions: dict[int, list[int]], forkserver_s: float, *, windows: int, events: list[int],
           width: int, height: int, repeats: int, equal: bool, cores: int, autogroup: bool | None) -> str:
    """The markdown of the results from the wall times [s] of the calls of each job count: windows/s
    (``windows`` / median time), the ratio to the fewest jobs and the parallel efficiency (ratio / jobs)."""
    rates = {jobs: windows / statistics.median(seconds) for jobs, seconds in calls.items()}
    base = rates[min(rates)]
    lines = ["# Batched fitting: windows/s of `cmax.fit_windows`", "",
             f"Written by `python -m benchmarks.speed_batch_fit`: {windows} se3 windows of `indoor_flying` "
             f"(0.1665 s, {width}x{height}, {min(events):,}-{max(events):,} events, scale unknown), fitted with "
             f"`fit_windows(..., jobs=n)`; windows/s = {windows} / median wall time of {repeats} interleaved calls "
             "(each call with jobs > 1 starts its workers). Results identical across the job counts: "
             f"{'yes' if equal else 'NO'}. Machine: {platform.machine()} ({cpu_name()}), {cores} cores available, "
             "torch on one "
             f"thread per worker (and one BLAS thread: `one_blas_thread`); this process's OMP_NUM_THREADS="
             f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, OPENBLAS_NUM_THREADS="
             f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')} (jobs=1 fits here); 1-minute load average during "
             f"the rounds {min(loads):.1f}-{max(loads):.1f}.", "",
             f"| jobs | windows/s | s per window | ratio to jobs={min(rates)} | parallel efficiency | "
             "CPU s per window | cores used (CPU / wall) | other busy sessions (mean) |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for jobs, rate in sorted(rates.items()):
        ratio = rate / base
        busy = f"{np.mean(sessions[jobs]):.1f}" if sessions.get(jobs) else "unknown"
        cpu_s = statistics.median(cpu[jobs])
        used = sum(cpu[jobs]) / sum(calls[jobs])
        lines.append(f"| {jobs} | {rate:.3f} | {1 / rate:.2f} | {ratio:.2f} | {ratio / jobs:.2f} | "
                     f"{cpu_s / windows:.2f} | {used:.2f} | {busy} |")
    lines += ["", "Every call [s], in the order run (rounds interleave the job counts):", ""]
    lines += [f"- jobs {jobs}: " + ", ".join(f"{t:.1f}" for t in seconds) for jobs, seconds in sorted(calls.items())]
    lines += ["", "Starting the forkserver and one worker (once per process: a new interpreter importing torch and "
              f"the fit) took {forkserver_s:.1f} s, outside the figures above.", "",
              "Other sessions' work on the machine shows in the load average above and the last column. "
              + ("The kernel's autogroup scheduling is on (`/proc/sys/kernel/sched_autogroup_enabled` = 1): it "
                 "shares the cores between sessions, not processes, so with S other busy sessions on C cores this "
                 "session gets about C / (S + 1) cores whatever its number of workers, and more workers gain only "
                 "where that exceeds one core (here, with 2 cores: no other busy session). The last column is S, "
                 "sampled every 0.5 s during the calls. " if autogroup else "")
              + "CPU s per window (median call's CPU time of this process and its workers / windows) tells the work "
              "done; cores used (all calls' CPU time / their wall time) tells the share of the machine the call got. "
              + "The figures for more jobs are therefore pessimistic, and noisy (the calls above); on an idle "
              "machine N windows on N cores take about the time of one.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--windows", type=int, default=6)
    parser.add_argument("--jobs", default="1,2", help="comma-separated worker counts")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    jobs_list = sorted({int(j) for j in args.jobs.split(",")})
    if args.windows < 1 or args.repeats < 1 or jobs_list[0] < 1:
        parser.error("--windows, --repeats and every --jobs must be positive")
    import torch

    torch.set_num_threads(1)
    windows, K = windows_of(args.windows, args.width, args.height)
    forkserver_s = start_forkserver()
    times: dict[int, list[float]] = {jobs: [] for jobs in jobs_list}
    sessions: dict[int, list[int]] = {jobs: [] for jobs in jobs_list}
    cpu: dict[int, list[float]] = {jobs: [] for jobs in jobs_list}
    loads, reference, equal = [], None, True
    for round_ in range(args.repeats):
        for jobs in jobs_list:
            seconds, cpu_s, results, busy = timed_call(windows, K, jobs)
            times[jobs].append(seconds)
            cpu[jobs].append(cpu_s)
            sessions[jobs] += busy
            loads.append(os.getloadavg()[0])
            reference = results if reference is None else reference
            equal &= same_results(results, reference)
            print(f"round {round_ + 1}, jobs {jobs}: {seconds:.2f} s ({args.windows / seconds:.3f} windows/s), "
                  f"CPU {cpu_s:.2f} s, "
                  f"load {loads[-1]:.1f}, other busy sessions {np.mean(busy) if busy else float('nan'):.1f}",
                  flush=True)
    text = report(times, cpu, loads, sessions, forkserver_s, windows=args.windows, events=[len(w) for w in windows],
                  width=args.width, height=args.height, repeats=args.repeats, equal=equal,
                  cores=len(os.sched_getaffinity(0)), autogroup=autogroup_enabled())
    print(text)
    if not args.no_write:
        from cmax.io.atomic import write_text_atomic

        write_text_atomic(RESULTS / "speed_batch_fit.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
