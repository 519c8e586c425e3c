"""Training configuration: frozen dataclasses read from JSON or TOML, with ``key=value`` overrides.

A config file holds the sections ``model`` (:class:`learned.model.ModelConfig`),
``data`` and ``train``; the command line overrides single fields with dotted
keys (``train.steps=200 model.width=8``; values are parsed as JSON, else kept
as strings).
"""
from __future__ import annotations

import json
import math
import os
import tomllib
import warnings
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from learned.device import DEVICE_NAMES, is_device_name
from learned.model import ModelConfig

__all__ = ["DataConfig", "TrainConfig", "Config", "load_config", "apply_overrides", "config_from_dict", "MODES",
           "REMOVED_KEYS", "check_paths_beside_config"]

MODES = ("teacher", "finetune", "student")

# Field annotations (strings: ``from __future__ import annotations``) -> accepted Python types.
_KINDS = {"int": ((int,), "a whole number"), "float": ((int, float), "a finite number"),
          "bool": ((bool,), "true or false"), "str": ((str,), "a string"), "tuple": ((tuple, list), "a list")}


def _check_types(cls: type, values: dict[str, Any], section: str) -> None:
    """TypeError/ValueError naming ``section.key`` for a value of the wrong type or a non-finite float."""
    for f in fields(cls):
        if f.name not in values:
            continue
        kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        if kind not in _KINDS:
            continue
        allowed, what = _KINDS[kind]
        value = values[f.name]
        if (isinstance(value, bool) and kind != "bool") or not isinstance(value, allowed):
            hint = ""
            if kind == "str" and isinstance(value, (int, float, bool)):   # key=123 is read as JSON: a number
                hint = (f"; a value that reads as JSON (a number, true) is taken as one: quote it, "
                        f"'{section}.{f.name}=\"{json.dumps(value)}\"'")
            raise TypeError(f"{section}.{f.name} must be {what}, got {value!r} ({type(value).__name__}){hint}")
        if kind == "float" and not math.isfinite(value):
            raise ValueError(f"{section}.{f.name} must be {what}, got {value!r}")


def _require(condition: bool, section: str, name: str, rule: str, value: object) -> None:
    if not condition:
        raise ValueError(f"{section}.{name} must be {rule}, got {value!r}")


