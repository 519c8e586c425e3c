"""Readers never guess (issue 20): time units, time ranges, polarity encodings and sizes are checked.

Each test builds the bad file by hand (h5py, bytes, numpy) and checks the
reader's refusal (the message names the file's field and the way out) or, under
a stated unit or encoding, the exact values read.
"""
from __future__ import annotations

import tracemalloc

import h5py
import numpy as np
import pytest

from cmax.events import Events
from cmax.io import FormatError, H5Reader, read, read_h5, read_mvsec, read_txt, write_h5
from cmax.io.info import file_info

W, H = 64, 48


def _dsec(path, t, *, p=None, x=None, t_offset=None, ms_to_idx=None, t_attrs=None, file_attrs=None):
    """A DSEC-layout file written with h5py directly (any dtypes, no checks)."""
    n = len(t)
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        group["x"] = rng.integers(0, W, n).astype(np.uint16) if x is None else x
        group["y"] = rng.integers(0, H, n).astype(np.uint16)
        group["t"] = t
        group["p"] = (np.arange(n) % 2).astype(np.uint8) if p is None else p
        for key, value in (t_attrs or {}).items():
            group["t"].attrs[key] = value
        if t_offset is not None:
            file["t_offset"] = t_offset
        if ms_to_idx is not None:
            file["ms_to_idx"] = ms_to_idx
        file.attrs["width"], file.attrs["height"] = W, H
        for key, value in (file_attrs or {}).items():
            file.attrs[key] = value
    return path


# -- time units -----------------------------------------------------------------------------
def test_float_seconds_are_refused_without_a_stated_unit(tmp_path):
    t_s = np.linspace(0.0, 0.5, 50_000)  # half a second of events, as float seconds
    path = _dsec(tmp_path / "seconds.h5", t_s)
    for call in (lambda: read_h5(path), lambda: H5Reader(path), lambda: file_info(path), lambda: read(path)):
        with pytest.raises(FormatError, match=r"events/t holds float64 times .* pass time_unit='s'"):
            call()
    events = read_h5(path, time_unit="s")
    assert events.t_start == 0 and events.t_end == 500_000
    np.testing.assert_array_equal(events.t, np.rint(t_s * 1e6).astype(np.int64))
    info = file_info(path, time_unit="s")
    assert info.duration_s == pytest.approx(0.5) and info.rate_hz == pytest.approx(100_000, rel=1e-3)


def test_a_unit_attribute_in_the_file_is_used_and_a_contradiction_refused(tmp_path):
    path = _dsec(tmp_path / "ms.h5", np.array([0.0, 1.5, 2.25]), t_attrs={"unit": "ms"})
    assert read_h5(path).t.tolist() == [0, 1500, 2250]
    assert read_h5(path, time_unit="ms").t.tolist() == [0, 1500, 2250]
    with pytest.raises(FormatError, match=r"time_unit='s' contradicts the unit the file states \('ms'\)"):
        read_h5(path, time_unit="s")
    # integer times with a file-level unit: scaled exactly
    path = _dsec(tmp_path / "int_ms.h5", np.array([0, 7, 9], np.int64), file_attrs={"time_unit": "ms"})
    assert read_h5(path).t.tolist() == [0, 7000, 9000]
    with pytest.raises(ValueError, match=r"time_unit must be one of 'us', 'ms', 's'"):
        read_h5(path, time_unit="minutes")
    path = _dsec(tmp_path / "odd.h5", np.array([0, 7], np.int64), t_attrs={"units": "furlongs"})
    with pytest.raises(FormatError, match=r"events/t attribute 'units' must be one of 'us', 'ms', 's'"):
        read_h5(path)


def test_fractional_microseconds_are_rounded_only_under_a_stated_unit(tmp_path):
    path = _dsec(tmp_path / "frac.h5", np.array([10.4, 10.6, 12.5, 13.5]))
    with pytest.raises(FormatError, match=r"float64 times"):
        read_h5(path)  # not truncated to 10, 10, 12, 13
    assert read_h5(path, time_unit="us").t.tolist() == [10, 11, 12, 14]  # nearest, half to even


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_times_are_named(tmp_path, bad):
    t = np.array([0.0, 0.1, bad, 0.3])
    path = _dsec(tmp_path / "nan.h5", t)
    with pytest.raises(FormatError, match=r"events/t\[2\] is -?(nan|inf), a non-finite time"):
        read_h5(path, time_unit="s")


