"""Conversion of videos to event files: one video, or a whole collection with a manifest.

One video (:func:`convert_video`) streams in constant memory::

    frames (cmax.sim.video source)  ->  [iter_upsample: adaptive sampling]
        ->  EventSimulator.step  ->  H5Writer.append  ->  <name>.h5 (DSEC layout)

The output is written by :class:`cmax.io.h5.H5Writer`: under an exclusive lock,
to a private temporary ``<name>.h5.<hex>.partial`` renamed when complete, with a
completion record written last, so a crashed conversion never leaves a file
that looks finished. A collection (:func:`convert_collection`) holds the lock
``.conversion.lock`` of its output folder (a second conversion into the same
folder fails at once), runs each video in its own worker process (at most
``workers`` at a time; a worker dies with its parent, and a worker's death fails
only its own video) and keeps ``manifest.json`` in the output folder, rewritten
atomically after each video: per video the frames, samples, events, duration,
events/s, category, status, error, the output file's name (relative to the
manifest's folder) and its byte size and SHA-256; globally the settings and the
simulator version. An entry is ``ok`` only once its file has been verified
(:func:`cmax.io.h5.verify_h5`: completion record, event count). A second run
skips the videos whose entry is ``ok`` and whose file still has the recorded
size, completion record, event count and SHA-256 (each skipped file is read
once) and whose source still has the recorded signature (files, bytes, latest
mtime, SHA-256 of its bytes: :mod:`cmax.sim.signature`; a moved source keeps it), and redoes
the others (failed, crashed, missing, truncated, damaged or foreign output; a source replaced,
re-exported, copied or touched, or replaced by other bytes of the same size and mtime). A file at a video's output that the manifest does
not list as that video's (a user's own ``a.h5`` beside ``a.mp4``) is refused before
any work unless ``overwrite=True``. A failing video (full disk, file-size limit, bad video) is
recorded and does not stop the others. An interrupted parallel run kills its
workers and removes their temporary files.

Jobs come from :func:`collect_jobs`: a video file, a folder of videos, a list
file (one video per line, optionally a tab or spaces and a category), or a
catalogue (:mod:`cmax.sim.catalogue`) resolved in a folder of videos named by
index, optionally one ``shard`` ``(i, n)`` of it.
"""
from __future__ import annotations

import hashlib
import json
import math
import numbers
import os
import signal
import sys
import threading
import time
import warnings
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np

from cmax._signals import sigint_deferred, sigterm_deferred
from cmax._workers import die_with_parent, recorded, reissue, start_forkserver
from cmax.io import VIDEO_SUFFIXES
from cmax.io.atomic import OutputLockedError, PathLock, discard_leftovers, file_sha256, lock_path, write_text_atomic
from cmax.sim.catalogue import load_catalogue, shard as take_shard
from cmax.sim.chunks import DEFAULT_CHUNK_FRAMES, written_from_chunks
from cmax.sim.esim import EsimSettings, EventSimulator
from cmax.sim.signature import signature_problem, source_signature
from cmax.sim.video import DEFAULT_PREFETCH, VideoFileSource, open_source

__all__ = [
    "ConvertSettings", "VideoJob", "VideoResult", "VIDEO_SUFFIXES", "collect_jobs",
    "convert_video", "convert_collection", "entry_output", "load_manifest", "merge_manifests", "write_manifest",
    "video_seed",
]

MANIFEST = "manifest.json"
#: Lock file of an output folder, held by the conversion writing into it.
FOLDER_LOCK = ".conversion.lock"
_FORMAT = "evtslowtv-manifest/1"
#: ``output_paths`` of a manifest whose entries name their output relative to its folder (``a.h5``,
#: ``shard0/a.h5`` after a merge); older manifests lack it (see :func:`entry_output`).
_RELATIVE = "relative"


