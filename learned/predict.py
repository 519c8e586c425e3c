"""``cmax depth FILE -o OUT/`` (also ``python -m learned.predict``): depth and twist of every window of an event file.

Reads any format :func:`cmax.io.read` reads (a DSEC-layout h5 through :class:`cmax.io.H5Reader`,
one window at a time; the other formats decoded whole), cuts it into consecutive windows of the
checkpoint's length (``--window``; a recording shorter than one window gives one window over the
whole recording), builds each window's event volume (that of :func:`cmax.representations.voxel_grid`,
as in training, by the compiled :func:`learned.volume.event_volume`) and runs the network on ``--batch`` windows at a time. Writes, atomically, in
``OUT/``:

* ``window_<k>.npz`` for window ``k`` (its position in the recording; windows with fewer than
  :data:`MIN_EVENTS` events are skipped): ``depth`` (H, W) float32 [m], ``inverse_depth``
  (H, W) float32 [1/m], ``twist`` (6,) float32 ``(v [m/s], omega [rad/s])`` in the camera
  frame, ``t0_us``, ``t1_us`` [µs] and ``K`` (3, 3) [px];
* ``window_<k>.png``: the depth with a colour bar in metres and the window's time in its title (s after the
  recording's first event, as ``--t0``/``--t1``),
  one colour scale for the whole run (``--depth-range``, default the 1st-99th percentiles of the depths
  of all its windows, drawn once every window is predicted);
* ``twists.csv`` (one line per window) and ``summary.json`` (inputs, settings, notes, counts).

One run at a time holds ``OUT/`` (a second one is refused at once); the results appear in ``OUT/`` when every
one of them is written, so a failed run leaves the folder as it was (:func:`run_prediction`).

Intrinsics come from ``--K`` (with ``--distortion``, the events are undistorted first), ``--calib`` (whose
distortion, when it has one, undistorts the events first) or the file's own ``gt/K``. The network is fully
convolutional and runs at any sensor size, but the depth it reads from the events' motion assumes the camera it
was trained with: a sensor size or focal length unlike the one in the checkpoint's card
(:mod:`learned.pretrained`, or the card ``learned.train`` stores in its checkpoints:
:func:`learned.evaluate.load_network`) is noted once, as is a window of another length than the checkpoint's
(:func:`window_note`). The checkpoint defaults to the model shipped in the package.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import numpy as np

from cmax._args import ArgumentParser, add_duration_options, float_list, positive_int, run_main
from cmax.cli.recording import (RAW_DSEC_AS_RECORDED, RAW_DSEC_CALIB, add_camera_options, add_recording_arguments,
                                calibration_note, check_calibration_camera, check_calibration_of_frames,
                                check_file_principal_point, given_k_note, no_intrinsics_message, tail_note,
                                time_span_us)
from cmax.io.provenance import check_calibrated_frames, check_raw_dsec
from cmax.events import window_starts
from cmax.io import Calibration, read_calibration, run_folder
from learned.kept_windows import KEPT_FOLDER, KeptBlocks

if TYPE_CHECKING:  # torch is imported only to predict (the parser is built at start-up)
    from cmax.camera import Camera
    from cmax.events import Events
    from learned.model import DepthPoseNet, ModelConfig

__all__ = ["MIN_EVENTS", "Recording", "DepthRun", "open_recording", "time_bounds", "window_plan", "camera_notes",
           "window_note",
           "event_volumes", "forward", "WindowPrediction", "predict_windows",
           "window_picture", "write_window", "earlier_results", "FOLDER_LOCK", "DEFAULT_BATCH", "MAX_BATCH_BYTES",
           "batch_bytes", "batch_that_fits", "SUMMARY_UNITS", "completed_record",
           "run_prediction", "predict_file", "add_arguments",
           "run", "main"]

#: Windows with fewer events are skipped (counted in the summary).
MIN_EVENTS = 10
#: The private folders of a run's results: ``out/.depth.<16 hex>.partial`` (:mod:`cmax.io.run_folder`).
_STAGE_PREFIX = "depth"
#: The lock a run holds on its output folder (:func:`cmax.io.run_folder.staged_run`), inside that folder: the same
#: lock as ``cmax fit`` and ``cmax emvs`` take, so that no two of them write into one folder at once.
FOLDER_LOCK = run_folder.FOLDER_LOCK
_CSV_HEADER = "window,t0_us,t1_us,events,vx,vy,vz,wx,wy,wz"
#: The units and frames of what a run writes, keyed by field or column (``summary.json``'s ``units``, as
#: ``cmax fit`` writes its own): twists.csv's header names its columns without them.
SUMMARY_UNITS = {
    "twists.csv vx, vy, vz": "m/s, camera frame (x right, y down, z forward)",
    "twists.csv wx, wy, wz": "rad/s, camera frame (x right, y down, z forward)",
    "twists.csv t0_us, t1_us; start_us, end_us": "µs on the file's clock (a window's ends; the span of the run)",
    "window_us": "µs",
    "t0_s, t1_s": "s after the first event (--t0, --t1)",
    "depth_range_m": "m: the colour scale of window_*.png (the depth itself is not bounded by it)",
    "K": "px: the pinhole of the pixels the network saw (with --calib of a rectified camera: the rectified frame's, "
         "in which the twists and depth maps are too, as in cmax fit's summary)",
    "window_NNNNN.npz": "depth (H, W) [m], inverse_depth (H, W) [1/m], twist (6,) (v [m/s], omega [rad/s], camera "
                        "frame), t0_us, t1_us [µs], K [px]",
}
#: Windows per forward pass when ``batch`` is not given (fewer where they would exceed :data:`MAX_BATCH_BYTES`).
DEFAULT_BATCH = 8
#: The most memory [bytes] one forward pass may take by :func:`batch_bytes`'s estimate (4 GiB): a ``batch`` of
#: windows that would take more is refused before any window is read. A module attribute: raise it deliberately
#: on a machine (or a GPU) with the memory for more.
MAX_BATCH_BYTES = 4 << 30


@dataclass(frozen=True, eq=False)
class Recording:
    """An event file opened for reading window by window.

    Attributes
    ----------
    path : Path
    format : str
        One of :data:`cmax.io.FORMATS`.
    width, height : int
        Sensor size [px].
    first_us, last_us : int
        Times of its first and last event [µs].
    K : ndarray (3, 3) or None
        The file's own intrinsics (``gt/K`` of an h5 file) [px], validated.
    window : callable
        ``window(t0_us, t1_us) -> Events`` with ``t0_us <= t < t1_us``.
    close : callable
        Releases the file.
    """

    path: Path
    format: str
    width: int
    height: int
    first_us: int
    last_us: int
    K: np.ndarray | None
    window: Callable[[int, int], "Events"]
    close: Callable[[], None]


def open_recording(path: str | Path, *, size: tuple[int, int] | None = None, time_unit: str | None = None,
                   polarity: str | None = None, t0_s: float | None = None,
                   t1_s: float | None = None, sort: bool = False, camera: str | None = None) -> Recording:
    """Open the event file at ``path``, of any format :func:`cmax.io.read` reads.

    ``size`` (width, height) [px], ``time_unit``, ``polarity`` and ``sort`` as :func:`cmax.io.read` takes them
    (for files that do not state them; never guessed); ``camera``: an MVSEC file's ``'left'`` (default) or
    ``'right'`` camera (refused for other files). A DSEC-layout h5 file is read window by
    window (:class:`cmax.io.H5Reader`), and so is a structured ``.npy`` (not ``sort``: only each window's rows
    are read); a Prophesee RAW file with ``t0_s`` / ``t1_s`` (seconds after its
    first event, as ``--t0`` / ``--t1``) is decoded holding only that span (its ``first_us`` stays the
    file's), and one too long to hold (:data:`cmax.events.MAX_EVENTS`) window after window
    (:class:`cmax.io.prophesee.RawWindows`); other formats are decoded whole. Raises FileNotFoundError,
    :class:`cmax.io.FormatError` or ValueError (one line each) for a missing, unreadable or empty file.
    """
    from cmax.cli.recording import file_span_us
    from cmax.io.provenance import h5_intrinsics
    from cmax.events import EventLimitError
    from cmax.io import H5Reader, check_sortable, detect_format, read
    from cmax.io.prophesee import RawWindows

    path = Path(path)
    kind = detect_format(path)
    check_sortable(path, kind, sort)
    width, height = size if size is not None else (None, None)
    options = {} if polarity is None else {"polarity": polarity}
    if camera is not None:
        if kind != "mvsec":
            raise ValueError(f"camera={camera!r} (cmax: --camera) applies to MVSEC files (a left and a right "
                             f"camera); {path} is a {kind} file of one camera")
        options["camera"] = camera
    if kind == "dsec":
        reader = H5Reader(path, width=width, height=height, time_unit=time_unit, **options)
        try:
            K = h5_intrinsics(reader.file, path)
            first, last = reader.t_start, reader.t_end   # "holds no events" when empty
        except BaseException:
            reader.close()
            raise
        return Recording(path, kind, reader.width, reader.height, first, last, K, reader.window, reader.close)
    if kind == "npy" and not sort:    # its windows' rows alone, by a binary search of its memory-mapped times
        return _npy_recording(path, width, height, time_unit, options)
    first = None
    if kind == "raw":      # a span of it decoded alone (a DSEC-layout h5 file is read window by window above)
        span = file_span_us(path, dict(width=width, height=height, time_unit=time_unit, **options), t0_s, t1_s)
        if span is not None:
            first, options = span[0], {**options, "t0_us": span[1], "t1_us": span[2]}
    try:
        events = read(path, width=width, height=height, time_unit=time_unit, sort=sort, **options)
    except EventLimitError:
        if kind != "raw":
            raise
        windows = RawWindows(path, width=width, height=height)
        if not windows.count:
            raise ValueError(f"{path} holds no events") from None
        return Recording(path, kind, windows.width, windows.height, windows.first_us, windows.last_us, None,
                         windows.window, windows.close)
    if len(events) == 0:
        if first is not None:
            raise ValueError(f"{path}: no events between --t0 {t0_s} s and --t1 {t1_s} s")
        raise ValueError(f"{path} holds no events")
    return Recording(path, kind, events.width, events.height, int(events.t[0]) if first is None else first,
                     int(events.t[-1]), None, events.slice_time, lambda: None)


def _npy_recording(path: Path, width: int | None, height: int | None, time_unit: str | None,
                   options: dict[str, Any]) -> Recording:
    """A structured ``.npy`` read window by window (:func:`cmax.io.read` with ``t0_us`` / ``t1_us`` reads only the
    window's rows), its span from its first and last rows (:func:`cmax.io.npy_time_span`)."""
    from cmax.io import npy_time_span, read

    def window(t0_us: int, t1_us: int) -> "Events":
        return read(path, width=width, height=height, time_unit=time_unit, t0_us=t0_us, t1_us=t1_us, **options)

    span = npy_time_span(path, time_unit=time_unit)
    if span is None:
        raise ValueError(f"{path} holds no events")
    first = window(span[0], span[0] + 1)     # the arguments checked as a whole read checks them, before any work
    return Recording(path, "npy", first.width, first.height, span[0], span[1], None, window, lambda: None)


def time_bounds(first_us: int, last_us: int, t0_s: float | None, t1_s: float | None) -> tuple[int, int]:
    """``(start, end)`` [µs], both inclusive: the part of a recording from ``t0_s`` to ``t1_s`` seconds after
    its first event (None: its first / last event) of a recording whose events span ``first_us`` to ``last_us``
    [µs], :func:`cmax.cli.recording.time_span_us` with its end made
    inclusive and clipped to the recording. ValueError when that part is empty or out of the recording."""
    start, stop = time_span_us(first_us, last_us, t0_s, t1_s)
    if start > last_us:
        raise ValueError(f"--t0 {t0_s} s is past the recording's last event ({(last_us - first_us) * 1e-6:.6f} s "
                         "after its first)")
    end = min(last_us, stop - 1)
    if end < start:
        raise ValueError(f"--t1 {t1_s} s leaves no time to predict")
    return start, end


def window_plan(start_us: int, end_us: int, window_us: int, *, explicit: bool) -> tuple[int, np.ndarray, str | None]:
    """``(window_us, starts (N,) int64 [µs], note)``: consecutive windows ``[t0, t0 + window_us)`` from
    ``start_us`` that fit in ``[start_us, end_us]`` (inclusive).

    A span shorter than ``window_us`` gives one window over the whole span with a note when the window is
    the checkpoint's (``explicit`` False), and a ValueError when the caller asked for it (``--window``). What
    the whole windows of a longer span leave out at its end: :func:`cmax.cli.recording.tail_note`.
    """
    if window_us < 1:
        raise ValueError(f"the window must be at least 1 µs long, got {window_us} µs")
    span = end_us - start_us + 1
    if window_us <= span:
        return window_us, window_starts(start_us, end_us, window_us, window_us), None
    if explicit:
        raise ValueError(f"--window {window_us * 1e-6:g} s is longer than the events to predict "
                         f"({span * 1e-6:.6f} s); give a shorter one, or leave --window out for one window over "
                         "the whole recording")
    note = (f"the recording ({span * 1e-3:.1f} ms) is shorter than the model's window ({window_us * 1e-3:.1f} ms): "
            "predicting one window over the whole recording (less motion per window than in training: its depth "
            "may be biased)")
    return span, np.array([start_us], dtype=np.int64), note


def _card_numbers(card: dict, key: str, count: int, where: str) -> list[float] | None:
    values = card.get(key)
    if values is None:
        return None
    if (not isinstance(values, list) or len(values) != count
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0
                       for v in values[:2])):
        raise ValueError(f"{where}: \"{key}\" must be a list of {count} numbers, got {values!r}")
    return [float(v) for v in values]


def window_note(trained_us: int, window_us: int, tolerance: float = 0.05) -> str | None:
    """A note for windows of ``window_us`` [µs] more than ``tolerance`` (a fraction) longer or shorter than the
    ``trained_us`` [µs] the network was trained on (its config's ``data.window_us``); None otherwise. The network
    reads depth and motion from the image motion over a window, which scales with its length, as with the focal
    length (:func:`camera_notes`).

    >>> window_note(166_500, 166_500) is None
    True
    >>> window_note(166_500, 50_000)[:60]
    'the network was trained on windows of 166.5 ms, these are 50'
    """
    ratio = window_us / trained_us
    if abs(ratio - 1.0) <= tolerance:
        return None
    return (f"the network was trained on windows of {trained_us * 1e-3:g} ms, these are {window_us * 1e-3:g} ms: the "
            f"image motion over a window scales with its length ({ratio:.3g}x a training window's), and the depth "
            f"and speed the network infers from it assume the trained length")


def camera_notes(card: dict | None, width: int, height: int, K: np.ndarray, where: str = "the card") -> list[str]:
    """Notes on how this camera differs from the one the network was trained with (from its card:
    ``"size": [W, H]`` [px], ``"K": [fx, fy, cx, cy]`` [px]), on a principal point off this sensor (the
    intrinsics of another camera?) and on a K unlike any camera's (:func:`cmax.camera.intrinsics_oddity`: the
    numbers in another order?); empty when they agree or nothing is recorded. ``width``, ``height``: this
    sensor's size [px]; ``K`` (3, 3): its intrinsics [px]; ``where``: how the notes name the card.

    >>> import numpy as np
    >>> K = np.array([[200.0, 0, 32], [0, 200, 24], [0, 0, 1]])
    >>> camera_notes(None, 64, 48, K)
    []
    >>> camera_notes(None, 1280, 720, K)[0][:48]          # 64x48's K on a 1280x720 sensor: its corner
    'K (fx 200, fy 200, cx 32, cy 24) is unlike a cam'
    >>> camera_notes(None, 32, 24, np.array([[200.0, 0, 640], [0, 200, 360], [0, 0, 1]]))[0][:56]
    'the principal point (640.0, 360.0) px lies off the 32x24'
    """
    from cmax.camera import intrinsics_oddity

    notes = []
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (0 <= cx <= width and 0 <= cy <= height):
        notes.append(f"the principal point ({cx:.1f}, {cy:.1f}) px lies off the {width}x{height} sensor: are these "
                     "the intrinsics of this camera?")
    elif (oddity := intrinsics_oddity(K, width, height)) is not None:
        notes.append(oddity)
    if not card:
        return notes
    size = _card_numbers(card, "size", 2, where)
    if size is not None and (int(size[0]), int(size[1])) != (width, height):
        notes.append(f"the network was trained on a {int(size[0])}x{int(size[1])} sensor, this file is {width}x{height}: "
                     "it is fully convolutional and runs at any size, but its depth assumes the trained camera")
    trained = _card_numbers(card, "K", 4, where)
    if trained is not None:
        ratio = float(K[0, 0]) / trained[0]
        if abs(ratio - 1.0) > 0.05:
            notes.append(f"the focal length here is {K[0, 0]:.1f} px, the network was trained at {trained[0]:.1f} px: "
                         f"the depth it infers from image motion scales with it (to first order, true depth = "
                         f"predicted x {ratio:.3g})")
    return notes


def event_volumes(windows: Sequence["Events"], bins: int,
                  pixels: Sequence[np.ndarray | None] | None = None) -> np.ndarray:
    """The network input of each of ``windows``: (B, bins, H, W) float32, the event volume over each window's own
    first..last event time, as :func:`learned.data.to_item` builds it in training with
    :func:`cmax.representations.voxel_grid`; computed by the compiled :func:`learned.volume.event_volume`,
    which equals it to float32 rounding and is faster (``benchmarks/results/speed_learned.md``). ``pixels``: for
    each window, None or its events' exact positions (N, 2) float64 [px] (undistorted and rectified:
    :meth:`cmax.Camera.undistorted_pixels`), spread bilinearly by ``voxel_grid(..., pixels=)``."""
    from cmax.representations import voxel_grid
    from learned.volume import event_volume

    pixels = [None] * len(windows) if pixels is None else pixels
    return np.stack([event_volume(events, bins) if xy is None else voxel_grid(events, bins, pixels=xy)
                     for events, xy in zip(windows, pixels)])


def batch_bytes(config: "ModelConfig", width: int, height: int, batch: int) -> int:
    """An upper estimate of the memory [bytes] of one forward pass of ``batch`` windows of ``width x height`` px
    through a network of ``config`` (its ``bins``, ``width``, ``space_to_depth`` and ``odd_twist``).

    Per pixel and window, in 4-byte numbers: ``2 * bins`` for the event volume and its copy on the way in,
    8 for the full-resolution outputs, and ``16 * width`` for the U-Net's feature maps per pixel of its finest
    level (a quarter of the pixels with ``space_to_depth``): the feature maps of the levels below halve, and a
    level holds its skip, its block's two convolutions and the decoder's concatenation. With ``odd_twist`` the
    volume and the feature maps count twice (the window played backwards goes through the encoder too).

    >>> from learned.model import ModelConfig
    >>> round(batch_bytes(ModelConfig(width=16, space_to_depth=True), 640, 480, 8) / 2**30, 2)   # 82 numbers a pixel
    0.75
    >>> batch_bytes(ModelConfig(width=16), 640, 480, 8) == 8 * batch_bytes(ModelConfig(width=16), 640, 480, 1)
    True
    """
    finest = 0.25 if config.space_to_depth else 1.0
    encoded = 2 if config.odd_twist else 1   # odd_twist: the encoder also runs on each window played backwards
    numbers = encoded * (2 * config.bins + 16 * config.width * finest) + 8
    return int(round(int(batch) * int(width) * int(height) * numbers * 4))


def batch_that_fits(config: "ModelConfig", width: int, height: int, batch: int | None) -> int:
    """The windows of ``width x height`` px per forward pass through a network of ``config``: ``batch``, or
    :data:`DEFAULT_BATCH` (fewer where that many would exceed :data:`MAX_BATCH_BYTES`) when None. ValueError naming ``batch`` (``--batch``) when the given one, or a single
    window, would take more than :data:`MAX_BATCH_BYTES` by :func:`batch_bytes`'s estimate, with the largest
    batch that fits; the results do not depend on the batch."""
    one = batch_bytes(config, width, height, 1)
    fits = MAX_BATCH_BYTES // one
    limit = f"learned.predict.MAX_BATCH_BYTES ({MAX_BATCH_BYTES / 2**30:g} GiB)"
    if fits < 1:
        raise ValueError(f"one window of {width}x{height} px takes about {one / 2**30:.1f} GiB in the network (an upper "
                         f"estimate), more than {limit}: a sensor this large does not fit; raise "
                         "learned.predict.MAX_BATCH_BYTES deliberately if the memory is there")
    if batch is None:
        return int(min(DEFAULT_BATCH, fits))
    if batch > fits:
        raise ValueError(f"batch={batch} (--batch) windows of {width}x{height} px take about "
                         f"{batch * one / 2**30:.1f} GiB in the network (an upper estimate), more than {limit}: give "
                         f"--batch {fits} or fewer (the results do not depend on it), or raise "
                         "learned.predict.MAX_BATCH_BYTES deliberately if the memory is there")
    return int(batch)


def forward(model: "DepthPoseNet", volumes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(inverse depth (B, H, W) float32 [1/m], twist (B, 6) float32 (v [m/s], omega [rad/s]))`` of the network
    ``model`` on event volumes ``volumes`` (B, bins, H, W) float32, on the device of its weights (on the CPU with the
    threads :func:`cmax._threads.torch_threads` allows now). torch's failure to allocate (on the CPU or the GPU) is
    raised as a one-line MemoryError naming the batch."""
    import torch

    from cmax._threads import torch_threads_scope

    device = next(model.parameters()).device
    try:
        with torch_threads_scope(volumes.size * model.config.width), torch.inference_mode():
            out = model(torch.from_numpy(np.ascontiguousarray(volumes, np.float32)).to(device))
    except RuntimeError as error:     # torch.OutOfMemoryError (a GPU) is one too
        if not _out_of_memory(error):
            raise
        batch, _, height, width = volumes.shape
        raise MemoryError(f"the network ran out of memory on {device} with {batch} windows of {width}x{height} px at "
                          "once: give a smaller --batch") from None
    return out.inverse_depth[:, 0].cpu().numpy().copy(), out.twist.cpu().numpy().copy()


def _out_of_memory(error: RuntimeError) -> bool:
    """Whether ``error`` is torch's failure to allocate (``DefaultCPUAllocator: can't allocate memory``, CUDA's
    ``out of memory``)."""
    import torch

    text = str(error)
    return (isinstance(error, getattr(torch, "OutOfMemoryError", ())) or "can't allocate memory" in text
            or "out of memory" in text.lower())


@dataclass(frozen=True, eq=False)
class WindowPrediction:
    """The network's output for one window.

    Attributes
    ----------
    index : int
        Position of the window in the recording (0 from the first start).
    t0_us, t1_us : int
        Window bounds [µs].
    events : int
        Events in the window.
    inverse_depth : ndarray (H, W) float32
        [1/m].
    twist : ndarray (6,) float32
        ``(v [m/s], omega [rad/s])``, camera frame.
    """

    index: int
    t0_us: int
    t1_us: int
    events: int
    inverse_depth: np.ndarray
    twist: np.ndarray


def predict_windows(model: "DepthPoseNet", window: Callable[[int, int], "Events"], starts: Sequence[int],
                    window_us: int, *, batch: int = 8,
                    transform: Callable[["Events"], "Events"] | None = None,
                    source: str = "the network", offset: int = 0,
                    camera: "Camera | None" = None) -> Iterator[WindowPrediction | None]:
    """For each of ``starts`` [µs] in order: the :class:`WindowPrediction` of the network ``model`` on
    ``[t0, t0 + window_us)``, or None when the
    window (read with ``window(t0, t1)``, then ``transform``) holds fewer than :data:`MIN_EVENTS` events.
    ``camera`` (a :class:`cmax.Camera` of the sensor, in place of ``transform``): the events are undistorted
    (and rectified) by it, and the volume spreads each one bilinearly from its exact position
    (:meth:`cmax.Camera.undistort_events_and_pixels`).
    ``batch`` windows go through the network at a time. ``offset``: the index of the first of ``starts`` in the
    recording (``WindowPrediction.index`` is ``offset`` plus the place in ``starts``).

    A window whose inverse depth or twist holds a NaN or an infinity (finite weights that overflow, e.g. a
    diverged run's saved just before its loss went non-finite) raises ``ValueError`` naming ``source`` (the
    checkpoint) and the window: such an output is never yielded, so never written as a depth map."""
    for first in range(0, len(starts), batch):
        chunk, positions = [], []
        for index in range(first, min(first + batch, len(starts))):
            t0 = int(starts[index])
            events = window(t0, t0 + window_us)
            events = events if transform is None else transform(events)
            xy = None
            if camera is not None and not camera.is_pinhole:
                events, xy, _ = camera.undistort_events_and_pixels(events)
            chunk.append((offset + index, t0, events if len(events) >= MIN_EVENTS else None))
            positions += [xy] if len(events) >= MIN_EVENTS else []
        kept = [events for _, _, events in chunk if events is not None]
        outputs = (iter(zip(*forward(model, event_volumes(kept, model.config.bins, positions)))) if kept
                   else iter(()))
        for index, t0, events in chunk:
            if events is None:
                yield None
            else:
                inverse, twist = next(outputs)
                if not (np.isfinite(inverse).all() and np.isfinite(twist).all()):
                    share = float(np.mean(~np.isfinite(inverse)))
                    raise ValueError(
                        f"{source} gives a non-finite output on window {index} ({t0}-{t0 + window_us} µs, "
                        f"{len(events):,} events): {share:.0%} of its inverse depth and "
                        f"{int(np.sum(~np.isfinite(twist)))} of 6 twist components are NaN or infinite; its weights "
                        "overflow on these events (a diverged or corrupt checkpoint?): nothing was written")
                yield WindowPrediction(index, t0, t0 + window_us, len(events), inverse, twist)


def window_picture(depth: np.ndarray, scale, title: str) -> np.ndarray:
    """The picture (titled ``title``) of a window's ``depth`` (H, W) [m]: :func:`cmax.viz.depth_panel` on ``scale``
    (a :class:`cmax.viz.DepthScale` or ``(near, far)`` [m]), each pixel a
    ``z x z`` block when the sensor is narrower than :data:`cmax.viz.MIN_PICTURE_WIDTH`
    (``z = cmax.viz.readable_zoom(W)``).

    >>> import numpy as np
    >>> window_picture(np.ones((48, 64), np.float32), (0.5, 60.0), "depth").shape[1] >= 5 * 64
    True
    """
    from cmax import viz

    return viz.depth_panel(viz.enlarge(depth, viz.readable_zoom(depth.shape[1])), scale, title)


#: Depths per window that :func:`run_prediction` keeps for the run's colour scale (an even subsample of the map).
SCALE_SAMPLES = 4096


def write_window(out: Path, prediction: WindowPrediction, K: np.ndarray) -> tuple[str, np.ndarray]:
    """Write ``window_<k>.npz`` of ``prediction`` (a :class:`WindowPrediction`) and the intrinsics ``K`` (3, 3) [px]
    (atomically) into ``out``; returns the window's ``twists.csv`` line and up to
    :data:`SCALE_SAMPLES` of its depths [m] (an even subsample, every depth of a small map) for
    :func:`run_scale`. The picture comes later (:func:`draw_window`), on the run's scale."""
    from cmax.io.atomic import save_npz_atomic

    p = prediction
    depth = (1.0 / p.inverse_depth).astype(np.float32)
    save_npz_atomic(out / f"window_{p.index:05d}.npz", depth=depth, inverse_depth=p.inverse_depth.astype(np.float32),
                    twist=p.twist.astype(np.float32), t0_us=np.int64(p.t0_us), t1_us=np.int64(p.t1_us),
                    K=np.asarray(K, float))
    sample = depth_sample(depth)
    line = ",".join([str(p.index), str(p.t0_us), str(p.t1_us), str(p.events)] + [f"{v:.6g}" for v in p.twist])
    return line, sample


def depth_sample(depth: np.ndarray) -> np.ndarray:
    """Up to :data:`SCALE_SAMPLES` of the depths ``depth`` (H, W) [m] of a window, an even subsample (every depth
    of a small map), for :func:`run_scale`.

    >>> depth_sample(np.ones((480, 640), np.float32)).shape
    (4096,)
    """
    flat = depth.ravel()
    return flat[::-(-flat.size // SCALE_SAMPLES)]


def run_scale(samples: list[np.ndarray], depth_range: tuple[float, float] | None):
    """The colour scale of every picture of a run: ``depth_range`` [m] when given, else the 1st-99th
    percentiles of the windows' sampled depths (:meth:`cmax.viz.DepthScale.from_depths`).

    >>> import numpy as np
    >>> run_scale([np.array([1.0, 2.0]), np.array([3.0])], (0.5, 9.0))
    DepthScale(near=0.5, far=9.0)
    >>> run_scale([np.linspace(1.0, 3.0, 101), np.linspace(2.0, 4.0, 101)], None)   # pooled: 1.0-4.0
    DepthScale(near=1.0402, far=3.9598)
    """
    from cmax import viz

    if depth_range is not None:
        return viz.DepthScale(*depth_range)
    return viz.DepthScale.from_depths(samples)


def draw_window(out: Path, index: int, scale, origin_us: int = 0) -> None:
    """``window_<index>.png`` (atomically) from its ``.npz`` in ``out``: the depth on ``scale`` (the run's
    :class:`cmax.viz.DepthScale`), the window's time in the title in s after ``origin_us`` [µs] (the recording's
    first event, the origin of ``--t0``/``--t1`` and of the titles of ``cmax fit`` and ``cmax show``; the
    ``.npz`` keeps the file's clock)."""
    from cmax import viz

    name = f"window_{index:05d}"
    with np.load(out / f"{name}.npz") as saved:
        depth, t0_us, t1_us = saved["depth"], int(saved["t0_us"]), int(saved["t1_us"])
    title = f"window {index}, {(t0_us - origin_us) * 1e-6:.3f}-{(t1_us - origin_us) * 1e-6:.3f} s, depth [m]"
    viz.save_png(out / f"{name}.png", window_picture(depth, scale, title))


@dataclass(frozen=True)
class DepthRun:
    """What :func:`run_prediction` did: ``windows`` written and ``skipped``, the window length ``window_us`` [µs],
    ``notes``, wall ``seconds`` and the ``output`` folder; ``complete``: the line saying that a ``resume`` found
    the same run's results complete in ``output`` (then the other fields are that run's, and nothing was done)."""

    windows: int
    skipped: int
    window_us: int
    notes: tuple[str, ...]
    seconds: float
    output: Path
    complete: str | None = None

    def summary_line(self) -> str:
        """The command's final line."""
        if self.complete is not None:
            return self.complete
        skipped = f", {self.skipped} skipped (fewer than {MIN_EVENTS} events)" if self.skipped else ""
        rate = self.windows / self.seconds if self.seconds > 0 else float("inf")
        noun = "window" if self.windows == 1 else "windows"
        return (f"{self.windows} {noun} of {self.window_us * 1e-3:g} ms predicted{skipped} in {self.seconds:.1f} s "
                f"({rate:.1f} windows/s); results in {self.output}")


def earlier_results(out: Path) -> list[Path]:
    """The files of an earlier :func:`run_prediction` in the folder ``out``: ``window_<k>.npz`` / ``.png`` (``k``
    five digits or more, as it names them), ``twists.csv``, ``summary.json``
    (:data:`cmax.io.run_folder.RESULT_NAMES`); empty when there are none (or no folder). Other files, such as a
    user's ``window_seat_photo.png``, are not."""
    return run_folder.run_results(out, ("depth",))


def _resolve_intrinsics(recording: Recording, K: np.ndarray | None) -> np.ndarray:
    if K is not None:
        return np.asarray(K, float)
    if recording.K is None:
        raise ValueError(no_intrinsics_message(recording.path))
    return recording.K


def _check_seconds(name: str, value: object, *, positive: bool) -> None:
    """TypeError / ValueError (one line naming ``name``) unless ``value`` is None or a finite number of seconds,
    > 0 (``positive``) or >= 0."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number of seconds, got {value!r} ({type(value).__name__})")
    if not (np.isfinite(value) and (value > 0 if positive else value >= 0)):
        raise ValueError(f"{name} must be a finite number of seconds {'> 0' if positive else '>= 0'}, got {value!r}")


def _check_arguments(K: object, window_s: object, t0_s: object, t1_s: object,
                     depth_range: object) -> np.ndarray | None:
    """:func:`run_prediction`'s checks of the arguments a caller can get wrong, before any work; returns ``K``
    as its checked (3, 3) matrix (None: none given)."""
    _check_seconds("window_s", window_s, positive=True)
    _check_seconds("t0_s", t0_s, positive=False)
    _check_seconds("t1_s", t1_s, positive=False)
    if depth_range is not None:
        from cmax import viz

        if isinstance(depth_range, (str, bytes)) or not hasattr(depth_range, "__len__") or len(depth_range) != 2:
            raise TypeError(f"depth_range must be (near, far) in metres, got {depth_range!r}")
        viz.DepthScale(*depth_range)   # 0 < near < far, finite numbers
    from cmax.camera import intrinsics_matrix

    return None if K is None else intrinsics_matrix(K)


def run_prediction(path: str | Path, out: str | Path, *, checkpoint: str | Path | None = None,
                   K: np.ndarray | None = None, calib: str | Path | None = None, calib_camera: str = "cam0",
                   distortion: np.ndarray | None = None, size: tuple[int, int] | None = None,
                   time_unit: str | None = None, polarity: str | None = None, sort: bool = False,
                   camera: str | None = None,
                   t0_s: float | None = None, t1_s: float | None = None, window_s: float | None = None,
                   depth_range: tuple[float, float] | None = None, batch: int | None = None, progress: bool = True,
                   note: Callable[[str], None] | None = None, overwrite: bool = False,
                   device: str = "cpu", resume: bool = False, as_recorded: bool = False) -> DepthRun:
    """Predict depth and twist for every window of the event file ``path`` into the folder ``out``.

    Parameters
    ----------
    checkpoint : path, optional
        A :mod:`learned.checkpoint` file (default: :func:`learned.pretrained.shipped_checkpoint`).
    K : array_like (3, 3) or (4,), optional
        Intrinsics [px], the pinhole matrix or ``[fx, fy, cx, cy]`` (checked as ``--K`` is:
        :func:`cmax.camera.intrinsics_matrix`); ``calib`` (ECD calib.txt or DSEC cam_to_cam.yaml, camera ``calib_camera``)
        instead; neither: the file's ``gt/K``. Events beside DSEC's ``rectify_map.h5`` (raw: distorted, not
        rectified) are refused without ``calib`` (:func:`cmax.io.provenance.check_raw_dsec`) unless ``as_recorded``.
    as_recorded : bool
        Take events that DSEC's ``rectify_map.h5`` beside them says are raw as they are, without ``calib``
        (``--as-recorded``).
    distortion : ndarray (4,) or (5,), optional
        OpenCV ``k1, k2, p1, p2[, k3]`` of ``K`` (with ``K`` only; a ``calib`` file brings its own): the
        events are undistorted (the volume spreads each one bilinearly from its exact undistorted position)
        before the network sees them.
    size, time_unit, polarity, sort, camera : as :func:`cmax.io.read` (for files that do not state them;
        ``camera``: an MVSEC file's ``'left'`` or ``'right'``; ``sort``: a
        file whose time goes back, sorted).
    t0_s, t1_s : float, optional
        Part to predict, seconds after the first event.
    window_s : float, optional
        Window length [s] (default: the checkpoint config's ``data.window_us``). ``window_s``, ``t0_s`` and
        ``t1_s`` must be finite numbers (``window_s`` > 0, the others >= 0), ``depth_range`` a pair of them.
    depth_range : (near, far) [m], optional
        Colour scale of every picture of the run, and nothing else: the predicted depth is neither clamped nor
        conditioned by it (default: the 1st-99th percentiles of all its windows' depths, :func:`run_scale`).
    batch : int, optional
        Windows per forward pass (default :data:`DEFAULT_BATCH`, fewer where they would exceed
        :data:`MAX_BATCH_BYTES`); a batch that would take more than :data:`MAX_BATCH_BYTES`
        (:func:`batch_bytes`'s estimate) is refused before any window is read (:func:`batch_that_fits`).
    device : str
        Where the network runs: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"auto"`` (a GPU when torch sees
        one); the events are read and their volumes built on the CPU.
    progress : bool
        A progress bar over the windows.
    note : callable, optional
        Receives each note (default: printed on stderr).
    overwrite : bool
        Replace the results of an earlier run in ``out`` (its ``window_<k>`` files, ``twists.csv``,
        ``summary.json``, or those of a ``cmax fit`` / ``cmax emvs`` run); without it such a folder is refused,
        as its windows would mix with this run's. Other files in ``out`` are never touched.
        The earlier results stay as they are until this run has succeeded.
    resume : bool
        Continue an interrupted run into ``out``: each finished block of windows (one forward pass) is kept in
        ``out/.depth.windows`` as it is done (:mod:`learned.kept_windows`); with ``resume`` the blocks of a run
        with the same file, checkpoint and options are taken after their files are checked, and the others
        predicted, in the same blocks (the results equal an uninterrupted run's). Another run's blocks are
        refused (ValueError naming what differs); without ``resume`` or ``overwrite`` a folder holding them is
        refused (FileExistsError); ``overwrite`` alone drops them. With both, the interrupted run is continued
        and an earlier complete run's results in ``out`` are replaced once it succeeds.

    The run holds ``out`` from its first look at it to its end (the lock ``out/.results.lock``,
    :data:`FOLDER_LOCK`, :func:`cmax.io.run_folder.staged_run`): a second run into the same folder meanwhile, or
    a ``cmax fit`` / ``cmax emvs`` run, is refused at once (:class:`cmax.io.atomic.OutputLockedError`, an
    OSError) and changes nothing; the results of those commands count as an earlier run's too. The results are
    written into a private folder ``out/.depth.<hex>.partial`` and moved into ``out`` once all of them are
    written (:func:`cmax.io.run_folder.publish`: the earlier ``summary.json`` removed first, the new one moved in
    last): a failed run leaves ``out`` as it was, one interrupted while its files move in leaves no
    ``summary.json`` (a killed run's private folder is removed by the next run).

    Raises FileNotFoundError, ValueError (including :class:`cmax.io.FormatError` and
    :class:`learned.checkpoint.CheckpointError`), OSError with a one-line message for every input a user can
    get wrong.
    """
    started = time.perf_counter()
    note = note or (lambda text: print(f"learned.predict: note: {text}", file=sys.stderr))
    K = _check_arguments(K, window_s, t0_s, t1_s, depth_range)
    if batch is not None and (isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1):
        raise ValueError(f"batch must be a whole number >= 1, got {batch!r}")
    from learned.device import resolve_device

    device = resolve_device(device)   # before any work
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"the output {out} is a file: give a folder (for window_*.npz, window_*.png, "
                              "twists.csv, summary.json)")
    try:
        with run_folder.staged_run(out, _STAGE_PREFIX, earlier_results, overwrite=overwrite,
                                   what="window_*.npz, twists.csv, ...", resume=resume) as stage:
            finished = run_folder.resumed_into_complete(out, resume=resume, overwrite=overwrite)
            run, kept = _predict_into(stage, path, checkpoint=checkpoint, K=K, calib=calib, calib_camera=calib_camera,
                                      distortion=distortion, size=size, time_unit=time_unit, polarity=polarity,
                                      sort=sort, camera=camera, t0_s=t0_s, t1_s=t1_s, window_s=window_s,
                                      depth_range=depth_range, batch=batch, progress=progress, note=note,
                                      device=device, resume=resume, overwrite=overwrite, as_recorded=as_recorded,
                                      finished=finished)
    except run_folder.ResultsComplete as complete:   # --resume of a run whose results are all in out
        summary = complete.summary
        return DepthRun(int(summary.get("windows", 0)), int(summary.get("skipped", 0)),
                        int(summary.get("window_us", 0)), (), time.perf_counter() - started, out, str(complete))
    kept.remove()   # the results are in out: the finished blocks are no longer needed
    return replace(run, seconds=time.perf_counter() - started, output=out)


def _predict_into(stage: Path, path: str | Path, *, checkpoint, K, calib, calib_camera, distortion, size,
                  time_unit, polarity, sort, camera, t0_s, t1_s, window_s, depth_range, batch, progress, note,
                  device, resume, overwrite, as_recorded=False, finished: dict | None = None
                  ) -> tuple[DepthRun, KeptBlocks]:
    """:func:`run_prediction`'s work, every result written into the empty folder ``stage`` (each block of windows
    kept as it is done, :class:`learned.kept_windows.KeptBlocks`, returned too)."""
    from tqdm.auto import tqdm

    from cmax import viz
    from cmax.io.atomic import write_text_atomic
    import functools

    from cmax.io.window_store import PendingSignatures, code_digest
    from learned.evaluate import load_network
    from learned.pretrained import card_limits, shipped_checkpoint

    started = time.perf_counter()
    checkpoint = Path(checkpoint) if checkpoint is not None else shipped_checkpoint()
    model, config, card = load_network(checkpoint)   # first: a refused checkpoint writes nothing
    model = model.to(device)
    explicit = window_s is not None
    window_us = int(config["data"]["window_us"]) if window_s is None else int(round(window_s * 1e6))
    if window_us < 1:
        raise ValueError(f"the window must be at least 1 µs long, got {window_us} µs")
    if depth_range is not None:
        viz.DepthScale(*depth_range)   # checked before any work
    calib_size = calibration = None
    if calib is None and calib_camera != "cam0":   # else taken and ignored: --K or the file's gt/K would be used
        raise ValueError(f"--calib-camera {calib_camera} chooses a camera of a --calib file (a DSEC cam_to_cam.yaml "
                         "or a Kalibr camchain): give --calib too")
    if distortion is not None:
        if K is None:
            raise ValueError("--distortion applies to --K: give both (a --calib file brings its own distortion)")
        distortion = np.asarray(distortion, float)
    if calib is not None:
        if K is not None:
            raise ValueError("give the intrinsics with --K or --calib, not both")
        calibration = read_calibration(calib, calib_camera)
        K, distortion, calib_size = calibration.K, calibration.distortion, calibration.size
        check_calibration_camera(calibration, calib, calib_camera, path, camera)
        if calib_size is None:   # the calibration of the frames a conversion resized: refused, the scaled K said
            check_calibration_of_frames(calib, K, distortion, path)
    elif not as_recorded:   # raw DSEC events (rectify_map.h5 beside them): K of no frame they lie in
        check_raw_dsec(path, RAW_DSEC_CALIB, RAW_DSEC_AS_RECORDED)
    hashing = None
    try:
        recording = open_recording(path, size=size, time_unit=time_unit, polarity=polarity, t0_s=t0_s, t1_s=t1_s,
                                   sort=sort, camera=camera)
    except ValueError as error:   # a file that stores no size: the calibration's resolution, when it has one
        if calib_size is None or size is not None or "width=" not in str(error):
            raise
        recording = open_recording(path, size=calib_size, time_unit=time_unit, polarity=polarity, t0_s=t0_s,
                                   t1_s=t1_s, sort=sort, camera=camera)
    try:
        if calib_size is not None and (recording.width, recording.height) != tuple(calib_size):
            raise ValueError(f"{calib} calibrates a {calib_size[0]}x{calib_size[1]} camera ({calib_camera}), the "
                             f"events come from a {recording.width}x{recording.height} sensor")
        if calib is not None and calib_size is None:
            check_calibrated_frames(calib, path, recording.width, recording.height)
        stated = K is not None
        K = _resolve_intrinsics(recording, K)
        given = given_k_note(path, K) if stated else None   # a K given over the file's own gt/K: said in a note
        # refused as cmax fit / emvs / learned.train refuse it: the network's depth assumes these pixels' K
        check_file_principal_point(K, path, recording.width, recording.height)
        batch = batch_that_fits(model.config, recording.width, recording.height, batch)   # before any window is read
        lens = calibration if calibration is not None else Calibration(K, distortion, None)
        lens_camera = None
        if lens.undistorts:   # the network sees the pixels of the pinhole the events are mapped to (rectified: its K)
            lens_camera = lens.camera(recording.width, recording.height, K)
            K = lens_camera.pinhole_K
        notes = [f"{checkpoint.name}: {limit}" for limit in card_limits(card, f"the card of {checkpoint}")]
        if calibration is not None and (said := calibration_note(calibration, calib, calib_camera, path)):
            notes.append(said)
        notes += camera_notes(card, recording.width, recording.height, K, f"the card of {checkpoint}")
        notes += [given] if given else []
        start, end = time_bounds(recording.first_us, recording.last_us, t0_s, t1_s)
        window_us, starts, short = window_plan(start, end, window_us, explicit=explicit)
        notes += [short] if short else []
        if (other := window_note(int(config["data"]["window_us"]), window_us)) is not None:
            notes.append(other)
        # the input files are hashed while the windows are predicted: the kept blocks wait for their signatures
        # only to compare them with an interrupted run's (resume) or to record them with the first block
        hashing = PendingSignatures({"file": path, "checkpoint": checkpoint, "calib": calib}, progress=progress)
        recorded = functools.partial(_run_record, path, checkpoint, calib, np.array(K), distortion, size, time_unit,
                                     polarity, sort, camera, t0_s, t1_s, window_us, len(starts), batch, device,
                                     progress, code=code_digest("cmax", "learned"))
        if finished is not None:   # --resume into complete results: the same run (nothing to do), or refused
            notes.append(run_folder.check_complete(   # the same run with files missing or changed: run again
                stage.parent, finished, completed_record(recorded(files=hashing.result()), depth_range),
                command="cmax depth"))
        for text in notes:
            note(text)
        kept = KeptBlocks(stage.parent, lambda: recorded(files=hashing.result()), resume=resume, overwrite=overwrite)
        # the same run's complete results with a file missing or changed: only the blocks that lost one run again
        adopted = kept.adopt(stage.parent, finished, len(starts), batch) if finished is not None else 0
        lines, skipped, samples, indices, blocks = [_CSV_HEADER], 0, [], [], []
        with tqdm(total=len(starts), desc="windows", unit="window", disable=not progress) as bar:
            for first in range(0, len(starts), batch):   # one forward pass each, kept once all its windows are
                block = starts[first:first + batch]
                done = kept.load(first)
                if done is None:
                    done = ([], [], 0)
                    for prediction in predict_windows(model, recording.window, block, window_us, batch=batch,
                                                      camera=lens_camera, source=str(checkpoint), offset=first):
                        bar.update(1)
                        if prediction is None:
                            done = (done[0], done[1], done[2] + 1)
                        else:
                            line, sample = write_window(stage, prediction, K)
                            done[0].append(prediction.index)
                            done[1].append(line)
                            samples.append(sample)
                    kept.save(first, *done, stage)
                else:
                    bar.update(len(block))
                    for index in done[0]:
                        kept.place(index, stage)
                        samples.append(depth_sample(kept.sample_of(index)))
                indices += done[0]
                blocks.append((first, done[0]))
                lines += done[1]
                skipped += done[2]
        kept.run     # every input hashed whole and unchanged (else refused) before the results are published
    finally:
        recording.close()
        if hashing is not None:    # stopped within one block, never left running
            hashing.close()
    if adopted:
        note(f"resumed: {adopted} of {len(indices)} windows taken from the complete results in {stage.parent} "
             "(each file as this run published it: summary.json's SHA-256); the others predicted again")
        notes.append(f"resumed: {adopted} windows taken from the complete results")
    if kept.resumed - adopted or kept.unverified:
        redone = f"; {kept.unverified} block(s) not verified, predicted again" if kept.unverified else ""
        note(f"resumed: {kept.resumed - adopted} of {len(indices)} windows taken from the interrupted run in "
             f"{stage.parent} (same file, checkpoint and options){redone}")
        notes.append(f"resumed: {kept.resumed - adopted} windows taken from the interrupted run{redone}")
    written = len(lines) - 1
    if not written:
        raise ValueError(f"{path}: none of its {len(starts)} windows of {window_us * 1e-3:g} ms holds "
                         f"{MIN_EVENTS} events or more")
    if (tail := tail_note(start, end, window_us, window_us, option="--window", unit_us=1_000_000,
                          origin_us=recording.first_us)) is not None:
        note(tail)                           # after the run: a mistake found during it stays one line
        notes.append(tail)
    scale = run_scale(samples, depth_range)
    with tqdm(total=len(indices), desc="pictures", unit="picture", disable=not progress) as bar:
        for first, block in blocks:   # kept block by block as they are drawn (~0.1 s each at 640x480)
            if block and not kept.load_pictures(first, block, scale, stage):
                for index in block:
                    draw_window(stage, index, scale, recording.first_us)
                    bar.update(1)
                kept.save_pictures(first, block, scale, stage)
            else:
                bar.update(len(block))
    write_text_atomic(stage / "twists.csv", "\n".join(lines) + "\n")
    run = DepthRun(written, skipped, window_us, tuple(notes), time.perf_counter() - started, stage)
    from cmax.cli.recording import camera_read

    summary = {"file": str(path), "format": recording.format, "camera": camera_read(recording.format, camera),
               "checkpoint": str(checkpoint),
               "size": [recording.width, recording.height], "K": np.asarray(K).tolist(),
               "distortion": None if distortion is None else distortion.tolist(),
               "distortion_model": None if distortion is None else lens.model,
               "rectified": lens.rectification is not None or lens.rectified_K is not None, "window_us": window_us,
               "t0_s": t0_s, "t1_s": t1_s, "start_us": start, "end_us": end, "depth_range_m": [scale.near, scale.far],
               "windows_total": len(starts), "windows": written, "skipped": skipped, "min_events": MIN_EVENTS,
               "notes": list(notes), "device": str(device), "seconds": run.seconds, "units": SUMMARY_UNITS,
               "run": completed_record(kept.run, depth_range),
               run_folder.OUTPUTS_KEY: run_folder.output_records(stage)}
    write_text_atomic(stage / "summary.json", json.dumps(summary, indent=2) + "\n")
    return run, kept


def completed_record(run: dict, depth_range: tuple[float, float] | None) -> dict:
    """What ``summary.json`` records of a complete run (``"run"``, compared by ``--resume``:
    :func:`cmax.io.run_folder.check_complete`): the run's record ``run`` (the kept blocks' ``run.json``: input
    files' signatures, options, code) with the pictures' colour scale ``depth_range`` [m] (None: the run's own
    percentiles) among its settings.

    Parameters
    ----------
    run : dict
        The run's record (:class:`learned.kept_windows.KeptBlocks`' ``run``).
    depth_range : (near, far) [m] or None
        The run's ``depth_range``.

    >>> completed_record({"settings": {"batch": 8}}, (1, 5))
    {'settings': {'batch': 8, 'depth_range': [1, 5]}}
    """
    from cmax.io.window_store import settings_record

    return {**run, "settings": {**run.get("settings", {}), **settings_record({"depth_range": depth_range})}}


def _run_record(path, checkpoint, calib, K, distortion, size, time_unit, polarity, sort, camera, t0_s, t1_s,
                window_us: int, windows: int, batch: int, device, progress: bool = True,
                files: dict | None = None, code: str | None = None) -> dict:
    """What a run of :func:`run_prediction` is, for ``resume`` to check: the event file's, the checkpoint's and
    the calibration's signatures (size, modification time, SHA-256: a progress bar while they are hashed when they
    hold more than 1 GiB and ``progress``; ``files``: those signatures when they are taken already,
    :class:`cmax.io.window_store.PendingSignatures`; ``code``: the digest of the code when taken already) and every
    option that changes a window, with the resolved window length [µs], number of windows and batch (the blocks of
    the forward passes)."""
    import cmax
    from cmax.io.window_store import code_digest, file_signatures, settings_record

    if files is None:
        files = file_signatures({"file": path, "checkpoint": checkpoint, "calib": calib}, progress=progress)
    return {"cmax": cmax.__version__, "code": code_digest("cmax", "learned") if code is None else code, **files,
            "settings": settings_record({"K": K, "distortion": distortion, "size": size, "time_unit": time_unit,
                                         "polarity": polarity, "sort": sort, "camera": camera, "t0_s": t0_s,
                                         "t1_s": t1_s, "window_us": window_us, "windows": windows, "batch": batch,
                                         "device": str(device)})}


def predict_file(checkpoint: str | Path | None, path: str | Path, out: str | Path, *, K: np.ndarray | None = None,
                 window_us: int | None = None, depth_range: tuple[float, float] | None = None,
                 progress: bool = True, **options: Any) -> int:
    """:func:`run_prediction` of ``checkpoint`` on the file ``path`` into ``out``, with the window ``window_us`` in µs
    (None: the checkpoint's); ``K`` (3, 3) or (4,) [px], ``depth_range``, ``progress`` and ``**options`` as there. Returns the number
    of windows written."""
    window_s = None if window_us is None else int(window_us) * 1e-6
    return run_prediction(path, out, checkpoint=checkpoint, K=K, window_s=window_s, depth_range=depth_range,
                          progress=progress, **options).windows


# -- command line ---------------------------------------------------------------------------
def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The options of ``cmax depth`` / ``python -m learned.predict`` (one definition for both); returns ``parser``."""
    parser.add_argument("file", type=Path, help="event file (any format cmax.io.read reads)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output folder")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="checkpoint of learned.train (default: the model shipped in learned/pretrained)")
    add_camera_options(parser, distortion_help=": events are undistorted first (the volume spreads each "
                                               "bilinearly from its exact undistorted position)")
    add_recording_arguments(parser)      # --size, --time-unit, --polarity, --t0, --t1, --sort, --camera
    add_duration_options(parser, "window", dest="window", unit="s", help="window length",
                         default="the checkpoint config's data.window_us", aliases=("--window",))
    parser.add_argument("--depth-range", type=float_list((2,), "--depth-range (near,far)"), default=None,
                        metavar="NEAR,FAR", help="colour scale of the depth pictures (window_*.png) [m], one for "
                        "the whole run, and nothing else: the predicted depth (window_*.npz) is neither clamped nor "
                        "conditioned by it, unlike cmax fit's and cmax emvs's --depth-range, which bound the depth "
                        "they search (default: the 1st-99th percentiles of all its windows' depths)")
    parser.add_argument("--batch", type=positive_int, default=None,
                        help=f"windows per forward pass (default {DEFAULT_BATCH}, fewer where that many would take "
                        f"more than {MAX_BATCH_BYTES >> 30} GiB; more is refused)")
    parser.add_argument("--device", default="cpu", metavar="DEVICE",
                        help="where the network runs: cpu, cuda, cuda:N or auto (a GPU when torch sees one); "
                             "default cpu")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the results of an earlier run in the output folder (else refused)")
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted run into the output folder: its finished blocks of windows "
                             "(kept in .depth.windows as each is done) are checked (the same event file, checkpoint "
                             "and options) and taken, the others predicted (default: off; a folder holding an "
                             "interrupted run's windows is refused without --resume or --overwrite; with "
                             "--overwrite too, an earlier complete run's results are replaced at the end; without "
                             "it, a complete run of the same file, checkpoint and options is left as it is: nothing "
                             "to do, unless a result it lists is missing or changed: then it runs again)")
    return parser


def run(args: argparse.Namespace, label: str = "python -m learned.predict") -> int:
    """Run the command of :func:`add_arguments`' options (``args``, as parsed); prints notes on stderr, prefixed
    by ``label``, and the summary line."""
    try:
        result = run_prediction(
            args.file, args.output, checkpoint=args.checkpoint, K=args.K, calib=args.calib,
            calib_camera=args.calib_camera, distortion=args.distortion, size=args.size, time_unit=args.time_unit,
            polarity=args.polarity, sort=args.sort, camera=args.camera,
            t0_s=args.t0, t1_s=args.t1, window_s=args.window,
            depth_range=None if args.depth_range is None else tuple(args.depth_range), batch=args.batch,
            progress=not args.quiet, note=lambda text: print(f"{label}: note: {text}", file=sys.stderr),
            overwrite=args.overwrite, device=args.device, resume=args.resume, as_recorded=args.as_recorded)
    except KeyboardInterrupt as stop:   # Ctrl-C, or SIGTERM (cmax._signals): say what is kept
        from cmax.io.window_store import stopped_line
        from learned.kept_windows import kept_windows

        if not (kept := kept_windows(args.output)):
            raise
        line, status = stopped_line(label, stop, kept, Path(args.output) / KEPT_FOLDER)
        print(line, file=sys.stderr)
        return status
    print(result.summary_line())
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m learned.predict`` with the arguments ``argv`` (None: the command line's); returns
    the exit status (2 and one line for a bad argument or file)."""
    parser = add_arguments(ArgumentParser(
        prog="python -m learned.predict",
        description="Depth [m] and twist of every window of an event file by the depth-pose network (the shipped "
        "model, or --checkpoint): window_<k>.npz and .png, twists.csv, summary.json in the output folder; the same "
        "command as cmax depth (docs/learned.md)."))
    return run_main(parser, run, argv)


if __name__ == "__main__":
    sys.exit(main())
