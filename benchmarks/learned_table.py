"""The learned experiment's table (issue 18 item 4): every method on the same held-out windows and pixel masks.

For each held-out file with ground truth (``SyntheticSequence.save``) the windows are
those of :func:`learned.evaluate.held_out_windows` (centred on the ground-truth depth
times; the window length from the checkpoints' ``data.window_us`` unless given), and
every method is scored on the same two masks of each window:

* ``dense``: every pixel with valid ground truth up to the scene's far limit (capped at 80 m);
* ``event``: the dense pixels holding at least one event of the window (the semi-dense
  protocol of the EMVS-style baselines).

Methods:

* each network (a name and N checkpoints, the training seeds): its depth and twist;
* ``constant``: one depth [m] everywhere (the caller's: the training set's median depth)
  with one twist for every window (the caller's: the training set's mean twist), the
  trivial baseline of depth and of motion;
* ``cmax.fit``: :func:`cmax.fit` (se3, default settings) on each window with the known speed
  (``|v|`` of the true twist at the window's middle) and the scene's depth range (as
  ``benchmarks/accuracy.py`` runs it); its depth at ``FitResult.mask`` only;
* ``EMVS (GT poses)``: :class:`cmax.emvs.EMVS` on each window's events with the true poses,
  the reference view at the window's middle (the time of the true depth), the scene's depth
  range, ``benchmarks.accuracy.TableSettings``' number of planes; its depth on its semi-dense mask.

A method without an estimate at some mask pixels is scored on the pixels it covers and its
``coverage`` (covered / mask pixels) is reported next to its errors. Metrics are
:func:`cmax.metrics.depth_metrics`, pooled over the windows of a sequence; motion errors
(:func:`cmax.metrics.motion_metrics`) are against the true twist at each window's middle.

:func:`score_all` returns one :class:`TableRow` per method x checkpoint x sequence x mask;
:func:`write_tables` writes the markdown tables (networks: mean and min-max over their
checkpoints) and the CSV (every row). The baselines' rows (``cmax.fit`` takes seconds per
window) are cached in a JSON file keyed by the file's SHA-256, the window length and the
baseline's settings, so that a re-run of the table does not refit.

Usage::

    python -m benchmarks.learned_table --data test/*.h5 \\
        --method teacher=runs/t0/last.pt,runs/t1/last.pt,runs/t2/last.pt --method student=... \\
        --constant-depth 3.1 --mean-twist 0.1,0,0.3,0,0.01,0 --output benchmarks/results/learned_table
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import h5py
import numpy as np

from cmax.io.atomic import file_sha256, write_text_atomic
from cmax.metrics import DepthMetrics, MotionMetrics

RESULTS = Path(__file__).resolve().parent / "results"
MASKS = ("dense", "event")
CONSTANT, FIT, EMVS_GT = "constant", "cmax.fit", "EMVS (GT poses)"
#: Version of the cached baseline rows: bump when what a baseline computes changes.
CACHE_VERSION = 1


@dataclass(frozen=True)
class TableRow:
    """One method (one checkpoint) on one sequence and one mask.

    ``seed`` names the checkpoint of a network (its index among the method's checkpoints,
    ``"0"``, ``"1"``, ...) and is empty for a baseline. Depth errors are [m] except
    ``rmse_log``, ``abs_rel`` and ``delta1`` [1]; ``coverage`` is the share of the mask's
    pixels the method has an estimate at; ``v_rms_m_s`` [m/s] and ``omega_rms_deg_s``
    [deg/s] are the twist's errors (NaN for a method without a twist).
    """

    method: str
    seed: str
    sequence: str
    mask: str
    windows: int
    abs_mean_m: float
    rmse_log: float
    abs_rel: float
    delta1: float
    err_10m: float
    err_20m: float
    err_30m: float
    coverage: float
    n_pixels: int
    v_rms_m_s: float = math.nan
    omega_rms_deg_s: float = math.nan


CSV_COLUMNS = tuple(f.name for f in dataclasses.fields(TableRow))


def make_row(method: str, seed: str, sequence: str, mask: str, windows: int, depth: DepthMetrics,
             motion: MotionMetrics | None) -> TableRow:
    """A :class:`TableRow` from pooled depth metrics and (optionally) motion metrics."""
    nan = math.nan
    return TableRow(method, seed, sequence, mask, windows, depth.abs_mean, depth.rmse_log, depth.abs_rel,
                    depth.delta1, depth.cutoff_errors[10.0], depth.cutoff_errors[20.0], depth.cutoff_errors[30.0],
                    depth.coverage, depth.n_pixels, motion.v_rms_m_s if motion else nan,
                    motion.omega_rms_deg_s if motion else nan)


# -- methods on the windows of one file ----------------------------------------------------------
def method_rows(method: str, seed: str, windows: Sequence, depth: np.ndarray,
                twist: np.ndarray | None) -> list[TableRow]:
    """Rows (one per mask) of predicted depths (N, H, W) [m] (NaN: no estimate) and twists (N, 6) or (6,)
    (None: the method has none) on ``windows`` (:func:`learned.evaluate.held_out_windows` of one file)."""
    from learned.evaluate import score_depth, score_motion

    motion = None if twist is None else score_motion(twist, windows)
    return [make_row(method, seed, windows[0].sequence, mask, len(windows), score_depth(depth, windows, mask), motion)
            for mask in MASKS]


def constant_prediction(windows: Sequence, depth_m: float) -> np.ndarray:
    """``depth_m`` [m] at every pixel of every window (N, H, W) float32."""
    if not (np.isfinite(depth_m) and depth_m > 0):
        raise ValueError(f"constant_depth_m must be a positive number of metres, got {depth_m}")
    return np.full((len(windows),) + windows[0].dense.shape, depth_m, np.float32)


def true_speed(window) -> float:
    """``|v|`` [m/s] of the true twist at the window's middle (the fit's known speed)."""
    if window.sample.twist is None:
        raise ValueError(f"{window.sequence}: cmax.fit with the known speed needs gt/twists")
    return float(np.linalg.norm(np.asarray(window.sample.twist, np.float64)[:3]))


def fit_windows(windows: Sequence, depth_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`cmax.fit` (se3, default settings, ``depth_range``) of each window with its known speed
    (:func:`true_speed`): depth (N, H, W) [m], NaN outside ``FitResult.mask``, and the fitted twists (N, 6)."""
    from tqdm import tqdm

    import cmax

    depths, twists = [], []
    for w in tqdm(windows, desc=f"cmax.fit {windows[0].sequence}", unit="window", file=sys.stderr, leave=False):
        fitted = cmax.fit(w.sample.events, w.sample.K, "se3", speed=true_speed(w), depth_range=depth_range)
        depths.append(np.where(fitted.mask, fitted.depth, np.nan).astype(np.float32))
        twists.append(np.r_[fitted.v, fitted.omega])
    return np.stack(depths), np.stack(twists)