# -- settings and records ---------------------------------------------------------------
@dataclass(frozen=True)
class ConvertSettings:
    """Settings of a conversion: the simulator, the resolution, sampling and time range.

    Attributes
    ----------
    esim : EsimSettings
        Event model (thresholds, mismatch, refractory period, noise, seed).
    size : (int, int) or None
        Output resolution ``(width, height)``; None keeps the video's.
    adaptive : bool
        Insert interpolated frames (:func:`cmax.sim.sampling.iter_upsample`) so
        that no pixel changes by more than ``lam * min(cp, cn)`` between samples.
    lam : float
        ``lambda`` of the adaptive sampling (> 0).
    method : {"flow", "linear"}
        Interpolation of the adaptive sampling.
    t0_s, t1_s : float or None
        Time range to convert, in seconds after the first frame, for a video and
        an image sequence alike (whatever clock its timestamps are on): frames with
        ``t_first + t0_s <= t < t_first + t1_s`` (:class:`cmax.sim.video.VideoFileSource`,
        :class:`cmax.sim.video.ImageFolderSource`); ``t0_s >= 0``, ``t1_s > 0`` and
        ``t1_s > t0_s``. A range that selects no frame fails the conversion.
    seed_per_video : bool
        :func:`convert_collection`: seed each video's simulator from ``esim.seed`` and the video's name
        (:meth:`for_video`), so that the videos of a collection get noise and threshold mismatch of their own,
        reproducibly; False gives every video ``esim.seed`` itself (the same noise in every video, as conversions
        before this option did). It matters only where the seed does (a seed and ``threshold_sigma``,
        ``shot_noise_rate_hz`` or ``leak_rate_hz`` above 0): only then does :meth:`to_dict` record it.
    K : (fx, fy, cx, cy) or None
        Pinhole intrinsics [px] of the frames as stored (before ``size`` resizes them): each output file then
        stores ``gt/K`` (3, 3), scaled to its pixels as ``cv2.resize`` moves pixel centres
        (:meth:`cmax.Camera.scaled`), which ``cmax fit``, ``emvs`` and ``depth`` read without ``--K``. A
        principal point outside a video's frames fails that video. None (the default): no ``gt/K``, and
        :meth:`to_dict` leaves it out (settings without it read as before it).
    """

    esim: EsimSettings = field(default_factory=EsimSettings)
    size: tuple[int, int] | None = None
    adaptive: bool = True
    lam: float = 0.5
    method: str = "flow"
    t0_s: float | None = None
    t1_s: float | None = None
    seed_per_video: bool = True
    K: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.esim, EsimSettings):
            raise TypeError(f"esim must be EsimSettings, got {type(self.esim).__name__}")
        if self.K is not None:
            from cmax.camera import intrinsics_matrix

            matrix = intrinsics_matrix(self.K, "K")
            if matrix[0, 1] != 0:
                raise ValueError(f"K must have no skew (the four numbers fx, fy, cx, cy), got {matrix.tolist()}")
            object.__setattr__(self, "K", tuple(float(v) for v in matrix[[0, 1, 0, 1], [0, 1, 2, 2]]))
        if self.size is not None:
            width, height = (int(v) for v in self.size)
            if width <= 0 or height <= 0:
                raise ValueError(f"size must be positive (width, height), got {self.size}")
            object.__setattr__(self, "size", (width, height))
        if not (isinstance(self.lam, (int, float)) and math.isfinite(self.lam) and self.lam > 0):
            raise ValueError(f"lam must be a positive number, got {self.lam!r}")
        if self.method not in ("flow", "linear"):
            raise ValueError(f"method must be 'flow' or 'linear', got {self.method!r}")
        for name in ("t0_s", "t1_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a non-negative number of seconds, got {value}")
        if self.t1_s is not None and self.t1_s <= 0:  # frames have t < t1_s: none at all
            raise ValueError(f"t1_s must be > 0 seconds (frames with t < t1_s are converted), got {self.t1_s}")
        if self.t0_s is not None and self.t1_s is not None and self.t1_s <= self.t0_s:
            raise ValueError(f"t1_s ({self.t1_s}) must be larger than t0_s ({self.t0_s})")
        if not isinstance(self.seed_per_video, bool):
            raise TypeError(f"seed_per_video must be a bool, got {self.seed_per_video!r}")

    @property
    def seeded_noise(self) -> bool:
        """Whether the events depend on ``esim.seed``: a seed, and threshold mismatch, shot noise or leak."""
        e = self.esim
        return e.seed is not None and (e.threshold_sigma > 0 or e.shot_noise_rate_hz > 0 or e.leak_rate_hz > 0)

    def for_video(self, name: str) -> "ConvertSettings":
        """The settings one video of a collection is converted with: with ``seed_per_video`` and
        :attr:`seeded_noise`, ``esim.seed`` replaced by :func:`video_seed` of it and ``name`` (and
        ``seed_per_video`` False: these settings are one video's); otherwise these settings unchanged."""
        if not (self.seed_per_video and self.seeded_noise):
            return self
        return replace(self, esim=replace(self.esim, seed=video_seed(self.esim.seed, name)), seed_per_video=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready settings (as stored in the manifest and the h5 attributes); ``seed_per_video`` only where it
        changes the events (:attr:`seeded_noise`) and is on, so that settings without it read as before it."""
        out = asdict(self)
        out["size"] = list(self.size) if self.size else None
        if not (self.seed_per_video and self.seeded_noise):
            del out["seed_per_video"]
        if self.K is None:
            del out["K"]
        else:
            out["K"] = list(self.K)
        return out

    def output_K(self, stored: tuple[int, int], width: int, height: int) -> np.ndarray | None:
        """``gt/K`` (3, 3) [px] of an output of ``width`` x ``height`` pixels made from frames stored at
        ``stored`` (width, height): :attr:`K` scaled to the output's pixels (None without :attr:`K`); ValueError
        when its principal point lies outside the stored frames (another size's or crop's K).

        >>> ConvertSettings(K=(200.0, 200.0, 119.5, 89.5)).output_K((240, 180), 120, 90).tolist()
        [[100.0, 0.0, 59.5], [0.0, 100.0, 44.5], [0.0, 0.0, 1.0]]
        """
        if self.K is None:
            return None
        from cmax.camera import Camera, check_principal_point, intrinsics_matrix

        K = intrinsics_matrix(self.K, "K")
        check_principal_point(K, stored[0], stored[1])           # of the frames as stored
        return Camera(K, stored[0], stored[1]).scaled(width, height).K


def video_seed(seed: int, name: str) -> int:
    """The simulator's seed of the video ``name`` in a collection seeded with ``seed``: 63 bits drawn by NumPy's
    ``SeedSequence`` from the seed and the SHA-256 of the name (UTF-8), the same on every machine and run.

    >>> video_seed(0, "a") == video_seed(0, "a") != video_seed(0, "b")
    True
    """
    digest = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:16], "little")
    return int(np.random.SeedSequence([int(seed), digest]).generate_state(1, np.uint64)[0] >> np.uint64(1))


@dataclass(frozen=True)
class VideoJob:
    """One video to convert: its ``source`` path, output stem ``name`` and ``category``."""

    name: str
    source: Path
    category: str | None = None


@dataclass(frozen=True)
class VideoResult:
    """Outcome of one conversion (one manifest entry).

    ``frames``: video frames read; ``samples``: frames fed to the simulator
    (with inserted ones); ``capped_intervals``: intervals between video frames
    where adaptive sampling hit a cap (one sample per µs, ``max_insert``) and
    the ``lam * C`` bound does not hold; ``duration_s``: last minus first frame time;
    ``status``: ``"ok"`` or ``"failed"`` (then ``error`` says why, and no output exists);
    ``bytes``, ``sha256``: size and checksum of the verified output file;
    ``source_signature``: the source as it was before it was read
    (:func:`cmax.sim.signature.source_signature`: resolved path, files, bytes,
    latest mtime in ns; None when the frames were passed in), which a resumed
    conversion compares, all but the path, with the source it would skip.
    """

    name: str
    source: str
    output: str
    category: str | None
    status: str
    frames: int = 0
    samples: int = 0
    capped_intervals: int = 0
    events: int = 0
    duration_s: float = 0.0
    events_per_s: float = 0.0
    wall_s: float = 0.0
    error: str | None = None
    bytes: int = 0
    sha256: str | None = None
    source_signature: dict[str, Any] | None = None


# -- one video --------------------------------------------------------------------------
def open_frames(source: str | os.PathLike, settings: ConvertSettings, *,
                prefetch: int = DEFAULT_PREFETCH) -> VideoFileSource:
    """The frames of a video (or of an image folder / timestamp file) in the settings' size and time range.

    Frames are uint8 grey (H, W) (the 8-bit values the reference ESIM works
    on), or float32 in [0, 255] for an image sequence of 16-bit images (rounding
    them to whole grey values would lose the steps between, most of a dark
    image's), decoded ``prefetch`` frames ahead in a background thread; times are
    the container's presentation times (or the image sequence's timestamps) in
    µs, from ``t0_s`` to ``t1_s`` seconds after the first frame.

    Raises
    ------
    FileNotFoundError
        No such file.
    cmax.sim.video.DecodeError
        OpenCV cannot decode the file (at once), or the stream ends early
        (truncated or corrupt, while iterating).
    ValueError
        No frame in the time range (while iterating).
    """
    # A folder or a .txt timestamp file is an image sequence (ECD images.txt, ESIM timestamps.txt).
    frames = open_source(source, size=settings.size, t0_s=settings.t0_s, t1_s=settings.t1_s,
                         dtype=np.uint8, prefetch=prefetch)
    if getattr(frames, "bit_depth", 8) > 8:
        frames.dtype = np.float32  # an ImageFolderSource decodes its images when iterated, to this type
    stored = getattr(frames, "stored_size", None)
    note = None if settings.size is None or stored is None else stretch_note(source, stored, settings.size)
    if note is not None:
        warnings.warn(note, UserWarning, stacklevel=2)
    return frames


def stretch_note(source: str | os.PathLike, stored: tuple[int, int], size: tuple[int, int]) -> str | None:
    """The warning for frames of ``stored`` (width, height) resized to a ``size`` of another aspect ratio (more
    than 1% apart), or None.

    >>> stretch_note("clip.mp4", (1280, 720), (346, 260))
    'clip.mp4: its 1280x720 frames are resized to 346x260, by 0.27 across and 0.361 down: the picture is stretched (pixels are no longer square: fx scales by 0.27, fy by 0.361); 346x195 (--size) keeps its shape'
    >>> stretch_note("clip.mp4", (1280, 720), (640, 360)) is None
    True
    """
    (w, h), (width, height) = stored, size
    across, down = width / w, height / h
    if abs(across / down - 1) <= 0.01:
        return None
    return (f"{source}: its {w}x{h} frames are resized to {width}x{height}, by {across:.3g} across and {down:.3g} "
            f"down: the picture is stretched (pixels are no longer square: fx scales by {across:.3g}, fy by "
            f"{down:.3g}); {width}x{max(1, round(width * h / w))} (--size) keeps its shape")


class _Count:
    """What a conversion has read so far: video frames, the first and last frame times [µs], intervals where
    adaptive sampling was capped, the last frame (as decoded), and the SHA-256 of the frames (times and pixels)
    from frame ``chunk_start`` on (those of the chunk being simulated)."""

    def __init__(self, frames: int = 0, first_t: int = 0, last_t: int = 0, capped: int = 0) -> None:
        self.frames, self.first_t, self.last_t, self.capped = frames, first_t, last_t, capped
        self.last_frame: np.ndarray | None = None
        self.chunk_start, self.digest = frames, hashlib.sha256()


def _frames_update(digest: "hashlib._Hash", frame: np.ndarray, t_us: int) -> None:
    """Add a video frame (its time [µs] and pixels, :func:`cmax.sim.chunks.frame_digest`) to ``digest``."""
    from cmax.sim.chunks import frame_digest

    digest.update(f"{int(t_us)}:{frame_digest(frame)};".encode())


def _counted(frames: Iterable[tuple[np.ndarray, int]], count: _Count):
    for frame, t_us in frames:
        if not count.frames:
            count.first_t = t_us
        count.frames += 1
        count.last_t, count.last_frame = t_us, frame
        if count.frames > count.chunk_start:      # not the kept chunks' last frame, read again on resume
            _frames_update(count.digest, frame, t_us)
        yield frame, t_us


class _NotContinued(ValueError):
    """The kept chunks cannot be continued: the source decodes to other frames than when they were kept."""


def _skip_kept(frames: Iterable[tuple[np.ndarray, int]], kept: int, records: list[dict], source: Path):
    """``frames`` from frame ``kept - 1`` on (the last frame of the kept chunks, whose ``records`` are given),
    after checking that the frames of each chunk are the ones it was simulated from (their SHA-256, where the
    record holds it: the video may have been replaced by another of the same size and modification time) and that
    this frame is the one the chunks ended on (time and pixels); :class:`_NotContinued` otherwise."""
    from cmax.sim.chunks import frame_digest

    record, stream = records[-1], iter(frames)
    ends = {int(r["end_frame"]) - 1: r for r in records if "frames_sha256" in r}
    digest = hashlib.sha256()
    for number, (frame, t_us) in enumerate(stream):
        _frames_update(digest, frame, t_us)
        if number in ends:
            chunk = ends[number]
            if digest.hexdigest() != chunk["frames_sha256"]:
                raise _NotContinued(
                    f"{source}: frames {chunk['first_frame']} to {number} decode to other pixels or times than when "
                    f"their chunk was kept (the video replaced by another of the same size and modification time?), "
                    "so the kept chunks cannot be continued")
            digest = hashlib.sha256()
        if number < kept - 1:
            continue
        if int(t_us) != record["last_t_us"] or frame_digest(frame) != record["frame_sha256"]:
            raise _NotContinued(f"{source}: frame {kept - 1} decodes differently from when its chunk was kept (at "
                                f"{t_us} µs, then {record['last_t_us']} µs, or to other pixels: another OpenCV or "
                                "FFmpeg?), so the kept chunks cannot be continued")
        yield frame, t_us
        yield from stream
        return
    raise _NotContinued(f"{source} decodes to fewer frames than the {kept} its kept chunks cover (another "
                        "OpenCV or FFmpeg?), so they cannot be continued")


def _chunk_run(signature: dict, settings: ConvertSettings) -> dict[str, Any]:
    """What a chunked conversion is (``run.json`` of :mod:`cmax.sim.chunks`): the source's signature, the
    settings and the code of cmax (the events change with any of them)."""
    from cmax.io.window_store import code_digest

    return {"format": "evtslowtv-chunks/1", "source": signature, "settings": _flat(settings.to_dict()),
            "code": code_digest("cmax")}


def convert_video(
    source: str | os.PathLike,
    output: str | os.PathLike,
    settings: ConvertSettings | None = None,
    *,
    category: str | None = None,
    frames: Iterable[tuple[np.ndarray, int]] | None = None,
    progress: Callable[[int], None] | None = None,
    overwrite: bool = False,
    chunk_frames: int | None = None,
    kept: str = "resume",
    keep_chunks: bool = False,
    resumed: Callable[[int, int], None] | None = None,
    signature: dict[str, Any] | None = None,
) -> VideoResult:
    """Convert one video to a DSEC-layout event file, streaming (constant memory).

    Parameters
    ----------
    source : path
        Video file (anything :mod:`cmax.sim.video` reads); recorded in the file.
    output : path
        The ``.h5`` file; written by :class:`cmax.io.h5.H5Writer` (locked, a private
        temporary file renamed when complete, completion record last).
    settings : ConvertSettings
    category : str, optional
        Stored in the file attributes and the result.
    frames : iterable of (frame, t_us), optional
        Frames to use instead of reading ``source`` (grey or BGR, µs); nothing is kept to resume then.
    progress : callable, optional
        Called with the number of new video frames read, now and then.
    overwrite : bool
        Replace an existing ``output`` (atomically, once the new file is
        complete; a failed conversion keeps the old one). Default False: an
        existing ``output`` raises ``FileExistsError`` before anything is read,
        as :func:`cmax.io.h5.write_h5` and ``cmax simulate`` do.
    chunk_frames : int, optional
        Keep the events in chunks of this many video frames (>= 1), each with the simulator's state after it
        (:mod:`cmax.sim.chunks`: ``.<name>.h5.chunks`` beside ``output``), so that a conversion killed part-way
        continues from its last kept chunk when it is run again, with the same events, bit for bit, as an
        uninterrupted one; ``output`` is then written from the chunks once the video has ended. None (the
        default): events go straight into ``output`` and an interrupted conversion starts over.
    kept : {"resume", "resume_or_restart", "restart"}
        With ``chunk_frames``, what to do with chunks a killed conversion into ``output`` kept: continue from
        them when they are of this run (the same source by size, modification time and SHA-256, the same settings and
        code; a chunk that fails its check is simulated again), and raise ValueError naming what differs when
        they are another's (``"resume"``, the default) or start over then (``"resume_or_restart"``); or start
        over whatever they are (``"restart"``). Kept chunks whose video frames decode to other pixels now
        (another OpenCV or FFmpeg; a video replaced by another of the same size and modification time) are
        another run's too (with ``"resume_or_restart"``: a UserWarning, and
        the video is converted from its first frame).
    keep_chunks : bool
        Leave the chunks in place once ``output`` is written (the caller removes them with
        :meth:`cmax.sim.chunks.KeptChunks.remove`, e.g. once the output is verified and recorded); default
        False: removed then.
    resumed : callable, optional
        Called once, with the video frames and the events the kept chunks hold, when the conversion continues
        from them.
    signature : dict, optional
        The source's signature (:func:`cmax.sim.signature.source_signature`) when the caller has just taken it
        (:func:`convert_collection` hashes a video with kept chunks before it converts anything): used as it is
        while the source's files still have its number, bytes and latest modification time (a ``stat``, no read),
        else the source is hashed again. None (the default): the source is hashed here, before it is read.

    Returns
    -------
    VideoResult
        With ``status="ok"``. Errors raise (the temporary file is removed; kept chunks stay, to resume):
        ``FileNotFoundError``, ``FileExistsError`` (``output`` exists and
        ``overwrite`` is False), ``ValueError`` for a video without frames in the
        range, unreadable or inconsistent frames, kept chunks of another run,
        ``OSError`` naming the output for a full disk or file-size limit,
        :class:`cmax.io.atomic.OutputLockedError` when another writer is writing ``output`` (with
        ``chunk_frames``: another conversion into ``output`` is running, its lock ``.<name>.h5.chunks.lock``).
    """
    from cmax.sim.chunks import KEPT_MODES, KeptChunks, chunk_folder

    settings = ConvertSettings() if settings is None else settings
    started = time.perf_counter()
    source, output = Path(source), Path(output)
    if chunk_frames is not None and (isinstance(chunk_frames, bool) or not isinstance(chunk_frames, numbers.Integral)
                                     or chunk_frames < 1):
        raise ValueError(f"chunk_frames must be an integer >= 1 or None, got {chunk_frames!r}")
    if kept not in KEPT_MODES:
        raise ValueError(f"kept must be one of {', '.join(KEPT_MODES)}, got {kept!r}")
    if not overwrite and os.path.lexists(output):  # before any frame is read (the writer checks again)
        raise FileExistsError(f"{output} exists (pass overwrite=True to replace it)")
    decoded = frames is None
    if frames is None and not source.exists():
        raise FileNotFoundError(f"video not found: {source}")
    # chunks: one conversion into output at a time, for the whole run (the output's own lock is taken only
    # when it is written from them)
    guard = PathLock(lock_path(chunk_folder(output)), output) if chunk_frames is not None and decoded else None
    not_continued = None
    try:
        if frames is None:
            if signature is None or not _still_signed(signature, source):
                signature = source_signature(source)  # before reading: a source changed meanwhile is redone on resume
            frames = open_frames(source, settings)
        else:
            signature = None
        chunks = None if guard is None else KeptChunks(output, _chunk_run(signature, settings), kept=kept)
        run = _Run(source, output, settings, chunks, frames, category, overwrite)
        if chunks is not None and chunks.redone:
            warnings.warn(f"{output}: {chunks.redone} kept chunk(s) are simulated again: a chunk failed its check "
                          "(changed since it was written), and the chunks after it (and those since the last kept "
                          "simulator state before it) depend on it", UserWarning, stacklevel=2)
        if chunks is not None and chunks.records and resumed is not None:
            resumed(chunks.frames, chunks.events)
        try:
            with _frames_on_the_grey_scale(decoded):
                if chunks is None or not chunks.records or not chunks.records[-1]["final"]:
                    run.simulate(frames, chunk_frames, progress)
                run.finish()
        except _NotContinued as error:
            run.abort()
            not_continued = error
        except BaseException:
            run.abort()
            raise
        if chunks is not None and not keep_chunks and not_continued is None:
            chunks.remove()
    finally:
        if guard is not None:
            guard.release()
    if not_continued is not None:
        if kept == "resume":
            raise ValueError(f"{not_continued}: pass --overwrite (kept='resume_or_restart') to start over")
        warnings.warn(f"{not_continued}: converting it from its first frame", UserWarning, stacklevel=2)
        return convert_video(source, output, settings, category=category, progress=progress, overwrite=overwrite,
                             chunk_frames=chunk_frames, kept="restart", keep_chunks=keep_chunks, signature=signature)
    count, duration = run.count, (run.count.last_t - run.count.first_t) * 1e-6
    return VideoResult(
        name=output.stem, source=str(source), output=str(output), category=category, status="ok",
        frames=count.frames, samples=run.samples, capped_intervals=count.capped,
        events=run.events, duration_s=duration,
        events_per_s=run.events / duration if duration > 0 else 0.0,
        wall_s=time.perf_counter() - started, source_signature=signature,
    )


def _still_signed(signature: dict[str, Any], source: Path) -> bool:
    """Whether ``source`` (its resolved path) and its files (:func:`cmax.sim.signature.source_files`) still have the
    path, number of files, total bytes and latest modification time [ns] that ``signature`` records (a ``stat``
    of each, nothing read); False where they cannot be listed."""
    from cmax.sim.signature import source_files

    try:
        stats = [os.stat(file) for file in source_files(source)]
    except (OSError, ValueError):
        return False
    now = (str(source.resolve()), len(stats), sum(s.st_size for s in stats), max(s.st_mtime_ns for s in stats))
    return now == tuple(signature.get(key) for key in ("path", "files", "bytes", "mtime_ns"))


class _Run:
    """One video's conversion: the simulation (into the output, or into kept chunks) and the output's writing."""

    def __init__(self, source: Path, output: Path, settings: ConvertSettings, chunks, frames, category, overwrite):
        self.source, self.output, self.settings, self.chunks = source, output, settings, chunks
        self.category, self.overwrite = category, overwrite
        self.stored = getattr(frames, "stored_size", None)   # the frames' (width, height) before --size resized them
        self.count, self.samples, self.size = _Count(), 0, None
        self.writer = self.chunk = self.K = None
        self.events = 0
        last = chunks.records[-1] if chunks is not None and chunks.records else None
        if last is not None:
            self.count = _Count(last["end_frame"], last["first_t_us"], last["last_t_us"], last["capped"])
            self.samples, self.size = last["samples"], (last["width"], last["height"])

    def _open_output(self, width: int, height: int, t_offset_us: int):
        """The output's writer (its K checked first)."""
        from cmax import __version__
        from cmax.io.h5 import H5Writer

        self.K = self.settings.output_K(self.stored or (width, height), width, height)
        frame_size = {} if self.stored is None else {"source_size": [int(self.stored[0]), int(self.stored[1])]}
        writer = H5Writer(
            self.output, width, height, t_offset_us=int(t_offset_us), overwrite=self.overwrite,
            source=str(self.source), category=self.category or "", simulator=f"cmax {__version__}",
            settings=self.settings.to_dict(), **frame_size,
        )
        return writer

    def simulate(self, frames, chunk_frames: int | None, progress) -> None:
        """Feed the frames (from the kept chunks' end on) to the simulator, keeping chunks or writing the output."""
        settings, chunks = self.settings, self.chunks
        resume = chunks is not None and bool(chunks.records)
        count = self.count
        if resume:
            count.frames -= 1                    # the chunks' last frame is read again, to restart the sampler
            frames = _skip_kept(frames, chunks.frames, chunks.records, self.source)
        stream: Iterable = _counted(frames, count)
        if settings.adaptive:
            from cmax.sim.sampling import iter_upsample

            def count_capped(interval) -> None:
                count.capped += int(interval.capped)

            stream = iter_upsample(stream, min(settings.esim.cp, settings.esim.cn), lam=settings.lam,
                                   method=settings.method, report=count_capped)
        simulator = EventSimulator.from_settings(settings.esim)
        if resume:
            simulator.restore(chunks.state())
        reported = count.frames + int(resume)
        for frame, t_us in stream:
            if resume:                            # the chunks' last frame: the simulator has seen it
                resume = False
                continue
            events = simulator.step(frame, t_us)
            if self.size is None:                 # the first frame: K checked before anything is written
                self.size = (events.width, events.height)
                self.settings.output_K(self.stored or self.size, *self.size)
                if chunks is None:
                    self.writer = self._open_output(events.width, events.height, t_us)
            if chunks is not None and self.chunk is None:
                self.chunk = chunks.open_chunk()
            (self.chunk or self.writer).append(events)
            self.samples += 1
            if chunks is not None and t_us == count.last_t and count.frames - chunks.frames >= chunk_frames:
                self._keep(simulator, final=False)  # a video frame, chunk_frames after the last kept chunk
            if progress is not None and count.frames > reported:
                progress(count.frames - reported)
                reported = count.frames
        if self.size is None:
            raise ValueError(f"{self.source}: no frames" + _range_note(settings))
        if chunks is not None:
            self._keep(simulator, final=True)

    def _keep(self, simulator: EventSimulator, *, final: bool) -> None:
        """Keep the chunk written so far with the simulator's state after it."""
        from cmax.sim.chunks import frame_digest

        if self.chunk is None:
            self.chunk = self.chunks.open_chunk()
        count = self.count
        self.chunks.save(self.chunk, simulator.state(), {
            "end_frame": count.frames, "samples": self.samples, "capped": count.capped,
            "first_t_us": int(count.first_t), "last_t_us": int(count.last_t),
            "frame_sha256": frame_digest(count.last_frame), "frames_sha256": count.digest.hexdigest(),
            "final": final, "width": self.size[0], "height": self.size[1]})
        self.chunk = None
        count.chunk_start, count.digest = count.frames, hashlib.sha256()

    def finish(self) -> None:
        """Write the output (from the kept chunks, when there are), complete, and rename it into place."""
        if self.chunks is not None:
            width, height = self.size
            self.writer = self._open_output(width, height, self.count.first_t)
            for events in self.chunks.iter_events(width, height):
                self.writer.append(events)
        K = self.K
        self.writer.close(extra=None if K is None else lambda file: file.create_dataset("gt/K", data=K))
        self.events = self.writer.count

    def abort(self) -> None:
        """Remove the temporary output and the chunk being written; the kept chunks stay (a folder without one
        is removed)."""
        if self.writer is not None:
            self.writer.abort()
        if self.chunk is not None:
            self.chunk.abort()
        if self.chunks is not None and not self.chunks.records:
            self.chunks.remove()


