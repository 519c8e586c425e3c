"""Frame sources: videos, image folders and arrays as streams of grey frames.

A *frame source* is an iterable of ``(frame, t_us)`` pairs, ``frame`` a
(H, W) grey image with values in [0, 255] -- float32 by default, or uint8 with
``dtype=np.uint8`` (exact 8-bit values, the fastest input of
:class:`cmax.sim.esim.EventSimulator`) -- ``t_us`` an int time in
microseconds, strictly increasing, with attributes ``width``, ``height``
(pixels, after resizing), ``fps`` (frames per second, or None) and
``frame_count`` (int, or None when unknown). Sources are re-iterable: every
``iter()`` starts from the beginning and reads lazily, one frame at a time,
so hours of video stream in constant memory (see
:func:`cmax.sim.sampling.iter_upsample`).

Prefetching: :class:`VideoFileSource` decodes its stream in a background
thread and :class:`ImageFolderSource` decodes its images in a small pool of
``decoders`` threads (default :func:`cmax.sim.prefetch.default_decoders`: the
available cores, at most 4), several images at once, at most ``prefetch``
frames (default 4) ahead of the consumer. OpenCV releases the GIL while it
decodes, as do zlib and the compiled kernel of :mod:`cmax.sim.png` (which
reads greyscale 8- and 16-bit PNGs, the same pixels as OpenCV, faster), so
decoding overlaps with the simulation of the previous frames;
memory grows by at most ``prefetch`` frames. The frames come in the same
order and with the same values as without prefetching. Errors of a decoder
are raised in the consuming thread, at the frame where they happened, naming
the file; stopping the iteration early (``break``, an error,
``KeyboardInterrupt``) stops the threads. ``prefetch=0`` decodes in the
consuming thread.

Colour is converted to grey with OpenCV's ``BGR2GRAY`` on the 8-bit values
(as the reference ESIM does); 16-bit images are scaled by ``255 / 65535``.
Resizing to ``size = (W, H)`` uses ``cv2.INTER_AREA`` on the float grey
frame, so the result is not re-quantised to 8 bits (with ``dtype=np.uint8``
it is rounded to whole grey values).

Errors: a missing path raises :class:`FileNotFoundError`; a file OpenCV
cannot decode (no frames, an unreadable image, a video that ends well before
its container says) or a truncated or corrupt PNG raises :class:`DecodeError`
naming the file; zero frames,
frames of different sizes in a folder and non-increasing times raise
:class:`ValueError`. A path that is not valid UTF-8 (a file name in another
encoding, read by Python with surrogate escapes) raises :class:`ValueError`
naming its bytes before OpenCV sees it: OpenCV crashes the process on it
(a segmentation fault), so such a video or image has to be renamed.
"""
from __future__ import annotations

import math
import os
import re
import warnings
from pathlib import Path
from typing import Iterator, Protocol, Union, runtime_checkable

import cv2
import numpy as np

from cmax.sim.png import PngError, read_png
from cmax.sim.prefetch import (DEFAULT_PREFETCH, _check_decoders, _check_prefetch, ordered_map,
                               prefetched)

__all__ = [
    "DEFAULT_PREFETCH",
    "IMAGE_SUFFIXES",
    "ArraySource",
    "DecodeError",
    "FrameSource",
    "ImageFolderSource",
    "VideoFileSource",
    "avi_rate_problem",
    "bare_stream_problem",
    "mp4_timing_problem",
    "open_source",
    "prefetched",
    "read_timestamps",
]

#: Image files an :class:`ImageFolderSource` lists (lower-case suffixes).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
#: How far before ``t0_s`` a :class:`VideoFileSource` seeks, in µs (the frames between are decoded and skipped).
SEEK_MARGIN_US = 1_000_000
#: Timestamp files looked for, in this order, in the folder and then its parent.
_TIMESTAMP_FILES = ("images.txt", "timestamps.txt")

PathLike = Union[str, Path]
Size = tuple[int, int]


class DecodeError(ValueError):
    """A video or image file could not be decoded (named in the message)."""


#: The first bytes of a JPEG image: a file that starts with them and is read as a video is a bare MJPEG stream.
_JPEG_START = b"\xff\xd8\xff"


def bare_stream_problem(path: PathLike) -> str | None:
    """Why the video file ``path`` cannot be converted when it is a bare MJPEG stream (JPEG images one after
    another, no container: ``.mjpeg`` as IP cameras and ``ffmpeg -f mjpeg`` write it, whatever its suffix): it
    stores no frame times, and FFmpeg's decoder invents 25 frames/s, so its times would be guessed. None for any
    other file (the container's times are used).

    >>> import tempfile
    >>> clip = Path(tempfile.mkdtemp()) / "clip.avi"
    >>> _ = clip.write_bytes(bytes([0xFF, 0xD8, 0xFF, 0xE0]) + bytes(60))   # a JPEG image's first bytes
    >>> bare_stream_problem(clip).split(":")[1]
    ' a bare MJPEG stream (JPEG images one after another, no container)'
    """
    path = Path(path)
    with open(path, "rb") as file:
        head = file.read(len(_JPEG_START))
    if head != _JPEG_START:
        return None
    framed = path.with_suffix(".mkv") if path.suffix.lower() != ".mkv" else path.with_name(f"{path.stem}_framed.mkv")
    return (f"{path}: a bare MJPEG stream (JPEG images one after another, no container): it stores no frame times "
            "and its frame rate would be guessed (the decoder assumes 25 frames/s); put it in a container at its "
            f"real rate, e.g. ffmpeg -framerate RATE -i {path} -c copy {framed}, or write its "
            "frames as images with a timestamps.txt (one time in seconds per image) and convert that folder")


