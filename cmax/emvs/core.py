"""``cmax.EMVS``: event-based multi-view stereo by space-sweep voting (the EMVS baseline).

Rebecq, Gallego, Mueggler, Scaramuzza, "EMVS: Event-based multi-view stereo -
3D reconstruction with an event camera in real-time", IJCV 126, 2018,
doi:10.1007/s11263-018-1106-2.

Events of 2000 points on a plane 2 m away, seen by a camera sliding 0.3 m along x, and the depth
EMVS finds with the camera-to-world poses ``(times_us, T_w_c)``:

>>> import numpy as np
>>> from cmax.events import Events
>>> rng = np.random.default_rng(0)
>>> camera = Camera.from_intrinsics(100.0, 100.0, 47.5, 35.5, 96, 72)      # fx, fy, cx, cy [px], W, H
>>> X, Y = rng.uniform(-1.5, 1.5, 2000), rng.uniform(-1.0, 1.0, 2000)      # the points [m], at Z = 2 m
>>> t_us = np.sort(rng.integers(0, 300_000, 30_000)); point = rng.integers(0, 2000, 30_000)
>>> u = 100 * (X[point] - 0.3 * (t_us / 300_000 - 0.5)) / 2 + 47.5        # the camera at x(t) [m]
>>> v = 100 * Y[point] / 2 + 35.5
>>> inside = (u > 0) & (u < 95) & (v > 0) & (v < 71)
>>> events = Events(np.rint(u[inside]), np.rint(v[inside]), t_us[inside], np.ones(inside.sum()), 96, 72)
>>> times_us = np.linspace(0, 300_000, 31).astype(np.int64)
>>> T_w_c = np.tile(np.eye(4), (31, 1, 1)); T_w_c[:, 0, 3] = 0.3 * (times_us / 300_000 - 0.5)
>>> result = EMVS(camera, depth_range=(1.0, 4.0), n_planes=50).run(events, (times_us, T_w_c))
>>> result.depth.shape, round(float(np.median(result.depth[result.mask])), 1)
((72, 96), 2.0)
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from tqdm.auto import tqdm

from cmax.camera import Camera
from cmax.emvs.dsi import base_plane_homographies, plane_depths, plane_transfers, project_packets, splat_votes
from cmax.emvs.gather import ShiftedAdditions, gather_votes
from cmax.emvs.poses import as_trajectory, check_coverage
from cmax.emvs.result import DSI, SemiDenseDepth, semi_dense_depth
from cmax.events import Events, require_events
from cmax.geometry import interpolate_poses, invert_pose
from cmax.hot_pixels import HotPixelFilter, check_filter, no_pixels

__all__ = ["EMVS"]

_VOTING = ("gather", "splat")


def _positive_int(name: str, value: object, minimum: int = 1) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _odd_size(name: str, value: object) -> int:
    size = _positive_int(name, value)
    if size % 2 == 0:
        raise ValueError(f"{name} must be odd, got {size}")
    return size


def _positive_float(name: str, value: object) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {value!r}")
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive and finite, got {value}")
    return float(value)


def _packets(t_us: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Start indices (K + 1,) of packets of ``size`` events and each packet's mid time (K,) [µs]."""
    starts = np.append(np.arange(0, len(t_us), size), len(t_us))
    mid = (t_us[starts[:-1]] + t_us[starts[1:] - 1]) // 2
    return starts, mid


def _groups(centres: np.ndarray, sizes: np.ndarray, max_events: int, max_travel: float) -> list[tuple[int, int]]:
    """Consecutive packets ``[j, m)`` with at most ``max_events`` events (or one packet) whose
    camera centres stay within ``max_travel`` [m] of the first one's."""
    groups, j, n = [], 0, len(sizes)
    look = max_events // max(int(sizes.min()), 1) + 2  # no group holds more packets
    while j < n:
        travel = np.linalg.norm(centres[j: j + look] - centres[j], axis=1)
        count = np.cumsum(sizes[j: j + look])
        fits = (travel <= max_travel) & (count <= max_events)
        m = j + max(1, int(np.argmin(fits)) if not fits.all() else len(fits))
        groups.append((j, m))
        j = m
    return groups