def _check_file_entry(entry: object, where: str) -> None:
    """TypeError naming ``where`` (``data.files[2]``, ``data.val_files[0]``) for an entry of a list of data files
    that is neither a path nor ``{"path", "K", "use_gt", "known_speed", "known_twist", "polarity", "calib",
    "calib_camera", "rectify_map", "as_recorded"}`` of the right types; ValueError for an empty path (``""``, an
    unset shell variable: ``Path("")`` is the current folder), for a ``polarity`` other than ``"01"`` or
    ``"signed"``, for a ``calib_camera`` without ``calib``, and for a ``rectify_map`` without ``K`` or with
    ``calib``."""
    path = entry.get("path") if isinstance(entry, dict) else entry
    if isinstance(path, str) and not path.strip():
        raise ValueError(f"{where} is an empty path (an unset shell variable, \"$FILE\"?): give an h5 event file, "
                         f"e.g. data.files=[\"a.h5\"]")
    if isinstance(entry, (str, Path)):
        return
    if not isinstance(entry, dict):
        raise TypeError(f"{where} must be a path or {{\"path\", \"K\", \"use_gt\"}}, got {entry!r}")
    unknown = set(entry) - {"path", "K", "use_gt", "known_speed", "known_twist", "polarity", "calib", "calib_camera",
                            "rectify_map", "as_recorded"}
    if unknown or not isinstance(entry.get("path"), (str, Path)):
        raise TypeError(f"{where} needs \"path\" (a string) and may hold \"K\", \"use_gt\", \"known_speed\", "
                        f"\"known_twist\", \"polarity\", \"calib\", \"calib_camera\", \"rectify_map\" and "
                        f"\"as_recorded\" only, got {entry!r}")
    for key in ("calib", "calib_camera", "rectify_map"):
        if key in entry and (not isinstance(entry[key], (str, Path)) or not str(entry[key]).strip()):
            raise TypeError(f"{where}.{key} must be a non-empty string (calib: a calibration file such as DSEC's "
                            f"cam_to_cam.yaml; calib_camera: its camera, e.g. cam0; rectify_map: DSEC's "
                            f"rectify_map.h5), got {entry[key]!r}")
    if "rectify_map" in entry and ("calib" in entry or entry.get("K") is None):
        raise ValueError(f"{where}.rectify_map maps the events into the rectified frame whose K the entry gives: give "
                         "\"K\" (DSEC: camRect0's camera_matrix) and no \"calib\" (which rectifies them itself)")
    if "calib_camera" in entry and "calib" not in entry:
        raise ValueError(f"{where}.calib_camera {entry['calib_camera']!r} chooses a camera of a calibration file: "
                         "give \"calib\" too (e.g. DSEC's cam_to_cam.yaml)")
    if entry.get("polarity", "01") not in ("01", "signed"):
        raise ValueError(f"{where}.polarity must be \"01\" (0 OFF, 1 ON) or \"signed\" (-1 OFF, +1 ON), "
                         f"got {entry['polarity']!r}")
    K = entry.get("K")
    if K is not None:
        flat = [v for row in K for v in row] if K and isinstance(K[0], (list, tuple)) else list(K) \
            if isinstance(K, (list, tuple)) else None
        if (flat is None or len(flat) not in (4, 9) or
                not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in flat)):
            raise TypeError(f"{where}.K must be [fx, fy, cx, cy] or a 3x3 list of finite numbers, got {K!r}")
    for key in ("use_gt", "known_speed", "known_twist", "as_recorded"):
        if not isinstance(entry.get(key, True), bool):
            raise TypeError(f"{where}.{key} must be true or false, got {entry[key]!r}")


