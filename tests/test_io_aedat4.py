"""Tests of the AEDAT 4.0 reader: a real DAVIS346 recording and hand-built files.

The synthetic files are assembled byte by byte below from the FlatBuffers
binary layout (root offset, identifier, vtable, table, vectors), independently
of the reader, so they give an exact expectation of the decoded values.
"""
from __future__ import annotations

import struct
from pathlib import Path

import lz4.frame
import numpy as np
import pytest

from cmax.events import Events
from cmax.io.aedat4 import (
    MAGIC,
    Aedat4Stream,
    ApsFrames,
    ImuSamples,
    aedat4_streams,
    read_aedat4,
    read_aedat4_frames,
    read_aedat4_imu,
)
from cmax.io.errors import FormatError

REAL_FILE = Path("davis346_pegboard") / "davis.aedat4"


# -- hand-built flatbuffers -------------------------------------------------------------
def _pad(buffer: bytearray, alignment: int) -> None:
    buffer.extend(b"\0" * (-len(buffer) % alignment))


def _size_prefixed(buffer: bytes) -> bytes:
    return struct.pack("<I", len(buffer)) + buffer


def _event_packet(t, x, y, p) -> bytes:
    """Size-prefixed ``EventPacket``: vtable at 8, table at 16, vector at 28."""
    buffer = bytearray(struct.pack("<I", 16) + b"EVTS")
    buffer += struct.pack("<HHH", 6, 8, 4)  # vtable: size 6, table 8 bytes, field 0 at +4
    _pad(buffer, 8)
    buffer += struct.pack("<iI", 16 - 8, 28 - 20)  # soffset to vtable; vector at 20 + 8
    buffer += b"\0" * 4  # so that the 16-byte structs start 8-aligned at 32
    buffer += struct.pack("<I", len(t))
    for ti, xi, yi, pi in zip(t, x, y, p):
        buffer += struct.pack("<qhh?3x", ti, xi, yi, bool(pi))
    return _size_prefixed(bytes(buffer))


def _imu_packet(samples: list[dict]) -> bytes:
    """Size-prefixed ``IMUPacket`` of ``Imu`` tables; absent keys are left out of the vtable.

    Each sample maps field index (0 t, 1 temperature, 2-4 accelerometer,
    5-7 gyroscope, 8-10 magnetometer) to its value.
    """
    buffer = bytearray(struct.pack("<I", 16) + b"IMUS")
    buffer += struct.pack("<HHH", 6, 8, 4)
    _pad(buffer, 8)
    buffer += struct.pack("<iI", 8, 4)  # table at 16; vector at 20 + 4 = 24
    vector = len(buffer)
    buffer += struct.pack("<I", len(samples)) + b"\0" * (4 * len(samples))
    for i, sample in enumerate(samples):
        fields = max(sample) + 1
        _pad(buffer, 2)
        vtable = len(buffer)
        offsets = [0] * fields
        layout = {0: 8, 1: 4, **{k: 16 + 4 * (k - 2) for k in range(2, 11)}}
        for k in sample:
            offsets[k] = layout[k]
        buffer += struct.pack(f"<HH{fields}H", 4 + 2 * fields, 52, *offsets)
        _pad(buffer, 8)
        table = len(buffer)
        body = bytearray(struct.pack("<i", table - vtable) + b"\0" * 48)
        for k, value in sample.items():
            struct.pack_into("<q" if k == 0 else "<f", body, layout[k], value)
        buffer += body
        slot = vector + 4 + 4 * i
        struct.pack_into("<I", buffer, slot, table - slot)
    return _size_prefixed(bytes(buffer))


def _frame_packet(t: int, image: np.ndarray) -> bytes:
    """Size-prefixed ``Frame`` with all 11 fields; ``image`` (H, W) uint8 gray.

    Vtable at 8 (26 bytes), table at 40 (60 bytes), pixel vector at 100.
    """
    buffer = bytearray(struct.pack("<I", 40) + b"FRME")
    # t, frame start/end, exposure start/end, format, width, height, x, y, pixels
    offsets = (8, 16, 24, 32, 40, 48, 50, 52, 54, 56, 4)
    buffer += struct.pack("<HH11H", 26, 60, *offsets)
    _pad(buffer, 8)
    stamps = (t, t - 10, t + 10, t - 2, t + 2)
    height, width = image.shape
    buffer += struct.pack("<iI5qbxhhhh2x", 40 - 8, 100 - 44, *stamps, 0, width, height, 0, 0)
    buffer += struct.pack("<I", image.size) + image.tobytes()
    return _size_prefixed(bytes(buffer))


