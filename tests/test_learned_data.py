"""learned.data: windows of h5 files with ground truth, and the consistency of each augmentation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.loss import ContrastLoss, EventBatch
from cmax.representations import voxel_grid
from benchmarks.synthetic_windows import make_window
from learned.data import H5WindowDataset, Sample, collate, flip_horizontal, flip_polarity, reverse_time, to_item


@pytest.fixture(scope="module")
def window() -> Sample:
    w = make_window("indoor_flying", 3, width=120, height=90, focal=90.0, duration_s=0.1, max_frames=60)
    return Sample(w.events, w.K, w.depth, w.twist, 0, int(w.events.t[-1]) + 1)


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("slider", seed=2, width=48, height=36, duration_s=1.0, texture_size=64)
    sequence = simulate_scene(scene, 0.5, EventSimulator(**{**scene.recommended_simulator, "seed": 2}),
                              depth_rate_hz=20)
    return sequence.save(tmp_path_factory.mktemp("data") / "slider.h5"), sequence, scene


def _loss(sample: Sample, collapse_weight: float = 0.0) -> float:
    item = collate([to_item(sample, max_events=5000)])
    events = EventBatch.from_padded(item["x"].double(), item["y"].double(), item["t"].double(),
                                    item["polarity"].double(), item["valid"], item["duration_s"].double(),
                                    width=sample.events.width, height=sample.events.height)
    rho = item["inverse_depth"].double()
    return float(ContrastLoss(collapse_weight=collapse_weight)(events, rho, item["twist"].double()[:1] * 0
                                                               + torch.as_tensor(sample.twist)[None], item["K"].double()))


def test_flip_horizontal_is_consistent(window):
    flipped = flip_horizontal(window)
    np.testing.assert_array_equal(flipped.depth, window.depth[:, ::-1])
    np.testing.assert_array_equal(voxel_grid(flipped.events, 5), voxel_grid(window.events, 5)[:, :, ::-1])
    assert flipped.K[0, 2] == pytest.approx(window.events.width - 1 - window.K[0, 2])
    np.testing.assert_allclose(flipped.twist, window.twist * [-1, 1, 1, 1, -1, -1])
    twice = flip_horizontal(flipped)
    np.testing.assert_array_equal(twice.events.x, window.events.x)
    np.testing.assert_allclose(twice.twist, window.twist)


def test_flipped_twist_explains_flipped_events_as_well(window):
    """The mirrored twist with the mirrored depth and K sharpens the mirrored events exactly as much.

    Both windows are prepared with the same dither only up to its sign, so compare
    against the unflipped loss with a tolerance of the dither's effect, and check that the
    unmirrored twist is clearly worse on the mirrored events.
    """
    flipped = flip_horizontal(window)
    original, mirrored = _loss(window), _loss(flipped)
    assert mirrored == pytest.approx(original, rel=0.01)
    wrong = Sample(flipped.events, flipped.K, flipped.depth, window.twist, 0, flipped.t1_us)
    assert _loss(wrong) > mirrored + 0.01


def test_polarity_flip_negates_the_volume_and_keeps_the_rest(window):
    flipped = flip_polarity(window)
    np.testing.assert_array_equal(voxel_grid(flipped.events, 5), -voxel_grid(window.events, 5))
    np.testing.assert_array_equal(flipped.depth, window.depth)
    assert _loss(flipped) == pytest.approx(_loss(window), rel=1e-9)


def test_time_reversal_reverses_bins_and_negates_twist(window):
    reversed_ = reverse_time(window)
    ev, rev = window.events, reversed_.events
    assert np.all(np.diff(rev.t) >= 0)
    # the volume's bins are normalised by the first and last event: reversed in time and negated in polarity
    np.testing.assert_allclose(voxel_grid(rev, 5), -voxel_grid(ev, 5)[::-1], atol=1e-5)
    np.testing.assert_allclose(reversed_.twist, -window.twist)
    assert _loss(reversed_, 0.1) == pytest.approx(_loss(window, 0.1), rel=0.01)
    assert _loss(Sample(rev, window.K, window.depth, window.twist, 0, window.t1_us)) > _loss(reversed_) + 0.01


def _training_loss(sample: Sample, twist) -> float:
    """The contrast term learned.train minimises (cmax.contrast.SHARED_OBJECTIVE on to_item's events, the
    speed anchor off) at ``sample``'s true inverse depth and ``twist``."""
    import dataclasses

    from cmax.contrast import SHARED_OBJECTIVE, DepthMotion
    from learned.train import _events

    item = collate([to_item(sample, max_events=20000)])
    events = dataclasses.replace(_events(item, sample.events.width, sample.events.height), speed=None)
    rho = item["inverse_depth"].clamp(min=1e-3)
    return float(SHARED_OBJECTIVE(events, DepthMotion(rho, torch.as_tensor(twist, dtype=torch.float32)[None])))


@pytest.mark.parametrize("augmentation, mirror", [(flip_horizontal, [-1, 1, 1, 1, -1, -1]),
                                                  (reverse_time, [-1, -1, -1, -1, -1, -1]),
                                                  (flip_polarity, [1, 1, 1, 1, 1, 1])])
def test_each_augmentation_moves_the_training_losss_minimum_to_the_closed_form_twist(window, augmentation, mirror):
    """The shared objective (the loss a finetune or student trains on, not the older ContrastLoss of the tests
    above) scores the augmented window at the closed-form transformed twist (the flip: v_x, omega_y, omega_z
    negated; time reversal: the twist negated; polarity: unchanged) as it scores the window at its true twist,
    and clearly better than at the untransformed and at the opposite twist: no augmentation teaches a sign."""
    transformed = window.twist * np.asarray(mirror, float)
    augmented = augmentation(window)
    np.testing.assert_allclose(augmented.twist, transformed)
    at_truth = _training_loss(augmented, transformed)
    assert at_truth == pytest.approx(_training_loss(window, window.twist), rel=0.02)
    assert at_truth + 0.03 < _training_loss(augmented, -transformed)
    if augmentation is not flip_polarity:
        assert at_truth + 0.03 < _training_loss(augmented, window.twist)