def _parallax_px(centres: np.ndarray, camera: Camera, depths: np.ndarray) -> float:
    """Largest shift [px] of a ray's votes between the nearest and farthest plane (see ``DSI.parallax_px``).

    ``centres`` (K, 3): camera centres of the packets in the reference frame [m].
    """
    K = camera.pinhole_K
    focal = max(K[0, 0], K[1, 1])
    radius = max(K[0, 2], camera.width - K[0, 2], K[1, 2], camera.height - K[1, 2])
    travel = focal * np.hypot(centres[:, 0], centres[:, 1]) + radius * np.abs(centres[:, 2])
    return float((1.0 / depths[0] - 1.0 / depths[-1]) * travel.max()) if len(travel) else 0.0


#: Events whose pixels :meth:`EMVS.dsi` undistorts and projects at once (whole groups of packets; one group may hold
#: more): memory holds the events and one such block's pixels and positions (about 25 bytes an event), not those
#: of every event of the span.
PROJECT_CHUNK_EVENTS = 1 << 22


def _blocks(groups: list[tuple[int, int]], starts: np.ndarray, max_events: int) -> list[tuple[int, int]]:
    """Consecutive groups ``[a, b)`` (indices into ``groups``) whose events (``starts``: packet start rows) number at
    most ``max_events``, or one group.

    >>> _blocks([(0, 1), (1, 2), (2, 4)], np.array([0, 10, 20, 30, 40]), 25)
    [(0, 2), (2, 3)]
    """
    blocks, a = [], 0
    while a < len(groups):
        b = a + 1
        while b < len(groups) and starts[groups[b][1]] - starts[groups[a][0]] <= max_events:
            b += 1
        blocks.append((a, b))
        a = b
    return blocks


#: Largest Disparity Space Image :class:`EMVS` allocates (``n_planes x height x width`` float32) [bytes]: a mistyped
#: ``n_planes`` (100000 planes of a 240x180 sensor: 16 GiB) is refused before any work, not met by the OOM killer.
MAX_DSI_BYTES = 4 << 30


