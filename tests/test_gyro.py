"""A known rotation from a gyroscope: ``cmax.fit(..., omega=)``, ``fit_sequence(gyro=)``, ``cmax fit --gyro``."""
from __future__ import annotations

import json

import numpy as np
import pytest

from cmax.cli import main
from cmax.fitting import fit_sequence
from cmax.fitting.sequence import check_gyro, window_gyro
from cmax.io import FormatError, read_gyro, write_h5
from test_fit_motion import angle_deg, point_scene


def test_window_mean_of_a_ramp_is_its_value_at_the_middle():
    """Samples of omega(t) = a + b t every 5 ms; windows whose edges fall between samples."""
    times = np.arange(0, 1_000_001, 5_000)
    a, b = np.array([0.1, -0.2, 0.3]), np.array([0.5, 1.0, -2.0])           # rad/s, rad/s^2
    omega = a + b * times[:, None] * 1e-6
    gyro = check_gyro((times, omega))
    for t0, t1 in [(12_345, 178_901), (0, 1_000_000), (500_001, 500_002)]:
        np.testing.assert_allclose(window_gyro(gyro, t0, t1), a + b * 0.5 * (t0 + t1) * 1e-6, rtol=1e-12)


@pytest.mark.parametrize("gyro, match", [
    ((np.array([0, 10]), np.zeros((3, 3))), "shapes"),
    ((np.array([0]), np.zeros((1, 3))), "N >= 2"),
    ((np.array([0, 10, 10]), np.zeros((3, 3))), "strictly increasing"),
    ((np.array([0, 10]), np.array([[0, 0, 0], [0, np.nan, 0]])), "finite"),
    ("gyro.txt", "gyro must be"),
])
def test_bad_gyro(gyro, match):
    with pytest.raises(ValueError, match=match):
        check_gyro(gyro)


def test_window_outside_the_gyro_is_an_error():
    gyro = check_gyro((np.array([100, 200]), np.zeros((2, 3))))
    with pytest.raises(ValueError, match="gyro covers 100-200 us"):
        window_gyro(gyro, 150, 250)


def test_read_gyro_text_and_bad_columns(tmp_path):
    path = tmp_path / "gyro.txt"
    path.write_text("# t wx wy wz\n0.000100 0.1 0.2 0.3\n0.000200 -0.1 0 1e-3\n")
    times, omega = read_gyro(path)
    np.testing.assert_array_equal(times, [100, 200])
    np.testing.assert_allclose(omega, [[0.1, 0.2, 0.3], [-0.1, 0.0, 1e-3]])
    (tmp_path / "bad.txt").write_text("0.1 0.2 0.3\n")
    with pytest.raises(FormatError, match="t wx wy wz"):
        read_gyro(tmp_path / "bad.txt")


def test_read_gyro_from_an_aedat4_file_is_in_radians_and_camera_axes(shared_data):
    """A DAVIS's IMU x and z point against the camera's (rpg_dvs_ros turns them as -x, y, -z); the readings were
    taken as camera axes. Stated axes replace the known ones."""
    from cmax.io import read_aedat4_imu

    path = shared_data / "davis346_pegboard" / "davis.aedat4"
    times, omega = read_gyro(path)
    imu = read_aedat4_imu(path, sort=True)
    np.testing.assert_allclose(np.degrees(omega), imu.gyroscope * np.array([-1.0, 1.0, -1.0]), rtol=1e-6)
    assert np.all(np.diff(times) > 0)
    _, raw = read_gyro(path, axes="x,y,z")
    np.testing.assert_allclose(np.degrees(raw), imu.gyroscope, rtol=1e-6)
    _, swapped = read_gyro(path, axes="y,-x,z")
    np.testing.assert_allclose(swapped, raw[:, [1, 0, 2]] * np.array([1.0, -1.0, 1.0]))


