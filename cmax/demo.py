"""``cmax demo``: the end-to-end demo on data it makes itself.

Steps (each prints a line; the whole run takes well under 3 minutes on 2 cores):

1. render a synthetic ``indoor_flying`` scene (ground-truth depth and poses) and
   simulate its events with the ESIM model;
2. write the events with the ground truth to a DSEC-layout HDF5 file;
3. fit depth and motion of ``n_windows`` windows of 0.1665 s (the paper's window), their middles
   spread evenly over the simulated time, with :func:`cmax.fit`, the scale fixed by the known
   ground-truth speed, and score each fit's depth against the rendered ground truth;
4. **pick the window by a stated rule**: the one of median depth error (abs_rel) among the fitted
   windows, so that the picture shows a typical fit, neither a chosen success nor a failure; its
   rank and the range of all windows' errors are written on the picture and in the report;
5. run the EMVS baseline (:class:`cmax.emvs.EMVS`) on all events with the ground-truth poses, its
   reference view at the chosen window's, score both against the rendered ground-truth depth
   (:func:`cmax.metrics.depth_metrics`) and the fitted motion against the true motion
   (:func:`cmax.metrics.motion_metrics`), and write ``report.png``, ``report.md`` and ``summary.txt``.
"""
from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from cmax.io.atomic import write_text_atomic

__all__ = ["DemoSettings", "DemoReport", "run_demo", "demo_outputs", "DEMO_LOCK", "MAX_SCENE_S"]

#: The lock file :func:`run_demo` holds in its output folder while it runs.
DEMO_LOCK = ".demo.lock"
#: The longest scene :func:`cmax.sim.make_scene` builds [s]: ``start_s + duration_s`` of the demo must fit in it.
MAX_SCENE_S = 600.0


def _fit_depth_grid() -> tuple[int, int]:
    """``(rows, columns)`` of :func:`cmax.fit`'s default inverse-depth grid, which the demo fits on: the smallest
    sensor [px] the demo can fit is ``columns`` wide and ``rows`` high (:class:`cmax.warp.DepthGrid`)."""
    import inspect

    from cmax.fitting.api import fit

    rows, columns = inspect.signature(fit).parameters["depth_grid"].default
    return int(rows), int(columns)


@dataclass(frozen=True)
class DemoSettings:
    """What the demo simulates and fits.

    Attributes
    ----------
    scene_name : str
        A preset of :func:`cmax.sim.make_scene`.
    seed : int
    width, height : int
        Sensor size [px]: at least 32 x 24, the size of :func:`cmax.fit`'s default depth grid (24 x 32 nodes).
    duration_s : float
        Simulated time [s] (EMVS uses all of it).
    window_s : float
        Length of the windows fitted by :func:`cmax.fit` [s].
    n_windows : int
        Windows fitted; their middles are spread evenly over the simulated time (they overlap
        when ``n_windows * window_s > duration_s``). The picture shows the one of median depth
        error; an odd count makes that median one of the windows.
    start_s : float
        Scene time at which the simulation starts [s].
    n_planes : int
        EMVS depth planes.
    texture_size : int
        Texture side of the scene (256 builds fast).
    """

    scene_name: str = "indoor_flying"
    seed: int = 0
    width: int = 240
    height: int = 180
    duration_s: float = 0.5
    window_s: float = 0.1665
    n_windows: int = 5
    start_s: float = 0.2
    n_planes: int = 100
    texture_size: int = 256

    def __post_init__(self) -> None:
        rows, columns = _fit_depth_grid()     # the windows are fitted on it: a smaller sensor failed after simulating
        why = f" (cmax.fit's default depth grid of {rows}x{columns} nodes needs a sensor of {columns}x{rows} px)"
        for name, minimum, reason in (("width", columns, why), ("height", rows, why), ("texture_size", 16, ""),
                                      ("n_planes", 2, ""), ("n_windows", 1, "")):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
                raise ValueError(f"{name} must be an integer >= {minimum}{reason}, got {value!r}")
        if not 0 < self.window_s <= self.duration_s:
            raise ValueError(f"window_s must be in (0, duration_s={self.duration_s}], got {self.window_s}")
        if not self.start_s >= 0:
            raise ValueError(f"start_s must be >= 0 seconds, got {self.start_s}")
        if self.start_s + self.duration_s > MAX_SCENE_S:   # was refused after "[1/5] rendering", as start + duration
            raise ValueError(f"duration_s must be at most {MAX_SCENE_S - self.start_s:g} seconds (a scene lasts at most "
                             f"{MAX_SCENE_S:g} s and the demo simulates it from start_s={self.start_s:g} s), got "
                             f"{self.duration_s:g}")


