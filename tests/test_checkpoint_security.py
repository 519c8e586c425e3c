"""Checkpoints load with ``weights_only=True``: a crafted pickle is refused by every entry point and never runs.

The crafted file's ``__reduce__`` calls ``os.system`` to create a marker file. A control
(``torch.load(weights_only=False)``) shows that the file really runs the command, so the
refusals below are meaningful.
"""
from __future__ import annotations

import os
import pickle
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from learned.checkpoint import (CheckpointError, load_checkpoint, rng_state, save_checkpoint, set_rng_state,
                                upgrade_checkpoint)
from learned.config import Config
from learned.model import DepthPoseNet, ModelConfig

ROOT = Path(__file__).resolve().parents[1]


class _RunsCommand:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch '{self.marker}'",)


def _payload(marker: Path | None = None) -> dict:
    model = DepthPoseNet(ModelConfig(width=2, levels=1))
    optimizer = torch.optim.AdamW(model.parameters())
    payload = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": 3,
               "config": Config(model=ModelConfig(width=2, levels=1)).to_dict(), "rng": rng_state()}
    if marker is not None:
        payload["model"] = {"stem.0.weight": _RunsCommand(marker)}
    return payload


@pytest.fixture
def crafted(tmp_path) -> tuple[Path, Path]:
    """A torch.save file whose loading runs ``touch MARKER``; returns (file, marker)."""
    marker = tmp_path / "MARKER"
    path = tmp_path / "crafted" / "last.pt"
    path.parent.mkdir()
    torch.save(_payload(marker), path)
    assert not marker.exists()
    return path, marker


def test_the_crafted_file_runs_code_when_unpickled_unsafely(crafted):
    """Control: without weights_only the file does run its command."""
    path, marker = crafted
    torch.load(path, weights_only=False)
    assert marker.exists()


def test_load_checkpoint_refuses_a_crafted_pickle(crafted):
    path, marker = crafted
    with pytest.raises(CheckpointError, match="refused: loading it would run code.*system"):
        load_checkpoint(path)
    assert not marker.exists()


@pytest.mark.parametrize("protocol, message", [(2, r"would run code .it calls \w+\.system"),
                                               (4, "refused by the safe loader")])
def test_a_plain_pickle_file_is_refused_too(tmp_path, protocol, message):
    marker = tmp_path / "MARKER"
    path = tmp_path / "raw.pt"
    path.write_bytes(pickle.dumps(_RunsCommand(marker), protocol=protocol))
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)
    assert not marker.exists()


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


def test_learned_predict_refuses_it(crafted, tmp_path, capsys):
    from learned.predict import main

    path, marker = crafted
    assert main([str(tmp_path / "any.h5"), "--checkpoint", str(path), "-o", str(tmp_path / "out")]) == 2
    assert "refused" in _one_error_line(capsys)
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_learned_evaluate_refuses_it(crafted, tmp_path, capsys):
    from learned.evaluate import main

    path, marker = crafted
    assert main(["--checkpoint", str(path), "--data", str(tmp_path / "any.h5")]) == 2
    assert "refused" in _one_error_line(capsys)
    assert not marker.exists()


def test_learned_train_resume_and_teacher_refuse_it(crafted, tmp_path, capsys):
    from learned.train import main

    path, marker = crafted
    base = ["--no-progress", f"data.files=[\"{tmp_path / 'any.h5'}\"]", "model.width=2", "model.levels=1"]
    assert main(["--mode", "teacher", "--resume", *base, f"train.out={path.parent}"]) == 2
    assert "refused" in _one_error_line(capsys)
    assert main(["--mode", "student", *base, f"train.out={tmp_path / 'student'}", f"train.teacher={path}"]) == 2
    assert "refused" in _one_error_line(capsys)
    assert not marker.exists()


