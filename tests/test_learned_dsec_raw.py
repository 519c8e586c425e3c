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
        assert "rectify_map.h5 lies beside" in message and f'"calib": "{yaml.resolve()}"' in message
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


def _drawn(seed: int, n: int, max_events: int) -> tuple[np.ndarray, np.ndarray]:
    """The subset and dither WarpEvents.from_events draws for ``seed`` (drawn here independently)."""
    keep = np.arange(n)
    if n > max_events:
        keep = np.sort(np.random.default_rng(seed).choice(n, max_events, replace=False))
    return keep, np.random.default_rng([seed, 1]).uniform(-0.5, 0.5, (len(keep), 2))


def test_the_contrast_loss_reads_the_calibrated_events_as_the_fit_does(sequence):
    """A calib entry: the item's loss events are EventWindows.from_events(raw events, camera) (each event dithered over
    its sensor pixel and mapped through the lens and R_rect0, unrounded), and OpenCV's undistortPoints of the
    dithered sensor pixels. Before: the nearest rectified pixel plus a dither (up to ~1 px away)."""
    import torch

    from cmax.contrast import EventWindows

    path, yaml, _ = sequence
    dataset = H5WindowDataset([{"path": str(path), "calib": str(yaml)}], window_us=100_000, max_events=500,
                              min_events=10)
    sample = dataset.sample(1)
    raw = dataset._reader(0).window(sample.t0_us, sample.t1_us)
    item = dataset[1]
    reference = EventWindows.from_events(raw, dataset._cameras[0], max_events=500, seed=dataset.seed + 1)
    n = int(item["valid"].sum())
    assert n == len(reference.x) == 500
    torch.testing.assert_close(item["x"][:n], reference.x, rtol=0, atol=1e-5)
    torch.testing.assert_close(item["y"][:n], reference.y, rtol=0, atol=1e-5)
    torch.testing.assert_close(item["t"][:n], reference.t, rtol=0, atol=1e-7)
    keep, dither = _drawn(dataset.seed + 1, len(sample.events), 500)
    sensor = np.column_stack([raw.x, raw.y])[dataset._cameras[0].undistorted_kept(raw)][keep]
    expected = _opencv(sensor + dither)
    loss_xy = np.column_stack([item["x"][:n].numpy(), item["y"][:n].numpy()])
    np.testing.assert_allclose(loss_xy, expected, atol=1e-3)
    rounded = np.column_stack([sample.events.x, sample.events.y])[keep]
    assert np.abs(loss_xy - rounded).max() > 0.6          # outside the old dither square around the rounded pixel


def test_the_contrast_loss_reads_the_rectify_map_between_pixel_centres(sequence):
    """A rectify_map entry: each loss event is its sensor pixel dithered and the map interpolated bilinearly there;
    at a pixel centre that is the map's own value, and near OpenCV's (the map is smooth)."""
    from scipy.ndimage import map_coordinates

    path, _, _ = sequence
    table_path = path.parent / "rectify_map.h5"
    dataset = H5WindowDataset([{"path": str(path), "K": [57.0, 57.0, 31.6, 23.3], "rectify_map": str(table_path)}],
                              window_us=100_000, max_events=500, min_events=10)
    with h5py.File(table_path, "r") as file:
        table = file["rectify_map"][:]
    sample = dataset.sample(2)
    ys, xs = np.mgrid[0:H, 0:W]
    centres = np.column_stack([xs.ravel(), ys.ravel()]).astype(np.float64)
    np.testing.assert_array_equal(sample.sensor.camera.undistort_points(centres),
                                  table.reshape(-1, 2).astype(np.float64))
    item = dataset[2]
    n = int(item["valid"].sum())
    keep, dither = _drawn(dataset.seed + 2, len(sample.events), 500)
    dithered = sample.sensor.pixels[keep] + dither
    loss_xy = np.column_stack([item["x"][:n].numpy(), item["y"][:n].numpy()])
    inside = (dithered >= 0).all(axis=1) & (dithered[:, 0] <= W - 1) & (dithered[:, 1] <= H - 1)
    bilinear = np.column_stack([map_coordinates(table[..., c].astype(np.float64), dithered[inside, ::-1].T, order=1)
                                for c in (0, 1)])
    np.testing.assert_allclose(loss_xy[inside], bilinear, atol=1e-4)
    np.testing.assert_allclose(loss_xy, _opencv(dithered), atol=0.02)
    assert np.abs(loss_xy - np.column_stack([sample.events.x, sample.events.y])[keep]).max() > 0.6