@dataclass(frozen=True)
class DemoReport:
    """What the demo wrote and measured.

    Attributes
    ----------
    report_png, report_md, summary_txt, events_h5 : Path
    fit_depth, emvs_depth : dict
        :meth:`cmax.metrics.DepthMetrics.as_dict` of ``cmax.fit`` and EMVS against ground truth.
    motion : dict
        :meth:`cmax.metrics.MotionMetrics.as_dict` of the fitted twist against the window's true twist.
    windows : tuple of dict
        Every fitted window: ``t_ref_us``, ``abs_rel`` (depth), ``direction_error_deg``,
        ``omega_rms_deg_s``, in time order.
    chosen : int
        Index into ``windows`` of the window shown (median ``abs_rel``).
    n_events : int
    seconds : dict
        Wall time of each step [s] and ``total``.
    """

    report_png: Path
    report_md: Path
    summary_txt: Path
    events_h5: Path
    fit_depth: dict
    emvs_depth: dict
    motion: dict
    windows: tuple
    chosen: int
    n_events: int
    seconds: dict


def demo_outputs(output_dir: str | os.PathLike, scene_name: str = DemoSettings.scene_name) -> list[Path]:
    """The files :func:`run_demo` writes into ``output_dir`` (``<scene_name>.h5``, ``report.png``, ``report.md``,
    ``summary.txt``) that exist there already (any kind of file, a link too)."""
    output_dir = Path(output_dir)
    names = (f"{scene_name}.h5", "report.png", "report.md", "summary.txt")
    return [output_dir / name for name in names if os.path.lexists(output_dir / name)]


def run_demo(
    output_dir: str | os.PathLike = "demo_output", *, settings: DemoSettings | None = None,
    log: Callable[[str], None] = print, overwrite: bool = False, **overrides,
) -> DemoReport:
    """Run the demo, writing into ``output_dir``.

    Parameters
    ----------
    output_dir : path
        Created if needed; receives ``<scene>.h5``, ``report.png``, ``report.md``, ``summary.txt``.
    overwrite : bool
        Replace those files when ``output_dir`` holds any of them (an earlier demo's, or a user's own
        ``report.md``); without it such a folder is refused, before any work, with a FileExistsError naming
        them (``cmax demo --overwrite``). Other files in ``output_dir`` are never touched. The run holds
        ``output_dir`` (the lock :data:`DEMO_LOCK` in it): a second demo into it meanwhile is refused at once
        with :class:`cmax.io.atomic.OutputLockedError`. The four files are written into a private folder
        ``output_dir/.demo.<16 hex>.partial`` and moved in together at the end (``report.md`` last,
        :func:`cmax.io.run_folder.publish`): a demo that fails or is stopped leaves ``output_dir`` as it was,
        never its new scene file beside an earlier demo's report.
    settings : DemoSettings, optional
        Defaults: indoor_flying, 240x180, 0.5 s, a 0.1665 s window.
    log : callable
        Receives the progress lines (``print`` by default).
    **overrides
        Fields of :class:`DemoSettings` (e.g. ``seed=1, duration_s=0.3``).

    Returns
    -------
    DemoReport
    """
    settings = replace(settings or DemoSettings(), **overrides)
    from cmax._threads import torch_threads_scope
    from cmax.io.run_folder import discard_stages, locked_folder, named_in_out, new_stage, publish

    with locked_folder(Path(output_dir), DEMO_LOCK) as output_dir:   # a second demo into it meanwhile: refused
        discard_stages(output_dir, _STAGE_PREFIX)   # those of killed demos
        if (existing := demo_outputs(output_dir, settings.scene_name)) and not overwrite:
            raise FileExistsError(f"{output_dir} already holds {', '.join(path.name for path in existing)}: the "
                                  "demo would replace them; --overwrite replaces them, or give another -o")
        stage = new_stage(output_dir, _STAGE_PREFIX)
        try:
            try:
                with torch_threads_scope(threads=1):  # one thread: fastest on a busy 2-core machine
                    report = _run(output_dir, settings, log, stage)
            except OSError as error:   # a full disk: named as the file in output_dir, which is as it was
                raise named_in_out(error, stage, output_dir) from None
            publish(stage, output_dir, existing, last=("report.md",))
        finally:
            shutil.rmtree(stage, ignore_errors=True)
        return report