def test_refused_through_a_real_process(crafted, tmp_path):
    path, marker = crafted
    result = subprocess.run([sys.executable, "-m", "learned.predict", str(tmp_path / "any.h5"), "--checkpoint",
                             str(path), "-o", str(tmp_path / "out")], cwd=ROOT, capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert result.returncode == 2
    assert result.stderr.startswith("python -m learned.predict: error: ") and "Traceback" not in result.stderr
    assert not marker.exists()


def test_a_saved_checkpoint_is_plain_data_and_restores_every_generator(tmp_path):
    random.seed(1), np.random.seed(2), torch.manual_seed(3)
    np.random.normal()  # a cached Gaussian is part of NumPy's state
    payload = _payload()
    config = payload["config"]
    config["data"]["files"] = (Path("a.h5"), {"path": "b.h5", "K": [1.0, 2.0, 3.0, 4.0]})
    path = save_checkpoint(tmp_path / "ok.pt", payload)
    expected = (random.random(), np.random.normal(), np.random.rand(), torch.rand(2))
    loaded = load_checkpoint(path)     # weights_only=True
    assert loaded["format"] == 2 and loaded["config"]["data"]["files"] == ("a.h5", {"path": "b.h5",
                                                                                     "K": [1.0, 2.0, 3.0, 4.0]})
    set_rng_state(loaded["rng"])
    again = (random.random(), np.random.normal(), np.random.rand(), torch.rand(2))
    assert expected[:3] == again[:3] and torch.equal(expected[3], again[3])


def test_objects_in_the_config_are_refused_at_save(tmp_path):
    payload = _payload()
    payload["config"]["train"]["out"] = object()
    with pytest.raises(TypeError, match=r"config.train.out: object cannot be stored"):
        save_checkpoint(tmp_path / "x.pt", payload)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("content, message", [
    (b"not a checkpoint at all", "is not a learned checkpoint"),
    (b"", "is not a learned checkpoint"),
])
def test_non_checkpoint_files_are_refused(tmp_path, content, message):
    path = tmp_path / "x.pt"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)


@pytest.mark.skipif(sys.platform == "win32", reason="FIFOs and /dev/zero are POSIX")
def test_a_device_or_a_pipe_is_named_as_such_not_as_missing(tmp_path, capsys):
    """A checkpoint path that is a link to /dev/zero or a FIFO was `no checkpoint at ...` (FileNotFoundError), about
    a path that exists; an event file of data.files that is one was `no such event file: ...`. Now each is named as
    not a regular file, and nothing is read from it (a FIFO would block, /dev/zero never ends)."""
    from cmax.io import FormatError
    from learned.data import H5WindowDataset
    from learned.evaluate import main

    (tmp_path / "zero.pt").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "pipe.pt")
    for name in ("zero.pt", "pipe.pt"):
        with pytest.raises(CheckpointError, match=f"{name} is not a regular file \\(a device, a pipe or a socket\\)"):
            load_checkpoint(tmp_path / name)
        assert main(["--checkpoint", str(tmp_path / name), "--data", str(tmp_path / "any.h5")]) == 2
        assert "is not a regular file" in _one_error_line(capsys)
        with pytest.raises(FormatError, match=f"{name} is not a regular file"):
            H5WindowDataset([str(tmp_path / name)], window_us=100_000)
    with pytest.raises(FileNotFoundError, match="no checkpoint at"):
        load_checkpoint(tmp_path / "missing.pt")


def test_wrong_contents_are_refused(tmp_path):
    torch.save({"weights": torch.zeros(3)}, tmp_path / "a.pt")
    with pytest.raises(CheckpointError, match=r"missing \['config', 'model', 'optimizer', 'rng', 'step'\]"):
        load_checkpoint(tmp_path / "a.pt")
    torch.save([1, 2], tmp_path / "b.pt")
    with pytest.raises(CheckpointError, match="holds a list"):
        load_checkpoint(tmp_path / "b.pt")
    payload = {**_payload(), "format": 2, "step": -1}
    torch.save(payload, tmp_path / "c.pt")
    with pytest.raises(CheckpointError, match="'step' must be an integer >= 0"):
        load_checkpoint(tmp_path / "c.pt")


def test_a_sparse_tensor_is_refused_in_one_line(tmp_path, capsys):
    """A checkpoint whose weight is a sparse tensor (torch.load(weights_only=True) rebuilds it) was a
    NotImplementedError traceback ('Cannot access storage of SparseTensorImpl'), exit 1, from learned.evaluate,
    learned.predict and --resume; now a CheckpointError naming the file and the tensor."""
    from learned.evaluate import main

    payload = {**_payload(), "format": 2}
    payload["model"] = {**payload["model"], "stem.0.weight": payload["model"]["stem.0.weight"].to_sparse()}
    torch.save(payload, tmp_path / "sparse.pt")
    with pytest.raises(CheckpointError, match=r"sparse.pt was refused: 1 of its tensors are not dense "
                                              r"\(e.g. model.stem.0.weight: torch.sparse_coo\)"):
        load_checkpoint(tmp_path / "sparse.pt")
    assert main(["--checkpoint", str(tmp_path / "sparse.pt"), "--data", str(tmp_path / "any.h5")]) == 2
    assert "not dense" in _one_error_line(capsys)