def _avi_rate_fields(head: bytes) -> tuple[int, int, int] | None:
    """``(frame period [µs] of the main header avih, dwScale, dwRate of the first video stream header strh)`` of
    an AVI file's first bytes ``head``; None for another file, or an AVI whose headers are not in ``head``.

    >>> import struct
    >>> avih = b"avih" + struct.pack("<II", 56, 0) + bytes(52)
    >>> strh = b"strh" + struct.pack("<I", 56) + b"vidsMJPG" + bytes(12) + struct.pack("<II", 1, 0)
    >>> _avi_rate_fields(b"RIFF" + bytes(4) + b"AVI LIST" + bytes(8) + avih + strh + bytes(28))
    (0, 1, 0)
    """
    if head[:4] != b"RIFF" or head[8:12] != b"AVI ":
        return None
    main = head.find(b"avih")
    if main < 0 or main + 12 > len(head):
        return None
    period = int.from_bytes(head[main + 8: main + 12], "little")
    stream = head.find(b"strh")
    while 0 <= stream and stream + 36 <= len(head):
        if head[stream + 8: stream + 12] == b"vids":
            return (period, int.from_bytes(head[stream + 28: stream + 32], "little"),
                    int.from_bytes(head[stream + 32: stream + 36], "little"))
        stream = head.find(b"strh", stream + 4)
    return None


def avi_rate_problem(path: PathLike) -> str | None:
    """Why the video file ``path`` cannot be converted when it is an AVI whose headers state no frame rate: its
    video stream's ``dwScale`` or ``dwRate`` is 0 and the main header's frame period too (broken writers leave
    them so). FFmpeg then assumes 25 frames/s and OpenCV reports that rate and times from it, so the frames' times
    would be guessed. None for any other file, and for an AVI that states its rate in either header (FFmpeg takes
    the frame period when the stream's rate is 0).

    >>> import struct, tempfile
    >>> clip = Path(tempfile.mkdtemp()) / "clip.avi"
    >>> avih = b"avih" + struct.pack("<II", 56, 0) + bytes(52)
    >>> strh = b"strh" + struct.pack("<I", 56) + b"vidsMJPG" + bytes(12) + struct.pack("<II", 1, 0)
    >>> _ = clip.write_bytes(b"RIFF" + bytes(4) + b"AVI LIST" + bytes(8) + avih + strh + bytes(28))
    >>> avi_rate_problem(clip).split(":")[1]
    " its AVI headers state no frame rate (the video stream's scale/rate 1/0, the main header's frame period 0 µs)"
    """
    path = Path(path)
    with open(path, "rb") as file:
        fields = _avi_rate_fields(file.read(1 << 16))
    if fields is None:
        return None
    period, scale, rate = fields
    if (scale and rate) or period:
        return None
    fixed = path.with_suffix(".mkv")
    return (f"{path}: its AVI headers state no frame rate (the video stream's scale/rate {scale}/{rate}, the main "
            "header's frame period 0 µs): the decoder would assume 25 frames/s and the frames' times would be "
            f"guessed; state its real rate with ffmpeg's -r before the input, e.g. ffmpeg -r RATE -i {path} -c copy "
            f"{fixed}, or write its frames as images with a timestamps.txt (one time in seconds per image) and "
            "convert that folder")


#: The largest ``moov`` box :func:`mp4_timing_problem` reads (bytes); a larger one is not checked.
_MAX_MOOV_BYTES = 1 << 26
#: ISO base media (mp4, mov, 3gp) container boxes :func:`_mp4_boxes` descends into on the way to a track's ``stts``.
_MP4_CONTAINERS = (b"trak", b"mdia", b"minf", b"stbl")


def _mp4_boxes(data: bytes, start: int, end: int) -> Iterator[tuple[bytes, int, int]]:
    """``(type, payload start, box end)`` of the ISO base media boxes in ``data[start:end]``, in order; stops at a
    box whose size does not fit (a truncated or foreign file).

    >>> list(_mp4_boxes((12).to_bytes(4, "big") + b"stts" + bytes(4), 0, 12))
    [(b'stts', 8, 12)]
    """
    i = start
    while i + 8 <= end:
        size, kind = int.from_bytes(data[i: i + 4], "big"), data[i + 4: i + 8]
        header = 8
        if size == 1 and i + 16 <= end:
            size, header = int.from_bytes(data[i + 8: i + 16], "big"), 16
        elif size == 0:
            size = end - i
        if size < header or i + size > end:
            return
        yield kind, i + header, i + size
        i += size


def _video_sample_durations(moov: bytes) -> tuple[int, int] | None:
    """``(samples, summed duration in the track's timescale)`` of the ``stts`` of the first video track (``hdlr``
    ``vide``) in the payload of a ``moov`` box; None without one (or with an empty ``stts``: a fragmented file,
    whose times are in its fragments)."""
    for kind, start, end in _mp4_boxes(moov, 0, len(moov)):
        if kind != b"trak":
            continue
        handler, stts = None, None
        pending = [(start, end)]
        while pending:
            low, high = pending.pop()
            for inner, a, b in _mp4_boxes(moov, low, high):
                if inner in _MP4_CONTAINERS:
                    pending.append((a, b))
                elif inner == b"hdlr" and b - a >= 12:
                    handler = moov[a + 8: a + 12]
                elif inner == b"stts" and b - a >= 8:
                    stts = moov[a: b]
        if handler != b"vide" or stts is None:
            continue
        count = min(int.from_bytes(stts[4:8], "big"), (len(stts) - 8) // 8)
        entries = [(int.from_bytes(stts[8 + 8 * k: 12 + 8 * k], "big"),         # (sample count, sample duration)
                    int.from_bytes(stts[12 + 8 * k: 16 + 8 * k], "big")) for k in range(count)]
        if not entries:
            return None
        return sum(n for n, _ in entries), sum(n * d for n, d in entries)
    return None


def mp4_timing_problem(path: PathLike) -> str | None:
    """Why the video file ``path`` cannot be converted when it is an mp4/mov whose video track states no frame
    durations: every sample of its ``stts`` table lasts 0 (broken writers leave it so). FFmpeg and OpenCV then
    make up a frame rate and times from it (a 10 fps clip came out at 0.5 fps, its frames 2 s apart), so the
    frames' times would be guessed. None for any other file, for a fragmented mp4 (times in its fragments) and
    for one whose ``moov`` box is larger than :data:`_MAX_MOOV_BYTES` (not checked).
    """
    path = Path(path)
    with open(path, "rb") as file:
        head = file.read(12)
        if head[4:8] != b"ftyp":
            return None
        size, offset = file.seek(0, os.SEEK_END), 0
        while offset + 8 <= size:                          # the top-level boxes: ftyp, mdat, moov, ... in any order
            file.seek(offset)
            header = file.read(16)
            length, kind = int.from_bytes(header[:4], "big"), header[4:8]
            skip = 8
            if length == 1 and len(header) == 16:
                length, skip = int.from_bytes(header[8:16], "big"), 16
            elif length == 0:
                length = size - offset
            if length < skip:
                return None
            if kind == b"moov":
                if length > _MAX_MOOV_BYTES:
                    return None
                file.seek(offset + skip)
                durations = _video_sample_durations(file.read(length - skip))
                if durations is None or durations[0] < 2 or durations[1] > 0:
                    return None
                return (f"{path}: its video track states no frame durations (each of its {durations[0]} samples "
                        "lasts 0 in its stts table): the decoder would make up a frame rate and the frames' times "
                        f"would be guessed; state its real rate with ffmpeg's -r before the input, e.g. ffmpeg -r RATE "
                        f"-i {path} -c copy {path.with_suffix('.mkv')}, or write its frames as images with a "
                        "timestamps.txt (one time in seconds per image) and convert that folder")
            offset += length
    return None


@runtime_checkable
class FrameSource(Protocol):
    """Iterable of ``(frame (H, W) float32 in [0, 255], t_us int)``; see the module docstring."""

    width: int
    height: int
    fps: float | None
    frame_count: int | None

    def __iter__(self) -> Iterator[tuple[np.ndarray, int]]: ...


# -- helpers ------------------------------------------------------------------------------
def _check_size(size: object) -> Size | None:
    if size is None:
        return None
    if (not isinstance(size, (tuple, list)) or len(size) != 2
            or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in size)):
        raise TypeError(f"size must be a (width, height) pair of integers, got {size!r}")
    if min(size) <= 0:
        raise ValueError(f"size must be positive (width, height) pixels, got {tuple(size)}")
    return int(size[0]), int(size[1])


