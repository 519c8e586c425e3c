"""Tests of cmax.io.prophesee: EVT 3.0 / EVT 2.0 decoding, encoding and error handling.

The hand-built word streams below were written from the format description
(docs.prophesee.ai, "EVT 2.0 Format" and "EVT 3.0 Format"), with the
expected events worked out by hand, independently of the decoder.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cmax.events import Events
from cmax.io.errors import FormatError
from cmax.io.prophesee import (
    iter_evt2, iter_evt3, iter_raw, read_evt2, read_evt3, read_raw, write_evt2, write_evt3,
)

from conftest import random_events

EVT3_HEADER = b"% evt 3.0\n% format EVT3;height=16;width=32\n% end\n"
EVT2_HEADER = b"% evt 2.0\n% geometry 32x16\n"

# EVT 3.0 words and the events they hold: (x, y, t, p).
EVT3_WORDS = [
    0x0001, 0x2001,       # ADDR_Y, ADDR_X before any TIME_HIGH: no time, skipped
    0x8FFE, 0x6005,       # TIME_HIGH 0xFFE, TIME_LOW 5 -> t = 0xFFE005 = 16769029
    0x0003,               # y = 3
    0x2805,               # ADDR_X x=5 p=1
    0x3010,               # VECT_BASE_X x=16 p=0
    0x4805,               # VECT_12 bits 0, 2, 11 -> x = 16, 18, 27; base -> 28
    0x5003,               # VECT_8 bits 0, 1 -> x = 28, 29; base -> 36
    0xA001, 0xE123, 0xF456, 0x7003,  # EXT_TRIGGER, OTHERS, CONTINUED_12, CONTINUED_4
    0x8FFF, 0x6FFF,       # t = 0xFFFFFF = 16777215
    0x0007, 0x2002,       # y = 7; ADDR_X x=2 p=0
    0x8000,               # TIME_HIGH 0 after 0xFFF: wraparound -> high = 4096
    0x6011, 0x6001,       # TIME_LOW 0x11 then 1 with no event between: t = 2**24 + 1
    0x3808,               # VECT_BASE_X x=8 p=1
    0x5080,               # VECT_8 bit 7 -> x = 15; base -> 16
    0x4001,               # VECT_12 bit 0 -> x = 16
    0x0009, 0x2001,       # y = 9; ADDR_X x=1 p=0
]
EVT3_EVENTS = [
    (5, 3, 16769029, 1),
    (16, 3, 16769029, 0), (18, 3, 16769029, 0), (27, 3, 16769029, 0),
    (28, 3, 16769029, 0), (29, 3, 16769029, 0),
    (2, 7, 16777215, 0),
    (15, 7, 16777217, 1), (16, 7, 16777217, 1),
    (1, 9, 16777217, 0),
]

# EVT 2.0 words: CD word = type << 28 | t_low6 << 22 | x << 11 | y.
EVT2_WORDS = [
    0x1FC02803,           # CD_ON before any TIME_HIGH: skipped
    0x8FFFFFFF,           # TIME_HIGH 2**28 - 1 -> base (2**28 - 1) * 64 = 17179869120
    0x1FC02803,           # CD_ON t_low 63, x=5, y=3 -> t = 17179869183
    0xA0000001, 0xE0000000, 0xF0000000,  # EXT_TRIGGER, OTHERS, CONTINUED
    0x80000000,           # TIME_HIGH 0: wraparound -> base 2**34
    0x00803801,           # CD_OFF t_low 2, x=7, y=1 -> t = 17179869186
    0x80000001,           # base 2**34 + 64
    0x10000000,           # CD_ON t_low 0, x=0, y=0 -> t = 17179869248
]
EVT2_EVENTS = [(5, 3, 17179869183, 1), (7, 1, 17179869186, 0), (0, 0, 17179869248, 1)]


def _write(path: Path, header: bytes, words: list[int], dtype: str) -> Path:
    path.write_bytes(header + np.asarray(words, dtype=dtype).tobytes())
    return path


def _as_tuples(events: Events) -> list[tuple[int, int, int, int]]:
    return list(zip(events.x.tolist(), events.y.tolist(), events.t.tolist(), events.p.tolist()))


def _check_dtypes(events: Events) -> None:
    assert (events.x.dtype, events.y.dtype, events.t.dtype, events.p.dtype) == (
        np.uint16, np.uint16, np.int64, np.int8
    )


@pytest.fixture
def evt3_file(tmp_path: Path) -> Path:
    return _write(tmp_path / "hand.raw", EVT3_HEADER, EVT3_WORDS, "<u2")


@pytest.fixture
def evt2_file(tmp_path: Path) -> Path:
    return _write(tmp_path / "hand2.raw", EVT2_HEADER, EVT2_WORDS, "<u4")


# -- hand-built streams ---------------------------------------------------------------
def test_evt3_hand_built_stream(evt3_file: Path) -> None:
    events = read_evt3(evt3_file)
    assert events.sensor_size == (32, 16)
    assert _as_tuples(events) == EVT3_EVENTS
    _check_dtypes(events)
    assert read_raw(evt3_file) == events


def test_evt2_hand_built_stream(evt2_file: Path) -> None:
    events = read_evt2(evt2_file)
    assert events.sensor_size == (32, 16)
    assert _as_tuples(events) == EVT2_EVENTS
    _check_dtypes(events)
    assert read_raw(evt2_file) == events


@pytest.mark.parametrize("codec", ["evt3", "evt2"])
def test_every_chunk_size_on_hand_built_stream(
    codec: str, evt3_file: Path, evt2_file: Path
) -> None:
    """Chunks of 1..all words split every word group (TIME_HIGH/LOW, BASE_X/VECT)."""
    path, read, iterate, n_bytes = (
        (evt3_file, read_evt3, iter_evt3, 2 * len(EVT3_WORDS)) if codec == "evt3"
        else (evt2_file, read_evt2, iter_evt2, 4 * len(EVT2_WORDS))
    )
    whole = read(path)
    for chunk_bytes in range(1, n_bytes + 2):
        parts = list(iterate(path, chunk_bytes=chunk_bytes))
        assert all(len(part) for part in parts)
        assert sum(map(_as_tuples, parts), []) == _as_tuples(whole)
        assert read(path, chunk_bytes=chunk_bytes) == whole


# -- the real recording ---------------------------------------------------------------
def _reference_time_low_rollovers(raw: Path, n_header: int) -> np.ndarray:
    """Per reference event, how many TIME_LOW words so far were lower than the one before.

    Worked out from the raw words by a plain scan (independent of the decoder).
    """
    words = np.frombuffer(raw.read_bytes()[n_header:], "<u2")
    types = words >> 12
    low_pos = np.flatnonzero(types == 0x6)
    low = (words[low_pos] & 0xFFF).astype(np.int64)
    fall_pos = low_pos[1:][np.diff(low) < 0]
    event_pos = np.flatnonzero((types == 0x2) | (types == 0x4) | (types == 0x5))
    masks = np.where(
        types[event_pos] == 0x2, 1,
        np.where(types[event_pos] == 0x4, words[event_pos] & 0xFFF, words[event_pos] & 0xFF),
    )
    counts = np.array([bin(int(mask)).count("1") for mask in masks])
    return np.searchsorted(fall_pos, np.repeat(event_pos, counts))


def test_evt3_sample_matches_reference(shared_data: Path) -> None:
    """x, y, p and the order equal the reference exactly; t follows the spec.

    The reference .npy (from a third-party decoder) adds 4096 µs at every
    TIME_LOW that is lower than the previous one, on top of TIME_HIGH. That
    counts the two genuine 24-bit rollovers twice (TIME_HIGH 0xB2D -> 0xB2E ->
    0xB2F) and turns nine TIME_LOW words that arrive a few µs early right after
    a TIME_HIGH (and carry no events) into 4 ms jumps: the reference spans
    53.9 ms, while the TIME_HIGH words of the file span under 12.3 ms. This
    decoder follows the format, so t equals the reference minus exactly
    4096 µs per such TIME_LOW fall.
    """
    folder = shared_data / "prophesee_gen4_driving"
    raw = folder / "evt3_sample.raw"
    reference = np.load(folder / "evt3_sample.npy")
    events = read_evt3(raw)
    assert len(events) == len(reference) == 219_596
    assert events.sensor_size == (1280, 720)        # from plugin_name hal_plugin_gen41_evk3
    _check_dtypes(events)
    for name in "xyp":
        np.testing.assert_array_equal(getattr(events, name), reference[name])
    data = raw.read_bytes()
    n_header = 0
    while data[n_header:n_header + 1] == b"%":
        n_header = data.index(b"\n", n_header) + 1
    rollovers = _reference_time_low_rollovers(raw, n_header)
    np.testing.assert_array_equal(events.t, reference["t"] - 4096 * rollovers)
    assert rollovers[-1] == 11
    assert events.t[0] == reference["t"][0] == 0xB2D000
    assert np.all(np.diff(events.t) >= 0)
    assert events.duration_us < 3 * 4096                 # three TIME_HIGH values
    assert read_raw(raw) == events


@pytest.mark.parametrize("chunk_bytes", [2, 1001, 4096, 65_537])
def test_evt3_sample_chunked_equals_one_shot(shared_data: Path, chunk_bytes: int) -> None:
    raw = shared_data / "prophesee_gen4_driving" / "evt3_sample.raw"
    whole = read_evt3(raw)
    if chunk_bytes == 2:   # one word per chunk on a slice only, to stay fast
        parts = []
        for part in iter_evt3(raw, chunk_bytes=2):
            parts.append(part)
            if sum(map(len, parts)) >= 300:
                break
        joined = np.concatenate([part.t for part in parts])
        np.testing.assert_array_equal(joined, whole.t[: joined.size])
        return
    parts = list(iter_evt3(raw, chunk_bytes=chunk_bytes))
    assert len(parts) > 1
    for name in "xytp":
        np.testing.assert_array_equal(
            np.concatenate([getattr(part, name) for part in parts]), getattr(whole, name)
        )


# -- encoders -------------------------------------------------------------------------
def _dense_rows(width: int = 64, height: int = 48) -> Events:
    """Runs along rows at equal times: VECT_12 words, chained base x, mixed polarity."""
    x = np.concatenate([np.arange(0, 40), np.arange(3, 9), [1, 2, 50], np.arange(12, 24)])
    y = np.concatenate([np.full(40, 5), np.full(6, 6), [6, 6, 6], np.full(12, 7)])
    p = np.concatenate([np.ones(40), np.zeros(6), [1, 0, 1], np.arange(12) % 2])
    t = np.concatenate([np.full(40, 100), np.full(9, 100), np.full(12, 5000)])
    return Events(x, y, t, p, width, height)


def _round_trip_cases() -> list[Events]:
    rng = np.random.default_rng(1)
    wide = np.sort(rng.integers(0, 1 << 36, 3000))           # gaps of hours: many wraps
    return [
        random_events(5000, seed=3, t_span_us=2000),         # many events per µs
        random_events(3000, width=1280, height=720, seed=4, t_span_us=60_000_000),
        Events(rng.integers(0, 2048, 3000), rng.integers(0, 2048, 3000), wide,
               rng.integers(0, 2, 3000), 2048, 2048),
        _dense_rows(),
        Events([3], [4], [(1 << 34) + 5], [1], 8, 8),
    ]


@pytest.mark.parametrize("case", range(len(_round_trip_cases())))
@pytest.mark.parametrize("codec", ["evt3", "evt2"])
def test_round_trip(tmp_path: Path, codec: str, case: int) -> None:
    events = _round_trip_cases()[case]
    write, read, iterate = (
        (write_evt3, read_evt3, iter_evt3) if codec == "evt3"
        else (write_evt2, read_evt2, iter_evt2)
    )
    path = tmp_path / f"{codec}.raw"
    write(path, events)
    assert not list(tmp_path.glob("*.partial"))
    back = read(path)
    assert back == events
    _check_dtypes(back)
    assert read_raw(path) == events
    for chunk_bytes in (6, 1000):
        parts = list(iterate(path, chunk_bytes=chunk_bytes))
        assert sum(map(_as_tuples, parts), []) == _as_tuples(events)


@pytest.mark.parametrize("codec", ["evt3", "evt2"])
def test_a_time_span_is_decoded_holding_only_that_span(tmp_path: Path, codec: str, monkeypatch) -> None:
    """``read_raw(..., t0_us=, t1_us=)`` equals the whole file cut to the span (open ends too), for every chunk
    size; with cmax.events.MAX_EVENTS under the file's count but over the span's, the whole file is refused and
    the span is read; ``iter_raw`` yields what the format's own iterator does."""
    events = random_events(20_000, seed=3, t_span_us=1_000_000)
    path = tmp_path / f"{codec}.raw"
    (write_evt3 if codec == "evt3" else write_evt2)(path, events)
    for t0, t1 in ((250_000, 400_000), (None, 100_000), (900_000, None), (2_000_000, None), (0, 1)):
        expected = events.slice_time(-1 if t0 is None else t0, 2**62 if t1 is None else t1)
        for chunk_bytes in (64, 4096, 1 << 20):
            assert read_raw(path, t0_us=t0, t1_us=t1, chunk_bytes=chunk_bytes) == expected, (t0, t1, chunk_bytes)
    span = events.slice_time(250_000, 400_000)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", len(span) + 100)
    with pytest.raises(ValueError, match="MAX_EVENTS"):
        read_raw(path)
    assert read_raw(path, t0_us=250_000, t1_us=400_000, chunk_bytes=4096) == span
    own = iter_evt3 if codec == "evt3" else iter_evt2
    assert [len(c) for c in iter_raw(path, chunk_bytes=4096)] == [len(c) for c in own(path, chunk_bytes=4096)]


