"""Prophesee RAW files: compiled EVT 3.0 and EVT 2.0 decoders and encoders.

A RAW file is an ASCII header of lines starting with ``%`` (optionally closed
by ``% end``) followed by little-endian words. Layouts, from Prophesee's
public format documentation (docs.prophesee.ai, "EVT 2.0 Format",
"EVT 3.0 Format"); bits are numbered from the least significant:

EVT 3.0, 16-bit words, type in bits 15..12:

==========  ====  ===========================================================
word        type  payload
==========  ====  ===========================================================
ADDR_Y      0x0   y in 10..0 (bit 11, master/slave, is ignored)
ADDR_X      0x2   one event at x = 10..0, polarity = bit 11, current y and time
VECT_BASE_X 0x3   base x = 10..0 and polarity = bit 11 for the vectors after it
VECT_12     0x4   events at base x + i for each set bit i of 11..0; base x += 12
VECT_8      0x5   events at base x + i for each set bit i of 7..0; base x += 8
TIME_LOW    0x6   low 12 bits of the 24-bit time base (µs)
CONTINUED_4 0x7   skipped (extra data of a previous word)
TIME_HIGH   0x8   high 12 bits of the time base; the low part restarts at 0
EXT_TRIGGER 0xA   skipped (external trigger edges are not camera events)
OTHERS      0xE   skipped (monitoring and vendor extensions)
CONTINUED12 0xF   skipped (extra data of a previous word)
==========  ====  ===========================================================

EVT 2.0, 32-bit words, type in bits 31..28: CD_OFF (0x0) and CD_ON (0x1)
carry time low 6 bits in 27..22, x in 21..11, y in 10..0; TIME_HIGH (0x8)
carries the upper 28 bits of the 34-bit time in 27..0; EXT_TRIGGER (0xA),
OTHERS (0xE) and CONTINUED (0xF) are skipped.

Other word types are reserved by the format; meeting one raises
:class:`~cmax.io.errors.FormatError` (this is also how garbage is detected),
as do a byte count that is not a whole number of words, an unterminated header
and events outside the sensor.

Decoding is one compiled pass over the words (numba) into columns allocated
once from a counted bound; the decoder state (time, y, base x, polarity) is
carried from one chunk to the next, so :func:`iter_evt3` / :func:`iter_evt2` decode files of any
size in bounded memory and give exactly what :func:`read_evt3` /
:func:`read_evt2` give. Words before the first TIME_HIGH (and events before the
first ADDR_Y / VECT_BASE_X that define them) have no defined time or address
and are skipped.

Time: the 24-bit (EVT 3.0) and 34-bit (EVT 2.0) time wraps around (every
16.8 s and 4.8 h); a TIME_HIGH value that falls by more than half its range is
read as a wraparound, so times come out as monotonic int64 microseconds. Both
formats carry time as a running base that the sensor only moves forward, so a
stream whose time goes back is corrupt: the readers raise on it by default;
``sort=True`` instead sorts stably (see :func:`read_evt3`). A TIME_LOW that is
lower than the one before, with no TIME_HIGH change, only moves the time base
(cameras emit such words a few µs early right after a TIME_HIGH, with no events
attached); it is not a wraparound. Some third-party decoders add 4096 µs at
each such fall, which also counts every genuine rollover twice; this decoder
does not (see ``tests/test_io_prophesee.py``).

The package's modules: :mod:`~cmax.io.prophesee._header` (the ``%`` header,
event format and sensor size), :mod:`~cmax.io.prophesee._decode` (the word
decoders), :mod:`~cmax.io.prophesee.reader` (the file readers and
:func:`read_raw`'s dispatch on the header) and
:mod:`~cmax.io.prophesee.writer` (the encoders and writers).
"""
from __future__ import annotations

# CHUNK_BYTES (the readers' default) and PathLike are importable from here, as before.
from cmax.io.prophesee._header import PathLike  # noqa: F401
from cmax.io.prophesee.reader import (  # noqa: F401
    CHUNK_BYTES, RawScan, RawWindows, iter_evt2, iter_evt3, iter_raw, read_evt2, read_evt3, read_raw, scan_raw,
)
from cmax.io.prophesee.writer import write_evt2, write_evt3

__all__ = [
    "read_raw", "read_evt3", "read_evt2", "iter_raw", "iter_evt3", "iter_evt2", "RawScan", "scan_raw", "RawWindows",
    "write_evt3", "write_evt2",
]
