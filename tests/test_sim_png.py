"""The fast greyscale PNG reader (cmax.sim.png) against OpenCV's ``imread(..., IMREAD_UNCHANGED)``."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from cmax.sim import png
from cmax.sim.png import PngError, decode_png, parse_png, read_png, unfilter_rows


def chunk(kind: bytes, payload: bytes, crc: int | None = None) -> bytes:
    """One PNG chunk: length, type, payload, CRC-32 of type + payload (or ``crc``)."""
    crc = zlib.crc32(kind + payload) if crc is None else crc
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def filter_rows(image: np.ndarray, kinds: list[int], bpp: int) -> bytes:
    """The PNG filtered stream of ``image`` (H, S) uint8, row y with filter ``kinds[y]``.

    Written from the specification's formulas (section 9.2), independently of
    the kernel: each filtered byte is the raw byte minus the predictor, with
    the predictor computed from the raw (unfiltered) neighbours.
    """
    raw = image.astype(np.int64)
    height, stride = raw.shape
    rows = []
    for y in range(height):
        above = raw[y - 1] if y else np.zeros(stride, np.int64)
        left = np.concatenate([np.zeros(bpp, np.int64), raw[y, :-bpp]])
        upper_left = np.concatenate([np.zeros(bpp, np.int64), above[:-bpp]])
        kind = kinds[y]
        if kind == 0:
            predictor = np.zeros(stride, np.int64)
        elif kind == 1:
            predictor = left
        elif kind == 2:
            predictor = above
        elif kind == 3:
            predictor = (left + above) // 2
        else:
            p = left + above - upper_left
            pa, pb, pc = np.abs(p - left), np.abs(p - above), np.abs(p - upper_left)
            predictor = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, above, upper_left))
        rows.append(bytes([kind]) + ((raw[y] - predictor) % 256).astype(np.uint8).tobytes())
    return b"".join(rows)


def grey_png(image: np.ndarray, kinds: list[int] | int, *, level: int = 6, idat_parts: int = 1,
             extra: bytes = b"", before_idat: bytes = b"") -> bytes:
    """A greyscale PNG of ``image`` (H, W) uint8 or uint16 written by hand, with the given row filters."""
    height, width = image.shape
    depth = 16 if image.dtype == np.uint16 else 8
    data = image.astype(">u2").view(np.uint8).reshape(height, -1) if depth == 16 else image
    kinds = [kinds] * height if isinstance(kinds, int) else kinds
    stream = zlib.compress(filter_rows(data, kinds, depth // 8), level)
    cuts = np.linspace(0, len(stream), idat_parts + 1).astype(int)
    idat = b"".join(chunk(b"IDAT", stream[a:b]) for a, b in zip(cuts[:-1], cuts[1:]))
    header = chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, 0, 0, 0, 0))
    return png.PNG_SIGNATURE + header + before_idat + idat + extra + chunk(b"IEND", b"")


def cv2_decode(data: bytes) -> np.ndarray | None:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


@pytest.fixture(scope="module")
def textured() -> np.ndarray:
    """A 37x53 uint8 image with smooth parts, edges and noise (every filter's branches taken)."""
    rng = np.random.default_rng(1)
    y, x = np.mgrid[:37, :53]
    image = 128 + 100 * np.sin(x / 5.0) * np.cos(y / 7.0) + rng.normal(0, 20, (37, 53))
    image[10:20, 5:30] = 255
    image[25:, 40:] = 0
    return np.clip(image, 0, 255).astype(np.uint8)


# -- the filters, against the specification and against OpenCV ----------------------------
@pytest.mark.parametrize("kind", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_each_filter_type_decodes_as_opencv(textured, kind, dtype):
    image = textured if dtype == np.uint8 else (textured.astype(np.uint16) * 257
                                                 + np.arange(53, dtype=np.uint16) * 3)
    data = grey_png(image, kind)
    decoded = decode_png(data)
    np.testing.assert_array_equal(decoded, image)
    assert decoded.dtype == dtype
    np.testing.assert_array_equal(decoded, cv2_decode(data))


def test_mixed_filters_and_split_idat(textured):
    kinds = [int(k) for k in np.random.default_rng(2).integers(0, 5, textured.shape[0])]
    data = grey_png(textured, kinds, level=9, idat_parts=5)
    np.testing.assert_array_equal(decode_png(data), textured)
    np.testing.assert_array_equal(decode_png(data), cv2_decode(data))


def test_kernel_on_one_row_and_one_column():
    for shape in ((1, 7), (9, 1), (1, 1)):
        image = np.random.default_rng(3).integers(0, 256, shape, dtype=np.uint8)
        for kind in range(5):
            data = grey_png(image, kind)
            np.testing.assert_array_equal(decode_png(data), image)


def test_kernel_reports_a_bad_filter_row():
    out = np.zeros((2, 2), np.uint8)
    assert unfilter_rows(np.frombuffer(bytes([0, 1, 2, 1, 200, 100]), np.uint8), out, 1) == -1
    np.testing.assert_array_equal(out, [[1, 2], [200, 44]])  # Sub: (200 + 100) mod 256
    bad = np.frombuffer(bytes([0, 1, 2, 5, 3, 4]), np.uint8)  # rows of 2 bytes, the 2nd of type 5
    assert unfilter_rows(bad, out, 1) == 1


@pytest.mark.parametrize("strategy", ["DEFAULT", "FILTERED", "HUFFMAN_ONLY", "RLE", "FIXED"])
@pytest.mark.parametrize("level", [0, 1, 9])
def test_opencv_written_pngs(tmp_path, textured, strategy, level):
    params = [cv2.IMWRITE_PNG_STRATEGY, getattr(cv2, f"IMWRITE_PNG_STRATEGY_{strategy}"),
              cv2.IMWRITE_PNG_COMPRESSION, level]
    for image in (textured, textured.astype(np.uint16) * 251):
        path = tmp_path / "x.png"
        assert cv2.imwrite(str(path), image, params)
        decoded = read_png(path)
        assert decoded is not None  # grey, 8 or 16 bit: the fast case
        np.testing.assert_array_equal(decoded, cv2.imread(str(path), cv2.IMREAD_UNCHANGED))


@pytest.mark.parametrize("name, kind", [("FILTER_NONE", 0), ("FILTER_SUB", 1), ("FILTER_UP", 2),
                                        ("FILTER_AVG", 3), ("FILTER_PAETH", 4),
                                        ("FAST_FILTERS", None), ("ALL_FILTERS", None)])
def test_opencv_written_pngs_each_filter(tmp_path, textured, name, kind):
    path = tmp_path / "x.png"
    assert cv2.imwrite(str(path), textured, [cv2.IMWRITE_PNG_FILTER, getattr(cv2, f"IMWRITE_PNG_{name}")])
    header, stream = parse_png(path.read_bytes())
    kinds = set(zlib.decompress(stream)[:: header.row_bytes + 1])
    assert kind is None or kind in kinds  # the file really uses the filter under test
    np.testing.assert_array_equal(read_png(path), cv2.imread(str(path), cv2.IMREAD_UNCHANGED))


def test_every_truck_pan_frame_as_opencv(shared_data):
    paths = sorted((shared_data / "esim_truck_pan" / "images").glob("image_*.png"))
    assert len(paths) == 161
    for path in paths:
        decoded = read_png(path)
        assert decoded is not None and decoded.dtype == np.uint8 and decoded.shape == (180, 240)
        np.testing.assert_array_equal(decoded, cv2.imread(str(path), cv2.IMREAD_UNCHANGED), err_msg=str(path))


def test_both_inflate_backends_agree(textured):
    data = grey_png(textured, 4)
    np.testing.assert_array_equal(decode_png(data, inflate=png.inflate_zlib), textured)
    if png.INFLATE_BACKEND == "isal":
        np.testing.assert_array_equal(decode_png(data, inflate=png.inflate_isal), textured)
    else:
        with pytest.raises(ImportError, match="isal"):
            png.inflate_isal(b"", 1)


# -- not the fast case: None (the caller uses OpenCV) ---------------------------------------
def test_other_files_are_left_to_opencv(tmp_path, textured):
    colour = cv2.imencode(".png", np.dstack([textured] * 3))[1].tobytes()
    grey_alpha = cv2.imencode(".png", np.dstack([textured] * 4))[1].tobytes()
    jpeg = cv2.imencode(".jpg", textured)[1].tobytes()
    transparent = grey_png(textured, 1, before_idat=chunk(b"tRNS", b"\x00\x07"))
    gamma = grey_png(textured, 1, before_idat=chunk(b"gAMA", struct.pack(">I", 45455)))
    unknown = grey_png(textured, 1, extra=chunk(b"abCd", b"xyz"))
    interrupted = grey_png(textured, 1, idat_parts=2)
    cut = interrupted.index(b"IDAT", interrupted.index(b"IDAT") + 4) - 4  # before the 2nd IDAT
    interrupted = interrupted[:cut] + chunk(b"tEXt", b"k\x00v") + interrupted[cut:]
    header = bytearray(grey_png(textured, 1))
    header[8 + 8 + 12] = 1  # interlace method: Adam7 (CRC fixed below)
    header[29:33] = struct.pack(">I", zlib.crc32(bytes(header[12:29])))
    huge = bytearray(grey_png(textured, 1))
    huge[16:24] = struct.pack(">II", 2**16, 2**15)  # 2**31 pixels: above OpenCV's limit
    huge[29:33] = struct.pack(">I", zlib.crc32(bytes(huge[12:29])))
    for data in (colour, grey_alpha, jpeg, transparent, gamma, unknown, interrupted, bytes(header),
                 bytes(huge)):
        assert decode_png(data) is None
    path = tmp_path / "colour.png"
    path.write_bytes(colour)
    assert read_png(path) is None


def test_metadata_chunks_are_skipped(textured):
    text = chunk(b"tEXt", b"Software\x00test") + chunk(b"pHYs", struct.pack(">IIB", 2835, 2835, 1))
    for data in (grey_png(textured, 2, before_idat=text), grey_png(textured, 2, extra=text)):
        np.testing.assert_array_equal(decode_png(data), textured)
        np.testing.assert_array_equal(decode_png(data), cv2_decode(data))
    bad_crc = grey_png(textured, 2, before_idat=chunk(b"tEXt", b"a\x00b", crc=0))
    np.testing.assert_array_equal(decode_png(bad_crc), textured)  # libpng drops it too
    np.testing.assert_array_equal(cv2_decode(bad_crc), textured)


def test_extra_image_data_is_left_to_opencv(textured):
    height, width = textured.shape
    stream = zlib.compress(filter_rows(textured, [0] * height, 1) + bytes(width + 1))  # one row too many
    data = (png.PNG_SIGNATURE + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", stream) + chunk(b"IEND", b""))
    assert decode_png(data) is None


# -- corrupt files: PngError naming the file ------------------------------------------------
def test_corrupt_and_truncated_files_raise(tmp_path, textured):
    good = grey_png(textured, 4, idat_parts=2)
    idat = good.index(b"IDAT")
    flipped = bytearray(good)
    flipped[idat + 30] ^= 0x10  # a bit of the compressed stream: the IDAT CRC no longer matches
    bad_filter_stream = zlib.compress(bytes([7]) + bytes(textured.shape[1]) + bytes(
        (textured.shape[0] - 1) * (textured.shape[1] + 1)))
    height, width = textured.shape
    header = chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
    short_stream = zlib.compress(bytes((height - 1) * (width + 1)))
    cases = {
        "truncated": good[: len(good) // 2],
        "without an IEND": good[: -12],
        "CRC mismatch in the IDAT": bytes(flipped),
        "CRC mismatch in the IHDR": good[:20] + b"\xff" + good[21:],
        "not a 13-byte IHDR": png.PNG_SIGNATURE + chunk(b"IDAT", b"x") + chunk(b"IEND", b""),
        "no IDAT": png.PNG_SIGNATURE + header + chunk(b"IEND", b""),
        "does not inflate": png.PNG_SIGNATURE + header + chunk(b"IDAT", b"garbage!") + chunk(b"IEND", b""),
        "inflates to": png.PNG_SIGNATURE + header + chunk(b"IDAT", short_stream) + chunk(b"IEND", b""),
        "filter type 7": png.PNG_SIGNATURE + header + chunk(b"IDAT", bad_filter_stream) + chunk(b"IEND", b""),
    }
    for fault, data in cases.items():
        path = tmp_path / f"{fault.replace(' ', '_')}.png"
        path.write_bytes(data)
        with pytest.raises(PngError, match=fault) as error:
            read_png(path)
        assert str(path) in str(error.value)
        assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is None, fault  # OpenCV refuses them too


def test_parse_png_returns_the_header_and_stream(textured):
    header, stream = parse_png(grey_png(textured, 3, idat_parts=3))
    assert header == png.PngHeader(53, 37, 8, 0, 0) and header.row_bytes == 53
    assert zlib.decompress(stream) == filter_rows(textured, [3] * 37, 1)
