"""DSEC-layout HDF5: round trips, windowed reads, ms_to_idx, atomic writes."""
from __future__ import annotations

import re

import h5py
import numpy as np
import pytest

from cmax import Events
from cmax.io import FormatError, H5Reader, H5Writer, read, read_h5, write_h5
from conftest import random_events


def test_round_trip_keeps_every_column(tmp_path):
    ev = random_events(5000, width=346, height=260, t_span_us=2_500_000)
    path = write_h5(tmp_path / "ev.h5", ev, source="test", settings={"cp": 0.2})
    back = read_h5(path)
    assert back == ev
    with H5Reader(path) as reader:
        assert reader.attrs["source"] == "test" and reader.attrs["settings"] == {"cp": 0.2}
        assert (reader.width, reader.height) == (346, 260)
        assert reader.t_start == ev.t_start and reader.t_end == ev.t_end


def test_layout_is_dsec(tmp_path):
    ev = random_events(3000, t_span_us=10_000)
    ev = Events(ev.x, ev.y, ev.t + 1_000_000_123, ev.p, ev.width, ev.height)
    path = write_h5(tmp_path / "ev.h5", ev)
    with h5py.File(path, "r") as file:
        assert set(file["events"]) == {"x", "y", "t", "p"}
        t_offset = int(file["t_offset"][()])
        t_rel = file["events/t"][:]
        ms_to_idx = file["ms_to_idx"][:]
    assert t_offset == ev.t_start
    np.testing.assert_array_equal(t_rel + t_offset, ev.t)
    # ms_to_idx[k] is the first index with relative time >= 1000*k (independent recomputation).
    expected = np.searchsorted(t_rel, 1000 * np.arange(len(ms_to_idx)), side="left")
    np.testing.assert_array_equal(ms_to_idx, expected)
    assert ms_to_idx[-1] == len(ev)


@pytest.mark.parametrize("chunk_size", [7, 256, 100_000])
def test_windowed_read_equals_slicing_in_memory(tmp_path, chunk_size):
    ev = random_events(20_000, t_span_us=1_000_000, seed=3)
    with H5Writer(tmp_path / "ev.h5", ev.width, ev.height, chunk_size=chunk_size) as writer:
        for part in ev.windows(count=1234):
            writer.append(part)
    rng = np.random.default_rng(1)
    with H5Reader(tmp_path / "ev.h5") as reader:
        assert len(reader) == len(ev)
        bounds = [(-5, 10), (0, 1), (999, 1001), (ev.t_end, ev.t_end + 1), (ev.t_end + 1, ev.t_end + 5000)]
        bounds += [tuple(sorted(rng.integers(-1000, 1_001_000, 2))) for _ in range(30)]
        for t0, t1 in bounds:
            assert reader.window(t0, t1) == ev.slice_time(t0, t1), (t0, t1)
        windows = list(reader.windows(50_000))
    assert sum(len(w) for w in windows) == len(ev)


def test_window_reads_only_its_slice(tmp_path, monkeypatch):
    ev = random_events(50_000, t_span_us=5_000_000, seed=2)
    path = write_h5(tmp_path / "ev.h5", ev)
    reader = H5Reader(path)
    requested = []
    original = reader._read

    def spy(start, stop):
        requested.append((start, stop))
        return original(start, stop)

    monkeypatch.setattr(reader, "_read", spy)
    window = reader.window(2_000_000, 2_010_000)
    # one read: the window's rows plus one row each side, to check the ms_to_idx entries used
    offset = ev.t_start  # write_h5's t_offset: ms boundaries are counted from it
    k0, k1 = (2_000_000 - offset) // 1000, -(-(2_010_000 - offset) // 1000)
    assert requested == [(ev.index_at(offset + 1000 * k0) - 1, ev.index_at(offset + 1000 * k1) + 1)]
    assert window == ev.slice_time(2_000_000, 2_010_000)
    assert len(window) < 200
    reader.close()


