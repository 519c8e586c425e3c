"""Catalogue of bad inputs: each must raise a clear, specific exception naming what is wrong.

Three tables, one test per row (``pytest -k <id>`` runs one):

* ``API_CASES``: the public functions on bad arguments (no files);
* ``FILE_CASES``: readers on truncated or corrupt copies of the real recordings
  in ``../shared/data`` (skipped without them);
* ``CLI_CASES``: the ``cmax`` command line; a bad argument exits with status 2 and
  one line on stderr naming it (no traceback).

Absurd sizes (a window of 10**9 events, 10**9 bins, a 65535x65535 event frame)
are refused before anything is allocated: ``tracemalloc`` checks that the
refusal itself stays small (numpy and h5py report their buffers to it).

The user-facing table of all this is ``docs/bad_input.md``.
"""
from __future__ import annotations

import dataclasses
import functools
import re
import subprocess
import sys
import tracemalloc
import warnings
from pathlib import Path
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch

import cmax
from cmax import Camera, Events, concatenate, geometry, viz
from cmax.cli import main
from cmax.events import EventLimitError
from cmax.io import (
    FormatError, H5Reader, H5Writer, read, read_aedat4, read_evt2, read_evt3, read_h5, read_mvsec,
    read_raw, read_txt, write_evt2, write_h5, write_txt,
)
from cmax.io.aedat4 import read_aedat4_frames, read_aedat4_imu
from cmax.io.prophesee._header import _read_header
from cmax.representations import event_frame, time_surface, voxel_grid, voxel_grid_batch
from cmax.sim import EventSimulator, make_scene, simulate_scene
from conftest import random_events

K_GOOD = np.array([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])


def _events(n: int = 200) -> Events:
    return random_events(n, width=64, height=48, seed=3)


@functools.lru_cache(maxsize=1)
def _flow_fit():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return cmax.fit(_events(), K_GOOD, model="flow")


def _init(**changes):
    """A warm start for ``cmax.fit(init=)``: a flow fit of :func:`_events` with ``changes`` to its fields."""
    return dataclasses.replace(_flow_fit(), **changes)


_POSES = (np.array([0, 100_000]), np.stack([np.eye(4), np.eye(4) + np.eye(4, k=3) * 0.1]))


def _emvs(**options):
    from cmax.emvs import EMVS

    return EMVS(**{"camera": Camera(K_GOOD, 64, 48), **options})


def _huge_view(value: int, dtype: str, n: int = 10**9) -> np.ndarray:
    """A read-only (n,) array that costs no memory (a zero-stride view)."""
    return np.broadcast_to(np.array(value, dtype=dtype), (n,))


