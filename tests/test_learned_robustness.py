"""``learned`` against crafted checkpoints, concurrent runs and reruns into one output folder.

* a checkpoint whose config describes a far larger network than its weights is refused before that network is
  built (it would allocate many GB);
* ``python -m learned.train`` and ``cmax depth`` hold their output folder: a second run into it meanwhile is
  refused in one line and changes nothing (the lock is taken here, in the test process);
* ``--overwrite`` records the input file in ``summary.json`` and keeps the earlier results until the new run
  succeeds;
* ``python -m learned.evaluate`` on a file without ground truth says so, not how to give K in a config.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import one_line_error, random_events


def _files(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones included) and its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _crafted(source: Path, target: Path, **model: int) -> Path:
    """``source`` with keys of its config's ``model`` changed (its weights kept), as a crafted file would be."""
    import torch

    ckpt = torch.load(source, weights_only=True)
    ckpt["config"]["model"].update(model)
    torch.save(ckpt, target)
    return target


def _never(*args, **kwargs):
    raise AssertionError("the network of the crafted config was built")


# -- 1. a config that does not fit its weights -----------------------------------------------------------------
@pytest.mark.parametrize("model, message", [
    ({"levels": 24}, "its weights do not fit its model config (3"),   # 16M channels at level 24
    ({"width": 2**40}, "describes a network torch cannot build"),                              # sizes past int64
    ({"levels": 1000}, "model.levels=1000, its weights 24 tensors"),   # refused before the config is checked
])
def test_a_config_larger_than_its_weights_is_refused_before_the_network_is_built(
        tiny_checkpoint, tmp_path, monkeypatch, model, message):
    import learned.evaluate
    from learned.checkpoint import CheckpointError

    monkeypatch.setattr(learned.evaluate, "DepthPoseNet", _never)   # were it built, it would take many GB
    crafted = _crafted(tiny_checkpoint, tmp_path / "crafted.pt", **model)
    with pytest.raises(CheckpointError) as caught:
        learned.evaluate.load_model(crafted)
    assert message in str(caught.value) and "\n" not in str(caught.value), caught.value


def test_cmax_depth_refuses_the_crafted_checkpoint_in_one_line(tiny_checkpoint, slider_file, tmp_path, capsys,
                                                                monkeypatch):
    import learned.evaluate
    from learned.predict import main

    monkeypatch.setattr(learned.evaluate, "DepthPoseNet", _never)   # were it built, it would take many GB
    crafted = _crafted(tiny_checkpoint, tmp_path / "crafted.pt", levels=24)
    status, err = one_line_error(lambda: main([str(slider_file), "-o", str(tmp_path / "out"), "--checkpoint",
                                               str(crafted), "--quiet"]), capsys)
    assert status == 2 and "crafted.pt: its weights do not fit its model config" in err, err
    assert not (tmp_path / "out").exists()


def test_check_weights_names_what_differs():
    from learned.checkpoint import CheckpointError, check_weights
    from learned.model import DepthPoseNet, ModelConfig

    config = ModelConfig(width=2, levels=1)
    state = DepthPoseNet(config).state_dict()
    check_weights(config, state, "ok.pt")   # fits: nothing raised
    with pytest.raises(CheckpointError, match=r"1 unexpected \(e\.g\. extra\)"):
        check_weights(config, {**state, "extra": state["heads.0.weight"]}, "x.pt")
    with pytest.raises(CheckpointError, match=r"1 of another shape \(e\.g\. heads\.0\.bias: \[3\], the config's \[1\]"):
        check_weights(config, {**state, "heads.0.bias": state["heads.0.bias"].repeat(3)}, "x.pt")


# -- 2. one training run at a time in train.out ------------------------------------------------------------------
def _train(slider_file: Path, out: Path, *extra: str) -> list[str]:
    return ["--mode", "teacher", "--no-progress", f'data.files=["{slider_file}"]', "train.val_every=0",
            "train.steps=1", "train.batch_size=1", "model.width=2", "model.levels=1", "data.window_us=50000",
            "data.max_events=500", f"train.out={out}", *extra]