def test_dataset_windows_are_centred_on_ground_truth(scene_file):
    path, sequence, scene = scene_file
    ds = H5WindowDataset([path], window_us=100_000, max_events=500)
    assert len(ds) > 0
    for i in range(len(ds)):
        sample = ds.sample(i)
        middle = (sample.t0_us + sample.t1_us) // 2
        k = int(np.argmin(np.abs(sequence.depth_t_us - middle)))
        assert sequence.depth_t_us[k] == middle
        np.testing.assert_array_equal(sample.depth, sequence.depth[k])
        np.testing.assert_allclose(sample.twist, scene.twist(middle * 1e-6), atol=1e-9)
    item = ds[0]
    assert item["volume"].shape == (5, 36, 48) and item["x"].shape == (500,)
    assert int(item["valid"].sum()) == min(500, len(ds.sample(0).events))
    mask = item["depth_mask"][0].numpy()
    np.testing.assert_allclose(item["inverse_depth"][0].numpy()[mask], 1.0 / ds.sample(0).depth[mask], rtol=1e-6)


def test_dataset_rejects_bad_input(scene_file, tmp_path):
    path, sequence, _ = scene_file
    from cmax.io import write_h5

    bare = write_h5(tmp_path / "bare.h5", sequence.events)
    with pytest.raises(ValueError, match="K"):
        H5WindowDataset([bare])
    ok = H5WindowDataset([{"path": bare, "K": [40.0, 40.0, 23.5, 17.5]}], window_us=100_000, max_events=100)
    assert ok.sample(0).depth is None and ok[0]["has_twist"].item() is False
    with pytest.raises(ValueError, match="files"):
        H5WindowDataset([])
    with pytest.raises(TypeError, match="data file"):
        H5WindowDataset([3])


def _copy_without(path, tmp_path, name: str, *keys: str):
    import shutil

    import h5py

    copy = shutil.copy(path, tmp_path / name)
    with h5py.File(copy, "a") as file:
        for key in keys:
            del file[key]
    return copy


def test_a_gt_group_with_part_of_the_ground_truth_is_read_as_far_as_it_goes(scene_file, tmp_path):
    """A user's own labelled file need not hold everything cmax scene writes. Was a KeyError traceback
    ("object 'depth_t' doesn't exist" / "'poses_t' doesn't exist") from learned.train and learned.evaluate."""
    path, sequence, _ = scene_file
    calibrated = _copy_without(path, tmp_path, "k_only.h5", "gt/depth", "gt/depth_t", "gt/poses", "gt/poses_t",
                               "gt/twists")
    ds = H5WindowDataset([calibrated], window_us=100_000, max_events=100)   # gt/K alone: its calibration
    assert len(ds) > 0 and ds.sample(0).depth is None and ds.sample(0).twist is None
    assert (ds.sample(0).t0_us - ds.spans[0][0]) % 100_000 == 0   # consecutive from the first event, as unlabelled
    np.testing.assert_array_equal(ds.sample(0).K, sequence.K)
    no_motion = _copy_without(path, tmp_path, "no_poses.h5", "gt/poses", "gt/poses_t", "gt/twists")
    ds = H5WindowDataset([no_motion], window_us=100_000, max_events=100)   # depth without twists
    labelled = H5WindowDataset([path], window_us=100_000, max_events=100)
    assert len(ds) == len(labelled) > 0
    np.testing.assert_array_equal(ds.sample(0).depth, labelled.sample(0).depth)
    assert ds.sample(0).twist is None and ds[0]["has_twist"].item() is False
    no_K = _copy_without(path, tmp_path, "no_k.h5", "gt/K")
    with pytest.raises(ValueError, match="no_k.h5 holds gt/depth but no gt/K"):
        H5WindowDataset([no_K], window_us=100_000)


def _rewritten(path, tmp_path, name: str, key: str, change):
    """A copy of ``path`` named ``name`` whose dataset ``key`` is ``change(its values)``."""
    import shutil

    import h5py

    copy = shutil.copy(path, tmp_path / name)
    with h5py.File(copy, "a") as file:
        values = change(file[key][:])
        del file[key]
        file[key] = values
    return copy


def _with_nan_row(values, row: int = 5):
    values = values.astype(np.float64)
    values[row] = np.nan
    return values


@pytest.mark.parametrize("name, key, change, message", [
    ("few_maps.h5", "gt/depth", lambda d: d[:-3], r"few_maps.h5: gt/depth holds (\d+) depth maps, gt/depth_t (\d+) "),
    ("small_maps.h5", "gt/depth", lambda d: d[:, :30, :40],
     "small_maps.h5: gt/depth holds maps of 40x30 pixels, its events come from a 48x36 sensor"),
    ("nan_twist.h5", "gt/twists", _with_nan_row, "nan_twist.h5: gt/twists holds NaN or infinite values in 1 of its"),
    ("short_poses.h5", "gt/poses_t", lambda t: t[:-1], r"short_poses.h5: gt/twists must be \(M, 6\)"),
], ids=["fewer_maps_than_times", "maps_of_another_size", "nan_twist", "fewer_times_than_twists"])
def test_ground_truth_whose_parts_do_not_fit_is_refused_naming_the_file(scene_file, tmp_path, capsys, name, key,
                                                                          change, message):
    """A user's labelled h5 with fewer depth maps than gt/depth_t times was an IndexError traceback (learned.train
    and learned.evaluate); maps of another size than the sensor failed at the first step in the loss's words
    (`pred, gt and mask must share one shape`), naming no file; a NaN twist stopped training at step 1 as a
    diverged run (`a lower train.lr or gradient clipping may keep the run stable`) and learned.evaluate with
    `v_gt must be finite`. Each is now refused when the file is opened, one line naming it, in training
    (a labelled file, or a file of known speed) and in evaluation."""
    import re

    from conftest import one_line_error

    from learned.evaluate import evaluate_files
    from learned.train import main

    path, sequence, _ = scene_file
    bad = _rewritten(path, tmp_path, name, key, change)
    with pytest.raises(ValueError, match=message) as refused:
        H5WindowDataset([bad], window_us=100_000)
    if name == "few_maps.h5":
        maps, times = map(int, re.search(message, str(refused.value)).groups())
        assert (maps, times) == (len(sequence.depth_t_us) - 3, len(sequence.depth_t_us))
    with pytest.raises(ValueError, match=message):
        evaluate_files(_tiny_checkpoint(tmp_path), [bad])
    status, err = one_line_error(lambda: main(["--mode", "teacher", "--no-progress", f'data.files=["{bad}"]',
                                               "model.width=4", "model.levels=2", "train.steps=1",
                                               f"train.out={tmp_path / 'run'}"]), capsys)
    assert status == 2 and re.search(message, err), err
    assert not (tmp_path / "run").exists()
    if key == "gt/twists":   # the speed of an unlabelled file comes from its twists too
        with pytest.raises(ValueError, match=message):
            H5WindowDataset([{"path": str(bad), "use_gt": False, "known_speed": True}], window_us=100_000)


