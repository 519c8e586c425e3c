"""What a new user meets first in ``python -m learned.train`` and ``python -m learned.predict``: an earlier run
is kept unless told, overrides may follow the options, and a mistake is one line that says what to do, before the
model is loaded."""
from __future__ import annotations

from pathlib import Path

import pytest

from conftest import one_line_error


# -- python -m learned.train -------------------------------------------------------------------------------
def _train(slider_file: Path, out: Path, *extra: str) -> list[str]:
    return ["--mode", "teacher", "--no-progress", f'data.files=["{slider_file}"]', "train.val_every=0",
            "train.steps=1", "train.batch_size=1", "model.width=2", "model.levels=1", "data.window_us=50000",
            "data.max_events=500", f"train.out={out}", *extra]


def test_train_keeps_an_earlier_run_unless_told(slider_file, tmp_path, capsys):
    from learned.checkpoint import load_checkpoint
    from learned.train import main

    out = tmp_path / "run"
    assert main(_train(slider_file, out)) == 0
    first = (out / "last.pt").read_bytes()
    status, err = one_line_error(lambda: main(_train(slider_file, out)), capsys)
    assert status == 2 and "last.pt exists (an earlier run): --resume continues it, --overwrite" in err
    assert (out / "last.pt").read_bytes() == first
    status, err = one_line_error(lambda: main(_train(slider_file, out, "--resume", "--overwrite")), capsys)
    assert status == 2 and "give one of them" in err
    (out / "log.jsonl").write_text('{"step": 99}\n')
    assert main(_train(slider_file, out, "--overwrite", "train.log_every=1")) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 1
    assert '"step": 99' not in (out / "log.jsonl").read_text()   # the new run's curves alone
    assert main(_train(slider_file, out, "--resume", "train.steps=2")) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 2


@pytest.mark.parametrize("extra, message", [
    (["train.val_every=5"], "or turn validation off with train.val_every=0"),
    (["data.files=[]"], "data.files is empty: give the training event files, e.g. 'data.files="),
    (["data.window_us=2000000"], "data.files hold no window: labelled windows are centred on their file's "
     "gt/depth_t, and each of the 4 window(s) of 2000 ms (data.window_us) reaches beyond its recording"),
    (["train.out=FILE"], "is a file: give a folder for last.pt"),
    # the index of a bad val_files entry (it was data.files[1], counted over files + val_files)
    (['data.val_files=[{"path": "v.h5", "K": [1, 2]}]'], "data.val_files[0].K must be [fx, fy, cx, cy]"),
    (['data.files=[{"path": "a.h5", "k": 1}]'], 'may hold "K", "use_gt", "known_speed", "known_twist", "polarity", "calib", "calib_camera", "rectify_map" and "as_recorded" only'),
    (["train.out=123"], """train.out must be a string, got 123 (int); a value that reads as JSON (a number, true) is taken as one: quote it, 'train.out="123"'"""),
])
def test_train_mistakes_say_what_to_do(slider_file, tmp_path, capsys, extra, message):
    from learned.train import main

    extra = [f"train.out={slider_file}" if e == "train.out=FILE" else e for e in extra]
    status, err = one_line_error(lambda: main(_train(slider_file, tmp_path / "run", *extra)), capsys)
    assert status == 2 and message in err, err
    assert not (tmp_path / "run" / "last.pt").exists()


def test_a_config_s_relative_files_missing_here_but_beside_it_are_named_in_both_places(slider_file, tmp_path,
                                                                                      capsys, monkeypatch):
    """A config in its own folder, listing data.files relative to it, run from another folder: was `error: no
    such event file: slider.h5`, which said neither where it was looked for nor where it is. Relative paths are
    read from the current folder (as they were: the run from the config's folder trains); the message now names
    the current folder and the file beside the config."""
    import shutil

    from learned.config import load_config
    from learned.train import main

    folder = tmp_path / "experiment"
    folder.mkdir()
    shutil.copy(slider_file, folder / "slider.h5")
    (folder / "c.toml").write_text('mode = "teacher"\n[data]\nfiles = ["slider.h5"]\n')
    monkeypatch.chdir(tmp_path)
    args = ["--config", "experiment/c.toml", *_train(slider_file, tmp_path / "run")[3:]]
    args = [a for a in args if not a.startswith("data.files=")]
    status, err = one_line_error(lambda: main(args), capsys)
    assert status == 2 and "no such file: slider.h5 (relative paths of a config are read from the current folder, " \
        f"{tmp_path})" in err and "experiment/slider.h5 lies beside the config experiment/c.toml" in err, err
    assert not (tmp_path / "run").exists()
    monkeypatch.chdir(folder)   # from the config's folder the same paths are found
    assert list(load_config(Path("c.toml"), ["train.steps=1"]).data.files) == ["slider.h5"]