def _check_dtype(dtype: object) -> type:
    """np.float32 or np.uint8 (the two output types of a frame source)."""
    try:
        kind = np.dtype(dtype)
    except TypeError:
        kind = None
    if kind not in (np.dtype(np.float32), np.dtype(np.uint8)):
        raise ValueError(f"dtype must be np.float32 or np.uint8, got {dtype!r}")
    return kind.type


def _to_grey(image: np.ndarray, size: Size | None, name: str,
             dtype: type = np.float32) -> np.ndarray:
    """(H, W) grey in [0, 255] of ``dtype`` from a grey, BGR or BGRA image, resized to ``size``.

    8-bit images stay 8-bit for ``dtype=np.uint8`` (no copy when grey and not
    resized); 16-bit ones are scaled by ``255 / 65535`` (rounded for uint8).
    """
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        image = cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise DecodeError(f"{name}: unsupported image layout {image.shape}")
    if image.dtype == np.uint16:
        grey = image.astype(np.float32) * np.float32(255 / 65535)
    elif image.dtype == np.uint8:
        grey = image if dtype is np.uint8 else image.astype(np.float32)
    else:
        raise DecodeError(f"{name}: unsupported pixel type {image.dtype} (expected 8 or 16 bit)")
    if size is not None and (grey.shape[1], grey.shape[0]) != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    if grey.dtype != dtype:  # uint16 or float resized, to uint8
        grey = np.rint(grey).astype(np.uint8)
    return grey


def _strictly_increasing(t_us: np.ndarray, what: str) -> None:
    steps = np.diff(t_us)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0])
        raise ValueError(f"{what}: timestamps must be strictly increasing; time {i + 1} "
                         f"({t_us[i + 1]} µs) follows time {i} ({t_us[i]} µs)")


def _mean_fps(t_us: np.ndarray) -> float | None:
    return None if t_us.size < 2 else (t_us.size - 1) * 1e6 / float(t_us[-1] - t_us[0])


#: Largest time a timestamp file may state in seconds (about the year 5100 as seconds since 1970); larger values
#: are another unit (ns or µs since 1970: 1.7e18, 1.7e15), never converted silently.
MAX_SECONDS = 1e11
#: Unit names and their size in seconds, smallest first (to name the unit of times too large for seconds).
_SMALLER_UNITS = (("nanoseconds", 1e-9), ("microseconds", 1e-6), ("milliseconds", 1e-3))


def _checked_seconds(seconds: np.ndarray, what: str) -> np.ndarray:
    """``seconds`` (float64, (T,)) if every value is finite and within ``MAX_SECONDS``; else a ValueError naming
    the first bad time and, for a large one, the unit it likely is (the one that puts it in 1973-5100 since 1970).

    >>> _checked_seconds(np.array([1.6e18, 1.65e18]), "timestamps.txt")
    Traceback (most recent call last):
    ...
    ValueError: timestamps.txt: time 0 (1.6e+18) is too large for seconds (5.07e+10 years): these look like nanoseconds (1600000000.000000 s since 1970 if so); write the times in seconds
    """
    bad = ~np.isfinite(seconds)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: time {i} is {seconds[i]} (times must be finite seconds)")
    large = np.abs(seconds) > MAX_SECONDS
    if large.any():
        i = int(np.flatnonzero(large)[0])
        value = float(seconds[i])
        unit = next((name for name, size in _SMALLER_UNITS if 1e8 <= abs(value) * size <= MAX_SECONDS), None)
        guess = ("another unit (ns? µs?)" if unit is None else
                 f"{unit} ({value * dict(_SMALLER_UNITS)[unit]:.6f} s since 1970 if so)")
        raise ValueError(f"{what}: time {i} ({value:.6g}) is too large for seconds ({value / 3.15576e7:.3g} years): "
                         f"these look like {guess}; write the times in seconds")
    return seconds


def _seconds_to_us(seconds: np.ndarray) -> np.ndarray:
    return np.rint(np.asarray(seconds, dtype=np.float64) * 1e6).astype(np.int64)


