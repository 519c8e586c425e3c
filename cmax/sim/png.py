"""A fast reader for the PNG files a simulator sees: 8- and 16-bit greyscale, not interlaced.

:func:`read_png` returns the pixels exactly as ``cv2.imread(path,
cv2.IMREAD_UNCHANGED)`` does -- (H, W) uint8, or uint16 in native byte order
-- for the common case, and None for every other file, which the caller then
reads with OpenCV as before. The common case: a PNG signature; IHDR first,
greyscale (colour type 0), bit depth 8 or 16, compression and filter method 0,
no interlacing; then only IDAT chunks (consecutive), IEND and the metadata
chunks ``tEXt``, ``zTXt``, ``iTXt``, ``tIME``, ``pHYs`` (skipped: they do not
change the pixels). Any other chunk (``tRNS``, ``gAMA``, ``sBIT``, ``iCCP``,
``PLTE``, ``acTL``, ...), colour, palette, bit depths 1/2/4 and Adam7
interlacing fall back to OpenCV, as does a zlib stream that holds more data
than the image needs (libpng accepts it with a warning).

Decoding: the IDAT payloads are inflated in one call with the exact output
size (``isal.isal_zlib`` when the optional ``isal`` package is installed,
else the standard library's ``zlib``; both release the GIL while they
inflate), then a compiled kernel (:func:`cmax._jit.kernel`, ``nogil``) undoes
the five PNG row filters (None, Sub, Up, Average, Paeth; PNG specification,
2nd ed., section 9) into the output array.

Integrity: the CRC-32 of every critical chunk (IHDR, IDAT, IEND) is checked,
as libpng does; those of the skipped metadata chunks are not (libpng drops a
metadata chunk with a bad CRC, which leaves the pixels alone). zlib checks
the stream's Adler-32. A file with a PNG signature that is truncated or
corrupt -- a chunk running past the end of the file, no IEND, a bad CRC, a
zlib stream that does not inflate or holds too little data, a row filter
type above 4 -- raises :class:`PngError` naming the file and the fault,
never a silently wrong image.

Example::

    image = read_png("frame_000.png")   # None: not the fast case, use cv2.imread
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Union

import numpy as np

from cmax._jit import kernel

try:  # optional, faster inflate (pip install evtslowtv[fast])
    from isal import isal_zlib as _isal_zlib
except ImportError:  # pragma: no cover - depends on the environment
    _isal_zlib = None

__all__ = [
    "INFLATE_BACKEND",
    "PNG_SIGNATURE",
    "PngError",
    "PngHeader",
    "decode_png",
    "inflate_isal",
    "inflate_zlib",
    "parse_png",
    "read_png",
    "unfilter_rows",
]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Ancillary chunks skipped by the fast path (text, time, pixel size: no effect on the pixels).
_METADATA_CHUNKS = frozenset({b"tEXt", b"zTXt", b"iTXt", b"tIME", b"pHYs"})
_CHUNK_HEAD = struct.Struct(">I4s")
#: Larger images go to OpenCV, which applies its own limit (``CV_IO_MAX_IMAGE_PIXELS``, 2**30 by default).
_MAX_PIXELS = 2**30
_IHDR = struct.Struct(">IIBBBBB")

PathLike = Union[str, Path]
Inflate = Callable[[bytes, int], bytes]


class PngError(ValueError):
    """A file with a PNG signature is truncated or corrupt (the message names the file and the fault)."""


@dataclass(frozen=True)
class PngHeader:
    """The IHDR fields of a PNG file.

    Attributes
    ----------
    width, height : int
        Pixels.
    bit_depth : int
        Bits per sample (1, 2, 4, 8 or 16).
    colour_type : int
        0 grey, 2 RGB, 3 palette, 4 grey + alpha, 6 RGBA.
    interlace : int
        0 none, 1 Adam7.
    """

    width: int
    height: int
    bit_depth: int
    colour_type: int
    interlace: int

    @property
    def bytes_per_pixel(self) -> int:
        """Bytes of one grey sample (1 or 2) in the fast case."""
        return self.bit_depth // 8

    @property
    def row_bytes(self) -> int:
        """Bytes of one unfiltered row in the fast case (without its filter-type byte)."""
        return self.width * self.bytes_per_pixel


def inflate_zlib(data: bytes, size: int) -> bytes:
    """The inflated zlib stream ``data`` (standard library), ``size`` bytes expected.

    The output buffer holds ``size + 1`` bytes: one that fits the data
    exactly makes both libraries grow it once more.
    """
    return zlib.decompress(data, 15, size + 1)


def inflate_isal(data: bytes, size: int) -> bytes:
    """As :func:`inflate_zlib`, with ISA-L's inflate (``isal`` package; ImportError without it)."""
    if _isal_zlib is None:
        raise ImportError("inflate_isal needs the optional isal package (pip install evtslowtv[fast])")
    return _isal_zlib.decompress(data, 15, size + 1)


