"""The paper's teacher -> fine-tune / student experiment (EvtSlowTV sections 4.4, 5) at this machine's scale.

One command runs it all, each stage cached (a finished stage is verified, not redone)::

    python -m benchmarks.learned_experiment --data-dir ~/evtslowtv_data --runs-dir ~/evtslowtv_runs

``--stage data`` / ``train`` / ``evaluate`` / ``curves`` run one stage; ``--seeds 0,1,2`` (default) the
training seeds. The recipe (ModelConfig, TrainConfig of each mode) is ``learned/configs/*.toml``, shipped
with the package; this module adds the data files and the seed.

Data (``--stage data``; 160x120, DAVIS346 intrinsics scaled; windows of 0.1665 s as in the paper)
-------------------------------------------------------------------------------------------------------
Slow presets are played faster (:class:`cmax.sim.scenes.TimeScaledScene`, :data:`SPEED_FACTOR`) so that
a window holds 3-4 px of translational parallax (the median over pixels and times; measured with
:func:`parallax_px`): at 160x120 the indoor_flying preset moves 1 px per window at its own speed.

* ``labelled/`` (the teacher's, standing in for MVSEC's training split): :data:`LABELLED_PRESETS` x
  :data:`LABELLED_SEEDS`, with ground-truth depth every 50 ms and twists. No indoor_flying.
* ``unlabelled/`` (the student's and the fine-tune's, standing in for EvtSlowTV): every translating preset
  (indoor_flying included) with other seeds, read with ``use_gt=false, known_speed=true`` (depth and twist
  hidden, the speed kept as the metric anchor), plus the real videos of ``../shared/data`` converted with
  :func:`cmax.sim.convert.convert_video` (no speed: their scale is left to the teacher term).
* ``val/``: held-out seeds of every preset (the learning curves).
* ``test/``: the held-out sequences: indoor_flying seeds 101-103 (the paper's test domain, never seen by the
  teacher), driving_day / driving_night seed 101, and the teacher's own domain (slider, driving seed 201);
  :data:`TEST_WINDOWS` non-overlapping windows each from 0.2 s, depth at each window's middle.

Training (``--stage train``): per seed, the teacher (``learned/configs/teacher.toml``), then the fine-tune
and the student from that teacher; ``runs/<mode>_s<seed>/``. Evaluation (``--stage evaluate``) scores
every checkpoint with :mod:`benchmarks.learned_table` (dense and event-pixel masks, the constant-depth
baseline, ``cmax.fit`` and EMVS rows) into ``benchmarks/results/accuracy_learned_table.{md,csv}``;
``--stage curves`` draws the learning curves (``benchmarks/results/learned_curves.png``); ``--stage ship``
copies the student of seed 0 into ``learned/pretrained/student.pt`` with its card ``student.json`` (scores on
the test files and on the fixed window ``tests/data/learned_window.npz``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
CONFIGS = Path(__file__).resolve().parents[1] / "learned" / "configs"
SIZE = (160, 120)
WINDOW_S = 0.1665
#: Speed-up of each preset (TimeScaledScene) so that a 0.1665 s window at 160x120 has 3-4 px of parallax.
SPEED_FACTOR = {"indoor_flying": 3.5, "slider": 2.0, "hiking": 6.0, "driving_day": 1.0, "driving_night": 1.0}
LABELLED_PRESETS = ("driving_day", "driving_night", "slider", "hiking")
LABELLED_SEEDS = tuple(range(1, 7))
UNLABELLED = tuple([("indoor_flying", s) for s in range(11, 17)]
                   + [(p, s) for p in ("slider", "driving_day", "driving_night", "hiking") for s in (11, 12)])
VAL = tuple((p, 51) for p in ("indoor_flying", "driving_day", "driving_night", "slider", "hiking"))
TEST_SEQUENCES = (("indoor_flying1", "indoor_flying", 101), ("indoor_flying2", "indoor_flying", 102),
                  ("indoor_flying3", "indoor_flying", 103), ("driving_day", "driving_day", 101),
                  ("driving_night", "driving_night", 101), ("own_slider", "slider", 201),
                  ("own_driving_day", "driving_day", 201), ("own_driving_night", "driving_night", 201))
TRAIN_DURATION_S, TEST_START_S, TEST_WINDOWS = 1.2, 0.2, 8
VIDEOS = {"bikes": SHARED / "videos" / "bikes.mp4", "truck_pan": SHARED / "esim_truck_pan" / "images",
          "slider_depth": SHARED / "ecd_slider_depth" / "images"}
MODES = ("teacher", "finetune", "student")
METHOD_NAMES = {"teacher": "EvtSL (teacher)", "finetune": "EvtSL->EvtSSL (fine-tune)",
                "student": "EvtSL->EvtSSL-bar (student)"}


# -- data --------------------------------------------------------------------------------------------
def _scene(preset: str, seed: int, duration_s: float):
    from cmax.sim.presets import make_scene
    from cmax.sim.scenes import TimeScaledScene

    factor = SPEED_FACTOR[preset]
    base = make_scene(preset, seed=seed, width=SIZE[0], height=SIZE[1], duration_s=factor * duration_s + 0.2,
                      texture_size=256)
    return base if factor == 1.0 else TimeScaledScene(base, factor)


def parallax_px(preset: str, seed: int, times_s=(0.3, 0.6, 0.9)) -> float:
    """Median over pixels and ``times_s`` of the translational image motion over one window [px]."""
    from cmax.sim.synthetic import motion_field

    scene = _scene(preset, seed, max(times_s) + 0.1)
    values = []
    for t in times_s:
        _, depth = scene.render(t)
        twist = np.r_[scene.twist(t)[:3], 0.0, 0.0, 0.0]
        du, dv = motion_field(depth, twist, scene.camera.K)
        values.append(np.nanmedian(np.hypot(du, dv)) * WINDOW_S)
    return float(np.median(values))


def _complete(path: Path, *, ground_truth: bool = True) -> bool:
    """True when ``path`` is a complete event file (:func:`cmax.io.h5.verify_h5`), with ``gt/depth`` and
    ``gt/twists`` when ``ground_truth`` (a resumed stage verifies what it keeps, never trusts its existence)."""
    import h5py

    from cmax.io.h5 import FormatError, verify_h5

    if not path.exists():
        return False
    try:
        verify_h5(path)
        if not ground_truth:
            return True
        with h5py.File(path, "r") as f:
            return "gt/depth" in f and "gt/twists" in f
    except (FormatError, OSError):
        return False


def simulate_file(job: tuple[str, int, str, float, float, tuple | None]) -> str:
    """Simulate one preset file (``job``: preset, seed, path, t0 [s], duration [s], depth times [s] or None)."""
    import torch

    from cmax.sim.esim import EventSimulator
    from cmax.sim.synthetic import simulate_scene

    torch.set_num_threads(1)
    preset, seed, path, t0_s, duration_s, depth_times = job
    path = Path(path)
    if _complete(path):
        return f"{path.name}: verified, kept"
    start = time.perf_counter()
    scene = _scene(preset, seed, t0_s + duration_s + 0.1)
    simulator = EventSimulator(**{**scene.recommended_simulator, "seed": seed})
    sequence = simulate_scene(scene, duration_s, simulator, t0_s=t0_s, min_step_s=1e-3,
                              depth_times_s=None if depth_times is None else np.asarray(depth_times))
    sequence.save(path, overwrite=True)
    return (f"{path.name}: {len(sequence.events):,} events, {len(sequence.frame_t_us)} frames, "
            f"{time.perf_counter() - start:.0f} s for {duration_s:g} s")


def data_jobs(root: Path) -> list[tuple]:
    """Every synthetic file of the experiment as a :func:`simulate_file` job."""
    jobs = []
    for label, preset, seed in TEST_SEQUENCES:
        middles = tuple(TEST_START_S + (np.arange(TEST_WINDOWS) + 0.5) * WINDOW_S)
        jobs.append((preset, seed, str(root / "test" / f"{label}.h5"), TEST_START_S,
                     TEST_WINDOWS * WINDOW_S + 0.01, middles))
    for preset in LABELLED_PRESETS:
        for seed in LABELLED_SEEDS:
            jobs.append((preset, seed, str(root / "labelled" / f"{preset}_{seed}.h5"), 0.0, TRAIN_DURATION_S, None))
    for preset, seed in UNLABELLED:
        jobs.append((preset, seed, str(root / "unlabelled" / f"{preset}_{seed}.h5"), 0.0, TRAIN_DURATION_S, None))
    for preset, seed in VAL:
        jobs.append((preset, seed, str(root / "val" / f"{preset}_{seed}.h5"), 0.0, TRAIN_DURATION_S, None))
    return jobs


def convert_videos(root: Path) -> list[str]:
    """The real videos of ``../shared/data`` as event files (ESIM, adaptive sampling) in ``unlabelled/``."""
    from cmax.sim.convert import ConvertSettings, convert_video
    from cmax.sim.esim import EsimSettings
    from cmax.sim.video import ImageFolderSource

    settings = ConvertSettings(EsimSettings(0.2, 0.2, 0.03, 0, seed=0), size=SIZE, adaptive=True, method="linear")
    lines = []
    for name, source in VIDEOS.items():
        out = root / "unlabelled" / f"video_{name}.h5"
        if not source.exists():
            lines.append(f"{source}: missing, skipped")
            continue
        if _complete(out, ground_truth=False):
            lines.append(f"{out.name}: verified, kept")
            continue
        frames = ImageFolderSource(source, size=SIZE, prefetch=0) if source.is_dir() else None
        convert_video(source, out, settings, frames=frames, overwrite=True)  # an incomplete file is redone
        lines.append(f"{out.name}: converted")
    return lines


def make_data(root: Path, jobs: int = 2) -> None:
    """Simulate and convert everything into ``root`` (cached: complete files are verified and kept)."""
    for name in ("labelled", "unlabelled", "val", "test"):
        (root / name).mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    todo = data_jobs(root)
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as pool:
            for line in pool.map(simulate_file, todo):
                print(line, file=sys.stderr, flush=True)
    else:
        for job in todo:
            print(simulate_file(job), file=sys.stderr, flush=True)
    for line in convert_videos(root):
        print(line, file=sys.stderr, flush=True)
    print(f"data: {time.perf_counter() - start:.0f} s with {jobs} processes", file=sys.stderr)


# -- training ----------------------------------------------------------------------------------------
def data_files(root: Path) -> dict[str, list]:
    """The ``data.files`` / ``data.val_files`` entries of each mode (see the module docstring)."""
    labelled = [str(p) for p in sorted((root / "labelled").glob("*.h5"))]
    unlabelled = [{"path": str(p), "use_gt": False, "known_speed": not p.stem.startswith("video_")}
                  for p in sorted((root / "unlabelled").glob("*.h5"))]
    from cmax.sim.presets import davis346_camera

    video_K = davis346_camera(*SIZE).K.tolist()   # converted videos carry no gt/K: the scenes' camera
    for entry in unlabelled:
        if not entry["known_speed"]:
            entry["K"] = video_K
    val = sorted((root / "val").glob("*.h5"))
    val_labelled = [str(p) for p in val if not p.stem.startswith("indoor_flying")]
    val_unlabelled = [{"path": str(p), "use_gt": False, "known_speed": True} for p in val]
    return {"teacher": (labelled, val_labelled), "finetune": (unlabelled, val_unlabelled),
            "student": (unlabelled, val_unlabelled)}


def run_dir(runs: Path, mode: str, seed: int) -> Path:
    return runs / f"{mode}_s{seed}"


#: Ablations (``--stage ablation``, seed 0): name -> (mode, config overrides, files read with the true twist).
ABLATIONS = {"finetune_true_twist": ("finetune", ["train.contrast_twist=truth"], True),
             "student_no_teacher_term": ("student", ["train.lam=1.0"], False)}


def train_one(mode: str, seed: int, root: Path, runs: Path, extra: list[str], *, name: str | None = None,
              true_twist: bool = False) -> Path:
    """Train (or resume, or verify as finished) one run; returns its ``last.pt``.

    ``name``: the run folder's name instead of the mode's (ablations); ``true_twist``: the unlabelled
    synthetic files are read with ``known_twist`` (their true twist kept, depth hidden).
    """
    import torch

    from learned.checkpoint import load_checkpoint
    from learned.config import load_config
    from learned.train import Trainer

    files, val = data_files(root)[mode]
    if true_twist:
        files = [{**f, "known_twist": f["known_speed"]} if isinstance(f, dict) else f for f in files]
        val = [{**f, "known_twist": f["known_speed"]} if isinstance(f, dict) else f for f in val]
    out = run_dir(runs, name or mode, seed)
    overrides = [f"data.files={json.dumps(files)}", f"data.val_files={json.dumps(val)}", f"train.seed={seed}",
                 f"train.out={out}"]
    if mode != "teacher":
        overrides.append(f"train.teacher={run_dir(runs, 'teacher', seed) / 'last.pt'}")
    config = load_config(CONFIGS / f"{mode}.toml", overrides + list(extra), mode=mode)
    last = out / "last.pt"
    if last.exists() and int(load_checkpoint(last)["step"]) >= config.train.steps:
        print(f"{mode} seed {seed}: finished run verified ({last})", file=sys.stderr)
        return last
    torch.manual_seed(seed)
    start = time.perf_counter()
    trainer = Trainer(config, resume=True, progress=True)
    losses = trainer.run()
    print(f"{mode} seed {seed}: {len(losses)} steps in {time.perf_counter() - start:.0f} s, "
          f"loss {losses[0] if losses else float('nan'):.4f} -> {losses[-1] if losses else float('nan'):.4f}",
          file=sys.stderr)
    return last


def train_ablations(root: Path, runs: Path, extra: list[str], seed: int = 0) -> None:
    for name, (mode, overrides, true_twist) in ABLATIONS.items():
        train_one(mode, seed, root, runs, list(overrides) + list(extra), name=name, true_twist=true_twist)


def train_all(root: Path, runs: Path, seeds: list[int], extra: list[str]) -> None:
    for seed in seeds:
        for mode in MODES:
            train_one(mode, seed, root, runs, extra)


# -- evaluation --------------------------------------------------------------------------------------
def evaluate(root: Path, runs: Path, seeds: list[int], baselines: bool = True) -> None:
    from benchmarks.learned_table import score_all, training_statistics, write_tables

    stats = training_statistics(sorted((root / "labelled").glob("*.h5")))
    methods = {METHOD_NAMES[m]: [run_dir(runs, m, s) / "last.pt" for s in seeds] for m in MODES}
    for name in ABLATIONS:   # seed 0 only, when run
        if (run_dir(runs, name, 0) / "last.pt").exists():
            methods[f"ablation: {name}"] = [run_dir(runs, name, 0) / "last.pt"]
    order = [label for label, _, _ in TEST_SEQUENCES]
    files = sorted((root / "test").glob("*.h5"), key=lambda p: order.index(p.stem) if p.stem in order else 99)
    rows = score_all(files, methods, constant_depth_m=stats.median_depth_m, mean_twist=np.asarray(stats.mean_twist),
                     window_s=WINDOW_S, baselines=baselines, cache=RESULTS / "accuracy_learned_table.baselines.json")
    write_tables(rows, RESULTS / "accuracy_learned_table.md", RESULTS / "accuracy_learned_table.csv")


# -- the shipped model --------------------------------------------------------------------------------
PRETRAINED = Path(__file__).resolve().parents[1] / "learned" / "pretrained"
FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "data" / "learned_window.npz"
#: The run that ships (chosen before any result was seen: the student of the first seed).
SHIPPED = ("student", 0)
#: The held-out window that the shipped model's card scores (test file, window index).
FIXTURE_WINDOW = ("indoor_flying1", 2)


def write_fixture(root: Path, out: Path = FIXTURE) -> Path:
    """One held-out window (events, K, true depth and twist) as a small npz: the card's fixed input."""
    from cmax.io.atomic import save_npz_atomic
    from learned.evaluate import held_out_windows

    label, index = FIXTURE_WINDOW
    window = held_out_windows(root / "test" / f"{label}.h5", int(round(WINDOW_S * 1e6)))[index]
    ev, sample = window.sample.events, window.sample
    out.parent.mkdir(parents=True, exist_ok=True)
    return save_npz_atomic(out, x=ev.x.astype(np.uint16), y=ev.y.astype(np.uint16),
                           t_us=(ev.t - sample.t0_us).astype(np.uint32), p=ev.p.astype(np.uint8),
                           t0_us=np.int64(sample.t0_us), t1_us=np.int64(sample.t1_us), K=sample.K,
                           depth=sample.depth.astype(np.float32), twist=np.asarray(sample.twist, np.float64),
                           far_m=np.float64(window.far_m), width=np.int64(ev.width), height=np.int64(ev.height))


