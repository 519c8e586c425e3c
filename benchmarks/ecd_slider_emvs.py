"""EMVS on real frames with real poses: the Event Camera Dataset's ``slider_depth``.

The 87 real APS frames of ``../shared/data/ecd_slider_depth`` (DAVIS240C,
240x180, 0-3.33 s) are turned into events by adaptive sampling
(:func:`cmax.sim.sampling.iter_upsample`, flow or linear interpolation) and
ESIM (:class:`cmax.sim.esim.EventSimulator`); the events (distorted pixels)
are undistorted with ``calib.txt`` and voted by :class:`cmax.emvs.EMVS` with the
ground-truth poses of ``groundtruth.txt`` over 0.47-2.4 m (the range the EMVS
authors use for this scene). Writes ``docs/ecd_slider_emvs.png`` (a frame, the
events around the reference time, the confidence map and the semi-dense
depth with a scale bar in metres) and prints the median depth of the main
structures (modes of the depth histogram).

Usage::

    python -m benchmarks.ecd_slider_emvs [--method flow|linear] [--output docs/ecd_slider_emvs.png]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from cmax import Camera, concatenate
from cmax.emvs import EMVS, SemiDenseDepth, read_tum_trajectory

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "ecd_slider_depth"
DEPTH_RANGE = (0.47, 2.4)


@dataclass(frozen=True, eq=False)
class Structure:
    """One mode of the semi-dense depth histogram."""

    median_depth_m: float
    fraction: float
    pixels: int
    centroid_xy: tuple[float, float]
    columns: tuple[int, int]


@dataclass(frozen=True, eq=False)
class SliderReport:
    result: SemiDenseDepth
    events: int
    frames_in: int
    frames_sampled: int
    simulate_s: float
    structures: tuple[Structure, ...]

    @property
    def depths(self) -> np.ndarray:
        return self.result.depth

    @property
    def mask(self) -> np.ndarray:
        return self.result.mask

    @property
    def mask_fraction(self) -> float:
        return float(self.result.mask.mean())


def load_frames(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """Grey frames (T, H, W) uint8 and their times (T,) int64 µs from ``images.txt``."""
    times, frames = [], []
    for line in (folder / "images.txt").read_text().split("\n"):
        if line.strip():
            t, name = line.split()
            times.append(int(round(float(t) * 1e6)))
            image = cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise FileNotFoundError(f"cannot read {folder / name}")
            frames.append(image)
    return np.stack(frames), np.asarray(times, np.int64)


def simulate(frames: np.ndarray, times_us: np.ndarray, *, threshold: float = 0.2, method: str = "flow",
             lam: float = 0.5):
    """Events of the frames: adaptive sampling (eq. 1) then ESIM; also the number of sampled frames."""
    from cmax.sim.esim import EventSimulator
    from cmax.sim.sampling import iter_upsample

    simulator = EventSimulator(cp=threshold, cn=threshold)
    chunks, sampled = [], 0
    stream = iter_upsample(zip(frames, times_us.tolist()), threshold, lam=lam, method=method)
    for frame, t_us in tqdm(stream, desc=f"simulating ({method})", unit="frame", leave=False):
        chunks.append(simulator.step(frame, t_us))
        sampled += 1
    return concatenate(chunks[1:]), sampled


def depth_structures(result: SemiDenseDepth, *, min_fraction: float = 0.05) -> tuple[Structure, ...]:
    """Modes of the masked depths: peaks of the smoothed histogram of inverse depth, nearest first.

    Each masked pixel joins the nearest peak (in inverse depth); peaks holding
    less than ``min_fraction`` of the pixels are left out.
    """
    depths = result.depth[result.mask]
    if depths.size == 0:
        return ()
    inverse = 1.0 / depths
    near, far = result.depth_range
    edges = np.linspace(1.0 / far, 1.0 / near, 61)
    histogram, _ = np.histogram(inverse, edges)
    smooth = np.convolve(histogram, np.array([1, 2, 3, 2, 1]) / 9.0, mode="same")
    centres = (edges[:-1] + edges[1:]) / 2
    peaks = [i for i in range(len(smooth)) if smooth[i] > 0
             and smooth[i] >= smooth[max(i - 1, 0)] and smooth[i] > smooth[min(i + 1, len(smooth) - 1)]]
    if not peaks:
        peaks = [int(np.argmax(smooth))]
    label = np.argmin(np.abs(inverse[:, None] - centres[peaks][None]), axis=1)
    rows, cols = np.nonzero(result.mask)
    structures = []
    for k in range(len(peaks)):
        members = label == k
        if members.mean() < min_fraction:
            continue
        structures.append(Structure(
            float(np.median(depths[members])), float(members.mean()), int(members.sum()),
            (float(cols[members].mean()), float(rows[members].mean())),
            (int(np.percentile(cols[members], 5)), int(np.percentile(cols[members], 95))),
        ))
    return tuple(sorted(structures, key=lambda s: s.median_depth_m))


def figure(frame: np.ndarray, events, result: SemiDenseDepth, camera: Camera) -> np.ndarray:
    """Frame (undistorted), events of +-10 ms around the reference time, confidence, depth + scale bar."""
    from cmax import viz
    from cmax.representations import event_frame

    undistorted = cv2.undistort(frame, camera.K, camera.distortion) if camera.is_distorted else frame
    window = events.slice_time(result.t_ref_us - 10_000, result.t_ref_us + 10_000)
    confidence = result.confidence
    top = float(np.percentile(confidence[confidence > 0], 99))
    grey = (255 * (1 - np.clip(confidence / top, 0, 1))).astype(np.uint8)
    depth = np.where(result.mask, result.depth, np.nan)  # no estimate: the grey hatch, never a depth colour
    tiles = [
        viz.titled(cv2.cvtColor(undistorted, cv2.COLOR_GRAY2BGR), "frame (undistorted)"),
        viz.event_panel(np.asarray(event_frame(window)), "events, t_ref +-10 ms"),
        viz.titled(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), "confidence (DSI max)"),
        viz.depth_panel(depth, result.depth_range, f"EMVS depth, {result.mask.mean():.0%} px"),
    ]
    return viz.hstack(tiles)


def run_slider(folder: Path = DATA, output: Path | None = ROOT / "docs" / "ecd_slider_emvs.png", *,
               method: str = "flow", threshold: float = 0.2, n_planes: int = 100) -> SliderReport:
    """Simulate, run EMVS with the ground-truth poses, write the figure; returns the report."""
    from cmax import viz

    frames, frame_times = load_frames(folder)
    start = time.perf_counter()
    events, sampled = simulate(frames, frame_times, threshold=threshold, method=method)
    simulate_s = time.perf_counter() - start
    camera = Camera.from_ecd_calib(folder / "calib.txt", frames.shape[2], frames.shape[1])
    times, poses = read_tum_trajectory(folder / "groundtruth.txt")
    events = events.slice_time(int(times[0]), int(times[-1]) + 1)  # the poses' span
    result = EMVS(camera, depth_range=DEPTH_RANGE, n_planes=n_planes).run(events, (times, poses))
    if output is not None:
        nearest = int(np.argmin(np.abs(frame_times - result.t_ref_us)))
        viz.save_png(output, figure(frames[nearest], events, result, camera))
    return SliderReport(result, len(events), len(frames), sampled, simulate_s, depth_structures(result))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.ecd_slider_emvs", description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "ecd_slider_emvs.png")
    parser.add_argument("--method", choices=("flow", "linear"), default="flow")
    parser.add_argument("--threshold", type=float, default=0.2)
    parser.add_argument("--planes", type=int, default=100)
    args = parser.parse_args(argv)
    report = run_slider(args.data, args.output, method=args.method, threshold=args.threshold,
                        n_planes=args.planes)
    r = report.result
    print(f"{report.frames_in} frames -> {report.frames_sampled} samples -> {report.events:,} events "
          f"({report.simulate_s:.1f} s); EMVS {r.n_planes} planes {r.depth_range[0]}-{r.depth_range[1]} m: "
          f"{r.seconds:.2f} s ({report.events / r.seconds / 1e6:.2f} Mev/s), t_ref {r.t_ref_us / 1e6:.3f} s, "
          f"mask {r.mask.mean():.1%} ({int(r.mask.sum())} px), median depth {np.median(r.depth[r.mask]):.3f} m")
    print("main structures (modes of the depth histogram, nearest first):")
    for s in report.structures:
        print(f"  median {s.median_depth_m:.2f} m: {s.fraction:.0%} of the mask, centroid x={s.centroid_xy[0]:.0f} "
              f"y={s.centroid_xy[1]:.0f} px, columns {s.columns[0]}-{s.columns[1]}")
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