# -- the public API --------------------------------------------------------------------------
API_CASES = [
    # Events: values
    ("events-x-nan", lambda: Events([np.nan], [0], [0], [1], 4, 4), ValueError, r"x contains a non-finite"),
    ("events-t-inf", lambda: Events([0], [0], [np.inf], [1], 4, 4), ValueError, r"t contains a non-finite"),
    ("events-p-nan", lambda: Events([0], [0], [0], [np.nan], 4, 4), ValueError, r"p contains a non-finite"),
    ("events-x-outside", lambda: Events([4], [0], [0], [1], 4, 4), ValueError, r"x must lie in \[0, width=4\)"),
    ("events-y-negative", lambda: Events([0], [-1], [0], [1], 4, 4), ValueError, r"y must lie in \[0, height=4\)"),
    ("events-t-unsorted", lambda: Events([0, 0], [0, 0], [5, 3], [1, 1], 4, 4), ValueError,
     r"t must be sorted in non-decreasing order; t\[1\]=3"),
    ("events-t-fraction", lambda: Events([0], [0], [0.5], [1], 4, 4), ValueError,
     r"t must hold whole numbers.*from float seconds: np\.rint\(t \* 1e6\)\.astype\(np\.int64\)"),
    ("events-t-beyond-int64", lambda: Events([0], [0], np.array([2**63 + 1], np.uint64), [1], 4, 4),
     ValueError, r"t does not fit into int64"),
    ("events-p-values", lambda: Events([0, 0], [0, 0], [0, 1], [0, 2], 4, 4), ValueError,
     r"p must hold polarities as \{0, 1\}, \{-1, \+1\}"),
    # Events: dtypes and shapes
    ("events-x-strings", lambda: Events(["a"], [0], [0], [1], 4, 4), TypeError, r"x must hold numbers"),
    ("events-x-complex", lambda: Events(np.array([1j]), [0], [0], [1], 4, 4), TypeError, r"x must hold numbers"),
    ("events-x-2d", lambda: Events(np.zeros((2, 2)), [0, 0], [0, 0], [1, 1], 4, 4), ValueError,
     r"x must be one-dimensional"),
    ("events-x-scalar", lambda: Events(0, 0, 0, 1, 4, 4), ValueError, r"x must be one-dimensional"),
    ("events-lengths-differ", lambda: Events([0, 1], [0], [0], [1], 4, 4), ValueError,
     r"x, y, t and p must have the same length"),
    ("events-width-zero", lambda: Events([], [], [], [], 0, 4), ValueError, r"width must be in \[1, 65535\]"),
    ("events-width-float", lambda: Events([], [], [], [], 4.0, 4), TypeError, r"width must be an integer"),
    ("events-height-bool", lambda: Events([], [], [], [], 4, True), TypeError, r"height must be an integer"),
    ("events-from-plain-array", lambda: Events.from_structured(np.zeros(3), 4, 4), TypeError,
     r"array must be a structured array"),
    ("events-from-array-shape", lambda: Events.from_array(np.zeros((3, 3)), 4, 4), ValueError,
     r"array must have shape \(N, 4\)"),
    ("events-from-array-order", lambda: Events.from_array(np.zeros((3, 4)), 4, 4, order="xxtp"), ValueError,
     r"order must be a permutation of 'xytp'"),
    ("events-index-backwards", lambda: _events()[[5, 2]], IndexError, r"non-decreasing"),
    ("concatenate-back-in-time", lambda: concatenate([_events()[100:], _events()[:100]]), ValueError,
     r"events would go back in time"),
    ("concatenate-sensors", lambda: concatenate([_events(), Events.empty(8, 8)]), ValueError,
     r"parts\[1\] has sensor"),
    # time windows
    ("slice-reversed", lambda: _events().slice_time(10, 5), ValueError, r"t1_us \(5\) must not be smaller"),
    ("slice-nan", lambda: _events().slice_time(np.nan, 5), ValueError, r"t0_us must be a finite time"),
    ("slice-fraction", lambda: _events().slice_time(0, 2.5), ValueError, r"t1_us must be whole microseconds"),
    ("slice-string", lambda: _events().slice_time("0", 5), TypeError, r"t0_us must be integer microseconds"),
    ("windows-zero-duration", lambda: list(_events().windows(duration_us=0)), ValueError,
     r"duration_us must be positive"),
    ("windows-negative-step", lambda: list(_events().windows(duration_us=10, step_us=-1)), ValueError,
     r"step_us must be positive"),
    ("windows-float-count", lambda: list(_events().windows(count=2.5)), TypeError, r"count must be an integer"),
    ("windows-both", lambda: list(_events().windows(duration_us=10, count=3)), ValueError,
     r"exactly one of duration_us and count"),
    # representations
    ("voxel-bins-zero", lambda: voxel_grid(_events(), bins=0), ValueError, r"bins must be >= 1"),
    ("voxel-bins-float", lambda: voxel_grid(_events(), bins=2.5), TypeError, r"bins must be an integer"),
    ("voxel-t0-nan", lambda: voxel_grid(_events(), t0_us=np.nan), TypeError, r"t0_us \(integer microseconds\)"),
    ("voxel-window-excludes-events", lambda: voxel_grid(_events(), t0_us=10**9), ValueError,
     r"lies before the window start"),
    ("voxel-not-events", lambda: voxel_grid(np.zeros((10, 4))), TypeError, r"events must be cmax.Events"),
    ("voxel-torch-x-outside", lambda: voxel_grid(cmax.EventTensors(
        torch.tensor([70]), torch.tensor([0]), torch.tensor([0]), torch.tensor([1]), 64, 48)),
     ValueError, r"events.x must lie in \[0, 64\)"),
    ("voxel-batch-empty-list", lambda: voxel_grid_batch([]), TypeError, r"non-empty sequence"),
    ("time-surface-tau-zero", lambda: time_surface(_events(), tau_us=0), ValueError, r"tau_us must be positive"),
    ("time-surface-ref-before-events", lambda: time_surface(_events(), t_ref_us=0), ValueError,
     r"t_ref_us=0 precedes the last event"),
    ("event-frame-signed-string", lambda: event_frame(_events(), signed="yes"), TypeError,
     r"signed must be a bool"),
    # pictures
    ("viz-volume-no-bins", lambda: viz.voxel_grid_image(np.zeros((0, 4, 4))), ValueError, r"at least one bin"),
    ("viz-volume-nan", lambda: viz.voxel_grid_image(np.full((2, 4, 4), np.nan)), ValueError,
     r"volume must be finite"),
    ("viz-counts-shape", lambda: viz.event_frame_image(np.zeros((3, 4, 4))), ValueError,
     r"counts must have shape \(2, H, W\)"),
    ("viz-signed-scale-zero", lambda: viz.signed_image(np.ones((4, 4)), scale=0), ValueError,
     r"scale must be a positive"),
    ("viz-depth-range-reversed", lambda: viz.depth_image(np.ones((4, 4)), depth_range=(5.0, 1.0)), ValueError,
     r"0 < near < far"),
    ("viz-hstack-nothing", lambda: viz.hstack([]), ValueError, r"at least one picture"),
    ("viz-titled-grey", lambda: viz.titled(np.zeros((4, 4), np.uint8), "t"), ValueError,
     r"image must be a non-empty \(H, W, 3\) BGR picture"),
    ("viz-png-float", lambda: viz.save_png("never.png", np.zeros((4, 4, 3))), TypeError, r"image must be uint8"),
    ("viz-png-empty", lambda: viz.save_png("never.png", np.zeros((0, 4, 3), np.uint8)), ValueError,
     r"non-empty"),
    # camera and geometry
    ("K-singular", lambda: Camera(np.zeros((3, 3)), 64, 48), ValueError, r"K must have positive focal lengths"),
    ("K-nan", lambda: Camera(np.full((3, 3), np.nan), 64, 48), ValueError, r"K must be finite"),
    ("K-inf", lambda: Camera(np.diag([np.inf, 1.0, 1.0]), 64, 48), ValueError, r"K must be finite"),
    ("K-shape", lambda: Camera(np.eye(4), 64, 48), ValueError, r"K must be a 3x3 matrix"),
    ("K-strings", lambda: Camera("fx fy cx cy", 64, 48), TypeError, r"K must be a 3x3 matrix of numbers"),
    ("K-not-pinhole", lambda: Camera(np.ones((3, 3)), 64, 48), ValueError, r"K must have the form"),
    ("distortion-length", lambda: Camera(K_GOOD, 64, 48, distortion=[0.1] * 3), ValueError,
     r"distortion of a radtan camera must have 4 or 5 or 8 or 12 or 14 coefficients"),
    ("distortion-nan", lambda: Camera(K_GOOD, 64, 48, distortion=[np.nan] * 5), ValueError,
     r"distortion must be finite"),
    ("project-behind-camera", lambda: Camera(K_GOOD, 64, 48).project([[0.0, 0.0, -1.0]]), ValueError,
     r"in front of the camera"),
    ("project-nan", lambda: Camera(K_GOOD, 64, 48).project([[np.nan, 0.0, 1.0]]), ValueError,
     r"points_c must be finite"),
    ("backproject-negative-depth", lambda: Camera(K_GOOD, 64, 48).backproject([[1.0, 1.0]], [-2.0]),
     ValueError, r"depth must be positive"),
    ("undistort-other-sensor", lambda: Camera(K_GOOD, 64, 48).undistort(Events.empty(8, 8)), ValueError,
     r"8x8 sensor, the camera is 64x48"),
    ("se3-exp-shape", lambda: geometry.se3_exp(np.zeros(5)), ValueError, r"xi must have shape \(\.\.\., 6\)"),
    ("se3-exp-nan", lambda: geometry.se3_exp([np.nan] * 6), ValueError, r"xi must be finite"),
    ("se3-log-not-rigid", lambda: geometry.se3_log(np.zeros((4, 4))), ValueError, r"last row"),
    ("so3-log-not-rotation", lambda: geometry.so3_log(2 * np.eye(3)), ValueError, r"R must be a rotation"),
    ("so3-log-reflection", lambda: geometry.so3_log(np.diag([1.0, 1.0, -1.0])), ValueError,
     r"determinant \+1"),
    ("interpolate-query-nan", lambda: geometry.interpolate_poses([0, 1], [np.eye(4)] * 2, [np.nan]),
     ValueError, r"query_times_us must hold finite"),
    ("interpolate-times-duplicated", lambda: geometry.interpolate_poses([0, 0], [np.eye(4)] * 2, [0]),
     ValueError, r"strictly increasing"),
    ("interpolate-outside", lambda: geometry.interpolate_poses([0, 1], [np.eye(4)] * 2, [2]), ValueError,
     r"must lie in \[0, 1\]"),
    # fitting (the cases: empty window, singular K, same timestamps)
    ("fit-empty-window", lambda: cmax.fit(Events.empty(64, 48), K_GOOD), ValueError, r"at least 10 events"),
    ("fit-singular-K", lambda: cmax.fit(_events(), np.zeros((3, 3))), ValueError, r"K must have positive focal"),
    ("fit-nan-K", lambda: cmax.fit(_events(), np.full((3, 3), np.nan)), ValueError, r"K must be finite"),
    ("fit-same-timestamps", lambda: cmax.fit(
        Events(np.arange(20), np.zeros(20), np.full(20, 7), np.ones(20), 64, 48), K_GOOD), ValueError,
     r"same timestamp"),
    ("fit-unknown-model", lambda: cmax.fit(_events(), K_GOOD, model="affine"), ValueError,
     r"model must be one of"),
    ("fit-negative-speed", lambda: cmax.fit(_events(), K_GOOD, speed=-1.0), ValueError,
     r"speed must be a positive"),
    ("fit-nan-speed", lambda: cmax.fit(_events(), K_GOOD, speed=float("nan")), ValueError,
     r"speed must be a positive"),
    ("fit-array-speed", lambda: cmax.fit(_events(), K_GOOD, speed=np.array([0.5])), ValueError,
     r"speed must be one positive number of m/s, got array\(\[0\.5\]\)"),
    ("fit-text-speed", lambda: cmax.fit(_events(), K_GOOD, speed="0.5"), ValueError,
     r"speed must be one positive number of m/s, got '0\.5'"),
    ("fit_windows-array-speed", lambda: cmax.fit_windows([_events()], K_GOOD, speed=np.array([0.5, 0.6])),
     ValueError, r"speed must be one positive number"),
    ("fit-unknown-solver", lambda: cmax.fit(_events(), K_GOOD, solver="adam"), ValueError, r"solver must be one of"),
    ("fit-not-events", lambda: cmax.fit(np.zeros((10, 4)), K_GOOD), TypeError,
     r"events must be cmax.Events, got ndarray of shape \(10, 4\): cmax.Events.from_array\(array, width, height, "
     r"order='xytp'\)"),
    ("fit-structured-array", lambda: cmax.fit(_events().to_structured(), K_GOOD), TypeError,
     r"got ndarray \(a structured array with fields \['x', 'y', 't', 'p'\]\): cmax.Events.from_structured"),
    ("fit-event-tensors", lambda: cmax.fit(_events().to_torch(), K_GOOD), TypeError,
     r"got EventTensors; these are the torch tensors of Events.to_torch\(\)"),
    ("fit-a-path", lambda: cmax.fit("room.h5", K_GOOD), TypeError, r"got str \(room.h5\): read the file with cmax.io.read"),
    ("fit-four-number-K", lambda: cmax.fit(_events(), [50.0, 50.0, 32.0, 24.0]), ValueError,
     r"K must be a 3x3 matrix, got shape \(4,\) \(four numbers fx, fy, cx, cy\? np.array\(\[\[fx, 0, cx\]"),
    ("fit-pose-shape", lambda: cmax.fit(_events(), K_GOOD, pose=np.zeros(5)), ValueError, r"pose must be a twist"),
    ("fit-pose-contradicting-speed", lambda: cmax.fit(_events(), K_GOOD, pose=[0.5, 0, 0, 0, 0, 0], speed=2.0),
     ValueError, r"pose moves at 0.5 m/s but speed=2 m/s: give one of them"),
    ("fit-unknown-option", lambda: cmax.fit(_events(), K_GOOD, foo=1), TypeError, r"unexpected keyword"),
    ("fit-init-flow-shape", lambda: cmax.fit(_events(), K_GOOD, model="flow", init=_init(flow=np.ones(3))),
     ValueError, r"init.flow must have shape \(2,\) \[px/s\], got shape \(3,\)"),
    ("fit-init-flow-one-number", lambda: cmax.fit(_events(), K_GOOD, model="flow", init=_init(flow=np.ones(1))),
     ValueError, r"init.flow must have shape \(2,\)"),
    ("fit-init-omega-shape", lambda: cmax.fit(_events(), K_GOOD, model="rotation", init=_init(omega=np.zeros(2))),
     ValueError, r"init.omega must have shape \(3,\) \[rad/s\], got shape \(2,\)"),
    ("fit-init-v-shape", lambda: cmax.fit(_events(), K_GOOD, speed=1.0, init=_init(v=np.zeros(2))),
     ValueError, r"init.v must have shape \(3,\) \[m/s\], got shape \(2,\)"),
    ("fit-depth-range-three", lambda: cmax.fit(_events(), K_GOOD, depth_range=(1, 3, 6)), ValueError,
     r"depth_range must be two numbers \(near, far\) in metres, got \(1, 3, 6\)"),
    ("fit-depth-range-infinite", lambda: cmax.fit(_events(), K_GOOD, depth_range=(1, float("inf"))), ValueError,
     r"depth_range must be finite metres"),
    ("fit-depth-grid-zero", lambda: cmax.fit(_events(), K_GOOD, depth_grid=(0, 0)), ValueError,
     r"depth_grid must be two positive"),
    ("fit-depth-coarsening-zero", lambda: cmax.fit(_events(), K_GOOD, depth_coarsening=0), ValueError,
     r"depth_coarsening must be an integer >= 1"),
    ("fit-negative-depth-smoothness", lambda: cmax.fit(_events(), K_GOOD, depth_smoothness=(-0.1, 1.0)), ValueError,
     r"depth_smoothness must be two non-negative numbers"),
    ("fit-negative-depth-range", lambda: cmax.fit(_events(), K_GOOD, depth_range=(-1.0, 5.0)), ValueError,
     r"depth_range must satisfy 0 < near < far"),
    ("fit-reversed-depth-range", lambda: cmax.fit(_events(), K_GOOD, depth_range=(5.0, 1.0)), ValueError,
     r"depth_range must satisfy 0 < near < far"),
    ("fit-zero-max-events", lambda: cmax.fit(_events(), K_GOOD, "flow", max_events=0), ValueError,
     r"max_events must be >= 10"),
    ("fit-sequence-zero-window", lambda: cmax.fit_sequence(_events(), K_GOOD, window_us=0), ValueError,
     r"window_us and step_us must be positive"),
    # EMVS (the cases: negative depth range, empty window, singular K via Camera)
    ("emvs-negative-depth-range", lambda: _emvs(depth_range=(-1.0, 5.0)), ValueError, r"0 < near < far"),
    ("emvs-reversed-depth-range", lambda: _emvs(depth_range=(5.0, 1.0)), ValueError, r"0 < near < far"),
    ("emvs-nan-depth-range", lambda: _emvs(depth_range=(np.nan, 1.0)), ValueError, r"0 < near < far"),
    ("emvs-one-plane", lambda: _emvs(n_planes=1), ValueError, r"n_planes must be an integer >= 2"),
    ("emvs-not-a-camera", lambda: _emvs(camera=K_GOOD), TypeError, r"camera must be a cmax.Camera, got ndarray \(a K matrix: cmax.Camera\(K, width, height"),
    ("emvs-empty-window", lambda: _emvs().run(Events.empty(64, 48), _POSES), ValueError,
     r"events must not be empty"),
    ("emvs-not-events", lambda: _emvs().run(np.zeros((3, 4)), _POSES), TypeError, r"events must be cmax.Events"),
    ("emvs-poses-too-short", lambda: _emvs().run(_events(), (np.array([0, 50_000]), _POSES[1])), ValueError,
     r"poses cover \[0, 50000\] µs but the events span"),
    ("emvs-poses-nan", lambda: _emvs().run(_events(), (_POSES[0], np.full((2, 4, 4), np.nan))), ValueError,
     r"T_w_c must be finite"),
    ("emvs-poses-same-times", lambda: _emvs().run(_events(), (np.array([0, 0]), _POSES[1])), ValueError,
     r"times_us must be strictly increasing"),
    # simulator (the cases: thresholds <= 0, same timestamps)
    ("esim-threshold-zero", lambda: EventSimulator(cp=0.0), ValueError, r"cp must be a finite positive"),
    ("esim-threshold-negative", lambda: EventSimulator(cn=-0.1), ValueError, r"cn must be a finite positive"),
    ("esim-threshold-nan", lambda: EventSimulator(cp=float("nan")), ValueError, r"cp must be a finite positive"),
    ("esim-frames-nan", lambda: EventSimulator().simulate(np.full((2, 4, 4), np.nan), [0, 10]), ValueError,
     r"frames\[0\] contains NaN"),
    ("esim-same-timestamps", lambda: EventSimulator().simulate(np.zeros((2, 4, 4), np.uint8), [0, 0]),
     ValueError, r"timestamps_us must be strictly increasing"),
    ("esim-no-frames", lambda: EventSimulator().simulate(np.zeros((0, 4, 4), np.uint8), []), ValueError,
     r"at least one frame"),
    ("esim-length-mismatch", lambda: EventSimulator().simulate(np.zeros((2, 4, 4), np.uint8), [0]), ValueError,
     r"timestamps_us has 1 entries but frames has 2"),
    ("scene-unknown-preset", lambda: make_scene("moon"), ValueError, r"name must be one of"),
    ("scene-negative-duration", lambda: simulate_scene(make_scene("slider", width=32, height=24), -1.0,
                                                        EventSimulator()), ValueError, r"duration_s must be positive"),
]