# -- python -m learned.predict ----------------------------------------------------------------------------------
def test_predict_refuses_a_file_as_output_before_loading_a_model(slider_file, tmp_path, capsys, monkeypatch):
    import learned.evaluate
    from learned.predict import main

    monkeypatch.setattr(learned.evaluate, "load_model", lambda *a: (_ for _ in ()).throw(AssertionError("loaded")))
    (tmp_path / "out.txt").write_text("notes")
    status, err = one_line_error(lambda: main([str(slider_file), "-o", str(tmp_path / "out.txt")]), capsys)
    assert status == 2 and "out.txt is a file: give a folder" in err


def test_a_checkpoint_folder_points_at_its_file(slider_file, tmp_path, capsys):
    from learned.predict import main

    (tmp_path / "run").mkdir()
    status, err = one_line_error(lambda: main([str(slider_file), "-o", str(tmp_path / "o"), "--checkpoint",
                                          str(tmp_path / "run")]), capsys)
    assert status == 2 and "it is a folder (it holds no .pt file)" in err
    (tmp_path / "run" / "last.pt").write_bytes(b"x")
    status, err = one_line_error(lambda: main([str(slider_file), "-o", str(tmp_path / "o"), "--checkpoint",
                                          str(tmp_path / "run")]), capsys)
    assert status == 2 and f"give the file, e.g. {tmp_path / 'run' / 'last.pt'}" in err