@dataclass(frozen=True)
class DataConfig:
    """Which windows to train on.

    Attributes
    ----------
    files : list
        Paths, or ``{"path", "K": [fx, fy, cx, cy], "use_gt": bool}``, with ``"calib"`` (and ``"calib_camera"``), or
        DSEC's ``"rectify_map"``, for raw events to undistort and rectify, or ``"as_recorded": true`` to take raw
        events as they are (see :class:`learned.data.FileSpec`).
    window_us : int
        Window length [µs] (the paper's 0.1665 s).
    max_events : int
        Raw events per window kept for the contrast loss.
    augment : bool
    val_files : list
        Held-out files (same forms as ``files``) whose loss is logged every ``train.val_every`` steps
        (``val/loss`` in ``log.jsonl``): the learning curve that says when training is flat.
    val_windows : int
        Windows of ``val_files`` used (evenly spread over them).
    """

    files: tuple = ()
    val_files: tuple = ()
    val_windows: int = 32
    window_us: int = 166_500
    max_events: int = 20_000
    augment: bool = True

    def __post_init__(self) -> None:
        _check_types(DataConfig, asdict(self), "data")
        object.__setattr__(self, "files", tuple(self.files))
        object.__setattr__(self, "val_files", tuple(self.val_files))
        for key in ("files", "val_files"):
            for i, entry in enumerate(getattr(self, key)):
                _check_file_entry(entry, f"data.{key}[{i}]")
        _require(self.val_windows >= 1, "data", "val_windows", ">= 1", self.val_windows)
        _require(self.window_us >= 1, "data", "window_us", "a whole number of µs >= 1", self.window_us)
        _require(self.max_events >= 1, "data", "max_events", ">= 1", self.max_events)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation and logging.

    Attributes
    ----------
    batch_size : int
        Global batch (split over the ranks of a ``torchrun`` job).
    lr, weight_decay : float
        AdamW (the paper: 1e-4, 1e-3).
    steps : int
        Optimiser steps in total.
    lam : float
        The paper's lambda (teacher: ``L_si + lam L_grad``; student: ``(1 - lam) L1``).
    teacher : str
        Checkpoint of the teacher (modes ``finetune``: initial weights; ``student``: the frozen teacher).
    out : str
        Run folder: the checkpoint ``last.pt`` (replaced every ``checkpoint_every`` steps and at the last
        step; no per-step copies are kept), ``config.json``, the learning curves ``log.jsonl`` and TensorBoard's
        ``tb/``. A step whose loss or weights go non-finite stops the run and saves nothing, so ``last.pt``
        stays the last good checkpoint.
    checkpoint_every, log_every, image_every : int
        In steps.
    seed : int
    collapse_weight : float
        Weight of the deformation guard added to the shared contrast objective (0: the objective alone,
        :data:`cmax.contrast.SHARED_OBJECTIVE`, which needs no guard).
    si_variance_weight : float
        w of ``L_si = mean(R^2) - w mean(R)^2`` (1: the paper's fully invariant form, which leaves the
        scale free; 0.85 keeps a weak pull towards metric scale, as in most supervised depth networks).
    twist_weight : float
        Teacher only: weight of a smooth-L1 loss between the predicted and the true twist, each component
        divided by its root mean square over the training windows (the data's own speed statistics), so
        that the pose head learns the motion of each window; 0 = the paper's teacher.
    schedule : str
        ``"constant"`` learning rate, or ``"cosine"``: linear warm-up over ``warmup_steps``, then a cosine
        decay to ``lr / 100`` at ``steps`` (a function of the step alone, so a resumed run is unchanged).
    warmup_steps : int
    val_every : int
        Steps between validation losses (0: never); needs ``data.val_files``.
    speed_weight : float
        Fine-tune and student: weight of :func:`learned.losses.speed_loss` on windows of known speed.
    clip_grad_norm : float
        Largest global gradient norm of a step (0: no clipping).
    contrast_twist : str
        Fine-tune and student: the twist the contrast objective warps with, ``"network"`` (the paper) or
        ``"truth"`` (an ablation: the window's true twist where its file is read with ``known_twist``, so
        that only the depth is learned from the contrast).
    device : str
        Where the network and the losses run: ``"cpu"``, ``"cuda"`` (under ``torchrun`` each rank takes the
        GPU of its ``LOCAL_RANK``, and the ranks meet over nccl instead of gloo), ``"cuda:N"``, or ``"auto"``
        (``"cuda"`` when torch sees a GPU, else ``"cpu"``). The files are read and the event volumes built on
        the CPU either way; ``--resume`` is bit-for-bit on the CPU only.
    """

    batch_size: int = 16
    lr: float = 1e-4
    weight_decay: float = 1e-3
    steps: int = 1000
    lam: float = 0.6
    teacher: str = ""
    out: str = "runs/learned"
    checkpoint_every: int = 100
    log_every: int = 10
    image_every: int = 100
    seed: int = 0
    collapse_weight: float = 0.0
    si_variance_weight: float = 0.85
    twist_weight: float = 1.0
    schedule: str = "constant"
    warmup_steps: int = 0
    val_every: int = 0
    speed_weight: float = 0.1
    clip_grad_norm: float = 1.0
    contrast_twist: str = "network"
    device: str = "cpu"

    def __post_init__(self) -> None:
        _check_types(TrainConfig, asdict(self), "train")
        _require(is_device_name(self.device), "train", "device", DEVICE_NAMES, self.device)
        _require(self.schedule in ("constant", "cosine"), "train", "schedule", "'constant' or 'cosine'",
                 self.schedule)
        _require(self.contrast_twist in ("network", "truth"), "train", "contrast_twist", "'network' or 'truth'",
                 self.contrast_twist)
        for name in ("batch_size", "checkpoint_every", "log_every", "image_every"):
            _require(getattr(self, name) >= 1, "train", name, "a whole number >= 1", getattr(self, name))
        for name in ("steps", "seed", "warmup_steps", "val_every"):
            _require(getattr(self, name) >= 0, "train", name, "a whole number >= 0", getattr(self, name))
        _require(self.lr > 0, "train", "lr", "> 0", self.lr)
        for name in ("weight_decay", "lam", "collapse_weight", "twist_weight", "speed_weight", "clip_grad_norm"):
            _require(getattr(self, name) >= 0, "train", name, ">= 0", getattr(self, name))
        _require(0 <= self.si_variance_weight <= 1, "train", "si_variance_weight", "in [0, 1]",
                 self.si_variance_weight)


@dataclass(frozen=True)
class Config:
    mode: str = "teacher"
    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.mode in ("finetune", "student") and not self.train.teacher:
            from learned.pretrained import CHECKPOINT

            raise ValueError(f"mode {self.mode!r} needs train.teacher (a teacher checkpoint, e.g. "
                             f"train.teacher=runs/teacher/last.pt, or the model that ships with the package: "
                             f"train.teacher={CHECKPOINT})")
        if self.train.val_every and not self.data.val_files:
            raise ValueError("train.val_every > 0 needs data.val_files (held-out files): give them, e.g. "
                             "'data.val_files=[\"val.h5\"]', or turn validation off with train.val_every=0")

    def to_dict(self) -> dict[str, Any]:
        """The config as nested plain dicts (``mode`` and ``{section: {key: value}}``), as ``config.json`` stores it."""
        return asdict(self)


#: Keys that earlier versions had, with the value they stored by default, and why they went. Configs and the
#: checkpoints of those versions hold them: at that value a key is dropped silently, at another one with a
#: warning (it never had an effect).
REMOVED_KEYS = {("data", "workers"): (0, "it never had an effect: the windows are read in the training process, "
                                         "and learned has no DataLoader")}


def _drop_removed(values: dict, name: str) -> dict:
    """``values`` (section ``name``) without the keys of :data:`REMOVED_KEYS`; a warning (one line) for each one
    set to other than its old default."""
    kept = dict(values)
    for (section, key), (default, why) in REMOVED_KEYS.items():
        if section == name and key in kept:
            value = kept.pop(key)
            if value != default:
                warnings.warn(f"{section}.{key}={value!r} is ignored: {section}.{key} is no longer a setting ({why})",
                              stacklevel=3)
    return kept


def _section(cls, values: dict, name: str):
    if not isinstance(values, dict):
        raise TypeError(f"[{name}] must be a table of keys, got {values!r}")
    values = _drop_removed(values, name)
    known = {f.name for f in fields(cls)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"unknown keys in [{name}]: {sorted(unknown)} (known: {sorted(known)})")
    _check_types(cls, values, name)
    values = {k: tuple(v) if isinstance(v, list) and k in ("files", "val_files") else v for k, v in values.items()}
    return cls(**values)


def config_from_dict(values: dict[str, Any]) -> Config:
    """A :class:`Config` from nested dicts (as written by :meth:`Config.to_dict`).

    Raises ValueError / TypeError naming the key for unknown keys, values of the
    wrong type, non-finite numbers and values out of range.
    """
    if not isinstance(values, dict):
        raise TypeError(f"a config must be a table of sections, got {type(values).__name__}")
    unknown = set(values) - {"mode", "model", "data", "train"}
    if unknown:
        raise ValueError(f"unknown config sections: {sorted(unknown)}")
    if not isinstance(values.get("mode", "teacher"), str):
        raise TypeError(f"mode must be one of {MODES}, got {values['mode']!r}")
    return Config(mode=values.get("mode", "teacher"),
                  model=_section(ModelConfig, values.get("model", {}), "model"),
                  data=_section(DataConfig, values.get("data", {}), "data"),
                  train=_section(TrainConfig, values.get("train", {}), "train"))


def _parse(value: str) -> Any:
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        return value


def apply_overrides(values: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Set the dotted keys of ``overrides`` (``train.steps=10``) in ``values``, nested dicts; returns a new dict."""
    values = json.loads(json.dumps(values))
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"overrides must look like section.key=value, got {item!r}")
        *path, last = key.split(".")
        target = values
        for depth, part in enumerate(path):
            target = target.setdefault(part, {})
            if not isinstance(target, dict):
                raise ValueError(f"override {item!r}: {'.'.join(path[:depth + 1])} is a value, not a section")
        target[last] = _parse(raw)
    return values


