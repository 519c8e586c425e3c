"""ECD text, MVSEC HDF5, NumPy files and format detection."""
from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest

from cmax import Events
from cmax.io import FormatError, detect_format, read, read_mvsec, read_txt, write_txt
from conftest import random_events


def test_ecd_text_hand_written(tmp_path):
    path = tmp_path / "events.txt"
    path.write_text("0.000100000 10 20 1\n0.000150000 11 21 0\n1.5 0 0 1\n")
    ev = read(path, width=240, height=180)
    assert ev.t.tolist() == [100, 150, 1_500_000]
    assert ev.x.tolist() == [10, 11, 0] and ev.y.tolist() == [20, 21, 0] and ev.p.tolist() == [1, 0, 1]
    assert detect_format(path) == "txt"


def test_ecd_text_round_trip(tmp_path):
    ev = random_events(1000, width=240, height=180)
    assert read_txt(write_txt(tmp_path / "e.txt", ev), width=240, height=180) == ev


def test_an_empty_text_file_of_zero_events_reads_back_through_read(tmp_path, capsys):
    """Report userC item 5: write_txt of no events writes 0 bytes, which read() refused as an empty file."""
    from cmax.cli import main

    path = write_txt(tmp_path / "e.txt", Events.empty(240, 180))
    assert path.stat().st_size == 0 and detect_format(path) == "txt"
    events = read(path, width=240, height=180)
    assert events == Events.empty(240, 180) and events == read_txt(path, width=240, height=180)
    with pytest.raises(ValueError, match=r"e\.txt \(txt\) stores no sensor size: pass width= and height="):
        read(path)
    assert main(["info", str(path), "--size", "240x180"]) == 0
    out = capsys.readouterr().out
    assert "240 x 180" in out and "events      0" in out
    (tmp_path / "e.h5").write_bytes(b"")                         # any other empty file is still refused
    with pytest.raises(FormatError, match=r"e\.h5 is empty \(0 bytes\)"):
        read(tmp_path / "e.h5", width=240, height=180)