#: The inflate used by default: ``"isal"`` when the isal package is importable, else ``"zlib"``.
INFLATE_BACKEND = "zlib" if _isal_zlib is None else "isal"
_DEFAULT_INFLATE: Inflate = inflate_zlib if _isal_zlib is None else inflate_isal
_crc32 = zlib.crc32 if _isal_zlib is None else _isal_zlib.crc32
_INFLATE_ERRORS = (zlib.error,) if _isal_zlib is None else (zlib.error, _isal_zlib.error)


def parse_png(data: bytes, name: str = "<bytes>") -> tuple[PngHeader, bytes] | None:
    """The header and the concatenated IDAT payloads of a fast-case PNG, or None.

    Parameters
    ----------
    data : bytes
        The whole file.
    name : str
        The file's name, for error messages.

    Returns
    -------
    (PngHeader, bytes) or None
        None when ``data`` is not a PNG or not the fast case (see the module
        docstring); the caller reads it another way.

    Raises
    ------
    PngError
        A PNG signature but a truncated or corrupt chunk structure.
    """
    if data[:8] != PNG_SIGNATURE:
        return None
    view, end, offset = memoryview(data), len(data), 8
    header, idat, idat_closed = None, [], False
    while True:
        if offset + 8 > end:
            raise PngError(f"{name}: truncated PNG (the file ends at byte {end} without an IEND chunk)")
        length, kind = _CHUNK_HEAD.unpack_from(data, offset)
        stop = offset + 12 + length
        if length > 0x7FFFFFFF or stop > end:
            raise PngError(f"{name}: truncated PNG (chunk {kind!r} at byte {offset} runs past the "
                           f"end of the file, {end} bytes)")
        critical = kind in (b"IHDR", b"IDAT", b"IEND")
        if critical and _crc32(view[offset + 4:stop - 4]) != int.from_bytes(data[stop - 4:stop], "big"):
            raise PngError(f"{name}: corrupt PNG (CRC mismatch in the {kind.decode()} chunk at byte "
                           f"{offset})")
        if header is None:
            if kind != b"IHDR" or length != 13:
                raise PngError(f"{name}: corrupt PNG (the first chunk is {kind!r} of {length} bytes, "
                               "not a 13-byte IHDR)")
            width, height, depth, colour, compression, filtering, interlace = _IHDR.unpack_from(
                data, offset + 8)
            header = PngHeader(width, height, depth, colour, interlace)
            if (colour != 0 or depth not in (8, 16) or compression or filtering or interlace
                    or not 0 < width < 2**31 or not 0 < height < 2**31 or width * height > _MAX_PIXELS):
                return None  # colour, palette, 1/2/4 bits, Adam7 or an odd header: OpenCV decides
        elif kind == b"IDAT":
            if idat_closed:
                return None  # IDAT chunks interrupted by another chunk: OpenCV decides
            idat.append(view[offset + 8:stop - 4])
        elif kind == b"IEND":
            break
        elif kind in _METADATA_CHUNKS:
            idat_closed = bool(idat)
        else:
            return None  # tRNS, gAMA, sBIT, PLTE, iCCP, acTL, a second IHDR, ...: OpenCV decides
        offset = stop
    if not idat:
        raise PngError(f"{name}: corrupt PNG (no IDAT chunk)")
    return header, b"".join(idat)


@kernel
def unfilter_rows(raw, out, bpp):  # pragma: no cover - compiled by numba
    """Undo the PNG row filters: ``raw`` uint8 (H * (1 + S),) into ``out`` uint8 (H, S), C-contiguous.

    Each row of ``raw`` is a filter-type byte (0 None, 1 Sub, 2 Up,
    3 Average, 4 Paeth) then S filtered bytes; ``bpp`` is the bytes per
    pixel (the distance of the left neighbour; S = width * bpp). Arithmetic
    is modulo 256, as the specification says. Returns -1 when every row was
    written, else the index of the first row whose filter type is above 4
    (the rows from it on are not valid).
    """
    height, stride = out.shape
    flat = out.reshape(height * stride)
    for y in range(height):
        src, dst = y * (stride + 1) + 1, y * stride
        kind = np.int64(raw[src - 1])
        if kind > 4:
            return y
        if y == 0 and kind >= 2:  # no row above: Up is None, Paeth is Sub, Average halves a only
            kind = 0 if kind == 2 else 1 if kind == 4 else 5
        if kind == 0:
            flat[dst:dst + stride] = raw[src:src + stride]
        elif kind == 2:
            for i in range(stride):
                flat[dst + i] = raw[src + i] + flat[dst - stride + i]
        elif bpp == 1:
            _unfilter_row_1(kind, raw, src, flat, dst, stride)
        else:
            _unfilter_row(kind, raw, src, flat, dst, stride, bpp)
    return -1