# -- arrays -------------------------------------------------------------------------------
class ArraySource:
    """Frames held in memory.

    Parameters
    ----------
    frames : array_like, shape (T, H, W)
        Grey values in [0, 255] (any real dtype), T >= 1.
    timestamps_us : array_like of int, shape (T,)
        Strictly increasing times in µs.
    size : (int, int), optional
        Output (width, height); frames are resized with ``INTER_AREA``.
    dtype : np.float32 or np.uint8
        Type of the yielded frames; uint8 needs whole grey values in ``frames``.
    """

    def __init__(self, frames: np.ndarray, timestamps_us: np.ndarray, *,
                 size: Size | None = None, dtype: type = np.float32) -> None:
        frames = np.asarray(frames)
        if frames.ndim != 3 or 0 in frames.shape:
            raise ValueError(f"frames must have shape (T, H, W) with T >= 1, got {frames.shape}")
        if frames.dtype.kind not in "uif":
            raise TypeError(f"frames must hold grey values, got dtype {frames.dtype}")
        low, high = float(frames.min()), float(frames.max())
        if not (0 <= low and high <= 255):
            raise ValueError(f"frames must hold grey values in [0, 255], got [{low}, {high}]")
        self.dtype = _check_dtype(dtype)
        whole = frames.dtype.kind in "iu" or np.array_equal(frames, np.rint(frames))
        if self.dtype is np.uint8 and not whole:
            raise ValueError("dtype=np.uint8 needs frames of whole grey values")
        times = np.asarray(timestamps_us)
        if times.shape != (frames.shape[0],):
            raise ValueError(f"timestamps_us must have shape ({frames.shape[0]},), got {times.shape}")
        if times.dtype.kind not in "iu":
            raise TypeError(f"timestamps_us must hold integer µs, got dtype {times.dtype}")
        times = times.astype(np.int64)
        _strictly_increasing(times, "ArraySource")
        self._frames, self.timestamps_us, self._size = frames, times, _check_size(size)
        self.width, self.height = self._size or (frames.shape[2], frames.shape[1])
        self.fps, self.frame_count = _mean_fps(times), int(frames.shape[0])

    def __len__(self) -> int:
        return self.frame_count

    def __iter__(self) -> Iterator[tuple[np.ndarray, int]]:
        for frame, t in zip(self._frames, self.timestamps_us.tolist()):
            grey = np.array(frame, dtype=np.float32)
            if self._size is not None and (grey.shape[1], grey.shape[0]) != self._size:
                grey = cv2.resize(grey, self._size, interpolation=cv2.INTER_AREA)
            yield (grey if self.dtype is np.float32 else np.rint(grey).astype(np.uint8)), t


# -- image folders ------------------------------------------------------------------------
def _natural_key(path: Path) -> list[object]:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _list_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()),
                  key=_natural_key)


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_timestamps(path: PathLike, folder: PathLike | None = None) -> tuple[np.ndarray, list[Path]]:
    """Times and image paths from an ESIM- or ECD-style timestamp file.

    Accepted line formats (blank lines and ``#`` comments are skipped; one
    format per file):

    * ``t`` -- time in seconds; line ``i`` belongs to the ``i``-th image of
      ``folder`` in natural name order (ESIM ``timestamps.txt``);
    * ``index t`` -- image index into that order and time in seconds;
    * ``t path`` -- time in seconds and the image path, relative to the
      timestamp file's directory or else to ``folder`` (ECD ``images.txt``).

    Parameters
    ----------
    path : str or Path
        The timestamp file.
    folder : str or Path, optional
        The image folder (default: the file's directory).

    Returns
    -------
    t_us : ndarray, int64, shape (T,)
        Times in µs (seconds rounded to whole µs), strictly increasing.
    images : list of Path, length T
    """
    path = Path(path)
    folder = path.parent if folder is None else Path(folder)
    if not path.is_file():
        raise FileNotFoundError(f"timestamp file not found: {path}")
    rows = [line.split() for line in path.read_text().splitlines()]
    rows = [row for row in rows if row and not row[0].startswith("#")]
    if not rows:
        raise ValueError(f"{path}: no timestamps (zero frames)")
    kinds = {("t" if len(r) == 1 else "index t" if _is_number(r[1]) else "t path")
             if len(r) in (1, 2) and _is_number(r[0]) else "bad" for r in rows}
    if len(kinds) != 1 or "bad" in kinds:
        raise ValueError(f"{path}: expected lines 't', 'index t' or 't path' (one format per file)")
    kind = kinds.pop()
    tokens = [r[1] if kind == "index t" else r[0] for r in rows]  # the time column as written
    if kind == "t path":
        seconds = [float(r[0]) for r in rows]
        images = []
        for row in rows:
            image = path.parent / row[1]
            images.append(image if image.is_file() else folder / row[1])
        missing = [p for p in images if not p.is_file()]
        if missing:
            raise FileNotFoundError(f"{path}: image {missing[0]} not found ({len(missing)} missing)")
    else:
        listed = _list_images(folder)
        if kind == "t":
            seconds, indices = [float(r[0]) for r in rows], list(range(len(rows)))
        else:
            if not all(float(r[0]).is_integer() for r in rows):
                raise ValueError(f"{path}: the index column must hold whole numbers")
            seconds, indices = [float(r[1]) for r in rows], [int(float(r[0])) for r in rows]
        if kind == "t" and len(rows) != len(listed):
            raise ValueError(f"{path} lists {len(rows)} times but {folder} holds {len(listed)} images")
        if min(indices) < 0 or max(indices) >= len(listed):
            raise ValueError(f"{path}: image index out of range [0, {len(listed)}) of {folder}")
        images = [listed[i] for i in indices]
    seconds = _checked_seconds(np.array(seconds, dtype=np.float64), str(path))
    note = _whole_number_note(tokens, seconds, str(path))
    if note is not None:
        warnings.warn(note, UserWarning, stacklevel=2)
    t_us = _seconds_to_us(seconds)
    _strictly_increasing(t_us, str(path))
    return t_us, images


#: Median step between frames, in seconds, from which whole-number times are taken for another unit (a warning).
WHOLE_STEP_S = 10.0