@pytest.mark.parametrize("flag", ["--overwrite", "--resume", None])
def test_a_second_training_run_into_a_held_folder_is_refused_and_changes_nothing(slider_file, tmp_path, capsys,
                                                                                  flag):
    from cmax.io.atomic import PathLock
    from learned.train import FOLDER_LOCK, main

    out = tmp_path / "run"
    out.mkdir()
    if flag is not None:   # an earlier run's files (the first run is still writing them)
        (out / "last.pt").write_bytes(b"not yet a checkpoint")
        (out / "log.jsonl").write_text('{"step": 1}\n')
    with PathLock(out / FOLDER_LOCK, out):
        before = _files(out)
        status, err = one_line_error(lambda: main(_train(slider_file, out, *([flag] if flag else []))), capsys)
        assert status == 2 and "is being written by another writer" in err, err
        assert _files(out) == before


def test_a_training_run_releases_its_folder(slider_file, tmp_path):
    from learned.train import main

    out = tmp_path / "run"
    assert main(_train(slider_file, out)) == 0
    assert main(_train(slider_file, out, "--resume", "train.steps=2")) == 0   # not refused by the first run's lock
    assert not list(out.glob("*.lock"))


# -- 3. and 4. one cmax depth run at a time in -o OUT; --overwrite --------------------------------------------------
def _depth(slider_file: Path, out: Path, checkpoint: Path, *extra: str) -> list[str]:
    return [str(slider_file), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet", *extra]


@pytest.mark.parametrize("earlier", [False, True])
def test_a_second_depth_run_into_a_held_folder_is_refused_and_changes_nothing(slider_file, tiny_checkpoint, tmp_path,
                                                                              capsys, earlier):
    from cmax.io.atomic import PathLock
    from learned.predict import FOLDER_LOCK, main

    out = tmp_path / "out"
    if earlier:
        assert main(_depth(slider_file, out, tiny_checkpoint)) == 0
        capsys.readouterr()                          # its notes (the 2 ms after its fifth window are left out)
    out.mkdir(exist_ok=True)
    with PathLock(out / FOLDER_LOCK, out):
        before = _files(out)
        status, err = one_line_error(lambda: main(_depth(slider_file, out, tiny_checkpoint, "--overwrite")), capsys)
        assert status == 2 and "is being written by another writer" in err, err
        assert _files(out) == before
    capsys.readouterr()
    assert main(_depth(slider_file, out, tiny_checkpoint, "--overwrite")) == 0   # released: runs
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]         # no lock, no private folder left


def test_overwrite_records_the_input_file_and_keeps_the_earlier_results_until_it_succeeds(slider_file, tiny_checkpoint,
                                                                                       tmp_path, capsys):
    from learned.predict import main

    out = tmp_path / "out"
    assert main(_depth(slider_file, out, tiny_checkpoint)) == 0
    assert main(_depth(slider_file, out, tiny_checkpoint, "--overwrite")) == 0
    assert json.loads((out / "summary.json").read_text())["file"] == str(slider_file)
    before = _files(out)
    assert len([name for name in before if name.endswith(".npz")]) == 5          # 0.3 s in windows of 50 ms
    capsys.readouterr()
    # a window of 0.2 ms holds no 10 events: the run fails after its checks, with the input named
    status = main(_depth(slider_file, out, tiny_checkpoint, "--overwrite", "--t0", "0.1", "--t1", "0.1002",
                         "--window", "0.0002"))
    *notes, err = capsys.readouterr().err.strip().splitlines()   # a note: 0.2 ms is not the checkpoint's 50 ms
    assert status == 2 and f"{slider_file}: none of its 1 windows" in err and "error:" in err, err
    assert [line for line in notes if "windows of 50 ms, these are 0.2 ms" not in line] == [], notes
    assert _files(out) == before                                                   # the earlier results kept
    assert main(_depth(slider_file, out, tiny_checkpoint, "--overwrite", "--window", "0.2")) == 0
    assert sorted(_files(out)) == ["summary.json", "twists.csv", "window_00000.npz", "window_00000.png"]