def _info_xml(streams: list[tuple[int, str, str, tuple[int, int] | None]]) -> str:
    nodes = []
    for stream_id, kind, name, size in streams:
        info = (f'<attr key="sizeX" type="int">{size[0]}</attr>'
                f'<attr key="sizeY" type="int">{size[1]}</attr>') if size else ""
        nodes.append(
            f'<node name="{stream_id}" path="/outInfo/{stream_id}/">'
            f'<attr key="originalOutputName" type="string">{name}</attr>'
            f'<attr key="typeIdentifier" type="string">{kind}</attr>'
            f'<node name="info" path="/outInfo/{stream_id}/info/">{info}</node></node>'
        )
    return f'<dv version="2.0"><node name="outInfo" path="/outInfo/">{"".join(nodes)}</node></dv>'


def _io_header(compression: int, xml: str, data_table_position: int = -1) -> bytes:
    """``IOHeader`` table at 24: compression at +4, position at +8, info string at +16."""
    buffer = bytearray(struct.pack("<I", 24) + b"IOHE")
    buffer += struct.pack("<HHHHH", 10, 20, 4, 8, 16)
    _pad(buffer, 8)
    text = xml.encode()
    buffer += struct.pack("<iiqI", 24 - 8, compression, data_table_position, 4)
    buffer += struct.pack("<I", len(text)) + text + b"\0"
    return bytes(buffer)


#: An empty ``FileDataTable``: root offset 12, identifier, 4-byte vtable, table.
_EMPTY_INDEX = _size_prefixed(struct.pack("<I", 12) + b"FTAB" + struct.pack("<HHi", 4, 4, 4))


def _aedat4(
    streams, packets: list[tuple[int, bytes]], *, compression: int = 1, index: bool = False
) -> bytes:
    """A whole file: magic, header, ``(stream id, flatbuffer)`` packets, optional index."""

    def compress(body: bytes) -> bytes:
        return lz4.frame.compress(body) if compression == 1 else body

    size = len(_io_header(compression, _info_xml(streams)))
    body = b"".join(struct.pack("<ii", stream_id, len(compress(fb))) + compress(fb)
                    for stream_id, fb in packets)
    position = len(MAGIC) + 4 + size + len(body) if index else -1
    header = _io_header(compression, _info_xml(streams), position)
    tail = compress(_EMPTY_INDEX) if index else b""
    return MAGIC + struct.pack("<i", size) + header + body + tail


SYNTHETIC_STREAMS = [(0, "EVTS", "events", (5, 4)), (2, "IMUS", "imu", None),
                     (3, "FRME", "frames", (3, 2))]
T = [100, 100, 105, 230, 231]
X = [0, 4, 2, 3, 1]
Y = [0, 3, 1, 2, 0]
P = [1, 0, 0, 1, 1]


@pytest.fixture(params=[0, 1], ids=["uncompressed", "lz4"])
def synthetic(tmp_path: Path, request) -> Path:
    imu = [
        {0: 150, 1: 30.5, 2: 0.0, 3: -1.0, 4: 0.25, 5: 1.5, 6: 2.5, 7: -3.5},
        {0: 160, 1: 31.0, 3: 0.5, 6: 7.0},  # short vtable: the rest defaults to 0
    ]
    image = np.arange(6, dtype=np.uint8).reshape(2, 3) * 40
    packets = [
        (0, _event_packet(T[:3], X[:3], Y[:3], P[:3])),
        (2, _imu_packet(imu)),
        (3, _frame_packet(200, image)),
        (0, _event_packet(T[3:], X[3:], Y[3:], P[3:])),
    ]
    path = tmp_path / "synthetic.aedat4"
    path.write_bytes(_aedat4(SYNTHETIC_STREAMS, packets, compression=request.param))
    return path


