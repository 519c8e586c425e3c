"""Every bad argument of every command -- ``cmax`` and ``python -m learned.*`` -- gives ONE line and exit 2.

Each case runs in-process (``main(argv)``, stderr captured); a few run through a real
process to check the console script and ``python -m``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cmax.io import write_h5
from conftest import random_events

ROOT = Path(__file__).resolve().parents[1]
K = "200,200,32,24"


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """An event file, a text file, a manifest, a valid tiny checkpoint and a non-checkpoint, by name."""
    folder = tmp_path_factory.mktemp("cli_errors")
    ev = random_events(3000, width=64, height=48, t_span_us=100_000, seed=2)
    out = {"FILE": write_h5(folder / "ev.h5", ev), "TEXT": folder / "notes.txt", "DIR": folder}
    out["TEXT"].write_text("hello\n")
    manifest = {"format": "evtslowtv-manifest/1", "simulator": "cmax x", "settings": {}, "catalogue": None,
                "missing": [], "videos": {"a": {"status": "ok", "events": 1, "frames": 2, "duration_s": 0.1}}}
    out["MANIFEST"] = folder / "manifest.json"
    out["MANIFEST"].write_text(json.dumps(manifest))
    out["BADVIDEOS"] = folder / "bad_videos.json"
    out["BADVIDEOS"].write_text(json.dumps({**manifest, "videos": 3}))
    out["NOSETTINGS"] = folder / "no_settings.json"
    out["NOSETTINGS"].write_text(json.dumps({"format": "evtslowtv-manifest/1", "videos": {}}))
    out["RESUME"] = folder / "resume"
    out["RESUME"].mkdir()
    (out["RESUME"] / "manifest.json").write_text(out["NOSETTINGS"].read_text())
    (folder / "a.avi").write_bytes(b"a video name is enough for collect_jobs")
    out["LIST"] = folder / "list.json"
    out["LIST"].write_text("[1, 2]")
    out["CKPT"] = _tiny_checkpoint(folder / "tiny.pt")
    out["CONFIG_LIST"] = folder / "config.json"
    out["CONFIG_LIST"].write_text("[1]")
    out["CONFIG_BAD"] = folder / "bad.toml"
    out["CONFIG_BAD"].write_text("[train\nsteps = ")
    out["YAML"] = folder / "config.yaml"
    out["YAML"].write_text("train: {}\n")
    return out


def _tiny_checkpoint(path: Path) -> Path:
    import torch

    from learned.checkpoint import rng_state, save_checkpoint
    from learned.config import Config
    from learned.model import DepthPoseNet, ModelConfig

    config = Config(model=ModelConfig(width=2, levels=1))
    model = DepthPoseNet(config.model)
    return save_checkpoint(path, {"model": model.state_dict(), "step": 0, "config": config.to_dict(),
                                  "rng": rng_state(),
                                  "optimizer": torch.optim.AdamW(model.parameters()).state_dict()})


def _expand(argv: list[str], files: dict[str, Path], tmp_path: Path) -> list[str]:
    """Placeholders (FILE, TEXT, ..., OUT, TMP) replaced by paths, also inside ``key=value`` arguments."""
    names = {**{k: str(v) for k, v in files.items()}, "OUT": str(tmp_path / "out"), "TMP": str(tmp_path)}
    pattern = re.compile(r"\b(" + "|".join(names) + r")\b")
    return [pattern.sub(lambda m: names[m.group(1)], a) for a in argv]


def _one_line_exit_2(call, capsys) -> str:
    try:
        status = call()
    except SystemExit as exit_:   # argparse
        status = exit_.code
    err = capsys.readouterr().err
    assert status == 2, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


CMAX_CASES = [
    # non-finite and out-of-range numbers, caught while parsing
    (["fit", "FILE", "--K", K, "-o", "OUT", "--window-ms", "inf"], "argument --window-ms: expected a finite number > 0"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--window-ms", "nan"], "argument --window-ms"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--window-ms", "-5"], "argument --window-ms"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--step-ms", "0"], "argument --step-ms"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--speed", "nan"], "argument --speed"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--max-events", "0"], "argument --max-events: expected a whole number"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--max-events", "1.5"], "argument --max-events"),
    (["fit", "FILE", "--K", "inf,1,2,3", "-o", "OUT"], "argument --K"),
    (["fit", "FILE", "--K", K, "-o", "OUT", "--window-ms", "0.0001"], "--window-ms must be at least 0.001 ms"),
    (["fit", "TMP/missing.h5", "--K", K, "-o", "OUT"], "cmax fit: error:"),
    (["fit", "TEXT", "--K", K, "-o", "OUT"], "cmax fit: error:"),
    (["show", "FILE", "--t0", "inf"], "cmax show: error: t0 must be a finite number"),
    (["show", "FILE", "--dt", "nan"], "dt must be a finite number"),
    (["emvs", "FILE", "--poses", "TEXT", "-o", "OUT", "--t0", "inf"], "argument --t0"),
    (["emvs", "FILE", "--poses", "TEXT", "-o", "OUT", "--planes", "0"], "argument --planes"),
    (["emvs", "FILE", "--poses", "TEXT", "-o", "OUT", "--depth-range", "1,inf"], "argument --depth-range"),
    (["emvs", "FILE", "--poses", "TEXT", "-o", "OUT", "--distortion", "1,2,3"], "argument --distortion"),
    (["emvs", "FILE", "--poses", "TEXT", "-o", "OUT", "--size", "0x0"], "argument --size"),
    (["scene", "indoor_flying", "-o", "OUT", "--duration", "inf"], "argument --duration: expected a finite number"),
    (["scene", "indoor_flying", "-o", "OUT", "--cp", "nan"], "argument --cp: expected a finite number > 0"),
    (["scene", "indoor_flying", "-o", "TMP/x.h5", "--duration", "700"], "argument --duration: expected seconds in (0, 600]"),
    (["scene", "indoor_flying", "-o", "FILE"], "exists: pass --overwrite to replace it"),
    (["scene", "indoor_flying", "-o", "OUT"], "cmax scene writes an HDF5 file: give a name ending in .h5"),
    (["emvs", "FILE", "-o", "OUT", "--K", K], "stores no poses (gt/poses): give them with --poses"),
    (["emvs", "FILE", "--poses", "FILE", "-o", "OUT", "--K", K], "is not a text file: expected a TUM trajectory"),
    (["scene", "indoor_flying", "-o", "OUT", "--seed", "-1"], "argument --seed"),
    (["scene", "indoor_flying", "-o", "OUT", "--depth-rate", "0"], "argument --depth-rate"),
    (["simulate", "TMP", "-o", "OUT", "--cp", "inf"], "cmax simulate: error: cp must be a finite positive"),
    (["simulate", "TMP", "-o", "OUT", "--lam", "nan"], "lam must be a positive number"),
    (["simulate", "TMP", "-o", "OUT", "--t0", "inf"], "t0_s must be a non-negative number of seconds"),
    (["simulate", "TMP", "-o", "OUT", "--workers", "0"], "argument --workers"),
    (["simulate", "TMP", "-o", "OUT", "--refractory-us", "-1"], "refractory_us must be >= 0"),
    (["simulate", "TMP", "-o", "OUT", "--shot-noise", "nan"], "shot_noise_rate_hz must be a finite non-negative"),
    (["simulate", "TMP/none.mp4", "-o", "TMP/x.h5"], "cmax simulate: error: input not found"),
    (["simulate", "TEXT", "-o", "TMP/x.h5"], "cmax simulate: error: INPUT must be a video"),
    (["demo", "-o", "OUT", "--duration", "inf"], "argument --duration"),
    (["demo", "-o", "OUT", "--window", "nan"], "argument --window"),
    (["demo", "-o", "OUT", "--seed", "-1"], "argument --seed"),
    (["info", "FILE", "--size", "12"], "argument --size"),
    (["info", "TMP/missing.h5"], "cmax info: error:"),
    (["manifest", "merge", "LIST", "-o", "OUT"], "is not a conversion manifest"),
    (["manifest", "merge", "BADVIDEOS", "-o", "OUT"], "'videos' must be an object of entries"),
    (["manifest", "merge", "TMP/none.json", "-o", "OUT"], "cmax manifest: error:"),
    (["manifest", "merge", "NOSETTINGS", "-o", "OUT"], "'settings' must be an object"),
    (["simulate", "DIR", "-o", "RESUME"], "'settings' must be an object"),
    (["frobnicate"], "cmax: error: argument COMMAND: invalid choice"),
    (["fit", "FILE", "-o", "OUT"], "stores no intrinsics (gt/K): give them with --K fx,fy,cx,cy or --calib"),
]


@pytest.mark.parametrize("argv, message", CMAX_CASES, ids=[" ".join(c[0][:1] + c[0][-2:]) for c in CMAX_CASES])
def test_cmax_bad_arguments_give_one_line_and_exit_2(files, tmp_path, capsys, argv, message):
    from cmax.cli import main

    err = _one_line_exit_2(lambda: main(_expand(argv, files, tmp_path)), capsys)
    assert message in err
    assert not (tmp_path / "out").exists() or argv[0] in ("fit",)   # nothing written for a refused command


LEARNED_CASES = [
    ("train", ["--mode", "teacher", "train.checkpoint_every=0"], "train.checkpoint_every must be a whole number >= 1"),
    ("train", ["--mode", "teacher", "train.log_every=0"], "train.log_every must be a whole number >= 1"),
    ("train", ["--mode", "teacher", "train.steps=abc"], "train.steps must be a whole number, got 'abc'"),
    ("train", ["--mode", "teacher", "train.lr=NaN"], "train.lr must be a finite number"),
    ("train", ["--mode", "teacher", "train.lr=-1"], "train.lr must be > 0"),
    ("train", ["--mode", "teacher", "train.batch_size=true"], "train.batch_size must be a whole number"),
    ("train", ["--mode", "teacher", 'model.width="4"'], "model.width must be a whole number, got '4'"),
    ("train", ["--mode", "teacher", "model.min_depth=Infinity"], "model.min_depth must be a finite number"),
    ("train", ["--mode", "teacher", "data.augment=1"], "data.augment must be true or false"),
    ("train", ["--mode", "teacher", "data.window_us=0"], "data.window_us must be a whole number of µs >= 1"),
    ("train", ["--mode", "teacher", 'data.files=[{"K": [1, 2, 3, 4]}]'], 'data.files[0] needs "path"'),
    ("train", ["--mode", "teacher", 'data.files=[{"path": "a.h5", "K": [1, 2]}]'], "data.files[0].K must be"),
    ("train", ["--mode", "teacher", "data.files=3"], "data.files must be a list"),
    ("train", ["--mode", "teacher", 'data.files=[""]', "train.out=OUT"],   # "$FILE" unset (was: read the cwd)
     'data.files[0] is an empty path (an unset shell variable, "$FILE"?)'),
    ("train", ["--mode", "teacher", 'data.files=["FILE"]', 'data.val_files=[{"path": " "}]', "train.out=OUT"],
     "data.val_files[0] is an empty path"),
    ("train", ["--mode", "teacher", "train.steps.x=1"], "train.steps must be a whole number, got {"),
    ("train", ["--mode", "teacher", "train.steps=3", "train.steps.x=1"], "train.steps is a value, not a section"),
    ("train", ["--mode", "teacher", "model=3"], "[model] must be a table of keys"),
    ("train", ["--mode", "teacher", "bogus.key=1"], "unknown config sections"),
    ("train", ["--mode", "teacher", "noequals"], "overrides must look like section.key=value"),
    ("train", ["--mode", "teacher", "--config", "TMP/missing.json"], "no config file at"),
    ("train", ["--mode", "teacher", "--config", "CONFIG_LIST"], "must hold a table of sections"),
    ("train", ["--mode", "teacher", "--config", "CONFIG_BAD"], "is not valid TOML"),
    ("train", ["--mode", "teacher", "--config", "YAML"], "config must be a .json or .toml file"),
    ("train", ["--mode", "student", "train.out=OUT"], "needs train.teacher"),
    ("train", ["--mode", "student", "train.teacher=TEXT", "train.out=OUT"], "is not a learned checkpoint"),
    ("train", ["--mode", "teacher", 'data.files=["TMP/missing.h5"]', "train.out=OUT"], "missing.h5"),
    ("train", ["--mode", "teacher", "--resume", "train.out=DIR", 'data.files=["FILE"]', "model.width=8"],
     "was written with other settings than this run's: model.width="),
    ("train", ["--mode", "lecturer"], "argument --mode: invalid choice"),
    ("predict", ["FILE", "--checkpoint", "TMP/missing.pt", "-o", "OUT"], "no checkpoint at"),
    ("predict", ["FILE", "--checkpoint", "TEXT", "-o", "OUT"], "is not a learned checkpoint"),
    ("predict", ["FILE", "--checkpoint", "DIR", "-o", "OUT"], "no checkpoint at"),
    ("predict", ["FILE", "--checkpoint", "CKPT", "-o", "OUT", "--window", "inf"], "argument --window"),
    ("predict", ["FILE", "--checkpoint", "CKPT", "-o", "OUT", "--window", "1e-9"], "at least 1 µs"),
    ("predict", ["FILE", "--checkpoint", "CKPT", "-o", "OUT", "--K", "1,2"], "argument --K"),
    ("predict", ["TMP/missing.h5", "--checkpoint", "CKPT", "-o", "OUT"], "no such event file"),
    ("predict", ["TEXT", "--checkpoint", "CKPT", "-o", "OUT"], "python -m learned.predict: error:"),
    ("evaluate", ["--checkpoint", "TEXT", "--data", "FILE"], "is not a learned checkpoint"),
    ("evaluate", ["--checkpoint", "CKPT", "--data", "FILE", "--window", "nan"], "argument --window"),
    ("evaluate", ["--checkpoint", "CKPT", "--data", "FILE"], "has no gt/K"),
    ("evaluate", ["--checkpoint", "CKPT"], "the following arguments are required: --data"),
]


@pytest.mark.parametrize("module, argv, message", LEARNED_CASES,
                         ids=[f"{c[0]} {' '.join(c[1][-2:])}" for c in LEARNED_CASES])
def test_learned_bad_arguments_give_one_line_and_exit_2(files, tmp_path, capsys, module, argv, message):
    import importlib

    main = importlib.import_module(f"learned.{module}").main
    argv = _expand(argv, files, tmp_path)
    if module == "train" and "train.out=" not in " ".join(argv):
        argv.append(f"train.out={tmp_path / 'run'}")
    if module == "train" and "--resume" in argv:   # a last.pt of another model width in train.out
        import shutil

        run = tmp_path / "resume"
        run.mkdir()
        shutil.copy(files["CKPT"], run / "last.pt")
        argv = [f"train.out={run}" if a.startswith("train.out=") else a for a in argv]
    err = _one_line_exit_2(lambda: main(argv + ["--no-progress"] if module == "train" else argv), capsys)
    assert message in err
    assert err.startswith(f"python -m learned.{module}: error: ")


def test_debug_flag_and_environment_show_the_traceback(files, tmp_path, monkeypatch, capsys):
    from cmax.cli import main

    missing = str(tmp_path / "missing.h5")
    assert main(["info", missing]) == 2
    with pytest.raises(OSError):
        main(["--debug", "info", missing])
    with pytest.raises(OSError):
        main(["info", missing, "--debug"])
    monkeypatch.setenv("CMAX_DEBUG", "1")
    with pytest.raises(OSError):
        main(["info", missing])
    from learned.predict import main as predict

    with pytest.raises(OSError):
        predict([str(files["FILE"]), "--checkpoint", missing, "-o", str(tmp_path / "o")])


def test_checkpoint_every_zero_is_refused_by_the_config_api():
    from learned.config import TrainConfig

    with pytest.raises(ValueError, match="train.checkpoint_every must be a whole number >= 1, got 0"):
        TrainConfig(checkpoint_every=0)
    with pytest.raises(TypeError, match="train.steps must be a whole number"):
        TrainConfig(steps=2.5)


def test_real_processes_print_one_line(files, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("CMAX_DEBUG", None)
    cmax = subprocess.run([sys.executable, "-m", "cmax.cli", "fit", str(files["FILE"]), "--K", K, "-o",
                           str(tmp_path / "o"), "--window-ms", "inf"], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=60)
    train = subprocess.run([sys.executable, "-m", "learned.train", "--mode", "teacher", "train.checkpoint_every=0",
                            f"train.out={tmp_path / 'run'}"], capture_output=True, text=True, env=env, cwd=ROOT,
                           timeout=120)
    for result in (cmax, train):
        assert result.returncode == 2
        assert len(result.stderr.strip().splitlines()) == 1 and "Traceback" not in result.stderr, result.stderr
    assert "--window-ms" in cmax.stderr and "checkpoint_every" in train.stderr


def _options(parser: argparse.ArgumentParser, name: str = "cmax"):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from _options(sub, f"{name} {sub_name}")
        elif action.option_strings and action.dest not in ("help", "version", "debug"):
            yield name, parser, action


def test_every_option_has_help_and_shows_its_default():
    from cmax._args import HelpFormatter
    from cmax.cli import build_parser

    count = 0
    for command, parser, action in _options(build_parser()):
        assert action.help, f"{command} {action.option_strings[0]} has no help"
        text = HelpFormatter(command)._get_help_string(action) % {"default": action.default, "prog": command}
        has_default = getattr(action, "api_default", None) is not None or action.default not in (None, False)
        if has_default:
            assert "default" in text, f"{command} {action.option_strings[0]}: {text}"
        count += 1
    assert count > 50


def test_help_shows_the_librarys_defaults(capsys):
    """One source of defaults: the numbers in --help are those of the API objects."""
    from cmax.cli import main
    from cmax.fitting.settings import BASE_MAX_EVENTS, max_events_for
    from cmax.sim.convert import ConvertSettings
    from cmax.sim.esim_settings import EsimSettings

    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    fit_help = " ".join(capsys.readouterr().out.split())
    assert f"default: by the sensor, {BASE_MAX_EVENTS:,} events up to 346x260 pixels" in fit_help   # 40,000 before
    assert f"{max_events_for(None, 640, 480):,} at 640x480, {max_events_for(None, 1280, 720):,} at 1280x720" in fit_help
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    sim_help = " ".join(capsys.readouterr().out.split())
    assert f"ON threshold [log intensity] (default: {EsimSettings().cp:g})" in sim_help
    assert f"a fraction of min(--cp, --cn) (default: {ConvertSettings().lam:g})" in sim_help


def test_polarity_option_reads_a_signed_file_and_is_refused_where_the_format_states_it(tmp_path, capsys):
    """cmax info/show name --polarity in their refusal of a -1/+1 file and read it with the option;
    a format that states its own polarities (EVT3 here) refuses the option in one line."""
    import h5py

    from cmax.cli import main
    from cmax.io.prophesee.writer import write_evt3

    n = 400
    path = tmp_path / "signed.h5"
    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        group["x"] = (np.arange(n) % 64).astype(np.uint16)
        group["y"] = (np.arange(n) % 48).astype(np.uint16)
        group["t"] = np.arange(n, dtype=np.int64) * 100
        group["p"] = np.where(np.arange(n) % 4 == 0, 1, -1).astype(np.int8)   # 25% ON
        file.attrs["width"], file.attrs["height"] = 64, 48
    err = _one_line_exit_2(lambda: main(["info", str(path)]), capsys)
    assert "(cmax: --polarity signed)" in err
    assert main(["info", str(path), "--polarity", "signed"]) == 0
    assert "100 ON / 300 OFF (25.0% ON)" in capsys.readouterr().out
    assert main(["show", str(path), "--polarity", "signed", "-o", str(tmp_path / "s.png")]) == 0
    assert (tmp_path / "s.png").stat().st_size > 0
    raw = tmp_path / "ev.raw"
    write_evt3(raw, random_events(200, width=64, height=48, t_span_us=10_000, seed=1))
    err = _one_line_exit_2(lambda: main(["info", str(raw), "--polarity", "signed"]), capsys)
    assert "states its polarities itself; polarity='signed' does not apply" in err


def test_a_closed_stdout_ends_quietly(files):
    """``cmax info MANY FILES | head -1``: no 'error: Broken pipe' line once the reader has left."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-c", "import sys; from cmax.cli import main; sys.exit(main())", "info",
               *[str(files["FILE"])] * 300]   # ~86 kB of output: more than a pipe holds (64 kB)
    done = subprocess.run(f"{subprocess.list2cmdline(command)} | head -1", shell=True, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.stdout.startswith("file ")
    assert done.stderr == "", done.stderr
