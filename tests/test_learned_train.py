"""Training: loss decreases, bit-for-bit resume, determinism, crash safety, torchrun (gloo) = one process."""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from learned.checkpoint import load_checkpoint
from learned.config import load_config
from learned.train import Trainer, batch_indices, learning_rate, main

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    """0.6 s of a tiny indoor_flying scene (48x36) with ground truth every 50 ms."""
    from benchmarks.synthetic_windows import tiny_training_file

    return tiny_training_file(tmp_path_factory.mktemp("learned"))


def tiny(scene_file: Path, out: Path, *extra: str) -> list[str]:
    return [f'data.files=["{scene_file}"]', "data.max_events=1500", "data.window_us=100000", "model.width=4",
            "model.levels=2", "train.batch_size=4", "train.lr=3e-3", f"train.out={out}", "train.log_every=1",
            "train.image_every=3", "train.checkpoint_every=2", *extra]


def params(path: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(path)["model"]


def test_batch_indices_cover_each_epoch_once():
    first = [i for s in range(5) for i in batch_indices(s, size=10, batch_size=2, seed=3)]
    assert sorted(first) == list(range(10))
    assert batch_indices(7, size=10, batch_size=4, seed=3) == batch_indices(7, size=10, batch_size=4, seed=3)
    assert batch_indices(0, size=10, batch_size=4, seed=3) != batch_indices(0, size=10, batch_size=4, seed=4)


def test_teacher_smoke_loss_decreases_and_logs(scene_file, tmp_path):
    config = load_config(None, tiny(scene_file, tmp_path, "train.steps=12"), mode="teacher")
    losses = Trainer(config, progress=False).run()
    assert len(losses) == 12 and all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.8 * np.mean(losses[:3])
    ckpt = load_checkpoint(tmp_path / "last.pt")
    assert ckpt["step"] == 12 and ckpt["config"]["mode"] == "teacher"
    assert set(ckpt["rng"]) == {"python", "numpy", "torch"}
    assert any((tmp_path / "tb").iterdir())          # TensorBoard event file


def test_student_and_finetune_run_from_teacher(scene_file, tmp_path):
    teacher = tmp_path / "teacher"
    Trainer(load_config(None, tiny(scene_file, teacher, "train.steps=2"), mode="teacher"), progress=False).run()
    for mode in ("student", "finetune"):
        out = tmp_path / mode
        config = load_config(None, tiny(scene_file, out, "train.steps=3", f"train.teacher={teacher / 'last.pt'}"),
                             mode=mode)
        trainer = Trainer(config, progress=False)
        if mode == "finetune":   # starts from the teacher's weights
            start = params(teacher / "last.pt")
            assert all(torch.equal(start[k], v) for k, v in trainer.model.state_dict().items())
        losses = trainer.run()
        assert len(losses) == 3 and all(np.isfinite(losses))
        # the shared objective: two squared average timestamps in [0, 1] (forward, backward) plus small terms
        assert 0 < losses[0] < 2.5


def test_finetune_takes_the_teachers_network_and_refuses_another(scene_file, tmp_path):
    """A teacher of another size than the defaults (the shipped model is one): finetune left at the default
    model config builds the teacher's network and starts from its weights (it failed: "its weights do not fit
    the model of this config"); a run that sets another model config is refused with the fields that differ;
    a student whose volumes have other time bins than the teacher's is refused before its first step."""
    from learned.model import ModelConfig

    teacher = tmp_path / "teacher"
    Trainer(load_config(None, tiny(scene_file, teacher, "train.steps=1"), mode="teacher"), progress=False).run()
    stated = load_checkpoint(teacher / "last.pt")["config"]["model"]
    assert (stated["width"], stated["levels"]) == (4, 2) != (ModelConfig().width, ModelConfig().levels)
    plain = [f'data.files=["{scene_file}"]', "data.max_events=1500", "data.window_us=100000", "train.batch_size=4",
             "train.steps=1", f"train.teacher={teacher / 'last.pt'}"]
    trainer = Trainer(load_config(None, [*plain, f"train.out={tmp_path / 'ft'}"], mode="finetune"), progress=False)
    assert (trainer.config.model.width, trainer.config.model.levels) == (4, 2)
    start = params(teacher / "last.pt")
    assert all(torch.equal(start[k], v) for k, v in trainer.model.state_dict().items())
    trainer.run()
    assert load_checkpoint(tmp_path / "ft" / "last.pt")["config"]["model"] == stated
    with pytest.raises(ValueError, match=r"model config is the teacher's .*model\.width=8 \(the teacher's 4\)"):
        Trainer(load_config(None, [*plain, "model.width=8", f"train.out={tmp_path / 'ft8'}"], mode="finetune"),
                progress=False)
    with pytest.raises(ValueError, match="reads event volumes of 5 time bins, this run's network 3"):
        Trainer(load_config(None, [*plain, "model.bins=3", f"train.out={tmp_path / 'st'}"], mode="student"),
                progress=False)


def test_resume_continues_bit_for_bit(scene_file, tmp_path):
    straight, split = tmp_path / "straight", tmp_path / "split"
    Trainer(load_config(None, tiny(scene_file, straight, "train.steps=6"), mode="teacher"), progress=False).run()
    Trainer(load_config(None, tiny(scene_file, split, "train.steps=3"), mode="teacher"), progress=False).run()
    assert load_checkpoint(split / "last.pt")["step"] == 3
    resumed = Trainer(load_config(None, tiny(scene_file, split, "train.steps=6"), mode="teacher"), resume=True,
                      progress=False)
    assert resumed.step == 3
    resumed.run()
    a, b = params(straight / "last.pt"), params(split / "last.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    opt_a = load_checkpoint(straight / "last.pt")["optimizer"]["state"]
    opt_b = load_checkpoint(split / "last.pt")["optimizer"]["state"]
    assert all(torch.equal(opt_a[k]["exp_avg"], opt_b[k]["exp_avg"]) for k in opt_a)


def test_same_seed_same_steps(scene_file, tmp_path):
    runs = []
    for name in ("a", "b"):
        runs.append(Trainer(load_config(None, tiny(scene_file, tmp_path / name, "train.steps=3"), mode="teacher"),
                            progress=False).run())
    assert runs[0] == runs[1]
    a, b = params(tmp_path / "a" / "last.pt"), params(tmp_path / "b" / "last.pt")
    assert all(torch.equal(a[k], b[k]) for k in a)
    other = Trainer(load_config(None, tiny(scene_file, tmp_path / "c", "train.steps=3", "train.seed=1"),
                                mode="teacher"), progress=False).run()
    assert other != runs[0]


def test_sigkill_leaves_a_loadable_checkpoint_and_resume_continues(scene_file, tmp_path):
    args = tiny(scene_file, tmp_path, "train.steps=400", "train.checkpoint_every=1", "train.image_every=1000")
    command = [sys.executable, "-m", "learned.train", "--mode", "teacher", "--no-progress", *args]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            if (tmp_path / "last.pt").exists() and load_checkpoint(tmp_path / "last.pt")["step"] >= 3:
                break
            time.sleep(0.05)
        time.sleep(0.3)  # kill it somewhere inside the next steps (possibly while writing)
        process.send_signal(signal.SIGKILL)
    finally:
        process.wait(timeout=30)
    assert process.returncode == -signal.SIGKILL
    ckpt = load_checkpoint(tmp_path / "last.pt")   # the file under the final name is always complete
    step = ckpt["step"]
    assert 3 <= step < 400
    assert main(["--mode", "teacher", "--resume", "--no-progress", *args[:-2], f"train.steps={step + 2}",
                 "train.checkpoint_every=1"]) == 0
    assert load_checkpoint(tmp_path / "last.pt")["step"] == step + 2


def torchrun_two_ranks(mode: str, overrides, timeout: float) -> None:
    """``torchrun --standalone --nproc_per_node 2 -m learned.train --mode MODE`` (gloo, one thread a rank) with
    the config ``overrides``; asserts it exits 0."""
    torchrun = os.path.join(os.path.dirname(sys.executable), "torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([torchrun, "--standalone", "--nproc_per_node", "2", "-m", "learned.train", "--mode",
                             mode, "--no-progress", *overrides],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, result.stderr[-3000:]


@pytest.mark.skipif(shutil.which("torchrun", path=os.path.dirname(sys.executable)) is None,
                    reason="torchrun not installed beside the Python interpreter")
def test_torchrun_two_processes_match_one(scene_file, tmp_path):
    """Two gloo ranks, 2 windows each, equal one process with the global batch of 4 (to float tolerance): the
    weights, and the losses logged in log.jsonl."""
    extra = ("train.steps=3", "data.augment=false")
    torchrun_two_ranks("teacher", tiny(scene_file, tmp_path / "ddp", *extra), timeout=120)
    Trainer(load_config(None, tiny(scene_file, tmp_path / "one", *extra), mode="teacher"), progress=False).run()
    a, b = params(tmp_path / "ddp" / "last.pt"), params(tmp_path / "one" / "last.pt")
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5)
    assert not torch.equal(a["stem.0.weight"], load_checkpoint(tmp_path / "one" / "last.pt")["model"]["stem.0.weight"] * 0)
    # the logged losses are the global batch's (they were rank 0's half batch: 0.48 against 1.10 in the report)
    import json

    logs = [[json.loads(line) for line in (tmp_path / run / "log.jsonl").read_text().splitlines()]
            for run in ("ddp", "one")]
    assert [line["step"] for line in logs[0]] == [line["step"] for line in logs[1]] == [1, 2, 3]
    for ddp, one in zip(*logs):
        assert set(ddp) == set(one) and {"loss/total", "loss/teacher", "loss/twist"} <= set(one)
        for key in one:
            assert ddp[key] == pytest.approx(one[key], rel=1e-4, abs=1e-6), (key, ddp, one)


@pytest.mark.skipif(shutil.which("torchrun", path=os.path.dirname(sys.executable)) is None,
                    reason="torchrun not installed beside the Python interpreter")
def test_torchrun_student_two_processes_match_one(scene_file, tmp_path):
    """A student under torchrun: its loss reads only the finest inverse depth, so the coarse decoder heads get
    no gradient. It failed at the second step (DDP: "Expected to have finished reduction in the prior
    iteration ... Parameter indices which did not receive grad for rank 0: 30 31"); now two gloo ranks train
    and equal one process with the global batch."""
    teacher = tmp_path / "teacher"
    Trainer(load_config(None, tiny(scene_file, teacher, "train.steps=1"), mode="teacher"), progress=False).run()
    extra = ("train.steps=2", "data.augment=false", f"train.teacher={teacher / 'last.pt'}")
    torchrun_two_ranks("student", tiny(scene_file, tmp_path / "ddp", *extra), timeout=180)
    Trainer(load_config(None, tiny(scene_file, tmp_path / "one", *extra), mode="student"), progress=False).run()
    a, b = params(tmp_path / "ddp" / "last.pt"), params(tmp_path / "one" / "last.pt")
    assert load_checkpoint(tmp_path / "ddp" / "last.pt")["step"] == 2
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("mode, extra", [("teacher", ()), ("teacher", ("train.twist_weight=0",)),
                                         ("student", ()), ("finetune", ())])
def test_ddp_sees_as_outputs_exactly_the_parameters_the_loss_trains(scene_file, tmp_path, mode, extra):
    """What DDP's find_unused_parameters relies on: the parameters reached back from the outputs of the module it
    wraps (Trainer.net's forward under torchrun) are those the run's loss gives a gradient; and it searches for
    unused ones only where some exist."""
    from learned.data import collate
    from learned.train import LossOutputs, loss_outputs

    teacher = tmp_path / "teacher"
    if mode != "teacher":
        Trainer(load_config(None, tiny(scene_file, teacher, "train.steps=1"), mode="teacher"), progress=False).run()
        extra = (*extra, f"train.teacher={teacher / 'last.pt'}")
    trainer = Trainer(load_config(None, tiny(scene_file, tmp_path / "run", "train.steps=1", *extra), mode=mode),
                      progress=False)
    all_scales, twist = loss_outputs(trainer.config)
    batch = collate([trainer.dataset[i] for i in range(2)])

    def trained(backward) -> set[str]:
        trainer.model.zero_grad(set_to_none=True)
        backward()
        return {name for name, p in trainer.model.named_parameters() if p.grad is not None}

    wrapped = LossOutputs(trainer.model, all_scales=all_scales, twist=twist)
    reached = trained(lambda: sum(t.sum() for t in (*wrapped(batch["volume"]).inverse_depths,
                                                    wrapped(batch["volume"]).twist) if t.requires_grad).backward())
    by_loss = trained(lambda: trainer.loss(batch)[0].backward())
    assert reached == by_loss
    everything = {name for name, _ in trainer.model.named_parameters()}
    assert (by_loss == everything) == (all_scales and twist)


def test_an_empty_train_out_is_refused_not_taken_for_the_current_folder(scene_file, tmp_path, monkeypatch, capsys):
    """`train.out=$OUT` with OUT unset: was a run that wrote last.pt, config.json, log.jsonl and tb/ into the
    current folder (Path("") is "."), exit 0."""
    monkeypatch.chdir(tmp_path)
    args = [a for a in tiny(scene_file, tmp_path) if not a.startswith("train.out=")]
    assert main(["--mode", "teacher", "--no-progress", *args, "train.steps=1", "train.out="]) == 2
    assert "train.out is empty" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("env", [{"RANK": "1"}, {"RANK": "1", "WORLD_SIZE": "1"}, {"RANK": "2", "WORLD_SIZE": "2"}])
def test_a_stray_rank_outside_a_torchrun_job_is_refused(scene_file, tmp_path, capsys, monkeypatch, env):
    """RANK=1 left in the environment by a scheduler, without WORLD_SIZE (or WORLD_SIZE=1): the run took itself for
    rank 1 of a torchrun job, trained, wrote nothing (no folder) and exited 0. Now refused in one line naming the
    variables, by the command and by Trainer; nothing is written. (torchrun itself: the test above.)"""
    from conftest import one_line_error

    monkeypatch.delenv("WORLD_SIZE", raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    out = tmp_path / "run"
    status, err = one_line_error(lambda: main(["--mode", "teacher", "--no-progress",
                                               *tiny(scene_file, out, "train.steps=2")]), capsys)
    assert status == 2, err
    world = f"WORLD_SIZE={env['WORLD_SIZE']}" if "WORLD_SIZE" in env else "WORLD_SIZE not set"
    assert f"the environment says RANK={env['RANK']}, {world}: not a rank of a torchrun job" in err, err
    assert "unset RANK" in err and not out.exists()
    with pytest.raises(ValueError, match="not a rank of a torchrun job"):
        Trainer(load_config(None, tiny(scene_file, out, "train.steps=2"), mode="teacher"), progress=False)
    assert not out.exists()


def test_the_curves_of_a_run_stopped_before_its_first_checkpoint_are_not_appended_to(scene_file, tmp_path, capsys):
    """A run killed before its first checkpoint leaves config.json, log.jsonl and tb/ without last.pt; a new run
    into that train.out (other settings, no flag) was taken: it appended its steps to log.jsonl (step 1 twice) and
    its events beside the old ones in tb/, exit 0. Now refused in one line, the folder untouched; --overwrite
    starts afresh: each step logged once."""
    from conftest import one_line_error

    out = tmp_path / "run"
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=3")]) == 0
    (out / "last.pt").unlink()   # as a kill before the first checkpoint leaves the folder
    before = {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()}
    args = ["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=2", "train.lr=1e-3")]
    status, err = one_line_error(lambda: main(args), capsys)
    assert status == 2 and "holds the learning curves of an earlier run that wrote no checkpoint" in err, err
    assert "log.jsonl" in err and "--overwrite" in err
    assert {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()} == before
    assert main([*args, "--overwrite"]) == 0
    steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert steps == [1, 2]
    assert len(list((out / "tb").glob("events.out.tfevents.*"))) <= 1   # the new run's alone (if TensorBoard is there)


def _damaged(state: dict, part: str) -> None:
    """Damage ``part`` of the checkpoint ``state`` in place, as a crafted or corrupted file would hold it."""
    if part == "rng":
        state["rng"] = {**state["rng"], "torch": torch.zeros(3, dtype=torch.uint8)}
    elif part == "rng_missing":
        state["rng"] = {}
    else:
        first = state["optimizer"]["state"][0]
        first["exp_avg"] = torch.zeros(7) if part == "optimizer_shape" else first["exp_avg"] * float("nan")


@pytest.mark.parametrize("part, message", [
    ("rng", r"its random generator states \(rng\) cannot be restored \(RuntimeError: "),
    ("rng_missing", r"its random generator states \(rng\) cannot be restored \(KeyError: 'python'\)"),
    ("optimizer_shape", r"its optimizer state does not fit this run \(exp_avg of parameter 0: \[7\], the "
                        r"parameter's \[4, 5, 3, 3\]\)"),
    ("optimizer_nan", r"its optimizer state holds NaN or infinite values \(exp_avg of parameter 0\)"),
], ids=["rng_of_another_size", "rng_missing", "optimizer_of_another_shape", "optimizer_nan"])
def test_resume_refuses_a_damaged_optimizer_or_rng_state_in_one_line(scene_file, tmp_path, capsys, part, message):
    """--resume of a last.pt whose RNG states or optimizer state were damaged: was a traceback (torch's
    `Expected a CPUGeneratorImplState of size 5056`, `KeyError: 'python'`, or at the first step `The size of
    tensor a (7) must match ...`), exit 1; a NaN in AdamW's moments stopped the run at its first step as a
    diverged run ('a lower train.lr ... may keep the run stable'). Now one line naming last.pt, exit 2, the
    checkpoint and the learning curves as they were."""
    from conftest import one_line_error

    out = tmp_path / "run"
    args = ["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=2")]
    assert main(args) == 0
    state = torch.load(out / "last.pt", weights_only=True)
    _damaged(state, part)
    torch.save(state, out / "last.pt")
    before = {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()}
    status, err = one_line_error(lambda: main([*args[:-1], "train.steps=4", "--resume"]), capsys)
    assert status == 2 and re.search(f"{re.escape(str(out / 'last.pt'))}: {message}", err), err
    assert {path.name: path.read_bytes() for path in out.iterdir() if path.is_file()} == before


