"""Depth accuracy on held-out synthetic sequences: the paper's Tables 2 and 3, plus ``cmax.fit``'s own table.

Sections:

* ``tables`` (this module): on held-out seeds of the ``indoor_flying`` preset
  (three sequences, like MVSEC flying1-3), ``driving_day`` and ``driving_night``
  (:func:`cmax.sim.make_scene`, events by :func:`cmax.sim.simulate_scene`), the
  depth errors of

  - ``EMVS (GT poses)``: :class:`cmax.emvs.EMVS` with the scene's poses;
  - ``EMVS (fit_sequence poses)``: EMVS with the poses of :func:`cmax.fit_sequence`
    (se3, the sequence's mean ground-truth speed fixes the scale);
  - ``cmax.fit``: the depth of every 0.1665 s window (the paper's window) by
    :func:`cmax.fit` with the window's mean ground-truth speed.

  Ground truth is the scene's depth rendered at each method's reference time
  (EMVS: ``t_ref_us``, the middle of its events; ``cmax.fit``: ``FitResult.t_ref_us``).
  Each method is scored on its own pixels (EMVS's semi-dense mask,
  ``FitResult.mask``) with valid ground truth up to ``max_eval_depth``;
  ``coverage`` is the fraction of valid ground-truth pixels that got a depth.
  Writes ``results/accuracy_tables{,_quick}.md|csv`` and
  ``results/accuracy_depth_<sequence>.png``; rows of
  ``results/accuracy_learned.csv`` (same columns, the learned models) are appended when present.
* ``cmax``: runs ``benchmarks/accuracy_cmax.py`` (``cmax.fit`` against its targets) and
  ``benchmarks/accuracy_presets.py`` (``cmax.fit`` on held-out windows of every scene preset).

Usage::

    python -m benchmarks.accuracy [--quick] [--section tables|cmax|all] [--cache DIR] [--sequences A,B]
"""
from __future__ import annotations

import argparse
import csv
import io
import os
import platform
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cmax.io.atomic import write_text_atomic
from cmax.metrics import DepthMetrics, MotionMetrics, depth_metrics, motion_metrics, window_twist

RESULTS = Path(__file__).resolve().parent / "results"
CSV_COLUMNS = ("method", "sequence", "abs_mean_m", "rmse_log", "abs_rel", "err_10m", "err_20m", "err_30m",
               "coverage", "n_pixels")
CUTOFFS = (10.0, 20.0, 30.0)
METHODS = ("EMVS (GT poses)", "EMVS (fit_sequence poses)", "cmax.fit")
#: Short names for the figure titles (tiles are narrow).
SHORT_NAMES = {"EMVS (GT poses)": "EMVS gt-pose", "EMVS (fit_sequence poses)": "EMVS fit-pose", "cmax.fit": "cmax.fit"}


@dataclass(frozen=True)
class SequenceSpec:
    """One held-out test sequence: a preset scene and its seed."""

    label: str
    preset: str
    seed: int


@dataclass(frozen=True)
class TableSettings:
    """What the ``tables`` section runs.

    Attributes
    ----------
    sequences : tuple of SequenceSpec
    width, height : int
        Sensor size [px] (the DAVIS346 intrinsics scaled to it).
    windows : int
        0.1665 s windows per sequence: ``fit_sequence`` walks them all, ``cmax.fit``
        scores each, EMVS integrates the events of all of them into one reference view.
    window_us : int
        Window length [µs] (the paper's 0.1665 s).
    start_s : float
        Scene time of the first window [s] (the simulation starts here).
    texture_size : int
        Texture side of the scenes (256 builds faster than 512).
    n_planes : int
        EMVS depth planes.
    far_limit_m : float
        Depth range of both methods and of the evaluation: the preset's stated
        range with its far end clipped to this.
    """

    sequences: tuple[SequenceSpec, ...]
    width: int = 346
    height: int = 260
    windows: int = 4
    window_us: int = 166_500
    start_s: float = 0.2
    texture_size: int = 512
    n_planes: int = 100
    far_limit_m: float = 80.0


SEQUENCES = (
    SequenceSpec("indoor_flying1", "indoor_flying", 101),
    SequenceSpec("indoor_flying2", "indoor_flying", 102),
    SequenceSpec("indoor_flying3", "indoor_flying", 103),
    SequenceSpec("driving_day", "driving_day", 101),
    SequenceSpec("driving_night", "driving_night", 101),
)
FULL = TableSettings(SEQUENCES)
QUICK = TableSettings((SEQUENCES[0], SEQUENCES[3], SEQUENCES[4]), width=200, height=150, windows=2,
                      texture_size=256, n_planes=64)