@kernel(inline="always")
def _unfilter_row_1(kind, raw, src, flat, dst, stride):  # pragma: no cover - compiled by numba
    """One row of Sub (1), Average (3), Paeth (4) or Average of the first row (5), one byte per pixel.

    The left neighbour ``a`` is carried in a register (the loop's only serial
    dependency); ``flat[dst - stride:dst]`` is the row above.
    """
    a = 0
    if kind == 1:
        for i in range(stride):
            a = (raw[src + i] + a) & 255
            flat[dst + i] = a
    elif kind == 5:
        for i in range(stride):
            a = (raw[src + i] + (a >> 1)) & 255
            flat[dst + i] = a
    elif kind == 3:
        for i in range(stride):
            a = (raw[src + i] + ((a + flat[dst - stride + i]) >> 1)) & 255
            flat[dst + i] = a
    else:
        c = 0
        for i in range(stride):
            b = np.int64(flat[dst - stride + i])
            a = (raw[src + i] + _paeth(a, b, c)) & 255
            flat[dst + i] = a
            c = b


@kernel(inline="always")
def _unfilter_row(kind, raw, src, flat, dst, stride, bpp):  # pragma: no cover - compiled by numba
    """As :func:`_unfilter_row_1` for ``bpp`` bytes per pixel (the left byte read back from ``flat``)."""
    for i in range(stride):
        a = np.int64(flat[dst + i - bpp]) if i >= bpp else 0
        if kind == 1:
            predictor = a
        elif kind == 5:
            predictor = a >> 1
        elif kind == 3:
            predictor = (a + flat[dst - stride + i]) >> 1
        else:
            c = np.int64(flat[dst - stride + i - bpp]) if i >= bpp else 0
            predictor = _paeth(a, np.int64(flat[dst - stride + i]), c)
        flat[dst + i] = (raw[src + i] + predictor) & 255


@kernel(inline="always")
def _paeth(a, b, c):  # pragma: no cover - compiled by numba
    """The Paeth predictor of left ``a``, above ``b``, upper-left ``c`` (int64 in [0, 255])."""
    pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
    if pa <= pb and pa <= pc:
        return a
    if pb <= pc:
        return b
    return c


def decode_png(data: bytes, name: str = "<bytes>", *, inflate: Inflate | None = None) -> np.ndarray | None:
    """The pixels of a fast-case PNG file held in ``data``, as ``cv2.imread(..., IMREAD_UNCHANGED)``.

    Parameters
    ----------
    data : bytes
        The whole file.
    name : str
        The file's name, for error messages.
    inflate : callable, optional
        ``inflate(stream, size) -> bytes``: :func:`inflate_zlib`,
        :func:`inflate_isal`; default the fastest importable
        (:data:`INFLATE_BACKEND`).

    Returns
    -------
    ndarray (H, W) uint8 or uint16 (native byte order), or None
        None when ``data`` is not the fast case (see the module docstring).

    Raises
    ------
    PngError
        A truncated or corrupt PNG.
    """
    parsed = parse_png(data, name)
    if parsed is None:
        return None
    header, stream = parsed
    size = header.height * (header.row_bytes + 1)
    try:
        raw = (inflate or _DEFAULT_INFLATE)(stream, size)
    except _INFLATE_ERRORS as error:
        raise PngError(f"{name}: corrupt PNG (the image data does not inflate: {error})") from error
    if len(raw) < size:
        raise PngError(f"{name}: corrupt PNG (the image data inflates to {len(raw)} bytes, "
                       f"{size} expected for {header.width}x{header.height} pixels)")
    if len(raw) > size:
        return None  # extra data after the image: libpng warns and decodes it, OpenCV decides
    out = np.empty((header.height, header.row_bytes), np.uint8)
    bad_row = unfilter_rows(np.frombuffer(raw, np.uint8), out, header.bytes_per_pixel)
    if bad_row >= 0:
        kind = raw[bad_row * (header.row_bytes + 1)]
        raise PngError(f"{name}: corrupt PNG (row {bad_row} has filter type {kind}, not 0-4)")
    if header.bit_depth == 16:
        return out.view(">u2").astype(np.uint16)
    return out


def read_png(path: PathLike, *, inflate: Inflate | None = None) -> np.ndarray | None:
    """The pixels of the PNG file ``path`` as ``cv2.imread(path, IMREAD_UNCHANGED)``, or None.

    Reads the file and calls :func:`decode_png` (see there and the module
    docstring); None means not the fast case (read it with OpenCV).

    Raises
    ------
    OSError
        The file cannot be read.
    PngError
        A truncated or corrupt PNG (the message names ``path``).
    """
    path = Path(path)
    return decode_png(path.read_bytes(), str(path), inflate=inflate)