def test_augmentations_keep_each_loss_event_on_its_own_sensor_pixel(sequence):
    """Mirrored: each loss event is the mirror image of its sensor pixel dithered and mapped through the lens (the
    mirrored sensor seen through the mirrored lens); time reversed: its sensor pixels reversed with the events."""
    path, yaml, _ = sequence
    dataset = H5WindowDataset([{"path": str(path), "calib": str(yaml)}], window_us=100_000, max_events=400,
                              min_events=10)
    sample = dataset.sample(0)
    from learned.data import to_item

    for augmented, mirrored in ((flip_horizontal(sample), True), (reverse_time(sample), False),
                                (flip_horizontal(flip_horizontal(sample)), False)):
        item = to_item(augmented, max_events=400, seed=3, pixels=augmented.pixels, sensor=augmented.sensor)
        keep, dither = _drawn(3, len(sample.events), 400)
        order = np.arange(len(sample.events))[::-1] if augmented.events.t[0] != sample.events.t[0] else \
            np.arange(len(sample.events))
        sensor = sample.sensor.pixels[order][keep]
        if mirrored:   # dithered on the mirrored sensor: x + u there is x - u on the sensor
            expected = _opencv(sensor + dither * [-1, 1]) * [-1, 1] + [W - 1, 0]
        else:
            expected = _opencv(sensor + dither)
        n = int(item["valid"].sum())
        np.testing.assert_allclose(np.column_stack([item["x"][:n].numpy(), item["y"][:n].numpy()]), expected,
                                   atol=1e-3)


def test_resume_refuses_a_calibration_file_changed_under_the_same_path(sequence, tiny_checkpoint, tmp_path, capsys):
    """--resume compared an entry's calib / rectify_map as typed paths: a cam_to_cam.yaml edited (camRect0's cx
    moved 0.3 px) after the checkpoint trained on as if nothing changed (exit 0). The checkpoint records their SHA-256:
    refused in one line naming the file; restored, the run resumes."""
    import json

    from conftest import one_line_error
    from learned.checkpoint import load_checkpoint
    from learned.train import main as train_main

    path, yaml, _ = sequence
    table = path.parent / "rectify_map.h5"
    out = tmp_path / "run"
    entry = {"path": str(path), "calib": str(yaml)}

    def run(steps: int, *flags: str, entry=entry) -> list[str]:
        return ["--mode", "finetune", "--no-progress", *flags, f"data.files=[{json.dumps(entry)}]",
                "data.window_us=50000", "data.max_events=300", "train.batch_size=2", f"train.steps={steps}",
                "train.checkpoint_every=2", "train.log_every=1", f"train.out={out}", f"train.teacher={tiny_checkpoint}"]

    assert train_main(run(2)) == 0
    assert load_checkpoint(out / "last.pt")["data_order"]["calibrations"][0]["rectify_map"] is None
    original = yaml.read_text()
    yaml.write_text(original.replace(f"{K_RECT[0, 2]}, {K_RECT[1, 2]}", f"{K_RECT[0, 2] + 0.3}, {K_RECT[1, 2]}"))
    capsys.readouterr()
    status, err = one_line_error(lambda: train_main(run(4, "--resume")), capsys)
    assert status == 2 and "trained with other calibration files" in err and f"data.files[0].calib {yaml}" in err, err
    assert load_checkpoint(out / "last.pt")["step"] == 2
    yaml.write_text(original)                       # restored: the same bytes, resumes
    assert train_main(run(4, "--resume")) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 4
    out = tmp_path / "mapped"                        # a rectify_map entry: its map's bytes are checked the same way
    mapped = {"path": str(path), "K": [57.0, 57.0, 31.6, 23.3], "rectify_map": str(table)}
    assert train_main(run(2, entry=mapped)) == 0
    with h5py.File(table, "a") as file:
        file["rectify_map"][0, 0] = file["rectify_map"][0, 0] + 0.25
    capsys.readouterr()
    status, err = one_line_error(lambda: train_main(run(4, "--resume", entry=mapped)), capsys)
    assert status == 2 and f"data.files[0].rectify_map {table}" in err, err