def test_the_pegboards_gyro_turns_with_the_events_in_camera_axes(shared_data):
    """Independent of the driver's convention: the rotation fitted to 20 ms windows of the DAVIS346 pegboard
    follows the gyroscope's mean over the same windows, axis by axis, only once the IMU's x is turned to the
    camera's (the pitch, x, is the best measured axis: a correlation of about -0.9 before)."""
    import warnings

    from cmax import fit
    from cmax.io import read

    path = shared_data / "davis346_pegboard" / "davis.aedat4"
    events = read(path)
    times, omega = read_gyro(path)
    K = np.array([[226.38, 0, 173.64], [0, 226.15, 133.73], [0, 0, 1]])
    fitted, gyro = [], []
    for start in range(int(events.t[0]), int(events.t[-1]) - 20_000, 10_000):
        window = events.slice_time(start, start + 20_000)
        inside = (times >= start) & (times < start + 20_000)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fitted.append(fit(window, K, model="rotation", max_events=20_000).omega)
        gyro.append(omega[inside].mean(0))
    fitted, gyro = np.array(fitted), np.array(gyro)
    assert np.corrcoef(fitted[:, 0], gyro[:, 0])[0, 1] > 0.5


def test_an_imu_of_an_unknown_camera_needs_its_axes(tmp_path, shared_data):
    path = shared_data / "davis346_pegboard" / "davis.aedat4"
    data = path.read_bytes().replace(b"DAVIS346_00000104", b"DVXPLR_0000000104")
    other = tmp_path / "other.aedat4"
    other.write_bytes(data)
    with pytest.raises(ValueError, match="no known orientation against the camera .*--gyro-axes"):
        read_gyro(other)
    assert read_gyro(other, axes="x,y,z")[1].shape[1] == 3
    with pytest.raises(ValueError, match="name each IMU axis once"):
        read_gyro(path, axes="x,x,z")


@pytest.fixture(scope="module")
def scene():
    """Two 0.15 s windows of a point scene under a constant twist."""
    return point_scene(2, duration_s=0.3, points=5000, max_omega_deg=30.0)


def test_fit_sequence_holds_each_window_at_the_gyro_mean(scene):
    events, K, v, omega = scene
    times = np.arange(-10_000, 320_001, 2_500)
    ramp = omega + np.radians(2.0) * (times[:, None] * 1e-6)                 # a slowly changing reading
    result = fit_sequence(events, K, window_us=145_000, speed=float(np.linalg.norm(v)), gyro=(times, ramp))
    assert len(result.results) == 2
    for r in result.results:
        np.testing.assert_allclose(r.omega, window_gyro((times, ramp), r.t0_us, r.t1_us), rtol=1e-12)
        assert angle_deg(r.v, v) < 6.0


def test_gyro_is_for_se3_only(scene):
    events, K, _, omega = scene
    with pytest.raises(ValueError, match="se3"):
        fit_sequence(events, K, "rotation", gyro=(np.array([0, 400_000]), np.stack([omega, omega])))


def test_cli_fit_with_a_gyro_file(scene, tmp_path):
    """`cmax fit --gyro`: every window's rotation in summary.json is the gyro's, the rest is fitted."""
    events, K, v, omega = scene
    write_h5(tmp_path / "scene.h5", events)
    lines = [f"{t:.6f} {omega[0]:.12g} {omega[1]:.12g} {omega[2]:.12g}" for t in np.arange(0.0, 0.31, 0.01)]
    (tmp_path / "gyro.txt").write_text("\n".join(lines) + "\n")
    args = ["fit", str(tmp_path / "scene.h5"), "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}",
            "-o", str(tmp_path / "out"), "--window-ms", "145", "--speed", str(float(np.linalg.norm(v))),
            "--gyro", str(tmp_path / "gyro.txt")]
    assert main(args) == 0
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["gyro"].endswith("gyro.txt") and len(summary["windows"]) == 2
    for window in summary["windows"]:
        np.testing.assert_allclose(window["omega"], omega, rtol=1e-9)
        assert angle_deg(np.array(window["v"]), v) < 6.0