@dataclass(frozen=True, eq=False)
class MethodResult:
    """One method on one sequence: its metrics, its first depth map and the matching ground truth."""

    method: str
    sequence: str
    metrics: DepthMetrics
    depth: np.ndarray
    gt: np.ndarray
    seconds: float


@dataclass(frozen=True, eq=False)
class SequenceRun:
    """A simulated test sequence."""

    spec: SequenceSpec
    scene: object
    sequence: object
    depth_range: tuple[float, float]
    seconds: float


# -- sequences --------------------------------------------------------------------------------
def simulate_sequence(spec: SequenceSpec, settings: TableSettings, cache: Path | None = None) -> SequenceRun:
    """Render ``spec``'s scene and simulate ``settings.windows`` windows of events (plus 10 ms).

    With ``cache``, the simulated sequence is kept there as an HDF5 file (events and
    ground truth, :meth:`cmax.sim.SyntheticSequence.save`) and read back by later runs
    (``seconds`` is then NaN: nothing was simulated).
    """
    from cmax.sim import EventSimulator, load_sequence, make_scene, simulate_scene

    start = time.perf_counter()
    duration_s = settings.windows * settings.window_us * 1e-6 + 0.01
    scene = make_scene(spec.preset, seed=spec.seed, width=settings.width, height=settings.height,
                       duration_s=max(1.0, settings.start_s + duration_s), texture_size=settings.texture_size)
    near, far = scene.info.depth_range_m
    depth_range = (float(near), float(min(far, settings.far_limit_m)))
    name = (f"{spec.preset}_{spec.seed}_{settings.width}x{settings.height}_{settings.texture_size}_"
            f"{settings.start_s:g}_{duration_s:g}.h5")
    if cache is not None and (cache / name).exists():
        return SequenceRun(spec, scene, load_sequence(cache / name), depth_range, float("nan"))
    simulator = EventSimulator(**{**scene.recommended_simulator, "seed": spec.seed})
    sequence = simulate_scene(scene, duration_s, simulator, t0_s=settings.start_s, depth_times_s=np.array([]))
    seconds = time.perf_counter() - start
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        sequence.save(cache / name, overwrite=True)
    return SequenceRun(spec, scene, sequence, depth_range, seconds)


def gt_depth_at(scene, t_us: int) -> np.ndarray:
    """Ground-truth z-depth (H, W) float32 [m] of ``scene`` at ``t_us`` (scene time 0 = 0 µs)."""
    return scene.render(t_us * 1e-6)[1]


def window_bounds(run: SequenceRun, settings: TableSettings) -> list[tuple[int, int]]:
    """``[t0, t1)`` [µs] of the windows, from the first event on."""
    t_first = int(run.sequence.events.t[0])
    return [(t_first + k * settings.window_us, t_first + (k + 1) * settings.window_us)
            for k in range(settings.windows)]


def mean_speed(run: SequenceRun, t0_us: int, t1_us: int) -> float:
    """Mean ground-truth ``|v|`` [m/s] over ``[t0, t1]``."""
    times = run.sequence.poses_t_us
    inside = (times >= t0_us) & (times <= t1_us)
    return float(np.mean(np.linalg.norm(run.sequence.twists[inside, :3], axis=1)))


def no_pixels(cutoffs: tuple[float, ...] = CUTOFFS) -> DepthMetrics:
    """Metrics of a method that gave no depth on any pixel with valid ground truth: NaN, coverage 0."""
    nan = float("nan")
    return DepthMetrics(nan, nan, nan, nan, nan, nan, nan, nan, {c: nan for c in cutoffs}, n_pixels=0,
                        coverage=0.0, n_frames=0)


def score(method: str, run: SequenceRun, depths: list[np.ndarray], gts: list[np.ndarray],
          seconds: float, max_depth: float) -> MethodResult:
    """Pooled metrics of predicted depths (NaN = no prediction) against ground truth.

    A method with no depth on any pixel of valid ground truth gets NaN errors and coverage 0
    (a row that says so, rather than no row).
    """
    pred, gt = np.stack(depths), np.stack(gts)
    scored = np.isfinite(pred) & (pred > 0) & np.isfinite(gt) & (gt > 1e-3) & (gt <= max_depth)
    metrics = (depth_metrics(pred, gt, cutoffs=CUTOFFS, max_depth=max_depth) if scored.any()
               else no_pixels())
    return MethodResult(method, run.spec.label, metrics, depths[0], gts[0], seconds)