#: The prefix of a demo's private folder of files (``.demo.<16 hex>.partial``, :func:`cmax.io.run_folder.new_stage`).
_STAGE_PREFIX = "demo"


def _run(output_dir: Path, s: DemoSettings, log: Callable[[str], None], stage: Path) -> DemoReport:
    """The demo's work: its files written into ``stage``, named (in the log and the report) as they will be in
    ``output_dir`` once moved there."""
    from cmax.emvs import EMVS
    from cmax.io.info import file_info
    from cmax.metrics import depth_metrics, motion_metrics
    from cmax.sim import EventSimulator, make_scene, simulate_scene

    seconds: dict[str, float] = {}
    start = clock = time.perf_counter()

    def lap(name: str) -> float:
        nonlocal clock
        now = time.perf_counter()
        seconds[name], clock = now - clock, now
        return seconds[name]

    log(f"[1/5] rendering '{s.scene_name}' (seed {s.seed}, {s.width}x{s.height}) and simulating "
        f"{s.duration_s:g} s of events ...")
    scene = make_scene(s.scene_name, seed=s.seed, width=s.width, height=s.height,
                       duration_s=max(1.0, s.start_s + s.duration_s), texture_size=s.texture_size)
    simulator = EventSimulator(**{**scene.recommended_simulator, "seed": s.seed})
    middle_s = s.start_s + s.duration_s / 2
    sequence = simulate_scene(scene, s.duration_s, simulator, t0_s=s.start_s, depth_times_s=np.array([middle_s]))
    log(f"      {len(sequence.events):,} events in {lap('simulation'):.1f} s")

    staged = sequence.save(stage / f"{s.scene_name}.h5", overwrite=True)
    path = output_dir / staged.name
    info_lines = replace(file_info(staged), path=str(path)).lines()
    log(f"[2/5] wrote {path} ({lap('write'):.1f} s)")

    near, far = scene.info.depth_range_m
    fits = _fit_windows(scene, sequence, s, (near, far), log)
    lap("cmax.fit")
    chosen = _median_window([f["abs_rel"] for f in fits])
    fitted, true_twist = fits[chosen]["result"], fits[chosen]["true_twist"]
    log(f"[4/5] window {chosen + 1} of {len(fits)} has the median depth error; EMVS on all "
        f"{len(sequence.events):,} events with the ground-truth poses ...")
    emvs = EMVS(scene.camera, depth_range=(near, far), n_planes=s.n_planes).run(
        sequence.events, (sequence.poses_t_us, sequence.poses), t_ref_us=fitted.t_ref_us)
    log(f"      {lap('EMVS'):.1f} s, {int(emvs.mask.sum()):,} semi-dense pixels")

    log("[5/5] scoring against ground truth and drawing the report ...")
    frame, gt_depth = scene.render(fitted.t_ref_us * 1e-6)
    fit_depth = np.where(fitted.mask, fitted.depth, np.nan)
    emvs_depth = np.where(emvs.mask, emvs.depth, np.nan)
    fit_metrics = depth_metrics(fit_depth, gt_depth)
    emvs_metrics = depth_metrics(emvs_depth, gt_depth)
    speed = float(np.linalg.norm(true_twist[:3]))
    motion = motion_metrics(fitted.v, fitted.omega, true_twist[:3], true_twist[3:])
    window = fits[chosen]["events"]
    windows = tuple({k: f[k] for k in ("t_ref_us", "abs_rel", "direction_error_deg", "omega_rms_deg_s")}
                    for f in fits)
    pictures = {"frame": frame, "events": window, "gt": gt_depth, "fit": fit_depth, "emvs": emvs_depth,
                "iwe_before": fitted.iwe_before, "iwe_after": fitted.iwe_after}
    lines = _summary_lines(s, fit_metrics.as_dict(), emvs_metrics.as_dict(), motion.as_dict(), speed,
                           true_twist, windows, chosen)
    png = output_dir / _save_report_png(stage / "report.png", pictures, lines, windows, chosen).name
    lap("report")
    seconds["total"] = time.perf_counter() - start
    summary = output_dir / write_text_atomic(stage / "summary.txt", "\n".join(info_lines + [""] + lines + [
        "", "seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items())]) + "\n").name
    report_md = output_dir / write_text_atomic(stage / "report.md",
                                               _markdown(s, lines, seconds, len(sequence.events))).name
    log(f"done in {seconds['total']:.1f} s: {png}, {report_md}, {summary}")
    for line in lines:
        log("      " + line)
    return DemoReport(png, report_md, summary, path, fit_metrics.as_dict(), emvs_metrics.as_dict(),
                      motion.as_dict(), windows, chosen, len(sequence.events), seconds)


def window_middles_us(s: DemoSettings) -> np.ndarray:
    """Middles [µs] of the ``n_windows`` windows: spread evenly so that every window lies in the
    simulated time ``[start_s, start_s + duration_s]`` (one window: the middle of that time)."""
    half = s.window_s / 2
    first, last = s.start_s + half, s.start_s + s.duration_s - half
    if s.n_windows == 1:
        return np.array([round((first + last) * 5e5)], np.int64)
    return np.round(np.linspace(first, last, s.n_windows) * 1e6).astype(np.int64)


def _median_window(errors: list[float]) -> int:
    """Index of the window of median error (the lower of the two middle ones for an even count;
    NaN errors rank last)."""
    values = np.asarray(errors, np.float64)
    order = np.argsort(np.where(np.isfinite(values), values, np.inf), kind="stable")
    return int(order[(len(order) - 1) // 2])


def _fit_windows(scene, sequence, s: DemoSettings, depth_range: tuple[float, float],
                 log: Callable[[str], None]) -> list[dict]:
    """``cmax.fit`` (se3, known speed) of every window and its depth error against the rendered truth."""
    import cmax
    from cmax.metrics import depth_metrics, motion_metrics, window_twist

    fits = []
    half_us = round(s.window_s * 5e5)
    middles = window_middles_us(s)
    log(f"[3/5] cmax.fit on {len(middles)} windows of {s.window_s:g} s (known speed) ...")
    for k, middle_us in enumerate(middles):
        window = sequence.events.slice_time(int(middle_us) - half_us, int(middle_us) + half_us)
        t0_us, t1_us = int(window.t[0]), int(window.t[-1])
        true_twist = window_twist(scene.pose(t0_us * 1e-6), scene.pose(t1_us * 1e-6), (t1_us - t0_us) * 1e-6)
        speed = float(np.linalg.norm(true_twist[:3]))
        result = cmax.fit(window, sequence.K, "se3", speed=speed, depth_range=depth_range)
        _, gt_depth = scene.render(result.t_ref_us * 1e-6)
        depth = depth_metrics(np.where(result.mask, result.depth, np.nan), gt_depth)
        motion = motion_metrics(result.v, result.omega, true_twist[:3], true_twist[3:])
        fits.append({"result": result, "events": window, "true_twist": true_twist, "t_ref_us": int(result.t_ref_us),
                     "abs_rel": float(depth.abs_rel), "direction_error_deg": float(motion.direction_error_deg),
                     "omega_rms_deg_s": float(motion.omega_rms_deg_s)})
        log(f"      window {k + 1}: {len(window):,} events, t_ref {result.t_ref_us * 1e-6:.3f} s, "
            f"abs_rel {depth.abs_rel:.3f}, direction error {motion.direction_error_deg:.1f} deg")
    return fits


def _rule_lines(windows: tuple, chosen: int) -> list[str]:
    """Where the shown window stands among the fitted ones."""
    errors = [w["abs_rel"] for w in windows]
    directions = [w["direction_error_deg"] for w in windows]
    rank = 1 + sorted(range(len(errors)), key=lambda i: (not np.isfinite(errors[i]), errors[i])).index(chosen)
    return [f"shown: window {chosen + 1} of {len(windows)} fitted, by the rule 'median cmax.fit depth error' "
            f"(rank {rank} of {len(windows)})",
            f"all {len(windows)} windows: abs_rel {np.nanmin(errors):.3f}-{np.nanmax(errors):.3f}, "
            f"direction error {np.nanmin(directions):.1f}-{np.nanmax(directions):.1f} deg"]


def _summary_lines(s: DemoSettings, fit: dict, emvs: dict, motion: dict, speed: float,
                   true_twist: np.ndarray, windows: tuple, chosen: int) -> list[str]:
    """The numbers written on the picture and into the text files."""
    omega_dps = np.degrees(np.linalg.norm(true_twist[3:]))
    return [
        f"scene {s.scene_name} seed {s.seed}, {s.width}x{s.height}, window {s.window_s:g} s",
        *_rule_lines(windows, chosen),
        f"true |v| {speed:.3f} m/s (given), |omega| {omega_dps:.2f} deg/s",
        f"cmax.fit depth: abs_rel {fit['abs_rel']:.3f}, Abs mean {fit['abs_mean']:.3f} m, "
        f"coverage {fit['coverage']:.2f}",
        f"EMVS depth:     abs_rel {emvs['abs_rel']:.3f}, Abs mean {emvs['abs_mean']:.3f} m, "
        f"coverage {emvs['coverage']:.2f}",
        f"cmax.fit motion: omega RMS error {motion['omega_rms_deg_s']:.2f} deg/s, "
        f"direction error {motion['direction_error_deg']:.1f} deg",
    ]


def _save_report_png(path: Path, p: dict, lines: list[str], windows: tuple, chosen: int) -> Path:
    """Frame, events, IWEs; ground truth, cmax.fit and EMVS depth on one colour scale with colour
    bars; the numbers below."""
    import cv2

    from cmax import viz
    from cmax.representations import event_frame

    gt = p["gt"]
    valid = np.isfinite(gt) & (gt > 0)
    scale = viz.DepthScale.from_depths(gt[valid])  # one scale, the truth's 1-99%, for all three maps

    def grey(image: np.ndarray) -> np.ndarray:
        return np.repeat(np.clip(image, 0, 255).astype(np.uint8)[..., None], 3, axis=2)

    ink = viz.robust_max(p["iwe_after"])  # one scale for both IWEs: the sharper one sets it
    t_ref = windows[chosen]["t_ref_us"] * 1e-6
    top = viz.hstack([
        viz.titled(grey(p["frame"]), f"rendered frame, t {t_ref:.3f} s"),
        viz.event_panel(event_frame(p["events"]), f"events ({len(p['events']):,})"),
        viz.titled(viz.iwe_image(p["iwe_before"], scale=ink), "IWE before"),
        viz.titled(viz.iwe_image(p["iwe_after"], scale=ink), "IWE after (cmax.fit)"),
    ])
    bottom = viz.hstack([
        viz.depth_panel(np.where(valid, gt, np.nan), scale, "ground-truth depth"),
        viz.depth_panel(p["fit"], scale, f"cmax.fit depth (window {chosen + 1}/{len(windows)})"),
        viz.depth_panel(p["emvs"], scale, "EMVS depth (true poses)"),
    ])
    text = np.full((18 * len(lines) + 8, max(top.shape[1], bottom.shape[1]), 3), 255, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(text, line, (6, 18 * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return viz.save_png(path, viz.vstack([top, bottom, text]))


def _markdown(s: DemoSettings, lines: list[str], seconds: dict, n_events: int) -> str:
    return "\n".join(
        ["# cmax demo", "", "![report](report.png)", "", f"{n_events:,} events simulated.", ""]
        + [f"- {line}" for line in lines]
        + ["", "| step | seconds |", "|---|---:|"] + [f"| {k} | {v:.1f} |" for k, v in seconds.items()]
        + ["", f"Settings: `{s}`", ""])