def test_cmax_info_names_the_imu_and_frame_streams_and_what_reads_them(synthetic: Path, capsys) -> None:
    """A DAVIS recording's IMU is what formats.md's AEDAT4 recipe passes as --gyro, yet cmax info summarised its
    events only: a DAVIS user learnt of the IMU from the docs. It now lists the file's other streams (those of its
    header, here IMUS and FRME) and what reads each; the IMU named is the one read_aedat4_imu reads."""
    from cmax.cli import main

    assert main(["info", str(synthetic)]) == 0
    lines = capsys.readouterr().out.splitlines()
    (streams,) = [line for line in lines if line.startswith("streams ")]
    assert "'imu' (IMUS): IMU samples: cmax fit --gyro FILE" in streams
    assert "'frames' (FRME): APS frames (cmax.io.read_aedat4_frames)" in streams
    assert "'events'" not in streams                    # the events are the block itself
    assert len(read_aedat4_imu(synthetic).t) == 2        # the stream named holds the samples --gyro reads


# -- synthetic files: exact decoding ----------------------------------------------------
def test_synthetic_events_decode_exactly(synthetic: Path) -> None:
    events = read_aedat4(synthetic)
    assert events == Events(X, Y, T, P, 5, 4)
    assert (events.x.dtype, events.y.dtype, events.t.dtype, events.p.dtype) == (
        np.uint16, np.uint16, np.int64, np.int8)
    assert read_aedat4(synthetic, stream="events") == events
    assert read_aedat4(synthetic, stream=0) == events


