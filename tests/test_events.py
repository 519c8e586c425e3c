"""Events: constructors, conversions, validation, slicing, windows, concatenation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax import STRUCTURED_DTYPE, Events, concatenate
from conftest import random_events


def test_columns_get_the_fixed_dtypes():
    ev = Events(np.array([1, 2], np.int32), [3.0, 4.0], np.array([5, 6], np.uint32), [True, False], 8, 8)
    assert (ev.x.dtype, ev.y.dtype, ev.t.dtype, ev.p.dtype) == (np.uint16, np.uint16, np.int64, np.int8)
    assert ev.p.tolist() == [1, 0]
    assert all(getattr(ev, name).flags.c_contiguous for name in "xytp")


@pytest.mark.parametrize("polarity, expected", [
    ([0, 1, 1], [0, 1, 1]), ([-1, 1, 1], [0, 1, 1]), ([False, True, True], [0, 1, 1]),
    (np.array([-1, 1, -1], np.int8), [0, 1, 0]),
])
def test_polarity_conventions(polarity, expected):
    ev = Events([0, 1, 2], [0, 0, 0], [1, 2, 3], polarity, 4, 4)
    assert ev.p.tolist() == expected
    assert ev.signed_polarity().tolist() == [2 * v - 1 for v in expected]


def test_structured_round_trip_from_other_dtypes():
    source = np.zeros(5, dtype=[("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "u1"), ("extra", "f4")])
    source["t"] = [1, 2, 2, 7, 9]
    source["x"] = [0, 5, 9, 3, 1]
    source["y"] = [1, 1, 2, 3, 4]
    source["p"] = [1, 0, 1, 1, 0]
    ev = Events.from_structured(source, 10, 5)
    back = ev.to_structured()
    assert back.dtype == STRUCTURED_DTYPE
    for name in "xytp":
        np.testing.assert_array_equal(back[name], source[name])
    assert Events.from_structured(back, 10, 5) == ev


def _tonic_dv_and_metavision(ev: Events) -> dict[str, np.ndarray]:
    """``ev`` in the structured layouts users hold: a tonic data set's (int64 x, y, t, p), Prophesee
    Metavision's ``EventCD`` (x, y, p, t) and dv-processing's ``EventStore.numpy()`` (timestamp, x, y, polarity)."""
    tonic = np.zeros(len(ev), dtype=[("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
    metavision = np.zeros(len(ev), dtype=[("x", "<u2"), ("y", "<u2"), ("p", "<i2"), ("t", "<i8")])
    dv = np.zeros(len(ev), dtype=[("timestamp", "<i8"), ("x", "<i2"), ("y", "<i2"), ("polarity", "i1")])
    for array in (tonic, metavision):
        array["x"], array["y"], array["t"], array["p"] = ev.x, ev.y, ev.t, ev.p
    dv["timestamp"], dv["x"], dv["y"], dv["polarity"] = ev.t, ev.x, ev.y, ev.p
    return {"tonic": tonic, "metavision": metavision, "dv": dv}


@pytest.mark.parametrize("layout", ["tonic", "metavision", "dv"])
def test_structured_arrays_of_other_tools_by_field_name(layout, tmp_path):
    """``from_structured``, ``from_array`` (which reads a structured array by its names, not by ``order``:
    a tonic user's first try) and ``cmax.io.read`` of the saved ``.npy`` give the same events."""
    from cmax.io import read

    ev = random_events(200)
    array = _tonic_dv_and_metavision(ev)[layout]
    assert Events.from_structured(array, ev.width, ev.height) == ev
    assert Events.from_array(array, ev.width, ev.height) == ev
    assert Events.from_array(array, ev.width, ev.height, order="txyp") == ev
    np.save(tmp_path / "events.npy", array)
    assert read(tmp_path / "events.npy", width=ev.width, height=ev.height) == ev


def test_a_field_name_and_its_alias_are_read_where_they_agree_and_refused_where_not():
    """Where both ``t`` and dv-processing's ``timestamp`` exist, ``t`` is read when the two are equal; when they
    differ neither is guessed right (it read ``t`` without a word)."""
    array = np.zeros(3, dtype=[("x", "u2"), ("y", "u2"), ("t", "i8"), ("timestamp", "i8"), ("p", "i1")])
    array["t"], array["timestamp"] = [1, 2, 3], [1, 2, 3]
    assert Events.from_structured(array, 4, 4).t.tolist() == [1, 2, 3]
    array["timestamp"] = [30, 20, 10]
    with pytest.raises(ValueError, match=r"fields 't' and 'timestamp', which differ from row 0 on \(1 vs 30\)"):
        Events.from_structured(array, 4, 4)


def test_array_round_trip_with_column_order():
    ev = random_events(300)
    for order in ("xytp", "txyp", "ptyx"):
        table = ev.to_array(order)
        assert table.shape == (300, 4)
        np.testing.assert_array_equal(table[:, order.index("t")], ev.t)
        assert Events.from_array(table, ev.width, ev.height, order=order) == ev


def test_to_torch_matches_columns():
    ev = random_events(100)
    tensors = ev.to_torch()
    assert tensors.x.dtype == torch.int64 and tensors.t.dtype == torch.int64
    np.testing.assert_array_equal(tensors.x.numpy(), ev.x)
    np.testing.assert_array_equal(tensors.t.numpy(), ev.t)
    signed = ev.to_torch(signed_polarity=True).p
    assert signed.dtype == torch.float32
    np.testing.assert_array_equal(signed.numpy(), 2.0 * ev.p - 1)
    assert (tensors.width, tensors.height) == (ev.width, ev.height)


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(t=[3, 2, 4]), ValueError, r"t must be sorted.*t\[1\]=2"),
    (dict(x=[0, 9, 1]), ValueError, r"x must lie in \[0, width=4\)"),
    (dict(y=[0, -1, 1]), ValueError, r"y must lie in \[0, height=3\)"),
    (dict(x=[0.0, np.nan, 1.0]), ValueError, "x contains a non-finite value"),
    (dict(t=[0.0, np.inf, 1.0]), ValueError, "t contains a non-finite value"),
    (dict(t=[0.5, 1.0, 2.0]), ValueError, "t must hold whole numbers"),
    (dict(p=[0, 2, 1]), ValueError, r"p must hold polarities"),
    (dict(p=[-1, 0, 1]), ValueError, r"p must hold polarities"),
    (dict(x=[[0, 1, 2]]), ValueError, r"x must be one-dimensional"),
    (dict(y=[0, 1]), ValueError, "same length"),
    (dict(x=["a", "b", "c"]), TypeError, "x must hold numbers"),
    (dict(width=0), ValueError, "width must be in"),
    (dict(height=2.5), TypeError, "height must be an integer"),
])
def test_bad_input_raises_clear_errors(kwargs, error, match):
    args = dict(x=[0, 1, 2], y=[0, 1, 2], t=[1, 2, 3], p=[0, 1, 1], width=4, height=3)
    args.update(kwargs)
    with pytest.raises(error, match=match):
        Events(**args)


