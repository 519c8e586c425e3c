"""SIGHUP (a closed ssh session or terminal, a batch system's hangup) stops every command as SIGTERM and Ctrl-C do,
with their clean-up, and a signal while a command's process exits leaves its exit status as the command gave it
(:mod:`cmax._signals`)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from conftest import sigterm_once

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="needs POSIX signals")


def _depth(slider_file, out, checkpoint) -> list[str]:
    return [sys.executable, "-m", "cmax.cli", "depth", str(slider_file), "-o", str(out), "--checkpoint",
            str(checkpoint), "--quiet", "--window", "0.005"]


def test_sighup_cleans_up_as_sigterm_does(slider_file, tiny_checkpoint, tmp_path):
    """Was: SIGHUP killed ``cmax depth -o D`` where it stood: exit -1, nothing on stderr, ``D/.results.lock`` and the
    private ``D/.depth.<hex>.partial`` left. Now the clean-up of SIGTERM: exit 129 (128 + SIGHUP), one line, no
    lock or stage left."""
    out = tmp_path / "D"
    status, err = sigterm_once(_depth(slider_file, out, tiny_checkpoint), out, ".depth.*.partial",
                               "its stage folder was seen", signum=signal.SIGHUP)
    assert status == 128 + signal.SIGHUP, err
    assert err == "cmax depth: terminated (SIGHUP)\n", err
    left = [path.name for path in out.iterdir()] if out.exists() else []
    assert not [name for name in left if name.endswith((".partial", ".lock"))], left


def test_a_command_started_under_nohup_keeps_ignoring_sighup(slider_file, tiny_checkpoint, tmp_path):
    """``nohup cmax ...`` starts the process with SIGHUP ignored: the handler that stops a run on SIGHUP must not
    replace that disposition (the run would stop when the terminal closes, what nohup is for)."""
    out = tmp_path / "D"
    status, err = sigterm_once(_depth(slider_file, out, tiny_checkpoint), out, ".depth.*.partial",
                               "its stage folder was seen", signum=signal.SIGHUP,
                               preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    assert status == 0, err
    assert (out / "summary.json").is_file() and "terminated" not in err


def test_the_stopped_line_names_the_signal():
    """``cmax fit`` / ``cmax depth`` stopped with windows kept: the line and status name the signal that came."""
    from pathlib import Path

    from cmax._signals import Terminated
    from cmax.io.window_store import stopped_line

    line, status = stopped_line("cmax fit", Terminated(signal.SIGHUP), 2, Path("F/.fit.windows"))
    assert line.startswith("cmax fit: terminated (SIGHUP): 2 finished window(s) kept in") and status == 129
    assert stopped_line("cmax fit", Terminated(), 2, Path("F"))[1] == 143


#: A command whose process takes seconds to exit after it returned: an object torn down with ``__main__`` (as
#: torch's libraries are, after Python has restored the default signal handlers) writes ``EXITING`` and waits.
_SLOW_EXIT = textwrap.dedent("""
    import os, sys, time
    from cmax._args import ArgumentParser, run_main

    class SlowTeardown:
        def __del__(self, open=open, sleep=time.sleep, path=os.environ["EXITING"]):   # builtins are gone by then
            open(path, "w").close()
            sleep(3)

    slow = SlowTeardown()
    sys.exit(run_main(ArgumentParser(prog="demo"), lambda args: 3))
