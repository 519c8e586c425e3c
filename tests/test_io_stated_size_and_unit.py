"""A caller's sensor size or time unit never overrides what a file states: equal is accepted, different refused.

``cmax.io.read(path, width=, height=)`` (CLI ``--size``) is for files that store no size; ``time_unit`` (CLI
``--time-unit``) for files that leave the unit open. Files written by :class:`cmax.io.H5Writer` state µs.
"""
from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from cmax.cli import main
from cmax.events import Events
from cmax.io import FormatError, H5Reader, read, read_evt2, read_evt3, read_h5, write_evt2, write_evt3, write_h5
from conftest import random_events

W, H = 64, 48
CONTRADICTS = r"width={}, height={} contradicts the 64x48 sensor that .*{} states; leave the size out"


@pytest.fixture
def events() -> Events:
    return random_events(500, width=W, height=H, t_span_us=50_000)


def _refused(call, width: int, height: int, name: str) -> None:
    """``call`` raises a plain ValueError (the caller's mistake, not a corrupt file) naming both sizes."""
    with pytest.raises(ValueError, match=CONTRADICTS.format(width, height, name)) as error:
        call()
    assert not isinstance(error.value, FormatError)
    assert "corrupt" not in str(error.value) and "\n" not in str(error.value)


# -- sensor size ----------------------------------------------------------------------
@pytest.mark.parametrize("width, height", [(128, 96), (32, 24), (64, 49)])
def test_h5_refuses_a_size_other_than_its_own(tmp_path: Path, events: Events, width: int, height: int) -> None:
    path = write_h5(tmp_path / "ev.h5", events)
    _refused(lambda: read(path, width=width, height=height), width, height, "ev.h5")
    _refused(lambda: read_h5(path, width=width, height=height, t0_us=0, t1_us=10_000), width, height, "ev.h5")
    _refused(lambda: H5Reader(path, width=width, height=height), width, height, "ev.h5")


def test_h5_accepts_its_own_size_and_a_size_where_it_states_none(tmp_path: Path, events: Events) -> None:
    path = write_h5(tmp_path / "ev.h5", events)
    assert read(path, width=W, height=H) == events
    with pytest.raises(ValueError, match="give both width and height"):
        read(path, width=W)
    with h5py.File(path, "a") as file:
        del file.attrs["width"], file.attrs["height"]
    assert read(path, width=W, height=H) == events
    assert read(path, width=100, height=90).sensor_size == (100, 90)


@pytest.mark.parametrize("kept", ["width", "height"])
def test_h5_stating_half_a_size_binds_that_half(tmp_path: Path, events: Events, kept: str) -> None:
    """An h5 file with a width attribute and no height (or the other way round) was read with any caller's size,
    the stated half ignored without a word (128x48 for a file stating width 64), and refused as one that
    "stores no sensor size" without one."""
    path = write_h5(tmp_path / "half.h5", events)
    with h5py.File(path, "a") as file:
        del file.attrs["height" if kept == "width" else "width"]
    missing = "height" if kept == "width" else "width"
    value = W if kept == "width" else H
    wrong = (128, H) if kept == "width" else (W, 40)
    with pytest.raises(ValueError, match=rf"width={wrong[0]}, height={wrong[1]} contradicts the {kept} {value} "
                                         rf"that .*half.h5 states; give {kept}={value} \(the file states no {missing}\)"
                       ) as error:
        read(path, width=wrong[0], height=wrong[1])
    assert not isinstance(error.value, FormatError)
    with pytest.raises(FormatError, match=rf"half.h5 states its sensor's {kept} \({value}\) but not its {missing}; "
                                          r"pass width= and height="):
        read(path)
    assert read(path, width=W, height=H) == events


@pytest.mark.parametrize("fmt", ["evt3", "evt2"])
def test_raw_refuses_a_size_other_than_its_header(tmp_path: Path, events: Events, fmt: str) -> None:
    writer, reader = {"evt3": (write_evt3, read_evt3), "evt2": (write_evt2, read_evt2)}[fmt]
    path = tmp_path / f"ev.{fmt}.raw"
    writer(path, events)
    _refused(lambda: read(path, width=128, height=96), 128, 96, f"ev.{fmt}.raw")
    _refused(lambda: reader(path, width=2000, height=2000), 2000, 2000, f"ev.{fmt}.raw")
    assert read(path, width=W, height=H) == events
    assert reader(path) == events


def test_raw_takes_the_callers_size_over_one_its_plugin_name_implies(tmp_path: Path) -> None:
    """A size implied by ``plugin_name`` is a guess, not stated: the caller's replaces it (it refused 2000x2000)."""
    path = tmp_path / "gen4.raw"
    path.write_bytes(b"% evt 3.0\n% plugin_name hal_plugin_gen41_evk3\n% end\n"
                     + np.array([0x8000, 0x6000, 0x0001, 0x2002], "<u2").tobytes())
    assert read(path).sensor_size == (1280, 720)
    assert read(path, width=2000, height=2000).sensor_size == (2000, 2000)
    assert read(path, width=1280, height=720).sensor_size == (1280, 720)