def test_an_old_format_checkpoint_is_refused_then_upgraded_only_when_trusted(tmp_path):
    old = _payload()
    old["rng"] = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    torch.save(old, tmp_path / "old.pt")   # format 1: NumPy's state as a pickled array
    with pytest.raises(CheckpointError, match="refused.*learned.checkpoint upgrade"):
        load_checkpoint(tmp_path / "old.pt")
    with pytest.raises(ValueError, match="trust=True"):
        upgrade_checkpoint(tmp_path / "old.pt", tmp_path / "new.pt")
    assert not (tmp_path / "new.pt").exists()
    upgrade_checkpoint(tmp_path / "old.pt", tmp_path / "new.pt", trust=True)
    new = load_checkpoint(tmp_path / "new.pt")
    assert all(torch.equal(new["model"][k], v) for k, v in old["model"].items())
    assert np.array_equal(np.asarray(new["rng"]["numpy"]["key"]), old["rng"]["numpy"][1])


def test_upgrade_command_needs_the_trust_flag(tmp_path, capsys):
    from learned.checkpoint import main

    torch.save(_payload(), tmp_path / "old.pt")
    assert main(["upgrade", str(tmp_path / "old.pt"), str(tmp_path / "new.pt")]) == 2
    assert "trust" in _one_error_line(capsys)
    assert main(["upgrade", str(tmp_path / "old.pt"), str(tmp_path / "new.pt"), "--trust-this-file"]) == 0
    assert load_checkpoint(tmp_path / "new.pt")["step"] == 3