def _frames_folder(parent):
    """An ECD-like folder (images.txt) next to the fixtures."""
    folder = parent / "ecd"
    folder.mkdir(exist_ok=True)
    (folder / "images.txt").write_text("0.0 images/frame_00000000.png\n")
    return folder


def _file(path, data: bytes):
    path.write_bytes(data)
    return path


@pytest.mark.parametrize("call, error, match", [pytest.param(*case[1:], id=case[0]) for case in API_CASES])
def test_bad_argument_raises_clear_error(call, error, match):
    with pytest.raises(error, match=match):
        call()


def test_duplicated_timestamps_are_legal():
    """Event streams have many events per µs: equal times are kept, in order (documented in Events)."""
    events = Events([3, 1, 2], [0, 0, 0], [5, 5, 5], [1, 0, 1], 4, 4)
    assert events.x.tolist() == [3, 1, 2]
    assert len(events.slice_time(5, 6)) == 3 and len(events.slice_time(5, 5)) == 0
    grid = voxel_grid(events, bins=3)  # t_N == t_0: every event in bin 0 with weight p (documented)
    assert grid[0, 0].tolist() == [0.0, -1.0, 1.0, 1.0] and not grid[1:].any()


def test_frames_in_zero_one_are_warned_not_guessed():
    """ESIM takes grey values in [0, 255]; float frames in [0, 1] (the skimage/torch convention) are not
    rescaled behind the user's back: the simulation runs as given, with a warning that says how to fix it.
    The same frames times 255 give more events and no warning."""
    from cmax.sim import EventSimulator

    rng = np.random.default_rng(0)
    frames, times = rng.random((3, 6, 8)), np.array([0, 1000, 2000])
    with pytest.warns(UserWarning, match=r"\[0, 1\] image\? multiply it by 255"):
        dark = EventSimulator().simulate(frames, times)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scaled = EventSimulator().simulate(frames * 255, times)
        EventSimulator().simulate(np.zeros((3, 6, 8)), times)             # black frames: nothing to say
    assert len(scaled) > len(dark)