def test_links_planted_in_the_output_folder_are_not_followed(scene_file, tmp_path):
    """config.json was written with Path.write_text, which followed a planted link out of the folder."""
    outside = tmp_path / "outside.txt"
    outside.write_text("precious\n")
    out = tmp_path / "run"
    out.mkdir()
    for name in ("config.json", f"last.pt.{os.getpid()}.partial"):
        (out / name).symlink_to(outside)
    Trainer(load_config(None, tiny(scene_file, out, "train.steps=2"), mode="teacher"), progress=False).run()
    assert outside.read_text() == "precious\n"
    assert not (out / "config.json").is_symlink() and '"mode": "teacher"' in (out / "config.json").read_text()
    assert load_checkpoint(out / "last.pt")["step"] == 2


@pytest.mark.skipif(sys.platform == "win32", reason="RLIMIT_FSIZE is POSIX")
def test_a_file_size_limit_stops_training_with_one_line_naming_the_file(scene_file, tmp_path):
    """Under `ulimit -f 1` TensorBoard's writer thread printed a traceback, then the run ended with
    `error: [Errno 27] File too large`, naming no file (log.jsonl was appended unguarded; torch.save's zip writer
    turned last.pt's error into a RuntimeError with a traceback). Now TensorBoard's failure is one warning naming
    its folder (TensorBoard off, the run goes on), and log.jsonl's or last.pt's is one error naming the file."""
    import resource

    def limited(limit: int, out: Path, *extra: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "learned.train", "--mode", "teacher", "--no-progress",
                               *tiny(scene_file, out, *extra)], cwd=ROOT, capture_output=True, text=True,
                              env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=120,
                              preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)))

    # 2 KiB (config.json, with its long paths, fits): TensorBoard's event file outgrows it at the first images,
    # log.jsonl some steps later
    out = tmp_path / "small"
    done = limited(2048, out, "train.steps=40", "train.checkpoint_every=100", "train.image_every=1")
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    warning, error = done.stderr.strip().splitlines()
    assert warning == (f"python -m learned.train: warning: TensorBoard could not write in {out / 'tb'} ([Errno 27] "
                       f"File too large): it is off for the rest of this run; the learning curves go on in "
                       f"{out / 'log.jsonl'}"), warning
    assert error.startswith("python -m learned.train: error: File too large while appending step ") and \
        error.endswith(f"to the learning curves (a line cut short there is dropped by --resume): {out / 'log.jsonl'}")
    # 2 KiB again, TensorBoard and log.jsonl writing little: the checkpoint outgrows it in its first record (where
    # torch.save turned the OSError into a RuntimeError); nothing of it is left
    out = tmp_path / "checkpoint"
    done = limited(2048, out, "train.steps=2", "train.log_every=100", "train.image_every=100")
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip() == ("python -m learned.train: error: File too large while writing; nothing was written "
                                   f"under this name (the temporary file was removed): {out / 'last.pt'}")
    assert sorted(path.name for path in out.iterdir()) == ["config.json", "log.jsonl", "tb"]