# -- methods ----------------------------------------------------------------------------------
def run_emvs(run: SequenceRun, settings: TableSettings, poses: object, method: str) -> MethodResult:
    """EMVS on the events of all windows with ``poses`` ((times, T_w_c) or a SequenceResult)."""
    from cmax.emvs import EMVS

    bounds = window_bounds(run, settings)
    events = run.sequence.events.slice_time(bounds[0][0], bounds[-1][1])
    start = time.perf_counter()
    result = EMVS(run.scene.camera, depth_range=run.depth_range, n_planes=settings.n_planes).run(events, poses)
    seconds = time.perf_counter() - start
    depth = np.where(result.mask, result.depth, np.nan).astype(np.float32)
    return score(method, run, [depth], [gt_depth_at(run.scene, result.t_ref_us)], seconds, run.depth_range[1])


def run_fit_sequence_poses(run: SequenceRun, settings: TableSettings):
    """:func:`cmax.fit_sequence` over the windows, the scale fixed by the mean ground-truth speed."""
    import cmax

    bounds = window_bounds(run, settings)
    # fit_sequence fits a window only when events reach its end: keep the 10 ms simulated after the last one.
    events = run.sequence.events.slice_time(bounds[0][0], bounds[-1][1] + 5_000)
    return cmax.fit_sequence(events, run.sequence.K, "se3", window_us=settings.window_us,
                             speed=mean_speed(run, bounds[0][0], bounds[-1][1]), depth_range=run.depth_range)


def run_fit_windows(run: SequenceRun, settings: TableSettings) -> tuple[MethodResult, list]:
    """:func:`cmax.fit` on every window with its mean ground-truth speed; pooled metrics and the fits."""
    import cmax

    depths, gts, fits = [], [], []
    start = time.perf_counter()
    for t0, t1 in window_bounds(run, settings):
        fitted = cmax.fit(run.sequence.events.slice_time(t0, t1), run.sequence.K, "se3",
                          speed=mean_speed(run, t0, t1), depth_range=run.depth_range)
        depths.append(np.where(fitted.mask, fitted.depth, np.nan).astype(np.float32))
        gts.append(gt_depth_at(run.scene, fitted.t_ref_us))
        fits.append(fitted)
    result = score("cmax.fit", run, depths, gts, (time.perf_counter() - start) / len(fits), run.depth_range[1])
    return result, fits


def fit_motion_errors(run: SequenceRun, fits: list) -> MotionMetrics:
    """Errors of the fitted twists against each window's true mean twist (:func:`cmax.metrics.window_twist`)."""
    truth = np.stack([window_twist(run.scene.pose(f.t0_us * 1e-6), run.scene.pose(f.t1_us * 1e-6),
                                   (f.t1_us - f.t0_us) * 1e-6) for f in fits])
    return motion_metrics(np.stack([f.v for f in fits]), np.stack([f.omega for f in fits]),
                          truth[:, :3], truth[:, 3:])


# -- output -----------------------------------------------------------------------------------
def csv_row(result: MethodResult) -> dict[str, object]:
    m = result.metrics
    return {"method": result.method, "sequence": result.sequence, "abs_mean_m": m.abs_mean,
            "rmse_log": m.rmse_log, "abs_rel": m.abs_rel, "err_10m": m.cutoff_errors[10.0],
            "err_20m": m.cutoff_errors[20.0], "err_30m": m.cutoff_errors[30.0],
            "coverage": m.coverage, "n_pixels": m.n_pixels}


