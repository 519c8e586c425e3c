"""``python -m learned.evaluate --checkpoint CKPT --data FILE [FILE ...]``: depth and motion metrics of a network.

Each file with ground truth (``cmax scene`` / ``SyntheticSequence.save``) is cut into
windows centred on its ground-truth depth times (:func:`held_out_windows`, through
:class:`learned.data.H5WindowDataset`, no augmentation), each with two pixel masks
(:func:`window_masks`): ``dense``, every pixel with valid ground truth up to the scene's
far limit (capped at 80 m as in ``benchmarks/accuracy.py``), and ``event``, the dense
pixels that hold at least one event of the window (the semi-dense protocol of EMVS-style
baselines). :func:`score_depth` scores any method's depth (NaN: no estimate, reported as
``coverage``) with :func:`cmax.metrics.depth_metrics`, pooled over a file's windows;
:func:`score_motion` its twist against the true twist at each window's middle
(:func:`cmax.metrics.motion_metrics`). The command line scores one network on the dense
mask; ``benchmarks/learned_table.py`` builds the table of every method on both masks.

:func:`objective_preferences` checks the contrast objective itself (issue 18, item 3):
on each window, is it lowest at the true depth and twist, or at the network's, or at a
constant depth?
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import h5py
import numpy as np
import torch

from cmax._args import ArgumentParser, add_duration_options, run_main
from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows
from cmax.events import Events
from cmax.io.atomic import write_text_atomic
from cmax.metrics import DepthMetrics, MotionMetrics, depth_metrics, motion_metrics
from cmax.representations import voxel_grid
from learned.checkpoint import CheckpointError, check_weights, load_checkpoint
from learned.config import config_from_dict
from learned.data import H5WindowDataset, Sample, collate
from learned.model import DepthPoseNet

__all__ = ["FileReport", "HeldOutWindow", "WindowPreference", "ObjectivePreferences", "load_model", "load_network",
           "repeated_files", "predict_batches", "far_limit", "depth_range", "event_mask", "window_masks", "check_ground_truth",
           "held_out_windows", "predict_windows",
           "no_pixels", "score_depth", "true_twists", "score_motion", "flat_depth_note", "evaluate_files",
           "candidate_parameters",
           "objective_preferences", "write_accuracy_csv", "main"]

CSV_COLUMNS = ("method", "sequence", "abs_mean_m", "rmse_log", "abs_rel", "err_10m", "err_20m", "err_30m",
               "coverage", "n_pixels")
FAR_LIMIT_M = 80.0


@dataclass(frozen=True, eq=False)
class FileReport:
    """Metrics of one file: its stem (``sequence``), the pooled ``depth`` metrics, the ``motion`` metrics (or None),
    the number of ``windows``, and the
    notes on how its camera differs from the one the network was trained with (:func:`learned.predict.camera_notes`:
    the depth a network infers from image motion scales with the focal length)."""

    sequence: str
    depth: DepthMetrics
    motion: MotionMetrics | None
    windows: int
    notes: tuple[str, ...] = ()


def load_model(checkpoint: str | Path) -> tuple[DepthPoseNet, dict]:
    """The network of a checkpoint (eval mode) and its config dict (validated).

    Raises FileNotFoundError or :class:`learned.checkpoint.CheckpointError` (a ValueError) for a
    missing, foreign, crafted or inconsistent checkpoint (see :func:`learned.checkpoint.load_checkpoint`).
    """
    model, config, _ = load_network(checkpoint)
    return model, config


def load_network(checkpoint: str | Path) -> tuple[DepthPoseNet, dict, dict | None]:
    """The network of a checkpoint (eval mode), its config dict (validated) and its card: the JSON file beside it
    (:func:`learned.pretrained.checkpoint_card`, ``student.json`` of the shipped ``student.pt``), else the record
    of its training data that ``learned.train`` stores in the checkpoint (``"card"``: ``"size": [W, H]`` [px], ``"K":
    [fx, fy, cx, cy]`` [px] when the training files share one focal length, ``"window_s"`` [s]), else None (a
    checkpoint of an earlier version). Where both are there, the checkpoint's record of its camera and window wins
    over the card's (a warning names the difference). Raises as :func:`load_model`."""
    from learned.pretrained import checkpoint_card

    ckpt = load_checkpoint(checkpoint)
    stated = ckpt["config"].get("model")
    levels = stated.get("levels") if isinstance(stated, dict) else None
    if isinstance(levels, int) and levels > len(ckpt["model"]):   # each level has weights; also bounds the checks
        raise CheckpointError(f"{checkpoint}: its model config has model.levels={levels}, its weights "
                              f"{len(ckpt['model'])} tensors: they do not fit")
    try:
        config = config_from_dict(ckpt["config"])
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{checkpoint}: its config is not valid: {error}") from None
    check_weights(config.model, ckpt["model"], checkpoint)   # on the meta device: a crafted config allocates nothing
    model = DepthPoseNet(config.model)
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as error:  # missing / unexpected keys, shapes that do not match the config
        raise CheckpointError(f"{checkpoint}: the weights do not match its model config "
                              f"({' '.join(str(error).split())[:300]})") from None
    card = checkpoint_card(checkpoint)
    if isinstance(ckpt.get("card"), dict):
        card = ckpt["card"] if card is None else _card_with_recorded_camera(card, ckpt["card"], checkpoint)
    return model.eval(), config.to_dict(), card