@pytest.mark.parametrize("codec", ["evt3", "evt2"])
def test_round_trip_in_small_encoder_blocks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, codec: str
) -> None:
    """The encoders work block by block; state (time high, y) carries across blocks."""
    import cmax.io.prophesee.writer as prophesee

    write, read = (write_evt3, read_evt3) if codec == "evt3" else (write_evt2, read_evt2)
    for case in _round_trip_cases():
        for block in (1, 7, 64):
            monkeypatch.setattr(prophesee, "_ENCODE_BLOCK", block)
            write(tmp_path / "blocks.raw", case[:700], overwrite=True)
            assert read(tmp_path / "blocks.raw") == case[:700]


def test_evt3_encoder_uses_vectors(tmp_path: Path) -> None:
    events = _dense_rows()
    write_evt3(tmp_path / "a.raw", events)
    write_evt2(tmp_path / "b.raw", events)
    header = len(b"% evt 3.0\n% format EVT3;height=48;width=64\n% geometry 64x48\n"
                 b"% generator evtslowtv\n% end\n")
    words = np.frombuffer((tmp_path / "a.raw").read_bytes()[header:], "<u2")
    assert np.count_nonzero(words >> 12 == 0x4) >= 5
    assert words.size < len(events) / 2


def test_evt3_words_of_a_run_of_two_and_a_vector(tmp_path: Path) -> None:
    """The words by the EVT 3.0 layout, by hand: a run of two events in one block stays two ADDR_X words,
    a run of three in the next block is VECT_BASE_X + VECT_12 (bits 1-3 of block 1), after the first
    unit's TIME_HIGH, TIME_LOW (100 µs) and ADDR_Y (row 5)."""
    events = Events([0, 1, 13, 14, 15], [5] * 5, [100] * 5, [1] * 5, 64, 8)
    write_evt3(tmp_path / "a.raw", events)
    header = b"% evt 3.0\n% format EVT3;height=8;width=64\n% geometry 64x8\n% generator evtslowtv\n% end\n"
    raw = (tmp_path / "a.raw").read_bytes()
    assert raw.startswith(header)
    words = np.frombuffer(raw[len(header):], "<u2").tolist()
    assert words == [0x8000, 0x6000 | 100, 5, 0x2800 | 0, 0x2800 | 1, 0x3800 | 12, 0x4000 | 0b1110]
    assert read_evt3(tmp_path / "a.raw") == events