@contextmanager
def _frames_on_the_grey_scale(decoded: bool) -> Iterator[None]:
    """Silence the "[0, 1] image?" warning (:func:`cmax.sim.esim.unit_range_note`) for frames decoded from a file.

    Decoded frames are grey values in [0, 255] whatever their range: a dark 16-bit image (values up to 257 of
    65535) is float32 frames within [0, 1], which the warning would take for a [0, 1] image and advise to
    multiply by 255. Frames a caller passes (``frames=``) keep the warning.
    """
    with warnings.catch_warnings():
        if decoded:
            warnings.filterwarnings("ignore", message=r"frames are floats in \[", category=UserWarning)
        yield


def _range_note(settings: ConvertSettings) -> str:
    if settings.t0_s is None and settings.t1_s is None:
        return ""
    from cmax.sim.video import range_words

    return " " + range_words(settings.t0_s, settings.t1_s)


# -- jobs -------------------------------------------------------------------------------
def _read_list_file(path: Path) -> list[VideoJob]:
    jobs = []
    for number, line in enumerate(path.read_text("utf-8").splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split("\t") if "\t" in line else line.rsplit(None, 1)
        video = Path(parts[0].strip())
        category = parts[1].strip() if len(parts) > 1 else None
        if len(parts) > 1 and video.suffix.lower() not in VIDEO_SUFFIXES and " " in line and "\t" not in line:
            video, category = Path(line), None  # a path with spaces and no category
        if not video.is_absolute():
            video = path.parent / video
        jobs.append(VideoJob(video.stem, video, category))
    if not jobs:
        raise ValueError(f"list file {path} names no videos")
    return jobs


def collect_jobs(
    source: str | os.PathLike,
    *,
    catalogue: str | None = None,
    shard: tuple[int, int] | None = None,
) -> tuple[list[VideoJob], list[str]]:
    """The videos to convert, and the catalogue entries whose video is missing.

    Parameters
    ----------
    source : path
        A video file, a folder of videos (suffixes :data:`VIDEO_SUFFIXES`, sorted
        by name), or a list file (``.txt``/``.tsv``/``.list``: one video per
        line, relative to the list's folder, optionally a tab and a category).
        With ``catalogue``, the folder holding the catalogue's videos named by
        index (``00000.mp4``, ...).
    catalogue : str, optional
        A catalogue of :mod:`cmax.sim.catalogue` (``"slowtv"``).
    shard : (i, n), optional
        Keep shard ``i`` of ``n`` (every n-th job from the i-th): disjoint shards
        that together cover all jobs (of the catalogue, when one is given).

    Raises
    ------
    FileNotFoundError, ValueError
        A missing source, a folder without videos, repeated output names.
    """
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"input not found: {source}")
    missing: list[str] = []
    if catalogue is not None:
        if not source.is_dir():
            raise ValueError(f"with a catalogue, INPUT must be the folder of its videos, got {source}")
        entries = load_catalogue(catalogue)
        entries = take_shard(entries, *shard) if shard else entries
        jobs = []
        for entry in entries:
            found = [source / f"{entry.name}{suffix}" for suffix in VIDEO_SUFFIXES]
            found = [path for path in found if path.is_file()]
            if found:
                jobs.append(VideoJob(entry.name, found[0], entry.category))
            else:
                missing.append(entry.name)
        return jobs, missing
    if source.is_dir():
        videos = sorted(p for p in source.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES and p.is_file())
        if not videos:
            raise ValueError(f"folder {source} holds no videos ({', '.join(VIDEO_SUFFIXES)})")
        jobs = [VideoJob(path.stem, path) for path in videos]
    elif source.suffix.lower() in (".txt", ".tsv", ".list", ".lst"):
        jobs = _read_list_file(source)
    elif source.suffix.lower() in VIDEO_SUFFIXES:
        jobs = [VideoJob(source.stem, source)]
    else:
        raise ValueError(f"INPUT must be a video ({', '.join(VIDEO_SUFFIXES)}), a folder of videos or a list file "
                         f"(.txt, .tsv, .list, .lst), got {source}")
    names = [job.name for job in jobs]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ValueError(f"several videos would write the same output name: {', '.join(repeated)}")
    return (take_shard(jobs, *shard) if shard else jobs), missing