def test_zero_one_frames_are_warned_once_in_the_streaming_api(tmp_path):
    """``EventSimulator.step``, ``iter_upsample`` and ``convert_video(frames=)`` took [0, 1] float frames without a
    word (``simulate`` warned): now once per simulator (per stream for ``iter_upsample``), at its first frame; a
    [0, 255] stream (its upsampled float frames too, a fade from black included) and 0/1 masks stay silent."""
    from cmax.sim import EventSimulator, iter_upsample
    from cmax.sim.convert import ConvertSettings, convert_video

    rng = np.random.default_rng(0)
    frames = [rng.random((32, 32)).astype(np.float32) for _ in range(3)]
    simulator = EventSimulator()
    with pytest.warns(UserWarning, match=r"\[0, 1\] image\? multiply it by 255") as caught:
        for i, frame in enumerate(frames):
            simulator.step(frame, i * 1000)
        simulator.reset()
        simulator.step(frames[0], 0)                                      # once per simulator
    assert len([w for w in caught if "multiply it by 255" in str(w.message)]) == 1
    with pytest.warns(UserWarning, match="multiply it by 255"):
        list(iter_upsample(zip(frames, [0, 1000, 2000]), 0.2, method="linear"))
    with pytest.warns(UserWarning, match="multiply it by 255"):
        convert_video("frames", tmp_path / "a.h5", ConvertSettings(adaptive=False), frames=zip(frames, [0, 1000, 2000]))
    fade = [np.zeros((32, 32), np.uint8), np.full((32, 32), 200, np.uint8)]   # from black: inserted frames < 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        simulator = EventSimulator()
        for frame, t in iter_upsample(zip(fade, [0, 1_000_000]), 0.2, method="linear"):
            simulator.step(frame, t)
        EventSimulator().step(np.eye(4, dtype=np.float32), 0)              # a 0/1 mask
        EventSimulator().step(frames[0] * 255, 0)


def test_a_rotation_in_deg_per_s_is_warned_not_guessed():
    """A gyroscope's deg/s given as rad/s (``omega=``, or a twist ``pose=``) turns 57.3 times too fast: the fit
    takes it as given (a fast spin is possible), with a warning that names the units; 1 rad/s says nothing."""
    rng = np.random.default_rng(0)
    n = 3000
    events = Events(rng.integers(0, 64, n), rng.integers(0, 48, n), np.sort(rng.integers(0, 50_000, n)),
                    rng.integers(0, 2, n), 64, 48)
    K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])
    deg = r"turns at 10 rad/s \(573 deg/s\).*deg/s passed as rad/s.*0\.175 rad/s if these were deg/s"
    with pytest.warns(UserWarning, match=deg):
        cmax.fit(events, K, speed=0.5, omega=[0.0, 6.0, -8.0])
    with pytest.warns(UserWarning, match=deg):
        cmax.fit(events, K, pose=[0.5, 0, 0, 0.0, 6.0, -8.0])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cmax.fit(events, K, speed=0.5, omega=[1.0, 0.0, 0.0])
    assert not [w for w in caught if "deg/s" in str(w.message)]


