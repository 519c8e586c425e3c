"""Plain-text event files as used by the Event Camera Dataset (ECD).

One event per line, ``t x y p``: time in seconds (float), pixel column and row,
polarity 0/1 (Mueggler et al., "The event-camera dataset and simulator",
IJRR 2017, doi:10.1177/0278364917691115).
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from cmax.events import Events
from cmax.io._checks import check_polarity_encoding, check_stated_size, check_time_unit, polarity_01, times_to_us
from cmax.io.atomic import AtomicOutput, write_with
from cmax.io.errors import FormatError

__all__ = ["read_txt", "write_txt"]


def read_txt(
    path: str | os.PathLike, *, width: int | None = None, height: int | None = None, time_unit: str | None = None,
    polarity: str = "01", sort: bool = False,
) -> Events:
    """Read an ECD ``events.txt`` at ``path`` (``t[s] x y p`` per line) into :class:`Events`.

    Time stamps are in seconds (ECD's unit) unless ``time_unit`` states another
    (``'ms'``, ``'us'``), and are rounded to the nearest microsecond (half to
    even); a column of whole numbers only, read without a stated unit, is
    refused (integer microseconds are not ECD's seconds). Polarity is 0/1
    (ECD's encoding) unless ``polarity='signed'`` states -1/+1; other values
    raise :class:`FormatError`. The file stores no sensor
    size, so ``width`` and ``height`` are required (ECD's DAVIS240C: 240 x 180),
    unless its first line states it as rpg_e2vid's ``events.txt`` does (``W H``;
    a size given too must equal it). Lines starting with ``#`` are comments; a UTF-8 byte order mark at the
    file's start is ignored; lines may end in LF, CRLF or CR alone (an old Mac's), also mixed; UTF-16 text that
    starts with its byte order mark (Windows PowerShell's ``>``) is read as the same text. A first line of other
    words (a header, fields separated by commas, NUL bytes) is refused naming what it holds.
    Time must not go back unless ``sort=True`` (the events are then sorted by
    time, stable); a file whose third column is the sorted one is refused as
    ``x y t p`` columns, not ECD's order.
    """
    path = Path(path)
    unit = check_time_unit(time_unit) or "s"
    polarity = check_polarity_encoding(polarity)
    header, skip = _size_header(path)
    if header is not None:
        width, height = check_stated_size(width, height, header, f"{path} (its first line)")
    elif width is None or height is None:
        raise ValueError(f"{path} (txt) stores no sensor size: pass width= and height= (cmax: --size WxH)")
    try:
        table = _load_table(path, skip)
    except (ValueError, UnicodeDecodeError) as error:
        text = str(error).split("; use `usecols`")[0]      # numpy's advice on selecting columns does not apply
        raise FormatError(f"{path} is not an ECD text file of 't x y p' lines ({text})") from None
    if table.size == 0:
        return Events.empty(width, height)
    if table.shape[1] != 4:
        raise FormatError(f"{path}: expected 4 columns 't x y p', found {table.shape[1]}")
    if not np.isfinite(table[:, 1:]).all():
        raise FormatError(f"{path} contains non-finite numbers")
    if (len(table) >= 10 and (np.diff(table[:, 0]) < 0).any() and (np.diff(table[:, 2]) >= 0).all()
            and table[-1, 2] > table[0, 2]):    # refused with sort=True too: sorting would not mend the order
        raise FormatError(f"{path}: column 1 goes back in time while column 3 never does: the columns look like "
                          "'x y t p', but ECD text is 't x y p' (reorder them, e.g. awk '{print $3, $1, $2, $4}')")
    if time_unit is None:
        _refuse_whole_seconds(table[:, 0], path)
    t_us = times_to_us(table[:, 0], unit, f"{path}: column t")
    p = polarity_01(table[:, 3], polarity, f"{path}: column p")
    try:
        return Events(table[:, 1], table[:, 2], t_us, p, width, height, sort=sort, time_unit="us")
    except ValueError as error:
        raise FormatError(f"{path}: {error}") from None


def _load_table(path: Path, skip: int) -> np.ndarray:
    """The numbers of the text file ``path`` after its first ``skip`` lines, (N, columns) float64 (``#`` comments
    dropped). A byte order mark (Windows editors) is not text. A byte that is not UTF-8 (a Latin-1 comment) makes
    it read again with such bytes as U+FFFD, which no number holds: harmless in a comment, refused naming its row
    elsewhere (the second read goes line by line, slower; the first lets numpy read the file in blocks)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)   # no events
        encoding = _encoding(path)
        try:
            return np.loadtxt(path, dtype=np.float64, ndmin=2, comments="#", skiprows=skip, encoding=encoding)
        except UnicodeDecodeError:
            with open(path, encoding=encoding, errors="replace") as handle:
                return np.loadtxt(handle, dtype=np.float64, ndmin=2, comments="#", skiprows=skip)


def _size_header(path: Path) -> tuple[tuple[int, int] | None, int]:
    """``((width, height), lines to skip)`` when the first line that is not a comment holds exactly two positive
    integers (rpg_e2vid's ``events.txt`` header), else ``(None, 0)``."""
    try:
        with open(path, "rb") as file:
            head = file.read(_HEAD_BYTES)          # a binary file without newlines is not read whole here
        head = head.removeprefix(_UTF8_BOM)
    except OSError as error:
        raise FormatError(f"{path} cannot be read ({error})") from None
    full = len(head) == _HEAD_BYTES
    if head[:2] in _UTF16_BOMS:                    # as UTF-8 for the checks below (errors: a unit cut at the end)
        head = head.decode("utf-16", errors="replace").encode("utf-8")
    lines = head.splitlines()      # LF, CRLF or CR-only (old Mac) line ends, as np.loadtxt reads them
    for number, line in enumerate(lines[:-1] if full else lines):
        words = line.split()
        if not words or words[0].startswith(b"#"):
            continue
        if len(words) == 2 and all(word.isdigit() and int(word) > 0 for word in words):
            return (int(words[0]), int(words[1])), number + 1
        _check_event_line(path, words)
        return None, 0
    return None, 0


def _check_event_line(path: Path, words: list[bytes]) -> None:
    """Refuse a text file whose first line that is not a comment is not four numbers ``t x y p``, before a
    missing sensor size is asked for: a frame list (``images.txt``), ``timestamps.txt``, ``calib.txt`` or a
    trajectory is no event file, whatever size is given."""
    def number(word: bytes) -> bool:
        try:
            float(word)
        except ValueError:
            return False
        return True

    if len(words) == 4 and all(number(word) for word in words):
        return
    line = b" ".join(words).decode("utf-8", "replace")
    shown = line if len(line) <= 60 else line[:57] + "..."
    start = f"{path} is not an ECD text file of 't x y p' lines: its first line reads {shown!r}"
    if any(b"\0" in word for word in words):
        raise FormatError(f"{start}, which holds NUL bytes: UTF-16 text without a byte order mark, or binary data? "
                          "ECD text is ASCII or UTF-8 (UTF-16 is read when it starts with its byte order mark): "
                          "save it as UTF-8")
    separator = next((mark for mark in (",", ";") if mark in line), None)
    if separator is not None:
        raise FormatError(f"{start}, its fields separated by {separator!r} (a CSV), but ECD text separates 't x y p' "
                          "by spaces, and a CSV does not state its column order (Metavision's metavision_file_to_csv "
                          "writes 'x,y,p,t'): write its columns as 't x y p' lines (t in seconds) once you know them")
    if len(words) == 4:
        word = next(word for word in words if not number(word)).decode("utf-8", "replace")
        raise FormatError(f"{start}: {word!r} is not a number (a header line? ECD text has none: drop it, or make it "
                          "a comment with '#', and keep the columns in ECD's order 't x y p')")
    hint = ("; a list of frames (ECD images.txt, ESIM timestamps.txt) becomes events with "
            "`cmax simulate FOLDER -o events.h5`" if len(words) <= 2 else "")
    raise FormatError(f"{start} ({len(words)} column(s) where 4 columns are expected){hint}")


#: Bytes of a text file's start that :func:`_size_header` reads.
_HEAD_BYTES = 1 << 16
#: The UTF-8 byte order mark that Windows editors put at a text file's start: not text.
_UTF8_BOM = b"\xef\xbb\xbf"
#: The byte order marks of UTF-16 (little, big endian), which Windows PowerShell's ``>`` and ``Out-File`` write.
_UTF16_BOMS = (b"\xff\xfe", b"\xfe\xff")


def _encoding(path: Path) -> str:
    """The text encoding of the file ``path``: ``"utf-16"`` when it starts with a UTF-16 byte order mark, else
    ``"utf-8-sig"`` (UTF-8 or ASCII, a UTF-8 byte order mark dropped)."""
    with open(path, "rb") as file:
        return "utf-16" if file.read(2) in _UTF16_BOMS else "utf-8-sig"


#: This many distinct times, every one a whole number, are not seconds of an event camera.
_WHOLE_TIMES = 100


#: Seconds since 1970 of March 1973 and of 2103: a clock since 1970 lies between them (in its own unit).
_SINCE_1970 = (1e8, 4.2e9)
#: Units of whole-number times, by how many of them make a second.
_WHOLE_UNITS = (("ns", 1e9), ("us", 1e6), ("ms", 1e3))


def _since_1970_unit(value: float) -> str | None:
    """The unit of :data:`_WHOLE_UNITS` in which the time ``value`` lies between 1973 and 2103 as a time since
    1970, or None (a clock started elsewhere: the unit cannot be told).

    >>> _since_1970_unit(1504645177000.0), _since_1970_unit(1.7e18), _since_1970_unit(957.0)
    ('ms', 'ns', None)
    """
    return next((unit for unit, per_second in _WHOLE_UNITS
                 if _SINCE_1970[0] <= abs(value) / per_second < _SINCE_1970[1]), None)


def _refuse_whole_seconds(t: np.ndarray, path: Path) -> None:
    """Refuse a time column read as ECD's seconds (no unit stated) whose every value is a whole number.

    An event camera's times in seconds carry decimals; a column of at least
    :data:`_WHOLE_TIMES` distinct whole numbers is integer microseconds (or
    ms, ns) that would read as hours or days of recording. Where the times lie between 1973 and 2103 as a time
    since 1970 in one unit (:func:`_since_1970_unit`), the refusal names that unit (milliseconds since 1970 were
    called microseconds, and read so, 1000 times too short); nanoseconds, which no reader takes, are to convert.
    """
    if t.size < _WHOLE_TIMES or not np.array_equal(t, np.round(t)):
        return
    distinct = int(np.count_nonzero(np.diff(t))) + 1
    if distinct < _WHOLE_TIMES:
        return
    start = (f"{path}: every time in column t is a whole number ({distinct:,} distinct, from {t[0]:.0f} to "
             f"{t[-1]:.0f}), but ECD text states seconds with decimals")
    unit = _since_1970_unit(float(t[0]))
    if unit == "ns":
        raise FormatError(f"{start}: these are nanoseconds since 1970 ({t[0] / 1e9:.3f} s), a unit no reader takes: "
                          "write them as seconds (t / 1e9, with decimals) or integer microseconds (t // 1000, then "
                          "time_unit='us', cmax: --time-unit us)")
    if unit is not None:
        words = {"us": "microseconds", "ms": "milliseconds"}[unit]
        raise FormatError(f"{start}: these are {words} since 1970 ({t[0] / dict(_WHOLE_UNITS)[unit]:.3f} s). State "
                          f"the unit: time_unit={unit!r} (cmax: --time-unit {unit})")
    raise FormatError(
        f"{start}: these look like integer microseconds. State the unit: time_unit='us' (cmax: --time-unit us), or "
        "time_unit='s' if they are whole seconds"
    )


def write_txt(path: str | os.PathLike, events: Events, *, overwrite: bool = False) -> Path:
    """Write events as ECD text (``t[s] x y p``, 9 decimals), atomically; returns the path.

    An existing ``path`` raises :class:`FileExistsError` (left untouched)
    unless ``overwrite=True``.
    """
    path = Path(path)
    table = np.column_stack([events.t / 1e6, events.x, events.y, events.p])

    def fill(output: AtomicOutput) -> None:
        with os.fdopen(os.dup(output.fd), "wb") as file:
            np.savetxt(file, table, fmt=["%.9f", "%d", "%d", "%d"])

    return write_with(path, fill, overwrite=overwrite)