@pytest.mark.parametrize("compression", [0, 1])
def test_packet_index_ends_the_packets(tmp_path: Path, compression: int) -> None:
    packets = [(0, _event_packet(T, X, Y, P))]
    path = tmp_path / "indexed.aedat4"
    data = _aedat4(SYNTHETIC_STREAMS[:1], packets, compression=compression, index=True)
    path.write_bytes(data)
    assert read_aedat4(path) == Events(X, Y, T, P, 5, 4)
    path.write_bytes(data[: -len(_EMPTY_INDEX) // 2])  # index declared, cut inside it
    with pytest.raises(FormatError):
        read_aedat4(path)


def test_synthetic_imu_decodes_fields_and_defaults(synthetic: Path) -> None:
    imu = read_aedat4_imu(synthetic)
    assert isinstance(imu, ImuSamples) and len(imu) == 2
    np.testing.assert_array_equal(imu.t, [150, 160])
    np.testing.assert_array_equal(imu.temperature, np.float32([30.5, 31.0]))
    np.testing.assert_array_equal(imu.accelerometer, np.float32([[0, -1, 0.25], [0, 0.5, 0]]))
    np.testing.assert_array_equal(imu.gyroscope, np.float32([[1.5, 2.5, -3.5], [0, 7, 0]]))
    assert imu.accelerometer.shape == (2, 3) and imu.accelerometer.dtype == np.float32
    assert imu.magnetometer is None


def test_synthetic_frame(synthetic: Path) -> None:
    frames = read_aedat4_frames(synthetic)
    assert isinstance(frames, ApsFrames) and len(frames) == 1
    np.testing.assert_array_equal(frames.images[0], np.arange(6).reshape(2, 3) * 40)
    assert frames.images.shape == (1, 2, 3) and frames.images.dtype == np.uint8
    assert (frames.t[0], frames.t_exposure_start[0], frames.t_exposure_end[0]) == (200, 198, 202)
    assert (frames.t_frame_start[0], frames.t_frame_end[0]) == (190, 210)
    np.testing.assert_array_equal(frames.origin, [[0, 0]])


def test_synthetic_streams(synthetic: Path) -> None:
    streams = aedat4_streams(synthetic)
    assert [(s.id, s.type_identifier, s.name, s.width, s.height) for s in streams] == [
        (0, "EVTS", "events", 5, 4), (2, "IMUS", "imu", None, None), (3, "FRME", "frames", 3, 2)]
    assert all(isinstance(s, Aedat4Stream) for s in streams)


def test_unknown_stream_request_raises(synthetic: Path) -> None:
    with pytest.raises(ValueError, match="no EVTS stream 'imu'"):
        read_aedat4(synthetic, stream="imu")
    with pytest.raises(ValueError, match="no EVTS stream 7"):
        read_aedat4(synthetic, stream=7)
    with pytest.raises(TypeError):
        read_aedat4(synthetic, stream=1.5)


def test_streams_without_packets_or_absent(tmp_path: Path) -> None:
    path = tmp_path / "empty.aedat4"
    path.write_bytes(_aedat4(SYNTHETIC_STREAMS[:2], []))
    events = read_aedat4(path)
    assert len(events) == 0 and events.sensor_size == (5, 4)
    imu = read_aedat4_imu(path)
    assert imu.t.shape == (0,) and imu.gyroscope.shape == (0, 3)
    with pytest.raises(ValueError, match="no FRME stream"):
        read_aedat4_frames(path)


def test_time_going_back_raises_or_sorts(tmp_path: Path) -> None:
    packets = [(0, _event_packet([50, 60], [1, 2], [0, 0], [1, 0])),
               (0, _event_packet([40, 70], [3, 4], [1, 1], [0, 1]))]
    path = tmp_path / "unsorted.aedat4"
    path.write_bytes(_aedat4(SYNTHETIC_STREAMS[:1], packets))
    with pytest.raises(FormatError, match="time goes back"):
        read_aedat4(path)
    events = read_aedat4(path, sort=True)
    assert events.t.tolist() == [40, 50, 60, 70] and events.x.tolist() == [3, 1, 2, 4]


def test_packet_of_the_wrong_type_raises(tmp_path: Path) -> None:
    path = tmp_path / "wrong_type.aedat4"
    path.write_bytes(_aedat4(SYNTHETIC_STREAMS[:2], [(2, _event_packet([1], [0], [0], [1]))]))
    with pytest.raises(FormatError, match="identifier b'IMUS'"):
        read_aedat4_imu(path)


def test_event_outside_sensor_raises(tmp_path: Path) -> None:
    path = tmp_path / "outside.aedat4"
    path.write_bytes(_aedat4(SYNTHETIC_STREAMS[:1], [(0, _event_packet([1], [5], [0], [1]))]))
    with pytest.raises(FormatError, match="x=5"):
        read_aedat4(path)


def test_zstd_without_package_or_bad_data_raises(tmp_path: Path) -> None:
    path = tmp_path / "zstd.aedat4"
    header = _io_header(3, _info_xml(SYNTHETIC_STREAMS[:1]))
    path.write_bytes(MAGIC + struct.pack("<i", len(header)) + header
                     + struct.pack("<ii", 0, 8) + b"notzstd!")
    with pytest.raises(FormatError, match="[Zz]std"):
        read_aedat4(path)


# -- malformed files --------------------------------------------------------------------
def test_not_aedat4_raises(tmp_path: Path) -> None:
    path = tmp_path / "other.aedat"
    path.write_bytes(b"#!AER-DAT2.0\r\n# some text\r\n" + bytes(100))
    with pytest.raises(FormatError, match="not an AEDAT 4.0 file"):
        read_aedat4(path)
    path.write_bytes(b"")
    with pytest.raises(FormatError):
        aedat4_streams(path)


def test_garbage_after_magic_raises(tmp_path: Path) -> None:
    path = tmp_path / "garbage.aedat4"
    rng = np.random.default_rng(0)
    for _ in range(5):
        path.write_bytes(MAGIC + rng.integers(0, 256, 2000, dtype=np.uint8).tobytes())
        with pytest.raises(FormatError):
            read_aedat4(path)


def test_garbage_packets_after_valid_header_raise(tmp_path: Path) -> None:
    header = _io_header(1, _info_xml(SYNTHETIC_STREAMS))
    path = tmp_path / "garbage_packets.aedat4"
    rng = np.random.default_rng(1)
    for _ in range(5):
        garbage = rng.integers(0, 256, 500, dtype=np.uint8).tobytes()
        path.write_bytes(MAGIC + struct.pack("<i", len(header)) + header + garbage)
        with pytest.raises(FormatError):
            read_aedat4(path)
    # A packet of a known stream and plausible size whose body is not LZ4.
    path.write_bytes(MAGIC + struct.pack("<i", len(header)) + header
                     + struct.pack("<ii", 0, 16) + bytes(range(16)))
    with pytest.raises(FormatError, match="LZ4"):
        read_aedat4(path)


def test_corrupt_header_fields_raise(tmp_path: Path) -> None:
    header = _io_header(1, _info_xml(SYNTHETIC_STREAMS))
    good = MAGIC + struct.pack("<i", len(header)) + header
    path = tmp_path / "corrupt.aedat4"
    cases = {
        "identifier": good.replace(b"IOHE", b"XXXX"),
        "compression": good[:18] + header[:28] + struct.pack("<i", 9) + header[32:],
        "xml": good.replace(b"<dv", b"<d?"),
        "size": MAGIC + struct.pack("<i", 10**6) + header,
        "vtable": good[:18] + header[:24] + struct.pack("<i", 10**6) + header[28:],
    }
    for name, data in cases.items():
        path.write_bytes(data)
        with pytest.raises(FormatError):
            read_aedat4(path)


def test_truncated_synthetic_raises_or_keeps_whole_packets(synthetic: Path, tmp_path: Path) -> None:
    data = synthetic.read_bytes()
    path = tmp_path / "cut.aedat4"
    for cut in range(1, len(data), 7):
        path.write_bytes(data[:cut])
        try:
            events = read_aedat4(path)
        except FormatError:
            continue
        # Without a packet index, a cut at a packet boundary is a shorter recording.
        assert events == Events(X, Y, T, P, 5, 4)[: len(events)]


# -- the real DAVIS346 recording --------------------------------------------------------
@pytest.fixture(scope="module")
def real_file(shared_data: Path) -> Path:
    path = shared_data / REAL_FILE
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    return path


def test_real_events(real_file: Path) -> None:
    events = read_aedat4(real_file)
    assert len(events) == 117_667
    assert events.sensor_size == (346, 260)
    assert np.all(np.diff(events.t) >= 0)
    assert 0.12e6 < events.duration_us < 0.14e6
    assert set(np.unique(events.p).tolist()) == {0, 1}
    assert events.x.max() < 346 and events.y.max() < 260


def test_real_imu(real_file: Path) -> None:
    imu = read_aedat4_imu(real_file)
    assert len(imu) == 130
    assert imu.t.dtype == np.int64 and np.all(np.diff(imu.t) > 0)
    np.testing.assert_allclose(imu.gyroscope.mean(axis=0), [5.7, 1.7, -1.0], atol=0.15)
    np.testing.assert_allclose(np.linalg.norm(imu.accelerometer, axis=1), 1.0, atol=0.1)
    assert np.all((imu.temperature > 0) & (imu.temperature < 60))


def test_real_frames_and_streams(real_file: Path) -> None:
    frames = read_aedat4_frames(real_file)
    assert frames.images.shape == (3, 260, 346) and frames.images.dtype == np.uint8
    assert np.all(frames.t_exposure_start <= frames.t) and np.all(frames.t <= frames.t_exposure_end)
    kinds = [(s.id, s.type_identifier, s.compression) for s in aedat4_streams(real_file)]
    assert kinds == [(0, "EVTS", "lz4"), (1, "FRME", "lz4"), (2, "IMUS", "lz4"), (3, "TRIG", "lz4")]


@pytest.mark.parametrize("cut", [5, 20, 200, 3126 + 4, 3126 + 500, 600_000, 1_189_500, -100, -1])
def test_real_truncated_raises(real_file: Path, tmp_path: Path, cut: int) -> None:
    """Cuts in the magic, header, a packet header, packet bodies, at the boundary
    before the packet index (which the header declares) and inside that index."""
    path = tmp_path / "cut.aedat4"
    path.write_bytes(real_file.read_bytes()[:cut])
    with pytest.raises(FormatError):
        read_aedat4(path)


def test_real_corrupt_packet_raises(real_file: Path, tmp_path: Path) -> None:
    data = bytearray(real_file.read_bytes())
    path = tmp_path / "corrupt.aedat4"
    first_packet = 14 + 4 + struct.unpack_from("<i", data, 14)[0]
    while struct.unpack_from("<i", data, first_packet)[0] != 0:  # the first event packet
        first_packet += 8 + struct.unpack_from("<i", data, first_packet + 4)[0]
    for offset, value in ((0, 99), (4, 2**30)):  # unknown stream id, size past the end
        corrupt = data.copy()
        struct.pack_into("<i", corrupt, first_packet + offset, value)
        path.write_bytes(bytes(corrupt))
        with pytest.raises(FormatError):
            read_aedat4(path)
    corrupt = data.copy()
    corrupt[first_packet + 8: first_packet + 12] = b"\0\0\0\0"  # breaks the LZ4 frame magic
    path.write_bytes(bytes(corrupt))
    with pytest.raises(FormatError):
        read_aedat4(path)


# -- sizes against the file (issue 20) --------------------------------------------------
def test_a_decompression_bomb_is_refused_before_its_output_is_allocated(tmp_path: Path, monkeypatch) -> None:
    import tracemalloc

    bomb = _event_packet(T, X, Y, P) + b"\0" * (200 << 20)  # 200 MB that LZ4 shrinks ~250x
    path = tmp_path / "bomb.aedat4"
    path.write_bytes(_aedat4(SYNTHETIC_STREAMS, [(0, bomb)]))
    assert path.stat().st_size < 1_000_000
    with pytest.raises(FormatError, match=r"packet at byte \d+\): a packet of [\d,]+ compressed bytes "
                                          r"decompresses to more than [\d,]+ bytes \(over 64x"):
        read_aedat4(path)
    # the memory of the refusal follows the bound (about twice the limit), not the 200 MB claimed
    monkeypatch.setattr("cmax.io.aedat4.MAX_EXPANSION", 8)
    tracemalloc.start()
    try:
        with pytest.raises(FormatError, match=r"over 8x"):
            read_aedat4(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 25_000_000, f"the refusal allocated {peak / 1e6:.0f} MB"


def test_packet_limits_follow_the_packet_and_the_frame_size() -> None:
    from cmax.io.aedat4 import MAX_EXPANSION, Aedat4Stream, _packet_limit

    events = Aedat4Stream(0, "EVTS", "events", 346, 260, "lz4")
    frames = Aedat4Stream(1, "FRME", "frames", 346, 260, "lz4")
    assert _packet_limit(1000, events) == MAX_EXPANSION * 1000 + 1024
    assert _packet_limit(1000, frames) == MAX_EXPANSION * 1000 + 1024 + 8 * 346 * 260  # one 16-bit BGRA frame


def test_a_uniform_frame_that_compresses_far_below_its_size_is_read(tmp_path: Path) -> None:
    image = np.zeros((120, 160), np.uint8)  # LZ4 shrinks it ~200x, beyond the 64x of event packets
    path = tmp_path / "dark.aedat4"
    path.write_bytes(_aedat4([(3, "FRME", "frames", (160, 120))], [(3, _frame_packet(200, image))]))
    frames = read_aedat4_frames(path)
    assert frames.images.shape == (1, 120, 160) and not frames.images.any()


def test_a_file_of_two_event_streams_says_which_one_it_read(tmp_path: Path) -> None:
    """A stereo recording (two EVTS streams) was read as its first camera's events without a word about the
    second; now a UserWarning names both and stream= reads either, a file of one stream stays silent."""
    import warnings

    from cmax.io import read

    streams = [(0, "EVTS", "events", (5, 4)), (1, "EVTS", "events_1", (5, 4))]
    packets = [(0, _event_packet([100, 200], [0, 1], [0, 0], [1, 1])),
               (1, _event_packet([150, 250], [2, 3], [1, 1], [0, 0]))]
    path = tmp_path / "stereo.aedat4"
    path.write_bytes(_aedat4(streams, packets))
    with pytest.warns(UserWarning, match=r"stereo.aedat4 holds 2 EVTS streams \[\(0, 'events'\), \(1, 'events_1'\)\]: "
                                         r"read the first, 0 'events'; pass stream="):
        first = read(path)
    assert first.t.tolist() == [100, 200]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_aedat4(path, stream="events_1").t.tolist() == [150, 250]
        assert read(path, stream=1).x.tolist() == [2, 3]
        single = tmp_path / "single.aedat4"
        single.write_bytes(_aedat4(streams[:1], packets[:1]))
        assert len(read(single)) == 2


def test_times_beyond_the_year_2100_as_microseconds_are_refused_naming_nanoseconds(tmp_path: Path) -> None:
    """AEDAT 4.0 stores µs since the Unix epoch; a file whose tool wrote nanoseconds (1.7e18) was read as µs without a
    word: a recording in the year 55,000 whose every interval was 1000 times too long (the DSEC, .npy and text
    readers refuse such times). Events and IMU samples are refused naming the time, its index and the conversion; a
    time of a real DV recording (1.6e15 µs, 2020) reads as it is."""
    from cmax.io import read

    ns = [1_700_000_000_000_000_000 + k * 1000 for k in range(3)]
    path = tmp_path / "ns.aedat4"
    stream = [(0, "EVTS", "events", (5, 4))]
    path.write_bytes(_aedat4(stream, [(0, _event_packet(ns, [0, 1, 2], [0, 1, 2], [1, 1, 0]))]))
    with pytest.raises(FormatError, match=r"ns.aedat4: event time 1700000000000002000 µs at index 2 lies beyond the "
                                          r"year 2100 as µs since the Unix epoch.*look like nanoseconds.*t // 1000"):
        read(path)
    imu = tmp_path / "imu.aedat4"
    imu.write_bytes(_aedat4([(0, "IMUS", "imu", None)], [(0, _imu_packet([{0: ns[0], 5: 1.0}]))]))
    with pytest.raises(FormatError, match=r"imu.aedat4: IMU time 1700000000000000000 µs at index 0 .*nanoseconds"):
        read_aedat4_imu(imu)
    real = [1_600_000_000_000_000 + k for k in range(3)]
    path.write_bytes(_aedat4(stream, [(0, _event_packet(real, [0, 1, 2], [0, 1, 2], [1, 1, 0]))]))
    assert read(path).t.tolist() == real


@pytest.mark.parametrize("size, said", [((0, 0), r"width must be in \[1, 65535\] pixels, got 0"),
                                        ((-5, 4), r"width must be in \[1, 65535\] pixels, got -5"),
                                        ((70000, 4), r"width must be in \[1, 65535\] pixels, got 70000"),
                                        ((60000, 60000), r"a 60000x60000 sensor .* larger than any event camera")])
def test_an_event_stream_of_a_bad_sensor_size_is_refused_as_the_other_readers_refuse_it(tmp_path: Path, size,
                                                                                          said) -> None:
    """An EVTS stream whose sizeX/sizeY declare 0x0, a negative, a > 65535 or a 3.6-gigapixel sensor gave Events of
    that size (an empty file: ``Events(n=0, width=-5, ...)``; with events: "event 0 has x=0, outside the 0x0
    sensor"), where the DSEC and Prophesee readers refuse such a size naming it (cmax.events' limits)."""
    from cmax.io import read

    path = tmp_path / "size.aedat4"
    path.write_bytes(_aedat4([(0, "EVTS", "events", size)], []))
    with pytest.raises(FormatError, match=rf"size.aedat4: event stream 0 declares a bad sensor size \(sizeX/sizeY\): "
                                          rf"{said}"):
        read(path)


@pytest.mark.parametrize("version", ["2.0", "3.1"])
def test_an_older_aedat_file_is_named_by_its_version(tmp_path: Path, version: str) -> None:
    """``read`` / ``cmax info`` of an AEDAT 2.0 or 3.1 file (jAER, cAER; DVS Gesture's recordings) was refused as
    "cannot tell the event format of ...: expected DSEC/MVSEC HDF5, AEDAT4, ...", although its first bytes name it."""
    from cmax.io import read

    path = tmp_path / "user01_fluorescent.aedat"
    path.write_bytes(f"#!AER-DAT{version}\r\n#!END-HEADER\r\n".encode() + bytes(28))
    with pytest.raises(FormatError, match=rf"user01_fluorescent.aedat is an AEDAT {version} file \(jAER / cAER; .*"
                                          r"not read \(AEDAT 4.0 is\)"):
        read(path)