#: The entries of a card that ``learned.train`` measures from its training data and stores in the checkpoint.
_RECORDED_CAMERA = ("size", "K", "window_s")


def _card_with_recorded_camera(card: dict, recorded: dict, checkpoint: str | Path) -> dict:
    """The card beside ``checkpoint`` (``card``, :func:`learned.pretrained.checkpoint_card`) with the camera and
    window the checkpoint records of its own training data (``recorded``: ``"size": [W, H]`` [px], ``"K": [fx, fy,
    cx, cy]`` [px], ``"window_s"`` [s], as :func:`learned.train.training_card` measures them) in place of its own:
    a card that states another camera (copied from another model, edited) would silence the notes on a camera
    unlike the trained one. Warns (one line naming both) where they differ beyond 0.1%; the card's other entries
    (limits, scores) are kept."""
    import warnings

    differences = []
    for key in _RECORDED_CAMERA:
        if key not in recorded or key not in card:
            continue
        stated, measured = card[key], recorded[key]
        try:
            same = np.allclose(np.asarray(stated, float), np.asarray(measured, float), rtol=1e-3, atol=0.0)
        except (TypeError, ValueError):   # not numbers, or another count of them
            same = False
        if not same:
            differences.append(f"{key} {stated!r} (the checkpoint: {measured!r})")
    if differences:
        beside = Path(checkpoint).with_suffix(".json")
        warnings.warn(f"{beside}, the card beside {checkpoint}, states another camera or window than the checkpoint "
                      f"records of its training data: {'; '.join(differences)}; the checkpoint's record is used for "
                      "the notes on this camera", UserWarning, stacklevel=3)
    return {**card, **{key: recorded[key] for key in _RECORDED_CAMERA if key in recorded}}


@torch.no_grad()
def predict_batches(model: DepthPoseNet, dataset: torch.utils.data.Dataset, batch_size: int = 8):
    """Yield (batch, output) of ``model`` over ``dataset`` in order, ``batch_size`` windows at a time."""
    for start in range(0, len(dataset), batch_size):
        batch = collate([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))])
        yield batch, model(batch["volume"])


def far_limit(path: str | Path) -> float:
    """The far end [m] of the depth evaluated in the file at ``path``: its scene's ``depth_range_m[1]`` capped at
    :data:`FAR_LIMIT_M` (80 m, as ``benchmarks/accuracy.py``); :data:`FAR_LIMIT_M` when the file states none."""
    with h5py.File(path, "r") as f:
        scene = f.attrs.get("scene")
    try:
        far = float(json.loads(scene)["depth_range_m"][1]) if scene is not None else FAR_LIMIT_M
    except (TypeError, ValueError, KeyError):
        far = FAR_LIMIT_M
    return min(far, FAR_LIMIT_M)



def depth_range(path: str | Path) -> tuple[float, float]:
    """``(near, far)`` [m] of the scene of the file at ``path`` (``depth_range_m``), far capped as :func:`far_limit`; raises a
    ValueError when the file does not state its range (a depth sweep over a guessed range would not be fair)."""
    with h5py.File(path, "r") as f:
        scene = f.attrs.get("scene")
    try:
        near = float(json.loads(scene)["depth_range_m"][0])
    except (TypeError, ValueError, KeyError):
        raise ValueError(f"{path}: no scene depth_range_m in its attributes (a file of SyntheticSequence.save)") \
            from None
    return near, far_limit(path)