def test_fit_sequence_checks_the_gyro_span_before_fitting(scene, monkeypatch):
    """An IMU that starts 5 ms after the events: a clear error before any window is fitted; the events cut
    to the gyro's span are accepted."""
    from types import SimpleNamespace

    import cmax.fitting.sequence as sequence

    events, K, v, omega = scene
    fits = []
    monkeypatch.setattr(sequence, "fit", lambda events, *a, **k: fits.append(k["omega"]) or
                        SimpleNamespace(twist=np.zeros(6), verdict=None, model="se3", quality=None))
    t0, t1 = int(events.t[0]), int(events.t[-1])
    late = (np.array([t0 + 5_000, t1 + 10_000]), np.stack([omega, omega]))
    with pytest.raises(ValueError, match=f"gyro covers {t0 + 5_000}-{t1 + 10_000} us, but the windows span {t0}-"):
        fit_sequence(events, K, window_us=145_000, speed=float(np.linalg.norm(v)), gyro=late)
    assert fits == []
    result = fit_sequence(events.slice_time(t0 + 5_000, t1 + 1), K, window_us=145_000,
                          speed=float(np.linalg.norm(v)), gyro=late)
    assert len(fits) == len(result.results) == 2
    np.testing.assert_allclose(fits, [omega, omega])


def test_stated_axes_turn_a_text_files_readings(tmp_path):
    """A text file is in camera axes unless ``axes=`` states otherwise: the camera's x, y, z as signed IMU axes."""
    path = tmp_path / "imu.txt"
    path.write_text("0.0 1 2 3\n0.1 4 5 6\n")
    _, same = read_gyro(path)
    _, turned = read_gyro(path, axes="-y,x,-z")
    np.testing.assert_array_equal(same, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(turned, [[-2, 1, -3], [-5, 4, -6]])
    for bad in ("x,y", "x,y,w", "-x,-x,z"):
        with pytest.raises(ValueError, match="name each IMU axis once"):
            read_gyro(path, axes=bad)


def test_an_hdf5_file_as_gyro_is_refused_in_one_line_naming_mvsec(tmp_path, capsys):
    """`cmax fit --gyro data.hdf5` with MVSEC's data file failed with "'utf-8' codec can't decode byte 0x89",
    naming neither HDF5 nor MVSEC; its IMU's columns and axes are stated nowhere, so it is refused, naming what to
    pass. Another binary file is named as not text."""
    h5py = pytest.importorskip("h5py")
    mvsec = tmp_path / "indoor_flying1_data.hdf5"
    rng = np.random.default_rng(0)
    with h5py.File(mvsec, "w") as file:
        left = file.create_group("davis/left")
        left["events"] = np.column_stack([rng.integers(0, 346, 400), rng.integers(0, 260, 400),
                                          np.sort(rng.uniform(1.5e9, 1.5e9 + 0.2, 400)),
                                          rng.choice([-1, 1], 400)]).astype(float)
        left["imu"] = rng.normal(size=(50, 6))
        left["imu_ts"] = np.linspace(1.5e9, 1.5e9 + 0.2, 50)
    with pytest.raises(FormatError, match=r"is an MVSEC data file \(IMU davis/left/imu\): its IMU is not read"):
        read_gyro(mvsec)
    other = write_h5(tmp_path / "ev.h5", point_scene_events())
    with pytest.raises(FormatError, match="is an HDF5 file, not a gyro file"):
        read_gyro(other)
    (tmp_path / "noise.bin").write_bytes(bytes([0xF0, 0x28, 0x8C, 0x28]) * 64)
    with pytest.raises(FormatError, match="is not a text file"):
        read_gyro(tmp_path / "noise.bin")
    status = main(["fit", str(other), "--K", "60,60,32,24", "--gyro", str(mvsec), "-o", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert status == 2 and "MVSEC data file" in err and "utf-8" not in err and len(err.strip().splitlines()) == 1


def point_scene_events():
    """A few events of a 64x48 sensor over 0.1 s (the gyro refusal comes before any fit)."""
    from cmax.events import Events

    rng = np.random.default_rng(1)
    return Events(rng.integers(0, 64, 300), rng.integers(0, 48, 300), np.sort(rng.integers(0, 100_000, 300)),
                  rng.integers(0, 2, 300), 64, 48)