def _tiny_checkpoint(tmp_path):
    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config, DataConfig
    from learned.model import DepthPoseNet, ModelConfig

    config = Config(model=ModelConfig(width=4, levels=2), data=DataConfig(window_us=100_000))
    checkpoint = tmp_path / "tiny.pt"
    save_checkpoint(checkpoint, {"model": DepthPoseNet(config.model).state_dict(), "optimizer": {}, "step": 0,
                                 "config": config.to_dict(), "rng": rng_state()})
    return checkpoint


def test_evaluate_scores_the_depth_of_a_file_without_twists(scene_file, tmp_path):
    """learned.evaluate on a file with depth but no poses: depth metrics, no motion metrics; without gt/K: one
    line naming the file."""
    from learned.evaluate import evaluate_files

    path, _, _ = scene_file
    checkpoint = _tiny_checkpoint(tmp_path)
    no_motion = _copy_without(path, tmp_path, "no_poses.h5", "gt/poses", "gt/poses_t", "gt/twists")
    (report,), (full,) = evaluate_files(checkpoint, [no_motion]), evaluate_files(checkpoint, [path])
    assert report.motion is None and full.motion is not None
    assert report.windows == full.windows and report.depth == full.depth
    with pytest.raises(ValueError, match="no_k.h5 holds gt/depth but no gt/K"):
        evaluate_files(checkpoint, [_copy_without(path, tmp_path, "no_k.h5", "gt/K")])


@pytest.mark.parametrize("scale", [1000.0, float("nan")])
def test_evaluate_says_why_a_file_has_no_depth_metric(scene_file, tmp_path, scale):
    """A user's gt/depth in millimetres (all beyond the far limit) or all NaN: no valid pixel. Was: `abs_mean nan m
    abs_rel nan ...` printed as a result, without a word; now a note names the rule and the depths' span."""
    import shutil

    import h5py

    from learned.evaluate import evaluate_files

    path, sequence, _ = scene_file
    copy = shutil.copy(path, tmp_path / "mm.h5")
    with h5py.File(copy, "a") as file:
        file["gt/depth"][...] = file["gt/depth"][()] * scale
    checkpoint = _tiny_checkpoint(tmp_path)
    (report,) = evaluate_files(checkpoint, [copy])
    assert np.isnan(report.depth.abs_rel)
    (note,) = [n for n in report.notes if "no pixel of its ground-truth depth" in n]
    if scale == 1000.0:
        import re

        finite = sequence.depth[np.isfinite(sequence.depth)] * scale
        low, high = map(float, re.search(r"span (\S+) to (\S+)\)", note).groups())
        assert finite.min() * 0.999 <= low <= high <= finite.max() * 1.001 and "metres" in note
    else:
        assert "NaN or infinite everywhere" in note
    (report,) = evaluate_files(checkpoint, [path])
    assert np.isfinite(report.depth.abs_rel) and not any("no pixel" in n for n in report.notes)


def test_a_file_of_signed_polarities_is_read_as_its_data_files_entry_states(scene_file, tmp_path):
    """An h5 file whose events/p holds -1/+1 (a user's own writer): read with "polarity": "signed" in its entry,
    its windows equal those of the 0/1 file. Was: the reader's refusal advised `pass polarity='signed' (cmax:
    --polarity signed)`, which neither data.files nor learned.train could take: such a file could not be used."""
    import shutil

    import h5py

    from cmax.io import FormatError
    from learned.config import load_config

    path, _, _ = scene_file
    signed = shutil.copy(path, tmp_path / "signed.h5")
    with h5py.File(signed, "a") as file:
        p = file["events/p"][:].astype(np.int8)
        del file["events/p"]
        file["events/p"] = 2 * p - 1
    original = H5WindowDataset([path], window_us=100_000, max_events=300)
    read = H5WindowDataset([{"path": str(signed), "polarity": "signed"}], window_us=100_000, max_events=300)
    assert len(read) == len(original) > 0
    for key, value in original[0].items():
        torch.testing.assert_close(read[0][key], value, rtol=0, atol=0, equal_nan=True)
    with pytest.raises(FormatError, match='-1/\\+1, not the "01" encoding .* add "polarity": "signed" to its entry'):
        H5WindowDataset([signed], window_us=100_000)
    with pytest.raises(FormatError, match='0/1, not the "signed" encoding .* add "polarity": "01"'):
        H5WindowDataset([{"path": str(path), "polarity": "signed"}], window_us=100_000)
    with pytest.raises(ValueError, match=r'data.files\[0\].polarity must be "01" .* or "signed"'):
        load_config(None, [f'data.files=[{{"path": "{signed}", "polarity": "pm1"}}]'], mode="teacher")


def test_a_K_of_another_sensor_size_or_no_camera_is_refused_naming_the_file(scene_file, tmp_path):
    """The calibration of 120x90 frames (a conversion at --size 48x36): its principal point lies off the 48x36
    sensor; refused before any window is read (was: trained on without a word). A focal
    length of 0 is named with the file (was: a bare 'K must have positive focal lengths' after training began)."""
    path, sequence, _ = scene_file
    from cmax.io import write_h5

    bare = write_h5(tmp_path / "bare.h5", sequence.events)
    with pytest.raises(ValueError, match=r"bare.h5: K's principal point \(59.5, 44.5\) lies outside the 48x36 image"):
        H5WindowDataset([{"path": bare, "K": [100.0, 100.0, 59.5, 44.5]}], window_us=100_000)
    with pytest.raises(ValueError, match=r"bare.h5: K must have positive focal lengths"):
        H5WindowDataset([{"path": bare, "K": [0.0, 0.0, 23.5, 17.5]}], window_us=100_000)
    ok = H5WindowDataset([{"path": bare, "K": [40.0, 40.0, 23.5, 17.5]}], window_us=100_000)
    np.testing.assert_array_equal(ok.specs[0].K, [[40, 0, 23.5], [0, 40, 17.5], [0, 0, 1]])


@pytest.mark.parametrize("K", [[["fx", 0, 23.5], [0, 40, 17.5], [0, 0, 1]], ["40", "40", "cx", "cy"],
                               [40.0, 40.0, 23.5], [[40.0, 0, 23.5], [0, 40.0, 17.5]]])