def test_t_plus_t_offset_beyond_int64_is_refused_not_wrapped(tmp_path):
    big = np.iinfo(np.int64).max - 50
    path = _dsec(tmp_path / "wrap.h5", np.array([0, 10, 100], np.int64), t_offset=np.int64(big))
    with pytest.raises(FormatError, match=r"events/t\[2\] = 100 µs plus t_offset = .* overflows int64"):
        read_h5(path)
    with H5Reader(path) as reader:
        assert reader.t_start == big  # the first event still fits
        with pytest.raises(FormatError, match=r"overflows int64"):
            reader.t_end
        assert reader.window(big, big + 11).t.tolist() == [big, big + 10]
    path = _dsec(tmp_path / "u64.h5", np.array([0, 2**63 + 5], np.uint64))
    with pytest.raises(FormatError, match=r"events/t\[1\] = 9223372036854775813 us does not fit"):
        read_h5(path)


def test_a_float_time_beyond_int64_microseconds_is_refused(tmp_path):
    path = _dsec(tmp_path / "far.h5", np.array([0.0, 1e13]))
    with pytest.raises(FormatError, match=r"events/t\[1\] = 10000000000000\.0 s does not fit into int64 microseconds"):
        read_h5(path, time_unit="s")


def test_t_offset_must_be_one_number(tmp_path):
    path = _dsec(tmp_path / "offsets.h5", np.arange(3, dtype=np.int64), t_offset=np.arange(5, dtype=np.int64))
    with pytest.raises(FormatError, match=r"t_offset must be a single number, got shape \(5,\)"):
        H5Reader(path)


def test_a_fractional_float_t_offset_needs_a_stated_unit(tmp_path):
    """A float t_offset in seconds beside integer µs events/t (as a re-export may write it) was read as µs and
    rounded: 1600000000.123456 became 1,600,000,000 µs, the absolute times 10^6 too small, without a word."""
    t = np.array([0, 5, 9], np.uint32)
    path = _dsec(tmp_path / "seconds.h5", t, t_offset=np.float64(1600000000.123456))
    with pytest.raises(FormatError, match=r"t_offset holds the fractional number 1600000000.123456, not whole "
                                          r"microseconds .* state it with a 'unit' attribute on t_offset"):
        read(path)
    with h5py.File(path, "r+") as file:
        file["t_offset"].attrs["unit"] = "s"
    assert read(path).t.tolist() == [1600000000123456, 1600000000123461, 1600000000123465]
    # whole floats are µs as integers are; a stated unit rounds a fraction (half to even), as for events/t
    whole = _dsec(tmp_path / "whole.h5", t, t_offset=np.float64(1600000000123456.0))
    assert read(whole).t.tolist() == [1600000000123456, 1600000000123461, 1600000000123465]
    half = _dsec(tmp_path / "half.h5", t, t_offset=np.float64(123.5))
    with pytest.raises(FormatError, match="fractional number 123.5"):
        read(half)
    assert read(half, time_unit="us").t.tolist() == [124, 129, 133]