def test_write_empty_and_invalid(tmp_path: Path) -> None:
    for write, read in ((write_evt3, read_evt3), (write_evt2, read_evt2)):
        write(tmp_path / f"empty{write.__name__}.raw", Events.empty(10, 5))
        assert read(tmp_path / f"empty{write.__name__}.raw") == Events.empty(10, 5)
        with pytest.raises(TypeError):
            write(tmp_path / "x.raw", np.zeros(3))
        with pytest.raises(ValueError, match="2048"):
            write(tmp_path / "x.raw", Events([0], [0], [0], [0], 4000, 10))
        with pytest.raises(ValueError, match=">= 0"):
            write(tmp_path / "x.raw", Events([0], [0], [-1], [0], 10, 10))
    with pytest.raises(ValueError, match="below"):
        write_evt3(tmp_path / "x.raw", Events([0], [0], [1 << 41], [0], 10, 10))
    # EVT 2.0 too (was: two events at 1.6e15 µs, epoch-like, written as 745 kB of TIME_HIGH words from 0)
    with pytest.raises(ValueError, match=r"below 1099511627776 µs .* for EVT 2.0, got 1600000000000500: times since"):
        write_evt2(tmp_path / "x.raw", Events([1, 2], [1, 2], [1_600_000_000_000_000, 1_600_000_000_000_500], [1, 0],
                                             640, 480))
    last = (1 << 40) - 1                  # the largest time both write, and read back exactly
    for write, read in ((write_evt3, read_evt3), (write_evt2, read_evt2)):
        events = Events([1, 2], [1, 2], [last - 100, last], [1, 0], 640, 480)
        assert read(write(tmp_path / f"last{write.__name__}.raw", events)) == events
    assert not (tmp_path / "x.raw").exists()
    assert not list(tmp_path.glob("*.partial"))