def read_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The true trajectory of a file: times (M,) int64 [µs] and camera-to-world poses (M, 4, 4)."""
    with h5py.File(path, "r") as f:
        if "gt/poses" not in f or "gt/poses_t" not in f:
            raise ValueError(f"{path}: EMVS with the true poses needs gt/poses and gt/poses_t")
        return f["gt/poses_t"][:].astype(np.int64), f["gt/poses"][:].astype(np.float64)


def emvs_windows(windows: Sequence, poses: tuple[np.ndarray, np.ndarray], depth_range: tuple[float, float],
                 n_planes: int) -> np.ndarray:
    """:class:`cmax.emvs.EMVS` on each window's events with the true ``poses`` (times µs, T_w_c), the reference
    view at the window's middle: depth (N, H, W) [m], NaN outside its semi-dense mask."""
    from cmax.camera import Camera
    from cmax.emvs import EMVS

    depths = []
    for w in windows:
        ev = w.sample.events
        emvs = EMVS(Camera(w.sample.K, ev.width, ev.height), depth_range=depth_range, n_planes=n_planes)
        middle = (int(w.sample.t0_us) + int(w.sample.t1_us)) // 2
        result = emvs.run(ev, poses, t_ref_us=middle)
        depths.append(np.where(result.mask, result.depth, np.nan).astype(np.float32))
    return np.stack(depths)