def read_learned_rows(path: Path) -> list[dict[str, object]]:
    """Rows of ``accuracy_learned.csv`` (same columns); raises on a file with other columns."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != CSV_COLUMNS:
            raise ValueError(f"{path} must have the columns {','.join(CSV_COLUMNS)}, got {reader.fieldnames}")
        rows = list(reader)
    for row in rows:
        for key in CSV_COLUMNS[2:]:
            row[key] = float(row[key]) if key != "n_pixels" else int(float(row[key]))
    return rows




def to_csv(rows: list[dict[str, object]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buffer.getvalue()


def _fmt(value: object, digits: int = 3) -> str:
    if isinstance(value, float):
        return "n/a" if not np.isfinite(value) else f"{value:.{digits}f}"
    return str(value)


def markdown_tables(rows: list[dict[str, object]], sequences: list[str]) -> list[str]:
    """Table 2 (Abs mean and rms_log per sequence), Table 3 (cut-off errors) and all figures."""
    methods = list(dict.fromkeys(str(r["method"]) for r in rows))
    table = {(r["method"], r["sequence"]): r for r in rows}
    lines = ["## Table 2: Abs mean [m] / rms_log per sequence", "",
             "| method | " + " | ".join(f"{s} Abs mean | {s} rms_log" for s in sequences) + " |",
             "|---|" + "---:|---:|" * len(sequences)]
    for method in methods:
        cells = []
        for s in sequences:
            r = table.get((method, s))
            cells += [_fmt(r["abs_mean_m"]), _fmt(r["rmse_log"])] if r else ["", ""]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    lines += ["", "## Table 3: mean |error| [m] over pixels with ground truth within the cut-off", "",
              "| sequence | cut-off | " + " | ".join(methods) + " |", "|---|---|" + "---:|" * len(methods)]
    for s in sequences:
        for cutoff in ("10m", "20m", "30m"):
            cells = [_fmt(table[(m, s)][f"err_{cutoff}"]) if (m, s) in table else "" for m in methods]
            lines.append(f"| {s} | 0 - {cutoff[:-1]} m | " + " | ".join(cells) + " |")
    lines += ["", "## All figures (the CSV)", "", "| " + " | ".join(CSV_COLUMNS) + " |",
              "|---|---|" + "---:|" * (len(CSV_COLUMNS) - 2)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r[c]) for c in CSV_COLUMNS) + " |")
    return lines


#: Text size of the colour bars of the figures (the tiles' titles use 0.45).
BAR_FONT_SCALE = 0.4


def row_with_colour_bar(tiles: list[np.ndarray], scale, height: int) -> np.ndarray:
    """``tiles`` (titled pictures whose bottom ``height`` rows are the images) side by side, bottom-aligned so that
    the images stay level whatever their titles' heights, with the colour bar [m] of ``scale`` (a
    :class:`cmax.viz.DepthScale`, the scale of every depth tile of the row) at the right, level with the images."""
    from cmax import viz

    tiles = [*tiles, viz.depth_colour_bar(max(height, 40), scale, font_scale=BAR_FONT_SCALE)]
    top = max(tile.shape[0] for tile in tiles)
    return viz.hstack([np.vstack([np.full((top - t.shape[0], t.shape[1], 3), 255, np.uint8), t]) for t in tiles])


def captioned(image: np.ndarray, caption: str, width: int = 640) -> np.ndarray:
    """``image`` under ``caption``, wrapped to lines of at most ``width`` px: the text size of the tiles' titles
    whatever the figure's width (a caption titled across a wide figure grows large)."""
    from cmax import viz

    strip = viz.titled(np.full((1, min(width, image.shape[1]), 3), 255, np.uint8), caption)[:-1]
    return viz.vstack([strip, image], gap=0)


def depth_figure(run: SequenceRun, results: list[MethodResult], events) -> np.ndarray:
    """Events (ON/OFF legend), ground truth and each method's depth side by side on one colour scale, the
    1st-99th percentiles of the ground truth, drawn as a colour bar in metres; "no estimate" hatched grey (BGR uint8)."""
    from cmax import viz
    from cmax.representations import event_frame

    gt = results[-1].gt
    valid = np.isfinite(gt) & (gt > 0) & (gt <= run.depth_range[1])
    depth_range = (float(np.percentile(gt[valid], 1)), float(np.percentile(gt[valid], 99)))
    if not depth_range[0] < depth_range[1]:
        depth_range = (depth_range[0], depth_range[0] * 1.01)
    scale = viz.DepthScale(*depth_range)
    tiles = [viz.event_panel(event_frame(events), f"events ({len(events):,})"),
             viz.titled(viz.depth_image(np.where(valid, gt, np.nan), scale),
                        f"GT {depth_range[0]:.1f}-{depth_range[1]:.1f} m")]
    for r in results:
        tiles.append(viz.titled(viz.depth_image(r.depth, scale),
                                f"{SHORT_NAMES.get(r.method, r.method)} " + (
                                    f"{r.metrics.abs_mean:.2f} m" if r.metrics.n_pixels else "no depth")))
    caption = (f"{run.spec.label} (seed {run.spec.seed}): events of the first window, ground truth at cmax.fit's "
               "t_ref, each method's depth (one colour scale, bar in m; hatched: no estimate; title: Abs mean "
               "over all its windows)")
    return captioned(row_with_colour_bar(tiles, scale, gt.shape[0]), caption)