# -- header and sensor size -----------------------------------------------------------
@pytest.mark.parametrize("header, size, stated", [
    (b"% evt 3.0\n% geometry 640x480\n", (640, 480), True),
    (b"% format EVT3;height=720;width=1280\n", (1280, 720), True),
    (b"% evt 3.0\n% plugin_name hal_plugin_gen41_evk3\n", (1280, 720), False),
    (b"% evt 3.0\n% plugin_name hal_plugin_imx636_evk4\n", (1280, 720), False),
    (b"% evt 3.0\n% plugin_name hal_plugin_gen31_fx3\n", (640, 480), False),
    (b"% evt 3.0\n% sensor_generation 4.1\n", (1280, 720), False),
])
def test_sensor_size_from_header(tmp_path: Path, header: bytes, size: tuple[int, int], stated: bool) -> None:
    """A stated size (format, geometry) is the file's; one inferred from the camera's name gives way to the caller's."""
    path = _write(tmp_path / "h.raw", header, [0x8000, 0x6000, 0x0001, 0x2002], "<u2")
    assert read_evt3(path).sensor_size == size
    assert read_raw(path).sensor_size == size
    assert read_evt3(path, width=size[0], height=size[1]).sensor_size == size
    if stated:
        with pytest.raises(ValueError, match=rf"width=100, height=90 contradicts the {size[0]}x{size[1]} sensor"):
            read_evt3(path, width=100, height=90)
    else:
        assert read_evt3(path, width=100, height=90).sensor_size == (100, 90)


