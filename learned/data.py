"""Training windows from event files: event volume, raw events for the contrast loss, ground truth, K.

A window is a :class:`Sample` (numpy): its events (:class:`cmax.Events`), the
intrinsics, and where known the z-depth at the window's middle and its twist.
Augmentations are pure functions ``Sample -> Sample`` (horizontal flip with
``cx`` mirrored and the twist mirrored, polarity flip, time reversal with the
twist negated); :func:`to_item` turns a sample into the tensors of one batch
entry (the event volume computed after augmentation). Datasets:

* :class:`H5WindowDataset` — DSEC-layout files (:class:`cmax.io.H5Reader`). Files made by
  ``cmax scene`` carry ``gt/``: windows are centred on the ground-truth depth times and
  hold that depth and the twist at the middle; files without ``gt/`` (``cmax simulate``)
  are cut into consecutive windows and need ``K`` from the caller.
* :class:`MVSECDataset` — MVSEC ``*_data.hdf5`` files (:func:`cmax.io.mvsec.read_mvsec`),
  optionally with the ``*_gt.hdf5`` depth (``davis/left/depth_image_rect`` and ``_ts``).
"""
from __future__ import annotations

import json
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Sequence

import h5py
import numpy as np
import torch

from cmax.camera import nearest_pixels
from cmax.events import Events
from cmax.fitting.window import SensorPixels
from cmax.io import FormatError, H5Reader, read_calibration
from cmax.io.calibration import DSEC_RECTIFY_MAP, topic_side
from cmax.io.provenance import check_calibrated_frames, check_raw_dsec, resized_note
from cmax.representations import voxel_grid
from cmax.warp import WarpEvents

if TYPE_CHECKING:
    from cmax.camera import Camera

__all__ = ["MAX_OPEN_FILES", "Sample", "flip_horizontal", "flip_polarity", "reverse_time", "augment", "to_item", "collate",
           "H5WindowDataset", "MVSECDataset", "FileSpec", "reaches_beyond", "longest_centred_window_us", "check_twists",
           "check_ground_truth_layout"]


#: Files an :class:`H5WindowDataset` keeps open at once, the least recently read closed first: each open file
#: holds a descriptor and h5py's chunk caches (about 4 MB), in every DataLoader worker; a file opened again
#: costs its opening and the decompression of its window's chunks once more.
MAX_OPEN_FILES = 64


@dataclass(frozen=True, eq=False)
class Sample:
    """One window.

    Attributes
    ----------
    events : Events
        Sorted events; times in µs.
    K : ndarray (3, 3)
    depth : ndarray (H, W) float32 or None
        z-depth [m] at the middle of ``[t0_us, t1_us]`` (NaN unknown).
    twist : ndarray (6,) or None
        ``(v [m/s], omega [rad/s])`` at the middle, camera frame.
    t0_us, t1_us : int
        Window bounds [µs].
    speed : float or None
        Known camera speed ``|v|`` [m/s] at the middle (the contrast loss's metric anchor), also where the
        twist is hidden; None: ``|v|`` of ``twist`` when it is given, else unknown.
    pixels : ndarray (N, 2) float64 or None
        The exact sub-pixel positions ``(x, y)`` [px of ``K``] of ``events`` (undistorted and rectified:
        :meth:`cmax.Camera.undistorted_pixels`), row for row; None: the events' own integer pixels.
    sensor : SensorPixels or None
        Through a lens (or DSEC's rectify map): each event's sensor pixel (N, 2) [px], row for row, and what maps a
        sensor position to the pixels of ``K`` (:class:`cmax.fitting.window.SensorPixels`, :func:`to_item`'s
        ``sensor``); None: the events were recorded at their pixels.
    """

    events: Events
    K: np.ndarray
    depth: np.ndarray | None
    twist: np.ndarray | None
    t0_us: int
    t1_us: int
    speed: float | None = None
    pixels: np.ndarray | None = None
    sensor: SensorPixels | None = None

    @property
    def known_speed(self) -> float:
        """``speed``, else ``|v|`` of the twist, else NaN [m/s] (unchanged by every augmentation)."""
        if self.speed is not None:
            return float(self.speed)
        return float(np.linalg.norm(self.twist[:3])) if self.twist is not None else float("nan")