def test_intrinsics_in_another_order_are_warned_not_guessed():
    """A valid K unlike any camera's: MVSEC's DAVIS346 numbers given in ROS's row order (fx, cx, fy, cy) or as
    cx, cy, fx, fy make fy / fx 0.77 and move the principal point 16% / 37% of the image off its centre; the
    fit runs as given, with a warning naming the order. MVSEC's own K says nothing."""
    rng = np.random.default_rng(0)
    n = 3000
    events = Events(rng.integers(0, 346, n), rng.integers(0, 260, n), np.sort(rng.integers(0, 50_000, n)),
                    rng.integers(0, 2, n), 346, 260)

    def K(fx, fy, cx, cy):
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])

    with pytest.warns(UserWarning, match=r"principal point is 16% .* fy / fx = 0\.77 .*order of the numbers"):
        cmax.fit(events, K(226.38, 173.64, 226.15, 133.73), model="flow")
    with pytest.warns(UserWarning, match=r"principal point is 37% of the image from its centre"):
        cmax.fit(events, K(173.64, 133.73, 226.38, 226.15), model="flow")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cmax.fit(events, K(226.38, 226.15, 173.64, 133.73), model="flow")
        cmax.fit(events, K(226.38, 240.0, 190.0, 145.0), model="flow")        # 6% aspect, 5% off centre: a camera
    assert not [w for w in caught if "unlike a camera" in str(w.message)]


def test_zero_length_windows_give_no_events(tmp_path):
    events = _events()
    t = int(events.t[50])
    assert len(events.slice_time(t, t)) == 0
    path = write_h5(tmp_path / "e.h5", events)
    with H5Reader(path) as reader:
        assert len(reader.window(t, t)) == 0
    assert voxel_grid(events.slice_time(t, t), bins=5).shape == (5, 48, 64)
    assert not voxel_grid(events.slice_time(t, t), bins=5).any()


def test_failed_png_write_leaves_no_partial_file(tmp_path):
    (tmp_path / "taken").mkdir()
    with pytest.raises(IsADirectoryError):
        viz.save_png(tmp_path / "taken", np.zeros((4, 4, 3), np.uint8))
    assert sorted(path.name for path in tmp_path.iterdir()) == ["taken"]


# -- absurd sizes: refused before allocating -------------------------------------------------
def _refused_within(limit_bytes: int, call, error, match) -> None:
    tracemalloc.start()
    try:
        with pytest.raises(error, match=match):
            call()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < limit_bytes, f"the refusal allocated {peak / 1e6:.0f} MB"


def test_events_of_a_billion_rows_are_refused_before_allocating():
    x = _huge_view(0, "u2")
    t = _huge_view(0, "i8")
    _refused_within(50_000_000, lambda: Events(x, x, t, _huge_view(1, "i1"), 4, 4), EventLimitError,
                    r"column x holds 1,000,000,000 events, more than cmax.events.MAX_EVENTS")


def _sparse_h5(path: Path, rows: int, rows_per_ms: int) -> Path:
    """A DSEC file that claims ``rows`` events (chunks never written, so a few kB on disk)."""
    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        for name, dtype in (("x", "u2"), ("y", "u2"), ("t", "i8"), ("p", "u1")):
            group.create_dataset(name, shape=(rows,), dtype=dtype, chunks=(1 << 20,))
        file.create_dataset("ms_to_idx", data=np.arange(0, rows + 1, rows_per_ms, dtype=np.uint64))
        file.create_dataset("t_offset", data=np.int64(0))
        file.attrs["width"], file.attrs["height"] = 64, 48
    return path


def test_window_of_a_billion_events_is_refused_before_reading(tmp_path):
    path = _sparse_h5(tmp_path / "huge.h5", 10**9, 10**6)
    assert path.stat().st_size < 10_000_000
    # The columns declare 10**9 rows whose chunks were never written: refused at open (issue 20),
    # before any fill values are read or allocated.
    _refused_within(60_000_000, lambda: H5Reader(path), FormatError,
                    r"events/x declares 1,000,000,000 entries in 954 chunks but the file stores only 0")


def test_whole_file_read_beyond_the_limit_is_refused(tmp_path, monkeypatch):
    events = _events(3000)
    write_evt2(tmp_path / "e.raw", events)
    write_h5(tmp_path / "e.h5", events)
    monkeypatch.setattr("cmax.events.MAX_EVENTS", 1000)
    with pytest.raises(EventLimitError, match=r"iter_evt2 streams it"):
        read_evt2(tmp_path / "e.raw", chunk_bytes=4096)
    with pytest.raises(EventLimitError, match=r"3,000 events"):
        read_h5(tmp_path / "e.h5")
    with H5Reader(tmp_path / "e.h5") as reader:  # windows below the limit still work
        assert sum(len(w) for w in reader.windows(10_000)) == 3000


@pytest.mark.parametrize("call, match", [
    pytest.param(lambda: voxel_grid(_events(), bins=10**9), r"bins=1000000000 on a 64x48 sensor", id="voxel-1e9-bins"),
    pytest.param(lambda: voxel_grid(Events.empty(8192, 8192), bins=20), r"bins=20 on a 8192x8192",
                 id="voxel-huge-sensor"),
    pytest.param(lambda: Events.empty(65535, 65535), r"a 65535x65535 sensor \(4,294,836,225 pixels\) is larger "
                 r"than any event camera", id="events-huge-sensor"),
    pytest.param(lambda: Events.empty(65535, 40000), r"larger than any event camera", id="events-huge-sensor-2"),
    pytest.param(lambda: voxel_grid_batch([_events().to_torch()] * 4, bins=10**8), r"4 samples of bins=100000000",
                 id="voxel-batch-huge"),
])
def test_absurd_output_sizes_are_refused_before_allocating(call, match):
    _refused_within(20_000_000, call, ValueError, match)


# -- corrupt and truncated files -------------------------------------------------------------
def _flip(data: bytes, start: int, count: int) -> bytes:
    return data[:start] + bytes(b ^ 0xA5 for b in data[start:start + count]) + data[start + count:]


