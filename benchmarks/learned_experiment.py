"""The paper's teacher / fine-tune / student experiment (sections 4.4, 5) at CPU scale.

Stages (``--stage``):

``data``
    Simulates the training and test files into ``--data-dir``:

    * ``train/``: synthetic preset scenes with ground truth (``cmax.sim.make_scene`` +
      ``simulate_scene``), presets ``TRAIN_PRESETS``, seeds ``TRAIN_SEEDS`` (never the
      held-out 101-103), 1 s each, a depth map every 50 ms;
    * ``ssl/``: events without ground truth (the student's and the fine-tuning's data):
      ``../shared/data/videos/bikes.mp4``, the truck-pan frames and the ECD slider frames
      converted by :func:`cmax.sim.convert.convert_video` (ESIM, adaptive sampling, linear
      interpolation), plus the synthetic indoor_flying scene of seed 11 (1.5 s) whose ``gt/`` the loaders never read
      (``use_gt=false``);
    * ``test/``: the held-out sequences of ``benchmarks/accuracy.py`` (``indoor_flying`` seeds
      101, 102, 103, ``driving_day`` and ``driving_night`` seed 101), starting at 0.2 s, four
      0.1665 s windows each, the ground-truth depth rendered at each window's middle.

``evaluate``
    Scores checkpoints on ``test/`` with :func:`learned.evaluate.evaluate_files` and writes
    ``benchmarks/results/accuracy_learned.csv`` (the columns of ``benchmarks/accuracy.py``).

Training itself runs ``python -m learned.train`` with the configs in
``benchmarks/results/learned/``; the exact commands are in ``accuracy_learned.md``.

Usage::

    python -m benchmarks.learned_experiment --stage data --data-dir /tmp/learned_data
    python -m benchmarks.learned_experiment --stage evaluate --data-dir /tmp/learned_data \\
        --checkpoint EvtSL=runs/teacher/last.pt --checkpoint "EvtSL->EvtSSL=runs/finetune/last.pt" ...
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SIZE = (160, 120)
WINDOW_S = 0.1665
TRAIN_PRESETS = ("indoor_flying", "driving_day", "driving_night", "slider", "hiking")
TRAIN_SEEDS = (1,)
SSL_SYNTHETIC = (("indoor_flying", 11),)
TEST_SEQUENCES = (("indoor_flying1", "indoor_flying", 101), ("indoor_flying2", "indoor_flying", 102),
                  ("indoor_flying3", "indoor_flying", 103), ("driving_day", "driving_day", 101),
                  ("driving_night", "driving_night", 101))
TEST_START_S, TEST_WINDOWS = 0.2, 4


def simulate_preset(preset: str, seed: int, path: Path, *, t0_s: float, duration_s: float,
                    depth_times_s: np.ndarray | None) -> None:
    from cmax.sim.esim import EventSimulator
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    if path.exists():
        return
    scene = make_scene(preset, seed=seed, width=SIZE[0], height=SIZE[1],
                       duration_s=max(1.0, t0_s + duration_s + 0.1), texture_size=256)
    simulator = EventSimulator(**{**scene.recommended_simulator, "seed": seed})
    sequence = simulate_scene(scene, duration_s, simulator, t0_s=t0_s, depth_times_s=depth_times_s)
    sequence.save(path, overwrite=True)
    print(f"{path}: {len(sequence.events):,} events", file=sys.stderr)


def make_data(root: Path) -> None:
    from cmax.sim.convert import ConvertSettings, convert_video
    from cmax.sim.esim import EsimSettings
    from cmax.sim.video import ImageFolderSource

    for name in ("train", "ssl", "test"):
        (root / name).mkdir(parents=True, exist_ok=True)
    for label, preset, seed in TEST_SEQUENCES:
        middles = TEST_START_S + (np.arange(TEST_WINDOWS) + 0.5) * WINDOW_S
        simulate_preset(preset, seed, root / "test" / f"{label}.h5", t0_s=TEST_START_S,
                        duration_s=TEST_WINDOWS * WINDOW_S + 0.01, depth_times_s=middles)
    settings = ConvertSettings(EsimSettings(0.2, 0.2, 0.03, 0, seed=0), size=SIZE, adaptive=True, method="linear")
    videos = {"bikes": SHARED / "videos" / "bikes.mp4"}
    folders = {"truck_pan": SHARED / "esim_truck_pan" / "images", "slider_depth": SHARED / "ecd_slider_depth" / "images"}
    for name, source in videos.items():
        out = root / "ssl" / f"{name}.h5"
        if not out.exists() and source.exists():
            convert_video(source, out, settings)
    for name, folder in folders.items():
        out = root / "ssl" / f"{name}.h5"
        if not out.exists() and folder.exists():
            convert_video(folder, out, settings, frames=ImageFolderSource(folder, size=SIZE, prefetch=0))
    for seed in TRAIN_SEEDS:
        for preset in TRAIN_PRESETS:
            simulate_preset(preset, seed, root / "train" / f"{preset}_{seed}.h5", t0_s=0.0, duration_s=1.0,
                            depth_times_s=None)
    for preset, seed in SSL_SYNTHETIC:
        simulate_preset(preset, seed, root / "ssl" / f"{preset}_{seed}.h5", t0_s=0.0, duration_s=1.5,
                        depth_times_s=None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stage", choices=("data", "evaluate"), required=True)
    parser.add_argument("--data-dir", type=Path, required=True)
    parser.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=PATH",
                        help="a checkpoint to score, named by its table row")
    parser.add_argument("--output", type=Path, default=RESULTS / "accuracy_learned.csv")
    args = parser.parse_args(argv)
    if args.stage == "data":
        make_data(args.data_dir)
        return 0
    from learned.evaluate import evaluate_files, write_accuracy_csv

    rows = []
    files = sorted((args.data_dir / "test").glob("*.h5"))
    order = [label for label, _, _ in TEST_SEQUENCES]
    files.sort(key=lambda p: order.index(p.stem) if p.stem in order else len(order))
    for spec in args.checkpoint:
        method, _, path = spec.partition("=")
        for report in evaluate_files(Path(path), files, window_s=WINDOW_S):
            rows.append((method, report))
    write_accuracy_csv(args.output, rows)
    print(args.output.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