# -- the cache of baseline rows -----------------------------------------------------------------
def cache_key(sha256: str, window_us: int, method: str, settings: Mapping[str, object]) -> str:
    """Key of a baseline's rows on one file: content hash, window length, method and its settings."""
    return json.dumps([CACHE_VERSION, sha256, int(window_us), method, dict(sorted(settings.items()))])


def read_cache(path: Path | None) -> dict[str, list[dict]]:
    """The cached rows (empty when there is no cache file)."""
    if path is None or not path.exists():
        return {}
    data = json.loads(path.read_text())
    if not isinstance(data, dict):
        raise ValueError(f"{path} is not a cache of learned_table (a JSON object)")
    return data


def rows_from_cache(entries: list[dict], sequence: str) -> list[TableRow]:
    """Cached row dicts back as rows (the sequence renamed to the file's current stem)."""
    return [TableRow(**{**entry, "sequence": sequence}) for entry in entries]


# -- the constant baseline's figures ----------------------------------------------------------------
@dataclass(frozen=True)
class TrainingStatistics:
    """What a trivial predictor learns from labelled training files: the median true depth [m] and the mean
    true twist (6,) ``(v m/s, omega rad/s)``, with the number of depth samples and twists they come from."""

    median_depth_m: float
    mean_twist: tuple[float, ...]
    depth_samples: int
    twists: int


def training_statistics(files: Sequence[str | Path], *, pixel_stride: int = 4) -> TrainingStatistics:
    """Median of the valid true depth (finite, > 1 mm, up to each file's far limit) over every depth map of
    ``files`` (every ``pixel_stride``-th row and column, to bound memory), and the mean of their true twists."""
    from learned.evaluate import MIN_DEPTH_M, far_limit

    if not files or pixel_stride < 1:
        raise ValueError(f"need training files and pixel_stride >= 1, got {len(files)} files, {pixel_stride}")
    depths, twists = [], []
    for path in files:
        far = far_limit(path)
        with h5py.File(path, "r") as f:
            if "gt/depth" not in f or "gt/twists" not in f:
                raise ValueError(f"{path}: training statistics need gt/depth and gt/twists")
            for k in range(f["gt/depth"].shape[0]):
                d = f["gt/depth"][k][::pixel_stride, ::pixel_stride]
                with np.errstate(invalid="ignore"):
                    depths.append(d[np.isfinite(d) & (d > MIN_DEPTH_M) & (d <= far)])
            twists.append(f["gt/twists"][:].astype(np.float64))
    depth, twist = np.concatenate(depths), np.concatenate(twists)
    if not depth.size or not len(twist):
        raise ValueError("the training files hold no valid depth or no twist")
    return TrainingStatistics(float(np.median(depth)), tuple(float(x) for x in twist.mean(0)), int(depth.size),
                              len(twist))


# -- everything ---------------------------------------------------------------------------------
def window_length_us(checkpoints: Sequence[Path], window_s: float | None) -> int:
    """The window length [µs]: ``window_s``, or the ``data.window_us`` all ``checkpoints`` agree on."""
    if window_s is not None:
        if not (np.isfinite(window_s) and window_s > 0):
            raise ValueError(f"window_s must be a positive number of seconds, got {window_s}")
        return max(1, int(round(window_s * 1e6)))
    from learned.checkpoint import load_checkpoint

    lengths = {int(load_checkpoint(p)["config"]["data"]["window_us"]) for p in checkpoints}
    if len(lengths) != 1:
        raise ValueError("give window_s: " + ("no checkpoint states a window length" if not lengths else
                                              f"the checkpoints' data.window_us differ: {sorted(lengths)} µs"))
    return lengths.pop()