def test_a_data_files_entry_s_K_is_refused_as_intrinsics_matrix_refuses_it(scene_file, K):
    """A ``data.files`` entry's K holding text or of the wrong size, on a file with ground truth: the message of
    :func:`cmax.camera.intrinsics_matrix` naming the file (was: numpy's ``could not convert string to float`` or
    ``operands could not be broadcast`` from the comparison with gt/K)."""
    from cmax.camera import intrinsics_matrix

    path, _, _ = scene_file
    with pytest.raises((TypeError, ValueError)) as expected:
        intrinsics_matrix(K, f"{path}: K")
    with pytest.raises(type(expected.value)) as raised:
        H5WindowDataset([{"path": str(path), "K": K}], window_us=100_000)
    assert str(raised.value) == str(expected.value)


def test_an_event_file_of_another_format_is_refused_with_its_conversion(scene_file, tmp_path):
    """A ``.npy`` (or ``.raw``, ``.aedat4``) in ``data.files``: the error gives the conversion, which works."""
    import cmax
    from cmax.io import FormatError

    _, sequence, _ = scene_file
    np.save(tmp_path / "tonic.npy", sequence.events.to_structured())
    with pytest.raises(FormatError, match=r"convert it once with cmax.io.write_h5\('events.h5', "
                                          r"cmax.io.read\('.*tonic.npy'\[, width=, height=\]\)\)"):
        H5WindowDataset([tmp_path / "tonic.npy"])
    converted = cmax.io.write_h5(tmp_path / "events.h5", cmax.io.read(tmp_path / "tonic.npy", width=48, height=36))
    dataset = H5WindowDataset([{"path": converted, "K": [40.0, 40.0, 23.5, 17.5]}], window_us=100_000,
                              max_events=100)
    assert len(dataset) > 0 and dataset.sample(0).events == sequence.events.slice_time(
        dataset.sample(0).t0_us, dataset.sample(0).t1_us)


@pytest.mark.filterwarnings("ignore:.*MVSECDataset without calib:UserWarning")   # calib=: its own tests below
def test_mvsec_dataset_reads_events_and_depth(tmp_path):
    import h5py

    from learned.data import MVSECDataset

    rng = np.random.default_rng(0)
    n = 4000
    t = np.sort(rng.uniform(100.0, 100.5, n))
    table = np.column_stack([rng.integers(0, 346, n), rng.integers(0, 260, n), t, rng.choice([-1.0, 1.0], n)])
    with h5py.File(tmp_path / "x_data.hdf5", "w") as f:
        f["davis/left/events"] = table
    depth = rng.uniform(1, 5, (2, 260, 346)).astype(np.float32)
    depth[:, :10] = np.nan
    with h5py.File(tmp_path / "x_gt.hdf5", "w") as f:
        f["davis/left/depth_image_rect"] = depth
        f["davis/left/depth_image_rect_ts"] = np.array([100.2, 100.3])
    K = np.array([[226.0, 0, 173.0], [0, 226.0, 130.0], [0, 0, 1]])
    ds = MVSECDataset(tmp_path / "x_data.hdf5", K, gt_file=tmp_path / "x_gt.hdf5", window_us=100_000, max_events=5000)
    assert len(ds) == 2
    item = ds[1]
    inside = (table[:, 2] * 1e6 >= 100.25e6 - 1) & (table[:, 2] * 1e6 < 100.35e6 + 1)
    assert abs(int(item["valid"].sum()) - int(inside.sum())) <= 2
    mask = item["depth_mask"][0].numpy()
    assert not mask[:10].any() and mask[10:].all()
    np.testing.assert_allclose(item["inverse_depth"][0].numpy()[mask], 1.0 / depth[1][mask], rtol=1e-6)
    events = ds._read(tmp_path / "x_data.hdf5", t0_us=int(ds.middles[1]) - 50_000, t1_us=int(ds.middles[1]) + 50_000)
    # each event's weight is split over the bins: the volume sums to the sum of signed polarities
    assert item["volume"].sum().item() == pytest.approx(float((2 * events.p.astype(int) - 1).sum()), abs=1e-3)
    with pytest.raises(ValueError, match="K"):
        MVSECDataset(tmp_path / "x_data.hdf5", np.eye(2), gt_file=tmp_path / "x_gt.hdf5")