def test_interrupted_writer_leaves_no_file(tmp_path):
    target = tmp_path / "ev.h5"
    ev = random_events(1000)
    with pytest.raises(RuntimeError, match="boom"):
        with H5Writer(target, ev.width, ev.height, chunk_size=100) as writer:
            writer.append(ev[:500])
            raise RuntimeError("boom")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_partial_file_has_other_name_while_writing(tmp_path):
    target = tmp_path / "ev.h5"
    ev = random_events(1000)
    writer = H5Writer(target, ev.width, ev.height, chunk_size=100)
    writer.append(ev)
    assert not target.exists() and len(list(tmp_path.glob("ev.h5.*.partial"))) == 1
    writer.close()
    assert target.exists() and not list(tmp_path.glob("*.partial")) and not list(tmp_path.glob("*.lock"))
    assert read(target) == ev


def test_writer_memory_is_bounded_by_chunk_size(tmp_path):
    ev = random_events(10_000)
    with H5Writer(tmp_path / "ev.h5", ev.width, ev.height, chunk_size=1000) as writer:
        for part in ev.windows(count=300):
            writer.append(part)
            assert writer._buffered < 1000 + 300
    assert read_h5(tmp_path / "ev.h5") == ev


def test_writer_rejects_bad_appends(tmp_path):
    ev = random_events(100)
    with H5Writer(tmp_path / "a.h5", ev.width, ev.height) as writer:
        writer.append(ev[50:])
        with pytest.raises(ValueError, match="time order"):
            writer.append(ev[:50])
        with pytest.raises(ValueError, match="sensor"):
            writer.append(Events([0], [0], [ev.t_end], [1], 5, 5))
        with pytest.raises(TypeError, match="cmax.Events"):
            writer.append(ev.to_structured())
    with pytest.raises(FileExistsError, match="overwrite"):
        H5Writer(tmp_path / "a.h5", ev.width, ev.height)
    with pytest.raises(FileNotFoundError, match="folder"):
        H5Writer(tmp_path / "missing" / "a.h5", 4, 4)
    with pytest.raises(ValueError, match="compression"):
        H5Writer(tmp_path / "b.h5", 4, 4, compression="zip")


def test_empty_file_round_trip(tmp_path):
    path = write_h5(tmp_path / "empty.h5", Events.empty(32, 24))
    back = read_h5(path)
    assert len(back) == 0 and back.sensor_size == (32, 24)
    with H5Reader(path) as reader:
        assert len(reader.window(0, 10)) == 0


def test_gzip_compression_round_trip(tmp_path):
    ev = random_events(2000)
    assert read_h5(write_h5(tmp_path / "g.h5", ev, compression="gzip")) == ev


def test_original_dsec_file_without_sensor_size(tmp_path):
    """A file written like DSEC's own (uint32 t, no attributes) reads with a given size."""
    ev = random_events(1000, width=640, height=480, t_span_us=20_000)
    path = tmp_path / "dsec.h5"
    with h5py.File(path, "w") as file:
        file["events/x"], file["events/y"] = ev.x, ev.y
        file["events/t"] = (ev.t - 5).astype(np.uint32)
        file["events/p"] = ev.p.astype(np.uint8)
        file["t_offset"] = np.int64(5)
        file["ms_to_idx"] = np.searchsorted(ev.t - 5, 1000 * np.arange(21)).astype(np.uint64)
    with pytest.raises(ValueError, match="pass width= and height="):
        read(path)
    assert read(path, width=640, height=480) == ev
    assert read(path, width=640, height=480, t0_us=3000, t1_us=9000) == ev.slice_time(3000, 9000)