def _whole_number_note(tokens: list[str], seconds: np.ndarray, what: str) -> str | None:
    """The warning for a time column of whole numbers whose frames would lie ``WHOLE_STEP_S`` or more apart.

    ``tokens`` are the times as written, ``seconds`` (T,) their values. Frame times written as integers
    ``0 33 67 100`` are milliseconds (or µs) since the start far more often than seconds of a time-lapse
    (nothing in the file says which); read as seconds they stretch a second of video over half a minute.
    Times with a decimal point, and whole seconds less than ``WHOLE_STEP_S`` apart, give None.

    >>> _whole_number_note(["0", "33", "67"], np.array([0.0, 33.0, 67.0]), "t.txt")[:62]
    't.txt: every time is a whole number, 33.5 apart (the median): '
    >>> _whole_number_note(["0.000", "0.033"], np.array([0.0, 0.033]), "t.txt") is None
    True
    """
    if seconds.size < 2 or not all(re.fullmatch(r"[+-]?\d+", token) for token in tokens):
        return None
    step = float(np.median(np.diff(seconds)))
    if step < WHOLE_STEP_S:
        return None
    span = float(seconds[-1] - seconds[0])
    hours = f" ({span / 3600:.3g} h)" if span >= 3600 else ""
    return (f"{what}: every time is a whole number, {step:g} apart (the median): read as seconds, the "
            f"{seconds.size} frames span {span:g} s{hours}; if they are milliseconds ({span * 1e-3:g} s) "
            f"or microseconds ({span * 1e-6:g} s), write the times in seconds with a decimal point")


def _find_timestamps(folder: Path) -> Path:
    for directory in (folder, folder.parent):
        for name in _TIMESTAMP_FILES:
            if (directory / name).is_file():
                return directory / name
    raise FileNotFoundError(f"no timestamps for {folder}: pass timestamps= or put one of "
                            f"{', '.join(_TIMESTAMP_FILES)} in the folder or its parent")


def _opencv_path(path: str | os.PathLike, what: str = "file") -> str:
    r"""``path`` as the ``str`` given to OpenCV; a path that is not valid UTF-8 is a one-line ValueError.

    Python reads a file name in another encoding (``cl\xffip.avi``) as a ``str``
    with surrogate escapes; ``cv2.VideoCapture`` and ``cv2.imread`` crash the
    process on such a string (a segmentation fault, no error), so it is refused
    here, naming the bytes of the path.

    >>> _opencv_path(os.fsdecode(b"cl\xffip.avi"), "video")
    Traceback (most recent call last):
    ...
    ValueError: the video b'cl\xffip.avi' has a name that is not valid UTF-8, which OpenCV cannot open (it would crash): rename it
    """
    text = os.fspath(path)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError(f"the {what} {os.fsencode(text)!r} has a name that is not valid UTF-8, which OpenCV cannot "
                         "open (it would crash): rename it") from None
    return text


def _imread(path: Path) -> np.ndarray:
    """The image as stored (``IMREAD_UNCHANGED``: grey stays grey, no colour conversion).

    Greyscale 8- and 16-bit PNGs go through :func:`cmax.sim.png.read_png`
    (the same pixels, faster); everything else through ``cv2.imread``.
    """
    if path.suffix.lower() == ".png":
        try:
            image = read_png(path)
        except PngError as error:
            raise DecodeError(str(error)) from error
        except OSError as error:
            raise DecodeError(f"cannot read the image {path}: {error}") from error
        if image is not None:
            return image
    try:
        image = cv2.imread(_opencv_path(path, "image"), cv2.IMREAD_UNCHANGED)
    except cv2.error as error:
        raise DecodeError(f"OpenCV cannot decode the image {path}: {error}") from error
    if image is None:
        raise DecodeError(f"OpenCV cannot decode the image {path}")
    return image


def _read_image(path: Path, size: Size | None, dtype: type = np.float32) -> np.ndarray:
    return _to_grey(_imread(path), size, str(path), dtype)


