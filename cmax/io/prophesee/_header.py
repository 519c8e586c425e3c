"""The ASCII header of a Prophesee RAW file: ``%`` lines, event format and sensor size.

A RAW file opens with text lines starting with ``%`` (``% key value``),
optionally closed by ``% end``; the little-endian event words follow. Without
``% end`` the header ends at the first line that is not text (``%`` then
printable characters up to ``\\n``), so an event word starting with the byte 0x25
is data, not a header line. The header names
the event format (``% evt 3.0`` or ``% format EVT3;width=W;height=H``) and the
sensor size (stated in the ``format`` line or a ``geometry WxH`` line, or only
implied by a known ``plugin_name`` or ``sensor_generation``: a guess, which a
caller's width and height replace).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Union

from cmax.events import _check_sensor_size
from cmax.io.errors import FormatError
from cmax.io._checks import check_stated_size

PathLike = Union[str, "os.PathLike[str]"]

_MAX_HEADER_BYTES = 1 << 20
#: Header keys that decide how the words are decoded: each may appear on several lines only with one value.
_DECODING_KEYS = ("evt", "format", "geometry")
#: Tab and carriage return, the control characters a header line may hold (removed by ``str.translate``).
_TAB_CR = {0x09: None, 0x0D: None}

#: Sensor sizes of HAL plugins, matched as substrings of ``plugin_name``, in order.
_PLUGIN_SIZES = (
    ("genx320", (320, 320)),
    ("gen41", (1280, 720)),
    ("imx636", (1280, 720)),
    ("gen4", (1280, 720)),
    ("gen31", (640, 480)),
    ("gen3", (640, 480)),
)


@dataclass(frozen=True)
class _Header:
    """The ``%`` lines of a RAW file as ``key -> value`` and where the words start."""

    fields: dict[str, str]
    data_offset: int

    def event_format(self) -> str | None:
        """``"evt3"``, ``"evt2"``, another lower-case name, or None if undeclared."""
        fmt = self.fields.get("format")
        if fmt:
            name = fmt.split(";")[0].strip().lower()
            return {"evt3": "evt3", "evt2": "evt2"}.get(name, name)
        evt = self.fields.get("evt")
        if evt:
            version = evt.strip()
            return {"3.0": "evt3", "3": "evt3", "2.0": "evt2", "2": "evt2"}.get(
                version, f"evt {version}"
            )
        return None

    def stated_size(self) -> tuple[int, int] | None:
        """(width, height) that a ``format ...;width=;height=`` or ``geometry WxH`` line states, or None."""
        return self._format_size() or self._geometry_size()

    def _format_size(self) -> tuple[int, int] | None:
        """(width, height) of the ``format ...;width=;height=`` line, or None (ValueError: not integers)."""
        options = dict(
            part.split("=", 1) for part in self.fields.get("format", "").split(";") if "=" in part
        )
        options = {key.strip().lower(): value.strip() for key, value in options.items()}
        if "width" in options and "height" in options:
            return int(options["width"]), int(options["height"])
        return None

    def _geometry_size(self) -> tuple[int, int] | None:
        """(width, height) of the ``geometry WxH`` line, or None (ValueError: not integers)."""
        geometry = self.fields.get("geometry", "").lower().split("x")
        if len(geometry) == 2:
            return int(geometry[0]), int(geometry[1])
        return None

    def contradiction(self) -> str | None:
        """What two lines of the header state differently (the event format of the ``evt`` and ``format``
        lines, the size of the ``format`` and ``geometry`` lines), or None: a header that contradicts itself
        cannot be read by trusting one of its lines."""
        names = {"3.0": "evt3", "3": "evt3", "2.0": "evt2", "2": "evt2"}
        by_evt = names.get(self.fields.get("evt", "").strip())
        by_format = {"evt3": "evt3", "evt2": "evt2"}.get(self.fields.get("format", "").split(";")[0].strip().lower())
        if by_evt and by_format and by_evt != by_format:
            return (f"its 'evt {self.fields['evt'].strip()}' line and its 'format {self.fields['format']}' line "
                    "declare different event formats")
        try:
            by_format_size, by_geometry = self._format_size(), self._geometry_size()
        except ValueError:                              # unreadable numbers: refused (or replaced) where read
            return None
        if by_format_size and by_geometry and by_format_size != by_geometry:
            return (f"its 'format' line states a {by_format_size[0]}x{by_format_size[1]} sensor, its "
                    f"'geometry' line {by_geometry[0]}x{by_geometry[1]}")
        return None

    def inferred_size(self) -> tuple[tuple[int, int], str] | None:
        """(width, height) implied by a known ``plugin_name`` or ``sensor_generation``, and the line that implies it.

        A guess from the camera's name, not a size the file states: an
        expelliarmus/tonic file names ``hal_plugin_gen3_fx3`` whatever its sensor.
        """
        plugin = self.fields.get("plugin_name", "")
        for pattern, size in _PLUGIN_SIZES:
            if pattern in plugin.lower():
                return size, f"plugin_name {plugin}"
        generation = self.fields.get("sensor_generation", "")
        size = {"3": (640, 480), "4": (1280, 720)}.get(generation.split(".")[0].strip())
        return None if size is None else (size, f"sensor_generation {generation}")


def _header_line_end(head: bytes, pos: int) -> int | None:
    """Where the text line that starts with ``%`` at ``pos`` ends: the index of its ``\\n``, or None.

    A header line is text: UTF-8 (in practice ASCII) without control characters
    other than tab and carriage return, up to ``\\n``. None when the bytes after
    ``pos`` are not: the ``%`` is then the first byte of an event word (0x25),
    not a header line. ``len(head)`` when the line is text to the end of ``head``.
    """
    end = head.find(b"\n", pos)
    body = head[pos + 1:len(head) if end < 0 else end]
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError:
        return None
    if not text.translate(_TAB_CR).isprintable():
        return None
    return len(head) if end < 0 else end


def _read_header(path: Path) -> _Header:
    """The ``%`` lines at the start of ``path``, up to ``% end`` or the first line that is not text.

    A header line is ``%`` followed by printable text (:func:`_header_line_end`) up to ``\\n``.
    Files without ``% end`` (older Metavision and ATIS recordings) end their
    header at the first line that is not: an event word whose first byte is
    0x25 (``%``) starts the data, it is not read as a header line.
    """
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES + 1)
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(head) and head[pos:pos + 1] == b"%":
        end = _header_line_end(head, pos)
        if end is None:
            break
        if end == len(head):
            raise FormatError(
                f"{path}: header line at byte {pos} has no end of line "
                "(truncated file, or not a Prophesee RAW file)"
            )
        line = head[pos + 1:end].decode("utf-8").strip()
        pos = end + 1
        if line.lower() == "end":
            break
        key, _, value = line.partition(" ")
        key, value = key.lower(), value.strip()
        if key in _DECODING_KEYS and fields.get(key, value) != value:   # two lines of one key, read by the last
            raise FormatError(f"{path}: the header contradicts itself: it has the lines '{key} {fields[key]}' and "
                              f"'{key} {value}' (a corrupt or hand-edited header; correct the wrong line)")
        if key:
            fields[key] = value
        if pos > _MAX_HEADER_BYTES:
            raise FormatError(f"{path}: header longer than {_MAX_HEADER_BYTES} bytes")
    header = _Header(fields, pos)
    if header.event_format() is None and fields.get("data", "").lower().startswith("file containing"):
        raise FormatError(
            f"{path}: the header's line '% Data {fields['data']}' marks a Prophesee DAT file (the Gen1 and 1 Mpx "
            "automotive datasets' *_td.dat: 8-byte events of a 32-bit time stamp and a 32-bit address), not EVT 2.0 "
            "or 3.0 words, which are the RAW formats read here: decode it with the automotive dataset toolbox's "
            "PSEELoader (or expelliarmus) and build cmax.Events(x, y, t, p, width, height) from its columns (t in µs)"
        )
    contradiction = header.contradiction()
    if contradiction is not None:
        raise FormatError(f"{path}: the header contradicts itself: {contradiction} (a corrupt or hand-edited "
                          "header; correct the wrong line)")
    return header


@dataclass(frozen=True)
class _Size:
    """A RAW file's sensor size in pixels, and the header line it is inferred from (None: stated or given)."""

    width: int
    height: int
    inferred_from: str | None = None


