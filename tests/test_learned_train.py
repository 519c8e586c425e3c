"""Training: loss decreases, bit-for-bit resume, determinism, crash safety, torchrun (gloo) = one process."""
from __future__ import annotations

import os
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
from learned.train import Trainer, batch_indices, main

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    """0.6 s of a tiny indoor_flying scene (48x36) with ground truth every 50 ms."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("indoor_flying", seed=5, width=48, height=36, duration_s=1.0, texture_size=64)
    sequence = simulate_scene(scene, 0.6, EventSimulator(**{**scene.recommended_simulator, "seed": 5}),
                              depth_rate_hz=20)
    return sequence.save(tmp_path_factory.mktemp("learned") / "tiny.h5")


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


@pytest.mark.skipif(shutil.which("torchrun", path=os.path.dirname(sys.executable)) is None,
                    reason="torchrun not installed beside the Python interpreter")
def test_torchrun_two_processes_match_one(scene_file, tmp_path):
    """Two gloo ranks, 2 windows each, equal one process with the global batch of 4 (to float tolerance)."""
    extra = ("train.steps=3", "data.augment=false")
    torchrun = os.path.join(os.path.dirname(sys.executable), "torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run([torchrun, "--standalone", "--nproc_per_node", "2", "-m", "learned.train", "--mode",
                             "teacher", "--no-progress", *tiny(scene_file, tmp_path / "ddp", *extra)],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    Trainer(load_config(None, tiny(scene_file, tmp_path / "one", *extra), mode="teacher"), progress=False).run()
    a, b = params(tmp_path / "ddp" / "last.pt"), params(tmp_path / "one" / "last.pt")
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=1e-4, atol=1e-5)
    assert not torch.equal(a["stem.0.weight"], load_checkpoint(tmp_path / "one" / "last.pt")["model"]["stem.0.weight"] * 0)


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