def test_sensor_size_unknown(tmp_path: Path) -> None:
    path = _write(tmp_path / "h.raw", b"% evt 3.0\n", [0x8000, 0x6000, 0x0001, 0x2002], "<u2")
    with pytest.raises(FormatError, match="pass width= and height="):
        read_evt3(path)
    with pytest.raises(ValueError, match="both"):
        read_evt3(path, width=10)
    assert _as_tuples(read_evt3(path, width=4, height=4)) == [(2, 1, 0, 0)]


def test_headerless_stream(tmp_path: Path) -> None:
    path = _write(tmp_path / "bare.raw", b"", EVT3_WORDS, "<u2")
    assert _as_tuples(read_evt3(path, width=32, height=16)) == EVT3_EVENTS
    with pytest.raises(FormatError, match="declares no event format"):
        read_raw(path, width=32, height=16)


# -- corrupt input --------------------------------------------------------------------
def test_truncated_word(tmp_path: Path) -> None:
    path = tmp_path / "odd.raw"
    path.write_bytes(EVT3_HEADER + np.asarray(EVT3_WORDS, "<u2").tobytes() + b"\x01")
    for call in (lambda: read_evt3(path), lambda: iter_evt3(path), lambda: read_raw(path)):
        with pytest.raises(FormatError, match="odd.raw.*whole number"):
            call()
    path2 = tmp_path / "short2.raw"
    path2.write_bytes(EVT2_HEADER + np.asarray(EVT2_WORDS, "<u4").tobytes()[:-2])
    with pytest.raises(FormatError, match="short2.raw.*4-byte words"):
        read_evt2(path2)


