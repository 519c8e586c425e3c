"""Writers that cannot lose data (issue 20): concurrent writers, planted links, truncated outputs,
full and size-limited file systems, killed parents and killed workers.

Each class of failure is provoked for real: a second process racing a writer, an
``RLIMIT_FSIZE`` set in a subprocess (and a 1 MiB tmpfs where the test may mount
one), ``SIGKILL`` of the parent of ``cmax simulate --workers 2`` with its worker
processes checked by process id afterwards. The expectations are independent of
the code under test: bytes and inodes of the other writer's file, the events
written, the errno of the file system, ``/proc``.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from cmax.cli import main
from cmax.io import read_h5, write_evt3, write_h5
from cmax.io.atomic import OutputLockedError, PathLock, save_npz_atomic, write_text_atomic
from cmax.io.errors import FormatError
from cmax.io.h5 import H5Writer, verify_h5
from cmax.sim.convert import FOLDER_LOCK, ConvertSettings, VideoJob, convert_collection, load_manifest
from conftest import random_events
from test_crash_safety import _write_video
from test_sim_convert import FAST, write_video

ROOT = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
POSIX = pytest.mark.skipif(not hasattr(signal, "SIGKILL") or os.name != "posix", reason="needs POSIX")
PROC = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc (Linux)")


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(TESTS), os.environ.get("PYTHONPATH", "")]),
                OMP_NUM_THREADS="1")


def _python(code: str, *args: str, timeout: float = 120, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], capture_output=True, text=True,
                          timeout=timeout, env=_env(), **kwargs)


def _cmax(*args: str) -> list[str]:
    return [sys.executable, "-m", "cmax.cli", *args]


def _listing(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir())


# -- two writers of one path --------------------------------------------------------------
RACE_WRITER = """
    import sys
    from conftest import random_events
    from cmax.io.h5 import H5Writer
    events = random_events(20_000, seed=1)
    with H5Writer(sys.argv[1], events.width, events.height, chunk_size=1000) as writer:
        writer.append(events[:10_000])
        print("half", flush=True)
        sys.stdin.readline()  # the other writer tries now
        writer.append(events[10_000:])
    print("done", flush=True)
