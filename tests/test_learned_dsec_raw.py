"""Training and prediction on raw DSEC events (events/left/events.h5 beside rectify_map.h5, no size attributes),
rectified through the sequence's cam_to_cam.yaml into camRect0's frame as DSEC's own tools do."""
from __future__ import annotations

from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from benchmarks.real_cmax import write_dsec_original
from cmax.cli import main as cmax_main
from cmax.events import Events
from cmax.representations import voxel_grid
from learned.config import load_config
from learned.data import H5WindowDataset, flip_horizontal, reverse_time

W, H = 64, 48
K_RAW = np.array([[55.3, 0, 33.1], [0, 55.2, 22.4], [0, 0, 1]])
DISTORTION = np.array([-0.18, 0.12, 4e-4, -6e-4])
R_RECT = cv2.Rodrigues(np.array([0.004, -0.012, 0.009]))[0]   # about 1 degree, as DSEC's R_rect0
K_RECT = np.array([[57.0, 0, 31.6], [0, 57.0, 23.3], [0, 0, 1]])


def _rows(matrix: np.ndarray) -> str:
    return "\n".join(f"  - [{', '.join(repr(float(v)) for v in row)}]" for row in matrix)


def _cam_to_cam() -> str:
    return (f"extrinsics:\n  R_rect0:\n{_rows(R_RECT)}\nintrinsics:\n  cam0:\n"
            f"    camera_matrix: [{K_RAW[0, 0]}, {K_RAW[1, 1]}, {K_RAW[0, 2]}, {K_RAW[1, 2]}]\n"
            f"    distortion_coeffs: [{', '.join(repr(float(v)) for v in DISTORTION)}]\n    distortion_model: radtan\n"
            f"    resolution: [{W}, {H}]\n  camRect0:\n"
            f"    camera_matrix: [{K_RECT[0, 0]}, {K_RECT[1, 1]}, {K_RECT[0, 2]}, {K_RECT[1, 2]}]\n"
            f"    resolution: [{W}, {H}]\n")


