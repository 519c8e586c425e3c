"""Event sequences with ground truth from renderable scenes: adaptive sampling, ESIM, HDF5 files.

:func:`simulate_scene` renders a :class:`~cmax.sim.scenes.Scene` at adaptive
times (paper eq. 1), feeds the frames to an
:class:`~cmax.sim.esim.EventSimulator`, and records ground-truth depth maps and
poses; :meth:`SyntheticSequence.save` writes everything into one HDF5 file
(events in the DSEC layout, ground truth in ``gt/``) and :func:`load_sequence`
reads it back.

Adaptive sampling
-----------------
After a sample at ``t_k`` the next one is at

    t_{k+1} = t_k + clip(lam * C / max_x |dL/dt (x, t_k)|, min_step_s, max_step_s)

(EvtSlowTV, paper eq. 1, with the safety factor ``lam``), where
``C = min(cp, cn)`` and ``L = log(I/255 + eps)``. The rate ``max |dL/dt|`` is
the **analytic motion-field bound** used by ESIM: brightness constancy gives
``dL/dt = -grad L . u`` with ``u`` the motion field of the pixel, computed
exactly from the rendered depth and the camera twist (rotation only where the
depth is NaN, i.e. at infinity); ``grad L`` is the central difference of the
rendered log image. Unlike a finite difference between two renders, it stays
finite at occlusion edges, which jump from one surface to another: an edge then
moves by about ``lam * C / jump`` pixels per sample. Sample times also land
exactly on every ``depth_times_s`` (those frames give the depth maps).
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm.auto import tqdm

import cmax.events
from cmax.events import EventLimitError, Events, concatenate
from cmax.io.h5 import H5Writer, decode_attrs, read_h5
from cmax.sim.esim import EventSimulator
from cmax.sim.scenes import Scene

__all__ = ["SyntheticSequence", "simulate_scene", "load_sequence", "motion_field", "write_ground_truth"]

_LOG_EPS = 1e-3


@dataclass(frozen=True, eq=False)
class SyntheticSequence:
    """Events of a rendered scene with its ground truth.

    Attributes
    ----------
    events : Events
        Times in absolute µs (``t_offset_us + 1e6 * t_s``).
    depth : ndarray, shape (N, H, W), float32
        z-depth [m] at ``depth_t_us``, NaN where unknown.
    depth_t_us : ndarray, shape (N,), int64
    poses : ndarray, shape (M, 4, 4), float64
        ``T_w_c`` at ``poses_t_us``.
    poses_t_us : ndarray, shape (M,), int64
    twists : ndarray, shape (M, 6), float64
        Body twists ``(v [m/s], omega [rad/s])`` at ``poses_t_us``, camera frame.
    K : ndarray, shape (3, 3)
    frame_t_us : ndarray, shape (F,), int64
        Times at which the scene was rendered and fed to the simulator.
    attrs : dict
        Settings (simulator, sampling) and the scene's description.
    """

    events: Events
    depth: np.ndarray
    depth_t_us: np.ndarray
    poses: np.ndarray
    poses_t_us: np.ndarray
    twists: np.ndarray
    K: np.ndarray
    frame_t_us: np.ndarray
    attrs: dict

    @property
    def width(self) -> int:
        return self.events.width

    @property
    def height(self) -> int:
        return self.events.height

    def pose_at(self, t_us: int) -> np.ndarray:
        """``T_w_c`` (4, 4) at ``t_us`` [µs, the events' clock], interpolated geodesically between the two
        stored poses around it (:func:`cmax.geometry.interpolate_poses`); ValueError outside them."""
        from cmax.events import check_time_us
        from cmax.geometry import interpolate_poses

        t_us = check_time_us("t_us", t_us)
        return interpolate_poses(self.poses_t_us, self.poses, np.array([t_us], np.int64))[0]

    def motion(self, t0_us: int, t1_us: int) -> np.ndarray:
        """``T_01`` (4, 4): the camera at ``t1_us`` in its frame at ``t0_us`` [µs], the ``pose=`` that
        :func:`cmax.fit` takes for a window from ``t0_us`` to ``t1_us`` (its first and last event)."""
        from cmax.geometry import relative_pose

        return relative_pose(self.pose_at(t0_us), self.pose_at(t1_us))

    def depth_at(self, t_us: int, max_offset_us: int = 0) -> np.ndarray:
        """The stored z-depth map (H, W) float32 [m] (NaN: unknown) rendered nearest to ``t_us`` [µs].

        Depth is stored only at ``depth_t_us``; a map rendered more than ``max_offset_us`` away from ``t_us``
        raises ValueError (by default the time must be one of ``depth_t_us``: the depth of another time
        would be another camera's). Centre a window on a depth time to compare a fit's depth at its
        ``t_ref_us`` (the window's middle) with it.
        """
        from cmax.events import check_time_us

        t_us = check_time_us("t_us", t_us)
        max_offset_us = check_time_us("max_offset_us", max_offset_us)
        if max_offset_us < 0:
            raise ValueError(f"max_offset_us must be >= 0, got {max_offset_us}")
        if not len(self.depth_t_us):
            raise ValueError("this sequence stores no depth maps")
        k = int(np.argmin(np.abs(self.depth_t_us.astype(np.int64) - t_us)))
        offset = abs(int(self.depth_t_us[k]) - t_us)
        if offset > max_offset_us:
            raise ValueError(f"no depth map within {max_offset_us} µs of {t_us} µs: the nearest is at "
                             f"{int(self.depth_t_us[k])} µs ({offset} µs away); depth_t_us holds the "
                             f"{len(self.depth_t_us)} times, or raise max_offset_us")
        return self.depth[k]

    def save(self, path: str | os.PathLike, *, overwrite: bool = False, compression: str = "blosc") -> Path:
        """Write events (DSEC layout, :class:`cmax.io.H5Writer`) and ``gt/`` into one HDF5 file.

        The file appears at ``path`` only when complete, ground truth included:
        :class:`~cmax.io.H5Writer` holds the lock of ``path`` (a second writer
        fails with :class:`~cmax.io.atomic.OutputLockedError`) and writes a
        private ``<path>.<hex>.partial`` (:mod:`cmax.io.atomic`: created
        exclusively, so no file of the user's is opened or removed); the events,
        then ``gt/``, then the completion record are written, and the file is
        renamed. A save killed before the end leaves only that temporary, which
        :func:`cmax.io.h5.verify_h5` refuses and the next save of ``path``
        removes. An existing ``path`` raises ``FileExistsError`` unless
        ``overwrite`` (then it is replaced only when the new file is complete).
        ``compression``: of the event columns, ``'blosc'``, ``'gzip'`` or ``'none'``. Returns the path.
        """
        path = Path(path)
        t_offset = int(self.frame_t_us[0]) if len(self.frame_t_us) else 0
        with H5Writer(path, self.width, self.height, t_offset_us=t_offset, overwrite=overwrite,
                      compression=compression, **self.attrs) as writer:
            for start in range(0, len(self.events), 1 << 20):
                writer.append(self.events[start: start + (1 << 20)])
            writer.close(extra=lambda file: write_ground_truth(file, self))
        return path


def write_ground_truth(file: h5py.File, sequence: SyntheticSequence) -> None:
    """Add ``gt/{depth, depth_t, poses, poses_t, twists, K}`` to an open HDF5 file.

    ``gt/depth`` (N, H, W) float32 [m] is chunked per map and gzip-compressed;
    times are int64 µs.
    """
    group = file.create_group("gt")
    chunks = (1,) + sequence.depth.shape[1:] if len(sequence.depth) else None
    group.create_dataset("depth", data=sequence.depth.astype(np.float32), chunks=chunks,
                         compression="gzip" if chunks else None, compression_opts=4 if chunks else None)
    group.create_dataset("depth_t", data=sequence.depth_t_us.astype(np.int64))
    group.create_dataset("poses", data=sequence.poses.astype(np.float64))
    group.create_dataset("poses_t", data=sequence.poses_t_us.astype(np.int64))
    group.create_dataset("twists", data=sequence.twists.astype(np.float64))
    group.create_dataset("K", data=np.asarray(sequence.K, dtype=np.float64))
    group.create_dataset("frame_t", data=sequence.frame_t_us.astype(np.int64))
    group.attrs["units"] = "depth: metres (z-depth, NaN unknown); times: µs; poses: T_w_c; twists: (v m/s, omega rad/s)"


def load_sequence(path: str | os.PathLike) -> SyntheticSequence:
    """Read the file at ``path`` written by :meth:`SyntheticSequence.save` (events and ``gt/``)."""
    path = Path(path)
    events = read_h5(path)
    with h5py.File(path, "r") as file:
        if "gt" not in file:
            raise ValueError(f"{path} has no gt/ group: not a synthetic sequence")
        gt = file["gt"]
        attrs = decode_attrs(file.attrs)
        return SyntheticSequence(
            events, gt["depth"][:], gt["depth_t"][:], gt["poses"][:], gt["poses_t"][:],
            gt["twists"][:] if "twists" in gt else np.zeros((len(gt["poses_t"]), 6)),
            gt["K"][:], gt["frame_t"][:] if "frame_t" in gt else np.zeros(0, np.int64), attrs,
        )


def motion_field(depth: np.ndarray, twist: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image velocity (du/dt, dv/dt) [px/s], each (H, W), of static points seen by a moving camera.

    For normalized coordinates ``x, y``, depth ``Z`` and body twist
    ``(v, omega)`` (camera frame)::

        dx/dt = (-v_x + x v_z) / Z + x y w_x - (1 + x^2) w_y + y w_z
        dy/dt = (-v_y + y v_z) / Z + (1 + y^2) w_x - x y w_y - x w_z

    scaled by ``fx``, ``fy`` (zero skew assumed); where the depth is NaN the
    point is taken at infinity (rotation only).
    """
    depth = np.asarray(depth, dtype=np.float64)
    v, w = np.asarray(twist, dtype=np.float64)[:3], np.asarray(twist, dtype=np.float64)[3:]
    H, W = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x = (np.arange(W) - cx) / fx
    y = (np.arange(H)[:, None] - cy) / fy
    inv_z = np.where(np.isfinite(depth), 1.0 / np.where(np.isfinite(depth), depth, 1.0), 0.0)
    dx = (-v[0] + x * v[2]) * inv_z + x * y * w[0] - (1 + x * x) * w[1] + y * w[2]
    dy = (-v[1] + y * v[2]) * inv_z + (1 + y * y) * w[0] - x * y * w[1] - x * w[2]
    return fx * dx, fy * dy


def _max_log_rate(intensity: np.ndarray, depth: np.ndarray, twist: np.ndarray, K: np.ndarray) -> float:
    """max |grad L . u| [1/s] over the image (see the module docstring)."""
    L = np.log(intensity.astype(np.float64) / 255.0 + _LOG_EPS)
    gy, gx = np.gradient(L)
    du, dv = motion_field(depth, twist, K)
    return float(np.abs(gx * du + gy * dv).max())


def _check_positive(name: str, value: object) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive and finite, got {value}")
    return float(value)


def _times_to_end(t0_s: float, t_end_s: float, rate_hz: float) -> np.ndarray:
    """Times [s] every ``1 / rate_hz`` from ``t0_s``, and ``t_end_s`` itself when the grid stops short of it by
    more than half a µs: ground truth that covers every event, the last ones included.

    >>> _times_to_end(0.0, 0.012, 200.0).tolist()
    [0.0, 0.005, 0.01, 0.012]
    """
    times = np.arange(t0_s, t_end_s + 1e-9, 1.0 / rate_hz)
    return times if t_end_s - times[-1] <= 5e-7 else np.append(times, t_end_s)


def _too_many_events(total: int, reached_s: float, duration_s: float) -> EventLimitError:
    """The error for a scene whose events outgrow ``cmax.events.MAX_EVENTS`` after ``reached_s`` of ``duration_s``.

    >>> str(_too_many_events(300, 0.5, 2.0)).startswith("the scene made 300 events in its first 0.5 s of 2 s")
    True
    """
    limit = int(cmax.events.MAX_EVENTS)
    fits = reached_s * limit / total
    return EventLimitError(
        f"the scene made {total:,} events in its first {reached_s:.3g} s of {duration_s:g} s, more than "
        f"cmax.events.MAX_EVENTS={limit:,} that fit in memory at once (a scene's events are held until it is "
        f"saved): simulate about {fits:.3g} s or less at a time (cmax scene --duration; simulate_scene(t0_s=) "
        "starts a part later in the scene), or raise cmax.events.MAX_EVENTS deliberately")


def simulate_scene(
    scene: Scene,
    duration_s: float,
    simulator: EventSimulator,
    *,
    lam: float = 0.5,
    depth_times_s: np.ndarray | None = None,
    depth_rate_hz: float = 20.0,
    pose_rate_hz: float = 200.0,
    t0_s: float = 0.0,
    t_offset_us: int = 0,
    min_step_s: float = 1e-4,
    max_step_s: float = 1e-2,
    progress: bool = False,
) -> SyntheticSequence:
    """Simulate an event camera moving through ``scene`` for ``duration_s`` seconds.

    Parameters
    ----------
    scene : Scene
        Anything with ``camera``, ``render(t_s)``, ``pose(t_s)``, ``twist(t_s)``.
    duration_s : float
        Length [s], from ``t0_s``.
    simulator : EventSimulator
        Its state is reset first; ``min(cp, cn)`` is the ``C`` of eq. 1.
    lam : float
        Safety factor of the adaptive step (paper's lambda), in (0, 1].
    depth_times_s : array_like, shape (N,), optional
        Scene times [s] of the ground-truth depth maps, inside
        ``[t0_s, t0_s + duration_s]``; default every ``1/depth_rate_hz`` s.
    pose_rate_hz : float
        Rate of the recorded poses and twists (analytic, so any rate is exact).
    t0_s : float
        Scene time of the first frame.
    t_offset_us : int
        Absolute time (µs) of scene time 0 in the output.
    min_step_s, max_step_s : float
        Clamp of the adaptive step [s] (``min_step_s >= 1e-5``: times are whole µs).
    progress : bool
        Show a progress bar (tqdm, on stderr) over simulated milliseconds.

    Returns
    -------
    SyntheticSequence

    Raises
    ------
    cmax.events.EventLimitError
        As soon as the events made so far (all held in memory) exceed
        ``cmax.events.MAX_EVENTS``, naming the scene time reached: a shorter
        ``duration_s`` fits.
    """
    duration_s = _check_positive("duration_s", duration_s)
    lam = _check_positive("lam", lam)
    if lam > 1:
        raise ValueError(f"lam must be in (0, 1], got {lam}")
    min_step_s = _check_positive("min_step_s", min_step_s)
    max_step_s = _check_positive("max_step_s", max_step_s)
    if min_step_s < 1e-5 or max_step_s < min_step_s:
        raise ValueError(f"need 1e-5 <= min_step_s <= max_step_s, got {min_step_s}, {max_step_s}")
    pose_rate_hz = _check_positive("pose_rate_hz", pose_rate_hz)
    if not isinstance(simulator, EventSimulator):
        raise TypeError(f"simulator must be an EventSimulator, got {type(simulator).__name__}")
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must have camera, render, pose and twist, got {type(scene).__name__}")
    t_end = t0_s + duration_s
    if depth_times_s is None:
        depth_times_s = _times_to_end(t0_s, t_end, _check_positive("depth_rate_hz", depth_rate_hz))
    depth_times_s = np.asarray(depth_times_s, dtype=np.float64)
    if depth_times_s.ndim != 1 or np.any(np.diff(depth_times_s) <= 0):
        raise ValueError("depth_times_s must be a strictly increasing (N,) array of seconds")
    if depth_times_s.size and (depth_times_s[0] < t0_s - 1e-9 or depth_times_s[-1] > t_end + 1e-9):
        raise ValueError(f"depth_times_s must lie in [{t0_s}, {t_end}] s")

    def to_us(t_s: float) -> int:
        return int(t_offset_us) + int(round(t_s * 1e6))

    K = scene.camera.K
    C = float(min(simulator.settings.cp, simulator.settings.cn))
    simulator.reset()
    required = list(depth_times_s) + [t_end]
    events, depths, frame_times = [], [], []
    t, next_required, total = float(t0_s), 0, 0
    bar = tqdm(total=round(duration_s * 1e3), unit="ms", desc="simulating (ms of scene)", disable=not progress)
    while True:
        intensity, depth = scene.render(t)
        t_us = to_us(t)
        events.append(simulator.step(intensity, t_us))
        total += len(events[-1])
        if total > cmax.events.MAX_EVENTS:
            bar.close()
            raise _too_many_events(total, t - t0_s, duration_s)
        frame_times.append(t_us)
        while next_required < len(depth_times_s) and depth_times_s[next_required] <= t + 5e-7:
            depths.append(depth)
            next_required += 1
        if t >= t_end - 5e-7:
            break
        rate = _max_log_rate(intensity, depth, scene.twist(t), K)
        step = min(max(lam * C / rate if rate > 0 else max_step_s, min_step_s), max_step_s)
        remaining = min(r for r in required if r > t + 5e-7) - t
        # Land on the next required time; split the last stretch rather than leave a sliver.
        t_next = t + (remaining if remaining <= step else remaining / 2 if remaining < step + min_step_s else step)
        if to_us(t_next) <= t_us:  # whole microseconds must increase
            t_next = (t_us + 1 - int(t_offset_us)) * 1e-6
        bar.update(round((t_next - t0_s) * 1e3) - bar.n)
        t = t_next
    bar.close()
    poses_t = _times_to_end(t0_s, t_end, pose_rate_hz)
    settings = {name: value for name, value in dataclasses.asdict(simulator.settings).items()}
    attrs: dict[str, Any] = {
        "source": "cmax.sim.simulate_scene",
        "simulated_s": [float(t0_s), float(t_end)],   # the span simulated; scene.duration_s is the scene's design
        "simulator": settings,
        "sampling": {"lam": lam, "C": C, "min_step_s": min_step_s, "max_step_s": max_step_s,
                     "rate": "analytic motion-field bound max|grad L . u|"},
    }
    info = getattr(scene, "info", None)
    if info is not None:
        attrs["scene"] = dataclasses.asdict(info)
    camera = scene.camera
    return SyntheticSequence(
        events=concatenate(events) if events else Events.empty(camera.width, camera.height),
        depth=np.stack(depths).astype(np.float32) if depths else np.zeros((0, camera.height, camera.width), np.float32),
        depth_t_us=np.array([to_us(t) for t in depth_times_s], dtype=np.int64),
        poses=np.stack([scene.pose(float(t)) for t in poses_t]),
        poses_t_us=np.array([to_us(t) for t in poses_t], dtype=np.int64),
        twists=np.stack([scene.twist(float(t)) for t in poses_t]),
        K=np.asarray(K, dtype=np.float64),
        frame_t_us=np.array(frame_times, dtype=np.int64),
        attrs=attrs,
    )