def test_twist_scale_is_one_rms_per_vector_with_a_floor_from_the_bounds():
    from types import SimpleNamespace

    from learned.model import ModelConfig
    from learned.train import twist_scale

    twists = np.array([[3.0, 0.0, 4.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.03, 0.04]])
    dataset = SimpleNamespace(_gt=[{"twists": twists}, None])
    model = ModelConfig(max_speed=10.0, max_angular_speed=2.0)
    scale = twist_scale(dataset, model).numpy()
    # v: mean |v|^2 over the two twists = 12.5, per component / 3; omega: sqrt(0.00125 / 3) = 0.02 is below
    # the floor 0.05 * 2 rad/s
    assert np.allclose(scale[:3], np.sqrt(25.0 / 6.0)) and np.allclose(scale[3:], 0.1)
    assert np.allclose(twist_scale(SimpleNamespace(_gt=[None]), model).numpy(), [10, 10, 10, 2, 2, 2])


def test_cosine_schedule_warms_up_then_decays_to_a_hundredth():
    from learned.train import learning_rate

    config = load_config(None, ["train.lr=0.01", "train.steps=110", "train.schedule=cosine", "train.warmup_steps=10"])
    rates = [learning_rate(s, config) for s in range(110)]
    assert rates[0] == pytest.approx(0.001) and rates[9] == pytest.approx(0.01)
    assert rates[60] == pytest.approx(0.01 * (0.01 + 0.99 * 0.5)) and rates[-1] > 0.0001
    assert all(type(r) is float for r in rates) and all(np.diff(rates[10:]) <= 0)
    assert learning_rate(5, load_config(None, ["train.lr=0.01"])) == 0.01


def test_validation_losses_are_logged_on_the_held_out_files(scene_file, tmp_path):
    import json

    config = load_config(None, tiny(scene_file, tmp_path, "train.steps=4", "train.val_every=2",
                                    f'data.val_files=["{scene_file}"]', "data.val_windows=3"), mode="teacher")
    trainer = Trainer(config, progress=False)
    trainer.run()
    lines = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    val = [line for line in lines if "val/loss" in line]
    assert [line["step"] for line in val] == [2, 4]
    dataset, picks = trainer.validation
    assert len(picks) == 3
    loss, _, _ = trainer.loss(collate_items(dataset, picks), net=trainer.model)   # the same windows, recomputed
    assert val[-1]["val/loss"] == pytest.approx(float(loss), rel=1e-5)


def collate_items(dataset, picks):
    from learned.data import collate
    return collate([dataset[i] for i in picks])


def test_speed_loss_and_known_speed_windows(scene_file):
    import h5py

    from learned.data import H5WindowDataset
    from learned.losses import speed_loss

    twist = torch.tensor([[3.0, 0.0, 4.0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]])
    assert float(speed_loss(twist, torch.tensor([10.0, float("nan")]))) == pytest.approx(0.25)
    assert float(speed_loss(twist, torch.tensor([float("nan")] * 2))) == 0.0
    hidden = H5WindowDataset([{"path": str(scene_file), "use_gt": False, "known_speed": True}], window_us=100_000)
    none = H5WindowDataset([{"path": str(scene_file), "use_gt": False}], window_us=100_000)
    with h5py.File(scene_file) as f:
        times, twists = f["gt/poses_t"][:], f["gt/twists"][:]
    item, sample = hidden[1], hidden.sample(1)
    middle = (sample.t0_us + sample.t1_us) // 2
    expected = np.linalg.norm(twists[np.argmin(np.abs(times - middle)), :3])
    assert sample.depth is None and sample.twist is None and not bool(item["has_twist"])
    assert float(item["speed"]) == pytest.approx(expected, rel=1e-6)
    assert np.isnan(float(none[1]["speed"]))
    known = H5WindowDataset([{"path": str(scene_file), "use_gt": False, "known_twist": True}], window_us=100_000)
    assert known.sample(1).depth is None and bool(known[1]["has_twist"])
    assert np.allclose(known.sample(1).twist, twists[np.argmin(np.abs(times - middle))])