def load_config(path: str | Path | None, overrides: list[str] = (), *, mode: str | None = None,
                require_mode: bool = False) -> Config:
    """Read a ``.json`` or ``.toml`` config at ``path`` (None: start from the defaults), apply ``overrides`` and ``mode`` (None: the
    config's own, else :class:`Config`'s default; ValueError when ``mode`` differs from the one the config or the
    overrides state, and, with ``require_mode``, when neither ``mode`` nor the config states one)."""
    values: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if path.suffix not in (".json", ".toml"):
            raise ValueError(f"config must be a .json or .toml file, got {path}")
        if not path.is_file():
            raise FileNotFoundError(f"no config file at {path}")
        try:
            text = path.read_text("utf-8")
            values = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
        except (ValueError, UnicodeDecodeError) as error:  # JSONDecodeError, TOMLDecodeError
            raise ValueError(f"{path} is not valid {path.suffix[1:].upper()}: {error}") from None
        if not isinstance(values, dict):
            raise TypeError(f"{path} must hold a table of sections, got {type(values).__name__}")
    values = apply_overrides(values, list(overrides))
    if mode is not None:
        stated = values.get("mode")
        if stated is not None and stated != mode:
            where = f"{path}" if path is not None else "the overrides"
            raise ValueError(f"--mode {mode}, but {where} says mode = {stated!r}: give the mode once, or make them "
                             "agree")
        values["mode"] = mode
    elif require_mode and "mode" not in values:
        raise ValueError("no mode: give --mode teacher|finetune|student, or a config that states mode = ...")
    config = config_from_dict(values)
    if path is not None:
        check_paths_beside_config(config, path)
    return config