# -- the section -------------------------------------------------------------------------------
def evaluate_sequence(spec: SequenceSpec, settings: TableSettings, log,
                      cache: Path | None = None) -> tuple[list[MethodResult], np.ndarray, dict]:
    """Simulate one sequence and score every method; returns results, figure and details
    (timings [s], event count, motion errors of the fits)."""
    run = simulate_sequence(spec, settings, cache)
    log(f"  simulated {len(run.sequence.events):,} events in {run.seconds:.1f} s, "
        f"depth range {run.depth_range[0]:g}-{run.depth_range[1]:g} m")
    fit_result, fits = run_fit_windows(run, settings)
    log(f"  cmax.fit: {len(fits)} windows, {fit_result.seconds:.1f} s per window, "
        f"Abs mean {fit_result.metrics.abs_mean:.3f} m")
    start = time.perf_counter()
    fitted_sequence = run_fit_sequence_poses(run, settings)
    sequence_seconds = time.perf_counter() - start
    log(f"  fit_sequence: {len(fitted_sequence.results)} windows in {sequence_seconds:.1f} s")
    sequence = run.sequence
    emvs_gt = run_emvs(run, settings, (sequence.poses_t_us, sequence.poses), METHODS[0])
    log(f"  EMVS (GT poses): {emvs_gt.seconds:.1f} s, Abs mean {emvs_gt.metrics.abs_mean:.3f} m, "
        f"coverage {emvs_gt.metrics.coverage:.3f}")
    emvs_fit = run_emvs(run, settings, fitted_sequence, METHODS[1])
    emvs_fit = replace(emvs_fit, seconds=emvs_fit.seconds + sequence_seconds)
    log(f"  EMVS (fit_sequence poses): Abs mean {emvs_fit.metrics.abs_mean:.3f} m")
    results = [emvs_gt, emvs_fit, fit_result]
    t0, t1 = window_bounds(run, settings)[0]
    figure = depth_figure(run, results, sequence.events.slice_time(t0, t1))
    details = {"simulation_s": run.seconds, "fit_s_per_window": fit_result.seconds,
               "emvs_s": emvs_gt.seconds, "fit_sequence_s": sequence_seconds, "events": len(sequence.events),
               "motion": {"cmax.fit": fit_motion_errors(run, fits)}}
    if fitted_sequence.results:
        details["motion"]["fit_sequence"] = fit_motion_errors(run, list(fitted_sequence.results))
    return results, figure, details


def run_tables(settings: TableSettings, *, quick: bool, results_dir: Path = RESULTS,
               cache: Path | None = None) -> Path:
    """The ``tables`` section: evaluate, write markdown, CSV and figures; returns the markdown path."""
    import torch
    from tqdm import tqdm

    from cmax import viz

    torch.set_num_threads(1)  # fastest on a shared machine; cmax.fit's own default
    results_dir.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    rows, timings = [], {}
    bar = tqdm(settings.sequences, desc="sequences", unit="seq", file=sys.stderr)
    for spec in bar:
        bar.set_postfix_str(spec.label)
        tqdm.write(f"{spec.label}: {spec.preset} seed {spec.seed}", file=sys.stderr)
        results, figure, timings[spec.label] = evaluate_sequence(
            spec, settings, lambda text: tqdm.write(text, file=sys.stderr), cache)
        rows += [csv_row(r) for r in results]
        viz.save_image(results_dir / f"accuracy_depth_{spec.label}{'_quick' if quick else ''}.png", figure)
    learned = results_dir / "accuracy_learned.csv"
    learned_rows = read_learned_rows(learned) if learned.exists() else []
    suffix = "_quick" if quick else ""
    write_text_atomic(results_dir / f"accuracy_tables{suffix}.csv", to_csv(rows + learned_rows))
    text = report(rows + learned_rows, settings, timings, quick=quick, learned=bool(learned_rows),
                  seconds=time.perf_counter() - start, loads=(load_before, os.getloadavg()[0]))
    return write_text_atomic(results_dir / f"accuracy_tables{suffix}.md", text)