def test_contrast_twist_truth_warps_with_the_true_twist(scene_file, tmp_path):
    """The ablation's switch: with contrast_twist=truth the student's contrast term uses the file's twist,
    so the loss equals the shared objective at the network's depth and the true twist."""
    from cmax.contrast import SHARED_OBJECTIVE, DepthMotion
    from learned.data import collate
    from learned.train import _events

    teacher = tmp_path / "teacher"
    Trainer(load_config(None, tiny(scene_file, teacher, "train.steps=1"), mode="teacher"), progress=False).run()
    files = f'data.files=[{{"path": "{scene_file}", "use_gt": false, "known_twist": true}}]'
    config = load_config(None, tiny(scene_file, tmp_path / "s", "train.steps=1", f"train.teacher={teacher / 'last.pt'}",
                                    "train.contrast_twist=truth", "train.speed_weight=0", "train.lam=1.0") + [files],
                         mode="student")
    trainer = Trainer(config, progress=False)
    batch = collate([trainer.dataset[i] for i in range(3)])
    loss, terms, output = trainer.loss(batch)
    expected = SHARED_OBJECTIVE(_events(batch, trainer.dataset.width, trainer.dataset.height),
                                DepthMotion(output.inverse_depth, batch["twist"])).mean()
    assert float(loss) == pytest.approx(float(expected), rel=1e-6)
    with pytest.raises(ValueError, match="contrast_twist"):
        load_config(None, ["train.contrast_twist=gyro"])


def test_the_training_device_is_chosen_and_checked(monkeypatch):
    """``train.device``: cpu as given; ``auto`` is the CPU where torch sees no GPU and ``cuda`` the rank's own GPU
    where it does; a GPU asked for where there is none is one clear error; a bad name is refused by the config."""
    from learned.config import TrainConfig
    from learned.device import resolve_device
    from learned.train import ddp_backend, on_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("cpu") == torch.device("cpu") == resolve_device("auto", 1)
    with pytest.raises(ValueError, match="sees no CUDA device"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="device must be"):
        resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto", 1) == torch.device("cuda:1") == resolve_device("cuda", 1)
    assert resolve_device("cuda:0", 1) == torch.device("cuda:0")
    assert ddp_backend(torch.device("cuda:1")) == "nccl" and ddp_backend(torch.device("cpu")) == "gloo"
    with pytest.raises(ValueError, match="train.device"):
        TrainConfig(device="gpu")
    batch = {"volume": torch.zeros(2, 5, 4, 4), "valid": torch.ones(2, 3, dtype=torch.bool), "name": ["a", "b"]}
    moved = on_device(batch, torch.device("meta"))
    assert moved["volume"].device.type == moved["valid"].device.type == "meta" and moved["name"] == ["a", "b"]