@dataclass(frozen=True, eq=False)
class HeldOutWindow:
    """One evaluation window of a file with ground truth, and its two pixel masks.

    Attributes
    ----------
    sequence : str
        The file's stem.
    sample : Sample
        The window's events (µs), ``K``, the true z-depth (H, W) [m] at its middle and the true twist
        ``(v m/s, omega rad/s)`` (6,) at its middle (or None when the file has no twists).
    dense : ndarray (H, W) bool
        Pixels with valid ground truth: finite, above 1 mm, at most ``far_m``.
    event : ndarray (H, W) bool
        ``dense`` and at least one event of the window at the pixel (the semi-dense protocol).
    far_m : float
        Far end of the evaluated depth [m] (:func:`far_limit`).
    """

    sequence: str
    sample: Sample
    dense: np.ndarray
    event: np.ndarray
    far_m: float

    @property
    def masks(self) -> dict[str, np.ndarray]:
        """``{"dense": ..., "event": ...}``."""
        return {"dense": self.dense, "event": self.event}


#: Ground truth at or below this depth [m] is not valid (:func:`cmax.metrics.depth_metrics`' ``min_depth``).
MIN_DEPTH_M = 1e-3


def event_mask(events: Events) -> np.ndarray:
    """Pixels (H, W) bool that hold at least one of ``events`` (integer sensor coordinates)."""
    hits = np.zeros((events.height, events.width), bool)
    hits[np.asarray(events.y, np.intp), np.asarray(events.x, np.intp)] = True
    return hits