"""


@POSIX
def test_a_second_process_cannot_touch_the_first_writers_file(tmp_path):
    target = tmp_path / "ev.h5"
    first = subprocess.Popen([sys.executable, "-c", textwrap.dedent(RACE_WRITER), str(target)], env=_env(),
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert first.stdout.readline().strip() == "half", first.stderr.read()
        (temporary,) = tmp_path.glob("ev.h5.*.partial")
        before = (temporary.stat().st_ino, temporary.read_bytes(), _listing(tmp_path))
        other = random_events(500, seed=7)
        # This process is the second writer: every way of writing the path fails at once.
        with pytest.raises(OutputLockedError, match="another writer"):
            H5Writer(target, 64, 48, overwrite=True)
        with pytest.raises(OutputLockedError):
            write_h5(target, other, overwrite=True)
        with pytest.raises(OutputLockedError):
            write_evt3(target, other, overwrite=True)
        second = _python("""
            import sys
            from conftest import random_events
            from cmax.io import write_h5
            write_h5(sys.argv[1], random_events(10, seed=3), overwrite=True)
        """, str(target))
        assert second.returncode == 1 and "OutputLockedError" in second.stderr
        assert (temporary.stat().st_ino, temporary.read_bytes(), _listing(tmp_path)) == before
        first.stdin.write("\n")
        first.stdin.flush()
        assert first.wait(timeout=60) == 0, first.stderr.read()
        assert first.stdout.readline().strip() == "done"
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert verify_h5(target, events=20_000) == 20_000
    assert read_h5(target) == random_events(20_000, seed=1)
    assert _listing(tmp_path) == ["ev.h5"]


def test_a_second_writer_in_the_same_process_fails_and_the_first_completes(tmp_path):
    target, events = tmp_path / "ev.h5", random_events(3000)
    with H5Writer(target, 64, 48, chunk_size=500) as writer:
        writer.append(events[:1000])
        with pytest.raises(OutputLockedError):
            H5Writer(target, 64, 48, overwrite=True)
        writer.append(events[1000:])
    assert read_h5(target) == events and verify_h5(target) == 3000
    with H5Writer(target, 64, 48, overwrite=True) as writer:  # the lock went with the first writer
        writer.append(events[:10])
    assert verify_h5(target, events=10) == 10 and _listing(tmp_path) == ["ev.h5"]


def test_a_conversion_into_a_locked_folder_fails_in_one_line(tmp_path, capsys):
    write_video(tmp_path / "a.avi")
    out = tmp_path / "out"
    out.mkdir()
    with PathLock(out / FOLDER_LOCK):  # another conversion is writing into out/
        assert main(["simulate", str(tmp_path / "a.avi"), "-o", str(out), "--quiet", "--no-adaptive"]) == 2
        with pytest.raises(OutputLockedError):
            convert_collection([VideoJob("a", tmp_path / "a.avi")], out, FAST, progress=False)
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and "being written by another writer" in error
    assert _listing(out) == []  # the lock file went with its holder; nothing else was made


# -- links planted at the names a writer uses ---------------------------------------------
def _plant(tmp_path: Path) -> tuple[Path, Path, bytes]:
    victim = tmp_path / "outside" / "precious.txt"
    victim.parent.mkdir()
    victim.write_bytes(b"do not overwrite")
    out = tmp_path / "out"
    out.mkdir()
    return out, victim, victim.read_bytes()


from cmax.emvs.result import write_ply  # noqa: E402
from cmax.io.text import write_txt  # noqa: E402
from cmax.viz import save_image  # noqa: E402

WRITERS = {
    "h5": lambda path: write_h5(path, random_events(200), overwrite=True),
    "evt3": lambda path: write_evt3(path, random_events(200), overwrite=True),
    "text": lambda path: write_text_atomic(path, "new"),
    "npz": lambda path: save_npz_atomic(path, a=np.arange(3)),
    "ecd_txt": lambda path: write_txt(path, random_events(50), overwrite=True),
    "picture": lambda path: save_image(path, np.zeros((4, 4), np.uint8)),
    "ply": lambda path: write_ply(path, np.ones((3, 3))),
}


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_links_planted_at_the_temporary_and_lock_names_are_never_followed(tmp_path, monkeypatch, kind):
    out, victim, content = _plant(tmp_path)
    target = out / ("ev.png" if kind == "picture" else "ev.out")
    write = WRITERS[kind]
    # The old fixed temporary name: ignored (left as it is); the file is written.
    (out / f"{target.name}.partial").symlink_to(victim)
    write(target)
    assert target.is_file() and not target.is_symlink() and victim.read_bytes() == content
    assert os.readlink(out / f"{target.name}.partial") == str(victim)
    # A link at the exact private name the writer draws: O_EXCL refuses it.
    import cmax.io.atomic as atomic

    monkeypatch.setattr(atomic.secrets, "token_hex", lambda n: "0123456789abcdef")
    (out / f"{target.name}.0123456789abcdef.partial").symlink_to(victim)
    before = target.read_bytes()
    with pytest.raises(FileExistsError):
        write(target)
    assert victim.read_bytes() == content and target.read_bytes() == before
    monkeypatch.undo()
    # A link at the lock name: refused, nothing written.
    (out / f"{target.name}.lock").symlink_to(victim)
    with pytest.raises(OSError, match="symbolic link"):
        write(target)
    assert victim.read_bytes() == content and target.read_bytes() == before


def test_a_link_at_the_final_name_is_replaced_not_followed(tmp_path):
    out, victim, content = _plant(tmp_path)
    target = out / "ev.h5"
    target.symlink_to(victim)
    with pytest.raises(FileExistsError):
        write_h5(target, random_events(100))
    write_h5(target, random_events(100), overwrite=True)
    assert not target.is_symlink() and verify_h5(target) == 100 and victim.read_bytes() == content


# -- the completion record and resuming ---------------------------------------------------
def test_verify_h5_accepts_complete_files_only(tmp_path):
    events = random_events(5000, t_span_us=3_000_000)
    path = write_h5(tmp_path / "ev.h5", events, compression="none")
    assert verify_h5(path) == 5000 and verify_h5(path, events=5000) == 5000
    with pytest.raises(FormatError, match="expected 4999"):
        verify_h5(path, events=4999)
    cut = tmp_path / "cut.h5"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(FormatError):
        verify_h5(cut)
    with h5py.File(tmp_path / "foreign.h5", "w") as file:  # the DSEC layout without the record
        for name in "xytp":
            file[f"events/{name}"] = np.zeros(3, np.int64)
        file["ms_to_idx"] = np.array([0, 3], np.uint64)
    with pytest.raises(FormatError, match="no completion record"):
        verify_h5(tmp_path / "foreign.h5")
    with h5py.File(tmp_path / "lying.h5", "w") as file:  # a record that does not match the data
        for name in "xytp":
            file[f"events/{name}"] = np.zeros(3, np.int64)
        file["ms_to_idx"] = np.array([0, 3], np.uint64)
        file.attrs["event_count"], file.attrs["complete"] = 4, True
    with pytest.raises(FormatError, match="says 4 events"):
        verify_h5(tmp_path / "lying.h5")
    (tmp_path / "link.h5").symlink_to(path)
    with pytest.raises(FormatError, match="not a regular file"):
        verify_h5(tmp_path / "link.h5")
    with pytest.raises(ValueError, match="reserved"):
        write_h5(tmp_path / "x.h5", events, complete=True)
    assert not (tmp_path / "x.h5").exists()


def test_resume_redoes_truncated_and_foreign_outputs(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    for shift, name in enumerate("abc"):
        write_video(videos / f"{name}.avi", shift=3 * shift)
    jobs = [VideoJob(name, videos / f"{name}.avi") for name in "abc"]
    out = tmp_path / "out"
    first = convert_collection(jobs, out, FAST, progress=False)
    assert all(entry["status"] == "ok" for entry in first["videos"].values())
    for name, entry in first["videos"].items():
        assert entry["bytes"] == (out / f"{name}.h5").stat().st_size and len(entry["sha256"]) == 64
    original = {name: read_h5(out / f"{name}.h5") for name in "abc"}
    untouched = (out / "c.h5").stat().st_mtime_ns
    with open(out / "a.h5", "r+b") as file:  # truncated under its final name
        file.truncate((out / "a.h5").stat().st_size // 2)
    write_h5(out / "b.h5", random_events(original["b"].__len__(), width=48, height=32), overwrite=True)  # foreign

    # A run over c alone: the manifest stops listing a and b as ok (their files are not as recorded).
    manifest = convert_collection(jobs[2:], out, FAST, progress=False)
    assert {name: entry["status"] for name, entry in manifest["videos"].items()} == {
        "a": "failed", "b": "failed", "c": "ok"}
    assert "output not verified" in manifest["videos"]["a"]["error"]
    assert load_manifest(out / "manifest.json")["totals"]["ok"] == 1

    seen = []
    manifest = convert_collection(jobs, out, FAST, progress=False, on_result=lambda r: seen.append(r.name))
    assert seen == ["a", "b"]
    assert (out / "c.h5").stat().st_mtime_ns == untouched
    for name in "abc":
        assert read_h5(out / f"{name}.h5") == original[name]
        assert manifest["videos"][name]["status"] == "ok"
        assert verify_h5(out / f"{name}.h5", events=manifest["videos"][name]["events"])
    assert _listing(out) == ["a.h5", "b.h5", "c.h5", "manifest.json"]


# -- malformed manifests ------------------------------------------------------------------
GOOD_ENTRY = {"status": "ok", "frames": 1, "events": 2, "duration_s": 0.1, "bytes": 3, "sha256": "0" * 64}
BAD_MANIFESTS = {
    "not json": "{",
    "a list": "[]",
    "other format": json.dumps({"format": "x"}),
    "videos a list": json.dumps({"format": "evtslowtv-manifest/1", "settings": {}, "videos": []}),
    "entry without status": json.dumps({"format": "evtslowtv-manifest/1", "settings": {}, "videos": {"a": {}}}),
    "entry a number": json.dumps({"format": "evtslowtv-manifest/1", "settings": {}, "videos": {"a": 3}}),
    "events a string": json.dumps({"format": "evtslowtv-manifest/1", "settings": {},
                                   "videos": {"a": dict(GOOD_ENTRY, events="many")}}),
    "negative frames": json.dumps({"format": "evtslowtv-manifest/1", "settings": {},
                                   "videos": {"a": dict(GOOD_ENTRY, frames=-1)}}),
    "settings null": json.dumps({"format": "evtslowtv-manifest/1", "settings": None, "videos": {}}),
    "missing a string": json.dumps({"format": "evtslowtv-manifest/1", "settings": {}, "videos": {},
                                    "missing": "a"}),
    "deeply nested": "[" * 100_000,
}


@pytest.mark.parametrize("case", sorted(BAD_MANIFESTS))
def test_malformed_manifests_give_one_line(tmp_path, capsys, case):
    path = tmp_path / "manifest.json"
    path.write_text(BAD_MANIFESTS[case])
    with pytest.raises(ValueError) as caught:
        load_manifest(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)
    assert main(["manifest", "merge", str(path), "-o", str(tmp_path / "merged.json")]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("cmax manifest: error:") and "\n" not in error
    assert not (tmp_path / "merged.json").exists()


def test_a_conversion_refuses_a_folder_with_a_malformed_manifest(tmp_path):
    write_video(tmp_path / "a.avi")
    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_bytes(b"\xff\xfe not utf-8")
    with pytest.raises(ValueError, match="not a JSON manifest"):
        convert_collection([VideoJob("a", tmp_path / "a.avi")], out, FAST, progress=False)
    assert _listing(out) == ["manifest.json"]


# -- full and size-limited file systems ---------------------------------------------------
LIMITED_WRITES = """
    import errno, os, resource, signal, sys
    from pathlib import Path
    import numpy as np
    from conftest import random_events
    from cmax.io import read_h5, write_evt3, write_h5
    from cmax.io.atomic import write_text_atomic

    folder = Path(sys.argv[1])
    if sys.argv[2] == "fsize":
        signal.signal(signal.SIGXFSZ, signal.SIG_DFL)  # as an embedding program may leave it
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))
    big = random_events(2_000_000, width=640, height=480, t_span_us=10_000_000)
    (folder / "old.txt").write_text("old")
    for name, write in (("big.h5", lambda p: write_h5(p, big)), ("big.raw", lambda p: write_evt3(p, big)),
                        ("old.txt", lambda p: write_text_atomic(p, "x" * (3 << 20)))):
        try:
            write(folder / name)
        except OSError as error:
            print(name, errno.errorcode[error.errno], error.filename, "\\n" not in str(error), flush=True)
        else:
            print(name, "written")
    print(sorted(os.listdir(folder)))
    small = random_events(1000, seed=5)
    write_h5(folder / "small.h5", small)  # the process goes on writing
    assert read_h5(folder / "small.h5") == small
    print("alive")