@pytest.fixture(scope="module")
def bad(shared_data, tmp_path_factory) -> SimpleNamespace:
    """Copies of the real recordings, written out, then truncated or corrupted."""
    folder = tmp_path_factory.mktemp("bad_files")
    raw = (shared_data / "prophesee_gen4_driving" / "evt3_sample.raw").read_bytes()
    aedat = (shared_data / "davis346_pegboard" / "davis.aedat4").read_bytes()
    video = (shared_data / "videos" / "bikes.mp4").read_bytes()
    events = read_evt3(shared_data / "prophesee_gen4_driving" / "evt3_sample.raw")[:20_000]
    h5 = write_h5(folder / "good.h5", events).read_bytes()
    write_evt2(folder / "good2.raw", events)
    evt2 = (folder / "good2.raw").read_bytes()
    write_txt(folder / "good.txt", events[:2000])
    text = (folder / "good.txt").read_bytes()
    header_end = _read_header(shared_data / "prophesee_gen4_driving" / "evt3_sample.raw").data_offset

    def put(name: str, data: bytes) -> Path:
        path = folder / name
        path.write_bytes(data)
        return path

    with h5py.File(folder / "unsorted.h5", "w") as file:  # a DSEC file whose times go back
        for name, values in (("x", [1, 2]), ("y", [1, 2]), ("t", [50, 10]), ("p", [1, 0])):
            file.create_dataset(f"events/{name}", data=np.asarray(values))
        file.attrs["width"], file.attrs["height"] = 64, 48
    table = np.column_stack([events.x[:500], events.y[:500], events.t[:500] / 1e6, 2.0 * events.p[:500] - 1])
    with h5py.File(folder / "mvsec.h5", "w") as file:
        file.create_dataset("davis/left/events", data=np.clip(table, 0, [345, 259, np.inf, 1]))
    mvsec = (folder / "mvsec.h5").read_bytes()
    with h5py.File(folder / "bad_index.h5", "w") as file:  # ms_to_idx pointing past the rows
        for name in "xytp":
            file.create_dataset(f"events/{name}", data=np.zeros(3, np.int64))
        file.create_dataset("ms_to_idx", data=np.array([0, 7, 2], np.uint64))
        file.attrs["width"], file.attrs["height"] = 64, 48
    return SimpleNamespace(
        folder=folder,
        h5_half=put("half.h5", h5[: len(h5) // 2]),
        h5_header=put("head.h5", h5[:100]),
        h5_empty=put("empty.h5", b""),
        h5_unsorted=folder / "unsorted.h5",
        h5_bad_index=folder / "bad_index.h5",
        mvsec=folder / "mvsec.h5",
        mvsec_half=put("mvsec_half.h5", mvsec[: len(mvsec) // 2]),
        h5_outside=_shrink_sensor(write_h5(folder / "outside.h5", events)),
        raw_odd=put("odd.raw", raw[: header_end + 2 * ((len(raw) - header_end) // 4) + 1]),
        raw_header_cut=put("cut.raw", raw[:20]),
        raw_garbage=put("garbage.raw", raw[:header_end] + bytes([0x00, 0x90]) * 500),
        raw_no_format=put("noformat.raw", b"% date today\n" + raw[header_end:]),
        raw_no_size=put("nosize.raw", b"% evt 3.0\n" + raw[header_end:]),
        raw_evt21=put("evt21.raw", b"% evt 2.1\n% geometry 64x48\n" + bytes(16)),
        evt2_cut=put("cut2.raw", evt2[:-3]),
        evt2_reserved=put("reserved2.raw", evt2[: evt2.index(b"% end\n") + 6] + bytes.fromhex("00000020") * 8),
        aedat_half=put("half.aedat4", aedat[: len(aedat) // 2]),
        aedat_magic=put("magic.aedat4", aedat[:20]),
        aedat_flipped=put("flipped.aedat4", _flip(aedat, 5000, 200)),
        txt_cut=put("cut.txt", text[: len(text) // 2 + 3]),
        txt_binary=put("binary.txt", b"\xff\xfe\x00\x01garbage\n"),
        txt_nan=put("nan.txt", b"0.1 1 2 1\nnan 1 2 1\n"),
        txt_unsorted=put("unsorted.txt", b"0.2 1 2 1\n0.1 1 2 1\n"),
        txt_outside=put("outside.txt", b"0.1 5000 2 1\n"),
        npy_garbage=put("garbage.npy", b"\x93NUMPY" + bytes(range(200))),
        unknown=put("mystery.bin", b"hello"),
        video_half=put("half.mp4", video[: len(video) // 3]),
        video_garbage=put("garbage.mp4", bytes(range(256)) * 64),
    )


def _append(path: Path, *parts: Events) -> None:
    with H5Writer(path, 64, 48, overwrite=True) as writer:
        for part in parts:
            writer.append(part)
    raise AssertionError("the writer accepted the events")


def _shrink_sensor(path: Path) -> Path:
    """Rewrite the stored sensor size so that the events lie outside it."""
    with h5py.File(path, "r+") as file:
        file.attrs["width"], file.attrs["height"] = 8, 8
    return path


FILE_CASES = [
    ("h5-truncated-half", lambda b: read(b.h5_half), FormatError, r"not a readable HDF5 file"),
    ("h5-truncated-header", lambda b: read(b.h5_header), FormatError, r"not a readable HDF5 file"),
    ("h5-empty-file", lambda b: read(b.h5_empty), FormatError, r"empty\.h5 is empty \(0 bytes\): no events to read"),
    ("h5-reader-truncated", lambda b: H5Reader(b.h5_half), FormatError, r"not a readable HDF5 file"),
    ("h5-times-go-back", lambda b: read_h5(b.h5_unsorted), FormatError, r"corrupt events .* t must be sorted"),
    ("h5-corrupt-ms-to-idx", lambda b: H5Reader(b.h5_bad_index), FormatError, r"corrupt ms_to_idx"),
    ("h5-events-outside-sensor", lambda b: read_h5(b.h5_outside), FormatError, r"x must lie in \[0, width=8\)"),
    ("h5-window-nan", lambda b: H5Reader(b.folder / "good.h5").window(np.nan, 10), ValueError,
     r"t0_us must be a finite time"),
    ("h5-window-reversed", lambda b: H5Reader(b.folder / "good.h5").window(10, 5), ValueError,
     r"must not be smaller"),
    ("h5-not-mvsec", lambda b: read_mvsec(b.folder / "good.h5"), FormatError, r"not an MVSEC data file"),
    ("mvsec-truncated", lambda b: read_mvsec(b.mvsec_half), FormatError, r"not a readable MVSEC HDF5 file"),
    ("mvsec-window-nan", lambda b: read_mvsec(b.mvsec, t1_us=float("nan")), ValueError,
     r"t1_us must be a finite time"),
    ("mvsec-camera", lambda b: read_mvsec(b.mvsec, camera="middle"), ValueError, r"camera must be 'left' or 'right'"),
    ("h5-writer-chunk-zero", lambda b: H5Writer(b.folder / "w.h5", 64, 48, chunk_size=0), ValueError,
     r"chunk_size must be positive"),
    ("h5-writer-compression", lambda b: H5Writer(b.folder / "w.h5", 64, 48, compression="zip"), ValueError,
     r"compression must be 'blosc', 'gzip' or 'none'"),
    ("h5-writer-other-sensor", lambda b: _append(b.folder / "w2.h5", Events.empty(8, 8)), ValueError,
     r"events have sensor \(8, 8\), the file has \(64, 48\)"),
    ("h5-writer-back-in-time", lambda b: _append(b.folder / "w3.h5", _events()[100:], _events()[:100]),
     ValueError, r"must be appended in time order"),
    ("h5-exists", lambda b: write_h5(b.folder / "good.h5", _events()), FileExistsError, r"overwrite=True"),
    ("h5-missing-folder", lambda b: write_h5(b.folder / "no" / "e.h5", _events()), FileNotFoundError,
     r"cannot write .*e\.h5: its folder .* does not exist"),
    ("evt3-truncated-odd-bytes", lambda b: read(b.raw_odd), FormatError, r"not a whole number of 2-byte words"),
    ("evt3-truncated-header", lambda b: read_raw(b.raw_header_cut), FormatError, r"has no end of line"),
    ("evt3-reserved-words", lambda b: read_evt3(b.raw_garbage), FormatError, r"reserved EVT 3.0 word type 0x9"),
    ("evt3-no-format-declared", lambda b: read_raw(b.raw_no_format), FormatError,
     r"declares no event format"),
    ("evt3-no-sensor-size", lambda b: read_evt3(b.raw_no_size), FormatError, r"gives no sensor size"),
    ("evt21-unsupported", lambda b: read_raw(b.raw_evt21), FormatError, r"unsupported event format 'evt 2.1'"),
    ("evt2-read-as-evt3", lambda b: read_evt3(b.folder / "good2.raw"), FormatError,
     r"declares 'evt2', not EVT 3.0"),
    ("evt2-truncated", lambda b: read(b.evt2_cut), FormatError, r"not a whole number of 4-byte words"),
    ("evt2-reserved-words", lambda b: read(b.evt2_reserved), FormatError, r"reserved EVT 2.0 word type 0x2"),
    ("evt3-chunk-bytes-zero", lambda b: read_evt3(b.raw_odd, chunk_bytes=0), ValueError,
     r"chunk_bytes must be positive"),
    ("aedat4-truncated-half", lambda b: read_aedat4(b.aedat_half), FormatError, r"truncated or corrupt"),
    ("aedat4-truncated-header", lambda b: read(b.aedat_magic), FormatError, r"truncated or corrupt"),
    ("aedat4-corrupt-packet", lambda b: read_aedat4(b.aedat_flipped), FormatError, r"packet at byte"),
    ("aedat4-imu-truncated", lambda b: read_aedat4_imu(b.aedat_half), FormatError, r"truncated or corrupt"),
    ("aedat4-frames-truncated", lambda b: read_aedat4_frames(b.aedat_half), FormatError, r"truncated or corrupt"),
    ("txt-truncated-line", lambda b: read_txt(b.txt_cut, width=1280, height=720), FormatError,
     r"not an ECD text file"),
    ("txt-binary", lambda b: read_txt(b.txt_binary, width=1280, height=720), FormatError, r"not an ECD text file"),
    ("txt-nan", lambda b: read_txt(b.txt_nan, width=1280, height=720), FormatError, r"non-finite"),
    ("txt-unsorted", lambda b: read_txt(b.txt_unsorted, width=1280, height=720), FormatError,
     r"t must be sorted"),
    ("txt-outside-sensor", lambda b: read_txt(b.txt_outside, width=1280, height=720), FormatError,
     r"x must lie in \[0, width=1280\)"),
    ("txt-without-size", lambda b: read(b.folder / "good.txt"), ValueError, r"pass width= and height="),
    ("npy-garbage", lambda b: read(b.npy_garbage, width=4, height=4), FormatError, r"not a readable .npy"),
    ("unknown-format", lambda b: read(b.unknown), FormatError, r"cannot tell the event format"),
    ("missing-file", lambda b: read(b.folder / "nope.h5"), FileNotFoundError, r"no such event file"),
    ("folder-instead-of-file", lambda b: read(b.folder), FormatError, r"is a folder, not an event file$"),
    ("frames-folder", lambda b: read(_frames_folder(b.folder)), FormatError,
     r"is a folder, not an event file: a sequence of frames .* `cmax simulate FOLDER -o events\.h5`"),
    ("video-file", lambda b: read(_file(b.folder / "clip.mp4", b"\x00\x00\x00\x18ftypmp42")), FormatError,
     r"cannot tell the event format .*; a video becomes events with `cmax simulate VIDEO -o events\.h5`"),
    ("video-truncated", lambda b: _convert(b.video_half, b.folder / "from_half_video.h5"), ValueError,
     r"video .*corrupt"),
    ("video-garbage", lambda b: _convert(b.video_garbage, b.folder / "from_garbage_video.h5"), ValueError,
     r"video .*corrupt"),
]


def _convert(source: Path, output: Path):
    from cmax.sim.convert import ConvertSettings, convert_video

    try:
        return convert_video(source, output, ConvertSettings(adaptive=False))
    finally:
        assert not output.exists() and not output.with_name(output.name + ".partial").exists()


@pytest.mark.parametrize("call, error, match", [pytest.param(*case[1:], id=case[0]) for case in FILE_CASES])
def test_bad_file_raises_clear_error(bad, call, error, match):
    with pytest.raises(error, match=match):
        call(bad)


def test_truncation_at_a_word_boundary_gives_a_prefix(shared_data, tmp_path):
    """EVT3 has no length field: a file cut at a word boundary cannot be told from a short
    recording; it decodes to a prefix of the events (documented in docs/bad_input.md)."""
    path = shared_data / "prophesee_gen4_driving" / "evt3_sample.raw"
    full = read_evt3(path)
    data = path.read_bytes()
    start = _read_header(path).data_offset
    cut = tmp_path / "cut.raw"
    cut.write_bytes(data[: start + 2 * ((len(data) - start) // 4)])
    part = read_evt3(cut)
    assert 0 < len(part) < len(full)
    assert part == full[: len(part)]


# -- the command line ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cli_file(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("cli")
    return write_h5(folder / "e.h5", random_events(500, width=64, height=48, t_span_us=100_000))


CLI_CASES = [
    ("unknown-command", ["emvs2"], r"invalid choice: 'emvs2'"),
    ("unknown-option", ["info", "{file}", "--frobnicate"], r"unrecognized arguments: --frobnicate"),
    ("info-missing-file", ["info", "{dir}/nope.h5"], r"cmax info: error: no such event file"),
    ("info-size-malformed", ["info", "{file}", "--size", "12"], r"argument --size: expected WIDTHxHEIGHT"),
    ("info-size-zero", ["info", "{file}", "--size", "0x0"], r"argument --size: width must be in \[1, 65535\]"),
    ("info-size-huge", ["info", "{file}", "--size", "60000x60000"], r"argument --size: a 60000x60000 sensor .* is larger than any event camera"),
    ("show-dt-nan", ["show", "{file}", "--dt", "nan"], r"cmax show: error: dt must be a finite number"),
    ("show-dt-inf", ["show", "{file}", "--dt", "inf"], r"cmax show: error: dt must be a finite number"),
    ("show-dt-negative", ["show", "{file}", "--dt", "-1"], r"dt must be positive"),
    ("show-t0-negative", ["show", "{file}", "--t0", "-1"], r"t0 must be >= 0"),
    ("show-dt-text", ["show", "{file}", "--dt", "soon"], r"argument --window-s/--dt: invalid float value"),
    ("show-bins-zero", ["show", "{file}", "--bins", "0"], r"bins must be >= 1"),
    ("show-bins-absurd", ["show", "{file}", "--bins", "1000000000"], r"bins=1000000000 on a 64x48 sensor"),
    ("show-mode", ["show", "{file}", "--mode", "movie"], r"argument --mode: invalid choice"),
    ("show-truncated-h5", ["show", "{dir}/half.h5"], r"cmax show: error: .* not a readable HDF5 file"),
    ("show-output-folder-missing", ["show", "{file}", "-o", "{dir}/no/such/folder/x.png"],
     r"cmax show: error: .*No such file or directory"),
    ("scene-unknown-preset", ["scene", "moon", "-o", "{dir}/s.h5"], r"argument preset: invalid choice"),
    ("scene-negative-duration", ["scene", "slider", "-o", "{dir}/s.h5", "--duration", "-1"],
     r"argument --duration: expected a finite number > 0"),
    ("scene-threshold-zero", ["scene", "slider", "-o", "{dir}/s.h5", "--cp", "0"],
     r"argument --cp: expected a finite number > 0"),
    ("simulate-missing-input", ["simulate", "{dir}/nope.mp4", "-o", "{dir}/o.h5"], r"input not found"),
    ("simulate-threshold-negative", ["simulate", "{file}", "-o", "{dir}/o.h5", "--cp", "-1"],
     r"cp must be a finite positive"),
    ("simulate-lam-nan", ["simulate", "{file}", "-o", "{dir}/o.h5", "--lam", "nan"], r"lam must be a positive"),
    ("simulate-bad-shard", ["simulate", "{dir}", "-o", "{dir}/out", "--shard", "5/2"], r"shard i/n needs"),
    ("simulate-bad-method", ["simulate", "{file}", "-o", "{dir}/o.h5", "--method", "magic"],
     r"argument --method: invalid choice"),
    ("simulate-not-a-video", ["simulate", "{dir}/notes.txt", "-o", "{dir}/o.h5"], r"INPUT must be a video"),
    ("manifest-binary", ["manifest", "merge", "{dir}/half.h5", "-o", "{dir}/m.json"], r"not a JSON manifest"),
    ("manifest-not-json", ["manifest", "merge", "{dir}/notes.txt", "-o", "{dir}/m.json"], r"not a JSON manifest"),
    ("fit-K-three-numbers", ["fit", "{file}", "--K", "1,2,3"], r"argument --K"),
    ("fit-K-nan", ["fit", "{file}", "--K", "nan,50,32,24"], r"--K: K must be finite"),
    ("fit-missing-file", ["fit", "{dir}/nope.h5", "--K", "50,50,32,24", "-o", "{dir}/fit"],
     r"cmax fit: error: no such event file"),
    ("emvs-K-three-numbers", ["emvs", "{file}", "--poses", "{dir}/t.txt", "-o", "{dir}/e", "--K", "1,2,3"],
     r"argument --K: --K must be fx,fy,cx,cy"),
    ("emvs-K-zero-focal", ["emvs", "{file}", "--poses", "{dir}/t.txt", "-o", "{dir}/e", "--K", "0,50,32,24"],
     r"argument --K: --K: K must have positive focal lengths"),
]


@pytest.mark.parametrize("argv, match", [pytest.param(*case[1:], id=case[0]) for case in CLI_CASES])
def test_bad_command_line_exits_2_with_one_line(cli_file, argv, match, capsys):
    folder = cli_file.parent
    (folder / "half.h5").write_bytes(cli_file.read_bytes()[:300])
    (folder / "notes.txt").write_text("videos: 3\n")
    argv = [arg.format(file=cli_file, dir=folder) for arg in argv]
    try:
        status = main(argv)
    except SystemExit as exit_:  # argparse's own errors
        status = exit_.code
    err = capsys.readouterr().err
    assert status == 2, err
    assert re.search(match, err), err
    assert "Traceback" not in err
    if not err.startswith("usage:"):
        assert err.strip().count("\n") == 0, err  # one line


@pytest.mark.parametrize("K, match", [("1,2,3", r"--K must be fx,fy,cx,cy"), ("50,nan,32,24", r"K must be finite")])
def test_learned_predict_rejects_a_bad_K(cli_file, K, match, capsys):
    """``python -m learned.predict --K`` shares ``cmax fit``'s parser: exit 2 and one line, no traceback."""
    from learned.predict import main as predict_main

    with pytest.raises(SystemExit) as exit_:
        predict_main([str(cli_file), "--checkpoint", str(cli_file), "-o", str(cli_file.parent / "p"), "--K", K])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and re.search(match, err) and "Traceback" not in err, err


def test_console_script_exit_status(cli_file):
    """The installed entry point (not only main()) exits 2 with the one-line message."""
    done = subprocess.run(
        [sys.executable, "-m", "cmax.cli", "show", str(cli_file), "--dt", "inf"],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith("cmax show: error: dt must be a finite")


def test_a_file_declaring_a_huge_sensor_is_refused_before_any_per_pixel_array(tmp_path):
    """A 70 kB h5 file declaring 16000 x 16000 pixels made ``cmax info`` build a 256-million-pixel count map per
    chunk (4 GB, 22 s for 5,000 events); 65535 x 65535 asked for tens of GB. Refused when the size is read."""
    import h5py

    from cmax.io import H5Reader, read

    with h5py.File(tmp_path / "big.h5", "w") as file:
        file.attrs["width"] = file.attrs["height"] = 16000
        for name, values in (("x", [1, 2]), ("y", [1, 2]), ("p", [0, 1]), ("t", [0, 10])):
            file[f"events/{name}"] = np.asarray(values, "u2" if name in "xy" else "u1" if name == "p" else "i8")
        file["ms_to_idx"] = np.zeros(2, "u8")
        file["t_offset"] = np.int64(0)
    for call in (lambda: read(tmp_path / "big.h5"), lambda: H5Reader(tmp_path / "big.h5")):
        _refused_within(50_000_000, call, ValueError, r"16000x16000 sensor \(256,000,000 pixels\) is larger than any")


@pytest.mark.parametrize("width, accepted", [(80.5, False), ("80.5", False), ([80, 2], False), (80.0, True),
                                             ("80", True), ([80], True)])
def test_an_h5_width_attribute_is_a_whole_number_or_refused(tmp_path, width, accepted):
    """A ``width`` of 80.5 was read as 80 without a word (``int()``); whole numbers in any form a writer stores
    them (80.0, "80", [80]) are read, anything else refused naming the file and the attribute."""
    import h5py

    from cmax.io import FormatError, read

    with h5py.File(tmp_path / "w.h5", "w") as file:
        file.attrs["width"], file.attrs["height"] = width, 60
        for name, values in (("x", [1, 2]), ("y", [1, 2]), ("p", [0, 1]), ("t", [0, 10])):
            file[f"events/{name}"] = np.asarray(values, "u2" if name in "xy" else "u1" if name == "p" else "i8")
        file["ms_to_idx"] = np.zeros(2, "u8")
        file["t_offset"] = np.int64(0)
    if accepted:
        assert read(tmp_path / "w.h5").width == 80
    else:
        with pytest.raises(FormatError, match=r"w.h5: its width attribute must be a whole number of pixels"):
            read(tmp_path / "w.h5")


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
def test_a_device_is_not_called_missing(capsys):
    """``cmax info /dev/zero`` said 'no such event file' about a path that exists."""
    from cmax.cli import main

    assert main(["info", "/dev/zero"]) == 2
    assert "/dev/zero is not a regular file (a device, a pipe or a socket)" in capsys.readouterr().err
