"""Bounds-checked reading of hand-decoded FlatBuffers (for the AEDAT4 reader).

The binary layout, as read here (all integers little-endian): a buffer
starts with a ``uint32`` offset to its root table, then a 4-byte file
identifier; a size-prefixed buffer has a ``uint32`` size before that. A
table starts with an ``int32`` offset back to its vtable (``uint16`` vtable
size, ``uint16`` table size, one ``uint16`` offset per field, 0 meaning the
field is absent and takes its default); vectors and strings are reached by a
``uint32`` forward offset and start with a ``uint32`` length.

Every read is checked against the buffer's end and fails with
:class:`~cmax.io.errors.FormatError`, never reading past the buffer. A vector
of tables is decoded with numpy gathers (:func:`_table_vector`), with no
Python loop over its elements.

References
----------
FlatBuffers documentation, "FlatBuffer Internals" (the binary layout).
"""
from __future__ import annotations

import struct

import numpy as np

from cmax.io.errors import FormatError


class _Flatbuffer:
    """Bounds-checked reads from one decoded FlatBuffer; errors become FormatError."""

    def __init__(self, data: bytes, identifier: bytes, where: str, *, size_prefixed: bool = True):
        self.where = where
        if size_prefixed:
            if len(data) < 12:
                self.fail(f"{len(data)} bytes are too few for a FlatBuffer")
            (size,) = struct.unpack_from("<I", data, 0)
            if size > len(data) - 4:
                self.fail(f"its size prefix says {size} bytes, only {len(data) - 4} follow")
            data = memoryview(data)[4: 4 + size]
        elif len(data) < 8:
            self.fail(f"{len(data)} bytes are too few for a FlatBuffer")
        self.data = data
        if bytes(data[4:8]) != identifier:
            self.fail(f"expected the identifier {identifier!r}, found {bytes(data[4:8])!r}")
        self.root = self.u32(0)

    def fail(self, message: str) -> None:
        raise FormatError(f"{self.where}: {message}")

    def _unpack(self, fmt: str, pos: int) -> int:
        if pos < 0 or pos + struct.calcsize(fmt) > len(self.data):
            self.fail(f"a read at byte {pos} runs past the {len(self.data)}-byte buffer")
        return struct.unpack_from(fmt, self.data, pos)[0]

    def u32(self, pos: int) -> int:
        return self._unpack("<I", pos)

    def field(self, table: int, index: int) -> int | None:
        """Absolute position of field ``index`` of the table at ``table``, or None if absent."""
        vtable = table - self._unpack("<i", table)
        vtable_size = self._unpack("<H", vtable)
        if 4 + 2 * index + 2 > vtable_size:
            return None
        offset = self._unpack("<H", vtable + 4 + 2 * index)
        return table + offset if offset else None

    def scalar(self, table: int, index: int, fmt: str, default: int | float = 0) -> int | float:
        pos = self.field(table, index)
        return default if pos is None else self._unpack(fmt, pos)

    def vector(self, table: int, index: int) -> tuple[int, int]:
        """``(start, length)`` of the vector (or string) in field ``index``; (0, 0) if absent."""
        pos = self.field(table, index)
        if pos is None:
            return 0, 0
        start = pos + self.u32(pos)
        return start + 4, self.u32(start)

    def span(self, start: int, nbytes: int) -> memoryview:
        if start < 0 or start + nbytes > len(self.data):
            self.fail(f"{nbytes} bytes at byte {start} run past the end of the buffer")
        return memoryview(self.data)[start: start + nbytes]


def _gather(u8: np.ndarray, positions: np.ndarray, dtype: str) -> np.ndarray:
    """Values of ``dtype`` at the byte ``positions`` of ``u8`` (caller checks bounds)."""
    size = np.dtype(dtype).itemsize
    chunks = u8[positions[:, None] + np.arange(size)]
    return np.ascontiguousarray(chunks).view(dtype).reshape(-1)


def _table_vector(
    fb: _Flatbuffer, start: int, length: int, fields: tuple[tuple[str, str], ...]
) -> dict[str, np.ndarray]:
    """Decode a vector of ``length`` tables at ``start``, vectorized over elements.

    ``fields`` lists ``(name, dtype)`` in schema order; absent fields read as 0.
    Returns one (length,) array per field and ``"<name>?"`` masks of presence.
    """
    u8 = np.frombuffer(fb.data, np.uint8)
    limit = u8.size

    def checked(positions: np.ndarray, nbytes: int) -> np.ndarray:
        if positions.size and (positions.min() < 0 or positions.max() + nbytes > limit):
            fb.fail("a table of the vector lies outside the buffer")
        return positions

    slots = start + 4 * np.arange(length, dtype=np.int64)
    checked(slots, 4)
    tables = slots + _gather(u8, slots, "<u4").astype(np.int64)
    vtables = tables - _gather(u8, checked(tables, 4), "<i4").astype(np.int64)
    vtable_sizes = _gather(u8, checked(vtables, 4), "<u2").astype(np.int64)
    out: dict[str, np.ndarray] = {}
    for index, (name, dtype) in enumerate(fields):
        has_slot = vtable_sizes >= 4 + 2 * index + 2
        offsets = np.zeros(length, np.int64)
        where = vtables[has_slot] + 4 + 2 * index
        offsets[has_slot] = _gather(u8, checked(where, 2), "<u2")
        present = offsets > 0
        values = np.zeros(length, dtype)
        where = tables[present] + offsets[present]
        values[present] = _gather(u8, checked(where, np.dtype(dtype).itemsize), dtype)
        out[name] = values
        out[name + "?"] = present
    return out