#: Reflection of the camera frame by x -> -x: v -> S v, omega -> det(S) S omega (a pseudo-vector).
_MIRROR_V = np.array([-1.0, 1.0, 1.0])
_MIRROR_OMEGA = np.array([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class _Mirrored:
    """The lens ``lens`` (an object with ``undistort_points``, e.g. a :class:`cmax.Camera`) of a ``width`` [px]
    sensor seen in a mirror: x -> width-1-x before and after it (:func:`flip_horizontal`)."""

    lens: object
    width: int

    def undistort_points(self, points: np.ndarray) -> np.ndarray:
        """The mirrored lens's pixels (M, 2) [px] of the mirrored sensor's positions ``points`` (M, 2) [px]."""
        points = np.array(points, dtype=np.float64)
        points[:, 0] = self.width - 1 - points[:, 0]
        mapped = np.array(self.lens.undistort_points(points), dtype=np.float64)
        mapped[:, 0] = self.width - 1 - mapped[:, 0]
        return mapped


@dataclass(frozen=True, eq=False)
class _MapLens:
    """DSEC's ``rectify_map`` (H, W, 2) [px] as a lens: ``undistort_points`` interpolates it bilinearly between
    the pixel centres (linearly extrapolated from the border cells), so that a position on a sensor pixel's
    centre gets the map's value there exactly."""

    table: np.ndarray

    def undistort_points(self, points: np.ndarray) -> np.ndarray:
        """The rectified positions (M, 2) float64 [px] of sensor positions ``points`` (M, 2) [px]."""
        points = np.asarray(points, dtype=np.float64)
        H, W = self.table.shape[:2]
        out = np.zeros((len(points), 2))
        corners = []
        for axis, size in ((0, W), (1, H)):
            low = np.clip(np.floor(points[:, axis]), 0, max(size - 2, 0)).astype(np.int64)
            high = np.minimum(low + 1, size - 1)
            frac = points[:, axis] - low
            corners.append(((low, 1.0 - frac), (high, frac)))
        for x, wx in corners[0]:
            for y, wy in corners[1]:
                weight = (wx * wy)[:, None]
                out += np.where(weight != 0, weight * self.table[y, x], 0.0)   # a centre reads its pixel alone
        return out


def flip_horizontal(sample: Sample) -> Sample:
    """Mirror ``sample`` left-right: ``x -> W-1-x``, ``cx -> W-1-cx``, depth flipped, twist mirrored (vx, wy, wz negated)."""
    ev = sample.events
    events = Events(ev.width - 1 - ev.x.astype(np.int64), ev.y, ev.t, ev.p, ev.width, ev.height,
                    time_unit="us")
    K = sample.K.copy()
    K[0, 2] = ev.width - 1 - K[0, 2]
    K[0, 1] = -K[0, 1]
    twist = None if sample.twist is None else sample.twist * np.r_[_MIRROR_V, _MIRROR_OMEGA]
    depth = None if sample.depth is None else np.ascontiguousarray(sample.depth[:, ::-1])
    pixels = None if sample.pixels is None else np.column_stack([ev.width - 1 - sample.pixels[:, 0],
                                                                 sample.pixels[:, 1]])
    sensor = sample.sensor
    if sensor is not None:   # the mirrored sensor seen through the mirrored lens: each event keeps its position
        lens = sensor.camera.lens if isinstance(sensor.camera, _Mirrored) else _Mirrored(sensor.camera, ev.width)
        sensor = SensorPixels(np.column_stack([ev.width - 1 - sensor.pixels[:, 0], sensor.pixels[:, 1]]), lens)
    return replace(sample, events=events, K=K, depth=depth, twist=twist, pixels=pixels, sensor=sensor)


def flip_polarity(sample: Sample) -> Sample:
    """Swap ON and OFF of ``sample`` (geometry and ground truth unchanged)."""
    ev = sample.events
    return replace(sample, events=Events(ev.x, ev.y, ev.t, 1 - ev.p, ev.width, ev.height, time_unit="us"))


def reverse_time(sample: Sample) -> Sample:
    """Play the window ``sample`` backwards: ``t -> t0 + t1 - t``, order reversed, polarity swapped, twist negated.

    Valid because the depth belongs to the window's middle, which stays in place.
    """
    ev = sample.events
    t = (sample.t0_us + sample.t1_us) - ev.t[::-1]
    events = Events(ev.x[::-1], ev.y[::-1], t, 1 - ev.p[::-1], ev.width, ev.height, time_unit="us")
    pixels = None if sample.pixels is None else np.ascontiguousarray(sample.pixels[::-1])
    sensor = None if sample.sensor is None else SensorPixels(np.ascontiguousarray(sample.sensor.pixels[::-1]),
                                                             sample.sensor.camera)
    return replace(sample, events=events, twist=None if sample.twist is None else -sample.twist, pixels=pixels,
                   sensor=sensor)


def augment(sample: Sample, rng: np.random.Generator, *, flip: bool = True, polarity: bool = True,
            time_reversal: bool = True) -> Sample:
    """Each enabled augmentation of ``sample`` (``flip``: :func:`flip_horizontal`, ``polarity``: :func:`flip_polarity`,
    ``time_reversal``: :func:`reverse_time`) with probability 1/2 (draws from ``rng`` in a fixed order)."""
    draws = rng.random(3)
    if flip and draws[0] < 0.5:
        sample = flip_horizontal(sample)
    if polarity and draws[1] < 0.5:
        sample = flip_polarity(sample)
    if time_reversal and draws[2] < 0.5:
        sample = reverse_time(sample)
    return sample


def to_item(sample: Sample, *, max_events: int, bins: int = 5, seed: int = 0,
            pixels: np.ndarray | None = None, sensor: SensorPixels | None = None) -> dict[str, torch.Tensor]:
    """Tensors of one batch entry from ``sample`` (``seed``: of the event subset and its dither; ``pixels``
    (N, 2) float64 [px], optional: the events' exact sub-pixel positions, e.g. undistorted and rectified ones
    (:meth:`cmax.Camera.undistorted_pixels`), from which the volume spreads each event bilinearly over 4 pixels:
    ``cmax.representations.voxel_grid(..., pixels=)``; ``sensor``, optional, for events undistorted by a lens
    (``sample.events`` at their nearest undistorted pixels, ``sample.K`` the camera's ``pinhole_K``): each
    event's sensor pixel (N, 2) [px] and the :class:`cmax.Camera` (:class:`cmax.fitting.window.SensorPixels`,
    :func:`cmax.camera.sensor_pixels`; or another lens with its ``undistort_points``: :class:`Sample`'s ``sensor``
    of :class:`H5WindowDataset`, augmented), so that the contrast loss's events are dithered over their sensor pixels
    and mapped through the lens, unrounded, as :func:`cmax.fit` and ``cmax.contrast.EventWindows.from_events(
    events, camera)`` take them; without it they are dithered around the events' integer pixels).

    Returns
    -------
    dict
        ``volume`` (bins, H, W) float32; ``x, y, t, polarity`` (max_events,) float32 padded,
        ``valid`` (max_events,) bool (the raw events for the contrast loss: a seeded uniform
        subset of at most ``max_events``, dithered (through the lens with ``sensor``), t in seconds since the
        first event);
        ``duration_s`` () float32; ``K`` (3, 3) float32; ``speed`` () float32 [m/s] (NaN: unknown); ``inverse_depth`` (1, H, W) float32
        (0 where unknown), ``depth_mask`` (1, H, W) bool; ``twist`` (6,) float32 and
        ``has_twist`` () bool.
    """
    ev = sample.events
    if len(ev) < 2:
        raise ValueError(f"the window [{sample.t0_us}, {sample.t1_us}) µs holds {len(ev)} events; need >= 2")
    lens = {}
    if sensor is not None:
        if not isinstance(sensor, SensorPixels):
            raise TypeError(f"sensor must be a cmax.fitting.window.SensorPixels or None, got {type(sensor).__name__}")
        if np.shape(sensor.pixels) != (len(ev), 2):
            raise ValueError(f"sensor.pixels must be ({len(ev)}, 2), one sensor pixel per event of the window, got "
                             f"{np.shape(sensor.pixels)}")
        lens = dict(pixels=sensor.pixels, lens=sensor.camera.undistort_points)
    volume = torch.from_numpy(voxel_grid(ev, bins, pixels=pixels))
    prepared = WarpEvents.from_events(ev, sample.K, max_events=max_events, seed=seed, **lens)
    n = len(prepared)
    pad = lambda a: torch.cat([a, a.new_zeros(max_events - n)])  # noqa: E731
    H, W = ev.height, ev.width
    if sample.depth is not None:
        depth = np.asarray(sample.depth, np.float32)
        mask = np.isfinite(depth) & (depth > 0)
        inverse = np.where(mask, 1.0 / np.where(mask, depth, 1.0), 0.0).astype(np.float32)
    else:
        mask, inverse = np.zeros((H, W), bool), np.zeros((H, W), np.float32)
    return {
        "volume": volume, "x": pad(prepared.x), "y": pad(prepared.y), "t": pad(prepared.t),
        "polarity": pad(prepared.polarity), "valid": torch.arange(max_events) < n,
        "duration_s": torch.tensor(prepared.duration_s, dtype=torch.float32),
        "K": torch.as_tensor(sample.K, dtype=torch.float32),
        "speed": torch.tensor(sample.known_speed, dtype=torch.float32),
        "inverse_depth": torch.from_numpy(inverse)[None], "depth_mask": torch.from_numpy(mask)[None],
        "twist": torch.as_tensor(sample.twist if sample.twist is not None else np.zeros(6), dtype=torch.float32),
        "has_twist": torch.tensor(sample.twist is not None),
    }


def collate(items: Sequence[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    """Stack ``items``, entries of :func:`to_item` (all of one sensor size and ``max_events``), into (B, ...) tensors (e.g. ``volume`` (B, bins, H, W))."""
    return {key: torch.stack([item[key] for item in items]) for key in items[0]}


@dataclass(frozen=True)
class FileSpec:
    """An event file at ``path`` and how to read it: ``K`` (3, 3) for files without ``gt/K``.

    ``use_gt`` False hides the ground truth (depth, poses) of ``gt/``; its ``gt/K`` (the
    calibration) is still used when no ``K`` is given. With the ground truth used, a ``K`` other than the
    file's ``gt/K`` (in whose camera that truth was made) is refused. ``known_speed`` (with ``use_gt`` False) keeps
    the camera speed ``|v|`` of each window (what odometry or a speedometer would give a real
    recording) as the contrast loss's metric anchor; the depth and the twist stay hidden.
    ``known_twist`` (with ``use_gt`` False; an ablation: the motion known, the depth hidden) keeps the
    whole twist of each window. ``polarity``: the encoding of the file's ``events/p``, ``"01"`` (0 OFF, 1 ON, as
    cmax writes it) or ``"signed"`` (-1 OFF, +1 ON), never guessed (:class:`cmax.io.H5Reader`).

    ``calib``: a calibration file (:func:`cmax.io.read_calibration`: a DSEC ``cam_to_cam.yaml``, a Kalibr
    camchain, ...) of the camera ``calib_camera`` that recorded the events: each window's events are undistorted
    (and rectified, for DSEC's raw ``cam0``: into ``camRect0``'s frame, that of its disparity maps and
    ``rectify_map.h5``) as ``cmax depth --calib`` maps them; the volume spreads each event bilinearly from its exact
    position, and ``K`` is that frame's (an entry's ``K`` must equal it). Its resolution gives the size of a file
    that stores none (DSEC's ``events.h5``). ``rectify_map`` instead: DSEC's ``rectify_map.h5`` of the events, its
    ``rectify_map`` (H, W, 2) the rectified position [px] of each raw pixel, looked up as DSEC's loaders do (the entry
    gives the rectified frame's ``K``, ``camRect0``'s; the map's shape gives the size). Events beside DSEC's
    ``rectify_map.h5`` (raw) without either are refused unless ``as_recorded`` says they are wanted as they are.
    """

    path: Path
    K: np.ndarray | None = None
    use_gt: bool = True
    known_speed: bool = False
    known_twist: bool = False
    polarity: str = "01"
    calib: Path | None = None
    calib_camera: str = "cam0"
    rectify_map: Path | None = None
    as_recorded: bool = False


def _as_spec(entry: object) -> FileSpec:
    if isinstance(entry, FileSpec):
        return entry
    if isinstance(entry, (str, Path)):
        return FileSpec(Path(entry))
    if isinstance(entry, dict):
        K = entry.get("K")
        if K is not None:   # the principal point is checked once the file's size is known (_file_K)
            from cmax.camera import intrinsics_matrix

            K = intrinsics_matrix(K, f"{entry['path']}: K")
        calib = entry.get("calib")
        return FileSpec(Path(entry["path"]), K, bool(entry.get("use_gt", True)), bool(entry.get("known_speed", False)),
                        bool(entry.get("known_twist", False)), str(entry.get("polarity", "01")),
                        None if calib is None else Path(calib), str(entry.get("calib_camera", "cam0")),
                        None if entry.get("rectify_map") is None else Path(entry["rectify_map"]),
                        bool(entry.get("as_recorded", False)))
    raise TypeError(f"a data file must be a path or {{'path', 'K', 'use_gt'}}, got {entry!r}")


def _mvsec_camera(calib: "str | Path | Camera | None", calib_camera: str, width: int,
                  height: int) -> "Camera | None":
    """The :class:`cmax.Camera` of :class:`MVSECDataset`'s ``calib``: a camchain path read with
    :func:`cmax.io.read_calibration` (camera ``calib_camera``), or a Camera of the ``width`` x
    ``height`` [px] sensor as given; None without one. ValueError naming the file or the size otherwise."""
    from cmax.camera import Camera

    if calib is None:
        return None
    if isinstance(calib, Camera):
        if (calib.width, calib.height) != (width, height):
            raise ValueError(f"calib is a camera of a {calib.width}x{calib.height} sensor; MVSEC's DAVIS is "
                             f"{width}x{height}")
        return calib
    if not isinstance(calib, (str, Path)):
        raise TypeError(f"calib must be a camchain path or a cmax.Camera, got {type(calib).__name__}")
    calibration = read_calibration(calib, calib_camera)
    if topic_side(calibration.topic) == "right":
        raise ValueError(f"{calib}: {calib_camera} is the right camera (rostopic {calibration.topic.strip()}); "
                         "MVSECDataset reads davis/left: choose the left camera with calib_camera (MVSEC: cam0)")
    if calibration.size is not None and tuple(calibration.size) != (width, height):
        raise ValueError(f"{calib} calibrates a {calibration.size[0]}x{calibration.size[1]} camera ({calib_camera}); "
                         f"MVSEC's DAVIS is {width}x{height}")
    return calibration.camera(width, height)


def _file_K(K: object, path: Path, width: int, height: int) -> np.ndarray:
    """The checked (3, 3) float64 ``K`` [px] of the ``width`` x ``height`` event file ``path``: ValueError naming
    the file for a matrix that is no camera's (a focal length <= 0) or whose principal point lies outside the
    sensor (another sensor size's K, e.g. the calibration of frames that ``cmax simulate --size`` resized)."""
    from cmax.camera import check_principal_point, intrinsics_matrix

    matrix = intrinsics_matrix(K, f"{path}: K")
    check_principal_point(matrix, width, height, f"{path}: K")
    return matrix


def reaches_beyond(t0_us: int, window_us: int, t_start_us: int, t_end_us: int) -> bool:
    """Whether the window ``[t0_us, t0_us + window_us)`` reaches further beyond the events ``[t_start_us,
    t_end_us]`` of its recording than a tenth of its length (the slack :class:`H5WindowDataset` allows): such a
    window is left out.

    >>> reaches_beyond(-10_000, 100_000, 0, 200_000), reaches_beyond(-20_000, 100_000, 0, 200_000)
    (False, True)
    """
    slack = window_us // 10
    return t0_us < t_start_us - slack or t0_us + window_us > t_end_us + 1 + slack


def longest_centred_window_us(centre_us: int, t_start_us: int, t_end_us: int) -> int:
    """The longest window [µs] centred on ``centre_us`` (as a labelled window is, on its ``gt/depth_t``) that does
    not :func:`reach beyond <reaches_beyond>` the events ``[t_start_us, t_end_us]``; 0 when none does (a centre at
    or outside an end of the recording).

    >>> longest_centred_window_us(50_000, 0, 1_000_000), longest_centred_window_us(0, 1_970, 249_995)
    (125001, 0)
    """
    room = min(centre_us - t_start_us, t_end_us + 1 - centre_us)
    if room <= 0:
        return 0
    window = int(2.5 * room) + 4   # half a window less its tenth: 0.4 w <= room, give or take the rounding
    while window > 0 and reaches_beyond(centre_us - window // 2, window, t_start_us, t_end_us):
        window -= 1
    return window


def _training_file(path: Path, polarity: str = "01", size: tuple[int, int] | None = None) -> H5Reader:
    """``H5Reader(path, polarity=polarity)``, of the sensor ``size`` (width, height) [px] (a calibration's) when the
    file stores none (DSEC's own ``events.h5``); a file it cannot read as DSEC-layout h5 (a ``.raw``, ``.aedat4``,
    ``.npy``, ...) is refused with the one-line conversion that makes it one."""
    if Path(path).is_dir():   # the reader said "no such event file" of a folder that exists
        found = sorted(Path(path).glob("*.h5"))
        listed = (f": the {len(found)} .h5 files in it are data.files="
                  f"{json.dumps([str(p) for p in found[:3]] + (['...'] if len(found) > 3 else []))}" if found
                  else " (it holds no .h5 file)")
        raise ValueError(f"{path} is a folder, not an event file: data.files lists h5 files one by one{listed}")
    try:
        return H5Reader(path, polarity=polarity)
    except FormatError as error:
        if size is not None and "stores no sensor size" in str(error):
            return H5Reader(path, polarity=polarity, width=size[0], height=size[1])
        dsec = ("stores no sensor size" in str(error)) * (
            "; DSEC's own events.h5: give its calibration in its entry instead, \"calib\": \"<sequence>/calibration/"
            "cam_to_cam.yaml\" (its size, and the raw events rectified into camRect0's frame)")
        raise FormatError(f"{error}; training reads DSEC-layout h5 files: convert it once with "
                          f"cmax.io.write_h5('events.h5', cmax.io.read('{path}'[, width=, height=])) and give its K "
                          f"in data.files{dsec}") from None


def _entry_calibration(spec: FileSpec):
    """The :class:`cmax.io.Calibration` of ``spec.calib`` (camera ``spec.calib_camera``), None without one.
    ValueError naming the file: a DSEC rectified camera ``camRectN`` (events taken as already rectified) for events
    beside DSEC's ``rectify_map.h5`` (raw ones)."""
    if spec.calib is None:
        return None
    calibration = read_calibration(spec.calib, spec.calib_camera)
    camera = spec.calib_camera
    if camera.startswith("camRect") and calibration.distortion is None and \
            (spec.path.parent / DSEC_RECTIFY_MAP).is_file():
        raise ValueError(f"{spec.path}: its entry's calib_camera {camera} of {spec.calib} is the rectified camera, but "
                         f"{spec.path.parent / DSEC_RECTIFY_MAP} lies beside it: DSEC's events are raw (distorted, not "
                         f"rectified); give \"calib_camera\": \"cam{camera[7:]}\" to undistort and rectify them "
                         f"into {camera}'s frame")
    return calibration


def _calibrated_camera(spec: FileSpec, calibration, width: int, height: int) -> "Camera":
    """The :class:`cmax.Camera` of ``calibration`` (``spec.calib``'s) on the ``width`` x ``height`` [px] sensor of
    ``spec.path``. ValueError naming the files: a calibration of another sensor size, or an entry's ``K`` other than
    the K of the frame the calibration maps the events into (to 0.01 px: rounded figures are taken); a calibration
    without a size in a sequence of frames of another size (:func:`cmax.io.provenance.check_calibrated_frames`)."""
    if calibration.size is not None and tuple(calibration.size) != (width, height):
        raise ValueError(f"{spec.calib} calibrates a {calibration.size[0]}x{calibration.size[1]} camera "
                         f"({spec.calib_camera}), the events of {spec.path} come from a {width}x{height} sensor")
    if calibration.size is None:
        check_calibrated_frames(spec.calib, spec.path, width, height)
    camera = calibration.camera(width, height)
    pinhole = _file_K(camera.pinhole_K, spec.path, width, height)
    if spec.K is not None and not np.allclose(_file_K(spec.K, spec.path, width, height), pinhole, rtol=0, atol=0.01):
        raise ValueError(f"{spec.path}: its entry gives K {np.asarray(spec.K, float).tolist()}, not the K of the frame "
                         f"its calib {spec.calib} ({spec.calib_camera}) maps the events into ({pinhole.tolist()}): "
                         "leave K out to use it")
    return camera


#: How far [px] the rectified positions of an entry's calibration may lie from those of DSEC's ``rectify_map.h5``
#: beside its events before a warning names both (a calibration of another sequence, or of the other camera).
MAP_DISAGREEMENT_PX = 0.5


def _map_disagreement(spec: FileSpec, camera: "Camera") -> str | None:
    """A warning when DSEC's ``rectify_map.h5`` lies beside ``spec.path`` and its rectified positions differ from
    those ``camera`` (of ``spec.calib``) gives by more than :data:`MAP_DISAGREEMENT_PX` at some pixel; None when they
    agree, or the map is not readable as one of this sensor (an empty file: nothing to compare)."""
    beside = spec.path.parent / DSEC_RECTIFY_MAP
    try:
        with h5py.File(beside, "r") as file:
            table = np.asarray(file["rectify_map"][:], np.float64)
    except (OSError, KeyError):
        return None
    if table.shape != (camera.height, camera.width, 2):
        return None
    difference = np.abs(table - camera.undistortion_map)
    worst = float(np.nanmax(difference)) if np.isfinite(difference).any() else 0.0
    if worst <= MAP_DISAGREEMENT_PX:
        return None
    return (f"{spec.path}: its calib {spec.calib} ({spec.calib_camera}) rectifies its events up to {worst:.2f} px "
            f"away from where {beside} beside them puts them: a calibration of another sequence or camera? The "
            "calibration's positions are used")


def _mapped(events: Events, table: np.ndarray) -> tuple[Events, np.ndarray, SensorPixels]:
    """``(events, pixels, sensor)``: ``events`` moved to their positions in ``table`` (H, W, 2) [px] (DSEC's rectify
    map, ``table[y, x]``) rounded to the nearest pixels, those outside the image or without a finite position dropped,
    the exact positions (M, 2) float64 [px] of those kept, and their sensor pixels with the map as their lens
    (bilinear between pixel centres, :class:`_MapLens`)."""
    exact = table[events.y, events.x].astype(np.float64)
    xy, inside = nearest_pixels(exact, events.width, events.height)
    return (Events(xy[inside, 0], xy[inside, 1], events.t[inside], events.p[inside], events.width, events.height,
                   time_unit="us"),
            exact[inside], SensorPixels(np.column_stack([events.x[inside], events.y[inside]]), _MapLens(table)))


def _through_lens(camera: "Camera", events: Events) -> tuple[Events, np.ndarray, SensorPixels | None]:
    """``(events, pixels, sensor)`` of ``events`` seen through ``camera``'s lens: at their nearest undistorted (and
    rectified) pixels, those outside the image dropped; their exact positions (M, 2) float64 [px]; and their sensor
    pixels with the camera (:class:`Sample`'s ``sensor``; None for a pinhole camera)
    (:meth:`cmax.Camera.undistort_events_and_pixels`: the lens's pixels found once)."""
    undistorted, pixels, kept = camera.undistort_events_and_pixels(events)
    sensor = None if camera.is_pinhole else SensorPixels(np.column_stack([events.x[kept], events.y[kept]]), camera)
    return undistorted, pixels, sensor


def _refuse_raw_dsec(spec: FileSpec) -> None:
    """ValueError naming ``spec.path`` when DSEC's ``rectify_map.h5`` lies beside it and its entry gives neither
    ``calib`` nor ``rectify_map`` nor ``as_recorded``: raw (distorted, unrectified) events paired with a K of
    another frame (DSEC's ``camRect0``, of its disparity maps) or of none (:func:`cmax.io.provenance.check_raw_dsec`,
    the policy of the command line too)."""
    if spec.calib is None and spec.rectify_map is None and not spec.as_recorded:
        check_raw_dsec(spec.path, 'add "calib": "{calib}" to its data.files entry (calib_camera cam0, the default) '
                                  '(or "rectify_map": "{map}" with camRect0\'s "K")',
                       '"as_recorded": true in the entry')


def _read_rectify_map(spec: FileSpec) -> np.ndarray | None:
    """The ``rectify_map`` (H, W, 2) float32 [px of the rectified frame] of ``spec.rectify_map`` (DSEC's
    ``rectify_map.h5``: the rectified position of each raw pixel), None without one. ValueError naming the file for
    one that is not such a map."""
    if spec.rectify_map is None:
        return None
    try:
        with h5py.File(spec.rectify_map, "r") as file:
            table = np.asarray(file["rectify_map"][:], np.float32) if "rectify_map" in file else None
    except OSError as error:
        raise ValueError(f"{spec.rectify_map} (rectify_map of {spec.path}'s entry) is not DSEC's rectify_map.h5: "
                         f"{error}") from None
    if table is None or table.ndim != 3 or table.shape[2] != 2 or 0 in table.shape:
        shape = None if table is None else table.shape
        raise ValueError(f"{spec.rectify_map} (rectify_map of {spec.path}'s entry) must hold rectify_map, (height, "
                         f"width, 2) [px], as DSEC's rectify_map.h5 does; got {'none' if shape is None else shape}")
    return table


@contextmanager
def _polarity_hint(spec: FileSpec) -> Iterator[None]:
    """Reword the reader's refusal of a polarity encoding other than ``spec.polarity`` (it advises the reader's
    ``polarity=`` argument) with the key of ``data.files`` that states it."""
    try:
        yield
    except FormatError as error:
        if "polarity values" not in str(error) or "pass polarity=" not in str(error):
            raise
        other = "01" if spec.polarity == "signed" else "signed"
        raise FormatError(f"{spec.path}: its events/p holds the polarities {'0/1' if other == '01' else '-1/+1'}, "
                          f"not the \"{spec.polarity}\" encoding its data.files entry states: add \"polarity\": "
                          f"\"{other}\" to its entry ({{\"path\": \"{spec.path}\", \"polarity\": \"{other}\", ...}})"
                          ) from None


def check_twists(path: str | Path, poses_t: np.ndarray, twists: np.ndarray) -> None:
    """Refuse (ValueError naming the file at ``path``) ``gt/twists`` that are not one finite ``(v m/s, omega
    rad/s)`` (6,) per time of ``gt/poses_t`` (M,) µs: a NaN there made the teacher's loss NaN at the first step
    that drew its window, reported as a diverged run.

    >>> import numpy as np
    >>> check_twists("a.h5", np.arange(2), np.zeros((2, 6)))
    >>> try:
    ...     check_twists("a.h5", np.arange(2), np.array([[0.0] * 6, [np.nan] * 6]))
    ... except ValueError as error:
    ...     print(str(error)[:61])
    a.h5: gt/twists holds NaN or infinite values in 1 of its 2 ro
    """
    twists, poses_t = np.asarray(twists), np.asarray(poses_t)
    if twists.ndim != 2 or twists.shape[1] != 6 or poses_t.shape != (len(twists),):
        raise ValueError(f"{path}: gt/twists must be (M, 6), one (v m/s, omega rad/s) per time of gt/poses_t (M,), "
                         f"got gt/twists {twists.shape} and gt/poses_t {poses_t.shape}")
    bad = np.flatnonzero(~np.isfinite(twists).all(axis=1)) if twists.dtype.kind in "fc" else np.empty(0, int)
    if len(bad):
        raise ValueError(f"{path}: gt/twists holds NaN or infinite values in {len(bad)} of its {len(twists)} rows "
                         f"(row {bad[0]}: {twists[bad[0]].tolist()}, at gt/poses_t {poses_t[bad[0]]} µs): the "
                         "teacher's twist term and the motion metrics need a finite twist (v m/s, omega rad/s) at "
                         "every pose time; repair those rows, or drop gt/twists and gt/poses_t (depth alone)")


def check_ground_truth_layout(path: str | Path, depth_shape: tuple[int, ...], depth_t: np.ndarray, width: int,
                              height: int, poses_t: np.ndarray | None = None, twists: np.ndarray | None = None
                              ) -> None:
    """Refuse (ValueError naming the file at ``path``) ground truth whose parts do not fit each other: ``gt/depth``
    of shape ``depth_shape`` must be (D, ``height``, ``width``), one depth map [m] of the sensor per time of
    ``depth_t`` (D,) µs (a map missing was an IndexError when its window was read), and ``twists`` (M, 6) one
    finite twist per time of ``poses_t`` (M,) µs (:func:`check_twists`; None: the file stores no twists).

    >>> import numpy as np
    >>> check_ground_truth_layout("a.h5", (3, 36, 48), np.arange(3), 48, 36)
    >>> try:
    ...     check_ground_truth_layout("a.h5", (2, 36, 48), np.arange(3), 48, 36)
    ... except ValueError as error:
    ...     print(str(error)[:62])
    a.h5: gt/depth holds 2 depth maps, gt/depth_t 3 times: each ti
    """
    depth_t = np.asarray(depth_t)
    if len(depth_shape) != 3 or depth_t.shape != (depth_shape[0],):
        count = f"{depth_shape[0]} depth maps" if len(depth_shape) == 3 else f"an array of shape {tuple(depth_shape)}"
        raise ValueError(f"{path}: gt/depth holds {count}, gt/depth_t {depth_t.shape[0] if depth_t.ndim else 1} "
                         "times: each time of gt/depth_t (D,) µs needs its depth map, gt/depth (D, H, W) [m]")
    if tuple(depth_shape[1:]) != (height, width):
        raise ValueError(f"{path}: gt/depth holds maps of {depth_shape[2]}x{depth_shape[1]} pixels, its events come "
                         f"from a {width}x{height} sensor: the depth must be of the events' sensor, "
                         f"gt/depth (D, {height}, {width}) [m]")
    if twists is not None and poses_t is not None:
        check_twists(path, poses_t, twists)


class H5WindowDataset(torch.utils.data.Dataset):
    """Windows of DSEC-layout files (see the module docstring).

    Parameters
    ----------
    files : sequence of path, dict or FileSpec
        ``{"path": ..., "K": [fx, fy, cx, cy] or 3x3, "use_gt": bool}`` for files without ``gt/``; ``"calib"``
        (and ``"calib_camera"``), or ``"rectify_map"`` with the rectified ``"K"``, for raw events to undistort and
        rectify (:class:`FileSpec`): DSEC's ``events.h5``, beside its ``rectify_map.h5``, is refused without one.
    window_us : int
        Window length [µs].
    max_events : int
        Raw events kept per window for the contrast loss.
    bins : int
        Time bins B of each window's event volume (B, H, W).
    augment : bool
        Random flips and time reversal (seeded per epoch and item: see :meth:`set_epoch`).
    seed : int
    min_events : int
        Windows with fewer events are left out of the index (reported by ``skipped``).

    Labelled windows (files with ``gt/``) are centred on the file's ``gt/depth_t``; a window that
    :func:`reaches beyond <reaches_beyond>` its recording is left out too, and reported by ``off_recording``
    (``(file index, centre µs)`` each) with the recordings' event spans in ``spans`` (``(t_start, t_end)`` µs per
    file): the reasons ``learned.train`` gives for a data set without a window. ``counts`` holds each file's
    number of events (with ``spans``, what ``--resume`` compares of a file: :func:`learned.train.file_fingerprint`).
    """

    def __init__(self, files: Sequence[object], *, window_us: int = 166_500, max_events: int = 20_000,
                 bins: int = 5, augment: bool = False, seed: int = 0, min_events: int = 100) -> None:
        if not files:
            raise ValueError("files: need at least one event file")
        if window_us <= 0 or max_events <= 0:
            raise ValueError(f"window_us and max_events must be positive, got {window_us}, {max_events}")
        self.specs = [_as_spec(f) for f in files]
        self.window_us, self.max_events, self.bins = int(window_us), int(max_events), bins
        self.augment, self.seed, self.epoch = augment, seed, 0
        self.index: list[tuple[int, int]] = []
        self._gt: list[dict | None] = []
        self._known_motion: list[tuple[np.ndarray, np.ndarray] | None] = []
        self.skipped, self.min_events = 0, int(min_events)
        self.off_recording: list[tuple[int, int]] = []
        self.spans: list[tuple[int, int]] = []
        self.counts: list[int] = []
        self._readers: dict[int, H5Reader] = {}
        self._cameras: list[Camera | None] = []
        self._tables: list[np.ndarray | None] = []
        self._sizes: list[tuple[int, int] | None] = []
        size = None
        for i, spec in enumerate(self.specs):
            _refuse_raw_dsec(spec)
            calibration, table = _entry_calibration(spec), _read_rectify_map(spec)
            calib_size = None if calibration is None or calibration.size is None else tuple(calibration.size)
            calib_size = (table.shape[1], table.shape[0]) if table is not None else calib_size
            with _training_file(spec.path, spec.polarity, calib_size) as reader, _polarity_hint(spec):
                if size is None:
                    size = (reader.width, reader.height)
                elif size != (reader.width, reader.height):
                    raise ValueError(f"{spec.path} is {reader.width}x{reader.height}, the first file {size[0]}x{size[1]}")
                self._sizes.append(None if calib_size is None else (reader.width, reader.height))
                if table is not None and table.shape[:2] != (reader.height, reader.width):
                    raise ValueError(f"{spec.rectify_map} maps a {table.shape[1]}x{table.shape[0]} sensor, the events "
                                     f"of {spec.path} come from a {reader.width}x{reader.height} one")
                self._tables.append(table)
                self._cameras.append(None if calibration is None else
                                     _calibrated_camera(spec, calibration, reader.width, reader.height))
                if calibration is not None:
                    spec = self.specs[i] = replace(spec, K=self._cameras[i].pinhole_K)
                    if (disagreement := _map_disagreement(spec, self._cameras[i])) is not None:
                        warnings.warn(disagreement, UserWarning, stacklevel=2)
                gt = self._load_gt(reader.file, spec, reader.width, reader.height)
                if gt is not None and spec.K is not None and not np.allclose(spec.K, gt["K"], rtol=1e-6, atol=1e-9):
                    raise ValueError(f"{spec.path}: its entry gives K {np.asarray(spec.K).tolist()}, but its ground "
                                     f"truth (gt/depth, gt/twists) was made with its gt/K {gt['K'].tolist()}: drop "
                                     f"the entry's K, or read the file with \"use_gt\": false to use your K")
                if spec.K is None and gt is None and "gt/K" in reader.file:   # calibration, not ground truth
                    spec = self.specs[i] = replace(spec, K=reader.file["gt/K"][:])
                if spec.K is not None:   # another sensor size's K (a calibration of frames simulated at --size)
                    spec = self.specs[i] = replace(spec, K=_file_K(spec.K, spec.path, reader.width, reader.height))
                self._gt.append(gt)
                self.spans.append((int(reader.t_start), int(reader.t_end)))
                self.counts.append(len(reader))
                self._known_motion.append(self._load_known_motion(reader.file, spec))
                if gt is not None:
                    starts = [int(t) - self.window_us // 2 for t in gt["depth_t"]]
                elif spec.K is None:
                    note = resized_note(spec.path)   # a conversion at --size: how its frames' K scales
                    raise ValueError(f"{spec.path} has no gt/K: give its intrinsics in its entry of the config's "
                                     f"data.files, e.g. 'data.files=[{{\"path\": \"{spec.path}\", "
                                     f"\"K\": [fx, fy, cx, cy]}}]'" + (f"; {note}" if note else ""))
                else:
                    starts = list(range(reader.t_start, reader.t_end - self.window_us + 1, self.window_us))
                for t0 in starts:   # windows may reach 10% beyond the recorded events
                    if reaches_beyond(t0, self.window_us, reader.t_start, reader.t_end):   # labelled ones only
                        self.off_recording.append((i, t0 + self.window_us // 2))
                        continue
                    if len(reader.window(t0, t0 + self.window_us)) < min_events:
                        self.skipped += 1
                        continue
                    self.index.append((i, t0))
        self.width, self.height = size

    @staticmethod
    def _load_gt(file: h5py.File, spec: FileSpec, width: int, height: int) -> dict | None:
        """The ground truth of ``gt/``: ``depth_t`` (D,) µs, ``K`` (3, 3), and ``twists`` (M, 6) with their
        ``poses_t`` (M,) µs, or None for those when the file stores no twists; None for a file without depth
        (no ``gt/depth`` or ``gt/depth_t``: a ``gt/K`` alone is the calibration). ValueError naming the file for
        a depth without the ``gt/K`` it was made with, and for ground truth whose parts do not fit each other
        (:func:`check_ground_truth_layout`: ``gt/depth`` (D, ``height``, ``width``) [m], finite twists)."""
        if "gt" not in file or not spec.use_gt:
            return None
        gt = file["gt"]
        if "depth" not in gt or "depth_t" not in gt:
            return None
        if "K" not in gt:
            raise ValueError(f"{spec.path} holds gt/depth but no gt/K, the intrinsics that depth was made with: "
                             "add gt/K to the file, or read it with \"use_gt\": false and its K in its data.files "
                             "entry")
        timed = "twists" in gt and "poses_t" in gt
        loaded = {"depth_t": gt["depth_t"][:], "poses_t": gt["poses_t"][:] if timed else None,
                  "twists": gt["twists"][:] if timed else None, "K": gt["K"][:]}
        check_ground_truth_layout(spec.path, gt["depth"].shape, loaded["depth_t"], width, height,
                                  loaded["poses_t"], loaded["twists"])
        return loaded

    @staticmethod
    def _load_known_motion(file: h5py.File, spec: FileSpec) -> tuple[np.ndarray, np.ndarray] | None:
        """``(poses_t (M,) µs, twists (M, 6))`` of a file whose speed (or twist) is known although its ground
        truth is hidden."""
        if spec.use_gt or not (spec.known_speed or spec.known_twist):
            return None
        if "gt/twists" not in file or "gt/poses_t" not in file:
            raise ValueError(f"{spec.path}: known_speed needs gt/twists and gt/poses_t in the file")
        poses_t, twists = file["gt/poses_t"][:], file["gt/twists"][:]
        check_twists(spec.path, poses_t, twists)
        return poses_t, twists

    def set_epoch(self, epoch: int) -> None:
        """Change the augmentation draws (called by the trainer each epoch)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.index)

    def sample(self, i: int) -> Sample:
        """The window ``i`` without augmentation."""
        file_index, t0 = self.index[i]
        spec, gt = self.specs[file_index], self._gt[file_index]
        reader = self._reader(file_index)
        events, pixels, sensor = self._rectified(file_index, reader.window(t0, t0 + self.window_us))
        if gt is None:
            speed = twist = None
            if self._known_motion[file_index] is not None:
                times, twists = self._known_motion[file_index]
                middle = twists[int(np.argmin(np.abs(times - (t0 + self.window_us // 2))))]
                speed = float(np.linalg.norm(middle[:3]))
                twist = middle.copy() if spec.known_twist else None
            return Sample(events, spec.K, None, twist, t0, t0 + self.window_us, speed, pixels, sensor)
        middle = t0 + self.window_us // 2
        k = int(np.argmin(np.abs(gt["depth_t"] - middle)))
        depth = reader.file["gt/depth"][k]
        twist = None
        if gt["twists"] is not None:
            twist = gt["twists"][int(np.argmin(np.abs(gt["poses_t"] - middle)))]
        return Sample(events, gt["K"], depth, twist, t0, t0 + self.window_us, pixels=pixels, sensor=sensor)

    def _rectified(self, file_index: int, events: Events) -> tuple[Events, np.ndarray | None, SensorPixels | None]:
        """``(events, pixels, sensor)`` of a window of file ``file_index``: with its entry's calibration (or rectify
        map), the events at their nearest undistorted (and rectified) pixels, those outside the image dropped
        (:meth:`cmax.Camera.undistort_events`), their exact positions (N, 2) float64 [px], and their sensor pixels
        with the camera (or the map) that maps them (:class:`Sample`'s ``sensor``; None for a pinhole camera); else
        ``(events, None, None)``."""
        camera, table = self._cameras[file_index], self._tables[file_index]
        if table is not None:
            return _mapped(events, table)
        return (events, None, None) if camera is None else _through_lens(camera, events)

    def _reader(self, file_index: int) -> H5Reader:
        """The open reader of file ``file_index``, opened on first use; at most :data:`MAX_OPEN_FILES` stay open
        (the least recently used closed first)."""
        reader = self._readers.pop(file_index, None)       # put back last: the dict's order is the order of use
        if reader is None:
            while self._readers and len(self._readers) >= MAX_OPEN_FILES:
                self._readers.pop(next(iter(self._readers))).close()
            size = self._sizes[file_index]
            reader = H5Reader(self.specs[file_index].path, polarity=self.specs[file_index].polarity,
                              **({} if size is None else {"width": size[0], "height": size[1]}))
        self._readers[file_index] = reader
        return reader

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        sample = self.sample(i)
        if self.augment:
            sample = augment(sample, np.random.default_rng([self.seed, self.epoch, i]))
        return to_item(sample, max_events=self.max_events, bins=self.bins, seed=self.seed + i, pixels=sample.pixels,
                       sensor=sample.sensor)

    def __getstate__(self) -> dict:   # open h5 files do not cross process boundaries
        state = dict(self.__dict__)
        state["_readers"] = {}
        return state


class MVSECDataset(torch.utils.data.Dataset):
    """Windows of an MVSEC data file, centred on its ground-truth depth times when a gt file is given.

    MVSEC's depth maps (``depth_image_rect``) and the K that goes with them lie in the RECTIFIED frame of its
    camchain (``P_rect``), while the events are recorded through the fisheye (Kalibr ``equidistant``) lens: given
    ``calib``, each window's events are undistorted and rectified into the depth's frame, as MVSEC's baselines do
    with its rectify maps or ``cv2.fisheye.undistortPoints(..., R_rect, P_rect)``: the event volume spreads each
    event bilinearly from its exact position (:meth:`cmax.Camera.undistorted_pixels`, no pixel left without
    events by rounding), the events of the contrast loss are dithered over their sensor pixels and mapped through
    the lens, unrounded, as :func:`cmax.fit` and ``cmax.contrast.EventWindows.from_events(events, camera)`` take
    them (:func:`to_item` with ``sensor``); those whose nearest rectified pixel lies outside the sensor are
    dropped. Without it the events are read as recorded (today's
    behaviour) and a warning says once that they and the depth lie in different frames.

    Parameters
    ----------
    data_file : path
        ``*_data.hdf5`` (events of ``davis/left``).
    K : array_like (3, 3) or (4,), optional
        Intrinsics [px] of the depth maps' (rectified) frame, or ``[fx, fy, cx, cy]``; its principal point must lie
        on the 346x260 sensor. With ``calib`` it may be left out (the calibration's rectified K is used), and must
        otherwise equal that K (to 0.01 px: rounded figures are taken, the lens's unrectified K is refused).
    calib : path or cmax.Camera, optional
        The left camera's calibration: MVSEC's Kalibr camchain (``camchain-imucam-<sequence>.yaml``; its camera
        ``calib_camera``, ``rectification_matrix`` and ``projection_matrix`` included), or a :class:`cmax.Camera`
        of the 346x260 sensor with ``model="equidistant"``, ``rectification=R_rect`` and ``rectified_K`` (the left
        3x3 of ``P_rect``) (explicit arrays). A calibration without a rectification is used as it is, with a
        warning when a gt file is given (its depth lies in the rectified frame).
    calib_camera : str
        The camera of a camchain ``calib``: ``cam0`` (MVSEC's left DAVIS, default).
    gt_file : path, optional
        ``*_gt.hdf5`` with ``davis/left/depth_image_rect`` (N, H, W) and ``..._ts`` [s]; at least one of its depth
        times must lie within the events of ``data_file`` (ValueError naming both spans: a gt file of another
        sequence).
    window_us, max_events, bins : as :class:`H5WindowDataset`.
    """

    def __init__(self, data_file: str | Path, K: object = None, *, calib: "str | Path | Camera | None" = None,
                 calib_camera: str = "cam0", gt_file: str | Path | None = None, window_us: int = 166_500,
                 max_events: int = 20_000, bins: int = 5) -> None:
        from cmax.io.mvsec import mvsec_time_span, read_mvsec

        from cmax.io.mvsec import MVSEC_HEIGHT, MVSEC_WIDTH

        self.data_file = Path(data_file)
        self.camera = _mvsec_camera(calib, calib_camera, MVSEC_WIDTH, MVSEC_HEIGHT)
        if self.camera is None:
            if K is None:
                raise ValueError(f"{self.data_file}: give K (the rectified intrinsics of the depth maps) or calib "
                                 "(MVSEC's camchain, which also rectifies the events)")
            self.K = _file_K(K, self.data_file, MVSEC_WIDTH, MVSEC_HEIGHT)   # as the other data sets check it
            warnings.warn(f"{self.data_file}: MVSECDataset without calib reads the events as recorded (through "
                          "MVSEC's fisheye lens, not rectified) but pairs them with the rectified K and depth maps "
                          "(depth_image_rect): events and depth lie in different frames, far apart toward the "
                          "corners; pass calib= MVSEC's camchain-imucam-<sequence>.yaml (or a cmax.Camera with its "
                          "rectification) to rectify the events into the depth's frame", UserWarning, stacklevel=2)
        else:
            pinhole = self.camera.pinhole_K
            if K is not None and not np.allclose(_file_K(K, self.data_file, MVSEC_WIDTH, MVSEC_HEIGHT), pinhole,
                                                 rtol=0, atol=0.01):
                raise ValueError(f"{self.data_file}: K {np.asarray(K, float).tolist()} is not the K of the frame calib "
                                 f"maps the events into ({pinhole.tolist()}); leave K out to use it")
            self.K = _file_K(pinhole, self.data_file, MVSEC_WIDTH, MVSEC_HEIGHT)
            if gt_file is not None and self.camera.rectification is None and self.camera.rectified_K is None:
                warnings.warn(f"{self.data_file}: calib gives no rectification (rectification_matrix, "
                              "projection_matrix): the events are undistorted onto the lens's own pinhole, but "
                              "MVSEC's depth maps lie in the rectified frame; give the camchain's rectification",
                              UserWarning, stacklevel=2)
        self.window_us, self.max_events, self.bins = int(window_us), int(max_events), bins
        self._read = read_mvsec
        self.gt_file = None if gt_file is None else Path(gt_file)
        if self.gt_file is not None:   # the times only: each depth map is read with its window (GBs in all)
            with h5py.File(self.gt_file, "r") as f:
                self.middles = np.rint(f["davis/left/depth_image_rect_ts"][:] * 1e6).astype(np.int64)
            span = mvsec_time_span(self.data_file)
            if span is None:
                raise ValueError(f"{self.data_file} holds no events of davis/left")
            if len(self.middles) and not ((self.middles >= span[0]) & (self.middles <= span[1])).any():
                raise ValueError(f"{self.gt_file}: none of its {len(self.middles)} depth times "
                                 f"({self.middles.min() * 1e-6:.6f} to {self.middles.max() * 1e-6:.6f} s) lies within "
                                 f"the events of {self.data_file} ({span[0] * 1e-6:.6f} to {span[1] * 1e-6:.6f} s): "
                                 "a gt file of another sequence?")
        else:                          # the first and last events' times only, not the file's events
            span = mvsec_time_span(self.data_file)
            if span is None:
                raise ValueError(f"{self.data_file} holds no events of davis/left")
            self.middles = np.arange(span[0] + self.window_us // 2, span[1] - self.window_us // 2, self.window_us)

    def events(self, i: int) -> Events:
        """The events of window ``i``: rectified into the depth's frame when the dataset has a calibration (at
        their nearest pixels, those outside dropped; :meth:`pixels` gives their exact positions), as recorded
        otherwise."""
        return self._window(i)[0]

    def pixels(self, i: int) -> np.ndarray:
        """The exact positions (N, 2) float64 [px of the depth's frame] of the events of window ``i``
        (:meth:`events`): undistorted and rectified, unrounded, when the dataset has a calibration
        (:meth:`cmax.Camera.undistorted_pixels`); their integer pixels otherwise."""
        return self._window(i)[1]

    def _window(self, i: int) -> tuple[Events, np.ndarray, SensorPixels | None]:
        """The events of window ``i`` (:meth:`events`), their exact positions (:meth:`pixels`) and, through a
        lens, their sensor pixels and the camera (None without a calibration or for a pinhole one)."""
        t0 = int(self.middles[i]) - self.window_us // 2
        events = self._read(self.data_file, t0_us=t0, t1_us=t0 + self.window_us)
        if self.camera is None:
            return events, np.column_stack([events.x, events.y]).astype(np.float64), None
        return _through_lens(self.camera, events)

    def __len__(self) -> int:
        return len(self.middles)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        t0 = int(self.middles[i]) - self.window_us // 2
        events, pixels, sensor = self._window(i)
        depth = None
        if self.gt_file is not None:
            with h5py.File(self.gt_file, "r") as f:
                depth = np.asarray(f["davis/left/depth_image_rect"][i], np.float32)
        return to_item(Sample(events, self.K, depth, None, t0, t0 + self.window_us), max_events=self.max_events,
                       bins=self.bins, seed=i, pixels=None if self.camera is None else pixels, sensor=sensor)