def test_sort_is_explicit_and_stable():
    ev = Events([0, 1, 2, 3], [0, 0, 0, 0], [5, 1, 5, 0], [1, 0, 0, 1], 4, 1, sort=True)
    assert ev.t.tolist() == [0, 1, 5, 5]
    assert ev.x.tolist() == [3, 1, 0, 2]


def test_structured_and_array_constructor_errors():
    with pytest.raises(TypeError, match="structured array"):
        Events.from_structured(np.zeros(3), 4, 4)
    with pytest.raises(ValueError, match=r"lacks the field\(s\) \['p'\]"):
        Events.from_structured(np.zeros(3, dtype=[("x", "u2"), ("y", "u2"), ("t", "i8")]), 4, 4)
    with pytest.raises(ValueError, match=r"shape \(N, 4\)"):
        Events.from_array(np.zeros((3, 3)), 4, 4)
    with pytest.raises(ValueError, match="permutation"):
        Events.from_array(np.zeros((3, 4)), 4, 4, order="xyzp")


def test_slice_time_is_half_open_and_matches_mask(small_events):
    ev = small_events
    t0, t1 = 20_000, 61_234
    window = ev.slice_time(t0, t1)
    mask = (ev.t >= t0) & (ev.t < t1)
    assert window == ev[mask]
    assert ev.slice_time(t0, t0).t.size == 0
    with pytest.raises(ValueError, match="t1_us"):
        ev.slice_time(10, 5)