def test_unterminated_header(tmp_path: Path) -> None:
    path = tmp_path / "cut.raw"
    path.write_bytes(b"% evt 3.0\n% format EVT3;width=1280")
    with pytest.raises(FormatError, match="cut.raw.*no end of line"):
        read_raw(path)


def _without_end_line(path: Path) -> Path:
    """``path`` rewritten without its ``% end`` line, as older Metavision/ATIS recordings are."""
    raw = path.read_bytes()
    assert raw.count(b"% end\n") == 1
    path.write_bytes(raw.replace(b"% end\n", b""))
    return path


@pytest.mark.parametrize("codec, first_t", [
    ("evt2", 0x25 * 64 + 41),      # first TIME_HIGH word 0x80000025: was 20 events dropped without a word
    ("evt3", 0x25 * 4096 + 10),    # first TIME_HIGH word 0x8025: was "not a whole number of 2-byte words"
])
def test_a_header_without_end_stops_at_an_event_word_starting_with_0x25(
    tmp_path: Path, codec: str, first_t: int
) -> None:
    """Report userC item 1: the first data word's byte 0x25 ('%') was read as a header line up to the next 0x0A."""
    n, rng = 200, np.random.default_rng(0)
    t = np.r_[np.full(20, first_t), np.sort(rng.integers(first_t + 64, first_t + 50_000, n - 20))]
    x = np.r_[np.full(20, 100), rng.integers(0, 640, n - 20)]
    events = Events(x, np.full(n, 33), t, np.zeros(n, int), width=640, height=480)
    writer, reader = {"evt2": (write_evt2, read_evt2), "evt3": (write_evt3, read_evt3)}[codec]
    path = _without_end_line(writer(tmp_path / f"noend.{codec}.raw", events))
    assert path.read_bytes().split(b"evtslowtv\n", 1)[1][:1] == b"%"      # the data starts with 0x25
    for read in (reader, read_raw):
        got = read(path)
        assert got == events and got.sensor_size == (640, 480)
    assert sum(len(chunk) for chunk in iter_raw(path, chunk_bytes=64)) == n


def test_a_header_line_may_hold_non_ascii_text(tmp_path: Path) -> None:
    header = "% evt 3.0\n% integrator_name Prophésée\t\r\n% geometry 32x16\n".encode("utf-8")
    path = _write(tmp_path / "utf8.raw", header, EVT3_WORDS, "<u2")
    assert _as_tuples(read_raw(path)) == EVT3_EVENTS


