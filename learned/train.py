"""``python -m learned.train [--mode teacher|finetune|student] --config CONFIG [key=value ...] [--resume]``.

Modes (EvtSlowTV section 5):

* ``teacher`` (EvtSL): ``L_si + lambda L_grad`` on files with ground truth (plus, by
  default, a twist term: ``train.twist_weight``);
* ``finetune`` (EvtSL -> EvtSSL): the teacher's weights trained further with the contrast loss;
* ``student`` (EvtSL -> EvtSSL-bar): a fresh network, ``L_contrast + (1 - lambda) L1`` to the frozen teacher.

Data order: the global batch of step ``s`` is a fixed function of ``(seed, s)``
(a seeded permutation per epoch), so a resumed run sees the same batches; in a
``torchrun`` job rank ``r`` of ``R`` takes entries ``r, r + R, ...`` of each
global batch (the role of a ``DistributedSampler``), gradients are averaged by
``DistributedDataParallel`` (gloo on the CPU; with ``train.device=cuda`` nccl, each rank on the GPU of its
``LOCAL_RANK``), and only rank 0 writes (a ``RANK`` that no ``torchrun`` job set is refused:
:func:`distributed_rank`).
Checkpoints (``out/last.pt``) hold the model, optimiser, step, config and RNG
states and are written atomically; ``--resume`` continues bit-for-bit on CPU, and refuses a config that
differs from the checkpoint's in a field that changes the steps still to run (:func:`config_differences`,
:data:`RESUMABLE`). One run at a time holds
``train.out`` (its lock :data:`FOLDER_LOCK`): a second one into the same folder is refused at once.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import sys
import threading
import warnings
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch
from tqdm import tqdm

from cmax._args import ArgumentParser, run_main
from cmax._threads import torch_threads
from cmax.contrast import SHARED_OBJECTIVE, CollapseGuard, EventWindows, WeightedSum
from cmax.io.atomic import check_unchanged, file_sha256, write_text_atomic
from cmax.io.window_store import HASH_PROGRESS_BYTES   # the one threshold of the hashing bars
from learned._output import locked_folder
from learned.checkpoint import (CheckpointError, load_checkpoint, nonfinite_tensors, rng_state, save_checkpoint,
                                set_rng_state)
from learned.config import Config, config_from_dict, load_config
from learned.data import H5WindowDataset, collate
from learned.device import resolve_device
from learned.losses import student_loss, teacher_loss
from learned.model import DepthPoseNet, ModelConfig, NetOutput


def ddp_backend(device: torch.device) -> str:
    """The process group of a ``torchrun`` job on ``device``: nccl between GPUs, gloo between CPUs (nccl refuses
    CPU tensors)."""
    return "nccl" if device.type == "cuda" else "gloo"


def on_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """A collated batch with every tensor on ``device`` (the others as they are)."""
    return {key: value.to(device, non_blocking=True) if isinstance(value, torch.Tensor) else value
            for key, value in batch.items()}


#: The lock a run holds on its ``train.out`` (:func:`learned._output.locked_folder`), inside that folder.
FOLDER_LOCK = ".train.lock"

#: Steps between two choices of torch's thread count (:func:`cmax._threads.torch_threads`: the cores less the
#: load of other processes; ``CMAX_TORCH_THREADS`` fixes it).
THREAD_CHECK_EVERY = 25

__all__ = ["FOLDER_LOCK", "TrainingDiverged", "batch_indices", "learning_rate", "twist_scale", "ddp_backend",
           "on_device", "nonfinite_terms", "global_mean", "drop_log_lines_after", "clear_tensorboard", "RUN_FILES",
           "clear_earlier_run", "RESUMABLE", "file_fingerprint", "data_fingerprints", "bytes_to_hash",
           "HASH_PROGRESS_BYTES", "fingerprint_differences", "repeated_files", "calibration_sha256",
           "training_card", "schedule_note", "unread_settings",
           "config_differences", "resolved_paths", "distributed_rank", "loss_outputs", "LossOutputs", "Trainer",
           "check_output", "earlier_curves", "check_optimizer_state", "main"]

def global_mean(values: dict[str, float], *, world: int, device: torch.device) -> dict[str, float]:
    """``values`` (one rank's loss terms) averaged over the ``world`` ranks of a ``torchrun`` job: with equal
    local batches (``train.batch_size`` a multiple of the ranks) the mean of the ranks' batch means is the
    global batch's mean, what one process with the whole batch logs (and what DDP's averaged gradients
    optimise). A collective: every rank calls it with the same keys in the same order. ``values`` as they are
    when ``world`` is 1. A NaN or an infinity on any rank makes that term non-finite on every rank.

    >>> import torch
    >>> global_mean({"total": 0.5}, world=1, device=torch.device("cpu"))
    {'total': 0.5}
    """
    if world == 1:
        return dict(values)
    summed = torch.tensor(list(values.values()), dtype=torch.float64, device=device)
    torch.distributed.all_reduce(summed)
    return dict(zip(values, (summed / world).tolist()))


def drop_log_lines_after(path: Path, step: int) -> int:
    """Keep in the learning curves ``path`` (``log.jsonl``) only the lines of steps up to ``step`` (a resumed run's
    checkpoint): a run killed after its last checkpoint logged steps that the resumed run logs again. A line that
    is not a whole JSON record (the half-written last line of a killed run) goes too. Rewritten atomically when
    anything goes; returns the number of lines dropped (0 when there is no such file)."""
    if not path.is_file() or path.is_symlink():
        return 0
    kept, dropped = [], 0
    for line in path.read_text("utf-8", errors="replace").splitlines():
        try:
            record = json.loads(line)
            keep = isinstance(record, dict) and isinstance(record.get("step"), int) and record["step"] <= step
        except ValueError:
            keep = False
        if keep:
            kept.append(line)
        else:
            dropped += 1
    if dropped:
        write_text_atomic(path, "".join(line + "\n" for line in kept))
    return dropped


def clear_tensorboard(folder: Path) -> list[Path]:
    """Remove TensorBoard's event files (``events.out.tfevents.*``, regular files only: a link is never followed)
    from ``folder`` (a run's ``tb/``), and ``folder`` itself when that leaves it empty; returns the files removed.
    ``--overwrite``: the new run's learning curves alone."""
    if folder.is_symlink() or not folder.is_dir():
        return []
    removed = [file for file in sorted(folder.glob("events.out.tfevents.*"))
               if file.is_file() and not file.is_symlink()]
    for file in removed:
        file.unlink()
    try:
        folder.rmdir()
    except OSError:   # something else is in it
        pass
    return removed


#: The files a run writes in its ``train.out`` besides TensorBoard's ``tb/``: what ``--overwrite`` removes of an
#: earlier run (:func:`clear_earlier_run`).
RUN_FILES = ("last.pt", "config.json", "log.jsonl")


def clear_earlier_run(out: Path) -> list[Path]:
    """Remove an earlier run's outputs from ``out`` (``--overwrite``): :data:`RUN_FILES` (a link at one of those
    names is removed itself, never followed; a folder is left) and TensorBoard's event files
    (:func:`clear_tensorboard`). Returns the paths removed.

    The command calls it under the folder's lock once the new run's config and data are checked, before the first
    step: a new run that fails before its first checkpoint then leaves no checkpoint of another run beside its own
    ``config.json`` and ``log.jsonl``."""
    removed = []
    for name in RUN_FILES:
        path = out / name
        if path.is_symlink() or path.is_file():
            path.unlink()
            removed.append(path)
    return removed + clear_tensorboard(out / "tb")


#: The config fields a ``--resume`` may change: how far the run goes, where it runs and writes, and how often it
#: logs, validates and saves. Any other field (the mode, the model, the data, the seed, the batch, the
#: optimisation) changes the steps still to run, so a resumed run that sets it otherwise is refused.
RESUMABLE = frozenset({"train.steps", "train.out", "train.device", "train.checkpoint_every", "train.log_every",
                       "train.image_every", "train.val_every", "data.val_files", "data.val_windows"})


def _fields(config: Config, paths: dict | None = None) -> dict[str, object]:
    """``{"mode": ..., "model.width": ..., ...}``: every field of ``config`` under its dotted key, as plain JSON
    data (tuples as lists); with ``paths`` (:func:`resolved_paths`), the data files and the teacher by the absolute
    paths it gives in place of the paths as typed."""
    values = json.loads(json.dumps(config.to_dict(), default=str))
    flat: dict[str, object] = {"mode": values.pop("mode")}
    for section, fields in values.items():
        flat.update({f"{section}.{name}": value for name, value in fields.items()})
    if paths is not None:
        flat["data.files"] = [{**entry, "path": path} if isinstance(entry, dict) else path
                              for entry, path in zip(flat["data.files"], paths["data.files"])]
        flat["train.teacher"] = paths["train.teacher"]
        if "data.calibrations" in paths:   # checkpoints of earlier versions compare them as typed
            flat["data.files"] = [{**entry, **{key: path for key, path in files.items() if key in entry}}
                                  if isinstance(entry, dict) else entry
                                  for entry, files in zip(flat["data.files"], paths["data.calibrations"])]
    return flat


def resolved_paths(config: Config) -> dict[str, object]:
    """``{"data.files": [absolute path, ...], "train.teacher": absolute path or "", "data.calibrations": [{"calib":
    absolute path, "rectify_map": ...} (the keys each entry gives), ...]}``: the files a run of ``config`` reads, as
    a checkpoint records them so that ``--resume`` compares files, not spellings (``a.h5`` and ``./a.h5`` are one
    file; ``a.h5`` typed in another folder is another)."""
    def absolute(path: object) -> str:
        return str(Path(path).expanduser().resolve())

    return {"data.files": [absolute(entry["path"] if isinstance(entry, dict) else entry)
                           for entry in config.data.files],
            "train.teacher": absolute(config.train.teacher) if config.train.teacher else "",
            "data.calibrations": [{key: absolute(entry[key]) for key in ("calib", "rectify_map")
                                   if isinstance(entry, dict) and isinstance(entry.get(key), str)}
                                  for entry in config.data.files]}


def config_differences(recorded: Config, now: Config, recorded_paths: dict | None = None) -> list[str]:
    """``"key=RECORDED (now NOW)"`` for each field outside :data:`RESUMABLE` in which ``now`` differs from
    ``recorded`` (a checkpoint's config), in the config's order (``mode``, ``model.*``, ``data.*``, ``train.*``).
    With ``recorded_paths`` (the checkpoint's :func:`resolved_paths`), the data files and the teacher are compared
    as the files they name; without (a checkpoint of an earlier version), as typed."""
    paths_now = None if recorded_paths is None else resolved_paths(now)
    if paths_now is not None and not isinstance(recorded_paths.get("data.calibrations"), list):
        paths_now.pop("data.calibrations")   # a checkpoint of an earlier version: its calibrations as typed
    before, after = _fields(recorded, recorded_paths), _fields(now, paths_now)
    return [f"{key}={json.dumps(before[key])} (now {json.dumps(after[key])})" for key in before
            if key not in RESUMABLE and before[key] != after.get(key)]


#: Bytes read from each end of a data file for the ``ends_sha256`` of its :func:`file_fingerprint` (the whole of a
#: smaller file), which checkpoints of earlier versions record alone.
FINGERPRINT_BYTES = 1 << 16




def _marks(stat: os.stat_result) -> list[int]:
    """What a file's ``stat`` says changed it, besides its size: its modification time [ns], inode and status
    change time [ns] (``st_ctime_ns``: set by the system on any write, and on setting the modification time back,
    never to a chosen value)."""
    return [int(stat.st_mtime_ns), int(stat.st_ino), int(stat.st_ctime_ns)]


def _recorded_sha256(size: int, marks: list[int], recorded: object) -> str | None:
    """The ``sha256`` of a file's ``recorded`` fingerprint when its size [bytes] and ``marks`` (:func:`_marks`)
    equal the file's ``size`` and ``marks`` now (the file need not be read again), else None."""
    known = (recorded.get("sha256") if isinstance(recorded, dict) and recorded.get("bytes") == size
             and recorded.get("stat") == marks else None)
    return known if isinstance(known, str) else None


def bytes_to_hash(path: str | Path, recorded: object = None) -> int:
    """Bytes [B] that :func:`file_fingerprint` reads to hash the whole file at ``path``: its size, or 0 when its
    ``recorded`` fingerprint's SHA-256 is taken instead."""
    stat = Path(path).stat()
    known = _recorded_sha256(int(stat.st_size), _marks(stat), recorded)
    return 0 if known is not None else int(stat.st_size)


def data_fingerprints(paths: list, counts: list[int], spans: list[tuple[int, int]], recorded: list, *,
                      progress: bool = True) -> list[dict[str, object]]:
    """The :func:`file_fingerprint` of each data file ``paths[i]`` (``counts[i]`` events over ``spans[i]`` [µs],
    ``recorded[i]``: its fingerprint in the checkpoint resumed, or None), with a progress bar [bytes] on stderr
    while the whole files are hashed when they hold more than :data:`HASH_PROGRESS_BYTES` (``progress``: allowed)."""
    total = sum(bytes_to_hash(path, known) for path, known in zip(paths, recorded))
    bar = tqdm(total=total, desc="hashing data files (checked by --resume)", unit="B", unit_scale=True,
               unit_divisor=1024, disable=not progress or total <= HASH_PROGRESS_BYTES)
    with bar:
        return [file_fingerprint(path, count, span, recorded=known, read=bar.update)
                for path, count, span, known in zip(paths, counts, spans, recorded)]


def file_fingerprint(path: str | Path, events: int, span_us: tuple[int, int], *,
                     recorded: object = None, read: Callable[[int], None] | None = None) -> dict[str, object]:
    """What ``--resume`` compares of one data file at ``path``: ``{"bytes": size, "events": events, "span_us":
    [first, last], "sha256": ..., "ends_sha256": ..., "stat": [mtime_ns, inode, ctime_ns]}``: the file's size [bytes], its
    number of ``events`` and their time span ``span_us`` (first, last) [µs] (as :class:`learned.data.H5WindowDataset`
    read them), the SHA-256 of the whole file (:func:`cmax.io.atomic.file_sha256`), that of its first and last
    :data:`FINGERPRINT_BYTES` (what earlier versions recorded), and its modification time [ns], inode and status
    change time [ns].

    ``recorded``: this file's fingerprint in the checkpoint being resumed; when its size, modification time, inode
    and status change time equal the file's now, its ``sha256`` is taken instead of reading the file again (a file
    rewritten in place whose modification time was then set back, ``touch -d`` or ``cp -p`` onto the same inode,
    has another status change time: it is read again; so is a file whose mode or owner changed).
    Another recording copied over the file, or any byte of it changed, changes the whole file's SHA-256. A file
    whose size or modification time changes while it is hashed (still being written or copied) is refused
    (:func:`cmax.io.atomic.check_unchanged`, ValueError naming it).
    ``read``: called with the bytes [B] of each chunk hashed (a progress bar's ``update``), or None."""
    path = Path(path)
    stat = path.stat()
    size, marks = int(stat.st_size), _marks(stat)
    ends = hashlib.sha256()
    known = _recorded_sha256(size, marks, recorded)
    with open(path, "rb") as file:
        ends.update(file.read(FINGERPRINT_BYTES))
        if size > FINGERPRINT_BYTES:
            file.seek(max(FINGERPRINT_BYTES, size - FINGERPRINT_BYTES))
            ends.update(file.read())
    if not isinstance(known, str):
        known = file_sha256(path, read)
        check_unchanged([path], [stat])      # a file still being written or copied: its hash stands for no file
    return {"bytes": size, "events": int(events), "span_us": [int(span_us[0]), int(span_us[1])],
            "sha256": known, "ends_sha256": ends.hexdigest(), "stat": marks}


#: Keys of a :func:`file_fingerprint` that are not compared as such: the contents' hashes (compared in
#: :func:`fingerprint_differences`) and the modification time and inode (a copy of the same bytes differs in them).
_NOT_COMPARED = ("sha256", "ends_sha256", "stat")


def fingerprint_differences(recorded: object, now: list[dict[str, object]], names: list[str]) -> list[str]:
    """``"data.files[i] NAME: events 6282 (now 8693), ..."`` for each data file (called ``names[i]``) whose
    :func:`file_fingerprint` ``now`` differs from the ``recorded`` one (a checkpoint's ``data_order["files"]``):
    in size, events or span, else in the SHA-256 of the whole file (of its first and last 64 KiB where the checkpoint,
    of an earlier version, records only those); empty when they agree or nothing (a checkpoint of an earlier
    version) or another number of files is recorded."""
    if not isinstance(recorded, list) or len(recorded) != len(now):
        return []
    differ = []
    for i, (before, after) in enumerate(zip(recorded, now)):
        if not isinstance(before, dict):
            continue
        changed = [f"{key} {json.dumps(before.get(key))} (now {json.dumps(value)})" for key, value in after.items()
                   if key not in _NOT_COMPARED and before.get(key) != value]
        if not changed and "sha256" in before:
            if before["sha256"] != after["sha256"]:
                changed = ["its contents (the SHA-256 of the whole file)"]
        elif not changed and before.get("ends_sha256") != after["ends_sha256"]:
            changed = ["its contents (the SHA-256 of its first and last 64 KiB)"]
        if changed:
            differ.append(f"data.files[{i}] {names[i]}: {', '.join(changed)}")
    return differ


def calibration_sha256(specs: list) -> list[dict[str, str | None]]:
    """``[{"calib": SHA-256 (hex) or None, "rectify_map": ...}, ...]``: the contents of each data file's calibration
    files (:class:`learned.data.FileSpec` ``specs[i]``'s ``calib`` and ``rectify_map``; None where it gives none),
    as a checkpoint records them so that ``--resume`` compares the files' bytes, not their paths alone."""
    return [{key: None if getattr(spec, key) is None else file_sha256(getattr(spec, key))
             for key in ("calib", "rectify_map")} for spec in specs]


def training_card(dataset: H5WindowDataset, window_us: int, tolerance: float = 0.05) -> dict[str, object]:
    """The camera and window a network trained on ``dataset`` with windows of ``window_us`` [µs] learned from, as a
    card (the keys of the shipped ``student.json``: ``"size": [W, H]`` [px], ``"K": [fx, fy, cx, cy]`` [px] of the
    first file, ``"window_s"`` [s]); ``"K"`` is left out when the files' focal lengths differ by more than
    ``tolerance`` (a fraction). Checkpoints store it, so that ``cmax depth`` and ``learned.evaluate`` note another
    camera or window (:func:`learned.predict.camera_notes`, :func:`learned.predict.window_note`)."""
    Ks = [np.asarray(gt["K"] if gt is not None else spec.K, float) for spec, gt in zip(dataset.specs, dataset._gt)
          if gt is not None or spec.K is not None]
    card: dict[str, object] = {"size": [int(dataset.width), int(dataset.height)]}
    if Ks:
        fx = np.array([[K[0, 0], K[1, 1]] for K in Ks])
        if np.all(np.abs(fx / fx[0] - 1.0) <= tolerance):
            K = Ks[0]
            card["K"] = [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]
    card["window_s"] = window_us / 1_000_000
    return card


#: The settings of ``train`` that a mode does not read, and what reads them.
UNREAD = {"teacher": {"teacher": "the teacher trains a fresh network on the ground truth; --mode finetune starts "
                                 "from a checkpoint",
                      "contrast_twist": "only finetune and student have a contrast term",
                      "collapse_weight": "only finetune and student have a contrast term",
                      "speed_weight": "only finetune and student have a speed term"},
          "finetune": {"twist_weight": "only the teacher has a twist term",
                       "si_variance_weight": "only the teacher has the scale-invariant term"},
          "student": {"twist_weight": "only the teacher has a twist term",
                      "si_variance_weight": "only the teacher has the scale-invariant term"}}


def unread_settings(config: Config) -> list[str]:
    """One sentence for each setting of ``config.train`` that its mode does not read (:data:`UNREAD`) and that is
    set to other than its default (e.g. ``train.teacher`` of a ``--mode teacher`` run: a fresh network, not the one
    the user named); empty when there is none.

    >>> from learned.config import load_config
    >>> unread_settings(load_config(None, ["train.teacher=t.pt"], mode="teacher"))[0][:56]
    "train.teacher='t.pt' is not read by --mode teacher: the "
    """
    defaults = type(config.train)()
    return [f"train.{key}={getattr(config.train, key)!r} is not read by --mode {config.mode}: {why}"
            for key, why in UNREAD[config.mode].items() if getattr(config.train, key) != getattr(defaults, key)]


def schedule_note(config: Config) -> str | None:
    """A sentence for a ``config`` whose cosine schedule (``train.schedule``) has a warm-up (``train.warmup_steps``)
    that lasts the whole run (``train.steps``): its learning rate only rises and the run ends at its peak, never decaying (the shipped
    configs warm up over 30 steps: a short trial run of theirs); None otherwise.

    >>> from learned.config import load_config
    >>> schedule_note(load_config(None, ["train.schedule=cosine", "train.warmup_steps=10", "train.steps=100"]))
    >>> schedule_note(load_config(None, ["train.schedule=cosine", "train.warmup_steps=30", "train.steps=20"]))[:54]
    'train.warmup_steps=30 is not shorter than train.steps='
    """
    tc = config.train
    if tc.schedule != "cosine" or tc.steps == 0 or tc.warmup_steps < tc.steps:
        return None
    return (f"train.warmup_steps={tc.warmup_steps} is not shorter than train.steps={tc.steps}: the whole run is the "
            f"cosine schedule's linear warm-up, its learning rate rising to {learning_rate(tc.steps - 1, config):.3g} "
            f"at the last step and never decaying; give fewer train.warmup_steps (a tenth of the steps, say) or "
            f"train.schedule=constant")


def _entry_path(entry: object) -> Path:
    return Path(entry["path"] if isinstance(entry, dict) else entry)


def _file_key(entry: object) -> tuple[int, int] | None:
    """``(device, inode)`` of the file a data entry names (one file under any spelling), None when it is missing."""
    try:
        status = os.stat(_entry_path(entry))
    except OSError:   # missing: the dataset names it
        return None
    return status.st_dev, status.st_ino


def repeated_files(files: tuple, val_files: tuple) -> list[str]:
    """Why the data files ``files`` (``data.files``) and ``val_files`` (``data.val_files``) are not what they say,
    one sentence each: a training file given twice (its windows weigh twice), and a validation file that is one
    of the training files (its loss is measured on windows the network trains on: no held-out learning curve).
    Files are compared as files (``a.h5`` and ``./a.h5`` are one); empty when there is nothing to say."""
    said, first_of = [], {}
    for j, entry in enumerate(files):
        key = _file_key(entry)
        if key is not None and key in first_of:
            said.append(f"data.files[{j}] {_entry_path(entry)} is data.files[{first_of[key]}]: its windows are drawn "
                        "twice as often as the other files'")
        elif key is not None:
            first_of[key] = j
    for j, entry in enumerate(val_files):
        key = _file_key(entry)
        if key is not None and key in first_of:
            said.append(f"data.val_files[{j}] {_entry_path(entry)} is data.files[{first_of[key]}], a training file: "
                        "its validation loss is measured on windows the network trains on, not held-out ones "
                        "(give files that are not in data.files)")
    return said


class TrainingDiverged(ValueError):
    """A step's loss or weights went non-finite: the run stops and saves nothing (``last.pt`` stays the last
    good checkpoint of this run, if it wrote one; the message says which ``last.pt``, if any, is there). A
    ValueError, so the command prints it as one line and exits with status 2."""


def nonfinite_terms(terms: dict[str, float]) -> list[str]:
    """The names of the loss terms (``{name: value}``) that are NaN or infinite, in ``terms``' order.

    >>> nonfinite_terms({"total": float("nan"), "teacher": 0.5, "twist": float("inf")})
    ['total', 'twist']
    """
    return [name for name, value in terms.items() if not np.isfinite(value)]


def batch_indices(step: int, *, size: int, batch_size: int, seed: int) -> list[int]:
    """Dataset indices (``batch_size`` of them) of the global batch of ``step``: consecutive slices of per-epoch
    permutations of ``range(size)`` seeded by ``seed`` and the epoch."""
    if size < 1:
        raise ValueError("the dataset is empty")
    start = step * batch_size
    out: list[int] = []
    while len(out) < batch_size:
        epoch, offset = divmod(start + len(out), size)
        order = np.random.default_rng([seed, epoch]).permutation(size)
        out.extend(order[offset: offset + batch_size - len(out)].tolist())
    return out


def _events(batch: dict[str, torch.Tensor], width: int, height: int) -> EventWindows:
    """The events of a collated batch with their intrinsics and the known speed of each window
    (:attr:`learned.data.Sample.known_speed`; NaN where unknown, whose scale is then left to the teacher term)."""
    speed = batch["speed"]
    return EventWindows.from_padded(batch["x"], batch["y"], batch["t"], batch["polarity"], batch["valid"],
                                    batch["duration_s"], batch["K"], width=width, height=height, speed=speed)


def twist_scale(dataset: H5WindowDataset, model: ModelConfig, *, floor: float = 0.05) -> torch.Tensor:
    """The teacher's twist-loss scale (6,) [m/s x3, rad/s x3]: the root mean square of one component of ``v``
    (``sqrt(mean |v|^2 / 3)``) and of ``omega`` over the ground-truth twists of ``dataset``'s files, each at
    least ``floor`` x the model's bound (``max_speed``, ``max_angular_speed``).

    One scale per vector, not per component: a component that barely moves in the data (the rotation of a
    drive, of a slider) would otherwise be divided by almost nothing and its noise would swamp the loss.
    The model's bounds when no file has twists.
    """
    bounds = np.array([model.max_speed, model.max_angular_speed])
    twists = [gt["twists"] for gt in dataset._gt if gt is not None and gt["twists"] is not None]
    if twists:
        all_twists = np.concatenate(twists)
        rms = np.sqrt([np.mean(all_twists[:, :3] ** 2), np.mean(all_twists[:, 3:] ** 2)])
        scales = np.maximum(rms, floor * bounds)
    else:
        scales = bounds
    return torch.as_tensor(np.repeat(scales, 3), dtype=torch.float32)


def learning_rate(step: int, config) -> float:
    """The learning rate of ``step`` (0-based) under ``config.train`` (see :class:`learned.config.TrainConfig`)."""
    tc = config.train
    if tc.schedule == "constant":
        return tc.lr
    if step < tc.warmup_steps:
        return tc.lr * (step + 1) / tc.warmup_steps
    span = max(tc.steps - tc.warmup_steps, 1)
    progress = min((step - tc.warmup_steps) / span, 1.0)
    return float(tc.lr * (0.01 + 0.99 * 0.5 * (1.0 + np.cos(np.pi * progress))))


def contrast_objective(collapse_weight: float):
    """The self-supervised term: :data:`cmax.contrast.SHARED_OBJECTIVE` itself, plus the collapse guard
    (:class:`cmax.contrast.CollapseGuard`) when ``collapse_weight`` > 0."""
    if collapse_weight == 0:
        return SHARED_OBJECTIVE
    return WeightedSum(((1.0, SHARED_OBJECTIVE), (float(collapse_weight), CollapseGuard())))


def _load_weights(model: DepthPoseNet, state: dict[str, torch.Tensor], source: str) -> None:
    """``model.load_state_dict(state)``; a mismatch raises :class:`CheckpointError` naming ``source``."""
    try:
        model.load_state_dict(state)
    except RuntimeError as error:  # missing / unexpected keys, other shapes
        raise CheckpointError(f"{source}: its weights do not fit the model of this config "
                              f"({' '.join(str(error).split())[:300]})") from None


def check_optimizer_state(optimizer: torch.optim.Optimizer, source: str | Path) -> None:
    """Refuse (:class:`CheckpointError` naming ``source``) an optimizer state loaded from a checkpoint whose
    per-parameter tensors (AdamW's ``exp_avg``, ``exp_avg_sq``: each of its parameter's shape) have another shape
    than their parameter or hold a NaN or an infinity: ``load_state_dict`` takes them, and the first resumed step
    failed with torch's shape error (a traceback) or made the weights non-finite, reported as a diverged run.

    >>> import torch
    >>> from learned.checkpoint import CheckpointError
    >>> net = torch.nn.Linear(2, 1)
    >>> adam = torch.optim.AdamW(net.parameters())
    >>> net(torch.ones(1, 2)).sum().backward(); adam.step()
    >>> check_optimizer_state(adam, "last.pt")
    >>> adam.state[net.weight]["exp_avg"] = torch.zeros(7)
    >>> try:
    ...     check_optimizer_state(adam, "last.pt")
    ... except CheckpointError as error:
    ...     print(str(error)[:64])
    last.pt: its optimizer state does not fit this run (exp_avg of p
    """
    for group in optimizer.param_groups:
        for index, parameter in enumerate(group["params"]):
            for key, value in optimizer.state.get(parameter, {}).items():
                if not isinstance(value, torch.Tensor) or value.ndim == 0:   # AdamW's step counter
                    continue
                if value.shape != parameter.shape:
                    raise CheckpointError(f"{source}: its optimizer state does not fit this run ({key} of parameter "
                                          f"{index}: {list(value.shape)}, the parameter's {list(parameter.shape)})")
                if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                    raise CheckpointError(f"{source}: its optimizer state holds NaN or infinite values ({key} of "
                                          f"parameter {index}): the resumed steps would make the weights "
                                          "non-finite; use an earlier checkpoint")


def with_teacher_model(config: Config) -> Config:
    """``config`` with the network its teacher fixes (``--mode finetune`` / ``student``; others unchanged).

    ``finetune`` trains the teacher's network further, so its model config is the teacher's (read from the
    checkpoint ``train.teacher``): a run that leaves ``model.*`` at the defaults takes it; one that sets it
    otherwise is refused with the fields that differ. ``student`` trains a network of its own, but the frozen
    teacher reads the student's event volumes: their ``model.bins`` must agree.

    Raises FileNotFoundError / :class:`learned.checkpoint.CheckpointError` for a missing or invalid teacher,
    ValueError for a model config that contradicts it.
    """
    if config.mode not in ("finetune", "student"):
        return config
    path = config.train.teacher
    checkpoint = load_checkpoint(path)
    try:
        teacher = config_from_dict(checkpoint["config"]).model
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"{path}: its config is not valid: {error}") from None
    if config.mode == "student":
        if teacher.bins != config.model.bins:
            raise ValueError(f"the teacher {path} reads event volumes of {teacher.bins} time bins, this run's network "
                             f"{config.model.bins} (model.bins), and the frozen teacher sees the student's volumes: "
                             f"set model.bins={teacher.bins}")
        return config
    if config.model == teacher:
        return config
    if config.model != ModelConfig():
        differ = ", ".join(f"model.{f.name}={getattr(config.model, f.name)!r} (the teacher's "
                           f"{getattr(teacher, f.name)!r})" for f in dataclasses.fields(ModelConfig)
                           if getattr(config.model, f.name) != getattr(teacher, f.name))
        raise ValueError(f"--mode finetune trains the teacher's network further, so its model config is the teacher's "
                         f"({path}); this run sets {differ}: drop those model.* settings")
    return dataclasses.replace(config, model=teacher)