def _expelliarmus_like(tmp_path: Path, events: Events) -> Path:
    """``events`` as EVT2 under the header expelliarmus (tonic's decoder) writes for every file it saves."""
    data = write_evt2(tmp_path / "plain.raw", events).read_bytes().split(b"% end\n", 1)[1]
    header = (b"% Date 1970-12-25 07:51:03 \n% evt 2.0 \n% firmware_version 0.0.0 \n% integrator_name Prophesee \n"
              b"% plugin_name hal_plugin_gen3_fx3 \n% serial_number 00000307 \n% system_ID 21 \n")
    path = tmp_path / "exp_like.raw"
    path.write_bytes(header + data)
    return path


def test_a_gen4_recording_saved_by_expelliarmus_reads_with_its_size(tmp_path: Path) -> None:
    """Report userC item 2: a gen3 plugin_name made a 1280x720 file unreadable, and --size 1280x720 was refused."""
    events = Events([1000, 5], [700, 3], [10, 20], [1, 0], width=1280, height=720)
    path = _expelliarmus_like(tmp_path, events)
    assert read(path, width=1280, height=720) == events
    assert read_evt2(path, width=1280, height=720) == events
    with pytest.raises(FormatError, match=r"x=1000 outside the 640x480 sensor.*the header does not state the sensor "
                       r"size, 640x480 is only inferred from its 'plugin_name hal_plugin_gen3_fx3' line: pass the "
                       r"sensor's width= and height= \(cmax: --size WxH\)") as caught:
        read(path)
    assert "states" not in str(caught.value)


def test_cmax_info_of_an_expelliarmus_file_takes_size(tmp_path: Path, capsys) -> None:
    path = _expelliarmus_like(tmp_path, Events([1000, 5], [700, 3], [10, 20], [1, 0], width=1280, height=720))
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "only inferred from its 'plugin_name hal_plugin_gen3_fx3' line" in err and err.count("\n") == 1
    assert main(["info", str(path), "--size", "1280x720"]) == 0
    assert "1280 x 720" in capsys.readouterr().out


def test_raw_without_a_size_takes_the_callers(tmp_path: Path) -> None:
    path = tmp_path / "bare.raw"
    path.write_bytes(b"% evt 3.0\n% end\n" + np.array([0x8000, 0x6000, 0x0001, 0x2002], "<u2").tobytes())
    assert read(path, width=4, height=4).sensor_size == (4, 4)


def test_mvsec_refuses_a_size_other_than_the_davis346(tmp_path: Path) -> None:
    path = tmp_path / "mvsec.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=np.array([[1, 2, 10.0, -1], [3, 4, 10.5, 1]]))
    with pytest.raises(ValueError, match=r"width=640, height=480 contradicts the 346x260 sensor"):
        read(path, width=640, height=480)
    assert read(path, width=346, height=260).sensor_size == (346, 260)


def test_aedat4_refuses_a_size_other_than_its_stream(shared_data: Path) -> None:
    path = shared_data / "davis346_pegboard" / "davis.aedat4"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    with pytest.raises(ValueError, match=r"width=100, height=100 contradicts the 346x260 sensor that .*davis\.aedat4"):
        read(path, width=100, height=100)
    assert read(path, width=346, height=260).sensor_size == (346, 260)


# -- time unit ------------------------------------------------------------------------
def test_h5_writer_states_microseconds_and_refuses_another_unit(tmp_path: Path, events: Events) -> None:
    path = write_h5(tmp_path / "ev.h5", events)
    with h5py.File(path, "r") as file:
        assert file["events/t"].attrs["unit"] == "us"
        assert file["t_offset"].attrs["unit"] == "us"
    for unit in ("s", "ms"):
        with pytest.raises(FormatError, match=rf"time_unit='{unit}' contradicts the unit the file states \('us'\)"):
            read(path, time_unit=unit)
    assert read(path, time_unit="us") == events


def test_h5_of_an_earlier_writer_reads_as_before(tmp_path: Path, events: Events) -> None:
    """Files written before the ``unit`` attributes existed: µs by default; another unit contradicts the layout."""
    path = write_h5(tmp_path / "old.h5", events)
    with h5py.File(path, "a") as file:
        del file["events/t"].attrs["unit"], file["t_offset"].attrs["unit"]
    assert read(path) == events
    assert read(path, time_unit="us") == events
    with pytest.raises(FormatError, match=r"time_unit='s' contradicts the file's layout: H5Writer .* integer µs"):
        read(path, time_unit="s")