def fixture_scores(checkpoint: Path, fixture: Path = FIXTURE) -> dict[str, float]:
    """Abs mean [m] and abs_rel of ``checkpoint`` on the fixture window (dense mask), and its mean twist."""
    import torch

    from cmax.events import Events
    from cmax.metrics import depth_metrics
    from cmax.representations import voxel_grid
    from learned.evaluate import load_model

    data = np.load(fixture)
    events = Events(data["x"].astype(np.int64), data["y"].astype(np.int64),
                    data["t_us"].astype(np.int64) + int(data["t0_us"]), data["p"].astype(np.int64),
                    int(data["width"]), int(data["height"]))
    model, _ = load_model(checkpoint)
    with torch.no_grad():
        out = model(torch.from_numpy(voxel_grid(events, model.config.bins))[None])
    depth = out.depth[0, 0].double().numpy()
    truth = data["depth"].astype(np.float64)
    m = depth_metrics(depth, truth, max_depth=float(data["far_m"]))
    return {"abs_mean_m": float(m.abs_mean), "abs_rel": float(m.abs_rel),
            "twist": [float(v) for v in out.twist[0]]}


def ship(root: Path, runs: Path) -> Path:
    """Copy the chosen student into ``learned/pretrained/student.pt`` (weights and config; no optimizer state)
    with its card ``student.json``: camera, window, the run, its test scores, its scores on the fixture."""
    import torch

    from benchmarks.learned_table import read_csv
    from cmax.io.atomic import write_text_atomic
    from cmax.sim.presets import davis346_camera
    from learned.checkpoint import load_checkpoint, save_checkpoint

    mode, seed = SHIPPED
    source = run_dir(runs, mode, seed) / "last.pt"
    ckpt = load_checkpoint(source)
    payload = {"model": {k: v.clone() for k, v in ckpt["model"].items()}, "optimizer": {}, "step": ckpt["step"],
               "config": ckpt["config"], "rng": {}}
    target = save_checkpoint(PRETRAINED / "student.pt", payload)
    if not FIXTURE.exists():
        write_fixture(root)
    K = davis346_camera(*SIZE).K
    table = RESULTS / "accuracy_learned_table.csv"
    scores = {row.sequence: {"abs_mean_m": row.abs_mean_m, "rmse_log": row.rmse_log}
              for row in (read_csv(table) if table.exists() else [])
              if row.method == METHOD_NAMES[mode] and row.seed == str(seed) and row.mask == "dense"}
    card = {"model": f"{METHOD_NAMES[mode]}, seed {seed}", "size": list(SIZE),
            "K": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])], "window_s": WINDOW_S,
            "steps": int(ckpt["step"]), "torch": torch.__version__,
            "reproduce": "CMAX_TORCH_THREADS=1 python -m benchmarks.learned_experiment --data-dir DATA "
                         "&& python -m benchmarks.learned_experiment --stage ship --data-dir DATA",
            "test_scores_dense": scores,
            "fixture": {"file": str(FIXTURE.relative_to(FIXTURE.parents[2])), "test_file": FIXTURE_WINDOW[0],
                        "window": FIXTURE_WINDOW[1], **fixture_scores(target)}}
    write_text_atomic(PRETRAINED / "student.json", json.dumps(card, indent=2) + "\n")
    return target