def test_a_killed_runs_private_folder_is_removed_by_the_next_run(slider_file, tiny_checkpoint, tmp_path):
    from learned.predict import main

    out = tmp_path / "out"
    left = out / ".depth.0123456789abcdef.partial"
    left.mkdir(parents=True)
    (left / "window_00000.npz").write_bytes(b"half written")
    assert main(_depth(slider_file, out, tiny_checkpoint)) == 0
    assert not left.exists() and (out / "summary.json").is_file()


# -- 5. evaluate on a file without ground truth ----------------------------------------------------------------------
def test_evaluate_on_an_event_file_of_another_format_names_no_config_key(tiny_checkpoint, tmp_path, capsys):
    """An ECD text file given to learned.evaluate was answered with training's advice ("... give its K in
    data.files"), a key evaluate does not have."""
    from learned.evaluate import main

    events = tmp_path / "events.txt"
    events.write_text("0.001 1 2 1\n0.002 3 4 0\n")
    status, err = one_line_error(lambda: main(["--checkpoint", str(tiny_checkpoint), "--data", str(events)]), capsys)
    assert status == 2 and "events.txt is not an HDF5 file: learned.evaluate scores the network against" in err, err
    assert "data.files" not in err and f"cmax depth {events} -o OUT" in err


def test_evaluate_on_a_file_without_ground_truth_says_so(tiny_checkpoint, tmp_path, capsys):
    from cmax.io.h5 import write_h5
    from learned.evaluate import main

    write_h5(tmp_path / "ev.h5", random_events(2000, seed=3))
    status, err = one_line_error(lambda: main(["--checkpoint", str(tiny_checkpoint), "--data",
                                               str(tmp_path / "ev.h5")]), capsys)
    assert status == 2 and "no ground truth to evaluate the network against" in err, err
    assert '{"path"' not in err and f"cmax depth {tmp_path / 'ev.h5'} -o OUT --K" in err


# -- 3. non-finite weights (a diverged run's) ------------------------------------------------------------------
def test_a_checkpoint_with_non_finite_weights_is_never_written_nor_loaded(tiny_checkpoint, slider_file, tmp_path,
                                                                         capsys):
    """A diverged run's NaN weights were saved over last.pt, loaded by load_model, and `cmax depth` wrote NaN
    depths and twists with exit 0."""
    import torch

    from learned.checkpoint import load_checkpoint, save_checkpoint
    from learned.evaluate import load_model
    from learned.predict import main

    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    ckpt["model"]["heads.0.bias"] = torch.full_like(ckpt["model"]["heads.0.bias"], float("nan"))
    nan_file = tmp_path / "nan.pt"
    torch.save(ckpt, nan_file)                      # as the earlier version wrote it
    for load in (load_checkpoint, load_model):
        with pytest.raises(ValueError, match=r"nan\.pt was refused: 1 of its 24 weight tensors hold NaN or "
                                             r"infinite values \(e\.g\. heads\.0\.bias\)"):
            load(nan_file)
    status, err = one_line_error(lambda: main([str(slider_file), "-o", str(tmp_path / "out"), "--checkpoint",
                                               str(nan_file), "--quiet"]), capsys)
    assert status == 2 and "nan.pt was refused" in err and "diverged" in err, err
    assert not (tmp_path / "out").exists()
    before = tiny_checkpoint.read_bytes()
    with pytest.raises(ValueError, match="was not written: 1 of its 24 weight tensors hold NaN"):
        save_checkpoint(tiny_checkpoint, {key: ckpt[key] for key in ("model", "optimizer", "step", "config", "rng")})
    assert tiny_checkpoint.read_bytes() == before


