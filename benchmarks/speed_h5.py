"""DSEC h5 reading against the h5py floor, in one process (issue 22, deliverable 3).

The file is synthetic, in the layout :class:`cmax.io.H5Writer` writes (Blosc/LZ4
with byte shuffle, 2**18-row chunks, ``ms_to_idx``, ``t_offset``): events at a
constant rate with random pixels and polarities, time increasing by random
steps. Two rows, each timed interleaved with its floor (the floor first on even
repeats, ours first on odd ones; medians of ``--repeats``, one thread; wall and
CPU time):

* **whole file**: floor = open the file with h5py, ``[:]`` of ``events/x, y, t,
  p``, read ``t_offset``, close; ours = :func:`cmax.io.read_h5` (open, the same
  reads, every check of the reader: sensor bounds, polarity encoding, time order,
  time unit, ``t + t_offset`` in place with the overflow check, allocation check
  of the datasets, ``ms_to_idx`` structure).
* **one 50 ms window** (a different window each repeat, the same for both):
  floor = on an open h5py file with ``ms_to_idx`` loaded, the four columns
  sliced at ``ms_to_idx[k0]:ms_to_idx[k1]``; ours = :meth:`H5Reader.window` on an
  open reader (rows located through ``ms_to_idx`` alone, one row of margin each
  side to verify the two index entries used, then the exact µs cut).

Usage::

    python -m benchmarks.speed_h5 [--events 5000000 50000000] [--repeats 9] [--keep FOLDER]

Writes ``benchmarks/results/speed_h5.md``.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (registers Blosc for the floor's reads)
import numpy as np

from cmax.events import Events
from cmax.io import H5Reader, H5Writer, read_h5
from cmax.io.atomic import write_text_atomic

RESULTS = Path(__file__).resolve().parent / "results"
WIDTH, HEIGHT = 640, 480
RATE_HZ = 20_000_000  # events per second: 50 ms hold 1 M events


def make_file(path: Path, count: int, seed: int = 0) -> Path:
    """A DSEC-layout file of ``count`` events at :data:`RATE_HZ`, written in 1 M-event pieces."""
    rng = np.random.default_rng(seed)
    mean_step = 1e6 / RATE_HZ
    t_last = 1_600_000_000_000_000  # an absolute epoch time in µs, as DSEC's t_offset
    piece = 1 << 20
    with H5Writer(path, WIDTH, HEIGHT, overwrite=True, source="benchmarks.speed_h5") as writer:
        for start in range(0, count, piece):
            n = min(piece, count - start)
            steps = rng.poisson(mean_step, n).astype(np.int64)
            t = t_last + np.cumsum(steps)
            t_last = int(t[-1])
            writer.append(Events._trusted(
                rng.integers(0, WIDTH, n).astype(np.uint16), rng.integers(0, HEIGHT, n).astype(np.uint16),
                t, rng.integers(0, 2, n).astype(np.int8), WIDTH, HEIGHT,
            ))
    return path


def floor_whole(path: Path) -> int:
    with h5py.File(path, "r") as file:
        columns = [file["events"][name][:] for name in "xytp"]
        int(file["t_offset"][()])
    return len(columns[2])


def ours_whole(path: Path) -> int:
    return len(read_h5(path))


def time_pair(floor, ours, arguments: list, repeats: int) -> dict[str, list[float]]:
    """Wall and CPU seconds of ``floor(a)`` and ``ours(a)`` for each ``a``, interleaved; the floor goes
    first on even repeats and second on odd ones (the second reader of a window may find chunks in
    HDF5's chunk cache, which the two open files share). CPU time (``time.process_time``) leaves out the time the process waits for a core,
    which dominates wall time on a shared, overloaded machine."""
    times: dict[str, list[float]] = {"floor_wall": [], "ours_wall": [], "floor_cpu": [], "ours_cpu": []}
    for repeat, argument in enumerate(arguments[:repeats]):
        pair = ((floor, "floor"), (ours, "ours"))
        for function, name in pair if repeat % 2 == 0 else pair[::-1]:
            wall, cpu = time.perf_counter(), time.process_time()
            function(argument)
            times[name + "_cpu"].append(time.process_time() - cpu)
            times[name + "_wall"].append(time.perf_counter() - wall)
    return times


def run(count: int, repeats: int, keep: Path | None) -> str:
    folder = None if keep is not None else tempfile.mkdtemp(prefix="speed_h5_")
    path = keep or Path(folder) / "synthetic.h5"
    if not path.exists():
        make_file(path, count)
    size_mb = path.stat().st_size / 1e6
    # one untimed warm-up of each (page cache, imports)
    floor_whole(path), ours_whole(path)
    whole = time_pair(floor_whole, ours_whole, [path] * repeats, repeats)

    reader = H5Reader(path)
    file = h5py.File(path, "r")
    index = file["ms_to_idx"][:].astype(np.int64)
    columns = [file["events"][name] for name in "xytp"]
    span_ms = len(index) - 2
    rng = np.random.default_rng(1)
    starts_ms = rng.integers(0, max(span_ms - 50, 1), repeats + 1)
    t_offset = reader.t_offset_us

    def floor_window(k0: int) -> int:
        a, b = int(index[k0]), int(index[min(k0 + 50, len(index) - 1)])
        return len([column[a:b] for column in columns][2])

    def ours_window(k0: int) -> int:
        return len(reader.window(t_offset + 1000 * int(k0), t_offset + 1000 * (int(k0) + 50)))

    floor_window(int(starts_ms[-1])), ours_window(int(starts_ms[-1]))
    window = time_pair(floor_window, ours_window, [int(k) for k in starts_ms[:-1]], repeats)
    events_per_window = int(np.median([index[min(k + 50, len(index) - 1)] - index[k] for k in starts_ms[:-1]]))
    reader.close()
    file.close()
    if keep is None:
        path.unlink()
        os.rmdir(folder)

    def row(what: str, times: dict[str, list[float]], clock: str, target: float) -> str:
        floor, ours = times["floor_" + clock], times["ours_" + clock]
        f, o = statistics.median(floor), statistics.median(ours)
        ratios = [b / a for a, b in zip(floor, ours)]
        verdict = "met" if o / f <= target else "NOT met"
        return (f"| {what} | {clock} | {1e3 * f:.1f} ms | {1e3 * o:.1f} ms | {o / f:.2f}× "
                f"| {min(ours) / min(floor):.2f}× | {min(ratios):.2f}–{max(ratios):.2f} | ≤ {target}× | {verdict} |")

    lines = [
        f"## {count / 1e6:g} M events",
        "",
        f"Synthetic DSEC-layout file: {count:,} events ({size_mb:.0f} MB on disk, Blosc/LZ4 + shuffle, "
        f"{WIDTH}x{HEIGHT}, {RATE_HZ / 1e6:.0f} M ev/s so a 50 ms window holds ~{events_per_window:,} events). "
        f"Medians of {repeats} interleaved repeats (order alternating), one process, "
        f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; load average at the end "
        f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores ({platform.processor() or platform.machine()}). "
        "Produced by `python -m benchmarks.speed_h5`; how each row is measured is in its docstring.",
        "",
        "| read | clock | h5py floor (median) | cmax (median) | ratio of medians | ratio of minimums "
        "| per-repeat ratios | target | (medians) |",
        "|---|---|---|---|---|---|---|---|---|",
        row("whole file (read_h5)", whole, "wall", 1.3),
        row("whole file (read_h5)", whole, "cpu", 1.3),
        row("one 50 ms window (H5Reader.window)", window, "wall", 1.5),
        row("one 50 ms window (H5Reader.window)", window, "cpu", 1.5),
        "",
        "wall: `time.perf_counter`; cpu: `time.process_time` of the process (all its threads), which leaves "
        "out the time spent waiting for a core when the machine is shared. The ratio of minimums is the "
        "least disturbed pair of figures when other work shares the machine.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--events", type=int, nargs="+", default=[5_000_000, 50_000_000],
                        help="events in the synthetic file (one section per count)")
    parser.add_argument("--repeats", type=int, default=9, help="interleaved repeats (>= 5)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="folder where the synthetic files are reused (or created and kept)")
    parser.add_argument("--output", type=Path, default=RESULTS / "speed_h5.md")
    args = parser.parse_args(argv)
    if args.repeats < 5:
        parser.error("--repeats must be >= 5")
    sections = []
    for count in args.events:
        keep = None if args.keep is None else args.keep / f"speed_h5_{count}.h5"
        sections.append(run(count, args.repeats, keep))
    text = "\n".join(["# DSEC h5 reading against the h5py floor", ""] + sections)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(args.output, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