def distributed_rank() -> tuple[int, int]:
    """``(rank, world)`` of this process from the environment ``torchrun`` sets (``RANK``, ``WORLD_SIZE``);
    ``(0, 1)`` outside a ``torchrun`` job.

    A rank other than 0 writes nothing, so a ``RANK`` that no ``torchrun`` job set (a scheduler's or an MPI
    wrapper's, left in the environment) would make a run train and save nothing: a ``RANK`` outside
    ``[0, WORLD_SIZE)`` -- ``RANK=1`` without ``WORLD_SIZE``, or with ``WORLD_SIZE=1`` -- and values that are not
    whole numbers are refused (ValueError, one line naming the variables).
    """
    text = {name: os.environ.get(name) for name in ("RANK", "WORLD_SIZE")}
    try:
        rank, world = int(text["RANK"] or 0), int(text["WORLD_SIZE"] or 1)
    except ValueError:
        rank = world = -1
    if world < 1 or not 0 <= rank < world:
        shown = ", ".join(f"{name}={value}" if value is not None else f"{name} not set"
                          for name, value in text.items())
        raise ValueError(f"the environment says {shown}: not a rank of a torchrun job (torchrun sets WORLD_SIZE > 1 "
                         "and 0 <= RANK < WORLD_SIZE), and a rank other than 0 would train and write nothing; unset "
                         "RANK (and WORLD_SIZE) to train in one process, or start the job with torchrun")
    return rank, world


