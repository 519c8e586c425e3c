"""EMVS speed: events/s at 240x180 with 100 planes, against a plain numpy port timed in the same run.

Events come from the synthetic ``slider`` scene (:func:`cmax.sim.make_scene`,
:func:`cmax.sim.simulate_scene`, 240x180, its recommended simulator) with its
ground-truth poses. Methods, timed round-robin (:func:`benchmarks.speed.run_group`):

* **numpy port (baseline)**: a plain port of EMVS to numpy: packets of 1024
  events sharing one pose, the plane-induced homography to the first plane,
  the affine transfer to every plane, and bilinear votes by ``np.add.at``
  (a loop over packets and planes, vectorized over the events of a packet);
* **ours, voting="splat"**: :class:`cmax.emvs.EMVS` with the exact bilinear votes (one compiled loop);
* **ours, voting="gather"** (the default): one splat per packet group on
  sub-pixel-shifted grids, one integer-shifted add per plane.

Then the default against its own method's floor (:func:`method_floor`), on
this sequence and on a longer one (3 s, about 1 M events): the image
additions of its run replayed with ``cv2.add``, and the same additions done
by the method's compiled loop, each plus one splat of every event.

All methods include the depth extraction (argmax, adaptive threshold, median
filter). The checks compare each depth map with the ground-truth depth at the
reference time and give the first call's time in a fresh process (numba
compiling, or loading its cache).

Usage::

    python -m benchmarks.speed_emvs [--duration 0.5] [--floor-duration 3.0] [--repeats 3] [--clock cpu]
    python -m benchmarks.speed --section emvs
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from cmax.emvs import EMVS
from cmax.emvs.result import DSI, semi_dense_depth
from cmax.geometry import interpolate_poses, invert_pose

SIZE = (240, 180)
PLANES = 100


def numpy_port_dsi(events, camera, times_us, poses, depth_range, n_planes, packet=1024) -> DSI:
    """The baseline: EMVS written plainly in numpy (np.add.at votes, loops over packets and planes)."""
    start = time.perf_counter()
    K, width, height = camera.K, camera.width, camera.height
    depths = 1.0 / np.linspace(1.0 / depth_range[0], 1.0 / depth_range[1], n_planes)
    t = events.t
    t_ref = (int(t[0]) + int(t[-1])) // 2
    T_w_ref = interpolate_poses(times_us, poses, [t_ref])[0]
    xy = camera.undistort(events).astype(np.float64)
    dsi = np.zeros(n_planes * height * width, np.float32)
    K_inv = np.linalg.inv(K)
    z0 = depths[0]
    for s in range(0, len(t), packet):
        e = min(s + packet, len(t))
        T = invert_pose(T_w_ref) @ interpolate_poses(times_us, poses, [(t[s] + t[e - 1]) // 2])[0]
        R, C = T[:3, :3], T[:3, 3]
        rays = np.column_stack([xy[s:e], np.ones(e - s)]) @ K_inv.T @ R.T
        ok = rays[:, 2] > 0
        P0 = C + ((z0 - C[2]) / rays[ok, 2])[:, None] * rays[ok]
        x0 = P0 @ K.T / z0
        for i, z in enumerate(depths):
            if z <= C[2]:
                continue
            lam = (z - C[2]) / (z0 - C[2])
            a = lam * z0 / z
            b = (1 - a) * K[:2, 2] + K[:2, :2] @ (C[:2] * (1 - lam) / z)
            x = a * x0[:, 0] + b[0]
            y = a * x0[:, 1] + b[1]
            xf, yf = np.floor(x), np.floor(y)
            fx, fy = x - xf, y - yf
            for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
                cx, cy = xf.astype(np.int64) + dx, yf.astype(np.int64) + dy
                w = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
                inside = (cx >= 0) & (cx < width) & (cy >= 0) & (cy < height)
                np.add.at(dsi, (i * height + cy[inside]) * width + cx[inside], w[inside].astype(np.float32))
    votes = dsi.reshape(n_planes, height, width)
    return DSI(votes, depths, K.copy(), t_ref, T_w_ref, len(t), time.perf_counter() - start)


def slider_sequence(duration_s: float, seed: int = 0):
    """Events, camera, poses and the depth at the middle of the slider scene at 240x180."""
    from cmax import Camera
    from cmax.sim import EventSimulator, make_scene, simulate_scene

    scene = make_scene("slider", seed=seed, width=SIZE[0], height=SIZE[1], duration_s=duration_s + 0.5,
                       texture_size=256)
    simulator = EventSimulator(**scene.recommended_simulator, seed=seed)
    sequence = simulate_scene(scene, duration_s, simulator, t0_s=0.2, pose_rate_hz=200.0)
    events = sequence.events
    t_ref = (int(events.t[0]) + int(events.t[-1])) // 2
    _, depth = scene.render(t_ref * 1e-6)
    camera = Camera(sequence.K, SIZE[0], SIZE[1])
    return events, camera, (sequence.poses_t_us, sequence.poses), depth


def method_floor(gather: EMVS, events, poses):
    """The gather method's floor: its per-plane image additions and one bilinear splat of every event.

    Runs ``gather`` once recording every image addition it makes
    (:func:`cmax.emvs.gather.add_shifted`: plane, image shape, integer offset);
    returns two functions that redo exactly those additions into a fresh DSI
    and splat all the events once (:func:`cmax.emvs.dsi.bilinear_splat` on a
    reference-sized image): work any implementation of this method does.

    * ``floor`` adds each image with ``cv2.add`` into its plane region, one
      call per addition (the floor's definition since it was introduced);
    * ``compiled`` hands the same additions to the compiled, row-banded loop
      that the method itself uses (:func:`cmax.emvs.gather.add_shifted`).

    The undistortion, poses, sub-pixel images and depth extraction are what the
    method adds on top. Returns ``(floor, compiled, number of additions)``.
    """
    import cv2

    from cmax.emvs import dsi as dsi_module
    from cmax.emvs import gather as gather_module

    calls = []
    original = gather_module.add_shifted

    def record(dsi, pool, layer_start, layer_shape, plane, layer, offset):
        calls.append((np.asarray(layer_shape)[layer].copy(), np.asarray(plane).copy(),
                      np.asarray(offset).copy()))
        original(dsi, pool, layer_start, layer_shape, plane, layer, offset)

    gather_module.add_shifted = record
    try:
        gather.run(events, poses)
    finally:
        gather_module.add_shifted = original
    shapes = np.concatenate([shape for shape, _, _ in calls])
    planes = np.concatenate([plane for _, plane, _ in calls])
    offsets = np.concatenate([offset for _, _, offset in calls])
    height, width = gather.camera.height, gather.camera.width
    distinct, layer = np.unique(shapes, axis=0, return_inverse=True)
    layer = layer.ravel()
    images = [np.ones(tuple(shape), np.float32) for shape in distinct]
    pool = np.concatenate([image.ravel() for image in images])
    starts = np.concatenate([[0], np.cumsum([image.size for image in images])[:-1]])
    x = events.x.astype(np.float64)[None] + 0.25
    y = events.y.astype(np.float64)[None] + 0.25
    n_planes = gather.n_planes

    def add_at_offset(target, image, qx, qy):
        image_h, image_w = image.shape
        lo_x, lo_y = max(0, -qx), max(0, -qy)
        hi_x, hi_y = min(width, image_w - qx), min(height, image_h - qy)
        if hi_x > lo_x and hi_y > lo_y:
            region = target[lo_y:hi_y, lo_x:hi_x]
            cv2.add(region, image[lo_y + qy: hi_y + qy, lo_x + qx: hi_x + qx], dst=region)

    def floor():
        target = np.zeros((n_planes, height, width), np.float32)
        for plane, k, (qx, qy) in zip(planes.tolist(), layer.tolist(), offsets.tolist()):
            add_at_offset(target[plane], images[k], qx, qy)
        dsi_module.bilinear_splat(x, y, None, width, height)
        return target

    def compiled():
        target = np.zeros((n_planes, height, width), np.float32)
        original(target, pool, starts, distinct, planes, layer, offsets)
        dsi_module.bilinear_splat(x, y, None, width, height)
        return target

    return floor, compiled, len(planes)


def first_call_seconds(duration_s: float = 0.05) -> dict:
    """Seconds of the first ``EMVS.run`` in a fresh process: numba compiling (empty cache), then loading its cache.

    Two child processes share a fresh ``NUMBA_CACHE_DIR``; each times its first
    and second call on a short slider sequence. The simulation is not timed.
    """
    from benchmarks.speed import first_calls_seconds

    setup = ("from benchmarks.speed_emvs import slider_sequence; from cmax.emvs import EMVS\n"
             f"events, camera, poses, _ = slider_sequence({duration_s})\n"
             "emvs = EMVS(camera, depth_range=(0.4, 3.0), n_planes=100)")
    return first_calls_seconds(setup, "emvs.run(events, poses)")


def _accuracy(result, depth_gt) -> str:
    mask = result.mask & np.isfinite(depth_gt)
    rel = np.abs(result.depth[mask] - depth_gt[mask]) / depth_gt[mask]
    return (f"mask {result.mask.mean():.1%}, median |rel err| {np.median(rel):.3f}, "
            f"{np.mean(rel < 0.1):.0%} within 10%")


def _floor_group(report, label: str, events, camera, poses, depth_range, repeats: int) -> None:
    """Time the default EMVS against its floor (both definitions, :func:`method_floor`) on one sequence."""
    from benchmarks.speed import run_group

    gather = EMVS(camera, depth_range=depth_range, n_planes=PLANES)
    floor, compiled, additions = method_floor(gather, events, poses)
    group = f"EMVS against its method's floor, {label}"
    run_group(report, group, [
        ("floor: the plane additions + one splat of every event", floor,
         f"{additions} image additions (cv2.add at integer offsets, one call each), replayed"),
        ("the same additions, compiled and row-banded, + one splat", compiled,
         "cmax.emvs.gather.add_shifted alone on the recorded additions"),
        ('ours, voting="gather" (default)', lambda: gather.run(events, poses), "the whole run"),
    ], len(events), repeats)
    rows = {row.method: row.median_s for row in report.rows if row.group == group}
    ours = rows['ours, voting="gather" (default)']
    report.summary.append(
        f"- {label}: ours {ours * 1e3:.1f} ms = **{ours / rows[next(iter(rows))]:.2f}x the floor** "
        f"({rows[next(iter(rows))] * 1e3:.1f} ms; target <= 1.5x), "
        f"{ours / rows['the same additions, compiled and row-banded, + one splat']:.2f}x the same additions "
        "compiled and row-banded")


def emvs_report(args: argparse.Namespace):
    """The ``emvs`` section of :mod:`benchmarks.speed`."""
    import cv2

    from benchmarks.speed import CLOCK, Report, run_group

    duration = getattr(args, "emvs_duration", 0.5)
    floor_duration = getattr(args, "emvs_floor_duration", 3.0)
    repeats = max(int(args.repeats), 3)
    cv2.setNumThreads(1)
    events, camera, poses, depth_gt = slider_sequence(duration)
    depth_range = (0.4, 3.0)
    n = len(events)
    long = slider_sequence(floor_duration) if floor_duration > 0 else None
    report = Report("emvs", "EMVS speed (240x180, 100 planes, slider scene)",
                    {"repeats": repeats, "events": n, "sensor": f"{SIZE[0]}x{SIZE[1]}", "planes": PLANES,
                     "depth_range_m": depth_range, "scene": f"slider seed 0, {duration} s, ground-truth poses",
                     "floor_scene": f"slider seed 0, {floor_duration} s ({len(long[0]) if long else 0} events)",
                     "opencv_threads": cv2.getNumThreads()})
    gather = EMVS(camera, depth_range=depth_range, n_planes=PLANES)
    splat = EMVS(camera, depth_range=depth_range, n_planes=PLANES, voting="splat")
    port = lambda: semi_dense_depth(numpy_port_dsi(events, camera, *poses, depth_range, PLANES))  # noqa: E731
    load_start = os.getloadavg()[0]
    if not getattr(args, "emvs_skip_port", False):
        run_group(report, "EMVS run", [
            ("numpy port (np.add.at, baseline)", port, "packets of 1024 events, one pose each"),
            ('ours, voting="splat" (exact)', lambda: splat.run(events, poses),
             "compiled bilinear splat, per-packet-group transfer"),
            ('ours, voting="gather" (default)', lambda: gather.run(events, poses),
             "one splat per group on 1/4-px-shifted grids, integer-shifted adds per plane"),
        ], n, repeats)
    _floor_group(report, f"{n} events", events, camera, poses, depth_range, repeats)
    if long is not None:
        _floor_group(report, f"{len(long[0])} events", long[0], long[1], long[2], depth_range, repeats)
    results = {"splat": splat.run(events, poses), "gather": gather.run(events, poses)}
    if not getattr(args, "emvs_skip_port", False):
        results["numpy port"] = port()
    for name, result in results.items():
        report.checks[f"{name}: depth vs ground truth"] = _accuracy(result, depth_gt)
    agree = results["gather"].mask & results["splat"].mask
    report.checks["gather vs splat: median |depth difference| on both masks [m]"] = float(
        np.median(np.abs(results["gather"].depth[agree] - results["splat"].depth[agree])))
    load_end = os.getloadavg()[0]
    first = first_call_seconds()
    for label, (first_s, second_s) in first.items():
        report.checks[f"first EMVS.run in a fresh process, {label} [s]"] = (
            f"{first_s:.2f} (second call {second_s * 1e3:.1f} ms)")
    report.notes += [
        f"Load average (1 min): {load_start:.2f} at the start, {load_end:.2f} at the end "
        "(2 cores shared by several people: absolute rates vary, ratios hold).",
        f"Clock: {CLOCK[0]} seconds; one OpenCV thread; the numba kernels run on one thread.",
        "Events per second = events / median time of EMVS.run (undistortion, pose interpolation, "
        "voting, depth extraction); the simulation of the events is not timed. Every method is called once "
        "before the timed calls, so numba compiling (or loading its cache) is not timed: the first-call "
        "checks give that cost.",
        "The floor is the method's own work: every image addition of its run, replayed (cv2.add per "
        "addition, as defined when the floor was introduced), plus one bilinear splat of every event. "
        "The second floor row does the same additions with the method's compiled, row-banded loop, which "
        "keeps a band of every plane in the cache while all groups' images are added to it: cheaper than "
        "one cv2.add per addition, so the method can come under the first floor; the ratio to the "
        "second row says what the rest of the method (projection, sub-pixel images, argmax, mask, "
        "median filter) costs.",
        "The gather path is exact bilinear voting with plane offsets rounded to 1/4 px when the camera moves "
        "parallel to the image plane (the slider); with motion along the optical axis the scaled planes are "
        "resampled with cv2.warpAffine instead and the rate drops (see the README).",
    ]
    return report


def main(argv: list[str] | None = None) -> int:
    from benchmarks.speed import CLOCKS, publish_report, timed_machine

    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed_emvs", description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=0.5, help="seconds of slider scene (default 0.5)")
    parser.add_argument("--floor-duration", type=float, default=3.0,
                        help="seconds of slider scene of the second floor group (default 3.0, about 1 M events; "
                             "0 skips it)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                        help="wall seconds, or CPU seconds of this process (steadier on a busy machine)")
    parser.add_argument("--skip-port", action="store_true",
                        help="skip the numpy port and splat rows (minutes), time only the floor groups")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    args.emvs_duration = args.duration
    args.emvs_floor_duration = args.floor_duration
    args.emvs_skip_port = args.skip_port
    machine = timed_machine(args.clock)   # first: the groups of the report are timed on its clock
    publish_report(emvs_report(args), machine, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