def check_paths_beside_config(config: Config, path: str | Path) -> None:
    """Raise FileNotFoundError for a relative file of ``config`` (a ``data.files`` entry, a ``data.val_files`` entry
    when ``train.val_every`` reads them, the teacher of a finetune or student) that is missing from the current
    folder, where every relative path is read from, but lies beside the config file at ``path``: the message names
    both places (the reader's own, ``no such event file: a.h5``, named neither). Paths found, absolute, or missing
    from both places are left to the readers.
    """
    folder = Path(path).parent
    if folder.resolve() == Path.cwd().resolve():
        return
    names = [entry if isinstance(entry, (str, Path)) else entry["path"] for entry in config.data.files]
    if config.train.val_every:
        names += [entry if isinstance(entry, (str, Path)) else entry["path"] for entry in config.data.val_files]
    if config.mode in ("finetune", "student") and config.train.teacher:
        names.append(config.train.teacher)
    for name in map(Path, names):
        if not name.is_absolute() and not os.path.lexists(name) and os.path.lexists(folder / name):
            raise FileNotFoundError(f"no such file: {name} (relative paths of a config are read from the current "
                                    f"folder, {Path.cwd()}); {folder / name} lies beside the config {path}: run from "
                                    f"{folder}, or give the paths from here (e.g. {folder / name}) or absolute ones")


def with_mode(config: Config, mode: str) -> Config:
    return replace(config, mode=mode)
