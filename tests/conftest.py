"""Shared fixtures: the real recordings in ``../shared/data`` and small synthetic events."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from cmax.events import Events

#: Real test data lives beside the project (``../shared/data``); users who clone
#: the project do not have it, so tests that need it skip with a reason.
SHARED_DATA = Path(
    os.environ.get("EVTSLOWTV_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not found at {SHARED_DATA} (set EVTSLOWTV_SHARED_DATA)")
    return SHARED_DATA


def random_events(n: int, width: int = 64, height: int = 48, seed: int = 0, t_span_us: int = 100_000) -> Events:
    """``n`` uniformly random events, sorted by time, for tests."""
    rng = np.random.default_rng(seed)
    t = np.sort(rng.integers(0, t_span_us, n))
    return Events(
        rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n),
        width, height,
    )


@pytest.fixture
def small_events() -> Events:
    """2,000 random events on a 64x48 sensor over 0.1 s."""
    return random_events(2000)


def one_line_error(call, capsys) -> tuple[int, str]:
    """Run ``call`` (a command's ``main``; argparse's ``SystemExit`` taken as its status) and check that it
    wrote exactly one line to stderr and no traceback; returns ``(status, stderr)``."""
    try:
        status = call()
    except SystemExit as exit_:   # argparse
        status = exit_.code
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return status, err


def counted_calls(monkeypatch, owner, name: str, interrupt_at: int | None = None) -> list:
    """Replace ``owner.name`` (a function, through ``monkeypatch``) by one that counts its calls and, at call number
    ``interrupt_at``, raises KeyboardInterrupt (a Ctrl-C in the middle of a run) instead of calling it; returns the
    list of calls (one item each). Counting again wraps the original function, not an earlier count."""
    real = getattr(getattr(owner, name), "counted_original", getattr(owner, name))
    calls: list = []

    def counted(*args, **kwargs):
        calls.append(1)
        if len(calls) == interrupt_at:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    counted.counted_original = real
    monkeypatch.setattr(owner, name, counted)
    return calls


def hash_held_back(monkeypatch, name: str, owner, attribute: str, interrupt_at: int) -> list[str]:
    """Hold back the SHA-256 of the input file called ``name`` (``cmax.io.window_store.file_sha256``, through
    ``monkeypatch``) until ``owner.attribute`` (the run's own work: a window's fit, a forward pass) has been called,
    waiting at most 60 s; that call is counted by :func:`counted_calls`, a Ctrl-C at call ``interrupt_at``. Returns
    the order of what happened: ``attribute`` at each call, ``"hashed"`` when the held-back hash is done."""
    import threading

    import cmax.io.window_store as window_store

    real, working, order = window_store.file_sha256, threading.Event(), []

    def held_back(path, read=None):
        if os.path.basename(path) == name:
            working.wait(60)
            order.append("hashed")
        return real(path, read)

    monkeypatch.setattr(window_store, "file_sha256", held_back)
    counted_calls(monkeypatch, owner, attribute, interrupt_at=interrupt_at)
    counted = getattr(owner, attribute)

    def called(*args, **kwargs):
        order.append(attribute)
        working.set()
        return counted(*args, **kwargs)

    monkeypatch.setattr(owner, attribute, called)
    return order


def hashing_threads() -> list:
    """The threads hashing a run's inputs (``cmax.io.window_store.PendingSignatures``) that are still alive."""
    import threading

    return [thread for thread in threading.enumerate() if thread.name == "cmax-hash-inputs"]


def sigterm_once(argv: list[str], folder: Path, pattern: str, what: str, *, signum: int | None = None,
                 preexec_fn=None, group: bool = False) -> tuple[int, str]:
    """Run ``argv`` in a subprocess, send it SIGTERM (or ``signum``) as soon as ``folder`` holds a file matching
    ``pattern`` (its private temporary or stage), and return its exit status and stderr. Fails when the run ends
    first (``what``: what it should have been doing). ``preexec_fn``: as :class:`subprocess.Popen`'s. ``group``:
    the run starts a session of its own and the signal goes to its whole process group (its workers too), as a
    batch system or a closed terminal sends it."""
    import signal
    import subprocess
    import time

    process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                               preexec_fn=preexec_fn, start_new_session=group)
    deadline = time.monotonic() + 120
    while not list(folder.glob(pattern)) and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    assert process.poll() is None, f"the run ended before {what}"
    signum = signal.SIGTERM if signum is None else signum
    os.killpg(process.pid, signum) if group else process.send_signal(signum)
    _, err = process.communicate(timeout=120)
    return process.returncode, err


def sigkill_after(argv: list[str], folder: Path, pattern: str, count: int) -> bool:
    """Run ``argv`` in a subprocess and SIGKILL it (no clean-up) as soon as ``folder`` holds ``count`` files
    matching ``pattern``; True once it is killed, False when the run ended first (a very fast machine)."""
    import signal
    import subprocess
    import time

    process = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while len(list(folder.glob(pattern))) < count and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.001)
    if process.poll() is not None:
        return False
    process.send_signal(signal.SIGKILL)
    process.wait(timeout=60)
    return True


@pytest.fixture(scope="session")
def slider_file(tmp_path_factory) -> Path:
    """0.3 s of a small slider scene (64x48) with its ground truth (gt/K, gt/poses), as `cmax scene` writes it."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("slider", seed=1, width=64, height=48, duration_s=1.0, texture_size=64)
    sequence = simulate_scene(scene, 0.3, EventSimulator(**{**scene.recommended_simulator, "seed": 1}),
                              depth_rate_hz=10)
    return sequence.save(tmp_path_factory.mktemp("new_user") / "slider.h5")


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """A checkpoint of a tiny network (width 2, one level, windows of 50 ms)."""
    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config, DataConfig
    from learned.model import DepthPoseNet, ModelConfig

    config = Config(model=ModelConfig(width=2, levels=1), data=DataConfig(window_us=50_000))
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt",
                           {"model": DepthPoseNet(config.model).state_dict(), "optimizer": {}, "step": 0,
                            "config": config.to_dict(), "rng": rng_state()})


#: MVSEC's indoor_flying left camera (camchain-imucam-indoor_flying.yaml, cam0: a Kalibr equidistant fisheye with
#: its rectification and projection), as public MVSEC loaders give it; the tests of calibration files share it.
MVSEC_LEFT_CAMCHAIN = """cam0:
  T_cam_imu:
  - [1.0, 0.0, 0.0, 0.0]
  - [0.0, 1.0, 0.0, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  - [0.0, 0.0, 0.0, 1.0]
  cam_overlaps: [1]
  camera_model: pinhole
  distortion_coeffs: [-0.048031442223833355, 0.011330957517194437, -0.055378166304281135, 0.021500973881459395]
  distortion_model: equidistant
  intrinsics: [226.38018519795807, 226.15002947047415, 173.6470807871759, 133.73271487507847]
  resolution: [346, 260]
  rostopic: /davis/left/image_raw
  projection_matrix:
  - [199.6530123165822, 0.0, 177.43276376280926, 0.0]
  - [0.0, 199.6530123165822, 126.81215684365904, 0.0]
  - [0.0, 0.0, 1.0, 0.0]
  rectification_matrix:
  - [0.999877311526236, 0.015019439766575743, -0.004447282784398257]
  - [-0.014996983873604017, 0.9998748347535599, 0.005040367172759556]
  - [0.004522429630305261, -0.004973052949604937, 0.9999774079320989]
"""