def test_a_file_simulated_at_another_size_without_K_says_how_its_frames_K_scales(tmp_path):
    """A conversion at --size: the refusal for its missing K gives the scale (was: only 'give its intrinsics')."""
    cv2 = pytest.importorskip("cv2")
    from cmax.cli import main

    y, x = np.mgrid[0:32, 0:48]
    video = cv2.VideoWriter(str(tmp_path / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25, (48, 32))
    for k in range(8):
        frame = (128 + 90 * np.sin(0.3 * (x - 2 * k)) * np.cos(0.2 * y)).astype(np.uint8)
        video.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    video.release()
    out = tmp_path / "clip.h5"
    assert main(["simulate", str(tmp_path / "clip.avi"), "-o", str(out), "--no-adaptive", "--quiet",
                 "--size", "24x16"]) == 0
    with pytest.raises(ValueError, match=r"has no gt/K: .*was simulated from 48x32 frames resized to 24x16 \(--size\): "
                                         r"a K of those frames scales to fx\*0.5, fy\*0.5"):
        H5WindowDataset([out], window_us=100_000)


def test_a_data_set_of_many_files_keeps_only_a_few_open(tmp_path, monkeypatch):
    """Every file sampled stayed open (about 4 MB of h5py caches and a descriptor each): over 300 files an epoch
    grew by 1 GB and, under `ulimit -n 200`, died with `FormatError: ... is not a readable HDF5 file (... Too many
    open files)`. At most MAX_OPEN_FILES stay open, the least recently read closed; the windows are unchanged."""
    import learned.data
    from cmax.events import Events
    from cmax.io import write_h5

    rng = np.random.default_rng(0)
    files = []
    for k in range(5):
        t = np.sort(rng.integers(0, 400_000, 3000))
        files.append({"path": write_h5(tmp_path / f"f{k}.h5", Events(rng.integers(0, 32, 3000), rng.integers(0, 24, 3000),
                                                                    t, rng.integers(0, 2, 3000), 32, 24)),
                      "K": [30.0, 30.0, 16.0, 12.0]})
    expected = [ds.sample(i).events for ds in [H5WindowDataset(files, window_us=100_000, max_events=500)]
                for i in range(len(ds))]
    monkeypatch.setattr(learned.data, "MAX_OPEN_FILES", 2)
    ds = H5WindowDataset(files, window_us=100_000, max_events=500)
    assert len(ds) == len(expected) >= 10
    for i in [*range(len(ds)), *reversed(range(len(ds)))]:
        events = ds.sample(i).events
        assert len(ds._readers) <= 2, sorted(ds._readers)
        np.testing.assert_array_equal(events.t, expected[i].t)
        np.testing.assert_array_equal(events.x, expected[i].x)
    closed = [r for r in [*ds._readers.values()] if not r.file.id.valid]
    assert not closed                                            # the readers kept are open ones


@pytest.mark.filterwarnings("ignore:.*MVSECDataset without calib:UserWarning")   # calib=: its own tests below
def test_mvsec_dataset_reads_one_depth_map_per_window_not_the_whole_file(tmp_path):
    """MVSECDataset loaded every depth map of the gt file at construction, twice (`[:]` then `astype`): 2.4 GB
    peak for 3,000 maps of 346x260, ~9 GB for outdoor_day2's ~12,000; without a gt file it read every event to
    learn the first and last times. Here 100 maps (36 MB) and 400,000 events (12.8 MB): a few MB are allocated."""
    import tracemalloc

    import h5py

    from learned.data import MVSECDataset

    rng = np.random.default_rng(1)
    n, maps = 400_000, 100
    t = np.sort(rng.uniform(100.0, 110.0, n))
    with h5py.File(tmp_path / "x_data.hdf5", "w") as f:
        f["davis/left/events"] = np.column_stack([rng.integers(0, 346, n), rng.integers(0, 260, n), t,
                                                  rng.choice([-1.0, 1.0], n)])
    depth = rng.uniform(1, 5, (maps, 260, 346)).astype(np.float32)
    with h5py.File(tmp_path / "x_gt.hdf5", "w") as f:
        f.create_dataset("davis/left/depth_image_rect", data=depth, chunks=(1, 260, 346))
        f["davis/left/depth_image_rect_ts"] = np.linspace(100.2, 109.8, maps)
    K = np.array([[226.0, 0, 173.0], [0, 226.0, 130.0], [0, 0, 1]])
    for gt in (tmp_path / "x_gt.hdf5", None):
        tracemalloc.start()
        try:
            ds = MVSECDataset(tmp_path / "x_data.hdf5", K, gt_file=gt, window_us=50_000, max_events=2000)
            item = ds[7]
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 8e6, (gt, peak)                              # the whole depth: 36 MB; the events 12.8 MB
        if gt is not None:
            assert len(ds) == maps
            mask = item["depth_mask"][0].numpy()
            np.testing.assert_allclose(item["inverse_depth"][0].numpy()[mask], 1.0 / depth[7][mask], rtol=1e-6)
        else:                                                       # consecutive windows over the events' span
            assert len(ds) == len(np.arange(round(t[0] * 1e6) + 25_000, round(t[-1] * 1e6) - 25_000, 50_000))


def test_a_folder_in_data_files_is_named_as_a_folder_with_its_h5_files(scene_file, tmp_path):
    """The output folder of `cmax simulate FOLDER -o OUT` given as a data file was refused as 'no such event file:
    OUT', of a folder that exists. It is named as a folder, with the .h5 files in it to list instead."""
    import shutil

    path, _, _ = scene_file
    folder = tmp_path / "converted"
    folder.mkdir()
    with pytest.raises(ValueError, match=r"converted is a folder, not an event file: .* \(it holds no \.h5 file\)"):
        H5WindowDataset([folder], window_us=100_000)
    shutil.copyfile(path, folder / "a.h5")
    with pytest.raises(ValueError, match=r"converted is a folder, not an event file: data.files lists h5 files one "
                                         r"by one: the 1 \.h5 files in it are data.files=\[\".*converted/a.h5\"\]"):
        H5WindowDataset([{"path": str(folder), "K": [40.0, 40.0, 23.5, 17.5]}], window_us=100_000)
    assert len(H5WindowDataset([folder / "a.h5"], window_us=100_000)) > 0


@pytest.mark.filterwarnings("ignore:.*MVSECDataset without calib:UserWarning")   # calib=: its own tests below
def test_mvsec_dataset_refuses_a_gt_file_of_another_sequence_and_checks_K(tmp_path):
    """MVSECDataset with the gt file of another sequence (its depth times 100 s after the events) was built, then
    failed at its first window with 'the window [...) µs holds 0 events; need >= 2'; a K of another sensor
    (principal point off the 346x260 sensor) was taken without a word, and [fx, fy, cx, cy] was refused."""
    import h5py

    from learned.data import MVSECDataset

    rng = np.random.default_rng(0)
    n = 2000
    t = np.sort(rng.uniform(100.0, 100.5, n))
    with h5py.File(tmp_path / "x_data.hdf5", "w") as f:
        f["davis/left/events"] = np.column_stack([rng.integers(0, 346, n), rng.integers(0, 260, n), t,
                                                  rng.choice([-1.0, 1.0], n)])
    for name, times in (("other_gt.hdf5", [200.2, 200.3]), ("x_gt.hdf5", [100.2, 100.3])):
        with h5py.File(tmp_path / name, "w") as f:
            f["davis/left/depth_image_rect"] = np.full((2, 260, 346), 3.0, np.float32)
            f["davis/left/depth_image_rect_ts"] = np.array(times)
    K = [226.0, 226.0, 173.0, 130.0]
    with pytest.raises(ValueError, match=r"other_gt.hdf5: none of its 2 depth times \(200.200000 to 200.300000 s\) "
                                         r"lies within the events of .*x_data.hdf5 \(100.0\d+ to 100.4\d+ s\)"):
        MVSECDataset(tmp_path / "x_data.hdf5", K, gt_file=tmp_path / "other_gt.hdf5", window_us=100_000)
    with pytest.raises(ValueError, match=r"K's principal point \(640, 360\) lies outside the 346x260 image"):
        MVSECDataset(tmp_path / "x_data.hdf5", [900.0, 900.0, 640.0, 360.0], gt_file=tmp_path / "x_gt.hdf5")
    ds = MVSECDataset(tmp_path / "x_data.hdf5", K, gt_file=tmp_path / "x_gt.hdf5", window_us=100_000)
    np.testing.assert_array_equal(ds.K, [[226, 0, 173], [0, 226, 130], [0, 0, 1]])
    assert len(ds) == 2 and int(ds[0]["valid"].sum()) > 100


@pytest.mark.filterwarnings("ignore:.*MVSECDataset without calib:UserWarning")
def test_mvsec_dataset_refuses_a_bad_k_as_the_other_data_sets_do(tmp_path):
    """MVSECDataset built its K from [fx, fy, cx, cy] by hand: a K of 3 numbers gave 'K must be (3, 3) or [fx, fy,
    cx, cy], got shape (3,)' (no file named), one of text numpy's 'could not convert string to float'. Now each
    gives the message of cmax.camera.intrinsics_matrix / check_principal_point naming the file, as
    H5WindowDataset's data files do."""
    import h5py

    from cmax.camera import check_principal_point, intrinsics_matrix
    from learned.data import MVSECDataset

    rng = np.random.default_rng(0)
    n = 500
    data = tmp_path / "x_data.hdf5"
    with h5py.File(data, "w") as f:
        f["davis/left/events"] = np.column_stack([rng.integers(0, 346, n), rng.integers(0, 260, n),
                                                  np.sort(rng.uniform(100.0, 100.5, n)), rng.choice([-1.0, 1.0], n)])
    for K in ([226.0, 226.0, 173.0], [["fx", 0, 173.0], [0, 226.0, 130.0], [0, 0, 1]], [226.0, -226.0, 173.0, 130.0]):
        with pytest.raises((TypeError, ValueError)) as shared:
            intrinsics_matrix(K, f"{data}: K")
        with pytest.raises(shared.type) as raised:
            MVSECDataset(data, K)
        assert str(raised.value) == str(shared.value) and str(data) in str(raised.value)
    outside = [[226.0, 0, 640.0], [0, 226.0, 360.0], [0, 0, 1]]
    with pytest.raises(ValueError) as shared:
        check_principal_point(np.array(outside), 346, 260, f"{data}: K")
    with pytest.raises(ValueError) as raised:
        MVSECDataset(data, outside)
    assert str(raised.value) == str(shared.value)


from conftest import MVSEC_LEFT_CAMCHAIN as MVSEC_CAMCHAIN  # noqa: E402  (MVSEC's left camera)


def _fisheye_scene(tmp_path, rng, n=3000):
    """An MVSEC data file whose events are the sensor pixels of known 3-D points seen through the camchain's
    fisheye lens: ``(path, points (n, 3) [m] in the camera frame)``. Each event is put on an integer pixel and
    its point on that pixel's ray, found with the Kannala-Brandt formula written out and solved by bisection."""
    import h5py

    K = np.array([[226.38018519795807, 0.0, 173.6470807871759], [0.0, 226.15002947047415, 133.73271487507847],
                  [0, 0, 1]])
    k1, k2, k3, k4 = -0.048031442223833355, 0.011330957517194437, -0.055378166304281135, 0.021500973881459395
    x, y = rng.integers(0, 346, n), rng.integers(0, 260, n)
    xd, yd = (x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1]
    r_d = np.hypot(xd, yd)
    lo, hi = np.zeros(n), np.full(n, 1.5)           # theta_d(theta) rises over [0, 1.5] rad for these coefficients
    for _ in range(80):
        theta = (lo + hi) / 2
        above = theta * (1 + k1 * theta ** 2 + k2 * theta ** 4 + k3 * theta ** 6 + k4 * theta ** 8) > r_d
        hi, lo = np.where(above, theta, hi), np.where(above, lo, theta)
    scale = np.tan((lo + hi) / 2) / np.where(r_d > 0, r_d, 1.0)
    depth = rng.uniform(1.0, 5.0, n)
    points = np.column_stack([xd * scale, yd * scale, np.ones(n)]) * depth[:, None]
    t = np.sort(rng.uniform(100.0, 100.5, n))
    with h5py.File(tmp_path / "fish_data.hdf5", "w") as f:
        f["davis/left/events"] = np.column_stack([x, y, t, rng.choice([-1.0, 1.0], n)])
    return tmp_path / "fish_data.hdf5", points, t


def test_mvsec_dataset_rectifies_the_events_into_the_depth_frame(tmp_path):
    """MVSECDataset read the events as recorded (fisheye, unrectified) and paired them with the rectified K and
    depth: up to about 100 px apart toward the corners with MVSEC's lens. Given the camchain, each event now lands
    where the rectified pinhole (R_rect, P_rect) projects its 3-D point, to the nearest pixel."""
    import warnings

    from cmax.camera import Camera
    from learned.data import MVSECDataset

    path, points, t = _fisheye_scene(tmp_path, np.random.default_rng(5))
    calib = tmp_path / "camchain-imucam-indoor_flying.yaml"
    calib.write_text(MVSEC_CAMCHAIN)
    R = np.array([[0.999877311526236, 0.015019439766575743, -0.004447282784398257],
                  [-0.014996983873604017, 0.9998748347535599, 0.005040367172759556],
                  [0.004522429630305261, -0.004973052949604937, 0.9999774079320989]])
    P = np.array([[199.6530123165822, 0.0, 177.43276376280926], [0.0, 199.6530123165822, 126.81215684365904],
                  [0, 0, 1]])
    rectified = (points @ R.T) @ P.T
    expected = rectified[:, :2] / rectified[:, 2:]
    import h5py

    with h5py.File(tmp_path / "fish_gt.hdf5", "w") as f:    # one depth time: one window over every event
        f["davis/left/depth_image_rect"] = np.full((1, 260, 346), 2.0, np.float32)
        f["davis/left/depth_image_rect_ts"] = np.array([100.25])
    with warnings.catch_warnings():
        warnings.simplefilter("error")        # a calibrated dataset says nothing
        ds = MVSECDataset(path, calib=calib, gt_file=tmp_path / "fish_gt.hdf5", window_us=600_000, max_events=5000)
        events = ds.events(0)
        assert int(ds[0]["valid"].sum()) == len(events)
    np.testing.assert_array_equal(ds.K, P)
    order = np.argsort(t, kind="stable")           # read_mvsec keeps the file's (sorted) order
    inside = np.all((np.rint(expected) >= 0) & (np.rint(expected) < [346, 260]), axis=1)[order]
    assert len(events) == int(inside.sum()) > 2000
    got = np.column_stack([events.x, events.y])
    assert np.abs(got - expected[order][inside]).max() <= 0.5 + 1e-6      # the nearest pixel of the true one
    raw_shift = np.abs(np.column_stack([ds._read(path).x, ds._read(path).y])[inside] - expected[order][inside]).max()
    assert raw_shift > 20                           # what the events were without the calibration
    # the same with the camera given as arrays
    camera = Camera(np.array([[226.38018519795807, 0.0, 173.6470807871759],
                              [0.0, 226.15002947047415, 133.73271487507847], [0, 0, 1]]), 346, 260,
                    [-0.048031442223833355, 0.011330957517194437, -0.055378166304281135, 0.021500973881459395],
                    "equidistant", R, P)
    same = MVSECDataset(path, P, calib=camera, gt_file=tmp_path / "fish_gt.hdf5", window_us=600_000).events(0)
    assert same == events


def test_mvsec_dataset_volume_spreads_each_event_from_its_exact_rectified_position(tmp_path):
    """The volume was built from the events at their nearest rectified pixels (up to 0.5 px off, holes in a
    regular pattern); now each event sits where the rectified pinhole projects its 3-D point (to 1e-3 px) and
    its weight is split bilinearly around it: the volume is that of the true positions."""
    from cmax.representations import voxel_grid
    from learned.data import MVSECDataset

    path, points, t = _fisheye_scene(tmp_path, np.random.default_rng(7))
    calib = tmp_path / "camchain.yaml"
    calib.write_text(MVSEC_CAMCHAIN)
    R = np.array([[0.999877311526236, 0.015019439766575743, -0.004447282784398257],
                  [-0.014996983873604017, 0.9998748347535599, 0.005040367172759556],
                  [0.004522429630305261, -0.004973052949604937, 0.9999774079320989]])
    P = np.array([[199.6530123165822, 0.0, 177.43276376280926], [0.0, 199.6530123165822, 126.81215684365904],
                  [0, 0, 1]])
    rectified = (points @ R.T) @ P.T
    order = np.argsort(t, kind="stable")
    expected = (rectified[:, :2] / rectified[:, 2:])[order]
    inside = np.all((np.rint(expected) >= 0) & (np.rint(expected) < [346, 260]), axis=1)
    ds = MVSECDataset(path, calib=calib, window_us=600_000, max_events=5000)
    ds.middles = np.array([int(round(100.25e6))])          # one window over every event
    events, pixels = ds.events(0), ds.pixels(0)
    assert len(events) == len(pixels) == int(inside.sum()) > 2000
    np.testing.assert_allclose(pixels, expected[inside], atol=1e-3)
    np.testing.assert_allclose(ds[0]["volume"].numpy(), voxel_grid(events, ds.bins, pixels=expected[inside]),
                               atol=1e-3)
    assert not np.allclose(ds[0]["volume"].numpy(), voxel_grid(events, ds.bins), atol=0.1)   # not the rounded one


def test_mvsec_item_loss_events_are_dithered_over_the_sensor_pixel_and_mapped_through_the_lens(tmp_path):
    """The contrast loss's events of an MVSEC item were the events at their nearest rectified pixels with a dither
    around them (two quantisations), while the volume used the exact positions. Now each event is dithered over
    its SENSOR pixel and mapped through the fisheye and the rectification, unrounded: OpenCV's
    fisheye.undistortPoints (R_rect, P_rect) of the dithered sensor pixels, and the very events
    EventWindows.from_events(events, camera) (what cmax.fit warps) gives for the same subset and seed."""
    import cv2

    from cmax.contrast import EventWindows
    from cmax.io.mvsec import read_mvsec
    from learned.data import MVSECDataset

    path, _, _ = _fisheye_scene(tmp_path, np.random.default_rng(8))
    calib = tmp_path / "camchain.yaml"
    calib.write_text(MVSEC_CAMCHAIN)
    ds = MVSECDataset(path, calib=calib, window_us=600_000, max_events=2000)
    ds.middles = np.array([int(round(100.25e6))])          # one window over every event
    item = ds[0]
    valid = item["valid"].numpy()
    got = np.column_stack([item["x"].numpy()[valid], item["y"].numpy()[valid]])
    raw = read_mvsec(path, t0_us=int(ds.middles[0]) - 300_000, t1_us=int(ds.middles[0]) + 300_000)
    events = ds.events(0)
    assert len(raw) == 3000 and 2000 < len(events) < 3000 and valid.sum() == 2000   # a subset: the lens drops some
    batch = EventWindows.from_events(raw, ds.camera, max_events=2000, seed=0)
    np.testing.assert_allclose(got, np.column_stack([batch.x.numpy(), batch.y.numpy()]), rtol=0, atol=1e-5)
    np.testing.assert_allclose(item["t"].numpy()[valid], batch.t.numpy(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(item["K"].numpy(), batch.K[0].numpy(), rtol=1e-6)
    kept = ds.camera.undistorted_kept(raw)                 # independently: OpenCV through the camchain
    keep = np.sort(np.random.default_rng(0).choice(len(kept), 2000, replace=False))
    dithered = np.column_stack([raw.x[kept], raw.y[kept]])[keep] + \
        np.random.default_rng([0, 1]).uniform(-0.5, 0.5, (2000, 2))
    expected = cv2.fisheye.undistortPoints(dithered.reshape(-1, 1, 2), ds.camera.K, ds.camera.distortion,
                                           R=ds.camera.rectification, P=ds.K,
                                           criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14))
    np.testing.assert_allclose(got, expected.reshape(-1, 2), atol=1e-4)
    rounded = np.column_stack([events.x, events.y])[keep]  # the old loss events: rounded pixel + dither
    assert np.abs(got - rounded).max() > 0.6               # beyond any dither around the rounded pixel
    assert np.mean(np.abs(got - rounded).max(axis=1) > 0.5) > 0.1


def test_mvsec_window_finds_the_kept_events_once(tmp_path, monkeypatch):
    """MVSECDataset._window found the events the lens keeps twice (undistorted_kept, then again in sensor_pixels);
    once now, with the same sensor pixels, bit for bit (values and dtype), and the same events and positions."""
    from cmax.camera import Camera, sensor_pixels
    from conftest import counted_calls
    from learned.data import MVSECDataset

    path, _, _ = _fisheye_scene(tmp_path, np.random.default_rng(8))
    calib = tmp_path / "camchain.yaml"
    calib.write_text(MVSEC_CAMCHAIN)
    ds = MVSECDataset(path, calib=calib, window_us=600_000, max_events=2000)
    ds.middles = np.array([int(round(100.25e6))])
    calls = counted_calls(monkeypatch, Camera, "undistorted_kept")
    events, pixels, sensor = ds._window(0)
    assert len(calls) == 1
    raw = ds._read(ds.data_file, t0_us=int(ds.middles[0]) - 300_000, t1_us=int(ds.middles[0]) + 300_000)
    expected = sensor_pixels(raw, ds.camera)
    assert sensor.pixels.dtype == expected.dtype and np.array_equal(sensor.pixels, expected)
    assert np.array_equal(pixels, ds.camera.undistorted_pixels(raw)[ds.camera.undistorted_kept(raw)])
    assert np.array_equal(events.x, ds.camera.undistort_events(raw).x)


def test_to_item_checks_its_sensor_pixels():
    from cmax import Events
    from cmax.camera import Camera
    from cmax.fitting.window import SensorPixels

    camera = Camera(np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]), 64, 48, [-0.2, 0.05, 0.0, 0.0])
    events = Events(np.array([10, 20, 30]), np.array([5, 6, 7]), np.array([0, 10, 20]), np.array([0, 1, 1]), 64, 48)
    sample = Sample(events, camera.pinhole_K, None, None, 0, 30)
    with pytest.raises(ValueError, match=r"sensor.pixels must be \(3, 2\), one sensor pixel per event"):
        to_item(sample, max_events=8, sensor=SensorPixels(np.zeros((2, 2)), camera))
    with pytest.raises(TypeError, match=r"sensor must be a cmax.fitting.window.SensorPixels or None, got ndarray"):
        to_item(sample, max_events=8, sensor=np.zeros((3, 2)))