def score_all(test_files: Sequence[str | Path], methods: Mapping[str, Sequence[str | Path]], *,
              constant_depth_m: float, mean_twist: Sequence[float], window_s: float | None = None,
              baselines: bool = True, cache: str | Path | None = None, n_planes: int | None = None
              ) -> list[TableRow]:
    """Every method on every file's windows and both masks (see the module docstring).

    Parameters
    ----------
    test_files : paths of held-out files with ground truth.
    methods : name -> checkpoints (the seeds of one recipe).
    constant_depth_m : the constant baseline's depth [m] (the training set's median depth).
    mean_twist : (6,) the constant baseline's twist ``(v m/s, omega rad/s)`` (the training set's mean).
    window_s : window length [s]; default the checkpoints' ``data.window_us``.
    baselines : also score ``cmax.fit`` and ``EMVS (GT poses)``.
    cache : JSON file of the baselines' rows (read, and rewritten atomically when new rows were computed).
    n_planes : EMVS planes (default ``benchmarks.accuracy.TableSettings.n_planes``).
    """
    from tqdm import tqdm

    from benchmarks.accuracy import TableSettings
    from learned.evaluate import depth_range, held_out_windows, load_model, predict_windows

    if not test_files:
        raise ValueError("test_files: need at least one held-out file")
    mean_twist = np.asarray(mean_twist, np.float64)
    if mean_twist.shape != (6,) or not np.all(np.isfinite(mean_twist)):
        raise ValueError(f"mean_twist must be 6 finite numbers (v m/s, omega rad/s), got {mean_twist.tolist()}")
    checkpoints = {name: [Path(p) for p in paths] for name, paths in methods.items()}
    for name, paths in checkpoints.items():
        if not paths:
            raise ValueError(f"method {name!r} has no checkpoint")
        if name in (CONSTANT, FIT, EMVS_GT):
            raise ValueError(f"{name!r} names a baseline: give the network another name")
    window_us = window_length_us([p for paths in checkpoints.values() for p in paths], window_s)
    n_planes = TableSettings.n_planes if n_planes is None else int(n_planes)
    cache_path = None if cache is None else Path(cache)
    cached = read_cache(cache_path)
    models = {name: [load_model(p)[0] for p in paths] for name, paths in checkpoints.items()}
    rows: list[TableRow] = []
    for path in tqdm([Path(p) for p in test_files], desc="sequences", unit="file", file=sys.stderr):
        windows = held_out_windows(path, window_us)
        for name, nets in models.items():
            for seed, model in enumerate(nets):
                depth, twist = predict_windows(model, windows)
                rows += method_rows(name, str(seed), windows, depth, twist)
        rows += method_rows(CONSTANT, "", windows, constant_prediction(windows, constant_depth_m), mean_twist)
        if not baselines:
            continue
        near_far = depth_range(path)
        sha = file_sha256(path)
        settings = {FIT: {"depth_range": near_far}, EMVS_GT: {"depth_range": near_far, "n_planes": n_planes}}
        for method in (FIT, EMVS_GT):
            key = cache_key(sha, window_us, method, settings[method])
            if key in cached:
                rows += rows_from_cache(cached[key], windows[0].sequence)
                continue
            if method == FIT:
                computed = method_rows(FIT, "", windows, *fit_windows(windows, near_far))
            else:
                depth = emvs_windows(windows, read_poses(path), near_far, n_planes)
                computed = method_rows(EMVS_GT, "", windows, depth, None)
            cached[key] = [dataclasses.asdict(r) for r in computed]
            rows += computed
            if cache_path is not None:   # after every baseline: an interrupted run keeps what it computed
                cache_path.parent.mkdir(parents=True, exist_ok=True)
                write_text_atomic(cache_path, json.dumps(cached, indent=1))
    return rows


# -- output ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spread:
    """Mean, min and max of one figure over a method's checkpoints (NaN values left out), and their count."""

    mean: float
    low: float
    high: float
    count: int