def loss_outputs(config: Config) -> tuple[bool, bool]:
    """``(all_scales, twist)``: which outputs of the network the loss of ``config``'s run reads. The teacher loss
    reads the inverse depth at every scale, the contrast (finetune, student) only the finest; the twist is read
    by the contrast, and by the teacher loss when ``train.twist_weight > 0``.

    >>> from learned.config import Config, TrainConfig
    >>> loss_outputs(Config()), loss_outputs(Config(train=TrainConfig(twist_weight=0.0)))
    ((True, True), (True, False))
    >>> loss_outputs(Config(mode="student", train=TrainConfig(teacher="teacher.pt")))
    (False, True)
    """
    teacher = config.mode == "teacher"
    return teacher, not teacher or config.train.twist_weight > 0


class LossOutputs(torch.nn.Module):
    """The network ``model`` as ``DistributedDataParallel`` wraps it: its forward gives only the outputs the run's
    loss reads (:func:`loss_outputs`): the inverse depth of every scale when ``all_scales``, else the finest alone;
    the twist as it is when ``twist``, else detached.

    DDP's ``find_unused_parameters`` looks for the parameters without a gradient by walking the autograd graph
    back from the tensors the forward returns: a returned output that the loss leaves out (the coarse decoder
    heads of a student, the pose head of a teacher without a twist term) counts as used, DDP waits for its
    gradients, and the second step fails with "Expected to have finished reduction in the prior iteration".
    """

    def __init__(self, model: DepthPoseNet, *, all_scales: bool, twist: bool) -> None:
        super().__init__()
        self.model, self.all_scales, self.twist = model, all_scales, twist

    def forward(self, volume: torch.Tensor) -> NetOutput:
        """:meth:`DepthPoseNet.forward` of ``volume`` (B, bins, H, W), keeping what the loss reads."""
        out = self.model(volume)
        return NetOutput(out.inverse_depths if self.all_scales else out.inverse_depths[:1],
                         out.twist if self.twist else out.twist.detach())