@dataclass(frozen=True, eq=False)
class EMVS:
    """EMVS: semi-dense depth from events and known camera poses by voting in a Disparity Space Image.

    Parameters
    ----------
    camera : Camera
        Intrinsics, sensor size and optional distortion and rectification; event coordinates are
        undistorted with the camera's lookup table, and the DSI lives on an
        ideal pinhole view with its :attr:`~cmax.Camera.pinhole_K` (``K``, or ``rectified_K``) and size. With a
        rectification ``R`` the view is the rectified camera's: the poses (of the camera) are turned into its
        ``T_w_rect = T_w_c [R^T | 0]``, and the depth map is the rectified frame's z-depth.
    depth_range : (float, float)
        ``(near, far)`` [m] of the planes, ``0 < near < far``.
    n_planes : int
        Planes of the DSI, uniform in inverse depth (>= 2; the DSI, ``n_planes x H x W`` float32, must fit
        in :data:`MAX_DSI_BYTES`).
    events_per_pose : int
        Events of one packet, sharing one camera pose interpolated on SE(3)
        at the packet's middle time; each packet is mapped to the base plane
        with its own plane-induced homography.
    events_per_transfer : int
        Most events of consecutive packets that share one affine transfer to
        the other planes (one splat and ``n_planes`` resamplings in the
        ``gather`` voting).
    transfer_tolerance_px : float
        Packets share a transfer only while their camera centres stay within
        ``2 * tol / (f * dr)`` metres of the group's first one, ``f`` the largest of
        ``fx, fy`` and the principal point's distances to the image border,
        ``dr`` half the inverse-depth range: a bound of about ``tol`` pixels on the
        displacement of a vote against its packet's own transfer.
    voting : {"gather", "splat"}
        ``gather`` (default, fast): one bilinear splat per group on the base
        plane resampled into every plane with ``cv2.warpAffine``; ``splat``:
        the exact bilinear votes of every event on every plane.
    subpixel : int
        ``gather`` voting: plane offsets are rounded to ``1/subpixel`` px (the
        votes move by at most ``1/(2 subpixel)`` px against ``splat``).
    threshold_kernel, threshold_c : int, float
        Adaptive Gaussian threshold of the confidence map (window [px] and
        offset on the 0-255 scale) that makes the semi-dense mask.
    median_size : int
        Median filter window of the depth (masked pixels only; 1 disables it).
    progress : bool
        Show a progress bar over the packet groups.
    hot_pixels : HotPixelFilter or None
        Which pixels are hot (:class:`cmax.hot_pixels.HotPixelFilter`: far more events than the scene's
        edges give any pixel, firing alone at a steady rate, or locked to a mains flicker; a defect or a
        flickering light): their events do not vote
        (``SemiDenseDepth.hot_pixels`` lists them). None: every event votes.
    """

    camera: Camera
    depth_range: tuple[float, float] = (0.5, 5.0)
    n_planes: int = 100
    events_per_pose: int = 256
    events_per_transfer: int = 32768
    transfer_tolerance_px: float = 0.5
    voting: str = "gather"
    subpixel: int = 4
    threshold_kernel: int = 5
    threshold_c: float = 5.0
    median_size: int = 5
    progress: bool = False
    hot_pixels: HotPixelFilter | None = field(default_factory=HotPixelFilter)

    def __post_init__(self) -> None:
        check_filter(self.hot_pixels)
        if not isinstance(self.camera, Camera):
            raise TypeError(f"camera must be a cmax.Camera, got {type(self.camera).__name__}"
                            + (" (a K matrix: cmax.Camera(K, width, height[, distortion]))"
                               if np.shape(self.camera) == (3, 3) else ""))
        try:
            near, far = (float(v) for v in self.depth_range)
        except (TypeError, ValueError):
            raise ValueError(f"depth_range must be (near, far) in metres, got {self.depth_range!r}") from None
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
            raise ValueError(f"depth_range must satisfy 0 < near < far (metres), got {self.depth_range!r}")
        object.__setattr__(self, "depth_range", (near, far))
        _positive_int("n_planes", self.n_planes, minimum=2)
        size = int(self.n_planes) * self.camera.width * self.camera.height * np.dtype(np.float32).itemsize
        if size > MAX_DSI_BYTES:
            raise ValueError(f"n_planes={self.n_planes} planes of {self.camera.width}x{self.camera.height} make a "
                             f"Disparity Space Image of {size / 2**30:.1f} GiB, more than cmax.emvs.core.MAX_DSI_BYTES "
                             f"({MAX_DSI_BYTES >> 30} GiB): give at most {MAX_DSI_BYTES // (size // self.n_planes):,} "
                             "planes (EMVS uses 100)")
        _positive_int("events_per_pose", self.events_per_pose)
        _positive_int("events_per_transfer", self.events_per_transfer)
        _positive_float("transfer_tolerance_px", self.transfer_tolerance_px)
        _positive_int("subpixel", self.subpixel)
        if self.voting not in _VOTING:
            raise ValueError(f"voting must be one of {sorted(_VOTING)}, got {self.voting!r}")
        _odd_size("threshold_kernel", self.threshold_kernel)
        if self.threshold_kernel < 3:
            raise ValueError(f"threshold_kernel must be >= 3, got {self.threshold_kernel}")
        if not np.isfinite(float(self.threshold_c)):
            raise ValueError(f"threshold_c must be finite, got {self.threshold_c}")
        _odd_size("median_size", self.median_size)

    @property
    def depths(self) -> np.ndarray:
        """Plane depths (n_planes,) [m], nearest first, uniform in inverse depth."""
        return plane_depths(self.depth_range, self.n_planes)

    def _check_events(self, events: object) -> Events:
        require_events(events)
        if len(events) == 0:
            raise ValueError("events must not be empty")
        if events.sensor_size != (self.camera.width, self.camera.height):
            raise ValueError(f"events come from a {events.width}x{events.height} sensor, "
                             f"the camera is {self.camera.width}x{self.camera.height}")
        return events

    def dsi(self, events: Events, poses: object, *, t_ref_us: int | None = None) -> DSI:
        """Vote the events into the Disparity Space Image of the reference view.

        Parameters
        ----------
        events : Events
            Non-empty, from the camera's sensor.
        poses : (times_us (M,), T_w_c (M, 4, 4)) or object with ``times_us`` and ``poses``
            Camera-to-world trajectory covering the events' time span [µs].
        t_ref_us : int, optional
            Time of the reference view; default the middle of the events' span,
            ``(t_first + t_last) // 2``.

        Returns
        -------
        DSI
        """
        start = time.perf_counter()
        events = self._check_events(events)
        hot = no_pixels()
        if self.hot_pixels is not None:
            events, hot = self.hot_pixels.apply(events)
        times, T_w_c = as_trajectory(poses)
        if self.camera.rectification is not None:   # the DSI's view is the rectified camera: T_w_rect = T_w_c [R^T | 0]
            T_c_rect = np.eye(4)
            T_c_rect[:3, :3] = self.camera.rectification.T
            T_w_c = T_w_c @ T_c_rect
        t = events.t
        check_coverage(times, int(t[0]), int(t[-1]))
        t_ref_us = (int(t[0]) + int(t[-1])) // 2 if t_ref_us is None else int(t_ref_us)
        T_w_ref = interpolate_poses(times, T_w_c, np.array([t_ref_us]))[0]
        K = self.camera.pinhole_K
        depths = self.depths
        starts, packet_t = _packets(t, self.events_per_pose)
        T_ref_c = invert_pose(T_w_ref) @ interpolate_poses(times, T_w_c, packet_t)
        centres = T_ref_c[:, :3, 3]
        parallax_px = _parallax_px(centres, self.camera, depths)
        inverse = 1.0 / depths
        reach = max(K[0, 0], K[1, 1], K[0, 2], self.camera.width - K[0, 2], K[1, 2], self.camera.height - K[1, 2])
        max_travel = 2.0 * self.transfer_tolerance_px / (reach * 0.5 * (inverse[0] - inverse[-1]))
        groups = _groups(centres, np.diff(starts), self.events_per_transfer, max_travel)
        sizes = np.diff(starts)
        first = np.array([j for j, _ in groups])
        weights = np.add.reduceat(sizes, first).astype(np.float64)[:, None]
        transfers = plane_transfers(np.add.reduceat(centres * sizes[:, None], first, axis=0) / weights, depths, K)
        # Every packet maps to its group's base plane: all homographies and projections in one pass each.
        z_base = np.array([depths[transfer.base] if transfer else depths[-1] for transfer in transfers])
        homographies = base_plane_homographies(T_ref_c, np.repeat(z_base, np.diff(np.append(first, len(sizes)))), K)
        votes = np.zeros((len(depths), self.camera.height, self.camera.width), np.float32)
        pending = ShiftedAdditions(votes)
        vote = (partial(gather_votes, subpixel=self.subpixel, pending=pending) if self.voting == "gather"
                else splat_votes)
        voted = 0
        with tqdm(total=len(groups), desc="EMVS", unit="group", disable=not self.progress) as bar:
            for a, b in _blocks(groups, starts, PROJECT_CHUNK_EVENTS):   # projected a block of groups at a time
                j0, m1 = groups[a][0], groups[b - 1][1]
                lo = starts[j0]
                pixels = self.camera.undistort(events[lo: starts[m1]])
                positions, hits = project_packets(pixels, homographies[j0:m1], sizes[j0:m1])
                hits &= np.isfinite(pixels).all(axis=1)    # NaN: a pixel the distortion model has no inverse for
                del pixels
                for (j, m), transfer in zip(groups[a:b], transfers[a:b]):
                    bar.update(1)
                    if transfer is None:
                        continue
                    group, group_hits = positions[starts[j] - lo: starts[m] - lo], hits[starts[j] - lo: starts[m] - lo]
                    if not group_hits.all():
                        group = group[group_hits]
                    voted += len(group)
                    vote(votes, group, transfer)
        pending.flush()
        return DSI(votes, depths, K.copy(), t_ref_us, T_w_ref, voted, time.perf_counter() - start,
                   parallax_px=parallax_px, hot_pixels=hot)

    def run(self, events: Events, poses: object, *, t_ref_us: int | None = None) -> SemiDenseDepth:
        """Semi-dense depth of the reference view from events and camera poses.

        Parameters
        ----------
        events : Events
            Non-empty, from the camera's sensor.
        poses : (times_us (M,), T_w_c (M, 4, 4)) or object with ``times_us`` and ``poses``
            Camera-to-world trajectory covering the events' time span [µs]
            (e.g. ground truth, :func:`cmax.emvs.read_tum_trajectory`, or
            :func:`cmax.fit_sequence`'s result).
        t_ref_us : int, optional
            Time of the reference view; default ``(t_first + t_last) // 2``.

        Returns
        -------
        SemiDenseDepth
        """
        start = time.perf_counter()
        dsi = self.dsi(events, poses, t_ref_us=t_ref_us)
        return semi_dense_depth(dsi, threshold_kernel=self.threshold_kernel, threshold_c=self.threshold_c,
                                median_size=self.median_size, seconds=time.perf_counter() - start)