# -- 4. run_prediction's arguments, checked as the command line checks them -------------------------------------------
def test_run_prediction_checks_K_and_the_times_as_the_command_line_does(tiny_checkpoint, slider_file, tmp_path):
    """A 4-number K crashed (IndexError), a NaN or transposed K was stored in every window and summary.json,
    window_s="0.05" failed inside numpy; each is one line before any work, and [fx, fy, cx, cy] is accepted."""
    import h5py
    import numpy as np

    from learned.predict import run_prediction

    with h5py.File(slider_file, "r") as f:
        K = f["gt/K"][()]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    run = run_prediction(slider_file, tmp_path / "four", checkpoint=tiny_checkpoint, K=[fx, fy, cx, cy],
                         progress=False, note=lambda text: None)
    assert run.windows >= 1
    assert np.allclose(json.loads((tmp_path / "four" / "summary.json").read_text())["K"], K)
    nan_K = K.copy()
    nan_K[0, 0] = np.nan
    bad = [({"K": nan_K}, ValueError, "K must be finite"),
           ({"K": K.T}, ValueError, r"K must have the form \[\[fx, s, cx\], \[0, fy, cy\], \[0, 0, 1\]\]"),
           ({"K": [fx, -fy, cx, cy]}, ValueError, "K must have positive focal lengths"),
           ({"K": [fx, fy, cx]}, ValueError, r"K must be a 3x3 matrix, got shape \(3,\)"),
           ({"K": "fx"}, TypeError, "K must be"),
           ({"window_s": "0.05"}, TypeError, r"window_s must be a number of seconds, got '0.05' \(str\)"),
           ({"window_s": True}, TypeError, "window_s must be a number of seconds"),
           ({"window_s": float("nan")}, ValueError, "window_s must be a finite number of seconds > 0"),
           ({"t0_s": -1.0}, ValueError, "t0_s must be a finite number of seconds >= 0"),
           ({"t1_s": "1"}, TypeError, "t1_s must be a number of seconds"),
           ({"depth_range": "0.4,3"}, TypeError, r"depth_range must be \(near, far\) in metres")]
    for kwargs, kind, message in bad:
        out = tmp_path / "refused"
        with pytest.raises(kind, match=message) as caught:
            run_prediction(slider_file, out, checkpoint=tiny_checkpoint, progress=False, note=lambda text: None,
                           **kwargs)
        assert "\n" not in str(caught.value) and not out.exists(), (kwargs, caught.value)


# -- 5. weights of another kind of number, and weights that overflow --------------------------------------------------
@pytest.mark.parametrize("dtype", ["complex64", "bool", "int32"])
def test_weights_of_another_kind_of_number_are_refused(tiny_checkpoint, tmp_path, dtype):
    """Complex, bool or integer weights of the right shapes were cast by load_state_dict without a word (a complex
    weight lost its imaginary part with only torch's own warning; bool weights gave depths of 0.5-0.8 m, exit 0)."""
    import torch

    from learned.checkpoint import CheckpointError
    from learned.evaluate import load_model

    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    ckpt["model"] = {name: tensor.to(getattr(torch, dtype)) for name, tensor in ckpt["model"].items()}
    torch.save(ckpt, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match=rf"other\.pt: its weights do not fit its model config \(24 of another "
                                              rf"kind of number \(e\.g\. \S+: torch\.{dtype}, the network's real "
                                              r"floating point\)\)"):
        load_model(tmp_path / "other.pt")
    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    ckpt["model"] = {name: tensor.to(torch.float16) for name, tensor in ckpt["model"].items()}
    torch.save(ckpt, tmp_path / "half.pt")
    load_model(tmp_path / "half.pt")            # another precision of real numbers loads


def test_weights_that_overflow_write_no_depth_map(tiny_checkpoint, slider_file, tmp_path, capsys):
    """Finite weights scaled by 1e30 (not refused as NaN weights) made the network's output NaN: with --depth-range
    every window_*.npz held NaN depth and twists.csv 'nan', exit 0; without it an error about the colour scale."""
    import torch

    from learned.predict import main

    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    ckpt["model"] = {name: tensor * 1e30 for name, tensor in ckpt["model"].items()}
    torch.save(ckpt, tmp_path / "huge.pt")
    for extra in ((), ("--depth-range", "0.5,10")):
        out = tmp_path / f"out{len(extra)}"
        status, err = one_line_error(lambda: main([str(slider_file), "-o", str(out), "--checkpoint",
                                                   str(tmp_path / "huge.pt"), "--quiet", *extra]), capsys)
        assert status == 2 and "huge.pt gives a non-finite output on window 0" in err, err
        assert not out.exists() or not any(out.glob("*.npz")), sorted(out.iterdir())