def test_windows_by_duration_partition_all_events(small_events):
    ev = small_events
    windows = list(ev.windows(duration_us=7_000))
    assert sum(len(w) for w in windows) == len(ev)
    assert concatenate(windows) == ev
    for k, w in enumerate(windows):
        start = ev.t_start + 7_000 * k
        assert np.all((w.t >= start) & (w.t < start + 7_000))
    overlapping = list(ev.windows(duration_us=10_000, step_us=5_000))
    assert len(overlapping) in (len(windows) * 7 // 5, len(windows) * 7 // 5 + 1, len(windows) * 7 // 5 - 1)


def test_windows_by_count(small_events):
    sizes = [len(w) for w in small_events.windows(count=300)]
    assert sizes == [300] * 6 + [200]
    with pytest.raises(ValueError, match="exactly one"):
        next(small_events.windows(count=3, duration_us=5))
    with pytest.raises(ValueError, match="count must be positive"):
        next(small_events.windows(count=0))


def test_indexing_and_len(small_events):
    ev = small_events
    assert len(ev) == 2000
    assert ev[3] == (int(ev.x[3]), int(ev.y[3]), int(ev.t[3]), int(ev.p[3]))
    assert len(ev[10:20]) == 10
    assert ev[np.array([1, 5, 9])].t.tolist() == ev.t[[1, 5, 9]].tolist()
    with pytest.raises(IndexError, match="non-decreasing"):
        ev[np.array([5, 1])]
    with pytest.raises(IndexError, match="negative step"):
        ev[::-1]


def test_concatenate_checks_sensor_and_order():
    a = Events([0], [0], [10], [1], 4, 4)
    b = Events([1], [1], [20], [0], 4, 4)
    assert concatenate([a, b]).t.tolist() == [10, 20]
    with pytest.raises(ValueError, match="back in time"):
        concatenate([b, a])
    with pytest.raises(ValueError, match="sensor"):
        concatenate([a, Events([0], [0], [30], [1], 5, 4)])
    with pytest.raises(ValueError, match="at least one"):
        concatenate([])


def test_empty_events():
    ev = Events.empty(10, 10)
    assert len(ev) == 0 and ev.duration_us == 0
    assert list(ev.windows(duration_us=5)) == []
    with pytest.raises(ValueError, match="empty"):
        ev.t_start


def test_input_arrays_are_not_modified():
    p = np.array([-1, 1, -1])
    x = np.array([0, 1, 2])
    Events(x, x, [1, 2, 3], p, 4, 4)
    assert p.tolist() == [-1, 1, -1] and x.tolist() == [0, 1, 2]


def test_validated_columns_cannot_change_behind_the_events_back():
    """The columns are checked once (inside the sensor, sorted), so nothing may change them afterwards: a caller's
    buffer that the events would share is copied, the columns are read-only, a tensor of ``to_torch`` is a copy.
    Before, shifting the caller's ``x`` after construction put events outside the sensor, and the compiled
    counting loop lost them (983 of 1000 counted) or corrupted the heap."""
    import torch

    from cmax.representations import event_frame, voxel_grid

    rng = np.random.default_rng(0)
    n = 1000
    x = rng.integers(0, 64, n).astype(np.uint16)
    t = np.sort(rng.integers(0, 10_000, n)).astype(np.int64)
    ev = Events(x, rng.integers(0, 48, n), t, rng.integers(0, 2, n), width=64, height=48)
    x += 70                                          # the caller reuses its buffers
    t[:] = t[::-1]
    assert ev.x.max() < 64 and np.all(np.diff(ev.t) >= 0)
    assert event_frame(ev).sum() == n                  # every event counted once
    assert voxel_grid(ev, 1).sum() == pytest.approx(ev.signed_polarity().sum())
    with pytest.raises(ValueError, match="read-only"):
        ev.x += 1
    tensors = ev.to_torch()
    tensors.t.add_(5)
    tensors.p.fill_(3)
    assert np.array_equal(ev.t, np.sort(ev.t)) and set(ev.p.tolist()) <= {0, 1}
    assert tensors.t[0] == ev.t[0] + 5
    xt = torch.randint(0, 64, (10,))
    from_tensor = Events(xt, xt % 48, torch.arange(10), xt % 2, 64, 48)
    xt += 100
    assert from_tensor.x.max() < 64
    assert not ev.slice_time(0, 5_000).x.flags.writeable


def test_times_of_a_uint32_clock_that_wrapped_are_named_not_sorted():
    """A recorder's uint32 µs clock wraps every 2**32 µs (71.6 min): the times drop from near 2**32 to near 0.
    Sorting them would put the events after the wrap first and span 71.6 min; the error names the wrap and
    the unwrapped times (+ 2**32 after the drop) are the true ones. A small step back is still 'out of order'."""
    t = np.array([2**32 - 20, 2**32 - 10, 2**32 - 3, 5, 12], np.uint32)
    for sort in (False, True):
        with pytest.raises(ValueError, match=r"t drops from 4294967293 µs at index 2 to 5 µs at index 3, 71\.6 min "
                                             r"back: a uint32 microsecond clock that wrapped"):
            Events(np.zeros(5), np.zeros(5), t, np.ones(5), 4, 4, sort=sort)
    unwrapped = t.astype(np.int64) + 2**32 * np.cumsum(np.r_[0, np.diff(t.astype(np.int64)) < -2**31])
    assert np.diff(Events(np.zeros(5), np.zeros(5), unwrapped, np.ones(5), 4, 4).t).tolist() == [10, 7, 8, 7]
    with pytest.raises(ValueError, match=r"t must be sorted in non-decreasing order; t\[1\]=3 µs comes after"):
        Events([0, 0], [0, 0], [5, 3], [1, 1], 4, 4)


TONIC_DTYPE = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "<i1")])   # tonic's events