@pytest.mark.parametrize("writer", ["write_txt", "write_evt2", "write_evt3"])
def test_event_writers_refuse_an_existing_file_unless_told(tmp_path, writer):
    """They replaced an existing file silently (write_h5 refused): now FileExistsError, the file untouched,
    and overwrite=True replaces it; each returns the path written."""
    import cmax.io

    write = getattr(cmax.io, writer)
    path = tmp_path / ("e.txt" if writer == "write_txt" else "e.raw")
    path.write_bytes(b"earlier results")
    with pytest.raises(FileExistsError, match="pass overwrite=True"):
        write(path, random_events(50))
    assert path.read_bytes() == b"earlier results"
    events = random_events(50, seed=4)
    assert write(path, events, overwrite=True) == path
    assert read(path, **({"width": events.width, "height": events.height} if writer == "write_txt" else {})) == events
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def test_ecd_text_errors(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("0.1 1 2\n0.2 1 2\n")
    with pytest.raises(FormatError, match="4 columns"):
        read_txt(path, width=240, height=180)
    path.write_text("0.1 1 2 1\nabc 1 2 1\n")
    with pytest.raises(FormatError):
        read_txt(path, width=240, height=180)
    path.write_text("0.2 1 2 1\n0.1 1 2 1\n")
    with pytest.raises(FormatError, match="sorted"):
        read_txt(path, width=240, height=180)
    with pytest.raises(ValueError, match="width= and height="):
        read(path)


def _write_mvsec(path, table):
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
        file.create_dataset("davis/left/image_raw", data=np.zeros((1, 260, 346), np.uint8))


def test_mvsec_layout(tmp_path):
    ev = random_events(4000, width=346, height=260, t_span_us=500_000)
    t0 = 1_504_645_177_000_000  # MVSEC stores seconds since the epoch
    table = np.column_stack([ev.x, ev.y, (ev.t + t0) / 1e6, ev.signed_polarity(np.float64)])
    _write_mvsec(tmp_path / "flying.hdf5", table)
    assert detect_format(tmp_path / "flying.hdf5") == "mvsec"
    back = read(tmp_path / "flying.hdf5")
    shifted = Events(ev.x, ev.y, ev.t + t0, ev.p, 346, 260)
    assert back == shifted
    window = read_mvsec(tmp_path / "flying.hdf5", t0_us=t0 + 100_000, t1_us=t0 + 200_000)
    assert window == shifted.slice_time(t0 + 100_000, t0 + 200_000)
    with pytest.raises(ValueError, match="camera"):
        read_mvsec(tmp_path / "flying.hdf5", camera="middle")
    with pytest.raises(FormatError, match="davis/right/events"):
        read_mvsec(tmp_path / "flying.hdf5", camera="right")


def test_structured_npy(tmp_path):
    ev = random_events(500)
    np.save(tmp_path / "ev.npy", ev.to_structured())
    assert read(tmp_path / "ev.npy", width=ev.width, height=ev.height) == ev
    np.save(tmp_path / "plain.npy", np.zeros((3, 4)))
    with pytest.raises(FormatError, match="structured"):
        read(tmp_path / "plain.npy", width=4, height=4)


def test_unknown_format(tmp_path):
    (tmp_path / "x.bin").write_bytes(b"\x00\x01garbage")
    with pytest.raises(FormatError, match="cannot tell"):
        read(tmp_path / "x.bin")
    with pytest.raises(FileNotFoundError):
        read(tmp_path / "missing.h5")


def test_an_npz_of_separate_arrays_is_refused_with_the_conversion_that_reads_it(tmp_path):
    """An ``np.savez`` of x, y, t, p arrays (the ESIM reference of rpg_vid2e, many tonic and numpy dumps) was
    refused as an unknown format with no way on; the refusal now gives the conversion, and following it reads the
    same events (float seconds stated as such)."""
    events = random_events(500, 64, 48, seed=1)
    np.savez(tmp_path / "dump.npz", x=events.x, y=events.y, t=events.t * 1e-6, p=events.signed_polarity())
    with pytest.raises(FormatError, match=r"an \.npz of separate arrays is not read: build cmax\.Events\(x, y, t, p, "
                                          r"width, height\) from them \(time_unit='s' for float seconds\) and "
                                          r"np\.save\('events\.npy', events\.to_structured\(\)\)"):
        read(tmp_path / "dump.npz")
    arrays = np.load(tmp_path / "dump.npz")
    converted = Events(arrays["x"], arrays["y"], arrays["t"], arrays["p"], 64, 48, time_unit="s")
    np.save(tmp_path / "events.npy", converted.to_structured())
    assert read(tmp_path / "events.npy", width=64, height=48) == events
    (tmp_path / "other.bin").write_bytes(b"PK\x03\x04" + bytes(12))    # a zip not named .npz: no such advice
    with pytest.raises(FormatError) as error:
        read(tmp_path / "other.bin")
    assert ".npz" not in str(error.value)


def test_time_window_on_formats_without_index(tmp_path):
    ev = random_events(800, width=240, height=180)
    write_txt(tmp_path / "e.txt", ev)
    assert read(tmp_path / "e.txt", width=240, height=180, t0_us=20_000, t1_us=40_000) == ev.slice_time(20_000, 40_000)


def test_a_file_whose_time_goes_back_is_sorted_when_asked(tmp_path, capsys):
    """The refusal said "pass sort=True", but cmax.io.read(..., sort=True) raised TypeError for text and .npy files
    and the command line had no such option. Now read(sort=True) and --sort sort text, .npy and AEDAT4 files (read
    whole); a file read by time span from disk (DSEC h5, Prophesee RAW) is refused, saying why."""
    from cmax.cli import main
    from cmax.io import write_h5

    events = random_events(300, width=64, height=48)
    order = np.random.default_rng(2).permutation(len(events))
    text = tmp_path / "shuffled.txt"
    text.write_text("".join(f"{t * 1e-6:.6f} {x} {y} {p}\n" for t, x, y, p in
                            zip(events.t[order], events.x[order], events.y[order], events.p[order])))
    npy = tmp_path / "shuffled.npy"
    np.save(npy, events.to_structured()[order])
    for path in (text, npy):
        with pytest.raises(FormatError, match=r"t must be sorted .*pass sort=True .*cmax: --sort"):
            read(path, width=64, height=48)
        back = read(path, width=64, height=48, sort=True)
        assert np.array_equal(back.t, events.t) and sorted(zip(back.t, back.x, back.y, back.p)) == sorted(
            zip(events.t, events.x, events.y, events.p))
    assert main(["info", str(text), "--size", "64x48", "--sort"]) == 0
    assert "events      300\n" in capsys.readouterr().out
    h5 = write_h5(tmp_path / "e.h5", events)
    with pytest.raises(ValueError, match=r"e.h5 \(dsec\) is read a time span at a time from disk"):
        read(h5, sort=True)
    assert main(["info", str(h5), "--sort"]) == 2
    assert "sorting applies to ECD text, .npy and AEDAT4 files" in capsys.readouterr().err
    with pytest.raises(TypeError, match="sort must be True or False"):
        read(text, width=64, height=48, sort="yes")
    from learned.predict import open_recording          # `cmax depth --sort` takes the same path

    recording = open_recording(text, size=(64, 48), sort=True)
    assert (recording.first_us, recording.last_us) == (int(events.t[0]), int(events.t[-1]))
    with pytest.raises(ValueError, match="sorting applies to ECD text"):
        open_recording(h5, sort=True)


def test_rpg_e2vid_text_states_its_size_on_its_first_line(tmp_path):
    """rpg_e2vid's events.txt: a 'W H' line, then 't x y p' (was: numpy's "use `usecols`" advice, and the size
    asked for although the file states it). Read with its size; a contradicting size refused; a file in 'x y t p'
    order is named as such (was: a bare "t must be sorted")."""
    events = random_events(200, width=64, height=48)
    lines = "".join(f"{t * 1e-6:.6f} {x} {y} {p}\n" for t, x, y, p in zip(events.t, events.x, events.y, events.p))
    path = tmp_path / "events.txt"
    path.write_text("64 48\n" + lines)
    assert read(path) == events and read(path, width=64, height=48) == events
    with pytest.raises(ValueError, match=r"width=240, height=180 contradicts the 64x48 sensor that .*its first line"):
        read(path, width=240, height=180)
    (tmp_path / "ragged.txt").write_text("0.1 1 2 1\n0.2 1 2\n")
    with pytest.raises(FormatError) as error:
        read(tmp_path / "ragged.txt", width=64, height=48)
    assert "usecols" not in str(error.value)
    swapped = tmp_path / "xytp.txt"
    swapped.write_text("".join(f"{x} {y} {t} {p}\n" for t, x, y, p in zip(events.t, events.x, events.y, events.p)))
    for sort in (False, True):           # sorting by the x column would not mend the order
        with pytest.raises(FormatError, match=r"the columns look like 'x y t p', but ECD text is 't x y p'"):
            read(swapped, width=64, height=48, sort=sort)
    with pytest.raises(ValueError, match=r"stores no sensor size: pass width= and height= \(cmax: --size WxH\)"):
        read(tmp_path / "ragged.txt")


@pytest.mark.parametrize("ends", [["\r"], ["\r\n"], ["\n", "\r"], ["\r\n", "\n", "\r"]],
                         ids=["cr", "crlf", "lf-then-cr", "mixed"])
@pytest.mark.parametrize("header", ["", "64 48", "# t x y p"])
def test_text_lines_ending_in_cr_alone_crlf_or_a_mix_read_as_the_events_written(tmp_path, ends, header):
    """ECD text saved by an old Mac editor ends its lines in CR alone (was: refused, "its first line reads '0.000000 0
    0 0 0.001000 1 ...' (800 column(s) where 4 columns are expected)", although np.loadtxt reads such lines; with
    rpg_e2vid's 'W H' line first, the size line was not found either). Each line end, and a mix of them, reads as
    the events written."""
    events = random_events(300, width=64, height=48)
    lines = [f"{t * 1e-6:.6f} {x} {y} {p}" for t, x, y, p in zip(events.t, events.x, events.y, events.p)]
    lines = ([header] if header else []) + lines
    text = "".join(line + ends[i * len(ends) // len(lines)] for i, line in enumerate(lines))
    path = tmp_path / "events.txt"
    path.write_bytes(text.encode())
    size = {} if header == "64 48" else {"width": 64, "height": 48}
    assert read(path, **size) == events


@pytest.mark.parametrize("codec, bom", [("utf-16-le", b"\xff\xfe"), ("utf-16-be", b"\xfe\xff")])
def test_utf16_text_with_its_byte_order_mark_reads_as_the_events_written(tmp_path, codec, bom):
    """Windows PowerShell's ``>`` writes UTF-16 with a byte order mark (was: refused, "its first line reads
    '\ufffd\ufffd0\\x00.\\x000...': ... is not a number (a header line? ...)"). Read as the same text, also past the
    64 KiB the first-line check reads and with rpg_e2vid's size line; without the mark it is refused naming the NUL
    bytes."""
    events = random_events(3000, width=64, height=48)
    text = "64 48\r\n" + "".join(f"{t * 1e-6:.6f} {x} {y} {p}\r\n"
                                   for t, x, y, p in zip(events.t, events.x, events.y, events.p))
    path = tmp_path / "events.txt"
    path.write_bytes(bom + text.encode(codec))
    assert path.stat().st_size > 1 << 16
    assert read(path) == events
    path.write_bytes(text.encode(codec))
    with pytest.raises(FormatError, match=r"events.txt is not an ECD text file .*which holds NUL bytes: UTF-16 text "
                                          r"without a byte order mark"):
        read(path, width=64, height=48)


def test_a_comment_in_latin_1_is_a_comment_and_a_byte_in_a_number_is_refused_naming_its_row(tmp_path):
    """A comment line saved in Latin-1 (``# caméra``: byte 0xe9, not UTF-8) made the whole file unreadable (was:
    "('utf-8' codec can't decode byte 0xe9 in position 5: invalid continuation byte)", no line named). The comment
    is skipped; such a byte inside a number is still refused, naming the row."""
    events = random_events(100, width=64, height=48)
    lines = [f"{t * 1e-6:.6f} {x} {y} {p}\n" for t, x, y, p in zip(events.t, events.x, events.y, events.p)]
    path = tmp_path / "events.txt"
    path.write_bytes("# caméra DAVIS240\n".encode("latin-1") + "".join(lines).encode())
    assert read(path, width=64, height=48) == events
    path.write_bytes("".join(lines[:10]).encode() + lines[10].replace(" ", "\xe9 ", 1).encode("latin-1")
                     + "".join(lines[11:]).encode())
    with pytest.raises(FormatError, match=r"events.txt is not an ECD text file .*at row 10, column 1"):
        read(path, width=64, height=48)


@pytest.mark.parametrize("text, columns", [
    ("0.000000000 images/frame_00000000.png\n0.038766001 images/frame_00000001.png\n", 2),   # ECD images.txt
    ("# timestamps\n0.000000000\n0.001866000\n", 1),                                       # ESIM timestamps.txt
    ("335.4 335.3 129.9 99.2 -0.13 0.06 0 0 0\n", 9),                                      # ECD calib.txt
    ("0.0223 0.1117 0.0 0.0 0.0 0.0 0.0 1.0\n", 8),                                        # a TUM trajectory
])
def test_a_text_file_that_holds_no_events_is_named_so_before_a_size_is_asked(tmp_path, capsys, text, columns):
    """Was: `cmax info images.txt` said "stores no sensor size: pass --size WxH"; given a size, it said the file is
    not an event file. The first line that is not a comment is checked first: the error says what the file is."""
    from cmax.cli import main

    path = tmp_path / "frames.txt"
    path.write_text(text)
    with pytest.raises(FormatError, match=rf"is not an ECD text file of 't x y p' lines: its first line reads .* "
                                          rf"\({columns} column\(s\) where 4 columns are expected\)"):
        read(path)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "stores no sensor size" not in err and "its first line reads" in err
    assert ("cmax simulate FOLDER" in err) == (columns <= 2)


EVENT_LINES = "".join(f"{0.001 * i:.9f} {i % 64} {i % 48} {i % 2}\n" for i in range(1, 151))


@pytest.mark.parametrize("text, said", [
    ("x y t p\n" + EVENT_LINES, r"its first line reads 'x y t p': 'x' is not a number \(a header line\?"),
    (EVENT_LINES.replace(" ", ","), r"its first line reads '0.001000000,1,1,1', its fields separated by ',' \(a CSV\)"),
    ("t,x,y,p\n" + EVENT_LINES.replace(" ", ","), r"its fields separated by ',' \(a CSV\), .* 'x,y,p,t'"),
    (EVENT_LINES.replace(" ", ", "), r"reads '0.001000000, 1, 1, 1', its fields separated by ','"),
    (EVENT_LINES.replace(" ", ";"), r"its fields separated by ';' \(a CSV\)"),
])
def test_a_header_or_a_csv_is_refused_naming_what_its_first_line_holds(tmp_path, capsys, text, said):
    """A header line ('x y t p') or comma-separated fields were refused with '(4 column(s) where 4 columns are
    expected)' or '(1 column(s) ...); a list of frames ... becomes events with cmax simulate': a message that
    contradicts itself or points elsewhere. Now the line is named for what it holds (a CSV's column order is not
    guessed: Metavision writes x,y,p,t)."""
    from cmax.cli import main

    path = tmp_path / "events.csv"
    path.write_text(text)
    with pytest.raises(FormatError, match=said) as refused:
        read(path, width=64, height=48)
    assert "columns are expected" not in str(refused.value) and "cmax simulate" not in str(refused.value)
    assert main(["info", str(path), "--size", "64x48"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "its first line reads" in err, err


def test_a_byte_order_mark_before_the_events_changes_nothing(tmp_path):
    """ECD text saved by a Windows editor starts with a UTF-8 byte order mark (was: refused, 'its first line reads
    '\\ufeff0.001000000 1 1 1''); it reads as the same file without it, an rpg_e2vid size line too."""
    plain, marked = tmp_path / "plain.txt", tmp_path / "marked.txt"
    plain.write_text(EVENT_LINES)
    marked.write_bytes(b"\xef\xbb\xbf" + EVENT_LINES.encode())
    expected = read(plain, width=64, height=48)
    assert read(marked, width=64, height=48) == expected and len(expected) == 150
    marked.write_bytes(b"\xef\xbb\xbf64 48\n" + EVENT_LINES.encode())
    assert read(marked) == expected


def test_a_window_of_a_npy_reads_only_its_rows(tmp_path):
    """read(..., t0_us=, t1_us=) and cmax show of a structured .npy loaded every row, then cut: 584 MB and 5.1 s for
    50 ms of a 20 M-event file. The window's rows are found by a binary search of the memory-mapped times; the
    events equal those of the whole file cut to the window, for integer µs and for float seconds."""
    import tracemalloc

    from cmax.show import read_window

    rng = np.random.default_rng(3)
    n = 1_000_000
    table = np.zeros(n, dtype=[("x", "<u2"), ("y", "<u2"), ("t", "<i8"), ("p", "u1")])
    table["x"], table["y"], table["p"] = rng.integers(0, 64, n), rng.integers(0, 48, n), rng.integers(0, 2, n)
    table["t"] = 7_000 + np.sort(rng.integers(0, 10_000_000, n))
    np.save(tmp_path / "us.npy", table)
    seconds = np.zeros(n, dtype=[("t", "<f8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    for name in "xyp":
        seconds[name] = table[name]
    seconds["t"] = table["t"] * 1e-6
    np.save(tmp_path / "s.npy", seconds)
    for name, unit in (("us.npy", None), ("s.npy", "s")):
        whole = read(tmp_path / name, width=64, height=48, time_unit=unit)
        for t0, t1 in ((2_000_000, 2_050_000), (0, 7_001), (9_999_000, 2**40), (5_000_000, 5_000_000)):
            tracemalloc.start()
            try:
                window = read(tmp_path / name, width=64, height=48, time_unit=unit, t0_us=t0, t1_us=t1)
                peak = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
            assert window == whole.slice_time(t0, t1), (name, t0, t1)
            assert peak < 4e6 or t1 - t0 > 1e6, (name, t0, t1, peak)    # the whole t column alone: 8 MB
        shown, _ = read_window(tmp_path / name, 3.0, 0.05, width=64, height=48, time_unit=unit)
        start = int(whole.t[0]) + 3_000_000
        assert shown == whole.slice_time(start, start + 50_000)


def _evt3_going_back(path, t_us: np.ndarray, x: np.ndarray, y: np.ndarray, p: np.ndarray) -> None:
    """An EVT 3.0 file (64x48) with one TIME_HIGH/TIME_LOW/ADDR_Y/ADDR_X group per event, in the given order."""
    words, high = [], -1
    for t, xi, yi, pi in zip(t_us.tolist(), x.tolist(), y.tolist(), p.tolist()):
        if t >> 12 != high:
            high = t >> 12
            words.append((0x8 << 12) | (high & 0xFFF))
        words += [(0x6 << 12) | (t & 0xFFF), yi, (0x2 << 12) | (pi << 11) | xi]
    path.write_bytes(b"% evt 3.0\n% format EVT3;height=48;width=64\n% end\n" + np.array(words, "<u2").tobytes())


def test_a_raw_file_whose_time_goes_back_a_few_us_has_a_way_out(tmp_path, capsys, monkeypatch):
    """A RAW recording with events a few µs out of order: the decoder says 'pass sort=True', the command line's
    --sort is refused for RAW files (read a span at a time) and was a dead end; the refusal now gives the line
    that sorts it once into a copy, and that copy reads with every event, in time order."""
    from cmax.cli import main

    rng = np.random.default_rng(3)
    t = np.sort(rng.integers(0, 20_000, 300))
    back = rng.choice(np.arange(1, 300), 5, replace=False)
    t[back] = np.maximum(t[back - 1] - 3, 0)                              # 3 µs before the event before it
    x, y, p = rng.integers(0, 64, 300), rng.integers(0, 48, 300), rng.integers(0, 2, 300)
    _evt3_going_back(tmp_path / "rec.raw", t, x, y, p)
    monkeypatch.chdir(tmp_path)
    assert main(["info", "rec.raw"]) == 2
    first = capsys.readouterr().err           # the first refusal gives the way through too (was: 'pass sort=True'
    assert "time goes back" in first and "--sort does not apply to RAW files" in first   # alone, then --sort refused)
    assert first.count("\n") == 1 and "io.read_raw('rec.raw', sort=True)" in first
    assert main(["info", "rec.raw", "--sort"]) == 2
    err = capsys.readouterr().err
    assert "sorting applies to ECD text, .npy and AEDAT4 files" in err
    code = err.split('python -c "', 1)[1].rsplit('"', 1)[0]
    exec(code, {})
    assert main(["info", "sorted.raw"]) == 0
    assert "events      300\n" in capsys.readouterr().out
    copy = read(tmp_path / "sorted.raw")
    assert copy.t.tolist() == sorted(t.tolist())
    assert sorted(zip(copy.t, copy.x, copy.y, copy.p)) == sorted(zip(t, x, y, p))


def test_an_mvsec_file_whose_time_goes_back_has_a_way_out(tmp_path, capsys, monkeypatch):
    """An MVSEC file whose rows go back in time: the refusal said '(pass sort=True ...; cmax: --sort)', and --sort
    was then refused for MVSEC files (read a time span at a time): a dead end. It names the rows and the line that
    writes a sorted copy, which reads with every event in time order."""
    import h5py

    from cmax.cli import main

    rng = np.random.default_rng(6)
    t = 1.5e9 + np.round(rng.random(300), 6)
    table = np.stack([rng.integers(0, 346, 300), rng.integers(0, 260, 300), t, rng.choice([-1.0, 1.0], 300)], 1)
    monkeypatch.chdir(tmp_path)
    with h5py.File("rig.hdf5", "w") as file:
        file.create_dataset("davis/left/events", data=table)
    assert main(["info", "rig.hdf5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the time goes back from" in err and "--sort does not apply" in err, err
    assert "cmax: --sort" not in err
    exec(err.split('python -c "', 1)[1].rsplit('"', 1)[0], {})
    copy = read(tmp_path / "sorted.hdf5")
    assert len(copy) == 300 and np.all(np.diff(copy.t) >= 0)
    assert sorted(zip(copy.x.tolist(), copy.y.tolist())) == sorted(zip(table[:, 0].tolist(), table[:, 1].tolist()))


def test_an_npz_archive_or_an_n_by_4_npy_is_refused_naming_the_call_that_reads_it(tmp_path):
    """tonic events saved with np.savez (an .npz archive) were refused as "cannot tell the event format ...", an
    (N, 4) .npy table as "expected a 1-D structured array ..." only. Both now name the call that reads them, and that
    call reads the events written."""
    events = random_events(300, width=64, height=48)
    archive = tmp_path / "ev.npz"
    np.savez(archive, events=events.to_structured())
    with pytest.raises(FormatError, match=r"ev.npz is a NumPy .npz archive of the arrays \['events'\], not one event "
                                          r"array: .*cmax.Events.from_structured\(np.load\('.*ev.npz'\)\['events'\], "
                                          r"width, height\)"):
        read(archive, width=64, height=48)
    assert Events.from_structured(np.load(archive)["events"], 64, 48) == events
    table = tmp_path / "table.npy"
    np.save(table, np.column_stack([events.x, events.y, events.t, events.p]).astype(np.int64))
    with pytest.raises(FormatError, match=r"table.npy: expected a 1-D structured array .* shape \(300, 4\): an "
                                          r"\(N, 4\) table, .*cmax.Events.from_array\(np.load\('.*table.npy'\), "
                                          r"width, height, order='xytp'\)"):
        read(table, width=64, height=48)
    assert Events.from_array(np.load(table), 64, 48, order="xytp") == events
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 cut")
    with pytest.raises(FormatError, match=r"bad.npz is not a readable .npz archive \(BadZipFile"):
        read(tmp_path / "bad.npz")


def test_an_h5_holding_events_in_two_layouts_says_which_it_read(tmp_path, capsys):
    """A DSEC-layout file that also holds MVSEC's davis/left/events (or Metavision's CD/events, event_utils'
    events/xs, ys, ts, ps) was read as DSEC without a word about the other events, as an AEDAT4 file of two
    event streams was before it warned. The DSEC events are read, and the other layout is named."""
    from cmax.cli import main
    from cmax.io import write_h5

    events = Events([1, 2, 3], [1, 2, 3], [10, 20, 30], [0, 1, 1], 346, 260)
    mvsec_rows = np.array([[5.0, 6.0, 1.5e9 + 1e-4 * k, 1.0] for k in range(7)])
    path = write_h5(tmp_path / "both.h5", events)
    with h5py.File(path, "r+") as file:
        file.create_group("davis/left")["events"] = mvsec_rows
    with pytest.warns(UserWarning, match=r"both.h5 holds events in another layout too: davis/left/events \(MVSEC, "
                                         r"7 rows\), which is not read: .*cmax.io.read_mvsec"):
        got = read(path)
    assert got == events                                            # the DSEC events, as before
    assert len(read_mvsec(path)) == 7                               # the way to the others
    assert main(["info", str(path)]) == 0
    assert "davis/left/events (MVSEC, 7 rows)" in capsys.readouterr().err
    alone = write_h5(tmp_path / "alone.h5", events)                 # one layout: silent
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read(alone) == events
    with h5py.File(alone, "r+") as file:
        file.create_group("CD")["events"] = np.zeros(3)
        for name in ("xs", "ys", "ts", "ps"):
            file["events"][name] = np.zeros(3)
    with pytest.warns(UserWarning, match=r"CD/events \(Metavision\).* events/xs, ys, ts, ps \(event_utils / E2VID"):
        read(alone)


def test_a_npy_holding_bytes_after_its_declared_rows_is_refused(tmp_path):
    """A .npy whose events were appended after np.save without its header's shape being updated (an interrupted
    npy-append-array, a logger writing records after the header) was read as the header's rows, the rest dropped
    without a word (np.load ignores trailing bytes). np.save writes none."""
    from cmax.cli import main

    events = random_events(100, 64, 48, seed=3)
    array = events.to_structured()
    path = tmp_path / "appended.npy"
    np.save(path, array[:60])
    with open(path, "ab") as file:                              # 40 more rows, the header still says 60
        file.write(array[60:].tobytes())
    with pytest.raises(FormatError, match=r"appended.npy: 40 rows \([0-9,]+ bytes\) follow the 60 rows its header "
                                          r"declares: .*np.fromfile"):
        read(path, width=64, height=48)
    assert main(["info", str(path), "--size", "64x48"]) == 2
    # the way out the message gives reads every row
    header = path.stat().st_size - 100 * array.dtype.itemsize
    whole = np.fromfile(path, dtype=array.dtype, offset=header)
    np.save(tmp_path / "fixed.npy", whole)
    assert read(tmp_path / "fixed.npy", width=64, height=48) == events
    with open(path, "ab") as file:                              # and part of a row: not whole rows
        file.write(b"\0" * 3)
    with pytest.raises(FormatError, match=r"[0-9,]+ bytes follow the 60 rows its header declares \(rows of "):
        read(path, width=64, height=48)
    empty = tmp_path / "empty.npy"
    np.save(empty, array[:0])
    with open(empty, "ab") as file:
        file.write(array[:5].tobytes())
    with pytest.raises(FormatError, match=r"empty.npy: 5 rows .* follow the 0 rows its header declares"):
        read(empty, width=64, height=48)
    # cut short mid-row (was: "is not a readable .npy file (mmap length is greater than file size)")
    cut = tmp_path / "cut.npy"
    np.save(cut, array)
    cut.write_bytes(cut.read_bytes()[:-7])
    with pytest.raises(FormatError, match=rf"cut.npy: its header declares 100 rows of {array.dtype.itemsize} bytes "
                                          r"\([0-9,]+ bytes of data\), but the file holds [0-9,]+, 99 whole rows: cut "
                                          "short"):
        read(cut, width=64, height=48)


@pytest.mark.parametrize("suffix", [".h5", ".npy", ".txt"])
def test_an_option_the_format_does_not_take_is_refused_naming_file_format_and_its_options(tmp_path, suffix):
    """``read(dsec.h5, camera='left')`` raised Python's ``read_h5() got an unexpected keyword argument 'camera'``:
    neither the file nor the format. Now one line naming both and the options that format does take."""
    from cmax.io import write_h5

    ev = random_events(300)
    path = tmp_path / f"ev{suffix}"
    {".h5": lambda: write_h5(path, ev), ".npy": lambda: np.save(path, ev.to_structured()),
     ".txt": lambda: write_txt(path, ev)}[suffix]()
    named = {".h5": "DSEC HDF5", ".npy": "NumPy .npy", ".txt": "ECD text"}[suffix]
    with pytest.raises(TypeError) as refused:
        read(path, width=ev.width, height=ev.height, camera="left", stream=0)
    message = str(refused.value)
    assert "\n" not in message and str(path) in message and named in message, message
    assert "camera=, stream=" in message and "takes polarity=" in message, message   # what the format does take
    assert read(path, width=ev.width, height=ev.height, polarity="01") == ev           # an option it takes: read


def test_mvsec_takes_its_camera_and_refuses_what_it_does_not_take(tmp_path):
    ev = random_events(300, width=346, height=260)
    _write_mvsec(tmp_path / "m.hdf5", np.column_stack([ev.x, ev.y, ev.t / 1e6, ev.signed_polarity(np.float64)]))
    assert len(read(tmp_path / "m.hdf5", camera="left")) == len(ev)
    with pytest.raises(TypeError, match=r"m\.hdf5 is MVSEC HDF5, whose reader takes no stream=: it takes camera=, "
                                        r"polarity="):
        read(tmp_path / "m.hdf5", stream=0)