def test_a_card_beside_a_trained_checkpoint_cannot_hide_the_camera_it_was_trained_with(tiny_checkpoint, slider_file,
                                                                                         tmp_path, capsys):
    """A checkpoint of ``learned.train`` records the camera of its training data (``"card"``). Was: a JSON card
    beside it (copied from another model, edited) replaced that record without a word: a card stating the file's
    own 64x48 camera silenced the notes that the network was trained on a 160x120 sensor at another focal length.
    Now the checkpoint's record wins, and a warning names the card's other camera."""
    import warnings

    import torch

    from learned.evaluate import load_network
    from learned.predict import main

    ckpt = torch.load(tiny_checkpoint, weights_only=True)
    recorded = {"size": [160, 120], "K": [300.0, 300.0, 80.0, 60.0], "window_s": 0.05}
    torch.save({**ckpt, "card": recorded}, tmp_path / "net.pt")
    (tmp_path / "net.json").write_text(json.dumps({"size": [64, 48], "K": [41.87, 41.75, 31.71, 24.28],
                                                   "window_s": 0.05, "limits": ["a limit the card states"]}))
    with pytest.warns(UserWarning, match=r"net.json, the card beside .*size \[64, 48\] \(the checkpoint: \[160, 120\]"):
        card = load_network(tmp_path / "net.pt")[2]
    assert {key: card[key] for key in recorded} == recorded and card["limits"] == ["a limit the card states"]
    assert main([str(slider_file), "-o", str(tmp_path / "D"), "--checkpoint", str(tmp_path / "net.pt"),
                 "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "the network was trained on a 160x120 sensor, this file is 64x48" in err, err
    assert "the network was trained at 300.0 px" in err and "states another camera" in err, err
    (tmp_path / "net.json").write_text(json.dumps({**recorded, "K": [300.01, 300.0, 80.0, 60.0]}))
    with warnings.catch_warnings():   # the same camera (to 0.1%): no warning
        warnings.simplefilter("error")
        load_network(tmp_path / "net.pt")


# -- 5. memory of one forward pass (--batch) ---------------------------------------------------------------------
def _tiny_config(checkpoint: Path):
    from learned.evaluate import load_model

    return load_model(checkpoint)[0].config


def test_a_batch_past_the_memory_limit_is_refused_before_any_window_is_read(tiny_checkpoint, slider_file, tmp_path,
                                                                             capsys, monkeypatch):
    """`cmax depth --batch 128` on a 640x480 recording asked ~8 GB of the network and failed after reading and
    building 128 windows with torch's allocator traceback (or the OOM killer); the limit is lowered here so that 3
    windows of the 64x48 slider fit and 4 do not."""
    import cmax.io
    import learned.predict as predict

    limit = predict.batch_bytes(_tiny_config(tiny_checkpoint), 64, 48, 3)
    monkeypatch.setattr(predict, "MAX_BATCH_BYTES", limit + 1)
    monkeypatch.setattr(cmax.io.H5Reader, "window", _never)      # no window read before the refusal
    out = tmp_path / "out"
    status, err = one_line_error(lambda: predict.main(_depth(slider_file, out, tiny_checkpoint, "--batch", "4")),
                                 capsys)
    assert status == 2 and "batch=4 (--batch) windows of 64x48 px" in err and "give --batch 3 or fewer" in err, err
    assert not out.exists() or not any(out.glob("window_*")), sorted(out.iterdir())


def test_the_default_batch_shrinks_to_the_memory_limit_with_the_same_results(tiny_checkpoint, slider_file, tmp_path,
                                                                             capsys, monkeypatch):
    """Without --batch, 8 windows a pass unless fewer fit: here 2; the twists are those of --batch 1."""
    import learned.predict as predict

    monkeypatch.setattr(predict, "MAX_BATCH_BYTES", predict.batch_bytes(_tiny_config(tiny_checkpoint), 64, 48, 2))
    assert predict.main(_depth(slider_file, tmp_path / "one", tiny_checkpoint, "--batch", "1")) == 0
    seen = []
    forward = predict.forward
    monkeypatch.setattr(predict, "forward", lambda model, volumes: seen.append(len(volumes)) or forward(model, volumes))
    assert predict.main(_depth(slider_file, tmp_path / "default", tiny_checkpoint)) == 0
    capsys.readouterr()
    assert len(seen) >= 3 and max(seen) == 2, seen                     # 5 windows of 50 ms: passes of 2, 2, 1
    one = np.loadtxt(tmp_path / "one" / "twists.csv", delimiter=",", skiprows=1)
    default = np.loadtxt(tmp_path / "default" / "twists.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(default, one, rtol=1e-5, atol=1e-6)


def test_a_sensor_too_large_for_one_window_is_refused(tiny_checkpoint):
    import learned.predict as predict

    config = _tiny_config(tiny_checkpoint)
    with pytest.raises(ValueError, match="one window of 8192x8192 px takes about"):
        predict.batch_that_fits(config, 8192, 8192, None)
    assert predict.batch_that_fits(config, 64, 48, None) == predict.DEFAULT_BATCH


def test_torch_running_out_of_memory_is_one_line_naming_the_batch(tiny_checkpoint, slider_file, tmp_path, capsys,
                                                                 monkeypatch):
    """torch's `RuntimeError: [enforce fail at alloc_cpu.cpp:127] ... DefaultCPUAllocator: can't allocate memory`
    came out of cmax depth as a traceback with exit status 1."""
    from learned.model import DepthPoseNet
    from learned.predict import main

    def exhausted(self, volume):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: "
                           "you tried to allocate 629145600 bytes. Error code 12 (Cannot allocate memory)")

    monkeypatch.setattr(DepthPoseNet, "forward", exhausted)
    status, err = one_line_error(lambda: main(_depth(slider_file, tmp_path / "out", tiny_checkpoint, "--batch", "2")),
                                 capsys)
    assert status == 2 and "ran out of memory on cpu with 2 windows of 64x48 px" in err and "--batch" in err, err


def test_the_pictures_drawn_after_the_windows_have_their_own_progress_bar(tiny_checkpoint, slider_file, tmp_path,
                                                                          capsys):
    """The pictures are drawn once every window is predicted (one colour scale): ~0.1 s each at 640x480, 40 min
    for an hour of 166.5 ms windows, with the windows' bar standing at 100% and nothing else on the screen."""
    from learned.predict import main

    assert main([str(slider_file), "-o", str(tmp_path / "out"), "--checkpoint", str(tiny_checkpoint)]) == 0
    err = capsys.readouterr().err
    assert "windows" in err and "pictures" in err and "5/5" in err.split("pictures")[-1], err


def test_cmax_depth_reads_a_npy_window_by_window(tiny_checkpoint, slider_file, tmp_path, capsys, monkeypatch):
    """A structured .npy was read whole before its windows were cut (the events of the whole file held through
    the run: 1.16 GB peak for 1.4 s of a 20 M-event file, 0.97 GB now); each window's rows are read alone, and the
    results are those of the same events in an h5 file."""
    import h5py

    import cmax.io
    from learned.predict import main

    events = cmax.io.read(slider_file)
    np.save(tmp_path / "slider.npy", events.to_structured())
    with h5py.File(slider_file, "r") as file:
        K = file["gt/K"][()]
    k = ",".join(repr(float(v)) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    assert main([str(slider_file), "-o", str(tmp_path / "h5"), "--checkpoint", str(tiny_checkpoint), "--quiet",
                 "--K", k]) == 0
    calls = []
    read = cmax.io.read
    monkeypatch.setattr(cmax.io, "read", lambda *a, **kw: calls.append((kw.get("t0_us"), kw.get("t1_us")))
                        or read(*a, **kw))
    assert main([str(tmp_path / "slider.npy"), "-o", str(tmp_path / "npy"), "--checkpoint", str(tiny_checkpoint),
                 "--quiet", "--K", k, "--size", "64x48"]) == 0
    capsys.readouterr()
    assert calls and all(t0 is not None and t1 is not None and t1 - t0 <= 50_000 for t0, t1 in calls), calls
    assert (tmp_path / "h5" / "twists.csv").read_text() == (tmp_path / "npy" / "twists.csv").read_text()