def window_masks(depth: np.ndarray, events: Events, far_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The dense mask (valid true ``depth`` (H, W) [m]: finite, > 1 mm, <= ``far_m``) and the event mask
    (dense and an event of the window's ``events`` at the pixel), each (H, W) bool."""
    depth = np.asarray(depth)
    if depth.shape != (events.height, events.width):
        raise ValueError(f"depth is {depth.shape}, the events' sensor {(events.height, events.width)}")
    with np.errstate(invalid="ignore"):
        dense = np.isfinite(depth) & (depth > MIN_DEPTH_M) & (depth <= far_m)
    return dense, dense & event_mask(events)


def check_ground_truth(path: str | Path) -> None:
    """Raise a ValueError naming the file at ``path`` when it is no h5 file or holds no ground truth to evaluate
    against (``gt/depth`` and the ``gt/K`` it was made with); a FileNotFoundError when there is nothing at
    ``path``. Cheap (the file's index only): :func:`evaluate_files` checks every file
    with it before the network runs, so that a bad last file does not discard the others' metrics."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as file:
            depth, K = "gt/depth" in file, "gt/K" in file
            values = np.asarray(file["gt/K"][()], float) if K and isinstance(file["gt/K"], h5py.Dataset) else None
    except OSError:   # missing, or not an h5 file (a folder: H5WindowDataset names it)
        if not path.exists():
            raise FileNotFoundError(f"no such event file: {path}") from None
        if path.is_file():
            raise ValueError(f"{path} is not an HDF5 file: learned.evaluate scores the network against the ground "
                             f"truth (gt/depth, gt/K) of h5 files as cmax scene writes them; to predict depth on "
                             f"this file, run cmax depth {path} -o OUT") from None
        if path.is_dir():   # was named in training's words ("data.files lists h5 files one by one")
            found = len(list(path.glob("*.h5")))
            raise ValueError(f"{path} is a folder, not an event file: --data lists h5 files one by one"
                             + (f" (--data {path / '*.h5'}: the {found} .h5 files in it)" if found else
                                " (it holds no .h5 file)")) from None
        depth = K = True
    if not depth:
        raise ValueError(f"{path} has no {'gt/depth' if K else 'gt/K nor gt/depth'}: no ground truth to evaluate "
                         f"the network against (files of cmax scene hold it); to predict depth on this file, run "
                         f"cmax depth {path} -o OUT --K fx,fy,cx,cy")
    if not K:
        raise ValueError(f"{path} holds gt/depth but no gt/K, the intrinsics that depth was made with: add gt/K "
                         "(3x3, as cmax scene writes it) to evaluate against that depth")
    if values is not None and not np.isfinite(values).all():
        raise ValueError(f"{path}: gt/K holds NaN or infinite values ({values.tolist()}): the intrinsics its "
                         "gt/depth was made with are unknown, so the network's depth cannot be scored against it")


def repeated_files(files: Sequence[str | Path]) -> None:
    """Raise a ValueError naming the first file of ``files`` (paths, as ``--data`` gives them) that is listed twice,
    with both positions (1-based): its windows would be scored twice. Files are compared as files (``a.h5`` and
    ``./a.h5``, or a link to it, are one); paths that do not exist are left to :func:`check_ground_truth`.

    >>> repeated_files(["a.h5", "b.h5"])
    """
    first_of: dict[tuple[int, int], int] = {}
    for j, path in enumerate(files):
        try:
            status = os.stat(path)
        except OSError:
            continue
        key = (status.st_dev, status.st_ino)
        if key in first_of:
            raise ValueError(f"{path} is listed twice in --data (files {first_of[key] + 1} and {j + 1}: "
                             f"{files[first_of[key]]} and {path}): its windows would be scored twice; give each "
                             "file once")
        first_of[key] = j


def held_out_windows(path: str | Path, window_us: int, *, min_events: int = 10) -> list[HeldOutWindow]:
    """The windows (``window_us`` [µs] long, at least ``min_events`` events) of the file at ``path`` with ground
    truth, centred on its depth times (:class:`learned.data.H5WindowDataset`,
    no augmentation), with their masks. Raises a ValueError for a file without ``gt/`` or without a window."""
    path = Path(path)
    check_ground_truth(path)
    dataset = H5WindowDataset([path], window_us=int(window_us), max_events=1000, min_events=min_events)
    if dataset._gt[0] is None:
        raise ValueError(f"{path} has no gt/: evaluation needs ground truth")
    if len(dataset) == 0:
        raise ValueError(f"{path}: no window of {window_us} µs with ground truth and at least {min_events} events")
    far = far_limit(path)
    windows = []
    for i in range(len(dataset)):
        sample = dataset.sample(i)
        dense, event = window_masks(sample.depth, sample.events, far)
        windows.append(HeldOutWindow(path.stem, sample, dense, event, far))
    return windows


@torch.no_grad()
def predict_windows(model: DepthPoseNet, windows: Sequence[HeldOutWindow], batch_size: int = 8
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The network's full-resolution z-depth (N, H, W) float32 [m] and twist (N, 6) ``(v m/s, omega rad/s)``
    of ``model`` for each of ``windows`` (its event volume, :func:`learned.data.to_item`: spread bilinearly from the
    events' exact positions where the sample has them, ``Sample.pixels``), ``batch_size`` at a time."""
    depths, twists = [], []
    for start in range(0, len(windows), batch_size):
        volume = np.stack([voxel_grid(w.sample.events, model.config.bins, pixels=w.sample.pixels)
                           for w in windows[start:start + batch_size]])
        out = model(torch.from_numpy(volume))
        depths.append(out.depth[:, 0].numpy()), twists.append(out.twist.numpy())
    return np.concatenate(depths).astype(np.float32), np.concatenate(twists).astype(np.float64)


def no_pixels(cutoffs: tuple[float, ...] = (10.0, 20.0, 30.0)) -> DepthMetrics:
    """Metrics of a method with no estimate on any pixel of the mask: NaN errors (also within each of ``cutoffs``
    [m]), coverage 0."""
    nan = float("nan")
    return DepthMetrics(nan, nan, nan, nan, nan, nan, nan, nan, {c: nan for c in cutoffs}, n_pixels=0,
                        coverage=0.0, n_frames=0)


def score_depth(pred: np.ndarray, windows: Sequence[HeldOutWindow], mask: str) -> DepthMetrics:
    """Pooled :func:`cmax.metrics.depth_metrics` of predicted z-depths ``pred`` (N, H, W) [m] (NaN: no estimate)
    against the windows' truth, on their ``mask`` ("dense" or "event"); ``coverage`` is the share of the mask's
    pixels that have an estimate. A method with no estimate on the mask gets :func:`no_pixels`."""
    if mask not in ("dense", "event"):
        raise ValueError(f"mask must be 'dense' or 'event', got {mask!r}")
    pred = np.asarray(pred)
    if pred.shape != (len(windows),) + windows[0].dense.shape:
        raise ValueError(f"pred is {pred.shape}, the windows need {(len(windows),) + windows[0].dense.shape}")
    gt = np.stack([w.sample.depth for w in windows])
    masks = np.stack([w.masks[mask] for w in windows])
    with np.errstate(invalid="ignore"):
        if not (masks & np.isfinite(pred) & (pred > 0)).any():
            return no_pixels()
    return depth_metrics(pred, gt, mask=masks, max_depth=max(w.far_m for w in windows))


def true_twists(windows: Sequence[HeldOutWindow]) -> np.ndarray | None:
    """The true twist (N, 6) at the middle of each of ``windows``; None when the file has no twists."""
    if any(w.sample.twist is None for w in windows):
        return None
    return np.stack([np.asarray(w.sample.twist, np.float64) for w in windows])


def score_motion(twists: np.ndarray, windows: Sequence[HeldOutWindow]) -> MotionMetrics | None:
    """:func:`cmax.metrics.motion_metrics` of predicted twists (N, 6) or one twist (6,) for every window
    against the true twist at the middle of each of ``windows``; None when the file has no twists."""
    truth = true_twists(windows)
    if truth is None:
        return None
    twists = np.broadcast_to(np.asarray(twists, np.float64), truth.shape)
    return motion_metrics(twists[:, :3], twists[:, 3:], truth[:, :3], truth[:, 3:])


def no_valid_depth_note(windows: Sequence[HeldOutWindow]) -> str | None:
    """A note for windows none of whose true depth pixels is valid (finite, above 1 mm, at most the far limit),
    whose depth metrics are therefore NaN: the span of the finite true depths [m], which tells depth in another
    unit (millimetres beyond the far limit) from a map of NaN; None when some pixel is valid."""
    if any(w.dense.any() for w in windows):
        return None
    finite = np.concatenate([np.asarray(w.sample.depth, np.float64)[np.isfinite(w.sample.depth)] for w in windows])
    far = max(w.far_m for w in windows)
    held = (f"its finite true depths span {finite.min():g} to {finite.max():g}" if finite.size
            else "its true depth is NaN or infinite everywhere")
    return (f"no pixel of its ground-truth depth (gt/depth) is valid in any of the {len(windows)} windows (finite, "
            f"above {MIN_DEPTH_M * 1e3:g} mm, at most the far limit {far:g} m; {held}): no depth metric can be "
            "computed (NaN); gt/depth must hold z-depth in metres")


def flat_depth_note(pred: np.ndarray, windows: Sequence[HeldOutWindow], metrics: DepthMetrics) -> str | None:
    """A note when the predicted z-depths ``pred`` (N, H, W) [m] of ``windows`` score worse (abs_rel and rmse_log
    both) on the dense mask than one constant depth, the median of ``pred`` itself there: the per-pixel structure of
    the maps adds nothing to their overall scale (an untrained or collapsed network), which the metrics ``metrics``
    (:func:`score_depth` of ``pred``) alone do not tell. The constant takes no ground truth; None otherwise."""
    pred = np.asarray(pred)
    masks = np.stack([w.dense for w in windows])
    with np.errstate(invalid="ignore"):
        values = pred[masks & np.isfinite(pred) & (pred > 0)]
    if values.size == 0:
        return None
    level = float(np.median(values))
    flat = score_depth(np.full(pred.shape, level, np.float32), windows, "dense")
    if not (flat.abs_rel < metrics.abs_rel and flat.rmse_log < metrics.rmse_log):
        return None
    return (f"one constant depth, the median of the network's own depths ({level:.3g} m), scores abs_rel "
            f"{flat.abs_rel:.3f} and rmse_log {flat.rmse_log:.3f}, better than the network's {metrics.abs_rel:.3f} "
            f"and {metrics.rmse_log:.3f}: its depth maps carry nothing here beyond their overall scale (an untrained "
            "or collapsed network?)")


def evaluate_files(checkpoint: str | Path, files: Sequence[str | Path], *, window_s: float | None = None,
                   batch_size: int = 8) -> list[FileReport]:
    """Metrics of ``checkpoint`` on each of ``files`` (with ground truth), on the dense mask
    (:func:`held_out_windows`); windows of ``window_s`` [s] (None: the checkpoint config's ``data.window_us``),
    ``batch_size`` at a time."""
    from learned.predict import camera_notes, window_note

    model, config, card = load_network(checkpoint)   # first: a refused checkpoint is named before any file
    for path in files:   # every file checked before the network runs on any
        check_ground_truth(path)
    repeated_files(files)
    window_us = int(round(window_s * 1e6)) if window_s is not None else int(config["data"]["window_us"])
    if window_us < 1:
        raise ValueError(f"the window must be at least 1 µs long, got {window_s} s")
    window = window_note(int(config["data"]["window_us"]), window_us)
    reports = []
    for path in map(Path, files):
        windows = held_out_windows(path, window_us)
        depth, twist = predict_windows(model, windows, batch_size)
        if not (np.isfinite(depth).all() and np.isfinite(twist).all()):   # finite weights that overflow
            bad = sorted({int(i) for i in np.flatnonzero(~np.isfinite(depth).all(axis=(1, 2)))}
                         | {int(i) for i in np.flatnonzero(~np.isfinite(twist).all(axis=1))})
            raise ValueError(f"{checkpoint} gives a non-finite output (NaN or infinite depth or twist) on {len(bad)} "
                             f"of the {len(windows)} windows of {path} (e.g. window {bad[0]}): its weights overflow "
                             "on these events (a diverged or corrupt checkpoint?); no metric can be computed")
        metrics = score_depth(depth, windows, "dense")
        first = windows[0].sample
        notes = camera_notes(card, first.events.width, first.events.height, np.asarray(first.K, float),
                             f"the card of {checkpoint}") + ([window] if window else [])
        invalid = no_valid_depth_note(windows)
        flat = flat_depth_note(depth, windows, metrics)
        notes = [*notes, *([invalid] if invalid else []), *([flat] if flat else [])]
        reports.append(FileReport(path.stem, metrics, score_motion(twist, windows), len(windows), tuple(notes)))
    return reports


#: The candidates of :func:`objective_preferences`, in the order they are reported.
CANDIDATES = ("truth", "network", "network depth + true twist", "constant depth + true twist")


@dataclass(frozen=True)
class WindowPreference:
    """The objective's value (lower is better) at each candidate of one window (of file ``sequence``, ``[t0_us,
    t1_us)`` [µs]), and the ``lowest`` candidate.

    ``values`` maps each of :data:`CANDIDATES` to the objective's value; ``speed_m_s`` is the known speed
    [m/s] the objective scaled every twist to (the true ``|v|`` at the window's middle).
    """

    sequence: str
    t0_us: int
    t1_us: int
    speed_m_s: float
    values: dict[str, float]
    lowest: str


@dataclass(frozen=True)
class ObjectivePreferences:
    """:func:`objective_preferences` over all windows: each window's values and how often each candidate won
    (``counts``: candidate -> windows)."""

    windows: tuple[WindowPreference, ...]
    counts: dict[str, int]


def candidate_parameters(window: HeldOutWindow, network_depth: np.ndarray, network_twist: np.ndarray
                         ) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Inverse depth (H, W) [1/m] and twist (6,) of each of :data:`CANDIDATES` for one window, given the
    network's ``network_depth`` (H, W) [m] and ``network_twist`` (6,).

    The true inverse depth takes the far limit where the truth is invalid (NaN sky, beyond ``far_m``); the
    constant is the median of the valid true depth; the network's depth is clipped to ``(0, far_m]`` likewise.
    """
    depth = np.asarray(window.sample.depth, np.float64)
    if not window.dense.any():
        raise ValueError(f"{window.sequence} window at {window.sample.t0_us} µs has no valid true depth")
    if window.sample.twist is None:
        raise ValueError(f"{window.sequence}: the objective check needs the true twist (gt/twists)")
    truth = 1.0 / np.where(window.dense, depth, window.far_m)
    network = 1.0 / np.clip(np.asarray(network_depth, np.float64), MIN_DEPTH_M, window.far_m)
    constant = np.full_like(truth, 1.0 / float(np.median(depth[window.dense])))
    twist = np.asarray(window.sample.twist, np.float64)
    network_twist = np.asarray(network_twist, np.float64)
    return dict(zip(CANDIDATES, ((truth, twist), (network, network_twist), (network, twist), (constant, twist))))


def window_preference(window: HeldOutWindow, network_depth: np.ndarray, network_twist: np.ndarray,
                      objective: object, *, max_events: int | None = None, seed: int = 0) -> WindowPreference:
    """The objective at each of :data:`CANDIDATES` of one window (its events as one
    :class:`cmax.contrast.EventWindows` with the true speed; float64)."""
    speed = float(np.linalg.norm(np.asarray(window.sample.twist, np.float64)[:3]))
    batch = EventWindows.from_events(window.sample.events, window.sample.K, speed=speed, max_events=max_events,
                                     seed=seed, dtype=torch.float64)
    values = {}
    with torch.no_grad():
        for name, (inverse, twist) in candidate_parameters(window, network_depth, network_twist).items():
            params = DepthMotion(torch.from_numpy(np.ascontiguousarray(inverse))[None, None],
                                 torch.from_numpy(twist)[None])
            values[name] = float(objective(batch, params)[0])
    return WindowPreference(window.sequence, int(window.sample.t0_us), int(window.sample.t1_us), speed, values,
                            min(values, key=values.get))


def objective_preferences(files: Sequence[str | Path], checkpoint: str | Path, objective: object = SHARED_OBJECTIVE, *,
                          window_s: float | None = None, max_events: int | None = None
                          ) -> ObjectivePreferences:
    """Which of :data:`CANDIDATES` the contrast ``objective`` (``objective(batch, params) -> (B,)``)
    finds lowest on each held-out window of ``files`` (issue 18 item 3: does the loss prefer the truth?).

    Every window (:func:`held_out_windows`, length from the checkpoint's ``data.window_us`` unless
    ``window_s``) is scored at the true inverse depth and true twist, at the network's depth and twist, at the
    network's depth with the true twist, and at a constant depth (the median true depth) with the true twist;
    the objective scales every twist's ``v`` to the window's true speed (:func:`cmax.contrast.twist_at_speed`).
    ``max_events``: a seeded uniform subset of each window's events (default the checkpoint's
    ``data.max_events``, as in training).
    """
    model, config = load_model(checkpoint)
    window_us = int(round(window_s * 1e6)) if window_s is not None else int(config["data"]["window_us"])
    max_events = int(config["data"]["max_events"]) if max_events is None else int(max_events)
    results = []
    for path in files:
        windows = held_out_windows(path, window_us)
        depths, twists = predict_windows(model, windows)
        results += [window_preference(w, d, t, objective, max_events=max_events)
                    for w, d, t in zip(windows, depths, twists)]
    counts = {name: sum(r.lowest == name for r in results) for name in CANDIDATES}
    return ObjectivePreferences(tuple(results), counts)


def csv_row(method: str, report: FileReport) -> dict[str, object]:
    m = report.depth
    return {"method": method, "sequence": report.sequence, "abs_mean_m": m.abs_mean, "rmse_log": m.rmse_log,
            "abs_rel": m.abs_rel, "err_10m": m.cutoff_errors[10.0], "err_20m": m.cutoff_errors[20.0],
            "err_30m": m.cutoff_errors[30.0], "coverage": m.coverage, "n_pixels": m.n_pixels}


def write_accuracy_csv(path: str | Path, rows: Sequence[tuple[str, FileReport]]) -> Path:
    """The rows (method, report) as ``accuracy_learned.csv`` at ``path`` (columns of ``benchmarks/accuracy.py``),
    atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for method, report in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in csv_row(method, report).items()})
    return write_text_atomic(path, buffer.getvalue())


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m learned.evaluate`` with the arguments ``argv`` (None: the command line's); returns
    the exit status (2 and one line for a bad argument or file)."""
    parser = ArgumentParser(prog="python -m learned.evaluate", description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True, help="checkpoint of learned.train (last.pt)")
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="h5 files with gt/")
    add_duration_options(parser, "window", dest="window", unit="s", help="window length",
                         default="the checkpoint config's data.window_us", aliases=("--window",))
    return run_main(parser, _run, argv)


def _run(args: argparse.Namespace) -> int:
    for report in evaluate_files(args.checkpoint, args.data, window_s=args.window):
        for note in report.notes:
            print(f"learned.evaluate: note: {report.sequence}: {note}", file=sys.stderr)
        m = report.depth
        line = (f"{report.sequence}: {report.windows} windows  abs_mean {m.abs_mean:.3f} m  abs_rel {m.abs_rel:.3f}  "
                f"rmse_log {m.rmse_log:.3f}  delta1 {m.delta1:.3f}  "
                + "  ".join(f"<{c:g}m {e:.3f}" for c, e in m.cutoff_errors.items()))
        if report.motion is not None:
            line += (f"  omega_rms {report.motion.omega_rms_deg_s:.2f} deg/s  v_rms {report.motion.v_rms_m_s:.3f} m/s")
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