"""


def _check_limited_writes(done: subprocess.CompletedProcess, folder: Path, code: str) -> None:
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    lines = done.stdout.splitlines()
    for line, name in zip(lines, ("big.h5", "big.raw", "old.txt")):
        assert line == f"{name} {code} {folder / name} True", line
    assert lines[3] == "['old.txt']" and lines[-1] == "alive"
    assert (folder / "old.txt").read_text() == "old"
    assert "Segmentation" not in done.stderr and "Traceback" not in done.stderr


@POSIX
def test_a_file_size_limit_gives_a_clean_error_and_leaves_nothing(tmp_path):
    done = _python(LIMITED_WRITES, str(tmp_path), "fsize")
    _check_limited_writes(done, tmp_path, "EFBIG")


@pytest.fixture
def tiny_tmpfs(tmp_path):
    """A 1 MiB tmpfs mounted at tmp_path/disk (root only); skips where it cannot be mounted."""
    disk = tmp_path / "disk"
    disk.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root and mount(8)")
    made = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)], capture_output=True)
    if made.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {made.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


@POSIX
def test_a_full_file_system_gives_a_clean_error_and_leaves_nothing(tiny_tmpfs):
    done = _python(LIMITED_WRITES, str(tiny_tmpfs), "full")
    _check_limited_writes(done, tiny_tmpfs, "ENOSPC")


LIMITED_SIMULATE = """
    import resource, sys
    resource.setrlimit(resource.RLIMIT_FSIZE, (150_000, 150_000))
    from cmax.cli import main
    sys.exit(main(["simulate", sys.argv[1], "-o", sys.argv[2], "--quiet", "--method", "linear",
                   "--workers", sys.argv[3]]))