def test_a_step_on_the_training_device_moves_the_batch_model_and_teacher(scene_file, tmp_path, monkeypatch):
    """The trainer puts the network, the frozen teacher and every batch on ``train.device`` (the CPU here:
    ``auto`` without a GPU) and trains as before: the same losses as the default device."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    teacher_out = tmp_path / "teacher"
    assert main(["--mode", "teacher", *tiny(scene_file, teacher_out, "train.steps=2")]) == 0
    runs = {}
    for device in ("cpu", "auto"):
        out = tmp_path / f"student_{device}"
        config = load_config(None, tiny(scene_file, out, "train.steps=2", f"train.teacher={teacher_out / 'last.pt'}",
                                        f"train.device={device}"), mode="student")
        trainer = Trainer(config, progress=False)
        assert trainer.device == torch.device("cpu")
        assert next(trainer.model.parameters()).device == trainer.device == next(trainer.teacher.parameters()).device
        assert all(v.device == trainer.device for v in next(trainer._batches()).values() if torch.is_tensor(v))
        runs[device] = trainer.run()
    assert runs["cpu"] == runs["auto"]


def test_a_diverging_run_stops_and_keeps_the_last_good_checkpoint(scene_file, tmp_path, capsys):
    """lr=1e8 without clipping: the loss goes NaN after a few steps. The run went on, replaced last.pt with NaN
    weights at every checkpoint and ended with exit 0; it must stop at the first non-finite step, name it and
    the terms, and leave last.pt as the last finite checkpoint."""
    import json

    args = ["--mode", "teacher", "--no-progress",
            *tiny(scene_file, tmp_path, "train.steps=12", "train.lr=1e8", "train.clip_grad_norm=0",
                  "train.checkpoint_every=1")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "training stopped and nothing was saved" in err, err
    step = int(err.split("error: step ")[1].split(":")[0])
    kept = load_checkpoint(tmp_path / "last.pt")   # loads: every weight finite
    assert kept["step"] == step - 1 and f"(step {step - 1}) is kept" in err, err
    assert all(torch.isfinite(t).all() for t in kept["model"].values() if t.is_floating_point())
    assert "the loss is not finite (loss/total=nan" in err or "weight tensors non-finite" in err, err
    logged = [json.loads(line)["step"] for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert max(logged) < step                        # the failed step is not in the learning curve


def test_resume_compares_the_files_not_their_spelling(scene_file, tmp_path, capsys, monkeypatch):
    """A run started with data.files=["data.h5"] resumed as ["./data.h5"] or by its absolute path reads the same
    file: it resumes (it was refused, the paths compared as typed). The same relative name typed in another
    folder names another file: refused, naming both absolute paths."""
    from conftest import one_line_error

    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    shutil.copyfile(scene_file, tmp_path / "a" / "data.h5")
    shutil.copyfile(scene_file, tmp_path / "b" / "data.h5")
    out = tmp_path / "run"
    monkeypatch.chdir(tmp_path / "a")
    assert main(["--mode", "teacher", "--no-progress", *tiny(Path("data.h5"), out, "train.steps=2")]) == 0
    for spelling, steps in (("./data.h5", 3), (tmp_path / "a" / "data.h5", 4)):
        assert main(["--mode", "teacher", "--no-progress", "--resume",
                     *tiny(spelling, out, f"train.steps={steps}")]) == 0, spelling
        assert load_checkpoint(out / "last.pt")["step"] == steps
    capsys.readouterr()
    monkeypatch.chdir(tmp_path / "b")
    status, err = one_line_error(lambda: main(["--mode", "teacher", "--no-progress", "--resume",
                                               *tiny(Path("data.h5"), out, "train.steps=5")]), capsys)
    assert status == 2 and "was written with other settings than this run's" in err, err
    assert f'data.files=["{tmp_path / "a" / "data.h5"}"] (now ["{tmp_path / "b" / "data.h5"}"])' in err, err


def test_resume_refuses_a_run_that_differs_from_the_checkpoint(scene_file, slider_file, tmp_path, capsys):
    """--resume continued a teacher run as a student, or with other data, seed, batch and lr, with exit 0 and no
    note (and overwrote config.json); another model config gave a raw load_state_dict dump. Each is refused in
    one line naming the fields (recorded, now); steps, logging and checkpoint intervals may change."""
    import hashlib

    from conftest import one_line_error

    data = tmp_path / "data.h5"
    shutil.copyfile(scene_file, data)
    out = tmp_path / "run"
    first = ["--mode", "teacher", "--no-progress", *tiny(data, out, "train.steps=2")]
    assert main(first) == 0
    capsys.readouterr()
    digest = hashlib.md5((out / "last.pt").read_bytes()).hexdigest()
    config_json = (out / "config.json").read_text()
    cases = [
        (["--mode", "student", f"train.teacher={ROOT / 'learned' / 'pretrained' / 'student.pt'}"],
         ['mode="teacher" (now "student")', 'train.teacher="" (now "']),
        (["--mode", "teacher", "train.batch_size=2", "train.seed=9", "train.lr=0.5", f'data.files=["{scene_file}"]'],
         [f'data.files=["{data}"] (now ["{scene_file}"])', "train.batch_size=4 (now 2)", "train.lr=0.003 (now 0.5)",
          "train.seed=0 (now 9)"]),
        (["--mode", "teacher", "model.width=8"], ["model.width=4 (now 8)"]),
    ]
    for extra, expected in cases:
        mode, rest = extra[:2], extra[2:]
        args = [*mode, "--no-progress", "--resume", *tiny(data, out, "train.steps=4"), *rest]
        status, err = one_line_error(lambda: main(args), capsys)
        assert status == 2 and "was written with other settings than this run's" in err, err
        assert all(text in err for text in expected), (expected, err)
        assert "Missing key" not in err and "state_dict" not in err
    # what does not change the steps still to run may change
    assert main(["--mode", "teacher", "--no-progress", "--resume",
                 *tiny(data, out, "train.steps=3", "train.log_every=2", "train.checkpoint_every=5")]) == 0
    capsys.readouterr()
    assert load_checkpoint(out / "last.pt")["step"] == 3
    assert hashlib.md5((out / "last.pt").read_bytes()).hexdigest() != digest and config_json
    # the same settings over files that changed: the stored data order no longer fits
    shutil.copyfile(slider_file, data)
    status, err = one_line_error(lambda: main(["--mode", "teacher", "--no-progress", "--resume",
                                               *tiny(data, out, "train.steps=4")]), capsys)
    assert status == 2 and "was trained on another data order: dataset_size" in err, err


def test_a_run_never_writes_over_its_own_teacher(scene_file, tmp_path, capsys):
    """train.teacher=runs/tt/last.pt train.out=runs/tt --overwrite replaced the teacher with the finetune's
    checkpoint; the refusal without --overwrite did not say that the file is the teacher."""
    from conftest import one_line_error

    out = tmp_path / "tt"
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=1")]) == 0
    capsys.readouterr()
    before = (out / "last.pt").read_bytes()
    for mode in ("finetune", "student"):
        for flags in ([], ["--overwrite"], ["--resume"]):
            args = ["--mode", mode, "--no-progress", *flags,
                    *tiny(scene_file, out, "train.steps=2", f"train.teacher={out / '.' / 'last.pt'}")]
            status, err = one_line_error(lambda: main(args), capsys)
            assert status == 2 and f"is {out / 'last.pt'}, the checkpoint this run writes" in err, err
            assert "own teacher" in err
    assert (out / "last.pt").read_bytes() == before


def test_validation_uses_the_sensor_size_of_its_own_files(scene_file, slider_file, tmp_path):
    """The contrast loss of a validation batch was built with the TRAINING files' sensor size: validating 64x48
    files while training on 48x36 ones failed after the first step ("inverse_depth grid ... is finer than the
    image"), and the other way round gave a silently different validation loss."""
    import json

    teacher = tmp_path / "teacher"
    Trainer(load_config(None, tiny(scene_file, teacher, "train.steps=1"), mode="teacher"), progress=False).run()
    for train_file, val_file in ((scene_file, slider_file), (slider_file, scene_file)):
        out = tmp_path / f"{train_file.stem}_{val_file.stem}"
        config = load_config(None, tiny(train_file, out, "train.steps=1", "train.val_every=1", "data.val_windows=2",
                                        f'data.val_files=["{val_file}"]', f"train.teacher={teacher / 'last.pt'}"),
                             mode="finetune")
        trainer = Trainer(config, progress=False)
        trainer.run()
        logged = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
        val = [line["val/loss"] for line in logged if "val/loss" in line]
        dataset, picks = trainer.validation
        assert (dataset.width, dataset.height) != (trainer.dataset.width, trainer.dataset.height)
        batch = collate_items(dataset, picks)
        loss, _, _ = trainer.loss(batch, net=trainer.model, size=(dataset.width, dataset.height))
        assert val == [pytest.approx(float(loss), rel=1e-5)]


def _tensorboard(folder: Path, tag: str) -> list[tuple[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(folder)).Reload()
    return [(event.step, round(event.value, 6)) for event in events.Scalars(tag)]


def test_overwrite_and_resume_keep_one_run_in_the_learning_curves(scene_file, tmp_path):
    """--overwrite kept the old run's TensorBoard events beside the new ones (lr: 0.1, 0.1, 0.1, then 1e-4 ...);
    --resume after a kill logged the steps after the checkpoint twice in log.jsonl (nor purged TensorBoard)."""
    import json

    pytest.importorskip("tensorboard")
    out = tmp_path / "run"
    run = ["--mode", "teacher", "--no-progress"]
    assert main([*run, *tiny(scene_file, out, "train.steps=3", "train.lr=0.1")]) == 0
    assert main([*run, "--overwrite", *tiny(scene_file, out, "train.steps=3")]) == 0
    assert _tensorboard(out / "tb", "lr") == [(1, 0.003), (2, 0.003), (3, 0.003)]
    assert [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()] == [1, 2, 3]
    # a kill after step 5 was logged and before its checkpoint: last.pt at step 4, log.jsonl up to step 5
    assert main([*run, "--resume", *tiny(scene_file, out, "train.steps=4")]) == 0
    at_four = (out / "last.pt").read_bytes()
    assert main([*run, "--resume", *tiny(scene_file, out, "train.steps=5")]) == 0
    (out / "last.pt").write_bytes(at_four)
    with open(out / "log.jsonl", "a") as log:
        log.write('{"step": 6, "loss/to')                      # the half-written line of the killed run
    assert main([*run, "--resume", *tiny(scene_file, out, "train.steps=6")]) == 0
    lines = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines] == [1, 2, 3, 4, 5, 6]
    assert [step for step, _ in _tensorboard(out / "tb", "loss/total")] == [1, 2, 3, 4, 5, 6]


def test_overwrite_removes_the_earlier_run_before_the_first_step(scene_file, tmp_path, capsys):
    """--overwrite removed log.jsonl and tb/ and wrote the new config.json at once, but left the earlier run's
    last.pt until the new run's first checkpoint: a new run that diverged before it left the old last.pt beside
    the new config.json and log.jsonl, and said "no checkpoint had been written yet". Now the earlier run's files
    go before the first step, and the message about last.pt is true (Trainer used directly over an old folder)."""
    import json

    from conftest import one_line_error
    from learned.train import TrainingDiverged

    out = tmp_path / "run"
    run = ["--mode", "teacher", "--no-progress"]
    assert main([*run, *tiny(scene_file, out, "train.steps=4")]) == 0
    old = (out / "last.pt").read_bytes()
    capsys.readouterr()
    diverging = ("train.steps=12", "train.lr=1e8", "train.clip_grad_norm=0", "train.checkpoint_every=20")
    status, err = one_line_error(lambda: main([*run, "--overwrite", *tiny(scene_file, out, *diverging)]), capsys)
    assert status == 2 and "training stopped and nothing was saved; no checkpoint had been written yet" in err, err
    assert not (out / "last.pt").exists()                         # the earlier run's checkpoint is gone too
    assert json.loads((out / "config.json").read_text())["train"]["lr"] == 1e8
    lines = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert lines and all(line["lr"] > 1 for line in lines)        # the new run's curves alone
    # the Python API over a folder that holds an earlier run's last.pt (no --overwrite to remove it)
    (out / "last.pt").write_bytes(old)
    with pytest.raises(TrainingDiverged, match=r"this run had written no checkpoint yet \(.*last\.pt is an "
                                               r"earlier run's, left as it was\)"):
        Trainer(load_config(None, tiny(scene_file, out, *diverging), mode="teacher"), progress=False).run()
    assert (out / "last.pt").read_bytes() == old
    # a run refused before training (no window) does not touch the earlier run
    status, err = one_line_error(lambda: main([*run, "--overwrite", *tiny(scene_file, out, "train.steps=2",
                                                                          "data.window_us=5000000")]), capsys)
    assert status == 2 and "hold no window" in err and (out / "last.pt").read_bytes() == old


def test_settings_that_did_nothing_or_said_the_wrong_thing(scene_file, tmp_path, capsys):
    """data.workers was checked and never used; a run shorter than train.log_every logged nothing (the last step
    only when steps % log_every == 0); train.steps=0 spoke of a last.pt that did not exist; a labelled file's
    own K in data.files was silently replaced by its gt/K."""
    import dataclasses
    import json
    import warnings

    from learned.config import DataConfig, config_from_dict
    from learned.data import H5WindowDataset

    # data.workers: gone; an old config or checkpoint that stores it at 0 loads quietly, another value warns
    assert "workers" not in {f.name for f in dataclasses.fields(DataConfig)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_config(None, ["data.workers=0"]).data == DataConfig()
        assert config_from_dict({"data": {"workers": 0, "window_us": 5000}}).data.window_us == 5000
    with pytest.warns(UserWarning, match=r"data\.workers=4 is ignored: data\.workers is no longer a setting"):
        load_config(None, ["data.workers=4"])
    # the last step is logged whatever train.log_every
    out = tmp_path / "short"
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=3", "train.log_every=10")]) == 0
    assert [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()] == [3]
    capsys.readouterr()
    # train.steps=0 on a new folder: says so, writes nothing
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, tmp_path / "zero", "train.steps=0")]) == 0
    assert capsys.readouterr().out == "teacher: nothing to train: train.steps=0; give train.steps=N (N >= 1)\n"
    assert not (tmp_path / "zero").exists()
    # K in a labelled file's entry: the same as its gt/K is fine, another one is refused, use_gt false honours it
    gt_K = H5WindowDataset([scene_file], window_us=100_000)._gt[0]["K"]
    H5WindowDataset([{"path": str(scene_file), "K": gt_K.tolist()}], window_us=100_000)
    other = [50.0, 50.0, 24.0, 18.0]
    with pytest.raises(ValueError, match=r"its entry gives K .* but its ground truth .* was made with its gt/K"):
        H5WindowDataset([{"path": str(scene_file), "K": other}], window_us=100_000)
    hidden = H5WindowDataset([{"path": str(scene_file), "K": other, "use_gt": False}], window_us=100_000)
    assert np.allclose(hidden.sample(0).K, [[50, 0, 24], [0, 50, 18], [0, 0, 1]])