def test_upgrade_of_a_truncated_or_empty_file_is_one_line(tmp_path, capsys):
    """`python -m learned.checkpoint upgrade` called torch.load unguarded: a 25-line traceback and exit 1."""
    from learned.checkpoint import main

    torch.save(_payload(), tmp_path / "old.pt")
    whole = (tmp_path / "old.pt").read_bytes()
    (tmp_path / "trunc.pt").write_bytes(whole[: len(whole) // 2])
    (tmp_path / "empty.pt").write_bytes(b"")
    for name in ("trunc.pt", "empty.pt"):
        assert main(["upgrade", str(tmp_path / name), str(tmp_path / "new.pt"), "--trust-this-file"]) == 2
        line = _one_error_line(capsys)
        assert f"{tmp_path / name} is not a learned checkpoint (torch.load: " in line, line
        assert not (tmp_path / "new.pt").exists()
        with pytest.raises(CheckpointError, match="is not a learned checkpoint"):   # was OSError: [Errno 22]
            load_checkpoint(tmp_path / name)


def test_a_checkpoint_cut_short_is_named_as_cut_short(tmp_path):
    """Was: a checkpoint cut short (a copy or download stopped, a full disk while it was saved) anywhere past its
    first bytes gave ``is not a learned checkpoint (torch.load: OSError: [Errno 22] Invalid argument)``, as for a
    foreign file. Now the line says the file is cut short (or empty); a foreign file is named as before."""
    torch.save(_payload(), tmp_path / "whole.pt")
    whole = (tmp_path / "whole.pt").read_bytes()
    for cut in (len(whole) // 2, len(whole) - 30, 100):
        (tmp_path / "cut.pt").write_bytes(whole[:cut])
        with pytest.raises(CheckpointError, match=rf"cut\.pt is not a learned checkpoint: it is cut short: its "
                                                  rf"{cut:,} bytes begin as torch.save's zip archive"):
            load_checkpoint(tmp_path / "cut.pt")
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"is not a learned checkpoint: the file is empty \(0 bytes\)"):
        load_checkpoint(tmp_path / "empty.pt")
    (tmp_path / "foreign.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError) as refused:
        load_checkpoint(tmp_path / "foreign.pt")
    assert "cut short" not in str(refused.value) and "foreign.pt is not a learned checkpoint (" in str(refused.value)


def test_save_checkpoint_never_follows_a_link_planted_at_a_temporary_name(tmp_path):
    """The old fixed name ``<path>.<pid>.partial`` followed a planted link and overwrote its target."""
    import os

    outside = tmp_path / "outside.txt"
    outside.write_text("precious\n")
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / f"last.pt.{os.getpid()}.partial").symlink_to(outside)
    saved = save_checkpoint(folder / "last.pt", _payload())
    assert outside.read_text() == "precious\n"
    assert load_checkpoint(saved)["step"] == _payload()["step"]
    assert not [p for p in folder.iterdir() if p.suffix == ".lock"]


def test_numpy_scalars_in_config_and_optimizer_are_stored_as_plain_numbers(tmp_path):
    """np.float64 is a float subclass: a learning rate computed with numpy once made our own checkpoint
    unloadable under weights_only=True."""
    import numpy as np
    import torch

    from learned.checkpoint import load_checkpoint, save_checkpoint

    net = torch.nn.Linear(2, 1)
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3)
    optimizer.param_groups[0]["lr"] = np.float64(5e-4)
    path = save_checkpoint(tmp_path / "c.pt", {"model": net.state_dict(), "optimizer": optimizer.state_dict(),
                                               "step": 1, "config": {"lr": np.float64(5e-4)}, "rng": {}})
    ckpt = load_checkpoint(path)
    assert type(ckpt["optimizer"]["param_groups"][0]["lr"]) is float and ckpt["config"]["lr"] == 5e-4


# -- files that would fill the memory before any check ---------------------------------------------------------------
def test_a_tensor_claiming_more_numbers_than_its_storage_is_refused(tmp_path):
    """A stride-0 view of one stored number, claiming 10^12 of them, is a 70 kB file; its NaN check asked for
    4 TB (was: `RuntimeError: ... DefaultCPUAllocator: can't allocate memory` traceback; at 3e8 numbers 2.3 GB
    used loading a 68 kB file)."""
    payload = _payload()
    payload["model"]["stem.0.weight"] = torch.zeros(1).as_strided((10**12,), (0,))
    torch.save({**payload, "format": 2}, tmp_path / "repeat.pt")
    with pytest.raises(CheckpointError, match=r"repeat\.pt was refused: 1 of its tensors claim more numbers than "
                                              r"the file stores \(e\.g\. model\.stem\.0\.weight: 1,000,000,000,000 "
                                              r"numbers over 4 bytes of storage"):
        load_checkpoint(tmp_path / "repeat.pt")


def test_a_checkpoint_of_compressed_entries_is_refused_before_loading(tmp_path):
    """torch.save stores its zip entries uncompressed; the same checkpoint re-zipped with deflate and 20 MB of zeros
    is a file of about 60 kB that expanded to 20 MB on loading (200 MB from 250 kB, and so on)."""
    import zipfile

    payload = _payload()
    payload["optimizer"]["padding"] = torch.zeros(5_000_000)
    torch.save({**payload, "format": 2}, tmp_path / "stored.pt")
    assert load_checkpoint(tmp_path / "stored.pt")["step"] == 3     # uncompressed: its own size, loads
    with zipfile.ZipFile(tmp_path / "stored.pt") as src, \
            zipfile.ZipFile(tmp_path / "deflated.pt", "w", zipfile.ZIP_DEFLATED, compresslevel=9) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info.filename))
    assert (tmp_path / "deflated.pt").stat().st_size < 200_000
    with pytest.raises(CheckpointError, match=r"deflated\.pt was refused: its zip entries expand to 2\d,\d{3},\d{3} "
                                              r"bytes from a file of \d+,\d{3} \(compressed"):
        load_checkpoint(tmp_path / "deflated.pt")


def test_upgrade_never_replaces_an_existing_file_without_overwrite(tmp_path, capsys):
    """`upgrade OLD NEW` replaced an existing NEW (another checkpoint) without a word, and `upgrade OLD OLD`
    replaced the format-1 original."""
    from learned.checkpoint import main

    old = _payload()
    old["rng"] = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    torch.save(old, tmp_path / "old.pt")
    other = save_checkpoint(tmp_path / "other.pt", {**_payload(), "step": 7})
    before = {name: (tmp_path / name).read_bytes() for name in ("old.pt", "other.pt")}
    assert main(["upgrade", str(tmp_path / "old.pt"), str(other), "--trust-this-file"]) == 2
    assert f"{other} exists: --overwrite replaces it, or give another NEW" in _one_error_line(capsys)
    assert main(["upgrade", str(tmp_path / "old.pt"), str(tmp_path / "old.pt"), "--trust-this-file"]) == 2
    assert "the checkpoint being converted" in _one_error_line(capsys)
    assert before == {name: (tmp_path / name).read_bytes() for name in ("old.pt", "other.pt")}
    assert main(["upgrade", str(tmp_path / "old.pt"), str(other), "--trust-this-file", "--overwrite"]) == 0
    assert load_checkpoint(other)["step"] == 3