# -- learning curves ---------------------------------------------------------------------------------
def read_log(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{key: (steps, values)}`` of a run's ``log.jsonl`` (the last value of a step wins: resumed runs)."""
    series: dict[str, dict[int, float]] = {}
    for line in path.read_text().splitlines():
        record = json.loads(line)
        step = int(record.pop("step"))
        for key, value in record.items():
            series.setdefault(key, {})[step] = float(value)
    return {k: (np.array(sorted(v)), np.array([v[s] for s in sorted(v)])) for k, v in series.items()}


COLOURS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40))   # RGB, one per seed


def line_plot(series, *, title: str, xlabel: str, ylabel: str, size: tuple[int, int] = (460, 320)) -> np.ndarray:
    """A line chart (H, W, 3) uint8 RGB drawn with OpenCV: ``series`` of ``(label, (r, g, b), x, y, markers)``,
    axes with 5 ticks each, a legend in the top right corner (the project does not depend on matplotlib)."""
    import cv2

    from cmax import viz

    W, H = size
    left, right, top, bottom = 58, 12, 10, 40
    image = np.full((H, W, 3), 255, np.uint8)
    xs = np.concatenate([np.asarray(x, float) for _, _, x, _, _ in series]) if series else np.array([0.0, 1.0])
    ys = np.concatenate([np.asarray(y, float) for _, _, _, y, _ in series]) if series else np.array([0.0, 1.0])
    x0, x1 = float(xs.min()), float(max(xs.max(), xs.min() + 1))
    y0, y1 = float(np.nanmin(ys)), float(np.nanmax(ys))
    y0, y1 = (y0 - 0.05 * (y1 - y0 + 1e-9), y1 + 0.05 * (y1 - y0 + 1e-9))

    def to_px(x, y):
        px = left + (np.asarray(x, float) - x0) / (x1 - x0) * (W - left - right)
        py = H - bottom - (np.asarray(y, float) - y0) / (y1 - y0) * (H - top - bottom)
        return np.stack([px, py], -1)

    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.rectangle(image, (left, top), (W - right, H - bottom), (0, 0, 0), 1)
    for k in range(5):
        xv, yv = x0 + k * (x1 - x0) / 4, y0 + k * (y1 - y0) / 4
        px, py = to_px(xv, yv)
        cv2.line(image, (int(px), H - bottom), (int(px), H - bottom + 4), (0, 0, 0), 1)
        cv2.putText(image, f"{xv:.0f}", (int(px) - 12, H - bottom + 16), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.line(image, (left - 4, int(py)), (left, int(py)), (0, 0, 0), 1)
        cv2.putText(image, f"{yv:.3g}", (4, int(py) + 4), font, 0.35, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(image, xlabel, (W // 2 - 20, H - 6), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for k, (label, colour, x, y, markers) in enumerate(series):
        points = to_px(x, y).round().astype(np.int32)
        cv2.polylines(image, [points], False, colour, 2 if markers else 1, cv2.LINE_AA)
        if markers:
            for p in points:
                cv2.circle(image, (int(p[0]), int(p[1])), 3, colour, -1, cv2.LINE_AA)
        cv2.putText(image, label, (W - right - 150, top + 14 + 13 * k), font, 0.35, colour, 1, cv2.LINE_AA)
    return viz.titled(image, f"{title} ({ylabel})")


def draw_curves(runs: Path, seeds: list[int], out: Path) -> Path:
    """Training (smoothed, thin) and validation loss (dots) against the step, one panel per mode, one colour
    per seed; ``out`` a PNG."""
    from cmax import viz

    panels = []
    for mode in MODES:
        series = []
        for k, seed in enumerate(seeds):
            log = run_dir(runs, mode, seed) / "log.jsonl"
            if not log.exists():
                continue
            data = read_log(log)
            colour = COLOURS[k % len(COLOURS)]
            if "loss/total" in data:
                steps, values = data["loss/total"]
                width = max(1, len(values) // 20)
                smooth = np.convolve(values, np.ones(width) / width, mode="valid")
                series.append((f"train, seed {seed}", tuple(c // 2 + 127 for c in colour), steps[width - 1:],
                               smooth, False))
            if "val/loss" in data:
                steps, values = data["val/loss"]
                series.append((f"validation, seed {seed}", colour, steps, values, True))
        panels.append(line_plot(series, title=METHOD_NAMES[mode], xlabel="step", ylabel="loss"))
    return viz.save_png(out, viz.hstack(panels))


def main(argv: list[str] | None = None) -> int:
    from cmax._args import ArgumentParser, run_main

    parser = ArgumentParser(prog="python -m benchmarks.learned_experiment", description=__doc__.splitlines()[0])
    parser.add_argument("--stage", choices=("all", "data", "train", "ablation", "evaluate", "curves", "ship",
                                            "parallax"),
                        default="all")
    parser.add_argument("--data-dir", type=Path, required=True, help="cache of the simulated files")
    parser.add_argument("--runs-dir", type=Path, default=None, help="training runs (default DATA_DIR/runs)")
    parser.add_argument("--seeds", default="0,1,2", help="training seeds, comma-separated")
    parser.add_argument("--jobs", type=int, default=2, help="processes simulating the data")
    parser.add_argument("--no-baselines", action="store_true", help="evaluate without the cmax.fit / EMVS rows")
    parser.add_argument("overrides", nargs="*", help="config overrides for every run (e.g. train.steps=10)")
    return run_main(parser, _run, argv)


def _run(args: argparse.Namespace) -> int:
    root, runs = args.data_dir, args.runs_dir or args.data_dir / "runs"
    seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    if args.stage == "parallax":
        for preset, factor in SPEED_FACTOR.items():
            print(f"{preset} x{factor:g}: {parallax_px(preset, 1):.2f} px per {WINDOW_S} s window at "
                  f"{SIZE[0]}x{SIZE[1]}")
        return 0
    if args.stage in ("all", "data"):
        make_data(root, args.jobs)
    if args.stage in ("all", "train"):
        train_all(root, runs, seeds, args.overrides)
    if args.stage == "ablation":
        train_ablations(root, runs, args.overrides)
    if args.stage in ("all", "evaluate"):
        evaluate(root, runs, seeds, baselines=not args.no_baselines)
    if args.stage in ("all", "curves"):
        print(draw_curves(runs, seeds, RESULTS / "learned_curves.png"))
    if args.stage in ("all", "ship"):
        print(ship(root, runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
