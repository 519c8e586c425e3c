"""Synthetic event windows with exact ground truth for the tests and benchmarks of :func:`cmax.fit` (a
fixture of the benchmarks and tests, not part of the installed library).

Each window is a piecewise-planar world (:mod:`cmax.sim.world`) seen by a
camera that moves with a **constant body twist** ``xi = (v, omega)``, so that
the warp models of :mod:`cmax.warp` are exact: ``T_w_c(t) = T_w_c(t0)
se3_exp(xi (t - t0))``. Frames are ray-cast (:class:`cmax.sim.render.PlanarRenderer`)
at a rate that moves no pixel by more than ``max_px_per_frame`` between two
frames, and turned into events by ESIM (:class:`cmax.sim.esim.EventSimulator`).
The ground-truth depth belongs to the middle of the window.

Presets (346x260 by default, like a DAVIS346 / MVSEC):

``slider``          a textured wall 1.5-4 m ahead, the camera slides parallel to it (constant flow)
``rotation``        inside a textured room (2-6 m), pure rotation of 20-60 deg/s
``indoor_flying``   a room of depth 1-6.5 m with boxes; 0.3-1 m/s and 5-25 deg/s, like MVSEC indoor_flying
``driving``         a street with facades and a road; 6-12 m/s forward, a small yaw rate
``two_planes``      two walls at different depths (1.2-2 m and 3-5 m), sliding motion

These constant-twist windows make the warp models exact (the flow and rotation
tests need that). :func:`preset_window` cuts a window out of the real scene
presets of :mod:`cmax.sim.presets` (smooth, slowly varying trajectories), with
the window's motion ``T01`` and the depth at its middle: what the depth and
se3 benchmarks and the objective-sanity test use.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cmax.camera import Camera
from cmax.events import Events, concatenate
from cmax.geometry import se3_exp
from cmax.sim.esim import EventSimulator
from cmax.sim.render import PlanarRenderer
from cmax.sim.trajectories import look_at_rotation
from cmax.sim.world import WorldBuilder

__all__ = ["SyntheticWindow", "PresetWindow", "PRESETS", "make_window", "preset_window", "davis_camera",
           "tiny_training_file"]

PRESETS = ("slider", "rotation", "indoor_flying", "driving", "two_planes")


@dataclass(frozen=True, eq=False)
class SyntheticWindow:
    """Events of one window and the ground truth.

    Attributes
    ----------
    events : Events
    K : ndarray (3, 3)
    twist : ndarray (6,)
        Constant body twist ``(v [m/s], omega [rad/s])``, camera frame.
    depth : ndarray (H, W) float32
        z-depth [m] at ``t_ref_us`` (NaN: sky).
    t_ref_us : int
        Middle of the window.
    T_w_c0 : ndarray (4, 4)
        Pose at the window's first frame (``t = 0``).
    preset : str
    seed : int
    """

    events: Events
    K: np.ndarray
    twist: np.ndarray
    depth: np.ndarray
    t_ref_us: int
    T_w_c0: np.ndarray
    preset: str
    seed: int

    @property
    def flow(self) -> np.ndarray:
        """Optical flow [px/s] at the image centre (exact and constant for ``slider``)."""
        z = float(np.nanmedian(self.depth))
        v = self.twist[:3]
        return np.array([self.K[0, 0] * v[0] / z, self.K[1, 1] * v[1] / z]) * -1.0


def davis_camera(width: int = 346, height: int = 260, focal: float = 250.0) -> Camera:
    return Camera.from_intrinsics(focal, focal, (width - 1) / 2, (height - 1) / 2, width, height)


def _unit(rng: np.random.Generator) -> np.ndarray:
    u = rng.normal(size=3)
    return u / np.linalg.norm(u)


def _pose(forward, position) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = look_at_rotation(forward)
    T[:3, 3] = position
    return T


def _room(b: WorldBuilder, rng: np.random.Generator, half: tuple[float, float, float], kinds: tuple[str, ...]) -> None:
    """A closed box room centred at the origin (z up) with textured walls, floor and ceiling."""
    hx, hy, hz = half
    tex = [b.texture(k) for k in kinds]
    pick = lambda: tex[int(rng.integers(len(tex)))]  # noqa: E731
    b.quad([-hx, hy, -hz], [2 * hx, 0, 0], [0, 0, 2 * hz], pick())   # front (y+)
    b.quad([-hx, -hy, -hz], [2 * hx, 0, 0], [0, 0, 2 * hz], pick())  # back
    b.quad([hx, -hy, -hz], [0, 2 * hy, 0], [0, 0, 2 * hz], pick())   # right
    b.quad([-hx, -hy, -hz], [0, 2 * hy, 0], [0, 0, 2 * hz], pick())  # left
    b.quad([-hx, -hy, -hz], [2 * hx, 0, 0], [0, 2 * hy, 0], pick(), gain=0.8)  # floor
    b.quad([-hx, -hy, hz], [2 * hx, 0, 0], [0, 2 * hy, 0], pick(), gain=1.1)   # ceiling


def _scene(preset: str, rng: np.random.Generator):
    """World, start pose and twist of a preset."""
    b = WorldBuilder(rng, texture_size=512)
    deg = np.pi / 180
    if preset in ("slider", "two_planes"):
        near = rng.uniform(1.5, 4.0) if preset == "slider" else rng.uniform(1.2, 2.0)
        poster = b.texture("poster")
        if preset == "slider":
            b.quad([-20, near, -15], [40, 0, 0], [0, 0, 30], poster, texels_per_metre=120.0)
        else:  # the near wall covers the left part of the view, the far wall the rest
            far = rng.uniform(3.0, 5.0)
            b.quad([-20, far, -15], [40, 0, 0], [0, 0, 30], b.texture("mat"), texels_per_metre=100.0)
            b.quad([-20, near, -15], [20 + rng.uniform(-0.1, 0.1) * near, 0, 0], [0, 0, 30], poster,
                   texels_per_metre=120.0)
        angle = rng.uniform(0, 2 * np.pi)
        speed = rng.uniform(0.15, 0.35) * near
        twist = np.r_[speed * np.cos(angle), 0.5 * speed * np.sin(angle), 0.0, 0, 0, 0]
        return b.build(), _pose([0, 1, 0], [0, 0, 0]), twist
    if preset == "rotation":
        _room(b, rng, (rng.uniform(2, 4), rng.uniform(3, 5), rng.uniform(2, 3)), ("poster", "wood", "mat", "plaster"))
        omega = _unit(rng) * rng.uniform(20, 60) * deg
        return b.build(), _pose([rng.uniform(-0.3, 0.3), 1, rng.uniform(-0.2, 0.2)], [0, 0, 0]), np.r_[0, 0, 0, omega]
    if preset == "indoor_flying":
        _room(b, rng, (3.5, 3.2, 1.6), ("poster", "mat", "wood", "plaster"))
        for _ in range(3):
            b.box([rng.uniform(-2.5, 2.5), rng.uniform(0.5, 2.6), -1.6 + 0.5], [0.8, 0.8, 1.0],
                  rng.uniform(0, np.pi), b.texture("poster"))
        position = [rng.uniform(-0.5, 0.5), -2.2, rng.uniform(-0.3, 0.3)]
        v = _unit(rng) * rng.uniform(0.3, 1.0)
        omega = _unit(rng) * rng.uniform(5, 25) * deg
        return b.build(), _pose([rng.uniform(-0.3, 0.3), 1, rng.uniform(-0.1, 0.1)], position), np.r_[v, omega]
    if preset == "driving":
        road, facade = b.texture("asphalt"), b.texture("facade")
        b.quad([-6, -5, 0], [12, 0, 0], [0, 120, 0], road, texels_per_metre=40.0)
        for side in (-6.0, 6.0):
            b.quad([side, -5, 0], [0, 120, 0], [0, 0, 12], facade, texels_per_metre=30.0)
        for k in range(4):
            b.box([rng.choice([-3.5, 3.5]), rng.uniform(8, 40), 0.75], [1.8, 4.2, 1.5], 0.0, b.texture("car"))
        v = np.array([rng.uniform(-0.2, 0.2), 0.0, rng.uniform(6, 12)])  # camera frame: z forward
        omega = np.array([0.0, rng.uniform(-5, 5) * deg, 0.0])
        return b.build(), _pose([0, 1, 0], [rng.uniform(-1.5, 1.5), 0, 1.4]), np.r_[v, omega]
    raise ValueError(f"preset must be one of {PRESETS}, got {preset!r}")


def _max_displacement(renderer: PlanarRenderer, T_w_c0: np.ndarray, twist: np.ndarray, duration_s: float) -> float:
    _, depth = renderer.render(T_w_c0)
    cam = renderer.camera
    ys, xs = np.mgrid[0:cam.height:8, 0:cam.width:8]
    d = depth[ys, xs].ravel()
    d = np.where(np.isfinite(d), d, 1e3)
    rays = np.column_stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]) @ np.linalg.inv(cam.K).T
    points = rays * d[:, None]
    T = np.linalg.inv(se3_exp(twist * duration_s))
    moved = points @ T[:3, :3].T + T[:3, 3]
    moved = moved[moved[:, 2] > 0.05]
    px = moved @ cam.K.T
    px = px[:, :2] / px[:, 2:]
    start = (np.column_stack([xs.ravel(), ys.ravel()]))[: len(px)]
    return float(np.max(np.abs(px - start[: len(px)]).sum(1))) if len(px) else 50.0


def make_window(preset: str, seed: int, *, width: int = 346, height: int = 260, duration_s: float = 0.1665,
                focal: float = 250.0, max_px_per_frame: float = 0.25, contrast_threshold: float = 0.2,
                max_frames: int = 250) -> SyntheticWindow:
    """Render and simulate one window of ``preset`` (see the module docstring) for ``seed``.

    The events span ``[0, duration_s]`` [µs from the window start]; the first
    frame only initialises the simulator.
    """
    rng = np.random.default_rng([seed, PRESETS.index(preset) if preset in PRESETS else 99])
    world, T_w_c0, twist = _scene(preset, rng)
    camera = davis_camera(width, height, focal)
    renderer = PlanarRenderer(world, camera)
    displacement = _max_displacement(renderer, T_w_c0, twist, duration_s)
    frames = int(np.clip(np.ceil(displacement / max_px_per_frame), 20, max_frames))
    times = np.linspace(0.0, duration_s, frames + 1)
    simulator = EventSimulator(cp=contrast_threshold, cn=contrast_threshold, threshold_sigma=0.03, seed=seed)
    chunks = []
    for t in times:
        intensity, _ = renderer.render(T_w_c0 @ se3_exp(twist * t))
        chunks.append(simulator.step(intensity, int(round(t * 1e6))))
    events = concatenate(chunks[1:])
    t_ref_us = int(round(duration_s * 0.5e6))
    _, depth = renderer.render(T_w_c0 @ se3_exp(twist * t_ref_us * 1e-6))
    return SyntheticWindow(events, camera.K.copy(), np.asarray(twist, float), depth, t_ref_us, T_w_c0, preset, seed)


@dataclass(frozen=True, eq=False)
class PresetWindow:
    """One window of a :mod:`cmax.sim.presets` scene and its ground truth.

    Attributes
    ----------
    events : Events
        Times in µs of scene time.
    K : ndarray (3, 3)
    T01 : ndarray (4, 4)
        The camera at the last event in the frame of the camera at the first
        (what :func:`cmax.fit` takes as ``pose``).
    twist : ndarray (6,)
        ``se3_log(T01) / duration``: the window's mean body twist ``(v, omega)``.
    depth : ndarray (H, W) float32
        z-depth [m] at ``t_ref_us`` (NaN: sky).
    t_ref_us : int
        Middle of the window (first and last event).
    preset : str
    seed : int
    """

    events: Events
    K: np.ndarray
    T01: np.ndarray
    twist: np.ndarray
    depth: np.ndarray
    t_ref_us: int
    preset: str
    seed: int


def preset_window(preset: str, seed: int, *, width: int = 346, height: int = 260, duration_s: float = 0.1665,
                  t0_s: float = 0.5, texture_size: int = 256) -> PresetWindow:
    """Simulate ``[t0_s, t0_s + duration_s]`` of the preset scene ``preset`` (seed) with its recommended simulator."""
    from cmax.geometry import se3_log
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene(preset, seed, width, height, duration_s=t0_s + duration_s + 0.1, texture_size=texture_size)
    simulator = EventSimulator(**scene.recommended_simulator, seed=seed)
    mid_guess = t0_s + duration_s / 2
    sequence = simulate_scene(scene, duration_s, simulator, t0_s=t0_s, depth_times_s=[mid_guess])
    events = sequence.events
    if len(events) < 2:
        raise ValueError(f"{preset} seed {seed}: the window has {len(events)} events")
    t0_us, t1_us = int(events.t[0]), int(events.t[-1])
    t_ref_us = (t0_us + t1_us) // 2
    _, depth = scene.render(t_ref_us * 1e-6)
    T01 = np.linalg.inv(scene.pose(t0_us * 1e-6)) @ scene.pose(t1_us * 1e-6)
    twist = se3_log(T01) / ((t1_us - t0_us) * 1e-6)
    return PresetWindow(events, sequence.K.copy(), T01, twist, depth.astype(np.float32), t_ref_us, preset, seed)


def tiny_training_file(folder: str | Path) -> Path:
    """0.6 s of a tiny ``indoor_flying`` scene (48x36) with ground truth every 50 ms, saved to ``folder/tiny.h5``
    (what :mod:`learned.train` reads): the training tests' and ``benchmarks.device_check``'s data."""
    from cmax.sim.presets import make_scene
    from cmax.sim.synthetic import simulate_scene

    scene = make_scene("indoor_flying", seed=5, width=48, height=36, duration_s=1.0, texture_size=64)
    sequence = simulate_scene(scene, 0.6, EventSimulator(**{**scene.recommended_simulator, "seed": 5}),
                              depth_rate_hz=20)
    return sequence.save(Path(folder) / "tiny.h5")