def test_garbage(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    path = tmp_path / "garbage.raw"
    path.write_bytes(EVT3_HEADER + rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(FormatError, match="garbage.raw.*reserved EVT 3.0 word type"):
        read_evt3(path)
    with pytest.raises(FormatError, match="garbage.raw"):
        list(iter_evt3(path, chunk_bytes=64))
    path2 = tmp_path / "garbage2.raw"
    path2.write_bytes(EVT2_HEADER + rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    with pytest.raises(FormatError, match="garbage2.raw.*reserved EVT 2.0 word type"):
        read_evt2(path2)
    path3 = tmp_path / "text.raw"
    path3.write_bytes(b"this is not an event file\n" * 10)
    with pytest.raises(FormatError, match="text.raw"):
        read_raw(path3)


@pytest.mark.parametrize("codec", ["evt3", "evt2"])
def test_words_that_decode_but_are_not_event_data_are_refused(tmp_path: Path, codec: str) -> None:
    """Bytes under a RAW header that hold no reserved word type but no Prophesee stream either (zeros of a file
    never written, 0xFF of erased flash, ECD text) decoded into 0 events without a word: every event word came
    before any TIME_HIGH. Real streams set their clock first (the Gen4 sample skips none of its words)."""
    header, dtype, read = ((EVT3_HEADER, "<u2", read_evt3) if codec == "evt3" else (EVT2_HEADER, "<u4", read_evt2))
    text = b"".join(b"%.6f %d %d %d\n" % (i * 1e-4, i % 32, i % 16, i % 2) for i in range(64))
    cases = {"zeros": bytes(4000), "ones": b"\xff" * 4000}
    if codec == "evt3":                 # as EVT 2.0 words, text holds reserved types (0x3: the digits), refused
        cases["text"] = text
    for name, data in cases.items():
        path = tmp_path / f"{name}.raw"
        path.write_bytes(header + data)
        for call in (lambda: read(path), lambda: read_raw(path), lambda: list(iter_raw(path, chunk_bytes=64)),
                     lambda: read_raw(path, t0_us=0, t1_us=10)):
            with pytest.raises(FormatError, match=rf"{name}.raw: its [0-9,]+ words of EVT {codec[-1]}.0 data hold "
                                                  r"no TIME_HIGH word .* not EVT .* event data"):
                call()
    # a TIME_HIGH word after text (a byte 0x80 of cp1252's euro sign): 0 events decoded, every other one skipped
    words = [0x2031, 0x3032, 0x0A31] * 20 + [0x8001] if codec == "evt3" else [0x00012345] * 60 + [0x80000001]
    path = _write(tmp_path / "late.raw", header, words, dtype)
    with pytest.raises(FormatError, match=r"late.raw: [0-9,]+ of the [0-9,]+ events its words hold come before a "
                                          r"time.* and only 0 after"):
        read_raw(path)
    # a stream of time words only (a dark scene) and a header alone hold no events: read, no error
    dark = [0x8001, 0x6005, 0x8002] if codec == "evt3" else [0x80000001, 0x80000002]
    assert len(read_raw(_write(tmp_path / "dark.raw", header, dark, dtype))) == 0
    assert len(read_raw(_write(tmp_path / "empty.raw", header, [], dtype))) == 0


def test_reserved_word_offset(tmp_path: Path) -> None:
    path = _write(tmp_path / "r.raw", EVT3_HEADER, [0x8000, 0x6000, 0x9000], "<u2")
    with pytest.raises(FormatError, match=rf"0x9, at byte offset {len(EVT3_HEADER) + 4}"):
        read_evt3(path)


def test_event_outside_sensor(tmp_path: Path) -> None:
    header = b"% evt 3.0\n% format EVT3;height=16;width=20\n% end\n"
    path = _write(tmp_path / "o.raw", header, [0x8000, 0x6000, 0x0001, 0x3010, 0x4800], "<u2")
    message = rf"x=27 outside the 20x16 sensor, at byte offset {len(header) + 8}"
    with pytest.raises(FormatError, match=message):
        read_evt3(path)
    path2 = _write(tmp_path / "o2.raw", EVT2_HEADER, [0x80000000, 0x00000020], "<u4")
    with pytest.raises(FormatError, match="y=32 outside"):
        read_evt2(path2)


def test_wrong_format_in_header(tmp_path: Path, evt2_file: Path) -> None:
    with pytest.raises(FormatError, match="declares 'evt2'"):
        read_evt3(evt2_file)
    path = _write(tmp_path / "e21.raw", b"% evt 2.1\n% geometry 32x16\n", [0, 0], "<u4")
    with pytest.raises(FormatError, match="unsupported event format 'evt 2.1'"):
        read_raw(path)


def test_time_going_back(tmp_path: Path) -> None:
    words = [0x8001, 0x6010, 0x0001, 0x2002, 0x600F, 0x2803, 0x6011, 0x2004]
    path = _write(tmp_path / "back.raw", EVT3_HEADER, words, "<u2")
    with pytest.raises(FormatError, match="time goes back from 4112 µs to 4111 µs"):
        read_evt3(path)
    with pytest.raises(FormatError, match="time goes back"):
        list(iter_evt3(path, chunk_bytes=10))
    expected = [(3, 1, 4111, 1), (2, 1, 4112, 0), (4, 1, 4113, 0)]
    assert _as_tuples(read_evt3(path, sort=True)) == expected
    assert _as_tuples(next(iter_evt3(path, sort=True))) == _as_tuples(read_evt3(path, sort=True))
    with pytest.raises(FormatError, match="spans chunks"):
        list(iter_evt3(path, sort=True, chunk_bytes=10))


def test_bad_arguments(evt3_file: Path) -> None:
    with pytest.raises(ValueError, match="chunk_bytes"):
        read_evt3(evt3_file, chunk_bytes=0)
    with pytest.raises(TypeError, match="chunk_bytes"):
        iter_evt3(evt3_file, chunk_bytes=1.5)
    with pytest.raises(TypeError):
        read_evt3(evt3_file, 32, 16)  # options are keyword-only


def test_file_info_of_a_raw_file_too_long_to_hold(tmp_path: Path, monkeypatch) -> None:
    """``cmax info`` of a RAW file over cmax.events.MAX_EVENTS (lowered here under its 400k events, over one
    chunk's): decoded chunk by chunk (it was decoded whole and refused), every figure that of the events."""
    from cmax.io.info import file_info

    events = random_events(400_000, seed=9, t_span_us=2_000_000)
    path = tmp_path / "long.raw"
    write_evt3(path, events)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 150_000)
    info = file_info(path)
    assert (info.format, info.count, info.width, info.height) == ("raw", len(events), 64, 48)
    assert (info.t_start_us, info.t_end_us) == (int(events.t[0]), int(events.t[-1]))
    assert info.on_count == int(np.count_nonzero(events.p))
    empty = tmp_path / "empty.raw"
    write_evt3(empty, Events([], [], [], [], 32, 16))
    info = file_info(empty)
    assert (info.count, info.width, info.height, info.t_start_us) == (0, 32, 16, None)


@pytest.mark.parametrize("lines, match", [
    (b"% evt 3.0\n% format EVT3;height=480;width=640\n% geometry 1280x720\n",
     r"its 'format' line states a 640x480 sensor, its 'geometry' line 1280x720"),
    (b"% evt 3.0\n% format EVT2;height=480;width=640\n",
     r"its 'evt 3.0' line and its 'format EVT2;height=480;width=640' line declare different event formats"),
    (b"% evt 2.0\n% evt 3.0\n% format EVT3;height=480;width=640\n",
     r"it has the lines 'evt 2.0' and 'evt 3.0'"),
])
def test_a_header_that_contradicts_itself_is_refused(tmp_path: Path, lines: bytes, match: str) -> None:
    """A header stating 640x480 in its format line and 1280x720 in its geometry line was read as 640x480
    without a word; 'evt 3.0' beside 'format EVT2' was decoded as EVT2 and failed on a 'reserved EVT 2.0 word'."""
    events = Events([1, 600], [2, 400], [10, 20], [1, 0], width=640, height=480)
    data = write_evt3(tmp_path / "ok.raw", events).read_bytes().split(b"% end\n", 1)[1]
    path = tmp_path / "contradicting.raw"
    path.write_bytes(lines + b"% end\n" + data)
    for call in (lambda: read_raw(path), lambda: read_raw(path, width=640, height=480), lambda: read_evt3(path)):
        with pytest.raises(FormatError, match=rf"contradicting.raw: the header contradicts itself: {match}"):
            call()
    agreeing = tmp_path / "agreeing.raw"
    agreeing.write_bytes(b"% evt 3.0\n% format EVT3;height=480;width=640\n% geometry 640x480\n% end\n" + data)
    assert read_raw(agreeing) == events


def test_a_prophesee_dat_file_is_refused_naming_the_dat_format_not_sent_to_the_evt_decoders(tmp_path: Path) -> None:
    """A Gen1 / 1 Mpx automotive ``*_td.dat`` (``% Data file containing CD events.``, ``% Height 240``, ``% Width
    304``, then a type byte, a size byte and 8-byte events) was refused by ``read`` with "the header declares no
    event format ...; call read_evt3 or read_evt2 directly", advice that sends its 8-byte events to the EVT decoders
    (which then fail on word alignment or reserved types, as if the file were corrupt). Every reader now names the DAT
    format and its loaders."""
    from cmax.io import read

    n = 100
    ts = np.arange(n, dtype=np.uint32) * 10
    address = (np.arange(n) % 304 | (np.arange(n) % 240) << 14 | (np.arange(n) % 2) << 28).astype(np.uint32)
    body = np.column_stack([ts, address]).astype(np.uint32).tobytes()
    path = tmp_path / "gen1_td.dat"
    path.write_bytes(b"% Data file containing CD events.\n% Version 2\n% Date 2019-01-01 00:00:00\n% Height 240\n"
                     b"% Width 304\n" + bytes([0, 8]) + body)
    said = r"gen1_td.dat: the header's line '% Data file containing CD events.' marks a Prophesee DAT file"
    for call in (lambda: read(path), lambda: read_evt2(path, width=304, height=240),
                 lambda: read_evt3(path, width=304, height=240), lambda: list(iter_evt3(path, width=304, height=240))):
        with pytest.raises(FormatError, match=said + r" .*not EVT 2.0 or 3.0 words.*PSEELoader"):
            call()