def test_resume_compares_the_calibration_files_not_their_spelling(sequence, tiny_checkpoint, tmp_path, monkeypatch,
                                                                  capsys):
    """An entry's calib typed "calibration/cam_to_cam.yaml" and resumed as "./calibration/cam_to_cam.yaml" or by its
    absolute path names the same file: it resumes (it was refused, compared as typed, as the data files' paths were
    before). Another folder's file of that relative name: refused, naming both absolute paths."""
    import json
    import shutil

    from conftest import one_line_error
    from learned.checkpoint import load_checkpoint
    from learned.train import main as train_main

    path, yaml, _ = sequence
    out = tmp_path / "run"
    monkeypatch.chdir(yaml.parent.parent)

    def run(steps: int, calib: str, *flags: str) -> list[str]:
        entry = {"path": str(path), "calib": calib}
        return ["--mode", "finetune", "--no-progress", *flags, f"data.files=[{json.dumps(entry)}]",
                "data.window_us=50000", "data.max_events=300", "train.batch_size=2", f"train.steps={steps}",
                "train.checkpoint_every=1", "train.log_every=1", f"train.out={out}", f"train.teacher={tiny_checkpoint}"]

    assert train_main(run(1, "calibration/cam_to_cam.yaml")) == 0
    for steps, spelling in ((2, "./calibration/cam_to_cam.yaml"), (3, str(yaml))):
        assert train_main(run(steps, spelling, "--resume")) == 0, spelling
        assert load_checkpoint(out / "last.pt")["step"] == steps
    other = tmp_path / "elsewhere"
    (other / "calibration").mkdir(parents=True)
    shutil.copyfile(yaml, other / "calibration" / "cam_to_cam.yaml")
    monkeypatch.chdir(other)
    capsys.readouterr()
    status, err = one_line_error(lambda: train_main(run(4, "calibration/cam_to_cam.yaml", "--resume")), capsys)
    assert status == 2 and "was written with other settings" in err and str(yaml) in err, err
    from learned.train import config_differences, resolved_paths

    def config(calib: str):
        entry = json.dumps({"path": str(path), "calib": calib})
        return load_config(None, [f"data.files=[{entry}]", f"train.teacher={tiny_checkpoint}"], mode="finetune")

    typed, dotted = config("calibration/cam_to_cam.yaml"), config("./calibration/cam_to_cam.yaml")
    recorded = resolved_paths(typed)
    assert config_differences(typed, dotted, recorded) == []
    del recorded["data.calibrations"]                # a checkpoint of an earlier version: compared as typed
    assert [d.split("=")[0] for d in config_differences(typed, dotted, recorded)] == ["data.files"]


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


