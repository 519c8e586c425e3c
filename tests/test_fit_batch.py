"""cmax.fit_windows and fit_sequence(jobs=): parallel fits equal serial ones bit for bit, in order, with
their warnings; a failing window is named; bad input is refused up front; no worker outlives the call."""
from __future__ import annotations

import dataclasses
import multiprocessing
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

import cmax
from cmax.events import Events
from cmax.fitting import LowMotionWarning, WindowFitError, fit_windows
from cmax.fitting import batch

ROOT = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT, F = 120, 90, 90.0
K = np.array([[F, 0, (WIDTH - 1) / 2], [0, F, (HEIGHT - 1) / 2], [0, 0, 1]])


def translating_edges(flow_px_s: tuple[float, float], seed: int, duration_s: float = 0.1, points: int = 300,
                      per_point: int = 15, t0_us: int = 0) -> Events:
    """Events of ``points`` random dots that all move with one constant flow [px/s]: each dot fires
    ``per_point`` ON events at uniform times over ``duration_s``, at its position rounded to a pixel."""
    rng = np.random.default_rng(seed)
    start = rng.uniform([10, 10], [WIDTH - 10, HEIGHT - 10], (points, 2))
    t = np.sort(rng.uniform(0, duration_s, points * per_point))
    dot = rng.integers(0, points, points * per_point)
    x = np.rint(start[dot, 0] + flow_px_s[0] * t).astype(int)
    y = np.rint(start[dot, 1] + flow_px_s[1] * t).astype(int)
    inside = (x >= 0) & (x < WIDTH) & (y >= 0) & (y < HEIGHT)
    return Events(x[inside], y[inside], t0_us + np.rint(t[inside] * 1e6).astype(np.int64),
                  np.ones(int(inside.sum()), int), WIDTH, HEIGHT)


def approaching_plane(seed: int) -> Events:
    """ON events of dots on a wall 2 m ahead the camera flies toward at 4 m/s (80x60, f = 60 px)."""
    rng = np.random.default_rng(seed)
    width, height, duration, points, per_point = 80, 60, 0.2, 200, 20
    cx, cy = (width - 1) / 2, (height - 1) / 2
    dots = rng.uniform([5, 5], [width - 5, height - 5], (points, 2))
    t = np.sort(rng.uniform(0, duration, (points, per_point)), axis=1)
    scale = 2.0 / (2.0 - 4.0 * (t - duration / 2))
    x, y = cx + (dots[:, :1] - cx) * scale, cy + (dots[:, 1:] - cy) * scale
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    order = np.argsort(t[inside], kind="stable")
    return Events(np.rint(x[inside][order]).astype(int), np.rint(y[inside][order]).astype(int),
                  np.rint(t[inside][order] * 1e6).astype(np.int64), np.ones(int(inside.sum()), int), width, height)


K_PLANE = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])


def assert_same(a: object, b: object, where: str = "result") -> None:
    """Field for field equality of two results (arrays bit for bit, NaN equal to NaN), ``seconds`` aside."""
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            if f.name != "seconds":
                assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, (tuple, list)):
        assert isinstance(b, (tuple, list)) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape, where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    elif isinstance(a, float):
        assert isinstance(b, float) and (a == b or (np.isnan(a) and np.isnan(b))), (where, a, b)
    else:
        assert a == b, (where, a, b)


def test_parallel_se3_fits_equal_cmax_fit_bit_for_bit_in_input_order():
    windows = [approaching_plane(seed) for seed in (0, 1, 2)]
    expected = [cmax.fit(w, K_PLANE, speed=4.0, depth_grid=(3, 4)) for w in windows]
    got = fit_windows(windows, K_PLANE, speed=4.0, depth_grid=(3, 4), jobs=2, progress=False)
    assert len(got) == 3
    assert not np.array_equal(expected[0].depth, expected[1].depth)     # the windows differ: order is tested
    for i, (a, b) in enumerate(zip(got, expected)):
        assert_same(a, b, f"window {i}")