def _check_time_range(t0_s: object, t1_s: object) -> None:
    """``t0_s``, ``t1_s``: None or finite seconds >= 0, ``t1_s`` after ``t0_s`` (ValueError otherwise)."""
    for name, value in (("t0_s", t0_s), ("t1_s", t1_s)):
        if value is not None and not (isinstance(value, (int, float, np.integer, np.floating))
                                      and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite time >= 0 in seconds, got {value!r}")
    if t0_s is not None and t1_s is not None and t1_s <= t0_s:
        raise ValueError(f"t1_s ({t1_s}) must be after t0_s ({t0_s})")


def range_words(t0_s: float | None, t1_s: float | None) -> str:
    """``t0_s``, ``t1_s`` (seconds after the first frame) in words, for messages.

    >>> range_words(0.1, 0.5), range_words(2.0, None)
    ('from 0.1 s to 0.5 s after the first frame', 'from 2.0 s after the first frame to the end')
    """
    if t1_s is None:
        return f"from {t0_s or 0} s after the first frame to the end"
    return f"from {t0_s or 0} s to {t1_s} s after the first frame"


def _in_range(t_us: np.ndarray, t0_s: float | None, t1_s: float | None) -> np.ndarray:
    """(T,) bool: the times ``t_us`` (int64 µs, increasing) with ``t0_s <= t - t_us[0] < t1_s`` (seconds after
    the first time; None: no bound).

    >>> _in_range(np.array([1_700_000_000_000_000, 1_700_000_000_050_000, 1_700_000_000_100_000]), 0.05, None)
    array([False,  True,  True])
    """
    elapsed = t_us - t_us[0]
    keep = np.ones(t_us.shape, bool)
    if t0_s is not None:
        keep &= elapsed >= int(round(t0_s * 1e6))
    if t1_s is not None:
        keep &= elapsed < int(round(t1_s * 1e6))
    return keep


class ImageFolderSource:
    """A folder of images with their times.

    Parameters
    ----------
    folder : str or Path
        Folder of images (``IMAGE_SUFFIXES``).
    timestamps : str, Path or array_like of int, optional
        A timestamp file (see :func:`read_timestamps`: ESIM ``timestamps.txt``,
        ``index t`` pairs, ECD ``images.txt``), or the times in **integer µs**
        of the folder's images in natural name order. Default: ``images.txt``
        or ``timestamps.txt`` in the folder, else in its parent.
    size : (int, int), optional
        Output (width, height); frames are resized with ``INTER_AREA``.
    t0_s, t1_s : float, optional
        Keep the images from ``t0_s`` (included) to ``t1_s`` (excluded) seconds
        after the first image, whatever clock the timestamps are on (0-based, or
        absolute as ROS or DSEC exports): ``t_first + t0_s <= t < t_first + t1_s``,
        as for a video. The times kept are not shifted. A range that selects no
        image raises ValueError naming the span of the images.
    dtype : np.float32 or np.uint8
        Type of the yielded frames (see the module docstring).
    prefetch : int
        Frames decoded ahead of the consumer, at most (0: decoded in the
        consuming thread, one at a time).
    decoders : int, optional
        Threads decoding images at once when ``prefetch > 0`` (at most
        ``prefetch`` are used); default
        :func:`cmax.sim.prefetch.default_decoders` (the available cores, at
        most 4).

    The first image is read at construction (for ``width``/``height``, and
    ``bit_depth``: 8, or 16 for a 16-bit first image, whose grey values
    ``v * 255 / 65535`` only float32 frames hold exactly); the others when
    iterated, where an image of another size raises ValueError.
    """

    def __init__(self, folder: PathLike, *, timestamps: PathLike | np.ndarray | None = None,
                 size: Size | None = None, t0_s: float | None = None, t1_s: float | None = None,
                 dtype: type = np.float32, prefetch: int = DEFAULT_PREFETCH, decoders: int | None = None) -> None:
        folder = Path(folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"image folder not found: {folder}")
        _check_time_range(t0_s, t1_s)
        self._size = _check_size(size)
        self.dtype, self.prefetch = _check_dtype(dtype), _check_prefetch(prefetch)
        self.decoders = _check_decoders(decoders)
        if timestamps is None or isinstance(timestamps, (str, Path)):
            file = _find_timestamps(folder) if timestamps is None else Path(timestamps)
            self.timestamps_us, self.images = read_timestamps(file, folder)
        else:
            times = np.asarray(timestamps)
            if times.dtype.kind not in "iu" or times.ndim != 1:
                raise TypeError("timestamps must be a path or a 1-D array of integer µs, got "
                                f"dtype {times.dtype} shape {times.shape} (for seconds pass "
                                "np.rint(t_s * 1e6).astype(np.int64))")
            self.images = _list_images(folder)
            if times.size != len(self.images):
                raise ValueError(f"{times.size} timestamps for {len(self.images)} images in {folder}")
            self.timestamps_us = times.astype(np.int64)
            _strictly_increasing(self.timestamps_us, str(folder))
        if not self.images:
            raise ValueError(f"no images in {folder} (zero frames)")
        if t0_s is not None or t1_s is not None:
            keep = _in_range(self.timestamps_us, t0_s, t1_s)
            if not keep.any():
                first, last = int(self.timestamps_us[0]), int(self.timestamps_us[-1])
                clock = "" if first == 0 else f"; on the timestamps' clock they start at {first * 1e-6:.6f} s"
                raise ValueError(f"{folder}: no images {range_words(t0_s, t1_s)} (zero frames): the "
                                 f"{len(self.images)} images span {(last - first) * 1e-6:.6f} s{clock}")
            self.timestamps_us = self.timestamps_us[keep]
            self.images = [image for image, kept in zip(self.images, keep) if kept]
        stored = _imread(self.images[0])
        first = _to_grey(stored, None, str(self.images[0]))
        self.bit_depth = 16 if stored.dtype == np.uint16 else 8
        self._shape = first.shape
        self.width, self.height = self._size or (first.shape[1], first.shape[0])
        self.stored_size = (int(first.shape[1]), int(first.shape[0]))  # (width, height) before resizing
        self.fps, self.frame_count = _mean_fps(self.timestamps_us), len(self.images)

    def __len__(self) -> int:
        return self.frame_count

    def __iter__(self) -> Iterator[tuple[np.ndarray, int]]:
        return ordered_map(self._decode, zip(self.images, self.timestamps_us.tolist()),
                           self.decoders, self.prefetch)

    def _decode(self, item: tuple[Path, int]) -> tuple[np.ndarray, int]:
        """One frame and its time; runs in a decoding thread."""
        path, t = item
        image = _imread(path)
        if image.shape[:2] != self._shape:
            raise ValueError(f"{path} is {image.shape[1]}x{image.shape[0]} pixels, the first image "
                             f"{self.images[0].name} {self._shape[1]}x{self._shape[0]}")
        return _to_grey(image, self._size, str(path), self.dtype), t


# -- video files --------------------------------------------------------------------------
def _stream_position(capture: cv2.VideoCapture, fps: float | None) -> float | None:
    """The last decoded frame's position in the stream, in frames, or None when OpenCV tells neither.

    The larger of OpenCV's ``CAP_PROP_PTS`` (the timestamp times the frame rate, from the stream's
    zero, not shifted to the first frame; some demuxers give none) and ``CAP_PROP_POS_MSEC`` (from the
    first frame) times ``fps``.
    """
    values = []
    prop = getattr(cv2, "CAP_PROP_PTS", None)
    if prop is not None:
        values.append(capture.get(prop))
    if fps:
        values.append(capture.get(cv2.CAP_PROP_POS_MSEC) * 1e-3 * fps)
    values = [float(v) for v in values if math.isfinite(v) and v >= 0]
    return max(values) if values else None


def _stopped_early(decoded: int, position: float | None, count: int, step: float | None = None) -> bool:
    """Whether a stream ended well before the ``count`` frames its container lists (truncated or corrupt).

    ``decoded`` frames were decoded, the last at stream ``position`` (frames from the stream's zero,
    :func:`_stream_position`; None: unknown), ``step`` frames after the one before it (None: unknown).
    Short means more than ``max(1, 1%)`` frames short. Matroska and WebM store no frame count: OpenCV
    estimates it from the duration and the stream's frame rate, which exceeds the frames of a
    variable-frame-rate stream or of one whose timestamps start after 0 (a cut segment); there the last
    frame still lies at the end of the stream, within its own display time (taken as long as the step
    before it). A truncated stream falls short on both counts.

    >>> _stopped_early(8, 51.0, 52), _stopped_early(25, 149.0, 150), _stopped_early(13, 12.0, 30)
    (False, False, True)
    >>> _stopped_early(28, 450.0, 500, step=50.0), _stopped_early(13, 12.0, 30, step=1.0)
    (False, True)
    """
    short = count - max(1, round(0.01 * count))
    if decoded >= short:
        return False
    return position is None or position + max(1.0, step or 0.0) < short


def _moved_note(path: str, moved: list[tuple[int, int, int]], frames: int) -> str:
    """The warning for frames whose container time was not after the frame before (``moved``: frame index,
    stated time, time before, in µs; ``frames`` read in all).

    >>> _moved_note("a.mkv", [(2, 40000, 40000)], 8)
    'a.mkv: 1 of its 8 frames has a time not after the frame before (duplicated or reordered timestamps in the container; the first: frame 2 at 40.000 ms, after 40.000 ms): each was placed 1 µs after the frame before, so the change to it happens within 1 µs'
    """
    index, stated, before = moved[0]
    verb = "has" if len(moved) == 1 else "have"
    return (f"{path}: {len(moved)} of its {frames} frames {verb} a time not after the frame before (duplicated or "
            f"reordered timestamps in the container; the first: frame {index} at {stated * 1e-3:.3f} ms, after "
            f"{before * 1e-3:.3f} ms): each was placed 1 µs after the frame before, so the change to it happens "
            "within 1 µs")


class VideoFileSource:
    """Frames of a video file (mp4, avi, mkv, ... whatever OpenCV's FFmpeg reads).

    Parameters
    ----------
    path : str or Path
        The video file.
    size : (int, int), optional
        Output (width, height); frames are resized with ``INTER_AREA``.
    t0_s, t1_s : float, optional
        Keep the frames from ``t0_s`` (included) to ``t1_s`` (excluded) seconds
        after the first frame (``t_first + t0_s <= t < t_first + t1_s``; the
        container's clock, which OpenCV starts at the stream's start, so
        ``t_first`` is 0 for nearly every file); the reader seeks near
        ``t0_s`` first. Times are not shifted to start at zero.
    dtype : np.float32 or np.uint8
        Type of the yielded frames (see the module docstring).
    prefetch : int
        Frames decoded ahead in a background thread (0: none).

    Times: each frame's presentation time from the container
    (``CAP_PROP_POS_MSEC`` after reading it), rounded to whole µs. When the
    container gives none (not finite, negative, or 0 after the first frame)
    the time is ``frame_index * 1e6 / fps``; when the rate is unknown too,
    iteration raises :class:`DecodeError` (times are never guessed). A time not after the previous one (duplicated or reordered
    timestamps) becomes the previous time + 1 µs, so times are always
    strictly increasing; a ``UserWarning`` at the end of the stream counts
    such frames and names the first.

    Decoding errors: a file OpenCV cannot open or that yields no frame, and a bare MJPEG stream (no
    container, no frame times: :func:`bare_stream_problem`) or an AVI whose headers state no frame rate
    (:func:`avi_rate_problem`: FFmpeg would assume 25 frames/s) or an mp4 whose video track states no frame
    durations (:func:`mp4_timing_problem`) raise :class:`DecodeError` at construction; a
    path that is not valid UTF-8 raises :class:`ValueError` (:func:`_opencv_path`: OpenCV would crash on it). When
    the decoder stops more than ``max(1, 1%)`` frames before the container's frame count, and the last
    frame decoded lies that far before the stream's end too (:func:`_stopped_early`: a Matroska count is
    an estimate, too large for a variable frame rate or a stream starting after 0), iteration raises
    :class:`DecodeError` after the frames it could decode (a truncated or
    corrupt stream). ``frame_count`` is the container's count (None when
    unknown or when ``t0_s``/``t1_s`` cut the video).
    """

    def __init__(self, path: PathLike, *, size: Size | None = None,
                 t0_s: float | None = None, t1_s: float | None = None,
                 dtype: type = np.float32, prefetch: int = DEFAULT_PREFETCH) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"video file not found: {self.path}")
        self._size = _check_size(size)
        self.dtype, self.prefetch = _check_dtype(dtype), _check_prefetch(prefetch)
        _check_time_range(t0_s, t1_s)
        self.t0_s, self.t1_s = t0_s, t1_s
        if (problem := bare_stream_problem(self.path) or avi_rate_problem(self.path)
                or mp4_timing_problem(self.path)) is not None:
            raise DecodeError(problem)                                 # times never guessed
        capture = self._open()
        try:
            fps = capture.get(cv2.CAP_PROP_FPS)
            count = capture.get(cv2.CAP_PROP_FRAME_COUNT)
            ok, image = capture.read()
            self.fps = float(fps) if math.isfinite(fps) and fps > 0 else None
            self._first_us = self._time_us(capture, first=True) if ok else 0  # t0_s, t1_s count from it
        finally:
            capture.release()
        if not ok or image is None:
            raise DecodeError(f"OpenCV opened {self.path} but decoded no frame from it")
        self._container_count = int(count) if math.isfinite(count) and count > 0 else None
        self.frame_count = self._container_count if t0_s is None and t1_s is None else None
        first = _to_grey(image, self._size, str(self.path))
        self.height, self.width = first.shape
        self.stored_size = (int(image.shape[1]), int(image.shape[0]))  # (width, height) before resizing

    def _open(self) -> cv2.VideoCapture:
        capture = cv2.VideoCapture(_opencv_path(self.path, "video"))
        if not capture.isOpened():
            capture.release()
            raise DecodeError(f"OpenCV cannot decode the video {self.path} "
                              "(not a video, an unsupported codec, or a truncated/corrupt file)")
        return capture

    def __len__(self) -> int:
        if self.frame_count is None:
            raise TypeError("the frame count of this video is unknown")
        return self.frame_count

    def _time_us(self, capture: cv2.VideoCapture, first: bool) -> int:
        msec = capture.get(cv2.CAP_PROP_POS_MSEC)
        if math.isfinite(msec) and msec >= 0 and (msec > 0 or first):
            return int(round(msec * 1000))
        index = max(0, int(capture.get(cv2.CAP_PROP_POS_FRAMES)) - 1)
        if not self.fps:
            raise DecodeError(f"{self.path}: frame {index} has no time in the container, which states no frame "
                              "rate either: its time would be guessed; write its frames as images with a "
                              "timestamps.txt (one time in seconds per image) and convert that folder")
        return int(round(index * 1e6 / self.fps))

    def __iter__(self) -> Iterator[tuple[np.ndarray, int]]:
        return prefetched(self._frames, self.prefetch)

    def _frames(self) -> Iterator[tuple[np.ndarray, int]]:
        t0_us = None if self.t0_s is None else self._first_us + int(round(self.t0_s * 1e6))
        t1_us = None if self.t1_s is None else self._first_us + int(round(self.t1_s * 1e6))
        # OpenCV seeks by frame number (time x frame rate): in a variable-frame-rate stream it can land seconds
        # past the time asked for. Seek SEEK_MARGIN_US before t0; a first frame after t0 (or none) means frames
        # from t0 on may have been passed over, and the stream is decoded from its start instead.
        seek_us = None if t0_us is None or t0_us - SEEK_MARGIN_US <= self._first_us else t0_us - SEEK_MARGIN_US
        capture = self._open()
        try:
            if seek_us is not None:
                capture.set(cv2.CAP_PROP_POS_MSEC, seek_us / 1000)
            previous, decoded, yielded, position, moved, step = None, 0, 0, None, [], None
            while True:
                ok, image = capture.read()
                got = ok and image is not None
                if previous is None and seek_us is not None and (not got or self._time_us(capture, False) > t0_us):
                    capture.release()  # the seek went too far (or past the end): from the start
                    capture, seek_us = self._open(), None
                    continue
                if not got:
                    break
                stated = self._time_us(capture, first=previous is None and seek_us is None)
                decoded = max(decoded, int(capture.get(cv2.CAP_PROP_POS_FRAMES)))
                position = _stream_position(capture, self.fps)
                t = stated if previous is None or stated > previous else previous + 1
                if t != stated:
                    moved.append((yielded, stated, previous))
                if previous is not None and self.fps:
                    step = (t - previous) * 1e-6 * self.fps  # the last interval, in frames
                previous = t
                if t0_us is not None and t < t0_us:
                    continue
                if t1_us is not None and t >= t1_us:
                    break
                yielded += 1
                yield _to_grey(image, self._size, str(self.path), self.dtype), t
            if moved:
                warnings.warn(_moved_note(str(self.path), moved, yielded), UserWarning, stacklevel=2)
            count = self._container_count
            finished = t1_us is None or (previous is not None and previous < t1_us)
            if finished and count is not None and _stopped_early(decoded, position, count, step):
                raise DecodeError(f"{self.path}: decoding stopped after frame {decoded} of the "
                                  f"{count} the container lists (truncated or corrupt video)")
            if yielded == 0:
                last = "" if previous is None else \
                    f": its last frame is {(previous - self._first_us) * 1e-6:.6f} s after the first"
                raise ValueError(f"{self.path}: no frames {range_words(self.t0_s, self.t1_s)} (zero frames){last}")
        finally:
            capture.release()