def _opencv(xy: np.ndarray) -> np.ndarray:
    """DSEC's rectify_map of the raw pixels ``xy`` (N, 2): cv2.undistortPoints(..., R=R_rect0, P=K_rect0)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    return cv2.undistortPoints(xy.reshape(-1, 1, 2).astype(np.float64), K_RAW, DISTORTION, R=R_RECT, P=K_RECT,
                               criteria=criteria).reshape(-1, 2)


@pytest.fixture()
def sequence(tmp_path) -> tuple[Path, Path, Events]:
    """``(events.h5, cam_to_cam.yaml, events)``: a DSEC sequence folder as DSEC ships it (no size attributes)."""
    left = tmp_path / "zurich_city_00_a" / "events" / "left"
    left.mkdir(parents=True)
    (tmp_path / "zurich_city_00_a" / "calibration").mkdir()
    yaml = tmp_path / "zurich_city_00_a" / "calibration" / "cam_to_cam.yaml"
    yaml.write_text(_cam_to_cam())
    rng = np.random.default_rng(7)
    n = 6000
    events = Events(rng.integers(0, W, n), rng.integers(0, H, n), np.sort(rng.integers(0, 400_000, n)) + 10 ** 9,
                    rng.integers(0, 2, n), W, H)
    path = write_dsec_original(left / "events.h5", events)
    ys, xs = np.mgrid[0:H, 0:W]
    table = _opencv(np.column_stack([xs.ravel(), ys.ravel()])).reshape(H, W, 2)
    with h5py.File(left / "rectify_map.h5", "w") as file:
        file["rectify_map"] = table.astype(np.float32)
    return path, yaml, events


def test_raw_dsec_windows_are_rectified_as_rectify_map_says(sequence):
    """A data.files entry with DSEC's cam_to_cam.yaml: each window's events sit at their rectify_map positions
    (OpenCV's undistortPoints with R_rect0, K_rect0), the volume spreads them bilinearly from there, and K is
    camRect0's. Before, the file was refused for its missing size, and the advised conversion trained the raw
    events against the rectified K without a word."""
    path, yaml, events = sequence
    dataset = H5WindowDataset([{"path": str(path), "calib": str(yaml)}], window_us=100_000, max_events=500,
                              min_events=10)
    assert len(dataset) == 3
    sample = dataset.sample(1)
    np.testing.assert_array_equal(sample.K, K_RECT)
    window = (events.t >= sample.t0_us) & (events.t < sample.t1_us)
    raw = np.column_stack([events.x[window], events.y[window]])
    with h5py.File(path.parent / "rectify_map.h5", "r") as file:
        mapped = file["rectify_map"][:][raw[:, 1], raw[:, 0]].astype(np.float64)
    exact = _opencv(raw)
    inside = (np.rint(exact) >= 0).all(axis=1) & (np.rint(exact[:, 0]) < W) & (np.rint(exact[:, 1]) < H)
    assert 0 < (~inside).sum() < len(inside) // 4          # the rectification pushes some events off the image
    np.testing.assert_allclose(sample.pixels, exact[inside], atol=1e-4)
    np.testing.assert_allclose(sample.pixels, mapped[inside], atol=1e-4)
    np.testing.assert_array_equal(sample.events.t, events.t[window][inside])
    assert np.abs(np.column_stack([sample.events.x, sample.events.y]) - exact[inside]).max() <= 0.5 + 1e-4
    truth = Events(np.rint(exact[inside, 0]).astype(np.int64), np.rint(exact[inside, 1]).astype(np.int64),
                   events.t[window][inside], events.p[window][inside], W, H)
    item = dataset[1]
    np.testing.assert_allclose(item["volume"].numpy(), voxel_grid(truth, dataset.bins, pixels=exact[inside]),
                               atol=1e-4)
    np.testing.assert_array_equal(item["K"].numpy(), K_RECT.astype(np.float32))


def test_rectify_map_entry_looks_the_positions_up_as_dsec_does(sequence):
    """{"path", "K": camRect0's, "rectify_map": rectify_map.h5}: the positions are the map's values (float32, as
    DSEC stores them), within 1e-4 px of those the calibration gives; the map's shape gives the size."""
    path, yaml, events = sequence
    table_path = path.parent / "rectify_map.h5"
    mapped = H5WindowDataset([{"path": str(path), "K": [57.0, 57.0, 31.6, 23.3], "rectify_map": str(table_path)}],
                             window_us=100_000, max_events=500, min_events=10)
    calibrated = H5WindowDataset([{"path": str(path), "calib": str(yaml)}], window_us=100_000, max_events=500,
                                 min_events=10)
    sample = mapped.sample(2)
    window = (events.t >= sample.t0_us) & (events.t < sample.t1_us)
    with h5py.File(table_path, "r") as file:
        table = file["rectify_map"][:]
    exact = table[events.y[window], events.x[window]].astype(np.float64)
    inside = (np.rint(exact) >= 0).all(axis=1) & (np.rint(exact[:, 0]) < W) & (np.rint(exact[:, 1]) < H)
    np.testing.assert_array_equal(sample.pixels, exact[inside])
    np.testing.assert_array_equal(sample.events.x, np.rint(exact[inside, 0]))
    np.testing.assert_array_equal(sample.K, K_RECT)
    np.testing.assert_allclose(sample.pixels, _opencv(np.column_stack([events.x, events.y])[window])[inside],
                               atol=1e-4)
    other = calibrated.sample(2)
    if len(other.pixels) == len(sample.pixels):   # the same events kept, but for a rounding knife-edge at the border
        np.testing.assert_allclose(other.pixels, sample.pixels, atol=1e-4)
    with h5py.File(path.parent / "bad_map.h5", "w") as file:
        file["rectify_map"] = table[:, :-1]
    from cmax.io import write_h5

    sized = write_h5(path.parent / "events_64x48.h5", events)   # a file that states its size: checked against the map
    with pytest.raises(ValueError, match=r"bad_map.h5 maps a 63x48 sensor, the events of .* a 64x48 one"):
        H5WindowDataset([{"path": str(sized), "K": [57.0, 57.0, 31.6, 23.3], "rectify_map": str(path.parent /
                                                                                                "bad_map.h5")}])


def test_a_calibration_that_disagrees_with_the_map_beside_is_named(sequence):
    """The entry's calibration and DSEC's rectify_map.h5 beside the events agree (both OpenCV's): no warning. The
    cam_to_cam.yaml of another sequence (camRect0's cx 3 px away) rectifies elsewhere: a warning names both files."""
    import warnings

    path, yaml, _ = sequence
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        H5WindowDataset([{"path": str(path), "calib": str(yaml)}], window_us=100_000, min_events=10)
    other = yaml.with_name("other_sequence.yaml")
    other.write_text(yaml.read_text().replace(f"{K_RECT[0, 0]}, {K_RECT[1, 1]}, {K_RECT[0, 2]}",
                                              f"{K_RECT[0, 0]}, {K_RECT[1, 1]}, {K_RECT[0, 2] + 3}"))
    with pytest.warns(UserWarning, match=r"other_sequence.yaml \(cam0\) rectifies its events up to 3.0\d px away "
                                         r"from where .*rectify_map.h5 beside them"):
        H5WindowDataset([{"path": str(path), "calib": str(other)}], window_us=100_000, min_events=10)


def test_augmentations_carry_the_exact_positions(sequence):
    """A mirrored window's volume is the mirror image of the window's (positions mirrored with the events); a
    reversed one pairs each event with its own position."""
    path, yaml, _ = sequence
    dataset = H5WindowDataset([{"path": str(path), "calib": str(yaml)}], window_us=100_000, max_events=500,
                              min_events=10)
    sample = dataset.sample(0)
    volume = voxel_grid(sample.events, 5, pixels=sample.pixels)
    flipped = flip_horizontal(sample)
    np.testing.assert_allclose(voxel_grid(flipped.events, 5, pixels=flipped.pixels), volume[:, :, ::-1], atol=1e-5)
    reversed_ = reverse_time(sample)
    np.testing.assert_array_equal(reversed_.pixels, sample.pixels[::-1])
    assert np.abs(reversed_.pixels - np.column_stack([reversed_.events.x, reversed_.events.y])).max() <= 0.5 + 1e-9


def test_raw_dsec_events_without_calib_are_refused_naming_the_calibration(sequence):
    """rectify_map.h5 beside the events and camRect0's K in the entry: raw events were trained against the
    rectified K without a word; now a one-line refusal that names the map and the cam_to_cam.yaml to add."""
    path, yaml, events = sequence
    from cmax.io import write_h5

    sized = write_h5(path.parent / "events_640.h5", events)   # what the old advice made: a file with its size
    for entry in ({"path": str(sized), "K": [57.0, 57.0, 31.6, 23.3]}, str(path)):
        with pytest.raises(ValueError) as error:
            H5WindowDataset([entry], window_us=100_000, min_events=10)
        message = str(error.value)
        assert "rectify_map.h5 lies beside it" in message and f'"calib": "{yaml.resolve()}"' in message
        assert "\n" not in message
    with pytest.raises(ValueError, match=r'is the rectified camera.*give "calib_camera": "cam0"'):
        H5WindowDataset([{"path": str(path), "calib": str(yaml), "calib_camera": "camRect0"}])
    with pytest.raises(ValueError, match=r"not the K of the frame its calib"):   # the raw cam0 K is another frame's
        H5WindowDataset([{"path": str(path), "calib": str(yaml), "K": [55.3, 55.2, 33.1, 22.4]}])
    (path.parent / "rectify_map.h5").unlink()               # without the map: nothing says the events are raw
    assert len(H5WindowDataset([{"path": str(sized), "K": [57.0, 57.0, 31.6, 23.3]}], window_us=100_000,
                               min_events=10)) == 3


def test_config_takes_and_checks_calib(tmp_path):
    config = load_config(None, ['data.files=[{"path": "e.h5", "calib": "c.yaml", "calib_camera": "cam1"}]'])
    assert config.data.files[0]["calib"] == "c.yaml"
    with pytest.raises(ValueError, match=r"data.files\[0\].calib_camera 'cam0' chooses a camera .* give \"calib\""):
        load_config(None, ['data.files=[{"path": "e.h5", "calib_camera": "cam0"}]'])
    with pytest.raises(TypeError, match=r"data.val_files\[0\].calib must be a non-empty string"):
        load_config(None, ['data.val_files=[{"path": "e.h5", "calib": 3}]'])
    for entry in ('{"path": "e.h5", "rectify_map": "m.h5"}', '{"path": "e.h5", "rectify_map": "m.h5", "calib": "c", '
                  '"K": [1, 1, 0, 0]}'):
        with pytest.raises(ValueError, match=r"data.files\[0\].rectify_map maps the events .* give \"K\""):
            load_config(None, [f"data.files=[{entry}]"])


def test_cmax_depth_refuses_raw_dsec_events_without_calib(sequence, tmp_path, capsys):
    """cmax depth --K on raw DSEC events beside rectify_map.h5 predicted on unrectified events; now exit 2 with
    one line naming --calib. With --calib cam_to_cam.yaml (cam0) the events are rectified, as before."""
    path, yaml, _ = sequence
    status = cmax_main(["depth", str(path), "-o", str(tmp_path / "out"), "--K", "57,57,31.6,23.3", "--size",
                        f"{W}x{H}", "--quiet"])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1, err
    assert "rectify_map.h5 lies beside" in err and f"--calib {yaml.resolve()}" in err
    assert not (tmp_path / "out").exists()


def test_cmax_fit_and_emvs_name_rectify_map_without_a_calibration_beside(sequence):
    """cmax fit / emvs --K on raw DSEC events with rectify_map.h5 beside them but DSEC's calibration download not
    placed in the sequence (no cam_to_cam.yaml anywhere near): the note says the events are raw and names --calib
    (was: no note; the distorted, unrectified events fitted as a pinhole's without a word). With the cam_to_cam.yaml
    in place, the note names it, as before."""
    import argparse

    from cmax.cli.recording import calibration_hint

    path, yaml, _ = sequence
    args = argparse.Namespace(file=str(path), calib=None, distortion=None)
    assert f"--calib {yaml.resolve()}" in calibration_hint(args)
    yaml.unlink()
    hint = calibration_hint(args)
    assert hint is not None and "rectify_map.h5 lies beside the events" in hint and "--calib" in hint
    assert calibration_hint(argparse.Namespace(file=str(path), calib=str(yaml), distortion=None)) is None