def test_no_window_says_the_labelled_centres_fall_off_the_recording(scene_file, tmp_path, capsys):
    """A short labelled file (cmax scene --duration 0.25 --depth-rate 4: depth at 0 and 250 ms only) was refused
    with "each needs 166.5 ms of events ... with at least 100 of them (0 window(s) had fewer)": the file holds
    250 ms of events; the real reason is that labelled windows are centred on gt/depth_t and those centres lie at
    the ends of the recording. Now that reason, with the centres and the events' span, and the longest
    data.window_us that fits one when there is one."""
    from conftest import one_line_error
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene
    from learned.data import H5WindowDataset

    scene = make_scene("slider", seed=51, width=48, height=36, duration_s=1.0, texture_size=64)
    short = simulate_scene(scene, 0.25, EventSimulator(**{**scene.recommended_simulator, "seed": 51}),
                           depth_rate_hz=4).save(tmp_path / "one.h5")
    run = ["--mode", "teacher", "--no-progress", "train.steps=1"]
    status, err = one_line_error(lambda: main([*run, *tiny(short, tmp_path / "a", "data.window_us=166500")]), capsys)
    assert status == 2 and "had fewer" not in err, err
    assert ("data.files hold no window: labelled windows are centred on their file's gt/depth_t, and each of the 2 "
            "window(s) of 166.5 ms (data.window_us) reaches beyond its recording by more than 16.65 ms, a tenth of a "
            "window (one.h5: centres at 0, 250 ms, events from ") in err, err
    assert err.strip().endswith("no window length fits a centre at an end of its recording: give labelled "
                                "recordings with depth times inside their events (cmax scene: a higher --depth-rate "
                                "or a longer --duration)"), err
    # a window longer than the recording (0.6 s, depth every 50 ms): the longest one that fits is named, and fits
    status, err = one_line_error(lambda: main([*run, *tiny(scene_file, tmp_path / "b", "data.window_us=1000000")]),
                                 capsys)
    assert status == 2 and "each of the 13 window(s) of 1000 ms (data.window_us) reaches beyond" in err, err
    longest = int(err.split("data.window_us=")[1].split(" or shorter fits at least one of them")[0])
    assert 0 < longest < 1_000_000
    assert len(H5WindowDataset([scene_file], window_us=longest).off_recording) < 13
    assert len(H5WindowDataset([scene_file], window_us=longest + 1000).off_recording) == 13


def test_the_mode_comes_from_the_command_or_the_config_and_they_must_agree(scene_file, tmp_path, capsys):
    """--mode finetune with a config that says mode = "teacher" trained a finetune without a word; --mode was
    required even though every shipped config states its mode. Now: the config's mode when --mode is absent,
    a one-line refusal when they differ, and one when neither states a mode."""
    from conftest import one_line_error

    config = tmp_path / "teacher.toml"
    config.write_text('mode = "teacher"\n')
    out = tmp_path / "run"
    assert main(["--config", str(config), "--no-progress", *tiny(scene_file, out, "train.steps=1")]) == 0
    assert capsys.readouterr().out.startswith("teacher: 1 steps")
    status, err = one_line_error(lambda: main(["--mode", "finetune", "--config", str(config), "--no-progress",
                                               *tiny(scene_file, tmp_path / "ft", "train.steps=1",
                                                     f"train.teacher={out / 'last.pt'}")]), capsys)
    assert status == 2 and f"--mode finetune, but {config} says mode = 'teacher'" in err, err
    status, err = one_line_error(lambda: main(["--no-progress", *tiny(scene_file, tmp_path / "none",
                                                                      "train.steps=1")]), capsys)
    assert status == 2 and "no mode: give --mode teacher|finetune|student" in err, err
    assert not (tmp_path / "ft").exists() and not (tmp_path / "none").exists()


def test_resume_refuses_to_stretch_a_cosine_schedule(scene_file, tmp_path, capsys):
    """A cosine run of 4 steps resumed with train.steps=8: the schedule's horizon moved, so step 4 ran at a
    learning rate back near the peak, not at the end of the decay (an audit's loss doubled). Refused, naming
    both rates; the constant schedule may still be extended; the 'nothing to train' line of a finished cosine
    run no longer advises raising train.steps."""
    from conftest import one_line_error

    out = tmp_path / "run"
    cosine = ("train.schedule=cosine", "train.warmup_steps=1")
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=4", *cosine)]) == 0
    capsys.readouterr()
    status, err = one_line_error(lambda: main(["--mode", "teacher", "--no-progress", "--resume",
                                               *tiny(scene_file, out, "train.steps=8", *cosine)]), capsys)
    recorded = load_config(None, tiny(scene_file, out, "train.steps=4", *cosine), mode="teacher")
    stretched = load_config(None, tiny(scene_file, out, "train.steps=8", *cosine), mode="teacher")
    assert status == 2 and "cosine schedule spans train.steps=4; train.steps=8 would move" in err, err
    assert (f"(step 4: {learning_rate(4, stretched):.3g}, not {learning_rate(4, recorded):.3g})" in err
            and learning_rate(4, stretched) > 10 * learning_rate(4, recorded)), err
    assert load_checkpoint(out / "last.pt")["step"] == 4
    assert main(["--mode", "teacher", "--no-progress", "--resume", *tiny(scene_file, out, "train.steps=4", *cosine)]) == 0
    assert "its cosine schedule has ended: train further as a new run" in capsys.readouterr().out


def test_resume_refuses_a_teacher_replaced_under_the_same_path(scene_file, tmp_path, capsys):
    """A student resumed after its train.teacher file was overwritten by another network went on learning from
    the new teacher without a word (the config only names the path). The checkpoint records the teacher's
    SHA-256: refused, in one line."""
    from conftest import one_line_error

    teacher, other = tmp_path / "t1", tmp_path / "t2"
    for out, seed in ((teacher, 0), (other, 1)):
        assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=1",
                                                                 f"train.seed={seed}")]) == 0
    path = tmp_path / "teacher.pt"
    shutil.copyfile(teacher / "last.pt", path)
    student = ("--mode", "student", "--no-progress")
    assert main([*student, *tiny(scene_file, tmp_path / "s", "train.steps=1", f"train.teacher={path}")]) == 0
    capsys.readouterr()
    shutil.copyfile(other / "last.pt", path)
    status, err = one_line_error(lambda: main([*student, "--resume", *tiny(scene_file, tmp_path / "s", "train.steps=2",
                                                                           f"train.teacher={path}")]), capsys)
    assert status == 2 and f"train.teacher {path} is not the file" in err and "contents changed" in err, err
    shutil.copyfile(teacher / "last.pt", path)      # restored: resumes
    assert main([*student, "--resume", *tiny(scene_file, tmp_path / "s", "train.steps=2", f"train.teacher={path}")]) == 0