def test_predict_keeps_an_earlier_runs_windows_from_mixing_with_new_ones(slider_file, tmp_path, capsys):
    """A second run into the same folder with another window left the first run's window files beside the
    new twists.csv; now it is refused, and --overwrite replaces them (only once its inputs are checked)."""
    import json

    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config, DataConfig
    from learned.model import DepthPoseNet, ModelConfig
    from learned.predict import main

    config = Config(model=ModelConfig(width=2, levels=1), data=DataConfig(window_us=50_000))
    checkpoint = save_checkpoint(tmp_path / "tiny.pt", {"model": DepthPoseNet(config.model).state_dict(),
                                                        "optimizer": {}, "step": 0, "config": config.to_dict(),
                                                        "rng": rng_state()})
    out = tmp_path / "out"
    base = [str(slider_file), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet"]
    assert main(base) == 0
    first = sorted(p.name for p in out.iterdir())
    assert len([name for name in first if name.endswith(".npz")]) == 5          # 0.3 s in windows of 50 ms
    assert "covers it in 6 windows" in capsys.readouterr().err                 # the sixth ends 2 ms late: noted
    status, err = one_line_error(lambda: main([*base, "--window", "0.2"]), capsys)
    assert status == 2 and "holds the results of an earlier run" in err and "--overwrite replaces them" in err
    status, err = one_line_error(lambda: main([*base, "--window", "5", "--overwrite"]), capsys)  # refused: kept
    assert status == 2 and sorted(p.name for p in out.iterdir()) == first
    assert main([*base, "--window", "0.2", "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["summary.json", "twists.csv", "window_00000.npz",
                                                     "window_00000.png"]
    assert json.loads((out / "summary.json").read_text())["windows"] == 1


def test_predict_refuses_a_principal_point_off_the_sensor(slider_file, tmp_path, capsys):
    """--K of another camera (here a 1280x720 one on a 64x48 file) is refused, not taken silently."""
    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config, DataConfig
    from learned.model import DepthPoseNet, ModelConfig
    from learned.predict import main

    config = Config(model=ModelConfig(width=2, levels=1), data=DataConfig(window_us=50_000))
    checkpoint = save_checkpoint(tmp_path / "tiny.pt", {"model": DepthPoseNet(config.model).state_dict(),
                                                        "optimizer": {}, "step": 0, "config": config.to_dict(),
                                                        "rng": rng_state()})
    base = [str(slider_file), "--checkpoint", str(checkpoint), "--quiet"]
    assert main([*base, "-o", str(tmp_path / "a"), "--K", "60,60,32,24"]) == 0
    assert "principal point" not in capsys.readouterr().err
    # refused, as cmax fit, cmax emvs and learned.train refuse it (was: a note, and depth maps written)
    assert main([*base, "-o", str(tmp_path / "b"), "--K", "900,900,640,360"]) == 2
    err = capsys.readouterr().err
    assert "K's principal point (640, 360) lies outside the 64x48 image" in err and err.count("\n") == 1
    assert not (tmp_path / "b").exists()


def test_teacher_refuses_files_without_ground_truth(slider_file, tmp_path, capsys):
    """--mode teacher on unlabelled files trained with a loss of 0 at every step (a run that looks fine)."""
    import cmax
    from cmax.io import write_h5
    from learned.train import main

    bare = write_h5(tmp_path / "bare.h5", cmax.io.read(slider_file))   # the same events, no gt/
    status, err = one_line_error(lambda: main(_train(bare, tmp_path / "run")), capsys)
    assert status == 2 and "has no gt/K: give its intrinsics in its entry of the config's data.files, e.g. " \
        """'data.files=[{"path": """ in err
    entry = f'data.files=[{{"path": "{bare}", "K": [60, 60, 32, 24]}}]'
    status, err = one_line_error(lambda: main(_train(bare, tmp_path / "run", entry)), capsys)
    assert status == 2 and "--mode teacher learns from ground-truth depth" in err and "its loss would be 0" in err
    assert not (tmp_path / "run" / "last.pt").exists()


def test_a_small_sensors_depth_picture_is_enlarged_to_stay_readable():
    """A 64x48 map was drawn at 64x48: its title wrapped and the colour bar's labels overlapped."""
    import numpy as np

    from cmax import viz
    from learned.predict import window_picture

    depth = np.linspace(1.0, 9.0, 64 * 48, dtype=np.float32).reshape(48, 64)
    picture = window_picture(depth, viz.DepthScale(1.0, 10.0), "window 0, 0.000-0.050 s, depth [m]")
    enlarged = viz.depth_image(np.repeat(np.repeat(depth, 5, axis=0), 5, axis=1), viz.DepthScale(1.0, 10.0))
    assert picture.shape[1] > viz.MIN_PICTURE_WIDTH == 5 * 64
    rows = [r for r in range(picture.shape[0] - 240 + 1) if np.array_equal(picture[r:r + 240, :320], enlarged)]
    assert len(rows) == 1                                    # the map, each pixel a 5x5 block, under its title
    big = np.ones((260, 346), np.float32)
    assert np.array_equal(window_picture(big, (0.5, 60.0), "t"), viz.depth_panel(big, (0.5, 60.0), "t"))


def test_resume_says_when_it_starts_afresh_or_has_nothing_to_do(slider_file, tmp_path, capsys):
    """--resume into a folder without last.pt (a typo in train.out) started at step 0 without a word, and a
    run already at train.steps printed nothing at all."""
    from learned.train import main

    out = tmp_path / "run"
    assert main(_train(slider_file, out, "--resume")) == 0
    captured = capsys.readouterr()
    assert f"note: --resume, but {out / 'last.pt'} does not exist: starting at step 0" in captured.err
    assert captured.out.startswith("teacher: 1 steps, loss ")
    assert main(_train(slider_file, out, "--resume")) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert captured.out == (f"teacher: nothing to train: {out / 'last.pt'} is at step 1 of train.steps=1; "
                            "raise train.steps to train further\n")


def test_a_torchrun_job_uses_gloo_even_where_cuda_is_available(slider_file, tmp_path, monkeypatch):
    """Training keeps its tensors on the CPU; with CUDA available the job asked for nccl, which refuses them."""
    import torch

    from learned.config import load_config
    from learned.train import Trainer

    chosen = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: False)
    monkeypatch.setattr(torch.distributed, "init_process_group", lambda backend, *a, **k: chosen.append(backend))
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    config = load_config(None, _train(slider_file, tmp_path / "run")[3:], mode="teacher")
    with pytest.raises(ValueError, match="multiple of the 2 ranks"):   # batch_size 1: stops after the group
        Trainer(config, progress=False)
    assert chosen == ["gloo"]


def test_a_torchrun_job_on_gpus_takes_its_rank_s_gpu_and_nccl(slider_file, tmp_path, monkeypatch):
    """``train.device=cuda`` under torchrun: the rank sets the GPU of its LOCAL_RANK before it joins the group,
    and the group is nccl (CUDA's presence faked: no GPU here)."""
    import torch

    from learned.config import load_config
    from learned.train import Trainer

    calls = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_device", lambda device: calls.append(("set_device", str(device))))
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: False)
    monkeypatch.setattr(torch.distributed, "init_process_group", lambda backend, *a, **k: calls.append(backend))
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("LOCAL_RANK", "1")
    config = load_config(None, [*_train(slider_file, tmp_path / "run")[3:], "train.device=cuda"], mode="teacher")
    with pytest.raises(ValueError, match="multiple of the 2 ranks"):   # batch_size 1: stops after the group
        Trainer(config, progress=False)
    assert calls == [("set_device", "cuda:1"), "nccl"]