def test_original_dsec_file_keeps_the_callers_unit(tmp_path: Path) -> None:
    """DSEC as shipped (uint32 t, t_offset, no attributes) states no unit: µs by default, the caller's if given."""
    path = tmp_path / "dsec.h5"
    with h5py.File(path, "w") as file:
        file["events/x"], file["events/y"] = np.array([1, 2], np.uint16), np.array([3, 4], np.uint16)
        file["events/t"], file["events/p"] = np.array([0, 7], np.uint32), np.array([0, 1], np.uint8)
        file["t_offset"] = np.int64(5)
    assert read(path, width=640, height=480).t.tolist() == [5, 12]
    assert read(path, width=640, height=480, time_unit="ms").t.tolist() == [5000, 12000]


# -- the CLI: one line, exit status 2 ------------------------------------------------
@pytest.mark.parametrize("option, message", [
    (["--size", "128x96"], "width=128, height=96 contradicts the 64x48 sensor"),
    (["--time-unit", "s"], "time_unit='s' contradicts the unit the file states ('us')"),
])
def test_cmax_info_refuses_in_one_line(tmp_path: Path, events: Events, capsys, option, message) -> None:
    path = write_h5(tmp_path / "ev.h5", events)
    assert main(["info", str(path), *option]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert main(["info", str(path), "--size", f"{W}x{H}"]) == 0
    assert "64 x 48" in capsys.readouterr().out


def test_seconds_stated_as_microseconds_are_refused_not_collapsed(tmp_path: Path, events: Events) -> None:
    """An ECD text file (float seconds) read with time_unit='us' (the unit a user guesses when float times are
    refused without one) rounded every time to 0 µs: the recording collapsed into one microsecond. Refused now;
    whole float µs still read, sub-µs float µs still round (test_reliability_readers), and seconds with
    nanosecond digits still round to µs under time_unit='s'."""
    from cmax.io import write_txt

    path = write_txt(tmp_path / "ecd.txt", events)                         # "t[s] x y p"
    with pytest.raises(FormatError, match=r"distinct times stated in us, which rounding to whole microseconds merges into 1 "):
        read(path, width=events.width, height=events.height, time_unit="us")
    assert read(path, width=events.width, height=events.height, time_unit="s") == events
    whole = tmp_path / "us.txt"
    whole.write_text("".join(f"{float(t):.1f} {x} {y} {p}\n" for t, x, y, p in
                             zip(events.t, events.x, events.y, events.p)))
    assert read(whole, width=events.width, height=events.height, time_unit="us") == events
    nano = tmp_path / "ns.txt"
    nano.write_text("".join(f"{t * 1e-6 + 3e-10:.10f} {x} {y} {p}\n" for t, x, y, p in
                            zip(events.t, events.x, events.y, events.p)))
    assert read(nano, width=events.width, height=events.height, time_unit="s") == events


def test_an_ecd_text_file_of_integer_microseconds_is_refused_without_a_unit(tmp_path: Path, events: Events,
                                                                             capsys) -> None:
    """Whole-number times read as ECD's seconds made 50 ms of events a 14-hour recording (0.000 Mev/s; `cmax fit`
    then cut it into a million windows). Refused without a unit, naming --time-unit; read with it."""
    path = tmp_path / "us.txt"
    path.write_text("".join(f"{t} {x} {y} {p}\n" for t, x, y, p in zip(events.t, events.x, events.y, events.p)))
    with pytest.raises(FormatError, match=r"every time in column t is a whole number .* integer microseconds.*"
                                          r"time_unit='us' \(cmax: --time-unit us\)"):
        read(path, width=W, height=H)
    assert read(path, width=W, height=H, time_unit="us") == events
    assert main(["info", str(path), "--size", f"{W}x{H}"]) == 2
    assert "--time-unit us" in capsys.readouterr().err
    # Whole seconds stated as seconds are the caller's word; a few whole times (a toy file) are not refused.
    assert len(read(path, width=W, height=H, time_unit="s")) == len(events)
    few = tmp_path / "few.txt"
    few.write_text("0 1 2 1\n1 3 4 0\n2 5 6 1\n")
    assert read(few, width=W, height=H).t.tolist() == [0, 1_000_000, 2_000_000]


def test_float32_times_that_already_lost_microseconds_are_refused(tmp_path: Path, events: Events) -> None:
    """float32 holds every integer only up to 2**24: a float32 µs column past 16.8 s (or float32 seconds past
    16.8 s) has lost microseconds before any reader sees it. Refused by Events, the .npy reader and from_array;
    float32 below that and float64 read as before."""
    late = np.float32(2**24 + 2)
    with pytest.raises(ValueError, match=r"float32 number, whose values there lie 2 µs apart"):
        Events([0, 1], [0, 1], np.array([0, late], np.float32), [0, 1], W, H)
    assert Events([0, 1], [0, 1], np.array([0, 2**24], np.float32), [0, 1], W, H).t.tolist() == [0, 2**24]
    table = events.to_structured().astype([("x", "<u2"), ("y", "<u2"), ("t", "<f4"), ("p", "<i1")])
    with pytest.raises(ValueError, match="microseconds are already lost"):
        Events.from_array(np.concatenate([table, np.array([(1, 1, late, 1)], table.dtype)]), W, H)
    seconds = table.astype([("x", "<u2"), ("y", "<u2"), ("t", "<f4"), ("p", "<i1")])
    seconds["t"] = (events.t + 20_000_000) / 1e6                           # 20 s in float32 seconds: 2 µs steps
    np.save(tmp_path / "s.npy", seconds)
    with pytest.raises(FormatError, match=r"s.npy: field t\[\d+\] = .* s is a float32 number, whose values there "
                                          r"lie 1.91 µs apart"):
        read(tmp_path / "s.npy", width=W, height=H, time_unit="s")
    seconds["t"] = events.t / 1e6                                          # below 16.8 s: within a microsecond
    np.save(tmp_path / "s.npy", seconds)
    assert np.abs(read(tmp_path / "s.npy", width=W, height=H, time_unit="s").t - events.t).max() <= 1


# -- integer times whose unit nobody states: µs by the format, checked against the file ----------------------------
def _dsec_in_ms(path: Path, n: int, span_ms: int, index: str | None) -> tuple[Path, np.ndarray]:
    """A DSEC-layout file (no unit attribute) whose integer events/t is in MILLISECONDS over ``span_ms``, with an
    ``ms_to_idx`` built for ms times (``index='ms'``), DSEC's recipe applied to the ms values (``'us'``), or none."""
    rng = np.random.default_rng(3)
    t = np.sort(rng.integers(0, span_ms, n)).astype(np.uint32)
    with h5py.File(path, "w") as file:
        for name, column in zip("xytp", (rng.integers(0, 640, n).astype(np.uint16),
                                         rng.integers(0, 480, n).astype(np.uint16), t,
                                         rng.integers(0, 2, n).astype(np.uint8))):
            file.create_dataset(f"events/{name}", data=column)
        file.create_dataset("t_offset", data=np.int64(0))
        if index is not None:
            step = 1 if index == "ms" else 1000
            file.create_dataset("ms_to_idx", data=np.searchsorted(t, step * np.arange(int(t[-1]) // step + 2)))
    return path, t


def test_integer_milliseconds_in_a_dsec_file_are_refused_where_the_file_shows_them(tmp_path: Path, capsys) -> None:
    # 200,000 events over 2 s (100 kev/s) in ms, with an index of one entry a millisecond: read as µs (the layout's
    # default) the recording lasted 2 ms, while its index spans 2 s (was: read as 2 ms, 100 Mev/s, exit 0)
    path, t = _dsec_in_ms(tmp_path / "ms_index.h5", 200_000, 2000, "ms")
    with pytest.raises(FormatError, match=r"ms_index.h5: ms_to_idx has 2,00\d entries .* but events/t ends "
                                          r"2.0 ms after t_offset .*pass time_unit='ms'"):
        read(path, width=640, height=480)
    assert main(["info", str(path), "--size", "640x480"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--time-unit ms" in err
    stated = read(path, width=640, height=480, time_unit="ms")       # the stated unit reads it, index and all
    assert stated.t[-1] == int(t[-1]) * 1000 and len(stated) == len(t)
    window = read(path, width=640, height=480, time_unit="ms", t0_us=500_000, t1_us=600_000)
    assert len(window) == int(np.sum((t >= 500) & (t < 600)))
    # no index, 3 M events in ms over 2 s (1.5 Mev/s): as µs a mean of 1.5e9 events/s, which no sensor produces
    path, _ = _dsec_in_ms(tmp_path / "ms_fast.h5", 3_000_000, 2000, None)
    with pytest.raises(FormatError, match=r"ms_fast.h5: events/t, read as microseconds .* puts 3,000,000 events in "
                                          r"2.0 ms: a mean of 1.5e\+09 events/s.*time_unit='ms'"):
        read(path, width=640, height=480)
    assert read(path, width=640, height=480, time_unit="us").t[-1] == 1999   # stated µs (a simulation): as told


def test_an_index_that_ends_before_the_last_event_is_refused_not_read_as_empty_windows(tmp_path: Path) -> None:
    # DSEC's ms_to_idx recipe applied to ms values, the unit then stated: the index (3 entries) ends long before
    # the events (2 s) (was: every window after 2 ms held 0 events without a word)
    path, t = _dsec_in_ms(tmp_path / "index_us.h5", 20_000, 2000, "us")
    with pytest.raises(FormatError, match=r"index_us.h5: ms_to_idx ends at 2 ms with every row before it, but the "
                                          r"last event of events/t lies 1,99\d.000 ms after t_offset"):
        read(path, width=640, height=480, time_unit="ms", t0_us=500_000, t1_us=600_000)


def test_integer_times_of_a_plausible_rate_and_files_of_this_writer_read_as_before(tmp_path: Path,
                                                                                   events: Events) -> None:
    assert read(write_h5(tmp_path / "ev.h5", events)) == events
    dense = Events(np.zeros(20_000, int), np.zeros(20_000, int), np.arange(20_000) // 5000, np.zeros(20_000, int),
                   8, 8, time_unit="us")                                 # 5000 events a µs: a simulation's burst
    path = write_h5(tmp_path / "dense.h5", dense)
    assert len(read(path)) == 20_000                                     # unit stated: not checked
    with h5py.File(path, "a") as file:                                   # an earlier H5Writer's file: µs all the same
        del file["events/t"].attrs["unit"], file["t_offset"].attrs["unit"]
    assert len(read(path)) == 20_000
    array = np.zeros(20_000, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    array["t"] = np.arange(20_000) * 10                                    # 100 kev/s as µs: plausible
    np.save(tmp_path / "plain.npy", array)
    assert len(read(tmp_path / "plain.npy", width=8, height=8)) == 20_000
    array["t"] = np.arange(20_000) // 100                                  # 20,000 events in 200 "µs": 1e8 ev/s
    np.save(tmp_path / "dense.npy", array)
    assert len(read(tmp_path / "dense.npy", width=8, height=8)) == 20_000  # below the limit: read as µs
    array["t"] = np.arange(20_000) // 2000                                 # 20,000 events in 10 "µs": 2e9 ev/s
    np.save(tmp_path / "ms.npy", array)
    with pytest.raises(FormatError, match=r"ms.npy: field t, read as microseconds .* 2.0e\+09 events/s"):
        read(tmp_path / "ms.npy", width=8, height=8)


def test_integer_nanoseconds_since_1970_read_as_microseconds_are_refused(tmp_path: Path) -> None:
    # a 2 s recording in ns since 1970 (a ROS / Metavision export): as µs it lay in the year 55,000 and lasted
    # 2000 s at 10 events/s (was: read so, without a word, `cmax info` exit 0)
    rng = np.random.default_rng(4)
    t = 1_700_000_000_000_000_000 + np.sort(rng.integers(0, 2 * 10**9, 20_000))
    array = np.zeros(t.size, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    array["t"] = t
    np.save(tmp_path / "ns.npy", array)
    with pytest.raises(FormatError, match=r"ns.npy: field t: the time 17000000019\d+, read as microseconds .* lies "
                                          r"after the year 2100 as µs since 1970: these look like nanoseconds "
                                          r"\(1700000002.000 s since 1970 if so\)"):
        read(tmp_path / "ns.npy", width=8, height=8)
    with h5py.File(tmp_path / "ns.h5", "w") as file:             # DSEC layout: t_offset in ns, events/t from 0
        for name, column in zip("xytp", (array["x"], array["y"], t - t[0], array["p"])):
            file.create_dataset(f"events/{name}", data=column)
        file.create_dataset("t_offset", data=np.int64(t[0]))
    with pytest.raises(FormatError, match=r"ns.h5: events/t: the time 17000000019\d+, .*nanoseconds"):
        read(tmp_path / "ns.h5", width=8, height=8)
    array["t"] = (t - t[0]) // 1000 + 1_700_000_000_000_000                 # the same in µs since 1970: read
    np.save(tmp_path / "us.npy", array)
    assert read(tmp_path / "us.npy", width=8, height=8).t[0] == 1_700_000_000_000_000


def test_cmax_info_says_when_integer_times_are_microseconds_by_assumption(tmp_path: Path, events: Events,
                                                                          capsys) -> None:
    # what no check can tell apart (a slow recording in ms, no index) is at least said (was: a plain µs line)
    path, _ = _dsec_in_ms(tmp_path / "slow.h5", 2_000, 2000, None)
    assert main(["info", str(path), "--size", "640x480"]) == 0
    assumed = "(the file states no unit: integer times read as µs, the format's default; --time-unit ms or s"
    assert assumed in capsys.readouterr().out
    assert main(["info", str(path), "--size", "640x480", "--time-unit", "ms"]) == 0
    assert re.search(r"\ntime        \d+000 \.\. \d+000 µs\n", capsys.readouterr().out)
    assert main(["info", str(write_h5(tmp_path / "ours.h5", events))]) == 0            # H5Writer's: µs, stated
    assert "states no unit" not in capsys.readouterr().out
    np.save(tmp_path / "ev.npy", events.to_structured())
    assert main(["info", str(tmp_path / "ev.npy"), "--size", f"{W}x{H}"]) == 0
    assert assumed in capsys.readouterr().out


def test_mvsec_times_that_are_whole_numbers_are_not_read_as_seconds(tmp_path: Path, capsys) -> None:
    # MVSEC stores float seconds since 1970 (decimals); a table of float µs from 0 read as seconds lasted 23 days
    # at 0.0 events/s (was: `cmax info` and `cmax show` without a word)
    rng = np.random.default_rng(5)
    t_us = np.unique(rng.integers(0, 2_000_000, 1000)).astype(float)
    table = np.stack([rng.integers(0, 346, t_us.size), rng.integers(0, 260, t_us.size), t_us,
                      rng.choice([-1.0, 1.0], t_us.size)], axis=1)
    path = tmp_path / "us_data.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    refused = r"us_data.hdf5: davis/left/events\[:, 2\] \(t\): every time is a whole number \([\d,]+ distinct, .* " \
              r"these look like integer microseconds. State the unit: time_unit='us'"
    with pytest.raises(FormatError, match=refused):
        read(path)
    with pytest.raises(FormatError, match=refused):                 # a window's one event alone would not show it
        read(path, t0_us=int(t_us[0]) * 10**6, t1_us=int(t_us[0]) * 10**6 + 50_000)
    assert main(["show", str(path), "-o", str(tmp_path / "w.png")]) == 2
    assert "look like integer microseconds" in capsys.readouterr().err and not (tmp_path / "w.png").exists()
    assert read(path, time_unit="us").t.tolist() == t_us.astype(np.int64).tolist()
    table[:, 2] = 1.5e9 + t_us * 1e-6                                 # seconds since 1970, as MVSEC: read
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    assert len(read(path)) == t_us.size


def test_mvsec_seconds_of_a_slow_recording_stated_as_milliseconds_are_refused(tmp_path: Path, capsys) -> None:
    """MVSEC's float seconds since 1970 (2017) with time_unit='ms': at 1,000 events/s no two events round to one µs,
    so the rounding check let it through and 20 s of events were read as 20 ms (was: read without a word, by
    read, read_mvsec's windows, iter_mvsec, mvsec_time_span and `cmax info --time-unit ms`). The file still reads
    as seconds without a unit; whole-number milliseconds and milliseconds since 1970 still read as ms."""
    from cmax.io.mvsec import iter_mvsec, mvsec_time_span, read_mvsec

    rng = np.random.default_rng(7)
    t_s = 1504645177.0 + np.sort(rng.uniform(0.0, 20.0, 20_000))       # 20 s at 1,000 events/s
    table = np.stack([rng.integers(0, 346, t_s.size), rng.integers(0, 260, t_s.size), t_s,
                      rng.choice([-1.0, 1.0], t_s.size)], axis=1)
    path = tmp_path / "slow_data.hdf5"
    with h5py.File(path, "w") as file:
        file.create_dataset("davis/left/events", data=table)
    refused = r"slow_data.hdf5: davis/left/events\[:, 2\] \(t\): time_unit='ms' states milliseconds, but these " \
              r"times .* are seconds since 1970 as MVSEC records them \(2017-09-05 .*\): read as milliseconds"
    first_us = int(np.rint(t_s[0] * 1e3 * 1e3))
    for reading in (lambda: read(path, time_unit="ms"), lambda: read_mvsec(path, time_unit="ms"),
                    lambda: read_mvsec(path, time_unit="ms", t0_us=first_us, t1_us=first_us + 10),
                    lambda: list(iter_mvsec(path, time_unit="ms", chunk_rows=5000)),
                    lambda: mvsec_time_span(path, time_unit="ms")):
        with pytest.raises(FormatError, match=refused):
            reading()
    assert main(["info", str(path), "--time-unit", "ms"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "are seconds since 1970 as MVSEC records them" in err, err
    events = read(path)                                                 # MVSEC's own unit: read, 20 s long
    np.testing.assert_array_equal(events.t, np.rint(t_s * 1e6).astype(np.int64))
    for t_ms in (1.2e9 + np.arange(t_s.size, dtype=float),              # whole milliseconds of a clock 14 days old
                 1504645177000.0 + (t_s - t_s[0]) * 1e3):               # milliseconds since 1970, with decimals
        table[:, 2] = t_ms
        with h5py.File(path, "w") as file:
            file.create_dataset("davis/left/events", data=table)
        np.testing.assert_array_equal(read(path, time_unit="ms").t, np.rint(t_ms * 1e3).astype(np.int64))


def test_mvsec_times_in_a_unit_that_cannot_be_right_are_refused_naming_the_unit_that_fits(tmp_path: Path,
                                                                                          capsys) -> None:
    """Every unit an MVSEC time column cannot be in is refused, naming the one that fits: float seconds since 1970
    of a slow recording (50 events/s) with time_unit='us' (was: read as 1,000 events within 20 µs); integer
    milliseconds since 1970 read as seconds, stated or MVSEC's default (was: read as the year 49,649 / 'these look
    like integer microseconds'); integer microseconds since 1970 with time_unit='ms' (was: read, the year 49,649).
    Each reads in the unit named, to the same microseconds."""
    from cmax.io.mvsec import iter_mvsec, mvsec_time_span, read_mvsec

    rng = np.random.default_rng(11)
    t_s = 1504645177.0 + np.sort(rng.uniform(0.0, 20.0, 1000))          # 20 s at 50 events/s, in 2017
    expected_us = np.rint(t_s * 1e6).astype(np.int64)
    path = tmp_path / "slow_data.hdf5"
    cases = (  # (time column as stored, the unit stated (None: MVSEC's seconds), the unit that fits)
        (t_s, "us", None),
        (np.rint(t_s * 1e3).astype(np.int64), "s", "ms"),
        (np.rint(t_s * 1e3).astype(np.int64), None, "ms"),
        (expected_us, "ms", "us"),
    )
    for column, stated, fits in cases:
        dtype = column.dtype
        table = np.stack([rng.integers(0, 346, t_s.size), rng.integers(0, 260, t_s.size),
                          np.zeros(t_s.size), rng.choice([-1, 1], t_s.size)], axis=1).astype(dtype)
        table[:, 2] = column
        with h5py.File(path, "w") as file:
            file.create_dataset("davis/left/events", data=table)
        if fits is None:
            refused = (r"slow_data.hdf5: davis/left/events\[:, 2\] \(t\): time_unit='us' states microseconds, but "
                       r"these times .* are seconds since 1970 as MVSEC records them \(2017-09-05 .*\): read as "
                       r"microseconds, [\d,]+ events of .* Leave time_unit out")
        else:
            refused = (rf"slow_data.hdf5: davis/left/events\[:, 2\] \(t\): the time \d+(\.0)?, read as .*, lies in "
                       rf"the year 49649 as seconds since 1970, past 2103, .* state time_unit='{fits}' "
                       rf"\(cmax: --time-unit {fits}\)")
        first_us = int(expected_us[0])
        for reading in (lambda: read(path, time_unit=stated), lambda: read_mvsec(path, time_unit=stated),
                        lambda: read_mvsec(path, time_unit=stated, t0_us=first_us, t1_us=first_us + 10),
                        lambda: list(iter_mvsec(path, time_unit=stated, chunk_rows=300)),
                        lambda: mvsec_time_span(path, time_unit=stated)):
            with pytest.raises(FormatError, match=refused):
                reading()
        assert main(["info", str(path)] + ([] if stated is None else ["--time-unit", stated])) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and (fits or "seconds since 1970") in err, err
        per_unit_us = {None: 1_000_000, "ms": 1000, "us": 1}[fits]
        np.testing.assert_array_equal(read(path, time_unit=fits).t,
                                      column * per_unit_us if column.dtype.kind == "i" else expected_us)


def _with_sensor_resolution(path: Path, events: Events, value) -> Path:
    """A DSEC-layout h5 of ``events`` whose only size is a ``sensor_resolution`` attribute ``value``."""
    with h5py.File(path, "w") as file:
        for name, column in (("x", events.x), ("y", events.y), ("t", events.t), ("p", events.p)):
            file[f"events/{name}"] = column
        file.attrs["sensor_resolution"] = value
    return path


def test_a_sensor_resolution_attribute_is_read_in_the_order_the_events_allow(tmp_path: Path, capsys) -> None:
    """`sensor_resolution` (event_utils / HQF write (height, width), other converters (width, height)) was
    ignored: 'stores no sensor size; pass width= and height='. It is read where only one order holds every event,
    refused naming both orders where both do, and where none does; a caller's size must be one of them."""
    rng = np.random.default_rng(5)
    wide = Events(rng.integers(0, 346, 800), rng.integers(0, 260, 800), np.sort(rng.integers(0, 50_000, 800)),
                  rng.integers(0, 2, 800), 346, 260)
    wide = Events(np.r_[wide.x, 345], np.r_[wide.y, 0], np.r_[wide.t, 50_000], np.r_[wide.p, 1], 346, 260)
    for value in ([260, 346], [346, 260]):      # (height, width) and (width, height): x reaches 345 > 259
        path = _with_sensor_resolution(tmp_path / f"{value[0]}.h5", wide, np.array(value, dtype=np.int32))
        assert read(path).sensor_size == (346, 260)
    square = _with_sensor_resolution(tmp_path / "square.h5", random_events(300, width=64, height=64), [64, 64])
    assert read(square).sensor_size == (64, 64)
    small = _with_sensor_resolution(tmp_path / "small.h5", random_events(300, width=200, height=200),
                                    np.array([260, 346]))
    with pytest.raises(FormatError, match=r"sensor_resolution attribute 260, 346 does not state its order, and both "
                                          r"\(height, width\), a 346x260 sensor and \(width, height\), a 260x346"):
        read(small)
    assert read(small, width=260, height=346).sensor_size == (260, 346)     # the caller's order chooses
    with pytest.raises(ValueError, match="width=640, height=480 contradicts the sensor_resolution attribute"):
        read(small, width=640, height=480)
    beyond = _with_sensor_resolution(tmp_path / "beyond.h5", random_events(300, width=400, height=400), [260, 346])
    with pytest.raises(FormatError, match="does not hold every event in either order") as error:
        read(beyond)                      # most of its events lie within 346x260 (was: 'holds none of its events')
    assert "holds none" not in str(error.value)
    odd = _with_sensor_resolution(tmp_path / "odd.h5", wide, [260, 346, 1])
    with pytest.raises(FormatError, match="sensor_resolution attribute must be two whole numbers"):
        read(odd)
    assert main(["info", str(small)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not state its order" in err[0]
    with h5py.File(small, "a") as file:            # width and height beside it: they must be one of its orders
        file.attrs["width"], file.attrs["height"] = 346, 260
    assert read(small).sensor_size == (346, 260)
    with h5py.File(small, "a") as file:
        file.attrs["width"], file.attrs["height"] = 640, 480
    with pytest.raises(FormatError, match=r"contradicts itself: its width and height attributes state a 640x480 "
                                          r"sensor, its sensor_resolution attribute 260, 346"):
        read(small)


def test_nanoseconds_with_their_index_are_not_advised_to_be_read_as_milliseconds(tmp_path: Path) -> None:
    # 20,000 events over 2 s in integer NANOSECONDS (a ROS export) with DSEC's ms_to_idx built for them (one entry
    # per 1e6 ns): read as µs the events run 1000 times past the index's end. Reading them as ms would make them
    # longer still, so the refusal must point at nanoseconds (was: 'in milliseconds? pass time_unit='ms'', and
    # --time-unit ms then refused them at 1,999,999,000 ms)
    rng = np.random.default_rng(5)
    t = np.sort(rng.integers(0, 2_000_000_000, 20_000))
    path = tmp_path / "ns.h5"
    with h5py.File(path, "w") as file:
        for name, column in zip("xytp", (rng.integers(0, 640, t.size).astype(np.uint16),
                                         rng.integers(0, 480, t.size).astype(np.uint16), t,
                                         rng.integers(0, 2, t.size).astype(np.uint8))):
            file.create_dataset(f"events/{name}", data=column)
        file.create_dataset("t_offset", data=np.int64(0))
        file.create_dataset("ms_to_idx", data=np.searchsorted(t, 1_000_000 * np.arange(int(t[-1]) // 1_000_000 + 2)))
    with pytest.raises(FormatError, match=r"ns.h5: ms_to_idx ends at 200\d ms .* in nanoseconds.*t // 1000") as error:
        read(path, width=640, height=480)
    assert "time_unit='ms'" not in str(error.value)


def test_a_burst_at_the_fastest_sensors_rated_peak_is_read_as_microseconds(tmp_path: Path) -> None:
    # a Prophesee IMX636 (Gen4.1) reads out up to 1.066e9 events/s: a recording of one 10 µs burst at that rate,
    # 10,660 events in t = 0..9 µs, is a legitimate recording in µs (was: refused as 'a mean of 1.1e+09 events/s,
    # more than any event sensor produces'); 1000 times that rate (times in ms) is still refused
    rng = np.random.default_rng(6)
    array = np.zeros(10_660, dtype=[("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    array["t"] = np.repeat(np.arange(10), 1066)
    array["x"], array["y"] = rng.integers(0, 1280, array.size), rng.integers(0, 720, array.size)
    np.save(tmp_path / "burst.npy", array)
    events = read(tmp_path / "burst.npy", width=1280, height=720)
    assert len(events) == 10_660 and int(events.t[-1]) == 9
    array["t"] = np.arange(array.size) // 10_000                 # 10,000 events a µs: 1e10 events/s
    np.save(tmp_path / "faster.npy", array)
    with pytest.raises(FormatError, match=r"faster.npy: field t, read as microseconds .* events/s"):
        read(tmp_path / "faster.npy", width=1280, height=720)


def test_an_index_that_ends_one_ms_early_is_called_corrupt_without_a_nanosecond_hint(tmp_path: Path) -> None:
    # an ms_to_idx corrupted near its end (its last entry already holds every row, though the last event lies 0.996 ms
    # after that entry's ms) was refused with "in nanoseconds, 1000 times the index's span?": the times span the
    # index's 199 ms, not 1000 times that; the nanosecond hint stays for times far past the index
    t = np.sort(np.random.default_rng(0).integers(0, 200_000, 20_000)).astype(np.uint32)
    index = np.searchsorted(t, 1000 * np.arange(200)).astype(np.uint64)
    index[150:] = len(t)
    path = tmp_path / "shifted.h5"
    with h5py.File(path, "w") as file:
        for name, values in (("x", np.zeros_like(t, np.uint16)), ("y", np.zeros_like(t, np.uint16)), ("t", t),
                             ("p", np.ones_like(t, np.uint8))):
            file.create_dataset(f"events/{name}", data=values)
        file.create_dataset("ms_to_idx", data=index)
        file.create_dataset("t_offset", data=np.int64(0))
    with pytest.raises(FormatError, match=r"shifted.h5: ms_to_idx ends at 199 ms with every row before it, but the "
                                          r"last event of events/t lies 199.9\d\d ms after t_offset; else the "
                                          r"index is corrupt$"):
        read(path, width=640, height=480)
