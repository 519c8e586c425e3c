"""Fuzzing with hypothesis: decoders never crash on garbage, and core invariants hold.

Decoders (EVT 2.0 / EVT 3.0 RAW, AEDAT4, ECD text, DSEC h5) get arbitrary bytes and
mutated copies of valid files (bytes flipped, cut, inserted); each either returns
:class:`~cmax.events.Events` that satisfy the container's invariants or raises
:class:`~cmax.io.FormatError` (a ``ValueError``) -- never ``IndexError``,
``struct.error``, ``OSError``, ``OverflowError`` or a decoder library's own error.

Invariants: h5 write/read round trip, windowed reads equal in-memory slicing,
voxel-grid conservation, the IWE of zero motion equals the event frame, warps
forward then back are the identity, and se3_exp/se3_log invert each other.

Every test is seeded (``derandomize=True``) with a small ``max_examples``: the file
runs in about 20-30 s and gives the same examples on every run.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings, strategies as st

from cmax import Events, geometry
from cmax.io import (
    FormatError, H5Reader, read_aedat4, read_evt2, read_evt3, read_h5, read_txt, write_evt2, write_evt3,
    write_h5, write_txt,
)
from cmax.iwe import image_of_warped_events, iwe_numpy
from cmax.representations import event_frame, voxel_grid
from cmax.warp import warp_flow, warp_rotation, warp_se3

#: Examples per test; for a deep run: ``CMAX_FUZZ_EXAMPLES=2000 pytest tests/test_fuzz.py``,
#: with ``CMAX_FUZZ_RANDOM=1`` for fresh random examples instead of the fixed seeded ones.
EXAMPLES = int(os.environ.get("CMAX_FUZZ_EXAMPLES", "40"))
RANDOM = os.environ.get("CMAX_FUZZ_RANDOM", "") not in ("", "0")

FUZZ = settings(
    max_examples=EXAMPLES, deadline=None, derandomize=not RANDOM, database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
FEW = settings(FUZZ, max_examples=max(1, EXAMPLES * 3 // 8))

_TMP = Path(".")  # the module's scratch folder, set by the fixture below


@pytest.fixture(scope="module", autouse=True)
def _scratch(tmp_path_factory):
    """Files written by the examples go to one temporary folder (hypothesis reuses it)."""
    global _TMP
    _TMP = tmp_path_factory.mktemp("fuzz")


def _file(name: str, data: bytes) -> Path:
    path = _TMP / name
    path.write_bytes(data)
    return path


def _check_decoded(result: object) -> None:
    """Whatever a decoder returns must satisfy the Events invariants."""
    assert isinstance(result, Events)
    assert result.x.dtype == np.uint16 and result.y.dtype == np.uint16
    assert result.t.dtype == np.int64 and result.p.dtype == np.int8
    if len(result):
        assert int(result.x.max()) < result.width and int(result.y.max()) < result.height
        assert np.all(np.diff(result.t) >= 0)
        assert set(np.unique(result.p).tolist()) <= {0, 1}


def _decode(reader, path: Path, **options) -> None:
    try:
        result = reader(path, **options)
    except FormatError:
        return
    _check_decoded(result)


# -- events for the invariants ---------------------------------------------------------------
@st.composite
def event_streams(draw, max_size: int = 300, max_sensor: int = 40):
    width = draw(st.integers(1, max_sensor))
    height = draw(st.integers(1, max_sensor))
    n = draw(st.integers(0, max_size))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    span = draw(st.sampled_from([1, 10, 1000, 250_000, 3_000_000]))
    start = draw(st.sampled_from([0, 17, 1_000_000_007, 2**40]))
    t = start + np.sort(rng.integers(0, span, n))
    return Events(rng.integers(0, width, n), rng.integers(0, height, n), t, rng.integers(0, 2, n), width, height)


# -- Prophesee RAW ---------------------------------------------------------------------------
RAW_HEADERS = {
    "evt3": b"% evt 3.0\n% format EVT3;height=48;width=64\n% end\n",
    "evt2": b"% evt 2.0\n% format EVT2;height=48;width=64\n% end\n",
}


@FUZZ
@given(words=st.binary(max_size=4000))
def test_evt3_decoder_on_arbitrary_words(words):
    path = _file("arbitrary3.raw", RAW_HEADERS["evt3"] + words)
    _decode(read_evt3, path)
    _decode(read_evt3, path, sort=True, chunk_bytes=64)


@FUZZ
@given(words=st.binary(max_size=4000))
def test_evt2_decoder_on_arbitrary_words(words):
    path = _file("arbitrary2.raw", RAW_HEADERS["evt2"] + words)
    _decode(read_evt2, path)
    _decode(read_evt2, path, sort=True, chunk_bytes=64)


def _words(types: list[int], bits: int, dtype: str, prefix: list[int]):
    """Streams of words of the format's defined types (random payloads, event words more likely),
    after ``prefix`` words that set time and address: decoded deep, not refused at once."""
    return st.lists(st.tuples(st.sampled_from(types), st.integers(0, (1 << bits) - 1)), max_size=400).map(
        lambda words: np.array(prefix + [(kind << bits) | payload for kind, payload in words], dtype).tobytes()
    )


#: EVT 3.0: TIME_HIGH, TIME_LOW, ADDR_Y, ADDR_X (x3), VECT_BASE_X, VECT_12 (x2), VECT_8, and the skipped types.
EVT3_TYPES = [0x8, 0x6, 0x0, 0x2, 0x2, 0x2, 0x3, 0x4, 0x4, 0x5, 0x7, 0xA, 0xE, 0xF]
EVT3_PREFIX = [0x8000 | 5, 0x6000 | 9, 0x0000 | 3, 0x3000 | 16]
#: EVT 2.0: CD_OFF, CD_ON (x3 each), TIME_HIGH, and the skipped types.
EVT2_TYPES = [0x0, 0x0, 0x0, 0x1, 0x1, 0x1, 0x8, 0xA, 0xE, 0xF]
EVT2_PREFIX = [(0x8 << 28) | 7]


BIG_SENSOR = {
    "evt3": b"% evt 3.0\n% format EVT3;height=2100;width=2100\n% end\n",
    "evt2": b"% evt 2.0\n% format EVT2;height=2100;width=2100\n% end\n",
}


@FUZZ
@given(words=_words(EVT3_TYPES, 12, "<u2", EVT3_PREFIX))
def test_evt3_decoder_on_words_of_defined_types(words):
    """Decoded deep: the result is valid Events, independent of the chunk size."""
    path = _file("typed3.raw", BIG_SENSOR["evt3"] + words)
    try:
        whole = read_evt3(path, sort=True)
    except FormatError:
        return
    _check_decoded(whole)
    assert read_evt3(path, sort=True, chunk_bytes=6) == whole
    try:
        assert read_evt3(path) == whole  # in stream order, when the stream's time never goes back
    except FormatError as error:
        assert "time goes back" in str(error)


@FUZZ
@given(words=_words(EVT2_TYPES, 28, "<u4", EVT2_PREFIX))
def test_evt2_decoder_on_words_of_defined_types(words):
    path = _file("typed2.raw", BIG_SENSOR["evt2"] + words)
    try:
        whole = read_evt2(path, sort=True)
    except FormatError:
        return
    _check_decoded(whole)
    assert read_evt2(path, sort=True, chunk_bytes=4) == whole
    try:
        assert read_evt2(path) == whole
    except FormatError as error:
        assert "time goes back" in str(error)


@FUZZ
@given(events=event_streams(max_size=400, max_sensor=2048))
def test_evt_writers_round_trip(events):
    assume(not len(events) or events.t[-1] < 2**40)
    write_evt3(_TMP / "round3.raw", events, overwrite=True)
    write_evt2(_TMP / "round2.raw", events, overwrite=True)
    assert read_evt3(_TMP / "round3.raw") == events
    assert read_evt2(_TMP / "round2.raw") == events


@FUZZ
@given(data=st.binary(max_size=600))
def test_raw_readers_on_arbitrary_files(data):
    """No header at all, or a broken one: the header parser must not crash either."""
    path = _file("arbitrary.raw", data)
    for reader in (read_evt3, read_evt2):
        _decode(reader, path)
    _decode(read_evt3, _file("header.raw", b"% " + data))
    _decode(read_evt3, _file("format.raw", b"% format EVT3;" + data[:40] + b"\n" + data[40:]))


def _mutate(data: bytes, draw_ops) -> bytes:
    """Apply (kind, position, value) edits: flip a byte, cut the tail, insert or delete bytes."""
    out = bytearray(data)
    for kind, position, value in draw_ops:
        if not out:
            break
        i = position % len(out)
        if kind == "flip":
            out[i] ^= value or 1
        elif kind == "cut":
            del out[i:]
        elif kind == "insert":
            out[i:i] = bytes([value]) * (1 + value % 5)
        else:
            del out[i: i + 1 + value % 7]
    return bytes(out)


MUTATIONS = st.lists(
    st.tuples(st.sampled_from(["flip", "cut", "insert", "delete"]), st.integers(0, 2**31), st.integers(0, 255)),
    min_size=1, max_size=6,
)


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory) -> dict[str, bytes]:
    """Small valid files of every format written by this library (synthetic, no shared data)."""
    folder = tmp_path_factory.mktemp("valid")
    rng = np.random.default_rng(7)
    n = 400
    events = Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, 40_000, n)),
                    rng.integers(0, 2, n), 64, 48)
    write_evt3(folder / "e3.raw", events)
    write_evt2(folder / "e2.raw", events)
    write_h5(folder / "e.h5", events[:50], compression="gzip")
    write_txt(folder / "e.txt", events[:60])
    return {name: (folder / name).read_bytes() for name in ("e3.raw", "e2.raw", "e.h5", "e.txt")}


@FUZZ
@given(ops=MUTATIONS)
def test_mutated_evt_files(valid_files, ops):
    _decode(read_evt3, _file("m3.raw", _mutate(valid_files["e3.raw"], ops)))
    _decode(read_evt2, _file("m2.raw", _mutate(valid_files["e2.raw"], ops)))


@FEW
@given(ops=MUTATIONS)
def test_mutated_real_evt3_file(shared_data, ops):
    data = (shared_data / "prophesee_gen4_driving" / "evt3_sample.raw").read_bytes()[:60_000]
    _decode(read_evt3, _file("real3.raw", _mutate(data, ops)))


# -- AEDAT4 ----------------------------------------------------------------------------------
@FUZZ
@given(data=st.binary(max_size=800))
def test_aedat4_decoder_on_arbitrary_bytes(data):
    _decode(read_aedat4, _file("arbitrary.aedat4", b"#!AER-DAT4.0\r\n" + data))
    _decode(read_aedat4, _file("noheader.aedat4", data))


@FEW
@given(ops=MUTATIONS)
def test_mutated_real_aedat4_file(shared_data, ops):
    data = (shared_data / "davis346_pegboard" / "davis.aedat4").read_bytes()
    _decode(read_aedat4, _file("real.aedat4", _mutate(data, ops)))


# -- ECD text --------------------------------------------------------------------------------
@FUZZ
@given(text=st.text(alphabet="0123456789.-+eEnaifNA #\t\n,x", max_size=300))
def test_txt_decoder_on_arbitrary_text(text):
    _decode(read_txt, _file("arbitrary.txt", text.encode()), width=64, height=48)


@FUZZ
@given(data=st.binary(max_size=300))
def test_txt_decoder_on_arbitrary_bytes(data):
    _decode(read_txt, _file("bytes.txt", data), width=64, height=48)


@FUZZ
@given(ops=MUTATIONS)
def test_mutated_txt_file(valid_files, ops):
    _decode(read_txt, _file("m.txt", _mutate(valid_files["e.txt"], ops)), width=64, height=48)


# -- DSEC h5 ---------------------------------------------------------------------------------
@FUZZ
@given(data=st.binary(max_size=600))
def test_h5_reader_on_arbitrary_bytes(data):
    _decode(read_h5, _file("arbitrary.h5", b"\x89HDF\r\n\x1a\n" + data))


@FUZZ
@given(ops=MUTATIONS)
def test_mutated_h5_file(valid_files, ops):
    _decode(read_h5, _file("m.h5", _mutate(valid_files["e.h5"], ops)))


# -- invariants ------------------------------------------------------------------------------
@FUZZ
@given(events=event_streams(), compression=st.sampled_from(["blosc", "gzip", "none"]))
def test_h5_round_trip_is_exact(events, compression):
    path = _TMP / "round.h5"
    write_h5(path, events, overwrite=True, compression=compression, source="fuzz")
    back = read_h5(path)
    assert back == events and back.sensor_size == events.sensor_size


@FUZZ
@given(events=event_streams(max_size=500), data=st.data())
def test_windowed_reads_equal_slicing_in_memory(events, data):
    path = _TMP / "windows.h5"
    write_h5(path, events, overwrite=True)
    low = int(events.t[0]) - 2000 if len(events) else -2000
    high = int(events.t[-1]) + 2000 if len(events) else 2000
    with H5Reader(path) as reader:
        for _ in range(4):
            t0 = data.draw(st.integers(low, high))
            t1 = data.draw(st.integers(t0, high + 1))
            assert reader.window(t0, t1) == events.slice_time(t0, t1)


@FUZZ
@given(events=event_streams(), bins=st.integers(1, 9))
def test_voxel_grid_conserves_signed_polarity_and_weight(events, bins):
    """Each event's weight (1 in total) is split between the bins around t*: summed over bins,
    the grid is the signed event frame, and |weights| add up to the event count."""
    grid = voxel_grid(events, bins=bins)
    signed = event_frame(events, signed=True)
    np.testing.assert_allclose(grid.sum(axis=0), signed, atol=1e-3)
    # Conservation of |weight|: the grid of positive-only polarity counts every event once.
    ones = Events(events.x, events.y, events.t, np.ones(len(events), np.int8), events.width, events.height)
    assert float(voxel_grid(ones, bins=bins).sum()) == pytest.approx(len(events), abs=1e-3 * max(1, len(events)))
    torch_grid = voxel_grid(events.to_torch(), bins=bins).numpy()
    np.testing.assert_allclose(torch_grid, grid, atol=2e-4 * max(1, len(events)) ** 0.5)


@FUZZ
@given(events=event_streams(max_size=400))
def test_iwe_of_zero_motion_is_the_event_frame(events):
    counts = event_frame(events).sum(axis=0)
    x = events.x.astype(np.float32)
    y = events.y.astype(np.float32)
    np.testing.assert_allclose(iwe_numpy(x, y, height=events.height, width=events.width, sigma=0), counts,
                               atol=1e-4)
    signed = iwe_numpy(x, y, height=events.height, width=events.width, sigma=0,
                       weights=events.signed_polarity())
    np.testing.assert_allclose(signed, event_frame(events, signed=True), atol=1e-4)
    # Zero flow through the warp gives the same image (torch entry point).
    tx, ty = torch.from_numpy(x).double(), torch.from_numpy(y).double()
    dt = torch.linspace(-0.05, 0.05, len(events), dtype=torch.float64)
    wx, wy = warp_flow(tx, ty, dt, torch.zeros(2, dtype=torch.float64))
    image = image_of_warped_events(wx, wy, height=events.height, width=events.width, sigma=0)
    np.testing.assert_allclose(image.numpy(), counts, atol=1e-9)


FINITE = dict(allow_nan=False, allow_infinity=False)
_K = torch.tensor([[200.0, 0.0, 64.0], [0.0, 210.0, 48.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _pixels(seed: int, n: int = 50) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    rng = np.random.default_rng(seed)
    x = torch.from_numpy(rng.uniform(0, 128, n))
    y = torch.from_numpy(rng.uniform(0, 96, n))
    dt = torch.from_numpy(rng.uniform(-0.05, 0.05, n))
    rays = torch.stack([x, y, torch.ones(n, dtype=torch.float64)], 1) @ torch.linalg.inv(_K).T
    return x, y, dt, rays


def _rays_of(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return torch.stack([x, y, torch.ones_like(x)], 1) @ torch.linalg.inv(_K).T


@FUZZ
@given(seed=st.integers(0, 2**32 - 1), flow=st.lists(st.floats(-500, 500, **FINITE), min_size=2, max_size=2))
def test_flow_warp_forward_then_back_is_identity(seed, flow):
    x, y, dt, _ = _pixels(seed)
    u = torch.tensor(flow, dtype=torch.float64)
    x1, y1 = warp_flow(x, y, dt, u)
    x2, y2 = warp_flow(x1, y1, -dt, u)
    torch.testing.assert_close(x2, x, atol=1e-9, rtol=0)
    torch.testing.assert_close(y2, y, atol=1e-9, rtol=0)


@FUZZ
@given(seed=st.integers(0, 2**32 - 1), omega=st.lists(st.floats(-3, 3, **FINITE), min_size=3, max_size=3))
def test_rotation_warp_forward_then_back_is_identity(seed, omega):
    x, y, dt, rays = _pixels(seed)
    w = torch.tensor(omega, dtype=torch.float64)
    x1, y1 = warp_rotation(rays, dt, w, _K)
    x2, y2 = warp_rotation(_rays_of(x1, y1), -dt, w, _K)
    torch.testing.assert_close(x2, x, atol=1e-7, rtol=0)
    torch.testing.assert_close(y2, y, atol=1e-7, rtol=0)


@FUZZ
@given(seed=st.integers(0, 2**32 - 1),
       v=st.lists(st.floats(-2, 2, **FINITE), min_size=3, max_size=3),
       omega=st.lists(st.floats(-2, 2, **FINITE), min_size=3, max_size=3),
       depth=st.floats(1.0, 20.0))
def test_se3_warp_forward_then_back_is_identity(seed, v, omega, depth):
    """Warping by exp(xi dt) then by exp(-xi dt) from the warped point (with its new depth)
    returns the pixel: the back warp needs the point's depth in the warped frame."""
    x, y, dt, rays = _pixels(seed)
    v_t, w_t = torch.tensor(v, dtype=torch.float64), torch.tensor(omega, dtype=torch.float64)
    xi = np.r_[v, omega]
    T = geometry.se3_exp(xi[None] * dt.numpy()[:, None])          # (N, 4, 4)
    points = rays.numpy() * depth
    moved = np.einsum("nij,nj->ni", T[:, :3, :3], points) + T[:, :3, 3]
    assume(np.all(moved[:, 2] > 0.2))                               # stays in front of the camera
    inv = torch.full((len(x),), 1.0 / depth, dtype=torch.float64)
    x1, y1 = warp_se3(rays, dt, v_t, w_t, inv, _K)
    x2, y2 = warp_se3(_rays_of(x1, y1), -dt, v_t, w_t, torch.from_numpy(1.0 / moved[:, 2]), _K)
    torch.testing.assert_close(x2, x, atol=1e-6, rtol=0)
    torch.testing.assert_close(y2, y, atol=1e-6, rtol=0)
    # And the forward warp is the pinhole projection of the moved point (closed form).
    K = _K.numpy()
    torch.testing.assert_close(x1, torch.from_numpy(K[0, 0] * moved[:, 0] / moved[:, 2] + K[0, 2]), atol=1e-6,
                               rtol=0)


@FUZZ
@given(xi=st.lists(st.floats(-3, 3, **FINITE), min_size=6, max_size=6))
def test_se3_exp_log_round_trip(xi):
    xi = np.asarray(xi)
    assume(np.linalg.norm(xi[3:]) < np.pi - 1e-3)  # the log returns angles in [0, pi)
    T = geometry.se3_exp(xi)
    np.testing.assert_allclose(geometry.se3_log(T), xi, atol=1e-8)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(geometry.se3_exp(geometry.se3_log(T)), T, atol=1e-9)