# -- manifests --------------------------------------------------------------------------
def write_manifest(path: str | os.PathLike, manifest: dict[str, Any]) -> None:
    """Write ``manifest`` as JSON atomically (lock, private temporary file, fsync, rename)."""
    path = Path(path)
    write_text_atomic(path, json.dumps(manifest, indent=2, sort_keys=False) + "\n")


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _is_seconds(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0


def check_manifest(manifest: Any, where: str) -> dict[str, Any]:
    """``manifest`` if it has the structure :func:`convert_collection` writes, else a one-line ValueError.

    Checked: the format tag, ``settings`` (an object), ``videos`` (an object of
    entries, each with ``status`` ``"ok"`` or ``"failed"``; an ``ok`` entry with
    non-negative integer ``frames``, ``events`` and ``bytes`` and finite
    non-negative ``duration_s``), ``missing`` (a list of names). ``where`` names
    the manifest in the message.
    """
    if not isinstance(manifest, dict) or manifest.get("format") != _FORMAT:
        raise ValueError(f"{where} is not a conversion manifest (format {_FORMAT})")
    if not isinstance(manifest.get("settings"), dict):
        raise ValueError(f"{where}: malformed manifest: 'settings' must be an object")
    videos = manifest.get("videos")
    if not isinstance(videos, dict):
        raise ValueError(f"{where}: malformed manifest: 'videos' must be an object of entries")
    missing = manifest.get("missing", [])
    if not isinstance(missing, list) or not all(isinstance(name, str) for name in missing):
        raise ValueError(f"{where}: malformed manifest: 'missing' must be a list of names")
    for name, entry in videos.items():
        if not isinstance(entry, dict) or entry.get("status") not in ("ok", "failed"):
            raise ValueError(f"{where}: malformed manifest: videos[{name!r}] needs a status 'ok' or 'failed'")
        if entry["status"] != "ok":
            continue
        for key, valid in (("frames", _is_count), ("events", _is_count), ("duration_s", _is_seconds)):
            if not valid(entry.get(key)):
                raise ValueError(f"{where}: malformed manifest: videos[{name!r}][{key!r}] = {entry.get(key)!r}")
    return manifest


def load_manifest(path: str | os.PathLike) -> dict[str, Any]:
    """A manifest written by :func:`convert_collection` (checked by :func:`check_manifest`).

    Raises ValueError (one line) for anything else, OSError for an unreadable path.
    """
    path = Path(path)
    try:
        manifest = json.loads(Path(path).read_text("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
        message = " ".join(str(error).split())
        raise ValueError(f"{path} is not a JSON manifest: {message}") from None
    return _with_relative_outputs(check_manifest(manifest, str(path)))


def _with_relative_outputs(manifest: dict[str, Any]) -> dict[str, Any]:
    """``manifest`` with ``output_paths`` ``"relative"``: an older manifest's outputs (bare names, or the
    paths typed at conversion time) become the names :func:`entry_output` finds them under."""
    if manifest.get("output_paths") == _RELATIVE:
        return manifest
    videos = {name: dict(entry, output=entry_output(entry, ".", relative=False).name) if "output" in entry
              else entry for name, entry in manifest["videos"].items()}
    return dict(manifest, videos=videos, output_paths=_RELATIVE)


def _flat(settings: Any, prefix: str = "") -> dict[str, Any]:
    """A settings dict with nested keys joined by dots (``{"esim": {"cp": 0.2}}`` -> ``{"esim.cp": 0.2}``)."""
    if not isinstance(settings, dict):
        return {prefix: settings}
    out: dict[str, Any] = {}
    for key, value in settings.items():
        out.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out


def settings_difference(recorded: dict[str, Any], now: dict[str, Any],
                        labels: tuple[str, str] = ("recorded", "now")) -> str:
    """The keys where two settings dicts (:meth:`ConvertSettings.to_dict`) differ, as ``key: old (recorded) vs
    new (now)`` (``labels`` name the two); nested keys joined by dots.

    >>> settings_difference({"esim": {"cp": 0.2}, "size": None}, {"esim": {"cp": 0.3}, "size": [64, 48]})
    'esim.cp: 0.2 (recorded) vs 0.3 (now), size: None (recorded) vs [64, 48] (now)'
    """
    old, new = _flat(recorded), _flat(now)
    missing = object()
    keys = [key for key in dict.fromkeys([*old, *new]) if old.get(key, missing) != new.get(key, missing)]
    return ", ".join(f"{key}: {old.get(key, 'absent')!r} ({labels[0]}) vs {new.get(key, 'absent')!r} ({labels[1]})"
                     for key in keys)


def _new_manifest(settings: ConvertSettings, catalogue: str | None, shard, missing) -> dict[str, Any]:
    from cmax import __version__

    return {
        "format": _FORMAT, "simulator": f"cmax {__version__}", "simulator_version": __version__,
        "settings": settings.to_dict(), "catalogue": catalogue,
        "shard": None if shard is None else f"{shard[0]}/{shard[1]}",
        "missing": list(missing), "videos": {}, "totals": {}, "output_paths": _RELATIVE,
    }


def _totals(videos: dict[str, dict]) -> dict[str, Any]:
    ok = [v for v in videos.values() if v["status"] == "ok"]
    return {
        "videos": len(videos), "ok": len(ok), "failed": len(videos) - len(ok),
        "frames": sum(v["frames"] for v in ok), "events": sum(v["events"] for v in ok),
        "duration_s": sum(v["duration_s"] for v in ok),
    }


def merge_manifests(manifests: Sequence[dict[str, Any]], *,
                    folders: Sequence[str | os.PathLike] | None = None,
                    into: str | os.PathLike | None = None,
                    names: Sequence[str] | None = None) -> dict[str, Any]:
    """Join the manifests of several shards or machines into one.

    Settings and simulator version must agree. A video present in several
    manifests keeps its ``ok`` entry (else the last one); an entry missing in one
    manifest but converted in another is not missing. Each manifest is checked
    first (:func:`check_manifest`).

    Parameters
    ----------
    manifests : sequence of dict
        The manifests (:func:`load_manifest`).
    folders : sequence of paths, optional
        The folder of each manifest (where its outputs lie), with ``into``.
    into : path, optional
        The folder the merged manifest will be written to. With ``folders``, each
        entry's ``output`` is rewritten relative to it (``shard0/00000.h5``), so
        that :func:`entry_output` finds the files from the merged manifest and a
        conversion resumed into ``into`` verifies and skips them. A manifest whose
        folder does not lie inside ``into`` is refused (ValueError). Without them
        the outputs are kept as they are (right only for manifests already in
        ``into``).
    names : sequence of str, optional
        How errors name each manifest (its file); default ``manifest i``.
    """
    if not manifests:
        raise ValueError("merge_manifests needs at least one manifest")
    if (folders is None) != (into is None):
        raise ValueError("merge_manifests takes folders= and into= together")
    if folders is not None and len(folders) != len(manifests):
        raise ValueError(f"merge_manifests got {len(folders)} folders for {len(manifests)} manifests")
    for number, manifest in enumerate(manifests, start=1):
        check_manifest(manifest, f"manifest {number} of {len(manifests)}")
    manifests = [_with_relative_outputs(manifest) for manifest in manifests]
    if folders is not None:
        manifests = [_outputs_relative_to(manifest, Path(folder), Path(into))
                     for manifest, folder in zip(manifests, folders)]
    names = [f"manifest {i}" for i in range(1, len(manifests) + 1)] if names is None else [str(n) for n in names]
    first = manifests[0]
    for name, other in zip(names[1:], manifests[1:]):
        for key in ("settings", "simulator", "catalogue"):
            if other.get(key) != first.get(key):
                labels = (names[0], name)
                difference = (settings_difference(first[key], other[key], labels) if key == "settings" else
                              f"{first.get(key)!r} ({labels[0]}) vs {other.get(key)!r} ({labels[1]})")
                raise ValueError(f"{name} differs from {names[0]} in {key!r} ({difference}): merge only "
                                 "conversions made with the same settings and simulator")
    videos: dict[str, dict] = {}
    missing: set[str] = set()
    for manifest in manifests:
        missing.update(manifest.get("missing", []))
        for name, entry in manifest["videos"].items():
            if name not in videos or entry["status"] == "ok":
                videos[name] = entry
    merged = dict(first, shard=None, videos=dict(sorted(videos.items())), output_paths=_RELATIVE)
    merged["missing"] = sorted(missing - set(videos))
    merged["totals"] = _totals(merged["videos"])
    return merged


def _outputs_relative_to(manifest: dict[str, Any], folder: Path, into: Path) -> dict[str, Any]:
    """``manifest`` (of ``folder``) with each entry's output relative to the folder ``into`` (POSIX ``/``)."""
    base = os.path.abspath(into)
    videos = {}
    for name, entry in manifest["videos"].items():
        target = os.path.abspath(entry_output(entry, folder, relative=True))
        relative = Path(os.path.relpath(target, base))
        if relative.parts[:1] == ("..",):
            raise ValueError(f"the outputs of {folder / MANIFEST} (e.g. {target}) lie outside {into}, the folder "
                             "of the merged manifest: write it into a folder that holds the manifests' folders "
                             f"(e.g. {Path(os.path.commonpath([base, os.path.abspath(folder)])) / MANIFEST})")
        videos[name] = dict(entry, output=relative.as_posix())
    return dict(manifest, videos=videos)


# -- verification -----------------------------------------------------------------------
def _verified(result: VideoResult) -> VideoResult:
    """``result`` with the byte size and SHA-256 of its output, after checking the file is complete."""
    from cmax.io.h5 import verify_h5

    verify_h5(result.output, events=result.events)
    size = os.lstat(result.output).st_size
    digest = file_sha256(result.output)
    if os.lstat(result.output).st_size != size:
        raise ValueError(f"{result.output} changed while it was verified")
    return replace(result, bytes=size, sha256=digest)


def output_problem(entry: dict | None, output: Path, read: Callable[[int], None] | None = None) -> str | None:
    """Why the manifest ``entry`` of ``output`` is not a finished video (None when it is).

    Finished: status ``ok``, and the file is a regular file of the recorded byte
    size whose completion record holds the recorded event count and whose
    SHA-256 equals the recorded one (so a file damaged in place, same size, is
    redone). Cost: the file is read once, in 4 MiB blocks (about 0.5 GB/s on one
    core from the page cache, i.e. some seconds for a file of several GB), so a
    resumed collection reads every file it skips. ``read``: called with the bytes [B] of each block hashed (a
    progress bar's ``update``), or None.
    """
    from cmax.io.h5 import verify_h5

    if not entry or entry.get("status") != "ok":
        return "not converted"
    if not _is_count(entry.get("bytes")) or not entry.get("sha256"):
        return "the manifest holds no size and checksum for it"
    try:
        size = os.lstat(output).st_size
        if size != entry["bytes"]:
            return f"{output.name} has {size} bytes, the manifest recorded {entry['bytes']}"
        verify_h5(output, events=entry["events"])
        if file_sha256(output, read) != entry["sha256"]:
            return f"{output.name} does not have the SHA-256 the manifest recorded (its bytes changed)"
    except (OSError, ValueError) as error:
        return " ".join(str(error).split())
    return None


def source_problem(entry: dict, source: str | os.PathLike, read: Callable[[int], None] | None = None) -> str | None:
    """Why ``source`` is not the source the manifest ``entry`` was converted from (None when it is).

    Compared: the entry's ``source_signature`` with the source's now (number of files, bytes,
    latest mtime in ns, and the SHA-256 of its bytes where the entry holds one: the source is read once;
    :mod:`cmax.sim.signature`: a moved source is the same); an entry of an older manifest,
    without a signature, by its ``source`` path alone (as typed, or resolved from this folder). ``read``: called
    with the bytes [B] of each block hashed (a progress bar's ``update``), or None.
    """
    recorded = entry.get("source_signature")
    if not isinstance(recorded, dict):
        old = entry.get("source")
        if isinstance(old, str) and (old == str(source) or Path(old).resolve() == Path(source).resolve()):
            return None
        return f"it was converted from {old}, now {source}"
    try:
        now = source_signature(source, read)
    except (OSError, ValueError) as error:
        return " ".join(str(error).split())
    return signature_problem(recorded, now)


# -- a collection -----------------------------------------------------------------------
def _failed(job: VideoJob, output: Path, error: str, started: float | None = None) -> VideoResult:
    wall = 0.0 if started is None else time.perf_counter() - started
    return VideoResult(job.name, str(job.source), str(output), job.category, "failed", wall_s=wall, error=error)


@dataclass(frozen=True)
class _Chunking:
    """How one job keeps chunks: ``frames`` video frames a chunk (None: no chunks) and the ``kept`` mode of
    :func:`convert_video`; ``signature``: its source's signature where :func:`_kept_runs` took it (to compare it
    with kept chunks), for :func:`convert_video` not to hash the source a second time; ``replace``: whether a file
    at its output may be replaced (it was there when the conversion checked its outputs, or ``overwrite``), else a
    file that appeared since fails the video."""

    frames: int | None = None
    kept: str = "resume"
    signature: dict | None = None
    replace: bool = True


def _resumed_note(name: str, bar) -> Callable[[int, int], None]:
    """The ``resumed`` of :func:`convert_video` for the job ``name``: a note on stderr, and the frame bar (when
    there is one) starts at the kept frames and says so."""
    def note(frames: int, events: int) -> None:
        print(f"cmax: note: {name}: continuing an interrupted conversion: {frames} frame(s) and {events:,} events "
              "kept (their files and the video's bytes verified by SHA-256; the kept frames are decoded again and "
              "compared only when the video goes on past them)", file=sys.stderr)
        if bar is not None:
            bar.update(frames)
            bar.set_postfix_str(f"{frames} kept")

    return note


def _hashing_bar(total: int, desc: str, position: int | None = None, progress: bool = True):
    """A tqdm bar [bytes] on stderr over hashing ``total`` bytes of videos (SHA-256), ``desc`` its label, at the
    line ``position``; shown when ``progress`` and ``total`` is more than
    :data:`cmax.io.window_store.HASH_PROGRESS_BYTES` (as cmax fit's input hashing)."""
    from tqdm.auto import tqdm

    from cmax.io.window_store import HASH_PROGRESS_BYTES

    return tqdm(total=total, desc=desc, unit="B", unit_scale=True, unit_divisor=1024, position=position,
                leave=False, disable=not progress or total <= HASH_PROGRESS_BYTES)


def _source_bytes(source: str | os.PathLike) -> int:
    """The bytes [B] of the files a conversion of ``source`` reads (:func:`cmax.sim.signature.source_files`)."""
    from cmax.sim.signature import source_files

    return sum(os.path.getsize(file) for file in source_files(source))


def _signature_with_bar(job: VideoJob, position: int | None) -> dict[str, Any]:
    """:func:`cmax.sim.signature.source_signature` of ``job``'s source, a bar [bytes] on the line ``position``
    (None: no bar, and no tqdm at all: a worker's first tqdm makes multiprocessing locks, which a worker killed
    with its process group leaves to the resource tracker's warnings) while it is read (:func:`_hashing_bar`): a
    multi-GB video takes seconds."""
    if position is None:
        return source_signature(job.source)
    with _hashing_bar(_source_bytes(job.source), f"{job.name}: hashing the video (SHA-256, for the manifest)",
                      position, position is not None) as bar:
        return source_signature(job.source, bar.update)


def _run_job(job: VideoJob, output: Path, settings: ConvertSettings, position: int | None,
             chunking: _Chunking = _Chunking()) -> VideoResult:
    """Worker: convert one job and verify its file, turning an error into a failed result; the chunks it
    keeps stay until the caller has recorded the result."""
    started = time.perf_counter()
    bar = None
    try:
        signature = chunking.signature
        if signature is None and os.path.exists(job.source):    # a missing one is convert_video's to name
            signature = _signature_with_bar(job, position)
        if position is not None:
            from tqdm.auto import tqdm

            bar = tqdm(desc=job.name, unit="frame", position=position, leave=False, mininterval=1.0)
        # overwrite: under the folder's lock, an output the manifest does not list as verified is redone
        # (replaced atomically when the new file is complete); a file it does not list at all was refused
        # before the conversion started, unless the caller asked to overwrite (convert_collection); one that
        # appeared since (a user's, another program's) is not replaced: chunking.replace is False
        if not chunking.replace and os.path.lexists(output):
            raise FileExistsError(f"{output} appeared after this conversion checked its outputs (a file of yours or "
                                  "of another program?) and is not replaced: move it and run again, or pass "
                                  "--overwrite (overwrite=True)")
        result = convert_video(job.source, output, settings.for_video(job.name), category=job.category,
                               progress=None if bar is None else bar.update, overwrite=chunking.replace,
                               chunk_frames=chunking.frames, kept=chunking.kept, keep_chunks=True,
                               resumed=_resumed_note(job.name, bar), signature=signature)
        result = _verified(replace(result, name=job.name))
    except Exception as error:  # reported in the manifest; the other videos go on
        message = " ".join(f"{type(error).__name__}: {error}".split())
        return _failed(job, output, message, started)
    finally:
        if bar is not None:
            bar.close()
    return result


def convert_collection(
    jobs: Sequence[VideoJob],
    output_dir: str | os.PathLike,
    settings: ConvertSettings | None = None,
    *,
    workers: int = 1,
    missing: Sequence[str] = (),
    catalogue: str | None = None,
    shard: tuple[int, int] | None = None,
    progress: bool = True,
    on_result: Callable[[VideoResult], None] | None = None,
    redo: Sequence[str] = (),
    overwrite: bool = False,
    chunk_frames: int | None = DEFAULT_CHUNK_FRAMES,
) -> dict[str, Any]:
    """Convert many videos to ``output_dir/<name>.h5`` with a resumable manifest.

    Parameters
    ----------
    jobs : sequence of VideoJob
        From :func:`collect_jobs`.
    output_dir : path
        Created if needed; holds the event files and ``manifest.json``. Locked
        (``.conversion.lock``) while the conversion runs: a second conversion
        into it raises :class:`cmax.io.atomic.OutputLockedError` and changes nothing.
    settings : ConvertSettings
        Must equal those of an existing manifest in ``output_dir`` (resume).
    workers : int
        Processes (>= 1); 1 converts in this process. Otherwise each video runs
        in its own process (``forkserver``, else ``spawn``), at most ``workers``
        at a time, killed if this process dies; a worker that dies fails its own
        video only. As with any such start, a script calling this needs the
        ``if __name__ == "__main__":`` guard.
    missing : sequence of str
        Catalogue entries without a video, recorded in the manifest.
    progress : bool
        tqdm bars: videos, and frames of each running video.
    on_result : callable, optional
        Called with each finished :class:`VideoResult` (in this process).
    redo : sequence of str
        Names of jobs to convert again even if their entry is ``ok`` (an
        overwrite): their entries are dropped only under the folder's lock, after
        the settings were compared, so a refused conversion changes nothing; the
        old file is replaced atomically when the new one is complete. Chunks an
        interrupted conversion of the same source and settings kept are continued
        (the same events), those of another run removed.
    overwrite : bool
        Replace files at the outputs of ``jobs`` that the folder's manifest does
        not list as this video's output. Default False: such files (a user's own
        ``a.h5`` beside ``a.mp4``, a file of another run) raise
        ``FileExistsError`` naming them, under the lock and before anything is
        converted or written; a file that appears at an output after that check fails its video and is
        kept (never replaced without ``overwrite``). Outputs the manifest lists (an ``ok`` entry, or one
        it marked failed because the output or the source changed) are the
        conversion's own and are verified, skipped or redone as described above;
        so is a file this conversion wrote from the chunks kept beside it before it was killed
        (:func:`cmax.sim.chunks.written_from_chunks`). With ``overwrite``, chunks a killed conversion kept for a video of another source, settings or code are
        removed and that video starts over (without it they are refused, see ``chunk_frames``). A folder at an
        output raises ``IsADirectoryError`` naming it, with or without ``overwrite``, before anything is converted.
    chunk_frames : int or None
        Each video's events are kept in chunks of this many video frames (default
        :data:`cmax.sim.chunks.DEFAULT_CHUNK_FRAMES`; :func:`convert_video`), so that a video whose conversion
        was killed continues from its last verified chunk, with the same events, bit for bit, as an
        uninterrupted conversion; the chunks are removed once its output is recorded as ``ok``. Chunks of
        another run (its source, settings or code changed since) raise ValueError naming them, under the lock
        and before anything is converted, unless ``overwrite`` (or the video is in ``redo``): then that video
        starts over. None: no chunks, an interrupted video starts over (chunks of another run beside its output
        are refused all the same: they are removed once it is recorded).

    Returns
    -------
    dict
        The manifest, also written to ``output_dir/manifest.json`` after every
        video (when the disk is full, the next write retries; the last one raises).
    """
    settings = ConvertSettings() if settings is None else settings
    if isinstance(workers, bool) or not isinstance(workers, numbers.Integral) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    workers = int(workers)
    if chunk_frames is not None and (isinstance(chunk_frames, bool) or not isinstance(chunk_frames, numbers.Integral)
                                     or chunk_frames < 1):
        raise ValueError(f"chunk_frames must be an integer >= 1 or None, got {chunk_frames!r}")
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    with PathLock(output_dir / FOLDER_LOCK, output_dir):
        return _convert_locked(jobs, output_dir, settings, workers, missing, catalogue, shard, progress, on_result,
                               set(redo), overwrite, chunk_frames)


def entry_output(entry: dict, folder: str | os.PathLike, *, relative: bool = True) -> Path:
    """The output file of the manifest ``entry`` of a manifest in ``folder``.

    ``relative=True`` (a manifest whose ``output_paths`` is ``"relative"``: all that
    :func:`convert_collection`, :func:`merge_manifests` and :func:`load_manifest`
    return): the entry stores the file's path relative to the manifest's folder, a
    name (``a.h5``) or, after a merge, a sub-path (``shard0/a.h5``); a path that
    is absolute or climbs out of the folder (``..``) is refused (ValueError).
    ``relative=False`` (older manifests, read as raw JSON): the entry holds a bare
    name or the path typed at conversion time (relative to that run's folder,
    or absolute); such a file always lies in the manifest's folder, so its name is
    kept. :func:`load_manifest` turns an older manifest into the first kind.
    """
    output = Path(str(entry["output"]))
    if not relative:
        return Path(folder) / output.name
    if output.is_absolute() or ".." in output.parts or output.name in ("", "."):
        raise ValueError(f"manifest entry output {str(entry['output'])!r} is not a path inside the manifest's "
                         "folder (absolute, or climbing out with '..')")
    return Path(folder) / output


def _manifest_entry(result: VideoResult) -> dict[str, Any]:
    """``result`` as a manifest entry: its output as a name relative to the manifest's folder."""
    return dict(asdict(result), output=Path(result.output).name)


def _listed_output(entry: dict | None, output: Path, folder: Path) -> bool:
    """Whether the manifest ``entry`` (of a manifest in ``folder``) lists ``output`` as its verified output:
    an ``ok`` entry, or one that records a checksum (an ``ok`` entry marked failed because its output or its
    source changed), whose output is ``output``."""
    if not entry or not (entry.get("status") == "ok" or entry.get("sha256")):
        return False
    try:
        return entry_output(entry, folder) == output
    except (KeyError, ValueError):
        return False


def _kept_runs(jobs, output_dir: Path, settings: ConvertSettings, redo, progress: bool = False) -> dict[str, dict]:
    """The conversion (``run.json`` of :mod:`cmax.sim.chunks`) of each of ``jobs`` whose output has a chunk folder
    beside it, by name (its source hashed once here, with a bar [bytes] when ``progress``: :func:`_hashing_bar`);
    ``redo`` names and unreadable sources (they fail their own video) are left out."""
    from cmax.sim.chunks import chunk_folder

    kept, sizes = [], {}
    for job in jobs:
        if job.name in redo or not chunk_folder(output_dir / f"{job.name}.h5").is_dir():
            continue
        try:
            sizes[job.name] = _source_bytes(job.source)
        except (OSError, ValueError):
            continue
        kept.append(job)
    runs: dict[str, dict] = {}
    if not kept:
        return runs
    with _hashing_bar(sum(sizes.values()), "hashing videos with kept chunks (SHA-256, checked against them)",
                      progress=progress) as bar:
        for job in kept:
            try:
                runs[job.name] = _chunk_run(source_signature(job.source, bar.update), settings.for_video(job.name))
            except (OSError, ValueError):
                continue
    return runs


def _check_unlisted_outputs(jobs, videos: dict, output_dir: Path, path: Path, redo, runs: dict[str, dict]) -> None:
    """Refuse (FileExistsError, naming them) files at the outputs of ``jobs`` that the manifest ``videos``
    does not list as theirs (see :func:`_listed_output`), but for outputs this very conversion (``runs``:
    :func:`_kept_runs`) wrote from the chunks still kept beside them (:func:`cmax.sim.chunks.written_from_chunks`:
    written again from them); ``redo`` names are being overwritten on purpose."""
    foreign = [output for job in jobs if job.name not in redo
               for output in [output_dir / f"{job.name}.h5"]
               if os.path.lexists(output) and not _listed_output(videos.get(job.name), output, output_dir)
               and not (job.name in runs and written_from_chunks(output, runs[job.name]))]
    if foreign:
        names = ", ".join(output.name for output in foreign[:5]) + (" ..." if len(foreign) > 5 else "")
        listed = f"{path} does not list" if os.path.lexists(path) else f"there is no {MANIFEST} listing"
        raise FileExistsError(f"{len(foreign)} output file(s) already exist in {output_dir} and {listed} them as "
                              f"converted: {names}; nothing was converted; pass --overwrite (overwrite=True) to "
                              "replace them, or convert into another folder")


def _check_folder_outputs(jobs, output_dir: Path) -> None:
    """Refuse (IsADirectoryError, naming them) folders at the outputs ``output_dir/<name>.h5`` of ``jobs``, with or
    without ``overwrite``, before anything is converted: a video's events are written to a file there, which
    ``overwrite`` may replace but never a folder (a link to a folder is a link, replaced as a file is)."""
    folders = [output for job in jobs for output in [output_dir / f"{job.name}.h5"]
               if output.is_dir() and not output.is_symlink()]
    if folders:
        names = ", ".join(output.name for output in folders[:5]) + (" ..." if len(folders) > 5 else "")
        raise IsADirectoryError(f"{len(folders)} output(s) of this conversion are folders in {output_dir}: {names}; "
                                "nothing was converted: each video is written to a file of that name, and "
                                "--overwrite (overwrite=True) replaces files, never folders: move or rename them, "
                                "or convert into another folder")


def _check_kept_chunks(output_dir: Path, runs: dict[str, dict]) -> None:
    """Refuse (ValueError, one line naming each video and what differs) chunks kept beside the outputs of the
    videos ``runs`` names (:func:`_kept_runs`) by a conversion of another source, settings or code."""
    from cmax.sim.chunks import kept_problem

    problems = [f"{name}: {problem}" for name, run in runs.items()
                if (problem := kept_problem(output_dir / f"{name}.h5", run)) is not None]
    if problems:
        raise ValueError(f"{len(problems)} video(s) have chunks of an interrupted conversion that differs from this "
                         "one; nothing was converted: " + " | ".join(problems))


def _verification_bar(videos: dict, sources: dict, progress: bool):
    """A tqdm bar [bytes] on stderr over what verifying the converted ``videos`` of a manifest (name: entry) reads
    to hash: the bytes each entry records of its source (those in ``sources``, name: path) and of its output;
    shown when ``progress`` and they hold more than :data:`cmax.io.window_store.HASH_PROGRESS_BYTES`."""
    from tqdm.auto import tqdm

    from cmax.io.window_store import HASH_PROGRESS_BYTES

    total = 0
    for name, entry in videos.items():
        if entry.get("status") != "ok":
            continue
        signature = entry.get("source_signature")
        if name in sources and isinstance(signature, dict) and _is_count(signature.get("bytes")):
            total += signature["bytes"]
        total += entry["bytes"] if _is_count(entry.get("bytes")) else 0
    return tqdm(total=total, desc="verifying converted videos (SHA-256 of sources and outputs)", unit="B",
                unit_scale=True, unit_divisor=1024, leave=False, disable=not progress or total <= HASH_PROGRESS_BYTES)


def _convert_locked(jobs, output_dir, settings, workers, missing, catalogue, shard, progress, on_result, redo,
                    overwrite=False, chunk_frames=None):
    path = output_dir / MANIFEST
    manifest = _new_manifest(settings, catalogue, shard, missing)
    previous_videos: dict = {}
    if os.path.lexists(path):
        previous = load_manifest(path)
        if previous["settings"] != manifest["settings"]:
            difference = settings_difference(previous["settings"], manifest["settings"])
            raise ValueError(f"{path} was written with other settings ({difference}); "
                             "convert into another folder or remove it")
        previous_videos = previous["videos"]
        manifest["videos"] = {name: entry for name, entry in previous["videos"].items() if name not in redo}
    _check_folder_outputs(jobs, output_dir)
    runs: dict[str, dict] = {}     # by name: the conversion of a video with kept chunks, its source hashed once
    # the outputs there now are checked below (listed, or refused unless overwrite); one that appears later is not
    present = {job.name for job in jobs if os.path.lexists(output_dir / f"{job.name}.h5")}
    if not overwrite:  # a file the manifest does not list is a user's or another run's: never replaced unasked
        runs = _kept_runs(jobs, output_dir, settings, redo, progress)
        _check_unlisted_outputs(jobs, previous_videos, output_dir, path, redo, runs)
        # nor are kept chunks of another run thrown away unasked (with chunk_frames None too: a video converted
        # without chunks removes those kept beside its output once it is recorded)
        _check_kept_chunks(output_dir, runs)
    sources = {job.name: job.source for job in jobs}
    names = set(sources)
    with _verification_bar(manifest["videos"], sources, progress) as hashed:
        for name, entry in manifest["videos"].items():  # never skip a video whose source changed
            if entry["status"] == "ok" and name in sources:
                if not os.path.lexists(sources[name]):  # deleted after its conversion (to free space): nothing to redo
                    print(f"cmax: note: {name}: its source {sources[name]} is not there (deleted or moved since it "
                          "was converted); its output is kept as converted, once verified", file=sys.stderr)
                    continue
                problem = source_problem(entry, sources[name], hashed.update)
                if problem is not None:
                    manifest["videos"][name] = dict(entry, status="failed",
                                                    error=f"the source changed since it was converted: {problem}")
                    print(f"cmax: note: {name}: the source changed since it was converted ({problem}); "
                          "converting it again", file=sys.stderr)
        for name, entry in manifest["videos"].items():  # never list a file that is not there as it was
            if entry["status"] == "ok":
                try:
                    problem = output_problem(entry, entry_output(entry, output_dir), hashed.update)
                except ValueError as error:  # an output path outside the folder
                    problem = str(error)
                if problem is not None:
                    manifest["videos"][name] = dict(entry, status="failed", error=f"output not verified: {problem}")
                    print(f"cmax: note: {name}: output not verified ({problem}); "
                          + ("converting it again" if name in names else "listed as failed"), file=sys.stderr)
    todo = [job for job in jobs if manifest["videos"].get(job.name, {}).get("status") != "ok"]
    for job in (job for job in jobs if job not in todo):   # verified and skipped: chunks a stop left
        _remove_chunks(output_dir / f"{job.name}.h5")
    manifest["totals"] = _totals(manifest["videos"])
    write_manifest(path, manifest)
    if (note := _other_chunks_note(output_dir, names)) is not None:
        print(note, file=sys.stderr)
    from tqdm.auto import tqdm

    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="videos", unit="video",
               disable=not progress, position=0)
    unsaved: list[OSError] = []

    def record(result: VideoResult) -> None:
        manifest["videos"][result.name] = _manifest_entry(result)
        manifest["videos"] = dict(sorted(manifest["videos"].items()))
        manifest["totals"] = _totals(manifest["videos"])
        try:
            write_manifest(path, manifest)
            unsaved.clear()
            if result.status == "ok":     # recorded as verified: its kept chunks are done with
                _remove_chunks(output_dir / f"{result.name}.h5")
        except OSError as error:  # a full disk: go on, the next record retries; the last try below says it once
            unsaved[:] = [error]
        bar.update(1)
        bar.set_postfix_str(f"{result.name} {result.status}")
        if on_result is not None:
            on_result(result)

    def chunking(job: VideoJob) -> _Chunking:
        # redo (--overwrite of one file): chunks of the same run continue (the same events as starting over)
        kept = "resume_or_restart" if overwrite or job.name in redo else "resume"
        return _Chunking(chunk_frames, kept, runs.get(job.name, {}).get("source"),
                         replace=overwrite or job.name in present)

    try:
        if workers == 1 or len(todo) <= 1:
            for job in todo:
                record(_run_job(job, output_dir / f"{job.name}.h5", settings, 1 if progress else None,
                                chunking(job)))
        else:
            _run_parallel(todo, output_dir, settings, workers, progress, record, chunking)
    finally:
        bar.close()
    if unsaved:
        write_manifest(path, manifest)  # a last try; raises when the disk is still full
    return manifest


def _other_chunks_note(output_dir: Path, names: set[str]) -> str | None:
    """A note naming the chunk folders in ``output_dir`` of videos other than ``names`` (interrupted conversions
    this one does not continue: they hold disk space until their videos are converted), or None."""
    suffix = ".h5.chunks"
    others = sorted(path.name for path in output_dir.glob(f".*{suffix}")
                    if path.is_dir() and path.name[1:-len(suffix)] not in names)
    if not others:
        return None
    listed = ", ".join(others[:5]) + (", ..." if len(others) > 5 else "")
    return (f"cmax: note: {output_dir} holds the kept chunks of {len(others)} interrupted conversion(s) of other "
            f"videos than this run's ({listed}): convert those videos into it to continue them, or remove the "
            "folders")


def _remove_chunks(output: Path) -> None:
    """Remove the chunks kept beside ``output`` (its conversion is recorded as verified), and what an earlier
    removal cut short left (:func:`cmax.sim.chunks.remove_chunk_folder`)."""
    from cmax.sim.chunks import chunk_folder, remove_chunk_folder

    folder = chunk_folder(output)
    if folder.is_dir() or folder.with_name(folder.name + ".removed").is_dir():
        remove_chunk_folder(output)


# -- worker processes -------------------------------------------------------------------
def _worker(connection, main_pid: int, job: VideoJob, output: Path, settings: ConvertSettings,
            position: int | None, chunking: _Chunking = _Chunking()) -> None:
    """Entry point of a worker process: one video, the result sent back through ``connection``."""
    die_with_parent(main_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the workers itself
    result, caught = recorded(lambda: _run_job(job, output, settings, position, chunking))   # re-issued by the parent
    connection.send((result, caught))
    connection.close()


def _worker_context():
    """``forkserver`` where there is one (workers forked from a clean server that has this module
    imported: fast to start, no inherited threads), else ``spawn``."""
    import multiprocessing

    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload([__name__])
        start_forkserver(context)       # Ctrl-C while it imports: no traceback of the server's
        return context
    return multiprocessing.get_context("spawn")


def _describe_exit(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exited with status {exitcode} without a result"


def _run_parallel(todo, output_dir, settings, workers, progress, record, chunking=lambda job: _Chunking()) -> None:
    """Each job in its own worker process, at most ``workers`` at once; all killed if this one stops.

    The parent waits on each worker's pipe: it becomes readable with the result,
    or at end-of-file when the worker died without one.
    """
    from multiprocessing.connection import wait

    context = _worker_context()
    pending = list(enumerate(todo))[::-1]
    running: dict[Any, tuple[Any, VideoJob]] = {}  # receiving end of the pipe -> (process, job)
    try:
        while pending or running:
            while pending and len(running) < workers:
                number, job = pending.pop()
                receive, send = context.Pipe(duplex=False)
                process = context.Process(
                    target=_worker, name=f"cmax-simulate-{job.name}", daemon=True,
                    args=(send, os.getpid(), job, output_dir / f"{job.name}.h5", settings,
                          1 + number % workers if progress else None, chunking(job)),
                )
                # a SIGTERM or Ctrl-C now stops the run once the worker is recorded (stopped below)
                with sigterm_deferred(), sigint_deferred():
                    process.start()
                    send.close()  # the worker holds the only writing end: its death reads as end-of-file
                    running[receive] = (process, job)
            for receive in wait(list(running)):
                process, job = running.pop(receive)
                try:
                    result, caught = receive.recv()
                except Exception:  # EOFError: died without a result; or a message cut short
                    result, caught = None, []
                finally:
                    receive.close()
                reissue(job.name, caught, stacklevel=1)
                process.join(timeout=60)
                if process.exitcode is None:  # sent its result but does not exit
                    process.kill()
                    process.join()
                if not isinstance(result, VideoResult):
                    output = output_dir / f"{job.name}.h5"
                    _discard_after_stop(output, process.pid)
                    result = _failed(job, output, f"worker process {_describe_exit(process.exitcode)}")
                record(result)
    finally:  # interrupted (Ctrl-C) or failed: stop the workers, remove what they were writing
        with _sigint_ignored():  # a second Ctrl-C must not cut the clean-up short
            for process, _ in running.values():
                process.kill()
            for receive, (process, job) in running.items():
                process.join()
                receive.close()
                _discard_after_stop(output_dir / f"{job.name}.h5", process.pid)


#: Longest wait [s] for the lock of a stopped worker's output before its temporaries are left to the next run.
STOPPED_WORKER_WAIT_S = 5.0


def _discard_after_stop(output: Path, pid: int | None, wait_s: float = STOPPED_WORKER_WAIT_S) -> None:
    """Remove the temporaries (``.partial``, lock) of a worker (process ``pid``) that was killed or died while
    writing ``output``, under the output's lock (:func:`cmax.io.atomic.discard_leftovers`: a file of another live
    writer is left alone). ``join`` can return before the worker is gone: a worker is the child of the
    ``forkserver``, and when a SIGTERM to the process group (``timeout``, a batch system) ended the server too,
    ``join`` returns at once while the killed worker still holds its lock; so while process ``pid`` still exists
    the lock is waited for, up to ``wait_s`` seconds. A lock still held once it is gone (or when ``pid`` is None)
    is another writer's: left at once. The same holds for the chunk it was keeping (:mod:`cmax.sim.chunks`); the
    chunks it kept stay, to be continued."""
    from cmax.sim.chunks import chunk_folder

    deadline = time.monotonic() + wait_s
    chunks = chunk_folder(output)
    targets = [output, chunks, *sorted({chunks / name.rsplit(".", 2)[0] for name in
                                        (os.listdir(chunks) if chunks.is_dir() else ()) if name.endswith(".partial")})]
    for target in targets:
        while True:
            worker_alive = pid is not None and _process_exists(pid)
            try:
                discard_leftovers(target)
                break
            except OutputLockedError:
                if not worker_alive or time.monotonic() >= deadline:
                    break
                time.sleep(0.02)
            except OSError:
                break


def _process_exists(pid: int) -> bool:
    """Whether a process ``pid`` exists (a zombie too): ``kill(pid, 0)``."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextmanager
def _sigint_ignored():
    """Ignore SIGINT inside the block (main thread only: elsewhere Python cannot change handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.default_int_handler)