"""


@POSIX
@pytest.mark.parametrize("workers", ["1", "2"])
def test_simulate_under_a_file_size_limit_records_the_failure_and_goes_on(tmp_path, workers):
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    _write_video(videos / "a.avi", 40, 0)
    _write_video(videos / "big.avi", 300, 1)  # its event file outgrows the limit
    _write_video(videos / "c.avi", 40, 2)
    done = _python(LIMITED_SIMULATE, str(videos), str(out), workers, timeout=300)
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])  # 1: some video failed
    assert "Segmentation" not in done.stderr and "Traceback" not in done.stderr
    manifest = load_manifest(out / "manifest.json")
    assert {name: entry["status"] for name, entry in manifest["videos"].items()} == {
        "a": "ok", "big": "failed", "c": "ok"}
    error = manifest["videos"]["big"]["error"]
    assert "File too large" in error and str(out / "big.h5") in error
    for name in "ac":
        assert verify_h5(out / f"{name}.h5", events=manifest["videos"][name]["events"]) > 0
    assert _listing(out) == ["a.h5", "c.h5", "manifest.json"]


TINY_LIMIT_SIMULATE = """
    import resource, sys
    resource.setrlimit(resource.RLIMIT_FSIZE, (1024, 1024))   # the first manifest (no video yet) fits, no more
    from cmax.cli import main
    sys.exit(main())