def test_an_ecd_calib_txt_of_another_sensor_is_refused_by_the_dataset(tmp_path):
    """``H5WindowDataset`` takes an entry's ECD ``calib.txt`` (no size stated) as the command line does: beside
    ECD frames of 240x180 (images.txt) for events of a 64x48 sensor it is refused naming both sizes (was: the
    DAVIS240C's K and lens applied to them without a word); beside frames of the events' size it is read."""
    from cmax.io import write_h5

    rng = np.random.default_rng(3)
    events = Events(rng.integers(0, 64, 4000), rng.integers(0, 48, 4000), np.sort(rng.integers(0, 400_000, 4000)),
                    rng.integers(0, 2, 4000), 64, 48)
    path = write_h5(tmp_path / "ev.h5", events)
    sequence = tmp_path / "slider_depth"
    (sequence / "images").mkdir(parents=True)
    (sequence / "calib.txt").write_text("60 60 32 24 -0.37 0.15 0 0 0\n")
    (sequence / "images.txt").write_text("0.000000000 images/frame_00000000.png\n")
    entry = [{"path": str(path), "calib": str(sequence / "calib.txt")}]
    assert cv2.imwrite(str(sequence / "images" / "frame_00000000.png"), np.zeros((180, 240), np.uint8))
    with pytest.raises(ValueError, match=r"calib.txt states no sensor size, but the frames of its sequence .* are "
                                         r"240x180: it calibrates a 240x180 sensor, the events of .*ev.h5 come from a "
                                         r"64x48 one"):
        H5WindowDataset(entry, window_us=100_000, min_events=10)
    assert cv2.imwrite(str(sequence / "images" / "frame_00000000.png"), np.zeros((48, 64), np.uint8))
    assert len(H5WindowDataset(entry, window_us=100_000, min_events=10)) > 0


def test_raw_dsec_events_are_refused_alike_by_fit_emvs_depth_and_train_unless_as_recorded(sequence, tmp_path,
                                                                                            capsys):
    """One policy for raw DSEC events (rectify_map.h5 beside them) without a calibration: cmax fit and cmax emvs
    refuse them as cmax depth does, in the same words (were: a note, then the raw events fitted as a pinhole's,
    exit 0 or 1); learned.train names its entry's keys. --as-recorded (an entry's "as_recorded": true) takes
    them as recorded: the run goes on past the check."""
    path, yaml, _ = sequence
    errors = {}
    for command in ("fit", "emvs", "depth"):
        status = cmax_main([command, str(path), "-o", str(tmp_path / command), "--K", "57,57,31.6,23.3", "--size",
                            f"{W}x{H}", "--quiet"])
        err = capsys.readouterr().err
        assert status == 2 and err.count("\n") == 1 and not (tmp_path / command).exists(), err
        errors[command] = err.split(": error: ", 1)[1]
    assert errors["fit"] == errors["emvs"] == errors["depth"]
    assert errors["fit"].startswith(f"DSEC's {path.parent / 'rectify_map.h5'} lies beside {path}, so its events are "
                                    "raw") and f"--calib {yaml.resolve()}" in errors["fit"]
    assert "or --as-recorded to take them as recorded" in errors["fit"]
    with pytest.raises(ValueError, match=r'rectify_map.h5 lies beside .* or "as_recorded": true in the entry'):
        H5WindowDataset([{"path": str(path), "K": [57.0, 57.0, 31.6, 23.3]}])
    assert len(H5WindowDataset([{"path": str(write_h5_sized(path)), "K": [57.0, 57.0, 31.6, 23.3],
                                 "as_recorded": True}], window_us=100_000, min_events=10)) == 3
    status = cmax_main(["fit", str(path), "-o", str(tmp_path / "fit"), "--K", "57,57,31.6,23.3", "--size", f"{W}x{H}",
                        "--quiet", "--as-recorded", "--window-ms", "100"])
    err = capsys.readouterr().err
    assert status in (0, 1) and "rectify_map.h5 lies beside" not in err and (tmp_path / "fit" / "summary.json").is_file(), err


def write_h5_sized(path: Path) -> Path:
    """A copy of DSEC's original ``path`` with its size stored, in the same folder (beside rectify_map.h5)."""
    from cmax.io import read, write_h5

    return write_h5(path.parent / "events_sized.h5", read(path, width=W, height=H))