def _no_window(dataset: H5WindowDataset) -> str:
    """Why ``dataset`` holds no window, and what to change (the end of an error message): the windows with too few
    events, and the labelled windows (centred on ``gt/depth_t``) that reach beyond their recording, with their
    centres, the recordings' spans and, when those are the only reason, the longest ``data.window_us`` that fits
    one of them."""
    from learned.data import longest_centred_window_us

    ms = lambda us: f"{us * 1e-3:g}"  # noqa: E731
    off = dataset.off_recording
    files: dict[int, list[int]] = {}
    for index, centre in off:
        files.setdefault(index, []).append(centre)
    shown = []
    for index, centres in list(files.items())[:3]:
        start, end = dataset.spans[index]
        listed = ", ".join(ms(c) for c in centres[:4]) + (", ..." if len(centres) > 4 else "")
        shown.append(f"{dataset.specs[index].path.name}: centres at {listed} ms, events from {ms(start)} to "
                     f"{ms(end)} ms")
    where = "; ".join(shown) + ("; ..." if len(files) > 3 else "")
    if off and not dataset.skipped:   # the centres alone: every window reaches beyond its recording
        longest = max(longest_centred_window_us(centre, *dataset.spans[index]) for index, centre in off)
        fix = (f"data.window_us={longest} or shorter fits at least one of them" if longest > 0 else
               "no window length fits a centre at an end of its recording: give labelled recordings with depth "
               "times inside their events (cmax scene: a higher --depth-rate or a longer --duration)")
        return (f"labelled windows are centred on their file's gt/depth_t, and each of the {len(off)} "
                f"window(s) of {ms(dataset.window_us)} ms (data.window_us) reaches beyond its recording by more than "
                f"{ms(dataset.window_us // 10)} ms, a tenth of a window ({where}); {fix}")
    beyond = (f"; {len(off)} more, labelled windows centred on gt/depth_t, reach beyond their recording ({where})"
              if off else "")
    return (f"each needs {ms(dataset.window_us)} ms of events (data.window_us) with at least {dataset.min_events} "
            f"of them ({dataset.skipped} window(s) had fewer){beyond}; give longer recordings or a shorter "
            "data.window_us")