def test_in_process_flow_fits_equal_cmax_fit():
    windows = [translating_edges((300.0, -100.0), seed) for seed in range(3)]
    expected = [cmax.fit(w, K, "flow") for w in windows]
    for i, (a, b) in enumerate(zip(fit_windows(windows, K, "flow", jobs=1, progress=False), expected)):
        assert_same(a, b, f"window {i}")


def test_warnings_come_back_in_window_order_named_by_window():
    """A window whose flow moves the events by half a pixel warns (LowMotionWarning); the fast ones do
    not. The workers' warnings reach the caller, in window order, each with its window's index."""
    flows = [(300.0, 0.0), (5.0, 0.0), (0.0, 250.0), (0.0, 4.0)]
    windows = [translating_edges(flow, seed) for seed, flow in enumerate(flows)]
    alone = []
    for w in windows:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cmax.fit(w, K, "flow")
        alone.append([str(c.message) for c in caught if c.category is LowMotionWarning])
    assert [bool(m) for m in alone] == [False, True, False, True]
    for jobs in (1, 2):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fit_windows(windows, K, "flow", jobs=jobs, progress=False)
        messages = [str(c.message) for c in caught if c.category is LowMotionWarning]
        assert messages == [f"window 1: {alone[1][0]}", f"window 3: {alone[3][0]}"], jobs


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_failing_window_is_named_and_keeps_its_cause(jobs):
    """A 60x45 window is too small for a 60x80 depth grid (the 120x90 ones are not): cmax.fit raises inside
    the fit, in the worker."""
    tiny = Events(np.arange(20) % 10, np.arange(20) % 7, np.arange(20) * 100, np.ones(20), 60, 45)
    windows = [translating_edges((300.0, 0.0), 0), tiny, translating_edges((300.0, 0.0), 1)]
    with pytest.raises(ValueError, match="finer than the image"):
        cmax.fit(tiny, K, "flow", depth_grid=(60, 80))
    with pytest.raises(WindowFitError, match=r"window 1 \(0-1900 us\): ValueError: .*finer than the image") as info:
        fit_windows(windows, K, "flow", jobs=jobs, progress=False, depth_grid=(60, 80))
    assert info.value.index == 1 and isinstance(info.value.__cause__, ValueError)
    assert multiprocessing.active_children() == []


@pytest.mark.parametrize("call, error, match", [
    (lambda w: fit_windows(w[0], K), TypeError, "sequence of cmax.Events"),
    (lambda w: fit_windows([w[0], "x"], K), TypeError, r"windows\[1\]: events must be cmax.Events"),
    (lambda w: fit_windows([w[0], w[0][:5]], K), ValueError, r"windows\[1\]: .*at least 10"),
    (lambda w: fit_windows(w, K, jobs=0), ValueError, "jobs must be a positive integer"),
    (lambda w: fit_windows(w, K, jobs=True), ValueError, "jobs must be a positive integer"),
    (lambda w: fit_windows(w, K, "affine"), ValueError, "model must be one of"),
    (lambda w: fit_windows(w, np.eye(2)), ValueError, "3x3"),
    (lambda w: fit_windows(w, K, speed=-1.0), ValueError, "speed must be a positive"),
    (lambda w: fit_windows(w, K, "flow", speed=1.0), ValueError, "se3"),
    (lambda w: fit_windows(w, K, pose=np.zeros(5)), ValueError, "pose must be"),
    (lambda w: fit_windows(w, K, omega=[0, 0]), ValueError, "omega must be an angular velocity"),
    (lambda w: fit_windows(w, K, solver="newton"), ValueError, "solver"),
    (lambda w: fit_windows(w, K, bogus=1), TypeError, "bogus"),
    (lambda w: fit_windows(w, K, settings=cmax.FitSettings(), sigma=2.0), TypeError, "not both"),
    (lambda w: fit_windows(w, K, jobs=2, num_threads=2), ValueError, "num_threads=2 needs jobs=1"),
])
def test_bad_input_is_refused_before_any_fit(call, error, match, monkeypatch):
    def no_fit(*args, **kwargs):
        raise AssertionError("a fit started")

    monkeypatch.setattr(batch, "fit", no_fit)
    with pytest.raises(error, match=match):
        call([translating_edges((300.0, 0.0), 0), translating_edges((300.0, 0.0), 1)])