def report(rows, settings: TableSettings, timings: dict, *, quick: bool, learned: bool, seconds: float,
           loads: tuple[float, float]) -> str:
    """The markdown page of the tables section."""
    import torch

    sequences = [s.label for s in settings.sequences]
    lines = [f"# Depth accuracy on held-out synthetic sequences{' (quick run)' if quick else ''}", "",
             f"`python -m benchmarks.accuracy --section tables{' --quick' if quick else ''}` took {seconds:.0f} s "
             f"on {platform.machine()} with {os.cpu_count()} cores, torch {torch.__version__} (1 thread); "
             f"1-minute load average {loads[0]:.2f} before, {loads[1]:.2f} after (other processes share the machine).",
             "", "Settings: " + ", ".join(f"{s.label} = `{s.preset}` seed {s.seed}" for s in settings.sequences)
             + f"; {settings.width}x{settings.height} px, {settings.windows} windows of "
             f"{settings.window_us / 1e6:g} s (the paper's) from scene time {settings.start_s:g} s; ESIM with each "
             f"preset's recommended settings; textures {settings.texture_size}; EMVS {settings.n_planes} planes. "
             "Depth range of every method and of the evaluation: the preset's stated range, far end clipped to "
             f"{settings.far_limit_m:g} m.", "",
             "Methods: **EMVS (GT poses)** -- EMVS on the events of all windows with the scene's poses, one "
             "reference view in the middle; **EMVS (fit_sequence poses)** -- the same with the poses of "
             "`cmax.fit_sequence` (se3, scale fixed by the sequence's mean ground-truth speed); **cmax.fit** -- "
             "every window fitted alone with its mean ground-truth speed, scores pooled over the windows. "
             "Ground truth: the scene's depth rendered at each result's `t_ref_us`. Each method is scored on "
             "its own pixels (EMVS's semi-dense mask, `FitResult.mask`); coverage = scored pixels / pixels "
             "with valid ground truth. Abs mean = mean |pred - gt| [m]; rms_log = RMS of log(pred / gt)." +
             (" Rows of the learned models come from `accuracy_learned.csv`." if learned else
              " The learned models' rows appear when `results/accuracy_learned.csv` exists."), ""]
    lines += markdown_tables(rows, sequences)
    lines += ["", "## Motion of the fits", "", "Errors of the fitted twists against each window's true mean "
              "twist `se3_log(T_w_0^-1 T_w_1) / T` (the speed |v| was given, so the direction is what was "
              "estimated).", "", "| sequence | fits | windows | omega RMS [deg/s] | v RMS [m/s] | "
              "direction mean [deg] | direction median [deg] |", "|---|---|---:|---:|---:|---:|---:|"]
    for label, t in timings.items():
        for name, m in t["motion"].items():
            lines.append(f"| {label} | {name} | {m.n_windows} | {m.omega_rms_deg_s:.2f} | {m.v_rms_m_s:.3f} | "
                         f"{m.direction_error_deg:.1f} | {m.direction_error_deg_median:.1f} |")
    lines += ["", "## Timings", "", "| sequence | events | simulation [s] | cmax.fit [s/window] | "
              "fit_sequence [s] | EMVS [s] |", "|---|---:|---:|---:|---:|---:|"]
    for label, t in timings.items():
        simulation = "cached" if not np.isfinite(t["simulation_s"]) else f"{t['simulation_s']:.1f}"
        lines.append(f"| {label} | {t['events']:,} | {simulation} | {t['fit_s_per_window']:.1f} | "
                     f"{t['fit_sequence_s']:.1f} | {t['emvs_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="3 sequences, 200x150, 2 windows each (under 3 minutes); writes *_quick files")
    parser.add_argument("--section", choices=("tables", "cmax", "all"), default="all")
    parser.add_argument("--cache", type=Path, default=None,
                        help="folder keeping the simulated sequences (h5) between runs")
    parser.add_argument("--sequences", default=None,
                        help=f"comma-separated subset of {','.join(s.label for s in SEQUENCES)}")
    args = parser.parse_args(argv)
    settings = QUICK if args.quick else FULL
    if args.sequences is not None:
        chosen = args.sequences.split(",")
        unknown = sorted(set(chosen) - {s.label for s in SEQUENCES})
        if unknown or not chosen:
            parser.error(f"--sequences must name some of {[s.label for s in SEQUENCES]}, got unknown {unknown}")
        settings = replace(settings, sequences=tuple(s for s in SEQUENCES if s.label in chosen))
    if args.section in ("tables", "all"):
        path = run_tables(settings, quick=args.quick, cache=args.cache)
        print(path.read_text())
    if args.section in ("cmax", "all"):
        from benchmarks.accuracy_cmax import main as accuracy_cmax_main
        from benchmarks.accuracy_presets import main as accuracy_presets_main

        accuracy_cmax_main(["--quick"] if args.quick else [])
        accuracy_presets_main(["--quick"] if args.quick else [])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