def _quiet_tensorboard_thread_errors() -> None:
    """Keep an :class:`OSError` of TensorBoard's writer thread (a full disk, a file-size limit) from printing a
    traceback: TensorBoard raises the same error at the trainer's next call, which reports it in one line
    (:meth:`Trainer._tensorboard_failed`). Installed once in :data:`threading.excepthook`; every other thread's
    exception goes to the hook that was there before."""
    previous = threading.excepthook
    if getattr(previous, "learned_quiet_tensorboard", False):
        return

    def hook(args) -> None:
        if isinstance(args.exc_value, OSError) and type(args.thread).__module__.startswith("tensorboard."):
            return
        previous(args)

    hook.learned_quiet_tensorboard = True
    threading.excepthook = hook


class Trainer:
    """One training run (a rank of it under ``torchrun``); :meth:`run` trains to ``config.train.steps``.

    ``resume``: continue from ``train.out/last.pt`` (checked against ``config``); ``progress``: a progress bar."""

    def __init__(self, config: Config, *, resume: bool = False, progress: bool = True) -> None:
        config = with_teacher_model(config)
        self.config, self.progress = config, progress
        self.rank, self.world = distributed_rank()
        self.device = resolve_device(config.train.device, int(os.environ.get("LOCAL_RANK", "0")))
        if self.device.type == "cuda":
            torch.cuda.set_device(self.device)
        if self.world > 1 and not torch.distributed.is_initialized():
            torch.distributed.init_process_group(ddp_backend(self.device))
        tc = config.train
        if tc.batch_size % self.world:
            raise ValueError(f"train.batch_size ({tc.batch_size}) must be a multiple of the {self.world} ranks")
        self.out = Path(tc.out)
        torch.manual_seed(tc.seed)
        self.model = DepthPoseNet(config.model).to(self.device)
        self.teacher = None
        teacher_window = None
        # what the teacher file holds, so that --resume notices one replaced under the same path
        self.teacher_sha256 = (file_sha256(tc.teacher) if tc.teacher and config.mode != "teacher"
                               and Path(tc.teacher).is_file() else "")
        if config.mode in ("finetune", "student"):
            from learned.evaluate import load_model

            from learned.predict import window_note

            teacher, teacher_config = load_model(tc.teacher)
            trained_us = int(teacher_config["data"]["window_us"])
            if (other := window_note(trained_us, config.data.window_us)) is not None:   # said once the run is checked
                teacher_window = (f"train.teacher {tc.teacher}: {other}; data.window_us={trained_us} trains on the "
                                  "teacher's windows")
            if config.mode == "finetune":
                _load_weights(self.model, teacher.state_dict(), f"the teacher {tc.teacher}")
            else:
                self.teacher = teacher.to(self.device).eval().requires_grad_(False)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
        self.step = 0
        self.saved_step: int | None = None   # the step of the good checkpoint in out/last.pt, if any
        ckpt = None
        if resume and (self.out / "last.pt").is_file():
            ckpt = load_checkpoint(self.out / "last.pt")
            self._check_resumed_config(ckpt)
            _load_weights(self.model, ckpt["model"], str(self.out / "last.pt"))
            try:
                self.optimizer.load_state_dict(ckpt["optimizer"])
            except (ValueError, KeyError, TypeError) as error:
                raise CheckpointError(f"{self.out / 'last.pt'}: its optimizer state does not fit this run "
                                      f"({error})") from None
            check_optimizer_state(self.optimizer, self.out / "last.pt")
            self.step = self.saved_step = int(ckpt["step"])
            try:
                set_rng_state(ckpt["rng"])
            except (KeyError, TypeError, ValueError, IndexError, RuntimeError) as error:   # a crafted or damaged rng
                raise CheckpointError(f"{self.out / 'last.pt'}: its random generator states (rng) cannot be "
                                      f"restored ({type(error).__name__}: {' '.join(str(error).split())[:200]}); "
                                      "the resumed steps would not be the ones of the run that wrote it") from None
        self.net = self.model
        if self.world > 1:
            all_scales, twist = loss_outputs(config)
            # every parameter has a gradient when the loss reads every output: no search for unused ones then
            self.net = torch.nn.parallel.DistributedDataParallel(
                LossOutputs(self.model, all_scales=all_scales, twist=twist),
                device_ids=[self.device.index] if self.device.type == "cuda" else None,
                find_unused_parameters=not (all_scales and twist))
        dc = config.data
        if not dc.files:
            raise ValueError("data.files is empty: give the training event files, e.g. 'data.files=[\"a.h5\", "
                             "\"b.h5\"]' (h5 files of cmax scene or cmax simulate)")
        self.dataset = H5WindowDataset(dc.files, window_us=dc.window_us, max_events=dc.max_events,
                                       bins=config.model.bins, augment=dc.augment, seed=tc.seed)
        if len(self.dataset) == 0:
            raise ValueError(f"data.files hold no window: {_no_window(self.dataset)}")
        if config.mode == "teacher" and all(gt is None for gt in self.dataset._gt):
            raise ValueError("--mode teacher learns from ground-truth depth (gt/depth, as cmax scene writes it) and "
                             "none of data.files holds it (or each says use_gt: false): its loss would be 0 at every "
                             "step; give labelled files, or train --mode finetune / student on unlabelled ones")
        order = ckpt.get("data_order") if ckpt is not None else None
        recorded = order.get("files") if isinstance(order, dict) else None
        if not isinstance(recorded, list) or len(recorded) != len(self.dataset.specs):
            recorded = [None] * len(self.dataset.specs)
        self.fingerprints = data_fingerprints([spec.path for spec in self.dataset.specs], self.dataset.counts,
                                              self.dataset.spans, recorded,
                                              progress=self.progress and self.rank == 0)
        self.calibrations = calibration_sha256(self.dataset.specs)
        if ckpt is not None:
            self._check_data_order(ckpt.get("data_order"))
            self._check_data_files(ckpt.get("data_order"))
            self._check_calibrations(ckpt.get("data_order"))
            self._check_teacher(ckpt.get("data_order"))
        self.contrast = contrast_objective(tc.collapse_weight)
        self.twist_scale = twist_scale(self.dataset, config.model).to(self.device)
        self.validation = None
        if self.rank == 0:
            for sentence in repeated_files(dc.files, dc.val_files if tc.val_every else ()):
                warnings.warn(sentence, stacklevel=2)
            if (sentence := schedule_note(config)) is not None:
                warnings.warn(sentence, stacklevel=2)
            for sentence in unread_settings(config) + ([teacher_window] if teacher_window else []):
                warnings.warn(sentence, stacklevel=2)
        if tc.val_every:
            val = H5WindowDataset(dc.val_files, window_us=dc.window_us, max_events=dc.max_events,
                                  bins=config.model.bins, augment=False, seed=tc.seed)
            if len(val) == 0:
                raise ValueError(f"data.val_files hold no window: {_no_window(val)}")
            picks = np.unique(np.linspace(0, len(val) - 1, min(dc.val_windows, len(val))).round().astype(int))
            self.validation = (val, picks.tolist())
        self.resumed = resume
        if resume and self.rank == 0:   # the steps a killed run logged after its checkpoint are run again
            drop_log_lines_after(self.out / "log.jsonl", self.step)
        self.log = None   # TensorBoard's writer, opened by run() (a run with nothing to train writes nothing)

    # -- resuming -----------------------------------------------------------------------------
    def _check_resumed_config(self, ckpt: dict) -> None:
        """Refuse (ValueError, one line naming the fields) to resume ``out/last.pt`` under a config whose fields
        outside :data:`RESUMABLE` differ from the ones it was written with."""
        path = self.out / "last.pt"
        try:
            recorded = config_from_dict(ckpt["config"])
        except (TypeError, ValueError) as error:
            raise CheckpointError(f"{path}: its config is not valid: {error}") from None
        order = ckpt.get("data_order")
        paths = order.get("paths") if isinstance(order, dict) else None
        if paths is not None and not (isinstance(paths, dict) and isinstance(paths.get("train.teacher"), str)
                                      and isinstance(paths.get("data.files"), list)
                                      and len(paths["data.files"]) == len(recorded.data.files)):
            raise CheckpointError(f"{path}: its data_order.paths is not valid: {paths!r}")
        calibrations = None if paths is None else paths.get("data.calibrations")
        if calibrations is not None and not (isinstance(calibrations, list)
                                             and len(calibrations) == len(recorded.data.files)
                                             and all(isinstance(c, dict) for c in calibrations)):
            raise CheckpointError(f"{path}: its data_order.paths is not valid: {paths!r}")
        differ = config_differences(recorded, self.config, paths)
        step = int(ckpt.get("step", 0))
        # a raised train.steps stretches a cosine schedule; a run stopped in its warm-up ran every step at the
        # rate the longer schedule gives it: resuming that run is the longer run, bit for bit
        if (not differ and recorded.train.schedule == "cosine" and recorded.train.steps != self.config.train.steps
                and any(learning_rate(k, recorded) != learning_rate(k, self.config) for k in range(step))):
            raise ValueError(f"--resume: {path}'s cosine schedule spans train.steps={recorded.train.steps}; "
                             f"train.steps={self.config.train.steps} would move the learning rate of the steps "
                             f"still to run (step {step}: {learning_rate(step, self.config):.3g}, not "
                             f"{learning_rate(step, recorded):.3g}); resume with train.steps={recorded.train.steps}, "
                             "or train further as a new run: --mode finetune train.teacher=" + str(path))
        if differ:
            raise ValueError(f"--resume: {path} was written with other settings than this run's: "
                             f"{', '.join(differ)}; repeat the settings of the run that wrote it, or start afresh "
                             f"with --overwrite or another train.out")

    def _check_teacher(self, order: object) -> None:
        """Refuse to resume when ``train.teacher`` holds another file than the one the checkpoint was trained
        with (its SHA-256 in ``data_order``; checkpoints of earlier versions store none)."""
        recorded = order.get("teacher_sha256") if isinstance(order, dict) else None
        if recorded and recorded != self.teacher_sha256:
            raise ValueError(f"--resume: train.teacher {self.config.train.teacher} is not the file "
                             f"{self.out / 'last.pt'} was trained with (its contents changed since): the resumed steps "
                             "would learn from another teacher; restore it, or start afresh with --overwrite or "
                             "another train.out")

    def _check_data_files(self, order: object) -> None:
        """Refuse to resume when a data file is not the one the checkpoint was trained on (its
        :func:`file_fingerprint` in ``data_order["files"]``; checkpoints of earlier versions store none): another
        recording copied over it keeps its path and may keep its number of windows."""
        differ = fingerprint_differences(order.get("files") if isinstance(order, dict) else None, self.fingerprints,
                                         [str(spec.path) for spec in self.dataset.specs])
        if differ:
            raise ValueError(f"--resume: {self.out / 'last.pt'} was trained on other data files than the ones at "
                             f"these paths now: {'; '.join(differ)}: the resumed steps would learn from other "
                             "events; restore the files, or start afresh with --overwrite or another train.out")

    def _check_calibrations(self, order: object) -> None:
        """Refuse to resume when a data file's ``calib`` or ``rectify_map`` holds other bytes than the checkpoint was
        trained with (:func:`calibration_sha256` in ``data_order["calibrations"]``; checkpoints of earlier versions
        store none): the resumed steps would rectify the events elsewhere."""
        recorded = order.get("calibrations") if isinstance(order, dict) else None
        if not isinstance(recorded, list) or len(recorded) != len(self.calibrations):
            return
        differ = [f"data.files[{i}].{key} {getattr(self.dataset.specs[i], key)}"
                  for i, (before, now) in enumerate(zip(recorded, self.calibrations)) if isinstance(before, dict)
                  for key in ("calib", "rectify_map") if before.get(key) != now[key]]
        if differ:
            raise ValueError(f"--resume: {self.out / 'last.pt'} was trained with other calibration files than the "
                             f"ones at these paths now ({', '.join(differ)}: their contents, the SHA-256 of the "
                             "whole file, changed): the resumed steps would rectify the events elsewhere; restore "
                             "the files, or start afresh with --overwrite or another train.out")

    def _check_data_order(self, order: object) -> None:
        """Refuse to resume when the checkpoint's ``data_order`` (seed, batch size, windows in the data set) is not
        this run's: the batches of the steps still to run would not be the ones the first run would have taken."""
        if not isinstance(order, dict):   # checkpoints of earlier versions store none
            return
        now = {"seed": self.config.train.seed, "batch_size": self.config.train.batch_size,
               "dataset_size": len(self.dataset)}
        differ = [f"{key} {order.get(key)!r} (now {value!r})" for key, value in now.items() if order.get(key) != value]
        if differ:
            raise ValueError(f"--resume: {self.out / 'last.pt'} was trained on another data order: "
                             f"{', '.join(differ)} (dataset_size: the windows data.files hold; a file changed?); "
                             f"the resumed steps would take other batches: start afresh with --overwrite or "
                             f"another train.out")

    # -- logging ------------------------------------------------------------------------------
    def _logger(self):
        """TensorBoard's writer on ``out/tb`` when it is installed (scalars always go to ``log.jsonl`` too), else
        None (also when it cannot start: :meth:`_tensorboard_failed`)."""
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            return None
        _quiet_tensorboard_thread_errors()
        try:
            # resumed: TensorBoard drops the events of the steps after the checkpoint (a killed run's)
            return SummaryWriter(str(self.out / "tb"), purge_step=self.step + 1 if self.resumed else None)
        except OSError as error:
            self._tensorboard_failed(error)
            return None

    def _tensorboard_failed(self, error: OSError) -> None:
        """TensorBoard could not write (a full disk, a file-size limit: the error of its writer thread, raised at
        the next call): a warning naming its folder, and TensorBoard off for the rest of the run; the learning
        curves go on in ``log.jsonl``, whose own write errors stop the run (:meth:`_scalars`)."""
        self.log = None
        reason = f"[Errno {error.errno}] {os.strerror(error.errno)}" if error.errno else str(error)
        warnings.warn(f"TensorBoard could not write in {self.out / 'tb'} ({reason}): it is off for the rest of this "
                      f"run; the learning curves go on in {self.out / 'log.jsonl'}", RuntimeWarning, stacklevel=2)

    def _scalars(self, values: dict[str, float]) -> None:
        """One line ``{"step", **values}`` in ``out/log.jsonl`` (the learning curves), and TensorBoard.

        A write error of ``log.jsonl`` (a full disk, a file-size limit) is an :class:`OSError` naming it (its
        errno kept); TensorBoard's is a warning (:meth:`_tensorboard_failed`)."""
        if self.rank != 0:
            return
        if self.log is not None:
            try:
                for key, value in values.items():
                    self.log.add_scalar(key, value, self.step)
            except OSError as error:
                self._tensorboard_failed(error)
        self.out.mkdir(parents=True, exist_ok=True)
        path = self.out / "log.jsonl"
        flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)  # never a planted link
        try:
            with os.fdopen(os.open(path, flags, 0o644), "a") as f:
                f.write(json.dumps({"step": self.step, **values}) + "\n")
        except OSError as error:
            reason = os.strerror(error.errno) if error.errno else str(error)
            raise OSError(error.errno, f"{reason} while appending step {self.step} to the learning curves (a line "
                                       "cut short there is dropped by --resume)", str(path)) from None

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Mean loss and terms over the validation windows (no augmentation, batches of ``batch_size``)."""
        dataset, picks = self.validation
        sums: dict[str, float] = {}
        for start in range(0, len(picks), self.config.train.batch_size):
            chosen = picks[start: start + self.config.train.batch_size]
            loss, terms, _ = self.loss(on_device(collate([dataset[i] for i in chosen]), self.device), net=self.model,
                                       size=(dataset.width, dataset.height))
            for key, value in {"loss": float(loss), **terms}.items():
                sums[key] = sums.get(key, 0.0) + value * len(chosen)
        return {f"val/{key}": value / len(picks) for key, value in sums.items()}

    def _images(self, batch: dict[str, torch.Tensor], output) -> None:
        if self.rank != 0 or self.log is None:
            return
        def norm(image: torch.Tensor) -> torch.Tensor:
            image = image - image.min()
            return image / image.max().clamp(min=1e-9)
        self.log.add_image("events/volume_sum", norm(batch["volume"][0].sum(0, keepdim=True)), self.step)
        self.log.add_image("depth/predicted_inverse", norm(output.inverse_depth[0].detach()), self.step)
        if bool(batch["depth_mask"][0].any()):
            self.log.add_image("depth/true_inverse", norm(batch["inverse_depth"][0]), self.step)
        if self.config.mode != "teacher":
            from cmax.iwe import image_of_warped_events
            from cmax.warp import warp_se3
            with torch.no_grad():
                keep = batch["valid"][0]
                x, y = batch["x"][0][keep], batch["y"][0][keep]
                K = batch["K"][0]
                rays = torch.stack([x, y, torch.ones_like(x)], -1) @ torch.linalg.inv(K).T
                rho = output.inverse_depth[0, 0][y.long().clamp(0, output.inverse_depth.shape[-2] - 1),
                                                  x.long().clamp(0, output.inverse_depth.shape[-1] - 1)]
                dt = batch["t"][0][keep] - 0.5 * batch["duration_s"][0]
                xw, yw = warp_se3(rays, dt, output.twist[0, :3], output.twist[0, 3:], rho, K)
                iwe = image_of_warped_events(xw, yw, height=self.dataset.height, width=self.dataset.width)
            self.log.add_image("events/iwe", norm(iwe[None]), self.step)

    # -- one step -----------------------------------------------------------------------------
    def _batches(self) -> Iterator[dict[str, torch.Tensor]]:
        tc = self.config.train
        step = self.step
        while True:
            indices = batch_indices(step, size=len(self.dataset), batch_size=tc.batch_size, seed=tc.seed)
            local = indices[self.rank::self.world]
            self.dataset.set_epoch(step * tc.batch_size // len(self.dataset))
            yield on_device(collate([self.dataset[i] for i in local]), self.device)
            step += 1

    def loss(self, batch: dict[str, torch.Tensor], net: torch.nn.Module | None = None,
             size: tuple[int, int] | None = None):
        """``(loss, terms, output)`` of one batch under the run's mode (``net``: default the trained one).

        ``size``: ``(width, height)`` [px] of the sensor the batch's events come from (default the training
        files'; a validation batch gives its own files', which may differ)."""
        tc, mode = self.config.train, self.config.mode
        output = (self.net if net is None else net)(batch["volume"])
        if mode == "teacher":
            mask = batch["depth_mask"]
            gt = torch.where(mask, 1.0 / torch.where(mask, batch["inverse_depth"], 1.0), 1.0)
            loss = teacher_loss(tuple(1.0 / d for d in output.inverse_depths), gt, mask, lam=tc.lam,
                                variance_weight=tc.si_variance_weight)
            terms = {"teacher": float(loss.detach())}
            if tc.twist_weight > 0:
                scale = self.twist_scale
                has = batch["has_twist"].to(output.twist.dtype)[:, None]
                err = torch.nn.functional.smooth_l1_loss(output.twist / scale, batch["twist"] / scale, reduction="none")
                twist_term = (err * has).mean()
                terms["twist"] = float(twist_term.detach())
                loss = loss + tc.twist_weight * twist_term
            return loss, terms, output
        teacher_rho = None
        if self.teacher is not None:
            with torch.no_grad():
                teacher_rho = self.teacher(batch["volume"]).inverse_depth
        width, height = size if size is not None else (self.dataset.width, self.dataset.height)
        events = _events(batch, width, height)
        twist = output.twist
        if tc.contrast_twist == "truth":   # the ablation: the motion known where the file gives it
            twist = torch.where(batch["has_twist"][:, None], batch["twist"].to(twist.dtype), twist)
        loss, terms = student_loss(output.inverse_depth, twist, events, teacher_inverse_depth=teacher_rho,
                                   lam=tc.lam, objective=self.contrast, speed_weight=tc.speed_weight)
        return loss, terms, output

    def save(self) -> Path | None:
        """Write ``last.pt`` (model, optimizer, step, config, RNG and data order) atomically on rank 0; its path, or
        None on the other ranks."""
        if self.rank != 0:
            return None
        payload = {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(), "step": self.step,
                   "config": self.config.to_dict(), "rng": rng_state(),
                   "data_order": {"seed": self.config.train.seed, "batch_size": self.config.train.batch_size,
                                  "dataset_size": len(self.dataset), "paths": resolved_paths(self.config),
                                  "teacher_sha256": self.teacher_sha256, "files": self.fingerprints,
                                  "calibrations": self.calibrations},
                   "card": training_card(self.dataset, self.config.data.window_us)}
        written = save_checkpoint(self.out / "last.pt", payload)
        self.saved_step = self.step
        return written

    def _diverged(self, what: str) -> TrainingDiverged:
        """The :class:`TrainingDiverged` of a step where ``what`` went non-finite: what stays in ``train.out``, and
        what may keep the run stable."""
        path = self.out / "last.pt"
        if self.saved_step is not None:
            kept = f"the last good checkpoint {path} (step {self.saved_step}) is kept"
        elif path.exists() or path.is_symlink():   # Trainer used directly over an earlier run's folder
            kept = f"this run had written no checkpoint yet ({path} is an earlier run's, left as it was)"
        else:
            kept = "no checkpoint had been written yet"
        return TrainingDiverged(f"{what}: training stopped and nothing was saved; {kept}; a lower train.lr or "
                                "gradient clipping (train.clip_grad_norm) may keep the run stable")

    def _check_loss(self, terms: dict[str, float]) -> None:
        """Raise :class:`TrainingDiverged` when a loss term (:func:`global_mean` over the ranks: every rank decides
        alike, as a rank that stopped alone would hang the others) of the step being run (``self.step + 1``) is
        not finite."""
        bad = nonfinite_terms(terms)
        if bad:
            values = ", ".join(f"loss/{name}={terms[name]:g}" for name in bad)
            raise self._diverged(f"step {self.step + 1}: the loss is not finite ({values})")

    def _check_weights(self) -> None:
        """Raise :class:`TrainingDiverged` when the update of step ``self.step`` left a weight non-finite (the same
        on every rank: DDP keeps their weights equal)."""
        state = self.model.state_dict()
        floats = [tensor for tensor in state.values() if tensor.is_floating_point()]
        if bool(torch.stack([torch.isfinite(tensor).all() for tensor in floats]).all()):   # one device sync
            return
        bad = nonfinite_tensors(state)
        raise self._diverged(f"step {self.step}: the update made {len(bad)} weight tensors non-finite (e.g. "
                             f"{bad[0]})")

    def run(self) -> list[float]:
        """Train from the current step to ``train.steps``; returns the losses of the steps run (each the global
        batch's: under ``torchrun`` averaged over the ranks, :func:`global_mean`, as are the logged terms)."""
        tc = self.config.train
        if self.step >= tc.steps:   # nothing to train (train.steps=0, or a resumed run already there): no write
            return []
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            if self.log is None:
                self.log = self._logger()
            write_text_atomic(self.out / "config.json", json.dumps(self.config.to_dict(), indent=2, default=str))
        losses = []
        start = self.step
        batches = self._batches()
        bar = tqdm(total=tc.steps, initial=self.step, desc=self.config.mode,
                   disable=not self.progress or self.rank != 0)
        self.model.train()
        while self.step < tc.steps:
            if self.step % THREAD_CHECK_EVERY == 0 or self.step == start:   # the machine's load changes
                torch.set_num_threads(torch_threads())
            for group in self.optimizer.param_groups:
                group["lr"] = learning_rate(self.step, self.config)
            batch = next(batches)
            loss, terms, output = self.loss(batch)
            logged = global_mean({"total": float(loss.detach()), **terms}, world=self.world, device=self.device)
            self._check_loss(logged)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if tc.clip_grad_norm > 0:   # of the averaged gradients: the same on every rank
                norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), tc.clip_grad_norm)
                logged["grad_norm"] = float(norm)
            self.optimizer.step()
            self.step += 1
            self._check_weights()
            losses.append(logged["total"])
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.4f}")
            if self.step % tc.log_every == 0 or self.step == tc.steps:   # the last step always
                self._scalars({f"loss/{k}": v for k, v in logged.items()}
                              | {"lr": self.optimizer.param_groups[0]["lr"]})
            if tc.val_every and (self.step % tc.val_every == 0 or self.step == tc.steps) and self.rank == 0:
                self._scalars(self.validate())
            if self.step % tc.image_every == 0:
                try:
                    self._images(batch, output)
                except OSError as error:
                    self._tensorboard_failed(error)
            if self.step % tc.checkpoint_every == 0 or self.step == tc.steps:
                self.save()
        bar.close()
        if self.log is not None:
            try:
                self.log.flush()
            except OSError as error:
                self._tensorboard_failed(error)
        return losses