def test_resume_refuses_a_data_file_replaced_by_another_recording_of_as_many_windows(scene_file, tmp_path, capsys):
    """--resume compared only the number of windows of data.files: another recording copied over a data file,
    as long and so with as many windows, was trained on without a word (exit 0). The checkpoint records each
    file's size, events, time span and the SHA-256 of its ends: refused in one line naming the file."""
    import h5py

    from cmax.io import H5Reader, write_h5
    from conftest import one_line_error
    from learned.data import H5WindowDataset

    data, other = tmp_path / "data.h5", tmp_path / "other.h5"
    shutil.copyfile(scene_file, data)
    with H5Reader(scene_file) as reader:     # the same times, the image mirrored: another recording
        ev = reader.window(reader.t_start, reader.t_end + 1)
    from cmax.events import Events
    write_h5(other, Events(ev.width - 1 - ev.x.astype(np.int64), ev.y, ev.t, ev.p, ev.width, ev.height))
    with h5py.File(scene_file, "r") as source, h5py.File(other, "a") as target:
        source.copy("gt", target)
    assert len(H5WindowDataset([data], window_us=100_000)) == len(H5WindowDataset([other], window_us=100_000))
    out = tmp_path / "run"
    assert main(["--mode", "teacher", "--no-progress", *tiny(data, out, "train.steps=2")]) == 0
    capsys.readouterr()
    shutil.copyfile(other, data)
    resume = ["--mode", "teacher", "--no-progress", "--resume", *tiny(data, out, "train.steps=4")]
    status, err = one_line_error(lambda: main(resume), capsys)
    assert status == 2 and "was trained on other data files" in err and f"data.files[0] {data}: " in err, err
    assert load_checkpoint(out / "last.pt")["step"] == 2
    shutil.copyfile(scene_file, data)        # the file restored (a copy: the same bytes): resumes
    assert main(resume) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 4
    # the same size, events and span, other bytes at an end: named by the SHA-256 of the ends
    from learned.train import file_fingerprint, fingerprint_differences

    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(b"x" * 200_000)
    b.write_bytes(b"y" + b"x" * 199_999)
    said = fingerprint_differences([file_fingerprint(a, 10, (0, 5))], [file_fingerprint(b, 10, (0, 5))], ["b.bin"])
    assert said == ["data.files[0] b.bin: its contents (the SHA-256 of the whole file)"], said


def test_a_data_file_changed_in_its_middle_is_not_trusted_on_resume(tmp_path):
    """The fingerprint hashed only the first and last 64 KiB of a data file: an h5 rewritten in place, of the same
    size, events and span, with other bytes in its middle, was trusted by --resume. The whole file is hashed now (the
    hash reused, without reading, only where size, modification time, inode and status change time are the recorded ones); a checkpoint
    of an earlier version, which records the ends alone, is compared by them as before."""
    from learned.train import file_fingerprint, fingerprint_differences

    path = tmp_path / "a.h5"
    path.write_bytes(bytes(range(256)) * 4000)                     # 1,024,000 bytes
    before = file_fingerprint(path, 10, (0, 5))
    with open(path, "r+b") as file:                                # one byte in the middle, in place
        file.seek(512_000)
        file.write(b"\xff")
    after = file_fingerprint(path, 10, (0, 5), recorded=before)
    assert fingerprint_differences([before], [after], ["a.h5"]) == [
        "data.files[0] a.h5: its contents (the SHA-256 of the whole file)"]
    legacy = {key: value for key, value in before.items() if key in ("bytes", "events", "span_us", "ends_sha256")}
    assert fingerprint_differences([legacy], [after], ["a.h5"]) == []           # what the ends alone cannot see
    assert fingerprint_differences([after], [file_fingerprint(path, 10, (0, 5))], ["a.h5"]) == []
    copy = tmp_path / "copy.h5"                                    # the same bytes elsewhere (another inode): agree
    copy.write_bytes(path.read_bytes())
    assert fingerprint_differences([after], [file_fingerprint(copy, 10, (0, 5), recorded=after)], ["a.h5"]) == []
    # the file untouched since (size, mtime, inode, status change time): the hash reused
    assert file_fingerprint(path, 10, (0, 5), recorded={**after, "sha256": "recorded"})["sha256"] == "recorded"