def _thread_counts() -> dict[str, int]:
    """Threads of every BLAS and OpenMP library loaded in this process (threadpoolctl)."""
    from threadpoolctl import threadpool_info

    return {info["filepath"]: info["num_threads"] for info in threadpool_info()}


def _torch_threads() -> tuple[int, int]:
    import torch

    return torch.get_num_threads(), torch.get_num_interop_threads()


def test_every_worker_runs_torch_and_blas_on_one_thread():
    pytest.importorskip("threadpoolctl")
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=batch._context(), initializer=batch._init_worker) as pool:
        assert pool.submit(_torch_threads).result() == (1, 1)
        counts = pool.submit(_thread_counts).result()
    assert any("openblas" in path for path in counts) and set(counts.values()) == {1}, counts


def test_one_blas_thread_without_threadpoolctl_sets_openblas_itself(tmp_path):
    """The fallback (no threadpoolctl): numpy's and scipy's OpenBLAS set through their own setters,
    checked in a fresh interpreter through threadpoolctl's own reading."""
    pytest.importorskip("threadpoolctl")
    code = textwrap.dedent("""
        import sys
        import numpy, scipy.linalg
        sys.modules["threadpoolctl"] = None          # import threadpoolctl fails inside the fallback
        from cmax.fitting.batch import one_blas_thread
        count = one_blas_thread()
        del sys.modules["threadpoolctl"]
        from threadpoolctl import threadpool_info
        print(count, sorted({i["num_threads"] for i in threadpool_info() if i["internal_api"] == "openblas"}))
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True).stdout
    count, threads = out.split(" ", 1)
    assert int(count) >= 1 and threads.strip() == "[1]", out


def test_jobs_none_means_every_available_core():
    assert batch.check_jobs(None) == len(os.sched_getaffinity(0))
    assert batch.check_jobs(3) == 3


def test_an_exception_in_the_caller_terminates_the_workers(monkeypatch):
    """KeyboardInterrupt in the calling process (here from the progress bar, after the first window)
    terminates the workers before it propagates: none is left running."""
    class Interrupting:
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def update(self, n):
            raise KeyboardInterrupt

    monkeypatch.setattr(batch, "tqdm", Interrupting)
    windows = [approaching_plane(seed) for seed in range(4)]
    with pytest.raises(KeyboardInterrupt):
        fit_windows(windows, K_PLANE, speed=4.0, depth_grid=(3, 4), jobs=2)
    assert multiprocessing.active_children() == []


def _descendants(pid: int) -> set[int]:
    """Process ids of the living (not zombie) descendants of ``pid``, from /proc."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat.rsplit(")", 1)[1].split()
            if fields[0] != "Z":
                parents[int(entry.name)] = int(fields[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def test_terminating_the_pool_frees_a_reader_left_with_part_of_a_result():
    """A worker terminated while it wrote its result leaves part of a message in the results pipe; the executor's
    manager thread then waits for the rest, and the interpreter's exit joins that thread forever (a Ctrl-C'd run
    that did not exit). Here the partial message is written by hand (a header announcing 1000 bytes, none
    following): after ``_terminate`` the manager thread ends."""
    import struct
    from concurrent.futures import ProcessPoolExecutor

    from cmax.fitting.batch import _terminate

    pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("forkserver"))
    assert pool.submit(abs, -3).result(timeout=60) == 3          # the manager thread and the worker run
    manager, writer = pool._executor_manager_thread, pool._result_queue._writer
    os.write(writer.fileno(), struct.pack("!i", 1000))           # what a worker killed mid-write leaves
    time.sleep(0.5)                                              # the manager reads the header, waits for the rest
    _terminate(pool)
    manager.join(timeout=30)
    stuck = manager.is_alive()
    if stuck:                                                    # free it, or this test process could not exit
        writer.close()
        manager.join(timeout=30)
    assert not stuck


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_ctrl_c_leaves_no_orphan_process(tmp_path):
    """SIGINT to the whole process group (a terminal's Ctrl-C) while workers fit: the call raises
    KeyboardInterrupt and every process it started is gone."""
    script = tmp_path / "interrupted.py"
    script.write_text(textwrap.dedent(f"""
        import faulthandler
        import signal
        import sys
        # a shell that starts the test run in the background leaves SIGINT ignored, and so in this child
        signal.signal(signal.SIGINT, signal.default_int_handler)
        faulthandler.register(signal.SIGUSR1, all_threads=True)   # the test's dump of a process that does not exit
        sys.path[:0] = [{str(ROOT)!r}, {str(Path(__file__).parent)!r}]
        from test_fit_batch import K_PLANE, approaching_plane
        import cmax
        if __name__ == "__main__":
            windows = [approaching_plane(seed % 8) for seed in range(400)]   # far more work than the test waits
            print("fitting", flush=True)
            cmax.fit_windows(windows, K_PLANE, speed=4.0, depth_grid=(3, 4), jobs=2, progress=False)
            print("finished", flush=True)
    """))
    process = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        seen = _started_workers(process)
        os.killpg(process.pid, signal.SIGINT)
        try:
            _, stderr = process.communicate(timeout=60)
        except subprocess.TimeoutExpired:     # every thread's stack, to say where it waits (it exits in ~2 s)
            os.kill(process.pid, signal.SIGUSR1)
            time.sleep(2.0)
            os.killpg(process.pid, signal.SIGKILL)
            _, stderr = process.communicate()
            pytest.fail(f"the interrupted process did not exit within 60 s; its threads:\n{stderr[-8000:]}")
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode != 0 and "KeyboardInterrupt" in stderr, stderr[-2000:]
    deadline = time.monotonic() + 10          # the forkserver exits once it sees its parent gone
    while any(_alive(pid) for pid in seen) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [pid for pid in seen if _alive(pid)]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_sigkill_of_the_caller_leaves_no_worker_running(tmp_path):
    """SIGKILL of the calling process alone (an OOM kill, ``kill -9`` of ``cmax fit --jobs 2``): its workers
    went on running, orphaned (about 1 GB per killed run); they now die with it."""
    script = tmp_path / "killed.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        sys.path[:0] = [{str(ROOT)!r}, {str(Path(__file__).parent)!r}]
        from test_fit_batch import K_PLANE, approaching_plane
        import cmax
        if __name__ == "__main__":
            windows = [approaching_plane(seed % 8) for seed in range(400)]   # far more work than the test waits
            print("fitting", flush=True)
            cmax.fit_windows(windows, K_PLANE, speed=4.0, depth_grid=(3, 4), jobs=2, progress=False)
    """))
    process = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                               text=True, start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    seen: set[int] = set()
    try:
        seen = _started_workers(process)
        process.kill()                                             # the caller alone, not its group
        process.wait()
        deadline = time.monotonic() + 15
        while any(_alive(pid) for pid in seen) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [pid for pid in seen if _alive(pid)]
    finally:
        for pid in seen:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _started_workers(process: subprocess.Popen) -> set[int]:
    """The processes that ``process`` (a script printing ``fitting`` before ``fit_windows(jobs=2)``) started, once
    the forkserver and two workers run and have fitted for a second."""
    assert process.stdout.readline().strip() == "fitting"
    seen: set[int] = set()
    deadline = time.monotonic() + 120
    while len(seen) < 3 and time.monotonic() < deadline:      # the forkserver and two workers
        seen |= _descendants(process.pid)
        time.sleep(0.2)
    assert len(seen) >= 3, seen
    time.sleep(1.0)
    return seen


def _alive(pid: int) -> bool:
    """Whether ``pid`` is a running (not zombie) process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _recording() -> Events:
    """0.1 s of dots moving at a constant flow, cut into five full 20 ms windows by the tests."""
    return translating_edges((200.0, 60.0), 5)


def test_parallel_sequence_equals_the_cold_serial_sequence_bit_for_bit():
    events = _recording()
    serial = cmax.fit_sequence(events, K, "flow", window_us=20_000, min_events=100, warm_start=False)
    parallel = cmax.fit_sequence(events, K, "flow", window_us=20_000, min_events=100, jobs=2)
    # events at 16-99,997 µs: windows from 16 µs, the fifth ending 20 µs after the last event (whole: within 1%)
    assert len(serial.results) == 5
    assert_same(parallel.results, serial.results, "results")
    assert np.array_equal(parallel.poses, serial.poses) and np.array_equal(parallel.times_us, serial.times_us)


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_sequence_names_the_window_of_each_warning(jobs):
    """Four 0.1 s windows, the second and fourth moving half a pixel: their LowMotionWarning comes back
    prefixed ``window 1:`` / ``window 3:``, fitted serially (warm starts off) or in parallel alike (serially it
    came without the window, so ``cmax fit``'s summary could not say which windows were warned)."""
    from cmax.events import concatenate

    flows = [(300.0, 0.0), (5.0, 0.0), (0.0, 250.0), (0.0, 4.0)]
    recording = concatenate([translating_edges(flow, seed, t0_us=100_000 * seed) for seed, flow in enumerate(flows)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cmax.fit_sequence(recording, K, "flow", window_us=100_000, min_events=100, jobs=jobs, warm_start=False)
    named = [str(c.message).split(":")[0] for c in caught if c.category is LowMotionWarning]
    assert named == ["window 1", "window 3"]


def test_sequence_warm_starts_by_default_and_refuses_them_in_parallel():
    """jobs=1 (the default) chains the windows: each equals cmax.fit warm-started from the one before."""
    events = _recording()
    sequence = cmax.fit_sequence(events, K, "flow", window_us=20_000, min_events=100)
    previous = None
    assert len(sequence.results) == 5
    for i, t0 in enumerate(range(int(events.t[0]), int(events.t[0]) + 100_000, 20_000)):
        previous = cmax.fit(events.slice_time(t0, t0 + 20_000), K, "flow", init=previous)
        assert_same(sequence.results[i], previous, f"window {i}")
    with pytest.raises(ValueError, match="jobs=2 needs warm_start=False"):
        cmax.fit_sequence(events, K, "flow", window_us=20_000, jobs=2, warm_start=True)
    with pytest.raises(ValueError, match="jobs must be a positive integer"):
        cmax.fit_sequence(events, K, "flow", window_us=20_000, jobs=0)
    with pytest.raises(TypeError, match="bogus"):                 # refused before any worker starts
        cmax.fit_sequence(events, K, "flow", window_us=20_000, jobs=2, bogus=1)


def test_benchmark_report_gives_windows_per_second_ratio_and_efficiency():
    from benchmarks.speed_batch_fit import report

    text = report({1: [10.0, 12.0, 11.0], 2: [6.0, 5.0, 7.0]}, {1: [9.0, 12.0, 10.0], 2: [12.0, 9.0, 12.0]},
                  [1.0, 2.0], {1: [0, 1], 2: [1, 1]}, 3.0, windows=6, events=[100, 200], width=160, height=120,
                  repeats=3, equal=True, cores=2, autogroup=True)
    # 6 windows / median 11 s = 0.545 windows/s (1.83 s each); 6 / 6 s = 1.0 windows/s: ratio 1.83, efficiency
    # 0.92; CPU per window: median 10 s / 6 and 12 s / 6; cores used: 31 s / 33 s and 33 s / 18 s
    assert "| 1 | 0.545 | 1.83 | 1.00 | 1.00 | 1.67 | 0.94 | 0.5 |" in text
    assert "| 2 | 1.000 | 1.00 | 1.83 | 0.92 | 2.00 | 1.83 | 1.0 |" in text
    assert "autogroup" in text and "Results identical across the job counts: yes" in text


def test_the_forkserver_warms_the_kernels_with_one_small_fit(monkeypatch):
    """``cmax.fitting._warm`` (the last module the forkserver preloads) fits a deterministic synthetic window
    through every se3 stage and leaves torch's thread count as it was."""
    import torch

    from cmax.fitting import batch
    from cmax.fitting._warm import warm, warm_events

    assert batch._PRELOAD[-1] == "cmax.fitting._warm"
    first, second = warm_events(), warm_events()
    assert np.array_equal(first[0].t, second[0].t) and np.array_equal(first[0].x, second[0].x)
    events, K, speed = first
    assert len(events) > 1000 and np.all(np.diff(events.t) >= 0)
    stages = []
    real_fit = cmax.fitting.api.fit

    def recording(*args, **kwargs):
        result = real_fit(*args, **kwargs)
        stages.extend(log.stage for log in result.stages)
        return result

    monkeypatch.setattr(cmax.fitting.api, "fit", recording)
    before = torch.get_num_threads()
    warm()
    assert torch.get_num_threads() == before
    assert {"patch_flow", "local_refine", "depth_sweep"} <= set(stages)


@pytest.mark.skipif(not Path("/proc/self/status").exists() or "forkserver" not in multiprocessing.get_all_start_methods(),
                    reason="reads the forkserver's signal dispositions from /proc (Linux)")
@pytest.mark.parametrize("module, context", [("cmax.fitting.batch", "_context"), ("cmax.sim.convert", "_worker_context")])
def test_the_forkserver_of_the_workers_ignores_ctrl_c(module: str, context: str) -> None:
    """Ctrl-C reaches the terminal's whole process group: the forkserver of ``cmax fit --jobs 2`` (and of ``cmax
    simulate --workers 2``), importing its preloaded modules for seconds, printed the traceback of its
    ``KeyboardInterrupt`` (some 30 lines under ``cmax fit: interrupted``). It is started with SIGINT ignored now
    (its workers inherit that; the calling process stops them)."""
    script = textwrap.dedent(f"""
        import signal
        signal.signal(signal.SIGINT, signal.default_int_handler)   # as a terminal starts it (CI may ignore SIGINT)
        from multiprocessing import forkserver
        from {module} import {context}
        {context}()
        pid = forkserver._forkserver._forkserver_pid
        assert pid is not None, "the forkserver was not started"
        ignored = next(int(line.split()[1], 16) for line in open(f"/proc/{{pid}}/status") if line.startswith("SigIgn"))
        print(bool(ignored >> (int(signal.SIGINT) - 1) & 1), signal.getsignal(signal.SIGINT) is signal.default_int_handler)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert done.returncode == 0 and done.stdout.split() == ["True", "True"], done.stderr[-2000:]


def test_ctrl_c_while_a_worker_starts_is_raised_once_the_worker_is_recorded() -> None:
    """``sigint_deferred`` holds Ctrl-C back over a worker's start and recording (a worker the pool started but had
    not recorded was left running when ``cmax fit --jobs 2`` stopped, and printed a traceback once it had exited)."""
    from cmax._signals import sigint_deferred

    steps = []
    outside = signal.signal(signal.SIGINT, signal.default_int_handler)   # as a terminal starts it (CI may ignore it)
    try:
        with pytest.raises(KeyboardInterrupt):
            with sigint_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)                      # the signal is handled (held) here, between bytecodes
                steps.append("recorded")
        assert steps == ["recorded"] and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, outside)
    with sigint_deferred():                           # no Ctrl-C: nothing raised
        steps.append("quiet")
    assert steps == ["recorded", "quiet"]


def test_an_ignored_ctrl_c_stays_ignored_and_a_handler_of_the_caller_s_own_gets_it() -> None:
    """A process started with SIGINT ignored (``nohup``, the background of a script) must not turn a Ctrl-C sent to
    its group into a ``KeyboardInterrupt`` while a worker starts (was: ``sigint_deferred`` installed its holder over
    the ignored disposition and raised); a handler the caller installed gets the held signal, not an exception."""
    from cmax._signals import sigint_deferred

    outside = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        try:
            with sigint_deferred():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
        except KeyboardInterrupt:                     # would stop the whole test run: fail this test instead
            pytest.fail("an ignored SIGINT was raised as KeyboardInterrupt")
        assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        got = []
        signal.signal(signal.SIGINT, lambda signum, frame: got.append(signum))
        with sigint_deferred():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            assert got == []                          # held until the block ends
        assert got == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, outside)