"""


@POSIX
def test_simulate_whose_manifest_cannot_be_written_says_so_in_one_line(tmp_path):
    """Was: one ``cmax: warning: could not write .../manifest.json: [Errno 27] File too large ...`` per video whose
    record could not be saved, then the same error again: 3 lines for two videos where every other command prints
    one. Now the one error of the last try (exit 2)."""
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    _write_video(videos / "a.avi", 40, 0)
    _write_video(videos / "b.avi", 40, 1)
    done = _python(TINY_LIMIT_SIMULATE, "simulate", str(videos), "-o", str(out), "--quiet", "--method", "linear",
                   timeout=300)
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cmax simulate: error: File too large"), done.stderr
    assert lines[0].endswith(str(out / "manifest.json")), lines
    assert not [name for name in _listing(out) if name.endswith((".partial", ".lock"))], _listing(out)


# -- worker processes ---------------------------------------------------------------------
def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def _descendants(pid: int) -> list[int]:
    found, todo = [], [pid]
    while todo:
        children = _children(todo.pop())
        found += children
        todo += children
    return found


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped by init, does not count)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


def _holder_of(pids: list[int], name: str) -> int | None:
    """The process among ``pids`` with ``name`` open."""
    for pid in pids:
        try:
            links = [os.readlink(fd) for fd in Path(f"/proc/{pid}/fd").iterdir()]
        except OSError:
            continue
        if any(Path(link).name == name for link in links):
            return pid
    return None


def _wait_for(condition, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.005)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@POSIX
@PROC
def test_killing_the_parent_of_two_workers_leaves_no_process(tmp_path):
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    for seed, name in enumerate("abc"):     # long enough that no video is done between the checks below
        _write_video(videos / f"{name}.avi", 1200, seed)
    parent = subprocess.Popen(_cmax("simulate", str(videos), "-o", str(out), "--quiet", "--method", "linear",
                                    "--workers", "2", "--chunk-frames", "0"),   # the outputs written as they go
                              env=_env(), stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE)
    try:
        partials = _wait_for(lambda: (lambda found: found if len(found) == 2 or parent.poll() is not None
                                      else None)(list(out.glob("*.h5.*.partial"))), 120, "two workers writing")
        assert parent.poll() is None, parent.stderr.read()
        names = [f"{p.name.split('.h5.')[0]}.h5.lock" for p in partials]

        def two_holders():      # /proc is read while the workers run: look again until both are seen
            pids = _descendants(parent.pid)
            found = {_holder_of(pids, name) for name in names}
            return (pids, found) if None not in found and len(found) == 2 else None

        workers, holders = _wait_for(two_holders, 5, f"two worker processes holding {names}")
        assert len(holders) == 2  # two worker processes, one per video
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=30)
        _wait_for(lambda: not any(_alive(pid) for pid in workers), 5, f"the workers {workers} to die")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
    assert not any(_alive(pid) for pid in workers)
    assert not (out / "c.h5").exists() and not (out / "a.h5").exists()
    assert load_manifest(out / "manifest.json")["videos"] == {}  # valid, and lists nothing unverified


@POSIX
@PROC
def test_a_killed_worker_fails_its_own_video_only(tmp_path):
    videos, out = tmp_path / "videos", tmp_path / "out"
    videos.mkdir()
    _write_video(videos / "a.avi", 300, 0)
    _write_video(videos / "b.avi", 30, 1)
    _write_video(videos / "c.avi", 10, 2)  # starts once a worker's slot is free
    jobs = [VideoJob(name, videos / f"{name}.avi") for name in "abc"]
    killed: list[int] = []

    def kill_the_worker_of_a() -> None:
        worker = _wait_for(lambda: _holder_of(_descendants(os.getpid()), "a.h5.lock"), 120, "the worker of a")
        os.kill(worker, signal.SIGKILL)
        killed.append(worker)

    killer = threading.Thread(target=kill_the_worker_of_a, daemon=True)
    killer.start()
    settings = ConvertSettings(method="linear")
    manifest = convert_collection(jobs, out, settings, workers=2, progress=False, chunk_frames=None)  # no chunks kept
    killer.join(timeout=10)
    assert killed and not _alive(killed[0])
    assert {name: entry["status"] for name, entry in manifest["videos"].items()} == {
        "a": "failed", "b": "ok", "c": "ok"}
    assert "killed by signal SIGKILL" in manifest["videos"]["a"]["error"]
    assert load_manifest(out / "manifest.json") == manifest
    for name in "bc":
        assert verify_h5(out / f"{name}.h5", events=manifest["videos"][name]["events"]) > 0
    assert _listing(out) == ["b.h5", "c.h5", "manifest.json"]  # a's temporary removed, no lock left


def test_one_wrong_timestamp_is_refused_before_the_index_is_allocated(tmp_path):
    events = random_events(14_000, t_span_us=1_000_000)
    t = events.t.copy()
    t[-1] += 2**40  # one timestamp off by 2**40 µs: an ms_to_idx of 8 GiB
    from cmax.events import Events

    wrong = Events(events.x, events.y, t, events.p, events.width, events.height)
    with pytest.raises(ValueError, match=r"time stamp is probably off") as caught:
        write_h5(tmp_path / "ev.h5", wrong)
    assert "GiB" in str(caught.value) and "\n" not in str(caught.value)
    assert _listing(tmp_path) == []
    with pytest.raises(ValueError, match="probably off"):  # an explicit offset far before the events
        with H5Writer(tmp_path / "ev.h5", 64, 48, t_offset_us=0) as writer:
            writer.append(Events(events.x, events.y, events.t + 2**50, events.p, 64, 48))
    assert _listing(tmp_path) == []
    long = Events(events.x[:2], events.y[:2], np.array([0, 2**24 * 1000 - 1]), events.p[:2], 64, 48)
    assert verify_h5(write_h5(tmp_path / "long.h5", long)) == 2  # 4.6 hours: allowed whatever the count


def test_a_writer_dropped_without_close_says_so_and_leaves_nothing(tmp_path):
    """A script that made an H5Writer and ended without close() (no ``with``) left ``X.h5.<hex>.partial`` and
    ``X.h5.lock`` and no output, without a word. Now a warning, and neither file stays."""
    import gc
    import warnings

    import numpy as np

    from cmax import Events
    from cmax.io import H5Writer

    writer = H5Writer(tmp_path / "x.h5", 64, 48)
    writer.append(Events(np.array([1]), np.array([1]), np.array([0]), np.array([1]), 64, 48))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        del writer
        gc.collect()
    assert any("was never closed: nothing was written there" in str(c.message) for c in caught), caught
    assert sorted(p.name for p in tmp_path.iterdir()) == []