def spread(values: Sequence[float]) -> Spread:
    """:class:`Spread` of ``values``; all NaN when none is finite."""
    finite = np.asarray([v for v in values if np.isfinite(v)], np.float64)
    if not finite.size:
        return Spread(math.nan, math.nan, math.nan, 0)
    return Spread(float(finite.mean()), float(finite.min()), float(finite.max()), int(finite.size))


def summarise(rows: Sequence[TableRow], field: str) -> dict[tuple[str, str, str], Spread]:
    """``(method, sequence, mask) -> Spread`` of ``field`` over the rows' checkpoints."""
    groups: dict[tuple[str, str, str], list[float]] = {}
    for row in rows:
        groups.setdefault((row.method, row.sequence, row.mask), []).append(float(getattr(row, field)))
    return {key: spread(values) for key, values in groups.items()}


def _cell(s: Spread | None, digits: int = 2) -> str:
    if s is None or s.count == 0:
        return "n/a"
    text = f"{s.mean:.{digits}f}"
    return text + (f" ({s.low:.{digits}f}–{s.high:.{digits}f})" if s.count > 1 else "")


def markdown_tables(rows: Sequence[TableRow]) -> list[str]:
    """The markdown of :func:`write_tables` (without the title)."""
    methods = list(dict.fromkeys(r.method for r in rows))
    sequences = list(dict.fromkeys(r.sequence for r in rows))
    seeds = {m: len({r.seed for r in rows if r.method == m}) for m in methods}
    windows = {s: next(r.windows for r in rows if r.sequence == s) for s in sequences}
    stats = {field: summarise(rows, field) for field in
             ("abs_mean_m", "rmse_log", "coverage", "err_10m", "err_20m", "err_30m", "v_rms_m_s", "omega_rms_deg_s")}
    name = lambda m: f"{m} ({seeds[m]} seeds)" if seeds[m] > 1 else m  # noqa: E731
    lines = ["Networks: mean over their checkpoints (the training seeds) with the min–max range in brackets; "
             "baselines: one run. Windows per sequence: " + ", ".join(f"{s} {windows[s]}" for s in sequences)
             + f". `{CONSTANT}`: one depth everywhere (the training set's median) and the training set's mean "
             f"twist for every window; `{FIT}`: se3 fit of each window with its true speed and the scene's depth "
             f"range, depth on its own mask; `{EMVS_GT}`: EMVS on each window's events with the true poses, the "
             "reference view at the window's middle. A method that has no estimate at some mask pixels is scored "
             "on the pixels it covers: its coverage (covered / mask pixels) follows in square brackets "
             "(n/a [0 %]: no estimate at all, e.g. a fit that found too little parallax).", ""]
    for mask in MASKS:
        title = {"dense": "dense: every pixel with valid ground truth",
                 "event": "event pixels: valid ground truth and at least one event in the window"}[mask]
        lines += [f"## Abs mean [m] / rms_log, {title}", "",
                  "| method | " + " | ".join(sequences) + " |", "|---|" + "---:|" * len(sequences)]
        for m in methods:
            cells = []
            for s in sequences:
                key = (m, s, mask)
                coverage = stats["coverage"].get(key)
                cell = f"{_cell(stats['abs_mean_m'].get(key))} / {_cell(stats['rmse_log'].get(key))}"
                if coverage is not None and coverage.count and coverage.mean < 0.9995:
                    cell += f" [{100 * coverage.mean:.0f} %]"
                cells.append(cell)
            lines.append(f"| {name(m)} | " + " | ".join(cells) + " |")
        lines += ["", f"Cut-off errors [m] (mean |error| over the pixels with ground truth within 10 / 20 / 30 m; "
                  f"networks: mean over their checkpoints), {mask} mask:", "",
                  "| method | " + " | ".join(sequences) + " |", "|---|" + "---:|" * len(sequences)]
        mean_only = lambda s: None if s is None else Spread(s.mean, s.mean, s.mean, min(s.count, 1))  # noqa: E731
        for m in methods:
            cells = [" / ".join(_cell(mean_only(stats[f"err_{c}m"].get((m, s, mask)))) for c in (10, 20, 30))
                     for s in sequences]
            lines.append(f"| {name(m)} | " + " | ".join(cells) + " |")
        lines.append("")
    moving = [m for m in methods if any(np.isfinite(r.v_rms_m_s) for r in rows if r.method == m)]
    if moving:
        lines += ["## Motion: v_rms [m/s] / omega_rms [deg/s] against the true twist at each window's middle", "",
                  f"`{CONSTANT}` predicts the training set's mean twist for every window; `{FIT}` had the true "
                  "speed, so its v error is in the direction only.", "",
                  "| method | " + " | ".join(sequences) + " |", "|---|" + "---:|" * len(sequences)]
        for m in moving:
            cells = [f"{_cell(stats['v_rms_m_s'].get((m, s, 'dense')), 3)} / "
                     f"{_cell(stats['omega_rms_deg_s'].get((m, s, 'dense')), 1)}" for s in sequences]
            lines.append(f"| {name(m)} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def to_csv(rows: Sequence[TableRow]) -> str:
    """The rows as CSV text (:data:`CSV_COLUMNS`; floats with 6 significant digits)."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in dataclasses.asdict(row).items()})
    return buffer.getvalue()


def read_csv(path: str | Path) -> list[TableRow]:
    """Rows of a CSV written by :func:`write_tables`; raises a ValueError for other columns."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != CSV_COLUMNS:
            raise ValueError(f"{path} must have the columns {','.join(CSV_COLUMNS)}, got {reader.fieldnames}")
        kinds = {f.name: f.type for f in dataclasses.fields(TableRow)}
        convert = {"int": int, "float": float, "str": str}
        return [TableRow(**{k: convert[kinds[k]](v) for k, v in row.items()}) for row in reader]


def write_tables(rows: Sequence[TableRow], md_path: str | Path, csv_path: str | Path, *,
                 title: str = "Learned depth: every method on the same windows and masks",
                 preamble: Sequence[str] = ()) -> tuple[Path, Path]:
    """The markdown tables (both masks, motion) and the CSV (every row), each written atomically."""
    if not rows:
        raise ValueError("rows: nothing to write")
    text = "\n".join([f"# {title}", "", *preamble, *([""] if preamble else []), *markdown_tables(rows)])
    return write_text_atomic(md_path, text.rstrip("\n") + "\n"), write_text_atomic(csv_path, to_csv(rows))


# -- the objective check --------------------------------------------------------------------------
def objective_lines(preferences, objective: str = "the shared contrast objective") -> list[str]:
    """Markdown of :func:`learned.evaluate.objective_preferences`: the counts, then every window's values."""
    from learned.evaluate import CANDIDATES

    total = len(preferences.windows)
    lines = [f"## Which parameters does {objective} prefer?", "",
             "On each held-out window: the objective (lower is better; every twist scaled to the window's true "
             "speed) at the truth, at the network's depth and twist, at the network's depth with the true twist, "
             "and at a constant depth (the window's median true depth) with the true twist.", "",
             "| lowest at | windows |", "|---|---:|"]
    lines += [f"| {name} | {preferences.counts[name]} of {total} |" for name in CANDIDATES]
    lines += ["", "| sequence | t0 [s] | speed [m/s] | " + " | ".join(CANDIDATES) + " | lowest |",
              "|---|---:|---:|" + "---:|" * len(CANDIDATES) + "---|"]
    for w in preferences.windows:
        lines.append(f"| {w.sequence} | {w.t0_us * 1e-6:.3f} | {w.speed_m_s:.3f} | "
                     + " | ".join(f"{w.values[name]:.5g}" for name in CANDIDATES) + f" | {w.lowest} |")
    return lines + [""]


# -- command line -----------------------------------------------------------------------------------
def _method(text: str) -> tuple[str, list[Path]]:
    name, sep, paths = text.partition("=")
    if not sep or not name or not paths:
        raise argparse.ArgumentTypeError(f"expected NAME=CKPT[,CKPT...], got {text!r}")
    return name, [Path(p) for p in paths.split(",")]


def main(argv: list[str] | None = None) -> int:
    """Score the methods, write ``OUTPUT.md``, ``OUTPUT.csv`` and the baseline cache ``OUTPUT.baselines.json``."""
    from cmax._args import ArgumentParser, float_list, positive_float, run_main

    parser = ArgumentParser(prog="python -m benchmarks.learned_table", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="held-out h5 files with gt/")
    parser.add_argument("--method", type=_method, action="append", default=[], metavar="NAME=CKPT[,CKPT...]",
                        help="a network row: its checkpoints (one per training seed)")
    parser.add_argument("--constant-depth", type=positive_float, default=None,
                        help="the constant baseline's depth [m] (the training set's median depth)")
    parser.add_argument("--mean-twist", type=float_list((6,), "vx,vy,vz,wx,wy,wz"), default=None,
                        help="the constant baseline's twist: 6 numbers, v [m/s] then omega [rad/s] (training mean)")
    parser.add_argument("--training-data", type=Path, nargs="+", default=None,
                        help="labelled training files: the constant baseline's depth and twist are their median "
                             "depth and mean twist (training_statistics), unless given above")
    parser.add_argument("--window", type=positive_float, default=None,
                        help="window length [s] (default: the checkpoints' data.window_us)")
    parser.add_argument("--no-baselines", action="store_true", help="leave out cmax.fit and EMVS")
    parser.add_argument("--objective-check", type=Path, default=None, metavar="CKPT",
                        help="also report which parameters the shared contrast objective (and its data term "
                             "alone) prefers with this network")
    parser.add_argument("--output", type=Path, default=RESULTS / "learned_table",
                        help="path prefix of the .md, .csv and .baselines.json files")
    return run_main(parser, _run, argv)


def _run(args: argparse.Namespace) -> int:
    import torch

    from cmax.contrast import SHARED_OBJECTIVE
    from learned.evaluate import objective_preferences

    torch.set_num_threads(1)
    start, load = time.perf_counter(), os.getloadavg()[0]
    methods = dict(args.method)
    if len(methods) != len(args.method):
        raise ValueError("--method: each name once")
    if args.training_data is not None and (args.constant_depth is None or args.mean_twist is None):
        stats = training_statistics(args.training_data)
        args.constant_depth = stats.median_depth_m if args.constant_depth is None else args.constant_depth
        args.mean_twist = stats.mean_twist if args.mean_twist is None else args.mean_twist
    if args.constant_depth is None or args.mean_twist is None:
        raise ValueError("give --constant-depth and --mean-twist, or --training-data to compute them")
    rows = score_all(args.data, methods, constant_depth_m=args.constant_depth, mean_twist=args.mean_twist,
                     window_s=args.window, baselines=not args.no_baselines,
                     cache=args.output.with_name(args.output.name + ".baselines.json"))
    preamble = [f"`python -m benchmarks.learned_table` on {', '.join(p.name for p in args.data)}: "
                f"{time.perf_counter() - start:.0f} s with 1 torch thread, 1-minute load {load:.2f} before and "
                f"{os.getloadavg()[0]:.2f} after. Constant baseline: {args.constant_depth:g} m and twist "
                f"{', '.join(f'{x:g}' for x in args.mean_twist)} (v m/s, omega rad/s)."]
    md, csv_path = write_tables(rows, args.output.with_name(args.output.name + ".md"),
                                args.output.with_name(args.output.name + ".csv"), preamble=preamble)
    if args.objective_check is not None:   # the objective, and its data term alone (the smoothness ablated)
        text = md.read_text()
        for objective, label in ((SHARED_OBJECTIVE, f"the shared objective (`{SHARED_OBJECTIVE}`)"),
                                 (dataclasses.replace(SHARED_OBJECTIVE, smoothness=0.0),
                                  "its data term alone (smoothness 0)")):
            preferences = objective_preferences(args.data, args.objective_check, objective, window_s=args.window)
            text += "\n" + "\n".join(objective_lines(preferences, label))
        write_text_atomic(md, text)
    print(md.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