def test_corrupt_files_raise_format_error(tmp_path):
    path = write_h5(tmp_path / "ev.h5", random_events(5000))
    data = path.read_bytes()
    (tmp_path / "cut.h5").write_bytes(data[: len(data) // 3])
    with pytest.raises(FormatError):
        H5Reader(tmp_path / "cut.h5")
    with h5py.File(tmp_path / "other.h5", "w") as file:
        file["something"] = np.zeros(3)
    with pytest.raises(FormatError, match="neither DSEC"):
        read(tmp_path / "other.h5")
    with pytest.raises(FormatError, match="lacks the DSEC"):
        H5Reader(tmp_path / "other.h5")
    with pytest.raises(FileNotFoundError):
        H5Reader(tmp_path / "nothing.h5")


def test_a_long_recordings_index_is_read_an_entry_at_a_time(tmp_path, monkeypatch):
    """H5Reader loaded and checked the whole ms_to_idx when it opened a file: an hour of recording (3.6 M entries)
    took 0.26 s and 86 MB at every opening (cmax show of 50 ms, each file a training set reopens), ten hours ten
    times that. An index longer than MAX_INDEX_IN_MEMORY is read an entry at a time: the windows are the same."""
    import tracemalloc

    import cmax.io.h5 as h5
    from cmax.io import FormatError, H5Reader

    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, 2_100_000_000, 20_000))         # 35 minutes: an index of 2.1 M entries, 17 MB
    ev = Events(rng.integers(0, 64, t.size), rng.integers(0, 48, t.size), t, rng.integers(0, 2, t.size), 64, 48)
    path = write_h5(tmp_path / "long.h5", ev)
    monkeypatch.setattr(h5, "MAX_INDEX_IN_MEMORY", 1 << 20, raising=False)   # the default, pinned
    tracemalloc.start()
    try:
        reader = H5Reader(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2e6, peak                                         # the index alone: 17 MB
    with reader:
        for t0, t1 in ((0, 1_000), (1_000_000_123, 1_000_900_456), (2_099_000_000, 2**40), (-7, 5), (3, 3)):
            assert reader.window(int(ev.t[0]) + t0, int(ev.t[0]) + t1) == ev.slice_time(int(ev.t[0]) + t0,
                                                                                           int(ev.t[0]) + t1)
    with h5py.File(path, "r+") as file:                            # an entry past the events' rows
        file["ms_to_idx"][1_000_000] = 10 * len(ev)
    with H5Reader(path) as reader, pytest.raises(FormatError, match=r"corrupt ms_to_idx \(entry 1000000 is 200000"):
        reader.window(int(ev.t[0]) + 1_000_000_000, int(ev.t[0]) + 1_000_000_400)   # uses ms_to_idx[1000000]


def test_a_small_uncompressed_file_is_not_padded_to_a_whole_chunk(tmp_path):
    """write_h5(compression='none') of 20,000 events (260 kB of columns) made a 3.3 MB file: every column
    allocated a whole chunk of 2**18 events. The file is now about the size of its columns."""
    ev = random_events(20_000, width=64, height=48, t_span_us=1_000_000)
    path = write_h5(tmp_path / "small.h5", ev, compression="none")
    columns = 20_000 * (2 + 2 + 8 + 1)
    assert path.stat().st_size < 2 * columns + 100_000, path.stat().st_size
    assert read_h5(path) == ev


def test_an_h5_file_of_another_tool_s_layout_is_named_in_the_refusal(tmp_path):
    """Was: `is HDF5 but neither DSEC (events/x..p) nor MVSEC (davis/...)` for v2e's, event_utils' and Metavision's
    HDF5 files alike, nothing said about what the file holds; still refused (their unit or order is not stated)."""
    v2e, event_utils, metavision, other = (tmp_path / name for name in ("v2e.h5", "eu.h5", "cd.h5", "other.h5"))
    with h5py.File(v2e, "w") as file:
        file["events"] = np.zeros((5, 4), np.int32)
    with h5py.File(event_utils, "w") as file:
        for name in ("xs", "ys", "ts", "ps"):
            file[f"events/{name}"] = np.zeros(5)
    with h5py.File(metavision, "w") as file:
        file["CD/events"] = np.zeros(5, [("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    with h5py.File(other, "w") as file:
        file["foo"], file["bar"] = [1], [2]
    for path, words in ((v2e, "it holds a table 'events' of shape (5, 4) (as v2e writes)"),
                        (event_utils, "it holds events/xs, ys, ts, ps (the event_utils / E2VID layout)"),
                        (metavision, "it holds CD/events (Metavision's HDF5 event file, compressed with its ECF codec)"),
                        (other, "its top-level names: bar, foo")):
        with pytest.raises(FormatError, match=r"neither DSEC .* nor MVSEC \(davis/\.\.\.\); " + re.escape(words)):
            read(path, width=8, height=8)