def _sensor_size(header: _Header, width: int | None, height: int | None, path: Path) -> _Size:
    """The sensor size: the one the header states, which a caller's size must equal (else :class:`ValueError`);
    else the caller's; else the one a known ``plugin_name``/``sensor_generation`` implies (a guess, which a
    caller's size replaces); else :class:`FormatError`."""
    if (width is None) != (height is None):
        raise ValueError("give both width and height, or neither")
    if width is not None:
        width, height = _check_sensor_size(width, height)
    try:
        stated = header.stated_size()
    except ValueError:
        if width is not None:
            return _Size(width, height)
        raise FormatError(f"{path}: unreadable sensor size in the header {header.fields}") from None
    if stated is not None:
        try:
            stated = _check_sensor_size(*stated)
        except (TypeError, ValueError) as error:
            raise FormatError(f"{path}: bad sensor size in the header: {error}") from None
        return _Size(*check_stated_size(width, height, stated, path))
    if width is not None:
        return _Size(width, height)
    inferred = header.inferred_size()
    if inferred is None:
        raise FormatError(
            f"{path}: the header gives no sensor size (no 'format ...;width=;height=', "
            "'geometry WxH' or known plugin_name line); pass width= and height= (cmax: --size WxH)"
        )
    return _Size(*inferred[0], inferred_from=inferred[1])