class _IntermixedParser(ArgumentParser):
    """Takes the ``key=value`` overrides before, between and after the options (``train.steps=3 --resume
    train.lr=1e-3``; a plain parser refused the ones after an option as unrecognized arguments)."""

    def parse_args(self, args=None, namespace=None):  # noqa: D102 (argparse API)
        return self.parse_intermixed_args(args, namespace)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m learned.train`` with the arguments ``argv`` (None: the command line's); returns the
    exit status (2 and one line for a bad argument, config or checkpoint)."""
    parser = _IntermixedParser(
        prog="python -m learned.train",
        description="Train the depth-pose network: --mode teacher (supervised, files with ground truth), finetune "
        "(the teacher's weights, contrast loss) or student (a fresh network, contrast + the frozen teacher). "
        "section.key=value overrides of the config may stand anywhere on the line (e.g. "
        "'data.files=[\"a.h5\"]' train.steps=100 train.out=runs/teacher); see docs/learned.md.")
    parser.add_argument("--mode", choices=("teacher", "finetune", "student"), default=None,
                        help="what to train (default: the config's mode; refused when the two differ)")
    parser.add_argument("--config", type=Path, default=None,
                        help="a .json or .toml config (default: the defaults of learned.config)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.pt when it exists")
    parser.add_argument("--overwrite", action="store_true",
                        help="start afresh over an earlier run in train.out: its last.pt, config.json, log.jsonl "
                        "and TensorBoard events are removed before the first step (once this run's config and data "
                        "are checked), so a new run that fails early leaves no checkpoint of the old one")
    parser.add_argument("--quiet", "--no-progress", dest="no_progress", action="store_true", help="no progress bar")
    parser.add_argument("overrides", nargs="*", help="section.key=value (e.g. train.steps=100)")
    return run_main(parser, _run, argv)


def _same_file(a: Path, b: Path) -> bool:
    """Whether the paths ``a`` and ``b`` name one file (through links and relative parts)."""
    try:
        return os.path.samefile(a, b)
    except OSError:   # one of them does not exist
        return a.resolve() == b.resolve()


def check_output(out: Path, *, resume: bool, overwrite: bool, teacher: str = "") -> None:
    """Refuse ``train.out`` (``out``) when it is a file, when its ``last.pt`` is ``teacher`` (the checkpoint a finetune or
    student run reads: with ``--overwrite`` the run would replace its own teacher, with ``--resume`` continue
    the teacher's run in another mode), or when it holds an earlier run's ``last.pt`` and neither ``--resume``
    (continue it) nor ``--overwrite`` (replace it) says what to do with it; likewise the learning curves of an
    earlier run stopped before its first checkpoint (:func:`earlier_curves`), which a new run would append to.

    The command runs this check again, and trains, holding the folder's lock (:data:`FOLDER_LOCK`,
    :func:`learned._output.locked_folder`): a second run into the same ``train.out`` meanwhile, ``--resume``
    included, is refused at once (one line) and changes nothing."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"train.out {out} is a file: give a folder for last.pt, config.json and log.jsonl")
    if resume and overwrite:
        raise ValueError("--resume continues the run in train.out, --overwrite replaces it: give one of them")
    if teacher and _same_file(out / "last.pt", Path(teacher)):
        raise ValueError(f"train.teacher {teacher} is {out / 'last.pt'}, the checkpoint this run writes: it would "
                         f"replace (or, with --resume, continue) its own teacher; give another train.out")
    if not resume and not overwrite and (out / "last.pt").is_file():
        raise FileExistsError(f"{out / 'last.pt'} exists (an earlier run): --resume continues it, --overwrite "
                              "starts afresh over it, or give another train.out=FOLDER")
    if not resume and not overwrite and (curves := earlier_curves(out)):
        raise FileExistsError(f"{out} holds the learning curves of an earlier run that wrote no checkpoint (stopped "
                              f"before its first: {', '.join(curves)}), which this run's would be appended to: "
                              "--overwrite starts afresh over them, or give another train.out=FOLDER")


def earlier_curves(out: Path) -> list[str]:
    """The learning curves an earlier run left in ``out`` (a run's ``train.out``): ``log.jsonl`` when it holds a
    line, and TensorBoard's event files in ``tb/``, as names relative to ``out`` (none: ``[]``). A run stopped before
    its first checkpoint leaves them without a ``last.pt``; a new run would append its steps to them (``log.jsonl``
    holding step 1 twice, TensorBoard showing both runs).

    >>> earlier_curves(Path("no/such/folder"))
    []
    """
    log = out / "log.jsonl"
    found = ["log.jsonl"] if log.is_file() and log.stat().st_size > 0 else []
    tb = out / "tb"
    if tb.is_dir() and not tb.is_symlink():
        found += [f"tb/{file.name}" for file in sorted(tb.glob("events.out.tfevents.*")) if file.is_file()][:3]
    return found


def _run(args: argparse.Namespace) -> int:
    rank, _ = distributed_rank()   # a stray RANK (no torchrun job) is refused first, before anything is read
    config = load_config(args.config, args.overrides, mode=args.mode, require_mode=True)
    if not config.train.out.strip():   # Path("") is the current folder
        raise ValueError("train.out is empty (an unset shell variable, train.out=$OUT?): give the folder for "
                         "last.pt, config.json and log.jsonl, e.g. train.out=runs/teacher (train.out=. for this one)")
    out = Path(config.train.out)
    teacher = config.train.teacher if config.mode in ("finetune", "student") else ""
    check_output(out, resume=args.resume, overwrite=args.overwrite, teacher=teacher)
    if rank != 0:   # the other ranks of a torchrun job write nothing
        return _train(args, config, out)
    with locked_folder(out, FOLDER_LOCK):   # one run at a time, from the look at last.pt to the last write
        check_output(out, resume=args.resume, overwrite=args.overwrite, teacher=teacher)
        return _train(args, config, out)


def _train(args: argparse.Namespace, config: Config, out: Path) -> int:
    rank0 = distributed_rank()[0] == 0
    if args.resume and rank0 and not (out / "last.pt").is_file():
        print(f"python -m learned.train: note: --resume, but {out / 'last.pt'} does not exist: starting at step 0",
              file=sys.stderr)
    trainer = Trainer(config, resume=args.resume, progress=not args.no_progress)
    if args.overwrite and rank0:   # config and data checked: the earlier run goes before the first step
        clear_earlier_run(out)
    losses = trainer.run()
    if trainer.rank == 0 and losses:
        print(f"{config.mode}: {len(losses)} steps, loss {losses[0]:.4f} -> {losses[-1]:.4f}; "
              f"{trainer.out / 'last.pt'}")
    elif trainer.rank == 0 and trainer.saved_step is None:   # train.steps=0, nothing resumed
        print(f"{config.mode}: nothing to train: train.steps={config.train.steps}; give train.steps=N (N >= 1)")
    elif trainer.rank == 0:
        further = ("raise train.steps to train further" if config.train.schedule == "constant" else
                   f"its cosine schedule has ended: train further as a new run (--mode finetune "
                   f"train.teacher={trainer.out / 'last.pt'} and another train.out)")
        print(f"{config.mode}: nothing to train: {trainer.out / 'last.pt'} is at step {trainer.step} of "
              f"train.steps={config.train.steps}; {further}")
    if torch.distributed.is_initialized():
        torch.distributed.destroy_process_group()
    return 0


if __name__ == "__main__":
    sys.exit(main())