def _tonic(t: np.ndarray, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    array = np.zeros(t.size, TONIC_DTYPE)
    array["x"], array["y"], array["t"], array["p"] = rng.integers(0, 64, t.size), rng.integers(0, 48, t.size), t, \
        rng.integers(0, 2, t.size)
    return array


def test_in_memory_times_of_no_stated_unit_are_checked_as_the_file_readers_check_them(tmp_path):
    """The tonic route (from_structured), Events(...) and from_array refuse what cmax.io.read refuses of the same
    array saved as .npy (was: nanoseconds since 1970 read as µs, a 2 s recording as 2000 s in the year 55,000, and
    20,000 events in 10 µs taken at 2e9 events/s, without a word); correct µs pass unchanged."""
    from cmax.io import read

    rng = np.random.default_rng(7)
    ns = _tonic(1_700_000_000 * 10**9 + np.sort(rng.integers(0, 2 * 10**9, 20_000)))
    burst = _tonic(np.arange(20_000) // 2000)                       # 20,000 events in 10 "µs"
    for name, array, refusal in (("ns", ns, r"t: the time 17000000019\d+, read as microseconds .* these look like "
                                             r"nanoseconds \(1700000002\.000 s since 1970 if so\)"),
                                 ("burst", burst, r"t, read as microseconds .* 2\.0e\+09 events/s")):
        np.save(tmp_path / f"{name}.npy", array)
        with pytest.raises(ValueError, match=refusal):               # the reader's verdict on the same numbers
            read(tmp_path / f"{name}.npy", width=64, height=48)
        for build in (lambda: Events.from_structured(array, 64, 48),
                      lambda: Events(array["x"], array["y"], array["t"], array["p"], 64, 48),
                      lambda: Events.from_array(np.stack([array[n] for n in "txyp"], 1), 64, 48, order="txyp")):
            with pytest.raises(ValueError, match=refusal):
                build()
    stated = Events.from_structured(burst, 64, 48, time_unit="us")    # a simulation's burst, its unit stated
    assert stated.t.tolist() == burst["t"].tolist()
    us = ns.copy()
    us["t"] //= 1000                                                 # the same recording in µs since 1970
    np.save(tmp_path / "us.npy", us)
    ev = Events.from_structured(us, 64, 48)
    assert ev == read(tmp_path / "us.npy", width=64, height=48) and ev.duration_us == us["t"][-1] - us["t"][0]
    assert np.array_equal(ev.to_structured().astype(TONIC_DTYPE), us)


def test_a_stated_time_unit_converts_times_as_the_readers_do():
    """Float seconds (an ECD text layout, evlib) with time_unit='s': rounded to the nearest µs, np.rint(t * 1e6)."""
    rng = np.random.default_rng(8)
    seconds = np.sort(rng.uniform(0, 2, 1000))
    ecd = np.stack([seconds, rng.integers(0, 64, 1000), rng.integers(0, 48, 1000), rng.integers(0, 2, 1000)], 1)
    ev = Events.from_array(ecd, 64, 48, order="txyp", time_unit="s")
    assert ev.t.tolist() == np.rint(seconds * 1e6).astype(np.int64).tolist()
    assert Events(ecd[:, 1], ecd[:, 2], torch.from_numpy(seconds * 1e3), ecd[:, 3], 64, 48, time_unit="ms") == ev
    with pytest.raises(ValueError, match=r"whole numbers, got 0\.0\d+ at index 0 .* state their unit: time_unit='s'"):
        Events.from_array(ecd, 64, 48, order="txyp")
    with pytest.raises(ValueError, match=r"time_unit must be one of 'us', 'ms', 's' \(or None\), got 'ns'"):
        Events([0], [0], [1], [1], 4, 4, time_unit="ns")


def test_a_field_spelt_as_another_tool_spells_it_is_refused_with_the_rename(tmp_path):
    """A time field named 'ts' (event_utils): refused naming the rename, whose call then reads the events
    (was: `array lacks the field(s) ['t']`, and for a .npy `expected ... fields x, y, t, p`, nothing more)."""
    from numpy.lib import recfunctions

    from cmax.io import FormatError, read

    array = _tonic(np.arange(100) * 10)
    renamed = recfunctions.rename_fields(array, {"t": "ts"})
    with pytest.raises(ValueError, match=r"lacks the field\(s\) \['t'\]; it has \['x', 'y', 'ts', 'p'\]: if 'ts' "
                                         r"holds t, rename it: numpy\.lib\.recfunctions\.rename_fields\(array, "
                                         r"\{'ts': 't'\}\)"):
        Events.from_structured(renamed, 64, 48)
    np.save(tmp_path / "ts.npy", renamed)
    with pytest.raises(FormatError, match=r"ts\.npy: expected .* if 'ts' holds t, rename it: numpy\.lib\.recfunctions"
                                          r"\.rename_fields\(np\.load\('.*ts\.npy'\), \{'ts': 't'\}\)"):
        read(tmp_path / "ts.npy", width=64, height=48)
    back = Events.from_structured(recfunctions.rename_fields(np.load(tmp_path / "ts.npy"), {"ts": "t"}), 64, 48)
    assert back == Events.from_structured(array, 64, 48)


def test_a_sensor_size_given_as_height_width_is_named_as_swapped():
    """An image's shape (H, W) passed as width, height (was: only `x must lie in [0, width=480), got 544`): the
    refusal says the events fit the swapped size, which then holds them; a size neither order fits says nothing."""
    rng = np.random.default_rng(9)
    array = np.zeros(2000, TONIC_DTYPE)
    array["x"], array["y"], array["t"] = rng.integers(0, 640, 2000), rng.integers(0, 480, 2000), np.arange(2000) * 50
    swapped = r"every event lies inside a 640x480 sensor: width and height swapped\? \(Events takes width=640, height=480"
    with pytest.raises(ValueError, match=r"x must lie in \[0, width=480\), got \d+ at index \d+; " + swapped):
        Events.from_structured(array, 480, 640)
    with pytest.raises(ValueError, match=swapped):
        Events(array["x"], array["y"], array["t"], array["p"], 480, 640)
    assert len(Events.from_structured(array, 640, 480)) == 2000
    with pytest.raises(ValueError, match=r"x must lie in \[0, width=600\), got \d+ at index \d+$"):
        Events.from_structured(array, 600, 470)


def test_a_polarity_of_0_255_or_of_signed_values_cast_to_uint8_is_refused_naming_the_conversion():
    """Polarities {0, 255} (an 8-bit image's) and {1, 255} (-1/+1 cast to uint8) stay refused, numpy and torch alike
    (was: only `got the values [0, 255]`); the conversions named give the events of the {0, 1} polarity."""
    from cmax.representations import voxel_grid

    p01 = np.array([0, 1, 1, 0, 1], np.uint8)
    x, t = np.arange(5), np.arange(5) * 10
    expected = Events(x, x, t, p01, 8, 8)
    for p, hint, converted in ((p01 * 255, r"0/255 as an 8-bit image stores them\? if 255 is ON pass p > 0",
                                p01 * 255 > 0),
                               ((2 * p01.astype(np.int8) - 1).astype(np.uint8),
                                r"-1/\+1 cast to uint8 \(-1 wraps to 255\)\? convert p to int8 \(255 becomes -1\)",
                                (2 * p01.astype(np.int8) - 1).astype(np.uint8).astype(np.int8))):
        with pytest.raises(ValueError, match=r"p must hold polarities as \{0, 1\}, \{-1, \+1\} or bool; got the "
                                             r"values \[\d, 255\]; " + hint):
            Events(x, x, t, p, 8, 8)
        tensors = expected.to_torch()._replace(p=torch.from_numpy(p))
        with pytest.raises(ValueError, match=r"events\.p must hold .* got the values \[\d, 255\]; " + hint):
            voxel_grid(tensors, 2)
        assert Events(x, x, t, converted, 8, 8) == expected


def test_times_as_numpy_durations_or_dates_are_refused_naming_the_exact_conversion():
    """evlib's / polars' Duration[us] as numpy timedelta64, datetime64 since 1970 (was: only `t must hold numbers,
    got dtype timedelta64[us]`): refused, naming the conversion, which gives the µs of the same times."""
    t_us = np.array([0, 10, 25, 1_000_000])
    x = np.zeros(4, int)
    for t, expected in ((t_us.astype("timedelta64[us]"), t_us),
                        (np.datetime64("2023-11-14T22:13:20", "ns") + t_us.astype("timedelta64[us]"),
                         1_700_000_000_000_000 + t_us)):
        kind = "timedelta64" if t.dtype.kind == "m" else "datetime64"
        with pytest.raises(TypeError, match=rf"t must hold numbers, got dtype {kind}\[\w+\] \(numpy times carry their "
                                            rf"unit: .* t\.astype\('{kind}\[us\]'\)\.astype\(np\.int64\)"):
            Events(x, x, t, x, 4, 4)
        converted = t.astype(f"{kind}[us]").astype(np.int64)
        assert Events(x, x, converted, x, 4, 4).t.tolist() == expected.tolist()


def test_an_n_by_4_array_in_t_x_y_p_order_read_as_x_y_t_p_names_the_column_in_time_order():
    """ECD's events.txt loaded with np.loadtxt (t [s], x, y, p) given to from_array with its default order 'xytp'
    (was: `x must hold whole numbers, got 0.00038...`, pointing at x): the line names column 0 as the one in time
    order and order='txyp', which (with time_unit='s') reads the events; a refusal of another cause says nothing."""
    rng = np.random.default_rng(10)
    t = np.sort(rng.uniform(0, 2, 1000))
    x, y, p = rng.integers(0, 240, 1000), rng.integers(0, 180, 1000), rng.integers(0, 2, 1000)
    ecd = np.stack([t, x, y, p], 1)
    hint = (r"; column 0 is the one in time order, not column 2: are the columns t, x, y, p\? \(order='txyp'; ECD/rpg "
            r"text files and v2e tables are t, x, y, p\)$")
    with pytest.raises(ValueError, match=r"^x must hold whole numbers, got 0\.0\d+ at index 0" + hint):
        Events.from_array(ecd, 240, 180)
    with pytest.raises(ValueError, match=r"^x must lie in \[0, width=240\), got \d+\.0 at index 0" + hint):
        Events.from_array(np.stack([np.rint(t * 1e6), x, y, p], 1), 240, 180)
    assert Events.from_array(ecd, 240, 180, order="txyp", time_unit="s") == \
        Events(x, y, np.rint(t * 1e6).astype(np.int64), p, 240, 180)
    with pytest.raises(ValueError, match=r"^x must lie in \[0, width=200\), got \d+(\.0)? at index \d+$"):
        Events.from_array(np.stack([x, y, np.rint(t * 1e6), p], 1), 200, 180)


def _with_second_column(ev: Events, column: str, name: str, values) -> np.ndarray:
    """``ev.to_structured()`` with one more field ``name`` holding ``values`` (a second spelling of ``column``)."""
    base = ev.to_structured()
    array = np.empty(len(ev), dtype=base.dtype.descr + [(name, np.asarray(values).dtype.str)])
    for field in base.dtype.names:
        array[field] = base[field]
    array[name] = values
    return array


@pytest.mark.parametrize("column, name, same", [
    ("t", "timestamp", lambda ev: ev.t), ("x", "xs", lambda ev: ev.x.astype(np.int32)),
    ("p", "polarity", lambda ev: ev.signed_polarity(np.int8))])    # -1/+1 of the same events: they agree
def test_a_column_held_twice_reads_when_both_agree_and_is_refused_naming_both_and_the_row_where_they_differ(
        tmp_path, column, name, same):
    """An array or .npy with ``t`` and ``timestamp`` (``x`` and ``xs``, ``p`` and ``polarity``) read ``t`` and
    ignored the other without a word, even where they disagreed."""
    from cmax.io import read
    from conftest import random_events

    ev = random_events(200)
    agree = _with_second_column(ev, column, name, same(ev))
    assert Events.from_structured(agree, ev.width, ev.height) == ev
    np.save(tmp_path / "agree.npy", agree)
    assert read(tmp_path / "agree.npy", width=ev.width, height=ev.height) == ev
    second = np.array(same(ev))
    second[137] = (1 - ev.p[137]) if column == "p" else second[137] + 1     # row 137 differs (polarity flipped)
    differ = _with_second_column(ev, column, name, second)
    np.save(tmp_path / "differ.npy", differ)
    for build, source in ((lambda: Events.from_structured(differ, ev.width, ev.height), "array"),
                          (lambda: read(tmp_path / "differ.npy", width=ev.width, height=ev.height),
                           str(tmp_path / "differ.npy"))):
        with pytest.raises(ValueError) as refused:
            build()
        message = str(refused.value)
        assert message.startswith(f"{source} holds fields {column!r} and {name!r}, which differ from row 137 "), message