""")


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_while_the_process_exits_leaves_the_commands_status(tmp_path, signum):
    """Was: a Ctrl-C or SIGTERM after the command had ended (its clean-up done, its line printed), while the
    interpreter exits, killed the process: exit -2 / -15 instead of the command's status (a second Ctrl-C or
    SIGTERM during the second or more that torch's teardown takes). Now ignored: the status is the command's."""
    exiting = tmp_path / "exiting"
    process = subprocess.Popen([sys.executable, "-c", _SLOW_EXIT], stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "EXITING": str(exiting)})
    deadline = time.monotonic() + 60
    while not exiting.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert exiting.exists(), process.communicate(timeout=60)
    process.send_signal(signum)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 3, (process.returncode, err)
    assert "Traceback" not in err, err


#: A command whose clean-up (a ``finally`` block, as a lock's release or a stage's removal) takes a while: it writes
#: ``STARTED`` when it runs, ``CLEANING`` when its clean-up starts and ``CLEANED`` when that ends.
_SLOW_CLEAN_UP = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from cmax._args import ArgumentParser, run_main

    def command(args):
        folder = Path(os.environ["MARKS"])
        try:
            (folder / "STARTED").touch()
            time.sleep(60)
        finally:
            (folder / "CLEANING").touch()
            time.sleep(1.5)
            (folder / "CLEANED").touch()
        return 0

    sys.exit(run_main(ArgumentParser(prog="demo"), command))
""")


def _wait_for(path, process) -> None:
    deadline = time.monotonic() + 60
    while not path.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert path.exists(), process.communicate(timeout=60)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_ctrl_c_during_the_clean_up_of_a_stop_signal_neither_cuts_it_short_nor_changes_the_status(tmp_path, signum):
    """Was: a Ctrl-C while the clean-up of a SIGTERM ran (an impatient user, a terminal's Ctrl-C after ``timeout``)
    raised ``KeyboardInterrupt`` inside it: the rest of the clean-up skipped (locks, stages left) and the run
    reported ``interrupted``, exit 130. Now ignored from the stop signal on, as a second SIGTERM is: the clean-up
    ends, the line and status are the stop signal's (128 + its number)."""
    process = subprocess.Popen([sys.executable, "-c", _SLOW_CLEAN_UP], stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "MARKS": str(tmp_path)})
    _wait_for(tmp_path / "STARTED", process)
    process.send_signal(signum)
    _wait_for(tmp_path / "CLEANING", process)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert (tmp_path / "CLEANED").exists(), err
    assert process.returncode == 128 + signum, (process.returncode, err)
    assert err == f"demo: terminated ({signal.Signals(signum).name})\n", err


def test_ctrl_c_alone_still_interrupts(tmp_path):
    """Control: a Ctrl-C with no stop signal before it interrupts the run as before (exit 130, its clean-up run)."""
    process = subprocess.Popen([sys.executable, "-c", _SLOW_CLEAN_UP], stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "MARKS": str(tmp_path)})
    _wait_for(tmp_path / "STARTED", process)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130 and err == "demo: interrupted\n", (process.returncode, err)
    assert (tmp_path / "CLEANED").exists()


def test_sighup_to_the_process_group_of_fit_with_workers_is_one_line(slider_file, tmp_path):
    """A closed ssh session signals the whole job: with ``--jobs 2`` multiprocessing's resource tracker, which ignores
    SIGINT and SIGTERM but not SIGHUP, died and was relaunched (``warning: resource_tracker: process died
    unexpectedly, relaunching``, then ``KeyError`` tracebacks of the new tracker). The forkserver, its workers and
    the tracker now start with SIGHUP ignored (as SIGINT): the calling process stops them, one line, exit 129."""
    out = tmp_path / "F"
    status, err = sigterm_once([sys.executable, "-m", "cmax.cli", "fit", str(slider_file), "-o", str(out), "--quiet",
                                "--window-ms", "30", "--min-events", "100", "--depth-grid", "6,8", "--jobs", "2"],
                               tmp_path, "F/.fit.windows/window_*", "its workers fitted a window", signum=signal.SIGHUP,
                               group=True)
    assert status == 129, err
    assert "Traceback" not in err and "resource_tracker" not in err, err
    assert [line for line in err.splitlines() if "terminated" in line] == [err.splitlines()[-1]], err
    assert err.splitlines()[-1].startswith("cmax fit: terminated (SIGHUP)"), err
    left = [path.name for path in out.iterdir()] if out.exists() else []
    assert not [name for name in left if name.endswith((".partial", ".lock"))], left