def test_a_data_file_rewritten_in_place_with_its_mtime_set_back_is_read_again_on_resume(tmp_path):
    """The recorded hash was reused where size, modification time and inode were the recorded ones: a byte changed
    in place and the mtime set back (touch -d, cp -p onto the file) kept all three, and --resume trusted the old
    hash. The status change time, which no one can set back, is compared too: the file is read again."""
    import hashlib
    import os

    from learned.train import file_fingerprint, fingerprint_differences

    path = tmp_path / "a.h5"
    path.write_bytes(bytes(range(256)) * 4000)
    before = file_fingerprint(path, 10, (0, 5))
    stat = path.stat()
    with open(path, "r+b") as file:                                # one byte in the middle, in place
        file.seek(512_000)
        file.write(b"\xff")
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))        # its mtime set back
    assert (path.stat().st_size, path.stat().st_mtime_ns, path.stat().st_ino) == (
        stat.st_size, stat.st_mtime_ns, stat.st_ino)
    after = file_fingerprint(path, 10, (0, 5), recorded=before)
    assert after["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest() != before["sha256"]
    assert fingerprint_differences([before], [after], ["a.h5"]) == [
        "data.files[0] a.h5: its contents (the SHA-256 of the whole file)"]


def test_hashing_large_data_files_at_start_shows_a_progress_bar(tmp_path, capsys, monkeypatch):
    """Each start hashes every data file whole (about 1.5 s a GB) with nothing on screen: hundreds of GB looked like
    a hung run. Above HASH_PROGRESS_BYTES a bar [bytes] shows it on stderr; files whose recorded hash is reused
    (size, mtime, inode unchanged) are not read and count nothing; --no-progress (progress=False) shows none."""
    import learned.train as train

    monkeypatch.setattr(train, "HASH_PROGRESS_BYTES", 1 << 20)
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    a.write_bytes(b"a" * (2 << 20))
    b.write_bytes(b"b" * (1 << 20))
    spans = [(0, 5), (0, 7)]
    found = train.data_fingerprints([a, b], [10, 20], spans, [None, None])
    assert found == [train.file_fingerprint(a, 10, (0, 5)), train.file_fingerprint(b, 20, (0, 7))]
    err = capsys.readouterr().err
    assert "hashing data files" in err and "3.00M" in err, err
    assert train.bytes_to_hash(a, found[0]) == 0 and train.bytes_to_hash(b, None) == 1 << 20
    assert train.data_fingerprints([a, b], [10, 20], spans, found) == found      # reused: nothing read, no bar
    assert "hashing" not in capsys.readouterr().err
    train.data_fingerprints([a, b], [10, 20], spans, [None, None], progress=False)
    assert "hashing" not in capsys.readouterr().err
    monkeypatch.setattr(train, "HASH_PROGRESS_BYTES", 4 << 20)                   # small files: no bar
    train.data_fingerprints([a, b], [10, 20], spans, [None, None])
    assert "hashing" not in capsys.readouterr().err


def test_a_validation_file_that_is_a_training_file_is_named(scene_file, slider_file, tmp_path, monkeypatch):
    """data.val_files holding a file of data.files gave a "held-out" learning curve measured on training windows,
    and a file given twice in data.files weighed twice, both without a word. Each is a warning naming the files
    (compared as files: ./a.h5 is a.h5); held-out validation files stay silent."""
    import warnings

    from learned.train import repeated_files

    monkeypatch.chdir(scene_file.parent)
    name = scene_file.name
    said = repeated_files((name, f"./{name}"), ({"path": str(slider_file)}, str(scene_file)))
    assert len(said) == 2, said
    assert said[0].startswith(f"data.files[1] {name} is data.files[0]"), said
    assert said[1].startswith(f"data.val_files[1] {scene_file} is data.files[0], a training file"), said
    assert repeated_files((name,), (str(slider_file), "missing.h5")) == []
    config = load_config(None, tiny(scene_file, tmp_path / "run", "train.steps=1", "train.val_every=1",
                                    f'data.val_files=["{scene_file}"]'), mode="teacher")
    with pytest.warns(UserWarning, match=r"data.val_files\[0\] .* is data.files\[0\], a training file"):
        Trainer(config, progress=False)
    config = load_config(None, tiny(scene_file, tmp_path / "run2", "train.steps=1", "train.val_every=1",
                                    f'data.val_files=["{slider_file}"]'), mode="teacher")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Trainer(config, progress=False)


def test_a_trained_checkpoint_records_its_camera_and_window_for_the_notes_of_depth_and_evaluate(
        scene_file, slider_file, tmp_path, capsys):
    """cmax depth and learned.evaluate noted another sensor size or focal length only from a card beside the
    shipped checkpoint: a network the user trained (its last.pt) on a 48x36 camera ran on another camera without a
    word, and no checkpoint's window length was compared with --window. learned.train now records the training
    camera and window in the checkpoint ("card"), and both commands note a camera or a window that differ."""
    import json

    from learned.evaluate import main as evaluate
    from learned.predict import main as predict

    out = tmp_path / "run"
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=1")]) == 0
    card = load_checkpoint(out / "last.pt")["card"]
    import h5py
    with h5py.File(scene_file, "r") as f:
        K = f["gt/K"][:]
    assert card["size"] == [48, 36] and card["window_s"] == pytest.approx(0.1)
    assert card["K"] == pytest.approx([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    capsys.readouterr()
    base = ["--checkpoint", str(out / "last.pt"), "--quiet"]
    assert predict([str(scene_file), "-o", str(tmp_path / "same"), *base]) == 0     # its own camera and window
    err = capsys.readouterr().err
    assert "the network was trained" not in err and "focal length" not in err, err
    fx = 2 * K[0, 0]   # another camera: the slider file (64x48) with twice the focal length
    assert predict([str(slider_file), "-o", str(tmp_path / "other"), *base, "--K", f"{fx},{fx},31.5,23.5"]) == 0
    err = capsys.readouterr().err
    assert "the network was trained on a 48x36 sensor, this file is 64x48" in err, err
    assert f"the network was trained at {K[0, 0]:.1f} px" in err and "predicted x 2" in err, err
    assert predict([str(scene_file), "-o", str(tmp_path / "short"), *base, "--window", "0.05"]) == 0
    err = capsys.readouterr().err
    assert "the network was trained on windows of 100 ms, these are 50 ms" in err, err
    assert json.loads((tmp_path / "short" / "summary.json").read_text())["window_us"] == 50_000
    assert evaluate(["--checkpoint", str(out / "last.pt"), "--data", str(scene_file), "--window", "0.05"]) == 0
    assert "trained on windows of 100 ms, these are 50 ms" in capsys.readouterr().err


def test_a_cosine_warm_up_as_long_as_the_run_is_named(scene_file, tmp_path):
    """A short run of a shipped config (warm-up 30 steps, train.steps=20) rose in learning rate at every step and
    ended at its peak, schedule = "cosine" notwithstanding, without a word. A warning names both settings."""
    import warnings

    config = load_config(None, tiny(scene_file, tmp_path / "a", "train.steps=3", "train.schedule=cosine",
                                    "train.warmup_steps=3"), mode="teacher")
    assert [learning_rate(s, config) for s in range(3)] == pytest.approx([1e-3, 2e-3, 3e-3])   # only rising
    with pytest.warns(UserWarning, match=r"train.warmup_steps=3 is not shorter than train.steps=3: .* rising to "
                                         r"0.003 at the last step"):
        Trainer(config, progress=False)
    config = load_config(None, tiny(scene_file, tmp_path / "b", "train.steps=3", "train.schedule=cosine",
                                    "train.warmup_steps=1"), mode="teacher")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Trainer(config, progress=False)


@pytest.mark.parametrize("mode", ["teacher", "finetune", "student"])
def test_settings_the_mode_does_not_read_are_named(scene_file, tmp_path, mode):
    """--mode teacher train.teacher=runs/t/last.pt trained a fresh network (the checkpoint, even a missing file,
    never read), and train.speed_weight / collapse_weight / contrast_twist of a teacher, twist_weight of a student,
    changed nothing, all without a word. Each is a warning naming the key; the shipped configs raise none."""
    import warnings

    from learned.train import unread_settings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        shipped = load_config(ROOT / "learned" / "configs" / f"{mode}.toml", [f'data.files=["{scene_file}"]',
                                                                          "train.val_every=0"])
    assert unread_settings(shipped) == []
    if mode == "teacher":
        config = load_config(None, tiny(scene_file, tmp_path / "t", "train.steps=1", "train.teacher=missing.pt",
                                        "train.speed_weight=5", "train.contrast_twist=truth"), mode="teacher")
        with pytest.warns(UserWarning) as said:
            Trainer(config, progress=False)
        text = [str(w.message) for w in said]
        assert any(t.startswith("train.teacher='missing.pt' is not read by --mode teacher") for t in text), text
        assert any(t.startswith("train.speed_weight=5 is not read by --mode teacher") for t in text), text
        assert any(t.startswith("train.contrast_twist='truth' is not read by --mode teacher") for t in text), text
    else:
        config = load_config(None, ["train.teacher=t.pt", "train.twist_weight=3"], mode=mode)
        assert [t[:45] for t in unread_settings(config)] == [f"train.twist_weight=3 is not read by --mode {mode}"[:45]]


def test_a_run_stopped_in_its_warm_up_resumes_with_a_raised_train_steps(scene_file, tmp_path, capsys):
    """--resume with a raised train.steps of a cosine run stopped in its warm-up was refused with the reason
    'step 2: 0.00225, not 0.00225': every step it ran had the rate the longer schedule gives it (the warm-up does
    not depend on train.steps). It resumes, and equals a run of the longer schedule from the start."""
    out, whole = tmp_path / "run", tmp_path / "whole"
    cosine = ("train.schedule=cosine", "train.warmup_steps=4")
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, out, "train.steps=2", *cosine)]) == 0
    assert main(["--mode", "teacher", "--no-progress", "--resume", *tiny(scene_file, out, "train.steps=6", *cosine)]) == 0
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, whole, "train.steps=6", *cosine)]) == 0
    capsys.readouterr()
    resumed, fresh = params(out / "last.pt"), params(whole / "last.pt")
    assert load_checkpoint(out / "last.pt")["step"] == 6
    for name, tensor in fresh.items():
        torch.testing.assert_close(resumed[name], tensor, rtol=0, atol=0)


def test_a_student_on_windows_of_another_length_than_its_teacher_s_is_named(scene_file, tmp_path):
    """A student (or finetune) with data.window_us=50000 under a teacher trained on 100 ms windows: the frozen
    teacher read volumes of half the image motion it was trained on, its inverse depth the student's target,
    without a word. A warning names the teacher and both lengths; equal windows stay silent."""
    import warnings

    teacher = tmp_path / "t"
    assert main(["--mode", "teacher", "--no-progress", *tiny(scene_file, teacher, "train.steps=1")]) == 0
    for mode in ("student", "finetune"):
        config = load_config(None, tiny(scene_file, tmp_path / f"{mode}50", "train.steps=1", "data.window_us=50000",
                                        f"train.teacher={teacher / 'last.pt'}"), mode=mode)
        with pytest.warns(UserWarning, match=r"train.teacher .*last.pt: the network was trained on windows of 100 ms, "
                                             r"these are 50 ms: .*; data.window_us=100000 trains on the teacher's"):
            Trainer(config, progress=False)
    config = load_config(None, tiny(scene_file, tmp_path / "same", "train.steps=1",
                                    f"train.teacher={teacher / 'last.pt'}"), mode="student")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Trainer(config, progress=False)


def test_a_data_file_that_grows_while_it_is_hashed_is_refused(tmp_path):
    """A data file still being written or copied while learned.train hashes it: its fingerprint would hold the size
    before and the SHA-256 of more bytes, recorded as if a whole file (was: recorded without a word). Refused naming it,
    as cmax fit's inputs are (cmax.io.atomic.check_unchanged); whole afterwards, it is fingerprinted."""
    from learned.train import file_fingerprint

    path = tmp_path / "growing.h5"
    path.write_bytes(b"x" * 3_000_000)
    grown = []

    def still_copying(nbytes: int) -> None:          # the writer appends while the first block is hashed
        if not grown:
            with open(path, "ab") as file:
                file.write(b"y" * 100)
            grown.append(nbytes)

    with pytest.raises(ValueError, match="growing.h5 changed while it was read to hash it: it has 3,000,100 bytes"):
        file_fingerprint(path, 10, (0, 5), read=still_copying)
    assert grown
    whole = file_fingerprint(path, 10, (0, 5))
    assert whole["bytes"] == 3_000_100 and whole["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