# -- ms_to_idx against t --------------------------------------------------------------------
def test_an_index_that_disagrees_with_t_is_named_not_an_empty_window(tmp_path):
    events = Events(np.zeros(3000, int), np.zeros(3000, int), np.arange(3000) * 10, np.ones(3000, int), W, H)
    good = write_h5(tmp_path / "good.h5", events)
    with h5py.File(good, "r") as file:
        index = file["ms_to_idx"][:]
    # the index of a recording 10x slower: structurally fine (monotone, in range), wrong for these times
    wrong = np.minimum(index // 10, len(events)).astype(np.uint64)
    path = _dsec(tmp_path / "bad.h5", events.t, ms_to_idx=wrong, t_offset=np.int64(0))
    np.testing.assert_array_equal(read_h5(path).t, events.t)  # a whole read does not use the index
    with H5Reader(path) as reader:
        with pytest.raises(FormatError, match=r"ms_to_idx disagrees with events/t: ms_to_idx\[10\] = 10"):
            reader.window(10_000, 20_000)
    with H5Reader(good) as reader:
        assert reader.window(10_000, 20_000) == events.slice_time(10_000, 20_000)


def test_an_index_shorter_than_the_recording_is_completed_on_disk(tmp_path):
    events = Events(np.zeros(5000, int), np.zeros(5000, int), np.arange(5000) * 7, np.ones(5000, int), W, H)
    t = events.t
    short = np.searchsorted(t, np.arange(0, 10) * 1000).astype(np.uint64)  # 10 ms of a 35 ms recording
    path = _dsec(tmp_path / "short.h5", t, ms_to_idx=short, t_offset=np.int64(0))
    with H5Reader(path) as reader:
        for t0, t1 in [(20_000, 30_000), (5_000, 34_000), (-100, 3)]:
            got = reader.window(t0, t1)
            assert got.t.tolist() == events.slice_time(t0, t1).t.tolist(), (t0, t1)


# -- declared sizes against stored data ----------------------------------------------------
def _declared_columns(path, rows, *, index_rows=None):
    """Event columns (10 stored rows, or ``rows`` declared contiguous and never written) and an
    optional chunked ``ms_to_idx`` declaring ``index_rows`` entries that are never written."""
    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        for name, dtype in (("x", "u2"), ("y", "u2"), ("t", "i8"), ("p", "u1")):
            if rows is None:
                group.create_dataset(name, data=np.zeros(10, dtype))
            else:
                group.create_dataset(name, shape=(rows,), dtype=dtype)
        if index_rows is not None:
            file.create_dataset("ms_to_idx", shape=(index_rows,), dtype="u8", chunks=(1 << 20,))
        file.attrs["width"], file.attrs["height"] = W, H
    return path


def _refusal_peak(call, match, error=FormatError) -> int:
    """Bytes allocated (tracemalloc peak) while ``call`` raises ``error`` matching ``match``."""
    tracemalloc.start()
    try:
        with pytest.raises(error, match=match):
            call()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_a_declared_index_larger_than_the_file_is_refused_before_allocating(tmp_path):
    path = _declared_columns(tmp_path / "index.h5", None, index_rows=600_000_000)  # 4.8 GB declared
    assert path.stat().st_size < 20_000
    match = r"ms_to_idx declares 600,000,000 entries in 573 chunks but the file stores only 0"
    for call in (lambda: H5Reader(path), lambda: file_info(path)):
        peak = _refusal_peak(call, match)
        assert peak < 5_000_000, f"the refusal allocated {peak / 1e6:.0f} MB"
    path = _declared_columns(tmp_path / "columns.h5", 300_000_000)  # contiguous layout, never written
    with pytest.raises(FormatError, match=r"events/x declares 300,000,000 entries but the file stores only 0"):
        file_info(path)


def test_a_column_that_is_a_group_is_a_format_error(tmp_path):
    path = tmp_path / "group.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        group.create_group("x")
        for name in "ytp":
            group[name] = np.zeros(3, np.uint16)
        file.attrs["width"], file.attrs["height"] = W, H
    with pytest.raises(FormatError, match=r"events/x must be a dataset, got a Group"):
        read(path)


# -- polarity ----------------------------------------------------------------------------
def test_signed_polarity_in_a_dsec_file_is_refused_not_counted_as_on(tmp_path):
    p = np.where(np.arange(1000) % 4 == 0, 1, -1).astype(np.int8)  # 25% ON as -1/+1
    path = _dsec(tmp_path / "signed.h5", np.arange(1000, dtype=np.int64), p=p)
    for call in (lambda: file_info(path), lambda: read_h5(path), lambda: read(path)):
        with pytest.raises(FormatError, match=r"events/p holds the polarity values \[-1, 1\], but the stated "
                                              r"encoding is 0 \(OFF\) / 1 \(ON\); pass polarity='signed'"):
            call()
    info = file_info(path, polarity="signed")
    assert info.on_count == 250 and info.on_fraction == pytest.approx(0.25)
    assert read_h5(path, polarity="signed").p.tolist() == (p > 0).astype(int).tolist()
    assert read(path, polarity="signed").p.sum() == 250


def test_other_polarity_values_are_refused_in_either_encoding(tmp_path):
    path = _dsec(tmp_path / "two.h5", np.arange(4, dtype=np.int64), p=np.array([0, 2, 0, 2], np.uint8))
    # values that fit neither encoding: no advice to pass the other one
    with pytest.raises(FormatError, match=r"polarity values \[0, 2\].*fit neither 0/1 nor -1/\+1"):
        file_info(path)
    with pytest.raises(FormatError, match=r"polarity values \[0, 2\].*fit neither 0/1 nor -1/\+1"):
        read_h5(path, polarity="signed")
    path = _dsec(tmp_path / "three.h5", np.arange(3, dtype=np.int64), p=np.array([-1, 0, 1], np.int8))
    with pytest.raises(FormatError, match=r"polarity values \[-1, 0, 1\].*fit neither"):
        read_h5(path, polarity="signed")
    # values that fit the other encoding: that one is named
    path = _dsec(tmp_path / "zero_one.h5", np.arange(2, dtype=np.int64), p=np.array([0, 1], np.int8))
    with pytest.raises(FormatError, match=r"pass polarity='01' \(cmax: --polarity 01\)"):
        read_h5(path, polarity="signed")
    with pytest.raises(ValueError, match=r"polarity must be one of \('01', 'signed'\)"):
        read_h5(path, polarity="pm1")


def test_text_files_state_their_polarity_and_unit(tmp_path):
    path = tmp_path / "events.txt"
    path.write_text("0.000001 1 2 -1\n0.000002 3 4 1\n")
    with pytest.raises(FormatError, match=r"column p holds the polarity values \[-1\.0, 1\.0\]"):
        read_txt(path, width=W, height=H)
    events = read_txt(path, width=W, height=H, polarity="signed")
    assert events.p.tolist() == [0, 1] and events.t.tolist() == [1, 2]
    path.write_text("1000 1 2 0\n2500 3 4 1\n")  # integer microseconds, not ECD's seconds
    assert read_txt(path, width=W, height=H, time_unit="us").t.tolist() == [1000, 2500]
    assert read(path, width=W, height=H, time_unit="us").t.tolist() == [1000, 2500]
    assert read_txt(path, width=W, height=H).t.tolist() == [1_000_000_000, 2_500_000_000]


def test_whole_number_text_times_since_1970_name_their_own_unit(tmp_path):
    """ECD text of integer milliseconds since 1970 (no unit) was refused as 'these look like integer microseconds.
    State the unit: time_unit='us'', and read so: a recording 1000 times too short; nanoseconds since 1970 were
    called microseconds too, then refused as float64 ('microseconds are already lost'). Now the unit whose
    reading lies in 1973-2103 is named; the times read in it (ns: converted as the message says)."""
    rng = np.random.default_rng(4)
    n = 200
    t_ms = 1504645177000 + np.sort(rng.choice(20_000, n, replace=False))      # 20 s of 2017, in ms
    columns = (rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(0, 2, n))
    path = tmp_path / "events.txt"

    def write(t) -> None:
        path.write_text("".join(f"{a} {b} {c} {d}\n" for a, b, c, d in zip(t, *columns)))

    write(t_ms)
    with pytest.raises(FormatError, match=r"these are milliseconds since 1970 \(1504645177\.\d+ s\)\. State the "
                                          r"unit: time_unit='ms'"):
        read_txt(path, width=W, height=H)
    assert read_txt(path, width=W, height=H, time_unit="ms").t.tolist() == (t_ms * 1000).tolist()
    write(t_ms * 1000)
    with pytest.raises(FormatError, match=r"these are microseconds since 1970 .* time_unit='us'"):
        read_txt(path, width=W, height=H)
    write(t_ms * 1_000_000 + 123)
    with pytest.raises(FormatError, match=r"these are nanoseconds since 1970 \(1504645177\.\d+ s\), a unit no reader "
                                          r"takes: .* integer microseconds \(t // 1000, then time_unit='us'"):
        read_txt(path, width=W, height=H)
    write((t_ms * 1_000_000 + 123) // 1000)
    assert read_txt(path, width=W, height=H, time_unit="us").t.tolist() == (t_ms * 1000).tolist()
    write(np.arange(957, 957 + n))                                      # a clock from boot: the unit is not told
    with pytest.raises(FormatError, match=r"these look like integer microseconds"):
        read_txt(path, width=W, height=H)


def test_mvsec_polarity_is_minus_one_plus_one_unless_stated(tmp_path):
    path = tmp_path / "mvsec.hdf5"
    table = np.array([[1, 2, 10.0, 0], [3, 4, 10.5, 1]])  # a 0/1 file in a -1/+1 format
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    with pytest.raises(FormatError, match=r"\(p\) holds the polarity values \[0\.0, 1\.0\], .* -1 \(OFF\) / \+1 "
                                          r"\(ON\); pass polarity='01'"):
        read_mvsec(path)
    events = read_mvsec(path, polarity="01")
    assert events.p.tolist() == [0, 1] and events.t.tolist() == [10_000_000, 10_500_000]
    assert read_mvsec(path, polarity="01", time_unit="ms").t.tolist() == [10_000, 10_500]


def test_npy_float_times_need_a_unit_and_signed_polarity_a_statement(tmp_path):
    array = np.zeros(3, [("x", "u2"), ("y", "u2"), ("t", "f8"), ("p", "i1")])
    array["t"], array["p"] = [0.5, 1.0, 1.5], [1, -1, 1]
    np.save(tmp_path / "ev.npy", array)
    with pytest.raises(FormatError, match=r"field t holds float64 times; state their unit"):
        read(tmp_path / "ev.npy", width=W, height=H)
    with pytest.raises(FormatError, match=r"field p holds the polarity values \[-1, 1\]"):
        read(tmp_path / "ev.npy", width=W, height=H, time_unit="s")
    events = read(tmp_path / "ev.npy", width=W, height=H, time_unit="s", polarity="signed")
    assert events.t.tolist() == [500_000, 1_000_000, 1_500_000] and events.p.tolist() == [1, 0, 1]


def test_npy_times_that_are_not_numbers_are_named_without_a_unit_too(tmp_path, capsys):
    """A structured .npy whose t field holds byte strings (a CSV loaded with np.genfromtxt(dtype=None)), read without a
    unit: `cmax info: error: invalid literal for int() with base 10: b''`, neither the file nor the field named
    (the implied-rate check cast them); now the FormatError every unit gave."""
    from cmax.cli import main
    from cmax.io import npy_time_span

    array = np.zeros(300, [("x", "u2"), ("y", "u2"), ("t", "S8"), ("p", "u1")])
    array["t"] = [f"{i * 1e-3:.5f}".encode() for i in range(300)]   # seconds, as the CSV wrote them
    np.save(tmp_path / "ev.npy", array)
    for unit in (None, "us", "s"):
        with pytest.raises(FormatError, match=r"ev.npy: field t must hold numbers \(times\), got dtype \|S8"):
            read(tmp_path / "ev.npy", width=W, height=H, time_unit=unit)
        with pytest.raises(FormatError, match=r"ev.npy: field t must hold numbers \(times\)"):
            npy_time_span(tmp_path / "ev.npy", time_unit=unit)
    assert main(["info", str(tmp_path / "ev.npy"), "--size", f"{W}x{H}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ev.npy: field t must hold numbers" in err, err


def test_formats_with_integer_microseconds_refuse_another_unit(tmp_path):
    from cmax.io import write_evt3

    events = Events([1, 2], [1, 2], [10, 20], [0, 1], W, H)
    write_evt3(tmp_path / "e.raw", events)
    assert read(tmp_path / "e.raw", time_unit="us") == events
    with pytest.raises(ValueError, match=r"stores integer microseconds; time_unit='s' does not apply"):
        read(tmp_path / "e.raw", time_unit="s")


# -- the writer's index against the event count -------------------------------------------
def test_one_time_stamp_off_by_2_to_40_us_is_refused_before_allocating_the_index(tmp_path):
    t = np.arange(14_000, dtype=np.int64) * 10
    t[-1] += 2**40  # one stamp ~12.7 days late: ms_to_idx would need 1.1e9 entries (8 GiB)
    events = Events(np.zeros(14_000, int), np.zeros(14_000, int), t, np.ones(14_000, int), W, H)
    peak = _refusal_peak(lambda: write_h5(tmp_path / "off.h5", events),
                         r"ms_to_idx would need 1,099,511,\d{3} entries \(8\.2 GiB\) for 14,000 events", ValueError)
    assert peak < 50_000_000, f"the refusal allocated {peak / 1e6:.0f} MB"
    assert not (tmp_path / "off.h5").exists()


def test_a_sparse_but_plausible_recording_is_written(tmp_path):
    from cmax.io.h5 import MIN_INDEX_ENTRIES

    # 5 events over 4 hours: within the index's floor of 2**24 ms whatever the count
    t = np.array([0, 1, 2, 3, (MIN_INDEX_ENTRIES - 10) * 1000], np.int64)
    events = Events(np.zeros(5, int), np.zeros(5, int), t, np.ones(5, int), W, H)
    path = write_h5(tmp_path / "sparse.h5", events)
    with H5Reader(path) as reader:
        assert reader.read() == events
        assert reader.window(int(t[-1]), int(t[-1]) + 1).t.tolist() == [int(t[-1])]


# -- the command line --------------------------------------------------------------------------
def test_cmax_info_refuses_float_times_in_one_line_and_reads_them_with_time_unit(tmp_path, capsys):
    from cmax.cli import main

    path = _dsec(tmp_path / "seconds.h5", np.linspace(0.0, 0.5, 50_000))
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--time-unit" in err and "float64 times" in err
    assert main(["info", str(path), "--time-unit", "s"]) == 0
    out = capsys.readouterr().out
    assert "duration    0.500000 s" in out and "rate        0.100 Mev/s" in out


def test_cmax_info_refuses_signed_polarity_in_one_line(tmp_path, capsys):
    from cmax.cli import main

    p = np.where(np.arange(100) % 2 == 0, 1, -1).astype(np.int8)
    path = _dsec(tmp_path / "signed.h5", np.arange(100, dtype=np.int64), p=p)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "polarity values [-1, 1]" in err


def test_cmax_show_and_fit_take_time_unit(tmp_path, capsys):
    from cmax.cli import build_parser, main

    rng = np.random.default_rng(3)
    path = _dsec(tmp_path / "seconds.h5", np.sort(rng.random(5000)) * 0.1)
    assert main(["show", str(path), "-o", str(tmp_path / "a.png")]) == 2
    assert "time_unit" in capsys.readouterr().err
    assert main(["show", str(path), "--time-unit", "s", "--dt", "0.05", "-o", str(tmp_path / "a.png")]) == 0
    assert (tmp_path / "a.png").stat().st_size > 0
    args = build_parser().parse_args(
        ["fit", str(path), "--K", "100,100,32,24", "-o", str(tmp_path), "--time-unit", "s"]
    )
    assert args.time_unit == "s"


def test_gyro_text_names_non_finite_samples_and_takes_a_unit(tmp_path):
    from cmax.io import read_gyro

    path = tmp_path / "gyro.txt"
    path.write_text("0.001 0 0 0\nnan 0 0 0\n")
    with pytest.raises(FormatError, match=r"gyro time\[1\] is nan, a non-finite time"):
        read_gyro(path)  # was -2**63 µs
    path.write_text("0.001 0 0 0\n0.002 0 inf 0\n")
    with pytest.raises(FormatError, match=r"gyro sample 1 has a non-finite angular velocity"):
        read_gyro(path)
    path.write_text("1000 0 0 1\n2000 0 0 1\n")
    times, omega = read_gyro(path, time_unit="us")
    assert times.tolist() == [1000, 2000] and omega[:, 2].tolist() == [1.0, 1.0]


def test_an_mvsec_file_declaring_rows_it_does_not_store_is_refused(tmp_path):
    path = tmp_path / "mvsec.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", shape=(200_000_000, 4), dtype="f8", chunks=(65536, 4))
    assert path.stat().st_size < 20_000
    with pytest.raises(FormatError, match=r"davis/left/events declares 800,000,000 entries .* stores only 0"):
        read_mvsec(path)
    with pytest.raises(FormatError, match=r"refusing to allocate"):
        file_info(path)


@pytest.mark.parametrize("row", [1, 65_535, 65_536, 65_537, 139_999])
def test_time_going_back_is_found_at_any_row_also_across_check_blocks(tmp_path, row):
    t = np.arange(140_000, dtype=np.int64) * 3
    t[row] = t[row - 1] - 1  # one step back at ``row``
    path = _dsec(tmp_path / "back.h5", t, t_offset=np.int64(10**12))
    with pytest.raises(FormatError, match=rf"corrupt events at row {row}: t must be sorted"):
        read_h5(path)
    with H5Reader(path) as reader:
        with pytest.raises(FormatError, match=rf"corrupt events at row {row}:"):
            reader.read_rows(row - 1, row + 1)
        assert reader.read_rows(row + 1, row + 3).t.tolist() == (10**12 + t[row + 1: row + 3]).tolist()


def test_the_h5_speed_benchmark_runs_on_a_small_file(tmp_path):
    from benchmarks import speed_h5

    path = speed_h5.make_file(tmp_path / "small.h5", 100_000)
    events = read_h5(path)
    assert len(events) == 100_000 and events.sensor_size == (speed_h5.WIDTH, speed_h5.HEIGHT)
    assert events.duration_us == pytest.approx(100_000 / speed_h5.RATE_HZ * 1e6, rel=0.01)
    text = speed_h5.run(100_000, 5, path)
    assert text.count("| whole file (read_h5) |") == 2 and text.count("| one 50 ms window") == 2


# -- cmax info checks every row, not only the first and last ----------------------------------
@pytest.mark.parametrize("defect, match", [
    ("nan", r"events/t\[10\] is nan, a non-finite time"),
    ("back", r"corrupt events at row 11: t must be sorted"),
    ("x", r"corrupt events at row 10: x must lie in \[0, width=64\)"),
])
def test_file_info_refuses_a_bad_row_in_the_middle_of_a_dsec_file(tmp_path, defect, match):
    t = np.linspace(0.0, 0.5, 50)  # float seconds, unit stated: first and last rows are fine
    x = np.zeros(50, np.uint16)
    if defect == "nan":
        t[10] = np.nan
    elif defect == "back":
        t[11] = t[9]
    else:
        x[10] = W
    path = _dsec(tmp_path / f"{defect}.h5", t, x=x)
    with pytest.raises(FormatError, match=match):
        read_h5(path, time_unit="s")
    with pytest.raises(FormatError, match=match):
        file_info(path, time_unit="s")


def test_file_info_checks_the_order_across_its_chunks(tmp_path, monkeypatch):
    import cmax.io.info as info

    monkeypatch.setattr(info, "_CHUNK", 8)
    t = np.arange(40, dtype=np.int64)
    t[16] = 3  # a step back exactly at a chunk boundary (rows 15 -> 16)
    path = _dsec(tmp_path / "boundary.h5", t)
    with pytest.raises(FormatError, match=r"row 16: t must be sorted"):
        file_info(path)
    good = _dsec(tmp_path / "good.h5", np.arange(40, dtype=np.int64))
    summary = file_info(good)
    assert (summary.count, summary.t_start_us, summary.t_end_us, summary.on_count) == (40, 0, 39, 20)


def test_uint32_times_of_an_h5_file_that_wrapped_are_named_as_a_wrapped_clock(tmp_path):
    """Was: `t must be sorted in non-decreasing order (4 µs comes after 4294967290 µs, before t_offset)` only,
    where the .npy and text readers name a uint32 microsecond clock that wrapped and how to unwrap it."""
    t = np.array([4294967000, 4294967290, 4, 300], np.uint32)
    path = _dsec(tmp_path / "wrapped.h5", t)
    with pytest.raises(FormatError, match=r"row 2: t must be sorted .*; a drop of 71\.6 min from near 2\*\*32 µs: "
                                          r"a uint32 microsecond clock that wrapped"):
        read(path)
    stepped_back = _dsec(tmp_path / "back.h5", np.array([10, 20, 5, 30], np.uint32))
    with pytest.raises(FormatError, match=r"\(5 µs comes after 20 µs, before t_offset\); DSEC-layout files are "):
        read(stepped_back)                                              # a step back is not a wrap


def test_a_dsec_layout_file_whose_time_goes_back_names_the_way_out(tmp_path, capsys):
    """A DSEC-layout h5 whose time goes back (a user's conversion of unsorted events) was refused as `corrupt
    events at row 2: t must be sorted ...` and `--sort` then as `sorting applies to ECD text, .npy and AEDAT4
    files`: a dead end. The refusal now says --sort does not apply and how to write a sorted copy; the copy
    written so reads, in time order, the same events."""
    from cmax.cli import main

    t = np.array([10, 20, 5, 30, 30, 25], np.int64)
    path = _dsec(tmp_path / "back.h5", t, file_attrs={"width": W, "height": H})
    with pytest.raises(FormatError, match=r"back.h5: events/t: corrupt events at row 2: .*--sort does not apply: "
                                          r"write a copy whose events/x, y, t, p are each reordered by "
                                          r"np.argsort\(t, kind='stable'\)"):
        read(path)
    assert main(["info", str(path)]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    with h5py.File(path, "r") as file:
        columns = {name: file[f"events/{name}"][:] for name in "xytp"}
    order = np.argsort(columns["t"], kind="stable")
    write_h5(tmp_path / "sorted.h5", Events(*(columns[name] for name in "xytp"), W, H, sort=True))
    copy = read(tmp_path / "sorted.h5")
    assert copy.t.tolist() == [5, 10, 20, 25, 30, 30]
    np.testing.assert_array_equal(copy.x, columns["x"][order])
    np.testing.assert_array_equal(copy.p, columns["p"][order])


def test_a_negative_or_whole_float_t_offset_of_no_stated_unit_is_refused(tmp_path):
    """DSEC ships t_offset as an int64 of µs, never negative. A negative one (an offset meant to be subtracted) and
    a whole float that seconds or milliseconds could equally mean (1600000000.0: 2020 as s since 1970, 26.7 min as
    µs) were read as µs without a word; a stated unit reads them, and µs-only values (0.0, 1.6e15) read as before."""
    t = np.array([0, 5, 9], np.uint32)
    negative = _dsec(tmp_path / "negative.h5", t, t_offset=np.int64(-5))
    with pytest.raises(FormatError, match=r"t_offset is -5, negative, and neither t_offset, the file nor the caller "
                                          r"states its unit: .* 'unit' attribute on t_offset"):
        read(negative)
    with h5py.File(negative, "r+") as file:
        file["t_offset"].attrs["unit"] = "us"
    assert read(negative).t.tolist() == [-5, 0, 4]                      # events/t + t_offset, as stated
    seconds = _dsec(tmp_path / "seconds.h5", t, t_offset=np.float64(1600000000.0))
    with pytest.raises(FormatError, match=r"t_offset holds the float 1600000000.0 .* read as µs it is "
                                          r"1,600.000000 s, read as seconds"):
        read(seconds)
    with pytest.raises(FormatError, match="t_offset holds the float"):
        file_info(seconds)
    assert read(seconds, time_unit="us").t.tolist() == [1600000000, 1600000005, 1600000009]   # the caller's unit
    with h5py.File(seconds, "r+") as file:
        file["t_offset"].attrs["unit"] = "s"
    assert read(seconds).t.tolist() == [1600000000000000, 1600000000000005, 1600000000000009]
    for whole in (0.0, 1600000000123456.0):                             # no other unit fits: µs as before
        path = _dsec(tmp_path / f"whole_{whole:.0f}.h5", t, t_offset=np.float64(whole))
        assert read(path).t.tolist() == (t.astype(np.int64) + int(whole)).tolist()
    # write_h5 states the unit of t_offset: events before the clock's zero round-trip
    events = Events([1, 2], [3, 4], [-20, -10], [0, 1], W, H)
    assert read(write_h5(tmp_path / "written.h5", events)) == events