def test_mvsec_dataset_without_calibration_warns_once_and_checks_the_calibration(tmp_path):
    import warnings

    from cmax.camera import Camera
    from learned.data import MVSECDataset

    path, _, _ = _fisheye_scene(tmp_path, np.random.default_rng(6), n=500)
    K = [199.65, 199.65, 177.43, 126.81]
    with pytest.warns(UserWarning, match=r"different frames.*pass calib="):
        ds = MVSECDataset(path, K, window_us=100_000)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds[0]                                       # said once, at construction, not per window
    with pytest.raises(ValueError, match=r"give K .* or calib"):
        MVSECDataset(path)
    calib = tmp_path / "camchain.yaml"
    calib.write_text(MVSEC_CAMCHAIN)
    with pytest.raises(ValueError, match=r"K \[226.38, .* is not the K of the frame calib maps the events into"):
        MVSECDataset(path, [226.38, 226.15, 173.65, 133.73], calib=calib)    # the lens's K, not the rectified one
    np.testing.assert_array_equal(MVSECDataset(path, K, calib=calib).K[0], [199.6530123165822, 0.0,
                                                                          177.43276376280926])  # K rounded: taken
    with pytest.raises(ValueError, match=r"calib is a camera of a 240x180 sensor; MVSEC's DAVIS is 346x260"):
        MVSECDataset(path, calib=Camera.from_intrinsics(200, 200, 120, 90, 240, 180))
    import h5py

    with h5py.File(tmp_path / "gt.hdf5", "w") as f:
        f["davis/left/depth_image_rect"] = np.full((1, 260, 346), 2.0, np.float32)
        f["davis/left/depth_image_rect_ts"] = np.array([100.25])
    unrectified = Camera(np.array([[226.38, 0, 173.65], [0, 226.15, 133.73], [0, 0, 1]]), 346, 260,
                         [-0.048, 0.0113, -0.0554, 0.0215], "equidistant")
    with pytest.warns(UserWarning, match=r"calib gives no rectification .* MVSEC's depth maps lie in the rectified"):
        MVSECDataset(path, calib=unrectified, gt_file=tmp_path / "gt.hdf5")
    calib.write_text(MVSEC_CAMCHAIN.replace("resolution: [346, 260]", "resolution: [640, 480]"))
    with pytest.raises(ValueError, match=r"calibrates a 640x480 camera \(cam0\); MVSEC's DAVIS is 346x260"):
        MVSECDataset(path, calib=calib)