def open_source(source: PathLike | np.ndarray | FrameSource, *,
                timestamps: PathLike | np.ndarray | None = None, size: Size | None = None,
                t0_s: float | None = None, t1_s: float | None = None,
                dtype: type = np.float32, prefetch: int = DEFAULT_PREFETCH,
                decoders: int | None = None) -> FrameSource:
    """A frame source for a path, an array or an existing source.

    * an array (T, H, W): :class:`ArraySource`, ``timestamps`` in integer µs required;
    * a folder: :class:`ImageFolderSource` (``timestamps`` optional);
    * a ``.txt`` file: :class:`ImageFolderSource` of the file's folder with
      the file as timestamps (ECD ``images.txt``, ESIM ``timestamps.txt``);
    * any other file: :class:`VideoFileSource` (``t0_s``, ``t1_s`` apply to files and folders);
    * a frame source: returned unchanged (no other argument allowed).

    ``size``: ``(width, height)`` [px] to resize every frame to (``cv2.INTER_AREA``; None: the frames' own).
    ``dtype`` (np.float32 or np.uint8) and ``prefetch`` (frames decoded ahead
    in background threads; files only) are passed on; ``decoders`` (threads
    decoding images at once) applies to image folders only.

    Raises
    ------
    FileNotFoundError
        The path does not exist.
    ValueError, TypeError
        Arguments that do not apply to the kind of source.
    """
    if isinstance(source, np.ndarray):
        if timestamps is None:
            raise ValueError("an array source needs timestamps= (integer µs)")
        if t0_s is not None or t1_s is not None:
            raise ValueError("t0_s/t1_s apply to video files and image folders, not to an array (slice it)")
        if decoders is not None:
            raise ValueError("decoders= applies to image folders only (an array needs no decoding)")
        return ArraySource(source, np.asarray(timestamps), size=size, dtype=dtype)
    if isinstance(source, (str, Path)):
        path = Path(source)
        if not path.exists():
            raise FileNotFoundError(f"no such file or folder: {path}")
        if path.is_dir() or path.suffix.lower() == ".txt":
            if path.is_dir():
                return ImageFolderSource(path, timestamps=timestamps, size=size, t0_s=t0_s, t1_s=t1_s,
                                         dtype=dtype, prefetch=prefetch, decoders=decoders)
            return ImageFolderSource(path.parent, timestamps=path, size=size, t0_s=t0_s, t1_s=t1_s, dtype=dtype,
                                     prefetch=prefetch, decoders=decoders)
        if timestamps is not None:
            raise ValueError("timestamps= does not apply to a video file (it has its own times)")
        if decoders is not None:
            raise ValueError("decoders= applies to image folders only (a video stream is decoded "
                             "in order by one thread)")
        return VideoFileSource(path, size=size, t0_s=t0_s, t1_s=t1_s, dtype=dtype,
                               prefetch=prefetch)
    if isinstance(source, FrameSource):
        if any(v is not None for v in (timestamps, size, t0_s, t1_s, decoders)):
            raise ValueError("an existing frame source takes no timestamps/size/t0_s/t1_s/decoders")
        return source
    raise TypeError(f"cannot make a frame source from {type(source).__name__}")
