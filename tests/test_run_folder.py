"""The output folder of ``cmax fit``, ``cmax emvs`` and ``cmax depth`` (:mod:`cmax.io.run_folder`): only the files
these commands write count as (and are replaced as) an earlier run's results."""
from __future__ import annotations

from pathlib import Path

import pytest

from cmax.cli import main as cmax_main
from cmax.io import run_folder

#: User files whose names look like results (depth_*.png, window_*.png, depth.*) but are not the commands' own.
USER_FILES = {"notes.txt": b"notes", "depth_groundtruth.png": b"a user's picture", "depth_of_field_study.npz": b"mine",
              "window_seat_photo.png": b"a photo", "depth_0001.npz": b"four digits", "depth.npz.bak": b"backup"}


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """A checkpoint of a tiny network (width 2, one level, windows of 50 ms)."""
    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config, DataConfig
    from learned.model import DepthPoseNet, ModelConfig

    config = Config(model=ModelConfig(width=2, levels=1), data=DataConfig(window_us=50_000))
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt",
                           {"model": DepthPoseNet(config.model).state_dict(), "optimizer": {}, "step": 0,
                            "config": config.to_dict(), "rng": rng_state()})


def _fit(slider_file: Path, out: Path, *extra: str) -> list[str]:
    return ["fit", str(slider_file), "-o", str(out), "--quiet", "--window-ms", "100", "--min-events", "200",
            "--depth-grid", "6,8", *extra]


def _depth(slider_file: Path, out: Path, checkpoint: Path, *extra: str) -> list[str]:
    return ["depth", str(slider_file), "-o", str(out), "--checkpoint", str(checkpoint), "--quiet", *extra]


def _emvs(slider_file: Path, out: Path, *extra: str) -> list[str]:
    return ["emvs", str(slider_file), "-o", str(out), "--planes", "20", *extra]


def _user_files(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for name, data in USER_FILES.items():
        (out / name).write_bytes(data)


def _kept(out: Path) -> bool:
    return all((out / name).read_bytes() == data for name, data in USER_FILES.items())


# -- 1. only the commands' own file names are results --------------------------------------------------------------
def test_run_results_match_only_the_names_the_commands_write(tmp_path):
    _user_files(tmp_path)
    assert run_folder.run_results(tmp_path) == []
    for name in ("depth_00000.npz", "depth_00012.png", "depth_123456.npz", "trajectory.txt", "summary.json",
                 "window_00003.npz", "window_00003.png", "twists.csv", "depth.npz", "depth.png", "points.ply"):
        (tmp_path / name).write_bytes(b"result")
    by = {command: [path.name for path in run_folder.run_results(tmp_path, (command,))]
          for command in run_folder.RESULT_NAMES}
    assert by["fit"] == ["depth_00000.npz", "depth_00012.png", "depth_123456.npz", "summary.json", "trajectory.txt"]
    assert by["depth"] == ["summary.json", "twists.csv", "window_00003.npz", "window_00003.png"]
    assert by["emvs"] == ["depth.npz", "depth.png", "points.ply"]


def test_fit_neither_counts_nor_removes_a_users_depth_files(slider_file, tmp_path, capsys):
    """Was: a folder of user files (``depth_groundtruth.png``, ``depth_of_field_study.npz``) refused as "an earlier
    run's results", and ``--overwrite`` deleted them."""
    out = tmp_path / "fitu"
    _user_files(out)
    assert cmax_main(_fit(slider_file, out)) in (0, 1)   # not refused: no earlier run's files
    assert _kept(out) and (out / "summary.json").is_file() and (out / "depth_00000.npz").is_file()
    capsys.readouterr()
    assert cmax_main(_fit(slider_file, out, "--overwrite")) in (0, 1)
    assert _kept(out)


def test_depth_neither_counts_nor_removes_a_users_window_files(slider_file, tiny_checkpoint, tmp_path, capsys):
    """Was: ``window_seat_photo.png`` refused as an earlier run's result, and deleted by ``--overwrite``."""
    out = tmp_path / "dep"
    _user_files(out)
    assert cmax_main(_depth(slider_file, out, tiny_checkpoint)) == 0
    assert _kept(out) and (out / "window_00000.npz").is_file()
    assert cmax_main(_depth(slider_file, out, tiny_checkpoint, "--overwrite", "--window", "0.1")) == 0
    assert _kept(out)
    assert sorted(p.name for p in out.glob("window_0*.npz")) == ["window_00000.npz", "window_00001.npz"]