def test_mvsec_dataset_refuses_the_right_camera_s_calibration(tmp_path):
    from learned.data import MVSECDataset

    path, _, _ = _fisheye_scene(tmp_path, np.random.default_rng(7), n=200)
    calib = tmp_path / "camchain.yaml"
    calib.write_text(MVSEC_CAMCHAIN + MVSEC_CAMCHAIN.replace("cam0:", "cam1:").replace("/davis/left/", "/davis/right/"))
    with pytest.raises(ValueError, match=r"cam1 is the right camera \(rostopic /davis/right/image_raw\); MVSECDataset "
                                         r"reads davis/left"):
        MVSECDataset(path, calib=calib, calib_camera="cam1")
    assert MVSECDataset(path, calib=calib, window_us=100_000).camera.model == "equidistant"


def test_the_data_set_reads_a_conversion_s_record_without_the_command_line(tmp_path):
    """Building an ``H5WindowDataset`` (its refusal of a ``cmax simulate --size`` conversion without K, which says
    how the frames' K scales, and the same file with a K) loads no ``cmax.cli`` module (was: learned.data
    imported ``cmax.cli.recording.resized_note`` for that note)."""
    import subprocess
    import sys
    import textwrap

    import h5py

    from cmax.events import Events
    from cmax.io import write_h5

    rng = np.random.default_rng(0)
    n = 4000
    events = Events(rng.integers(0, 24, n), rng.integers(0, 16, n), np.sort(rng.integers(0, 400_000, n)),
                    rng.integers(0, 2, n), 24, 16)
    path = write_h5(tmp_path / "conv.h5", events)
    with h5py.File(path, "a") as file:       # the attributes of a conversion of 48x32 frames at --size 24x16
        file.attrs.update(width=24, height=16, source_size="[48, 32]", source=str(tmp_path / "clip.avi"))
    script = textwrap.dedent(f"""
        import sys
        from learned.data import H5WindowDataset
        try:
            H5WindowDataset([{str(path)!r}], window_us=100_000)
        except ValueError as error:
            print("refused:", "resized to 24x16 (--size): a K of those frames scales to fx*0.5" in str(error))
        ds = H5WindowDataset([{{"path": {str(path)!r}, "K": [20.0, 20.0, 11.5, 7.5]}}], window_us=100_000)
        print("windows:", len(ds) > 0)
        print("cli:", sorted(m for m in sys.modules if m.startswith("cmax.cli")))
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == ["refused: True", "windows: True", "cli: []"], result.stdout
