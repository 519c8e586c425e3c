"""EMVS speed: events/s at 240x180 with 100 planes, against a plain numpy port timed in the same run.

Events come from the synthetic ``slider`` scene (:func:`cmax.sim.make_scene`,
:func:`cmax.sim.simulate_scene`, 240x180, its recommended simulator) with its
ground-truth poses. Methods, timed round-robin (:func:`benchmarks.speed.run_group`):

* **numpy port (baseline)**: a plain port of EMVS to numpy: packets of 1024
  events sharing one pose, the plane-induced homography to the first plane,
  the affine transfer to every plane, and bilinear votes by ``np.add.at``
  (a loop over packets and planes, vectorized over the events of a packet);
* **ours, voting="splat"**: :class:`cmax.emvs.EMVS` with the exact bilinear votes (``np.bincount``);
* **ours, voting="gather"** (the default): one splat per packet group on
  sub-pixel-shifted grids, one integer-shifted add per plane.

All methods include the depth extraction (argmax, adaptive threshold, median
filter). The checks compare each depth map with the ground-truth depth at the
reference time.

Usage::

    python -m benchmarks.speed_emvs [--duration 0.5] [--repeats 3]
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

    Runs ``gather`` once recording each ``_add_at_offset`` call (plane, offset,
    image shape) of :mod:`cmax.emvs.dsi`; returns a function that replays
    exactly those additions (``cv2.add`` of a float32 image into the plane
    region, as the method does) into a fresh DSI and splats all the events
    once (:func:`cmax.emvs.dsi.bilinear_splat` on a reference-sized image):
    work any implementation of this method does. The undistortion, poses,
    sub-pixel images and depth extraction are what the method adds on top.
    """
    import cv2

    from cmax.emvs import dsi as dsi_module

    calls = []
    original = dsi_module._add_at_offset

    def record(target, image, qx, qy):
        calls.append((image.shape, qx, qy))
        original(target, image, qx, qy)

    dsi_module._add_at_offset = record
    try:
        gather.run(events, poses)
    finally:
        dsi_module._add_at_offset = original
    height, width = gather.camera.height, gather.camera.width
    images = {shape: np.ones(shape, np.float32) for shape, _, _ in calls}
    x = events.x.astype(np.float64)[None] + 0.25
    y = events.y.astype(np.float64)[None] + 0.25
    planes = gather.n_planes

    def floor():
        target = np.zeros((planes, height, width), np.float32)
        for k, (shape, qx, qy) in enumerate(calls):
            original(target[k % planes], images[shape], qx, qy)
        dsi_module.bilinear_splat(x, y, None, width, height)
        return target

    return floor, len(calls)


def _accuracy(result, depth_gt) -> str:
    mask = result.mask & np.isfinite(depth_gt)
    rel = np.abs(result.depth[mask] - depth_gt[mask]) / depth_gt[mask]
    return (f"mask {result.mask.mean():.1%}, median |rel err| {np.median(rel):.3f}, "
            f"{np.mean(rel < 0.1):.0%} within 10%")


def emvs_report(args: argparse.Namespace):
    """The ``emvs`` section of :mod:`benchmarks.speed`."""
    from benchmarks.speed import Report, run_group

    duration = getattr(args, "emvs_duration", 0.5)
    repeats = max(int(args.repeats), 3)
    events, camera, poses, depth_gt = slider_sequence(duration)
    depth_range = (0.4, 3.0)
    n = len(events)
    report = Report("emvs", "EMVS speed (240x180, 100 planes, slider scene)",
                    {"repeats": repeats, "events": n, "sensor": f"{SIZE[0]}x{SIZE[1]}", "planes": PLANES,
                     "depth_range_m": depth_range, "scene": f"slider seed 0, {duration} s, ground-truth poses",
                     "opencv_threads": __import__("cv2").getNumThreads()})
    gather = EMVS(camera, depth_range=depth_range, n_planes=PLANES)
    splat = EMVS(camera, depth_range=depth_range, n_planes=PLANES, voting="splat")
    port = lambda: semi_dense_depth(numpy_port_dsi(events, camera, *poses, depth_range, PLANES))  # noqa: E731
    load_start = os.getloadavg()[0]
    run_group(report, "EMVS run", [
        ("numpy port (np.add.at, baseline)", port, "packets of 1024 events, one pose each"),
        ('ours, voting="splat" (exact)', lambda: splat.run(events, poses), "np.bincount, per-packet-group transfer"),
        ('ours, voting="gather" (default)', lambda: gather.run(events, poses),
         "one splat per group on 1/4-px-shifted grids, integer-shifted adds per plane"),
    ], n, repeats)
    floor, additions = method_floor(gather, events, poses)
    run_group(report, "EMVS against its method's floor", [
        ("floor: the plane additions + one splat of every event", floor,
         f"{additions} image additions (cv2.add at integer offsets), replayed"),
        ('ours, voting="gather" (default)', lambda: gather.run(events, poses), "the whole run"),
    ], n, repeats)
    results = {"numpy port": port(), "splat": splat.run(events, poses), "gather": gather.run(events, poses)}
    for name, result in results.items():
        report.checks[f"{name}: depth vs ground truth"] = _accuracy(result, depth_gt)
    agree = results["gather"].mask & results["splat"].mask
    report.checks["gather vs splat: median |depth difference| on both masks [m]"] = float(
        np.median(np.abs(results["gather"].depth[agree] - results["splat"].depth[agree])))
    report.notes += [
        f"Load average (1 min): {load_start:.2f} at the start, {os.getloadavg()[0]:.2f} at the end "
        "(2 cores shared by several people: absolute rates vary, ratios hold).",
        "Events per second = events / median wall time of EMVS.run (undistortion, pose interpolation, "
        "voting, depth extraction); the simulation of the events is not timed.",
        "The gather path is exact bilinear voting with plane offsets rounded to 1/4 px when the camera moves "
        "parallel to the image plane (the slider); with motion along the optical axis the scaled planes are "
        "resampled with cv2.warpAffine instead and the rate drops (see the README).",
    ]
    return report


def main(argv: list[str] | None = None) -> int:
    from benchmarks.speed import machine_info, publish_report

    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed_emvs", description=__doc__.split("\n")[0])
    parser.add_argument("--duration", type=float, default=0.5, help="seconds of slider scene (default 0.5)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    args.emvs_duration = args.duration
    machine = machine_info()
    publish_report(emvs_report(args), machine, write=not args.no_write)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
